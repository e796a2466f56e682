"""`lineage`: which stage, parameters, code fingerprint, library versions and input digests
produced an artifact, recursively down to the source, from the records alone (also after a
pull into a cache that never ran anything)."""

from __future__ import annotations

import json

from conftest import cli, cli_json, make_toy_input

from gcvd_flow.engine.store import Store


def test_lineage_of_a_run_stage_and_of_digests(tmp_path):
    inp = make_toy_input(tmp_path / "input", n=6)
    out, cache = tmp_path / "out", tmp_path / "cache"
    cli_json("run", str(inp), "--out", str(out), "--cache", str(cache), "--pipeline", "toy", "--set",
             "transform.scale=3.0")
    run = json.loads((out / "run.json").read_text())["stages"]
    doc = cli_json("lineage", str(out), "summarize")
    nodes = doc["nodes"]
    assert doc["roots"] == [run["summarize"]["key"]]
    assert {n["stage"] for n in nodes.values()} == {"summarize", "transform", "decode"}
    t = nodes[run["transform"]["key"]]
    assert t["params"] == {"kill_worker": -1, "scale": 3.0, "sleep": 0.0} and t["output"] == run["transform"]["output"]
    assert t["env"]["numpy"] and t["code"] == run["transform"]["fields"]["code"] and t["items"] == 6
    assert t["inputs"]["decode"] == {"digest": run["decode"]["output"], "from": run["decode"]["key"]}
    src = nodes[run["decode"]["key"]]["inputs"]["source"]
    assert src["from"] is None and src["source"]  # down to the source files
    text = cli("lineage", str(out), "summarize", check=True).stdout
    assert "transform (stage" in text and '"scale": 3.0' in text and "source: not produced by a stage" in text
    # it names the input the source digests are of, and is shorter than --full (one line per record)
    assert doc["input"] == str(inp) and f"input: {inp}" in text and f"the run's input {inp}" in text
    full = cli("lineage", str(out), "summarize", "--full", check=True).stdout
    assert "code files:" in full and "code files:" not in text
    assert len(text.splitlines()) < len(full.splitlines())

    # an item's output digest and one of its objects: the item record, then its input item, then the file
    store = Store(cache)
    item_key = store.get_record(run["transform"]["key"])["children"][2]
    item = store.get_record(item_key)
    doc = cli_json("lineage", item["outputs"], "--cache", str(cache))
    assert doc["roots"] == [item_key]
    chain = doc["nodes"]
    assert chain[item_key]["record_kind"] == "item" and chain[item_key]["stage"] == "transform"
    up = chain[item_key]["inputs"]["item"]["from"]
    assert chain[up]["stage"] == "decode" and chain[up]["inputs"]["blob"]["source"]
    obj = max(item["objects"], key=item["objects"].get)
    doc = cli_json("lineage", obj, "--cache", str(cache))
    assert doc["roots"] == [item_key] and obj[:12] in doc["note"]

    # after a pull, a teammate's cache tells the same story without the producer's machine
    remote = tmp_path / "remote"
    cli_json("push", str(remote), "--cache", str(cache))
    cli_json("pull", "--remote", str(remote), "--cache", str(tmp_path / "teammate"))
    doc2 = cli_json("lineage", item["outputs"], "--cache", str(tmp_path / "teammate"))
    assert doc2["nodes"] == cli_json("lineage", item["outputs"], "--cache", str(cache))["nodes"]

    p = cli("lineage", "0" * 64, "--cache", str(cache))
    assert p.returncode == 2 and "no record" in p.stderr
    p = cli("lineage", str(out), "nosuchstage")
    assert p.returncode == 2 and "no stage 'nosuchstage'" in p.stderr
