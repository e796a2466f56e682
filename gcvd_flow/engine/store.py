"""Content-addressed store: immutable blobs, stage records, locks, verification, gc.

Layout of a cache directory::

    objects/ab/cdef...      blobs named by the BLAKE3 of their bytes, read-only
    records/ab/<key>.json   what a stage (or one item of a map stage) produced for a key
    locks/ab/<key>.lock     advisory OS locks (flock): released by the kernel when the
                            holder dies, so a kill -9 never leaves a stale lock
    tmp/                    files being written; never read as results
    runs/<id>.json          roots of finished runs (for gc), pins/<name>.json pinned roots
    quarantine/             objects whose bytes no longer match their name (found by fsck)

Write protocol (docs/design.md, "Write protocol and locks"): write to ``tmp/``, hash, rename into
``objects/``; the record
that points at the outputs is written the same way and last. A reader therefore only ever sees
complete objects, and a record only once all of its objects exist, whatever moment a process
is killed at.

Durability against power loss: by default the store calls ``syncfs`` once per stage and
before each stage record (``Store.sync``) instead of ``fsync`` per object, because on this
class of disk a per-object fsync costs ~10 ms and dominated cold runs of 1000-item stages
(measured in docs/benchmarks.md). Records carry the size of every object they name and reads
re-hash objects, so an object lost or torn by a power cut is detected and recomputed, never
read as a result. ``GCVD_FLOW_FSYNC=always`` restores fsync per object and record.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import re
import shutil
import stat
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Protocol

import blake3

from gcvd_flow.engine import jsonio
from gcvd_flow.engine.errors import StoreError  # noqa: F401 - re-exported
from gcvd_flow.engine.jsonio import read_regular
from gcvd_flow.engine.keys import digest_bytes, is_digest, key_of
from gcvd_flow.engine.names import ENV_FSYNC
from gcvd_flow.engine.paths import default_cache_dir  # noqa: F401 - re-exported

PIN_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]{0,127}")


def _roots_file(path: Path, what: str) -> dict[str, Any]:
    """A runs/<id>.json or pins/<name>.json: {"records": [record keys], ...}; StoreError naming
    the file for anything else (unreadable, not a regular file, other JSON shapes)."""
    try:
        doc = jsonio.loads(read_regular(path, MAX_ROOTS_BYTES))
    except (OSError, ValueError) as exc:
        raise StoreError(f"{path}: not a valid {what} file ({getattr(exc, 'strerror', None) or exc}); "
                         f"remove it") from None
    recs = doc.get("records") if isinstance(doc, dict) else None
    if not isinstance(recs, list) or not all(is_digest(k) for k in recs):
        raise StoreError(f"{path}: not a valid {what} file (\"records\" must be a list of record keys); remove it")
    return doc


MAX_ROOTS_BYTES = 64 << 20
MAX_OBJECT_BYTES = 1 << 46  # 64 TiB: a record declaring more (10**100) is malformed


def record_problem(key: str, rec: Any) -> str | None:
    """Why ``rec`` is not a usable record for ``key`` (None if it is): malformed, or filed
    under a key its preimage does not hash to (a swapped or forged-by-mistake record)."""
    if not isinstance(rec, dict) or not is_digest(rec.get("outputs")):
        return "malformed record"
    objs = rec.get("objects")
    if not isinstance(objs, dict) or not all(is_digest(d) and type(s) is int and 0 <= s <= MAX_OBJECT_BYTES
                                             for d, s in objs.items()):
        return "malformed object list"
    if not isinstance(rec.get("children", []), list) or not all(is_digest(c) for c in rec.get("children", [])):
        return "malformed children"
    try:
        if key_of(rec.get("preimage")) != key:
            return "its preimage does not hash to its key"
    except (TypeError, ValueError):
        return "unreadable preimage"
    return None


class CorruptObject(StoreError):
    """An object's bytes do not match its digest (it has been moved to quarantine)."""

    def __init__(self, message: str, digest: str = ""):
        super().__init__(message)
        self.digest = digest


class MissingObject(StoreError):
    """An object a record names is not in the cache (deleted, or lost with a crash), or one the
    store's object source could not supply (``remote``: it said why already, on one line)."""

    def __init__(self, message: str, digest: str = "", remote: bool = False):
        super().__init__(message)
        self.digest = digest
        self.remote = remote


