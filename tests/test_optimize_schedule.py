"""The per-window learning-rate schedule (``lr_schedule`` / ``lr_final_frac`` of the keyframe and
segment windows): the rates every Adam step uses, bit-exact resume, and its effect on a window."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from test_optimize import SMALL, SMALL_SEG, MemCheckpointer, _assert_same, _kf_run, tiny  # noqa: F401 (fixture)

from gcvd_flow.stages.optimize.segments import optimize_segments
from gcvd_flow.stages.optimize.solver import Solver, lr_factor

torch.set_num_threads(1)


def test_lr_factor_values() -> None:
    """1 at the first step, lr_final_frac at the last, monotone in between; cosine at the middle
    halfway; constant always 1."""
    for sched in ("cosine", "linear"):
        f = [lr_factor(sched, s, 11, 0.1) for s in range(11)]
        assert f[0] == 1.0 and math.isclose(f[-1], 0.1)
        assert all(a > b for a, b in zip(f, f[1:]))
        assert math.isclose(f[5], 0.55)
    assert math.isclose(lr_factor("linear", 2, 11, 0.0), 0.8)
    assert math.isclose(lr_factor("cosine", 2, 11, 0.0), 0.5 * (1 + math.cos(math.pi * 0.2)))
    assert all(lr_factor("constant", s, 11, 0.1) == 1.0 for s in range(11))
    assert lr_factor("cosine", 0, 1, 0.1) == 1.0  # one step: the start rate
    with pytest.raises(ValueError, match="lr_schedule 'step'"):
        lr_factor("step", 0, 10, 0.1)


class _RateSpy:
    """Records every group's learning rate at each Adam step of every window (Solver.step)."""

    def __init__(self) -> None:
        self.rates: list[list[float]] = []
        self.base: list[list[float]] = []
        self.start: list[list[float]] = []

    def __enter__(self) -> "_RateSpy":
        self.orig = Solver.step
        spy = self

        def step(solver: Solver, gen: torch.Generator) -> float:
            spy.rates.append([float(g["lr"]) for g in solver.opt.param_groups])
            spy.base.append(list(solver.base_lrs))
            spy.start.append(list(solver.start_lrs))
            return spy.orig(solver, gen)

        Solver.step = step  # type: ignore[method-assign]
        return self

    def __exit__(self, *exc: object) -> None:
        Solver.step = self.orig  # type: ignore[method-assign]


def test_keyframe_window_steps_follow_the_schedule(tiny: dict) -> None:  # noqa: F811
    """Every group (head, poses, mesh shape, per-frame scale) steps at its start rate (base rate x
    lr_start_mult, poses x pose_lr_start_mult) times the schedule's factor of the step index;
    constant leaves the base rates untouched; the schedule changes the result."""
    over = dict(window=8, steps=12, lr_final_frac=0.05, lr_start_mult=3.0, pose_lr_start_mult=2.0)
    with _RateSpy() as spy:
        cos = _kf_run(tiny, lr_schedule="cosine", **over)
    assert len(spy.rates) == 12 and len(spy.rates[0]) == 4
    base = spy.base[0]
    assert base == [SMALL.lr, SMALL.pose_lr, SMALL.lr * SMALL.mesh_lr_mult * SMALL.mesh_shape_lr_frac,
                    SMALL.lr * SMALL.mesh_lr_mult]
    start = [b * m for b, m in zip(base, (3.0, 2.0, 3.0, 3.0))]
    assert spy.start[0] == start
    for s, rates in enumerate(spy.rates):
        assert rates == [b * lr_factor("cosine", s, 12, 0.05) for b in start]
    assert spy.rates[0] == start and math.isclose(spy.rates[-1][1], 0.05 * 2.0 * SMALL.pose_lr)
    assert math.isclose(spy.rates[-1][0], 0.05 * 3.0 * SMALL.lr)
    with _RateSpy() as spy:
        const = _kf_run(tiny, lr_schedule="constant", **over)
    assert all(r == base for r in spy.rates)
    assert cos["poses"].tobytes() != const["poses"].tobytes()
    with _RateSpy() as spy:
        lin = _kf_run(tiny, lr_schedule="linear", **over)
    assert all(math.isclose(r, b * (0.05 + 0.95 * (1 - 6 / 11))) for r, b in zip(spy.rates[6], start))
    assert lin["poses"].tobytes() != cos["poses"].tobytes()


