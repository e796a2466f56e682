"""A small incremental structure from motion with one shared focal length (stages.sfm):
two-view start, PnP, triangulation of feature tracks, and bundle adjustments with the focal
length (and optionally the principal point) free. Poses are T_c_w (world to camera, (4, 4)),
points (3,) in the world frame, pixels at the frames' working resolution."""

from __future__ import annotations

import logging
from typing import Any

import cv2
import numpy as np

from gcvd_flow.stages.sfm.tracks import RANSAC_SEED

log = logging.getLogger("gcvd_flow.stages.frontend.calibrate")  # the calibrate stage's messages


TRACK_KEY = 1_000_000  # point key = model * TRACK_KEY + track index (several reconstructions)


def focal_K(f: float, c: np.ndarray) -> np.ndarray:
    return np.array([[f, 0, c[0]], [0, f, c[1]], [0, 0, 1.0]])


def rodrigues(r: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(r, np.float64).reshape(3, 1))[0]


def triangulate_points(P1: np.ndarray, P2: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    X = cv2.triangulatePoints(P1, P2, x1.T.astype(np.float64), x2.T.astype(np.float64))
    return (X[:3] / X[3:]).T


def project_points(K: np.ndarray, T_c_w: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) -> (pixels (N, 2), depth (N,)) in the camera T_c_w (world-to-camera)."""
    Xc = X @ T_c_w[:3, :3].T + T_c_w[:3, 3]
    p = Xc @ K.T
    return p[:, :2] / p[:, 2:3], Xc[:, 2]


def camera_centre(T_c_w: np.ndarray) -> np.ndarray:
    """Camera centre (3,) in the world of a world-to-camera pose (4, 4)."""
    return -T_c_w[:3, :3].T @ T_c_w[:3, 3]


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
    add_points(tracks, T, pts, K, max_px)
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
        add_points(tracks, T, pts, K, max_px)
        n_reg = sum(v is not None for v in T.values())
        if refine is not None and n_reg >= next_refine:
            next_refine = int(np.ceil(n_reg * 1.5))
            good = {f: v for f, v in T.items() if v is not None}
            good, pts, K = refine(good, pts, K)
            T = {f: good.get(f) for f in T}
    return {f: v for f, v in T.items() if v is not None}, pts, K


def add_points(tracks, T, pts, K, max_px: float) -> None:
    """Triangulate tracks not yet triangulated that two registered frames see (the pair furthest
    apart in the track), if the point lies in front of both and reprojects within ``max_px``."""
    for i, t in enumerate(tracks):
        if i in pts:
            continue
        fs = [f for f in t if T.get(f) is not None]
        if len(fs) < 2:
            continue
        a, b = min(fs), max(fs)
        X = triangulate_points(K @ T[a][:3], K @ T[b][:3], t[a][None], t[b][None])[0]
        ok = True
        for f in (a, b):
            p, z = project_points(K, T[f], X[None])
            if z[0] <= 0 or np.linalg.norm(p[0] - t[f]) > max_px:
                ok = False
        if ok:
            pts[i] = X


def bundle_adjust_focal(tracks, T: dict[int, np.ndarray], pts: dict[int, np.ndarray], K: np.ndarray,
                        robust_px: float = 1.0, iterations: int = 50, max_px: tuple[float, ...] = (10.0, 2.0)
                        ) -> dict[str, Any]:
    """Rounds of :func:`adjust_focal`: each keeps the observations that the previous solution (first: the
    initial reconstruction) explains within ``max_px[r]`` px, in front of the camera."""
    out: dict[str, Any] = {}
    n_iter = 0
    for px in max_px:
        out = adjust_focal(tracks, T, pts, K, robust_px=robust_px, iterations=iterations, max_px=px)
        n_iter += out["iterations"]
        if not out["T"]:
            break
        T = out["T"]  # world-to-camera
        pts = out["pts"]
        K = focal_K(out["focal"], np.asarray(K)[:2, 2])
    out["iterations"] = n_iter  # of all rounds
    return out


def observations(tracks, T: dict[int, np.ndarray], pts: dict[int, np.ndarray], K: np.ndarray, max_px: float
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
        p, z = project_points(K, T[f], np.array([pts[i] for i in keys]))
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


def adjust_focal(tracks, T: dict[int, np.ndarray], pts: dict[int, np.ndarray], K: np.ndarray,
                 robust_px: float, iterations: int, max_px: float, marginal: bool = False,
                 pp_prior: tuple[np.ndarray, np.ndarray] | None = None, rel_tol: float | None = None,
                 solver: str = "schur") -> dict[str, Any]:
    """Bundle adjustment with one shared focal length (fx = fy, principal point fixed): poses,
    points and f. ``pts`` keys are model * TRACK_KEY + track: several disconnected reconstructions
    (models) of one camera share the focal length. Gauge of each model (:func:`_gauge`): its first
    pose and its distance to its furthest camera. With ``pp_prior`` = (centre (2,), sigma (2,) px)
    the principal point is free too (square pixels), pulled towards ``centre`` by a Gaussian prior
    of ``sigma``; it starts at K's.
    ``solver``: "schur" (:mod:`stages.sfm.focal_ba`, the default) or "gtsam" (the same factor graph
    in gtsam: the reference the tests hold it to). LM stops at ``iterations`` or a relative cost
    decrease of ``rel_tol`` (default 1e-5). Returns {focal, pp (2,), median_px, observations, points,
    frames, iterations (LM), T (world-to-camera (4, 4) per frame), pts, errors (reprojection error
    per observation, px), with ``marginal`` rel_sigma_formal (the marginal std of f:
    :func:`stages.sfm.focal_ba.intrinsics_cov`, gtsam's :func:`formal_cov`) and, with ``pp_prior``,
    pp_sigma_formal (2,) px}."""
    obs, count = observations(tracks, T, pts, K, max_px)
    frames = sorted(count)
    if len(frames) < 3 or not obs:
        return {"focal": float(K[0, 0]), "pp": np.asarray(K)[:2, 2].copy(), "median_px": 0.0, "observations": 0,
                "points": 0, "frames": len(frames), "iterations": 0, "T": {}, "pts": {}, "errors": np.zeros(0)}
    ids = sorted(obs)
    gauge = _gauge(obs, ids, T)
    run = _adjust_gtsam if solver == "gtsam" else _adjust_schur
    f, pp, poses, points, n_iter, cov = run(obs, ids, frames, T, pts, K, robust_px, iterations, pp_prior,
                                            rel_tol, gauge, marginal)
    err = observation_errors(focal_K(f, pp), poses, points, obs)
    out = {"focal": f, "pp": pp, "median_px": float(np.median(err)), "observations": sum(map(len, obs.values())),
           "points": len(ids), "frames": len(frames), "iterations": n_iter, "T": poses, "pts": points, "errors": err}
    if marginal:
        var = cov(err) if cov is not None else None  # (f, cx, cy) variances px^2, None: not computable
        out["rel_sigma_formal"] = float(np.sqrt(var[0]) / f) if var is not None else float("inf")
        if pp_prior is not None:
            out["pp_sigma_formal"] = np.sqrt(var[1:3]) if var is not None else np.full(2, np.inf)
    return out


def _gauge(obs, ids: list[int], T: dict[int, np.ndarray]
           ) -> list[tuple[int, set[int], int, tuple[int, float] | None, int | None]]:
    """Per model: (its id, its frames, its first frame (held), (its furthest frame, their centres'
    distance) held, or where that distance is 0 its first point (held)). The minimal gauge: a point
    held in place also holds its bearing from the first camera, which pulls f towards the value the
    point was triangulated at (each structure-from-motion pass moved f only part of the way, the
    lens-free loop ending 0.2-1.1 % off depending on the guess: with the distance held all three
    guesses end at the same f, 0.06 % off) and held the principal point of a planar-motion clip
    where it started (orbit: cy 5.3 px off at a formal std of 0.03 px)."""
    model_frames: dict[int, set[int]] = {}
    for i in ids:
        model_frames.setdefault(i // TRACK_KEY, set()).update(f for f, _ in obs[i])
    out: list[tuple[int, set[int], int, tuple[int, float] | None, int | None]] = []
    for m, fs in model_frames.items():
        f0 = min(fs)
        far = max(fs, key=lambda fr: float(np.linalg.norm(camera_centre(T[fr]) - camera_centre(T[f0]))))
        dist = float(np.linalg.norm(camera_centre(T[far]) - camera_centre(T[f0])))
        if dist > 1e-9:
            out.append((m, fs, f0, (far, dist), None))
        else:
            out.append((m, fs, f0, None, next(i for i in ids if i // TRACK_KEY == m)))
    return out


def _noise_scale(err: np.ndarray) -> float:
    """Observation noise (px) from the reprojection errors' median (|r| of a 2-D Gaussian: median =
    1.1774 sigma), at least 1e-3: the adjustment weighs every observation as 1 px."""
    return max(1.4826 * float(np.median(err)) / 1.1774, 1e-3)


def _scene_size(poses: dict[int, np.ndarray], points: dict[int, np.ndarray], first: int) -> float:
    origin = camera_centre(poses[first])
    return float(np.median([np.linalg.norm(X - origin) for X in points.values()]))


def _adjust_schur(obs, ids, frames, T, pts, K, robust_px, iterations, pp_prior, rel_tol, gauge, marginal):
    from threadpoolctl import threadpool_limits

    from gcvd_flow.stages.sfm import focal_ba

    fi = {fr: n for n, fr in enumerate(frames)}
    pi = {i: n for n, i in enumerate(ids)}
    rows = [(pi[i], fi[fr], uv) for i in ids for fr, uv in obs[i]]
    fixed_cam, fixed_pt = np.zeros(len(frames), bool), np.zeros(len(ids), bool)
    ranges = []
    for m, fs, f0, rng, i0 in gauge:
        fixed_cam[fi[f0]] = True
        if rng is not None:
            ranges.append(focal_ba.Range(fi[f0], fi[rng[0]], rng[1], np.array(sorted(fi[fr] for fr in fs)),
                                         np.array([pi[i] for i in ids if i // TRACK_KEY == m])))
        else:
            fixed_pt[pi[i0]] = True
    f = float(K[0, 0])
    prob = focal_ba.Problem(
        obs_pt=np.array([r[0] for r in rows]), obs_cam=np.array([r[1] for r in rows]),
        uv=np.array([r[2] for r in rows], np.float64), robust_px=robust_px, fixed_cam=fixed_cam, fixed_pt=fixed_pt,
        pp_prior=None if pp_prior is None else (np.asarray(pp_prior[0], np.float64), np.asarray(pp_prior[1], np.float64)),
        f_prior_sigma=10 * f if pp_prior is not None else float("inf"), ranges=tuple(ranges))
    Ts = np.array([T[fr] for fr in frames], np.float64)
    state = focal_ba.State(Ts[:, :3, :3].copy(), Ts[:, :3, 3].copy(), np.array([pts[i] for i in ids], np.float64),
                           np.array([f, K[0, 2], K[1, 2]], np.float64), f)
    # numpy's OpenBLAS on one thread: results independent of the core count, and no idle threads
    # spinning against a second process (as the bundle_adjustment stage)
    with threadpool_limits(limits=1, user_api="blas"):
        res = focal_ba.solve(prob, state, iterations, rel_tol=1e-5 if rel_tol is None else rel_tol)
    s = res.state
    poses = {}
    for n, fr in enumerate(frames):
        P = np.eye(4)
        P[:3, :3], P[:3, 3] = s.R[n], s.t[n]
        poses[fr] = P
    points = {i: s.X[n].copy() for n, i in enumerate(ids)}
    f, pp = float(s.intr[0]), s.intr[1:].copy()

    def cov(err):
        with threadpool_limits(limits=1, user_api="blas"):
            c = focal_ba.intrinsics_cov(prob, s, 10.0 * max(_scene_size(poses, points, frames[0]), 1e-9))
        return None if c is None else np.pad(np.diag(c), (0, 3 - len(c))) * _noise_scale(err) ** 2

    return f, pp, poses, points, res.iterations, cov if marginal else None


def _adjust_gtsam(obs, ids, frames, T, pts, K, robust_px, iterations, pp_prior, rel_tol, gauge, marginal):
    import gtsam

    c_key, p_key = ord("c") << 56, ord("p") << 56  # gtsam.symbol(ch, j) = these + j, no call per factor
    KEY = gtsam.symbol("k", 0)
    graph = gtsam.NonlinearFactorGraph()
    vals = gtsam.Values()
    noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(robust_px),
                                           gtsam.noiseModel.Isotropic.Sigma(2, 1.0))
    for fr in frames:
        vals.insert(c_key + fr, gtsam.Pose3(np.linalg.inv(T[fr])))
    if pp_prior is None:
        vals.insert(KEY, gtsam.Cal3f(float(K[0, 0]), float(K[0, 2]), float(K[1, 2])))
        factor: Any = gtsam.GeneralSFMFactor2Cal3f
    else:
        vals.insert(KEY, gtsam.Cal3_S2(float(K[0, 0]), float(K[0, 0]), 0.0, float(K[0, 2]), float(K[1, 2])))
        factor = gtsam.GeneralSFMFactor2Cal3_S2
        add_pp_factors(graph, KEY, float(K[0, 0]), pp_prior)
    for i in ids:
        pk = p_key + i
        vals.insert(pk, np.asarray(pts[i], np.float64))  # a Point3 (gtsam's is a float64 3-vector)
        for fr, uv in obs[i]:  # uv: float64 (2,) rows of observations()' arrays, as Point2 is
            graph.add(factor(uv, noise, c_key + fr, pk, KEY))
    for _, _, f0, rng, i0 in gauge:
        graph.add(gtsam.PriorFactorPose3(c_key + f0, gtsam.Pose3(np.linalg.inv(T[f0])),
                                         gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        if rng is not None:
            graph.add(gtsam.RangeFactorPose3(c_key + f0, c_key + rng[0], rng[1],
                                             gtsam.noiseModel.Isotropic.Sigma(1, 1e-6 * rng[1])))
        else:
            graph.add(gtsam.PriorFactorPoint3(p_key + i0, gtsam.Point3(*pts[i0]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    opt = gtsam.LevenbergMarquardtOptimizer(graph, vals, _lm_params(iterations, rel_tol))
    res = opt.optimize()
    if pp_prior is None:
        f, pp = float(res.atCal3f(KEY).fx()), np.asarray(K)[:2, 2].copy()
    else:
        cal = res.atCal3_S2(KEY)
        f, pp = 0.5 * float(cal.fx() + cal.fy()), np.array([cal.px(), cal.py()], np.float64)
    poses = {fr: np.linalg.inv(res.atPose3(c_key + fr).matrix()) for fr in frames}
    points = {i: np.asarray(res.atPoint3(p_key + i)) for i in ids}

    def cov(err):
        c = formal_cov(graph, res, KEY, [p_key + i for i in ids], c_key + frames[0], err)
        return None if c is None else (np.array([c[0, 0], 0.0, 0.0]) if pp_prior is None else np.diag(c)[[0, 3, 4]])

    return f, pp, poses, points, int(opt.iterations()), cov if marginal else None


def _lm_params(iterations: int, rel_tol: float | None):
    """gtsam LM parameters: at most ``iterations``; with ``rel_tol`` LM stops when the cost
    decreases by less than this fraction (gtsam's default 1e-5)."""
    import gtsam

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    if rel_tol is not None:
        params.setRelativeErrorTol(rel_tol)
    return params


def add_pp_factors(graph, key: int, f: float, pp_prior: tuple[np.ndarray, np.ndarray]) -> None:
    """The Cal3_S2 of :func:`adjust_focal` with a free principal point: fx = fy (square pixels, a tight
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


def formal_cov(graph, res, key: int, point_keys: list[int], first_pose: int, err: np.ndarray
                ) -> np.ndarray | None:
    """Marginal covariance (px^2) of the calibration ``key`` (Cal3f: (1, 1), f; Cal3_S2: (5, 5), fx,
    fy, skew, cx, cy) from the sparse Gauss-Newton information (gtsam Marginals), scaled by the
    robust residual spread. Small on real clips (f: 0.01-0.1 % where the errors were 1-3 %), but
    large where the motion leaves f unobservable (pure forward translation: the cost is flat along
    f), which the perturbation terms of :func:`_uncertainty` cannot see. Weak priors on the points
    (10 x the scene's size) keep a point seen from nearly one place from making the system
    indeterminate. None when it cannot be computed."""
    import gtsam

    s = _noise_scale(err)
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


def observation_errors(K: np.ndarray, T: dict[int, np.ndarray], pts: dict[int, np.ndarray],
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
        p, z = project_points(K, T[f], np.array([pts[rows[k][0]] for k in ks]))
        e = np.linalg.norm(p - np.array([rows[k][2] for k in ks]), axis=1)
        out[ks] = np.where(z > 1e-9, e, 1e3)
    return out
