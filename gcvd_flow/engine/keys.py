"""Cache keys: canonical typed encoding, BLAKE3 digests and code fingerprints.

A key is ``BLAKE3(canonical_encoding([record_kind, stage_name, code_fingerprint, params,
input_digests, env]))`` (docs/design.md, "Cache keys"). Keys must be equal on every machine that
has the same
code, parameters, inputs and numeric environment, so nothing here may depend on absolute
paths, host names, user names or times.
"""

from __future__ import annotations

import ast
import functools
import importlib.metadata
import importlib.util
import inspect
import json
import math
import re
import struct
import sys
import textwrap
import types
from pathlib import Path
from typing import Any, Callable, Iterable

import blake3
import numpy as np

DIGEST_HEX_LEN = 64

# Which modules' source is part of a fingerprint is the pipeline's to say
# (``Pipeline.packages``, e.g. ("stages", "gcvd_flow.pipeline")); third-party packages are
# represented by their versions in `env` instead.
Packages = tuple[str, ...]


class EncodingError(TypeError):
    """A value cannot be encoded canonically (it would make keys ambiguous)."""


# --------------------------------------------------------------------------------------------
# digests


# Below this size BLAKE3's thread pool costs more (spinning, futexes) than it saves.
_MT_THRESHOLD = 8 << 20


def digest_bytes(data: bytes | memoryview) -> str:
    """Hex BLAKE3 digest of a byte string."""
    if len(data) >= _MT_THRESHOLD:
        return blake3.blake3(data, max_threads=blake3.blake3.AUTO).hexdigest()
    return blake3.blake3(data).hexdigest()


def digest_file(path: str | Path, chunk: int = 1 << 22) -> str:
    """Hex BLAKE3 digest of a file's bytes, streamed in 4 MiB chunks."""
    h = blake3.blake3()
    with open(path, "rb") as f:
        while True:
            block = f.read(chunk)
            if not block:
                break
            h.update(block)
    return h.hexdigest()


_HEX_DIGEST = re.compile(r"[0-9a-f]{64}")


def is_digest(s: Any) -> bool:
    return isinstance(s, str) and len(s) == DIGEST_HEX_LEN and _HEX_DIGEST.fullmatch(s) is not None


# --------------------------------------------------------------------------------------------
# canonical encoding


def _len_prefixed(tag: bytes, payload: bytes) -> bytes:
    return tag + str(len(payload)).encode() + b":" + payload


def canonical_encode(obj: Any) -> bytes:
    """Injective, type-tagged byte encoding.

    ``1``, ``1.0``, ``"1"`` and ``True`` encode differently; dict key order does not matter;
    floats are encoded by exact value (``float.hex``) so that no rounding merges two keys.
    """
    # bool before int: bool is a subclass of int.
    if obj is None:
        return b"N"
    if obj is True:
        return b"T"
    if obj is False:
        return b"F"
    if isinstance(obj, np.generic):
        return canonical_encode(obj.item())
    if isinstance(obj, int):
        return _len_prefixed(b"i", str(obj).encode())
    if isinstance(obj, float):
        if math.isnan(obj):
            return b"fnan"
        return _len_prefixed(b"f", obj.hex().encode())
    if isinstance(obj, str):
        return _len_prefixed(b"s", obj.encode("utf-8"))
    if isinstance(obj, (bytes, bytearray, memoryview)):
        return _len_prefixed(b"b", bytes(obj))
    if isinstance(obj, (list, tuple)):
        body = b"".join(canonical_encode(x) for x in obj)
        return b"l" + str(len(obj)).encode() + b":" + body
    if isinstance(obj, dict):
        pairs = sorted((canonical_encode(k), canonical_encode(v)) for k, v in obj.items())
        body = b"".join(k + v for k, v in pairs)
        return b"d" + str(len(pairs)).encode() + b":" + body
    if isinstance(obj, np.ndarray):
        a = np.ascontiguousarray(obj)
        header = canonical_encode([a.dtype.str, list(a.shape)])
        return _len_prefixed(b"a", header + digest_bytes(a.tobytes()).encode())
    if hasattr(obj, "model_dump"):  # pydantic models: their fields, as a dict
        return canonical_encode(obj.model_dump(mode="python"))
    raise EncodingError(f"cannot encode a value of type {type(obj).__name__} canonically")


