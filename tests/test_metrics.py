"""Trajectory and depth metrics: known cases, and agreement with the `evo` package."""

from __future__ import annotations

import os

import numpy as np
import pytest

from gcvd_flow.evaluate import metrics

os.environ.setdefault("MPLBACKEND", "Agg")


def _traj(n: int = 50, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    from scipy.spatial.transform import Rotation

    poses = np.tile(np.eye(4), (n, 1, 1))
    ang = np.cumsum(rng.normal(0, 0.02, (n, 3)), axis=0)
    poses[:, :3, :3] = Rotation.from_rotvec(ang).as_matrix()
    poses[:, :3, 3] = np.cumsum(rng.normal(0, 0.05, (n, 3)), axis=0)
    return poses


def _sim3(poses: np.ndarray, s: float, seed: int = 1) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(np.random.default_rng(seed).normal(0, 1, 3)).as_matrix()
    t = np.array([1.0, -2.0, 0.5])
    out = poses.copy()
    out[:, :3, :3] = R @ poses[:, :3, :3]
    out[:, :3, 3] = s * (R @ poses[:, :3, 3].T).T + t
    return out


def test_identity_and_similarity_transform_give_zero_error():
    gt = _traj()
    assert metrics.ate(gt, gt)["ate_rmse"] < 1e-12
    est = _sim3(gt, 0.37)
    res = metrics.ate(est, gt)
    assert res["ate_rmse"] < 1e-9 and abs(res["scale"] - 1 / 0.37) < 1e-9
    r = metrics.rpe(est, gt)
    assert r["rpe_trans"] < 1e-9 and r["rpe_rot"] < 1e-6
    assert metrics.ate(est, gt, align="se3")["ate_rmse"] > 0.01  # scale is not free without sim3


def test_known_noise_level():
    gt = _traj(400)
    est = gt.copy()
    est[:, :3, 3] += np.random.default_rng(3).normal(0, 0.01, (400, 3))
    assert 0.015 < metrics.ate(est, gt)["ate_rmse"] < 0.019  # sqrt(3) * 0.01


def test_depth_metrics_median_scaling_and_validity():
    g = np.full((20, 20), 2.0)
    g[0, 0] = 0  # invalid
    g[1, 1] = 20  # beyond max depth
    m = metrics.depth_metrics(g * 3.0, g)
    assert m["abs_rel"] < 1e-12 and m["delta1"] == 1.0
    p = g.copy()
    p[5:10] *= 1.5
    m = metrics.depth_metrics(p, g)
    assert 0.05 < m["abs_rel"] < 0.5 and m["delta1"] < 1.0


def test_agrees_with_evo():
    evo_traj = pytest.importorskip("evo.core.trajectory")
    from evo.core import (
        metrics as evo_metrics,
        sync,  # noqa: F401  (import check)
    )

    gt = _traj(120, seed=5)
    est = _sim3(gt, 0.5)
    rng = np.random.default_rng(7)
    est[:, :3, 3] += rng.normal(0, 0.01, (120, 3))
    from scipy.spatial.transform import Rotation

    est[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.01, (120, 3))).as_matrix() @ est[:, :3, :3]

    ref = evo_traj.PosePath3D(poses_se3=list(gt))
    e = evo_traj.PosePath3D(poses_se3=list(est))
    e.align(ref, correct_scale=True)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, e))
    ours = metrics.ate(est, gt)
    assert ours["ate_rmse"] == pytest.approx(ape.get_statistic(evo_metrics.StatisticsType.rmse), rel=1e-6)

    for rel, key in ((evo_metrics.PoseRelation.translation_part, "rpe_trans"),
                     (evo_metrics.PoseRelation.rotation_angle_deg, "rpe_rot")):
        rpe = evo_metrics.RPE(rel, delta=1, delta_unit=evo_metrics.Unit.frames, all_pairs=False)
        rpe.process_data((ref, e))
        assert metrics.rpe(est, gt)[key] == pytest.approx(rpe.get_statistic(evo_metrics.StatisticsType.rmse), rel=1e-6)


def test_umeyama_recovers_known_similarity():
    rng = np.random.default_rng(11)
    src = rng.normal(size=(30, 3))
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec([0.3, -1.2, 2.0]).as_matrix()
    t = np.array([0.5, 2.0, -1.0])
    dst = 2.5 * src @ R.T + t
    s, R2, t2 = metrics.umeyama_alignment(src, dst)
    assert s == pytest.approx(2.5, rel=1e-12)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    np.testing.assert_allclose(t2, t, atol=1e-12)
    s, R3, _ = metrics.umeyama_alignment(src, dst, with_scale=False)
    assert s == 1.0 and np.linalg.det(R3) == pytest.approx(1.0)
    # A reflection is never returned, even when it would fit better.
    s, R4, _ = metrics.umeyama_alignment(src, src * np.array([1, 1, -1]))
    assert np.linalg.det(R4) == pytest.approx(1.0)
    with pytest.raises(ValueError):
        metrics.umeyama_alignment(src[:2], dst[:2])


