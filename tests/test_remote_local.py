"""Directory remotes through fsspec (plain paths and file:// URLs): names from the remotes file,
temporary files and renames, what fsck --remote reports and repairs, usage errors."""

from __future__ import annotations

import os
import time

from conftest import by_stage, cli, cli_json, make_toy_input

from gcvd_flow.engine.store import Store


def test_named_directory_remote_fsck_and_repair(tmp_path):
    inp = make_toy_input(tmp_path / "input", n=6)
    share = tmp_path / "share"
    remotes = tmp_path / "remotes.toml"
    remotes.write_text(f'default = "share"\n[remotes.share]\nurl = "file://{share}"\n')
    cli_json("run", str(inp), "--out", str(tmp_path / "oa"), "--cache", str(tmp_path / "ca"), "--pipeline", "toy")
    # the default remote of the remotes file, given by --remotes
    rep = cli_json("push", "--remotes", str(remotes), "--cache", str(tmp_path / "ca"), "--out", str(tmp_path / "oa"))
    assert rep["records"] > 6 and not any((share / "tmp").iterdir())
    again = cli_json("push", "--remotes", str(remotes), "--cache", str(tmp_path / "ca"), "--all")
    assert again["objects"] == 0 and again["records"] == 0  # only what is missing moves
    assert Store(share).fsck().corrupt == []  # a directory remote is a cache directory

    # what a killed writer leaves behind: a temporary file (reported, not bad), and a stray FIFO
    stale = share / "tmp" / "12345-deadbeef"
    stale.write_bytes(b"partial")
    old = time.time() - 3600
    os.utime(stale, (old, old))
    fifo = share / "objects" / "ab" / ("c" * 62)
    fifo.parent.mkdir(parents=True, exist_ok=True)
    os.mkfifo(fifo)
    victim = next(d for d in Store(share).iter_objects() if not d.startswith("ab"))
    vp = Store(share).object_path(victim)
    vp.write_bytes(vp.read_bytes()[:-1])  # truncated
    rep = cli_json("fsck", "--remote", "share", "--remotes", str(remotes))
    assert not rep["clean"] and rep["tmp_files"] == 1 and stale.exists() and fifo.exists()
    assert [b.split(":")[0] for b in rep["bad_objects"]] == [victim] and rep["bad_records"]
    assert rep["stray_files"] == [str(fifo)]
    text = cli("fsck", "--remote", f"file://{share}", check=True).stdout
    assert "--repair" in text and f"bad: {victim}" in text
    rep = cli_json("fsck", "--remote", str(share), "--repair")
    assert rep["repaired"] and rep["tmp_removed"] == 1
    assert not stale.exists() and not fifo.exists() and not vp.exists()
    assert cli_json("fsck", "--remote", str(share))["clean"]
    # the next push restores what repair deleted; a reader computes nothing
    cli_json("push", str(share), "--cache", str(tmp_path / "ca"))
    doc = cli_json("run", str(inp), "--out", str(tmp_path / "ob"), "--cache", str(tmp_path / "cb"), "--pipeline",
                   "toy", "--remote", "share", env={"GCVD_FLOW_REMOTES": str(remotes)})
    assert all(s["executed"] == 0 for s in by_stage(doc).values())


def test_remote_usage_errors_are_one_line(tmp_path):
    cache = tmp_path / "cache"
    p = cli("push", str(tmp_path / "a"), "--remote", str(tmp_path / "b"), "--cache", str(cache))
    assert p.returncode == 2 and "give the remote once" in p.stderr
    p = cli("push", "--cache", str(cache), env={"GCVD_FLOW_REMOTES": str(tmp_path / "none.toml")})
    assert p.returncode == 2 and "no remote given" in p.stderr
    bad = tmp_path / "bad.toml"
    bad.write_text("[remotes.x\n")
    p = cli("pull", "--remote", "x", "--remotes", str(bad), "--cache", str(cache))
    assert p.returncode == 2 and "not valid TOML" in p.stderr
    p = cli("fsck", "--remote", str(tmp_path / "nothing-here"))
    assert p.returncode == 2 and "remote not found" in p.stderr
    (tmp_path / "file").write_text("x")
    p = cli("push", str(tmp_path / "file"), "--cache", str(cache))
    assert p.returncode == 2 and "is a file" in p.stderr
