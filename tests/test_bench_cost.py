"""benchmarks/bench_cost.py: the order the checkouts run in, round by round."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from conftest import ROOT


def test_rounds_alternate_the_order_of_the_checkouts():
    """ABC, CBA, ABC: no checkout always runs last (a machine slowing over a round fell on "this")."""
    spec = importlib.util.spec_from_file_location("bench_cost", ROOT / "benchmarks" / "bench_cost.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    trees = {"ref": Path("/r"), "also0": Path("/a"), "this": Path("/t")}
    names = [[t for t, _ in mod.round_order(trees, r)] for r in range(3)]
    assert names == [["ref", "also0", "this"], ["this", "also0", "ref"], ["ref", "also0", "this"]]
    assert dict(mod.round_order(trees, 1)) == trees
