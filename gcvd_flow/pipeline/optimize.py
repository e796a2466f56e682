"""Blocks optimize_keyframes, optimize_edges, pose_graph, bundle_adjustment and optimize_segments
(stages/optimize)."""

from __future__ import annotations

from typing import Any

import numpy as np

from gcvd_flow.engine.dag import Stage
from gcvd_flow.pipeline.context import StageContext
from gcvd_flow.pipeline.frontend import CALIBRATE, FLOW, INGEST
from gcvd_flow.pipeline.graph import ASSOCIATION, KEYFRAMES
from gcvd_flow.pipeline.masks import MASKS
from gcvd_flow.pipeline.priors import PRIORS
from gcvd_flow.pipeline.registry import config_section, declare, section, section_from_dataclass
from gcvd_flow.pipeline.shared import _hard_mask, _HardMasks, _user_keeps
from gcvd_flow.stages.graph import keyframes as keyframes_mod
from gcvd_flow.stages.optimize import params as opt_params

# ============================================================================== optimisation: shared
DepthParams = config_section("depth")(section_from_dataclass(opt_params.DepthModel, "DepthParams"))
LossParams = config_section("losses")(section_from_dataclass(opt_params.LossWeights, "LossParams"))
OptimizeKeyframesParams = config_section("optimize_keyframes")(
    section_from_dataclass(opt_params.KeyframeSettings, "OptimizeKeyframesParams"))
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
def run_optimize_keyframes(inputs: dict[str, Any], b: Any, ctx: StageContext) -> dict[str, Any]:
    """Keyframe windows -> {keyframes, poses (K,4,4) T_w_c, depths [K x (H,W)],
    rel_poses [{a, b, tau, T_b_a = inv(T_w_b) @ T_w_a}], state, windows}."""
    # heavy (torch / gtsam / scipy): imported when the stage runs, not when the CLI starts
    from gcvd_flow.stages.optimize import keyframes as opt_keyframes

    kf = list(inputs["keyframes"]["indices"])
    frames = inputs["ingest"]
    pair_flows = keyframes_mod.keyframe_pair_flows(kf, inputs["association"]["edge_flows"])
    res = opt_keyframes.optimize_keyframes(
        _stack(frames, kf, "image"), _stack(inputs["priors"], kf, "inv_depth"),
        np.stack([_hard_mask(inputs["masks"][i]) for i in kf]), np.asarray(inputs["calibrate"]["K"]), pair_flows,
        depth=b.depth, losses=b.losses, kf=b.optimize_keyframes, seed=ctx.seed, checkpointer=ctx.checkpointer,
        window_map=ctx.map)  # schedule=independent: the windows side by side on the run's workers
    return {"keyframes": kf, "poses": np.asarray(res["poses"], np.float64),
            "depths": [np.asarray(d, np.float32) for d in res["depths"]],
            "rel_poses": [{"a": int(r["a"]), "b": int(r["b"]), "tau": int(r["tau"]),
                           "T_b_a": np.asarray(r["T_b_a"], np.float64)} for r in res["rel_poses"]],
            "state": {k: np.asarray(v) for k, v in res["state"].items()},
            "windows": res["windows"]}  # per window: pairs, points per step, steps run (plateau stop)


OPTIMIZE_KEYFRAMES = declare(Stage("optimize_keyframes", run_optimize_keyframes,
                           deps=(INGEST, CALIBRATE, PRIORS, MASKS, KEYFRAMES, ASSOCIATION), params=OPT,
                           kind="keyframe_solution", uses_seed=True))


# ============================================================================== optimize_edges
def run_optimize_edges(inputs: dict[str, Any], b: Any, ctx: StageContext) -> dict[str, Any]:
    """Verified non-sequential keyframe pairs -> {edges: [{a, b, i, j, T_b_a, loss}]}, a, b keyframe
    positions, i, j frame indices, T_b_a = inv(T_w_b) @ T_w_a (camera a -> camera b coordinates)."""
    # heavy (torch / gtsam / scipy): imported when the stage runs, not when the CLI starts
    from gcvd_flow.stages.optimize import edges as opt_edges

    okf = inputs["optimize_keyframes"]
    kf = list(okf["keyframes"])
    pos = {f: k for k, f in enumerate(kf)}
    T_w_k = np.asarray(okf["poses"])
    frames, priors_, masks_ = inputs["ingest"], inputs["priors"], inputs["masks"]
    K = np.asarray(inputs["calibrate"]["K"])
    flows = {(e["i"], e["j"]): _flow_dict(e) for e in inputs["association"]["edge_flows"]}
    graph_edges = [(int(e["i"]), int(e["j"])) for e in inputs["association"]["graph"].get("nonsequential_edges", [])]

    def calls():  # built lazily: only the edges in flight are in memory
        for n, (i, j) in enumerate(graph_edges):
            yield dict(img_a=frames[i]["image"], img_b=frames[j]["image"], prior_a=priors_[i]["inv_depth"],
                       prior_b=priors_[j]["inv_depth"], mask_a=_hard_mask(masks_[i]), mask_b=_hard_mask(masks_[j]), K=K,
                       flow=flows[(i, j)], init_T_b_a=_inv(T_w_k[pos[j]]) @ T_w_k[pos[i]], depth=b.depth,
                       losses=b.losses, kf=b.optimize_keyframes, edge=b.optimize_edges, seed=ctx.seed + n)

    edges = []
    # the edges are independent: side by side on the run's workers (same result wherever)
    for (i, j), res in zip(graph_edges, ctx.map(opt_edges.optimize_edge_call, calls())):
        edges.append({"a": pos[i], "b": pos[j], "i": i, "j": j, "T_b_a": np.asarray(res["T_b_a"], np.float64),
                      "loss": float(res["loss"])})
    return {"edges": edges}


