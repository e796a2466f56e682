"""Flow-guided temporal depth filter (CVD2 style, docs/design.md, "Stage: depth_filter")."""

from __future__ import annotations

import numpy as np
from geometry_ref import rigid_flow

from gcvd_flow.stages.depth.filter import chain_flow, filter_depth

F = 100.0
W, H = 128, 96
K = np.array([[F, 0.0, (W - 1) / 2], [0.0, F, (H - 1) / 2], [0.0, 0.0, 1.0]])


def _plane_clip(n: int, step_x: float) -> tuple[np.ndarray, np.ndarray]:
    """Tilted plane z_w = 2 + 0.3 x_w + 0.2 y_w seen by cameras translating along x.

    Returns (depth (n, H, W) float32, poses (n, 4, 4) c2w)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rx, ry = (u - K[0, 2]) / F, (v - K[1, 2]) / F
    depths, poses = [], []
    for k in range(n):
        tx = step_x * k
        depths.append((2.0 + 0.3 * tx) / (1.0 - 0.3 * rx - 0.2 * ry))
        p = np.eye(4)
        p[0, 3] = tx
        poses.append(p)
    return np.asarray(depths, np.float32), np.asarray(poses)


def _gt_flows(depth: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = len(depth)
    fwd = np.stack([rigid_flow(depth[k], K, poses[k], poses[k + 1]) for k in range(n - 1)])
    bwd = np.stack([rigid_flow(depth[k + 1], K, poses[k + 1], poses[k]) for k in range(n - 1)])
    return np.nan_to_num(fwd), np.nan_to_num(bwd)


def _absrel(est: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    return float(np.mean(np.abs(est[mask] - gt[mask]) / gt[mask]))


def test_constant_depth_static_clip_stays_constant() -> None:
    depth = np.full((9, H, W), 2.5, np.float32)
    zeros = np.zeros((8, H, W, 2), np.float32)
    out = filter_depth(depth, zeros, zeros, center=4)
    assert out.dtype == np.float32 and out.shape == (H, W)
    np.testing.assert_allclose(out, 2.5, rtol=1e-6)
    # Window clipped at the start of the clip works too.
    np.testing.assert_allclose(filter_depth(depth, zeros, zeros, center=0), 2.5, rtol=1e-6)


def test_round_trip_is_consistent_in_both_directions() -> None:
    depth, poses = _plane_clip(9, 0.15)  # ~7 px per frame
    fwd, bwd = _gt_flows(depth, poses)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    for j in (0, 2, 6, 8):  # past and future neighbours of centre 4
        xj, yj, ok = chain_flow(fwd, bwd, 4, j, xx, yy)
        xr, yr, ok_r = chain_flow(fwd, bwd, j, 4, xj, yj)
        err = np.hypot(xr - xx, yr - yy)[ok & ok_r]
        assert ok.mean() > 0.5
        assert np.median(err) < 0.05, (j, np.median(err))
        # The track really moved (so a wrong-direction flow would show up as ~2x motion).
        assert np.median(np.abs(xj - xx)[ok]) > 10.0


def test_noise_reduced_on_synthetic_clip_with_gt_flows() -> None:
    from gcvd_flow.evaluate.synth import render_clip

    clip = render_clip(40, "orbit", size=(W, H))
    sl = slice(16, 25)  # 9 frames, ~1 deg per frame
    gt = clip.depth[sl]
    rng = np.random.default_rng(0)
    noisy = (gt * rng.lognormal(0.0, 0.05, gt.shape)).astype(np.float32)
    fwd = np.stack([rigid_flow(gt[k], clip.K, clip.poses[sl][k], clip.poses[sl][k + 1]) for k in range(8)])
    bwd = np.stack([rigid_flow(gt[k + 1], clip.K, clip.poses[sl][k + 1], clip.poses[sl][k]) for k in range(8)])
    out = filter_depth(noisy, np.nan_to_num(fwd), np.nan_to_num(bwd), center=4)
    m = out > 0
    before, after = _absrel(noisy[4], gt[4], m), _absrel(out, gt[4], m)
    assert m.mean() > 0.99
    assert after < 0.55 * before, (before, after)


def test_past_neighbours_count_as_much_as_future_ones() -> None:
    """Mirror-symmetric motion: filtering with only past or only future neighbours must help
    equally. With the authors' backward-term bug the round trip for past neighbours measures
    ~2x the motion (14 px per frame here), exp(-0.1 * e) kills their weight, and the past-only
    result stays as noisy as the input."""
    depth, poses = _plane_clip(9, 0.15)
    fwd, bwd = _gt_flows(depth, poses)
    rng = np.random.default_rng(1)
    noisy = (depth * rng.lognormal(0.0, 0.05, depth.shape)).astype(np.float32)

    past_only = noisy.copy()
    past_only[5:] = 0.0  # future depths invalid
    future_only = noisy.copy()
    future_only[:4] = 0.0
    out_p = filter_depth(past_only, fwd, bwd, center=4)
    out_f = filter_depth(future_only, fwd, bwd, center=4)
    # Compare on pixels tracked in both directions (the middle band of the image).
    m = np.zeros((H, W), bool)
    m[8:-8, 40:-40] = True
    base = _absrel(noisy[4], depth[4], m)
    ep, ef = _absrel(out_p, depth[4], m), _absrel(out_f, depth[4], m)
    assert ep < 0.6 * base, (base, ep, ef)
    assert ef < 0.6 * base, (base, ep, ef)
    assert abs(ep - ef) < 0.15 * base, (base, ep, ef)


def test_one_walk_per_side_equals_chaining_to_each_neighbour() -> None:
    """filter_depth tracks to all neighbours of a side in one walk; each track must equal
    chaining from the centre to that neighbour on its own, step by step, to the bit."""
    from gcvd_flow.stages.depth.filter import _sample, _walk, chain_flow
    from gcvd_flow.stages.geometry.image import inside_image

    def chained(fwd, bwd, start, end, x, y):
        inside = inside_image(x, y, w, h, 0.0)
        step = 1 if end >= start else -1
        for k in range(start, end, step):
            f = _sample(fwd[k] if step > 0 else bwd[k - 1], x, y)
            x, y = x + f[..., 0], y + f[..., 1]
            inside = inside & inside_image(x, y, w, h, 0.0) & np.isfinite(x) & np.isfinite(y)
        return x, y, inside

    rng = np.random.default_rng(5)
    m, h, w = 6, 24, 32
    fwd = (rng.standard_normal((m - 1, h, w, 2)) * 1.5).astype(np.float32)
    bwd = (rng.standard_normal((m - 1, h, w, 2)) * 1.5).astype(np.float32)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    for c, end in ((2, 5), (3, 0)):
        walked = {j: t for j, *t in _walk(fwd, bwd, c, end, xx, yy)}
        assert sorted(walked) == sorted(set(range(min(c, end), max(c, end) + 1)) - {c})
        for j, t in walked.items():
            ref = chained(fwd, bwd, c, j, xx, yy)
            assert all(np.array_equal(a, b) for a, b in zip(t, ref))
            assert all(np.array_equal(a, b) for a, b in zip(chain_flow(fwd, bwd, c, j, xx, yy), ref))


def test_fill_uncertain_follows_the_confident_surface_along_image_edges():
    """A low-confidence blob with wrong depth on the right plane takes the right plane's depth
    (not the left one's across the image edge); confident pixels and invalid zeros stay."""
    from gcvd_flow.stages.depth.filter import fill_uncertain

    h, w = 48, 64
    gray = np.full((h, w), 0.2)
    gray[:, 32:] = 0.8  # an image edge between two surfaces
    depth = np.ones((h, w), np.float32)
    depth[:, 32:] = 2.0
    conf = np.full((h, w), 0.9, np.float32)
    blob = np.zeros((h, w), bool)
    blob[14:34, 40:56] = True
    depth[blob], conf[blob] = 3.0, 0.0  # triangulation failed there; the network guessed 3 m
    depth[0, 0], conf[0, 0] = 0.0, 0.0
    out = fill_uncertain(gray, depth, conf, source=0.7, full=0.7)
    assert np.allclose(out[blob], 2.0, rtol=0.02)
    assert np.array_equal(out[~blob & (conf >= 0.7)], depth[~blob & (conf >= 0.7)])
    assert out[0, 0] == 0.0 and out.dtype == np.float32
    half = fill_uncertain(gray, depth, np.where(blob, 0.2, conf).astype(np.float32), source=0.7, full=0.4)
    assert np.allclose(half[blob], np.sqrt(3.0 * 2.0), rtol=0.02)  # half its own log-depth
    assert np.array_equal(fill_uncertain(gray, depth, conf, full=0.0), depth)


def test_tracks_leaving_through_nan_or_inf_are_outside() -> None:
    """The walk's inside mask (no separate isfinite test) is False once a track's flow sample is
    NaN or infinite, and each yielded mask is its own array (the earlier frames' stay as they were)."""
    from gcvd_flow.stages.depth.filter import _walk

    h, w = 6, 8
    fwd = np.zeros((3, h, w, 2), np.float32)
    fwd[1, 2, :, 0] = np.nan
    fwd[1, 4, :, 1] = np.inf
    fwd[1, 5, :, 0] = -np.inf
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    steps = list(_walk(fwd, fwd.copy(), 0, 3, xx, yy))
    assert steps[0][3].all()
    last = steps[-1][3]
    assert not last[2].any() and not last[4].any() and not last[5].any() and last[0].all()
    x, y = steps[-1][1], steps[-1][2]
    assert not (last & ~(np.isfinite(x) & np.isfinite(y))).any()  # what the isfinite test said
    assert steps[0][3].all()  # not changed by the later steps


def test_window_given_frame_by_frame_is_the_stacked_window():
    """The stage hands filter_depth its window as per-frame arrays (no stacked copy): the same bits
    as the stacked (M, H, W) / (M-1, H, W, 2) arrays, and a bad frame shape is refused."""
    import pytest

    rng = np.random.default_rng(2)
    m, h, w = 5, 20, 24
    depths = (rng.random((m, h, w)) + 0.5).astype(np.float32) * (rng.random((m, h, w)) > 0.05)
    fwd = (rng.normal(size=(m - 1, h, w, 2)) * 0.7).astype(np.float32)
    bwd = (rng.normal(size=(m - 1, h, w, 2)) * 0.7).astype(np.float32)
    for c in (0, 2, 4):
        want = filter_depth(depths, fwd, bwd, center=c)
        got = filter_depth(list(depths), list(fwd), list(bwd), center=c)
        assert want.tobytes() == got.tobytes()
    with pytest.raises(ValueError):
        filter_depth(list(depths), list(fwd[:, :-1]), list(bwd), center=2)
