"""The suite's command runner (tests/conftest.py ``cli``, tests/cli_fork.py): a command forked from
the warm server gives what a fresh interpreter gives (exit code, stdout, stderr), sees the
environment it is given, and is killed at its timeout."""

import os
import subprocess

import pytest
from conftest import _ForkServer, cli


@pytest.mark.parametrize("args", [
    ("run", "/nonexistent/clip", "--out", "/nonexistent/out"),  # a one-line error, exit code 2
    ("dag", "--pipeline", "toy"),                                 # stdout, exit code 0
    ("run", "--no-such-option"),                                  # argparse's usage error
])
def test_forked_command_matches_a_fresh_interpreter(args):
    forked, fresh = cli(*args), cli(*args, fresh=True)
    assert (forked.returncode, forked.stdout, forked.stderr) == (fresh.returncode, fresh.stdout, fresh.stderr)
    assert forked.stdout or forked.stderr


def test_forked_command_sees_its_environment_and_working_directory(tmp_path, toy_input):
    """GCVD_FLOW_CACHE names the default cache: the forked run writes there, not where the
    server's environment (or the previous command's) would have it."""
    for name in ("a", "b"):
        cache = tmp_path / f"cache-{name}"
        cli("run", str(toy_input), "--out", str(tmp_path / name), "--pipeline", "toy", check=True,
            env={"GCVD_FLOW_CACHE": str(cache)})
        assert cache.is_dir() and any(cache.rglob("*")), name
    assert "GCVD_FLOW_CACHE" not in os.environ


def test_forked_command_is_killed_at_its_timeout(toy_input, tmp_path):
    with pytest.raises(subprocess.TimeoutExpired):
        cli("run", str(toy_input), "--out", str(tmp_path / "o"), "--cache", str(tmp_path / "c"), "--pipeline", "toy",
            "--set", "transform.sleep=5", timeout=2)
    # the server serves the next command
    assert cli("dag", "--pipeline", "toy").returncode == 0


def test_interpreter_start_variables_need_a_fresh_interpreter():
    import gcvd_flow.api  # noqa: F401 - an entry point: sets OMP_WAIT_POLICY in this process, as the CLI does in its own

    env = dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
    assert not _ForkServer.differs(env)  # the suite's commands are forked (none was, when this held the
    # server's imports to an environment without the CLI's OMP_WAIT_POLICY)
    assert _ForkServer.differs({**env, "PYTHONPATH": "/elsewhere"})
    assert _ForkServer.differs({**env, "OMP_NUM_THREADS": "7"})
    assert _ForkServer.differs({**env, "OMP_WAIT_POLICY": "ACTIVE"})
