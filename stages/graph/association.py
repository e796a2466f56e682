"""Keyframe association: global descriptors, loop candidates, verification, the keyframe graph.

docs/design.md, "Stage: association". Every keyframe gets a global descriptor; the cosine-similarity
matrix proposes
non-sequential pairs (more than ``min_separation`` keyframes apart, local maxima of an
``nms`` x ``nms`` max-pool over the matrix, similarity >= threshold); each candidate is
verified geometrically (SIFT + RANSAC homography / essential-matrix inlier ratio >= 0.5),
by flow (fraction of forward-backward consistent pixels >= 0.1 with a 2 px test) and by size
of motion (mean flow <= the keyframe threshold, i.e. the two views are "one keyframe apart").

Default descriptor (weight-free, ``global_descriptor``): a 3-level spatial pyramid (1x1, 2x2,
4x4 cells) of 8-bin unsigned gradient-orientation histograms (magnitude weighted, soft
binned) plus an 8x6 colour thumbnail standardised per channel; each part is power-normalised
(signed square root), mean-centred and L2-normalised, then both are concatenated with equal
weight and L2-normalised again. It is place- and layout-specific (the pyramid keeps where
structure is) and tolerant to the few-pixel shifts between views of the same place.
Its cosine similarities are NOT on the scale of the paper's ResNet-GAP features (paper
threshold 0.9); see ``DEFAULT_SIMILARITY_THRESHOLD`` for the calibrated value. The ImageNet
ResNet-18 descriptor (paper) is in ``stages/backends/resnet.py``; pass its descriptors to
:func:`build_graph` via ``descriptors=`` together with ``similarity_threshold=0.9``.

Opt-in candidates (``retrieval="vocabulary"``): visual vocabularies of the clip's own keyframes'
SIFT features scored over all keyframe pairs (:mod:`stages.graph.retrieval`); the global
descriptor below (the default) finds revisits only from nearly the same viewpoint.

Keyframe-pair flow: views of a revisited place can be far apart in image space, where DIS
alone fails; so b is first pre-warped onto a with the RANSAC homography, DIS runs on the
residual motion, and the result is mapped back to flow in b's original pixel coordinates.

Pure functions; deterministic (cv2.setRNGSeed before every RANSAC call, DIS is deterministic).
"""

from __future__ import annotations

import logging
from typing import Any, Callable, Iterable, Literal

import cv2
import numpy as np
from scipy.ndimage import maximum_filter

from gcvd_flow.stages.frontend.flow import dis_flow, fb_consistency
from gcvd_flow.stages.frontend.params import settings_with
from gcvd_flow.stages.geometry.image import apply_homography
from gcvd_flow.stages.geometry.two_view import pose_from_essential
from gcvd_flow.stages.graph import retrieval as retrieval_mod
from gcvd_flow.stages.graph.params import AssociationSettings
from gcvd_flow.stages.sfm.features import SiftFeatures, ratio_matches, sift_features

log = logging.getLogger(__name__)

# Calibrated on stages.synth clips (loop / orbit / forward / rotation, 120 frames, every 4th
# frame paired with every other, at 160x120 and 256x192; 1740 pairs per size), binned by the
# ground-truth mean rigid flow between the two views in units of the keyframe threshold
# (0.1 * min(H, W)):
#   <= 1 threshold (what verification accepts): min 0.715 / 0.753, 5th pct 0.78 / 0.80
#   1-3 thresholds:                             median 0.68, 95th pct 0.82 / 0.80
#   > 3 thresholds (different places):           max 0.59 / 0.57, median 0.40 / 0.47
# 0.7 keeps every pair verification could accept and drops all clearly different places;
# the geometric/flow verification rejects the rest. (Not comparable with ResNet's 0.9.)
DEFAULT_SIMILARITY_THRESHOLD: float = 0.7
# The paper's threshold for ImageNet ResNet GAP features (stages/backends/resnet.py).
RESNET_SIMILARITY_THRESHOLD: float = 0.9

DESCRIPTOR_SIZE: tuple[int, int] = (128, 96)  # (W, H) the image is resampled to
_ORI_BINS = 8
_PYRAMID = (1, 2, 4)
_THUMB: tuple[int, int] = (8, 6)  # (W, H)

SIFT_RATIO = 0.75
# OpenCV's default contrast threshold (0.04) is tuned for megapixel photos; at working
# resolutions (<= 384 px) it leaves ~60 keypoints on a 160x120 frame and homographies of
# wide-baseline pairs fail. 0.02 gives ~4-5x more keypoints (measured on stages.synth clips).
SIFT_CONTRAST = 0.02
RANSAC_SEED = 0
MIN_MATCHES = 12
HOMOGRAPHY_RANSAC_PX = 3.0
ESSENTIAL_RANSAC_PX = 1.0
# Forward motion (prewarp_sequential="auto"): a consecutive pair moves forward when its baseline
# lies within FORWARD_MAX_DEG of the optical axis (the epipole well inside the image), the clip when
# FORWARD_MIN_SHARE of its pairs do (the calibrate stage's rule: KITTI 1.0; HoloLens walk-through
# 0.41-0.56, synthetic walk 0.47, loop 0.06, ICL 0 there).
FORWARD_MAX_DEG = 30.0
FORWARD_MIN_SHARE = 0.8


