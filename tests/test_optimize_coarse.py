"""Cheaper optimisation steps: coarse-to-fine points (``coarse_points`` / ``coarse_frac`` of the
keyframe and segment windows) and the fused photometric term (``losses.photometric_terms``)."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from test_optimize import SMALL, SMALL_SEG, MemCheckpointer, _assert_same, _kf_run, tiny  # noqa: F401 (fixture)

from gcvd_flow.stages.optimize import losses as L
from gcvd_flow.stages.optimize.segments import optimize_segments
from gcvd_flow.stages.optimize.solver import Coarse, Solver

torch.set_num_threads(1)


class _SampleSpy:
    """Records the sampled point indices of every Adam step (Solver._sample): per step, per point
    group, (pairs, points) flat pixel indices, and the window's pixel count."""

    def __init__(self) -> None:
        self.draws: list[list[torch.Tensor]] = []
        self.pixels: list[int] = []

    def __enter__(self) -> "_SampleSpy":
        self.orig = Solver._sample
        spy = self

        def sample(solver: Solver, gen: torch.Generator) -> list[torch.Tensor]:
            out = spy.orig(solver, gen)
            spy.draws.append([t.clone() for t in out])
            spy.pixels.append(solver.h * solver.w_)
            return out

        Solver._sample = sample  # type: ignore[method-assign]
        return self

    def __exit__(self, *exc: object) -> None:
        Solver._sample = self.orig  # type: ignore[method-assign]


def test_coarse_phase_values() -> None:
    c = Coarse(8, 0.5)
    assert [c.active(s, 6) for s in range(6)] == [True] * 3 + [False] * 3
    assert not Coarse(0, 0.9).active(0, 6) and not Coarse(8, 0.0).active(0, 6)
    assert all(Coarse(8, 1.0).active(s, 6) for s in range(6))
    assert c.points_of(32, 32) == 8 and c.points_of(16, 32) == 4  # a group scales with the stage's points
    assert c.points_of(2, 32) == 1 and Coarse(64, 0.5).points_of(32, 32) == 32  # in [1, full]


def test_keyframe_windows_draw_coarse_then_full_points(tiny: dict) -> None:  # noqa: F811
    """The first coarse_frac of every window's steps draw coarse_points per pair, fresh each step (a
    different subset every step, inside the image), the rest the full number; the run is
    deterministic and differs from the uniform one; coarse_points 0 is the previous computation."""
    over = dict(steps=6, coarse_points=8, coarse_frac=0.5)
    with _SampleSpy() as spy:
        r1 = _kf_run(tiny, **over)
    assert len(spy.draws) % 6 == 0 and len(spy.draws) >= 12  # two windows or more
    for s, draw in enumerate(spy.draws):
        (idx,) = draw  # one point group (uniform allocation)
        assert idx.shape[1] == (8 if s % 6 < 3 else SMALL.points)
        assert int(idx.min()) >= 0 and int(idx.max()) < spy.pixels[s]
    assert not torch.equal(spy.draws[0][0], spy.draws[1][0])  # re-drawn every step
    _assert_same(r1, _kf_run(tiny, **over))
    off = _kf_run(tiny, **{**over, "coarse_points": 0})
    assert off["poses"].tobytes() != r1["poses"].tobytes()
    with _SampleSpy() as spy:
        ref = _kf_run(tiny, steps=6)
    assert all(d[0].shape[1] == SMALL.points for d in spy.draws)
    _assert_same(off, ref)


def test_coarse_points_scale_each_point_group(tiny: dict) -> None:  # noqa: F811
    """With points_by_weight each point group draws its own number scaled by coarse_points / points."""
    with _SampleSpy() as spy:
        _kf_run(tiny, steps=4, points_by_weight=True, coarse_points=16, coarse_frac=0.5)
    full = [d.shape[1] for d in spy.draws[-1]]
    assert full == [32, 16]  # taus (1, 2): weights 1, 1/2
    assert [d.shape[1] for d in spy.draws[0]] == [16, 8]


@pytest.mark.parametrize("interrupt_after", [1, 2])  # saved at step 2 (coarse phase) / step 4 (fine) of window 0
def test_coarse_keyframe_resume_is_bit_exact(tiny: dict, interrupt_after: int) -> None:  # noqa: F811
    """The phase is a function of the step index: a resumed window draws what the uninterrupted one did."""
    over = dict(coarse_points=8, coarse_frac=0.5)
    ref = _kf_run(tiny, **over)
    ck = MemCheckpointer(interrupt_after)
    with pytest.raises(KeyboardInterrupt):
        _kf_run(tiny, ck, **over)
    ck.interrupt_after = None
    with _SampleSpy() as spy:
        res = _kf_run(tiny, ck, **over)
    _assert_same(res, ref)
    first = 2 * interrupt_after  # the resumed window's first step
    assert spy.draws[0][0].shape[1] == (8 if first < 3 else SMALL.points)


