"""Networks: the test-time-trained depth and pose nets, and the weights backends (RAFT, MiDaS,
ResNet-18, Mask R-CNN) in plain torch, all read through one safe weights reader
(``weights.read_state_dict``: safetensors, or ``torch.load(weights_only=True)``).

``load_model(name, path, **options)`` is the registry by name: the pipeline says *which*
backend a parameter chose; the loader modules are imported only when used.
"""

from __future__ import annotations

import importlib
from typing import Any

# name -> (module, loader function); loaders take the weights path and keyword options
REGISTRY: dict[str, tuple[str, str]] = {
    "raft": ("stages.models.raft", "load_raft"),
    "midas": ("stages.models.midas", "load_midas"),
    "resnet18": ("stages.models.resnet", "load_resnet18"),
    "maskrcnn": ("stages.models.maskrcnn", "load_maskrcnn"),
}


def load_model(name: str, path: str, **options: Any) -> Any:
    """Load the weights backend ``name`` from the file ``path`` (eval mode, CPU)."""
    if name not in REGISTRY:
        raise ValueError(f"unknown model {name!r}; known: {', '.join(sorted(REGISTRY))}")
    module, fn = REGISTRY[name]
    return getattr(importlib.import_module(module), fn)(path, **options)
