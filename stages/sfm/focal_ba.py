"""Levenberg-Marquardt for the calibrate stage's bundle adjustment (:func:`stages.sfm.reconstruction.
adjust_focal`): poses, points and one shared focal length (optionally the principal point), with
analytic Jacobians and the points eliminated by a Schur complement (numpy, no gtsam).

The cost is the factor graph that function gave gtsam, term for term:

* observation o of point p in frame k: X_c = R_k X_p + t_k (world-to-camera), projected with
  fx = fy = f and the principal point (cx, cy); residual r = projection - (u, v) px under a Huber
  loss of scale ``robust_px`` on |r| (gtsam's Robust Huber over an isotropic 1 px sigma): cost
  |r|^2 / 2 within it, k |r| - k^2 / 2 beyond; IRLS weight min(1, k / |r|). A point at or behind
  the camera costs the constant residual (2 f, 2 f) with zero Jacobians, as gtsam's projection
  factors: a zero residual there (what the calibrate stage's first version of this solver had)
  rewarded steps that flipped part of an early reconstruction behind its cameras. Nothing is
  printed (gtsam printed a line per such factor and linearisation);
* with the principal point free: a Gaussian prior pulling it to ``centre`` (sigma px per axis) and
  a weak one on f (10 f wide), as gtsam's Cal3_S2 prior; fx = fy exactly (gtsam needed a tight
  factor for that);
* the gauge: held variables (a pose per model, and a point where the scale is not held by a range)
  are not moved at all, which is what gtsam's 1e-6 priors on them did to 1e-6. A range (the
  distance d between a held camera a and another one b, gtsam's RangeFactorPose3 at 1e-6 d) is held
  exactly: camera b does not move along the baseline to first order (its translation step is
  taken in a basis whose first axis, the one along the baseline, is held), and after each step
  the model is scaled about camera a's centre back to d (the cost does not change under that
  scaling). gtsam's stiff range made the Marquardt damping of camera b's translation ~1e12 times
  its neighbours': 130-170 LM iterations crawling along the principal-point valley where this
  takes ~10.

Poses move as T <- Exp(xi) T (xi = (omega rad, v), :func:`stages.geometry.se3.se3_exp`), points
and intrinsics additively. Damping is Marquardt's (lambda x the Hessian's diagonal, clamped): the
unknowns are in radians, metres and pixels. The Schur complement is accumulated per chunk of
points over only the frames that chunk sees (a video's tracks span a few neighbouring frames).

Arrays: R (F, 3, 3), t (F, 3) world-to-camera; X (P, 3) world points; observations sorted by
point: obs_pt (M,), obs_cam (M,) int, uv (M, 2) px.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gcvd_flow.stages.geometry.se3 import hat, se3_exp

MIN_DIAGONAL, MAX_DIAGONAL = 1e-6, 1e32  # clamp of the Marquardt damping diagonal
MIN_MODEL_FIDELITY = 1e-3  # a step is kept when it achieves this fraction of the predicted decrease
LAMBDA_FACTOR, LAMBDA_MAX, LAMBDA_MIN = 10.0, 1e5, 1e-12
CHUNK_POINTS = 256  # points per Schur chunk: a chunk's frames stay few, its GEMM stays large


@dataclass(frozen=True)
class Range:
    """|c_a - c_b| = d between the centres of frames a (held) and b, kept by scaling the model about
    c_a: its frames ``cams`` and points ``pts`` (int index arrays)."""

    a: int
    b: int
    d: float
    cams: np.ndarray
    pts: np.ndarray


@dataclass(frozen=True)
class Problem:
    """The fixed data of one adjustment (everything but the variables)."""

    obs_pt: np.ndarray  # (M,) int, nondecreasing: the observed point
    obs_cam: np.ndarray  # (M,) int: the observing frame
    uv: np.ndarray  # (M, 2) float64 px
    robust_px: float  # Huber scale, px
    fixed_cam: np.ndarray  # (F,) bool: poses held (the gauge)
    fixed_pt: np.ndarray  # (P,) bool: points held (the gauge's scale where no range holds it)
    pp_prior: tuple[np.ndarray, np.ndarray] | None  # (centre (2,), sigma (2,)) px: principal point free
    f_prior_sigma: float  # px, the weak prior on f with the principal point free (inf: none)
    ranges: tuple[Range, ...]  # |c_a - c_b| = d, a held

    @property
    def n_intr(self) -> int:
        return 1 if self.pp_prior is None else 3


@dataclass
class State:
    R: np.ndarray  # (F, 3, 3)
    t: np.ndarray  # (F, 3)
    X: np.ndarray  # (P, 3)
    intr: np.ndarray  # (3,) f, cx, cy
    f0: float = 0.0  # the f prior's mean (the starting f)


def _project(p: Problem, s: State, jacobians: bool):
    """Residuals r (M, 2) px, in front (M,) bool and, with ``jacobians``, the camera (M, 2, 6),
    point (M, 2, 3) and intrinsics (M, 2, n_intr) Jacobians (zero behind the camera)."""
    R, t = s.R[p.obs_cam], s.t[p.obs_cam]
    Xc = np.einsum("mij,mj->mi", R, s.X[p.obs_pt]) + t
    z = Xc[:, 2]
    front = z > 0
    iz = np.where(front, 1.0 / np.where(front, z, 1.0), 0.0)
    xn, yn = Xc[:, 0] * iz, Xc[:, 1] * iz
    f, cx, cy = s.intr
    r = np.stack([f * xn + cx, f * yn + cy], 1) - p.uv
    r[~front] = 2.0 * f  # the cheirality residual, constant (its Jacobians are 0)
    if not jacobians:
        return r, front
    a = f * iz
    Pj = np.zeros((len(z), 2, 3))
    Pj[:, 0, 0], Pj[:, 0, 2] = a, -a * xn
    Pj[:, 1, 1], Pj[:, 1, 2] = a, -a * yn
    Jc = np.concatenate([-Pj @ hat(Xc), Pj], axis=2)  # d Xc / d(omega, v) = [-[Xc]x, I]
    Jc[p.fixed_cam[p.obs_cam]] = 0.0
    Jp = Pj @ R
    Jp[p.fixed_pt[p.obs_pt]] = 0.0
    Jk = np.zeros((len(z), 2, p.n_intr))
    Jk[:, 0, 0], Jk[:, 1, 0] = xn, yn
    if p.n_intr == 3:
        Jk[:, 0, 1], Jk[:, 1, 2] = front, front
    return r, front, Jc, Jp, Jk


def _huber(r: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
    """Per observation: (cost, IRLS weight) of the Huber loss on |r|."""
    e = np.sqrt(np.sum(r * r, axis=1))
    inside = e <= k
    cost = np.where(inside, 0.5 * e * e, k * e - 0.5 * k * k)
    w = np.where(inside, 1.0, k / np.maximum(e, 1e-300))
    return cost, w


def _centres(s: State) -> np.ndarray:
    return -np.einsum("fji,fj->fi", s.R, s.t)  # c = -R^T t, (F, 3)


def _prior_terms(p: Problem, s: State):
    """Residuals e (n,), information (n,) and intrinsics Jacobian rows (n, n_intr) of the priors."""
    rows, info, ji = [], [], []
    if p.pp_prior is not None:
        centre, sigma = p.pp_prior
        for ax in range(2):
            rows.append(s.intr[1 + ax] - centre[ax]); info.append(1.0 / sigma[ax] ** 2)
            ji.append(np.eye(3)[1 + ax])
        if np.isfinite(p.f_prior_sigma):
            rows.append(s.intr[0] - s.f0); info.append(1.0 / p.f_prior_sigma ** 2)
            ji.append(np.eye(3)[0])
    return np.asarray(rows, np.float64), np.asarray(info, np.float64), np.asarray(ji, np.float64).reshape(-1, 3)


def total_cost(p: Problem, s: State) -> float:
    r, _ = _project(p, s, False)
    e, info, _ = _prior_terms(p, s)
    return float(_huber(r, p.robust_px)[0].sum() + 0.5 * np.sum(info * e * e))


@dataclass
class _System:
    """The IRLS Gauss-Newton system at one state: H = J^T w J, g = J^T w r, split into the
    cameras + intrinsics part (dense) and the point blocks."""

    Haa: np.ndarray  # (6F + n_intr, 6F + n_intr)
    ga: np.ndarray  # (6F + n_intr,)
    V: np.ndarray  # (P, 3, 3)
    gp: np.ndarray  # (P, 3)
    Wc: np.ndarray  # (M, 6, 3) camera-point block of each observation
    Wk: np.ndarray  # (M, n_intr, 3) intrinsics-point block
    cost: float
    bases: dict[int, np.ndarray]  # range camera b -> its translation-step basis (:func:`_range_bases`)


def _tn(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Per observation A^T B: (M, r, i), (M, r, j) -> (M, i, j) (a batched matmul: ~2.4x einsum's speed)."""
    return np.matmul(A.transpose(0, 2, 1), B)


