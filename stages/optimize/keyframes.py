"""Keyframe optimisation: sliding-window test-time training of keyframe poses and depths.

Windows of ``window`` keyframes overlap by ``overlap``; the overlap's poses are held fixed (the
gauge), the new frames are chained onto the optimised overlap from the initial essential-matrix
chain (rigid re-anchoring + the overlap's scale change). Pairs (i, i + tau), tau in ``taus``, both
directions, weighted 1/tau; the flow loss only for tau in ``flow_taus``.

Poses are T_w_c (camera-to-world); the relative poses returned are T_b_a = inv(T_w_b) @ T_w_a
(camera a -> camera b coordinates).

Resume: a ``checkpointer`` receives every ``checkpoint_every`` steps the full state (global
arrays, window parameters, Adam moments, generator state) and at each window boundary the shared
weights; a restarted call resumes from it bit-exactly.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator, Mapping, cast

import numpy as np
import torch

from gcvd_flow.stages.models.depth_net import DepthNet, Encoded, mesh_shape
from gcvd_flow.stages.models.pose_net import PoseNet
from gcvd_flow.stages.optimize.chain_check import checked_pair_poses
from gcvd_flow.stages.optimize.frames import (
    FlowPair,
    Frames,
    chained_flow,
    flows_at_loss_res,
    full_depth,
    init_depth_full,
    loss_size,
    prepare_frames,
)
from gcvd_flow.stages.optimize.init import essential_chain
from gcvd_flow.stages.optimize.params import DepthModel, KeyframeSettings, LossWeights
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

log = logging.getLogger(__name__)

__all__ = ["optimize_keyframes"]

_STAGE = "keyframes"  # checkpoint meta["stage"]
_STAGE_INDEPENDENT = "keyframes-independent"


def optimize_keyframes(
    images: np.ndarray,
    priors: np.ndarray,
    static_masks: np.ndarray,
    K: np.ndarray,
    pair_flows: Mapping[tuple[int, int], Mapping[str, np.ndarray]],
    depth: DepthModel = DepthModel(),
    losses: LossWeights = LossWeights(),
    kf: KeyframeSettings = KeyframeSettings(),
    seed: int = 0,
    checkpointer: Checkpointer | None = None,
    window_map: KeyframeWindowMap = map,
) -> dict[str, Any]:
    """Sliding-window test-time training over keyframes.

    images (K, H, W, 3) uint8; priors (K, H, W) relative inverse depth; static_masks (K, H, W)
    uint8 1 = static; K (3, 3); pair_flows[(k, k+1)] flow dicts of consecutive keyframes (indices
    into this keyframe list). Returns dict(poses (K, 4, 4) float64 T_w_c with T_w_0 = I,
    depths (K, H, W) float32 (scale of the poses), rel_poses [dict(a, b, tau, T_b_a (4, 4)
    float64 = inv(T_w_b) @ T_w_a)] for every (k, k + tau), tau in taus, state {name: array}:
    trained head weights ``head.*`` and the per-frame meshes ``mesh`` (K, gh, gw)), windows
    [dict(start, keyframes, pairs, points_per_step, steps, max_steps, loss)] per window: its
    first keyframe and size, its ordered pairs and the points drawn per step over all of them,
    the Adam steps it ran (fewer than max_steps = kf.steps when its loss plateaued:
    ``kf.stop_rel``) and the mean loss of its last min(steps, kf.stop_every) steps.

    ``kf.schedule="independent"``: the windows are independent jobs (``_independent_windows``),
    so ``window_map(solve_keyframe_window, jobs)`` may compute them anywhere and in any order
    (the engine's worker processes) with the same result.
    """
    images = np.asarray(images)
    nk, H, W = images.shape[:3]
    K = np.asarray(K, np.float64)
    gshape = mesh_shape(*loss_size(H, W, kf.loss_scale)[:2], depth.mesh_vertices)
    flows = [pair_flows[(k, k + 1)] for k in range(nk - 1)]
    if kf.schedule == "independent":
        with torch_threads(kf.threads), deterministic(seed):
            net = DepthNet(layer_norm=depth.layer_norm, mesh=depth.mesh, seed=seed)
            init, mesh_init = _initial_solution(net, images, priors, static_masks, K, flows, kf, gshape)
        settings = _WindowSettings(depth, losses, kf, seed, gshape)
        return _independent_windows(images, priors, static_masks, K, flows, init, mesh_init, settings,
                                    checkpointer, window_map)
    with torch_threads(kf.threads):
        with deterministic(seed) as gen:
            net = DepthNet(layer_norm=depth.layer_norm, mesh=depth.mesh, seed=seed)
            posenet = PoseNet(seed=seed) if kf.pose_param == "net" else None
            fr = prepare_frames(net, images, priors, static_masks, K, kf.loss_scale, gshape)
            h, w = fr.imgs.shape[-2:]
            # initialisation: essential-matrix chain (global, deterministic, recomputed on resume)
            init, mesh_init = _initial_solution(net, images, priors, static_masks, K, flows, kf, gshape)
            codes = posenet.encode(fr.imgs, torch.arange(nk)) if posenet is not None else None
            flows_lr = flows_at_loss_res(flows, h, w, fr.f)
            starts = _window_starts(nk, kf)
            run = _Progress.start(init, mesh_init, len(starts), checkpointer, gen)
            for wi in range(run.w_start, len(starts)):
                fr_idx = list(range(starts[wi], min(starts[wi] + kf.window, nk)))
                win = _keyframe_window(wi, fr_idx, fr, codes, flows_lr, init, mesh_init, run, kf)
                if win is None:
                    break
                solver = _window_solver(win, net, posenet, depth, losses, kf)
                loss = _optimise_window(solver, wi, len(starts), run, gen, kf.steps, checkpointer)
                log.debug("keyframe window %d/%d loss %.4f", wi + 1, len(starts), loss)
                run.stats[wi] = _window_stats(solver, kf)
                with torch.no_grad():
                    run.g_base[fr_idx] = solver.poses().detach()
                    run.g_mesh[fr_idx] = solver.meshes().detach().clone()
                if checkpointer is not None and wi + 1 < len(starts):
                    _save_boundary(checkpointer, run, gen, solver, wi + 1)
            poses = run.g_base.numpy().astype(np.float64)
            depths = full_depth(net, images, priors, run.g_mesh, depth.mesh, fr.enc)
        res = _results(poses, depths, run.g_mesh, _net_state(net, posenet), kf.taus)
        res["windows"] = _window_records(run.stats, starts, nk, kf)
        return res


def _window_solver(win: Window, net: DepthNet, posenet: PoseNet | None, depth: DepthModel, losses: LossWeights,
                   kf: KeyframeSettings) -> Solver:
    """A keyframe window's solver: the stage's lr and its schedule, pair blocks, point allocation and
    plateau stop."""
    return Solver(win, net, posenet, kf.lr, depth, losses, kf, kf.pair_blocks, kf.points_by_weight,
                  kf.stop_every, kf.stop_rel, LrSchedule.of(kf), Coarse.of(kf))


def _window_stats(solver: Solver, kf: KeyframeSettings) -> torch.Tensor:
    """(4,) float64: pairs, points per step, steps run, mean loss of the last min(steps, stop_every)
    (0 without a step)."""
    ls = solver.losses_run[-max(1, kf.stop_every):]
    loss = math.fsum(ls) / len(ls) if ls else 0.0
    return torch.tensor([len(solver.w.pairs), solver.points_per_step, len(solver.losses_run), loss],
                        dtype=torch.float64)


def _window_records(stats: torch.Tensor, starts: list[int], nk: int, kf: KeyframeSettings) -> list[dict[str, Any]]:
    """The ``windows`` records of the output from (n_windows, 4) ``_window_stats`` rows (a window
    that never ran, having no pair: zeros)."""
    return [{"start": int(s), "keyframes": min(s + kf.window, nk) - s, "pairs": int(st[0]),
             "points_per_step": int(st[1]), "steps": int(st[2]), "max_steps": int(kf.steps), "loss": float(st[3])}
            for s, st in zip(starts, stats.tolist())]


def _window_starts(nk: int, kf: KeyframeSettings) -> list[int]:
    """First keyframe of every window: windows of ``kf.window`` overlapping by ``kf.overlap``."""
    return list(range(0, max(nk - kf.overlap, 1), max(1, kf.window - kf.overlap)))


def _net_state(net: DepthNet, posenet: PoseNet | None) -> dict[str, np.ndarray]:
    """The trained weights: depth head ``head.*`` (and pose decoder ``posenet.*``)."""
    state = {k: v.numpy() for k, v in net.trainable_state().items()}
    if posenet is not None:
        state.update({f"posenet.{k}": v.detach().numpy() for k, v in posenet.decoder.state_dict().items()})
    return state


@dataclass
class _Progress:
    """The optimisation's global state: the optimised poses / meshes of all keyframes (those of
    unfinished windows at their initial values) and where a resumed run continues."""

    g_base: torch.Tensor  # (K, 4, 4) float64 T_w_c of finished windows
    g_mesh: torch.Tensor  # (K, gh, gw) float32 log-scale meshes
    stats: torch.Tensor  # (n_windows, 4) float64 ``_window_stats`` of the finished windows
    w_start: int = 0  # first window to run
    s_start: int = 0  # its first step
    resume: dict[str, torch.Tensor] | None = None  # checkpointed tensors, until consumed

    @classmethod
    def start(cls, init: torch.Tensor, mesh_init: torch.Tensor, n_windows: int, checkpointer: Checkpointer | None,
              gen: torch.Generator) -> "_Progress":
        """Fresh from the initial solution, or from the checkpointer's last keyframe state
        (which also restores the generator)."""
        run = cls(init.clone(), mesh_init.clone(), torch.zeros(n_windows, 4, dtype=torch.float64))
        if checkpointer is not None:
            ck = load_checkpoint(checkpointer)
            if ck is not None and ck[1].get("stage") == _STAGE:
                t, meta = ck
                run = cls(t["g_base"].clone(), t["g_mesh"].clone(), t["window_stats"].clone(), int(meta["window"]),
                          int(meta["step"]), t)
                gen.set_state(t["rng"].clone())
        return run

    def checkpoint(self, gen: torch.Generator) -> dict[str, torch.Tensor]:
        return {"g_base": self.g_base.clone(), "g_mesh": self.g_mesh.clone(), "window_stats": self.stats.clone(),
                "rng": gen.get_state()}


def _initial_solution(
    net: DepthNet, images: np.ndarray, priors: np.ndarray, static_masks: np.ndarray, K: np.ndarray,
    flows: list[Mapping[str, np.ndarray]], kf: KeyframeSettings, gshape: tuple[int, int],
) -> tuple[torch.Tensor, torch.Tensor]:
    """Initial poses (K, 4, 4) float64 T_w_c and log-scale meshes (K, gh, gw) float32 (one
    value per frame): the essential-matrix chain (its pairs checked and repaired first with
    ``kf.chain_check_deg`` > 0: ``stages.optimize.chain_check``; rotation-dominated pairs carrying
    the scale along the flow with ``kf.chain_prior_scale_below`` > 0), or identity poses / zero meshes."""
    nk = len(images)
    if kf.init == "essential" and nk > 1:
        ref = init_depth_full(net, images, priors)
        pair_poses = None
        if kf.chain_check_deg > 0:
            pair_poses, changed, _ = checked_pair_poses(flows, np.asarray(static_masks), K, kf.chain_check_deg)
            if changed:
                log.info("essential chain: %d pair(s) repaired by the three-view check: %s", len(changed), changed)
        init_np, log_m = essential_chain(flows, np.asarray(static_masks), ref, K, pair_poses=pair_poses,
                                         prior_scale_below=kf.chain_prior_scale_below)
    else:
        init_np, log_m = np.tile(np.eye(4), (nk, 1, 1)), np.zeros(nk)
    mesh_init = torch.as_tensor(log_m, dtype=torch.float32)[:, None, None].expand(nk, *gshape).clone()
    return torch.as_tensor(init_np), mesh_init


def _keyframe_window(
    wi: int, fr_idx: list[int], fr: Frames, codes: torch.Tensor | None, flows_lr: Mapping[int, FlowPair],
    init: torch.Tensor, mesh_init: torch.Tensor, run: _Progress, kf: KeyframeSettings,
) -> Window | None:
    """Window ``wi`` over keyframes ``fr_idx`` (consecutive), or None if it has no pair.

    Its first frame (window 0) or its overlap with the previous window keeps the optimised pose
    (fixed: the gauge); the new frames are chained from the optimised overlap by the initial
    relative poses, scaled by the overlap's mean scale change, their meshes shifted likewise."""
    n = len(fr_idx)
    s0 = fr_idx[0]
    n_old = 0 if wi == 0 else min(kf.overlap, n)
    base = run.g_base[fr_idx].clone()
    mesh0 = run.g_mesh[fr_idx].clone()
    if wi > 0:
        # chain new frames from the optimised overlap (rigid re-anchoring + scale change)
        anc = s0 + n_old - 1
        sig = float(torch.exp((run.g_mesh[s0 : s0 + n_old] - mesh_init[s0 : s0 + n_old]).mean()))
        for j in range(n_old, n):
            T_anc_j = torch.linalg.inv(init[anc]) @ init[fr_idx[j]]  # camera j -> anchor camera
            T_anc_j[:3, 3] *= sig
            base[j] = run.g_base[anc] @ T_anc_j
            mesh0[j] = mesh_init[fr_idx[j]] + math.log(sig)
    pose_train = torch.ones(n, dtype=torch.float64)
    pose_train[: max(n_old, 1)] = 0  # gauge: first frame / overlap poses fixed
    pairs = _keyframe_pairs(fr_idx, flows_lr, kf)
    if not pairs:
        return None
    sl = slice(fr_idx[0], fr_idx[-1] + 1)
    return Window(
        fr.imgs[sl], Encoded(fr.enc.feat[sl], fr.enc.log_prior[sl]), fr.static[sl], fr.dyn_mesh[sl],
        fr.K, pairs, base, pose_train, mesh0, torch.ones(n), codes[sl] if codes is not None else None,
        keep=None if fr.keep is None else fr.keep[sl],
    )


