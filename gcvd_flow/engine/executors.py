"""Where map items are computed: in this process, or in a pool of worker processes.

An item task carries only digests, JSON sub-trees and picklable loaders, never arrays: each
worker loads its inputs from the store and writes its outputs to the store itself, so the
parent does not ship megabytes through pipes. Every task takes the item's OS lock and
re-checks the record first, which is what makes two concurrent runs compute each item once.
"""

from __future__ import annotations

import multiprocessing
import os
import time
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator

from gcvd_flow.engine.artifacts import Encoder, decode_tree, load_value
from gcvd_flow.engine.store import Store


@dataclass
class ResolvedRef:
    """An item input: ``how`` is 'artifact' (a manifest digest), 'tree' (a JSON sub-tree of
    another artifact, decoded on load), 'const' (the payload itself), 'external'
    (``loader()`` gives the value) or 'list' (a list of resolved refs, loaded in order)."""

    how: str
    digest: str
    payload: Any = None

    def load(self, store: Store) -> Any:
        if self.how == "artifact":
            return load_value(store, self.digest)
        if self.how == "tree":
            return decode_tree(store, self.payload)
        if self.how == "const":
            return self.payload
        if self.how == "list":
            return [r.load(store) for r in self.payload]
        return self.payload()


@dataclass
class ItemTask:
    store_root: str
    verify: bool
    stage_name: str
    fn: Callable[..., Any]
    kind: str
    key: str
    refs: dict[str, ResolvedRef]
    params: Any
    seed: int
    index: int
    resources: dict[str, Callable[[Any], Any]] | None = None
    resource_key: str = ""  # digest of the parameters the resources are opened with
    preimage: Any = None  # what ``key`` is the digest of (goes into the record)


@dataclass
class ItemResult:
    index: int
    key: str
    output: str
    objects: dict[str, int]
    computed: bool
    seconds: float


# Resources (e.g. loaded models) of this process: (stage, name, parameter digest) -> object.
# A few stay open: a run's stages use one model each, and re-opening costs seconds.
_RESOURCES: dict[tuple[str, str, str], Any] = {}
_RESOURCES_KEEP = 4


def open_resource(stage: str, name: str, opener: Callable[[Any], Any] | None, params: Any,
                  params_key: str) -> Any:
    """The resource ``name`` of ``stage`` for these parameters, opened once per process."""
    if opener is None:
        raise KeyError(f"stage {stage!r} declares no resource {name!r}")
    k = (stage, name, params_key)
    hit = _RESOURCES.pop(k, None)
    if hit is None:
        hit = opener(params)
    _RESOURCES[k] = hit  # most recently used last
    while len(_RESOURCES) > _RESOURCES_KEEP:
        _RESOURCES.pop(next(iter(_RESOURCES)))
    return hit


class ItemContext:
    """The ``ctx`` a map item sees: its stage name, the seed, a logger and its resources."""

    def __init__(self, stage: str, seed: int, index: int, params: Any = None,
                 resources: dict[str, Callable[[Any], Any]] | None = None, resource_key: str = ""):
        self.stage = stage
        self.seed = seed
        self.index = index
        self.checkpointer = None
        self._params, self._resources, self._resource_key = params, resources or {}, resource_key

    def log(self, msg: str) -> None:
        import sys

        print(f"{self.stage}[{self.index}]: {msg}", file=sys.stderr)

    def resource(self, name: str) -> Any:
        return open_resource(self.stage, name, self._resources.get(name), self._params, self._resource_key)


_STORES: dict[tuple[str, bool], Store] = {}


def _store(root: str, verify: bool) -> Store:
    s = _STORES.get((root, verify))
    if s is None:
        s = _STORES[(root, verify)] = Store(root, verify=verify)
    return s


def compute_item(task: ItemTask) -> ItemResult:
    store = _store(task.store_root, task.verify)
    t0 = time.perf_counter()
    rec = store.get_record(task.key)
    if rec is None:
        with store.lock(task.key):
            rec = store.get_record(task.key)  # another process may have finished it meanwhile
            if rec is None:
                inputs = {name: r.load(store) for name, r in task.refs.items()}
                ctx = ItemContext(task.stage_name, task.seed, task.index, task.params, task.resources,
                                  task.resource_key)
                value = task.fn(inputs, task.params, ctx)
                enc = Encoder(store)
                out = enc.manifest(task.kind, value)
                rec = {"record_kind": "item", "stage": task.stage_name, "key": task.key,
                       "outputs": out, "objects": enc.objects, "preimage": task.preimage,
                       "inputs": {n: r.digest for n, r in sorted(task.refs.items())},
                       "seconds": round(time.perf_counter() - t0, 6)}
                store.put_record(task.key, rec)
                return ItemResult(task.index, task.key, out, enc.objects, True,
                                  time.perf_counter() - t0)
    return ItemResult(task.index, task.key, rec["outputs"], rec["objects"], False,
                      time.perf_counter() - t0)


class InProcessExecutor:
    jobs = 1

    def run(self, tasks: Iterable[ItemTask]) -> Iterator[ItemResult]:
        for t in tasks:
            yield compute_item(t)

    def close(self) -> None:
        pass


def _worker_init(pipeline_init: Callable[[], None] | None) -> None:
    # Workers share the machine's cores: one BLAS / OpenMP thread each; the pipeline pins the
    # thread pools of the libraries its stages use (it knows them, the engine does not).
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    if pipeline_init is not None:
        pipeline_init()


class ProcessPoolItemExecutor:
    """Items in parallel worker processes (``--jobs N``); results in completion order."""

    def __init__(self, jobs: int, worker_init: Callable[[], None] | None = None):
        self.jobs = max(1, jobs)
        # forkserver: a clean, thread-free parent for workers (fork after numeric libraries
        # created threads can deadlock).
        ctx = multiprocessing.get_context("forkserver")
        self._pool = ProcessPoolExecutor(max_workers=self.jobs, mp_context=ctx,
                                         initializer=_worker_init, initargs=(worker_init,))

    def run(self, tasks: Iterable[ItemTask]) -> Iterator[ItemResult]:
        pending: set[Future] = set()
        it = iter(tasks)
        exhausted = False
        while True:
            while not exhausted and len(pending) < 2 * self.jobs:
                try:
                    pending.add(self._pool.submit(compute_item, next(it)))
                except StopIteration:
                    exhausted = True
            if not pending:
                return
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for f in done:
                yield f.result()

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


def make_executor(jobs: int, worker_init: Callable[[], None] | None = None):
    return InProcessExecutor() if jobs <= 1 else ProcessPoolItemExecutor(jobs, worker_init)
