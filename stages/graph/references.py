"""Which other frames (or adjacent-pair flows) each frame of an N-frame clip reads: the index
arithmetic behind the pipeline's per-item inputs (``gcvd_flow.pipeline``'s ``items`` functions).
Pure functions of (frame index i, clip length n, parameters); frame indices are positions in the
ingested clip (0 .. n-1), flow index k is the adjacent pair (k, k+1).

A map stage's items are cached by exactly the pieces they read, so these rules decide what a
trimmed or extended clip re-uses: each is written so that an existing frame's references do not
change when frames are appended (once the clip is long enough), except where noted.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from gcvd_flow.stages.depth.params import FusionReferencesSettings

FarPair = tuple[int, int, str, float]  # (a, b) with a < b, DIS preset, forward-backward threshold px


def prior_references(i: int, n: int, span: int) -> list[int]:
    """Frame i's prior references: ``span`` and ``span // 2`` (at least 1) frames back, forward
    for the first frames (i < span and in the clip's first half), clamped to the clip, never i."""
    step = -1 if (i >= span or i >= n - 1 - i) else 1
    js = [min(max(i + step * k, 0), n - 1) for k in (span, max(1, span // 2))]
    return [j for j in js if j != i]


def symmetric_prior_references(i: int, n: int, span: int) -> list[int]:
    """Frame i's prior references, the pair-sharing rule: ``span`` frames back and ``span``
    frames forward (the first two of i - span, i + span, i - span // 2, i + span // 2 that lie
    in the clip, never i). Frame i's forward pair (i, i + span) is frame i + span's backward
    one, so each direct flow serves two frames: about n - span pairs for n frames instead of
    about 2 n. A frame within ``span`` of the clip's end reads a frame that appending frames
    changes (the rule above of the extension property does not hold for them)."""
    out: list[int] = []
    for j in (i - span, i + span, i - max(1, span // 2), i + max(1, span // 2)):
        if 0 <= j < n and j != i and j not in out:
            out.append(j)
    # a clip shorter than span // 2 + 1 frames: the clamped references of prior_references, once
    return out[:2] or list(dict.fromkeys(prior_references(i, n, span)))


def offset_references(i: int, n: int, offsets: Iterable[int]) -> list[int]:
    """Frames i + offset (offsets signed, 0 skipped) that lie in the clip, in ``offsets`` order."""
    return [i + off for off in offsets if 0 <= i + off < n and off != 0]


def symmetric_references(i: int, n: int, distances: Iterable[int]) -> list[int]:
    """Frames i - k and i + k for each distance k (in that order) that lie in the clip."""
    return [j for k in distances for j in (i - k, i + k) if 0 <= j < n]


def flow_chain(i: int, n: int, span: int) -> tuple[str, list[int]]:
    """Adjacent flows from frame i toward a reference ``span`` frames away: ("bwd", [i-1, i-2,
    ...]) backward, or ("fwd", [i, i+1, ...]) for the first ``span`` frames (while in the clip's
    first half); at most ``span`` flows, clamped to the clip. Existing frames never read later
    flows once the clip has 2 * span frames, so extending a clip only adds items."""
    if i >= span or i >= n - 1 - i:
        return "bwd", [i - 1 - k for k in range(min(span, i))]
    return "fwd", [i + k for k in range(min(span, n - 1 - i))]


def window(i: int, n: int, radius: int) -> tuple[int, int]:
    """The frames [lo, hi] (inclusive) within ``radius`` of frame i, clamped to the clip."""
    return max(0, i - radius), min(n - 1, i + radius)


def far_pair(i: int, j: int, preset: str, fb_thresh: float) -> FarPair:
    """The unordered pair of frames i, j with the flow settings it is computed with."""
    return (min(i, j), max(i, j), preset, float(fb_thresh))


def far_pairs(n: int, consumers: Sequence[tuple[Callable[[int], list[int]], str, float]]) -> list[FarPair]:
    """The sorted union of the direct-flow pairs several consumers ask for: each consumer is
    (frame i -> its reference frames, DIS preset, forward-backward threshold px); pairs asked for
    twice with the same settings are computed once."""
    pairs: set[FarPair] = set()
    for i in range(n):
        for refs, preset, fb_thresh in consumers:
            pairs.update(far_pair(i, j, preset, fb_thresh) for j in refs(i))
    return sorted(pairs)


# ------------------------------------------------------------------------------ fusion references
# depth_fusion's references chosen from the final poses (``depth_fusion.references=baseline``)
# instead of fixed index offsets: what a reference is good for is its triangulation angle (the
# inverse-depth noise of a flow measurement ~ flow noise / angle) and how much of the frame it
# sees, neither of which an index offset says on a clip whose speed varies.


def view_samples(depth: np.ndarray, K: np.ndarray, grid: int = 16) -> np.ndarray:
    """Points (M, 3) in camera coordinates (depth units) of a ``grid``-column lattice of pixel
    centres (rows in proportion) of depth (H, W) with positive depth; K (3, 3). M <= grid^2."""
    depth = np.asarray(depth, np.float64)
    h, w = depth.shape
    rows = max(2, int(round(grid * h / max(w, 1))))
    us = (np.arange(grid) + 0.5) * w / grid
    vs = (np.arange(rows) + 0.5) * h / rows
    uu, vv = np.meshgrid(us, vs)
    z = depth[vv.astype(int), uu.astype(int)]
    ok = np.isfinite(z) & (z > 0)
    pix = np.stack([uu[ok], vv[ok], np.ones(int(ok.sum()))], 1)
    return (pix @ np.linalg.inv(np.asarray(K, np.float64)).T) * z[ok, None]


def view_geometry(poses: np.ndarray, samples: Sequence[np.ndarray], K: np.ndarray, size: tuple[int, int],
                  i: int, js: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """(overlap, median angle deg), each (len(js),), of frame i against frames js: overlap is
    the fraction of frame i's sample points (``view_samples``) that land in front of camera j
    inside its (w, h) = ``size`` image; the angle is the median, over those points, of the angle
    between the rays from the two camera centres (0 where none lands). poses (N, 4, 4) T_w_c."""
    w, h = size
    pts = np.asarray(samples[i], np.float64)
    out_ov, out_ang = np.zeros(len(js)), np.zeros(len(js))
    if len(pts) == 0 or len(js) == 0:
        return out_ov, out_ang
    Ti = np.asarray(poses[i], np.float64)
    X = pts @ Ti[:3, :3].T + Ti[:3, 3]  # (M, 3) world
    ray_i = X - Ti[:3, 3]
    K = np.asarray(K, np.float64)
    for k, j in enumerate(js):
        Tj = np.asarray(poses[j], np.float64)
        Xj = (X - Tj[:3, 3]) @ Tj[:3, :3]  # world -> camera j (R^T (X - t))
        z = Xj[:, 2]
        front = z > 1e-9
        uv = (Xj[front] @ K.T)[:, :2] / z[front, None]
        inside = np.zeros(len(X), bool)
        inside[front] = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        out_ov[k] = inside.mean()
        if inside.any():
            a, b = ray_i[inside], X[inside] - Tj[:3, 3]
            c = np.sum(a * b, 1) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-300)
            out_ang[k] = float(np.degrees(np.median(np.arccos(np.clip(c, -1.0, 1.0)))))
    return out_ov, out_ang


def _take(i: int, c: tuple[float, int, bool], chosen: list[int], have: set[tuple[int, int]],
          new: list[tuple[int, int]]) -> int:
    """Frame i takes candidate c = (cost, j, flow exists); a new pair is recorded. -> 1 if new."""
    chosen.append(c[1])
    if c[2]:
        return 0
    pair = (min(i, c[1]), max(i, c[1]))
    have.add(pair)
    new.append(pair)
    return 1


def baseline_references(poses: np.ndarray, samples: Sequence[np.ndarray], K: np.ndarray, size: tuple[int, int],
                        rule: FusionReferencesSettings, free: Iterable[tuple[int, int]] = ()
                        ) -> tuple[list[list[int]], list[tuple[int, int]]]:
    """Each frame's fusion references chosen by view geometry, and the new flow pairs they need.

    Frame i's candidates are the frames within ``rule.max_gap`` whose overlap and median
    triangulation angle (``view_geometry``) are usable (``FusionReferencesSettings``: its fields, documented there); each costs
    |log(angle / target)| plus ``new_flow_cost`` unless its pair's flow exists: adjacent pairs
    (the flow stage's), ``free`` pairs (a, b), a < b (e.g. flow_far's for the priors) and pairs
    an earlier frame already chose. The cheapest candidate on each side comes first (both sides
    see the occlusions the other misses), then the cheapest others, up to ``rule.max_refs``;
    at most ``rule.max_new_flows`` of them new pairs. (Topping a frame with fewer than 2 up from views
    that see 40-80 % of it lowered the HoloLens confident share, 44.5 % -> 37 %: not done.) Frames are visited
    in order, then once more to fill each frame's free
    places with usable pairs that later frames added (no new flow), so the choice is
    deterministic and the new pairs number at most max_new * N.

    Returns (refs: per frame the chosen frame indices, sorted; new pairs (a, b), a < b, sorted)."""
    n = len(poses)
    have = {(int(a), int(b)) for a, b in free}
    new: list[tuple[int, int]] = []
    refs: list[list[int]] = []
    usable: list[list[tuple[float, int]]] = []  # per frame: (angle cost, j) seeing min_overlap of it
    target = np.log(rule.target_angle_deg)

    def exists(i: int, j: int) -> bool:
        return abs(i - j) == 1 or (min(i, j), max(i, j)) in have

    # pass 1, frames in order: each frame's choice, new pairs included
    for i in range(n):
        js = [j for j in range(max(0, i - rule.max_gap), min(n, i + rule.max_gap + 1)) if j != i]
        ov, ang = view_geometry(poses, samples, K, size, i, js)
        full = sorted((abs(float(np.log(a)) - target), j) for j, o, a in zip(js, ov, ang)
                      if o >= rule.min_overlap and rule.min_angle_deg <= a <= rule.max_angle_deg)
        usable.append(full)  # (angle cost, j)
        cand = sorted((c + (0.0 if exists(i, j) else rule.new_flow_cost), j, exists(i, j)) for c, j in full)
        chosen: list[int] = []
        n_new = 0
        for side in (-1, 1):  # the cheapest usable candidate on each side first
            best = next((c for c in cand if (c[1] - i) * side > 0 and (c[2] or n_new < rule.max_new_flows)), None)
            if best is not None and len(chosen) < rule.max_refs:
                n_new += _take(i, best, chosen, have, new)
        for c in cand:
            if len(chosen) >= rule.max_refs:
                break
            if c[1] not in chosen and (c[2] or n_new < rule.max_new_flows):
                n_new += _take(i, c, chosen, have, new)
        refs.append(chosen)
    # pass 2: the pairs later frames added are there for earlier frames too; each frame keeps
    # its own choice and fills its free places from them (a side it has none on first)
    for i in range(n):
        chosen = refs[i]
        # (only views within a factor exp(new_flow_cost / 2) ~ 1.4 of the target angle: a near
        # view at a small angle adds disagreement, not accuracy; HoloLens confident share 44 % ->
        # 37 % when every usable existing pair filled the places)
        extra = [j for c, j in usable[i] if j not in chosen and exists(i, j) and c <= rule.new_flow_cost / 2]
        for side in (-1, 1):
            if len(chosen) < rule.max_refs and not any((j - i) * side > 0 for j in chosen):
                pick = next((j for j in extra if (j - i) * side > 0), None)
                if pick is not None:
                    chosen.append(pick)
                    extra.remove(pick)
        chosen.extend(extra[: max(0, rule.max_refs - len(chosen))])
        refs[i] = sorted(chosen)
    return refs, sorted(new)
