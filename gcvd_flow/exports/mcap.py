"""``mcap``: DIR/run.mcap for Foxglove: JSON messages with foxglove JSON schemas (zstd chunks).

Per frame, at log time the frame's source timestamp (TUM RGB-D ``rgb.txt``), else source frame
index / fps (``--fps``, which also overrides a timestamp, else the input's, else 30):
``/camera/image`` ``foxglove.CompressedImage`` (PNG; ``--mcap-images jpeg``, or ``raw`` for
``foxglove.RawImage`` rgb8), ``/camera/depth`` ``foxglove.RawImage`` 32FC1,
``/camera/calibration`` ``foxglove.CameraCalibration`` (K in the OpenCV pixel convention, no
distortion), ``/tf`` ``foxglove.FrameTransform`` world -> camera (the camera-to-world pose), and
for runs with confidence/ ``/camera/confidence`` ``foxglove.RawImage`` 32FC1 (the depth's
confidence in [0, 1], little-endian float32 like the depth; its channel is registered after the
others, so files of runs without confidence keep their channel ids).
Once, at the first frame's time: ``/trajectory`` ``foxglove.PosesInFrame`` (all poses) and
``/points`` ``foxglove.PointCloud`` (the fused cloud, voxel ``--voxel`` or median depth / 100).
"""

from __future__ import annotations

import base64
import json
from collections.abc import Iterator
from typing import Any

import numpy as np

from gcvd_flow.engine.errors import UsageError
from gcvd_flow.exports._common import DEFAULT_FPS, MCAP_IMAGES, ExportContext, _atomic, uses_images
from gcvd_flow.exports.clouds import auto_voxel, fused_cloud
from gcvd_flow.exports.foxglove_schemas import NAMES as SCHEMA_NAMES, schema_bytes
from gcvd_flow.io.formats import png_bytes

TOPICS = {  # topic -> schema (the image topic's schema depends on --mcap-images)
    "/camera/image": "foxglove.CompressedImage", "/camera/depth": "foxglove.RawImage",
    "/camera/calibration": "foxglove.CameraCalibration", "/tf": "foxglove.FrameTransform",
    "/trajectory": "foxglove.PosesInFrame", "/points": "foxglove.PointCloud"}
CONFIDENCE_TOPIC = "/camera/confidence"  # foxglove.RawImage 32FC1, runs with confidence/ only


# ------------------------------------------------------------------------------ the writer


def _image_msg(ts: dict[str, int], rgb: np.ndarray, how: str, width: int, height: int) -> dict[str, Any]:
    if how == "raw":
        return {"timestamp": ts, "frame_id": "camera", "width": width, "height": height,
                "encoding": "rgb8", "step": width * 3, "data": _b64(np.ascontiguousarray(rgb).tobytes())}
    if how == "png":
        return {"timestamp": ts, "frame_id": "camera", "format": "png", "data": _b64(png_bytes(rgb))}
    import cv2

    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, 92])
    if not ok:
        raise OSError("JPEG encoding failed")
    return {"timestamp": ts, "frame_id": "camera", "format": "jpeg", "data": _b64(buf.tobytes())}


def _messages(ctx: ExportContext, pts: np.ndarray, cols: np.ndarray) -> Iterator[tuple[str, int, dict[str, Any]]]:
    """(topic, log time ns, message) in write order: trajectory and cloud, then per frame
    /tf, calibration, image, depth (, confidence)."""
    from scipy.spatial.transform import Rotation

    run = ctx.run
    quats = Rotation.from_matrix(run.poses[:, :3, :3]).as_quat()  # x, y, z, w
    K = run.K
    calib_P = [K[0, 0], 0.0, K[0, 2], 0.0, 0.0, K[1, 1], K[1, 2], 0.0, 0.0, 0.0, 1.0, 0.0]
    t0 = ctx.time_ns(0)
    yield "/trajectory", t0, {"timestamp": _stamp(t0), "frame_id": "world",
                              "poses": [_pose_msg(run.poses[k, :3, 3], quats[k]) for k in range(len(run))]}
    yield "/points", t0, _point_cloud_msg(t0, pts, cols)
    for k in range(len(run)):
        t = ctx.time_ns(k)
        ts = _stamp(t)
        yield "/tf", t, {"timestamp": ts, "parent_frame_id": "world", "child_frame_id": "camera",
                         "translation": _xyz(run.poses[k, :3, 3]), "rotation": _xyzw(quats[k])}
        yield "/camera/calibration", t, {
            "timestamp": ts, "frame_id": "camera", "width": run.width, "height": run.height,
            "distortion_model": "plumb_bob", "D": [0.0] * 5, "K": [float(v) for v in K.reshape(-1)],
            "R": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], "P": [float(v) for v in calib_P]}
        yield "/camera/image", t, _image_msg(ts, run.images[k], ctx.opt.mcap_images,  # type: ignore[index]
                                             run.width, run.height)
        yield "/camera/depth", t, _float_image_msg(ts, run.depth(k))
        if run.has_confidence:
            yield CONFIDENCE_TOPIC, t, _float_image_msg(ts, run.confidence(k))


