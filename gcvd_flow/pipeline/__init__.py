"""The GCVD pipeline: its configuration and its DAG, one block per stage.

    ingest [map: frame] -> flow [map: pair i,i+1] -> flow_far [map: pair i,j] -> masks [map: frame]
    -> priors_direct [map: frame] (reads flow_far) -> priors [map: frame] (passes priors_direct's on,
    or reads the adjacent-flow chain where no direct flow held) -> keyframes -> association -> optimize_keyframes
    -> optimize_edges -> pose_graph
    -> bundle_adjustment -> optimize_segments -> fusion_samples [map: frame]
    -> fusion_references [map: one item] -> fusion_flow [map: pair i,j]
    -> depth_fusion [map: frame] (reads flow, flow_far, fusion_flow)
    -> depth_filter [map: frame] -> depth_consensus [map: frame]

Each block holds everything about one stage: its parameters (a pydantic section, ``--set
section.key=value``, derived from the stage's parameter dataclass in ``stages/*/params.py``), for
a map stage the inputs of each item (typed references to the declared stages: an item of another
stage, a list of them, a part of a whole stage's output, a constant; which frames an item reads
is ``stages/graph/references.py``'s), the function the
engine calls — ``run_<stage>(inputs, params, ctx)``, which unpacks the inputs by the names the
items declared and calls the algorithm in ``stages/`` — and the declaration. Each map item
reads exactly the pieces it needs (a frame, its neighbours' flows, ...), so a trimmed, extended
or re-strided clip re-uses every item whose inputs did not change. Adding a stage is adding a
block here plus its algorithm in ``stages/`` (docs/contributing.md).

Conventions (docs/contributing.md): frames uint8 (H, W, 3) RGB; flows float32 (H, W, 2) px;
poses T_w_c camera-to-world (4, 4) float64; depth float32 (H, W), one global scale.

The blocks are modules of this package (declared in this order: frontend, masks, priors, graph, optimize, depth);
gcvd_flow.pipeline.<name> is every name of every block, as when this was one file."""

from __future__ import annotations

import functools
import sys
from typing import Any

from pydantic import ConfigDict, create_model

