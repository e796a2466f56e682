"""`runs PATH...`: a table of run directories, like `dvc exp show`.

One row per run directory found under the paths (a directory holding ``run.json``; the search
does not descend into a run directory, nor into hidden folders): its name, when it finished
(``run.json``'s modification time), the parameters that *differ* among the listed runs (all of
them with ``--all-params``), the numbers of its ``metrics.json``, and how many stage results it
reused vs computed (from the sweep that made it, else from its ``run.json``).

Everything read is treated as untrusted (a folder someone handed over): files are read through
``jsonio`` (regular files only, never a FIFO or a device; size, nesting and numbers bounded), and a
``run.json`` / ``metrics.json`` / ``sweep.json`` of the wrong shape is one line naming the file
(exit 2), never a traceback nor a hang. ``collect(..., keep_broken=True)`` (the `report DIR`
index) lists such a run with its error instead, so one broken run does not hide the others.
"""

from __future__ import annotations

import csv
import datetime
import io
import json
import math
import os
from pathlib import Path
from typing import Any, Callable

from gcvd_flow.engine import jsonio
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
    """The JSON document at ``path`` (None when absent); one-line UsageError naming it when it is
    not a regular file, too large, too deep, holds an out-of-range number or is no JSON."""
    return jsonio.load_optional(path, what, limit=jsonio.RUN_FILE_BYTES)


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
    flat = flatten(doc)  # depth bounded by jsonio
    return {k: v for k, v in flat.items() if isinstance(v, (int, float, str, bool)) or v is None}


def _count(s: Any, key: str) -> int:
    """A stage's item count: a non-negative integer (ValueError otherwise)."""
    v = s.get(key, 0) if isinstance(s, dict) else None
    if isinstance(v, float) and v.is_integer():
        v = int(v)
    if not isinstance(v, int) or isinstance(v, bool) or v < 0:
        raise ValueError(key)
    return v


def _stage_counts(stages: Any) -> dict[str, int] | None:
    """Stages reused / computed and their items; None when any count is not a count."""
    if not isinstance(stages, list):
        return None
    try:
        executed = [_count(s, "executed") for s in stages]
        cached = [_count(s, "cached") for s in stages]
    except ValueError:
        return None
    return {"computed": sum(1 for n in executed if n > 0), "reused": sum(1 for n in executed if n == 0),
            "items_computed": sum(executed), "items_reused": sum(cached)}


def _sweep_stages(run: Path, cache: dict[Path, dict[str, Any]],
                  notes: list[str] | None = None) -> list[dict[str, Any]] | None:
    """The stage counts the sweep in the parent folder recorded for ``run`` (if any). An
    unreadable sweep.json is a UsageError, or with ``notes`` a note (run.json's counts serve)."""
    parent = run.resolve().parent
    if parent not in cache:
        try:
            doc = _read_json(parent / SWEEP_FILE, "sweep record")
        except UsageError as exc:
            if notes is None:
                raise
            notes.append(str(exc))
            doc = None
        rows = doc.get("runs") if isinstance(doc, dict) else None
        cache[parent] = {str(r.get("name")): r for r in rows if isinstance(r, dict)} if isinstance(rows, list) else {}
    row = cache[parent].get(run.resolve().name)
    return row.get("stages") if isinstance(row, dict) and isinstance(row.get("stages"), list) else None


def read_run(run: Path, sweeps: dict[Path, dict[str, Any]], notes: list[str] | None = None) -> dict[str, Any]:
    """One run's row before the column rule: every parameter, metrics, stage counts."""
    p = run / RUN_FILE
    doc = _read_json(p, "run record")
    if not isinstance(doc, dict) or not isinstance(doc.get("config", {}), dict):
        raise UsageError(f"{p}: not a valid run record (expected an object with a config object)")
    inv: dict[str, Any] = doc["invocation"] if isinstance(doc.get("invocation"), dict) else {}
    stages = _sweep_stages(run, sweeps, notes)
    if stages is None and isinstance(doc.get("counts"), dict):
        stages = [{"name": k, **v} for k, v in doc["counts"].items() if isinstance(v, dict)]
    when = datetime.datetime.fromtimestamp(p.stat().st_mtime, datetime.timezone.utc)
    params = flatten(doc.get("config") or {})  # depth bounded by jsonio
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