def _sum_by(keys: np.ndarray, x: np.ndarray, n: int) -> np.ndarray:
    """x (N, ...) summed by integer key (N,) in [0, n) -> (n, ...)."""
    flat = x.reshape(len(x), -1)
    out = np.stack([np.bincount(keys, flat[:, j], n) for j in range(flat.shape[1])], 1)
    return out.reshape((n,) + x.shape[1:])


def _range_bases(p: Problem, s: State) -> dict[int, np.ndarray]:
    """Per range: camera b's translation-step basis Q (3, 3), orthonormal, first column R_b u with
    u the unit baseline c_b - c_a (a step v moves c_b by -R_b^T v, so only Q's first axis changes
    |c_b - c_a| to first order)."""
    c = _centres(s)
    out = {}
    for rg in p.ranges:
        n = s.R[rg.b] @ (c[rg.b] - c[rg.a])
        n = n / max(float(np.linalg.norm(n)), 1e-300)
        Q, _ = np.linalg.qr(np.column_stack([n, np.eye(3)]))
        out[rg.b] = Q * np.sign(Q[:, 0] @ n)  # first column +n (qr's sign is free)
    return out


def _linearize(p: Problem, s: State) -> _System:
    F, P, ni = len(s.R), len(s.X), p.n_intr
    r, front, Jc, Jp, Jk = _project(p, s, True)
    bases = _range_bases(p, s)
    for b, Q in bases.items():
        m = p.obs_cam == b
        Jc[m, :, 3:] = Jc[m, :, 3:] @ Q
        Jc[m, :, 3] = 0.0  # along the baseline: held
    cost, w = _huber(r, p.robust_px)
    w = w * front
    wJp = Jp * w[:, None, None]
    V = _sum_by(p.obs_pt, _tn(wJp, Jp), P)
    gp = _sum_by(p.obs_pt, np.einsum("mri,mr->mi", wJp, r), P)
    Wc = _tn(Jc, wJp)
    Wk = _tn(Jk, wJp)
    wJc, wJk = Jc * w[:, None, None], Jk * w[:, None, None]
    na = 6 * F + ni
    H = np.zeros((na, na))
    cc = _sum_by(p.obs_cam, _tn(wJc, Jc), F)
    ck = _sum_by(p.obs_cam, _tn(wJc, Jk), F)
    for k in range(F):
        H[6 * k:6 * k + 6, 6 * k:6 * k + 6] = cc[k]
    H[:6 * F, 6 * F:] = ck.reshape(6 * F, ni)
    H[6 * F:, :6 * F] = H[:6 * F, 6 * F:].T
    H[6 * F:, 6 * F:] = np.tensordot(wJk, Jk, axes=([0, 1], [0, 1]))
    g = np.concatenate([_sum_by(p.obs_cam, np.einsum("mri,mr->mi", wJc, r), F).ravel(),
                        np.einsum("mri,mr->i", wJk, r)])
    e, info, ji = _prior_terms(p, s)
    H[6 * F:, 6 * F:] += (ji[:, :ni].T * info) @ ji[:, :ni]
    g[6 * F:] += (ji[:, :ni].T * info) @ e
    held = np.zeros(na, bool)  # held unknowns: an identity row and no gradient (their step is 0)
    held[:6 * F] = np.repeat(p.fixed_cam, 6)
    held[[6 * b + 3 for b in bases]] = True
    H[held, :] = 0.0
    H[:, held] = 0.0
    H[held, held] = 1.0
    g[held] = 0.0
    V[p.fixed_pt] = np.eye(3)
    gp[p.fixed_pt] = 0.0
    return _System(H, g, V, gp, Wc, Wk, float(cost.sum() + 0.5 * np.sum(info * e * e)), bases)


