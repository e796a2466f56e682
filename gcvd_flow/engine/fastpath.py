"""No-op detection for `gcvd-flow run` from file metadata alone (stdlib only, no numpy).

After a successful run, the run directory gets a stamp: the invocation, the size and
modification time (ns) of every input file, config file, source file of the pipeline's packages
and metadata file of its numeric libraries (the pipeline says which: ``PipelineSpec.watched_paths``,
recorded in the stamp), the cache records the run ended with and the files it exported. When a later `run`
with the same invocation finds every one of those unchanged and every record still in the
cache, nothing can have changed, so it answers from the stamp without importing the
pipeline — the way make, ninja and DVC's state database skip unchanged work. Anything
different (a touched file, a --set, a deleted record or output) falls through to the full
runner, which decides by content hashes as usual.
"""

from __future__ import annotations

import importlib.util
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

STAMP = ".gcvd-stamp.json"


def _stat(path: str) -> list[int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return [st.st_size, st.st_mtime_ns, st.st_ino]


def _tree_stats(root: str, suffixes: tuple[str, ...] | None = None) -> dict[str, list[int] | None]:
    out: dict[str, list[int] | None] = {}
    if os.path.isfile(root):
        return {root: _stat(root)}
    stack = [root]
    while stack:
        d = stack.pop()
        try:
            entries = list(os.scandir(d))
        except OSError:
            out[d] = None
            continue
        for e in entries:
            if e.is_dir(follow_symlinks=True):
                if e.name not in ("__pycache__", ".git"):
                    stack.append(e.path)
            elif suffixes is None or e.name.endswith(suffixes):
                st = e.stat()
                out[e.path] = [st.st_size, st.st_mtime_ns, st.st_ino]
    return dict(sorted(out.items()))


def fingerprint(invocation: dict[str, Any], cache: str, out: str, watch: dict[str, list[str]]) -> dict[str, Any]:
    """Everything a no-op decision depends on, from metadata only."""
    sources: dict[str, Any] = {}
    for d in watch.get("dirs", []):
        sources.update(_tree_stats(d, (".py", ".json")))
    doc = {
        "invocation": invocation,
        "cache": os.path.abspath(cache),
        "python": sys.version,
        "env": {k: os.environ.get(k) for k in ("GCVD_FLOW_CACHE", "GCVD_FLOW_FSYNC")},
        "input": _tree_stats(invocation["input"]) if invocation.get("input") else {},
        "config_file": _stat(invocation["config_file"]) if invocation.get("config_file") else None,
        "sources": sources,
        "libraries": {f: _stat(f) for f in watch.get("files", [])},
        "set_paths": _set_paths(invocation.get("sets") or []),
    }
    return doc


def _set_paths(sets: list[str]) -> dict[str, Any]:
    """Files and folders named by --set values (weights files, a masks folder): their metadata, so
    that editing one is not answered from the stamp."""
    out: dict[str, Any] = {}
    for item in sets:
        value = item.partition("=")[2].strip()
        if len(value) >= 2 and value[0] == value[-1] and value[0] in "'\"":
            value = value[1:-1]
        if value and os.path.exists(os.path.expanduser(value)):
            out.update(_tree_stats(os.path.expanduser(value)))
    return out


def write(out: str, invocation: dict[str, Any], cache: str, result: dict[str, Any],
          record_paths: list[str], watch: dict[str, list[str]]) -> None:
    fp = fingerprint(invocation, cache, out, watch)
    outputs = {p: s for p, s in _tree_stats(out).items() if not p.endswith(STAMP)}
    doc = {"fingerprint": fp, "watch": watch, "result": result, "records": sorted(record_paths),
           "outputs": outputs}
    tmp = os.path.join(out, STAMP + ".tmp")
    with open(tmp, "w") as f:
        json.dump(doc, f, sort_keys=True)
    os.replace(tmp, os.path.join(out, STAMP))


def check(out: str, invocation: dict[str, Any], cache: str) -> dict[str, Any] | None:
    """The previous result if nothing changed since the stamped run, else None."""
    t0 = time.perf_counter()
    try:
        with open(os.path.join(out, STAMP)) as f:
            doc = json.load(f)
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or not isinstance(doc.get("watch"), dict):
        return None
    if doc.get("fingerprint") != fingerprint(invocation, cache, out, doc["watch"]):
        return None
    if any(not os.path.exists(p) for p in doc.get("records", [])):
        return None
    outputs = {p: s for p, s in _tree_stats(out).items() if not p.endswith(STAMP)}
    if outputs != doc.get("outputs"):
        return None
    res = doc["result"]
    res["stages"] = [{"name": s["name"], "executed": 0, "cached": s["executed"] + s["cached"], "seconds": 0.0}
                     for s in res["stages"]]
    res["seconds"] = round(time.perf_counter() - t0, 3)
    res["noop"] = "unchanged since the last run (file metadata)"
    return res
