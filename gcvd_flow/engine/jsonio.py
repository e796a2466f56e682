"""Reading JSON the tool did not necessarily write: one loader with a depth limit, and typed
accessors that fail as one-line ``UsageError`` naming the file and the key.

Every file the engine reads back (run.json, records, run lists, pins, remote records) may have
been edited, truncated or written by an attacker. ``json.loads`` alone raises ``RecursionError``
on deep nesting, accepts ``NaN`` and numbers of any size, and any *shape*; the callers then fail
with a ``TypeError`` or ``KeyError`` far from the file. Here:

* ``loads`` parses with a nesting limit (``MAX_DEPTH``) checked without recursion, and turns
  every parse problem (syntax, bad UTF-8, recursion, a 5000-digit integer) into ``ValueError``;
* ``load_file`` reads a file (regular files only: never a FIFO, which would block) and raises
  ``UsageError("<path>: <what> is not valid JSON (...)")``;
* ``field`` / ``mapping`` / ``sequence`` check a value's type and raise
  ``UsageError("<path>: <key> must be <type>")``.

Stdlib only (the no-op fast path imports this module).
"""

from __future__ import annotations

import json
import math
import os
import stat
from pathlib import Path
from typing import Any

from gcvd_flow.engine.errors import UsageError

MAX_DEPTH = 64  # deeper than anything the tool writes (run.json: 6), far below the interpreter's limit
MAX_FILE_BYTES = 256 << 20


def check_depth(doc: Any, max_depth: int = MAX_DEPTH) -> None:
    """ValueError when lists / dicts nest deeper than ``max_depth`` (iterative: no recursion)."""
    stack = [(doc, 1)]
    while stack:
        v, d = stack.pop()
        if isinstance(v, dict):
            if d > max_depth:
                raise ValueError(f"nested deeper than {max_depth} levels")
            stack.extend((x, d + 1) for x in v.values())
        elif isinstance(v, list):
            if d > max_depth:
                raise ValueError(f"nested deeper than {max_depth} levels")
            stack.extend((x, d + 1) for x in v)


def loads(data: str | bytes, max_depth: int = MAX_DEPTH) -> Any:
    """Parse JSON; ValueError for anything that is not a JSON document nested at most
    ``max_depth`` deep (syntax, encoding, recursion, oversized integers)."""
    try:
        doc = json.loads(data)
    except RecursionError:
        raise ValueError(f"nested deeper than {max_depth} levels") from None
    except (ValueError, UnicodeDecodeError, TypeError) as exc:
        raise ValueError(str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from None
    check_depth(doc, max_depth)
    return doc


def read_regular(path: str | Path, limit: int = MAX_FILE_BYTES) -> bytes:
    """The bytes of a regular file (not a FIFO, device or socket: reading those blocks or never
    ends). FileNotFoundError when absent; OSError(EINVAL) for a non-regular file or one larger
    than ``limit``."""
    import errno

    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise OSError(errno.EINVAL, "not a regular file", str(path))
        if st.st_size > limit:
            raise OSError(errno.EFBIG, f"larger than {limit} bytes", str(path))
        with os.fdopen(fd, "rb", closefd=False) as f:
            data = f.read(st.st_size + 1)  # + 1: a file that grew since fstat is found too long
        if len(data) > limit:
            raise OSError(errno.EFBIG, f"larger than {limit} bytes", str(path))
        return data
    finally:
        os.close(fd)


def load_file(path: str | Path, what: str = "file", missing: str | None = None) -> Any:
    """A JSON file as a value; one-line UsageError naming ``path`` for an absent (``missing``
    says what to do), unreadable or invalid file."""
    p = Path(path)
    try:
        raw = read_regular(p)
    except FileNotFoundError:
        raise UsageError(f"{p}: {missing or what + ' not found'}") from None
    except OSError as exc:
        raise UsageError(f"{p}: cannot read {what} ({exc.strerror or exc})") from None
    try:
        return loads(raw)
    except ValueError as exc:
        raise UsageError(f"{p}: {what} is not valid JSON ({exc})") from None


_TYPES = {dict: "an object", list: "a list", str: "a string", int: "an integer", float: "a number",
          bool: "true or false"}


def field(doc: Any, key: str, typ: type | tuple[type, ...], where: str, optional: bool = False) -> Any:
    """``doc[key]`` checked to be of ``typ`` (int excludes bool; float accepts finite ints and
    floats only); None when absent (or null) and ``optional``; UsageError otherwise."""
    v = doc.get(key) if isinstance(doc, dict) else None
    if v is None:
        if optional:
            return None
        raise UsageError(f"{where}: {key} is missing")
    if not is_a(v, typ):
        types = typ if isinstance(typ, tuple) else (typ,)
        raise UsageError(f"{where}: {key} must be {' or '.join(_TYPES.get(t, t.__name__) for t in types)}, "
                         f"not {_short(v)}")
    return v


def is_a(v: Any, typ: type | tuple[type, ...]) -> bool:
    types = typ if isinstance(typ, tuple) else (typ,)
    for t in types:
        if t is int and isinstance(v, int) and not isinstance(v, bool):
            return True
        if t is float and isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
            return True
        if t not in (int, float) and isinstance(v, t):
            return True
    return False


def _short(v: Any) -> str:
    text = json.dumps(v, default=str) if not isinstance(v, float) else repr(v)
    return text if len(text) <= 40 else text[:37] + "..."