# ----------------------------------------------------------------------------- descriptor


def _power_l2(v: np.ndarray) -> np.ndarray:
    v = np.sign(v) * np.sqrt(np.abs(v))
    v = v - v.mean()
    n = np.linalg.norm(v)
    return v / n if n > 0 else v


def global_descriptor(image: np.ndarray) -> np.ndarray:
    """Weight-free global descriptor of an image.

    Args:
        image: uint8 (H, W, 3) RGB (any size; resampled to ``DESCRIPTOR_SIZE``).

    Returns:
        float32 (D,) L2-normalised, D = 8 * (1 + 4 + 16) + 3 * 8 * 6 = 312.
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"image must be (H, W, 3), got {img.shape}")
    small = cv2.resize(img, DESCRIPTOR_SIZE, interpolation=cv2.INTER_AREA).astype(np.float32)

    # Gradient-orientation pyramid. Blur first so the histogram reflects structure, not the
    # pixel-level texture noise that changes with any sub-pixel shift.
    gray = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY)
    gray = cv2.GaussianBlur(gray, (0, 0), 1.0)
    gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3)
    mag = np.hypot(gx, gy)
    # Unsigned orientation in [0, pi): robust to contrast inversion between views.
    ang = np.mod(np.arctan2(gy, gx), np.pi) / np.pi * _ORI_BINS
    b0 = np.floor(ang).astype(np.int64) % _ORI_BINS
    frac = ang - np.floor(ang)
    b1 = (b0 + 1) % _ORI_BINS
    h, w = gray.shape
    hog_parts = []
    for cells in _PYRAMID:
        ys = np.minimum((np.arange(h) * cells) // h, cells - 1)
        xs = np.minimum((np.arange(w) * cells) // w, cells - 1)
        cell = (ys[:, None] * cells + xs[None, :]).ravel()
        hist = np.zeros((cells * cells, _ORI_BINS), np.float64)
        np.add.at(hist, (cell, b0.ravel()), (mag * (1 - frac)).ravel())
        np.add.at(hist, (cell, b1.ravel()), (mag * frac).ravel())
        # Normalise each cell by its own energy so bright, high-contrast cells do not
        # dominate; the epsilon keeps flat cells (walls) near zero instead of amplifying noise.
        norm = np.linalg.norm(hist, axis=1, keepdims=True)
        hist = hist / (norm + 1e-3 * (norm.mean() + 1e-6) + 1e-6)
        hog_parts.append(hist.ravel() / np.sqrt(cells * cells))
    hog = _power_l2(np.concatenate(hog_parts))

    # Colour layout thumbnail, standardised per channel (exposure/white-balance tolerant).
    thumb = cv2.resize(small, _THUMB, interpolation=cv2.INTER_AREA)
    thumb = thumb.reshape(-1, 3).astype(np.float64)
    thumb = (thumb - thumb.mean(0)) / (thumb.std(0) + 1.0)
    col = _power_l2(thumb.ravel())

    desc = np.concatenate([hog, col]) / np.sqrt(2.0)
    n = np.linalg.norm(desc)
    return (desc / n if n > 0 else desc).astype(np.float32)


def similarity_matrix(desc: np.ndarray) -> np.ndarray:
    """Cosine similarity (K, K) float64 of L2-normalised descriptors (K, D)."""
    d = np.asarray(desc, dtype=np.float64)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return d @ d.T


def candidate_pairs(
    desc: np.ndarray,
    threshold: float = DEFAULT_SIMILARITY_THRESHOLD,
    nms: int = 8,
    min_separation: int = 8,
    per_keyframe: int = 0,
    max_candidates: int | None = None,
) -> list[tuple[int, int, float]]:
    """Loop-closure candidates among keyframes.

    Args:
        desc: (K, D) L2-normalised descriptors, one per keyframe (in keyframe order).
        threshold: minimum cosine similarity.
        nms: side of the max-pool window over the similarity matrix; a pair survives only if
            it is the maximum of its nms x nms neighbourhood (of eligible pairs). This keeps
            one pair per revisit instead of a block of near-duplicates.
        min_separation: only pairs with b - a > min_separation (keyframe units) are eligible;
            closer pairs are already linked by sequential edges (tau <= 8).
        per_keyframe: also keep, for every keyframe, its ``per_keyframe`` most similar eligible
            partners (above ``threshold``): a revisit that lasts several keyframes then gives
            several loop edges (one per keyframe of it) instead of the single NMS maximum, which
            ties more of the path to the revisit in the pose graph and bundle adjustment. 0: the
            paper's NMS candidates only.
        max_candidates: keep at most this many (the most similar); None: all.

    Returns:
        [(a, b, similarity)] with a < b keyframe positions, sorted by decreasing similarity
        (ties by (a, b)).
    """
    s = similarity_matrix(desc)
    k = s.shape[0]
    a_idx, b_idx = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
    eligible = (b_idx - a_idx) > min_separation
    masked = np.where(eligible, s, -np.inf)
    if nms > 1:
        pooled = maximum_filter(masked, size=int(nms), mode="constant", cval=-np.inf)
    else:
        pooled = masked
    keep = eligible & (masked >= threshold) & (masked >= pooled)
    if per_keyframe > 0 and k:
        sym = np.maximum(masked, masked.T)  # partners before or after, each pair once as (a < b)
        order = np.argsort(-sym, axis=1, kind="stable")[:, : int(per_keyframe)]
        for a in range(k):
            for b in order[a]:
                lo, hi = min(a, int(b)), max(a, int(b))
                if eligible[lo, hi] and s[lo, hi] >= threshold:
                    keep[lo, hi] = True
    out = [(int(a), int(b), float(s[a, b])) for a, b in zip(*np.nonzero(keep))]
    out.sort(key=lambda t: (-t[2], t[0], t[1]))
    return out if max_candidates is None else out[: int(max_candidates)]


# ----------------------------------------------------------------------------- matching


def _sift_features(img: np.ndarray) -> SiftFeatures:
    """SIFT keypoint positions and descriptors of one image, all of them (a keyframe takes part in
    several pairs: its features are computed once; a top-level function for the worker map)."""
    return sift_features(img, 0, contrast=SIFT_CONTRAST)


def _sift_matches(img_a: np.ndarray, img_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ratio-test SIFT matches: (pts_a (M, 2), pts_b (M, 2)) float64 px, deterministic order."""
    return ratio_matches(_sift_features(img_a), _sift_features(img_b), SIFT_RATIO)


