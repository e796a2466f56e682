"""Share caches: push / pull / read through / verify a remote cache through fsspec.

A remote has the layout of a local cache (``objects/ab/cdef...``, ``records/ab/<key>.json``),
so a teammate's cache directory is a remote as it is, and so is a prefix in a bucket
(``s3://bucket/prefix`` through s3fs, credentials and endpoint from the standard AWS
environment) or a directory on an SSH server (``sftp://host/path`` through paramiko). Any
other fsspec file system works the same way; there is no code of ours per backend beyond the
two facts below.

Upload (push): objects first, then the records that name them (a map stage's item records
before the stage record). Where the file system can rename (local paths, SFTP), every file is
written under ``tmp/`` and renamed into place; object stores (S3, GCS, Azure) have no rename
but a PUT is atomic (an object appears whole or not at all), so there files are put directly
under their final name. Which objects the remote already has is learnt by *listing* its fan-out
directories (one request per directory, or one recursive listing for big pushes), never one
request per object; only missing objects (or ones of the wrong size) move. A push killed at any
point therefore leaves whole objects and records whose objects all exist: the remote stays
readable, and the next push completes it.

Download (pull, read-through runs): a record is used only if its preimage hashes to the key it
is filed under (``store.record_problem``: a swapped record is refused with a one-line warning
naming it); every object is read at most to the size its record declares (for local paths only
as a regular file: no FIFO, no symlink), re-hashed, and refused (one warning line, never used)
unless its bytes hash to its name. A pulled record enters the local store only once all its
objects and child records did. A read-through run (``RemoteRecords``) installs records with
their child records only; their objects stay on the remote until something reads one
(``RemoteObjects``, the store's fallback), then come in exactly as pulled ones do. Nothing
pulled is unpickled or executed: artifacts are JSON and npy / PNG / safetensors.

What a remote is *not* trusted for: a writer with access to it can publish wrong outputs under
a correctly derived key (the preimage proves which computation a record claims to be, not that
it was done honestly). Restrict write access to the remote (docs/teams.md).
"""

from __future__ import annotations

import os
import stat
import threading
import time
import uuid
from pathlib import Path
from typing import Any, Callable, Iterable, Literal

from gcvd_flow.engine import jsonio
from gcvd_flow.engine.errors import StoreError, UsageError
from gcvd_flow.engine.keys import digest_bytes, is_digest
from gcvd_flow.engine.names import TOOL
from gcvd_flow.engine.store import Store, canonical_json, record_problem

MAX_RECORD_BYTES = 64 << 20
BATCH_BYTES = 64 << 20  # at most this much object data in memory per transfer batch
BATCH_COUNT = 64  # objects / records per concurrent request batch
LIST_ALL_ABOVE = 32  # more fan-out directories than this: one recursive listing instead
# Protocols whose PUT is atomic and which have no (cheap) rename: files go in under their name.
ATOMIC_PUT_PROTOCOLS = {"s3", "s3a", "gs", "gcs", "az", "abfs", "abfss", "adl", "oss", "memory"}
STALE_TMP_S = 600.0  # fsck --repair deletes temporary files older than this

Log = Callable[[str], None]


def _stderr(msg: str) -> None:
    import sys

    print(msg, file=sys.stderr, flush=True)


def _read_regular(path: str | Path, limit: int) -> bytes | None:
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


