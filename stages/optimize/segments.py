"""Segment optimisation: all frames' poses and depths, keyframe poses frozen.

Frames are processed in windows of at most ``window`` frames cut at keyframes. Non-keyframe poses
start from PnP on flow tracks of the neighbouring keyframes (``init="pnp"``) or a geodesic
interpolation of their poses (``"interp"``); the depth model starts from the keyframe depths
reprojected into every frame (``prior="transfer"``) or from the priors (``"prior"``). Pairs
(i, i + tau), tau in ``taus``, both directions, weighted tau ** pair_power.

Poses are T_w_c (camera-to-world, 4x4 float64).

Resume: a ``checkpointer`` receives every ``checkpoint_every`` steps the global state, the
window's solver state and the depth of each finished window as its own shard; a restarted call
resumes from it bit-exactly.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch

from stages.models.depth_net import DepthNet, mesh_shape
from stages.optimize.frames import (
    FlowPair, area_resize, chained_flow, fit_mesh, flow_at_loss_res, full_depth, init_depth_full, loss_size,
    prepare_frames,
)
from stages.optimize.init import interp_pose, pnp_init, transfer_depths
from stages.optimize.params import DepthModel, KeyframeSettings, LossWeights, SegmentSettings
from stages.optimize.solver import (
    Checkpointer, Pair, Solver, Window, deterministic, load_checkpoint, run_solver, torch_threads,
)

__all__ = ["optimize_segments"]

_STAGE = "segments"  # checkpoint meta["stage"]

# window_priors(a, b) -> the depth model's prior input (b - a + 1, H, W) of frames a..b
WindowPriors = Callable[[int, int], np.ndarray]
# depth_sink(i, depth (H, W) float32) -> a handle standing for frame i's final depth (see
# ``optimize_segments``)
DepthSink = Callable[[int, np.ndarray], Any]


def optimize_segments(
    images: np.ndarray,
    priors: np.ndarray,
    static_masks: np.ndarray,
    K: np.ndarray,
    adjacent_flows: Sequence[Mapping[str, np.ndarray]],
    keyframe_indices: Sequence[int],
    keyframe_poses: np.ndarray,
    keyframe_depths: np.ndarray,
    depth: DepthModel = DepthModel(),
    losses: LossWeights = LossWeights(),
    kf: KeyframeSettings = KeyframeSettings(),
    seg: SegmentSettings = SegmentSettings(),
    seed: int = 0,
    checkpointer: Checkpointer | None = None,
    state: Mapping[str, np.ndarray] | None = None,
    depth_sink: DepthSink | None = None,
) -> dict[str, Any]:
    """Non-keyframe poses + all depths, keyframe poses frozen.

    images (N, H, W, 3) uint8; priors (N, H, W); static_masks (N, H, W); K (3, 3);
    adjacent_flows[i]: flow dict of (i, i+1); keyframe_indices (Kf,) sorted frame indices;
    keyframe_poses (Kf, 4, 4) T_w_c (frozen); keyframe_depths (Kf, H, W) initial depth of the
    keyframes (same scale as the poses; a lazy sequence of (H, W) float32 arrays will do);
    state: optional ``optimize_keyframes`` state (head weights) to start the depth head from
    (with ``prior="prior"``). Images, priors and masks may
    be lazy sequences: only one window (or chunk) of them is ever materialised. Pose / mesh
    learning rates, points, taus and flow_taus come from ``kf``.
    Returns dict(poses (N, 4, 4) float64 T_w_c, depths (N, H, W) float32).

    depth_sink: called with (frame, depth (H, W) float32) as soon as a window is final (a window's
    boundary keyframe again by the next window, which overrides it); the stage then keeps only
    the returned handles, returned as ``depths`` (a list of N handles) and given to the
    checkpointer as the finished windows' shards. The caller (the engine) stores each depth map
    at once, so memory does not grow with the clip by a depth map per frame.
    """
    N = len(images)
    H, W = np.asarray(images[0]).shape[:2]
    K = np.asarray(K, np.float64)
    kfi = [int(k) for k in keyframe_indices]
    kpos = np.asarray(keyframe_poses, np.float64)
    gshape = mesh_shape(*loss_size(H, W, seg.loss_scale)[:2], depth.mesh_vertices)
    with torch_threads(kf.threads), deterministic(seed) as gen:
        net = DepthNet(layer_norm=depth.layer_norm, mesh=depth.mesh, seed=seed)
        if state is not None:
            net.load_trainable_state({k: torch.as_tensor(np.asarray(v)) for k, v in state.items() if k.startswith("head.")})
        init = _initial_poses(N, kfi, kpos, keyframe_depths, adjacent_flows, K, seg.init)
        h, w, _ = loss_size(H, W, seg.loss_scale)
        kd_all = keyframe_depths  # indexed one keyframe at a time
        if seg.prior == "transfer":
            # the depth model now starts from the keyframe stage's depth (not the raw prior), so
            # the keyframe head, trained on the raw prior's features, is not reused
            net = DepthNet(layer_norm=depth.layer_norm, mesh=depth.mesh, seed=seed)
            window_priors: WindowPriors = partial(_transfer_priors, init, kfi, kpos, kd_all, priors, K)
            # fitted per window from the window's transferred priors (computed once, when the
            # window starts): see _optimise_window
            mesh_init = torch.zeros(N, *gshape)
        else:
            window_priors = partial(_own_priors, priors)
            mesh_init = _prior_mesh_init(net, images, priors, kfi, kd_all, N, (h, w), gshape)
        windows = _segment_windows(kfi, N, seg.window)
        is_kf = np.zeros(N, bool)
        is_kf[kfi] = True
        clip = _Clip(images, window_priors, static_masks, adjacent_flows, is_kf, K, (h, w), gshape,
                     seg.prior == "transfer")
        # g_pose shares memory with init: later windows' transfer depths see the updated poses
        run = _Progress.start(torch.as_tensor(init), mesh_init.clone(), windows, (H, W), net, checkpointer, gen,
                              depth_sink)
        for wi in range(run.w_start, len(windows)):
            _optimise_window(wi, run, net, clip, depth, losses, kf, seg, gen, checkpointer)
        poses = run.g_pose.numpy().astype(np.float64)
    return {"poses": poses, "depths": run.out_depth if depth_sink is None else run.handles}


def _initial_poses(
    N: int, kfi: list[int], kpos: np.ndarray, keyframe_depths: np.ndarray,
    adjacent_flows: Sequence[Mapping[str, np.ndarray]], K: np.ndarray, init_mode: str,
) -> np.ndarray:
    """Initial T_w_c (N, 4, 4) float64: keyframes exact; others interpolated between the
    bracketing keyframes (extrapolated = nearest keyframe), then with ``init_mode="pnp"``
    registered by PnP against each bracketing keyframe and blended by position (where only one
    registration succeeds, that one)."""
    init = np.zeros((N, 4, 4))
    for i in range(N):
        j = int(np.searchsorted(kfi, i, side="right")) - 1
        if j >= 0 and kfi[j] == i:
            init[i] = kpos[j]
        elif j < 0:
            init[i] = kpos[0]
        elif j >= len(kfi) - 1:
            init[i] = kpos[-1]
        else:
            init[i] = interp_pose(kpos[j], kpos[j + 1], (i - kfi[j]) / (kfi[j + 1] - kfi[j]))
    if init_mode == "pnp":
        for j in range(len(kfi) - 1):
            inner = list(range(kfi[j] + 1, kfi[j + 1]))
            if not inner:
                continue
            # PnP against both bracketing keyframes, blended by position (geodesically): with a
            # hard switch at the middle, the two halves' registrations met with a jump of up to
            # 3 cm between neighbouring frames on ICL, which the window's steps did not remove
            from_a = pnp_init(adjacent_flows, kfi[j], kpos[j], np.asarray(keyframe_depths[j], np.float32), inner, K)
            from_b = pnp_init(adjacent_flows, kfi[j + 1], kpos[j + 1], np.asarray(keyframe_depths[j + 1], np.float32),
                              inner, K)
            for i in inner:
                a, b = from_a.get(i), from_b.get(i)
                if a is not None and b is not None:
                    init[i] = interp_pose(a, b, (i - kfi[j]) / (kfi[j + 1] - kfi[j]))
                elif a is not None or b is not None:
                    init[i] = a if a is not None else b
    return init


def _transfer_priors(
    init: np.ndarray, kfi: list[int], kpos: np.ndarray, kd_all: Sequence[np.ndarray], priors: Any, K: np.ndarray,
    a: int, b: int,
) -> np.ndarray:
    """Prior input (b - a + 1, H, W) float32 of frames a..b: the inverse of their transferred
    keyframe depths (``init.transfer_depths``)."""
    target = transfer_depths(init, kfi, kpos, kd_all, priors[a : b + 1], K, range(a, b + 1))
    return (1.0 / np.maximum(target, 1e-6)).astype(np.float32)


def _own_priors(priors: Any, a: int, b: int) -> np.ndarray:
    """Prior input (b - a + 1, H, W) of frames a..b: their own priors."""
    return np.asarray(priors[a : b + 1])


def _transfer_mesh_init(net: DepthNet, pri_w: np.ndarray, hw: tuple[int, int], gshape: tuple[int, int]) -> torch.Tensor:
    """Meshes (n, gh, gw) float32 that make the untrained network reproduce the transferred
    depths 1 / pri_w (n, H, W): fit of log(target / network depth) at loss resolution hw (per
    frame: the same whichever frames are fitted together)."""
    h, w = hw
    target = torch.as_tensor(1.0 / pri_w)
    ref = torch.as_tensor(init_depth_full(net, None, pri_w))
    ratio = torch.log(target.clamp(min=1e-6) / ref.clamp(min=1e-6))
    return fit_mesh(area_resize(ratio.numpy(), h, w), gshape)


def _prior_mesh_init(
    net: DepthNet, images: Any, priors: Any, kfi: list[int], kd_all: Sequence[np.ndarray], N: int, hw: tuple[int, int],
    gshape: tuple[int, int],
) -> torch.Tensor:
    """Meshes (N, gh, gw) float32 with the priors as input: keyframe meshes fit
    log(keyframe_depth / network depth) at loss resolution hw, the other frames interpolate the
    bracketing keyframes' meshes (nearest keyframe's outside)."""
    h, w = hw
    # the loaded keyframe head is not zero: evaluate the network itself
    kref = torch.as_tensor(full_depth(net, images[kfi], priors[kfi], torch.zeros(len(kfi), 2, 2), False))
    kd = torch.as_tensor(np.stack([np.asarray(d, np.float32) for d in kd_all]))
    ratio = torch.log(kd.clamp(min=1e-6) / kref.clamp(min=1e-6))
    ratio = torch.where(kd > 0, ratio, torch.nan)
    fill = torch.nanmedian(ratio.flatten(1), 1).values
    ratio = torch.where(torch.isnan(ratio), fill[:, None, None], ratio)
    kmesh = fit_mesh(area_resize(ratio.numpy(), h, w), gshape)
    mesh_init = torch.zeros(N, *gshape)
    for i in range(N):
        j = int(np.searchsorted(kfi, i, side="right")) - 1
        if j >= 0 and kfi[j] == i:
            mesh_init[i] = kmesh[j]
        elif j < 0 or j >= len(kfi) - 1:
            mesh_init[i] = kmesh[max(j, 0)]
        else:
            s = (i - kfi[j]) / (kfi[j + 1] - kfi[j])
            mesh_init[i] = (1 - s) * kmesh[j] + s * kmesh[j + 1]
    return mesh_init


def _segment_windows(kfi: list[int], N: int, max_len: int) -> list[tuple[int, int]]:
    """Windows [(a, b)] (inclusive frame ranges) cut at keyframes, of at most ``max_len`` frames
    unless two keyframes are further apart; consecutive windows share their boundary keyframe."""
    cuts = sorted(set([0] + kfi + [N - 1]))
    windows: list[tuple[int, int]] = []
    a = cuts[0]
    for c_prev, c in zip(cuts[:-1], cuts[1:]):
        if c - a + 1 > max_len and c_prev > a:
            windows.append((a, c_prev))
            a = c_prev
    windows.append((a, cuts[-1]))
    return windows


@dataclass
class _Clip:
    """The clip's inputs as the windows read them (images, masks, flows may be lazy sequences)."""

    images: Any  # (N, H, W, 3) uint8
    window_priors: WindowPriors  # depth model prior input of frames a..b
    static_masks: Any  # (N, H, W) 1 = static
    adjacent_flows: Sequence[Mapping[str, np.ndarray]]  # [i]: flow dict of pair (i, i+1)
    is_kf: np.ndarray  # (N,) bool, True = keyframe (pose frozen)
    K: np.ndarray  # (3, 3) float64 at working resolution
    loss_hw: tuple[int, int]  # loss resolution (h, w)
    gshape: tuple[int, int]  # mesh grid (gh, gw)
    fit_meshes: bool = False  # initial meshes fitted to the window priors when a window starts


