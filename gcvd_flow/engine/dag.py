"""Stage declarations and the pipeline graph.

Two kinds of stage:

* :class:`Stage` — a whole-input stage: ``fn(inputs, params, ctx) -> value``; ``inputs`` maps
  each dependency's name to its value (for a map dependency a :class:`MapValue`).
* :class:`MapStage` — maps ``fn(item_inputs, params, ctx) -> value`` over items (frames,
  pairs). ``items(view, params)`` says which upstream pieces each item reads, as references;
  every item is cached by the digests of exactly those pieces, so trimming, extending or
  striding a clip re-uses every item whose own inputs are unchanged, and a crash resumes at
  the first missing item.

References an item can hold: :class:`ItemRef` (one item of a map stage), :class:`PartRef`
(a sub-tree of a whole stage's output or a map stage's summary, e.g. one depth map of a list),
:class:`ExternalRef` (a piece of the run's input, e.g. a video frame, named by a digest
of its source bytes and loaded by a picklable loader), :class:`Const` (a small JSON value) —
or a *list* of references (e.g. "the chain of flows toward the reference frame"), which the
stage function receives as a list of values. The input names of an item are the parameter
names the stage function reads; there is nothing to parse on either side.

Resources: a stage may declare ``resources={"model": open_fn}``; ``ctx.resource("model")`` returns
``open_fn(params)``, opened once per worker process and parameter set and shared by the items
that worker computes (model weights, say). The engine owns that cache; stage code keeps none.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Protocol, Sequence

import numpy as np

from gcvd_flow.engine.errors import UsageError


class PipelineError(ValueError):
    pass


# ------------------------------------------------------------------------------ references


def stage_name(stage: str | Stage) -> str:
    """A stage's name from its declaration (the object ``declare`` returned) or the name itself."""
    return stage if isinstance(stage, str) else stage.name


@dataclass(frozen=True, init=False)
class ItemRef:
    """Item ``index`` of a map stage (given as its declaration or its name; held by name)."""

    stage: str
    index: int

    def __init__(self, stage: str | Stage, index: int) -> None:
        object.__setattr__(self, "stage", stage_name(stage))
        object.__setattr__(self, "index", index)


@dataclass(frozen=True, init=False)
class PartRef:
    """A sub-tree of a whole stage's value (``path`` of keys / indices); () is the whole. The
    stage is given as its declaration or its name (held by name)."""

    stage: str
    path: tuple = ()
    summary: bool = False  # True: a sub-tree of a map stage's summary instead

    def __init__(self, stage: str | Stage, path: tuple = (), summary: bool = False) -> None:
        object.__setattr__(self, "stage", stage_name(stage))
        object.__setattr__(self, "path", tuple(path))
        object.__setattr__(self, "summary", summary)


@dataclass(frozen=True)
class ExternalRef:
    digest: str  # content digest of the source piece (e.g. file bytes, or video digest + index)
    loader: Any  # picklable callable () -> value


@dataclass(frozen=True)
class Const:
    """A small JSON-able value handed to an item (keyed by its canonical encoding)."""

    value: Any


Ref = ItemRef | PartRef | ExternalRef | Const
ItemInputs = dict[str, "Ref | list[Ref]"]  # what an ``items`` function returns per item


# ------------------------------------------------------------------------------ stages


