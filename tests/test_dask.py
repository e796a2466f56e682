"""The Dask executor: map items as Dask tasks on a distributed.LocalCluster (started by the CLI,
or an existing cluster reached by --scheduler), reading inputs from and writing outputs to the
store. Same artifacts (output digests) as the in-process executor; a worker killed mid-stage
costs a retry, never a wrong or partial result."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import ROOT, by_stage, cli_json, make_toy_input

from gcvd_flow.engine.store import Store


def _outputs(out: Path) -> dict[str, str]:
    return {k: v["output"] for k, v in json.loads((out / "run.json").read_text())["stages"].items()}


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ref")
    inp = make_toy_input(tmp / "input", n=24)
    cli_json("run", str(inp), "--out", str(tmp / "out"), "--cache", str(tmp / "cache"), "--pipeline", "toy")
    return inp, _outputs(tmp / "out")


def test_local_cluster_of_two_workers_gives_the_same_outputs(reference, tmp_path):
    inp, ref = reference
    doc = cli_json("run", str(inp), "--out", str(tmp_path / "out"), "--cache", str(tmp_path / "cache"),
                   "--pipeline", "toy", "--executor", "dask", "--jobs", "2")
    st = by_stage(doc)
    assert st["decode"]["executed"] == 24 and st["transform"]["executed"] == 24
    assert _outputs(tmp_path / "out") == ref
    assert Store(tmp_path / "cache").fsck().corrupt == []


def test_two_clients_on_one_cluster_and_cache_compute_each_item_once(reference, tmp_path):
    """--scheduler: an existing cluster. Two runs at the same time share it and the cache: the
    per-item lock and record re-check on the workers make every item computed once in total."""
    from distributed import LocalCluster

    inp, ref = reference
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        procs = [subprocess.Popen([sys.executable, "-m", "gcvd_flow", "run", str(inp), "--out", str(tmp_path / f"o{i}"),
                                   "--cache", str(tmp_path / "cache"), "--pipeline", "toy", "--executor", "dask",
                                   "--scheduler", cluster.scheduler_address, "--set", "transform.sleep=0.05",
                                   "--json"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for i in range(2)]
        docs = []
        for p in procs:
            out, err = p.communicate(timeout=180)
            assert p.returncode == 0, err
            docs.append(by_stage(json.loads(out)))
    for stage in ("decode", "transform"):
        assert sum(d[stage]["executed"] for d in docs) == 24, (stage, docs)
    for i in range(2):  # transform.sleep changes keys, not values: the same output digests
        assert _outputs(tmp_path / f"o{i}") == ref


def test_a_worker_killed_mid_stage_costs_a_retry_not_a_result(reference, tmp_path):
    import psutil

    inp, ref = reference
    out, cache = tmp_path / "out", tmp_path / "cache"
    p = subprocess.Popen([sys.executable, "-m", "gcvd_flow", "run", str(inp), "--out", str(out), "--cache",
                          str(cache), "--pipeline", "toy", "--executor", "dask", "--jobs", "2", "--set",
                          "transform.sleep=0.15", "--json"], cwd=ROOT, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    killed = None
    deadline = time.time() + 60
    while time.time() < deadline and killed is None and p.poll() is None:
        time.sleep(0.2)
        records = sum(1 for _ in (cache / "records").rglob("*.json")) if (cache / "records").is_dir() else 0
        if records < 30:  # decode finished (24 items + its stage record) and transform under way
            continue
        # the workers: forked by the run's forkserver (not the forkserver itself, nor the
        # resource tracker or the janitor)
        workers = [c for c in psutil.Process(p.pid).children(recursive=True)
                   if "multiprocessing.forkserver" in " ".join(c.parent().cmdline())]
        if workers:
            killed = workers[0].pid
            workers[0].send_signal(signal.SIGKILL)
    stdout, stderr = p.communicate(timeout=120)
    assert killed is not None, "no worker process found to kill"
    assert p.returncode == 0, stderr
    doc = json.loads(stdout)
    st = by_stage(doc)
    assert st["transform"]["executed"] + st["transform"]["cached"] == 24
    assert _outputs(out) == ref  # byte-identical artifacts despite the lost worker
    assert Store(cache).fsck().corrupt == []


def test_run_many_on_one_cluster_reports_a_table_and_counts_failures(reference, tmp_path):
    from conftest import cli

    inp, ref = reference
    other = make_toy_input(tmp_path / "other", n=10, seed=3)
    (tmp_path / "broken").mkdir()  # no .bin files: this input fails, the others run
    p = cli("run-many", str(inp), str(tmp_path / "broken"), str(other), "--out", str(tmp_path / "runs"),
            "--cache", str(tmp_path / "cache"), "--pipeline", "toy", "--executor", "dask", "--jobs", "2", "--json")
    assert p.returncode == 1, p.stderr
    doc = json.loads(p.stdout)
    ok = [r for r in doc["runs"] if r["ok"]]
    assert [r["ok"] for r in doc["runs"]] == [True, False, True] and doc["failed"] == 1
    assert "no .bin files" in doc["runs"][1]["error"]
    assert ok[0]["items"] == 24 and ok[1]["items"] == 10 and ok[1]["executed"] == 2 * 10 + 3
    # the map stages (decode, transform) of both inputs ran together on the cluster, before the
    # whole stages of either: their items were interleaved on the workers
    assert ok[0]["interleaved"] == 2 * 24 and ok[1]["interleaved"] == 2 * 10
    assert _outputs(tmp_path / "runs" / "input") == ref
    # again, as a table: every stage of both inputs is a cache hit now
    p = cli("run-many", str(inp), str(other), "--out", str(tmp_path / "runs"), "--cache", str(tmp_path / "cache"),
            "--pipeline", "toy")
    assert p.returncode == 0, p.stderr
    lines = p.stdout.splitlines()
    assert lines[0].split() == ["input", "status", "items", "executed", "cache", "hits", "seconds"]
    assert lines[2].split()[:5] == ["input", "ok", "24", "0", str(2 * 24 + 3)]
    assert lines[-1].startswith("2 of 2 inputs ok, 0 failed")


def test_ctrl_c_with_dask_exits_130_cleanly_and_a_rerun_completes(reference, tmp_path):
    inp, ref = reference
    out, cache = tmp_path / "out", tmp_path / "cache"
    cmd = [sys.executable, "-m", "gcvd_flow", "run", str(inp), "--out", str(out), "--cache", str(cache), "--pipeline",
           "toy", "--executor", "dask", "--jobs", "2"]
    # SIGINT back to its default in the child (a suite started in the background inherits it ignored)
    # 24 items of 1 s on 2 workers: still running at 4 s on a fast machine (with 0.2 s a fast
    # machine had finished and was tearing the cluster down when the signal came)
    p = subprocess.Popen(cmd + ["--set", "transform.sleep=1.0"], cwd=ROOT, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    time.sleep(4.0)  # the cluster is up, items are running (or, on a slow machine, it is starting)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err, err
    assert Store(cache).fsck().corrupt == []
    cli_json("run", str(inp), "--out", str(out), "--cache", str(cache), "--pipeline", "toy", "--executor", "dask",
             "--jobs", "2")
    assert _outputs(out) == ref


def _square(x: int) -> int:
    return x * x


def test_stage_map_calls_as_dask_tasks_come_back_in_order():
    """A whole stage's ``ctx.map`` (segment windows, loop edges) on the Dask executor: each call
    a task on the cluster, results in argument order, a few calls in this process."""
    from gcvd_flow.engine.executors import MIN_CALLS, DaskItemExecutor

    ex = DaskItemExecutor(2)
    try:
        assert list(ex.map_calls(_square, iter(range(11)))) == [i * i for i in range(11)]
        assert list(ex.map_calls(_square, range(MIN_CALLS - 1))) == [i * i for i in range(MIN_CALLS - 1)]
    finally:
        ex.close()


def _worker_environ() -> dict[str, str | None]:
    import os

    return {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "PYTHONHASHSEED")}


def test_a_local_cluster_leaves_the_callers_environment_alone():
    """distributed's nannies set OMP_ / MKL_ / OPENBLAS_NUM_THREADS and PYTHONHASHSEED in the
    process that starts the cluster, at its start and at every worker restart: an API user's
    later subprocesses and torch threads would inherit them. The executor's nannies leave the
    caller's environment as it was, and the workers still get the variables."""
    import os

    from gcvd_flow.engine.executors import DaskItemExecutor

    before = dict(os.environ)
    ex = DaskItemExecutor(2)
    try:
        assert dict(os.environ) == before
        assert list(ex.map_calls(_square, iter(range(11)))) == [i * i for i in range(11)]
        ex._client.restart()  # the nannies start their workers again
        assert dict(os.environ) == before
        seen = ex._client.run(_worker_environ)
        assert len(seen) == 2
        assert all(v == {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "PYTHONHASHSEED": "6640"}
                   for v in seen.values()), seen
    finally:
        ex.close()
    assert dict(os.environ) == before
