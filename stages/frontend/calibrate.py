"""Focal self-calibration: one focal length (fx = fy) from the video itself.

When no intrinsics are given the ingest guess f = 300/384 x long side is typically 5-35 % off
on real cameras, and poses and depth fall apart with it. :func:`estimate_focal` estimates the
focal length from the frames (principal point fixed, at the image centre unless given):

1. Frames chosen by image motion (:func:`_select_by_motion`: the next frame is the last whose SIFT
   matches moved less than 5 % of the long side; a slow clip is thinned, a wide-baseline one keeps
   every frame); SIFT features once per chosen frame.
2. Frame pairs (each frame with the next two): RANSAC fundamental matrix F, and a homography on
   its inliers. A clip where most pairs are explained by a homography (the camera mainly
   rotates) is solved from the homographies (H = K R K^-1: a 1-D search over f on how far
   K^-1 H K is from a scaled rotation, then a joint robust refinement of f and each pair's
   rotation on the transfer error, :func:`refine_focal`); pure rotation determines f, the
   epipolar constraint does not.
3. Otherwise: tracks (RANSAC-verified matches chained over frames 1-3 apart; each pair matched
   once), at most ~``tracks_per_frame`` per frame kept for the structure from motion (spatially
   bucketed, the longest first: :func:`select_tracks`; a richly textured clip has thousands), a
   small incremental structure from motion at the current f (two-view start, PnP, triangulation;
   bundle adjustments with f free whenever the registered frames grew by half, and a new
   reconstruction where the track chain breaks), then a bundle adjustment (stages.sfm.focal_ba) of all
   reconstructions with one shared focal length (two rounds, the second on the
   observations within 2 px); repeated from its f while that moves > 1 % (``pass_tol``, at most ``passes``); finally one adjustment
   over all tracks from that solution (the capped set alone left the synthetic loop's f 1-2 %
   towards the guess). Two-view geometry alone was 8-10 % off on handheld footage (near the
   two-view degenerate configuration); the multi-view adjustment is what determines f
   (docs/benchmarks.md).
4. Uncertainty (:func:`_uncertainty`), meant to match the real error rather than the formal one
   (0.01-0.1 % where real clips were 1-3 % off): the jackknife spread over frame blocks left
   out, how far f moves when the principal point is ``pp_frac`` of the image size off the centre,
   and the formal std, combined in quadrature. Not determined (the caller keeps the guess and
   warns): fewer than 6 usable pairs (a camera that hardly moves), a reconstruction of < 25 % of
   the chosen frames, a motion uncertainty (blocks, formal) above ``max_rel_sigma``, forward-only motion
   (:func:`forward_share`: f and the principal point trade off), or an estimate outside 0.3-3 x
   the guess.

Pure: arrays in, a dict out; deterministic (OpenCV's RANSAC seeded; SIFT and the solver, on one BLAS thread, are).
Units: pixels at the frames' (working) resolution.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import cv2
import numpy as np

from gcvd_flow.stages.frontend.params import CalibrateSettings, settings_with
from gcvd_flow.stages.geometry.se3 import hat
from gcvd_flow.stages.sfm.features import UniqueRatioMatcher, matched_points, sift_features
from gcvd_flow.stages.sfm.reconstruction import (
    TRACK_KEY,
    add_points,
    adjust_focal,
    bundle_adjust_focal,
    focal_K,
    incremental_reconstruction,
    observations,
    rodrigues,
)
from gcvd_flow.stages.sfm.tracks import RANSAC_SEED, UnionFind, feature_tracks, select_tracks

log = logging.getLogger(__name__)

SIFT_RATIO = 0.8
START_FIT_TOL = 0.02  # a later SfM start is kept over an earlier one when its median reprojection error is this much lower
PP_REL_TOL = 1e-9  # LM relative cost decrease at which the free-principal-point adjustments stop


@dataclass(frozen=True)
class FocalEstimate:
    """What :func:`estimate_focal` found (pixels at the frames' working resolution). ``focal`` and
    ``principal_point`` are what to use: the estimate when ``determined`` / ``pp_estimated``, else
    the guess, with ``reason`` / ``pp_reason`` saying why (one line each). The rest explains the
    estimate: the work it saw and the terms of its uncertainty."""

    focal: float  # px: the estimate (determined) or the guess
    determined: bool
    rel_sigma: float  # relative std of focal (inf: nothing determined)
    pairs: int  # frame pairs with enough matched motion
    rotation_pairs: int  # of them explained by a homography
    frames: int  # frames the solution registered
    points: int  # triangulated points of the final adjustment
    tracks: int
    median_px: float  # median reprojection (or transfer) error of the final adjustment
    method: str  # "rotation" (homographies), "bundle adjustment" or "" (not reached)
    iterations: int  # Levenberg-Marquardt iterations, all adjustments
    pp_frac: float  # the principal-point offset (share of the image size) the uncertainty allows for
    principal_point: list[float]  # (cx, cy) px
    pp_estimated: bool
    pp_reason: str  # why the principal point was not estimated ("" when it was, or was kept by choice)
    reason: str = ""  # why the focal length was not determined ("" when it was)
    pp_sigma: list[float] | None = None  # std (cx, cy) px of the free-principal-point adjustment
    pp_estimate: list[float] | None = None  # its (cx, cy) px, used or not
    pp_z: float | None = None  # its distance from the centre, in std
    pp_sigma_blocks: list[float] | None = None
    pp_sigma_formal: list[float] | None = None
    pp_note: str = ""  # why the centre was kept although the principal point was estimated
    pp_weight: list[float] | None = None  # the estimate's weight against the centre per axis (used: centre + weight x offset)
    pp_sensitivity: list[float] | None = None  # d log f per pp_frac x image size, (x, y)
    focal_centre: float | None = None  # px: the focal length with the principal point at the centre
    estimate: float | None = None  # px: the estimate when it was not determined (for the warning)
    forward_share: float | None = None  # share of forward steps (forward-only motion: f undetermined)
    block_focals: list[float] = field(default_factory=list)  # px: the jackknife's, one per block left out
    pp_focals: list[float] = field(default_factory=list)  # px: with the principal point moved by pp_frac
    start_focals: list[list[float]] = field(default_factory=list)  # [start x guess, focal px, median px, frames] per run
    rel_sigma_blocks: float | None = None  # the terms of rel_sigma: jackknife over frame blocks,
    rel_sigma_pp: float | None = None  # ... the principal-point allowance,
    rel_sigma_formal: float | None = None  # ... and the adjustment's formal std
    rel_sigma_motion: float | None = None  # blocks and formal alone (what the motion determines)

    @classmethod
    def from_record(cls, rec: dict[str, Any]) -> FocalEstimate:
        """From estimate_focal's working record; a key without a field is a TypeError (a new
        result must be declared here, where it is typed and documented)."""
        return cls(**rec)


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


# ------------------------------------------------------------------------------ the cost


def _algebraic_cost(g: PairGeometry, f: float, c: np.ndarray) -> float:
    """How far the pair's matrix is from a valid one at focal ``f`` (0 = consistent)."""
    K = focal_K(f, c)
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


