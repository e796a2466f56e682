"""The layering rules hold by test (docs/contributing.md, "Layering"):

* the engine (``gcvd_flow/engine``) imports no project package — neither ``gcvd_flow.stages``, nor
  the product (``gcvd_flow.pipeline``, ``gcvd_flow.io`` ...), nor ``gcvd_flow.artifacts_schema`` — and neither
  cv2 nor torch, at module level or inside functions;
* ``stages/`` (``gcvd_flow.stages``) never imports the rest of ``gcvd_flow`` and never touches the file
  system (the engine serialises, the product reads files);
* only ``gcvd_flow/pipeline/`` (the blocks) and the weights opener import ``stages/`` (and the
  intrinsics.txt reader the camera grammar, stages/frontend/lens.py);
* no import cycle among the project's modules (imports inside functions count), and reading data
  (``gcvd_flow/io``) depends on no exporter, report or evaluation;
* importing the engine sets no process setting (the product's entry points do), and the engine
  spells its name and environment variables once (``gcvd_flow/engine/names.py``);
* no function in ``stages/`` or ``gcvd_flow/`` is longer than 80 lines unless a comment on the
  line before it says why it must be long.
"""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
ENGINE = ROOT / "gcvd_flow" / "engine"
STAGES = ROOT / "stages"

ENGINE_FORBIDDEN = ("stages", "artifacts_schema", "cv2", "torch", "gcvd_flow")  # gcvd_flow.engine excepted
STAGES_FORBIDDEN = ("gcvd_flow", "stages", "artifacts_schema")  # gcvd_flow.stages excepted
# calls that read or write files; stages receive arrays and return arrays
FILE_IO_CALLS = {"open", "imread", "imwrite", "load_file", "save_file", "safe_open", "read_text", "write_text",
                 "read_bytes", "write_bytes", "mkdir", "unlink", "rmtree", "VideoCapture", "VideoWriter"}
FILE_IO_ATTR_CALLS = {("np", "load"), ("np", "save"), ("np", "savez"), ("torch", "load"), ("torch", "save"),
                      ("o3d", "io"), ("os", "remove"), ("shutil", "copy")}
