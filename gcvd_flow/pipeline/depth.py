"""Blocks fusion_samples, fusion_references, fusion_flow, depth_fusion, depth_filter and
depth_consensus (stages/depth)."""

from __future__ import annotations

from typing import Any

import numpy as np

from gcvd_flow.engine.dag import Const, ItemRef, MapStage, PartRef
from gcvd_flow.pipeline.context import ItemContext
from gcvd_flow.pipeline.frontend import CALIBRATE, FLOW, FLOW_FAR, INGEST, _far_index, run_flow_far
from gcvd_flow.pipeline.masks import MASKS, _has_user_masks, _user_mask_refs
from gcvd_flow.pipeline.optimize import OPTIMIZE_SEGMENTS
from gcvd_flow.pipeline.registry import declare, section
from gcvd_flow.pipeline.shared import _eroded_keep, _far_flow, _fusion_refs
from gcvd_flow.stages.depth import (
    consensus as depth_consensus,
    filter as depth_filter,
    fusion as depth_fusion,
    params as depth_params,
    smooth as depth_smooth,
    tilt as depth_tilt,
)
from gcvd_flow.stages.frontend import (
    user_masks,
)
from gcvd_flow.stages.graph import references

# ============================================================================== depth_fusion
# Each frame's fusion references (depth_fusion.references): "baseline" chooses them from the final
# poses and a grid of each frame's depth (fusion_samples) by triangulation angle and overlap
# (stages.graph.references.baseline_references), in the fusion_references stage (a map stage of
# one item, so it reads parts, never a whole clip's depth maps), so they are cached, named in its output and explained by
# plan / why like any stage; the flows of the chosen pairs that no other stage computes are the
# items of fusion_flow (keyed by the two images, preset and threshold only, like flow_far's).
# "offsets" is the fixed-offset rule, its flows flow_far's items.
DepthFusionParams = section("depth_fusion", depth_params.DepthFusionSettings)


FusionReferencesParams = section("fusion_references", depth_params.FusionReferencesSettings)


def _fusion_samples_items(view, p: depth_params.DepthFusionSettings):
    baseline = p.enabled and p.references == "baseline"
    return [{"K": PartRef(CALIBRATE, ("K",)), "depth": PartRef(OPTIMIZE_SEGMENTS, ("depths", i))}
            for i in range(view.len(INGEST) if baseline else 0)]


def run_fusion_samples(inputs: dict[str, Any], p: depth_params.DepthFusionSettings, ctx: ItemContext) -> dict[str, Any]:
    """Frame i's optimised depth -> {points float32 (M, 3): a grid of its pixels in camera
    coordinates (pose scale), size int [w, h]}: what fusion_references projects, a few KB per frame
    (the whole clip's depth maps are never held at once)."""
    d = np.asarray(inputs["depth"], np.float32)
    return {"points": references.view_samples(d, np.asarray(inputs["K"], np.float64)).astype(np.float32),
            "size": np.asarray([d.shape[1], d.shape[0]], np.int64)}


FUSION_SAMPLES = declare(MapStage("fusion_samples", run_fusion_samples, deps=(INGEST, CALIBRATE, OPTIMIZE_SEGMENTS),
                                  params="depth_fusion", kind="fusion_samples", items=_fusion_samples_items,
                                  description="a grid of each frame's optimised depth, for choosing its "
                                              "fusion references"))


def _fusion_references_items(view, b: Any):
    # one item: the clip's poses, its frames' samples and flow_far's pairs, each read as a part
    # (no stage's whole output is decoded: the clip's depth maps are never held at once)
    p = b.depth_fusion
    baseline = p.enabled and p.references == "baseline"
    return [{"n": Const(view.len(INGEST)), "K": PartRef(CALIBRATE, ("K",)),
             "poses": PartRef(OPTIMIZE_SEGMENTS, ("poses",)),
             "samples": [ItemRef(FUSION_SAMPLES, i) for i in range(view.len(FUSION_SAMPLES))] if baseline else [],
             "far_pairs": PartRef(FLOW_FAR, ("pairs",), summary=True) if baseline else Const([])}]