def _tangent_basis(t: np.ndarray) -> np.ndarray:
    """(3, 2): two unit vectors orthogonal to unit t (the translation direction's 2 DoF)."""
    a = np.eye(3)[int(np.argmin(np.abs(t)))]
    u = np.cross(t, a)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(t, u)], axis=1)


def _init_pose(g: PairGeometry, f: float, c: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(rotation vector (3,), unit translation (3,) or None for a rotation pair) at focal f."""
    K = focal_K(f, c)
    if g.kind == "rotation":
        M = np.linalg.inv(K) @ g.H @ K
        U, _, Vt = np.linalg.svd(M)
        R = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
        return cv2.Rodrigues(R)[0].ravel(), None
    E = K.T @ g.F @ K
    _, R, t, _ = cv2.recoverPose(E, g.x1, g.x2, K)
    return cv2.Rodrigues(R)[0].ravel(), t.ravel() / max(float(np.linalg.norm(t)), 1e-12)


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
        K = focal_K(f, self.c)
        Ki = np.linalg.inv(K)
        out = np.empty(self.n_rows)
        for g, sl, rows, t0, B in zip(self.pairs, self.slices, self.rows, self.t0, self.basis):
            p = x[sl]
            R = rodrigues(p[:3])
            if t0 is None:  # x2 ~ K R K^-1 x1: transfer error, px
                q = np.c_[g.x1, np.ones(len(g.x1))] @ (K @ R @ Ki).T
                out[rows] = (q[:, :2] / q[:, 2:3] - g.x2).ravel()
                continue
            t = t0 + B @ p[3:5]
            t = t / np.linalg.norm(t)
            F = Ki.T @ hat(np.asarray(t, np.float64)[None])[0] @ R @ Ki
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


# ------------------------------------------------------------------------------ multi-view


def _reconstructions(tracks, n: int, K: np.ndarray, parallax: float, refine: Any
                     ) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray], np.ndarray]:
    """Incremental reconstructions until every frame is in one or cannot start one: where the
    track chain breaks (a fast turn, a blurred stretch) a new reconstruction starts after it. Returns
    (T_c_w per frame, points keyed model * TRACK_KEY + track, K as refined so far)."""
    T_all: dict[int, np.ndarray] = {}
    pts_all: dict[int, np.ndarray] = {}
    used: set[int] = set()
    m = 0
    while n - len(used) >= 3:
        T, pts, K = incremental_reconstruction(tracks, n, K, parallax, refine=refine, exclude=frozenset(used))
        if len(T) < 3:
            used.add(min(f for f in range(n) if f not in used))  # no start here: try after this frame
            continue
        used |= set(T)
        T_all.update(T)
        pts_all.update({m * TRACK_KEY + i: X for i, X in pts.items()})
        m += 1
    return T_all, pts_all, K


def _sample(n: int, max_frames: int) -> list[int]:
    return np.unique(np.round(np.linspace(0, n - 1, min(n, max_frames))).astype(int)).tolist()


def _select_by_motion(images: Sequence[np.ndarray], max_frames: int, n_features: int, target_frac: float,
                      min_frames: int = 20, knn: UniqueRatioMatcher | None = None,
                      keep: Sequence[np.ndarray] | None = None) -> tuple[list[int], list]:
    """Frames spaced by image motion rather than by index: from each chosen frame, the next is the
    last one whose matches moved less than ``target_frac`` x the long side (median) while still
    sharing enough matches. A slow clip is thinned, a fast one (wide baseline) keeps every frame.
    Candidates: at most 4 x ``max_frames`` frames, evenly; at most ``max_frames`` are kept
    (evenly among the chosen); fewer than ``min_frames``: the spacing is halved (up to 3 times).
    ``keep``: the user's kept masks of ``images`` (:func:`sift_features`), None without.
    Returns (indices into ``images``, their features)."""
    cand = _sample(len(images), 4 * max_frames)
    feats: dict[int, Any] = {}

    def feat(i: int):
        if i not in feats:
            feats[i] = sift_features(np.asarray(images[cand[i]]), n_features, None if keep is None else keep[cand[i]])
        return feats[i]

    target = target_frac * max(np.asarray(images[cand[0]]).shape[:2])
    for _ in range(4):  # too few frames for a reconstruction: halve the spacing
        chosen = _chosen(feat, len(cand), target, knn or UniqueRatioMatcher(SIFT_RATIO))
        if len(chosen) >= min(min_frames, len(cand)):
            break
        target /= 2
    if len(chosen) > max_frames:
        chosen = [chosen[k] for k in _sample(len(chosen), max_frames)]
    return [cand[k] for k in chosen], [feat(k) for k in chosen]


def _chosen(feat: Any, n: int, target: float, knn: UniqueRatioMatcher) -> list[int]:
    """Greedy spacing of :func:`_select_by_motion` over candidate positions 0..n-1."""
    chosen, a = [0], 0
    while a < n - 1:
        nxt = a + 1
        for b in range(a + 1, n):
            x1, x2 = matched_points(feat(a), feat(b), knn)
            if len(x1) < 60 or np.median(np.linalg.norm(x2 - x1, axis=1)) >= target:
                nxt = max(a + 1, b if len(x1) >= 60 else b - 1)
                break
            nxt = b
        chosen.append(nxt)
        a = nxt
    return chosen


def estimate_focal(images: Sequence[np.ndarray], K_guess: np.ndarray, settings: CalibrateSettings | None = None, *,
                   min_pairs: int = 6, robust_px: float = 1.0, ransac_px: float = 1.0, rotation_share: float = 0.7,
                   motion_frac: float = 0.05, blocks: int = 5, max_forward_share: float = 0.8,
                   keep: Sequence[np.ndarray] | None = None, pp_prior: float = 0.05, pp_use_all: bool = False, aspect: float = 1.0,
                   start_map: Callable[..., Any] = map, **overrides: Any) -> FocalEstimate:
    """Frames (N x uint8 (H, W, 3) RGB, working resolution) + the guessed K (3, 3) ->
    :class:`FocalEstimate` (focal, its relative std rel_sigma from the jackknife over frame blocks
    (:func:`_jackknife`), the principal-point allowance and the formal std; the principal point).
    The focal length is not determined (the guess is kept, with the reason) when rel_sigma_motion (the
    blocks and formal terms) exceeds ``max_rel_sigma`` or a share >= ``max_forward_share`` of the steps between registered frames
    moves along the optical axis (forward-only motion: KITTI 1.0, HoloLens walk 0.41, ICL 0).

    Mostly-rotating clips (a share >= ``rotation_share`` of the frame pairs explained by a
    homography) are solved from the pairs' homographies (H = K R K^-1); all others by a small
    structure from motion at the guess followed by a bundle adjustment with the focal length free
    (repeated from its result, at most ``cfg.passes`` times, while that moves by more than ``cfg.pass_tol``;
    the lens-free loop ends at 207.03 px from guesses 190 / 200 / 215, true 206.9), on at most about
    ``tracks_per_frame`` tracks per frame (:func:`select_tracks`).

    ``keep``: the user's kept masks (--masks) of the frames, N x (H, W), 1 = not masked, or None:
    no feature on (or within MASK_DILATE_PX of) a masked pixel, so no pair, track or bundle
    adjustment sees one (:func:`sift_features`).

    ``aspect``: fy / fx of the frames' pixels (the working resize's sy / sx: the source's pixels are
    square, a 540x360 frame at 256x170 is not); the estimate is made in square pixels (keypoint rows
    divided by it) and returned for the frames' pixels: ``focal`` is fx, fy = aspect x fx.

    ``start_map``: how the structure-from-motion starts (``cfg.starts``) and the independent bundle
    adjustments of the uncertainty and principal-point steps (:func:`_adjust_job`) are run: ``map``
    here, or a caller's parallel map of the same contract (the engine's ``ctx.map``); the result does
    not depend on it.

    ``settings``: the calibrate stage's :class:`CalibrateSettings` (None: its defaults), with
    ``overrides`` by field name; ``mode`` is the caller's (whether to estimate at all)."""
    cfg = settings_with(CalibrateSettings, settings, overrides)
    c = np.asarray(K_guess, np.float64)[:2, 2].copy()
    c[1] = (c[1] + 0.5) / aspect - 0.5  # rows in square pixels (pixel-centre convention)
    f_guess = float(K_guess[0, 0])
    knn = UniqueRatioMatcher(SIFT_RATIO)
    sel, feats = _select_by_motion(images, cfg.max_frames, cfg.features, motion_frac, knn=knn, keep=keep)
    if aspect != 1.0:
        feats = [((pos + [0.0, 0.5]) / [1.0, aspect] - [0.0, 0.5], des) for pos, des in feats]
    pairs = _frame_pairs(sel, feats, knn, ransac_px)
    n_rot = sum(g.kind == "rotation" for g in pairs)
    out: dict[str, Any] = {"focal": f_guess, "determined": False, "rel_sigma": float("inf"), "pairs": len(pairs),
                           "rotation_pairs": n_rot, "frames": 0, "points": 0, "tracks": 0, "median_px": 0.0,
                           "method": "", "iterations": 0, "block_focals": [], "pp_frac": cfg.pp_frac,
                           "principal_point": [float(v) for v in c], "pp_estimated": False, "pp_sigma": None,
                           "pp_reason": "not estimated: the focal length is not determined"}
    if len(pairs) < min_pairs:
        out["reason"] = (f"only {len(pairs)} frame pair(s) with enough matched motion (need {min_pairs}): "
                         "the camera hardly moves")
        return _frames_pixels(out, aspect)
    size = np.asarray(images[sel[0]]).shape[1::-1]
    if n_rot >= rotation_share * len(pairs):
        f, rel = _rotation_focal([g for g in pairs if g.kind == "rotation"], c, f_guess, blocks, cfg.pp_frac, size, out)
        out.update(frames=len(sel))
    else:
        f, rel = _tracks_focal(feats, len(sel), c, f_guess, size, cfg, out, ransac_px=ransac_px, knn=knn,
                               robust_px=robust_px, blocks=blocks, start_map=start_map)
    out["rel_sigma"] = rel
    ba, polish = out.pop("_ba", None), out.pop("_polish", None)
    if _focal_determined(f, rel, f_guess, out, cfg.max_rel_sigma, max_forward_share):
        out.update(focal=float(f), determined=True, reason="")
        _principal_point_step(polish if pp_use_all and polish is not None else ba, f, c, size, cfg, out,
                              robust_px=robust_px, blocks=blocks, pp_prior=pp_prior, job_map=start_map)
    else:
        _not_determined(f, rel, out, max_forward_share)
    return _frames_pixels(out, aspect)


