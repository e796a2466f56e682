"""The report's pictures: trajectory plots (matplotlib, Agg) and frame tiles, as PNG bytes.

Top view and side view are the planes of a PCA of the reference trajectory (ground truth when
given, else the estimate): the top view shows the two directions of most motion, the side view
the first against the least — whatever the dataset's world axes are.
"""

from __future__ import annotations

import base64
import io
from typing import Any

import numpy as np

from gcvd_flow.io.formats import png_bytes

TILE_MAX_WIDTH = 300  # px: shown at 150 CSS px, sharp on a 2x display, small in the file


def _fit(img: np.ndarray, nearest: bool = False) -> np.ndarray:
    """Downscale an image wider than TILE_MAX_WIDTH (area averaging, or nearest for labels)."""
    import cv2

    h, w = img.shape[:2]
    if w <= TILE_MAX_WIDTH:
        return img
    size = (TILE_MAX_WIDTH, max(1, round(h * TILE_MAX_WIDTH / w)))
    return cv2.resize(img, size, interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_AREA)


def data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def _axes_of(ref: np.ndarray) -> np.ndarray:
    """(3, 3) rows = principal directions of the positions, most variance first."""
    p = ref[np.all(np.isfinite(ref), axis=1)]
    if len(p) < 3:
        return np.eye(3)
    _, _, vt = np.linalg.svd(p - p.mean(0), full_matrices=False)
    return vt if vt.shape == (3, 3) else np.eye(3)


def trajectory_png(est: np.ndarray, gt: np.ndarray | None, keyframes: list[int],
                   loops: list[dict[str, Any]], dpi: int = 90, unit: str = "run units") -> bytes:
    """Top and side view of the camera centres: estimate (line), ground truth (grey), keyframes
    (dots), loop edges (red: used by the pose graph, dashed grey: rejected); axes labelled in
    ``unit`` (the poses' units). PNG bytes."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    ref = gt if gt is not None and np.isfinite(gt).any() else est
    axes = _axes_of(ref)
    centre = np.nanmean(ref, axis=0)
    fig = Figure(figsize=(9.6, 4.4), dpi=dpi)
    for n, (title, (u, v)) in enumerate((("top view", (0, 1)), ("side view", (0, 2)))):
        ax = fig.add_subplot(1, 2, n + 1)
        pe = (est - centre) @ axes.T
        if gt is not None:
            pg = (gt - centre) @ axes.T
            ax.plot(pg[:, u], pg[:, v], color="0.55", lw=2.2, label="ground truth")
        ax.plot(pe[:, u], pe[:, v], color="#1f5fbf", lw=1.4,
                label="estimate (Sim(3)-aligned)" if gt is not None else "estimate")
        for lp in loops:
            a, b = pe[lp["a"]], pe[lp["b"]]
            ax.plot([a[u], b[u]], [a[v], b[v]], color="#d62728" if lp["used"] else "0.6",
                    ls="-" if lp["used"] else "--", lw=1.0)
        if keyframes:
            ax.scatter(pe[keyframes, u], pe[keyframes, v], s=14, color="#ff7f0e", zorder=3, label="keyframes")
        ax.scatter(pe[:1, u], pe[:1, v], s=40, marker="s", color="k", zorder=4, label="start")
        if loops:
            ax.plot([], [], color="#d62728", lw=1.0, label="loop edges")
        ax.set_title(title)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, lw=0.3)
        ax.set_xlabel(f"principal axis 1 [{unit}]")
        ax.set_ylabel(f"principal axis {2 if n == 0 else 3} [{unit}]")
        if n == 0:
            ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def depth_tile(depth: np.ndarray, cmap: str = "turbo") -> bytes:
    """Depth (H, W) in a perceptual colormap (near = red for turbo), robust 2-98 % range of the
    valid pixels, invalid pixels black. PNG bytes."""
    import matplotlib

    d = np.asarray(depth, np.float64)
    ok = np.isfinite(d) & (d > 0)
    rgb = np.zeros(d.shape + (3,), np.uint8)
    if ok.any():
        inv = np.zeros_like(d)
        inv[ok] = 1.0 / d[ok]  # inverse depth: near things bright, far detail kept
        lo, hi = np.percentile(inv[ok], [2, 98])
        x = np.clip((inv - lo) / max(hi - lo, 1e-12), 0, 1)
        colours = matplotlib.colormaps[cmap](x)[..., :3]
        rgb[ok] = (colours[ok] * 255).round().astype(np.uint8)
    return png_bytes(_fit(rgb, nearest=True))


def mask_tile(static: np.ndarray, rgb: np.ndarray | None) -> bytes:
    """The motion mask: static pixels as the dimmed grey frame, moving (0) in magenta. PNG."""
    s = np.asarray(static) > 0
    base = np.full(s.shape, 90, np.uint8) if rgb is None else (np.asarray(rgb).mean(-1) * 0.6).astype(np.uint8)
    out = np.repeat(base[..., None], 3, axis=-1)
    out[~s] = (230, 30, 200)
    return png_bytes(_fit(out, nearest=True))


def rgb_tile(rgb: np.ndarray) -> bytes:
    return png_bytes(_fit(np.asarray(rgb, np.uint8)))
