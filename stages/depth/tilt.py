"""Per-frame photometric choice of the unconfident depth's range (a gcvd-flow addition, opt-in).

Why: on real footage the unconfident pixels (texture-less surfaces, no multi-view triangulation)
carry a per-frame tilt of their log depth against the truth, of either sign (HoloLens walk: the
ground-truth map log d_gt = a + b log d over them has b 0.68-1.11 between the quartiles), which
the frame's confident pixels do not reveal (a map fitted on their ground truth leaves AbsRel
0.1025 vs 0.1023; docs/log/2026-11-28-realdepth.md). The references' images do: frame i's
unconfident pixels, moved into each reference with the final poses at depth hypotheses
log d' = mu + b (log d - mu) (mu: their median log depth, b from ``slopes``), land on matching
image content only for the right range. The hypothesis with the least mean absolute difference
of the high-passed grey images (a 7x7 box mean removed: insensitive to auto-exposure offsets) is
taken, its slope moved toward 1 by ``shrink`` (half-way by default: one number per frame from a
noisy cost), and applied to the unconfident pixels only.

Shapes: images uint8 (H, W, 3) RGB; depth, confidence float32 (H, W); K (3, 3); poses (4, 4)
camera-to-world at the depth's scale.
"""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np

from gcvd_flow.stages.frontend.flow import warp_sample

MIN_PIXELS = 300  # fewer unconfident pixels: nothing to choose
MIN_LANDED = 100  # per reference: fewer pixels landing inside it say nothing
SLOPES = tuple(round(0.7 + 0.05 * k, 2) for k in range(13))  # 0.7 ... 1.3, the hypotheses


def _high_pass(image: np.ndarray) -> np.ndarray:
    grey = cv2.cvtColor(np.asarray(image, np.uint8), cv2.COLOR_RGB2GRAY).astype(np.float32)
    return grey - cv2.blur(grey, (7, 7))


def _cost(rays: np.ndarray, z: np.ndarray, own: np.ndarray, pose: np.ndarray,
          refs: Sequence[tuple[np.ndarray, np.ndarray]], K: np.ndarray) -> float:
    """Mean |high-pass difference| of the points rays * z seen from the references (inf: none lands)."""
    X = rays * z
    h, w = refs[0][0].shape
    total, count = 0.0, 0
    for hp_j, pose_j in refs:
        T = np.linalg.inv(pose_j) @ pose
        Y = T[:3, :3] @ X + T[:3, 3:4]
        front = Y[2] > 1e-6
        p = K @ Y
        zz = np.where(front, p[2], 1.0)
        u, v = p[0] / zz, p[1] / zz
        ok = front & (u >= 0) & (u < w - 1) & (v >= 0) & (v < h - 1)
        if ok.sum() < MIN_LANDED:
            continue
        total += float(np.abs(own[ok] - warp_sample(hp_j, np.stack([u[ok], v[ok]], -1))).sum())
        count += int(ok.sum())
    return total / count if count else float("inf")


def photometric_tilt(depth: np.ndarray, confidence: np.ndarray, image: np.ndarray, pose: np.ndarray,
                     refs: Sequence[tuple[np.ndarray, np.ndarray]], K: np.ndarray,
                     slopes: Sequence[float], shrink: float = 0.5,
                     min_confidence: float = 0.5) -> tuple[np.ndarray, float]:
    """Frame i's depth with its unconfident pixels (confidence < ``min_confidence``) re-ranged by
    the photometrically best slope (module docstring) -> (depth float32 (H, W), applied slope;
    1.0 when nothing was chosen). refs: [(image_j uint8 (H, W, 3), pose_j (4, 4)), ...]."""
    depth = np.asarray(depth, np.float64)
    unc = (np.asarray(confidence) < min_confidence) & (depth > 0) & np.isfinite(depth)
    if unc.sum() < MIN_PIXELS or not refs or not len(slopes):
        return depth.astype(np.float32), 1.0
    vs, us = np.nonzero(unc)
    Ki = np.linalg.inv(np.asarray(K, np.float64))
    rays = Ki @ np.stack([us, vs, np.ones_like(us)], 0).astype(np.float64)
    logd = np.log(depth[vs, us])
    mu = float(np.median(logd))
    own = _high_pass(image)[vs, us]
    hps = [(_high_pass(img), np.asarray(pj, np.float64)) for img, pj in refs]
    pose = np.asarray(pose, np.float64)
    K = np.asarray(K, np.float64)
    costs = [_cost(rays, np.exp(mu + b * (logd - mu)), own, pose, hps, K) for b in slopes]
    if not np.isfinite(costs).any():
        return depth.astype(np.float32), 1.0
    b = 1.0 + (1.0 - shrink) * (float(slopes[int(np.argmin(costs))]) - 1.0)
    out = depth.copy()
    out[vs, us] = np.exp(mu + b * (logd - mu))
    return out.astype(np.float32), b
