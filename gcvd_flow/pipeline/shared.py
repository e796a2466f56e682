"""Helpers more than one block reads: the items of the masks and flow stages seen by a later stage,
the user's --masks files, and which reference frames priors and depth_fusion read."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from gcvd_flow.engine.errors import UsageError
from gcvd_flow.io.sources import Source
from gcvd_flow.stages.frontend import (
    ingest as ingest_mod,
    params as frontend_params,
    user_masks,
)
from gcvd_flow.stages.graph import references


def _undistort_of(cam: dict[str, Any]) -> list[Any] | None:
    """The ingest summary's lens as item input [intrinsics, coefficients, model] (None: pinhole)."""
    if "distortion" not in cam:
        return None
    return [cam["distortion_intrinsics"], cam["distortion"], cam.get("distortion_model", "OPENCV")]


# Direct DIS flows between frames further apart, computed once per pair for every stage that
# triangulates against a reference: priors (frame i vs i-span and i-span/2, forward for the
# first frames) and depth_fusion (frame i vs i+offset). The pairs are the union of what their
# sections ask for, each item keyed by its two images, preset and threshold only, so changing
# depth_fusion.offsets computes only the new pairs and leaves priors' items cached. Pair (a, b)
# (a < b) holds compute_pair_flow(a, b): frame b's flow to a is its bwd / bwd_valid, exactly
# what compute_pair_flow(b, a) returns as fwd / fwd_valid.
def _prior_refs(i: int, n: int, p: Any) -> list[int]:
    """Frame i's prior references (the geometric backend only): stages.graph.references."""
    if p.backend != "geometric":
        return []
    if p.references == "symmetric":
        return references.symmetric_prior_references(i, n, p.span)
    return references.prior_references(i, n, p.span)


def _fusion_refs(i: int, n: int, p: Any) -> list[int]:
    """Frame i's fixed-offset fusion references (depth_fusion.references=offsets)."""
    return references.offset_references(i, n, p.offsets) if p.enabled and p.references == "offsets" else []


def _fusion_far_refs(i: int, n: int, p: Any) -> list[int]:
    """Frame i's fusion references whose flow flow_far computes (references=offsets): the
    adjacent ones (+-1) are the flow stage's own pairs, read from there. With
    references=baseline the pairs are chosen from the poses and computed by fusion_flow."""
    return [j for j in _fusion_refs(i, n, p) if abs(j - i) != 1]


def _far_flow(fl: dict[str, Any], direction: str) -> tuple[np.ndarray, np.ndarray]:
    """A flow_far item seen from one of its frames: (flow to the other frame, its valid mask)."""
    if direction == "fwd":
        return np.asarray(fl["fwd"]), np.asarray(fl["fwd_valid"], bool)
    return np.asarray(fl["bwd"]), np.asarray(fl["bwd_valid"], bool)


def _user_mask_files(src: Source, p: frontend_params.MasksSettings, sel: list[int]) -> list[str]:
    """The --masks PNG of each selected source frame: DIR/<frame stem>.png when any PNG of DIR is
    named as a frame (then every PNG must be: one that matches no frame is one line, exit 2, not a
    silent fall-back to frame order), else the k-th PNG of DIR (natural order) when DIR holds one
    per source frame. A missing one: one line, exit 2."""
    from pathlib import Path

    from gcvd_flow.io.sources import natural_key

    d = Path(str(p.user_dir)).expanduser()
    pngs = sorted((f for f in d.iterdir() if f.suffix.lower() == ".png" and f.is_file()), key=lambda f: natural_key(f.name))
    by_stem = {f.stem: f for f in pngs}
    stems = [Path(nm).stem for nm in src.names] if src.names else [str(i) for i in range(len(src.items))]
    names = [stems[i] for i in sel]
    known = set(stems)
    if any(f.stem in known for f in pngs):
        stray = next((f for f in pngs if f.stem not in known), None)
        if stray is not None:
            raise UsageError(f"{stray}: --masks: this mask's name matches no frame (the other masks are named as "
                             f"the frames, e.g. {stems[0]}.png)")
        if all(nm in by_stem for nm in names):
            return [str(by_stem[nm]) for nm in names]
    elif len(pngs) == len(src.items):
        return [str(pngs[i]) for i in sel]
    missing = next(nm for nm in names if nm not in by_stem)
    raise UsageError(f"{d}: no mask for frame {missing} (expected {missing}.png, or one PNG per frame in frame "
                     f"order: found {len(pngs)} PNGs for {len(src.items)} frames)")


