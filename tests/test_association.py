"""Association: descriptor, candidates, keyframe-pair flow, verification, graph, ResNet-18."""

from __future__ import annotations

import json
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import torch
from geometry_ref import rigid_flow

from gcvd_flow.evaluate.synth import render_clip
from gcvd_flow.io.weights import open_model
from gcvd_flow.stages.frontend.flow import compute_pair_flow
from gcvd_flow.stages.graph.association import (
    DEFAULT_SIMILARITY_THRESHOLD,
    build_graph,
    candidate_pairs,
    flow_epipolar_agreement,
    global_descriptor,
    keyframe_pair_flow,
    verify_pair,
)
from gcvd_flow.stages.graph.keyframes import keyframe_pair_flows, pair_motion, select_keyframes
from gcvd_flow.stages.models.resnet import ResNet18, resnet_descriptor

SIZE = (160, 120)


def _keyframes(frames: np.ndarray, delta: float = 0.1) -> dict:
    n, h, w = frames.shape[:3]
    motion = [
        pair_motion(compute_pair_flow(frames[i], frames[i + 1], preset="fast")["fwd"], None, None)
        for i in range(n - 1)
    ]
    return select_keyframes(motion, h, w, delta=delta)


@pytest.fixture(scope="module")
def loop_render():
    return render_clip(121, "loop", size=SIZE)


@pytest.fixture(scope="module")
def loop_clip(loop_render):
    # 121 rendered poses with the last == the first; dropping it leaves a loop whose last frame
    # is one step short of the start (a real revisit, not a copy of frame 0).
    return loop_render.frames[:-1], loop_render.K


@pytest.fixture(scope="module")
def rotation_clip():
    return render_clip(60, "rotation", size=SIZE)


def test_descriptor_shape_and_discrimination(loop_clip, rotation_clip) -> None:
    frames, _ = loop_clip
    d0 = global_descriptor(frames[0])
    assert d0.dtype == np.float32 and d0.shape == (312,)
    assert np.linalg.norm(d0) == pytest.approx(1.0, abs=1e-5)
    assert np.array_equal(d0, global_descriptor(frames[0]))
    # Same place (end of loop vs start) is above the default threshold...
    assert float(d0 @ global_descriptor(frames[-1])) > DEFAULT_SIMILARITY_THRESHOLD + 0.1
    # ...opposite ends of a 40 deg pan (no overlap of note) are well below it.
    r = rotation_clip.frames
    assert float(global_descriptor(r[0]) @ global_descriptor(r[-1])) < DEFAULT_SIMILARITY_THRESHOLD - 0.1


def test_candidate_pairs_separation_and_nms() -> None:
    k, d = 30, 16
    rng = np.random.default_rng(0)
    desc = rng.normal(size=(k, d))
    desc[20:23] = desc[2] + 0.01 * rng.normal(size=(3, d))  # revisit: 20..22 look like 2
    desc[5] = desc[9] + 0.01 * rng.normal(size=d)  # similar but only 4 apart: not eligible
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    pairs = candidate_pairs(desc, threshold=0.9, nms=8, min_separation=8)
    assert len(pairs) == 1  # NMS keeps one of (2, 20), (2, 21), (2, 22)
    a, b, s = pairs[0]
    assert a == 2 and b in (20, 21, 22) and s > 0.99
    assert len(candidate_pairs(desc, threshold=0.9, nms=1, min_separation=8)) == 3
    assert candidate_pairs(desc, threshold=0.9, nms=8, min_separation=25) == []
    # per_keyframe: each of 20..22 also proposes its best partner (2): the whole revisit
    more = candidate_pairs(desc, threshold=0.9, nms=8, min_separation=8, per_keyframe=1)
    assert sorted((a, b) for a, b, _ in more) == [(2, 20), (2, 21), (2, 22)]
    assert len(candidate_pairs(desc, threshold=0.9, nms=8, min_separation=8, per_keyframe=1, max_candidates=2)) == 2


def test_keyframe_pair_flow_prewarp_matches_gt(rotation_clip) -> None:
    c = rotation_clip
    a, b = 10, 50  # ~77 px apart: plain DIS fails here
    out = keyframe_pair_flow(c.frames[a], c.frames[b])
    gt_f = rigid_flow(c.depth[a], c.K, c.poses[a], c.poses[b])
    gt_b = rigid_flow(c.depth[b], c.K, c.poses[b], c.poses[a])
    ef = np.linalg.norm(out["fwd"] - gt_f, axis=-1)[out["fwd_valid"]]
    eb = np.linalg.norm(out["bwd"] - gt_b, axis=-1)[out["bwd_valid"]]
    assert out["fwd_valid"].mean() > 0.4 and out["bwd_valid"].mean() > 0.4
    assert np.median(ef) < 0.3 and np.median(eb) < 0.3
    assert np.mean(ef < 2.0) > 0.95
    assert out["homography"].shape == (3, 3) and out["fwd"].dtype == np.float32
    plain = compute_pair_flow(c.frames[a], c.frames[b], fb_thresh=2.0)
    assert np.median(np.linalg.norm(plain["fwd"] - gt_f, axis=-1)[plain["fwd_valid"]]) > 5.0


