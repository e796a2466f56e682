"""CVD2-style flow-guided temporal depth filter (docs/design.md, "Stage: depth_filter").

For the centre frame c of a window, every pixel p is tracked through the chained optical flow
to each neighbour j within ±radius frames. The neighbour's depth sampled at the tracked
position votes for p with weight

    w_j(p) = exp(-2 * max(d_c, d_j) / min(d_c, d_j) - 0.1 * e_j(p))

where e_j(p) (px) is the forward-backward inconsistency of the chained flow between c and j
(round trip c -> j -> c). The centre votes for itself with ratio 1 and e = 0, i.e. exp(-2).
Samples whose tracked position leaves the image or comes within ``border`` px of its edge, or
whose depth is invalid (0), get weight 0.

Note: the neighbour depth is used as is (no reprojection into frame c); with the small
baselines of ±4 adjacent frames the change of a point's depth between frames is small and the
depth-ratio weight down-weights larger disagreements. This matches the reference behaviour.

Pure function, numpy/OpenCV only. Shapes: depths (M, H, W) float32 metres (up to scale, 0 =
invalid); flows (M-1, H, W, 2) float32 px.
"""

from __future__ import annotations

import logging
from typing import Iterator, Sequence

import cv2
import numpy as np

from gcvd_flow.stages.depth.params import DepthFilterSettings
from gcvd_flow.stages.geometry.image import inside_image

_DEFAULTS = DepthFilterSettings()  # the stage's parameters (stages/depth/params.py)

log = logging.getLogger(__name__)

RATIO_WEIGHT: float = 2.0
INCONSISTENCY_WEIGHT: float = 0.1


