"""--masks is a hard exclusion at every resolution (stages/frontend/user_masks.py): a value whose
footprint touches a user-masked pixel never enters a loss, a track, a triangulation or the depth
consensus. The tests scramble what lies under the user's masks (images, depths, priors, flows) and
ask for bit-identical losses, gradients and depths; each fails when the footprint check it covers
is removed (a masked pixel at a mask's edge kept a partial weight before)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gcvd_flow import pipeline
from gcvd_flow.stages.frontend import user_masks
from gcvd_flow.stages.optimize import losses as L
from gcvd_flow.stages.optimize.frames import keep_resize, loss_size, prepare_frames

RNG = np.random.default_rng(7)


def _blob_masks(n: int, h: int, w: int) -> np.ndarray:
    """(n, h, w) int8 hard masks: 1 static, 0 dynamic (soft), -1 a user-masked block per frame."""
    m = np.ones((n, h, w), np.int8)
    for k in range(n):
        m[k, h // 4 : h // 4 + h // 5, w // 3 + 3 * k : w // 3 + 3 * k + w // 6] = -1
        m[k, h - h // 5 :, : w // 6] = 0  # a motion-masked corner stays soft
    return m


@pytest.mark.parametrize("hw,scale", [((96, 128), 0.25), ((90, 130), 0.23), ((72, 96), 0.5)])
def test_loss_resolution_keep_is_a_min_pool_of_each_cells_footprint(hw, scale):
    """prepare_frames: keep and the static weight are 0 at every loss-resolution cell whose area
    footprint (the pixels the area resize averages) holds a user-masked pixel, 1 elsewhere."""
    from gcvd_flow.stages.models.depth_net import DepthNet

    H, W = hw
    masks = _blob_masks(2, H, W)
    masks[0, 1, W - 3] = -1  # single pixels: an area average would leave these cells ~0.9 weight
    masks[1, H - 2, 5] = -1
    h, w, _ = loss_size(H, W, scale)
    fr = prepare_frames(DepthNet(seed=0), RNG.integers(0, 255, (2, H, W, 3), dtype=np.uint8),
                        np.ones((2, H, W), np.float32), masks, np.eye(3), scale, (3, 4))
    want = np.ones((2, h, w))
    for i in range(h):
        for j in range(w):
            r0, r1 = (i * H) // h, -((-(i + 1) * H) // h)
            c0, c1 = (j * W) // w, -((-(j + 1) * W) // w)
            want[:, i, j] = (masks[:, r0:r1, c0:c1] >= 0).all(axis=(1, 2))
    assert fr.keep is not None and np.array_equal(fr.keep.numpy(), want)
    assert fr.static.numpy()[want == 0].max() == 0
    # without the user's masks: the loss resolution as before, no hard mask
    assert prepare_frames(DepthNet(seed=0), np.zeros((2, H, W, 3), np.uint8), np.ones((2, H, W), np.float32),
                          (masks > 0).astype(np.uint8), np.eye(3), scale, (3, 4)).keep is None
    assert np.array_equal(keep_resize(np.ones((1, H, W)), h, w).numpy(), np.ones((1, h, w)))


# ------------------------------------------------------------------------------ window losses
N, HL, WL = 3, 24, 32
KL = np.array([[30.0, 0, (WL - 1) / 2], [0, 30.0, (HL - 1) / 2], [0, 0, 1]])


def _scene():
    """A loss-resolution window of 3 frames: images, depths, keep (1 = kept), static, log prior,
    poses T_w_c (translating along x and y), and rigid tau-1 flows (+ noise) between them."""
    keep = np.ones((N, HL, WL), np.float32)
    for k in range(N):
        keep[k, 8:14, 10 + 3 * k : 18 + 3 * k] = 0
    static = keep.copy()
    static[:, 20:, :4] = 0  # a motion-masked corner
    v, u = np.mgrid[0:HL, 0:WL]
    depth = (2.0 + 0.02 * u + 0.01 * v)[None].repeat(N, 0).astype(np.float32)
    poses = np.tile(np.eye(4), (N, 1, 1))
    poses[:, 0, 3] = [0.0, 0.05, 0.1]
    poses[:, 1, 3] = [0.0, 0.02, 0.03]
    flows = {}
    for a, b in [(0, 1), (1, 2), (1, 0), (2, 1)]:
        rays = np.stack([(u - KL[0, 2]) / KL[0, 0], (v - KL[1, 2]) / KL[1, 1], np.ones_like(u, float)], -1)
        pw = rays * depth[a][..., None] + poses[a][:3, 3]
        pc = pw - poses[b][:3, 3]
        uvb = np.stack([KL[0, 0] * pc[..., 0] / pc[..., 2] + KL[0, 2], KL[1, 1] * pc[..., 1] / pc[..., 2] + KL[1, 2]], -1)
        flows[(a, b)] = (uvb - np.stack([u, v], -1) + RNG.normal(0, 0.3, uvb.shape)).astype(np.float32)
    return {"imgs": RNG.random((N, 3, HL, WL)).astype(np.float32), "depth": depth, "keep": keep, "static": static,
            "log_prior": RNG.normal(0, 0.3, (N, 1, HL, WL)).astype(np.float32), "poses": poses, "flows": flows}


def _scrambled(sc):
    """The same scene with everything under the user's masks replaced by noise."""
    out = {k: (dict(v) if isinstance(v, dict) else v.copy()) for k, v in sc.items()}
    m = sc["keep"] == 0
    rng = np.random.default_rng(11)
    out["imgs"] = np.where(m[:, None], rng.random(sc["imgs"].shape), sc["imgs"]).astype(np.float32)
    out["depth"] = np.where(m, rng.uniform(0.5, 6.0, m.shape), sc["depth"]).astype(np.float32)
    out["log_prior"] = np.where(m[:, None], rng.normal(0, 2, m[:, None].shape), sc["log_prior"]).astype(np.float32)
    for (a, b), f in sc["flows"].items():
        out["flows"][(a, b)] = np.where(m[a][..., None], rng.normal(0, 5, f.shape), f).astype(np.float32)
    return out


