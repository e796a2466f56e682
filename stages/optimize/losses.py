"""GCVD losses on sampled points (torch).

The optimiser samples M points per ordered frame pair instead of warping whole images (docs/design.md, "Lessons from the prototype"),
so the pairwise terms take point tensors:

- points are grouped by pair: leading dims (P, M) = (pairs, points per pair);
- ``weight`` (P, M) >= 0 marks usable points (valid, static, inside the other image);
- every pairwise term returns a per-pair mean (P,), so the caller can weight pairs by 1/tau.

Terms and GCVD default weights (``DEFAULT_WEIGHTS``): photometric 1 (L1 + DSSIM on 3x3 patches),
flow 10 (rigid flow vs. precomputed flow, px at loss resolution, tau = 1 only), depth consistency
0.5 (|Da - Db| / (Da + Db)), depth-gradient orientation 0.1 ((1 - cos)^2 of inverse-depth gradients
vs. the prior's, 3 scales), mesh smoothness 0.5 (weighted up in dynamic areas).
"""

from __future__ import annotations

from typing import Any, cast

import torch
import torch.nn.functional as F

__all__ = [
    "DEFAULT_WEIGHTS",
    "weighted_mean",
    "photometric_loss",
    "photometric_terms",
    "patch_stats",
    "flow_loss",
    "depth_consistency_loss",
    "prior_gradients",
    "gradient_orientation_loss",
    "mesh_smoothness_loss",
    "dense_photometric_loss",
]

DEFAULT_WEIGHTS: dict[str, float] = {"photo": 1.0, "flow": 10.0, "depth": 0.5, "grad": 0.1, "mesh": 0.5}

_C1, _C2 = 0.01**2, 0.03**2


def weighted_mean(values: torch.Tensor, weight: torch.Tensor, dim: int = -1) -> torch.Tensor:
    """Sum(w * v) / max(sum(w), 1e-6) along ``dim`` (pairs without usable points give 0)."""
    return (values * weight).sum(dim) / weight.sum(dim).clamp(min=1e-6)


def photometric_loss(
    patch_a: torch.Tensor, patch_b: torch.Tensor, weight: torch.Tensor, alpha: float = 0.85
) -> torch.Tensor:
    """(1 - alpha) * L1 + alpha * DSSIM between colour patches.

    patch_a, patch_b: (P, M, 9, C) intensities in [0, 1] of the 3x3 neighbourhood of each point in
    frame a and its per-pixel rigid warp in frame b; weight (P, M) -> (P,).
    DSSIM = (1 - SSIM) / 2 with SSIM from the patch means / variances / covariance (the usual 3x3
    box-filtered SSIM, evaluated only at the sampled points).
    """
    l1 = (patch_a[:, :, 4] - patch_b[:, :, 4]).abs().mean(-1)
    mu_a, mu_b = patch_a.mean(2), patch_b.mean(2)
    va = (patch_a * patch_a).mean(2) - mu_a * mu_a
    vb = (patch_b * patch_b).mean(2) - mu_b * mu_b
    cov = (patch_a * patch_b).mean(2) - mu_a * mu_b
    ssim = ((2 * mu_a * mu_b + _C1) * (2 * cov + _C2)) / ((mu_a**2 + mu_b**2 + _C1) * (va + vb + _C2))
    dssim = ((1 - ssim) / 2).clamp(0, 1).mean(-1)
    return weighted_mean((1 - alpha) * l1 + alpha * dssim, weight)


