"""Plan, execute and explain a pipeline against a content-addressed store.

For each stage in topological order the runner computes the key (docs/design.md, "Cache keys") from the stage's
code fingerprint, its own parameters, the digests of its inputs' *outputs* and the numeric
environment. A record for the key means the stage is cached; otherwise it runs (a map stage
item by item, each item keyed by its own inputs) and its record is written last.
"""

from __future__ import annotations

import contextlib
import functools
import os
import sys
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Iterator, Mapping

from gcvd_flow.engine import keys
from gcvd_flow.engine.artifacts import Encoder, Stored, Tensors, decode_tree, is_leaf, leaf_digests, load_manifest, load_value, validate
from gcvd_flow.engine.dag import Const, ExternalRef, ItemRef, MapStage, MapValue, PartRef, Pipeline, PipelineError, Stage, stage_name
from gcvd_flow.engine.errors import UsageError
from gcvd_flow.engine.executors import (
    SHARED,
    InProcessExecutor,
    ItemTask,
    ProcessPoolItemExecutor,
    ResolvedRef,
    closing,
    make_executor,
    open_resource,
)
from gcvd_flow.engine.names import ENV_OVERLAP
from gcvd_flow.engine.store import Store

# ------------------------------------------------------------------------------ reports


@dataclass
class StageReport:
    name: str
    action: str = "cached"  # plan: "run" | "cached"
    reasons: list[str] = field(default_factory=list)
    executed: int = 0
    cached: int = 0
    seconds: float = 0.0
    key: str | None = None
    output: str | None = None
    fields: dict[str, Any] | None = None

    def as_run_json(self) -> dict[str, Any]:
        return {"name": self.name, "executed": self.executed, "cached": self.cached,
                "seconds": round(self.seconds, 3)}

    def as_plan_json(self) -> dict[str, Any]:
        return {"name": self.name, "action": self.action, "reasons": self.reasons}


# ------------------------------------------------------------------------------ progress


class Progress:
    """One self-overwriting line per stage on a TTY: items done, items/s, ETA."""

    def __init__(self, name: str, total: int, enabled: bool):
        self.name, self.total, self.enabled = name, total, enabled and total > 0
        self.done = 0
        self.t0 = time.perf_counter()
        self._last = 0.0

    def update(self, n: int = 1) -> None:
        self.done += n
        if not self.enabled:
            return
        now = time.perf_counter()
        if now - self._last < 0.1 and self.done < self.total:
            return
        self._last = now
        rate = self.done / max(now - self.t0, 1e-9)
        eta = (self.total - self.done) / rate if rate > 0 else 0.0
        width = 24
        filled = int(width * self.done / self.total)
        bar = "#" * filled + "." * (width - filled)
        sys.stderr.write(f"\r{self.name:<20} [{bar}] {self.done}/{self.total} "
                         f"{rate:6.1f} it/s ETA {int(eta) // 60}:{int(eta) % 60:02d} ")
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")
            sys.stderr.flush()


def progress_enabled(json_mode: bool) -> bool:
    return sys.stderr.isatty() and not json_mode and not os.environ.get("CI")


# ------------------------------------------------------------------------------ checkpoints


