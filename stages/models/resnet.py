"""ImageNet ResNet-18 global descriptor (the paper's association feature), plain torch.

The architecture matches torchvision's ``resnet18`` parameter for parameter (same module
names: ``conv1``, ``bn1``, ``layer{1..4}.{0,1}.{conv1,bn1,conv2,bn2,downsample.{0,1}}``,
``fc``), so a torchvision state dict (``resnet18-f37072fd.pth``) or its safetensors export
loads with ``strict=True``. torchvision itself is not importable beside this torch build.

Descriptor: ImageNet normalisation -> conv trunk -> global average pooling -> L2 norm,
float32 (512,). Use it with ``stages.association.RESNET_SIMILARITY_THRESHOLD`` (0.9).
No file is downloaded here: the user supplies a local weights file.
"""

from __future__ import annotations

import logging
from typing import Mapping

import numpy as np
import torch
from torch import nn

from gcvd_flow.stages.models.weights import load_strict

log = logging.getLogger(__name__)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class BasicBlock(nn.Module):
    expansion = 1

    def __init__(self, inplanes: int, planes: int, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(inplanes, planes, 3, stride=stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(planes, planes, 3, stride=1, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.downsample: nn.Module | None = None
        if stride != 1 or inplanes != planes:
            self.downsample = nn.Sequential(
                nn.Conv2d(inplanes, planes, 1, stride=stride, bias=False),
                nn.BatchNorm2d(planes),
            )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class ResNet18(nn.Module):
    """ResNet-18 (BasicBlock, [2, 2, 2, 2]) with torchvision parameter names."""

    def __init__(self, num_classes: int = 1000) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        self.layer1 = self._make_layer(64, 64, 1)
        self.layer2 = self._make_layer(64, 128, 2)
        self.layer3 = self._make_layer(128, 256, 2)
        self.layer4 = self._make_layer(256, 512, 2)
        self.avgpool = nn.AdaptiveAvgPool2d((1, 1))
        self.fc = nn.Linear(512, num_classes)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    @staticmethod
    def _make_layer(inplanes: int, planes: int, stride: int) -> nn.Sequential:
        return nn.Sequential(BasicBlock(inplanes, planes, stride), BasicBlock(planes, planes, 1))

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) normalised images -> (B, 512, H/32, W/32) trunk features."""
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        return self.layer4(self.layer3(self.layer2(self.layer1(x))))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc(torch.flatten(self.avgpool(self.features(x)), 1))


def load_resnet18(state: Mapping[str, torch.Tensor], source: str = "state dict") -> ResNet18:
    """Build ResNet-18 from a state dict (eval mode: BatchNorm uses running statistics); a key
    or shape mismatch raises ``ValueError`` naming it and ``source``."""
    model = ResNet18()
    # torchvision's published file predates BatchNorm's num_batches_tracked buffer
    state = {**{k: v for k, v in model.state_dict().items() if k.endswith("num_batches_tracked")}, **state}
    load_strict(model, state, source)
    model.eval()
    return model


@torch.no_grad()
def resnet_descriptor(model: ResNet18, image: np.ndarray) -> np.ndarray:
    """GAP descriptor of one image.

    Args:
        model: a :class:`ResNet18` (eval mode).
        image: uint8 (H, W, 3) RGB at working resolution (no resize: the GAP makes the
            descriptor size-independent, and the paper uses the working resolution).

    Returns:
        float32 (512,) L2-normalised.
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"image must be uint8 (H, W, 3), got {img.dtype} {img.shape}")
    x = torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1).float().div_(255.0)
    mean = torch.tensor(IMAGENET_MEAN).view(3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(3, 1, 1)
    x = ((x - mean) / std).unsqueeze(0)
    was_training = model.training
    model.eval()
    try:
        f = model.features(x).mean(dim=(2, 3))[0]
    finally:
        model.train(was_training)
    f = f / f.norm().clamp_min(1e-12)
    return f.numpy().astype(np.float32)
