"""Weight-free geometric prior: rank agreement with GT inverse depth, degenerate fallbacks."""

from __future__ import annotations

import numpy as np
from scipy.stats import spearmanr

from stages.flow import compute_pair_flow
from stages.priors import geometric_prior
from stages.synth import render_clip

N = 16


def _chain(clip, i, n):
    out = []
    for j in range(i, min(i + n, len(clip.frames) - 1)):
        r = compute_pair_flow(clip.frames[j], clip.frames[j + 1])
        out.append((r["fwd"], r["fwd_valid"]))
    return out


def test_orbit_spearman():
    clip = render_clip(N, "orbit", size=(256, 192), seed=0)
    rhos = []
    for i in (0, 5, 10):
        r = geometric_prior(clip.frames[i], clip.K, _chain(clip, i, 5))
        inv = r["inv_depth"]
        assert inv.dtype == np.float32 and inv.shape == (192, 256)
        assert (inv > 0).all() and abs(float(np.median(inv)) - 1.0) < 1e-3
        c = r["confidence"]
        assert c.dtype == np.float32 and c.min() >= 0 and c.max() <= 1 and c.mean() > 0.5
        rhos.append(spearmanr(inv.ravel(), 1.0 / clip.depth[i].ravel())[0])
    print(f"orbit geometric prior Spearman vs GT inverse depth: {np.round(rhos, 3).tolist()}")
    assert min(rhos) >= 0.7


def test_rotation_falls_back():
    clip = render_clip(10, "rotation", size=(128, 96), seed=0)
    r = geometric_prior(clip.frames[2], clip.K, _chain(clip, 2, 4))
    assert r["inv_depth"].shape == (96, 128) and np.all(r["inv_depth"] == 1.0)
    assert np.all(r["confidence"] == 0.0)
    empty = geometric_prior(clip.frames[0], clip.K, [])
    assert np.all(empty["inv_depth"] == 1.0) and np.all(empty["confidence"] == 0.0)
