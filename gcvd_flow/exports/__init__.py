"""`gcvd-flow export RUN_DIR --format FMT ...`: a finished run in the formats other tools read.

Reads RUN_DIR (``poses.txt``, ``depth/NNNNNN.npy``, ``cameras.json``, ``run.json``) and, for
the formats that need colour, the run's RGB frames at working resolution: the output of its
``ingest`` stage, decoded from the cache by the digest recorded in ``run.json``
(:func:`gcvd_flow.api.recorded_output`; neither the input video nor the current code is needed,
and the frames are exactly the ones the run used). Writes into DIR (default RUN_DIR/export):

    tum          DIR/poses.txt                    copy of the trajectory (TUM, camera-to-world)
    depth-png    DIR/depth/NNNNNN.png             uint16 millimetres of depth * --depth-scale, 0 = invalid
    ply          DIR/points.ply                   coloured point cloud (every N-th frame, optional voxel grid)
    tsdf         DIR/mesh.ply                     TSDF-fused triangle mesh (open3d VoxelBlockGrid)
    mcap         DIR/run.mcap                     foxglove JSON schemas: image, depth, calibration, /tf, trajectory, cloud
    colmap       DIR/colmap/{cameras,images,points3D}.txt (+ DIR/images/NNNNNN.png)
    nerfstudio   DIR/transforms.json (+ DIR/images/, DIR/depth/ PNGs)

Every file is written to a temporary name in its folder and renamed into place, so an
interrupted export never leaves a partial file under a final name; files that reference
others (transforms.json, images.txt) are written after what they reference.
"""

from __future__ import annotations

import argparse
import base64
import json
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator

from gcvd_flow.engine.dag import MapValue  # a lazily loaded sequence: frames / depth are read one at a time
from gcvd_flow.engine.errors import UsageError
from gcvd_flow.io.run_dir import RunData, attach_images, load_run  # noqa: F401 - part of this API

if TYPE_CHECKING:  # numpy & co. are imported where used: the CLI builds its parser without them
    import numpy as np


FORMATS = ("tum", "depth-png", "colmap", "ply", "tsdf", "nerfstudio", "mcap")  # also the write order
NEEDS_IMAGES = frozenset({"ply", "tsdf", "nerfstudio", "mcap"})
MCAP_IMAGES = ("png", "jpeg", "raw")
DEFAULT_FPS = 30.0
UINT16_MAX = 65535


# ------------------------------------------------------------------------------ atomic writes


@contextmanager
def _atomic(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix, for writers that go by it); rename
    it onto ``path`` only when the block succeeds."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _write_bytes(path: Path, data: bytes) -> None:
    with _atomic(path) as tmp:
        tmp.write_bytes(data)


def _write_text(path: Path, text: str) -> None:
    _write_bytes(path, text.encode())


def _png_bytes(img: np.ndarray) -> bytes:
    import cv2
    import numpy as np

    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 3])
    if not ok:
        raise OSError("PNG encoding failed")
    return buf.tobytes()


def depth_to_mm16(depth: np.ndarray, depth_scale: float = 1.0) -> tuple[np.ndarray, int]:
    """float depth (H, W) -> uint16 millimetres of depth * depth_scale, and the count of pixels
    clipped to 65535. Valid depth (finite, > 0) is rounded and clipped to [1, 65535] (so it never
    becomes 0); invalid depth is 0."""
    import numpy as np

    d = np.asarray(depth, np.float64) * (1000.0 * depth_scale)
    ok = np.isfinite(d) & (d > 0)
    mm = np.where(ok, np.round(np.where(ok, d, 0.0)), 0.0)
    clipped = int(np.count_nonzero(mm > UINT16_MAX))
    return np.where(ok, np.clip(mm, 1, UINT16_MAX), 0).astype(np.uint16), clipped


def _rel(path: Path, base: Path) -> str:
    return os.path.relpath(path, base)


