"""Reading JSON the tool did not necessarily write: one loader with a depth limit, and typed
accessors that fail as one-line ``UsageError`` naming the file and the key.

Every file the engine reads back (run.json, records, run lists, pins, remote records) may have
been edited, truncated or written by an attacker. ``json.loads`` alone raises ``RecursionError``
on deep nesting, accepts ``NaN`` and numbers of any size, and any *shape*; the callers then fail
with a ``TypeError`` or ``KeyError`` far from the file. Here:

* ``loads`` parses with a nesting limit (``MAX_DEPTH``) checked without recursion, and turns
  every parse problem (syntax, bad UTF-8, recursion) into ``ValueError``; so are numbers no
  float can hold (an integer of more than ``MAX_INT_DIGITS`` digits such as ``10**400`` or a
  5000-digit one, a literal such as ``1e999`` that overflows to infinity): every number read
  converts to a float. ``NaN`` / ``Infinity``, which Python's own ``json.dumps`` writes (a
  metric of an empty set), stay accepted: readers must handle non-finite floats anyway;
* ``read_regular`` reads the bytes of a regular file only (never a FIFO, which would block, nor
  a device such as ``/dev/zero``, which never ends; a symlink counts as what it points to) up
  to a size limit;
* ``load_file`` reads a file that way and raises
  ``UsageError("<path>: <what> is not valid JSON (...)")``; ``load_optional`` is the same but
  None for an absent file;
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
# run.json, metrics.json, sweep.json of a run folder (any user may hand one over): the largest the
# tool writes is run.json's file digests, ~100 bytes per output file
RUN_FILE_BYTES = 32 << 20
MAX_INT_DIGITS = 300  # |n| < 10**300: converts to a float (1.8e308) without OverflowError


def _parse_int(text: str) -> int:
    digits = len(text) - text.startswith("-")
    if digits > MAX_INT_DIGITS:
        raise ValueError(f"an integer of {digits} digits (at most {MAX_INT_DIGITS})")
    return int(text)


def _parse_float(text: str) -> float:
    v = float(text)
    if v in (float("inf"), float("-inf")):  # 1e999: a literal that overflows (Infinity is a constant)
        raise ValueError(f"number {text[:20]}{'...' if len(text) > 20 else ''} is out of range")
    return v


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
        doc = json.loads(data, parse_int=_parse_int, parse_float=_parse_float)
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


def load_file(path: str | Path, what: str = "file", missing: str | None = None,
              limit: int = MAX_FILE_BYTES) -> Any:
    """A JSON file as a value; one-line UsageError naming ``path`` for an absent (``missing``
    says what to do), unreadable (not a regular file, larger than ``limit``) or invalid file."""
    doc = _load(Path(path), what, limit)
    if doc is _ABSENT:
        raise UsageError(f"{path}: {missing or what + ' not found'}")
    return doc


def load_optional(path: str | Path, what: str = "file", limit: int = RUN_FILE_BYTES) -> Any:
    """``load_file`` for a file that may be absent: None then (also for a dangling symlink)."""
    doc = _load(Path(path), what, limit)
    return None if doc is _ABSENT else doc


_ABSENT = object()


def _load(p: Path, what: str, limit: int) -> Any:
    try:
        raw = read_regular(p, limit)
    except FileNotFoundError:
        return _ABSENT
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
