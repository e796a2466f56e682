"""Split the one-file gcvd_flow/pipeline.py into the package gcvd_flow/pipeline/ (issue 39 item 4).

    python tools/split_pipeline.py [--source gcvd_flow/pipeline.py] [--keep]

Moves, never rewrites: every top-level statement of the file (a function, class or assignment, with
the comments above it) lands unchanged in one module, chosen by the ``# ===== <block>`` banner it
sits under (BLOCKS) or, for the helpers more than one block reads, by name (SHARED: shared.py).
Each module gets the old header's imports plus ``from gcvd_flow.pipeline.<earlier> import <name>``
for what it uses from the modules declared before it; ``ruff check --fix`` then drops the unused
ones. ``__init__`` imports the block modules in declaration order (the stages keep their order),
assembles the pipeline (the file's last block) and re-exports every name, so
``gcvd_flow.pipeline.X`` keeps working. Re-run it on a pipeline.py that other branches edited
(restore the file from git first when the package already exists), then tools/relayout.py (imports)
and ``ruff check --fix``.
"""

from __future__ import annotations

import argparse
import ast
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PKG = ROOT / "gcvd_flow" / "pipeline"

# banner -> module; in declaration order (a module's blocks are contiguous)
BLOCKS = {
    "ingest": "frontend", "user masks": "frontend", "calibrate": "frontend", "flow": "frontend",
    "flow_far": "frontend",
    "masks": "masks",
    "priors": "priors",
    "keyframes": "graph", "association": "graph",
    "optimisation: shared": "optimize", "optimize_keyframes": "optimize", "optimize_edges": "optimize",
    "pose_graph": "optimize", "bundle_adjustment": "optimize", "optimize_segments": "optimize",
    "depth_fusion": "depth", "depth_filter": "depth", "depth_consensus": "depth",
}
ORDER = ["registry", "shared", "frontend", "masks", "priors", "graph", "optimize", "depth"]
# helpers several blocks read, with no stage of their own: reading items and the --masks files,
# choosing reference frames (pure functions of items, settings and files)
SHARED = {"_undistort_of", "_user_mask_files", "_MaskFile", "_user_keep", "_prior_refs", "_fusion_refs",
          "_fusion_far_refs", "_far_flow", "_solve_mask", "_hard_mask", "_user_keeps", "_eroded_keep",
          "_HardMasks"}
DOCS = {
    "registry": "How a block declares itself: its config section (``--set section.key=value``, derived from the\n"
               "stage's parameter dataclass) and its stage, in declaration order.",
    "shared": "Helpers more than one block reads: the items of the masks and flow stages seen by a later stage,\n"
              "the user's --masks files, and which reference frames priors and depth_fusion read.",
    "frontend": "Blocks ingest, user_masks, calibrate, flow and flow_far (stages/frontend).",
    "masks": "Block masks (stages/frontend/masks.py, stages/frontend/user_masks.py), and the references later\n"
             "stages' items make to its items.",
    "priors": "Block priors (stages/frontend/priors.py).",
    "graph": "Blocks keyframes and association (stages/graph).",
    "optimize": "Blocks optimize_keyframes, optimize_edges, pose_graph, bundle_adjustment and optimize_segments\n"
                "(stages/optimize).",
    "depth": "Blocks fusion_samples, fusion_references, fusion_flow, depth_fusion, depth_filter and\n"
             "depth_consensus (stages/depth).",
}
BANNER = re.compile(r"^# =+ (.+)$")


def _defined(node: ast.stmt) -> list[str]:
    if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
        return [node.name]
    if isinstance(node, ast.Assign):
        return [t.id for t in node.targets if isinstance(t, ast.Name)]
    if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
        return [node.target.id]
    return []


def _used(node: ast.AST) -> tuple[set[str], set[str]]:
    """(names a statement reads, those of them it reads only in annotations)."""
    ann_ids: set[int] = set()
    for n in ast.walk(node):
        for a in (getattr(n, "annotation", None), getattr(n, "returns", None)):
            if isinstance(a, ast.AST):
                ann_ids |= {id(m) for m in ast.walk(a)}
    names = [n for n in ast.walk(node) if isinstance(n, ast.Name)]
    code = {n.id for n in names if id(n) not in ann_ids}
    return {n.id for n in names}, {n.id for n in names if id(n) in ann_ids} - code