class Remote:
    """A remote cache at an fsspec URL (or plain path) with its storage options."""

    def __init__(self, url: str, options: dict[str, Any] | None = None, label: str | None = None):
        import fsspec

        self.url = url
        self.label = label or url
        try:
            self.fs, root = fsspec.core.url_to_fs(url, **(options or {}))
        except (ValueError, ImportError, TypeError) as exc:
            raise UsageError(f"remote {self.label}: {exc}") from None
        protos = self.fs.protocol if isinstance(self.fs.protocol, (tuple, list)) else (self.fs.protocol,)
        self.local = bool({"file", "local"} & set(protos))
        self.atomic_put = bool(ATOMIC_PUT_PROTOCOLS & set(protos))
        self.root = root.rstrip("/") if root not in ("/", "") else root
        self._dirs: set[str] = set()
        if self.local and os.path.exists(self.root) and not os.path.isdir(self.root):
            raise UsageError(f"{url}: remote is a file, not a cache directory")

    # ------------------------------------------------------------ paths

    def obj(self, digest: str) -> str:
        return f"{self.root}/objects/{digest[:2]}/{digest[2:]}"

    def rec(self, key: str) -> str:
        return f"{self.root}/records/{key[:2]}/{key}.json"

    def exists(self) -> bool:
        try:
            return bool(self.fs.exists(f"{self.root}/records")) or bool(self.fs.exists(f"{self.root}/objects"))
        except OSError:
            return False

    # ------------------------------------------------------------ listing (batched existence)

    def _ls_many(self, dirs: list[str]) -> list[list[dict[str, Any]]]:
        """``ls(detail=True)`` of several directories: concurrently on async file systems."""
        if getattr(self.fs, "async_impl", False):
            import asyncio

            from fsspec.asyn import sync

            async def one(d: str) -> list[dict[str, Any]]:
                try:
                    return await self.fs._ls(d, detail=True)
                except FileNotFoundError:
                    return []

            async def all_() -> list[list[dict[str, Any]]]:
                return list(await asyncio.gather(*(one(d) for d in dirs)))

            return sync(self.fs.loop, all_)
        out = []
        for d in dirs:
            try:
                out.append(self.fs.ls(d, detail=True))
            except (FileNotFoundError, NotADirectoryError):
                out.append([])
        return out

    def _is_link(self, path: str) -> bool:
        """Whether ``path`` is a symbolic link (local and SFTP remotes; object stores have none)."""
        if self.local:
            return os.path.islink(path)
        ftp = getattr(self.fs, "ftp", None)
        if ftp is not None and hasattr(ftp, "lstat"):
            try:
                return stat.S_ISLNK(ftp.lstat(path).st_mode)
            except OSError:  # absent
                return False
        return False

    def _local_entries(self, top: str) -> list[dict[str, Any]]:
        """Everything under ``top`` (a local remote), never through a symbolic link: files as
        type "file", links as type "link" (listed, not followed), other kinds as "other"."""
        out = []
        for dirpath, dirnames, filenames in os.walk(top):  # followlinks=False: linked folders are not entered
            for name in sorted(dirnames + filenames):
                path = os.path.join(dirpath, name)
                try:
                    st = os.lstat(path)
                except OSError:
                    continue
                if stat.S_ISDIR(st.st_mode):
                    continue
                kind = "file" if stat.S_ISREG(st.st_mode) else "link" if stat.S_ISLNK(st.st_mode) else "other"
                out.append({"name": path, "type": kind, "size": st.st_size, "mtime": st.st_mtime,
                            "islink": kind == "link"})
        return out

    def _entries(self, area: str, prefixes: Iterable[str] | None) -> list[dict[str, Any]]:
        """The files of one area (objects, records, tmp), or of its fan-out folders ``prefixes``.
        Never through a symbolic link: a linked area or fan-out folder is listed as one entry of
        type "link" (stray: ``fsck --repair`` deletes the link itself, nothing it points to)."""
        self.fs.invalidate_cache()
        prefixes = None if prefixes is None else sorted(set(prefixes))
        top = f"{self.root}/{area}"
        if self._is_link(top):
            return [{"name": top, "type": "link", "size": 0, "islink": True}]
        if self.local:
            if prefixes is None or len(prefixes) > LIST_ALL_ABOVE:
                return self._local_entries(top) if os.path.isdir(top) else []
            out = []
            for p in prefixes:
                d = f"{top}/{p}"
                if os.path.islink(d):
                    out.append({"name": d, "type": "link", "size": 0, "islink": True})
                elif os.path.isdir(d):
                    out.extend(e for e in self._local_entries(d))
            return out
        if prefixes is None or len(prefixes) > LIST_ALL_ABOVE:
            try:
                found = self.fs.find(f"{self.root}/{area}", detail=True)
            except FileNotFoundError:
                return []
            return list(found.values())
        return [e for batch in self._ls_many([f"{self.root}/{area}/{p}" for p in prefixes]) for e in batch]

    def _is_file(self, e: dict[str, Any]) -> bool:
        return e.get("type") == "file" and not (self.local and e.get("islink"))

    def object_sizes(self, digests: Iterable[str] | None = None) -> dict[str, int]:
        """digest -> size of the remote's objects (those with these digests' prefixes, or all)."""
        prefixes = None if digests is None else {d[:2] for d in digests}
        out = {}
        for e in self._entries("objects", prefixes):
            parts = e["name"].rstrip("/").split("/")
            name = parts[-2] + parts[-1] if len(parts) >= 2 else ""
            if self._is_file(e) and is_digest(name) and parts[-2] == name[:2]:
                out[name] = int(e.get("size") or 0)
        return out

    def record_keys(self, keys: Iterable[str] | None = None) -> set[str]:
        prefixes = None if keys is None else {k[:2] for k in keys}
        out = set()
        for e in self._entries("records", prefixes):
            base = e["name"].rstrip("/").rsplit("/", 1)[-1]
            if self._is_file(e) and base.endswith(".json") and is_digest(base[:-5]):
                out.add(base[:-5])
        return out

    def other_files(self) -> dict[str, list[str]]:
        """Files under objects/ and records/ that are no object or record (for fsck)."""
        bad: dict[str, list[str]] = {"objects": [], "records": []}
        for area in bad:
            for e in self._entries(area, None):
                parts = e["name"].rstrip("/").split("/")
                ok = (len(parts) >= 2 and self._is_file(e)
                      and (is_digest(parts[-2] + parts[-1]) and len(parts[-2]) == 2 if area == "objects"
                           else parts[-1].endswith(".json") and is_digest(parts[-1][:-5])))
                if not ok:
                    bad[area].append(e["name"])
        return bad

    # ------------------------------------------------------------ reads

    def read_many(self, paths: list[str], limits: list[int]) -> list[bytes | None]:
        """At most ``limit`` bytes of each path (None: absent, unreadable, or longer)."""
        if not paths:
            return []
        if self.local:
            return [_read_regular(p, lim) for p, lim in zip(paths, limits)]
        res = self.fs.cat_ranges(paths, [0] * len(paths), [lim + 1 for lim in limits], on_error="return")
        out: list[bytes | None] = []
        for path, r, lim in zip(paths, res, limits):
            if isinstance(r, BaseException) and not isinstance(r, (FileNotFoundError, IsADirectoryError)):
                r = self._entry_error(path, r)
            out.append(r if isinstance(r, bytes) and len(r) <= lim else None)
        return out

    def _entry_error(self, path: str, exc: BaseException) -> bytes | None:
        """A read of one entry failed: if the remote answers for that entry, the entry is what is
        bad (an empty object, whose byte range 0..n S3 calls "not satisfiable") and the others are
        still used: b"" for an empty one, None otherwise. If it does not answer, the remote
        itself is failing (network, credentials): that error is raised."""
        try:
            info = self.fs.info(path)
        except FileNotFoundError:
            return None
        except Exception:  # noqa: BLE001 - the remote does not answer: its error, not the entry's
            raise exc from None
        return b"" if info.get("size") == 0 else None

    # ------------------------------------------------------------ writes

    def _makedirs(self, d: str) -> None:
        if d not in self._dirs:
            self.fs.makedirs(d, exist_ok=True)
            self._dirs.add(d)

    def write_many(self, files: dict[str, bytes]) -> None:
        """Each file appears whole under its name or not at all (see the module docstring)."""
        if not files:
            return
        if self.atomic_put:
            self.fs.pipe(files)
            return
        tmp_dir = f"{self.root}/tmp"
        self._makedirs(tmp_dir)
        for path, data in files.items():
            tmp = f"{tmp_dir}/{os.getpid()}-{uuid.uuid4().hex}"
            self.fs.pipe_file(tmp, data)
            self._makedirs(path.rsplit("/", 1)[0])
            self.fs.mv(tmp, path)

    def delete(self, paths: list[str]) -> list[str]:
        """Delete entries of the remote: only a file (a link, FIFO, ... itself: unlinking never
        follows it) whose folder's real path is inside the remote's root; never a folder, never
        through a link. Returns the paths it refused to delete."""
        ok: list[str] = []
        refused: list[str] = []
        for p in paths:
            (ok if self._deletable(p) else refused).append(p)
        for i in range(0, len(ok), 500):
            try:
                self.fs.rm(ok[i:i + 500])
            except FileNotFoundError:
                pass
        return refused

    def _deletable(self, path: str) -> bool:
        if not path.startswith(self.root.rstrip("/") + "/"):
            return False
        parent = path.rsplit("/", 1)[0]
        if self.local:
            root = os.path.realpath(self.root)
            try:
                st = os.lstat(path)
            except FileNotFoundError:
                return False
            inside = os.path.realpath(parent) == root or os.path.realpath(parent).startswith(root + os.sep)
            return inside and not stat.S_ISDIR(st.st_mode)
        ftp = getattr(self.fs, "ftp", None)
        if ftp is not None and hasattr(ftp, "lstat") and hasattr(ftp, "normalize"):  # SFTP
            try:
                st = ftp.lstat(path)
                root, real_parent = ftp.normalize(self.root), ftp.normalize(parent)
            except OSError:
                return False
            inside = real_parent == root or real_parent.startswith(root.rstrip("/") + "/")
            return inside and not stat.S_ISDIR(st.st_mode)
        return True  # object stores: keys, no links, no folders to escape through

    def tmp_files(self) -> list[dict[str, Any]]:
        return self._entries("tmp", None)


