"""`sweep`: the cartesian product of parameter grids, one run directory per combination, all
through one DAG definition, one cache and one item executor.

``gcvd-flow sweep INPUT --out DIR --grid keyframes.delta=0.05,0.1,0.15`` runs
``DIR/keyframes.delta=0.05`` ... with ``--set keyframes.delta=V`` each. What makes it cheaper
than separate runs is the cache: a stage whose key does not depend on the swept parameters has
the same key in every combination, so it is computed once and found cached by the others.
With an executor (``--jobs`` > 1 or Dask) the pre-processing map stages (for GCVD: ingest,
user_masks, flow, flow_far, masks, priors; and ``calibrate``, the small whole stage between them,
see :func:`prefix_stages`) run first, in waves, one wave per stage: in each wave one
run per *distinct* setting of the sections that stage (and its ancestors) reads, side by side
on the shared workers, so the items of combinations that differ there interleave and the items
they share are computed once. Then every combination runs to the end, one after the other
(whole stages set process-wide thread counts; two must not share a process), and with ``--gt``
it is evaluated through the product's hook.

Resuming: every item and stage is in the cache as soon as it is computed, so running the same
command again after an interrupt computes only what is missing. ``DIR/sweep.json`` records the
grid and, as runs finish, each run's stages and metrics (what `runs` and `report` read).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

from gcvd_flow.engine.errors import StoreError, UsageError

SWEEP_FILE = "sweep.json"
MAX_RUNS_DEFAULT = 64
MAX_EXIT = 100
WAVE_THREADS = 8  # runs of one wave side by side (they only plan and wait: the workers compute)


@dataclass(frozen=True)
class Grid:
    """One ``--grid SECTION.KEY=V1,V2``: the key and its values as typed (text) and parsed."""

    key: str
    texts: tuple[str, ...]
    values: tuple[Any, ...]


def _split_values(text: str) -> list[str]:
    """Split at top-level commas: ``[1,2],[3,4]`` is two values, ``"a,b"`` one."""
    out: list[str] = []
    cur: list[str] = []
    depth, quote = 0, ""
    for ch in text:
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append("".join(cur).strip())
            cur = []
            continue
        cur.append(ch)
    out.append("".join(cur).strip())
    return out


def parse_grids(items: list[str]) -> list[Grid]:
    """``--grid`` texts -> grids; a malformed one is a UsageError naming it."""
    from gcvd_flow.engine.config import _parse_value

    grids: list[Grid] = []
    for item in items:
        key, eq, raw = item.partition("=")
        key = key.strip()
        if not eq or not key or any(not p for p in key.split(".")):
            raise UsageError(f"--grid {item!r}: expected SECTION.KEY=V1,V2,...")
        texts = [t for t in _split_values(raw) if t] if raw.strip() else []
        if not texts:
            raise UsageError(f"--grid {item!r}: empty list of values")
        if any(g.key == key for g in grids):
            raise UsageError(f"--grid {key}: given twice (list all its values in one --grid)")
        values = [_parse_value(t) for t in texts]
        canon = [json.dumps(v, sort_keys=True) + type(v).__name__ for v in values]
        dup = next((t for t, c in zip(texts, canon) if canon.count(c) > 1), None)
        if dup is not None:
            raise UsageError(f"--grid {key}: value {dup} is listed twice")
        grids.append(Grid(key, tuple(texts), tuple(values)))
    if not grids:
        raise UsageError("sweep: no --grid SECTION.KEY=V1,V2,... given")
    return grids


def _safe(text: str) -> str:
    """A value's text as a directory-name part (no separators, no leading dot)."""
    s = "".join(c if c.isprintable() and c not in "/\\\0" else "_" for c in text)
    return s if s and not s.startswith(".") else "_" + s


MAX_NAME_BYTES = 120  # a run directory name longer than this is cut and given a digest of the whole


def _dir_name(name: str) -> str:
    """A combination's run directory name; one past MAX_NAME_BYTES (file systems take 255) is
    cut there and ends with ``~`` and 12 hex digits of the full name's digest (still unique)."""
    if len(name.encode("utf-8")) <= MAX_NAME_BYTES:
        return name
    from gcvd_flow.engine.keys import digest_bytes

    head = name.encode("utf-8")[:MAX_NAME_BYTES - 13].decode("utf-8", "ignore")
    return f"{head}~{digest_bytes(name.encode('utf-8'))[:12]}"


@dataclass(frozen=True)
class Combo:
    name: str  # run directory name, e.g. "keyframes.delta=0.15" or "a.x=1,b.y=fast"
    sets: tuple[str, ...]  # the --set overrides of this combination
    params: dict[str, Any]  # key -> parsed value


