"""Levenberg-Marquardt for the bundle adjustment of :mod:`stages.optimize.bundle_adjustment`, with
analytic Jacobians and a Schur complement on the landmarks (numpy, no gtsam).

The problem is the factor graph that module gives gtsam, term for term, so both solvers minimise
the same cost and :func:`total_cost` equals gtsam's ``graph.error``:

* landmark l: inverse depth (theta, phi, rho) in the camera frame of its anchor keyframe a(l),
  the point X_a = (cos(phi) sin(theta), sin(phi), cos(phi) cos(theta)) / rho (gtsam_unstable's
  InvDepthFactorVariant3);
* observation (l, k, u, v): X_a moved to the world by T_w_a, into camera k by inv(T_w_k),
  projected with the pinhole K (Cal3_S2, skew 0); residual = projection - (u, v) px. The anchor's
  own observation (k = a, InvDepthFactorVariant3a) depends on (theta, phi) only. A point at or
  behind camera k (depth <= 0) gets gtsam's cheirality residual (2 fx, 2 fx) and no gradient;
* each residual under a Cauchy loss of scale k px (gtsam's noiseModel.mEstimator.Cauchy over an
  isotropic sigma of 1 px): cost 0.5 k^2 log(1 + |r|^2 / k^2), IRLS weight 1 / (1 + |r|^2 / k^2);
* a prior per pose (PriorFactorPose3): residual Logmap(inv(T_w_k_prior) T_w_k) in the twist
  order (rotation rad, translation m; ``stages.geometry.se3``), cost 0.5 sum(info * residual^2).

Poses are updated as gtsam's Pose3.retract does: T <- T Exp(xi), xi = (omega, v) (the SE(3)
exponential of ``stages.geometry.se3``; checked against gtsam in tests/test_bundle_adjustment.py);
landmarks additively.

Why a custom solver: gtsam_unstable's inverse-depth factors differentiate numerically and gtsam
eliminates the ~20k landmarks through its general multifrontal machinery; here one linearisation
is a few vectorised numpy passes over the observations, each landmark's 3x3 block is eliminated in
batch, and the reduced camera system (6K x 6K, K keyframes ~ 100) is dense and solved by Cholesky.

Arrays: poses (K, 4, 4) float64 camera-to-world, OpenCV axes; landmarks (L, 3) float64
(theta rad, phi rad, rho 1/m); observations (M,) int landmark / keyframe indices and (M, 2) px.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, NamedTuple, overload

import numpy as np
import scipy.linalg

from gcvd_flow.stages.geometry.se3 import se3_dlog, se3_exp, se3_log

MIN_DIAGONAL, MAX_DIAGONAL = 1e-6, 1e32  # clamp of the Marquardt damping diagonal (gtsam's defaults)
MIN_MODEL_FIDELITY = 1e-3  # a step is kept when it achieves this fraction of the predicted decrease
LAMBDA_FACTOR, LAMBDA_MAX = 10.0, 1e5  # as gtsam's LevenbergMarquardtParams
LAMBDA_MIN = 1e-12  # relative to diag(H): Gauss-Newton to double precision


@dataclass(frozen=True)
class Problem:
    """The fixed data of a bundle adjustment (everything but the variables)."""

    K: np.ndarray  # (3, 3) pinhole intrinsics fx, fy, cx, cy (skew ignored, as Cal3_S2(fx, fy, 0, cx, cy))
    anchor: np.ndarray  # (L,) int: keyframe whose camera frame holds landmark l's (theta, phi, rho)
    obs_lm: np.ndarray  # (M,) int: landmark of each observation
    obs_cam: np.ndarray  # (M,) int: keyframe that observes it (= anchor[obs_lm] for the anchor observation)
    uv: np.ndarray  # (M, 2) float64: measured pixel
    robust_px: float  # Cauchy scale k, px
    prior_poses: np.ndarray  # (K, 4, 4) float64 T_w_k the pose priors pull towards
    prior_info: np.ndarray  # (K, 6) float64 information 1 / sigma^2 of each prior (rot rad^-2, trans m^-2)


class SolveResult(NamedTuple):
    poses: np.ndarray  # (K, 4, 4) float64
    landmarks: np.ndarray  # (L, 3) float64
    iterations: int  # linearisations (gtsam's LevenbergMarquardtOptimizer.iterations())
    initial_cost: float
    final_cost: float


# ------------------------------------------------------------------------------------ the residuals
# Per-observation quantities are component-major, (..., M): each operation is one contiguous
# elementwise pass. Passes run over chunks of CHUNK_OBS observations: their temporaries (64 KB a
# row) stay in cache and are recycled by the allocator, while whole-array temporaries (1.2 MB a row
# for 150k observations) are fresh mmapped pages every time: 5-8x slower per element.
CHUNK_OBS = 8192


class Linearization(NamedTuple):
    r: np.ndarray  # (2, M) px residual (projection - measurement)
    A: np.ndarray  # (2, 6, M) d r / d (omega, v) of the anchor pose (right perturbation)
    B: np.ndarray  # (2, 6, M) d r / d (omega, v) of the observing pose
    C: np.ndarray  # (2, 3, M) d r / d (theta, phi, rho)


def _pair_table(poses: np.ndarray) -> np.ndarray:
    """(12, K * K): for observer k and anchor a, column k K + a holds Q = R_k^T R_a (rows 0-8,
    row-major; anchor camera -> camera k) and d = R_k^T (t_a - t_k) (rows 9-11, m). K^2 pairs are
    few next to the observations for keyframe counts in the hundreds."""
    R, t = poses[:, :3, :3], poses[:, :3, 3]
    n = len(poses)
    Q = np.tensordot(R, R, axes=([1], [1]))  # (k, i, a, l): one GEMM
    d = np.tensordot(R, t, axes=([1], [1])) - np.einsum("kji,kj->ki", R, t)[:, :, None]  # (k, i, a)
    return np.concatenate([Q.transpose(1, 3, 0, 2).reshape(9, n * n), d.transpose(1, 0, 2).reshape(3, n * n)])


def _landmark_table(landmarks: np.ndarray) -> np.ndarray:
    """(7, L): unit ray m = (cos phi sin theta, sin phi, cos phi cos theta) in the anchor camera,
    rho (1/m) and d m / d phi = (-sin phi sin theta, cos phi, -sin phi cos theta)."""
    th, ph, rho = np.ascontiguousarray(landmarks.T)
    st, ct, sp, cp = np.sin(th), np.cos(th), np.sin(ph), np.cos(ph)
    return np.stack([cp * st, sp, cp * ct, rho, -sp * st, cp, -sp * ct])


def _observations(problem: Problem, pairs: np.ndarray, lms: np.ndarray, sl: slice, jacobians: bool
                  ) -> tuple[np.ndarray, ...]:
    """Residuals r (2, N) of observations ``sl`` and where the point is in front of the camera
    (valid (N,)); with ``jacobians`` also A (2, 6, N), B (2, 6, N), C (2, 3, N) as in
    :class:`Linearization` but unmasked (nonzero where not valid and, for the anchor's own
    observation, A = -B: its pose cancels). From :func:`_pair_table` and :func:`_landmark_table`.

    Computed on h = rho X_k = R_k^T (R_a m + rho (t_a - t_k)): h projects to the same pixel as X_k
    (projection is scale-invariant) but stays finite as rho -> 0 (far points). The point is in
    front of camera k when X_k's depth h_z / rho > 0, otherwise the residual is gtsam's cheirality
    error (2 fx, 2 fx)."""
    fx, fy, cx, cy = problem.K[0, 0], problem.K[1, 1], problem.K[0, 2], problem.K[1, 2]
    j, k = problem.obs_lm[sl], problem.obs_cam[sl]
    a, n = problem.anchor[j], int(round(np.sqrt(pairs.shape[1])))
    # np.take keeps the gathered rows contiguous (x[:, idx] would interleave them: ~4x slower passes)
    Q0, Q1, Q2, Q3, Q4, Q5, Q6, Q7, Q8, d0, d1, d2 = np.take(pairs, k * n + a, axis=1)
    m0, m1, m2, rho, e0, e1, e2 = np.take(lms, j, axis=1)
    h0 = Q0 * m0 + Q1 * m1 + Q2 * m2 + rho * d0
    h1 = Q3 * m0 + Q4 * m1 + Q5 * m2 + rho * d1
    h2 = Q6 * m0 + Q7 * m1 + Q8 * m2 + rho * d2
    valid = h2 * rho > 0
    iz = 1.0 / np.where(valid, h2, 1.0)
    xn, yn = h0 * iz, h1 * iz
    r = np.stack([fx * xn + cx - problem.uv[sl, 0], fy * yn + cy - problem.uv[sl, 1]])
    r[:, ~valid] = 2.0 * fx  # gtsam's CheiralityException residual
    if not jacobians:
        return r, valid
    ax, ay = fx * iz, fy * iz  # d pixel / d h = [[ax, 0, -ax xn], [0, ay, -ay yn]]
    F = [[ax * (Q0 - xn * Q6), ax * (Q1 - xn * Q7), ax * (Q2 - xn * Q8)],  # (d pixel / d h) Q
         [ay * (Q3 - yn * Q6), ay * (Q4 - yn * Q7), ay * (Q5 - yn * Q8)]]
    A, B, C = np.empty((2, 6, len(j))), np.empty((2, 6, len(j))), np.empty((2, 3, len(j)))
    for i, ((f0, f1, f2), a_i, xy) in enumerate(zip(F, (ax, ay), (xn, yn))):
        # anchor pose: R_a <- R_a Exp(w): h += -Q [m]x w, row i gets m x F_i; t_a <- t_a + R_a v: h += rho Q v
        A[i, 0], A[i, 1], A[i, 2] = m1 * f2 - m2 * f1, m2 * f0 - m0 * f2, m0 * f1 - m1 * f0
        A[i, 3], A[i, 4], A[i, 5] = rho * f0, rho * f1, rho * f2
        # landmark: d m / d theta = (m2, 0, -m0), d m / d phi = e, d h / d rho = d
        C[i, 0], C[i, 1], C[i, 2] = f0 * m2 - f2 * m0, f0 * e0 + f1 * e1 + f2 * e2, a_i * ((d0, d1)[i] - xy * d2)
    # observing pose: h <- Exp(-w) (h - rho v) ~ h + [h]x w - rho v; row i gets P_i x h, h = h_z (xn, yn, 1)
    B[0, 0], B[0, 1], B[0, 2] = fx * xn * yn, -fx * (1 + xn * xn), fx * yn
    B[0, 3], B[0, 4], B[0, 5] = -rho * ax, 0.0, rho * ax * xn
    B[1, 0], B[1, 1], B[1, 2] = fy * (1 + yn * yn), -fy * xn * yn, -fy * xn
    B[1, 3], B[1, 4], B[1, 5] = 0.0, -rho * ay, rho * ay * yn
    return r, valid, A, B, C


def _ranges(n: int) -> list[slice]:
    """[0, n) in CHUNK_OBS pieces."""
    return [slice(i, min(i + CHUNK_OBS, n)) for i in range(0, n, CHUNK_OBS)]


@overload
def reprojection(problem: Problem, poses: np.ndarray, landmarks: np.ndarray, jacobians: Literal[False] = False
                 ) -> np.ndarray: ...
@overload
def reprojection(problem: Problem, poses: np.ndarray, landmarks: np.ndarray, jacobians: Literal[True]
                 ) -> Linearization: ...
@overload
def reprojection(problem: Problem, poses: np.ndarray, landmarks: np.ndarray, jacobians: bool = False
                 ) -> Linearization | np.ndarray: ...
def reprojection(problem: Problem, poses: np.ndarray, landmarks: np.ndarray, jacobians: bool = False
                 ) -> Linearization | np.ndarray:
    """Residuals (2, M) px of all observations; with ``jacobians`` a :class:`Linearization` (see
    :func:`_observations` for the model). Derivatives are zero where the point is behind the
    camera (gtsam's constant cheirality residual) and the pose derivatives of the anchor's own
    observation are exactly zero (its pose cancels), set so rather than left to rounding."""
    pairs, lms = _pair_table(poses), _landmark_table(landmarks)
    parts = [_observations(problem, pairs, lms, sl, jacobians) for sl in _ranges(len(problem.obs_lm))]
    if not parts:
        return Linearization(*(np.zeros(s + (0,)) for s in ((2,), (2, 6), (2, 6), (2, 3)))) if jacobians \
            else np.zeros((2, 0))
    if not jacobians:
        return np.concatenate([r for r, _ in parts], 1)
    r, valid, A, B, C = (np.concatenate(x, -1) for x in zip(*parts))
    keep = valid & (problem.obs_cam != problem.anchor[problem.obs_lm])
    return Linearization(r, A * keep, B * keep, C * valid)


def cauchy_cost(r: np.ndarray, k: float) -> np.ndarray:
    """(2, M) residuals -> (M,) gtsam's Cauchy loss 0.5 k^2 log(1 + |r|^2 / k^2)."""
    return 0.5 * k * k * np.log1p((r[0] ** 2 + r[1] ** 2) / (k * k))


def prior_terms(problem: Problem, poses: np.ndarray, jacobians: bool = False
                ) -> tuple[np.ndarray, np.ndarray | None]:
    """Residuals (K, 6) Logmap(inv(T_w_k_prior) T_w_k) and, with ``jacobians``, their derivatives (K, 6, 6)
    by the right perturbation of T_k (the inverse right Jacobian of SE(3) at the residual)."""
    e = se3_log(np.linalg.inv(problem.prior_poses) @ poses)
    return e, (se3_dlog(e) if jacobians else None)


def total_cost(problem: Problem, poses: np.ndarray, landmarks: np.ndarray) -> float:
    """gtsam's graph.error for this problem: robust reprojection terms plus pose priors."""
    pairs, lms = _pair_table(poses), _landmark_table(landmarks)
    e, _ = prior_terms(problem, poses)
    return float(sum(cauchy_cost(_observations(problem, pairs, lms, sl, False)[0], problem.robust_px).sum()
                     for sl in _ranges(len(problem.obs_lm))) + 0.5 * np.sum(problem.prior_info * e * e))


# ------------------------------------------------------------------------------- the linear system
class _Group(NamedTuple):
    """The landmarks anchored in one keyframe, contiguous after sorting: their observations touch
    only a few poses (the anchor and the keyframes the tracks reach, ~10), so their share of the
    reduced camera system is one small dense GEMM."""

    lms: slice  # landmark range
    obs: slice  # observation range
    lm_local: np.ndarray  # (N,) landmark of each observation, relative to lms.start
    obs_col: np.ndarray  # (N,) position of each observation's pose (its keyframe) in the group's poses
    cols: np.ndarray  # (6U,) rows / columns of the group's U poses in the reduced camera system


class _Chunk(NamedTuple):
    """Consecutive groups with about CHUNK_OBS observations: one vectorised pass."""

    lms: slice
    obs: slice
    groups: list[_Group]


class _Layout(NamedTuple):
    """Index arrays of a problem sorted by :func:`_sorted_problem`, fixed over the iterations."""

    own: np.ndarray  # (L,) the anchor's own observation of each landmark
    other: np.ndarray  # (M,) 1.0 where the observer is not the anchor, 0.0 for the anchor's own observation
    pair_obs: np.ndarray  # (P, 2) observation range [o0, o1) of each (anchor, observer) pair, anchor != observer
    pair_a: np.ndarray  # (P,) their anchor
    pair_k: np.ndarray  # (P,) their observer
    chunks: list[_Chunk]


def _sorted_problem(problem: Problem) -> tuple[Problem, np.ndarray, _Layout]:
    """The problem with landmarks ordered by anchor and observations by (anchor, observer,
    landmark) (stable, so deterministic): each anchor's landmarks and observations are contiguous,
    and each (anchor, observer) pair's observations. Returns it, the landmark order and the layout.
    Every landmark must have exactly one observation by its anchor and at most one by any other
    keyframe (as tracks do)."""
    order = np.argsort(problem.anchor, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    obs_a = problem.anchor[problem.obs_lm]
    obs_order = np.lexsort((rank[problem.obs_lm], problem.obs_cam, obs_a))
    p = Problem(problem.K, problem.anchor[order], rank[problem.obs_lm][obs_order], problem.obs_cam[obs_order],
                problem.uv[obs_order], problem.robust_px, problem.prior_poses, problem.prior_info)
    n_l, n_k = len(order), len(p.prior_poses)
    a, k = p.anchor[p.obs_lm], p.obs_cam
    own = k == a
    if (np.bincount(p.obs_lm[own], minlength=n_l) != 1).any():
        raise ValueError("every landmark needs exactly one observation by its anchor keyframe")
    if len(np.unique(p.obs_lm * n_k + k)) != len(k):
        raise ValueError("a keyframe observes a landmark at most once")
    own_obs = np.empty(n_l, np.int64)
    own_obs[p.obs_lm[own]] = np.flatnonzero(own)
    pair = a * n_k + k
    starts = np.flatnonzero(np.r_[True, pair[1:] != pair[:-1]])
    bounds = np.r_[starts, len(pair)]
    other = a[starts] != k[starts]  # the (a, a) pairs: anchors' own observations, no pose Jacobian
    chunks, groups = [], []
    for m in np.unique(p.anchor):
        l0, l1 = np.searchsorted(p.anchor, [m, m + 1])
        o0, o1 = np.searchsorted(a, [m, m + 1])
        cams = np.unique(k[o0:o1])
        groups.append(_Group(slice(l0, l1), slice(o0, o1), p.obs_lm[o0:o1] - l0, np.searchsorted(cams, k[o0:o1]),
                             (cams[:, None] * 6 + np.arange(6)).ravel()))
        if o1 - groups[0].obs.start >= CHUNK_OBS or m == p.anchor[-1]:
            chunks.append(_Chunk(slice(groups[0].lms.start, l1), slice(groups[0].obs.start, o1), groups))
            groups = []
    pair_obs = np.stack([bounds[:-1][other], bounds[1:][other]], 1)
    return p, order, _Layout(own_obs, (~own).astype(np.float64), pair_obs, a[starts][other], k[starts][other], chunks)


def _sum_by(keys: np.ndarray, x: np.ndarray, n: int) -> np.ndarray:
    """x (..., N) summed by integer key (N,) in [0, n) -> (..., n); one bincount per row (the
    fastest numpy reduction over unsorted keys)."""
    flat = x.reshape(-1, x.shape[-1])
    return np.stack([np.bincount(keys, row, n) for row in flat]).reshape(x.shape[:-1] + (n,))


_SYM3 = ([0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2])  # the 6 entries of a symmetric 3 x 3: 00 01 02 11 12 22
_TRIL3 = ([0, 1, 1, 2, 2, 2], [0, 0, 1, 0, 1, 2])  # the 6 entries of a lower-triangular 3 x 3: 00 10 11 20 21 22


class _System(NamedTuple):
    """Gauss-Newton system of the IRLS-weighted problem at one point (undamped)."""

    Hpp: np.ndarray  # (6K, 6K) pose block
    gp: np.ndarray  # (6K,) pose gradient
    Hll: np.ndarray  # (6, L) landmark blocks, entries _SYM3
    gl: np.ndarray  # (3, L) landmark gradient
    W: np.ndarray  # (6, 3, M) pose-landmark block of each observation's keyframe and landmark
    cost: float
    sJ: np.ndarray  # (13, M, 2) scratch of the pose Jacobians, kept for reuse


def _linearize(p: Problem, layout: _Layout, poses: np.ndarray, landmarks: np.ndarray,
               reuse: _System | None = None) -> _System:
    """H = J^T w J and g = J^T w r with w the Cauchy IRLS weight (what gtsam's Robust noise model
    does when it whitens a factor: scale Jacobian and residual by sqrt(w)); g is the robust cost's
    gradient. A point behind its camera has weight 0 (constant residual). Landmark blocks: per
    chunk, summed by landmark. W: the anchor's block of landmark l (from all its observations)
    sits at the anchor's own observation, the observer's block at each other observation. Pose
    blocks: one GEMM per (anchor, observer) pair over sqrt(w) [A B r], whose two residual rows are
    stored adjacent so that a pair's observations are one contiguous (13, 2 n) matrix. ``reuse``:
    a system no longer needed whose large arrays are overwritten (fresh ones would cost page
    faults on every linearisation)."""
    n, n_l, M, k2 = len(poses), len(landmarks), len(p.obs_lm), p.robust_px**2
    pairs, lms = _pair_table(poses), _landmark_table(landmarks)
    if reuse is None:
        sJ, W, Hll, gl = np.empty((13, M, 2)), np.empty((6, 3, M)), np.empty((6, n_l)), np.empty((3, n_l))
    else:
        sJ, W, Hll, gl = reuse.sJ, reuse.W, reuse.Hll, reuse.gl
    cost = 0.0
    for c in layout.chunks:
        r, valid, A, B, C = _observations(p, pairs, lms, c.obs, True)
        e2 = r[0] ** 2 + r[1] ** 2
        cost += 0.5 * k2 * np.log1p(e2 / k2).sum()
        w = valid / (1.0 + e2 / k2)
        s = np.sqrt(w)
        for i in range(2):  # written in place: a temporary and a strided copy cost ~10x more
            np.multiply(A[i], s, out=sJ[:6, c.obs, i])
            np.multiply(B[i], s, out=sJ[6:12, c.obs, i])
            np.multiply(r[i], s, out=sJ[12, c.obs, i])
        j, nl, wC = p.obs_lm[c.obs] - c.lms.start, c.lms.stop - c.lms.start, w * C
        Hll[:, c.lms] = _sum_by(j, np.einsum("icn,idn->cdn", wC, C)[_SYM3], nl)
        gl[:, c.lms] = _sum_by(j, np.einsum("icn,in->cn", wC, r), nl)
        W[..., c.obs] = np.einsum("ipn,icn->pcn", B, wC)
        # the anchor's own observation does not depend on the anchor pose (A = -B there, not 0)
        W[..., layout.own[c.lms]] = _sum_by(j, np.einsum("ipn,icn->pcn", A, wC * layout.other[c.obs]), nl)
    G = np.empty((len(layout.pair_obs), 13, 13))
    for i, (o0, o1) in enumerate(layout.pair_obs):
        X = sJ[:, o0:o1].reshape(13, -1)
        G[i] = X @ X.T
    H, g = np.zeros((n, n, 6, 6)), np.zeros((n, 6))
    pa, pk = layout.pair_a, layout.pair_k
    np.add.at(H, (pa, pa), G[:, :6, :6])
    np.add.at(H, (pk, pk), G[:, 6:12, 6:12])
    H[pa, pk] += G[:, :6, 6:12]  # each (anchor, observer) pair once
    H[pk, pa] += G[:, 6:12, :6]
    np.add.at(g, pa, G[:, :6, 12])
    np.add.at(g, pk, G[:, 6:12, 12])
    e, J = prior_terms(p, poses, jacobians=True)
    assert J is not None  # jacobians=True
    JtI = J.transpose(0, 2, 1) * p.prior_info[:, None, :]
    H[np.arange(n), np.arange(n)] += JtI @ J
    g += np.einsum("kij,kj->ki", JtI, e)
    cost += 0.5 * np.sum(p.prior_info * e * e)
    return _System(H.transpose(0, 2, 1, 3).reshape(6 * n, 6 * n), g.ravel(), Hll, gl, W, float(cost), sJ)


def _inverse_cholesky(H: np.ndarray) -> np.ndarray | None:
    """(6, L) symmetric 3 x 3 blocks (entries _SYM3) -> (6, L) entries 00 10 11 20 21 22 of
    L^-1 with H = L L^T, in closed form over all blocks at once (batched LAPACK calls on 3 x 3
    matrices cost ~10x more); None if a block is not positive definite."""
    a00, a01, a02, a11, a12, a22 = H
    with np.errstate(invalid="ignore", divide="ignore"):
        l00 = np.sqrt(a00)
        l10, l20 = a01 / l00, a02 / l00
        l11 = np.sqrt(a11 - l10 * l10)
        l21 = (a12 - l20 * l10) / l11
        l22 = np.sqrt(a22 - l20 * l20 - l21 * l21)
    if not (np.all(l00 > 0) and np.all(l11 > 0) and np.all(l22 > 0)):  # also catches NaN
        return None
    i00, i11, i22 = 1 / l00, 1 / l11, 1 / l22
    i10 = -l10 * i00 * i11
    return np.stack([i00, i10, i11, -(l20 * i00 + l21 * i10) * i22, -l21 * i11 * i22, i22])


def _damped_step(p: Problem, layout: _Layout, sys: _System, lam: float
                 ) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Solve (H + lam D) [dp; dl] = -g, D = diag(H) clamped (Marquardt: scale-free over radians,
    metres and 1/m), by eliminating the landmarks: with Hll = L L^T per landmark and Y = W L^-T,
    S = Hpp - Y Y^T, b = -gp + Y L^-1 gl; dl = -L^-T (L^-1 gl + Y^T dp). Returns (dp (K, 6),
    dl (L, 3), predicted cost decrease of the quadratic model) or None if not positive definite."""
    Dp = np.clip(np.diag(sys.Hpp), MIN_DIAGONAL, MAX_DIAGONAL)
    Dl = np.clip(sys.Hll[[0, 3, 5]], MIN_DIAGONAL, MAX_DIAGONAL)
    n = len(p.prior_poses)
    Hd = sys.Hll.copy()
    Hd[[0, 3, 5]] += lam * Dl
    Li = _inverse_cholesky(Hd)
    if Li is None:
        return None
    i00, i10, i11, i20, i21, i22 = Li
    g0, g1, g2 = sys.gl
    glp = np.stack([i00 * g0, i10 * g0 + i11 * g1, i20 * g0 + i21 * g1 + i22 * g2])  # L^-1 gl
    S = sys.Hpp + lam * np.diag(Dp)
    b = -sys.gp.reshape(n, 6)
    Ys = []
    for c in layout.chunks:
        j, k = p.obs_lm[c.obs], p.obs_cam[c.obs]
        Lo = np.zeros((3, 3, len(j)))
        Lo[_TRIL3] = np.take(Li, j, axis=1)
        Y = np.einsum("pen,cen->pcn", sys.W[..., c.obs], Lo)  # (6, 3, N) W L^-T
        b += _sum_by(k, np.einsum("pcn,cn->pn", Y, np.take(glp, j, axis=1)), n).T
        rows = Y.reshape(18, -1).T  # (N, 18): each observation's 6 x 3 block
        for g in c.groups:  # Y Y^T: all pairs of observations of one landmark, one GEMM per anchor
            U, nl = len(g.cols) // 6, g.lms.stop - g.lms.start
            Yd = np.zeros((nl * U, 18))  # block (landmark, pose), zero where the pose does not see it
            Yd[g.lm_local * U + g.obs_col] = rows[g.obs.start - c.obs.start:g.obs.stop - c.obs.start]
            Z = Yd.reshape(nl, U, 6, 3).transpose(0, 3, 1, 2).reshape(3 * nl, 6 * U)
            S[np.ix_(g.cols, g.cols)] -= Z.T @ Z
        Ys.append(Y)
    # factorised with numpy's LAPACK, as the GEMMs above use numpy's BLAS: scipy bundles a second
    # OpenBLAS whose thread pool would compete with numpy's (measured 10x slower factorisations)
    try:
        Lc = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        return None
    dp = scipy.linalg.solve_triangular(Lc, scipy.linalg.solve_triangular(Lc, b.ravel(), lower=True), lower=True,
                                       trans="T")
    dpr = np.ascontiguousarray(dp.reshape(n, 6).T)
    x = glp
    for c, Y in zip(layout.chunks, Ys):
        Ytd = np.einsum("pcn,pn->cn", Y, np.take(dpr, p.obs_cam[c.obs], axis=1))
        x[:, c.lms] += _sum_by(p.obs_lm[c.obs] - c.lms.start, Ytd, c.lms.stop - c.lms.start)
    dl = -np.stack([i00 * x[0] + i10 * x[1] + i20 * x[2], i11 * x[1] + i21 * x[2], i22 * x[2]]).T  # -L^-T x
    # model decrease -(g.d + d.H.d / 2) = (lam d.D.d - g.d) / 2 since (H + lam D) d = -g
    pred = 0.5 * (lam * (dp @ (Dp * dp) + np.sum(Dl * dl.T * dl.T)) - sys.gp @ dp - np.sum(sys.gl * dl.T))
    return dp.reshape(n, 6), dl, float(pred)


def solve(problem: Problem, poses: np.ndarray, landmarks: np.ndarray, max_iterations: int = 100,
          relative_tol: float = 1e-5, lambda_initial: float = 1e-5) -> SolveResult:
    """Levenberg-Marquardt from poses (K, 4, 4) and landmarks (L, 3). Each iteration linearises
    once and tries lambda until a step achieves MIN_MODEL_FIDELITY of its predicted decrease
    (lambda / 10 after it, x 10 per failure, up to LAMBDA_MAX, as gtsam). Stops after
    ``max_iterations`` linearisations, when a kept step lowers the cost by less than
    ``relative_tol`` of it, or when no lambda helps (a minimum to numerical precision).

    A candidate is linearised at once rather than first costed: steps are nearly always kept,
    and the linearisation computes the cost anyway (only the last iteration's is costed alone)."""
    p, order, layout = _sorted_problem(problem)
    x_p, x_l = np.asarray(poses, np.float64).copy(), np.asarray(landmarks, np.float64)[order].copy()
    sys = _linearize(p, layout, x_p, x_l)
    cost0 = cost = sys.cost
    lam, it, spare = lambda_initial, 0, None
    while it < max_iterations:
        it += 1
        new = None
        while lam <= LAMBDA_MAX:
            step = _damped_step(p, layout, sys, lam)
            if step is not None and step[2] > 0:
                cand_p, cand_l = x_p @ se3_exp(step[0]), x_l + step[1]
                if it == max_iterations:
                    cand, c = None, total_cost(p, cand_p, cand_l)
                else:
                    cand = _linearize(p, layout, cand_p, cand_l, reuse=spare)
                    c, spare = cand.cost, cand  # if rejected, its arrays are free again
                if np.isfinite(c) and cost - c > MIN_MODEL_FIDELITY * step[2]:
                    new = cand_p, cand_l, c, cand
                    break
            lam *= LAMBDA_FACTOR
        if new is None:
            break
        lam = max(lam / LAMBDA_FACTOR, LAMBDA_MIN)
        decrease = cost - new[2]
        x_p, x_l, cost = new[:3]
        if new[3] is None or decrease < relative_tol * abs(cost + decrease):
            break
        spare, sys = sys, new[3]
    out_l = np.empty_like(x_l)
    out_l[order] = x_l
    return SolveResult(x_p, out_l, it, cost0, cost)
