"""Initial poses and depths of the optimisations (two-view geometry, PnP, depth transfer).

Poses are T_w_c (camera-to-world, 4x4 float64, OpenCV axes); a relative pose mapping camera-a
coordinates into camera-b coordinates is T_b_a = inv(T_w_b) @ T_w_a. Pixels (M, 2) are (u, v),
the centre of the top-left pixel is (0, 0); depth is z-depth.

The initialisation decides the result (docs/design.md, "Lessons from the prototype"):
- keyframes: ``essential_chain``: MAGSAC++ essential matrix per consecutive keyframe pair (about
  5x smaller translation-direction error than RANSAC on DIS flow), scale propagated by
  triangulating each keyframe from both of its pairs on the same pixel grid;
- loop edges: ``two_view_pose`` on the edge's own flow (the chain's drift is not inherited);
- non-keyframes: ``pnp_init``: PnP of flow-tracked keyframe points lifted with the keyframe depth
  (correct scale, well conditioned at tiny baselines); their depth model starts from the
  keyframe depths reprojected into them (``transfer_depths``).
"""

from __future__ import annotations

import math
from typing import Mapping, Sequence

import cv2
import numpy as np

from gcvd_flow.stages.frontend.flow import warp_sample
from gcvd_flow.stages.frontend.user_masks import flow_target_kept, user_keep
from gcvd_flow.stages.geometry.two_view import pose_from_essential, rotation_from_homography
from gcvd_flow.stages.optimize.frames import normalised_prior

__all__ = [
    "rays",
    "two_view_pose",
    "triangulate",
    "sample_np",
    "pair_masks",
    "chain_pair_poses",
    "essential_chain",
    "interp_pose",
    "pnp_init",
    "splat_depth",
    "fill_small_holes",
    "transfer_depths",
]


