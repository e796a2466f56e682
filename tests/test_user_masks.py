"""--masks DIR: the user's masks (one PNG per frame, non-zero = leave out) are combined with the
motion masks (static = 0 there), keyed by their content, and a missing or mis-sized mask is one
line and exit 2."""

import numpy as np
import pytest
from conftest import cli

from gcvd_flow import pipeline
from gcvd_flow.stages.frontend.ingest import FrameError


def test_user_mask_zeroes_the_static_mask_at_working_resolution():
    static = np.ones((36, 48), np.uint8)
    user = np.zeros((72, 96), bool)
    user[10:30, 20:50] = True
    out = pipeline._with_user_mask(static, {"user_mask": user, "source_size": [96, 72]})
    # a working pixel is out when any source pixel it covers is: rows 5..14, cols 10..24
    assert out[5:15, 10:25].max() == 0 and out.sum() == static.sum() - 10 * 15
    assert pipeline._with_user_mask(static, {}) is static
    with pytest.raises(FrameError, match="48x36"):
        pipeline._with_user_mask(static, {"user_mask": np.zeros((36, 48), bool), "source_size": [96, 72]})


def _masks(folder, n, size=(72, 96), names=None):
    import cv2

    folder.mkdir()
    for i in range(n):
        m = np.zeros(size, np.uint8)
        m[20:40, 30:60] = 255
        cv2.imwrite(str(folder / f"{names[i] if names else f'{i:06d}'}.png"), m)


def test_mask_items_read_each_frames_mask_by_name_or_order(tmp_path):
    """_mask_items gives every ingest item its own mask file (by the frame's name, else in frame
    order, for the frames ingest selected) as a content-keyed input; run_masks zeroes them."""
    from types import SimpleNamespace

    from gcvd_flow.io.sources import open_source

    clip = tmp_path / "clip"
    cli("synth", str(clip), "--frames", "6", "--size", "96x72", "--trajectory", "loop", check=True)
    src = open_source(str(clip))
    by_order = tmp_path / "order"
    _masks(by_order, 6, names=[f"m{i:02d}" for i in range(6)])
    view = SimpleNamespace(source=src, len=lambda s: 3, summary=lambda s: {"frame_indices": [0, 2, 4]})
    items = pipeline._mask_items(view, pipeline.MasksParams(backend="none", user_dir=str(by_order)))
    assert [it["user_mask"].loader.path.endswith(f"m{k:02d}.png") for k, it in zip((0, 2, 4), items)] == [True] * 3
    m = items[1]["user_mask"].loader()
    assert m.shape == (72, 96) and m[20:40, 30:60].all() and m.sum() == 20 * 30
    fl = {"fwd": np.zeros((72, 96, 2), np.float32), "fwd_valid": np.ones((72, 96), bool),
          "bwd": np.zeros((72, 96, 2), np.float32), "bwd_valid": np.ones((72, 96), bool)}
    inputs = {**{k: (v.value if hasattr(v, "value") else v) for k, v in items[1].items() if k != "chain"},
              "chain": [fl], "user_mask": m}
    static = pipeline.run_masks(inputs, pipeline.MasksParams(backend="none", user_dir=str(by_order)), None)["static"]
    assert static[20:40, 30:60].max() == 0 and static.sum() == 72 * 96 - 20 * 30
    # the same masks under the frames' names
    named = tmp_path / "named"
    _masks(named, 6)
    items = pipeline._mask_items(view, pipeline.MasksParams(backend="none", user_dir=str(named)))
    assert items[2]["user_mask"].loader.path.endswith("000004.png")


def test_missing_or_missized_masks_are_one_line_exit_2(tmp_path):
    clip = tmp_path / "clip"
    cli("synth", str(clip), "--frames", "4", "--size", "96x72", "--trajectory", "loop", check=True)
    few = tmp_path / "few"
    _masks(few, 3)
    r = cli("run", str(clip), "--out", str(tmp_path / "run"), "--cache", str(tmp_path / "cache"), "--masks", str(few),
            "--until", "masks", "--profile", "fast")
    assert r.returncode == 2 and "no mask for frame 000003" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 2  # the camera line and the error
    r = cli("plan", str(clip), "--out", str(tmp_path / "run"), "--masks", str(tmp_path / "nope"))
    assert r.returncode == 2 and "not a folder" in r.stderr


TUM_SYNTH = [[206.9, 206.9, 127.5, 95.5], [0.2624, -0.9531, -0.0054, 0.0026, 1.1633], "OPENCV"]  # fr1 at 256 px


def test_only_a_lens_that_leaves_a_black_border_gets_one():
    from gcvd_flow.stages.frontend import user_masks

    assert user_masks.lens_border(TUM_SYNTH, (256, 192))  # its corners fall outside the frame
    assert not user_masks.lens_border([[200, 200, 127.5, 95.5], [0.03, -0.01, 0.004, -0.001], "OPENCV_FISHEYE"], (256, 192))
    assert not user_masks.lens_border([[200, 200, 127.5, 95.5], [-0.25, 0.08, 0.001, -0.0008, -0.02], "OPENCV"], (256, 192))
    assert not user_masks.lens_border(None, (256, 192))


def test_the_lens_black_border_is_left_out_as_a_user_mask_would_be():
    """Without --masks, a lens whose undistortion leaves the frame's corners black (TUM fr1's):
    the mask items carry the border as the user's exclusion (user_keep 0 there, static 0, the
    summary says so); a pinhole clip's items stay as they were (no user_keep)."""
    from types import SimpleNamespace

    from gcvd_flow.stages.frontend import lens

    src = SimpleNamespace(size=(256, 192))
    lensed = {"frame_indices": [0, 1], "width": 256, "height": 192, "distortion_intrinsics": TUM_SYNTH[0],
              "distortion": TUM_SYNTH[1], "distortion_model": "OPENCV"}
    p = pipeline.MasksParams(backend="none")
    fl = {"fwd": np.zeros((192, 256, 2), np.float32), "fwd_valid": np.ones((192, 256), bool)}
    for summary, border in ((lensed, True), ({"frame_indices": [0, 1], "width": 256, "height": 192}, False)):
        view = SimpleNamespace(source=src, len=lambda s: 2, summary=lambda s, d=summary: d)
        items = pipeline._mask_items(view, p)
        assert ("source_size" in items[0]) == border and "user_mask" not in items[0]
        assert (pipeline._mask_summary(view, p) is not None) == border
        assert len(pipeline._user_mask_items(view, p)) == (2 if border else 0)
        inputs = {**{k: v.value for k, v in items[0].items() if hasattr(v, "value")}, "chain": [fl], "direction": "fwd"}
        out = pipeline.run_masks(inputs, p, None)
        if not border:
            assert "user_keep" not in out and out["static"].all()
            continue
        mx, my = lens.undistort_maps(lens.parse_camera(",".join(map(str, TUM_SYNTH[0] + TUM_SYNTH[1]))), (256, 192))
        outside = (mx < -0.5) | (mx > 255.5) | (my < -0.5) | (my > 191.5)
        keep = out["user_keep"] > 0
        assert not keep[outside].any() and out["static"][outside].max() == 0
        assert keep.mean() > 0.9 and keep[60:130, 80:180].all()
