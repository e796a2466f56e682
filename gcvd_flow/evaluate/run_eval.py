"""`gcvd-flow eval`: a finished run (RUN_DIR) against a ground-truth folder.

Ground truth (``load_gt``): the generic layout's ``gt/`` (a ``gcvd-flow synth`` OUT folder or
its ``gt/``): ``poses.txt`` (TUM) and ``depth/*.png``; or a Redwood / ICL-NUIM folder: the
first ``*.log`` and ``depth/*.png``. Depth PNGs are uint16 in 1/``depth_scale`` metres
(1000, or the number in a ``depth_scale`` file). Poses and depth are matched by *source* frame
index (the ``t`` column of the run's poses.txt).

Metrics (``gcvd_flow.evaluate.metrics``): ATE RMSE after Sim(3) Umeyama alignment, RPE
trans / rot over consecutive frames, depth AbsRel / SqRel / RMSE / delta < 1.25 with per-frame
median scaling at the run's working resolution.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from gcvd_flow.engine.errors import UsageError
from gcvd_flow.evaluate import metrics
from gcvd_flow.io.formats import read_depth_png, read_redwood_log, read_tum_poses
from gcvd_flow.io.sources import natural_key


def load_gt(gt: str | Path) -> dict[str, Any]:
    """Ground truth of a dataset folder: {poses (M, 4, 4) T_w_c by source frame, depth_files
    (sorted PNG paths, possibly empty), depth_scale (stored units per metre)}."""
    gt = Path(gt)
    if not gt.exists():
        raise UsageError(f"{gt}: no such directory")
    if (gt / "gt").is_dir():  # a synth OUT folder
        gt = gt / "gt"
    out: dict[str, Any] = {"depth_files": [], "depth_scale": 1000.0}
    if (gt / "poses.txt").exists():
        _, out["poses"] = read_tum_poses(gt / "poses.txt")
    else:
        logs = sorted(gt.glob("*.log"))
        if not logs:
            raise UsageError(f"{gt}: no poses.txt (TUM) or *.log (Redwood) ground truth")
        out["poses"] = read_redwood_log(logs[0])
    if (gt / "depth").is_dir():
        out["depth_files"] = sorted((p for p in (gt / "depth").iterdir() if p.suffix.lower() == ".png"),
                                    key=lambda p: natural_key(p.name))
    if (gt / "depth_scale").exists():
        try:
            out["depth_scale"] = float((gt / "depth_scale").read_text().split()[0])
        except (IndexError, ValueError):
            raise UsageError(f"{gt / 'depth_scale'}: expected one number (stored units per metre)") from None
        if not (np.isfinite(out["depth_scale"]) and out["depth_scale"] > 0):
            raise UsageError(f"{gt / 'depth_scale'}: must be a positive number")
    return out


def trajectory_metrics(est: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """ATE (Sim(3)-aligned), RPE (delta 1) and path length of est vs gt, both (N, 4, 4) T_w_c."""
    res: dict[str, float] = {}
    res.update(metrics.ate(est, gt))
    res.update(metrics.rpe(est, gt, delta=1))
    res["path_length"] = float(metrics.path_length(gt))
    res["ate_percent_of_path"] = 100.0 * res["ate_rmse"] / max(res["path_length"], 1e-12)
    return res


def depth_errors(run: Path, idx: list[int], gt: dict[str, Any], max_depth: float) -> dict[str, Any]:
    """Aggregated depth metrics of run/depth/NNNNNN.npy against the ground-truth PNGs (frames
    without either are skipped); {} when no frame has both."""
    import cv2

    per_frame = []
    for i in idx:
        pred_path = run / "depth" / f"{i:06d}.npy"
        if not pred_path.exists() or i >= len(gt["depth_files"]):
            continue
        pred = np.load(pred_path, allow_pickle=False)
        g = read_depth_png(gt["depth_files"][i], gt["depth_scale"])  # DatasetError names the file
        if g.shape != pred.shape:  # compare at the run's working resolution
            g = cv2.resize(g, (pred.shape[1], pred.shape[0]), interpolation=cv2.INTER_NEAREST)
        per_frame.append(metrics.depth_metrics(pred, g, max_depth=max_depth))
    if not per_frame:
        return {}
    return {**metrics.aggregate_depth_metrics(per_frame), "depth_frames": len(per_frame)}


def evaluate(run_dir: str | Path, gt_dir: str | Path, max_depth: float = 10.0) -> dict[str, Any]:
    """ATE / RPE of poses.txt and depth errors of depth/*.npy against a ground-truth folder."""
    run = Path(run_dir)
    if not (run / "poses.txt").exists():
        raise UsageError(f"{run / 'poses.txt'}: missing (is {run} a finished run?)")
    try:
        cams = json.loads((run / "cameras.json").read_text())
    except (OSError, ValueError) as exc:
        raise UsageError(f"{run / 'cameras.json'}: missing or not valid JSON ({exc})") from None
    stamps, est = read_tum_poses(run / "poses.txt")
    idx = [int(round(t)) for t in stamps]
    gt = load_gt(gt_dir)
    if max(idx) >= len(gt["poses"]):
        raise UsageError(f"{gt_dir}: ground truth has {len(gt['poses'])} poses, the run uses frame {max(idx)}")
    res: dict[str, Any] = {"frames": len(idx)}
    res.update(trajectory_metrics(est, np.asarray(gt["poses"])[idx]))
    if gt["depth_files"]:
        res.update(depth_errors(run, idx, gt, max_depth))
    res["width"], res["height"] = cams.get("width"), cams.get("height")
    return res


def format_metrics(res: dict[str, Any]) -> str:
    """The metrics as a small table (what `gcvd-flow eval` prints without --json)."""
    rows = [("ATE RMSE", "ate_rmse", "m"), ("ATE / path", "ate_percent_of_path", "%"),
            ("RPE trans", "rpe_trans", "m"), ("RPE rot", "rpe_rot", "deg"), ("AbsRel", "abs_rel", ""),
            ("SqRel", "sq_rel", ""), ("RMSE", "rmse", "m"), ("delta<1.25", "delta1", "")]
    lines = [f"{label:<12} {res[k]:10.4f} {unit}" for label, k, unit in rows if k in res]
    lines.append(f"{'frames':<12} {res['frames']:10d}")
    return "\n".join(lines)


def write_metrics(run_dir: str | Path, res: dict[str, Any]) -> Path:
    """RUN_DIR/metrics.json."""
    path = Path(run_dir) / "metrics.json"
    path.write_text(json.dumps(res, indent=1, sort_keys=True))
    return path
