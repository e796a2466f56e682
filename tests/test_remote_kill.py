"""A push killed with SIGKILL half-way leaves a readable remote; the next push completes it
(S3 through s3fs against moto's standalone server on 127.0.0.1)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid

from conftest import ROOT, by_stage, cli_json, make_toy_input
from remote_servers import DUMMY_AWS, moto_s3, s3fs_client


def test_push_killed_midway_then_rerun_leaves_a_clean_remote(tmp_path):
    n = 120
    total_records = 2 * (n + 1) + 3  # decode and transform items + their stage records, 3 whole stages
    inp = make_toy_input(tmp_path / "input", n=n, size=20000)
    with moto_s3() as endpoint:
        fs = s3fs_client(endpoint)
        bucket = f"kill-{uuid.uuid4().hex[:8]}"  # moto's state is per process, shared by its servers
        fs.mkdir(bucket)
        env = {**DUMMY_AWS, "AWS_ENDPOINT_URL": endpoint}
        out_a, cache_a = tmp_path / "out_a", tmp_path / "cache_a"
        cli_json("run", str(inp), "--out", str(out_a), "--cache", str(cache_a), "--pipeline", "toy", env=env)
        url = f"s3://{bucket}/cache"
        p = subprocess.Popen([sys.executable, "-m", "gcvd_flow", "push", "--remote", url, "--cache", str(cache_a),
                              "--out", str(out_a)], cwd=ROOT, env={**os.environ, **env},
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        n_objects = 0
        deadline = time.time() + 60
        while time.time() < deadline and p.poll() is None:
            try:
                n_objects = len(fs.find(f"{bucket}/cache/objects"))
            except FileNotFoundError:
                n_objects = 0
            if n_objects >= 40:
                break
            time.sleep(0.02)
        p.send_signal(signal.SIGKILL)
        p.wait(timeout=30)
        assert p.returncode == -signal.SIGKILL, "the push finished before it could be killed"
        n_records = len(fs.find(f"{bucket}/cache/records")) if fs.exists(f"{bucket}/cache/records") else 0
        assert n_records < total_records  # killed half-way: not every record was published
        rep = cli_json("fsck", "--remote", url, env=env)
        assert rep["clean"], rep  # whatever was published is whole and consistent
        # a reader of the half-pushed remote gets only verified results
        doc = cli_json("run", str(inp), "--out", str(tmp_path / "out_b"), "--cache", str(tmp_path / "cache_b"),
                       "--pipeline", "toy", "--remote", url, env=env)
        assert doc["remote"]["pulled"]["refused"] == 0
        # the next push completes it: only what is missing moves
        rep = cli_json("push", "--remote", url, "--cache", str(cache_a), "--out", str(out_a), env=env)
        assert 0 < rep["objects"] and rep["refused"] == 0
        rep = cli_json("fsck", "--remote", url, env=env)
        assert rep["clean"] and rep["records"] == total_records, rep
        doc = cli_json("run", str(inp), "--out", str(tmp_path / "out_c"), "--cache", str(tmp_path / "cache_c"),
                       "--pipeline", "toy", "--remote", url, env=env)
        assert all(s["executed"] == 0 for s in by_stage(doc).values())
