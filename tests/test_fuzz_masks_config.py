"""Seeded fuzz of issue 36's surfaces: ``--masks`` encodings and names, and hostile setting values
in ``--set``, TOML and ``sweep --grid``. Every case either gives the right result (the decoded
mask equals the one encoded; the frame -> mask mapping is the documented one; a setting is taken
as typed) or is exit 2 with one line ``gcvd-flow: error: ...`` — never a traceback, never a
silent wrong result. Commands run in-process (``gcvd_flow.cli.main``) on one 6-frame clip.
``GCVD_FUZZ_SEED`` / ``GCVD_FUZZ_SCALE`` vary and widen it.
"""

from __future__ import annotations

import os
import random
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import cli, run_main

from gcvd_flow import pipeline
from gcvd_flow.engine.errors import UsageError
from gcvd_flow.io.formats import read_user_mask_png

SEED = int(os.environ.get("GCVD_FUZZ_SEED", "36"))
SCALE = int(os.environ.get("GCVD_FUZZ_SCALE", "1"))
H, W = 72, 96


def check_clean(what: str, code: int, err: str) -> None:
    assert "Traceback" not in err and "internal error" not in err, f"{what}\n{err}"
    if code == 2:
        lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith(("warning:", "camera:"))]
        assert len(lines) == 1 and lines[0].startswith("gcvd-flow: error:"), f"{what}\n{err}"
    else:
        assert code == 0, f"{what}: exit {code}\n{err}"


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("fz") / "clip"
    cli("synth", str(d), "--frames", "6", "--size", f"{W}x{H}", "--trajectory", "loop", check=True)
    return d


# ------------------------------------------------------------------------------ mask encodings


def _pattern(rng: random.Random) -> np.ndarray:
    r = np.random.default_rng(rng.randrange(2 ** 32))
    kind = rng.randrange(5)
    if kind == 0:
        return np.zeros((H, W), bool)
    if kind == 1:
        return np.ones((H, W), bool)
    if kind == 2:  # one pixel
        out = np.zeros((H, W), bool)
        out[rng.randrange(H), rng.randrange(W)] = True
        return out
    return r.random((H, W)) < rng.choice([0.01, 0.3, 0.9])


def _encode(path: Path, out: np.ndarray, rng: random.Random) -> str:
    """Write ``out`` (True = leave out) in a random encoding the reader must decode to ``out``."""
    r = np.random.default_rng(rng.randrange(2 ** 32))
    deep = rng.random() < 0.5
    top = 65535 if deep else 255
    dt = np.uint16 if deep else np.uint8
    value = r.integers(1, top + 1, (H, W)).astype(dt)  # any non-zero value leaves the pixel out
    grey = np.where(out, value, 0).astype(dt)
    varying = out.any() and not out.all()
    mode = rng.choice(["grey", "rgb", "rgba_opaque", "rgba_const"] + (["alpha", "cutout"] if varying else []))
    if mode == "grey":
        cv2.imwrite(str(path), grey)
    elif mode == "rgb":  # a non-zero value in one random channel
        rgb = np.zeros((H, W, 3), dt)
        rgb[..., rng.randrange(3)] = grey
        cv2.imwrite(str(path), rgb)
    elif mode in ("rgba_opaque", "rgba_const"):  # alpha one value everywhere: the colour decides
        a = top if mode == "rgba_opaque" else rng.randrange(1, top + 1)
        cv2.imwrite(str(path), np.dstack([grey, grey * 0, grey * 0, np.full((H, W), a, dt)]))
    elif mode == "alpha":  # the mask only in alpha, black colour
        cv2.imwrite(str(path), np.dstack([grey * 0] * 3 + [grey]))
    else:  # a cut-out: random colour (black included), alpha = the mask
        colour = r.integers(0, top + 1, (H, W, 3)).astype(dt)
        colour[r.random((H, W)) < 0.2] = 0
        cv2.imwrite(str(path), np.dstack([colour, grey]))
    return f"{mode} {'16' if deep else '8'}-bit"


