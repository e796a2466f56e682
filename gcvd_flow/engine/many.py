"""`run-many`: many inputs through one DAG definition and one cache.

Inputs run one after the other, each into ``DIR/<input name>``, sharing one item executor (one
process pool or one Dask cluster, started once) and the cache, so a clip that shares items with
an earlier one (same frames, same settings) reuses them. A failing input is reported and the
others still run; the exit code is the number of failures (at most 100).
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

from gcvd_flow.engine.errors import UsageError

MAX_EXIT = 100


def run_dir_names(inputs: list[str]) -> list[str]:
    """One distinct directory name per input: its file stem or folder name (-2, -3 on clashes)."""
    names: list[str] = []
    seen: dict[str, int] = {}
    for inp in inputs:
        p = Path(inp.rstrip("/")) if inp.rstrip("/") else Path(inp)
        base = (p.stem if p.suffix and not p.is_dir() else p.name) or "input"
        n = seen.get(base, 0) + 1
        seen[base] = n
        names.append(base if n == 1 else f"{base}-{n}")
    return names


def _row(inp: str, out: Path, res: dict[str, Any] | None, seconds: float, error: str | None) -> dict[str, Any]:
    row: dict[str, Any] = {"input": inp, "out": str(out), "ok": error is None, "seconds": round(seconds, 3)}
    if res is not None:
        stages = res.get("stages") or []
        first = stages[0] if stages else {"executed": 0, "cached": 0}
        row.update(items=first["executed"] + first["cached"], executed=sum(s["executed"] for s in stages),
                   cache_hits=sum(s["cached"] for s in stages))
    if error is not None:
        row["error"] = error
    return row


def run_many(inputs: list[str], out_root: str, base: Any, log: Callable[[str], None]) -> dict[str, Any]:
    """Run every input with the settings of ``base`` (an api.Invocation); never stops early."""
    from gcvd_flow.engine import api
    from gcvd_flow.engine.errors import StoreError
    from gcvd_flow.engine.executors import make_executor

    if not inputs:
        raise UsageError("run-many: no INPUT given")
    spec = api.load_spec(base.pipeline, allow_module_ref=True)
    root = Path(out_root)
    executor = None
    if base.executor == "dask" or base.jobs > 1:
        executor = make_executor(base.jobs, spec.pipeline.worker_init, base.executor, base.scheduler)
    rows = []
    t_all = time.perf_counter()
    try:
        for inp, name in zip(inputs, run_dir_names(inputs)):
            out = root / name
            t0 = time.perf_counter()
            try:
                res = api.run(replace(base, input=inp, out=str(out)), log=lambda m, n=name: log(f"[{n}] {m}"),
                              executor=executor)
                rows.append(_row(inp, out, res, time.perf_counter() - t0, None))
            except KeyboardInterrupt:
                raise
            except (UsageError, StoreError, OSError) as exc:
                rows.append(_row(inp, out, None, time.perf_counter() - t0, str(exc).splitlines()[0] if str(exc) else type(exc).__name__))
            except Exception as exc:  # noqa: BLE001 - one input's bug must not stop the others
                rows.append(_row(inp, out, None, time.perf_counter() - t0, f"{type(exc).__name__}: {exc}".splitlines()[0]))
            if not rows[-1]["ok"]:
                log(f"[{name}] failed: {rows[-1]['error']}")
    finally:
        if executor is not None:
            executor.close()
    failed = sum(1 for r in rows if not r["ok"])
    return {"runs": rows, "failed": failed, "seconds": round(time.perf_counter() - t_all, 3)}


def format_table(doc: dict[str, Any]) -> str:
    head = f"{'input':<28} {'status':<7} {'items':>6} {'executed':>9} {'cache hits':>10} {'seconds':>8}"
    lines = [head, "-" * len(head)]
    for r in doc["runs"]:
        name = Path(r["input"]).name or r["input"]
        if r["ok"]:
            lines.append(f"{name[:28]:<28} {'ok':<7} {r['items']:>6} {r['executed']:>9} {r['cache_hits']:>10} "
                         f"{r['seconds']:>8.2f}")
        else:
            lines.append(f"{name[:28]:<28} {'FAILED':<7} {'':>6} {'':>9} {'':>10} {r['seconds']:>8.2f}  {r['error']}")
    n = len(doc["runs"])
    lines.append(f"{n - doc['failed']} of {n} inputs ok, {doc['failed']} failed, {doc['seconds']:.1f} s")
    return "\n".join(lines)


def exit_code(doc: dict[str, Any]) -> int:
    return min(int(doc["failed"]), MAX_EXIT)
