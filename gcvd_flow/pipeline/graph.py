"""Blocks keyframes and association (stages/graph)."""

from __future__ import annotations

from typing import Any

import numpy as np

import gcvd_flow.pipeline.priors  # noqa: F401  (its stages are declared before these)
from gcvd_flow.engine.dag import Stage
from gcvd_flow.io.weights import open_model
from gcvd_flow.pipeline.context import StageContext
from gcvd_flow.pipeline.frontend import CALIBRATE, FLOW, INGEST
from gcvd_flow.pipeline.masks import MASKS
from gcvd_flow.pipeline.registry import declare, section
from gcvd_flow.pipeline.shared import _solve_mask
from gcvd_flow.stages.graph import keyframes as keyframes_mod, params as graph_params

# ============================================================================== keyframes
KeyframesParams = section("keyframes", graph_params.KeyframesSettings)


def run_keyframes(inputs: dict[str, Any], p: Any, ctx: StageContext) -> dict[str, Any]:
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


KEYFRAMES = declare(Stage("keyframes", run_keyframes, deps=(FLOW, MASKS), params="keyframes", kind="keyframes"))


# ============================================================================== association
AssociationParams = section("association", graph_params.AssociationSettings)


def _open_resnet(p: graph_params.AssociationSettings) -> Any:
    return open_model("resnet18", p.weights)


def run_association(inputs: dict[str, Any], p: Any, ctx: StageContext) -> dict[str, Any]:
    """Keyframes -> {graph (JSON), edge_flows [{i, j, fwd, bwd, fwd_valid, bwd_valid}]}."""
    # heavy (torch / gtsam / scipy): imported when the stage runs, not when the CLI starts
    from gcvd_flow.stages.graph import association as association_mod

    kf = inputs["keyframes"]["indices"]
    frames = inputs["ingest"]
    K = np.asarray(inputs["calibrate"]["K"])
    images = [frames[i]["image"] for i in kf]
    kw: dict[str, Any] = {}  # the settings travel whole (p); these are the backend's and enabled's
    if p.backend == "resnet18":
        from gcvd_flow.stages.models.resnet import resnet_descriptor

        model = ctx.resource("model")
        kw["descriptor_fn"] = lambda img: resnet_descriptor(model, img)
    if not p.enabled:
        kw["descriptors"] = np.eye(len(kf), dtype=np.float32)  # nothing similar: no loop edges
        kw["similarity_threshold"] = 2.0
    graph, edge_flows = association_mod.build_graph(kf, images, K, inputs["keyframes"]["threshold_px"] or 1e9, p,
                                                    call_map=ctx.map, **kw)
    flows_out = [{"i": int(a), "j": int(b), **{k: v for k, v in fl.items() if k in ("fwd", "bwd", "fwd_valid", "bwd_valid")}}
                 for (a, b), fl in sorted(edge_flows.items())]
    return {"graph": graph, "edge_flows": flows_out}


ASSOCIATION = declare(Stage("association", run_association, deps=(INGEST, CALIBRATE, KEYFRAMES), params="association",
                    kind="graph", resources={"model": _open_resnet}))
