"""Global bundle adjustment of the keyframe poses over multi-view point tracks (gtsam).

What COLMAP has and GCVD lacks: after the pose graph, every keyframe pose is refined jointly with
3-D points that several keyframes observe, under robust (Cauchy) reprojection factors. The pose
graph only knows relative poses per window and per loop edge; the reprojection factors tie every
keyframe to the same points, which removes drift that windows chained by relative poses keep.

Tracks come from the flows the cache already holds: from a grid of pixels in keyframe m, the
forward-backward-consistent flow to keyframe m+1 is followed for up to ``track_length``
keyframes (a pixel leaves its track where the flow is inconsistent or leaves the image). A
landmark starts at keyframe m's optimised depth along the pixel's ray, placed in the world with
the pose graph's T_w_m; tracks seen by fewer than ``min_views`` keyframes are dropped. Gauge:
the first keyframe is fixed; every pose also has a weak prior to its pose-graph value, which
fixes the global scale (monocular BA has none of its own) without holding the shape.

Shapes: flows float32 (H, W, 2) px and bool (H, W) consistency; depth float32 (H, W); K (3, 3);
poses T_w_k (K, 4, 4) camera-to-world, OpenCV axes.
"""

from __future__ import annotations

import logging
from typing import Any, Sequence, TypedDict

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


