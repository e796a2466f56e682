"""Flow, motion masks and geometric priors on synthetic clips with exact ground truth."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_ref import rigid_flow
from scipy.stats import spearmanr

from gcvd_flow.evaluate.synth import render_clip
from gcvd_flow.stages.frontend import flow, masks, priors


@pytest.fixture(scope="module")
def orbit():
    c = render_clip(24, "orbit", size=(256, 192), seed=0)
    return c, [flow.compute_pair_flow(c.frames[i], c.frames[i + 1]) for i in range(23)]


@pytest.fixture(scope="module")
def moving():
    c = render_clip(24, "orbit", size=(256, 192), moving_object=True, seed=0)
    return c, [flow.compute_pair_flow(c.frames[i], c.frames[i + 1]) for i in range(23)]


def test_dis_flow_epe_below_one_pixel(orbit):
    c, fl = orbit
    epes = []
    for i in range(0, 23, 4):
        gt = rigid_flow(c.depth[i], c.K, c.poses[i], c.poses[i + 1])
        v = fl[i]["fwd_valid"]
        epes.append(np.linalg.norm(fl[i]["fwd"][v] - gt[v], axis=-1).mean())
    assert np.mean(epes) < 1.0, epes
    assert min(fl[i]["fwd_valid"].mean() for i in range(23)) > 0.7


def test_flow_is_deterministic(orbit):
    c, fl = orbit
    again = flow.compute_pair_flow(c.frames[0], c.frames[1])
    assert all(np.array_equal(again[k], fl[0][k]) for k in fl[0])


def _chain_back(fl, i, span=6):
    return [(fl[i - 1 - j]["bwd"], fl[i - 1 - j]["bwd_valid"]) for j in range(span)]


def test_motion_mask_finds_the_moving_object(moving):
    c, fl = moving
    ious = []
    for i in (8, 14, 20):
        ch = _chain_back(fl, i)
        m = masks.motion_static_mask(c.K, [ch[0], flow.chain_flows(ch)])
        pred, gt = m == 0, c.dynamic[i]
        ious.append((pred & gt).sum() / max((pred | gt).sum(), 1))
    assert np.mean(ious) >= 0.5, ious


def test_motion_mask_keeps_a_static_scene_static(orbit):
    c, fl = orbit
    fracs = []
    for i in (8, 14, 20):
        ch = _chain_back(fl, i)
        fracs.append(masks.motion_static_mask(c.K, [ch[0], flow.chain_flows(ch)]).mean())
    assert np.mean(fracs) >= 0.97, fracs


def test_geometric_prior_ranks_depth_like_ground_truth(orbit):
    c, fl = orbit
    rhos = []
    for i in (8, 14, 20):
        pr = priors.geometric_prior(c.frames[i], c.K, _chain_back(fl, i))
        assert pr["inv_depth"].dtype == np.float32 and (pr["inv_depth"] > 0).all()
        assert abs(np.median(pr["inv_depth"]) - 1.0) < 1e-3
        rhos.append(spearmanr(pr["inv_depth"].ravel(), (1.0 / c.depth[i]).ravel()).statistic)
    assert np.mean(rhos) >= 0.7, rhos


def test_pure_rotation_gives_a_flat_prior_and_no_crash():
    c = render_clip(10, "rotation", size=(160, 120), seed=0)
    fl = [flow.compute_pair_flow(c.frames[i], c.frames[i + 1]) for i in range(9)]
    pr = priors.geometric_prior(c.frames[0], c.K, [(f["fwd"], f["fwd_valid"]) for f in fl[:6]])
    assert np.allclose(pr["inv_depth"], 1.0) and pr["confidence"].max() == 0
    m = masks.motion_static_mask(c.K, [(fl[0]["fwd"], fl[0]["fwd_valid"])])
    assert m.mean() > 0.97
