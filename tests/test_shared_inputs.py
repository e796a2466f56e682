"""Map items that read the same inputs (MapStage.share_inputs, executors.SharedInputs): a worker
loads, verifies and decodes each shared input once for the whole stage rather than once per item
that reads it, hands the items read-only arrays, and the outputs are those of loading per item.
Loads are counted, never timed."""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np
import pytest

from gcvd_flow.engine import executors
from gcvd_flow.engine.artifacts import Encoder
from gcvd_flow.engine.dag import Const, ItemRef, MapStage, Pipeline
from gcvd_flow.engine.runner import Runner
from gcvd_flow.engine.store import Store

N, RADIUS = 9, 3
LOAD_VALUE = executors.load_value


def frame_item(inputs: dict[str, Any], params: Any, ctx: Any) -> dict[str, Any]:
    i = int(inputs["i"])
    return {"depth": np.full((16, 16), i + 0.5, np.float32), "mask": np.full((16, 16), 1 + i % 2, np.uint8)}


def window_item(inputs: dict[str, Any], params: Any, ctx: Any) -> dict[str, Any]:
    depths = [np.asarray(f["depth"]) * f["mask"] for f in inputs["frames"]]
    return {"mean": np.mean(depths, axis=0).astype(np.float32), "frames": ctx.input_digest("frames")}


def writing_item(inputs: dict[str, Any], params: Any, ctx: Any) -> dict[str, Any]:
    d = inputs["frames"][0]["depth"]
    d += 1  # modifies its input
    return {"mean": d}


def _frames(view: Any, params: Any) -> list[dict[str, Any]]:
    return [{"i": Const(i)} for i in range(N)]


def _windows(view: Any, params: Any) -> list[dict[str, Any]]:
    n = view.len("frames")
    return [{"frames": [ItemRef("frames", j) for j in range(max(0, i - RADIUS), min(n, i + RADIUS + 1))]}
            for i in range(n)]


def _pipeline(share: bool, fn: Any = window_item) -> Pipeline:
    return Pipeline([MapStage("frames", frame_item, kind="t", items=_frames),
                     MapStage("window", fn, deps=("frames",), kind="t", items=_windows, share_inputs=share)])


def _run(tmp_path: Any, share: bool, monkeypatch: pytest.MonkeyPatch, fn: Any = window_item) -> tuple[Runner, Counter]:
    """The pipeline run in this process (jobs 1); the item artifacts the window stage loaded, counted."""
    loaded: Counter = Counter()
    def counting(store: Store, digest: str) -> Any:
        loaded[digest] += 1
        return LOAD_VALUE(store, digest)

    runner = Runner(_pipeline(share, fn), Store(tmp_path / ("shared" if share else "plain")), None, log=lambda m: None)
    runner.run("frames")
    monkeypatch.setattr(executors, "load_value", counting)
    runner.run("window")
    return runner, loaded


def test_a_shared_input_is_loaded_once_per_worker_with_the_same_outputs(tmp_path, monkeypatch):
    shared, loads = _run(tmp_path, True, monkeypatch)
    plain, plain_loads = _run(tmp_path, False, monkeypatch)
    frames = shared._items["frames"]
    assert sorted(loads) == sorted(frames) and set(loads.values()) == {1}  # each frame once
    assert plain_loads[frames[4]] == 2 * RADIUS + 1  # without: once per item that reads it
    for a, b in zip(shared.value("window"), plain.value("window")):
        assert np.asarray(a["mean"]).tobytes() == np.asarray(b["mean"]).tobytes()
    # the digests the items saw are those of the frames they read
    assert shared.value("window")[4]["frames"] == frames[4 - RADIUS:4 + RADIUS + 1]
    assert executors.SHARED.bytes == 0  # dropped when the stage ended


def test_shared_arrays_are_read_only(tmp_path, monkeypatch):
    """An item that wrote into a shared array would change what the next item reads: it raises."""
    with pytest.raises(ValueError, match="read-only"):
        _run(tmp_path, True, monkeypatch, writing_item)


def test_shared_inputs_stay_within_the_budget_and_a_new_stage_starts_afresh(tmp_path):
    store = Store(tmp_path / "c")
    refs = [executors.ResolvedRef("artifact", Encoder(store).manifest("t", {"a": np.full(1000, k, np.float64)}))
            for k in range(4)]
    cache = executors.SharedInputs(budget=2 * 8000 + 500)  # two of the 8000-byte values
    cache.begin(("root", "stage-1"))
    for r in refs[:3]:
        cache.load(r, store)
    assert cache.loads == 3 and cache.bytes <= cache.budget
    first = cache.load(refs[2], store)
    assert cache.hits == 1 and not first["a"].flags.writeable
    first["b"] = 1  # the containers are the item's own
    assert "b" not in cache.load(refs[2], store)
    cache.load(refs[0], store)  # evicted by the third
    assert cache.loads == 4
    cache.begin(("root", "stage-2"))
    assert cache.bytes == 0
    cache.load(refs[2], store)
    assert cache.loads == 5
