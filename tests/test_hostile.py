"""Hostile round two (issue 32): compare, eval's gate, run-many, remotes and the local store
against wrong results that exit 0, data loss outside the cache, and hangs.

Each test here fails without its fix. Two 16-frame GCVD runs (``base`` and ``var``, which
differs in optimize_segments.steps) are made once for the module; the engine cases use the toy
pipeline.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest
from conftest import cli, cli_json, make_toy_input

TOY = ("--pipeline", "toy")


def one_line_error(p: subprocess.CompletedProcess, *fragments: str) -> str:
    assert p.returncode == 2, (p.returncode, p.stdout, p.stderr)
    lines = [ln for ln in p.stderr.splitlines() if ln.strip() and not ln.startswith(("camera:", "warning:"))]
    assert len(lines) == 1 and "Traceback" not in p.stderr, p.stderr
    assert lines[0].startswith("gcvd-flow: error: "), p.stderr
    for f in fragments:
        assert f in lines[0], (f, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def gruns(tmp_path_factory) -> dict[str, Path]:
    """A 16-frame clip and two runs of it in one cache: base and var (optimize_segments.steps=5)."""
    d = tmp_path_factory.mktemp("hostile")
    clip, cache = d / "clip", d / "cache"
    cli("synth", str(clip), "--frames", "16", "--size", "128x96", check=True)
    c = ("--cache", str(cache), "--profile", "fast")
    cli("run", str(clip), "--out", str(d / "base"), *c, check=True)
    cli("run", str(clip), "--out", str(d / "var"), *c, "--set", "optimize_segments.steps=5", check=True)
    return {"dir": d, "clip": clip, "cache": cache, "base": d / "base", "var": d / "var"}


@pytest.fixture
def toy(tmp_path) -> dict[str, Path]:
    inp = make_toy_input(tmp_path / "input", n=6)
    return {"input": inp, "cache": tmp_path / "cache", "out": tmp_path / "out", "tmp": tmp_path}


def toy_run(t: dict[str, Path], *extra: str, out: Path | None = None, check: bool = True):
    p = cli("run", str(t["input"]), "--out", str(out or t["out"]), "--cache", str(t["cache"]), *TOY, *extra)
    if check:
        assert p.returncode == 0, p.stderr
    return p


# ------------------------------------------------------------------------------ 1. compare --check


def test_compare_check_verifies_the_run_dirs_own_files(gruns, tmp_path):
    base, var = gruns["base"], gruns["var"]
    doc = json.loads((base / "run.json").read_text())
    assert "poses.txt" in doc["files"] and "depth/000003.npy" in doc["files"] and "cameras.json" in doc["files"]
    same = tmp_path / "same"
    shutil.copytree(base, same)
    p = cli("compare", str(base), str(same), "--check")
    assert p.returncode == 0 and "identical" in p.stdout, p.stdout + p.stderr
    for what in ("poses.txt", "depth/000003.npy"):  # var's file in a copy of base: digests all equal
        b = tmp_path / what.replace("/", "_")
        shutil.copytree(base, b)
        shutil.copyfile(var / what, b / what)
        p = cli("compare", str(base), str(b), "--check")
        assert p.returncode == 1, p.stdout
        assert "identical" not in p.stdout and f"RUN_B files: {what}: differs" in p.stdout, p.stdout
        doc = cli_json("compare", str(base), str(b))
        assert doc["identical"] is False and doc["files"]["b"] and not doc["files"]["a"]


# ------------------------------------------------------------------------------ 4. one writer per RUN_DIR


def test_a_second_run_into_a_run_dir_being_written_exits_2(toy):
    from gcvd_flow.engine.outputs import run_dir_lock

    toy_run(toy)
    with run_dir_lock(toy["out"]):  # as a run in progress holds it
        p = toy_run(toy, "--set", "transform.scale=3.0", check=False)
        one_line_error(p, str(toy["out"]), "another run is writing")
    toy_run(toy, "--set", "transform.scale=3.0")  # released: runs


def test_fast_path_never_stamps_a_run_dir_whose_files_differ_from_run_json(toy):
    from gcvd_flow.engine import fastpath

    toy_run(toy)
    out = toy["out"]
    stamp = json.loads((out / fastpath.STAMP).read_text())
    inv = stamp["fingerprint"]["invocation"]
    assert fastpath.check(str(out), inv, str(toy["cache"])) is not None  # the no-op answer
    (out / "report.json").write_text('{"another": "run"}')  # a second writer's file, before the stamp
    fastpath.write(str(out), inv, str(toy["cache"]), stamp["result"], stamp["records"], stamp["watch"])
    assert not (out / fastpath.STAMP).exists()
    assert fastpath.check(str(out), inv, str(toy["cache"])) is None
    doc = cli_json("run", str(toy["input"]), "--out", str(out), "--cache", str(toy["cache"]), *TOY)
    assert "noop" not in doc and json.loads((out / "report.json").read_text()) != {"another": "run"}


# ------------------------------------------------------------------------------ 2. run-many names


def test_run_many_never_writes_two_inputs_into_one_run_dir(tmp_path):
    from gcvd_flow.engine.many import run_dir_names

    inputs = [make_toy_input(tmp_path / sub, n=3, seed=k) for k, sub in enumerate(("a/clip", "b/clip", "c/clip-2"))]
    assert len(set(run_dir_names([str(i) for i in inputs]))) == 3
    out = tmp_path / "runs"
    doc = cli_json("run-many", *map(str, inputs), "--out", str(out), "--cache", str(tmp_path / "cache"), *TOY)
    dirs = [Path(r["out"]) for r in doc["runs"]]
    assert doc["failed"] == 0 and len(set(dirs)) == 3 and sorted(d.name for d in dirs) == ["clip", "clip-2", "clip-3"]
    for inp, d in zip(inputs, dirs):  # each run dir holds its own input's result
        assert json.loads((d / "run.json").read_text())["invocation"]["input"] == str(inp.resolve())


# ------------------------------------------------------------------------------ 3. eval --baseline fails closed


@pytest.mark.parametrize("bad", ['NaN', '"0.01"', 'null', '[0.01]', '1' + '0' * 400, '1e400', '[' * 5000 + ']' * 5000])
def test_eval_baseline_that_cannot_be_compared_is_exit_2(gruns, tmp_path, bad):
    base = tmp_path / "baseline.json"
    base.write_text('{"frames": 16, "ate_rmse": %s, "abs_rel": %s}' % (bad, bad))
    p = cli("eval", str(gruns["base"]), "--gt", str(gruns["clip"]), "--baseline", str(base), "--no-write")
    one_line_error(p, str(base))
    assert "no metric worse" not in p.stdout


def test_eval_baseline_still_gates(gruns, tmp_path):
    doc = cli_json("eval", str(gruns["base"]), "--gt", str(gruns["clip"]), "--no-write")
    base = tmp_path / "baseline.json"
    base.write_text(json.dumps(doc))
    p = cli("eval", str(gruns["base"]), "--gt", str(gruns["clip"]), "--baseline", str(base), "--no-write")
    assert p.returncode == 0 and "no metric worse" in p.stdout, p.stderr
    doc["ate_rmse"] /= 10
    base.write_text(json.dumps(doc))
    p = cli("eval", str(gruns["base"]), "--gt", str(gruns["clip"]), "--baseline", str(base), "--no-write")
    assert p.returncode == 1 and "regression: ate_rmse" in p.stderr, p.stderr


# ------------------------------------------------------------------------------ 5. never outside a remote or the cache


def test_fsck_remote_repair_never_follows_a_symlink_out_of_the_remote(toy):
    toy_run(toy)
    remote = toy["tmp"] / "remote"
    cli("push", str(remote), "--cache", str(toy["cache"]), check=True)
    victim = toy["tmp"] / "victim"
    (victim / "sub").mkdir(parents=True)
    for f in (victim / "a", victim / "sub" / "b"):
        f.write_text("keep")
        os.utime(f, (1e9, 1e9))  # older than any stale-temp-file age
    shutil.rmtree(remote / "tmp", ignore_errors=True)
    (remote / "tmp").symlink_to(victim)
    (remote / "objects" / "zz").symlink_to(victim)
    (remote / "records" / "ab").mkdir(exist_ok=True)
    (remote / "records" / "ab" / ("ab" * 32 + ".json")).symlink_to(victim / "a")
    doc = cli_json("fsck", "--remote", str(remote))
    assert not doc["clean"] and len(doc["stray_files"]) == 3, doc
    doc = cli_json("fsck", "--remote", str(remote), "--repair")
    assert sorted(p.relative_to(victim).as_posix() for p in victim.rglob("*")) == ["a", "sub", "sub/b"]
    assert (victim / "a").read_text() == "keep" and (victim / "sub" / "b").read_text() == "keep"
    assert not (remote / "tmp").exists() and not os.path.lexists(remote / "objects" / "zz")
    assert cli_json("fsck", "--remote", str(remote))["clean"]
    assert cli_json("pull", str(remote), "--cache", str(toy["tmp"] / "c2"))["records"] > 0


def test_fsck_repair_during_a_push_keeps_the_pushed_records(toy):
    """A push that lands between fsck's listings: its records name objects fsck's object listing
    must see (records are listed first); --repair deleted them when objects were listed first."""
    from gcvd_flow.engine import remote as rm
    from gcvd_flow.engine.store import Store

    toy_run(toy)
    r = rm.Remote(str(toy["tmp"] / "remote"))
    toy_run(toy, "--set", "transform.scale=3.0", out=toy["tmp"] / "out2")
    store = Store(toy["cache"])
    first = [json.loads((toy["out"] / "run.json").read_text())["stages"][s]["key"] for s in ("report",)]
    rm.upload(store, r, [k for k, _ in store.iter_records()][:0] + first)  # the remote holds run 1
    later = [s["key"] for s in json.loads((toy["tmp"] / "out2" / "run.json").read_text())["stages"].values()]
    calls = []

    def push_in_between(orig):
        def listing(*a, **kw):
            res = orig(*a, **kw)
            if not calls:
                calls.append(1)
                rm.upload(store, r, later)  # a push lands right after fsck's first listing
            return res
        return listing

    r.object_sizes = push_in_between(r.object_sizes)
    r.record_keys = push_in_between(r.record_keys)
    rep = rm._fsck_remote(r, repair=True)
    assert calls and rep["bad_records"] == [], rep["bad_records"]
    assert set(later) <= rm.Remote(str(toy["tmp"] / "remote")).record_keys()


def test_pin_names_cannot_leave_the_cache(toy):
    toy_run(toy)
    outside = toy["cache"].parent / "x.json"
    for name in ("../x", "/tmp/x", ".hidden", "a/b", ""):
        p = cli("pin", name, "--out", str(toy["out"]), "--cache", str(toy["cache"]))
        one_line_error(p, "pin name")
        p = cli("pin", name, "--remove", "--out", str(toy["out"]), "--cache", str(toy["cache"]))
        one_line_error(p, "pin name")
    assert not outside.exists()
    outside.write_text("mine")
    one_line_error(cli("pin", "../x", "--remove", "--out", str(toy["out"]), "--cache", str(toy["cache"])))
    assert outside.read_text() == "mine"
    cli("pin", "good-1.0", "--out", str(toy["out"]), "--cache", str(toy["cache"]), check=True)


# ------------------------------------------------------------------------------ 6. FIFOs in the local cache


def test_a_fifo_in_the_local_cache_neither_hangs_run_nor_fsck(toy):
    toy_run(toy)
    cache = toy["cache"]
    rec = sorted((cache / "records").glob("*/*.json"))[0]
    rec.unlink()
    os.mkfifo(rec)
    obj = sorted((cache / "objects").glob("*/*"))[0]
    obj.chmod(0o644)
    obj.unlink()
    os.mkfifo(obj)
    p = cli("run", str(toy["input"]), "--out", str(toy["tmp"] / "o2"), "--cache", str(cache), *TOY, timeout=60)
    assert p.returncode == 0, p.stderr
    p = cli("fsck", "--cache", str(cache), "--json", timeout=60)
    assert p.returncode == 0, p.stderr
    assert not [f for f in cache.rglob("*") if f.is_fifo() and "quarantine" not in f.parts]
    assert cli_json("fsck", "--cache", str(cache))["corrupt"] == []


# ------------------------------------------------------------------------------ 7. one bad remote entry (S3)


@pytest.fixture(scope="module")
def s3_golden(tmp_path_factory):
    """moto's S3 server on loopback holding a pushed toy run (s3://BUCKET/golden)."""
    import uuid

    from remote_servers import DUMMY_AWS, moto_s3, s3fs_client

    tmp = tmp_path_factory.mktemp("s3")
    inp = make_toy_input(tmp / "input", n=8)
    bucket = f"hostile-{uuid.uuid4().hex[:8]}"
    with moto_s3() as endpoint:
        fs = s3fs_client(endpoint)
        fs.mkdir(bucket)
        env = {**DUMMY_AWS, "AWS_ENDPOINT_URL": endpoint}
        url = f"s3://{bucket}/golden"
        cli("run", str(inp), "--out", str(tmp / "out"), "--cache", str(tmp / "cache"), *TOY, "--remote", url,
            "--push", env=env, check=True)
        yield {"fs": fs, "env": env, "url": url, "bucket": bucket, "input": inp, "out": tmp / "out",
               "cache": tmp / "cache"}