def run_fusion_references(inputs: dict[str, Any], b: Any, ctx: ItemContext) -> dict[str, Any]:
    """The clip (one item) -> {refs: per frame its reference frames (list of int lists), flows:
    the pairs [a, b], a < b, fusion_flow computes (neither adjacent nor flow_far's)}."""
    p = b.depth_fusion
    n = int(inputs["n"])
    if not p.enabled:
        return {"refs": [[] for _ in range(n)], "flows": []}
    if p.references == "offsets":
        return {"refs": [_fusion_refs(i, n, p) for i in range(n)], "flows": []}
    poses = np.asarray(inputs["poses"], np.float64)
    K = np.asarray(inputs["K"], np.float64)
    samples = [np.asarray(it["points"], np.float64) for it in inputs["samples"]]
    w, h = (int(v) for v in np.asarray(inputs["samples"][0]["size"]))
    free = [(a, c) for a, c, preset, fb in inputs["far_pairs"]
            if preset == p.preset and float(fb) == float(p.fb_thresh)]
    refs, flows = references.baseline_references(poses, samples, K, (w, h), b.fusion_references,
                                                 free)
    return {"refs": refs, "flows": [list(pr) for pr in flows]}


FUSION_REFERENCES = declare(MapStage("fusion_references", run_fusion_references,
                                     deps=(INGEST, CALIBRATE, FLOW_FAR, OPTIMIZE_SEGMENTS, FUSION_SAMPLES),
                                     params=("depth_fusion", "fusion_references"), kind="fusion_references",
                                     items=_fusion_references_items,
                                     description="each frame's depth_fusion references, chosen by triangulation "
                                                 "angle and overlap at the final poses (one item: the clip)"))


def _fusion_flow_items(view, b: Any):
    p = b.depth_fusion
    return [{"a": ItemRef(INGEST, a), "b": ItemRef(INGEST, c), "preset": Const(p.preset),
             "fb_thresh": Const(float(p.fb_thresh))} for a, c in view.value(FUSION_REFERENCES)[0]["flows"]]


# the same function as flow_far's: one DIS forward + backward per pair
FUSION_FLOW = declare(MapStage("fusion_flow", run_flow_far, deps=(INGEST, FUSION_REFERENCES),
                               params=("depth_fusion",), kind="flow_far", items=_fusion_flow_items,
                               # the section as a bundle, left out of item keys: an item is keyed by
                               # its two images, preset and threshold only
                               selection_params=("depth_fusion",),
                               description="direct flows of the fusion reference pairs no other stage computes"))


def _fusion_items(view, p: depth_params.DepthFusionSettings):
    # a reference's flow: the flow stage's pair (adjacent), flow_far's (shared with priors) or
    # fusion_flow's, seen from frame i ("fwd": i is the pair's first frame, "bwd": its second)
    n = view.len(INGEST)
    chosen = view.value(FUSION_REFERENCES)[0]
    far = _far_index(view) if p.enabled else {}
    own = {tuple(pr): k for k, pr in enumerate(chosen["flows"])}
    user = p.enabled and _has_user_masks(view)
    out = []
    for i in range(n):
        js = [int(j) for j in chosen["refs"][i]]
        refs: list[Any] = []
        for j in js:
            a, c = min(i, j), max(i, j)
            pair = references.far_pair(i, j, p.preset, p.fb_thresh)
            refs.append(ItemRef(FLOW, a) if c - a == 1 else ItemRef(FLOW_FAR, far[pair]) if pair in far
                        else ItemRef(FUSION_FLOW, own[(a, c)]))
        out.append({"index": Const(i), "K": PartRef(CALIBRATE, ("K",)),
                    "poses": PartRef(OPTIMIZE_SEGMENTS, ("poses",)),
                    "depth": PartRef(OPTIMIZE_SEGMENTS, ("depths", i)),
                    "refs": refs, "ref_dirs": Const(["fwd" if i < j else "bwd" for j in js]),
                    "ref_indices": Const(js), **_user_mask_refs(user, [i, *js])})
    return out


