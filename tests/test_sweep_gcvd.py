"""Issue 30's GCVD case: a 3-value sweep of keyframes.delta on a 40-frame clip (128x96,
--profile fast) computes each flow item once, evaluates all three runs, `runs --json` lists
three rows whose only parameter is keyframes.delta, and `report DIR` writes an index page that
renders in headless Chromium (skipped when Chromium is absent, as in tests/test_report.py)."""

from __future__ import annotations

import html.parser
import json
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import cli, cli_json
from test_report import _chromium, _page_loads, _read_png, _shot

pytestmark = pytest.mark.slow  # a GCVD sweep (three runs of a 40-frame clip)

N_FRAMES = 40
DELTAS = ("0.05", "0.1", "0.15")


@pytest.fixture(scope="module")
def sweep(tmp_path_factory) -> dict:
    base = tmp_path_factory.mktemp("sweep")
    clip = base / "clip"
    cli("synth", str(clip), "--frames", str(N_FRAMES), "--size", "128x96", "--trajectory", "orbit", check=True)
    doc = cli_json("sweep", str(clip), "--out", str(base / "sw"), "--cache", str(base / "cache"),
                   "--profile", "fast", "--grid", f"keyframes.delta={','.join(DELTAS)}", "--gt", str(clip))
    return {"base": base, "clip": clip, "dir": base / "sw", "doc": doc}


def _executed(doc: dict, stage: str) -> list[int]:
    return [next(s["executed"] for s in r["stages"] if s["name"] == stage) for r in doc["runs"]]


def test_keyframe_sweep_shares_flow_and_evaluates_every_run(sweep):
    doc = sweep["doc"]
    assert [r["name"] for r in doc["runs"]] == [f"keyframes.delta={d}" for d in DELTAS] and doc["failed"] == 0
    for stage, n in (("ingest", N_FRAMES), ("flow", N_FRAMES - 1), ("masks", N_FRAMES), ("priors", N_FRAMES)):
        assert _executed(doc, stage) == [n, 0, 0], stage  # computed once, by the first run
    assert _executed(doc, "keyframes") == [1, 1, 1]
    kfs = []
    for r in doc["runs"]:
        m = json.loads((Path(r["out"]) / "metrics.json").read_text())
        assert r["metrics"] == m and m["frames"] == N_FRAMES and 0 < m["ate_rmse"] < 0.2 and "abs_rel" in m
        kfs.append(m["keyframes"])
    assert kfs[0] > kfs[2]  # a larger threshold, fewer keyframes: the parameter reached the stage
    runs = cli_json("runs", str(sweep["dir"]))
    assert len(runs["runs"]) == 3 and runs["params"] == ["keyframes.delta"]
    assert [r["params"] for r in runs["runs"]] == [{"keyframes.delta": float(d)} for d in DELTAS]
    assert all(r["metrics"]["ate_rmse"] == d["metrics"]["ate_rmse"] for r, d in zip(runs["runs"], doc["runs"]))


class _Refs(html.parser.HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.refs: list[tuple[str, str, str]] = []
        self.tags: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        self.refs += [(tag, k, v) for k, v in attrs if k in ("src", "href", "srcset", "data", "action") and v]


@pytest.fixture(scope="module")
def index(sweep) -> Path:
    doc = cli_json("report", str(sweep["dir"]))
    page = Path(doc["report"])
    assert page == sweep["dir"] / "index.html"
    return page


def test_index_page_links_each_run_report(sweep, index):
    text = index.read_text()
    p = _Refs()
    p.feed(text)
    assert "script" not in p.tags and "iframe" not in p.tags and "link" not in p.tags
    assert not re.search(r"\bon[a-z]+\s*=", text) and "content=\"default-src 'none'; img-src data:;" in text
    links = [v for t, k, v in p.refs if t == "a"]
    assert sorted(links) == sorted(f"keyframes.delta={d}/report.html" for d in DELTAS)
    for link in links:  # relative links to the runs' own reports, written beside them
        assert "<h2>Trajectory</h2>" in (index.parent / link).read_text()
    imgs = [v for t, k, v in p.refs if t == "img"]
    assert len(imgs) == 1 and imgs[0].startswith("data:image/png;base64,")  # one swept parameter, one plot
    table = text[text.index("id='runs'"):text.index("</table>", text.index("id='runs'"))]
    for r in sweep["doc"]["runs"]:
        assert f"{r['metrics']['ate_rmse']:.4g}" in table and r["name"] in table
    assert "<th>keyframes.delta</th>" in table and "<th>flow.preset</th>" not in table


def test_index_page_renders_in_chromium(index, tmp_path):
    exe = _chromium()
    full = tmp_path / "full.png"
    log = _shot(exe, index, full, tmp_path, "1200,1400")
    assert _page_loads(log, index) == []  # the links are not loaded; nothing else is referenced
    img = _read_png(full)
    assert img.std() > 20
    hidden = tmp_path / "no-plot.html"
    hidden.write_text(index.read_text().replace("</style>", "img.plot{visibility:hidden}</style>"))
    _shot(exe, hidden, tmp_path / "no-plot.png", tmp_path, "1200,1400")
    changed = np.any(np.abs(img.astype(int) - _read_png(tmp_path / "no-plot.png")) > 8, axis=-1)
    assert changed.sum() > 5_000, changed.sum()
    drawn = img[changed].astype(float)
    assert np.count_nonzero(drawn.max(1) - drawn.min(1) > 60) > 300  # coloured plot lines and markers