def _losses(sc, hard: bool = True):
    """Every term of the window's loss (all pixels of every pair, the depth-gradient term) and its
    gradients w.r.t. depth and poses."""
    from gcvd_flow.stages.models.depth_net import DepthNet, Encoded
    from gcvd_flow.stages.optimize.params import DepthModel, KeyframeSettings, LossWeights
    from gcvd_flow.stages.optimize.solver import Pair, Solver, Window

    pairs = [Pair(a, b, 1, 1.0, torch.as_tensor(f), torch.ones(HL, WL)) for (a, b), f in sc["flows"].items()]
    pairs += [Pair(0, 2, 2, 0.5), Pair(2, 0, 2, 0.5)]
    win = Window(torch.as_tensor(sc["imgs"]), Encoded(torch.zeros(N, 4, HL, WL), torch.as_tensor(sc["log_prior"])),
                 torch.as_tensor(sc["static"]), torch.zeros(N, 2, 3), torch.as_tensor(KL), pairs,
                 torch.as_tensor(sc["poses"]), torch.ones(N, dtype=torch.float64), torch.zeros(N, 2, 3), torch.ones(N),
                 keep=torch.as_tensor(sc["keep"]) if hard else None)
    solver = Solver(win, DepthNet(seed=0), None, 1e-4, DepthModel(), LossWeights(), KeyframeSettings(),
                    pair_blocks=2)
    depth = torch.as_tensor(sc["depth"]).clone().requires_grad_(True)
    T = torch.as_tensor(sc["poses"]).clone().requires_grad_(True)
    idx = torch.arange(HL * WL).repeat(len(pairs), 1)
    total = sum(solver._block_loss(b, depth, T, idx[b.sel]) for thread in solver.blocks for b in thread)
    grad = L.gradient_orientation_loss(depth, None, 3, win.static, prior_grads=solver.prior_grads).sum()
    (total + grad).backward()
    return total.detach(), grad.detach(), depth.grad, T.grad


def test_masked_cells_never_enter_a_window_loss():
    """Photometric (3x3 patches in a, bilinear samples in b), depth consistency, flow (the flow's
    target in b) and depth-gradient (3 min-pooled scales) terms: bit-identical losses and
    gradients when the images, depths, priors and flows under the user's masks are noise."""
    sc = _scene()
    a, b = _losses(sc), _losses(_scrambled(sc))
    assert float(a[0]) > 0 and float(a[1]) > 0
    for x, y in zip(a, b):
        assert torch.equal(x, y)
    assert float(a[2][torch.as_tensor(sc["keep"]) == 0].abs().max()) == 0  # no gradient into a masked cell
    # without the hard mask (the motion masks' soft treatment) the noise does leak in
    assert not torch.equal(_losses(sc, hard=False)[0], _losses(_scrambled(sc), hard=False)[0])