OPTIMIZE_EDGES = declare(Stage("optimize_edges", run_optimize_edges,
                       deps=(INGEST, CALIBRATE, PRIORS, MASKS, ASSOCIATION, OPTIMIZE_KEYFRAMES),
                       params=OPT + ("optimize_edges",), kind="edges", uses_seed=True))


# ============================================================================== pose_graph
PoseGraphParams = section("pose_graph", opt_params.PoseGraphSettings)


def run_pose_graph(inputs: dict[str, Any], p: Any, ctx: StageContext) -> dict[str, Any]:
    """Keyframe poses + sequential and loop edges -> globally consistent keyframe poses."""
    # heavy (torch / gtsam / scipy): imported when the stage runs, not when the CLI starts
    from gcvd_flow.stages.optimize import pose_graph as pose_graph_mod

    okf = inputs["optimize_keyframes"]
    T_w_k = np.asarray(okf["poses"], np.float64)
    if not p.enabled or len(T_w_k) < 2:
        return {"poses": T_w_k, "enabled": False, "iterations": 0, "initial_error": 0.0, "final_error": 0.0}
    # edges T_b_a = inv(T_w_b) @ T_w_a as the optimisations give them (the pose graph inverts)
    edges = [{"a": r["a"], "b": r["b"], "T_b_a": r["T_b_a"], "weight": 1.0 / r["tau"]} for r in okf["rel_poses"]]
    K = np.asarray(inputs["calibrate"]["K"])

    def own_rotation(e: dict[str, Any]) -> np.ndarray | None:  # the loop pair's two-view rotation, on demand
        fl = next(f for f in inputs["association"]["edge_flows"] if (int(f["i"]), int(f["j"])) == (e["i"], e["j"]))
        return pose_graph_mod.loop_pair_rotation(np.asarray(fl["fwd"]), np.asarray(fl["fwd_valid"]), K)

    # Gate gross outliers: a loop measurement that disagrees by tens of degrees with odometry is a
    # failed edge optimisation, unless (loop_self_check_deg) the pair's own geometry vouches for it
    loops, rejected = pose_graph_mod.gate_loops(
        T_w_k, inputs["optimize_edges"]["edges"], p.max_loop_rotation_deg, p.loop_weight,
        self_check_deg=p.loop_self_check_deg, robust=p.loop_robust, own_rotation=own_rotation)
    edges += loops
    if rejected:
        ctx.log(f"ignored {len(rejected)} loop edge(s) disagreeing with odometry by > {p.max_loop_rotation_deg} deg")
    res = pose_graph_mod.optimize_pose_graph(T_w_k, edges, kind=p.kind, max_iterations=p.max_iterations)
    return {"poses": np.asarray(res["poses"], np.float64), "enabled": True,
            "iterations": int(res["iterations"]), "initial_error": float(res["initial_error"]),
            "final_error": float(res["final_error"]), "rejected_loops": rejected}


POSE_GRAPH = declare(Stage("pose_graph", run_pose_graph, deps=(CALIBRATE, ASSOCIATION, OPTIMIZE_KEYFRAMES, OPTIMIZE_EDGES),
                   params="pose_graph", kind="poses"))


# ============================================================================== bundle_adjustment
BundleAdjustmentParams = section("bundle_adjustment", opt_params.BundleAdjustmentSettings)


