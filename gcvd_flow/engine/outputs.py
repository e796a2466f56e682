"""RUN_DIR's own files: their digests in run.json, checking them, and one writer at a time.

A run records in run.json (``files``) the BLAKE3 digest of every file its export wrote
(relative path -> digest). ``check_files`` re-hashes them: `compare --check` calls two run
dirs identical only when both match what their run.json says, and the no-op fast path stamps a
run dir only after its files were checked against its run.json (a run dir mixed by two writers,
or edited by hand, is never taken as up to date).

``run_dir_lock`` is an OS lock on ``RUN_DIR/.gcvd-lock`` held while a run writes RUN_DIR (export,
run.json, the fast-path stamp): a second run into the same RUN_DIR exits 2 with one line instead
of interleaving its files with the first one's. The kernel releases it when the holder dies.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import stat
import threading
from pathlib import Path
from typing import Any, Iterable, Iterator

from gcvd_flow.engine import jsonio
from gcvd_flow.engine.errors import UsageError
from gcvd_flow.engine.names import TOOL

LOCK = ".gcvd-lock"
# files in RUN_DIR that are not outputs: the engine's own bookkeeping, and what later commands
# (eval, report, export) add to a finished run
NOT_OUTPUTS = ("run.json", "run.json.tmp", ".gcvd-stamp.json", ".gcvd-stamp.json.tmp", LOCK)

def is_digest(s: Any) -> bool:
    """keys.is_digest without importing keys (numpy): this module serves the no-op fast path."""
    return isinstance(s, str) and len(s) == 64 and all(c in "0123456789abcdef" for c in s)


_held: dict[str, tuple[int, int, bool]] = {}  # abspath -> (fd, depth, created): reentrant within a process
_held_lock = threading.Lock()


def check_out_dir(out: str | Path) -> Path:
    """RUN_DIR must be (or be creatable as) a writable directory: checked before any work."""
    p = Path(out)
    if p.exists() and not p.is_dir():
        raise UsageError(f"{p}: exists and is not a directory (--out needs a directory)")
    anc = p
    while not anc.exists():
        if anc.is_symlink():  # a dangling link: mkdir would say "File exists"
            raise UsageError(f"{anc}: a symbolic link to {os.readlink(anc)}, which does not exist, so {p} "
                             "cannot be created")
        anc = anc.parent
    if not anc.is_dir():
        raise UsageError(f"{anc}: is not a directory, so {p} cannot be created")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise UsageError(f"{anc}: not writable, so {p} cannot be {'written' if anc == p else 'created'}")
    return p


@contextlib.contextmanager
def run_dir_lock(out: str | Path, busy: str | None = None) -> Iterator[None]:
    """Hold RUN_DIR's writer lock (creating RUN_DIR); UsageError at once when another process
    holds it (``busy``: what to say after the path). Reentrant in one process (the CLI holds it
    around api.run, which takes it too). A sweep folder is locked the same way."""
    key = os.path.abspath(out)
    with _held_lock:
        if key in _held:
            fd, depth, created = _held[key]
            _held[key] = (fd, depth + 1, created)
        else:
            created = not os.path.exists(key)
            Path(key).mkdir(parents=True, exist_ok=True)
            fd = os.open(os.path.join(key, LOCK), os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                os.close(fd)
                _remove_if_empty(key, created)
                if exc.errno in (errno.EAGAIN, errno.EACCES):
                    raise UsageError(f"{out}: " + (busy or "another run is writing this run directory; wait "
                                                   "for it to finish or use another --out")) from None
                raise
            _held[key] = (fd, 1, created)
    try:
        yield
    finally:
        with _held_lock:
            fd, depth, created = _held[key]
            if depth > 1:
                _held[key] = (fd, depth - 1, created)
            else:
                del _held[key]
                _remove_if_empty(key, created)
                os.close(fd)  # releases the flock


def _remove_if_empty(d: str, created: bool) -> None:
    """A RUN_DIR this lock created and nothing wrote into (the run failed early) is removed."""
    if not created:
        return
    try:
        if os.listdir(d) == [LOCK]:
            os.unlink(os.path.join(d, LOCK))
            os.rmdir(d)
    except OSError:
        pass


def _regular_files(root: Path, paths: Iterable[str | Path]) -> list[Path]:
    """The regular files among ``paths`` and, for folders, under them (symlinks not followed)."""
    out: list[Path] = []
    for p in paths:
        p = Path(p)
        try:
            st = p.lstat()
        except OSError:
            continue
        if stat.S_ISREG(st.st_mode):
            out.append(p)
        elif stat.S_ISDIR(st.st_mode):
            for dirpath, dirnames, filenames in os.walk(p):  # os.walk follows no symlinked folders
                dirnames.sort()
                for f in sorted(filenames):
                    q = Path(dirpath) / f
                    if stat.S_ISREG(q.lstat().st_mode):
                        out.append(q)
    return sorted({q for q in out if q.name not in NOT_OUTPUTS})


def digest_outputs(out: str | Path, paths: Iterable[str | Path]) -> dict[str, str]:
    """Relative path (posix) -> BLAKE3 of every regular file among / under ``paths`` (what the
    export returned), for run.json's ``files``."""
    from gcvd_flow.engine.keys import digest_file

    root = Path(out)
    res = {}
    for f in _regular_files(root, paths):
        try:
            rel = f.resolve().relative_to(root.resolve()).as_posix()
        except ValueError:
            continue  # an export that wrote outside RUN_DIR: not RUN_DIR's file
        res[rel] = digest_file(f)
    return dict(sorted(res.items()))


