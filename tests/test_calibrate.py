"""Focal self-calibration (stages/frontend/calibrate.py, the calibrate stage): the focal length of
synthetic clips rendered at other fields of view than the guess is recovered, also from a
rotation-only clip; a clip whose motion cannot determine it keeps the guess and says so."""

import numpy as np
import pytest

from gcvd_flow.evaluate.synth import default_intrinsics, render_clip
from stages.frontend.calibrate import estimate_focal

SIZE = (160, 120)


@pytest.mark.slow
@pytest.mark.parametrize("trajectory,n,scale", [("loop", 30, 1.2), ("loop", 30, 0.8)])
def test_focal_recovered_at_other_fields_of_view(trajectory, n, scale):
    K_guess = default_intrinsics(SIZE)
    clip = render_clip(n, trajectory, size=SIZE, seed=0, focal=K_guess[0, 0] * scale)
    res = estimate_focal(list(clip.frames), K_guess)
    assert res["determined"], res
    assert res["method"] == "bundle adjustment"
    assert abs(res["focal"] / clip.K[0, 0] - 1) < 0.02, (res["focal"], clip.K[0, 0])
    assert 0 < res["rel_sigma"] < 0.03


@pytest.mark.slow
def test_focal_recovered_from_pure_rotation():
    K_guess = default_intrinsics(SIZE)
    clip = render_clip(20, "rotation", size=SIZE, seed=0, focal=K_guess[0, 0] * 0.8)
    res = estimate_focal(list(clip.frames), K_guess)
    assert res["determined"] and res["method"] == "rotation", res
    assert abs(res["focal"] / clip.K[0, 0] - 1) < 0.02, (res["focal"], clip.K[0, 0])


def test_static_clip_keeps_the_guess_and_says_why():
    K_guess = default_intrinsics(SIZE)
    clip = render_clip(2, "orbit", size=SIZE, seed=0, focal=K_guess[0, 0] * 1.2)
    frames = [clip.frames[0]] * 10  # a camera that does not move
    res = estimate_focal(frames, K_guess)
    assert not res["determined"]
    assert res["focal"] == K_guess[0, 0]
    assert "hardly moves" in res["reason"]


class _Frames:
    """The ingest MapValue as run_calibrate reads it: items [{image}], len, summary (camera)."""

    def __init__(self, images, K, guessed):
        self._images = images
        h, w = images[0].shape[:2]
        self.summary = {"K": K.tolist(), "width": w, "height": h, "source_width": 2 * w, "source_height": 2 * h,
                        "guessed": guessed, "origin": "guess" if guessed else "user (--intrinsics)"}

    def __len__(self):
        return len(self._images)

    def __getitem__(self, i):
        return {"image": self._images[i]}


class _Ctx:
    def __init__(self):
        self.lines = []

    def log(self, msg):
        self.lines.append(msg)


def test_calibrate_stage_warns_and_keeps_the_guess_when_the_motion_cannot_tell():
    from gcvd_flow import pipeline

    K_guess = default_intrinsics(SIZE)
    clip = render_clip(2, "orbit", size=SIZE, seed=0)
    ctx = _Ctx()
    out = pipeline.run_calibrate({"ingest": _Frames([clip.frames[0]] * 8, K_guess, True)},
                                 pipeline.CalibrateParams(), ctx)
    assert not out["estimated"] and out["guessed"]
    np.testing.assert_array_equal(out["K"], K_guess)
    assert out["warning"].startswith("focal length not estimated")
    assert [ln for ln in ctx.lines if ln.startswith("warning: ")] == ["warning: " + out["warning"]]


def test_calibrate_stage_with_given_intrinsics_does_nothing():
    from gcvd_flow import pipeline

    K = default_intrinsics(SIZE)
    K[0, 0] = K[1, 1] = 111.0
    ctx = _Ctx()
    out = pipeline.run_calibrate({"ingest": _Frames([np.zeros((120, 160, 3), np.uint8)] * 3, K, False)},
                                 pipeline.CalibrateParams(), ctx)
    assert not out["estimated"] and not out["guessed"] and not out["warning"] and not ctx.lines
    np.testing.assert_array_equal(out["K"], K)
    assert out["focal_source"] == [222.0, 222.0]