def combinations(grids: list[Grid], max_runs: int = MAX_RUNS_DEFAULT) -> list[Combo]:
    """The cartesian product, in grid order (the last grid varies fastest)."""
    n = 1
    for g in grids:
        n *= len(g.values)
    if n > max_runs:
        sizes = " x ".join(str(len(g.values)) for g in grids)
        raise UsageError(f"--grid: {sizes} = {n} runs, more than --max-runs {max_runs}")
    out = []
    for pick in itertools.product(*(range(len(g.values)) for g in grids)):
        parts = [(g.key, g.texts[i], g.values[i]) for g, i in zip(grids, pick)]
        out.append(Combo(_dir_name(",".join(f"{k}={_safe(t)}" for k, t, _ in parts)),
                         tuple(f"{k}={t}" for k, t, _ in parts), {k: v for k, _, v in parts}))
    names = [c.name for c in out]
    clash = next((n for n in names if names.count(n) > 1), None)
    if clash is not None:  # two values that differ only in characters a folder name cannot hold
        raise UsageError(f"--grid: two combinations would share the run directory {clash!r}")
    return out


def check_combinations(spec: Any, base: Any, combos: list[Combo]) -> None:
    """Resolve every combination's config before anything runs: an unknown key or a value of
    the wrong type is one line naming the --grid."""
    from gcvd_flow.engine.config import build_config

    build_config(spec.config_model, spec.profiles, base.profile, base.config_file, list(base.sets))
    from gcvd_flow.engine.runs import flatten

    seen: dict[str, str] = {}
    for c in combos:
        try:
            cfg = build_config(spec.config_model, spec.profiles, base.profile, base.config_file,
                               list(base.sets) + list(c.sets))
        except UsageError as exc:
            raise UsageError(f"--grid {', '.join(c.sets)}: {exc}") from None
        resolved = flatten(json.loads(cfg.model_dump_json()))
        for k in c.params:  # as the model typed them (1 -> 1.0 for a float)
            if k in resolved:
                c.params[k] = resolved[k]
        canon = json.dumps(c.params, sort_keys=True, default=str)
        if canon in seen:
            raise UsageError(f"--grid {', '.join(c.sets)}: the same settings as {seen[canon]}")
        seen[canon] = c.name


# ------------------------------------------------------------------------------ the waves


def _sections(stage: Any) -> set[str]:
    p = stage.params
    return set() if p is None else {p} if isinstance(p, str) else set(p)


def prefix_stages(pipeline: Any) -> list[Any]:
    """The pre-processing prefix that runs in waves: the map stages whose dependencies are map
    stages of the prefix or *bridges*, and those bridges: whole stages that read only map stages
    of the prefix and are read by a later map stage of it (for GCVD: ``calibrate``, between
    ingest and masks / priors). A bridge runs one representative at a time (whole stages set
    process-wide thread counts); without bridges one small whole stage early in the DAG would
    cut every map stage after it out of the waves."""
    maps: set[str] = set()
    bridges: set[str] = set()
    candidates: list[Any] = []
    for s in pipeline.stages:
        if s.is_map and all(d in maps or d in bridges for d in s.deps):
            maps.add(s.name)
            candidates.append(s)
        elif not s.is_map and all(d in maps for d in s.deps):
            bridges.add(s.name)
            candidates.append(s)
    read_by_maps = {d for s in candidates if s.is_map for d in s.deps}
    return [s for s in candidates if s.is_map or s.name in read_by_maps]


def _wave_groups(pipeline: Any, stage: Any, combos: list[Combo]) -> list[Combo]:
    """One representative per distinct setting of the swept keys that ``stage`` or one of its
    ancestors reads. A key without a section (top level, e.g. ``seed``) counts as read by all."""
    read: set[str] = set()
    todo, seen = [stage.name], set()
    while todo:
        s = pipeline.get(todo.pop())
        if s.name in seen:
            continue
        seen.add(s.name)
        read |= _sections(s)
        todo.extend(s.deps)
    reps: dict[str, Combo] = {}
    for c in combos:
        sig = json.dumps({k: v for k, v in c.params.items() if "." not in k or k.split(".")[0] in read},
                         sort_keys=True, default=str)
        reps.setdefault(sig, c)
    return list(reps.values())


