"""RAFT optical flow (Teed & Deng, ECCV 2020), "raft-things" configuration, plain torch.

Written from the paper's description; module / parameter names follow the official
princeton-vl/RAFT ``raft-things.pth`` state dict (after stripping the DataParallel ``module.``
prefix), so that file, or a safetensors export of it, loads with ``strict=True``:

* ``fnet``  feature encoder, instance norm (no affine parameters), 7x7/2 stem (64) and three
  stages of two residual blocks (64, 96 /2, 128 /2) -> 1x1 conv to 256-d at 1/8 resolution.
* ``cnet``  context encoder, same layout with batch norm; its 256 channels are split into the
  GRU hidden state (128, tanh) and the context input (128, ReLU).
* all-pairs correlation (dot product / sqrt(256)), 4-level pyramid (2x2 average pooling of the
  second frame's axis), lookup radius 4 -> 4 * 81 = 324 channels.
* ``update_block``: motion encoder (``encoder.convc1/convc2/convf1/convf2/conv``), separable
  ConvGRU (``gru.convz1/convr1/convq1`` 1x5 and ``gru.convz2/convr2/convq2`` 5x1, hidden 128,
  input 256), ``flow_head`` (conv1 3x3 -> 256, conv2 3x3 -> 2) and ``mask`` (3x3 -> 256, ReLU,
  1x1 -> 8*8*9, scaled by 0.25) for convex upsampling.

Parameter count: 5,257,536 (the paper quotes 5.26 M / 5.3 M for raft-things).

Deviation from the reference code, only for very small inputs: when a correlation pyramid level
would have a side < 2 the reference code divides by zero (side 1) or fails (side 0); here a side
of 1 is not pooled further and the lookup normalises coordinates with ``align_corners=False``
(mathematically identical to the reference's ``align_corners=True`` normalisation whenever the
side is >= 2). For inputs >= 128 px on each side (after padding) the computation is the same.

No file is downloaded here: the user supplies a local weights file.
"""

from __future__ import annotations

import logging
from typing import Mapping

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from gcvd_flow.stages.models.weights import load_strict

log = logging.getLogger(__name__)

HIDDEN_DIM = 128
CONTEXT_DIM = 128
FEATURE_DIM = 256
CORR_LEVELS = 4
CORR_RADIUS = 4


# --------------------------------------------------------------------------------------------
# encoders
# --------------------------------------------------------------------------------------------


def _norm(kind: str, channels: int) -> nn.Module:
    if kind == "instance":
        return nn.InstanceNorm2d(channels)  # affine=False: no parameters, as in raft-things
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    raise ValueError(f"unknown norm {kind!r}")