@dataclasses.dataclass(frozen=True)
class _MaskFile:
    """Picklable loader: a --masks PNG -> bool (H, W), True = leave out (non-zero on the decoded
    8/16-bit grey, RGB or RGBA values; alpha: gcvd_flow.io.formats.read_user_mask_png)."""

    path: str

    def __call__(self) -> np.ndarray:
        from gcvd_flow.io.formats import read_user_mask_png

        return read_user_mask_png(self.path)


def _user_keep(inputs: dict[str, Any], shape: tuple[int, int]) -> np.ndarray:
    """The user's mask (source resolution, True = out) as a kept mask uint8 (h, w) at working
    resolution, 1 = kept: a working pixel is out when any source pixel it is made of is (through
    ingest's undistortion when it has one: stages.frontend.user_masks.source_to_working)."""
    sw, sh = inputs["source_size"]
    user = np.asarray(inputs["user_mask"], bool) if "user_mask" in inputs else np.zeros((sh, sw), bool)
    if user.shape != (sh, sw):
        raise ingest_mod.FrameError(f"--masks: a mask is {user.shape[1]}x{user.shape[0]}, the frames are {sw}x{sh}")
    und = inputs.get("undistort")
    return user_masks.source_to_working(user, (shape[1], shape[0]), None if und is None else tuple(und))


def _solve_mask(item: dict[str, Any]) -> np.ndarray:
    """The mask the optimisations use: ``solve`` (static and flow agreeing with the static scene),
    ``static`` for a mask item without it."""
    return np.asarray(item.get("solve", item["static"]))


def _hard_mask(item: dict[str, Any]) -> np.ndarray:
    """``_solve_mask`` with the user's (--masks) pixels as -1 (int8) when there are any, the
    optimisations' hard exclusion (stages.frontend.user_masks.hard_masks); uint8 as before without."""
    return user_masks.hard_masks(_solve_mask(item), item.get("user_keep"))


def _user_keeps(masks: Any, frames: Any) -> list[np.ndarray] | None:
    """The user's (--masks) kept pixels bool (H, W) of ``frames`` (mask items' user_keep), None without --masks."""
    frames = [int(f) for f in frames]
    if not frames or "user_keep" not in masks[frames[0]]:
        return None
    return [np.asarray(masks[f]["user_keep"]) > 0 for f in frames]


def _eroded_keep(item: dict[str, Any]) -> np.ndarray:
    """A mask item's user_keep bool (H, W) less every pixel next to a user-masked one: a bilinear
    sample (OpenCV's 1/32-quantised weights included) that reads only pixels kept here mixes no
    user-masked pixel."""
    import cv2

    return cv2.erode(np.asarray(item["user_keep"], np.uint8), np.ones((3, 3), np.uint8),
                     borderType=cv2.BORDER_REPLICATE) > 0


class _HardMasks:
    """masks[i] / masks[a:b] -> ``_hard_mask`` of those mask items, loaded when read (the lazy
    field stack optimize_segments reads one window at a time)."""

    def __init__(self, items: Any):
        self._items = items

    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, i: Any) -> np.ndarray:
        if isinstance(i, slice):
            return np.stack([_hard_mask(self._items[j]) for j in range(*i.indices(len(self._items)))])
        return _hard_mask(self._items[int(i)])
