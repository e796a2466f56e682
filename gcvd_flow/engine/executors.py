"""Where map items are computed: in this process, or in a pool of worker processes.

An item task carries only digests, JSON sub-trees and picklable loaders, never arrays: each
worker loads its inputs from the store and writes its outputs to the store itself, so the
parent does not ship megabytes through pipes. Every task takes the item's OS lock and
re-checks the record first, which is what makes two concurrent runs compute each item once.

The worker processes a run starts end with it, however it ends (docs/design.md, "The process
tree of a run"): pool workers watch the run through a pipe and exit at its EOF, Dask workers
are watched the same way by distributed; workers never act on Ctrl-C (the run ends them), and
what they put in the temp dir lives in a directory of the run that a janitor process removes
when the run has ended.
"""

from __future__ import annotations

import contextlib
import itertools
import multiprocessing
import multiprocessing.connection
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections import deque
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator

import numpy as np

from gcvd_flow.engine.artifacts import Encoder, decode_tree, load_value
from gcvd_flow.engine.errors import WorkerError
from gcvd_flow.engine.names import ENV_JOBS, TOOL
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
    share_scope: str | None = None  # the stage's key when its items share inputs (MapStage.share_inputs)


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
    """The ``ctx`` a map item sees: its stage name, the seed, a logger, its resources and the
    digests of its inputs."""

    def __init__(self, stage: str, seed: int, index: int, params: Any = None,
                 resources: dict[str, Callable[[Any], Any]] | None = None, resource_key: str = "",
                 refs: dict[str, ResolvedRef] | None = None):
        self.stage = stage
        self.seed = seed
        self.index = index
        self.checkpointer = None
        self._params, self._resources, self._resource_key = params, resources or {}, resource_key
        self._refs = refs or {}

    def input_digest(self, name: str) -> Any:
        """The content digest of input ``name`` (a list of them for a list of references): two
        inputs with the same digest are the same value, so a stage can key what it derives from
        an input on it instead of hashing the value again (None: not known)."""
        r = self._refs.get(name)
        return None if r is None else _digests(r)

    def log(self, msg: str) -> None:
        import sys

        print(f"{self.stage}[{self.index}]: {msg}", file=sys.stderr)

    def resource(self, name: str) -> Any:
        return open_resource(self.stage, name, self._resources.get(name), self._params, self._resource_key)


def _digests(r: ResolvedRef) -> Any:
    return [_digests(x) for x in r.payload] if r.how == "list" else r.digest


# What a worker keeps of the inputs of a ``share_inputs`` stage (MapStage.share_inputs), at most
# this many bytes of arrays: a window of frames (depth_consensus: +-64 frames of depth,
# confidence and masks, ~60 MB at 256x192) fits at 4x that resolution.
SHARED_INPUTS_BYTES = 256 << 20


class SharedInputs:
    """The inputs this process loaded for the items of one ``share_inputs`` stage, by digest: an
    input that many items read (a window's frames) is read from the store, verified and decoded
    once per worker, and every item gets the same arrays, made read only (an item that wrote
    into one would change what the next item reads: it raises instead). Dicts and lists are
    fresh per item. Least recently used values go first beyond ``budget`` bytes; everything goes
    when a task of another stage (or run) arrives (``begin``). ``loads``: values read from the
    store, ``hits``: values served again."""

    def __init__(self, budget: int = SHARED_INPUTS_BYTES):
        from collections import OrderedDict

        self.budget = budget
        self.scope: tuple[str, str] | None = None
        self._values: OrderedDict[tuple[str, str], tuple[Any, int]] = OrderedDict()
        self.bytes = self.loads = self.hits = 0

    def begin(self, scope: tuple[str, str] | None) -> None:
        if scope != self.scope:
            self._values.clear()
            self.scope, self.bytes = scope, 0

    def load(self, ref: ResolvedRef, store: Store) -> Any:
        if ref.how == "list":
            return [self.load(r, store) for r in ref.payload]
        if ref.how == "const":
            return ref.payload
        k = (ref.how, ref.digest)
        got = self._values.get(k)
        if got is not None:
            self._values.move_to_end(k)
            self.hits += 1
            return _fresh_containers(got[0])
        value = _read_only(ref.load(store))
        self.loads += 1
        n = _nbytes(value)
        if n <= self.budget:
            self._values[k] = (value, n)
            self.bytes += n
            while self.bytes > self.budget:
                self.bytes -= self._values.popitem(last=False)[1][1]
        return _fresh_containers(value)


