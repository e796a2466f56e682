"""Parameters of the keyframe graph stages (keyframes, association): one frozen dataclass per
stage; the pipeline derives each config section from it (``stages/params.py``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from stages.params import WEIGHTS_FILE, param


@dataclass(frozen=True)
class KeyframesSettings:
    """Keyframe selection by accumulated static-scene flow (stages.graph.keyframes)."""

    enabled: bool = True
    delta: float = param(0.1, "accumulated flow threshold, fraction of min(H, W)", gt=0)
    max_gap: int = param(39, ge=1)


@dataclass(frozen=True)
class AssociationSettings:
    """Loop candidates and the keyframe graph (stages.graph.association)."""

    enabled: bool = True
    backend: Literal["default", "resnet18"] = "default"
    weights: str | None = param(None, "ResNet-18 weights file", json_schema_extra=WEIGHTS_FILE)
    threshold: float | None = param(None, "descriptor similarity threshold (None: backend default)")
    nms: int = 8
    min_separation: int = 8
    min_inlier_ratio: float = 0.5
    min_consistent: float = 0.1

    def check(self) -> None:
        if self.backend == "resnet18" and not self.weights:
            raise ValueError("association.backend=resnet18 needs association.weights=FILE "
                             "(torchvision resnet18, .pth or .safetensors)")
