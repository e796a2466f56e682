"""Bundle adjustment over flow tracks: inconsistent keyframe poses come back towards the truth."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from gcvd_flow.evaluate.metrics import ate
from gcvd_flow.evaluate.synth import render_clip
from geometry_ref import rigid_flow
from stages.optimize.bundle_adjustment import build_tracks, bundle_adjust


def _pair_flow(clip, a: int, b: int) -> dict[str, np.ndarray]:
    """Exact flows both ways between frames a and b, as the association stage stores them."""
    out = {}
    for name, (s, t) in (("fwd", (a, b)), ("bwd", (b, a))):
        fl = rigid_flow(clip.depth[s], clip.K, clip.poses[s], clip.poses[t])
        out[name], out[name + "_valid"] = np.nan_to_num(fl).astype(np.float32), np.isfinite(fl).all(-1)
    return out


def _keyframe_problem(seed: int = 0, trajectory: str = "walk", n_frames: int = 40, step: int = 3,
                      loop_edge: bool = False):
    """Keyframes every ``step`` frames; edge flows between consecutive keyframes (and, with
    ``loop_edge``, between the last and the first)."""
    clip = render_clip(n_frames=n_frames, trajectory=trajectory, size=(128, 96), seed=seed)
    kf = list(range(0, n_frames, step))
    edges = {(a, b): _pair_flow(clip, a, b) for a, b in zip(kf, kf[1:])}
    if loop_edge:
        edges[(kf[0], kf[-1])] = _pair_flow(clip, kf[0], kf[-1])
    return clip.K, clip.poses[kf], [clip.depth[k] for k in kf], edges, kf


def _jitter(T: np.ndarray, seed: int) -> np.ndarray:
    """Independent pose errors per keyframe (0.5 deg, 1 cm): what inconsistent windows leave.
    (A smooth drift with no loop and 4-keyframe tracks is not observable: scale can drift.)"""
    rng = np.random.default_rng(seed)
    out = T.copy()
    for k in range(1, len(T)):
        step = np.eye(4)
        step[:3, :3] = Rotation.from_rotvec(rng.normal(0, np.radians(0.5), 3)).as_matrix()
        step[:3, 3] = rng.normal(0, 0.01, 3)
        out[k] = T[k] @ step
    return out


def test_tracks_follow_the_flow():
    K, T_gt, depths, edges, kf = _keyframe_problem()
    tracks = build_tracks(edges, kf, depths[0].shape, stride=16, track_length=4)
    assert len(tracks) > 50 and max(len(t) for t in tracks) == 4
    # a track's observations are the projections of one 3-D point (exact flows, exact depth)
    m, u, v = tracks[0][0]
    z = depths[m][int(round(v)), int(round(u))]
    X = T_gt[m] @ np.r_[z * (np.linalg.inv(K) @ [u, v, 1.0]), 1.0]
    for k, a, b in tracks[0][1:]:
        p = K @ (np.linalg.inv(T_gt[k]) @ X)[:3]
        assert np.hypot(p[0] / p[2] - a, p[1] / p[2] - b) < 0.6


def test_bundle_adjustment_makes_poses_agree_with_the_tracks():
    K, T_gt, depths, edges, kf = _keyframe_problem()
    T0 = _jitter(T_gt, seed=1)
    before = ate(T0, T_gt)["ate_rmse"]
    res = bundle_adjust(T0, depths, edges, kf, K, stride=12, track_length=4, min_views=3)
    after = ate(res["poses"], T_gt)["ate_rmse"]
    print(f"ATE {before * 100:.2f} cm -> {after * 100:.2f} cm, median reprojection "
          f"{res['initial_median_px']:.2f} -> {res['final_median_px']:.2f} px, {res['landmarks']} tracks")
    assert res["landmarks"] > 100 and res["final_median_px"] < res["initial_median_px"]
    assert after < 0.5 * before
    np.testing.assert_allclose(res["poses"][0], T0[0], atol=1e-6)  # the gauge: first keyframe fixed


def _drift(T: np.ndarray, deg_per_kf: float = 0.4) -> np.ndarray:
    """A smooth drift: each keyframe's pose relative to the previous is turned a little more
    (about the vertical axis), as chained windows leave it; the error grows along the path."""
    out = T.copy()
    for k in range(1, len(T)):
        step = np.linalg.inv(T[k - 1]) @ T[k]
        turn = np.eye(4)
        turn[:3, :3] = Rotation.from_rotvec([0, np.radians(deg_per_kf), 0]).as_matrix()
        out[k] = out[k - 1] @ turn @ step
    return out


def test_tracks_cross_loop_edges():
    """A loop edge (first <-> last keyframe) adds the other end's view to tracks that reach
    either end; those observations are the same 3-D point (exact flows)."""
    K, T_gt, depths, edges, kf = _keyframe_problem(trajectory="loop", n_frames=48, step=4, loop_edge=True)
    n = len(kf)
    tracks = build_tracks(edges, kf, depths[0].shape, stride=16, track_length=4)
    across = [t for t in tracks if {o[0] for o in t} >= {0, n - 1}]
    assert len(across) > 20
    without = build_tracks({e: f for e, f in edges.items() if e != (kf[0], kf[-1])}, kf, depths[0].shape,
                           stride=16, track_length=4)
    assert not [t for t in without if {o[0] for o in t} >= {0, n - 1}]
    for t in across[:10]:
        m, u, v = t[0]
        X = T_gt[m] @ np.r_[depths[m][int(round(v)), int(round(u))] * (np.linalg.inv(K) @ [u, v, 1.0]), 1.0]
        for k, a, b in t[1:]:
            p = K @ (np.linalg.inv(T_gt[k]) @ X)[:3]
            assert np.hypot(p[0] / p[2] - a, p[1] / p[2] - b) < 1.0


def test_loop_edge_lets_bundle_adjustment_remove_drift():
    """Drift comes from small systematic flow errors that every link of the chain repeats
    (here +0.15 px horizontally on each consecutive pair): chain tracks agree with them and turn
    the path; the loop edge's unbiased view of the start ties the end back to it."""
    K, T_gt, depths, edges, kf = _keyframe_problem(trajectory="loop", n_frames=48, step=4, loop_edge=True)
    loop = (kf[0], kf[-1])
    biased = {}
    for e, f in edges.items():
        f = dict(f)
        if e != loop:
            f["fwd"] = f["fwd"] + np.float32([0.15, 0.0])
            f["bwd"] = f["bwd"] - np.float32([0.15, 0.0])
        biased[e] = f
    kw = dict(stride=12, track_length=4, min_views=3, robust_px=1.0, prior_trans_frac=1.0, prior_rot_sigma=1.0,
              consistent_px=0.0)
    def loop_gap(T: np.ndarray) -> float:
        """Error (m) of the last keyframe's position seen from the first: the loop's closure."""
        rel, rel_gt = np.linalg.inv(T[0]) @ T[-1], np.linalg.inv(T_gt[0]) @ T_gt[-1]
        scale = ate(T, T_gt)["scale"]
        return float(np.linalg.norm(scale * rel[:3, 3] - rel_gt[:3, 3]))

    with_loop = loop_gap(bundle_adjust(T_gt, depths, biased, kf, K, **kw)["poses"])
    chain_only = {e: f for e, f in biased.items() if e != loop}
    without = loop_gap(bundle_adjust(T_gt, depths, chain_only, kf, K, **kw)["poses"])
    print(f"loop closure error from the true poses: {without * 100:.2f} cm with chain tracks, "
          f"{with_loop * 100:.2f} cm with the loop edge")
    assert with_loop < 0.5 * without


