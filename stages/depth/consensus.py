"""Multi-view depth consensus with the final poses (a gcvd-flow addition, after depth_filter).

Why: after fusion every frame's depth is triangulated where its own flows to i+-8 were
consistent and wide enough (the confident pixels, AbsRel ~0.03 on ICL); elsewhere it is the
optimised network depth (AbsRel ~0.1). The same surface is usually seen confidently from
*other* frames: a pixel in a textureless patch at frame i lies on the flow-consistent part of
frame i+32, or was triangulated with a wider angle from there. With globally consistent poses
(what GCVD's pose graph gives), frame j's depth map can be carried into frame i exactly, and
the estimates of one surface point averaged by how much each view trusts it -- what MVS
fusion (COLMAP's geometric consistency check, depth-map fusion) does, here as a per-frame
filter so the output stays one depth map per frame.

For frame i and every reference j = i +- offsets (default 8, 16, 24, 32, 48, 64: near ones see
the same flow errors, far ones are more independent):
  * back-project pixel p of i with its depth, project into j, sample j's depth and confidence
    there (bilinear, only where the four pixels mixed are valid and static), back-project that
    and move it into frame i: z_ji(p) (its depth in i) and the round-trip reprojection error
    e(p) in pixels;
  * the estimate is used when |log z_ji - log d_i| < ``max_log_dev`` (0.2; beyond: another
    surface, an occlusion), with weight (c_j^2 + prior) * exp(-(e / sigma)^2), sigma =
    ``reproj_sigma_px`` (3); frame i's own depth has weight c_i^2 + prior.
The output is the weighted mean in log depth; pixels the masks stage marks as moving keep
theirs. Confident pixels keep their depth (their weight dominates); unconfident ones are
pulled to what confident views of the same point say. Measured through the cache (one pass,
the defaults, against the stage off): AbsRel ICL 0.0523 -> 0.0492, synthetic loop 0.0404 ->
0.0374, moving-object clip 0.1465 -> 0.1445 (with max_log_dev 0.4, sigma 2 and no masks: 0.0493,
0.0376, 0.1494).

Pure function, numpy/OpenCV only. Shapes: depth float32 (H, W) in the poses' scale (0 =
invalid); confidence float32 (H, W) in [0, 1]; poses (4, 4) camera-to-world; K (3, 3).
"""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np

from gcvd_flow.stages.depth.params import DepthConsensusSettings

PRIOR_WEIGHT = 0.01  # weight of an estimate with confidence 0: it counts only where no view is sure
CONFIDENCE_POWER = 2  # a view at confidence 0.9 outweighs one at 0.5 by 3.2
BLOCK_ROWS = 32  # rows of frame i handled at once (the result is bit-identical for any)


class _Camera:
    """Pinhole K (3, 3) and the pixel grid of an (H, W) frame, built once per frame.

    Points are handled in pixel-homogeneous form (u z, v z, z): a rigid motion T of camera
    coordinates is then the 3x4 matrix [K R K^-1 | K t] on them: one (3, 3) @ (3, N) product
    instead of nine scaled adds (the stage's cost is these per-pixel passes)."""

    def __init__(self, K: np.ndarray, h: int, w: int):
        self.K = np.asarray(K, np.float64)
        self.h, self.w = h, w
        self.u = np.broadcast_to(np.arange(w, dtype=np.float32)[None, :], (h, w))
        self.v = np.broadcast_to(np.arange(h, dtype=np.float32)[:, None], (h, w))

    def motion(self, T: np.ndarray) -> np.ndarray:
        """T (4, 4) on camera coordinates as a 3x4 float64 matrix on (u z, v z, z, 1)."""
        K = self.K
        return np.concatenate([K @ T[:3, :3] @ np.linalg.inv(K), (K @ T[:3, 3])[:, None]], 1)

    def moved(self, T: np.ndarray, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, ...]:
        """Pixels (u, v) at depth z (H, W) each, in the frame T moves them to: (u', v', z')."""
        return self.moved_by(self.motion(T).astype(np.float32), u, v, z)

    @staticmethod
    def moved_by(M: np.ndarray, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, ...]:
        """``moved`` with T's float32 ``motion`` M (3, 4) given (computed once per pair of frames)."""
        pts = np.stack([u * z, v * z, z]).reshape(3, -1)
        out = M[:, :3] @ pts
        out += np.ascontiguousarray(M[:, 3:])  # (a broadcast from the strided column is 10x slower)
        pu, pv, pz = out.reshape(3, *z.shape)
        # a point behind the camera (z' <= 0) lands far outside the image: nothing is sampled there
        pz_safe = np.maximum(pz, 1e-6)
        return pu / pz_safe, pv / pz_safe, pz


