"""GCVD depth network: backbone -> non-affine LayerNorm -> depth = clip(1/disp) -> mesh deformation.

Weight-free default (docs/design.md, "Weight-free defaults"): a small U-Net with a fixed, seeded
random initialisation reads
the image *and* the log of the single-image prior and produces per-pixel features. A trainable
head (the "last two layers": two 1x1 convolutions, ``head.0`` and ``head.2``) predicts a
log-inverse-depth *residual* on top of the prior. The last head layer is zero-initialised, so the
network reproduces the prior exactly before any training: "fitted to the prior first" holds by
construction instead of costing a pre-fit phase on a CPU.

Why 1x1 head layers: their output at a pixel depends only on that pixel's (frozen, cached)
features, so a training step costs O(pixels x head) without re-running the backbone. The
optimiser runs the backbone once per frame at the loss resolution and upsamples the learned
log-correction of the prior to the working resolution (stages.optimize.frames.full_depth).

Weights backend hook: pass ``backbone=<nn.Module>`` (e.g. MiDaS) mapping an image (B, 3, H, W)
in [0, 1] to inverse depth (B, 1, H, W) or (B, H, W). Its output is used in place of the prior
(frozen, evaluated once per frame); the same trainable head / LayerNorm / mesh follow.

Pipeline of ``decode``: log_disp = log_prior + head(features); if ``layer_norm``: per-frame
non-affine normalisation of log_disp (zero mean, unit variance) re-multiplied by the frozen
per-frame std of the log prior, so the per-frame depth *scale* is not a network output (the mesh
carries it); depth = clip(exp(-log_disp), 1e-3, 1e3); if ``mesh``: depth * exp(bilinear(mesh)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import cast

import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = ["DepthNet", "UNetBackbone", "mesh_shape", "upsample_mesh"]

DEPTH_MIN, DEPTH_MAX = 1e-3, 1e3


def mesh_shape(h: int, w: int, n_long: int = 17) -> tuple[int, int]:
    """Mesh vertex grid (gh, gw): ``n_long`` vertices on the long side, same spacing on the short."""
    if w >= h:
        gw = n_long
        gh = max(2, int(round((n_long - 1) * (h - 1) / max(w - 1, 1))) + 1)
    else:
        gh = n_long
        gw = max(2, int(round((n_long - 1) * (w - 1) / max(h - 1, 1))) + 1)
    return gh, gw


def upsample_mesh(mesh: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Bilinear upsampling of vertex values (B, gh, gw) to pixels (B, h, w); vertices sit on the
    image corners (align_corners=True), so a zero mesh is exactly the identity deformation."""
    return F.interpolate(mesh[:, None], size=(h, w), mode="bilinear", align_corners=True)[:, 0]


