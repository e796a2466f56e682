"""Multi-view depth fusion at known poses: recovers per-pixel detail a smooth depth lacks."""

from __future__ import annotations

import numpy as np
from geometry_ref import rigid_flow

from gcvd_flow.evaluate.synth import render_clip
from gcvd_flow.stages.depth.fusion import fuse_depth, fuse_depth_flows


def _absrel(z: np.ndarray, gt: np.ndarray) -> float:
    m = gt > 0
    z = z * np.median(gt[m]) / np.median(z[m])
    return float(np.mean(np.abs(z[m] - gt[m]) / gt[m]))


def test_fusion_corrects_a_distorted_depth_at_pose_scale():
    clip = render_clip(30, "loop", size=(256, 192), seed=0)
    i = 15
    gt = clip.depth[i]
    v, u = np.mgrid[0:192, 0:256]
    # a wrong depth: 15 % low-frequency distortion, and at twice the poses' scale
    wrong = (2.0 * gt * (1 + 0.15 * np.sin(u / 40.0) * np.cos(v / 30.0))).astype(np.float32)
    refs = [(clip.frames[j], clip.poses[j]) for j in (i - 2, i + 2)]  # 30 frames: +-2 ~ +-8 of the 120-frame clip
    fused, measured, conf = fuse_depth(clip.frames[i], wrong, clip.poses[i], refs, clip.K)
    assert fused.dtype == np.float32 and fused.shape == gt.shape and measured > 0.6
    before, after = _absrel(wrong, gt), _absrel(fused, gt)
    print(f"fusion AbsRel {before:.3f} -> {after:.3f}, measured {measured:.2f}")
    assert after < 0.5 * before and after < 0.05
    # the result is at the poses' scale (triangulation), not at the input depth's
    assert abs(float(np.median(fused / gt)) - 1.0) < 0.03
    # deterministic
    again, _, conf2 = fuse_depth(clip.frames[i], wrong, clip.poses[i], refs, clip.K)
    assert np.array_equal(fused, again) and np.array_equal(conf, conf2)
    # confidence: in [0, 1], zero where nothing was measured, and it ranks the pixels: the
    # most confident half is more accurate than the least confident measured half
    assert conf.dtype == np.float32 and conf.min() >= 0 and conf.max() <= 1 and (conf > 0).mean() > 0.5
    err = np.abs(fused * np.median(gt / fused) - gt) / gt
    measured_px = conf > 0
    hi = conf >= np.median(conf[measured_px])
    assert err[measured_px & hi].mean() < err[measured_px & ~hi].mean()


def test_fusion_without_baseline_keeps_the_depth():
    clip = render_clip(6, "rotation", size=(128, 96), seed=0)
    d = clip.depth[2].astype(np.float32)
    out, measured, conf = fuse_depth(clip.frames[2], d, clip.poses[2], [(clip.frames[4], clip.poses[4])], clip.K)
    assert measured == 0.0 and np.array_equal(out, d) and not conf.any()
    out, measured, _ = fuse_depth(clip.frames[2], d, clip.poses[2], [], clip.K)
    assert measured == 0.0 and np.array_equal(out, d)


def test_fusion_with_every_triangulation_rejected_keeps_the_depth():
    """A reference with a baseline too small for any usable angle: no NaN (an empty median
    used to turn whole frames into NaN), the optimised depth is kept."""
    clip = render_clip(6, "orbit", size=(96, 72), seed=0)
    d = clip.depth[2].astype(np.float32)
    near = clip.poses[2].copy()
    near[:3, 3] += 1e-4  # 0.1 mm: triangulation angles far below min_angle_deg
    out, measured, _ = fuse_depth(clip.frames[2], d, clip.poses[2], [(clip.frames[2], near)], clip.K)
    assert measured == 0.0 and np.isfinite(out).all() and np.array_equal(out, d)


