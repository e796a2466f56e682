"""Mask R-CNN semantic mask backend: architecture, weight loading, RoIAlign / NMS, masks, pipeline.

No real checkpoint is available offline: the tests use randomly initialised models
(torch.manual_seed(0)) saved and loaded back, and references written from torchvision's
CPU-kernel semantics. Images are small and min_size 192 keeps every forward well under a second.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import by_stage, cli, cli_json
from safetensors.torch import save_file

from gcvd_flow.io.weights import open_model
from gcvd_flow.stages.models.maskrcnn import (
    DYNAMIC_COCO_CLASSES,
    MaskRCNN,
    batched_nms,
    build_maskrcnn,
    cell_anchors,
    nms,
    roi_align,
    semantic_static_mask,
)

TORCHVISION_PARAMS = 44_401_393  # sum(p.numel() for p in maskrcnn_resnet50_fpn().parameters())
TORCHVISION_TENSORS = 307  # its state dict: 265 backbone.body (frozen BN: 4 buffers each), 16 fpn, 6 rpn, 20 roi_heads


@pytest.fixture(scope="module")
def model() -> MaskRCNN:
    torch.manual_seed(0)
    m = build_maskrcnn(min_size=192)
    m.roi_heads.detections_per_img = 10  # bounds the mask head's cost in these tests
    return m


@pytest.fixture(scope="module")
def weights(model, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("maskrcnn") / "maskrcnn.safetensors"
    save_file({k: v.detach().clone().contiguous() for k, v in model.state_dict().items()}, str(path))
    return path


def _image(h: int, w: int, seed: int = 0) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    img[h // 4:h // 2, w // 4:w // 2] = (200, 40, 40)  # some structure
    return torch.from_numpy(img).permute(2, 0, 1).float() / 255.0


# ------------------------------------------------------------------------------------------
# architecture and weights
# ------------------------------------------------------------------------------------------


def test_parameter_count_and_torchvision_key_names(model):
    assert sum(p.numel() for p in model.parameters()) == TORCHVISION_PARAMS
    state = model.state_dict()
    assert len(state) == TORCHVISION_TENSORS
    for k in ("backbone.body.conv1.weight", "backbone.body.bn1.running_var", "backbone.body.layer1.0.conv1.weight",
              "backbone.body.layer1.0.downsample.1.running_mean", "backbone.body.layer4.2.bn3.bias",
              "backbone.fpn.inner_blocks.0.0.weight", "backbone.fpn.layer_blocks.3.0.bias",
              "rpn.head.conv.0.0.weight", "rpn.head.cls_logits.weight", "rpn.head.bbox_pred.bias",
              "roi_heads.box_head.fc6.weight", "roi_heads.box_head.fc7.bias",
              "roi_heads.box_predictor.cls_score.weight", "roi_heads.box_predictor.bbox_pred.weight",
              "roi_heads.mask_head.0.0.weight", "roi_heads.mask_head.3.0.bias",
              "roi_heads.mask_predictor.conv5_mask.weight", "roi_heads.mask_predictor.mask_fcn_logits.weight"):
        assert k in state, k
    assert not any("num_batches_tracked" in k for k in state)
    assert not any(".bn" in name or "downsample.1" in name for name, _ in model.named_parameters())  # frozen BN
    assert tuple(state["roi_heads.box_head.fc6.weight"].shape) == (1024, 256 * 7 * 7)
    assert tuple(state["roi_heads.box_predictor.bbox_pred.weight"].shape) == (91 * 4, 1024)
    assert tuple(state["rpn.head.cls_logits.weight"].shape) == (3, 256, 1, 1)
    assert tuple(state["roi_heads.mask_predictor.conv5_mask.weight"].shape) == (256, 256, 2, 2)


def test_build_is_deterministic_under_seed(model):
    torch.manual_seed(0)
    other = build_maskrcnn(min_size=192)
    a, b = model.state_dict(), other.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_safetensors_roundtrip_gives_identical_outputs(model, weights):
    loaded = open_model("maskrcnn", weights, min_size=192)
    assert not loaded.training and loaded.min_size == 192
    loaded.roi_heads.detections_per_img = model.roi_heads.detections_per_img
    img = _image(192, 256)
    a, b = model(img), loaded(img)
    for k in ("boxes", "labels", "scores", "masks"):
        assert torch.equal(a[k], b[k]), k


def test_legacy_torchvision_key_names_load(model, tmp_path):
    """Checkpoints from torchvision < 0.13 (the released COCO file among them) use older names."""
    legacy = {}
    for k, v in model.state_dict().items():
        k = k.replace("rpn.head.conv.0.0.", "rpn.head.conv.")
        for block in ("inner_blocks", "layer_blocks"):
            for i in range(4):
                k = k.replace(f"backbone.fpn.{block}.{i}.0.", f"backbone.fpn.{block}.{i}.")
        for i in range(4):
            k = k.replace(f"roi_heads.mask_head.{i}.0.", f"roi_heads.mask_head.mask_fcn{i + 1}.")
        legacy[k] = v
    assert "rpn.head.conv.weight" in legacy and "roi_heads.mask_head.mask_fcn4.bias" in legacy
    assert "backbone.fpn.inner_blocks.2.weight" in legacy
    legacy["backbone.body.bn1.num_batches_tracked"] = torch.tensor(0)
    path = tmp_path / "maskrcnn_legacy.pth"
    torch.save(legacy, str(path))
    loaded = open_model("maskrcnn", path)
    a, b = model.state_dict(), loaded.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_renamed_key_is_an_error_naming_it(model, tmp_path):
    state = {k: v.detach().clone().contiguous() for k, v in model.state_dict().items()}
    state["roi_heads.box_head.fc_6.weight"] = state.pop("roi_heads.box_head.fc6.weight")
    path = tmp_path / "bad.safetensors"
    save_file(state, str(path))
    with pytest.raises(ValueError, match=r"roi_heads\.box_head\.fc6\.weight") as err:
        open_model("maskrcnn", path)
    assert str(path) in str(err.value)


# ------------------------------------------------------------------------------------------
# RoIAlign, NMS, anchors, transform
# ------------------------------------------------------------------------------------------


def _ref_roi_align(feat: np.ndarray, rois: np.ndarray, ph: int, pw: int, scale: float, sr: int,
                   aligned: bool) -> np.ndarray:
    """torchvision's roi_align CPU kernel, one sample at a time, in float64."""
    _, C, H, W = feat.shape

    def bilinear(f: np.ndarray, y: float, x: float) -> np.ndarray:
        if y < -1.0 or y > H or x < -1.0 or x > W:
            return np.zeros(C)
        y, x = max(y, 0.0), max(x, 0.0)
        y_lo, x_lo = int(y), int(x)
        if y_lo >= H - 1:
            y_hi = y_lo = H - 1
            y = float(y_lo)
        else:
            y_hi = y_lo + 1
        if x_lo >= W - 1:
            x_hi = x_lo = W - 1
            x = float(x_lo)
        else:
            x_hi = x_lo + 1
        ly, lx = y - y_lo, x - x_lo
        hy, hx = 1 - ly, 1 - lx
        return (hy * hx * f[:, y_lo, x_lo] + hy * lx * f[:, y_lo, x_hi]
                + ly * hx * f[:, y_hi, x_lo] + ly * lx * f[:, y_hi, x_hi])

    out = np.zeros((len(rois), C, ph, pw))
    off = 0.5 if aligned else 0.0
    for r, (b, x1, y1, x2, y2) in enumerate(rois):
        f = feat[int(b)]
        sx, sy = x1 * scale - off, y1 * scale - off
        rw, rh = x2 * scale - off - sx, y2 * scale - off - sy
        if not aligned:
            rw, rh = max(rw, 1.0), max(rh, 1.0)
        bh, bw = rh / ph, rw / pw
        gh = sr if sr > 0 else math.ceil(rh / ph)
        gw = sr if sr > 0 else math.ceil(rw / pw)
        for i in range(ph):
            for j in range(pw):
                acc = np.zeros(C)
                for iy in range(gh):
                    for ix in range(gw):
                        acc += bilinear(f, sy + i * bh + (iy + 0.5) * bh / gh, sx + j * bw + (ix + 0.5) * bw / gw)
                out[r, :, i, j] = acc / max(gh * gw, 1)
    return out