def open_remote(name_or_url: str | None, remotes_file: str | None = None) -> Remote:
    from gcvd_flow.engine.remotes_config import resolve

    spec = resolve(name_or_url, remotes_file)
    return Remote(spec.url, spec.options, spec.label)


# ------------------------------------------------------------------------------ upload


def _batches(items: list[tuple[str, int]], max_bytes: int = BATCH_BYTES, max_count: int = BATCH_COUNT):
    batch: list[tuple[str, int]] = []
    total = 0
    for it in items:
        if batch and (total + it[1] > max_bytes or len(batch) >= max_count):
            yield batch
            batch, total = [], 0
        batch.append(it)
        total += it[1]
    if batch:
        yield batch


def _local_closure(local: Store, keys: Iterable[str]) -> list[tuple[str, dict[str, Any]]]:
    """(key, record) of the keys and their children, children before their parent."""
    out: list[tuple[str, dict[str, Any]]] = []
    seen: set[str] = set()
    for key in keys:
        if key in seen or not is_digest(key):
            continue
        seen.add(key)
        rec = local.get_record(key)
        if rec is None:
            continue
        for c in rec.get("children", []):
            if c not in seen:
                seen.add(c)
                crec = local.get_record(c)
                if crec is not None:
                    out.append((c, crec))
        out.append((key, rec))
    return out


