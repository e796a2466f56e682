"""Weight-free motion masks: pixels whose flow disagrees with the static scene's geometry.

For each neighbour flow of a frame, the static scene's two-view geometry is fitted robustly
(essential matrix by RANSAC on a grid of forward-backward-consistent correspondences, with
the known K); a pixel's Sampson distance to that geometry, compared with the inlier residual
scale, says whether its motion is explained by the camera alone. Under (near) pure rotation
or tiny motion the essential matrix is degenerate, and a homography is the right model
instead: we fit both and keep the one explaining more correspondences. Flags of several
neighbours are OR-ed, cleaned (opening, small components removed) and dilated (the paper's
5x5), and returned as 1 = static.

Limitations (documented, as in every epipolar test): an object moving along its epipolar
line is not detected. The paper's Mask R-CNN semantic masks are the optional
``masks.backend=maskrcnn`` (or ``motion+maskrcnn``), stages.backends.maskrcnn, with local weights.
"""

from __future__ import annotations

import logging
from typing import Sequence

import cv2
import numpy as np

from gcvd_flow.stages.frontend.flow import pixel_grid
from gcvd_flow.stages.frontend.params import MasksSettings

log = logging.getLogger(__name__)

GRID_STEP = 4  # px between sampled correspondences for the robust fit
MIN_POINTS = 30


