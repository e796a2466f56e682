"""How a stage declares its parameters: a frozen dataclass per stage (in the ``params`` module of
its sub-package), each field made with :func:`param`. The pipeline derives the stage's config
section (``--set section.key=value``) from it (``gcvd_flow.pipeline.section_from_dataclass``), so
a field's name, type, default, description and constraints are written once, here in stages/,
and function defaults read the same class attributes (``KeyframesSettings.delta``).

``param(default, description, **constraints)``: ``constraints`` are pydantic-style (``ge``,
``gt``, ``le``, ``json_schema_extra=WEIGHTS_FILE`` for a local file whose content enters the cache
key) plus ``validator``: a function value -> value (raise ValueError with a message naming the
key) run when the config is built. A dataclass may define ``check(self)`` (raise ValueError) for
rules across fields (e.g. a backend that needs a weights file).
"""

from __future__ import annotations

from dataclasses import field
from typing import Any

WEIGHTS_FILE = {"file": True}  # a path parameter: its content digest, not the path, enters keys
USER_DIR = {"dir": True}  # a folder parameter: its files' names and contents, not the path, enter keys


def param(default: Any, description: str = "", **constraints: Any) -> Any:
    """A dataclass field with a config description and pydantic-style constraints."""
    md: dict[str, Any] = dict(constraints)
    if description:
        md["description"] = description
    return field(default=default, metadata=md)