def test_consistent_poses_are_kept():
    """Poses that already reproject the tracks within flow noise are returned unchanged."""
    K, T_gt, depths, edges, kf = _keyframe_problem()
    res = bundle_adjust(T_gt, depths, edges, kf, K, consistent_px=0.25)
    assert res["skipped"] and res["initial_median_px"] < 0.25 and res["landmarks"] > 100
    np.testing.assert_array_equal(res["poses"], T_gt)
    moved = bundle_adjust(_jitter(T_gt, seed=1), depths, edges, kf, K, consistent_px=0.25)
    assert not moved["skipped"] and moved["iterations"] > 0


def test_depth_scale_follows_the_adjusted_landmarks():
    """A keyframe whose depth map is 10 % too far (the scale drift chained windows leave) gets
    its landmarks pulled back by the other views: depth_scale ~ 1 / 1.1 there, ~ 1 elsewhere —
    what optimize_segments multiplies the keyframe depths by."""
    K, T_gt, depths, edges, kf = _keyframe_problem()
    depths = [d * (1.1 if m == 5 else 1.0) for m, d in enumerate(depths)]
    res = bundle_adjust(T_gt, depths, edges, kf, K, consistent_px=0.0)
    scale = res["depth_scale"]
    assert scale.shape == (len(kf),)
    assert abs(scale[5] - 1 / 1.1) < 0.02, scale
    assert np.all(np.abs(np.delete(scale, 5) - 1) < 0.02), scale