def test_loop_closes_end_to_start(loop_clip) -> None:
    frames, K = loop_clip
    sel = _keyframes(frames)
    kfs = sel["indices"]
    assert len(kfs) > 9  # enough keyframes for pairs more than 8 apart
    graph, flows = build_graph(kfs, [frames[i] for i in kfs], K, sel["threshold_px"])
    json.dumps(graph)  # JSON-able
    loops = graph["nonsequential_edges"]
    assert any(e["i"] <= kfs[1] and e["j"] >= kfs[-2] for e in loops), graph
    for e in loops:
        assert e["inlier_ratio"] >= 0.5 and e["consistent_fraction"] >= 0.1
        assert e["n_inliers"] >= 20 and (e["epipolar"] == -1.0 or e["epipolar"] >= 0.5)
        assert (e["i"], e["j"]) in flows
    n = len(kfs)
    assert len(graph["sequential_edges"]) == sum(max(0, n - t) for t in (1, 2, 4, 8))
    assert {e["weight"] for e in graph["sequential_edges"]} == {1.0, 0.5, 0.25, 0.125}
    for m in range(n - 1):
        f = flows[(kfs[m], kfs[m + 1])]
        assert f["fwd"].shape == frames.shape[1:3] + (2,)
    by_pos = keyframe_pair_flows(kfs, [{"i": i, "j": j, **fl} for (i, j), fl in flows.items()])
    assert sorted(by_pos) == [(m, m + 1) for m in range(n - 1)]
    assert np.array_equal(by_pos[(0, 1)]["fwd"], flows[(kfs[0], kfs[1])]["fwd"])
    # Deterministic, also with its SIFT, pair flows and candidate checks run on worker processes
    # (the pipeline passes the engine's ctx.map as call_map): the same graph and flow bits
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("forkserver")) as pool:
        graph2, flows2 = build_graph(kfs, [frames[i] for i in kfs], K, sel["threshold_px"], call_map=pool.map)
    assert json.dumps(graph2) == json.dumps(graph)
    assert sorted(flows2) == sorted(flows)
    for key, fl in flows.items():
        for name, arr in fl.items():
            assert np.array_equal(flows2[key][name], arr), (key, name)


def test_forward_clip_has_no_loop_edge() -> None:
    clip = render_clip(120, "forward", size=SIZE)
    sel = _keyframes(clip.frames, delta=0.03)
    kfs = sel["indices"]
    imgs = [clip.frames[i] for i in kfs]
    graph, _ = build_graph(kfs, imgs, clip.K, sel["threshold_px"], verify="paper")
    assert graph["nonsequential_edges"] == []
    # Make every pair >= 3 keyframes apart a candidate: the paper's verification must reject them
    # all, because such views are >= 3 keyframe thresholds of motion apart (the geometric one
    # accepts what overlaps: these are true views of one scene).
    graph, flows = build_graph(
        kfs, imgs, clip.K, sel["threshold_px"], similarity_threshold=-1.0, nms=1, min_separation=2, verify="paper"
    )
    assert graph["nonsequential_edges"] == []
    assert len(graph["rejected"]) >= 5
    assert all("mean flow" in r["reason"] or "matches" in r["reason"] for r in graph["rejected"])
    assert len(flows) == len(kfs) - 1


def test_verify_pair_accepts_a_near_view(loop_clip) -> None:
    frames, K = loop_clip
    v = verify_pair(frames[0], frames[3], K, keyframe_threshold_px=12.0)
    assert v["accepted"], v["reason"]
    assert v["mean_flow"] < 12.0 and v["inlier_ratio"] > 0.8
    v = verify_pair(frames[0], frames[3], K, keyframe_threshold_px=0.5, mode="paper")
    assert not v["accepted"] and "mean flow" in v["reason"]
    assert verify_pair(frames[0], frames[3], K, keyframe_threshold_px=0.5)["accepted"]