@pytest.fixture(scope="module")
def roi_case() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    feat = rng.normal(size=(2, 3, 11, 13)).astype(np.float32)
    rois = []
    for k in range(24):
        x1, y1 = rng.uniform(-30, 60), rng.uniform(-30, 50)
        rois.append([k % 2, x1, y1, x1 + rng.uniform(0, 50), y1 + rng.uniform(0, 50)])
    # the whole map, fully outside, degenerate (a point), straddling the bottom-right corner
    rois += [[0, 0, 0, 52, 44], [1, -100, -100, -90, -90], [0, 40, 30, 40, 30], [1, 51.9, 43.9, 60, 60]]
    return feat, np.asarray(rois, np.float32)


@pytest.mark.parametrize("scale", [0.25, 0.5])
@pytest.mark.parametrize("sampling_ratio", [2, 1, 0])
@pytest.mark.parametrize("aligned", [False, True])
def test_roi_align_matches_kernel_reference(roi_case, scale, sampling_ratio, aligned):
    feat, rois = roi_case
    pooled = (7, 7) if sampling_ratio == 2 else (3, 5)
    got = roi_align(torch.from_numpy(feat), torch.from_numpy(rois), pooled, scale, sampling_ratio, aligned)
    assert got.shape == (len(rois), 3, *pooled) and got.dtype == torch.float32
    ref = _ref_roi_align(feat.astype(np.float64), rois.astype(np.float64), *pooled, scale, sampling_ratio, aligned)
    np.testing.assert_allclose(got.numpy(), ref, atol=5e-5, rtol=0)
    assert np.abs(ref).max() > 0.1  # the case is not trivially zero


