"""Hostile round three (issue 36), masks and settings: each failure of the issue that was a wrong
result with exit 0 or a traceback on aaaa9c0, as a test.

* ``--masks`` PNGs are judged on their decoded values, whatever the encoding (16-bit 0/1 and 0/200,
  grey + alpha, RGBA cut-outs, palette); a PNG named after no frame while others are is exit 2
  (aaaa9c0: read as 8-bit colour, so a 16-bit 0/1 mask or a mask in alpha masked nothing; a stray
  name fell back to frame order silently);
* frames masked almost entirely or black: a warning, depth 0 / confidence 0, a report signal; a
  clip with nothing to solve is exit 2 (aaaa9c0: exit 0, depth 1.0 everywhere, "valid depth 100 % ok");
* ``inf`` / ``nan`` and nonsense ranges in --set, TOML and --grid: exit 2 naming the key
  (aaaa9c0: ``keyframes.delta=inf`` a traceback in key hashing, ``steps=-5`` accepted);
* ``export --voxel`` / ``--tsdf-voxel`` nan, inf, negative: exit 2 naming the option (aaaa9c0: a
  one-point PLY, a traceback);
* sweep: a 300-character grid value gets a short run folder name, a missing INPUT is refused
  before the sweep folder is made, a dangling symlink as --out is one clear line.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import cli
from PIL import Image

from gcvd_flow import pipeline
from gcvd_flow.engine.errors import UsageError
from gcvd_flow.io.formats import DatasetError, read_user_mask_png
from gcvd_flow.stages.frontend import solvable

H, W = 48, 64


def _pattern(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = np.zeros((H, W), bool)
    out[10:30, 20:45] = True
    out |= rng.random((H, W)) < 0.05
    return out


def _one_line_exit_2(r) -> str:
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert "Traceback" not in r.stderr, r.stderr
    errs = [ln for ln in r.stderr.splitlines() if ln.strip() and not ln.startswith(("camera:", "warning:"))]
    assert len(errs) == 1 and errs[0].startswith("gcvd-flow: error:"), r.stderr
    return errs[0]


# ------------------------------------------------------------------------------ mask encodings


def _write(path: Path, kind: str, out: np.ndarray) -> None:
    """``out`` (True = leave out) encoded as a segmentation tool might."""
    m8 = out.astype(np.uint8)
    rng = np.random.default_rng(1)
    colour = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    colour[::7, ::5] = 0  # black pixels inside a cut-out: alpha decides, not the colour
    if kind == "grey8_255":
        cv2.imwrite(str(path), m8 * 255)
    elif kind == "grey8_1":
        cv2.imwrite(str(path), m8)
    elif kind == "grey16_1":
        cv2.imwrite(str(path), out.astype(np.uint16))
    elif kind == "grey16_200":
        cv2.imwrite(str(path), out.astype(np.uint16) * 200)
    elif kind == "rgb_red":
        Image.fromarray(np.stack([m8 * 255, m8 * 0, m8 * 0], -1), "RGB").save(path)
    elif kind == "rgb16":
        cv2.imwrite(str(path), np.stack([out.astype(np.uint16) * 3] * 3, -1))
    elif kind == "rgba_opaque":  # colour mask, alpha 255 everywhere (an editor's RGBA export)
        Image.fromarray(np.dstack([m8 * 255] * 3 + [np.full((H, W), 255, np.uint8)]), "RGBA").save(path)
    elif kind == "rgba_alpha_only":  # black colour, the mask in alpha
        Image.fromarray(np.dstack([m8 * 0] * 3 + [m8 * 255]), "RGBA").save(path)
    elif kind == "rgba_cutout":  # the object's own colours, opaque on the object, transparent elsewhere
        Image.fromarray(np.dstack([colour, m8 * 255]), "RGBA").save(path)
    elif kind == "la_alpha":
        Image.fromarray(np.dstack([m8 * 0, m8 * 255]), "LA").save(path)
    elif kind == "rgba16_alpha":
        cv2.imwrite(str(path), np.dstack([np.zeros((H, W, 3), np.uint16), out.astype(np.uint16) * 65535]))
    elif kind == "palette":
        Image.fromarray(m8 * 255, "L").convert("P").save(path)
    else:
        raise AssertionError(kind)


KINDS = ["grey8_255", "grey8_1", "grey16_1", "grey16_200", "rgb_red", "rgb16", "rgba_opaque", "rgba_alpha_only",
         "rgba_cutout", "la_alpha", "rgba16_alpha", "palette"]


@pytest.mark.parametrize("kind", KINDS)
def test_every_mask_encoding_masks_its_decoded_non_zero_pixels(tmp_path, kind):
    out = _pattern()
    p = tmp_path / "m.png"
    _write(p, kind, out)
    got = pipeline._MaskFile(str(p))()  # the loader the user_masks / masks stages use
    assert got.shape == (H, W) and got.dtype == bool
    assert np.array_equal(got, out), f"{kind}: {int((got != out).sum())} pixels differ"


def test_alpha_with_one_value_everywhere_carries_no_mask(tmp_path):
    out = _pattern()
    m8 = out.astype(np.uint8) * 255
    clear = tmp_path / "clear.png"  # fully transparent, colour left in: nothing is drawn
    Image.fromarray(np.dstack([m8, m8, m8, np.zeros((H, W), np.uint8)]), "RGBA").save(clear)
    assert not read_user_mask_png(clear).any()
    half = tmp_path / "half.png"  # one semi-transparent overlay: the colour decides
    Image.fromarray(np.dstack([m8, m8 * 0, m8 * 0, np.full((H, W), 128, np.uint8)]), "RGBA").save(half)
    assert np.array_equal(read_user_mask_png(half), out)


def test_a_16_bit_mask_reaches_the_user_masks_stage(tmp_path):
    """The stage output, not only the loader: aaaa9c0's user_keep for a 16-bit 0/1 mask was all ones."""
    out = np.zeros((72, 96), bool)
    out[20:40, 30:60] = True
    p = tmp_path / "m.png"
    cv2.imwrite(str(p), out.astype(np.uint16))
    keep = pipeline.run_user_masks({"user_mask": pipeline._MaskFile(str(p))(), "source_size": [96, 72],
                                    "size": [48, 36]}, None, None)["user_keep"]
    assert keep.shape == (36, 48) and keep[10:20, 15:30].max() == 0 and keep.sum() == 36 * 48 - 10 * 15