def _correspondences(flow: np.ndarray, valid: np.ndarray, step: int = GRID_STEP) -> tuple[np.ndarray, np.ndarray]:
    h, w = flow.shape[:2]
    v, u = np.mgrid[step // 2:h:step, step // 2:w:step]
    keep = valid[v, u]
    pa = np.stack([u[keep], v[keep]], -1).astype(np.float64)
    pb = pa + flow[v[keep], u[keep]].astype(np.float64)
    return pa, pb


def _sampson(F: np.ndarray, pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    """Sampson distance (px^2 scale) of correspondences pa -> pb to the fundamental matrix F."""
    xa = np.concatenate([pa, np.ones((len(pa), 1))], 1)
    xb = np.concatenate([pb, np.ones((len(pb), 1))], 1)
    Fxa = xa @ F.T
    Ftxb = xb @ F
    num = np.sum(xb * Fxa, axis=1) ** 2
    den = Fxa[:, 0] ** 2 + Fxa[:, 1] ** 2 + Ftxb[:, 0] ** 2 + Ftxb[:, 1] ** 2
    return num / np.maximum(den, 1e-12)


def motion_residual(K: np.ndarray, flow: np.ndarray, valid: np.ndarray, seed: int = 0) -> np.ndarray | None:
    """Per-pixel residual (px) of the flow against the fitted static-scene model, or None.

    K (3, 3); flow (H, W, 2) px from this frame to a neighbour; valid bool (H, W).
    The residual is sqrt(Sampson distance) for the essential model, or the transfer error for
    the homography model; both are in pixels.
    """
    pa, pb = _correspondences(flow, valid)
    if len(pa) < MIN_POINTS:
        return None
    cv2.setRNGSeed(seed)
    E, inl_e = cv2.findEssentialMat(pa, pb, K, method=cv2.RANSAC, prob=0.999, threshold=1.0)
    Hm, inl_h = cv2.findHomography(pa, pb, cv2.RANSAC, 1.5)
    n_e = int(inl_e.sum()) if inl_e is not None and E is not None and E.shape == (3, 3) else -1
    n_h = int(inl_h.sum()) if inl_h is not None and Hm is not None else -1
    h, w = flow.shape[:2]
    p = pixel_grid(h, w).reshape(-1, 2)  # (u, v) float64, read-only
    q = p + flow.reshape(-1, 2).astype(np.float64)
    if n_h >= 0.9 * max(n_e, 0) and n_h > 0:
        # pure rotation / planar scene / tiny baseline: the homography explains the static scene
        ph = np.concatenate([p, np.ones((len(p), 1))], 1) @ Hm.T
        pred = ph[:, :2] / np.maximum(np.abs(ph[:, 2:3]), 1e-9) * np.sign(ph[:, 2:3])
        res = np.linalg.norm(pred - q, axis=1)
    elif n_e > 0:
        Kinv = np.linalg.inv(K)
        F = Kinv.T @ E @ Kinv
        res = np.sqrt(_sampson(F, p, q))
    else:
        return None
    return res.reshape(h, w).astype(np.float32)


def texture_weight(image: np.ndarray, frac: float, block: int = 7) -> np.ndarray:
    """How far a pixel's flow can be trusted, float32 (H, W) in [0, 1]: the smaller eigenvalue
    of the image's structure tensor over ``block`` px (Shi-Tomasi), relative to ``frac`` x its
    median over the frame, clipped at 1. Flow in textureless areas and along straight edges (the
    aperture problem) is interpolated, not measured: on a static real kitchen its errors were
    most of the pixels the epipolar test flagged (dark cupboard doors, edges, a shiny counter).
    image: uint8 (H, W, 3) RGB."""
    gray = cv2.cvtColor(np.ascontiguousarray(image, dtype=np.uint8), cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    lam = cv2.cornerMinEigenVal(gray, block, ksize=3)
    ref = frac * float(np.median(lam)) + 1e-12
    return np.clip(lam / ref, 0.0, 1.0).astype(np.float32)


def _residuals(K: np.ndarray, flows: Sequence[tuple[np.ndarray, np.ndarray]],
               seed: int) -> list[tuple[np.ndarray, np.ndarray, float, float]]:
    """(residual (H, W) px, valid bool (H, W), median, robust sigma of the valid residuals) of
    each neighbour flow whose static-scene model could be fitted (:func:`motion_residual`; the
    statistics NaN without a valid pixel): computed once per frame, whatever the thresholds
    applied to them afterwards."""
    out: list[tuple[np.ndarray, np.ndarray, float, float]] = []
    for flow, valid in flows:
        valid = np.asarray(valid, bool)
        res = motion_residual(K, flow, valid, seed)
        if res is not None:
            r = res[valid]
            med = np.median(r) if r.size else np.nan
            sigma = 1.4826 * np.median(np.abs(r - med)) if r.size else np.nan
            out.append((res, valid, med, sigma))
    return out


def _residual_ratio(K: np.ndarray, flows: Sequence[tuple[np.ndarray, np.ndarray]], sigma_mult: float,
                    min_threshold: float, seed: int,
                    residuals: list[tuple[np.ndarray, np.ndarray, float, float]] | None = None) -> np.ndarray:
    """max over the neighbour flows of (epipolar residual / that flow's threshold), float32
    (H, W); 0 where no flow is valid. Threshold = max(min_threshold, median + sigma_mult x
    robust sigma of the valid pixels' residuals). ``residuals``: :func:`_residuals` of the same
    flows, when already computed (the fits are most of the cost)."""
    h, w = flows[0][0].shape[:2]
    ratio = np.zeros((h, w), np.float32)
    for res, valid, med, sigma in _residuals(K, flows, seed) if residuals is None else residuals:
        if not valid.any():
            continue
        thr = max(min_threshold, float(med + sigma_mult * sigma))
        # invalid (occluded / inconsistent) pixels carry no evidence either way
        ratio = np.maximum(ratio, np.where(valid, res / thr, 0.0).astype(np.float32))
    return ratio


def _clean(flagged: np.ndarray, min_area: float, dilate: int) -> np.ndarray:
    """Flagged pixels bool (H, W) -> static mask uint8 (H, W), 1 = static: a 3x3 opening, components
    smaller than ``min_area`` of the image dropped (flow noise), the rest dilated by ``dilate`` px."""
    h, w = flagged.shape
    m = cv2.morphologyEx(flagged.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    keep = np.zeros(n, bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= max(4, min_area * h * w)
    m = keep[lab].astype(np.uint8)
    if dilate > 0:
        m = cv2.dilate(m, np.ones((dilate, dilate), np.uint8))
    return (1 - m).astype(np.uint8)


def motion_masks(K: np.ndarray, flows: Sequence[tuple[np.ndarray, np.ndarray]], image: np.ndarray | None = None,
                 dilate: int = MasksSettings.dilate, min_threshold: float = 1.0, sigma_mult: float = 4.0, min_area: float = 0.002,
                 texture_frac: float = 0.0, solve_sigma_mult: float = 4.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(static, solve) uint8 (H, W) masks of one frame, 1 = keep.

    ``static``: what moves (:func:`motion_static_mask`, with the residuals scaled by the image's
    texture, :func:`texture_weight`, when ``image`` and ``texture_frac`` > 0).
    ``solve``: the pixels whose flow the optimisation should trust: static and agreeing with the
    static scene's geometry at ``solve_sigma_mult`` without texture weighting. Flow errors in flat
    areas are not motion (so not in ``static``, which users see and export), but they are bad
    flow: on the real walk-through, handing them to the keyframe optimisation doubled its ATE
    (0.059 -> 0.119 m). For ``texture_frac`` 0 and equal sigmas both masks are the same."""
    if not flows:
        raise ValueError("motion_masks needs at least one neighbour flow")
    residuals = _residuals(K, flows, seed)  # fitted once, thresholded at both sigmas
    ratio = _residual_ratio(K, flows, sigma_mult, min_threshold, seed, residuals)
    weighted = ratio * texture_weight(image, texture_frac) if image is not None and texture_frac > 0 else ratio
    static = _clean(weighted > 1.0, min_area, dilate)
    if solve_sigma_mult == sigma_mult:
        plain = ratio
    else:
        plain = _residual_ratio(K, flows, solve_sigma_mult, min_threshold, seed, residuals)
    solve = np.minimum(static, _clean(plain > 1.0, min_area, dilate)) if weighted is not plain else static
    return static, solve


def motion_static_mask(K: np.ndarray, flows: Sequence[tuple[np.ndarray, np.ndarray]], dilate: int = MasksSettings.dilate,
                       min_threshold: float = 1.0, sigma_mult: float = 4.0, min_area: float = 0.002,
                       seed: int = 0, image: np.ndarray | None = None, texture_frac: float = 0.0) -> np.ndarray:
    """Static mask of one frame from its flows to neighbours: uint8 (H, W), 1 = static.

    flows: [(flow (H, W, 2) px from this frame to a neighbour, valid bool (H, W)), ...].
    A pixel is dynamic when its residual exceeds max(min_threshold, sigma_mult * robust sigma
    of the residuals of valid pixels) in any neighbour flow (the residual scaled by the image's
    texture first when ``image`` is given and ``texture_frac`` > 0, :func:`texture_weight`);
    components smaller than ``min_area`` of the image are dropped (flow noise), the rest
    dilated by ``dilate`` px.
    """
    if not flows:
        raise ValueError("motion_static_mask needs at least one neighbour flow")
    ratio = _residual_ratio(K, flows, sigma_mult, min_threshold, seed)
    if image is not None and texture_frac > 0:
        ratio = ratio * texture_weight(image, texture_frac)
    return _clean(ratio > 1.0, min_area, dilate)
