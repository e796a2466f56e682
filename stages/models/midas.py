"""MiDaS v2.1 "small" monocular depth network (Ranftl et al., TPAMI 2020), plain torch.

Variant: the released ``midas_v21_small_256.pt`` (hub name ``MiDaS_small``:
``MidasNet_small(features=64, backbone="efficientnet_lite3", exportable=True,
non_negative=True, blocks={"expand": True})``). Written without timm / geffnet; module and
parameter names follow that checkpoint so it (or a safetensors export) loads ``strict=True``:

* ``pretrained.layer1..layer4`` -- EfficientNet-Lite3 trunk (TF-ported: BatchNorm eps 1e-3,
  TF "same" padding for the stride-2 convs, ReLU6, no squeeze-excite), channel multiplier 1.2,
  depth multiplier 1.4 (first/last stage not scaled). ``layer1 = [conv_stem, bn1, act1,
  blocks[0], blocks[1]]`` (1/4, 32 ch), ``layer2 = [blocks[2]]`` (1/8, 48 ch),
  ``layer3 = [blocks[3], blocks[4]]`` (1/16, 136 ch), ``layer4 = [blocks[5], blocks[6]]``
  (1/32, 384 ch). Block names: depthwise-separable ``conv_dw, bn1, conv_pw, bn2``; inverted
  residual ``conv_pw, bn1, conv_dw, bn2, conv_pwl, bn3``.
* ``scratch.layer{1..4}_rn`` -- 3x3 convs (no bias) to 64 / 128 / 256 / 512 channels ("expand").
* ``scratch.refinenet{4..1}`` -- feature fusion blocks: ``resConfUnit1`` (on the skip input),
  add, ``resConfUnit2``, bilinear x2 upsampling (align_corners=True), 1x1 ``out_conv``
  (512->256, 256->128, 128->64, 64->64). Residual conv units: ReLU, 3x3 conv, ReLU, 3x3 conv, + x.
* ``scratch.output_conv`` -- conv 3x3 64->32, bilinear x2, conv 3x3 32->32, ReLU, conv 1x1
  32->1, ReLU: relative inverse depth (larger = nearer) at the input resolution.

Parameter count: 21,320,545 (MiDaS v2.1 small is quoted as ~21 M).

No file is downloaded here: the user supplies a local weights file.
"""

from __future__ import annotations

import logging
import math
from typing import Mapping

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from gcvd_flow.stages.models.weights import load_strict

log = logging.getLogger(__name__)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
NET_SIZE = 256  # long side of the network input for the "small" model
BN_EPS_TF = 1e-3

# EfficientNet-Lite3 stages after channel (x1.2, rounded to 8) and depth (x1.4, ceil) scaling:
# (block type, kernel, stride, expansion, out channels, repeats)
LITE3_STAGES = (
    ("ds", 3, 1, 1, 24, 1),
    ("ir", 3, 2, 6, 32, 3),
    ("ir", 5, 2, 6, 48, 3),
    ("ir", 3, 2, 6, 96, 5),
    ("ir", 5, 1, 6, 136, 5),
    ("ir", 5, 2, 6, 232, 6),
    ("ir", 3, 1, 6, 384, 1),
)
STEM_CHANNELS = 32
ENCODER_CHANNELS = (32, 48, 136, 384)


# --------------------------------------------------------------------------------------------
# EfficientNet-Lite3 trunk
# --------------------------------------------------------------------------------------------