def upload(local: Store, remote: Remote, keys: Iterable[str], log: Log = _stderr) -> dict[str, Any]:
    """Push records (with their children) and their objects; objects first, records last."""
    stats: dict[str, Any] = {"records": 0, "objects": 0, "bytes": 0, "refused": 0, "skipped": 0,
                             "refused_records": [], "refused_objects": []}
    recs = _local_closure(local, keys)
    need: dict[str, int] = {}
    for _, rec in recs:
        need.update(rec["objects"])
    have = remote.object_sizes(need)
    missing = sorted((d, s) for d, s in need.items() if have.get(d) != s)
    bad: set[str] = set()
    for batch in _batches(missing):
        files = {}
        for d, _ in batch:
            try:
                files[remote.obj(d)] = local.get_bytes(d, verify=True)  # never publish a corrupt object
            except StoreError as exc:
                bad.add(d)
                log(f"warning: not pushing local object {d[:12]}: {exc}")
        remote.write_many(files)
        stats["objects"] += len(files)
        stats["bytes"] += sum(len(v) for v in files.values())
    present = remote.record_keys(k for k, _ in recs)
    todo = [(k, r) for k, r in recs if k not in present and not bad & set(r["objects"])]
    stats["skipped"] = sum(1 for k, _ in recs if k not in present) - len(todo)  # name a corrupt object
    # children precede parents in ``recs``; a batch is written before the next starts
    for i in range(0, len(todo), BATCH_COUNT):
        remote.write_many({remote.rec(k): canonical_json(r) for k, r in todo[i:i + BATCH_COUNT]})
        stats["records"] += len(todo[i:i + BATCH_COUNT])
    stats["refused_objects"] = sorted(bad)
    return stats


