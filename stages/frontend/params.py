"""Parameters of the front-end stages (ingest, flow, masks, priors): one frozen dataclass per
stage; the pipeline derives each config section from it (``stages/params.py``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Literal, TypeVar

from gcvd_flow.stages.frontend.lens import parse_camera
from gcvd_flow.stages.params import USER_DIR, WEIGHTS_FILE, param

DisPreset = Literal["ultrafast", "fast", "medium", "fine", "fine-fast", "fine-wide"]


def _valid_intrinsics(v: str | None) -> str | None:
    if v is not None:
        parse_camera(v)  # ValueError naming what is wrong (check_camera at ingest: the frame size)
    return v


def _positive_starts(v: tuple[float, ...]) -> tuple[float, ...]:
    if not v or any(not 0.3 < x < 3.0 for x in v):
        raise ValueError("starts are one or more multiples of the guessed focal length, each within 0.3-3")
    return v


@dataclass(frozen=True)
class IngestSettings:
    """Which source frames, at which working resolution, with which intrinsics."""

    start: int = param(0, "first source frame", ge=0)
    end: int | None = param(None, "one past the last source frame (None: all)")
    stride: int = param(1, "take every stride-th frame", ge=1)
    long_side: int = param(256, "working resolution, px of the long side (paper: 384)", ge=16, le=16384)
    min_short_frac: float = param(0.5, "the short side is at least this fraction of long_side: frames wider than "
                                  "2:1 (a 1226x370 driving camera) get a longer long side instead of a few dozen "
                                  "rows (0: the long side alone decides)", ge=0, le=1)
    intrinsics: str | None = param(None, "fx,fy,cx,cy at the source resolution, optionally followed by the lens "
                                   "distortion k1,k2,p1,p2[,k3] (OpenCV order), or OPENCV_FISHEYE:fx,fy,cx,cy,"
                                   "k1,k2,k3,k4 (cv2.fisheye): frames are undistorted at ingest",
                                   validator=_valid_intrinsics)


@dataclass(frozen=True)
class CalibrateSettings:
    """One focal length estimated from the video when no intrinsics are given (stages.frontend.calibrate)."""

    mode: Literal["auto", "off"] = param("auto", "auto: estimate one focal length (fx = fy) from the video when no "
                                         "intrinsics are given (flag, intrinsics.txt or a dataset default); off: keep "
                                         "the guess f = 300/384 x long side")
    max_frames: int = param(48, "frames sampled by image motion over the clip for the estimate", ge=3)
    features: int = param(1000, "SIFT features per sampled frame (the strongest)", ge=100)
    max_rel_sigma: float = param(0.03, "an estimate whose spread over frame blocks and formal std (std / f) exceed "
                                 "this is not used: the motion does not determine the focal length; the guess is "
                                 "kept (the reported uncertainty also holds the principal-point term)", gt=0)
    tracks_per_frame: int = param(150, "SIFT tracks per frame for the structure from motion (spatially bucketed; "
                                  "one final adjustment uses all): bounds the work on richly textured clips", ge=0)
    passes: int = param(4, "structure-from-motion passes at most, each restarted from the last focal length", ge=1)
    starts: tuple[float, ...] = param((1.0, 0.8, 1.25), "the structure from motion is made from the guess x each of "
                                      "these; the run whose final adjustment fits best (most frames, then the lowest "
                                      "median reprojection error) is kept: where the reconstruction depends on where it "
                                      "starts, the wrong ones fit worse", validator=_positive_starts)
    pass_tol: float = param(0.01, "the passes stop when f moves less than this (relative); the lens-free synthetic "
                            "loop ends at the same f from guesses 8 % apart", gt=0)
    pp_frac: float = param(0.02, "the principal point is assumed at the centre; the uncertainty includes how far f "
                           "moves if it is off by this x the image size (x and y)", ge=0)
    principal_point: Literal["auto", "centre"] = param(
        "auto", "auto: with an estimated focal length, also estimate the principal point (square pixels) and use it, "
        "moved towards the centre by its uncertainty (pp_spread), when its std is within pp_max_sigma of the image "
        "size and it lies > 2 std from the centre (else the centre, with a warning when the motion does not determine "
        "it); centre: always the image centre")
    pp_max_sigma: float = param(0.025, "the largest std (x / width, y / height) of a principal point estimate that "
                                "is used", gt=0)
    pp_spread: float = param(0.025, "how far real cameras' principal points lie from the image centre (std, x / width, "
                             "y / height; HoloLens 2 2.9 %, TUM's Kinect 3.3 %, KITTI 3.7 % of the height): an estimate "
                             "of std s is used as centre + w x its offset, w = spread^2 / (spread^2 + s^2) per axis",
                             gt=0)


@dataclass(frozen=True)
class FlowSettings:
    """Flow of adjacent pairs (stages.frontend.flow.compute_pair_flow)."""

    backend: Literal["dis", "raft"] = "dis"
    preset: DisPreset = param("fine-wide", "DIS preset; 'fine' = medium at full resolution (slower than 'medium', "
                                           "more accurate); 'fine-wide' = fine, and a pair DIS mostly loses (frames "
                                           "far apart) again from the homography of its SIFT matches")
    fb_thresh: float = param(1.0, "forward-backward consistency, px", gt=0)
    weights: str | None = param(None, "RAFT weights file", json_schema_extra=WEIGHTS_FILE)

    def check(self) -> None:
        if self.backend == "raft" and not self.weights:
            raise ValueError("flow.backend=raft needs flow.weights=FILE (raft-things, .pth or .safetensors)")


@dataclass(frozen=True)
class MasksSettings:
    """Likely-dynamic pixels (stages.frontend.masks, stages.models.maskrcnn)."""

    backend: Literal["motion", "maskrcnn", "motion+maskrcnn", "none"] = param(
        "motion", "motion: flow vs. static geometry; maskrcnn: COCO instances of moving "
        "classes (needs weights); motion+maskrcnn: dynamic if either says so")
    dilate: int = param(5, ge=0)
    texture_frac: float = param(1.0, "motion evidence is scaled down where the image's Shi-Tomasi texture is below "
                                     "this x its median (flow there is interpolated, not observed); 0 = off", ge=0)
    sigma_mult: float = param(5.0, "a pixel moves when its epipolar residual exceeds median + sigma_mult x robust "
                                   "sigma", gt=0)
    span: int = param(6, "frames spanned by the chained flow (an object moving along epipolar lines over 1 "
                      "frame rarely does over several)", ge=1)
    weights: str | None = param(None, "Mask R-CNN weights file", json_schema_extra=WEIGHTS_FILE)
    score_thresh: float = param(0.5, "Mask R-CNN detections scoring less are ignored", ge=0, le=1)
    min_size: int = param(800, "Mask R-CNN input short side, px (torchvision: 800)", ge=32)
    user_dir: str | None = param(None, "your own masks (--masks DIR): one PNG per frame, named as the frame (or in "
                                 "frame order), non-zero = leave this pixel out; combined with the backend's masks",
                                 json_schema_extra=USER_DIR)

    def check(self) -> None:
        if "maskrcnn" in self.backend and not self.weights:
            raise ValueError(f"masks.backend={self.backend} needs masks.weights=FILE "
                             "(torchvision maskrcnn_resnet50_fpn weights, .pth or .safetensors)")


@dataclass(frozen=True)
class PriorsSettings:
    """Single-image depth prior (stages.frontend.priors, stages.models.midas)."""

    backend: Literal["geometric", "midas"] = "geometric"
    span: int = param(8, "frames between a frame and its reference for triangulation", ge=1)
    references: Literal["back", "symmetric"] = param(
        "back", "back: span and span/2 frames back (forward for the first frames), two direct flows per frame, and an"
                " appended frame never changes an existing frame's references; symmetric (opt-in): span back and span"
                " forward, each direct flow shared by the two frames it joins (fewer far flows, but the fusion "
                "references no longer find the span/2 pairs)")
    preset: DisPreset = param("fine", "DIS preset of the prior's direct flows ('fine': full-resolution finest level; "
                              "'fine-fast': the same with 12 instead of 25 gradient-descent iterations)")
    fb_thresh: float = param(1.0, gt=0)
    chain_fallback: bool = param(
        True, "when no direct flow to the references keeps enough consistent pixels (fast motion), triangulate the "
              "chain of chain_links adjacent flows toward the reference instead (its longest prefix that keeps them) "
              "rather than fall back to a constant prior")
    chain_links: int = param(8, "adjacent flows the fallback may chain, at most span", ge=1)
    weights: str | None = param(None, "MiDaS weights file", json_schema_extra=WEIGHTS_FILE)

    def check(self) -> None:
        if self.backend == "midas" and not self.weights:
            raise ValueError("priors.backend=midas needs priors.weights=FILE (MiDaS v2.1 small, .pt or .safetensors)")


_S = TypeVar("_S")


def settings_with(cls: type[_S], settings: Any, overrides: dict[str, Any]) -> _S:
    """A stage's settings as the algorithm reads them: ``settings`` (the dataclass ``cls`` or the
    pipeline's config section of it, whose fields are the same; None: the dataclass's defaults)
    with ``overrides`` (field names; a name that is no field: TypeError). The defaults are
    written once, in ``cls``; the algorithm reads every field from the result."""
    base = cls() if settings is None else settings
    if not overrides:
        return base
    values = {f.name: getattr(base, f.name) for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(overrides) - set(values))
    if unknown:
        raise TypeError(f"{cls.__name__} has no field {', '.join(unknown)}")
    return cls(**{**values, **overrides})
