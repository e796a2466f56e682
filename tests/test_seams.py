"""The seams where adding a stage used to go wrong silently (issue 39 (a), (c), (f), (g)): each is
now an error where the mistake is made, and these tests make the mistake on purpose."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
from conftest import make_toy_input

from gcvd_flow import artifacts_schema
from gcvd_flow.engine.api import PipelineSpec
from gcvd_flow.engine.artifacts import ArtifactError, validate
from gcvd_flow.engine.dag import ItemRef, MapStage, Pipeline, PipelineError, Stage
from gcvd_flow.engine.runner import Runner
from gcvd_flow.engine.store import Store
from gcvd_flow.engine.sweep import Combo, _wave_groups, prefix_stages
from gcvd_flow.testing import toy


def _toy_stages() -> dict[str, Stage]:
    return {s.name: dataclasses.replace(s) for s in toy.PIPELINE.stages}


# (a) every artifact kind has a schema --------------------------------------------------------


def test_every_kind_of_the_pipelines_has_its_schema():
    from gcvd_flow import pipeline

    for spec in (pipeline.SPEC, toy.SPEC):
        for s in spec.pipeline.stages:
            for kind in (s.kind, getattr(s, "summary_kind", None)):
                if kind is not None:
                    assert (Path(spec.schema_dir) / f"{kind}.json").is_file(), (s.name, kind)
    # the toy pipeline's kind lives beside it, not among the product's schemas
    assert not (Path(artifacts_schema.SCHEMA_DIR) / "toy.json").exists()


def test_a_kind_without_schema_is_a_declaration_error(tmp_path):
    st = _toy_stages()
    st["report"] = dataclasses.replace(st["report"], kind="no_such_kind")
    with pytest.raises(PipelineError, match="no_such_kind"):
        PipelineSpec("toy2", Pipeline(list(st.values())), toy.ToyConfig, schema_dir=toy.SCHEMA_DIR)


def test_calibration_and_fusion_samples_manifests_are_validated():
    import gcvd_flow.pipeline  # noqa: F401 - registers the product's schema folder

    arr = {"$npy": "0" * 64, "dtype": "<f8", "shape": [3, 3]}
    good = {"kind": "calibration", "value": {"K": arr, "estimated": False, "guessed": True, "origin": "guess",
                                             "focal_source": [1.0, 1.0], "rel_sigma": None, "warning": ""}}
    validate("calibration", good)
    bad = json.loads(json.dumps(good))
    bad["value"]["estimated"] = "yes"
    with pytest.raises(ArtifactError, match="calibration"):
        validate("calibration", bad)
    with pytest.raises(ArtifactError, match="fusion_samples"):
        validate("fusion_samples", {"kind": "fusion_samples", "value": {"points": arr}})


# (g) selection_params name real parameters -----------------------------------------------------


def test_misspelt_selection_params_is_a_declaration_error():
    st = _toy_stages()
    st["decode"] = dataclasses.replace(st["decode"], selection_params=("start", "end", "strde"))
    with pytest.raises(PipelineError, match="strde"):
        PipelineSpec("toy3", Pipeline(list(st.values())), toy.ToyConfig, schema_dir=toy.SCHEMA_DIR)


# (f) deps= against what items functions read ---------------------------------------------------


def _run(tmp_path: Path, stages: list[Stage]) -> None:
    src = make_toy_input(tmp_path / "in", n=4, size=64)
    cfg = toy.ToyConfig()
    runner = Runner(Pipeline(stages), Store(tmp_path / "cache"), cfg, toy.open_source(str(src), cfg))
    runner.plan()
    runner.run()


def test_an_item_reference_to_an_undeclared_stage_is_an_error(tmp_path):
    st = _toy_stages()
    # reads decode's items but declares only summarize: its key would miss decode's output
    sneaky = MapStage("sneaky", toy.transform_item, deps=("summarize",), params="transform", kind="toy",
                      items=lambda view, p: [{"item": ItemRef("decode", 0)}])
    with pytest.raises(PipelineError, match="sneaky.*decode"):
        _run(tmp_path, [st["decode"], st["transform"], st["summarize"], sneaky])


def test_an_undeclared_read_in_an_items_function_is_an_error(tmp_path):
    st = _toy_stages()
    sneaky = MapStage("sneaky", toy.transform_item, deps=("transform",), params="transform", kind="toy",
                      items=lambda view, p: [{"item": ItemRef("transform", i)} for i in range(view.len("decode"))])
    with pytest.raises(PipelineError, match="sneaky.*decode"):
        _run(tmp_path, [st["decode"], st["transform"], sneaky])


def test_declared_references_run(tmp_path):
    st = _toy_stages()
    _run(tmp_path, list(st.values()))


# (c) the sweep's wave prefix -------------------------------------------------------------------


def test_sweep_prefix_keeps_masks_and_priors_in_the_waves():
    from gcvd_flow import pipeline

    names = [s.name for s in prefix_stages(pipeline.PIPELINE)]
    assert {"ingest", "flow", "flow_far", "masks", "priors"} <= set(names)
    assert "calibrate" in names and names.index("calibrate") < names.index("masks")
    assert not {"keyframes", "association", "optimize_keyframes", "depth_fusion"} & set(names)
    masks = pipeline.PIPELINE.get("masks")
    combos = [Combo(f"masks.sigma_mult={v}", (f"masks.sigma_mult={v}",), {"masks.sigma_mult": v}) for v in (1.0, 2.0)]
    assert len(_wave_groups(pipeline.PIPELINE, masks, combos)) == 2  # the two settings interleave
    assert len(_wave_groups(pipeline.PIPELINE, pipeline.PIPELINE.get("flow"), combos)) == 1  # flow: once


def test_prefix_bridges_are_whole_stages_read_by_a_later_prefix_map_stage():
    def fn(*a):
        return None

    m = lambda n, deps=(): MapStage(n, fn, deps=deps, kind="toy", items=lambda v, p: [])  # noqa: E731
    w = lambda n, deps=(): Stage(n, fn, deps=deps, kind="toy")  # noqa: E731
    p = Pipeline([m("a"), w("b", ("a",)), m("c", ("a", "b")), w("d", ("c",)), w("e", ("d",)), m("f", ("e",)),
                  w("g", ("c",))])
    assert [s.name for s in prefix_stages(p)] == ["a", "b", "c"]  # d, g: no later map stage reads them


# (d) readers name stages through their declarations ----------------------------------------------


def test_readers_do_not_spell_stage_names():
    """A stage name written as a string in a reader (report, run dir, exports, eval, CLI) would
    silently read nothing after a rename; they go through the declarations (``G.X.name``,
    ``RUN_DIR_SOURCES``)."""
    import ast

    from conftest import ROOT

    from gcvd_flow import pipeline

    names = set(pipeline.STAGE_NAMES)
    # the calls that read a stage's recorded output by its name
    stage_readers = {"recorded_part", "recorded_output", "_map_output", "value", "stage_value", "get_stage"}
    readers = [p for d in ("report", "io", "exports", "evaluate") for p in (ROOT / "gcvd_flow" / d).rglob("*.py")]
    readers.append(ROOT / "gcvd_flow" / "cli.py")
    found = []
    for path in readers:
        for node in ast.walk(ast.parse(path.read_text())):
            f = getattr(node, "func", None)
            if isinstance(node, ast.Call) and (getattr(f, "id", None) or getattr(f, "attr", None)) in stage_readers:
                for a in [*node.args, *(k.value for k in node.keywords)]:
                    if isinstance(a, ast.Constant) and a.value in names:
                        found.append(f"{path.relative_to(ROOT)}:{a.lineno} {a.value!r}")
    assert found == []


# (b) the benchmarks' stage groups come from the pipeline ------------------------------------------


def test_stage_groups_cover_every_stage_once():
    import importlib.util

    from conftest import ROOT

    from gcvd_flow import pipeline

    g = pipeline.STAGE_GROUPS
    assert [n for k in ("pre", "main", "post") for n in g[k]] == pipeline.STAGE_NAMES
    assert "calibrate" in g["pre"] and "fusion_samples" in g["post"] and "bundle_adjustment" in g["main"]
    spec = importlib.util.spec_from_file_location("bench_runtime", ROOT / "benchmarks" / "bench_runtime.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    assert (bench.PRE, bench.MAIN, bench.POST) == (g["pre"], g["main"], g["post"])