# ------------------------------------------------------------------------------ download


class Downloader:
    """Verified transfers from one remote into one local store. Remembers what it refused, so
    an object named by several records is fetched (and warned about) once."""

    def __init__(self, local: Store, remote: Remote, log: Log = _stderr):
        self.local, self.remote, self.log = local, remote, log
        self.refused_objects: dict[str, str] = {}
        self.refused_records: dict[str, str] = {}
        self.promised: dict[str, int] = {}  # digest -> size: objects on the remote, fetched when read
        self.stats: dict[str, Any] = {"records": 0, "objects": 0, "bytes": 0}

    def _warn_record(self, key: str, why: str) -> None:
        if key not in self.refused_records:
            self.refused_records[key] = why
            self.log(f"warning: remote {self.remote.label}: record {key[:12]} refused ({why}); not used")

    def _warn_object(self, digest: str, why: str) -> None:
        if digest not in self.refused_objects:
            self.refused_objects[digest] = why
            self.log(f"warning: remote {self.remote.label}: object {digest[:12]} refused ({why}); not used")

    def fetch_records(self, keys: list[str]) -> dict[str, dict[str, Any]]:
        """Valid remote records of ``keys`` (absent ones silently missing, bad ones refused)."""
        out: dict[str, dict[str, Any]] = {}
        for i in range(0, len(keys), BATCH_COUNT):
            chunk = keys[i:i + BATCH_COUNT]
            raws = self.remote.read_many([self.remote.rec(k) for k in chunk], [MAX_RECORD_BYTES] * len(chunk))
            for k, raw in zip(chunk, raws):
                if raw is None:
                    continue
                try:
                    rec = jsonio.loads(raw)  # depth-limited: 200,000 nested [ is a refused record
                except ValueError:
                    rec = None
                problem = record_problem(k, rec)
                if problem is not None:
                    self._warn_record(k, problem)
                    continue
                out[k] = rec
        return out

    def fetch_objects(self, need: dict[str, int]) -> None:
        """Bring missing objects into the local store, each verified; bad ones refused."""
        todo = sorted((d, s) for d, s in need.items()
                      if self.local.object_size(d) != s and d not in self.refused_objects)
        for batch in _batches(todo):
            datas = self.remote.read_many([self.remote.obj(d) for d, _ in batch], [s for _, s in batch])
            for (d, size), data in zip(batch, datas):
                if data is None:
                    self._warn_object(d, "missing, unreadable or larger than its record says")
                elif len(data) != size:
                    self._warn_object(d, f"{len(data)} bytes, its record says {size}")
                elif digest_bytes(data) != d:  # never trust a name
                    self._warn_object(d, "its bytes do not hash to its name")
                else:
                    self.local.put_bytes(data)
                    self.stats["objects"] += 1
                    self.stats["bytes"] += size

    def download(self, keys: Iterable[str], list_first: bool = False, objects: bool = True) -> list[str]:
        """Install the remote records of ``keys`` (with their children and objects) into the
        local store; returns the keys installed. ``list_first``: learn which records exist by
        listing (many keys, most probably absent) instead of asking for each. ``objects=False``
        (read-through runs): the records come in verified, their objects stay on the remote
        until something reads them (``promised``; ``RemoteObjects`` fetches them)."""
        keys = [k for k in dict.fromkeys(keys) if is_digest(k) and k not in self.refused_records]
        if list_first and keys:
            present = self.remote.record_keys(keys)
            keys = [k for k in keys if k in present]
        recs = self.fetch_records(keys)
        kids = sorted({c for r in recs.values() for c in r.get("children", [])
                       if c not in recs and self.local.read_record(c) is None})
        both = {**self.fetch_records(kids), **recs}
        if objects:
            need: dict[str, int] = {}
            for r in both.values():
                need.update(r["objects"])
            self.fetch_objects(need)
            if recs:
                self.local.sync()  # objects durable before the records that name them
        installed: list[str] = []
        for k, r in sorted(both.items(), key=lambda kv: bool(kv[1].get("children"))):  # children first
            if objects and any(self.local.object_size(d) != s for d, s in r["objects"].items()):
                continue
            if any(self.local.read_record(c) is None for c in r.get("children", [])):
                continue
            if self.local.read_record(k) is None:
                self.local.put_record(k, r)
                self.stats["records"] += 1
            if not objects:
                self.promise(r["objects"])
            installed.append(k)
        return installed

    def promise(self, objects: dict[str, int]) -> None:
        """Objects a record that came in names: the remote holds them (objects are pushed before
        the records naming them), so they may be fetched when read."""
        for d, size in objects.items():
            if d not in self.promised:
                self.promised[d] = size
                self.stats["objects_named"] = self.stats.get("objects_named", 0) + 1
                self.stats["bytes_named"] = self.stats.get("bytes_named", 0) + size

    def report(self) -> dict[str, Any]:
        return {**self.stats, "refused": len(self.refused_objects),
                "refused_objects": sorted(self.refused_objects),
                "refused_records": [f"{k[:12]}: {w}" for k, w in sorted(self.refused_records.items())]}