def test_fusion_fuses_within_max_log_dev_but_counts_agreement_within_agree_log_dev():
    """A region of the optimised depth 50 % too far: with max_log_dev 0.6 its triangulations are
    fused (the region comes out right), yet they do not count as agreeing (agree_log_dev 0.3), so
    the region's confidence stays what the 0.3 gate gave; with both at 0.3 the region keeps the
    wrong depth."""
    clip = render_clip(30, "loop", size=(128, 96), seed=0)
    i = 15
    gt = clip.depth[i]
    wrong = gt.astype(np.float32).copy()
    wrong[30:60, 40:80] *= 1.5  # log(1.5) = 0.41: between the two gates
    refs = [(clip.frames[j], clip.poses[j]) for j in (i - 2, i + 2)]
    region = (slice(34, 56), slice(44, 76))
    wide, _, conf_wide = fuse_depth(clip.frames[i], wrong, clip.poses[i], refs, clip.K, max_log_dev=0.6, agree_log_dev=0.3)
    narrow, _, conf_narrow = fuse_depth(clip.frames[i], wrong, clip.poses[i], refs, clip.K, max_log_dev=0.3, agree_log_dev=0.3)
    scale = np.median(gt / wide)
    assert np.median(np.abs(wide[region] * scale / gt[region] - 1)) < 0.05
    assert np.median(np.abs(narrow[region] * scale / gt[region] - 1)) > 0.3
    np.testing.assert_array_equal(conf_wide, conf_narrow)  # same agreeing measurements, same confidence
    assert np.median(conf_wide[region]) < 0.1 < np.median(conf_wide)


def test_confident_share_on_a_fast_pan_with_near_and_far_references():
    """Wide-baseline footage (a room scan panning several degrees per frame): far references
    leave the view, near ones measure. With coverage counted against two agreeing views
    (``coverage_refs=2``, the pipeline's default) a large share of the pixels is confident and
    right; counted against every reference (the rule before 2026-11-25) few are."""
    clip = render_clip(100, "scan", size=(128, 96), seed=0)
    i = 53
    gt = clip.depth[i]
    v, u = np.mgrid[0:96, 0:128]
    smooth = (gt * (1 + 0.15 * np.sin(u / 20.0) * np.cos(v / 15.0))).astype(np.float32)
    refs = [(clip.frames[i + k], clip.poses[i + k]) for k in (-8, -4, -2, 2, 4, 8)]
    fused, _, conf = fuse_depth(clip.frames[i], smooth, clip.poses[i], refs, clip.K, coverage_refs=2)
    _, _, conf_all = fuse_depth(clip.frames[i], smooth, clip.poses[i], refs, clip.K, coverage_refs=len(refs))
    ok = (conf >= 0.5) & (gt > 0)
    err = np.abs(fused * np.median(gt[gt > 0] / fused[gt > 0]) - gt) / np.maximum(gt, 1e-6)
    share, share_all = ok.mean(), ((conf_all >= 0.5) & (gt > 0)).mean()
    print(f"confident share {share:.3f} (every reference: {share_all:.3f}), AbsRel on it {err[ok].mean():.4f}, "
          f"elsewhere {err[~ok & (gt > 0)].mean():.4f}")
    assert share >= 0.4 and share >= share_all + 0.2
    assert err[ok].mean() <= 0.05 and err[ok].mean() < err[~ok & (gt > 0)].mean()



def test_spread_of_the_agreeing_measurements_lowers_the_confidence():
    """Two references that see a region 20 % apart (both within agree_log_dev of the optimised
    depth) count as agreeing; with ``spread_log_sigma`` the region's confidence falls by
    exp(-(s / sigma)^2 / 2) (s = their spread in log depth: 0.091), elsewhere (s = 0) it stays."""
    clip = render_clip(30, "loop", size=(128, 96), seed=0)
    i = 15
    gt = clip.depth[i].astype(np.float64)
    off = gt.copy()
    region = (slice(30, 60), slice(40, 80))
    off[region] *= 1.2  # reference i + 3 sees the region's surface 20 % further away
    flows = []
    for j, d in ((i - 3, gt), (i + 3, off)):
        f = rigid_flow(d, clip.K, clip.poses[i], clip.poses[j])
        flows.append((np.nan_to_num(f), np.isfinite(f).all(-1), clip.poses[j]))
    plain = fuse_depth_flows(gt, clip.poses[i], flows, clip.K, spread_log_sigma=0.0)[2]
    spread = fuse_depth_flows(gt, clip.poses[i], flows, clip.K, spread_log_sigma=0.1)[2]
    inner = (slice(34, 56), slice(44, 76))
    s = np.log(1.2) / 2  # two equally weighted measurements log(1.2) apart: std = half of it
    ratio = spread[inner] / np.maximum(plain[inner], 1e-6)
    assert np.median(plain[inner]) > 0.5  # both references agree with the optimised depth there
    np.testing.assert_allclose(np.median(ratio), np.exp(-0.5 * (s / 0.1) ** 2), rtol=0.1)
    outside = np.ones(gt.shape, bool)
    outside[25:65, 35:85] = False
    np.testing.assert_allclose(spread[outside], plain[outside], rtol=1e-4, atol=1e-6)
