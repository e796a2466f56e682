"""Every third-party module the product imports is a declared dependency (issue 29).

`make setup` installs the test requirements too, which pulled in Pillow and matplotlib and so hid
that pyproject.toml did not declare them: a plain `pip install .` then failed in `run` ("No module
named 'PIL'") and in `report`. This test fails fast on such an import; `.ci/check-install` (run
by .ci/run) proves it end to end in a fresh venv.
"""

from __future__ import annotations

import ast
import re
import shutil
import subprocess
import sys
import tomllib
import zipfile
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OWN = {"gcvd_flow"}


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def declared() -> set[str]:
    """Distribution names of pyproject's [project] dependencies (normalised, no extras)."""
    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return {_norm(re.split(r"[\s\[<>=!~;]", d, maxsplit=1)[0]) for d in doc["project"]["dependencies"]}


def imported_modules(*dirs: str) -> dict[str, list[str]]:
    """Top-level third-party module -> files importing it (absolute imports, any depth)."""
    found: dict[str, list[str]] = {}
    for d in dirs:
        for f in sorted((ROOT / d).rglob("*.py")):
            for node in ast.walk(ast.parse(f.read_text(), str(f))):
                names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                         [node.module] if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module
                         else [])
                for n in names:
                    top = n.split(".")[0]
                    if top not in OWN and top not in sys.stdlib_module_names:
                        found.setdefault(top, []).append(str(f.relative_to(ROOT)))
    return found


def test_every_third_party_import_is_a_declared_dependency():
    deps = declared()
    dists = metadata.packages_distributions()
    missing = []
    for mod, files in sorted(imported_modules("gcvd_flow", "stages").items()):
        providers = {_norm(p) for p in dists.get(mod, [])}
        if not providers & deps:
            missing.append(f"{mod} (from {', '.join(sorted(providers)) or 'no installed distribution'}; "
                           f"imported in {files[0]})")
    assert not missing, "imported but not in pyproject.toml's dependencies: " + "; ".join(missing)


def test_the_check_finds_an_undeclared_import():
    """The mapping the test relies on: PIL is Pillow's, cv2 opencv's, gtsam_unstable gtsam's."""
    dists = metadata.packages_distributions()
    assert "pillow" in {_norm(p) for p in dists["PIL"]}
    assert "opencv-python-headless" in {_norm(p) for p in dists["cv2"]}
    assert {"pillow", "matplotlib"} <= declared()
    assert {"PIL", "matplotlib", "numpy", "torch"} <= set(imported_modules("gcvd_flow", "stages"))