def _homography(pts_a: np.ndarray, pts_b: np.ndarray) -> tuple[np.ndarray | None, float]:
    """RANSAC homography H with p_a ~ H p_b, and its inlier ratio among the matches."""
    if len(pts_a) < max(4, MIN_MATCHES):
        return None, 0.0
    cv2.setRNGSeed(RANSAC_SEED)
    h, inl = cv2.findHomography(
        pts_b, pts_a, cv2.RANSAC, HOMOGRAPHY_RANSAC_PX, maxIters=2000, confidence=0.999
    )
    if h is None or inl is None or not np.all(np.isfinite(h)):
        return None, 0.0
    return h, float(inl.ravel().astype(bool).mean())


def _essential(pts_a: np.ndarray, pts_b: np.ndarray, K: np.ndarray) -> tuple[np.ndarray | None, float, int]:
    """RANSAC essential matrix E (3, 3) with x_b^T E x_a = 0 (normalised coordinates), or None;
    its inlier ratio among the matches and its inlier count (the calibrated form of the
    fundamental test)."""
    if len(pts_a) < max(5, MIN_MATCHES):
        return None, 0.0, 0
    cv2.setRNGSeed(RANSAC_SEED)
    e, inl = cv2.findEssentialMat(
        pts_a, pts_b, np.asarray(K, np.float64), cv2.RANSAC, 0.999, ESSENTIAL_RANSAC_PX
    )
    if e is None or inl is None or e.shape != (3, 3):
        return None, 0.0, 0
    mask = inl.ravel().astype(bool)
    return np.asarray(e, np.float64), float(mask.mean()), int(mask.sum())


def _essential_inlier_ratio(pts_a: np.ndarray, pts_b: np.ndarray, K: np.ndarray) -> float:
    """Inlier ratio of a RANSAC essential matrix (the calibrated form of the fundamental test)."""
    return _essential(pts_a, pts_b, K)[1]