@dataclass(frozen=True)
class _Chunk:
    obs: slice  # its observations (contiguous: sorted by point)
    pts: slice  # its points
    cams: np.ndarray  # (n,) the frames its observations see


def _chunks(p: Problem, n_points: int) -> list[_Chunk]:
    starts = np.searchsorted(p.obs_pt, np.arange(0, n_points + CHUNK_POINTS, CHUNK_POINTS).clip(max=n_points))
    out = []
    for i in range(len(starts) - 1):
        o = slice(int(starts[i]), int(starts[i + 1]))
        if o.stop > o.start:
            pts = slice(i * CHUNK_POINTS, min((i + 1) * CHUNK_POINTS, n_points))
            out.append(_Chunk(o, pts, np.unique(p.obs_cam[o])))
    return out


def _reduced(p: Problem, sys: _System, chunks: list[_Chunk], Vd: np.ndarray, gp: np.ndarray, F: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The Schur complement S = Haa - W V^-1 W^T and b = -(ga - W V^-1 gp) with the point blocks
    Vd (P, 3, 3); returns (S, b, V^-1)."""
    ni = sys.Wk.shape[1]
    Vi = np.linalg.inv(Vd)
    Lv = np.linalg.cholesky(Vi)  # V^-1 = Lv Lv^T, so W V^-1 W^T = Y Y^T with Y = W Lv
    S, b = sys.Haa.copy(), -sys.ga.copy()
    Vg = np.einsum("pij,pj->pi", Vi, gp)
    for c in chunks:
        j, k = p.obs_pt[c.obs], p.obs_cam[c.obs]
        Yc = sys.Wc[c.obs] @ Lv[j]  # (m, 6, 3)
        Yk = sys.Wk[c.obs] @ Lv[j]  # (m, ni, 3)
        col = np.searchsorted(c.cams, k)
        npt = c.pts.stop - c.pts.start
        Z = np.zeros((npt, 3, len(c.cams), 6))
        Z[j - c.pts.start, :, col, :] = Yc.transpose(0, 2, 1)
        Zk = _sum_by(j - c.pts.start, Yk.transpose(0, 2, 1), npt)  # (npt, 3, ni)
        Zf = np.concatenate([Z.reshape(3 * npt, 6 * len(c.cams)), Zk.reshape(3 * npt, ni)], axis=1)
        idx = np.concatenate([(6 * c.cams[:, None] + np.arange(6)).ravel(), 6 * F + np.arange(ni)])
        S[np.ix_(idx, idx)] -= Zf.T @ Zf
        vg = Vg[j]
        b[:6 * F] += _sum_by(k, np.einsum("mij,mj->mi", sys.Wc[c.obs], vg), F).ravel()
        b[6 * F:] += np.einsum("mij,mj->i", sys.Wk[c.obs], vg)
    return S, b, Vi


def _damped_step(p: Problem, sys: _System, chunks: list[_Chunk], lam: float, F: int):
    """Solve (H + lam D) d = -g with D = diag(H) clamped; returns (d_cams (F, 6), d_intr (n_intr,),
    d_points (P, 3), predicted decrease) or None where the system is not positive definite."""
    Da = np.clip(np.diag(sys.Haa), MIN_DIAGONAL, MAX_DIAGONAL)
    Dp = np.clip(np.diagonal(sys.V, axis1=1, axis2=2), MIN_DIAGONAL, MAX_DIAGONAL)
    Vd = sys.V.copy()
    Vd[:, [0, 1, 2], [0, 1, 2]] += lam * Dp
    try:
        S, b, Vi = _reduced(p, sys, chunks, Vd, sys.gp, F)
        S[np.diag_indices_from(S)] += lam * Da
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        return None
    da = np.linalg.solve(L.T, np.linalg.solve(L, b))
    dcam = da[:6 * F].reshape(F, 6)
    x = sys.gp + _sum_by(p.obs_pt, np.einsum("mji,mj->mi", sys.Wc, dcam[p.obs_cam])
                         + np.einsum("mji,j->mi", sys.Wk, da[6 * F:]), len(Vi))
    dp = -np.einsum("pij,pj->pi", Vi, x)
    dp[p.fixed_pt] = 0.0
    pred = 0.5 * (lam * (da @ (Da * da) + np.sum(Dp * dp * dp)) - sys.ga @ da - np.sum(sys.gp * dp))
    dcam = dcam.copy()
    for cam, Q in sys.bases.items():
        dcam[cam, 3:] = Q @ dcam[cam, 3:]
    return dcam, da[6 * F:], dp, float(pred)


def _moved(p: Problem, s: State, dcam: np.ndarray, dk: np.ndarray, dp: np.ndarray) -> State:
    """The state after a step, each range's model scaled about its camera a back to distance d."""
    T = np.zeros((len(s.R), 4, 4))
    T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = s.R, s.t, 1.0
    T = se3_exp(dcam) @ T
    T[p.fixed_cam, :3, :3], T[p.fixed_cam, :3, 3] = s.R[p.fixed_cam], s.t[p.fixed_cam]
    intr = s.intr.copy()
    intr[:len(dk)] += dk
    out = State(T[:, :3, :3].copy(), T[:, :3, 3].copy(), s.X + dp, intr, s.f0)
    c = _centres(out)
    for rg in p.ranges:
        k = rg.d / max(float(np.linalg.norm(c[rg.b] - c[rg.a])), 1e-300)
        cams = rg.cams[~p.fixed_cam[rg.cams]]  # camera a stays bit for bit
        cn = c[rg.a] + k * (c[cams] - c[rg.a])
        out.t[cams] = -np.einsum("fij,fj->fi", out.R[cams], cn)
        out.X[rg.pts] = c[rg.a] + k * (out.X[rg.pts] - c[rg.a])
    return out


@dataclass
class Result:
    state: State
    iterations: int
    cost0: float
    cost: float


def solve(p: Problem, s: State, max_iterations: int, rel_tol: float = 1e-5, abs_tol: float = 1e-5,
          lambda_initial: float = 1e-5) -> Result:
    """LM from ``s``: each iteration linearises once and tries lambda (x 10 per failure, up to
    LAMBDA_MAX; / 10 after a kept step) until a step achieves MIN_MODEL_FIDELITY of its predicted
    decrease. Stops after ``max_iterations``, when a kept step lowers the cost by less than
    ``rel_tol`` of it or by less than ``abs_tol`` (gtsam's two tolerances), or when no lambda helps."""
    F = len(s.R)
    chunks = _chunks(p, len(s.X))
    sys = _linearize(p, s)
    cost0 = cost = sys.cost
    lam, it = lambda_initial, 0
    while it < max_iterations:
        it += 1
        new = None
        while lam <= LAMBDA_MAX:
            step = _damped_step(p, sys, chunks, lam, F)
            if step is not None and step[3] > 0:
                cand = _moved(p, s, *step[:3])
                c = total_cost(p, cand)
                if np.isfinite(c) and cost - c > MIN_MODEL_FIDELITY * step[3]:
                    new = cand, c
                    break
            lam *= LAMBDA_FACTOR
        if new is None:
            break
        lam = max(lam / LAMBDA_FACTOR, LAMBDA_MIN)
        decrease = cost - new[1]
        s, cost = new
        if decrease < rel_tol * abs(cost + decrease) or decrease < abs_tol:
            break
        sys = _linearize(p, s)
    return Result(s, it, cost0, cost)


def intrinsics_cov(p: Problem, s: State, point_sigma: float) -> np.ndarray | None:
    """Marginal covariance of the intrinsics (n_intr, n_intr) (unit: px^2 for 1 px of observation
    noise) from the undamped IRLS Gauss-Newton information at ``s``, each point given a weak prior
    of ``point_sigma`` (a point seen from nearly one place would leave the system singular); the
    held variables are held exactly. None where it is not positive definite."""
    sys = _linearize(p, s)
    V = sys.V.copy()
    V[:, [0, 1, 2], [0, 1, 2]] += np.where(p.fixed_pt, 0.0, 1.0 / point_sigma ** 2)[:, None]
    try:
        S, _, _ = _reduced(p, sys, _chunks(p, len(s.X)), V, sys.gp, len(s.R))
        cov = np.linalg.inv(S)[6 * len(s.R):, 6 * len(s.R):]
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) <= 0):
        return None
    return cov