def _keyframe_pairs(fr_idx: list[int], flows_lr: Mapping[int, FlowPair], kf: KeyframeSettings) -> list[Pair]:
    """Pairs (i, i + tau) and (i + tau, i) of a window (window-local indices), weight 1/tau,
    with loss-resolution flows where tau is in flow_taus."""
    n = len(fr_idx)
    pairs = []
    for tau in kf.taus:
        for i in range(n - tau):
            ga = fr_idx[i]
            f1 = chained_flow(flows_lr, ga, tau) if tau in kf.flow_taus else None
            pairs.append(Pair(i, i + tau, tau, 1.0 / tau, *(f1[0] if f1 else (None, None))))
            pairs.append(Pair(i + tau, i, tau, 1.0 / tau, *(f1[1] if f1 else (None, None))))
    return pairs


def _optimise_window(
    solver: Solver, wi: int, n_windows: int, run: _Progress, gen: torch.Generator, steps: int,
    checkpointer: Checkpointer | None,
) -> float:
    """Run window ``wi``'s Adam steps (from a checkpoint when resuming); returns the last loss."""
    start = 0
    if run.resume is not None:
        if run.s_start > 0:
            solver.load(run.resume)
            start = run.s_start
        else:  # saved at a window boundary: only the shared weights carry over
            solver.net.load_trainable_state(dict(run.resume))
            if solver.posenet is not None:
                solver.posenet.decoder.load_state_dict(
                    {k[8:]: v for k, v in run.resume.items() if k.startswith("posenet.")})
        run.resume = None

    def save(step_done: int) -> None:
        t = run.checkpoint(gen)
        t.update(solver.state())
        checkpointer.save(t, {"stage": _STAGE, "window": wi, "step": step_done})  # type: ignore[union-attr]

    return run_solver(solver, gen, steps, start, save if checkpointer is not None else None)


