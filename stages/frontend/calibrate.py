"""Focal self-calibration: one focal length (fx = fy) from the video itself.

When no intrinsics are given the ingest guess f = 300/384 x long side is typically 5-35 % off
on real cameras, and poses and depth fall apart with it. This module estimates the focal
length from the frames (principal point fixed, usually at the image centre):

1. Frames are sampled evenly over the clip (at most ``max_frames``); SIFT features once per
   frame; ratio-test matches between each frame and the next 1, 2, 4, 8 sampled frames.
2. Per pair a RANSAC fundamental matrix F (inliers) and a homography H on those inliers. A pair
   whose F inliers a homography explains almost all of (tiny parallax: the camera mainly
   rotated) is a *rotation* pair — for it H = K R K^-1 (pure rotation determines f, the
   epipolar constraint does not: any rotation-only flow fits some essential matrix of any f);
   the other pairs are *general* pairs: F = K^-T [t]x R K^-1.
3. Initial value: a 1-D search over f on a log grid, each pair scoring how far its matrix is
   from a valid one at that f (general: the two non-zero singular values of K^T F K must be
   equal; rotation: K^-1 H K must be a scaled rotation); the median over pairs is minimised.
4. Refinement: a small bundle adjustment over all pairs' inlier matches with one shared focal
   length and each pair's relative pose (general: rotation + translation direction, residual
   the Sampson distance in px; rotation: rotation only, residual the transfer error in px),
   robust (Cauchy) loss; scipy's sparse trust-region least squares.
5. Uncertainty: the focal length's marginal standard deviation from the Gauss-Newton normal
   equations (pair poses eliminated by the Schur complement), scaled by the robust residual
   spread. When it exceeds ``max_rel_sigma`` (forward-only or near-static motion, too few
   pairs), the motion does not determine the focal length: the result says so and the caller
   keeps the guess.

Pure: arrays in, a dict out; deterministic (OpenCV's RANSAC seeded, SIFT and scipy are).
Units: pixels at the frames' (working) resolution.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Sequence

import cv2
import numpy as np

log = logging.getLogger(__name__)

RANSAC_SEED = 1234
SIFT_RATIO = 0.8
PAIR_OFFSETS = (1, 2, 4, 8)  # partners of a sampled frame, in sampled-frame steps


@dataclass
class PairGeometry:
    """One frame pair's inlier matches (x1, x2 (M, 2) px) and its model: kind "general" (F) or
    "rotation" (H: x2 ~ H x1)."""

    a: int
    b: int
    x1: np.ndarray
    x2: np.ndarray
    kind: str
    F: np.ndarray
    H: np.ndarray


# ------------------------------------------------------------------------------ matches


def _features(img: np.ndarray, n_features: int) -> tuple[np.ndarray, np.ndarray | None]:
    gray = img if img.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(img, np.uint8), cv2.COLOR_RGB2GRAY)
    sift = cv2.SIFT_create(nfeatures=n_features, contrastThreshold=0.02)
    kp, des = sift.detectAndCompute(gray, None)
    return np.asarray([k.pt for k in kp], np.float64).reshape(-1, 2), des


def _match(fa, fb) -> tuple[np.ndarray, np.ndarray]:
    (pa, da), (pb, db) = fa, fb
    if da is None or db is None or len(pa) < 8 or len(pb) < 8:
        return np.zeros((0, 2)), np.zeros((0, 2))
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    good = [(m[0].queryIdx, m[0].trainIdx) for m in knn if len(m) == 2 and m[0].distance < SIFT_RATIO * m[1].distance]
    # one match per keypoint of b (the closest): duplicates bias the fit
    best: dict[int, tuple[int, int]] = {}
    for q, t in good:
        if t not in best:
            best[t] = (q, t)
    ia = np.asarray([q for q, _ in best.values()], np.int64)
    ib = np.asarray([t for _, t in best.values()], np.int64)
    return pa[ia].reshape(-1, 2), pb[ib].reshape(-1, 2)


def pair_geometry(a: int, b: int, x1: np.ndarray, x2: np.ndarray, *, ransac_px: float = 1.0,
                  min_inliers: int = 30, rotation_share: float = 0.9,
                  min_motion_px: float = 1.0, max_matches: int = 200) -> PairGeometry | None:
    """Matches of a frame pair -> its F inliers and model kind, or None (too few inliers, or
    the images hardly moved: median displacement < ``min_motion_px``)."""
    if len(x1) < min_inliers:
        return None
    cv2.setRNGSeed(RANSAC_SEED)
    F, inl = cv2.findFundamentalMat(x1, x2, cv2.FM_RANSAC, ransac_px, 0.999, 5000)
    if F is None or inl is None or F.shape != (3, 3):
        return None
    keep = inl.ravel().astype(bool)
    if keep.sum() < min_inliers:
        return None
    x1, x2 = x1[keep], x2[keep]
    if len(x1) > max_matches:  # an even subset (matches come in keypoint order: scale, position)
        sub = np.linspace(0, len(x1) - 1, max_matches).round().astype(int)
        x1, x2 = x1[sub], x2[sub]
    if np.median(np.linalg.norm(x2 - x1, axis=1)) < min_motion_px:
        return None
    cv2.setRNGSeed(RANSAC_SEED)
    H, hin = cv2.findHomography(x1, x2, cv2.RANSAC, ransac_px, maxIters=5000, confidence=0.999)
    kind = "general"
    if H is not None and hin is not None and np.all(np.isfinite(H)):
        err = _transfer_error(H, x1, x2)
        if np.mean(err < ransac_px) >= rotation_share:
            kind = "rotation"
    else:
        H = np.eye(3)
    return PairGeometry(a, b, x1, x2, kind, F, H)


def _transfer_error(H: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    p = np.c_[x1, np.ones(len(x1))] @ H.T
    return np.linalg.norm(p[:, :2] / p[:, 2:3] - x2, axis=1)


def collect_pairs(images: Sequence[np.ndarray], *, max_frames: int = 48, n_features: int = 2000,
                  offsets: Sequence[int] = PAIR_OFFSETS, **pair_kw: Any) -> list[PairGeometry]:
    """Frames (N x uint8 (H, W, 3) RGB) -> the usable pairs of evenly sampled frames (indices
    into ``images``)."""
    n = len(images)
    sel = np.unique(np.round(np.linspace(0, n - 1, min(n, max_frames))).astype(int)).tolist()
    feats = {i: _features(np.asarray(images[i]), n_features) for i in sel}
    pairs = []
    for p, a in enumerate(sel):
        for off in offsets:
            if p + off >= len(sel):
                break
            b = sel[p + off]
            x1, x2 = _match(feats[a], feats[b])
            g = pair_geometry(a, b, x1, x2, **pair_kw)
            if g is not None:
                pairs.append(g)
    return pairs


# ------------------------------------------------------------------------------ the cost


def _K(f: float, c: np.ndarray) -> np.ndarray:
    return np.array([[f, 0, c[0]], [0, f, c[1]], [0, 0, 1.0]])


def _algebraic_cost(g: PairGeometry, f: float, c: np.ndarray) -> float:
    """How far the pair's matrix is from a valid one at focal ``f`` (0 = consistent)."""
    K = _K(f, c)
    if g.kind == "rotation":
        M = np.linalg.inv(K) @ g.H @ K
        d = np.linalg.det(M)
        if abs(d) < 1e-12:
            return 1.0
        M = M / np.cbrt(d)
        return float(np.linalg.norm(M.T @ M - np.eye(3)))
    s = np.linalg.svd(K.T @ g.F @ K, compute_uv=False)
    return float((s[0] - s[1]) / max(s[0], 1e-300))


