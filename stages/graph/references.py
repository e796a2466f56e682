"""Which other frames (or adjacent-pair flows) each frame of an N-frame clip reads: the index
arithmetic behind the pipeline's per-item inputs (``gcvd_flow.pipeline``'s ``items`` functions).
Pure functions of (frame index i, clip length n, parameters); frame indices are positions in the
ingested clip (0 .. n-1), flow index k is the adjacent pair (k, k+1).

A map stage's items are cached by exactly the pieces they read, so these rules decide what a
trimmed or extended clip re-uses: each is written so that an existing frame's references do not
change when frames are appended (once the clip is long enough), except where noted.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

FarPair = tuple[int, int, str, float]  # (a, b) with a < b, DIS preset, forward-backward threshold px


def prior_references(i: int, n: int, span: int) -> list[int]:
    """Frame i's prior references: ``span`` and ``span // 2`` (at least 1) frames back, forward
    for the first frames (i < span and in the clip's first half), clamped to the clip, never i."""
    step = -1 if (i >= span or i >= n - 1 - i) else 1
    js = [min(max(i + step * k, 0), n - 1) for k in (span, max(1, span // 2))]
    return [j for j in js if j != i]


def offset_references(i: int, n: int, offsets: Iterable[int]) -> list[int]:
    """Frames i + offset (offsets signed, 0 skipped) that lie in the clip, in ``offsets`` order."""
    return [i + off for off in offsets if 0 <= i + off < n and off != 0]


def symmetric_references(i: int, n: int, distances: Iterable[int]) -> list[int]:
    """Frames i - k and i + k for each distance k (in that order) that lie in the clip."""
    return [j for k in distances for j in (i - k, i + k) if 0 <= j < n]


def flow_chain(i: int, n: int, span: int) -> tuple[str, list[int]]:
    """Adjacent flows from frame i toward a reference ``span`` frames away: ("bwd", [i-1, i-2,
    ...]) backward, or ("fwd", [i, i+1, ...]) for the first ``span`` frames (while in the clip's
    first half); at most ``span`` flows, clamped to the clip. Existing frames never read later
    flows once the clip has 2 * span frames, so extending a clip only adds items."""
    if i >= span or i >= n - 1 - i:
        return "bwd", [i - 1 - k for k in range(min(span, i))]
    return "fwd", [i + k for k in range(min(span, n - 1 - i))]


def window(i: int, n: int, radius: int) -> tuple[int, int]:
    """The frames [lo, hi] (inclusive) within ``radius`` of frame i, clamped to the clip."""
    return max(0, i - radius), min(n - 1, i + radius)


def far_pair(i: int, j: int, preset: str, fb_thresh: float) -> FarPair:
    """The unordered pair of frames i, j with the flow settings it is computed with."""
    return (min(i, j), max(i, j), preset, float(fb_thresh))


def far_pairs(n: int, consumers: Sequence[tuple[Callable[[int], list[int]], str, float]]) -> list[FarPair]:
    """The sorted union of the direct-flow pairs several consumers ask for: each consumer is
    (frame i -> its reference frames, DIS preset, forward-backward threshold px); pairs asked for
    twice with the same settings are computed once."""
    pairs: set[FarPair] = set()
    for i in range(n):
        for refs, preset, fb_thresh in consumers:
            pairs.update(far_pair(i, j, preset, fb_thresh) for j in refs(i))
    return sorted(pairs)