def key_of(obj: Any) -> str:
    """Digest of the canonical encoding of ``obj``."""
    return digest_bytes(canonical_encode(obj))


# --------------------------------------------------------------------------------------------
# code fingerprints


_DOCUMENTED = (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)

# How many times this process parsed source text (tests check that a module is parsed once).
PARSES = {"count": 0}


def _parse(source: str) -> ast.AST:
    PARSES["count"] += 1
    return ast.parse(source)


def _strip_docstrings(tree: ast.AST) -> ast.AST:
    """Removes docstrings (the first statement of a module, function or class body when it is a
    string constant; an emptied body becomes ``pass``) so that documentation edits do not
    invalidate caches."""
    for node in _statements(tree):
        if isinstance(node, _DOCUMENTED):
            body = node.body
            if (body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
                    and isinstance(body[0].value.value, str)):
                node.body = body[1:] or [ast.Pass()]
    return tree


_BODY_NODES = (ast.stmt, ast.excepthandler, ast.match_case)


def _statements(tree: ast.AST) -> Iterable[ast.AST]:
    """``tree`` and every statement in it (through bodies, else-branches, handlers and match
    cases), without descending into expressions: what ``ast.walk`` yields of the nodes that can
    hold a docstring or an import, at a tenth of its visits (a function or class inside an
    expression is a lambda: no docstring, no import)."""
    todo = [tree]
    while todo:
        node = todo.pop()
        yield node
        for field in node._fields:
            value = getattr(node, field, None)
            if isinstance(value, list):
                todo.extend(v for v in reversed(value) if isinstance(v, _BODY_NODES))


def _tree_digest(tree: ast.AST) -> str:
    """Digest of a parsed tree without docstrings, comments or layout (changes ``tree``)."""
    return digest_bytes(ast.dump(_strip_docstrings(tree), annotate_fields=True, include_attributes=False).encode())


def normalized_ast_digest(source: str) -> str:
    """Digest of a source text's AST without docstrings, comments or layout."""
    return _tree_digest(_parse(source))


def _is_project_module(name: str, packages: Packages) -> bool:
    return any(name == p or name.startswith(p + ".") for p in packages)


@functools.lru_cache(maxsize=None)
def _package_dirs(top: str) -> tuple[str, ...]:
    """The directories of top-level package ``top`` (its spec's search locations; () when it is
    not a package)."""
    try:
        spec = importlib.util.find_spec(top)
    except (ImportError, ValueError):
        return ()
    return tuple(spec.submodule_search_locations or ()) if spec is not None else ()


@functools.lru_cache(maxsize=None)
def _module_file(name: str) -> Path | None:
    """The .py file of module ``name`` (a package's ``__init__.py``), found on the file system
    from its top-level package as the import system would, or None. Why not
    ``importlib.util.find_spec``: for ``a.b.c`` it imports ``a.b``, so fingerprinting a stage
    imported every module its closure names (torch and its models for a cached stage whose code
    never runs; 3.7 s of a tiny run's 14.7)."""
    top, *rest = name.split(".")
    for base in _package_dirs(top):
        d = Path(base).joinpath(*rest[:-1])
        if not rest:
            f = d / "__init__.py"
        elif (d / rest[-1] / "__init__.py").is_file():
            f = d / rest[-1] / "__init__.py"
        else:
            f = d / f"{rest[-1]}.py"
        if f.is_file() and all((Path(base).joinpath(*rest[:i]) / "__init__.py").is_file() for i in range(1, len(rest))):
            return f
    return None


def _module_source(name: str) -> tuple[str, str] | None:
    """(source text, path relative to the project root) of a project module, or None."""
    origin = _module_file(name)
    if origin is None:
        return None
    rel_parts = name.split(".")
    rel = "/".join(rel_parts) + ("/__init__.py" if origin.name == "__init__.py" else ".py")
    return origin.read_text(encoding="utf-8"), rel


