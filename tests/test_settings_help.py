"""Issue 39 item 2: a setting's help (``--set`` / ``gcvd-flow config``) says what the setting does;
the measurements behind its default live in docs/benchmarks.md ("Why the defaults are what they
are"), where they carry a command and a date. Help strings with a before -> after figure, a
metric name, a date or a log path fail here (they went stale within days when they lived there)."""

from __future__ import annotations

import dataclasses
import importlib
import pkgutil
import re

import gcvd_flow.stages as stages_pkg

MEASUREMENT = re.compile(r"->|\b(ATE|AbsRel|RPE|IoU)\b|\b20\d\d-\d\d-\d\d\b|\bmeasured\b|docs/log/|\buntil\b"
                         r"|\bsince 20\d\d")


def _settings_classes() -> list[type]:
    out = []
    for info in pkgutil.walk_packages(stages_pkg.__path__, "gcvd_flow.stages."):
        if info.name.rsplit(".", 1)[-1] != "params":
            continue
        mod = importlib.import_module(info.name)
        out += [c for c in vars(mod).values()
                if isinstance(c, type) and dataclasses.is_dataclass(c) and c.__module__ == info.name]
    return out


def test_the_rule_catches_what_used_to_be_there():
    for text in ("blended as first built, ICL 0.048 -> 0.060", "8 until 2026-11-25", "KITTI 07 ATE 1.90 m",
                 "(docs/log/2026-11-28-cost2.md)", "2.0 measured in the log", "since 2026-11-28"):
        assert MEASUREMENT.search(text), text
    for text in ("on unless >= 80 % of the pairs' translations are within 30 degrees", "0 = off",
                 "Cauchy scale of the reprojection error, px", "(1 - (c / splat_keep)^2)"):
        assert not MEASUREMENT.search(text), text


def test_no_setting_help_carries_a_measurement():
    classes = _settings_classes()
    assert len(classes) >= 15, [c.__name__ for c in classes]  # every stage's settings were found
    bad = [f"{c.__name__}.{f.name}: ...{m.group(0)}... in {f.metadata['description'][:90]!r}"
           for c in classes for f in dataclasses.fields(c)
           if (m := MEASUREMENT.search(f.metadata.get("description", "")))]
    assert not bad, "move the figure to docs/benchmarks.md ('Why the defaults are what they are'):\n" + "\n".join(bad)