def check_files(out: str | Path, files: dict[str, str] | None) -> list[str]:
    """What differs between RUN_DIR's files and the digests its run.json records (``files``):
    one line per missing, unreadable or changed file; one line when nothing is recorded (a run
    dir from before file digests existed: it cannot be checked)."""
    from gcvd_flow.engine.keys import digest_file

    if files is None:
        return ["run.json records no file digests (written by an older version; run again)"]
    root = Path(out)
    problems = []
    for rel, want in sorted(files.items()):
        p = root / rel
        if ".." in Path(rel).parts or Path(rel).is_absolute():
            problems.append(f"{rel}: not a path inside the run directory")
            continue
        try:
            if not stat.S_ISREG(p.lstat().st_mode):
                problems.append(f"{rel}: not a regular file")
                continue
            got = digest_file(p)
        except FileNotFoundError:
            problems.append(f"{rel}: missing")
            continue
        except OSError as exc:
            problems.append(f"{rel}: unreadable ({exc.strerror or exc})")
            continue
        if got != want:
            problems.append(f"{rel}: differs from what run.json records")
    return problems


def outputs_of(result: dict[str, Any]) -> list[str]:
    """The paths an export returned (``result["outputs"]``: name -> path)."""
    return [v for v in (result.get("outputs") or {}).values() if isinstance(v, str)]


# ------------------------------------------------------------------------------ run.json


def read_run_dir(out: str | Path) -> dict[str, Any]:
    """RUN_DIR/run.json, checked for the shape the engine writes (``check_run_doc``); every
    problem is a one-line UsageError naming the file and the key."""
    p = Path(out) / "run.json"
    doc = jsonio.load_file(p, "run record", missing=f"no run recorded in this directory (run `{TOOL} run` first)",
                           limit=jsonio.RUN_FILE_BYTES)
    return check_run_doc(doc, str(p))


_STAGE_FIELD_MAPS = ("params", "code_files", "inputs", "libraries", "env")


def check_run_doc(doc: Any, where: str) -> dict[str, Any]:
    """``doc`` if it has run.json's shape: an object whose ``stages`` maps names to
    {key, output: digest or null, fields: object}, ``stage_order`` a list of its stage names,
    ``invocation`` / ``config`` objects, ``cache`` a string and ``files`` path -> digest (all
    optional but ``stages``). Raises UsageError("<where>: <key> ...") otherwise."""
    if not isinstance(doc, dict):
        raise UsageError(f"{where}: not a run record (a JSON object expected)")
    stages = jsonio.field(doc, "stages", dict, where)
    for name, st in stages.items():
        if not isinstance(st, dict):
            raise UsageError(f"{where}: stages.{name} must be an object")
        for k in ("key", "output"):
            if st.get(k) is not None and not is_digest(st[k]):
                raise UsageError(f"{where}: stages.{name}.{k} must be a digest or null")
        fields = jsonio.field(st, "fields", dict, f"{where}: stages.{name}", optional=True)
        for k in _STAGE_FIELD_MAPS:
            jsonio.field(fields or {}, k, dict, f"{where}: stages.{name}.fields", optional=True)
    order = jsonio.field(doc, "stage_order", list, where, optional=True)
    if order is not None and not all(isinstance(s, str) for s in order):
        raise UsageError(f"{where}: stage_order must be a list of stage names")
    for k in ("invocation", "config", "env"):
        jsonio.field(doc, k, dict, where, optional=True)
    inv = doc.get("invocation") or {}
    for k in ("input", "config_file", "profile", "pipeline"):
        jsonio.field(inv, k, str, f"{where}: invocation", optional=True)
    sets = jsonio.field(inv, "sets", list, f"{where}: invocation", optional=True)
    if sets is not None and not all(isinstance(s, str) for s in sets):
        raise UsageError(f"{where}: invocation.sets must be a list of strings")
    jsonio.field(doc, "cache", str, where, optional=True)
    files = jsonio.field(doc, "files", dict, where, optional=True)
    if files is not None and not all(isinstance(k, str) and is_digest(v) for k, v in files.items()):
        raise UsageError(f"{where}: files must map paths to digests")
    return doc
