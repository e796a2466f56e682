"""Depth confidence in the exports: depth-png's confidence/ PNGs, nerfstudio's mask_path masks,
the MCAP /camera/confidence channel, --min-confidence for the clouds, and run dirs without
confidence/ (from before it existed).

One tiny run at working resolution 64x48 of a 96x72 synthetic clip, so that nerfstudio's
full-resolution images (96x72) need upsampled masks. depth_fusion is off for speed, so the run's
own confidence is 0 everywhere; a copy of the run dir gets a known confidence pattern (uniform
random values, exact 0.5s, 0 where the depth is invalid, one frame with nothing above 0.5) that
every check compares against. Each output is read back the way its consumer reads it: cv2 /
PIL for PNGs (nerfstudio's own mask reading: PIL, non-zero = use), the mcap reader for MCAP.
"""

from __future__ import annotations

import base64
import json
import shutil
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import cli, cli_json
from PIL import Image

N_FRAMES, W, H = 12, 96, 72  # the clip (source resolution)
WW, WH = 64, 48  # the run's working resolution
QUICK = ["--set", "optimize_keyframes.steps=2", "--set", "optimize_edges.steps=2",
         "--set", "optimize_segments.steps=2", "--set", "depth_fusion.enabled=false",
         "--set", f"ingest.long_side={WW}"]
EMPTY_FRAME = 4  # the frame whose confidence stays below 0.5 everywhere


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("conf")
    clip, run_dir, cache = base / "clip", base / "run", base / "cache"
    cli("synth", str(clip), "--frames", str(N_FRAMES), "--trajectory", "loop", "--size", f"{W}x{H}", check=True)
    cli_json("run", str(clip), "--out", str(run_dir), "--cache", str(cache), *QUICK)
    conf_run = base / "conf-run"
    shutil.copytree(run_dir, conf_run)
    rng = np.random.default_rng(7)
    for k, i in enumerate(_frame_indices(run_dir)):
        depth = np.load(run_dir / "depth" / f"{i:06d}.npy")
        c = rng.uniform(0, 1, depth.shape).astype(np.float32)
        c[::5, ::3] = 0.5  # exactly at the default threshold: kept (>=)
        if k == EMPTY_FRAME:
            c = np.minimum(c, 0.49).astype(np.float32)
        c[~(np.isfinite(depth) & (depth > 0))] = 0.0
        np.save(conf_run / "confidence" / f"{i:06d}.npy", c, allow_pickle=False)
    old = base / "old-run"  # a run dir from before confidence/ existed
    shutil.copytree(run_dir, old)
    shutil.rmtree(old / "confidence")
    return {"clip": clip, "run": run_dir, "conf": conf_run, "old": old, "cache": cache, "base": base}


def _frame_indices(run_dir: Path) -> list[int]:
    return json.loads((run_dir / "cameras.json").read_text())["frame_indices"]


def _conf(run_dir: Path, i: int) -> np.ndarray:
    return np.load(run_dir / "confidence" / f"{i:06d}.npy", allow_pickle=False)


def _export(run_dir: Path, to: Path, fmt: str, *extra: str) -> dict:
    return cli_json("export", str(run_dir), "--format", fmt, "--to", str(to), *extra)


def test_the_run_writes_confidence_the_fixture_replaces(runs):
    idx = _frame_indices(runs["run"])
    assert len(idx) == N_FRAMES
    c = _conf(runs["run"], idx[0])
    assert c.dtype == np.float32 and c.shape == (WH, WW)
    assert not (runs["old"] / "confidence").exists()


