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


def make_toy_input(folder: Path, n: int = 40, size: int = 2000, seed: int = 0) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for i in range(n):
        (folder / f"{i:05d}.bin").write_bytes(rng.integers(0, 256, size, dtype=np.uint8).tobytes())
    return folder


@pytest.fixture
def toy_input(tmp_path: Path) -> Path:
    return make_toy_input(tmp_path / "input")


def cli(*args: str, check: bool = False, timeout: float = 600, env: dict | None = None):
    """Run `python -m gcvd_flow ARGS`; returns the CompletedProcess (text mode)."""
    e = dict(os.environ)
    e.setdefault("OMP_NUM_THREADS", "1")
    if env:
        e.update(env)
    p = subprocess.run([sys.executable, "-m", "gcvd_flow", *args], capture_output=True, text=True,
                       timeout=timeout, cwd=ROOT, env=e)
    if check and p.returncode != 0:
        raise AssertionError(f"gcvd-flow {' '.join(args)} failed ({p.returncode}):\n{p.stderr}")
    return p


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