def collect(paths: list[str], all_params: bool = False, sort: str | None = None,
            keep_broken: bool = False) -> dict[str, Any]:
    """The --json document: {"runs": [{name, out, when, input, params, metrics, stages}],
    "params": [the parameter columns], "metrics": [the metric names]}. A run whose files are
    unreadable is a UsageError, or with ``keep_broken`` a row of "broken": [{name, out, error}]
    (and an unreadable sweep.json a line of "notes")."""
    dirs = find_run_dirs(paths)
    sweeps: dict[Path, dict[str, Any]] = {}
    notes: list[str] | None = [] if keep_broken else None
    rows, broken = [], []
    for d in dirs:
        try:
            rows.append(read_run(d, sweeps, notes))
        except UsageError as exc:
            if not keep_broken:
                raise
            broken.append({"name": d.name, "out": str(d), "error": str(exc)})
    keys = sorted({k for r in rows for k in r["all_params"]}) if all_params else differing_keys(rows)
    inputs_differ = len({r["input"] for r in rows}) > 1
    out = []
    for r in rows:
        params = {k: r["all_params"].get(k) for k in keys}
        out.append({"name": r["name"], "out": r["out"], "when": r["when"], "input": r["input"],
                    "params": params, "metrics": r["metrics"], "stages": r["stages"]})
    metrics = sorted({k for r in rows for k, v in r["metrics"].items() if isinstance(v, (int, float))})
    doc = {"runs": sort_rows(out, sort), "params": keys, "metrics": metrics, "inputs_differ": inputs_differ}
    if keep_broken:
        doc.update(broken=broken, notes=notes or [])
    return doc


# ------------------------------------------------------------------------------ output


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float) or (isinstance(v, int) and abs(v) >= 10 ** 15):
        return f"{v:.4g}"
    if isinstance(v, (list, dict)):
        return json.dumps(v, separators=(",", ":"))
    return str(v)


FORMULA_PREFIXES = ("=", "+", "-", "@", "\t", "\r")


def csv_safe(text: str) -> str:
    """A text cell a spreadsheet will not run as a formula (OWASP "CSV injection"): a leading
    = + - @ tab or carriage return gets a single quote in front."""
    return "'" + text if text.startswith(FORMULA_PREFIXES) else text


def table(doc: dict[str, Any], metric_columns: tuple[str, ...] = (),
          text_cell: Callable[[str], str] = str) -> tuple[list[str], list[list[str]]]:
    """Header and cells: name, when, [input], params, metrics (those of ``metric_columns`` that
    occur, else every numeric one), stages reused / computed. ``text_cell`` is applied to the
    cells that hold text (not numbers): names, inputs, string values."""

    def cell(v: Any) -> str:
        return text_cell(v) if isinstance(v, str) else _cell(v)

    metrics = [m for m in metric_columns if m in doc["metrics"]] or list(doc["metrics"])
    head = ["name", "when"] + (["input"] if doc.get("inputs_differ") else []) + list(doc["params"]) + metrics \
        + ["stages reused/computed"]
    cells = []
    for r in doc["runs"]:
        st = r["stages"]
        stages = f"{st['reused']}/{st['computed']}" if st else ""
        cells.append([cell(r["name"]), r["when"]] + ([cell(r["input"] or "")] if doc.get("inputs_differ") else [])
                     + [cell(r["params"].get(k)) for k in doc["params"]]
                     + [cell(r["metrics"].get(m)) for m in metrics] + [stages])
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
    """Every metric; text (names, string parameters, headers) formula-escaped, numbers as they are."""
    head, cells = table(doc, text_cell=csv_safe)
    return "\n".join(_csv_line(row) for row in [[csv_safe(h) for h in head], *cells])


def _csv_line(cells: list[str]) -> str:
    """One CSV record without its line end. Written with a CRLF terminator so that a cell holding
    a CR (not only a LF) is quoted, then the CRLF is cut: records end in LF."""
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\r\n").writerow(cells)
    return buf.getvalue()[:-2]


def json_doc(doc: dict[str, Any]) -> dict[str, Any]:
    return {"runs": doc["runs"], "params": doc["params"]}
