"""Map stages beside a whole stage (runner._Beside): a map stage whose inputs are all there runs on
the workers while a whole stage runs in the run's process; the outputs are those of running the
stages one after another, errors are the run's, and no thread is left behind. The overlap is
checked by a barrier (the whole stage waits for an item of the later map stage to have run),
never by timing."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from gcvd_flow.engine.dag import Const, ItemRef, MapStage, Pipeline, Stage
from gcvd_flow.engine.runner import Runner
from gcvd_flow.engine.store import Store

N = 12
# the stages' parameters (a dict per section): "marks", a folder the side items mark (test only:
# stages never write files); "wait": the whole stage waits for a mark (at most a minute); "fail":
# that stage raises


def _src_items(view: Any, params: Any) -> list[dict[str, Any]]:
    return [{"i": Const(i)} for i in range(N)]


def src_item(inputs: dict[str, Any], params: Any, ctx: Any) -> dict[str, Any]:
    return {"v": np.full((8, 8), inputs["i"] + 0.25, np.float32)}


def _side_items(view: Any, params: Any) -> list[dict[str, Any]]:
    return [{"src": ItemRef("src", i)} for i in range(view.len("src"))]


def side_item(inputs: dict[str, Any], params: Any, ctx: Any) -> dict[str, Any]:
    if params["fail"] and ctx.index == 3:
        raise ValueError("side item 3 failed")
    Path(params["marks"], f"{ctx.index}-{os.getpid()}").write_text("")
    return {"w": np.asarray(inputs["src"]["v"]) * 2}


def whole(inputs: dict[str, Any], params: Any, ctx: Any) -> dict[str, Any]:
    marks = Path(params["marks"])
    if params["wait"]:
        deadline = time.monotonic() + 60
        while not any(marks.iterdir()) and time.monotonic() < deadline:
            time.sleep(0.02)
        (marks.parent / "seen").write_text(str(sorted(p.name for p in marks.iterdir())))
    if params["fail"]:
        raise RuntimeError("whole stage failed")
    src = inputs["src"]
    return {"total": float(sum(float(np.sum(src[i]["v"])) for i in range(len(src))))}


def final(inputs: dict[str, Any], params: Any, ctx: Any) -> dict[str, Any]:
    side = inputs["side"]
    return {"total": inputs["whole"]["total"], "side": float(sum(float(np.sum(side[i]["w"])) for i in range(len(side))))}


def _pipeline() -> Pipeline:
    return Pipeline([MapStage("src", src_item, kind="t", items=_src_items),
                     Stage("whole", whole, deps=("src",), kind="t", params="whole"),
                     MapStage("side", side_item, deps=("src",), kind="t", items=_side_items, params="side"),
                     Stage("final", final, deps=("whole", "side"), kind="t")])


def _config(marks: Path, wait: bool = False, fail: str = "") -> SimpleNamespace:
    marks.mkdir(parents=True, exist_ok=True)
    return SimpleNamespace(whole={"marks": str(marks), "wait": wait, "fail": fail == "whole"},
                           side={"marks": str(marks), "wait": False, "fail": fail == "side"})


def _run(tmp_path: Path, tag: str, monkeypatch: pytest.MonkeyPatch, overlap: bool, wait: bool,
         fail: str = "") -> Runner:
    monkeypatch.setenv("GCVD_FLOW_OVERLAP", "1" if overlap else "0")
    runner = Runner(_pipeline(), Store(tmp_path / tag / "cache"), config=_config(tmp_path / tag / "marks", wait, fail),
                    jobs=2, log=lambda m: None)
    runner.run()
    return runner


def test_a_ready_map_stage_runs_beside_a_whole_stage_with_the_same_outputs(tmp_path, monkeypatch):
    side_by_side = _run(tmp_path, "beside", monkeypatch, overlap=True, wait=True)
    seen = (tmp_path / "beside" / "seen").read_text()
    assert seen != "[]", "no item of the later map stage ran while the whole stage waited for one"
    assert all(int(m.split("-")[1]) != os.getpid() for m in eval(seen))  # on the workers  # noqa: S307
    one_by_one = _run(tmp_path, "serial", monkeypatch, overlap=False, wait=False)
    assert side_by_side._outputs == one_by_one._outputs
    assert side_by_side._items == one_by_one._items
    assert [r.executed for r in side_by_side.reports.values()] == [N, 1, N, 1]
    assert list(side_by_side.reports) == ["src", "whole", "side", "final"]
    assert not [t for t in threading.enumerate() if t.name.startswith("beside")]


@pytest.mark.parametrize("failing,error", [("side", ValueError), ("whole", RuntimeError)])
def test_an_error_beside_or_in_the_whole_stage_is_the_runs_and_leaves_no_thread(tmp_path, monkeypatch, failing, error):
    with pytest.raises(error):
        _run(tmp_path, failing, monkeypatch, overlap=True, wait=False, fail=failing)
    assert not [t for t in threading.enumerate() if t.name.startswith("beside")]
    again = Runner(_pipeline(), Store(tmp_path / failing / "cache"), config=_config(tmp_path / failing / "marks"),
                   jobs=2, log=lambda m: None)
    again.run()  # the same cache, healthy now: the stage records written were whole
    assert again.reports["final"].executed == 1
    assert again.reports["src"].executed == 0 and again.reports["src"].cached == N


def test_the_overlap_is_opt_in_and_only_on_a_local_pool(tmp_path, monkeypatch):
    from gcvd_flow.engine.executors import InProcessExecutor, ProcessPoolItemExecutor

    monkeypatch.delenv("GCVD_FLOW_OVERLAP", raising=False)
    runner = Runner(_pipeline(), Store(tmp_path / "cache"), config=_config(tmp_path / "marks"), jobs=2)
    pool = ProcessPoolItemExecutor(2)
    try:
        assert not runner._may_overlap(pool)  # the default: one stage after another
        monkeypatch.setenv("GCVD_FLOW_OVERLAP", "1")
        assert runner._may_overlap(pool) and not runner._may_overlap(InProcessExecutor())
        runner.records = object()  # a remote's write-through follows the stages one at a time
        assert not runner._may_overlap(pool)
    finally:
        pool.close()


def test_waiting_for_items_wakes_when_a_pool_shutdown_cancels_them():
    """A future cancelled the way ProcessPoolExecutor.shutdown(cancel_futures=True) cancels its
    queued items (Future.cancel, no set_running_or_notify_cancel) does not wake a plain
    concurrent.futures.wait: the beside stage's wait must still return (it hung a test run)."""
    from concurrent.futures import Future

    from gcvd_flow.engine.executors import _wait_first

    fut: Future = Future()
    got: list = []
    waiter = threading.Thread(target=lambda: got.append(_wait_first([fut])), daemon=True)
    waiter.start()
    waiter.join(0.2)
    assert waiter.is_alive()  # nothing finished yet: it waits
    assert fut.cancel()
    waiter.join(30)
    assert not waiter.is_alive() and got == [({fut}, set())]