# ------------------------------------------------------------------------------ push / pull


def _run_keys(out: str | None, store: Store) -> list[str]:
    if out is None:
        return [k for k, _ in store.iter_records()]
    from gcvd_flow.engine.outputs import read_run_dir

    stages = read_run_dir(out)["stages"]  # one-line UsageError for any other shape
    return [s["key"] for s in stages.values() if s.get("key")]


def _as_remote(remote: str | Remote | None, remotes_file: str | None = None) -> Remote:
    return remote if isinstance(remote, Remote) else open_remote(remote, remotes_file)


_BUGS = (TypeError, AttributeError, NameError, KeyError, IndexError, AssertionError)


class _RemoteErrors:
    """A backend's error (network, credentials, a missing bucket) as one line naming the remote."""

    def __init__(self, r: Remote):
        self.r = r

    def __enter__(self) -> None:
        return None

    def __exit__(self, typ, exc, tb) -> Literal[False]:  # never swallows: returns False or raises
        if exc is None or isinstance(exc, (UsageError, StoreError)) or not isinstance(exc, Exception):
            return False
        if isinstance(exc, _BUGS):  # our bug, not the remote's state: keep the traceback
            return False
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise UsageError(f"remote {self.r.label}: {text}") from exc


def push(local: Store, remote: str | Remote | None, out: str | None = None, remotes_file: str | None = None,
         log: Log = _stderr) -> dict[str, Any]:
    """Copy a run's records (or all) with their objects to the remote."""
    r = _as_remote(remote, remotes_file)
    with local.lease(), _RemoteErrors(r):
        return upload(local, r, _run_keys(out, local), log)


def pull(local: Store, remote: str | Remote | None, out: str | None = None, remotes_file: str | None = None,
         log: Log = _stderr) -> dict[str, Any]:
    """Copy a run's records (or all the remote has) into the local cache, verified."""
    r = _as_remote(remote, remotes_file)
    with local.lease(), _RemoteErrors(r):
        if not r.exists():
            raise UsageError(f"{r.label}: remote not found (not a {TOOL} cache)")
        keys = _run_keys(out, local) if out else sorted(r.record_keys())
        d = Downloader(local, r, log)
        installed = d.download(keys)
        rep = d.report()
        rep["skipped"] = len(set(keys) - set(installed))
        return rep


# ------------------------------------------------------------------------------ read-through runs


