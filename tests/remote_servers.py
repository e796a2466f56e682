"""Real servers on loopback for the remote-cache tests: moto's standalone S3 server (through
s3fs, as a user's S3 or MinIO would be reached) and Debian's OpenSSH sshd (through fsspec's
SFTP file system). Both listen on 127.0.0.1 only, on a free port, and stop with the test."""

from __future__ import annotations

import contextlib
import getpass
import logging
import os
import shutil
import socket
import subprocess
import time
from pathlib import Path
from typing import Iterator

DUMMY_AWS = {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing", "AWS_DEFAULT_REGION": "us-east-1",
             "AWS_SESSION_TOKEN": "testing", "AWS_CONFIG_FILE": "/dev/null", "AWS_SHARED_CREDENTIALS_FILE": "/dev/null"}


@contextlib.contextmanager
def moto_s3() -> Iterator[str]:
    """A ThreadedMotoServer on 127.0.0.1 (a real HTTP S3 endpoint); yields its URL."""
    from moto.server import ThreadedMotoServer

    logging.getLogger("werkzeug").disabled = True  # one access-log line per request otherwise
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    try:
        host, port = server.get_host_and_port()
        yield f"http://{host}:{port}"
    finally:
        server.stop()


def s3fs_client(endpoint: str):
    import s3fs

    return s3fs.S3FileSystem(key="testing", secret="testing", endpoint_url=endpoint,
                             skip_instance_cache=True, use_listings_cache=False)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


SSHD = shutil.which("sshd") or "/usr/sbin/sshd"


@contextlib.contextmanager
def sshd(tmp: Path) -> Iterator[dict]:
    """Debian's sshd on a loopback port with a throw-away host key and client key; yields the
    storage options of fsspec's SFTP file system. Raises RuntimeError(reason) when it cannot
    be started (not installed, no privilege-separation directory, ...)."""
    if not os.path.exists(SSHD):
        raise RuntimeError("openssh-server is not installed (no sshd; `make sysdeps` installs it)")
    if not shutil.which("ssh-keygen"):
        raise RuntimeError("ssh-keygen is not installed")
    tmp.mkdir(parents=True, exist_ok=True)
    os.chmod(tmp, 0o700)
    for name in ("host", "client"):
        subprocess.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-f", str(tmp / name)], check=True)
    shutil.copy(tmp / "client.pub", tmp / "authorized_keys")
    if os.geteuid() == 0:
        with contextlib.suppress(OSError):
            os.makedirs("/run/sshd", mode=0o755, exist_ok=True)  # sshd's privilege-separation dir
    port = _free_port()
    conf = tmp / "sshd_config"
    conf.write_text(f"ListenAddress 127.0.0.1\nPort {port}\nHostKey {tmp / 'host'}\nPidFile {tmp / 'sshd.pid'}\n"
                    f"AuthorizedKeysFile {tmp / 'authorized_keys'}\nPasswordAuthentication no\n"
                    "KbdInteractiveAuthentication no\nUsePAM no\nStrictModes no\nPermitRootLogin prohibit-password\n"
                    "Subsystem sftp internal-sftp\n")
    proc = subprocess.Popen([SSHD, "-D", "-e", "-f", str(conf)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    try:
        deadline = time.time() + 10
        while True:
            if proc.poll() is not None:
                raise RuntimeError(f"sshd did not start: {(proc.stdout.read() or '').strip()[:300]}")
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=0.5):
                break
            if time.time() > deadline:
                raise RuntimeError("sshd did not listen within 10 s")
            time.sleep(0.05)
        yield {"host": "127.0.0.1", "port": port, "username": getpass.getuser(),
               "key_filename": str(tmp / "client")}
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
