"""Ground-truth revisits: which keyframe pairs a loop closure should find, and how well the
association's retrieval and verification did on them (benchmarks/bench_retrieval.py, tests).

A *revisit pair* is a pair of keyframes far apart in time (more than ``min_frames`` frames and
more than ``min_separation`` keyframes, so the sequential edges do not already link them) whose
views share the scene: at least ``min_overlap`` of each one's ground-truth depth points (a grid
every ``stride`` px) project into the other's image, in front of it and not hidden behind its
ground-truth surface (``overlap``). A second, depth-free definition (``pose_revisit_pairs``:
camera centres within ``max_dist`` m and optical axes within ``max_angle_deg``) is what the
previous round measured (HoloLens walk-through: 28 pairs at 15 frames / 0.5 m / 30 deg).

Pure numpy: no file I/O (the caller loads the ground truth). Poses are T_w_c (camera-to-world),
depth is z-depth in metres (0 or non-finite = invalid), K is the (3, 3) intrinsics of the depth.
"""

from __future__ import annotations

from typing import Any, Iterable, Sequence

import numpy as np

# a point counts as visible in the other view when it is at most this much (relative) behind the
# other view's own ground-truth surface there (sensor depth noise / resampling: a few percent)
OCCLUSION_TOL = 0.1


def view_overlap(depth_a: np.ndarray, T_w_a: np.ndarray, T_w_b: np.ndarray, K: np.ndarray,
                 depth_b: np.ndarray | None = None, stride: int = 8) -> float:
    """Share of view a's valid depth points (every ``stride`` px) that view b sees.

    Args:
        depth_a: (H, W) z-depth of view a [m]; 0 / non-finite = invalid.
        T_w_a, T_w_b: (4, 4) camera-to-world poses.
        K: (3, 3) intrinsics of both views (same camera, same size).
        depth_b: (H, W) z-depth of view b, for occlusion (None: no occlusion test).
    Returns:
        fraction in [0, 1] (0 when a has no valid point).
    """
    d = np.asarray(depth_a, np.float64)
    h, w = d.shape
    ys, xs = np.mgrid[0:h:stride, 0:w:stride]
    z = d[ys, xs]
    ok = np.isfinite(z) & (z > 0)
    if not ok.any():
        return 0.0
    x, y, z = xs[ok].astype(np.float64), ys[ok].astype(np.float64), z[ok]
    Kinv = np.linalg.inv(K)
    p_a = (Kinv @ np.stack([x, y, np.ones_like(x)])) * z  # (3, M) in a's camera
    T_b_a = np.linalg.inv(T_w_b) @ T_w_a
    p_b = T_b_a[:3, :3] @ p_a + T_b_a[:3, 3:4]
    zb = p_b[2]
    front = zb > 1e-6
    uv = (K @ p_b)[:2] / np.where(front, zb, 1.0)
    u, v = np.round(uv[0]).astype(np.int64), np.round(uv[1]).astype(np.int64)
    seen = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    if depth_b is not None and seen.any():
        db = np.asarray(depth_b, np.float64)[v[seen], u[seen]]
        known = np.isfinite(db) & (db > 0)
        hidden = known & (zb[seen] > db * (1.0 + OCCLUSION_TOL))
        seen[np.nonzero(seen)[0][hidden]] = False
    return float(seen.mean())


def revisit_pairs(kf_indices: Sequence[int], poses: np.ndarray, depths: Sequence[np.ndarray], K: np.ndarray,
                  min_frames: int = 15, min_separation: int = 8, min_overlap: float = 0.3,
                  stride: int = 8) -> dict[tuple[int, int], float]:
    """{(frame i, frame j): overlap} of the keyframe pairs (i < j) that revisit a place.

    Args:
        kf_indices: increasing frame indices of the keyframes.
        poses: (N, 4, 4) ground-truth T_w_c of every frame; depths: (N,) sequence of (H, W)
            ground-truth z-depth [m] (indexed by frame); K: (3, 3) of the depth maps.
        min_frames, min_separation: a pair must be more than this many frames and keyframes apart.
        min_overlap: both views must see at least this share of the other's depth points.
    Returns:
        overlap = min of the two directions' :func:`view_overlap`, for every qualifying pair.
    """
    kfs = [int(i) for i in kf_indices]
    out: dict[tuple[int, int], float] = {}
    for a in range(len(kfs)):
        for b in range(a + min_separation + 1, len(kfs)):
            i, j = kfs[a], kfs[b]
            if j - i <= min_frames:
                continue
            o = view_overlap(depths[i], poses[i], poses[j], K, depths[j], stride)
            if o < min_overlap:
                continue
            o = min(o, view_overlap(depths[j], poses[j], poses[i], K, depths[i], stride))
            if o >= min_overlap:
                out[(i, j)] = o
    return out


def pose_revisit_pairs(kf_indices: Sequence[int], poses: np.ndarray, min_frames: int = 15, min_separation: int = 8,
                       max_dist: float = 0.5, max_angle_deg: float = 30.0) -> set[tuple[int, int]]:
    """Keyframe pairs (frame i < frame j) more than ``min_frames`` frames and ``min_separation``
    keyframes apart whose ground-truth camera centres are within ``max_dist`` [m] and optical
    axes within ``max_angle_deg``."""
    kfs = [int(i) for i in kf_indices]
    P = np.asarray(poses, np.float64)
    out = set()
    cos_max = np.cos(np.deg2rad(max_angle_deg))
    for a in range(len(kfs)):
        for b in range(a + min_separation + 1, len(kfs)):
            i, j = kfs[a], kfs[b]
            if j - i <= min_frames:
                continue
            if np.linalg.norm(P[i, :3, 3] - P[j, :3, 3]) <= max_dist and P[i, :3, 2] @ P[j, :3, 2] >= cos_max:
                out.add((i, j))
    return out


def retrieval_report(revisits: Iterable[tuple[int, int]], candidates: Iterable[tuple[int, int]],
                     verified: Iterable[tuple[int, int]], true_pairs: Iterable[tuple[int, int]] | None = None,
                     ) -> dict[str, Any]:
    """Recall of the candidates and precision of the verified loop edges.

    Args:
        revisits: ground-truth revisit pairs (frame i < frame j).
        candidates: pairs the retrieval proposed (verified or rejected).
        verified: pairs the verification accepted.
        true_pairs: pairs that count as a correct loop for precision (default ``revisits``; pass a
            looser set, e.g. a lower overlap, so that a sound edge between views that share less
            than the recall bar is not called false).
    Returns:
        {revisits, candidates, verified, found (revisits among the candidates), recall,
        verified_true, precision (verified_true / verified; None without verified edges),
        verified_revisits (revisits among the verified), false_verified [[i, j]]}.
    """
    rev = {(int(i), int(j)) for i, j in revisits}
    cand = {(int(i), int(j)) for i, j in candidates}
    ver = {(int(i), int(j)) for i, j in verified}
    true = rev if true_pairs is None else {(int(i), int(j)) for i, j in true_pairs} | rev
    good = ver & true
    return {
        "revisits": len(rev), "candidates": len(cand), "verified": len(ver),
        "found": len(rev & cand), "recall": len(rev & cand) / len(rev) if rev else None,
        "verified_revisits": len(rev & ver), "verified_true": len(good),
        "precision": len(good) / len(ver) if ver else None,
        "false_verified": sorted([list(p) for p in ver - true]),
    }