def _tamper(s3, kind: str) -> tuple[str, str]:
    """A copy of the golden remote with one bad entry; (url, the bad entry's key or digest)."""
    import uuid

    from gcvd_flow.engine.store import Store

    fs, url = s3["fs"], f"s3://{s3['bucket']}/{uuid.uuid4().hex[:8]}"
    fs.copy(s3["url"].removeprefix("s3://") + "/", url.removeprefix("s3://") + "/", recursive=True)
    store = Store(s3["cache"])
    key = json.loads((s3["out"] / "run.json").read_text())["stages"]["transform"]["key"]
    child = store.get_record(key)["children"][2]  # one item of a map stage
    rec_path = f"{url.removeprefix('s3://')}/records/{child[:2]}/{child}.json"
    if kind == "empty object":  # one the export has to read
        report = json.loads((s3["out"] / "run.json").read_text())["stages"]["report"]["key"]
        digest = sorted(store.get_record(report)["objects"])[0]
        fs.pipe(f"{url.removeprefix('s3://')}/objects/{digest[:2]}/{digest[2:]}", b"")
        return url, digest
    if kind == "empty record":
        fs.pipe(rec_path, b"")
    elif kind == "nested record":
        fs.pipe(rec_path, b"[" * 200_000)
    elif kind == "huge size":
        rec = store.get_record(child)
        rec["objects"] = {d: 10 ** 100 for d in rec["objects"]}
        fs.pipe(rec_path, json.dumps(rec).encode())
    return url, child


