"""Point clouds and meshes of a run: the ``ply`` and ``tsdf`` formats and their geometry.

``ply``  DIR/points.ply  binary PLY, coloured points: every valid depth pixel of every N-th
         frame (``--every``) backprojected at its pose into the world frame; ``--voxel M``
         averages points per M-sized voxel (default off); ``--min-confidence C`` (only when
         given, and for runs with confidence/) keeps the pixels whose confidence is >= C.
``tsdf`` DIR/mesh.ply    triangle mesh with vertex colours from open3d TSDF fusion
         (``VoxelBlockGrid``) of depth + colour of every N-th frame at the run's poses; voxel
         length ``--tsdf-voxel``, default median depth / 100; truncation 4 voxels.

The geometry is arrays in, arrays out (no file I/O), in the conventions of docs/contributing.md:
pose float64 (4, 4) camera-to-world T_w_c, OpenCV camera axes (x right, y down, z forward);
depth float32 (H, W) z-depth in scene units, 0 = invalid; image uint8 (H, W, 3) RGB; K float64
(3, 3) with the top-left pixel's centre at (0, 0). The MCAP export's cloud comes from here too.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from gcvd_flow.engine.errors import UsageError
from gcvd_flow.exports._common import ExportContext, _atomic, rigid_inverse, uses_images
from gcvd_flow.io.depth_maps import median_depth, valid_depth  # noqa: F401 - median_depth: part of this API

# ------------------------------------------------------------------------------ geometry


def pixels_to_world(u: np.ndarray, v: np.ndarray, z: np.ndarray, K: np.ndarray, T_w_c: np.ndarray) -> np.ndarray:
    """Pixels (u, v) (M,) with z-depth z (M,) -> world points float64 (M, 3): T_w_c [z K^-1 (u, v, 1), 1]."""
    K = np.asarray(K, np.float64)
    x = (u - K[0, 2]) / K[0, 0] * z
    y = (v - K[1, 2]) / K[1, 1] * z
    cam = np.stack([x, y, z], axis=1)
    T = np.asarray(T_w_c, np.float64)
    return cam @ T[:3, :3].T + T[:3, 3]


def backproject_frame(depth: np.ndarray, K: np.ndarray, T_w_c: np.ndarray, image: np.ndarray | None = None,
                      stride: int = 1) -> tuple[np.ndarray, np.ndarray | None]:
    """World points of a frame's valid depth pixels (every ``stride``-th row and column).

    Returns (points float64 (M, 3) in the world frame, colours uint8 (M, 3) or None).
    """
    d = np.asarray(depth, np.float32)[::stride, ::stride]
    vi, ui = np.nonzero(valid_depth(d))
    z = d[vi, ui].astype(np.float64)
    u = ui.astype(np.float64) * stride
    v = vi.astype(np.float64) * stride
    pts = pixels_to_world(u, v, z, K, T_w_c)
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


def default_voxel(median: float) -> float:
    """Default voxel size / TSDF voxel length: 1/100 of the scene's median depth."""
    return float(median) / 100.0


# ------------------------------------------------------------------------------ TSDF


def tsdf_mesh(depths: Sequence[np.ndarray], images: Sequence[np.ndarray], poses: np.ndarray, K: np.ndarray,
              voxel_length: float, sdf_trunc: float | None = None, depth_trunc: float | None = None,
              every: int = 1, min_weight: float | None = None) -> dict[str, Any]:
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
        # open3d's stubs want SizeVectors for attr_channels; it takes ints
        attr_channels=(1, 1, 3), voxel_size=float(voxel_length),  # type: ignore[arg-type]
        block_resolution=8, block_count=20000, device=o3c.Device("CPU:0"))
    Kt = o3c.Tensor(np.asarray(K, np.float64))  # type: ignore[call-overload]  # stubs: dtype, device required
    n = 0
    for k in range(0, len(poses), max(1, int(every))):
        d = np.asarray(depths[k], np.float32)
        ok = valid_depth(d) & (d <= depth_max)
        if not ok.any():
            continue
        depth = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(np.where(ok, d, 0), np.float32)))  # type: ignore[call-overload]  # stubs: dtype, device required
        color = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(images[k], np.float32) / 255.0))  # type: ignore[call-overload]  # stubs: dtype, device required
        ext = o3c.Tensor(rigid_inverse(np.asarray(poses[k], np.float64)))  # type: ignore[call-overload]  # stubs: dtype, device required
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