class Conv2dSame(nn.Conv2d):
    """Conv with TensorFlow "SAME" padding computed from the input size (asymmetric if needed)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        ih, iw = x.shape[-2:]
        kh, kw = self.weight.shape[-2:]
        sh, sw = self.stride
        dh, dw = self.dilation
        ph = max((math.ceil(ih / sh) - 1) * sh + (kh - 1) * dh + 1 - ih, 0)
        pw = max((math.ceil(iw / sw) - 1) * sw + (kw - 1) * dw + 1 - iw, 0)
        if ph or pw:
            x = F.pad(x, [pw // 2, pw - pw // 2, ph // 2, ph - ph // 2])
        return super().forward(x)


def _conv(cin: int, cout: int, k: int, stride: int = 1, groups: int = 1) -> nn.Conv2d:
    """Bias-free conv with TF "same" padding (static symmetric when stride is 1)."""
    if stride == 1:
        return nn.Conv2d(cin, cout, k, stride=1, padding=k // 2, groups=groups, bias=False)
    return Conv2dSame(cin, cout, k, stride=stride, padding=0, groups=groups, bias=False)


def _bn(c: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(c, eps=BN_EPS_TF)


class DepthwiseSeparable(nn.Module):
    def __init__(self, cin: int, cout: int, k: int, stride: int) -> None:
        super().__init__()
        self.conv_dw = _conv(cin, cin, k, stride, groups=cin)
        self.bn1 = _bn(cin)
        self.act1 = nn.ReLU6()
        self.conv_pw = _conv(cin, cout, 1)
        self.bn2 = _bn(cout)
        self.has_residual = stride == 1 and cin == cout

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.bn2(self.conv_pw(self.act1(self.bn1(self.conv_dw(x)))))
        return y + x if self.has_residual else y


class InvertedResidual(nn.Module):
    def __init__(self, cin: int, cout: int, k: int, stride: int, expansion: int) -> None:
        super().__init__()
        mid = cin * expansion
        self.conv_pw = _conv(cin, mid, 1)
        self.bn1 = _bn(mid)
        self.act1 = nn.ReLU6()
        self.conv_dw = _conv(mid, mid, k, stride, groups=mid)
        self.bn2 = _bn(mid)
        self.act2 = nn.ReLU6()
        self.conv_pwl = _conv(mid, cout, 1)
        self.bn3 = _bn(cout)
        self.has_residual = stride == 1 and cin == cout

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.act1(self.bn1(self.conv_pw(x)))
        y = self.act2(self.bn2(self.conv_dw(y)))
        y = self.bn3(self.conv_pwl(y))
        return y + x if self.has_residual else y


def _lite3_blocks() -> list[nn.Sequential]:
    stages = []
    cin = STEM_CHANNELS
    for kind, k, stride, exp, cout, reps in LITE3_STAGES:
        blocks: list[nn.Module] = []
        for i in range(reps):
            s = stride if i == 0 else 1
            if kind == "ds":
                blocks.append(DepthwiseSeparable(cin, cout, k, s))
            else:
                blocks.append(InvertedResidual(cin, cout, k, s, exp))
            cin = cout
        stages.append(nn.Sequential(*blocks))
    return stages


class Encoder(nn.Module):
    """``pretrained``: EfficientNet-Lite3 cut into four stages (1/4, 1/8, 1/16, 1/32)."""

    def __init__(self) -> None:
        super().__init__()
        b = _lite3_blocks()
        stem = [_conv(3, STEM_CHANNELS, 3, stride=2), _bn(STEM_CHANNELS), nn.ReLU6()]
        self.layer1 = nn.Sequential(*stem, b[0], b[1])
        self.layer2 = nn.Sequential(b[2])
        self.layer3 = nn.Sequential(b[3], b[4])
        self.layer4 = nn.Sequential(b[5], b[6])


# --------------------------------------------------------------------------------------------
# decoder ("scratch")
# --------------------------------------------------------------------------------------------


class ResidualConvUnit(nn.Module):
    def __init__(self, features: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, 3, padding=1, bias=True)
        self.conv2 = nn.Conv2d(features, features, 3, padding=1, bias=True)
        self.activation = nn.ReLU(inplace=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.conv2(self.activation(self.conv1(self.activation(x))))
        return out + x


class FeatureFusionBlock(nn.Module):
    def __init__(self, features: int, expand: bool) -> None:
        super().__init__()
        out_features = features // 2 if expand else features
        self.resConfUnit1 = ResidualConvUnit(features)
        self.resConfUnit2 = ResidualConvUnit(features)
        self.out_conv = nn.Conv2d(features, out_features, 1, bias=True)

    def forward(self, x: torch.Tensor, skip: torch.Tensor | None = None) -> torch.Tensor:
        if skip is not None:
            x = x + self.resConfUnit1(skip)
        x = self.resConfUnit2(x)
        x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)
        return self.out_conv(x)


class _Upsample2x(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)


class Scratch(nn.Module):
    def __init__(self, features: int = 64) -> None:
        super().__init__()
        outs = (features, features * 2, features * 4, features * 8)  # expand=True
        c1, c2, c3, c4 = ENCODER_CHANNELS
        self.layer1_rn = nn.Conv2d(c1, outs[0], 3, padding=1, bias=False)
        self.layer2_rn = nn.Conv2d(c2, outs[1], 3, padding=1, bias=False)
        self.layer3_rn = nn.Conv2d(c3, outs[2], 3, padding=1, bias=False)
        self.layer4_rn = nn.Conv2d(c4, outs[3], 3, padding=1, bias=False)
        self.activation = nn.ReLU()
        self.refinenet4 = FeatureFusionBlock(outs[3], expand=True)
        self.refinenet3 = FeatureFusionBlock(outs[2], expand=True)
        self.refinenet2 = FeatureFusionBlock(outs[1], expand=True)
        self.refinenet1 = FeatureFusionBlock(outs[0], expand=False)
        self.output_conv = nn.Sequential(
            nn.Conv2d(features, features // 2, 3, padding=1),
            _Upsample2x(),
            nn.Conv2d(features // 2, 32, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(32, 1, 1),
            nn.ReLU(),  # non_negative=True
            nn.Identity(),
        )


class MidasNet(nn.Module):
    """MiDaS v2.1 small. (B, 3, H, W) ImageNet-normalised, H, W multiples of 32 -> (B, H, W)."""

    def __init__(self, features: int = 64) -> None:
        super().__init__()
        self.pretrained = Encoder()
        self.scratch = Scratch(features)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        if h % 32 or w % 32:
            raise ValueError(f"input sides must be multiples of 32, got {h}x{w}")
        p, s = self.pretrained, self.scratch
        l1 = p.layer1(x)
        l2 = p.layer2(l1)
        l3 = p.layer3(l2)
        l4 = p.layer4(l3)
        path = s.refinenet4(s.layer4_rn(l4))
        path = s.refinenet3(path, s.layer3_rn(l3))
        path = s.refinenet2(path, s.layer2_rn(l2))
        path = s.refinenet1(path, s.layer1_rn(l1))
        return s.output_conv(path).squeeze(1)


# --------------------------------------------------------------------------------------------
# loading / inference
# --------------------------------------------------------------------------------------------


def load_midas(state: Mapping[str, torch.Tensor], source: str = "state dict") -> MidasNet:
    """Build MidasNet from a state dict (eval mode); any key or shape mismatch raises
    ``ValueError`` naming the first offending key and ``source`` (the file it came from)."""
    model = MidasNet()
    load_strict(model, state, source)
    model.eval()
    return model


def network_size(h: int, w: int, long_side: int = NET_SIZE) -> tuple[int, int]:
    """MiDaS "upper_bound" resize keeping aspect: long side <= ``long_side``, multiples of 32."""
    scale = long_side / max(h, w)

    def fit(x: float) -> int:
        y = int(round(x / 32) * 32)
        if y > long_side:
            y = int(math.floor(x / 32) * 32)
        return max(y, 32)

    return fit(h * scale), fit(w * scale)


@torch.no_grad()
def midas_prior(model: MidasNet, image: np.ndarray) -> np.ndarray:
    """MiDaS-shaped prior of one image (docs/contributing.md, "Array conventions").

    ImageNet normalisation, bicubic resize to the network size (long side 256, multiples of 32,
    aspect kept), network, bilinear resize back to (H, W), clip to >= 0 plus an epsilon of
    1e-4 x the map's maximum (1e-6 if the map is all zero), division by the median.

    Returns:
        float32 (H, W) relative inverse depth, > 0, median 1, larger = nearer.
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"image must be uint8 (H, W, 3), got {img.dtype} {img.shape}")
    h, w = img.shape[:2]
    nh, nw = network_size(h, w)
    x: np.ndarray = cv2.resize(img.astype(np.float32) / 255.0, (nw, nh), interpolation=cv2.INTER_CUBIC)
    x = (x - np.asarray(IMAGENET_MEAN, np.float32)) / np.asarray(IMAGENET_STD, np.float32)
    t = torch.from_numpy(np.ascontiguousarray(x)).permute(2, 0, 1)[None].float()
    was_training = model.training
    model.eval()
    try:
        out = model(t)
    finally:
        model.train(was_training)
    out = F.interpolate(out[:, None], size=(h, w), mode="bilinear", align_corners=False)[0, 0]
    p = np.nan_to_num(out.numpy().astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    p = np.maximum(p, 0.0)
    top = float(p.max())
    p = p + (1e-4 * top if top > 0 else 1e-6)
    return (p / np.median(p)).astype(np.float32)