def split(text: str) -> tuple[str, str, dict[str, list[tuple[str, ast.stmt]]], str]:
    """(docstring, header imports, module -> [(source, node)], the pipeline's last block)."""
    lines = text.splitlines(keepends=True)
    tree = ast.parse(text)
    body = tree.body
    doc = ast.get_docstring(tree) or ""
    imports = [n for n in body if isinstance(n, (ast.Import, ast.ImportFrom))]
    header = "".join(lines[imports[0].lineno - 1:imports[-1].end_lineno])
    mods: dict[str, list[tuple[str, ast.stmt]]] = {m: [] for m in ORDER}
    tail: list[str] = []
    block, prev_end = "registry", imports[-1].end_lineno
    for node in body:
        if node in imports or (isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)):
            continue
        start = node.lineno - 1 - len(getattr(node, "decorator_list", []) or [])
        if getattr(node, "decorator_list", None):
            start = node.decorator_list[0].lineno - 1
        chunk_lines = lines[prev_end:start]
        for ln in chunk_lines:
            m = BANNER.match(ln.strip())
            if m:
                block = m.group(1).strip()
        src = "".join(chunk_lines) + "".join(lines[start:node.end_lineno])
        prev_end = node.end_lineno
        if block == "the pipeline":
            tail.append(src)
            continue
        names = _defined(node)
        mod = "shared" if names and all(n in SHARED for n in names) else BLOCKS.get(block, block)
        mods[mod].append((src, node))
    return doc, header, mods, "".join(tail)


def _strip_banners_from_shared(src: str) -> str:
    return "".join(ln for ln in src.splitlines(keepends=True) if not BANNER.match(ln.strip()))


def _imports_used(header: str, code: str) -> str:
    """The import statements of ``header`` cut to the names ``code`` reads."""
    used = {n.id for n in ast.walk(ast.parse(code)) if isinstance(n, ast.Name)}
    out = []
    for node in ast.parse(header).body:
        if isinstance(node, ast.ImportFrom) and node.module == "__future__":
            out.append(ast.unparse(node))
            continue
        assert isinstance(node, (ast.Import, ast.ImportFrom))
        node.names = [a for a in node.names if (a.asname or a.name).split(".")[0] in used]
        if node.names:
            out.append(ast.unparse(node))
    return "\n".join(out) + "\n"


def _typed_ctx(text: str) -> str:
    """Adapters' ``ctx: Any`` -> ``ctx: ItemContext`` (a map stage's function) or ``StageContext``."""
    kinds = {fn: kind for kind, fn in re.findall(r"\b(MapStage|Stage)\(\s*\"\w+\",\s*(\w+)", text)}
    used = set()

    def sub(mt: re.Match) -> str:
        kind = kinds.get(mt.group(1))
        if kind is None:
            return mt.group(0)
        name = "ItemContext" if kind == "MapStage" else "StageContext"
        used.add(name)
        return mt.group(0).replace("ctx: Any)", f"ctx: {name})")

    text = re.sub(r"^def (run_\w+)\([^)]*ctx: Any\)", sub, text, flags=re.M)
    if used:
        imp = f"from gcvd_flow.pipeline.context import {', '.join(sorted(used))}\n"
        text = text.replace("from gcvd_flow.engine.dag import", imp + "from gcvd_flow.engine.dag import", 1)
    return text


def _typed_sections(text: str) -> str:
    """``XParams = section("x", Settings)`` -> mypy reads ``XParams`` (the adapters' annotation) as the
    settings dataclass, whose fields the section has (section_from_dataclass); at run time the section."""
    return re.sub(r'^(\w+Params) = section\(("\w+"), ([\w.]+)\)$',
                  r"if typing.TYPE_CHECKING:  # mypy: the section's fields are the dataclass's\n    \1 = \3\n"
                  r"else:\n    \1 = section(\2, \3)", text, flags=re.M)