def _read_only(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        v.flags.writeable = False
    elif isinstance(v, dict):
        for x in v.values():
            _read_only(x)
    elif isinstance(v, list):
        for x in v:
            _read_only(x)
    return v


def _fresh_containers(v: Any) -> Any:
    if isinstance(v, dict):
        return {k: _fresh_containers(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_fresh_containers(x) for x in v]
    return v


def _nbytes(v: Any) -> int:
    if isinstance(v, np.ndarray):
        return int(v.nbytes)
    if isinstance(v, dict):
        return 64 + sum(_nbytes(x) for x in v.values())
    if isinstance(v, list):
        return 64 + sum(_nbytes(x) for x in v)
    return 32


SHARED = SharedInputs()  # this process's (a pool worker's, or the run's for in-process items)


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
                SHARED.begin(None if task.share_scope is None else (task.store_root, task.share_scope))
                inputs = {name: r.load(store) if task.share_scope is None else SHARED.load(r, store)
                          for name, r in task.refs.items()}
                ctx = ItemContext(task.stage_name, task.seed, task.index, task.params, task.resources,
                                  task.resource_key, task.refs)
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


JOBS_ENV = ENV_JOBS


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity, e.g. a container's cpuset)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # not Linux
        return max(1, os.cpu_count() or 1)


def parse_jobs(text: str, where: str = "--jobs") -> int:
    """A jobs setting: a positive integer, or ``auto`` (0: one worker per usable core)."""
    from gcvd_flow.engine.errors import UsageError

    t = str(text).strip().lower()
    if t == "auto":
        return 0
    try:
        n = int(t)
    except ValueError:
        n = -1
    if n < 1:
        raise UsageError(f"{where}: expected a positive integer or 'auto', got {text!r}")
    return n


def resolve_jobs(jobs: int | None) -> int:
    """Worker processes for map items: ``jobs`` if >= 1, else ``$GCVD_FLOW_JOBS`` if set, else
    one per usable core. Results do not depend on it (items are pure; each worker's numeric
    libraries run single-threaded, and the item results were checked bit-identical to
    in-process ones), only the wall time does."""
    if jobs is not None and jobs >= 1:
        return int(jobs)
    env = os.environ.get(JOBS_ENV, "").strip()
    return (parse_jobs(env, f"${JOBS_ENV}") if env else 0) or usable_cores()


# A whole stage's ``ctx.map`` with fewer calls than this runs them in the calling process:
# starting workers costs more than two calls save.
MIN_CALLS = 3


def _map_calls(fn: Callable[[Any], Any], args: Iterable[Any], submit: Callable[[Any], Any], jobs: int,
               wait_any: Callable[[list[Any]], None] | None = None) -> Iterator[Any]:
    """``fn(arg)`` for each argument through ``submit`` (see ``_ordered``), or here when there
    are fewer than MIN_CALLS arguments (only that many are looked at to decide)."""
    it = iter(args)
    head = list(itertools.islice(it, MIN_CALLS))
    if len(head) < MIN_CALLS:
        return map(fn, head)
    return _ordered(submit, itertools.chain(head, it), jobs, wait_any or _wait_any)


class InProcessExecutor:
    jobs = 1
    min_items = 1

    def run(self, tasks: Iterable[ItemTask]) -> Iterator[ItemResult]:
        for t in tasks:
            yield compute_item(t)

    def map_calls(self, fn: Callable[[Any], Any], args: Iterable[Any]) -> Iterator[Any]:
        return map(fn, args)

    def close(self, abort: bool = False) -> None:
        pass


def _wait_first(futures: Iterable[Future]) -> tuple[set[Future], set[Future]]:
    """``wait(futures, return_when=FIRST_COMPLETED)`` that also returns when a future was
    cancelled by ``shutdown(cancel_futures=True)``: such a cancel does not wake ``wait`` (CPython
    notifies waiters only from ``set_running_or_notify_cancel``), so a stage running beside a
    failed one waited forever for its cancelled items (a hang seen in tests/test_overlap.py)."""
    pending = set(futures)
    while True:
        done, pending = wait(pending, timeout=1.0, return_when=FIRST_COMPLETED)
        cancelled = {f for f in pending if f.cancelled()}
        if done or cancelled:
            return done | cancelled, pending - cancelled


def _wait_any(futures: list[Future]) -> None:
    _wait_first(futures)


def _ordered(submit: Callable[[Any], Any], args: Iterator[Any], jobs: int,
             wait_any: Callable[[list[Any]], None] = _wait_any) -> Iterator[Any]:
    """Results of ``submit(arg)`` in argument order, with at most ``jobs + 1`` calls unfinished
    (one queued, so that a worker that finishes starts the next call at once rather than wait
    for the caller to build its argument) and ``2 * jobs + 1`` unreturned: an argument is only
    built when it is submitted (a stage's window jobs hold megabytes), and finished results
    wait for the earlier ones to be taken."""
    pending: deque[Any] = deque()  # futures, in argument order
    exhausted = False
    try:
        while True:
            while not exhausted and len(pending) <= 2 * jobs and sum(not f.done() for f in pending) <= jobs:
                try:
                    pending.append(submit(next(args)))
                except StopIteration:
                    exhausted = True
            if not pending:
                return
            if pending[0].done():
                yield pending.popleft().result()
            else:
                wait_any([f for f in pending if not f.done()])
    finally:
        for f in pending:
            f.cancel()


# ------------------------------------------------------------------------------ process lifetime
#
# The worker processes of a run end with it however it ends, kill -9 and the OOM killer
# included, so none of this relies on the run's own clean-up (docs/design.md, "The process tree
# of a run"):
# - a pool worker watches the run through the pipe multiprocessing keeps between them (only the
#   run holds its write end: EOF once the run has ended) and exits at once;
# - the forkserver exits when its "alive" pipe, held by the run and the pool workers, reaches
#   EOF; the resource tracker when its pipe (the same holders and the forkserver) does, and
#   it then unlinks the semaphores the run left in /dev/shm;
# - Dask workers of a local cluster are watched the same way by distributed (their nannies
#   live in the run process);
# - a janitor removes the run's temp dir (the forkserver's socket, the Dask scratch space) once
#   the run has ended.
# Workers never act on Ctrl-C, which the terminal sends to the whole process group (they
# printed tracebacks): the run ends them (``close(abort=True)``).

_JANITOR = """
import os, shutil, signal, sys, time
for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
    signal.signal(s, signal.SIG_IGN)
while os.read(0, 4096):
    pass
for delay in (0.0, 0.5, 1.0):  # again: a worker that was still ending may have written into it
    time.sleep(delay)
    shutil.rmtree(sys.argv[1], ignore_errors=True)
"""
_RUN_TMP: str | None = None
_JANITOR_PROC: subprocess.Popen | None = None


def run_temp_dir() -> str:
    """A temp directory of this process (the run), removed once the process has ended, however
    it ended: a janitor (a bare python, in a session of its own so that signals to the run's
    process group pass it by) reads a pipe whose only write end this process holds and removes
    the directory at its EOF. Created on first use; the same path for the process's lifetime."""
    global _RUN_TMP, _JANITOR_PROC
    if _RUN_TMP is None or _JANITOR_PROC is None or _JANITOR_PROC.poll() is not None:
        path = tempfile.mkdtemp(prefix=f"{TOOL}-")  # short: the forkserver's socket goes in it
        _JANITOR_PROC = subprocess.Popen([sys.executable, "-I", "-S", "-c", _JANITOR, path], stdin=subprocess.PIPE,
                                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        _RUN_TMP = path
    return _RUN_TMP


@contextlib.contextmanager
def _ctrl_c_blocked() -> Iterator[None]:
    """Processes started inside begin with SIGINT blocked, which they keep through fork and
    exec; a Ctrl-C meanwhile reaches this process when the block ends. (Python handles signals
    in the main thread only.)"""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _start_forkserver(tmp: str) -> None:
    """Start the forkserver now, from this thread, with SIGINT blocked (its children, the pool
    workers, inherit that) and its socket in the run's temp dir ``tmp``; by default it starts
    on the first submit, from whichever thread submits."""
    from multiprocessing import forkserver, resource_tracker

    resource_tracker.ensure_running()  # first: starting it would unblock SIGINT (it blocks and unblocks it)
    old = tempfile.tempdir
    # where multiprocessing makes this process's socket, TMP/pymp-XXXXXXXX/listener-XXXXXXXX, if
    # that fits a socket address (108 bytes); else in its usual place (left there after kill -9)
    if len(os.fsencode(tmp)) + 34 < 108:
        tempfile.tempdir = tmp
    # workers run one BLAS / OpenMP thread each (``_worker_init``), which OpenBLAS reads when
    # numpy loads: in the forkserver's environment, before a worker imports anything
    omp = os.environ.get("OMP_NUM_THREADS")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    try:
        with _ctrl_c_blocked():
            forkserver.ensure_running()
    finally:
        tempfile.tempdir = old
        if omp is None:
            del os.environ["OMP_NUM_THREADS"]


def _exit_with_the_run() -> None:
    """In a pool worker: a thread that waits for EOF on the pipe from the run (the parent
    sentinel multiprocessing gives every child) and ends this process then, mid-item or idle.
    An item cut short leaves nothing under a final name (the store renames complete files)."""
    parent = multiprocessing.parent_process()
    if parent is None or parent.sentinel is None:
        return
    sentinel = parent.sentinel

    def watch() -> None:
        multiprocessing.connection.wait([sentinel])
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-the-run", daemon=True).start()


def _pool_worker_init(pipeline_init: Callable[[], None] | None) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole process group: the run ends us
    _exit_with_the_run()
    _worker_init(pipeline_init)


def _lost_workers(it: Iterator[Any], lost: tuple[type[BaseException], ...],
                  message: Callable[[BaseException], str]) -> Iterator[Any]:
    """``it``, with a failure that means the workers were lost (a type in ``lost``) raised as a
    one-line WorkerError (exit 2) instead of the executor's traceback."""
    try:
        yield from it
    except lost as exc:
        raise WorkerError(message(exc)) from None


_RESUME = "the cache is consistent: finished items are kept, run again to resume"


@contextlib.contextmanager
def closing(executor: Any) -> Iterator[Any]:
    """Close ``executor`` when the block is left: after its running items have finished, or at
    once, its workers ended, when an interrupt (Ctrl-C, SIGTERM, SIGHUP: a KeyboardInterrupt)
    or SystemExit leaves the block."""
    try:
        yield executor
    except BaseException as exc:
        executor.close(abort=not isinstance(exc, Exception))
        raise
    executor.close()


def _worker_init(pipeline_init: Callable[[], None] | None) -> None:
    # Workers share the machine's cores: one BLAS / OpenMP thread each; the pipeline pins the
    # thread pools of the libraries its stages use (it knows them, the engine does not).
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    if pipeline_init is not None:
        pipeline_init()


class ProcessPoolItemExecutor:
    """Items in parallel worker processes (``--jobs N``); results in completion order.

    A stage with fewer than ``min_items`` items to compute runs them in the calling process:
    starting the workers (each imports the pipeline's numeric libraries, ~1-2 s) costs more than
    a handful of items saves. Workers start on the first stage that needs them and serve the
    rest of the run."""

    min_items = 8

    def __init__(self, jobs: int, worker_init: Callable[[], None] | None = None):
        self.jobs = max(1, jobs)
        # forkserver: a clean, thread-free parent for workers (fork after numeric libraries
        # created threads can deadlock).
        ctx = multiprocessing.get_context("forkserver")
        _start_forkserver(run_temp_dir())
        self._pool = ProcessPoolExecutor(max_workers=self.jobs, mp_context=ctx,
                                         initializer=_pool_worker_init, initargs=(worker_init,))

    def run(self, tasks: Iterable[ItemTask]) -> Iterator[ItemResult]:
        return _lost_workers(self._run(tasks), (BrokenProcessPool,), _pool_lost)

    def _run(self, tasks: Iterable[ItemTask]) -> Iterator[ItemResult]:
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
            done, pending = _wait_first(pending)
            for f in done:
                yield f.result()

    def map_calls(self, fn: Callable[[Any], Any], args: Iterable[Any]) -> Iterator[Any]:
        """``fn(arg)`` for each argument on the workers, in argument order (see ``_ordered``);
        fewer than MIN_CALLS calls run here."""
        return _lost_workers(_map_calls(fn, args, lambda a: self._pool.submit(fn, a), self.jobs),
                             (BrokenProcessPool,), _pool_lost)

    def close(self, abort: bool = False) -> None:
        """Wait for the running items (queued ones are cancelled); ``abort``: end the workers
        now instead (an interrupt: their items are recomputed by the next run)."""
        if abort:
            # the pool keeps its worker processes in ``_processes`` (CPython, since 3.2)
            for p in list((getattr(self._pool, "_processes", None) or {}).values()):
                with contextlib.suppress(Exception):
                    p.kill()
        self._pool.shutdown(wait=True, cancel_futures=True)


def _pool_lost(exc: BaseException) -> str:
    return f"a worker process ended unexpectedly (killed, out of memory?); {_RESUME}"


_DASK_INIT_DONE = False


def compute_item_on_dask_worker(task: ItemTask, worker_init: Callable[[], None] | None = None) -> ItemResult:
    """A map item as a Dask task. The worker reads the item's inputs from the store and writes
    its outputs to the store itself (``task.store_root`` must be the same path on every worker:
    a shared file system); only the task (digests, loaders) and the result (digests) travel.

    Two workers given the same item (Dask retries a task whose worker died; two runs or two
    clusters share the cache) still compute it once: ``compute_item`` takes the item's OS lock
    (flock on ``locks/``) and re-checks the record under it, exactly as for two local processes.
    The lock must therefore be honoured across the machines of the cluster: it is on one machine
    and on NFSv4 / CephFS / Lustre (which implement flock across clients); on a file system
    that ignores flock, concurrent duplicates are still harmless (same key, same bytes, records
    and objects replaced atomically), they only cost the duplicate work."""
    global _DASK_INIT_DONE
    if not _DASK_INIT_DONE:
        _worker_init(worker_init)
        _DASK_INIT_DONE = True
    return compute_item(task)


class DaskItemExecutor:
    """Items as Dask tasks: on the cluster at ``scheduler`` (``tcp://host:port``), else on a
    ``distributed.LocalCluster`` of ``jobs`` worker processes with one thread each. Results come
    in completion order; at most ``4 x workers`` tasks are in flight (the client holds only
    digests, but a million-item stage need not be submitted at once)."""

    def __init__(self, jobs: int, worker_init: Callable[[], None] | None = None, scheduler: str | None = None):
        import logging

        import dask
        from distributed import Client, LocalCluster

        self.worker_init = worker_init
        self._cluster = None
        # distributed logs what it retries and what it gives up on, tracebacks included, through
        # the handlers of its logger: the run reports lost workers or scheduler as one line
        for handler in logging.getLogger("distributed").handlers:
            handler.setLevel(logging.CRITICAL)
        if scheduler:
            try:
                self._client = Client(scheduler, timeout="15s")
            except (OSError, ValueError, TypeError) as exc:
                from gcvd_flow.engine.errors import UsageError

                why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                raise UsageError(f"cannot reach the Dask scheduler at {scheduler}: {why}") from None
        else:
            from distributed.deploy.spec import SpecCluster

            before = set(SpecCluster._instances)
            try:
                # the cluster's scratch space in the run's temp dir; its workers forked by the run's
                # forkserver, which was started with Ctrl-C blocked: they inherit that, from birth
                # (and so do workers the nannies restart later: the setting stays for the process)
                tmp = run_temp_dir()
                _start_forkserver(tmp)
                dask.config.set({"distributed.worker.multiprocessing-method": "forkserver"})
                import distributed.utils as dask_utils

                if getattr(dask_utils, "_forkserver_preload_set", None) is False:
                    # distributed would import its list of packages into this process to preload
                    # them in a new forkserver; ours is running already (~1 s for nothing)
                    dask_utils._forkserver_preload_set = True
                with dask.config.set({"temporary-directory": tmp}):  # the scheduler's scratch space
                    self._cluster = LocalCluster(n_workers=max(1, jobs), threads_per_worker=1, processes=True,
                                                 worker_class=_nanny_keeping_environ(),
                                                 dashboard_address=None, silence_logs=logging.CRITICAL,
                                                 env={"OMP_NUM_THREADS": "1"}, local_directory=tmp,
                                                 # its HTTP routes (no dashboard) on a free port: on
                                                 # 8787, taken, it warned on stderr
                                                 scheduler_kwargs={"dashboard_address": "127.0.0.1:0"})
                self._client = Client(self._cluster)
            except BaseException:  # e.g. Ctrl-C while the workers start: no half-made cluster at exit
                for c in set(SpecCluster._instances) - before:
                    c.shutdown_on_close = False
                raise
        self.jobs = max(1, len(self._client.scheduler_info().get("workers", {})) or jobs)

    def run(self, tasks: Iterable[ItemTask]) -> Iterator[ItemResult]:
        return _lost_workers(self._run(tasks), _dask_lost_types(), _dask_lost)

    def _run(self, tasks: Iterable[ItemTask]) -> Iterator[ItemResult]:
        from distributed import as_completed

        it = iter(tasks)
        limit = 4 * self.jobs
        first = []
        for t in it:
            first.append(self._submit(t))
            if len(first) >= limit:
                break
        if not first:
            return
        ac = as_completed(first)
        for fut in ac:
            res = fut.result()  # a task that failed raises here, as in the process pool
            fut.release()
            nxt = next(it, None)
            if nxt is not None:
                ac.add(self._submit(nxt))
            yield res

    def map_calls(self, fn: Callable[[Any], Any], args: Iterable[Any]) -> Iterator[Any]:
        """``fn(arg)`` for each argument as Dask tasks, in argument order; the arguments travel to
        the workers (they are a stage's own inputs, not store digests)."""
        from distributed import wait as dask_wait

        return _lost_workers(_map_calls(fn, args, lambda a: self._client.submit(fn, a, pure=False, retries=2),
                                        self.jobs, lambda fs: dask_wait(fs, return_when="FIRST_COMPLETED")),
                             _dask_lost_types(), _dask_lost)

    def _submit(self, task: ItemTask):
        # A unique task key per submission: the item's lock and record re-check decide whether
        # work happens and who reports it computed (two clients sharing a cluster and a cache see
        # each item computed once in total), not Dask's deduplication of equal keys.
        # retries: a task whose worker died (killed, OOM) is retried on another worker.
        return self._client.submit(compute_item_on_dask_worker, task, self.worker_init, pure=False, retries=2,
                                   key=f"{task.stage_name}-{task.index}-{task.key[:16]}-{uuid.uuid4().hex[:8]}")

    def close(self, abort: bool = False) -> None:
        try:
            self._client.close()
        except Exception:  # noqa: BLE001 - closing after Ctrl-C or a lost scheduler
            pass
        if self._cluster is not None:
            try:
                self._cluster.close()
            except Exception:  # noqa: BLE001 - workers already gone (Ctrl-C reaches them too):
                self._cluster.shutdown_on_close = False  # no second attempt (and traceback) at exit


def _nanny_keeping_environ() -> type:
    """distributed's ``Nanny`` that leaves this process's environment alone. A nanny sets its
    pre-spawn variables (OMP_ / MKL_ / OPENBLAS_NUM_THREADS, MALLOC_TRIM_THRESHOLD_ and
    PYTHONHASHSEED) in the calling process before it starts a worker, at the cluster's start and
    at every restart, and never takes them back: a library user's later subprocesses and torch
    would inherit them. Our workers are forked by the run's forkserver, started before the
    cluster, so the caller's environment never reached them anyway; each worker still gets the
    variables, as the nanny applies its ``env`` (which holds them) in the worker itself."""
    from distributed import Nanny

    class NannyKeepingEnviron(Nanny):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.pre_spawn_env = {}

    return NannyKeepingEnviron


def _dask_lost_types() -> tuple[type[BaseException], ...]:
    from concurrent.futures import CancelledError

    from distributed import KilledWorker
    from distributed.comm.core import CommClosedError

    return (KilledWorker, CancelledError, CommClosedError)


def _dask_lost(exc: BaseException) -> str:
    from distributed import KilledWorker

    if isinstance(exc, KilledWorker):
        n = exc.allowed_failures + 1
        what = "item {1} of stage {0}".format(*str(exc.task).split("-")) if str(exc.task).count("-") == 3 else \
            f"task {exc.task}"  # an item's task key is stage-index-key-nonce (``_submit``)
        return f"Dask workers died computing {what} ({n} time{'s' if n > 1 else ''}: killed, out of memory?); {_RESUME}"
    if isinstance(exc, OSError):
        return f"lost the connection to the Dask scheduler ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__}); {_RESUME}"
    why = getattr(exc, "reason", None) or (str(exc).splitlines()[0] if str(exc) else "no reason given")
    return f"the Dask scheduler cancelled the run's tasks ({why}; was the scheduler stopped?); {_RESUME}"


def make_executor(jobs: int, worker_init: Callable[[], None] | None = None, kind: str = "process",
                  scheduler: str | None = None):
    """``process``: in this process (jobs == 1) or a local process pool; ``dask``: a Dask cluster.
    ``jobs`` 0 (``auto``): see :func:`resolve_jobs`."""
    jobs = resolve_jobs(jobs)
    if kind == "dask":
        return DaskItemExecutor(jobs, worker_init, scheduler)
    if scheduler:
        from gcvd_flow.engine.errors import UsageError

        raise UsageError("--scheduler needs --executor dask")
    return InProcessExecutor() if jobs <= 1 else ProcessPoolItemExecutor(jobs, worker_init)
