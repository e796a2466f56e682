"""Per-pixel depth confidence (RUN_DIR/confidence/NNNNNN.npy, float32 in [0, 1], 0 = unmeasured)
in the forms the exports write; arrays in, arrays out. Not a format itself:

- ``depth-png`` (and nerfstudio, which shares its files): DIR/confidence/NNNNNN.png, uint16
  round(confidence x 65535), a second 16-bit grey PNG beside the depth PNG (not an alpha
  channel: readers of 16-bit grey depth PNGs, nerfstudio among them, get the depth file they
  expect, untouched);
- ``nerfstudio``: DIR/masks/NNNNNN.png, per frame ``mask_path``: uint8 single-channel, 255 where
  confidence >= ``--min-confidence`` (default 0.5), 0 = nerfstudio ignores the pixel, at the
  size of the exported image (nearest neighbour, pixel centres);
- ``mcap``: ``/camera/confidence`` foxglove.RawImage 32FC1, like ``/camera/depth``;
- ``ply`` and the MCAP cloud: pixels below ``--min-confidence`` dropped when it is given.
"""

from __future__ import annotations

import numpy as np

CONF_PNG_MAX = 65535


def confidence_to_u16(conf: np.ndarray) -> np.ndarray:
    """float confidence (H, W) in [0, 1] -> uint16 round(c x 65535) (NaN -> 0, clipped to [0, 1]);
    reads back as png / 65535 within 0.5 / 65535."""
    c = np.clip(np.nan_to_num(np.asarray(conf, np.float64), nan=0.0), 0.0, 1.0)
    return np.round(c * CONF_PNG_MAX).astype(np.uint16)


def nearest_resize(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest-neighbour resize of (h, w[, ...]) to (height, width[, ...]) with pixel centres: output
    pixel x takes input pixel floor((x + 0.5) w / width) (the convention of the intrinsics scaling
    c' = (c + 0.5) s - 0.5, so a mask stays aligned with the scaled camera)."""
    h, w = img.shape[:2]
    if (h, w) == (height, width):
        return img
    # integer arithmetic: floor((2x + 1) w / (2 width)) exactly (in floats 1.5 * (64 / 96) < 1)
    rows = np.minimum((2 * np.arange(height, dtype=np.int64) + 1) * h // (2 * height), h - 1)
    cols = np.minimum((2 * np.arange(width, dtype=np.int64) + 1) * w // (2 * width), w - 1)
    return img[rows[:, None], cols[None, :]]


def confidence_mask(conf: np.ndarray, threshold: float, width: int, height: int) -> np.ndarray:
    """nerfstudio mask: uint8 (height, width), 255 where confidence >= threshold, else 0, thresholded
    at the confidence's resolution, then resized to the image's by nearest neighbour."""
    keep = np.nan_to_num(np.asarray(conf, np.float32), nan=0.0) >= np.float32(threshold)
    return nearest_resize(np.where(keep, 255, 0).astype(np.uint8), width, height)