def test_prior_gradient_weights_are_zero_wherever_a_scale_meets_a_masked_pixel():
    keep = torch.ones(1, 16, 16)
    keep[0, 5, 6] = 0
    grads = L.prior_gradients(torch.rand(1, 16, 16) + 0.5, 3, torch.ones(1, 16, 16), keep=keep)
    w0, w1, w2 = (g[3][0] for g in grads)
    assert w0[5, 6] == 0 and w0[4, 6] == 0 and w0[5, 5] == 0  # every difference reading (5, 6)
    assert w1[2, 3] == 0 and w1[2, 2] == 0 and w1[1, 3] == 0  # the 2x2 cell (2, 3) holds it
    assert w2[1, 1] == 0 and w2[0, 1] == 0 and w2[1, 0] == 0
    soft = L.prior_gradients(torch.rand(1, 16, 16) + 0.5, 3, keep)[1][3][0]
    assert 0 < float(soft[2, 3]) < 1  # the motion masks' weights stay soft (area-pooled)


# ------------------------------------------------------------------------------ geometry stages
def test_bundle_adjustment_tracks_never_touch_a_masked_pixel():
    from gcvd_flow.stages.optimize.bundle_adjustment import flow_tracks

    h, w = 48, 64
    flow = np.zeros((h, w, 2), np.float32)
    flow[..., 0] = 1.37
    flow[..., 1] = -0.61
    fl = {"fwd": flow, "bwd": -flow, "fwd_valid": np.ones((h, w), bool), "bwd_valid": np.ones((h, w), bool)}
    edges = {(0, 5): fl, (5, 9): fl, (9, 14): fl, (0, 14): {k: v * (3 if k in ("fwd", "bwd") else 1) for k, v in fl.items()}}
    keep = [np.ones((h, w), bool) for _ in range(4)]
    for k, kp in enumerate(keep):
        kp[10 + 2 * k : 22 + 2 * k, 20 : 31 + k] = False

    def touches(tracks):
        return sum(not user_masks.footprint_kept(keep[m], np.array([u]), np.array([v]))[0]
                   for t in tracks for m, u, v in t)

    free = flow_tracks(edges, [0, 5, 9, 14], (h, w), stride=3, track_length=3)
    kept = flow_tracks(edges, [0, 5, 9, 14], (h, w), stride=3, track_length=3, keep=keep)
    assert touches(free) > 20 and touches(kept) == 0 and len(kept) > 0.6 * len(free)


def test_initial_two_view_correspondences_skip_targets_in_a_masked_pixel():
    flow = np.zeros((20, 30, 2))
    flow[..., 0] = 2.5
    keep_b = np.ones((20, 30), bool)
    keep_b[5, 12] = False
    ok = user_masks.flow_target_kept(flow, keep_b)
    # targets x + 2.5 mix columns floor and ceil: 12 from x = 9.5 - 2.5 and x = 10 (12.5)
    assert not ok[5, 9] and not ok[5, 10] and ok[5, 8] and ok[5, 11] and ok.sum() == 20 * 30 - 2


def _plane(tx: float, h: int = 72, w: int = 96, f: float = 80.0) -> np.ndarray:
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return ((2.0 + 0.3 * tx) / (1.0 - 0.3 * (u - (w - 1) / 2) / f - 0.2 * (v - (h - 1) / 2) / f)).astype(np.float32)


def _pose(tx: float) -> np.ndarray:
    p = np.eye(4)
    p[0, 3] = tx
    return p


def _K(h: int = 72, w: int = 96, f: float = 80.0) -> np.ndarray:
    return np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])


def _mask_item(keep: np.ndarray) -> dict[str, np.ndarray]:
    return {"static": keep.astype(np.uint8), "solve": keep.astype(np.uint8), "user_keep": keep.astype(np.uint8)}


