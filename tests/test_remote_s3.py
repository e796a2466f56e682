"""Remote caches on S3: s3fs against moto's standalone server on 127.0.0.1 (real HTTP, not an
in-process mock of boto calls), driven through the CLI as two machines with separate caches."""

from __future__ import annotations

import json
import uuid
from pathlib import Path

import pytest
from conftest import by_stage, cli, cli_json, make_toy_input
from remote_servers import DUMMY_AWS, moto_s3, s3fs_client

from gcvd_flow.engine.store import Store

BUCKET = f"gcvd-team-{uuid.uuid4().hex[:8]}"  # moto's state is shared by its servers in a process


@pytest.fixture(scope="module")
def s3():
    with moto_s3() as endpoint:
        fs = s3fs_client(endpoint)
        fs.mkdir(BUCKET)
        yield {"endpoint": endpoint, "fs": fs, "env": {**DUMMY_AWS, "AWS_ENDPOINT_URL": endpoint}}


@pytest.fixture(scope="module")
def machine_a(s3, tmp_path_factory):
    """Machine A ran the toy pipeline and pushed it to s3://BUCKET/golden (by a configured name)."""
    tmp = tmp_path_factory.mktemp("machine_a")
    inp = make_toy_input(tmp / "input", n=12)
    remotes = tmp / "remotes.toml"
    # the endpoint from the remotes file (an fsspec option), not from the environment
    remotes.write_text(f'[remotes.team]\nurl = "s3://{BUCKET}/golden"\nendpoint_url = "{s3["endpoint"]}"\n')
    env = {**DUMMY_AWS, "GCVD_FLOW_REMOTES": str(remotes)}
    doc = cli_json("run", str(inp), "--out", str(tmp / "out"), "--cache", str(tmp / "cache"), "--pipeline", "toy",
                   "--remote", "team", "--push", env=env)
    assert doc["remote"]["pushed"]["records"] > 12
    return {"input": inp, "out": tmp / "out", "cache": tmp / "cache", "url": f"s3://{BUCKET}/golden"}


def _copy_remote(s3, src: str) -> str:
    """A fresh copy of a remote (server-side copies): each test tampers with its own."""
    dst = f"s3://{BUCKET}/{uuid.uuid4().hex[:8]}"
    s3["fs"].copy(src.removeprefix("s3://") + "/", dst.removeprefix("s3://") + "/", recursive=True)
    return dst


def _run_b(machine_a, tmp_path, url, env, name="b"):
    p = cli("run", str(machine_a["input"]), "--out", str(tmp_path / f"out_{name}"), "--cache",
            str(tmp_path / f"cache_{name}"), "--pipeline", "toy", "--remote", url, "--json", env=env)
    assert p.returncode == 0, p.stderr
    return json.loads(p.stdout), p.stderr


def _outputs(out: Path) -> dict[str, str]:
    return {k: v["output"] for k, v in json.loads((out / "run.json").read_text())["stages"].items()}


def test_machine_b_with_an_empty_cache_computes_nothing(s3, machine_a, tmp_path):
    doc, err = _run_b(machine_a, tmp_path, machine_a["url"], s3["env"])
    assert sum(s["executed"] for s in doc["stages"]) == 0, err
    assert doc["remote"]["pulled"]["refused"] == 0 and "warning" not in err
    assert _outputs(tmp_path / "out_b") == _outputs(machine_a["out"])
    # a second machine-B run needs nothing from the remote any more
    doc2, _ = _run_b(machine_a, tmp_path, machine_a["url"], s3["env"])
    assert sum(s["executed"] for s in doc2["stages"]) == 0 and "remote" not in doc2  # the no-op fast path
    # (after the runs: fsck drops the records whose objects B never needed, which stayed remote)
    assert Store(tmp_path / "cache_b").fsck().corrupt == []
    fsck = cli_json("fsck", "--remote", machine_a["url"], env=s3["env"])
    assert fsck["clean"] and fsck["objects"] > 0 and fsck["records"] > 12


def _item_objects(machine_a, stage: str, index: int) -> tuple[str, dict[str, int]]:
    """(item key, its objects) of item ``index`` of ``stage`` in machine A's cache."""
    store = Store(machine_a["cache"])
    key = json.loads((machine_a["out"] / "run.json").read_text())["stages"][stage]["key"]
    child = store.get_record(key)["children"][index]
    return child, store.get_record(child)["objects"]


def _largest(objects: dict[str, int]) -> str:
    return max(objects, key=lambda d: objects[d])


def _obj(url: str, d: str) -> str:
    return f"{url.removeprefix('s3://')}/objects/{d[:2]}/{d[2:]}"


def _rec(url: str, k: str) -> str:
    return f"{url.removeprefix('s3://')}/records/{k[:2]}/{k}.json"


@pytest.mark.parametrize("damage", ["flipped_byte", "truncated", "swapped_objects", "missing_object",
                                    "swapped_record"])
