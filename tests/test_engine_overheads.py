"""The engine's own overheads (issue 38): each module's source is parsed once per fingerprint pass
and the digests stay those of the previous recipe; a PNG object is decoded once per process and
every read still reads and verifies the object; .npy headers parsed once give the arrays numpy
gives. Mechanisms are counted, never timed."""

from __future__ import annotations

import ast
import importlib
import io
import sys
import textwrap
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from gcvd_flow.engine import artifacts, keys
from gcvd_flow.engine.artifacts import Encoder, decode_leaf, load_value, npy_array, png_bytes
from gcvd_flow.engine.store import CorruptObject, MissingObject, Store

ROOT = Path(__file__).resolve().parent.parent


# ------------------------------------------------------------------------------ fingerprints


class _OldStrip(ast.NodeTransformer):
    """The docstring stripper of the previous recipe (a NodeTransformer), kept as the reference:
    the digests of every project file must stay the same (keys must not move)."""

    def _strip(self, node):
        self.generic_visit(node)
        body = getattr(node, "body", None)
        if (body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)):
            node.body = body[1:] or [ast.Pass()]
        return node

    visit_Module = visit_FunctionDef = visit_AsyncFunctionDef = visit_ClassDef = _strip


def _old_digest(source: str) -> str:
    tree = _OldStrip().visit(ast.parse(source))
    return keys.digest_bytes(ast.dump(tree, annotate_fields=True, include_attributes=False).encode())


def test_ast_digests_are_those_of_the_previous_recipe():
    files = sorted((ROOT / "stages").rglob("*.py")) + sorted((ROOT / "gcvd_flow").rglob("*.py"))
    assert len(files) > 50
    extra = textwrap.dedent('''
        """module doc"""
        class A:
            """only a docstring"""
        def f():
            "doc"
            def g():
                """inner"""
                return 1
            if True:
                class B:
                    """nested"""
                    x = 1
            return g
        async def h():
            """doc"""
            await x
    ''')
    for text in [p.read_text(encoding="utf-8") for p in files] + [extra]:
        assert keys.normalized_ast_digest(text) == _old_digest(text)


@pytest.fixture
def shared_package(tmp_path, monkeypatch):
    """Two stage modules importing the same helper modules."""
    pkg = tmp_path / "ppkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "base.py").write_text("def one():\n    return 1\n")
    (pkg / "helper.py").write_text("from ppkg import base\n\n\ndef scale(x):\n    return x * base.one()\n")
    for name in ("a", "b"):
        (pkg / f"stage_{name}.py").write_text(textwrap.dedent(f'''
            from ppkg import helper


            def run(inputs, params, ctx):
                """Stage {name}."""
                from ppkg import base

                return helper.scale(inputs) + base.one()
        '''))
    monkeypatch.syspath_prepend(str(tmp_path))
    keys.clear_caches()
    yield pkg
    for m in [m for m in sys.modules if m == "ppkg" or m.startswith("ppkg.")]:
        del sys.modules[m]
    keys.clear_caches()


def test_each_module_and_function_is_parsed_once(shared_package, monkeypatch):
    parsed: Counter = Counter()
    real = ast.parse

    def counting(source, *a, **kw):
        parsed[source] += 1
        return real(source, *a, **kw)

    monkeypatch.setattr(keys.ast, "parse", counting)
    fps = [keys.code_fingerprint(importlib.import_module(f"ppkg.stage_{n}").run, ("ppkg",)) for n in ("a", "b")]
    files = dict(fps[0][1])
    assert "ppkg/helper.py" in files and "ppkg/base.py" in files and "ppkg/__init__.py" in files
    assert parsed and max(parsed.values()) == 1, [s[:40] for s, n in parsed.items() if n > 1]
    # two module sources (helper, base), __init__, and the two stage functions: five texts
    assert len(parsed) == 5
    assert fps[0][0] != fps[1][0]  # their own code differs (the docstrings are stripped, not the names)


# ------------------------------------------------------------------------------ decoded PNG objects


@pytest.fixture
def store(tmp_path):
    artifacts.PNG_MEMO.clear()
    yield Store(tmp_path / "cache")
    artifacts.PNG_MEMO.clear()


def _png_node(store: Store, a: np.ndarray) -> dict:
    return {"$png": store.put_bytes(png_bytes(a)), "dtype": "|u1", "shape": list(a.shape)}


def test_a_png_object_is_decoded_once_and_served_as_fresh_equal_arrays(store, monkeypatch):
    decodes: Counter = Counter()
    real = artifacts.png_array

    def counting(data, where="PNG"):
        decodes[where] += 1
        return real(data, where)

    monkeypatch.setattr(artifacts, "png_array", counting)
    a = np.random.default_rng(0).integers(0, 255, (24, 32, 3), dtype=np.uint8)
    node = _png_node(store, a)
    first = decode_leaf(store, node)
    second = decode_leaf(store, node)
    assert sum(decodes.values()) == 1 and artifacts.PNG_MEMO.hits >= 1
    assert first.tobytes() == second.tobytes() == a.tobytes() and second.dtype == np.uint8
    assert second.flags.writeable and not np.shares_memory(first, second)
    second[:] = 0  # an item writing into its input changes nothing for the next reader
    assert decode_leaf(store, node).tobytes() == a.tobytes()
    assert sum(decodes.values()) == 1


