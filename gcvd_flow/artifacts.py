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

from .store import Store, canonical_json

SCHEMA_DIR = Path(__file__).resolve().parent.parent / "artifacts_schema"


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


# -------------------------------------------------------------------------------- encoding


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.ascontiguousarray(a), allow_pickle=False)
    return buf.getvalue()


def _png_bytes(a: np.ndarray) -> bytes:
    import cv2  # lazy: only image artifacts need it

    if a.dtype != np.uint8 or a.ndim not in (2, 3):
        raise ArtifactError(f"PNG codec needs uint8 (H,W[,3]) arrays, got {a.dtype} {a.shape}")
    img = a if a.ndim == 2 else np.ascontiguousarray(a[..., ::-1])  # RGB -> cv2's BGR
    ok, enc = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 3])
    if not ok:
        raise ArtifactError("PNG encoding failed")
    return enc.tobytes()


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
        if isinstance(v, np.ndarray) and _png_friendly(v):
            v = Png(v)
        if isinstance(v, np.ndarray):
            if v.dtype == object:
                raise ArtifactError(f"{path}: object arrays cannot be stored safely")
            return {"$npy": self._put(_npy_bytes(v)), "dtype": v.dtype.str, "shape": list(v.shape)}
        if isinstance(v, Png):
            a = np.asarray(v.array)
            return {"$png": self._put(_png_bytes(a)), "dtype": a.dtype.str, "shape": list(a.shape)}
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

    def manifest(self, kind: str, value: Any, **extra: Any) -> str:
        doc = {"kind": kind, "value": self.tree(value), **extra}
        validate(kind, doc)
        return self._put(canonical_json(doc))


# -------------------------------------------------------------------------------- decoding


def decode_leaf(store: Store, node: dict[str, Any]) -> Any:
    if "$npy" in node:
        data = store.get_bytes(node["$npy"])
        return np.lib.format.read_array(io.BytesIO(data), allow_pickle=False)
    if "$png" in node:
        import cv2

        data = np.frombuffer(store.get_bytes(node["$png"]), np.uint8)
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ArtifactError(f"object {node['$png'][:12]} is not a readable PNG")
        return img if img.ndim == 2 else np.ascontiguousarray(img[..., ::-1])
    if "$safetensors" in node:
        from safetensors.numpy import load

        return load(store.get_bytes(node["$safetensors"]))
    raise ArtifactError(f"unknown leaf {sorted(node)}")


def is_leaf(node: Any) -> bool:
    return isinstance(node, dict) and any(k.startswith("$") for k in node)


def decode_tree(store: Store, node: Any) -> Any:
    if is_leaf(node):
        return decode_leaf(store, node)
    if isinstance(node, dict):
        return {k: decode_tree(store, v) for k, v in node.items()}
    if isinstance(node, list):
        return [decode_tree(store, v) for v in node]
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

    path = SCHEMA_DIR / f"{kind}.json"
    if not path.exists():
        return None
    from referencing import Registry, Resource

    schema = json.loads(path.read_text())
    base = json.loads((SCHEMA_DIR / "common.json").read_text())
    registry = Registry().with_resources([(base["$id"], Resource.from_contents(base))])
    return jsonschema.validators.validator_for(schema)(schema, registry=registry)


def validate(kind: str, doc: dict[str, Any]) -> None:
    """Validate a manifest against ``artifacts_schema/<kind>.json`` (when the schema exists).

    Map stages' manifests (kind ``map:<item kind>``) validate against ``map.json``.
    """
    v = _validator("map" if kind.startswith("map:") else kind)
    if v is None:
        return
    errors = sorted(v.iter_errors(doc), key=lambda e: list(e.absolute_path))
    if errors:
        e = errors[0]
        where = "/".join(str(p) for p in e.absolute_path) or "(root)"
        raise ArtifactError(f"{kind} artifact does not match its schema at {where}: {e.message}")
