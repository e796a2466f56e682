"""Tests for gcvd_flow.io.formats: roundtrips, layout, malformed input, the shared ICL log."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import numpy as np
import pytest

from gcvd_flow.engine.errors import UsageError
from gcvd_flow.evaluate.synth import render_clip
from gcvd_flow.io import formats as ds

ICL = Path("/work/shared/data/icl_livingroom1_micro")


def _random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    P = np.tile(np.eye(4), (n, 1, 1))
    P[:, :3, :3] = ds.quat_to_rotmat(q)
    P[:, :3, 3] = rng.uniform(-5, 5, (n, 3))
    return P


def test_quaternion_roundtrip_including_180_degrees():
    P = _random_poses(200)
    R = P[:, :3, :3]
    # Near-180-degree rotations are the hard case for trace-based conversions.
    R = np.concatenate([R, np.diag([1.0, -1, -1])[None], np.diag([-1.0, 1, -1])[None], np.diag([-1.0, -1, 1])[None]])
    q = ds.rotmat_to_quat(R)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    assert np.all(q[:, 3] >= 0)
    np.testing.assert_allclose(ds.quat_to_rotmat(q), R, atol=1e-12)
    # TUM order is (qx, qy, qz, qw): 90 deg about z.
    Rz = ds.quat_to_rotmat(np.array([0, 0, np.sqrt(0.5), np.sqrt(0.5)]))
    np.testing.assert_allclose(Rz, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)


def test_tum_roundtrip(tmp_path):
    P = _random_poses(50, seed=1)
    ts = np.arange(50, dtype=np.float64) * 0.5 + 0.25
    f = tmp_path / "sub" / "poses.txt"
    ds.write_tum_poses(f, ts, P)
    ts2, P2 = ds.read_tum_poses(f)
    np.testing.assert_array_equal(ts2, ts)
    np.testing.assert_allclose(P2, P, atol=1e-8, rtol=0)  # %.9f: 5e-10 per printed value
    np.testing.assert_allclose(P2[:, :3, 3], P[:, :3, 3], atol=1e-9, rtol=0)


def test_depth_png_roundtrip(tmp_path):
    rng = np.random.default_rng(0)
    d = rng.uniform(0.1, 9.0, (12, 16)).astype(np.float32)
    d[0, 0] = 0.0
    d[0, 1] = np.nan
    d[0, 2] = 70.0  # beyond uint16 millimetres: clipped to 65535, counted
    d[0, 3] = 1e-4  # valid but < 0.5 mm: 1 mm, never 0 (= invalid)
    assert ds.write_depth_png(tmp_path / "000000.png", d) == 1
    assert ds.write_depth_png(tmp_path / "000001.png", d * 0.5) == 0  # 0.5 * 70 m = 35 m fits
    seq = ds.read_depth_pngs(tmp_path)
    assert len(seq) == 2 and [p.name for p in seq.paths] == ["000000.png", "000001.png"]
    back = seq[0]
    assert back.dtype == np.float32 and back.shape == d.shape
    ok = np.isfinite(d) & (d > 0.001) & (d < 65)
    assert np.all(np.abs(back[ok] - d[ok]) <= 0.0005 + 1e-6)  # rounding to 1 mm
    assert back[0, 0] == 0 and back[0, 1] == 0  # invalid -> 0
    assert back[0, 2] == np.float32(65.535) and back[0, 3] == np.float32(0.001)
    assert seq.load_all().shape == (2, 12, 16)


def test_depth_to_png16_clipping_scale_and_invalid():
    d = np.array([[0.0, np.nan, -1.0, 1e-4, np.inf], [1.2345, 65.5354, 65.5356, 70.0, 2.0]], np.float32)
    png, clipped = ds.depth_to_png16(d)
    assert png.dtype == np.uint16
    assert png[0].tolist() == [0, 0, 0, 1, 0]  # invalid -> 0, tiny valid depth -> 1
    assert png[1].tolist() == [round(float(np.float32(1.2345)) * 1000), 65535, 65535, 65535, 2000]
    assert clipped == 2  # 65.5356 m and 70 m round above 65535 mm; 65.5354 m rounds to 65535
    png2, clipped2 = ds.depth_to_png16(d, scale=500.0)  # half-millimetre units of depth / 2
    assert clipped2 == 0 and png2[1, 3] == 35000 and png2[0, 3] == 1
    # the export's depth-png is the same conversion (one writer per format)
    from gcvd_flow.exports.depth_png import depth_to_mm16

    mm, c = depth_to_mm16(d, depth_scale=0.5)
    np.testing.assert_array_equal(mm, png2)
    assert c == clipped2


def test_png_bytes_is_the_one_encoder(tmp_path):
    import cv2

    rgb = np.random.default_rng(1).integers(0, 256, (9, 7, 3), dtype=np.uint8)
    ds.write_rgb_png(tmp_path / "a.png", rgb)
    assert (tmp_path / "a.png").read_bytes() == ds.png_bytes(rgb)
    np.testing.assert_array_equal(ds.read_rgb(tmp_path / "a.png"), rgb)  # RGB in, RGB out
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "a.png"))[..., ::-1], rgb)  # BGR on disk
    d16 = np.array([[0, 1, 65535]], np.uint16)
    back = cv2.imdecode(np.frombuffer(ds.png_bytes(d16), np.uint8), cv2.IMREAD_UNCHANGED)
    assert back.dtype == np.uint16 and back.tolist() == d16.tolist()
    m = np.eye(4, dtype=bool)
    ds.write_mask_png(tmp_path / "m.png", m)
    np.testing.assert_array_equal(ds.read_mask_png(tmp_path / "m.png"), m)


def test_generic_layout_roundtrip_and_deterministic_bytes(tmp_path):
    clip = render_clip(n_frames=4, trajectory="orbit", size=(48, 32), moving_object=True, seed=2)
    a, b = tmp_path / "a", tmp_path / "b"
    ds.write_generic_layout(a, clip)
    ds.write_generic_layout(b, clip)

    def digest(root: Path) -> dict[str, str]:
        return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*")) if p.is_file()}

    da = digest(a)
    assert da == digest(b)
    assert {"frames/000000.png", "intrinsics.txt", "gt/poses.txt", "gt/depth/000003.png", "gt/dynamic/000003.png"} <= set(da)

    lay = ds.read_generic_layout(a)
    assert len(lay.frame_paths) == 4
    np.testing.assert_array_equal(lay.load_frames(), clip.frames)  # PNG is lossless
    np.testing.assert_allclose(lay.K, clip.K, atol=1e-9)
    np.testing.assert_array_equal(lay.timestamps, np.arange(4.0))
    np.testing.assert_allclose(lay.poses, clip.poses, atol=1e-8)
    assert np.max(np.abs(lay.depth.load_all() - clip.depth)) <= 0.0005 + 1e-6
    np.testing.assert_array_equal(lay.load_dynamic(), clip.dynamic)


def test_intrinsics_formats(tmp_path):
    f = tmp_path / "intrinsics.txt"
    f.write_text("525 526 319.5 239.5\n")
    np.testing.assert_array_equal(ds.read_intrinsics_txt(f), [[525, 0, 319.5], [0, 526, 239.5], [0, 0, 1]])
    f.write_text("525 0 319.5\n0 526 239.5\n0 0 1\n")
    np.testing.assert_array_equal(ds.read_intrinsics_txt(f), [[525, 0, 319.5], [0, 526, 239.5], [0, 0, 1]])


@pytest.mark.parametrize(
    "reader, text, fragment",
    [
        (ds.read_tum_poses, "0 1 2 3 0 0 0 1\n1 1 2 3 0 0 1\n", "line 2"),
        (ds.read_tum_poses, "0 1 2 3 0 0 0 1\n1 1 2 x 0 0 0 1\n", "not numeric"),
        (ds.read_tum_poses, "0 1 2 3 0 0 0 0.2\n", "quaternion"),
        (ds.read_tum_poses, "# only a comment\n", "no poses"),
        (ds.read_redwood_log, "0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n", "5 lines per pose"),
        (ds.read_redwood_log, "0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1\n0 0 0 1\n", "line 4"),
        (ds.read_intrinsics_txt, "525 525 319.5\n", "fx,fy,cx,cy"),
        (ds.read_intrinsics_txt, "-1 525 319.5 239.5\n", "positive"),
        (ds.read_intrinsics_txt, "525 0 319.5\n0 -525 239.5\n0 0 1\n", "positive"),
        (ds.read_intrinsics_txt, "nan 525 319.5 239.5\n", "non-finite"),
        (ds.read_intrinsics_txt, "525 525 inf 239.5\n", "non-finite"),
    ],
)
def test_malformed_files_name_the_file(tmp_path, reader, text, fragment):
    f = tmp_path / "bad_file.txt"
    f.write_text(text)
    with pytest.raises(ds.DatasetError) as ei:
        reader(f)
    msg = str(ei.value)
    assert str(f) in msg and fragment in msg
    assert isinstance(ei.value, ValueError) and isinstance(ei.value, UsageError)


def test_missing_and_non_depth_files(tmp_path):
    with pytest.raises(ds.DatasetError, match="missing.txt"):
        ds.read_tum_poses(tmp_path / "missing.txt")
    ds.write_rgb_png(tmp_path / "rgb.png", np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(ds.DatasetError, match="rgb.png"):
        ds.read_depth_png(tmp_path / "rgb.png")
    with pytest.raises(ds.DatasetError, match="nope"):
        ds.read_depth_pngs(tmp_path / "nope")


def test_layout_count_mismatch_is_reported(tmp_path):
    clip = render_clip(n_frames=3, trajectory="rotation", size=(32, 24), seed=0)
    ds.write_generic_layout(tmp_path, clip)
    (tmp_path / "gt" / "depth" / "000002.png").unlink()
    with pytest.raises(ds.DatasetError, match="2 depth maps for 3 frames"):
        ds.read_generic_layout(tmp_path)


def test_icl_redwood_log():
    log = ICL / "trajectory_open3d_slac.log"
    if not log.exists():
        pytest.skip(f"shared ICL micro data set not present ({log})")
    P = ds.read_redwood_log(log)
    assert P.shape == (211, 4, 4)
    np.testing.assert_allclose(P[:, 3], np.tile([0, 0, 0, 1.0], (211, 1)), atol=1e-6)
    R = P[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-4)
    # First pose is (near) identity in this file; the camera moves a few metres overall.
    np.testing.assert_allclose(P[0], np.eye(4), atol=1e-3)
    assert 1.0 < np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1).sum() < 10.0


@pytest.mark.parametrize("text, fragment", [("nan 75 31.5 23.5\n", "non-finite"),
                                            ("-75 75 31.5 23.5\n", "focal lengths must be positive"),
                                            ("75 75 31.5\n", "fx,fy,cx,cy")])
def test_garbage_intrinsics_txt_stops_the_run_in_one_line(tmp_path, text, fragment):
    from conftest import cli

    clip = render_clip(n_frames=3, trajectory="rotation", size=(32, 24), seed=0)
    ds.write_generic_layout(tmp_path / "clip", clip)
    (tmp_path / "clip" / "intrinsics.txt").write_text(text)
    p = cli("run", str(tmp_path / "clip"), "--out", str(tmp_path / "run"), "--cache", str(tmp_path / "cache"))
    assert p.returncode == 2, p.stderr
    err = p.stderr.strip().splitlines()
    assert len(err) == 1 and str(tmp_path / "clip" / "intrinsics.txt") in err[0] and fragment in err[0], err
    assert not (tmp_path / "run" / "poses.txt").exists()


def test_sources_read_intrinsics_with_the_formats_reader(tmp_path):
    from gcvd_flow.io.sources import open_source

    clip = render_clip(n_frames=3, trajectory="rotation", size=(32, 24), seed=0)
    ds.write_generic_layout(tmp_path, clip)
    (tmp_path / "intrinsics.txt").write_text("30 0 15.5\n0 31 11.5\n0 0 1\n")  # a 3x3 matrix
    src = open_source(str(tmp_path))
    assert src.intrinsics == (30.0, 31.0, 15.5, 11.5) and src.intrinsics_origin == "intrinsics.txt"
    np.testing.assert_array_equal(src.items[1].loader(), clip.frames[1])  # frames read by formats.read_rgb


# ------------------------------------------------------------------------------ TUM timestamps

N_TUM, T0, RATE = 14, 1305031102.175304, 30.0
TUM_QUICK = ["--set", "optimize_keyframes.steps=2", "--set", "optimize_edges.steps=2",
             "--set", "optimize_segments.steps=2", "--set", "depth_fusion.enabled=false"]


def _tum_folder(root: Path, clip) -> Path:
    """A TUM RGB-D folder of a synthetic clip: rgb.txt / depth.txt (depth stamped 4 ms later, in
    1/5000 m) and a groundtruth.txt that also has decoy poses between the frames."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb, dep, gt = ["# color images"], ["# depth maps"], ["# timestamp tx ty tz qx qy qz qw"]
    q = ds.rotmat_to_quat(clip.poses[:, :3, :3])
    for i in range(len(clip.frames)):
        t = T0 + i / RATE
        ds.write_rgb_png(root / "rgb" / f"{t:.6f}.png", clip.frames[i])
        ds.write_depth_png(root / "depth" / f"{t + 0.004:.6f}.png", clip.depth[i], scale=5000.0)
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        dep.append(f"{t + 0.004:.6f} depth/{t + 0.004:.6f}.png")
        gt.append(f"{t + 0.003:.4f} " + " ".join(f"{v:.9f}" for v in (*clip.poses[i, :3, 3], *q[i])))
        gt.append(f"{t + 0.5 / RATE:.4f} 9 9 9 0 0 0 1")  # 16.7 ms away: never the nearest
    for name, lines in (("rgb.txt", rgb), ("depth.txt", dep), ("groundtruth.txt", gt)):
        (root / name).write_text("\n".join(lines) + "\n")
    return root