class Checkpointer:
    """Lets a long whole stage save and resume its state inside the store.

    ``save(tensors, meta, shards)`` stores the tensors as one safetensors object, each shard
    (``{name: {key: array}}``) as its own safetensors object and the meta as JSON, under a record
    keyed by the stage key (atomically: an interrupted save leaves the previous checkpoint in
    place). Shards are for state that grows and no longer changes (e.g. the results of finished
    windows): being content-addressed, a shard saved again unchanged is written once, so saving
    every window costs O(window), not O(clip), in memory and disk. ``load()`` returns
    ``(arrays, meta)`` or None (numpy arrays; tensors given to ``save`` come back as arrays),
    shard arrays among them as ``"shard/key"``.
    """

    def __init__(self, store: Store, stage_key: str, stage: str, log: Callable[[str], None]):
        self.store = store
        self.preimage = ["checkpoint", stage_key]
        self.key = keys.key_of(self.preimage)
        self.stage = stage
        self.log = log
        self.saves = 0

    @staticmethod
    def _arrays(tensors: dict[str, Any]) -> dict[str, Any]:
        arrays = {}
        for k, v in tensors.items():
            if hasattr(v, "detach"):
                v = v.detach().cpu().contiguous().numpy()
            arrays[k] = v
        return arrays

    def save(self, tensors: dict[str, Any], meta: dict[str, Any],
             shards: dict[str, dict[str, Any]] | None = None) -> None:
        enc = Encoder(self.store)
        value: dict[str, Any] = {"tensors": Tensors(self._arrays(tensors)), "meta": meta}
        if shards:
            # views, encoded one at a time: never more than one shard's bytes in memory; a shard
            # of handles (``StageContext.put``) points at objects the stage already stored
            value["shards"] = {name: t if _has_stored(t) else Tensors(self._arrays(t)) for name, t in shards.items()}
        out = enc.manifest("checkpoint", value)
        self.store.put_record(self.key, {"record_kind": "checkpoint", "stage": self.stage, "preimage": self.preimage,
                                         "outputs": out, "objects": enc.objects})
        self.saves += 1

    def load(self) -> tuple[dict[str, Any], dict[str, Any]] | None:
        rec = self.store.get_record(self.key)
        if rec is None:
            return None
        value = load_value(self.store, rec["outputs"])
        tensors = dict(value["tensors"])
        for name, arrays in (value.get("shards") or {}).items():
            tensors.update({f"{name}/{k}": v for k, v in arrays.items()})
        meta = value["meta"]
        shown = ', '.join(f'{k}={meta[k]}' for k in sorted(meta) if isinstance(meta[k], (int, float, str)))
        self.log(f"resuming from checkpoint ({shown})")
        return tensors, meta

    def discard(self) -> None:
        self.store.delete_record(self.key)


def _load_item(store: Store, digests: list[str], i: int) -> Any:
    """Item i of a map stage's output (``digests``: its items' value digests)."""
    return load_value(store, digests[i])


def _has_stored(shard: dict[str, Any]) -> bool:
    return any(isinstance(v, Stored) or (isinstance(v, list) and any(isinstance(x, Stored) for x in v))
               for v in shard.values())


class StageContext:
    """The ``ctx`` a whole stage sees: name, seed, logger, checkpointer, resources, ``put`` to
    store part of its output before it returns, and ``map`` to spread independent calls over the
    run's worker processes."""

    def __init__(self, stage: Stage, seed: int, log: Callable[[str], None],
                 checkpointer: Checkpointer | None, params: Any = None, params_key: str = "",
                 store: Store | None = None, executor: Any = None):
        self.stage = stage.name
        self.seed = seed
        self._log = log
        self.checkpointer = checkpointer
        self._resources, self._params, self._params_key = stage.resources, params, params_key
        self._store = store
        self._executor = executor

    def map(self, fn: Callable[[Any], Any], args: Iterable[Any]) -> Iterator[Any]:
        """``fn(arg)`` for each argument, results in argument order: on the run's workers
        (``--jobs``; a few calls, or no workers, run here). ``fn`` must be a module-level
        function and the arguments picklable; the stage's output must not depend on where the
        calls ran (its key does not hold the job count). Arguments are built lazily, a few
        at a time, so an iterator of large per-call inputs costs memory for those in flight."""
        if self._executor is None:
            return map(fn, args)
        return self._executor.map_calls(fn, args)

    def put(self, value: Any) -> Stored:
        """Store ``value`` (arrays, lists, dicts) now and return a handle the stage may put in
        its output (or a checkpoint shard) in its place: memory stays at one part, not the
        whole output. The objects are written like the output's (content-addressed,
        atomically); until the stage's record exists they are unreferenced, like any object
        of an interrupted stage."""
        if self._store is None:
            raise RuntimeError(f"{self.stage}: this context has no store to put values in")
        return Encoder(self._store).stored(value)

    def log(self, msg: str) -> None:
        self._log(f"{self.stage}: {msg}")

    def resource(self, name: str) -> Any:
        return open_resource(self.stage, name, self._resources.get(name), self._params, self._params_key)


# ------------------------------------------------------------------------------ runner


