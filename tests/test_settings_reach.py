"""Issue 39 seam (e): every field of a stage's settings reaches its computation. The calibrate,
association and bundle_adjustment adapters pass their config section whole to the algorithm
(no hand-copied kw dict), and the algorithm reads every field the adapter does not read itself:
a field added to the dataclass but read by nobody fails here, where it would otherwise change
the stage's cache key but not its result."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import textwrap
from typing import Any

import numpy as np
import pytest

from gcvd_flow.evaluate.synth import default_intrinsics, render_clip
from gcvd_flow.pipeline import frontend as frontend_blocks, graph as graph_blocks, optimize as optimize_blocks
from gcvd_flow.stages.frontend.calibrate import estimate_focal
from gcvd_flow.stages.frontend.params import CalibrateSettings, settings_with
from gcvd_flow.stages.graph.association import build_graph
from gcvd_flow.stages.graph.params import AssociationSettings
from gcvd_flow.stages.optimize.bundle_adjustment import bundle_adjust
from gcvd_flow.stages.optimize.params import BundleAdjustmentSettings


class _Recorder:
    """The dataclass's defaults, recording which fields are read."""

    def __init__(self, cls: type) -> None:
        object.__setattr__(self, "_inner", cls())
        object.__setattr__(self, "read", set())

    def __getattr__(self, name: str) -> Any:
        self.read.add(name)
        return getattr(self._inner, name)


def _fields(cls: type) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


def _adapter_reads(fns: tuple[Any, ...], settings_arg: str, algorithm: str) -> tuple[set[str], bool]:
    """(fields the adapter (and its resource openers) read off their settings argument, whether
    the adapter passes that argument itself to the call of ``algorithm``)."""
    tree = ast.parse("\n".join(textwrap.dedent(inspect.getsource(fn)) for fn in fns))
    reads = {n.attr for n in ast.walk(tree)
             if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name) and n.value.id == settings_arg}
    passed = any(isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr == algorithm
                 and any(isinstance(a, ast.Name) and a.id == settings_arg for a in n.args)
                 for n in ast.walk(tree))
    return reads, passed


def _calibrate(rec: Any) -> None:
    """A clip whose focal length is determined (the path that reads every setting: the structure
    from motion, the decision, the principal point)."""
    K = default_intrinsics((160, 120))
    clip = render_clip(30, "loop", size=(160, 120), seed=0, focal=K[0, 0] * 1.2)
    assert estimate_focal(list(clip.frames), K, rec).determined


def _association(rec: Any) -> None:
    build_graph([], [], np.eye(3), 10.0, rec)


def _bundle(rec: Any) -> None:
    bundle_adjust(np.stack([np.eye(4)] * 2), [np.ones((8, 8), np.float32)] * 2, {}, [0, 1], np.eye(3), rec)


CASES = [
    pytest.param(CalibrateSettings, _calibrate, (frontend_blocks.run_calibrate,), "estimate_focal",
                 marks=pytest.mark.slow, id="CalibrateSettings"),
    pytest.param(AssociationSettings, _association, (graph_blocks.run_association, graph_blocks._open_resnet),
                 "build_graph", id="AssociationSettings"),
    pytest.param(BundleAdjustmentSettings, _bundle, (optimize_blocks.run_bundle_adjustment,), "bundle_adjust",
                 id="BundleAdjustmentSettings"),
]


@pytest.mark.parametrize("cls,call,adapter,algorithm", CASES)
def test_every_setting_reaches_the_computation(cls, call, adapter, algorithm) -> None:
    adapter_reads, passed = _adapter_reads(adapter, "p", algorithm)
    assert passed, f"{adapter[0].__name__} does not pass its settings to {algorithm}"
    rec = _Recorder(cls)
    call(rec)
    assert rec.read <= _fields(cls)
    unread = _fields(cls) - rec.read - adapter_reads
    assert not unread, f"{cls.__name__} fields neither the adapter nor {algorithm} reads: {sorted(unread)}"


def test_the_recorder_sees_a_field_nobody_reads() -> None:
    """The check above fails for a field the algorithm ignores (here: a dataclass with one more field)."""
    extra = dataclasses.make_dataclass("Extra", [("unused_knob", int, 3)], bases=(BundleAdjustmentSettings,), frozen=True)
    rec = _Recorder(extra)
    _bundle(rec)
    assert _fields(extra) - rec.read - {"enabled"} == {"unused_knob"}


def test_overrides_replace_fields_by_name_and_reject_others() -> None:
    s = settings_with(BundleAdjustmentSettings, None, {"stride": 7})
    assert s == dataclasses.replace(BundleAdjustmentSettings(), stride=7)
    assert settings_with(BundleAdjustmentSettings, None, {}) == BundleAdjustmentSettings()
    with pytest.raises(TypeError, match="no field strid"):
        settings_with(BundleAdjustmentSettings, None, {"strid": 7})
    with pytest.raises(TypeError, match="no field"):
        build_graph([], [], np.eye(3), 10.0, nms_window=3)


def test_optimize_segments_reads_every_segment_setting() -> None:
    """optimize_segments takes its SegmentSettings whole (``seg``; its adapter passes the config
    section ``b.optimize_segments``) and its module reads every field (a run is too heavy here:
    checked on the source, as the attributes read off ``seg`` / ``cfg`` / ``settings``)."""
    from gcvd_flow.stages.optimize import segments
    from gcvd_flow.stages.optimize.params import SegmentSettings

    tree = ast.parse(inspect.getsource(segments))
    reads = {n.attr for n in ast.walk(tree)
             if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name) and n.value.id in ("seg", "cfg")
             or isinstance(n, ast.Attribute) and isinstance(n.value, ast.Attribute) and n.value.attr == "seg"}
    assert _fields(SegmentSettings) - reads == set()
    adapter = inspect.getsource(optimize_blocks.run_optimize_segments)
    assert "seg=b.optimize_segments" in adapter.replace(" ", "")
