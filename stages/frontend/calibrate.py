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
3. Otherwise: tracks (RANSAC-verified matches chained over frames 1-3 apart), a small incremental
   structure from motion at the current f (two-view start, PnP, triangulation; bundle
   adjustments with f free whenever the registered frames grew by half, and a new reconstruction
   where the track chain breaks), then a gtsam bundle adjustment of all reconstructions with one
   shared focal length (``Cal3f``; two rounds, the second on the observations within 2 px);
   repeated from its f while that moves > 1 %. Two-view geometry alone was 8-10 % off on
   handheld footage (near the two-view degenerate configuration); the multi-view adjustment is
   what determines f (docs/benchmarks.md).
4. Uncertainty: the marginal std of f from the dense Gauss-Newton information matrix, scaled by
   the robust residual spread (a lower bound: correlated errors and the principal point are not
   in it). Not determined (the caller keeps the guess and warns): fewer than 6 usable pairs (a
   camera that hardly moves), a reconstruction of < 25 % of the chosen frames, an uncertainty
   above ``max_rel_sigma``, or an estimate outside 0.3-3 x the guess.

Pure: arrays in, a dict out; deterministic (OpenCV's RANSAC seeded; SIFT, gtsam, scipy are).
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


def _inlier_matches(fa, fb, ransac_px: float, min_inliers: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Keypoint indices (ia, ib) of a pair's ratio-test matches that a RANSAC F keeps."""
    (pa, da), (pb, db) = fa, fb
    if da is None or db is None or len(pa) < 8 or len(pb) < 8:
        return None
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    best: dict[int, int] = {}
    for m in knn:
        if len(m) == 2 and m[0].distance < SIFT_RATIO * m[1].distance and m[0].trainIdx not in best:
            best[m[0].trainIdx] = m[0].queryIdx
    if len(best) < min_inliers:
        return None
    ib = np.asarray(list(best.keys()), np.int64)
    ia = np.asarray(list(best.values()), np.int64)
    cv2.setRNGSeed(RANSAC_SEED)
    F, inl = cv2.findFundamentalMat(pa[ia], pb[ib], cv2.FM_RANSAC, ransac_px, 0.999, 5000)
    if F is None or inl is None:
        return None
    keep = inl.ravel().astype(bool)
    return (ia[keep], ib[keep]) if keep.sum() >= min_inliers else None


def build_tracks(feats: list, ransac_px: float = 1.0, min_inliers: int = 20,
                 offsets: Sequence[int] = (1, 2, 3)) -> list[dict[int, np.ndarray]]:
    """Features of the sampled frames (positions (K, 2) px, descriptors) -> tracks: {frame position:
    pixel (2,)} seen in >= 3 frames, from RANSAC-verified matches chained over frame pairs; a track
    claiming two keypoints in one frame is dropped."""
    uf = _UnionFind()
    for a in range(len(feats)):
        for off in offsets:
            b = a + off
            if b >= len(feats):
                break
            m = _inlier_matches(feats[a], feats[b], ransac_px, min_inliers)
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


def _visible(K: np.ndarray, T_c_w: np.ndarray, X: np.ndarray, uv: np.ndarray, max_px: float) -> bool:
    """Point X (3,) in front of camera T_c_w and reprojecting within ``max_px`` of uv."""
    p, z = _project(K, T_c_w, np.asarray(X)[None])
    return bool(z[0] > 1e-9 and np.linalg.norm(p[0] - uv) <= max_px)


def bundle_adjust_focal(tracks, T: dict[int, np.ndarray], pts: dict[int, np.ndarray], K: np.ndarray,
                        robust_px: float = 1.0, iterations: int = 50, max_px: tuple[float, ...] = (10.0, 2.0)
                        ) -> dict[str, Any]:
    """Rounds of :func:`_adjust`: each keeps the observations that the previous solution (first: the
    initial reconstruction) explains within ``max_px[r]`` px, in front of the camera."""
    out: dict[str, Any] = {}
    for px in max_px:
        out = _adjust(tracks, T, pts, K, robust_px=robust_px, iterations=iterations, max_px=px)
        if not out["T"]:
            break
        T = out["T"]  # world-to-camera
        pts = out["pts"]
        K = _K(out["focal"], np.asarray(K)[:2, 2])
    return out


def _observations(tracks, T: dict[int, np.ndarray], pts: dict[int, np.ndarray], K: np.ndarray, max_px: float
                  ) -> tuple[dict[int, list[tuple[int, np.ndarray]]], dict[int, int]]:
    """The observations a bundle adjustment uses: of each point, the registered frames where it lies
    in front and reprojects within ``max_px`` (at least two); frames seeing fewer than 8 points are
    left out (their pose would be undetermined). Returns ({point key: [(frame, uv (2,))]},
    {frame: observation count})."""
    obs: dict[int, list[tuple[int, np.ndarray]]] = {}
    for i in sorted(pts):
        o = [(f, uv) for f, uv in tracks[i % TRACK_KEY].items() if f in T and _visible(K, T[f], pts[i], uv, max_px)]
        if len(o) >= 2:
            obs[i] = o
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
            robust_px: float, iterations: int, max_px: float) -> dict[str, Any]:
    """gtsam bundle adjustment with one shared focal length (Cal3f: fx = fy, principal point fixed):
    poses, points and f. ``pts`` keys are model * TRACK_KEY + track: several disconnected
    reconstructions (models) of one camera share the focal length. Gauge of each model: its first
    pose and its first point are held by tight priors (the point fixes the scale). Returns {focal,
    log_sigma (a function: marginal std of log f, scaled by the robust residual spread), median_px,
    observations, points, frames, T, pts}."""
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
        return {"focal": float(K[0, 0]), "log_sigma": lambda: float("inf"), "median_px": 0.0, "observations": 0,
                "points": 0, "frames": len(frames), "T": {}, "pts": {}, "errors": np.zeros(0)}
    for f in frames:
        vals.insert(C(f), gtsam.Pose3(np.linalg.inv(T[f])))
    cal = gtsam.Cal3f(float(K[0, 0]), float(K[0, 2]), float(K[1, 2]))
    vals.insert(KEY, cal)
    n_obs = 0
    ids = sorted(obs)
    for i in ids:
        vals.insert(P(i), gtsam.Point3(*pts[i]))
        for f, uv in obs[i]:
            graph.add(gtsam.GeneralSFMFactor2Cal3f(gtsam.Point2(*uv), noise, C(f), P(i), KEY))
            n_obs += 1
    model_frames: dict[int, set[int]] = {}
    for i in ids:
        model_frames.setdefault(i // TRACK_KEY, set()).update(f for f, _ in obs[i])
    for m, fs in model_frames.items():
        f0 = min(fs)
        graph.add(gtsam.PriorFactorPose3(C(f0), gtsam.Pose3(np.linalg.inv(T[f0])), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        i0 = next(i for i in ids if i // TRACK_KEY == m)
        graph.add(gtsam.PriorFactorPoint3(P(i0), gtsam.Point3(*pts[i0]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    res = gtsam.LevenbergMarquardtOptimizer(graph, vals, params).optimize()
    f = float(res.atCal3f(KEY).fx())
    calk = res.atCal3f(KEY)
    err = []
    for i in ids:
        X = res.atPoint3(P(i))
        for fr, uv in obs[i]:
            if True:
                cam = gtsam.PinholeCameraCal3f(res.atPose3(C(fr)), calk)
                try:
                    err.append(np.linalg.norm(cam.project(X) - uv))
                except RuntimeError:
                    err.append(1e3)
    err = np.asarray(err)
    s = max(1.4826 * float(np.median(err)) / 1.1774, 1e-3)  # |r| of 2-D Gaussian: median = 1.1774 sigma
    # weak priors on the points (10 x the scene's size) for the marginals only: a point seen from
    # nearly one place has an unbounded depth, which makes the exact system indeterminate
    size = float(np.median([np.linalg.norm(res.atPoint3(P(i)) - res.atPose3(C(frames[0])).translation()) for i in ids]))
    for i in ids:
        graph.add(gtsam.PriorFactorPoint3(P(i), res.atPoint3(P(i)), gtsam.noiseModel.Isotropic.Sigma(3, 10.0 * size)))
    scale = s / f

    def log_sigma() -> float:  # computed on demand: the dense information matrix is the costly part
        var = _marginal_variance(graph, res, [C(fr) for fr in frames] + [P(i) for i in ids], KEY)
        return float(np.sqrt(var) * scale) if np.isfinite(var) else float("inf")

    poses = {fr: np.linalg.inv(res.atPose3(C(fr)).matrix()) for fr in frames}
    points = {i: np.asarray(res.atPoint3(P(i))) for i in ids}
    return {"focal": f, "log_sigma": log_sigma, "median_px": float(np.median(err)), "observations": n_obs,
            "points": len(ids), "frames": len(frames), "T": poses, "pts": points, "errors": err}


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


def _marginal_variance(graph, values, keys: list[int], key: int) -> float:
    """Marginal variance of the 1-D variable ``key`` from the dense Gauss-Newton information matrix
    (``key`` ordered last), solved with a tiny ridge (1e-10 x the largest diagonal) so that a
    nearly indeterminate point does not make the focal length's variance undefined. inf when the
    system cannot be solved."""
    import gtsam

    ordering = gtsam.Ordering()
    for k in keys:
        ordering.push_back(k)
    ordering.push_back(key)
    H, _ = graph.linearize(values).hessian(ordering)
    H = np.asarray(H, np.float64)
    H = H + np.eye(len(H)) * 1e-10 * float(np.max(np.diag(H)))
    e = np.zeros(len(H))
    e[-1] = 1.0
    try:
        x = np.linalg.solve(H, e)
    except np.linalg.LinAlgError:
        return float("inf")
    return float(x[-1]) if np.isfinite(x[-1]) and x[-1] > 0 else float("inf")


def _sample(n: int, max_frames: int) -> list[int]:
    return np.unique(np.round(np.linspace(0, n - 1, min(n, max_frames))).astype(int)).tolist()


def _select_by_motion(images: Sequence[np.ndarray], max_frames: int, n_features: int, target_frac: float,
                      min_frames: int = 20) -> tuple[list[int], list]:
    """Frames spaced by image motion rather than by index: from each chosen frame, the next is the
    last one whose matches moved less than ``target_frac`` x the long side (median) while still
    sharing enough matches. A slow clip is thinned, a fast one (wide baseline) keeps every frame.
    Candidates: at most 4 x ``max_frames`` frames, evenly; at most ``max_frames`` are kept
    (evenly among the chosen); fewer than ``min_frames``: the spacing is halved (up to 3 times).
    Returns (indices into ``images``, their features)."""
    cand = _sample(len(images), 4 * max_frames)
    feats: dict[int, Any] = {}

    def feat(i: int):
        if i not in feats:
            feats[i] = _features(np.asarray(images[cand[i]]), n_features)
        return feats[i]

    target = target_frac * max(np.asarray(images[cand[0]]).shape[:2])
    for _ in range(4):  # too few frames for a reconstruction: halve the spacing
        chosen = _chosen(feat, len(cand), target)
        if len(chosen) >= min(min_frames, len(cand)):
            break
        target /= 2
    if len(chosen) > max_frames:
        chosen = [chosen[k] for k in _sample(len(chosen), max_frames)]
    return [cand[k] for k in chosen], [feat(k) for k in chosen]


def _chosen(feat: Any, n: int, target: float) -> list[int]:
    """Greedy spacing of :func:`_select_by_motion` over candidate positions 0..n-1."""
    chosen, a = [0], 0
    while a < n - 1:
        nxt = a + 1
        for b in range(a + 1, n):
            x1, x2 = _match(feat(a), feat(b))
            if len(x1) < 60 or np.median(np.linalg.norm(x2 - x1, axis=1)) >= target:
                nxt = max(a + 1, b if len(x1) >= 60 else b - 1)
                break
            nxt = b
        chosen.append(nxt)
        a = nxt
    return chosen


def estimate_focal(images: Sequence[np.ndarray], K_guess: np.ndarray, *, max_frames: int = 48,
                   n_features: int = 1000, min_pairs: int = 6, max_rel_sigma: float = 0.03,
                   robust_px: float = 1.0, ransac_px: float = 1.0, rotation_share: float = 0.7,
                   passes: int = 4, motion_frac: float = 0.05) -> dict[str, Any]:
    """Frames (N x uint8 (H, W, 3) RGB, working resolution) + the guessed K (3, 3) -> {
    focal (px, working resolution; the guess when not determined), determined (bool),
    rel_sigma (std of f / f), method ("bundle adjustment" | "rotation"), pairs, rotation_pairs,
    frames (registered), points, median_px, reason (why not determined, '' when determined)}.
    The principal point is K_guess's.

    Mostly-rotating clips (a share >= ``rotation_share`` of the frame pairs explained by a
    homography) are solved from the pairs' homographies (H = K R K^-1); all others by a small
    structure from motion at the guess followed by a bundle adjustment with the focal length free
    (repeated from its result, at most ``passes`` times, while that moves by more than 1 %)."""
    c = np.asarray(K_guess, np.float64)[:2, 2].copy()
    f_guess = float(K_guess[0, 0])
    sel, feats = _select_by_motion(images, max_frames, n_features, motion_frac)
    pairs = []
    for p in range(len(sel)):
        for off in (1, 2):
            if p + off < len(sel):
                g = pair_geometry(p, p + off, *_match(feats[p], feats[p + off]), ransac_px=ransac_px)
                if g is not None:
                    pairs.append(g)
    n_rot = sum(g.kind == "rotation" for g in pairs)
    out: dict[str, Any] = {"focal": f_guess, "determined": False, "rel_sigma": float("inf"), "pairs": len(pairs),
                           "rotation_pairs": n_rot, "frames": 0, "points": 0, "median_px": 0.0, "method": ""}
    if len(pairs) < min_pairs:
        out["reason"] = (f"only {len(pairs)} frame pair(s) with enough matched motion (need {min_pairs}): "
                         "the camera hardly moves")
        return out
    if n_rot >= rotation_share * len(pairs):
        rot = [g for g in pairs if g.kind == "rotation"]
        f0, _, _ = initial_focal(rot, c, f_guess)
        fit = refine_focal(rot, c, f0, robust_px=0.5)
        rel = float(np.expm1(fit["log_sigma"])) if np.isfinite(fit["log_sigma"]) else float("inf")
        out.update(method="rotation", median_px=fit["median_px"], frames=len(sel))
        f = fit["focal"]
    else:
        tracks = build_tracks(feats, ransac_px=ransac_px)
        f, rel = f_guess, float("inf")

        def refine(T, pts, K):
            ba = bundle_adjust_focal(tracks, T, pts, K, robust_px=robust_px, max_px=(10.0,))
            if not ba["T"] or not 0.3 * f_guess < ba["focal"] < 3.0 * f_guess:
                return T, pts, K
            return ba["T"], {**pts, **ba["pts"]}, _K(ba["focal"], c)

        parallax = 0.04 * max(np.asarray(images[sel[0]]).shape[:2])
        sigma_of = None
        for _ in range(passes):
            T, pts, K = _reconstructions(tracks, len(sel), _K(f, c), parallax, refine)
            if len(T) < 3 or len(pts) < 20:
                break
            ba = bundle_adjust_focal(tracks, T, pts, K, robust_px=robust_px)
            if not ba["T"] or ba["frames"] < out["frames"]:  # a pass that registered fewer frames: stop
                break
            moved = abs(np.log(ba["focal"] / f))
            f = ba["focal"]
            sigma_of = ba["log_sigma"]
            out.update(method="bundle adjustment", median_px=ba["median_px"], frames=ba["frames"], points=ba["points"])
            if moved < 0.01:
                break
        if sigma_of is not None:
            ls = sigma_of()
            rel = float(np.expm1(ls)) if np.isfinite(ls) else float("inf")
        if out["frames"] < max(3, 0.25 * len(sel)):
            rel = float("inf")  # a reconstruction of a few frames says nothing about the clip's camera
    out["rel_sigma"] = rel
    in_range = 0.3 * f_guess < f < 3.0 * f_guess
    if rel <= max_rel_sigma and in_range:
        out.update(focal=float(f), determined=True, reason="")
    else:
        out["estimate"] = float(f)
        out["reason"] = (f"the motion does not determine the focal length (estimate {f:.1f} px +- "
                         f"{100 * rel:.0f} %: forward-only or near-static motion?)")
    return out
