"""Networks: the test-time-trained depth and pose nets, and the weights backends (RAFT, MiDaS,
ResNet-18, Mask R-CNN) in plain torch, built from a state dict that the caller read
(``gcvd_flow.io.weights.read_state_dict``: safetensors, or ``torch.load(weights_only=True)``).

``load_model(name, state, source, **options)`` is the registry by name: the pipeline says
*which* backend a parameter chose; the loader modules are imported only when used.
"""

from __future__ import annotations

import importlib
from typing import Any

# name -> (module, loader function); loaders take (state dict, source label, **options)
REGISTRY: dict[str, tuple[str, str]] = {
    "raft": ("gcvd_flow.stages.models.raft", "load_raft"),
    "midas": ("gcvd_flow.stages.models.midas", "load_midas"),
    "resnet18": ("gcvd_flow.stages.models.resnet", "load_resnet18"),
    "maskrcnn": ("gcvd_flow.stages.models.maskrcnn", "load_maskrcnn"),
}


def load_model(name: str, state: Any, source: str = "state dict", **options: Any) -> Any:
    """The weights backend ``name`` with the weights ``state`` (name -> tensor; eval mode, CPU).
    ``source`` names where the weights came from in error messages."""
    if name not in REGISTRY:
        raise ValueError(f"unknown model {name!r}; known: {', '.join(sorted(REGISTRY))}")
    module, fn = REGISTRY[name]
    return getattr(importlib.import_module(module), fn)(state, source, **options)
