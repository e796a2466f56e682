"""Segment optimisation: all frames' poses and depths, keyframe poses frozen.

Frames are processed in windows of at most ``window`` frames cut at keyframes. Non-keyframe poses
start from PnP on flow tracks of the neighbouring keyframes (``init="pnp"``) or a geodesic
interpolation of their poses (``"interp"``); the depth model starts from the keyframe depths
reprojected into every frame (``prior="transfer"``) or from the priors (``"prior"``). Pairs
(i, i + tau), tau in ``taus``, both directions, weighted tau ** pair_power.

Poses are T_w_c (camera-to-world, 4x4 float64).

Windows are independent of each other (keyframe poses are frozen, and each window starts its
own depth head, meshes and generator), so they may be solved in parallel (``window_map``).

Resume: a ``checkpointer`` receives after each finished window (in window order) all frames'
poses and the depth of each finished window as its own shard; a restarted call continues with
the next window (a window's own steps are not checkpointed: it takes seconds) and gives the same
bits.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator, Mapping, Sequence

import numpy as np
import torch

from gcvd_flow.stages.models.depth_net import DepthNet, mesh_shape
from gcvd_flow.stages.optimize.frames import (
    FlowPair,
    area_resize,
    chained_flow,
    fit_mesh,
    flows_at_loss_res,
    full_depth,
    init_depth_full,
    loss_size,
    prepare_frames,
)
from gcvd_flow.stages.optimize.init import interp_pose, pnp_init, transfer_depths
from gcvd_flow.stages.optimize.params import DepthModel, KeyframeSettings, LossWeights, SegmentSettings
from gcvd_flow.stages.optimize.solver import (
    Checkpointer,
    Coarse,
    LrSchedule,
    Pair,
    Solver,
    Window,
    deterministic,
    load_checkpoint,
    run_solver,
    torch_threads,
    window_seed,
)

__all__ = ["optimize_segments", "solve_window", "WindowJob", "WindowResult", "window_seed"]

_STAGE = "segments"  # checkpoint meta["stage"]

# window_map(solve_window, jobs) -> the results in job order (``map``, or a process pool's)
WindowMap = Callable[[Callable[["WindowJob"], "WindowResult"], Iterable["WindowJob"]], Iterable["WindowResult"]]
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
    keyframe_depths: Sequence[np.ndarray],
    depth: DepthModel = DepthModel(),
    losses: LossWeights = LossWeights(),
    kf: KeyframeSettings = KeyframeSettings(),
    seg: SegmentSettings = SegmentSettings(),
    seed: int = 0,
    checkpointer: Checkpointer | None = None,
    state: Mapping[str, np.ndarray] | None = None,
    depth_sink: DepthSink | None = None,
    window_map: WindowMap = map,
) -> dict[str, Any]:
    """Non-keyframe poses + all depths, keyframe poses frozen.

    images (N, H, W, 3) uint8; priors (N, H, W); static_masks (N, H, W); K (3, 3);
    adjacent_flows[i]: flow dict of (i, i+1); keyframe_indices (Kf,) sorted frame indices;
    keyframe_poses (Kf, 4, 4) T_w_c (frozen); keyframe_depths (Kf, H, W) initial depth of the
    keyframes (same scale as the poses; a lazy sequence of (H, W) float32 arrays will do);
    state: optional ``optimize_keyframes`` state (head weights) to start the depth head from
    (with ``prior="prior"``). Images, priors and masks may be lazy sequences: only the windows
    in flight are ever materialised. Pose / mesh learning rates, points, taus and flow_taus come
    from ``kf``. Returns dict(poses (N, 4, 4) float64 T_w_c, depths (N, H, W) float32).

    The windows are independent (keyframe poses are frozen; each window starts its own depth
    head, meshes and random generator from the seed and its number, on ``seg.threads`` torch
    threads), so ``window_map(solve_window, jobs)`` may compute them anywhere and in any order
    (the engine's worker processes): the result does not depend on it.

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
    h, w, _ = loss_size(H, W, seg.loss_scale)
    gshape = mesh_shape(h, w, depth.mesh_vertices)
    head, mesh_init = (None, None) if seg.prior == "transfer" else _prior_start(
        images, priors, kfi, keyframe_depths, state, depth, seg, seed, (h, w), gshape)
    windows = _segment_windows(kfi, N, seg.window)
    settings = _Settings(depth, losses, kf, seg, seed, (h, w), gshape)
    is_kf = np.zeros(N, bool)
    is_kf[kfi] = True
    g_pose = torch.zeros(N, 4, 4, dtype=torch.float64)  # every frame is in a window, which sets it
    run = _Progress.start(g_pose, windows, (H, W), checkpointer, depth_sink)

    def jobs() -> Iterator[WindowJob]:  # built lazily: only the windows in flight are in memory
        for wi in range(run.w_start, len(windows)):
            a, b = windows[wi]
            yield WindowJob(
                wi, np.asarray(images[a : b + 1]), np.asarray(priors[a : b + 1]), np.asarray(static_masks[a : b + 1]),
                [adjacent_flows[k] for k in range(a, b)], is_kf[a : b + 1], K,
                *_window_keyframes(kfi, kpos, keyframe_depths, a, b),
                None if mesh_init is None else mesh_init[a : b + 1], head, settings)

    for wi, res in zip(range(run.w_start, len(windows)), window_map(solve_window, jobs())):
        a, b = windows[wi]
        run.g_pose[a : b + 1] = torch.as_tensor(res.poses)
        run.set_depth(a, res.depth)
        if checkpointer is not None and wi + 1 < len(windows):
            checkpointer.save({"g_pose": run.g_pose.clone()}, {"stage": _STAGE, "window": wi + 1},
                              run.depth_shards(wi + 1))
    poses = run.g_pose.numpy().astype(np.float64)
    return {"poses": poses, "depths": run.out_depth if depth_sink is None else run.handles}


def _prior_start(
    images: Any, priors: Any, kfi: list[int], kd_all: Sequence[np.ndarray], state: Mapping[str, np.ndarray] | None,
    depth: DepthModel, seg: SegmentSettings, seed: int, hw: tuple[int, int], gshape: tuple[int, int],
) -> tuple[dict[str, np.ndarray] | None, np.ndarray]:
    """With prior="prior": the keyframe stage's depth head (or None) and the initial meshes
    (N, gh, gw) of all frames (``_prior_mesh_init``)."""
    head = None
    with torch_threads(seg.threads), deterministic(seed):
        net = DepthNet(layer_norm=depth.layer_norm, mesh=depth.mesh, seed=seed)
        if state is not None:
            head = {k: np.asarray(v) for k, v in state.items() if k.startswith("head.")}
            net.load_trainable_state({k: torch.as_tensor(v) for k, v in head.items()})
        return head, _prior_mesh_init(net, images, priors, kfi, kd_all, len(images), hw, gshape).numpy()


def _window_keyframes(
    kfi: list[int], kpos: np.ndarray, kd_all: Sequence[np.ndarray], a: int, b: int,
) -> tuple[list[int], np.ndarray, list[np.ndarray]]:
    """The keyframes frames a..b are registered against and whose depths are transferred into
    them (those inside and the nearest on either side): frame indices relative to a, T_w_c
    (m, 4, 4), depths [(H, W)]."""
    lo = max(int(np.searchsorted(kfi, a, side="right")) - 1, 0)
    hi = min(int(np.searchsorted(kfi, b, side="right")), len(kfi) - 1)
    sel = range(lo, hi + 1)
    return [kfi[j] - a for j in sel], kpos[lo : hi + 1], [np.asarray(kd_all[j], np.float32) for j in sel]


def _initial_poses(
    n: int, kfl: list[int], kpos: np.ndarray, kd: Sequence[np.ndarray], flows: Sequence[Mapping[str, np.ndarray]],
    K: np.ndarray, init_mode: str,
) -> np.ndarray:
    """Initial T_w_c (n, 4, 4) float64 of a window's frames 0..n-1: keyframes exact; others
    interpolated between the bracketing keyframes (extrapolated = nearest keyframe), then with
    ``init_mode="pnp"`` registered by PnP against each bracketing keyframe and blended by
    position (where only one registration succeeds, that one). kfl: window-relative keyframe
    indices (sorted; they may lie outside the window), kpos (m, 4, 4) and kd [(H, W)] theirs;
    flows[i]: flow dict of (i, i + 1). Windows are cut at keyframes, so the keyframes around a
    window's inner frames are inside it and their flows are the window's."""
    init = np.zeros((n, 4, 4))
    for i in range(n):
        j = int(np.searchsorted(kfl, i, side="right")) - 1
        if j >= 0 and kfl[j] == i:
            init[i] = kpos[j]
        elif j < 0:
            init[i] = kpos[0]
        elif j >= len(kfl) - 1:
            init[i] = kpos[-1]
        else:
            init[i] = interp_pose(kpos[j], kpos[j + 1], (i - kfl[j]) / (kfl[j + 1] - kfl[j]))
    if init_mode == "pnp":
        for j in range(len(kfl) - 1):
            inner = list(range(max(kfl[j] + 1, 0), min(kfl[j + 1], n)))
            if not inner or kfl[j] < 0 or kfl[j + 1] >= n:
                continue
            # PnP against both bracketing keyframes, blended by position (geodesically): with a
            # hard switch at the middle, the two halves' registrations met with a jump of up to
            # 3 cm between neighbouring frames on ICL, which the window's steps did not remove
            from_a = pnp_init(flows, kfl[j], kpos[j], kd[j], inner, K)
            from_b = pnp_init(flows, kfl[j + 1], kpos[j + 1], kd[j + 1], inner, K)
            for i in inner:
                pa, pb = from_a.get(i), from_b.get(i)
                if pa is not None and pb is not None:
                    init[i] = interp_pose(pa, pb, (i - kfl[j]) / (kfl[j + 1] - kfl[j]))
                elif pa is not None or pb is not None:
                    init[i] = pa if pa is not None else pb
    return init


def _transfer_mesh_init(net: DepthNet, pri_w: np.ndarray, hw: tuple[int, int], gshape: tuple[int, int]) -> torch.Tensor:
    """Meshes (n, gh, gw) float32 that make the untrained network reproduce the transferred
    depths 1 / pri_w (n, H, W): fit of log(target / network depth) at loss resolution hw (per
    frame: the same whichever frames are fitted together)."""
    h, w = hw
    target = torch.as_tensor(1.0 / pri_w)
    ref = torch.as_tensor(init_depth_full(net, None, pri_w))  # type: ignore[arg-type]  # images: unused
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


@dataclass(frozen=True)
class _Settings:
    """What every window shares (picklable)."""

    depth: DepthModel
    losses: LossWeights
    kf: KeyframeSettings
    seg: SegmentSettings
    seed: int
    loss_hw: tuple[int, int]  # loss resolution (h, w)
    gshape: tuple[int, int]  # mesh grid (gh, gw)


@dataclass
class WindowJob:
    """Everything one window (n frames starting at frame a) needs; picklable, so that it can be
    solved in a worker process."""

    index: int  # window number: seeds the window's generator
    images: np.ndarray  # (n, H, W, 3) uint8
    priors: np.ndarray  # (n, H, W) the frames' own priors (relative inverse depth)
    static: np.ndarray  # (n, H, W) 1 = static
    flows: list[Mapping[str, np.ndarray]]  # (n - 1) flow dicts of the pairs (i, i + 1)
    is_kf: np.ndarray  # (n,) bool, True = keyframe (pose frozen)
    K: np.ndarray  # (3, 3) float64 at working resolution
    # the keyframes the frames are registered against (and, prior="transfer", whose depths are
    # transferred into them): window-relative frame indices, T_w_c (m, 4, 4), depths [(H, W)]
    keyframes: list[int]
    keyframe_poses: np.ndarray
    keyframe_depths: list[np.ndarray]
    mesh_init: np.ndarray | None  # (n, gh, gw) initial meshes (prior="prior"); else fitted
    head: dict[str, np.ndarray] | None  # depth head to start from (prior="prior")
    settings: _Settings


@dataclass
class WindowResult:
    poses: np.ndarray  # (n, 4, 4) float64 T_w_c
    depth: np.ndarray  # (n, H, W) float32 at working resolution
    steps: int = 0  # Adam steps run (fewer than seg.steps when the loss plateaued: seg.stop_rel)


@dataclass
class _Progress:
    """Global state: all frames' poses and finished windows' depth; where a resumed run
    continues."""

    g_pose: torch.Tensor  # (N, 4, 4) float64 T_w_c
    out_depth: np.ndarray | None  # (N, H, W) float32, filled window by window (no sink)
    windows: list[tuple[int, int]]
    sink: DepthSink | None = None
    handles: list[Any] | None = None  # (N,) the sink's handles of finished frames
    w_start: int = 0  # first window to run

    @classmethod
    def start(
        cls, g_pose: torch.Tensor, windows: list[tuple[int, int]], hw: tuple[int, int],
        checkpointer: Checkpointer | None, sink: DepthSink | None = None,
    ) -> "_Progress":
        """Fresh, or from the checkpointer's last segment state (the finished windows' poses and
        depth)."""
        n = len(g_pose)
        if sink is None:
            run = cls(g_pose, np.zeros((n,) + hw, np.float32), windows)
        else:
            run = cls(g_pose, None, windows, sink, [None] * n)
        if checkpointer is None:
            return run
        ck = load_checkpoint(checkpointer)
        if ck is None or ck[1].get("stage") != _STAGE:
            return run
        t, meta = ck
        run.g_pose = t["g_pose"].clone()
        shards = sorted(k for k in t if k.startswith("depth") and k.endswith("/depth"))
        for k in shards:  # finished windows' depth, one shard per window, in window order
            run.set_depth(windows[int(k[len("depth") : -len("/depth")])][0], t.pop(k).numpy())
        run.w_start = int(meta["window"])
        return run

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


def _segment_pairs(n: int, seg_flows: Mapping[int, FlowPair], kf: KeyframeSettings, pair_power: float) -> list[Pair]:
    """Pairs (i, i + tau) and (i + tau, i) of a window of n frames (window-local indices; seg_flows
    keyed by them too), weight tau ** pair_power, with flows where tau is in flow_taus."""
    pairs = []
    for tau in kf.taus:
        wt = float(tau) ** pair_power
        for i in range(n - tau):
            f1 = chained_flow(seg_flows, i, tau) if tau in kf.flow_taus else None
            pairs.append(Pair(i, i + tau, tau, wt, *(f1[0] if f1 else (None, None))))
            pairs.append(Pair(i + tau, i, tau, wt, *(f1[1] if f1 else (None, None))))
    return pairs


def solve_window(job: WindowJob) -> WindowResult:
    """Optimise one window from its job: a fresh depth head (or the keyframe head), meshes fitted
    to the transferred keyframe depths (or given), ``seg.steps`` Adam steps on
    ``seg.threads`` torch threads -> its poses and working-resolution depth."""
    st = job.settings
    n = len(job.images)
    h, w = st.loss_hw
    with torch_threads(st.seg.threads), deterministic(window_seed(st.seed, job.index)) as gen:
        poses0 = _initial_poses(n, job.keyframes, job.keyframe_poses, job.keyframe_depths, job.flows, job.K,
                                st.seg.init)
        net = DepthNet(layer_norm=st.depth.layer_norm, mesh=st.depth.mesh, seed=st.seed)
        if job.head is not None:
            net.load_trainable_state({k: torch.as_tensor(v) for k, v in job.head.items()})
        if st.seg.prior == "transfer":
            # the depth model starts from the keyframe depths reprojected into the frames (its
            # input is their inverse) and meshes that reproduce them with the untrained head
            target = transfer_depths(poses0, job.keyframes, job.keyframe_poses, job.keyframe_depths, job.priors,
                                     job.K, range(n))
            pri_w = (1.0 / np.maximum(target, 1e-6)).astype(np.float32)
            mesh = _transfer_mesh_init(net, pri_w, (h, w), st.gshape)
        else:
            pri_w, mesh = job.priors, torch.as_tensor(job.mesh_init)
        fr = prepare_frames(net, job.images, pri_w, job.static, job.K, st.seg.loss_scale, st.gshape)
        seg_flows = flows_at_loss_res(job.flows, h, w, fr.f)
        pairs = _segment_pairs(n, seg_flows, st.kf, st.seg.pair_power)
        if not pairs:
            return WindowResult(poses0, full_depth(net, job.images, pri_w, mesh, st.depth.mesh))
        win = Window(
            fr.imgs, fr.enc, fr.static, fr.dyn_mesh, fr.K, pairs, torch.as_tensor(poses0),
            torch.as_tensor((~job.is_kf).astype(np.float64)), mesh, torch.ones(n), None, st.seg.grad_mult,
            keep=fr.keep,
        )
        solver = Solver(win, net, None, st.seg.lr, st.depth, st.losses, st.kf, 1, st.seg.points_by_weight,
                        st.seg.stop_every, st.seg.stop_rel,
                        LrSchedule(st.seg.lr_schedule, st.seg.lr_final_frac, st.seg.lr_start_mult,
                                   st.seg.pose_lr_start_mult), Coarse(st.seg.coarse_points, st.seg.coarse_frac))
        run_solver(solver, gen, st.seg.steps, 0, None)
        with torch.no_grad():
            poses, meshes = solver.poses().numpy(), solver.meshes().clone()
        return WindowResult(poses, full_depth(net, job.images, pri_w, meshes, st.depth.mesh, fr.enc),
                            len(solver.losses_run))