def _save_boundary(checkpointer: Checkpointer, run: _Progress, gen: torch.Generator, solver: Solver,
                   next_window: int) -> None:
    """Checkpoint at a window boundary: global state and the shared weights (no window state)."""
    t = run.checkpoint(gen)
    t.update({k: v for k, v in solver.state().items() if not k.startswith(("adam.", "win."))})
    checkpointer.save(t, {"stage": _STAGE, "window": next_window, "step": 0})


def _results(
    poses: np.ndarray, depths: np.ndarray, g_mesh: torch.Tensor, state: dict[str, np.ndarray],
    taus: tuple[int, ...], rel: list[dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """The stage's output dict (see ``optimize_keyframes``) from poses (K, 4, 4) T_w_c, depths
    (K, H, W), meshes (K, gh, gw) and the trained weights; the relative poses given, or those of
    ``poses``."""
    nk = len(poses)
    if rel is None:
        rel = [{"a": a, "b": a + tau, "tau": tau, "T_b_a": np.linalg.inv(poses[a + tau]) @ poses[a]}
               for tau in taus for a in range(nk - tau)]
    return {"poses": poses, "depths": depths, "rel_poses": rel, "state": {**state, "mesh": g_mesh.numpy()}}


# ------------------------------------------------------------------ independent windows
# Each window starts from the initial essential-matrix chain (not from the previous window's
# optimised overlap), with its own depth head and generator, so the windows can be solved side
# by side. A window is then placed onto the keyframes already placed by a similarity: the scale
# from the overlap's depths, rotation and translation fitted to the overlap's poses (least
# squares); its new keyframes keep their optimised relative poses. A clip of one window gives
# exactly the chained schedule's result. Opt-in: without the chained schedule's fixed overlap the
# scale of a panning clip drifts from window to window (docs/benchmarks.md).

@dataclass(frozen=True)
class _WindowSettings:
    """What every keyframe window shares (picklable)."""

    depth: DepthModel
    losses: LossWeights
    kf: KeyframeSettings
    seed: int
    gshape: tuple[int, int]  # mesh grid (gh, gw)


@dataclass
class KeyframeJob:
    """Everything one keyframe window of n keyframes needs; picklable (a worker solves it)."""

    index: int  # window number: seeds its generator (window 0: the run's seed)
    start: int  # its first keyframe's index in the clip's keyframe list (PoseNet frame codes)
    images: np.ndarray  # (n, H, W, 3) uint8
    priors: np.ndarray  # (n, H, W) relative inverse depth
    static: np.ndarray  # (n, H, W) 1 = static
    K: np.ndarray  # (3, 3) float64 at working resolution
    flows: list[Mapping[str, np.ndarray]]  # (n - 1) flow dicts of the pairs (k, k + 1)
    init: np.ndarray  # (n, 4, 4) float64 T_w_c of the essential-matrix chain
    mesh_init: np.ndarray  # (n, gh, gw) float32
    settings: _WindowSettings


@dataclass
class KeyframeWindowResult:
    """A solved window in its own frame (first keyframe where the chain put it, its own scale)."""

    poses: np.ndarray  # (n, 4, 4) float64 T_w_c
    meshes: np.ndarray  # (n, gh, gw) float32 log-scale meshes (of this window's head)
    depths: np.ndarray  # (n, H, W) float32, scale of the poses
    state: dict[str, np.ndarray]  # the window's trained weights (``_net_state``)
    stats: np.ndarray  # (4,) float64 ``_window_stats`` (zeros: no pair, no step)


KeyframeWindowMap = Callable[[Callable[[KeyframeJob], KeyframeWindowResult], Iterable[KeyframeJob]],
                             Iterable[KeyframeWindowResult]]


def solve_keyframe_window(job: KeyframeJob) -> KeyframeWindowResult:
    """One keyframe window from the initial chain: a fresh depth head (and pose decoder),
    ``kf.steps`` Adam steps on ``kf.threads`` torch threads, its first pose fixed (the gauge)."""
    st, kf = job.settings, job.settings.kf
    n = len(job.images)
    with torch_threads(kf.threads), deterministic(st.seed if job.index == 0 else window_seed(st.seed, job.index)) as gen:
        net = DepthNet(layer_norm=st.depth.layer_norm, mesh=st.depth.mesh, seed=st.seed)
        posenet = PoseNet(seed=st.seed) if kf.pose_param == "net" else None
        fr = prepare_frames(net, job.images, job.priors, job.static, job.K, kf.loss_scale, st.gshape)
        h, w = fr.imgs.shape[-2:]
        codes = posenet.encode(fr.imgs, torch.arange(job.start, job.start + n)) if posenet is not None else None
        flows_lr = flows_at_loss_res(job.flows, h, w, fr.f)
        pairs = _keyframe_pairs(list(range(n)), flows_lr, kf)
        poses, meshes = torch.as_tensor(job.init).clone(), torch.as_tensor(job.mesh_init).clone()
        stats = torch.zeros(4, dtype=torch.float64)
        if pairs:
            pose_train = torch.ones(n, dtype=torch.float64)
            pose_train[0] = 0  # gauge
            win = Window(fr.imgs, fr.enc, fr.static, fr.dyn_mesh, fr.K, pairs, poses, pose_train, meshes,
                         torch.ones(n), codes, keep=fr.keep)
            solver = _window_solver(win, net, posenet, st.depth, st.losses, kf)
            run_solver(solver, gen, kf.steps, 0, None)
            stats = _window_stats(solver, kf)
            with torch.no_grad():
                poses, meshes = solver.poses().detach().clone(), solver.meshes().detach().clone()
        depths = full_depth(net, job.images, job.priors, meshes, st.depth.mesh, fr.enc)
        return KeyframeWindowResult(poses.numpy().astype(np.float64), meshes.numpy(),
                                    np.asarray(depths, np.float32), _net_state(net, posenet), stats.numpy())


def _rigid_fit(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Rigid M (4, 4) with M @ src[k] ~ dst[k] over poses (n, 4, 4) T_w_c in least squares: the
    chordal mean of the rotation differences, then the mean camera-centre offset."""
    U, _, Vt = np.linalg.svd(sum(d[:3, :3] @ s[:3, :3].T for s, d in zip(src, dst)))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = np.mean(dst[:, :3, 3] - src[:, :3, 3] @ R.T, axis=0)
    return M


class _Placed:
    """The keyframes placed so far, window by window (``add`` in window order)."""

    def __init__(self, nk: int, spans: list[tuple[int, int]], overlap: int) -> None:
        self.spans, self.overlap = spans, overlap
        self.poses = np.zeros((nk, 4, 4))
        self.meshes: list[np.ndarray | None] = [None] * nk
        self.depths: list[np.ndarray | None] = [None] * nk
        self.window_poses: list[np.ndarray] = []  # each window's poses, placed (for rel_poses)
        self.state: dict[str, np.ndarray] = {}

    def add(self, wi: int, res: KeyframeWindowResult) -> None:
        a, b = self.spans[wi]
        n_old = 0 if wi == 0 else min(self.overlap, b - a)
        scale, M = 1.0, np.eye(4)
        if n_old > 0:
            # scale: median log ratio of the overlap's depths; rigid part: fitted to the overlap's poses
            old = cast(list[np.ndarray], self.depths[a : a + n_old])  # placed by the previous window
            logs = np.concatenate([np.log(old[k][ok] / res.depths[k][ok]) for k in range(n_old)
                                   for ok in [(old[k] > 0) & (res.depths[k] > 0)]])
            scale = float(np.exp(np.median(logs))) if logs.size else 1.0
        placed = res.poses.copy()
        placed[:, :3, 3] *= scale
        if n_old > 0:
            M = _rigid_fit(placed[:n_old], self.poses[a : a + n_old])
        placed = M @ placed
        self.window_poses.append(placed)
        for k in range(n_old, b - a):
            self.poses[a + k] = placed[k]
            self.depths[a + k] = res.depths[k] * np.float32(scale)
            self.meshes[a + k] = res.meshes[k] + np.float32(np.log(scale))
        self.state = res.state  # the last window's weights, as the chained schedule's final net

    def rel_poses(self, taus: tuple[int, ...]) -> list[dict[str, Any]]:
        """T_b_a of every (a, a + tau) from the last window holding both (its own optimisation;
        the placed poses where no window holds both: tau > overlap)."""
        rel = []
        for tau in taus:
            for a in range(len(self.poses) - tau):
                holding = [k for k, (s, e) in enumerate(self.spans) if s <= a and a + tau < e]
                P, s0 = (self.window_poses[holding[-1]], self.spans[holding[-1]][0]) if holding else (self.poses, 0)
                rel.append({"a": a, "b": a + tau, "tau": tau,
                            "T_b_a": np.linalg.inv(P[a + tau - s0]) @ P[a - s0]})
        return rel


def _independent_windows(
    images: np.ndarray, priors: np.ndarray, static_masks: np.ndarray, K: np.ndarray,
    flows: list[Mapping[str, np.ndarray]], init: torch.Tensor, mesh_init: torch.Tensor, st: _WindowSettings,
    checkpointer: Checkpointer | None, window_map: KeyframeWindowMap,
) -> dict[str, Any]:
    """The independent schedule: solve the windows through ``window_map``, place them in order
    (a checkpoint after each, holding every finished window's result as its own shard)."""
    nk, kf = len(images), st.kf
    spans = [(s, min(s + kf.window, nk)) for s in _window_starts(nk, kf)]
    placed = _Placed(nk, spans, kf.overlap)
    done: list[KeyframeWindowResult] = []
    ck = load_checkpoint(checkpointer) if checkpointer is not None else None
    if ck is not None and ck[1].get("stage") == _STAGE_INDEPENDENT:
        t = ck[0]
        for wi in range(int(ck[1]["window"])):
            p = f"win{wi:04d}/"
            win_res = KeyframeWindowResult(
                t[p + "poses"].numpy(), t[p + "meshes"].numpy(), t[p + "depths"].numpy(),
                {k[len(p) + 6:]: v.numpy() for k, v in t.items() if k.startswith(p + "state.")},
                t[p + "stats"].numpy())
            done.append(win_res)
            placed.add(wi, win_res)

    def jobs() -> Iterator[KeyframeJob]:  # built lazily: only the windows in flight are in memory
        for wi in range(len(done), len(spans)):
            a, b = spans[wi]
            yield KeyframeJob(wi, a, images[a:b], priors[a:b], static_masks[a:b], K, flows[a : b - 1],
                              init[a:b].numpy(), mesh_init[a:b].numpy(), st)

    for wi, win_res in zip(range(len(done), len(spans)), window_map(solve_keyframe_window, jobs())):
        done.append(win_res)
        placed.add(wi, win_res)
        if checkpointer is not None and wi + 1 < len(spans):
            shards = {f"win{k:04d}": {"poses": torch.as_tensor(r.poses), "meshes": torch.as_tensor(r.meshes),
                                      "depths": torch.as_tensor(r.depths), "stats": torch.as_tensor(r.stats),
                                      **{f"state.{n}": torch.as_tensor(v) for n, v in r.state.items()}}
                      for k, r in enumerate(done)}
            checkpointer.save({"windows_done": torch.tensor(wi + 1)}, {"stage": _STAGE_INDEPENDENT, "window": wi + 1},
                              shards)
    # every keyframe is placed by now: no None left in depths / meshes
    res = _results(placed.poses, np.stack(cast(list[np.ndarray], placed.depths)),
                   torch.as_tensor(np.stack(cast(list[np.ndarray], placed.meshes))), placed.state,
                   kf.taus, placed.rel_poses(kf.taus))
    res["windows"] = _window_records(torch.as_tensor(np.stack([r.stats for r in done])), [a for a, _ in spans], nk, kf)
    return res
