"""Mask R-CNN (He et al., ICCV 2017), ResNet-50-FPN, COCO: the semantic mask backend, plain torch.

Inference only (no training losses), one image at a time. Written without torchvision (not
installable beside this torch build); the architecture matches torchvision's
``maskrcnn_resnet50_fpn`` (v1, 91 COCO labels) parameter for parameter, with torchvision's
*current* (>= 0.13, ``Conv2dNormActivation``) module names, so its state dict or a safetensors
export of it loads with ``strict=True``:

* ``backbone.body`` -- ResNet-50 trunk without ``fc``: ``conv1``, ``bn1``,
  ``layer{1..4}.{i}.{conv1,bn1,conv2,bn2,conv3,bn3,downsample.{0,1}}`` (stride on the 3x3
  conv). Every norm is a ``FrozenBatchNorm2d``: buffers ``weight, bias, running_mean,
  running_var`` only (no ``num_batches_tracked``, no parameters).
* ``backbone.fpn`` -- ``inner_blocks.{0..3}.0`` (1x1 laterals from 256/512/1024/2048 to 256)
  and ``layer_blocks.{0..3}.0`` (3x3 outputs); levels '0'..'3' at strides 4..32 plus 'pool'
  (``max_pool2d(P5, 1, 2)``, LastLevelMaxPool).
* ``rpn.head`` -- ``conv.0.0`` (3x3 + ReLU), ``cls_logits`` (3 anchors), ``bbox_pred`` (12).
* ``roi_heads.box_head.fc6/fc7`` (256*7*7 -> 1024 -> 1024) and
  ``roi_heads.box_predictor.cls_score/bbox_pred`` (91 / 364).
* ``roi_heads.mask_head.{0..3}.0`` (four 3x3 convs + ReLU on 14x14 RoIs) and
  ``roi_heads.mask_predictor.conv5_mask`` (2x2 transposed conv to 28x28) /
  ``mask_fcn_logits`` (1x1 to 91 per-class mask logits).

Checkpoints written before torchvision 0.13 -- among them the released
``maskrcnn_resnet50_fpn_coco-bf2d0c1e.pth`` -- name four of these differently
(``backbone.fpn.{inner,layer}_blocks.{i}.weight``, ``rpn.head.conv.weight``,
``roi_heads.mask_head.mask_fcn{1..4}.weight``); torchvision renames them on load
(``_load_from_state_dict`` version hooks) and so does :func:`load_maskrcnn`
(:func:`upgrade_state_dict`), which also drops ``num_batches_tracked`` buffers as torchvision's
``FrozenBatchNorm2d`` does. Everything else must match exactly.

Parameter count: 44,401,393 (``sum(p.numel() for p in model.parameters())``, the figure
torchvision gives for ``maskrcnn_resnet50_fpn``; the frozen-BN buffers are not parameters).

Inference follows torchvision's eval path: GeneralizedRCNNTransform (ImageNet mean/std, bilinear
resize so the short side is ``min_size`` and the long side <= 1333, zero padding to multiples
of 32); anchors 32..512 (one size per level) x aspect ratios (0.5, 1, 2); RPN (1000 top
anchors per level before NMS, NMS 0.7 per level, 1000 kept, box coder weights (1, 1, 1, 1),
clipping, boxes < 1e-3 px removed); MultiScaleRoIAlign over '0'..'3' (level
floor(4 + log2(sqrt(area) / 224)) clamped to 2..5, sampling ratio 2, ``aligned=False``, 7x7
boxes / 14x14 masks); box head, weights (10, 10, 5, 5), score > 0.05, per-class NMS 0.5,
100 detections; mask head, the predicted class's 28x28 sigmoid mask pasted back into the
original image (torchvision's ``paste_masks_in_image``). NMS and RoIAlign are written here in
plain torch / numpy with torchvision's CPU-kernel semantics: RoIAlign samples with
``grid_sample`` on a map padded by one replicated pixel, which reproduces the kernel's boundary
rules (equal up to float rounding, ~1e-6); batched NMS always uses the coordinate-offset trick
(torchvision switches to a per-class loop above 1000 CPU boxes: same result up to the rounding
of the offsets).

BatchNorm epsilon: torchvision's FrozenBatchNorm2d defaults to 1e-5, but
``maskrcnn_resnet50_fpn`` sets it to 0.0 after loading the COCO v1 weights
(``overwrite_eps(model, 0.0)``: they come from Detectron, which folds BN without epsilon).
This module exists to run those weights, so ``bn_eps`` defaults to 0.0.

No file is downloaded here: the user supplies a local weights file.
"""

from __future__ import annotations

import logging
import math
from collections import OrderedDict
from typing import Mapping, Sequence, cast

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from gcvd_flow.stages.models.resnet import IMAGENET_MEAN, IMAGENET_STD
from gcvd_flow.stages.models.weights import load_strict

log = logging.getLogger(__name__)

NUM_CLASSES = 91
MIN_SIZE = 800
MAX_SIZE = 1333
SIZE_DIVISIBLE = 32
BN_EPS_COCO = 0.0

ANCHOR_SIZES = (32, 64, 128, 256, 512)  # one per FPN level '0'..'3', 'pool'
ASPECT_RATIOS = (0.5, 1.0, 2.0)
RPN_PRE_NMS_TOP_N = 1000  # per level
RPN_POST_NMS_TOP_N = 1000
RPN_NMS_THRESH = 0.7
RPN_MIN_SIZE = 1e-3
RPN_BOX_WEIGHTS = (1.0, 1.0, 1.0, 1.0)
BOX_WEIGHTS = (10.0, 10.0, 5.0, 5.0)
BBOX_XFORM_CLIP = math.log(1000.0 / 16)
BOX_SCORE_THRESH = 0.05
BOX_NMS_THRESH = 0.5
BOX_MIN_SIZE = 1e-2
DETECTIONS_PER_IMG = 100
BOX_POOL_SIZE = 7
MASK_POOL_SIZE = 14
SAMPLING_RATIO = 2
CANONICAL_SCALE = 224
CANONICAL_LEVEL = 4

