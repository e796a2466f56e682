"""Canonical encoding, digests and code fingerprints (docs/design.md, "Cache keys")."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from gcvd_flow.engine import keys


def test_typed_encoding_distinguishes_one_values():
    ks = {keys.key_of(v) for v in (1, 1.0, "1", True)}
    assert len(ks) == 4


def test_dict_order_does_not_matter_but_values_do():
    assert keys.key_of({"a": 1, "b": [1, 2]}) == keys.key_of({"b": [1, 2], "a": 1})
    assert keys.key_of({"a": 1}) != keys.key_of({"a": 2})
    assert keys.key_of([1, 2]) != keys.key_of([2, 1])


def test_floats_by_exact_value_and_strings_length_prefixed():
    import math

    assert keys.key_of(0.1) != keys.key_of(math.nextafter(0.1, 1.0))  # one ulp apart
    assert keys.key_of(["ab", "c"]) != keys.key_of(["a", "bc"])
    assert keys.key_of(np.float64(0.5)) == keys.key_of(0.5)


def test_arrays_encode_dtype_shape_and_content():
    a = np.arange(6, dtype=np.float32)
    assert keys.key_of(a) == keys.key_of(a.copy())
    assert keys.key_of(a) != keys.key_of(a.astype(np.float64))
    assert keys.key_of(a) != keys.key_of(a.reshape(2, 3))


def test_unencodable_values_are_rejected():
    with pytest.raises(keys.EncodingError):
        keys.key_of(object())


def test_env_has_no_paths_or_names():
    from gcvd_flow.pipeline import PIPELINE

    env = PIPELINE.numeric_env()
    text = repr(env)
    import socket

    assert "/" not in text
    assert socket.gethostname() not in text
    assert set(env) >= {"numpy", "torch", "opencv", "device", "dtype", "deterministic"}


# Third-party libraries the pipeline's code imports that compute no stored result, and why.
# Everything else it imports (stages/, gcvd_flow/pipeline.py and the project modules they reach,
# at module level or inside functions) must have its version in every key.
NOT_NUMERIC = {
    "pydantic": "parses the configuration; params enter keys in their own canonical encoding",
    "jsonschema": "validates artifact metadata", "referencing": "jsonschema's schema registry",
    "blake3": "computes the digests themselves (a fixed algorithm)",
    "platformdirs": "finds the default cache directory", "fsspec": "remote caches move bytes verbatim",
    "distributed": "the Dask executor (results do not depend on where an item ran)",
    "dask": "the Dask executor's configuration (results do not depend on where an item ran)",
    "threadpoolctl": "pins BLAS to one thread around bundle adjustment (results then do not depend on it)",
}


def _pipeline_libraries() -> dict[str, set[str]]:
    """Distribution -> project modules importing it, for the code a GCVD run executes."""
    import importlib.metadata

    from import_graph import closure, project_graph, third_party_imports

    graph = project_graph()
    reached = closure(["gcvd_flow.pipeline"] + [m for m in graph if m.startswith("gcvd_flow.stages")], graph)
    dists = importlib.metadata.packages_distributions()
    out: dict[str, set[str]] = {}
    for top, importers in third_party_imports(reached).items():
        assert top in dists, f"{top} (imported by {sorted(importers)}) is not installed"
        for d in dists[top]:
            out.setdefault(d.lower(), set()).update(importers)
    return out


def test_every_library_computing_a_stored_result_is_in_the_key():
    from gcvd_flow.engine.keys import ENGINE_LIBRARIES
    from gcvd_flow.pipeline import PIPELINE

    keyed = {d.lower() for _, dists in ENGINE_LIBRARIES + PIPELINE.numeric_libraries for d in dists}
    found = _pipeline_libraries()
    assert {"scipy", "pillow", "torch", "gtsam"} <= set(found), sorted(found)  # the finder finds
    missing = {d: sorted(m)[:3] for d, m in found.items() if d not in keyed and d not in NOT_NUMERIC}
    assert not missing, ("libraries the pipeline imports whose versions are not in the cache key "
                         f"(add them to PIPELINE's numeric_libraries, or to NOT_NUMERIC with a reason): {missing}")
    env = PIPELINE.numeric_env()
    assert env["scipy"] and env["pillow"] and env["safetensors"], env


def _make_package(root, name: str, files: dict[str, str], monkeypatch):
    """Write a throw-away package `name` under `root`, importable and counted as project code."""
    pkg = root / name
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    for fname, text in files.items():
        (pkg / fname).write_text(text)
    monkeypatch.syspath_prepend(str(root))
    return pkg


def _forget(name: str) -> None:
    keys.clear_caches()
    for m in [m for m in sys.modules if m == name or m.startswith(name + ".")]:
        del sys.modules[m]


@pytest.fixture
def temp_package(tmp_path, monkeypatch):
    """A throw-away project package `fpkg` (stage module + helper module) on sys.path."""
    pkg = tmp_path / "fpkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "helper.py").write_text("def scale(x):\n    return x * 2\n")
    (pkg / "other.py").write_text("def unrelated():\n    return 0\n")
    (pkg / "stage.py").write_text(textwrap.dedent('''
        """A stage module."""
        from fpkg import helper


        def run(inputs, params, ctx):
            """Docstring."""
            return helper.scale(inputs)


        def unused_neighbour():
            return 1
    '''))
    monkeypatch.syspath_prepend(str(tmp_path))
    yield pkg
    for m in [m for m in sys.modules if m == "fpkg" or m.startswith("fpkg.")]:
        del sys.modules[m]
    keys.clear_caches()


def _fingerprint(pkg_name: str = "fpkg.stage"):
    keys.clear_caches()
    for m in [m for m in sys.modules if m == "fpkg" or m.startswith("fpkg.")]:
        del sys.modules[m]
    mod = importlib.import_module(pkg_name)
    return keys.code_fingerprint(mod.run, ("fpkg",))


def test_reformatting_and_comments_do_not_invalidate(temp_package):
    fp0, files = _fingerprint()
    assert any("helper.py" in f for f, _ in files)
    (temp_package / "stage.py").write_text(textwrap.dedent('''
        """A stage module, re-documented."""
        from fpkg import helper  # the helper


        def run(inputs,
                params,
                ctx):
            """Another docstring entirely."""
            # a comment
            return helper.scale( inputs )


        def unused_neighbour():
            return 1
    '''))
    assert _fingerprint()[0] == fp0


def test_changed_helper_invalidates(temp_package):
    fp0, _ = _fingerprint()
    (temp_package / "helper.py").write_text("def scale(x):\n    return x * 3\n")
    assert _fingerprint()[0] != fp0


def test_changed_function_body_invalidates_but_unrelated_neighbour_does_not(temp_package):
    fp0, _ = _fingerprint()
    src = (temp_package / "stage.py").read_text()
    (temp_package / "stage.py").write_text(src.replace("return 1", "return 2"))
    assert _fingerprint()[0] == fp0, "editing an unrelated function must not invalidate"
    (temp_package / "stage.py").write_text(src.replace("helper.scale(inputs)", "helper.scale(inputs) + 1"))
    assert _fingerprint()[0] != fp0


def test_fingerprint_independent_of_location(tmp_path, temp_package):
    fp0, files0 = _fingerprint()
    assert all(not f.startswith("/") for f, _ in files0)


def test_imports_inside_the_function_count(tmp_path, monkeypatch):
    pkg = _make_package(tmp_path, "lpkg", {
        "algo.py": "def solve(x):\n    return x + 1\n",
        "step.py": "def run(inputs, params, ctx):\n    from lpkg import algo\n\n    return algo.solve(inputs)\n",
    }, monkeypatch)

    def fp():
        _forget("lpkg")
        return keys.code_fingerprint(importlib.import_module("lpkg.step").run, ("lpkg",))

    fp0, files = fp()
    assert any("lpkg/algo.py" in f for f, _ in files)
    (pkg / "algo.py").write_text("def solve(x):\n    return x + 2\n")
    assert fp()[0] != fp0
    _forget("lpkg")


def test_helpers_in_other_adapter_modules_are_followed_function_by_function(tmp_path, monkeypatch):
    """Adapters split over several modules (gcvd_flow/pipeline/*.py): a helper moved to a shared
    adapter module stays in its stages' keys one function at a time, as in the stage's own module,
    so the split makes no key coarser; without ``adapters`` that module would enter whole."""
    pkg = _make_package(tmp_path, "apkg", {
        "algo.py": "def solve(x):\n    return x + 1\n",
        "shared.py": textwrap.dedent('''
            from apkg import algo


            def helper(x):
                return algo.solve(x) * 2


            class Holder:
                def get(self, x):
                    return x


            def unrelated():
                return 0
        '''),
        "step.py": textwrap.dedent('''
            from apkg.shared import Holder, helper as _helper


            def run(inputs, params, ctx):
                return _helper(Holder().get(inputs))


            def neighbour():
                return 1
        '''),
    }, monkeypatch)

    def fp(adapters=("apkg.shared", "apkg.step")):
        _forget("apkg")
        return keys.code_fingerprint(importlib.import_module("apkg.step").run, ("apkg",), adapters)

    fp0, files = fp()
    names = [f for f, _ in files]
    assert "apkg.shared:helper" in names and "apkg.shared:Holder" in names
    assert "apkg/algo.py" in names and "apkg/shared.py" not in names  # stages-like code: whole modules
    src = (pkg / "shared.py").read_text()
    (pkg / "shared.py").write_text(src.replace("return 0", "return 5"))
    assert fp()[0] == fp0, "editing an unrelated helper of the shared adapter module must not invalidate"
    coarse = fp(adapters=())[0]
    (pkg / "shared.py").write_text(src)
    assert fp(adapters=())[0] != coarse, "without adapters the shared module enters whole"
    (pkg / "shared.py").write_text(src.replace("* 2", "* 3"))
    assert fp()[0] != fp0, "editing the moved helper must change the key"
    (pkg / "shared.py").write_text(src.replace("return x\n", "return x + 0\n"))
    assert fp()[0] != fp0, "editing a method of a moved helper class must change the key"
    (pkg / "shared.py").write_text(src)
    (pkg / "algo.py").write_text("def solve(x):\n    return x + 2\n")
    assert fp()[0] != fp0, "what the moved helper uses from other project modules still counts"
    _forget("apkg")


def test_a_changed_item_selection_rule_reruns_the_map_stage(tmp_path, monkeypatch):
    """Which items a map stage has is its ``items`` function's doing: a changed rule (here the
    helper it calls keeps fewer items, as a changed reference rule keeps fewer pairs) must not
    find the old stage record and hand back the old item list, while the items themselves (keyed
    by their inputs) stay cached. Before 2026-11-29 the stage key held only the stage function's
    code: the old list came back with exit 0."""
    from gcvd_flow.engine.dag import MapStage, Pipeline, Stage
    from gcvd_flow.engine.runner import Runner
    from gcvd_flow.engine.store import Store

    pkg = _make_package(tmp_path, "spkg", {
        "rule.py": "def chosen(n):\n    return [k for k in range(n) if k % 2 == 0]\n",
        "stage.py": textwrap.dedent('''
            from gcvd_flow.engine.dag import Const
            from spkg import rule


            def square(inputs, params, ctx):
                return {"v": inputs["k"] ** 2}


            def pick(view, params):
                return [{"k": Const(k)} for k in rule.chosen(8)]


            def total(inputs, params, ctx):
                return {"sum": sum(int(it["v"]) for it in inputs["square"])}
        '''),
    }, monkeypatch)
    del pkg

    def run_once() -> tuple[dict, dict]:
        _forget("spkg")
        import spkg.stage as st

        pipe = Pipeline([MapStage("square", st.square, items=st.pick), Stage("total", st.total, deps=("square",))],
                        packages=("spkg",), adapters=("spkg",))
        runner = Runner(pipe, Store(tmp_path / "cache"), config=None, log=lambda m: None)
        reports = {r.name: r for r in runner.run()}
        return reports, runner.value("total")

    reports, total = run_once()
    assert total["sum"] == sum(k * k for k in (0, 2, 4, 6)) and reports["square"].executed == 4
    assert "spkg/rule.py" in reports["square"].fields["code_files"]  # `why` names the rule's file
    (tmp_path / "spkg" / "rule.py").write_text("def chosen(n):\n    return [k for k in range(n) if k % 4 == 0]\n")
    reports, total = run_once()
    assert total["sum"] == sum(k * k for k in (0, 4)), "the old item list came back"
    assert reports["square"].action == "run" and reports["square"].executed == 0  # the items are reused
    reports, total = run_once()
    assert reports["square"].action == "cached" and total["sum"] == 16


def test_a_constant_the_stage_function_reads_enters_its_fingerprint(tmp_path, monkeypatch):
    """Modules followed function by function (the stage's own, the adapters) also give the
    constants a function reads: its own assignment, or the project module it was imported from.
    Before 2026-11-29 a changed module-level threshold in an adapter module kept the key."""
    pkg = _make_package(tmp_path, "cpkg", {
        "consts.py": "LIMIT = 3\n",
        "step.py": textwrap.dedent('''
            from cpkg.consts import LIMIT

            SCALE = 2.0
            TABLE = {"a": (1, 2)}
            UNUSED = 5


            def run(inputs, params, ctx):
                return inputs * SCALE + TABLE["a"][0] + LIMIT
        '''),
    }, monkeypatch)

    def fp():
        _forget("cpkg")
        return keys.code_fingerprint(importlib.import_module("cpkg.step").run, ("cpkg",), ("cpkg.step",))

    fp0, files = fp()
    assert {"cpkg.step:SCALE", "cpkg.step:TABLE", "cpkg/consts.py"} <= {f for f, _ in files}
    src = (pkg / "step.py").read_text()
    (pkg / "step.py").write_text(src.replace("UNUSED = 5", "UNUSED = 6"))
    assert fp()[0] == fp0, "a constant the function does not read must not invalidate"
    (pkg / "step.py").write_text(src.replace("SCALE = 2.0", "SCALE = 2.5"))
    assert fp()[0] != fp0
    (pkg / "step.py").write_text(src.replace('(1, 2)', '(4, 2)'))
    assert fp()[0] != fp0
    (pkg / "step.py").write_text(src)
    assert fp()[0] == fp0
    (pkg / "consts.py").write_text("LIMIT = 4\n")
    assert fp()[0] != fp0
    _forget("cpkg")


def test_a_lambda_items_function_has_the_same_fingerprint_in_every_process(tmp_path):
    """A lambda whose source cannot be parsed alone is fingerprinted by its code object: the same
    in a process with another string hash seed (a set literal compiles to a frozenset constant)."""
    src = ("import json, sys\nfrom gcvd_flow.engine import keys\n"
           "f = (None,\n     lambda v, p: [k for k in ('a', 'b', 'c', 'd') if k in {'a', 'c', 'd', 'x'}])[1]\n"
           "print(keys.selection_fingerprint(f, ('nothing',))[0])\n")
    script = tmp_path / "fp.py"
    script.write_text(src)
    outs = {subprocess.run([sys.executable, str(script)], capture_output=True, text=True, check=True,
                           env={**os.environ, "PYTHONHASHSEED": seed}).stdout.strip() for seed in ("1", "2", "3")}
    assert len(outs) == 1 and len(next(iter(outs))) == 64


def test_fingerprinting_imports_none_of_the_modules_it_reads(temp_package):
    """A stage's closure is read from the files, not imported: a stage whose body imports a
    package lazily (as the stages import torch's models) is fingerprinted without running that
    package's code (find_spec("fpkg.tools.heavy") imported fpkg.tools: 3.7 s of torch per run)."""
    tools = temp_package / "tools"
    tools.mkdir()
    (tools / "__init__.py").write_text("raise RuntimeError('fpkg.tools was imported')\n")
    (tools / "heavy.py").write_text("def model():\n    return 3\n")
    (temp_package / "stage.py").write_text(textwrap.dedent('''
        def run(inputs, params, ctx):
            from fpkg.tools import heavy
            return heavy.model()
    '''))
    fp0, files = _fingerprint()
    assert "fpkg.tools" not in sys.modules
    assert {"fpkg/tools/__init__.py", "fpkg/tools/heavy.py"} <= {f for f, _ in files}, files
    (tools / "heavy.py").write_text("def model():\n    return 4\n")
    assert _fingerprint()[0] != fp0  # the lazily imported module is still part of the key
