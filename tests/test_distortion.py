"""Lens distortion: `synth --distortion` renders through OpenCV's radial-tangential model and writes
the coefficients into intrinsics.txt; ingest undistorts each frame with them (and the coefficients
are in each ingest item's key); 4-number intrinsics keep working as before."""

from types import SimpleNamespace

import numpy as np
import pytest
from conftest import cli

from gcvd_flow import pipeline
from gcvd_flow.evaluate.run_eval import sample_source_map
from gcvd_flow.evaluate.synth import render_clip
from gcvd_flow.io.formats import read_distortion_txt, read_intrinsics_txt
from gcvd_flow.io.sources import open_source
from gcvd_flow.stages.frontend.ingest import undistort_frame
from gcvd_flow.stages.frontend.lens import parse_camera

DIST = (-0.28, 0.08, 0.001, -0.0005)


def _interior(img: np.ndarray, border: int = 8) -> np.ndarray:
    m = img.sum(-1) > 0
    m[:border], m[-border:], m[:, :border], m[:, -border:] = False, False, False, False
    return m


def test_undistort_recovers_the_pinhole_frame():
    d = render_clip(2, "loop", size=(160, 120), distortion=DIST)
    p = render_clip(2, "loop", size=(160, 120))
    assert d.distortion == DIST and np.array_equal(d.K, p.K)
    # ground-truth depth is registered to the distorted frames (as a real RGB-D dataset's): seen
    # back through the lens it is the pinhole clip's, and pixel by pixel it is not
    K = d.K
    pos = pipeline.source_positions(_lens_cameras(K, DIST, (160, 120)), (120, 160))
    back = sample_source_map(d.depth[1], pos, (160, 120))
    ok = back > 0
    assert ok.mean() > 0.9
    assert np.median(np.abs(back[ok] / p.depth[1][ok] - 1)) < 1e-6
    assert np.mean(np.abs(d.depth[1] / p.depth[1] - 1)) > 0.02
    K = d.K
    u = undistort_frame(d.frames[1], (K[0, 0], K[1, 1], K[0, 2], K[1, 2]), DIST)
    m = _interior(u)
    assert m.mean() > 0.7
    err_undistorted = np.abs(u.astype(float) - p.frames[1])[m].mean()
    err_distorted = np.abs(d.frames[1].astype(float) - p.frames[1])[m].mean()
    assert err_undistorted < 3.0 < 8.0 < err_distorted, (err_undistorted, err_distorted)


def _lens_cameras(K: np.ndarray, dist: tuple, size: tuple[int, int], work: tuple[int, int] | None = None) -> dict:
    """cameras.json of a run that undistorted frames of ``size`` (w, h) to ``work`` (w, h)."""
    w, h = work or size
    sx, sy = w / size[0], h / size[1]
    Kw = np.array([[K[0, 0] * sx, 0, (K[0, 2] + 0.5) * sx - 0.5], [0, K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5],
                   [0, 0, 1]])
    return {"width": w, "height": h, "K": Kw.tolist(), "source_width": size[0], "source_height": size[1],
            "distortion": list(dist), "distortion_model": "OPENCV",
            "distortion_intrinsics": [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]}


def test_eval_reads_the_ground_truth_depth_through_the_lens(tmp_path):
    """A run of a lens clip writes depth of the pinhole camera; the dataset's depth is registered
    to the distorted frames. `eval` maps it through the run's lens (cameras.json): a run whose
    depth is exactly right scores AbsRel 0.011 (nearest-pixel sampling at edges), 0.056 on this
    lens if compared pixel by pixel."""
    import json

    from gcvd_flow.evaluate.run_eval import evaluate
    from gcvd_flow.io.formats import write_generic_layout, write_tum_poses

    size, work = (160, 120), (128, 96)
    d = render_clip(4, "loop", size=size, distortion=DIST)
    p = render_clip(4, "loop", size=(128, 96), focal=d.K[0, 0] * 0.8)  # the pinhole camera at working size
    write_generic_layout(tmp_path / "clip", d)
    run = tmp_path / "run"
    (run / "depth").mkdir(parents=True)
    write_tum_poses(run / "poses.txt", np.arange(4, dtype=np.float64), d.poses)
    cams = {**_lens_cameras(d.K, DIST, size, work), "frame_indices": [0, 1, 2, 3]}
    (run / "cameras.json").write_text(json.dumps(cams))
    for i in range(4):
        np.save(run / "depth" / f"{i:06d}.npy", p.depth[i].astype(np.float32))
    right = evaluate(run, tmp_path / "clip")["abs_rel"]
    assert right < 0.015  # nearest-pixel sampling (synth's and eval's) at depth edges: 0.011
    (run / "cameras.json").write_text(json.dumps({k: v for k, v in cams.items() if not k.startswith("distortion")}))
    assert evaluate(run, tmp_path / "clip")["abs_rel"] > 3 * right  # 0.056


def test_parse_eight_numbers():
    cam = parse_camera("100,101,50,40,-0.28,0.08,0,0")
    assert cam.intrinsics == (100.0, 101.0, 50.0, 40.0)
    assert (cam.model, cam.coeffs) == ("OPENCV", (-0.28, 0.08, 0.0, 0.0))
    assert not parse_camera("100,101,50,40").distorted
    assert not parse_camera("100,101,50,40,0,0,0,0").distorted  # all zero: nothing to undistort
    with pytest.raises(ValueError, match="k1,k2,p1,p2"):
        parse_camera("1,2,3,4,5")


