"""Multi-view depth consensus (stages/depth/consensus.py): depth carried between frames with the
poses, averaged by confidence; other surfaces and unseen pixels left alone."""

from __future__ import annotations

import numpy as np
import pytest

from gcvd_flow.stages.depth import consensus
from gcvd_flow.stages.depth.consensus import carry_depth, consensus_depth

F = 100.0
W, H = 128, 96
K = np.array([[F, 0.0, (W - 1) / 2], [0.0, F, (H - 1) / 2], [0.0, 0.0, 1.0]])


def _plane(tx: float) -> np.ndarray:
    """Depth (H, W) float32 of the tilted plane z_w = 2 + 0.3 x_w + 0.2 y_w seen from (tx, 0, 0)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rx, ry = (u - K[0, 2]) / F, (v - K[1, 2]) / F
    return ((2.0 + 0.3 * tx) / (1.0 - 0.3 * rx - 0.2 * ry)).astype(np.float32)


def _pose(tx: float) -> np.ndarray:
    p = np.eye(4)
    p[0, 3] = tx
    return p


def _refs(xs, conf: float = 0.9, scale: float = 1.0):
    return [(_plane(x) * scale, np.full((H, W), conf, np.float32), _pose(x)) for x in xs]


REGION = (slice(30, 60), slice(40, 80))  # rows, cols of frame i's wrong, unconfident depth


def _wrong_frame(factor: float = 1.15) -> tuple[np.ndarray, np.ndarray]:
    depth = _plane(0.0)
    depth[REGION] *= factor
    conf = np.full((H, W), 0.9, np.float32)
    conf[REGION] = 0.0
    return depth, conf


def _log_err(est: np.ndarray, mask: np.ndarray) -> float:
    return float(np.mean(np.abs(np.log(est[mask] / _plane(0.0)[mask]))))


def test_carried_depth_of_a_consistent_neighbour_is_exact():
    T_ji = np.linalg.inv(_pose(0.2)) @ _pose(0.0)
    cam = consensus._Camera(K, H, W)
    z, c, err2, ok = carry_depth(cam, slice(0, H), _plane(0.0), _plane(0.2), np.full((H, W), 0.7, np.float32), T_ji)
    assert ok.mean() > 0.7  # the rest leaves frame j's image
    assert not ok[:, :3].any()  # the camera moves right: what i sees at its left edge is out of j
    np.testing.assert_allclose(z[ok], _plane(0.0)[ok], rtol=1e-4)
    assert np.sqrt(err2[ok]).max() < 0.05
    np.testing.assert_allclose(c[ok & (np.sqrt(err2) < 0.05)][:100], 0.7, rtol=1e-5)


def test_unconfident_region_takes_its_confident_neighbours_depth():
    depth, conf = _wrong_frame(1.15)  # |log 1.15| = 0.14: within max_log_dev (0.2)
    out = consensus_depth(depth, conf, _pose(0.0), _refs([-0.2, -0.1, 0.1, 0.2]), K)
    region = np.zeros((H, W), bool)
    region[REGION] = True
    assert _log_err(depth, region) > 0.13
    assert _log_err(out, region) < 0.01  # own weight 0.01 against four views at 0.9^2 + 0.01
    # confident, correct pixels stay correct
    assert _log_err(out, ~region) < 1e-4
    assert out.dtype == np.float32 and out.shape == (H, W)


def test_a_confident_frame_is_not_pulled_by_unconfident_neighbours():
    depth = _plane(0.0) * 1.1  # 10 % off, but the frame says it is sure
    conf = np.full((H, W), 1.0, np.float32)
    out = consensus_depth(depth, conf, _pose(0.0), _refs([-0.1, 0.1], conf=0.0), K)
    # two views at weight 0.01 each against 1.01: the log error shrinks by at most 2 %
    assert np.all(np.abs(np.log(out / depth)) < 0.02 * np.log(1.1) + 1e-4)


def test_another_surface_is_not_averaged_in():
    depth, conf = _wrong_frame(1.15)
    # the references all see something 60 % further (log ratio >= 0.33 > max_log_dev): occlusion

    out = consensus_depth(depth, conf, _pose(0.0), _refs([-0.2, 0.2], scale=1.6), K)
    np.testing.assert_allclose(out, depth, rtol=1e-5)


def test_no_references_and_invalid_pixels():
    depth, conf = _wrong_frame()
    np.testing.assert_allclose(consensus_depth(depth, conf, _pose(0.0), [], K), depth, rtol=1e-6)
    depth[:5] = 0.0
    out = consensus_depth(depth, conf, _pose(0.0), _refs([0.1]), K)
    assert np.all(out[:5] == 0) and np.all(out[5:] > 0)


def test_result_does_not_depend_on_the_row_blocks(monkeypatch):
    depth, conf = _wrong_frame()
    refs = _refs([-0.2, 0.1, 0.3])
    a = consensus_depth(depth, conf, _pose(0.0), refs, K)
    monkeypatch.setattr(consensus, "BLOCK_ROWS", 7)
    b = consensus_depth(depth, conf, _pose(0.0), refs, K)
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("bad", [(0,), (-8, 8)])
def test_offsets_must_be_positive_distances(bad):
    from pydantic import ValidationError

    from gcvd_flow.pipeline import DepthConsensusParams

    with pytest.raises(ValidationError):
        DepthConsensusParams(offsets=bad)
    assert DepthConsensusParams(offsets=(16, 8, 8)).offsets == (8, 16)


def test_moving_pixels_are_neither_averaged_nor_carried():
    depth, conf = _wrong_frame(1.15)
    refs = _refs([-0.2, 0.2])
    region = np.zeros((H, W), bool)
    region[REGION] = True
    static = (~region).astype(np.uint8)  # frame i's wrong region is a moving object
    out = consensus_depth(depth, conf, _pose(0.0), refs, K, static=static,
                          ref_static=[np.ones((H, W), np.uint8)] * 2)
    np.testing.assert_array_equal(out[region], depth[region])
    # a reference whose every pixel moves gives nothing: the depth is unchanged everywhere
    out = consensus_depth(depth, conf, _pose(0.0), refs, K, static=np.ones((H, W), np.uint8),
                          ref_static=[np.zeros((H, W), np.uint8)] * 2)
    np.testing.assert_allclose(out, depth, rtol=1e-6)
    # and with static masks everywhere the region is corrected as without masks
    out = consensus_depth(depth, conf, _pose(0.0), refs, K, static=np.ones((H, W), np.uint8),
                          ref_static=[np.ones((H, W), np.uint8)] * 2)
    assert _log_err(out, region) < 0.01