@dataclass
class Stage:
    name: str
    fn: Callable[..., Any]
    # the stages this one reads, by declaration (the objects ``declare`` returned, as hloc passes
    # handles) or by name; held as names (``__post_init__``: str), hence Any for mypy
    deps: tuple[Any, ...] = ()
    params: str | tuple[str, ...] | None = None  # config section(s) of this stage's parameters
    kind: str = "generic"  # artifact schema kind of the output
    version: int = 0  # bump to force invalidation without a code change
    description: str = ""
    # Declares a non-deterministic op for the record; keys do not depend on it.
    nondeterministic: str | None = None
    uses_seed: bool = False  # the run's seed is part of the key
    # name -> picklable ``open(params) -> object``; see the module docstring
    resources: dict[str, Callable[[Any], Any]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.deps = tuple(stage_name(d) for d in self.deps)

    @property
    def is_map(self) -> bool:
        return False


@dataclass
class MapStage(Stage):
    items: Callable[["DepsView", Any], list[ItemInputs]] = None  # type: ignore[assignment]
    summary: Callable[["DepsView", Any], Any] | None = None
    summary_kind: str | None = None  # schema of the summary (e.g. "camera")
    # Parameters that choose *which* items exist (start/end/stride) rather than how one is
    # computed: they are left out of item keys so that a trimmed clip re-uses its items.
    selection_params: tuple[str, ...] = ()
    # Items that read the same inputs (a window of frames around each item): each worker keeps
    # what it loaded for this stage, by digest, and hands the next item that reads it the same
    # value, read only (loaded, verified and decoded once per worker rather than once per item;
    # executors.SharedInputs). The stage function must not modify its inputs.
    share_inputs: bool = False

    @property
    def is_map(self) -> bool:
        return True


@dataclass
class Pipeline:
    """The stage graph plus what the engine must know about the code behind it.

    ``packages``: modules (or package prefixes) whose source enters code fingerprints;
    ``adapters``: those of them (names or prefixes) holding the stage functions and their helpers:
    their functions and classes enter a stage's fingerprint one by one, as those of the stage
    function's own module do (adapters split over several modules keep keys as fine as one module's);
    ``numeric_libraries``: (label, (distribution, alternatives...)) whose versions enter every key;
    ``numeric_settings``: further (name, value) pairs that change numerics (device, dtype);
    ``worker_init``: picklable callable run once in every worker process (e.g. to pin the
    thread counts of the numeric libraries the stages use).
    """

    stages: list[Stage] = field(default_factory=list)
    packages: tuple[str, ...] = ()
    adapters: tuple[str, ...] = ()
    numeric_libraries: tuple[tuple[str, tuple[str, ...]], ...] = ()
    numeric_settings: tuple[tuple[str, Any], ...] = ()
    worker_init: Callable[[], None] | None = None

    def __post_init__(self) -> None:
        seen: set[str] = set()
        for s in self.stages:
            if s.name in seen:
                raise PipelineError(f"duplicate stage name {s.name!r}")
            for d in s.deps:
                if d not in seen:
                    raise PipelineError(f"stage {s.name!r} depends on {d!r}, which is not declared before it")
            if isinstance(s, MapStage) and s.items is None:
                raise PipelineError(f"map stage {s.name!r} has no items function")
            seen.add(s.name)

    def names(self) -> list[str]:
        return [s.name for s in self.stages]

    def numeric_env(self) -> dict[str, Any]:
        from gcvd_flow.engine.keys import numeric_env

        return numeric_env(self.numeric_libraries, self.numeric_settings)

    def get(self, stage: str | Stage) -> Stage:
        name = stage_name(stage)
        for s in self.stages:
            if s.name == name:
                return s
        raise UsageError(f"unknown stage {name!r}; stages: {', '.join(self.names())}")

    def descendants(self, name: str) -> list[str]:
        out: set[str] = {name}
        for s in self.stages:
            if any(d in out for d in s.deps):
                out.add(s.name)
        return [s.name for s in self.stages if s.name in out]

    def upto(self, name: str | None) -> list[Stage]:
        """The stages needed to produce ``name`` (all when None), in order."""
        if name is None:
            return list(self.stages)
        need = {name}
        for s in reversed(self.stages):
            if s.name in need:
                need.update(s.deps)
        return [s for s in self.stages if s.name in need]


# ------------------------------------------------------------------------------ values


class DepsView(Protocol):
    """What an ``items`` / ``summary`` function sees of its dependencies and of the input."""

    source: Any

    def len(self, stage: str | Stage) -> int: ...

    def value(self, stage: str | Stage) -> Any: ...

    def summary(self, stage: str | Stage) -> Any: ...


class MapValue(Sequence):
    """A map stage's output as seen by a whole stage: lazily loaded items plus the summary.

    ``field(name)`` views one field of every item as a lazily stacked array, ``recent(keep)``
    keeps the last ``keep`` decoded items: both let a stage over a long clip hold a window of
    it instead of the whole clip.
    """

    def __init__(self, loader: Callable[[int], Any], n: int, summary: Any):
        self._loader = loader
        self._n = n
        self.summary = summary

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self._loader(j) for j in range(*i.indices(self._n))]
        if i < 0:
            i += self._n
        if not 0 <= i < self._n:
            raise IndexError(i)
        return self._loader(i)

    def field(self, name: str) -> "LazyStack":
        return LazyStack(self, name)

    def recent(self, keep: int) -> "RecentItems":
        return RecentItems(self, keep)


class LazyStack:
    """One field of a map stage's items as a lazily loaded (N, ...) array: ``x[a:b]`` and
    ``x[[i, j]]`` load and stack just those items, ``x[i]`` loads one."""

    def __init__(self, items: Sequence, name: str):
        self._items, self._name = items, name

    def __len__(self) -> int:
        return len(self._items)

    def _one(self, i: int) -> np.ndarray:
        return np.asarray(self._items[i][self._name])

    def __getitem__(self, i: Any) -> np.ndarray:
        if isinstance(i, slice):
            return np.stack([self._one(j) for j in range(*i.indices(len(self._items)))])
        if isinstance(i, (list, tuple, np.ndarray)):
            return np.stack([self._one(int(j)) for j in i])
        return self._one(int(i))


class RecentItems:
    """``x[i]`` loads item i and keeps the ``keep`` most recently used items decoded (a window
    that re-reads its items does not decode them again)."""

    def __init__(self, items: Sequence, keep: int):
        self._items, self._keep = items, keep
        self._cache: dict[int, Any] = {}

    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, i: int) -> Any:
        hit = self._cache.pop(i, None)
        if hit is None:
            hit = self._items[i]
        self._cache[i] = hit  # most recently used last
        while len(self._cache) > self._keep:
            self._cache.pop(next(iter(self._cache)))
        return hit
