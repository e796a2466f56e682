"""Where does a run's scale drift come from? Per-stage keyframe scales and the loop edges' fate.

For a finished run (or one stopped with ``--until bundle_adjustment``) and its ground truth, from
the run's cache: the keyframe poses after optimize_keyframes, pose_graph and bundle_adjustment,
each Sim(3)-aligned to the ground truth (ATE) with the scale fitted per 20-frame window of
keyframes (as ``gcvd-flow eval``'s "scale drift between 20-frame windows", on keyframes only);
bundle adjustment's per-keyframe depth scale (spread = max / min, the report's "scale spread");
every loop edge: its rotation disagreement with odometry (the pose graph's gate) and with the
ground truth, and its translation length against the ground truth's, in the odometry's scale.

    PYTHONPATH=. .venv/bin/python benchmarks/scale_probe.py RUN_DIR GT_DIR [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Callable

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from gcvd_flow.engine.store import Store  # noqa: E402
from gcvd_flow.evaluate import metrics as M  # noqa: E402
from gcvd_flow.evaluate.run_eval import load_gt  # noqa: E402
from gcvd_flow.report.collect import recorded_part  # noqa: E402

WINDOW = 20  # frames per window, as gcvd-flow eval (--window: sparse keyframes need longer ones)


def _rot_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def window_scales(est: np.ndarray, gt: np.ndarray, frames: list[int], window: int = WINDOW) -> np.ndarray:
    """Per ``window``-frame window (by source frame index) holding 3+ keyframes: Umeyama scale of
    its keyframes / the whole one's."""
    s_all, _, _ = M.umeyama_alignment(est[:, :3, 3], gt[:, :3, 3])
    out = []
    f = np.asarray(frames)
    for a in range(0, int(f.max()) + 1, window):
        sel = (f >= a) & (f < a + window)
        if sel.sum() >= 3:
            s, _, _ = M.umeyama_alignment(est[sel, :3, 3], gt[sel, :3, 3])
            out.append(s / s_all)
    return np.asarray(out)


def recorded_run(run_dir: Path) -> tuple[Callable[..., Any], list[int], list[int]]:
    """A finished run read from its cache: (part(stage, *path): a stage's recorded output,
    optimize_keyframes' keyframes (positions in the run's frames), the same as source frame indices)."""
    doc = json.loads((run_dir / "run.json").read_text())
    store = Store(Path(doc["cache"]), verify=False)
    part = lambda stage, *path: recorded_part(doc, store, stage, path)  # noqa: E731
    okf_frames = [int(i) for i in part("optimize_keyframes", "keyframes")]
    idx = [int(i) for i in json.loads((run_dir / "cameras.json").read_text())["frame_indices"]] \
        if (run_dir / "cameras.json").exists() else None
    return part, okf_frames, [idx[k] for k in okf_frames] if idx else okf_frames


def probe(run_dir: Path, gt_dir: Path, window: int = WINDOW) -> dict:
    part, okf_frames, src = recorded_run(run_dir)
    gt_all = np.asarray(load_gt(gt_dir)["poses"])
    gt = gt_all[src]
    out: dict = {"keyframes": len(src)}
    for stage in ("optimize_keyframes", "pose_graph", "bundle_adjustment"):
        try:
            est = np.asarray(part(stage, "poses"), np.float64)
        except Exception as exc:  # noqa: BLE001 - a stage the run did not reach
            out[stage] = f"absent ({exc})"
            continue
        ws = window_scales(est, gt, src, window)
        out[stage] = {"ate": M.ate(est, gt)["ate_rmse"], "scale_window": [round(float(s), 3) for s in ws],
                      "scale_spread": float(ws.max() / ws.min()) if len(ws) else 1.0}
    try:
        ds = np.asarray(part("bundle_adjustment", "depth_scale"), np.float64)
        out["ba_depth_scale"] = {"min": float(ds.min()), "max": float(ds.max()), "spread": float(ds.max() / ds.min()),
                                 "values": [round(float(v), 3) for v in ds]}
    except Exception:  # noqa: BLE001
        pass
    T = np.asarray(part("optimize_keyframes", "poses"), np.float64)
    s_all, _, _ = M.umeyama_alignment(T[:, :3, 3], gt[:, :3, 3])
    rejected = {(int(r["i"]), int(r["j"])) for r in (part("pose_graph", "rejected_loops")
                                                      if part("pose_graph", "enabled") else [])}
    loops = []
    for e in part("optimize_edges", "edges"):
        a, b = int(e["a"]), int(e["b"])
        T_a_b = np.linalg.inv(np.asarray(e["T_b_a"], np.float64))
        odo = np.linalg.inv(T[a]) @ T[b]
        true = np.linalg.inv(gt[a]) @ gt[b]
        t_true = max(float(np.linalg.norm(true[:3, 3])), 1e-9)
        loops.append({"i": int(e["i"]), "j": int(e["j"]), "used": (int(e["i"]), int(e["j"])) not in rejected,
                      "rot_vs_odometry_deg": _rot_deg(odo[:3, :3].T @ T_a_b[:3, :3]),
                      "rot_vs_gt_deg": _rot_deg(true[:3, :3].T @ T_a_b[:3, :3]),
                      "odometry_rot_vs_gt_deg": _rot_deg(true[:3, :3].T @ odo[:3, :3]),
                      "t_len_edge_over_gt": float(np.linalg.norm(T_a_b[:3, 3])) * s_all / t_true,
                      "t_len_odometry_over_gt": float(np.linalg.norm(odo[:3, 3])) * s_all / t_true})
    out["loops"] = loops
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("gt_dir", type=Path)
    ap.add_argument("--window", type=int, default=WINDOW, help="frames per window (default 20)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    res = probe(a.run_dir, a.gt_dir, a.window)
    if a.json:
        print(json.dumps(res, indent=1))
        return
    print(f"{res['keyframes']} keyframes")
    for stage in ("optimize_keyframes", "pose_graph", "bundle_adjustment"):
        r = res[stage]
        if isinstance(r, str):
            print(f"  {stage:<19} {r}")
            continue
        ws = r["scale_window"] or [float("nan")]
        print(f"  {stage:<19} keyframe ATE {r['ate']:.4f}  window scales {min(ws):.3f}-{max(ws):.3f}  {ws}")
    if "ba_depth_scale" in res:
        d = res["ba_depth_scale"]
        print(f"  BA depth scale {d['min']:.3f}-{d['max']:.3f} (spread {d['spread']:.2f})")
    for lp in res["loops"]:
        print(f"  loop {lp['i']:>4}-{lp['j']:<4} {'used' if lp['used'] else 'REJECTED':<8} rot vs odometry "
              f"{lp['rot_vs_odometry_deg']:6.2f} deg, vs gt {lp['rot_vs_gt_deg']:6.2f} (odometry vs gt "
              f"{lp['odometry_rot_vs_gt_deg']:5.2f}); |t| edge/gt {lp['t_len_edge_over_gt']:.3f}, "
              f"odometry/gt {lp['t_len_odometry_over_gt']:.3f}")


if __name__ == "__main__":
    main()
