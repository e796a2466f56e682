"""A run's processes end with it, however it ends (issue 31), and lost workers or a signal to
the whole process group give one line, not tracebacks (issue 32, item 8).

Each test starts `python -m gcvd_flow run` of the toy pipeline in a session of its own, with
TMPDIR pointing at a fresh directory, finds the run's descendants by walking /proc while it
runs (and the /dev/shm semaphores they map), then ends it and checks that every one of those
processes is gone within 10 s and that nothing of the run is left in the temp dir or /dev/shm.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from conftest import ROOT, cli_json, make_toy_input

from gcvd_flow.engine.store import Store

N = 24
TOY = ("--pipeline", "toy")
POOL = ("--jobs", "2")
DASK = ("--executor", "dask", "--jobs", "2")


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ref")
    inp = make_toy_input(tmp / "input", n=N)
    cli_json("run", str(inp), "--out", str(tmp / "out"), "--cache", str(tmp / "cache"), *TOY)
    return inp, _outputs(tmp / "out")


def _outputs(out: Path) -> dict[str, str]:
    return {k: v["output"] for k, v in json.loads((out / "run.json").read_text())["stages"].items()}


class Run:
    """`gcvd-flow run` in a session (and process group) of its own, signals at their defaults,
    stdout / stderr in files (a pipe would be held open by any process that outlives it)."""

    def __init__(self, tmp: Path, inp: Path, *args: str, env: dict[str, str] | None = None,
                 command: tuple[str, ...] | None = None):
        self.cache, self.out = tmp / "cache", tmp / "out"
        # a short TMPDIR: the forkserver's socket address must fit in 108 bytes (with a longer
        # one it goes to multiprocessing's usual place in TMPDIR, and stays there after kill -9)
        self.tmp = Path(tempfile.mkdtemp(prefix="gcvd-lifetime-", dir="/tmp"))
        e = dict(os.environ, TMPDIR=str(self.tmp), OMP_NUM_THREADS="1", **(env or {}))
        self.err_path = tmp / "stderr.txt"
        with open(tmp / "stdout.txt", "w") as out, open(self.err_path, "w") as err:
            self.p = subprocess.Popen([sys.executable, "-m", "gcvd_flow", *(command or ("run", str(inp))), "--out", str(self.out),
                                       "--cache", str(self.cache), *TOY, *args], cwd=ROOT, env=e, stdout=out,
                                      stderr=err, start_new_session=True, preexec_fn=_default_signals)

    def records(self) -> int:
        root = self.cache / "records"
        return sum(1 for _ in root.rglob("*.json")) if root.is_dir() else 0

    def wait_for(self, records: int, workers: int, timeout: float = 90) -> dict[int, str]:
        """Wait until the cache holds ``records`` records and the run has ``workers`` worker
        processes; returns its descendants {pid: start time}."""
        deadline = time.time() + timeout
        while time.time() < deadline:
            assert self.p.poll() is None, self.stderr()
            tree = _descendants(self.p.pid)
            if self.records() >= records and len(_workers(tree)) >= workers:
                return tree
            time.sleep(0.1)
        raise AssertionError(f"the run did not get that far in {timeout} s: {self.records()} records, "
                             f"{len(_workers(_descendants(self.p.pid)))} workers\n{self.stderr()}")

    def stderr(self) -> str:
        return self.err_path.read_text()

    def finish(self, timeout: float = 60) -> int:
        return self.p.wait(timeout=timeout)

    def close(self) -> None:
        if self.p.poll() is None:
            self.p.kill()
            self.p.wait()
        shutil.rmtree(self.tmp, ignore_errors=True)


@pytest.fixture
def runs():
    """Start runs with ``runs(tmp, inp, *args)``; they are ended and their TMPDIR removed after."""
    made: list[Run] = []

    def start(*a, **kw) -> Run:
        made.append(Run(*a, **kw))
        return made[-1]

    yield start
    for r in made:
        r.close()


def _default_signals() -> None:
    for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):  # a suite started in the background ignores some
        signal.signal(s, signal.SIG_DFL)


def _stat(pid: int) -> list[str] | None:
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return text.rsplit(")", 1)[1].split()  # fields from the state on (the name may hold spaces)


def _descendants(pid: int) -> dict[int, str]:
    """{pid: start time} of every live descendant of ``pid`` (walking /proc)."""
    children: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        st = _stat(int(d)) if d.isdigit() else None
        if st is not None:
            children.setdefault(int(st[1]), []).append(int(d))
    out: dict[int, str] = {}
    todo = [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            st = _stat(c)
            if st is not None:
                out[c] = st[19]
                todo.append(c)
    return out


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _workers(tree: dict[int, str]) -> list[int]:
    """The pool's and the local Dask cluster's worker processes: children of the forkserver
    (or started by multiprocessing's spawn)."""
    parent = {p: int((_stat(p) or [0, 0])[1]) for p in tree}
    forked = {p for p in tree if "multiprocessing.forkserver" in _cmdline(p)}  # the server and its children
    return [p for p in tree if (p in forked and parent[p] in forked) or "spawn_main" in _cmdline(p)]


def _alive(tree: dict[int, str]) -> dict[int, str]:
    """Those of ``tree`` still running (same pid and start time, not a zombie)."""
    out = {}
    for pid, start in tree.items():
        st = _stat(pid)
        if st is not None and st[19] == start and st[0] != "Z":
            out[pid] = _cmdline(pid)[:160]
    return out


def _shm(tree: dict[int, str]) -> set[str]:
    """The /dev/shm files (multiprocessing's semaphores) mapped by these processes."""
    names = set()
    for pid in tree:
        try:
            names |= {line.split()[-1] for line in Path(f"/proc/{pid}/maps").read_text().splitlines()
                      if "/dev/shm/" in line}
        except OSError:
            pass
    return names


def _all_gone(run: Run, tree: dict[int, str], shm: set[str], within: float = 10.0) -> None:
    deadline = time.time() + within
    while time.time() < deadline and (_alive(tree) or any(run.tmp.iterdir()) or any(map(os.path.exists, shm))):
        time.sleep(0.2)
    assert not _alive(tree), f"alive {within} s after the run ended: {_alive(tree)}"
    assert not list(run.tmp.iterdir()), f"left in the temp dir: {sorted(map(str, run.tmp.rglob('*')))}"
    assert not [s for s in shm if os.path.exists(s)], "semaphores left in /dev/shm"


def _one_line(err: str, needle: str) -> None:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in err, err


@pytest.mark.parametrize("executor", [POOL, DASK], ids=["process", "dask"])
def test_kill_9_of_a_run_leaves_no_process_temp_file_or_semaphore(reference, tmp_path, executor, runs):
    inp, _ = reference
    run = runs(tmp_path, inp, *executor, "--set", "transform.sleep=0.2")
    tree = run.wait_for(records=N + 1 + 2, workers=2)  # decode done, transform under way
    assert any("multiprocessing.forkserver" in _cmdline(p) for p in tree), tree
    shm = _shm(tree)
    run.p.send_signal(signal.SIGKILL)
    assert run.finish() == -signal.SIGKILL
    _all_gone(run, tree, shm)
    assert Store(run.cache).fsck().corrupt == []


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_sigterm_and_sighup_end_a_run_with_128_plus_signum_and_it_resumes(reference, tmp_path, sig, runs):
    inp, ref = reference
    run = runs(tmp_path, inp, *POOL, "--set", "transform.sleep=0.2")
    tree = run.wait_for(records=N + 1 + 2, workers=2)
    shm = _shm(tree)
    run.p.send_signal(sig)
    assert run.finish() == 128 + sig, run.stderr()
    _all_gone(run, tree, shm)
    _one_line(run.stderr(), f"interrupted by {signal.Signals(sig).name}; the cache is consistent")  # late lines too
    if sig != signal.SIGTERM:
        return  # (the resumed run is the same after either)
    # the next run resumes: what finished is cached, the rest computed; the same outputs
    doc = cli_json("run", str(inp), "--out", str(run.out), "--cache", str(run.cache), *TOY, *POOL, "--set",
                   "transform.sleep=0.2")
    st = {s["name"]: s for s in doc["stages"]}
    assert st["decode"]["cached"] == N and 0 < st["transform"]["cached"] < N
    assert _outputs(run.out) == ref


@pytest.mark.parametrize("executor", [POOL, DASK], ids=["process", "dask"])
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_to_the_process_group_gives_one_line_not_worker_tracebacks(reference, tmp_path, executor, sig, runs):
    """Ctrl-C (the terminal signals the whole foreground group) or a CI runner's SIGTERM to the
    group, while the workers wait between stages (idle workers printed KeyboardInterrupt
    tracebacks): one line, exit 128 + signum, the workers ended by the run."""
    inp, _ = reference
    run = runs(tmp_path, inp, *executor, "--set", "threshold.sleep=60", "--set", "decode.end=10")
    tree = run.wait_for(records=2 * (10 + 1) + 1, workers=2)  # decode, transform, summarize done
    time.sleep(0.5)  # into threshold's sleep
    shm = _shm(tree)
    os.killpg(run.p.pid, sig)
    assert run.finish() == 128 + sig, run.stderr()
    _all_gone(run, tree, shm)
    _one_line(run.stderr(), "interrupted")  # also nothing its processes wrote as they ended


def test_sigterm_ends_run_many_while_its_inputs_share_the_workers(reference, tmp_path, runs):
    """run-many runs the map stages of all inputs at once, on threads sharing the workers: a
    SIGTERM ends it now, not once those stages are done."""
    inp, _ = reference
    other = make_toy_input(tmp_path / "other", n=N, seed=5)
    run = runs(tmp_path, inp, *POOL, "--set", "transform.sleep=0.5", command=("run-many", str(inp), str(other)))
    tree = run.wait_for(records=2 * N + 4, workers=2)  # both decodes done, transform under way
    shm = _shm(tree)
    t0 = time.time()
    run.p.send_signal(signal.SIGTERM)
    assert run.finish() == 128 + signal.SIGTERM, run.stderr()
    assert time.time() - t0 < 5  # the remaining transform items take ~2 x 24 x 0.5 / 2 = 12 s
    _all_gone(run, tree, shm)
    _one_line(run.stderr(), "interrupted by SIGTERM")


@pytest.mark.parametrize("executor", [POOL, DASK], ids=["process", "dask"])
def test_workers_killed_again_and_again_are_one_line_and_exit_2(reference, tmp_path, executor, runs):
    """Item 3 of transform kills the worker computing it every time (as the OOM killer would):
    the process pool breaks, Dask gives up on the task (KilledWorker; at the first death here)."""
    inp, _ = reference
    run = runs(tmp_path, inp, *executor, "--set", "transform.kill_worker=3",
              env={"DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES": "0"})
    assert run.finish(timeout=120) == 2, run.stderr()
    # (Dask names the task it gave up on: item 3, or one that was on the same worker)
    needle = "a worker process ended unexpectedly" if executor == POOL else "Dask workers died computing item"
    _one_line(run.stderr(), needle)
    assert Store(run.cache).fsck().corrupt == []


def test_the_dask_scheduler_stopped_mid_run_is_one_line_and_exit_2(reference, tmp_path, runs):
    from distributed import LocalCluster

    inp, _ = reference
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        run = runs(tmp_path, inp, "--executor", "dask", "--scheduler", cluster.scheduler_address, "--set",
                  "transform.sleep=0.2")
        deadline = time.time() + 90
        while run.records() < N + 3 and time.time() < deadline and run.p.poll() is None:
            time.sleep(0.1)
        assert run.p.poll() is None, run.stderr()
    assert run.finish() == 2, run.stderr()
    # "the Dask scheduler cancelled the run's tasks", or "lost the connection to the Dask scheduler"
    _one_line(run.stderr(), "Dask scheduler")
    assert Store(run.cache).fsck().corrupt == []