class _PhotoTerms(torch.autograd.Function):
    """Per-point (1 - alpha) * L1 + alpha * DSSIM of channel-major patches with a hand-written
    backward (to patch_b only: patch_a is an image of fixed pixels, it never needs one). The same
    values as ``photometric_loss``'s terms; autograd through that formula takes ~10 passes over the
    (P, C, M, 9) patch tensors forward and backward, this one 3 forward and 3 backward (the
    photometric term was the largest part of a solver step)."""

    @staticmethod
    def forward(ctx: Any, pa: torch.Tensor, pb: torch.Tensor, alpha: float,
                a_stats: tuple[torch.Tensor, torch.Tensor] | None) -> torch.Tensor:
        C = pa.shape[1]
        mu_a, sq_a = patch_stats(pa) if a_stats is None else a_stats
        mu_b = pb.mean(-1)  # (P, C, M)
        va = sq_a - mu_a * mu_a
        vb = (pb * pb).mean(-1) - mu_b * mu_b
        cov = (pa * pb).mean(-1) - mu_a * mu_b
        a1, a2 = 2 * mu_a * mu_b + _C1, 2 * cov + _C2
        b1, b2 = mu_a * mu_a + mu_b * mu_b + _C1, va + vb + _C2
        den = b1 * b2
        ssim = a1 * a2 / den
        raw = (1 - ssim) / 2
        d4 = pa[..., 4] - pb[..., 4]  # the centre pixels' difference (P, C, M)
        out = (1 - alpha) * d4.abs().mean(1) + alpha * raw.clamp(0, 1).mean(1)
        ctx.save_for_backward(pa, pb, mu_a, mu_b, a1, a2, b1, b2, den, ssim, raw, d4)
        ctx.alpha, ctx.C = alpha, C
        return out

    @staticmethod
    def backward(ctx: Any, g: torch.Tensor) -> tuple[None, torch.Tensor, None, None]:
        pa, pb, mu_a, mu_b, a1, a2, b1, b2, den, ssim, raw, d4 = ctx.saved_tensors
        alpha, C = ctx.alpha, ctx.C
        g = g[:, None]  # (P, 1, M)
        # d loss / d ssim (clamp passes the gradient on [0, 1], as torch's clamp does)
        gs = g * (-alpha / (2 * C)) * ((raw >= 0) & (raw <= 1)).to(g.dtype)
        # d ssim / d b_k = 2 / (9 den) * (s0 + a1 * a_k - ssim * b1 * b_k), with
        # s0 = mu_a * a2 - ssim * mu_b * b2 - a1 * mu_a + ssim * b1 * mu_b
        n = pa.shape[-1]
        k = gs * (2.0 / n) / den
        sb = ssim * b1
        s0 = mu_a * a2 - ssim * mu_b * b2 - a1 * mu_a + sb * mu_b
        grad = torch.addcmul((k * s0)[..., None], pa, (k * a1)[..., None])
        grad = grad.addcmul_(pb, (-k * sb)[..., None])
        grad[..., 4] -= g * ((1 - alpha) / C) * torch.sign(d4)
        return None, grad, None, None


