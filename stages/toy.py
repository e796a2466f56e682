"""Toy stages for engine tests, benchmarks and the pre-vision demo.

Pure functions with the engine's stage signature ``fn(inputs, params, ctx)``; they do cheap
numeric work on byte blobs so that caching behaviour can be tested without vision.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np


def _scaled(x: np.ndarray, scale: float) -> np.ndarray:
    return (x.astype(np.float32) * np.float32(scale)).astype(np.float32)


def decode_item(inputs: dict[str, Any], params: Any, ctx: Any) -> dict[str, Any]:
    """Bytes of one input file -> float32 array (N,) with values in [0, 255]."""
    raw = inputs["blob"]
    return {"values": np.frombuffer(raw, dtype=np.uint8).astype(np.float32)}


def transform_item(inputs: dict[str, Any], params: Any, ctx: Any) -> dict[str, Any]:
    """One item scaled by ``params.scale``; ``params.sleep`` seconds of simulated work."""
    if params.sleep:
        time.sleep(params.sleep)
    x = inputs["item"]["values"]
    return {"values": _scaled(x, params.scale), "mean": float(x.mean())}


def summarize(inputs: dict[str, Any], params: Any, ctx: Any) -> dict[str, Any]:
    """Mean of every transformed item, rounded to ``params.digits`` decimals."""
    items = inputs["transform"]
    means = [float(items[i]["values"].mean()) for i in range(len(items))]
    return {"means": np.asarray(means, dtype=np.float64),
            "total": round(float(np.sum(means)), params.digits)}


def threshold(inputs: dict[str, Any], params: Any, ctx: Any) -> dict[str, Any]:
    """Which item means exceed ``params.cut``."""
    means = inputs["summarize"]["means"]
    return {"above": (means > params.cut).astype(np.uint8), "cut": params.cut}


def report(inputs: dict[str, Any], params: Any, ctx: Any) -> dict[str, Any]:
    above = inputs["threshold"]["above"]
    return {"count": int(above.sum()), "n": int(above.size)}
