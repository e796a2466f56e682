"""Where is a run's depth range compressed? Per-stage slope of log depth on log ground truth.

For a finished run and its ground-truth depth, from the run's cache: per frame, the least-squares
fit log(pred) = a + b log(gt) over the valid pixels (gt in (0, 10] m, pred > 0), for the prior
(1 / inv_depth), the keyframe depths after optimize_keyframes, the per-frame depths after
optimize_segments, depth_fusion, depth_filter, depth_consensus and the exported depth. b < 1 is
a compressed depth range (near too far, far too near); b is scale-free (a absorbs the scale).
Prints the median b (and its 10th-90th percentiles) per stage, and the median b of the
confident pixels (confidence >= 0.5) where the stage has a confidence.

    PYTHONPATH=. .venv/bin/python benchmarks/depth_slope.py RUN_DIR GT_DIR [--cache DIR] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from gcvd_flow.engine import api  # noqa: E402
from gcvd_flow.evaluate.run_eval import match_gt, read_depth_png  # noqa: E402

MAX_DEPTH = 10.0
MIN_PIXELS = 200


def log_slope(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Slope b of log(pred) = a + b log(gt) over the valid pixels (nan when too few)."""
    v = (gt > 0) & (gt <= MAX_DEPTH) & (pred > 0) & np.isfinite(pred)
    if mask is not None:
        v &= mask
    if v.sum() < MIN_PIXELS:
        return float("nan")
    x, y = np.log(gt[v].astype(np.float64)), np.log(pred[v].astype(np.float64))
    x = x - x.mean()
    den = float(x @ x)
    return float(x @ (y - y.mean()) / den) if den > 1e-12 else float("nan")


def _stage_maps(run: Path, cache: str | None, pos: list[int]) -> dict[str, dict[int, tuple[np.ndarray, np.ndarray | None]]]:
    """stage -> {run position: (depth, confidence or None)}."""
    out: dict[str, dict[int, tuple[np.ndarray, np.ndarray | None]]] = {}
    pri = api.recorded_output(run, "priors", cache)
    out["priors"] = {k: (1.0 / np.maximum(np.asarray(pri[k]["inv_depth"], np.float64), 1e-9), None) for k in pos}
    ok = api.recorded_output(run, "optimize_keyframes", cache)
    kf = {int(f): np.asarray(d) for f, d in zip(ok["keyframes"], ok["depths"])}
    out["optimize_keyframes"] = {k: (kf[k], None) for k in pos if k in kf}
    seg = api.recorded_output(run, "optimize_segments", cache)
    out["optimize_segments"] = {k: (np.asarray(seg["depths"][k]), None) for k in pos}
    for s in ("depth_fusion", "depth_filter", "depth_consensus"):
        m = api.recorded_output(run, s, cache)
        out[s] = {k: (np.asarray(m[k]["depth"]), np.asarray(m[k]["confidence"])) for k in pos}
    return out


def _resize(g: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    return g if g.shape == shape else cv2.resize(g, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)


def slopes(run_dir: str | Path, gt_dir: str | Path, cache: str | None) -> dict[str, dict[str, float]]:
    run = Path(run_dir)
    m = match_gt(run, gt_dir)
    maps = _stage_maps(run, cache, list(m.run_pos))
    gts = {k: read_depth_png(gp, m.depth_scale) for k, gp in zip(m.run_pos, m.depth_files) if gp is not None}
    maps["exported"] = {k: (np.load(run / "depth" / f"{i:06d}.npy"), np.load(run / "confidence" / f"{i:06d}.npy"))
                        for k, i in zip(m.run_pos, m.frame_indices)}
    res: dict[str, dict[str, float]] = {}
    for stage, per in maps.items():
        b_all, b_conf = [], []
        for k, (d, c) in per.items():
            if k not in gts:
                continue
            g = _resize(gts[k].astype(np.float64), d.shape)
            b_all.append(log_slope(d, g))
            if c is not None:
                b_conf.append(log_slope(d, g, c >= 0.5))
        a = np.asarray(b_all)
        row = {"frames": int(np.isfinite(a).sum()), "b_median": float(np.nanmedian(a)),
               "b_p10": float(np.nanpercentile(a, 10)), "b_p90": float(np.nanpercentile(a, 90))}
        if b_conf and np.isfinite(b_conf).any():
            row["b_conf_median"] = float(np.nanmedian(b_conf))
        res[stage] = row
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("gt")
    ap.add_argument("--cache", default=os.environ.get("GCVD_FLOW_CACHE"), help="default: the run's own (run.json)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    res = slopes(a.run, a.gt, a.cache)
    if a.json:
        print(json.dumps(res, indent=1))
        return
    print(f"{'stage':20s} {'frames':>6s} {'median b':>9s} {'p10-p90':>13s} {'confident b':>12s}")
    for s, r in res.items():
        c = f"{r['b_conf_median']:.3f}" if "b_conf_median" in r else "-"
        print(f"{s:20s} {r['frames']:6d} {r['b_median']:9.3f} {r['b_p10']:6.3f}-{r['b_p90']:.3f} {c:>12s}")


if __name__ == "__main__":
    main()
