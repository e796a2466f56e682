"""Optical flow between adjacent frames, forward-backward consistency, flow chaining.

Default backend: OpenCV DIS (weight-free, CPU, deterministic). Optional backend: RAFT
(`stages/backends/raft_net.py`) when the user has weights.

Shapes/units: images uint8 (H, W, 3) RGB; flows float32 (H, W, 2) as (dx, dy) in pixels, the
forward flow of pair (a, b) maps pixel p of a to p + flow[p] in b; masks bool (H, W).
"""

from __future__ import annotations

import functools
import logging
from typing import Any, Sequence

import cv2
import numpy as np

from gcvd_flow.stages.geometry.image import apply_homography, inside_image, to_gray

log = logging.getLogger(__name__)

__all__ = [
    "compute_pair_flow",
    "dis_flow",
    "fb_consistency",
    "warp_sample",
    "chain_flows",
    "pixel_grid",
    "DIS_PRESETS",
]

DIS_PRESETS: dict[str, int] = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
    # "medium" whose finest pyramid level is the full image (medium stops at half resolution):
    # ~3.5x the time, 2.4x lower median end-point error on 8-frame pairs of the synthetic loop
    # (0.11 -> 0.046 px), which is what triangulating a depth prior needs
    "fine": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
    # "fine" with 12 instead of medium's 25 gradient-descent iterations per patch: 0.61x the time,
    # 0.018 px median (0.37 px p90) from "fine" on 8-frame ICL pairs at 256x192
    "fine-fast": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
    # "fine", and where the pair's flows are mostly inconsistent (wide baselines: beyond what DIS's
    # coarsest level finds from a zero start) DIS again from the homography of the pair's SIFT
    # matches, keeping the more consistent of the two (HoloLens pairs 2 frames apart: median
    # end-point error 3.85 -> 1.49 px against the sensor's flow; 3 apart 42.7 -> 2.2 px)
    "fine-wide": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}
FINEST_SCALE = {"fine": 0, "fine-fast": 0, "fine-wide": 0}
GRADIENT_DESCENT_ITERATIONS = {"fine-fast": 12}
# fine-wide: a pair whose forward and backward flows keep less than this share of consistent pixels
# is tried again from a homography; the homography needs this many RANSAC (3 px) inliers
WIDE_BELOW = 0.45
WIDE_MIN_INLIERS = 20
WIDE_FEATURES = 1000


def dis_flow(img_a: np.ndarray, img_b: np.ndarray, preset: str = "medium", init: np.ndarray | None = None
             ) -> np.ndarray:
    """DIS flow a -> b, float32 (H, W, 2) px; ``init`` (H, W, 2) px: DIS starts from it (at its
    coarsest level) instead of from zero.

    A fresh DIS object per call: the object keeps no state we rely on, and a new one guarantees
    that results do not depend on call history (byte-identical across calls).
    """
    if preset not in DIS_PRESETS:
        raise ValueError(f"unknown DIS preset {preset!r}; choose one of {sorted(DIS_PRESETS)}")
    dis = cv2.DISOpticalFlow_create(DIS_PRESETS[preset])  # type: ignore[attr-defined]  # in cv2, not in its stubs
    if preset in FINEST_SCALE:
        dis.setFinestScale(FINEST_SCALE[preset])
    if preset in GRADIENT_DESCENT_ITERATIONS:
        dis.setGradientDescentIterations(GRADIENT_DESCENT_ITERATIONS[preset])
    start = None if init is None else np.array(init, dtype=np.float32, order="C")  # DIS writes into it
    flow = dis.calc(to_gray(img_a), to_gray(img_b), start)
    return np.ascontiguousarray(flow, dtype=np.float32)