class UNetBackbone(nn.Module):
    """Tiny 3-level U-Net, fixed seeded random weights (never trained). (B, 4, H, W) -> (B, C, H, W)."""

    def __init__(self, in_ch: int = 4, width: int = 16, out_ch: int = 16, seed: int = 0) -> None:
        super().__init__()
        self.e1 = nn.Conv2d(in_ch, width, 3, padding=1)
        self.e2 = nn.Conv2d(width, 2 * width, 3, stride=2, padding=1)
        self.e3 = nn.Conv2d(2 * width, 2 * width, 3, stride=2, padding=1)
        self.d2 = nn.Conv2d(4 * width, 2 * width, 3, padding=1)
        self.d1 = nn.Conv2d(3 * width, out_ch, 3, padding=1)
        g = torch.Generator().manual_seed(seed)
        with torch.no_grad():
            for m in self.modules():
                if isinstance(m, nn.Conv2d):
                    fan_in = m.in_channels * m.kernel_size[0] * m.kernel_size[1]
                    m.weight.copy_(torch.randn(m.weight.shape, generator=g) * math.sqrt(2.0 / fan_in))
                    assert m.bias is not None  # every Conv2d here has a bias
                    m.bias.zero_()
        for p in self.parameters():
            p.requires_grad_(False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        a = F.relu(self.e1(x))
        b = F.relu(self.e2(a))
        c = F.relu(self.e3(b))
        c = F.interpolate(c, size=b.shape[-2:], mode="bilinear", align_corners=False)
        b = F.relu(self.d2(torch.cat([b, c], 1)))
        b = F.interpolate(b, size=(h, w), mode="bilinear", align_corners=False)
        return self.d1(torch.cat([a, b], 1))


@dataclass
class Encoded:
    """Frozen per-frame inputs of the trainable part. feat (B, C, h, w); log_prior (B, 1, h, w)."""

    feat: torch.Tensor
    log_prior: torch.Tensor

    def downsample(self, h: int, w: int) -> "Encoded":
        """Area-average to (h, w) (used for the loss resolution)."""
        if self.feat.shape[-2:] == (h, w):
            return self
        return Encoded(
            F.interpolate(self.feat, size=(h, w), mode="area"),
            F.interpolate(self.log_prior, size=(h, w), mode="area"),
        )


class DepthNet(nn.Module):
    """Depth network of GCVD (see module docstring). Trainable parameters: ``head`` only."""

    def __init__(
        self,
        layer_norm: bool = True,
        mesh: bool = True,
        feat_ch: int = 16,
        hidden: int = 16,
        seed: int = 0,
        backbone: nn.Module | None = None,
    ) -> None:
        super().__init__()
        self.layer_norm = layer_norm
        self.use_mesh = mesh
        self.unet = UNetBackbone(4, 16, feat_ch, seed=seed)
        self.external = backbone
        if backbone is not None:
            for p in backbone.parameters():
                p.requires_grad_(False)
        g = torch.Generator().manual_seed(seed + 1)
        self.head = nn.Sequential(nn.Conv2d(feat_ch + 1, hidden, 1), nn.ReLU(), nn.Conv2d(hidden, 1, 1))
        h0, h2 = cast(nn.Conv2d, self.head[0]), cast(nn.Conv2d, self.head[2])
        with torch.no_grad():
            w0 = h0.weight
            w0.copy_(torch.randn(w0.shape, generator=g) * math.sqrt(2.0 / (feat_ch + 1)))
            assert h0.bias is not None and h2.bias is not None  # both built with bias=True
            h0.bias.zero_()
            # zero last layer: the untrained network outputs the prior exactly
            h2.weight.zero_()
            h2.bias.zero_()

    @torch.no_grad()
    def encode(self, images: torch.Tensor, prior: torch.Tensor | None) -> Encoded:
        """images (B, 3, H, W) float in [0, 1]; prior (B, H, W) relative inverse depth > 0 (or None
        when an external backbone is set) -> frozen features at full resolution."""
        if self.external is not None:
            disp = self.external(images)
            if disp.dim() == 4:
                disp = disp[:, 0]
            disp = F.interpolate(disp[:, None], size=images.shape[-2:], mode="bilinear", align_corners=False)[:, 0]
            prior = disp.clamp(min=1e-6)
            prior = prior / prior.flatten(1).median(1).values[:, None, None]
        assert prior is not None
        lp = self.log_prior(prior)
        x = torch.cat([images - 0.5, lp], 1)
        return Encoded(self.unet(x), lp)

    @staticmethod
    def log_prior(prior: torch.Tensor) -> torch.Tensor:
        """Relative inverse depth (B, H, W) -> zero-mean log inverse depth (B, 1, H, W). The
        untrained network's depth is exactly clip(exp(-log_prior)) (head zero, LayerNorm keeps it)."""
        lp = torch.log(prior.clamp(min=1e-4))[:, None]
        return lp - lp.flatten(1).mean(1)[:, None, None, None]

    @staticmethod
    def head_input(enc: Encoded) -> torch.Tensor:
        """The head's input as a pixel-major matrix (B * h * w, C + 1): features and log prior of
        every pixel. Constant while the head trains, so a solver builds it once per window."""
        x = torch.cat([enc.feat, enc.log_prior], 1)
        return x.permute(0, 2, 3, 1).reshape(-1, x.shape[1]).contiguous()

    def head_residual(self, x: torch.Tensor) -> torch.Tensor:
        """The head (two 1x1 convolutions) on a ``head_input`` matrix (P, C + 1) -> (P,) log
        inverse-depth residuals. As two matrix products rather than ``self.head``'s convolutions:
        the same arithmetic, at a fifth of the convolutions' forward + backward time on CPU
        (their backward dominated a solver step)."""
        l0, l2 = cast(nn.Conv2d, self.head[0]), cast(nn.Conv2d, self.head[2])
        assert l0.bias is not None and l2.bias is not None  # both built with bias=True
        hidden = torch.addmm(l0.bias, x, l0.weight.flatten(1).t()).relu_()  # in place: one (P, hidden) buffer less
        return torch.addmm(l2.bias, hidden, l2.weight.flatten(1).t())[:, 0]

    @staticmethod
    def prior_std(enc: Encoded) -> torch.Tensor:
        """(B, 1, 1, 1) the per-frame std of the log prior that ``decode``'s LayerNorm re-multiplies
        by. Constant while the head trains, so a solver computes it once per window."""
        return enc.log_prior.flatten(1).std(1, correction=0).detach()[:, None, None, None]

    def decode(self, enc: Encoded, mesh: torch.Tensor | None = None, head_in: torch.Tensor | None = None,
               ref_std: torch.Tensor | None = None) -> torch.Tensor:
        """Trainable part: Encoded (B, ., h, w) + log-scale mesh (B, gh, gw) -> depth (B, h, w).
        ``head_in``: ``head_input(enc)``, ``ref_std``: ``prior_std(enc)`` when the caller keeps
        them (they are rebuilt otherwise)."""
        lp = enc.log_prior
        b, _, h, w = lp.shape
        x = self.head_input(enc) if head_in is None else head_in
        log_disp = lp + self.head_residual(x).view(b, 1, h, w)
        if self.layer_norm:
            # non-affine LayerNorm over each frame, times the frozen std of the prior: the network
            # can reshape a frame's depth but not rescale it (scale lives in the mesh)
            ref_std = self.prior_std(enc) if ref_std is None else ref_std
            log_disp = F.layer_norm(log_disp, log_disp.shape[1:]) * ref_std
        depth = torch.exp(-log_disp[:, 0]).clamp(DEPTH_MIN, DEPTH_MAX)
        if self.use_mesh and mesh is not None:
            depth = depth * torch.exp(upsample_mesh(mesh, depth.shape[-2], depth.shape[-1]))
        return depth

    def forward(self, images: torch.Tensor, prior: torch.Tensor | None, mesh: torch.Tensor | None = None) -> torch.Tensor:
        return self.decode(self.encode(images, prior), mesh)

    def trainable_state(self) -> dict[str, torch.Tensor]:
        """The weights that test-time training changes (the head)."""
        return {f"head.{k}": v.detach().clone() for k, v in self.head.state_dict().items()}

    def load_trainable_state(self, state: dict[str, torch.Tensor]) -> None:
        sd = {k[len("head."):]: torch.as_tensor(v) for k, v in state.items() if k.startswith("head.")}
        if sd:
            self.head.load_state_dict(sd)