class RemoteObjects:
    """The local store's object source during a read-through run (``Store.fallback``): the
    objects named by the records that came in (``Downloader.promised``) count as present, and
    are downloaded only when something reads one — the runner decoding a stage's value, a map
    item's inputs before it is dispatched, the export writing RUN_DIR. Each comes in as a pulled
    one does: read at most to its recorded size, re-hashed, refused with one warning line and
    never used unless its bytes hash to its name. A refused object (or any once the remote has
    failed) is no longer offered, so the records naming it become invisible and what they held
    is recomputed (the run's self-healing pass)."""

    def __init__(self, records: "RemoteRecords"):
        self._records = records
        self._lock = threading.Lock()  # a stage may read from several threads

    def size(self, digest: str) -> int | None:
        down = self._records._down
        if down is None or self._records.failed is not None or digest in down.refused_objects:
            return None
        return down.promised.get(digest)

    def fetch(self, digests: Iterable[str]) -> None:
        down = self._records._down
        with self._lock:
            need = {d: s for d in digests if (s := self.size(d)) is not None}
            if need and down is not None:
                self._records._guard("read-through", lambda: down.fetch_objects(need))


class RemoteRecords:
    """The runner's record source for ``run --remote`` / ``--push``: the local store first,
    then the remote (a record found there comes in verified, with its children; its objects
    follow when read, through ``objects``, the store's fallback); ``stage_done`` pushes each
    finished stage the remote does not hold yet.

    As with Bazel's remote cache, the remote is an accelerator, not a dependency: if it cannot
    be reached (network, credentials, a missing bucket), one warning line says so and the run
    goes on with the local cache alone (nothing half-downloaded is ever installed, and what was
    only on the remote is recomputed)."""

    def __init__(self, store: Store, remote: Remote | None, push: bool = False, log: Log = _stderr):
        self.store, self.remote, self.push, self.log = store, remote, push, log
        self._down = Downloader(store, remote, log) if remote is not None else None
        self._tried: set[str] = set()
        self.pushed: dict[str, int] = {"records": 0, "objects": 0, "bytes": 0}
        self.failed: str | None = None
        self.objects = RemoteObjects(self)
        self.attach(store)

    def attach(self, store: Store) -> None:
        """Serve ``store`` (a run opens its store again for each self-healing pass; what came
        in, was refused and was tried is remembered across passes)."""
        self.store = store
        if self._down is not None:
            self._down.local = store
            store.fallback = self.objects

    def _guard(self, what: str, fn: Callable[[], Any]) -> None:
        if self.failed is not None or self.remote is None:
            return
        try:
            fn()
        except (StoreError, UsageError, *_BUGS):
            raise
        except Exception as exc:  # noqa: BLE001 - any backend's error: network, auth, bucket
            self.failed = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
            self.log(f"warning: remote {self.remote.label}: {what} failed ({self.failed}); "
                     f"going on without the remote")

    def get_record(self, key: str) -> dict[str, Any] | None:
        rec = self.store.get_record(key)
        down = self._down
        if rec is None and down is not None and key not in self._tried:
            self._tried.add(key)
            self._guard("read-through", lambda: down.download([key], objects=False))
            rec = self.store.get_record(key)
        return rec

    def prefetch(self, keys: list[str]) -> None:
        """Items of a map stage: the records this store lacks, fetched in concurrent batches
        (one request per record: the cost follows the run's size, not the remote's)."""
        down = self._down
        if down is None:
            return
        missing = [k for k in keys if k not in self._tried and self.store.get_record(k) is None]
        self._tried.update(missing)
        if missing:
            self._guard("read-through", lambda: down.download(missing, objects=False))

    def stage_done(self, key: str | None, executed: int) -> None:
        remote = self.remote
        if not self.push or key is None or remote is None:
            return

        def push_stage() -> None:
            if not executed and key in remote.record_keys([key]):
                return
            st = upload(self.store, remote, [key], self.log)
            for k in self.pushed:
                self.pushed[k] += st[k]

        self._guard("push", push_stage)

    def report(self) -> dict[str, Any]:
        out: dict[str, Any] = {"remote": self.remote.label if self.remote else None}
        if self._down is not None:
            out["pulled"] = self._down.report()
        if self.push:
            out["pushed"] = dict(self.pushed)
        if self.failed:
            out["failed"] = self.failed
        return out


def record_source(store: Store, remote: str | None, remotes_file: str | None = None, push: bool = False,
                  log: Log = _stderr) -> RemoteRecords:
    return RemoteRecords(store, open_remote(remote, remotes_file), push=push, log=log)