@pytest.mark.parametrize("kind", ["empty object", "empty record", "nested record", "huge size"])
def test_one_bad_s3_entry_is_skipped_and_repaired(s3_golden, tmp_path, kind):
    s3 = s3_golden
    url, bad = _tamper(s3, kind)
    env = s3["env"]
    # a read-through run uses the rest of the remote: only the bad item is recomputed
    p = cli("run", str(s3["input"]), "--out", str(tmp_path / "o"), "--cache", str(tmp_path / "c1"), *TOY,
            "--remote", url, "--json", env=env)
    assert p.returncode == 0, p.stderr
    doc = json.loads(p.stdout)
    assert "failed" not in doc["remote"] and "damaged" not in p.stderr, p.stderr
    assert bad[:12] in p.stderr and sum(s["executed"] for s in doc["stages"]) <= 4, (p.stderr, doc["stages"])
    # pull takes everything else, with one warning
    p = cli("pull", "--remote", url, "--cache", str(tmp_path / "c2"), "--json", env=env)
    assert p.returncode == 0, p.stderr
    assert [ln for ln in p.stderr.splitlines() if ln.strip()] and bad[:12] in p.stderr
    assert json.loads(p.stdout)["records"] > 8
    # fsck --remote names it, --repair removes it, and the remote is clean
    doc = cli_json("fsck", "--remote", url, env=env)
    assert not doc["clean"] and any(bad in line for line in doc["bad_objects"] + doc["bad_records"]), doc
    cli("fsck", "--remote", url, "--repair", env=env, check=True)
    assert cli_json("fsck", "--remote", url, env=env)["clean"]


