"""Keyframe pose-graph optimisation with gtsam Levenberg-Marquardt (docs/design.md, "Stage: pose_graph").

Nodes are keyframe poses T_w_k (camera-to-world). Each edge (a, b) carries a measured relative
pose ``T_a_b = inv(T_w_a) @ T_w_b`` (camera-b coordinates -> camera-a coordinates, i.e. camera b
expressed in camera a; gtsam's ``between(a, b)``) and an information weight:
sequential edges at distance tau have weight 1/tau, verified non-sequential (loop) edges 1.
The information matrix of an edge is ``weight * I`` (noise sigma = 1/sqrt(weight)) over the
tangent space (6-D for SE(3), 7-D for Sim(3)). The ``fixed`` keyframe gets a tight prior so
the gauge (and, for Sim(3), the global scale) is pinned.

Sim(3) convention. Node k is the similarity S_k = [s_k R_k | t_k] mapping camera-k coordinates
in the *local* depth units of keyframe k to world: x_w = s_k R_k x_c + t_k. The relative
measurement S_a_b = inv(S_a) @ S_b = [(s_b/s_a) R_a_b | t_a_b] has its translation in a's local
units and scale ratio s_a_b = s_b/s_a; edges produced inside one optimisation window share one
scale (s_a_b = 1, the default) while a loop edge may report the scale ratio it observed. Monocular
scale drift then shows up as an inconsistency that only Sim(3) nodes can absorb. The returned
``poses`` are rigid (R_k, t_k) and ``scales`` holds s_k (all 1 for SE(3)).

gtsam's Similarity3(R, t, s) has matrix [R t; 0 1/s], i.e. the projective equivalent of
[sR st; 0 1]; helpers below convert so that gtsam's compose/between equal our 4x4 products.
"""

from __future__ import annotations

import logging
from typing import Any, Callable, Literal, TypedDict

import gtsam
import numpy as np

from gcvd_flow.stages.geometry.se3 import loop_disagreement_deg

log = logging.getLogger(__name__)

MAX_ITERATIONS: int = 100
PRIOR_SIGMA: float = 1e-6


class PoseGraphResult(TypedDict):
    poses: np.ndarray  # (K, 4, 4) float64 T_w_k (camera-to-world), rigid
    scales: np.ndarray  # (K,) float64, Sim(3) node scales (1 for SE(3))
    initial_error: float
    final_error: float
    iterations: int


def _sim3_from_matrix(m: np.ndarray) -> gtsam.Similarity3:
    """[sR | t] (4x4, bottom row 0 0 0 1) -> gtsam.Similarity3 acting identically."""
    a = np.asarray(m, dtype=np.float64)[:3, :3]
    s = float(np.cbrt(np.linalg.det(a)))
    r = a / s
    # Re-orthonormalise: accumulated float error would make Rot3 reject / drift the matrix.
    u, _, vt = np.linalg.svd(r)
    r = u @ vt
    t = np.asarray(m, dtype=np.float64)[:3, 3]
    return gtsam.Similarity3(gtsam.Rot3(r), t / s, s)


def _matrix_from_sim3(s3: gtsam.Similarity3) -> tuple[np.ndarray, float]:
    """gtsam.Similarity3 -> (rigid 4x4 [R | t_world], scale s) in our convention."""
    s = float(s3.scale())
    r = s3.rotation().matrix()
    t = np.asarray(s3.translation(), dtype=np.float64).reshape(3) * s
    out = np.eye(4)
    out[:3, :3] = r
    out[:3, 3] = t
    return out, s


def _pose3(m: np.ndarray) -> gtsam.Pose3:
    """Rigid 4x4 -> gtsam.Pose3 (rotation re-orthonormalised)."""
    m = np.asarray(m, dtype=np.float64)
    u, _, vt = np.linalg.svd(m[:3, :3])
    return gtsam.Pose3(gtsam.Rot3(u @ vt), m[:3, 3].copy())


def edge_measurement(T_w_a: np.ndarray, T_w_b: np.ndarray) -> np.ndarray:
    """T_a_b = inv(T_w_a) @ T_w_b (4, 4) for camera-to-world poses: the edge measurement
    ``T_a_b`` of this module (the inverse of ``stages.geometry.torch_ops.relative_pose``, which
    gives T_b_a).
    """
    return np.linalg.inv(np.asarray(T_w_a, np.float64)) @ np.asarray(T_w_b, np.float64)