def run_depth_fusion(inputs: dict[str, Any], p: depth_params.DepthFusionSettings, ctx: ItemContext) -> dict[str, Any]:
    """Frame i's optimised depth fused with its multi-view triangulation -> {depth float32 (H, W),
    measured float (fraction of pixels triangulated), confidence float32 (H, W) in [0, 1]}."""
    depth = np.asarray(inputs["depth"], np.float32)
    if not p.enabled:
        return {"depth": depth, "measured": 0.0, "confidence": np.zeros_like(depth)}
    poses = np.asarray(inputs["poses"], np.float64)
    i = int(inputs["index"])
    flows = [(*_far_flow(fl, d), poses[int(j)])
             for fl, d, j in zip(inputs["refs"], inputs["ref_dirs"], inputs["ref_indices"])]
    if "user_masks" in inputs:  # --masks: no triangulation of, or from, a user-masked pixel
        keep = [np.asarray(m["user_keep"]) > 0 for m in inputs["user_masks"]]  # frame i's, then the references'
        flows = [(f, v & keep[0] & user_masks.flow_target_kept(f, k), T) for (f, v, T), k in zip(flows, keep[1:])]
    fused, measured, confidence = depth_fusion.fuse_depth_flows(
        depth, poses[i], flows, np.asarray(inputs["K"]), min_angle_deg=p.min_angle_deg,
        max_log_dev=p.max_log_dev, agree_log_dev=p.agree_log_dev, coverage_refs=p.coverage_refs,
        spread_log_sigma=p.spread_log_sigma)
    return {"depth": fused, "measured": measured, "confidence": confidence}


DEPTH_FUSION = declare(MapStage("depth_fusion", run_depth_fusion,
                        deps=(INGEST, CALIBRATE, FLOW, FLOW_FAR, MASKS, OPTIMIZE_SEGMENTS, FUSION_REFERENCES,
                              FUSION_FLOW),
                        params="depth_fusion", kind="depth", items=_fusion_items,
                        description="optimised depth fused with multi-view triangulation at the final poses"))


# ============================================================================== depth_filter
DepthFilterParams = section("depth_filter", depth_params.DepthFilterSettings)


def _filter_items(view, p: depth_params.DepthFilterSettings):
    n = view.len(INGEST)
    r = p.radius if p.enabled else 0
    user = r > 0 and _has_user_masks(view)
    out = []
    for i in range(n):
        lo, hi = references.window(i, n, r)
        out.append({"center": Const(i - lo), "depths": [ItemRef(DEPTH_FUSION, j) for j in range(lo, hi + 1)],
                    "flows": [ItemRef(FLOW, j) for j in range(lo, hi)], "image": ItemRef(INGEST, i),
                    **_user_mask_refs(user, list(range(lo, hi + 1)))})
    return out


def run_depth_filter(inputs: dict[str, Any], p: depth_params.DepthFilterSettings, ctx: ItemContext) -> dict[str, Any]:
    """Frame i's depth filtered with its +-radius neighbours -> {depth float32 (H, W),
    confidence float32 (H, W): depth_fusion's, zero where the filter invalidated the depth}."""
    depths: Any = [np.asarray(d["depth"]) for d in inputs["depths"]]  # filter_depth takes them unstacked
    center = int(inputs["center"])
    conf = np.asarray(inputs["depths"][center].get("confidence", np.zeros_like(depths[center])), np.float32)
    if not p.enabled or len(depths) == 1:
        return {"depth": depths[center].astype(np.float32), "confidence": conf}
    fwd: Any = [np.asarray(fl["fwd"]) for fl in inputs["flows"]]
    bwd: Any = [np.asarray(fl["bwd"]) for fl in inputs["flows"]]
    if "user_masks" in inputs:  # --masks: nothing at or next to a user-masked pixel is read: the
        # neighbours' depths there are invalid (0), and a track whose flow sample meets one (on
        # its way through any frame, there or back) becomes NaN, which the filter drops
        keep = [_eroded_keep(m) for m in inputs["user_masks"]]
        depths = np.stack([d if j == center else np.where(k, d, 0) for j, (d, k) in enumerate(zip(depths, keep))])
        fwd = np.where(np.stack(keep[:-1])[..., None], fwd, np.nan).astype(np.float32)  # on frame k's grid
        bwd = np.where(np.stack(keep[1:])[..., None], bwd, np.nan).astype(np.float32)  # on frame k+1's grid
    out = np.asarray(depth_filter.filter_depth(depths, fwd, bwd, center, radius=p.radius, border=p.border),
                     np.float32)
    conf = np.where(out > 0, conf, 0.0).astype(np.float32)
    if p.fill_below > 0:
        gray = np.asarray(inputs["image"]["image"], np.float64).mean(axis=2) / 255.0
        out = depth_filter.fill_uncertain(gray, out, conf, source=p.fill_from, full=p.fill_below)
    return {"depth": out, "confidence": conf}


