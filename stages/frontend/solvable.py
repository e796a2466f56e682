"""Frames that leave nothing to solve: masked (``--masks``) almost entirely, or without texture
(a black or blank frame). Neither flow nor the photometric loss measures anything there, so a
depth the optimisation hands out for such a frame is its initial guess (1.0 everywhere), not a
measurement: the run marks it invalid (depth 0, confidence 0) and says so, and a clip with fewer
than two solvable frames is bad input. Pure numpy.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["MIN_KEPT_SHARE", "MIN_GREY_STD", "frame_problem", "unsolvable_frames"]

#: a frame the user's masks leave less than this share of is masked beyond solving
MIN_KEPT_SHARE = 0.05
#: grey levels (of 255): kept pixels varying less than this (std) have no texture to match
MIN_GREY_STD = 1.0


def frame_problem(image: np.ndarray, keep: np.ndarray | None = None) -> str | None:
    """Why frame ``image`` (uint8 (H, W, 3) or (H, W)) leaves nothing to solve, or None.
    ``keep``: the user's kept mask (H, W), 1 = not masked, None without --masks."""
    img = np.asarray(image, np.float32)
    grey = img.mean(axis=2) if img.ndim == 3 else img
    values = grey.ravel()
    if keep is not None:
        k = np.asarray(keep) > 0
        share = float(np.mean(k)) if k.size else 0.0
        if share < MIN_KEPT_SHARE:
            return f"masked: {100 * share:.1f} % of its pixels left (--masks; less than {100 * MIN_KEPT_SHARE:g} %)"
        values = grey[k]
    if values.size == 0 or float(np.std(values)) < MIN_GREY_STD:
        return "no texture (a black or blank frame)"
    return None


def unsolvable_frames(images: Sequence[np.ndarray], keeps: Sequence[np.ndarray] | None = None) -> list[tuple[int, str]]:
    """[(k, why)] for the frames of ``images`` (with their kept masks ``keeps``, or None) that
    leave nothing to solve (:func:`frame_problem`), in order."""
    out = []
    for k in range(len(images)):
        why = frame_problem(images[k], None if keeps is None else keeps[k])
        if why is not None:
            out.append((k, why))
    return out

