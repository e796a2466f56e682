"""Rename the imports of the card's top-level folders to the one installed package (issue 39 item 4).

    python tools/relayout.py [PATH ...]     (default: the whole checkout)

The repository keeps ``stages/`` and ``artifacts_schema/`` at the top (the product card fixes them);
``pip install .`` installs them as ``gcvd_flow.stages`` and ``gcvd_flow.artifacts_schema`` (the
symlinks gcvd_flow/stages -> ../stages and gcvd_flow/artifacts_schema -> ../artifacts_schema make
the checkout the same package tree), so code imports them by those names only:

    from stages.x import y        ->  from gcvd_flow.stages.x import y
    import stages.x as y          ->  import gcvd_flow.stages.x as y
    import artifacts_schema       ->  from gcvd_flow import artifacts_schema
    "stages.x.y" (a dotted name in a string: lazy loaders, ruff settings)  ->  "gcvd_flow.stages.x.y"
    packages=("stages", ...)      ->  packages=("gcvd_flow.stages", ...)

Idempotent: re-run it after merging a branch that still says ``stages.``; it prints the files it
changed. Only Python, Markdown code and the pyproject are rewritten; prose that names the folder
(``stages/``) is left as it is.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OLD = ("stages", "artifacts_schema")
RULES = [
    (re.compile(r"^(\s*)from (stages|artifacts_schema)(?=[.\s])", re.M), r"\1from gcvd_flow.\2"),
    (re.compile(r"^(\s*)import (stages|artifacts_schema)\.(\S+) as ", re.M), r"\1import gcvd_flow.\2.\3 as "),
    (re.compile(r"^(\s*)import (stages|artifacts_schema)\s*$", re.M), r"\1from gcvd_flow import \2"),
    (re.compile(r"^(\s*)import (stages|artifacts_schema)(\s*#.*)$", re.M), r"\1from gcvd_flow import \2\3"),
]
CODE_RULES = [  # .py and pyproject only
    (re.compile(r"""(["'])(stages|artifacts_schema)\.(?=[A-Za-z_])"""), r"\1gcvd_flow.\2."),
    (re.compile(r"""packages=\((["'])stages\1"""), r'packages=(\1gcvd_flow.stages\1'),
    (re.compile(r'known-first-party = \["gcvd_flow", "stages", "artifacts_schema"\]'), 'known-first-party = ["gcvd_flow"]'),
]
BARE_IMPORT = re.compile(r"^\s*import (stages|artifacts_schema)(\.\S+)?\s*(#.*)?$", re.M)


def files(paths: list[str]) -> list[Path]:
    if paths:
        return [Path(p) for p in paths]
    out = [ROOT / "pyproject.toml", ROOT / "README.md"]
    for top in ("gcvd_flow", "stages", "artifacts_schema", "tests", "benchmarks", "tools", "docs", ".ci"):
        base = ROOT / top
        if not base.exists():
            continue
        for p in sorted(base.rglob("*")):
            if p.is_symlink() or any(q.is_symlink() for q in p.parents if ROOT in q.parents):
                continue  # gcvd_flow/stages -> ../stages: rewritten once, as stages/
            if p.is_file() and (p.suffix in (".py", ".md") or p.parent.name == ".ci"):
                out.append(p)
    return out


def rewrite(text: str, code: bool) -> str:
    for rx, sub in RULES + (CODE_RULES if code else []):
        text = rx.sub(sub, text)
    return text


def main(argv: list[str]) -> int:
    changed, left = [], []
    for p in files(argv):
        if p.name in ("relayout.py", "split_pipeline.py"):  # they spell the old names on purpose
            continue
        text = p.read_text(encoding="utf-8")
        new = rewrite(text, code=p.suffix in (".py", ".toml"))
        if new != text:
            p.write_text(new, encoding="utf-8")
            changed.append(str(p.relative_to(ROOT)))
        left += [f"{p.relative_to(ROOT)}: {m.group(0).strip()}" for m in BARE_IMPORT.finditer(new)]
    print("\n".join(changed) if changed else "nothing to rename")
    if left:
        print("left for a hand edit (a bare `import stages.x` used as stages.x.y):\n" + "\n".join(left), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