def test_confidence_pngs_round_trip_and_depth_pngs_stay_grey(runs, tmp_path):
    doc = _export(runs["conf"], tmp_path, "depth-png")
    assert doc["formats"]["depth-png"]["confidence_dir"] == str(tmp_path / "confidence")
    for i in _frame_indices(runs["conf"]):
        png = cv2.imread(str(tmp_path / "confidence" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert png.dtype == np.uint16 and png.shape == (WH, WW)
        c = _conf(runs["conf"], i)
        assert np.max(np.abs(png / 65535.0 - c.astype(np.float64))) <= 0.5 / 65535 + 1e-9
        assert np.all(png[c == 0] == 0) and np.all(png[c == 1] == 65535)
        depth = cv2.imread(str(tmp_path / "depth" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert depth.dtype == np.uint16 and depth.shape == (WH, WW)  # one grey channel, no alpha


def _nerfstudio_mask(path: Path) -> np.ndarray:
    """What nerfstudio does with a mask_path file (data_utils.get_image_mask_tensor_from_path):
    PIL, one channel, non-zero = use the pixel."""
    return np.array(Image.open(path)).astype(bool)


def test_nerfstudio_masks_full_res(runs, tmp_path):
    """--full-res (default): images 96x72 from the clip; masks at that size: 255 exactly where the
    confidence >= 0.5 at the working-resolution pixel under each image pixel's centre."""
    doc = _export(runs["conf"], tmp_path, "nerfstudio")
    info = doc["formats"]["nerfstudio"]
    assert (info["width"], info["height"], info["resolution"]) == (W, H, "source")
    assert info["masks"]["files"] == N_FRAMES and info["masks"]["min_confidence"] == 0.5
    assert info["masks"]["empty"] == 1
    ns = json.loads((tmp_path / "transforms.json").read_text())
    idx = _frame_indices(runs["conf"])
    for k, fr in enumerate(ns["frames"]):
        assert fr["mask_path"] == f"masks/{idx[k]:06d}.png"
        mask = cv2.imread(str(tmp_path / fr["mask_path"]), cv2.IMREAD_UNCHANGED)
        img = cv2.imread(str(tmp_path / fr["file_path"]), cv2.IMREAD_UNCHANGED)
        assert mask.dtype == np.uint8 and mask.ndim == 2 and mask.shape == img.shape[:2] == (H, W)
        assert set(np.unique(mask)) <= {0, 255}
        keep = _conf(runs["conf"], idx[k]) >= 0.5
        ref = np.where(keep, 255, 0).astype(np.uint8)[_nearest(H, WH)[:, None], _nearest(W, WW)[None, :]]
        np.testing.assert_array_equal(mask, ref)
        assert np.array_equal(_nerfstudio_mask(tmp_path / fr["mask_path"]), ref > 0)
        assert mask.any() == (k != EMPTY_FRAME)
    # the confidence PNGs beside the depth PNGs; no transforms.json key for them (nerfstudio has none)
    assert all((tmp_path / "confidence" / f"{i:06d}.png").is_file() for i in idx)
    keys = set(ns) | {key for fr in ns["frames"] for key in fr}
    assert not any("confidence" in key for key in keys)


def test_nerfstudio_masks_working_res_and_threshold(runs, tmp_path):
    """--no-full-res: masks at 64x48, 255 exactly where confidence >= --min-confidence."""
    doc = _export(runs["conf"], tmp_path, "nerfstudio", "--no-full-res", "--min-confidence", "0.8")
    assert doc["formats"]["nerfstudio"]["masks"]["min_confidence"] == 0.8
    ns = json.loads((tmp_path / "transforms.json").read_text())
    for fr, i in zip(ns["frames"], _frame_indices(runs["conf"])):
        mask = cv2.imread(str(tmp_path / fr["mask_path"]), cv2.IMREAD_UNCHANGED)
        assert mask.dtype == np.uint8 and mask.shape == (WH, WW)
        c = _conf(runs["conf"], i)
        np.testing.assert_array_equal(mask, np.where(c >= np.float32(0.8), 255, 0))
        assert 0 < np.count_nonzero(mask) < mask.size or i == _frame_indices(runs["conf"])[EMPTY_FRAME]


def test_nerfstudio_without_usable_confidence_writes_no_masks(runs, tmp_path):
    """The real run's confidence is 0 everywhere (depth_fusion off): masks would hide every pixel
    from nerfstudio, so none are written (a warning says why); --min-confidence 0: no masks."""
    p = cli("export", str(runs["run"]), "--format", "nerfstudio", "--to", str(tmp_path / "a"), "--json")
    assert p.returncode == 0, p.stderr
    assert "no masks written" in p.stderr
    assert "confidence >= 0.5" in json.loads(p.stdout)["formats"]["nerfstudio"]["masks"]["reason"]
    ns = json.loads((tmp_path / "a" / "transforms.json").read_text())
    assert not any("mask_path" in fr for fr in ns["frames"]) and not (tmp_path / "a" / "masks").exists()
    _export(runs["conf"], tmp_path / "b", "nerfstudio", "--min-confidence", "0")
    ns = json.loads((tmp_path / "b" / "transforms.json").read_text())
    assert not any("mask_path" in fr for fr in ns["frames"]) and not (tmp_path / "b" / "masks").exists()


def test_mcap_confidence_channel(runs, tmp_path):
    import jsonschema
    from mcap.reader import make_reader

    _export(runs["conf"], tmp_path, "mcap")
    msgs: dict[str, list] = {"/camera/confidence": [], "/camera/depth": []}
    with open(tmp_path / "run.mcap", "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=True):
            if channel.topic in msgs:
                assert schema.name == "foxglove.RawImage" and channel.message_encoding == "json"
                msg = json.loads(message.data)
                jsonschema.validate(msg, json.loads(schema.data))
                msgs[channel.topic].append((message.log_time, msg))
    assert len(msgs["/camera/confidence"]) == len(msgs["/camera/depth"]) == N_FRAMES
    for (t, m), (td, _), i in zip(msgs["/camera/confidence"], msgs["/camera/depth"], _frame_indices(runs["conf"])):
        assert t == td  # at the frame's time, like its depth
        assert (m["encoding"], m["width"], m["height"], m["step"]) == ("32FC1", WW, WH, 4 * WW)
        c = np.frombuffer(base64.b64decode(m["data"]), "<f4").reshape(WH, WW)
        np.testing.assert_array_equal(c, _conf(runs["conf"], i))


def test_old_run_dir_without_confidence_exports_without_it(runs, tmp_path):
    doc = _export(runs["old"], tmp_path, "depth-png,nerfstudio,mcap")
    assert doc["formats"]["depth-png"]["confidence_dir"] is None
    assert doc["formats"]["nerfstudio"]["masks"]["reason"] == "the run has no confidence/"
    assert not (tmp_path / "confidence").exists() and not (tmp_path / "masks").exists()
    ns = json.loads((tmp_path / "transforms.json").read_text())
    assert len(ns["frames"]) == N_FRAMES and not any("mask_path" in fr for fr in ns["frames"])
    from mcap.reader import make_reader

    with open(tmp_path / "run.mcap", "rb") as f:
        topics = {c.topic for c in make_reader(f).get_summary().channels.values()}
    assert "/camera/depth" in topics and "/camera/confidence" not in topics


def test_partial_confidence_is_left_out_with_a_warning(runs, tmp_path):
    part = tmp_path / "part"
    shutil.copytree(runs["conf"], part)
    (part / "confidence" / f"{_frame_indices(part)[3]:06d}.npy").unlink()
    p = cli("export", str(part), "--format", "depth-png", "--to", str(tmp_path / "o"))
    assert p.returncode == 0, p.stderr
    assert "no confidence exported" in p.stderr and "missing" in p.stderr
    assert (tmp_path / "o" / "depth").is_dir() and not (tmp_path / "o" / "confidence").exists()


def test_ply_min_confidence_drops_points_only_when_given(runs, tmp_path):
    idx = _frame_indices(runs["conf"])
    depths = [np.load(runs["conf"] / "depth" / f"{i:06d}.npy") for i in idx]
    valid = [np.isfinite(d) & (d > 0) for d in depths]
    all_pts = _export(runs["conf"], tmp_path / "a", "ply")["formats"]["ply"]["points"]
    assert all_pts == sum(int(v.sum()) for v in valid)
    kept = _export(runs["conf"], tmp_path / "b", "ply", "--min-confidence", "0.5")["formats"]["ply"]["points"]
    assert kept == sum(int((v & (_conf(runs["conf"], i) >= 0.5)).sum()) for v, i in zip(valid, idx))
    assert 0 < kept < all_pts


@pytest.mark.parametrize("value", ["nan", "1.5", "-0.1", "inf"])
def test_bad_min_confidence_exits_2_with_one_line(runs, tmp_path, capsys, value):
    from gcvd_flow.cli import main

    rc = main(["export", str(runs["conf"]), "--format", "nerfstudio", "--min-confidence", value,
               "--to", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "--min-confidence" in err[0], err
    assert not (tmp_path / "o").exists()  # checked before anything is written


def _nearest(n_out: int, n_in: int) -> np.ndarray:
    """Input pixel under each output pixel's centre, exactly: pixel i covers [i, i + 1) in pixel
    units, output pixel x's centre is at (x + 0.5) n_in / n_out there."""
    return np.array([int(Fraction(2 * x + 1, 2) * Fraction(n_in, n_out)) for x in range(n_out)])


def _ties(n_out: int, n_in: int) -> np.ndarray:
    """Output pixels whose centre lies exactly on a border between two input pixels."""
    return np.array([(Fraction(2 * x + 1, 2) * Fraction(n_in, n_out)).denominator == 1 for x in range(n_out)])


@pytest.mark.parametrize("src,dst", [((48, 64), (72, 96)), ((5, 7), (13, 11)), ((72, 96), (48, 64)),
                                     ((4, 4), (4, 4)), ((480, 640), (1080, 1920))])
def test_nearest_resize_pixel_centres(src, dst):
    """Exact nearest neighbour with pixel centres; PIL's NEAREST (what nerfstudio resizes masks
    with) agrees wherever a centre is not exactly on a pixel border (there its fixed-point
    arithmetic may pick either neighbour)."""
    from gcvd_flow.exports.confidence import nearest_resize

    img = np.random.default_rng(1).integers(0, 256, src).astype(np.uint8)
    got = nearest_resize(img, dst[1], dst[0])
    assert got.shape == dst
    np.testing.assert_array_equal(got, img[_nearest(dst[0], src[0])[:, None], _nearest(dst[1], src[1])[None, :]])
    pil = np.array(Image.fromarray(img).resize((dst[1], dst[0]), Image.NEAREST))
    clean = ~_ties(dst[0], src[0])[:, None] & ~_ties(dst[1], src[1])[None, :]
    np.testing.assert_array_equal(got[clean], pil[clean])


def test_broken_confidence_file_exits_2_naming_it_before_writing(runs, tmp_path, capsys):
    from gcvd_flow.cli import main

    bad = tmp_path / "bad"
    shutil.copytree(runs["conf"], bad)
    f = bad / "confidence" / f"{_frame_indices(bad)[2]:06d}.npy"
    np.save(f, np.zeros((3, 3), np.float32), allow_pickle=False)
    rc = main(["export", str(bad), "--format", "tum,depth-png", "--to", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and str(f) in err[0], err
    assert not (tmp_path / "o").exists()