def _project_imports(tree: ast.AST, package: str, packages: Packages) -> set[str]:
    """Project modules named by the import statements anywhere in ``tree`` (relative imports
    resolved against ``package``; ``from stages import flow`` also names ``stages.flow``)."""
    found: set[str] = set()
    for node in _statements(tree):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if _is_project_module(a.name, packages))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - (node.level - 1)] if node.level > 1 else parts)
                mod = f"{base}.{node.module}" if node.module else base
            else:
                mod = node.module or ""
            if not _is_project_module(mod, packages):
                continue
            found.add(mod)
            for alias in node.names:
                sub = f"{mod}.{alias.name}"
                if _module_file(sub) is not None:
                    found.add(sub)
    return found


def _imported_project_modules(name: str, tree: ast.AST, packages: Packages) -> set[str]:
    """Project modules that module ``name`` (parsed: ``tree``) imports (absolute and relative
    imports)."""
    origin = _module_file(name)
    is_pkg = origin is not None and origin.name == "__init__.py"
    package = name if is_pkg else name.rpartition(".")[0]
    found = _project_imports(tree, package, packages)
    # a module also depends on its parent packages' __init__ (executed on import)
    parts = name.split(".")
    for i in range(1, len(parts)):
        if _is_project_module(".".join(parts[:i]), packages):
            found.add(".".join(parts[:i]))
    found.discard(name)
    return found


