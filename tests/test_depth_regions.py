"""`gcvd-flow eval`'s per-region depth breakdown (gcvd_flow.evaluate.regions): each class is
computed from the frames and the ground truth, and an error put into one region shows up there
and nowhere else."""

from __future__ import annotations

import numpy as np
import pytest

from gcvd_flow.evaluate.regions import RegionBreakdown, depth_edges, format_regions, frame_regions, local_gradient

H, W = 48, 64


def _scene() -> tuple[np.ndarray, np.ndarray]:
    """Ground truth: a slanted plane 2..4 m (left to right) with a box at 1 m in its middle; the
    image: textured (random) on the left half, flat grey on the right half."""
    gt = np.tile(np.linspace(2.0, 4.0, W), (H, 1))
    gt[16:32, 24:40] = 1.0
    rng = np.random.default_rng(0)
    gray = np.full((H, W), 128.0)
    gray[:, : W // 2] = rng.uniform(0, 255, (H, W // 2))
    return gt, gray


def test_depth_edges_at_discontinuities_only():
    gt, _ = _scene()
    e = depth_edges(gt, radius=2)
    assert e[16, 30] and e[15, 30] and e[31, 30] and e[24, 24] and e[24, 22]
    assert not e[24, 31] and not e[5, 5] and not e[24, 44]  # inside the box, on the (slanted) plane
    ramp = np.tile(np.linspace(1.0, 1.5, W), (H, 1))  # a slanted plane: no jump anywhere
    assert not depth_edges(ramp).any()
    holes = np.full((H, W), 2.0)
    holes[10:20, 10:20] = 0.0  # missing ground truth is not an edge
    assert not depth_edges(holes).any()


def test_texture_classes_follow_the_image_gradient():
    _, gray = _scene()
    g = local_gradient(gray)
    assert g[:, :20].min() > 10 and g[:, 40:].max() < 1e-3
    r = frame_regions(np.full((H, W), 2.0), gray=gray)
    assert r["textured"][:, :20].all() and r["textureless"][:, 40:].all()
    assert "confident" not in r and "dynamic" not in r  # no confidence, no masks: classes left out


def test_error_is_booked_to_the_region_that_has_it():
    """Depth 50 % off on the texture-less, far right quarter: the error shows up in the
    textureless / unconfident / far classes, the textured left half and the near box stay exact."""
    gt, gray = _scene()
    pred = gt.copy()
    pred[:, 48:] *= 1.5  # texture-less, far (3.5-4 m)
    conf = np.ones((H, W))
    conf[:, 48:] = 0.1  # ... and marked unconfident
    static = np.ones((H, W), np.uint8)
    static[0:4, 0:4] = 0
    b = RegionBreakdown()
    for _ in range(3):
        b.add(pred, gt, gray=gray, confidence=conf, static=static)
    r = b.result()
    assert r["textured"]["abs_rel"] < 1e-9 and r["confident"]["abs_rel"] < 1e-9
    assert r["textureless"]["error_share"] == pytest.approx(1.0) and r["unconfident"]["abs_rel"] == pytest.approx(0.5)
    assert r["far"]["error_share"] == pytest.approx(1.0) and r["near"]["abs_rel"] < 1e-9
    assert r["far"]["log_bias"] > 0.3 and r["near"]["log_bias"] == pytest.approx(0.0)
    assert r["dynamic"]["pixels"] == 3 * 16 and r["dynamic"]["abs_rel"] < 1e-9
    assert r["border"]["share"] + r["interior"]["share"] == pytest.approx(1.0)
    assert r["depth_edge"]["share"] > 0 and r["depth_edge"]["abs_rel"] < 1e-9
    shares = sum(r[k]["error_share"] for k in ("near", "mid", "far"))
    assert shares == pytest.approx(1.0)
    text = format_regions(r)
    assert "textureless" in text and "100.0%" in text


def test_breakdown_skips_frames_without_ground_truth():
    b = RegionBreakdown()
    b.add(np.ones((H, W)), np.zeros((H, W)))
    assert b.result() == {}


def test_eval_reports_the_regions(tmp_path):
    """`gcvd-flow eval` on a run dir (no cache: no texture / dynamic classes) has the breakdown
    in its JSON and its table; a quarter of the frame wrong and unconfident is found there."""
    from test_metrics import _fake_run

    from gcvd_flow.evaluate.run_eval import evaluate, format_metrics
    from gcvd_flow.evaluate.synth import render_clip
    from gcvd_flow.io.formats import write_generic_layout

    clip = render_clip(n_frames=4, trajectory="orbit", size=(48, 32), seed=0)
    write_generic_layout(tmp_path / "clip", clip)
    run = _fake_run(tmp_path, clip, [0, 1, 2, 3])
    (run / "confidence").mkdir()
    for i in range(4):
        d = np.load(run / "depth" / f"{i:06d}.npy")
        d[:, :12] *= 3.0
        np.save(run / "depth" / f"{i:06d}.npy", d)
        conf = np.ones_like(d)
        conf[:, :12] = 0.2
        np.save(run / "confidence" / f"{i:06d}.npy", conf)
    res = evaluate(run, tmp_path / "clip")
    reg = res["regions"]
    assert "textureless" not in reg and "dynamic" not in reg
    # (one median scaling over the whole frame: the wrong quarter shifts it a little)
    assert reg["unconfident"]["error_share"] > 0.75 and reg["unconfident"]["abs_rel"] > 10 * reg["confident"]["abs_rel"]
    assert reg["unconfident"]["share"] == pytest.approx(0.25, abs=0.02)
    assert "depth by region" in format_metrics(res)
