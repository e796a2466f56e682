"""Global bundle adjustment of the keyframe poses over multi-view point tracks (gtsam).

What COLMAP has and GCVD lacks: after the pose graph, every keyframe pose is refined jointly with
3-D points that several keyframes observe, under robust (Cauchy) reprojection factors. The pose
graph only knows relative poses per window and per loop edge; the reprojection factors tie every
keyframe to the same points, which removes drift that windows chained by relative poses keep.

Tracks come from the flows the cache already holds (:func:`build_tracks`): from a grid of pixels
in keyframe m, the forward-backward-consistent flow to keyframe m+1 is followed for up to
``track_length`` keyframes (a pixel leaves its track where the flow is inconsistent or leaves the
image), and from every keyframe the track reaches, one hop across each loop edge of the
association's keyframe graph adds the view at the other end of the loop. Each landmark is
parameterised by inverse depth in its first keyframe (gtsam_unstable's InvDepthFactorVariant3:
bearing angles and 1/distance, well conditioned for far and for barely-moved points) and starts
at that keyframe's optimised depth. Tracks seen by fewer than ``min_views`` keyframes are
dropped. Gauge: the first keyframe is fixed; every pose also has a weak prior to its pose-graph
value, which fixes the global scale (monocular BA has none of its own) without holding the shape.

Shapes: flows float32 (H, W, 2) px and bool (H, W) consistency; depth float32 (H, W); K (3, 3);
poses T_w_k (K, 4, 4) camera-to-world, OpenCV axes.
"""

from __future__ import annotations

import logging
from typing import Mapping, Sequence, TypedDict

import gtsam
import numpy as np

log = logging.getLogger(__name__)


class BundleResult(TypedDict):
    poses: np.ndarray  # (K, 4, 4) float64 T_w_k
    landmarks: int
    observations: int
    initial_median_px: float  # median reprojection error over all observations (robust to outliers)
    final_median_px: float
    iterations: int
    skipped: bool  # poses returned unchanged (already consistent with the tracks, or no tracks)
    depth_scale: np.ndarray  # (K,) float64: median new / old distance of the landmarks anchored in each keyframe


