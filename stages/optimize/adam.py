"""Adam, step for step the arithmetic of ``torch.optim.Adam`` on CPU (its single-tensor path,
default betas and eps, no weight decay, amsgrad off), without torch.optim.

Why not torch.optim.Adam: its ``step`` and ``add_param_group`` import ``torch._dynamo`` on first
use (to mark themselves as not traceable), 2 s of imports in every process that optimises: the
largest fixed cost of a small run and of each worker process. The update is the same operations
in the same order, so the results are bit-identical to torch's (``tests/test_adam.py``).

Interface: the part of ``torch.optim.Optimizer`` the solver uses: ``param_groups`` (a list of
{"params": [tensor, ...], "lr": float}; a group's "lr" may be changed between steps),
``zero_grad()`` (to None), ``step()``, and ``state_dict`` / ``load_state_dict`` with torch's
"state" layout ({"state": {global parameter index: {"step", "exp_avg", "exp_avg_sq"}}}).
"""

from __future__ import annotations

from typing import Any, Iterable

import torch

BETA1, BETA2, EPS = 0.9, 0.999, 1e-8  # torch.optim.Adam's defaults


class Adam:
    def __init__(self, groups: Iterable[dict[str, Any]]) -> None:
        self.param_groups: list[dict[str, Any]] = [{"params": list(g["params"]), "lr": float(g["lr"])}
                                                   for g in groups]
        self.state: dict[int, dict[str, torch.Tensor]] = {}  # global parameter index -> moments

    def _params(self) -> Iterable[tuple[int, torch.Tensor, float]]:
        i = 0
        for g in self.param_groups:
            for p in g["params"]:
                yield i, p, float(g["lr"])
                i += 1

    def zero_grad(self) -> None:
        """Gradients to None (torch's ``zero_grad(set_to_none=True)``)."""
        for _, p, _ in self._params():
            p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        for i, p, lr in self._params():
            if p.grad is None:  # as torch: no gradient, no state and no update
                continue
            st = self.state.get(i)
            if st is None:
                st = self.state[i] = {"step": torch.tensor(0.0, dtype=torch.float32),
                                      "exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
                                      "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format)}
            grad, exp_avg, exp_avg_sq = p.grad, st["exp_avg"], st["exp_avg_sq"]
            st["step"] += 1
            exp_avg.lerp_(grad, 1 - BETA1)
            exp_avg_sq.mul_(BETA2).addcmul_(grad, grad, value=1 - BETA2)
            step = st["step"].item()
            bias_correction1 = 1 - BETA1 ** step
            bias_correction2 = 1 - BETA2 ** step
            step_size = lr / bias_correction1
            denom = (exp_avg_sq.sqrt() / bias_correction2 ** 0.5).add_(EPS)
            p.addcdiv_(exp_avg, denom, value=-step_size)

    def state_dict(self) -> dict[str, Any]:
        return {"state": {i: dict(st) for i, st in self.state.items()}}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        """Moments by global parameter index (checked against the parameters' shapes; copies)."""
        params = {i: p for i, p, _ in self._params()}
        state: dict[int, dict[str, torch.Tensor]] = {}
        for i, st in sd["state"].items():
            p = params.get(int(i))
            if p is None:
                raise ValueError(f"Adam state for parameter {i}: there are {len(params)} parameters")
            for name in ("exp_avg", "exp_avg_sq"):
                if tuple(st[name].shape) != tuple(p.shape):
                    raise ValueError(f"Adam state {i}.{name}: shape {tuple(st[name].shape)}, parameter {tuple(p.shape)}")
            state[int(i)] = {"step": torch.as_tensor(st["step"], dtype=torch.float32).clone().reshape(()),
                             "exp_avg": st["exp_avg"].to(p.dtype).clone(),
                             "exp_avg_sq": st["exp_avg_sq"].to(p.dtype).clone()}
        self.state = state
