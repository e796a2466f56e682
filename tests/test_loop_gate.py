"""Loop edges the drifted odometry rejects are kept on their own two-view rotation
(pose_graph.loop_self_check_deg), under a robust kernel (pose_graph.loop_robust)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from gcvd_flow.stages.optimize.params import PoseGraphSettings
from gcvd_flow.stages.optimize.pose_graph import edge_measurement, gate_loops, loop_pair_rotation, optimize_pose_graph
from tests.test_pose_graph import _ate, _chain, _look_at_circle


def _drifted_loop(turn_per_step: float = 0.02, n: int = 40):
    """Ground truth on a circle, odometry with a heading drift of ``turn_per_step`` rad per step
    (40 keyframes: 45 degrees over the loop) and the loop edge (n-1 -> 0) in the optimisations'
    convention T_b_a = inv(T_w_b) @ T_w_a, exact."""
    gt = _look_at_circle(n)
    bias = Rotation.from_rotvec([0.0, turn_per_step, 0.0]).as_matrix()
    meas = []
    for k in range(n - 1):
        t = edge_measurement(gt[k], gt[k + 1])
        t[:3, :3] = bias @ t[:3, :3]
        meas.append(t)
    odo = _chain(gt[0], meas)
    seq = [dict(a=k, b=k + 1, T_a_b=meas[k], weight=1.0) for k in range(n - 1)]
    seq += [dict(a=k, b=k + 2, T_a_b=meas[k] @ meas[k + 1], weight=0.5) for k in range(n - 2)]  # windows' tau = 2
    loop = {"a": n - 1, "b": 0, "i": n - 1, "j": 0, "T_b_a": np.linalg.inv(gt[0]) @ gt[n - 1]}
    return gt, odo, seq, loop


def _turned(R: np.ndarray, deg: float) -> np.ndarray:
    return Rotation.from_rotvec([np.radians(deg), 0.0, 0.0]).as_matrix() @ R


def test_a_correct_loop_the_drifted_odometry_rejects_is_kept_on_its_own_rotation() -> None:
    gt, odo, seq, loop = _drifted_loop()
    own = lambda e: _turned(loop["T_b_a"][:3, :3], 1.0)  # noqa: E731  (the pair's flow: 1 degree off)
    # the odometry gate alone rejects it: the drift is past 30 degrees over the loop
    kept, rejected = gate_loops(odo, [loop], 30.0, 1.0, self_check_deg=0.0, own_rotation=own)
    assert not kept and rejected[0]["rotation_disagreement_deg"] > 40 and "own_rotation_deg" not in rejected[0]
    # the default keeps it: a verified loop whose edge agrees with its own two-view rotation is
    # not a failed edge optimisation, whatever the drift (held-out walk B: 2 loops verified, 0 used)
    default = PoseGraphSettings()
    kept, rejected = gate_loops(odo, [loop], default.max_loop_rotation_deg, 1.0,
                                self_check_deg=default.loop_self_check_deg, robust=default.loop_robust, own_rotation=own)
    assert not rejected and len(kept) == 1 and "robust" not in kept[0]
    ate_odo = _ate(odo, gt)
    closed = optimize_pose_graph(odo, seq + kept)["poses"]
    assert _ate(closed, gt) < 0.1 * ate_odo, (_ate(closed, gt), ate_odo)
    kept, _ = gate_loops(odo, [loop], 30.0, 1.0, self_check_deg=5.0, robust=0.3, own_rotation=own)
    assert kept[0]["robust"] == 0.3
    # a loop within the gate is kept as before, without a kernel
    _, odo_small, _, loop_small = _drifted_loop(0.005)
    kept, rejected = gate_loops(odo_small, [loop_small], 30.0, 1.0, self_check_deg=5.0, robust=0.1, own_rotation=own)
    assert not rejected and "robust" not in kept[0]


def test_a_loop_its_own_geometry_does_not_vouch_for_stays_rejected() -> None:
    _, odo, _, loop = _drifted_loop()
    far = lambda e: _turned(loop["T_b_a"][:3, :3], 12.0)  # noqa: E731
    kept, rejected = gate_loops(odo, [loop], 30.0, 1.0, self_check_deg=5.0, own_rotation=far)
    assert not kept and abs(rejected[0]["own_rotation_deg"] - 12.0) < 1e-6
    kept, rejected = gate_loops(odo, [loop], 30.0, 1.0, self_check_deg=5.0, own_rotation=lambda e: None)
    assert not kept and "own_rotation_deg" not in rejected[0]


def test_the_robust_kernel_bounds_what_a_wrong_loop_does() -> None:
    gt, _, seq, _ = _drifted_loop(0.0)
    n = len(gt)
    wrong = edge_measurement(gt[n - 1], gt[n // 2])  # a look-alike place: right rotation class, wrong place
    wrong[:3, 3] += np.array([1.5, 0.0, 0.0])
    loop = {"a": n - 1, "b": n // 2, "T_a_b": wrong, "weight": 1.0}
    plain = optimize_pose_graph(gt, seq + [loop])["poses"]
    robust = optimize_pose_graph(gt, seq + [{**loop, "robust": 0.1}])["poses"]
    moved = lambda P: float(np.linalg.norm(P[:, :3, 3] - gt[:, :3, 3], axis=1).max())  # noqa: E731
    assert moved(robust) < 0.5 * moved(plain), (moved(robust), moved(plain))


def test_loop_pair_rotation_from_the_pairs_flow() -> None:
    rng = np.random.default_rng(1)
    h, w = 120, 160
    K = np.array([[140.0, 0, 80], [0, 140.0, 60], [0, 0, 1]])
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    z = 2.0 + rng.uniform(0, 3, (h, w))
    X = np.stack([uu, vv, np.ones_like(uu)], -1) @ np.linalg.inv(K).T * z[..., None]
    R = Rotation.from_rotvec(np.radians([3.0, 20.0, -2.0])).as_matrix()
    t = np.array([0.4, 0.05, 0.1])
    p = (X @ R.T + t) @ K.T
    fwd = p[..., :2] / p[..., 2:] - np.stack([uu, vv], -1)
    valid = np.ones((h, w), bool)
    got = loop_pair_rotation(fwd, valid, K)
    assert got is not None
    err = np.degrees(np.arccos(np.clip((np.trace(got.T @ R) - 1) / 2, -1, 1)))
    assert err < 0.5, err
    assert loop_pair_rotation(fwd, np.zeros((h, w), bool), K) is None