def params_for_key(params: Any) -> Any:
    """A stage's parameters as they enter its key (file paths replaced by file digests)."""
    if params is None:
        return None
    if hasattr(params, "key_dict"):
        return params.key_dict()
    if hasattr(params, "model_dump"):
        return params.model_dump(mode="python")
    return params


class ParamBundle:
    """Several config sections seen by one stage: ``bundle.depth.mesh``; keyed as a dict."""

    def __init__(self, sections: dict[str, Any]):
        self._sections = sections
        for k, v in sections.items():
            setattr(self, k, v)

    def key_dict(self) -> dict[str, Any]:
        return {k: params_for_key(v) for k, v in self._sections.items()}

    def __reduce__(self):  # picklable for worker processes
        return (ParamBundle, (self._sections,))


class _View:
    """The DepsView handed to ``items`` and ``summary`` functions of ``stage``: it reads only the
    stages ``stage`` declares in ``deps=`` (an undeclared read would be missing from its key)."""

    def __init__(self, runner: "Runner", stage: Stage):
        self._r = runner
        self._stage = stage
        self.source = runner.source

    def _dep(self, stage: str | Stage) -> str:
        name = stage_name(stage)
        if name not in self._stage.deps:
            raise PipelineError(f"stage {self._stage.name!r} reads {name!r} in its items or summary function "
                                f"but does not declare it in deps=")
        return name

    def len(self, stage: str | Stage) -> int:
        return len(self._r._items[self._dep(stage)])

    def value(self, stage: str | Stage) -> Any:
        return self._r.value(self._dep(stage))

    def summary(self, stage: str | Stage) -> Any:
        return decode_tree(self._r.store, self._r._manifest(self._dep(stage)).get("summary"))


def check_item_refs(stage: Stage, items: list[dict[str, Any]]) -> None:
    """Every item / part reference an items function built names a declared dependency: the
    stage's key holds only its deps' outputs, so an undeclared one would leave it stale."""
    bad: set[str] = set()

    def walk(r: Any) -> None:
        if isinstance(r, list):
            for x in r:
                walk(x)
        elif isinstance(r, (ItemRef, PartRef)) and r.stage not in stage.deps:
            bad.add(r.stage)

    for it in items:
        for r in it.values():
            walk(r)
    if bad:
        raise PipelineError(f"stage {stage.name!r}: its items reference {', '.join(sorted(bad))}, "
                            f"not declared in deps= ({', '.join(stage.deps) or 'none'})")


