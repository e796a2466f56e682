"""Small image helpers every stage shares (one implementation each).

Pixel convention (docs/contributing.md): pixel (u, v) = column u, row v; the centre of the
top-left pixel is (0, 0), so an h x w image spans [0, w - 1] x [0, h - 1].
"""

from __future__ import annotations

import cv2
import numpy as np


def to_gray(img: np.ndarray) -> np.ndarray:
    """uint8 (H, W, 3) RGB (or an (H, W) grey image, returned as is) -> uint8 (H, W) grey (OpenCV's
    RGB2GRAY weights), contiguous."""
    if img.ndim == 2:
        return np.ascontiguousarray(img, dtype=np.uint8)
    return cv2.cvtColor(np.ascontiguousarray(img, dtype=np.uint8), cv2.COLOR_RGB2GRAY)


def inside_image(u: np.ndarray, v: np.ndarray, w: int, h: int, border: float = 0.0) -> np.ndarray:
    """bool mask (same shape as u, v) of positions (u, v) px at least ``border`` px inside an
    h x w image: border <= u <= w - 1 - border and the same for v. NaN is never inside (every
    comparison with NaN is False) and +-inf fails one bound."""
    out = u >= border
    out &= u <= w - 1 - border
    out &= v >= border
    out &= v <= h - 1 - border
    return out


def apply_homography(h: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (x, y) (any shape each) mapped by the 3x3 homography h: (x', y') float64 (a
    vanishing denominator is held at 1e-12)."""
    den = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    den = np.where(np.abs(den) < 1e-12, 1e-12, den)
    xo = (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / den
    yo = (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / den
    return xo, yo