def _bilinear(field: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """field (H, W, C) sampled at float pixel positions (x, y) (M,) -> (M, C)."""
    h, w = field.shape[:2]
    x0 = np.clip(np.floor(x).astype(np.int64), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(np.int64), 0, h - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    f = field.astype(np.float64)
    return ((1 - fx) * (1 - fy) * f[y0, x0] + fx * (1 - fy) * f[y0, x0 + 1]
            + (1 - fx) * fy * f[y0 + 1, x0] + fx * fy * f[y0 + 1, x0 + 1])


def _median_error(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> float:
    """Median reprojection error (px) over the projection factors (the mean would be the
    outliers the robust loss ignores)."""
    errs = [float(np.linalg.norm(f.unwhitenedError(values))) for f in (graph.at(i) for i in range(graph.size()))
            if not isinstance(f, gtsam.PriorFactorPose3)]
    return float(np.median(errs)) if errs else 0.0


Track = list[tuple[int, float, float]]  # [(keyframe position, u, v), ...], first = anchor


def build_tracks(edge_flows: Mapping[tuple[int, int], dict[str, np.ndarray]], keyframes: Sequence[int],
                       shape: tuple[int, int], stride: int = 12, track_length: int = 4,
                       border: int = 2) -> list[Track]:
    """Tracks over the keyframe graph: started on a ``stride`` grid in every keyframe, followed
    forward through the consecutive keyframes' flows for up to ``track_length`` keyframes, and at
    every keyframe the track reaches, one hop across each other edge of the graph (loop edges of
    the association: fwd for i -> j, bwd for j -> i). The hop ties a point seen at the start of
    a loop to the same point seen at its end — what lets bundle adjustment keep the loop closed.

    edge_flows: (frame i, frame j) -> {fwd, bwd (H, W, 2) px, fwd_valid, bwd_valid (H, W) bool};
    keyframes: frame index of each keyframe position."""
    pos = {int(f): m for m, f in enumerate(keyframes)}
    n = len(keyframes)
    seq = {m: edge_flows[(keyframes[m], keyframes[m + 1])] for m in range(n - 1)
           if (keyframes[m], keyframes[m + 1]) in edge_flows}
    hops: dict[int, list[tuple[int, np.ndarray, np.ndarray]]] = {}
    for (i, j), fl in edge_flows.items():
        a, b = pos.get(int(i)), pos.get(int(j))
        if a is None or b is None or abs(a - b) == 1:
            continue
        hops.setdefault(a, []).append((b, fl["fwd"], fl["fwd_valid"]))
        hops.setdefault(b, []).append((a, fl["bwd"], fl["bwd_valid"]))
    h, w = shape
    vv, uu = np.mgrid[border:h - border:stride, border:w - border:stride]
    tracks: list[Track] = []
    for m in range(n):
        x, y = uu.ravel().astype(np.float64), vv.ravel().astype(np.float64)
        obs: list[Track] = [[(m, float(a), float(b))] for a, b in zip(x, y)]
        alive = np.arange(len(x))
        for k in range(m, min(m + track_length, n)):
            if k > m:  # step k-1 -> k along the chain
                if k - 1 not in seq:
                    break
                x, y, ok = _follow(seq[k - 1]["fwd"], seq[k - 1]["fwd_valid"], x, y, border)
                x, y, alive = x[ok], y[ok], alive[ok]
                for t, a, b in zip(alive, x, y):
                    obs[t].append((k, float(a), float(b)))
            for other, fwd, valid in hops.get(k, ()):
                if m <= other < m + track_length:
                    continue  # the chain sees it already
                hx, hy, ok = _follow(fwd, valid, x, y, border)
                for t, a, b in zip(alive[ok], hx[ok], hy[ok]):
                    if all(o[0] != other for o in obs[t]):
                        obs[t].append((other, float(a), float(b)))
            if not len(alive):
                break
        tracks.extend(o for o in obs if len(o) >= 2)
    return tracks


def _follow(fwd: np.ndarray, valid: np.ndarray, x: np.ndarray, y: np.ndarray, border: int
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions (x, y) (M,) moved by flow fwd (H, W, 2); ok (M,) where the flow is
    forward-backward consistent there and the target stays ``border`` px inside the image."""
    h, w = valid.shape
    xi, yi = np.round(x).astype(np.int64), np.round(y).astype(np.int64)
    ok = valid[np.clip(yi, 0, h - 1), np.clip(xi, 0, w - 1)].copy()
    d = _bilinear(fwd, x, y) if len(x) else np.zeros((0, 2))
    x2, y2 = x + d[:, 0], y + d[:, 1]
    ok &= (x2 >= border) & (x2 < w - 1 - border) & (y2 >= border) & (y2 < h - 1 - border)
    return x2, y2, ok


def inverse_depth_landmark(u: float, v: float, z: float, Kinv: np.ndarray) -> np.ndarray:
    """(theta, phi, rho) of gtsam_unstable's InvDepthFactorVariant3: the point at depth z
    (metres along the optical axis) on pixel (u, v)'s ray, in its anchor camera's frame:
    X_c = (cos(phi) sin(theta), sin(phi), cos(phi) cos(theta)) / rho."""
    X = z * (Kinv @ np.array([u, v, 1.0]))
    return np.array([np.arctan2(X[0], X[2]), np.arctan2(X[1], np.hypot(X[0], X[2])), 1.0 / np.linalg.norm(X)])


def bundle_adjust(T_w_k: np.ndarray, depths: Sequence[np.ndarray],
                        edge_flows: Mapping[tuple[int, int], dict[str, np.ndarray]], keyframes: Sequence[int],
                        K: np.ndarray, stride: int = 12, track_length: int = 8, min_views: int = 3,
                        robust_px: float = 0.3, prior_rot_sigma: float = 0.05, prior_trans_frac: float = 0.05,
                        max_iterations: int = 30, consistent_px: float = 0.25) -> BundleResult:
    """Refine keyframe poses T_w_k (K, 4, 4) over tracks of the keyframe graph
    (:func:`build_tracks`), landmarks as inverse depth in their first keyframe.

    If the given poses (with landmarks at the keyframes' depth) already reproject the tracks to a
    median error below ``consistent_px``, they are kept (``skipped``): the tracks hold no evidence
    of drift then, only flow noise (~0.1 px for DIS), which the dense windows average better than
    sparse tracks can. On the synthetic loop, bundle adjustment started at the exact poses moves
    them to 1.4 mm keyframe ATE (median error 0.11 px); the pose graph gives 1.0 mm."""
    import gtsam_unstable

    T_w_k = np.asarray(T_w_k, np.float64)
    n = len(T_w_k)
    h, w = np.asarray(depths[0]).shape
    tracks = [t for t in build_tracks(edge_flows, keyframes, (h, w), stride, track_length)
              if len(t) >= min_views]
    if n < 3 or not tracks:
        return {"poses": T_w_k, "landmarks": 0, "observations": 0, "initial_median_px": 0.0,
                "final_median_px": 0.0, "iterations": 0, "skipped": True, "depth_scale": np.ones(n)}
    med = float(np.median([np.median(d[d > 0]) for d in depths if (d > 0).any()] or [1.0]))
    cal = gtsam.Cal3_S2(K[0, 0], K[1, 1], 0.0, K[0, 2], K[1, 2])
    pix = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(robust_px),
                                         gtsam.noiseModel.Isotropic.Sigma(2, 1.0))
    graph, values = _pose_priors(T_w_k, prior_rot_sigma, prior_trans_frac * med)
    Kinv, X, L = np.linalg.inv(K), gtsam.symbol, gtsam.symbol  # pose x_k, landmark l_j
    n_obs = n_lm = 0
    anchor: dict[int, int] = {}  # landmark j -> its keyframe
    for j, track in enumerate(tracks):
        m, u, v = track[0]
        z = float(np.asarray(depths[m])[int(round(v)), int(round(u))])
        if not z > 0:
            continue
        values.insert(L("l", j), inverse_depth_landmark(u, v, z, Kinv))
        n_lm += 1
        anchor[j] = m
        graph.add(gtsam_unstable.InvDepthFactorVariant3a(X("x", m), L("l", j), np.array([u, v]), cal, pix))
        for k, a, b in track[1:]:
            graph.add(gtsam_unstable.InvDepthFactorVariant3b(X("x", m), X("x", k), L("l", j),
                                                             np.array([a, b]), cal, pix))
        n_obs += len(track)
    e0 = _median_error(graph, values)
    if e0 < consistent_px:
        return {"poses": T_w_k, "landmarks": n_lm, "observations": n_obs, "initial_median_px": e0,
                "final_median_px": e0, "iterations": 0, "skipped": True, "depth_scale": np.ones(n)}
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = opt.optimize()
    poses = np.stack([result.atPose3(X("x", k)).matrix() for k in range(n)])
    e1 = _median_error(graph, result)
    log.debug("bundle adjustment: %d landmarks, %d observations, median %.3f -> %.3f px", n_lm, n_obs, e0, e1)
    return {"poses": poses, "landmarks": n_lm, "observations": n_obs, "initial_median_px": e0,
            "final_median_px": e1, "iterations": int(opt.iterations()), "skipped": False,
            "depth_scale": _depth_scale(values, result, anchor, n)}


def _depth_scale(before: gtsam.Values, after: gtsam.Values, anchor: dict[int, int], n: int,
                 min_landmarks: int = 20) -> np.ndarray:
    """(n,) per keyframe: median ratio of its anchored landmarks' distance after / before the
    adjustment (inverse depth rho: before / after). Moving a keyframe corrects the local scale
    that drift had; its depth map must follow or the frames between keyframes fit depth at the
    old scale against poses at the new one. 1 where fewer than ``min_landmarks`` anchor there."""
    ratios: dict[int, list[float]] = {}
    for j, m in anchor.items():
        r0, r1 = before.atVector(gtsam.symbol("l", j))[2], after.atVector(gtsam.symbol("l", j))[2]
        if r0 > 0 and r1 > 0:
            ratios.setdefault(m, []).append(r0 / r1)
    return np.array([float(np.median(ratios[m])) if len(ratios.get(m, ())) >= min_landmarks else 1.0
                     for m in range(n)])


def _pose_priors(T_w_k: np.ndarray, rot_sigma: float, trans_sigma: float
                 ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """The poses as values, a weak prior to each (global scale: monocular BA has none) and a
    tight one on the first (the gauge)."""
    weak = gtsam.noiseModel.Diagonal.Sigmas(np.array([rot_sigma] * 3 + [trans_sigma] * 3))
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k, T in enumerate(T_w_k):
        values.insert(gtsam.symbol("x", k), gtsam.Pose3(T))
        graph.add(gtsam.PriorFactorPose3(gtsam.symbol("x", k), gtsam.Pose3(T), weak))
    graph.add(gtsam.PriorFactorPose3(gtsam.symbol("x", 0), gtsam.Pose3(T_w_k[0]),
                                     gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    return graph, values