def test_depth_consensus_never_averages_a_masked_pixels_depth_in():
    """References' depths under the user's masks scrambled (within the consensus's agreement
    gate, so they would be used): frame i's consensus depth is bit-identical. OpenCV's bilinear
    weights are 1/32-quantised: a sample 1/32 px from a masked pixel read it with weight 1/1024,
    which passed the consensus's 0.999 validity test before (the keep is eroded by one pixel)."""
    xs = [0.0, -0.15, 0.12, 0.3]
    keeps = [np.ones((72, 96), bool) for _ in xs]
    for k, kp in enumerate(keeps):
        kp[20:40, 30 + 5 * k : 50 + 5 * k] = False

    def run(scramble: bool, masks=None):
        rng = np.random.default_rng(3)
        refs = []
        for x, kp in zip(xs[1:], keeps[1:]):
            d = _plane(x)
            if scramble:
                d = np.where(kp, d, d * rng.uniform(0.9, 1.1, d.shape)).astype(np.float32)
            refs.append({"depth": d, "confidence": np.full(d.shape, 0.8, np.float32)})
        own = {"depth": _plane(0.0) * 1.05, "confidence": np.full((72, 96), 0.1, np.float32)}
        inputs = {"index": 0, "K": _K(), "poses": np.stack([_pose(x) for x in xs]), "depth": own, "refs": refs,
                  "ref_indices": [1, 2, 3], "static": masks or [_mask_item(kp) for kp in keeps]}
        return pipeline.run_depth_consensus(inputs, pipeline.DepthConsensusParams(), None)["depth"]

    base = run(False)
    assert np.abs(base - _plane(0.0) * 1.05).max() > 1e-3  # the references do move the depth
    assert np.array_equal(base, run(True))
    # with the user's mask only in the static mask (the masks stage's 0s, no user_keep), it leaked
    plain = [{"static": kp.astype(np.uint8)} for kp in keeps]
    assert not np.array_equal(run(False, plain), run(True, plain))