def test_tum_rgbd_stamps_in_poses_txt_and_eval_by_timestamp(tmp_path):
    """poses.txt carries rgb.txt's stamps (evo associates it with groundtruth.txt out of the box),
    cameras.json the frame indices; eval matches TUM ground truth by nearest stamp (<= 0.01 s, evo's
    default); the MCAP export logs at those stamps."""
    import json

    from conftest import cli, cli_json
    from evo.core import sync
    from evo.tools import file_interface

    from gcvd_flow.evaluate.run_eval import evaluate
    from gcvd_flow.io.formats import write_generic_layout

    clip = render_clip(n_frames=N_TUM, trajectory="loop", size=(96, 72), seed=0)
    tum = _tum_folder(tmp_path / "tum", clip)
    K = clip.K
    run = tmp_path / "run"
    cli("run", str(tum), "--out", str(run), "--cache", str(tmp_path / "cache"), *TUM_QUICK,
        "--intrinsics", f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}", check=True)
    stamps, _ = ds.read_tum_poses(run / "poses.txt")
    np.testing.assert_allclose(stamps, T0 + np.arange(N_TUM) / RATE, atol=2e-6)
    cams = json.loads((run / "cameras.json").read_text())
    assert cams["frame_indices"] == list(range(N_TUM)) and cams["timestamp_kind"] == "seconds"
    ref = file_interface.read_tum_trajectory_file(str(tum / "groundtruth.txt"))
    est = file_interface.read_tum_trajectory_file(str(run / "poses.txt"))
    ref_a, _ = sync.associate_trajectories(ref, est)  # evo's default max_diff
    assert ref_a.num_poses == N_TUM and np.all(ref_a.positions_xyz < 5)  # no decoy matched
    res = cli_json("eval", str(run), "--gt", str(tum))
    assert res["association"] == "timestamp" and res["frames"] == N_TUM and res["depth_frames"] == N_TUM
    write_generic_layout(tmp_path / "generic", clip)  # the same ground truth, matched by index
    by_index = evaluate(run, tmp_path / "generic")
    assert by_index["association"] == "frame index"
    assert res["ate_rmse"] == pytest.approx(by_index["ate_rmse"], rel=1e-6)
    assert res["abs_rel"] == pytest.approx(by_index["abs_rel"], abs=2e-3)  # 0.2 vs 1 mm quantisation
    # ground truth 15 ms off: evo's default (max_diff 0.01 s) matches nothing, and neither does eval
    late = tmp_path / "late"
    shutil.copytree(tum, late)
    (late / "groundtruth.txt").write_text("".join(
        f"{t + 0.015:.6f} " + " ".join(f"{v:.9f}" for v in (*clip.poses[i, :3, 3], *ds.rotmat_to_quat(
            clip.poses[i:i + 1, :3, :3])[0])) + "\n" for i, t in enumerate(T0 + np.arange(N_TUM) / RATE)))
    with pytest.raises(sync.SyncException):  # evo: "found no matching timestamps"
        sync.associate_trajectories(file_interface.read_tum_trajectory_file(str(late / "groundtruth.txt")), est)
    p = cli("eval", str(run), "--gt", str(late))
    assert p.returncode == 2 and "0 of the run's 14 timestamps" in p.stderr
    # the MCAP export logs each frame at its rgb.txt stamp, not at frame index / 30
    from mcap.reader import make_reader

    cli("export", str(run), "--format", "mcap", "--to", str(tmp_path / "exp"), "--cache", str(tmp_path / "cache"),
        check=True)
    with open(tmp_path / "exp" / "run.mcap", "rb") as f:
        times = [m.log_time for _, ch, m in make_reader(f).iter_messages() if ch.topic == "/tf"]
    np.testing.assert_array_equal(times, [round(t * 1e9) for t in cams["timestamps"]])