DEPTH_FILTER = declare(MapStage("depth_filter", run_depth_filter, deps=(INGEST, FLOW, MASKS, DEPTH_FUSION), params="depth_filter",
                        kind="depth", items=_filter_items, share_inputs=True))  # the +-radius window, once per worker


# ============================================================================== depth_consensus
DepthConsensusParams = section("depth_consensus", depth_params.DepthConsensusSettings)


def _consensus_items(view, p: depth_params.DepthConsensusSettings):
    n = view.len(INGEST)
    out = []
    for i in range(n):
        refs = references.symmetric_references(i, n, p.offsets) if p.enabled else []
        splat = references.symmetric_references(i, n, p.splat_offsets) if p.enabled and p.splat_offsets else []
        both = refs + [j for j in splat if j not in refs]  # the carry's first, in its order
        tilt = references.symmetric_references(i, n, p.tilt_offsets) if p.enabled and p.tilt_offsets else []
        out.append({"index": Const(i), "K": PartRef(CALIBRATE, ("K",)),
                    "poses": PartRef(OPTIMIZE_SEGMENTS, ("poses",)), "depth": ItemRef(DEPTH_FILTER, i),
                    "refs": [ItemRef(DEPTH_FILTER, j) for j in both], "ref_indices": Const(both),
                    "static": [ItemRef(MASKS, j) for j in [i, *both]] if both else [],
                    **({"splat_indices": Const(splat)} if splat else {}),
                    **({"image": ItemRef(INGEST, i)} if splat or tilt or (p.enabled and p.smooth_lambda > 0) else {}),
                    **({"tilt_images": [ItemRef(INGEST, j) for j in tilt], "tilt_indices": Const(tilt)} if tilt else {})})
    return out


def _open_source_cache(p: depth_params.DepthConsensusSettings) -> Any:
    return depth_consensus.SourceCache()


def _source_names(ctx: Any, sel: list[int]) -> list[str] | None:
    """Per splat reference k in ``sel``: the digests of its depth_filter item and its masks item
    (its static mask, eroded by the user's --masks, is a function of that item), which name what
    its splat source is computed from (None: the engine gave no digests)."""
    digest = getattr(ctx, "input_digest", None)
    refs, static = (digest("refs"), digest("static")) if digest is not None else (None, None)
    if not isinstance(refs, list) or not isinstance(static, list):
        return None
    return [f"{refs[k]}:{static[1 + k]}" for k in sel]


