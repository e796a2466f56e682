"""The per-window solver shared by the three optimisations: Adam on sampled-point losses.

A ``Window`` holds n frames at loss resolution (h, w) and the ordered frame pairs whose losses
are summed; ``Solver`` owns the trainable parameters of the window (per-frame pose corrections
``delta``, log-scale meshes, the depth head through ``net``) and one Adam optimiser; ``run_solver``
steps it and hands checkpoints to a ``Checkpointer``.

Model: depth_i = DepthNet(image_i, prior_i) * exp(mesh_i); camera-to-world pose
T_w_i = base_i @ pose_from_rt(delta_i) (``pose_param="direct"``) or with delta_i the output of
the pose network (``pose_param="net"``). Trainable: the depth head (lr), the per-frame
log-scales (lr * mesh_lr_mult), the spatial mesh vertices (lr * mesh_lr_mult *
mesh_shape_lr_frac) and the pose corrections (pose_lr).

Losses are evaluated on M = ``points`` random points per ordered pair (a, b) per step
(docs/design.md, "Lessons from the prototype"): every pair and so every pose gets a gradient at every step, at a cost independent of the
image size. A point of frame a is lifted with a's depth and moved into camera b by
T_b_a = inv(T_w_b) @ T_w_a (camera-a -> camera-b coordinates).

Determinism: all randomness comes from one torch.Generator seeded by ``seed`` (``deterministic``);
``torch.use_deterministic_algorithms(True)`` is on inside it, and the torch thread count is a
parameter (``torch_threads``), as is the number of pair blocks.

Pair blocks (``pair_blocks`` > 1, the keyframe windows): the pair terms are independent given the
window's depth and poses, so each step decodes the depth once, differentiates every block's pair
losses up to that depth and those poses on a thread of its own (torch releases the GIL inside
its kernels, and the serial parts of the step -- the deterministic scatter-adds of the gathers'
backward -- run side by side), sums the block gradients in block order and runs one backward
through the depth head and poses. Same points as one block (sampled once for all pairs), the
same gradient up to float rounding; on two cores a 40-keyframe step 57 -> 39 ms.

Measured on 2 shared cores (DIS medium flow, all-static masks, a weight-free flow-triangulation
prior, default parameters, working resolution 256x192): synthetic loop 120 frames ATE 0.49 % of
the path, AbsRel 0.053; ICL livingroom 211 frames ATE 3.1 cm, AbsRel 0.092; ~0.35 s/frame for
flow + prior + both optimisations.
"""

from __future__ import annotations

import contextlib
import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Mapping, Protocol

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from gcvd_flow.stages.geometry import torch_ops as G
from gcvd_flow.stages.models.depth_net import DepthNet, Encoded
from gcvd_flow.stages.models.pose_net import PoseNet
from gcvd_flow.stages.optimize import losses as L
from gcvd_flow.stages.optimize.adam import Adam
from gcvd_flow.stages.optimize.params import DepthModel, KeyframeSettings, LossWeights

__all__ = [
    "Checkpointer",
    "torch_threads",
    "load_checkpoint",
    "deterministic",
    "window_seed",
    "Pair",
    "Window",
    "Solver",
    "run_solver",
    "lr_factor",
    "LrSchedule",
    "LR_SCHEDULES",
    "Coarse",
]


class Checkpointer(Protocol):
    """Implemented by the engine; ``load`` returns the last saved state or None."""

    def load(self) -> tuple[dict[str, np.ndarray], dict[str, Any]] | None: ...

    def save(self, tensors: dict[str, torch.Tensor], meta: dict[str, Any],
             shards: dict[str, dict[str, torch.Tensor]] | None = None) -> None: ...


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run with a fixed number of torch threads: float reductions split differently across
    threads give different bits, so the thread count is a parameter (in the key), not an
    accident of the machine or of OMP_NUM_THREADS."""
    prev = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(prev)


def load_checkpoint(checkpointer: Checkpointer) -> tuple[dict[str, torch.Tensor], dict[str, Any]] | None:
    """The checkpointer's last state with its arrays as tensors (the engine stores numpy)."""
    ck = checkpointer.load()
    if ck is None:
        return None
    arrays, meta = ck
    return {k: v.clone() if isinstance(v, torch.Tensor) else torch.from_numpy(np.array(v))
            for k, v in arrays.items()}, meta


@contextlib.contextmanager
def deterministic(seed: int) -> Iterator[torch.Generator]:
    """Deterministic torch algorithms, torch / OpenCV global seeds set, and the generator that
    drives all point sampling."""
    prev = torch.are_deterministic_algorithms_enabled()
    set_deterministic_algorithms(True)
    torch.manual_seed(seed)
    cv2.setRNGSeed(seed)
    try:
        yield torch.Generator().manual_seed(seed)
    finally:
        set_deterministic_algorithms(prev)