# torchvision's 91-index COCO labels of things that move (index 0 is the background; the
# indices skip the "N/A" slots of the original 91 COCO category ids).
DYNAMIC_COCO_NAMES = {
    1: "person", 2: "bicycle", 3: "car", 4: "motorcycle", 5: "airplane", 6: "bus", 7: "train",
    8: "truck", 9: "boat", 16: "bird", 17: "cat", 18: "dog", 19: "horse", 20: "sheep", 21: "cow",
    22: "elephant", 23: "bear", 24: "zebra", 25: "giraffe",
}
DYNAMIC_COCO_CLASSES: tuple[int, ...] = tuple(sorted(DYNAMIC_COCO_NAMES))


# --------------------------------------------------------------------------------------------
# boxes, NMS
# --------------------------------------------------------------------------------------------


def box_area(boxes: torch.Tensor) -> torch.Tensor:
    """(K, 4) xyxy -> (K,)."""
    return (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])


def decode_boxes(deltas: torch.Tensor, boxes: torch.Tensor, weights: Sequence[float]) -> torch.Tensor:
    """Apply (dx, dy, dw, dh) deltas to reference boxes (torchvision's BoxCoder.decode_single).

    deltas (K, 4 * C) (C classes, or 1 for the RPN); boxes (K, 4) xyxy. Returns (K, C, 4) xyxy.
    """
    boxes = boxes.to(deltas.dtype)
    widths = boxes[:, 2] - boxes[:, 0]
    heights = boxes[:, 3] - boxes[:, 1]
    ctr_x = boxes[:, 0] + 0.5 * widths
    ctr_y = boxes[:, 1] + 0.5 * heights
    wx, wy, ww, wh = weights
    dx = deltas[:, 0::4] / wx
    dy = deltas[:, 1::4] / wy
    dw = (deltas[:, 2::4] / ww).clamp(max=BBOX_XFORM_CLIP)
    dh = (deltas[:, 3::4] / wh).clamp(max=BBOX_XFORM_CLIP)
    pred_ctr_x = dx * widths[:, None] + ctr_x[:, None]
    pred_ctr_y = dy * heights[:, None] + ctr_y[:, None]
    half_w = 0.5 * (torch.exp(dw) * widths[:, None])
    half_h = 0.5 * (torch.exp(dh) * heights[:, None])
    return torch.stack((pred_ctr_x - half_w, pred_ctr_y - half_h, pred_ctr_x + half_w, pred_ctr_y + half_h), dim=2)