@dataclass
class _Progress:
    """Global state: all frames' poses, meshes and finished windows' depth; where a resumed run
    continues."""

    g_pose: torch.Tensor  # (N, 4, 4) float64 T_w_c
    g_mesh: torch.Tensor  # (N, gh, gw) float32 log-scale meshes
    out_depth: np.ndarray | None  # (N, H, W) float32, filled window by window (no sink)
    windows: list[tuple[int, int]]
    sink: DepthSink | None = None
    handles: list[Any] | None = None  # (N,) the sink's handles of finished frames
    w_start: int = 0  # first window to run
    s_start: int = 0  # its first step
    resume: dict[str, torch.Tensor] | None = None  # checkpointed tensors, until consumed

    @classmethod
    def start(
        cls, g_pose: torch.Tensor, g_mesh: torch.Tensor, windows: list[tuple[int, int]], hw: tuple[int, int],
        net: DepthNet, checkpointer: Checkpointer | None, gen: torch.Generator, sink: DepthSink | None = None,
    ) -> "_Progress":
        """Fresh, or from the checkpointer's last segment state (restores the generator, the
        finished windows' depth and, at a window boundary, the depth head)."""
        n = len(g_pose)
        if sink is None:
            run = cls(g_pose, g_mesh, np.zeros((n,) + hw, np.float32), windows)
        else:
            run = cls(g_pose, g_mesh, None, windows, sink, [None] * n)
        if checkpointer is None:
            return run
        ck = load_checkpoint(checkpointer)
        if ck is None or ck[1].get("stage") != _STAGE:
            return run
        t, meta = ck
        run.g_pose, run.g_mesh = t["g_pose"].clone(), t["g_mesh"].clone()
        shards = sorted(k for k in t if k.startswith("depth") and k.endswith("/depth"))
        for k in shards:  # finished windows' depth, one shard per window, in window order
            run.set_depth(windows[int(k[len("depth") : -len("/depth")])][0], t.pop(k).numpy())
        run.w_start, run.s_start, run.resume = int(meta["window"]), int(meta["step"]), t
        gen.set_state(t["rng"].clone())
        if "head.0.weight" in t and meta["step"] == 0:
            net.load_trainable_state(dict(t))
        return run

    def checkpoint(self, gen: torch.Generator) -> dict[str, torch.Tensor]:
        return {"g_pose": self.g_pose.clone(), "g_mesh": self.g_mesh.clone(), "rng": gen.get_state()}

    def set_depth(self, a: int, depth: np.ndarray) -> None:
        """Frames a .. a + len(depth) - 1 are final with depth (n, H, W): into ``out_depth``, or
        handed to the sink (only its handles are kept)."""
        if self.sink is None:
            self.out_depth[a : a + len(depth)] = depth  # type: ignore[index]
            return
        for j, d in enumerate(np.asarray(depth, np.float32)):
            self.handles[a + j] = self.sink(a + j, d)  # type: ignore[index]

    def depth_shards(self, n_done: int) -> dict[str, dict[str, Any]]:
        """The depth of each finished window as its own shard: unchanged shards are stored once,
        so a checkpoint never copies (or rewrites) the whole clip's depth. With a sink, a shard
        holds the sink's handles of its frames."""
        if self.sink is not None:
            return {f"depth{k:04d}": {"depth": self.handles[wa : wb + 1]}  # type: ignore[index]
                    for k, (wa, wb) in enumerate(self.windows[:n_done])}
        return {f"depth{k:04d}": {"depth": torch.as_tensor(self.out_depth[wa : wb + 1])}  # type: ignore[index]
                for k, (wa, wb) in enumerate(self.windows[:n_done])}