from gcvd_flow import artifacts_schema
from gcvd_flow.engine.api import PipelineSpec
from gcvd_flow.engine.dag import Pipeline
from gcvd_flow.engine.errors import UsageError
from gcvd_flow.io import run_dir
from gcvd_flow.io.sources import Source, open_source as _open_source
from gcvd_flow.pipeline.depth import (
    DEPTH_CONSENSUS as DEPTH_CONSENSUS,
    DEPTH_FILTER as DEPTH_FILTER,
    DEPTH_FUSION as DEPTH_FUSION,
    FUSION_FLOW as FUSION_FLOW,
    FUSION_REFERENCES as FUSION_REFERENCES,
    FUSION_SAMPLES as FUSION_SAMPLES,
    DepthConsensusParams as DepthConsensusParams,
    DepthFilterParams as DepthFilterParams,
    DepthFusionParams as DepthFusionParams,
    FusionReferencesParams as FusionReferencesParams,
    _consensus_items as _consensus_items,
    _filter_items as _filter_items,
    _fusion_flow_items as _fusion_flow_items,
    _fusion_items as _fusion_items,
    _fusion_references_items as _fusion_references_items,
    _fusion_samples_items as _fusion_samples_items,
    run_depth_consensus as run_depth_consensus,
    run_depth_filter as run_depth_filter,
    run_depth_fusion as run_depth_fusion,
    run_fusion_references as run_fusion_references,
    run_fusion_samples as run_fusion_samples,
)
from gcvd_flow.pipeline.frontend import (
    CALIBRATE as CALIBRATE,
    FLOW as FLOW,
    FLOW_FAR as FLOW_FAR,
    INGEST as INGEST,
    USER_MASKS as USER_MASKS,
    CalibrateParams as CalibrateParams,
    FlowParams as FlowParams,
    IngestParams as IngestParams,
    _camera as _camera,
    _far_index as _far_index,
    _far_pairs as _far_pairs,
    _far_refs as _far_refs,
    _flow_far_items as _flow_far_items,
    _flow_far_summary as _flow_far_summary,
    _flow_items as _flow_items,
    _ingest_items as _ingest_items,
    _ingest_summary as _ingest_summary,
    _open_raft as _open_raft,
    _principal_point_outcome as _principal_point_outcome,
    _SampledImages as _SampledImages,
    _unsolvable as _unsolvable,
    _user_mask_items as _user_mask_items,
    run_calibrate as run_calibrate,
    run_flow as run_flow,
    run_flow_far as run_flow_far,
    run_ingest as run_ingest,
    run_user_masks as run_user_masks,
    source_positions as source_positions,
    undistort_source_frame as undistort_source_frame,
)
from gcvd_flow.pipeline.graph import (
    ASSOCIATION as ASSOCIATION,
    KEYFRAMES as KEYFRAMES,
    AssociationParams as AssociationParams,
    KeyframesParams as KeyframesParams,
    _open_resnet as _open_resnet,
    run_association as run_association,
    run_keyframes as run_keyframes,
)
from gcvd_flow.pipeline.masks import (
    MASKS as MASKS,
    MasksParams as MasksParams,
    _backend_mask as _backend_mask,
    _chain_refs as _chain_refs,
    _has_user_masks as _has_user_masks,
    _mask_items as _mask_items,
    _mask_summary as _mask_summary,
    _open_maskrcnn as _open_maskrcnn,
    _user_mask_refs as _user_mask_refs,
    _with_user_mask as _with_user_mask,
    run_masks as run_masks,
)
from gcvd_flow.pipeline.optimize import (
    BUNDLE_ADJUSTMENT as BUNDLE_ADJUSTMENT,
    OPT as OPT,
    OPTIMIZE_EDGES as OPTIMIZE_EDGES,
    OPTIMIZE_KEYFRAMES as OPTIMIZE_KEYFRAMES,
    OPTIMIZE_SEGMENTS as OPTIMIZE_SEGMENTS,
    POSE_GRAPH as POSE_GRAPH,
    BundleAdjustmentParams as BundleAdjustmentParams,
    DepthParams as DepthParams,
    LossParams as LossParams,
    OptimizeEdgesParams as OptimizeEdgesParams,
    OptimizeKeyframesParams as OptimizeKeyframesParams,
    OptimizeSegmentsParams as OptimizeSegmentsParams,
    PoseGraphParams as PoseGraphParams,
    _flow_dict as _flow_dict,
    _FlowDicts as _FlowDicts,
    _inv as _inv,
    _ScaledDepths as _ScaledDepths,
    _stack as _stack,
    run_bundle_adjustment as run_bundle_adjustment,
    run_optimize_edges as run_optimize_edges,
    run_optimize_keyframes as run_optimize_keyframes,
    run_optimize_segments as run_optimize_segments,
    run_pose_graph as run_pose_graph,
)
from gcvd_flow.pipeline.priors import (
    PRIORS as PRIORS,
    PRIORS_DIRECT as PRIORS_DIRECT,
    PriorsParams as PriorsParams,
    _open_midas as _open_midas,
    _prior_items as _prior_items,
    run_priors as run_priors,
    run_priors_direct as run_priors_direct,
)
from gcvd_flow.pipeline.registry import (
    _SECTIONS as _SECTIONS,
    _STAGES as _STAGES,
    _field_check as _field_check,
    _section_check as _section_check,
    config_section as config_section,
    declare as declare,
    section as section,
    section_from_dataclass as section_from_dataclass,
)
from gcvd_flow.pipeline.shared import (
    _eroded_keep as _eroded_keep,
    _far_flow as _far_flow,
    _fusion_far_refs as _fusion_far_refs,
    _fusion_refs as _fusion_refs,
    _hard_mask as _hard_mask,
    _HardMasks as _HardMasks,
    _MaskFile as _MaskFile,
    _prior_refs as _prior_refs,
    _solve_mask as _solve_mask,
    _undistort_of as _undistort_of,
    _user_keep as _user_keep,
    _user_keeps as _user_keeps,
    _user_mask_files as _user_mask_files,
)
from gcvd_flow.stages.frontend import ingest as ingest_mod

# ============================================================================== the pipeline
# The run's whole configuration: ``seed`` plus one section per declared config section.
# (typed Any: the sections are built at import time, mypy cannot see the fields)
GCVDConfig: Any = create_model("GCVDConfig", __config__=ConfigDict(extra="forbid"), seed=(int, 0),  # type: ignore[call-overload]
                               **{name: (model, model()) for name, model in _SECTIONS.items()})


PROFILES: dict[str, dict[str, Any]] = {
    # The paper's / authors' settings (GPU-sized), and the paper's method: no bundle adjustment.
    "paper": {
        "bundle_adjustment": {"enabled": False},
        "association": {"verify": "paper", "per_keyframe": 0, "retrieval": "global", "prewarp_sequential": "on"},
        "ingest": {"long_side": 384, "min_short_frac": 0.0},
        "flow": {"preset": "medium"},
        "optimize_keyframes": {"window": 40, "overlap": 8, "steps": 300, "lr": 2e-4, "points": 1024,
                               "points_by_weight": False, "stop_rel": 0.0, "photo_warp": "pixel", "coarse_points": 0},
        "optimize_edges": {"steps": 300, "lr": 1e-4},
        "optimize_segments": {"steps": 100, "lr": 1e-4, "loss_scale": 1.0, "coarse_points": 0},
    },
    # Accuracy first: the paper's working resolution, everything else the defaults (2026-11-29,
    # docs/benchmarks.md "Working resolution": ICL and KITTI ATE -14 / -33 %, ICL AbsRel -17 %,
    # HoloLens AbsRel -4 % and RPE -13 / -28 % over four turns of the clip, its ATE within its
    # 2-3.5x spread; ICL 2.0x, HoloLens 1.65x the time).
    "quality": {
        "ingest": {"long_side": 384},
    },
    # Quick look / CI: small images, few steps.
    "fast": {
        "ingest": {"long_side": 160},
        "flow": {"preset": "fast"},
        "optimize_keyframes": {"steps": 60},
        "optimize_edges": {"steps": 40},
        "optimize_segments": {"steps": 25},
    },
}


