"""Geometry (SE(3), projection, rigid flow, point sampling) and the depth / pose networks."""

from __future__ import annotations

import numpy as np
import torch
from geometry_ref import rigid_flow as rigid_flow_np

from gcvd_flow.stages.geometry import torch_ops as G
from gcvd_flow.stages.models.depth_net import DepthNet, mesh_shape, upsample_mesh
from gcvd_flow.stages.models.pose_net import DirectPoses, PoseNet, positional_encoding


def _rand_twists(n: int, seed: int = 0, rot: float = 0.6) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    xi = torch.randn(n, 6, generator=g, dtype=torch.float64)
    xi[:, :3] *= rot  # (w, v): rotation first
    return xi


def test_se3_exp_log_roundtrip() -> None:
    xi = _rand_twists(64)
    xi = torch.cat([xi, torch.zeros(1, 6, dtype=torch.float64), 1e-9 * torch.ones(1, 6, dtype=torch.float64)])
    T = G.se3_exp(xi)
    R = T[:, :3, :3]
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand_as(R), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(len(xi), dtype=torch.float64))
    assert torch.allclose(G.se3_log(T), xi, atol=1e-9)


def test_one_twist_order_in_torch_and_numpy() -> None:
    # stages.geometry.torch_ops and stages.geometry.se3 (gtsam's Pose3.Expmap) read (w, v) alike
    from gcvd_flow.stages.geometry import se3

    xi = _rand_twists(16, 7)
    np.testing.assert_allclose(G.se3_exp(xi).numpy(), se3.se3_exp(xi.numpy()), atol=1e-12)
    np.testing.assert_allclose(G.se3_log(G.se3_exp(xi)).numpy(), se3.se3_log(se3.se3_exp(xi.numpy())), atol=1e-9)
    rot_only = torch.zeros(1, 6, dtype=torch.float64)
    rot_only[0, 2] = 0.5  # the first three components rotate: about z by 0.5 rad, no translation
    T = G.se3_exp(rot_only)[0]
    assert torch.allclose(T[:3, 3], torch.zeros(3, dtype=torch.float64)) and abs(float(T[0, 1]) + np.sin(0.5)) < 1e-12


def test_pose_from_rt_roundtrip_and_so3_matches_cv2() -> None:
    import cv2

    rt = _rand_twists(16, 1)
    T = G.pose_from_rt(rt)
    assert torch.allclose(G.rt_from_pose(T), rt, atol=1e-9)
    for i in range(4):
        Rcv = cv2.Rodrigues(rt[i, :3].numpy())[0]
        assert np.allclose(T[i, :3, :3].numpy(), Rcv, atol=1e-10)
    assert torch.allclose(T[:, :3, 3], rt[:, 3:])


def test_so3_gradient_finite_at_zero() -> None:
    w = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
    G.so3_exp(w).sum().backward()
    assert torch.isfinite(w.grad).all()


def test_relative_pose_matches_inverse() -> None:
    T_w_a, T_w_b = G.se3_exp(_rand_twists(5, 2)), G.se3_exp(_rand_twists(5, 3))
    assert torch.allclose(G.relative_pose(T_w_a, T_w_b), torch.linalg.inv(T_w_b) @ T_w_a, atol=1e-12)


def test_rigid_flow_matches_numpy_reference() -> None:
    h, w = 24, 32
    K = np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]])
    rng = np.random.default_rng(0)
    depth = rng.uniform(1.0, 3.0, (h, w))
    T_w_a = G.se3_exp(0.1 * _rand_twists(1, 4))[0].numpy()
    T_w_b = G.se3_exp(0.1 * _rand_twists(1, 5))[0].numpy()
    ref = rigid_flow_np(depth, K, T_w_a, T_w_b)
    T = torch.as_tensor(np.linalg.inv(T_w_b) @ T_w_a)[None]
    ours = G.rigid_flow(torch.as_tensor(depth)[None], torch.as_tensor(K), T)[0].numpy()
    assert np.abs(ours - ref).max() < 1e-5  # the reference returns float32
    assert np.abs(ref).max() > 1.0  # a non-trivial motion