class Runner:
    # Set by the API before run(): where records are looked up besides the store (a remote for
    # `run --remote`: remote.RemoteRecords with get_record / prefetch / stage_done), which item
    # executor ("process" or "dask", and the Dask scheduler address) and an executor shared by
    # several runs (run-many), closed by its owner.
    records: Any = None
    executor_kind: str = "process"
    scheduler: str | None = None
    shared_executor: Any = None

    def __init__(self, pipeline: Pipeline, store: Store, config: Any, source: Any = None,
                 jobs: int = 1, json_mode: bool = False, seed: int = 0,
                 log: Callable[[str], None] | None = None):
        self.pipeline = pipeline
        self.store = store
        self.config = config
        self.source = source
        self.jobs = jobs
        self.json_mode = json_mode
        self.seed = seed
        self.log = log or (lambda m: print(m, file=sys.stderr))
        self._outputs: dict[str, str] = {}  # stage -> manifest digest
        self._items: dict[str, list[str]] = {}  # map stage -> item manifest digests
        self._manifests: dict[str, dict[str, Any]] = {}
        self._values: dict[str, Any] = {}
        self.reports: dict[str, StageReport] = {}

    # ---------------------------------------------------------------- helpers

    def stage_params(self, stage: Stage) -> Any:
        if stage.params is None:
            return None
        if isinstance(stage.params, tuple):  # a stage reading several config sections
            return ParamBundle({name: getattr(self.config, name) for name in stage.params})
        return getattr(self.config, stage.params)

    def _manifest(self, stage: str) -> dict[str, Any]:
        m = self._manifests.get(stage)
        if m is None:
            m = self._manifests[stage] = load_manifest(self.store, self._outputs[stage])
        return m

    def output(self, stage: str) -> str:
        return self._outputs[stage]

    def value(self, stage: str | Stage) -> Any:
        """The decoded output of a finished stage (given by declaration or name; a MapValue for
        map stages)."""
        stage = stage_name(stage)
        if stage in self._values:
            return self._values[stage]
        st = self.pipeline.get(stage)
        man = self._manifest(stage)
        if st.is_map:
            digests = self._items[stage]
            v: Any = MapValue(functools.partial(_load_item, self.store, digests), len(digests),
                              decode_tree(self.store, man.get("summary")))
        else:
            v = decode_tree(self.store, man["value"])
        self._values[stage] = v
        return v

    def part(self, stage: str | Stage, path: tuple = ()) -> Any:
        """A sub-tree of a finished whole stage's output (keys / indices in ``path``), decoding
        only the objects under it: e.g. the poses of a stage whose other outputs are large."""
        stage = stage_name(stage)
        if stage in self._values:
            node = self._values[stage]
            for p in path:
                node = node[p]
            return node
        node = self._manifest(stage)["value"]
        for p in path:
            node = node[p]
        return decode_tree(self.store, node)

    def _key_fields(self, stage: Stage, inputs: Mapping[str, str | None]) -> dict[str, Any]:
        fp, files = keys.code_fingerprint(stage.fn, self.pipeline.packages, self.pipeline.adapters)
        for name, opener in sorted(stage.resources.items()):  # e.g. the code that builds a model
            rfp, rfiles = keys.code_fingerprint(opener, self.pipeline.packages, self.pipeline.adapters)
            fp, files = keys.key_of([fp, name, rfp]), tuple(sorted(set(files) | set(rfiles)))
        params = params_for_key(self.stage_params(stage))
        out = {"code": fp, "code_files": {k: v for k, v in files}, "version": stage.version,
               "params": params, "seed": self.seed if stage.uses_seed else None,
               "inputs": inputs, "env": self.pipeline.numeric_env()}
        if isinstance(stage, MapStage):
            # which items exist and the summary are the items / summary functions' doing: their
            # code enters the *stage* key (a changed reference rule must not find the old stage
            # record and reuse its item list), not the item keys (an item is its inputs' function)
            sel = [(name, fn) for name, fn in (("items", stage.items), ("summary", stage.summary)) if fn is not None]
            sel_fps: list[Any] = []
            for name, fn in sel:
                sfp, sfiles = keys.selection_fingerprint(fn, self.pipeline.packages, self.pipeline.adapters)
                sel_fps += [name, sfp]
                out["code_files"].update(sfiles)
            out["item_code"] = fp
            out["code"] = keys.key_of([fp, "selection", *sel_fps])
        return out

    @staticmethod
    def _preimage(record_kind: str, stage: Stage, f: dict[str, Any], params: Any = None,
                  inputs: Any = None) -> list[Any]:
        p = f["params"] if params is None else params
        code = f["item_code"] if record_kind == "item" and "item_code" in f else f["code"]
        return keys.key_preimage(record_kind, stage.name, code,
                                 {"params": p, "seed": f["seed"], "version": f["version"]},
                                 f["inputs"] if inputs is None else inputs, f["env"])

    def _key(self, record_kind: str, stage: Stage, f: dict[str, Any], params: Any = None,
             inputs: Any = None) -> str:
        return keys.key_of(self._preimage(record_kind, stage, f, params, inputs))

    def _item_params(self, stage: MapStage, f: dict[str, Any]) -> Any:
        p = f["params"]
        if isinstance(p, dict) and stage.selection_params:
            p = {k: v for k, v in p.items() if k not in stage.selection_params}
        return p

    def _resolve(self, ref: Any) -> ResolvedRef:
        if isinstance(ref, list):
            parts = [self._resolve(r) for r in ref]
            return ResolvedRef("list", keys.key_of([p.digest for p in parts]), parts)
        if isinstance(ref, ItemRef):
            return ResolvedRef("artifact", self._items[ref.stage][ref.index])
        if isinstance(ref, PartRef):
            man = self._manifest(ref.stage)
            node: Any = man.get("summary") if ref.summary else man["value"]
            for p in ref.path:
                node = node[p]
            if is_leaf(node):
                digest = next(v for k, v in node.items() if k.startswith("$"))
            else:
                digest = keys.key_of(node)
            return ResolvedRef("tree", digest, node)
        if isinstance(ref, ExternalRef):
            return ResolvedRef("external", ref.digest, ref.loader)
        if isinstance(ref, Const):
            return ResolvedRef("const", keys.key_of(ref.value), ref.value)
        raise TypeError(f"unknown reference {ref!r}")

    def _input_digests(self, stage: Stage) -> dict[str, str] | None:
        if not all(d in self._outputs for d in stage.deps):
            return None
        ins = {d: self._outputs[d] for d in stage.deps}
        if not stage.deps and self.source is not None and hasattr(self.source, "digest"):
            ins = {"source": self.source.digest}
        return ins

    # ---------------------------------------------------------------- plan / why

    def plan(self, previous: dict[str, Any] | None = None, target: str | None = None) -> list[StageReport]:
        """Dry run: per stage `run` or `cached` with reasons; computes nothing."""
        out = []
        for stage in self.pipeline.upto(target):
            rep = StageReport(stage.name)
            ins = self._input_digests(stage)
            prev_fields = (previous or {}).get(stage.name, {}).get("fields")
            if ins is None:
                waiting = [d for d in stage.deps if d not in self._outputs]
                rep.action = "run"
                rep.reasons.append(f"upstream will run: {', '.join(waiting)}")
                f = self._key_fields(stage, {d: self._outputs.get(d) for d in stage.deps})
                if prev_fields:
                    section = stage.params if isinstance(stage.params, str) else None
                    rep.reasons.extend(r for r in diff_fields(prev_fields, f, section) if not r.startswith("input "))
                out.append(rep)
                continue
            f = self._key_fields(stage, ins)
            key = self._key("stage", stage, f)
            rep.key, rep.fields = key, f
            rec = self.store.get_record(key)
            if rec is not None:
                self._outputs[stage.name] = rec["outputs"]
                if stage.is_map:
                    self._items[stage.name] = list(self._manifest(stage.name)["items"])
                rep.action = "cached"
                out.append(rep)
                continue
            rep.action = "run"
            if prev_fields:
                rep.reasons.extend(diff_fields(prev_fields, f, stage.params if isinstance(stage.params, str) else None))
            elif previous is None or stage.name not in (previous or {}):
                rep.reasons.append("no previous run of this stage")
            if isinstance(stage, MapStage):
                try:
                    items = stage.items(_View(self, stage), self.stage_params(stage))
                    check_item_refs(stage, items)
                    item_params = self._item_params(stage, f)
                    missing = 0
                    for it in items:
                        refs = {n: self._resolve(r).digest for n, r in sorted(it.items())}
                        ik = self._key("item", stage, f, item_params, refs)
                        if self.store.get_record(ik) is None:
                            missing += 1
                    rep.reasons.append(f"{missing} of {len(items)} items to compute")
                except UsageError:
                    raise
            if not rep.reasons:
                rep.reasons.append("no record for this key in the cache")
            out.append(rep)
        return out

    # ---------------------------------------------------------------- execution

    def run(self, target: str | None = None) -> list[StageReport]:
        executor = self.shared_executor or make_executor(self.jobs, self.pipeline.worker_init,
                                                         self.executor_kind, self.scheduler)
        stages = list(self.pipeline.upto(target))
        beside = _Beside(self, executor) if self._may_overlap(executor) else None
        try:
            # an executor of this run is closed with it (at once, its workers ended, on Ctrl-C,
            # SIGTERM or SIGHUP); a shared one by its owner
            with closing(executor) if executor is not self.shared_executor else contextlib.nullcontext():
                self._run_stages(stages, executor, beside)
        finally:
            if beside is not None:
                beside.close()
        return [self.reports[s.name] for s in self.pipeline.upto(target)]

    def _run_stages(self, stages: list[Stage], executor: Any, beside: "_Beside | None") -> None:
        last_reader = {d: k for k, st in enumerate(stages) for d in st.deps}
        for k, stage in enumerate(stages):
            rep = beside.take(stage.name) if beside is not None else None
            if rep is None:
                if beside is not None and not stage.is_map:
                    beside.start(stages[k + 1:])
                rep = self._run_stage(stage, executor)
            self.reports[stage.name] = rep
            if self.records is not None:  # write-through (`run --push`)
                self.records.stage_done(rep.key, rep.executed)
            # decoded outputs no later stage reads are dropped (decoded again if asked
            # for): a long clip's keyframe depths need not live until the last stage
            for name in [n for n in list(self._values) if last_reader.get(n, -1) <= k]:
                self._values.pop(name, None)

    def _may_overlap(self, executor: Any) -> bool:
        """Whether map stages may run beside a whole stage (``_Beside``): opt-in (``$GCVD_FLOW_OVERLAP``
        is ``1``: it did not measure better on the 2-core machine, docs/log/2026-11-28-fastengine.md),
        on a local process pool of two or more workers, without a remote (whose write-through and
        read-through follow the stages one at a time)."""
        return (os.environ.get(ENV_OVERLAP, "").strip() == "1" and isinstance(executor, ProcessPoolItemExecutor)
                and executor.jobs >= 2 and self.records is None and self.store.fallback is None)

    def _run_stage(self, stage: Stage, executor, beside: bool = False) -> StageReport:
        t0 = time.perf_counter()
        ins = self._input_digests(stage)
        assert ins is not None
        f = self._key_fields(stage, ins)
        key = self._key("stage", stage, f)
        rep = StageReport(stage.name, key=key, fields=f)
        # read-through (`run --remote`): a record missing here is looked up in the remote
        rec = self.store.get_record(key) if self.records is None else self.records.get_record(key)
        if rec is not None:
            self._outputs[stage.name] = rec["outputs"]
            if stage.is_map:
                self._items[stage.name] = list(self._manifest(stage.name)["items"])
                rep.cached = len(self._items[stage.name])
            else:
                rep.cached = 1
            rep.action = "cached"
            rep.output = rec["outputs"]
            rep.seconds = time.perf_counter() - t0
            return rep
        rep.action = "run"
        if isinstance(stage, MapStage):
            self._run_map(stage, f, key, rep, executor, beside)
        else:
            self._run_whole(stage, f, key, rep, executor)
        rep.output = self._outputs[stage.name]
        rep.seconds = time.perf_counter() - t0
        return rep

    def _run_whole(self, stage: Stage, f: dict[str, Any], key: str, rep: StageReport, executor: Any = None) -> None:
        t0 = time.perf_counter()
        with self.store.lock(key):
            rec = self.store.get_record(key)
            if rec is None:
                inputs = {d: self.value(d) for d in stage.deps}
                ckpt = Checkpointer(self.store, key, stage.name, self.log)
                params = self.stage_params(stage)
                ctx = StageContext(stage, self.seed, self.log, ckpt, params, keys.key_of(f["params"]), self.store,
                                   executor)
                value = stage.fn(inputs, params, ctx)
                enc = Encoder(self.store)
                out = enc.manifest(stage.kind, value)
                rec = {"record_kind": "stage", "stage": stage.name, "key": key, "outputs": out,
                       "objects": enc.objects, "fields": _jsonable_fields(f),
                       "preimage": self._preimage("stage", stage, f),
                       "seconds": round(time.perf_counter() - t0, 6)}
                if stage.nondeterministic:
                    rec["nondeterministic"] = stage.nondeterministic
                self.store.sync()
                self.store.put_record(key, rec)
                ckpt.discard()
                rep.executed = 1
            else:
                rep.cached = 1
        self._outputs[stage.name] = rec["outputs"]

    def _run_map(self, stage: MapStage, f: dict[str, Any], key: str, rep: StageReport,
                 executor, beside: bool = False) -> None:
        """``beside``: running beside a whole stage (``_Beside``): its items on the workers, however
        few, and no progress line."""
        t0 = time.perf_counter()
        params = self.stage_params(stage)
        view = _View(self, stage)
        items = stage.items(view, params)
        check_item_refs(stage, items)
        summary = stage.summary(view, params) if stage.summary is not None else None
        item_params = self._item_params(stage, f)
        tasks = []
        item_keys = []
        params_key = keys.key_of(f["params"])  # the resources' parameter digest: the same for every item
        for i, it in enumerate(items):
            refs = {n: self._resolve(r) for n, r in sorted(it.items())}
            pre = self._preimage("item", stage, f, item_params, {n: r.digest for n, r in refs.items()})
            ik = keys.key_of(pre)
            item_keys.append(ik)
            tasks.append(ItemTask(str(self.store.root), self.store.verify, stage.name, stage.fn,
                                  stage.kind, ik, refs, params, self.seed, i, stage.resources or None,
                                  params_key, pre, key if stage.share_inputs else None))
        outputs: list[str | None] = [None] * len(tasks)
        objects: dict[str, int] = {}
        prog = Progress(stage.name, len(tasks), progress_enabled(self.json_mode) and not beside)
        if self.records is not None:  # read-through: the items this store lacks, in one batch
            self.records.prefetch([t.key for t in tasks])
        # cached items are resolved here without a round trip through a worker process
        todo = []
        for t in tasks:
            rec = self.store.get_record(t.key)
            if rec is not None:
                outputs[t.index] = rec["outputs"]
                objects.update(rec["objects"])
                rep.cached += 1
                prog.update()
            else:
                todo.append(t)
        run_exec = executor if beside or len(todo) >= max(2, getattr(executor, "min_items", 2)) else InProcessExecutor()
        try:
            for res in run_exec.run(self._with_inputs(todo)):
                outputs[res.index] = res.output
                objects.update(res.objects)
                if res.computed:
                    rep.executed += 1
                else:
                    rep.cached += 1
                prog.update()
        finally:
            prog.close()
            if run_exec is not executor:
                SHARED.begin(None)  # what items computed here kept of their shared inputs
        enc = Encoder(self.store)
        summary_tree = enc.tree(summary) if summary is not None else None
        if summary_tree is not None and stage.summary_kind:
            validate(stage.summary_kind, summary_tree)
        out = enc.manifest(f"map:{stage.kind}", None, items=outputs, summary=summary_tree)
        # the stage record names its items' objects too: one lookup tells whether all are there
        rec = {"record_kind": "stage", "stage": stage.name, "key": key, "outputs": out,
               "objects": {**objects, **enc.objects}, "children": item_keys, "fields": _jsonable_fields(f),
               "preimage": self._preimage("stage", stage, f), "seconds": round(time.perf_counter() - t0, 6)}
        self.store.sync()
        self.store.put_record(key, rec)
        self._outputs[stage.name] = out
        self._items[stage.name] = list(outputs)  # type: ignore[arg-type]

    # Read-through runs: the objects of a task's inputs are fetched here, in the runner, before
    # the task is dispatched (a chunk of tasks per round trip), not by the workers. Workers
    # (process pool, Dask, even the in-process executor) open the store by path: giving each the
    # store's fallback would mean a remote connection and credentials per worker (and per Dask
    # host), and refusals warned about from many processes, out of reach of the run's
    # self-healing pass. The runner knows what a task reads (its references are manifest
    # digests and manifest sub-trees), and what it writes lands in the store the workers read.
    def _with_inputs(self, tasks: list[ItemTask]) -> Iterator[ItemTask]:
        if self.store.fallback is None:
            yield from tasks
            return
        for i in range(0, len(tasks), INPUT_CHUNK):
            chunk = tasks[i:i + INPUT_CHUNK]
            refs = _flat_refs([r for t in chunk for r in t.refs.values()])
            self.store.ensure(r.digest for r in refs if r.how == "artifact")  # the manifests first
            leaves: list[str] = []
            for r in refs:
                if r.how == "artifact":
                    leaves += leaf_digests(load_manifest(self.store, r.digest)["value"])
                elif r.how == "tree":
                    leaves += leaf_digests(r.payload)
            self.store.ensure(leaves)
            yield from chunk

    # ---------------------------------------------------------------- records

    def stage_summary(self) -> dict[str, Any]:
        """What a run dir and the cache's run list remember of this run."""
        return {name: {"key": r.key, "output": r.output, "fields": _jsonable_fields(r.fields or {})}
                for name, r in self.reports.items()}


