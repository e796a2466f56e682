"""Remote caches over SSH: fsspec's SFTP file system (paramiko) against Debian's OpenSSH sshd
started on a loopback port. Skipped, with the reason printed, where sshd cannot be started."""

from __future__ import annotations

import json

import pytest
from conftest import by_stage, cli, cli_json, make_toy_input
from remote_servers import sshd

from gcvd_flow.engine.store import Store


@pytest.fixture(scope="module")
def ssh(tmp_path_factory):
    try:
        with sshd(tmp_path_factory.mktemp("sshd")) as opts:
            yield opts
    except RuntimeError as exc:
        print(f"SKIP SFTP tests: {exc}")
        pytest.skip(f"cannot start sshd on 127.0.0.1: {exc}")


def test_sftp_remote_shares_a_run_and_refuses_a_flipped_byte(ssh, tmp_path):
    inp = make_toy_input(tmp_path / "input", n=8)
    served = tmp_path / "served"  # the directory sshd serves (here on the same machine)
    remotes = tmp_path / "remotes.toml"
    remotes.write_text(f'[remotes.nas]\nurl = "sftp://{ssh["host"]}:{ssh["port"]}{served}"\n'
                       f'username = "{ssh["username"]}"\nkey_filename = "{ssh["key_filename"]}"\n')
    env = {"GCVD_FLOW_REMOTES": str(remotes)}
    a = cli_json("run", str(inp), "--out", str(tmp_path / "oa"), "--cache", str(tmp_path / "ca"), "--pipeline",
                 "toy", "--remote", "nas", "--push", env=env)
    assert a["remote"]["pushed"]["objects"] > 8
    assert not any((served / "tmp").iterdir())  # every file went in under a temporary name, then renamed
    b = cli_json("run", str(inp), "--out", str(tmp_path / "ob"), "--cache", str(tmp_path / "cb"), "--pipeline",
                 "toy", "--remote", "nas", env=env)
    assert all(s["executed"] == 0 for s in b["stages"])
    # flip a byte of one decoded item on the server: refused, recomputed, never used (the server
    # lacks transform's item 2, so the run recomputes it and reads decode's item 2: objects
    # come only when read)
    keys = {k: v["key"] for k, v in json.loads((tmp_path / "oa" / "run.json").read_text())["stages"].items()}
    ca = Store(tmp_path / "ca")
    item = ca.get_record(ca.get_record(keys["decode"])["children"][2])
    victim = max(item["objects"], key=item["objects"].get)
    path = served / "objects" / victim[:2] / victim[2:]
    data = bytearray(path.read_bytes())
    data[10] ^= 0xFF
    path.write_bytes(bytes(data))
    k2 = ca.get_record(keys["transform"])["children"][2]
    (served / "records" / k2[:2] / f"{k2}.json").unlink()
    p = cli("run", str(inp), "--out", str(tmp_path / "oc"), "--cache", str(tmp_path / "cc"), "--pipeline", "toy",
            "--remote", "nas", "--json", env=env)
    assert p.returncode == 0, p.stderr
    st = by_stage(json.loads(p.stdout))
    assert st["decode"]["executed"] == 1 and st["transform"]["executed"] == 1, p.stderr
    assert f"object {victim[:12]} refused" in p.stderr
    assert (tmp_path / "oc" / "report.json").read_text() == (tmp_path / "oa" / "report.json").read_text()
    rep = cli_json("fsck", "--remote", "nas", "--repair", env=env)
    assert any(b.startswith(victim) for b in rep["bad_objects"]) and not path.exists()
    assert cli_json("fsck", "--remote", "nas", env=env)["clean"]