def test_segment_windows_follow_their_own_coarse_setting(tiny: dict) -> None:  # noqa: F811
    """optimize_segments.coarse_points drives the segment windows (not the keyframe setting)."""
    kres = _kf_run(tiny, steps=2)
    c = tiny["clip"]

    def run(seg_coarse: int, kf_coarse: int) -> tuple[dict, list[int]]:
        with _SampleSpy() as spy:
            out = optimize_segments(c.frames, tiny["prior"], tiny["masks"], c.K, tiny["adj"], tiny["kf"],
                                    kres["poses"], kres["depths"], kf=dataclasses.replace(SMALL, coarse_points=kf_coarse),
                                    seg=dataclasses.replace(SMALL_SEG, coarse_points=seg_coarse, coarse_frac=0.5),
                                    seed=0, state=kres["state"])
        return out, [d[0].shape[1] for d in spy.draws]

    out, m = run(4, 0)
    n = SMALL_SEG.steps
    assert len(m) % n == 0 and len(m) > n  # several windows
    assert m == [4, 4, SMALL.points, SMALL.points] * (len(m) // n)
    ref, m = run(0, 4)
    assert all(x == SMALL.points for x in m)
    assert out["poses"].tobytes() != ref["poses"].tobytes()


def test_plateau_stop_waits_for_the_end_of_the_coarse_phase(tiny: dict) -> None:  # noqa: F811
    """A converged window (every learning rate 0) stops at the first check of the fine phase, never
    in the coarse phase (its losses are drawn on a quarter of the points); without the coarse phase
    at the first check (test_optimize.py)."""
    plateau = dict(window=8, steps=40, points=128, stop_every=5, stop_rel=0.02, lr=0.0, pose_lr=0.0,
                   mesh_lr_mult=0.0)
    coarse = _kf_run(tiny, coarse_points=32, coarse_frac=0.5, **plateau)
    assert [w["steps"] for w in coarse["windows"]] == [25]  # steps 20-24 at 128 points against 15-19 at 32
    plain = _kf_run(tiny, coarse_points=0, **plateau)
    assert [w["steps"] for w in plain["windows"]] == [10]


def _patches(dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(P, C, M, 9) patches a, b (b a noisy a; one point identical, one flat) and weights (P, M)."""
    g = torch.Generator().manual_seed(0)
    pa = torch.rand(4, 3, 6, 9, generator=g, dtype=dtype)
    pb = (pa + 0.2 * torch.randn(4, 3, 6, 9, generator=g, dtype=dtype)).clamp(0, 1)
    pb[0, :, 0] = pa[0, :, 0]
    pa[1, :, 1] = 0.5
    pb[1, :, 1] = 0.5
    return pa, pb, torch.rand(4, 6, generator=g, dtype=dtype)


def test_fused_photometric_term_matches_the_formula_and_its_gradient() -> None:
    """photometric_terms gives photometric_loss's values and autograd's gradient of that formula
    (float64: to rounding; float32: to float32 rounding), and passes gradcheck; no gradient to patch_a."""
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 1e-6)):
        pa, pb, w = _patches(dtype)
        b_ref = pb.clone().requires_grad_(True)
        b_new = pb.clone().requires_grad_(True)
        a_new = pa.clone().requires_grad_(True)
        ref = L.photometric_loss(pa.permute(0, 2, 3, 1), b_ref.permute(0, 2, 3, 1), w)
        new = L.weighted_mean(L.photometric_terms(a_new, b_new), w)
        torch.testing.assert_close(new, ref, atol=tol, rtol=tol)
        up = torch.linspace(-1, 2, 4, dtype=dtype)
        (ref * up).sum().backward()
        (new * up).sum().backward()
        assert b_ref.grad is not None and b_new.grad is not None and float(b_ref.grad.abs().max()) > 1e-3
        torch.testing.assert_close(b_new.grad, b_ref.grad, atol=tol, rtol=1e-5)
        assert a_new.grad is None
    pa, pb, _ = _patches(torch.float64)
    assert torch.autograd.gradcheck(lambda b: L.photometric_terms(pa, b), (pb.clone().requires_grad_(True),))
    assert float(L.photometric_terms(pa, pa).abs().max()) < 1e-9