def flow_epipolar_agreement(
    E: np.ndarray, K: np.ndarray, fwd: np.ndarray, valid: np.ndarray, max_px: float = 2.0, step: int = 4
) -> float:
    """Share of a's forward-backward-consistent flow correspondences (on a ``step`` px grid)
    within ``max_px`` (Sampson distance, px) of the epipolar geometry E (3, 3) that the SIFT
    matches gave: the dense flow and the sparse features must describe the same two-view
    geometry. A look-alike place (repeated texture, another room with the same furniture) can
    give a homography of a few features, rarely a dense flow field that obeys it. fwd (H, W, 2)
    px a -> b, valid bool (H, W); 0.0 when no pixel is consistent."""
    h, w = valid.shape
    v, u = np.mgrid[step // 2:h:step, step // 2:w:step]
    keep = valid[v, u]
    if not keep.any():
        return 0.0
    pa = np.stack([u[keep], v[keep]], -1).astype(np.float64)
    pb = pa + fwd[v[keep], u[keep]].astype(np.float64)
    Kinv = np.linalg.inv(np.asarray(K, np.float64))
    F = Kinv.T @ E @ Kinv
    xa = np.concatenate([pa, np.ones((len(pa), 1))], 1)
    xb = np.concatenate([pb, np.ones((len(pb), 1))], 1)
    Fxa, Ftxb = xa @ F.T, xb @ F
    num = np.sum(xb * Fxa, axis=1) ** 2
    den = Fxa[:, 0] ** 2 + Fxa[:, 1] ** 2 + Ftxb[:, 0] ** 2 + Ftxb[:, 1] ** 2
    return float(np.mean(num / np.maximum(den, 1e-12) <= max_px ** 2))


def _flow_with_prewarp(
    img_a: np.ndarray, img_b: np.ndarray, h_ab: np.ndarray, fb_thresh: float
) -> dict[str, np.ndarray]:
    """Flow a <-> b with b pre-warped onto a by h_ab (p_a ~ h_ab p_b)."""
    hgt, wid = img_a.shape[:2]
    yy, xx = np.mgrid[0:hgt, 0:wid].astype(np.float64)
    # b_w(p) = b(h_ab^-1 p): b resampled on a's grid. Pixels of b_w with no source in b are
    # filled by edge replication; they get no valid flow below (source-in-image tests).
    b_w = cv2.warpPerspective(
        img_b, h_ab, (wid, hgt), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    fwd_w = dis_flow(img_a, b_w).astype(np.float64)  # on a's grid, into b_w coords
    bwd_w = dis_flow(b_w, img_a).astype(np.float64)  # on b_w's grid, into a coords
    h_inv = np.linalg.inv(h_ab)

    # Forward: p in a -> p + fwd_w(p) in b_w -> h_ab^-1 (.) in b.
    tx, ty = apply_homography(h_inv, xx + fwd_w[..., 0], yy + fwd_w[..., 1])
    fwd = np.stack([tx - xx, ty - yy], -1)

    # Backward: q in b sits at h_ab q in b_w; sample bwd_w there (bilinear) -> point in a.
    qx, qy = apply_homography(h_ab, xx, yy)
    samp = cv2.remap(
        bwd_w.astype(np.float32), qx.astype(np.float32), qy.astype(np.float32),
        cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE,
    )
    bwd = np.stack([qx + samp[..., 0] - xx, qy + samp[..., 1] - yy], -1)
    b_src_ok = (qx >= 0) & (qx <= wid - 1) & (qy >= 0) & (qy <= hgt - 1)

    # Pixels of a whose b_w neighbourhood came from outside b (replicated border) are not
    # measurements; fb_consistency already rejects targets outside b.
    finite_f = np.isfinite(fwd).all(-1)
    finite_b = np.isfinite(bwd).all(-1) & b_src_ok
    fwd = np.where(finite_f[..., None], fwd, 0.0).astype(np.float32)
    bwd = np.where(finite_b[..., None], bwd, 0.0).astype(np.float32)
    fwd_valid = fb_consistency(fwd, bwd, fb_thresh) & finite_f
    bwd_valid = fb_consistency(bwd, fwd, fb_thresh) & finite_b
    return {"fwd": fwd, "bwd": bwd, "fwd_valid": fwd_valid, "bwd_valid": bwd_valid}


def keyframe_pair_flow(
    img_a: np.ndarray,
    img_b: np.ndarray,
    fb_thresh: float = 2.0,
    _matches: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict[str, np.ndarray]:
    """Flow between two keyframes with homography pre-warping.

    Args:
        img_a, img_b: uint8 (H, W, 3) RGB of the same size.
        fb_thresh: forward-backward consistency threshold in px (paper: 2 for keyframe pairs).

    Returns:
        dict(fwd float32 (H, W, 2) a -> b on a's grid, bwd float32 (H, W, 2) b -> a on b's
        grid, fwd_valid / bwd_valid bool (H, W), homography float64 (3, 3) with
        p_a ~ H p_b (identity when SIFT/RANSAC found none)).
    """
    if img_a.shape != img_b.shape:
        raise ValueError(f"image shapes differ: {img_a.shape} vs {img_b.shape}")
    pts_a, pts_b = _matches if _matches is not None else _sift_matches(img_a, img_b)
    h, _ = _homography(pts_a, pts_b)
    if h is None:
        h = np.eye(3)
    out = _flow_with_prewarp(img_a, img_b, h, fb_thresh)
    out["homography"] = np.asarray(h, np.float64)
    return out


def forward_share(features: list[SiftFeatures], K: np.ndarray, max_deg: float = FORWARD_MAX_DEG) -> float:
    """Share of consecutive keyframe pairs whose translation (SIFT matches, RANSAC essential
    matrix, cheirality) lies within ``max_deg`` of the first keyframe's optical axis, among the
    pairs with an essential matrix of at least MIN_MATCHES inliers; 0.0 when there is none. A
    rotation-only pair's translation direction is noise, which rarely falls in the cone."""
    n = k = 0
    for fa, fb in zip(features[:-1], features[1:]):
        pts_a, pts_b = ratio_matches(fa, fb, SIFT_RATIO)
        E, _, n_inl = _essential(pts_a, pts_b, K)
        if E is None or n_inl < MIN_MATCHES:
            continue
        _, t, n_front = pose_from_essential(E, pts_a, pts_b, np.asarray(K, np.float64))
        if n_front <= 0 or not np.linalg.norm(t) > 0:
            continue
        n += 1
        k += abs(float(t[2])) / float(np.linalg.norm(t)) >= np.cos(np.radians(max_deg))
    return k / n if n else 0.0


RetrievalMode = Literal["vocabulary", "global"]
PrewarpMode = Literal["auto", "on", "off"]
VerifyMode = Literal["geometric", "paper"]


# The body is the sparse test (feature matches) then the dense one (pre-warped flow), each a
# short list of rules; long because the docstring documents both modes and every output key
def verify_pair(
    img_a: np.ndarray,
    img_b: np.ndarray,
    K: np.ndarray,
    keyframe_threshold_px: float,
    min_inlier_ratio: float = 0.5,
    min_consistent: float = 0.1,
    fb_thresh: float = 2.0,
    mode: VerifyMode = "geometric",
    min_inliers: int = 20,
    min_epipolar: float = 0.5,
    epipolar_px: float = 2.0,
    _matches: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Geometric + flow verification of a loop candidate (docs/design.md, "Stage: association").

    Both modes require ``min_inlier_ratio`` (max of homography and essential-matrix RANSAC
    inlier ratios over ratio-test SIFT matches) and ``min_consistent`` (fraction of a's pixels
    with ``fb_thresh`` px forward-backward consistent pre-warped flow). Then:

    - ``"paper"``: the mean flow must be <= the keyframe threshold (the two views "one keyframe
      apart"). A handheld camera rarely returns that exactly: on real revisits the accepted
      geometry came with 25-48 px of mean flow against a 19 px threshold.
    - ``"geometric"`` (default): wide-baseline revisits are accepted when the geometry is sound:
      at least ``min_inliers`` essential-matrix inliers (a ratio of few matches says little),
      and the dense flow agrees with that essential matrix (:func:`flow_epipolar_agreement`:
      share of consistent pixels within ``epipolar_px`` >= ``min_epipolar``). Under pure
      rotation or a planar view the homography explains the matches and the essential test is
      skipped (every flow obeys a rotation's epipolar geometry).

    Returns a dict with ``accepted`` (bool), ``inlier_ratio``, ``n_matches``, ``n_inliers``
    (essential-matrix inliers), ``consistent_fraction``, ``mean_flow`` (px, mean |fwd| over
    consistent pixels, in original coordinates), ``epipolar`` (flow share agreeing with E, -1
    when not computed), ``reason`` ("ok" or why it was rejected) and the flow dict of
    :func:`keyframe_pair_flow` (``fwd``, ``bwd``, ``fwd_valid``, ``bwd_valid``, ``homography``).
    A pair the feature matches already reject (too few matches, inlier ratio, too few inliers)
    gets no dense flow (the expensive part: retrieval proposes many candidates): no flow keys,
    ``consistent_fraction`` -1, ``mean_flow`` inf.
    """
    if mode not in ("geometric", "paper"):
        raise ValueError(f"mode must be 'geometric' or 'paper', got {mode!r}")
    pts_a, pts_b = _matches if _matches is not None else _sift_matches(img_a, img_b)
    n_matches = int(len(pts_a))
    _, h_ratio = _homography(pts_a, pts_b)
    E, e_ratio, n_inl = _essential(pts_a, pts_b, K)
    inlier_ratio = max(h_ratio, e_ratio)
    n_model = int(max(n_inl, int(round(h_ratio * n_matches))))
    sparse = None  # the feature matches alone reject the pair: no dense flow (most of the cost)
    if n_matches < MIN_MATCHES:
        sparse = f"too few matches ({n_matches} < {MIN_MATCHES})"
    elif inlier_ratio < min_inlier_ratio:
        sparse = f"inlier ratio {inlier_ratio:.3f} < {min_inlier_ratio}"
    elif mode == "geometric" and n_model < min_inliers:
        sparse = f"too few inliers ({n_model} < {min_inliers})"
    if sparse is not None:
        return {"accepted": False, "inlier_ratio": float(inlier_ratio), "n_matches": n_matches, "n_inliers": n_model,
                "consistent_fraction": -1.0, "mean_flow": float("inf"), "epipolar": -1.0, "reason": sparse}
    flow = keyframe_pair_flow(img_a, img_b, fb_thresh=fb_thresh, _matches=(pts_a, pts_b))
    valid = flow["fwd_valid"]
    consistent = float(valid.mean())
    mag = np.linalg.norm(flow["fwd"].astype(np.float64), axis=-1)
    mean_flow = float(mag[valid].mean()) if valid.any() else float("inf")
    planar = h_ratio >= e_ratio  # rotation / planar view: the homography is the model
    epi = -1.0
    if mode == "geometric" and E is not None and not planar:
        epi = flow_epipolar_agreement(E, K, flow["fwd"], valid, max_px=epipolar_px)

    if consistent < min_consistent:
        reason = f"consistent fraction {consistent:.3f} < {min_consistent}"
    elif mode == "paper" and not mean_flow <= keyframe_threshold_px:
        reason = f"mean flow {mean_flow:.2f} px > keyframe threshold {keyframe_threshold_px:.2f} px"
    elif mode == "geometric" and not planar and epi < min_epipolar:
        reason = f"flow disagrees with the matches' geometry ({epi:.3f} < {min_epipolar} within {epipolar_px} px)"
    else:
        reason = "ok"
    out: dict[str, Any] = {
        "accepted": reason == "ok",
        "inlier_ratio": float(inlier_ratio),
        "n_matches": n_matches,
        "n_inliers": n_model,
        "consistent_fraction": consistent,
        "mean_flow": mean_flow,
        "epipolar": float(epi),
        "reason": reason,
    }
    out.update(flow)
    return out


# ----------------------------------------------------------------------------- graph


def sequential_edges(kfs: list[int], taus: tuple[int, ...]) -> list[dict[str, Any]]:
    """{i, j, tau, weight = 1/tau} for every keyframe and every tau that stays in the clip."""
    out = []
    for m in range(len(kfs)):
        for tau in sorted(set(int(t) for t in taus)):
            if m + tau < len(kfs):
                out.append({"i": kfs[m], "j": kfs[m + tau], "tau": tau, "weight": 1.0 / tau})
    return out


# call_map(fn, args) -> [fn(a) for a in args] in argument order: ``map``, or the run's worker
# processes (``fn`` module-level, arguments picklable); every call is a pure function of its
# arguments, so the graph does not depend on where the calls ran
CallMap = Callable[[Callable[[Any], Any], Iterable[Any]], Iterable[Any]]


def _pair_flow_call(args: tuple[np.ndarray, np.ndarray, SiftFeatures, SiftFeatures, float, bool]
                    ) -> dict[str, np.ndarray]:
    """One consecutive keyframe pair: (img_a, img_b, features a, features b, fb_thresh, prewarp) ->
    :func:`keyframe_pair_flow`, or without ``prewarp`` the plain flow (homography: identity)."""
    img_a, img_b, fa, fb, fb_thresh, prewarp = args
    if not prewarp:
        return {**_flow_with_prewarp(img_a, img_b, np.eye(3), fb_thresh), "homography": np.eye(3)}
    return keyframe_pair_flow(img_a, img_b, fb_thresh=fb_thresh, _matches=ratio_matches(fa, fb, SIFT_RATIO))


def _verify_call(args: tuple[np.ndarray, np.ndarray, SiftFeatures, SiftFeatures, np.ndarray, float, dict[str, Any]],
                 ) -> dict[str, Any]:
    """One loop candidate: (img_a, img_b, features a, features b, K, keyframe threshold px,
    verify_pair keywords) -> :func:`verify_pair`."""
    img_a, img_b, fa, fb, K, threshold_px, kw = args
    return verify_pair(img_a, img_b, K, threshold_px, _matches=ratio_matches(fa, fb, SIFT_RATIO), **kw)


def _verify_candidates(
    cands: list[tuple[int, int, float]],
    kfs: list[int],
    kf_images: list[np.ndarray] | np.ndarray,
    K: np.ndarray,
    keyframe_threshold_px: float,
    edge_flows: dict[tuple[int, int], dict[str, np.ndarray]],
    features: list[SiftFeatures],
    call_map: CallMap = map,
    **verify_kw: Any,
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """(accepted, rejected) statistics of each candidate pair (a, b, similarity) (keyframe
    positions); the flows of accepted pairs are added to ``edge_flows`` under frame indices."""
    accepted, rejected = [], []
    calls = ((kf_images[a], kf_images[b], features[a], features[b], K, keyframe_threshold_px, verify_kw)
             for a, b, _ in cands)
    for (a, b, sim), v in zip(cands, call_map(_verify_call, calls)):
        stats = {
            "i": kfs[a],
            "j": kfs[b],
            "similarity": float(sim),
            "inlier_ratio": v["inlier_ratio"],
            "consistent_fraction": v["consistent_fraction"],
            "n_inliers": v["n_inliers"],
            "epipolar": v["epipolar"],
            # inf (no consistent pixel) is not JSON: record None.
            "mean_flow": v["mean_flow"] if np.isfinite(v["mean_flow"]) else None,
        }
        if v["accepted"]:
            accepted.append(stats)
            keys = ("fwd", "bwd", "fwd_valid", "bwd_valid", "homography")
            edge_flows[(kfs[a], kfs[b])] = {k: v[k] for k in keys}
        else:
            rejected.append({**stats, "reason": v["reason"]})
    return accepted, rejected


def _consecutive_flows(kfs: list[int], kf_images: list[np.ndarray] | np.ndarray, features: list[SiftFeatures],
                       fb_thresh: float, call_map: CallMap = map, prewarp: bool = False
                       ) -> dict[tuple[int, int], dict[str, np.ndarray]]:
    """{(frame i, frame j): keyframe_pair_flow} of every pair of consecutive keyframes (pre-warped
    by the homography only with ``prewarp``: see :func:`build_graph`)."""
    calls = ((kf_images[m], kf_images[m + 1], features[m], features[m + 1], fb_thresh, prewarp)
             for m in range(len(kfs) - 1))
    return {(kfs[m], kfs[m + 1]): fl for m, fl in enumerate(call_map(_pair_flow_call, calls))}


def suppress_loops(accepted: list[dict[str, Any]], kfs: list[int], window: int) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Non-maximum suppression of verified loop edges: (kept, suppressed).

    An edge is kept unless a better one (more inliers, then a larger consistent fraction, then
    the lower (i, j)) was kept with both ends within ``window // 2`` keyframes of its ends: one
    loop edge per revisited stretch, as the paper's NMS over the similarity matrix gives. More
    edges of the same revisit did not help the pose graph (their relative poses, from wider
    views, are noisier): synthetic loop 0.88 -> 1.12 mm, HoloLens 0.061 -> 0.069 m with all.
    ``window`` <= 1 keeps all. Keeps the input order."""
    if window <= 1:
        return list(accepted), []
    pos = {f: k for k, f in enumerate(kfs)}
    r = int(window) // 2
    order = sorted(range(len(accepted)), key=lambda k: (-accepted[k]["n_inliers"], -accepted[k]["consistent_fraction"],
                                                          accepted[k]["i"], accepted[k]["j"]))
    kept_idx: list[int] = []
    for k in order:
        a, b = pos[accepted[k]["i"]], pos[accepted[k]["j"]]
        if all(abs(a - pos[accepted[m]["i"]]) > r or abs(b - pos[accepted[m]["j"]]) > r for m in kept_idx):
            kept_idx.append(k)
    keep = set(kept_idx)
    return ([e for k, e in enumerate(accepted) if k in keep], [e for k, e in enumerate(accepted) if k not in keep])


# The body is the four steps in order (SIFT + consecutive flows, descriptors, candidates,
# verification); long because half of it is the docstring documenting every argument and the output
def build_graph(
    kf_indices: list[int],
    kf_images: list[np.ndarray] | np.ndarray,
    K: np.ndarray,
    keyframe_threshold_px: float,
    settings: AssociationSettings | None = None,
    *,
    taus: tuple[int, ...] = (1, 2, 4, 8),
    similarity_threshold: float | None = None,
    descriptors: np.ndarray | None = None,
    descriptor_fn: Callable[[np.ndarray], np.ndarray] | None = None,
    fb_thresh: float = 2.0,
    call_map: CallMap = map,
    seed: int = 0,
    **overrides: Any,
) -> tuple[dict[str, Any], dict[tuple[int, int], dict[str, np.ndarray]]]:
    """Build the keyframe graph: sequential edges + verified non-sequential edges.

    Args:
        kf_indices: frame indices of the keyframes (increasing).
        kf_images: uint8 (H, W, 3) RGB image of each keyframe.
        K: (3, 3) intrinsics.
        keyframe_threshold_px: threshold used for keyframe selection (``threshold_px``).
        settings: the association stage's :class:`AssociationSettings` (None: its defaults),
            ``overrides`` replacing fields by name; every argument below named like a field
            (nms, min_separation, verify, ...) is that field. ``enabled``, ``backend`` and
            ``weights`` are the caller's (it passes ``descriptors`` / ``descriptor_fn``).
        similarity_threshold: None: the settings' ``threshold``, or DEFAULT_SIMILARITY_THRESHOLD.
        taus: keyframe distances of sequential edges (weight 1/tau).
        similarity_threshold: descriptor threshold (default calibrated for
            :func:`global_descriptor`; use ``RESNET_SIMILARITY_THRESHOLD`` for ResNet).
        nms, min_separation: see :func:`candidate_pairs`; min_separation defaults to max(taus).
        descriptors: (K, D) precomputed descriptors (e.g. ResNet-18); else computed with
            ``descriptor_fn`` (default :func:`global_descriptor`).
        call_map: runs the independent calls (SIFT per keyframe, flow per consecutive pair,
            verification per loop candidate), e.g. on worker processes; results are the same.
        per_keyframe, max_candidates: see :func:`candidate_pairs` (max_candidates caps both
            retrievals: the best-scoring candidates are verified).
        retrieval: "vocabulary" (when neither ``descriptors`` nor ``descriptor_fn`` is given): visual vocabularies
        learned (``seed``) from these keyframes' own SIFT features
            (VLAD of ``words`` words and a TF-IDF bag of words), candidates over all keyframe
            pairs by :func:`stages.graph.retrieval.relative_candidates` (``top_k`` per keyframe,
            score >= ``min_ratio`` relative to the temporal neighbours', averaged over
            +-``window`` keyframes of the path, the path gone elsewhere in between by
            ``min_departure``); "global" (default): the whole-image descriptor with
            ``similarity_threshold`` and NMS (:func:`candidate_pairs`; also whenever descriptors
            or a descriptor_fn are given, e.g. ResNet-18).
        loop_nms: :func:`suppress_loops` window over the verified loop edges (<= 1: keep all).
        prewarp_sequential: pre-warp consecutive keyframes by their RANSAC homography as loop
            candidates are ("on"), or not ("off"), or "auto": on unless the clip moves forward
            (:func:`forward_share` >= FORWARD_MIN_SHARE). Under forward motion the homography is
            the wrong model (a zoom about the epipole fitted to a 3-D street): the flows through
            the frame resampled by it carry a parallax bias that bundle adjustment turned into
            scale drift (KITTI 07 at 424x128: keyframe ATE after bundle adjustment 0.66 -> 0.36 m
            from the same pose graph), while consecutive keyframes are close enough for DIS
            unaided; on hand-held clips the pre-warp (mostly the rotation) helps (without it:
            synthetic loop 0.9 -> 3.6 mm, ICL 1.15 -> 1.32 cm, HoloLens 0.061 -> 0.075 m). When
            "auto" turns it off the graph records ``forward_share`` and ``prewarp_sequential``.
        verify, min_inliers, min_epipolar: :func:`verify_pair`'s ``mode`` ("geometric", the
            default, accepts wide-baseline revisits; "paper" keeps the one-keyframe-apart rule)
            and its thresholds.
            Every keyframe's SIFT features are held until the graph is built (~0.3 MB each at
            the working size; the consecutive flows the graph returns are ~1 MB per pair).

    Returns:
        (graph, edge_flows). ``graph`` is JSON-able: {keyframes, similarity_threshold,
        keyframe_threshold_px, sequential_edges: [{i, j, tau, weight}], nonsequential_edges:
        [{i, j, similarity, inlier_ratio, consistent_fraction, mean_flow}], suppressed: [the same, verified but
        suppressed by ``loop_nms``], rejected: [{i, j,
        similarity, inlier_ratio, consistent_fraction, mean_flow, reason}]}, i < j frame
        indices. ``edge_flows[(i, j)]`` is the :func:`keyframe_pair_flow` dict of every tau = 1
        sequential edge and every accepted non-sequential edge.
    """
    cfg = settings_with(AssociationSettings, settings, overrides)
    nms, min_separation, min_inlier_ratio, min_consistent = cfg.nms, cfg.min_separation, cfg.min_inlier_ratio, cfg.min_consistent
    verify, min_inliers, min_epipolar, per_keyframe = cfg.verify, cfg.min_inliers, cfg.min_epipolar, cfg.per_keyframe
    max_candidates, retrieval, words, top_k, min_ratio = cfg.max_candidates, cfg.retrieval, cfg.words, cfg.top_k, cfg.min_ratio
    window, loop_nms, min_departure, prewarp_sequential = cfg.window, cfg.loop_nms, cfg.min_departure, cfg.prewarp_sequential
    if similarity_threshold is None:  # the settings' threshold (None there: the default descriptor's)
        similarity_threshold = DEFAULT_SIMILARITY_THRESHOLD if cfg.threshold is None else cfg.threshold
    kfs = [int(i) for i in kf_indices]
    n = len(kfs)
    if len(kf_images) != n:
        raise ValueError(f"{n} keyframe indices but {len(kf_images)} images")
    if any(b <= a for a, b in zip(kfs, kfs[1:])):
        raise ValueError("kf_indices must be strictly increasing")
    sep = max(taus) if min_separation is None else int(min_separation)

    sequential = sequential_edges(kfs, taus)
    features = list(call_map(_sift_features, kf_images))
    if prewarp_sequential not in ("auto", "on", "off"):
        raise ValueError(f"prewarp_sequential must be 'auto', 'on' or 'off', got {prewarp_sequential!r}")
    share = forward_share(features, K) if prewarp_sequential == "auto" and n > 1 else None
    prewarp = prewarp_sequential == "on" or (share is not None and share < FORWARD_MIN_SHARE)
    edge_flows = _consecutive_flows(kfs, kf_images, features, fb_thresh, call_map, prewarp)

    if retrieval not in ("vocabulary", "global"):
        raise ValueError(f"retrieval must be 'vocabulary' or 'global', got {retrieval!r}")
    use_vocab = retrieval == "vocabulary" and descriptors is None and descriptor_fn is None
    if use_vocab:
        raw = [f[1] for f in features]
        descs = [retrieval_mod.vlad_descriptors(raw, words=words, seed=seed), retrieval_mod.bow_descriptors(raw, seed=seed)]
        cands = retrieval_mod.relative_candidates(descs, min_separation=sep, top_k=top_k, min_ratio=min_ratio,
                                                  window=window, min_departure=min_departure) if n else []
        cands = cands if max_candidates is None else cands[: int(max_candidates)]
    else:
        if descriptors is None:
            fn = descriptor_fn or global_descriptor
            descriptors = (
                np.stack([fn(img) for img in kf_images]) if n else np.zeros((0, 1), np.float32)
            )
        desc = np.asarray(descriptors)
        if desc.shape[0] != n:
            raise ValueError(f"descriptors have {desc.shape[0]} rows for {n} keyframes")
        cands = candidate_pairs(desc, similarity_threshold, nms=nms, min_separation=sep, per_keyframe=per_keyframe,
                                max_candidates=max_candidates) if n else []
    accepted, rejected = _verify_candidates(
        cands, kfs, kf_images, K, keyframe_threshold_px, edge_flows, features, call_map,
        min_inlier_ratio=min_inlier_ratio, min_consistent=min_consistent, fb_thresh=fb_thresh, mode=verify,
        min_inliers=min_inliers, min_epipolar=min_epipolar)
    accepted, suppressed = suppress_loops(accepted, kfs, loop_nms)
    for e in suppressed:
        edge_flows.pop((e["i"], e["j"]), None)
    log.debug(
        "graph: %d keyframes, %d sequential, %d loop edges, %d rejected",
        n, len(sequential), len(accepted), len(rejected),
    )
    graph = {
        "keyframes": kfs,
        "similarity_threshold": float(similarity_threshold),
        "keyframe_threshold_px": float(keyframe_threshold_px),
        "verify": verify,
        "retrieval": "vocabulary" if use_vocab else "global",
        "candidates": len(cands),
        "sequential_edges": sequential,
        "nonsequential_edges": accepted,
        "suppressed": suppressed,
        "rejected": rejected,
    }
    if share is not None and not prewarp:  # (recorded only then: other clips' graphs stay as they were)
        graph.update(forward_share=float(share), prewarp_sequential=False)
    return graph, edge_flows

