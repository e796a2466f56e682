"""Safe loading of model weights from local files, shared by the weights backends.

``.safetensors`` files are read as tensors only; ``.pt``/``.pth`` files with
``torch.load(weights_only=True)`` (no arbitrary unpickling). Loading is strict: a missing,
unexpected or mis-shaped key is a ``ValueError`` naming the key and the file.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn


def read_state_dict(path: Path) -> dict[str, torch.Tensor]:
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        state = load_file(str(path), device="cpu")
    else:
        state = torch.load(str(path), map_location="cpu", weights_only=True)
        if isinstance(state, dict):
            for key in ("state_dict", "model"):  # MiDaS training checkpoints: {"model", "optimizer"}
                if key in state and isinstance(state[key], dict):
                    state = state[key]
                    break
    if not isinstance(state, dict):
        raise ValueError(f"{path}: expected a state dict, got {type(state).__name__}")
    return {(k[len("module."):] if k.startswith("module.") else k): v for k, v in state.items()}


def load_strict(model: nn.Module, state: dict[str, torch.Tensor], path: Path) -> None:
    expected = model.state_dict()
    missing = [k for k in expected if k not in state]
    unexpected = [k for k in state if k not in expected]
    if missing or unexpected:
        parts = []
        if missing:
            parts.append(f"missing key {missing[0]!r} ({len(missing)} missing)")
        if unexpected:
            parts.append(f"unexpected key {unexpected[0]!r} ({len(unexpected)} unexpected)")
        raise ValueError(f"{path}: not a {type(model).__name__} state dict: " + "; ".join(parts))
    for k, v in expected.items():
        if tuple(state[k].shape) != tuple(v.shape):
            raise ValueError(f"{path}: key {k!r} has shape {tuple(state[k].shape)}, expected {tuple(v.shape)}")
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as e:  # pragma: no cover - guarded above
        raise ValueError(f"{path}: {e}") from e
