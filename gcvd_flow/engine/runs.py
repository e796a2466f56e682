"""`runs PATH...`: a table of run directories, like `dvc exp show`.

One row per run directory found under the paths (a directory holding ``run.json``; the search
does not descend into a run directory, nor into hidden folders): its name, when it finished
(``run.json``'s modification time), the parameters that *differ* among the listed runs (all of
them with ``--all-params``), the numbers of its ``metrics.json``, and how many stage results it
reused vs computed (from the sweep that made it, else from its ``run.json``).

Everything read is treated as untrusted: a ``run.json`` or ``metrics.json`` of the wrong shape is
one line naming the file (exit 2), never a traceback.
"""

from __future__ import annotations

import csv
import datetime
import io
import json
import math
import os
from pathlib import Path
from typing import Any

from gcvd_flow.engine.errors import UsageError

RUN_FILE = "run.json"
METRICS_FILE = "metrics.json"
SWEEP_FILE = "sweep.json"
MAX_DEPTH = 6  # folder levels searched below each PATH
MAX_RUNS = 10_000


def find_run_dirs(paths: list[str]) -> list[Path]:
    """Run directories at or under ``paths``, in sorted order, each once."""
    found: list[Path] = []
    seen: set[Path] = set()
    for raw in paths:
        root = Path(raw)
        if not root.exists():
            raise UsageError(f"{raw}: no such file or directory")
        if root.is_file():
            if root.name != RUN_FILE:
                raise UsageError(f"{raw}: not a run directory nor a folder of runs")
            root = root.parent
        base_depth = len(root.resolve().parts)
        for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
            here = Path(dirpath)
            if RUN_FILE in filenames:
                dirnames[:] = []
                key = here.resolve()
                if key not in seen:
                    seen.add(key)
                    found.append(here)
                continue
            dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
            if len(here.resolve().parts) - base_depth >= MAX_DEPTH:
                dirnames[:] = []
        if len(found) > MAX_RUNS:
            raise UsageError(f"more than {MAX_RUNS} run directories under {raw}")
    return found


def _read_json(path: Path, what: str) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise UsageError(f"{path}: not a readable {what} ({type(exc).__name__})") from None


def flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    """{"a": {"b": 1}} -> {"a.b": 1}; lists stay values."""
    out: dict[str, Any] = {}
    if isinstance(d, dict):
        for k, v in d.items():
            key = f"{prefix}{k}"
            if isinstance(v, dict) and v:
                out.update(flatten(v, key + "."))
            else:
                out[key] = v
    return out


def _metrics(run: Path) -> dict[str, Any]:
    doc = _read_json(run / METRICS_FILE, "metrics file")
    if doc is None:
        return {}
    if isinstance(doc, dict) and isinstance(doc.get("metrics"), dict):
        doc = doc["metrics"]  # `eval --baseline --json`'s shape
    if not isinstance(doc, dict):
        raise UsageError(f"{run / METRICS_FILE}: expected a JSON object of metrics")
    try:
        flat = flatten(doc)
    except RecursionError:
        raise UsageError(f"{run / METRICS_FILE}: nested too deeply") from None
    return {k: v for k, v in flat.items() if isinstance(v, (int, float, str, bool)) or v is None}


def _stage_counts(stages: Any) -> dict[str, int] | None:
    if not isinstance(stages, list):
        return None
    try:
        return {"computed": sum(1 for s in stages if int(s.get("executed", 0)) > 0),
                "reused": sum(1 for s in stages if int(s.get("executed", 0)) == 0),
                "items_computed": sum(int(s.get("executed", 0)) for s in stages),
                "items_reused": sum(int(s.get("cached", 0)) for s in stages)}
    except (TypeError, ValueError, AttributeError):
        return None


def _sweep_stages(run: Path, cache: dict[Path, dict[str, Any]]) -> list[dict[str, Any]] | None:
    """The stage counts the sweep in the parent folder recorded for ``run`` (if any)."""
    parent = run.resolve().parent
    if parent not in cache:
        doc = _read_json(parent / SWEEP_FILE, "sweep record")
        rows = doc.get("runs") if isinstance(doc, dict) else None
        cache[parent] = {str(r.get("name")): r for r in rows if isinstance(r, dict)} if isinstance(rows, list) else {}
    row = cache[parent].get(run.resolve().name)
    return row.get("stages") if isinstance(row, dict) and isinstance(row.get("stages"), list) else None


def read_run(run: Path, sweeps: dict[Path, dict[str, Any]]) -> dict[str, Any]:
    """One run's row before the column rule: every parameter, metrics, stage counts."""
    p = run / RUN_FILE
    doc = _read_json(p, "run record")
    if not isinstance(doc, dict) or not isinstance(doc.get("config", {}), dict):
        raise UsageError(f"{p}: not a valid run record (expected an object with a config object)")
    inv: dict[str, Any] = doc["invocation"] if isinstance(doc.get("invocation"), dict) else {}
    stages = _sweep_stages(run, sweeps)
    if stages is None and isinstance(doc.get("counts"), dict):
        stages = [{"name": k, **v} for k, v in doc["counts"].items() if isinstance(v, dict)]
    when = datetime.datetime.fromtimestamp(p.stat().st_mtime, datetime.timezone.utc)
    try:
        params = flatten(doc.get("config") or {})
    except RecursionError:
        raise UsageError(f"{p}: config nested too deeply") from None
    return {"name": run.name, "out": str(run), "when": when.strftime("%Y-%m-%d %H:%M:%S UTC"),
            "input": inv.get("input") if isinstance(inv.get("input"), str) else None,
            "all_params": params, "metrics": _metrics(run), "stages": _stage_counts(stages)}


