"""Codecs: how a stage's return value becomes content-addressed objects, and back.

A stage returns a tree of dicts / lists / JSON scalars whose leaves may be numpy arrays. The
tree is stored as a canonical-JSON *manifest* in which every array is replaced by a
descriptor pointing at its own object:

    {"$npy": digest, "dtype": "<f4", "shape": [H, W]}      numpy .npy, loaded allow_pickle=False
    {"$png": digest, "dtype": "|u1", "shape": [H, W, 3]}   lossless PNG (uint8 images and masks)
    {"$safetensors": digest}                               a dict of arrays (wrap in Tensors)

The manifest's digest is the artifact's digest, so equal content gives equal digests (early
cutoff), and a teammate's artifact can only ever be decoded into arrays and JSON: nothing in
it can execute code.
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from gcvd_flow.engine.store import Store, canonical_json

# The engine's own schemas: map stages' manifests (``map.json``), checkpoints
# (``checkpoint.json``) and the shared definitions every schema may $ref (``common.json``:
# digest, array, png, safetensors, ...). Validated whatever the pipeline registers.
ENGINE_SCHEMA_DIR = Path(__file__).resolve().parent / "schemas"
ENGINE_KINDS = ("map", "checkpoint")

# Folders of ``<kind>.json`` schemas, registered by the pipelines that define the kinds
# (``PipelineSpec.schema_dir``); the first folder holding a kind's schema wins.
_SCHEMA_DIRS: list[Path] = []


def register_schema_dir(path: str | Path) -> None:
    """Validate artifacts of the kinds described in ``path`` (one ``<kind>.json`` each; they may
    $ref the engine's ``https://gcvd-flow/schemas/common.json``)."""
    p = Path(path).resolve()
    if p not in _SCHEMA_DIRS:
        _SCHEMA_DIRS.append(p)
        _validator.cache_clear()


class ArtifactError(ValueError):
    """A value cannot be stored, or a stored manifest does not match its schema."""


@dataclass(frozen=True)
class Png:
    """Marks a uint8 (H, W) or (H, W, 3) RGB array to be stored as PNG instead of .npy."""

    array: np.ndarray


@dataclass(frozen=True)
class Tensors:
    """Marks a flat dict of arrays to be stored as one safetensors object."""

    arrays: dict[str, np.ndarray]


@dataclass(frozen=True)
class Stored:
    """A part of a value already written to the store while the stage ran (``ctx.put``): its
    manifest node and the objects (digest -> size) it points at. A stage that produces more than
    fits in memory (one depth map per frame of a long clip) stores each part as soon as it is
    final and returns these handles; the encoder writes only the node into the manifest."""

    node: Any
    objects: dict[str, int]


# -------------------------------------------------------------------------------- encoding


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.ascontiguousarray(a), allow_pickle=False)
    return buf.getvalue()


def png_bytes(a: np.ndarray) -> bytes:
    """Lossless PNG of a uint8 (H, W) grey or (H, W, 3) RGB array (zlib level 3: as small as
    level 9 on video frames at a third of the time)."""
    from PIL import Image  # lazy: only image artifacts need it

    if a.dtype != np.uint8 or a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] != 3):
        raise ArtifactError(f"PNG codec needs uint8 (H,W[,3]) arrays, got {a.dtype} {a.shape}")
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(a)).save(buf, format="PNG", compress_level=3)
    return buf.getvalue()


