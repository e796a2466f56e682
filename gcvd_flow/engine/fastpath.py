"""No-op detection for `gcvd-flow run` from file metadata alone (stdlib only, no numpy).

After a successful run, the run directory gets a stamp: the invocation, the size and
modification time (ns) of every input file, config file, source file of the pipeline's packages
and metadata file of its numeric libraries (the pipeline says which: ``PipelineSpec.watched_paths``,
recorded in the stamp), the cache records the run ended with and the files it exported. When a later `run`
with the same invocation finds every one of those unchanged and every record still in the
cache, nothing can have changed, so it answers from the stamp without importing the
pipeline — the way make, ninja and DVC's state database skip unchanged work. Anything
different (a touched file, a --set, a deleted record or output) falls through to the full
runner, which decides by content hashes as usual. A stamp is written only after RUN_DIR's
files were re-hashed and found to be what its run.json records (``outputs.check_files``): a
run dir mixed by two writers or edited is never answered from a stamp.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import time
from typing import Any

from gcvd_flow.engine.names import ENV_CACHE, ENV_FSYNC

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


def _outputs(out: str) -> dict[str, list[int] | None]:
    """Metadata of every file in RUN_DIR but the stamp and the writer lock."""
    from gcvd_flow.engine.outputs import LOCK

    return {p: s for p, s in _tree_stats(out).items()
            if not p.endswith(STAMP) and not p.endswith(STAMP + ".tmp") and os.path.basename(p) != LOCK}


def fingerprint(invocation: dict[str, Any], cache: str, out: str, watch: dict[str, list[str]]) -> dict[str, Any]:
    """Everything a no-op decision depends on, from metadata only."""
    sources: dict[str, Any] = {}
    for d in watch.get("dirs", []):
        sources.update(_tree_stats(d, (".py", ".json")))
    doc = {
        "invocation": invocation,
        "cache": os.path.abspath(cache),
        "python": sys.version,
        "env": {k: os.environ.get(k) for k in (ENV_CACHE, ENV_FSYNC)},
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
    from gcvd_flow.engine import jsonio
    from gcvd_flow.engine.outputs import check_files

    stamp = os.path.join(out, STAMP)
    try:  # only a run dir whose files are what its run.json records is ever answered from the stamp
        files = jsonio.load_file(os.path.join(out, "run.json"), "run record").get("files")
        ok = isinstance(files, dict) and not check_files(out, files)
    except (AttributeError, ValueError):  # UsageError is a ValueError
        ok = False
    if not ok:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(stamp)
        return
    fp = fingerprint(invocation, cache, out, watch)
    outputs = _outputs(out)
    doc = {"fingerprint": fp, "watch": watch, "result": result, "records": sorted(record_paths),
           "outputs": outputs}
    tmp = os.path.join(out, STAMP + ".tmp")
    with open(tmp, "w") as f:
        json.dump(doc, f, sort_keys=True)
    os.replace(tmp, os.path.join(out, STAMP))


def check(out: str, invocation: dict[str, Any], cache: str) -> dict[str, Any] | None:
    """The previous result if nothing changed since the stamped run, else None (also for a
    stamp that is unreadable or of another shape: the full runner then decides)."""
    t0 = time.perf_counter()
    from gcvd_flow.engine import jsonio

    try:
        doc = jsonio.loads(jsonio.read_regular(os.path.join(out, STAMP)))
        return _answer(doc, out, invocation, cache, t0)
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        return None


def _answer(doc: Any, out: str, invocation: dict[str, Any], cache: str, t0: float) -> dict[str, Any] | None:
    if not isinstance(doc, dict) or not isinstance(doc.get("watch"), dict):
        return None
    watch = {k: [str(p) for p in v] for k, v in doc["watch"].items() if isinstance(v, list)}
    if doc.get("fingerprint") != fingerprint(invocation, cache, out, watch):
        return None
    records = doc.get("records")
    if not isinstance(records, list) or any(not isinstance(p, str) or not os.path.exists(p) for p in records):
        return None
    if _outputs(out) != doc.get("outputs"):
        return None
    res = doc.get("result")
    if not isinstance(res, dict):
        return None
    res["stages"] = [{"name": str(s["name"]), "executed": 0, "cached": int(s["executed"]) + int(s["cached"]),
                      "seconds": 0.0} for s in res["stages"]]
    res["seconds"] = round(time.perf_counter() - t0, 3)
    res["noop"] = "unchanged since the last run (file metadata)"
    return res
