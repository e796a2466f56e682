"""Share caches: push / pull records and objects to a remote store (a shared directory).

A remote has the same layout as a local cache, so a teammate's cache directory on a network
share is a remote as it is. Everything pulled is verified: an object whose bytes do not hash
to its name is refused, and a record is copied only once every object it names arrived, so a
broken or malicious remote can cost a recomputation but never a wrong result (and artifacts
are JSON + npy/PNG/safetensors: nothing in them can execute code).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Iterable

from gcvd_flow.engine.errors import UsageError
from gcvd_flow.engine.keys import digest_bytes, is_digest
from gcvd_flow.engine.store import Store


def _valid_record(rec: Any) -> bool:
    return (isinstance(rec, dict) and is_digest(rec.get("outputs", ""))
            and isinstance(rec.get("objects"), dict)
            and all(is_digest(d) and isinstance(s, int) for d, s in rec["objects"].items())
            and all(is_digest(c) for c in rec.get("children", [])))


def _read_record(store: Store, key: str) -> dict[str, Any] | None:
    try:
        rec = json.loads(store.record_path(key).read_bytes())
    except (OSError, ValueError):
        return None
    return rec if _valid_record(rec) else None


def _copy(src: Store, dst: Store, keys: Iterable[str]) -> dict[str, int]:
    stats = {"records": 0, "objects": 0, "bytes": 0, "refused": 0, "skipped": 0}
    todo = list(keys)
    seen: set[str] = set()
    while todo:
        key = todo.pop()
        if key in seen or not is_digest(key):
            continue
        seen.add(key)
        rec = _read_record(src, key)
        if rec is None:
            stats["skipped"] += 1
            continue
        todo.extend(rec.get("children", []))
        ok = True
        for digest in rec["objects"]:
            if dst.has(digest):
                continue
            try:
                data = src.object_path(digest).read_bytes()
            except OSError:
                ok = False
                continue
            if digest_bytes(data) != digest:  # never trust a name
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


def push(local: Store, remote_dir: str, out: str | None = None) -> dict[str, int]:
    """Copy a run's records (or all) with their objects to the remote store."""
    remote = Store(remote_dir, verify=True)
    return _copy(local, remote, _run_keys(out, local))


def pull(local: Store, remote_dir: str, out: str | None = None) -> dict[str, int]:
    """Copy a run's records (or all the remote has) into the local cache, verified."""
    if not Path(remote_dir).is_dir():
        raise UsageError(f"{remote_dir}: remote not found")
    remote = Store(remote_dir, verify=True)
    keys = _run_keys(out, remote) if out else [k for k, _ in remote.iter_records()]
    return _copy(remote, local, keys)
