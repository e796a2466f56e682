"""Shared fixtures: toy inputs, a CLI runner, and where the shared real data lives."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent

# The suite runs on 2 xdist workers: runs compute their map items in-process unless a test asks
# for workers (--jobs N, or tests/test_jobs.py, which unsets this); results do not depend on it.
os.environ.setdefault("GCVD_FLOW_JOBS", "1")
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
