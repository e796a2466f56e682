"""The whole GCVD pipeline on a tiny synthetic loop: outputs, accuracy bound, determinism,
and resuming a killed optimisation from its checkpoint."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, by_stage, cli, cli_json

pytestmark = pytest.mark.slow

# Small and quick: 40 frames at 128x96, few optimisation steps.
QUICK = ["--set", "optimize_keyframes.steps=40", "--set", "optimize_edges.steps=20",
         "--set", "optimize_segments.steps=15", "--set", "optimize_keyframes.checkpoint_every=5"]


@pytest.fixture(scope="module")
def loop_clip(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("e2e") / "loop"
    cli("synth", str(out), "--frames", "40", "--trajectory", "loop", "--size", "128x96", check=True)
    return out


@pytest.fixture(scope="module")
def reference_run(loop_clip, tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("ref")
    cli_json("run", str(loop_clip), "--out", str(work / "run"), "--cache", str(work / "cache"), *QUICK)
    return work / "run"


def test_outputs_and_metrics(reference_run, loop_clip):
    run = reference_run
    poses = (run / "poses.txt").read_text().splitlines()
    assert len(poses) == 40
    depth = sorted((run / "depth").glob("*.npy"))
    assert len(depth) == 40
    d = np.load(depth[0], allow_pickle=False)
    assert d.dtype == np.float32 and d.shape == (96, 128) and (d > 0).mean() > 0.9
    conf = [np.load(p, allow_pickle=False) for p in sorted((run / "confidence").glob("*.npy"))]
    assert len(conf) == 40 and conf[0].shape == (96, 128) and conf[0].dtype == np.float32
    allc = np.stack(conf)
    assert allc.min() >= 0 and allc.max() <= 1 and (allc > 0).mean() > 0.3  # most pixels triangulated
    cams = json.loads((run / "cameras.json").read_text())
    assert cams["width"] == 128 and cams["keyframes"][0] == 0 and cams["keyframes"][-1] == 39
    rj = json.loads((run / "run.json").read_text())
    assert rj["stage_order"] == ["ingest", "user_masks", "calibrate", "flow", "flow_far", "masks", "priors_direct", "priors",
                                  "keyframes", "association",
                                  "optimize_keyframes", "optimize_edges", "pose_graph", "bundle_adjustment",
                                  "optimize_segments", "fusion_samples", "fusion_references", "fusion_flow", "depth_fusion", "depth_filter",
                                  "depth_consensus"]
    m = cli_json("eval", str(run), "--gt", str(loop_clip))
    # loose bounds for a 40-step CPU run at 128x96 (the full-size figures are in docs/benchmarks.md)
    assert m["ate_percent_of_path"] < 5.0, m  # measured 1.8%
    assert m["abs_rel"] < 0.35, m  # measured 0.28 on this 40-frame 128x96 clip


def test_same_inputs_and_seed_give_byte_identical_artifacts(reference_run, loop_clip, tmp_path):
    cli_json("run", str(loop_clip), "--out", str(tmp_path / "run"), "--cache", str(tmp_path / "cache"), *QUICK)
    a = json.loads((reference_run / "run.json").read_text())["stages"]
    b = json.loads((tmp_path / "run" / "run.json").read_text())["stages"]
    assert {k: v["output"] for k, v in a.items()} == {k: v["output"] for k, v in b.items()}
    assert (reference_run / "poses.txt").read_bytes() == (tmp_path / "run" / "poses.txt").read_bytes()


def _checkpoint_saved(cache: Path) -> bool:
    for p in (cache / "records").glob("*/*.json"):
        try:
            if json.loads(p.read_text()).get("record_kind") == "checkpoint":
                return True
        except (OSError, ValueError):
            pass
    return False


def test_killed_optimisation_resumes_from_checkpoint(reference_run, loop_clip, tmp_path):
    cache, out = tmp_path / "cache", tmp_path / "run"
    cmd = [sys.executable, "-m", "gcvd_flow", "run", str(loop_clip), "--out", str(out), "--cache", str(cache), *QUICK]
    p = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 240
    while not _checkpoint_saved(cache):
        assert p.poll() is None, "the run finished before any checkpoint was saved"
        assert time.time() < deadline
        time.sleep(0.05)
    p.send_signal(signal.SIGKILL)
    p.wait()
    res = cli("run", str(loop_clip), "--out", str(out), "--cache", str(cache), *QUICK, "--json", check=True)
    assert "resuming from checkpoint" in res.stderr
    stages = by_stage(json.loads(res.stdout))
    assert stages["flow"]["executed"] == 0 and stages["optimize_keyframes"]["executed"] == 1
    # resumed result == uninterrupted result, byte for byte
    a = json.loads((reference_run / "run.json").read_text())["stages"]
    b = json.loads((out / "run.json").read_text())["stages"]
    assert a["optimize_keyframes"]["output"] == b["optimize_keyframes"]["output"]
    assert a["depth_consensus"]["output"] == b["depth_consensus"]["output"]


def test_pose_graph_lowers_ate_on_the_loop(reference_run, loop_clip):
    """The loop edge (end -> start) enters the pose graph and pulls the drift back: with bundle
    adjustment off in both (since 2026-11-25 its weak prior lets it close the loop by itself, over
    the tracks that hop across the loop edge, so the final poses no longer show the pose graph),
    the run with `pose_graph.enabled=false` (sharing the cache: only pose_graph and what follows
    re-run) ends further from the ground truth. Measured: ATE 1.15 % vs 1.34 % of the path."""
    work = reference_run.parent
    runs = {}
    for name, pg in (("pg", "true"), ("no-pg", "false")):
        out = work / f"run-ba-off-{name}"
        doc = cli_json("run", str(loop_clip), "--out", str(out), "--cache", str(work / "cache"), *QUICK,
                       "--set", f"pose_graph.enabled={pg}", "--set", "bundle_adjustment.enabled=false")
        st = by_stage(doc)
        assert st["optimize_keyframes"]["executed"] == 0 and st["optimize_edges"]["executed"] == 0
        runs[name] = out
    on = cli_json("eval", str(runs["pg"]), "--gt", str(loop_clip))
    without = cli_json("eval", str(runs["no-pg"]), "--gt", str(loop_clip))
    assert on["ate_rmse"] < 0.95 * without["ate_rmse"], (on["ate_rmse"], without["ate_rmse"])