def _frames_pixels(out: dict[str, Any], aspect: float) -> FocalEstimate:
    """estimate_focal's record (square pixels) as a :class:`FocalEstimate` in the frames' pixels:
    principal-point rows and their std times ``aspect`` (fy / fx)."""
    def row(v: list[float] | None, centre: bool) -> list[float] | None:
        return None if v is None else [v[0], (v[1] + 0.5) * aspect - 0.5 if centre else v[1] * aspect]

    if aspect != 1.0:
        out.update(principal_point=row(out["principal_point"], True), pp_estimate=row(out.get("pp_estimate"), True),
                   **{k: row(out.get(k), False) for k in ("pp_sigma", "pp_sigma_blocks", "pp_sigma_formal")})
    return FocalEstimate.from_record(out)


def _frame_pairs(sel: list[int], feats: list[Any], knn: Any, ransac_px: float) -> list[PairGeometry]:
    """The two-view geometry of each selected frame with its next and next-but-one (the pairs
    with enough matched motion; :func:`pair_geometry`)."""
    pairs = []
    for p in range(len(sel)):
        for off in (1, 2):
            if p + off < len(sel):
                g = pair_geometry(p, p + off, *matched_points(feats[p], feats[p + off], knn), ransac_px=ransac_px)
                if g is not None:
                    pairs.append(g)
    return pairs


