"""Can a frame's confident depth tell how to correct its unconfident depth? (issue 37 item 4)

For a finished run and its ground-truth depth: per frame, AbsRel (each frame scaled by its
median, as ``gcvd-flow eval`` does) of the exported depth after per-frame log-linear maps
log d' = a + b log d applied to the pixels with confidence < 0.5:

- ``self``: fitted without ground truth, robustly (Huber IRLS), on the confident pixels as
  log d_exported = a + b log d_net (d_net: optimize_segments' depth), applied to the net depth
  of the unconfident pixels, or its slope b applied to their exported depth about their median
  (the brief's idea);
- ``oracle-conf``: fitted to the ground truth on the confident pixels (the idea's upper bound:
  perfect confident depth), applied to the unconfident pixels;
- ``oracle-unconf``: fitted to the ground truth on the unconfident pixels themselves;
- ``expand B``: the unconfident pixels' log depth stretched by a fixed B about their median.

Also prints the per-frame slopes both ways: b_fwd of log pred on log gt (< 1 reads as a
compressed range) and b_map of log gt on log pred (the map a correction would apply), on the
interior of the ground truth (no > 5 % jump within 2 px), with their correlation.

    PYTHONPATH=. .venv/bin/python benchmarks/range_fit_probe.py RUN_DIR GT_DIR [--cache DIR]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from gcvd_flow.engine import api  # noqa: E402
from gcvd_flow.evaluate.run_eval import match_gt, read_depth_png  # noqa: E402

EXPAND = (1.05, 1.1)


def _fit(x: np.ndarray, y: np.ndarray, robust: bool = False) -> tuple[float, float]:
    """y = a + b x, least squares (Huber-reweighted five times when robust)."""
    w = np.ones_like(x)
    a, b = 0.0, 1.0
    for _ in range(5 if robust else 1):
        mx, my = np.average(x, weights=w), np.average(y, weights=w)
        vx = float(w @ (x - mx) ** 2)
        b = float(w @ ((x - mx) * (y - my)) / vx) if vx > 1e-12 else 1.0
        a = my - b * mx
        r = np.abs(y - a - b * x)
        s = 1.4826 * float(np.median(r)) + 1e-6
        w = np.minimum(1.0, 1.5 * s / np.maximum(r, 1e-12))
    return a, b


def _variants(d: np.ndarray, net: np.ndarray, g: np.ndarray, v: np.ndarray, conf: np.ndarray) -> dict[str, np.ndarray]:
    d = d * np.median(g[v]) / np.median(d[v])  # eval's per-frame scale first: the maps act on the shape only
    lD, lN, lg = np.log(np.maximum(d, 1e-9)), np.log(np.maximum(net, 1e-9)), np.log(np.where(g > 0, g, 1.0))
    cf, uc = conf >= 0.5, conf < 0.5
    out = {"exported": d}

    def mapped(sel_fit: np.ndarray, x: np.ndarray, y: np.ndarray, robust: bool = False) -> np.ndarray:
        if sel_fit.sum() < 200 or not uc.any():
            return d
        a, b = _fit(x[sel_fit], y[sel_fit], robust)
        p = d.copy()
        p[uc] = np.exp(a + b * lD[uc])
        return p

    mu = float(np.median(lD[uc])) if uc.any() else 0.0
    if (cf & (d > 0)).sum() >= 200 and uc.any():
        a, b = _fit(lN[cf & (d > 0)], lD[cf & (d > 0)], robust=True)
        p = d.copy()
        p[uc] = np.exp(a + b * lN[uc])
        out["self: map of net applied to net"] = p
        p = d.copy()
        p[uc] = np.exp(mu + b * (lD[uc] - mu))
        out["self: its slope applied to exported"] = p
    else:
        out["self: map of net applied to net"] = out["self: its slope applied to exported"] = d
    out["oracle-conf (GT on confident)"] = mapped(cf & v, lD, lg)
    out["oracle-unconf (GT on unconfident)"] = mapped(uc & v, lD, lg)
    for e in EXPAND:
        p = d.copy()
        p[uc] = np.exp(mu + e * (lD[uc] - mu))
        out[f"expand {e}"] = p
    return out


def _slopes(d: np.ndarray, g: np.ndarray, v: np.ndarray, conf: np.ndarray, rows: dict[str, list[float]]) -> None:
    lg = np.log(np.where(g > 0, g, 1.0)).astype(np.float32)
    k = np.ones((5, 5), np.uint8)
    inner = v & ((cv2.dilate(lg, k) - cv2.erode(lg, k)) < 0.05)
    lD = np.log(np.maximum(d, 1e-9))
    for name, sel in (("confident", inner & (conf >= 0.5)), ("unconfident", inner & (conf < 0.5))):
        if sel.sum() >= 300:
            rows[f"{name} b_fwd"].append(_fit(lg[sel], lD[sel])[1])
            rows[f"{name} b_map"].append(_fit(lD[sel], lg[sel])[1])
            rows[f"{name} corr"].append(float(np.corrcoef(lg[sel], lD[sel])[0, 1]))


def probe(run_dir: str | Path, gt_dir: str | Path, cache: str | None) -> tuple[dict[str, tuple[float, float]], dict[str, list[float]]]:
    run = Path(run_dir)
    m = match_gt(run, gt_dir)
    seg = api.recorded_output(run, "optimize_segments", cache)
    sums: dict[str, list[float]] = {}
    rows: dict[str, list[float]] = {f"{n} {s}": [] for n in ("confident", "unconfident") for s in ("b_fwd", "b_map", "corr")}
    for k, gp, fi in zip(m.run_pos, m.depth_files, m.frame_indices):
        if gp is None:
            continue
        d = np.load(run / "depth" / f"{fi:06d}.npy").astype(np.float64)
        conf = np.load(run / "confidence" / f"{fi:06d}.npy")
        g = read_depth_png(gp, m.depth_scale).astype(np.float64)
        g = g if g.shape == d.shape else cv2.resize(g, (d.shape[1], d.shape[0]), interpolation=cv2.INTER_NEAREST)
        net = np.asarray(seg["depths"][k], np.float64)
        v = (g > 0) & (g <= 10.0) & (d > 0) & np.isfinite(d)
        _slopes(d, g, v, conf, rows)
        for name, p in _variants(d, net, g, v, conf).items():
            s = np.median(g[v]) / np.median(p[v])
            e = np.abs(p[v] * s - g[v]) / g[v]
            c = conf[v] >= 0.5
            acc = sums.setdefault(name, [0.0, 0.0, 0.0, 0.0])
            acc[0] += float(e.sum()); acc[1] += e.size; acc[2] += float(e[c].sum()); acc[3] += float(c.sum())
    res = {n: (a[0] / a[1], a[2] / max(a[3], 1.0)) for n, a in sums.items()}
    return res, rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("gt")
    ap.add_argument("--cache", default=os.environ.get("GCVD_FLOW_CACHE"), help="default: the run's own (run.json)")
    a = ap.parse_args()
    res, rows = probe(a.run, a.gt, a.cache)
    print(f"{'variant':38s} {'AbsRel':>7s} {'confident':>9s}")
    for n, (ar, ac) in res.items():
        print(f"{n:38s} {ar:7.4f} {ac:9.4f}")
    for n, x in rows.items():
        if x:
            print(f"{n:22s} median {np.median(x):.3f}  p25 {np.percentile(x, 25):.3f}  p75 {np.percentile(x, 75):.3f}  ({len(x)} frames)")


if __name__ == "__main__":
    main()
