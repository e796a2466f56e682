"""Bundle adjustment over flow tracks: inconsistent keyframe poses come back towards the truth."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_ref import rigid_flow
from scipy.spatial.transform import Rotation

from gcvd_flow.evaluate.metrics import ate, umeyama_alignment
from gcvd_flow.evaluate.synth import render_clip
from gcvd_flow.stages.geometry import se3
from gcvd_flow.stages.optimize import ba_solver
from gcvd_flow.stages.optimize.bundle_adjustment import bundle_adjust, flow_tracks, gtsam_graph, inverse_depth_landmark, solve_gtsam


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
    tracks = flow_tracks(edges, kf, depths[0].shape, stride=16, track_length=4)
    assert len(tracks) > 50 and max(len(t) for t in tracks) == 4
    # a track's observations are the projections of one 3-D point (exact flows, exact depth)
    m, u, v = tracks[0][0]
    z = depths[m][int(round(v)), int(round(u))]
    X = T_gt[m] @ np.r_[z * (np.linalg.inv(K) @ [u, v, 1.0]), 1.0]
    for k, a, b in tracks[0][1:]:
        p = K @ (np.linalg.inv(T_gt[k]) @ X)[:3]
        assert np.hypot(p[0] / p[2] - a, p[1] / p[2] - b) < 0.6


@pytest.mark.parametrize("solver", ["schur", "gtsam"])
def test_bundle_adjustment_makes_poses_agree_with_the_tracks(solver):
    K, T_gt, depths, edges, kf = _keyframe_problem()
    T0 = _jitter(T_gt, seed=1)
    before = ate(T0, T_gt)["ate_rmse"]
    res = bundle_adjust(T0, depths, edges, kf, K, stride=12, track_length=4, min_views=3, solver=solver)
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
    tracks = flow_tracks(edges, kf, depths[0].shape, stride=16, track_length=4)
    across = [t for t in tracks if {o[0] for o in t} >= {0, n - 1}]
    assert len(across) > 20
    without = flow_tracks({e: f for e, f in edges.items() if e != (kf[0], kf[-1])}, kf, depths[0].shape,
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



def test_depth_scale_of_every_keyframe_comes_from_what_it_observes():
    """A keyframe's depth map 30x too far (a jump of the keyframe windows' chain: the synthetic
    scan's keyframe 17) and the last keyframe's 2x too far (no landmark is anchored in the last
    keyframe): each gets the scale that brings its depth map onto the adjusted landmarks it
    observes, not 1 (segments between them otherwise fit depth and poses at scales 2-30x apart;
    the scan's frames 12-16 ended 0.7-1.6 m off)."""
    K, T_gt, depths, edges, kf = _keyframe_problem()
    wrong = {5: 30.0, len(kf) - 1: 2.0}
    depths = [d * wrong.get(m, 1.0) for m, d in enumerate(depths)]
    scale = bundle_adjust(T_gt, depths, edges, kf, K, consistent_px=0.0)["depth_scale"]
    for m, c in wrong.items():
        assert abs(scale[m] * c - 1) < 0.05, (m, scale)
    assert np.all(np.abs(np.delete(scale, list(wrong)) - 1) < 0.05), scale


def _shrunk_start(c: float = 16.0):
    """The walk's first third of keyframes ``c`` times too small (poses about the first keyframe
    and their depths with them, the rest following rigidly): the HoloLens walk's turning start as
    the keyframe windows leave it (6-16x)."""
    K, T_gt, depths, edges, kf = _keyframe_problem(n_frames=60, step=3)
    m = len(kf) // 3
    T0, d0 = T_gt.copy(), [d / c if k <= m else d for k, d in enumerate(depths)]
    for k in range(1, len(kf)):
        j = min(k, m)
        T0[k, :3, 3] = T_gt[0, :3, 3] + (T_gt[j, :3, 3] - T_gt[0, :3, 3]) / c + (T_gt[k, :3, 3] - T_gt[j, :3, 3])
    return K, T_gt, T0, d0, edges, kf, np.arange(len(kf)) <= m


def test_a_restart_adjusts_again_from_the_rescaled_depths():
    """``restarts=1`` is a second adjustment from the first one's poses with each keyframe's depth
    scaled by its depth_scale (depth_scale then the product); on the shrunk start it gets the
    start's scale closer to the truth than the first adjustment alone."""
    K, T_gt, T0, d0, edges, kf, start = _shrunk_start()
    kw = dict(stride=12, track_length=16, min_views=3, consistent_px=0.0, max_iterations=3)
    one = bundle_adjust(T0, d0, edges, kf, K, **kw)
    two = bundle_adjust(T0, d0, edges, kf, K, restarts=1, **kw)
    again = bundle_adjust(one["poses"], [d * np.float32(s) for d, s in zip(d0, one["landmark_scale"])], edges, kf, K, **kw)
    np.testing.assert_array_equal(two["poses"], again["poses"])
    np.testing.assert_array_equal(two["depth_scale"], one["landmark_scale"] * again["depth_scale"])
    assert two["iterations"] == one["iterations"] + again["iterations"]
    assert two["initial_median_px"] == one["initial_median_px"]

    def start_scale(T: np.ndarray) -> float:  # > 1: the start is too small against the whole walk
        s_all = umeyama_alignment(T[:, :3, 3], T_gt[:, :3, 3])[0]
        return umeyama_alignment(T[start, :3, 3], T_gt[start, :3, 3])[0] / s_all

    assert start_scale(T0) > 10
    assert start_scale(two["poses"]) < start_scale(one["poses"]) - 2
    np.testing.assert_array_equal(bundle_adjust(T0, d0, edges, kf, K, restarts=0, **kw)["poses"], one["poses"])

# ------------------------------------------------------------------ the Schur solver against gtsam
def _synthetic_problem(seed: int = 0, n_kf: int = 5, n_lm: int = 300, noise_px: float = 0.3,
                       outliers: float = 0.05, robust_px: float = 0.3):
    """Keyframes along a short arc looking at points 1.5-4 m away; landmarks anchored in random
    keyframes, observed (with pixel noise, ``outliers`` of them moved by up to 20 px) by every
    keyframe that sees them in its image. Returns (problem, true poses, initial poses, initial
    landmarks, weak prior sigmas): poses jittered by 0.5 deg / 1 cm (keyframe 0 exact), priors
    at the jittered poses as the pipeline sets them, landmarks at the true depth +-5 %."""
    rng = np.random.default_rng(seed)
    K = np.array([[200.0, 0, 64], [0, 200.0, 48], [0, 0, 1]])
    Kinv = np.linalg.inv(K)
    T = np.tile(np.eye(4), (n_kf, 1, 1))
    for k in range(n_kf):
        T[k, :3, :3] = Rotation.from_rotvec([0.02 * k, -0.05 * k, 0.01]).as_matrix()
        T[k, :3, 3] = [0.12 * k, 0.02 * np.sin(k), 0.01 * k]
    anchor = rng.integers(0, n_kf, n_lm)
    u, v, z = rng.uniform(8, 120, n_lm), rng.uniform(8, 88, n_lm), rng.uniform(1.5, 4.0, n_lm)
    X = np.einsum("lij,lj->li", T[anchor, :3, :3], z[:, None] * (np.stack([u, v, np.ones(n_lm)], 1) @ Kinv.T))
    X += T[anchor, :3, 3]
    obs_lm, obs_cam, uv = [], [], []
    for j in range(n_lm):
        views = [(int(anchor[j]), u[j], v[j])]
        for k in range(n_kf):
            p = K @ (np.linalg.inv(T[k]) @ np.r_[X[j], 1.0])[:3]
            if k != anchor[j] and p[2] > 0 and 0 <= p[0] / p[2] < 128 and 0 <= p[1] / p[2] < 96:
                views.append((k, p[0] / p[2], p[1] / p[2]))
        if len(views) >= 3:
            for k, a, b in views:
                obs_lm.append(j), obs_cam.append(k), uv.append((a, b))
    keep = np.unique(obs_lm)
    remap = -np.ones(n_lm, np.int64)
    remap[keep] = np.arange(len(keep))
    uv = np.array(uv) + rng.normal(0, noise_px, (len(uv), 2))
    bad = rng.random(len(uv)) < outliers
    uv[bad] += rng.uniform(-20, 20, (int(bad.sum()), 2))
    T0 = _jitter(T, seed + 1)
    weak = np.array([0.05] * 3 + [0.05 * 2.5] * 3)
    info = np.tile(1 / weak**2, (n_kf, 1))
    info[0] += 1 / 1e-12  # the gauge: sigma 1e-6 on keyframe 0, as bundle_adjust sets it
    prob = ba_solver.Problem(K, anchor[keep], remap[np.array(obs_lm)], np.array(obs_cam), uv, robust_px, T0, info)
    lm0 = inverse_depth_landmark(u[keep], v[keep], z[keep] * rng.uniform(0.95, 1.05, len(keep)), Kinv)
    return prob, T, T0, lm0, weak


def _pose_gap(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    """Largest rotation (rad) and translation (m) difference between two pose sets (K, 4, 4)."""
    rel = np.linalg.inv(A) @ B
    return (float(np.max(np.linalg.norm(Rotation.from_matrix(rel[:, :3, :3]).as_rotvec(), axis=1))),
            float(np.max(np.linalg.norm(A[:, :3, 3] - B[:, :3, 3], axis=1))))


def test_schur_solver_reaches_gtsams_solution():
    """Same cost function (checked against gtsam's graph.error, a point behind a camera
    included) and same minimum: poses within 1e-4 rad / 1e-4 m, cost equal to 1e-6."""
    prob, T_gt, T0, lm0, weak = _synthetic_problem()
    assert len(lm0) > 200 and len(prob.uv) > 3 * len(lm0)
    graph, values = gtsam_graph(prob, T0, lm0, weak)
    assert ba_solver.total_cost(prob, T0, lm0) == pytest.approx(graph.error(values), rel=1e-10)
    behind = lm0.copy()
    behind[0, 2] *= -1  # negative inverse depth: behind its anchor (and, here, every other view)
    g2, v2 = gtsam_graph(prob, T0, behind, weak)
    assert ba_solver.total_cost(prob, T0, behind) == pytest.approx(g2.error(v2), rel=1e-10)

    ours = ba_solver.solve(prob, T0, lm0, max_iterations=100, relative_tol=1e-10)
    ref = solve_gtsam(prob, T0, lm0, weak, max_iterations=100, relative_tol=1e-10)
    rot, trans = _pose_gap(ours.poses, ref.poses)
    print(f"cost {ours.initial_cost:.4f} -> ours {ours.final_cost:.6f} ({ours.iterations} it), gtsam "
          f"{ref.final_cost:.6f} ({ref.iterations} it); poses differ by {rot:.1e} rad, {trans:.1e} m")
    assert rot < 1e-4 and trans < 1e-4
    assert ours.final_cost == pytest.approx(ref.final_cost, rel=1e-6)
    assert ours.final_cost == pytest.approx(ba_solver.total_cost(prob, ref.poses, ref.landmarks), rel=1e-6)
    assert ours.final_cost < 0.5 * ours.initial_cost
    np.testing.assert_allclose(ours.landmarks, ref.landmarks, atol=1e-3)  # rho of a barely-moved point: looser
    assert _pose_gap(ours.poses, T_gt)[1] < 0.5 * _pose_gap(T0, T_gt)[1]  # and the jitter is mostly gone


def test_analytic_jacobians_match_finite_differences():
    """Reprojection Jacobians (anchor pose, observing pose, landmark; right perturbation
    T Exp(xi) as gtsam's Pose3.retract), the prior's Jacobian, and the SE(3) maps against gtsam."""
    prob, _, T0, lm0, _ = _synthetic_problem(n_lm=40)
    lin = ba_solver.reprojection(prob, T0, lm0, jacobians=True)
    anchor = prob.anchor[prob.obs_lm]
    eps = 1e-6
    for k in range(len(T0)):
        for c in range(6):
            d = np.zeros((len(T0), 6))
            d[k, c] = eps
            plus = ba_solver.reprojection(prob, T0 @ se3.se3_exp(d), lm0)
            minus = ba_solver.reprojection(prob, T0 @ se3.se3_exp(-d), lm0)
            analytic = lin.A[:, c] * (anchor == k) + lin.B[:, c] * (prob.obs_cam == k)
            np.testing.assert_allclose((plus - minus) / (2 * eps), analytic, atol=2e-5 * np.abs(analytic).max())
            e_p, _ = ba_solver.prior_terms(prob, T0 @ se3.se3_exp(d))
            e_m, _ = ba_solver.prior_terms(prob, T0 @ se3.se3_exp(-d))
            _, J = ba_solver.prior_terms(prob, T0, jacobians=True)
            np.testing.assert_allclose((e_p - e_m)[k] / (2 * eps), J[k][:, c], atol=1e-7)
    for c in range(3):
        d = np.zeros_like(lm0)
        d[:, c] = eps
        numeric = (ba_solver.reprojection(prob, T0, lm0 + d) - ba_solver.reprojection(prob, T0, lm0 - d)) / (2 * eps)
        np.testing.assert_allclose(numeric, lin.C[:, c], atol=2e-5 * np.abs(lin.C[:, c]).max())
    assert np.all(lin.A[:, :, anchor == prob.obs_cam] == 0) and np.all(lin.B[:, :, anchor == prob.obs_cam] == 0)
    import gtsam
    xi = np.random.default_rng(3).normal(0, 0.7, (6, 6))
    for x, T in zip(xi, se3.se3_exp(xi)):
        P = gtsam.Pose3(T0[1])
        np.testing.assert_allclose(T, gtsam.Pose3.Expmap(x).matrix(), atol=1e-12)
        np.testing.assert_allclose(T0[1] @ T, P.retract(x).matrix(), atol=1e-12)  # retract = compose(Expmap)
        np.testing.assert_allclose(se3.se3_log(T[None])[0], gtsam.Pose3.Logmap(gtsam.Pose3(T)), atol=1e-10)
        np.testing.assert_allclose(se3.se3_dlog(x[None])[0], gtsam.Pose3.LogmapDerivative(gtsam.Pose3(T)),
                                   atol=1e-10)


def test_schur_step_solves_the_full_damped_system():
    """One damped step of the Schur solver equals the dense solve of (H + lam D) d = -g built
    from the public Jacobians (IRLS-weighted reprojection terms plus the pose priors)."""
    from gcvd_flow.stages.optimize.ba_solver import _damped_step, _linearize, _sorted_problem

    prob, _, T0, lm0, _ = _synthetic_problem(n_lm=120)
    p, order, layout = _sorted_problem(prob)
    lm = lm0[order]
    n, L, M = len(T0), len(lm), len(p.uv)
    lin = ba_solver.reprojection(p, T0, lm, jacobians=True)
    w = 1 / (1 + (lin.r**2).sum(0) / p.robust_px**2)
    J = np.zeros((2 * M, 6 * n + 3 * L))
    rows = np.arange(2 * M).reshape(M, 2)
    for o, (a, k, j) in enumerate(zip(p.anchor[p.obs_lm], p.obs_cam, p.obs_lm)):
        J[rows[o], 6 * a:6 * a + 6] += lin.A[:, :, o]
        J[rows[o], 6 * k:6 * k + 6] += lin.B[:, :, o]
        J[rows[o], 6 * n + 3 * j:6 * n + 3 * j + 3] = lin.C[:, :, o]
    H = J.T @ (np.repeat(w, 2)[:, None] * J)
    g = J.T @ (np.repeat(w, 2) * lin.r.T.ravel())
    e, Jp = ba_solver.prior_terms(p, T0, jacobians=True)
    for k in range(n):
        H[6 * k:6 * k + 6, 6 * k:6 * k + 6] += Jp[k].T @ (p.prior_info[k][:, None] * Jp[k])
        g[6 * k:6 * k + 6] += Jp[k].T @ (p.prior_info[k] * e[k])
    lam = 1e-3
    dense = np.linalg.solve(H + lam * np.diag(np.clip(np.diag(H), 1e-6, None)), -g)
    dp, dl, pred = _damped_step(p, layout, _linearize(p, layout, T0, lm), lam)
    np.testing.assert_allclose(dp.ravel(), dense[:6 * n], atol=1e-9 * np.abs(dense).max())
    np.testing.assert_allclose(dl.ravel(), dense[6 * n:], atol=1e-9 * np.abs(dense).max())
    assert pred == pytest.approx(-(g @ dense + 0.5 * dense @ H @ dense), rel=1e-8)


def test_schur_solver_is_deterministic():
    """Two runs give the same bytes (stable sorts, no threading-dependent reductions)."""
    K, T_gt, depths, edges, kf = _keyframe_problem()
    T0 = _jitter(T_gt, seed=1)
    a = bundle_adjust(T0, depths, edges, kf, K, stride=12, track_length=4, min_views=3)
    b = bundle_adjust(T0, depths, edges, kf, K, stride=12, track_length=4, min_views=3)
    assert not a["skipped"] and a["iterations"] > 0
    assert a["poses"].tobytes() == b["poses"].tobytes()
    assert a["depth_scale"].tobytes() == b["depth_scale"].tobytes()
    assert a["final_median_px"] == b["final_median_px"]


def test_bundle_adjustment_stage_runs_numpy_blas_on_one_thread(monkeypatch):
    """The stage limits numpy's OpenBLAS to one thread while it adjusts (its idle pthreads spin:
    two runs adjusting at once took 55 s instead of 1.6; docs/benchmarks.md), and restores it."""
    from types import SimpleNamespace

    from threadpoolctl import threadpool_info, threadpool_limits

    from gcvd_flow import pipeline
    from gcvd_flow.stages.optimize import bundle_adjustment as ba_mod

    def blas_threads() -> list[int]:
        return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]

    seen = []

    def fake_adjust(T_w_k, *args, **kwargs):
        seen.append(blas_threads())
        return {"poses": T_w_k, "landmarks": 0, "observations": 0, "initial_median_px": 0.0, "final_median_px": 0.0,
                "iterations": 0, "skipped": True, "depth_scale": np.ones(len(T_w_k))}

    monkeypatch.setattr(ba_mod, "bundle_adjust", fake_adjust)
    poses = np.tile(np.eye(4), (2, 1, 1))
    inputs = {"pose_graph": {"poses": poses}, "optimize_keyframes": {"depths": [np.ones((4, 4))] * 2, "keyframes": [0, 1]},
              "association": {"edge_flows": []}, "ingest": SimpleNamespace(summary={"K": np.eye(3)}),
              "calibrate": {"K": np.eye(3)}, "masks": [{"static": np.ones((4, 4), np.uint8)}] * 2}
    ctx = SimpleNamespace(log=lambda msg: None)
    with threadpool_limits(limits=2, user_api="blas"):  # as on a 2-core machine, whatever this one has
        before = blas_threads()
        out = pipeline.run_bundle_adjustment(inputs, pipeline.BundleAdjustmentParams(), ctx)
        assert blas_threads() == before
    assert seen and seen[0] and set(seen[0]) == {1}
    assert np.array_equal(out["poses"], poses)