def test_a_memoised_png_is_still_read_and_verified(store):
    a = np.arange(64 * 48, dtype=np.uint8).reshape(48, 64)
    node = _png_node(store, a)
    assert decode_leaf(store, node).tobytes() == a.tobytes()
    path = store.object_path(node["$png"])
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.chmod(0o644)
    path.write_bytes(bytes(data))
    with pytest.raises(CorruptObject):
        decode_leaf(store, node)  # same size, flipped byte: found although its decoding is memoised
    node2 = _png_node(store, a)
    assert decode_leaf(store, node2).tobytes() == a.tobytes()  # rewritten, whole again
    store.object_path(node2["$png"]).unlink()
    with pytest.raises(MissingObject):
        decode_leaf(store, node2)


def test_unverified_reads_are_not_memoised(tmp_path, store):
    a = np.full((16, 16), 7, np.uint8)
    loose = Store(tmp_path / "loose", verify=False)
    node = _png_node(loose, a)
    path = loose.object_path(node["$png"])
    path.chmod(0o644)
    path.write_bytes(png_bytes(np.full((16, 16), 9, np.uint8)))  # not the bytes its name says
    assert decode_leaf(loose, node)[0, 0] == 9  # --no-verify: read as it is
    assert artifacts.PNG_MEMO.bytes == 0  # ... and not kept for verified readers
    node2 = _png_node(store, a)
    assert node2["$png"] == node["$png"] and decode_leaf(store, node2)[0, 0] == 7


def test_the_png_memo_stays_within_its_budget(store):
    memo = artifacts.DecodedMemo(budget=4 * 32 * 32)
    for i in range(10):
        memo.put(f"{i:064x}", np.full((32, 32), i, np.uint8))
    assert memo.bytes <= memo.budget and memo.get(f"{9:064x}") is not None and memo.get(f"{0:064x}") is None


# ------------------------------------------------------------------------------ .npy headers


ARRAYS = [np.arange(12, dtype=np.float32).reshape(3, 4), np.arange(6, dtype=">i4").reshape(2, 3),
          np.array(3.5), np.zeros((0, 3), np.float64), np.asfortranarray(np.arange(6.0).reshape(2, 3)),
          np.array([True, False]), np.arange(10, dtype=np.complex64), np.zeros((2, 2), [("a", "<f4"), ("b", "u1")])]


def _npy(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, a, allow_pickle=False)
    return buf.getvalue()


def test_npy_arrays_are_numpys_and_a_header_is_parsed_once(monkeypatch):
    parses: Counter = Counter()
    real = np.lib.format.read_array

    def counting(fp, *a, **kw):
        parses["read_array"] += 1
        return real(fp, *a, **kw)

    monkeypatch.setattr(artifacts, "_NPY_HEADERS", {})
    monkeypatch.setattr(np.lib.format, "read_array", counting)
    for a in ARRAYS:
        for _ in range(3):
            got = npy_array(_npy(a))
            want = real(io.BytesIO(_npy(a)), allow_pickle=False)
            assert got.dtype == want.dtype and got.shape == want.shape and got.tobytes() == want.tobytes()
            assert got.flags.writeable and got.flags.c_contiguous == want.flags.c_contiguous
    # C-order, non-empty headers are parsed by numpy once; the empty and Fortran ones every time
    assert parses["read_array"] == len(ARRAYS) + 2 * 2
    b = np.arange(12, dtype=np.float32).reshape(3, 4) * 2
    assert npy_array(_npy(b)).tobytes() == b.tobytes()  # same header, other data


def test_npy_with_a_known_header_but_wrong_length_is_numpys_error(monkeypatch):
    monkeypatch.setattr(artifacts, "_NPY_HEADERS", {})
    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    npy_array(_npy(a))
    with pytest.raises(ValueError):
        npy_array(_npy(a)[:-4])  # truncated: numpy's own check, not a short array
    longer = npy_array(_npy(a) + b"\0" * 8)  # trailing bytes: what numpy gives
    assert longer.tobytes() == np.lib.format.read_array(io.BytesIO(_npy(a) + b"\0" * 8)).tobytes()


def test_object_arrays_are_refused_with_a_known_header(store, monkeypatch):
    monkeypatch.setattr(artifacts, "_NPY_HEADERS", {})
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    for _ in range(2):
        with pytest.raises(ValueError):
            npy_array(buf.getvalue())


def test_values_round_trip_through_the_store(store):
    value = {"frame": np.random.default_rng(1).integers(0, 255, (16, 20, 3), dtype=np.uint8),
             "depth": np.linspace(0, 1, 320, dtype=np.float32).reshape(16, 20), "n": 3}
    enc = Encoder(store)
    digest = enc.manifest("thing", value)
    for _ in range(2):
        got = load_value(store, digest)
        assert got["n"] == 3 and got["frame"].tobytes() == value["frame"].tobytes()
        assert got["depth"].dtype == np.float32 and got["depth"].tobytes() == value["depth"].tobytes()