def write(doc: str, header: str, mods: dict[str, list[tuple[str, ast.stmt]]], tail: str) -> list[Path]:
    where = {n: m for m in ORDER for _, node in mods[m] for n in _defined(node)}
    clash = sorted(set(where) & set(ORDER))
    if clash:
        raise SystemExit(f"names {clash} would hide the modules of the same name in gcvd_flow.pipeline")
    written = []
    PKG.mkdir(exist_ok=True)
    for m in ORDER:
        used: set[str] = set()
        ann_only: set[str] = set()
        for _, node in mods[m]:
            u, a = _used(node)
            used |= u
            ann_only |= a
        own = {n for _, node in mods[m] for n in _defined(node)}
        earlier: dict[str, list[str]] = {}
        later: dict[str, list[str]] = {}  # annotations only: a section model of a later block
        for n in sorted(used - own):
            if n in where:
                if ORDER.index(where[n]) > ORDER.index(m) and n not in ann_only:
                    raise SystemExit(f"{m}.py reads {n} of the later module {where[n]}.py: add it to SHARED or move it")
                (earlier if ORDER.index(where[n]) < ORDER.index(m) else later).setdefault(where[n], []).append(n)
        out = [f'"""{DOCS[m]}"""\n\n', header, "\n"]
        for k in ORDER:
            if k in earlier:
                out.append(f"from gcvd_flow.pipeline.{k} import {', '.join(earlier[k])}\n")
        i = ORDER.index(m)
        if i > ORDER.index("frontend") and ORDER[i - 1] not in earlier:  # stages declared in module order
            out.append(f"import gcvd_flow.pipeline.{ORDER[i - 1]}  # noqa: F401  (its stages are declared before these)\n")
        if later:
            out.append("\nif typing.TYPE_CHECKING:\n")
            for k in ORDER:
                if k in later:
                    out.append(f"    from gcvd_flow.pipeline.{k} import {', '.join(later[k])}\n")
        chunks = [src if m != "shared" else _strip_banners_from_shared(src) for src, _ in mods[m]]
        text = _typed_sections(_typed_ctx("".join(out) + "\n" + "".join(chunks).lstrip("\n")))
        if m == "registry":  # pickles name the section models where the package re-exports them
            text = text.replace("__module__=__name__", '__module__="gcvd_flow.pipeline"')
        path = PKG / f"{m}.py"
        path.write_text(text.rstrip("\n") + "\n")
        written.append(path)
    init = [f'"""{doc}\n\nThe blocks are modules of this package (declared in this order: {", ".join(ORDER[2:])});\n'
            'gcvd_flow.pipeline.<name> is every name of every block, as when this was one file."""\n\n',
            _imports_used(header, tail), "\n"]
    for m in ORDER:
        names = [n for _, node in mods[m] for n in _defined(node)]
        out_names = ", ".join(f"{n} as {n}" for n in names)
        init.append(f"from gcvd_flow.pipeline.{m} import {out_names}\n")
    pkgs = next((p for p in ('packages=("gcvd_flow.stages", "gcvd_flow.pipeline"),\n',
                             'packages=("stages", "gcvd_flow.pipeline"),\n') if p in tail), None)  # before tools/relayout.py
    assert pkgs is not None, "the pipeline's packages changed: update tools/split_pipeline.py"
    tail = tail.replace(pkgs, pkgs + '    # the blocks\' modules: their functions and classes enter a stage\'s key one by one\n'
                                     '    adapters=("gcvd_flow.pipeline",),\n')
    init.append("\n" + tail.lstrip("\n"))
    path = PKG / "__init__.py"
    path.write_text("".join(init).rstrip("\n") + "\n")
    written.append(path)
    return written


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", default=str(ROOT / "gcvd_flow" / "pipeline.py"))
    ap.add_argument("--keep", action="store_true", help="keep the source file (default: git rm it)")
    a = ap.parse_args()
    src = Path(a.source)
    parts = split(src.read_text())
    if not a.keep and src.resolve() == (ROOT / "gcvd_flow" / "pipeline.py").resolve():
        src.unlink()
    files = write(*parts)
    ruff = [sys.executable, "-m", "ruff"]
    for args in (["check", "--fix", "--select", "F401,I", "--unsafe-fixes"], ["check", "--fix"]):
        subprocess.run(ruff + args + [str(f) for f in files], cwd=ROOT, check=False)
    print("wrote " + ", ".join(str(f.relative_to(ROOT)) for f in files))
    return 0


if __name__ == "__main__":
    sys.exit(main())
