"""The essential chain's three-view check (issue 37 item 1, ``optimize_keyframes.chain_check_deg``):
a keyframe pair whose two-view rotation is off (the HoloLens clip's pairs 33-35) is found by the
triplets it belongs to and repaired; clean pairs are left bit-identical. Each test fails without
the mechanism."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from gcvd_flow.stages.optimize.chain_check import (
    checked_pair_poses,
    repair_pairs,
    rotation_deg,
    translation_given_rotation,
    triplet_gaps,
    triplet_poses,
)
from gcvd_flow.stages.optimize.init import chain_pair_poses, essential_chain

K = np.array([[50.0, 0, 47.5], [0, 50.0, 35.5], [0, 0, 1]])
H, W = 72, 96


def _room_depth(T_w_c: np.ndarray) -> np.ndarray:
    """z-depth (H, W) of the inside of the box [-3, 3] x [-1.5, 1.5] x [-4, 3] seen from T_w_c (convex:
    nothing is occluded, every flow below is exact)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    d_c = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)  # z = 1 rays
    d_w = d_c @ T_w_c[:3, :3].T
    o = T_w_c[:3, 3]
    lo, hi = np.array([-3.0, -1.5, -4.0]), np.array([3.0, 1.5, 3.0])
    with np.errstate(divide="ignore"):
        t = np.where(d_w > 0, (hi - o) / d_w, (lo - o) / d_w)
    return np.min(np.where(np.isfinite(t) & (t > 0), t, np.inf), axis=-1)


def _flow(depth_a: np.ndarray, T_b_a: np.ndarray) -> np.ndarray:
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    X = (np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T) * depth_a[..., None]
    x = (X @ T_b_a[:3, :3].T + T_b_a[:3, 3]) @ K.T
    return (x[..., :2] / x[..., 2:] - np.stack([u, v], -1)).astype(np.float32)


def _walk(n: int = 8) -> tuple[np.ndarray, list[dict[str, np.ndarray]]]:
    """A walk along x looking into a corner of the room, the yaw swaying by 1-6 degrees a step; its
    exact pair flows."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        poses[k, :3, :3] = Rotation.from_euler("y", 5.0 * np.sin(1.3 * k) + 35.0, degrees=True).as_matrix()
        poses[k, :3, 3] = [-1.5 + 0.3 * k, 0.1 * np.sin(k), 0.05 * k]
    depth = [_room_depth(P) for P in poses]
    flows = []
    for k in range(n - 1):
        T = np.linalg.inv(poses[k + 1]) @ poses[k]  # camera k -> camera k+1
        fwd, bwd = _flow(depth[k], T), _flow(depth[k + 1], np.linalg.inv(T))
        inside = lambda f: ((np.mgrid[0:H, 0:W][1] + f[..., 0] >= 0) & (np.mgrid[0:H, 0:W][1] + f[..., 0] <= W - 1)  # noqa: E731
                            & (np.mgrid[0:H, 0:W][0] + f[..., 1] >= 0) & (np.mgrid[0:H, 0:W][0] + f[..., 1] <= H - 1))
        flows.append({"fwd": fwd, "bwd": bwd, "fwd_valid": inside(fwd), "bwd_valid": inside(bwd)})
    return poses, flows


def _rel(poses: np.ndarray, k: int) -> np.ndarray:
    return np.linalg.inv(poses[k + 1]) @ poses[k]


def _tdir_deg(T: np.ndarray, T_true: np.ndarray) -> float:
    a, b = T[:3, 3], T_true[:3, 3]
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def _corrupt(T: np.ndarray, deg: float) -> np.ndarray:
    """The rotation / translation ambiguity: the rotation turned by ``deg`` about y, the translation
    direction turned with it (twice as far), as a two-view estimate on a rotation-dominated flow errs."""
    out = T.copy()
    dR = Rotation.from_euler("y", deg, degrees=True).as_matrix()
    out[:3, :3] = dR @ T[:3, :3]
    out[:3, 3] = Rotation.from_euler("y", 2 * deg, degrees=True).as_matrix() @ T[:3, 3]
    return out


def test_a_corrupted_pair_is_flagged_by_its_triplets_and_repaired() -> None:
    poses, flows = _walk()
    sm = np.ones((len(poses), H, W), np.uint8)
    pairs = chain_pair_poses(flows, sm, K)
    for k in range(len(flows)):  # exact flows: every pair is right to start with
        assert rotation_deg(_rel(poses, k)[:3, :3].T @ pairs[k][0][:3, :3]) < 0.3
        assert _tdir_deg(pairs[k][0], _rel(poses, k)) < 3.0
    triplets = triplet_poses(flows, sm, K)
    assert triplet_gaps(pairs, triplets).max() < 0.5
    bad = 3
    broken = list(pairs)
    broken[bad] = (_corrupt(pairs[bad][0], 6.0), pairs[bad][1])
    gaps = triplet_gaps(broken, triplets)
    assert set(np.nonzero(gaps > 2.0)[0].tolist()) == {bad - 1, bad}  # both triplets holding the pair
    fixed, changed = repair_pairs(broken, triplets, 2.0, flows, sm, K)
    assert changed == [bad]
    assert rotation_deg(_rel(poses, bad)[:3, :3].T @ fixed[bad][0][:3, :3]) < 0.5
    assert _tdir_deg(fixed[bad][0], _rel(poses, bad)) < 3.0  # re-estimated from its own flow
    for k in range(len(flows)):
        if k != bad:
            assert fixed[k] is broken[k]
    # the chain's scale: the corrupted pair makes a jump in the step lengths, the repaired one not
    ones = np.ones(sm.shape)

    def step_ratio(pp: list) -> np.ndarray:
        P = essential_chain(flows, sm, ones, K, pair_poses=pp)[0]
        est = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1)
        true = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
        r = est / true
        return r / r[0]

    assert np.abs(step_ratio(pairs) - 1).max() < 0.05
    assert np.abs(step_ratio(broken) - 1).max() > 0.15
    assert np.abs(step_ratio(fixed) - 1).max() < 0.05


def test_clean_chain_is_left_as_it_is() -> None:
    poses, flows = _walk()
    sm = np.ones((len(poses), H, W), np.uint8)
    pairs = chain_pair_poses(flows, sm, K)
    checked, changed, gaps = checked_pair_poses(flows, sm, K, 2.0)
    assert changed == [] and gaps.shape == (len(flows) - 1,)
    for (T0, c0), (T1, c1) in zip(pairs, checked):
        assert np.array_equal(T0, T1) and (c0 is None) == (c1 is None)
    # essential_chain given the unchanged pairs is bit-identical to computing them itself
    ones = np.ones(sm.shape)
    a, b = essential_chain(flows, sm, ones, K), essential_chain(flows, sm, ones, K, pair_poses=checked)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


def test_translation_given_the_rotation_recovers_the_direction() -> None:
    poses, flows = _walk()
    T_true = _rel(poses, 2)
    valid = flows[2]["fwd_valid"]
    for t0 in (None, np.array([1.0, 0.0, 0.0]), -T_true[:3, 3]):
        T, corr = translation_given_rotation(T_true[:3, :3], flows[2]["fwd"], valid, K, t0=t0)
        assert corr is not None and len(corr[0]) > 0.8 * min(valid.sum(), 3000)
        assert _tdir_deg(T, T_true) < 1.0
        np.testing.assert_array_equal(T[:3, :3], T_true[:3, :3])