def test_roi_align_small_chunks_and_empty(roi_case):
    feat, rois = roi_case
    f, r = torch.from_numpy(feat), torch.from_numpy(rois)
    assert torch.allclose(roi_align(f, r, 7, 0.25, 2, max_elements=1), roi_align(f, r, 7, 0.25, 2), atol=1e-6)
    assert roi_align(f, r[:0], 7, 0.25, 2).shape == (0, 3, 7, 7)


def _ref_nms(boxes: np.ndarray, scores: np.ndarray, thr: float) -> list[int]:
    """Greedy NMS, pair by pair: by decreasing score (ties: lower index first)."""
    order = sorted(range(len(boxes)), key=lambda i: (-scores[i], i))
    suppressed, keep = set(), []
    for a, i in enumerate(order):
        if i in suppressed:
            continue
        keep.append(i)
        for j in order[a + 1:]:
            w = max(np.float32(0), min(boxes[i, 2], boxes[j, 2]) - max(boxes[i, 0], boxes[j, 0]))
            h = max(np.float32(0), min(boxes[i, 3], boxes[j, 3]) - max(boxes[i, 1], boxes[j, 1]))
            inter = w * h
            ai = (boxes[i, 2] - boxes[i, 0]) * (boxes[i, 3] - boxes[i, 1])
            aj = (boxes[j, 2] - boxes[j, 0]) * (boxes[j, 3] - boxes[j, 1])
            union = ai + aj - inter
            if union > 0 and float(inter / union) > thr:
                suppressed.add(j)
    return keep


