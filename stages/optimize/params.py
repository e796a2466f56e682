"""Parameters of the optimisations, declared once (plain dataclasses, one per concern).

The pipeline derives its config sections from these classes (``gcvd_flow.pipeline``:
``depth``, ``losses``, ``optimize_keyframes``, ``optimize_edges``, ``optimize_segments``,
``pose_graph``, ``bundle_adjustment``; see ``stages/params.py``), so a
field's name, default, description and constraint are written here only. ``metadata`` holds the
``description`` and the numeric constraints (``ge``, ``gt``, ...) the config section enforces.
The stage functions read the fields as attributes, so they accept these dataclasses and the
pipeline's pydantic sections alike.

Units: learning rates per Adam step; ``loss_scale`` = fraction of the working resolution at which
the losses are evaluated; ``points`` = samples per ordered frame pair per step.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from gcvd_flow.stages.params import param as _f


def _frame_distances(v: tuple[int, ...]) -> tuple[int, ...]:
    if not v or any(k < 1 for k in v):
        raise ValueError("frame distances tau >= 1 (at least one)")
    return v


__all__ = ["DepthModel", "LossWeights", "KeyframeSettings", "EdgeSettings", "SegmentSettings",
           "PoseGraphSettings", "BundleAdjustmentSettings"]


@dataclass(frozen=True)
class DepthModel:
    """The depth model (stages.models.depth_net.DepthNet) of all three optimisations."""

    layer_norm: bool = _f(True, "per-frame non-affine LayerNorm of the log inverse depth")
    mesh: bool = _f(True, "per-frame log-scale deformation mesh")
    mesh_vertices: int = _f(17, "mesh vertices on the long side", ge=2, le=4096)


@dataclass(frozen=True)
class LossWeights:
    """Loss weights of all three optimisations (stages.optimize.losses)."""

    grad: bool = _f(True, "use the depth-gradient orientation loss")
    w_photo: float = _f(1.0, ge=0)
    w_flow: float = _f(10.0, ge=0)
    w_depth: float = _f(0.5, ge=0)
    w_grad: float = _f(0.1, ge=0)
    w_mesh: float = _f(0.5, ge=0)


@dataclass(frozen=True)
class KeyframeSettings:
    """Keyframe windows, and the solver settings all three optimisations share (pose_lr,
    mesh_lr_mult, mesh_shape_lr_frac, points, taus, flow_taus, photo_warp; checkpoint_every
    for the keyframe windows; the edge optimisation also uses loss_scale; edges and segments
    have their own ``threads``)."""

    window: int = _f(40, "keyframes per optimisation window", ge=2)
    overlap: int = _f(8, "keyframes shared by consecutive windows (their poses are held fixed)", ge=1)
    steps: int = _f(150, "Adam steps per window", ge=1)
    lr: float = _f(2e-4, "depth head lr (paper); mesh lr = lr * mesh_lr_mult", ge=0)
    pose_lr: float = _f(5e-4, "lr of the pose corrections (5e-4 holds, 3e-3 drifts)", ge=0)
    mesh_lr_mult: float = _f(100.0, "per-frame log-scale lr = lr * mesh_lr_mult", ge=0)
    loss_scale: float = _f(0.25, "loss resolution, fraction of the working resolution (also edges)", gt=0, le=1)
    points: int = _f(128, "sampled points per ordered pair per step", ge=1)
    pose_param: Literal["direct", "net"] = _f("direct", "per-frame pose corrections or a pose network")
    init: Literal["essential", "identity"] = _f("essential", "initial keyframe poses: essential-matrix "
                                                "chain or identity")
    chain_check_deg: float = _f(0.0, "essential chain: pairs in a keyframe triplet whose chained-flow rotation "
                                     "disagrees with the composed pairs' by more than this (degrees) get the rotation"
                                     " medoid of their own and two bridged estimates and a translation re-estimated "
                                     "with it (stages/optimize/chain_check.py; 0 = off)", ge=0)
    chain_prior_scale_below: float = _f(0.0, "essential chain: a pair whose parallax (flow left after its rotation) "
                                             "is below this fraction of its flow (rotation-dominated), or a rotation-only "
                                             "pair, carries the scale by moving the previous frame's depth along the flow "
                                             "instead of same-pixel triangulated depth ratios (stages/optimize/init.py "
                                             "essential_chain; 0 = off)", ge=0, le=1)
    checkpoint_every: int = _f(50, "steps between checkpoints", ge=1)
    schedule: Literal["chained", "independent"] = _f(
        "chained", "chained (the authors'): each window starts from the previous one's optimised, "
        "fixed overlap, one after the other; independent: every window starts from the initial "
        "essential-matrix chain and they run side by side on the workers (3+ windows), each then "
        "placed onto the previous one by a similarity fitted on the overlap (faster, but the fixed "
        "overlap no longer carries the scale: see docs/benchmarks.md)")
    threads: int = _f(1, "torch threads of the keyframe windows (results are bit-identical only for the same count)", ge=1)
    pair_blocks: int = _f(2, "keyframe windows: the pairs are split into this many blocks whose losses and gradients "
                             "(up to the shared depth and poses) are computed on threads of their own each step, then"
                             " summed in block order (1 = one block, the sum unsplit; results are bit-identical only "
                             "for the same count)", ge=1)
    taus: tuple[int, ...] = _f((1, 2, 4, 8), "frame distances of the optimised pairs (all stages)",
                              validator=_frame_distances)
    flow_taus: tuple[int, ...] = _f((1,), "pairs that also get the flow loss; tau > 1 uses flows chained "
                                    "from the tau = 1 flows (the authors use tau = 1 only)",
                                    validator=_frame_distances)
    photo_warp: Literal["pixel", "centre"] = _f("centre", "photometric 3x3 patches (all three optimisations): the "
                                                          "centre warped and the patch shifted with it (a ninth of "
                                                          "the geometry per step), or every pixel warped with its own"
                                                          " depth (the paper's, 'pixel'; --profile paper)")
    mesh_shape_lr_frac: float = _f(0.1, "spatial mesh vertex lr = lr * mesh_lr_mult * this: on point-sampled "
                                   "losses a fast spatial mesh bends the depth along flow noise, while poses "
                                   "need a fast per-frame scale", ge=0)
    points_by_weight: bool = _f(False, "keyframe windows: a pair's points per step in proportion to its weight 1/tau "
                                       "(points * weight / max weight, at least 8): the least variance of the "
                                       "window's loss for the points drawn (opt-in: cheaper steps, worse on some "
                                       "clips)")
    stop_every: int = _f(25, "keyframe windows: steps between plateau checks", ge=1)
    lr_schedule: Literal["constant", "cosine", "linear"] = _f(
        "constant", "keyframe windows: the learning rates over a window's steps: constant (lr, pose_lr and the mesh "
        "rates), or from a start rate (lr_start_mult, pose_lr_start_mult x them) at the first step down to "
        "lr_final_frac of it at the last, along a half cosine or a line (a function of the step index, so a "
        "resumed window matches an uninterrupted one)")
    lr_start_mult: float = _f(1.0, "keyframe windows, lr_schedule cosine / linear: the depth head's and the mesh "
                              "rates at a window's first step, as a multiple of lr and the mesh rates", gt=0)
    pose_lr_start_mult: float = _f(1.0, "keyframe windows, lr_schedule cosine / linear: the pose rate at a window's "
                                   "first step, as a multiple of pose_lr", gt=0)
    lr_final_frac: float = _f(0.1, "keyframe windows, lr_schedule cosine / linear: every rate at a window's last "
                              "step, as a fraction of its first-step rate", ge=0, le=1)
    coarse_points: int = _f(0, "keyframe windows, coarse-to-fine: points per ordered pair per step in the first "
                            "coarse_frac of a window's steps (a random subset, re-drawn every step; 0: always "
                            "points); the plateau stop does not fire in that phase", ge=0)
    coarse_frac: float = _f(0.5, "keyframe windows, coarse-to-fine: the fraction of a window's steps that draw "
                            "coarse_points points per pair", ge=0, le=1)
    stop_rel: float = _f(0.0, "keyframe windows stop early when the mean loss of the last stop_every steps is "
                         "less than this fraction below that of the stop_every steps before (0: never)", ge=0)

    def check(self) -> None:
        if self.overlap >= self.window:
            raise ValueError(f"optimize_keyframes.overlap ({self.overlap}) must be less than optimize_keyframes.window "
                             f"({self.window})")


@dataclass(frozen=True)
class EdgeSettings:
    """Non-sequential (loop) edge optimisation."""

    steps: int = _f(100, "Adam steps per edge", ge=1)
    lr: float = _f(1e-4, "depth head lr", ge=0)
    essential_init: bool = _f(True, "re-estimate the edge's rotation / translation direction by two-view "
                              "geometry on its flow (the keyframe-chain init carries the chain's drift); "
                              "|t| is kept")
    threads: int = _f(1, "torch threads per edge; the edges are independent and run side by side on the "
                      "run's worker processes (--jobs) (results are bit-identical only for the same count)", ge=1)


@dataclass(frozen=True)
class SegmentSettings:
    """Segment optimisation: all frames, keyframe poses frozen."""

    # 50, not 60: every window's loss flattens at ~step 50-60; 50 held every ATE / AbsRel row and
    # make regress, 40 failed make regress (ATE +6.1 %) (docs/log/2026-11-29-segstop.md)
    steps: int = _f(50, "Adam steps per window", ge=1)
    lr: float = _f(1e-4, "depth head lr", ge=0)
    loss_scale: float = _f(0.25, "loss resolution, fraction of the working resolution", gt=0, le=1)
    pair_power: float = _f(0.5, "pair weight tau ** pair_power", ge=0)
    grad_mult: float = _f(5.0, "multiplier of the gradient loss weight", ge=0)
    window: int = _f(40, "frames per window (windows are cut at keyframes)", ge=2)
    init: Literal["pnp", "interp"] = _f("pnp", "non-keyframe pose init: keyframe depth + flow tracks + PnP, "
                                        "or geodesic interpolation")
    prior: Literal["transfer", "prior"] = _f("transfer", "depth model input: keyframe depths reprojected "
                                             "into the frames (own prior only in holes), or the priors")
    threads: int = _f(1, "torch threads per window; the windows are independent and run side by side on "
                      "the run's worker processes (--jobs), so one thread each keeps every core busy "
                      "(results are bit-identical only for the same count, whatever --jobs is)", ge=1)
    points_by_weight: bool = _f(False, "a pair's points per step in proportion to its weight tau ** pair_power "
                                "(see optimize_keyframes.points_by_weight)")
    stop_every: int = _f(20, "steps between plateau checks", ge=1)
    lr_schedule: Literal["constant", "cosine", "linear"] = _f(
        "constant", "the learning rates over a window's steps (lr, and the keyframe stage's pose and mesh rates): "
        "constant, or cosine / linear from the start rates to lr_final_frac of them (see "
        "optimize_keyframes.lr_schedule)")
    lr_start_mult: float = _f(1.0, "lr_schedule cosine / linear: the depth head's and the mesh rates at a window's "
                              "first step, as a multiple of lr and the mesh rates", gt=0)
    pose_lr_start_mult: float = _f(1.0, "lr_schedule cosine / linear: the pose rate at a window's first step, as a "
                                   "multiple of optimize_keyframes.pose_lr", gt=0)
    lr_final_frac: float = _f(0.1, "lr_schedule cosine / linear: every rate at a window's last step, as a fraction "
                              "of its first-step rate", ge=0, le=1)
    coarse_points: int = _f(0, "coarse-to-fine: points per ordered pair per step in the first coarse_frac of a "
                            "window's steps (a random subset of optimize_keyframes.points, re-drawn every step; 0: "
                            "always optimize_keyframes.points)", ge=0)
    coarse_frac: float = _f(0.5, "coarse-to-fine: the fraction of a window's steps that draw coarse_points points per "
                            "pair", ge=0, le=1)
    stop_rel: float = _f(0.0, "stop a window early when the mean loss of the last stop_every steps is less than "
                         "this fraction below that of the stop_every steps before (0: never)", ge=0)


@dataclass(frozen=True)
class PoseGraphSettings:
    """Pose graph over the keyframes (stages.optimize.pose_graph)."""

    enabled: bool = True
    kind: Literal["se3", "sim3"] = "se3"
    max_iterations: int = _f(100, ge=1)
    loop_weight: float = _f(1.0, ge=0)
    max_loop_rotation_deg: float = _f(30.0, "loop edges disagreeing more with odometry are ignored, unless "
                                      "they pass loop_self_check_deg", gt=0)
    loop_self_check_deg: float = _f(5.0, "keep a loop edge the odometry gate rejects when its rotation is within "
                                    "this many degrees of the loop pair's own two-view rotation (from the pair's "
                                    "flow, independent of the drifting odometry); 0 = off", ge=0)
    # a kernel cannot tell a correct loop far from drifted odometry from a wrong one: at 0.1 it
    # bounds a wrong loop but also holds back a correct one 60+ degrees off (tests/test_loop_gate.py)
    loop_robust: float = _f(0.0, "Cauchy scale of the whitened residual of loop edges kept by "
                            "loop_self_check_deg (0 = plain least squares)", ge=0)


@dataclass(frozen=True)
class BundleAdjustmentSettings:
    """Bundle adjustment of the keyframe poses over flow tracks (stages.optimize.bundle_adjustment)."""

    enabled: bool = _f(True, "refine keyframe poses over flow tracks (robust reprojection "
                       "factors) after the pose graph")
    stride: int = _f(12, "px between track starts in every keyframe", ge=2)
    track_length: int = _f(16, "keyframes a track follows at most (plus one hop across each loop edge)", ge=2)
    min_views: int = _f(3, "keyframes that must see a point", ge=2)
    robust_px: float = _f(0.3, "Cauchy scale of the reprojection error, px", gt=0)
    # The prior only fixes the global scale (monocular BA has none); 0.05 (until 2026-11-25) held
    # the pose graph's scale drift in place: on the real walk-through the first 20 frames stayed 2.4x
    # too small and the keyframe ATE 0.131 m; at 2 / 2: 0.0536 m, per-window scale 0.95-1.10
    prior_rot_sigma: float = _f(2.0, "weak prior to the pose graph, rad", gt=0)
    prior_trans_frac: float = _f(2.0, "weak prior to the pose graph, x median depth", gt=0)
    max_iterations: int = _f(30, ge=1)
    restarts: int = _f(0, "adjust again this many times from the last adjustment's poses, each keyframe's depth "
                          "rescaled as its landmarks moved (landmarks re-initialised); gets a first adjustment "
                          "out of a local minimum (stages/optimize/bundle_adjustment.py)", ge=0)
    consistent_px: float = _f(0.25, "keep the pose graph's poses when they already reproject the tracks "
                              "to this median error, px (flow noise, no drift)", ge=0)
    solver: Literal["schur", "gtsam"] = _f("schur", "Levenberg-Marquardt of the same cost: 'schur' (numpy, analytic "
                                                    "Jacobians, landmarks eliminated by the Schur complement; the "
                                                    "fast one) or 'gtsam' (gtsam_unstable's inverse-depth factors, "
                                                    "numerical derivatives; the reference)")
