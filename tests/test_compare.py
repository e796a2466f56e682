"""`gcvd-flow compare` and `gcvd-flow eval --baseline` (the CI regression checks).

Three runs of one tiny synthetic clip share a cache: A, A again (identical), and B with another
flow preset and mask dilation. Every difference measure is checked against a computation of its
own from the cached outputs.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import cli, cli_json

N_FRAMES, W, H = 14, 96, 72
QUICK = ["--set", "optimize_keyframes.steps=2", "--set", "optimize_edges.steps=2",
         "--set", "optimize_segments.steps=2", "--set", "depth_fusion.enabled=false"]
CHANGED = ["--set", "flow.preset=medium", "--set", "masks.dilate=2"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("compare")
    clip, cache = base / "clip", base / "cache"
    cli("synth", str(clip), "--frames", str(N_FRAMES), "--trajectory", "loop", "--size", f"{W}x{H}",
        "--moving-object", check=True)
    for name, extra in (("a", []), ("a2", []), ("b", CHANGED)):
        cli("run", str(clip), "--out", str(base / name), "--cache", str(cache), *QUICK, *extra, check=True)
    return {"clip": clip, "cache": cache, "a": base / "a", "a2": base / "a2", "b": base / "b", "base": base}


def test_identical_runs_compare_equal(runs):
    doc = cli_json("compare", str(runs["a"]), str(runs["a2"]))  # caches from run.json
    assert doc["identical"] is True and all(r["equal"] for r in doc["stages"])
    assert [r["stage"] for r in doc["stages"]][:5] == ["ingest", "user_masks", "calibrate", "flow", "flow_far"]
    assert doc["outputs"]["poses"]["ate_rmse"] < 1e-12 and doc["outputs"]["depth"]["median_abs_log_ratio"] == 0
    p = cli("compare", str(runs["a"]), str(runs["a2"]), "--check")
    assert p.returncode == 0 and "identical" in p.stdout


def _by_stage(doc: dict) -> dict[str, dict]:
    return {r["stage"]: r for r in doc["stages"]}


def test_changed_run_differences_are_measured(runs):
    from gcvd_flow.engine import api
    from gcvd_flow.evaluate import metrics
    from gcvd_flow.io.formats import read_tum_poses

    doc = cli_json("compare", str(runs["a"]), str(runs["b"]), "--cache", str(runs["cache"]), "--max-items", "100")
    st = _by_stage(doc)
    # flow_far reads ingest alone (its own preset); priors read the adjacent flows too (chain_fallback)
    assert doc["identical"] is False and st["ingest"]["equal"] and st["flow_far"]["equal"]
    assert not st["flow"]["equal"] and not st["masks"]["equal"] and not st["depth_filter"]["equal"]
    fa, fb = (api.recorded_output(runs[k], "flow", str(runs["cache"])) for k in ("a", "b"))
    epe = np.mean([np.mean(np.linalg.norm(fb[i]["fwd"] - fa[i]["fwd"], axis=-1)) for i in range(len(fa))])
    assert st["flow"]["items_differing"] == N_FRAMES - 1 and st["flow"]["fwd_epe_px"] == pytest.approx(epe)
    assert 0 < epe < 5
    ma, mb = (api.recorded_output(runs[k], "masks", str(runs["cache"])) for k in ("a", "b"))
    ious = []
    for i in range(len(ma)):
        da, db = ma[i]["static"] == 0, mb[i]["static"] == 0
        u = np.count_nonzero(da | db)
        ious.append(1.0 if u == 0 else np.count_nonzero(da & db) / u)
    assert st["masks"]["mask_iou"] == pytest.approx(np.mean(ious)) and 0 < np.mean(ious) < 1
    _, pa = read_tum_poses(runs["a"] / "poses.txt")
    _, pb = read_tum_poses(runs["b"] / "poses.txt")
    ate = metrics.ate(pb, pa)["ate_rmse"]
    assert doc["outputs"]["poses"]["ate_rmse"] == pytest.approx(ate) and ate > 0
    assert st["optimize_segments"]["poses_ate_rmse"] == pytest.approx(ate)
    da = np.load(runs["a"] / "depth" / "000000.npy")
    db = np.load(runs["b"] / "depth" / "000000.npy")
    assert st["depth_filter"]["depth_median_abs_log_ratio"] > 0 and np.any(da != db)
    text = cli("compare", str(runs["a"]), str(runs["b"]), check=True).stdout
    assert "flow" in text and "DIFFERS" in text and "fwd_epe_px" in text and "mask_iou" in text
    assert cli("compare", str(runs["a"]), str(runs["b"]), "--check").returncode == 1


def test_compare_without_cache_still_compares_the_run_dirs(runs, tmp_path):
    empty = tmp_path / "empty"
    (empty / "objects").mkdir(parents=True)
    doc = cli_json("compare", str(runs["a"]), str(runs["b"]), "--cache", str(empty))
    st = _by_stage(doc)
    assert st["ingest"]["equal"] and "note" in st["flow"] and doc["outputs"]["poses"]["ate_rmse"] > 0
    p = cli("compare", str(runs["a"]), str(tmp_path / "missing"))
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1 and "missing" in p.stderr


def test_eval_baseline_gates_on_regressions(runs, tmp_path):
    res = cli_json("eval", str(runs["a"]), "--gt", str(runs["clip"]), "--no-write")
    assert not (runs["a"] / "metrics.json").exists()
    same = tmp_path / "same.json"
    same.write_text(json.dumps(res))
    p = cli("eval", str(runs["a"]), "--gt", str(runs["clip"]), "--baseline", str(same), "--tolerance", "0%")
    assert p.returncode == 0 and "no metric worse" in p.stdout, p.stderr
    better = dict(res, ate_rmse=res["ate_rmse"] / 2, delta1=1.0)  # a baseline the run cannot meet
    (tmp_path / "better.json").write_text(json.dumps({"metrics": better, "note": "wrapped"}))
    p = cli("eval", str(runs["a"]), "--gt", str(runs["clip"]), "--baseline", str(tmp_path / "better.json"))
    lines = [ln for ln in p.stderr.splitlines() if ln.startswith("regression:")]
    assert p.returncode == 1 and len(lines) == 2
    assert lines[0].startswith("regression: ate_rmse:") and "+100.0%" in lines[0] and "tolerance 5%" in lines[0]
    assert lines[1].startswith("regression: delta1:")
    p = cli("eval", str(runs["a"]), "--gt", str(runs["clip"]), "--baseline", str(tmp_path / "better.json"),
            "--tolerance", "150%", "--json")
    doc = json.loads(p.stdout)
    assert p.returncode == 1 and [r.split(":")[0] for r in doc["regressions"]] == ["delta1"]
    for bad, fragment in ((["--tolerance", "x%"], "--tolerance"), (["--baseline", str(tmp_path / "no.json")], "no.json")):
        args = ["--baseline", str(same)] + bad if bad[0] == "--tolerance" else bad
        p = cli("eval", str(runs["a"]), "--gt", str(runs["clip"]), *args)
        assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1 and fragment in p.stderr


def test_compare_to_baseline_rules():
    from gcvd_flow.evaluate.run_eval import compare_to_baseline, parse_tolerance

    assert parse_tolerance("5%") == pytest.approx(0.05) and parse_tolerance("0.1") == pytest.approx(0.1)
    base = {"frames": 10, "ate_rmse": 0.010, "rpe_rot": 0.0, "abs_rel": 0.05, "delta1": 0.90}
    ok = {"frames": 10, "ate_rmse": 0.0104, "rpe_rot": 0.0, "abs_rel": 0.01, "delta1": 0.896}
    assert compare_to_baseline(ok, base, 0.05) == []  # within 5 % (1 - delta1: 0.104 vs 0.100)
    worse = dict(ok, ate_rmse=0.0106, delta1=0.89, frames=9, rpe_rot=0.1)
    out = compare_to_baseline(worse, base, 0.05)
    assert [ln.split(":")[0] for ln in out] == ["frames", "ate_rmse", "rpe_rot", "delta1"]
    assert compare_to_baseline({**ok, "abs_rel": float("nan")}, base, 0.05)[0].startswith("abs_rel")


def test_status_uses_the_cache_the_run_recorded(runs, tmp_path):
    """`status --out RUN_DIR` without --cache: run.json's "cache", not $GCVD_FLOW_CACHE / the default."""
    doc = json.loads((runs["a"] / "run.json").read_text())
    assert Path(doc["cache"]) == runs["cache"].resolve()
    elsewhere = tmp_path / "other-cache"
    p = cli("status", "--out", str(runs["a"]), "--json", env={"GCVD_FLOW_CACHE": str(elsewhere)})
    assert p.returncode == 0, p.stderr
    assert {s["name"]: s["action"] for s in json.loads(p.stdout)["stages"]}["depth_filter"] == "cached"
    assert all(s["action"] == "cached" for s in json.loads(p.stdout)["stages"])
    p = cli("status", "--out", str(runs["a"]), "--json", "--cache", str(elsewhere))  # --cache still wins
    assert any(s["action"] == "run" for s in json.loads(p.stdout)["stages"])