def run_bundle_adjustment(inputs: dict[str, Any], p: opt_params.BundleAdjustmentSettings, ctx: StageContext) -> dict[str, Any]:
    """Pose-graph keyframe poses -> {poses (K, 4, 4) T_w_k refined over flow tracks, statistics}."""
    pg = inputs["pose_graph"]
    T_w_k = np.asarray(pg["poses"], np.float64)
    if not p.enabled:
        return {"poses": T_w_k, "enabled": False, "depth_scale": np.ones(len(T_w_k))}
    # heavy (torch / gtsam / scipy): imported when the stage runs, not when the CLI starts
    from threadpoolctl import threadpool_limits

    from gcvd_flow.io.native_output import native_stdout_silenced
    from gcvd_flow.stages.optimize import bundle_adjustment as ba_mod

    okf = inputs["optimize_keyframes"]
    edges = {(int(e["i"]), int(e["j"])): _flow_dict(e) for e in inputs["association"]["edge_flows"]}
    # numpy's OpenBLAS on one thread: its idle threads spin (OMP_WAIT_POLICY does not reach its
    # pthreads), so two runs adjusting at once on two cores took 55 s instead of 1.6; a second
    # thread bought nothing alone (2.4 vs 2.4 s), and one thread makes the result independent of
    # the machine's core count (OpenBLAS's default thread count changed the poses' bits)
    with native_stdout_silenced(), threadpool_limits(limits=1, user_api="blas"):
        res = ba_mod.bundle_adjust(T_w_k, [np.asarray(d) for d in okf["depths"]], edges, list(okf["keyframes"]),
                                   np.asarray(inputs["calibrate"]["K"]), p,
                                   keep=_user_keeps(inputs["masks"], okf["keyframes"]))
    ctx.log(f"{res['landmarks']} tracks, {res['observations']} observations, median reprojection error "
            f"{res['initial_median_px']:.2f} -> {res['final_median_px']:.2f} px"
            + (" (poses kept: already consistent with the tracks)" if res["skipped"] and res["landmarks"] else ""))
    return {"poses": np.asarray(res["poses"], np.float64), "enabled": True, "landmarks": res["landmarks"],
            "observations": res["observations"], "initial_median_px": res["initial_median_px"],
            "final_median_px": res["final_median_px"], "iterations": res["iterations"],
            "skipped": bool(res["skipped"]), "depth_scale": np.asarray(res["depth_scale"], np.float64)}


BUNDLE_ADJUSTMENT = declare(Stage("bundle_adjustment", run_bundle_adjustment,
                                  deps=(INGEST, CALIBRATE, MASKS, ASSOCIATION, OPTIMIZE_KEYFRAMES, POSE_GRAPH),
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


def run_optimize_segments(inputs: dict[str, Any], b: Any, ctx: StageContext) -> dict[str, Any]:
    """All frames with keyframe poses frozen -> {poses (N,4,4) T_w_c, depths [N x (H,W)]}.

    The windows are solved side by side on the run's worker processes (``ctx.map``; the result
    does not depend on where). Images, priors and masks are read one window at a time (lazily
    stacked fields) and flows through a window-sized cache of decoded items, and each window's
    depth maps go to the store as soon as they are final (``ctx.put``): memory stays flat in the
    clip length (at 256x192 one flow pair is ~0.9 MB, one depth map 0.19 MB)."""
    # heavy (torch / gtsam / scipy): imported when the stage runs, not when the CLI starts
    from gcvd_flow.stages.optimize import segments as opt_segments

    frames, flows = inputs["ingest"], inputs["flow"]
    okf, ba = inputs["optimize_keyframes"], inputs["bundle_adjustment"]
    masks_ = inputs["masks"]
    hard = _HardMasks(masks_) if "user_keep" in masks_[0] else masks_.field("solve")  # --masks: int8, -1 = user's
    res = opt_segments.optimize_segments(
        frames.field("image"), inputs["priors"].field("inv_depth"), hard,
        np.asarray(inputs["calibrate"]["K"]), _FlowDicts(flows.recent(48)), list(okf["keyframes"]),
        np.asarray(ba["poses"]), _ScaledDepths(okf["depths"], np.asarray(ba["depth_scale"], np.float32)),
        depth=b.depth, losses=b.losses, kf=b.optimize_keyframes, seg=b.optimize_segments,
        seed=ctx.seed, checkpointer=ctx.checkpointer, state=okf["state"], depth_sink=lambda i, d: ctx.put(d),
        window_map=ctx.map)
    # depths: one handle per frame, each depth map stored when its window finished
    return {"poses": np.asarray(res["poses"], np.float64), "depths": res["depths"]}


OPTIMIZE_SEGMENTS = declare(Stage("optimize_segments", run_optimize_segments,
                          deps=(INGEST, CALIBRATE, FLOW, PRIORS, MASKS, OPTIMIZE_KEYFRAMES, BUNDLE_ADJUSTMENT),
                          params=OPT + ("optimize_segments",), kind="segment_solution", uses_seed=True))
