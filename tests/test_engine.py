"""The stage-cached DAG engine on the toy pipeline: caching, invalidation, resume, locks."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import ROOT, by_stage, cli, cli_json, make_toy_input

from gcvd_flow.engine import api
from gcvd_flow.engine.store import Store


def toy(*args: str) -> list[str]:
    return [*args, "--pipeline", "toy"]


def run_toy(inp: Path, out: Path, cache: Path, *extra: str) -> dict:
    return by_stage(cli_json("run", str(inp), "--out", str(out), "--cache", str(cache), "--pipeline", "toy", *extra))


def test_rerun_executes_nothing(toy_input, tmp_path):
    first = run_toy(toy_input, tmp_path / "out", tmp_path / "cache")
    assert first["decode"]["executed"] == 40 and first["report"]["executed"] == 1
    second = run_toy(toy_input, tmp_path / "out", tmp_path / "cache")
    assert all(s["executed"] == 0 for s in second.values()), second
    assert second["transform"]["cached"] == 40


def test_param_change_reruns_only_that_stage_and_descendants(toy_input, tmp_path):
    run_toy(toy_input, tmp_path / "out", tmp_path / "cache")
    res = run_toy(toy_input, tmp_path / "out", tmp_path / "cache", "--set", "threshold.cut=100")
    assert res["decode"]["executed"] == res["transform"]["executed"] == res["summarize"]["executed"] == 0
    assert res["threshold"]["executed"] == 1 and res["report"]["executed"] == 1
    # the plan after that run says everything is cached, and a further change is explained
    plan = by_stage(cli_json("plan", str(toy_input), "--out", str(tmp_path / "out"), "--cache",
                             str(tmp_path / "cache"), "--pipeline", "toy", "--set", "threshold.cut=150"))
    assert plan["summarize"]["action"] == "cached"
    assert plan["threshold"]["action"] == "run"
    assert any("threshold.cut" in r and "100.0 -> 150.0" in r for r in plan["threshold"]["reasons"])
    assert plan["report"]["action"] == "run"


def test_early_cutoff(toy_input, tmp_path):
    run_toy(toy_input, tmp_path / "out", tmp_path / "cache")
    # `sleep` changes transform's key but not its output bytes: downstream stays cached
    res = run_toy(toy_input, tmp_path / "out", tmp_path / "cache", "--set", "transform.sleep=0.0001")
    assert res["transform"]["executed"] == 40
    assert res["summarize"]["executed"] == 0 and res["summarize"]["cached"] == 1
    assert res["report"]["executed"] == 0


def test_map_items_reused_after_trim_extend_and_stride(toy_input, tmp_path):
    c = tmp_path / "cache"
    res = run_toy(toy_input, tmp_path / "o", c, "--set", "decode.end=30")
    assert res["decode"]["executed"] == 30
    res = run_toy(toy_input, tmp_path / "o", c, "--set", "decode.end=20")
    assert res["decode"]["executed"] == 0 and res["decode"]["cached"] == 20
    assert res["transform"]["executed"] == 0
    assert res["summarize"]["executed"] == 1  # a different set of items
    res = run_toy(toy_input, tmp_path / "o", c, "--set", "decode.end=38")
    assert res["decode"]["executed"] == 8 and res["transform"]["executed"] == 8
    res = run_toy(toy_input, tmp_path / "o", c, "--set", "decode.stride=2")
    assert res["decode"]["executed"] == 1  # items 0, 2, .., 36 are cached; 38 is new
    assert res["decode"]["cached"] == 19


def test_same_pipeline_in_two_places_gives_identical_keys(tmp_path):
    a = make_toy_input(tmp_path / "a" / "in")
    b = tmp_path / "elsewhere" / "deeper" / "in"
    shutil.copytree(a, b)
    cli_json("run", str(a), "--out", str(tmp_path / "a" / "out"), "--cache", str(tmp_path / "ca"), "--pipeline", "toy")
    cli_json("run", str(b), "--out", str(tmp_path / "b" / "out"), "--cache", str(tmp_path / "cb"), "--pipeline", "toy")
    ra = json.loads((tmp_path / "a" / "out" / "run.json").read_text())["stages"]
    rb = json.loads((tmp_path / "b" / "out" / "run.json").read_text())["stages"]
    assert {k: (v["key"], v["output"]) for k, v in ra.items()} == {k: (v["key"], v["output"]) for k, v in rb.items()}


def _verify_cache(cache: Path) -> None:
    """Every record resolves to complete, uncorrupted objects."""
    store = Store(cache)
    rep = store.fsck()
    assert rep.corrupt == [] and rep.records_removed == 0
    for _key, path in store.iter_records():
        rec = json.loads(path.read_text())
        for d in rec.get("objects", {}):
            assert store.has(d)


@pytest.mark.parametrize("kill_after", [0.8, 1.6, 2.6])
def test_kill9_leaves_consistent_cache_and_resumes(toy_input, tmp_path, kill_after):
    cache, out = tmp_path / "cache", tmp_path / "out"
    cmd = [sys.executable, "-m", "gcvd_flow", "run", str(toy_input), "--out", str(out), "--cache", str(cache),
           "--pipeline", "toy", "--set", "transform.sleep=0.05", "--json"]
    p = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(kill_after)
    p.send_signal(signal.SIGKILL)
    p.wait()
    _verify_cache(cache)
    store = Store(cache)
    done_items = sum(1 for _, path in store.iter_records()
                     if json.loads(path.read_text()).get("stage") == "transform"
                     and json.loads(path.read_text()).get("record_kind") == "item")
    res = by_stage(cli_json("run", str(toy_input), "--out", str(out), "--cache", str(cache), "--pipeline", "toy",
                            "--set", "transform.sleep=0.05"))
    assert res["transform"]["executed"] == 40 - done_items
    assert res["transform"]["cached"] == done_items
    assert res["decode"]["executed"] + res["decode"]["cached"] == 40
    _verify_cache(cache)


def test_concurrent_runs_compute_each_item_once(toy_input, tmp_path):
    cache = tmp_path / "cache"
    procs = [subprocess.Popen([sys.executable, "-m", "gcvd_flow", "run", str(toy_input), "--out", str(tmp_path / f"o{i}"),
                               "--cache", str(cache), "--pipeline", "toy", "--set", "transform.sleep=0.03", "--json"],
                              cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    docs = []
    for p in procs:
        out, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
        docs.append(by_stage(json.loads(out)))
    assert sum(d["transform"]["executed"] for d in docs) == 40
    assert sum(d["decode"]["executed"] for d in docs) == 40
    outs = [json.loads((tmp_path / f"o{i}" / "run.json").read_text())["stages"]["report"]["output"] for i in range(2)]
    assert outs[0] == outs[1]


def test_corrupt_object_found_by_fsck_and_never_returned(toy_input, tmp_path):
    cache, out = tmp_path / "cache", tmp_path / "out"
    run_toy(toy_input, out, cache)
    store = Store(cache)
    # corrupt the summarize output's array (same size: only hashing can tell)
    rec = json.loads(store.record_path(json.loads((out / "run.json").read_text())["stages"]["summarize"]["key"]).read_text())
    victim = max(rec["objects"], key=lambda d: rec["objects"][d])
    path = store.object_path(victim)
    os.chmod(path, 0o644)
    data = bytearray(path.read_bytes())
    data[-1] ^= 0xFF
    path.write_bytes(bytes(data))
    # a run reads it, detects the mismatch, quarantines it and recomputes
    res = run_toy(toy_input, out, cache, "--set", "threshold.cut=10")
    assert res["summarize"]["executed"] == 1
    assert store.has(victim)  # recomputed with the right bytes
    assert Store(cache).fsck().corrupt == []
    # fsck finds a corruption directly too
    os.chmod(path, 0o644)
    path.write_bytes(bytes(data))
    doc = cli_json("fsck", "--cache", str(cache))
    assert doc["corrupt"] == [victim]
    assert (cache / "quarantine" / victim).exists()
    res = run_toy(toy_input, out, cache)
    assert res["summarize"]["executed"] == 1


def test_objects_are_read_only(toy_input, tmp_path):
    run_toy(toy_input, tmp_path / "out", tmp_path / "cache")
    store = Store(tmp_path / "cache")
    modes = {oct(store.object_path(d).stat().st_mode & 0o777) for d in store.iter_objects()}
    assert modes == {"0o444"}


def test_why_names_param_code_and_input_changes(toy_input, tmp_path):
    cache, out = tmp_path / "cache", tmp_path / "out"
    run_toy(toy_input, out, cache)
    doc = cli_json("why", "threshold", "--out", str(out), "--cache", str(cache), "--set", "threshold.cut=5")
    assert doc["action"] == "run"
    assert any(r == "param threshold.cut changed: 200.0 -> 5.0" for r in doc["reasons"]), doc
    doc = cli_json("why", "summarize", "--out", str(out), "--cache", str(cache), "--set", "decode.end=10")
    assert any(r.startswith("upstream will run") or r.startswith("input transform changed") for r in doc["reasons"])
    doc = cli_json("why", "report", "--out", str(out), "--cache", str(cache))
    assert doc["action"] == "cached" and doc["reasons"] == []
    # a changed input file: decode's input changes
    (toy_input / "00003.bin").write_bytes(b"\x01" * 2000)
    doc = cli_json("why", "decode", "--out", str(out), "--cache", str(cache))
    assert any(r.startswith("input source changed") for r in doc["reasons"]), doc


def test_why_names_changed_code_file():
    old = {"code_files": {"stages/flow.py": "a", "stages/x:run": "b"}, "params": {"p": 1}, "inputs": {}, "env": {}}
    new = {"code_files": {"stages/flow.py": "c", "stages/x:run": "b"}, "params": {"p": 1}, "inputs": {}, "env": {}}
    assert api.diff_fields(old, new) == ["code changed: stages/flow.py"]


def test_gc_keeps_last_runs(toy_input, tmp_path):
    cache, out = tmp_path / "cache", tmp_path / "out"
    run_toy(toy_input, out, cache, "--set", "transform.scale=3")
    run_toy(toy_input, out, cache)
    before = sum(1 for _ in Store(cache).iter_objects())
    doc = cli_json("gc", "--cache", str(cache), "--keep", "1")
    assert doc["objects_removed"] > 0
    assert sum(1 for _ in Store(cache).iter_objects()) == before - doc["objects_removed"]
    res = run_toy(toy_input, out, cache)
    assert all(s["executed"] == 0 for s in res.values())
    res = run_toy(toy_input, out, cache, "--set", "transform.scale=3")
    assert res["transform"]["executed"] == 40


def test_pinned_run_survives_gc(toy_input, tmp_path):
    cache = tmp_path / "cache"
    run_toy(toy_input, tmp_path / "pinned", cache, "--set", "transform.scale=3")
    cli("pin", "keepme", "--out", str(tmp_path / "pinned"), "--cache", str(cache), check=True)
    run_toy(toy_input, tmp_path / "other", cache)
    cli_json("gc", "--cache", str(cache), "--keep", "1")
    res = run_toy(toy_input, tmp_path / "pinned2", cache, "--set", "transform.scale=3")
    assert all(s["executed"] == 0 for s in res.values()), res


def test_parallel_jobs_match_serial(toy_input, tmp_path):
    run_toy(toy_input, tmp_path / "o1", tmp_path / "c1")
    par = run_toy(toy_input, tmp_path / "o2", tmp_path / "c2", "--jobs", "2")
    assert par["transform"]["executed"] == 40
    r1 = json.loads((tmp_path / "o1" / "run.json").read_text())["stages"]
    r2 = json.loads((tmp_path / "o2" / "run.json").read_text())["stages"]
    assert {k: v["output"] for k, v in r1.items()} == {k: v["output"] for k, v in r2.items()}


@pytest.mark.parametrize("args,needle", [
    (["--set", "threshold.cutt=1"], "unknown config key 'threshold.cutt'; did you mean 'threshold.cut'?"),
    (["--set", "treshold.cut=1"], "unknown config key 'treshold'; did you mean 'threshold'?"),
    (["--set", "threshold.cut=abc"], "threshold.cut"),
    (["--set", "nosuch.key=1"], "unknown config key 'nosuch'"),
    (["--profile", "nope"], "unknown profile 'nope'"),
    (["--config", "/nonexistent.toml"], "config file not found"),
])
def test_bad_usage_is_one_line_exit_2(toy_input, tmp_path, args, needle):
    p = cli("run", str(toy_input), "--out", str(tmp_path / "o"), "--cache", str(tmp_path / "c"), "--pipeline", "toy", *args)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], p.stderr
    assert not (tmp_path / "o" / "run.json").exists()


def test_missing_input_is_exit_2(tmp_path):
    p = cli("run", str(tmp_path / "nope"), "--out", str(tmp_path / "o"), "--cache", str(tmp_path / "c"), "--pipeline", "toy")
    assert p.returncode == 2 and "nope" in p.stderr and "Traceback" not in p.stderr


def test_config_file_and_profiles(toy_input, tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[threshold]\ncut = 42.0\n[profiles.mine]\nthreshold = { cut = 7.0 }\n")
    cache = tmp_path / "cache"
    cli_json("run", str(toy_input), "--out", str(tmp_path / "o"), "--cache", str(cache), "--pipeline", "toy", "--config", str(cfg))
    rj = json.loads((tmp_path / "o" / "run.json").read_text())
    assert rj["config"]["threshold"]["cut"] == 42.0
    cli_json("run", str(toy_input), "--out", str(tmp_path / "o"), "--cache", str(cache), "--pipeline", "toy",
             "--profile", "fast", "--set", "threshold.cut=8")
    rj = json.loads((tmp_path / "o" / "run.json").read_text())
    assert rj["config"]["transform"]["scale"] == 1.0 and rj["config"]["threshold"]["cut"] == 8.0


def test_status_and_dag(toy_input, tmp_path):
    run_toy(toy_input, tmp_path / "o", tmp_path / "c")
    p = cli("status", "--out", str(tmp_path / "o"), "--cache", str(tmp_path / "c"), check=True)
    assert p.stdout.count("up to date") == 5
    p = cli("dag", "--pipeline", "toy", check=True)
    assert "transform [map] <- decode" in p.stdout


def test_noop_fast_path_and_what_invalidates_it(toy_input, tmp_path):
    out, cache = tmp_path / "out", tmp_path / "cache"
    base = ["run", str(toy_input), "--out", str(out), "--cache", str(cache), "--pipeline", "toy"]
    cli_json(*base)
    doc = cli_json(*base)
    assert "noop" in doc and all(s["executed"] == 0 for s in doc["stages"])
    assert by_stage(doc)["transform"]["cached"] == 40
    # touching an input (same bytes) leaves the fast path, and content hashing finds nothing to do
    os.utime(toy_input / "00001.bin", ns=(1, 1))
    doc = cli_json(*base)
    assert "noop" not in doc and all(s["executed"] == 0 for s in doc["stages"])
    # a deleted output is re-exported by the full path
    (out / "report.json").unlink()
    doc = cli_json(*base)
    assert "noop" not in doc and (out / "report.json").exists()
    # a removed record is recomputed
    assert "noop" in cli_json(*base)
    store = Store(cache)
    key = json.loads((out / "run.json").read_text())["stages"]["report"]["key"]
    store.delete_record(key)
    doc = cli_json(*base)
    assert "noop" not in doc and by_stage(doc)["report"]["executed"] == 1
    # different parameters never take the fast path
    doc = cli_json(*base, "--set", "threshold.cut=1")
    assert "noop" not in doc and by_stage(doc)["threshold"]["executed"] == 1


@pytest.mark.parametrize("jobs", ["1", "2"])
def test_ctrl_c_exits_130_and_leaves_a_consistent_cache(toy_input, tmp_path, jobs):
    cache, out = tmp_path / "cache", tmp_path / "out"
    cmd = [sys.executable, "-m", "gcvd_flow", "run", str(toy_input), "--out", str(out), "--cache", str(cache),
           "--pipeline", "toy", "--set", "transform.sleep=0.05", "--jobs", jobs]
    # SIGINT back to its default in the child: a test run started in the background (`make test &`)
    # inherits SIGINT ignored, as shells do for background jobs, and Ctrl-C would never arrive
    p = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    # interrupt once the transform stage is under way (40 decode items + a few transform items
    # recorded), not after a fixed time: on a loaded machine start-up alone can take seconds
    deadline = time.time() + 60
    while len(list((cache / "records").glob("*/*.json"))) < 45 and p.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err
    _verify_cache(cache)
    res = by_stage(cli_json("run", str(toy_input), "--out", str(out), "--cache", str(cache), "--pipeline", "toy",
                            "--set", "transform.sleep=0.05"))
    assert res["transform"]["executed"] + res["transform"]["cached"] == 40
    if jobs == "1":  # the serial run had finished some transform items before Ctrl-C: they are kept
        assert res["transform"]["cached"] > 0


def test_ctrl_c_during_a_stages_calls_on_the_workers_exits_130_and_stops_them(toy_input, tmp_path):
    """Ctrl-C while a whole stage's ``ctx.map`` calls run on the worker processes (as
    optimize_segments' windows do): exit 130, no traceback, no worker left behind (they hold the
    run's stderr, so communicate() would not return), a consistent cache, and a rerun that
    computes the interrupted stage."""
    cache, out = tmp_path / "cache", tmp_path / "out"
    cmd = [sys.executable, "-m", "gcvd_flow", "run", str(toy_input), "--out", str(out), "--cache", str(cache),
           "--pipeline", "toy", "--set", "summarize.sleep=0.3", "--jobs", "2"]
    p = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    # decode and transform (40 items each) recorded: summarize's 40 calls (6 s on 2 workers) run
    deadline = time.time() + 60
    while len(list((cache / "records").glob("*/*.json"))) < 82 and p.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    time.sleep(1.0)
    assert p.poll() is None, "the run ended before it could be interrupted"
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err
    _verify_cache(cache)
    res = by_stage(cli_json("run", str(toy_input), "--out", str(out), "--cache", str(cache), "--pipeline", "toy",
                            "--set", "summarize.sleep=0.01"))
    assert res["summarize"]["executed"] == 1 and res["transform"]["cached"] == 40


def test_push_pull_shares_a_run_and_refuses_tampered_objects(toy_input, tmp_path):
    a_cache, b_cache, remote = tmp_path / "a", tmp_path / "b", tmp_path / "remote"
    run_toy(toy_input, tmp_path / "oa", a_cache)
    doc = cli_json("push", str(remote), "--cache", str(a_cache), "--out", str(tmp_path / "oa"))
    assert doc["records"] > 40 and doc["refused"] == 0
    # tamper with one object on the remote: pull must refuse it and not install its record
    victim = next(Store(remote).iter_objects())
    vp = Store(remote).object_path(victim)
    os.chmod(vp, 0o644)
    vp.write_bytes(b"tampered" + vp.read_bytes()[8:])
    doc = cli_json("pull", str(remote), "--cache", str(b_cache))
    assert doc["refused"] == 1
    res = run_toy(toy_input, tmp_path / "ob", b_cache)
    assert sum(s["executed"] for s in res.values()) <= 2  # only what the tampered object held
    assert Store(b_cache).fsck().corrupt == []


def test_checkpoint_shards_are_stored_once_and_come_back_flat(tmp_path):
    """A shard saved again unchanged is the same object (no rewrite, no copy of finished
    work per save); load() returns shard arrays as "shard/key" beside the tensors."""
    import numpy as np

    from gcvd_flow.engine.runner import Checkpointer
    from gcvd_flow.engine.store import Store

    store = Store(tmp_path / "cache")
    ck = Checkpointer(store, "k" * 64, "demo", lambda m: None)
    big = {"depth": np.arange(4096, dtype=np.float32).reshape(64, 64)}
    ck.save({"step": np.array([1])}, {"window": 1}, {"w0": big})
    n_objects = sum(1 for _ in (tmp_path / "cache" / "objects").rglob("*") if _.is_file())
    ck.save({"step": np.array([2])}, {"window": 2}, {"w0": big, "w1": {"depth": big["depth"] + 1}})
    added = sum(1 for _ in (tmp_path / "cache" / "objects").rglob("*") if _.is_file()) - n_objects
    assert added == 3  # the tensors, shard w1 and the manifest: w0 is not written again
    tensors, meta = ck.load()
    assert meta == {"window": 2} and sorted(tensors) == ["step", "w0/depth", "w1/depth"]
    assert np.array_equal(np.asarray(tensors["w1/depth"]), big["depth"] + 1)


def test_stage_puts_parts_before_returning(tmp_path):
    """``ctx.put`` stores a part of a stage's output at once (so a stage need not hold its whole
    output in memory); the handle in the output, or in a checkpoint shard, becomes the part's
    node, the record lists its objects, and the value reads back as if returned whole."""
    import numpy as np

    from gcvd_flow.engine.artifacts import Encoder, load_value
    from gcvd_flow.engine.dag import Stage
    from gcvd_flow.engine.runner import Checkpointer, StageContext

    store = Store(tmp_path / "cache")
    ctx = StageContext(Stage("demo", lambda i, p, c: None), 0, lambda m: None, None, store=store)
    parts = [np.full((16, 16), k, np.float32) for k in range(3)]
    handles = [ctx.put(a) for a in parts]
    assert all(h.node["$npy"] in h.objects for h in handles)
    enc = Encoder(store)
    digest = enc.manifest("toy", {"depths": handles, "n": 3})
    whole = Encoder(store).manifest("toy", {"depths": parts, "n": 3})
    assert digest == whole  # the same artifact as returning the arrays
    assert set(enc.objects) >= {h.node["$npy"] for h in handles}
    back = load_value(store, digest)
    assert all(np.array_equal(a, b) for a, b in zip(back["depths"], parts))
    # a checkpoint shard of handles comes back as the stored arrays
    ck = Checkpointer(store, "c" * 64, "demo", lambda m: None)
    ck.save({"step": np.array([1])}, {"window": 1}, {"w0": {"depth": handles[:2]}})
    tensors, _ = ck.load()
    assert [np.asarray(a).tolist() for a in tensors["w0/depth"]] == [p.tolist() for p in parts[:2]]
    with pytest.raises(RuntimeError, match="no store"):
        StageContext(Stage("demo", lambda i, p, c: None), 0, lambda m: None, None).put(parts[0])


def test_runner_drops_decoded_outputs_no_later_stage_reads(tmp_path, monkeypatch):
    """A stage's decoded output is dropped once the last stage that reads it has run (a long
    clip's keyframe depths need not live until the last stage), and decoded again if asked
    for (the run dir's outputs are written after the last stage)."""
    from gcvd_flow.engine.runner import Runner

    held: dict[str, list[str]] = {}
    run_stage = Runner._run_stage

    def spy(self, stage, executor):
        held[stage.name] = sorted(self._values)  # decoded outputs held when the stage starts
        return run_stage(self, stage, executor)

    monkeypatch.setattr(Runner, "_run_stage", spy)
    inp = make_toy_input(tmp_path / "in", n=6)
    api.run(api.Invocation(input=str(inp), out=str(tmp_path / "o"), cache=str(tmp_path / "c"), pipeline="toy"),
            log=lambda m: None)
    # toy: decode -> transform -> summarize -> threshold -> report, each read only by the next
    assert list(held) == ["decode", "transform", "summarize", "threshold", "report"]
    assert all(v == [] for v in held.values()), held
    assert json.loads((tmp_path / "o" / "run.json").read_text())["stages"]["report"]["output"]


def test_mistyped_gcvd_key_gets_a_suggestion():
    """A mistyped --set key names the closest real one (difflib), also across sections."""
    from gcvd_flow.engine.config import build_config
    from gcvd_flow.engine.errors import UsageError
    from gcvd_flow.pipeline import PROFILES, GCVDConfig

    for bad, good in (("keyframes.detla=0.2", "keyframes.delta"), ("association.delta=0.2", "keyframes.delta"),
                      ("bundle_adjusment.enabled=false", "bundle_adjustment")):
        with pytest.raises(UsageError, match=f"did you mean '{good}'"):
            build_config(GCVDConfig, PROFILES, sets=[bad])
