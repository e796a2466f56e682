"""The GCVD DAG: the one place that wires ``stages/`` into engine stages.

    ingest [map: frame] -> flow [map: pair i,i+1] -> masks [map: frame] -> priors [map: frame]
    -> keyframes -> association -> optimize_keyframes -> optimize_edges -> pose_graph
    -> optimize_segments -> depth_fusion [map: frame] -> depth_filter [map: frame]

Each map item reads exactly the pieces it needs (a frame, its neighbours' flows, ...), so a
trimmed, extended or re-strided clip re-uses every item whose inputs did not change. Config
sections are pydantic models; ``--set section.key=value`` overrides any field.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from stages import ingest as ingest_mod
from stages import steps

from .api import PipelineSpec
from .config import Section
from .dag import Const, ItemRef, MapStage, PartRef, Pipeline, Stage
from .errors import UsageError
from .sources import Source, open_source as _open_source

WEIGHTS = {"file": True}  # marks a path parameter: its content digest enters the key


# ------------------------------------------------------------------------------ config


class IngestParams(Section):
    start: int = Field(0, ge=0, description="first source frame")
    end: int | None = Field(None, description="one past the last source frame (None: all)")
    stride: int = Field(1, ge=1, description="take every stride-th frame")
    long_side: int = Field(256, ge=16, description="working resolution, px of the long side (paper: 384)")
    intrinsics: str | None = Field(None, description="fx,fy,cx,cy at the source resolution")

    @field_validator("intrinsics")
    @classmethod
    def _parse(cls, v: str | None) -> str | None:
        if v is not None:
            ingest_mod.parse_intrinsics(v)
        return v


class FlowParams(Section):
    backend: Literal["dis", "raft"] = "dis"
    preset: Literal["ultrafast", "fast", "medium", "fine"] = Field(
        "fine", description="DIS preset; 'fine' = medium at full resolution (loop clip: ATE 0.06 % vs "
        "0.08 % of the path with 'medium', at ~3.5x the flow time)")
    fb_thresh: float = Field(1.0, gt=0, description="forward-backward consistency, px")
    weights: str | None = Field(None, json_schema_extra=WEIGHTS, description="RAFT weights file")


class MasksParams(Section):
    backend: Literal["motion", "maskrcnn", "motion+maskrcnn", "none"] = Field(
        "motion", description="motion: flow vs. static geometry; maskrcnn: COCO instances of moving "
        "classes (needs weights); motion+maskrcnn: dynamic if either says so")
    dilate: int = Field(5, ge=0)
    span: int = Field(6, ge=1, description="frames spanned by the chained flow (an object moving "
                      "along epipolar lines over 1 frame rarely does over several)")
    weights: str | None = Field(None, json_schema_extra=WEIGHTS, description="Mask R-CNN weights file")
    score_thresh: float = Field(0.5, ge=0, le=1, description="Mask R-CNN detections scoring less are ignored")
    min_size: int = Field(800, ge=32, description="Mask R-CNN input short side, px (torchvision: 800)")

    @model_validator(mode="after")
    def _needs_weights(self) -> "MasksParams":
        if "maskrcnn" in self.backend and not self.weights:
            raise ValueError(f"masks.backend={self.backend} needs masks.weights=FILE "
                             "(torchvision maskrcnn_resnet50_fpn weights, .pth or .safetensors)")
        return self


class PriorsParams(Section):
    backend: Literal["geometric", "midas"] = "geometric"
    span: int = Field(8, ge=1, description="frames between a frame and its reference for triangulation")
    preset: Literal["ultrafast", "fast", "medium", "fine"] = Field(
        "fine", description="DIS preset of the prior's direct flows ('fine': full-resolution "
        "finest level; prior AbsRel 0.058 vs 0.095 with 'medium' on the synthetic loop)")
    fb_thresh: float = Field(1.0, gt=0)
    weights: str | None = Field(None, json_schema_extra=WEIGHTS, description="MiDaS weights file")

    @model_validator(mode="after")
    def _needs_weights(self) -> "PriorsParams":
        if self.backend == "midas" and not self.weights:
            raise ValueError("priors.backend=midas needs priors.weights=FILE "
                             "(MiDaS v2.1 small, .pt or .safetensors)")
        return self


class KeyframesParams(Section):
    enabled: bool = True
    delta: float = Field(0.1, gt=0, description="accumulated flow threshold, fraction of min(H, W)")
    max_gap: int = Field(39, ge=1)


class AssociationParams(Section):
    enabled: bool = True
    backend: Literal["default", "resnet18"] = "default"
    weights: str | None = Field(None, json_schema_extra=WEIGHTS, description="ResNet-18 weights file")
    threshold: float | None = Field(None, description="descriptor similarity threshold (None: backend default)")
    nms: int = 8
    min_separation: int = 8
    min_inlier_ratio: float = 0.5
    min_consistent: float = 0.1

    @model_validator(mode="after")
    def _needs_weights(self) -> "AssociationParams":
        if self.backend == "resnet18" and not self.weights:
            raise ValueError("association.backend=resnet18 needs association.weights=FILE "
                             "(torchvision resnet18, .pth or .safetensors)")
        return self


class DepthParams(Section):
    layer_norm: bool = True
    mesh: bool = True
    mesh_vertices: int = 17


class LossParams(Section):
    grad: bool = True
    w_photo: float = 1.0
    w_flow: float = 10.0
    w_depth: float = 0.5
    w_grad: float = 0.1
    w_mesh: float = 0.5


class OptimizeKeyframesParams(Section):
    window: int = 40
    overlap: int = 8
    steps: int = 150
    lr: float = 2e-4
    pose_lr: float = 5e-4
    mesh_lr_mult: float = 100.0
    loss_scale: float = 0.25
    points: int = 128
    pose_param: Literal["direct", "net"] = "direct"
    init: Literal["essential", "identity"] = "essential"
    checkpoint_every: int = 50
    threads: int = Field(2, ge=1, description="torch threads of the optimisation stages (results "
                         "are bit-identical only for the same count)")


class OptimizeEdgesParams(Section):
    steps: int = 100
    lr: float = 1e-4


class PoseGraphParams(Section):
    enabled: bool = True
    kind: Literal["se3", "sim3"] = "se3"
    max_iterations: int = 100
    loop_weight: float = 1.0
    max_loop_rotation_deg: float = Field(30.0, gt=0, description="loop edges disagreeing more with odometry are ignored")


class OptimizeSegmentsParams(Section):
    steps: int = 60
    lr: float = 1e-4
    loss_scale: float = 0.25
    pair_power: float = 0.5
    grad_mult: float = 5.0
    window: int = 40


class DepthFusionParams(Section):
    enabled: bool = True
    offsets: tuple[int, ...] = Field((-8, 8), description="reference frames (relative "
                                     "index) triangulated against each frame with the final poses")
    preset: Literal["ultrafast", "fast", "medium", "fine"] = "fine"
    fb_thresh: float = Field(1.0, gt=0, description="forward-backward consistency, px")
    min_angle_deg: float = Field(0.2, ge=0, description="smallest usable triangulation angle")
    max_log_dev: float = Field(0.3, gt=0, description="measurements further from the optimised "
                               "depth (|log ratio|) are dropped")


class DepthFilterParams(Section):
    enabled: bool = True
    radius: int = Field(4, ge=0)
    border: int = 4


class GCVDConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    seed: int = 0
    ingest: IngestParams = IngestParams()
    flow: FlowParams = FlowParams()
    masks: MasksParams = MasksParams()
    priors: PriorsParams = PriorsParams()
    keyframes: KeyframesParams = KeyframesParams()
    association: AssociationParams = AssociationParams()
    depth: DepthParams = DepthParams()
    losses: LossParams = LossParams()
    optimize_keyframes: OptimizeKeyframesParams = OptimizeKeyframesParams()
    optimize_edges: OptimizeEdgesParams = OptimizeEdgesParams()
    pose_graph: PoseGraphParams = PoseGraphParams()
    optimize_segments: OptimizeSegmentsParams = OptimizeSegmentsParams()
    depth_fusion: DepthFusionParams = DepthFusionParams()
    depth_filter: DepthFilterParams = DepthFilterParams()


PROFILES: dict[str, dict[str, Any]] = {
    # The paper's / authors' settings (GPU-sized).
    "paper": {
        "ingest": {"long_side": 384},
        "flow": {"preset": "medium"},
        "optimize_keyframes": {"window": 40, "overlap": 8, "steps": 300, "lr": 2e-4, "points": 1024},
        "optimize_edges": {"steps": 300, "lr": 1e-4},
        "optimize_segments": {"steps": 100, "lr": 1e-4, "loss_scale": 1.0},
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


# ------------------------------------------------------------------------------ items


def _camera_intrinsics(src: Source, p: IngestParams) -> tuple[tuple[float, float, float, float] | None, str]:
    if p.intrinsics:
        return ingest_mod.parse_intrinsics(p.intrinsics), "user (--intrinsics)"
    if src.intrinsics is not None:
        return src.intrinsics, src.intrinsics_origin or "dataset"
    return None, "guess"


def _ingest_items(view, p: IngestParams):
    src: Source = view.source
    sel = list(range(len(src.items)))[p.start:p.end:p.stride]
    if len(sel) < 2:
        raise UsageError(f"ingest selects {len(sel)} frame(s) of {len(src.items)} "
                         f"(start={p.start}, end={p.end}, stride={p.stride}); need at least 2")
    return [{"frame": src.items[i], "source_size": Const(list(src.size)),
             "name": Const(src.names[i] if src.names else str(i))} for i in sel]


def _ingest_summary(view, p: IngestParams) -> dict[str, Any]:
    src: Source = view.source
    w, h = ingest_mod.working_size(src.size[0], src.size[1], p.long_side)
    intr, origin = _camera_intrinsics(src, p)
    cam = ingest_mod.make_camera(src.size[0], src.size[1], w, h, intr, origin)
    cam["frame_indices"] = list(range(len(src.items)))[p.start:p.end:p.stride]
    cam["fps"] = src.fps
    cam["layout"] = src.layout
    return cam


def _pairs(view, p):
    return [{"a": ItemRef("ingest", i), "b": ItemRef("ingest", i + 1)} for i in range(view.len("ingest") - 1)]


def _chain_refs(i: int, n: int, span: int) -> dict[str, Any]:
    """Flows from frame i toward a reference `span` frames away: backward (i -> i-1 -> ...),
    or forward for the first `span` frames. Existing items never read later frames once the
    clip has 2*span frames, so extending a clip only adds items."""
    refs: dict[str, Any] = {}
    if i >= span or i >= n - 1 - i:
        refs["direction"] = Const("bwd")
        for k in range(min(span, i)):
            refs[f"chain{k:02d}"] = ItemRef("flow", i - 1 - k)
    else:
        refs["direction"] = Const("fwd")
        for k in range(min(span, n - 1 - i)):
            refs[f"chain{k:02d}"] = ItemRef("flow", i + k)
    return refs


def _mask_items(view, p: MasksParams):
    # The semantic backend reads the frame itself; the motion backend its flows (only).
    n = view.len("ingest")
    out = []
    for i in range(n):
        it: dict[str, Any] = {}
        if p.backend != "maskrcnn":
            it = {"K": PartRef("ingest", ("K",), summary=True), **_chain_refs(i, n, p.span)}
        if "maskrcnn" in p.backend:
            it["image"] = ItemRef("ingest", i)
        out.append(it)
    return out


def _prior_items(view, p: PriorsParams):
    # Reference frames span and span/2 frames back (forward for the first frames): the prior
    # triangulates a direct flow to the reference; chaining adjacent flows drifts ~0.1 px per
    # link, which on ICL turned 2-view poses off by degrees (AbsRel 0.25 vs 0.085 direct).
    n = view.len("ingest")
    out = []
    for i in range(n):
        it: dict[str, Any] = {"image": ItemRef("ingest", i), "K": PartRef("ingest", ("K",), summary=True)}
        if p.backend == "geometric":
            step = -1 if (i >= p.span or i >= n - 1 - i) else 1
            for name, k in (("ref", p.span), ("ref_near", max(1, p.span // 2))):
                j = min(max(i + step * k, 0), n - 1)
                if j != i:
                    it[name] = ItemRef("ingest", j)
        out.append(it)
    return out


def _fusion_items(view, p: DepthFusionParams):
    n = view.len("ingest")
    out = []
    for i in range(n):
        it: dict[str, Any] = {"index": Const(i), "image": ItemRef("ingest", i),
                              "K": PartRef("ingest", ("K",), summary=True),
                              "poses": PartRef("optimize_segments", ("poses",)),
                              "depth": PartRef("optimize_segments", ("depths", i))}
        if p.enabled:
            for k, off in enumerate(p.offsets):
                j = i + off
                if 0 <= j < n and j != i:
                    it[f"ref{k:02d}"] = ItemRef("ingest", j)
                    it[f"index_ref{k:02d}"] = Const(j)
        out.append(it)
    return out


def _filter_items(view, p: DepthFilterParams):
    n = view.len("ingest")
    r = p.radius if p.enabled else 0
    out = []
    for i in range(n):
        lo, hi = max(0, i - r), min(n - 1, i + r)
        it: dict[str, Any] = {"center": Const(i - lo)}
        for k, j in enumerate(range(lo, hi + 1)):
            it[f"d{k:02d}"] = ItemRef("depth_fusion", j)
        for k, j in enumerate(range(lo, hi)):
            it[f"f{k:02d}"] = ItemRef("flow", j)
        out.append(it)
    return out


OPT = ("depth", "losses", "optimize_keyframes")

PIPELINE = Pipeline([
    MapStage("ingest", steps.ingest_frame, params="ingest", kind="frames", items=_ingest_items,
             summary=_ingest_summary, summary_kind="camera", selection_params=("start", "end", "stride", "intrinsics"),
             description="frames at working resolution + camera"),
    MapStage("flow", steps.flow_pair, deps=("ingest",), params="flow", kind="flow", items=_pairs,
             description="forward/backward flow of adjacent pairs + consistency"),
    MapStage("masks", steps.static_mask, deps=("ingest", "flow"), params="masks", kind="mask",
             items=_mask_items, description="1 = static"),
    MapStage("priors", steps.depth_prior, deps=("ingest",), params="priors", kind="prior",
             items=_prior_items, description="MiDaS-shaped relative inverse depth"),
    Stage("keyframes", steps.select_keyframes, deps=("flow", "masks"), params="keyframes", kind="keyframes"),
    Stage("association", steps.associate, deps=("ingest", "keyframes"), params="association", kind="graph"),
    Stage("optimize_keyframes", steps.optimize_keyframes,
          deps=("ingest", "priors", "masks", "keyframes", "association"), params=OPT, kind="keyframe_solution",
          uses_seed=True),
    Stage("optimize_edges", steps.optimize_edges,
          deps=("ingest", "priors", "masks", "association", "optimize_keyframes"),
          params=OPT + ("optimize_edges",), kind="edges", uses_seed=True),
    Stage("pose_graph", steps.pose_graph, deps=("optimize_keyframes", "optimize_edges"), params="pose_graph",
          kind="poses"),
    Stage("optimize_segments", steps.optimize_segments,
          deps=("ingest", "flow", "priors", "masks", "optimize_keyframes", "pose_graph"),
          params=OPT + ("optimize_segments",), kind="segment_solution", uses_seed=True),
    MapStage("depth_fusion", steps.fuse_depth, deps=("ingest", "optimize_segments"), params="depth_fusion",
             kind="depth", items=_fusion_items, description="optimised depth fused with multi-view "
             "triangulation at the final poses"),
    MapStage("depth_filter", steps.filter_depth, deps=("flow", "depth_fusion"), params="depth_filter",
             kind="depth", items=_filter_items),
])

STAGE_NAMES = PIPELINE.names()


# ------------------------------------------------------------------------------ source & export


def open_source(path: str, config: GCVDConfig) -> Source:
    src = _open_source(path)
    p = config.ingest
    n_sel = len(range(len(src.items))[p.start:p.end:p.stride])
    if n_sel < 2:
        raise UsageError(f"{path}: ingest selects {n_sel} frame(s) of {len(src.items)} "
                         f"(start={p.start}, end={p.end}, stride={p.stride}); need at least 2")
    intr, origin = _camera_intrinsics(src, p)
    w, h = ingest_mod.working_size(src.size[0], src.size[1], p.long_side)
    cam = ingest_mod.make_camera(src.size[0], src.size[1], w, h, intr, origin)
    K = cam["K"]
    note = "GUESSED, pass --intrinsics fx,fy,cx,cy for accurate results" if cam["guessed"] else origin
    print(f"camera: {src.layout} input {src.size[0]}x{src.size[1]} -> working {w}x{h}, fx={K[0, 0]:.1f} "
          f"fy={K[1, 1]:.1f} cx={K[0, 2]:.1f} cy={K[1, 2]:.1f} ({note})", file=sys.stderr)
    return src


def write_tum(path: Path, stamps: list[float], poses: np.ndarray) -> None:
    """TUM trajectory: `t tx ty tz qx qy qz qw`, camera-to-world."""
    from scipy.spatial.transform import Rotation

    lines = []
    for t, T in zip(stamps, poses):
        q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x, y, z, w
        if q[3] < 0:
            q = -q
        lines.append(f"{t:.6f} " + " ".join(f"{v:.9f}" for v in (*T[:3, 3], *q)))
    path.write_text("\n".join(lines) + "\n")


def export(out: Path, runner, config: GCVDConfig) -> dict[str, Any]:
    """RUN_DIR: poses.txt (TUM c2w), depth/NNNNNN.npy (float32), cameras.json."""
    frames = runner.value("ingest")
    cam = frames.summary
    idx = list(cam["frame_indices"])
    # only the poses: decoding the whole segment solution would hold every depth map at once
    poses = np.asarray(runner.part("optimize_segments", ("poses",)), np.float64)
    write_tum(out / "poses.txt", [float(i) for i in idx], poses)
    depth_dir = out / "depth"
    depth_dir.mkdir(exist_ok=True)
    for old in depth_dir.glob("*.npy"):
        old.unlink()
    filt = runner.value("depth_filter")
    for k, i in enumerate(idx):
        np.save(depth_dir / f"{i:06d}.npy", np.asarray(filt[k]["depth"], np.float32), allow_pickle=False)
    K = np.asarray(cam["K"])
    doc = {"width": cam["width"], "height": cam["height"], "fx": K[0, 0], "fy": K[1, 1],
           "cx": K[0, 2], "cy": K[1, 2], "K": K.tolist(), "source_width": cam["source_width"],
           "source_height": cam["source_height"], "intrinsics_guessed": cam["guessed"],
           "intrinsics_origin": cam["origin"], "frame_indices": idx, "fps": cam.get("fps"),
           "keyframes": [idx[k] for k in runner.value("keyframes")["indices"]]}
    (out / "cameras.json").write_text(json.dumps(doc, indent=1))
    return {"poses": str(out / "poses.txt"), "depth": str(depth_dir), "cameras": str(out / "cameras.json")}


SPEC = PipelineSpec("gcvd", PIPELINE, GCVDConfig, PROFILES, open_source=open_source, export=export)
