"""Faults and hostile input, driven through the CLI (issues "faults" and "cache correctness").

Every case ends in exit 0 (where the cache can heal) or exit 2 with exactly one line on stderr
that names the file or key, never a traceback, and with a cache that ``fsck`` reports clean.
Most cases use the toy pipeline (fast); the vision-specific ones (paths, weights, intrinsics)
run the GCVD pipeline on a few tiny frames.
"""

from __future__ import annotations

import json
import os
import pickle
import random
import shutil
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, by_stage, cli, cli_json, make_toy_input

from gcvd_flow.engine.store import Store

TOY = ("--pipeline", "toy")


def toy_run(inp: Path, out: Path, cache: Path, *extra: str, check: bool = True):
    p = cli("run", str(inp), "--out", str(out), "--cache", str(cache), *TOY, *extra, "--json")
    if check:
        assert p.returncode == 0, p.stderr
    return p


def one_line_error(p: subprocess.CompletedProcess, *fragments: str) -> str:
    """The process failed cleanly: exit 2, one stderr line 'gcvd-flow: error: ...' naming things."""
    assert p.returncode == 2, (p.returncode, p.stderr)
    lines = [ln for ln in p.stderr.splitlines() if ln.strip() and not ln.startswith("camera:")]
    assert len(lines) == 1, p.stderr
    assert lines[0].startswith("gcvd-flow: error: ") and "Traceback" not in p.stderr, p.stderr
    for f in fragments:
        assert f in lines[0], (f, lines[0])
    return lines[0]


def fsck_clean(cache: Path) -> None:
    doc = cli_json("fsck", "--cache", str(cache))
    assert doc["corrupt"] == [], doc


def outputs(run_dir: Path) -> dict[str, str]:
    return {k: v["output"] for k, v in json.loads((run_dir / "run.json").read_text())["stages"].items()}


# ------------------------------------------------------------------------------ self-healing cache