class ObjectSource(Protocol):
    """Where a store gets objects it lacks (``Store.fallback``; a read-through run installs the
    remote's: ``remote.RemoteObjects``). ``size`` is the size of an object the source can
    supply (None: it cannot); ``fetch`` brings such objects into the store, each verified
    against its digest and size; what it refuses stays absent (it says why)."""

    def size(self, digest: str) -> int | None: ...

    def fetch(self, digests: Iterable[str]) -> None: ...


def canonical_json(obj: Any) -> bytes:
    """Deterministic JSON bytes (sorted keys, no spaces, no NaN)."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True,
                      allow_nan=False).encode()


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@dataclass
class FsckReport:
    objects: int = 0
    bytes: int = 0
    corrupt: list[str] = field(default_factory=list)
    records_removed: int = 0
    tmp_removed: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {"objects": self.objects, "bytes": self.bytes, "corrupt": self.corrupt or [],
                "records_removed": self.records_removed, "tmp_removed": self.tmp_removed}


def _syncfs(path: Path) -> None:
    """Flush the file system holding ``path`` (Linux syncfs; os.sync elsewhere)."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        fd = os.open(path, os.O_RDONLY)
        try:
            libc.syncfs(fd)
        finally:
            os.close(fd)
    except (OSError, AttributeError):
        os.sync()


