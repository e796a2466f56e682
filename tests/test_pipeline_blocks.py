"""The pipeline's blocks: stage declarations referenced as objects, RUN_DIR's sources, parameter
sections derived from the stages' dataclasses, and the index rules of the items
(stages/graph/references.py) that decide what each item reads."""

from __future__ import annotations

import dataclasses

import pytest

from gcvd_flow import pipeline as gp
from gcvd_flow.engine.dag import ItemRef, MapStage, PartRef, Pipeline, PipelineError, Stage
from gcvd_flow.stages.depth import params as depth_params
from gcvd_flow.stages.frontend import params as frontend_params
from gcvd_flow.stages.graph import params as graph_params, references as R
from gcvd_flow.stages.optimize import params as opt_params


def _noop(inputs, p, ctx):
    return {}


def test_stage_objects_stand_for_their_names():
    assert ItemRef(gp.INGEST, 3) == ItemRef("ingest", 3) and hash(ItemRef(gp.INGEST, 3)) == hash(ItemRef("ingest", 3))
    assert PartRef(gp.OPTIMIZE_SEGMENTS, ("poses",)) == PartRef("optimize_segments", ("poses",))
    a = Stage("a", _noop)
    b = Stage("b", _noop, deps=(a,))
    assert b.deps == ("a",) and Pipeline([a, b]).get(a) is a
    with pytest.raises(PipelineError, match="not declared before"):
        Pipeline([b, a])
    # every declared stage object is in the pipeline, in declaration order
    declared = [v for v in vars(gp).values() if isinstance(v, Stage)]
    assert sorted(s.name for s in declared) == sorted(gp.PIPELINE.names())


def test_run_dir_reads_the_final_stages_of_the_pipeline():
    src = gp.RUN_DIR_SOURCES
    stages = gp.PIPELINE.stages
    # the depth it writes is the last depth stage's, the poses those of the stage that poses every frame
    assert src.depth == [s.name for s in stages if s.kind == "depth"][-1]
    assert src.poses == [s.name for s in stages if s.kind == "segment_solution"][-1]
    assert src.frames == [s.name for s in stages if isinstance(s, MapStage) and s.summary_kind == "camera"][0]
    assert src.keyframes == [s.name for s in stages if s.kind == "keyframes"][-1]
    assert gp.SPEC.export.keywords["sources"] is src


def test_every_section_is_derived_from_a_stage_dataclass():
    # the defaults live in stages/: a section's default is its dataclass's
    for name, section in gp._SECTIONS.items():
        fields = section.model_fields
        owners = [c for mod in (frontend_params, graph_params, depth_params, opt_params)
                  for c in vars(mod).values() if dataclasses.is_dataclass(c) and isinstance(c, type)
                  and {f.name for f in dataclasses.fields(c)} == set(fields)]
        assert owners, f"section {name!r} has no parameter dataclass in stages/"
        for f in dataclasses.fields(owners[0]):
            assert fields[f.name].default == f.default, (name, f.name)


def test_reference_rules():
    n = 20
    assert R.prior_references(0, n, 8) == [8, 4] and R.prior_references(12, n, 8) == [4, 8]
    assert R.prior_references(19, n, 8) == [11, 15]
    assert R.prior_references(0, 2, 8) == [1, 1]  # both clamped to the other frame (kept: the bits of the priors)
    assert R.symmetric_prior_references(10, n, 8) == [2, 18] and R.symmetric_prior_references(3, n, 8) == [11, 7]
    assert R.symmetric_prior_references(19, n, 8) == [11, 15] and R.symmetric_prior_references(0, 2, 8) == [1]
    assert R.offset_references(3, n, (-8, 8, 0)) == [11] and R.offset_references(15, n, (-8, 8)) == [7]
    assert R.symmetric_references(10, n, (8, 16)) == [2, 18] and R.symmetric_references(0, n, (8,)) == [8]
    assert R.flow_chain(2, n, 6) == ("fwd", [2, 3, 4, 5, 6, 7]) and R.flow_chain(9, n, 6) == ("bwd", [8, 7, 6, 5, 4, 3])
    assert R.flow_chain(1, 3, 6) == ("bwd", [0])
    assert R.window(1, n, 4) == (0, 5) and R.window(18, n, 4) == (14, 19)
    pairs = R.far_pairs(n, [(lambda i: R.offset_references(i, n, (-8, 8)), "fine", 1.0),
                            (lambda i: R.offset_references(i, n, (8,)), "fine", 1)])
    assert pairs == [(i, i + 8, "fine", 1.0) for i in range(n - 8)]  # asked for 3 times, computed once


def test_extending_a_clip_keeps_the_references_of_its_frames():
    # what lets an extended clip re-use its items: old frames read the same frames / flows
    for span in (4, 6, 8):
        for n in (2 * span, 2 * span + 5):
            for i in range(n):
                assert R.flow_chain(i, n, span) == R.flow_chain(i, n + 7, span)
                assert R.prior_references(i, n, span) == R.prior_references(i, n + 7, span)