def _float_image_msg(ts: dict[str, int], img: np.ndarray) -> dict[str, Any]:
    """foxglove.RawImage 32FC1 of a float (H, W) image (little-endian float32 rows)."""
    a = np.ascontiguousarray(img, "<f4")
    h, w = a.shape
    return {"timestamp": ts, "frame_id": "camera", "width": w, "height": h, "encoding": "32FC1",
            "step": w * 4, "data": _b64(a.tobytes())}


@uses_images("required")
def write(ctx: ExportContext) -> dict[str, Any]:
    from mcap.writer import Writer

    opt = ctx.opt
    if opt.mcap_images not in MCAP_IMAGES:
        raise UsageError(f"--mcap-images {opt.mcap_images!r}: choose one of {', '.join(MCAP_IMAGES)}")
    voxel = opt.voxel if opt.voxel > 0 else auto_voxel(ctx)
    pts, cols = fused_cloud(ctx, voxel)
    topics = dict(TOPICS)
    if opt.mcap_images == "raw":
        topics["/camera/image"] = "foxglove.RawImage"
    if ctx.run.has_confidence:
        topics[CONFIDENCE_TOPIC] = "foxglove.RawImage"
    dst = ctx.out / "run.mcap"
    counts: dict[str, int] = {}
    with _atomic(dst) as tmp, open(tmp, "wb") as f:
        w = Writer(f)
        w.start(profile="", library=f"gcvd-flow {_version()}")
        schema_ids: dict[str, int] = {}
        channels: dict[str, int] = {}
        for topic, schema in topics.items():  # registration order fixes the ids in the file
            if schema not in schema_ids:
                schema_ids[schema] = w.register_schema(name=schema, encoding="jsonschema",
                                                       data=schema_bytes(schema))
            counts[topic] = 0
            channels[topic] = w.register_channel(topic=topic, message_encoding="json",
                                                 schema_id=schema_ids[schema])
        for topic, t_ns, msg in _messages(ctx, pts, cols):
            w.add_message(channels[topic], log_time=t_ns, publish_time=t_ns, sequence=counts[topic],
                          data=json.dumps(msg, separators=(",", ":")).encode())
            counts[topic] += 1
        w.finish()
    return {"file": str(dst), "messages": counts, "fps": opt.fps or ctx.run.fps or DEFAULT_FPS,
            "cloud_points": int(len(pts)), "cloud_voxel": voxel}


# ------------------------------------------------------------------------------ message pieces


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


def _cloud_dtype() -> np.dtype:
    return np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
                     ("blue", "u1"), ("alpha", "u1")])


def _point_cloud_msg(t_ns: int, pts: np.ndarray, cols: np.ndarray) -> dict[str, Any]:
    dt = _cloud_dtype()
    buf = np.zeros(len(pts), dt)
    buf["x"], buf["y"], buf["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    buf["red"], buf["green"], buf["blue"], buf["alpha"] = cols[:, 0], cols[:, 1], cols[:, 2], 255
    assert dt.fields is not None and dt.names is not None  # a structured dtype
    fields = [{"name": n, "offset": dt.fields[n][1], "type": 7 if n in "xyz" else 1}
              for n in dt.names]  # foxglove.NumericType: 7 FLOAT32, 1 UINT8
    return {"timestamp": _stamp(t_ns), "frame_id": "world",
            "pose": _pose_msg([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]),
            "point_stride": dt.itemsize, "fields": fields, "data": _b64(buf.tobytes())}


def _version() -> str:
    from gcvd_flow.engine.api import _version as v

    return v()


# ------------------------------------------------------------------------------ foxglove JSON schemas
# The upstream files, vendored verbatim in gcvd_flow/exports/foxglove_schemas/ (source and commit
# named there); schema names are what Foxglove keys its panels on; bytes are base64 strings in JSON.
FOXGLOVE_SCHEMAS: dict[str, dict[str, Any]] = {n: json.loads(schema_bytes(n)) for n in SCHEMA_NAMES}