def _tracks_focal(feats: list[Any], n_sel: int, c: np.ndarray, f_guess: float, size: Any, cfg: CalibrateSettings,
                  out: dict[str, Any], *, ransac_px: float, knn: Any, robust_px: float, blocks: int,
                  start_map: Callable[..., Any] = map) -> tuple[float, float]:
    """(focal, rel_sigma) from tracks over the selected frames: a small structure from motion and
    a bundle adjustment with the focal length free (:func:`_sfm_focal`), from each of ``cfg.starts``
    (through ``start_map``: the builtin map, or the engine's ``ctx.map`` to run them side by side;
    the same result either way), the best-fitting kept (:func:`_best_start`); rel_sigma inf when it
    registered fewer than max(3, a quarter of) the frames."""
    all_tracks = feature_tracks(feats, ransac_px=ransac_px, knn=knn)
    tracks = select_tracks(all_tracks, size, cfg.tracks_per_frame)
    out["tracks"] = len(tracks)
    calls = ((tracks, all_tracks, n_sel, c, f_guess, robust_px, cfg.passes, 0.04 * max(size), dict(out), cfg.pass_tol,
              start * f_guess) for start in cfg.starts)
    runs = list(start_map(_sfm_start, calls))
    f, rel = _best_start(runs, cfg.starts, tracks, c, robust_px, blocks, cfg.pp_frac, size, out, job_map=start_map)
    if out["frames"] < max(3, 0.25 * n_sel):
        rel = float("inf")  # a reconstruction of a few frames says nothing about the clip's camera
    return f, rel


def _sfm_start(args: tuple) -> tuple[float, dict[str, Any]]:
    """One structure-from-motion start of :func:`_tracks_focal` (a module-level function of picklable
    arguments, for ``start_map``): (focal, its working record)."""
    tracks, all_tracks, n, c, f_guess, robust_px, passes, parallax, out, pass_tol, f_start = args
    f = _sfm_focal(tracks, all_tracks, n, c, f_guess, robust_px, passes, parallax, out, pass_tol=pass_tol,
                   f_start=f_start)
    return f, out


def _best_start(runs: list[tuple[float, dict[str, Any]]], starts: Sequence[float], tracks, c: np.ndarray,
                robust_px: float, blocks: int, pp_frac: float, size: Any, out: dict[str, Any],
                job_map: Callable[..., Any] = map) -> tuple[float, float]:
    """Of the structure-from-motion runs started from the guess x ``starts`` (focal, their working
    records), the one whose final adjustment fits best: the most registered frames, then the lowest
    median reprojection error, lower by more than START_FIT_TOL (runs that end at the same solution
    differ in their last digits: the first start's is kept). A reconstruction that depends on where
    it starts ends in a worse fit where it is wrong (HoloLens frames 33-66: 232.6 px at a median
    0.221 px from 0.8 x the guess, 267.0 px / 0.245 px from the guess; true 234.9). Its record
    goes into ``out`` (iterations summed over the runs, start_focals = [start, focal, median px,
    frames] per run), then its uncertainty (:func:`_uncertainty`). Returns (focal, rel_sigma);
    rel_sigma inf when no run reconstructed."""
    ok = [k for k, (_, r) in enumerate(runs) if "_ba" in r]
    iterations = sum(r["iterations"] for _, r in runs)
    out["start_focals"] = [[float(st), float(f), float(r.get("median_px", 0.0)), int(r.get("frames", 0))]
                           for st, (f, r) in zip(starts, runs)]
    if not ok:
        out.update({k: v for k, v in runs[0][1].items() if k not in ("start_focals", "iterations")})
        out["iterations"] = iterations
        return runs[0][0], float("inf")
    best = ok[0]
    for k in ok[1:]:  # a later start replaces the earlier only if it registers more frames or fits clearly better
        more = runs[k][1]["frames"] > runs[best][1]["frames"]
        same = runs[k][1]["frames"] == runs[best][1]["frames"]
        if more or (same and runs[k][1]["median_px"] < (1 - START_FIT_TOL) * runs[best][1]["median_px"]):
            best = k
    f, run = runs[best]
    out.update({k: v for k, v in run.items() if k not in ("start_focals", "iterations")})
    tracks_b, final = out["_ba"]
    rel, it = _uncertainty(tracks_b, final, focal_K(f, c), robust_px, blocks, pp_frac, size, out, job_map=job_map)
    out["iterations"] = iterations + it
    return f, rel


def _focal_determined(f: float, rel: float, f_guess: float, out: dict[str, Any], max_rel_sigma: float,
                      max_forward_share: float) -> bool:
    """Whether the estimate f is used: the motion's uncertainty (blocks and formal terms; recorded
    as out's rel_sigma_motion) within ``max_rel_sigma``, f within 0.3-3 x the guess, and the
    camera not moving forward only."""
    in_range = 0.3 * f_guess < f < 3.0 * f_guess
    forward = out.get("forward_share", 0.0) >= max_forward_share
    # the decision rests on what the motion says (blocks, formal); the principal-point term is the same
    # risk for any camera whose principal point is unknown and varied 2.2-4.3 % between settings on
    # HoloLens: it is reported in rel_sigma, not a reason to drop a good estimate
    motion_rel = float(np.hypot(out.get("rel_sigma_blocks", 0.0), out.get("rel_sigma_formal", 0.0)))
    motion_rel = motion_rel if np.isfinite(rel) else float("inf")
    out["rel_sigma_motion"] = motion_rel
    return bool(motion_rel <= max_rel_sigma and in_range and not forward)


def _principal_point_step(ba: Any, f: float, c: np.ndarray, size: Any, cfg: CalibrateSettings, out: dict[str, Any],
                          *, robust_px: float, blocks: int, pp_prior: float, job_map: Callable[..., Any] = map) -> None:
    """With the focal length determined: the principal point per ``cfg.principal_point``
    (:func:`_estimate_pp` from the adjustment ``ba``; none from a rotating camera's homographies)."""
    if cfg.principal_point == "auto" and ba is not None:
        _estimate_pp(ba, focal_K(f, c), size, robust_px, blocks, cfg.pp_max_sigma, cfg.pp_spread, pp_prior, out,
                     job_map=job_map)
    elif cfg.principal_point == "auto":
        out["pp_reason"] = (f"not estimated from a rotating camera's homographies (method {out['method']}); "
                            "assumed at the image centre")
    else:
        out["pp_reason"] = ""


