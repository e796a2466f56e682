"""`sweep` and `runs` on the toy pipeline: shared items computed once, interleaved map stages,
resuming an interrupted sweep, the runs table's differing-columns rule, bad grids.

(The GCVD case of issue 30 — a keyframes.delta sweep with --gt — is in tests/test_sweep_gcvd.py.)
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import ROOT, cli, cli_json, make_toy_input

TOY = ["--pipeline", "toy"]
N = 40  # toy input files (items per map stage)


def _executed(doc: dict, stage: str) -> int:
    return sum(s["executed"] for r in doc["runs"] for s in r["stages"] if s["name"] == stage)


def _item_records(cache: Path, stage: str) -> int:
    n = 0
    for f in (cache / "records").glob("*/*.json"):
        d = json.loads(f.read_text())
        n += d.get("record_kind") == "item" and d.get("stage") == stage
    return n


@pytest.mark.parametrize("jobs", ["1", "2"])
def test_shared_items_computed_once(tmp_path, jobs):
    """3 x 2 runs: decode is shared by all six, transform by the three of each scale, summarize
    likewise; the map stages run in waves on the workers with --jobs 2."""
    inp = make_toy_input(tmp_path / "in", n=N)
    doc = cli_json("sweep", str(inp), "--out", str(tmp_path / "sw"), "--cache", str(tmp_path / "c"), *TOY,
                   "--grid", "threshold.cut=100,150,200", "--grid", "transform.scale=1,2", "--jobs", jobs)
    assert [r["name"] for r in doc["runs"]] == [f"threshold.cut={c},transform.scale={s}"
                                                for c in (100, 150, 200) for s in (1, 2)]
    assert all(r["ok"] for r in doc["runs"]) and doc["failed"] == 0
    assert doc["runs"][0]["params"] == {"threshold.cut": 100.0, "transform.scale": 1.0}
    assert _executed(doc, "decode") == N  # once for all six runs
    assert _executed(doc, "transform") == 2 * N  # once per scale
    assert _executed(doc, "summarize") == 2
    assert _executed(doc, "threshold") == 6
    assert _item_records(tmp_path / "c", "transform") == 2 * N
    for r in doc["runs"]:
        out = Path(r["out"])
        assert out.parent == tmp_path / "sw" and (out / "run.json").is_file()
        cfg = json.loads((out / "run.json").read_text())["config"]
        assert cfg["threshold"]["cut"] == r["params"]["threshold.cut"]
    # the same results as one separate run of that combination in its own cache
    alone = tmp_path / "alone"
    cli("run", str(inp), "--out", str(alone), "--cache", str(tmp_path / "c2"), *TOY,
        "--set", "threshold.cut=150", "--set", "transform.scale=2", check=True)
    ref = json.loads((alone / "run.json").read_text())["stages"]
    got = json.loads((tmp_path / "sw" / "threshold.cut=150,transform.scale=2" / "run.json").read_text())["stages"]
    assert {k: v["output"] for k, v in got.items()} == {k: v["output"] for k, v in ref.items()}
    # sweeping again computes nothing
    again = cli_json("sweep", str(inp), "--out", str(tmp_path / "sw"), "--cache", str(tmp_path / "c"), *TOY,
                     "--grid", "threshold.cut=100,150,200", "--grid", "transform.scale=1,2", "--jobs", jobs)
    assert sum(s["executed"] for r in again["runs"] for s in r["stages"]) == 0


def test_interrupted_sweep_resumes(tmp_path):
    """Ctrl-C in the middle of the shared map stage; the same command again computes exactly the
    items that are missing, and the runs equal an uninterrupted sweep's."""
    inp = make_toy_input(tmp_path / "in", n=N)
    cache = tmp_path / "c"
    args = ["sweep", str(inp), "--out", str(tmp_path / "sw"), "--cache", str(cache), *TOY,
            "--set", "transform.sleep=0.05", "--grid", "threshold.cut=100,200,300", "--jobs", "1"]
    env = dict(os.environ, PYTHONPATH=str(ROOT), GCVD_FLOW_JOBS="1")
    p = subprocess.Popen([sys.executable, "-m", "gcvd_flow", *args], cwd=ROOT, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.time()
    while (not (cache / "records").is_dir() or _item_records(cache, "transform") < 8) and time.time() - t0 < 120:
        time.sleep(0.05)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130, err
    done, decoded = _item_records(cache, "transform"), _item_records(cache, "decode")
    assert 8 <= done < N, done
    sweep_doc = json.loads((tmp_path / "sw" / "sweep.json").read_text())
    assert sweep_doc["state"] == "running" and len(sweep_doc["runs"]) == 3
    doc = cli_json(*args[:-2], "--jobs", "1", env={"GCVD_FLOW_JOBS": "1"})
    assert _executed(doc, "transform") == N - done  # only what was missing
    assert _executed(doc, "decode") == N - decoded
    assert json.loads((tmp_path / "sw" / "sweep.json").read_text())["state"] == "done"
    fresh = cli_json(*args[:2], "--out", str(tmp_path / "sw2"), *args[4:], env={"GCVD_FLOW_JOBS": "1"})
    for a, b in zip(doc["runs"], fresh["runs"]):
        sa = json.loads((Path(a["out"]) / "run.json").read_text())["stages"]
        sb = json.loads((Path(b["out"]) / "run.json").read_text())["stages"]
        assert {k: v["output"] for k, v in sa.items()} == {k: v["output"] for k, v in sb.items()}


def test_interrupted_waves_exit_at_once_and_resume(tmp_path):
    """Ctrl-C while the map prefix runs in waves on worker processes (--jobs 2): exit 130 at
    once (a wave thread waiting on the closed pool once kept the process alive), no process
    left, and the same command computes exactly the missing items."""
    inp = make_toy_input(tmp_path / "in", n=N)
    cache = tmp_path / "c"
    args = ["sweep", str(inp), "--out", str(tmp_path / "sw"), "--cache", str(cache), *TOY,
            "--set", "transform.sleep=0.1", "--grid", "transform.scale=1,2,3", "--jobs", "2"]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.Popen([sys.executable, "-m", "gcvd_flow", *args], cwd=ROOT, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.time()
    while (not (cache / "records").is_dir() or _item_records(cache, "transform") < 10) and time.time() - t0 < 120:
        time.sleep(0.05)
    p.send_signal(signal.SIGINT)
    t1 = time.time()
    try:
        _, err = p.communicate(timeout=30)
    finally:
        if p.poll() is None:  # hung: do not leave it behind
            p.kill()
            p.communicate()
    assert p.returncode == 130 and time.time() - t1 < 20, err
    assert "cannot schedule" not in err and len(err.strip().splitlines()) == 1, err
    done = _item_records(cache, "transform")
    assert 10 <= done < 3 * N
    doc = cli_json(*args)
    assert _executed(doc, "transform") == 3 * N - done and _executed(doc, "decode") == 0


@pytest.mark.parametrize("grid,needle", [
    (["threshold.nope=1,2"], "threshold.nope"),
    (["nosection.cut=1,2"], "nosection"),
    (["threshold.cut=1,abc"], "threshold.cut"),
    (["threshold.cut="], "empty list"),
    (["threshold.cut=, ,"], "empty list"),
    (["threshold.cut"], "SECTION.KEY=V1,V2"),
    (["threshold.cut=1,1"], "listed twice"),
    (["threshold.cut=1,1.0"], "same settings"),
    (["report.x=a/b,a_b"], "share the run directory"),
    (["threshold.cut=1", "threshold.cut=2"], "given twice"),
    (["threshold.cut=1,2,3,4,5", "transform.scale=1,2,3,4,5,6,7,8,9,10,11,12,13"], "more than --max-runs 64"),
])
def test_bad_grids_exit_2_before_running(tmp_path, toy_input, grid, needle):
    out = tmp_path / "sw"
    args = [a for g in grid for a in ("--grid", g)]
    p = cli("sweep", str(toy_input), "--out", str(out), "--cache", str(tmp_path / "c"), *TOY, *args)
    assert p.returncode == 2, p.stderr
    assert len(p.stderr.strip().splitlines()) == 1 and needle in p.stderr, p.stderr
    assert not out.exists() and not (tmp_path / "c").exists()  # nothing ran, nothing written


def test_max_runs_and_sort_checked(tmp_path, toy_input):
    p = cli("sweep", str(toy_input), "--out", str(tmp_path / "sw"), *TOY, "--grid", "threshold.cut=1,2,3",
            "--max-runs", "2")
    assert p.returncode == 2 and "3 runs, more than --max-runs 2" in p.stderr
    p = cli("sweep", str(toy_input), "--out", str(tmp_path / "sw"), *TOY, "--grid", "threshold.cut=1,2",
            "--sort", "ate_rmse")
    assert p.returncode == 2 and "--gt" in p.stderr and len(p.stderr.strip().splitlines()) == 1


# ------------------------------------------------------------------------------ runs


def _fake_metrics(run: Path, **m) -> None:
    (run / "metrics.json").write_text(json.dumps(m))


def test_runs_table_shows_only_differing_parameters(tmp_path, toy_input):
    cache = str(tmp_path / "c")
    cli_json("sweep", str(toy_input), "--out", str(tmp_path / "sw"), "--cache", cache, *TOY,
             "--set", "summarize.digits=3", "--grid", "threshold.cut=100,150,50")
    runs = sorted((tmp_path / "sw").iterdir())
    runs = [r for r in runs if r.is_dir()]
    for r, err in zip(runs, (0.3, 0.1, 0.2)):
        _fake_metrics(r, err=err, note="x")
    doc = cli_json("runs", str(tmp_path / "sw"))
    assert [r["name"] for r in doc["runs"]] == ["threshold.cut=100", "threshold.cut=150", "threshold.cut=50"]
    assert all(list(r["params"]) == ["threshold.cut"] for r in doc["runs"])  # digits=3 is the same in all
    assert [r["params"]["threshold.cut"] for r in doc["runs"]] == [100.0, 150.0, 50.0]
    assert doc["runs"][0]["metrics"] == {"err": 0.3, "note": "x"}
    # a fourth run that also differs in summarize.digits adds that column; --all-params: all
    cli("run", str(toy_input), "--out", str(tmp_path / "other" / "d5"), "--cache", cache, *TOY,
        "--set", "summarize.digits=5", "--set", "threshold.cut=100", check=True)
    doc = cli_json("runs", str(tmp_path / "sw"), str(tmp_path / "other"), "--sort=-err")
    assert sorted(doc["params"]) == ["summarize.digits", "threshold.cut"]
    assert [r["name"] for r in doc["runs"]] == ["threshold.cut=100", "threshold.cut=50", "threshold.cut=150", "d5"]
    d5 = doc["runs"][-1]
    assert d5["params"] == {"summarize.digits": 5, "threshold.cut": 100.0} and d5["metrics"] == {}
    # summarize re-ran; its inputs and, by early cutoff, the later stages were reused
    assert d5["stages"]["computed"] == 1 and d5["stages"]["reused"] == 4
    full = cli_json("runs", str(tmp_path / "sw"), "--all-params")
    assert {"threshold.cut", "summarize.digits", "transform.scale", "decode.stride", "seed"} <= set(full["params"])
    one = cli_json("runs", str(runs[0]))
    assert one["runs"][0]["params"] == {}  # one run: nothing differs
    text = cli("runs", str(tmp_path / "sw"), "--sort", "err", check=True).stdout.splitlines()
    assert "threshold.cut" in text[0] and "digits" not in text[0] and "err" in text[0]
    assert [ln.split()[0] for ln in text[2:]] == ["threshold.cut=150", "threshold.cut=50", "threshold.cut=100"]
    csv = cli("runs", str(tmp_path / "sw"), "--csv", check=True).stdout.splitlines()
    assert csv[0].startswith("name,when,threshold.cut,err") and len(csv) == 4
    md = cli("runs", str(tmp_path / "sw"), "--md", check=True).stdout.splitlines()
    assert md[0].startswith("| name | when | threshold.cut") and md[1].startswith("|---|")


@pytest.mark.parametrize("content,what", [("[1, 2]", "run.json"), ("{", "run.json"),
                                          ('{"config": 5}', "run.json")])
def test_runs_bad_files_exit_2(tmp_path, content, what):
    bad = tmp_path / "r"
    bad.mkdir()
    (bad / "run.json").write_text(content)
    p = cli("runs", str(tmp_path))
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1 and what in p.stderr, p.stderr


def test_runs_bad_metrics_and_paths_exit_2(tmp_path):
    run = tmp_path / "r"
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"config": {"a": {"b": 1}}}))
    (run / "metrics.json").write_text("[1, 2, 3]")
    p = cli("runs", str(tmp_path))
    assert p.returncode == 2 and "metrics.json" in p.stderr and len(p.stderr.strip().splitlines()) == 1
    p = cli("runs", str(tmp_path / "nope"))
    assert p.returncode == 2 and "nope" in p.stderr
    (run / "metrics.json").write_text(json.dumps({"x": 1.5}))
    p = cli("runs", str(tmp_path), "--sort", "y")
    assert p.returncode == 2 and "--sort y" in p.stderr


def test_python_api_sweep_and_runs(tmp_path, toy_input):
    from gcvd_flow import api
    from gcvd_flow.engine.api import Invocation
    from gcvd_flow.engine.errors import UsageError

    inv = Invocation(input=str(toy_input), out=str(tmp_path / "sw"), pipeline="toy", cache=str(tmp_path / "c"),
                     jobs=1)
    doc = api.sweep(inv, ["threshold.cut=10,20"])
    assert [r["name"] for r in doc["runs"]] == ["threshold.cut=10", "threshold.cut=20"] and doc["failed"] == 0
    assert api.runs(tmp_path / "sw", sort="-threshold.cut")["runs"][0]["name"] == "threshold.cut=20"
    with pytest.raises(UsageError, match="empty list"):
        api.sweep(inv, ["threshold.cut="])
