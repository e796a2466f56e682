"""What the solver computes once per window equals what a step computed before (bit for bit)."""

from __future__ import annotations

import torch

from gcvd_flow.stages.geometry import torch_ops as G
from gcvd_flow.stages.models.depth_net import DepthNet
from gcvd_flow.stages.optimize import losses as L
from gcvd_flow.stages.optimize.solver import _patch_index, _patch_stats_table


def test_patch_stats_table_equals_the_stats_of_gathered_patches() -> None:
    g = torch.Generator().manual_seed(3)
    imgs = torch.rand(4, 3, 11, 13, generator=g)
    n, c, h, w = imgs.shape
    table = _patch_stats_table(imgs)  # (n, 2c, h * w)
    pa = torch.tensor([0, 3, 1, 3])
    idx = torch.randint(0, h * w, (4, 50), generator=g)
    idx[0, :4] = torch.tensor([0, w - 1, h * w - 1, (h - 1) * w])  # corners: clamped patches
    nidx = _patch_index(idx, h, w).reshape(4, -1)
    patches = G.gather_pixels(imgs[pa], nidx).transpose(1, 2).view(4, c, 50, 9)
    mu, sq = L.patch_stats(patches)
    got = table[pa].gather(2, idx[:, None, :].expand(-1, 2 * c, -1))
    assert torch.equal(got[:, :c], mu) and torch.equal(got[:, c:], sq)
    # a wrong patch order or border rule would change the table
    assert not torch.equal(_patch_stats_table(imgs.flip(-1)).flip(-1), table)
    pb = (patches + 0.05 * torch.rand(patches.shape, generator=g)).requires_grad_(True)
    plain = L.photometric_terms(patches, pb)
    given = L.photometric_terms(patches, pb, a_stats=(got[:, :c], got[:, c:]))
    assert torch.equal(plain, given)
    ga, = torch.autograd.grad(plain.sum(), pb)
    gb, = torch.autograd.grad(given.sum(), pb)
    assert torch.equal(ga, gb)


def test_sample_points_and_prior_std_equal_the_per_step_forms() -> None:
    g = torch.Generator().manual_seed(5)
    img = torch.rand(2, 3, 9, 12, generator=g)
    uv = (torch.rand(2, 40, 2, generator=g) * torch.tensor([14.0, 11.0]) - 1).requires_grad_(True)
    gx = uv[..., 0] * (2.0 / 11) - 1
    gy = uv[..., 1] * (2.0 / 8) - 1
    ref = torch.nn.functional.grid_sample(img, torch.stack([gx, gy], -1)[:, None], mode="bilinear",
                                          padding_mode="border", align_corners=True)[:, :, 0].transpose(1, 2)
    got = G.sample_points(img, uv)
    assert torch.equal(got, ref)
    w = torch.rand(got.shape, generator=g)
    assert torch.equal(torch.autograd.grad((ref * w).sum(), uv)[0], torch.autograd.grad((got * w).sum(), uv)[0])
    inside = G.inside_image(uv, 9, 12)
    assert inside.any() and not inside.all()
    net = DepthNet(seed=0)
    enc = net.encode(img, torch.rand(2, 9, 12, generator=g) + 0.5)
    last = net.head[2]
    assert isinstance(last, torch.nn.Conv2d)
    with torch.no_grad():
        last.weight.normal_(generator=g)
    assert torch.equal(net.decode(enc, ref_std=net.prior_std(enc)), net.decode(enc))