def set_deterministic_algorithms(mode: bool) -> None:
    """torch's deterministic-algorithms flag, as ``torch.use_deterministic_algorithms(mode)`` sets
    it for eager code. Why not that function: it also imports ``torch._inductor.config`` (and with it
    torch._dynamo: 2 s per process, every worker's and every tiny run's largest fixed cost) to set
    Inductor's own flag, and nothing here compiles with Inductor."""
    setter = getattr(torch._C, "_set_deterministic_algorithms", None)
    if setter is None:  # a torch without the private setter: the public function
        torch.use_deterministic_algorithms(mode)
    else:
        setter(mode, warn_only=False)


def window_seed(seed: int, index: int) -> int:
    """The seed of window ``index``'s generator: a function of the run's seed and the window
    alone, so a window's result does not depend on which windows ran before it (31 bits: OpenCV takes a C int)."""
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1)[0] & 0x7FFFFFFF)


@dataclass
class Pair:
    """An ordered frame pair (a, b) of a window: points of a are warped into b."""

    a: int  # window-local frame indices
    b: int
    tau: int
    weight: float
    flow: torch.Tensor | None = None  # (h, w, 2) at loss resolution, px
    valid: torch.Tensor | None = None  # (h, w) float


@dataclass
class Window:
    """Everything a window optimisation needs, at loss resolution."""

    imgs: torch.Tensor  # (n, 3, h, w)
    enc: Encoded  # (n, ., h, w)
    static: torch.Tensor  # (n, h, w) float, 1 = static
    dyn_mesh: torch.Tensor  # (n, gh, gw) dynamic fraction
    K: torch.Tensor  # (3, 3) float64 at loss resolution
    pairs: list[Pair]
    base: torch.Tensor  # (n, 4, 4) float64 base poses T_w_c (camera-to-world)
    pose_train: torch.Tensor  # (n,) float64 1 = trainable
    mesh_init: torch.Tensor  # (n, gh, gw) float32 initial log-scale meshes
    mesh_train: torch.Tensor  # (n,) float32 1 = trainable
    pose_code: torch.Tensor | None = None  # (n, D) PoseNet codes
    grad_mult: float = 1.0
    keep: torch.Tensor | None = None  # (n, h, w) 1 = no user-masked (--masks) pixel in the cell; None: none


@dataclass
class _PairBlock:
    """Pairs of a window that share a number of points per step (one point group), with what
    their losses read, gathered once per window (constant over the steps). A thread's share of a
    group is every ``stride``-th of its pairs: strided rather than contiguous, as the pairs are
    ordered by tau and only tau = 1 has a flow loss, so strides balance the work."""

    sel: torch.Tensor  # (P,) the block's pairs (indices into the window's pair list)
    group: int  # its point group (index into ``Solver.groups``)
    rows: torch.Tensor  # (P,) its pairs' rows in that group's sampled points
    pa: torch.Tensor  # (P,) window-local frame a of each pair
    pb: torch.Tensor  # (P,) frame b
    pw: torch.Tensor  # (P,) pair weights, normalised over the whole window
    amask: torch.Tensor  # (P, h * w) usable pixels of frame a: static, and fb-consistent where flow exists
    img_pa: torch.Tensor  # (P, 3, h, w) image of frame a
    img_pb: torch.Tensor  # (P, 3, h, w) image of frame b
    pa_offset: torch.Tensor  # (P, 1) flat offset of frame a's depth in the (n * h * w) depth vector
    flow_idx: torch.Tensor  # (Pf,) block-local indices of the pairs with a flow loss
    flows: torch.Tensor | None  # (Pf, h * w, 2) their flows, px
    fvalid: torch.Tensor | None  # (Pf, h * w) their consistency masks
    keep_pb: torch.Tensor | None = None  # (P, h, w) bool the user's kept cells of frame b (None: no --masks)
    stats_pa: torch.Tensor | None = None  # (P, 2 * 3, h * w) frame a's 3x3 patch means, then mean squares

    @classmethod
    def gather(cls, win: "Window", pw: torch.Tensor, group: int, members: torch.Tensor, first: int, stride: int,
               hw: int, a_stats: torch.Tensor | None = None) -> "_PairBlock":
        """The block of the group's pairs ``members`` (indices into ``win``'s pair list) at rows
        first, first + stride, ...; pw (npair,) all pairs' weights; a_stats (n, 2 * 3, h * w)
        the frames' patch statistics (``_patch_stats_table``)."""
        rows = torch.arange(first, len(members), stride)
        sel = members[rows]
        sub = [win.pairs[i] for i in sel.tolist()]
        pa = torch.tensor([q.a for q in sub], dtype=torch.long)
        pb = torch.tensor([q.b for q in sub], dtype=torch.long)
        fl = [i for i, q in enumerate(sub) if q.flow is not None]
        flows = torch.stack([sub[i].flow.reshape(hw, 2) for i in fl]) if fl else None
        fvalid = torch.stack([sub[i].valid.reshape(hw) for i in fl]) if fl else None
        flow_idx = torch.tensor(fl, dtype=torch.long)
        amask = win.static[pa].reshape(len(sub), hw).clone()
        if fvalid is not None:  # i.e. fl
            amask[flow_idx] = amask[flow_idx] * fvalid
        keep_pb = None
        if win.keep is not None:
            # the user's exclusion is hard: a point whose 3x3 patch holds a user-masked cell of
            # frame a is out (its neighbours' colours enter the photometric term), and so is a
            # point whose samples in b mix one (_block_loss)
            amask = amask * (1 - F.max_pool2d(1 - win.keep[pa][:, None], 3, 1, 1)[:, 0]).reshape(len(sub), hw)
            keep_pb = win.keep[pb] > 0
        return cls(sel, group, rows, pa, pb, pw[sel], amask, win.imgs[pa], win.imgs[pb], (pa * hw)[:, None],
                   flow_idx, flows, fvalid, keep_pb, None if a_stats is None else a_stats[pa])