def _not_determined(f: float, rel: float, out: dict[str, Any], max_forward_share: float) -> None:
    """out's estimate and reason when the focal length is not used."""
    out["estimate"] = float(f)
    if out.get("forward_share", 0.0) >= max_forward_share:
        out["reason"] = (f"the camera only moves forward ({100 * out['forward_share']:.0f} % of the steps along "
                         "the optical axis): the focal length cannot be separated from the principal point "
                         f"(assumed at the image centre; estimate {f:.1f} px +- {100 * rel:.0f} %)")
    else:
        out["reason"] = (f"the motion does not determine the focal length (estimate {f:.1f} px +- "
                         f"{100 * rel:.0f} %: forward-only or near-static motion?)")


def _estimate_pp(ba_tracks: tuple[list, dict[str, Any]], K: np.ndarray, size: tuple[int, int], robust_px: float,
                 blocks: int, max_sigma: float, spread: float, prior_frac: float, out: dict[str, Any],
                 min_z: float = 2.0, job_map: Callable[..., Any] = map) -> None:
    """The principal point decision of :func:`estimate_focal` (the focal length is determined).
    The estimate of :func:`principal_point` (offset o from the centre, std s per axis) is used
    when s is within ``max_sigma`` x the image size and it lies more than ``min_z`` std from the
    centre (within, the centre is kept: the motion confirms it, no warning; synthetic and
    software-centred cameras sit exactly there), moved towards the centre by its uncertainty:
    centre + w o with w = p^2 / (p^2 + s^2), p = ``spread`` x the image size, how far real cameras'
    principal points lie from the centre (the most probable point under that spread: a well
    determined estimate is used as it is, an uncertain one only as far as the motion supports it);
    the focal length is then adjusted again with it. A larger std keeps the centre with a reason
    (pp_reason: the caller warns). Fills out's principal_point, pp_estimate, pp_sigma (px, of the
    estimate), pp_sigma_blocks / _formal, pp_z, pp_weight, pp_estimated, pp_reason and, when used,
    focal, focal_centre and rel_sigma (the joint adjustment's spreads and the principal-point term
    scaled to the used point's std, s sqrt(w))."""
    tracks, ba = ba_tracks
    c0 = K[:2, 2]
    res = principal_point(tracks, ba, K, size, robust_px=robust_px, blocks=blocks, prior_frac=prior_frac,
                          max_sigma=max_sigma, job_map=job_map)
    out["iterations"] = out.get("iterations", 0) + res["iterations"]
    sig = np.asarray(res["sigma"], np.float64)
    est = np.asarray(res["pp"], np.float64)
    z = float(np.hypot(*((est - c0) / np.maximum(sig, 1e-9)))) if np.all(np.isfinite(sig)) else 0.0
    out.update(pp_estimate=[float(v) for v in est], pp_sigma=[float(v) for v in sig], pp_z=z,
               pp_sigma_blocks=None if res.get("sigma_blocks", sig) is None else [float(v) for v in res["sigma_blocks"]],
               pp_sigma_formal=[float(v) for v in res.get("sigma_formal", sig)])
    rel = sig / np.asarray(size, np.float64)
    desc = (f"estimate ({est[0]:.1f}, {est[1]:.1f}) px +- ({sig[0]:.1f}, {sig[1]:.1f}) px, "
            f"{100 * float(np.max(rel)):.1f} % of the image")
    if not np.all(rel <= max_sigma):
        out["pp_reason"] = (f"the motion does not determine it ({desc}; needs <= {100 * max_sigma:g} %): "
                            f"assumed at the image centre ({c0[0]:.1f}, {c0[1]:.1f})")
        return
    if z <= min_z:
        out["pp_reason"] = ""
        out["pp_note"] = f"the image centre is kept: the {desc} is within {z:.1f} std of it"
        return
    p2 = (spread * np.asarray(size, np.float64)) ** 2
    w = p2 / (p2 + sig ** 2)
    used = c0 + w * (est - c0)
    focal = float(res["focal"])
    if res.get("T"):  # f with the point used (f and the principal point trade off along a valley)
        refit = adjust_focal(tracks, res["T"], res["pts"], focal_K(focal, used), robust_px=robust_px, iterations=100,
                             max_px=2.0, rel_tol=PP_REL_TOL)
        out["iterations"] += refit["iterations"]
        focal = float(refit["focal"]) if refit["T"] else focal
    sens = np.asarray(out.get("pp_sensitivity", [0.0, 0.0]), np.float64)  # d log f per pp_frac x size
    sig_used = sig * np.sqrt(w)
    pp_term = float(np.hypot(*(sens * sig_used / np.maximum(out.get("pp_frac", 0.02) * np.asarray(size), 1e-9))))
    rel_f = float(np.sqrt(res["rel_sigma_blocks"] ** 2 + res["rel_sigma_formal"] ** 2 + pp_term ** 2))
    out.update(principal_point=[float(v) for v in used], pp_estimated=True, pp_reason="", focal=focal,
               pp_weight=[float(v) for v in w], focal_centre=float(out["focal"]), rel_sigma=rel_f,
               rel_sigma_blocks=res["rel_sigma_blocks"], rel_sigma_formal=res["rel_sigma_formal"], rel_sigma_pp=pp_term)


