"""`lineage`: what produced an artifact, recursively down to the source.

Everything comes from the records in the cache (no run needs to be repeated, and the producer's
machine is not needed: a pulled record carries the same facts). A record's ``preimage`` is
exactly what its key is the digest of — stage name, code fingerprint, parameters, seed, stage
version, input digests and numeric environment (library versions, device, dtype) — and stage
records add ``fields`` (which source files the code fingerprint covers). Inputs are followed to
the records whose output they are; an input no record produced is the source (input files,
frames) or a constant.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from gcvd_flow.engine.errors import UsageError
from gcvd_flow.engine.keys import is_digest
from gcvd_flow.engine.outputs import read_run_dir
from gcvd_flow.engine.store import Store

MAX_NODES = 10_000


class _Index:
    """output digest -> record key, and object digest -> record key (built on first need)."""

    def __init__(self, store: Store, known: dict[str, str] | None = None):
        self.store = store
        self.outputs: dict[str, str] = dict(known or {})
        self.objects: dict[str, str] = {}
        self._full = False

    def _build(self) -> None:
        if self._full:
            return
        self._full = True
        for key, _path in self.store.iter_records():
            rec = self.store.read_record(key)  # None: unreadable, not a record, or not this key's
            if rec is None or rec.get("record_kind") == "checkpoint":
                continue
            if is_digest(rec.get("outputs")):
                self.outputs.setdefault(rec["outputs"], key)
            for d in rec.get("objects") or {}:
                # the smallest producer: an item record rather than its stage record
                if rec.get("record_kind") == "item" or d not in self.objects:
                    self.objects[d] = key

    def producer(self, digest: str) -> str | None:
        if digest not in self.outputs:
            self._build()
        return self.outputs.get(digest)

    def containing(self, digest: str) -> str | None:
        self._build()
        return self.objects.get(digest)


def _node(store: Store, key: str, index: _Index) -> dict[str, Any]:
    rec = store.read_record(key)
    if rec is None:
        return {"key": key, "missing": True}
    pre = rec["preimage"] if isinstance(rec["preimage"], list) else []  # any JSON that hashes to the key
    kind, stage, code, keyed, inputs, env = (list(pre) + [None] * 6)[:6]
    keyed = keyed if isinstance(keyed, dict) else {}
    inputs = inputs if isinstance(inputs, dict) else {}
    node: dict[str, Any] = {"key": key, "record_kind": kind, "stage": stage, "output": rec["outputs"],
                            "code": code, "version": keyed.get("version"), "seed": keyed.get("seed"),
                            "params": keyed.get("params"), "env": env, "inputs": {}}
    fields: dict[str, Any] = rec["fields"] if isinstance(rec.get("fields"), dict) else {}
    if fields.get("code_files"):
        node["code_files"] = fields["code_files"]
    if rec.get("children"):
        node["items"] = len(rec["children"])
    if rec.get("seconds") is not None:
        node["seconds"] = rec["seconds"]
    for name, d in sorted(inputs.items()):
        if not isinstance(d, str):
            continue
        src = index.producer(d)
        node["inputs"][name] = {"digest": d, "from": src} if src else {"digest": d, "from": None, "source": True}
    return node


def trace(store: Store, roots: list[str], known: dict[str, str] | None = None) -> dict[str, dict[str, Any]]:
    """Nodes (by record key) of every record reachable from ``roots`` through their inputs."""
    index = _Index(store, known)
    nodes: dict[str, dict[str, Any]] = {}
    todo = list(roots)
    while todo and len(nodes) < MAX_NODES:
        key = todo.pop(0)
        if key in nodes:
            continue
        nodes[key] = n = _node(store, key, index)
        todo.extend(i["from"] for i in n.get("inputs", {}).values() if i.get("from"))
    return nodes


def open_cache(root: Path, given: bool) -> Store:
    """The cache at ``root`` for reading: never created (`lineage` only reads); one line naming
    it when it is not a cache directory (``given``: it came from --cache)."""
    from gcvd_flow.engine.paths import is_cache_dir

    if not is_cache_dir(root):
        what = "--cache " if given else "the cache "
        state = "does not exist" if not root.exists() else "is not a cache directory (no objects/ and records/)"
        raise UsageError(f"{what}{root}: {state}")
    return Store(root)


def _run_dir_cache(out: Path, cache: str | None) -> Store:
    from gcvd_flow.engine.paths import default_cache_dir, is_cache_dir

    if cache:
        return open_cache(Path(cache).expanduser(), True)
    root = read_run_dir(out).get("cache")
    return open_cache(Path(root) if root and is_cache_dir(root) else default_cache_dir(), False)


def lineage(target: str, stage: str | None = None, cache: str | None = None) -> dict[str, Any]:
    """The lineage of a run's stage (all stages without one), or of a digest: a record key, an
    output digest or an object digest in the cache."""
    p = Path(target)
    if (p / "run.json").is_file():
        run_doc = read_run_dir(p)
        stages = run_doc["stages"]  # one-line UsageError for any other shape
        if stage is not None and stage not in stages:
            raise UsageError(f"{p / 'run.json'}: no stage {stage!r} (stages: {', '.join(stages)})")
        store = _run_dir_cache(p, cache)
        names = [stage] if stage else list(reversed(list(stages)))  # the last stage first: it reaches the rest
        roots = [stages[n]["key"] for n in names if stages[n].get("key")]
        known = {s["output"]: s["key"] for s in stages.values() if s.get("output") and s.get("key")}
        doc = {"target": str(p), "roots": roots, "nodes": trace(store, roots, known)}
        inp = (run_doc.get("invocation") or {}).get("input") if isinstance(run_doc, dict) else None
        if isinstance(inp, str):
            doc["input"] = inp  # the file / folder the run read: what the "source" digests are of
        return doc
    if stage is not None:
        raise UsageError(f"{target}: not a run directory (STAGE goes with RUN_DIR)")
    if not is_digest(target):
        raise UsageError(f"{target}: neither a run directory nor a 64-hex digest")
    from gcvd_flow.engine.paths import default_cache_dir

    store = open_cache(Path(cache).expanduser() if cache else default_cache_dir(), bool(cache))
    index = _Index(store)
    root = target if store.read_record(target) is not None else index.producer(target)
    note = None
    if root is None:
        root = index.containing(target)
        note = f"object {target[:12]} is part of the output of record {root[:12]}" if root else None
    if root is None:
        raise UsageError(f"{target[:12]}: no record in {store.root} names this digest (pull it first?)")
    doc = {"target": target, "roots": [root], "nodes": trace(store, [root])}
    if note:
        doc["note"] = note
    return doc


def _short(v: Any, limit: int = 400) -> str:
    text = v if isinstance(v, str) else json.dumps(v, sort_keys=True)
    return text if len(text) <= limit else text[:limit] + " ..."  # --json has everything


def _shared_env(nodes: dict[str, dict[str, Any]]) -> Any:
    """The numeric environment when every record has the same one (the usual case), else None."""
    envs = {json.dumps(n.get("env"), sort_keys=True) for n in nodes.values() if not n.get("missing")}
    return json.loads(envs.pop()) if len(envs) == 1 else None


def format_text(doc: dict[str, Any], full: bool = False) -> str:
    """The tree as text: by default one line per record (stage, key, output, code, seed, params
    cut at 160 characters) with the shared environment once at the top; ``full``: also the code
    files, all parameters and each record's environment. Source inputs name the run's input."""
    nodes = doc["nodes"]
    lines = [doc["note"]] if doc.get("note") else []
    if doc.get("input"):
        lines.append(f"input: {doc['input']}")
    env = None if full else _shared_env(nodes)
    if env is not None:
        lines.append(f"env (every record): {_short(env, 300)}")
    source = "source: not produced by a stage" + (f"; the run's input {doc['input']}" if doc.get("input") else "")
    shown: set[str] = set()

    def show(key: str, depth: int) -> None:
        pad = "  " * depth
        n = nodes.get(key)
        if n is None:
            return
        if n.get("missing"):
            lines.append(f"{pad}record {key[:12]}: not in this cache")
            return
        what = f"{n['stage']} ({n['record_kind']} {key[:12]})"
        if key in shown:
            lines.append(f"{pad}{what}: see above")
            return
        shown.add(key)
        head = f"{pad}{what} -> output {n['output'][:12]}" + (f", {n['items']} items" if n.get("items") else "")
        if not full:
            seed = "" if n["seed"] is None else f", seed {n['seed']}"
            lines.append(f"{head}; code {str(n['code'])[:12]}{seed}; params {_short(n['params'], 160)}")
        else:
            lines.append(head)
            lines.append(f"{pad}  code {str(n['code'])[:12]}  version {n['version']}  seed {n['seed']}")
            if n.get("code_files"):
                lines.append(f"{pad}  code files: " + ", ".join(sorted(n["code_files"])))
            lines.append(f"{pad}  params: {_short(n['params'])}")
        if env is None:
            lines.append(f"{pad}  env: {_short(n['env'])}")
        for name, i in n["inputs"].items():
            up = nodes.get(i["from"]) if i.get("from") else None
            if up is not None and i["from"] in shown and not up.get("missing"):
                lines.append(f"{pad}  input {name} = {i['digest'][:12]}, produced by {up['stage']} "
                             f"({up['record_kind']} {i['from'][:12]}, above)")
            elif i.get("from"):
                lines.append(f"{pad}  input {name} = {i['digest'][:12]}, produced by:")
                show(i["from"], depth + 2)
            else:
                lines.append(f"{pad}  input {name} = {i['digest'][:12]} ({source})")

    for r in doc["roots"]:
        show(r, 0)
    return "\n".join(lines)