_POOLS: dict[int, ThreadPoolExecutor] = {}
os.register_at_fork(after_in_child=_POOLS.clear)  # a forked child has none of the parent's threads


def _pool(n: int) -> ThreadPoolExecutor:
    """A process-wide pool of n threads for the pair blocks (created once, reused by every window)."""
    if n not in _POOLS:
        _POOLS[n] = ThreadPoolExecutor(max_workers=n, thread_name_prefix="gcvd-pairs")
    return _POOLS[n]


def _sum_grads(grads: list[torch.Tensor | None], like: torch.Tensor) -> torch.Tensor:
    """The blocks' gradients summed in block order (a block that does not reach ``like``: zero)."""
    total = torch.zeros_like(like)
    for g in grads:
        if g is not None:
            total = total + g
    return total


_OFFS = torch.tensor([(dv, du) for dv in (-1, 0, 1) for du in (-1, 0, 1)])  # 3x3 patch (row, column) offsets
_OFFS_UV = _OFFS.flip(-1).to(torch.float32)  # the same offsets as (u, v) pixel shifts
# A point of frame a whose depth in camera b is below this (m) is behind b or on its image plane:
# it enters no term of the pair (its projection, and the gradient of its projection, are unbounded)
MIN_DEPTH_IN_B = 1e-3


