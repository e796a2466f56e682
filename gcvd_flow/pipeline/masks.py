"""Block masks (stages/frontend/masks.py, stages/frontend/user_masks.py), and the references later
stages' items make to its items."""

from __future__ import annotations

from typing import Any

import numpy as np

from gcvd_flow.engine.dag import Const, ExternalRef, ItemRef, MapStage, PartRef
from gcvd_flow.io.weights import open_model
from gcvd_flow.pipeline.context import ItemContext
from gcvd_flow.pipeline.frontend import CALIBRATE, FLOW, INGEST, _lens_border
from gcvd_flow.pipeline.registry import declare, section
from gcvd_flow.pipeline.shared import _MaskFile, _undistort_of, _user_keep, _user_mask_files
from gcvd_flow.stages.frontend import (
    flow,
    masks as masks_mod,
    params as frontend_params,
)
from gcvd_flow.stages.graph import references

# ============================================================================== masks
MasksParams = section("masks", frontend_params.MasksSettings)


def _chain_refs(i: int, n: int, span: int) -> dict[str, Any]:
    """Flows from frame i toward a reference `span` frames away (stages.graph.references.flow_chain)."""
    direction, flows = references.flow_chain(i, n, span)
    return {"direction": Const(direction), "chain": [ItemRef(FLOW, k) for k in flows]}


def _mask_items(view, p: frontend_params.MasksSettings):
    # The semantic backend reads the frame itself; the motion backend its flows (only); the user's
    # mask of the frame enters by its content (an ExternalRef: file digest + loader).
    n = view.len(INGEST)
    user, und = [], _lens_border(view)
    if p.user_dir:
        from gcvd_flow.engine.keys import digest_file

        sel = list(view.summary(INGEST)["frame_indices"])  # the source frames ingest selected
        user = [ExternalRef(digest_file(f), _MaskFile(f)) for f in _user_mask_files(view.source, p, sel)]
        cam = view.summary(INGEST)
        und = _undistort_of(cam)
    out = []
    for i in range(n):
        it: dict[str, Any] = {}
        if p.backend != "maskrcnn":
            it = {"K": PartRef(CALIBRATE, ("K",)), **_chain_refs(i, n, p.span)}
        if "maskrcnn" in p.backend or (p.backend != "none" and p.texture_frac > 0):
            it["image"] = ItemRef(INGEST, i)
        if user or und:  # --masks, or the lens' black border alone
            if user:
                it["user_mask"] = user[i]
            it["source_size"] = Const(list(view.source.size))
            if und:  # ingest undistorts the frames: the masks go through the same remap
                it["undistort"] = Const(und)
        out.append(it)
    return out


def _open_maskrcnn(p: frontend_params.MasksSettings) -> Any:
    return open_model("maskrcnn", p.weights, min_size=p.min_size)


def _with_user_mask(static: np.ndarray, inputs: dict[str, Any]) -> np.ndarray:
    """static uint8 (h, w) with the user's mask (source resolution, True = out) set to 0."""
    if "source_size" not in inputs:
        return static
    return np.where(_user_keep(inputs, static.shape) > 0, static, 0).astype(np.uint8)


def run_masks(inputs: dict[str, Any], p: frontend_params.MasksSettings, ctx: ItemContext) -> dict[str, Any]:
    """Frame i -> {static: uint8 (H, W), 1 = static, solve: uint8 (H, W), 1 = static and flow the
    optimisations trust}: the backend's masks with the user's (--masks) pixels set to 0; with
    --masks also user_keep: uint8 (H, W), 1 = not masked by the user (what the later stages
    exclude hard, at every resolution: stages.frontend.user_masks)."""
    masks = _backend_mask(inputs, p, ctx)
    if "source_size" not in inputs:
        return masks
    keep = _user_keep(inputs, masks["static"].shape)
    return {**{k: np.where(keep > 0, v, 0).astype(np.uint8) for k, v in masks.items()}, "user_keep": keep}


def _backend_mask(inputs: dict[str, Any], p: frontend_params.MasksSettings, ctx: Any) -> dict[str, Any]:
    """Frame i -> {static, solve}, from its adjacent and chained flows (backend motion), its
    image's Mask R-CNN instances of moving classes (maskrcnn), or both (motion+maskrcnn: static
    where both say static)."""
    semantic = None
    if "maskrcnn" in p.backend:
        from gcvd_flow.stages.models.maskrcnn import semantic_static_mask

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


def _mask_summary(view, p: frontend_params.MasksSettings) -> dict[str, Any] | None:
    """{"user_masks": True} when the items carry the user's (--masks) kept pixels, else None (the
    stage's manifest as without a summary): what later items functions ask, without loading an item
    (a read-through run from a remote fetches no mask item then)."""
    return {"user_masks": True} if p.user_dir or _lens_border(view) else None


def _has_user_masks(view) -> bool:
    """Whether the masks stage's items carry the user's (--masks) kept pixels (user_keep)."""
    return bool((view.summary(MASKS) or {}).get("user_masks"))


def _user_mask_refs(user: bool, frames: list[int]) -> dict[str, Any]:
    """{"user_masks": the mask items of ``frames``} with --masks (``user``: their user_keep), {}
    without (the items are keyed as before)."""
    return {"user_masks": [ItemRef(MASKS, j) for j in frames]} if user else {}


MASKS = declare(MapStage("masks", run_masks, deps=(INGEST, CALIBRATE, FLOW), params="masks", kind="mask",
                 items=_mask_items, summary=_mask_summary, resources={"model": _open_maskrcnn},
                 share_inputs=True,  # frame i reads the flows i .. i + span - 1: each read once per worker
                 description="1 = static"))