def test_rpe_known_noise_and_input_checks():
    gt = _traj(300, seed=2)
    est = gt.copy()
    # A constant extra step of 2 cm along x in every relative motion -> rpe_trans = 0.02 m
    # when compared unaligned.
    steps = np.linalg.inv(gt[:-1]) @ gt[1:]
    steps[:, 0, 3] += 0.02
    for i in range(1, 300):
        est[i] = est[i - 1] @ steps[i - 1]
    r = metrics.rpe(est, gt, align="none")
    assert r["rpe_trans"] == pytest.approx(0.02, rel=1e-9) and r["rpe_rot"] < 1e-5
    with pytest.raises(ValueError):
        metrics.ate(est[:10], gt)
    with pytest.raises(ValueError):
        metrics.rpe(est, gt, delta=0)
    with pytest.raises(ValueError):
        metrics.ate(est, gt, align="sim4")


def test_path_length_and_aggregate():
    P = np.tile(np.eye(4), (4, 1, 1))
    P[:, :3, 3] = [[0, 0, 0], [1, 0, 0], [1, 2, 0], [1, 2, 2]]
    assert metrics.path_length(P) == pytest.approx(5.0)
    nan = float("nan")
    agg = metrics.aggregate_depth_metrics([
        {"abs_rel": 0.1, "sq_rel": 0.2, "rmse": 0.3, "delta1": 0.9},
        {"abs_rel": 0.3, "sq_rel": 0.4, "rmse": 0.5, "delta1": 0.7},
        {"abs_rel": nan, "sq_rel": nan, "rmse": nan, "delta1": nan},  # skipped
    ])
    assert agg == pytest.approx({"abs_rel": 0.2, "sq_rel": 0.3, "rmse": 0.4, "delta1": 0.8})
    assert np.isnan(metrics.depth_metrics(np.ones((2, 2)), np.ones((2, 2)))["abs_rel"])  # < 10 px


def test_agrees_with_evo_trajectories_sync_se3_and_delta():
    evo_traj = pytest.importorskip("evo.core.trajectory")
    from evo.core import metrics as evo_metrics, sync
    from scipy.spatial.transform import Rotation

    n = 150
    gt = _traj(n, seed=9)
    est = _sim3(gt, 1.0)  # SE(3) only: scale stays 1
    rng = np.random.default_rng(4)
    est[:, :3, 3] += rng.normal(0, 0.02, (n, 3))
    est[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.02, (n, 3))).as_matrix() @ est[:, :3, :3]

    def traj(p: np.ndarray) -> "evo_traj.PoseTrajectory3D":
        xyz = p[:, :3, 3]
        q = Rotation.from_matrix(p[:, :3, :3]).as_quat()[:, [3, 0, 1, 2]]  # evo wants w first
        return evo_traj.PoseTrajectory3D(positions_xyz=xyz, orientations_quat_wxyz=q, timestamps=np.arange(len(p), dtype=float))

    ref, e = sync.associate_trajectories(traj(gt), traj(est))
    e.align(ref, correct_scale=False)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, e))
    ours = metrics.ate(est, gt, align="se3")
    assert ours["ate_rmse"] == pytest.approx(ape.get_statistic(evo_metrics.StatisticsType.rmse), rel=1e-6)
    assert ours["ate_mean"] == pytest.approx(ape.get_statistic(evo_metrics.StatisticsType.mean), rel=1e-6)
    assert ours["ate_median"] == pytest.approx(ape.get_statistic(evo_metrics.StatisticsType.median), rel=1e-6)

    for delta in (1, 5):
        for rel, key in ((evo_metrics.PoseRelation.translation_part, "rpe_trans"),
                         (evo_metrics.PoseRelation.rotation_angle_deg, "rpe_rot")):
            rpe = evo_metrics.RPE(rel, delta=delta, delta_unit=evo_metrics.Unit.frames, all_pairs=True)
            rpe.process_data((ref, e))
            ours_r = metrics.rpe(est, gt, delta=delta, align="se3")[key]
            assert ours_r == pytest.approx(rpe.get_statistic(evo_metrics.StatisticsType.rmse), rel=1e-6)


