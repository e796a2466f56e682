"""Non-sequential (loop) edge optimisation: the relative pose of a verified keyframe pair.

The two frames form one window: camera a is the reference (identity, fixed), camera b's pose
T_a_b = inv(T_b_a) is optimised together with both depths. Relative poses follow
T_b_a = inv(T_w_b) @ T_w_a (camera a -> camera b coordinates).
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np
import torch

from gcvd_flow.stages.frontend.user_masks import flow_target_kept, user_keep
from gcvd_flow.stages.models.depth_net import DepthNet, mesh_shape
from gcvd_flow.stages.optimize.frames import flow_at_loss_res, init_depth_full, loss_size, prepare_frames
from gcvd_flow.stages.optimize.init import sample_np, triangulate, two_view_pose
from gcvd_flow.stages.optimize.params import DepthModel, EdgeSettings, KeyframeSettings, LossWeights
from gcvd_flow.stages.optimize.solver import Pair, Solver, Window, deterministic, run_solver, torch_threads

__all__ = ["optimize_edge", "optimize_edge_call"]


def optimize_edge(
    img_a: np.ndarray,
    img_b: np.ndarray,
    prior_a: np.ndarray,
    prior_b: np.ndarray,
    mask_a: np.ndarray,
    mask_b: np.ndarray,
    K: np.ndarray,
    flow: Mapping[str, np.ndarray],
    init_T_b_a: np.ndarray,
    depth: DepthModel = DepthModel(),
    losses: LossWeights = LossWeights(),
    kf: KeyframeSettings = KeyframeSettings(),
    edge: EdgeSettings = EdgeSettings(),
    seed: int = 0,
) -> dict[str, Any]:
    """Relative pose of a verified non-sequential keyframe pair.

    Images (H, W, 3) uint8, priors (H, W), masks (H, W) uint8, K (3, 3), flow dict of (a, b),
    init_T_b_a (4, 4) = inv(T_w_b) @ T_w_a (e.g. from the keyframe poses; its translation sets
    the scale). The loss resolution, pose / mesh learning rates and points come from ``kf``.
    Depths are initialised from the priors, scaled so that triangulation with the initial pose
    agrees. Returns dict(T_b_a (4, 4) float64, loss float).
    """
    images = np.stack([img_a, img_b])
    priors = np.stack([prior_a, prior_b])
    masks = np.stack([mask_a, mask_b])
    H, W = images.shape[1:3]
    K = np.asarray(K, np.float64)
    T_b_a0 = np.asarray(init_T_b_a, np.float64)
    gshape = mesh_shape(*loss_size(H, W, kf.loss_scale)[:2], depth.mesh_vertices)
    keep_b = user_keep(mask_b)
    if keep_b is not None:  # --masks: a correspondence whose target in b mixes a user-masked pixel is out
        mask_a = (np.asarray(mask_a) > 0) & flow_target_kept(np.asarray(flow["fwd"], np.float64), keep_b)
    with torch_threads(edge.threads), deterministic(seed) as gen:
        if edge.essential_init:
            T_b_a0 = _two_view_init(flow, mask_a, K, T_b_a0)
        net = DepthNet(layer_norm=depth.layer_norm, mesh=depth.mesh, seed=seed)
        fr = prepare_frames(net, images, priors, masks, K, kf.loss_scale, gshape)
        h, w = fr.imgs.shape[-2:]
        log_m = _initial_log_scales(init_depth_full(net, images, priors), flow, mask_a, K, T_b_a0)
        fa, fb = flow_at_loss_res(flow, "fwd", h, w, fr.f), flow_at_loss_res(flow, "bwd", h, w, fr.f)
        # world = camera a: T_w_a = I, T_w_b = T_a_b = inv(T_b_a)
        base = torch.stack([torch.eye(4, dtype=torch.float64), torch.as_tensor(np.linalg.inv(T_b_a0))])
        mesh0 = torch.as_tensor(log_m, dtype=torch.float32)[:, None, None].expand(2, *gshape).clone()
        win = Window(
            fr.imgs, fr.enc, fr.static, fr.dyn_mesh, fr.K, [Pair(0, 1, 1, 1.0, *fa), Pair(1, 0, 1, 1.0, *fb)],
            base, torch.tensor([0.0, 1.0], dtype=torch.float64), mesh0, torch.ones(2), keep=fr.keep,
        )
        solver = Solver(win, net, None, edge.lr, depth, losses, kf)
        loss = run_solver(solver, gen, edge.steps, 0, None)
        T_w_c = solver.poses().detach().numpy()
    return {"T_b_a": np.linalg.inv(T_w_c[1]) @ T_w_c[0], "loss": float(loss)}


def optimize_edge_call(kwargs: dict[str, Any]) -> dict[str, Any]:
    """``optimize_edge(**kwargs)``: the edges are independent, and a process pool's map passes
    one argument."""
    return optimize_edge(**kwargs)


def _two_view_init(flow: Mapping[str, np.ndarray], mask_a: np.ndarray, K: np.ndarray, T_b_a0: np.ndarray) -> np.ndarray:
    """Rotation and translation direction re-estimated from the edge's own flow (the keyframe
    chain's drift is not inherited), |t| of ``T_b_a0`` kept; ``T_b_a0`` when that fails."""
    T_e, corr = two_view_pose(np.asarray(flow["fwd"], np.float32), np.asarray(flow["fwd_valid"], bool) & (mask_a > 0), K)
    if corr is not None:
        tn = float(np.linalg.norm(T_b_a0[:3, 3]))
        T_e[:3, 3] *= tn
        return T_e
    return T_b_a0


def _initial_log_scales(
    ref: np.ndarray, flow: Mapping[str, np.ndarray], mask_a: np.ndarray, K: np.ndarray, T_b_a0: np.ndarray
) -> np.ndarray:
    """Per-frame log depth scales (2,) of the untrained depths ref (2, H, W) that make them agree
    with triangulating the flow a -> b at pose T_b_a0 (zeros if that is not possible)."""
    log_m = np.zeros(2)
    valid = np.asarray(flow["fwd_valid"], bool) & (mask_a > 0)
    ys, xs = np.nonzero(valid)
    if len(xs) > 20 and np.linalg.norm(T_b_a0[:3, 3]) > 0:
        st = max(1, len(xs) // 3000)
        uva = np.stack([xs[::st], ys[::st]], 1).astype(np.float64)
        uvb = uva + np.asarray(flow["fwd"], np.float64)[ys[::st], xs[::st]]
        da, db, ok = triangulate(uva, uvb, K, T_b_a0)
        if ok.sum() > 20:
            log_m[0] = math.log(np.median(da[ok] / sample_np(ref[0], uva[ok])))
            log_m[1] = math.log(np.median(db[ok] / sample_np(ref[1], uvb[ok])))
    return log_m
