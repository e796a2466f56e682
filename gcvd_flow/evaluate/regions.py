"""Where the depth error is: AbsRel split by region classes (pure numpy / OpenCV).

Every frame is scaled once, by the median over all its valid pixels (as ``metrics.depth_metrics``
does), and each valid pixel's error |p - g| / g is then booked to the regions it belongs to:

* ``confident`` / ``unconfident``: the run's confidence >= ``min_confidence`` or not (when the run
  has confidence maps);
* ``textureless`` / ``textured``: the frame's local image gradient (mean Sobel magnitude over a
  ``TEXTURE_WINDOW`` box, grey levels per pixel) below / above ``TEXTURELESS_GRAD`` (when the
  frames are available);
* ``depth_edge``: within ``EDGE_RADIUS`` px of a ground-truth depth discontinuity (a jump of more
  than ``EDGE_LOG_JUMP`` in log depth between 4-neighbours, both valid);
* ``near`` / ``mid`` / ``far``: ground-truth depth in the clip's lower, middle or upper third (the
  33rd and 67th percentiles of all valid ground-truth pixels of the clip);
* ``border``: within ``BORDER_PX`` of the image edge (``interior``: the rest);
* ``dynamic``: pixels the masks stage marks as moving (when the masks are available).

Per region: its share of the valid pixels (``share``), the pixel-pooled AbsRel over the clip
(``abs_rel``), its share of the summed error (``error_share``: where the error is), the median
log ratio of prediction to ground truth (``log_bias``: a region consistently too near < 0 or too
far > 0 after the frame's scaling) and delta < 1.25. Shapes: depth, confidence (H, W) float;
grey image (H, W) in grey levels 0..255; static (H, W), 1 = static.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

TEXTURE_WINDOW = 7  # px, box over which the gradient magnitude is averaged
TEXTURELESS_GRAD = 3.0  # grey levels / px: below = texture-less (a plain wall, a ceiling)
EDGE_LOG_JUMP = 0.1  # |log g(p) - log g(q)| between 4-neighbours: a depth discontinuity (10 %)
EDGE_RADIUS = 2  # px around a discontinuity (both sides) that count as "depth_edge"
BORDER_PX = 8  # px from the image edge
NEAR_FAR_QUANTILES = (1 / 3, 2 / 3)

# the order of the printed table and of the JSON
REGIONS = ("confident", "unconfident", "textureless", "textured", "depth_edge", "near", "mid", "far", "border",
           "interior", "dynamic")


def local_gradient(gray: np.ndarray, window: int = TEXTURE_WINDOW) -> np.ndarray:
    """Mean Sobel gradient magnitude (grey levels per px) over a ``window`` box, float32 (H, W)."""
    g = np.asarray(gray, np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8.0  # the 3x3 Sobel sums 8 px differences
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    return cv2.blur(np.sqrt(gx * gx + gy * gy), (window, window), borderType=cv2.BORDER_REFLECT)


def depth_edges(gt: np.ndarray, log_jump: float = EDGE_LOG_JUMP, radius: int = EDGE_RADIUS) -> np.ndarray:
    """bool (H, W): within ``radius`` px of a jump of more than ``log_jump`` in log ground-truth
    depth between 4-neighbours that are both valid (> 0); a hole in the ground truth is no edge."""
    g = np.asarray(gt, np.float64)
    valid = g > 0
    lg = np.log(np.where(valid, g, 1.0))
    edge = np.zeros(g.shape, bool)
    jx = valid[:, 1:] & valid[:, :-1] & (np.abs(lg[:, 1:] - lg[:, :-1]) > log_jump)
    jy = valid[1:] & valid[:-1] & (np.abs(lg[1:] - lg[:-1]) > log_jump)
    edge[:, 1:] |= jx
    edge[:, :-1] |= jx
    edge[1:] |= jy
    edge[:-1] |= jy
    if radius > 0 and edge.any():
        k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
        edge = cv2.dilate(edge.astype(np.uint8), k) > 0
    return edge


def frame_regions(gt: np.ndarray, gray: np.ndarray | None = None, confidence: np.ndarray | None = None,
                  static: np.ndarray | None = None, min_confidence: float = 0.5,
                  border: int = BORDER_PX) -> dict[str, np.ndarray]:
    """The depth-independent region masks of one frame, bool (H, W) each (``near``/``mid``/``far``
    need the whole clip: ``RegionBreakdown``). Classes whose input is None are left out."""
    h, w = gt.shape
    out: dict[str, np.ndarray] = {}
    if confidence is not None:
        conf = np.asarray(confidence) >= min_confidence
        out["confident"], out["unconfident"] = conf, ~conf
    if gray is not None:
        flat = local_gradient(gray) < TEXTURELESS_GRAD
        out["textureless"], out["textured"] = flat, ~flat
    out["depth_edge"] = depth_edges(gt)
    b = np.zeros((h, w), bool)
    if border > 0:
        b[:border], b[-border:], b[:, :border], b[:, -border:] = True, True, True, True
    out["border"], out["interior"] = b, ~b
    if static is not None:
        out["dynamic"] = np.asarray(static) <= 0
    return out


@dataclass
class RegionBreakdown:
    """Accumulates frames (``add``) and reports the per-region errors (``result``)."""

    max_depth: float = 10.0
    min_confidence: float = 0.5
    _err: list[np.ndarray] = field(default_factory=list)
    _logr: list[np.ndarray] = field(default_factory=list)
    _gt: list[np.ndarray] = field(default_factory=list)
    _masks: list[dict[str, np.ndarray]] = field(default_factory=list)

    def add(self, pred: np.ndarray, gt: np.ndarray, gray: np.ndarray | None = None,
            confidence: np.ndarray | None = None, static: np.ndarray | None = None) -> None:
        """One frame: pred (H, W) depth up to scale, gt (H, W) metres (0 = invalid); the others as in
        ``frame_regions``. A frame with fewer than 10 valid pixels is skipped (as in depth_metrics)."""
        pred = np.asarray(pred, np.float64)
        gt = np.asarray(gt, np.float64)
        valid = (gt > 0) & (gt <= self.max_depth) & (pred > 0) & np.isfinite(pred)
        if valid.sum() < 10:
            return
        p, g = pred[valid], gt[valid]
        p = np.clip(p * (np.median(g) / np.median(p)), 1e-3, self.max_depth)
        self._err.append(np.abs(p - g) / g)
        self._logr.append(np.log(p / g))
        self._gt.append(g)
        regions = frame_regions(gt, gray, confidence, static, self.min_confidence)
        self._masks.append({k: m[valid] for k, m in regions.items()})

    def result(self) -> dict[str, dict[str, float]]:
        """{region: {share, abs_rel, error_share, log_bias, delta1, pixels}} for every region some
        frame had (a class missing from some frame, e.g. no frames in the cache for one, is left out)."""
        if not self._err:
            return {}
        err, logr, g = (np.concatenate(a) for a in (self._err, self._logr, self._gt))
        masks: dict[str, np.ndarray] = {}
        for name in REGIONS:
            if all(name in m for m in self._masks):
                masks[name] = np.concatenate([m[name] for m in self._masks])
        lo, hi = np.quantile(g, NEAR_FAR_QUANTILES)
        masks["near"], masks["mid"], masks["far"] = g < lo, (g >= lo) & (g <= hi), g > hi
        total = float(err.sum())
        out: dict[str, dict[str, float]] = {}
        for name in REGIONS:
            m = masks.get(name)
            if m is None:
                continue
            n = int(m.sum())
            row: dict[str, Any] = {"pixels": n, "share": n / len(err)}
            if n:
                row.update(abs_rel=float(err[m].mean()), error_share=float(err[m].sum() / max(total, 1e-300)),
                           log_bias=float(np.median(logr[m])), delta1=float(np.mean(np.abs(logr[m]) < np.log(1.25))))
            out[name] = row
        out["near"]["max_depth_m"] = float(lo)
        out["far"]["min_depth_m"] = float(hi)
        return out


def format_regions(regions: dict[str, dict[str, float]]) -> str:
    """The breakdown as a table: region, share of pixels, AbsRel, share of the error, log bias."""
    lines = [f"{'region':<12} {'pixels':>7} {'AbsRel':>7} {'of error':>8} {'bias':>7}"]
    for name, r in regions.items():
        if "abs_rel" not in r:
            lines.append(f"{name:<12} {100 * r['share']:6.1f}% {'-':>7} {'-':>8} {'-':>7}")
            continue
        lines.append(f"{name:<12} {100 * r['share']:6.1f}% {r['abs_rel']:7.4f} {100 * r['error_share']:7.1f}% "
                     f"{r['log_bias']:+7.3f}")
    return "\n".join(lines)
