"""Statistics of a run's depth maps that reading a RUN_DIR and the exports share.

Depth maps are float32 (H, W) z-depth in scene units, 0 (or non-finite) = invalid
(docs/contributing.md). Kept here, not in an exporter, so that reading a run depends on no
export (``gcvd_flow.io.run_dir`` -> ``gcvd_flow.exports`` was an import circle).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np


def valid_depth(depth: np.ndarray) -> np.ndarray:
    """bool mask of usable depth: finite and > 0."""
    return np.isfinite(depth) & (depth > 0)


def median_depth(depths: Iterable[np.ndarray], stride: int = 4) -> float:
    """Median of the valid depth over frames (every ``stride``-th pixel); 0 if none is valid."""
    vals = [d[::stride, ::stride][valid_depth(d[::stride, ::stride])] for d in (np.asarray(x, np.float32) for x in depths)]
    allv = np.concatenate(vals) if vals else np.zeros(0, np.float32)
    return float(np.median(allv)) if len(allv) else 0.0
