"""The gcvd-flow Python API: the CLI's verbs, with the GCVD pipeline as the default, and the
results loaded back.

    from gcvd_flow import api
    res = api.run(api.Invocation(input="walk.mp4", out="runs/walk", sets=["keyframes.delta=0.15"]))
    plan = api.plan(api.Invocation(input="walk.mp4", out="runs/walk"))

    r = api.load("runs/walk")        # r.poses (N, 4, 4) T_w_c, r.depth[k] (read when indexed),
                                     # r.cameras (cameras.json), r.K, r.timestamps, r.frame_indices
    m = api.eval("runs/loop", gt="clips/loop")          # the metrics dict (also RUN_DIR/metrics.json)
    page = api.report("runs/loop", gt="clips/loop")     # RUN_DIR/report.html
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gcvd_flow.engine import api as _engine
from gcvd_flow.engine.api import fsck, gc, open_store, plan, read_run_dir, recorded_output, run, status, why
from gcvd_flow.engine.errors import UsageError
from gcvd_flow.runtime import quiet_openmp

quiet_openmp()  # the Python API is an entry point of the product (gcvd_flow/runtime.py)

PIPELINE = "gcvd"


@dataclass
class Invocation(_engine.Invocation):
    pipeline: str = PIPELINE


@dataclass
class Result:
    """A finished run loaded from RUN_DIR. ``depth[k]`` reads depth/NNNNNN.npy of frame k when
    indexed (float32 (H, W), one global scale with the poses, 0 = invalid)."""

    run_dir: Path
    poses: np.ndarray  # (N, 4, 4) float64 camera-to-world, OpenCV axes
    timestamps: np.ndarray  # (N,) poses.txt's t: seconds where the input has them, else frame index
    frame_indices: list[int]  # source frame index of each frame
    K: np.ndarray  # (3, 3) at working resolution
    width: int
    height: int
    cameras: dict[str, Any]  # cameras.json as written
    depth: Sequence[np.ndarray]
    keyframes: list[int] = field(default_factory=list)  # source frame indices
    metrics: dict[str, Any] | None = None  # metrics.json of `gcvd-flow eval`, if any
    # confidence[k]: confidence/NNNNNN.npy of frame k (float32 in [0, 1], 0 = unmeasured), read
    # when indexed; None when the run directory has none
    confidence: Sequence[np.ndarray] | None = None

    def __len__(self) -> int:
        return len(self.poses)


def load(run_dir: str | Path) -> Result:
    """Load a finished run (poses, lazy depth, cameras); one-line UsageError naming a bad file."""
    from gcvd_flow.engine import jsonio
    from gcvd_flow.io.formats import read_tum_poses
    from gcvd_flow.io.run_dir import load_run, read_cameras

    data = load_run(run_dir)
    root = Path(run_dir)
    cams = read_cameras(root)  # checked by load_run
    stamps, _ = read_tum_poses(root / "poses.txt")
    try:
        metrics = jsonio.load_optional(root / "metrics.json", "metrics file")
    except UsageError:  # unreadable: as if not evaluated
        metrics = None
    conf = None
    if all((root / "confidence" / f"{data.name(k)}.npy").is_file() for k in range(len(data))):
        from gcvd_flow.engine.dag import MapValue

        conf = MapValue(lambda k: np.load(root / "confidence" / f"{data.name(k)}.npy", allow_pickle=False),
                        len(data), None)
    return Result(root, data.poses, stamps, list(data.frame_indices), data.K, data.width, data.height, cams,
                  data.depths, [int(i) for i in cams.get("keyframes") or []], metrics, conf)


def eval(run_dir: str | Path, gt: str | Path, max_depth: float = 10.0, write: bool = True) -> dict[str, Any]:  # noqa: A001
    """`gcvd-flow eval`: ATE / RPE / depth errors against a ground-truth folder; writes
    RUN_DIR/metrics.json unless ``write=False``."""
    from gcvd_flow.evaluate.run_eval import evaluate, write_metrics

    res = evaluate(run_dir, gt, max_depth)
    if write:
        write_metrics(run_dir, res)
    return res


def report(run_dir: str | Path, gt: str | Path | None = None, to: str | Path | None = None,
           cache: str | None = None, every: int | None = None) -> Path:
    """`gcvd-flow report`: write the self-contained HTML page (default RUN_DIR/report.html)."""
    from gcvd_flow.report import write_report

    return write_report(run_dir, to=to, gt=gt, cache=cache, every=every)


def compare(run_a: str | Path, run_b: str | Path, cache: str | None = None) -> dict[str, Any]:
    """`gcvd-flow compare`: per stage, equal outputs or how far apart (B against A)."""
    from gcvd_flow.evaluate.compare import compare_runs

    return compare_runs(run_a, run_b, cache=cache)


def sweep(inv: Invocation, grid: list[str], gt: str | Path | None = None, max_runs: int = 64) -> dict[str, Any]:
    """`gcvd-flow sweep`: every combination of ``grid`` (``["keyframes.delta=0.05,0.1"]``) run
    into ``inv.out/<key>=<value>`` with ``inv``'s settings, through one cache; with ``gt`` each run
    is evaluated (its metrics.json). Returns the --json document ({"runs": [...], "failed": n})."""
    from gcvd_flow.engine import sweep as _sweep
    from gcvd_flow.evaluate.run_eval import evaluate_run

    plan_ = _sweep.prepare(str(inv.input), str(inv.out), inv, list(grid), gt=str(gt) if gt else None,
                           max_runs=max_runs, can_evaluate=True)
    return _sweep.run_sweep(plan_, log=_engine._stderr, evaluate=evaluate_run)


def runs(*paths: str | Path, all_params: bool = False, sort: str | None = None) -> dict[str, Any]:
    """`gcvd-flow runs --json`: one row per run directory under ``paths`` (name, params that
    differ, metrics, stages reused / computed)."""
    from gcvd_flow.engine import runs as _runs

    return _runs.collect([str(p) for p in paths], all_params=all_params, sort=sort)


__all__ = ["Invocation", "Result", "run", "plan", "why", "status", "recorded_output", "fsck", "gc", "open_store",
           "read_run_dir", "load", "eval", "report", "compare", "sweep", "runs"]
