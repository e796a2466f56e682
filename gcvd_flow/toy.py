"""A 5-stage toy pipeline over a folder of ``*.bin`` files (engine tests and benchmarks).

``decode`` (map, one item per file) -> ``transform`` (map) -> ``summarize`` -> ``threshold``
-> ``report``. It exercises everything the GCVD pipeline relies on (per-item caching,
selection parameters, early cutoff, whole stages) without any vision code.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import BaseModel, Field

from stages import toy

from .api import PipelineSpec
from .config import Section
from .dag import ExternalRef, ItemRef, MapStage, Pipeline, Stage
from .errors import UsageError
from .keys import digest_file, key_of


class DecodeParams(Section):
    start: int = 0
    end: int | None = None
    stride: int = Field(1, ge=1)


class TransformParams(Section):
    scale: float = 2.0
    sleep: float = 0.0  # simulated work per item (tests kill runs mid-stage)


class SummarizeParams(Section):
    digits: int = 6


class ThresholdParams(Section):
    cut: float = 200.0


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
    MapStage("decode", toy.decode_item, params="decode", kind="toy", items=_decode_items,
             selection_params=("start", "end", "stride")),
    MapStage("transform", toy.transform_item, deps=("decode",), params="transform", kind="toy",
             items=_transform_items),
    Stage("summarize", toy.summarize, deps=("transform",), params="summarize", kind="toy"),
    Stage("threshold", toy.threshold, deps=("summarize",), params="threshold", kind="toy"),
    Stage("report", toy.report, deps=("threshold",), kind="toy"),
])


def export(out: Path, runner, config) -> dict[str, Any]:
    rep = runner.value("report")
    (out / "report.json").write_text(json.dumps(rep, sort_keys=True))
    return {"report": str(out / "report.json")}


SPEC = PipelineSpec("toy", PIPELINE, ToyConfig, profiles={"fast": {"transform": {"scale": 1.0}}},
                    open_source=open_source, export=export)