def rays(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixels uv (M, 2) -> camera rays (M, 3) float64 with z = 1."""
    return np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))], 1)


def two_view_pose(
    fwd: np.ndarray, valid: np.ndarray, K: np.ndarray, n_pts: int = 3000, min_parallax: float = 0.5,
    rotation_max_residual_px: float | None = None,
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
    """Relative pose T_b_a (4, 4) float64 (camera a -> camera b coordinates) with unit
    translation (zero if rotation-only / unreliable) from the forward flow a -> b (H, W, 2) px and
    a usable-pixel mask (H, W) of frame a; also the correspondences (uv_a (M, 2), uv_b (M, 2)) px
    of the RANSAC inliers, or None.

    ``rotation_max_residual_px`` (opt-in, not used by the pipeline): a homography that fits is
    taken for a rotation only when its rotation itself moves the pixels onto the flow within this
    median distance (1.0: the homography's own threshold). Forward motion towards a far scene
    passes as a homography (KITTI 07 at 256x78: 4 keyframe pairs lost their translation); on the
    HoloLens walk-through the same test gave 4 short pairs a translation and cost ATE 0.061 ->
    0.068 m, and at KITTI's new working size (424x128) no pair needs it (docs/log/2026-11-28-forward.md)."""
    h, w = valid.shape
    ys, xs = np.nonzero(valid)
    T_b_a = np.eye(4)
    if len(xs) < 50:
        return T_b_a, None
    step = max(1, len(xs) // n_pts)
    xs, ys = xs[::step], ys[::step]
    uv_a = np.stack([xs, ys], 1).astype(np.float64)
    uv_b = uv_a + fwd[ys, xs].astype(np.float64)
    f = float(K[0, 0])
    # Rotation-only (or no) motion first: E is then degenerate and its decomposition arbitrary
    # (identical frames gave a ~176-degree rotation).
    R_h = rotation_from_homography(uv_a, uv_b, K, max_residual_px=rotation_max_residual_px)
    if R_h is not None:
        T_b_a[:3, :3] = R_h
        return T_b_a, None
    # MAGSAC++ (USAC): ~5x smaller translation-direction error than plain RANSAC on DIS flow
    E, inl = cv2.findEssentialMat(uv_a, uv_b, K, method=cv2.USAC_MAGSAC, prob=0.999, threshold=max(0.5, f / 500))
    if E is None or E.shape[0] < 3:
        return T_b_a, None
    E = E[:3]
    if E.shape != (3, 3):
        return T_b_a, None
    # Own cheirality test: cv2.recoverPose ignores points beyond 50 baselines, so on video
    # baselines it may return the 180-degree "twisted pair" (stages.two_view).
    m = inl[:, 0] > 0
    R, t_unit, _ = pose_from_essential(E, uv_a[m], uv_b[m], K)
    t = t_unit.reshape(3, 1)
    T_b_a[:3, :3] = R
    # rotation-only test: residual flow after removing the rotation (infinite homography)
    ra = rays(uv_a[m], K) @ R.T
    pa = ra[:, :2] / ra[:, 2:3] * np.array([K[0, 0], K[1, 1]]) + np.array([K[0, 2], K[1, 2]])
    parallax = np.median(np.linalg.norm(pa - uv_b[m], axis=1))
    if parallax < min_parallax:
        # (near) no translation: E is degenerate, the rotation is that of the infinite homography
        Hm, _ = cv2.findHomography(uv_a, uv_b, cv2.RANSAC, 1.0)
        if Hm is not None:
            U, _, Vt = np.linalg.svd(np.linalg.inv(K) @ Hm @ K)
            T_b_a[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        return T_b_a, None
    T_b_a[:3, 3] = t[:, 0]
    return T_b_a, (uv_a[m], uv_b[m])


def triangulate(
    uv_a: np.ndarray, uv_b: np.ndarray, K: np.ndarray, T_b_a: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares z-depths (d_a (M,), d_b (M,)) of correspondences uv_a, uv_b (M, 2) px with
    d_a R x_a + t = d_b x_b for T_b_a = [R | t] (camera a -> camera b), and a usable mask (M,)
    (positive depths, triangulation angle above 0.2 degrees)."""
    r = rays(uv_a, K) @ T_b_a[:3, :3].T
    x = rays(uv_b, K)
    t = T_b_a[:3, 3]
    rr, xx, rx = (r * r).sum(1), (x * x).sum(1), (r * x).sum(1)
    rt, xt = r @ t, x @ t
    det = rr * xx - rx * rx
    ok = det > 1e-10
    det = np.where(ok, det, 1.0)
    da = (-rt * xx + rx * xt) / det
    db = (rr * xt - rx * rt) / det
    cosang = rx / np.sqrt(rr * xx)
    ok &= (da > 0) & (db > 0) & (cosang < math.cos(math.radians(0.2)))
    return da, db, ok


def sample_np(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear sample of img (H, W) at pixel points uv (M, 2) -> float64 (M,), the points clamped
    to [0, W - 1.001] x [0, H - 1.001] (the initialisation's clamp, kept for its results);
    ``warp_sample``'s arithmetic, term by term (the same bits as the copy this replaced)."""
    h, w = img.shape
    uv_c = np.stack([np.clip(uv[:, 0], 0, w - 1.001), np.clip(uv[:, 1], 0, h - 1.001)], axis=1)
    return warp_sample(np.asarray(img, np.float64), uv_c)


def _grid_depths(
    flow: np.ndarray, valid: np.ndarray, K: np.ndarray, T_o_s: np.ndarray, stride: int
) -> tuple[np.ndarray, np.ndarray]:
    """Triangulated depth (gh, gw) of the source frame s on a regular pixel grid (NaN = unusable)
    from a flow field (H, W, 2) px s -> o, its mask (H, W) and the relative pose T_o_s (camera s ->
    camera o coordinates); also the grid's pixels (gh * gw, 2)."""
    h, w = valid.shape
    ys, xs = np.mgrid[stride // 2 : h : stride, stride // 2 : w : stride]
    uv = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
    uv2 = uv + flow[ys.ravel(), xs.ravel()].astype(np.float64)
    d, _, ok = triangulate(uv, uv2, K, T_o_s)
    ok &= valid[ys.ravel(), xs.ravel()]
    return np.where(ok, d, np.nan).reshape(ys.shape), uv


def pair_masks(fl: Mapping[str, np.ndarray], static_masks: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Usable pixels (forward (H, W) of frame k, backward (H, W) of frame k + 1) of the flow dict
    ``fl`` of pair (k, k + 1): flow-valid, static, and (--masks) not landing on a user-masked pixel."""
    sm = np.asarray(static_masks)
    fv = np.asarray(fl["fwd_valid"], bool) & (sm[k] > 0)
    bv = np.asarray(fl["bwd_valid"], bool) & (sm[k + 1] > 0)
    keep = user_keep(sm[k : k + 2])  # the user's kept pixels of both (int8 masks, -1 = masked), or None
    if keep is not None:  # --masks: a correspondence whose target mixes a user-masked pixel is out
        fv &= flow_target_kept(np.asarray(fl["fwd"], np.float64), keep[1])
        bv &= flow_target_kept(np.asarray(fl["bwd"], np.float64), keep[0])
    return fv, bv


def chain_pair_poses(
    flows: Sequence[Mapping[str, np.ndarray]], static_masks: np.ndarray, K: np.ndarray
) -> list[tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]]:
    """``two_view_pose`` (T_{k+1}_k, inlier correspondences or None) of every consecutive pair
    (k, k + 1) from its forward flow ``flows[k]``, on ``pair_masks``' pixels."""
    return [two_view_pose(np.asarray(fl["fwd"], np.float32), pair_masks(fl, static_masks, k)[0], K)
            for k, fl in enumerate(flows)]


def essential_chain(
    flows: Sequence[Mapping[str, np.ndarray]],
    static_masks: np.ndarray,
    ref_depths: np.ndarray,
    K: np.ndarray,
    stride: int = 2,
    pair_poses: Sequence[tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]] | None = None,
    prior_scale_below: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Chain of two-view poses with consistent scale.

    flows[k]: flow dict of pair (k, k+1); static_masks (N, H, W); ref_depths (N, H, W): the
    network's initial depth (prior-shaped, scale-ambiguous per frame); K (3, 3).
    Returns (poses (N, 4, 4) float64 T_w_c (camera-to-world) with T_w_0 = I, log_scale (N,)):
    frame k's depth is ~ ref_depths[k] * exp(log_scale[k]) in the chain's units.

    Scale propagation without the prior: frame k is triangulated on the *same* pixel grid by
    pair (k-1, k) (through the backward flow) and by pair (k, k+1) (forward flow); the median
    ratio of the two depth maps rescales pair (k, k+1)'s unit translation. Frame 0 keeps the
    prior's scale. Rotation-only pairs get a zero translation and pass the scale through.

    pair_poses: the pairs' ``two_view_pose`` results (T_{k+1}_k, correspondences or None) when
    already computed (``chain_pair_poses``, possibly repaired by ``stages.optimize.chain_check``).

    prior_scale_below (opt-in, 0 = off): a rotation-dominated pair, whose median parallax (flow
    left after its rotation) is below this fraction of its median flow, or a rotation-only pair,
    does not propagate the scale by same-pixel depth ratios (ill-conditioned: on the HoloLens
    walk's turning start they inflate the first window 4-15x). Its translation is scaled so that
    frame k's triangulated depth matches frame k's known depth (prior x scale) in median, and
    frame k + 1's scale comes from frame k's depth carried through the pair's motion along the
    flow (``_transferred_log_scale``): the same 3D points, so the scale passes through however
    small the parallax.
    """
    n = len(flows) + 1
    if pair_poses is None:
        pair_poses = chain_pair_poses(flows, static_masks, K)
    T_next_cur, d_fwd, d_bwd, grid_uv = _pair_depths(flows, static_masks, K, pair_poses, stride)

    def ref_ratio(k: int, d: np.ndarray) -> float:
        m = np.isfinite(d).ravel()
        r = d.ravel()[m] / sample_np(ref_depths[k], grid_uv[m])  # type: ignore[index]
        return float(np.median(r))

    log_m = np.zeros(n)  # log depth scale of frame k relative to ref_depths[k]
    poses = np.tile(np.eye(4), (n, 1, 1))
    known = False  # whether log_m[k] is anchored by a triangulation
    prev_scale = 1.0  # the previous pair's scale s (read only once known)
    for k in range(n - 1):
        T_k1_k = T_next_cur[k].copy()
        fwd, bwd = d_fwd[k], d_bwd[k]
        weak = prior_scale_below > 0 and _parallax_fraction(flows[k], static_masks, k, K, T_k1_k, stride) < prior_scale_below
        if fwd is not None:
            assert bwd is not None  # a pair's two depth maps are None together (above)
            if weak:  # rotation-dominated: the scale from frame k's known depth, carried along the flow
                s = math.exp(log_m[k]) / ref_ratio(k, fwd)
                T_k1_k[:3, 3] *= s
                prev_scale, known = s, True
                log_m[k + 1] = _transferred_log_scale(flows[k], static_masks, k, ref_depths, log_m[k], K, T_k1_k, stride)
            else:
                if k > 0 and (prev_bwd := d_bwd[k - 1]) is not None and known:
                    # same-pixel ratio: depth of frame k (previous pair, already scaled) / (this pair)
                    prev = prev_bwd * prev_scale
                    both = np.isfinite(prev) & np.isfinite(fwd)
                    if both.sum() >= 20:
                        s = float(np.median(prev[both] / fwd[both]))
                    else:
                        s = math.exp(log_m[k]) / ref_ratio(k, fwd)
                else:
                    s = math.exp(log_m[k]) / ref_ratio(k, fwd)
                T_k1_k[:3, 3] *= s
                prev_scale = s
                log_m[k + 1] = math.log(s * ref_ratio(k + 1, bwd))
                known = True
        else:
            log_m[k + 1] = (_transferred_log_scale(flows[k], static_masks, k, ref_depths, log_m[k], K, T_k1_k, stride)
                            if prior_scale_below > 0 else log_m[k])
            known = False
        poses[k + 1] = poses[k] @ np.linalg.inv(T_k1_k)  # T_w_{k+1} = T_w_k @ T_k_{k+1}
    return poses, log_m


def _pair_depths(
    flows: Sequence[Mapping[str, np.ndarray]], static_masks: np.ndarray, K: np.ndarray,
    pair_poses: Sequence[tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]], stride: int,
) -> tuple[list[np.ndarray], list[np.ndarray | None], list[np.ndarray | None], np.ndarray | None]:
    """Per consecutive pair (k, k + 1): T_{k+1}_k (unit translation; zero when the pair cannot
    triangulate), the grid depths of frame k and of frame k + 1 at unit baseline (None together:
    rotation-only or fewer than 20 usable), and the grid's pixels (None without any)."""
    T_next_cur: list[np.ndarray] = []  # T_{k+1}_k: camera k -> camera k+1, unit translation
    d_fwd: list[np.ndarray | None] = []  # depth of frame k from pair (k, k+1), unit baseline
    d_bwd: list[np.ndarray | None] = []  # depth of frame k+1 from pair (k, k+1), unit baseline
    grid_uv = None
    for k, fl in enumerate(flows):
        fv, bv = pair_masks(fl, static_masks, k)
        T_k1_k, corr = pair_poses[k][0].copy(), pair_poses[k][1]
        T_next_cur.append(T_k1_k)
        if corr is None:
            d_fwd.append(None)
            d_bwd.append(None)
            continue
        da, grid_uv = _grid_depths(np.asarray(fl["fwd"]), fv, K, T_k1_k, stride)
        db, _ = _grid_depths(np.asarray(fl["bwd"]), bv, K, np.linalg.inv(T_k1_k), stride)
        d_fwd.append(da if np.isfinite(da).sum() >= 20 else None)
        d_bwd.append(db if np.isfinite(db).sum() >= 20 else None)
        if d_fwd[-1] is None or d_bwd[-1] is None:
            d_fwd[-1] = d_bwd[-1] = None
            T_next_cur[-1][:3, 3] = 0.0
    return T_next_cur, d_fwd, d_bwd, grid_uv


def _grid(valid: np.ndarray, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (M, 2) of a regular grid over an (H, W) mask and the mask there (M,)."""
    h, w = valid.shape
    ys, xs = np.mgrid[stride // 2 : h : stride, stride // 2 : w : stride]
    return np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64), valid[ys.ravel(), xs.ravel()]


def _parallax_fraction(
    fl: Mapping[str, np.ndarray], static_masks: np.ndarray, k: int, K: np.ndarray, T_k1_k: np.ndarray, stride: int
) -> float:
    """Median parallax (the flow left after the pair's rotation, px) over the median flow (px) of
    pair (k, k + 1) on ``pair_masks``' grid pixels: near 0 for a rotation-dominated pair, 1 for a
    pure translation (1.0 when no pixel is usable: nothing to judge)."""
    uv, ok = _grid(pair_masks(fl, static_masks, k)[0], stride)
    if ok.sum() < 20:
        return 1.0
    uv = uv[ok]
    uv2 = uv + np.asarray(fl["fwd"], np.float64)[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    r = rays(uv, K) @ T_k1_k[:3, :3].T
    rot = r[:, :2] / r[:, 2:3] * np.array([K[0, 0], K[1, 1]]) + np.array([K[0, 2], K[1, 2]])
    flow = float(np.median(np.linalg.norm(uv2 - uv, axis=1)))
    return float(np.median(np.linalg.norm(uv2 - rot, axis=1))) / flow if flow > 0 else 1.0


def _transferred_log_scale(
    fl: Mapping[str, np.ndarray], static_masks: np.ndarray, k: int, ref_depths: np.ndarray, log_m_k: float,
    K: np.ndarray, T_k1_k: np.ndarray, stride: int,
) -> float:
    """log depth scale of frame k + 1 relative to ref_depths[k + 1]: frame k's depth
    (ref_depths[k] * exp(log_m_k)) on ``pair_masks``' grid pixels, moved into camera k + 1 by
    T_k1_k (translation in the chain's scale) and compared with frame k + 1's reference depth
    where the flow lands (median log ratio); log_m_k when fewer than 20 points land in front."""
    uv, ok = _grid(pair_masks(fl, static_masks, k)[0], stride)
    uv = uv[ok]
    uv2 = uv + np.asarray(fl["fwd"], np.float64)[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    d = sample_np(ref_depths[k], uv) * math.exp(log_m_k)
    z = ((rays(uv, K) * d[:, None]) @ T_k1_k[:3, :3].T + T_k1_k[:3, 3])[:, 2]
    front = z > 1e-6
    if front.sum() < 20:
        return log_m_k
    return float(np.median(np.log(z[front] / sample_np(ref_depths[k + 1], uv2[front]))))


def interp_pose(T_w_a: np.ndarray, T_w_b: np.ndarray, s: float) -> np.ndarray:
    """Geodesic interpolation between two camera-to-world poses (4, 4), s in [0, 1] -> (4, 4)."""
    T_a_b = np.linalg.inv(T_w_a) @ T_w_b
    r = cv2.Rodrigues(T_a_b[:3, :3])[0][:, 0]
    out = np.eye(4)
    out[:3, :3] = cv2.Rodrigues(r * s)[0]
    out[:3, 3] = T_a_b[:3, 3] * s
    return T_w_a @ out


def pnp_init(
    adjacent_flows: Sequence[Mapping[str, np.ndarray]],
    kf_frame: int,
    T_w_kf: np.ndarray,
    kf_depth: np.ndarray,
    targets: Sequence[int],
    K: np.ndarray,
    stride: int = 4,
) -> dict[int, np.ndarray]:
    """Camera-to-world poses {frame: T_w_c (4, 4)} of frames ``targets`` (all on one side of
    keyframe ``kf_frame``, pose T_w_kf, depth kf_depth (H, W)) by PnP: grid points of the keyframe,
    lifted with its (already optimised, correctly scaled) depth, are tracked through the adjacent
    flows (adjacent_flows[i]: flow dict of pair (i, i+1)) and registered in each target frame.
    Well conditioned even for tiny baselines, unlike two-view geometry; frames with too few tracks
    are omitted."""
    h, w = kf_depth.shape
    ys, xs = np.mgrid[stride // 2 : h : stride, stride // 2 : w : stride]
    uv0 = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
    d = kf_depth[ys.ravel(), xs.ravel()].astype(np.float64)
    X = rays(uv0, K) * d[:, None]
    alive = d > 0
    uv = uv0.copy()
    out: dict[int, np.ndarray] = {}
    fwd = targets[0] > kf_frame
    order = sorted(targets) if fwd else sorted(targets, reverse=True)
    cur = kf_frame
    for t in order:
        while cur != t:
            if fwd:
                fl, key, vk, nxt = adjacent_flows[cur], "fwd", "fwd_valid", cur + 1
            else:
                fl, key, vk, nxt = adjacent_flows[cur - 1], "bwd", "bwd_valid", cur - 1
            uv_prev = uv
            uv = uv + warp_sample(np.asarray(fl[key], np.float32), uv).astype(np.float64)
            # validity of the link is read at the point's position in the link's source frame
            v_ok = warp_sample(np.asarray(fl[vk], np.float32), uv_prev) > 0.5
            alive &= v_ok & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
            cur = nxt
        if alive.sum() < 12:
            continue
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            X[alive], uv[alive], K, None, reprojectionError=1.0, iterationsCount=200, flags=cv2.SOLVEPNP_EPNP
        )
        if not ok or inl is None or len(inl) < 12:
            continue
        idx = inl[:, 0]
        rvec, tvec = cv2.solvePnPRefineLM(X[alive][idx], uv[alive][idx], K, None, rvec, tvec)
        T_t_kf = np.eye(4)  # keyframe camera -> target camera
        T_t_kf[:3, :3] = cv2.Rodrigues(rvec)[0]
        T_t_kf[:3, 3] = tvec[:, 0]
        out[t] = T_w_kf @ np.linalg.inv(T_t_kf)
    return out


def splat_depth(depth_k: np.ndarray, K: np.ndarray, T_i_k: np.ndarray) -> np.ndarray:
    """Forward-warp a depth map (H, W) of frame k into frame i (T_i_k: camera k -> camera i
    coordinates) with a z-buffer at the nearest pixel; 0 where nothing lands. -> (H, W) float32
    z-depth in frame i."""
    h, w = depth_k.shape
    v, u = np.mgrid[0:h, 0:w]
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(np.float64)
    d = depth_k.ravel().astype(np.float64)
    X = rays(uv, K) * d[:, None]
    Y = X @ T_i_k[:3, :3].T + T_i_k[:3, 3]
    z = Y[:, 2]
    ok = (d > 0) & (z > 1e-6)
    ui = np.round(K[0, 0] * Y[ok, 0] / z[ok] + K[0, 2]).astype(np.int64)
    vi = np.round(K[1, 1] * Y[ok, 1] / z[ok] + K[1, 2]).astype(np.int64)
    zin = z[ok]
    inb = (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    out = np.full(h * w, np.inf)
    np.minimum.at(out, vi[inb] * w + ui[inb], zin[inb])
    out[~np.isfinite(out)] = 0.0
    return out.reshape(h, w).astype(np.float32)


def fill_small_holes(depth: np.ndarray, sigma: float = 1.0, min_density: float = 0.3) -> np.ndarray:
    """Close splatting cracks by normalised convolution in log depth (0 = hole stays a hole
    where too few neighbours are valid)."""
    m = (depth > 0).astype(np.float32)
    ld = np.where(depth > 0, np.log(np.maximum(depth, 1e-9)), 0).astype(np.float32)
    num = cv2.GaussianBlur(ld * m, (0, 0), sigma)
    den = cv2.GaussianBlur(m, (0, 0), sigma)
    fill = (m == 0) & (den > min_density)
    out = depth.copy()
    out[fill] = np.exp(num[fill] / den[fill])
    return out


def transfer_depths(
    init: np.ndarray, kf: Sequence[int], kpos: np.ndarray, kd: np.ndarray | Sequence[np.ndarray], priors: np.ndarray,
    K: np.ndarray, frames: Sequence[int],
) -> np.ndarray:
    """Depth targets (len(frames), H, W) float32 for the segment stage: keyframe depth at
    keyframes; for the other frames the z-buffered reprojection of the two bracketing keyframes
    (nearer one first), with the frame's own prior (scaled to agree) in the remaining holes.
    init (N, 4, 4) initial T_w_c of all frames; kf (Kf,) keyframe indices, kpos (Kf, 4, 4) their
    T_w_c, kd (Kf, H, W) their depths (or a sequence of (H, W) arrays, read one at a time);
    priors (len(frames), H, W) those frames' priors."""
    pri = normalised_prior(priors)
    out = np.zeros((len(frames),) + pri.shape[1:], np.float32)
    for n, i in enumerate(frames):
        j = int(np.searchsorted(kf, i, side="right")) - 1
        if j >= 0 and kf[j] == i:
            d = kd[j].copy()
        else:
            cand = [c for c in (j, j + 1) if 0 <= c < len(kf)]
            cand.sort(key=lambda c: abs(kf[c] - i))
            d = np.zeros(pri.shape[1:], np.float32)
            for c in cand:
                T_i_c = np.linalg.inv(init[i]) @ kpos[c]  # keyframe c's camera -> camera i
                sp = fill_small_holes(splat_depth(kd[c], K, T_i_c))
                d = np.where(d > 0, d, sp)
        hole = ~(d > 0)
        if hole.any():
            own = 1.0 / pri[n]
            good = ~hole
            s = (float(np.median(d[good] / own[good])) if good.sum() > 20
                 else float(np.median(kd[max(j, 0)][kd[max(j, 0)] > 0]) / np.median(own)))
            d = np.where(hole, own * s, d)
        out[n] = d
    return out

