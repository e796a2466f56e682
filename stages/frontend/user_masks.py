"""The user's own masks (``--masks DIR``) as a hard exclusion at every resolution and footprint.

Motion masks are soft where they are meant to be (the mesh-smoothness weight, the depth-gradient
term's pooled weights); the user's mask is not: a pixel the user masked must never enter a loss,
a track or a depth average. So wherever an image quantity is resized or sampled, a value whose
*footprint* (the source pixels an area average covers, or the pixels a bilinear sample mixes with
a non-zero weight) touches a user-masked pixel is left out: a min-pool of the kept mask, never an
average.

Conventions. ``keep``: bool / uint8 (H, W), 1 = the user did not mask this pixel. The optimisation
stages receive the user's exclusion folded into their static masks as int8 (:func:`hard_masks`):
1 = static, 0 = likely dynamic (soft), -1 = masked by the user (hard); without ``--masks`` they
receive the masks stage's uint8 masks unchanged (same bits as before). Positions are pixel
centres, (0, 0) = the top-left pixel's centre. Pure numpy / OpenCV.
"""

from __future__ import annotations

import cv2
import numpy as np

from gcvd_flow.stages.frontend import lens

__all__ = [
    "source_to_working",
    "lens_border",
    "hard_masks",
    "user_keep",
    "footprint_kept",
    "flow_target_kept",
]


def source_to_working(out: np.ndarray, size: tuple[int, int],
                      undistort: tuple | list | None = None) -> np.ndarray:
    """The user's mask bool (H0, W0), True = left out, at source resolution -> kept mask uint8
    (h, w), 1 = no source pixel the working pixel is made of was masked.

    size = (w, h). ``undistort`` = (intrinsics (fx, fy, cx, cy), coefficients[, model]) in source
    px when ingest undistorts the frames (model OPENCV when not given; stages.frontend.lens): the
    mask goes through the same remap (bilinear, so an output pixel is out when any of the four
    source pixels it mixes is). Then the area resize of ingest: a working pixel is out when any
    source pixel it covers is."""
    m: np.ndarray = np.asarray(out, np.float32)
    if undistort is not None:
        model = str(undistort[2]) if len(undistort) > 2 else "OPENCV"
        fx, fy, cx, cy = (float(v) for v in undistort[0])
        cam = lens.Camera(fx, fy, cx, cy, model, tuple(float(v) for v in undistort[1]))
        h0, w0 = m.shape
        mx, my = lens.undistort_maps(cam, (w0, h0))
        # cv2.remap's bilinear weights are 1/32-quantised: a tap with a weight under 1/32 may get
        # none. Dilating by one pixel first makes the test "any of the four taps" exact.
        m = cv2.dilate(m, np.ones((3, 3), np.uint8))
        # a working pixel the lens leaves outside the source frame (ingest's black border) shows
        # nothing: left out like a masked one
        m = cv2.remap(m, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=1)
    w, h = size
    if (m.shape[1], m.shape[0]) != (w, h):
        m = cv2.resize(m, (w, h), interpolation=cv2.INTER_AREA)
    return (m <= 0).astype(np.uint8)


def lens_border(undistort: tuple | list | None, source_size: tuple[int, int] | list[int]) -> bool:
    """Whether ingest's undistortion (``undistort`` as in :func:`source_to_working`, None: none)
    leaves working pixels whose rays fall outside the source frame (its black border, e.g. the
    corners of a barrel-corrected image): those are then left out as user-masked pixels are
    (:func:`source_to_working` of an empty mask), so no loss, track or average sees the border."""
    if undistort is None:
        return False
    w0, h0 = int(source_size[0]), int(source_size[1])
    return bool((source_to_working(np.zeros((h0, w0), bool), (w0, h0), undistort) == 0).any())


def hard_masks(masks: np.ndarray, keep: np.ndarray | None) -> np.ndarray:
    """Static masks (..., H, W) uint8, 1 = static, and the user's kept mask (same shape, 1 = kept)
    or None -> the masks unchanged (None) or int8 with -1 where the user masked."""
    if keep is None:
        return masks
    return np.where(np.asarray(keep) > 0, np.asarray(masks) > 0, -1).astype(np.int8)


def user_keep(masks: np.ndarray) -> np.ndarray | None:
    """Masks from :func:`hard_masks` (..., H, W) -> the user's kept mask bool (same shape), None when
    no pixel is the user's (then nothing needs the hard treatment)."""
    m = np.asarray(masks)
    if m.dtype.kind != "i":
        return None
    keep = m >= 0
    return None if keep.all() else keep


def footprint_kept(keep: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Whether bilinear samples at (x, y) (M,) px of an (H, W) image mix only kept pixels: the
    pixels floor / ceil of each coordinate (clamped to the image, as the samplers clamp) are all
    ``keep`` -> bool (M,). A position exactly on a pixel centre mixes that pixel only."""
    keep = np.asarray(keep, bool)
    h, w = keep.shape
    x = np.clip(np.nan_to_num(np.asarray(x, np.float64), nan=0.0), 0, w - 1)
    y = np.clip(np.nan_to_num(np.asarray(y, np.float64), nan=0.0), 0, h - 1)
    x0, x1 = np.floor(x).astype(np.int64), np.ceil(x).astype(np.int64)
    y0, y1 = np.floor(y).astype(np.int64), np.ceil(y).astype(np.int64)
    return keep[y0, x0] & keep[y0, x1] & keep[y1, x0] & keep[y1, x1]


def flow_target_kept(flow: np.ndarray, keep_b: np.ndarray) -> np.ndarray:
    """Flow a -> b (H, W, 2) px and frame b's kept mask (H, W) -> bool (H, W): pixel p's target
    p + flow(p) mixes only kept pixels of b (:func:`footprint_kept`)."""
    h, w = flow.shape[:2]
    v, u = np.mgrid[0:h, 0:w]
    ok = footprint_kept(keep_b, (u + flow[..., 0]).ravel(), (v + flow[..., 1]).ravel())
    return ok.reshape(h, w)
