"""`gcvd-flow report RUN_DIR [--gt GT_DIR] [--to report.html]`: one self-contained HTML page
that says in ten seconds whether a run worked.

* the verdict first: good / suspect / failed from the run's own health signals (no ground
  truth needed; ``report/verdict.py``), then with ground truth the metrics (ATE, RPE, AbsRel, δ<1.25, frames /
  keyframes; ``gcvd_flow.evaluate.run_eval``), else the run's health signals (share of pixels
  passing flow consistency, static pixels, valid depth, keyframes and gaps, loop edges found /
  verified / used, pose-graph residual before / after);
* trajectory, top and side view (Sim(3)-aligned to ground truth when given; keyframes, loop
  edges);
* a strip of every N-th frame: RGB, depth (turbo), motion mask;
* per stage: seconds, items, executed / cached, output digest prefix;
* settings: the resolved config with differences from the defaults highlighted, library versions.

Stage outputs are read from the cache the run recorded (run.json ``cache``, or ``cache=``) by
their output digests; without the cache the page still has poses, depth and the tables.

    from gcvd_flow.report import write_report
    write_report("runs/walk", to="runs/walk/report.html", gt=None)
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Any

from gcvd_flow.engine.errors import UsageError
from gcvd_flow.report.collect import ReportData, collect


def build_report(run_dir: str | Path, gt: str | Path | None = None, cache: str | None = None,
                 every: int | None = None) -> str:
    """The report page of RUN_DIR as an HTML string."""
    from gcvd_flow.report.page import render

    return render(collect(run_dir, gt=gt, cache=cache, every=every))


def write_report(run_dir: str | Path, to: str | Path | None = None, gt: str | Path | None = None,
                 cache: str | None = None, every: int | None = None) -> Path:
    """Write the page (default RUN_DIR/report.html) under a temporary name, then rename."""
    return Path(write_report_doc(run_dir, to=to, gt=gt, cache=cache, every=every)["report"])


def write_report_doc(run_dir: str | Path, to: str | Path | None = None, gt: str | Path | None = None,
                     cache: str | None = None, every: int | None = None) -> dict[str, Any]:
    """Write the page like :func:`write_report`; returns what `report --json` prints:
    {"report": path, "verdict": "good" | "suspect" | "failed", "health": [{"name", "value", "status"}]}
    (the verdict from the health signals only, with or without ``gt``: ``report/verdict.py``)."""
    from gcvd_flow.report.page import render
    from gcvd_flow.report.verdict import health_json

    out = check_page_path(Path(to) if to else Path(run_dir) / "report.html")
    data = collect(run_dir, gt=gt, cache=cache, every=every)
    write_page(out, render(data))
    return {"report": str(out), "verdict": data.verdict, "health": health_json(data.signals)}


__all__ = ["ReportData", "build_report", "collect", "write_report", "write_report_doc"]


def check_page_path(out: Path) -> Path:
    """``out`` if a page can be written there: not a directory (``--to`` names a file)."""
    if out.is_dir():
        raise UsageError(f"{out}: is a directory (--to names the page's file, e.g. {out / 'report.html'})")
    return out


def write_page(out: Path, text: str) -> None:
    """Write ``out`` under a temporary name, then rename; a failure is one line naming ``out``."""
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, out)
    except OSError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise UsageError(f"{out}: cannot write the page ({exc.strerror or exc})") from None
