"""Forward driving (issue 37): the camera moves along its optical axis (epipole inside the image,
large depth range), as on KITTI. Each test fails without its mechanism."""

from __future__ import annotations

import numpy as np

from stages.frontend.ingest import working_size
from stages.optimize.init import two_view_pose


def test_wide_frames_keep_half_the_long_side_as_rows() -> None:
    """A 1226x370 driving camera at the default 256 px long side kept 78 rows: forward motion's
    parallax was then too few pixels for bundle adjustment to hold the scale (KITTI 07 0-99:
    keyframe ATE 0.70 m before bundle adjustment, 1.80 m after; at 400x120, 0.76 -> 0.66 m).
    The short side is now at least half the long side; frames up to 2:1 keep their size."""
    from gcvd_flow.engine.config import build_config
    from gcvd_flow.pipeline import PROFILES, GCVDConfig

    frac = build_config(GCVDConfig, PROFILES).ingest.min_short_frac
    assert frac == 0.5
    assert working_size(1226, 370, 256, frac) == (424, 128)
    assert working_size(370, 1226, 256, frac) == (128, 424)
    for src, work in (((640, 480), (256, 192)), ((540, 360), (256, 170)), ((1920, 1080), (256, 144))):
        assert working_size(*src, 256, frac) == work == working_size(*src, 256)
    assert working_size(300, 50, 256, frac) == (300, 50)  # never past the source
    assert build_config(GCVDConfig, PROFILES, profile="paper").ingest.min_short_frac == 0.0  # the paper's 384 px


def _forward_flow(K: np.ndarray, depth: np.ndarray, T_b_a: np.ndarray) -> np.ndarray:
    """Exact flow (H, W, 2) of a static scene with z-depth ``depth`` (H, W) seen from camera a,
    moved into camera b by T_b_a."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    X = (np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T) * depth[..., None]
    Xb = X @ T_b_a[:3, :3].T + T_b_a[:3, 3]
    x = Xb @ K.T
    return (x[..., :2] / x[..., 2:] - np.stack([u, v], -1)).astype(np.float32)


def test_two_view_forward_motion_is_not_taken_for_a_rotation() -> None:
    """Driving along the optical axis towards a far scene (KITTI at 256x78: 0.3 m steps, a street
    10-80 m away): the image zooms about the epipole by ~1 px over most of the frame, so one
    homography fits 95 % of the pixels within 1 px and its singular values pass the rotation
    test; the old test then dropped the translation (zero baseline, no triangulation). The
    rotation itself must explain the flow: here it leaves ~3 px, so the pair keeps its forward
    translation."""
    from scipy.spatial.transform import Rotation

    K = np.array([[147.6, 0, 125.3], [0, 149.1, 38.2], [0, 0, 1]])
    v, u = np.mgrid[0:78, 0:256].astype(np.float64)
    # a street: road below the horizon (camera 1.65 m high), facades 12 m to either side, far end at 80 m
    ray_y, ray_x = (v - K[1, 2]) / K[1, 1], (u - K[0, 2]) / K[0, 0]
    z_road = np.where(ray_y > 0, 1.65 / np.maximum(ray_y, 1e-9), np.inf)
    z_wall = 12.0 / np.maximum(np.abs(ray_x), 1e-9)
    depth = np.minimum(np.minimum(z_road, z_wall), 80.0)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("y", 0.4, degrees=True).as_matrix()
    T[:3, 3] = T[:3, :3] @ np.array([0.0, 0.0, -0.25])  # camera b is 0.25 m ahead of a
    flow = _forward_flow(K, depth, T)
    T_est, corr = two_view_pose(flow, np.ones(depth.shape, bool), K)
    assert corr is not None, "forward motion taken for a rotation"
    t = T_est[:3, 3] / np.linalg.norm(T_est[:3, 3])
    assert t @ (T[:3, 3] / np.linalg.norm(T[:3, 3])) > np.cos(np.radians(3.0))
    np.testing.assert_allclose(T_est[:3, :3], T[:3, :3], atol=2e-3)