def _clean_stale(folder: Path, keep: set[str], suffix: str) -> None:
    """Drop NNNNNN<suffix> files of an earlier export that this one does not write."""
    if folder.is_dir():
        for p in folder.glob(f"[0-9][0-9][0-9][0-9][0-9][0-9]{suffix}"):
            if p.name not in keep:
                p.unlink()


# ------------------------------------------------------------------------------ the exporter


@dataclass
class Options:
    every: int = 1
    voxel: float = 0.0
    tsdf_voxel: float | None = None
    depth_scale: float = 1.0
    fps: float | None = None
    mcap_images: str = "png"
    max_points: int = 20000


class Exporter:
    def __init__(self, run: RunData, out: Path, opt: Options, log: Callable[[str], None]):
        self.run, self.out, self.opt, self.log = run, out, opt, log
        self._done: dict[str, Any] = {}  # shared outputs written once (images/, depth/)
        self.written: set[str] = set()

    # -------------------------------------------------------------- shared pieces

    def images_dir(self) -> dict[str, Any]:
        if "images" not in self._done:
            run, d = self.run, self.out / "images"
            assert run.images is not None
            names = set()
            for k in range(len(run)):
                _write_bytes(d / f"{run.name(k)}.png", _png_bytes(run.images[k]))
                names.add(f"{run.name(k)}.png")
            _clean_stale(d, names, ".png")
            self._done["images"] = {"dir": str(d), "files": len(run)}
        return self._done["images"]

    def depth_pngs(self) -> dict[str, Any]:
        if "depth" not in self._done:
            run, d = self.run, self.out / "depth"
            clipped, names = 0, set()
            for k in range(len(run)):
                mm, c = depth_to_mm16(run.depth(k), self.opt.depth_scale)
                clipped += c
                _write_bytes(d / f"{run.name(k)}.png", _png_bytes(mm))
                names.add(f"{run.name(k)}.png")
            _clean_stale(d, names, ".png")
            if clipped:
                self.log(f"warning: depth-png: {clipped} pixels exceeded 65.535 m x --depth-scale and were "
                         f"clipped to 65535 mm (use a smaller --depth-scale)")
            self._done["depth"] = {"dir": str(d), "files": len(run), "unit": "mm",
                                   "depth_scale": self.opt.depth_scale, "clipped_pixels": clipped}
        return self._done["depth"]

    def fused_cloud(self, voxel: float) -> tuple[np.ndarray, np.ndarray]:
        import numpy as np
        from gcvd_flow.exports.geometry import fuse_point_cloud

        key = ("cloud", voxel)
        if key not in self._done:
            run = self.run
            pts, cols = fuse_point_cloud(run.depths, run.poses, run.K, run.images, self.opt.every, voxel)
            if cols is None:
                cols = np.full((len(pts), 3), 128, np.uint8)
            self._done[key] = (pts, cols)
        return self._done[key]

    def auto_voxel(self) -> float:
        from gcvd_flow.exports.geometry import default_voxel

        return default_voxel(self.run.median_depth())

    def time_ns(self, k: int) -> int:
        fps = self.opt.fps or self.run.fps or DEFAULT_FPS
        return int(round(self.run.frame_indices[k] / fps * 1e9))

    # -------------------------------------------------------------- formats

    def tum(self) -> dict[str, Any]:
        src = self.run.run_dir / "poses.txt"
        dst = self.out / "poses.txt"
        _write_bytes(dst, src.read_bytes())
        return {"file": str(dst), "poses": len(self.run)}

    def depth_png(self) -> dict[str, Any]:
        return self.depth_pngs()

    def ply(self) -> dict[str, Any]:
        import numpy as np
        import open3d as o3d

        pts, cols = self.fused_cloud(self.opt.voxel)
        if len(pts) == 0:
            raise UsageError(f"{self.run.run_dir / 'depth'}: no valid depth to make a point cloud of")
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        pcd.colors = o3d.utility.Vector3dVector(cols.astype(np.float64) / 255.0)
        dst = self.out / "points.ply"
        with _atomic(dst) as tmp:
            if not o3d.io.write_point_cloud(str(tmp), pcd, write_ascii=False):
                raise OSError(f"{dst}: open3d could not write the point cloud")
        return {"file": str(dst), "points": int(len(pts)), "every": self.opt.every, "voxel": self.opt.voxel}

    def tsdf(self) -> dict[str, Any]:
        import numpy as np
        import open3d as o3d

        from gcvd_flow.exports.geometry import tsdf_mesh

        run = self.run
        voxel = self.opt.tsdf_voxel or self.auto_voxel()
        assert run.images is not None
        m = tsdf_mesh(run.depths, run.images, run.poses, run.K, voxel, every=self.opt.every)
        if len(m["triangles"]) == 0:
            raise UsageError(f"{run.run_dir}: the TSDF fusion produced an empty mesh (voxel {voxel:.4g}; "
                             f"try --tsdf-voxel)")
        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(m["vertices"]),
                                         o3d.utility.Vector3iVector(m["triangles"]))
        mesh.vertex_colors = o3d.utility.Vector3dVector(m["colors"].astype(np.float64) / 255.0)
        dst = self.out / "mesh.ply"
        with _atomic(dst) as tmp:
            if not o3d.io.write_triangle_mesh(str(tmp), mesh, write_ascii=False):
                raise OSError(f"{dst}: open3d could not write the mesh")
        return {"file": str(dst), "vertices": int(len(m["vertices"])), "triangles": int(len(m["triangles"])),
                "voxel_length": voxel, "sdf_trunc": 4 * voxel, "frames_integrated": int(m["frames"]),
                "every": self.opt.every}

    def colmap(self) -> dict[str, Any]:
        import numpy as np
        from gcvd_flow.exports.geometry import c2w_to_colmap, sample_tracks

        run, d = self.run, self.out / "colmap"
        have_images = run.images is not None
        if have_images:
            self.images_dir()
        else:
            self.log(f"warning: colmap: {run.images_error}; writing the model without images/")
        K = run.K
        # COLMAP puts the top-left pixel's centre at (0.5, 0.5); we (OpenCV) at (0, 0).
        _write_text(d / "cameras.txt",
                    "# Camera list with one line of data per camera:\n"
                    "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n# Number of cameras: 1\n"
                    f"1 PINHOLE {run.width} {run.height} {_f(K[0, 0])} {_f(K[1, 1])} "
                    f"{_f(K[0, 2] + 0.5)} {_f(K[1, 2] + 0.5)}\n")
        tracks = sample_tracks(run.depths, run.poses, K, range(0, len(run), self.opt.every), self.opt.max_points)
        n_pts = len(tracks["xyz"])
        colors = np.full((n_pts, 3), 128, np.uint8)
        if have_images and n_pts:
            for k in np.unique(tracks["frame"]):
                sel = tracks["frame"] == k
                uv = tracks["uv"][sel].astype(np.int64)
                colors[sel] = run.images[int(k)][uv[:, 1], uv[:, 0]]
        # POINTS2D of each image: its own sampled pixels, in the order of the point ids.
        obs: dict[int, list[str]] = {}
        p2d_idx = np.zeros(n_pts, np.int64)
        for pid in range(n_pts):
            k = int(tracks["frame"][pid])
            lst = obs.setdefault(k, [])
            p2d_idx[pid] = len(lst)
            u, v = tracks["uv"][pid]
            lst.append(f"{_f(u + 0.5)} {_f(v + 0.5)} {pid + 1}")
        lines = ["# 3D point list with one line of data per point:",
                 "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
                 f"# Number of points: {n_pts}, mean track length: {1 if n_pts else 0}"]
        for pid in range(n_pts):
            x, y, z = tracks["xyz"][pid]
            r, g, b = colors[pid]
            lines.append(f"{pid + 1} {_f(x)} {_f(y)} {_f(z)} {r} {g} {b} 0 {int(tracks['frame'][pid]) + 1} "
                         f"{p2d_idx[pid]}")
        _write_text(d / "points3D.txt", "\n".join(lines) + "\n")
        qvec, tvec = c2w_to_colmap(run.poses)
        lines = ["# Image list with two lines of data per image:",
                 "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
                 "#   POINTS2D[] as (X, Y, POINT3D_ID)",
                 f"# Number of images: {len(run)}, mean observations per image: {n_pts / max(len(run), 1):g}"]
        for k in range(len(run)):
            lines.append(f"{k + 1} " + " ".join(_f(v) for v in (*qvec[k], *tvec[k])) + f" 1 {run.name(k)}.png")
            lines.append(" ".join(obs.get(k, [])))
        _write_text(d / "images.txt", "\n".join(lines) + "\n")
        return {"dir": str(d), "images": len(run), "points3D": n_pts,
                "image_dir": str(self.out / "images") if have_images else None}

    def nerfstudio(self) -> dict[str, Any]:
        from gcvd_flow.exports.geometry import opencv_to_opengl

        run = self.run
        self.images_dir()
        self.depth_pngs()
        gl = opencv_to_opengl(run.poses)
        K = run.K
        doc: dict[str, Any] = {
            "camera_model": "OPENCV", "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]),
            # nerfstudio samples pixel centres at (i + 0.5): principal point in corner coordinates
            "cx": float(K[0, 2] + 0.5), "cy": float(K[1, 2] + 0.5), "w": run.width, "h": run.height,
            "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
            # depth PNG value * factor = depth in the units of the poses
            "depth_unit_scale_factor": 1e-3 / self.opt.depth_scale,
            "frames": [{"file_path": f"images/{run.name(k)}.png", "depth_file_path": f"depth/{run.name(k)}.png",
                        "transform_matrix": gl[k].tolist(), "frame_index": run.frame_indices[k]}
                       for k in range(len(run))],
        }
        if (self.out / "points.ply").exists() and "ply" in self.written:
            doc["ply_file_path"] = "points.ply"
        dst = self.out / "transforms.json"
        _write_text(dst, json.dumps(doc, indent=1))
        return {"file": str(dst), "frames": len(run)}

    def mcap(self) -> dict[str, Any]:
        import numpy as np
        from mcap.writer import Writer
        from scipy.spatial.transform import Rotation

        import cv2

        run, opt = self.run, self.opt
        if opt.mcap_images not in MCAP_IMAGES:
            raise UsageError(f"--mcap-images {opt.mcap_images!r}: choose one of {', '.join(MCAP_IMAGES)}")
        voxel = opt.voxel if opt.voxel > 0 else self.auto_voxel()
        pts, cols = self.fused_cloud(voxel)
        quats = Rotation.from_matrix(run.poses[:, :3, :3]).as_quat()  # x, y, z, w
        K = run.K
        calib_P = [K[0, 0], 0.0, K[0, 2], 0.0, 0.0, K[1, 1], K[1, 2], 0.0, 0.0, 0.0, 1.0, 0.0]
        dst = self.out / "run.mcap"
        counts: dict[str, int] = {}
        with _atomic(dst) as tmp, open(tmp, "wb") as f:
            w = Writer(f)
            w.start(profile="", library=f"gcvd-flow {_version()}")
            sids: dict[str, int] = {}

            def channel(topic: str, schema: str) -> int:
                if schema not in sids:
                    sids[schema] = w.register_schema(name=schema, encoding="jsonschema",
                                                     data=json.dumps(FOXGLOVE_SCHEMAS[schema]).encode())
                counts[topic] = 0
                return w.register_channel(topic=topic, message_encoding="json", schema_id=sids[schema])

            image_schema = "foxglove.RawImage" if opt.mcap_images == "raw" else "foxglove.CompressedImage"
            ch = {"/camera/image": channel("/camera/image", image_schema),
                  "/camera/depth": channel("/camera/depth", "foxglove.RawImage"),
                  "/camera/calibration": channel("/camera/calibration", "foxglove.CameraCalibration"),
                  "/tf": channel("/tf", "foxglove.FrameTransform"),
                  "/trajectory": channel("/trajectory", "foxglove.PosesInFrame"),
                  "/points": channel("/points", "foxglove.PointCloud")}

            def put(topic: str, t_ns: int, msg: dict[str, Any]) -> None:
                w.add_message(ch[topic], log_time=t_ns, publish_time=t_ns, sequence=counts[topic],
                              data=json.dumps(msg, separators=(",", ":")).encode())
                counts[topic] += 1

            t0 = self.time_ns(0)
            put("/trajectory", t0, {"timestamp": _stamp(t0), "frame_id": "world",
                                    "poses": [_pose_msg(run.poses[k, :3, 3], quats[k]) for k in range(len(run))]})
            put("/points", t0, _point_cloud_msg(t0, pts, cols))
            for k in range(len(run)):
                t = self.time_ns(k)
                ts = _stamp(t)
                tr, q = run.poses[k, :3, 3], quats[k]
                put("/tf", t, {"timestamp": ts, "parent_frame_id": "world", "child_frame_id": "camera",
                               "translation": _xyz(tr), "rotation": _xyzw(q)})
                put("/camera/calibration", t, {
                    "timestamp": ts, "frame_id": "camera", "width": run.width, "height": run.height,
                    "distortion_model": "plumb_bob", "D": [0.0] * 5, "K": [float(v) for v in K.reshape(-1)],
                    "R": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], "P": [float(v) for v in calib_P]})
                rgb = run.images[k]  # type: ignore[index]
                if opt.mcap_images == "raw":
                    msg = {"timestamp": ts, "frame_id": "camera", "width": run.width, "height": run.height,
                           "encoding": "rgb8", "step": run.width * 3, "data": _b64(np.ascontiguousarray(rgb).tobytes())}
                elif opt.mcap_images == "png":
                    msg = {"timestamp": ts, "frame_id": "camera", "format": "png", "data": _b64(_png_bytes(rgb))}
                else:
                    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR),
                                           [cv2.IMWRITE_JPEG_QUALITY, 92])
                    msg = {"timestamp": ts, "frame_id": "camera", "format": "jpeg", "data": _b64(buf.tobytes())}
                put("/camera/image", t, msg)
                depth = np.ascontiguousarray(run.depth(k), "<f4")
                put("/camera/depth", t, {"timestamp": ts, "frame_id": "camera", "width": run.width,
                                         "height": run.height, "encoding": "32FC1", "step": run.width * 4,
                                         "data": _b64(depth.tobytes())})
            w.finish()
        return {"file": str(dst), "messages": counts, "fps": opt.fps or run.fps or DEFAULT_FPS,
                "cloud_points": int(len(pts)), "cloud_voxel": voxel}