def test_a_file_that_is_not_a_png_is_one_line(tmp_path):
    p = tmp_path / "m.png"
    ok, jpg = cv2.imencode(".jpg", np.full((H, W), 255, np.uint8))
    p.write_bytes(jpg.tobytes())
    with pytest.raises(DatasetError, match="not a PNG"):
        read_user_mask_png(p)
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + b"junk" * 10)
    with pytest.raises(DatasetError, match="not a readable"):
        read_user_mask_png(p)


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("clip") / "clip"
    cli("synth", str(d), "--frames", "6", "--size", "96x72", "--trajectory", "loop", check=True)
    return d


def _mask_dir(folder: Path, names: list[str]) -> Path:
    folder.mkdir()
    for nm in names:
        cv2.imwrite(str(folder / f"{nm}.png"), np.zeros((72, 96), np.uint8))
    return folder


def test_a_mask_named_after_no_frame_is_exit_2_naming_it(clip, tmp_path):
    # six PNGs for six frames, five named as frames and one not: aaaa9c0 fell back to frame order
    masks = _mask_dir(tmp_path / "m", [f"{i:06d}" for i in range(5)] + ["000006"])
    r = cli("run", str(clip), "--out", str(tmp_path / "run"), "--cache", str(tmp_path / "cache"), "--masks",
            str(masks), "--until", "user_masks", "--profile", "fast")
    line = _one_line_exit_2(r)
    assert "000006.png" in line and "matches no frame" in line
    # none named as a frame: frame order, as documented
    order = _mask_dir(tmp_path / "o", [f"mask_{i}" for i in range(6)])
    r = cli("run", str(clip), "--out", str(tmp_path / "run2"), "--cache", str(tmp_path / "cache"), "--masks",
            str(order), "--until", "user_masks", "--profile", "fast")
    assert r.returncode == 0, r.stderr


# ------------------------------------------------------------------------------ nothing to solve