def _bilinear(field: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """field (H, W, C) sampled at float pixel positions (x, y) (M,) -> (M, C)."""
    h, w = field.shape[:2]
    x0 = np.clip(np.floor(x).astype(np.int64), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(np.int64), 0, h - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    f = field.astype(np.float64)
    return ((1 - fx) * (1 - fy) * f[y0, x0] + fx * (1 - fy) * f[y0, x0 + 1]
            + (1 - fx) * fy * f[y0 + 1, x0] + fx * fy * f[y0 + 1, x0 + 1])


def build_tracks(flows: Sequence[dict[str, np.ndarray]], n_keyframes: int, shape: tuple[int, int],
                 stride: int = 12, track_length: int = 4, border: int = 2) -> list[list[tuple[int, float, float]]]:
    """Tracks [(keyframe, u, v), ...] started on a ``stride`` grid in every keyframe and followed
    through ``flows[m]`` (keyframe m -> m + 1: fwd (H, W, 2), fwd_valid (H, W))."""
    h, w = shape
    vv, uu = np.mgrid[border:h - border:stride, border:w - border:stride]
    tracks: list[list[tuple[int, float, float]]] = []
    for m in range(n_keyframes - 1):
        x, y = uu.ravel().astype(np.float64), vv.ravel().astype(np.float64)
        obs = [[(m, float(a), float(b))] for a, b in zip(x, y)]
        alive = np.arange(len(x))
        for k in range(m, min(m + track_length - 1, n_keyframes - 1)):
            fl = flows[k]
            xi, yi = np.round(x).astype(np.int64), np.round(y).astype(np.int64)
            ok = fl["fwd_valid"][np.clip(yi, 0, h - 1), np.clip(xi, 0, w - 1)]
            d = _bilinear(fl["fwd"], x, y)
            x, y = x + d[:, 0], y + d[:, 1]
            ok &= (x >= border) & (x < w - 1 - border) & (y >= border) & (y < h - 1 - border)
            x, y, alive = x[ok], y[ok], alive[ok]
            for t, a, b in zip(alive, x, y):
                obs[t].append((k + 1, float(a), float(b)))
            if not len(alive):
                break
        tracks.extend(o for o in obs if len(o) >= 2)
    return tracks


def bundle_adjust(T_w_k: np.ndarray, depths: Sequence[np.ndarray], flows: Sequence[dict[str, np.ndarray]],
                  K: np.ndarray, stride: int = 12, track_length: int = 4, min_views: int = 3,
                  robust_px: float = 1.0, prior_rot_sigma: float = 0.05, prior_trans_frac: float = 0.05,
                  max_iterations: int = 30) -> BundleResult:
    """Refine keyframe poses T_w_k (K, 4, 4) over flow tracks (module docstring)."""
    T_w_k = np.asarray(T_w_k, np.float64)
    n = len(T_w_k)
    h, w = np.asarray(depths[0]).shape
    tracks = [t for t in build_tracks(flows, n, (h, w), stride, track_length) if len(t) >= min_views]
    med = float(np.median([np.median(d[d > 0]) for d in depths if (d > 0).any()] or [1.0]))
    graph, values, n_obs = _factor_graph(T_w_k, depths, tracks, K, robust_px, prior_rot_sigma,
                                         prior_trans_frac * med)
    if n < 3 or not tracks:
        return {"poses": T_w_k, "landmarks": 0, "observations": 0, "initial_median_px": 0.0,
                "final_median_px": 0.0, "iterations": 0}
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = opt.optimize()
    poses = np.stack([result.atPose3(gtsam.symbol("x", k)).matrix() for k in range(n)])
    e0, e1 = _median_error(graph, values), _median_error(graph, result)
    log.debug("bundle adjustment: %d landmarks, %d observations, median %.3f -> %.3f px", len(tracks), n_obs, e0, e1)
    return {"poses": poses, "landmarks": len(tracks), "observations": n_obs, "initial_median_px": e0,
            "final_median_px": e1, "iterations": int(opt.iterations())}


def _factor_graph(T_w_k: np.ndarray, depths: Sequence[np.ndarray], tracks: list[list[tuple[int, float, float]]],
                  K: np.ndarray, robust_px: float, rot_sigma: float, trans_sigma: float
                  ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, int]:
    """Projection factors (Cauchy: outliers such as flow across depth edges stop pulling) for every observation, landmarks at keyframe depth, a tight
    prior on the first pose and weak priors on all poses (the gauge and the global scale)."""
    cal = gtsam.Cal3_S2(K[0, 0], K[1, 1], 0.0, K[0, 2], K[1, 2])
    pix = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(robust_px),
                                         gtsam.noiseModel.Isotropic.Sigma(2, 1.0))
    weak = gtsam.noiseModel.Diagonal.Sigmas(np.array([rot_sigma] * 3 + [trans_sigma] * 3))
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    Kinv = np.linalg.inv(K)
    for k, T in enumerate(T_w_k):
        values.insert(gtsam.symbol("x", k), gtsam.Pose3(T))
        graph.add(gtsam.PriorFactorPose3(gtsam.symbol("x", k), gtsam.Pose3(T), weak))
    graph.add(gtsam.PriorFactorPose3(gtsam.symbol("x", 0), gtsam.Pose3(T_w_k[0]),
                                     gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    n_obs = 0
    for j, track in enumerate(tracks):
        m, u, v = track[0]
        z = float(np.asarray(depths[m])[int(round(v)), int(round(u))])
        if not z > 0:
            continue
        X_c = z * (Kinv @ np.array([u, v, 1.0]))
        X_w = T_w_k[m][:3, :3] @ X_c + T_w_k[m][:3, 3]
        values.insert(gtsam.symbol("l", j), gtsam.Point3(*X_w))
        for k, a, b in track:
            graph.add(gtsam.GenericProjectionFactorCal3_S2(gtsam.Point2(a, b), pix, gtsam.symbol("x", k),
                                                           gtsam.symbol("l", j), cal))
            n_obs += 1
    return graph, values, n_obs


def _median_error(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> float:
    """Median reprojection error (px) over the projection factors (the mean would be the
    outliers the robust loss ignores)."""
    errs = [float(np.linalg.norm(f.unwhitenedError(values))) for f in (graph.at(i) for i in range(graph.size()))
            if isinstance(f, gtsam.GenericProjectionFactorCal3_S2)]
    return float(np.median(errs)) if errs else 0.0
