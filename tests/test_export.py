"""`gcvd-flow export`: every format read back with its own reader and checked against the run.

One tiny synthetic clip (16 frames, 96x72) and one quick run for the whole module; the
properties checked would fail if a convention (w2c vs c2w, OpenGL flip, COLMAP's half-pixel
offset, millimetres, MCAP schemas) or a writer broke.
"""

from __future__ import annotations

import base64
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import cli, cli_json

from gcvd_flow.io.formats import read_tum_poses

N_FRAMES, W, H = 16, 96, 72
SCHEMAS = Path(__file__).resolve().parent.parent / "gcvd_flow" / "exports" / "foxglove_schemas"
# Few optimisation steps: the exports are checked against the run's own outputs, not against
# ground truth. depth_fusion off: its triangulation needs more parallax than this clip has.
QUICK = ["--set", "optimize_keyframes.steps=2", "--set", "optimize_edges.steps=2",
         "--set", "optimize_segments.steps=2", "--set", "depth_fusion.enabled=false"]


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("export")
    clip, run_dir, cache = base / "clip", base / "run", base / "cache"
    cli("synth", str(clip), "--frames", str(N_FRAMES), "--trajectory", "loop", "--size", f"{W}x{H}", check=True)
    cli_json("run", str(clip), "--out", str(run_dir), "--cache", str(cache), *QUICK)
    return {"clip": clip, "run": run_dir, "cache": cache, "base": base}


@pytest.fixture(scope="module")
def exported(run) -> dict:
    out = run["base"] / "exp"
    doc = cli_json("export", str(run["run"]), "--format", "all", "--cache", str(run["cache"]), "--to", str(out))
    return {"out": out, "doc": doc}


def _run_data(run_dir: Path):
    cams = json.loads((run_dir / "cameras.json").read_text())
    _, poses = read_tum_poses(run_dir / "poses.txt")
    depths = [np.load(run_dir / "depth" / f"{i:06d}.npy", allow_pickle=False) for i in cams["frame_indices"]]
    return cams, np.asarray(cams["K"]), poses, depths


def _backproject_all(K, poses, depths) -> np.ndarray:
    pts = []
    for T, d in zip(poses, depths):
        v, u = np.nonzero(np.isfinite(d) & (d > 0))
        z = d[v, u].astype(np.float64)
        cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], 1)
        pts.append(cam @ T[:3, :3].T + T[:3, 3])
    return np.concatenate(pts)


def test_export_all_writes_every_format(exported):
    doc = exported["doc"]
    assert list(doc["formats"]) == ["tum", "depth-png", "colmap", "ply", "tsdf", "nerfstudio", "mcap"]
    assert doc["skipped"] == {} and doc["frames"] == N_FRAMES
    out = exported["out"]
    assert not list(out.rglob(".*.tmp-*")), "temporary files left behind"


def test_tum_is_a_copy(run, exported):
    assert (exported["out"] / "poses.txt").read_bytes() == (run["run"] / "poses.txt").read_bytes()


def _colmap_text(d: Path) -> tuple[list[str], list[str], dict[int, tuple[np.ndarray, list[tuple[int, int]]]]]:
    """(image header lines, POINTS2D lines, {point id: (xyz, track [(image id, point2D idx)])})."""
    lines = [ln for ln in (d / "images.txt").read_text().split("\n") if not ln.startswith("#")]
    pts = {}
    for ln in (d / "points3D.txt").read_text().splitlines():
        if not ln.startswith("#"):
            v = ln.split()
            tr = [int(x) for x in v[8:]]
            pts[int(v[0])] = (np.array([float(x) for x in v[1:4]]), list(zip(tr[0::2], tr[1::2])))
    return lines[0::2][:N_FRAMES], lines[1::2][:N_FRAMES], pts