def run_depth_consensus(inputs: dict[str, Any], p: depth_params.DepthConsensusSettings, ctx: ItemContext) -> dict[str, Any]:
    """Frame i's filtered depth averaged with the depths its references see at its pixels (moving
    pixels, by the masks stage, left out), then (splat_offsets) corrected with their confident
    depth splatted into it, then (smooth_lambda) its log depth averaged edge-aware over the image by
    confidence -> {depth float32 (H, W), confidence float32 (H, W): depth_filter's, lowered at the
    output's depth edges (edge_jump)}."""
    own = inputs["depth"]
    depth = np.asarray(own["depth"], np.float32)
    conf = np.asarray(own.get("confidence", np.zeros_like(depth)), np.float32)
    if not p.enabled or not inputs["refs"]:
        return {"depth": depth, "confidence": conf}
    poses = np.asarray(inputs["poses"], np.float64)
    idx = [int(j) for j in inputs["ref_indices"]]
    refs = [(np.asarray(r["depth"]), np.asarray(r.get("confidence", np.zeros_like(depth))), poses[j])
            for r, j in zip(inputs["refs"], idx)]
    static = [np.asarray(m["static"]) for m in inputs["static"]]  # frame i's, then the references'
    if "user_keep" in inputs["static"][0]:  # --masks: no reference sample mixes a user-masked pixel
        static[1:] = [np.where(_eroded_keep(m), st, 0) for m, st in zip(inputs["static"][1:], static[1:])]
    # with splat_offsets the items add the splat's references: carry only the consensus's own offsets
    carry = ([k for k, j in enumerate(idx) if abs(j - int(inputs["index"])) in set(p.offsets)]
             if "splat_indices" in inputs else list(range(len(idx))))
    pose, K = poses[int(inputs["index"])], np.asarray(inputs["K"])
    out = depth_consensus.consensus_depth(depth, conf, pose, [refs[k] for k in carry], K,
                                          max_log_dev=p.max_log_dev, reproj_sigma_px=p.reproj_sigma_px,
                                          static=static[0], ref_static=[static[1 + k] for k in carry])
    if "splat_indices" in inputs:
        use = set(int(j) for j in inputs["splat_indices"])
        sel = [k for k, j in enumerate(idx) if j in use]
        gray = np.asarray(inputs["image"]["image"], np.float64).mean(axis=2) / 255.0
        sources = None if ctx is None else depth_consensus.reference_sources(  # each reference once per worker
            [refs[k] for k in sel], [static[1 + k] for k in sel], K, p.splat_min_confidence,
            p.splat_ref_edge_jump or None, cache=ctx.resource("splat_sources"), names=_source_names(ctx, sel))
        out = depth_consensus.splat_consensus(out, conf, pose, [refs[k] for k in sel], K, guide=gray, sources=sources,
                                              min_confidence=p.splat_min_confidence, front=p.splat_front,
                                              static=static[0], ref_static=[static[1 + k] for k in sel],
                                              keep_confidence=p.splat_keep, keep_edges=p.splat_keep_edges or None,
                                              ref_edge_jump=p.splat_ref_edge_jump or None)
    if p.edge_jump > 0:
        conf = depth_consensus.edge_confidence(out, conf, p.edge_jump)
    if p.smooth_lambda > 0 and "image" in inputs:  # unconfident depth's blotches averaged out along the image
        # (the masks stage's moving pixels take part: on these clips they are mostly static surfaces it
        # flags, and leaving them out measured worse; a user-masked pixel (--masks) neither gives nor takes)
        user = inputs["static"][0].get("user_keep")
        out = depth_smooth.smooth_depth(out, conf, np.asarray(inputs["image"]["image"]), p.smooth_lambda,
                                        p.smooth_sigma, p.smooth_keep, static=user)
    if "tilt_indices" in inputs:  # the unconfident pixels' range chosen photometrically (opt-in)
        out, _ = depth_tilt.photometric_tilt(out, conf, np.asarray(inputs["image"]["image"]), pose,
                                             [(np.asarray(im["image"]), poses[int(j)]) for im, j
                                              in zip(inputs["tilt_images"], inputs["tilt_indices"])],
                                             K, depth_tilt.SLOPES, shrink=p.tilt_shrink)
    return {"depth": out, "confidence": conf}


DEPTH_CONSENSUS = declare(MapStage("depth_consensus", run_depth_consensus,
                                   deps=(INGEST, CALIBRATE, MASKS, OPTIMIZE_SEGMENTS, DEPTH_FILTER),
                                   params="depth_consensus", resources={"splat_sources": _open_source_cache},
                                   kind="depth", items=_consensus_items, share_inputs=True,
                                   description="filtered depth averaged with what confident views of the "
                                               "same points say, carried with the final poses"))
