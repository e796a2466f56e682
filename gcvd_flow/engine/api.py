"""The Python API: the same verbs as the CLI (run, plan, why, status, fsck, gc).

A *pipeline spec* bundles what the engine needs to know about a product pipeline: the stage
graph, its config model and profiles, how to open an input, how to export results into a
run directory, and where its artifact schemas are. Installed packages register their specs as
entry points in the group ``gcvd_flow.pipelines`` (name -> ``module:attr``); the engine knows
no pipeline by itself. A run directory records the *name* of its pipeline, and opening it
accepts only registered names: data never chooses which code is imported.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import importlib.util
import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from gcvd_flow.engine.artifacts import register_schema_dir
from gcvd_flow.engine.config import build_config
from gcvd_flow.engine.dag import Pipeline, PipelineError
from gcvd_flow.engine.errors import UsageError
from gcvd_flow.engine.keys import ENGINE_LIBRARIES
from gcvd_flow.engine.names import ENTRY_POINT_GROUP, TOOL
from gcvd_flow.engine.outputs import check_out_dir, check_run_doc, digest_outputs, outputs_of, read_run_dir, run_dir_lock  # noqa: F401
from gcvd_flow.engine.paths import is_cache_dir
from gcvd_flow.engine.runner import Runner, StageReport, diff_fields
from gcvd_flow.engine.store import CorruptObject, MissingObject, Store, StoreError, default_cache_dir

RUN_FILE = "run.json"


@dataclass
class PipelineSpec:
    name: str
    pipeline: Pipeline
    config_model: type
    profiles: dict[str, dict[str, Any]] = field(default_factory=dict)
    open_source: Callable[[str, Any], Any] | None = None
    export: Callable[[Path, Runner, Any], dict[str, Any]] | None = None
    schema_dir: Path | None = None  # <kind>.json schemas of the artifacts its stages write

    def __post_init__(self) -> None:
        if self.schema_dir is not None:
            register_schema_dir(self.schema_dir)
            self._check_schemas()
        self._check_selection_params()

    def _check_schemas(self) -> None:
        """Every artifact kind the stages write has its schema (else its manifests would never
        be validated): a declaration error, not a silent skip."""
        assert self.schema_dir is not None
        for s in self.pipeline.stages:
            for kind in (s.kind, getattr(s, "summary_kind", None)):
                if kind is not None and not (Path(self.schema_dir) / f"{kind}.json").is_file():
                    raise PipelineError(f"stage {s.name!r} writes artifacts of kind {kind!r}, which has no schema "
                                        f"{Path(self.schema_dir) / (kind + '.json')}")

    def _check_selection_params(self) -> None:
        """A map stage's selection_params must name what its key's params hold: parameters of its
        one config section, or sections of its several (a misspelt name would silently stay in
        every item key)."""
        fields = getattr(self.config_model, "model_fields", None)
        if fields is None:
            return
        for s in self.pipeline.stages:
            sel = getattr(s, "selection_params", ())
            if not sel:
                continue
            if isinstance(s.params, str) and s.params in fields:
                known = set(getattr(fields[s.params].annotation, "model_fields", {}))
            else:
                known = set(s.params or ())
            bad = [n for n in sel if n not in known]
            if bad:
                raise PipelineError(f"stage {s.name!r}: selection_params {bad} are not among its parameters "
                                    f"({', '.join(sorted(known)) or 'none'})")

    def watched_paths(self) -> dict[str, list[str]]:
        """What the no-op fast path stats: source folders of the fingerprinted packages, of
        the engine and of the schemas, and the metadata files of the numeric libraries."""
        dirs = {str(Path(__file__).resolve().parent)}
        for pkg in self.pipeline.packages:
            top = pkg.split(".")[0]
            spec = importlib.util.find_spec(top)
            if spec is not None and spec.submodule_search_locations:
                dirs.update(str(Path(d).resolve()) for d in spec.submodule_search_locations)
        if self.schema_dir is not None:
            dirs.add(str(Path(self.schema_dir).resolve()))
        files: list[str] = []
        for _, dists in ENGINE_LIBRARIES + self.pipeline.numeric_libraries:
            for d in dists:
                try:
                    meta = [f for f in importlib.metadata.distribution(d).files or [] if f.name == "METADATA"]
                except importlib.metadata.PackageNotFoundError:
                    continue
                files.extend(str(f.locate()) for f in meta)
        return {"dirs": sorted(dirs), "files": sorted(files)}




def registered_pipelines() -> dict[str, str]:
    """Pipeline name -> ``module:attr`` of every installed pipeline (entry points)."""
    return {ep.name: ep.value for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}


def load_spec(name: str, allow_module_ref: bool = False) -> PipelineSpec:
    """The spec of a registered pipeline; ``module:attr`` only when the caller allows it (a
    developer's explicit command-line choice — never a name read from a run dir or cache)."""
    known = registered_pipelines()
    ref = known.get(name)
    if ref is None:
        if not (allow_module_ref and ":" in name):
            raise UsageError(f"unknown pipeline {name!r}; installed: {', '.join(sorted(known)) or 'none'}")
        ref = name
    mod, _, attr = ref.partition(":")
    try:
        spec = getattr(importlib.import_module(mod), attr)
    except (ImportError, AttributeError) as exc:
        raise UsageError(f"pipeline {name!r}: cannot load {ref} ({exc})") from None
    if not isinstance(spec, PipelineSpec):
        raise UsageError(f"pipeline {name!r}: {ref} is not a PipelineSpec")
    return spec


@dataclass
class Invocation:
    input: str | None
    out: str | None
    config_file: str | None = None
    profile: str | None = None
    sets: list[str] = field(default_factory=list)
    cache: str | None = None
    jobs: int = 0  # map-item worker processes; 0 = auto (executors.resolve_jobs)
    json_mode: bool = False
    pipeline: str = ""  # a registered pipeline name (the product's CLI and API set theirs)
    verify: bool = True
    remote: str | None = None  # read-through remote: a name in the remotes file or a URL
    remotes_file: str | None = None
    push: bool = False  # write-through: push what each stage computed to the remote
    executor: str = "process"  # or "dask"
    scheduler: str | None = None  # Dask scheduler address; None: a LocalCluster of `jobs` workers

    def recorded(self) -> dict[str, Any]:
        """What a run dir remembers to recompute keys later (`why`, `status`)."""
        return {"input": os.path.abspath(self.input) if self.input else None,
                "config_file": os.path.abspath(self.config_file) if self.config_file else None,
                "profile": self.profile, "sets": list(self.sets), "pipeline": self.pipeline}


def open_store(cache: str | None, verify: bool = True) -> Store:
    root = Path(cache) if cache else default_cache_dir()
    if root.exists() and not root.is_dir():
        raise UsageError(f"{root}: cache is not a directory")
    try:
        store = Store(root, verify=verify)
    except OSError as exc:
        raise UsageError(f"cannot use cache directory {root}: {exc.strerror}") from None
    if not os.access(store.root / "objects", os.W_OK | os.X_OK):
        raise UsageError(f"{root}: cache directory is not writable")
    return store


def _prepare(inv: Invocation, log: Callable[[str], None], target: str | None = None,
             allow_module_ref: bool = True, writes_out: bool = True) -> tuple[PipelineSpec, Any, Runner]:
    if not inv.pipeline:
        raise UsageError("no pipeline named")
    spec = load_spec(inv.pipeline, allow_module_ref)
    config = build_config(spec.config_model, spec.profiles, inv.profile, inv.config_file, inv.sets)
    if target is not None:
        spec.pipeline.get(target)  # unknown stage -> one clear line
    if inv.input is None:
        raise UsageError("no INPUT given")
    if inv.out and writes_out:
        check_out_dir(inv.out)
    source = spec.open_source(inv.input, config) if spec.open_source else None
    store = open_store(inv.cache, inv.verify)
    seed = int(getattr(config, "seed", 0))
    runner = Runner(spec.pipeline, store, config, source=source, jobs=inv.jobs,
                    json_mode=inv.json_mode, seed=seed, log=log)
    return spec, config, runner


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _previous_stages(out: str | None) -> dict[str, Any] | None:
    """The stages run.json recorded, for `plan`'s reasons (None: no or an unusable run.json)."""
    if not out or not (Path(out) / RUN_FILE).exists():
        return None
    try:
        return read_run_dir(out)["stages"]
    except UsageError:
        return None


MAX_HEALING_PASSES = 8


def _attach(inv: Invocation, runner: Runner, log: Callable[[str], None], executor: Any, records: Any) -> Any:
    """Remote record source (made once per run, kept across its self-healing passes: it
    remembers what came in and what it refused; it is also the store's lazy object source),
    executor kind and a shared executor (run-many) for one pass; returns the record source."""
    if records is None and (inv.remote or inv.push):
        from gcvd_flow.engine.remote import record_source

        records = record_source(runner.store, inv.remote, inv.remotes_file, push=inv.push, log=log)
    if records is not None:
        records.attach(runner.store)
        runner.records = records
    runner.executor_kind, runner.scheduler, runner.shared_executor = inv.executor, inv.scheduler, executor
    return records


def run(inv: Invocation, log: Callable[[str], None] = _stderr, target: str | None = None,
        executor: Any = None) -> dict[str, Any]:
    """Run the pipeline, export results into ``inv.out``; returns the --json document.

    Self-healing: a corrupt object (quarantined on read) or a missing one makes every record
    that names it invisible (records are checked against their objects), so another pass
    recomputes exactly what it held; the run ends normally with one warning line naming the
    damaged objects and the stages that recomputed something. The same object failing twice
    (a recomputation that cannot restore it) is an error."""
    if not inv.out:
        return _run(inv, log, target, executor)
    check_out_dir(inv.out)
    with run_dir_lock(inv.out):  # one writer of RUN_DIR at a time (engine/outputs.py)
        return _run(inv, log, target, executor)


def _run(inv: Invocation, log: Callable[[str], None], target: str | None, executor: Any) -> dict[str, Any]:
    t0 = time.perf_counter()
    damaged: list[str] = []
    from_remote: set[str] = set()  # objects the remote could not supply (it said so on one line)
    passes: list[list[StageReport]] = []
    records = None
    while True:
        spec, config, runner = _prepare(inv, log, target)
        records = _attach(inv, runner, log, executor, records)
        try:
            with runner.store.lease():  # gc waits for this run (and never deletes its objects)
                reports = runner.run(target)
                passes.append(reports)
                result = _finish_run(inv, spec, config, runner, target)
            break
        except (CorruptObject, MissingObject) as exc:
            passes.append(list(runner.reports.values()))
            if exc.digest in damaged or len(damaged) >= MAX_HEALING_PASSES:
                raise StoreError(f"{exc}; recomputing did not restore it (run `{TOOL} fsck`)") from None
            damaged.append(exc.digest)
            if getattr(exc, "remote", False):
                from_remote.add(exc.digest)
    result["stages"] = [r.as_run_json() for r in _merge_passes(passes)]
    result["seconds"] = round(time.perf_counter() - t0, 3)
    if runner.records is not None:
        result["remote"] = runner.records.report()
    if damaged:
        redone = sorted({r.name for ps in passes[1:] for r in ps if r.executed})
        result["healed"] = {"objects": damaged, "recomputed": redone}
        local = [d for d in damaged if d not in from_remote]
        if local:
            log(f"warning: {len(local)} damaged cache object(s) ({', '.join(d[:12] for d in local)}) were "
                f"quarantined or missing; recomputed: {', '.join(redone) or 'nothing'}")
    return result


def _merge_passes(passes: list[list[StageReport]]) -> list[StageReport]:
    """The last pass's reports, with what earlier (interrupted) passes executed counted as
    executed rather than cached."""
    final = [StageReport(r.name, r.action, list(r.reasons), r.executed, r.cached, r.seconds, r.key, r.output,
                         r.fields) for r in passes[-1]]
    for r in final:
        earlier = sum(p.executed for ps in passes[:-1] for p in ps if p.name == r.name)
        r.executed += earlier
        r.cached = max(0, r.cached - earlier)
        r.seconds += sum(p.seconds for ps in passes[:-1] for p in ps if p.name == r.name)
    return final


def _finish_run(inv: Invocation, spec: PipelineSpec, config: Any, runner: Runner,
                target: str | None) -> dict[str, Any]:
    """Register the run in the cache, export its results and write RUN_DIR/run.json."""
    result: dict[str, Any] = {}
    stage_records = runner.stage_summary()
    runner.store.add_run({"records": [r["key"] for r in stage_records.values() if r["key"]],
                          "pipeline": spec.name})
    if inv.out:
        out = Path(inv.out)
        out.mkdir(parents=True, exist_ok=True)
        if spec.export is not None and target is None:
            try:
                result["outputs"] = spec.export(out, runner, config)
            except OSError as exc:  # a full disk under RUN_DIR: say where (numpy's errors name no file)
                if exc.filename is not None:
                    raise
                what = exc.strerror or (f"cannot write the run's outputs ({exc}; is the disk full?)" if str(exc)
                                        else "cannot write the run's outputs (is the disk full?)")
                raise OSError(exc.errno, what, str(out)) from exc
        files = digest_outputs(out, outputs_of(result))  # what compare --check and the fast path verify
        doc = {"invocation": inv.recorded(), "config": json.loads(config.model_dump_json()),
               "stages": stage_records, "stage_order": list(stage_records),
               # what this run computed vs found cached (read by `runs`)
               "counts": {n: {"executed": r.executed, "cached": r.cached, "seconds": round(r.seconds, 3)}
                          for n, r in runner.reports.items()},
               "env": spec.pipeline.numeric_env(), "gcvd_flow": _version(),
               "cache": str(runner.store.root.resolve()), "files": files}
        tmp = out / (RUN_FILE + ".tmp")
        tmp.write_text(json.dumps(doc, indent=1, sort_keys=True))
        os.replace(tmp, out / RUN_FILE)
        result["out"] = str(out)
    result["cache"] = str(runner.store.root)
    result["_watch"] = spec.watched_paths()
    result["_record_paths"] = [str(runner.store.record_path(r["key"])) for r in stage_records.values() if r["key"]]
    return result


def plan(inv: Invocation, log: Callable[[str], None] = _stderr) -> list[StageReport]:
    _, _, runner = _prepare(inv, log, writes_out=False)
    return runner.plan(_previous_stages(inv.out))


def _invocation_from_run(out: str, extra: Invocation | None) -> Invocation:
    doc = read_run_dir(out)
    rec = doc.get("invocation") if isinstance(doc, dict) else None
    if not isinstance(rec, dict):
        raise UsageError(f"{Path(out) / RUN_FILE}: not a valid run record (no invocation)")
    name = rec.get("pipeline")
    if not isinstance(name, str) or name not in registered_pipelines():
        # a run dir travels between people: it may name a pipeline, never code to import
        raise UsageError(f"{Path(out) / RUN_FILE}: invocation.pipeline {name!r} is not an installed "
                         f"pipeline ({', '.join(sorted(registered_pipelines()))})")
    inv = Invocation(input=rec.get("input"), out=out, config_file=rec.get("config_file"),
                     profile=rec.get("profile"), sets=[str(s) for s in rec.get("sets") or []],
                     pipeline=name)
    if extra is not None:
        inv.cache = extra.cache
        inv.json_mode = extra.json_mode
        if extra.config_file:
            inv.config_file = extra.config_file
        if extra.profile:
            inv.profile = extra.profile
        inv.sets += list(extra.sets)
    if inv.cache is None and isinstance(doc.get("cache"), str) and is_cache_dir(doc["cache"]):
        inv.cache = doc["cache"]  # the cache the run recorded, when no --cache is given (never a
        # folder it merely names: `status` / `why` must not create a cache wherever run.json points)
    return inv


def why(stage: str, out: str, extra: Invocation | None = None,
        log: Callable[[str], None] = _stderr) -> dict[str, Any]:
    """Field-by-field difference between the current key of ``stage`` and its last run."""
    inv = _invocation_from_run(out, extra)
    previous = read_run_dir(out)["stages"]
    spec, _, runner = _prepare(inv, log, allow_module_ref=False, writes_out=False)
    spec.pipeline.get(stage)  # unknown stage -> clear error
    reports = {r.name: r for r in runner.plan(previous, target=stage)}
    rep = reports[stage]
    prev = previous.get(stage)
    if prev is None:
        reasons = ["this stage has no recorded run in this directory"]
    elif rep.action == "cached":
        reasons = []
    else:
        reasons = rep.reasons
    return {"stage": stage, "action": rep.action, "reasons": reasons,
            "key": rep.key, "previous_key": (prev or {}).get("key")}


def status(out: str, extra: Invocation | None = None, log: Callable[[str], None] = _stderr) -> list[StageReport]:
    inv = _invocation_from_run(out, extra)
    previous = read_run_dir(out)["stages"]
    _, _, runner = _prepare(inv, log, allow_module_ref=False, writes_out=False)
    return runner.plan(previous)


def recorded_output(out: str | Path, stage: str, cache: str | None = None, verify: bool = True) -> Any:
    """The output a run directory recorded for ``stage``, decoded from the cache by its digest.

    Needs neither the run's input nor the current code: ``run.json`` names the exact content
    the run produced (its output digest), so this is what the run used even if the input or the
    code changed since. A map stage gives a lazily loading ``MapValue`` (with ``.summary``);
    every object its items need is checked to be present first. Raises ``UsageError`` if the
    run directory has no output recorded for ``stage``, ``StoreError`` if the cache does not
    hold it (any more) and ``ArtifactError`` for an unreadable manifest. Adds nothing to the
    cache (a corrupt object is quarantined, as on every verified read).
    """
    from gcvd_flow.engine.artifacts import decode_tree, load_manifest, load_value, manifest_objects
    from gcvd_flow.engine.dag import MapValue

    rec = (read_run_dir(out).get("stages") or {}).get(stage) or {}
    digest = rec.get("output")
    if not digest:
        raise UsageError(f"{Path(out) / RUN_FILE}: no output of stage {stage!r} recorded")
    root = Path(cache).expanduser() if cache else default_cache_dir()
    if not (root / "objects").is_dir():
        raise StoreError(f"{root} is not a {TOOL} cache directory")
    store = Store(root, verify=verify)
    man = load_manifest(store, digest)
    if "items" not in man:
        return decode_tree(store, man.get("value"))
    items = list(man["items"])
    for d in items:
        missing = [o for o in manifest_objects(store, d) if not store.has(o)]
        if missing:
            raise StoreError(f"object {missing[0][:12]} of stage {stage!r} is missing from the cache")
    return MapValue(lambda i: load_value(store, items[i]), len(items), decode_tree(store, man.get("summary")))


def fsck(cache: str | None) -> dict[str, Any]:
    return open_store(cache).fsck().as_dict()


def gc(cache: str | None, keep: int, wait: bool = True, log: Callable[[str], None] = _stderr) -> dict[str, int]:
    """Drop what the last ``keep`` runs and the pins do not reach; waits for runs in progress."""
    if not 0 <= keep <= Store.MAX_KEEP:
        raise UsageError(f"--keep {keep}: must be from 0 to {Store.MAX_KEEP} (runs to keep)")
    try:
        return open_store(cache).gc(keep=keep, wait=wait,
                                    on_wait=lambda: log("gc: waiting for the runs using this cache to finish"))
    except StoreError as exc:
        raise UsageError(f"gc: {exc}") from None


def _version() -> str:
    try:
        import importlib.metadata

        return importlib.metadata.version(TOOL)
    except Exception:
        return "0+unknown"


__all__ = ["Invocation", "PipelineSpec", "run", "plan", "why", "status", "recorded_output", "fsck", "gc",
           "diff_fields"]
