"""Keyframe selection by accumulated static-scene image motion (docs/design.md, "Stage: keyframes").

GCVD places a keyframe whenever the camera has moved "enough" since the previous keyframe,
where "enough" is measured in image space: the mean optical-flow magnitude over *static*
pixels, accumulated over adjacent frame pairs, exceeds ``delta * min(H, W)`` pixels
(paper: delta = 0.1, i.e. 9.6 px at 96 px short side ... 28.8 px at 288).

Pure functions, no I/O. Units: pixels at flow resolution.
"""

from __future__ import annotations

import logging
from typing import Any, Iterable, Mapping, TypedDict

import numpy as np

from gcvd_flow.stages.graph.params import KeyframesSettings

log = logging.getLogger(__name__)


_DEFAULTS = KeyframesSettings()  # the keyframes stage's parameters (stages/graph/params.py)


class KeyframeSelection(TypedDict):
    indices: list[int]
    accumulated: list[float]
    threshold_px: float


def pair_motion(fwd: np.ndarray, valid: np.ndarray | None, static_mask: np.ndarray | None) -> float:
    """Mean flow magnitude (px) over pixels that are both flow-consistent and static.

    Args:
        fwd: float (H, W, 2) forward flow of the pair, px.
        valid: bool (H, W) forward-backward consistency mask, or None (= all valid).
        static_mask: uint8/bool (H, W), 1 = static, or None (= all static).

    Returns:
        Mean |flow| in px over the selected pixels. When no pixel survives both masks
        (e.g. the whole frame is dynamic or occluded) we fall back to the mean over all
        pixels: under-estimating motion to 0 would stall keyframe placement until the
        max-gap rule kicks in, whereas the unmasked mean is a reasonable upper guess.
    """
    fwd = np.asarray(fwd, dtype=np.float32)
    if fwd.ndim != 3 or fwd.shape[2] != 2:
        raise ValueError(f"fwd must be (H, W, 2), got {fwd.shape}")
    mag = np.linalg.norm(fwd, axis=2)
    sel = np.isfinite(mag)
    if valid is not None:
        sel &= np.asarray(valid, dtype=bool)
    if static_mask is not None:
        sel &= np.asarray(static_mask) > 0
    if not sel.any():
        finite = np.isfinite(mag)
        return float(mag[finite].mean()) if finite.any() else 0.0
    return float(mag[sel].mean())


def select_keyframes(
    motion: np.ndarray | list[float],
    height: int,
    width: int,
    delta: float = _DEFAULTS.delta,
    max_gap: int = _DEFAULTS.max_gap,
) -> KeyframeSelection:
    """Select keyframes from per-pair image motion.

    Args:
        motion: (N-1,) mean static flow magnitude in px of each adjacent pair (t, t+1),
            e.g. from :func:`pair_motion`.
        height, width: flow resolution in px (the threshold scales with min(H, W)).
        delta: threshold as a fraction of the short image side.
        max_gap: a keyframe is forced so that two consecutive keyframes are never more than
            ``max_gap`` frames apart (keeps every keyframe window's pairs overlapping).

    Returns:
        ``indices``: sorted keyframe frame indices; always contains 0 and N-1.
        ``accumulated``: (N,) motion accumulated since the previous keyframe, evaluated at
        each frame *before* the reset (so at a keyframe it shows the value that triggered it;
        0 at frame 0).
        ``threshold_px``: delta * min(H, W).

    Rule: frame t becomes a keyframe when ``accumulated[t] > threshold_px`` (strictly), or when
    ``t - last_keyframe == max_gap``; the accumulator then restarts at 0. The last frame is
    always a keyframe (even if it is only one frame after the previous one) because the
    trajectory must be anchored at both ends.

    Pure rotation: a rotating camera still produces image flow (about f * angle px), so the
    rule places keyframes by image motion exactly as for translation, even though rotation
    gives no parallax for depth. This is the paper's behaviour and is kept deliberately:
    keyframe spacing is an image-overlap criterion, not a baseline criterion. A camera that
    does not move at all produces ~0 flow and only the first/last/max-gap keyframes.
    """
    m = np.asarray(motion, dtype=np.float64).reshape(-1)
    n = m.size + 1
    if height <= 0 or width <= 0:
        raise ValueError("height and width must be positive")
    if max_gap < 1:
        raise ValueError("max_gap must be >= 1")
    # Non-finite motion (a failed flow) counts as zero: the max-gap rule still bounds the gap.
    m = np.where(np.isfinite(m) & (m > 0), m, 0.0)
    threshold = float(delta) * float(min(height, width))

    indices = [0]
    accumulated = [0.0] * n
    acc = 0.0
    for t in range(1, n):
        acc += float(m[t - 1])
        accumulated[t] = acc
        if acc > threshold or t - indices[-1] >= max_gap or t == n - 1:
            indices.append(t)
            acc = 0.0
    log.debug("selected %d keyframes of %d frames (threshold %.2f px)", len(indices), n, threshold)
    return KeyframeSelection(indices=indices, accumulated=accumulated, threshold_px=threshold)


FLOW_FIELDS = ("fwd", "bwd", "fwd_valid", "bwd_valid")


def keyframe_pair_flows(kf_indices: list[int], edge_flows: Iterable[Mapping[str, Any]]
                        ) -> dict[tuple[int, int], dict[str, np.ndarray]]:
    """The flows of consecutive keyframes keyed by keyframe *position* (m, m + 1), as
    ``stages.optimize.keyframes.optimize_keyframes`` reads them.

    ``edge_flows``: the association's flows, each {i, j (frame indices), fwd, bwd (H, W, 2)
    float32 px, fwd_valid, bwd_valid (H, W) bool}; pairs that are not consecutive keyframes are
    ignored. RuntimeError naming the positions when a consecutive pair has no flow (a bug)."""
    pos = {int(f): k for k, f in enumerate(kf_indices)}
    out: dict[tuple[int, int], dict[str, np.ndarray]] = {}
    for e in edge_flows:
        a, c = pos.get(int(e["i"])), pos.get(int(e["j"]))
        if a is not None and c is not None and c == a + 1:
            out[(a, c)] = {k: np.asarray(e[k]) for k in FLOW_FIELDS}
    missing = [k for k in range(len(kf_indices) - 1) if (k, k + 1) not in out]
    if missing:
        raise RuntimeError(f"association has no flow for consecutive keyframe pairs {missing[:5]}")
    return out