MAX_LINES = 80


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import in a file, in function bodies too; relative imports resolved."""
    tree = ast.parse(path.read_text())
    rel = path.relative_to(ROOT).with_suffix("")
    package = ".".join(rel.parts[:-1] if rel.name != "__init__" else rel.parts[:-1])
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.append((node.lineno, mod))
            out += [(node.lineno, f"{mod}.{a.name}") for a in node.names]
    return out


def _forbidden(mod: str, prefixes: tuple[str, ...], allowed: tuple[str, ...] = ()) -> bool:
    if any(mod == a or mod.startswith(a + ".") for a in allowed):
        return False
    return any(mod == p or mod.startswith(p + ".") for p in prefixes)


def test_engine_imports_nothing_of_the_product_nor_cv2_or_torch():
    bad = [f"{p.relative_to(ROOT)}:{line} imports {mod}"
           for p in sorted(ENGINE.rglob("*.py")) for line, mod in _imports(p)
           if _forbidden(mod, ENGINE_FORBIDDEN, allowed=("gcvd_flow.engine",))]
    assert not bad, "forbidden edges out of the engine:\n" + "\n".join(bad)


def test_stages_import_no_product_code():
    bad = [f"{p.relative_to(ROOT)}:{line} imports {mod}"
           for p in sorted(STAGES.rglob("*.py")) for line, mod in _imports(p)
           if _forbidden(mod, STAGES_FORBIDDEN, allowed=("gcvd_flow.stages",))]
    assert not bad, "forbidden edges out of stages/:\n" + "\n".join(bad)


def test_stages_do_no_file_io():
    bad = []
    for p in sorted(STAGES.rglob("*.py")):
        for node in ast.walk(ast.parse(p.read_text())):
            if not isinstance(node, ast.Call):
                continue
            f = node.func
            name = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else None
            owner = f.value.id if isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) else None
            if name in FILE_IO_CALLS or (owner, name) in FILE_IO_ATTR_CALLS:
                bad.append(f"{p.relative_to(ROOT)}:{node.lineno} calls {owner + '.' if owner else ''}{name}")
    assert not bad, "file I/O in stages/:\n" + "\n".join(bad)


def test_the_walker_sees_imports_inside_functions(tmp_path, monkeypatch):
    # the check above must not pass just because an import hides in a function body
    src = "def f():\n    import torch\n    from gcvd_flow.stages.frontend import flow\n"
    probe = tmp_path / "gcvd_flow" / "engine" / "probe.py"
    probe.parent.mkdir(parents=True)
    probe.write_text(src)
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    mods = {m for _, m in _imports(probe)}
    assert "torch" in mods and "gcvd_flow.stages.frontend.flow" in mods
    assert _forbidden("torch", ENGINE_FORBIDDEN) and not _forbidden("gcvd_flow.engine.keys", ENGINE_FORBIDDEN,
                                                                     allowed=("gcvd_flow.engine",))


def test_importing_the_engine_loads_neither_stages_nor_cv2_nor_torch():
    code = ("import sys, pkgutil, importlib, gcvd_flow.engine as e\n"
            "for m in pkgutil.iter_modules(e.__path__): importlib.import_module('gcvd_flow.engine.' + m.name)\n"
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('stages', 'cv2', 'torch', 'artifacts_schema')\n"
            "             or (m.startswith('gcvd_flow.') and not m.startswith('gcvd_flow.engine')))\n"
            "print(' '.join(bad))\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "", f"importing the engine loaded: {p.stdout.strip()}"


def _long_functions() -> list[str]:
    out = []
    for root in (ROOT / "gcvd_flow", STAGES):
        for p in sorted(root.rglob("*.py")):
            lines = p.read_text().splitlines()
            for node in ast.walk(ast.parse("\n".join(lines))):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    n = node.end_lineno - node.lineno + 1
                    first = min([d.lineno for d in node.decorator_list] + [node.lineno])
                    why = lines[first - 2].strip() if first >= 2 else ""
                    if n > MAX_LINES and not (why.startswith("#") and "long" in why.lower()):
                        out.append(f"{p.relative_to(ROOT)}:{node.lineno} {node.name} ({n} lines)")
    return out


def test_no_function_over_80_lines_without_a_reason():
    bad = _long_functions()
    assert not bad, "functions over 80 lines (split them, or say why on the line above):\n" + "\n".join(bad)


def test_a_forbidden_edge_would_be_caught():
    assert _forbidden("cv2", ENGINE_FORBIDDEN) and _forbidden("gcvd_flow.pipeline", ENGINE_FORBIDDEN,
                                                              allowed=("gcvd_flow.engine",))
    assert _forbidden("gcvd_flow.engine.dag", STAGES_FORBIDDEN, allowed=("gcvd_flow.stages",))
    assert not _forbidden("gcvd_flow.stages.geometry", STAGES_FORBIDDEN, allowed=("gcvd_flow.stages",))


# ------------------------------------------------------------------------------ the import graph
# (tests/import_graph.py: module-level imports and those inside functions, from the source)
from import_graph import cycles, project_graph  # noqa: E402

# the product modules that may import stages/: the pipeline wires them in, the weights opener
# hands a state dict to stages.models.load_model (docs/contributing.md, "Layering")
STAGES_IMPORTERS = {"gcvd_flow.pipeline", "gcvd_flow.io.weights"}
# single imports allowed beside them: intrinsics.txt and --intrinsics are one camera grammar
# (lens.parse_camera: text -> Camera, no I/O), read by the file reader too
STAGES_IMPORTS_ALLOWED = {("gcvd_flow.io.formats", "gcvd_flow.stages.frontend.lens")}


def test_no_import_cycle_among_the_project_modules():
    found = cycles(project_graph())
    assert not found, "import cycles (a deferred import inside a function counts too):\n" + "\n".join(
        " <-> ".join(c) for c in found)


def test_the_cycle_finder_sees_a_cycle_through_a_function_level_import(monkeypatch):
    import import_graph

    graph = project_graph()
    graph["gcvd_flow.io.formats"] = graph["gcvd_flow.io.formats"] | {"gcvd_flow.exports.clouds"}
    assert any("gcvd_flow.io.formats" in c for c in cycles(graph))
    # and the source reader records imports inside function bodies
    mods = import_graph.project_modules()
    assert "gcvd_flow.io.depth_maps" in graph["gcvd_flow.io.run_dir"], \
        f"run_dir's deferred import not seen in {sorted(graph['gcvd_flow.io.run_dir'])} ({mods['gcvd_flow.io.run_dir']})"


def test_only_the_pipeline_and_the_weights_opener_import_stages():
    def is_stages(t: str) -> bool:
        return t == "gcvd_flow.stages" or t.startswith("gcvd_flow.stages.")

    def stages_targets(m: str, targets: set[str]) -> list[str]:
        return sorted(t for t in targets if is_stages(t) and (m, t) not in STAGES_IMPORTS_ALLOWED)

    bad = [f"{m} imports {stages_targets(m, targets)}"
           for m, targets in sorted(project_graph().items())
           if not is_stages(m) and m not in STAGES_IMPORTERS and not m.startswith("gcvd_flow.pipeline.")
           and stages_targets(m, targets)]
    assert not bad, "product modules importing stages/ (wire the algorithm in gcvd_flow/pipeline/):\n" + "\n".join(bad)


def test_reading_data_depends_on_no_exporter_or_report():
    bad = [f"{m} imports {t}" for m, targets in sorted(project_graph().items()) if m.startswith("gcvd_flow.io")
           for t in sorted(targets) if t.startswith(("gcvd_flow.exports", "gcvd_flow.report", "gcvd_flow.evaluate"))]
    assert not bad, "gcvd_flow/io must not depend on the consumers of its data:\n" + "\n".join(bad)


def test_importing_the_engine_sets_no_process_setting_the_cli_does():
    code = ("import os, io, contextlib, sys\n"
            "import gcvd_flow.engine.api, gcvd_flow.engine.cli, gcvd_flow.engine.executors\n"
            "assert 'OMP_WAIT_POLICY' not in os.environ, 'set by importing the engine'\n"
            "from gcvd_flow import cli\n"
            "assert 'OMP_WAIT_POLICY' not in os.environ, 'set by importing the CLI module'\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            "    cli.main(['dag'])\n"
            "print(os.environ.get('OMP_WAIT_POLICY'), 'torch' in sys.modules)\n")
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120, env=env)
    assert p.returncode == 0, p.stderr
    assert p.stdout.split()[0] == "PASSIVE", p.stdout


def test_the_engine_spells_its_name_and_environment_variables_once():
    # gcvd_flow/engine/names.py holds them; code elsewhere in the engine uses the constants
    bad = []
    for p in sorted(ENGINE.rglob("*.py")):
        if p.name == "names.py":
            continue
        tree = ast.parse(p.read_text())
        docstrings = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant)}
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings:
                if "GCVD_FLOW_" in node.value or "gcvd-flow" in node.value or "gcvd_flow.pipelines" in node.value:
                    bad.append(f"{p.relative_to(ROOT)}:{node.lineno} {node.value!r}")
    assert not bad, "use gcvd_flow.engine.names instead of:\n" + "\n".join(bad)
