"""``nerfstudio``: DIR/transforms.json (+ DIR/images/, DIR/depth/ PNGs).

``camera_model`` OPENCV (k1..p2 = 0), ``fl_x fl_y cx cy w h`` of the images (cx, cy + 0.5:
nerfstudio samples pixel centres at i + 0.5); the images are at the source resolution with
``--full-res`` (the default; intrinsics scaled), the depth PNGs at the working resolution
(nerfstudio resizes depth to its image, nearest neighbour); per frame ``file_path``, ``depth_file_path`` and
``transform_matrix``: camera-to-world in the OpenGL convention (camera x right, y up, z
backward: our OpenCV pose with its y and z columns negated). ``depth_unit_scale_factor`` =
0.001 / --depth-scale maps the depth PNGs back to pose units; ``ply_file_path`` when ``ply``
was exported before. Written after the images and depth PNGs it references.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from gcvd_flow.exports._common import ExportContext, uses_images, write_text
from gcvd_flow.exports.depth_png import depth_pngs

#: Right-multiplying a c2w pose by this flips the camera's y and z axes (OpenCV <-> OpenGL).
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def opencv_to_opengl(c2w: np.ndarray) -> np.ndarray:
    """OpenCV-axes c2w (..., 4, 4) -> OpenGL/nerfstudio-axes c2w (y and z camera axes negated)."""
    return np.asarray(c2w, np.float64) @ OPENGL_FROM_OPENCV


def opengl_to_opencv(c2w_gl: np.ndarray) -> np.ndarray:
    """Inverse of :func:`opencv_to_opengl` (the flip is its own inverse)."""
    return np.asarray(c2w_gl, np.float64) @ OPENGL_FROM_OPENCV


@uses_images("required")
def write(ctx: ExportContext) -> dict[str, Any]:
    run = ctx.run
    ctx.images_dir()
    depth_pngs(ctx)
    gl = opencv_to_opengl(run.poses)
    view = ctx.view()
    K = view.K
    doc: dict[str, Any] = {
        "camera_model": "OPENCV", "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]),
        # nerfstudio samples pixel centres at (i + 0.5): principal point in corner coordinates
        "cx": float(K[0, 2] + 0.5), "cy": float(K[1, 2] + 0.5), "w": view.width, "h": view.height,
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        # depth PNG value * factor = depth in the units of the poses
        "depth_unit_scale_factor": 1e-3 / ctx.opt.depth_scale,
        "frames": [{"file_path": f"images/{run.name(k)}.png", "depth_file_path": f"depth/{run.name(k)}.png",
                    "transform_matrix": gl[k].tolist(), "frame_index": run.frame_indices[k]}
                   for k in range(len(run))],
    }
    if (ctx.out / "points.ply").exists() and "ply" in ctx.written:
        doc["ply_file_path"] = "points.ply"
    dst = ctx.out / "transforms.json"
    write_text(dst, json.dumps(doc, indent=1))
    return {"file": str(dst), "frames": len(run), "width": view.width, "height": view.height,
            "resolution": view.resolution}