@pytest.mark.parametrize("interrupt_after", [2, 3])  # mid-window 0 (step 4 of 6), at the boundary to window 1
def test_scheduled_keyframe_resume_is_bit_exact(tiny: dict, interrupt_after: int) -> None:  # noqa: F811
    """The rates are a function of the step index: a window resumed from a checkpoint mid-way
    gives the bits of the uninterrupted run."""
    over = dict(lr_schedule="cosine", lr_final_frac=0.1, lr_start_mult=2.0)
    ref = _kf_run(tiny, **over)
    ck = MemCheckpointer(interrupt_after)
    with pytest.raises(KeyboardInterrupt):
        _kf_run(tiny, ck, **over)
    ck.interrupt_after = None
    with _RateSpy() as spy:
        res = _kf_run(tiny, ck, **over)
    _assert_same(res, ref)
    if interrupt_after == 2:  # resumed at step 4 of window 0: its last two steps at their scheduled rates
        assert [r[0] for r in spy.rates[:2]] == [SMALL.lr * 2.0 * lr_factor("cosine", s, 6, 0.1) for s in (4, 5)]


def test_segment_windows_follow_their_own_schedule(tiny: dict) -> None:  # noqa: F811
    """optimize_segments.lr_schedule and its start multipliers drive the segment windows' rates (not
    the keyframe settings), from each window's first step; constant: the base rates."""
    kres = _kf_run(tiny, steps=2)
    c = tiny["clip"]

    def run(seg_sched: str, kf_sched: str) -> tuple[dict, list[list[float]]]:
        with _RateSpy() as spy:
            out = optimize_segments(c.frames, tiny["prior"], tiny["masks"], c.K, tiny["adj"], tiny["kf"],
                                    kres["poses"], kres["depths"], kf=dataclasses.replace(SMALL, lr_schedule=kf_sched, lr_start_mult=5.0),
                                    seg=dataclasses.replace(SMALL_SEG, lr_schedule=seg_sched, lr_final_frac=0.2,
                                                            lr_start_mult=2.0, pose_lr_start_mult=1.5),
                                    seed=0, state=kres["state"])
        return out, spy.rates

    out, rates = run("linear", "constant")
    n = SMALL_SEG.steps
    assert len(rates) % n == 0 and len(rates) > n  # several windows
    f = [lr_factor("linear", s, n, 0.2) for s in range(n)]
    assert [r[0] for r in rates] == [SMALL_SEG.lr * 2.0 * x for x in f] * (len(rates) // n)
    assert [r[1] for r in rates] == [SMALL.pose_lr * 1.5 * x for x in f] * (len(rates) // n)
    ref, rates = run("constant", "cosine")
    assert all(r[0] == SMALL_SEG.lr for r in rates)
    assert out["poses"].tobytes() != ref["poses"].tobytes()


def test_decayed_window_settles_where_a_constant_rate_keeps_moving(tiny: dict) -> None:  # noqa: F811
    """The point of the schedule: at a constant rate Adam moves the poses at a near-constant pace
    to the last step, with a decaying one they settle (the last steps move them a fraction as
    far). One 8-keyframe window; the poses' movement over its last 3 steps."""

    def last_moves(sched: str) -> float:
        snaps: list[np.ndarray] = []
        orig = Solver.step

        def step(solver: Solver, gen: torch.Generator) -> float:
            out = orig(solver, gen)
            snaps.append(solver.poses().detach().numpy()[:, :3, 3].copy())
            return out

        Solver.step = step  # type: ignore[method-assign]
        try:
            _kf_run(tiny, window=8, steps=20, points=128, lr_schedule=sched, lr_final_frac=0.05)
        finally:
            Solver.step = orig  # type: ignore[method-assign]
        return float(np.abs(snaps[-1] - snaps[-4]).max())

    const, cos = last_moves("constant"), last_moves("cosine")
    assert const > 0 and cos < 0.3 * const, (const, cos)


def test_a_larger_start_rate_decayed_ends_lower_in_as_many_steps(tiny: dict) -> None:  # noqa: F811
    """What the schedule is for: the windows are short of steps rather than noisy (a decay from the
    base rates ends higher than the constant rates), so the rates start above the base ones and
    decay: the same steps end at a lower loss (mean of the last 5 steps' losses, one 8-keyframe
    window, 40 steps)."""

    def last5(**over: object) -> float:
        losses: list[float] = []
        orig = Solver.step

        def step(solver: Solver, gen: torch.Generator) -> float:
            losses.append(orig(solver, gen))
            return losses[-1]

        Solver.step = step  # type: ignore[method-assign]
        try:
            _kf_run(tiny, window=8, steps=40, points=128, **over)
        finally:
            Solver.step = orig  # type: ignore[method-assign]
        return float(np.mean(losses[-5:]))

    const = last5()
    decay = last5(lr_schedule="cosine", lr_final_frac=0.05)
    boosted = last5(lr_schedule="cosine", lr_final_frac=0.05, lr_start_mult=3.0, pose_lr_start_mult=2.0)
    # measured: 1.072, 1.173, 1.003
    assert decay > const and boosted < 0.97 * const, (const, decay, boosted)