def _rotation_focal(rot: list[PairGeometry], c: np.ndarray, f_guess: float, blocks: int, pp_frac: float,
                    size: tuple[int, int], out: dict[str, Any]) -> tuple[float, float]:
    """Focal length (px) of a rotating camera from its homographies and its relative uncertainty:
    the jackknife spread of the same refinement with each of ``blocks`` contiguous runs of pairs
    left out, combined with how far f moves with the principal point ``pp_frac`` x the image size
    off (as :func:`_uncertainty`). Fills out's method, median_px, block_focals, pp_focals,
    rel_sigma_blocks, rel_sigma_pp."""
    f0, _, _ = initial_focal(rot, c, f_guess)
    fit = refine_focal(rot, c, f0, robust_px=0.5)
    f = fit["focal"]
    parts = [p for p in np.array_split(np.arange(len(rot)), blocks) if len(p)] if len(rot) >= 2 * blocks else []
    fs = [refine_focal([g for k, g in enumerate(rot) if k not in set(p.tolist())], c, f, robust_px=0.5,
                       max_nfev=15)["focal"] for p in parts]
    pp_fs = [refine_focal(rot, c + sign * np.asarray(d), f, robust_px=0.5, max_nfev=15)["focal"]
             for d in ((pp_frac * size[0], 0.0), (0.0, pp_frac * size[1])) for sign in (1.0, -1.0)]
    rel_b = _jackknife_rel(fs)
    # the larger one-sided move per axis: for a rotating camera a principal point shift is nearly a
    # rotation, so f's first-order (central) change is ~0 and understated the error (0.09 % vs 0.19 %)
    dev = np.abs(np.log(np.asarray(pp_fs) / f)).reshape(2, 2).max(axis=1)
    rel_pp = float(np.hypot(*dev))
    out.update(method="rotation", median_px=fit["median_px"], block_focals=[float(x) for x in fs],
               pp_focals=[float(x) for x in pp_fs], rel_sigma_blocks=rel_b, rel_sigma_pp=rel_pp)
    return f, float(np.hypot(rel_b, rel_pp))


def _jackknife_rel(fs: Sequence[float]) -> float:
    """Delete-a-block jackknife std of log f over the leave-one-block-out estimates ``fs`` (a
    relative std of f); inf with fewer than 3 estimates."""
    if len(fs) < 3:
        return float("inf")
    lf = np.log(np.asarray(fs, np.float64))
    b = len(lf)
    return float(np.sqrt((b - 1) / b * np.sum((lf - lf.mean()) ** 2)))


def _sfm_focal(tracks, all_tracks, n: int, c: np.ndarray, f_guess: float, robust_px: float, passes: int,
               parallax: float, out: dict[str, Any],
               pass_tol: float = 0.01, f_start: float | None = None) -> float:
    """Focal length (px) from reconstructions of ``tracks`` (the capped set, :func:`select_tracks`)
    over ``n`` frames, polished by one bundle adjustment over ``all_tracks`` (the cap alone biased
    the synthetic loop's f by 1-2 % towards the guess). The first reconstruction is made at
    ``f_start`` (default the guess; the guess bounds every adjustment's f to 0.3-3 x itself). Fills
    out's method, median_px, frames, points, iterations, forward_share and the solutions ``_ba``
    (capped tracks) and ``_polish`` (all tracks) when it reconstructed; its uncertainty is the
    caller's (:func:`_best_start`, for the start it keeps)."""
    f, iters = f_guess if f_start is None else f_start, [0]

    def refine(T, pts, K):
        ba = bundle_adjust_focal(tracks, T, pts, K, robust_px=robust_px, max_px=(10.0,))
        iters[0] += ba["iterations"]
        if not ba["T"] or not 0.3 * f_guess < ba["focal"] < 3.0 * f_guess:
            return T, pts, K
        return ba["T"], {**pts, **ba["pts"]}, focal_K(ba["focal"], c)

    final = None
    for _ in range(passes):
        T, pts, K = _reconstructions(tracks, n, focal_K(f, c), parallax, refine)
        if len(T) < 3 or len(pts) < 20:
            break
        ba = bundle_adjust_focal(tracks, T, pts, K, robust_px=robust_px)
        iters[0] += ba["iterations"]
        if not ba["T"] or ba["frames"] < out["frames"]:  # a pass that registered fewer frames: stop
            break
        moved = abs(np.log(ba["focal"] / f))
        f, final = ba["focal"], ba
        out.update(method="bundle adjustment", median_px=ba["median_px"], frames=ba["frames"], points=ba["points"])
        if moved < pass_tol:
            break
    if final is None:
        out["iterations"] = iters[0]
        return f
    if len(all_tracks) > len(tracks):
        pts_all = _retriangulate(all_tracks, tracks, final, focal_K(f, c))
        pol = bundle_adjust_focal(all_tracks, final["T"], pts_all, focal_K(f, c),
                                  robust_px=robust_px, max_px=(2.0,))
        iters[0] += pol["iterations"]
        if pol["T"] and pol["frames"] >= final["frames"] and 0.3 * f_guess < pol["focal"] < 3.0 * f_guess:
            f = pol["focal"]
            out.update(median_px=pol["median_px"], points=pol["points"])
            out["_polish"] = (all_tracks, pol)
    out["_ba"] = (tracks, final)  # for the principal point (estimate_focal pops it)
    out["forward_share"] = forward_share(final["T"])
    out["iterations"] = iters[0]
    return f


def forward_share(T: dict[int, np.ndarray], max_deg: float = 30.0) -> float:
    """Share of consecutive registered frames (world-to-camera poses T (4, 4)) whose baseline lies
    within ``max_deg`` of the first one's optical axis: 1 for a camera that only moves forward (a
    car, a walk looking ahead), where the focal length and the principal point trade off."""
    fr = sorted(T)
    n, k = 0, 0
    for a, b in zip(fr, fr[1:]):
        ca, cb = -T[a][:3, :3].T @ T[a][:3, 3], -T[b][:3, :3].T @ T[b][:3, 3]
        d = T[a][:3, :3] @ (cb - ca)  # baseline in camera a
        if np.linalg.norm(d) < 1e-12:
            continue
        n += 1
        k += abs(d[2]) / np.linalg.norm(d) >= np.cos(np.radians(max_deg))
    return k / n if n else 0.0