def test_bad_remote_content_is_refused_and_recomputed(s3, machine_a, tmp_path, damage):
    fs = s3["fs"]
    url = _copy_remote(s3, machine_a["url"])
    k3, objs3 = _item_objects(machine_a, "transform", 3)
    k5, objs5 = _item_objects(machine_a, "transform", 5)
    d3, d5 = _largest(objs3), _largest(objs5)
    named = d3
    if damage == "flipped_byte":
        data = bytearray(fs.cat_file(_obj(url, d3)))
        data[len(data) // 2] ^= 0x01
        fs.pipe_file(_obj(url, d3), bytes(data))
    elif damage == "truncated":
        fs.pipe_file(_obj(url, d3), fs.cat_file(_obj(url, d3))[:-100])
    elif damage == "swapped_objects":  # same sizes, each under the other's name
        a, b = fs.cat_file(_obj(url, d3)), fs.cat_file(_obj(url, d5))
        assert len(a) == len(b)
        fs.pipe_file(_obj(url, d3), b)
        fs.pipe_file(_obj(url, d5), a)
    elif damage == "missing_object":
        fs.rm_file(_obj(url, d3))
    else:  # item 3's record filed under item 5's key
        fs.pipe_file(_rec(url, k5), fs.cat_file(_rec(url, k3)))
        named = k5
    # B reads transform's items: the remote lacks summarize (objects come only when read, so
    # damage to objects no stage of B's run reads would cost B nothing)
    fs.rm_file(_rec(url, json.loads((machine_a["out"] / "run.json").read_text())["stages"]["summarize"]["key"]))
    doc, err = _run_b(machine_a, tmp_path, url, s3["env"])
    st = by_stage(doc)
    expected = 2 if damage == "swapped_objects" else 1
    assert st["transform"]["executed"] == expected and st["summarize"]["executed"] == 1, err
    assert sum(s["executed"] for s in doc["stages"]) == expected + 1
    assert named[:12] in err and "refused" in err, err
    warnings = [ln for ln in err.splitlines() if ln.startswith("warning:")]
    assert all(len(ln) < 300 for ln in warnings) and len(warnings) <= 2, err
    # the run's results are the producer's (nothing bad entered B's cache) ...
    assert _outputs(tmp_path / "out_b") == _outputs(machine_a["out"])
    assert Store(tmp_path / "cache_b").fsck().corrupt == []
    if damage != "flipped_byte":
        return
    # ... and fsck --remote finds the damage, deletes only with --repair, then a push heals it
    rep = cli_json("fsck", "--remote", url, env=s3["env"])
    assert not rep["clean"] and any(b.startswith(d3) for b in rep["bad_objects"])
    assert rep["bad_records"] and fs.exists(_obj(url, d3))
    rep = cli_json("fsck", "--remote", url, "--repair", env=s3["env"])
    assert rep["repaired"] and not fs.exists(_obj(url, d3))
    assert cli_json("fsck", "--remote", url, env=s3["env"])["clean"]
    cli_json("push", "--remote", url, "--cache", str(tmp_path / "cache_b"), "--out", str(tmp_path / "out_b"),
             env=s3["env"])
    doc, err = _run_b(machine_a, tmp_path, url, s3["env"], name="c")
    assert sum(s["executed"] for s in doc["stages"]) == 0 and "warning" not in err, err


def test_unknown_remote_name_and_missing_bucket_are_one_line_errors(s3, machine_a, tmp_path):
    p = cli("push", "--remote", "teem", "--cache", str(machine_a["cache"]),
            env={**s3["env"], "GCVD_FLOW_REMOTES": str(tmp_path / "none.toml")})
    assert p.returncode == 2 and "unknown remote 'teem'" in p.stderr and len(p.stderr.splitlines()) == 1
    p = cli("pull", "--remote", "s3://no-such-bucket/x", "--cache", str(tmp_path / "c"), env=s3["env"])
    assert p.returncode == 2 and "remote not found" in p.stderr and "Traceback" not in p.stderr


def test_an_unreachable_remote_is_one_warning_and_the_run_goes_on(tmp_path):
    inp = make_toy_input(tmp_path / "input", n=4)
    env = {**DUMMY_AWS, "AWS_ENDPOINT_URL": "http://127.0.0.1:9", "AWS_MAX_ATTEMPTS": "1"}  # nothing listens
    p = cli("run", str(inp), "--out", str(tmp_path / "out"), "--cache", str(tmp_path / "cache"), "--pipeline", "toy",
            "--remote", "s3://team/cache", "--push", "--json", env=env)
    assert p.returncode == 0, p.stderr
    warnings = [ln for ln in p.stderr.splitlines() if ln.startswith("warning:")]
    assert len(warnings) == 1 and "going on without the remote" in warnings[0], p.stderr
    doc = json.loads(p.stdout)
    assert by_stage(doc)["transform"]["executed"] == 4 and doc["remote"]["failed"]
    p = cli("push", "--remote", "s3://team/cache", "--cache", str(tmp_path / "cache"), env=env)
    assert p.returncode == 2 and p.stderr.startswith("gcvd-flow: error: remote s3://team/cache: ")
    assert len(p.stderr.splitlines()) == 1
