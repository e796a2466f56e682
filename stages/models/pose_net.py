"""GCVD pose network: frozen encoder + sinusoidal frame-index encoding + trainable decoder.

Both parameterisations output, per frame, a 6-vector ``(r, t)`` (axis-angle rad, translation in
scene units) that is *right-multiplied* onto an initial camera-to-world pose:
``T_w_i = T_w_i_init @ pose_from_rt(delta_i)`` (a correction in the camera's own frame).

- ``PoseNet``: GCVD's design. A fixed, seeded random conv encoder (never trained) summarises the
  image, a sinusoidal encoding of the frame index is appended, and an MLP decoder (trainable; last
  layer zero-initialised, so the initial poses are returned unchanged) predicts the correction.
- ``DirectPoses``: one free 6-vector per frame.

Default in ``stages.optimize``: ``DirectPoses``. With a good initialisation (two-view essential-
matrix chain, docs/design.md, "Lessons from the prototype") every frame needs an independent small
correction; the decoder couples
frames through shared weights. Measured (keyframe stage, DIS flow, flow-triangulation prior, same
settings): ICL 211 frames ATE 2.9 cm direct vs 3.5 cm PoseNet; synthetic loop 120 frames 0.48 %
vs 0.46 % of the path (a tie). ``pose_param="net"`` selects the network.
"""

from __future__ import annotations

import math
from typing import cast

import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = ["PoseNet", "DirectPoses", "positional_encoding"]


def positional_encoding(index: torch.Tensor, n_freq: int = 8, period: float = 512.0) -> torch.Tensor:
    """Sinusoidal encoding of frame indices (B,) -> (B, 2 * n_freq), wavelengths from 2 to ``period``."""
    i = index.to(torch.float32)[:, None]
    freqs = torch.exp(torch.linspace(math.log(2 * math.pi / period), math.log(math.pi), n_freq))
    return torch.cat([torch.sin(i * freqs), torch.cos(i * freqs)], 1)


class _Encoder(nn.Module):
    def __init__(self, width: int = 16, seed: int = 0) -> None:
        super().__init__()
        self.convs = nn.ModuleList(
            [nn.Conv2d(3, width, 3, 2, 1), nn.Conv2d(width, 2 * width, 3, 2, 1), nn.Conv2d(2 * width, 4 * width, 3, 2, 1)]
        )
        g = torch.Generator().manual_seed(seed)
        with torch.no_grad():
            for m in self.convs:
                c = cast(nn.Conv2d, m)
                fan = c.in_channels * 9
                c.weight.copy_(torch.randn(c.weight.shape, generator=g) * math.sqrt(2.0 / fan))
                assert c.bias is not None  # built with bias=True
                c.bias.zero_()
        for p in self.parameters():
            p.requires_grad_(False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for c in self.convs:
            x = F.relu(c(x))
        return x.mean((2, 3))


class PoseNet(nn.Module):
    """images (B, 3, H, W) in [0, 1] + frame indices (B,) -> pose corrections (B, 6).

    Only ``decoder`` trains. The encoder features are computed once per frame (``encode``) and
    cached by the optimiser, so a step costs one small MLP.
    """

    def __init__(self, width: int = 16, n_freq: int = 8, hidden: int = 64, seed: int = 0) -> None:
        super().__init__()
        self.encoder = _Encoder(width, seed)
        self.n_freq = n_freq
        d_in = 4 * width + 2 * n_freq
        self.decoder = nn.Sequential(nn.Linear(d_in, hidden), nn.ReLU(), nn.Linear(hidden, 6))
        g = torch.Generator().manual_seed(seed + 7)
        l0, l2 = cast(nn.Linear, self.decoder[0]), cast(nn.Linear, self.decoder[2])
        with torch.no_grad():
            l0.weight.copy_(torch.randn(l0.weight.shape, generator=g) / math.sqrt(d_in))
            cast(torch.Tensor, l0.bias).zero_()  # nn.Linear leaves bias unannotated; bias=True here
            l2.weight.zero_()
            cast(torch.Tensor, l2.bias).zero_()

    @torch.no_grad()
    def encode(self, images: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        """Frozen code (B, D) of images (B, 3, H, W) and frame indices (B,)."""
        small = F.interpolate(images, size=(48, 64), mode="area") - 0.5
        return torch.cat([self.encoder(small), positional_encoding(index, self.n_freq)], 1)

    def decode(self, code: torch.Tensor) -> torch.Tensor:
        return self.decoder(code)

    def forward(self, images: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        return self.decode(self.encode(images, index))


class DirectPoses(nn.Module):
    """One free 6-vector correction per frame: (n,) -> (n, 6)."""

    def __init__(self, n: int) -> None:
        super().__init__()
        self.delta = nn.Parameter(torch.zeros(n, 6, dtype=torch.float64))

    def forward(self) -> torch.Tensor:
        return self.delta