@functools.lru_cache(maxsize=None)
def _module_info(name: str, packages: Packages
                 ) -> tuple[str, str, frozenset[str], dict[str, tuple[str, str]]] | None:
    """(AST digest, relative path, project modules it imports, its top-level data bindings): name ->
    ("assign", digest of the assigning statement) or ("import", the project module it comes from)."""
    src = _module_source(name)
    if src is None:
        return None
    text, rel = src
    tree = _parse(text)  # once: its imports and bindings first, then its digest (which strips its docstrings)
    deps = frozenset(_imported_project_modules(name, tree, packages))
    package = name if rel.endswith("__init__.py") else name.rpartition(".")[0]
    bindings: dict[str, tuple[str, str]] = {}
    for node in getattr(tree, "body", []):
        if isinstance(node, (ast.Assign, ast.AnnAssign, ast.AugAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names = [n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)]
            dig = digest_bytes(ast.dump(node, annotate_fields=True, include_attributes=False).encode())
            for n in names:  # a name assigned twice: both statements count
                prev = bindings.get(n)
                bindings[n] = ("assign", dig if prev is None or prev[0] != "assign" else key_of([prev[1], dig]))
        elif isinstance(node, ast.ImportFrom):
            mod = (_project_imports(ast.Module(body=[node], type_ignores=[]), package, packages) or {""})
            src_mod = min(mod, key=len)  # the module named by the statement (not its submodules)
            for a in node.names:
                if src_mod:
                    bindings[a.asname or a.name] = ("import", src_mod)
    return _tree_digest(tree), rel, deps, bindings


def module_closure(roots: Iterable[str], packages: Packages) -> dict[str, str]:
    """Project modules reachable from ``roots`` by imports: {relative path: AST digest}."""
    out: dict[str, str] = {}
    seen: set[str] = set()
    todo = list(roots)
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        info = _module_info(name, packages)
        if info is None:
            continue
        digest, rel, deps, _ = info
        out[rel] = digest
        todo.extend(sorted(deps))
    return out


def _code_names(fn: Callable) -> set[str]:
    """Global names a function's code (including nested functions) refers to."""
    names: set[str] = set()
    stack = [fn.__code__]
    while stack:
        c = stack.pop()
        names.update(c.co_names)
        stack.extend(k for k in c.co_consts if isinstance(k, types.CodeType))
    return names


def _object_module(obj: Any) -> str | None:
    if isinstance(obj, types.ModuleType):
        return obj.__name__
    mod = getattr(obj, "__module__", None)
    return mod if isinstance(mod, str) else None


def _object_code(obj: Any, own_module: str, packages: Packages) -> tuple[str | None, set[str]]:
    """(AST digest of a function's or class's source, or None when it is not available; the
    project modules imported *inside* its body, ``from stages import x``), from one parse."""
    try:
        tree = _parse(textwrap.dedent(inspect.getsource(obj)))
    except (OSError, TypeError, SyntaxError):
        return None, set()
    imports = _project_imports(tree, own_module.rpartition(".")[0], packages)
    return _tree_digest(tree), imports


def code_fingerprint(fn: Callable, packages: Packages,
                     adapters: Packages = ()) -> tuple[str, tuple[tuple[str, str], ...]]:
    """Fingerprint of a stage function: its own AST plus the code it uses from ``packages``
    (module names or prefixes, e.g. ``("stages", "gcvd_flow.pipeline")``).

    Returns (digest, ((name, AST digest), ...)); the per-file digests let `why` name what
    changed. Helpers in the function's own module, and in the modules ``adapters`` names (module
    names or prefixes: a pipeline's adapters split over several modules), are followed function by
    function (so an unrelated edit in those modules does not invalidate it); other project modules
    it uses are included whole, with everything they import inside the project, transitively.
    """
    return _code_fingerprint_cached(fn, tuple(packages), tuple(adapters))


def _is_engine_object(obj: Any) -> bool:
    """A declaration of the engine's own (a stage, a reference): which stage it names is the
    inputs' part of a key, not code."""
    return type(obj).__module__.startswith(__name__.rpartition(".")[0] + ".")


@functools.lru_cache(maxsize=None)
def _code_fingerprint_cached(fn: Callable, packages: Packages,
                             adapters: Packages) -> tuple[str, tuple[tuple[str, str], ...]]:
    own_module = fn.__module__
    files: dict[str, str] = {}
    modules: set[str] = set()
    todo: list[Any] = [fn]
    seen: set[int] = set()
    while todo:
        obj = todo.pop()
        if id(obj) in seen:
            continue
        seen.add(id(obj))
        obj_module = _object_module(obj) or own_module
        digest, local_imports = _object_code(obj, obj_module, packages)
        if digest is None:
            raise EncodingError(f"cannot fingerprint {obj!r}: its source is not available")
        files[f"{obj_module}:{obj.__qualname__}"] = digest
        modules.update(local_imports)
        code_objs = [obj] if inspect.isfunction(obj) else [
            m for m in vars(obj).values() if inspect.isfunction(m)
        ]
        g = getattr(obj, "__globals__", None) or vars(sys.modules[obj_module])
        for f in code_objs:
            for name in _code_names(f):
                ref = g.get(name)
                mod = _object_module(ref)
                data = name in g and not (isinstance(ref, types.ModuleType) or inspect.isfunction(ref)
                                          or inspect.isclass(ref) or _is_engine_object(ref))
                if data and (obj_module == own_module or _is_project_module(obj_module, adapters)):
                    # a data global (a constant, a table, a settings instance) of a module followed
                    # function by function: its assignment, or the module it was imported from
                    info = _module_info(obj_module, packages)
                    how = None if info is None else info[3].get(name)
                    if how is not None and how[0] == "assign":
                        files[f"{obj_module}:{name}"] = how[1]
                    elif how is not None and _is_project_module(how[1], packages):
                        modules.add(how[1])
                    if mod is None:
                        continue
                if mod is None or not _is_project_module(mod, packages):
                    continue
                if (mod == own_module or _is_project_module(mod, adapters)) and not isinstance(ref, types.ModuleType):
                    if inspect.isfunction(ref) or inspect.isclass(ref):
                        todo.append(ref)
                else:
                    modules.add(mod)
    files.update(module_closure(sorted(modules), packages))
    items = tuple(sorted(files.items()))
    return key_of([list(x) for x in items]), items


def selection_fingerprint(fn: Callable, packages: Packages,
                          adapters: Packages = ()) -> tuple[str, tuple[tuple[str, str], ...]]:
    """code_fingerprint of a map stage's items or summary function. One whose source cannot be
    parsed on its own (a lambda inside a longer expression) is fingerprinted by its compiled code
    instead: its bytecode, constants and names (what it calls is then not followed)."""
    try:
        return code_fingerprint(fn, packages, adapters)
    except EncodingError:
        code = getattr(fn, "__code__", None)
        if code is None:
            raise
        return key_of(_code_identity(code)), ((f"{fn.__module__}:{fn.__qualname__}", key_of(_code_identity(code))),)


def _code_identity(code: types.CodeType) -> list[Any]:
    """Bytecode, constants and names of a code object, the same in every process (a frozenset
    constant, `x in {"a", "b"}`, listed sorted: its repr follows the string hash seed)."""
    def const(c: Any) -> Any:
        if isinstance(c, types.CodeType):
            return _code_identity(c)
        return sorted(map(repr, c)) if isinstance(c, frozenset) else repr(c)

    return [code.co_code.hex(), [const(c) for c in code.co_consts], list(code.co_names)]


def clear_caches() -> None:
    """Forget memoised fingerprints (tests edit source files within one process)."""
    _module_info.cache_clear()
    _code_fingerprint_cached.cache_clear()
    _module_file.cache_clear()
    _package_dirs.cache_clear()
    importlib.invalidate_caches()


# --------------------------------------------------------------------------------------------
# numeric environment


def _version(dist: str) -> str | None:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


# The engine's own codecs of stored values, (label, (distribution, alternatives...)) like
# ``Pipeline.numeric_libraries``: numpy (arrays, .npy), Pillow (PNG images) and safetensors
# (tensor dicts, checkpoints) write the bytes whose digests are outputs, so their versions enter
# every key whatever the pipeline.
ENGINE_LIBRARIES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("numpy", ("numpy",)), ("pillow", ("pillow",)), ("safetensors", ("safetensors",)))