def test_backproject_project_identity() -> None:
    K = torch.tensor([[50.0, 0, 20.0], [0, 50.0, 15.0], [0, 0, 1]], dtype=torch.float64)
    d = torch.rand(2, 30, 40, dtype=torch.float64) + 0.5
    uv, z = G.project(G.backproject(d, K), K)
    v, u = torch.meshgrid(torch.arange(30.0, dtype=torch.float64), torch.arange(40.0, dtype=torch.float64), indexing="ij")
    assert torch.allclose(uv[0], torch.stack([u, v], -1).reshape(-1, 2), atol=1e-10)
    assert torch.allclose(z, d.reshape(2, -1))


def test_sample_bilinear_and_gather() -> None:
    h, w = 10, 14
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    img = torch.stack([2 * u + 3 * v, u - v])[None]  # linear: bilinear sampling is exact
    pts = torch.tensor([[[0.0, 0.0], [3.25, 4.5], [12.9, 8.1], [20.0, 1.0]]])
    val, inside = G.sample_bilinear(img, pts)
    assert torch.allclose(val[0, :3, 0], 2 * pts[0, :3, 0] + 3 * pts[0, :3, 1], atol=1e-4)
    assert inside.tolist() == [[True, True, True, False]]
    idx = torch.tensor([[0, 15, w * h - 1]])
    g = G.gather_pixels(img, idx)
    assert g[0, 1, 0] == 2 * 1 + 3 * 1 and g[0, 2, 1] == (w - 1) - (h - 1)


def test_sample_frames_equals_sampling_the_stacked_frames_values_and_gradients() -> None:
    # the solver samples depth of frame pb[p] at uv[p] from the (n, h, w) stack; the reference is
    # grid_sample on the (P, 1, h, w) stack, including points outside (border clamp)
    g = torch.Generator().manual_seed(0)
    field = torch.rand(5, 7, 9, generator=g, dtype=torch.float64, requires_grad=True)
    frame = torch.tensor([3, 0, 3, 4])
    uv = (torch.rand(4, 30, 2, generator=g, dtype=torch.float64) * torch.tensor([11.0, 9.0]) - 1.0).requires_grad_(True)
    ours = G.sample_frames(field, frame, uv)
    ref = G.sample_bilinear(field[frame][:, None], uv)[0][..., 0]
    assert ours.shape == (4, 30) and (uv[..., 0] > 8).any() and (uv[..., 1] < 0).any()
    assert torch.allclose(ours, ref, atol=1e-12)
    for a, b in zip(torch.autograd.grad((ours ** 2).sum(), [field, uv]), torch.autograd.grad((ref ** 2).sum(), [field, uv])):
        assert torch.allclose(a, b, atol=1e-12)


def test_depth_net_head_as_matrix_products_equals_its_convolutions() -> None:
    # decode evaluates the 1x1-convolution head as two matrix products (faster on CPU): same values
    # and gradients as running the nn.Sequential of convolutions on the feature maps
    imgs, prior = _img_prior()
    net = DepthNet(seed=0)
    with torch.no_grad():
        net.head[2].weight.normal_(0, 0.1)
        net.head[2].bias.fill_(0.2)
    enc = net.encode(imgs, prior)
    conv = net.head(torch.cat([enc.feat, enc.log_prior], 1))[:, 0]
    mm = net.head_residual(net.head_input(enc)).view_as(conv)
    assert torch.allclose(mm, conv, atol=1e-5) and conv.abs().max() > 0.05
    g_mm = torch.autograd.grad((mm ** 2).sum(), list(net.head.parameters()))
    g_conv = torch.autograd.grad((conv ** 2).sum(), list(net.head.parameters()))
    for a, b in zip(g_mm, g_conv):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-4)
    assert torch.equal(net.decode(enc, head_in=net.head_input(enc)), net.decode(enc))


def _img_prior(b: int = 2, h: int = 24, w: int = 32) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    imgs = torch.rand(b, 3, h, w, generator=g)
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    prior = (0.5 + u / w + 0.3 * v / h)[None].repeat(b, 1, 1)
    return imgs, prior / prior.flatten(1).median(1).values[:, None, None]


def test_depth_net_reproduces_prior_before_training() -> None:
    imgs, prior = _img_prior()
    for ln in (True, False):
        d = DepthNet(layer_norm=ln, seed=0)(imgs, prior)
        ratio = d * prior
        # depth = 1 / prior up to one scale per frame
        assert torch.allclose(ratio, ratio.flatten(1).mean(1)[:, None, None].expand_as(ratio), rtol=1e-4)