class Store:
    """A content-addressed object store plus key → record map in one directory."""

    def __init__(self, root: str | Path, verify: bool = True):
        self.root = Path(root).expanduser()
        self.verify = verify
        # objects this store lacks but may fetch when read (None: a record naming a missing
        # object is invisible; a read-through run sets the remote's, see ObjectSource)
        self.fallback: ObjectSource | None = None
        self.fsync_always = os.environ.get(ENV_FSYNC, "") == "always"
        self._dirs: set[str] = set()  # fan-out directories known to exist (saves mkdir calls)
        self._objects = str(self.root / "objects")
        self._tmp = str(self.root / "tmp")
        for sub in ("objects", "records", "locks", "tmp", "runs", "pins", "quarantine"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)

    def _ensure_dir(self, d: str | Path) -> None:
        k = str(d)
        if k not in self._dirs:
            os.makedirs(k, exist_ok=True)
            self._dirs.add(k)

    # ---------------------------------------------------------------- objects

    def object_path(self, digest: str) -> Path:
        return Path(self._object_file(digest))

    def _object_file(self, digest: str) -> str:
        """object_path as a string (the hot paths: pathlib's joins cost more than the reads)."""
        if not is_digest(digest):
            raise StoreError(f"not a digest: {digest!r}")
        return f"{self._objects}/{digest[:2]}/{digest[2:]}"

    def has(self, digest: str) -> bool:
        return os.path.exists(self._object_file(digest))

    def _tmp_file(self) -> Path:
        return Path(f"{self._tmp}/{os.getpid()}-{uuid.uuid4().hex}")

    def _publish(self, tmp: Path, digest: str) -> None:
        """Rename a complete temp file into place as an immutable object. An existing object of
        another size (truncated by a crash or by hand) is replaced, never trusted."""
        dest = self._object_file(digest)
        size = self.object_size(digest)
        if size is not None and size == os.stat(tmp).st_size:
            tmp.unlink(missing_ok=True)
            return
        # chmod before rename: an object is never visible writable
        self._ensure_dir(os.path.dirname(dest))
        os.chmod(tmp, 0o444)
        os.replace(tmp, dest)
        if self.fsync_always:
            _fsync_dir(Path(dest).parent)

    def put_bytes(self, data: bytes | memoryview) -> str:
        digest = digest_bytes(data)
        if self.object_size(digest) == len(data):
            return digest  # present and whole (reads re-hash: a same-size corruption is caught there)
        tmp = self._tmp_file()
        with open(tmp, "wb") as f:
            f.write(data)
            if self.fsync_always:
                f.flush()
                os.fsync(f.fileno())
        self._publish(tmp, digest)
        return digest

    def sync(self) -> None:
        """Make everything written so far durable (called before stage records)."""
        if not self.fsync_always:
            _syncfs(self.root)

    @contextlib.contextmanager
    def writer(self) -> Iterator["_ObjectWriter"]:
        """Stream bytes into a new object; ``w.digest`` is set when the block exits."""
        w = _ObjectWriter(self._tmp_file())
        try:
            yield w
            w.finish()
            self._publish(w.tmp, w.digest)
        finally:
            if not w.file.closed:
                w.file.close()
            w.tmp.unlink(missing_ok=True)

    def get_bytes(self, digest: str, verify: bool | None = None) -> bytes:
        path = self._object_file(digest)
        data = self._read(path)
        want = self.fallback.size(digest) if self.fallback is not None else None
        if want is not None and (data is None or len(data) != want):
            self.ensure([digest])  # fetched lazily, verified on its way in (or MissingObject)
            data = self._read(path)
        if data is None:
            raise MissingObject(f"object {digest[:12]} is missing from the cache", digest)
        if self.verify if verify is None else verify:
            if digest_bytes(data) != digest:
                self.quarantine(digest)
                raise CorruptObject(f"object {digest[:12]} is corrupt (moved to quarantine)", digest)
        return data

    @staticmethod
    def _read(path: str | Path) -> bytes | None:
        """The bytes of a regular file; None when absent or not a regular file (a FIFO or a
        device put in the cache would block a read, or never end)."""
        try:
            return read_regular(path, 1 << 62)
        except (FileNotFoundError, NotADirectoryError):
            return None
        except OSError as exc:
            if exc.errno in (errno.EINVAL, errno.EFBIG, errno.ELOOP):
                return None
            raise

    def ensure(self, digests: Iterable[str]) -> None:
        """Fetch from the fallback, in one batch (one round trip, not one per object), those of
        ``digests`` it offers that are absent here or of another size (truncated: never
        trusted); no-op without a fallback. Raises ``MissingObject`` (``remote=True``) for
        one the fallback then did not supply (refused: it said why)."""
        fb = self.fallback
        if fb is None:
            return
        need = {d: s for d in dict.fromkeys(digests) if (s := fb.size(d)) is not None and self.object_size(d) != s}
        if not need:
            return
        fb.fetch(list(need))
        for d, s in need.items():
            if self.object_size(d) != s:
                raise MissingObject(f"object {d[:12]} is missing from the cache and the remote could not "
                                    f"supply it", d, remote=True)

    def quarantine(self, digest: str) -> None:
        src = self.object_path(digest)
        if os.path.lexists(src):
            dest = self.root / "quarantine" / digest
            os.replace(src, dest)

    def object_size(self, digest: str) -> int | None:
        try:
            return os.stat(self._object_file(digest)).st_size
        except (FileNotFoundError, NotADirectoryError):
            return None

    def iter_objects(self) -> Iterator[str]:
        base = self.root / "objects"
        for d in sorted(base.iterdir()):
            if d.is_dir() and not d.is_symlink():  # never through a link out of the cache
                for f in sorted(d.iterdir()):
                    yield d.name + f.name

    # ---------------------------------------------------------------- records

    def record_path(self, key: str) -> Path:
        return self.root / "records" / key[:2] / f"{key}.json"

    def put_record(self, key: str, record: dict[str, Any]) -> None:
        """Atomically write the record for ``key`` (write last: it makes outputs visible).

        A record carries ``preimage``, the data its key is the digest of (keys.key_preimage), so
        that any reader can check the record belongs to the key it is filed under."""
        if key_of(record.get("preimage")) != key:
            raise StoreError(f"record for {key[:12]} does not carry its key's preimage")
        path = self.record_path(key)
        self._ensure_dir(path.parent)
        tmp = self._tmp_file()
        with open(tmp, "wb") as f:
            f.write(canonical_json(record))
            if self.fsync_always:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, path)
        if self.fsync_always:
            _fsync_dir(path.parent)

    def read_record(self, key: str) -> dict[str, Any] | None:
        """The record filed under ``key`` if it is well-formed and belongs to ``key`` (its
        preimage hashes to ``key``), whether or not its objects are present; else None."""
        raw = self._read(self.record_path(key))
        if raw is None:
            return None
        try:
            rec = jsonio.loads(raw)
        except ValueError:  # not JSON, or nested deeper than any record
            return None
        return rec if record_problem(key, rec) is None else None

    def get_record(self, key: str) -> dict[str, Any] | None:
        """The record for ``key`` if it belongs to ``key`` and every object it names is present
        with its recorded size (a map stage's record names its items' objects too) — here, or
        with that size in the fallback (``self.fallback``: fetched when read)."""
        rec = self.read_record(key)
        if rec is None:
            return None
        fb = self.fallback
        for digest, size in rec["objects"].items():
            if self.object_size(digest) != size and (fb is None or fb.size(digest) != size):
                return None
        return rec

    def delete_record(self, key: str) -> None:
        self.record_path(key).unlink(missing_ok=True)

    def iter_records(self) -> Iterator[tuple[str, Path]]:
        base = self.root / "records"
        for d in sorted(base.iterdir()):
            if d.is_dir() and not d.is_symlink():  # never through a link out of the cache
                for f in sorted(d.glob("*.json")):
                    yield f.stem, f

    # ---------------------------------------------------------------- locks

    @contextlib.contextmanager
    def lock(self, key: str, blocking: bool = True) -> Iterator[bool]:
        """Exclusive OS lock for ``key``; yields whether it was acquired."""
        path = self.root / "locks" / key[:2] / f"{key}.lock"
        self._ensure_dir(path.parent)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            flags = fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB)
            try:
                fcntl.flock(fd, flags)
            except OSError as exc:
                if exc.errno in (errno.EAGAIN, errno.EACCES):
                    yield False
                    return
                raise
            try:
                yield True
            finally:
                fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)

    @contextlib.contextmanager
    def lease(self) -> Iterator[None]:
        """Held by every run, pull and push for as long as it reads or writes the store: a shared
        OS lock that gc must take exclusively, so gc never deletes what a live run is using. The
        kernel releases it when the holder dies (kill -9 leaves no stale lease)."""
        fd = self._gc_lock_fd()
        try:
            fcntl.flock(fd, fcntl.LOCK_SH)
            yield
        finally:
            os.close(fd)

    def _gc_lock_fd(self) -> int:
        path = self.root / "locks" / "gc.lock"
        return os.open(path, os.O_RDWR | os.O_CREAT, 0o644)

    # ---------------------------------------------------------------- runs and gc

    def add_run(self, run: dict[str, Any]) -> str:
        # nanosecond prefix: runs sort by start order even within one second
        run_id = f"{time.time_ns():020d}-{uuid.uuid4().hex[:8]}"
        path = self.root / "runs" / f"{run_id}.json"
        tmp = self._tmp_file()
        tmp.write_bytes(canonical_json(run))
        os.replace(tmp, path)
        return run_id

    def runs(self) -> list[tuple[str, dict[str, Any]]]:
        """(id, {records: [keys], ...}) of the finished runs, oldest first. A run file that is
        not of this shape is a StoreError naming it (gc must not guess which roots to keep)."""
        return [(p.stem, _roots_file(p, "run list")) for p in sorted((self.root / "runs").glob("*.json"))]

    def _pin_path(self, name: str) -> Path:
        if not isinstance(name, str) or not PIN_NAME.fullmatch(name):
            raise StoreError(f"pin name {name!r}: use letters, digits, '.', '_' and '-' only (not starting "
                             f"with '.'), at most 128")
        return self.root / "pins" / f"{name}.json"

    def pin(self, name: str, run: dict[str, Any]) -> None:
        path = self._pin_path(name)
        tmp = self._tmp_file()
        tmp.write_bytes(canonical_json(run))
        os.replace(tmp, path)

    def unpin(self, name: str) -> None:
        self._pin_path(name).unlink(missing_ok=True)

    def pinned(self) -> list[dict[str, Any]]:
        """The pins' roots; a pin file that is not a pin is a StoreError naming it."""
        return [_roots_file(p, "pin") for p in sorted((self.root / "pins").glob("*.json"))]

    def reachable(self, roots: list[str]) -> set[str]:
        """Objects reachable from ``roots`` (record keys) through records and manifests."""
        live: set[str] = set()
        for key in roots:
            rec = self.get_record(key)
            if rec is None:
                continue
            live.update(rec.get("objects", {}))
            for sub in rec.get("children", []):
                sub_rec = self.get_record(sub)
                if sub_rec is not None:
                    live.update(sub_rec.get("objects", {}))
        return live

    MAX_KEEP = 1_000_000

    def gc(self, keep: int = 5, wait: bool = True, on_wait: Any = None) -> dict[str, int]:
        """Delete objects and records not reachable from the last ``keep`` runs or pins.

        Waits for runs in progress (their leases) unless ``wait`` is False, in which case it
        raises StoreError; ``on_wait()`` is called once if it has to wait."""
        if not isinstance(keep, int) or isinstance(keep, bool) or not 0 <= keep <= self.MAX_KEEP:
            raise ValueError(f"keep must be an integer from 0 to {self.MAX_KEEP}, got {keep!r}")
        fd = self._gc_lock_fd()
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                if exc.errno not in (errno.EAGAIN, errno.EACCES):
                    raise
                if not wait:
                    raise StoreError("a run, pull or push is using the cache; gc did nothing (try again later)") from None
                if on_wait is not None:
                    on_wait()
                fcntl.flock(fd, fcntl.LOCK_EX)
            return self._gc_locked(keep)
        finally:
            os.close(fd)

    def _gc_locked(self, keep: int) -> dict[str, int]:
        runs = self.runs()
        roots_runs = [r for _, r in runs[-keep:]] if keep > 0 else []
        roots_runs += self.pinned()
        root_keys: list[str] = []
        for r in roots_runs:
            root_keys.extend(r.get("records", []))
        live_keys: set[str] = set(root_keys)
        for key in root_keys:
            rec = self.get_record(key)
            if rec is not None:
                live_keys.update(rec.get("children", []))
        live = self.reachable(sorted(live_keys))
        removed_objects = removed_bytes = removed_records = 0
        for key, path in list(self.iter_records()):
            if key not in live_keys:
                path.unlink(missing_ok=True)
                removed_records += 1
        for digest in list(self.iter_objects()):
            if digest not in live:
                p = self.object_path(digest)
                removed_bytes += p.stat().st_size
                p.unlink(missing_ok=True)
                removed_objects += 1
        for p in sorted((self.root / "runs").glob("*.json"))[: max(0, len(runs) - keep)]:
            p.unlink(missing_ok=True)
        removed_tmp = self._clean_tmp()
        return {"objects_removed": removed_objects, "bytes_removed": removed_bytes,
                "records_removed": removed_records, "tmp_removed": removed_tmp,
                "objects_kept": len(live)}

    def _clean_tmp(self, older_than_s: float = 0.0) -> int:
        """Remove temp files of writers that are gone (their pid no longer exists): only files
        named as writers name them (``<pid>-<hex>``), directly in tmp/, never through a link."""
        n = 0
        now = time.time()
        tmp_dir = self.root / "tmp"
        if tmp_dir.is_symlink() or not tmp_dir.is_dir():
            return 0
        for p in tmp_dir.iterdir():
            pid_s, _, rest = p.name.partition("-")
            if not (pid_s.isdigit() and rest):
                continue
            try:
                st = p.lstat()
            except FileNotFoundError:
                continue
            if not (stat.S_ISREG(st.st_mode) or stat.S_ISLNK(st.st_mode)):
                continue
            alive = False
            try:
                os.kill(int(pid_s), 0)
                alive = True
            except (ProcessLookupError, OverflowError, ValueError):
                alive = False
            except PermissionError:
                alive = True
            if not alive and now - st.st_mtime >= older_than_s:
                p.unlink(missing_ok=True)
                n += 1
        return n

    def _load_record_file(self, path: Path) -> Any:
        """A record file's JSON, or None when it is unreadable, not a regular file or not JSON."""
        raw = self._read(path)
        if raw is None:
            return None
        try:
            return jsonio.loads(raw)
        except ValueError:
            return None

    def fsck(self) -> FsckReport:
        """Re-hash every object; quarantine mismatches (and anything in objects/ that is not a
        regular file: a FIFO would block every reader); drop records that are unreadable, not
        records, or lost objects."""
        rep = FsckReport(corrupt=[])
        for digest in list(self.iter_objects()):
            path = self.object_path(digest)
            h = blake3.blake3()
            try:
                fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW)
            except FileNotFoundError:
                continue
            except OSError:  # a symlink (ELOOP) or unreadable: not an object
                self.quarantine(digest)
                rep.corrupt.append(digest)
                continue
            with os.fdopen(fd, "rb") as f:
                if stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                    for block in iter(lambda: f.read(1 << 22), b""):
                        h.update(block)
                        rep.bytes += len(block)
            rep.objects += 1
            if h.hexdigest() != digest:
                self.quarantine(digest)
                rep.corrupt.append(digest)
        recs: dict[str, Any] = {}
        for key, path in list(self.iter_records()):
            rec = self._load_record_file(path)
            if record_problem(key, rec) is not None or any(self.object_size(d) != s for d, s in rec["objects"].items()):
                path.unlink(missing_ok=True)
                rep.records_removed += 1
            else:
                recs[key] = rec
        # a map stage whose items lost their records is incomplete too
        for key, rec in recs.items():
            if any(c not in recs for c in rec.get("children", [])):
                self.record_path(key).unlink(missing_ok=True)
                rep.records_removed += 1
        rep.tmp_removed = self._clean_tmp()
        return rep

    def clear(self) -> None:
        shutil.rmtree(self.root)


class _ObjectWriter:
    def __init__(self, tmp: Path):
        self.tmp = tmp
        self.file = open(tmp, "wb")
        self._h = blake3.blake3()
        self.digest = ""
        self.size = 0

    def write(self, data: bytes | memoryview) -> None:
        self._h.update(data)
        self.file.write(data)
        self.size += len(data)

    def finish(self) -> None:
        self.file.close()
        self.digest = self._h.hexdigest()