def _broken(path: Path, rng: random.Random) -> str:
    kind = rng.randrange(5)
    good = cv2.imencode(".png", np.zeros((H, W), np.uint8))[1].tobytes()
    data = [b"", good[: rng.randrange(8, len(good) - 1)], cv2.imencode(".jpg", np.zeros((H, W), np.uint8))[1].tobytes(),
            bytes(rng.randrange(256) for _ in range(200)), good[:8] + bytes(rng.randrange(256) for _ in range(100))][kind]
    path.write_bytes(data)
    return ["empty", "truncated", "jpeg", "random bytes", "png header + junk"][kind]


def test_fuzz_mask_encodings_decode_to_the_encoded_mask(tmp_path):
    rng = random.Random(SEED)
    for case in range(60 * SCALE):
        p = tmp_path / f"{case}.png"
        if rng.random() < 0.15:
            what = _broken(p, rng)
            try:
                read_user_mask_png(p)
            except UsageError as exc:  # one line naming the file
                assert str(p) in str(exc) and "\n" not in str(exc), (what, exc)
            else:
                raise AssertionError(f"case {case}: a broken PNG ({what}) was read")
            continue
        out = _pattern(rng)
        what = _encode(p, out, rng)
        got = pipeline._MaskFile(str(p))()
        assert np.array_equal(got, out), f"case {case} ({what}): {int((got != out).sum())} pixels differ"


def test_fuzz_masks_through_the_cli_are_exit_0_or_one_line(clip, tmp_path):
    """Mask folders with a random encoding per file, some broken or mis-sized: `run --until
    user_masks` ends in exit 0 or exit 2 with one line."""
    rng = random.Random(SEED + 1)
    cache = tmp_path / "cache"
    for case in range(6 * SCALE):
        d = tmp_path / f"m{case}"
        d.mkdir()
        trouble = rng.choice(["none", "broken", "size"])
        bad = rng.randrange(6)
        for i in range(6):
            p = d / f"{i:06d}.png"
            if i == bad and trouble == "broken":
                _broken(p, rng)
            elif i == bad and trouble == "size":
                cv2.imwrite(str(p), np.zeros((H + 1, W), np.uint8))
            else:
                _encode(p, _pattern(rng), rng)
        code, _, err = run_main("run", clip, "--out", tmp_path / f"r{case}", "--cache", cache, "--masks", d,
                                "--until", "user_masks", "--jobs", "1", "--profile", "fast")
        check_clean(f"case {case} ({trouble})", code, err)
        assert (code == 0) == (trouble == "none"), f"case {case} ({trouble}): exit {code}\n{err}"


# ------------------------------------------------------------------------------ mask names


def _names(rng: random.Random, frames: list[str]) -> tuple[list[str], str]:
    """Mask file names and what the reader must do: "name", "order", "error" or "missing K"
    (an error when source frame K is selected, else "name")."""
    n = len(frames)
    kind = rng.randrange(7)
    if kind == 0:
        return [f"{f}.png" for f in frames], "name"
    if kind == 1:  # named as the frames, shuffled on disk (names decide, not order)
        return [f"{f}.png" for f in rng.sample(frames, n)], "name"
    if kind == 2:  # no frame's name, one per frame: frame order
        return [f"mask {k} é.png" for k in range(n)], "order"
    if kind == 3:  # named as the frames but one stray (the off-by-one numbering of a tool)
        return [f"{k + 1:06d}.png" for k in range(n)], "error"
    if kind == 4:  # one frame's mask missing: refused when that frame is selected
        drop = rng.randrange(n)
        return [f"{f}.png" for j, f in enumerate(frames) if j != drop], f"missing {drop}"
    if kind == 5:  # the frames' names plus an unrelated PNG
        return [f"{f}.png" for f in frames] + ["README.png"], "error"
    return [f"m{k}.PNG" for k in range(n + rng.choice([-1, 1]))], "error"  # wrong count in frame order


