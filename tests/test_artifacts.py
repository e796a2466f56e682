"""Codecs and schemas: arrays round-trip exactly, nothing can smuggle code, schemas bite."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from gcvd_flow import artifacts_schema
from gcvd_flow.engine.artifacts import ArtifactError, Encoder, Tensors, load_manifest, load_value, register_schema_dir, validate

register_schema_dir(artifacts_schema.SCHEMA_DIR)  # what a pipeline spec does when it is loaded
from gcvd_flow.engine.store import Store


@pytest.fixture
def store(tmp_path):
    return Store(tmp_path / "cache")


def test_roundtrip_arrays_png_and_safetensors(store):
    rng = np.random.default_rng(0)
    value = {
        "image": rng.integers(0, 256, (24, 32, 3), dtype=np.uint8),
        "mask": (rng.random((24, 32)) > 0.5).astype(np.uint8),
        "flow": rng.standard_normal((24, 32, 2)).astype(np.float32),
        "valid": rng.random((24, 32)) > 0.3,
        "nested": [{"T": np.eye(4)}, 3, "text", None, True, 1.5],
        "state": Tensors({"w": rng.standard_normal((3, 3)).astype(np.float32)}),
    }
    enc = Encoder(store)
    d = enc.manifest("generic", value)
    man = load_manifest(store, d)
    assert "$png" in man["value"]["image"] and "$png" in man["value"]["mask"]
    assert "$npy" in man["value"]["flow"]
    back = load_value(store, d)
    for k in ("image", "mask", "flow", "valid"):
        assert back[k].dtype == value[k].dtype and np.array_equal(back[k], value[k])
    assert np.array_equal(back["nested"][0]["T"], np.eye(4))
    assert back["nested"][1:] == [3, "text", None, True, 1.5]
    assert np.array_equal(back["state"]["w"], value["state"].arrays["w"])
    # equal content -> equal digest (early cutoff depends on it)
    assert Encoder(store).manifest("generic", value) == d


def test_object_arrays_and_nan_are_refused(store):
    with pytest.raises(ArtifactError):
        Encoder(store).manifest("generic", {"x": np.array([object()], dtype=object)})
    with pytest.raises(ArtifactError):
        Encoder(store).manifest("generic", {"x": float("nan")})
    with pytest.raises(ArtifactError):
        Encoder(store).manifest("generic", {"$npy": 1})


def test_pickled_array_in_store_is_not_loaded(store):
    """A teammate's cache holding a pickled object array must not execute anything."""
    buf = io.BytesIO()
    # Deliberately unsafe: this builds the malicious input whose loading must be refused.
    np.save(buf, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    blob = store.put_bytes(buf.getvalue())
    doc = json.dumps({"kind": "generic", "value": {"x": {"$npy": blob, "dtype": "|O", "shape": [1]}}},
                     sort_keys=True, separators=(",", ":")).encode()
    d = store.put_bytes(doc)
    with pytest.raises(ValueError, match="allow_pickle"):
        load_value(store, d)


def test_schema_violation_names_the_place(store):
    with pytest.raises(ArtifactError, match="keyframes artifact does not match its schema"):
        Encoder(store).manifest("keyframes", {"indices": [], "threshold_px": 1.0})
    with pytest.raises(ArtifactError, match="flow"):
        Encoder(store).manifest("flow", {"fwd": np.zeros((2, 2, 2), np.float32)})
    Encoder(store).manifest("keyframes", {"indices": [0, 5], "threshold_px": 12.0})
    validate("map:frames", {"kind": "map:frames", "value": None, "items": ["0" * 64], "summary": None})


def test_the_engines_schemas_bite_without_any_pipeline_schemas(store, monkeypatch):
    # map manifests and checkpoints are the engine's: validated with no folder registered
    from gcvd_flow.engine import artifacts

    monkeypatch.setattr(artifacts, "_SCHEMA_DIRS", [])
    artifacts._validator.cache_clear()
    try:
        with pytest.raises(ArtifactError, match="map:frames artifact does not match"):
            validate("map:frames", {"kind": "map:frames", "value": None, "items": ["not a digest"]})
        with pytest.raises(ArtifactError, match="checkpoint artifact does not match"):
            Encoder(store).manifest("checkpoint", {"tensors": 3})
        Encoder(store).manifest("keyframes", {"indices": []})  # a product kind: not registered here
    finally:
        artifacts._validator.cache_clear()


def test_product_schemas_resolve_the_engines_common_definitions(store):
    from gcvd_flow import artifacts_schema
    assert not (artifacts_schema.SCHEMA_DIR / "common.json").exists()
    with pytest.raises(ArtifactError, match="depth artifact does not match"):
        validate("depth", {"kind": "depth", "value": {"depth": {"$npy": "x" * 64, "dtype": "<f4", "shape": [2, 2]}}})
    validate("depth", {"kind": "depth", "value": {"depth": {"$npy": "0" * 64, "dtype": "<f4", "shape": [2, 2]}}})
