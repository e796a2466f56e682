"""Keyframe selection: threshold rule, forced first/last, max gap, pure rotation."""

from __future__ import annotations

import numpy as np
import pytest

from gcvd_flow.stages.frontend.flow import compute_pair_flow
from gcvd_flow.stages.graph.keyframes import pair_motion, select_keyframes


def test_pair_motion_masks() -> None:
    fwd = np.zeros((10, 20, 2), np.float32)
    fwd[:, :10, 0] = 3.0  # left half moves 3 px (static scene)
    fwd[:, 10:, 1] = 40.0  # right half: a dynamic object moving 40 px
    static = np.ones((10, 20), np.uint8)
    static[:, 10:] = 0
    valid = np.ones((10, 20), bool)
    assert pair_motion(fwd, valid, static) == pytest.approx(3.0)
    assert pair_motion(fwd, valid, None) == pytest.approx(21.5)
    valid[:, :5] = False
    assert pair_motion(fwd, valid, static) == pytest.approx(3.0)
    # Nothing static and valid: falls back to the unmasked mean instead of 0.
    assert pair_motion(fwd, np.zeros((10, 20), bool), static) == pytest.approx(21.5)


def test_threshold_rule_and_first_last_forced() -> None:
    # 120 x 160 -> threshold 12 px; 5 px per pair -> keyframe every 3rd frame (15 > 12).
    sel = select_keyframes(np.full(20, 5.0), 120, 160)
    assert sel["threshold_px"] == pytest.approx(12.0)
    assert sel["indices"] == [0, 3, 6, 9, 12, 15, 18, 20]
    assert len(sel["accumulated"]) == 21
    assert sel["accumulated"][3] == pytest.approx(15.0)
    assert sel["accumulated"][4] == pytest.approx(5.0)  # reset after the keyframe


def test_slower_motion_gives_fewer_keyframes() -> None:
    rng = np.random.default_rng(0)
    m = rng.uniform(0.5, 1.5, 200)
    fast = select_keyframes(m * 4.0, 96, 128)["indices"]
    slow = select_keyframes(m * 1.0, 96, 128)["indices"]
    assert len(slow) < len(fast)
    assert len(fast) > 2.5 * len(slow)


def test_max_gap_rule() -> None:
    sel = select_keyframes(np.zeros(99), 96, 128, max_gap=39)  # 100 frames
    assert sel["indices"] == [0, 39, 78, 99]
    sel = select_keyframes(np.full(99, 0.1), 96, 128, max_gap=10)
    assert max(np.diff(sel["indices"])) <= 10
    assert sel["indices"][0] == 0 and sel["indices"][-1] == 99


def test_degenerate_inputs() -> None:
    assert select_keyframes(np.zeros(0), 96, 128)["indices"] == [0]
    assert select_keyframes([np.nan, 50.0], 96, 128)["indices"] == [0, 2]


def test_pure_rotation_clip_places_keyframes_by_image_motion() -> None:
    from gcvd_flow.evaluate.synth import render_clip

    clip = render_clip(40, "rotation", size=(128, 96))
    motion = [
        pair_motion(f["fwd"], f["fwd_valid"], None)
        for f in (compute_pair_flow(clip.frames[i], clip.frames[i + 1], preset="fast") for i in range(39))
    ]
    sel = select_keyframes(motion, 96, 128)
    # A 40 deg pan at f = 100 px gives ~70 px of image motion: rotation produces flow, so
    # keyframes are placed every ~9.6 px of it (documented behaviour), not only at the ends.
    assert sum(motion) > 50.0
    assert sel["indices"][0] == 0 and sel["indices"][-1] == 39
    assert 5 <= len(sel["indices"]) <= 12
    assert sel["indices"] == sorted(set(sel["indices"]))