def flip_objects(cache: Path, digests: list[str]) -> None:
    store = Store(cache)
    for d in digests:
        p = store.object_path(d)
        os.chmod(p, 0o644)
        data = bytearray(p.read_bytes())
        data[len(data) // 2] ^= 0xFF
        p.write_bytes(bytes(data))


def flip_random_objects(cache: Path, k: int, seed: int, must: tuple[str, ...] = ()) -> list[str]:
    """Flip a byte in k random objects, plus those in ``must`` (objects the next run has to read)."""
    objs = sorted(Store(cache).iter_objects())
    victims = sorted(set(random.Random(seed).sample(objs, min(k, len(objs)))) | set(must))
    flip_objects(cache, victims)
    return victims


def heal_and_check(run, first: Path, cache: Path, tmp_path: Path) -> None:
    """Run again: identical outputs, one warning naming what was recomputed; then fsck
    quarantines what the run did not need to read, and the next run restores that too."""
    p = run(tmp_path / "again")
    assert p.returncode == 0 and "Traceback" not in p.stderr, p.stderr
    warnings = [ln for ln in p.stderr.splitlines() if ln.startswith("warning:")]
    assert len(warnings) == 1 and "recomputed" in warnings[0], p.stderr
    assert outputs(tmp_path / "again") == outputs(first)
    cli_json("fsck", "--cache", str(cache))  # quarantines corrupt objects no run needed yet
    for name in ("again2", "again3"):
        p = run(tmp_path / name)
        assert p.returncode == 0, p.stderr
        assert outputs(tmp_path / name) == outputs(first)
    fsck_clean(cache)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_corruption_heals_to_identical_outputs(tmp_path, seed):
    inp = make_toy_input(tmp_path / "in", n=30)
    cache, first = tmp_path / "cache", tmp_path / "first"
    toy_run(inp, first, cache)
    flip_random_objects(cache, k=8, seed=seed, must=(outputs(first)["report"],))
    heal_and_check(lambda out: toy_run(inp, out, cache, check=False), first, cache, tmp_path)
    assert (tmp_path / "again" / "report.json").read_bytes() == (first / "report.json").read_bytes()
    res = by_stage(json.loads(toy_run(inp, tmp_path / "fourth", cache).stdout))
    assert sum(s["executed"] for s in res.values()) == 0


def test_gcvd_run_heals_from_random_corruption(tmp_path, tiny_clip):
    cache = tmp_path / "cache"
    args = ("--cache", str(cache), "--profile", "fast")
    cli("run", str(tiny_clip), "--out", str(tmp_path / "a"), *args, check=True)
    seg = json.loads((tmp_path / "a" / "run.json").read_text())["stages"]["depth_filter"]["output"]
    flip_random_objects(cache, k=6, seed=7, must=(seg,))
    heal_and_check(lambda out: cli("run", str(tiny_clip), "--out", str(out), *args), tmp_path / "a", cache, tmp_path)
    for f in ("poses.txt", "cameras.json"):
        assert (tmp_path / "again" / f).read_bytes() == (tmp_path / "a" / f).read_bytes()


def test_object_deleted_by_hand_is_recomputed(tmp_path):
    inp = make_toy_input(tmp_path / "in", n=10)
    cache = tmp_path / "cache"
    toy_run(inp, tmp_path / "a", cache)
    store = Store(cache)
    victim = sorted(store.iter_objects())[3]
    store.object_path(victim).unlink()
    p = toy_run(inp, tmp_path / "b", cache)
    assert outputs(tmp_path / "b") == outputs(tmp_path / "a")
    assert store.object_size(victim) is not None or "warning" in p.stderr


def test_truncated_object_is_rewritten(tmp_path):
    """put_bytes used to skip a path that existed: a truncated object stayed truncated forever."""
    inp = make_toy_input(tmp_path / "in", n=10)
    cache = tmp_path / "cache"
    toy_run(inp, tmp_path / "a", cache)
    store = Store(cache)
    sizes = {d: store.object_size(d) for d in store.iter_objects()}
    victim = max(sizes, key=sizes.get)
    p = store.object_path(victim)
    os.chmod(p, 0o644)
    p.write_bytes(p.read_bytes()[: sizes[victim] // 2])
    toy_run(inp, tmp_path / "b", cache)
    assert store.object_size(victim) == sizes[victim]
    assert outputs(tmp_path / "b") == outputs(tmp_path / "a")
    fsck_clean(cache)


# ------------------------------------------------------------------------------ records and remotes


def _record_of(run_dir: Path, stage: str) -> str:
    return json.loads((run_dir / "run.json").read_text())["stages"][stage]["key"]


def test_swapped_record_on_a_remote_is_never_used(tmp_path):
    """A record filed under another key (valid objects, wrong key) must not substitute results."""
    inp = make_toy_input(tmp_path / "in", n=10)
    remote = tmp_path / "remote"
    default, other = tmp_path / "default", tmp_path / "other"
    toy_run(inp, default, tmp_path / "ca")
    toy_run(inp, other, tmp_path / "ca", "--set", "summarize.digits=2")
    cli_json("push", str(remote), "--cache", str(tmp_path / "ca"))
    rs = Store(remote)
    key_default, key_other = _record_of(default, "summarize"), _record_of(other, "summarize")
    shutil.copyfile(rs.record_path(key_other), rs.record_path(key_default))
    doc = cli_json("pull", str(remote), "--cache", str(tmp_path / "cb"))
    assert any(key_default[:12] in r for r in doc["refused_records"]), doc
    mine = tmp_path / "mine"
    toy_run(inp, mine, tmp_path / "cb")
    assert outputs(mine) == outputs(default)
    assert (mine / "report.json").read_bytes() == (default / "report.json").read_bytes()


def test_swapped_record_in_the_local_cache_is_ignored(tmp_path):
    inp = make_toy_input(tmp_path / "in", n=10)
    cache = tmp_path / "cache"
    a, b = tmp_path / "a", tmp_path / "b"
    toy_run(inp, a, cache)
    toy_run(inp, b, cache, "--set", "threshold.cut=10")
    st = Store(cache)
    shutil.copyfile(st.record_path(_record_of(b, "threshold")), st.record_path(_record_of(a, "threshold")))
    c = tmp_path / "c"
    res = by_stage(json.loads(toy_run(inp, c, cache).stdout))
    assert res["threshold"]["executed"] == 1
    assert outputs(c) == outputs(a)


def test_hostile_remote_fifo_and_symlink_objects_are_refused(tmp_path):
    inp = make_toy_input(tmp_path / "in", n=6)
    remote = tmp_path / "remote"
    toy_run(inp, tmp_path / "a", tmp_path / "ca")
    cli_json("push", str(remote), "--cache", str(tmp_path / "ca"))
    rs = Store(remote)
    objs = sorted(rs.iter_objects())
    fifo, link = rs.object_path(objs[0]), rs.object_path(objs[1])
    fifo.unlink()
    os.mkfifo(fifo)
    link.unlink()
    os.symlink("/dev/zero", link)
    p = cli("pull", str(remote), "--cache", str(tmp_path / "cb"), "--json", timeout=60)  # a FIFO used to hang
    assert p.returncode == 0, p.stderr
    doc = json.loads(p.stdout)
    assert doc["refused"] == 2 and set(doc["refused_objects"]) == {objs[0], objs[1]}
    fsck_clean(tmp_path / "cb")
    toy_run(inp, tmp_path / "b", tmp_path / "cb")
    assert outputs(tmp_path / "b") == outputs(tmp_path / "a")


def test_push_to_a_file_is_a_one_line_error(tmp_path):
    inp = make_toy_input(tmp_path / "in", n=4)
    toy_run(inp, tmp_path / "a", tmp_path / "ca")
    target = tmp_path / "not-a-dir"
    target.write_text("x")
    one_line_error(cli("push", str(target), "--cache", str(tmp_path / "ca")), str(target))


# ------------------------------------------------------------------------------ gc


def test_gc_never_races_a_run(tmp_path):
    inp = make_toy_input(tmp_path / "in", n=40)
    cache, out = tmp_path / "cache", tmp_path / "out"
    cmd = [sys.executable, "-m", "gcvd_flow", "run", str(inp), "--out", str(out), "--cache", str(cache), *TOY,
           "--set", "transform.sleep=0.03", "--json"]
    run = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    gcs = 0
    while run.poll() is None and gcs < 40:
        g = cli("gc", "--keep", "0", "--cache", str(cache), "--no-wait")
        assert g.returncode in (0, 2), g.stderr
        gcs += 1
        time.sleep(0.1)
    stdout, stderr = run.communicate(timeout=120)
    assert run.returncode == 0, stderr
    assert gcs > 0
    # a gc that waits for the run instead: the default; the run's records survive a default gc
    res = by_stage(json.loads(toy_run(inp, tmp_path / "again", cache).stdout))
    cli_json("gc", "--cache", str(cache))
    res = by_stage(json.loads(toy_run(inp, tmp_path / "again2", cache).stdout))
    assert sum(s["executed"] for s in res.values()) == 0
    fsck_clean(cache)


def test_gc_waits_for_a_live_lease(tmp_path):
    inp = make_toy_input(tmp_path / "in", n=4)
    cache = tmp_path / "cache"
    toy_run(inp, tmp_path / "a", cache)
    store = Store(cache)
    with store.lease():
        one_line_error(cli("gc", "--keep", "0", "--cache", str(cache), "--no-wait"), "gc")
        assert any(True for _ in store.iter_objects())


@pytest.mark.parametrize("keep", ["-1", "-100", "99999999999"])
def test_gc_rejects_negative_or_absurd_keep(tmp_path, keep):
    inp = make_toy_input(tmp_path / "in", n=4)
    cache = tmp_path / "cache"
    toy_run(inp, tmp_path / "a", cache)
    n = len(list(Store(cache).iter_objects()))
    one_line_error(cli("gc", "--keep", keep, "--cache", str(cache)), "--keep")
    assert len(list(Store(cache).iter_objects())) == n


# ------------------------------------------------------------------------------ data never chooses code


def test_run_dir_cannot_name_code_to_import(tmp_path):
    inp = make_toy_input(tmp_path / "in", n=4)
    run_dir = tmp_path / "shared-run"
    toy_run(inp, run_dir, tmp_path / "cache")
    marker = tmp_path / "PWNED"
    (run_dir / "evilmod.py").write_text(f"open({str(marker)!r}, 'w').write('x')\nSPEC = None\n")
    doc = json.loads((run_dir / "run.json").read_text())
    doc["invocation"]["pipeline"] = "evilmod:SPEC"
    (run_dir / "run.json").write_text(json.dumps(doc))
    for verb in (["status", "--out", str(run_dir)], ["why", "report", "--out", str(run_dir)]):
        env = {"PYTHONPATH": str(run_dir)}
        p = subprocess.run([sys.executable, "-m", "gcvd_flow", *verb, "--cache", str(tmp_path / "cache")],
                           cwd=run_dir, capture_output=True, text=True, env={**os.environ, **env}, timeout=120)
        one_line_error(p, "evilmod:SPEC", "run.json")
        assert not marker.exists()


# ------------------------------------------------------------------------------ bad paths and inputs


@pytest.fixture(scope="module")
def tiny_clip(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("tiny") / "clip"
    cli("synth", str(d), "--frames", "8", "--size", "64x48", "--trajectory", "orbit", check=True)
    return d


def test_non_utf8_paths_work_or_exit_2(tmp_path, tiny_clip):
    weird = Path(os.fsdecode(bytes(tmp_path) + b"/clip\xff"))
    shutil.copytree(tiny_clip, weird)
    p = cli("run", str(weird), "--out", str(tmp_path / "o"), "--cache", str(tmp_path / "c"), "--profile", "fast",
            "--until", "masks")
    assert p.returncode == 0, p.stderr  # used to be a segfault (exit -11)
    video = Path(os.fsdecode(bytes(tmp_path) + b"/v\xff.mp4"))
    video.write_bytes(b"\0" * 64)
    one_line_error(cli("run", str(video), "--out", str(tmp_path / "o2"), "--cache", str(tmp_path / "c")), "UTF-8")


def test_device_and_fifo_inputs(tmp_path):
    fifo = tmp_path / "pipe.mp4"
    os.mkfifo(fifo)
    for inp in ("/dev/null", str(fifo)):
        one_line_error(cli("run", inp, "--out", str(tmp_path / "o"), "--cache", str(tmp_path / "c"), timeout=60), inp)


def test_out_dir_that_is_a_file_or_under_one(tmp_path, tiny_clip):
    f = tmp_path / "file"
    f.write_text("x")
    one_line_error(cli("run", str(tiny_clip), "--out", str(f), "--cache", str(tmp_path / "c")), str(f))
    one_line_error(cli("run", str(tiny_clip), "--out", str(f / "sub"), "--cache", str(tmp_path / "c")), str(f))
    one_line_error(cli("run", str(tiny_clip), "--out", str(tmp_path / "o"), "--cache", str(f)), str(f))


def test_config_path_that_is_a_directory(tmp_path, tiny_clip):
    one_line_error(cli("run", str(tiny_clip), "--out", str(tmp_path / "o"), "--cache", str(tmp_path / "c"),
                       "--config", str(tmp_path)), str(tmp_path))


def test_raft_without_weights(tmp_path, tiny_clip):
    one_line_error(cli("run", str(tiny_clip), "--out", str(tmp_path / "o"), "--cache", str(tmp_path / "c"),
                       "--set", "flow.backend=raft"), "flow.weights")


def _weights_run(tmp_path: Path, clip: Path, weights: Path) -> subprocess.CompletedProcess:
    return cli("run", str(clip), "--out", str(tmp_path / "o"), "--cache", str(tmp_path / "c"), "--profile", "fast",
               "--set", "flow.backend=raft", "--set", f"flow.weights={json.dumps(str(weights))}", "--until", "flow")


class _Evil:
    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_malicious_and_malformed_weights(tmp_path, tiny_clip):
    marker = tmp_path / "PWNED"
    evil = tmp_path / "evil.pth"
    with open(evil, "wb") as f:  # a pickle that would run a command when unpickled (must be refused)
        pickle.dump({"w": _Evil(str(marker))}, f)
    one_line_error(_weights_run(tmp_path, tiny_clip, evil), "evil.pth", "unpickle")
    assert not marker.exists()
    huge = tmp_path / "huge.safetensors"
    huge.write_bytes(struct.pack("<Q", 1 << 50) + b"{}")
    one_line_error(_weights_run(tmp_path, tiny_clip, huge), "huge.safetensors")
    import torch
    from safetensors.torch import save_file

    wrong = tmp_path / "wrong.safetensors"
    save_file({"conv.weight": torch.zeros(3, 3)}, str(wrong))
    one_line_error(_weights_run(tmp_path, tiny_clip, wrong), "wrong.safetensors", "RAFT")
    fsck_clean(tmp_path / "c")


def test_edited_intrinsics_file_reruns_ingest(tmp_path, tiny_clip):
    """intrinsics.txt is an input of ingest: editing it must change the cameras, not be ignored."""
    clip = tmp_path / "clip"
    shutil.copytree(tiny_clip, clip)
    args = ("--cache", str(tmp_path / "c"), "--profile", "fast", "--until", "flow", "--json")
    cli("run", str(clip), "--out", str(tmp_path / "a"), *args, check=True)
    fx, fy, cx, cy = (clip / "intrinsics.txt").read_text().split()
    (clip / "intrinsics.txt").write_text(f"{float(fx) * 1.5} {fy} {cx} {cy}\n")
    doc = by_stage(json.loads(cli("run", str(clip), "--out", str(tmp_path / "b"), *args, check=True).stdout))
    assert doc["ingest"]["executed"] + doc["ingest"]["cached"] > 0
    from gcvd_flow import api

    cam = api.recorded_output(tmp_path / "b", "ingest", str(tmp_path / "c")).summary
    assert np.isclose(np.asarray(cam["K"])[0, 0], float(fx) * 1.5)


# ------------------------------------------------------------------------------ full or read-only disks


def _mount_tmpfs(where: Path, opts: str) -> bool:
    where.mkdir(parents=True, exist_ok=True)
    return subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(where)],
                          capture_output=True).returncode == 0


def _umount(where: Path) -> None:
    subprocess.run(["umount", "-l", str(where)], capture_output=True)


@pytest.fixture
def small_fs(tmp_path):
    mnt = tmp_path / "small"
    if not _mount_tmpfs(mnt, "size=256k"):
        pytest.skip("cannot mount a small tmpfs here (needs root / CAP_SYS_ADMIN)")
    yield mnt
    _umount(mnt)


def test_disk_full_on_the_cache(tmp_path, small_fs):
    inp = make_toy_input(tmp_path / "in", n=40, size=20000)  # ~3 MB of decoded items: does not fit
    p = cli("run", str(inp), "--out", str(tmp_path / "o"), "--cache", str(small_fs / "cache"), *TOY)
    one_line_error(p, "No space left")
    fsck_clean(small_fs / "cache")


def test_disk_full_on_the_output(tmp_path, small_fs):
    inp = make_toy_input(tmp_path / "in", n=4)
    filler = small_fs / "filler"
    with open(filler, "wb") as f:  # leave almost nothing free
        try:
            f.write(b"\0" * (256 << 10))
        except OSError:
            pass
    p = cli("run", str(inp), "--out", str(small_fs / "out"), "--cache", str(tmp_path / "c"), *TOY)
    one_line_error(p, "No space left")
    fsck_clean(tmp_path / "c")


def test_read_only_output_and_cache(tmp_path):
    ro = tmp_path / "ro"
    if not _mount_tmpfs(ro, "ro,size=64k"):
        pytest.skip("cannot mount a read-only tmpfs here (needs root / CAP_SYS_ADMIN)")
    try:
        inp = make_toy_input(tmp_path / "in", n=4)
        one_line_error(cli("run", str(inp), "--out", str(ro / "out"), "--cache", str(tmp_path / "c"), *TOY), str(ro))
        one_line_error(cli("run", str(inp), "--out", str(tmp_path / "o"), "--cache", str(ro / "cache"), *TOY),
                       str(ro))
    finally:
        _umount(ro)


def test_sigint_during_heal_free_run_is_consistent(tmp_path):
    """Ctrl-C still exits 130 with a consistent cache under the lease (regression guard)."""
    inp = make_toy_input(tmp_path / "in", n=40)
    cache = tmp_path / "cache"
    cmd = [sys.executable, "-m", "gcvd_flow", "run", str(inp), "--out", str(tmp_path / "o"), "--cache", str(cache),
           *TOY, "--set", "transform.sleep=0.05"]
    p = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    time.sleep(1.5)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    fsck_clean(cache)
    one = cli("gc", "--cache", str(cache), "--no-wait")  # the lease died with the run
    assert one.returncode == 0, one.stderr
