"""Losses: zero at the ground truth, positive (and growing) when perturbed."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gcvd_flow.evaluate.synth import render_clip
from gcvd_flow.stages.geometry import torch_ops as G
from gcvd_flow.stages.optimize import losses as L


@pytest.fixture(scope="module")
def pair() -> dict:
    c = render_clip(6, "orbit", size=(96, 72), seed=0)
    a, b = 0, 1
    T = torch.as_tensor(np.linalg.inv(c.poses[b]) @ c.poses[a])[None].float()
    return dict(
        img=torch.as_tensor(c.frames[[a, b]]).permute(0, 3, 1, 2).float() / 255,
        depth=torch.as_tensor(c.depth[[a, b]]).float(),
        K=torch.as_tensor(c.K).float(),
        T=T,
    )


def _warp(p: dict, depth_a: torch.Tensor, T: torch.Tensor, n: int = 400, seed: int = 0):
    """Sample n 3x3 patches in frame a, warp them to b; return patches, projections, weights."""
    h, w = depth_a.shape
    g = torch.Generator().manual_seed(seed)
    u = torch.randint(2, w - 2, (n,), generator=g)
    v = torch.randint(2, h - 2, (n,), generator=g)
    du = torch.tensor([-1, 0, 1] * 3)
    dv = torch.tensor([-1] * 3 + [0] * 3 + [1] * 3)
    idx = ((v[:, None] + dv) * w + (u[:, None] + du)).reshape(1, -1)
    rays = G.pixel_rays(h, w, p["K"])
    X = rays[idx[0]][None] * depth_a.reshape(1, -1).gather(1, idx)[..., None]
    uv, z = G.project(G.transform(T, X), p["K"])
    pb, inside = G.sample_bilinear(p["img"][1:2], uv)
    pa = G.gather_pixels(p["img"][0:1], idx)
    db, _ = G.sample_bilinear(p["depth"][1:2, None], uv.reshape(1, n, 9, 2)[:, :, 4])
    wgt = inside.reshape(1, n, 9).all(-1).float()
    return pa.reshape(1, n, 9, 3), pb.reshape(1, n, 9, 3), uv.reshape(1, n, 9, 2)[:, :, 4], z.reshape(1, n, 9)[:, :, 4], db[..., 0], wgt


def test_photometric_and_depth_consistency_small_at_gt_larger_when_perturbed(pair: dict) -> None:
    pa, pb, _, z, db, w = _warp(pair, pair["depth"][0], pair["T"])
    photo_gt = L.photometric_loss(pa, pb, w).item()
    dc_gt = L.depth_consistency_loss(z, db, w).item()
    # identical patches give exactly zero
    assert L.photometric_loss(pa, pa, w).item() == pytest.approx(0.0, abs=1e-6)
    assert L.depth_consistency_loss(z, z, w).item() == pytest.approx(0.0, abs=1e-7)
    dT = G.pose_from_rt(torch.tensor([[0.0, 0.03, 0.0, 0.05, 0.0, 0.0]]))
    pa2, pb2, _, z2, db2, w2 = _warp(pair, pair["depth"][0], dT @ pair["T"])
    assert w.sum() > 200 and w2.sum() > 200
    assert photo_gt < 0.06 and dc_gt < 0.03  # occlusions + interpolation residual only
    assert L.photometric_loss(pa2, pb2, w2).item() > 2 * photo_gt
    assert L.depth_consistency_loss(z2, db2, w2).item() > 2 * dc_gt


def test_flow_loss_zero_for_exact_rigid_flow(pair: dict) -> None:
    flow = G.rigid_flow(pair["depth"][:1], pair["K"], pair["T"])  # (1, h, w, 2)
    h, w = flow.shape[1:3]
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    target = (torch.stack([u, v], -1) + flow[0]).reshape(1, -1, 2)
    X = G.backproject(pair["depth"][:1], pair["K"])
    uv, _ = G.project(G.transform(pair["T"], X), pair["K"])
    wgt = torch.ones(1, h * w)
    assert L.flow_loss(uv, target, wgt).item() < 2e-3  # Charbonnier epsilon only
    assert L.flow_loss(uv + torch.tensor([0.5, 0.0]), target, wgt).item() == pytest.approx(0.5, abs=1e-2)
    # masked points do not count
    wgt[:, ::2] = 0
    bad = uv.clone()
    bad[:, ::2] += 10
    assert L.flow_loss(bad, target, wgt).item() < 2e-3


def test_gradient_orientation_loss(pair: dict) -> None:
    d = pair["depth"]
    prior = 1.0 / d
    assert L.gradient_orientation_loss(d, prior).max().item() < 1e-6
    assert L.gradient_orientation_loss(d * 3.0, prior * 0.2).max().item() < 1e-6  # scale-invariant
    flipped = torch.flip(d, dims=[-1])
    assert L.gradient_orientation_loss(flipped, prior).min().item() > 0.1


def test_mesh_smoothness_and_dynamic_weighting() -> None:
    flat = torch.full((2, 5, 7), 0.4)
    assert L.mesh_smoothness_loss(flat).max().item() == 0.0
    bumpy = flat.clone()
    bumpy[:, 2, 3] += 0.5
    base = L.mesh_smoothness_loss(bumpy)
    assert (base > 0).all()
    dyn = torch.zeros(2, 5, 7)
    dyn[1, 1:4, 2:5] = 1.0
    weighted = L.mesh_smoothness_loss(bumpy, dyn, dyn_gain=10.0)
    assert weighted[0] == pytest.approx(base[0].item()) and weighted[1] > 5 * base[1]


def test_dense_photometric_matches_identity() -> None:
    img = torch.rand(1, 3, 20, 24)
    m = torch.ones(1, 20, 24)
    assert L.dense_photometric_loss(img, img, m).item() == pytest.approx(0.0, abs=1e-6)
    assert L.dense_photometric_loss(img, torch.roll(img, 3, -1), m).item() > 0.05


def test_default_weights() -> None:
    assert L.DEFAULT_WEIGHTS == {"photo": 1.0, "flow": 10.0, "depth": 0.5, "grad": 0.1, "mesh": 0.5}


def test_points_behind_camera_b_enter_no_term_of_the_pair() -> None:
    """A window pair whose camera b stands 0.5 m ahead of a: the points of a at 0.4 m lie behind b.
    They enter no term (photometric, depth consistency, and the flow loss, whose gradient of such
    a point was 10^5x the window's and collapsed a real keyframe's depth scale): the pair's loss
    does not change when their flow targets do, their depth gets no gradient, and the gradient of
    the pixels in front stays bounded."""
    from gcvd_flow.stages.models.depth_net import DepthNet, Encoded
    from gcvd_flow.stages.optimize.params import DepthModel, KeyframeSettings, LossWeights
    from gcvd_flow.stages.optimize.solver import Pair, Solver, Window

    n, h, w = 2, 12, 16
    K = np.array([[20.0, 0, (w - 1) / 2], [0, 20.0, (h - 1) / 2], [0, 0, 1]])
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[1, 2, 3] = 0.5  # camera b 0.5 m ahead along a's optical axis
    depth = np.full((n, h, w), 2.0, np.float32)
    behind = np.zeros((h, w), bool)
    behind[3:7, 4:9] = True
    depth[0][behind] = 0.4
    rng = np.random.default_rng(0)
    imgs = torch.as_tensor(rng.random((n, 3, h, w)).astype(np.float32))

    def pair_loss(flow: np.ndarray) -> tuple[float, torch.Tensor]:
        pairs = [Pair(0, 1, 1, 1.0, torch.as_tensor(flow), torch.ones(h, w))]
        win = Window(imgs, Encoded(torch.zeros(n, 4, h, w), torch.zeros(n, 1, h, w)), torch.ones(n, h, w),
                     torch.zeros(n, 2, 3), torch.as_tensor(K), pairs, torch.as_tensor(poses),
                     torch.ones(n, dtype=torch.float64), torch.zeros(n, 2, 3), torch.ones(n))
        solver = Solver(win, DepthNet(seed=0), None, 1e-4, DepthModel(), LossWeights(), KeyframeSettings())
        d = torch.as_tensor(depth).clone().requires_grad_(True)
        idx = torch.arange(h * w)[None]
        total = sum(solver._block_loss(b, d, torch.as_tensor(poses), idx[b.sel]) for t in solver.blocks for b in t)
        total.backward()
        return float(total.detach()), d.grad

    flow = rng.normal(0, 1, (h, w, 2)).astype(np.float32)
    scrambled = flow.copy()
    scrambled[behind] = rng.normal(0, 50, (int(behind.sum()), 2))
    (loss, grad), (loss2, _) = pair_loss(flow), pair_loss(scrambled)
    assert np.isfinite(loss) and loss > 0 and loss == loss2
    assert float(grad[0][torch.as_tensor(behind)].abs().max()) == 0
    assert float(grad.abs().max()) < 10 and np.isfinite(grad.numpy()).all()
