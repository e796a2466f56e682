"""The GCVD pipeline: its configuration and its DAG, one block per stage.

    ingest [map: frame] -> flow [map: pair i,i+1] -> flow_far [map: pair i,j] -> masks [map: frame]
    -> priors [map: frame] (reads flow_far) -> keyframes -> association -> optimize_keyframes
    -> optimize_edges -> pose_graph
    -> bundle_adjustment -> optimize_segments -> depth_fusion [map: frame] (reads flow_far)
    -> depth_filter [map: frame] -> depth_consensus [map: frame]

Each block holds everything about one stage: its parameters (a pydantic section: ``--set
section.key=value``), for a map stage the inputs of each item (typed references: an item of
another stage, a list of them, a part of a whole stage's output, a constant), the function the
engine calls — ``run_<stage>(inputs, params, ctx)``, which unpacks the inputs by the names the
items declared and calls the algorithm in ``stages/`` — and the declaration. Each map item
reads exactly the pieces it needs (a frame, its neighbours' flows, ...), so a trimmed, extended
or re-strided clip re-uses every item whose inputs did not change. Adding a stage is adding a
block here plus its algorithm in ``stages/`` (docs/contributing.md).

Conventions (docs/contributing.md): frames uint8 (H, W, 3) RGB; flows float32 (H, W, 2) px;
poses T_w_c camera-to-world (4, 4) float64; depth float32 (H, W), one global scale.
"""

from __future__ import annotations

import dataclasses
import sys
import typing
from typing import Any, Literal

import numpy as np
from pydantic import ConfigDict, Field, create_model, field_validator, model_validator

import artifacts_schema
from gcvd_flow.engine.api import PipelineSpec
from gcvd_flow.engine.config import Section
from gcvd_flow.engine.dag import Const, ItemRef, MapStage, PartRef, Pipeline, Stage
from gcvd_flow.engine.errors import UsageError
from gcvd_flow.io import run_dir
from gcvd_flow.io.weights import open_model
from gcvd_flow.io.sources import Source, open_source as _open_source
from stages.depth import consensus as depth_consensus
from stages.depth import filter as depth_filter
from stages.depth import fusion as depth_fusion
from stages.frontend import flow
from stages.frontend import ingest as ingest_mod
from stages.frontend import masks as masks_mod
from stages.frontend import priors as priors_mod
from stages.graph import keyframes as keyframes_mod
from stages.optimize import params as opt_params

WEIGHTS = {"file": True}  # marks a path parameter: its content digest enters the key

# What the blocks below declare, in order: the config sections (name -> model) and the stages.
# GCVDConfig and PIPELINE at the end are assembled from them, so adding a stage is one block.
_SECTIONS: dict[str, type[Section]] = {}
_STAGES: list[Stage] = []


def config_section(name: str):
    """Class decorator (or call on a model): ``--set NAME.key=value`` configures this model."""
    def register(model: type[Section]) -> type[Section]:
        _SECTIONS[name] = model
        return model
    return register


def declare(stage: Stage) -> Stage:
    """Add a stage to the pipeline (stages run in the order they are declared)."""
    _STAGES.append(stage)
    return stage


# ============================================================================== ingest
@config_section("ingest")
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


def run_ingest(inputs: dict[str, Any], p: Any, ctx: Any) -> dict[str, Any]:
    """Source frame -> working resolution. Output {image: uint8 (h, w, 3) RGB (PNG)}."""
    rgb = inputs["frame"]
    src_w, src_h = inputs["source_size"]
    if (rgb.shape[1], rgb.shape[0]) != (src_w, src_h):
        raise ingest_mod.FrameError(f"{inputs['name']}: frame size {rgb.shape[1]}x{rgb.shape[0]} differs from "
                         f"the first frame's {src_w}x{src_h}")
    size = ingest_mod.working_size(src_w, src_h, p.long_side)
    return {"image": ingest_mod.prepare_frame(rgb, size)}


INGEST = declare(MapStage("ingest", run_ingest, params="ingest", kind="frames", items=_ingest_items,
                  summary=_ingest_summary, summary_kind="camera",
                  selection_params=("start", "end", "stride", "intrinsics"),
                  description="frames at working resolution + camera"))


# ============================================================================== flow
@config_section("flow")
class FlowParams(Section):
    backend: Literal["dis", "raft"] = "dis"
    preset: Literal["ultrafast", "fast", "medium", "fine"] = Field(
        "fine", description="DIS preset; 'fine' = medium at full resolution (loop clip: ATE 0.06 % vs "
        "0.08 % of the path with 'medium', at ~3.5x the flow time)")
    fb_thresh: float = Field(1.0, gt=0, description="forward-backward consistency, px")
    weights: str | None = Field(None, json_schema_extra=WEIGHTS, description="RAFT weights file")

    @model_validator(mode="after")
    def _needs_weights(self) -> "FlowParams":
        if self.backend == "raft" and not self.weights:
            raise ValueError("flow.backend=raft needs flow.weights=FILE (raft-things, .pth or .safetensors)")
        return self


def _flow_items(view, p: FlowParams):
    return [{"a": ItemRef("ingest", i), "b": ItemRef("ingest", i + 1)} for i in range(view.len("ingest") - 1)]


def _open_raft(p: FlowParams) -> Any:
    return open_model("raft", p.weights)


def run_flow(inputs: dict[str, Any], p: FlowParams, ctx: Any) -> dict[str, Any]:
    """Adjacent pair (i, i+1) -> {fwd, bwd (H, W, 2) float32 px, fwd_valid, bwd_valid bool}."""
    model = ctx.resource("model") if p.backend == "raft" else None
    return flow.compute_pair_flow(inputs["a"]["image"], inputs["b"]["image"], backend=p.backend,
                                  preset=p.preset, fb_thresh=p.fb_thresh, model=model)


FLOW = declare(MapStage("flow", run_flow, deps=("ingest",), params="flow", kind="flow", items=_flow_items,
                resources={"model": _open_raft}, description="forward/backward flow of adjacent pairs + consistency"))