def clip_boxes(boxes: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """(..., 4) xyxy clamped to [0, w] x [0, h]; size = (h, w)."""
    h, w = size
    x = boxes[..., 0::2].clamp(min=0, max=w)
    y = boxes[..., 1::2].clamp(min=0, max=h)
    return torch.stack((x, y), dim=boxes.dim()).reshape(boxes.shape)


def remove_small_boxes(boxes: torch.Tensor, min_size: float) -> torch.Tensor:
    """(K, 4) -> int64 indices of the boxes whose sides are both >= min_size."""
    ws, hs = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
    return torch.where((ws >= min_size) & (hs >= min_size))[0]


def nms(boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """Greedy non-maximum suppression (torchvision's CPU kernel).

    boxes (K, 4) xyxy, scores (K,). Boxes are visited by decreasing score (stable sort); each kept
    box suppresses the later ones whose IoU with it is > ``iou_threshold`` (compared in double,
    IoU in the boxes' precision). Returns int64 indices of the kept boxes, by decreasing score.
    """
    if boxes.numel() == 0:
        return torch.zeros(0, dtype=torch.int64)
    order = torch.sort(scores, descending=True, stable=True).indices
    b = boxes[order].detach().cpu().numpy()
    x1, y1, x2, y2 = (np.ascontiguousarray(b[:, k]) for k in range(4))
    areas = (x2 - x1) * (y2 - y1)
    thr = np.float64(iou_threshold)
    zero = np.zeros((), b.dtype)
    suppressed = np.zeros(len(b), bool)
    keep = []
    with np.errstate(invalid="ignore", divide="ignore"):  # 0 / 0 -> nan -> never suppresses
        for i in range(len(b)):
            if suppressed[i]:
                continue
            keep.append(i)
            w = np.maximum(zero, np.minimum(x2[i], x2[i + 1:]) - np.maximum(x1[i], x1[i + 1:]))
            h = np.maximum(zero, np.minimum(y2[i], y2[i + 1:]) - np.maximum(y1[i], y1[i + 1:]))
            inter = w * h
            suppressed[i + 1:] |= inter / (areas[i] + areas[i + 1:] - inter) > thr
    return order[torch.as_tensor(keep, dtype=torch.int64)]


def batched_nms(boxes: torch.Tensor, scores: torch.Tensor, idxs: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """NMS independently per category ``idxs`` (K,), by offsetting each category's boxes by
    idx * (max coordinate + 1) so that boxes of different categories never overlap.
    Returns int64 indices by decreasing score."""
    if boxes.numel() == 0:
        return torch.zeros(0, dtype=torch.int64)
    offsets = idxs.to(boxes) * (boxes.max() + 1)
    return nms(boxes + offsets[:, None], scores, iou_threshold)


# --------------------------------------------------------------------------------------------
# RoIAlign
# --------------------------------------------------------------------------------------------


def _sample_grid(coord: torch.Tensor, size: int) -> torch.Tensor:
    """Sample positions (K, S) in feature pixels -> ``grid_sample`` coordinates on the padded map.

    torchvision's RoIAlign reads a sample at y in [-1, size] at clamp(y, 0, size - 1) and counts
    one outside that range as 0. On the feature map padded by one replicated pixel per side,
    bilinear sampling at y + 1 gives the clamped reading exactly in that range; samples outside
    it are sent far off the map, where ``padding_mode="zeros"`` reads 0.
    """
    valid = (coord >= -1.0) & (coord <= size)
    norm = (coord + 1.0) * (2.0 / (size + 1)) - 1.0  # align_corners=True on size + 2 pixels
    return torch.where(valid, norm, torch.full_like(norm, -4.0))


def _roi_align_grid(padded: torch.Tensor, start: tuple[torch.Tensor, torch.Tensor],
                    bin_size: tuple[torch.Tensor, torch.Tensor], pooled: tuple[int, int],
                    grid: tuple[int, int]) -> torch.Tensor:
    """RoIAlign of k RoIs of one image sharing one sampling grid (gh x gw samples per bin).

    padded (1, C, H + 2, W + 2) features with a replicated border; start = (y0, x0) and
    bin_size = (bh, bw), each (k,), in (unpadded) feature pixels.
    Returns (k, C, ph, pw): per bin, the mean of its samples.
    """
    C, H, W = padded.shape[1], padded.shape[2] - 2, padded.shape[3] - 2
    (ph, pw), (gh, gw) = pooled, grid
    (y0, x0), (bh, bw) = start, bin_size
    k = y0.shape[0]
    if gh == 0 or gw == 0:
        return padded.new_zeros((k, C, ph, pw))

    def positions(s0: torch.Tensor, b: torch.Tensor, n_bins: int, g: int) -> torch.Tensor:
        i = torch.arange(n_bins * g, dtype=padded.dtype)
        p, j = torch.div(i, g, rounding_mode="floor"), i.remainder(g)
        return s0[:, None] + p[None] * b[:, None] + (j[None] + 0.5) * b[:, None] / g  # (k, n_bins * g)

    gy = _sample_grid(positions(y0, bh, ph, gh), H)
    gx = _sample_grid(positions(x0, bw, pw, gw), W)
    Sy, Sx = ph * gh, pw * gw
    # the (x, y) sample points of each RoI, (k, Sy, Sx, 2), on the one map (expanded, not copied)
    pts = torch.stack((gx[:, None, :].expand(k, Sy, Sx), gy[:, :, None].expand(k, Sy, Sx)), -1)
    vals = F.grid_sample(padded.expand(k, -1, -1, -1), pts, mode="bilinear", padding_mode="zeros",
                         align_corners=True)  # (k, C, Sy, Sx)
    # the mean over each bin's gh x gw samples (out-of-range ones count as zeros)
    return F.avg_pool2d(vals, (gh, gw))


def roi_align(features: torch.Tensor, rois: torch.Tensor, output_size: int | tuple[int, int], spatial_scale: float,
              sampling_ratio: int, aligned: bool = False, max_elements: int = 1 << 22) -> torch.Tensor:
    """RoIAlign (torchvision.ops.roi_align semantics), plain torch.

    Args:
        features: (N, C, H, W).
        rois: (K, 5) rows (batch index, x1, y1, x2, y2) in input-image pixels.
        output_size: ph or (ph, pw) bins.
        spatial_scale: feature pixels per input pixel (e.g. 1/4).
        sampling_ratio: samples per bin side; <= 0: ceil(roi side / bins), per RoI.
        aligned: False (torchvision's default, used by Mask R-CNN): no half-pixel shift, and RoI
            sides are at least 1 feature pixel.
        max_elements: RoIs are sampled in chunks of about this many values.

    Returns:
        (K, C, ph, pw): per bin, the average of bilinear samples on a regular grid; samples
        outside [-1, size] count as zeros in the average.
    """
    ph, pw = (output_size, output_size) if isinstance(output_size, int) else output_size
    C = features.shape[1]
    K = rois.shape[0]
    out = features.new_zeros((K, C, ph, pw))
    if K == 0:
        return out
    rois = rois.to(features.dtype)
    offset = 0.5 if aligned else 0.0
    x1 = rois[:, 1] * spatial_scale - offset
    y1 = rois[:, 2] * spatial_scale - offset
    roi_w = rois[:, 3] * spatial_scale - offset - x1
    roi_h = rois[:, 4] * spatial_scale - offset - y1
    if not aligned:
        roi_w, roi_h = roi_w.clamp(min=1.0), roi_h.clamp(min=1.0)
    bin_h, bin_w = roi_h / ph, roi_w / pw
    if sampling_ratio > 0:
        grids = torch.full((K, 2), sampling_ratio, dtype=torch.int64)
    else:
        grids = torch.stack((torch.ceil(roi_h / ph), torch.ceil(roi_w / pw)), 1).to(torch.int64)
    batch = rois[:, 0].to(torch.int64)
    for n in torch.unique(batch).tolist():
        padded = F.pad(features[n:n + 1], (1, 1, 1, 1), mode="replicate")
        for gh, gw in torch.unique(grids[batch == n], dim=0).tolist():
            members = torch.where((batch == n) & (grids[:, 0] == gh) & (grids[:, 1] == gw))[0]
            for part in members.split(max(1, max_elements // max(1, C * ph * gh * pw * gw))):
                out[part] = _roi_align_grid(padded, (y1[part], x1[part]), (bin_h[part], bin_w[part]),
                                            (ph, pw), (gh, gw))
    return out


def _infer_scale(feature: torch.Tensor, image_size: tuple[int, int]) -> float:
    """Power-of-two feature scale from the heights (torchvision's MultiScaleRoIAlign)."""
    approx = float(feature.shape[-2]) / float(image_size[0])
    return 2.0 ** float(torch.tensor(approx).log2().round())


def multiscale_roi_align(features: Sequence[torch.Tensor], boxes: torch.Tensor, image_size: tuple[int, int],
                         output_size: int, sampling_ratio: int = SAMPLING_RATIO) -> torch.Tensor:
    """RoIAlign of each box on its FPN level (torchvision's MultiScaleRoIAlign, one image).

    features: FPN levels '0'..'3', each (1, C, h_l, w_l); boxes (K, 4) xyxy in the resized image;
    image_size (h, w) of the resized image before padding. A box of side sqrt(area) = s goes to
    level floor(4 + log2(s / 224) + 1e-6), clamped to the available levels.
    Returns (K, C, output_size, output_size).
    """
    scales = [_infer_scale(f, image_size) for f in features]
    k_min, k_max = int(-math.log2(scales[0])), int(-math.log2(scales[-1]))
    s = torch.sqrt(box_area(boxes))
    target = torch.floor(CANONICAL_LEVEL + torch.log2(s / CANONICAL_SCALE) + torch.tensor(1e-6, dtype=s.dtype))
    levels = target.clamp(min=k_min, max=k_max).to(torch.int64) - k_min
    rois = torch.cat([boxes.new_zeros((boxes.shape[0], 1)), boxes], dim=1)
    out = features[0].new_zeros((boxes.shape[0], features[0].shape[1], output_size, output_size))
    for level, (feat, scale) in enumerate(zip(features, scales)):
        idx = torch.where(levels == level)[0]
        if idx.numel():
            out[idx] = roi_align(feat, rois[idx], output_size, scale, sampling_ratio)
    return out


# --------------------------------------------------------------------------------------------
# masks back into the image
# --------------------------------------------------------------------------------------------


def paste_masks_in_image(masks: torch.Tensor, boxes: torch.Tensor, size: tuple[int, int],
                         padding: int = 1) -> torch.Tensor:
    """Paste M x M box-relative masks into an image (torchvision's paste_masks_in_image).

    masks (N, M, M) probabilities; boxes (N, 4) xyxy px of the target image; size (H, W).
    Each mask gets a ``padding``-px zero border, its box is grown accordingly and truncated to
    integers, the mask is resized bilinearly to the box's (w + 1, h + 1) px and copied in
    (clipped to the image). Returns (N, H, W) float.
    """
    H, W = size
    out = masks.new_zeros((masks.shape[0], H, W))
    if masks.shape[0] == 0:
        return out
    M = masks.shape[-1]
    masks = F.pad(masks, (padding,) * 4)
    scale = float(M + 2 * padding) / M
    half_w = (boxes[:, 2] - boxes[:, 0]) * 0.5 * scale
    half_h = (boxes[:, 3] - boxes[:, 1]) * 0.5 * scale
    cx, cy = (boxes[:, 2] + boxes[:, 0]) * 0.5, (boxes[:, 3] + boxes[:, 1]) * 0.5
    grown = torch.stack((cx - half_w, cy - half_h, cx + half_w, cy + half_h), 1).to(torch.int64)
    for n, (bx0, by0, bx1, by1) in enumerate(grown.tolist()):
        w, h = max(bx1 - bx0 + 1, 1), max(by1 - by0 + 1, 1)
        m = F.interpolate(masks[n][None, None], size=(h, w), mode="bilinear", align_corners=False)[0, 0]
        x0, x1 = max(bx0, 0), min(bx1 + 1, W)
        y0, y1 = max(by0, 0), min(by1 + 1, H)
        if x1 > x0 and y1 > y0:
            out[n, y0:y1, x0:x1] = m[y0 - by0:y1 - by0, x0 - bx0:x1 - bx0]
    return out


# --------------------------------------------------------------------------------------------
# backbone: ResNet-50 + FPN
# --------------------------------------------------------------------------------------------


class FrozenBatchNorm2d(nn.Module):
    """BatchNorm with fixed statistics and affine terms, all buffers: y = (x - mean) / sqrt(var + eps) * w + b."""

    weight: torch.Tensor  # buffers (register_buffer), declared for the type checker
    bias: torch.Tensor
    running_mean: torch.Tensor
    running_var: torch.Tensor

    def __init__(self, num_features: int, eps: float = BN_EPS_COCO) -> None:
        super().__init__()
        self.eps = eps
        self.register_buffer("weight", torch.ones(num_features))
        self.register_buffer("bias", torch.zeros(num_features))
        self.register_buffer("running_mean", torch.zeros(num_features))
        self.register_buffer("running_var", torch.ones(num_features))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        scale = self.weight * (self.running_var + self.eps).rsqrt()
        shift = self.bias - self.running_mean * scale
        return x * scale.view(1, -1, 1, 1) + shift.view(1, -1, 1, 1)


class Bottleneck(nn.Module):
    """ResNet v1.5 bottleneck: 1x1 -> 3x3 (strided) -> 1x1 (x4 channels), projection shortcut."""

    expansion = 4

    def __init__(self, inplanes: int, planes: int, stride: int, bn_eps: float) -> None:
        super().__init__()
        out = planes * self.expansion
        self.conv1 = nn.Conv2d(inplanes, planes, 1, bias=False)
        self.bn1 = FrozenBatchNorm2d(planes, bn_eps)
        self.conv2 = nn.Conv2d(planes, planes, 3, stride=stride, padding=1, bias=False)
        self.bn2 = FrozenBatchNorm2d(planes, bn_eps)
        self.conv3 = nn.Conv2d(planes, out, 1, bias=False)
        self.bn3 = FrozenBatchNorm2d(out, bn_eps)
        self.relu = nn.ReLU(inplace=True)
        self.downsample: nn.Module | None = None
        if stride != 1 or inplanes != out:
            self.downsample = nn.Sequential(nn.Conv2d(inplanes, out, 1, stride=stride, bias=False),
                                            FrozenBatchNorm2d(out, bn_eps))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        y = self.relu(self.bn1(self.conv1(x)))
        y = self.relu(self.bn2(self.conv2(y)))
        return self.relu(self.bn3(self.conv3(y)) + identity)


class ResNet50Body(nn.Module):
    """``backbone.body``: ResNet-50 stem and stages (blocks 3, 4, 6, 3), no pooling / fc."""

    layer1: nn.Sequential  # set by name in __init__ (the checkpoint's keys)
    layer2: nn.Sequential
    layer3: nn.Sequential
    layer4: nn.Sequential

    def __init__(self, bn_eps: float) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, stride=2, padding=3, bias=False)
        self.bn1 = FrozenBatchNorm2d(64, bn_eps)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        inplanes = 64
        for i, (planes, blocks, stride) in enumerate(((64, 3, 1), (128, 4, 2), (256, 6, 2), (512, 3, 2)), 1):
            layer = [Bottleneck(inplanes, planes, stride, bn_eps)]
            inplanes = planes * Bottleneck.expansion
            layer += [Bottleneck(inplanes, planes, 1, bn_eps) for _ in range(blocks - 1)]
            setattr(self, f"layer{i}", nn.Sequential(*layer))
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """(1, 3, H, W), H, W multiples of 32 -> [C2 (256, H/4), C3 (512, H/8), C4 (1024, H/16), C5 (2048, H/32)]."""
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        feats = []
        for layer in (self.layer1, self.layer2, self.layer3, self.layer4):
            x = layer(x)
            feats.append(x)
        return feats


class FeaturePyramidNetwork(nn.Module):
    """``backbone.fpn``: top-down pathway with nearest upsampling, 256 channels, plus 'pool'."""

    def __init__(self, in_channels: Sequence[int] = (256, 512, 1024, 2048), out_channels: int = 256) -> None:
        super().__init__()
        self.inner_blocks = nn.ModuleList([nn.Sequential(nn.Conv2d(c, out_channels, 1)) for c in in_channels])
        self.layer_blocks = nn.ModuleList([nn.Sequential(nn.Conv2d(out_channels, out_channels, 3, padding=1))
                                           for _ in in_channels])
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_uniform_(m.weight, a=1)
                nn.init.zeros_(cast(torch.Tensor, m.bias))  # every Conv2d here has a bias

    def forward(self, x: list[torch.Tensor]) -> list[torch.Tensor]:
        """[C2..C5] -> [P2, P3, P4, P5, P6 = max_pool2d(P5, 1, stride 2)], each (1, 256, h_l, w_l)."""
        last = self.inner_blocks[-1](x[-1])
        results = [self.layer_blocks[-1](last)]
        for idx in range(len(x) - 2, -1, -1):
            lateral = self.inner_blocks[idx](x[idx])
            last = lateral + F.interpolate(last, size=lateral.shape[-2:], mode="nearest")
            results.insert(0, self.layer_blocks[idx](last))
        results.append(F.max_pool2d(results[-1], 1, 2, 0))
        return results


class Backbone(nn.Module):
    def __init__(self, bn_eps: float) -> None:
        super().__init__()
        self.body = ResNet50Body(bn_eps)
        self.fpn = FeaturePyramidNetwork()

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        return self.fpn(self.body(x))


# --------------------------------------------------------------------------------------------
# region proposals
# --------------------------------------------------------------------------------------------


def cell_anchors(size: int, aspect_ratios: Sequence[float] = ASPECT_RATIOS) -> torch.Tensor:
    """(A, 4) zero-centred anchors of one size, aspect ratio h / w, rounded to integers."""
    scales = torch.as_tensor([float(size)])
    ratios = torch.as_tensor(aspect_ratios, dtype=torch.float32)
    h_ratios = torch.sqrt(ratios)
    w_ratios = 1 / h_ratios
    ws = (w_ratios[:, None] * scales[None, :]).view(-1)
    hs = (h_ratios[:, None] * scales[None, :]).view(-1)
    return (torch.stack([-ws, -hs, ws, hs], dim=1) / 2).round()


def grid_anchors(feature_sizes: Sequence[tuple[int, int]], padded_size: tuple[int, int]) -> list[torch.Tensor]:
    """Anchors of every level: (h_l * w_l * A, 4) xyxy, ordered (y, x, anchor) like the head outputs.

    The stride of a level is padded_size // feature size (integer division, as torchvision).
    """
    out = []
    for (gh, gw), size in zip(feature_sizes, ANCHOR_SIZES):
        sy, sx = padded_size[0] // gh, padded_size[1] // gw
        shift_y, shift_x = torch.meshgrid(torch.arange(gh, dtype=torch.int32) * sy,
                                          torch.arange(gw, dtype=torch.int32) * sx, indexing="ij")
        shift_x, shift_y = shift_x.reshape(-1), shift_y.reshape(-1)
        shifts = torch.stack((shift_x, shift_y, shift_x, shift_y), dim=1)
        out.append((shifts.view(-1, 1, 4) + cell_anchors(size).view(1, -1, 4)).reshape(-1, 4))
    return out


class RPNHead(nn.Module):
    """``rpn.head``: shared 3x3 conv + ReLU, then per-anchor objectness and box deltas."""

    def __init__(self, in_channels: int = 256, num_anchors: int = len(ASPECT_RATIOS)) -> None:
        super().__init__()
        conv = nn.Sequential(nn.Conv2d(in_channels, in_channels, 3, padding=1), nn.ReLU(inplace=True))
        self.conv = nn.Sequential(conv)  # torchvision: Sequential(Conv2dNormActivation(...)) -> conv.0.0
        self.cls_logits = nn.Conv2d(in_channels, num_anchors, 1)
        self.bbox_pred = nn.Conv2d(in_channels, num_anchors * 4, 1)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.normal_(m.weight, std=0.01)
                nn.init.zeros_(cast(torch.Tensor, m.bias))  # every Conv2d here has a bias

    def forward(self, feats: list[torch.Tensor]) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Levels (1, 256, h, w) -> objectness (1, A, h, w) and deltas (1, 4A, h, w) per level."""
        ts = [self.conv(f) for f in feats]
        return [self.cls_logits(t) for t in ts], [self.bbox_pred(t) for t in ts]


class RegionProposalNetwork(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.head = RPNHead()
        self.pre_nms_top_n = RPN_PRE_NMS_TOP_N
        self.post_nms_top_n = RPN_POST_NMS_TOP_N
        self.nms_thresh = RPN_NMS_THRESH

    def forward(self, feats: list[torch.Tensor], padded_size: tuple[int, int],
                image_size: tuple[int, int]) -> torch.Tensor:
        """FPN levels of one image -> (P, 4) proposals xyxy in the resized image, P <= post_nms_top_n."""
        objectness, deltas = self.head(feats)
        A = objectness[0].shape[1]
        anchors = grid_anchors([tuple(o.shape[-2:]) for o in objectness], padded_size)
        # (1, A, h, w) -> (h * w * A,) and (1, 4A, h, w) -> (h * w * A, 4): the anchors' order
        scores = [o[0].permute(1, 2, 0).reshape(-1) for o in objectness]
        deltas = [d[0].view(A, 4, *d.shape[-2:]).permute(2, 3, 0, 1).reshape(-1, 4) for d in deltas]
        # the top pre_nms_top_n anchors of each level, then NMS within each level
        keep_s, keep_d, keep_a, keep_l = [], [], [], []
        for level, (s, d, a) in enumerate(zip(scores, deltas, anchors)):
            top = s.topk(min(self.pre_nms_top_n, s.numel())).indices
            keep_s.append(s[top])
            keep_d.append(d[top])
            keep_a.append(a[top])
            keep_l.append(torch.full((top.numel(),), level, dtype=torch.int64))
        probs, levels = torch.sigmoid(torch.cat(keep_s)), torch.cat(keep_l)
        boxes = clip_boxes(decode_boxes(torch.cat(keep_d), torch.cat(keep_a), RPN_BOX_WEIGHTS)[:, 0], image_size)
        keep = remove_small_boxes(boxes, RPN_MIN_SIZE)
        boxes, probs, levels = boxes[keep], probs[keep], levels[keep]
        keep = batched_nms(boxes, probs, levels, self.nms_thresh)[: self.post_nms_top_n]
        return boxes[keep]


# --------------------------------------------------------------------------------------------
# RoI heads
# --------------------------------------------------------------------------------------------


class TwoMLPHead(nn.Module):
    def __init__(self, in_channels: int = 256 * BOX_POOL_SIZE ** 2, representation: int = 1024) -> None:
        super().__init__()
        self.fc6 = nn.Linear(in_channels, representation)
        self.fc7 = nn.Linear(representation, representation)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(K, 256, 7, 7) -> (K, 1024)."""
        return F.relu(self.fc7(F.relu(self.fc6(x.flatten(start_dim=1)))))


class FastRCNNPredictor(nn.Module):
    def __init__(self, in_channels: int = 1024, num_classes: int = NUM_CLASSES) -> None:
        super().__init__()
        self.cls_score = nn.Linear(in_channels, num_classes)
        self.bbox_pred = nn.Linear(in_channels, num_classes * 4)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(K, 1024) -> class logits (K, classes), per-class deltas (K, 4 * classes)."""
        return self.cls_score(x), self.bbox_pred(x)


class MaskRCNNHeads(nn.Sequential):
    """``roi_heads.mask_head``: four (3x3 conv 256 + ReLU) blocks, named ``{0..3}.0``."""

    def __init__(self, in_channels: int = 256, layers: Sequence[int] = (256, 256, 256, 256)) -> None:
        blocks = []
        for c in layers:
            blocks.append(nn.Sequential(nn.Conv2d(in_channels, c, 3, padding=1), nn.ReLU(inplace=True)))
            in_channels = c
        super().__init__(*blocks)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
                nn.init.zeros_(cast(torch.Tensor, m.bias))  # every Conv2d here has a bias


class MaskRCNNPredictor(nn.Sequential):
    """``roi_heads.mask_predictor``: 2x upsampling transposed conv + ReLU, 1x1 per-class logits."""

    def __init__(self, in_channels: int = 256, dim_reduced: int = 256, num_classes: int = NUM_CLASSES) -> None:
        super().__init__(OrderedDict([
            ("conv5_mask", nn.ConvTranspose2d(in_channels, dim_reduced, 2, 2, 0)),
            ("relu", nn.ReLU(inplace=True)),
            ("mask_fcn_logits", nn.Conv2d(dim_reduced, num_classes, 1, 1, 0)),
        ]))
        for name, param in self.named_parameters():
            if "weight" in name:
                nn.init.kaiming_normal_(param, mode="fan_out", nonlinearity="relu")


class RoIHeads(nn.Module):
    def __init__(self, num_classes: int = NUM_CLASSES) -> None:
        super().__init__()
        self.box_head = TwoMLPHead()
        self.box_predictor = FastRCNNPredictor(1024, num_classes)
        self.mask_head = MaskRCNNHeads()
        self.mask_predictor = MaskRCNNPredictor(256, 256, num_classes)
        self.score_thresh = BOX_SCORE_THRESH
        self.nms_thresh = BOX_NMS_THRESH
        self.detections_per_img = DETECTIONS_PER_IMG

    def detect(self, feats: list[torch.Tensor], proposals: torch.Tensor,
               image_size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Proposals (P, 4) -> boxes (N, 4) xyxy in the resized image, scores (N,), labels (N,) int64.

        Every (proposal, foreground class) pair with softmax score > score_thresh is a candidate
        box (the class's regression); candidates are NMS-ed per class and the best
        detections_per_img kept, by decreasing score.
        """
        if proposals.shape[0] == 0:
            return proposals.new_zeros((0, 4)), proposals.new_zeros((0,)), torch.zeros(0, dtype=torch.int64)
        x = self.box_head(multiscale_roi_align(feats, proposals, image_size, BOX_POOL_SIZE))
        class_logits, box_regression = self.box_predictor(x)
        num_classes = class_logits.shape[-1]
        boxes = clip_boxes(decode_boxes(box_regression, proposals, BOX_WEIGHTS), image_size)  # (P, classes, 4)
        scores = F.softmax(class_logits, -1)
        labels = torch.arange(num_classes).view(1, -1).expand_as(scores)
        boxes, scores, labels = boxes[:, 1:].reshape(-1, 4), scores[:, 1:].reshape(-1), labels[:, 1:].reshape(-1)
        keep = torch.where(scores > self.score_thresh)[0]
        boxes, scores, labels = boxes[keep], scores[keep], labels[keep]
        keep = remove_small_boxes(boxes, BOX_MIN_SIZE)
        boxes, scores, labels = boxes[keep], scores[keep], labels[keep]
        keep = batched_nms(boxes, scores, labels, self.nms_thresh)[: self.detections_per_img]
        return boxes[keep], scores[keep], labels[keep]

    def mask_probs(self, feats: list[torch.Tensor], boxes: torch.Tensor, labels: torch.Tensor,
                   image_size: tuple[int, int]) -> torch.Tensor:
        """Boxes (N, 4) in the resized image and their labels (N,) -> (N, 28, 28) sigmoid masks of those classes."""
        if boxes.shape[0] == 0:
            return boxes.new_zeros((0, 2 * MASK_POOL_SIZE, 2 * MASK_POOL_SIZE))
        logits = self.mask_predictor(self.mask_head(multiscale_roi_align(feats, boxes, image_size, MASK_POOL_SIZE)))
        return logits[torch.arange(boxes.shape[0]), labels].sigmoid()


# --------------------------------------------------------------------------------------------
# the model
# --------------------------------------------------------------------------------------------


class MaskRCNN(nn.Module):
    """Mask R-CNN ResNet-50-FPN with torchvision's parameter names; one image per call."""

    def __init__(self, num_classes: int = NUM_CLASSES, min_size: int = MIN_SIZE, max_size: int = MAX_SIZE,
                 bn_eps: float = BN_EPS_COCO) -> None:
        super().__init__()
        self.min_size = min_size
        self.max_size = max_size
        self.backbone = Backbone(bn_eps)
        self.rpn = RegionProposalNetwork()
        self.roi_heads = RoIHeads(num_classes)

    def transform(self, image: torch.Tensor) -> tuple[torch.Tensor, tuple[int, int]]:
        """(3, H, W) in [0, 1] -> normalised, resized, zero-padded (1, 3, Hp, Wp); and the resized (h, w).

        Resize: scale = min(min_size / short side, max_size / long side), bilinear, output side
        floor(side * scale); padding to multiples of 32 (bottom / right).
        """
        mean = torch.as_tensor(IMAGENET_MEAN, dtype=image.dtype)[:, None, None]
        std = torch.as_tensor(IMAGENET_STD, dtype=image.dtype)[:, None, None]
        x = (image - mean) / std
        shape = torch.tensor(x.shape[-2:])
        lo, hi = torch.min(shape).to(torch.float32), torch.max(shape).to(torch.float32)
        scale = torch.min(float(self.min_size) / lo, float(self.max_size) / hi).item()
        x = F.interpolate(x[None], scale_factor=scale, mode="bilinear", recompute_scale_factor=True,
                          align_corners=False)
        h, w = x.shape[-2:]
        hp, wp = (int(math.ceil(s / SIZE_DIVISIBLE) * SIZE_DIVISIBLE) for s in (h, w))
        return F.pad(x, (0, wp - w, 0, hp - h)), (h, w)

    def forward(self, image: torch.Tensor, classes: Sequence[int] | None = None,
                min_score: float = 0.0) -> dict[str, torch.Tensor]:
        """Detect and segment the instances in one image.

        Args:
            image: float (3, H, W) RGB in [0, 1].
            classes, min_score: optional filter applied to the detections before the mask head
                (saves its cost); the defaults keep torchvision's output.

        Returns:
            dict of boxes (N, 4) float xyxy px of the input image, labels (N,) int64 (COCO 91-index),
            scores (N,), masks (N, H, W) float probabilities; by decreasing score, N <= 100.
        """
        if image.dim() != 3 or image.shape[0] != 3 or not image.is_floating_point():
            raise ValueError(f"image must be float (3, H, W), got {image.dtype} {tuple(image.shape)}")
        H, W = image.shape[-2:]
        with torch.no_grad():
            x, size = self.transform(image)
            feats = self.backbone(x)
            proposals = self.rpn(feats, tuple(x.shape[-2:]), size)
            boxes, scores, labels = self.roi_heads.detect(feats[:4], proposals, size)
            keep = scores >= min_score
            if classes is not None:
                keep &= torch.isin(labels, torch.as_tensor(list(classes), dtype=torch.int64))
            boxes, scores, labels = boxes[keep], scores[keep], labels[keep]
            masks = self.roi_heads.mask_probs(feats[:4], boxes, labels, size)
            ratio_h = torch.tensor(H, dtype=torch.float32) / torch.tensor(size[0], dtype=torch.float32)
            ratio_w = torch.tensor(W, dtype=torch.float32) / torch.tensor(size[1], dtype=torch.float32)
            boxes = boxes * torch.stack((ratio_w, ratio_h, ratio_w, ratio_h))
            masks = paste_masks_in_image(masks, boxes, (H, W))
        return {"boxes": boxes, "labels": labels, "scores": scores, "masks": masks}


def build_maskrcnn(num_classes: int = NUM_CLASSES, min_size: int = MIN_SIZE) -> MaskRCNN:
    """A randomly initialised model in eval mode (deterministic under ``torch.manual_seed``)."""
    return MaskRCNN(num_classes=num_classes, min_size=min_size).eval()


# --------------------------------------------------------------------------------------------
# loading / inference
# --------------------------------------------------------------------------------------------

_LEGACY_SUFFIX = {"weight", "bias"}


def upgrade_state_dict(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Rename pre-0.13 torchvision keys to the current layout; drop ``num_batches_tracked``.

    ``backbone.fpn.{inner,layer}_blocks.{i}.{w,b}`` -> ``....{i}.0.{w,b}``,
    ``rpn.head.conv.{w,b}`` -> ``rpn.head.conv.0.0.{w,b}``,
    ``roi_heads.mask_head.mask_fcn{k}.{w,b}`` -> ``roi_heads.mask_head.{k-1}.0.{w,b}``.
    """
    out = {}
    for key, v in state.items():
        parts = key.split(".")
        if parts[-1] == "num_batches_tracked":
            continue
        if parts[-1] in _LEGACY_SUFFIX:
            if parts[:2] == ["backbone", "fpn"] and len(parts) == 5 and parts[2] in ("inner_blocks", "layer_blocks"):
                key = ".".join(parts[:4] + ["0", parts[4]])
            elif parts[:-1] == ["rpn", "head", "conv"]:
                key = f"rpn.head.conv.0.0.{parts[-1]}"
            elif parts[:2] == ["roi_heads", "mask_head"] and len(parts) == 4 and parts[2].startswith("mask_fcn"):
                key = f"roi_heads.mask_head.{int(parts[2][len('mask_fcn'):]) - 1}.0.{parts[-1]}"
        out[key] = v
    return out


def load_maskrcnn(state: Mapping[str, torch.Tensor], source: str = "state dict", min_size: int = MIN_SIZE) -> MaskRCNN:
    """Build torchvision's ``maskrcnn_resnet50_fpn`` from its state dict (eval mode); legacy key
    names are upgraded (:func:`upgrade_state_dict`), any other key or shape mismatch raises
    ``ValueError`` naming the first offending key and ``source``."""
    model = MaskRCNN(min_size=min_size)
    load_strict(model, upgrade_state_dict(dict(state)), source)
    model.eval()
    return model


def semantic_static_mask(model: MaskRCNN, image: np.ndarray, classes: Sequence[int] = DYNAMIC_COCO_CLASSES,
                         score_thresh: float = 0.5, mask_thresh: float = 0.5, dilate: int = 5) -> np.ndarray:
    """Static mask of one frame from Mask R-CNN instances of dynamic classes.

    Args:
        model: a :class:`MaskRCNN`.
        image: uint8 (H, W, 3) RGB.
        classes: COCO 91-index labels counted as dynamic (default :data:`DYNAMIC_COCO_CLASSES`).
        score_thresh: detections scoring below are ignored.
        mask_thresh: a pixel belongs to an instance where its mask probability is >= this.
        dilate: the dynamic region is dilated with a ``dilate`` x ``dilate`` square (0: none).

    Returns:
        uint8 (H, W): 1 = static, 0 = covered by a detected instance of a dynamic class.
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"image must be uint8 (H, W, 3), got {img.dtype} {img.shape}")
    h, w = img.shape[:2]
    with torch.inference_mode():
        x = torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1).float().div_(255.0)
        det = model(x, classes=classes, min_score=score_thresh)
        wanted = torch.as_tensor(list(classes), dtype=torch.int64)
        keep = (det["scores"] >= score_thresh) & torch.isin(det["labels"], wanted)
        masks = det["masks"][keep]
        dynamic = (masks >= mask_thresh).any(dim=0).numpy() if masks.shape[0] else np.zeros((h, w), bool)
    m = dynamic.astype(np.uint8)
    if dilate > 0:
        m = cv2.dilate(m, np.ones((dilate, dilate), np.uint8))
    return (1 - m).astype(np.uint8)