def test_s3_unreachable_or_misconfigured_is_one_line(tmp_path):
    from remote_servers import DUMMY_AWS

    env = {**DUMMY_AWS, "AWS_ENDPOINT_URL": "http://127.0.0.1:1", "AWS_MAX_ATTEMPTS": "1"}
    for verb in (("pull",), ("fsck",)):
        args = (*verb, "--remote", "s3://nobucket/x") + (() if verb[0] == "fsck" else ("--cache", str(tmp_path / "c")))
        one_line_error(cli(*args, env=env, timeout=120), "s3://nobucket/x")
    remotes = tmp_path / "remotes.toml"
    remotes.write_text('[remotes.t]\nurl = "s3://b/p"\nendpoint_url = 12\n')
    one_line_error(cli("pull", "--remote", "t", "--remotes", str(remotes), "--cache", str(tmp_path / "c")),
                   "endpoint_url")


# ------------------------------------------------------------------------------ 8. a full disk under RUN_DIR


def test_full_disk_under_run_dir_names_it(gruns, tmp_path):
    small = tmp_path / "small"
    small.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=300k", "tmpfs", str(small)], capture_output=True).returncode:
        pytest.skip("cannot mount a small tmpfs here (needs root / CAP_SYS_ADMIN)")
    try:  # every stage is cached: only the export writes, and the depth maps do not fit
        p = cli("run", str(gruns["clip"]), "--out", str(small / "out"), "--cache", str(gruns["cache"]),
                "--profile", "fast")
        line = one_line_error(p, str(small / "out"))
        assert "disk full" in line or "No space left" in line, line
    finally:
        subprocess.run(["umount", "-l", str(small)], capture_output=True)