class ResidualBlock(nn.Module):
    """Two 3x3 convs (first one strided), norm + ReLU after each; 1x1 strided projection."""

    def __init__(self, in_planes: int, planes: int, norm: str, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_planes, planes, 3, stride=stride, padding=1)
        self.conv2 = nn.Conv2d(planes, planes, 3, padding=1)
        self.relu = nn.ReLU(inplace=True)
        self.norm1 = _norm(norm, planes)
        self.norm2 = _norm(norm, planes)
        self.downsample: nn.Module | None = None
        if stride != 1:
            # the checkpoint stores this norm twice (as norm3 and as downsample.1): same module
            self.norm3 = _norm(norm, planes)
            self.downsample = nn.Sequential(nn.Conv2d(in_planes, planes, 1, stride=stride), self.norm3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.relu(self.norm1(self.conv1(x)))
        y = self.relu(self.norm2(self.conv2(y)))
        if self.downsample is not None:
            x = self.downsample(x)
        return self.relu(x + y)


class BasicEncoder(nn.Module):
    """Residual encoder to 1/8 resolution: stem 64 /2, stages 64, 96 /2, 128 /2, 1x1 to out."""

    def __init__(self, output_dim: int, norm: str) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, stride=2, padding=3)
        self.norm1 = _norm(norm, 64)
        self.relu1 = nn.ReLU(inplace=True)
        self.layer1 = self._stage(64, 64, norm, 1)
        self.layer2 = self._stage(64, 96, norm, 2)
        self.layer3 = self._stage(96, 128, norm, 2)
        self.conv2 = nn.Conv2d(128, output_dim, 1)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, (nn.BatchNorm2d, nn.InstanceNorm2d)) and m.weight is not None:
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    @staticmethod
    def _stage(cin: int, cout: int, norm: str, stride: int) -> nn.Sequential:
        return nn.Sequential(ResidualBlock(cin, cout, norm, stride), ResidualBlock(cout, cout, norm, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.relu1(self.norm1(self.conv1(x)))
        x = self.layer3(self.layer2(self.layer1(x)))
        return self.conv2(x)


# --------------------------------------------------------------------------------------------
# correlation
# --------------------------------------------------------------------------------------------


def coords_grid(batch: int, ht: int, wd: int, device=None) -> torch.Tensor:
    """(B, 2, ht, wd) pixel coordinates, channel 0 = x (column), channel 1 = y (row)."""
    ys, xs = torch.meshgrid(
        torch.arange(ht, dtype=torch.float32, device=device),
        torch.arange(wd, dtype=torch.float32, device=device),
        indexing="ij",
    )
    return torch.stack([xs, ys], dim=0)[None].expand(batch, -1, -1, -1).contiguous()


class CorrPyramid:
    """All-pairs correlation volume of two (B, D, H, W) feature maps with a pooled pyramid."""

    def __init__(self, fmap1: torch.Tensor, fmap2: torch.Tensor, levels: int = CORR_LEVELS,
                 radius: int = CORR_RADIUS) -> None:
        b, d, h, w = fmap1.shape
        self.radius = radius
        corr = torch.einsum("bdi,bdj->bij", fmap1.reshape(b, d, h * w), fmap2.reshape(b, d, h * w))
        corr = (corr / d**0.5).reshape(b * h * w, 1, h, w)
        self.levels: list[torch.Tensor] = [corr]
        self.scales: list[tuple[float, float]] = [(1.0, 1.0)]  # (x, y) down-scaling per level
        sx, sy = 1.0, 1.0
        for _ in range(levels - 1):
            hh, ww = corr.shape[-2:]
            ky, kx = (2 if hh >= 2 else 1), (2 if ww >= 2 else 1)
            corr = F.avg_pool2d(corr, (ky, kx), stride=(ky, kx))
            sx, sy = sx * kx, sy * ky
            self.levels.append(corr)
            self.scales.append((sx, sy))
        r = radius
        lin = torch.linspace(-r, r, 2 * r + 1, dtype=torch.float32)
        # window (a, b) samples at offset (x = lin[a], y = lin[b]): this is the channel order
        # the released weights were trained with (x offset along the first window axis).
        ox, oy = torch.meshgrid(lin, lin, indexing="ij")
        self.delta = torch.stack([ox, oy], dim=-1).view(1, 2 * r + 1, 2 * r + 1, 2)

    def __call__(self, coords: torch.Tensor) -> torch.Tensor:
        """coords (B, 2, H, W) in level-0 pixels -> (B, levels * (2r+1)^2, H, W)."""
        b, _, h, w = coords.shape
        centre = coords.permute(0, 2, 3, 1).reshape(b * h * w, 1, 1, 2)
        delta = self.delta.to(coords)
        out = []
        for corr, (sx, sy) in zip(self.levels, self.scales):
            scale = torch.tensor([sx, sy], dtype=coords.dtype, device=coords.device)
            pts = centre / scale + delta  # (BHW, 2r+1, 2r+1, 2) pixel coords at this level
            hh, ww = corr.shape[-2:]
            gx = (2.0 * pts[..., 0] + 1.0) / ww - 1.0
            gy = (2.0 * pts[..., 1] + 1.0) / hh - 1.0
            grid = torch.stack([gx, gy], dim=-1)
            s = F.grid_sample(corr, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
            out.append(s.view(b, h, w, -1))
        return torch.cat(out, dim=-1).permute(0, 3, 1, 2).contiguous()


# --------------------------------------------------------------------------------------------
# update block
# --------------------------------------------------------------------------------------------


class MotionEncoder(nn.Module):
    """Correlation + current flow -> 126 motion features, concatenated with the flow (128)."""

    def __init__(self, corr_planes: int = CORR_LEVELS * (2 * CORR_RADIUS + 1) ** 2) -> None:
        super().__init__()
        self.convc1 = nn.Conv2d(corr_planes, 256, 1)
        self.convc2 = nn.Conv2d(256, 192, 3, padding=1)
        self.convf1 = nn.Conv2d(2, 128, 7, padding=3)
        self.convf2 = nn.Conv2d(128, 64, 3, padding=1)
        self.conv = nn.Conv2d(192 + 64, 128 - 2, 3, padding=1)

    def forward(self, flow: torch.Tensor, corr: torch.Tensor) -> torch.Tensor:
        c = F.relu(self.convc2(F.relu(self.convc1(corr))))
        f = F.relu(self.convf2(F.relu(self.convf1(flow))))
        m = F.relu(self.conv(torch.cat([c, f], dim=1)))
        return torch.cat([m, flow], dim=1)


class SepConvGRU(nn.Module):
    """ConvGRU applied twice: horizontal (1x5) then vertical (5x1) gates."""

    def __init__(self, hidden_dim: int = HIDDEN_DIM, input_dim: int = 256) -> None:
        super().__init__()
        c = hidden_dim + input_dim
        self.convz1 = nn.Conv2d(c, hidden_dim, (1, 5), padding=(0, 2))
        self.convr1 = nn.Conv2d(c, hidden_dim, (1, 5), padding=(0, 2))
        self.convq1 = nn.Conv2d(c, hidden_dim, (1, 5), padding=(0, 2))
        self.convz2 = nn.Conv2d(c, hidden_dim, (5, 1), padding=(2, 0))
        self.convr2 = nn.Conv2d(c, hidden_dim, (5, 1), padding=(2, 0))
        self.convq2 = nn.Conv2d(c, hidden_dim, (5, 1), padding=(2, 0))

    @staticmethod
    def _step(h: torch.Tensor, x: torch.Tensor, cz: nn.Conv2d, cr: nn.Conv2d, cq: nn.Conv2d) -> torch.Tensor:
        hx = torch.cat([h, x], dim=1)
        z = torch.sigmoid(cz(hx))
        r = torch.sigmoid(cr(hx))
        q = torch.tanh(cq(torch.cat([r * h, x], dim=1)))
        return (1 - z) * h + z * q

    def forward(self, h: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        h = self._step(h, x, self.convz1, self.convr1, self.convq1)
        return self._step(h, x, self.convz2, self.convr2, self.convq2)


class FlowHead(nn.Module):
    def __init__(self, input_dim: int = HIDDEN_DIM, hidden_dim: int = 256) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(input_dim, hidden_dim, 3, padding=1)
        self.conv2 = nn.Conv2d(hidden_dim, 2, 3, padding=1)
        self.relu = nn.ReLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv2(self.relu(self.conv1(x)))


class UpdateBlock(nn.Module):
    def __init__(self, hidden_dim: int = HIDDEN_DIM) -> None:
        super().__init__()
        self.encoder = MotionEncoder()
        self.gru = SepConvGRU(hidden_dim=hidden_dim, input_dim=CONTEXT_DIM + 128)
        self.flow_head = FlowHead(hidden_dim, hidden_dim=256)
        self.mask = nn.Sequential(
            nn.Conv2d(hidden_dim, 256, 3, padding=1),
            nn.ReLU(inplace=True),
            nn.Conv2d(256, 8 * 8 * 9, 1),
        )

    def forward(self, net, inp, corr, flow):
        motion = self.encoder(flow, corr)
        net = self.gru(net, torch.cat([inp, motion], dim=1))
        delta = self.flow_head(net)
        mask = 0.25 * self.mask(net)  # scaling used by the released model (balances gradients)
        return net, mask, delta


# --------------------------------------------------------------------------------------------
# RAFT
# --------------------------------------------------------------------------------------------


def upsample_flow_convex(flow: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B, 2, H, W) flow at 1/8 + (B, 576, H, W) mask logits -> (B, 2, 8H, 8W) flow.

    Every full-resolution pixel is a convex (softmax) combination of the 3x3 coarse neighbours;
    mask channel k * 64 + i * 8 + j weights neighbour k for sub-pixel (row i, column j).
    """
    b, _, h, w = flow.shape
    m = torch.softmax(mask.view(b, 1, 9, 8, 8, h, w), dim=2)
    nb = F.unfold(8.0 * flow, (3, 3), padding=1).view(b, 2, 9, 1, 1, h, w)
    up = (m * nb).sum(dim=2)  # (b, 2, 8, 8, h, w)
    return up.permute(0, 1, 4, 2, 5, 3).reshape(b, 2, 8 * h, 8 * w)


class RAFT(nn.Module):
    """RAFT ("raft-things" configuration). Inputs are RGB in [0, 255], sides multiples of 8."""

    def __init__(self) -> None:
        super().__init__()
        self.hidden_dim = HIDDEN_DIM
        self.context_dim = CONTEXT_DIM
        self.fnet = BasicEncoder(FEATURE_DIM, norm="instance")
        self.cnet = BasicEncoder(HIDDEN_DIM + CONTEXT_DIM, norm="batch")
        self.update_block = UpdateBlock(HIDDEN_DIM)

    def forward(self, image1: torch.Tensor, image2: torch.Tensor, iters: int = 12,
                flow_init: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, 3, H, W) x2 in [0, 255] -> (flow at 1/8 (B, 2, H/8, W/8), flow (B, 2, H, W))."""
        b, _, h, w = image1.shape
        if h % 8 or w % 8:
            raise ValueError(f"image sides must be multiples of 8, got {h}x{w}")
        image1 = 2.0 * (image1 / 255.0) - 1.0
        image2 = 2.0 * (image2 / 255.0) - 1.0
        fmaps = self.fnet(torch.cat([image1, image2], dim=0)).float()
        fmap1, fmap2 = fmaps[:b], fmaps[b:]
        corr_fn = CorrPyramid(fmap1, fmap2)
        ctx = self.cnet(image1)
        net, inp = torch.split(ctx, [self.hidden_dim, self.context_dim], dim=1)
        net, inp = torch.tanh(net), torch.relu(inp)

        coords0 = coords_grid(b, h // 8, w // 8, device=image1.device)
        coords1 = coords0.clone()
        if flow_init is not None:
            coords1 = coords1 + flow_init
        flow_up = 8.0 * F.interpolate(coords1 - coords0, scale_factor=8, mode="bilinear", align_corners=True)
        for _ in range(iters):
            coords1 = coords1.detach()
            corr = corr_fn(coords1)
            net, up_mask, delta = self.update_block(net, inp, corr, coords1 - coords0)
            coords1 = coords1 + delta
            flow_up = upsample_flow_convex(coords1 - coords0, up_mask)
        return coords1 - coords0, flow_up


# --------------------------------------------------------------------------------------------
# loading / inference
# --------------------------------------------------------------------------------------------


def load_raft(state: Mapping[str, torch.Tensor], source: str = "state dict") -> RAFT:
    """Build RAFT from a state dict (eval mode); any key or shape mismatch raises
    ``ValueError`` naming the first offending key and ``source`` (the file it came from)."""
    model = RAFT()
    load_strict(model, state, source)
    model.eval()
    return model


def _to_tensor(img: np.ndarray, name: str) -> torch.Tensor:
    a = np.asarray(img)
    if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8:
        raise ValueError(f"{name} must be uint8 (H, W, 3), got {a.dtype} {a.shape}")
    return torch.from_numpy(np.ascontiguousarray(a)).permute(2, 0, 1).float()[None]


@torch.no_grad()
def raft_flow(model: RAFT, img_a: np.ndarray, img_b: np.ndarray, iters: int = 12) -> np.ndarray:
    """Forward flow from ``img_a`` to ``img_b``.

    Args:
        model: a :class:`RAFT` (switched to eval mode for the call).
        img_a, img_b: uint8 (H, W, 3) RGB of the same size.
        iters: GRU refinement iterations (12 in the paper's evaluation at test time).

    Returns:
        float32 (H, W, 2) flow (dx, dy) in pixels: pixel p of ``img_a`` maps to p + flow[p].
    """
    a, b = _to_tensor(img_a, "img_a"), _to_tensor(img_b, "img_b")
    if a.shape != b.shape:
        raise ValueError(f"images differ in size: {tuple(a.shape[2:])} vs {tuple(b.shape[2:])}")
    h, w = a.shape[2:]
    ph, pw = (-h) % 8, (-w) % 8
    pad = (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2)  # left, right, top, bottom
    x = F.pad(torch.cat([a, b], dim=0), pad, mode="replicate")
    was_training = model.training
    model.eval()
    try:
        _, flow = model(x[:1], x[1:], iters=int(iters))
    finally:
        model.train(was_training)
    flow = flow[0, :, pad[2]:pad[2] + h, pad[0]:pad[0] + w]
    return flow.permute(1, 2, 0).contiguous().numpy().astype(np.float32)