def test_requirements_txt_pins_what_pyproject_declares():
    """requirements.txt (what `make setup` installs) holds the same pins as pyproject.toml."""
    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    pins = {_norm(d.split("==")[0]): d.split("==")[1] for d in doc["project"]["dependencies"]}
    req = {}
    for line in (ROOT / "requirements.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if "==" in line:
            name, ver = line.split("==")
            req[_norm(name)] = ver.strip()
    assert {k: req.get(k) for k in pins} == pins


def test_one_png_writer_for_the_cache_and_the_exports():
    """io.formats.png_bytes (every export's PNG) writes what the artifact store writes (uint8),
    and uint16 depth / confidence PNGs with the same codec read back exactly with OpenCV."""
    import cv2
    import numpy as np

    from gcvd_flow.engine.artifacts import png_bytes as store_png
    from gcvd_flow.io.formats import png_bytes

    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
    grey = rng.integers(0, 2, (20, 30), dtype=np.uint8)
    assert png_bytes(rgb) == store_png(rgb) and png_bytes(grey) == store_png(grey)
    d16 = rng.integers(0, 65536, (20, 30), dtype=np.uint16)
    back = cv2.imdecode(np.frombuffer(png_bytes(d16), np.uint8), cv2.IMREAD_UNCHANGED)
    assert back.dtype == np.uint16 and np.array_equal(back, d16)
    rgb_back = cv2.imdecode(np.frombuffer(png_bytes(rgb), np.uint8), cv2.IMREAD_COLOR)
    assert np.array_equal(rgb_back[..., ::-1], rgb)


def test_a_missing_module_is_one_line_naming_it(monkeypatch, capsys, tmp_path):
    """A package missing from the installation: one line naming the module, exit 2, no traceback."""
    import gcvd_flow.report
    from gcvd_flow.cli import main

    def missing(*a, **k):
        raise ModuleNotFoundError("No module named 'matplotlib'", name="matplotlib")

    monkeypatch.setattr(gcvd_flow.report, "write_report_doc", missing)
    assert main(["report", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'matplotlib' is not installed" in err[0]


def _wheel(tmp_path: Path) -> Path:
    """The wheel `pip install .` installs, built from a copy of the checkout (symlinks kept)."""
    src = tmp_path / "src"
    skip = shutil.ignore_patterns(".git", ".venv*", "build", "*.egg-info", "__pycache__", "out", "demo-out", "bench-out")
    shutil.copytree(ROOT, src, symlinks=True, ignore=skip)
    p = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
                        "--disable-pip-version-check", "-w", str(tmp_path / "dist"), str(src)],
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    (whl,) = (tmp_path / "dist").glob("gcvd_flow-*.whl")
    return whl


def test_pip_install_installs_one_top_level_package_and_no_stages_module(tmp_path):
    """`pip install .` puts gcvd_flow alone into site-packages: the card's top-level stages/ and
    artifacts_schema/ folders are gcvd_flow.stages and gcvd_flow.artifacts_schema there, so another
    project's `stages` module cannot collide with ours (issue 39)."""
    whl = _wheel(tmp_path)
    names = zipfile.ZipFile(whl).namelist()
    assert {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")} == {"gcvd_flow"}
    for f in ("gcvd_flow/stages/__init__.py", "gcvd_flow/stages/optimize/params.py",
              "gcvd_flow/artifacts_schema/__init__.py", "gcvd_flow/artifacts_schema/depth.json"):
        assert f in names, f
    target = tmp_path / "site"
    p = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--disable-pip-version-check",
                        "--target", str(target), str(whl)], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    # no site-packages (-S: this venv's editable install maps `stages` to a checkout), outside the checkout
    code = (f"import sys; sys.path[:0] = [{str(target)!r}]\n"
            "import gcvd_flow.stages, gcvd_flow.artifacts_schema as a\n"
            "assert (a.SCHEMA_DIR / 'depth.json').is_file()\n"
            "for name in ('stages', 'artifacts_schema'):\n"
            "    try:\n"
            "        __import__(name)\n"
            "    except ModuleNotFoundError:\n"
            "        print('no', name)\n")
    p = subprocess.run([sys.executable, "-S", "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path,
                       env={"PATH": "/usr/bin:/bin"})
    assert p.returncode == 0, p.stderr
    assert p.stdout.split("\n")[:2] == ["no stages", "no artifacts_schema"], p.stdout


def test_the_checkout_maps_the_card_folders_into_the_package():
    """In the checkout gcvd_flow/stages and gcvd_flow/artifacts_schema are the top-level folders
    (what the wheel installs), and no code imports them by their old top-level names."""
    for name in ("stages", "artifacts_schema"):
        link = ROOT / "gcvd_flow" / name
        assert link.is_symlink() and link.resolve() == (ROOT / name).resolve(), link
    old = [f"{f.relative_to(ROOT)}: {n}" for d in ("gcvd_flow", "stages", "tests", "benchmarks", "tools")
           for f in sorted((ROOT / d).rglob("*.py")) if "gcvd_flow/stages" not in str(f.relative_to(ROOT))
           for node in ast.walk(ast.parse(f.read_text(), str(f)))
           for n in ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module] if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module else [])
           if n.split(".")[0] in ("stages", "artifacts_schema")]
    assert not old, "imports of the old top-level names (run tools/relayout.py): " + "; ".join(old)