def test_wide_baseline_revisit_closes_the_loop(loop_clip) -> None:
    """A handheld camera returns near, not onto, its start: the clip stops 8 frames short of
    closing its loop, so its last keyframe sees the start with 14 px of mean flow, more than
    the 12 px keyframe threshold. The geometric verification accepts that revisit (and tracks it
    into the graph); the paper's one-keyframe-apart rule rejects it."""
    frames, K = loop_clip
    frames = frames[:-8]
    sel = _keyframes(frames)
    kfs, thr = sel["indices"], sel["threshold_px"]
    imgs = [frames[i] for i in kfs]
    graph, flows = build_graph(kfs, imgs, K, thr, per_keyframe=1)
    closing = [e for e in graph["nonsequential_edges"] if e["i"] <= kfs[1] and e["j"] >= kfs[-2]]
    assert closing, graph["rejected"]
    assert max(e["mean_flow"] for e in closing) > thr  # wider than the paper's rule allows
    assert all((e["i"], e["j"]) in flows for e in closing)
    assert graph["verify"] == "geometric" and graph["candidates"] >= len(graph["nonsequential_edges"])
    paper, _ = build_graph(kfs, imgs, K, thr, per_keyframe=1, verify="paper")
    assert not [e for e in paper["nonsequential_edges"] if e["i"] <= kfs[1] and e["j"] >= kfs[-2]]
    assert any("mean flow" in r["reason"] for r in paper["rejected"])


def test_false_candidates_are_rejected(loop_clip) -> None:
    """A look-alike place (the same room layout with other surfaces: the descriptor finds it
    similar) and a mirrored view are rejected by the geometric verification."""
    frames, K = loop_clip
    other = render_clip(2, "loop", size=SIZE, seed=5).frames[0]
    v = verify_pair(frames[0], other, K, keyframe_threshold_px=12.0)
    assert not v["accepted"] and ("matches" in v["reason"] or "inlier" in v["reason"]), v["reason"]
    v = verify_pair(frames[0], np.ascontiguousarray(frames[20][:, ::-1]), K, keyframe_threshold_px=12.0)
    assert not v["accepted"], v["reason"]


def _essential(T_w_a: np.ndarray, T_w_b: np.ndarray) -> np.ndarray:
    T_b_a = np.linalg.inv(T_w_b) @ T_w_a
    t = T_b_a[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return tx @ T_b_a[:3, :3]


def test_flow_epipolar_agreement(loop_render) -> None:
    """Dense flow that obeys the two views' geometry agrees with their essential matrix; the
    same flow against another pair's geometry does not (what rejects a candidate whose few
    feature matches fit a geometry its dense flow does not)."""
    c = loop_render
    a, b = 0, 12
    fl = rigid_flow(c.depth[a], c.K, c.poses[a], c.poses[b])
    valid = np.isfinite(fl).all(-1)
    fl = np.where(valid[..., None], fl, 0.0)
    right = flow_epipolar_agreement(_essential(c.poses[a], c.poses[b]), c.K, fl, valid)
    wrong = flow_epipolar_agreement(_essential(c.poses[a], c.poses[60]), c.K, fl, valid)
    assert right > 0.99 and wrong < 0.3, (right, wrong)
    assert flow_epipolar_agreement(_essential(c.poses[a], c.poses[b]), c.K, fl, np.zeros_like(valid)) == 0.0


def test_resnet18_roundtrip_safetensors_and_pth(tmp_path: Path, loop_clip) -> None:
    from safetensors.torch import save_file

    torch.manual_seed(0)
    model = ResNet18().eval()
    sd = model.state_dict()
    # torchvision's resnet18 layout: 11,689,512 parameters, 122 state-dict tensors.
    assert sum(p.numel() for p in model.parameters()) == 11_689_512
    assert len(sd) == 122
    for key in ("conv1.weight", "layer2.0.downsample.0.weight", "layer4.1.bn2.running_var", "fc.bias"):
        assert key in sd
    # Make BN statistics non-trivial so a loader that dropped buffers would be caught.
    with torch.no_grad():
        for name, t in sd.items():
            if name.endswith("running_mean"):
                t.copy_(torch.randn_like(t) * 0.1)
            elif name.endswith("running_var"):
                t.copy_(torch.rand_like(t) + 0.5)
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(tmp_path / "r18.safetensors"))
    torch.save({"state_dict": {f"module.{k}": v for k, v in model.state_dict().items()}}, tmp_path / "r18.pth")

    frames, _ = loop_clip
    ref = resnet_descriptor(model, frames[0])
    assert ref.shape == (512,) and ref.dtype == np.float32
    assert np.linalg.norm(ref) == pytest.approx(1.0, abs=1e-5)
    for fname in ("r18.safetensors", "r18.pth"):
        loaded = open_model("resnet18", tmp_path / fname)
        assert not loaded.training
        np.testing.assert_allclose(resnet_descriptor(loaded, frames[0]), ref, atol=1e-6)
    # A mismatched file is rejected (strict loading).
    save_file({"conv1.weight": torch.zeros(64, 3, 7, 7)}, str(tmp_path / "bad.safetensors"))
    with pytest.raises(ValueError, match="bad.safetensors"):
        open_model("resnet18", tmp_path / "bad.safetensors")
