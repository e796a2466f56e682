"""Directory remotes through fsspec (plain paths and file:// URLs): names from the remotes file,
temporary files and renames, what fsck --remote reports and repairs, usage errors; read-through
runs that download only the objects they read."""

from __future__ import annotations

import json
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


# ------------------------------------------------------------------------------ lazy read-through


def _objects_of(store: Store, key: str) -> dict[str, int]:
    return store.get_record(key)["objects"]


def _stage_keys(out) -> dict[str, str]:
    return {k: v["key"] for k, v in json.loads((out / "run.json").read_text())["stages"].items()}


def _item_objects(store: Store, key: str) -> set[str]:
    """The objects of a map stage's items (not its own manifest)."""
    return {d for c in store.get_record(key)["children"] for d in store.get_record(c)["objects"]}


def test_read_through_downloads_only_the_objects_the_run_reads(tmp_path):
    inp = make_toy_input(tmp_path / "input", n=12)
    share = tmp_path / "share"
    cli_json("run", str(inp), "--out", str(tmp_path / "oa"), "--cache", str(tmp_path / "ca"), "--pipeline", "toy")
    pushed = cli_json("push", str(share), "--cache", str(tmp_path / "ca"))
    a, keys = Store(tmp_path / "ca"), _stage_keys(tmp_path / "oa")
    a_objects = set(a.iter_objects())
    assert pushed["objects"] == len(a_objects) > 40
    b_run = ["run", str(inp), "--cache", str(tmp_path / "cb"), "--pipeline", "toy", "--remote", str(share)]
    doc = cli_json(*b_run, "--out", str(tmp_path / "ob"))
    assert all(s["executed"] == 0 for s in doc["stages"])
    assert (tmp_path / "ob" / "report.json").read_bytes() == (tmp_path / "oa" / "report.json").read_bytes()
    b_objects = set(Store(tmp_path / "cb").iter_objects())
    pulled = doc["remote"]["pulled"]
    # the records came in naming every object; only what the run read was downloaded: the two
    # map stages' manifests (their item lists give the downstream keys) and report's output
    assert pulled["objects_named"] == len(a_objects) and pulled["bytes_named"] == pushed["bytes"]
    assert b_objects == {a.get_record(keys[s])["outputs"] for s in ("decode", "transform", "report")}
    assert pulled["objects"] == len(b_objects) == 3 and pulled["bytes"] < pushed["bytes"] / 20
    item_objects = _item_objects(a, keys["decode"]) | _item_objects(a, keys["transform"])
    assert len(item_objects) == 48 and not item_objects & b_objects
    # a stage to recompute reads its inputs: a whole stage in this process (summarize's output,
    # fetched when threshold decodes it), map items in worker processes (the runner fetches a
    # task's inputs before dispatching it) -- on a process pool and on Dask
    doc = cli_json(*b_run, "--out", str(tmp_path / "oc"), "--set", "threshold.cut=100")
    assert [s["name"] for s in doc["stages"] if s["executed"]] == ["threshold", "report"]
    assert set(_objects_of(a, keys["summarize"])) <= set(Store(tmp_path / "cb").iter_objects())
    for n, executor in ((3, ["--jobs", "2"]), (4, ["--executor", "dask", "--jobs", "2"])):
        doc = cli_json(*b_run, "--out", str(tmp_path / f"o{n}"), "--set", f"transform.scale={n}", *executor)
        assert by_stage(doc)["decode"]["executed"] == 0 and by_stage(doc)["transform"]["executed"] == 12
    b_objects = set(Store(tmp_path / "cb").iter_objects())
    assert _item_objects(a, keys["decode"]) <= b_objects and not _item_objects(a, keys["transform"]) & b_objects
    # without the remote, a record whose objects never came is not usable: recomputed, as ever
    doc = cli_json("run", str(inp), "--cache", str(tmp_path / "cb"), "--pipeline", "toy", "--out",
                   str(tmp_path / "od"))
    assert by_stage(doc)["transform"]["executed"] == 12 and by_stage(doc)["decode"]["executed"] == 0


def test_a_lazily_fetched_corrupt_object_is_refused_and_its_stage_recomputed(tmp_path):
    inp = make_toy_input(tmp_path / "input", n=8)
    share = tmp_path / "share"
    cli_json("run", str(inp), "--out", str(tmp_path / "oa"), "--cache", str(tmp_path / "ca"), "--pipeline", "toy")
    cli_json("push", str(share), "--cache", str(tmp_path / "ca"))
    a, keys, rs = Store(tmp_path / "ca"), _stage_keys(tmp_path / "oa"), Store(share)
    # report's output (read to write RUN_DIR) and an item's array (never read by this run)
    read, unread = a.get_record(keys["report"])["outputs"], sorted(_item_objects(a, keys["transform"]))[0]
    for d in (read, unread):
        p = rs.object_path(d)
        data = bytearray(p.read_bytes())
        data[len(data) // 2] ^= 0x01
        p.chmod(0o644)
        p.write_bytes(bytes(data))
    p = cli("run", str(inp), "--out", str(tmp_path / "ob"), "--cache", str(tmp_path / "cb"), "--pipeline", "toy",
            "--remote", str(share), "--json")
    assert p.returncode == 0, p.stderr
    warnings = [ln for ln in p.stderr.splitlines() if ln.startswith("warning:")]
    assert len(warnings) == 1 and read[:12] in warnings[0] and "refused" in warnings[0], p.stderr
    doc = json.loads(p.stdout)
    assert [s["name"] for s in doc["stages"] if s["executed"]] == ["report"]
    assert doc["remote"]["pulled"]["refused_objects"] == [read] and doc["healed"]["recomputed"] == ["report"]
    assert (tmp_path / "ob" / "report.json").read_bytes() == (tmp_path / "oa" / "report.json").read_bytes()
    b = Store(tmp_path / "cb")
    assert b.fsck().corrupt == [] and not b.has(unread) and b.has(read)  # recomputed: the producer's bytes


def test_a_remote_lost_after_its_records_came_in_is_one_warning_and_the_run_goes_on(tmp_path, monkeypatch):
    from gcvd_flow.engine import api
    from gcvd_flow.engine.remote import Remote

    inp = make_toy_input(tmp_path / "input", n=6)
    share = tmp_path / "share"
    cli_json("run", str(inp), "--out", str(tmp_path / "oa"), "--cache", str(tmp_path / "ca"), "--pipeline", "toy")
    cli_json("push", str(share), "--cache", str(tmp_path / "ca"))
    read_many = Remote.read_many

    def records_only(self, paths, limits):  # the network goes down once the records are in
        if any("/objects/" in p for p in paths):
            raise ConnectionError("connection reset by peer")
        return read_many(self, paths, limits)

    monkeypatch.setattr(Remote, "read_many", records_only)
    lines: list[str] = []
    doc = api.run(api.Invocation(input=str(inp), out=str(tmp_path / "ob"), cache=str(tmp_path / "cb"),
                                 pipeline="toy", remote=str(share)), log=lines.append)
    assert len(lines) == 1 and "going on without the remote" in lines[0] and "ConnectionError" in lines[0], lines
    assert doc["remote"]["failed"] and doc["remote"]["pulled"]["objects"] == 0
    assert by_stage(doc)["decode"]["executed"] == 6 and by_stage(doc)["transform"]["executed"] == 6
    assert (tmp_path / "ob" / "report.json").read_bytes() == (tmp_path / "oa" / "report.json").read_bytes()