def _sample(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear sample ``img`` (H, W[, C]) at float pixel positions (x, y) (H', W') with OpenCV
    (positions quantised to 1/32 px, border replicated): not ``warp_sample``, whose exact
    positions would change the filter's results."""
    return cv2.remap(
        np.ascontiguousarray(img, dtype=np.float32),
        np.ascontiguousarray(x, dtype=np.float32),
        np.ascontiguousarray(y, dtype=np.float32),
        interpolation=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )


def chain_flow(
    fwd_flows: np.ndarray | Sequence[np.ndarray],
    bwd_flows: np.ndarray | Sequence[np.ndarray],
    start: int,
    end: int,
    x0: np.ndarray,
    y0: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Track positions (x0, y0) in frame ``start`` to frame ``end`` through adjacent flows.

    Args:
        fwd_flows: (M-1, H, W, 2), fwd_flows[k] maps frame k -> k+1.
        bwd_flows: (M-1, H, W, 2), bwd_flows[k] maps frame k+1 -> k.
        start, end: window-local frame indices.
        x0, y0: float positions in frame ``start``.

    Returns:
        x, y: positions in frame ``end``; inside: bool, False once the track left the image.

    Each step samples the flow *of the frame the track currently is in*: going forward from
    frame k we need fwd_flows[k] (defined on frame k's pixel grid); going backward from frame
    k+1 we need bwd_flows[k] (defined on frame k+1's grid).
    """
    x, y, inside = x0, y0, None
    for _, x, y, inside in _walk(fwd_flows, bwd_flows, start, end, x0, y0):  # noqa: B007 - the walk's last position is the result
        pass
    if inside is None:  # start == end
        h, w = _frame_size(fwd_flows, x0)
        x, y = x0.astype(np.float32).copy(), y0.astype(np.float32).copy()
        inside = inside_image(x, y, w, h, 0.0)
    return x, y, inside


def _frame_size(flows: Sequence[np.ndarray] | np.ndarray, x0: np.ndarray) -> tuple[int, int]:
    """(H, W) of the frames of a window's flows ((M-1, H, W, 2) or M-1 (H, W, 2) arrays); a window
    of one frame has none: then the positions' grid x0 (H, W) says it."""
    if isinstance(flows, np.ndarray):
        return int(flows.shape[1]), int(flows.shape[2])
    h, w = np.shape(flows[0])[:2] if len(flows) else np.shape(x0)[:2]
    return int(h), int(w)


def _walk(fwd_flows: np.ndarray | Sequence[np.ndarray], bwd_flows: np.ndarray | Sequence[np.ndarray], start: int, end: int, x0: np.ndarray,
          y0: np.ndarray) -> Iterator[tuple[int, np.ndarray, np.ndarray, np.ndarray]]:
    """``chain_flow`` one frame at a time: yields (frame, x, y, inside) for every frame after
    ``start`` up to ``end``, so that the tracks to all neighbours on one side cost one pass.
    fwd_flows, bwd_flows: (M-1, H, W, 2) arrays or sequences of M-1 (H, W, 2) arrays."""
    h, w = _frame_size(fwd_flows, x0)
    x = x0.astype(np.float32).copy()
    y = y0.astype(np.float32).copy()
    inside = inside_image(x, y, w, h, 0.0)
    step = 1 if end >= start else -1
    for k in range(start, end, step):
        flow = fwd_flows[k] if step > 0 else bwd_flows[k - 1]
        f = _sample(flow, x, y)
        x = x + f[..., 0]
        y = y + f[..., 1]
        inside = inside & inside_image(x, y, w, h, 0.0)  # (NaN and +-inf are never inside: no isfinite)
        yield k + step, x, y, inside


def _window(depths: np.ndarray | Sequence[np.ndarray], fwd_flows: np.ndarray | Sequence[np.ndarray],
            bwd_flows: np.ndarray | Sequence[np.ndarray]) -> tuple[list[np.ndarray], ...]:
    """filter_depth's window as per-frame float32 arrays, its shapes checked (ValueError). Per frame,
    not stacked: the filter reads one frame's depth or flow at a time, and a stacked copy of the
    window (~8 MB of fresh pages per frame at 256x192) cost a sixth of the stage."""
    if len(depths) == 0:
        raise ValueError("filter_depth needs at least one frame")
    ds = [np.asarray(d, dtype=np.float32) for d in depths]
    fw = [np.asarray(f, dtype=np.float32) for f in fwd_flows]
    bw = [np.asarray(f, dtype=np.float32) for f in bwd_flows]
    m, (h, w) = len(ds), ds[0].shape
    if (len(fw) != m - 1 or len(bw) != m - 1
            or any(f.shape != (h, w, 2) for f in (*fw, *bw)) or any(d.shape != (h, w) for d in ds)):
        shapes = [d.shape for d in ds], [f.shape for f in fw], [f.shape for f in bw]
        raise ValueError(f"depths must be {m} x ({h}, {w}) and flows {m - 1} x ({h}, {w}, 2); got {shapes}")
    return ds, fw, bw


def filter_depth(
    depths: np.ndarray | Sequence[np.ndarray],
    fwd_flows: np.ndarray | Sequence[np.ndarray],
    bwd_flows: np.ndarray | Sequence[np.ndarray],
    center: int,
    radius: int = _DEFAULTS.radius,
    border: int = _DEFAULTS.border,
) -> np.ndarray:
    """Filter the depth of frame ``center`` with its ±radius neighbours.

    Args:
        depths: float (M, H, W) depth of the window's frames (0 = invalid), or M (H, W) arrays.
        fwd_flows: float (M-1, H, W, 2), flow of pair (k, k+1) on frame k's grid, px (or M-1 arrays).
        bwd_flows: float (M-1, H, W, 2), flow of pair (k+1 -> k) on frame k+1's grid, px (or M-1 arrays).
        center: window-local index of the frame to filter.
        radius: neighbours c-radius .. c+radius (clipped to the window) are used.
        border: samples tracked to within this many px of the image edge are ignored.

    Returns:
        float32 (H, W) filtered depth; pixels where the centre depth is invalid stay 0.
    """
    depths, fwd_flows, bwd_flows = _window(depths, fwd_flows, bwd_flows)
    m, (h, w) = len(depths), depths[0].shape
    if not 0 <= center < m:
        raise ValueError(f"center {center} outside window of {m} frames")

    d_c = depths[center]
    valid_c = np.isfinite(d_c) & (d_c > 0)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)

    # The centre's own vote: ratio 1, no inconsistency.
    w_self = np.exp(-RATIO_WEIGHT * 1.0)
    num = np.where(valid_c, w_self * d_c, 0.0).astype(np.float64)
    den = np.where(valid_c, w_self, 0.0).astype(np.float64)

    lo, hi = max(0, center - radius), min(m - 1, center + radius)
    # Track c -> j (j > c: fwd_flows[c..j-1]; j < c: bwd_flows[j..c-1]), one walk per side.
    tracks = {j: (x, y, ok) for end in (lo, hi) for j, x, y, ok in _walk(fwd_flows, bwd_flows, center, end, xx, yy)}
    for j in sorted(tracks):  # lo..hi without the centre, ascending (the order of the sums)
        xj, yj, ok = tracks[j]
        # Round trip j -> c, starting from the tracked positions in frame j. The return path
        # must use the flows of the *opposite* direction, each sampled on the grid of the frame
        # the track is in: for j > c these are bwd_flows[j-1..c] (k+1 -> k), for j < c they
        # are fwd_flows[j..c-1] (k -> k+1). The authors' code gets the backward (j < c) term
        # wrong (docs/design.md, "Known traps of the authors' code"): sampling the backward flow
        # again on the way back measures about twice the motion instead of the round-trip error, so
        # every past neighbour of a moving camera looks inconsistent and the filter silently
        # becomes one-sided (tests/test_depth_filter.py checks past/future symmetry).
        # chain_flow picks the flow by the direction of travel, right in both cases.
        xr, yr, ok_r = chain_flow(fwd_flows, bwd_flows, j, center, xj, yj)
        incons = np.hypot(xr - xx, yr - yy)

        d_j = _sample(depths[j], xj, yj)
        # Bilinear sampling across a 0 (invalid) depth would fabricate a small depth; require
        # all contributing texels valid by sampling the validity mask too.
        v_j = _sample((depths[j] > 0).astype(np.float32), xj, yj) > 0.999
        use = (
            valid_c
            & ok
            & ok_r
            & v_j
            & inside_image(xj, yj, w, h, float(border))
            & np.isfinite(incons)
            & (d_j > 0)
        )
        d_j_safe = np.where(use, d_j, 1.0)
        d_c_safe = np.where(use, d_c, 1.0)
        ratio = np.maximum(d_c_safe, d_j_safe) / np.minimum(d_c_safe, d_j_safe)
        wj = np.where(use, np.exp(-RATIO_WEIGHT * ratio - INCONSISTENCY_WEIGHT * incons), 0.0)
        num += wj * d_j_safe
        den += wj

    out = np.where(den > 0, num / np.maximum(den, 1e-300), 0.0)
    return out.astype(np.float32)


def fill_uncertain(gray: np.ndarray, depth: np.ndarray, confidence: np.ndarray, source: float = 0.7,
                   full: float = 0.4, eps: float = 1e-3) -> np.ndarray:
    """Depth (H, W) float32 where confidence is low pulled towards an edge-aware fill from the
    confident pixels: log-depth of pixels with confidence >= ``source`` is densified by
    confidence-weighted guided filtering over the grey image (``stages.frontend.priors.densify``,
    coarse radii bridge large holes), clipped to the confident range, and each pixel keeps
    ``min(1, confidence / full)`` of its own log-depth (pixels at least ``full`` confident keep
    theirs). Textureless surfaces (a white chair, a wall) are where triangulation fails and the
    network's depth is weakest; their depth then follows their confidently measured
    surroundings along the image's edges (ICL: AbsRel 0.053 -> 0.049). Where low confidence
    means a small triangulation angle rather than bad depth, it hurts (synthetic loop: 0.042 ->
    0.129), hence off by default. Zero (invalid) depth stays zero.

    gray (H, W) in [0, 1]; depth (H, W) metres up to scale, 0 = invalid; confidence (H, W) in
    [0, 1]. ``full`` <= 0 returns the depth unchanged."""
    from gcvd_flow.stages.frontend.priors import densify

    depth = np.asarray(depth, np.float32)
    valid = depth > 0
    w = np.where(valid & (confidence >= source), confidence, 0.0).astype(np.float64)
    if full <= 0 or (w > 0).sum() < 16:
        return depth
    log_d = np.log(np.where(valid, depth, 1.0).astype(np.float64))
    dense, _ = densify(np.asarray(gray, np.float64), log_d, w, eps=eps)
    dense = np.clip(dense, log_d[w > 0].min(), log_d[w > 0].max())
    a = np.clip(np.asarray(confidence, np.float64) / full, 0.0, 1.0)
    return np.where(valid, np.exp(a * log_d + (1 - a) * dense), 0.0).astype(np.float32)
