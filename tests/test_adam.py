"""The solver's Adam (stages/optimize/adam.py) is torch.optim.Adam bit for bit, resumes from its
state_dict, and an optimisation step imports neither torch._dynamo nor torch._inductor (2 s per
process that torch.optim.Adam and torch.use_deterministic_algorithms cost)."""

import subprocess
import sys

import pytest
import torch

from gcvd_flow.stages.optimize.adam import Adam


def _problem(seed: int):
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(5, 3, generator=g, dtype=torch.float32).requires_grad_(True)
    b = torch.randn(7, generator=g, dtype=torch.float64).requires_grad_(True)
    c = torch.randn(4, generator=g, dtype=torch.float32).requires_grad_(True)
    return [a, b, c]


def _loss(params, step: int) -> torch.Tensor:
    a, b, c = params
    loss = (a.sin() ** 2).sum() * 1.7 + (b.double() ** 3).abs().sum().float() * 0.3
    if step % 3:  # c gets no gradient on every third step (its state must not move then)
        loss = loss + (c * torch.arange(4.0)).cos().sum()
    return loss


def _run(opt_cls, params, steps: range, opt=None):
    opt = opt or opt_cls([{"params": params[:2], "lr": 0.05}, {"params": params[2:], "lr": 0.2}])
    for s in steps:
        opt.param_groups[0]["lr"] = 0.05 * (1 - s / 40)  # a schedule, as the solver's
        if isinstance(opt, Adam):
            opt.zero_grad()
        else:
            opt.zero_grad(set_to_none=True)
        _loss(params, s).backward()
        opt.step()
    return opt


def test_same_bits_as_torch_adam():
    ours, theirs = _problem(0), _problem(0)
    with torch.no_grad():
        for p, q in zip(ours, theirs):
            q.copy_(p)
    o = _run(Adam, ours, range(30))
    t = _run(torch.optim.Adam, theirs, range(30))
    for p, q in zip(ours, theirs):
        assert p.dtype == q.dtype and torch.equal(p, q), (p - q).abs().max()
    ts = t.state_dict()["state"]
    assert sorted(o.state) == sorted(ts)
    for i, st in o.state_dict()["state"].items():
        for k in ("step", "exp_avg", "exp_avg_sq"):
            assert torch.equal(st[k], ts[i][k]), (i, k)


def test_resumes_from_its_state_dict_to_the_same_bits():
    straight, resumed = _problem(1), _problem(1)
    _run(Adam, straight, range(20))
    first = _run(Adam, resumed, range(10))
    saved = {i: {k: v.clone() for k, v in st.items()} for i, st in first.state_dict()["state"].items()}
    again = Adam([{"params": resumed[:2], "lr": 0.05}, {"params": resumed[2:], "lr": 0.2}])
    sd = again.state_dict()
    sd["state"] = saved
    again.load_state_dict(sd)
    _run(Adam, resumed, range(10, 20), opt=again)
    for p, q in zip(straight, resumed):
        assert torch.equal(p, q)


def test_state_of_another_shape_is_refused():
    p = torch.zeros(3, requires_grad=True)
    opt = Adam([{"params": [p], "lr": 0.1}])
    with pytest.raises(ValueError, match="shape"):
        opt.load_state_dict({"state": {0: {"step": torch.tensor(1.0), "exp_avg": torch.zeros(4),
                                           "exp_avg_sq": torch.zeros(4)}}})


def test_an_optimisation_step_imports_neither_dynamo_nor_inductor():
    code = """
import sys, torch
from gcvd_flow.stages.optimize.adam import Adam
from gcvd_flow.stages.optimize.solver import deterministic
p = torch.ones(3, requires_grad=True)
opt = Adam([{"params": [p], "lr": 0.1}])
assert not torch.are_deterministic_algorithms_enabled()
with deterministic(0):
    assert torch.are_deterministic_algorithms_enabled()
    (p ** 2).sum().backward()
    opt.step()
assert not torch.are_deterministic_algorithms_enabled()
print(sorted(m for m in sys.modules if m.startswith(("torch._dynamo", "torch._inductor"))))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", out.stdout