def _waves_help(spec: Any, combos: list[Combo]) -> bool:
    """Whether some prefix stage has two distinct settings to interleave; else the first run
    computes the shared prefix by itself (the waves would only add a pass)."""
    return any(len(_wave_groups(spec.pipeline, s, combos)) > 1 for s in prefix_stages(spec.pipeline))


def _prefix_waves(combos: list[Combo], invs: dict[str, Any], spec: Any, executor: Any,
                  log: Callable[[str], None]) -> dict[tuple[str, str], tuple[int, float]]:
    """Run the map prefix in waves (see the module docstring). Returns (run name, stage) ->
    (items executed, seconds) for what the waves computed. Failures are left for the full pass
    to report."""
    from gcvd_flow.engine import api

    early: dict[tuple[str, str], tuple[int, float]] = {}
    failed: set[str] = set()

    def one(c: Combo, target: str) -> None:
        try:
            # no run directory yet: a run.json of the prefix alone would look like a finished run
            res = api.run(replace(invs[c.name], out=None), target=target, log=lambda m: log(f"[{c.name}] {m}"),
                          executor=executor)
        except Exception as exc:  # noqa: BLE001 - reported (again) by the full pass
            failed.add(c.name)
            if not stopping.is_set():  # after Ctrl-C: the closed executor's errors are no news
                log(f"[{c.name}] {target}: {_error_line(exc)}")
            return
        for s in res.get("stages") or []:
            if s["executed"]:
                n, sec = early.get((c.name, s["name"]), (0, 0.0))
                early[(c.name, s["name"])] = (n + s["executed"], sec + s["seconds"])

    # Daemon threads, not a thread pool: on Ctrl-C the main thread leaves at once and closes the
    # shared executor; a wave thread still waiting for an item of the closed pool must not keep
    # the process alive (a pool's threads are joined at interpreter exit: that hung).
    stopping = threading.Event()
    try:
        for stage in prefix_stages(spec.pipeline):
            reps = [c for c in _wave_groups(spec.pipeline, stage, combos) if c.name not in failed]
            side_by_side = WAVE_THREADS if stage.is_map else 1  # a bridge: one at a time
            for i in range(0, len(reps), side_by_side):
                threads = [threading.Thread(target=one, args=(c, stage.name), daemon=True,
                                            name=f"sweep-wave-{c.name}") for c in reps[i:i + side_by_side]]
                for t in threads:
                    t.start()
                for t in threads:
                    while t.is_alive():
                        t.join(0.2)
    except BaseException:
        stopping.set()
        raise
    return early


# ------------------------------------------------------------------------------ the sweep


def _merge_stages(stages: list[dict[str, Any]], name: str,
                  early: dict[tuple[str, str], tuple[int, float]]) -> list[dict[str, Any]]:
    """The final pass's stage counts with what the waves computed for this run counted as
    executed (the final pass found it cached)."""
    out = []
    for s in stages:
        n, sec = early.get((name, s["name"]), (0, 0.0))
        out.append({"name": s["name"], "executed": s["executed"] + n, "cached": max(0, s["cached"] - n),
                    "seconds": round(s["seconds"] + sec, 3)})
    return out


def _write_json(path: Path, doc: dict[str, Any]) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(doc, indent=1, sort_keys=False))
    os.replace(tmp, path)


def _error_line(exc: BaseException) -> str:
    text = str(exc).splitlines()[0] if str(exc) else ""
    if isinstance(exc, (UsageError, StoreError, OSError)):
        return text or type(exc).__name__
    return f"{type(exc).__name__}: {text}"


@dataclass
class SweepPlan:
    """A checked sweep: what `run_sweep` runs."""

    input: str
    root: Path
    grids: list[Grid]
    combos: list[Combo]
    base: Any  # api.Invocation shared by every run (its sets come first, the grid's last)
    gt: str | None = None


def prepare(input_: str, out_root: str, base: Any, grid_texts: list[str], gt: str | None = None,
            max_runs: int = MAX_RUNS_DEFAULT, can_evaluate: bool = False) -> SweepPlan:
    """Everything checked before anything runs (UsageError otherwise)."""
    from gcvd_flow.engine import api

    if max_runs < 1:
        raise UsageError("--max-runs must be at least 1")
    grids = parse_grids(grid_texts)
    combos = combinations(grids, max_runs)
    spec = api.load_spec(base.pipeline, allow_module_ref=True)
    check_combinations(spec, base, combos)
    if gt is not None:
        if not can_evaluate:
            raise UsageError("--gt: this program has no evaluation")
        if not Path(gt).exists():
            raise UsageError(f"--gt {gt}: no such file or directory")
    if not os.path.lexists(input_):  # before the sweep folder is made
        raise UsageError(f"{input_}: no such file or directory")
    root = api.check_out_dir(out_root)
    if (root / "run.json").is_file():
        raise UsageError(f"{root}: is a run directory; give a new or sweep directory to --out")
    return SweepPlan(input_, root, grids, combos, base, gt)