def png_array(data: bytes, where: str = "PNG") -> np.ndarray:
    """Decode PNG bytes into uint8 (H, W) or (H, W, 3) RGB (RGBA / palette / 16-bit refused)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data), formats=["PNG"]) as img:
            if img.mode not in ("L", "RGB"):
                raise ArtifactError(f"{where}: PNG mode {img.mode} is not one this store writes")
            return np.asarray(img).copy()
    except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError) as exc:
        raise ArtifactError(f"{where} is not a readable PNG ({exc})") from None


def _safetensors_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    from safetensors.numpy import save

    return save({k: np.ascontiguousarray(v) for k, v in sorted(arrays.items())})


def _png_friendly(a: np.ndarray) -> bool:
    """uint8 images and masks are stored as (lossless) PNG: 3-20x smaller than .npy."""
    return (a.dtype == np.uint8 and min(a.shape[:2], default=0) >= 8
            and (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)))


class Encoder:
    """Writes the objects of one value into a store, remembering their sizes for the record."""

    def __init__(self, store: Store):
        self.store = store
        self.objects: dict[str, int] = {}

    def _put(self, data: bytes) -> str:
        d = self.store.put_bytes(data)
        self.objects[d] = len(data)
        return d

    def tree(self, v: Any, path: str = "$") -> Any:
        if isinstance(v, Stored):
            self.objects.update(v.objects)
            return v.node
        if isinstance(v, np.ndarray) and _png_friendly(v):
            v = Png(v)
        if isinstance(v, np.ndarray):
            if v.dtype == object:
                raise ArtifactError(f"{path}: object arrays cannot be stored safely")
            return {"$npy": self._put(_npy_bytes(v)), "dtype": v.dtype.str, "shape": list(v.shape)}
        if isinstance(v, Png):
            a = np.asarray(v.array)
            return {"$png": self._put(png_bytes(a)), "dtype": a.dtype.str, "shape": list(a.shape)}
        if isinstance(v, Tensors):
            return {"$safetensors": self._put(_safetensors_bytes(v.arrays)),
                    "keys": sorted(v.arrays)}
        if isinstance(v, dict):
            out = {}
            for k, x in v.items():
                if not isinstance(k, str):
                    raise ArtifactError(f"{path}: dict keys must be strings, got {k!r}")
                if k.startswith("$"):
                    raise ArtifactError(f"{path}: key {k!r} is reserved")
                out[k] = self.tree(x, f"{path}.{k}")
            return out
        if isinstance(v, (list, tuple)):
            return [self.tree(x, f"{path}[{i}]") for i, x in enumerate(v)]
        if isinstance(v, np.generic):
            return self.tree(v.item(), path)
        if isinstance(v, float) and not math.isfinite(v):
            raise ArtifactError(f"{path}: non-finite float {v} cannot be stored in JSON")
        if v is None or isinstance(v, (bool, int, float, str)):
            return v
        raise ArtifactError(f"{path}: cannot store a value of type {type(v).__name__}")

    def stored(self, value: Any) -> Stored:
        """Write ``value``'s objects now (a fresh encoder's); the handle stands for the value in
        a later manifest."""
        return Stored(self.tree(value), dict(self.objects))

    def manifest(self, kind: str, value: Any, **extra: Any) -> str:
        doc = {"kind": kind, "value": self.tree(value), **extra}
        validate(kind, doc)
        return self._put(canonical_json(doc))


# -------------------------------------------------------------------------------- decoding


# .npy headers this process has parsed (numpy parses each with ast.literal_eval: a map stage's
# thousands of small arrays share a few headers): header bytes -> (dtype, shape, element count).
_NPY_HEADERS: dict[bytes, tuple[np.dtype, tuple[int, ...], int]] = {}
_NPY_HEADERS_KEEP = 4096


def npy_array(data: bytes) -> np.ndarray:
    """The array of .npy bytes, as ``np.lib.format.read_array(..., allow_pickle=False)`` gives it (a
    fresh, writable array): a version 1.0 header numpy has parsed here before, C order, no objects,
    with exactly its data after it, is not parsed again; anything else goes through numpy."""
    head_end = 10 + int.from_bytes(data[8:10], "little") if data[:8] == b"\x93NUMPY\x01\x00" else 0
    seen = _NPY_HEADERS.get(data[:head_end]) if head_end else None
    if seen is not None and len(data) - head_end == seen[2] * seen[0].itemsize:
        dtype, shape, count = seen
        return np.frombuffer(data, dtype, count, head_end).reshape(shape).copy()
    a = np.lib.format.read_array(io.BytesIO(data), allow_pickle=False)
    if head_end and len(data) >= head_end:
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(io.BytesIO(data[8:head_end]))
        count = math.prod(shape)
        if not fortran and not dtype.hasobject and count > 0 and len(data) - head_end == count * dtype.itemsize:
            if len(_NPY_HEADERS) >= _NPY_HEADERS_KEEP:
                _NPY_HEADERS.clear()
            _NPY_HEADERS[data[:head_end]] = (dtype, tuple(shape), count)
    return a


# Decoded PNG objects this process keeps, by digest, at most this many bytes of arrays: video
# frames and masks are read by many items of many stages (each ICL frame was decoded ~19 times in
# a run), and decoding is what reading a PNG object costs.
DECODED_PNG_BYTES = 128 << 20


class DecodedMemo:
    """Least recently used decoded arrays of this process by object digest, at most ``budget``
    bytes; the memo's copies are read only, callers get fresh writable copies (an item that writes
    into its input changes nothing here). ``hits`` / ``misses`` are counted, never timed."""

    def __init__(self, budget: int = DECODED_PNG_BYTES):
        import threading
        from collections import OrderedDict

        self.budget = budget
        self._arrays: OrderedDict[str, np.ndarray] = OrderedDict()
        self.bytes = self.hits = self.misses = 0
        self._lock = threading.Lock()  # a run's threads (map stages beside a whole stage) share it

    def get(self, digest: str) -> np.ndarray | None:
        with self._lock:
            a = self._arrays.get(digest)
            if a is None:
                self.misses += 1
                return None
            self._arrays.move_to_end(digest)
            self.hits += 1
        return a.copy()

    def put(self, digest: str, a: np.ndarray) -> None:
        if a.nbytes > self.budget // 4:
            return
        kept = a.copy()
        kept.flags.writeable = False
        with self._lock:
            if digest in self._arrays:
                return
            self._arrays[digest] = kept
            self.bytes += kept.nbytes
            while self.bytes > self.budget:
                self.bytes -= self._arrays.popitem(last=False)[1].nbytes

    def clear(self) -> None:
        with self._lock:
            self._arrays.clear()
            self.bytes = 0


PNG_MEMO = DecodedMemo()


def decode_leaf(store: Store, node: dict[str, Any]) -> Any:
    if "$npy" in node:
        return npy_array(store.get_bytes(node["$npy"]))
    if "$png" in node:
        digest = node["$png"]
        # read (and verified) as always: a corrupt or missing object is found on every read; only
        # the decoding of an object this process decoded before is saved
        data = store.get_bytes(digest)
        a = PNG_MEMO.get(digest)
        if a is None:
            a = png_array(data, f"object {digest[:12]}")
            if store.verify:  # only bytes that matched their digest (``--no-verify`` reads are not kept)
                PNG_MEMO.put(digest, a)
        return a
    if "$safetensors" in node:
        from safetensors.numpy import load

        return load(store.get_bytes(node["$safetensors"]))
    raise ArtifactError(f"unknown leaf {sorted(node)}")


def is_leaf(node: Any) -> bool:
    return isinstance(node, dict) and any(k.startswith("$") for k in node)


def leaf_digests(node: Any) -> list[str]:
    """The objects a (sub-)tree of a manifest points at, in order."""
    if is_leaf(node):
        return [d for k, d in node.items() if k.startswith("$")]
    if isinstance(node, dict):
        return [d for v in node.values() for d in leaf_digests(v)]
    if isinstance(node, list):
        return [d for v in node for d in leaf_digests(v)]
    return []


def decode_tree(store: Store, node: Any) -> Any:
    if getattr(store, "fallback", None) is not None:  # read-through run: this tree's objects in one batch
        store.ensure(leaf_digests(node))
    return _decode(store, node)


def _decode(store: Store, node: Any) -> Any:
    if is_leaf(node):
        return decode_leaf(store, node)
    if isinstance(node, dict):
        return {k: _decode(store, v) for k, v in node.items()}
    if isinstance(node, list):
        return [_decode(store, v) for v in node]
    return node


def load_manifest(store: Store, digest: str) -> dict[str, Any]:
    try:
        doc = json.loads(store.get_bytes(digest))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ArtifactError(f"object {digest[:12]} is not a manifest") from exc
    if not isinstance(doc, dict) or "kind" not in doc:
        raise ArtifactError(f"object {digest[:12]} is not a manifest")
    return doc


def load_value(store: Store, digest: str) -> Any:
    return decode_tree(store, load_manifest(store, digest)["value"])


def manifest_objects(store: Store, digest: str) -> dict[str, int]:
    """All objects an artifact consists of (the manifest and its blobs), with sizes."""
    out = {digest: store.object_size(digest) or 0}

    def walk(node: Any) -> None:
        if is_leaf(node):
            for k, d in node.items():
                if k.startswith("$"):
                    out[d] = store.object_size(d) or 0
        elif isinstance(node, dict):
            for v in node.values():
                walk(v)
        elif isinstance(node, list):
            for v in node:
                walk(v)

    walk(load_manifest(store, digest)["value"])
    return out


# -------------------------------------------------------------------------------- schemas


@lru_cache(maxsize=None)
def _validator(kind: str):
    import jsonschema

    dirs = [ENGINE_SCHEMA_DIR] if kind in ENGINE_KINDS else _SCHEMA_DIRS
    folder = next((d for d in dirs if (d / f"{kind}.json").exists()), None)
    if folder is None:
        return None
    from referencing import Registry, Resource

    schema = json.loads((folder / f"{kind}.json").read_text())
    base = json.loads((ENGINE_SCHEMA_DIR / "common.json").read_text())
    registry = Registry().with_resources([(base["$id"], Resource.from_contents(base))])
    return jsonschema.validators.validator_for(schema)(schema, registry=registry)


def validate(kind: str, doc: dict[str, Any]) -> None:
    """Validate a manifest against ``<kind>.json`` of the registered schema folders (when one
    exists; a product's kinds are in ``artifacts_schema/``).

    Map stages' manifests (kind ``map:<item kind>``) validate against the engine's ``map.json``,
    checkpoints against its ``checkpoint.json``, with or without a registered folder.
    """
    v = _validator("map" if kind.startswith("map:") else kind)
    if v is None:
        return
    errors = sorted(v.iter_errors(doc), key=lambda e: list(e.absolute_path))
    if errors:
        e = errors[0]
        where = "/".join(str(p) for p in e.absolute_path) or "(root)"
        raise ArtifactError(f"{kind} artifact does not match its schema at {where}: {e.message}")