def patch_stats(patch: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and mean square over the last dim (the 3x3 pixels) of channel-major patches (..., 9)
    -> two (...) tensors: the patch-a side of the SSIM, a function of the pixel alone (the same
    bits whether computed for a step's points or for every pixel beforehand: one row's mean is
    reduced the same way whatever the other rows)."""
    return patch.mean(-1), (patch * patch).mean(-1)


def photometric_terms(patch_a: torch.Tensor, patch_b: torch.Tensor, alpha: float = 0.85,
                      a_stats: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """Per point (1 - alpha) * L1 + alpha * DSSIM (``photometric_loss``'s terms before the weighted
    mean) of channel-major patches patch_a, patch_b (P, C, M, 9) (contiguous: the 3x3 pixels of
    a point last; pixel 4 the centre) -> (P, M). Differentiable in patch_b only. ``a_stats``:
    ``patch_stats(patch_a)`` (P, C, M) each when the caller has them (e.g. gathered from a
    per-pixel table built once per window)."""
    return cast(torch.Tensor, _PhotoTerms.apply(patch_a.detach(), patch_b, alpha, a_stats))


def flow_loss(uv_b: torch.Tensor, target_uv_b: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Mean end-point error (px) between rigidly projected points uv_b (P, M, 2) and the points
    given by the precomputed flow target_uv_b (P, M, 2) -> (P,). Caller masks fb-inconsistent /
    dynamic pixels through ``weight``; the error is Charbonnier-smoothed to keep a gradient at 0."""
    err = ((uv_b - target_uv_b) ** 2).sum(-1).add(1e-6).sqrt()
    return weighted_mean(err, weight)


def depth_consistency_loss(z_ab: torch.Tensor, d_b: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """|Da->b - Db| / (Da->b + Db): z of frame-a points in camera b (P, M) vs. depth of b sampled at
    their projections (P, M) -> (P,)."""
    z = z_ab.clamp(min=1e-6)
    return weighted_mean((z - d_b).abs() / (z + d_b).clamp(min=1e-6), weight)


def _grad_xy(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Central-ish differences on (B, h, w), cropped to a common (B, h-1, w-1) support."""
    gx = x[:, :-1, 1:] - x[:, :-1, :-1]
    gy = x[:, 1:, :-1] - x[:, :-1, :-1]
    return gx, gy


PriorGradients = list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]


def prior_gradients(prior_disp: torch.Tensor, scales: int = 3, mask: torch.Tensor | None = None,
                    keep: torch.Tensor | None = None) -> PriorGradients:
    """The prior's side of :func:`gradient_orientation_loss`, per scale: (rx, ry, |r|, w), each
    (B, h_s - 1, w_s - 1). It does not change during an optimisation, so the solver computes it
    once per window. prior_disp (B, h, w) relative inverse depth; mask (B, h, w) optional weights
    (area-pooled: soft at the coarser scales); keep (B, h, w) optional hard mask, 1 = kept (the
    user's --masks): min-pooled, and a gradient is out when any of the three pixels it differences is."""
    ref = prior_disp
    m = torch.ones_like(ref) if mask is None else mask.to(ref.dtype)
    k = None if keep is None else keep.to(ref.dtype)
    out: PriorGradients = []
    for s in range(scales):
        if s > 0:
            ref = F.avg_pool2d(ref[:, None], 2)[:, 0]
            m = F.avg_pool2d(m[:, None], 2)[:, 0]
            if k is not None:
                k = 1 - F.max_pool2d(1 - k[:, None], 2)[:, 0]
        if min(ref.shape[-2:]) < 3:
            break
        rx, ry = _grad_xy(ref)
        nr = (rx * rx + ry * ry).sqrt()
        # only where the prior has a gradient worth following
        if k is None:
            w = m[:, :-1, :-1] * (nr > 1e-3 * ref.abs().mean((1, 2), keepdim=True)).to(ref.dtype)
        else:  # the scale of the prior, and the weights, from the kept pixels only
            scale = (ref.abs() * k).sum((1, 2), keepdim=True) / k.sum((1, 2), keepdim=True).clamp(min=1)
            w = m[:, :-1, :-1] * (nr > 1e-3 * scale).to(ref.dtype) * k[:, :-1, :-1] * k[:, :-1, 1:] * k[:, 1:, :-1]
        out.append((rx, ry, nr, w))
    return out


def gradient_orientation_loss(
    depth: torch.Tensor, prior_disp: torch.Tensor | None, scales: int = 3, mask: torch.Tensor | None = None,
    prior_grads: PriorGradients | None = None,
) -> torch.Tensor:
    """(1 - cos)^2 between the 2D gradients of the predicted inverse depth and of the prior.

    depth (B, h, w) > 0; prior_disp (B, h, w) relative inverse depth; mask (B, h, w) optional
    weights. Evaluated at ``scales`` resolutions (x1, x1/2, x1/4, area pooling), averaged -> (B,).
    Orientation only (scale-invariant), so it keeps the prior's edges without fixing its scale.
    ``prior_grads``: :func:`prior_gradients` of (prior_disp, scales, mask), computed beforehand
    (then prior_disp may be None).
    """
    if prior_grads is None:
        assert prior_disp is not None
        prior_grads = prior_gradients(prior_disp, scales, mask)
    disp = 1.0 / depth.clamp(min=1e-6)
    out = torch.zeros(depth.shape[0], dtype=depth.dtype)
    for s, (rx, ry, nr, w) in enumerate(prior_grads):
        if s > 0:
            disp = F.avg_pool2d(disp[:, None], 2)[:, 0]
        gx, gy = _grad_xy(disp)
        num = gx * rx + gy * ry
        nd = (gx * gx + gy * gy + 1e-12).sqrt()
        cos = num / (nd * nr.clamp(min=1e-12))
        out = out + weighted_mean(((1 - cos) ** 2).flatten(1), w.flatten(1))
    return out / scales


def mesh_smoothness_loss(mesh: torch.Tensor, dynamic: torch.Tensor | None = None, dyn_gain: float = 10.0) -> torch.Tensor:
    """Squared differences of neighbouring log-scale vertices (B, gh, gw) -> (B,).

    dynamic (B, gh, gw) in [0, 1]: fraction of likely-dynamic pixels around each vertex; edges
    there are weighted by (1 + dyn_gain * dynamic) so moving objects cannot bend the mesh.
    """
    dx = (mesh[:, :, 1:] - mesh[:, :, :-1]) ** 2
    dy = (mesh[:, 1:, :] - mesh[:, :-1, :]) ** 2
    if dynamic is None:
        return dx.mean((1, 2)) + dy.mean((1, 2))
    wx = 1 + dyn_gain * torch.maximum(dynamic[:, :, 1:], dynamic[:, :, :-1])
    wy = 1 + dyn_gain * torch.maximum(dynamic[:, 1:, :], dynamic[:, :-1, :])
    return (wx * dx).mean((1, 2)) + (wy * dy).mean((1, 2))


def dense_photometric_loss(
    img_a: torch.Tensor, img_b_warped: torch.Tensor, mask: torch.Tensor, alpha: float = 0.85
) -> torch.Tensor:
    """Whole-image variant (B, C, H, W) images, mask (B, H, W) -> (B,), using kornia's SSIM.
    Kept for evaluation / tests; the optimiser uses the point-sampled ``photometric_loss``."""
    import kornia

    l1 = (img_a - img_b_warped).abs().mean(1)
    dssim = kornia.losses.ssim_loss(img_a, img_b_warped, window_size=3, reduction="none").mean(1)
    return weighted_mean(((1 - alpha) * l1 + alpha * dssim).flatten(1), mask.flatten(1).to(img_a.dtype))
