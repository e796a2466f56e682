"""Block priors (stages/frontend/priors.py)."""

from __future__ import annotations

from typing import Any

import numpy as np

from gcvd_flow.engine.dag import Const, ItemRef, MapStage, PartRef
from gcvd_flow.io.weights import open_model
from gcvd_flow.pipeline.context import ItemContext
from gcvd_flow.pipeline.frontend import CALIBRATE, FLOW, FLOW_FAR, INGEST, _far_index, _far_refs
from gcvd_flow.pipeline.masks import MASKS, _has_user_masks, _user_mask_refs
from gcvd_flow.pipeline.registry import declare, section
from gcvd_flow.pipeline.shared import _far_flow, _prior_refs
from gcvd_flow.stages.frontend import (
    params as frontend_params,
    priors as priors_mod,
    user_masks,
)
from gcvd_flow.stages.graph import references

# ============================================================================== priors
PriorsParams = section("priors", frontend_params.PriorsSettings)


def _prior_direct_items(view, p: frontend_params.PriorsSettings):
    # Reference frames span back and span forward (priors.references=symmetric: each pair serves
    # the two frames it joins), or span and span/2 back (references=back): the prior
    # triangulates a direct flow to the reference; chaining adjacent flows drifts ~0.1 px per
    # link, which on ICL turned 2-view poses off by degrees (AbsRel 0.25 vs 0.085 direct).
    # The direct flows are flow_far's items (shared with depth_fusion). The chain of adjacent
    # flows (chain_fallback) is not read here: the priors stage reads it for the frames whose
    # direct flows all failed, and only for those.
    n = view.len(INGEST)
    index = _far_index(view) if p.backend == "geometric" else {}
    user = p.backend == "geometric" and _has_user_masks(view)
    out = []
    for i in range(n):
        it: dict[str, Any] = {"image": ItemRef(INGEST, i), "K": PartRef(CALIBRATE, ("K",))}
        js = _prior_refs(i, n, p)
        if js:
            it.update(_far_refs(index, i, js, p.preset, p.fb_thresh), **_user_mask_refs(user, [i, *js]))
        out.append(it)
    return out


def _chain_of(i: int, n: int, p: frontend_params.PriorsSettings) -> tuple[str, list[int]]:
    """Frame i's chain_fallback chain: its direction and the flow items (at most chain_links)."""
    direction, ks = references.flow_chain(i, n, p.span)
    return direction, ks[:p.chain_links]


def _prior_items(view, p: frontend_params.PriorsSettings):
    # Frame i's prior is priors_direct's item, passed on, unless none of its direct flows kept
    # enough consistent pixels (its "fallback" flag; fast motion) and priors.chain_fallback is on:
    # then the item reads the chain of adjacent flows toward the reference and triangulates it.
    n = view.len(INGEST)
    direct = view.value(PRIORS_DIRECT)
    user = p.backend == "geometric" and _has_user_masks(view)
    out: list[dict[str, Any]] = []
    for i in range(n):
        direction, ks = _chain_of(i, n, p)
        if p.backend == "geometric" and p.chain_fallback and ks and _prior_refs(i, n, p) and direct[i].get("fallback"):
            out.append({"image": ItemRef(INGEST, i), "K": PartRef(CALIBRATE, ("K",)), "chain_dir": Const(direction),
                        "chain": [ItemRef(FLOW, k) for k in ks], **_user_mask_refs(user, [i])})
        else:
            out.append({"direct": ItemRef(PRIORS_DIRECT, i)})
    return out


def _open_midas(p: frontend_params.PriorsSettings) -> Any:
    return open_model("midas", p.weights)


def run_priors_direct(inputs: dict[str, Any], p: frontend_params.PriorsSettings, ctx: ItemContext) -> dict[str, Any]:
    """Frame i -> {inv_depth float32 (H, W) median 1, confidence float32 (H, W), fallback: bool}
    from its direct flows (or MiDaS); fallback: no direct flow kept enough consistent pixels (the
    priors stage then triangulates the adjacent-flow chain when priors.chain_fallback is on)."""
    return _prior(inputs, p, ctx)


def run_priors(inputs: dict[str, Any], p: frontend_params.PriorsSettings, ctx: ItemContext) -> dict[str, Any]:
    """Frame i -> {inv_depth float32 (H, W) median 1, confidence float32 (H, W)}: priors_direct's
    item (``direct``), or the prior of the adjacent-flow chain (``chain``), or (items with
    ``refs``, as priors_direct's) from the direct flows with the chain as the fallback."""
    if "direct" in inputs:
        d = inputs["direct"]
        return {"inv_depth": np.asarray(d["inv_depth"]), "confidence": np.asarray(d["confidence"])}
    out = _prior(inputs, p, ctx)
    out.pop("fallback")
    return out


def _prior(inputs: dict[str, Any], p: frontend_params.PriorsSettings, ctx: ItemContext) -> dict[str, Any]:
    """The prior of frame i from its direct flows (``refs``), with the adjacent-flow ``chain``
    (when given) as the fallback; ``fallback``: whether no direct flow was usable."""
    image = inputs["image"]["image"]
    if p.backend == "midas":
        from gcvd_flow.stages.models.midas import midas_prior

        inv = midas_prior(ctx.resource("model"), image)
        return {"inv_depth": inv.astype(np.float32), "confidence": np.ones_like(inv, np.float32), "fallback": False}
    K = np.asarray(inputs["K"])
    # direct flows to the far reference (more parallax) and the near one (sees what the far
    # one lost); the prior fuses both (stages.frontend.priors.geometric_prior)
    flows = []
    keep = [np.asarray(m["user_keep"]) > 0 for m in inputs.get("user_masks", [])]  # --masks: frame i's, the refs'
    for k, (fl, direction) in enumerate(zip(inputs.get("refs", []), inputs.get("ref_dirs", []))):
        fwd, valid = _far_flow(fl, direction)
        if valid.mean() >= priors_mod.MIN_VALID_FRACTION:
            if keep:  # no triangulation of, or from, a user-masked pixel
                valid = valid & keep[0] & user_masks.flow_target_kept(fwd, keep[k + 1])
            flows.append((fwd, valid))
    chain = [_far_flow(fl, inputs["chain_dir"]) for fl in inputs.get("chain", [])] if not flows and p.chain_fallback else []
    if keep and chain:  # frame i's user mask (the chain's other frames have theirs in flow's masks)
        chain[0] = (chain[0][0], chain[0][1] & keep[0])
    out = priors_mod.prior_with_fallback(image, K, flows, chain)
    return {"inv_depth": out["inv_depth"].astype(np.float32),
            "confidence": out["confidence"].astype(np.float32), "fallback": not flows}


PRIORS_DIRECT = declare(MapStage("priors_direct", run_priors_direct, deps=(INGEST, CALIBRATE, FLOW_FAR, MASKS),
                                 params="priors", kind="prior", items=_prior_direct_items,
                                 resources={"model": _open_midas},
                                 description="MiDaS-shaped relative inverse depth from the direct flows (or MiDaS)"))
PRIORS = declare(MapStage("priors", run_priors, deps=(INGEST, CALIBRATE, FLOW, MASKS, PRIORS_DIRECT), params="priors",
                          kind="prior", items=_prior_items,
                          description="MiDaS-shaped relative inverse depth: priors_direct's, or from the adjacent-flow "
                                      "chain where no direct flow held (priors.chain_fallback)"))
