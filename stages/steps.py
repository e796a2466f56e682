"""The GCVD stages as the engine calls them: ``fn(inputs, params, ctx) -> value``.

Each function here is a thin adapter: it unpacks the inputs the pipeline declared
(gcvd_flow/pipeline.py says which upstream pieces each stage or item reads), calls the
algorithm in the other ``stages`` modules, and returns arrays / JSON. No file I/O: model
weights named by a parameter are read through ``_cached_model`` only, whose loaders live in
``stages.backends`` (and whose *content digest*, not path, is in the cache key).

Array conventions are those of docs/CONTRACT.md (frames uint8 RGB, flows (H, W, 2) px,
poses camera-to-world 4x4, depth float32 metres up to one global scale).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from stages import ingest as ingest_mod

# ------------------------------------------------------------------------------- helpers


@functools.lru_cache(maxsize=4)
def _cached_model(kind: str, path: str, min_size: int | None = None) -> Any:
    """Load weights once per process (items of a map stage share the model).

    ``min_size``: the Mask R-CNN input short side (part of the model's transform)."""
    if kind == "raft":
        from stages.backends.raft_net import load_raft

        return load_raft(path)
    if kind == "midas":
        from stages.backends.midas_net import load_midas

        return load_midas(path)
    if kind == "resnet18":
        from stages.backends.resnet import load_resnet18

        return load_resnet18(path)
    if kind == "maskrcnn":
        from stages.backends.maskrcnn import MIN_SIZE, load_maskrcnn

        return load_maskrcnn(path, min_size=min_size or MIN_SIZE)
    raise ValueError(f"unknown model kind {kind!r}")


def _inv(T: np.ndarray) -> np.ndarray:
    return np.linalg.inv(np.asarray(T, np.float64))


# ------------------------------------------------------------------------------- ingest


def ingest_frame(inputs: dict[str, Any], p: Any, ctx: Any) -> dict[str, Any]:
    """Source frame -> working resolution. Output {image: uint8 (h, w, 3) RGB (PNG)}."""
    rgb = inputs["frame"]
    src_w, src_h = inputs["source_size"]
    if (rgb.shape[1], rgb.shape[0]) != (src_w, src_h):
        raise ingest_mod.FrameError(f"{inputs['name']}: frame size {rgb.shape[1]}x{rgb.shape[0]} differs from "
                         f"the first frame's {src_w}x{src_h}")
    size = ingest_mod.working_size(src_w, src_h, p.long_side)
    return {"image": ingest_mod.prepare_frame(rgb, size)}


# ------------------------------------------------------------------------------- flow


def flow_pair(inputs: dict[str, Any], p: Any, ctx: Any) -> dict[str, Any]:
    """Adjacent pair (i, i+1) -> {fwd, bwd (H, W, 2) float32 px, fwd_valid, bwd_valid bool}."""
    from stages import flow

    model = _cached_model("raft", p.weights) if p.backend == "raft" else None
    return flow.compute_pair_flow(inputs["a"]["image"], inputs["b"]["image"], backend=p.backend,
                                  preset=p.preset, fb_thresh=p.fb_thresh, model=model)


# ------------------------------------------------------------------------------- masks


def _chain(inputs: dict[str, Any]) -> list[tuple[np.ndarray, np.ndarray]]:
    """The (flow, valid) chain from this frame toward its reference frame, in order."""
    fwd = inputs["direction"] == "fwd"
    n = len([k for k in inputs if k.startswith("chain")])
    out = []
    for k in range(n):
        fl = inputs[f"chain{k:02d}"]
        out.append((fl["fwd"], fl["fwd_valid"]) if fwd else (fl["bwd"], fl["bwd_valid"]))
    return out


def static_mask(inputs: dict[str, Any], p: Any, ctx: Any) -> dict[str, Any]:
    """Frame i -> {static: uint8 (H, W), 1 = static}, from its adjacent and chained flows
    (backend motion), its image's Mask R-CNN instances of moving classes (maskrcnn), or both
    (motion+maskrcnn: static where both say static)."""
    from stages import flow, masks

    semantic = None
    if "maskrcnn" in p.backend:
        from stages.backends.maskrcnn import semantic_static_mask

        model = _cached_model("maskrcnn", p.weights, p.min_size)
        semantic = semantic_static_mask(model, inputs["image"]["image"], score_thresh=p.score_thresh,
                                        dilate=p.dilate)
        if p.backend == "maskrcnn":
            return {"static": semantic}
    chain = _chain(inputs)
    h, w = chain[0][0].shape[:2]
    if p.backend == "none":
        return {"static": np.ones((h, w), np.uint8)}
    neighbours = [chain[0]]
    if len(chain) > 1:
        neighbours.append(flow.chain_flows(chain))
    motion = masks.motion_static_mask(np.asarray(inputs["K"]), neighbours, dilate=p.dilate)
    return {"static": motion if semantic is None else np.minimum(motion, semantic)}


# ------------------------------------------------------------------------------- priors


def depth_prior(inputs: dict[str, Any], p: Any, ctx: Any) -> dict[str, Any]:
    """Frame i -> {inv_depth float32 (H, W) median 1, confidence float32 (H, W)}."""
    from stages import priors

    image = inputs["image"]["image"]
    if p.backend == "midas":
        from stages.backends.midas_net import midas_prior

        inv = midas_prior(_cached_model("midas", p.weights), image)
        return {"inv_depth": inv.astype(np.float32), "confidence": np.ones_like(inv, np.float32)}
    from stages import flow

    K = np.asarray(inputs["K"])
    # direct flows to the far reference (more parallax) and the near one (sees what the far
    # one lost); the prior fuses both (stages.priors.geometric_prior)
    flows = []
    for ref in ("ref", "ref_near"):
        if ref in inputs:
            fl = flow.compute_pair_flow(image, inputs[ref]["image"], preset=p.preset, fb_thresh=p.fb_thresh)
            if fl["fwd_valid"].mean() >= priors.MIN_VALID_FRACTION:
                flows.append((fl["fwd"], fl["fwd_valid"]))
    out = priors.geometric_prior(image, K, flows[:1], extra=flows[1:]) if flows else None
    if out is None:
        h, w = image.shape[:2]
        out = {"inv_depth": np.ones((h, w), np.float32), "confidence": np.zeros((h, w), np.float32)}
    return {"inv_depth": out["inv_depth"].astype(np.float32),
            "confidence": out["confidence"].astype(np.float32)}


# ------------------------------------------------------------------------------- keyframes


def select_keyframes(inputs: dict[str, Any], p: Any, ctx: Any) -> dict[str, Any]:
    """All frames -> {indices, accumulated, threshold_px, motion} (JSON)."""
    from stages import keyframes

    flows, masks_ = inputs["flow"], inputs["masks"]
    n = len(masks_)
    motion = [keyframes.pair_motion(flows[i]["fwd"], flows[i]["fwd_valid"], masks_[i]["static"])
              for i in range(n - 1)]
    h, w = masks_[0]["static"].shape
    if not p.enabled:  # ablation "w/o keyframes": every frame is a keyframe
        return {"indices": list(range(n)), "accumulated": [0.0] * n, "threshold_px": 0.0,
                "motion": motion, "enabled": False}
    sel = keyframes.select_keyframes(np.asarray(motion), h, w, delta=p.delta, max_gap=p.max_gap)
    return {"indices": [int(i) for i in sel["indices"]],
            "accumulated": [float(a) for a in sel["accumulated"]],
            "threshold_px": float(sel["threshold_px"]), "motion": [float(m) for m in motion],
            "enabled": True}


# ------------------------------------------------------------------------------- association


def associate(inputs: dict[str, Any], p: Any, ctx: Any) -> dict[str, Any]:
    """Keyframes -> {graph (JSON), edge_flows [{i, j, fwd, bwd, fwd_valid, bwd_valid}]}."""
    from stages import association

    kf = inputs["keyframes"]["indices"]
    frames = inputs["ingest"]
    K = np.asarray(frames.summary["K"])
    images = [frames[i]["image"] for i in kf]
    kw: dict[str, Any] = dict(nms=p.nms, min_separation=p.min_separation,
                              min_inlier_ratio=p.min_inlier_ratio, min_consistent=p.min_consistent)
    if p.threshold is not None:
        kw["similarity_threshold"] = p.threshold
    if p.backend == "resnet18":
        from stages.backends.resnet import resnet_descriptor

        model = _cached_model("resnet18", p.weights)
        kw["descriptor_fn"] = lambda img: resnet_descriptor(model, img)
    if not p.enabled:
        kw["descriptors"] = np.eye(len(kf), dtype=np.float32)  # nothing similar: no loop edges
        kw["similarity_threshold"] = 2.0
    graph, edge_flows = association.build_graph(kf, images, K, inputs["keyframes"]["threshold_px"] or 1e9, **kw)
    flows_out = [{"i": int(a), "j": int(b), **{k: v for k, v in fl.items() if k in ("fwd", "bwd", "fwd_valid", "bwd_valid")}}
                 for (a, b), fl in sorted(edge_flows.items())]
    return {"graph": graph, "edge_flows": flows_out}


# ------------------------------------------------------------------------------- optimisation

# Config section -> OptimizeParams field names, for fields whose names differ.
_SECTION_FIELDS = {
    "optimize_edges": {"steps": "edge_steps", "lr": "edge_lr"},
    "optimize_segments": {"steps": "seg_steps", "lr": "seg_lr", "loss_scale": "seg_loss_scale",
                          "pair_power": "seg_pair_power", "grad_mult": "seg_grad_mult",
                          "window": "seg_window"},
}


def optimize_params(bundle: Any) -> dict[str, Any]:
    """Flatten the config sections a stage reads into ``stages.optimize.OptimizeParams`` fields."""
    import dataclasses

    from stages.optimize import OptimizeParams

    known = {f.name for f in dataclasses.fields(OptimizeParams)}
    out: dict[str, Any] = {}
    for section in ("depth", "losses", "optimize_keyframes", "optimize_edges", "optimize_segments"):
        model = getattr(bundle, section, None)
        if model is None:
            continue
        rename = _SECTION_FIELDS.get(section, {})
        for k, v in model.model_dump().items():
            name = rename.get(k, k)
            if name in known:
                out[name] = tuple(v) if isinstance(v, list) else v
    return out


class _torch_threads:
    """Run with a fixed number of torch threads: float reductions split differently across
    threads give different bits, so the thread count is a parameter (in the key), not an
    accident of the machine or of OMP_NUM_THREADS."""

    def __init__(self, n: int):
        self.n = n

    def __enter__(self) -> None:
        import torch

        self.prev = torch.get_num_threads()
        torch.set_num_threads(self.n)

    def __exit__(self, *exc: Any) -> None:
        import torch

        torch.set_num_threads(self.prev)


def _stack(items: Any, indices: list[int], field: str) -> np.ndarray:
    return np.stack([np.asarray(items[i][field]) for i in indices])


def _flow_dict(fl: dict[str, Any]) -> dict[str, np.ndarray]:
    return {k: np.asarray(fl[k]) for k in ("fwd", "bwd", "fwd_valid", "bwd_valid")}


class _LazyStack:
    """field of a map stage's items as a lazily loaded (N, ...) array: ``x[a:b]`` and
    ``x[[i, j]]`` stack just those items, ``x[i]`` loads one. Lets optimize_segments hold one
    window of images / priors / masks instead of the whole clip."""

    def __init__(self, items: Any, field: str):
        self._items, self._field = items, field

    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, i: Any) -> np.ndarray:
        if isinstance(i, slice):
            return _stack(self._items, list(range(*i.indices(len(self._items)))), self._field)
        if isinstance(i, (list, tuple, np.ndarray)):
            return _stack(self._items, [int(j) for j in i], self._field)
        return np.asarray(self._items[int(i)][self._field])