def optimize_pose_graph(
    init_poses: np.ndarray,
    edges: list[dict[str, Any]],
    kind: Literal["se3", "sim3"] = "se3",
    fixed: int = 0,
    max_iterations: int = MAX_ITERATIONS,
) -> PoseGraphResult:
    """Optimise keyframe poses.

    Args:
        init_poses: (K, 4, 4) float64 T_w_k (camera-to-world) initial keyframe poses.
        edges: dicts with ``a``, ``b`` (node indices 0..K-1), ``T_a_b`` (4, 4) measured
            relative pose inv(T_w_a) @ T_w_b, ``weight`` (information multiplier), and for
            ``kind="sim3"`` optionally ``s_a_b`` (scale ratio s_b/s_a, default 1). Instead of
            ``T_a_b`` an edge may carry ``T_b_a`` = inv(T_w_b) @ T_w_a (camera a -> camera b),
            the convention of ``stages.optimize`` (``rel_poses[*]["T_b_a"]``,
            ``optimize_edge(...)["T_b_a"]``) and ``stages.geometry.torch_ops.relative_pose``;
            it is inverted here.
        kind: "se3" (paper) or "sim3" (absorbs monocular scale drift).
        fixed: node pinned by a tight prior at its initial pose (and scale 1).
        max_iterations: LM iteration cap (paper and docs/design.md: 100).

    Returns:
        dict(poses (K, 4, 4) T_w_k, scales (K,), initial_error, final_error, iterations), errors
        being gtsam's total factor-graph error 0.5 * sum of squared whitened residuals.
    """
    init = np.asarray(init_poses, dtype=np.float64)
    if init.ndim != 3 or init.shape[1:] != (4, 4):
        raise ValueError(f"init_poses must be (K, 4, 4), got {init.shape}")
    n = init.shape[0]
    if not 0 <= fixed < n:
        raise ValueError(f"fixed node {fixed} outside 0..{n - 1}")
    if kind not in ("se3", "sim3"):
        raise ValueError(f"kind must be 'se3' or 'sim3', got {kind!r}")
    sim = kind == "sim3"
    graph, values = _build_graph(init, edges, sim, fixed)

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(max_iterations))
    # Fixed ordering choice -> deterministic elimination.
    params.setOrderingType("COLAMD")
    initial_error = float(graph.error(values))
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    final_error = float(graph.error(result))

    poses = np.empty_like(init)
    scales = np.ones(n, dtype=np.float64)
    for k in range(n):
        if sim:
            poses[k], scales[k] = _matrix_from_sim3(result.atSimilarity3(k))
        else:
            poses[k] = result.atPose3(k).matrix()
    log.debug(
        "pose graph %s: %d nodes, %d edges, error %.4g -> %.4g in %d iterations",
        kind, n, len(edges), initial_error, final_error, optimizer.iterations(),
    )
    return PoseGraphResult(
        poses=poses,
        scales=scales,
        initial_error=initial_error,
        final_error=final_error,
        iterations=int(optimizer.iterations()),
    )


