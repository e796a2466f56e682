"""benchmarks/bench_orientation.py turns a clip by quarter turns: its frames, intrinsics and
ground-truth poses must stay one camera (a wrong turn would score the method against a
different trajectory and read as the method's error)."""

from __future__ import annotations

import importlib.util

import cv2
import numpy as np
import pytest
from conftest import ROOT


def _bench():
    spec = importlib.util.spec_from_file_location("bench_orientation", ROOT / "benchmarks" / "bench_orientation.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("turns", [1, 2, 3])
def test_turn_pixel_is_where_cv2_rotate_moves_a_pixel(turns):
    b = _bench()
    w, h = 7, 5
    img = np.zeros((h, w), np.uint8)
    for u, v in [(0, 0), (6, 1), (2, 4), (3, 2)]:
        img[:] = 0
        img[v, u] = 255
        vv, uu = np.argwhere(cv2.rotate(img, b._CODES[turns]) == 255)[0]
        assert b.turn_pixel(u, v, w, h, turns) == (uu, vv)


@pytest.mark.parametrize("turns", [0, 1, 2, 3])
def test_turned_camera_projects_every_point_where_the_image_turn_sends_it(turns):
    """A world point seen by the original camera at pixel p is seen by the turned camera (turned
    K, camera-to-world rotation R M) at turn_pixel(p)."""
    b = _bench()
    rng = np.random.default_rng(turns)
    w, h = 540, 360
    fx, fy, cx, cy = 495.6, 495.5, 269.5, 169.2
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    t = rng.normal(size=3)
    pts_cam = np.c_[rng.uniform(-1, 1, (20, 2)), rng.uniform(2, 5, 20)]
    pts_w = pts_cam @ R.T + t
    u, v = fx * pts_cam[:, 0] / pts_cam[:, 2] + cx, fy * pts_cam[:, 1] / pts_cam[:, 2] + cy
    fx2, fy2, cx2, cy2 = b.turned_intrinsics(fx, fy, cx, cy, w, h, turns)
    R2 = R @ b.camera_turn(turns)
    p2 = (pts_w - t) @ R2  # world -> turned camera
    u2, v2 = fx2 * p2[:, 0] / p2[:, 2] + cx2, fy2 * p2[:, 1] / p2[:, 2] + cy2
    eu, ev = b.turn_pixel(u, v, w, h, turns)
    assert np.allclose(u2, eu, atol=1e-9) and np.allclose(v2, ev, atol=1e-9)


def test_turn_clip_writes_one_consistent_camera(tmp_path):
    b = _bench()
    src = tmp_path / "src"
    (src / "frames").mkdir(parents=True)
    (src / "gt" / "depth").mkdir(parents=True)
    img = np.zeros((4, 6, 3), np.uint8)
    img[1, 5] = 200
    cv2.imwrite(str(src / "frames" / "000000.png"), img)
    cv2.imwrite(str(src / "gt" / "depth" / "000000.png"), (img[..., 0].astype(np.uint16) * 10))
    (src / "intrinsics.txt").write_text("10 11 2.5 1.5\n")
    (src / "gt" / "poses.txt").write_text("0 1 2 3 0 0 0 1\n")
    dst = b.turn_clip(src, tmp_path / "dst", 1)
    out = cv2.imread(str(dst / "frames" / "000000.png"))
    assert out.shape[:2] == (6, 4) and tuple(np.argwhere(out[..., 0] == 200)[0]) == (5, 2)  # (v, u) of turn_pixel(5, 1)
    assert cv2.imread(str(dst / "gt" / "depth" / "000000.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    assert [float(x) for x in (dst / "intrinsics.txt").read_text().split()] == [11, 10, 4 - 1 - 1.5, 2.5]
    from gcvd_flow.io.formats import read_tum_poses

    _, poses = read_tum_poses(dst / "gt" / "poses.txt")
    assert np.allclose(poses[0, :3, 3], [1, 2, 3])  # positions do not turn
    assert np.allclose(poses[0, :3, :3], b.camera_turn(1))
