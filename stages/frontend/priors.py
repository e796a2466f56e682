"""Weight-free geometric depth prior, shaped like MiDaS output (relative inverse depth).

For frame i the pipeline hands over the chain of flows toward a reference frame
(i -> i+1 -> ... or i -> i-1 -> ...). We compose the chain (stages.flow.chain_flows) up to the
longest prefix that keeps enough consistent pixels, fit the two-view geometry (essential
matrix by RANSAC, cheirality without a distance limit: stages.two_view), triangulate every consistent pixel, and turn the sparse,
noisy inverse depths into a dense map with an edge-aware normalised guided filter (weights =
triangulation confidence, guide = the image), coarse to fine so that large holes fill from
their surroundings. The result is divided by its median (MiDaS output is affine-ambiguous;
we keep it positive so it can be used as inverse depth directly).

Pure rotation or too little parallax makes triangulation meaningless; then the prior is a
constant 1 with confidence 0 (documented, not an error).
"""

from __future__ import annotations

import functools
import logging
from typing import Sequence

import cv2
import numpy as np

from gcvd_flow.stages.frontend.flow import chain_flows
from gcvd_flow.stages.geometry.two_view import relative_pose, rotation_from_homography, triangulate_with_angles

log = logging.getLogger(__name__)

MIN_VALID_FRACTION = 0.25  # stop chaining when fewer pixels stay consistent
MIN_PARALLAX_DEG = 0.3  # median triangulation angle below this: no usable depth
GRID_STEP = 3
RANSAC_THRESHOLD_PX = 0.5  # epipolar distance; 1 px let small-baseline poses drift by degrees


def _box(x: np.ndarray, r: int) -> np.ndarray:
    return cv2.boxFilter(x, cv2.CV_64F, (2 * r + 1, 2 * r + 1), normalize=True, borderType=cv2.BORDER_REFLECT)


def guided_filter(guide: np.ndarray, src: np.ndarray, r: int, eps: float) -> np.ndarray:
    """He et al.'s guided filter with a grey guide in [0, 1]: edge-aware smoothing of ``src``."""
    I = guide.astype(np.float64)
    return _guided(I, _guide_stats(I, r), src, r, eps)


def _guide_stats(I: np.ndarray, r: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean, variance) of the guide I (float64 (H, W)) over the box of radius r: what every
    guided filter of that guide and radius shares (densify filters two maps per radius)."""
    mean_I = _box(I, r)
    return mean_I, _box(I * I, r) - mean_I * mean_I


def _guided(I: np.ndarray, stats: tuple[np.ndarray, np.ndarray], src: np.ndarray, r: int, eps: float) -> np.ndarray:
    """guided_filter with the guide's :func:`_guide_stats` given (the same arithmetic, in the same order)."""
    mean_I, var_I = stats
    p = src.astype(np.float64)
    mean_p = _box(p, r)
    cov_Ip = _box(I * p, r) - mean_I * mean_p
    a = cov_Ip / (var_I + eps)
    b = mean_p - a * mean_I
    return _box(a, r) * I + _box(b, r)


