"""warp_sample, fb_consistency and chain_flows restructured for cost (issue 38: channels-first
sampling shared by chain_flows' links, neighbours as shifted views, the pixel grid computed once
per size) equal the former code byte for byte: flow, masks and every other reader of them keep
their outputs."""

from __future__ import annotations

import numpy as np
import pytest

from gcvd_flow.stages.frontend import flow as F


def _former_warp_sample(field, coords):
    f = np.asarray(field)
    squeeze = f.ndim == 2
    if squeeze:
        f = f[..., None]
    h, w = f.shape[:2]
    x = np.minimum(np.fmax(coords[..., 0].astype(np.float64), 0.0), w - 1.0)
    y = np.minimum(np.fmax(coords[..., 1].astype(np.float64), 0.0), h - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), w - 2) if w > 1 else np.zeros_like(x, np.int64)
    y0 = np.minimum(np.floor(y).astype(np.int64), h - 2) if h > 1 else np.zeros_like(y, np.int64)
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    ax = x - x0
    ay = y - y0
    bx, by = 1 - ax, 1 - ay
    ff = np.ascontiguousarray(f.reshape(h * w, -1).T, dtype=np.float64)
    r0, r1 = y0 * w, y1 * w
    out = None
    for rows, cols, wx, wy in ((r0, x0, bx, by), (r0, x1, ax, by), (r1, x0, bx, ay), (r1, x1, ax, ay)):
        term = ff.take(rows + cols, axis=1)
        term *= wx
        term *= wy
        out = term if out is None else out + term
    dtype = np.float32 if f.dtype != np.float64 else np.float64
    if squeeze:
        return out[0].astype(dtype)
    return np.ascontiguousarray(np.moveaxis(out, 0, -1), dtype=dtype)


def _former_fb(fwd, bwd, thresh=1.0):
    h, w = fwd.shape[:2]
    tgt = F._grid(h, w) + fwd.astype(np.float64)
    inside = F._inside(tgt, h, w)
    back = _former_warp_sample(bwd, tgt)
    return inside & (np.linalg.norm(fwd.astype(np.float64) + back, axis=-1) < thresh)


def _former_chain(flows):
    f0, v0 = flows[0]
    h, w = f0.shape[:2]
    base = F._grid(h, w)
    total = f0.astype(np.float64).copy()
    valid = np.asarray(v0, bool).copy()
    valid &= F._inside(base + total, h, w)
    for f, vm in flows[1:]:
        pos = base + total
        both = np.concatenate([f.astype(np.float64), np.asarray(vm, np.float64)[..., None]], -1)
        sampled = _former_warp_sample(both, pos)
        total = total + sampled[..., :2]
        valid &= sampled[..., 2] > 0.999
        valid &= F._inside(base + total, h, w)
    return total.astype(np.float32), valid


def _flow(rng, h, w, scale):
    return (rng.normal(size=(h, w, 2)) * scale).astype(np.float32)


@pytest.mark.parametrize("h,w", [(72, 96), (1, 7), (6, 1), (2, 2)])
def test_warp_sample_equals_the_former_code(h, w):
    rng = np.random.default_rng(h * 100 + w)
    coords = np.stack([rng.uniform(-3, w + 3, size=(h, w)), rng.uniform(-3, h + 3, size=(h, w))], -1)
    coords[0, 0] = (np.nan, 1.0)
    coords[-1, -1] = (np.inf, -np.inf)
    coords[..., 0][rng.uniform(size=(h, w)) < 0.2] = w - 1.0  # on the last column / row exactly
    coords[..., 1][rng.uniform(size=(h, w)) < 0.2] = h - 1.0
    for field in (rng.normal(size=(h, w)).astype(np.float32), rng.normal(size=(h, w, 3)),
                  rng.normal(size=(h, w, 2)).astype(np.float32), rng.uniform(size=(h, w)) > 0.5):
        got, want = F.warp_sample(field, coords), _former_warp_sample(field, coords)
        assert got.dtype == want.dtype and got.shape == want.shape and np.array_equal(got, want, equal_nan=True)
    pts = coords.reshape(-1, 2)[:5]  # a list of points rather than an image of them
    field = rng.normal(size=(h, w, 2))
    assert np.array_equal(F.warp_sample(field, pts), _former_warp_sample(field, pts))


