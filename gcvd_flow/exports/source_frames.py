"""The run's frames at the *source* resolution, for exports that feed training tools
(``--full-res``, the default for ``colmap`` and ``nerfstudio``).

The cache holds the frames at working resolution only; the source frames are read again from
the run's INPUT (run.json ``invocation.input``), and only if it is still what the run used: its
content digest (every frame's bytes, the layout, the intrinsics it declares) must equal the one
the ``ingest`` stage recorded. Intrinsics are scaled back with the pixel-centre convention of
``stages/frontend/ingest.make_camera``: c_src = (c_work + 0.5) / s - 0.5, f_src = f_work / s.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from gcvd_flow.engine.dag import MapValue
from gcvd_flow.engine.errors import UsageError
from gcvd_flow.engine.outputs import read_run_dir
from gcvd_flow.io.run_dir import RunData, read_cameras


@dataclass
class FrameView:
    """Frames to export with their camera: images (lazy uint8 (h, w, 3) RGB or None), K (3, 3)
    for them, their size, and ``scale`` = (w / working width, h / working height)."""

    images: Any
    K: np.ndarray
    width: int
    height: int
    scale: tuple[float, float]
    resolution: str  # "source" | "working"

    def to_view(self, uv: np.ndarray) -> np.ndarray:
        """Working-resolution pixels (M, 2), centre of the top-left pixel (0, 0) -> this view's."""
        s = np.asarray(self.scale, np.float64)
        return (np.asarray(uv, np.float64) + 0.5) * s - 0.5


def working_view(run: RunData) -> FrameView:
    return FrameView(run.images, run.K, run.width, run.height, (1.0, 1.0), "working")


def scale_K(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """K at a resolution sx, sy times the given one (pixel centres: c' = (c + 0.5) s - 0.5)."""
    K2 = np.array(K, np.float64)
    K2[0, 0], K2[1, 1] = K[0, 0] * sx, K[1, 1] * sy
    K2[0, 2], K2[1, 2] = (K[0, 2] + 0.5) * sx - 0.5, (K[1, 2] + 0.5) * sy - 0.5
    return K2


def source_view(run: RunData) -> FrameView | str:
    """The source-resolution view, or the reason it is unavailable (a str)."""
    from gcvd_flow.io.sources import open_source
    from gcvd_flow.pipeline import RUN_DIR_SOURCES, undistort_source_frame

    try:
        doc = read_run_dir(run.run_dir)
        cams = read_cameras(run.run_dir)
        src_w, src_h = int(cams["source_width"]), int(cams["source_height"])
        recorded = doc["stages"][RUN_DIR_SOURCES.frames]["fields"]["inputs"]["source"]
        input_ = doc["invocation"]["input"]
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:  # UsageError is a ValueError
        return f"run.json / cameras.json do not say where the source frames are ({exc})"
    if (src_w, src_h) == (run.width, run.height):
        return working_view(run) if run.images is not None else "the run's frames are not available"
    try:
        src = open_source(str(input_))
    except UsageError as exc:
        return f"the input {input_} cannot be read ({exc})"
    if src.digest != recorded:
        return f"the input {input_} changed since the run (its content digest differs)"
    if tuple(src.size) != (src_w, src_h) or max(run.frame_indices) >= len(src.items):
        return f"the input {input_} does not match cameras.json"
    items = src.items
    idx = list(run.frame_indices)
    sx, sy = src_w / run.width, src_h / run.height
    K_src = scale_K(run.K, sx, sy)
    dist = cams.get("distortion")  # the run undistorted its frames at ingest: so do the exports

    def get(k: int) -> np.ndarray:
        img = items[idx[k]].loader()
        if img.shape != (src_h, src_w, 3):
            raise UsageError(f"{input_}: frame {idx[k]} is {img.shape[1]}x{img.shape[0]}, expected {src_w}x{src_h}")
        return img if dist is None else undistort_source_frame(img, cams)

    return FrameView(MapValue(get, len(idx), None), K_src, src_w, src_h, (sx, sy), "source")
