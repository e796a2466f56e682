"""Share caches: push / pull records and objects to a remote store (a shared directory).

A remote has the same layout as a local cache, so a teammate's cache directory on a network
share is a remote as it is. Everything pulled is verified: an object whose bytes do not hash
to its name is refused, and a record is copied only once every object it names arrived, so a
broken or malicious remote can cost a recomputation but never a wrong result (and artifacts
are JSON + npy/PNG/safetensors: nothing in them can execute code).
"""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path
from typing import Any, Iterable

from gcvd_flow.engine.errors import UsageError
from gcvd_flow.engine.keys import digest_bytes, is_digest
from gcvd_flow.engine.store import Store, record_problem


MAX_RECORD_BYTES = 64 << 20


def _read_regular(path: Path, limit: int) -> bytes | None:
    """At most ``limit`` bytes of a regular file that is not a symlink; None for anything else
    (a FIFO would block, a link could point at /dev/zero or out of the remote)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError:
        return None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_size > limit:
            return None
        with os.fdopen(fd, "rb", closefd=False) as f:
            data = f.read(limit + 1)
        return data if len(data) <= limit else None
    finally:
        os.close(fd)


def _read_record(store: Store, key: str, stats: dict[str, Any]) -> dict[str, Any] | None:
    raw = _read_regular(store.record_path(key), MAX_RECORD_BYTES)
    if raw is None:
        return None
    try:
        rec = json.loads(raw)
    except ValueError:
        rec = None
    problem = record_problem(key, rec)
    if problem is not None:
        stats["refused_records"].append(f"{key[:12]}: {problem}")
        return None
    return rec


def _copy(src: Store, dst: Store, keys: Iterable[str]) -> dict[str, Any]:
    """Copy records (and their children) with their objects; objects first, then the record,
    and only when every object arrived whole. Objects are read only as regular files, at most
    the size the record declares, and re-hashed; a record must hash-match its key."""
    stats: dict[str, Any] = {"records": 0, "objects": 0, "bytes": 0, "refused": 0, "skipped": 0,
                             "refused_records": []}
    refused: set[str] = set()
    todo = list(keys)
    seen: set[str] = set()
    while todo:
        key = todo.pop()
        if key in seen or not is_digest(key):
            continue
        seen.add(key)
        rec = _read_record(src, key, stats)
        if rec is None:
            stats["skipped"] += 1
            continue
        todo.extend(rec.get("children", []))
        ok = True
        for digest, size in rec["objects"].items():
            if dst.object_size(digest) == size:
                continue
            if digest in refused:
                ok = False
                continue
            data = _read_regular(src.object_path(digest), size)
            if data is None or len(data) != size or digest_bytes(data) != digest:  # never trust a name
                refused.add(digest)
                stats["refused"] += 1
                ok = False
                continue
            dst.put_bytes(data)
            stats["objects"] += 1
            stats["bytes"] += len(data)
        if ok and dst.get_record(key) is None:
            dst.sync()
            dst.put_record(key, rec)
            stats["records"] += 1
    stats["refused_objects"] = sorted(refused)
    return stats


def _run_keys(out: str | None, store: Store) -> list[str]:
    if out is None:
        return [k for k, _ in store.iter_records()]
    p = Path(out) / "run.json"
    try:
        stages = json.loads(p.read_text())["stages"]
    except (OSError, ValueError, KeyError):
        raise UsageError(f"{p}: not a run record") from None
    return [s["key"] for s in stages.values() if s.get("key")]


def push(local: Store, remote_dir: str, out: str | None = None) -> dict[str, Any]:
    """Copy a run's records (or all) with their objects to the remote store."""
    p = Path(remote_dir)
    if p.exists() and not p.is_dir():
        raise UsageError(f"{remote_dir}: remote is a file, not a cache directory")
    remote = Store(remote_dir, verify=True)
    with local.lease(), remote.lease():
        return _copy(local, remote, _run_keys(out, local))


def pull(local: Store, remote_dir: str, out: str | None = None) -> dict[str, Any]:
    """Copy a run's records (or all the remote has) into the local cache, verified."""
    if not Path(remote_dir).is_dir() or not (Path(remote_dir) / "records").is_dir():
        raise UsageError(f"{remote_dir}: remote not found (not a gcvd-flow cache directory)")
    remote = Store(remote_dir, verify=True)
    keys = _run_keys(out, local) if out else [k for k, _ in remote.iter_records()]
    with local.lease():
        return _copy(remote, local, keys)