# ------------------------------------------------------------------------------ the writers


def confident_depths(ctx: ExportContext) -> Sequence[np.ndarray]:
    """The run's depth (lazy), set to 0 (invalid) where the confidence is below ``--min-confidence``
    when that option is given and the run has confidence/; else the depth as it is."""
    from gcvd_flow.engine.dag import MapValue

    run, thr = ctx.run, ctx.opt.min_confidence
    if thr is None or thr <= 0 or not run.has_confidence:
        return run.depths

    def get(k: int) -> np.ndarray:
        d = run.depth(k)
        return np.where(run.confidence(k) >= np.float32(thr), d, np.float32(0.0)).astype(np.float32)

    return MapValue(get, len(run), None)


def fused_cloud(ctx: ExportContext, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """The run's fused cloud (every --every-th frame, voxel grid ``voxel``, pixels below a given
    --min-confidence dropped), once per export; grey points without images."""

    def make() -> tuple[np.ndarray, np.ndarray]:
        run = ctx.run
        pts, cols = fuse_point_cloud(confident_depths(ctx), run.poses, run.K, run.images, ctx.opt.every, voxel)
        if cols is None:
            cols = np.full((len(pts), 3), 128, np.uint8)
        return pts, cols

    return ctx.shared(("cloud", voxel), make)


def auto_voxel(ctx: ExportContext) -> float:
    """Default voxel size of the run: its median depth / 100."""
    return default_voxel(ctx.run.median_depth())


@uses_images("required")
def write_ply(ctx: ExportContext) -> dict[str, Any]:
    import open3d as o3d

    pts, cols = fused_cloud(ctx, ctx.opt.voxel)
    if len(pts) == 0:
        thr = ctx.opt.min_confidence if ctx.run.has_confidence else None
        low = f" with confidence >= {thr:g}" if thr else ""
        raise UsageError(f"{ctx.run.run_dir / 'depth'}: no valid depth{low} to make a point cloud of")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.colors = o3d.utility.Vector3dVector(cols.astype(np.float64) / 255.0)
    dst = ctx.out / "points.ply"
    with _atomic(dst) as tmp:
        # open3d's stubs say PathLike; it takes str
        if not o3d.io.write_point_cloud(str(tmp), pcd, write_ascii=False):  # type: ignore[arg-type]
            raise OSError(f"{dst}: open3d could not write the point cloud")
    return {"file": str(dst), "points": int(len(pts)), "every": ctx.opt.every, "voxel": ctx.opt.voxel,
            "min_confidence": ctx.opt.min_confidence if ctx.run.has_confidence else None}


@uses_images("required")
def write_tsdf(ctx: ExportContext) -> dict[str, Any]:
    import open3d as o3d

    run = ctx.run
    voxel = ctx.opt.tsdf_voxel or auto_voxel(ctx)
    assert run.images is not None
    m = tsdf_mesh(run.depths, run.images, run.poses, run.K, voxel, every=ctx.opt.every)
    if len(m["triangles"]) == 0:
        raise UsageError(f"{run.run_dir}: the TSDF fusion produced an empty mesh (voxel {voxel:.4g}; "
                         f"try --tsdf-voxel)")
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(m["vertices"]),
                                     o3d.utility.Vector3iVector(m["triangles"]))
    mesh.vertex_colors = o3d.utility.Vector3dVector(m["colors"].astype(np.float64) / 255.0)
    dst = ctx.out / "mesh.ply"
    with _atomic(dst) as tmp:
        # open3d's stubs say PathLike; it takes str
        if not o3d.io.write_triangle_mesh(str(tmp), mesh, write_ascii=False):  # type: ignore[arg-type]
            raise OSError(f"{dst}: open3d could not write the mesh")
    return {"file": str(dst), "vertices": int(len(m["vertices"])), "triangles": int(len(m["triangles"])),
            "voxel_length": voxel, "sdf_trunc": 4 * voxel, "frames_integrated": int(m["frames"]),
            "every": ctx.opt.every}