def homography_flows(img_a: np.ndarray, img_b: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The flows a -> b and b -> a (H, W, 2) float32 px of one homography fitted (RANSAC, 3 px) to
    the SIFT ratio-test matches of the two images, or None when fewer than WIDE_MIN_INLIERS
    support it. The fit runs in a canonical direction (by the images' content), so the pair
    asked for the other way round gets the same two flows swapped."""
    import hashlib

    from gcvd_flow.stages.sfm.features import ratio_matches, sift_features

    swap = hashlib.blake2b(img_a.tobytes(), digest_size=8).digest() > hashlib.blake2b(img_b.tobytes(),
                                                                                       digest_size=8).digest()
    first, second = (img_b, img_a) if swap else (img_a, img_b)
    pa, pb = ratio_matches(sift_features(first, WIDE_FEATURES), sift_features(second, WIDE_FEATURES), 0.8)
    if len(pa) < WIDE_MIN_INLIERS:
        return None
    H, inl = cv2.findHomography(pa, pb, cv2.RANSAC, 3.0)
    if H is None or inl is None or int(inl.sum()) < WIDE_MIN_INLIERS or abs(np.linalg.det(H)) < 1e-8:
        return None
    h, w = img_a.shape[:2]
    grid = pixel_grid(h, w)

    def flow_of(M: np.ndarray) -> np.ndarray:
        return np.stack(apply_homography(M, grid[..., 0], grid[..., 1]), -1) - grid

    fwd, bwd = flow_of(H), flow_of(np.linalg.inv(H))
    if not (np.all(np.isfinite(fwd)) and np.all(np.isfinite(bwd))):
        return None
    fwd, bwd = np.clip(fwd, -4 * max(h, w), 4 * max(h, w)), np.clip(bwd, -4 * max(h, w), 4 * max(h, w))
    return (bwd, fwd) if swap else (fwd, bwd)


def warp_sample(field: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """Bilinearly sample `field` (H, W) or (H, W, C) at float pixel coords (..., 2) = (u, v).

    Coordinates outside the image are clamped to the border (callers decide validity with
    their own in-bounds test). Pure numpy so that it is exact (cv2.remap quantises the
    sub-pixel position to 1/32 px) and deterministic.
    """
    f = np.asarray(field)
    squeeze = f.ndim == 2
    if squeeze:
        f = f[..., None]
    h, w = f.shape[:2]
    # channels first (from the flattened field), so that every product runs over contiguous
    # pixels rather than a trailing axis of 1-3
    out = _sample_cf(np.ascontiguousarray(f.reshape(h * w, -1).T, dtype=np.float64), h, w, coords)
    dtype = np.float32 if f.dtype != np.float64 else np.float64
    if squeeze:
        return out[0].reshape(coords.shape[:-1]).astype(dtype)
    return np.ascontiguousarray(np.moveaxis(out.reshape(-1, *coords.shape[:-1]), 0, -1), dtype=dtype)


def _sample_cf(ff: np.ndarray, h: int, w: int, coords: np.ndarray) -> np.ndarray:
    """warp_sample's arithmetic on a channels-first field ff float64 (C, h * w): the samples
    (C, N) at coords (..., 2) flattened to N points."""
    return _sample_xy(ff, h, w, coords[..., 0], coords[..., 1])


def _clamped(c: np.ndarray, hi: float) -> np.ndarray:
    """c as float64, flat, clamped to [0, hi] like np.clip but NaN -> 0 (fmax ignores NaN): a
    non-finite coordinate samples a border pixel instead of indexing with a garbage integer."""
    out = np.fmax(c, 0.0, dtype=np.float64).ravel()  # a fresh array (float64 before the max: exact)
    return np.minimum(out, hi, out=out)


def _floor_index(c: np.ndarray, n: int) -> np.ndarray:
    """min(floor(c), n - 2) as int64 of clamped coordinates c >= 0 (truncation is floor), 0 when n == 1."""
    if n <= 1:
        return np.zeros_like(c, np.int64)
    out = c.astype(np.int64)
    return np.minimum(out, n - 2, out=out)


def _sample_xy(ff: np.ndarray, h: int, w: int, cx: np.ndarray, cy: np.ndarray) -> np.ndarray:
    """_sample_cf at the points (cx, cy) (any shape each, flattened to N): the same arithmetic, for
    callers that keep their coordinates channels-first (chain_flows)."""
    x = _clamped(cx, w - 1.0)
    y = _clamped(cy, h - 1.0)
    x0 = _floor_index(x, w)
    y0 = _floor_index(y, h)
    ax = x - x0
    ay = y - y0
    bx, by = 1 - ax, 1 - ay
    # the four neighbours of x0 + w y0 (x1 = x0 + 1, y1 = y0 + 1 unless the image is one pixel
    # wide / high): gathered (take: ~4x faster than a fancy index) as shifted views of ff, one
    # channel at a time (a take along axis 1 of the strided (C, N - shift) view copied it first:
    # 25x slower for 3 channels); the arithmetic is the same, term by term and in the same order
    # (in place), as f[y0, x0] * (1 - ax) * (1 - ay) + f[y0, x1] * ax * (1 - ay) + ...
    i00 = y0 * w
    i00 += x0
    dx, dy = (1 if w > 1 else 0), (w if h > 1 else 0)
    out: np.ndarray | None = None
    ff = np.ascontiguousarray(ff)
    for shift, wx, wy in ((0, bx, by), (dx, ax, by), (dy, bx, ay), (dx + dy, ax, ay)):
        term = np.empty((ff.shape[0], i00.size), ff.dtype)
        for c in range(ff.shape[0]):  # indices are in range: 'clip' only skips the checked copy
            ff[c, shift:].take(i00, out=term[c], mode="clip")
        term *= wx
        term *= wy
        if out is None:
            out = term
        else:
            out += term
    assert out is not None  # four terms
    return out


def _inside(tgt: np.ndarray, h: int, w: int) -> np.ndarray:
    """Finite target coordinates (H, W, 2) inside an h x w image: bool (H, W)."""
    return inside_image(tgt[..., 0], tgt[..., 1], w, h)


@functools.lru_cache(maxsize=8)
def pixel_grid(h: int, w: int) -> np.ndarray:
    """_grid(h, w), computed once per size and read-only (callers add to it, never write it)."""
    g = _grid(h, w)
    g.setflags(write=False)
    return g


@functools.lru_cache(maxsize=8)
def pixel_grid_cf(h: int, w: int) -> np.ndarray:
    """pixel_grid channels first: float64 (2, h * w) rows u and v, read-only."""
    g = np.ascontiguousarray(pixel_grid(h, w).reshape(h * w, 2).T)
    g.setflags(write=False)
    return g


def _grid(h: int, w: int) -> np.ndarray:
    """Pixel coordinates (u, v) of an h x w image, float64 (H, W, 2)."""
    v, u = np.mgrid[0:h, 0:w]
    return np.stack([u, v], -1).astype(np.float64)


def _targets(flow: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Target coordinates p + flow(p) (H, W, 2) float64 and their in-image mask (H, W)."""
    h, w = flow.shape[:2]
    tgt = pixel_grid(h, w) + flow.astype(np.float64)
    return tgt, _inside(tgt, h, w)


def fb_consistency(fwd: np.ndarray, bwd: np.ndarray, thresh: float = 1.0) -> np.ndarray:
    """Forward-backward consistency of `fwd` (a -> b) given `bwd` (b -> a): bool (H, W).

    Valid iff p + fwd(p) lies inside image b and |fwd(p) + bwd(p + fwd(p))| < thresh px
    (bwd sampled bilinearly). Occluded pixels and pixels leaving the view fail this test.
    """
    tgt, inside = _targets(fwd)
    back = warp_sample(bwd, tgt)
    err = np.linalg.norm(fwd.astype(np.float64) + back, axis=-1)
    return inside & (err < thresh)


def chain_flows(
    flows: Sequence[tuple[np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray]:
    """Compose successive flows i->i+1, i+1->i+2, ... into the flow i->i+k.

    Each element is (flow (H, W, 2), valid bool (H, W)) defined on its own source frame.
    The composite is f(p) = f0(p) + f1(p + f0(p)) + ...; a pixel stays valid only if every
    link is valid where the chain passes (validity sampled bilinearly, all four neighbours
    must be valid: a conservative choice that keeps occlusion edges out) and stays in view.
    Returns (flow float32 (H, W, 2), valid bool (H, W)).
    """
    if len(flows) == 0:
        raise ValueError("chain_flows needs at least one flow")
    f0, v0 = flows[0]
    h, w = f0.shape[:2]
    # channels first (u row, v row over the h * w pixels): every pass below runs over contiguous
    # memory; the values and the order of the operations are those of the (h, w, 2) layout
    base = pixel_grid_cf(h, w)
    total = np.ascontiguousarray(f0.reshape(h * w, 2).T, dtype=np.float64)
    valid = np.asarray(v0, bool).reshape(-1).copy()
    pos = base + total
    valid &= inside_image(pos[0], pos[1], w, h)
    both = np.empty((3, h * w), np.float64)
    for f, vm in flows[1:]:
        # the link's flow and validity sampled together (one set of bilinear weights)
        both[:2] = f.reshape(h * w, 2).T
        both[2] = np.asarray(vm).reshape(-1)
        sampled = _sample_xy(both, h, w, pos[0], pos[1])
        total += sampled[:2]
        valid &= sampled[2] > 0.999
        np.add(base, total, out=pos)
        valid &= inside_image(pos[0], pos[1], w, h)
    return np.ascontiguousarray(total.T, dtype=np.float32).reshape(h, w, 2), valid.reshape(h, w)


def compute_pair_flow(
    img_a: np.ndarray,
    img_b: np.ndarray,
    backend: str = "dis",
    preset: str = "medium",
    fb_thresh: float = 1.0,
    model: Any = None,
) -> dict[str, np.ndarray]:
    """Forward and backward flow of an adjacent pair plus their consistency masks.

    img_a, img_b: uint8 (H, W, 3) RGB. backend: "dis" (preset in ultrafast/fast/medium) or
    "raft" (`model` = module from stages.models.raft.load_raft). fb_thresh in px (paper: 1).
    Returns dict(fwd float32 (H, W, 2), bwd float32 (H, W, 2), fwd_valid bool, bwd_valid bool).
    """
    if img_a.shape != img_b.shape:
        raise ValueError(f"image shapes differ: {img_a.shape} vs {img_b.shape}")
    if backend == "dis" and preset == "fine-wide":
        return _wide_pair_flow(img_a, img_b, fb_thresh)
    if backend == "dis":
        fwd = dis_flow(img_a, img_b, preset)
        bwd = dis_flow(img_b, img_a, preset)
    elif backend == "raft":
        if model is None:
            raise ValueError("backend='raft' needs model=load_raft(path)")
        from gcvd_flow.stages.models.raft import raft_flow

        fwd = raft_flow(model, img_a, img_b)
        bwd = raft_flow(model, img_b, img_a)
    else:
        raise ValueError(f"unknown flow backend {backend!r}; use 'dis' or 'raft'")
    return {
        "fwd": fwd,
        "bwd": bwd,
        "fwd_valid": fb_consistency(fwd, bwd, fb_thresh),
        "bwd_valid": fb_consistency(bwd, fwd, fb_thresh),
    }


def _wide_pair_flow(img_a: np.ndarray, img_b: np.ndarray, fb_thresh: float) -> dict[str, np.ndarray]:
    """compute_pair_flow with the "fine-wide" preset: "fine", and when less than WIDE_BELOW of the
    pixels pass the forward-backward test (both directions together), DIS again from the
    homography of the pair's SIFT matches; the more consistent pair of flows is kept."""
    fwd, bwd = dis_flow(img_a, img_b, "fine"), dis_flow(img_b, img_a, "fine")
    out = {"fwd": fwd, "bwd": bwd, "fwd_valid": fb_consistency(fwd, bwd, fb_thresh),
           "bwd_valid": fb_consistency(bwd, fwd, fb_thresh)}
    share = (out["fwd_valid"].mean() + out["bwd_valid"].mean()) / 2
    if share >= WIDE_BELOW:
        return out
    start = homography_flows(img_a, img_b)
    if start is None:
        return out
    fwd2, bwd2 = dis_flow(img_a, img_b, "fine", start[0]), dis_flow(img_b, img_a, "fine", start[1])
    alt = {"fwd": fwd2, "bwd": bwd2, "fwd_valid": fb_consistency(fwd2, bwd2, fb_thresh),
           "bwd_valid": fb_consistency(bwd2, fwd2, fb_thresh)}
    return alt if (alt["fwd_valid"].mean() + alt["bwd_valid"].mean()) / 2 > share else out