def test_associate_is_nearest_within_max_diff():
    from gcvd_flow.evaluate.run_eval import associate

    ref = np.array([10.0, 10.03, 10.05, 10.2, 9.99])
    got = associate(np.array([10.0, 10.021, 10.1, 10.19, 9.5]), ref)
    assert got.tolist() == [0, 1, -1, 3, -1]
    assert associate(np.array([1.0]), np.zeros(0)).tolist() == [-1]


def test_video_poses_are_stamped_index_over_fps(tmp_path):
    import json

    import cv2
    from conftest import cli

    clip = render_clip(n_frames=12, trajectory="orbit", size=(96, 72), seed=1)
    video = tmp_path / "clip.mp4"
    wr = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (96, 72))
    if not wr.isOpened():
        pytest.skip("this OpenCV build cannot write mp4")
    for f in clip.frames:
        wr.write(np.ascontiguousarray(f[..., ::-1]))
    wr.release()
    run = tmp_path / "run"
    cli("run", str(video), "--out", str(run), "--cache", str(tmp_path / "cache"), *TUM_QUICK,
        "--set", "ingest.start=2", "--set", "ingest.stride=2", check=True)
    stamps, _ = ds.read_tum_poses(run / "poses.txt")
    cams = json.loads((run / "cameras.json").read_text())
    assert cams["frame_indices"] == [2, 4, 6, 8, 10] and cams["fps"] == pytest.approx(10.0)
    np.testing.assert_allclose(stamps, np.array([2, 4, 6, 8, 10]) / 10.0, atol=1e-6)