def test_fb_consistency_and_chain_equal_the_former_code():
    rng = np.random.default_rng(7)
    h, w = 72, 96
    for scale in (0.3, 4.0):
        fwd, bwd = _flow(rng, h, w, scale), _flow(rng, h, w, scale)
        assert np.array_equal(F.fb_consistency(fwd, bwd, 0.7), _former_fb(fwd, bwd, 0.7))
        smooth = np.float32([1.3, -0.7]) * scale + _flow(rng, h, w, 0.05)
        got = F.fb_consistency(smooth, -smooth)  # a consistent pair: most pixels valid
        assert np.array_equal(got, _former_fb(smooth, -smooth)) and got.mean() > 0.3
        links = [(_flow(rng, h, w, scale), rng.uniform(size=(h, w)) > 0.05) for _ in range(6)]
        for k in (1, 2, 6):
            (f, v), (f0, v0) = F.chain_flows(links[:k]), _former_chain(links[:k])
            assert np.array_equal(f, f0) and np.array_equal(v, v0) and v.any()


def _former_motion_residual(K, flow, valid, seed=0):
    import cv2

    from gcvd_flow.stages.frontend import masks as M

    pa, pb = M._correspondences(flow, valid)
    if len(pa) < M.MIN_POINTS:
        return None
    cv2.setRNGSeed(seed)
    E, inl_e = cv2.findEssentialMat(pa, pb, K, method=cv2.RANSAC, prob=0.999, threshold=1.0)
    Hm, inl_h = cv2.findHomography(pa, pb, cv2.RANSAC, 1.5)
    n_e = int(inl_e.sum()) if inl_e is not None and E is not None and E.shape == (3, 3) else -1
    n_h = int(inl_h.sum()) if inl_h is not None and Hm is not None else -1
    h, w = flow.shape[:2]
    v, u = np.mgrid[0:h, 0:w]
    p = np.stack([u, v], -1).reshape(-1, 2).astype(np.float64)
    q = p + flow.reshape(-1, 2).astype(np.float64)
    if n_h >= 0.9 * max(n_e, 0) and n_h > 0:
        ph = np.concatenate([p, np.ones((len(p), 1))], 1) @ Hm.T
        pred = ph[:, :2] / np.maximum(np.abs(ph[:, 2:3]), 1e-9) * np.sign(ph[:, 2:3])
        res = np.linalg.norm(pred - q, axis=1)
    elif n_e > 0:
        Kinv = np.linalg.inv(K)
        res = np.sqrt(M._sampson(Kinv.T @ E @ Kinv, p, q))
    else:
        return None
    return res.reshape(h, w).astype(np.float32)


def _former_ratio(K, flows, sigma_mult, min_threshold=1.0, seed=0):
    h, w = flows[0][0].shape[:2]
    ratio = np.zeros((h, w), np.float32)
    for flow, valid in flows:
        valid = np.asarray(valid, bool)
        res = _former_motion_residual(K, flow, valid, seed)
        if res is None:
            continue
        r = res[valid]
        if r.size == 0:
            continue
        sigma = 1.4826 * np.median(np.abs(r - np.median(r)))
        thr = max(min_threshold, float(np.median(r) + sigma_mult * sigma))
        ratio = np.maximum(ratio, np.where(valid, res / thr, 0.0).astype(np.float32))
    return ratio


def test_motion_masks_equal_the_former_code():
    """masks: the residual statistics computed once per neighbour (both thresholds read them) and
    the pixel grid shared: the same ratios and masks as the former code."""
    from gcvd_flow.evaluate.synth import render_clip
    from gcvd_flow.stages.frontend import masks as M

    clip = render_clip(8, "orbit", size=(96, 72), seed=2)
    pairs = [F.compute_pair_flow(clip.frames[j], clip.frames[j + 1]) for j in range(6)]
    links = [(p["fwd"], p["fwd_valid"]) for p in pairs]
    flows = [links[0], F.chain_flows(links)]
    for fl in (flows, [links[0]]):
        assert all(np.array_equal(M.motion_residual(clip.K, f, np.asarray(v, bool)),
                                  _former_motion_residual(clip.K, f, np.asarray(v, bool))) for f, v in fl)
        for sm in (4.0, 5.0):
            got = M._residual_ratio(clip.K, fl, sm, 1.0, 0)
            assert np.array_equal(got, _former_ratio(clip.K, fl, sm)) and got.max() > 0
    static, solve = M.motion_masks(clip.K, flows, image=clip.frames[0], sigma_mult=5.0, texture_frac=1.0)
    weighted = _former_ratio(clip.K, flows, 5.0) * M.texture_weight(clip.frames[0], 1.0)
    want_static = M._clean(weighted > 1.0, 0.002, 5)
    want_solve = np.minimum(want_static, M._clean(_former_ratio(clip.K, flows, 4.0) > 1.0, 0.002, 5))
    assert np.array_equal(static, want_static) and np.array_equal(solve, want_solve)
    # a neighbour without a valid pixel carries no evidence (as before)
    empty = [(flows[0][0], np.zeros_like(flows[0][1], bool))]
    assert not M._residual_ratio(clip.K, empty, 5.0, 1.0, 0).any()
