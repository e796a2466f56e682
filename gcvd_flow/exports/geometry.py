"""Pure geometry behind `gcvd-flow export`: point clouds, TSDF meshes, pose conventions.

Arrays in, arrays out, no file I/O (the writers live in ``gcvd_flow/exports.py``).
Conventions as everywhere in ``stages/`` (docs/CONTRACT.md):

- pose: float64 (4, 4) camera-to-world (c2w), OpenCV camera axes (x right, y down, z forward);
  a trajectory is (N, 4, 4);
- depth: float32 (H, W) z-depth in scene units (metres up to one global scale), 0 = invalid;
- image: uint8 (H, W, 3) RGB; K: float64 (3, 3), pixel centre of the top-left pixel at (0, 0).

Other conventions, converted here:

- COLMAP stores world-to-camera (w2c) rotations as Hamilton quaternions (QW, QX, QY, QZ) plus
  the w2c translation; its pixel coordinates put the top-left pixel's *centre* at (0.5, 0.5).
- nerfstudio / NeRF / OpenGL: camera-to-world with camera axes x right, y up, z backward, i.e.
  the OpenCV pose with its y and z columns negated.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

__all__ = [
    "OPENGL_FROM_OPENCV", "opencv_to_opengl", "opengl_to_opencv", "c2w_to_colmap", "colmap_to_c2w",
    "backproject_frame", "VoxelAccumulator", "fuse_point_cloud", "median_depth", "default_voxel",
    "tsdf_mesh", "sample_tracks",
]

#: Right-multiplying a c2w pose by this flips the camera's y and z axes (OpenCV <-> OpenGL).
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


# ------------------------------------------------------------------------------ pose conventions


def opencv_to_opengl(c2w: np.ndarray) -> np.ndarray:
    """OpenCV-axes c2w (..., 4, 4) -> OpenGL/nerfstudio-axes c2w (y and z camera axes negated)."""
    return np.asarray(c2w, np.float64) @ OPENGL_FROM_OPENCV


def opengl_to_opencv(c2w_gl: np.ndarray) -> np.ndarray:
    """Inverse of :func:`opencv_to_opengl` (the flip is its own inverse)."""
    return np.asarray(c2w_gl, np.float64) @ OPENGL_FROM_OPENCV


def _rigid_inverse(T: np.ndarray) -> np.ndarray:
    R, t = T[..., :3, :3], T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def c2w_to_colmap(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """c2w poses (N, 4, 4) -> COLMAP (qvec (N, 4) as QW QX QY QZ with QW >= 0, tvec (N, 3)).

    ``qvec``/``tvec`` describe world-to-camera: x_cam = R(qvec) @ x_world + tvec.
    """
    from scipy.spatial.transform import Rotation

    w2c = _rigid_inverse(np.asarray(c2w, np.float64).reshape(-1, 4, 4))
    q = Rotation.from_matrix(w2c[:, :3, :3]).as_quat()  # x, y, z, w
    q[q[:, 3] < 0] *= -1.0
    return np.concatenate([q[:, 3:], q[:, :3]], axis=1), w2c[:, :3, 3].copy()


def colmap_to_c2w(qvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """COLMAP (qvec (N, 4) QW QX QY QZ, tvec (N, 3)) world-to-camera -> c2w poses (N, 4, 4)."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(qvec, np.float64).reshape(-1, 4)
    w2c = np.tile(np.eye(4), (len(q), 1, 1))
    w2c[:, :3, :3] = Rotation.from_quat(np.concatenate([q[:, 1:], q[:, :1]], axis=1)).as_matrix()
    w2c[:, :3, 3] = np.asarray(tvec, np.float64).reshape(-1, 3)
    return _rigid_inverse(w2c)


# ------------------------------------------------------------------------------ point clouds


def _valid(depth: np.ndarray) -> np.ndarray:
    return np.isfinite(depth) & (depth > 0)


def backproject_frame(depth: np.ndarray, K: np.ndarray, c2w: np.ndarray, image: np.ndarray | None = None,
                      stride: int = 1) -> tuple[np.ndarray, np.ndarray | None]:
    """World points of a frame's valid depth pixels (every ``stride``-th row and column).

    Returns (points float64 (M, 3) in the world frame, colours uint8 (M, 3) or None). Pixel
    (u, v) with depth d goes to c2w @ [d K^-1 (u, v, 1), 1].
    """
    d = np.asarray(depth, np.float32)[::stride, ::stride]
    v, u = np.nonzero(_valid(d))
    z = d[v, u].astype(np.float64)
    u = u.astype(np.float64) * stride
    v = v.astype(np.float64) * stride
    K = np.asarray(K, np.float64)
    x = (u - K[0, 2]) / K[0, 0] * z
    y = (v - K[1, 2]) / K[1, 1] * z
    cam = np.stack([x, y, z], axis=1)
    T = np.asarray(c2w, np.float64)
    pts = cam @ T[:3, :3].T + T[:3, 3]
    cols = None
    if image is not None:
        cols = np.asarray(image, np.uint8)[(v.astype(np.int64)), (u.astype(np.int64))].reshape(-1, 3)
    return pts, cols