def _fake_run(tmp_path, clip, frames, scale=1.0):
    """A RUN_DIR as `gcvd-flow run` writes it, from ground truth (poses and depth scaled by `scale`)."""
    import json

    from gcvd_flow.io.formats import write_tum_poses

    run = tmp_path / "run"
    (run / "depth").mkdir(parents=True)
    P = clip.poses[frames].copy()
    P[:, :3, 3] *= scale
    write_tum_poses(run / "poses.txt", np.asarray(frames, np.float64), P)
    for i in frames:
        np.save(run / "depth" / f"{i:06d}.npy", (clip.depth[i] * scale).astype(np.float32))
    h, w = clip.depth.shape[1:]
    (run / "cameras.json").write_text(json.dumps({"width": w, "height": h, "K": clip.K.tolist(),
                                                  "frame_indices": list(frames)}))
    return run


def test_run_eval_against_a_synth_folder(tmp_path):
    """`gcvd-flow eval`'s code: ground truth by source frame index, Sim(3) and median scaling."""
    from gcvd_flow.evaluate.run_eval import evaluate, format_metrics, load_gt
    from gcvd_flow.evaluate.synth import render_clip
    from gcvd_flow.io.formats import write_generic_layout

    clip = render_clip(n_frames=6, trajectory="orbit", size=(48, 32), seed=0)
    write_generic_layout(tmp_path / "clip", clip)
    gt = load_gt(tmp_path / "clip")
    assert gt["poses"].shape == (6, 4, 4) and len(gt["depth_files"]) == 6 and gt["depth_scale"] == 1000.0
    frames = [0, 2, 3, 5]  # a strided / trimmed run: matched by source frame index
    res = evaluate(_fake_run(tmp_path, clip, frames, scale=0.3), tmp_path / "clip")
    assert res["frames"] == 4 and res["depth_frames"] == 4 and (res["width"], res["height"]) == (48, 32)
    assert res["ate_rmse"] < 1e-6 and res["scale"] == pytest.approx(1 / 0.3, rel=1e-6)
    assert res["abs_rel"] < 1e-3  # the GT PNGs are rounded to 1 mm
    assert "ATE RMSE" in format_metrics(res) and "AbsRel" in format_metrics(res)


def test_run_eval_confident_pixels(tmp_path):
    """With confidence maps, eval also scores the confident pixels alone: wrong depth that the
    run marked unconfident leaves abs_rel_confident at ~0 while abs_rel sees it."""
    from gcvd_flow.evaluate.run_eval import evaluate, format_metrics
    from gcvd_flow.evaluate.synth import render_clip
    from gcvd_flow.io.formats import write_generic_layout

    clip = render_clip(n_frames=4, trajectory="orbit", size=(48, 32), seed=0)
    write_generic_layout(tmp_path / "clip", clip)
    run = _fake_run(tmp_path, clip, [0, 1, 2, 3])
    assert "abs_rel_confident" not in evaluate(run, tmp_path / "clip")  # run dir without confidence
    (run / "confidence").mkdir()
    for i in range(4):
        d = np.load(run / "depth" / f"{i:06d}.npy")
        d[:, :12] *= 3.0  # a quarter of the frame badly wrong ...
        np.save(run / "depth" / f"{i:06d}.npy", d)
        conf = np.ones_like(d)
        conf[:, :12] = 0.2  # ... and marked unconfident
        np.save(run / "confidence" / f"{i:06d}.npy", conf)
    res = evaluate(run, tmp_path / "clip")
    assert res["abs_rel"] > 0.2 and res["abs_rel_confident"] < 1e-3 and res["delta1_confident"] == 1.0
    assert res["confident_fraction"] == pytest.approx(0.75, abs=0.02) and res["min_confidence"] == 0.5
    assert "AbsRel conf" in format_metrics(res)
    top = res["abs_rel_most_confident"]  # the most confident half never holds the wrong quarter
    assert top["top25"] < 1e-3 and top["top50"] < 1e-3 and top["top75"] < 1e-3