def test_synth_writes_and_ingest_applies_the_distortion(tmp_path):
    out = tmp_path / "clip"
    r = cli("synth", str(out), "--frames", "3", "--size", "96x72", "--trajectory", "loop",
            "--distortion=" + ",".join(str(v) for v in DIST))
    assert r.returncode == 0, r.stderr
    assert np.allclose(read_distortion_txt(out / "intrinsics.txt"), DIST)
    K = read_intrinsics_txt(out / "intrinsics.txt")
    src = open_source(str(out))
    assert src.distortion == pytest.approx(DIST)
    cfg = pipeline.GCVDConfig()
    items = pipeline._ingest_items(SimpleNamespace(source=src), cfg.ingest)
    assert items[0]["undistort"].value[1] == pytest.approx(list(DIST))  # in the item's key
    assert items[0]["undistort"].value[2] == "OPENCV"
    it = items[1]
    img = pipeline.run_ingest({"frame": it["frame"].loader(), "source_size": it["source_size"].value,
                               "name": "f", "undistort": it["undistort"].value}, cfg.ingest, None)["image"]
    raw = it["frame"].loader()
    expect = undistort_frame(raw, (K[0, 0], K[1, 1], K[0, 2], K[1, 2]), DIST)
    assert np.array_equal(img, expect) and not np.array_equal(img, raw)
    # --intrinsics with 4 numbers: no undistortion, items keyed as before
    cfg4 = pipeline.GCVDConfig(ingest={"intrinsics": f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}"})
    assert "undistort" not in pipeline._ingest_items(SimpleNamespace(source=src), cfg4.ingest)[0]


def test_bad_distortion_is_one_line_exit_2(tmp_path):
    r = cli("synth", str(tmp_path / "x"), "--frames", "2", "--distortion", "0.1,0.2")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr


QUICK = ["--set", "optimize_keyframes.steps=2", "--set", "optimize_edges.steps=2",
         "--set", "optimize_segments.steps=2", "--set", "depth_fusion.enabled=false"]


@pytest.mark.slow
def test_export_ships_undistorted_frames_with_a_pinhole_camera(tmp_path):
    """A run of a distorted clip (coefficients in intrinsics.txt) exported to COLMAP at the source
    resolution: the images are the undistorted source frames, the camera PINHOLE with the source
    intrinsics, and pycolmap loads the model with the points reprojecting onto the images."""
    pycolmap = pytest.importorskip("pycolmap")
    import cv2
    from conftest import cli_json

    clip, run_dir, out = tmp_path / "clip", tmp_path / "run", tmp_path / "exp"
    cli("synth", str(clip), "--frames", "8", "--size", "96x72", "--trajectory", "loop",
        "--distortion=" + ",".join(str(v) for v in DIST), check=True)
    cli_json("run", str(clip), "--out", str(run_dir), "--cache", str(tmp_path / "cache"), *QUICK,
             "--set", "ingest.long_side=64")
    cams = __import__("json").loads((run_dir / "cameras.json").read_text())
    assert cams["frames_undistorted"] and cams["distortion"] == pytest.approx(list(DIST))
    cli_json("export", str(run_dir), "--format", "colmap", "--to", str(out))
    K = read_intrinsics_txt(clip / "intrinsics.txt")
    rec = pycolmap.Reconstruction(str(out / "colmap/sparse/0"))
    cam = rec.cameras[1]
    assert cam.model.name == "PINHOLE" and (cam.width, cam.height) == (96, 72)
    np.testing.assert_allclose(cam.params, [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5], rtol=1e-9)
    rec.update_point_3d_errors()
    assert rec.compute_mean_reprojection_error() < 1.0
    src = cv2.imread(str(clip / "frames" / "000003.png"))[..., ::-1]
    got = cv2.imread(str(out / "images/000003.png"))[..., ::-1]
    np.testing.assert_array_equal(got, undistort_frame(src, (K[0, 0], K[1, 1], K[0, 2], K[1, 2]), DIST))


def test_undistortion_is_bicubic_and_closer_to_the_pinhole_frame_than_bilinear():
    """A fisheye lens stretches its periphery by up to ~1.4x when undistorted: bilinear resampling
    blurs the frame (a fisheye clip's depth AbsRel 1.11x the pinhole clip's), bicubic keeps it
    nearer the pinhole render (1.01x; docs/log/2026-11-28-cams3.md). Fails if ingest goes back
    to bilinear."""
    import cv2

    from gcvd_flow.stages.frontend import lens

    fish = (0.03, -0.01, 0.004, -0.001)
    d = render_clip(2, "loop", size=(256, 192), distortion=fish, distortion_model="OPENCV_FISHEYE")
    p = render_clip(2, "loop", size=(256, 192))
    K = d.K
    cam = lens.make_camera((K[0, 0], K[1, 1], K[0, 2], K[1, 2]), "OPENCV_FISHEYE", fish)
    ours = lens.undistort_image(d.frames[1], cam)
    mx, my = lens.undistort_maps(cam, (256, 192))
    bilinear = cv2.remap(np.ascontiguousarray(d.frames[1]), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    m = _interior(p.frames[1])
    err_ours = np.abs(ours.astype(float) - p.frames[1])[m].mean()
    err_bilinear = np.abs(bilinear.astype(float) - p.frames[1])[m].mean()
    assert err_ours < 0.85 * err_bilinear, (err_ours, err_bilinear)
