"""``nerfstudio``: DIR/transforms.json (+ DIR/images/, DIR/depth/ PNGs).

``camera_model`` OPENCV (k1..p2 = 0), ``fl_x fl_y cx cy w h`` of the images (cx, cy + 0.5:
nerfstudio samples pixel centres at i + 0.5); the images are at the source resolution with
``--full-res`` (the default; intrinsics scaled), the depth PNGs at the working resolution
(nerfstudio resizes depth to its image, nearest neighbour); per frame ``file_path``, ``depth_file_path`` and
``transform_matrix``: camera-to-world in the OpenGL convention (camera x right, y up, z
backward: our OpenCV pose with its y and z columns negated). ``depth_unit_scale_factor`` =
0.001 / --depth-scale maps the depth PNGs back to pose units; ``ply_file_path`` when ``ply``
was exported before; ``applied_transform`` the identity (the poses are in our world: without the
key nerfstudio reads a folder that also holds colmap/sparse/0 as an old COLMAP conversion and
swaps x and y, flips z). Written after the images and depth PNGs it references.

Confidence (runs with RUN_DIR/confidence/): per frame ``mask_path`` ``masks/NNNNNN.png``, what
nerfstudio's dataparser reads (``nerfstudio/data/dataparsers/nerfstudio_dataparser.py``: a
per-frame key, on every frame or none; ``data_utils.get_image_mask_tensor_from_path``: one
channel, non-zero = use the pixel, 0 = never sampled; ``InputDataset.get_data`` asserts the mask
has the image's size): uint8, 255 where the depth confidence >= ``--min-confidence`` (default
0.5), else 0, at the image's size (upsampled by nearest neighbour with ``--full-res``). nerfstudio
drops masked pixels from every loss (colour too), so the masks keep training to pixels whose
depth the run trusts. ``--min-confidence 0`` writes no masks; no masks either when no pixel of
any frame reaches the threshold (e.g. ``depth_fusion.enabled=false``: confidence 0 everywhere),
with a warning. The confidence itself is in DIR/confidence/NNNNNN.png (the depth-png files,
beside depth/): nerfstudio has no transforms.json key for it, so none is written.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from gcvd_flow.exports._common import ExportContext, clean_stale, uses_images, write_bytes, write_text
from gcvd_flow.exports.confidence import confidence_mask
from gcvd_flow.exports.depth_png import depth_pngs
from gcvd_flow.io.formats import png_bytes

#: Right-multiplying a c2w pose by this flips the camera's y and z axes (OpenCV <-> OpenGL).
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def opencv_to_opengl(c2w: np.ndarray) -> np.ndarray:
    """OpenCV-axes c2w (..., 4, 4) -> OpenGL/nerfstudio-axes c2w (y and z camera axes negated)."""
    return np.asarray(c2w, np.float64) @ OPENGL_FROM_OPENCV


def opengl_to_opencv(c2w_gl: np.ndarray) -> np.ndarray:
    """Inverse of :func:`opencv_to_opengl` (the flip is its own inverse)."""
    return np.asarray(c2w_gl, np.float64) @ OPENGL_FROM_OPENCV


def confidence_masks(ctx: ExportContext, width: int, height: int) -> dict[str, Any]:
    """DIR/masks/NNNNNN.png (see the module docstring): {"dir": str or None, "files", "empty"
    (frames without a pixel to use), "min_confidence", "reason" when no masks were written}."""
    run, d, thr = ctx.run, ctx.out / "masks", ctx.opt.mask_threshold
    info: dict[str, Any] = {"dir": None, "files": 0, "empty": 0, "min_confidence": thr}
    reason = ("the run has no confidence/" if not run.has_confidence else
              "--min-confidence 0 (every pixel passes)" if thr <= 0 else None)
    if reason is None:  # a first pass (one frame at a time) to know whether any pixel passes at all
        info["empty"] = sum(not confidence_mask(run.confidence(k), thr, run.width, run.height).any()
                            for k in range(len(run)))
        if info["empty"] == len(run):
            reason = f"no pixel of any frame has confidence >= {thr:g}"
            ctx.log(f"warning: nerfstudio: no masks written: {reason} (was depth_fusion off?)")
    if reason is not None:
        clean_stale(d, set(), ".png")
        return {**info, "reason": reason}
    names = set()
    for k in range(len(run)):
        mask = confidence_mask(run.confidence(k), thr, width, height)
        write_bytes(d / f"{run.name(k)}.png", png_bytes(mask))
        names.add(f"{run.name(k)}.png")
    clean_stale(d, names, ".png")
    if info["empty"]:
        ctx.log(f"warning: nerfstudio: {info['empty']} of {len(run)} masks have no pixel with confidence >= "
                f"{thr:g} (nerfstudio samples no ray from those frames)")
    return {**info, "dir": str(d), "files": len(names)}


@uses_images("required")
def write(ctx: ExportContext) -> dict[str, Any]:
    run = ctx.run
    ctx.images_dir()
    depth_pngs(ctx)
    gl = opencv_to_opengl(run.poses)
    view = ctx.view()
    masks = confidence_masks(ctx, view.width, view.height)
    K = view.K
    doc: dict[str, Any] = {
        "camera_model": "OPENCV", "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]),
        # nerfstudio samples pixel centres at (i + 0.5): principal point in corner coordinates
        "cx": float(K[0, 2] + 0.5), "cy": float(K[1, 2] + 0.5), "w": view.width, "h": view.height,
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        # depth PNG value * factor = depth in the units of the poses
        "depth_unit_scale_factor": 1e-3 / ctx.opt.depth_scale,
        # the poses are in our world as they are: without this key nerfstudio (1.1.x,
        # nerfstudio_dataparser.py) takes a folder holding colmap/sparse/0 for an old COLMAP
        # conversion and maps its outputs back with x and y swapped and z flipped
        "applied_transform": np.eye(4)[:3].tolist(),
        "frames": [{"file_path": f"images/{run.name(k)}.png", "depth_file_path": f"depth/{run.name(k)}.png",
                    "transform_matrix": gl[k].tolist(), "frame_index": run.frame_indices[k]}
                   for k in range(len(run))],
    }
    if masks["dir"] is not None:  # every frame or none, as nerfstudio requires
        for k, fr in enumerate(doc["frames"]):
            fr["mask_path"] = f"masks/{run.name(k)}.png"
    if (ctx.out / "points.ply").exists() and "ply" in ctx.written:
        doc["ply_file_path"] = "points.ply"
    dst = ctx.out / "transforms.json"
    write_text(dst, json.dumps(doc, indent=1))
    return {"file": str(dst), "frames": len(run), "width": view.width, "height": view.height,
            "resolution": view.resolution, "masks": masks}