# ------------------------------------------------------------------------------ fsck --remote


def fsck_remote(remote: str | Remote | None, repair: bool = False, remotes_file: str | None = None,
                log: Log = _stderr) -> dict[str, Any]:
    """Verify a remote in place: re-hash every object, check every record (preimage, objects
    present with their sizes, children present). Lists what is bad; deletes it (and stale
    temporary files) only with ``repair``."""
    r = _as_remote(remote, remotes_file)
    with _RemoteErrors(r):
        if not r.exists():
            raise UsageError(f"{r.label}: remote not found (not a {TOOL} cache)")
        return _fsck_remote(r, repair)


def _fsck_remote(r: Remote, repair: bool) -> dict[str, Any]:
    # Records are listed before objects: a push writes a record only after all its objects, so
    # every record listed here names objects the later object listing sees. (Listing objects
    # first made a record pushed in between look as if it lost its objects, and --repair
    # deleted good records of a push in progress.)
    keys = sorted(r.record_keys())
    sizes = r.object_sizes()
    bad_objects: dict[str, str] = {}
    for batch in _batches(sorted(sizes.items())):
        datas = r.read_many([r.obj(d) for d, _ in batch], [s for _, s in batch])
        for (d, _), data in zip(batch, datas):
            if data is None:
                bad_objects[d] = "unreadable"
            elif digest_bytes(data) != d:
                bad_objects[d] = "its bytes do not hash to its name"
    good = {d: s for d, s in sizes.items() if d not in bad_objects}
    bad_records: dict[str, str] = {}
    recs = {}
    for i in range(0, len(keys), BATCH_COUNT):
        chunk = keys[i:i + BATCH_COUNT]
        for k, raw in zip(chunk, r.read_many([r.rec(k) for k in chunk], [MAX_RECORD_BYTES] * len(chunk))):
            try:
                rec = jsonio.loads(raw) if raw is not None else None
            except ValueError:
                rec = None
            problem = "unreadable" if raw is None else record_problem(k, rec)
            if problem is None and isinstance(rec, dict):  # record_problem checked its shape
                lost = [d for d, s in rec["objects"].items() if good.get(d) != s]
                problem = f"names {len(lost)} missing or bad object(s), e.g. {lost[0][:12]}" if lost else None
            if problem is not None or not isinstance(rec, dict):
                bad_records[k] = problem or "not a record"
            else:
                recs[k] = rec
    for k, rec in recs.items():
        lost = [c for c in rec.get("children", []) if c not in recs]
        if lost:
            bad_records[k] = f"{len(lost)} child record(s) missing or bad, e.g. {lost[0][:12]}"
    others = r.other_files()
    now = time.time()
    tmp = r.tmp_files()
    stray = others["objects"] + others["records"] + [e["name"] for e in tmp if e.get("type") != "file"]
    stale = [e["name"] for e in tmp if e.get("type") == "file" and now - _mtime(e, now) > STALE_TMP_S]
    rep = {"remote": r.label, "objects": len(sizes), "bytes": sum(sizes.values()), "records": len(keys),
           "bad_objects": [f"{d}: {w}" for d, w in sorted(bad_objects.items())],
           "bad_records": [f"{k}: {w}" for k, w in sorted(bad_records.items())],
           "stray_files": stray, "tmp_files": len(tmp),
           "clean": not bad_objects and not bad_records and not stray, "repaired": False}
    if repair:
        refused = r.delete(sorted(r.rec(k) for k in bad_records))  # records first: never one naming a deleted object
        refused += r.delete(sorted(r.obj(d) for d in bad_objects) + stray + stale)
        rep["repaired"] = True
        rep["tmp_removed"] = len([p for p in stale if p not in refused])
        if refused:  # not a regular file, or not really inside the remote: left alone
            rep["not_deleted"] = refused
    return rep


def _mtime(entry: dict[str, Any], default: float) -> float:
    for k in ("mtime", "LastModified", "created", "time"):
        v: Any = entry.get(k)
        if isinstance(v, (int, float)):
            return float(v)
        if hasattr(v, "timestamp"):
            return float(v.timestamp())
    return default