def _patch_index(idx: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Flat pixel indices (..., 9) of the 3x3 patches (clamped to the image, ``_OFFS`` order)
    around flat pixel indices idx (...)."""
    u0, v0 = idx % w, idx // w
    nu = (u0[..., None] + _OFFS[:, 1]).clamp(0, w - 1)
    nv = (v0[..., None] + _OFFS[:, 0]).clamp(0, h - 1)
    return nv * w + nu


def _patch_stats_table(imgs: torch.Tensor) -> torch.Tensor:
    """Every pixel's 3x3 patch mean and mean square per channel, imgs (n, C, h, w) -> (n, 2C, h * w):
    ``L.patch_stats`` of the patches a step gathers at its points, computed once per window (a
    frame-a patch is fixed pixels; its statistics are the same bits at every step)."""
    n, c, h, w = imgs.shape
    nidx = _patch_index(torch.arange(h * w), h, w).reshape(-1)
    patches = imgs.reshape(n, c, h * w)[:, :, nidx].view(n, c, h * w, 9)
    return torch.cat(L.patch_stats(patches), 1)


class Solver:
    """Runs Adam on one window; state is exposed for checkpointing.

    ``lr`` is the depth head's learning rate (the stage's); the pose and mesh rates and the
    number of sampled points come from ``kf``, the loss weights from ``losses``.

    ``points_by_weight``: a pair gets ``kf.points`` * its weight / the largest pair weight points
    per step (at least ``_MIN_POINTS``) instead of ``kf.points`` each (see ``_points_per_pair``).
    ``stop_every`` / ``stop_rel``: the plateau test of ``plateaued`` (stop_rel 0: never).
    ``schedule``: the learning rates over a window's steps (``LrSchedule``; None or "constant":
    the base rates, never touched).
    """

    _coarse_now = False  # whether this step draws the coarse phase's (fewer) points (``set_step``)

    def __init__(
        self, win: Window, net: DepthNet, posenet: PoseNet | None, lr: float, depth: DepthModel,
        losses: LossWeights, kf: KeyframeSettings, pair_blocks: int = 1, points_by_weight: bool = False,
        stop_every: int = 25, stop_rel: float = 0.0, schedule: LrSchedule | None = None,
        coarse: Coarse | None = None,
    ) -> None:
        self.w, self.net, self.posenet = win, net, posenet
        self.depth, self.losses, self.kf = depth, losses, kf
        self.points_by_weight, self.stop_every, self.stop_rel = points_by_weight, max(1, stop_every), stop_rel
        self.losses_run: list[float] = []  # every step's loss so far (checkpointed: the plateau test reads it)
        n = win.base.shape[0]
        self.delta = torch.zeros(n, 6, dtype=torch.float64, requires_grad=True)
        self.mesh = win.mesh_init.clone().requires_grad_(True)
        self.lscale = torch.zeros(n, requires_grad=True)
        groups = [{"params": list(net.head.parameters()), "lr": lr}]
        if posenet is None:
            groups.append({"params": [self.delta], "lr": kf.pose_lr})
        else:
            groups.append({"params": list(posenet.decoder.parameters()), "lr": kf.pose_lr})
        groups.append({"params": [self.mesh], "lr": lr * kf.mesh_lr_mult * kf.mesh_shape_lr_frac})
        groups.append({"params": [self.lscale], "lr": lr * kf.mesh_lr_mult})
        self.opt = Adam(groups)  # torch.optim.Adam's arithmetic without its 2-s torch._dynamo import
        self.schedule = schedule or LrSchedule()
        self.coarse = coarse or Coarse()
        if self.schedule.kind not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule {self.schedule.kind!r}: one of {', '.join(LR_SCHEDULES)}")
        self.base_lrs = [float(g["lr"]) for g in self.opt.param_groups]  # head, poses, mesh shape, per-frame scale
        sch = self.schedule
        self.start_lrs = [b * m for b, m in zip(self.base_lrs, (sch.start_mult, sch.pose_start_mult, sch.start_mult,
                                                                   sch.start_mult))]
        h, w = win.imgs.shape[-2:]
        self.h, self.w_ = h, w
        self.rays = G.pixel_rays(h, w, win.K).to(torch.float32)  # (h*w, 3)
        self.K32 = win.K.to(torch.float32)  # the intrinsics the warp projects with (constant over the window)
        self._prep_pairs(pair_blocks)

    def _prep_pairs(self, n_blocks: int) -> None:
        """The point groups (pairs sharing a number of points per step, most points first) and
        the thread blocks: ``blocks[k]`` holds thread k's share of every group."""
        win = self.w
        pr = win.pairs
        pw = torch.tensor([q.weight for q in pr], dtype=torch.float32)
        pw = pw / pw.sum().clamp(min=1e-9)
        hw = self.h * self.w_
        self.head_in = self.net.head_input(win.enc)  # (n * h * w, C + 1)
        self.ref_std = self.net.prior_std(win.enc)  # (n, 1, 1, 1)
        a_stats = _patch_stats_table(win.imgs) if self.losses.w_photo > 0 else None
        self.prior_grads = L.prior_gradients(torch.exp(win.enc.log_prior[:, 0]), 3, win.static, keep=win.keep)
        m = _points_per_pair([q.weight for q in pr], self.kf.points, self.points_by_weight)
        self.groups = [(mg, torch.tensor([i for i, mi in enumerate(m) if mi == mg], dtype=torch.long))
                       for mg in sorted(set(m), reverse=True)]  # [(points, (P_g,) pair indices)]
        self.points_per_step = int(sum(m))
        n_blocks = max(1, min(n_blocks, len(pr)))
        blocks = [[_PairBlock.gather(win, pw, g, members, k, n_blocks, hw, a_stats)
                   for g, (_, members) in enumerate(self.groups) if k < len(members)] for k in range(n_blocks)]
        self.blocks = [b for b in blocks if b]

    def poses(self) -> torch.Tensor:
        """(n, 4, 4) float64 T_w_c (camera-to-world)."""
        if self.posenet is None:
            d = self.delta
        else:
            assert self.w.pose_code is not None  # a PoseNet window carries its codes
            d = self.posenet.decode(self.w.pose_code).to(torch.float64)
        d = d * self.w.pose_train[:, None]
        return self.w.base @ G.pose_from_rt(d)

    def meshes(self) -> torch.Tensor:
        """Effective log-scale meshes (n, gh, gw): vertex offsets + per-frame scale."""
        full = self.mesh + self.lscale[:, None, None]
        m = self.w.mesh_train[:, None, None]
        return full * m + full.detach() * (1 - m)

    def _sample(self, gen: torch.Generator) -> list[torch.Tensor]:
        """Per point group, (P_g, M_g) flat pixel indices in frame a of this step's points
        (consumes ``gen``; one group: (npair, points), the draw of the uniform allocation). In the
        coarse phase (``Coarse``) a group draws M_g * coarse.points / kf.points points (at least 1,
        at most M_g): a fresh random subset every step, so the steps still cover the image."""
        ms = [mg for mg, _ in self.groups]
        if self._coarse_now:
            ms = [self.coarse.points_of(mg, self.kf.points) for mg in ms]
        return [torch.randint(0, self.h * self.w_, (len(members), m), generator=gen)
                for m, (_, members) in zip(ms, self.groups)]

    def _thread_loss(self, blocks: list["_PairBlock"], depth: torch.Tensor, T_w_c: torch.Tensor,
                     idx: list[torch.Tensor]) -> torch.Tensor:
        """Sum of one thread's blocks' losses (in group order); idx from ``_sample``."""
        total = self._block_loss(blocks[0], depth, T_w_c, idx[blocks[0].group][blocks[0].rows])
        for b in blocks[1:]:
            total = total + self._block_loss(b, depth, T_w_c, idx[b.group][b.rows])
        return total

    def _add_regularisers(self, total: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """``total`` + the pair-independent terms: depth-gradient orientation, mesh smoothness."""
        lw, win = self.losses, self.w
        if lw.grad and lw.w_grad > 0:
            total = total + lw.w_grad * win.grad_mult * L.gradient_orientation_loss(
                depth, None, 3, win.static, prior_grads=self.prior_grads).mean()
        if self.depth.mesh and lw.w_mesh > 0:
            total = total + lw.w_mesh * L.mesh_smoothness_loss(self.mesh, win.dyn_mesh).mean()
        return total

    def _depth(self) -> torch.Tensor:
        """(n, h, w) depth of the window's frames at loss resolution."""
        return self.net.decode(self.w.enc, self.meshes() if self.depth.mesh else None, self.head_in, self.ref_std)

    def loss(self, gen: torch.Generator) -> torch.Tensor:
        """The window's total loss (scalar) on freshly sampled points (consumes ``gen``)."""
        depth = self._depth()
        T_w_c = self.poses()
        idx = self._sample(gen)
        total = self._thread_loss(self.blocks[0], depth, T_w_c, idx)
        for b in self.blocks[1:]:
            total = total + self._thread_loss(b, depth, T_w_c, idx)
        return self._add_regularisers(total, depth)

    def _block_loss(self, blk: "_PairBlock", depth: torch.Tensor, T_w_c: torch.Tensor, idx: torch.Tensor,
                    ) -> torch.Tensor:
        """Sum over a block's pairs of weight * pair loss: depth (n, h, w), T_w_c (n, 4, 4) float64,
        idx (P, M) the block's sampled flat pixel indices in frame a -> scalar."""
        lw = self.losses
        w = self.w_
        npair, M = idx.shape
        T_b_a = G.relative_pose(T_w_c[blk.pa], T_w_c[blk.pb]).to(torch.float32)  # (npair, 4, 4)
        u0, v0 = idx % w, idx // w
        nidx = _patch_index(idx, self.h, w).reshape(npair, M * 9)
        uv, uvc, zc = self._warp(blk, depth, T_b_a, idx, nidx)
        if self.kf.photo_warp == "centre":  # the centre sample of a patch is uvc itself (offset 0)
            img_b, ins_c = G.sample_points(blk.img_pb, uv), G.inside_image(uvc, self.h, w)
        else:
            img_b, inside = G.sample_bilinear(blk.img_pb, uv)
            ins_c = inside.reshape(npair, M, 9)[:, :, 4]
        d_b = G.sample_frames(depth, blk.pb, uvc)  # (npair, M)
        in_front = (zc > MIN_DEPTH_IN_B).float()
        wgt = blk.amask.gather(1, idx) * ins_c.float() * in_front
        if blk.keep_pb is not None:  # every sample of the point in b (its patch, its depth) mixes kept cells only
            wgt = wgt * G.footprint_kept(blk.keep_pb, uv.detach()).reshape(npair, M, 9).all(-1).float()
        pair_loss = torch.zeros(npair)
        if lw.w_photo > 0:
            pair_loss = pair_loss + lw.w_photo * L.weighted_mean(self._photo_terms(blk, idx, nidx, img_b), wgt)
        if lw.w_depth > 0:
            pair_loss = pair_loss + lw.w_depth * L.depth_consistency_loss(zc, d_b, wgt)
        if lw.w_flow > 0 and len(blk.flow_idx):
            fi = blk.flow_idx
            fidx = idx[fi]
            assert blk.flows is not None  # set whenever flow_idx is not empty
            tgt = blk.flows.gather(1, fidx[..., None].expand(-1, -1, 2))
            base_uv = torch.stack([u0[fi], v0[fi]], -1).to(torch.float32)
            # in front of b only, as the other terms: the flow loss of a point on b's image plane
            # had gradients 10^5 times the window's (a blurred HoloLens frame whose prior put pixels
            # at 1/14 of its median depth), which Adam turned into a full-rate collapse of that
            # frame's depth scale (0.003 m after two windows; docs/log/2026-11-29-lead11.md)
            fwgt = blk.amask[fi].gather(1, fidx) * in_front[fi]
            if blk.keep_pb is not None:  # the flow's target in b mixes kept cells only
                fwgt = fwgt * G.footprint_kept(blk.keep_pb[fi], base_uv + tgt).float()
            fl = L.flow_loss(uvc[fi], base_uv + tgt, fwgt)
            pair_loss = pair_loss.index_add(0, fi, lw.w_flow * fl)
        return (blk.pw * pair_loss).sum()

    @staticmethod
    def _photo_terms(blk: "_PairBlock", idx: torch.Tensor, nidx: torch.Tensor, img_b: torch.Tensor) -> torch.Tensor:
        """Photometric terms (npair, M) of the points idx (npair, M), patches nidx (npair, M * 9),
        img_b (npair, M * 9, 3) their warped patches in b: channel-major patches (npair, 3, M, 9)
        (the views' own memory order), frame a's statistics gathered from the block's table."""
        npair, M = idx.shape
        pa_ = G.gather_pixels(blk.img_pa, nidx).transpose(1, 2).view(npair, -1, M, 9)
        pb_ = img_b.transpose(1, 2).view(npair, -1, M, 9)
        a_stats = None
        if blk.stats_pa is not None:
            st = blk.stats_pa.gather(2, idx[:, None, :].expand(-1, blk.stats_pa.shape[1], -1))
            a_stats = (st[:, : pa_.shape[1]], st[:, pa_.shape[1] :])
        return L.photometric_terms(pa_, pb_, a_stats=a_stats)

    def _warp(self, blk: "_PairBlock", depth: torch.Tensor, T_b_a: torch.Tensor, idx: torch.Tensor,
              nidx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Where the sampled points of frame a land in frame b: depth (n, h, w), T_b_a (npair, 4, 4),
        idx (npair, M) flat pixel indices of the points in a, nidx (npair, M * 9) of their 3x3
        patches -> (uv (npair, M * 9, 2) px in b of the patch pixels, uvc (npair, M, 2) px and zc
        (npair, M) depth in camera b of the centres).

        ``photo_warp="pixel"`` (the paper) lifts every patch pixel with its own depth;
        ``"centre"`` lifts only the centre and shifts the patch with it (the patch is 3 pixels
        wide at loss resolution, where the frame-to-frame rotation and foreshortening inside it
        are far below a pixel): a ninth of the lifting, transform and projection, forward and
        backward."""
        npair, M = idx.shape
        K = self.K32
        if self.kf.photo_warp == "centre":
            d_a = depth.reshape(-1)[blk.pa_offset + idx]  # (npair, M)
            uvc, zc = G.project(G.transform(T_b_a, self.rays[idx] * d_a[..., None]), K)
            uv = (uvc[:, :, None, :] + _OFFS_UV).reshape(npair, M * 9, 2)
            return uv, uvc, zc
        d_a = depth.reshape(-1).gather(0, (blk.pa_offset + nidx).reshape(-1)).view(npair, M * 9)
        uv, z = G.project(G.transform(T_b_a, self.rays[nidx] * d_a[..., None]), K)
        return uv, uv.reshape(npair, M, 9, 2)[:, :, 4], z.reshape(npair, M, 9)[:, :, 4]

    def _split_backward(self, gen: torch.Generator) -> torch.Tensor:
        """Loss and gradients with the pair blocks on threads: each block's loss is
        differentiated up to the shared depth and poses (``autograd.grad``), the block gradients
        are summed in block order, then one backward runs through the depth head and poses."""
        depth = self._depth()
        T_w_c = self.poses()
        idx = self._sample(gen)
        d_leaf = depth.detach().requires_grad_(True)
        T_leaf = T_w_c.detach().requires_grad_(True)

        def block(b: list[_PairBlock]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            with torch.enable_grad():
                part = self._thread_loss(b, d_leaf, T_leaf, idx)
                g_d, g_T = torch.autograd.grad(part, (d_leaf, T_leaf), allow_unused=True)
            return part.detach(), g_d, g_T

        futures = [_pool(len(self.blocks) - 1).submit(block, b) for b in self.blocks[1:]]
        results = [block(self.blocks[0])] + [f.result() for f in futures]
        g_d = _sum_grads([r[1] for r in results], d_leaf)
        g_T = _sum_grads([r[2] for r in results], T_leaf)
        reg = self._add_regularisers(torch.zeros(()), depth)
        outs, grads = [depth, T_w_c], [g_d, g_T]
        if reg.requires_grad:
            outs.append(reg)
            grads.append(torch.ones_like(reg))
        torch.autograd.backward(outs, grads)
        total = results[0][0]
        for r in results[1:]:
            total = total + r[0]
        return total + reg.detach()

    def set_step(self, step: int, steps: int) -> None:
        """Set every group's learning rate for step ``step`` (0-based) of ``steps``: a function of
        the step index alone, so a window resumed at a checkpointed step gets the same rates (and
        the same points per pair: the coarse phase, ``Coarse``)."""
        self._coarse_now = self.coarse.active(step, steps) and self.coarse.points < self.kf.points
        if self.schedule.kind == "constant":
            return
        f = lr_factor(self.schedule.kind, step, steps, self.schedule.final_frac)
        for g, start in zip(self.opt.param_groups, self.start_lrs):
            g["lr"] = start * f

    def step(self, gen: torch.Generator) -> float:
        self.opt.zero_grad()
        if len(self.blocks) > 1:
            loss = self._split_backward(gen)
        else:
            loss = self.loss(gen)
            loss.backward()
        self.opt.step()
        self.losses_run.append(float(loss.detach()))
        return self.losses_run[-1]

    def plateaued(self) -> bool:
        """Whether the loss has stopped falling: checked every ``stop_every`` steps (from the
        window's first step), true when the mean loss of the last ``stop_every`` steps is less than
        ``stop_rel`` (relative) below the mean of the ``stop_every`` before. Means over blocks of
        steps, as every step's loss is drawn on fresh random points. A function of the losses
        only: deterministic, and the same on a resumed window (they are checkpointed). Never in the
        coarse phase (``Coarse``): its losses are drawn on a fraction of the points, noisier."""
        n, e = len(self.losses_run), self.stop_every
        if self.stop_rel <= 0 or self._coarse_now or n < 2 * e or n % e:
            return False
        prev = math.fsum(self.losses_run[n - 2 * e : n - e]) / e
        cur = math.fsum(self.losses_run[n - e :]) / e
        return prev - cur < self.stop_rel * abs(prev)

    # -- checkpoint state --
    def state(self) -> dict[str, torch.Tensor]:
        out: dict[str, torch.Tensor] = {
            "win.delta": self.delta.detach().clone(),
            "win.mesh": self.mesh.detach().clone(),
            "win.lscale": self.lscale.detach().clone(),
            "win.losses": torch.tensor(self.losses_run, dtype=torch.float64),
        }
        for k, v in self.net.trainable_state().items():
            out[k] = v
        if self.posenet is not None:
            for k, v in self.posenet.decoder.state_dict().items():
                out[f"posenet.{k}"] = v.detach().clone()
        for i, st in self.opt.state_dict()["state"].items():
            for k, v in st.items():
                out[f"adam.{i}.{k}"] = torch.as_tensor(v).detach().clone()
        return out

    def load(self, t: Mapping[str, torch.Tensor]) -> None:
        with torch.no_grad():
            self.delta.copy_(t["win.delta"])
            self.mesh.copy_(t["win.mesh"])
            self.lscale.copy_(t["win.lscale"])
        self.losses_run = [float(x) for x in t["win.losses"].tolist()] if "win.losses" in t else []
        self.net.load_trainable_state(dict(t))
        if self.posenet is not None:
            self.posenet.decoder.load_state_dict({k[len("posenet."):]: v for k, v in t.items() if k.startswith("posenet.")})
        sd = self.opt.state_dict()
        st: dict[int, dict[str, torch.Tensor]] = {}
        for k, v in t.items():
            if k.startswith("adam."):
                _, i, name = k.split(".", 2)
                st.setdefault(int(i), {})[name] = v.clone()
        sd["state"] = st
        self.opt.load_state_dict(sd)


def run_solver(
    solver: Solver,
    gen: torch.Generator,
    steps: int,
    start: int,
    save: Callable[[int], None] | None,
) -> float:
    """Steps ``start`` .. ``steps``-1, fewer when the loss plateaus (``Solver.plateaued``, tested
    before the checkpoint of the same step, so a resumed window stops where an uninterrupted one
    does); ``save(step_done)`` is called every checkpoint_every steps (not after the last one).
    Returns the last step's loss (NaN if no step ran); ``len(solver.losses_run)`` steps ran."""
    loss = float("nan")
    every = max(1, solver.kf.checkpoint_every)
    for s in range(start, steps):
        solver.set_step(s, steps)
        loss = solver.step(gen)
        if solver.plateaued():
            break
        if save is not None and (s + 1) % every == 0 and (s + 1) < steps:
            save(s + 1)
    return loss


LR_SCHEDULES = ("constant", "cosine", "linear")


@dataclass(frozen=True)
class Coarse:
    """Coarse-to-fine points: the first ``frac`` of a window's steps draw ``points`` points per
    ordered pair (a random subset of the usual number, re-drawn every step from the window's
    generator), the rest the full number. Adam takes steps of about its rate whatever the points,
    so the early steps, where the parameters are far from their optimum, cost a fraction of a
    full step; the late steps see every pair at full density. ``points`` 0: off."""

    points: int = 0
    frac: float = 0.0

    @classmethod
    def of(cls, s: Any) -> "Coarse":
        """From a settings section's coarse_points, coarse_frac."""
        return cls(int(s.coarse_points), float(s.coarse_frac))

    def active(self, step: int, steps: int) -> bool:
        """Whether step ``step`` (0-based) of ``steps`` is in the coarse phase."""
        return 0 < self.points and step < int(round(self.frac * steps))

    def points_of(self, full: int, points: int) -> int:
        """A point group's points per pair in the coarse phase: ``full`` (its usual number, of a
        stage drawing ``points`` per pair) scaled by self.points / points, in [1, full]."""
        return max(1, min(full, int(round(full * self.points / max(points, 1)))))


@dataclass(frozen=True)
class LrSchedule:
    """A window's learning rates over its steps: at step s of ``steps`` a group's rate is its start
    rate times ``lr_factor(kind, s, steps, final_frac)``; the start rate is its base rate times
    ``start_mult`` (depth head, mesh shape, per-frame scale) or ``pose_start_mult`` (poses)."""

    kind: str = "constant"
    final_frac: float = 0.1
    start_mult: float = 1.0
    pose_start_mult: float = 1.0

    @classmethod
    def of(cls, s: Any) -> "LrSchedule":
        """From a settings section's lr_schedule, lr_final_frac, lr_start_mult, pose_lr_start_mult."""
        return cls(s.lr_schedule, s.lr_final_frac, s.lr_start_mult, s.pose_lr_start_mult)


def lr_factor(schedule: str, step: int, steps: int, final_frac: float) -> float:
    """The learning-rate multiplier at step ``step`` (0-based) of a window of ``steps``, relative
    to the start rate: "constant" 1; "cosine" 1 at the first step falling along a half cosine to
    ``final_frac`` at the last; "linear" the same along a straight line. Adam at a fixed rate keeps moving at a
    near-constant pace to the last step (its step size does not shrink with the gradient), so a
    window stops where the noise of its sampled points leaves it; a decaying rate lets it settle."""
    if schedule == "constant" or steps <= 1:
        return 1.0
    t = min(max(step, 0), steps - 1) / (steps - 1)
    if schedule == "cosine":
        return final_frac + (1.0 - final_frac) * 0.5 * (1.0 + math.cos(math.pi * t))
    if schedule == "linear":
        return final_frac + (1.0 - final_frac) * (1.0 - t)
    raise ValueError(f"lr_schedule {schedule!r}: one of {', '.join(LR_SCHEDULES)}")


_MIN_POINTS = 8  # points per pair and step with ``points_by_weight`` (at least; never more than ``points``)


def _points_per_pair(weights: list[float], points: int, by_weight: bool) -> list[int]:
    """Points per step of each pair (weights (npair,) > 0): ``points`` each, or with
    ``by_weight`` ``points`` * weight / max weight, rounded, at least min(_MIN_POINTS, points).

    Why by weight: a pair's loss is the mean over its points, so its variance falls as 1 / points,
    and the window's loss is the weighted sum of the pairs' means; for a fixed number of points
    in all, the variance of that sum is least with the points in proportion to the weights
    (Neyman allocation). The keyframe windows weight pairs 1 / tau: with taus (1, 2, 4, 8) a
    40-keyframe window's 290 pairs take 18176 points per step instead of 37120, the flow
    loss's tau = 1 pairs all 128 of theirs."""
    if not by_weight or not weights:
        return [points] * len(weights)
    top = max(weights)
    lo = min(_MIN_POINTS, points)
    return [max(lo, int(round(points * w / top))) for w in weights]


