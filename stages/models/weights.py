"""Strict loading of a state dict into a model (the file is read by the caller:
``gcvd_flow.io.weights.read_state_dict``; nothing in ``stages/`` touches the disk).

A missing, unexpected or mis-shaped key is a ``ValueError`` naming the key and the source.
"""

from __future__ import annotations

from typing import Mapping

import torch
from torch import nn


def load_strict(model: nn.Module, state: Mapping[str, torch.Tensor], source: str) -> None:
    """Copy ``state`` into ``model``: every key present, none extra, every shape equal."""
    expected = model.state_dict()
    missing = [k for k in expected if k not in state]
    unexpected = [k for k in state if k not in expected]
    if missing or unexpected:
        parts = []
        if missing:
            parts.append(f"missing key {missing[0]!r} ({len(missing)} missing)")
        if unexpected:
            parts.append(f"unexpected key {unexpected[0]!r} ({len(unexpected)} unexpected)")
        raise ValueError(f"{source}: not a {type(model).__name__} state dict: " + "; ".join(parts))
    for k, v in expected.items():
        if tuple(state[k].shape) != tuple(v.shape):
            raise ValueError(f"{source}: key {k!r} has shape {tuple(state[k].shape)}, expected {tuple(v.shape)}")
    try:
        model.load_state_dict(dict(state), strict=True)
    except RuntimeError as e:  # pragma: no cover - guarded above
        raise ValueError(f"{source}: {e}") from e