def _retriangulate(tracks, ba_tracks, ba: dict[str, Any], K: np.ndarray) -> dict[int, np.ndarray]:
    """Points of ``tracks`` triangulated in the poses of a bundle adjustment ``ba`` (T, pts keyed
    model * TRACK_KEY + index into ``ba_tracks``): each reconstruction (model) separately, as its
    poses live in their own frame; keys model * TRACK_KEY + index into ``tracks``."""
    model_of: dict[int, int] = {}
    for key, o in observations(ba_tracks, ba["T"], ba["pts"], K, 2.0)[0].items():
        for fr, _ in o:
            model_of.setdefault(fr, key // TRACK_KEY)
    out: dict[int, np.ndarray] = {}
    for m in sorted(set(model_of.values())):
        T = {fr: v for fr, v in ba["T"].items() if model_of.get(fr) == m}
        pts: dict[int, np.ndarray] = {}
        add_points(tracks, T, pts, K, 2.0)
        out.update({m * TRACK_KEY + i: X for i, X in pts.items()})
    return out


def _uncertainty(tracks, ba: dict[str, Any], K: np.ndarray, robust_px: float, blocks: int, pp_frac: float,
                 size: tuple[int, int], out: dict[str, Any], job_map: Callable[..., Any] = map) -> tuple[float, int]:
    """Relative std of f: the jackknife spread over frame blocks (:func:`_jackknife`) combined with
    how far f moves when the principal point (assumed at the centre) is off by ``pp_frac`` x the
    image's width (x) and height (y) (the bundle adjustment repeated from ``ba`` with it moved). The
    second term is what forward motion cannot separate (KITTI: a principal point 10 px off at
    1226 px moved f 11 %); and the formal std (:func:`_formal_rel_sigma`: where f is unobservable,
    the perturbed adjustments stay where they start). The adjustments are independent: they go
    through ``job_map`` together (:func:`_adjust_job`). Returns (rel sigma, LM iterations); fills
    out's block_focals, pp_focals, rel_sigma_blocks, rel_sigma_pp, rel_sigma_formal."""
    calls = _block_calls(tracks, ba, K, robust_px, blocks, max_px=2.0, iterations=10)
    nb = len(calls)  # then the 4 principal-point moves, then the formal std
    moves = [sign * d for d in (np.array([pp_frac * size[0], 0.0]), np.array([0.0, pp_frac * size[1]]))
             for sign in (1.0, -1.0)]  # central differences: both runs gated and converged alike
    calls += [(tracks, ba["T"], ba["pts"], focal_K(ba["focal"], K[:2, 2] + d),  # from the capped adjustment's solution
               dict(robust_px=robust_px, iterations=30, max_px=2.0 + float(np.abs(d).sum())), False) for d in moves]
    calls.append((tracks, ba["T"], ba["pts"], focal_K(ba["focal"], K[:2, 2]),
                  dict(robust_px=robust_px, iterations=1, max_px=2.0, marginal=True), False))
    res = list(job_map(_adjust_job, calls))
    iters = sum(r["iterations"] for r in res[:-1])  # the formal std's one evaluation is not counted (as before)
    fs = [r["focal"] for r in res[:nb] if r["frames"] >= 3]
    rel_b = _jackknife_rel(fs)
    pp_fs = [r["focal"] if r["solved"] else float("nan") for r in res[nb:nb + 4]]
    sens = [abs(np.log(a / b)) / 2 if np.isfinite(a) and np.isfinite(b) else float("inf")
            for a, b in (pp_fs[0:2], pp_fs[2:4])]
    rel_pp = float(np.hypot(sens[0], sens[1]))  # x, y
    rel_f = float(res[-1].get("rel_sigma_formal", float("inf")))
    out.update(block_focals=fs, pp_focals=pp_fs, rel_sigma_blocks=rel_b, rel_sigma_pp=rel_pp, rel_sigma_formal=rel_f,
               pp_sensitivity=[float(x) for x in sens])
    return float(np.sqrt(rel_b ** 2 + rel_pp ** 2 + rel_f ** 2)), iters


def _adjust_job(args: tuple) -> dict[str, Any]:
    """One independent bundle adjustment of the uncertainty and principal-point steps (a module-level
    function of picklable arguments, for the job map): (tracks, T, pts, K, adjust_focal's keyword
    arguments, split) -> its summary {focal, pp (2,), frames, iterations, solved, and
    rel_sigma_formal when asked}. ``split``: T leaves a block of frames out, so the points are
    first split where that parts a reconstruction (:func:`_split_models`)."""
    tracks, T, pts, K, kw, split = args
    if split:
        pts = _split_models(tracks, T, pts, K, kw["max_px"])
    res = adjust_focal(tracks, T, pts, K, **kw)
    keep = {"focal": float(res["focal"]), "pp": [float(v) for v in res["pp"]], "frames": int(res["frames"]),
            "iterations": int(res["iterations"]), "solved": bool(res["T"])}
    if "rel_sigma_formal" in res:
        keep["rel_sigma_formal"] = float(res["rel_sigma_formal"])
    return keep


def _block_calls(tracks, ba: dict[str, Any], K: np.ndarray, robust_px: float, blocks: int, max_px: float,
                 iterations: int, pp_prior: tuple[np.ndarray, np.ndarray] | None = None,
                 rel_tol: float | None = None) -> list[tuple]:
    """The :func:`_adjust_job` calls of :func:`_jackknife`: ``ba``'s adjustment without each of
    ``blocks`` contiguous blocks of its registered frames."""
    frames = sorted(ba["T"])
    calls = []
    for part in np.array_split(np.asarray(frames), blocks):
        drop = set(part.tolist())
        T = {f: v for f, v in ba["T"].items() if f not in drop}
        calls.append((tracks, T, ba["pts"], K, dict(robust_px=robust_px, iterations=iterations, max_px=max_px,
                                                    pp_prior=pp_prior, rel_tol=rel_tol), True))
    return calls


def _jackknife(tracks, ba: dict[str, Any], K: np.ndarray, robust_px: float, blocks: int,
               max_px: float = 2.0, iterations: int = 10,
               pp_prior: tuple[np.ndarray, np.ndarray] | None = None, rel_tol: float | None = None,
               job_map: Callable[..., Any] = map) -> tuple[list[Any], int]:
    """The final bundle adjustment repeated ``blocks`` times (from its solution), each time without
    one contiguous block of the registered frames (through ``job_map``: :func:`_adjust_job`). The
    spread of these focal lengths is the
    estimate's uncertainty: it reflects how much f depends on which motion the clip happens to have
    (near-degenerate stretches, lens and principal-point model error, rolling shutter), which the
    formal covariance (0.01-0.1 % on real clips whose errors were 1-3 %) does not. Where leaving a
    block out splits a reconstruction, each part gets its own gauge. Returns (focal per block that
    kept >= 3 frames, LM iterations); with ``pp_prior`` (the principal point free, :func:`adjust_focal`)
    the focal lengths are (f, cx, cy) triples."""
    res = list(job_map(_adjust_job, _block_calls(tracks, ba, K, robust_px, blocks, max_px, iterations, pp_prior,
                                                 rel_tol)))
    fs = [r["focal"] if pp_prior is None else (r["focal"], *r["pp"]) for r in res if r["frames"] >= 3]
    return fs, sum(r["iterations"] for r in res)


def principal_point(tracks, ba: dict[str, Any], K: np.ndarray, size: tuple[int, int], *, robust_px: float = 1.0,
                    blocks: int = 5, prior_frac: float = 0.05, iterations: int = 300,
                    block_iterations: int = 60, max_sigma: float | None = None,
                    job_map: Callable[..., Any] = map) -> dict[str, Any]:
    """The principal point (with one shared focal length, square pixels) from a focal-only bundle
    adjustment's solution ``ba`` (T, pts of ``tracks``) at K: the adjustment repeated with the
    principal point free, pulled towards K's (the image centre) by a prior of ``prior_frac`` x the
    image size (W, H); its uncertainty per axis is the quadrature sum of the jackknife spread over
    ``blocks`` contiguous frame blocks left out (:func:`_jackknife`) and the formal marginal std
    (:func:`formal_cov`, which holds the prior: where the motion says nothing it stays ~ the
    prior's width). Returns {pp (2,), focal, sigma (2,), sigma_blocks, sigma_formal (px),
    rel_sigma_blocks, rel_sigma_formal (of f), T, pts (the joint solution), iterations}. The joint
    adjustment runs to a relative cost decrease of 1e-9 (at most ``iterations``), the block
    adjustments at most ``block_iterations``:
    the principal point moves with f and the rotations along a flat valley, where LM's default
    tolerance (1e-5) stopped the off-centre loop with cy 1.5 px short of the minimum it reaches from
    the true point (at a lower residual). With ``max_sigma`` (a fraction of the image size): when the
    formal std alone exceeds it on an axis, the block adjustments are skipped (sigma_blocks None,
    sigma = the formal std): the std is at least the formal one, so the principal point is not
    determined whatever they give (30-frame loop at 160x120: 5 x 60 LM iterations, 17 of 50 s)."""
    c0 = np.asarray(K, np.float64)[:2, 2]
    ba = largest_model(tracks, ba, K)
    # the adjustment weighs every observation as 1 px of noise: the prior is widened by the residuals'
    # robust spread (0.07-0.5 px) so that it pulls as prior_frac x size would against the real noise
    # (unscaled it held the orbit's cy 3.6 px towards the centre at a formal std of 0.65 px)
    err = np.asarray(ba.get("errors", []), np.float64)
    noise = max(1.4826 * float(np.median(err)) / 1.1774, 1e-3) if len(err) else 1.0
    prior = (c0, prior_frac * np.asarray(size, np.float64) / noise)
    joint = adjust_focal(tracks, ba["T"], ba["pts"], K, robust_px=robust_px, iterations=iterations, max_px=2.0,
                         marginal=True, pp_prior=prior, rel_tol=PP_REL_TOL)
    iters = joint["iterations"]
    if not joint["T"]:
        return {"pp": c0, "focal": float(K[0, 0]), "sigma": np.full(2, np.inf), "iterations": iters}
    formal = np.asarray(joint.get("pp_sigma_formal", np.full(2, np.inf)), np.float64)
    decided = max_sigma is not None and not np.all(formal <= max_sigma * np.asarray(size, np.float64))
    est: list[Any] = []
    if not decided:
        est, it = _jackknife(tracks, joint, focal_K(joint["focal"], joint["pp"]), robust_px, blocks, pp_prior=prior,
                             iterations=block_iterations, rel_tol=PP_REL_TOL, job_map=job_map)
        iters += it
    if len(est) >= 3:
        e = np.asarray(est, np.float64)
        b = len(e)
        spread = np.sqrt((b - 1) / b * np.sum((e[:, 1:] - e[:, 1:].mean(axis=0)) ** 2, axis=0))
        rel_b = _jackknife_rel(e[:, 0].tolist())
    else:
        spread, rel_b = np.full(2, np.inf), float("inf")
    return {"pp": joint["pp"], "focal": joint["focal"], "T": joint["T"], "pts": joint["pts"],
            "sigma": formal if decided else np.hypot(spread, formal),
            "sigma_blocks": None if decided else spread,
            "sigma_formal": formal, "rel_sigma_blocks": rel_b, "rel_sigma_formal": joint["rel_sigma_formal"],
            "block_estimates": [list(x) for x in est], "iterations": iters}


def largest_model(tracks, ba: dict[str, Any], K: np.ndarray, max_px: float = 2.0) -> dict[str, Any]:
    """``ba`` (T, pts keyed model * TRACK_KEY + track) restricted to the reconstruction seen by the
    most frames (the lowest model number among equals). Why: with the principal point free, a small
    model (3-7 frames of short baseline) is near-singular, and its indeterminate system stalls the
    joint adjustment of all models (HoloLens walk: 60 LM iterations, the principal point unmoved,
    formal std inf; its largest model alone, 18 of 40 frames, finds cy 0.5 px from the truth)."""
    obs, _ = observations(tracks, ba["T"], ba["pts"], K, max_px)
    frames: dict[int, set[int]] = {}
    for i, o in obs.items():
        frames.setdefault(i // TRACK_KEY, set()).update(f for f, _ in o)
    if len(frames) <= 1:
        return ba
    best = max(sorted(frames), key=lambda m: len(frames[m]))
    return {**ba, "T": {f: v for f, v in ba["T"].items() if f in frames[best]},
            "pts": {i: X for i, X in ba["pts"].items() if i // TRACK_KEY == best}}


def _split_models(tracks, T: dict[int, np.ndarray], pts: dict[int, np.ndarray], K: np.ndarray, max_px: float
                  ) -> dict[int, np.ndarray]:
    """Points re-keyed so that each connected part (frames linked by shared points) of the
    observations within ``max_px`` is its own model (its own gauge in :func:`adjust_focal`)."""
    obs, _ = observations(tracks, T, pts, K, max_px)
    uf = UnionFind()
    for o in obs.values():
        for f, _ in o[1:]:
            uf.union((o[0][0], 0), (f, 0))
    roots = sorted({uf.find((o[0][0], 0)) for o in obs.values()})
    comp = {r: k for k, r in enumerate(roots)}
    return {i + comp[uf.find((o[0][0], 0))] * 1000 * TRACK_KEY: pts[i] for i, o in obs.items()}
