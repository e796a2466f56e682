"""Inputs at loss resolution, and the depth read out at working resolution.

The losses are evaluated at a reduced "loss resolution" (h, w) = ``loss_size(H, W, scale)``;
``prepare_frames`` area-downsamples a set of frames (images, priors, static masks) to it and runs
the depth network's frozen backbone once, ``flow_at_loss_res`` / ``chained_flow`` bring flows to
it, and ``full_depth`` evaluates the trained model back at the working resolution (H, W).
Pixel convention: the centre of the top-left pixel is (0, 0).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from gcvd_flow.stages.frontend.user_masks import user_keep
from gcvd_flow.stages.models.depth_net import DEPTH_MAX, DEPTH_MIN, DepthNet, Encoded, upsample_mesh

__all__ = [
    "FlowPair",
    "Frames",
    "scaled_K",
    "loss_size",
    "area_resize",
    "keep_resize",
    "images_tensor",
    "normalised_prior",
    "prepare_frames",
    "flow_at_loss_res",
    "flows_at_loss_res",
    "chained_flow",
    "full_depth",
    "init_depth_full",
    "fit_mesh",
]

# (flow (h, w, 2) px at loss resolution, consistency mask (h, w) float 1 = usable)
FlowLR = tuple[torch.Tensor, torch.Tensor]
# (forward a -> b, backward b -> a) of one pair (a, b)
FlowPair = tuple[FlowLR, FlowLR]


def scaled_K(K: np.ndarray, f: float) -> np.ndarray:
    """Intrinsics (3, 3) float64 after area-downsampling by factor f (pixel-centre convention
    (0, 0) = centre)."""
    Ks = np.array(K, dtype=np.float64).copy()
    Ks[0, 0] /= f
    Ks[1, 1] /= f
    Ks[0, 2] = (Ks[0, 2] + 0.5) / f - 0.5
    Ks[1, 2] = (Ks[1, 2] + 0.5) / f - 0.5
    return Ks


def loss_size(h: int, w: int, scale: float) -> tuple[int, int, float]:
    """Loss resolution (h', w') of an (h, w) image and the downsampling factor (w / w')."""
    ws = max(8, int(round(w * scale)))
    hs = max(6, int(round(h * ws / w)))
    return hs, ws, w / ws


def area_resize(x: np.ndarray | torch.Tensor, h: int, w: int) -> torch.Tensor:
    """(N, H, W) or (N, H, W, C) -> area-averaged float32 (N, h, w[, C])."""
    t = torch.as_tensor(np.asarray(x), dtype=torch.float32)
    if t.dim() == 3:
        return F.interpolate(t[:, None], size=(h, w), mode="area")[:, 0]
    return F.interpolate(t.permute(0, 3, 1, 2), size=(h, w), mode="area").permute(0, 2, 3, 1)


def images_tensor(images: np.ndarray) -> torch.Tensor:
    """uint8 (N, H, W, 3) RGB -> float32 (N, 3, H, W) in [0, 1]."""
    return torch.as_tensor(np.ascontiguousarray(images), dtype=torch.float32).permute(0, 3, 1, 2) / 255.0


def normalised_prior(priors: np.ndarray) -> np.ndarray:
    """Relative inverse depth (N, H, W) -> float32 (N, H, W) with per-frame median 1, invalid
    pixels set to 1, clipped to [1e-3, 1e3]."""
    p = np.asarray(priors, dtype=np.float32)
    p = np.where(np.isfinite(p) & (p > 0), p, np.nan)
    med = np.nanmedian(p.reshape(p.shape[0], -1), axis=1)
    med = np.where(np.isfinite(med) & (med > 0), med, 1.0)
    p = p / med[:, None, None]
    return np.nan_to_num(p, nan=1.0).clip(1e-3, 1e3).astype(np.float32)


@dataclass
class Frames:
    """Per-frame inputs at loss resolution (h, w) for a set of n frames."""

    imgs: torch.Tensor  # (n, 3, h, w) float32 in [0, 1]
    enc: Encoded  # backbone features + log prior, (n, ., h, w)
    static: torch.Tensor  # (n, h, w) float32, 1 = static
    dyn_mesh: torch.Tensor  # (n, gh, gw) float32 dynamic fraction per mesh cell
    K: torch.Tensor  # (3, 3) float64 at loss resolution
    f: float  # downsampling factor W / w
    keep: torch.Tensor | None = None  # (n, h, w) float32 1 = no user-masked pixel in the cell; None: no --masks


def prepare_frames(
    net: DepthNet, images: np.ndarray, priors: np.ndarray, masks: np.ndarray, K: np.ndarray, scale: float,
    gshape: tuple[int, int],
) -> Frames:
    """images (n, H, W, 3) uint8, priors (n, H, W), masks (n, H, W) 1 = static (int8 with -1 where
    the user masked: stages.frontend.user_masks), K (3, 3) at working resolution -> their
    ``Frames`` at ``loss_size(H, W, scale)``; gshape = (gh, gw) mesh."""
    n, H, W = images.shape[:3]
    h, w, f = loss_size(H, W, scale)
    # the backbone runs at the loss resolution: only the head's loss-resolution correction is
    # ever used (see full_depth), and a full-resolution U-Net pass would cost ~16x more
    imgs = F.interpolate(images_tensor(images), size=(h, w), mode="area")
    pri = area_resize(normalised_prior(priors), h, w)
    encs = [net.encode(imgs[i : i + 8], pri[i : i + 8]) for i in range(0, n, 8)]
    enc = Encoded(torch.cat([e.feat for e in encs]), torch.cat([e.log_prior for e in encs]))
    st = (np.asarray(masks) > 0).astype(np.float32)
    static = (area_resize(st, h, w) > 0.99).float()
    dyn = 1 - area_resize(st, gshape[0], gshape[1])
    keep = user_keep(masks)
    keep_lr = None if keep is None else keep_resize(keep, h, w)
    if keep_lr is not None:
        static = static * keep_lr
    return Frames(imgs, enc, static, dyn, torch.as_tensor(scaled_K(K, f)), f, keep_lr)


def keep_resize(keep: np.ndarray | torch.Tensor, h: int, w: int) -> torch.Tensor:
    """The user's kept mask (N, H, W) (1 = kept) -> float32 (N, h, w), 1 where no pixel of the
    cell's footprint (the pixels ``area_resize`` averages) is masked: a min-pool, never an average."""
    out = 1 - torch.as_tensor(np.asarray(keep), dtype=torch.float32)
    return 1 - F.adaptive_max_pool2d(out[:, None], (h, w))[:, 0]


def flow_at_loss_res(fl: Mapping[str, np.ndarray], key: str, h: int, w: int, f: float) -> FlowLR:
    """Flow ``fl[key]`` (H, W, 2) px, key "fwd" or "bwd", at loss resolution (h, w) in px of that
    resolution, and its consistency mask (h, w) float (1 where the whole cell is consistent)."""
    fw = area_resize(np.asarray(fl[key], np.float32)[None], h, w)[0] / f
    vk = "fwd_valid" if key == "fwd" else "bwd_valid"
    v = (area_resize(np.asarray(fl[vk], np.float32)[None], h, w)[0] > 0.99).float()
    return fw, v


def flows_at_loss_res(flows: Sequence[Mapping[str, np.ndarray]], h: int, w: int, f: float) -> dict[int, FlowPair]:
    """Flow dicts of the pairs (k, k + 1) -> {k: (forward, backward) at loss resolution}."""
    return {k: (flow_at_loss_res(fl, "fwd", h, w, f), flow_at_loss_res(fl, "bwd", h, w, f)) for k, fl in enumerate(flows)}


def chained_flow(flows_lr: Mapping[int, FlowPair], a: int, tau: int) -> FlowPair | None:
    """Loss-resolution flows (fwd, bwd) of pair (a, a + tau) composed from the tau = 1 flows
    ``flows_lr[k]`` of pairs (k, k + 1); None if a link is missing."""
    if any(k not in flows_lr for k in range(a, a + tau)):
        return None
    if tau == 1:
        return flows_lr[a]
    from gcvd_flow.stages.frontend.flow import chain_flows

    fw = chain_flows([(flows_lr[k][0][0].numpy(), flows_lr[k][0][1].numpy() > 0.5) for k in range(a, a + tau)])
    bw = chain_flows([(flows_lr[k][1][0].numpy(), flows_lr[k][1][1].numpy() > 0.5) for k in reversed(range(a, a + tau))])
    return (
        (torch.as_tensor(fw[0]), torch.as_tensor(fw[1], dtype=torch.float32)),
        (torch.as_tensor(bw[0]), torch.as_tensor(bw[1], dtype=torch.float32)),
    )


@torch.no_grad()
def full_depth(
    net: DepthNet, images: np.ndarray, priors: np.ndarray, mesh: torch.Tensor, use_mesh: bool, enc_lr: Encoded | None = None
) -> np.ndarray:
    """Depth (n, H, W) float32 at working resolution; images (n, H, W, 3), priors (n, H, W),
    mesh (n, gh, gw) log-scale meshes.

    With ``enc_lr`` (the loss-resolution inputs the head was trained on), the trained model is
    evaluated where it was trained and only its log-correction of the prior is upsampled onto the
    full-resolution prior: depth = prior_depth_full * up(depth_lr / prior_depth_lr). Evaluating the
    1x1 head on full-resolution features instead would feed it feature statistics it never saw.
    Without ``enc_lr`` the network runs on full-resolution features (used for the untrained net).
    """
    pri = torch.as_tensor(normalised_prior(priors))
    H, W = pri.shape[-2:]
    out = []
    for i in range(len(images)):
        m = mesh[i : i + 1] if use_mesh else None
        if enc_lr is None:
            enc = net.encode(images_tensor(images[i : i + 1]), pri[i : i + 1])
            out.append(net.decode(enc, m)[0])
            continue
        e = Encoded(enc_lr.feat[i : i + 1], enc_lr.log_prior[i : i + 1])
        corr = torch.log(net.decode(e, m)) + e.log_prior[:, 0]
        up = F.interpolate(corr[:, None], size=(H, W), mode="bilinear", align_corners=False)[:, 0]
        out.append(torch.exp(up - net.log_prior(pri[i : i + 1])[:, 0])[0])
    return torch.stack(out).numpy().astype(np.float32)


def init_depth_full(net: DepthNet, images: np.ndarray, priors: np.ndarray) -> np.ndarray:
    """Depth (n, H, W) float32 of the untrained network (zero head, zero mesh):
    clip(exp(-log_prior)). Computed without running the backbone (the zero-initialised head
    ignores the features); ``images`` is unused."""
    lp = net.log_prior(torch.as_tensor(normalised_prior(priors)))[:, 0]
    return torch.exp(-lp).clamp(DEPTH_MIN, DEPTH_MAX).numpy().astype(np.float32)


def fit_mesh(log_ratio: torch.Tensor, gshape: tuple[int, int]) -> torch.Tensor:
    """Least-squares-ish vertex values (B, gh, gw) whose bilinear upsampling approximates the
    log-ratio field (B, h, w): area average to the grid, then a few residual refinements."""
    h, w = log_ratio.shape[-2:]
    m = F.interpolate(log_ratio[:, None], size=gshape, mode="area")[:, 0]
    for _ in range(3):
        r = log_ratio - upsample_mesh(m, h, w)
        m = m + F.interpolate(r[:, None], size=gshape, mode="area")[:, 0]
    return m
