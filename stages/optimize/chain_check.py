"""Three-view check and repair of the essential-matrix chain's pairs (opt-in:
``optimize_keyframes.chain_check_deg``).

A consecutive keyframe pair whose two-view rotation is wrong (flow dominated by a large rotation:
the rotation / translation ambiguity) gives its translation direction tens of degrees off and the
chain's scale a jump at it (the HoloLens clip's pairs 33-35: rotation 2.7-6.6 degrees off,
translation 34-83 degrees off, the chain's scale x4.6; docs/log/2026-11-28-scale.md). Each triplet
(k, k+1, k+2) is checked: the rotation of ``two_view_pose`` on the flow chained k -> k+1 -> k+2
against the two pairs' rotations composed. A pair in a triplet that disagrees by more than the
threshold gets three rotation candidates that do not share an estimate: its own, and the two
bridges through its neighbours (R_{k+1,k} = R_{k+1,k-1} R_{k,k-1}^T and R_{k+2,k+1}^T R_{k+2,k});
the candidate nearest the other two (the rotation medoid) is kept. When that is not its own and
more than the threshold from it, the pair's translation direction is re-estimated from its own flow with that rotation held fixed
(``translation_given_rotation``). Pure functions, no file I/O.

Poses as in ``stages.optimize.init``: T_b_a (4, 4) float64 maps camera-a into camera-b
coordinates; pair k is (k, k+1) with flow dict ``flows[k]``.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from gcvd_flow.stages.frontend.flow import chain_flows
from gcvd_flow.stages.optimize.init import chain_pair_poses, pair_masks, rays, triangulate, two_view_pose

__all__ = ["rotation_deg", "triplet_poses", "triplet_gaps", "rotation_medoid", "translation_given_rotation",
           "repair_pairs", "checked_pair_poses"]

PairPose = tuple[np.ndarray, "tuple[np.ndarray, np.ndarray] | None"]


def rotation_deg(R: np.ndarray) -> float:
    """Angle (degrees) of a rotation matrix (3, 3)."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def triplet_poses(flows: Sequence[Mapping[str, np.ndarray]], static_masks: np.ndarray, K: np.ndarray) -> list[np.ndarray]:
    """T_{k+2}_k (4, 4) of every triplet k = 0 .. len(flows) - 2: ``two_view_pose`` on the forward
    flow chained k -> k+1 -> k+2 (``chain_flows``), on frame k's usable pixels."""
    out = []
    for k in range(len(flows) - 1):
        fv0 = pair_masks(flows[k], static_masks, k)[0]
        fv1 = pair_masks(flows[k + 1], static_masks, k + 1)[0]
        f02, v02 = chain_flows([(np.asarray(flows[k]["fwd"]), fv0), (np.asarray(flows[k + 1]["fwd"]), fv1)])
        out.append(two_view_pose(f02, v02, K)[0])
    return out


def triplet_gaps(pairs: Sequence[PairPose], triplets: Sequence[np.ndarray]) -> np.ndarray:
    """Rotation disagreement (degrees) (len(triplets),) of each triplet k: the chained-flow
    rotation R_{k+2,k} against R_{k+2,k+1} R_{k+1,k} of the pairs."""
    return np.array([rotation_deg(T13[:3, :3].T @ pairs[k + 1][0][:3, :3] @ pairs[k][0][:3, :3])
                     for k, T13 in enumerate(triplets)])


def rotation_medoid(Rs: Sequence[np.ndarray]) -> int:
    """Index of the rotation (3, 3) with the smallest summed angle to the others (the first on a tie)."""
    cost = [sum(rotation_deg(A.T @ B) for B in Rs) for A in Rs]
    return int(np.argmin(cost))


