"""Shared fixtures: toy inputs, a CLI runner, and where the shared real data lives."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent

# The suite runs on 2 xdist workers: runs compute their map items in-process unless a test asks
# for workers (--jobs N, or tests/test_jobs.py, which unsets this); results do not depend on it.
os.environ.setdefault("GCVD_FLOW_JOBS", "1")
# A suite started in the background by a shell without job control (`cmd &` in a script) inherits
# SIGINT ignored, and so would every run it starts: the interrupt tests' Ctrl-C would do nothing
# (the run exits 0). A handler, unlike SIG_IGN, is reset to the default in the child at exec.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)
SHARED_DATA = ROOT.parent / "shared" / "data"

# The files whose tests run whole pipelines, heaviest first (worker seconds in the suite's
# --durations of 2026-11-29: 207, 130, 82, 75, ...). `--dist loadfile` hands the files to the two
# workers in collection order: alphabetically, test_sweep_gcvd.py (~80 s) came among the last, and
# the other worker could sit idle for as long; this way the last files handed out are short ones.
HEAVY_FIRST = ("test_calibrate.py", "test_gcvd_e2e.py", "test_report.py", "test_jobs.py", "test_hostile.py",
               "test_remote_s3.py", "test_sweep_gcvd.py", "test_compare.py", "test_remote_gcvd.py",
               "test_fusion_references.py", "test_remote_kill.py", "test_pipeline.py", "test_fuzz_inputs.py",
               "test_dask.py")


@pytest.fixture(autouse=True)
def _no_leaked_start_variables():
    """Put back the variables an interpreter reads at start (cli_fork.FRESH_ENV_PREFIXES) that a
    test changed in this process, after which every later command of this worker would go to a
    fresh interpreter (tests/test_cli_fork.py checks that they are forked). distributed's own
    nannies did this until the executor's kept them from it (test_dask checks that it does)."""
    from cli_fork import FRESH_ENV_PREFIXES

    before = {k: v for k, v in os.environ.items() if k.startswith(FRESH_ENV_PREFIXES)}
    yield
    for k in [k for k in os.environ if k.startswith(FRESH_ENV_PREFIXES) and k not in before]:
        del os.environ[k]
    os.environ.update(before)


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(HEAVY_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: each file's own order is kept


def make_toy_input(folder: Path, n: int = 40, size: int = 2000, seed: int = 0) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for i in range(n):
        (folder / f"{i:05d}.bin").write_bytes(rng.integers(0, 256, size, dtype=np.uint8).tobytes())
    return folder


@pytest.fixture
def toy_input(tmp_path: Path) -> Path:
    return make_toy_input(tmp_path / "input")


def cli(*args: str, check: bool = False, timeout: float = 600, env: dict | None = None, fresh: bool = False):
    """Run `python -m gcvd_flow ARGS`; returns the CompletedProcess (text mode). The process is
    forked from a warm parent (tests/cli_fork.py: the same command without ~5 s of imports and
    fingerprints) unless ``fresh``, GCVD_TEST_FRESH_CLI=1, or ``env`` sets a variable that is read
    when an interpreter starts."""
    e = dict(os.environ)
    e.setdefault("OMP_NUM_THREADS", "1")
    if env:
        e.update(env)
    cmd = [sys.executable, "-m", "gcvd_flow", *args]
    if fresh or _FRESH_ALWAYS or _ForkServer.differs(e):
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=ROOT, env=e)
    else:
        p = _ForkServer.run(cmd, e, timeout)
    if check and p.returncode != 0:
        raise AssertionError(f"gcvd-flow {' '.join(args)} failed ({p.returncode}):\n{p.stderr}")
    return p


# GCVD_TEST_FRESH_CLI=1: every command in a fresh interpreter (to compare, or to rule the fork server out)
_FRESH_ALWAYS = os.environ.get("GCVD_TEST_FRESH_CLI") == "1"
# the fork server's environment: the worker's at start, with cli()'s OMP_NUM_THREADS default
_SERVER_ENV = {"OMP_NUM_THREADS": "1", **os.environ}


