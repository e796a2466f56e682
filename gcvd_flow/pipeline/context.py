"""What an adapter gets as ``ctx`` (the engine's gcvd_flow.engine.executors.ItemContext for a map
stage's item, gcvd_flow.engine.runner.StageContext for a whole stage), as types the adapters name:
``run_<stage>(inputs, params, ctx: ItemContext | StageContext)``."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import Any, Protocol


class ItemContext(Protocol):
    """A map stage's item: its stage's name, the run's seed, a logger and the stage's resources
    (``resource(name)``: the opened model of ``MapStage(resources={name: opener})``)."""

    stage: str
    seed: int

    def log(self, msg: str) -> None: ...

    def resource(self, name: str) -> Any: ...


class StageContext(ItemContext, Protocol):
    """A whole stage: an item's context plus its checkpointer (None: no checkpoints), ``map`` to
    spread independent calls over the run's workers (``fn`` module-level, arguments picklable,
    results in argument order) and ``put`` to store part of the output before it returns."""

    checkpointer: Any

    def map(self, fn: Callable[[Any], Any], args: Iterable[Any]) -> Iterator[Any]: ...

    def put(self, value: Any) -> Any: ...