@pytest.mark.parametrize("seed", range(6))
def test_nms_matches_greedy_reference(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 200))
    xy = rng.uniform(0, 100, (n, 2))
    boxes = np.concatenate([xy, xy + rng.uniform(0, 40, (n, 2))], 1).astype(np.float32)
    if seed % 2:
        boxes[n // 2:] = boxes[:n - n // 2]  # exact duplicates
    scores = (rng.integers(0, 20, n) / 20.0).astype(np.float32)  # many ties
    classes = rng.integers(0, 4, n)
    for thr in (0.3, 0.5, 0.7):
        assert nms(torch.from_numpy(boxes), torch.from_numpy(scores), thr).tolist() == _ref_nms(boxes, scores, thr)
        per_class = []
        for c in range(4):
            idx = np.flatnonzero(classes == c)
            per_class += [int(idx[k]) for k in _ref_nms(boxes[idx], scores[idx], thr)]
        got = batched_nms(torch.from_numpy(boxes), torch.from_numpy(scores), torch.from_numpy(classes), thr)
        assert got.tolist() == sorted(per_class, key=lambda i: (-scores[i], i))
    assert nms(torch.zeros(0, 4), torch.zeros(0), 0.5).tolist() == []


def test_anchors_and_transform_sizes():
    assert cell_anchors(32).tolist() == [[-23, -11, 23, 11], [-16, -16, 16, 16], [-11, -23, 11, 23]]
    m = MaskRCNN(min_size=800)
    x, size = m.transform(torch.rand(3, 100, 1000))  # the long side limits: 1333 / 1000
    assert size == (133, 1333) and tuple(x.shape) == (1, 3, 160, 1344)
    x, size = m.transform(torch.rand(3, 300, 400))
    assert size == (800, 1066) and tuple(x.shape) == (1, 3, 800, 1088)
    assert float(x[0, :, :, 1066:].abs().max()) == 0.0  # zero padding after normalisation


# ------------------------------------------------------------------------------------------
# forward, semantic masks
# ------------------------------------------------------------------------------------------


def test_forward_shapes_dtypes_and_determinism(model):
    img = _image(192, 256)
    a, b = model(img), model(img)
    n = a["boxes"].shape[0]
    assert 0 < n <= 10
    assert a["boxes"].shape == (n, 4) and a["boxes"].dtype == torch.float32
    assert a["labels"].shape == (n,) and a["labels"].dtype == torch.int64
    assert a["scores"].shape == (n,) and a["scores"].dtype == torch.float32
    assert a["masks"].shape == (n, 192, 256) and a["masks"].dtype == torch.float32
    boxes = a["boxes"]
    assert (boxes[:, 0] >= 0).all() and (boxes[:, 2] <= 256).all() and (boxes[:, 3] <= 192).all()
    assert (boxes[:, 2] >= boxes[:, 0]).all() and (boxes[:, 3] >= boxes[:, 1]).all()
    assert (a["scores"] > 0.05).all() and (a["scores"][:-1] >= a["scores"][1:]).all()
    assert ((a["labels"] >= 1) & (a["labels"] <= 90)).all()
    assert a["masks"].min() >= 0 and a["masks"].max() <= 1
    for k in a:
        assert torch.equal(a[k], b[k]), k
    # the optional filter only drops detections before the mask head
    keep = a["labels"] == a["labels"][0]
    c = model(img, classes=[int(a["labels"][0])], min_score=0.0)
    assert torch.equal(c["labels"], a["labels"][keep]) and torch.allclose(c["masks"], a["masks"][keep], atol=1e-5)


class _FixedDetections(torch.nn.Module):
    """Stands in for the network: three instances, whatever the filter asked for."""

    def forward(self, image, classes=None, min_score=0.0):
        h, w = image.shape[-2:]
        masks = torch.zeros(3, h, w)
        masks[0, 10:30, 10:40] = 0.9  # person, confident
        masks[0, 14:16, 14:16] = 0.3  # ... with a hole below the mask threshold
        masks[1, 40:60, 10:40] = 0.9  # dining table (67): not a moving class
        masks[2, 10:30, 60:90] = 0.9  # car, low score
        return {"boxes": torch.tensor([[10, 10, 40, 30], [10, 40, 40, 60], [60, 10, 90, 30]], dtype=torch.float32),
                "labels": torch.tensor([1, 67, 3]), "scores": torch.tensor([0.9, 0.95, 0.3]), "masks": masks}


def test_semantic_mask_filters_classes_and_scores():
    img = np.zeros((70, 100, 3), np.uint8)
    m = semantic_static_mask(_FixedDetections(), img, dilate=0)
    assert m.dtype == np.uint8 and m.shape == (70, 100)
    expect = np.ones((70, 100), np.uint8)
    expect[10:30, 10:40] = 0
    expect[14:16, 14:16] = 1
    np.testing.assert_array_equal(m, expect)
    # a lower score threshold admits the car; the dilation grows regions by dilate // 2 px
    m = semantic_static_mask(_FixedDetections(), img, score_thresh=0.2, dilate=5)
    assert (m[8:32, 8:42] == 0).all() and (m[8:32, 58:92] == 0).all()
    assert m[7, 20] == 1 and m[20, 7] == 1 and m[33, 20] == 1 and (m[40:, :] == 1).all()
    # only the named classes count
    m = semantic_static_mask(_FixedDetections(), img, classes=(67,), dilate=0)
    assert (m[40:60, 10:40] == 0).all() and m.sum() == 70 * 100 - 20 * 30
    with pytest.raises(ValueError, match="uint8"):
        semantic_static_mask(_FixedDetections(), img.astype(np.float32))


def test_dynamic_classes_are_torchvision_coco_labels():
    # person .. boat are 1 .. 9; bird .. giraffe 16 .. 25 (12 is an unused "N/A" slot)
    assert DYNAMIC_COCO_CLASSES == (1, 2, 3, 4, 5, 6, 7, 8, 9, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25)


@pytest.mark.parametrize("label, masked", [(1, True), (62, False)])
def test_semantic_mask_with_rigged_network(monkeypatch, label, masked):
    """A real forward (backbone, RPN, mask head, paste) with the box stage and the mask
    predictor rigged: one detection of ``label`` whose mask is ~1 over its box."""
    torch.manual_seed(0)
    model = build_maskrcnn(min_size=192)
    with torch.no_grad():
        model.roi_heads.mask_predictor.mask_fcn_logits.weight.zero_()
        model.roi_heads.mask_predictor.mask_fcn_logits.bias.fill_(10.0)

    def detect(feats, proposals, size):
        assert size == (192, 256)  # the 96x128 image is resized x2
        return torch.tensor([[40.0, 60.0, 120.0, 140.0]]), torch.tensor([0.99]), torch.tensor([label])

    monkeypatch.setattr(model.roi_heads, "detect", detect)
    img = (_image(96, 128).permute(1, 2, 0).numpy() * 255).astype(np.uint8)
    m = semantic_static_mask(model, img, dilate=3)  # the box is (20, 30, 60, 70) in the image
    assert m.shape == (96, 128)
    assert (m[75:] == 1).all() and (m[:, 66:] == 1).all() and (m[:26] == 1).all() and (m[:, :16] == 1).all()
    if masked:
        assert (m[32:68, 22:58] == 0).all()
    else:
        assert (m == 1).all()


# ------------------------------------------------------------------------------------------
# pipeline
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_clip(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("clip") / "orbit"
    cli("synth", str(out), "--frames", "4", "--trajectory", "orbit", "--size", "64x48", check=True)
    return out


def test_pipeline_maskrcnn_without_weights_is_a_one_line_error(tiny_clip, tmp_path):
    p = cli("run", str(tiny_clip), "--out", str(tmp_path / "o"), "--cache", str(tmp_path / "c"),
            "--until", "masks", "--set", "masks.backend=maskrcnn")
    assert p.returncode == 2, p.stderr
    lines = [l for l in p.stderr.strip().splitlines() if not l.startswith("camera:")]
    assert len(lines) == 1 and "masks.weights" in lines[0], p.stderr
    assert "Traceback" not in p.stderr


def _masks_of_run(out: Path, cache: Path) -> list[np.ndarray]:
    from gcvd_flow.engine.artifacts import load_manifest, load_value
    from gcvd_flow.engine.store import Store

    store = Store(cache)
    run = json.loads((out / "run.json").read_text())
    items = load_manifest(store, run["stages"]["masks"]["output"])["items"]
    return [np.asarray(load_value(store, d)["static"]) for d in items]


def test_pipeline_masks_stage_with_maskrcnn_weights(model, tiny_clip, tmp_path):
    """Random weights rigged to see background only: the semantic mask is all static, so
    maskrcnn gives ones and motion+maskrcnn equals motion."""
    state = {k: v.detach().clone().contiguous() for k, v in model.state_dict().items()}
    state["roi_heads.box_predictor.cls_score.weight"].zero_()
    state["roi_heads.box_predictor.cls_score.bias"].zero_()
    state["roi_heads.box_predictor.cls_score.bias"][0] = 20.0
    w = tmp_path / "maskrcnn.safetensors"
    save_file(state, str(w))
    cache = tmp_path / "cache"
    base = ["run", str(tiny_clip), "--cache", str(cache), "--until", "masks", "--set", "ingest.long_side=64",
            "--set", f"masks.weights={json.dumps(str(w))}", "--set", "masks.min_size=64"]
    masks = {}
    for backend in ("maskrcnn", "motion+maskrcnn", "motion"):
        out = tmp_path / backend.replace("+", "_")
        rep = by_stage(cli_json(*base, "--out", str(out), "--set", f"masks.backend={backend}"))
        assert rep["masks"]["executed"] == 4
        masks[backend] = _masks_of_run(out, cache)
    for m in masks["maskrcnn"]:
        assert m.dtype == np.uint8 and m.shape == (48, 64) and (m == 1).all()
    for a, b in zip(masks["motion+maskrcnn"], masks["motion"]):
        np.testing.assert_array_equal(a, b)