def _rotation_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def gate_loops(T_w_k: np.ndarray, loops: list[dict[str, Any]], max_rotation_deg: float, weight: float,
               self_check_deg: float = 0.0, robust: float = 0.0,
               own_rotation: Callable[[dict[str, Any]], np.ndarray | None] | None = None,
               ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Loop edges {a, b, i, j, T_b_a} -> (pose-graph edges, rejected).

    An edge whose rotation agrees with the odometry T_w_k (K, 4, 4) within ``max_rotation_deg``
    is kept (weight ``weight``). The odometry drifts, and over a long loop its rotation error alone
    can pass any fixed gate, so an edge that fails it is kept on its own evidence when
    ``self_check_deg`` > 0 and ``own_rotation(edge)`` (the loop pair's two-view rotation R_b_a
    (3, 3) from its own flow, or None: no evidence) is within ``self_check_deg`` of the edge's:
    the edge's optimisation and the pair's epipolar geometry agree independently of the odometry.
    Such an edge carries a Cauchy kernel of scale ``robust`` (0: none) in the graph, so a
    consistent but wrong loop (a look-alike place) bends the trajectory less.
    Rejected: {i, j, rotation_disagreement_deg, and own_rotation_deg where the pair's own rotation
    was compared}."""
    kept: list[dict[str, Any]] = []
    rejected: list[dict[str, Any]] = []
    for e in loops:
        angle = loop_disagreement_deg(T_w_k[e["a"]], T_w_k[e["b"]], e["T_b_a"])
        edge = {"a": e["a"], "b": e["b"], "T_b_a": e["T_b_a"], "weight": weight}
        if angle <= max_rotation_deg:
            kept.append(edge)
            continue
        own = own_rotation(e) if self_check_deg > 0 and own_rotation is not None else None
        own_deg = None if own is None else _rotation_deg(np.asarray(own).T @ np.asarray(e["T_b_a"])[:3, :3])
        if own_deg is not None and own_deg <= self_check_deg:
            kept.append({**edge, "robust": robust} if robust > 0 else edge)
            continue
        rejected.append({"i": e["i"], "j": e["j"], "rotation_disagreement_deg": angle,
                         **({} if own_deg is None else {"own_rotation_deg": own_deg})})
    return kept, rejected


def loop_pair_rotation(fwd: np.ndarray, valid: np.ndarray, K: np.ndarray, min_pixels: int = 200) -> np.ndarray | None:
    """The rotation R_b_a (3, 3) of a loop pair from its own forward flow a -> b (H, W, 2) px on
    the consistent pixels ``valid`` (H, W) (essential matrix, or a homography when the pair barely
    translates: ``stages.optimize.init.two_view_pose``); None with fewer than ``min_pixels``."""
    from gcvd_flow.stages.optimize.init import two_view_pose

    if int(np.count_nonzero(valid)) < min_pixels:
        return None
    T_b_a, _ = two_view_pose(np.asarray(fwd, np.float32), np.asarray(valid, bool), np.asarray(K, np.float64))
    return T_b_a[:3, :3]


def _build_graph(
    init: np.ndarray, edges: list[dict[str, Any]], sim: bool, fixed: int
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """Factor graph (prior on ``fixed`` + one between factor per edge) and initial values from
    T_w_k (K, 4, 4); Sim(3) nodes if ``sim``, else SE(3)."""
    n = init.shape[0]
    dim = 7 if sim else 6
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k in range(n):
        if sim:
            values.insert(k, _sim3_from_matrix(init[k]))
        else:
            values.insert(k, _pose3(init[k]))

    prior_noise = gtsam.noiseModel.Isotropic.Sigma(dim, PRIOR_SIGMA)
    if sim:
        graph.add(gtsam.PriorFactorSimilarity3(fixed, _sim3_from_matrix(init[fixed]), prior_noise))
    else:
        graph.add(gtsam.PriorFactorPose3(fixed, _pose3(init[fixed]), prior_noise))

    for e in edges:
        a, b = int(e["a"]), int(e["b"])
        if not (0 <= a < n and 0 <= b < n) or a == b:
            raise ValueError(f"bad edge ({a}, {b}) for {n} nodes")
        weight = float(e.get("weight", 1.0))
        if not weight > 0:
            raise ValueError(f"edge ({a}, {b}) weight must be > 0, got {weight}")
        noise: gtsam.noiseModel.Base = gtsam.noiseModel.Isotropic.Sigma(dim, 1.0 / np.sqrt(weight))
        robust = float(e.get("robust", 0.0))
        if robust > 0:  # Cauchy on the whitened residual: a wrong edge pulls less the more it disagrees
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(robust), noise)
        T_a_b = _edge_T_a_b(e, a, b)
        if sim:
            s_a_b = float(e.get("s_a_b", 1.0))
            m = T_a_b.copy()
            u, _, vt = np.linalg.svd(m[:3, :3])
            m[:3, :3] = s_a_b * (u @ vt)
            graph.add(gtsam.BetweenFactorSimilarity3(a, b, _sim3_from_matrix(m), noise))
        else:
            graph.add(gtsam.BetweenFactorPose3(a, b, _pose3(T_a_b), noise))
    return graph, values


def _edge_T_a_b(e: dict[str, Any], a: int, b: int) -> np.ndarray:
    """The edge's measurement T_a_b (4, 4) float64, from ``T_a_b`` or by inverting ``T_b_a``."""
    if ("T_a_b" in e) == ("T_b_a" in e):
        raise ValueError(f"edge ({a}, {b}) needs exactly one of T_a_b, T_b_a")
    if "T_a_b" in e:
        return np.asarray(e["T_a_b"], dtype=np.float64)
    return np.linalg.inv(np.asarray(e["T_b_a"], dtype=np.float64))
