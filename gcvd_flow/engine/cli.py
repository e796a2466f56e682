"""The engine's command line: run, plan, why, status, dag, fsck, gc, pin, push, pull, run-many,
sweep, runs, lineage.

A product builds its CLI on this one (:class:`Product`): it names its pipeline and program,
adds its own verbs and options through hooks, and calls :func:`main`. The engine knows nothing
of what the product computes.

Exit codes: 0 success, 2 bad usage or bad input (one line on stderr, no traceback), also lost
workers (a worker killed again and again, the Dask scheduler gone), 1 internal error, 128 + the
signal's number when stopped by a signal, handled alike (one line, the worker processes ended,
the cache consistent; run again to resume): 130 Ctrl-C (SIGINT), 143 SIGTERM (e.g. a CI
timeout), 129 SIGHUP (the terminal closed). An ignored SIGHUP (nohup) stays ignored.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import signal
import sys
import threading
import traceback
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Sequence

from gcvd_flow.engine.errors import StoreError, UsageError, WorkerError
from gcvd_flow.engine.names import ENV_CACHE, ENV_JOBS, ENV_REMOTES


@dataclass
class Product:
    """What a product adds to the engine's CLI.

    ``add_run_args(parser)`` adds options to run / plan / why / status, ``run_sets(args)`` turns
    them into ``--set`` overrides (so they enter keys like any parameter), ``add_commands(sub)``
    adds verbs (each sets ``handler=fn(args) -> exit code``).
    """

    prog: str
    description: str
    pipeline: str
    version: str = "0"
    add_run_args: Callable[[argparse.ArgumentParser], None] = lambda p: None
    run_sets: Callable[[argparse.Namespace], list[str]] = lambda a: []
    add_commands: Callable[[Any], None] = lambda sub: None
    epilog: str = ""
    extra: dict[str, Any] = field(default_factory=dict)
    # `sweep --gt`: evaluate one finished run dir against ground truth, write its metrics.json,
    # return the metrics; `runs` / `sweep` tables show these metrics (others: --json / --csv)
    evaluate: Callable[[Any, str], dict[str, Any]] | None = None
    metric_columns: tuple[str, ...] = ()


_PRODUCT: Product | None = None


def _product() -> Product:
    if _PRODUCT is None:
        raise UsageError("no product configured")
    return _PRODUCT


def _jobs_arg(text: str) -> int:
    """argparse type of --jobs: N >= 1 or auto (0)."""
    from gcvd_flow.engine.executors import parse_jobs

    try:
        return parse_jobs(text)
    except UsageError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--jobs: ")) from None


def _add_run_args(p: argparse.ArgumentParser, input_required: bool = True) -> None:
    if input_required:
        p.add_argument("input", metavar="INPUT", help="video file, image folder or dataset folder")
    p.add_argument("--out", required=input_required, metavar="RUN_DIR", help="run directory for the results")
    _add_config_args(p)
    p.add_argument("--jobs", type=_jobs_arg, default=0, metavar="N|auto",
                   help="map items (and a stage's independent calls) in N worker processes (default auto: "
                   f"${ENV_JOBS}, else one per usable core; results do not depend on it)")


def _add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", dest="config_file", metavar="FILE", help="TOML file of parameters")
    p.add_argument("--profile", metavar="NAME", help="named parameter profile (e.g. paper, fast)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override one parameter (repeatable)")
    _product().add_run_args(p)
    p.add_argument("--cache", metavar="DIR", help=f"cache directory (default: ${ENV_CACHE} or the user cache dir)")
    p.add_argument("--json", dest="json_mode", action="store_true", help="machine-readable output on stdout")
    p.add_argument("--no-verify", dest="verify", action="store_false",
                   help="skip re-hashing objects read from the cache (faster, less safe)")
    p.add_argument("--pipeline", default=_product().pipeline,
                   help="installed pipeline to run (developers: also module:attr)")


def _add_remote_args(p: argparse.ArgumentParser, help_: str) -> None:
    p.add_argument("--remote", dest="remote_name", metavar="NAME|URL", help=help_)
    p.add_argument("--remotes", dest="remotes_file", metavar="FILE",
                   help=f"remotes file (default: ${ENV_REMOTES} or the user config dir's remotes.toml)")


def _add_scale_args(p: argparse.ArgumentParser) -> None:
    """Teams and clusters (docs/teams.md): a remote cache read through / written through, and
    where map items run."""
    _add_remote_args(p, "look records this cache lacks up in this remote (name or URL) before computing")
    p.add_argument("--push", action="store_true",
                   help="push what each stage computed to the remote (--remote, else the default remote)")
    p.add_argument("--executor", choices=("process", "dask"), default="process",
                   help="map items in local processes (default) or as Dask tasks")
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                   help="with --executor dask: the cluster's scheduler (default: a local cluster of --jobs workers)")


def _add_scale_commands(sub: Any) -> None:
    p = sub.add_parser("run-many", help="run many inputs through one DAG and one cache; a summary table")
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="videos / image folders / dataset folders")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="one run directory per input: DIR/<input name>; a repeated name gets the first "
                   "free -2, -3, ... (never one shared by two inputs)")
    _add_config_args(p)
    p.add_argument("--jobs", type=_jobs_arg, default=0, metavar="N|auto",
                   help="map items in N worker processes / Dask workers (default auto: one per usable core)")
    _add_scale_args(p)
    p.set_defaults(handler=_cmd_run_many)

    _add_sweep_commands(sub)

    p = sub.add_parser("lineage", help="what produced an artifact: stage, parameters, code, libraries, inputs")
    p.add_argument("target", metavar="RUN_DIR|DIGEST", help="a run directory, or a record key / output / object digest")
    p.add_argument("stage", nargs="?", metavar="STAGE", help="with RUN_DIR: this stage only (default: all)")
    p.add_argument("--cache", metavar="DIR", help=f"default: the run's cache, else ${ENV_CACHE} / the user cache dir")
    p.add_argument("--full", action="store_true", help="every record's code files, all parameters and environment "
                   "(default: one line per record, the shared environment once)")
    p.add_argument("--json", dest="json_mode", action="store_true", help="machine-readable output on stdout")
    p.set_defaults(handler=_cmd_lineage)


def _add_sweep_commands(sub: Any) -> None:
    from gcvd_flow.engine.sweep import MAX_RUNS_DEFAULT

    p = sub.add_parser("sweep", help="run every combination of parameter grids through one DAG and one cache; "
                       "a table of the runs")
    p.add_argument("input", metavar="INPUT", help="video file, image folder or dataset folder")
    p.add_argument("--out", required=True, metavar="DIR", help="one run directory per combination: DIR/KEY=VALUE")
    p.add_argument("--grid", dest="grids", action="append", default=[], metavar="SECTION.KEY=V1,V2",
                   help="values of one parameter (repeatable: the cartesian product of all grids runs)")
    p.add_argument("--gt", metavar="GT_DIR", help="evaluate every run against this ground truth (metrics.json)")
    p.add_argument("--sort", metavar="METRIC", help="sort the table by this metric or parameter (--sort=-METRIC: descending)")
    p.add_argument("--max-runs", type=int, default=MAX_RUNS_DEFAULT, metavar="N",
                   help=f"refuse grids of more than N combinations (default {MAX_RUNS_DEFAULT})")
    _add_config_args(p)
    p.add_argument("--jobs", type=_jobs_arg, default=0, metavar="N|auto",
                   help="map items in N worker processes / Dask workers (default auto: one per usable core)")
    _add_scale_args(p)
    p.set_defaults(handler=_cmd_sweep)

    p = sub.add_parser("runs", help="a table of run directories: the parameters that differ, metrics, "
                       "stages reused / computed")
    p.add_argument("paths", nargs="+", metavar="PATH", help="run directories or folders holding them (searched)")
    p.add_argument("--all-params", action="store_true", help="every parameter, not only those that differ")
    p.add_argument("--sort", metavar="METRIC", help="sort by this metric or parameter (--sort=-METRIC: descending)")
    fmt = p.add_mutually_exclusive_group()
    fmt.add_argument("--json", dest="json_mode", action="store_true", help="machine-readable output on stdout")
    fmt.add_argument("--csv", action="store_true", help="CSV on stdout (every metric)")
    fmt.add_argument("--md", action="store_true", help="a Markdown table on stdout")
    p.set_defaults(handler=_cmd_runs)


def build_parser(product: Product) -> argparse.ArgumentParser:
    global _PRODUCT
    _PRODUCT = product
    ap = argparse.ArgumentParser(prog=product.prog, description=product.description, epilog=product.epilog)
    ap.add_argument("--version", action="version", version=f"{product.prog} {product.version}")
    sub = ap.add_subparsers(dest="cmd", required=True, metavar="COMMAND")

    p = sub.add_parser("run", help="run the pipeline on a video / folder; results in RUN_DIR")
    _add_run_args(p)
    p.add_argument("--until", metavar="STAGE", help="stop after STAGE (and what it needs)")
    _add_scale_args(p)
    p = sub.add_parser("plan", help="dry run: which stages would run, and why")
    _add_run_args(p)
    p.set_defaults(out_required=False)

    p = sub.add_parser("why", help="why STAGE would re-run: field-by-field key difference")
    p.add_argument("stage", help="the stage to explain (see `dag`)")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run directory of an earlier run")
    _add_config_args(p)

    p = sub.add_parser("status", help="which stages of a run are up to date")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run directory of an earlier run")
    _add_config_args(p)

    p = sub.add_parser("dag", help="print the stage graph")
    p.add_argument("--json", dest="json_mode", action="store_true", help="machine-readable output on stdout")
    p.add_argument("--pipeline", default=product.pipeline, help="installed pipeline (developers: also module:attr)")

    p = sub.add_parser("fsck", help="re-hash every cached object; quarantine corrupt ones")
    p.add_argument("--cache", metavar="DIR", help=f"cache directory (default: ${ENV_CACHE} or the user cache dir)")
    p.add_argument("--json", dest="json_mode", action="store_true", help="machine-readable output on stdout")
    _add_remote_args(p, "verify this remote in place instead (lists what is bad; deletes only with --repair)")
    p.add_argument("--repair", action="store_true", help="with --remote: delete bad objects and records")

    p = sub.add_parser("gc", help="delete objects not reachable from the last N runs or pins")
    p.add_argument("--cache", metavar="DIR", help=f"cache directory (default: ${ENV_CACHE} or the user cache dir)")
    p.add_argument("--keep", type=int, default=5, metavar="N", help="runs to keep (default 5; pins are always kept)")
    p.add_argument("--no-wait", action="store_true",
                   help="fail (exit 2) instead of waiting when a run, pull or push is using the cache")
    p.add_argument("--json", dest="json_mode", action="store_true", help="machine-readable output on stdout")

    p = sub.add_parser("pin", help="keep a run's artifacts through gc (until unpinned)")
    p.add_argument("name", help="name of the pin")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run directory of an earlier run")
    p.add_argument("--cache", metavar="DIR", help=f"cache directory (default: ${ENV_CACHE} or the user cache dir)")
    p.add_argument("--remove", action="store_true", help="remove the pin instead")

    for name, help_ in (("push", "copy a run's artifacts (or the whole cache) to a remote cache directory"),
                        ("pull", "copy a run's artifacts (or all) from a remote cache directory, verified")):
        p = sub.add_parser(name, help=help_)
        p.add_argument("remote", metavar="REMOTE_DIR", nargs="?", help="a directory (or use --remote)")
        _add_remote_args(p, "remote by name (remotes.toml) or URL: s3://bucket/prefix, sftp://host/path, a path")
        which = p.add_mutually_exclusive_group()
        which.add_argument("--out", metavar="RUN_DIR", help="only this run's stages (default: everything)")
        which.add_argument("--all", action="store_true", help="everything (the default)")
        p.add_argument("--cache", metavar="DIR", help=f"cache directory (default: ${ENV_CACHE} or the user cache dir)")
        p.add_argument("--json", dest="json_mode", action="store_true", help="machine-readable output on stdout")

    _add_scale_commands(sub)
    product.add_commands(sub)
    return ap


def _invocation(a: argparse.Namespace, input_: str | None = None, out: str | None = None):
    from gcvd_flow.engine.api import Invocation

    sets = _all_sets(a)
    return Invocation(input=input_ if input_ is not None else getattr(a, "input", None),
                          out=out if out is not None else getattr(a, "out", None),
                          config_file=getattr(a, "config_file", None), profile=getattr(a, "profile", None),
                          sets=sets, cache=getattr(a, "cache", None), jobs=getattr(a, "jobs", 0),
                          json_mode=getattr(a, "json_mode", False),
                          pipeline=getattr(a, "pipeline", None) or _product().pipeline,
                          verify=getattr(a, "verify", True), remote=getattr(a, "remote_name", None),
                          remotes_file=getattr(a, "remotes_file", None), push=getattr(a, "push", False),
                          executor=getattr(a, "executor", None) or "process", scheduler=getattr(a, "scheduler", None))


def _print_json(doc: Any) -> None:
    print(json.dumps(doc, indent=1, sort_keys=False))


def _fast_noop(a: argparse.Namespace) -> dict[str, Any] | None:
    """`run` whose inputs, code and outputs are untouched since its last run: answer at once."""
    from gcvd_flow.engine import fastpath
    from gcvd_flow.engine.paths import default_cache_dir

    if not a.out:
        return None
    cache = a.cache or str(default_cache_dir())
    return fastpath.check(a.out, stamp_invocation(a), cache)


def _all_sets(a: argparse.Namespace) -> list[str]:
    return list(getattr(a, "sets", []) or []) + list(_product().run_sets(a))


def stamp_invocation(a: argparse.Namespace) -> dict[str, Any]:
    """The parts of a `run` invocation that decide its result (not --jobs, --json, ...)."""
    import os

    return {"input": os.path.abspath(a.input), "pipeline": a.pipeline, "until": a.until,
            "config_file": os.path.abspath(a.config_file) if a.config_file else None,
            "profile": a.profile, "sets": _all_sets(a)}


def _print_run(res: dict[str, Any], json_mode: bool) -> None:
    if json_mode:
        _print_json(res)
        return
    for s in res["stages"]:
        print(f"{s['name']:<20} executed {s['executed']:>5}  cached {s['cached']:>5}  {s['seconds']:8.2f} s")
    for k, v in (res.get("outputs") or {}).items():
        print(f"{k}: {v}")


def _cmd_run(a: argparse.Namespace) -> int:
    if not a.out:
        return _cmd_run_locked(a)
    from gcvd_flow.engine.outputs import check_out_dir, run_dir_lock

    check_out_dir(a.out)
    with run_dir_lock(a.out):  # the fast path's answer and the stamp belong to this run only
        return _cmd_run_locked(a)


def _cmd_run_locked(a: argparse.Namespace) -> int:
    res = None if a.push else _fast_noop(a)  # --push: check the remote has everything
    if res is not None:
        _print_run(res, a.json_mode)
        return 0
    from gcvd_flow.engine import api, fastpath

    res = api.run(_invocation(a), target=a.until)
    record_paths = res.pop("_record_paths")
    watch = res.pop("_watch")
    if a.out:
        noop = {k: v for k, v in res.items() if k != "remote"}  # a no-op replay transfers nothing
        fastpath.write(a.out, stamp_invocation(a), res["cache"], noop, record_paths, watch)
    _print_run(res, a.json_mode)
    return 0


def _cmd_plan(a: argparse.Namespace) -> int:
    from gcvd_flow.engine import api

    reps = api.plan(_invocation(a))
    if a.json_mode:
        _print_json({"stages": [r.as_plan_json() for r in reps]})
    else:
        for r in reps:
            print(f"{r.name:<20} {r.action:<7} {'; '.join(r.reasons)}")
    return 0


def _cmd_why(a: argparse.Namespace) -> int:
    from gcvd_flow.engine import api

    res = api.why(a.stage, a.out, _invocation(a, input_=None, out=a.out))
    if a.json_mode:
        _print_json(res)
    elif res["action"] == "cached":
        print(f"{a.stage}: up to date (key {str(res['key'])[:12]})")
    else:
        print(f"{a.stage} would run:")
        for r in res["reasons"]:
            print(f"  - {r}")
    return 0


def _cmd_status(a: argparse.Namespace) -> int:
    from gcvd_flow.engine import api

    reps = api.status(a.out, _invocation(a, input_=None, out=a.out))
    if a.json_mode:
        _print_json({"stages": [r.as_plan_json() for r in reps]})
    else:
        for r in reps:
            state = "up to date" if r.action == "cached" else "changed: " + "; ".join(r.reasons)
            print(f"{r.name:<20} {state}")
    return 0


def _cmd_dag(a: argparse.Namespace) -> int:
    from gcvd_flow.engine import api

    spec = api.load_spec(a.pipeline, allow_module_ref=True)
    stages: list[dict[str, Any]] = [{"name": s.name, "deps": list(s.deps), "map": s.is_map, "kind": s.kind}
                                    for s in spec.pipeline.stages]
    if a.json_mode:
        _print_json({"stages": stages})
    else:
        for s in stages:
            arrow = " <- " + ", ".join(s["deps"]) if s["deps"] else ""
            print(f"{s['name']}{' [map]' if s['map'] else ''}{arrow}")
    return 0


def _cmd_fsck(a: argparse.Namespace) -> int:
    from gcvd_flow.engine import api

    if a.remote_name:
        return _cmd_fsck_remote(a)
    rep = api.fsck(a.cache)
    if a.json_mode:
        _print_json(rep)
    else:
        print(f"checked {rep['objects']} objects ({rep['bytes'] / 1e6:.1f} MB): "
              f"{len(rep['corrupt'])} corrupt (quarantined), {rep['records_removed']} records dropped")
        for d in rep["corrupt"]:
            print(f"corrupt: {d}")
    return 0


def _cmd_gc(a: argparse.Namespace) -> int:
    from gcvd_flow.engine import api

    rep = api.gc(a.cache, a.keep, wait=not a.no_wait)
    if a.json_mode:
        _print_json(rep)
    else:
        print(f"removed {rep['objects_removed']} objects ({rep['bytes_removed'] / 1e6:.1f} MB), "
              f"{rep['records_removed']} records; kept {rep['objects_kept']} objects")
    return 0


def _cmd_pin(a: argparse.Namespace) -> int:
    from gcvd_flow.engine import api

    store = api.open_store(a.cache)
    if a.remove:
        store.unpin(a.name)
        print(f"unpinned {a.name}")
    else:
        run = api.read_run_dir(a.out)
        store.pin(a.name, {"records": [s["key"] for s in run["stages"].values() if s.get("key")]})
        print(f"pinned {a.out} as {a.name}")
    return 0


def _cmd_push_pull(a: argparse.Namespace) -> int:
    from gcvd_flow.engine import api, remote

    if a.remote and a.remote_name:
        raise UsageError("give the remote once: REMOTE_DIR or --remote NAME|URL")
    store = api.open_store(a.cache)
    rep = (remote.push if a.cmd == "push" else remote.pull)(store, a.remote_name or a.remote, a.out,
                                                            remotes_file=a.remotes_file)
    if a.json_mode:
        _print_json(rep)
    else:
        print(f"{a.cmd}: {rep['records']} records, {rep['objects']} objects ({rep['bytes'] / 1e6:.1f} MB)"
              + (f", {rep['refused']} objects refused (hash mismatch)" if rep["refused"] else "")
              + (f", {len(rep['refused_records'])} records refused" if rep.get("refused_records") else ""))
    return 0


def _cmd_fsck_remote(a: argparse.Namespace) -> int:
    from gcvd_flow.engine import remote

    rep = remote.fsck_remote(a.remote_name, repair=a.repair, remotes_file=a.remotes_file)
    if a.json_mode:
        _print_json(rep)
        return 0
    print(f"remote {rep['remote']}: {rep['objects']} objects ({rep['bytes'] / 1e6:.1f} MB), {rep['records']} "
          f"records: {len(rep['bad_objects'])} bad objects, {len(rep['bad_records'])} bad records, "
          f"{len(rep['stray_files'])} stray files, {rep['tmp_files']} temporary files"
          + (" (deleted)" if rep["repaired"] and not rep["clean"] else "")
          + ("; clean" if rep["clean"] else "" if rep["repaired"] else "; run with --repair to delete them"))
    for line in rep["bad_objects"] + rep["bad_records"] + rep["stray_files"]:
        print(f"bad: {line}")
    for path in rep.get("not_deleted", []):
        print(f"not deleted (a folder, or not inside the remote): {path}")
    return 0


def _cmd_run_many(a: argparse.Namespace) -> int:
    from gcvd_flow.engine import api, many

    doc = many.run_many(a.inputs, a.out, _invocation(a, input_="", out=a.out), log=api._stderr)
    if a.json_mode:
        _print_json(doc)
    else:
        print(many.format_table(doc))
    return many.exit_code(doc)


def _cmd_sweep(a: argparse.Namespace) -> int:
    from gcvd_flow.engine import api, runs, sweep

    product = _product()
    plan = sweep.prepare(a.input, a.out, _invocation(a, input_=a.input, out=a.out), a.grids, gt=a.gt,
                         max_runs=a.max_runs, can_evaluate=product.evaluate is not None)
    if a.sort:
        sweep_sort_known(a.sort, plan, a.gt is not None)
    doc = sweep.run_sweep(plan, log=api._stderr, evaluate=product.evaluate)
    sort = a.sort
    try:
        doc["runs"] = runs.sort_rows(doc["runs"], sort)
    except UsageError as exc:  # e.g. a metric the evaluation did not give: the runs are done, show them
        api._stderr(f"warning: {exc}; the table is not sorted")
        sort = None
    if a.json_mode:
        _print_json(doc)
    else:
        done = [r["out"] for r in doc["runs"] if r["ok"]]
        table = runs.collect(done, sort=sort) if done else {"runs": []}
        print(runs.format_text(table, product.metric_columns))
        n = len(doc["runs"])
        print(f"{n - doc['failed']} of {n} runs ok, {doc['failed']} failed, {doc['seconds']:.1f} s")
        for r in doc["runs"]:
            if not r["ok"]:
                print(f"{r['name']}: FAILED: {r['error']}")
    return sweep.exit_code(doc)


def sweep_sort_known(sort: str, plan: Any, evaluated: bool) -> None:
    """--sort must name a swept parameter, or a metric when the runs are evaluated."""
    key = sort[1:] if sort.startswith("-") else sort
    if not evaluated and key not in {g.key for g in plan.grids}:
        raise UsageError(f"--sort {key}: not a swept parameter (metrics need --gt)")


def _cmd_runs(a: argparse.Namespace) -> int:
    from gcvd_flow.engine import runs

    doc = runs.collect(a.paths, all_params=a.all_params, sort=a.sort)
    if a.json_mode:
        _print_json(runs.json_doc(doc))
    elif a.csv:
        print(runs.format_csv(doc))
    elif a.md:
        print(runs.format_md(doc, _product().metric_columns))
    else:
        print(runs.format_text(doc, _product().metric_columns))
    return 0


def _cmd_lineage(a: argparse.Namespace) -> int:
    from gcvd_flow.engine import lineage

    doc = lineage.lineage(a.target, a.stage, a.cache)
    if a.json_mode:
        _print_json(doc)
    else:
        print(lineage.format_text(doc, full=a.full))
    return 0


ENGINE_COMMANDS = {"run": _cmd_run, "plan": _cmd_plan, "why": _cmd_why, "status": _cmd_status, "dag": _cmd_dag,
                   "fsck": _cmd_fsck, "gc": _cmd_gc, "pin": _cmd_pin, "push": _cmd_push_pull,
                   "pull": _cmd_push_pull}


def dispatch(a: argparse.Namespace) -> int:
    handler = ENGINE_COMMANDS.get(a.cmd) or getattr(a, "handler", None)
    if handler is None:
        raise UsageError(f"unknown command {a.cmd!r}")
    return int(handler(a) or 0)


class Stopped(KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised in the main thread: handled as Ctrl-C is."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _raise_stopped(signum: int, frame: Any) -> None:
    raise Stopped(signum)


@contextlib.contextmanager
def _stop_signals_interrupt() -> Iterator[None]:
    """SIGTERM and SIGHUP raise :class:`Stopped` inside the block (unless ignored: nohup), so a
    run ends through the same path as on Ctrl-C: its executor ends the workers, the store's
    files stay whole. The previous handlers are back after the block."""
    old = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGHUP):
            if signal.getsignal(sig) == signal.SIG_DFL:
                old[sig] = signal.signal(sig, _raise_stopped)
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def _say(line: str) -> None:
    """One line on stderr, which may be a closed terminal (SIGHUP)."""
    with contextlib.suppress(OSError, ValueError):
        print(line, file=sys.stderr)


def main(product: Product, argv: Sequence[str] | None = None) -> int:
    ap = build_parser(product)
    a = ap.parse_args(argv)
    try:
        with _stop_signals_interrupt():
            return dispatch(a)
    except UsageError as exc:
        print(f"{product.prog}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM / SIGHUP (Stopped)
        signum = getattr(exc, "signum", signal.SIGINT)
        how = "interrupted" if signum == signal.SIGINT else f"interrupted by {signal.Signals(signum).name}"
        _say(f"{product.prog}: {how}; the cache is consistent, run again to resume")
        return 128 + signum
    except BrokenPipeError:
        return 0
    except (StoreError, WorkerError) as exc:  # a cache that cannot serve this run; lost workers
        print(f"{product.prog}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the environment: permissions, a full disk, a file where a folder must be
        where = exc.filename if exc.filename is not None else ""
        what = exc.strerror or (str(exc).splitlines() or [""])[0] or type(exc).__name__
        full = exc.errno == errno.ENOSPC or "No space left" in what
        hint = "; the cache is consistent, free space and run again" if full else ""
        print(f"{product.prog}: error: {where}{': ' if where else ''}{what}{hint}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as exc:  # the installation lacks a package: say which, in one line
        print(f"{product.prog}: error: the Python module {exc.name!r} is not installed; install "
              f"{product.prog} with its dependencies (pip install {product.prog} / pip install .)", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 - last resort: an internal error, with its traceback
        if getattr(exc, "user_error", False):  # bad input found inside a stage
            print(f"{product.prog}: error: {exc}", file=sys.stderr)
            return 2
        traceback.print_exc()
        print(f"{product.prog}: internal error (this is a bug; the traceback is above)", file=sys.stderr)
        return 1