class _LazyFlows:
    """flows[i] -> flow dict of pair (i, i+1), loaded when indexed (not all held in memory:
    at 256x192 one pair is ~0.9 MB, so a 1000-frame clip would hold ~0.9 GB of flows)."""

    def __init__(self, items: Any, keep: int = 48):
        self._items = items
        self._keep = keep  # a window's worth stays decoded (windows re-read their flows)
        self._cache: dict[int, dict[str, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, i: int) -> dict[str, np.ndarray]:
        hit = self._cache.pop(i, None)
        if hit is None:
            hit = _flow_dict(self._items[i])
        self._cache[i] = hit  # most recently used last
        while len(self._cache) > self._keep:
            self._cache.pop(next(iter(self._cache)))
        return hit


def optimize_keyframes(inputs: dict[str, Any], b: Any, ctx: Any) -> dict[str, Any]:
    """Keyframe windows -> {keyframes, poses (K,4,4) c2w, depths [K x (H,W)], rel_poses, state}."""
    from stages import optimize

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
    with _torch_threads(b.optimize_keyframes.threads):
        res = optimize.optimize_keyframes(
            _stack(frames, kf, "image"), _stack(inputs["priors"], kf, "inv_depth"),
            _stack(inputs["masks"], kf, "static"), np.asarray(frames.summary["K"]), pair_flows,
            params=optimize_params(b), seed=ctx.seed, checkpointer=ctx.checkpointer)
    return {"keyframes": kf, "poses": np.asarray(res["poses"], np.float64),
            "depths": [np.asarray(d, np.float32) for d in res["depths"]],
            "rel_poses": [{"a": int(r["a"]), "b": int(r["b"]), "tau": int(r["tau"]),
                           "T": np.asarray(r["T"], np.float64)} for r in res["rel_poses"]],
            "state": {k: np.asarray(v) for k, v in res["state"].items()}}


def optimize_edges(inputs: dict[str, Any], b: Any, ctx: Any) -> dict[str, Any]:
    """Verified non-sequential keyframe pairs -> {edges: [{a, b, i, j, T_ab, loss}]}.

    T_ab follows stages.optimize (camera a -> camera b coordinates, inv(P_b) @ P_a).
    """
    from stages import optimize

    okf = inputs["optimize_keyframes"]
    kf = list(okf["keyframes"])
    pos = {f: k for k, f in enumerate(kf)}
    P = np.asarray(okf["poses"])
    frames, priors_, masks_ = inputs["ingest"], inputs["priors"], inputs["masks"]
    K = np.asarray(frames.summary["K"])
    flows = {(e["i"], e["j"]): _flow_dict(e) for e in inputs["association"]["edge_flows"]}
    params = optimize_params(b)
    edges = []
    for n, e in enumerate(inputs["association"]["graph"].get("nonsequential_edges", [])):
        i, j = int(e["i"]), int(e["j"])
        a, c = pos[i], pos[j]
        with _torch_threads(b.optimize_keyframes.threads):
            res = optimize.optimize_edge(
                frames[i]["image"], frames[j]["image"], priors_[i]["inv_depth"], priors_[j]["inv_depth"],
                masks_[i]["static"], masks_[j]["static"], K, flows[(i, j)], _inv(P[c]) @ P[a],
                params=params, seed=ctx.seed + n)
        edges.append({"a": a, "b": c, "i": i, "j": j, "T_ab": np.asarray(res["T_ab"], np.float64),
                      "loss": float(res["loss"])})
    return {"edges": edges}


def pose_graph(inputs: dict[str, Any], p: Any, ctx: Any) -> dict[str, Any]:
    """Keyframe poses + sequential and loop edges -> globally consistent keyframe poses."""
    from stages import pose_graph as pg

    okf = inputs["optimize_keyframes"]
    P = np.asarray(okf["poses"], np.float64)
    if not p.enabled or len(P) < 2:
        return {"poses": P, "enabled": False, "iterations": 0, "initial_error": 0.0, "final_error": 0.0}
    # stages.optimize gives T = inv(P_b) @ P_a; the pose graph measures inv(P_a) @ P_b.
    edges = [{"a": r["a"], "b": r["b"], "T_ab": _inv(r["T"]), "weight": 1.0 / r["tau"]} for r in okf["rel_poses"]]
    rejected = []
    for e in inputs["optimize_edges"]["edges"]:
        meas = _inv(e["T_ab"])
        # Gate gross outliers: drift bends a trajectory by degrees, not tens of degrees, so a
        # loop measurement that disagrees that much with odometry is a failed edge optimisation.
        odo = np.linalg.inv(P[e["a"]]) @ P[e["b"]]
        dR = odo[:3, :3].T @ meas[:3, :3]
        angle = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
        if angle > p.max_loop_rotation_deg:
            rejected.append({"i": e["i"], "j": e["j"], "rotation_disagreement_deg": angle})
            continue
        edges.append({"a": e["a"], "b": e["b"], "T_ab": meas, "weight": p.loop_weight})
    if rejected:
        ctx.log(f"ignored {len(rejected)} loop edge(s) disagreeing with odometry by > {p.max_loop_rotation_deg} deg")
    res = pg.optimize_pose_graph(P, edges, kind=p.kind, max_iterations=p.max_iterations)
    return {"poses": np.asarray(res["poses"], np.float64), "enabled": True,
            "iterations": int(res["iterations"]), "initial_error": float(res["initial_error"]),
            "final_error": float(res["final_error"]), "rejected_loops": rejected}


def optimize_segments(inputs: dict[str, Any], b: Any, ctx: Any) -> dict[str, Any]:
    """All frames with keyframe poses frozen -> {poses (N,4,4) c2w, depths [N x (H,W)]}."""
    from stages import optimize

    frames, flows = inputs["ingest"], inputs["flow"]
    okf = inputs["optimize_keyframes"]
    with _torch_threads(b.optimize_keyframes.threads):
        res = optimize.optimize_segments(
            _LazyStack(frames, "image"), _LazyStack(inputs["priors"], "inv_depth"),
            _LazyStack(inputs["masks"], "static"), np.asarray(frames.summary["K"]),
            _LazyFlows(flows), list(okf["keyframes"]),
            np.asarray(inputs["pose_graph"]["poses"]), np.stack(okf["depths"]),
            params=optimize_params(b), seed=ctx.seed, checkpointer=ctx.checkpointer, state=okf["state"])
    return {"poses": np.asarray(res["poses"], np.float64),
            "depths": [np.asarray(d, np.float32) for d in res["depths"]]}


# ------------------------------------------------------------------------------- depth filter


def fuse_depth(inputs: dict[str, Any], p: Any, ctx: Any) -> dict[str, Any]:
    """Frame i's optimised depth fused with its multi-view triangulation -> {depth float32 (H, W),
    measured float (fraction of pixels triangulated)}."""
    from stages import depth_fusion

    depth = np.asarray(inputs["depth"], np.float32)
    if not p.enabled:
        return {"depth": depth, "measured": 0.0}
    poses = np.asarray(inputs["poses"], np.float64)
    i = int(inputs["index"])
    refs = [(inputs[k]["image"], poses[int(inputs[f"index_{k}"])]) for k in sorted(inputs)
            if k.startswith("ref") and not k.startswith("index")]
    fused, measured = depth_fusion.fuse_depth(
        inputs["image"]["image"], depth, poses[i], refs, np.asarray(inputs["K"]), preset=p.preset,
        fb_thresh=p.fb_thresh, min_angle_deg=p.min_angle_deg, max_log_dev=p.max_log_dev)
    return {"depth": fused, "measured": measured}


def filter_depth(inputs: dict[str, Any], p: Any, ctx: Any) -> dict[str, Any]:
    """Frame i's depth filtered with its +-radius neighbours -> {depth float32 (H, W)}."""
    from stages import depth_filter

    m = len([k for k in inputs if k.startswith("d")])
    depths = np.stack([np.asarray(inputs[f"d{k:02d}"]["depth"]) for k in range(m)])
    center = int(inputs["center"])
    if not p.enabled or m == 1:
        return {"depth": depths[center].astype(np.float32)}
    fwd = np.stack([inputs[f"f{k:02d}"]["fwd"] for k in range(m - 1)])
    bwd = np.stack([inputs[f"f{k:02d}"]["bwd"] for k in range(m - 1)])
    out = depth_filter.filter_depth(depths, fwd, bwd, center, radius=p.radius, border=p.border)
    return {"depth": np.asarray(out, np.float32)}
