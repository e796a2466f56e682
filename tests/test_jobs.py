"""--jobs: map items in worker processes, one per usable core by default; results never depend
on it."""

from __future__ import annotations

import json
import os

import pytest
from conftest import cli, cli_json, make_toy_input

from gcvd_flow.engine import api
from gcvd_flow.engine.errors import UsageError
from gcvd_flow.engine.executors import InProcessExecutor, ProcessPoolItemExecutor, resolve_jobs, usable_cores


def test_auto_is_one_worker_per_usable_core_unless_the_environment_says(monkeypatch):
    monkeypatch.delenv("GCVD_FLOW_JOBS", raising=False)
    assert resolve_jobs(0) == usable_cores() == len(os.sched_getaffinity(0))
    monkeypatch.setenv("GCVD_FLOW_JOBS", "3")
    assert resolve_jobs(0) == 3
    assert resolve_jobs(1) == 1  # an explicit --jobs wins
    monkeypatch.setenv("GCVD_FLOW_JOBS", "auto")
    assert resolve_jobs(0) == usable_cores()
    monkeypatch.setenv("GCVD_FLOW_JOBS", "many")
    with pytest.raises(UsageError, match="GCVD_FLOW_JOBS"):
        resolve_jobs(0)


@pytest.mark.parametrize("args,env,needle", [
    (["--jobs", "0"], {}, "--jobs"),
    (["--jobs", "two"], {}, "--jobs"),
    ([], {"GCVD_FLOW_JOBS": "-1"}, "GCVD_FLOW_JOBS"),
])
def test_a_bad_jobs_setting_is_one_line_exit_2(toy_input, tmp_path, args, env, needle):
    p = cli("run", str(toy_input), "--out", str(tmp_path / "o"), "--cache", str(tmp_path / "c"),
            "--pipeline", "toy", *args, env=env)
    assert p.returncode == 2, p.stderr
    last = p.stderr.strip().splitlines()[-1]
    assert needle in last and "positive integer or 'auto'" in last, p.stderr
    assert not (tmp_path / "o" / "run.json").exists()


class _Spy:
    """A pool-like executor that records how many tasks each stage handed it."""

    jobs = 2
    min_items = ProcessPoolItemExecutor.min_items

    def __init__(self) -> None:
        self.batches: list[int] = []

    def run(self, tasks):
        tasks = list(tasks)
        self.batches.append(len(tasks))
        return InProcessExecutor().run(tasks)

    def close(self) -> None:
        pass


@pytest.mark.parametrize("n,on_workers", [(40, True), (ProcessPoolItemExecutor.min_items - 1, False)])
def test_small_stages_stay_in_process_large_ones_go_to_the_workers(tmp_path, n, on_workers):
    """Starting workers costs ~1-2 s (each imports the numeric libraries): a stage with fewer
    than min_items items to compute runs them in the calling process."""
    inp = make_toy_input(tmp_path / f"in{n}", n=n)
    spy = _Spy()
    api.run(api.Invocation(input=str(inp), out=str(tmp_path / "o"), cache=str(tmp_path / "c"), pipeline="toy"),
            log=lambda m: None, executor=spy)
    assert (spy.batches == [n, n]) if on_workers else (spy.batches == []), spy.batches


def test_default_jobs_give_the_serial_results(tmp_path, monkeypatch):
    monkeypatch.delenv("GCVD_FLOW_JOBS", raising=False)
    inp = make_toy_input(tmp_path / "in", n=40)
    outs = []
    for tag, extra in (("auto", []), ("serial", ["--jobs", "1"])):
        doc = cli_json("run", str(inp), "--out", str(tmp_path / tag), "--cache", str(tmp_path / f"c{tag}"),
                       "--pipeline", "toy", *extra, env={"GCVD_FLOW_JOBS": ""})
        assert all(s["executed"] for s in doc["stages"]), doc
        outs.append({k: v["output"] for k, v in json.loads((tmp_path / tag / "run.json").read_text())["stages"].items()})
    assert outs[0] == outs[1]