def test_depth_fusion_never_triangulates_from_a_masked_pixel():
    """Flows of frame i's user-masked pixels scrambled, and flows landing in the reference's
    user-masked pixels moved around inside them: the fused depth and confidence are bit-identical."""
    h, w, K = 72, 96, _K()
    keep_i, keep_j = np.ones((h, w), bool), np.ones((h, w), bool)
    keep_i[10:30, 10:40] = False
    keep_j[40:60, 50:80] = False
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    d = _plane(0.0)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]], -1)
    tgt = (rays * d[..., None] + np.array([-0.2, 0.0])) / d[..., None] * K[0, 0] + K[:2, 2]
    flow = (tgt - np.stack([u, v], -1)).astype(np.float32)
    into_j = ~user_masks.flow_target_kept(flow, keep_j)
    assert into_j.sum() > 200

    def run(f, with_masks=True):
        fl = {"fwd": f, "bwd": -f, "fwd_valid": np.ones((h, w), bool), "bwd_valid": np.ones((h, w), bool)}
        inputs = {"depth": d * 1.1, "poses": np.stack([_pose(0.0), _pose(0.2)]), "index": 0, "refs": [fl],
                  "ref_dirs": ["fwd"], "ref_indices": [1], "K": K}
        if with_masks:
            inputs["user_masks"] = [_mask_item(keep_i), _mask_item(keep_j)]
        out = pipeline.run_depth_fusion(inputs, pipeline.DepthFusionParams(), None)
        return out["depth"], out["confidence"]

    rng = np.random.default_rng(5)
    noisy = np.where(keep_i[..., None], flow, flow + rng.normal(0, 3, flow.shape)).astype(np.float32)
    import cv2

    deep = cv2.erode((~keep_j).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0  # 2 px inside j's mask
    inner = ~user_masks.flow_target_kept(flow, ~deep)  # moved by < 1 px, these targets stay in the mask
    assert inner.sum() > 100
    noisy = np.where(inner[..., None], noisy + rng.uniform(-0.9, 0.9, flow.shape), noisy).astype(np.float32)
    a, b = run(flow), run(noisy)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert a[1][~keep_i].max() == 0 and a[1][into_j].max() == 0 and a[1][keep_i & ~into_j].mean() > 0.1
    assert not np.array_equal(run(flow, False)[0], run(noisy, False)[0])  # without the masks: leaks


def test_depth_filter_never_reads_a_neighbours_masked_depth():
    h, w = 48, 64
    flow = np.zeros((h, w, 2), np.float32)
    flow[..., 0] = 1.3
    fl = {"fwd": flow, "bwd": -flow, "fwd_valid": np.ones((h, w), bool), "bwd_valid": np.ones((h, w), bool)}
    keeps = [np.ones((h, w), bool) for _ in range(5)]
    for k, kp in enumerate(keeps):
        kp[10:30, 20 + k : 40 + k] = False

    def run(scramble: bool, flows: bool = False, masks: bool = True):
        rng = np.random.default_rng(2)
        depths, fls = [], []
        for k, kp in enumerate(keeps):
            d = np.full((h, w), 2.0, np.float32) + 0.01 * k + 0.002 * np.arange(w, dtype=np.float32)
            if scramble and k != 2:
                d = np.where(kp, d, rng.uniform(1.9, 2.1, d.shape)).astype(np.float32)
            depths.append({"depth": d, "confidence": np.full((h, w), 0.5, np.float32)})
        for k in range(4):  # pair (k, k+1): fwd on frame k's grid, bwd on frame k+1's
            f = dict(fl)
            if flows:  # what moves a track through a masked pixel of an intermediate frame
                f["fwd"] = np.where(keeps[k][..., None], fl["fwd"], fl["fwd"] + rng.normal(0, 1, flow.shape))
                f["bwd"] = np.where(keeps[k + 1][..., None], fl["bwd"], fl["bwd"] + rng.normal(0, 1, flow.shape))
            fls.append({n: np.asarray(v, np.float32) if n in ("fwd", "bwd") else v for n, v in f.items()})
        inputs = {"center": 2, "depths": depths, "flows": fls, "image": {"image": np.zeros((h, w, 3), np.uint8)}}
        if masks:
            inputs["user_masks"] = [_mask_item(kp) for kp in keeps]
        return pipeline.run_depth_filter(inputs, pipeline.DepthFilterParams(radius=2), None)["depth"]

    base = run(False)
    assert np.array_equal(base, run(True)) and np.array_equal(base, run(True, flows=True))
    assert not np.array_equal(run(False, masks=False), run(True, flows=True, masks=False))


def test_user_mask_follows_the_frames_undistortion_and_resize():
    """A single masked source pixel: every working pixel whose undistortion remap (bilinear taps)
    or area resize reads it is out."""
    import cv2

    sw, sh = 120, 90
    intr, dist = (100.0, 100.0, 59.5, 44.5), (-0.2, 0.05, 0.001, -0.002)
    user = np.zeros((sh, sw), bool)
    user[20, 90] = True
    keep = user_masks.source_to_working(user, (sw, sh), (intr, dist))
    K = np.array([[intr[0], 0, intr[2]], [0, intr[1], intr[3]], [0, 0, 1.0]])
    mx, my = cv2.initUndistortRectifyMap(K, np.asarray(dist), None, K, (sw, sh), cv2.CV_32FC1)
    reads = ((np.floor(mx) == 90) | (np.ceil(mx) == 90)) & ((np.floor(my) == 20) | (np.ceil(my) == 20))
    assert reads.sum() >= 1 and keep[reads].max() == 0 and keep.mean() > 0.99
    small = user_masks.source_to_working(user, (sw // 3, sh // 3), (intr, dist))
    assert small[reads.nonzero()[0] // 3, reads.nonzero()[1] // 3].max() == 0
    # the masks stage: user_keep beside static / solve, both 0 where the user masked
    inputs = {"user_mask": user, "source_size": [sw, sh], "undistort": [list(intr), list(dist)]}
    assert np.array_equal(pipeline._user_keep(inputs, (sh, sw)), keep)


def test_pipeline_hands_the_users_exclusion_to_the_optimisations():
    """run_masks adds user_keep (and zeroes static / solve there); the optimisations get int8
    masks with -1 there (one frame or a lazily stacked window), bundle adjustment the kept pixels;
    without --masks the masks are the uint8 arrays of before."""
    fl = {"fwd": np.zeros((24, 32, 2), np.float32), "fwd_valid": np.ones((24, 32), bool),
          "bwd": np.zeros((24, 32, 2), np.float32), "bwd_valid": np.ones((24, 32), bool)}
    user = np.zeros((48, 64), bool)
    user[10:20, 30:41] = True
    p = pipeline.MasksParams(backend="none")
    item = pipeline.run_masks({"direction": "fwd", "chain": [fl], "user_mask": user, "source_size": [64, 48]}, p, None)
    assert item["user_keep"][5:10, 15:21].max() == 0 and item["user_keep"].sum() == 24 * 32 - 5 * 6
    assert np.array_equal(item["solve"], item["user_keep"]) and np.array_equal(item["static"], item["user_keep"])
    hard = pipeline._hard_mask(item)
    assert hard.dtype == np.int8 and set(np.unique(hard)) == {-1, 1} and np.array_equal(hard < 0, item["user_keep"] == 0)
    plain = pipeline.run_masks({"direction": "fwd", "chain": [fl]}, p, None)
    assert "user_keep" not in plain and pipeline._hard_mask(plain).dtype == np.uint8
    stack = pipeline._HardMasks([item, item, item])
    assert stack[0:3].shape == (3, 24, 32) and stack[0:3].dtype == np.int8 and np.array_equal(stack[1], hard)
    keeps = pipeline._user_keeps([item, item, item], [0, 2])
    assert len(keeps) == 2 and keeps[1].dtype == bool and pipeline._user_keeps([plain], [0]) is None


def test_geometric_prior_never_triangulates_a_masked_pixel():
    """The prior densifies triangulations of frame i's flows: flows of its user-masked pixels
    scrambled (and ones landing in the reference's mask moved inside it) leave it bit-identical."""
    import cv2

    h, w, K = 72, 96, _K()
    keep_i, keep_j = np.ones((h, w), bool), np.ones((h, w), bool)
    keep_i[10:30, 10:40] = False
    keep_j[40:60, 50:80] = False
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    d = _plane(0.0)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]], -1)
    flow = ((rays * d[..., None] + np.array([-0.2, 0.05])) / d[..., None] * K[0, 0] + K[:2, 2]
            - np.stack([u, v], -1)).astype(np.float32)
    image = (np.random.default_rng(1).random((h, w, 3)) * 255).astype(np.uint8)
    deep = cv2.erode((~keep_j).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    inner = ~user_masks.flow_target_kept(flow, ~deep)
    rng = np.random.default_rng(4)
    noisy = np.where(keep_i[..., None], flow, flow + rng.normal(0, 3, flow.shape))
    noisy = np.where(inner[..., None], noisy + rng.uniform(-0.9, 0.9, flow.shape), noisy).astype(np.float32)

    def run(f, with_masks=True):
        fl = {"fwd": f, "bwd": -f, "fwd_valid": np.ones((h, w), bool), "bwd_valid": np.ones((h, w), bool)}
        inputs = {"image": {"image": image}, "K": K, "refs": [fl], "ref_dirs": ["fwd"]}
        if with_masks:
            inputs["user_masks"] = [_mask_item(keep_i), _mask_item(keep_j)]
        return pipeline.run_priors(inputs, pipeline.PriorsParams(), None)["inv_depth"]

    a = run(flow)
    assert inner.sum() > 100 and a.std() > 0
    assert np.array_equal(a, run(noisy))
    assert not np.array_equal(run(flow, False), run(noisy, False))


def test_a_masked_run_hands_the_users_masks_to_every_stage_that_samples(tmp_path, monkeypatch):
    """A whole run with --masks (in process): the masks stage's items carry user_keep, and the
    footprint checks of priors and fusion, bundle adjustment, the window losses, filter and
    consensus all run (the items functions found the user's masks)."""
    from collections import Counter

    from conftest import cli

    from gcvd_flow import api
    from gcvd_flow.stages.geometry import torch_ops
    from gcvd_flow.stages.optimize import bundle_adjustment as ba_mod

    clip = tmp_path / "clip"
    cli("synth", str(clip), "--frames", "12", "--size", "96x72", "--trajectory", "loop", "--moving-object", check=True)
    calls: Counter = Counter()

    def spy(name, real):
        def f(*a, **kw):
            calls[name] += 1
            return real(*a, **kw)
        return f

    monkeypatch.setattr(user_masks, "flow_target_kept", spy("targets", user_masks.flow_target_kept))
    monkeypatch.setattr(ba_mod, "footprint_kept", spy("tracks", ba_mod.footprint_kept))
    monkeypatch.setattr(torch_ops, "footprint_kept", spy("losses", torch_ops.footprint_kept))
    from gcvd_flow.pipeline import depth as depth_blocks  # the module whose adapters read it

    monkeypatch.setattr(depth_blocks, "_eroded_keep", spy("depth reads", pipeline._eroded_keep))
    sets = [f"masks.user_dir={clip / 'gt' / 'dynamic'}", "optimize_keyframes.steps=4", "optimize_edges.steps=2",
            "optimize_segments.steps=2"]
    api.run(api.Invocation(input=str(clip), out=str(tmp_path / "run"), cache=str(tmp_path / "cache"), profile="fast",
                           sets=sets, jobs=1, json_mode=True), log=lambda m: None)
    masks = api.recorded_output(tmp_path / "run", "masks", str(tmp_path / "cache"))
    assert all("user_keep" in masks[i] for i in range(12)) and masks[3]["user_keep"].min() == 0
    # priors (12 frames x refs) and fusion triangulate; the tracks, losses and depth reads check footprints
    assert calls["targets"] >= 24 and calls["tracks"] > 0 and calls["losses"] > 0, calls
    assert calls["depth reads"] >= 24, calls  # depth_filter's neighbours and depth_consensus's references