def limit_threads() -> None:
    """Worker processes share the cores: one torch / OpenCV thread each, idle OpenMP threads
    asleep (``gcvd_flow.runtime.quiet_openmp``; workers not started by our CLI, e.g. Dask's)."""
    from gcvd_flow.runtime import quiet_openmp

    quiet_openmp()
    import cv2
    import torch

    torch.set_num_threads(1)
    cv2.setNumThreads(1)


PIPELINE = Pipeline(
    list(_STAGES),
    packages=("gcvd_flow.stages", "gcvd_flow.pipeline"),
    # the blocks' modules: their functions and classes enter a stage's key one by one
    adapters=("gcvd_flow.pipeline",),
    # every third-party library whose code computes a stored result (tests/test_keys.py finds
    # them in the stages' imports); the engine adds its codecs (numpy, Pillow, safetensors)
    numeric_libraries=(("torch", ("torch",)), ("opencv", ("opencv-python-headless", "opencv-python")),
                       ("kornia", ("kornia",)), ("gtsam", ("gtsam",)), ("scipy", ("scipy",))),
    numeric_settings=(("device", "cpu"), ("dtype", "float32"), ("deterministic", True)),
    worker_init=limit_threads,
)

STAGE_NAMES = PIPELINE.names()


def open_source(path: str, config: Any) -> Source:  # config: a GCVDConfig
    import os
    import stat

    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise UsageError(f"{path}: no such file or directory") from None
    except OSError as exc:
        raise UsageError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise UsageError(f"{path}: not a video file or a folder (a device, FIFO or socket cannot be an input)")
    src = _open_source(path)
    p = config.ingest
    n_sel = len(range(len(src.items))[p.start:p.end:p.stride])
    if n_sel < 2:
        raise UsageError(f"{path}: ingest selects {n_sel} frame(s) of {len(src.items)} "
                         f"(start={p.start}, end={p.end}, stride={p.stride}); need at least 2")
    given, origin = _camera(src, p)  # a camera no lens has: one line, exit 2, before anything runs
    w, h = ingest_mod.working_size(src.size[0], src.size[1], p.long_side, p.min_short_frac)
    cam = ingest_mod.make_camera(src.size[0], src.size[1], w, h, None if given is None else given.intrinsics, origin)
    K = cam["K"]
    note = ("not given: the focal length will be estimated from the video (calibrate stage; or pass "
            "--intrinsics fx,fy,cx,cy)" if cam["guessed"] and config.calibrate.mode == "auto" else
            "GUESSED, pass --intrinsics fx,fy,cx,cy for accurate results" if cam["guessed"] else origin)
    note += "" if given is None or not given.distorted else f"; lens {given.describe()}: undistorted at ingest"
    print(f"camera: {src.layout} input {src.size[0]}x{src.size[1]} -> working {w}x{h}, fx={K[0, 0]:.1f} "
          f"fy={K[1, 1]:.1f} cx={K[0, 2]:.1f} cy={K[1, 2]:.1f} ({note})", file=sys.stderr)
    return src


# The run's three parts as benchmarks report them: pre-processing (up to the keyframe optimisation),
# the paper's optimisation (keyframes .. segments) and the depth post-processing, from the order above
# (a stage added anywhere lands in exactly one of them).
_A, _B = STAGE_NAMES.index(OPTIMIZE_KEYFRAMES.name), STAGE_NAMES.index(OPTIMIZE_SEGMENTS.name)
STAGE_GROUPS = {"pre": tuple(STAGE_NAMES[:_A]), "main": tuple(STAGE_NAMES[_A:_B + 1]), "post": tuple(STAGE_NAMES[_B + 1:])}

# What RUN_DIR is written from (and what its readers look up in the cache): the final frames,
# keyframes, poses and depth of the DAG above.
RUN_DIR_SOURCES = run_dir.RunSources(frames=INGEST, keyframes=KEYFRAMES, poses=OPTIMIZE_SEGMENTS, depth=DEPTH_CONSENSUS,
                                     calibration=CALIBRATE)

SPEC = PipelineSpec("gcvd", PIPELINE, GCVDConfig, PROFILES, open_source=open_source,
                    export=functools.partial(run_dir.write_run_dir, sources=RUN_DIR_SOURCES),
                    schema_dir=artifacts_schema.SCHEMA_DIR)