def _f(x: float) -> str:
    """Shortest text that reads back to the same float (and no "-0.0")."""
    return repr(float(x) + 0.0)


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def _stamp(t_ns: int) -> dict[str, int]:
    return {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}


def _xyz(v) -> dict[str, float]:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def _xyzw(q) -> dict[str, float]:
    return {"x": float(q[0]), "y": float(q[1]), "z": float(q[2]), "w": float(q[3])}


def _pose_msg(t, q) -> dict[str, Any]:
    return {"position": _xyz(t), "orientation": _xyzw(q)}


def _cloud_dtype():
    import numpy as np

    return np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
                     ("blue", "u1"), ("alpha", "u1")])


def _point_cloud_msg(t_ns: int, pts: np.ndarray, cols: np.ndarray) -> dict[str, Any]:
    import numpy as np

    dt = _cloud_dtype()
    buf = np.zeros(len(pts), dt)
    buf["x"], buf["y"], buf["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    buf["red"], buf["green"], buf["blue"], buf["alpha"] = cols[:, 0], cols[:, 1], cols[:, 2], 255
    fields = [{"name": n, "offset": dt.fields[n][1], "type": 7 if n in "xyz" else 1}
              for n in dt.names]  # foxglove.NumericType: 7 FLOAT32, 1 UINT8
    return {"timestamp": _stamp(t_ns), "frame_id": "world",
            "pose": _pose_msg([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]),
            "point_stride": dt.itemsize, "fields": fields, "data": _b64(buf.tobytes())}


def _version() -> str:
    from gcvd_flow.engine.api import _version as v

    return v()


# ------------------------------------------------------------------------------ foxglove JSON schemas
# The field layout of https://github.com/foxglove/foxglove-sdk/tree/main/schemas/jsonschema
# (schema names are what Foxglove keys its panels on; bytes are base64 strings in JSON).

def _obj(title: str, props: dict[str, Any], description: str = "") -> dict[str, Any]:
    d: dict[str, Any] = {"title": title, "type": "object", "properties": props}
    if description:
        d["description"] = description
    return d


_TIME = _obj("time", {"sec": {"type": "integer", "minimum": 0},
                      "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}})
_STR = {"type": "string"}
_UINT = {"type": "integer", "minimum": 0}
_NUM = {"type": "number"}
_BYTES = {"type": "string", "contentEncoding": "base64"}
_VEC3 = _obj("foxglove.Vector3", {"x": _NUM, "y": _NUM, "z": _NUM})
_QUAT = _obj("foxglove.Quaternion", {"x": _NUM, "y": _NUM, "z": _NUM, "w": _NUM})
_POSE = _obj("foxglove.Pose", {"position": _VEC3, "orientation": _QUAT})


def _nums(n: int | None = None) -> dict[str, Any]:
    d: dict[str, Any] = {"type": "array", "items": _NUM}
    if n is not None:
        d.update(minItems=n, maxItems=n)
    return d


FOXGLOVE_SCHEMAS: dict[str, dict[str, Any]] = {
    "foxglove.RawImage": _obj("foxglove.RawImage", {
        "timestamp": _TIME, "frame_id": _STR, "width": _UINT, "height": _UINT, "encoding": _STR,
        "step": _UINT, "data": _BYTES}, "A raw image"),
    "foxglove.CompressedImage": _obj("foxglove.CompressedImage", {
        "timestamp": _TIME, "frame_id": _STR, "data": _BYTES, "format": _STR}, "A compressed image"),
    "foxglove.CameraCalibration": _obj("foxglove.CameraCalibration", {
        "timestamp": _TIME, "frame_id": _STR, "width": _UINT, "height": _UINT, "distortion_model": _STR,
        "D": _nums(), "K": _nums(9), "R": _nums(9), "P": _nums(12)}, "Camera calibration parameters"),
    "foxglove.FrameTransform": _obj("foxglove.FrameTransform", {
        "timestamp": _TIME, "parent_frame_id": _STR, "child_frame_id": _STR, "translation": _VEC3,
        "rotation": _QUAT}, "A transform between two reference frames in 3D space"),
    "foxglove.PosesInFrame": _obj("foxglove.PosesInFrame", {
        "timestamp": _TIME, "frame_id": _STR, "poses": {"type": "array", "items": _POSE}},
        "An array of timestamped poses for an object or reference frame in 3D space"),
    "foxglove.PointCloud": _obj("foxglove.PointCloud", {
        "timestamp": _TIME, "frame_id": _STR, "pose": _POSE, "point_stride": _UINT,
        "fields": {"type": "array", "items": _obj("foxglove.PackedElementField", {
            "name": _STR, "offset": _UINT,
            "type": {"title": "foxglove.NumericType", "oneOf": [
                {"title": t, "const": i} for i, t in enumerate(
                    ("UNKNOWN", "UINT8", "INT8", "UINT16", "INT16", "UINT32", "INT32", "FLOAT32", "FLOAT64"))]}})},
        "data": _BYTES}, "A collection of N-dimensional points"),
}


# ------------------------------------------------------------------------------ API + CLI


def parse_formats(values: Sequence[str]) -> list[str]:
    """`--format` values (repeatable, comma-separated, `all`) -> formats in write order."""
    asked: set[str] = set()
    for v in values:
        for f in (s.strip().lower() for s in v.split(",")):
            if not f:
                continue
            if f == "all":
                asked.update(FORMATS)
            elif f in FORMATS:
                asked.add(f)
            else:
                raise UsageError(f"unknown export format {f!r}; choose from {', '.join(FORMATS)}, all")
    if not asked:
        raise UsageError(f"no --format given; choose from {', '.join(FORMATS)}, all")
    return [f for f in FORMATS if f in asked]


def export_run(run_dir: str | Path, formats: Sequence[str], to: str | Path | None = None,
               options: Options | None = None, cache: str | None = None, verify: bool = True,
               log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Export a finished run (the Python API of `gcvd-flow export`).

    Returns {"out", "formats": {fmt: details}, "skipped": {fmt: reason}, "seconds"}. Formats
    that need the run's RGB frames are *skipped* (not an exception) when the cache no longer
    holds them; bad input raises UsageError before anything is written.
    """
    t0 = time.perf_counter()
    log = log or (lambda m: print(m, file=sys.stderr, flush=True))
    opt = options or Options()
    fmts = parse_formats(formats)
    if opt.every < 1:
        raise UsageError(f"--every {opt.every}: must be >= 1")
    if opt.voxel < 0 or (opt.tsdf_voxel is not None and opt.tsdf_voxel <= 0):
        raise UsageError("--voxel must be >= 0 and --tsdf-voxel > 0")
    if not (opt.depth_scale > 0 and math.isfinite(opt.depth_scale)):
        raise UsageError(f"--depth-scale {opt.depth_scale}: must be a positive number")
    if opt.fps is not None and not opt.fps > 0:
        raise UsageError(f"--fps {opt.fps}: must be > 0")
    if opt.max_points < 0:
        raise UsageError(f"--max-points {opt.max_points}: must be >= 0")
    if opt.mcap_images not in MCAP_IMAGES:
        raise UsageError(f"--mcap-images {opt.mcap_images!r}: choose one of {', '.join(MCAP_IMAGES)}")
    run = load_run(run_dir)
    out = Path(to) if to is not None else Path(run_dir) / "export"
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"{out}: cannot create the export directory ({exc.strerror})") from None
    if any(f in NEEDS_IMAGES or f == "colmap" for f in fmts):
        attach_images(run, cache, verify)
    ex = Exporter(run, out, opt, log)
    doc: dict[str, Any] = {"out": str(out), "frames": len(run), "formats": {}, "skipped": {}}
    for f in fmts:
        if f in NEEDS_IMAGES and run.images is None:
            doc["skipped"][f] = run.images_error
            continue
        doc["formats"][f] = getattr(ex, f.replace("-", "_"))()
        ex.written.add(f)
    doc["seconds"] = round(time.perf_counter() - t0, 3)
    return doc


def cmd_export(a: argparse.Namespace) -> int:
    """`gcvd-flow export` (its arguments are declared in product_cli.py, which stays light)."""
    opt = Options(every=a.every, voxel=a.voxel, tsdf_voxel=a.tsdf_voxel, depth_scale=a.depth_scale, fps=a.fps,
                  mcap_images=a.mcap_images, max_points=a.max_points)
    doc = export_run(a.run_dir, a.formats, a.to, opt, a.cache, a.verify)
    if a.json_mode:
        print(json.dumps(doc, indent=1))
    else:
        for f, info in doc["formats"].items():
            where = info.get("file") or info.get("dir")
            extra = ", ".join(f"{k} {v}" for k, v in info.items()
                              if k not in ("file", "dir") and not isinstance(v, (dict, type(None))))
            print(f"{f:<11} {where}  ({extra})")
    if doc["skipped"]:
        names = ", ".join(doc["skipped"])
        reason = next(iter(doc["skipped"].values()))
        raise UsageError(f"not exported: {names}: {reason}; pass the run's --cache DIR")
    return 0