def _segment_pairs(
    n: int, a: int, seg_flows: Mapping[int, FlowPair], kf: KeyframeSettings, pair_power: float
) -> list[Pair]:
    """Pairs (i, i + tau) and (i + tau, i) of a window of n frames starting at frame a
    (window-local indices), weight tau ** pair_power, with flows where tau is in flow_taus."""
    pairs = []
    for tau in kf.taus:
        wt = float(tau) ** pair_power
        for i in range(n - tau):
            f1 = chained_flow(seg_flows, a + i, tau) if tau in kf.flow_taus else None
            pairs.append(Pair(i, i + tau, tau, wt, *(f1[0] if f1 else (None, None))))
            pairs.append(Pair(i + tau, i, tau, wt, *(f1[1] if f1 else (None, None))))
    return pairs


def _optimise_window(
    wi: int, run: _Progress, net: DepthNet, clip: _Clip, depth: DepthModel, losses: LossWeights,
    kf: KeyframeSettings, seg: SegmentSettings, gen: torch.Generator, checkpointer: Checkpointer | None,
) -> None:
    """Optimise window ``wi`` (from a checkpoint when resuming) and store its poses, meshes and
    working-resolution depth in ``run``; checkpoint at its end unless it is the last window."""
    a, b = run.windows[wi]
    h, w = clip.loss_hw
    n = b - a + 1
    imgs_w, pri_w = np.asarray(clip.images[a : b + 1]), clip.window_priors(a, b)
    if clip.fit_meshes:
        # frames after the boundary keyframe (which keeps the previous window's mesh) start from
        # the fit; on a resumed window this recomputes what the checkpoint already holds
        first = 0 if wi == 0 else 1
        run.g_mesh[a + first : b + 1] = _transfer_mesh_init(net, pri_w[first:], (h, w), clip.gshape)
    fr = prepare_frames(net, imgs_w, pri_w, np.asarray(clip.static_masks[a : b + 1]), clip.K, seg.loss_scale,
                        clip.gshape)
    fl = clip.adjacent_flows
    seg_flows = {k: (flow_at_loss_res(fl[k], "fwd", h, w, fr.f), flow_at_loss_res(fl[k], "bwd", h, w, fr.f))
                 for k in range(a, b)}
    pairs = _segment_pairs(n, a, seg_flows, kf, seg.pair_power)
    if not pairs:
        run.set_depth(a, full_depth(net, imgs_w, pri_w, run.g_mesh[a : b + 1], depth.mesh))
        return
    pose_train = torch.as_tensor((~clip.is_kf[a : b + 1]).astype(np.float64))
    win = Window(
        fr.imgs, fr.enc, fr.static, fr.dyn_mesh, fr.K, pairs, run.g_pose[a : b + 1].clone(), pose_train,
        run.g_mesh[a : b + 1].clone(), torch.ones(n), None, seg.grad_mult,
    )
    solver = Solver(win, net, None, seg.lr, depth, losses, kf)
    start = 0
    if run.resume is not None:
        if int(run.s_start) > 0:
            solver.load(run.resume)
            start = run.s_start
        run.resume = None

    def save(step_done: int) -> None:
        t = run.checkpoint(gen)
        t.update(solver.state())
        checkpointer.save(t, {"stage": _STAGE, "window": wi, "step": step_done},  # type: ignore[union-attr]
                          run.depth_shards(wi))

    run_solver(solver, gen, seg.steps, start, save if checkpointer is not None else None)
    with torch.no_grad():
        run.g_pose[a : b + 1] = solver.poses().detach()
        run.g_mesh[a : b + 1] = solver.meshes().detach().clone()
    run.set_depth(a, full_depth(net, imgs_w, pri_w, run.g_mesh[a : b + 1], depth.mesh, fr.enc))
    del fr, imgs_w, pri_w, seg_flows, pairs, win, solver
    if checkpointer is not None and wi + 1 < len(run.windows):
        t = run.checkpoint(gen)
        t.update(net.trainable_state())
        checkpointer.save(t, {"stage": _STAGE, "window": wi + 1, "step": 0}, run.depth_shards(wi + 1))