def test_gcvd_map_stages_on_workers_are_bit_identical_to_in_process(tmp_path):
    """DIS flow, masks and priors computed by 2 single-threaded workers equal the in-process
    results (OpenCV's DIS splits its patch search by thread, and still gives the same bits)."""
    clip = tmp_path / "clip"
    cli("synth", str(clip), "--frames", "16", "--trajectory", "orbit", "--size", "128x96", check=True)
    outs = []
    for jobs in ("1", "2"):
        out, executed = {}, {}
        for until in ("masks", "priors"):  # masks needs flow; priors needs flow_far (and masks)
            doc = cli_json("run", str(clip), "--out", str(tmp_path / f"o{jobs}"), "--cache",
                           str(tmp_path / f"c{jobs}"), "--until", until, "--jobs", jobs)
            for s in doc["stages"]:  # the first run's report of a stage counts
                executed.setdefault(s["name"], s["executed"])
            out.update({k: v["output"] for k, v in json.loads((tmp_path / f"o{jobs}" / "run.json").read_text())["stages"].items()})
        assert executed["flow"] == 15 and executed["masks"] == 16 and executed["priors"] == 16, executed
        outs.append(out)
    assert set(outs[0]) >= {"flow", "flow_far", "masks", "priors"}
    assert outs[0] == outs[1]


def _pid_and_square(x: int) -> tuple[int, int]:
    return os.getpid(), x * x


def test_stage_map_calls_run_in_order_on_the_workers_building_arguments_lazily():
    """``ctx.map`` of a whole stage (segment windows, loop edges): results in argument order,
    computed by the worker processes, with only a few arguments built ahead (a window's job
    holds tens of MB); a handful of calls stays in this process."""
    from gcvd_flow.engine.executors import MIN_CALLS

    ex = ProcessPoolItemExecutor(2)
    try:
        built: list[int] = []

        def args():
            for i in range(9):
                built.append(i)
                yield i

        it = ex.map_calls(_pid_and_square, args())
        first = next(it)
        assert first[1] == 0 and len(built) <= 2 * 2 + 1 < 9  # not all arguments built at once
        rest = list(it)
        assert [r[1] for r in [first, *rest]] == [i * i for i in range(9)]
        assert {r[0] for r in [first, *rest]} - {os.getpid()} and os.getpid() not in {r[0] for r in rest}
        few = list(ex.map_calls(_pid_and_square, range(MIN_CALLS - 1)))
        assert [r[0] for r in few] == [os.getpid()] * (MIN_CALLS - 1)
    finally:
        ex.close()


def test_gcvd_segment_windows_on_workers_are_bit_identical_to_in_process(tmp_path):
    """optimize_segments' windows (here 9 of them) run on the workers with --jobs 2 (``ctx.map``)
    and in this process with --jobs 1: the same bits (each window is seeded by its own number
    and runs on its own torch thread count, whoever computes it). The clip's one loop edge runs
    in-process either way (tests/test_optimize.py checks an edge on a worker)."""
    clip = tmp_path / "clip"
    cli("synth", str(clip), "--frames", "40", "--trajectory", "loop", "--size", "128x96", check=True)
    quick = ["optimize_keyframes.steps=10", "optimize_edges.steps=5", "optimize_segments.steps=5",
             "optimize_segments.window=8"]
    outs = []
    for jobs in ("1", "2"):
        cli_json("run", str(clip), "--out", str(tmp_path / f"o{jobs}"), "--cache", str(tmp_path / f"c{jobs}"),
                 "--until", "optimize_segments", "--jobs", jobs, *[a for s in quick for a in ("--set", s)])
        run = json.loads((tmp_path / f"o{jobs}" / "run.json").read_text())["stages"]
        outs.append({k: run[k]["output"] for k in ("optimize_keyframes", "optimize_segments")})
    assert outs[0] == outs[1]
