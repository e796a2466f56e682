"""Bundle adjustment again, offline, on a finished run's recorded inputs: does a setting move the scale?

Reads from the run's cache what the bundle_adjustment stage read (the pose graph's keyframe poses,
optimize_keyframes' depths and keyframes, association's edge flows, the calibrated K), adjusts with
``key=value`` overrides of ``BundleAdjustmentSettings``, and prints the keyframe ATE and the window
scales (``scale_probe.window_scales``: each 20-frame window's Sim(3) scale over the whole
trajectory's) before and after. One adjustment takes seconds where a run takes minutes, so a
setting can be tried over the four turns of ``benchmarks/bench_orientation.py`` at once. Runs made
with ``--masks`` are adjusted without the user's masks (a probe, not the stage).

    PYTHONPATH=. .venv/bin/python benchmarks/ba_probe.py RUN_DIR GT_DIR [robust_px=1.0 ...] [--json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from scale_probe import recorded_run, window_scales  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from gcvd_flow.evaluate import metrics as M  # noqa: E402
from gcvd_flow.evaluate.run_eval import load_gt  # noqa: E402
from gcvd_flow.pipeline.optimize import _flow_dict  # noqa: E402
from gcvd_flow.stages.optimize import bundle_adjustment as ba_mod  # noqa: E402
from gcvd_flow.stages.optimize.params import BundleAdjustmentSettings  # noqa: E402


def overrides(pairs: list[str]) -> dict[str, Any]:
    """``key=value`` strings -> BundleAdjustmentSettings fields, each value in its field's type."""
    fields = {f.name: f for f in dataclasses.fields(BundleAdjustmentSettings)}
    out: dict[str, Any] = {}
    for a in pairs:
        k, _, v = a.partition("=")
        if k not in fields:
            print(f"ba_probe: {k!r} is no bundle_adjustment setting ({', '.join(sorted(fields))})", file=sys.stderr)
            sys.exit(2)
        kind = type(getattr(BundleAdjustmentSettings(), k))
        out[k] = (v.lower() in ("1", "true", "yes")) if kind is bool else kind(v)
    return out


def summary(poses: np.ndarray, gt: np.ndarray, frames: list[int]) -> dict[str, Any]:
    """Keyframe ATE (m, Sim(3)-aligned) and window scales of poses (K, 4, 4) T_w_c against gt."""
    return {"keyframe_ate": float(M.ate(poses, gt)["ate_rmse"]),
            "window_scales": [round(float(x), 3) for x in window_scales(poses, gt, frames)]}


def probe(run_dir: Path, gt_dir: Path, settings: dict[str, Any]) -> dict[str, Any]:
    part, kfs, src = recorded_run(run_dir)
    depths = [np.asarray(d) for d in part("optimize_keyframes", "depths")]
    poses = np.asarray(part("pose_graph", "poses"), np.float64)
    edges = {(int(e["i"]), int(e["j"])): _flow_dict(e) for e in part("association", "edge_flows")}
    K = np.asarray(part("calibrate", "K"), np.float64)
    gt = np.asarray(load_gt(gt_dir)["poses"])[src]
    with threadpool_limits(limits=1, user_api="blas"):  # as the stage: one BLAS thread
        res = ba_mod.bundle_adjust(poses, depths, edges, kfs, K, dataclasses.replace(BundleAdjustmentSettings(), **settings))
    return {"settings": settings, "before": summary(poses, gt, src), "after": summary(res["poses"], gt, src),
            "median_px": [res["initial_median_px"], res["final_median_px"]], "iterations": res["iterations"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("gt", type=Path)
    ap.add_argument("settings", nargs="*", help="key=value overrides of BundleAdjustmentSettings")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    out = probe(a.run, a.gt, overrides(a.settings))
    if a.json:
        print(json.dumps(out))
        return
    for k in ("before", "after"):
        s = out[k]
        print(f"{k:6s} keyframe ATE {s['keyframe_ate']:.4f} m  window scales {s['window_scales']}")
    print(f"median reprojection {out['median_px'][0]:.3f} -> {out['median_px'][1]:.3f} px, "
          f"{out['iterations']} iterations, settings {out['settings']}")


if __name__ == "__main__":
    main()