def test_frame_problem_flags_masked_and_textureless_frames_only():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    assert solvable.frame_problem(img) is None
    assert "no texture" in solvable.frame_problem(np.zeros((H, W, 3), np.uint8))
    assert "no texture" in solvable.frame_problem(np.full((H, W, 3), 128, np.uint8))
    keep = np.ones((H, W), np.uint8)
    keep[:, : int(W * 0.97)] = 0  # 3 % left
    assert "masked" in solvable.frame_problem(img, keep)
    keep[:, : int(W * 0.5)] = 1  # half left
    assert solvable.frame_problem(img, keep) is None
    flat = img.copy()
    flat[:, : W // 2] = 0  # the kept half is black: nothing to match there
    assert "no texture" in solvable.frame_problem(flat, (np.arange(W) < W // 2)[None].repeat(H, 0))
    assert solvable.unsolvable_frames([img, np.zeros_like(img), img]) == [(1, "no texture (a black or blank frame)")]


def test_a_clip_with_nothing_to_solve_is_exit_2(clip, tmp_path):
    black = tmp_path / "black"
    (black / "frames").mkdir(parents=True)
    for f in sorted((clip / "frames").iterdir()):
        cv2.imwrite(str(black / "frames" / f.name), np.zeros((72, 96, 3), np.uint8))
    r = cli("run", str(black), "--out", str(tmp_path / "rb"), "--cache", str(tmp_path / "cache"), "--profile", "fast")
    assert "nothing to solve" in _one_line_exit_2(r) and not (tmp_path / "rb" / "depth").exists()
    every = tmp_path / "every"
    every.mkdir()
    for f in sorted((clip / "frames").iterdir()):
        cv2.imwrite(str(every / f.name), np.full((72, 96), 1, np.uint16))  # 16-bit, every pixel masked
    r = cli("run", str(clip), "--out", str(tmp_path / "rm"), "--cache", str(tmp_path / "cache"), "--masks", str(every),
            "--profile", "fast")
    assert "masked" in _one_line_exit_2(r) and not (tmp_path / "rm" / "depth").exists()


@pytest.fixture(scope="module")
def part_run(tmp_path_factory) -> dict[str, Path]:
    """A 16-frame clip with frames 5-7 black, run to the end."""
    d = tmp_path_factory.mktemp("part")
    clip = d / "clip"
    cli("synth", str(clip), "--frames", "16", "--size", "128x96", check=True)
    for i in (5, 6, 7):
        cv2.imwrite(str(clip / "frames" / f"{i:06d}.png"), np.zeros((96, 128, 3), np.uint8))
    r = cli("run", str(clip), "--out", str(d / "run"), "--cache", str(d / "cache"), "--profile", "fast",
            "--set", "depth_fusion.enabled=false")
    assert r.returncode == 0, r.stderr
    return {"clip": clip, "run": d / "run", "cache": d / "cache", "stderr": r.stderr}  # type: ignore[dict-item]


def test_black_frames_are_marked_invalid_warned_and_reported(part_run, tmp_path):
    run = part_run["run"]
    warn = [ln for ln in str(part_run["stderr"]).splitlines() if ln.startswith("warning:") and "nothing to solve" in ln]
    assert len(warn) == 1 and "source frames 5-7" in warn[0], part_run["stderr"]
    for i in range(16):
        d, c = np.load(run / "depth" / f"{i:06d}.npy"), np.load(run / "confidence" / f"{i:06d}.npy")
        if i in (5, 6, 7):
            assert not d.any() and not c.any(), i  # invalid, never the optimiser's constant guess
        else:
            assert (d > 0).mean() > 0.5, i
    cams = json.loads((run / "cameras.json").read_text())
    assert [u["frame"] for u in cams["unsolvable_frames"]] == [5, 6, 7]
    r = cli("report", str(run), "--to", str(tmp_path / "r.html"), "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["verdict"] != "good"
    html = (tmp_path / "r.html").read_text()
    assert "frames with nothing to solve" in html and "3 of 16" in html
    assert "100.0 % of pixels" not in html.split("valid depth", 1)[1][:200]


# ------------------------------------------------------------------------------ settings


@pytest.mark.parametrize("item,key", [("keyframes.delta=inf", "keyframes.delta"), ("keyframes.delta=nan", "keyframes.delta"),
                                      ("keyframes.delta=-inf", "keyframes.delta"),
                                      ("association.threshold=nan", "association.threshold"),
                                      ("optimize_keyframes.steps=-5", "optimize_keyframes.steps"),
                                      ("optimize_keyframes.points=0", "optimize_keyframes.points"),
                                      ("losses.w_flow=-1", "losses.w_flow"),
                                      ("optimize_segments.loss_scale=0", "optimize_segments.loss_scale"),
                                      ("optimize_keyframes.taus=[0,1]", "optimize_keyframes.taus"),
                                      ("pose_graph.max_iterations=-1", "pose_graph.max_iterations"),
                                      ("optimize_keyframes.overlap=40", "optimize_keyframes")])
def test_non_finite_and_out_of_range_settings_are_exit_2_naming_the_key(clip, tmp_path, item, key):
    r = cli("run", str(clip), "--out", str(tmp_path / "run"), "--cache", str(tmp_path / "cache"), "--set", item)
    assert f"config key '{key}'" in _one_line_exit_2(r)
    assert not (tmp_path / "run").exists()


def test_non_finite_settings_in_a_toml_file_and_a_grid_are_exit_2(clip, tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[keyframes]\ndelta = inf\n")
    r = cli("plan", str(clip), "--out", str(tmp_path / "run"), "--config", str(cfg))
    assert "config key 'keyframes.delta'" in _one_line_exit_2(r)
    r = cli("sweep", str(clip), "--out", str(tmp_path / "sw"), "--grid", "keyframes.delta=0.1,nan")
    assert "keyframes.delta" in _one_line_exit_2(r) and not (tmp_path / "sw").exists()


# ------------------------------------------------------------------------------ export options


@pytest.mark.parametrize("args,flag", [(("--voxel", "nan"), "--voxel"), (("--voxel", "inf"), "--voxel"),
                                       (("--voxel", "-1"), "--voxel"), (("--tsdf-voxel", "nan"), "--tsdf-voxel"),
                                       (("--tsdf-voxel", "inf"), "--tsdf-voxel"), (("--tsdf-voxel", "0"), "--tsdf-voxel"),
                                       (("--fps", "inf"), "--fps")])
def test_non_finite_export_sizes_are_exit_2_naming_the_option(part_run, tmp_path, args, flag):
    r = cli("export", str(part_run["run"]), "--format", "ply,tsdf", "--to", str(tmp_path / "e"), *args)
    assert _one_line_exit_2(r).startswith(f"gcvd-flow: error: {flag} ")
    assert not (tmp_path / "e").exists()


# ------------------------------------------------------------------------------ sweep arguments


def test_a_long_grid_value_gets_a_short_unique_run_folder_name():
    from gcvd_flow.engine import sweep

    # two values that differ only past the cut (aaaa9c0: "File name too long" when the run started)
    long_a, long_b = '"' + "a" * 300 + 'b"', '"' + "a" * 300 + 'c"'
    combos = sweep.combinations(sweep.parse_grids([f"masks.user_dir={long_a},{long_b},x"]))
    names = [c.name for c in combos]
    assert all(len(n.encode()) <= sweep.MAX_NAME_BYTES for n in names) and len(set(names)) == 3
    assert names[2] == "masks.user_dir=x"  # short names as before
    assert names[0].startswith('masks.user_dir="aaaa') and "~" in names[0]
    assert combos[0].sets == (f"masks.user_dir={long_a}",)  # the value itself is not cut
    delta = "0.1" + "0" * 297 + "1"  # a float spelled in 300 characters
    (c,) = sweep.combinations(sweep.parse_grids([f"keyframes.delta={delta}"]))
    assert len(c.name.encode()) <= sweep.MAX_NAME_BYTES


def test_sweep_checks_input_and_out_before_making_anything(clip, tmp_path):
    r = cli("sweep", str(tmp_path / "nope"), "--out", str(tmp_path / "sw"), "--grid", "keyframes.delta=0.1,0.2")
    assert "no such file or directory" in _one_line_exit_2(r) and not (tmp_path / "sw").exists()
    link = tmp_path / "dangling"
    os.symlink(tmp_path / "gone" / "x", link)
    r = cli("sweep", str(clip), "--out", str(link), "--grid", "keyframes.delta=0.1,0.2")
    line = _one_line_exit_2(r)
    assert "symbolic link" in line and "does not exist" in line and "File exists" not in line
    with pytest.raises(UsageError, match="symbolic link"):
        from gcvd_flow.engine.outputs import check_out_dir

        check_out_dir(link / "sub")
