"""A 5-stage toy pipeline over a folder of ``*.bin`` files (engine tests and benchmarks).

``decode`` (map, one item per file) -> ``transform`` (map) -> ``summarize`` -> ``threshold``
-> ``report``. It exercises everything the GCVD pipeline relies on (per-item caching,
selection parameters, early cutoff, whole stages) without any vision code.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, Field

from gcvd_flow.engine.api import PipelineSpec
from gcvd_flow.engine.config import Section
from gcvd_flow.engine.dag import ExternalRef, ItemRef, MapStage, Pipeline, Stage
from gcvd_flow.engine.errors import UsageError
from gcvd_flow.engine.keys import digest_file, key_of

SCHEMA_DIR = Path(__file__).resolve().parent / "schemas"  # toy.json: the toy pipeline's one artifact kind

# ------------------------------------------------------------------------------ stage functions


def _scaled(x: np.ndarray, scale: float) -> np.ndarray:
    return (x.astype(np.float32) * np.float32(scale)).astype(np.float32)


def decode_item(inputs: dict[str, Any], params: Any, ctx: Any) -> dict[str, Any]:
    """Bytes of one input file -> float32 array (N,) with values in [0, 255]."""
    raw = inputs["blob"]
    return {"values": np.frombuffer(raw, dtype=np.uint8).astype(np.float32)}


def transform_item(inputs: dict[str, Any], params: Any, ctx: Any) -> dict[str, Any]:
    """One item scaled by ``params.scale``; ``params.sleep`` seconds of simulated work. Item
    ``params.kill_worker``, computed on a worker process, kills that process (SIGKILL, as the
    out-of-memory killer does) every time: tests of lost workers."""
    if params.sleep:
        time.sleep(params.sleep)
    if ctx.index == params.kill_worker and multiprocessing.parent_process() is not None:
        os.kill(os.getpid(), signal.SIGKILL)
    x = inputs["item"]["values"]
    return {"values": _scaled(x, params.scale), "mean": float(x.mean())}


def _slow_mean(args: tuple[np.ndarray, float]) -> float:
    values, sleep = args
    time.sleep(sleep)
    return float(values.mean())


def summarize(inputs: dict[str, Any], params: Any, ctx: Any) -> dict[str, Any]:
    """Mean of every transformed item, rounded to ``params.digits`` decimals. With
    ``params.sleep`` each mean is a ``ctx.map`` call that sleeps first (a whole stage's calls
    on the workers, for tests that interrupt them); the values are the same."""
    items = inputs["transform"]
    if params.sleep:
        means = list(ctx.map(_slow_mean, ((items[i]["values"], params.sleep) for i in range(len(items)))))
    else:
        means = [float(items[i]["values"].mean()) for i in range(len(items))]
    return {"means": np.asarray(means, dtype=np.float64),
            "total": round(float(np.sum(means)), params.digits)}


def threshold(inputs: dict[str, Any], params: Any, ctx: Any) -> dict[str, Any]:
    """Which item means exceed ``params.cut``; ``params.sleep`` seconds of work in the run's
    own process first (the workers idle meanwhile, as during a long whole stage)."""
    if params.sleep:
        time.sleep(params.sleep)
    means = inputs["summarize"]["means"]
    return {"above": (means > params.cut).astype(np.uint8), "cut": params.cut}


def report(inputs: dict[str, Any], params: Any, ctx: Any) -> dict[str, Any]:
    above = inputs["threshold"]["above"]
    return {"count": int(above.sum()), "n": int(above.size)}


# ------------------------------------------------------------------------------ parameters


class DecodeParams(Section):
    start: int = 0
    end: int | None = None
    stride: int = Field(default=1, ge=1)


class TransformParams(Section):
    scale: float = 2.0
    sleep: float = 0.0  # simulated work per item (tests kill runs mid-stage)
    kill_worker: int = -1  # this item kills the worker process computing it (tests of lost workers)


class SummarizeParams(Section):
    digits: int = 6
    sleep: float = 0.0  # per item, as ctx.map calls (tests interrupt a stage's calls on the workers)


class ThresholdParams(Section):
    cut: float = 200.0
    sleep: float = 0.0  # in the run's process, workers idle (tests interrupt a run there)


class ToyConfig(BaseModel):
    model_config = {"extra": "forbid"}
    seed: int = 0
    decode: DecodeParams = DecodeParams()
    transform: TransformParams = TransformParams()
    summarize: SummarizeParams = SummarizeParams()
    threshold: ThresholdParams = ThresholdParams()


@dataclass(frozen=True)
class FileBytes:
    """Picklable loader of one input file."""

    path: str

    def __call__(self) -> bytes:
        return Path(self.path).read_bytes()


@dataclass
class ToySource:
    items: list[ExternalRef]
    digest: str


def open_source(path: str, config: Any) -> ToySource:
    root = Path(path)
    if not root.is_dir():
        raise UsageError(f"{path}: not a directory of .bin files")
    files = sorted(root.glob("*.bin"))
    if not files:
        raise UsageError(f"{path}: no .bin files")
    refs = [ExternalRef(digest_file(f), FileBytes(str(f))) for f in files]
    return ToySource(refs, key_of([r.digest for r in refs]))


def _decode_items(view, p: DecodeParams):
    sel = view.source.items[p.start:p.end:p.stride]
    return [{"blob": r} for r in sel]


def _transform_items(view, p):
    return [{"item": ItemRef("decode", i)} for i in range(view.len("decode"))]


PIPELINE = Pipeline([
    MapStage("decode", decode_item, params="decode", kind="toy", items=_decode_items,
             selection_params=("start", "end", "stride")),
    MapStage("transform", transform_item, deps=("decode",), params="transform", kind="toy",
             items=_transform_items),
    Stage("summarize", summarize, deps=("transform",), params="summarize", kind="toy"),
    Stage("threshold", threshold, deps=("summarize",), params="threshold", kind="toy"),
    Stage("report", report, deps=("threshold",), kind="toy"),
], packages=("gcvd_flow.testing.toy",))


def export(out: Path, runner, config) -> dict[str, Any]:
    rep = runner.value("report")
    (out / "report.json").write_text(json.dumps(rep, sort_keys=True))
    return {"report": str(out / "report.json")}


SPEC = PipelineSpec("toy", PIPELINE, ToyConfig, profiles={"fast": {"transform": {"scale": 1.0}}},
                    open_source=open_source, export=export, schema_dir=SCHEMA_DIR)