# ============================================================================== flow_far
# Direct DIS flows between frames further apart, computed once per pair for every stage that
# triangulates against a reference: priors (frame i vs i-span and i-span/2, forward for the
# first frames) and depth_fusion (frame i vs i+offset). The pairs are the union of what their
# sections ask for, each item keyed by its two images, preset and threshold only, so changing
# depth_fusion.offsets computes only the new pairs and leaves priors' items cached. Pair (a, b)
# (a < b) holds compute_pair_flow(a, b): frame b's flow to a is its bwd / bwd_valid, exactly
# what compute_pair_flow(b, a) returns as fwd / fwd_valid.
def _prior_refs(i: int, n: int, p: "PriorsParams") -> list[int]:
    """Frame i's prior references: span and span/2 frames back, forward for the first frames."""
    if p.backend != "geometric":
        return []
    step = -1 if (i >= p.span or i >= n - 1 - i) else 1
    js = [min(max(i + step * k, 0), n - 1) for k in (p.span, max(1, p.span // 2))]
    return [j for j in js if j != i]


def _fusion_refs(i: int, n: int, p: "DepthFusionParams") -> list[int]:
    return [i + off for off in p.offsets if 0 <= i + off < n and off != 0] if p.enabled else []


def _fusion_far_refs(i: int, n: int, p: "DepthFusionParams") -> list[int]:
    """Frame i's fusion references whose flow flow_far computes: the adjacent ones (+-1) are the
    flow stage's own pairs, read from there."""
    return [j for j in _fusion_refs(i, n, p) if abs(j - i) != 1]


def _far_pair(i: int, j: int, preset: str, fb_thresh: float) -> tuple[int, int, str, float]:
    return (min(i, j), max(i, j), preset, float(fb_thresh))


def _far_pairs(n: int, b: Any) -> list[tuple[int, int, str, float]]:
    pairs = set()
    for i in range(n):
        pairs.update(_far_pair(i, j, b.priors.preset, b.priors.fb_thresh) for j in _prior_refs(i, n, b.priors))
        pairs.update(_far_pair(i, j, b.depth_fusion.preset, b.depth_fusion.fb_thresh)
                     for j in _fusion_far_refs(i, n, b.depth_fusion))
    return sorted(pairs)


def _flow_far_items(view, b: Any):
    return [{"a": ItemRef("ingest", a), "b": ItemRef("ingest", c), "preset": Const(preset),
             "fb_thresh": Const(fb)} for a, c, preset, fb in _far_pairs(view.len("ingest"), b)]


def _flow_far_summary(view, b: Any) -> dict[str, Any]:
    return {"pairs": [list(pr) for pr in _far_pairs(view.len("ingest"), b)]}


def _far_index(view) -> dict[tuple, int]:
    """flow_far's pairs (a, b, preset, fb_thresh) -> item index, from its summary."""
    return {tuple(pr): k for k, pr in enumerate(view.summary("flow_far")["pairs"])}


def _far_refs(index: dict[tuple, int], i: int, js: list[int], preset: str, fb_thresh: float) -> dict[str, Any]:
    """Item inputs reading frame i's flows to frames js from flow_far: refs (the pair items)
    and ref_dirs ("fwd": i is the pair's first frame, "bwd": its second)."""
    return {"refs": [ItemRef("flow_far", index[_far_pair(i, j, preset, fb_thresh)]) for j in js],
            "ref_dirs": Const(["fwd" if i < j else "bwd" for j in js])}


def run_flow_far(inputs: dict[str, Any], b: Any, ctx: Any) -> dict[str, Any]:
    """Pair (a, b), a < b -> {fwd, bwd (H, W, 2) float32 px, fwd_valid, bwd_valid bool} (DIS)."""
    return flow.compute_pair_flow(inputs["a"]["image"], inputs["b"]["image"], preset=inputs["preset"],
                                  fb_thresh=inputs["fb_thresh"])


def _far_flow(fl: dict[str, Any], direction: str) -> tuple[np.ndarray, np.ndarray]:
    """A flow_far item seen from one of its frames: (flow to the other frame, its valid mask)."""
    if direction == "fwd":
        return np.asarray(fl["fwd"]), np.asarray(fl["fwd_valid"], bool)
    return np.asarray(fl["bwd"]), np.asarray(fl["bwd_valid"], bool)


FLOW_FAR = declare(MapStage("flow_far", run_flow_far, deps=("ingest",), params=("priors", "depth_fusion"),
                   kind="flow_far", items=_flow_far_items, summary=_flow_far_summary,
                   selection_params=("priors", "depth_fusion"),
                   description="direct flows of the pairs priors and depth_fusion triangulate, once per pair"))


# ============================================================================== masks
@config_section("masks")
class MasksParams(Section):
    backend: Literal["motion", "maskrcnn", "motion+maskrcnn", "none"] = Field(
        "motion", description="motion: flow vs. static geometry; maskrcnn: COCO instances of moving "
        "classes (needs weights); motion+maskrcnn: dynamic if either says so")
    dilate: int = Field(5, ge=0)
    texture_frac: float = Field(1.0, ge=0, description="motion evidence is scaled down where the image's "
                                "Shi-Tomasi texture is below this x its median (flow there is interpolated, "
                                "not measured); 0 = off. Static real walk-through: 4.1 % of pixels flagged "
                                "-> 0.9 % (with sigma_mult 5), moving-object IoU 0.459 -> 0.454")
    sigma_mult: float = Field(5.0, gt=0, description="a pixel moves when its epipolar residual exceeds "
                              "median + sigma_mult x robust sigma (4 until 2026-11-25)")
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


def _chain_refs(i: int, n: int, span: int) -> dict[str, Any]:
    """Flows from frame i toward a reference `span` frames away: backward (i -> i-1 -> ...),
    or forward for the first `span` frames. Existing items never read later frames once the
    clip has 2*span frames, so extending a clip only adds items."""
    refs: dict[str, Any] = {}
    if i >= span or i >= n - 1 - i:
        refs["direction"] = Const("bwd")
        refs["chain"] = [ItemRef("flow", i - 1 - k) for k in range(min(span, i))]
    else:
        refs["direction"] = Const("fwd")
        refs["chain"] = [ItemRef("flow", i + k) for k in range(min(span, n - 1 - i))]
    return refs


def _mask_items(view, p: MasksParams):
    # The semantic backend reads the frame itself; the motion backend its flows (only).
    n = view.len("ingest")
    out = []
    for i in range(n):
        it: dict[str, Any] = {}
        if p.backend != "maskrcnn":
            it = {"K": PartRef("ingest", ("K",), summary=True), **_chain_refs(i, n, p.span)}
        if "maskrcnn" in p.backend or (p.backend != "none" and p.texture_frac > 0):
            it["image"] = ItemRef("ingest", i)
        out.append(it)
    return out


def _open_maskrcnn(p: MasksParams) -> Any:
    return open_model("maskrcnn", p.weights, min_size=p.min_size)


def run_masks(inputs: dict[str, Any], p: MasksParams, ctx: Any) -> dict[str, Any]:
    """Frame i -> {static: uint8 (H, W), 1 = static, solve: uint8 (H, W), 1 = static and flow the
    optimisations trust}, from its adjacent and chained flows (backend motion), its image's Mask
    R-CNN instances of moving classes (maskrcnn), or both (motion+maskrcnn: static where both say
    static)."""
    semantic = None
    if "maskrcnn" in p.backend:
        from stages.models.maskrcnn import semantic_static_mask

        semantic = semantic_static_mask(ctx.resource("model"), inputs["image"]["image"],
                                        score_thresh=p.score_thresh, dilate=p.dilate)
        if p.backend == "maskrcnn":
            return {"static": semantic, "solve": semantic}
    fwd = inputs["direction"] == "fwd"
    chain = [(fl["fwd"], fl["fwd_valid"]) if fwd else (fl["bwd"], fl["bwd_valid"]) for fl in inputs["chain"]]
    h, w = chain[0][0].shape[:2]
    if p.backend == "none":
        return {"static": np.ones((h, w), np.uint8), "solve": np.ones((h, w), np.uint8)}
    neighbours = [chain[0]]
    if len(chain) > 1:
        neighbours.append(flow.chain_flows(chain))
    image = inputs["image"]["image"] if p.texture_frac > 0 else None
    motion, solve = masks_mod.motion_masks(np.asarray(inputs["K"]), neighbours, image=image, dilate=p.dilate,
                                           sigma_mult=p.sigma_mult, texture_frac=p.texture_frac)
    if semantic is not None:
        motion, solve = np.minimum(motion, semantic), np.minimum(solve, semantic)
    return {"static": motion, "solve": solve}


def _solve_mask(item: dict[str, Any]) -> np.ndarray:
    """The mask the optimisations use: ``solve`` (static and flow agreeing with the static scene),
    ``static`` for a mask item without it."""
    return np.asarray(item.get("solve", item["static"]))


MASKS = declare(MapStage("masks", run_masks, deps=("ingest", "flow"), params="masks", kind="mask",
                 items=_mask_items, resources={"model": _open_maskrcnn}, description="1 = static"))


# ============================================================================== priors
@config_section("priors")
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


def _prior_items(view, p: PriorsParams):
    # Reference frames span and span/2 frames back (forward for the first frames): the prior
    # triangulates a direct flow to the reference; chaining adjacent flows drifts ~0.1 px per
    # link, which on ICL turned 2-view poses off by degrees (AbsRel 0.25 vs 0.085 direct).
    # The direct flows are flow_far's items (shared with depth_fusion).
    n = view.len("ingest")
    index = _far_index(view) if p.backend == "geometric" else {}
    out = []
    for i in range(n):
        it: dict[str, Any] = {"image": ItemRef("ingest", i), "K": PartRef("ingest", ("K",), summary=True)}
        js = _prior_refs(i, n, p)
        if js:
            it.update(_far_refs(index, i, js, p.preset, p.fb_thresh))
        out.append(it)
    return out


def _open_midas(p: PriorsParams) -> Any:
    return open_model("midas", p.weights)


def run_priors(inputs: dict[str, Any], p: PriorsParams, ctx: Any) -> dict[str, Any]:
    """Frame i -> {inv_depth float32 (H, W) median 1, confidence float32 (H, W)}."""
    image = inputs["image"]["image"]
    if p.backend == "midas":
        from stages.models.midas import midas_prior

        inv = midas_prior(ctx.resource("model"), image)
        return {"inv_depth": inv.astype(np.float32), "confidence": np.ones_like(inv, np.float32)}
    K = np.asarray(inputs["K"])
    # direct flows to the far reference (more parallax) and the near one (sees what the far
    # one lost); the prior fuses both (stages.frontend.priors.geometric_prior)
    flows = []
    for fl, direction in zip(inputs.get("refs", []), inputs.get("ref_dirs", [])):
        fwd, valid = _far_flow(fl, direction)
        if valid.mean() >= priors_mod.MIN_VALID_FRACTION:
            flows.append((fwd, valid))
    out = priors_mod.geometric_prior(image, K, flows[:1], extra=flows[1:]) if flows else None
    if out is None:
        h, w = image.shape[:2]
        out = {"inv_depth": np.ones((h, w), np.float32), "confidence": np.zeros((h, w), np.float32)}
    return {"inv_depth": out["inv_depth"].astype(np.float32),
            "confidence": out["confidence"].astype(np.float32)}


PRIORS = declare(MapStage("priors", run_priors, deps=("ingest", "flow_far"), params="priors", kind="prior",
                  items=_prior_items, resources={"model": _open_midas},
                  description="MiDaS-shaped relative inverse depth"))


# ============================================================================== keyframes
@config_section("keyframes")
class KeyframesParams(Section):
    enabled: bool = True
    delta: float = Field(0.1, gt=0, description="accumulated flow threshold, fraction of min(H, W)")
    max_gap: int = Field(39, ge=1)


def run_keyframes(inputs: dict[str, Any], p: Any, ctx: Any) -> dict[str, Any]:
    """All frames -> {indices, accumulated, threshold_px, motion} (JSON)."""
    flows, masks_ = inputs["flow"], inputs["masks"]
    n = len(masks_)
    motion = [keyframes_mod.pair_motion(flows[i]["fwd"], flows[i]["fwd_valid"], _solve_mask(masks_[i]))
              for i in range(n - 1)]
    h, w = masks_[0]["static"].shape
    if not p.enabled:  # ablation "w/o keyframes": every frame is a keyframe
        return {"indices": list(range(n)), "accumulated": [0.0] * n, "threshold_px": 0.0,
                "motion": motion, "enabled": False}
    sel = keyframes_mod.select_keyframes(np.asarray(motion), h, w, delta=p.delta, max_gap=p.max_gap)
    return {"indices": [int(i) for i in sel["indices"]],
            "accumulated": [float(a) for a in sel["accumulated"]],
            "threshold_px": float(sel["threshold_px"]), "motion": [float(m) for m in motion],
            "enabled": True}


KEYFRAMES = declare(Stage("keyframes", run_keyframes, deps=("flow", "masks"), params="keyframes", kind="keyframes"))


# ============================================================================== association
@config_section("association")
class AssociationParams(Section):
    enabled: bool = True
    backend: Literal["default", "resnet18"] = "default"
    weights: str | None = Field(None, json_schema_extra=WEIGHTS, description="ResNet-18 weights file")
    threshold: float | None = Field(None, description="descriptor similarity threshold (None: backend default)")
    nms: int = 8
    min_separation: int = 8
    min_inlier_ratio: float = 0.5
    min_consistent: float = 0.1
    per_keyframe: int = Field(0, ge=0, description="candidates also: each keyframe's most similar eligible "
                              "partners (a revisit lasting several keyframes gives several loop edges); 0: NMS only (default: "
                              "the extra, wider edges moved the synthetic loop's pose graph 1.00 -> 1.28 mm and "
                              "the real walk-through's bundle adjustment by noise, 0.0536 -> 0.0517 m)")
    max_candidates: int = Field(40, ge=0, description="loop candidates verified at most (the most similar)")
    verify: Literal["geometric", "paper"] = Field(
        "geometric", description="loop verification: geometric (essential-matrix inliers and the dense flow "
        "agreeing with them; accepts wide-baseline revisits) or paper (mean flow <= the keyframe threshold)")
    min_inliers: int = Field(20, ge=5, description="geometric: essential-matrix (or homography) inliers a loop "
                             "needs (real revisit at 256x170: 24-42; KITTI forward-motion look-alikes at 256x78, "
                             "whose edges wrecked its pose graph (keyframe ATE 0.74 -> 3.46 m): 15-17)")
    min_epipolar: float = Field(0.5, ge=0, le=1, description="geometric: share of consistent flow within 2 px "
                                "of the matches' epipolar geometry")

    @model_validator(mode="after")
    def _needs_weights(self) -> "AssociationParams":
        if self.backend == "resnet18" and not self.weights:
            raise ValueError("association.backend=resnet18 needs association.weights=FILE "
                             "(torchvision resnet18, .pth or .safetensors)")
        return self


def _open_resnet(p: AssociationParams) -> Any:
    return open_model("resnet18", p.weights)


def run_association(inputs: dict[str, Any], p: Any, ctx: Any) -> dict[str, Any]:
    """Keyframes -> {graph (JSON), edge_flows [{i, j, fwd, bwd, fwd_valid, bwd_valid}]}."""
    # heavy (torch / gtsam / scipy): imported when the stage runs, not when the CLI starts
    from stages.graph import association as association_mod

    kf = inputs["keyframes"]["indices"]
    frames = inputs["ingest"]
    K = np.asarray(frames.summary["K"])
    images = [frames[i]["image"] for i in kf]
    kw: dict[str, Any] = dict(nms=p.nms, min_separation=p.min_separation,
                              min_inlier_ratio=p.min_inlier_ratio, min_consistent=p.min_consistent,
                              verify=p.verify, min_inliers=p.min_inliers, min_epipolar=p.min_epipolar,
                              per_keyframe=p.per_keyframe, max_candidates=p.max_candidates)
    if p.threshold is not None:
        kw["similarity_threshold"] = p.threshold
    if p.backend == "resnet18":
        from stages.models.resnet import resnet_descriptor

        model = ctx.resource("model")
        kw["descriptor_fn"] = lambda img: resnet_descriptor(model, img)
    if not p.enabled:
        kw["descriptors"] = np.eye(len(kf), dtype=np.float32)  # nothing similar: no loop edges
        kw["similarity_threshold"] = 2.0
    graph, edge_flows = association_mod.build_graph(kf, images, K, inputs["keyframes"]["threshold_px"] or 1e9,
                                                    call_map=ctx.map, **kw)
    flows_out = [{"i": int(a), "j": int(b), **{k: v for k, v in fl.items() if k in ("fwd", "bwd", "fwd_valid", "bwd_valid")}}
                 for (a, b), fl in sorted(edge_flows.items())]
    return {"graph": graph, "edge_flows": flows_out}


ASSOCIATION = declare(Stage("association", run_association, deps=("ingest", "keyframes"), params="association",
                    kind="graph", resources={"model": _open_resnet}))


# ============================================================================== optimisation: shared
def section_from_dataclass(cls: type, name: str) -> type[Section]:
    """A config section (pydantic, ``Section``) with the fields of a parameter dataclass of
    ``stages.optimize.params``: same names, types and defaults; ``metadata`` gives each field's
    description and constraints (``ge``, ``gt``, ...). The parameters are declared only there."""
    hints = typing.get_type_hints(cls)
    fields: dict[str, Any] = {
        f.name: (hints[f.name], Field(f.default, **dict(f.metadata))) for f in dataclasses.fields(cls)
    }
    return create_model(name, __base__=Section, __module__=__name__, __doc__=cls.__doc__, **fields)


DepthParams = config_section("depth")(section_from_dataclass(opt_params.DepthModel, "DepthParams"))
LossParams = config_section("losses")(section_from_dataclass(opt_params.LossWeights, "LossParams"))
OptimizeKeyframesParams = config_section("optimize_keyframes")(section_from_dataclass(opt_params.KeyframeSettings, "OptimizeKeyframesParams"))
OptimizeEdgesParams = config_section("optimize_edges")(section_from_dataclass(opt_params.EdgeSettings, "OptimizeEdgesParams"))
OptimizeSegmentsParams = config_section("optimize_segments")(section_from_dataclass(opt_params.SegmentSettings, "OptimizeSegmentsParams"))

# the sections every optimisation stage reads (optimize_keyframes also holds the shared solver
# settings: pose_lr, mesh_lr_mult, mesh_shape_lr_frac, points, taus, flow_taus, threads, ...)
OPT = ("depth", "losses", "optimize_keyframes")


def _stack(items: Any, indices: list[int], field: str) -> np.ndarray:
    return np.stack([np.asarray(items[i][field]) for i in indices])


def _flow_dict(fl: dict[str, Any]) -> dict[str, np.ndarray]:
    return {k: np.asarray(fl[k]) for k in ("fwd", "bwd", "fwd_valid", "bwd_valid")}


def _inv(T: np.ndarray) -> np.ndarray:
    return np.linalg.inv(np.asarray(T, np.float64))


# ============================================================================== optimize_keyframes
def run_optimize_keyframes(inputs: dict[str, Any], b: Any, ctx: Any) -> dict[str, Any]:
    """Keyframe windows -> {keyframes, poses (K,4,4) T_w_c, depths [K x (H,W)],
    rel_poses [{a, b, tau, T_b_a = inv(T_w_b) @ T_w_a}], state}."""
    # heavy (torch / gtsam / scipy): imported when the stage runs, not when the CLI starts
    from stages.optimize import keyframes as opt_keyframes

    kf = list(inputs["keyframes"]["indices"])
    frames = inputs["ingest"]
    pos = {f: k for k, f in enumerate(kf)}
    pair_flows = {}
    for e in inputs["association"]["edge_flows"]:
        a, c = pos.get(e["i"]), pos.get(e["j"])
        if a is not None and c is not None and c == a + 1:
            pair_flows[(a, c)] = _flow_dict(e)
    missing = [k for k in range(len(kf) - 1) if (k, k + 1) not in pair_flows]
    if missing:
        raise RuntimeError(f"association has no flow for consecutive keyframe pairs {missing[:5]}")
    res = opt_keyframes.optimize_keyframes(
        _stack(frames, kf, "image"), _stack(inputs["priors"], kf, "inv_depth"),
        np.stack([_solve_mask(inputs["masks"][i]) for i in kf]), np.asarray(frames.summary["K"]), pair_flows,
        depth=b.depth, losses=b.losses, kf=b.optimize_keyframes, seed=ctx.seed, checkpointer=ctx.checkpointer,
        window_map=ctx.map)  # schedule=independent: the windows side by side on the run's workers
    return {"keyframes": kf, "poses": np.asarray(res["poses"], np.float64),
            "depths": [np.asarray(d, np.float32) for d in res["depths"]],
            "rel_poses": [{"a": int(r["a"]), "b": int(r["b"]), "tau": int(r["tau"]),
                           "T_b_a": np.asarray(r["T_b_a"], np.float64)} for r in res["rel_poses"]],
            "state": {k: np.asarray(v) for k, v in res["state"].items()}}


OPTIMIZE_KEYFRAMES = declare(Stage("optimize_keyframes", run_optimize_keyframes,
                           deps=("ingest", "priors", "masks", "keyframes", "association"), params=OPT,
                           kind="keyframe_solution", uses_seed=True))


# ============================================================================== optimize_edges
def run_optimize_edges(inputs: dict[str, Any], b: Any, ctx: Any) -> dict[str, Any]:
    """Verified non-sequential keyframe pairs -> {edges: [{a, b, i, j, T_b_a, loss}]}, a, b keyframe
    positions, i, j frame indices, T_b_a = inv(T_w_b) @ T_w_a (camera a -> camera b coordinates)."""
    # heavy (torch / gtsam / scipy): imported when the stage runs, not when the CLI starts
    from stages.optimize import edges as opt_edges

    okf = inputs["optimize_keyframes"]
    kf = list(okf["keyframes"])
    pos = {f: k for k, f in enumerate(kf)}
    T_w_k = np.asarray(okf["poses"])
    frames, priors_, masks_ = inputs["ingest"], inputs["priors"], inputs["masks"]
    K = np.asarray(frames.summary["K"])
    flows = {(e["i"], e["j"]): _flow_dict(e) for e in inputs["association"]["edge_flows"]}
    graph_edges = [(int(e["i"]), int(e["j"])) for e in inputs["association"]["graph"].get("nonsequential_edges", [])]

    def calls():  # built lazily: only the edges in flight are in memory
        for n, (i, j) in enumerate(graph_edges):
            yield dict(img_a=frames[i]["image"], img_b=frames[j]["image"], prior_a=priors_[i]["inv_depth"],
                       prior_b=priors_[j]["inv_depth"], mask_a=_solve_mask(masks_[i]), mask_b=_solve_mask(masks_[j]), K=K,
                       flow=flows[(i, j)], init_T_b_a=_inv(T_w_k[pos[j]]) @ T_w_k[pos[i]], depth=b.depth,
                       losses=b.losses, kf=b.optimize_keyframes, edge=b.optimize_edges, seed=ctx.seed + n)

    edges = []
    # the edges are independent: side by side on the run's workers (same result wherever)
    for (i, j), res in zip(graph_edges, ctx.map(opt_edges.optimize_edge_call, calls())):
        edges.append({"a": pos[i], "b": pos[j], "i": i, "j": j, "T_b_a": np.asarray(res["T_b_a"], np.float64),
                      "loss": float(res["loss"])})
    return {"edges": edges}


OPTIMIZE_EDGES = declare(Stage("optimize_edges", run_optimize_edges,
                       deps=("ingest", "priors", "masks", "association", "optimize_keyframes"),
                       params=OPT + ("optimize_edges",), kind="edges", uses_seed=True))


# ============================================================================== pose_graph
@config_section("pose_graph")
class PoseGraphParams(Section):
    enabled: bool = True
    kind: Literal["se3", "sim3"] = "se3"
    max_iterations: int = 100
    loop_weight: float = 1.0
    max_loop_rotation_deg: float = Field(30.0, gt=0, description="loop edges disagreeing more with odometry are ignored")


def run_pose_graph(inputs: dict[str, Any], p: Any, ctx: Any) -> dict[str, Any]:
    """Keyframe poses + sequential and loop edges -> globally consistent keyframe poses."""
    # heavy (torch / gtsam / scipy): imported when the stage runs, not when the CLI starts
    from stages.optimize import pose_graph as pose_graph_mod

    okf = inputs["optimize_keyframes"]
    T_w_k = np.asarray(okf["poses"], np.float64)
    if not p.enabled or len(T_w_k) < 2:
        return {"poses": T_w_k, "enabled": False, "iterations": 0, "initial_error": 0.0, "final_error": 0.0}
    # the optimisations give T_b_a = inv(T_w_b) @ T_w_a; the pose graph measures T_a_b = inv(T_w_a) @ T_w_b
    edges = [{"a": r["a"], "b": r["b"], "T_a_b": _inv(r["T_b_a"]), "weight": 1.0 / r["tau"]} for r in okf["rel_poses"]]
    rejected = []
    for e in inputs["optimize_edges"]["edges"]:
        T_a_b = _inv(e["T_b_a"])
        # Gate gross outliers: drift bends a trajectory by degrees, not tens of degrees, so a
        # loop measurement that disagrees that much with odometry is a failed edge optimisation.
        T_a_b_odo = np.linalg.inv(T_w_k[e["a"]]) @ T_w_k[e["b"]]
        dR = T_a_b_odo[:3, :3].T @ T_a_b[:3, :3]
        angle = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
        if angle > p.max_loop_rotation_deg:
            rejected.append({"i": e["i"], "j": e["j"], "rotation_disagreement_deg": angle})
            continue
        edges.append({"a": e["a"], "b": e["b"], "T_a_b": T_a_b, "weight": p.loop_weight})
    if rejected:
        ctx.log(f"ignored {len(rejected)} loop edge(s) disagreeing with odometry by > {p.max_loop_rotation_deg} deg")
    res = pose_graph_mod.optimize_pose_graph(T_w_k, edges, kind=p.kind, max_iterations=p.max_iterations)
    return {"poses": np.asarray(res["poses"], np.float64), "enabled": True,
            "iterations": int(res["iterations"]), "initial_error": float(res["initial_error"]),
            "final_error": float(res["final_error"]), "rejected_loops": rejected}


POSE_GRAPH = declare(Stage("pose_graph", run_pose_graph, deps=("optimize_keyframes", "optimize_edges"),
                   params="pose_graph", kind="poses"))


# ============================================================================== bundle_adjustment
@config_section("bundle_adjustment")
class BundleAdjustmentParams(Section):
    enabled: bool = Field(True, description="refine keyframe poses over flow tracks (robust reprojection "
                          "factors) after the pose graph")
    stride: int = Field(12, ge=2, description="px between track starts in every keyframe")
    track_length: int = Field(16, ge=2, description="keyframes a track follows at most (plus one hop "
                              "across each loop edge); 8 until 2026-11-25 (real walk-through, keyframe ATE "
                              "0.0813 -> 0.0536 m with the weak prior below)")
    min_views: int = Field(3, ge=2, description="keyframes that must see a point")
    robust_px: float = Field(0.3, gt=0, description="Cauchy scale of the reprojection error, px")
    # The prior only fixes the global scale (monocular BA has none); 0.05 (until 2026-11-25) held
    # the pose graph's scale drift in place: on the real walk-through the first 20 frames stayed 2.4x
    # too small and the keyframe ATE 0.131 m; at 2 / 2: 0.0536 m, per-window scale 0.95-1.10
    prior_rot_sigma: float = Field(2.0, gt=0, description="weak prior to the pose graph, rad")
    prior_trans_frac: float = Field(2.0, gt=0, description="weak prior to the pose graph, x median depth")
    max_iterations: int = Field(30, ge=1)
    consistent_px: float = Field(0.25, ge=0, description="keep the pose graph's poses when they already "
                                 "reproject the tracks to this median error, px (flow noise, no drift)")
    solver: Literal["schur", "gtsam"] = Field("schur", description="Levenberg-Marquardt of the same cost: "
                                              "'schur' (numpy, analytic Jacobians, landmarks eliminated by the "
                                              "Schur complement; ~10x faster) or 'gtsam' (gtsam_unstable's "
                                              "inverse-depth factors, numerical derivatives; the reference)")


def run_bundle_adjustment(inputs: dict[str, Any], p: BundleAdjustmentParams, ctx: Any) -> dict[str, Any]:
    """Pose-graph keyframe poses -> {poses (K, 4, 4) T_w_k refined over flow tracks, statistics}."""
    pg = inputs["pose_graph"]
    T_w_k = np.asarray(pg["poses"], np.float64)
    if not p.enabled:
        return {"poses": T_w_k, "enabled": False, "depth_scale": np.ones(len(T_w_k))}
    # heavy (torch / gtsam / scipy): imported when the stage runs, not when the CLI starts
    from stages.optimize import bundle_adjustment as ba_mod

    from threadpoolctl import threadpool_limits

    from gcvd_flow.io.native_output import native_stdout_silenced

    okf = inputs["optimize_keyframes"]
    edges = {(int(e["i"]), int(e["j"])): _flow_dict(e) for e in inputs["association"]["edge_flows"]}
    # numpy's OpenBLAS on one thread: its idle threads spin (OMP_WAIT_POLICY does not reach its
    # pthreads), so two runs adjusting at once on two cores took 55 s instead of 1.6; a second
    # thread bought nothing alone (2.4 vs 2.4 s), and one thread makes the result independent of
    # the machine's core count (OpenBLAS's default thread count changed the poses' bits)
    with native_stdout_silenced(), threadpool_limits(limits=1, user_api="blas"):
        res = ba_mod.bundle_adjust(T_w_k, [np.asarray(d) for d in okf["depths"]], edges, list(okf["keyframes"]),
                                   np.asarray(inputs["ingest"].summary["K"]), stride=p.stride,
                                   track_length=p.track_length, min_views=p.min_views, robust_px=p.robust_px,
                                   prior_rot_sigma=p.prior_rot_sigma, prior_trans_frac=p.prior_trans_frac,
                                   max_iterations=p.max_iterations, consistent_px=p.consistent_px,
                                   solver=p.solver)
    ctx.log(f"{res['landmarks']} tracks, {res['observations']} observations, median reprojection error "
            f"{res['initial_median_px']:.2f} -> {res['final_median_px']:.2f} px"
            + (" (poses kept: already consistent with the tracks)" if res["skipped"] and res["landmarks"] else ""))
    return {"poses": np.asarray(res["poses"], np.float64), "enabled": True, "landmarks": res["landmarks"],
            "observations": res["observations"], "initial_median_px": res["initial_median_px"],
            "final_median_px": res["final_median_px"], "iterations": res["iterations"],
            "skipped": bool(res["skipped"]), "depth_scale": np.asarray(res["depth_scale"], np.float64)}


BUNDLE_ADJUSTMENT = declare(Stage("bundle_adjustment", run_bundle_adjustment,
                                  deps=("ingest", "association", "optimize_keyframes", "pose_graph"),
                                  params="bundle_adjustment", kind="poses"))


# ============================================================================== optimize_segments
class _FlowDicts:
    """flows[i] -> the arrays of pair (i, i+1)'s flow."""

    def __init__(self, items: Any):
        self._items = items

    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, i: int) -> dict[str, np.ndarray]:
        return _flow_dict(self._items[i])


class _ScaledDepths:
    """depths[k] * scale[k] on access: the keyframe depths in bundle adjustment's scale without
    a second copy of all of them."""

    def __init__(self, depths: Any, scale: np.ndarray):
        self._depths, self._scale = depths, scale

    def __len__(self) -> int:
        return len(self._depths)

    def __getitem__(self, k: int) -> np.ndarray:
        return np.asarray(self._depths[k], np.float32) * self._scale[k]


def run_optimize_segments(inputs: dict[str, Any], b: Any, ctx: Any) -> dict[str, Any]:
    """All frames with keyframe poses frozen -> {poses (N,4,4) T_w_c, depths [N x (H,W)]}.

    The windows are solved side by side on the run's worker processes (``ctx.map``; the result
    does not depend on where). Images, priors and masks are read one window at a time (lazily
    stacked fields) and flows through a window-sized cache of decoded items, and each window's
    depth maps go to the store as soon as they are final (``ctx.put``): memory stays flat in the
    clip length (at 256x192 one flow pair is ~0.9 MB, one depth map 0.19 MB)."""
    # heavy (torch / gtsam / scipy): imported when the stage runs, not when the CLI starts
    from stages.optimize import segments as opt_segments

    frames, flows = inputs["ingest"], inputs["flow"]
    okf, ba = inputs["optimize_keyframes"], inputs["bundle_adjustment"]
    res = opt_segments.optimize_segments(
        frames.field("image"), inputs["priors"].field("inv_depth"), inputs["masks"].field("solve"),
        np.asarray(frames.summary["K"]), _FlowDicts(flows.recent(48)), list(okf["keyframes"]),
        np.asarray(ba["poses"]), _ScaledDepths(okf["depths"], np.asarray(ba["depth_scale"], np.float32)),
        depth=b.depth, losses=b.losses, kf=b.optimize_keyframes, seg=b.optimize_segments,
        seed=ctx.seed, checkpointer=ctx.checkpointer, state=okf["state"], depth_sink=lambda i, d: ctx.put(d),
        window_map=ctx.map)
    # depths: one handle per frame, each depth map stored when its window finished
    return {"poses": np.asarray(res["poses"], np.float64), "depths": res["depths"]}


OPTIMIZE_SEGMENTS = declare(Stage("optimize_segments", run_optimize_segments,
                          deps=("ingest", "flow", "priors", "masks", "optimize_keyframes", "bundle_adjustment"),
                          params=OPT + ("optimize_segments",), kind="segment_solution", uses_seed=True))


# ============================================================================== depth_fusion
@config_section("depth_fusion")
class DepthFusionParams(Section):
    enabled: bool = True
    offsets: tuple[int, ...] = Field((-8, -4, -2, -1, 1, 2, 4, 8), description="reference frames (relative "
                                     "index) triangulated against each frame with the final poses; +-1 "
                                     "are the flow stage's pairs and +-4 the priors' (no new flow). Was "
                                     "(-8, 8) until 2026-11-25: on a wide-baseline real walk-through frames 8 "
                                     "apart rarely overlap (confident share 0.3 % -> 48 %, AbsRel 0.167 -> "
                                     "0.143; ICL 74 % -> 97 %, AbsRel 0.0493 -> 0.0487)")
    preset: Literal["ultrafast", "fast", "medium", "fine"] = "fine"
    fb_thresh: float = Field(1.0, gt=0, description="forward-backward consistency, px")
    min_angle_deg: float = Field(0.2, ge=0, description="smallest usable triangulation angle")
    max_log_dev: float = Field(0.6, gt=0, description="measurements further from the optimised "
                               "depth (|log ratio|) are dropped (0.3 until 2026-11-24: AbsRel ICL "
                               "0.0530 -> 0.0523, loop 0.0419 -> 0.0405)")
    agree_log_dev: float = Field(0.3, gt=0, description="measurements within this of the optimised "
                                 "depth count as agreeing in the confidence")
    coverage_refs: int = Field(2, ge=1, description="agreeing references that give a pixel full coverage "
                               "in the confidence (with two offsets: agreeing / references)")


def _fusion_items(view, p: DepthFusionParams):
    # the flows to the references are flow_far's items (shared with priors)
    n = view.len("ingest")
    index = _far_index(view) if p.enabled else {}
    out = []
    for i in range(n):
        far = _fusion_far_refs(i, n, p)
        near = [j for j in _fusion_refs(i, n, p) if abs(j - i) == 1]
        refs = _far_refs(index, i, far, p.preset, p.fb_thresh)
        # adjacent references: the flow stage's pair (i, i+1) seen from i (fwd) or from i+1 (bwd)
        refs["refs"] += [ItemRef("flow", min(i, j)) for j in near]
        refs["ref_dirs"] = Const(refs["ref_dirs"].value + ["fwd" if j > i else "bwd" for j in near])
        out.append({"index": Const(i), "K": PartRef("ingest", ("K",), summary=True),
                    "poses": PartRef("optimize_segments", ("poses",)),
                    "depth": PartRef("optimize_segments", ("depths", i)),
                    **refs, "ref_indices": Const(far + near)})
    return out


def run_depth_fusion(inputs: dict[str, Any], p: DepthFusionParams, ctx: Any) -> dict[str, Any]:
    """Frame i's optimised depth fused with its multi-view triangulation -> {depth float32 (H, W),
    measured float (fraction of pixels triangulated), confidence float32 (H, W) in [0, 1]}."""
    depth = np.asarray(inputs["depth"], np.float32)
    if not p.enabled:
        return {"depth": depth, "measured": 0.0, "confidence": np.zeros_like(depth)}
    poses = np.asarray(inputs["poses"], np.float64)
    i = int(inputs["index"])
    flows = [(*_far_flow(fl, d), poses[int(j)])
             for fl, d, j in zip(inputs["refs"], inputs["ref_dirs"], inputs["ref_indices"])]
    fused, measured, confidence = depth_fusion.fuse_depth_flows(
        depth, poses[i], flows, np.asarray(inputs["K"]), min_angle_deg=p.min_angle_deg,
        max_log_dev=p.max_log_dev, agree_log_dev=p.agree_log_dev, coverage_refs=p.coverage_refs)
    return {"depth": fused, "measured": measured, "confidence": confidence}


DEPTH_FUSION = declare(MapStage("depth_fusion", run_depth_fusion, deps=("ingest", "flow", "flow_far", "optimize_segments"),
                        params="depth_fusion", kind="depth", items=_fusion_items,
                        description="optimised depth fused with multi-view triangulation at the final poses"))


# ============================================================================== depth_filter
@config_section("depth_filter")
class DepthFilterParams(Section):
    enabled: bool = True
    radius: int = Field(4, ge=0)
    border: int = 4
    fill_from: float = Field(0.7, ge=0, le=1, description="depth confidence of the pixels an edge-aware "
                             "fill of uncertain depth is made from")
    fill_below: float = Field(0.0, ge=0, le=1, description="pixels less confident than this are pulled "
                              "towards that fill (in proportion; 0 = off, the default: it helps ICL, "
                              "AbsRel 0.053 -> 0.049, and hurts the synthetic loop, 0.042 -> 0.129)")


def _filter_items(view, p: DepthFilterParams):
    n = view.len("ingest")
    r = p.radius if p.enabled else 0
    out = []
    for i in range(n):
        lo, hi = max(0, i - r), min(n - 1, i + r)
        out.append({"center": Const(i - lo), "depths": [ItemRef("depth_fusion", j) for j in range(lo, hi + 1)],
                    "flows": [ItemRef("flow", j) for j in range(lo, hi)], "image": ItemRef("ingest", i)})
    return out


def run_depth_filter(inputs: dict[str, Any], p: DepthFilterParams, ctx: Any) -> dict[str, Any]:
    """Frame i's depth filtered with its +-radius neighbours -> {depth float32 (H, W),
    confidence float32 (H, W): depth_fusion's, zero where the filter invalidated the depth}."""
    depths = np.stack([np.asarray(d["depth"]) for d in inputs["depths"]])
    center = int(inputs["center"])
    conf = np.asarray(inputs["depths"][center].get("confidence", np.zeros_like(depths[center])), np.float32)
    if not p.enabled or len(depths) == 1:
        return {"depth": depths[center].astype(np.float32), "confidence": conf}
    fwd = np.stack([fl["fwd"] for fl in inputs["flows"]])
    bwd = np.stack([fl["bwd"] for fl in inputs["flows"]])
    out = np.asarray(depth_filter.filter_depth(depths, fwd, bwd, center, radius=p.radius, border=p.border),
                     np.float32)
    conf = np.where(out > 0, conf, 0.0).astype(np.float32)
    if p.fill_below > 0:
        gray = np.asarray(inputs["image"]["image"], np.float64).mean(axis=2) / 255.0
        out = depth_filter.fill_uncertain(gray, out, conf, source=p.fill_from, full=p.fill_below)
    return {"depth": out, "confidence": conf}


DEPTH_FILTER = declare(MapStage("depth_filter", run_depth_filter, deps=("ingest", "flow", "depth_fusion"), params="depth_filter",
                        kind="depth", items=_filter_items))


# ============================================================================== depth_consensus
@config_section("depth_consensus")
class DepthConsensusParams(Section):
    enabled: bool = True
    offsets: tuple[int, ...] = Field((8, 16, 24, 32, 48, 64), description="references (frames i - k "
                                     "and i + k) whose filtered depth is carried into frame i with the "
                                     "final poses")
    max_log_dev: float = Field(0.2, gt=0, description="a carried depth further from frame i's (|log "
                               "ratio|) is another surface (an occlusion) and not used")
    reproj_sigma_px: float = Field(3.0, gt=0, description="round-trip reprojection error scale, px "
                                   "(weight exp(-(e / sigma)^2))")

    @field_validator("offsets")
    @classmethod
    def _positive_offsets(cls, v: tuple[int, ...]) -> tuple[int, ...]:
        if any(k <= 0 for k in v):
            raise ValueError("offsets are frame distances k > 0 (frames i - k and i + k are used)")
        return tuple(sorted(set(v)))


def _consensus_items(view, p: DepthConsensusParams):
    n = view.len("ingest")
    out = []
    for i in range(n):
        refs = [j for k in (p.offsets if p.enabled else ()) for j in (i - k, i + k) if 0 <= j < n]
        out.append({"index": Const(i), "K": PartRef("ingest", ("K",), summary=True),
                    "poses": PartRef("optimize_segments", ("poses",)), "depth": ItemRef("depth_filter", i),
                    "refs": [ItemRef("depth_filter", j) for j in refs], "ref_indices": Const(refs),
                    "static": [ItemRef("masks", j) for j in [i, *refs]] if refs else []})
    return out


def run_depth_consensus(inputs: dict[str, Any], p: DepthConsensusParams, ctx: Any) -> dict[str, Any]:
    """Frame i's filtered depth averaged with the depths its references see at its pixels (moving
    pixels, by the masks stage, left out) -> {depth float32 (H, W), confidence float32 (H, W):
    depth_filter's, unchanged}."""
    own = inputs["depth"]
    depth = np.asarray(own["depth"], np.float32)
    conf = np.asarray(own.get("confidence", np.zeros_like(depth)), np.float32)
    if not p.enabled or not inputs["refs"]:
        return {"depth": depth, "confidence": conf}
    poses = np.asarray(inputs["poses"], np.float64)
    refs = [(np.asarray(r["depth"]), np.asarray(r.get("confidence", np.zeros_like(depth))), poses[int(j)])
            for r, j in zip(inputs["refs"], inputs["ref_indices"])]
    static = [np.asarray(m["static"]) for m in inputs["static"]]  # frame i's, then the references'
    out = depth_consensus.consensus_depth(depth, conf, poses[int(inputs["index"])], refs, np.asarray(inputs["K"]),
                                          max_log_dev=p.max_log_dev, reproj_sigma_px=p.reproj_sigma_px,
                                          static=static[0], ref_static=static[1:])
    return {"depth": out, "confidence": conf}


DEPTH_CONSENSUS = declare(MapStage("depth_consensus", run_depth_consensus,
                                   deps=("ingest", "masks", "optimize_segments", "depth_filter"),
                                   params="depth_consensus",
                                   kind="depth", items=_consensus_items,
                                   description="filtered depth averaged with what confident views of the "
                                               "same points say, carried with the final poses"))


# ============================================================================== the pipeline
# The run's whole configuration: ``seed`` plus one section per declared config section.
GCVDConfig = create_model("GCVDConfig", __config__=ConfigDict(extra="forbid"), seed=(int, 0),
                          **{name: (model, model()) for name, model in _SECTIONS.items()})


PROFILES: dict[str, dict[str, Any]] = {
    # The paper's / authors' settings (GPU-sized), and the paper's method: no bundle adjustment.
    "paper": {
        "bundle_adjustment": {"enabled": False},
        "association": {"verify": "paper", "per_keyframe": 0},
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


def limit_threads() -> None:
    """Worker processes share the cores: one torch / OpenCV thread each."""
    import cv2
    import torch

    torch.set_num_threads(1)
    cv2.setNumThreads(1)


PIPELINE = Pipeline(
    list(_STAGES),
    packages=("stages", "gcvd_flow.pipeline"),
    numeric_libraries=(("torch", ("torch",)), ("opencv", ("opencv-python-headless", "opencv-python")),
                       ("kornia", ("kornia",)), ("gtsam", ("gtsam",))),
    numeric_settings=(("device", "cpu"), ("dtype", "float32"), ("deterministic", True)),
    worker_init=limit_threads,
)

STAGE_NAMES = PIPELINE.names()


def open_source(path: str, config: GCVDConfig) -> Source:
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
    intr, origin = _camera_intrinsics(src, p)
    w, h = ingest_mod.working_size(src.size[0], src.size[1], p.long_side)
    cam = ingest_mod.make_camera(src.size[0], src.size[1], w, h, intr, origin)
    K = cam["K"]
    note = "GUESSED, pass --intrinsics fx,fy,cx,cy for accurate results" if cam["guessed"] else origin
    print(f"camera: {src.layout} input {src.size[0]}x{src.size[1]} -> working {w}x{h}, fx={K[0, 0]:.1f} "
          f"fy={K[1, 1]:.1f} cx={K[0, 2]:.1f} cy={K[1, 2]:.1f} ({note})", file=sys.stderr)
    return src


SPEC = PipelineSpec("gcvd", PIPELINE, GCVDConfig, PROFILES, open_source=open_source,
                    export=run_dir.write_run_dir, schema_dir=artifacts_schema.SCHEMA_DIR)