INPUT_CHUNK = 32  # map tasks whose input objects a read-through run fetches in one batch


class _Beside:
    """Map stages run beside a whole stage. A whole stage runs in the run's process, on one core
    (unless it spreads calls with ``ctx.map``), while the workers wait; a later map stage whose
    inputs are all there already (it cannot depend on the whole stage) is started on a thread
    of the run that hands its items to the same workers, and the loop takes its report when it
    reaches it. Outputs are those of running the stages one after another: an item's result
    does not depend on where or when it ran, and each stage is still keyed, written and
    recorded by itself (records last)."""

    def __init__(self, runner: Runner, executor: Any):
        from concurrent.futures import ThreadPoolExecutor

        self.runner, self.executor = runner, executor
        self._threads = ThreadPoolExecutor(max_workers=1, thread_name_prefix="beside")
        self._running: dict[str, Any] = {}
        self.started: list[str] = []  # stage names, in the order they were started beside

    def start(self, later: list[Stage]) -> None:
        for st in later:
            if (st.is_map and st.name not in self._running and st.name not in self.runner._outputs
                    and all(d in self.runner._outputs for d in st.deps)):
                self._running[st.name] = self._threads.submit(self.runner._run_stage, st, self.executor, True)
                self.started.append(st.name)

    def take(self, name: str) -> StageReport | None:
        """The report of stage ``name`` if it was started beside (waits for it), else None."""
        fut = self._running.pop(name, None)
        return None if fut is None else fut.result()

    def close(self) -> None:
        """Wait for what is still running (after an error: its items were cancelled with the
        executor, or run to their end on a shared one), its errors dropped: the run's own error
        is the one reported."""
        for fut in self._running.values():
            with contextlib.suppress(BaseException):
                fut.result()
        self._running.clear()
        self._threads.shutdown(wait=True)


