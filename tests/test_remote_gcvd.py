"""The GCVD pipeline itself on a tiny synthetic clip, beyond one machine: machine A runs
in-process and pushes to S3 (s3fs -> moto's standalone server on 127.0.0.1); machine C runs the
same clip's map stages on a 2-worker Dask LocalCluster (byte-identical artifacts); machine B, with an empty
cache, reads through the remote, computes nothing and downloads only the objects it reads."""

from __future__ import annotations

import json
import uuid
from pathlib import Path

import pytest
from conftest import cli, cli_json
from remote_servers import DUMMY_AWS, moto_s3, s3fs_client

from gcvd_flow.engine.store import Store


def _outputs(out: Path) -> dict[str, str]:
    return {k: v["output"] for k, v in json.loads((out / "run.json").read_text())["stages"].items()}


@pytest.mark.slow
def test_gcvd_on_dask_and_through_s3_gives_identical_artifacts(tmp_path):
    clip = tmp_path / "clip"
    cli("synth", str(clip), "--frames", "8", "--size", "96x72", check=True)
    base = ["run", str(clip), "--profile", "fast"]
    with moto_s3() as endpoint:
        bucket = f"gcvd-{uuid.uuid4().hex[:8]}"  # moto's state is per process, shared by its servers
        s3fs_client(endpoint).mkdir(bucket)
        env = {**DUMMY_AWS, "AWS_ENDPOINT_URL": endpoint}
        a = cli_json(*base, "--out", str(tmp_path / "a"), "--cache", str(tmp_path / "ca"), "--remote",
                     f"s3://{bucket}/gcvd", "--push", env=env)
        assert a["remote"]["pushed"]["objects"] > 0
        # the map stages on Dask (whole stages run in the client process either way)
        c = cli_json(*base, "--out", str(tmp_path / "c"), "--cache", str(tmp_path / "cc"), "--executor", "dask",
                     "--jobs", "2", "--until", "keyframes", env=env)
        assert [s["name"] for s in c["stages"]] == ["ingest", "user_masks", "calibrate", "flow", "masks", "keyframes"]
        assert all(s["executed"] > 0 for s in c["stages"] if s["name"] != "user_masks")  # no item without --masks
        full = _outputs(tmp_path / "a")
        assert _outputs(tmp_path / "c") == {k: full[k] for k in _outputs(tmp_path / "c")}
        b = cli_json(*base, "--out", str(tmp_path / "b"), "--cache", str(tmp_path / "cb"), "--remote",
                     f"s3://{bucket}/gcvd", env=env)
        assert sum(s["executed"] for s in b["stages"]) == 0 and b["remote"]["pulled"]["refused"] == 0
        assert _outputs(tmp_path / "b") == _outputs(tmp_path / "a")
        assert _files(tmp_path / "b") == _files(tmp_path / "a")  # RUN_DIR byte-identical
    # B downloaded the records and only the objects it read (what it wrote into RUN_DIR, the
    # stages' manifests): none of the intermediates (flows, masks, priors, ...)
    pulled, pushed = b["remote"]["pulled"], a["remote"]["pushed"]
    ca, b_objects = Store(tmp_path / "ca"), set(Store(tmp_path / "cb").iter_objects())
    keys = {k: v["key"] for k, v in json.loads((tmp_path / "a" / "run.json").read_text())["stages"].items()}
    for stage in ("flow", "masks", "priors", "association", "optimize_keyframes"):
        objects = set(ca.get_record(keys[stage])["objects"]) - {ca.get_record(keys[stage])["outputs"]}
        assert objects and not objects & b_objects, stage
    assert pulled["objects_named"] == pushed["objects"] and pulled["objects"] == len(b_objects)
    assert pulled["objects"] < pushed["objects"] / 2 and pulled["bytes"] < pushed["bytes"] / 4
    print(f"read-through: {pulled['objects']} of {pushed['objects']} objects, "
          f"{pulled['bytes']} of {pushed['bytes']} bytes")


def _files(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*"))
            if p.is_file() and p.name not in ("run.json", ".gcvd-stamp.json")}