def densify(guide: np.ndarray, values: np.ndarray, weights: np.ndarray, radii: Sequence[int] = (2, 4, 8, 16, 32),
            eps: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Fill a sparse map edge-aware: normalised guided filtering, coarse radii fill holes.

    guide (H, W) in [0, 1]; values, weights (H, W) (weights 0 where unknown).
    Returns (dense values (H, W), support (H, W) in [0, 1]).

    The fill stays within the range of the known values: a normalised guided filter is a ratio of
    two independently fitted linear models, so where the weights are sparse it can overshoot
    without bound (a denominator just above its threshold: log-depth corrections of 40 and depth
    10^17 on HoloLens frames without a confident pixel, before 2026-11-29).
    """
    out = np.zeros_like(values, dtype=np.float64)
    have = np.zeros(values.shape, bool)
    support = np.zeros(values.shape, np.float64)
    I = guide.astype(np.float64)
    vw = values * weights
    for r in radii:
        stats = _guide_stats(I, r)  # shared by the numerator's and the denominator's filter
        num = _guided(I, stats, vw, r, eps)
        den = _guided(I, stats, weights, r, eps)
        ok = (den > 1e-3) & ~have
        est = num / np.maximum(den, 1e-6)
        out[ok] = est[ok]
        support[ok] = np.clip(den[ok] / max(float(weights.max()), 1e-9), 0, 1)
        have |= ok
        if have.all():
            break
    known = values[weights > 0]
    if not have.all():
        out[~have] = np.median(known) if known.size else 1.0
    if known.size:
        np.clip(out, known.min(), known.max(), out=out)
    return out, support


def _constant(h: int, w: int) -> dict[str, np.ndarray]:
    return {"inv_depth": np.ones((h, w), np.float32), "confidence": np.zeros((h, w), np.float32)}


@functools.lru_cache(maxsize=8)
def _sample_grid(h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v) int64 (H, W) pixel coordinates and the bool (H, W) grid of every GRID_STEP-th row and
    column, once per image size (read-only: every frame's fit samples the same grid)."""
    vv, uu = np.mgrid[0:h, 0:w]
    on_grid = (vv % GRID_STEP == 0) & (uu % GRID_STEP == 0)
    for a in (uu, vv, on_grid):
        a.setflags(write=False)
    return uu, vv, on_grid


def _triangulate_reference(flow: np.ndarray, valid: np.ndarray, K: np.ndarray,
                           seed: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Sparse inverse depth (H, W) (unit-baseline scale, 0 where unknown) and its weight (H, W)
    in [0, 1] from one flow (H, W, 2) px to a reference and its usable mask (H, W); None when
    the pair cannot be triangulated (rotation only, too little parallax, RANSAC failure)."""
    h, w = valid.shape
    uu, vv, on_grid = _sample_grid(h, w)
    sel = valid & on_grid
    if sel.sum() < 30:
        return None
    pa = np.stack([uu[sel], vv[sel]], -1).astype(np.float64)
    pb = pa + flow[sel].astype(np.float64)
    if rotation_from_homography(pa, pb, K, seed) is not None:
        log.info("prior: flow is explained by a camera rotation alone")
        return None
    rel = relative_pose(pa, pb, K, threshold=RANSAC_THRESHOLD_PX, seed=seed)
    if rel is None:
        return None
    R, t, _ = rel
    # triangulate every consistent pixel (midpoint method in closed form, vectorised)
    idx_v, idx_u = np.nonzero(valid)  # row-major, as a boolean index orders them
    p_all = np.stack([idx_u, idx_v], -1).astype(np.float64)
    q_all = p_all + flow[idx_v, idx_u].astype(np.float64)
    za, parallax = triangulate_with_angles(p_all, q_all, K, R, t)
    good = np.isfinite(za) & (za > 0) & (parallax > 0.05)
    if good.sum() < 30 or np.median(parallax[good]) < MIN_PARALLAX_DEG:
        log.info("prior: too little parallax (median %.3f deg)", float(np.median(parallax)) if parallax.size else 0)
        return None
    inv = np.zeros((h, w))
    wgt = np.zeros((h, w))
    idx_v, idx_u = idx_v[good], idx_u[good]
    inv_vals = 1.0 / za[good]
    # robust clip of outliers (flow errors at occlusion edges)
    lo, hi = np.percentile(inv_vals, [1, 99])
    inv[idx_v, idx_u] = np.clip(inv_vals, lo, hi)
    # confidence grows with the triangulation angle (depth noise ~ 1 / parallax)
    wgt[idx_v, idx_u] = np.clip(parallax[good] / 2.0, 0.05, 1.0)
    return inv, wgt


def geometric_prior(image: np.ndarray, K: np.ndarray, chain: Sequence[tuple[np.ndarray, np.ndarray]],
                    seed: int = 0, extra: Sequence[tuple[np.ndarray, np.ndarray]] = ()) -> dict[str, np.ndarray]:
    """Relative inverse depth of ``image`` from flows toward reference frames.

    image uint8 (H, W, 3); K (3, 3); chain [(flow (H, W, 2), valid bool (H, W)), ...] successive
    flows from this frame toward the main reference; extra [(flow, valid), ...] direct flows to
    further references. Each reference is triangulated on its own (its own two-view pose, unit
    baseline), brought to the main reference's scale by the median ratio on pixels both see, and
    the sparse maps are averaged with triangulation-angle weights: a second reference fills what
    the first cannot see (occlusions, pixels that left its view) and halves noise where both do.
    Returns {inv_depth float32 (H, W) > 0 with median 1, confidence float32 (H, W) in [0, 1]}.
    """
    h, w = image.shape[:2]
    if not chain:
        return _constant(h, w)
    # longest prefix of the chain that keeps enough consistent pixels (more baseline = better)
    flow, valid = chain[0]
    valid = np.asarray(valid, bool)
    for k in range(2, len(chain) + 1):
        f, v = chain_flows(chain[:k])
        if v.mean() < MIN_VALID_FRACTION:
            break
        flow, valid = f, v
    maps = []
    for fl, va in [(flow, valid), *[(f, np.asarray(v, bool)) for f, v in extra]]:
        r = _triangulate_reference(np.asarray(fl), va, K, seed)
        if r is not None:
            maps.append(r)
    if not maps:
        log.info("prior: no reference could be triangulated; constant prior")
        return _constant(h, w)
    inv, wgt = maps[0]
    num, den = inv * wgt, wgt.copy()
    for inv_k, wgt_k in maps[1:]:
        both = (wgt > 0) & (wgt_k > 0)
        if both.sum() < 30:
            continue
        s = float(np.median(inv[both] / inv_k[both]))
        num += s * inv_k * wgt_k
        den += wgt_k
    have = den > 0
    inv = np.where(have, num / np.maximum(den, 1e-12), 0.0)
    wgt = np.clip(den, 0.0, 1.0)
    lo = float(np.percentile(inv[have], 1))
    gray = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY).astype(np.float64) / 255.0
    dense, support = densify(gray, inv, wgt)
    dense = np.maximum(dense, lo * 0.5)
    med = np.median(dense)
    if not np.isfinite(med) or med <= 0:
        return _constant(h, w)
    return {"inv_depth": (dense / med).astype(np.float32), "confidence": support.astype(np.float32)}


def prior_with_fallback(image: np.ndarray, K: np.ndarray, direct: Sequence[tuple[np.ndarray, np.ndarray]],
                        chain: Sequence[tuple[np.ndarray, np.ndarray]] = ()) -> dict[str, np.ndarray]:
    """geometric_prior from the direct flows [(flow, valid), ...] to the references (the caller keeps
    those with MIN_VALID_FRACTION of their pixels consistent; the first is the main reference); when there is none (fast motion:
    a direct flow over many frames fails its forward-backward check almost everywhere), from the
    chain of adjacent flows toward the reference instead (geometric_prior keeps its longest prefix
    that stays consistent); a constant prior when there is neither."""
    usable = [(f, np.asarray(v, bool)) for f, v in direct]
    if usable:
        return geometric_prior(image, K, usable[:1], extra=usable[1:])
    if chain:
        log.info("prior: no direct flow is consistent enough; triangulating the adjacent-flow chain")
        return geometric_prior(image, K, chain)
    h, w = image.shape[:2]
    return _constant(h, w)
