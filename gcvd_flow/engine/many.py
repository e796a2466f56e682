"""`run-many`: many inputs through one DAG definition and one cache.

Each input runs into ``DIR/<input name>`` (made unique: ``run_dir_names``), all sharing one item executor (one process pool or
one Dask cluster, started once) and the cache, so a clip that shares items with an earlier one
(same frames, same settings) reuses them. With an executor, the map stages that come before the
first whole stage (for GCVD: ingest, flow, masks, priors) run for all inputs at once, so the
items of different clips interleave on the workers; then every input runs to the end, one after
the other (the whole stages set process-wide thread counts of the numeric libraries, so two of
them must not share a process). A failing input is reported and the others still run; the exit
code is the number of failures (at most 100).
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

from gcvd_flow.engine.errors import UsageError

MAX_EXIT = 100


def _prefixed(log: Callable[[str], None], name: str) -> Callable[[str], None]:
    """``log`` with every line prefixed by the input's run-dir name."""
    return lambda m: log(f"[{name}] {m}")


def run_dir_names(inputs: list[str]) -> list[str]:
    """One distinct directory name per input: its file stem or folder name; on a clash the
    later input gets the first free ``NAME-2``, ``NAME-3``, ... not already taken by any input's
    own name (inputs a/clip, b/clip, c/clip-2 give clip, clip-3, clip-2), so no two inputs
    ever share a run directory."""
    bases = []
    for inp in inputs:
        p = Path(inp.rstrip("/")) if inp.rstrip("/") else Path(inp)
        bases.append((p.stem if p.suffix and not p.is_dir() else p.name) or "input")
    taken = set(bases)  # every input's own name is reserved for the first input bearing it
    names: list[str] = []
    used: set[str] = set()
    for base in bases:
        name, n = base, 1
        while name in used or (name != base and name in taken):
            n += 1
            name = f"{base}-{n}"
        used.add(name)
        names.append(name)
    assert len(set(names)) == len(names)
    return names


def _row(inp: str, out: Path, res: dict[str, Any] | None, seconds: float, error: str | None,
         early: int = 0) -> dict[str, Any]:
    """A summary row; ``early`` items were computed in the interleaved map-stage pass and show
    as cache hits in the final pass (they count as executed here)."""
    row: dict[str, Any] = {"input": inp, "out": str(out), "ok": error is None, "seconds": round(seconds, 3)}
    if res is not None:
        stages = res.get("stages") or []
        first = stages[0] if stages else {"executed": 0, "cached": 0}
        row.update(items=first["executed"] + first["cached"], executed=sum(s["executed"] for s in stages) + early,
                   cache_hits=sum(s["cached"] for s in stages) - early, interleaved=early)
    if error is not None:
        row["error"] = error
    return row


def run_many(inputs: list[str], out_root: str, base: Any, log: Callable[[str], None]) -> dict[str, Any]:
    """Run every input with the settings of ``base`` (an api.Invocation); never stops early."""
    from gcvd_flow.engine import api
    from gcvd_flow.engine.errors import StoreError
    from gcvd_flow.engine.executors import closing, make_executor, resolve_jobs

    if not inputs:
        raise UsageError("run-many: no INPUT given")
    spec = api.load_spec(base.pipeline, allow_module_ref=True)
    root = Path(out_root)
    executor = None
    if base.executor == "dask" or resolve_jobs(base.jobs) > 1:
        executor = make_executor(base.jobs, spec.pipeline.worker_init, base.executor, base.scheduler)
    rows = []
    t_all = time.perf_counter()
    names = run_dir_names(inputs)
    # an interrupt (Ctrl-C, SIGTERM, SIGHUP) ends the shared workers at once (executors.closing)
    with closing(executor) if executor is not None else contextlib.nullcontext():
        early = _map_stages_of_all_inputs(inputs, names, root, base, spec, executor, log) if executor else {}
        for inp, name in zip(inputs, names):
            out = root / name
            t0 = time.perf_counter()
            try:
                res = api.run(replace(base, input=inp, out=str(out)), log=_prefixed(log, name),
                              executor=executor)
                rows.append(_row(inp, out, res, time.perf_counter() - t0 + early.get(name, (0, 0.0))[1], None,
                                 early.get(name, (0, 0.0))[0]))
            except KeyboardInterrupt:
                raise
            except (UsageError, StoreError, OSError) as exc:
                rows.append(_row(inp, out, None, time.perf_counter() - t0, str(exc).splitlines()[0] if str(exc) else type(exc).__name__))
            except Exception as exc:  # noqa: BLE001 - one input's bug must not stop the others
                rows.append(_row(inp, out, None, time.perf_counter() - t0, f"{type(exc).__name__}: {exc}".splitlines()[0]))
            if not rows[-1]["ok"]:
                log(f"[{name}] failed: {rows[-1]['error']}")
    failed = sum(1 for r in rows if not r["ok"])
    return {"runs": rows, "failed": failed, "seconds": round(time.perf_counter() - t_all, 3)}


def _prefix_map_targets(pipeline: Any) -> list[str]:
    """The map stages before the first whole stage that no other such stage depends on (running
    them as targets runs the whole map prefix of the DAG)."""
    prefix: list[str] = []
    for s in pipeline.stages:
        if s.is_map and all(d in prefix for d in s.deps):
            prefix.append(s.name)
    needed = {d for s in pipeline.stages if s.name in prefix for d in s.deps}
    return [n for n in prefix if n not in needed]


def _map_stages_of_all_inputs(inputs: list[str], names: list[str], root: Path, base: Any, spec: Any,
                              executor: Any, log: Callable[[str], None]) -> dict[str, tuple[int, float]]:
    """Run the map prefix of every input concurrently (threads sharing the executor: the items
    are computed by its workers, the threads only plan and wait). Returns name -> (items
    executed, seconds). Failures are left for the full pass to report."""
    from concurrent.futures import ThreadPoolExecutor

    from gcvd_flow.engine import api

    targets = _prefix_map_targets(spec.pipeline)

    def one(inp: str, name: str) -> tuple[int, float]:
        t0, executed = time.perf_counter(), 0
        for target in targets:
            try:
                res = api.run(replace(base, input=inp, out=str(root / name)), target=target,
                              log=_prefixed(log, name), executor=executor)
            except Exception:  # noqa: BLE001 - reported by the full pass
                break
            executed += sum(s["executed"] for s in res.get("stages") or [])
        return executed, time.perf_counter() - t0

    if not targets or len(inputs) < 2:
        return {}
    with ThreadPoolExecutor(max_workers=min(len(inputs), 8)) as pool:
        futures = {name: pool.submit(one, inp, name) for inp, name in zip(inputs, names)}
        try:
            return {name: f.result() for name, f in futures.items()}
        except BaseException as exc:
            if not isinstance(exc, Exception):  # an interrupt: the threads' items fail now, so they
                executor.close(abort=True)      # end, instead of computing the whole map prefix
            raise


def format_table(doc: dict[str, Any]) -> str:
    head = f"{'input':<28} {'status':<7} {'items':>6} {'executed':>9} {'cache hits':>10} {'seconds':>8}"
    lines = [head, "-" * len(head)]
    for r in doc["runs"]:
        name = Path(r["out"]).name or r["input"]  # the run dir's name: unique, unlike the inputs' names
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