def test_layer_norm_switch_removes_network_scale() -> None:
    imgs, prior = _img_prior()
    on, off = DepthNet(layer_norm=True), DepthNet(layer_norm=False)
    with torch.no_grad():
        for net in (on, off):
            net.head[2].bias.fill_(0.7)  # a network that changes the overall scale
            net.head[2].weight.normal_(0, 0.05)
    enc = on.encode(imgs, prior)
    d_on, d_off = on.decode(enc), off.decode(off.encode(imgs, prior))
    # LayerNorm: the mean log inverse depth of each frame is pinned at 0 whatever the head does
    assert torch.allclose(torch.log(d_on).flatten(1).mean(1), torch.zeros(2), atol=1e-5)
    assert (torch.log(d_off).flatten(1).mean(1) < -0.5).all()


def test_mesh_identity_at_zero_and_scales_when_set() -> None:
    imgs, prior = _img_prior()
    net = DepthNet(mesh=True)
    gh, gw = mesh_shape(24, 32, 17)
    assert (gh, gw) == (13, 17)
    base = net(imgs, prior, None)
    assert torch.equal(net(imgs, prior, torch.zeros(2, gh, gw)), base)
    m = torch.full((2, gh, gw), 0.3)
    assert torch.allclose(net(imgs, prior, m), base * np.exp(0.3), rtol=1e-6)
    assert torch.equal(DepthNet(mesh=False)(imgs, prior, m), base)
    up = upsample_mesh(torch.arange(gh * gw, dtype=torch.float32).reshape(1, gh, gw), 25, 33)
    assert up[0, 0, 0] == 0 and up[0, -1, -1] == gh * gw - 1  # vertices on the image corners


def test_depth_net_external_backbone_hook() -> None:
    imgs, prior = _img_prior()

    class Fake(torch.nn.Module):
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return 1.0 + x.mean(1, keepdim=True)

    net = DepthNet(backbone=Fake())
    d = net(imgs, None)
    disp = 1.0 + imgs.mean(1)
    r = d * disp
    assert torch.allclose(r, r.flatten(1).mean(1)[:, None, None].expand_as(r), rtol=1e-3)
    assert [n for n, p in net.named_parameters() if p.requires_grad] == ["head.0.weight", "head.0.bias", "head.2.weight", "head.2.bias"]


def test_pose_net_zero_initial_correction_and_trainable_decoder() -> None:
    imgs, _ = _img_prior(3)
    net = PoseNet(seed=0)
    out = net(imgs, torch.arange(3))
    assert out.shape == (3, 6) and torch.equal(out, torch.zeros(3, 6))
    trainable = {n for n, p in net.named_parameters() if p.requires_grad}
    assert trainable and all(n.startswith("decoder.") for n in trainable)
    pe = positional_encoding(torch.arange(4), 8)
    assert pe.shape == (4, 16) and not torch.allclose(pe[0], pe[1])
    assert DirectPoses(5)().shape == (5, 6)


def test_backbones_are_seeded() -> None:
    a, b, c = DepthNet(seed=3), DepthNet(seed=3), DepthNet(seed=4)
    assert torch.equal(a.unet.e1.weight, b.unet.e1.weight)
    assert not torch.equal(a.unet.e1.weight, c.unet.e1.weight)


def test_loop_disagreement_is_the_rotation_between_measurement_and_odometry() -> None:
    from gcvd_flow.stages.geometry import se3

    T_w_a, T_w_b = G.se3_exp(0.3 * _rand_twists(1, 8))[0].numpy(), G.se3_exp(0.3 * _rand_twists(1, 9))[0].numpy()
    T_b_a = np.linalg.inv(T_w_b) @ T_w_a
    assert se3.loop_disagreement_deg(T_w_a, T_w_b, T_b_a) < 1e-5
    turn = np.eye(4)
    turn[:3, :3] = G.so3_exp(torch.tensor([0.0, 0.0, np.radians(40.0)], dtype=torch.float64)).numpy()
    assert abs(se3.loop_disagreement_deg(T_w_a, T_w_b, turn @ T_b_a) - 40.0) < 1e-6
