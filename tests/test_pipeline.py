"""The GCVD pipeline's first half through the CLI: caching contract, inputs, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import SHARED_DATA, by_stage, cli, cli_json

PRE = ("ingest", "flow", "masks", "priors")


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("clip") / "orbit"
    cli("synth", str(out), "--frames", "32", "--trajectory", "orbit", "--size", "160x120", check=True)
    return out


def test_synth_writes_the_generic_layout(clip):
    assert len(list((clip / "frames").glob("*.png"))) == 32
    assert len(list((clip / "gt" / "depth").glob("*.png"))) == 32
    assert len((clip / "gt" / "poses.txt").read_text().splitlines()) == 32
    assert len((clip / "intrinsics.txt").read_text().split()) == 4


def test_caching_contract(clip, tmp_path):
    out, cache = tmp_path / "run", tmp_path / "cache"

    def run(*sets: str) -> dict:
        """Run up to association, then priors (not needed by association): merged per stage."""
        args = [a for s in sets for a in ("--set", s)]
        res = {}
        for until in ("association", "priors"):  # the first run's report of a stage counts
            for name, rep in by_stage(cli_json("run", str(clip), "--out", str(out), "--cache", str(cache),
                                               "--until", until, *args)).items():
                res.setdefault(name, rep)
        return res

    first = run("ingest.end=24")
    assert first["ingest"]["executed"] == 24 and first["flow"]["executed"] == 23
    assert first["priors"]["executed"] == 24
    again = run("ingest.end=24")
    assert all(s["executed"] == 0 for s in again.values()), again
    # a keyframe threshold change re-runs keyframes and what follows only
    kf = run("ingest.end=24", "keyframes.delta=0.15")
    assert all(kf[s]["executed"] == 0 for s in PRE), kf
    assert kf["keyframes"]["executed"] == 1
    # extending the clip by 8 frames computes only the new frames' items
    ext = run("ingest.end=32")
    assert ext["ingest"]["executed"] == 8 and ext["ingest"]["cached"] == 24
    assert ext["flow"]["executed"] == 8
    assert ext["masks"]["executed"] == 8
    assert ext["priors"]["executed"] == 8


def test_plan_reports_reasons(clip, tmp_path):
    out, cache = tmp_path / "run", tmp_path / "cache"
    cli_json("run", str(clip), "--out", str(out), "--cache", str(cache), "--until", "keyframes",
             "--set", "ingest.end=16")
    plan = by_stage(cli_json("plan", str(clip), "--out", str(out), "--cache", str(cache),
                             "--set", "ingest.end=16", "--set", "flow.preset=fast"))
    assert plan["ingest"]["action"] == "cached"
    assert plan["flow"]["action"] == "run"
    assert any("flow.preset changed: 'fine-wide' -> 'fast'" in r for r in plan["flow"]["reasons"])
    assert plan["masks"]["action"] == "run"


def _one_line_exit2(p, needle: str) -> None:
    assert p.returncode == 2, p.stderr
    lines = [l for l in p.stderr.strip().splitlines() if not l.startswith("camera:")]
    assert len(lines) == 1 and needle in lines[0], p.stderr
    assert "Traceback" not in p.stderr


def _run(inp, tmp_path, *extra):
    return cli("run", str(inp), "--out", str(tmp_path / "o"), "--cache", str(tmp_path / "c"), *extra)


def test_missing_input(tmp_path):
    _one_line_exit2(_run(tmp_path / "nothing.mp4", tmp_path), "nothing.mp4")


def test_corrupt_video(tmp_path):
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    _one_line_exit2(_run(bad, tmp_path), "bad.mp4")


def _write_video(path: Path, n: int = 30, size=(96, 64)) -> bool:
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, size)
    if not vw.isOpened():
        return False
    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, (size[1] + 40, size[0] + 40, 3), dtype=np.uint8)
    for i in range(n):
        vw.write(np.ascontiguousarray(base[i % 40: i % 40 + size[1], :size[0]]))
    vw.release()
    return True


def test_video_input_and_truncated_video(tmp_path):
    good = tmp_path / "clip.avi"
    if not _write_video(good):
        pytest.skip("this OpenCV build cannot write MJPG/AVI (needed to make a test video)")
    doc = cli_json("run", str(good), "--out", str(tmp_path / "o1"), "--cache", str(tmp_path / "c1"),
                   "--until", "ingest")
    assert by_stage(doc)["ingest"]["executed"] == 30
    cut = tmp_path / "cut.avi"
    data = good.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    p = _run(cut, tmp_path)
    _one_line_exit2(p, "cut.avi")
    assert "fail" in p.stderr or "corrupt" in p.stderr or "truncated" in p.stderr


def test_single_frame_and_empty_folder(tmp_path):
    one = tmp_path / "one"
    one.mkdir()
    cv2.imwrite(str(one / "a.png"), np.zeros((32, 32, 3), np.uint8))
    _one_line_exit2(_run(one, tmp_path), "need at least 2")
    empty = tmp_path / "empty"
    empty.mkdir()
    _one_line_exit2(_run(empty, tmp_path), "no images")


def test_mixed_frame_sizes_named_and_not_cached(tmp_path):
    d = tmp_path / "mixed"
    d.mkdir()
    rng = np.random.default_rng(0)
    for i in range(4):
        shape = (48, 64, 3) if i != 2 else (40, 64, 3)
        cv2.imwrite(str(d / f"{i:03d}.png"), rng.integers(0, 256, shape, dtype=np.uint8))
    p = _run(d, tmp_path, "--until", "ingest")
    _one_line_exit2(p, "002.png")
    assert not (tmp_path / "o" / "run.json").exists()


@pytest.mark.parametrize("intr", ["1,2,3", "a,b,c,d", "0,500,320,240"])
def test_bad_intrinsics(clip, tmp_path, intr):
    _one_line_exit2(_run(clip, tmp_path, "--intrinsics", intr), "intrinsics")


def test_icl_frames_ingest_through_redwood_layout(tmp_path):
    icl = SHARED_DATA / "icl_livingroom1_micro"
    if not icl.exists():
        pytest.skip(f"ICL-NUIM frames not found at {icl} (../shared/data is absent)")
    p = cli("run", str(icl), "--out", str(tmp_path / "o"), "--cache", str(tmp_path / "c"), "--until", "ingest",
            "--set", "ingest.end=6", "--json", check=True)
    assert by_stage(json.loads(p.stdout))["ingest"]["executed"] == 6
    assert "redwood input 640x480 -> working 256x192, fx=210.0 fy=210.0" in p.stderr


def test_weights_backend_through_the_cli_keys_by_content(clip, tmp_path):
    """flow.backend=raft with a weights file: runs, and the file's digest (not path) is keyed."""
    import torch
    from safetensors.torch import save_file

    from gcvd_flow.stages.models.raft import RAFT

    torch.manual_seed(0)
    model = RAFT()
    w1 = tmp_path / "a" / "raft.safetensors"
    w1.parent.mkdir()
    save_file({k: v.detach().clone().contiguous() for k, v in model.state_dict().items()}, str(w1))
    w2 = tmp_path / "b" / "copy.safetensors"
    w2.parent.mkdir()
    w2.write_bytes(w1.read_bytes())
    base = ["run", str(clip), "--cache", str(tmp_path / "c"), "--until", "flow",
            "--set", "ingest.end=3", "--set", "ingest.long_side=64", "--set", "flow.backend=raft"]
    first = by_stage(cli_json(*base, "--out", str(tmp_path / "o1"), "--set", f"flow.weights={json.dumps(str(w1))}"))
    assert first["flow"]["executed"] == 2
    again = by_stage(cli_json(*base, "--out", str(tmp_path / "o2"), "--set", f"flow.weights={json.dumps(str(w2))}"))
    assert again["flow"]["executed"] == 0 and again["flow"]["cached"] == 2
    p = cli(*base, "--out", str(tmp_path / "o3"), "--set", "flow.weights='/nonexistent/raft.pth'")
    _one_line_exit2(p, "/nonexistent/raft.pth")
