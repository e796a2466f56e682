"""Trajectory and depth metrics as the field reports them (pure numpy).

* ATE: RMSE of camera positions after a Sim(3) Umeyama alignment of the estimate to the
  ground truth (metres) — evo's ``evo_ape --align --correct_scale``.
* RPE (delta = 1 frame): the alignment's scale applied to the estimate, then per pair the
  error E = inv(inv(Tgt_w_i) Tgt_w_j) @ (inv(T_w_i) T_w_j) (Tgt: ground truth); RMSE of |t(E)| (m) and of angle(E) (degrees) —
  evo's ``evo_rpe --delta 1 --delta_unit f --align --correct_scale`` (trans_part, angle_deg).
* Depth: per-frame median scaling, ground truth > 0 and <= ``max_depth``; AbsRel, SqRel, RMSE
  (m), δ < 1.25.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def umeyama_alignment(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) minimising sum |dst - (s R src + t)|^2 (Umeyama 1991, closed form).

    src, dst: (N, 3) corresponding points, N >= 3 (units of dst); ``with_scale=False`` fixes
    s = 1 (SE(3) alignment). Returns s (float), R (3, 3) proper rotation, t (3,).
    """
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"umeyama_alignment: src and dst must both be (N, 3), got {src.shape} and {dst.shape}")
    if len(src) < 3:
        raise ValueError(f"umeyama_alignment: needs at least 3 points, got {len(src)}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    var_s = (xs ** 2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale and var_s > 0 else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def _check_pair(est: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    est = np.asarray(est, np.float64)
    gt = np.asarray(gt, np.float64)
    if est.shape != gt.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise ValueError(f"trajectories must both be (N, 4, 4) camera-to-world, got {est.shape} and {gt.shape}")
    return est, gt


def _align(est: np.ndarray, gt: np.ndarray, align: str) -> tuple[np.ndarray, float]:
    """Estimate poses aligned to the ground truth; returns (aligned (N,4,4), scale).

    The alignment is fitted on camera positions only (as evo does) and applied to the
    whole poses: rotations are rotated, positions similarity-transformed.
    """
    if align not in ("sim3", "se3", "none"):
        raise ValueError(f"align must be 'sim3', 'se3' or 'none', got {align!r}")
    est = np.asarray(est, np.float64).copy()
    if align == "none" or len(est) < 3:
        return est, 1.0
    s, R, t = umeyama_alignment(est[:, :3, 3], gt[:, :3, 3], with_scale=(align == "sim3"))
    out = est.copy()
    out[:, :3, :3] = R @ est[:, :3, :3]
    out[:, :3, 3] = (s * (R @ est[:, :3, 3].T)).T + t
    return out, s


def ate(est_poses: np.ndarray, gt_poses: np.ndarray, align: str = "sim3") -> dict[str, float]:
    """Absolute trajectory error of camera positions after alignment ('sim3'|'se3'|'none').

    est_poses, gt_poses: (N, 4, 4) camera-to-world, frame i of one = frame i of the other.
    Returns ate_rmse / ate_mean / ate_median in ground-truth units (m) and ``scale``, the
    factor that maps the estimate into ground-truth units (1 unless 'sim3').
    """
    est_poses, gt = _check_pair(est_poses, gt_poses)
    al, s = _align(est_poses, gt, align)
    err = np.linalg.norm(al[:, :3, 3] - gt[:, :3, 3], axis=1)
    return {"ate_rmse": float(np.sqrt(np.mean(err ** 2))), "ate_mean": float(err.mean()),
            "ate_median": float(np.median(err)), "scale": float(s)}


def _rot_angle_deg(R: np.ndarray) -> np.ndarray:
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def rpe(est_poses: np.ndarray, gt_poses: np.ndarray, delta: int = 1, align: str = "sim3") -> dict[str, float]:
    """Relative pose error over ``delta`` frames: RMSE translation (m) and rotation (deg).

    est_poses, gt_poses: (N, 4, 4) camera-to-world. The estimate is first aligned as in
    ``ate`` (so with 'sim3' its translations are in metres); then for every i the error
    E_i = inv(inv(Tgt_w_i) Tgt_w_{i+delta}) (inv(T_w_i) T_w_{i+delta}) (Tgt: ground truth); rpe_trans = RMSE |t(E_i)|,
    rpe_rot = RMSE angle(R(E_i)) in degrees.
    """
    est_poses, gt = _check_pair(est_poses, gt_poses)
    if delta < 1:
        raise ValueError(f"delta must be >= 1, got {delta}")
    est, _ = _align(est_poses, gt, align)
    n = len(gt) - delta
    if n <= 0:
        return {"rpe_trans": 0.0, "rpe_rot": 0.0}
    rel_gt = np.linalg.inv(gt[:n]) @ gt[delta:]
    rel_est = np.linalg.inv(est[:n]) @ est[delta:]
    E = np.linalg.inv(rel_gt) @ rel_est
    t = np.linalg.norm(E[:, :3, 3], axis=1)
    r = _rot_angle_deg(E[:, :3, :3])
    return {"rpe_trans": float(np.sqrt(np.mean(t ** 2))), "rpe_rot": float(np.sqrt(np.mean(r ** 2)))}


def window_scales(est_poses: np.ndarray, gt_poses: np.ndarray, window: int = 20) -> np.ndarray:
    """Scale drift: for every run of ``window`` consecutive frames, the Sim(3) (Umeyama) scale
    fitted on that window's camera positions alone, divided by the whole trajectory's; (W,)
    float64, empty when there are fewer than two windows. 1 everywhere = no drift; the spread
    (max / min) is what windows chained by relative poses accumulate."""
    est_poses, gt = _check_pair(est_poses, gt_poses)
    n = len(gt)
    if n < 2 * window or window < 3:
        return np.zeros(0)
    s_all, _, _ = umeyama_alignment(est_poses[:, :3, 3], gt[:, :3, 3], with_scale=True)
    out = []
    for a in range(0, n - window + 1, window):
        s, _, _ = umeyama_alignment(est_poses[a:a + window, :3, 3], gt[a:a + window, :3, 3], with_scale=True)
        out.append(s / s_all)
    return np.asarray(out, np.float64)


def path_length(poses: np.ndarray) -> float:
    """Total distance travelled by the camera centres of (N, 4, 4) poses (pose units)."""
    p = np.asarray(poses)[:, :3, 3]
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def depth_metrics(pred: np.ndarray, gt: np.ndarray, max_depth: float = 10.0) -> dict[str, float]:
    """Errors of one depth map after per-frame median scaling.

    pred, gt: (H, W) depth (gt in metres; pred up to scale). Valid pixels: gt > 0,
    gt <= max_depth, pred finite and > 0. pred is scaled by median(gt)/median(pred) over
    the valid pixels and clipped to [1e-3, max_depth]. Returns abs_rel, sq_rel (m), rmse (m),
    delta1 (fraction with max(p/g, g/p) < 1.25); all NaN if fewer than 10 valid pixels.
    """
    pred = np.asarray(pred, np.float64)
    gt = np.asarray(gt, np.float64)
    valid = (gt > 0) & (gt <= max_depth) & (pred > 0) & np.isfinite(pred)
    if valid.sum() < 10:
        return {"abs_rel": float("nan"), "sq_rel": float("nan"), "rmse": float("nan"), "delta1": float("nan")}
    p, g = pred[valid], gt[valid]
    p = np.clip(p * (np.median(g) / np.median(p)), 1e-3, max_depth)
    ratio = np.maximum(p / g, g / p)
    return {"abs_rel": float(np.mean(np.abs(p - g) / g)), "sq_rel": float(np.mean((p - g) ** 2 / g)),
            "rmse": float(np.sqrt(np.mean((p - g) ** 2))), "delta1": float(np.mean(ratio < 1.25))}


SPARSIFICATION_SHARES = (0.25, 0.5, 0.75)


def sparsification_abs_rel(pred: np.ndarray, gt: np.ndarray, confidence: np.ndarray, max_depth: float = 10.0,
                           shares: tuple[float, ...] = SPARSIFICATION_SHARES) -> dict[str, float]:
    """AbsRel of the most confident ``share`` of a frame's valid pixels, for each share, with
    the frame median-scaled on those pixels (as ``depth_metrics``): how well the confidence
    ranks the error, whatever its calibration (a fixed threshold mixes both). Ties in the
    confidence are broken by pixel order (deterministic).

    pred, gt, confidence: (H, W); returns {"top25": AbsRel, ...} (NaN below 10 pixels)."""
    pred = np.asarray(pred, np.float64)
    gt = np.asarray(gt, np.float64)
    valid = ((gt > 0) & (gt <= max_depth) & (pred > 0) & np.isfinite(pred)).ravel()
    idx = np.flatnonzero(valid)
    order = idx[np.argsort(-np.asarray(confidence, np.float64).ravel()[idx], kind="stable")]
    out = {}
    for q in shares:
        keep = np.zeros(pred.size, bool)
        keep[order[: int(round(q * len(order)))]] = True
        out[f"top{round(q * 100)}"] = depth_metrics(np.where(keep.reshape(pred.shape), pred, 0.0), gt,
                                                    max_depth)["abs_rel"]
    return out


def aggregate_depth_metrics(per_frame: list[dict[str, float]]) -> dict[str, Any]:
    """Mean over frames (frames without enough valid pixels are skipped)."""
    keys = ("abs_rel", "sq_rel", "rmse", "delta1")
    out = {}
    for k in keys:
        vals = [m[k] for m in per_frame if np.isfinite(m[k])]
        out[k] = float(np.mean(vals)) if vals else float("nan")
    return out