def _flat_refs(refs: list[ResolvedRef]) -> list[ResolvedRef]:
    """``refs`` with lists of references expanded."""
    out: list[ResolvedRef] = []
    for r in refs:
        out.extend(_flat_refs(r.payload) if r.how == "list" else [r])
    return out


def _jsonable_fields(f: dict[str, Any]) -> dict[str, Any]:
    import json

    return json.loads(json.dumps(f, default=str))


def _flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(d, dict):
        return {prefix: d}
    out: dict[str, Any] = {}
    for k, v in d.items():
        name = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, dict):
            out.update(_flatten(v, name))
        else:
            out[name] = v
    return out


def diff_fields(old: dict[str, Any], new: dict[str, Any], stage: str | None = None) -> list[str]:
    """Human-readable, field-by-field differences between two sets of key fields."""
    new = _jsonable_fields(new)
    reasons = []
    section = stage + "." if stage else ""
    po, pn = _flatten(old.get("params") or {}), _flatten(new.get("params") or {})
    for k in sorted(set(po) | set(pn)):
        if po.get(k, "<unset>") != pn.get(k, "<unset>"):
            reasons.append(f"param {section}{k} changed: {po.get(k, '<unset>')!r} -> {pn.get(k, '<unset>')!r}")
    if old.get("seed") != new.get("seed"):
        reasons.append(f"seed changed: {old.get('seed')!r} -> {new.get('seed')!r}")
    if old.get("version") != new.get("version"):
        reasons.append(f"stage version changed: {old.get('version')} -> {new.get('version')}")
    co, cn = old.get("code_files") or {}, new.get("code_files") or {}
    for k in sorted(set(co) | set(cn)):
        if k not in co:
            reasons.append(f"code added: {k}")
        elif k not in cn:
            reasons.append(f"code removed: {k}")
        elif co[k] != cn[k]:
            reasons.append(f"code changed: {k}")
    io_, in_ = old.get("inputs") or {}, new.get("inputs") or {}
    for k in sorted(set(io_) | set(in_)):
        if io_.get(k) != in_.get(k):
            a, b = io_.get(k), in_.get(k)
            reasons.append(f"input {k} changed: {str(a)[:12]} -> {str(b)[:12] if b else '(will be recomputed)'}")
    eo, en = old.get("env") or {}, new.get("env") or {}
    for k in sorted(set(eo) | set(en)):
        if eo.get(k) != en.get(k):
            reasons.append(f"env {k} changed: {eo.get(k)!r} -> {en.get(k)!r}")
    return reasons
