"""Small numpy geometry helpers (no torch): pixel grids, back-projection, exact rigid flow.

Conventions (docs/contributing.md): pixel (u, v) = (column, row), centre of the top-left pixel is
(0, 0); poses are camera-to-world 4x4 in OpenCV camera axes; depth is z-depth in metres.
"""

from __future__ import annotations

import numpy as np

__all__ = ["pixel_grid", "backproject", "project", "rigid_flow", "relative_pose"]


def pixel_grid(h: int, w: int) -> np.ndarray:
    """(H, W, 2) float64 array of pixel coordinates (u, v)."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack([u, v], axis=-1)


def backproject(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame 3D points (H, W, 3) float64 from z-depth (H, W) and intrinsics K (3, 3)."""
    h, w = depth.shape
    uv = pixel_grid(h, w)
    Kinv = np.linalg.inv(np.asarray(K, dtype=np.float64))
    rays = np.concatenate([uv, np.ones((h, w, 1))], axis=-1) @ Kinv.T
    return rays * depth[..., None].astype(np.float64)


def project(points: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project camera-frame points (..., 3) -> (pixels (..., 2), z (...))."""
    p = points @ np.asarray(K, dtype=np.float64).T
    z = points[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = p[..., :2] / p[..., 2:3]
    return uv, z


def relative_pose(pose_a: np.ndarray, pose_b: np.ndarray) -> np.ndarray:
    """T_b<-a (4, 4): maps camera-a coordinates to camera-b coordinates (poses camera-to-world)."""
    return np.linalg.inv(np.asarray(pose_b, np.float64)) @ np.asarray(pose_a, np.float64)


def rigid_flow(
    depth_a: np.ndarray, K: np.ndarray, pose_a: np.ndarray, pose_b: np.ndarray
) -> np.ndarray:
    """Exact flow (H, W, 2) float32 in px induced by camera motion a -> b on a static scene.

    depth_a: (H, W) z-depth of frame a in metres (<= 0 or non-finite = invalid);
    K: (3, 3); pose_a, pose_b: (4, 4) camera-to-world. Pixels with invalid depth or that land
    behind camera b get NaN (callers mask with np.isfinite).
    """
    depth_a = np.asarray(depth_a, dtype=np.float64)
    h, w = depth_a.shape
    X = backproject(depth_a, K)
    T = relative_pose(pose_a, pose_b)
    Xb = X @ T[:3, :3].T + T[:3, 3]
    uv_b, zb = project(Xb, K)
    flow = uv_b - pixel_grid(h, w)
    bad = ~(np.isfinite(depth_a) & (depth_a > 0) & (zb > 1e-9))
    flow[bad] = np.nan
    return flow.astype(np.float32)
