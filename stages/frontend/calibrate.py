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
   reconstruction where the track chain breaks), then a gtsam bundle adjustment of all
   reconstructions with one shared focal length (``Cal3f``; two rounds, the second on the
   observations within 2 px); repeated from its f while that moves > 1 %; finally one adjustment
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

Pure: arrays in, a dict out; deterministic (OpenCV's RANSAC seeded; SIFT, gtsam, scipy are).
Units: pixels at the frames' (working) resolution.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Sequence

import cv2
import numpy as np

from gcvd_flow.stages.frontend.params import CalibrateSettings, settings_with

log = logging.getLogger(__name__)

RANSAC_SEED = 1234
SIFT_RATIO = 0.8
# The user's mask (--masks) grows by this many px before keypoints are kept off it: a SIFT keypoint's
# rounded location and the centre of its descriptor's support stay off the masked pixels.
MASK_DILATE_PX = 4
# ... and a keypoint whose blob (MASK_SUPPORT x its SIFT size, the diameter OpenCV reports) reaches a
# masked pixel is dropped too: a large-scale keypoint next to the mask describes the masked content
# (an image-fixed patch's edge then makes an image-fixed track).
MASK_SUPPORT = 1.0
TRACK_KEY = 1_000_000  # point key = model * TRACK_KEY + track index (several reconstructions)


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


def usable(keep: np.ndarray, dilate_px: int = MASK_DILATE_PX) -> np.ndarray:
    """The user's kept mask (H, W), 1 = not masked -> uint8 (H, W), 1 = a keypoint may sit here:
    kept and more than ``dilate_px`` px (Chebyshev) from any masked pixel, so that neither a
    keypoint's rounded location nor the core of its descriptor's support is on the mask."""
    k = (np.asarray(keep) > 0).astype(np.uint8)
    return cv2.erode(k, np.ones((2 * dilate_px + 1,) * 2, np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=1)


def _features(img: np.ndarray, n_features: int, keep: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """SIFT keypoints (M, 2) px and descriptors (M, 128) of an image: the ``n_features`` strongest.
    With ``keep`` (the user's kept mask (H, W), 1 = not masked) the strongest among those not
    on or within MASK_DILATE_PX of a masked pixel and whose blob (MASK_SUPPORT x size) reaches
    none: OpenCV keeps its n strongest *before* it applies a detection mask, so a textured masked
    area would otherwise take the budget; here the cap comes after the mask."""
    gray = img if img.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(img, np.uint8), cv2.COLOR_RGB2GRAY)
    if keep is None:
        sift = cv2.SIFT_create(nfeatures=n_features, contrastThreshold=0.02)  # type: ignore[attr-defined]
        kp, des = sift.detectAndCompute(gray, None)
        return np.asarray([k.pt for k in kp], np.float64).reshape(-1, 2), des
    sift = cv2.SIFT_create(nfeatures=0, contrastThreshold=0.02)  # type: ignore[attr-defined]
    ok = usable(keep)
    kp = sift.detect(gray, ok)
    if kp:
        h, w = ok.shape
        pts = np.asarray([k.pt for k in kp], np.float64).reshape(-1, 2)
        xi = np.clip(np.round(pts[:, 0]).astype(np.int64), 0, w - 1)
        yi = np.clip(np.round(pts[:, 1]).astype(np.int64), 0, h - 1)
        # px from each pixel to the nearest masked one (L2; large where nothing is masked)
        dist = cv2.distanceTransform((np.asarray(keep) > 0).astype(np.uint8), cv2.DIST_L2, 5)
        size = np.asarray([k.size for k in kp], np.float64)
        sel = np.flatnonzero((ok[yi, xi] > 0) & (dist[yi, xi] > MASK_SUPPORT * size))
        order = sel[np.argsort(-np.asarray([kp[i].response for i in sel]), kind="stable")][:n_features]
        kp = [kp[i] for i in order]
    if not kp:
        return np.zeros((0, 2), np.float64), None
    kp, des = sift.compute(gray, kp)
    return np.asarray([k.pt for k in kp], np.float64).reshape(-1, 2), des


class _Knn:
    """Ratio-test matches of feature pairs, each pair matched once (frame selection, pair geometry
    and tracks ask for the same pairs): {(id(desc a), id(desc b)): (ia, ib) keypoint indices}."""

    def __init__(self):
        self.cache: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, fa, fb) -> tuple[np.ndarray, np.ndarray]:
        (pa, da), (pb, db) = fa, fb
        if da is None or db is None or len(pa) < 8 or len(pb) < 8:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        key = (id(da), id(db))
        if key not in self.cache:
            knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
            # one match per keypoint of b (the first in a's order): duplicates bias the fit
            best: dict[int, int] = {}
            for m in knn:
                if len(m) == 2 and m[0].distance < SIFT_RATIO * m[1].distance and m[0].trainIdx not in best:
                    best[m[0].trainIdx] = m[0].queryIdx
            self.cache[key] = (np.asarray(list(best.values()), np.int64), np.asarray(list(best.keys()), np.int64))
        return self.cache[key]


def _match(fa, fb, knn: _Knn | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Matched pixel positions (x_a, x_b), (M, 2) each, of two frames' features."""
    ia, ib = (knn or _Knn())(fa, fb)
    return fa[0][ia].reshape(-1, 2), fb[0][ib].reshape(-1, 2)


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


# ------------------------------------------------------------------------------ multi-view


class _UnionFind:
    def __init__(self):
        self.parent: dict[tuple[int, int], tuple[int, int]] = {}

    def find(self, x):
        self.parent.setdefault(x, x)
        while self.parent[x] != x:
            self.parent[x] = self.parent[self.parent[x]]
            x = self.parent[x]
        return x

    def union(self, a, b):
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[max(ra, rb)] = min(ra, rb)


def _inlier_matches(fa, fb, ransac_px: float, min_inliers: int, knn: _Knn | None = None
                    ) -> tuple[np.ndarray, np.ndarray] | None:
    """Keypoint indices (ia, ib) of a pair's ratio-test matches that a RANSAC F keeps."""
    ia, ib = (knn or _Knn())(fa, fb)
    if len(ia) < min_inliers:
        return None
    cv2.setRNGSeed(RANSAC_SEED)
    F, inl = cv2.findFundamentalMat(fa[0][ia], fb[0][ib], cv2.FM_RANSAC, ransac_px, 0.999, 5000)
    if F is None or inl is None:
        return None
    keep = inl.ravel().astype(bool)
    return (ia[keep], ib[keep]) if keep.sum() >= min_inliers else None


def build_tracks(feats: list, ransac_px: float = 1.0, min_inliers: int = 20,
                 offsets: Sequence[int] = (1, 2, 3), knn: _Knn | None = None) -> list[dict[int, np.ndarray]]:
    """Features of the sampled frames (positions (K, 2) px, descriptors) -> tracks: {frame position:
    pixel (2,)} seen in >= 3 frames, from RANSAC-verified matches chained over frame pairs; a track
    claiming two keypoints in one frame is dropped."""
    uf = _UnionFind()
    for a in range(len(feats)):
        for off in offsets:
            b = a + off
            if b >= len(feats):
                break
            m = _inlier_matches(feats[a], feats[b], ransac_px, min_inliers, knn)
            if m is None:
                continue
            for i, j in zip(*m):
                uf.union((a, int(i)), (b, int(j)))
    groups: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for node in sorted(uf.parent):
        groups.setdefault(uf.find(node), []).append(node)
    tracks = []
    for nodes in groups.values():
        frames = [f for f, _ in nodes]
        if len(nodes) < 3 or len(set(frames)) != len(frames):
            continue
        tracks.append({f: feats[f][0][k] for f, k in nodes})
    return tracks


def select_tracks(tracks: list[dict[int, np.ndarray]], size: tuple[int, int], per_frame: int,
                  grid: tuple[int, int] = (8, 6)) -> list[dict[int, np.ndarray]]:
    """At most about ``per_frame`` tracks per frame, spread over the image: each frame's tracks are
    binned into a ``grid`` = (columns, rows) of cells over ``size`` = (W, H) px and every cell keeps
    its longest ones (ties: the earlier track) up to its share; the result is the union over frames,
    in the original order. Bounds the bundle adjustments' work on richly textured clips (thousands
    of SIFT tracks) while keeping every frame registered and the points spread over the image."""
    if per_frame <= 0:
        return tracks
    gx, gy = grid
    per_cell = max(1, int(np.ceil(per_frame / (gx * gy))))
    W, H = size
    by_cell: dict[tuple[int, int, int], list[tuple[int, int]]] = {}
    for i, t in enumerate(tracks):
        for f, uv in t.items():
            cx = min(gx - 1, max(0, int(uv[0] * gx / W)))
            cy = min(gy - 1, max(0, int(uv[1] * gy / H)))
            by_cell.setdefault((f, cx, cy), []).append((-len(t), i))
    keep: set[int] = set()
    for cell in sorted(by_cell):
        keep.update(i for _, i in sorted(by_cell[cell])[:per_cell])
    return [tracks[i] for i in sorted(keep)]


def _triangulate(P1: np.ndarray, P2: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    X = cv2.triangulatePoints(P1, P2, x1.T.astype(np.float64), x2.T.astype(np.float64))
    return (X[:3] / X[3:]).T


def _project(K: np.ndarray, T_c_w: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) -> (pixels (N, 2), depth (N,)) in the camera T_c_w (world-to-camera)."""
    Xc = X @ T_c_w[:3, :3].T + T_c_w[:3, 3]
    p = Xc @ K.T
    return p[:, :2] / p[:, 2:3], Xc[:, 2]


def incremental_reconstruction(tracks: list[dict[int, np.ndarray]], n_frames: int, K: np.ndarray,
                               min_parallax_px: float, max_px: float = 3.0, min_points: int = 12,
                               refine: Any = None, exclude: frozenset = frozenset()
                               ) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray], np.ndarray]:
    """A small incremental structure from motion at intrinsics K over the frames not in ``exclude``:
    two-view start (the first such frame and the first later one whose median track motion exceeds
    ``min_parallax_px``), then every frame by
    PnP (RANSAC) on the points already triangulated, new points triangulated after each; every time
    the registered frames grew by half, ``refine(T, pts, K) -> (T, pts, K)`` (a bundle adjustment
    with the focal length free: later frames are registered with a better one). Returns (T_c_w
    world-to-camera (4, 4) per registered frame position, point (3,) per track index, K)."""
    T: dict[int, np.ndarray] = {}
    pts: dict[int, np.ndarray] = {}
    start = None
    free = [f for f in range(n_frames) if f not in exclude]
    if len(free) < 2:
        return T, pts, K
    a = free[0]
    for b in free[1:]:
        shared = [t for t in tracks if a in t and b in t]
        if len(shared) < 2 * min_points:
            break
        x1 = np.array([t[a] for t in shared])
        x2 = np.array([t[b] for t in shared])
        start = (b, x1, x2)
        if np.median(np.linalg.norm(x2 - x1, axis=1)) >= min_parallax_px:
            break
    if start is None:
        return T, pts, K
    b, x1, x2 = start
    cv2.setRNGSeed(RANSAC_SEED)
    E, inl = cv2.findEssentialMat(x1, x2, K, cv2.RANSAC, 0.999, 1.0)
    if E is None or E.shape != (3, 3):
        return T, pts, K
    _, R, t, _ = cv2.recoverPose(E, x1, x2, K, mask=inl)
    T[a] = np.eye(4)
    T[b] = np.eye(4)
    T[b][:3, :3], T[b][:3, 3] = R, t.ravel()
    _add_points(tracks, T, pts, K, max_px)
    next_refine = 6
    while True:
        best, best_n = None, 0
        for f in free:
            if f in T:
                continue
            n = sum(1 for i, t in enumerate(tracks) if f in t and i in pts)
            if n > best_n:
                best, best_n = f, n
        if best is None or best_n < min_points:
            break
        ids = [i for i, t in enumerate(tracks) if best in t and i in pts]
        obj = np.array([pts[i] for i in ids]); img = np.array([tracks[i][best] for i in ids])
        ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K, None, iterationsCount=200, reprojectionError=max_px,
                                                 confidence=0.999, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok or inl is None or len(inl) < min_points:
            T[best] = None  # type: ignore[assignment]  # tried: never again
            continue
        Tb = np.eye(4)
        Tb[:3, :3], Tb[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        T[best] = Tb
        _add_points(tracks, T, pts, K, max_px)
        n_reg = sum(v is not None for v in T.values())
        if refine is not None and n_reg >= next_refine:
            next_refine = int(np.ceil(n_reg * 1.5))
            good = {f: v for f, v in T.items() if v is not None}
            good, pts, K = refine(good, pts, K)
            T = {f: good.get(f) for f in T}
    return {f: v for f, v in T.items() if v is not None}, pts, K


def _add_points(tracks, T, pts, K, max_px: float) -> None:
    """Triangulate tracks not yet triangulated that two registered frames see (the pair furthest
    apart in the track), if the point lies in front of both and reprojects within ``max_px``."""
    for i, t in enumerate(tracks):
        if i in pts:
            continue
        fs = [f for f in t if T.get(f) is not None]
        if len(fs) < 2:
            continue
        a, b = min(fs), max(fs)
        X = _triangulate(K @ T[a][:3], K @ T[b][:3], t[a][None], t[b][None])[0]
        ok = True
        for f in (a, b):
            p, z = _project(K, T[f], X[None])
            if z[0] <= 0 or np.linalg.norm(p[0] - t[f]) > max_px:
                ok = False
        if ok:
            pts[i] = X


def bundle_adjust_focal(tracks, T: dict[int, np.ndarray], pts: dict[int, np.ndarray], K: np.ndarray,
                        robust_px: float = 1.0, iterations: int = 50, max_px: tuple[float, ...] = (10.0, 2.0)
                        ) -> dict[str, Any]:
    """Rounds of :func:`_adjust`: each keeps the observations that the previous solution (first: the
    initial reconstruction) explains within ``max_px[r]`` px, in front of the camera."""
    out: dict[str, Any] = {}
    n_iter = 0
    for px in max_px:
        out = _adjust(tracks, T, pts, K, robust_px=robust_px, iterations=iterations, max_px=px)
        n_iter += out["iterations"]
        if not out["T"]:
            break
        T = out["T"]  # world-to-camera
        pts = out["pts"]
        K = _K(out["focal"], np.asarray(K)[:2, 2])
    out["iterations"] = n_iter  # of all rounds
    return out


def _observations(tracks, T: dict[int, np.ndarray], pts: dict[int, np.ndarray], K: np.ndarray, max_px: float
                  ) -> tuple[dict[int, list[tuple[int, np.ndarray]]], dict[int, int]]:
    """The observations a bundle adjustment uses: of each point, the registered frames where it lies
    in front and reprojects within ``max_px`` (at least two); frames seeing fewer than 8 points are
    left out (their pose would be undetermined). Returns ({point key: [(frame, uv (2,))]},
    {frame: observation count})."""
    cand: dict[int, list[tuple[int, np.ndarray]]] = {}  # frame -> [(point key, uv)]
    for i in sorted(pts):
        for f, uv in tracks[i % TRACK_KEY].items():
            if f in T:
                cand.setdefault(f, []).append((i, uv))
    good: dict[int, list[tuple[int, np.ndarray]]] = {}
    for f in sorted(cand):  # all of a frame's candidates projected at once
        keys = [i for i, _ in cand[f]]
        uv = np.array([u for _, u in cand[f]], np.float64)
        p, z = _project(K, T[f], np.array([pts[i] for i in keys]))
        ok = (z > 1e-9) & (np.linalg.norm(p - uv, axis=1) <= max_px)
        for k in np.flatnonzero(ok):
            good.setdefault(keys[k], []).append((f, uv[k]))
    obs = {i: sorted(o, key=lambda x: x[0]) for i, o in sorted(good.items()) if len(o) >= 2}
    while True:
        count: dict[int, int] = {}
        for o in obs.values():
            for f, _ in o:
                count[f] = count.get(f, 0) + 1
        weak = {f for f, n in count.items() if n < 8}
        if not weak:
            return obs, count
        obs = {i: [(f, uv) for f, uv in o if f not in weak] for i, o in obs.items()}
        obs = {i: o for i, o in obs.items() if len(o) >= 2}


def _adjust(tracks, T: dict[int, np.ndarray], pts: dict[int, np.ndarray], K: np.ndarray,
            robust_px: float, iterations: int, max_px: float, marginal: bool = False,
            pp_prior: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, Any]:
    """gtsam bundle adjustment with one shared focal length (Cal3f: fx = fy, principal point fixed):
    poses, points and f. ``pts`` keys are model * TRACK_KEY + track: several disconnected
    reconstructions (models) of one camera share the focal length. Gauge of each model: its first
    pose and its first point are held by tight priors (the point fixes the scale). With
    ``pp_prior`` = (centre (2,), sigma (2,) px) the principal point is free too (Cal3_S2 with square
    pixels: fx = fy and no skew held by tight factors), pulled towards ``centre`` by a Gaussian
    prior of ``sigma``; it starts at K's. Its gauge is minimal (the first pose and its distance to
    the model's furthest camera): a point held in place fixes its bearing, which held the principal
    point of a planar-motion clip where it started (orbit: cy 5.3 px off at a formal std of 0.03 px).
    Returns {focal, pp (2,), median_px, observations, points,
    frames, iterations (LM), T (world-to-camera (4, 4) per frame), pts, errors (reprojection error
    per observation, px), with ``marginal`` rel_sigma_formal (:func:`_formal_cov`) and, with
    ``pp_prior``, pp_sigma_formal (2,) px}."""
    import gtsam

    C = lambda k: gtsam.symbol("c", k)  # noqa: E731
    P = lambda k: gtsam.symbol("p", k)  # noqa: E731
    KEY = gtsam.symbol("k", 0)
    graph = gtsam.NonlinearFactorGraph()
    vals = gtsam.Values()
    noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(robust_px),
                                           gtsam.noiseModel.Isotropic.Sigma(2, 1.0))
    obs, count = _observations(tracks, T, pts, K, max_px)
    frames = sorted(count)
    if len(frames) < 3 or not obs:
        return {"focal": float(K[0, 0]), "pp": np.asarray(K)[:2, 2].copy(), "median_px": 0.0, "observations": 0,
                "points": 0, "frames": len(frames), "iterations": 0, "T": {}, "pts": {}, "errors": np.zeros(0)}
    for fr in frames:
        vals.insert(C(fr), gtsam.Pose3(np.linalg.inv(T[fr])))
    if pp_prior is None:
        vals.insert(KEY, gtsam.Cal3f(float(K[0, 0]), float(K[0, 2]), float(K[1, 2])))
        factor: Any = gtsam.GeneralSFMFactor2Cal3f
    else:
        vals.insert(KEY, gtsam.Cal3_S2(float(K[0, 0]), float(K[0, 0]), 0.0, float(K[0, 2]), float(K[1, 2])))
        factor = gtsam.GeneralSFMFactor2Cal3_S2
        _add_pp_factors(graph, KEY, float(K[0, 0]), pp_prior)
    n_obs = 0
    ids = sorted(obs)
    for i in ids:
        vals.insert(P(i), gtsam.Point3(*pts[i]))
        for fr, uv in obs[i]:
            graph.add(factor(gtsam.Point2(*uv), noise, C(fr), P(i), KEY))
            n_obs += 1
    model_frames: dict[int, set[int]] = {}
    for i in ids:
        model_frames.setdefault(i // TRACK_KEY, set()).update(f for f, _ in obs[i])
    for m, fs in model_frames.items():
        f0 = min(fs)
        graph.add(gtsam.PriorFactorPose3(C(f0), gtsam.Pose3(np.linalg.inv(T[f0])), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        if pp_prior is not None:  # a minimal gauge: a point held fixed would also hold the principal point
            far = max(fs, key=lambda fr: float(np.linalg.norm(_centre(T[fr]) - _centre(T[f0]))))
            dist = float(np.linalg.norm(_centre(T[far]) - _centre(T[f0])))
            if dist > 1e-9:
                graph.add(gtsam.RangeFactorPose3(C(f0), C(far), dist, gtsam.noiseModel.Isotropic.Sigma(1, 1e-6 * dist)))
                continue
        i0 = next(i for i in ids if i // TRACK_KEY == m)
        graph.add(gtsam.PriorFactorPoint3(P(i0), gtsam.Point3(*pts[i0]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, vals, params)
    res = opt.optimize()
    if pp_prior is None:
        f, pp = float(res.atCal3f(KEY).fx()), np.asarray(K)[:2, 2].copy()
    else:
        cal = res.atCal3_S2(KEY)
        f, pp = 0.5 * float(cal.fx() + cal.fy()), np.array([cal.px(), cal.py()], np.float64)
    poses = {fr: np.linalg.inv(res.atPose3(C(fr)).matrix()) for fr in frames}
    points = {i: np.asarray(res.atPoint3(P(i))) for i in ids}
    err = _obs_errors(_K(f, pp), poses, points, obs)
    out = {"focal": f, "pp": pp, "median_px": float(np.median(err)), "observations": n_obs, "points": len(ids),
           "frames": len(frames), "iterations": int(opt.iterations()), "T": poses, "pts": points, "errors": err}
    if marginal:
        cov = _formal_cov(graph, res, KEY, [P(i) for i in ids], C(frames[0]), err)
        out["rel_sigma_formal"] = float(np.sqrt(cov[0, 0]) / f) if cov is not None else float("inf")
        if pp_prior is not None:
            out["pp_sigma_formal"] = np.sqrt(np.diag(cov)[3:5]) if cov is not None else np.full(2, np.inf)
    return out


def _centre(T_c_w: np.ndarray) -> np.ndarray:
    """Camera centre (3,) in the world of a world-to-camera pose (4, 4)."""
    return -T_c_w[:3, :3].T @ T_c_w[:3, 3]


def _add_pp_factors(graph, key: int, f: float, pp_prior: tuple[np.ndarray, np.ndarray]) -> None:
    """The Cal3_S2 of :func:`_adjust` with a free principal point: fx = fy (square pixels, a tight
    factor on fx - fy), no skew, the principal point pulled to ``centre`` with ``sigma`` px
    (``pp_prior``); fx and fy themselves free (a prior 10 x f wide)."""
    import gtsam

    centre, sigma = (np.asarray(v, np.float64) for v in pp_prior)
    graph.add(gtsam.PriorFactorCal3_S2(key, gtsam.Cal3_S2(f, f, 0.0, float(centre[0]), float(centre[1])),
                                       gtsam.noiseModel.Diagonal.Sigmas(
                                           np.array([10 * f, 10 * f, 1e-4, float(sigma[0]), float(sigma[1])]))))

    def square(this, values, jacobians):  # fx - fy; Cal3_S2's tangent is (fx, fy, s, u0, v0)
        cal = values.atCal3_S2(this.keys()[0])
        if jacobians is not None:
            jacobians[0] = np.array([[1.0, -1.0, 0.0, 0.0, 0.0]])
        return np.array([cal.fx() - cal.fy()])

    graph.add(gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, 1e-3), [key], square))


def _formal_cov(graph, res, key: int, point_keys: list[int], first_pose: int, err: np.ndarray
                ) -> np.ndarray | None:
    """Marginal covariance (px^2) of the calibration ``key`` (Cal3f: (1, 1), f; Cal3_S2: (5, 5), fx,
    fy, skew, cx, cy) from the sparse Gauss-Newton information (gtsam Marginals), scaled by the
    robust residual spread. Small on real clips (f: 0.01-0.1 % where the errors were 1-3 %), but
    large where the motion leaves f unobservable (pure forward translation: the cost is flat along
    f), which the perturbation terms of :func:`_uncertainty` cannot see. Weak priors on the points
    (10 x the scene's size) keep a point seen from nearly one place from making the system
    indeterminate. None when it cannot be computed."""
    import gtsam

    s = max(1.4826 * float(np.median(err)) / 1.1774, 1e-3)  # |r| of a 2-D Gaussian: median = 1.1774 sigma
    origin = res.atPose3(first_pose).translation()
    size = float(np.median([np.linalg.norm(res.atPoint3(k) - origin) for k in point_keys]))
    g = gtsam.NonlinearFactorGraph(graph)
    for k in point_keys:
        g.add(gtsam.PriorFactorPoint3(k, res.atPoint3(k), gtsam.noiseModel.Isotropic.Sigma(3, 10.0 * max(size, 1e-9))))
    try:
        cov = np.atleast_2d(np.asarray(gtsam.Marginals(g, res).marginalCovariance(key), np.float64))
    except RuntimeError:
        return None
    if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) <= 0):
        return None
    return cov * s * s


def _obs_errors(K: np.ndarray, T: dict[int, np.ndarray], pts: dict[int, np.ndarray],
                obs: dict[int, list[tuple[int, np.ndarray]]]) -> np.ndarray:
    """Reprojection errors (px) of every observation, points in key order and each point's
    observations in order; 1000 px where a point lies behind the camera. Each frame's observations
    are projected at once."""
    rows = [(i, f, uv) for i in sorted(obs) for f, uv in obs[i]]
    out = np.empty(len(rows))
    by_frame: dict[int, list[int]] = {}
    for k, (_, f, _) in enumerate(rows):
        by_frame.setdefault(f, []).append(k)
    for f, ks in by_frame.items():
        p, z = _project(K, T[f], np.array([pts[rows[k][0]] for k in ks]))
        e = np.linalg.norm(p - np.array([rows[k][2] for k in ks]), axis=1)
        out[ks] = np.where(z > 1e-9, e, 1e3)
    return out


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
                      min_frames: int = 20, knn: _Knn | None = None,
                      keep: Sequence[np.ndarray] | None = None) -> tuple[list[int], list]:
    """Frames spaced by image motion rather than by index: from each chosen frame, the next is the
    last one whose matches moved less than ``target_frac`` x the long side (median) while still
    sharing enough matches. A slow clip is thinned, a fast one (wide baseline) keeps every frame.
    Candidates: at most 4 x ``max_frames`` frames, evenly; at most ``max_frames`` are kept
    (evenly among the chosen); fewer than ``min_frames``: the spacing is halved (up to 3 times).
    ``keep``: the user's kept masks of ``images`` (:func:`_features`), None without.
    Returns (indices into ``images``, their features)."""
    cand = _sample(len(images), 4 * max_frames)
    feats: dict[int, Any] = {}

    def feat(i: int):
        if i not in feats:
            feats[i] = _features(np.asarray(images[cand[i]]), n_features, None if keep is None else keep[cand[i]])
        return feats[i]

    target = target_frac * max(np.asarray(images[cand[0]]).shape[:2])
    for _ in range(4):  # too few frames for a reconstruction: halve the spacing
        chosen = _chosen(feat, len(cand), target, knn or _Knn())
        if len(chosen) >= min(min_frames, len(cand)):
            break
        target /= 2
    if len(chosen) > max_frames:
        chosen = [chosen[k] for k in _sample(len(chosen), max_frames)]
    return [cand[k] for k in chosen], [feat(k) for k in chosen]


def _chosen(feat: Any, n: int, target: float, knn: _Knn) -> list[int]:
    """Greedy spacing of :func:`_select_by_motion` over candidate positions 0..n-1."""
    chosen, a = [0], 0
    while a < n - 1:
        nxt = a + 1
        for b in range(a + 1, n):
            x1, x2 = _match(feat(a), feat(b), knn)
            if len(x1) < 60 or np.median(np.linalg.norm(x2 - x1, axis=1)) >= target:
                nxt = max(a + 1, b if len(x1) >= 60 else b - 1)
                break
            nxt = b
        chosen.append(nxt)
        a = nxt
    return chosen


def estimate_focal(images: Sequence[np.ndarray], K_guess: np.ndarray, settings: CalibrateSettings | None = None, *,
                   min_pairs: int = 6, robust_px: float = 1.0, ransac_px: float = 1.0, rotation_share: float = 0.7,
                   passes: int = 4, motion_frac: float = 0.05, blocks: int = 5, max_forward_share: float = 0.8,
                   keep: Sequence[np.ndarray] | None = None, pp_prior: float = 0.05, pp_use_all: bool = False,
                   **overrides: Any) -> dict[str, Any]:
    """Frames (N x uint8 (H, W, 3) RGB, working resolution) + the guessed K (3, 3) -> {
    focal (px, working resolution; the guess when not determined), determined (bool),
    rel_sigma (std of f / f: the spread over leave-one-block-out re-estimates, :func:`_jackknife`),
    method ("bundle adjustment" | "rotation"), pairs, rotation_pairs, frames (registered), points,
    tracks, median_px, iterations (LM iterations of all bundle adjustments), block_focals,
    pp_focals, rel_sigma_blocks / _pp / _formal (the terms of rel_sigma), forward_share
    (:func:`forward_share`), reason (why not determined, '' when determined)}. The principal point
    is K_guess's: not determined (the guess is kept, with the reason) when rel_sigma_motion (the
    blocks and formal terms) exceeds ``max_rel_sigma`` or a share >= ``max_forward_share`` of the steps between registered frames
    moves along the optical axis (forward-only motion: KITTI 1.0, HoloLens walk 0.41, ICL 0).

    Mostly-rotating clips (a share >= ``rotation_share`` of the frame pairs explained by a
    homography) are solved from the pairs' homographies (H = K R K^-1); all others by a small
    structure from motion at the guess followed by a bundle adjustment with the focal length free
    (repeated from its result, at most ``passes`` times, while that moves by more than 1 %), on at
    most about ``tracks_per_frame`` tracks per frame (:func:`select_tracks`).

    ``keep``: the user's kept masks (--masks) of the frames, N x (H, W), 1 = not masked, or None:
    no feature on (or within MASK_DILATE_PX of) a masked pixel, so no pair, track or bundle
    adjustment sees one (:func:`_features`).

    ``settings``: the calibrate stage's :class:`CalibrateSettings` (None: its defaults), with
    ``overrides`` by field name; ``mode`` is the caller's (whether to estimate at all)."""
    cfg = settings_with(CalibrateSettings, settings, overrides)
    c = np.asarray(K_guess, np.float64)[:2, 2].copy()
    f_guess = float(K_guess[0, 0])
    knn = _Knn()
    sel, feats = _select_by_motion(images, cfg.max_frames, cfg.features, motion_frac, knn=knn, keep=keep)
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
        return out
    size = np.asarray(images[sel[0]]).shape[1::-1]
    if n_rot >= rotation_share * len(pairs):
        f, rel = _rotation_focal([g for g in pairs if g.kind == "rotation"], c, f_guess, blocks, cfg.pp_frac, size, out)
        out.update(frames=len(sel))
    else:
        f, rel = _tracks_focal(feats, len(sel), c, f_guess, size, cfg, out, ransac_px=ransac_px, knn=knn,
                               robust_px=robust_px, passes=passes, blocks=blocks)
    out["rel_sigma"] = rel
    ba, polish = out.pop("_ba", None), out.pop("_polish", None)
    if _focal_determined(f, rel, f_guess, out, cfg.max_rel_sigma, max_forward_share):
        out.update(focal=float(f), determined=True, reason="")
        _principal_point_step(polish if pp_use_all and polish is not None else ba, f, c, size, cfg, out,
                              robust_px=robust_px, blocks=blocks, pp_prior=pp_prior)
    else:
        _not_determined(f, rel, out, max_forward_share)
    return out


def _frame_pairs(sel: list[int], feats: list[Any], knn: Any, ransac_px: float) -> list[PairGeometry]:
    """The two-view geometry of each selected frame with its next and next-but-one (the pairs
    with enough matched motion; :func:`pair_geometry`)."""
    pairs = []
    for p in range(len(sel)):
        for off in (1, 2):
            if p + off < len(sel):
                g = pair_geometry(p, p + off, *_match(feats[p], feats[p + off], knn), ransac_px=ransac_px)
                if g is not None:
                    pairs.append(g)
    return pairs


def _tracks_focal(feats: list[Any], n_sel: int, c: np.ndarray, f_guess: float, size: Any, cfg: CalibrateSettings,
                  out: dict[str, Any], *, ransac_px: float, knn: Any, robust_px: float, passes: int,
                  blocks: int) -> tuple[float, float]:
    """(focal, rel_sigma) from tracks over the selected frames: a small structure from motion and
    a bundle adjustment with the focal length free (:func:`_sfm_focal`); rel_sigma inf when it
    registered fewer than max(3, a quarter of) the frames."""
    all_tracks = build_tracks(feats, ransac_px=ransac_px, knn=knn)
    tracks = select_tracks(all_tracks, size, cfg.tracks_per_frame)
    out["tracks"] = len(tracks)
    f, rel = _sfm_focal(tracks, all_tracks, n_sel, c, f_guess, robust_px, passes, 0.04 * max(size), blocks,
                        cfg.pp_frac, size, out)
    if out["frames"] < max(3, 0.25 * n_sel):
        rel = float("inf")  # a reconstruction of a few frames says nothing about the clip's camera
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
                          *, robust_px: float, blocks: int, pp_prior: float) -> None:
    """With the focal length determined: the principal point per ``cfg.principal_point``
    (:func:`_estimate_pp` from the adjustment ``ba``; none from a rotating camera's homographies)."""
    if cfg.principal_point == "auto" and ba is not None:
        _estimate_pp(ba, _K(f, c), size, robust_px, blocks, cfg.pp_max_sigma, pp_prior, out)
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
                 blocks: int, max_sigma: float, prior_frac: float, out: dict[str, Any], min_z: float = 3.0) -> None:
    """The principal point decision of :func:`estimate_focal` (the focal length is determined): the
    estimate of :func:`principal_point` is used (with its focal length) when its std per axis is
    within ``max_sigma`` x the image size and it lies more than ``min_z`` std from the centre;
    within ``min_z`` std the centre is kept (the motion confirms it, no warning); a larger std keeps
    the centre with a reason (pp_reason: the caller warns). Fills out's principal_point,
    pp_estimate, pp_sigma (px), pp_sigma_blocks / _formal, pp_z, pp_estimated, pp_reason and, when
    used, focal and rel_sigma (the joint adjustment's spreads and the principal-point term scaled
    to the estimate's std)."""
    tracks, ba = ba_tracks
    c0 = K[:2, 2]
    res = principal_point(tracks, ba, K, size, robust_px=robust_px, blocks=blocks, prior_frac=prior_frac)
    out["iterations"] = out.get("iterations", 0) + res["iterations"]
    sig = np.asarray(res["sigma"], np.float64)
    est = np.asarray(res["pp"], np.float64)
    z = float(np.hypot(*((est - c0) / np.maximum(sig, 1e-9)))) if np.all(np.isfinite(sig)) else 0.0
    out.update(pp_estimate=[float(v) for v in est], pp_sigma=[float(v) for v in sig], pp_z=z,
               pp_sigma_blocks=[float(v) for v in res.get("sigma_blocks", sig)],
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
    sens = np.asarray(out.get("pp_sensitivity", [0.0, 0.0]), np.float64)  # d log f per pp_frac x size
    pp_term = float(np.hypot(*(sens * sig / np.maximum(out.get("pp_frac", 0.02) * np.asarray(size), 1e-9))))
    rel_f = float(np.sqrt(res["rel_sigma_blocks"] ** 2 + res["rel_sigma_formal"] ** 2 + pp_term ** 2))
    out.update(principal_point=[float(v) for v in est], pp_estimated=True, pp_reason="", focal=float(res["focal"]),
               focal_centre=float(out["focal"]), rel_sigma=rel_f, rel_sigma_blocks=res["rel_sigma_blocks"],
               rel_sigma_formal=res["rel_sigma_formal"], rel_sigma_pp=pp_term)


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
               parallax: float, blocks: int, pp_frac: float, size: tuple[int, int], out: dict[str, Any]
               ) -> tuple[float, float]:
    """Focal length (px) from reconstructions of ``tracks`` (the capped set, :func:`select_tracks`)
    over ``n`` frames, polished by one bundle adjustment over ``all_tracks`` (the cap alone biased
    the synthetic loop's f by 1-2 % towards the guess), and its relative uncertainty
    (:func:`_uncertainty`). Fills out's method, median_px, frames, points, iterations, block_focals,
    pp_focals."""
    f, iters = f_guess, [0]

    def refine(T, pts, K):
        ba = bundle_adjust_focal(tracks, T, pts, K, robust_px=robust_px, max_px=(10.0,))
        iters[0] += ba["iterations"]
        if not ba["T"] or not 0.3 * f_guess < ba["focal"] < 3.0 * f_guess:
            return T, pts, K
        return ba["T"], {**pts, **ba["pts"]}, _K(ba["focal"], c)

    final = None
    for _ in range(passes):
        T, pts, K = _reconstructions(tracks, n, _K(f, c), parallax, refine)
        if len(T) < 3 or len(pts) < 20:
            break
        ba = bundle_adjust_focal(tracks, T, pts, K, robust_px=robust_px)
        iters[0] += ba["iterations"]
        if not ba["T"] or ba["frames"] < out["frames"]:  # a pass that registered fewer frames: stop
            break
        moved = abs(np.log(ba["focal"] / f))
        f, final = ba["focal"], ba
        out.update(method="bundle adjustment", median_px=ba["median_px"], frames=ba["frames"], points=ba["points"])
        if moved < 0.01:
            break
    if final is None:
        out["iterations"] = iters[0]
        return f, float("inf")
    if len(all_tracks) > len(tracks):
        pts_all = _retriangulate(all_tracks, tracks, final, _K(f, c))
        pol = bundle_adjust_focal(all_tracks, final["T"], pts_all, _K(f, c),
                                  robust_px=robust_px, max_px=(2.0,))
        iters[0] += pol["iterations"]
        if pol["T"] and pol["frames"] >= final["frames"] and 0.3 * f_guess < pol["focal"] < 3.0 * f_guess:
            f = pol["focal"]
            out.update(median_px=pol["median_px"], points=pol["points"])
            out["_polish"] = (all_tracks, pol)
    out["_ba"] = (tracks, final)  # for the principal point (estimate_focal pops it)
    out["forward_share"] = forward_share(final["T"])
    rel, it = _uncertainty(tracks, final, _K(f, c), robust_px, blocks, pp_frac, size, out)
    out["iterations"] = iters[0] + it
    return f, rel


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
    for key, o in _observations(ba_tracks, ba["T"], ba["pts"], K, 2.0)[0].items():
        for fr, _ in o:
            model_of.setdefault(fr, key // TRACK_KEY)
    out: dict[int, np.ndarray] = {}
    for m in sorted(set(model_of.values())):
        T = {fr: v for fr, v in ba["T"].items() if model_of.get(fr) == m}
        pts: dict[int, np.ndarray] = {}
        _add_points(tracks, T, pts, K, 2.0)
        out.update({m * TRACK_KEY + i: X for i, X in pts.items()})
    return out


def _uncertainty(tracks, ba: dict[str, Any], K: np.ndarray, robust_px: float, blocks: int, pp_frac: float,
                 size: tuple[int, int], out: dict[str, Any]) -> tuple[float, int]:
    """Relative std of f: the jackknife spread over frame blocks (:func:`_jackknife`) combined with
    how far f moves when the principal point (assumed at the centre) is off by ``pp_frac`` x the
    image's width (x) and height (y) (the bundle adjustment repeated from ``ba`` with it moved). The
    second term is what forward motion cannot separate (KITTI: a principal point 10 px off at
    1226 px moved f 11 %); and the formal std (:func:`_formal_rel_sigma`: where f is unobservable,
    the perturbed adjustments stay where they start). Returns (rel sigma, LM iterations); fills
    out's block_focals, pp_focals, rel_sigma_blocks, rel_sigma_pp, rel_sigma_formal."""
    fs, iters = _jackknife(tracks, ba, K, robust_px, blocks)
    rel_b = _jackknife_rel(fs)
    pp_fs: list[float] = []
    sens: list[float] = []
    for d in (np.array([pp_frac * size[0], 0.0]), np.array([0.0, pp_frac * size[1]])):
        pair = []
        for sign in (1.0, -1.0):  # central difference: both runs gated and converged alike
            Kd = _K(ba["focal"], K[:2, 2] + sign * d)  # from the capped adjustment's own solution
            res = _adjust(tracks, ba["T"], ba["pts"], Kd, robust_px=robust_px, iterations=30,
                          max_px=2.0 + float(np.abs(d).sum()))
            iters += res["iterations"]
            pair.append(float(res["focal"]) if res["T"] else float("nan"))
        pp_fs += pair
        sens.append(abs(np.log(pair[0] / pair[1])) / 2 if all(np.isfinite(pair)) else float("inf"))
    rel_pp = float(np.hypot(sens[0], sens[1]))  # x, y
    formal = _adjust(tracks, ba["T"], ba["pts"], _K(ba["focal"], K[:2, 2]), robust_px=robust_px, iterations=1, max_px=2.0,
                     marginal=True)
    rel_f = float(formal.get("rel_sigma_formal", float("inf")))
    out.update(block_focals=fs, pp_focals=pp_fs, rel_sigma_blocks=rel_b, rel_sigma_pp=rel_pp, rel_sigma_formal=rel_f,
               pp_sensitivity=[float(x) for x in sens])
    return float(np.sqrt(rel_b ** 2 + rel_pp ** 2 + rel_f ** 2)), iters


def _jackknife(tracks, ba: dict[str, Any], K: np.ndarray, robust_px: float, blocks: int,
               max_px: float = 2.0, iterations: int = 10,
               pp_prior: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[list[Any], int]:
    """The final bundle adjustment repeated ``blocks`` times (from its solution), each time without
    one contiguous block of the registered frames. The spread of these focal lengths is the
    estimate's uncertainty: it reflects how much f depends on which motion the clip happens to have
    (near-degenerate stretches, lens and principal-point model error, rolling shutter), which the
    formal covariance (0.01-0.1 % on real clips whose errors were 1-3 %) does not. Where leaving a
    block out splits a reconstruction, each part gets its own gauge. Returns (focal per block that
    kept >= 3 frames, LM iterations); with ``pp_prior`` (the principal point free, :func:`_adjust`)
    the focal lengths are (f, cx, cy) triples."""
    frames = sorted(ba["T"])
    fs, iters = [], 0
    for part in np.array_split(np.asarray(frames), blocks):
        drop = set(part.tolist())
        T = {f: v for f, v in ba["T"].items() if f not in drop}
        pts = _split_models(tracks, T, ba["pts"], K, max_px)
        res = _adjust(tracks, T, pts, K, robust_px=robust_px, iterations=iterations, max_px=max_px, pp_prior=pp_prior)
        iters += res["iterations"]
        if res["frames"] >= 3:
            fs.append(float(res["focal"]) if pp_prior is None else (float(res["focal"]), *map(float, res["pp"])))
    return fs, iters


def principal_point(tracks, ba: dict[str, Any], K: np.ndarray, size: tuple[int, int], *, robust_px: float = 1.0,
                    blocks: int = 5, prior_frac: float = 0.05, iterations: int = 60) -> dict[str, Any]:
    """The principal point (with one shared focal length, square pixels) from a focal-only bundle
    adjustment's solution ``ba`` (T, pts of ``tracks``) at K: the adjustment repeated with the
    principal point free, pulled towards K's (the image centre) by a prior of ``prior_frac`` x the
    image size (W, H); its uncertainty per axis is the quadrature sum of the jackknife spread over
    ``blocks`` contiguous frame blocks left out (:func:`_jackknife`) and the formal marginal std
    (:func:`_formal_cov`, which holds the prior: where the motion says nothing it stays ~ the
    prior's width). Returns {pp (2,), focal, sigma (2,), sigma_blocks, sigma_formal (px),
    rel_sigma_blocks, rel_sigma_formal (of f), iterations}."""
    c0 = np.asarray(K, np.float64)[:2, 2]
    # the adjustment weighs every observation as 1 px of noise: the prior is widened by the residuals'
    # robust spread (0.07-0.5 px) so that it pulls as prior_frac x size would against the real noise
    # (unscaled it held the orbit's cy 3.6 px towards the centre at a formal std of 0.65 px)
    err = np.asarray(ba.get("errors", []), np.float64)
    noise = max(1.4826 * float(np.median(err)) / 1.1774, 1e-3) if len(err) else 1.0
    prior = (c0, prior_frac * np.asarray(size, np.float64) / noise)
    joint = _adjust(tracks, ba["T"], ba["pts"], K, robust_px=robust_px, iterations=iterations, max_px=2.0,
                    marginal=True, pp_prior=prior)
    iters = joint["iterations"]
    if not joint["T"]:
        return {"pp": c0, "focal": float(K[0, 0]), "sigma": np.full(2, np.inf), "iterations": iters}
    Kj = _K(joint["focal"], joint["pp"])
    est, it = _jackknife(tracks, joint, Kj, robust_px, blocks, pp_prior=prior, iterations=15)
    iters += it
    if len(est) >= 3:
        e = np.asarray(est, np.float64)
        b = len(e)
        spread = np.sqrt((b - 1) / b * np.sum((e[:, 1:] - e[:, 1:].mean(axis=0)) ** 2, axis=0))
        rel_b = _jackknife_rel(e[:, 0].tolist())
    else:
        spread, rel_b = np.full(2, np.inf), float("inf")
    formal = np.asarray(joint.get("pp_sigma_formal", np.full(2, np.inf)), np.float64)
    return {"pp": joint["pp"], "focal": joint["focal"], "sigma": np.hypot(spread, formal), "sigma_blocks": spread,
            "sigma_formal": formal, "rel_sigma_blocks": rel_b, "rel_sigma_formal": joint["rel_sigma_formal"],
            "block_estimates": [list(x) for x in est], "iterations": iters}


def _split_models(tracks, T: dict[int, np.ndarray], pts: dict[int, np.ndarray], K: np.ndarray, max_px: float
                  ) -> dict[int, np.ndarray]:
    """Points re-keyed so that each connected part (frames linked by shared points) of the
    observations within ``max_px`` is its own model (its own gauge in :func:`_adjust`)."""
    obs, _ = _observations(tracks, T, pts, K, max_px)
    uf = _UnionFind()
    for o in obs.values():
        for f, _ in o[1:]:
            uf.union((o[0][0], 0), (f, 0))
    roots = sorted({uf.find((o[0][0], 0)) for o in obs.values()})
    comp = {r: k for k, r in enumerate(roots)}
    return {i + comp[uf.find((o[0][0], 0))] * 1000 * TRACK_KEY: pts[i] for i, o in obs.items()}