class VoxelAccumulator:
    """Streaming voxel-grid average: add points frame by frame, get one point per voxel.

    The result (centroid and mean colour of every occupied voxel of size ``voxel``) equals
    downsampling the concatenation of all points at once, but memory stays bounded by the
    number of occupied voxels. ``voxel <= 0`` keeps every point.
    """

    def __init__(self, voxel: float):
        self.voxel = float(voxel)
        self._parts: list[tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]] = []
        self._n_parts = 0

    def add(self, points: np.ndarray, colors: np.ndarray | None) -> None:
        if len(points) == 0:
            return
        if self.voxel <= 0:
            self._parts.append((np.zeros((0, 3), np.int64), points, colors, np.ones(len(points))))
            return
        keys = np.floor(points / self.voxel).astype(np.int64)
        self._parts.append(self._reduce(keys, points, None if colors is None else colors.astype(np.float64),
                                        np.ones(len(points))))
        self._n_parts += 1
        if self._n_parts >= 16:  # merge now and then so that memory stays ~ occupied voxels
            self._parts = [self._merge()]
            self._n_parts = 1

    @staticmethod
    def _reduce(keys, sums, csums, counts):
        uniq, inv = np.unique(keys, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        s = np.stack([np.bincount(inv, weights=sums[:, k], minlength=len(uniq)) for k in range(3)], axis=1)
        c = None
        if csums is not None:
            c = np.stack([np.bincount(inv, weights=csums[:, k], minlength=len(uniq)) for k in range(3)], axis=1)
        return uniq, s, c, np.bincount(inv, weights=counts, minlength=len(uniq))

    def _merge(self):
        keys = np.concatenate([p[0] for p in self._parts])
        sums = np.concatenate([p[1] for p in self._parts])
        cols = None if any(p[2] is None for p in self._parts) else np.concatenate([p[2] for p in self._parts])
        counts = np.concatenate([p[3] for p in self._parts])
        return self._reduce(keys, sums, cols, counts)

    def result(self) -> tuple[np.ndarray, np.ndarray | None]:
        """(points float64 (M, 3), colours uint8 (M, 3) or None)."""
        if not self._parts:
            return np.zeros((0, 3)), None
        if self.voxel <= 0:
            pts = np.concatenate([p[1] for p in self._parts])
            has_col = all(p[2] is not None for p in self._parts)
            cols = np.concatenate([p[2] for p in self._parts]).astype(np.uint8) if has_col else None
            return pts, cols
        _, s, c, n = self._merge()
        pts = s / n[:, None]
        cols = None if c is None else np.clip(np.round(c / n[:, None]), 0, 255).astype(np.uint8)
        return pts, cols


def fuse_point_cloud(depths: Sequence[np.ndarray], poses: np.ndarray, K: np.ndarray,
                     images: Sequence[np.ndarray] | None = None, every: int = 1,
                     voxel: float = 0.0) -> tuple[np.ndarray, np.ndarray | None]:
    """One point cloud from the depth of every ``every``-th frame, backprojected at its pose.

    ``depths`` and ``images`` may be lazy sequences (only the used frames are read). With
    ``voxel > 0`` (scene units) points are averaged per voxel. Returns (points float64 (M, 3)
    world frame, colours uint8 (M, 3) or None without images).
    """
    acc = VoxelAccumulator(voxel)
    for k in range(0, len(poses), max(1, int(every))):
        pts, cols = backproject_frame(depths[k], K, poses[k], None if images is None else images[k])
        acc.add(pts, cols)
    return acc.result()


def median_depth(depths: Iterable[np.ndarray], stride: int = 4) -> float:
    """Median of the valid depth over frames (every ``stride``-th pixel); 0 if none is valid."""
    vals = [d[::stride, ::stride][_valid(d[::stride, ::stride])] for d in (np.asarray(x, np.float32) for x in depths)]
    allv = np.concatenate(vals) if vals else np.zeros(0, np.float32)
    return float(np.median(allv)) if len(allv) else 0.0


def default_voxel(median: float) -> float:
    """Default voxel size / TSDF voxel length: 1/100 of the scene's median depth."""
    return float(median) / 100.0


def sample_tracks(depths: Sequence[np.ndarray], poses: np.ndarray, K: np.ndarray, frames: Sequence[int],
                  max_points: int) -> dict[str, np.ndarray]:
    """A sparse, regular sample of depth pixels as 3D points, each observed by its own frame.

    For COLMAP's points3D / POINTS2D: pixels on a grid (the same stride in every used frame,
    chosen so that about ``max_points`` points result). Returns {"frame": int64 (M,) index into
    ``poses``, "uv": float64 (M, 2) pixel (u, v) in our convention, "xyz": float64 (M, 3) world}.
    """
    frames = list(frames)
    if not frames:
        return {"frame": np.zeros(0, np.int64), "uv": np.zeros((0, 2)), "xyz": np.zeros((0, 3))}
    h, w = np.asarray(depths[frames[0]]).shape
    per_frame = max(1.0, max_points / len(frames))
    stride = max(1, int(np.ceil(np.sqrt(h * w / per_frame))))
    fr, uv, xyz = [], [], []
    K = np.asarray(K, np.float64)
    for k in frames:
        d = np.asarray(depths[k], np.float32)
        off = stride // 2
        sub = d[off::stride, off::stride]
        v, u = np.nonzero(_valid(sub))
        u = u * stride + off
        v = v * stride + off
        z = d[v, u].astype(np.float64)
        cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
        T = np.asarray(poses[k], np.float64)
        xyz.append(cam @ T[:3, :3].T + T[:3, 3])
        uv.append(np.stack([u, v], axis=1).astype(np.float64))
        fr.append(np.full(len(u), k, np.int64))
    return {"frame": np.concatenate(fr), "uv": np.concatenate(uv), "xyz": np.concatenate(xyz)}


# ------------------------------------------------------------------------------ TSDF


def tsdf_mesh(depths: Sequence[np.ndarray], images: Sequence[np.ndarray], poses: np.ndarray, K: np.ndarray,
              voxel_length: float, sdf_trunc: float | None = None, depth_trunc: float | None = None,
              every: int = 1, min_weight: float | None = None) -> dict[str, np.ndarray]:
    """Fuse depth + colour of every ``every``-th frame into a TSDF and extract a triangle mesh.

    open3d's tensor ``VoxelBlockGrid`` (TSDF, weight and colour per voxel; blocks of 8^3
    voxels, allocated where depth lands). ``voxel_length`` in scene units; ``sdf_trunc``
    defaults to 4 voxels; depth beyond ``depth_trunc`` (default: no limit) is ignored; frames
    without valid depth are skipped. A surface voxel must have been seen ``min_weight`` times
    (default min(3, frames integrated); open3d's default is 3). Returns {"vertices": float64
    (V, 3) world, "triangles": int32 (F, 3), "colors": uint8 (V, 3), "frames": int (frames
    integrated)}. (The legacy ScalableTSDFVolume of open3d-cpu 0.20 extracts nothing here, not
    even for a fronto-parallel plane, hence the tensor pipeline.)
    """
    import open3d as o3d

    o3c = o3d.core
    if not voxel_length > 0:
        raise ValueError(f"voxel_length must be > 0, got {voxel_length}")
    mult = 4.0 if sdf_trunc is None else float(sdf_trunc) / float(voxel_length)
    depth_max = 1e30 if depth_trunc is None else float(depth_trunc)
    vbg = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"), attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=(1, 1, 3), voxel_size=float(voxel_length), block_resolution=8, block_count=20000,
        device=o3c.Device("CPU:0"))
    Kt = o3c.Tensor(np.asarray(K, np.float64))
    n = 0
    for k in range(0, len(poses), max(1, int(every))):
        d = np.asarray(depths[k], np.float32)
        ok = _valid(d) & (d <= depth_max)
        if not ok.any():
            continue
        depth = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(np.where(ok, d, 0), np.float32)))
        color = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(images[k], np.float32) / 255.0))
        ext = o3c.Tensor(_rigid_inverse(np.asarray(poses[k], np.float64)))
        try:
            blocks = vbg.compute_unique_block_coordinates(depth, Kt, ext, 1.0, depth_max, mult)
        except RuntimeError:  # no block touched (e.g. all depth behind depth_trunc)
            continue
        vbg.integrate(blocks, depth, color, Kt, Kt, ext, 1.0, depth_max, mult)
        n += 1
    empty = {"vertices": np.zeros((0, 3)), "triangles": np.zeros((0, 3), np.int32),
             "colors": np.zeros((0, 3), np.uint8), "frames": n}
    if n == 0:
        return empty
    w = float(min(3, n)) if min_weight is None else float(min_weight)
    try:
        mesh = vbg.extract_triangle_mesh(weight_threshold=w)
    except RuntimeError:  # nothing above the weight threshold
        return empty
    if "positions" not in mesh.vertex or len(mesh.vertex.positions) == 0:
        return empty
    verts = mesh.vertex.positions.numpy().astype(np.float64)
    tris = mesh.triangle.indices.numpy().astype(np.int32) if "indices" in mesh.triangle else np.zeros((0, 3), np.int32)
    cols = mesh.vertex.colors.numpy() if "colors" in mesh.vertex else np.full((len(verts), 3), 0.5)
    return {"vertices": verts, "triangles": tris,
            "colors": np.clip(np.round(cols * 255.0), 0, 255).astype(np.uint8), "frames": n}
