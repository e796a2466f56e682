"""How a block declares itself: its config section (``--set section.key=value``, derived from the
stage's parameter dataclass) and its stage, in declaration order."""

from __future__ import annotations

import dataclasses
import typing
from typing import Any

from pydantic import Field, create_model, field_validator, model_validator

from gcvd_flow.engine.config import Section
from gcvd_flow.engine.dag import Stage

# What the blocks below declare, in order: the config sections (name -> model) and the stages.
# GCVDConfig and PIPELINE at the end are assembled from them, so adding a stage is one block.
_SECTIONS: dict[str, type[Section]] = {}
_STAGES: list[Stage] = []


def config_section(name: str):
    """Class decorator (or call on a model): ``--set NAME.key=value`` configures this model."""
    def register(model: type[Section]) -> type[Section]:
        _SECTIONS[name] = model
        return model
    return register


def declare(stage: Stage) -> Stage:
    """Add a stage to the pipeline (stages run in the order they are declared)."""
    _STAGES.append(stage)
    return stage


def section_from_dataclass(cls: type, name: str) -> type[Section]:
    """A config section (pydantic, ``Section``) with the fields of a stage's parameter dataclass
    (``stages/params.py``): same names, types and defaults; each field's ``metadata`` gives its
    description and constraints (``ge``, ``gt``, ...; ``validator``: value -> value, run as a
    field validator), and the class's ``check(self)`` runs on the whole section. The parameters
    are declared only there."""
    hints = typing.get_type_hints(cls)
    fields: dict[str, Any] = {}
    validators: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        md = dict(f.metadata)
        check = md.pop("validator", None)
        fields[f.name] = (hints[f.name], Field(f.default, **md))
        if check is not None:
            validators[f"_check_{f.name}"] = field_validator(f.name)(_field_check(check))
    if hasattr(cls, "check"):
        validators["_check"] = model_validator(mode="after")(_section_check(cls.check))
    return create_model(name, __base__=Section, __module__="gcvd_flow.pipeline", __doc__=cls.__doc__,
                        __validators__=validators, **fields)


def _field_check(check: Any) -> Any:
    def run(cls: Any, v: Any) -> Any:
        return check(v)
    return run


def _section_check(check: Any) -> Any:
    def run(self: Any) -> Any:
        check(self)  # reads the section's fields as the dataclass's attributes
        return self
    return run


_Settings = typing.TypeVar("_Settings")


def section(name: str, cls: type[_Settings]) -> type[_Settings]:
    """``--set NAME.key=value`` configures the section derived from the dataclass ``cls``. At run
    time a pydantic ``Section``; typed as ``cls`` because it has exactly its fields (names, types,
    defaults), so mypy checks every adapter's reads against the dataclass. Adapters annotate their
    settings with the dataclass (a variable is not a type to mypy)."""
    sec = config_section(name)(section_from_dataclass(cls, "".join(w.title() for w in name.split("_")) + "Params"))
    return typing.cast("type[_Settings]", sec)