def test_sparsification_ranks_by_confidence():
    """sparsification_abs_rel keeps the most confident share of the pixels: a confidence that
    ranks the error scores ~0 at the top, one that ranks it backwards scores the wrong pixels,
    and a constant one keeps pixel order (deterministic)."""
    from gcvd_flow.evaluate.metrics import depth_metrics, sparsification_abs_rel

    gt = np.full((20, 40), 2.0)
    pred = gt.copy()
    pred[:, 30:] *= np.where(np.arange(20)[:, None] % 2 == 0, 1.5, 0.5)  # the last quarter of the columns wrong
    good = np.where(np.arange(40)[None, :] >= 30, 0.1, 0.9) * np.ones((20, 1))
    ranked = sparsification_abs_rel(pred, gt, good)
    assert ranked["top25"] < 1e-9 and ranked["top75"] < 1e-9
    backwards = sparsification_abs_rel(pred, gt, 1.0 - good)
    assert backwards["top25"] > 0.3 and backwards["top75"] > ranked["top75"] + 0.1
    flat = sparsification_abs_rel(pred, gt, np.ones_like(gt))
    assert flat["top75"] == pytest.approx(depth_metrics(np.where(np.arange(800).reshape(20, 40) < 600, pred, 0), gt)
                                          ["abs_rel"])


def test_run_eval_bad_ground_truth_names_the_file(tmp_path):
    from gcvd_flow.engine.errors import UsageError
    from gcvd_flow.evaluate.run_eval import evaluate, load_gt
    from gcvd_flow.evaluate.synth import render_clip
    from gcvd_flow.io.formats import write_generic_layout

    clip = render_clip(n_frames=4, trajectory="orbit", size=(48, 32), seed=0)
    write_generic_layout(tmp_path / "clip", clip)
    (tmp_path / "clip" / "gt" / "depth_scale").write_text("-5\n")
    with pytest.raises(UsageError, match="depth_scale"):
        load_gt(tmp_path / "clip")
    (tmp_path / "clip" / "gt" / "depth_scale").unlink()
    run = _fake_run(tmp_path, clip, [0, 1, 2, 3])
    with pytest.raises(UsageError, match="ground truth has 3 poses"):
        (tmp_path / "clip" / "gt" / "poses.txt").write_text(
            "\n".join((tmp_path / "clip" / "gt" / "poses.txt").read_text().splitlines()[:3]) + "\n")
        evaluate(run, tmp_path / "clip")
    with pytest.raises(UsageError, match="poses.txt"):
        evaluate(tmp_path / "nope", tmp_path / "clip")


def test_run_eval_against_the_icl_frames_by_index(tmp_path):
    """Redwood / ICL ground truth (a *.log, depth/ PNGs) is matched by source frame index; a run
    made of the ground truth itself (scaled, strided) evaluates to ~0 (the shared data is optional)."""
    import json
    from pathlib import Path

    from gcvd_flow.evaluate.run_eval import evaluate
    from gcvd_flow.io.formats import read_depth_png, read_redwood_log, write_tum_poses

    icl = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "icl_livingroom1_micro"
    if not icl.is_dir():
        pytest.skip(f"{icl} not present (shared ICL-NUIM frames)")
    gt = read_redwood_log(sorted(icl.glob("*.log"))[0])
    frames = list(range(3, 60, 7))
    run = tmp_path / "run"
    (run / "depth").mkdir(parents=True)
    P = gt[frames].copy()
    P[:, :3, 3] *= 0.5
    write_tum_poses(run / "poses.txt", np.asarray(frames, np.float64), P)
    for i in frames:
        np.save(run / "depth" / f"{i:06d}.npy", 0.5 * read_depth_png(icl / "depth" / f"{i:05d}.png"))
    (run / "cameras.json").write_text(json.dumps({"width": 640, "height": 480, "frame_indices": frames,
                                                  "K": [[525, 0, 319.5], [0, 525, 239.5], [0, 0, 1]]}))
    res = evaluate(run, icl)
    assert res["association"] == "frame index" and res["frames"] == len(frames) == res["depth_frames"]
    assert res["ate_rmse"] < 1e-9 and res["scale"] == pytest.approx(2.0) and res["abs_rel"] < 1e-6


def test_window_scales_see_scale_drift():
    """A trajectory whose second half is travelled at twice the scale: the windows there need
    half the scale of the first half's; an exact copy has all window scales 1."""
    from gcvd_flow.evaluate.metrics import window_scales

    n = 80
    gt = np.tile(np.eye(4), (n, 1, 1))
    t = np.linspace(0, 1, n)
    gt[:, :3, 3] = np.stack([np.cos(3 * t), np.sin(3 * t), 0.3 * t], 1)
    assert np.allclose(window_scales(gt, gt), 1.0)
    est = gt.copy()
    steps = np.diff(gt[:, :3, 3], axis=0)
    steps[n // 2:] *= 2.0
    est[1:, :3, 3] = gt[0, :3, 3] + np.cumsum(steps, axis=0)
    ws = window_scales(est, gt)
    assert len(ws) == 4 and ws[:2].min() / ws[2:].max() == pytest.approx(2.0, rel=1e-6)
    assert len(window_scales(gt[:30], gt[:30])) == 0