def initial_focal(pairs: list[PairGeometry], c: np.ndarray, f_guess: float,
                  lo: float = 0.3, hi: float = 3.0, steps: int = 121) -> tuple[float, np.ndarray, np.ndarray]:
    """1-D search: the f (on a log grid over [lo, hi] x f_guess) minimising the median over
    pairs of the algebraic cost. Returns (f, grid (S,), median cost (S,))."""
    grid = f_guess * np.exp(np.linspace(np.log(lo), np.log(hi), steps))
    costs = np.array([[_algebraic_cost(g, f, c) for g in pairs] for f in grid])
    med = np.median(costs, axis=1)
    return float(grid[int(np.argmin(med))]), grid, med


# ------------------------------------------------------------------------------ refinement


def _rodrigues(r: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(r, np.float64).reshape(3, 1))[0]


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


def _tangent_basis(t: np.ndarray) -> np.ndarray:
    """(3, 2): two unit vectors orthogonal to unit t (the translation direction's 2 DoF)."""
    a = np.eye(3)[int(np.argmin(np.abs(t)))]
    u = np.cross(t, a)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(t, u)], axis=1)


def _init_pose(g: PairGeometry, f: float, c: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(rotation vector (3,), unit translation (3,) or None for a rotation pair) at focal f."""
    K = _K(f, c)
    if g.kind == "rotation":
        M = np.linalg.inv(K) @ g.H @ K
        U, _, Vt = np.linalg.svd(M)
        R = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
        return cv2.Rodrigues(R)[0].ravel(), None
    E = K.T @ g.F @ K
    _, R, t, _ = cv2.recoverPose(E, g.x1, g.x2, K)
    t = t.ravel() / max(np.linalg.norm(t), 1e-12)
    return cv2.Rodrigues(R)[0].ravel(), t


class _Problem:
    """The joint least-squares problem: x = [log f, per pair: rotation vector (3) + for general
    pairs 2 tangent coordinates of the translation direction]."""

    def __init__(self, pairs: list[PairGeometry], c: np.ndarray, f0: float):
        self.pairs, self.c = pairs, c
        self.t0, self.basis, self.slices, self.rows = [], [], [], []
        x = [np.log(f0)]
        col, row = 1, 0
        for g in pairs:
            r, t = _init_pose(g, f0, c)
            x.extend(r)
            n = 3
            if t is not None:
                x.extend([0.0, 0.0])
                n = 5
            self.t0.append(t)
            self.basis.append(None if t is None else _tangent_basis(t))
            self.slices.append(slice(col, col + n))
            m = len(g.x1) * (2 if g.kind == "rotation" else 1)
            self.rows.append(slice(row, row + m))
            col, row = col + n, row + m
        self.x0, self.n_rows = np.asarray(x), row

    def residuals(self, x: np.ndarray) -> np.ndarray:
        f = float(np.exp(x[0]))
        K = _K(f, self.c)
        Ki = np.linalg.inv(K)
        out = np.empty(self.n_rows)
        for g, sl, rows, t0, B in zip(self.pairs, self.slices, self.rows, self.t0, self.basis):
            p = x[sl]
            R = _rodrigues(p[:3])
            if t0 is None:  # x2 ~ K R K^-1 x1: transfer error, px
                q = np.c_[g.x1, np.ones(len(g.x1))] @ (K @ R @ Ki).T
                out[rows] = (q[:, :2] / q[:, 2:3] - g.x2).ravel()
                continue
            t = t0 + B @ p[3:5]
            t = t / np.linalg.norm(t)
            F = Ki.T @ _skew(t) @ R @ Ki
            h1 = np.c_[g.x1, np.ones(len(g.x1))]
            h2 = np.c_[g.x2, np.ones(len(g.x2))]
            Fx1, Ftx2 = h1 @ F.T, h2 @ F
            num = np.sum(h2 * Fx1, axis=1)
            den = np.sqrt(Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2) + 1e-300
            out[rows] = num / den  # Sampson distance, px
        return out

    def sparsity(self):
        from scipy.sparse import lil_matrix

        A = lil_matrix((self.n_rows, len(self.x0)), dtype=np.int8)
        A[:, 0] = 1
        for sl, rows in zip(self.slices, self.rows):
            A[rows, sl] = 1
        return A


def _focal_sigma(jac, residuals: np.ndarray, n_params: int, robust_px: float) -> float:
    """Marginal std of log f from J (rows already weighted by the robust loss): the Schur
    complement of the pair blocks in J^T J, scaled by the robust residual variance."""
    H = (jac.T @ jac).toarray() if hasattr(jac, "toarray") else np.asarray(jac).T @ np.asarray(jac)
    m = len(residuals)
    # robust spread of the residuals (MAD), the noise level the covariance is scaled by
    s = 1.4826 * float(np.median(np.abs(residuals))) if m else robust_px
    s = max(s, 1e-3)
    try:
        cov = np.linalg.pinv(H, rcond=1e-12)
    except np.linalg.LinAlgError:
        return float("inf")
    var = float(cov[0, 0])
    return float(np.sqrt(max(var, 0.0))) * s if np.isfinite(var) else float("inf")


def refine_focal(pairs: list[PairGeometry], c: np.ndarray, f0: float, *, robust_px: float = 0.5,
                 max_nfev: int = 60) -> dict[str, Any]:
    """Joint robust refinement of one focal length and every pair's relative pose. Returns
    {focal, log_sigma (std of log f), median_px (robust residual), pairs, rotation_pairs}."""
    from scipy.optimize import least_squares

    prob = _Problem(pairs, c, f0)
    res = least_squares(prob.residuals, prob.x0, jac_sparsity=prob.sparsity(), loss="cauchy",
                        f_scale=robust_px, method="trf", max_nfev=max_nfev)
    r = prob.residuals(res.x)
    return {"focal": float(np.exp(res.x[0])), "log_sigma": _focal_sigma(res.jac, r, len(res.x), robust_px),
            "median_px": float(np.median(np.abs(r))), "pairs": len(pairs),
            "rotation_pairs": sum(g.kind == "rotation" for g in pairs), "x": res.x, "problem": prob}


def _reclassify(pairs: list[PairGeometry], fit: dict[str, Any], max_px: float) -> bool:
    """Rotation pairs that the fitted rotation does not explain (a plane seen while moving)
    become general pairs. True when any changed."""
    prob, r = fit["problem"], fit["problem"].residuals(fit["x"])
    changed = False
    for g, rows in zip(pairs, prob.rows):
        if g.kind == "rotation":
            e = np.linalg.norm(r[rows].reshape(-1, 2), axis=1)
            if np.median(e) > max_px:
                g.kind = "general"
                changed = True
    return changed


def estimate_focal(images: Sequence[np.ndarray], K_guess: np.ndarray, *, max_frames: int = 48,
                   n_features: int = 2000, min_pairs: int = 6, max_rel_sigma: float = 0.03,
                   robust_px: float = 0.5, ransac_px: float = 1.0) -> dict[str, Any]:
    """Frames (N x uint8 (H, W, 3) RGB, working resolution) + the guessed K (3, 3) -> {
    focal (px, working resolution; the guess when not determined), determined (bool),
    rel_sigma (std of f / f), initial_focal, pairs, rotation_pairs, median_px, reason (str:
    why not determined, '' when determined)}. The principal point is K_guess's."""
    c = np.asarray(K_guess, np.float64)[:2, 2].copy()
    f_guess = float(K_guess[0, 0])
    pairs = collect_pairs(images, max_frames=max_frames, n_features=n_features, ransac_px=ransac_px)
    out: dict[str, Any] = {"focal": f_guess, "determined": False, "rel_sigma": float("inf"),
                           "initial_focal": f_guess, "pairs": len(pairs),
                           "rotation_pairs": sum(g.kind == "rotation" for g in pairs), "median_px": 0.0}
    if len(pairs) < min_pairs:
        out["reason"] = (f"only {len(pairs)} frame pair(s) with enough matched motion (need {min_pairs}): "
                         "the camera hardly moves")
        return out
    f0, _, _ = initial_focal(pairs, c, f_guess)
    fit = refine_focal(pairs, c, f0, robust_px=robust_px)
    if _reclassify(pairs, fit, max_px=2.0 * ransac_px):
        fit = refine_focal(pairs, c, fit["focal"], robust_px=robust_px)
    rel = float(np.expm1(fit["log_sigma"])) if np.isfinite(fit["log_sigma"]) else float("inf")
    out.update(initial_focal=f0, rel_sigma=rel, pairs=fit["pairs"], rotation_pairs=fit["rotation_pairs"],
               median_px=fit["median_px"])
    in_range = 0.3 * f_guess < fit["focal"] < 3.0 * f_guess
    if rel <= max_rel_sigma and in_range:
        out.update(focal=fit["focal"], determined=True, reason="")
    else:
        out["estimate"] = fit["focal"]
        out["reason"] = (f"the motion does not determine the focal length (estimate {fit['focal']:.1f} px "
                         f"+- {100 * rel:.0f} %: forward-only or near-static motion?)")
    return out