def _sweep_doc(plan: SweepPlan, rows: list[dict[str, Any]], state: str) -> dict[str, Any]:
    return {"sweep": 1, "state": state, "input": os.path.abspath(plan.input),
            "grid": [{"key": g.key, "values": list(g.values)} for g in plan.grids],
            "sets": list(plan.base.sets), "profile": plan.base.profile, "runs": rows}


def run_sweep(plan: SweepPlan, log: Callable[[str], None],
              evaluate: Callable[[Path, str], dict[str, Any]] | None = None) -> dict[str, Any]:
    """Run every combination (never stops early on a failing one); returns the --json doc.
    The sweep folder is locked like a run directory: a second sweep into it while this one runs
    exits 2 at once (it would replace run directories this sweep.json describes)."""
    from gcvd_flow.engine.outputs import run_dir_lock

    with run_dir_lock(plan.root, busy="another sweep is writing this folder; wait for it to finish "
                                      "or use another --out"):
        return _run_sweep_locked(plan, log, evaluate)


def _run_sweep_locked(plan: SweepPlan, log: Callable[[str], None],
                      evaluate: Callable[[Path, str], dict[str, Any]] | None) -> dict[str, Any]:
    from gcvd_flow.engine import api
    from gcvd_flow.engine.executors import closing, make_executor, resolve_jobs

    base = plan.base
    spec = api.load_spec(base.pipeline, allow_module_ref=True)
    plan.root.mkdir(parents=True, exist_ok=True)
    invs = {c.name: replace(base, input=plan.input, out=str(plan.root / c.name), sets=list(base.sets) + list(c.sets))
            for c in plan.combos}
    pending = [{"name": c.name, "out": str(plan.root / c.name), "params": c.params} for c in plan.combos]
    _write_json(plan.root / SWEEP_FILE, _sweep_doc(plan, pending, "running"))
    executor = None
    if base.executor == "dask" or resolve_jobs(base.jobs) > 1:
        executor = make_executor(base.jobs, spec.pipeline.worker_init, base.executor, base.scheduler)
    t_all = time.perf_counter()
    rows: list[dict[str, Any]] = []
    # an interrupt (Ctrl-C, SIGTERM, SIGHUP) ends the shared workers at once (executors.closing)
    with closing(executor) if executor is not None else contextlib.nullcontext():
        early = _prefix_waves(plan.combos, invs, spec, executor, log) if executor and _waves_help(spec, plan.combos) \
            else {}
        for c in plan.combos:
            rows.append(_run_one(c, invs[c.name], early, executor, plan.gt, evaluate, log))
            _write_json(plan.root / SWEEP_FILE, _sweep_doc(plan, rows + pending[len(rows):], "running"))
    _write_json(plan.root / SWEEP_FILE, _sweep_doc(plan, rows, "done"))
    failed = sum(1 for r in rows if not r["ok"])
    return {"runs": rows, "failed": failed, "seconds": round(time.perf_counter() - t_all, 3)}


def _run_one(c: Combo, inv: Any, early: dict[tuple[str, str], tuple[int, float]], executor: Any,
             gt: str | None, evaluate: Callable[[Path, str], dict[str, Any]] | None,
             log: Callable[[str], None]) -> dict[str, Any]:
    """One combination to the end (+ its evaluation): its row of the --json document."""
    from gcvd_flow.engine import api

    row: dict[str, Any] = {"name": c.name, "out": inv.out, "params": c.params, "metrics": {}, "stages": [],
                           "ok": True}
    t0 = time.perf_counter()
    try:
        res = api.run(inv, log=lambda m: log(f"[{c.name}] {m}"), executor=executor)
        row["stages"] = _merge_stages(res.get("stages") or [], c.name, early)
        if gt is not None and evaluate is not None:
            row["metrics"] = evaluate(Path(inv.out), gt)
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # noqa: BLE001 - one combination's failure must not stop the others
        row.update(ok=False, error=_error_line(exc))
        log(f"[{c.name}] failed: {row['error']}")
    row["seconds"] = round(time.perf_counter() - t0 + sum(s for (n, _), (_, s) in early.items() if n == c.name), 3)
    return row


def exit_code(doc: dict[str, Any]) -> int:
    return min(int(doc["failed"]), MAX_EXIT)
