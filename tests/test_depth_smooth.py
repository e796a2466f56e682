"""Edge-aware, confidence-weighted smoothing of the final depth (stages.depth.smooth,
depth_consensus.smooth_lambda): an unconfident, texture-less surface with blotchy depth takes
the depth its confident surroundings and its own average say; colour edges stop it; confident
pixels keep their depth."""

from __future__ import annotations

import cv2
import numpy as np

from gcvd_flow.stages.depth.smooth import fast_global_smooth, smooth_depth

H, W = 72, 96
LAM, SIGMA, KEEP = 300.0, 0.03, 0.7  # the stage's defaults


def _plane() -> np.ndarray:
    """Depth (H, W) of a tilted plane: 1 / z affine in the pixel coordinates (a wall at an angle)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    return (1.0 / (0.5 + 0.003 * u + 0.002 * v)).astype(np.float32)


def _blotches(seed: int, amp: float = 0.25) -> np.ndarray:
    """A multiplicative error exp(n), n smooth over ~10 px patches (what densified sparse depth
    looks like on a wall), mean about zero."""
    rng = np.random.default_rng(seed)
    n = cv2.resize(rng.normal(0.0, amp, (H // 9, W // 9)), (W, H), interpolation=cv2.INTER_CUBIC)
    return np.exp(n - n.mean()).astype(np.float32)


def _log_err(d: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> float:
    return float(np.mean(np.abs(np.log(d[mask] / ref[mask]))))


def _wall_frame(seed: int = 0):
    """A uniformly grey wall: an 8-px border confident (0.9) at the plane's depth, the texture-less
    interior unconfident (0.05) with blotchy depth."""
    truth = _plane()
    inner = np.zeros((H, W), bool)
    inner[8:-8, 8:-8] = True
    depth = np.where(inner, truth * _blotches(seed), truth).astype(np.float32)
    conf = np.where(inner, 0.05, 0.9).astype(np.float32)
    img = np.full((H, W, 3), 128, np.uint8)
    return truth, depth, conf, img, inner


def test_an_unconfident_textureless_plane_takes_the_planes_depth():
    """The blotches (~20 % in log) average out: the interior ends within a few % of the plane;
    without smoothing (lambda 0) it keeps its error."""
    for seed in range(3):
        truth, depth, conf, img, inner = _wall_frame(seed)
        before = _log_err(depth, truth, inner)
        out = smooth_depth(depth, conf, img, LAM, SIGMA, KEEP)
        assert before > 0.1
        assert _log_err(out, truth, inner) < 0.25 * before
        assert _log_err(out, truth, inner) < 0.04
        np.testing.assert_array_equal(smooth_depth(depth, conf, img, 0.0, SIGMA, KEEP), depth)


def test_confident_pixels_keep_their_depth_and_invalid_ones_stay_zero():
    truth, depth, conf, img, inner = _wall_frame()
    depth[0:3, 40:50] = 0.0
    out = smooth_depth(depth, conf, img, LAM, SIGMA, KEEP)
    sure = (conf >= KEEP) & (depth > 0)
    np.testing.assert_array_equal(out[sure], depth[sure])
    assert (out[depth == 0] == 0).all() and (out[depth > 0] > 0).all()
    # half the keep confidence keeps a quarter of its own log depth: (c / keep)^2
    half = conf.copy()
    half[inner] = KEEP / 2
    out_half = smooth_depth(depth, half, img, LAM, SIGMA, KEEP)
    full = smooth_depth(depth, half, img, LAM, SIGMA, 1e-9 + KEEP / 2)  # every pixel keeps all of it
    np.testing.assert_array_equal(full, depth)
    sm = fast_global_smooth(np.log(np.where(depth > 0, depth, 1.0)), np.where(depth > 0, half.astype(np.float64) ** 2
                            + 0.01, 0.0), img / 255.0, LAM, SIGMA)
    expect = np.exp(0.25 * np.log(np.where(depth > 0, depth, 1.0)) + 0.75 * sm)
    np.testing.assert_allclose(out_half[inner], expect[inner], rtol=1e-5)


def test_a_colour_edge_of_equal_grey_stops_the_smoothing():
    """Left half red, right half green, the same grey level, at depths 1 and 2, all unconfident
    with blotches: each half keeps its own depth up to the boundary (an RGB guide); a grey guide
    would mix them there."""
    depth = np.where(np.arange(W)[None, :] < W // 2, 1.0, 2.0) * _blotches(5, 0.1)
    depth = np.broadcast_to(depth, (H, W)).astype(np.float32)
    truth = np.broadcast_to(np.where(np.arange(W)[None, :] < W // 2, 1.0, 2.0), (H, W))
    img = np.zeros((H, W, 3), np.uint8)
    img[:, : W // 2] = (170, 50, 80)
    img[:, W // 2:] = (50, 170, 80)  # equal mean (grey) of the channels: only colour separates them
    conf = np.full((H, W), 0.05, np.float32)
    out = smooth_depth(depth, conf, img, LAM, SIGMA, KEEP)
    band = np.zeros((H, W), bool)
    band[:, W // 2 - 3: W // 2 + 3] = True  # the 3 px on each side of the boundary
    assert _log_err(out, truth, band) < 0.06
    grey = np.repeat(img.mean(axis=2, keepdims=True).astype(np.uint8), 3, axis=2)
    assert _log_err(smooth_depth(depth, conf, grey, LAM, SIGMA, KEEP), truth, band) > 0.15


def test_excluded_pixels_neither_give_nor_take():
    """``static`` (the user's --masks keep): a masked blob with a wild depth keeps it, and its
    neighbours' depth is the same as if the blob's depth were anything else."""
    truth, depth, conf, img, inner = _wall_frame()
    keep = np.ones((H, W), bool)
    keep[30:40, 40:50] = False
    wild = depth.copy()
    wild[~keep] *= 5.0
    a = smooth_depth(depth, conf, img, LAM, SIGMA, KEEP, static=keep)
    b = smooth_depth(wild, conf, img, LAM, SIGMA, KEEP, static=keep)
    np.testing.assert_array_equal(a[keep], b[keep])
    np.testing.assert_array_equal(b[~keep], wild[~keep])
    assert not np.array_equal(smooth_depth(depth, conf, img, LAM, SIGMA, KEEP)[keep],
                              smooth_depth(wild, conf, img, LAM, SIGMA, KEEP)[keep])


def test_reruns_are_byte_identical():
    truth, depth, conf, img, inner = _wall_frame(1)
    a = smooth_depth(depth, conf, img, LAM, SIGMA, KEEP)
    assert a.dtype == np.float32 and a.tobytes() == smooth_depth(depth, conf, img, LAM, SIGMA, KEEP).tobytes()


def test_the_stage_smooths_by_default_and_not_with_lambda_zero():
    """pipeline.run_depth_consensus: the default item smooths the unconfident wall (a reference
    that sees nothing confidently leaves the carry and splat without effect); smooth_lambda=0
    returns the blotches."""
    from gcvd_flow.pipeline import DepthConsensusParams, run_depth_consensus

    truth, depth, conf, img, inner = _wall_frame()
    K = np.array([[80.0, 0, (W - 1) / 2], [0, 80.0, (H - 1) / 2], [0, 0, 1]])
    far = np.eye(4)
    far[0, 3] = 100.0  # sees none of it
    inputs = {"index": 0, "K": K, "poses": np.stack([np.eye(4), far]),
              "depth": {"depth": depth, "confidence": conf},
              "refs": [{"depth": depth, "confidence": np.zeros_like(conf)}], "ref_indices": [1],
              "static": [{"static": np.ones((H, W), np.uint8)} for _ in range(2)], "image": {"image": img}}
    on = run_depth_consensus(inputs, DepthConsensusParams(offsets=(1,), edge_jump=0.0), None)
    off = run_depth_consensus(inputs, DepthConsensusParams(offsets=(1,), edge_jump=0.0, smooth_lambda=0.0), None)
    np.testing.assert_allclose(off["depth"], depth, rtol=1e-6)  # the carry's exp(log) round trip only
    assert _log_err(on["depth"], truth, inner) < 0.25 * _log_err(depth, truth, inner)
    np.testing.assert_array_equal(on["confidence"], conf)


def test_edge_weights_are_the_channel_reduction_bit_for_bit() -> None:
    """edge_weights' channel sum == numpy's sum over the last axis (the previous code), bit for bit."""
    from gcvd_flow.stages.depth.smooth import edge_weights

    rng = np.random.default_rng(5)
    for shape in ((37, 41, 3), (19, 23), (8, 9, 1), (11, 13, 2), (7, 6, 4)):
        img = rng.uniform(0, 1, shape)
        ax, ay = edge_weights(img, 0.03)
        x = img if img.ndim == 3 else img[..., None]
        ax0 = np.exp(-np.square(x[:, 1:] - x[:, :-1]).sum(-1) * (1.0 / 0.03 ** 2))
        ay0 = np.exp(-np.square(x[1:] - x[:-1]).sum(-1) * (1.0 / 0.03 ** 2))
        assert ax.tobytes() == ax0.tobytes() and ay.tobytes() == ay0.tobytes()