class _ForkServer:
    """This worker's ``python tests/cli_fork.py`` (started on first use, ends with the worker)."""

    proc: subprocess.Popen | None = None
    defaults: dict[str, str] = {}  # variables the server's imports set by default (a fresh command sets them too)

    @classmethod
    def start(cls) -> subprocess.Popen:
        if cls.proc is None or cls.proc.poll() is not None:
            cls.proc = subprocess.Popen([sys.executable, str(ROOT / "tests" / "cli_fork.py")], stdin=subprocess.PIPE,
                                        stdout=subprocess.PIPE, bufsize=0, cwd=ROOT, env=_SERVER_ENV)
            assert cls.proc.stdout is not None
            cls.defaults = json.loads(cls.proc.stdout.readline())["defaults"]
        return cls.proc

    @classmethod
    def differs(cls, env: dict) -> bool:
        """Whether a command with ``env`` would start differently from the server: a variable that
        an interpreter or a numeric library reads at start has another value."""
        from cli_fork import FRESH_ENV_PREFIXES

        cls.start()
        ours, theirs = {**cls.defaults, **env}, {**cls.defaults, **_SERVER_ENV}
        return any(ours.get(k) != theirs.get(k) for k in set(ours) | set(theirs) if k.startswith(FRESH_ENV_PREFIXES))

    @classmethod
    def run(cls, cmd: list[str], env: dict, timeout: float) -> subprocess.CompletedProcess:
        proc = cls.start()
        assert proc.stdin is not None and proc.stdout is not None
        try:
            return cls._exchange(proc, cmd, env, timeout)
        except BaseException as exc:
            if not isinstance(exc, subprocess.TimeoutExpired):  # the answers are out of step: a new server
                proc.kill()
                proc.wait()
                cls.proc = None
            raise

    @staticmethod
    def _exchange(proc: subprocess.Popen, cmd: list[str], env: dict, timeout: float) -> subprocess.CompletedProcess:
        import contextlib
        import select
        import tempfile
        import time

        assert proc.stdin is not None and proc.stdout is not None
        with tempfile.TemporaryDirectory(prefix="gcvd-cli-") as tmp:
            out, err = os.path.join(tmp, "stdout"), os.path.join(tmp, "stderr")
            # the imports' defaults where the command's environment has none: a fresh interpreter's
            # imports would set them (os.environ.setdefault), the server's ran before this command
            env = {**_ForkServer.defaults, **env}
            proc.stdin.write(json.dumps({"args": cmd[3:], "env": env, "cwd": str(ROOT), "stdout": out,
                                         "stderr": err}).encode() + b"\n")
            pid = json.loads(proc.stdout.readline())["pid"]
            deadline = time.monotonic() + timeout
            try:
                while not select.select([proc.stdout], [], [], max(0.0, deadline - time.monotonic()))[0]:
                    if time.monotonic() >= deadline:
                        os.kill(pid, signal.SIGKILL)
                        json.loads(proc.stdout.readline())  # its end: the server stays in step
                        raise subprocess.TimeoutExpired(cmd, timeout)
            except BaseException as exc:  # e.g. Ctrl-C of the suite: the command does not outlive the test
                if not isinstance(exc, subprocess.TimeoutExpired):
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pid, signal.SIGKILL)
                raise
            end = json.loads(proc.stdout.readline())
            code = end["returncode"]
            return subprocess.CompletedProcess(cmd, code, _read_text(out), _read_text(err))


def _read_text(path: str) -> str:
    with open(path, encoding="utf-8", errors="replace", newline=None) as f:
        return f.read()


def cli_json(*args: str, **kw) -> dict:
    p = cli(*args, "--json", check=True, **kw)
    return json.loads(p.stdout)


def by_stage(doc: dict) -> dict[str, dict]:
    return {s["name"]: s for s in doc["stages"]}


def run_main(*args: object) -> tuple[int, str, str]:
    """The CLI in-process (fast, for fuzzing): (exit code, stdout, stderr); argparse's SystemExit
    becomes its code."""
    import contextlib
    import io

    from gcvd_flow.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main([str(a) for a in args])
        except SystemExit as exc:  # argparse
            code = int(exc.code or 0)
    return code, out.getvalue(), err.getvalue()


def json_paths(doc: object, prefix: tuple = ()) -> list[tuple]:
    """Every node path of a JSON document (dict keys, the first 4 list items), for mutating one."""
    out = [prefix]
    if isinstance(doc, dict):
        for k, v in doc.items():
            out += json_paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc[:4]):
            out += json_paths(v, prefix + (i,))
    return out