def test_colmap_model_inverts_to_the_run_poses_and_reprojects(run, exported):
    from gcvd_flow.exports.colmap import colmap_to_c2w

    cams, K, poses, depths = _run_data(run["run"])
    d = exported["out"] / "colmap" / "sparse" / "0"
    cam_line = [ln for ln in (d / "cameras.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(cam_line) == 1
    cid, model, w, h, fx, fy, cx, cy = cam_line[0].split()
    assert (model, int(w), int(h)) == ("PINHOLE", W, H)
    np.testing.assert_allclose([float(fx), float(fy), float(cx), float(cy)],
                               [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5])
    heads, obs, pts = _colmap_text(d)
    assert len(heads) == N_FRAMES
    q = np.array([[float(v) for v in ln.split()[1:5]] for ln in heads])
    t = np.array([[float(v) for v in ln.split()[5:8]] for ln in heads])
    names = [ln.split()[9] for ln in heads]
    assert names == [f"{i:06d}.png" for i in cams["frame_indices"]]
    assert all((exported["out"] / "images" / n).is_file() for n in names)
    np.testing.assert_allclose(colmap_to_c2w(q, t), poses, atol=1e-6)
    assert 1000 < len(pts) <= 25000
    assert np.mean([len(tr) for _, tr in pts.values()]) > 2  # multi-view tracks
    # every observation is the point's projection (COLMAP pixel convention, +0.5), at a pixel where
    # that frame's depth agrees, and the track and POINTS2D refer to each other
    checked = 0
    for img_id in (1, N_FRAMES // 2, N_FRAMES):
        tok = obs[img_id - 1].split()
        for j in range(0, len(tok), 3 * 37):
            x, y, pid = float(tok[j]), float(tok[j + 1]), int(tok[j + 2])
            X, track = pts[pid]
            assert (img_id, j // 3) in track
            w2c = np.linalg.inv(poses[img_id - 1])
            pc = w2c[:3, :3] @ X + w2c[:3, 3]
            uv = (K @ pc)[:2] / pc[2]
            np.testing.assert_allclose(uv + 0.5, [x, y], atol=1e-6)
            dk = depths[img_id - 1][int(round(uv[1])), int(round(uv[0]))]
            assert abs(dk - pc[2]) <= 0.03 * pc[2] + 1e-9
            checked += 1
    assert checked > 5


def test_colmap_text_and_binary_load_in_pycolmap(run, exported, tmp_path):
    """The model as COLMAP reads it (pycolmap): camera, poses, multi-view tracks, reprojection."""
    pycolmap = pytest.importorskip("pycolmap")
    cams, K, poses, _ = _run_data(run["run"])
    out = tmp_path / "bin"
    doc = cli_json("export", str(run["run"]), "--format", "colmap", "--colmap-binary", "--to", str(out),
                   "--cache", str(run["cache"]))
    assert doc["formats"]["colmap"]["binary"] and sorted(p.name for p in (out / "colmap/sparse/0").iterdir()) \
        == ["cameras.bin", "images.bin", "points3D.bin"]
    models = [pycolmap.Reconstruction(str(exported["out"] / "colmap/sparse/0")),
              pycolmap.Reconstruction(str(out / "colmap/sparse/0"))]
    for rec in models:
        cam = rec.cameras[1]
        assert (cam.model_name, cam.width, cam.height) == ("PINHOLE", W, H)
        np.testing.assert_allclose(cam.params, [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5])
        assert rec.num_reg_images() == N_FRAMES and rec.num_points3D() > 1000
        for img in rec.images.values():
            k = cams["frame_indices"].index(int(img.name[:6]))
            w2c = np.eye(4)
            w2c[:3] = img.cam_from_world().matrix()
            np.testing.assert_allclose(np.linalg.inv(w2c), poses[k], atol=1e-6)
        assert rec.compute_mean_track_length() > 2
        rec.update_point_3d_errors()
        assert rec.compute_mean_reprojection_error() < 1.0
    a, b = models
    assert a.num_points3D() == b.num_points3D() and a.compute_num_observations() == b.compute_num_observations()


def test_colmap_export_survives_pycolmap_bundle_adjustment(run, exported):
    """COLMAP's own bundle adjuster accepts the model: every track has two views at least (a
    one-view track made `colmap bundle_adjuster` abort and pycolmap.bundle_adjustment raise), and
    since the observations are the points' projections, adjustment leaves the poses in place."""
    pycolmap = pytest.importorskip("pycolmap")
    _, _, poses, _ = _run_data(run["run"])
    rec = pycolmap.Reconstruction(str(exported["out"] / "colmap/sparse/0"))
    lengths = [p.track.length() for p in rec.points3D.values()]
    assert lengths and min(lengths) >= 2
    opts = pycolmap.BundleAdjustmentOptions()
    pycolmap.bundle_adjustment(rec, opts)
    rec.update_point_3d_errors()
    assert rec.num_points3D() == len(lengths) and rec.compute_mean_reprojection_error() < 1e-3
    for img in rec.images.values():
        w2c = np.eye(4)
        w2c[:3] = img.cam_from_world().matrix()
        k = img.image_id - 1
        np.testing.assert_allclose(np.linalg.inv(w2c)[:3, 3], poses[k][:3, 3], atol=1e-4)


def test_full_res_images_and_scaled_intrinsics(run, tmp_path):
    """A run at 64x48 of the 96x72 clip: colmap and nerfstudio images are the source frames, the
    intrinsics scaled with pixel centres (c' = (c + 0.5) s - 0.5); --no-full-res keeps 64x48; an
    input changed since the run falls back to the working resolution with a warning."""
    pycolmap = pytest.importorskip("pycolmap")
    small = tmp_path / "small"
    cli("run", str(run["clip"]), "--out", str(small), "--cache", str(run["cache"]), *QUICK,
        "--set", "ingest.long_side=64", check=True)
    cams, K, poses, _ = _run_data(small)
    assert (cams["width"], cams["height"]) == (64, 48)
    out = tmp_path / "full"
    doc = cli_json("export", str(small), "--format", "colmap,nerfstudio", "--to", str(out))  # cache from run.json
    assert doc["formats"]["colmap"]["resolution"] == "source" and doc["formats"]["nerfstudio"]["width"] == W
    s = W / 64
    fx, cx, cy = K[0, 0] * s, (K[0, 2] + 0.5) * s, (K[1, 2] + 0.5) * s  # COLMAP / nerfstudio: + 0.5
    rec = pycolmap.Reconstruction(str(out / "colmap/sparse/0"))
    cam = rec.cameras[1]
    assert (cam.width, cam.height) == (W, H)
    np.testing.assert_allclose(cam.params, [fx, fx, cx, cy], rtol=1e-12)
    rec.update_point_3d_errors()
    assert rec.compute_mean_reprojection_error() < 1.0 and rec.compute_mean_track_length() > 2
    ns = json.loads((out / "transforms.json").read_text())
    assert (ns["w"], ns["h"]) == (W, H)
    np.testing.assert_allclose([ns["fl_x"], ns["cx"], ns["cy"]], [fx, cx, cy], rtol=1e-12)
    img = cv2.imread(str(out / "images" / "000003.png"), cv2.IMREAD_COLOR)  # colmap and nerfstudio share images/
    np.testing.assert_array_equal(img, cv2.imread(str(run["clip"] / "frames" / "000003.png"), cv2.IMREAD_COLOR))
    low = cli_json("export", str(small), "--format", "colmap", "--no-full-res", "--to", str(tmp_path / "low"))
    assert (low["formats"]["colmap"]["width"], low["formats"]["colmap"]["resolution"]) == (64, "working")
    moved = tmp_path / "clip-moved"
    shutil.copytree(run["clip"], moved)
    doc = json.loads((small / "run.json").read_text())
    doc["invocation"]["input"] = str(moved)
    (small / "run.json").write_text(json.dumps(doc))
    img = cv2.imread(str(moved / "frames" / "000000.png"))
    cv2.imwrite(str(moved / "frames" / "000000.png"), 255 - img)  # the input changed since the run
    p = cli("export", str(small), "--format", "colmap", "--to", str(tmp_path / "changed"), "--json")
    assert p.returncode == 0 and json.loads(p.stdout)["formats"]["colmap"]["width"] == 64
    assert "changed since the run" in p.stderr


def test_nerfstudio_transforms_flip_back_to_the_poses(run, exported):
    cams, K, poses, _ = _run_data(run["run"])
    out = exported["out"]
    doc = json.loads((out / "transforms.json").read_text())
    assert doc["camera_model"] == "OPENCV" and (doc["w"], doc["h"]) == (W, H)
    np.testing.assert_allclose([doc["fl_x"], doc["fl_y"], doc["cx"], doc["cy"]],
                               [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5])
    assert doc["depth_unit_scale_factor"] == pytest.approx(1e-3)
    assert doc["ply_file_path"] == "points.ply"
    assert len(doc["frames"]) == N_FRAMES
    for k, fr in enumerate(doc["frames"]):
        assert (out / fr["file_path"]).is_file() and (out / fr["depth_file_path"]).is_file()
        gl = np.array(fr["transform_matrix"])
        np.testing.assert_allclose(gl @ np.diag([1, -1, -1, 1]), poses[k], atol=1e-12)
        # OpenGL cameras look down their -z axis: the same world direction as OpenCV's +z
        np.testing.assert_allclose(-gl[:3, 2], poses[k][:3, 2], atol=1e-12)


# nerfstudio's conventions (v1.1.5, nerfstudio/data/dataparsers/), restated for the tests: nerfstudio
# is too heavy to install here. nerfstudio_dataparser.py: ``applied_transform`` (3x4, saved coords
# <- our world) from transforms.json, else, when DATA/colmap/sparse/0 exists, the one old COLMAP
# conversions used. colmap_dataparser.py (defaults images_path "images", colmap_path
# "colmap/sparse/0", assume_colmap_world_coordinate_convention True): c2w = inv(w2c), camera y
# and z columns negated (OpenGL), then world rows (0, 2, 1) with the new z negated, which it
# records as applied_transform.
NS_OLD_COLMAP = np.array([[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, 0]], np.float64)


def _ns_applied_transform(data: Path, meta: dict) -> np.ndarray:
    """nerfstudio_dataparser's applied_transform as a 4x4 (identity when it has none)."""
    a = np.eye(4)
    if "applied_transform" in meta:
        a[:3] = np.asarray(meta["applied_transform"], np.float64)
    elif (data / "colmap/sparse/0").exists():
        a[:3] = NS_OLD_COLMAP
    return a


def _ns_colmap_dataparser(data: Path) -> tuple[list[Path], np.ndarray, np.ndarray]:
    """colmap_dataparser with its defaults: (image files, c2w (N, 4, 4) OpenGL in its coords,
    applied_transform 4x4)."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(data / "colmap/sparse/0"))
    files, c2ws = [], []
    for img_id in sorted(rec.images):
        img = rec.images[img_id]
        w2c = np.eye(4)
        w2c[:3] = img.cam_from_world().matrix()
        c2w = np.linalg.inv(w2c)
        c2w[0:3, 1:3] *= -1
        c2w = c2w[np.array([0, 2, 1, 3]), :]
        c2w[2, :] *= -1
        files.append(data / "images" / img.name)
        c2ws.append(c2w)
    applied = np.eye(4)
    applied[:3] = np.eye(4)[:3][np.array([0, 2, 1]), :]
    applied[2, :] *= -1
    return files, np.array(c2ws), applied


def test_nerfstudio_places_the_scene_in_our_world_beside_a_colmap_export(run, exported):
    """One folder with colmap/ and transforms.json (the README's example): nerfstudio's mapping
    back to the saved world is the identity, not the old COLMAP conversion's axis swap."""
    _, _, poses, _ = _run_data(run["run"])
    out = exported["out"]
    assert (out / "colmap/sparse/0").is_dir()
    meta = json.loads((out / "transforms.json").read_text())
    applied = _ns_applied_transform(out, meta)
    np.testing.assert_array_equal(applied, np.eye(4))
    gl = np.array([fr["transform_matrix"] for fr in meta["frames"]])
    ours = np.linalg.inv(applied) @ gl @ np.diag([1.0, -1, -1, 1])
    np.testing.assert_allclose(ours, poses, atol=1e-12)


def test_nerfstudio_colmap_dataparser_reads_a_colmap_only_export(run, tmp_path):
    """nerfstudio's COLMAP dataparser with its default paths on a COLMAP-only export: every image
    where it looks, and its poses mapped back through its applied_transform are the run's."""
    pytest.importorskip("pycolmap")
    _, _, poses, _ = _run_data(run["run"])
    out = tmp_path / "col"
    cli_json("export", str(run["run"]), "--format", "colmap", "--to", str(out), "--cache", str(run["cache"]))
    files, c2w_ns, applied = _ns_colmap_dataparser(out)
    assert len(files) == N_FRAMES and all(f.is_file() for f in files)
    ours = np.linalg.inv(applied) @ c2w_ns @ np.diag([1.0, -1, -1, 1])
    np.testing.assert_allclose(ours, poses, atol=1e-6)


def test_depth_pngs_are_millimetres(run, exported):
    cams, _, _, depths = _run_data(run["run"])
    for i, d in zip(cams["frame_indices"], depths):
        png = cv2.imread(str(exported["out"] / "depth" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert png.dtype == np.uint16 and png.shape == (H, W)
        valid = np.isfinite(d) & (d > 0)
        assert valid.mean() > 0.5
        assert np.all(np.abs(png[valid].astype(np.float64) - d[valid] * 1000.0) <= 0.5 + 1e-3)
        assert np.all(png[~valid] == 0)


def test_depth_png_scale_clipping_and_invalid():
    from gcvd_flow.exports import depth_to_mm16

    d = np.array([[0.0, np.nan, -1.0, 0.0001], [1.2345, 70.0, np.inf, 2.0]], np.float32)
    mm, clipped = depth_to_mm16(d)
    assert mm[0].tolist() == [0, 0, 0, 1]  # invalid -> 0; valid but < 0.5 mm -> 1, never "invalid"
    assert mm[1].tolist() == [round(float(np.float32(1.2345)) * 1000), 65535, 0, 2000]
    assert clipped == 1
    mm2, _ = depth_to_mm16(d, depth_scale=0.5)
    assert mm2[1, 1] == 35000 and mm2[1, 3] == 1000


def test_ply_points_lie_in_the_backprojected_depth(run, exported):
    import open3d as o3d

    _, K, poses, depths = _run_data(run["run"])
    ref = _backproject_all(K, poses, depths)
    pcd = o3d.io.read_point_cloud(str(exported["out"] / "points.ply"))
    pts = np.asarray(pcd.points)
    assert len(pts) == len(ref) == exported["doc"]["formats"]["ply"]["points"]  # every=1, no voxel grid
    assert pcd.has_colors()
    lo, hi = ref.min(0), ref.max(0)
    tol = 1e-5 * (1 + np.abs(ref).max())
    assert np.all(pts >= lo - tol) and np.all(pts <= hi + tol)
    np.testing.assert_allclose(np.sort(pts[:, 2]), np.sort(ref[:, 2]), atol=1e-5)


def test_tsdf_mesh_lies_on_the_run_depth(run, exported):
    import open3d as o3d
    from scipy.spatial import cKDTree

    _, K, poses, depths = _run_data(run["run"])
    info = exported["doc"]["formats"]["tsdf"]
    mesh = o3d.io.read_triangle_mesh(str(exported["out"] / "mesh.ply"))
    tri, verts = np.asarray(mesh.triangles), np.asarray(mesh.vertices)
    assert len(tri) > 100 and len(tri) == info["triangles"] and mesh.has_vertex_colors()
    voxel = info["voxel_length"]
    med = np.median(np.concatenate([d[np.isfinite(d) & (d > 0)] for d in depths]))
    assert voxel == pytest.approx(med / 100, rel=0.2)  # default: median depth / 100
    ref = _backproject_all(K, poses, depths)
    dist, _ = cKDTree(ref).query(verts[:: max(1, len(verts) // 3000)])
    assert np.median(dist) < 2 * voxel, (np.median(dist), voxel)


def test_mcap_topics_schemas_counts_and_poses(run, exported):
    import jsonschema
    from mcap.reader import make_reader
    from scipy.spatial.transform import Rotation

    cams, K, poses, depths = _run_data(run["run"])
    path = exported["out"] / "run.mcap"
    expected = {"/camera/image": ("foxglove.CompressedImage", N_FRAMES),
                "/camera/depth": ("foxglove.RawImage", N_FRAMES),
                "/camera/confidence": ("foxglove.RawImage", N_FRAMES),  # the run has confidence/
                "/camera/calibration": ("foxglove.CameraCalibration", N_FRAMES),
                "/tf": ("foxglove.FrameTransform", N_FRAMES),
                "/trajectory": ("foxglove.PosesInFrame", 1),
                "/points": ("foxglove.PointCloud", 1)}
    seen: dict[str, list] = {t: [] for t in expected}
    with open(path, "rb") as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            assert schema.name == expected[channel.topic][0]
            # the upstream foxglove-sdk file, byte for byte (vendored, not retyped)
            assert schema.data == (SCHEMAS / f"{schema.name}.json").read_bytes()
            assert json.loads(schema.data)["$comment"] == "Generated by https://github.com/foxglove/foxglove-sdk"
            msg = json.loads(message.data)
            if len(seen[channel.topic]) < 2:
                jsonschema.validate(msg, json.loads(schema.data))
            seen[channel.topic].append((message.log_time, msg))
    assert {t: len(v) for t, v in seen.items()} == {t: n for t, (_, n) in expected.items()}
    # /tf: the camera-to-world pose at frame index / 30 fps (synthetic clips have no fps)
    for k, (t_ns, msg) in enumerate(seen["/tf"]):
        assert t_ns == round(cams["frame_indices"][k] / 30.0 * 1e9)
        assert (msg["parent_frame_id"], msg["child_frame_id"]) == ("world", "camera")
        T = np.eye(4)
        r = msg["rotation"]
        T[:3, :3] = Rotation.from_quat([r["x"], r["y"], r["z"], r["w"]]).as_matrix()
        T[:3, 3] = [msg["translation"][c] for c in "xyz"]
        np.testing.assert_allclose(T, poses[k], atol=1e-9)
    # depth: 32FC1 bytes equal the run's depth exactly
    _, dm = seen["/camera/depth"][3]
    assert dm["encoding"] == "32FC1" and dm["step"] == 4 * W
    d = np.frombuffer(base64.b64decode(dm["data"]), "<f4").reshape(H, W)
    np.testing.assert_array_equal(d, depths[3])
    # image: the PNG decodes to the exported frame
    _, im = seen["/camera/image"][3]
    assert im["format"] == "png"
    rgb = cv2.imdecode(np.frombuffer(base64.b64decode(im["data"]), np.uint8), cv2.IMREAD_COLOR)
    ref = cv2.imread(str(exported["out"] / "images" / f"{cams['frame_indices'][3]:06d}.png"), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(rgb, ref)
    _, cal = seen["/camera/calibration"][0]
    np.testing.assert_allclose(np.reshape(cal["K"], (3, 3)), K)
    _, traj = seen["/trajectory"][0]
    assert len(traj["poses"]) == N_FRAMES
    _, pc = seen["/points"][0]
    assert pc["point_stride"] == 16 and [f["name"] for f in pc["fields"]][:3] == ["x", "y", "z"]
    n_pts = len(base64.b64decode(pc["data"])) // 16
    assert n_pts == exported["doc"]["formats"]["mcap"]["cloud_points"] > 100


def test_exported_images_are_the_runs_frames(run, exported):
    # the cached working-resolution frames; the synthetic clip is already at working resolution
    src = cv2.imread(str(run["clip"] / "frames" / "000005.png"), cv2.IMREAD_COLOR)
    out = cv2.imread(str(exported["out"] / "images" / "000005.png"), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(src, out)


def test_missing_cache_exports_what_it_can_and_fails_in_one_line(run, tmp_path):
    empty = tmp_path / "empty-cache"
    empty.mkdir()
    out = tmp_path / "exp"
    p = cli("export", str(run["run"]), "--format", "tum,colmap,ply", "--cache", str(empty), "--to", str(out))
    assert p.returncode == 2, p.stderr
    err = [ln for ln in p.stderr.splitlines() if ln.startswith("gcvd-flow: error")]
    assert len(err) == 1 and "ply" in err[0] and str(empty) in err[0]
    assert (out / "poses.txt").is_file() and (out / "colmap" / "sparse" / "0" / "images.txt").is_file()
    assert not (out / "points.ply").exists() and not (out / "images").exists()


def _main(capsys, *args: str) -> tuple[int, list[str]]:
    from gcvd_flow.cli import main

    rc = main(list(args))
    return rc, capsys.readouterr().err.strip().splitlines()


def test_bad_inputs_exit_2_with_one_line(run, tmp_path, capsys):
    missing = tmp_path / "nope"
    rc, err = _main(capsys, "export", str(missing), "--format", "tum")
    assert rc == 2 and len(err) == 1 and str(missing) in err[0]

    rc, err = _main(capsys, "export", str(run["run"]), "--format", "obj")
    assert rc == 2 and len(err) == 1 and "'obj'" in err[0]
    rc, err = _main(capsys, "export", str(run["run"]))
    assert rc == 2 and len(err) == 1 and "--format" in err[0]

    bad = tmp_path / "bad"
    shutil.copytree(run["run"], bad)
    (bad / "poses.txt").write_text("0 1 2 3 not-a-number\n")
    rc, err = _main(capsys, "export", str(bad), "--format", "tum", "--to", str(tmp_path / "o1"))
    assert rc == 2 and len(err) == 1 and str(bad / "poses.txt") in err[0]
    assert not (tmp_path / "o1" / "poses.txt").exists()

    shutil.copy(run["run"] / "poses.txt", bad / "poses.txt")
    (bad / "depth" / "000007.npy").unlink()
    rc, err = _main(capsys, "export", str(bad), "--format", "depth-png", "--to", str(tmp_path / "o2"))
    assert rc == 2 and len(err) == 1 and str(bad / "depth" / "000007.npy") in err[0]
    assert not (tmp_path / "o2" / "depth").exists()  # checked before anything is written

    (bad / "depth" / "000007.npy").write_bytes(b"\x93NUMPY garbage")
    rc, err = _main(capsys, "export", str(bad), "--format", "depth-png", "--to", str(tmp_path / "o3"))
    assert rc == 2 and len(err) == 1 and "000007.npy" in err[0]


def test_interrupted_write_leaves_no_file(tmp_path):
    from gcvd_flow.exports import _atomic

    target = tmp_path / "x" / "mesh.ply"
    with pytest.raises(KeyboardInterrupt):
        with _atomic(target) as tmp:
            tmp.write_bytes(b"half a mesh")
            raise KeyboardInterrupt
    assert not target.exists() and list(target.parent.iterdir()) == []
    with _atomic(target) as tmp:
        assert tmp.suffix == ".ply" and tmp.parent == target.parent
        tmp.write_bytes(b"whole")
    assert target.read_bytes() == b"whole" and list(target.parent.iterdir()) == [target]


# ------------------------------------------------------------------------------ pure geometry


def test_colmap_and_opengl_conversions_round_trip():
    from scipy.spatial.transform import Rotation

    from gcvd_flow.exports.colmap import c2w_to_colmap, colmap_to_c2w
    from gcvd_flow.exports.nerfstudio import opencv_to_opengl, opengl_to_opencv

    rng = np.random.default_rng(0)
    rots = Rotation.random(50, random_state=1).as_matrix()
    rots[0] = np.diag([1.0, -1.0, -1.0])  # 180 degrees about x
    c2w = np.tile(np.eye(4), (50, 1, 1))
    c2w[:, :3, :3] = rots
    c2w[:, :3, 3] = rng.normal(size=(50, 3)) * 5
    q, t = c2w_to_colmap(c2w)
    assert np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0)
    np.testing.assert_allclose(colmap_to_c2w(q, t), c2w, atol=1e-12)
    # x_cam = R(q) x_world + t  for the camera centre gives 0
    R = Rotation.from_quat(np.concatenate([q[:, 1:], q[:, :1]], 1)).as_matrix()
    np.testing.assert_allclose(np.einsum("nij,nj->ni", R, c2w[:, :3, 3]) + t, 0, atol=1e-12)
    np.testing.assert_allclose(opengl_to_opencv(opencv_to_opengl(c2w)), c2w)


def test_voxel_accumulator_matches_global_downsampling():
    from gcvd_flow.exports.clouds import VoxelAccumulator

    rng = np.random.default_rng(3)
    pts = rng.uniform(-1, 1, size=(20000, 3))
    cols = rng.integers(0, 256, size=(20000, 3)).astype(np.uint8)
    acc = VoxelAccumulator(0.25)
    for chunk in range(0, 20000, 700):  # > 16 chunks: exercises the periodic merge
        acc.add(pts[chunk:chunk + 700], cols[chunk:chunk + 700])
    got, got_c = acc.result()
    keys = np.floor(pts / 0.25).astype(np.int64)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    ref = np.stack([np.bincount(inv, pts[:, k]) / np.bincount(inv) for k in range(3)], 1)
    assert len(got) == len(uniq) == 512
    order = np.lexsort(np.floor(got / 0.25).T[::-1])
    np.testing.assert_allclose(got[order], ref, atol=1e-12)
    ref_c = np.stack([np.bincount(inv, cols[:, k].astype(float)) / np.bincount(inv) for k in range(3)], 1)
    np.testing.assert_array_equal(got_c[order], np.round(ref_c).astype(np.uint8))


# benchmarks/ba_probe.py on this module's finished run (the run is costly; the probe reads its cache)
def _ba_probe():
    import importlib.util

    from conftest import ROOT

    spec = importlib.util.spec_from_file_location("ba_probe", ROOT / "benchmarks" / "ba_probe.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_ba_probe_reproduces_the_bundle_adjustment_stage_and_parses_its_settings(run):
    """The probe re-adjusts from what the stage read: at the default settings it ends where the
    stage ended (else it reads other inputs, and what it says about a setting is about another
    problem). Its key=value settings take their field's type; an unknown key is exit 2."""
    from gcvd_flow.engine.store import Store
    from gcvd_flow.report.collect import recorded_part

    bp = _ba_probe()
    doc = json.loads((run["run"] / "run.json").read_text())
    store = Store(Path(doc["cache"]), verify=False)
    kfs = [int(i) for i in recorded_part(doc, store, "optimize_keyframes", ("keyframes",))]
    stage = np.asarray(recorded_part(doc, store, "bundle_adjustment", ("poses",)), np.float64)
    from gcvd_flow.evaluate.run_eval import load_gt

    gt_kf = np.asarray(load_gt(run["clip"])["poses"])[kfs]
    out = bp.probe(run["run"], run["clip"], {})
    assert out["after"] == bp.summary(stage, gt_kf, kfs)
    one = bp.probe(run["run"], run["clip"], {"max_iterations": 1})
    assert one["iterations"] == 1 and one["after"] != out["after"]  # the settings reach the adjustment
    assert bp.overrides(["robust_px=1", "enabled=false", "solver=gtsam", "stride=8"]) == \
        {"robust_px": 1.0, "enabled": False, "solver": "gtsam", "stride": 8}
    with pytest.raises(SystemExit) as e:
        bp.overrides(["no_such_key=1"])
    assert e.value.code == 2
