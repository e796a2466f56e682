"""The essential chain's scale over a rotation-dominated stretch (issue 37 item 1,
``optimize_keyframes.chain_prior_scale_below``): a walk that turns on the spot for a few keyframes
(the HoloLens walk's start) must come out of the turn at the scale it went in with. Without the
option the chain restarts its scale from the next frame's depth prior, whose scale is arbitrary per
frame; with it, the scale is carried through the turn along the flow."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation
from test_chain_check import H, K, W, _flow, _room_depth, _walk

from gcvd_flow.stages.optimize.init import _parallax_fraction, chain_pair_poses, essential_chain


def _turning_walk(turn_step: float = 0.01) -> tuple[np.ndarray, list[dict[str, np.ndarray]], np.ndarray]:
    """Walk in the test room: 4 steps of 0.25 m (yaw 2 degrees a step), 6 steps turning 6 degrees
    on the spot (``turn_step`` m), 4 steps of 0.25 m again. Exact flows; the reference depths are the
    true depths times a factor per frame that halves during the turn (a monocular prior knows no
    scale: a median-normalised one changes it whenever the view does)."""
    yaw, pos = 35.0, np.array([-1.5, 0.0, 0.0])
    poses = np.tile(np.eye(4), (15, 1, 1))
    steps = [(0.25, 2.0)] * 4 + [(turn_step, 6.0)] * 6 + [(0.25, 2.0)] * 4
    for k in range(15):
        if k > 0:
            yaw += steps[k - 1][1]
            pos = pos + np.array([1.0, 0.0, 0.3]) * steps[k - 1][0]
        poses[k, :3, :3] = Rotation.from_euler("y", yaw, degrees=True).as_matrix()
        poses[k, :3, 3] = pos
    depth = [_room_depth(P) for P in poses]
    v, u = np.mgrid[0:H, 0:W]
    flows = []
    for k in range(14):
        T = np.linalg.inv(poses[k + 1]) @ poses[k]
        fwd, bwd = _flow(depth[k], T), _flow(depth[k + 1], np.linalg.inv(T))
        inside = lambda f: (u + f[..., 0] >= 0) & (u + f[..., 0] <= W - 1) & (v + f[..., 1] >= 0) & (v + f[..., 1] <= H - 1)  # noqa: E731
        flows.append({"fwd": fwd, "bwd": bwd, "fwd_valid": inside(fwd), "bwd_valid": inside(bwd)})
    factor = np.array([1.0] * 5 + [0.8, 0.7, 0.6, 0.55] + [0.5] * 6)
    ref = np.stack(depth) * factor[:, None, None]
    return poses, flows, ref


def _step_ratios(poses: np.ndarray, est: np.ndarray) -> np.ndarray:
    """Estimated / true step lengths, relative to the first step's."""
    r = np.linalg.norm(np.diff(est[:, :3, 3], axis=0), axis=1) / np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    return r / r[0]


def test_the_scale_comes_through_a_turn_on_the_spot() -> None:
    poses, flows, ref = _turning_walk()
    sm = np.ones((len(poses), H, W), np.uint8)
    pairs = chain_pair_poses(flows, sm, K)
    assert all(pairs[k][1] is None for k in range(4, 10))  # the turn: rotation-only pairs
    assert all(pairs[k][1] is not None for k in (*range(4), *range(10, 14)))
    off = _step_ratios(poses, essential_chain(flows, sm, ref, K)[0])
    on = _step_ratios(poses, essential_chain(flows, sm, ref, K, prior_scale_below=0.25)[0])
    np.testing.assert_allclose(off[:4], 1.0, atol=0.02)  # before the turn both are right
    np.testing.assert_allclose(on[:4], 1.0, atol=0.02)
    assert np.abs(off[10:] - 1).min() > 0.3  # after it the prior's scale: about 0.5
    np.testing.assert_allclose(on[10:], 1.0, atol=0.1)  # carried through the turn


def test_a_well_conditioned_walk_is_left_as_it_is() -> None:
    """Every pair of the swaying walk has a parallax above a quarter of its flow: the option changes
    no bit of the chain."""
    poses, flows = _walk()
    sm = np.ones((len(poses), H, W), np.uint8)
    pairs = chain_pair_poses(flows, sm, K)
    assert min(_parallax_fraction(flows[k], sm, k, K, pairs[k][0], 2) for k in range(len(flows))) > 0.25
    ref = np.ones(sm.shape)
    a, b = essential_chain(flows, sm, ref, K), essential_chain(flows, sm, ref, K, prior_scale_below=0.25)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


def test_the_parallax_fraction_tells_rotation_from_translation() -> None:
    poses, flows, _ = _turning_walk(turn_step=0.0)
    sm = np.ones((len(poses), H, W), np.uint8)
    frac = [_parallax_fraction(flows[k], sm, k, K, np.linalg.inv(poses[k + 1]) @ poses[k], 2) for k in range(14)]
    assert max(frac[4:10]) < 0.01  # a pure rotation leaves no parallax
    assert min(frac[:4] + frac[10:]) > 0.25