def translation_given_rotation(
    R: np.ndarray, fwd: np.ndarray, valid: np.ndarray, K: np.ndarray, t0: np.ndarray | None = None,
    n_pts: int = 3000, iters: int = 15, scale_px: float = 1.0,
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
    """Pose T_b_a (4, 4) with rotation R and the unit translation that best explains the flow a ->
    b (H, W, 2) on ``valid`` (H, W) pixels (up to n_pts of them): t . ((R x_a) x x_b) = 0, solved by
    iteratively reweighted least squares on the point-to-epipolar-line distance (Cauchy, ``scale_px``)
    from t0 (else the unweighted solution); the sign with more points in front of both cameras.
    Also the correspondences (uv_a, uv_b) within 2 scale_px of their line and triangulable, or None
    (then the translation is zero: fewer than 50 pixels)."""
    ys, xs = np.nonzero(valid)
    T = np.eye(4)
    T[:3, :3] = R
    if len(xs) < 50:
        return T, None
    step = max(1, len(xs) // n_pts)
    xs, ys = xs[::step], ys[::step]
    ua = np.stack([xs, ys], 1).astype(np.float64)
    ub = ua + np.asarray(fwd)[ys, xs].astype(np.float64)
    ra, xb = rays(ua, K) @ R.T, rays(ub, K)
    a = np.cross(ra, xb)
    t = (np.linalg.svd(a / np.linalg.norm(a, axis=1, keepdims=True).clip(1e-12), full_matrices=False)[2][-1]
         if t0 is None or np.linalg.norm(t0) < 1e-9 else np.asarray(t0, np.float64) / np.linalg.norm(t0))
    f = float(K[0, 0])
    r = np.zeros(len(a))
    for _ in range(iters):
        den = np.linalg.norm(np.cross(t, ra)[:, :2], axis=1).clip(1e-12)  # epipolar lines in b
        r = np.abs(a @ t) / den * f
        w = 1.0 / den / (1.0 + (r / scale_px) ** 2)
        t = np.linalg.svd(a * w[:, None], full_matrices=False)[2][-1]
    den = np.linalg.norm(np.cross(t, ra)[:, :2], axis=1).clip(1e-12)
    r = np.abs(a @ t) / den * f
    T[:3, 3] = t
    ok = triangulate(ua, ub, K, T)[2]
    T_neg = T.copy()
    T_neg[:3, 3] = -t
    ok_neg = triangulate(ua, ub, K, T_neg)[2]
    if ok_neg.sum() > ok.sum():
        T, ok = T_neg, ok_neg
    inl = ok & (r < 2 * scale_px)
    return T, (ua[inl], ub[inl])


def repair_pairs(
    pairs: Sequence[PairPose], triplets: Sequence[np.ndarray], thresh_deg: float,
    flows: Sequence[Mapping[str, np.ndarray]], static_masks: np.ndarray, K: np.ndarray,
) -> tuple[list[PairPose], list[int]]:
    """The pairs with those in a triplet disagreeing by more than ``thresh_deg`` repaired (module
    docstring: only where the rotation medoid is a bridge more than ``thresh_deg`` from the pair's
    own rotation), and the indices of the pairs changed. A pair needs both neighbours (three
    candidates; the chain's first and last pair stay) and a translation of its own (rotation-only
    pairs stay)."""
    gaps = triplet_gaps(pairs, triplets)
    out = list(pairs)
    changed = []
    for k in range(1, len(pairs) - 1):
        if max(gaps[k - 1], gaps[k]) <= thresh_deg or pairs[k][1] is None:
            continue
        R_own = pairs[k][0][:3, :3]
        R_prev = triplets[k - 1][:3, :3] @ pairs[k - 1][0][:3, :3].T  # through frame k-1
        R_next = pairs[k + 1][0][:3, :3].T @ triplets[k][:3, :3]  # through frame k+2
        i = rotation_medoid([R_own, R_prev, R_next])
        if i == 0 or rotation_deg(R_own.T @ [R_own, R_prev, R_next][i]) <= thresh_deg:
            continue  # its own rotation is the consensus, or within the threshold of it
        fv = pair_masks(flows[k], static_masks, k)[0]
        T, corr = translation_given_rotation([R_own, R_prev, R_next][i], np.asarray(flows[k]["fwd"]), fv, K,
                                             t0=pairs[k][0][:3, 3])
        if corr is None or len(corr[0]) < 50:
            continue
        out[k] = (T, corr)
        changed.append(k)
    return out, changed


def checked_pair_poses(
    flows: Sequence[Mapping[str, np.ndarray]], static_masks: np.ndarray, K: np.ndarray, thresh_deg: float,
) -> tuple[list[PairPose], list[int], np.ndarray]:
    """The chain's pair poses (``chain_pair_poses``) checked and repaired: (pair poses for
    ``essential_chain(pair_poses=...)``, the repaired pairs, the triplet gaps (degrees) before)."""
    pairs = chain_pair_poses(flows, static_masks, K)
    if len(pairs) < 3:
        return pairs, [], np.zeros(max(len(pairs) - 1, 0))
    triplets = triplet_poses(flows, static_masks, K)
    repaired, changed = repair_pairs(pairs, triplets, thresh_deg, flows, static_masks, K)
    return repaired, changed, triplet_gaps(pairs, triplets)
