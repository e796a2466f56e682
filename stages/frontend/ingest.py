"""Ingest: source frames to the working resolution, and the camera at that resolution.

Default intrinsics guess (no ``--intrinsics``): the GCVD authors' f = 300 px at a 384 px long
side, i.e. f = 0.78125 * long side (a 65.2 degree horizontal field of view for landscape
video), principal point at the image centre. It is recorded in the ``camera`` artifact with
``guessed = true`` and printed, because a wrong focal length biases depth and poses.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from gcvd_flow.stages.frontend import lens

DEFAULT_FOCAL_PER_LONG_SIDE = 300.0 / 384.0


class FrameError(ValueError):
    """A frame of the user's input is unusable (the CLI reports it as bad input, exit 2)."""

    user_error = True


def working_size(src_w: int, src_h: int, long_side: int | None, min_short_frac: float = 0.0) -> tuple[int, int]:
    """(w, h) with the long side scaled to ``long_side`` (None or 0: keep), even numbers.

    ``min_short_frac``: the short side is at least this fraction of ``long_side`` (the long side
    grows for frames wider than that, never past the source): a 1226x370 driving camera at 256 px
    would keep 78 rows, where forward motion's parallax is too few pixels for bundle adjustment to
    hold the scale (docs/benchmarks.md); at 0.5 it gets 424x128, about the pixels of a 4:3 clip."""
    if not long_side or long_side >= max(src_w, src_h):
        return src_w, src_h
    s = long_side / max(src_w, src_h)
    if min_short_frac > 0:
        s = min(1.0, max(s, min_short_frac * long_side / min(src_w, src_h)))
        if s >= 1.0:
            return src_w, src_h
    w = max(2, int(round(src_w * s / 2)) * 2)
    h = max(2, int(round(src_h * s / 2)) * 2)
    return w, h


def prepare_frame(rgb: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize a source frame uint8 (H0, W0, 3) RGB to ``size`` = (w, h) (area filter)."""
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[..., None], 3, axis=2)
    if rgb.shape[2] == 4:
        rgb = rgb[..., :3]
    w, h = size
    if (rgb.shape[1], rgb.shape[0]) == (w, h):
        return np.ascontiguousarray(rgb, dtype=np.uint8)
    return cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)


def undistort_frame(rgb: np.ndarray, intrinsics: tuple[float, float, float, float],
                    distortion: tuple[float, ...], model: str = "OPENCV") -> np.ndarray:
    """Source frame uint8 (H, W, 3) seen through the lens (``model`` OPENCV: k1, k2, p1, p2[, k3];
    OPENCV_FISHEYE: k1..k4; stages.frontend.lens) -> the pinhole image of the same intrinsics
    (fx, fy, cx, cy, source pixels): each output pixel samples the input where the distortion
    moves it (bilinear; outside the frame: black)."""
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    return lens.undistort_image(rgb, lens.Camera(fx, fy, cx, cy, model, tuple(float(v) for v in distortion)))


def make_camera(src_w: int, src_h: int, work_w: int, work_h: int,
                intrinsics: tuple[float, float, float, float] | None,
                intrinsics_origin: str = "user") -> dict[str, Any]:
    """Camera at working resolution. ``intrinsics`` are at the *source* resolution.

    Returns {K: (3,3) float64, width, height, source_width, source_height, guessed, origin}.
    Scaling uses pixel-centre coordinates: c' = (c + 0.5) * s - 0.5.
    """
    sx, sy = work_w / src_w, work_h / src_h
    if intrinsics is None:
        f = DEFAULT_FOCAL_PER_LONG_SIDE * max(work_w, work_h)
        fx, fy = f, f * sy / sx  # square source pixels; the working resize may not keep them square
        cx, cy = (work_w - 1) / 2.0, (work_h - 1) / 2.0
        origin = "guess: f = 300/384 * long side (GCVD authors), centred principal point"
    else:
        fx0, fy0, cx0, cy0 = intrinsics
        fx, fy = fx0 * sx, fy0 * sy
        cx, cy = (cx0 + 0.5) * sx - 0.5, (cy0 + 0.5) * sy - 0.5
        origin = intrinsics_origin
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
    return {"K": K, "width": int(work_w), "height": int(work_h), "source_width": int(src_w),
            "source_height": int(src_h), "guessed": intrinsics is None, "origin": origin}