def _canon(v: Any) -> str:
    return json.dumps(v, sort_keys=True, default=str)


def differing_keys(rows: list[dict[str, Any]]) -> list[str]:
    """Parameter keys whose value is not the same in every row (a key missing from some rows
    differs). One run alone: none differ."""
    keys = sorted({k for r in rows for k in r["all_params"]})
    return [k for k in keys if len({_canon(r["all_params"].get(k, "\0missing")) for r in rows}) > 1]


def _sort_value(row: dict[str, Any], key: str) -> Any:
    v = row["metrics"].get(key, row["params"].get(key))
    if isinstance(v, bool) or v is None:
        return None
    if isinstance(v, (int, float)):
        return None if math.isnan(v) else float(v)
    return str(v)


def sort_rows(rows: list[dict[str, Any]], sort: str | None) -> list[dict[str, Any]]:
    """By a metric (or a parameter), ascending; ``-NAME`` descending; rows without it last."""
    if not sort:
        return rows
    key, rev = (sort[1:], True) if sort.startswith("-") else (sort, False)
    if rows and not any(key in r["metrics"] or key in r["params"] for r in rows):
        known = sorted({k for r in rows for k in r["metrics"]} | {k for r in rows for k in r["params"]})
        raise UsageError(f"--sort {key}: no run has this metric or parameter (known: {', '.join(known) or 'none'})")
    have = [r for r in rows if _sort_value(r, key) is not None]
    rest = [r for r in rows if _sort_value(r, key) is None]
    nums = all(isinstance(_sort_value(r, key), float) for r in have)
    have.sort(key=lambda r: _sort_value(r, key) if nums else str(_sort_value(r, key)), reverse=rev)
    return have + rest


def collect(paths: list[str], all_params: bool = False, sort: str | None = None) -> dict[str, Any]:
    """The --json document: {"runs": [{name, out, when, input, params, metrics, stages}],
    "params": [the parameter columns], "metrics": [the metric names]}."""
    dirs = find_run_dirs(paths)
    sweeps: dict[Path, dict[str, Any]] = {}
    rows = [read_run(d, sweeps) for d in dirs]
    keys = sorted({k for r in rows for k in r["all_params"]}) if all_params else differing_keys(rows)
    inputs_differ = len({r["input"] for r in rows}) > 1
    out = []
    for r in rows:
        params = {k: r["all_params"].get(k) for k in keys}
        out.append({"name": r["name"], "out": r["out"], "when": r["when"], "input": r["input"],
                    "params": params, "metrics": r["metrics"], "stages": r["stages"]})
    metrics = sorted({k for r in rows for k, v in r["metrics"].items() if isinstance(v, (int, float))})
    return {"runs": sort_rows(out, sort), "params": keys, "metrics": metrics, "inputs_differ": inputs_differ}


# ------------------------------------------------------------------------------ output


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, (list, dict)):
        return json.dumps(v, separators=(",", ":"))
    return str(v)


def table(doc: dict[str, Any], metric_columns: tuple[str, ...] = ()) -> tuple[list[str], list[list[str]]]:
    """Header and cells: name, when, [input], params, metrics (those of ``metric_columns`` that
    occur, else every numeric one), stages reused / computed."""
    metrics = [m for m in metric_columns if m in doc["metrics"]] or list(doc["metrics"])
    head = ["name", "when"] + (["input"] if doc.get("inputs_differ") else []) + list(doc["params"]) + metrics \
        + ["stages reused/computed"]
    cells = []
    for r in doc["runs"]:
        st = r["stages"]
        stages = f"{st['reused']}/{st['computed']}" if st else ""
        cells.append([r["name"], r["when"]] + ([r["input"] or ""] if doc.get("inputs_differ") else [])
                     + [_cell(r["params"].get(k)) for k in doc["params"]]
                     + [_cell(r["metrics"].get(m)) for m in metrics] + [stages])
    return head, cells


def format_text(doc: dict[str, Any], metric_columns: tuple[str, ...] = ()) -> str:
    if not doc["runs"]:
        return "no run directories found"
    head, cells = table(doc, metric_columns)
    widths = [max(len(h), *(len(c[i]) for c in cells)) for i, h in enumerate(head)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(head, widths)), "  ".join("-" * w for w in widths)]
    lines += ["  ".join(c.ljust(w) for c, w in zip(row, widths)) for row in cells]
    return "\n".join(lines)


def format_md(doc: dict[str, Any], metric_columns: tuple[str, ...] = ()) -> str:
    head, cells = table(doc, metric_columns)

    def esc(s: str) -> str:
        return s.replace("|", "\\|")

    lines = ["| " + " | ".join(esc(h) for h in head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(esc(c) for c in row) + " |" for row in cells]
    return "\n".join(lines)


def format_csv(doc: dict[str, Any]) -> str:
    head, cells = table(doc)  # every metric
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(head)
    w.writerows(cells)
    return buf.getvalue().rstrip("\n")


def json_doc(doc: dict[str, Any]) -> dict[str, Any]:
    return {"runs": doc["runs"], "params": doc["params"]}