def numeric_env(libraries: tuple[tuple[str, tuple[str, ...]], ...] = (),
                settings: tuple[tuple[str, Any], ...] = ()) -> dict[str, Any]:
    """What changes numerics, and nothing personal: the interpreter, the engine's own codecs
    (``ENGINE_LIBRARIES``), the versions of the pipeline's numeric ``libraries`` ((label,
    (distribution, alternatives...)), ...) and its ``settings`` (e.g. device, dtype, determinism)."""
    return dict(_numeric_env(tuple(libraries), tuple(settings)))


@functools.lru_cache(maxsize=None)
def _numeric_env(libraries: tuple[tuple[str, tuple[str, ...]], ...],
                 settings: tuple[tuple[str, Any], ...]) -> tuple[tuple[str, Any], ...]:
    env: dict[str, Any] = {
        "python": f"{sys.version_info.major}.{sys.version_info.minor}",
        "byteorder": sys.byteorder,
        "float_size": struct.calcsize("d"),
    }
    for label, dists in ENGINE_LIBRARIES + libraries:
        env[label] = next((v for v in map(_version, dists) if v), None)
    env.update(dict(settings))
    return tuple(sorted(env.items()))


def key_preimage(record_kind: str, stage_name: str, code_fp: str, params: Any,
                 input_digests: Any, env: dict[str, Any]) -> list[Any]:
    """What a key is the digest of (docs/design.md, "Cache keys"), as JSON-able data: records
    carry it, so that whoever reads a record can re-derive its key (a record filed under
    another key — a swapped or misplaced record — is detected, never used)."""
    return json.loads(json.dumps([record_kind, stage_name, code_fp, params, input_digests, env],
                                 allow_nan=False, default=_no_json))


def _no_json(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    raise EncodingError(f"cannot put a value of type {type(obj).__name__} in a key")


def stage_key(record_kind: str, stage_name: str, code_fp: str, params: Any,
              input_digests: Any, env: dict[str, Any]) -> str:
    """The cache key recipe (docs/design.md, "Cache keys")."""
    return key_of(key_preimage(record_kind, stage_name, code_fp, params, input_digests, env))