def test_fuzz_mask_names_map_by_name_or_order_or_exit_2(clip, tmp_path):
    from types import SimpleNamespace

    from gcvd_flow.io.sources import natural_key, open_source

    rng = random.Random(SEED + 2)
    src = open_source(str(clip))
    frames = [Path(nm).stem for nm in src.names]
    for case in range(30 * SCALE):
        d = tmp_path / f"n{case}"
        d.mkdir()
        names, expect = _names(rng, frames)
        for nm in names:
            cv2.imwrite(str(d / nm), np.zeros((H, W), np.uint8))
        sel = sorted(rng.sample(range(len(frames)), rng.randrange(2, len(frames) + 1)))
        if expect.startswith("missing"):
            expect = "error" if int(expect.split()[1]) in sel else "name"
        view = SimpleNamespace(source=src, len=lambda s, sel=sel: len(sel), summary=lambda s, sel=sel: {"frame_indices": sel})
        p = pipeline.MasksParams(backend="none", user_dir=str(d))
        try:
            files = [Path(it["user_mask"].loader.path).name for it in pipeline._mask_items(view, p)]
        except UsageError as exc:
            assert expect == "error", f"case {case} {names}: {exc}"
            assert "\n" not in str(exc) and str(d) in str(exc), exc
            continue
        if expect == "name":
            assert files == [f"{frames[i]}.png" for i in sel], (case, names, files)
        else:
            assert expect == "order", f"case {case}: {names} should have been refused, got {files}"
            ordered = sorted(names, key=natural_key)
            assert files == [ordered[i] for i in sel], (case, names, files)


# ------------------------------------------------------------------------------ settings and grids

HOSTILE = ["inf", "-inf", "nan", "+nan", "1e999", "-1e999", "10" * 200, "-5", "-1", "0", "1e300", "-1e300", "1e-320",
           '"' + "x" * 300 + '"', '""', "[]", "[inf]", "[1, nan]", "{a = 1}", "true", "'$\\foo$'", "0.5", "3"]


def _leaf_keys() -> list[str]:
    from gcvd_flow.engine.config import known_keys

    keys = known_keys(pipeline.GCVDConfig)
    return [k for k in keys if not any(o.startswith(k + ".") for o in keys)]


def test_fuzz_hostile_setting_values_are_taken_or_refused_naming_the_key(clip, tmp_path):
    rng = random.Random(SEED + 3)
    keys = _leaf_keys()
    for case in range(40 * SCALE):
        key, value = rng.choice(keys), rng.choice(HOSTILE)
        how = rng.choice(["set", "toml"])
        if how == "set":
            args: tuple = ("--set", f"{key}={value}")
        else:
            sec, _, name = key.rpartition(".")
            cfg = tmp_path / f"c{case}.toml"
            cfg.write_text(f"[{sec}]\n{name} = {value}\n")
            args = ("--config", cfg)
        code, _, err = run_main("plan", clip, "--out", tmp_path / f"p{case}", *args)
        check_clean(f"case {case}: {how} {key}={value[:40]}", code, err)
        if value in ("inf", "-inf", "nan", "+nan", "1e999", "-1e999", "[inf]", "[1, nan]"):
            assert code == 2, f"{key}={value} accepted"
        if code == 2 and "config key" in err:
            assert f"'{key.split('.')[0]}" in err, err  # the key (or its section, for a cross-field rule)
        assert not (tmp_path / f"p{case}").exists()  # plan is a dry run


def test_fuzz_grid_values_fail_at_parse_time_or_get_a_usable_run_folder(clip, tmp_path):
    from gcvd_flow.engine import api, sweep

    rng = random.Random(SEED + 4)
    keys = _leaf_keys()
    spec = api.load_spec("gcvd")
    for case in range(30 * SCALE):
        grids = [f"{k}={','.join(rng.sample(HOSTILE, rng.randrange(1, 4)))}"
                 for k in rng.sample(keys, rng.randrange(1, 3))]
        out = tmp_path / f"s{case}"
        base = api.Invocation(input=str(clip), out=str(out), pipeline="gcvd")
        try:
            plan = sweep.prepare(str(clip), str(out), base, grids, max_runs=64)
        except UsageError as exc:
            assert "\n" not in str(exc) and str(exc).startswith("--grid"), (grids, exc)
        else:
            names = [c.name for c in plan.combos]
            assert len(set(names)) == len(names), grids
            for nm in names:
                assert 0 < len(nm.encode()) <= sweep.MAX_NAME_BYTES and "/" not in nm and not nm.startswith("."), nm
            for c in plan.combos:  # each run's config builds, keys included (aaaa9c0: inf broke key hashing)
                from gcvd_flow.engine.config import build_config
                from gcvd_flow.engine.keys import key_of

                key_of(build_config(spec.config_model, spec.profiles, None, None, list(c.sets)).model_dump())
        assert not out.exists(), grids  # nothing is made before the sweep runs