_DEFAULTS = DepthConsensusSettings()  # the stage's parameters (stages/depth/params.py)


def carry_depth(cam: _Camera, rows: slice, depth_i: np.ndarray, depth_j: np.ndarray, conf_j: np.ndarray,
                T_j_i: np.ndarray, valid_j: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """Frame j's depth carried to frame i's pixels in ``rows``.

    depth_i: (R, W) float32, frame i's depth in those rows; depth_j, conf_j: (H, W) float32;
    T_j_i (4, 4) maps frame-i camera coordinates to frame j's (inv(T_w_j) @ T_w_i); valid_j: (H, W)
    float32, 1 where depth_j > 0 (computed here when not given). Returns, (R, W) each: z, depth
    in frame i of the point j sees where i's pixel lands; c, j's confidence there; err2 px^2,
    squared distance between i's pixel and that point projected back into i; ok bool, all four
    pixels the bilinear sample mixes are inside j and valid (a sample mixing a depth with the
    zeros of invalid pixels or of the outside would be a depth no surface has), in front of i.
    """
    if valid_j is None:
        valid_j = (depth_j > 0).astype(np.float32)
    return _carry(cam, rows, depth_i, _CarryRef(cam, T_j_i, depth_j, conf_j, valid_j))


class _CarryRef:
    """A reference j of frame i as ``_carry`` reads it: the float32 motions i -> j and j -> i
    (``_Camera.motion``, once per pair rather than once per block of rows), j's depth,
    confidence and valid (float32, 1 = valid and static)."""

    __slots__ = ("to_j", "to_i", "depth", "conf", "valid")

    def __init__(self, cam: _Camera, T_j_i: np.ndarray, depth_j: np.ndarray, conf_j: np.ndarray, valid_j: np.ndarray):
        self.to_j = cam.motion(T_j_i).astype(np.float32)
        self.to_i = cam.motion(np.linalg.inv(T_j_i)).astype(np.float32)
        self.depth, self.conf, self.valid = depth_j, conf_j, valid_j


def _carry(cam: _Camera, rows: slice, depth_i: np.ndarray, view: _CarryRef) -> tuple[np.ndarray, ...]:
    """``carry_depth`` of one reference (the same arithmetic)."""
    u, v = cam.u[rows], cam.v[rows]
    qu, qv, _ = cam.moved_by(view.to_j, u, v, depth_i)
    dj, cj, vj = (cv2.remap(a, qu, qv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
                  for a in (view.depth, view.conf, view.valid))
    # j's point at the landing position, moved back into frame i
    pu, pv, pz = cam.moved_by(view.to_i, qu, qv, dj)
    ok = (vj > 0.999) & (pz > 1e-6)
    err2 = (pu - u) ** 2 + (pv - v) ** 2
    return np.where(ok, pz, 1.0), cj, err2, ok


def consensus_depth(
    depth: np.ndarray,
    confidence: np.ndarray,
    pose: np.ndarray,
    refs: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
    K: np.ndarray,
    max_log_dev: float = _DEFAULTS.max_log_dev,
    reproj_sigma_px: float = _DEFAULTS.reproj_sigma_px,
    static: np.ndarray | None = None,
    ref_static: Sequence[np.ndarray] | None = None,
) -> np.ndarray:
    """Frame i's depth float32 (H, W) averaged with its references' (module docstring).

    refs: [(depth_j (H, W), confidence_j (H, W), pose_j (4, 4) camera-to-world), ...]. Pixels
    with depth 0 stay 0; with no reference the depth is returned unchanged. static (H, W) and
    ref_static [(H, W), ...] (1 = static, the masks stage's): a moving object is where the
    poses do not say where a point goes, so its pixels in frame i keep their depth and its
    pixels in a reference are not sampled (without: AbsRel of the moving-object clip 0.1465 ->
    0.1494, the object's depth smeared onto the background it passes; with: 0.1445).
    """
    depth = np.asarray(depth, np.float32)
    confidence = np.asarray(confidence, np.float32)
    cam = _Camera(K, *depth.shape)
    pose = np.asarray(pose, np.float64)
    statics: Sequence[np.ndarray | None] = [None] * len(refs) if ref_static is None else ref_static
    views = [_CarryRef(cam, np.linalg.inv(np.asarray(pose_j, np.float64)) @ pose, np.asarray(depth_j, np.float32),
                   np.asarray(conf_j, np.float32),
                   ((np.asarray(depth_j) > 0) & (True if st is None else np.asarray(st) > 0)).astype(np.float32))
             for (depth_j, conf_j, pose_j), st in zip(refs, statics)]
    out = np.zeros_like(depth)
    # blocks of rows: every temporary stays small (heap-allocated, in cache); whole 256x192
    # temporaries are fresh pages on every allocation (page faults) and took ~1.4x as long
    for r0 in range(0, depth.shape[0], BLOCK_ROWS):
        rows = slice(r0, r0 + BLOCK_ROWS)
        out[rows] = _consensus_rows(cam, rows, depth[rows], confidence[rows], views, max_log_dev, reproj_sigma_px)
    if static is not None:
        out = np.where(np.asarray(static) > 0, out, depth)
    return out


def _consensus_rows(cam: _Camera, rows: slice, depth: np.ndarray, confidence: np.ndarray,
                    views: list[_CarryRef], max_log_dev: float, reproj_sigma_px: float) -> np.ndarray:
    """``consensus_depth`` of the pixels in ``rows``."""
    valid = depth > 0
    log_d = np.log(np.where(valid, depth, 1.0))
    own = confidence ** CONFIDENCE_POWER + PRIOR_WEIGHT
    num, den = own * log_d, own.copy()
    inv_var = 1.0 / np.float32(reproj_sigma_px) ** 2
    for view in views:
        z, c, err2, ok = _carry(cam, rows, depth, view)
        log_z = np.log(z)
        use = ok & (np.abs(log_z - log_d) < max_log_dev)
        wgt = np.where(use, (c ** CONFIDENCE_POWER + PRIOR_WEIGHT) * np.exp(-err2 * inv_var), 0.0)
        num += wgt * log_z
        den += wgt
    return np.where(valid, np.exp(num / den), 0.0).astype(np.float32)


# ------------------------------------------------------------------ forward splatting (splat_offsets)
KEEP_POWER = 2.0
SPLAT_FOOTPRINT = ((0, 0), (1, 0), (0, 1), (1, 1))  # a point covers the 4 pixels around where it lands


def splat_points(K: np.ndarray, shape: tuple[int, int], T_i_j: np.ndarray, depth_j: np.ndarray,
                 weight_j: np.ndarray, target: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame j's pixels with weight > 0 moved into frame i (T_i_j maps j's camera coordinates to
    i's) and projected: (flat pixel index into i's (H, W) grid, depth in i, weight), each point
    covering the 4 pixels around its landing position (no holes between neighbours on a
    receding surface); points behind i or outside its image are left out, and with ``target``
    (bool (H, W)) the landings on pixels where it is False."""
    return project_source(splat_source(K, depth_j, weight_j), K, shape, T_i_j,
                          None if target is None else SplatTarget(target))


class SplatSource:
    """A reference's splatted pixels, independent of the frame they are splatted into: their
    points in the reference's camera (float64 (3, N)) and weights (float64 (N,)). Computed once
    per reference and reused for every target frame (``splat_consensus(sources=...)``)."""

    __slots__ = ("X", "weight")

    def __init__(self, X: np.ndarray, weight: np.ndarray):
        self.X, self.weight = X, weight


def splat_source(K: np.ndarray, depth_j: np.ndarray, weight_j: np.ndarray) -> SplatSource:
    """The pixels of frame j with weight > 0 back-projected with their depth (see ``splat_points``)."""
    K = np.asarray(K, np.float64)
    vs, us = np.nonzero(weight_j > 0)
    z = np.asarray(depth_j, np.float64)[vs, us]
    rays = np.stack([us, vs, np.ones_like(us)], 0).astype(np.float64)
    return SplatSource((np.linalg.inv(K) @ rays) * z, np.asarray(weight_j, np.float64)[vs, us])


class SplatTarget:
    """A target mask (bool (H, W)) with what ``project_source`` reads of it computed once: the flat
    mask and, flat over the landing positions -2 <= u <= W, -2 <= v <= H (floor; -2 and W / H stand
    for every position further out), whether a landing's footprint reaches it."""

    __slots__ = ("flat", "reach")

    def __init__(self, target: np.ndarray):
        target = np.asarray(target, bool)
        h, w = target.shape
        reach = np.zeros((h + 3, w + 3), bool)
        reach[1:h + 2, 1:w + 2] = _footprint_reach(target)
        self.flat, self.reach = target.ravel(), reach.ravel()


def project_source(src: SplatSource, K: np.ndarray, shape: tuple[int, int], T_i_j: np.ndarray,
                   target: SplatTarget | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``splat_points`` of a precomputed reference.

    The arithmetic of every landing is that of the first version (two float64 products on all
    the points: BLAS gives other last bits on a subset of them, 5 of 480 subsets tried), so the
    bits are the same; what changed is the bookkeeping around it (no copy when every point is in
    front, the landing tested against ``target`` in one lookup on the floored floats, only the
    few that reach it converted to int): 1.4 -> 0.6 ms per call on ICL, 3.7 % of the points
    reach a target there (docs/log/2026-11-28-cons.md)."""
    h, w = shape
    K = np.asarray(K, np.float64)
    Y = T_i_j[:3, :3] @ src.X
    Y += T_i_j[:3, 3:4]
    front = Y[2] > 1e-6
    if front.all():
        wj = src.weight
    else:
        Y, wj = Y[:, front], src.weight[front]
    q = K @ Y
    u = np.divide(q[0], q[2])
    v = np.divide(q[1], q[2])
    np.floor(u, out=u)
    np.floor(v, out=v)
    if target is not None:  # first drop the points whose whole footprint misses the targets (same landings)
        np.clip(u, -2, w, out=u)  # -2 and w (h): every position whose footprint is outside
        np.clip(v, -2, h, out=v)
        code = v + 2
        code *= w + 3
        code += u
        code += 2
        sel = np.flatnonzero(target.reach[code.astype(np.intp)])
        uf, vf, zj, wj = u[sel].astype(np.int64), v[sel].astype(np.int64), Y[2, sel], wj[sel]
    else:
        uf, vf, zj = u.astype(np.int64), v.astype(np.int64), Y[2]
    idx, zs, ws = [], [], []
    for du, dv in SPLAT_FOOTPRINT:
        uu, vv = uf + du, vf + dv
        ok = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
        flat = vv[ok] * w + uu[ok]
        if target is not None:
            hit = target.flat[flat]
            ok[ok] = hit
            flat = flat[hit]
        idx.append(flat)
        zs.append(zj[ok])
        ws.append(wj[ok])
    return np.concatenate(idx), np.concatenate(zs), np.concatenate(ws)


def _footprint_reach(target: np.ndarray) -> np.ndarray:
    """bool (H + 1, W + 1): [v + 1, u + 1] is True when a point landing at (u, v) (floor, -1 <= u < W,
    -1 <= v < H) covers a target pixel with its SPLAT_FOOTPRINT (offsets 0 or 1)."""
    h, w = target.shape
    pad = np.zeros((h + 2, w + 2), bool)
    pad[1:h + 1, 1:w + 1] = target
    reach = np.zeros((h + 1, w + 1), bool)
    for du, dv in SPLAT_FOOTPRINT:
        reach |= pad[dv:dv + h + 1, du:du + w + 1]
    return reach


def splat_consensus(
    depth: np.ndarray,
    confidence: np.ndarray,
    pose: np.ndarray,
    refs: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
    K: np.ndarray,
    guide: np.ndarray | None = None,
    min_confidence: float = 0.5,
    front: float = 0.1,
    static: np.ndarray | None = None,
    ref_static: Sequence[np.ndarray | None] | None = None,
    keep_confidence: float | None = None,
    keep_edges: float | None = None,
    ref_edge_jump: float | None = None,
    sources: Sequence[SplatSource | None] | None = None,
) -> np.ndarray:
    """Frame i's depth float32 (H, W) corrected with its references' confident depth splatted
    forward into it (z-buffered), and the correction spread edge-aware over what no view covers.

    ``consensus_depth`` carries a reference's depth to where frame i's *own* depth says a pixel's
    point lands, and uses it only within ``max_log_dev`` of that depth: where frame i's depth is
    bad (a texture-less wall no flow triangulates, 20-40 % off), the point lands elsewhere and
    is rejected as an occlusion. Splatting does not need frame i's depth: every confident pixel
    (>= ``min_confidence``, static) of a reference is moved into frame i with the final poses;
    per pixel the nearest landing depth z_min is the visible surface and the landings within
    ``front`` (relative) of it are averaged in log depth, weighted by confidence^2, with frame i's
    own estimate (weight confidence^2 + PRIOR_WEIGHT). With ``guide`` (grey (H, W) in [0, 1]) the
    log correction of the pixels that were covered or are confident themselves is densified
    by guided filtering over the image (``stages.frontend.priors.densify``) into the pixels
    neither covered nor confident: the correction is smooth where the depth error is (a
    surface's depth off by a scale), the depth's own shape is kept.

    With ``keep_confidence``, frame i's pixels at least that confident keep their own depth (their
    correction is 0, and it anchors the spread): with tens of references a confident pixel's own
    estimate is otherwise outvoted by the other views' landings, each with its own small error
    and the splat's rounding (ICL, 93 % confident: AbsRel 0.048 -> 0.060 without, see
    docs/log/2026-11-28-depth2.md).

    refs: [(depth_j (H, W), confidence_j (H, W), pose_j (4, 4) camera-to-world), ...]; static /
    ref_static as in ``consensus_depth``. Pixels with depth 0 stay 0. ``sources``: the refs'
    ``reference_sources`` (the same min_confidence, ref_static and ref_edge_jump), computed once
    when the references serve several frames; the output is the same bits.
    """
    depth = np.asarray(depth, np.float32)
    h, w = depth.shape
    valid = depth > 0
    conf = np.asarray(confidence, np.float64)
    pose = np.asarray(pose, np.float64)
    T_i_w = np.linalg.inv(pose)
    target = _splat_targets(conf, valid, min_confidence, keep_confidence, keep_edges, depth)
    if sources is None:
        sources = reference_sources(refs, ref_static, K, min_confidence, ref_edge_jump)
    pts = _landings(refs, sources, T_i_w, K, (h, w), target)
    if not pts:
        return depth
    idx, z, wt = (np.concatenate(a) for a in zip(*pts))
    zmin = np.full(h * w, np.inf)
    np.minimum.at(zmin, idx, z)
    keep = z < zmin[idx] * (1.0 + front)  # the visible surface, not what it occludes
    num = np.bincount(idx[keep], wt[keep] * np.log(z[keep]), h * w).reshape(h, w)
    den = np.bincount(idx[keep], wt[keep], h * w).reshape(h, w)
    log_d = np.log(np.where(valid, depth, 1.0).astype(np.float64))
    own = conf ** CONFIDENCE_POWER + PRIOR_WEIGHT
    fused = (own * log_d + num) / (own + den)
    if keep_confidence is not None:
        alpha = np.clip(conf / max(keep_confidence, 1e-6), 0.0, 1.0) ** KEEP_POWER
        fused = alpha * log_d + (1.0 - alpha) * fused
    if keep_edges is not None:
        fused = np.where(_near_depth_edge(log_d, valid, keep_edges), log_d, fused)
    if guide is not None:
        fused = _spread_correction(guide, log_d, fused, (den > 0) | (conf >= min_confidence))
    out = np.where(valid, np.exp(fused), 0.0).astype(np.float32)
    if static is not None:
        out = np.where(np.asarray(static) > 0, out, depth)
    return out


def _landings(refs: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]], sources: Sequence[SplatSource | None],
              T_i_w: np.ndarray, K: np.ndarray, shape: tuple[int, int],
              target: np.ndarray | None) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Every reference's splat source moved into frame i (T_i_w: world to frame i's camera)."""
    tgt = None if target is None else SplatTarget(target)
    return [project_source(src, K, shape, T_i_w @ np.asarray(pose_j, np.float64), tgt)
            for (_, _, pose_j), src in zip(refs, sources) if src is not None]


def reference_sources(refs: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
                      ref_static: Sequence[np.ndarray | None] | None, K: np.ndarray, min_confidence: float,
                      ref_edge_jump: float | None, cache: SourceCache | None = None,
                      names: Sequence[str] | None = None) -> list[SplatSource | None]:
    """Per reference, its confident static pixels (weight confidence^2; with ``ref_edge_jump`` the
    confidence lowered at its own depth edges) as a ``SplatSource`` (None: nothing to splat). They
    do not depend on the target frame: compute them once for all the frames a reference serves
    (``cache``: a ``SourceCache`` kept across the frames). ``names``: per reference a string that
    names its depth, confidence and static mask exactly (the store's digests of the values they
    come from); without, the cache keys on a hash of their content."""
    out: list[SplatSource | None] = []
    for k, (depth_j, conf_j, _) in enumerate(refs):
        st = None if ref_static is None else ref_static[k]
        key = b"" if cache is None else cache.key(K, depth_j, conf_j, st, min_confidence, ref_edge_jump,
                                                  None if names is None else names[k])
        if cache is not None and key in cache:
            out.append(cache.get(key))
            continue
        dj = np.asarray(depth_j, np.float32)
        if ref_edge_jump is not None:  # a reference's pixels straddling its occlusion boundaries
            conf_j = edge_confidence(dj, conf_j, ref_edge_jump)
        wj = np.where((dj > 0) & (np.asarray(conf_j) >= min_confidence), np.asarray(conf_j, np.float64) ** 2, 0.0)
        if st is not None:
            wj = np.where(np.asarray(st) > 0, wj, 0.0)
        out.append(splat_source(K, dj, wj) if wj.any() else None)
        if cache is not None:
            cache.put(key, out[-1])
    return out


SOURCE_CACHE_BYTES = 256 << 20


class SourceCache:
    """The ``SplatSource`` of the references seen last, at most ``capacity`` of them and ``budget``
    bytes (least recently used first out), keyed by everything they are computed from (depth,
    confidence, static mask, K, min_confidence, ref_edge_jump): a frame serves as reference to
    every frame within the largest splat offset, each time the same source. ~32 bytes per
    splatted pixel per entry (ICL 256x192: ~1.3 MB); the +-64 window of the defaults touches
    ~170 references over the 16 frames between two uses of a far one, so the budget holds ~190."""

    def __init__(self, capacity: int = 100_000, budget: int = SOURCE_CACHE_BYTES):
        from collections import OrderedDict

        self.capacity, self.budget = capacity, budget
        self._d: OrderedDict[bytes, tuple[SplatSource | None, int]] = OrderedDict()
        self.bytes = 0
        self.hits = 0
        self.hashed = 0  # keys computed from the arrays' content (no ``name``)

    def key(self, K: np.ndarray, depth: np.ndarray, conf: np.ndarray, static: np.ndarray | None,
            min_confidence: float, ref_edge_jump: float | None, name: str | None = None) -> bytes:
        """The key of a reference's source; with ``name`` (exactly naming depth, confidence and
        static mask, e.g. their store digests) the arrays are not read."""
        import hashlib

        hsh = hashlib.blake2b(repr((float(min_confidence), ref_edge_jump)).encode(), digest_size=20)
        hsh.update(np.ascontiguousarray(K, np.float64).data)
        if name is not None:
            hsh.update(b"name:" + name.encode())
            return hsh.digest()
        self.hashed += 1
        for a in (np.asarray(depth), np.asarray(conf), static):
            if a is None:
                hsh.update(b"none")
                continue
            a = np.ascontiguousarray(a)
            hsh.update(repr((a.dtype.str, a.shape)).encode())
            hsh.update(a.data)
        return hsh.digest()

    def __contains__(self, key: bytes) -> bool:
        return key in self._d

    def get(self, key: bytes) -> SplatSource | None:
        self._d.move_to_end(key)
        self.hits += 1
        return self._d[key][0]

    def put(self, key: bytes, src: SplatSource | None) -> None:
        n = 64 if src is None else 64 + src.X.nbytes + src.weight.nbytes
        if key in self._d:
            self.bytes -= self._d[key][1]
        self._d[key] = (src, n)
        self.bytes += n
        while len(self._d) > self.capacity or self.bytes > self.budget:
            self.bytes -= self._d.popitem(last=False)[1][1]


def _splat_targets(conf: np.ndarray, valid: np.ndarray, min_confidence: float, keep_confidence: float | None,
                   keep_edges: float | None, depth: np.ndarray) -> np.ndarray | None:
    """bool (H, W): the pixels of frame i whose output a landing can change (None: all). A pixel
    that keeps its own depth (confidence >= ``keep_confidence``, or at its own depth edge with
    ``keep_edges``) and is confident (so it anchors the spread whatever lands on it) takes no
    landing: leaving its landings out gives the same bits (each pixel's z-buffer and sums are its
    own) and skips most of the work on a well-measured clip (ICL: ~90 % of the pixels)."""
    if keep_confidence is None and keep_edges is None:
        return None
    kept = np.zeros(conf.shape, bool)
    if keep_confidence is not None:
        kept |= conf >= max(keep_confidence, 1e-6)
    if keep_edges is not None:
        kept |= _near_depth_edge(np.log(np.where(valid, depth, 1.0).astype(np.float64)), valid, keep_edges)
    return ~(kept & valid & (conf >= min_confidence))


def _near_depth_edge(log_d: np.ndarray, valid: np.ndarray, jump: float) -> np.ndarray:
    """bool (H, W): pixels within 2 px of a log-depth jump > ``jump`` of the frame's own depth (the
    5x5 range of log depth; invalid pixels count as edges): where a 2x2 splat footprint puts a
    foreground point over the background and a rounded landing straddles the boundary."""
    k = np.ones((5, 5), np.uint8)
    ld = log_d.astype(np.float32)
    near = (cv2.dilate(ld, k) - cv2.erode(ld, k)) > jump
    return near | (cv2.dilate((~valid).astype(np.uint8), k) > 0)


EDGE_CONFIDENCE_FACTOR = 0.45  # at a depth edge even confidence 1 falls below 0.5 (unconfident)


def edge_confidence(depth: np.ndarray, confidence: np.ndarray, jump: float, radius: int = 2) -> np.ndarray:
    """confidence float32 (H, W), multiplied by ``EDGE_CONFIDENCE_FACTOR`` within ``radius`` px of a
    jump of the frame's log depth larger than ``jump`` (the (2 radius + 1)^2 range) or of an invalid
    pixel.

    Flow-consistent triangulation marks a pixel confident whatever it straddles; at an occlusion
    boundary the depth is a mix of the two surfaces (DIS's patches, the 3x3 median, the network's
    smooth mesh), a few % to tens of % off. The confident pixels within 2 px of a 10 % jump are
    10 % of them on the HoloLens walk, AbsRel 0.149 against 0.056 for the rest (ICL: 7 %, 0.136
    against 0.027; docs/log/2026-11-28-depth2.md). The depth itself is not changed."""
    depth = np.asarray(depth, np.float32)
    valid = depth > 0
    k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    ld = np.log(np.where(valid, depth, 1.0)).astype(np.float32)
    ld_hi = cv2.dilate(np.where(valid, ld, -1e6).astype(np.float32), k)
    ld_lo = cv2.erode(np.where(valid, ld, 1e6).astype(np.float32), k)
    edge = valid & ((ld_hi - ld_lo) > jump)
    edge |= valid & (cv2.dilate((~valid).astype(np.uint8), k) > 0)
    conf = np.asarray(confidence, np.float32)
    return np.where(edge, conf * np.float32(EDGE_CONFIDENCE_FACTOR), conf).astype(np.float32)


def _spread_correction(guide: np.ndarray, log_d: np.ndarray, fused: np.ndarray, known: np.ndarray) -> np.ndarray:
    """log depth (H, W): ``fused`` where ``known``, elsewhere ``log_d`` plus the correction
    fused - log_d of the known pixels densified edge-aware over ``guide``."""
    from gcvd_flow.stages.frontend.priors import densify

    if known.sum() < 16 or known.all():
        return fused
    dense, _ = densify(np.asarray(guide, np.float64), fused - log_d, known.astype(np.float64))
    return np.where(known, fused, log_d + dense)
