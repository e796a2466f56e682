"""stages.depth.tilt: the unconfident depth's per-frame range chosen by the references' images."""

from __future__ import annotations

import numpy as np

from gcvd_flow.stages.depth import tilt

H, W = 96, 128
K = np.array([[100.0, 0, 64], [0, 100.0, 48], [0, 0, 1]])
RNG = np.random.default_rng(3)
FREQ = RNG.uniform(10, 40, (12, 2)) * RNG.choice([-1, 1], (12, 2))
PHASE = RNG.uniform(0, 2 * np.pi, 12)


def _render(centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Image and depth of a camera at ``centre`` (identity rotation) looking at the textured plane
    Z - 0.8 Y = 2 (depth 1.45-3.25 m over the frame)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    r = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)])
    t = (2.0 - centre[2] + 0.8 * centre[1]) / (r[2] - 0.8 * r[1])
    X, Z = centre[0] + t * r[0], centre[2] + t * r[2]
    tex = sum(np.sin(fx * X + fz * Z + p) for (fx, fz), p in zip(FREQ, PHASE))
    grey = np.clip(128 + 25 * tex, 0, 255).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=2), t  # r[2] = 1: t is the depth


def _pose(centre: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = centre
    return T


def _frame() -> tuple[np.ndarray, np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    img, depth = _render(np.zeros(3))
    refs = [(_render(c)[0], _pose(c)) for c in (np.array([-0.15, 0, 0]), np.array([0.15, 0.05, 0]))]
    return img, depth, refs


def _abs_rel(pred: np.ndarray, gt: np.ndarray) -> float:
    s = np.median(gt) / np.median(pred)
    return float(np.mean(np.abs(pred * s - gt) / gt))


def test_a_range_compressed_unconfident_depth_is_stretched_back():
    img, gt, refs = _frame()
    mu = np.median(np.log(gt))
    squashed = np.exp(mu + 0.8 * (np.log(gt) - mu)).astype(np.float32)  # slope 0.8: needs 1.25
    conf = np.zeros((H, W), np.float32)
    before = _abs_rel(squashed, gt)
    out, b = tilt.photometric_tilt(squashed, conf, img, _pose(np.zeros(3)), refs, K, tilt.SLOPES, shrink=0.0)
    assert abs(b - 1.25) < 0.026
    assert _abs_rel(out, gt) < 0.2 * before
    half, bh = tilt.photometric_tilt(squashed, conf, img, _pose(np.zeros(3)), refs, K, tilt.SLOPES, shrink=0.5)
    assert abs(bh - (1 + 0.5 * (b - 1))) < 1e-9
    assert _abs_rel(out, gt) < _abs_rel(half, gt) < 0.7 * before


def test_correct_depth_is_kept_and_confident_pixels_are_untouched():
    img, gt, refs = _frame()
    conf = np.zeros((H, W), np.float32)
    out, b = tilt.photometric_tilt(gt.astype(np.float32), conf, img, _pose(np.zeros(3)), refs, K, tilt.SLOPES, 0.0)
    assert b == 1.0  # the true range is the best hypothesis
    mu = np.median(np.log(gt))
    squashed = np.exp(mu + 0.8 * (np.log(gt) - mu)).astype(np.float32)
    conf[:, :40] = 0.9
    out, b = tilt.photometric_tilt(squashed, conf, img, _pose(np.zeros(3)), refs, K, tilt.SLOPES, 0.0)
    assert b > 1.1
    np.testing.assert_array_equal(out[:, :40], squashed[:, :40])
    assert not np.allclose(out[:, 40:], squashed[:, 40:])


def test_nothing_to_choose_from_leaves_the_depth():
    img, gt, refs = _frame()
    d = gt.astype(np.float32)
    out, b = tilt.photometric_tilt(d, np.ones((H, W), np.float32), img, _pose(np.zeros(3)), refs, K, tilt.SLOPES)
    assert b == 1.0 and np.array_equal(out, d)
    out, b = tilt.photometric_tilt(d, np.zeros((H, W), np.float32), img, _pose(np.zeros(3)), [], K, tilt.SLOPES)
    assert b == 1.0 and np.array_equal(out, d)
