"""The GCVD pipeline: its configuration and its DAG, one block per stage.

    ingest [map: frame] -> flow [map: pair i,i+1] -> flow_far [map: pair i,j] -> masks [map: frame]
    -> priors [map: frame] (reads flow_far) -> keyframes -> association -> optimize_keyframes
    -> optimize_edges -> pose_graph
    -> bundle_adjustment -> optimize_segments -> fusion_samples [map: frame]
    -> fusion_references [map: one item] -> fusion_flow [map: pair i,j]
    -> depth_fusion [map: frame] (reads flow, flow_far, fusion_flow)
    -> depth_filter [map: frame] -> depth_consensus [map: frame]

Each block holds everything about one stage: its parameters (a pydantic section, ``--set
section.key=value``, derived from the stage's parameter dataclass in ``stages/*/params.py``), for
a map stage the inputs of each item (typed references to the declared stages: an item of another
stage, a list of them, a part of a whole stage's output, a constant; which frames an item reads
is ``stages/graph/references.py``'s), the function the
engine calls — ``run_<stage>(inputs, params, ctx)``, which unpacks the inputs by the names the
items declared and calls the algorithm in ``stages/`` — and the declaration. Each map item
reads exactly the pieces it needs (a frame, its neighbours' flows, ...), so a trimmed, extended
or re-strided clip re-uses every item whose inputs did not change. Adding a stage is adding a
block here plus its algorithm in ``stages/`` (docs/contributing.md).

Conventions (docs/contributing.md): frames uint8 (H, W, 3) RGB; flows float32 (H, W, 2) px;
poses T_w_c camera-to-world (4, 4) float64; depth float32 (H, W), one global scale.
"""

from __future__ import annotations

import dataclasses
import functools
import sys
import typing
from typing import Any

import numpy as np
from pydantic import ConfigDict, Field, create_model, field_validator, model_validator

import artifacts_schema
from gcvd_flow.engine.api import PipelineSpec
from gcvd_flow.engine.config import Section
from gcvd_flow.engine.dag import Const, ExternalRef, ItemRef, MapStage, PartRef, Pipeline, Stage
from gcvd_flow.engine.errors import UsageError
from gcvd_flow.io import run_dir
from gcvd_flow.io.sources import Source, open_source as _open_source
from gcvd_flow.io.weights import open_model
from stages.depth import consensus as depth_consensus, filter as depth_filter, fusion as depth_fusion, params as depth_params
from stages.frontend import (
    flow,
    ingest as ingest_mod,
    lens,
    masks as masks_mod,
    params as frontend_params,
    priors as priors_mod,
    solvable,
    user_masks,
)
from stages.graph import keyframes as keyframes_mod, params as graph_params, references
from stages.optimize import params as opt_params

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
    return create_model(name, __base__=Section, __module__=__name__, __doc__=cls.__doc__,
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


def section(name: str, cls: type) -> type[Section]:
    """``--set NAME.key=value`` configures the section derived from the dataclass ``cls``."""
    return config_section(name)(section_from_dataclass(cls, "".join(w.title() for w in name.split("_")) + "Params"))


# ============================================================================== ingest
IngestParams = section("ingest", frontend_params.IngestSettings)


def _camera(src: Source, p: IngestParams) -> tuple[lens.Camera | None, str]:
    """The camera --intrinsics, the layout's intrinsics.txt or a dataset default gives (source px;
    None: none given) and where it came from, checked against the frame size: a value no lens
    has is one line naming it and the option or file, exit 2 (stages.frontend.lens.check_camera)."""
    if p.intrinsics:
        cam, origin, where = lens.parse_camera(p.intrinsics), "user (--intrinsics)", "--intrinsics"
    elif src.intrinsics is not None:
        cam = lens.make_camera(src.intrinsics, src.distortion_model if src.distortion else "PINHOLE", src.distortion or ())
        origin = src.intrinsics_origin or "dataset"
        where = f"{src.path}/intrinsics.txt" if origin == "intrinsics.txt" else f"{src.path} ({origin})"
    else:
        return None, "guess"
    try:
        lens.check_camera(cam, src.size)
    except ValueError as exc:
        raise UsageError(f"{where}: {exc}") from None
    return cam, origin


def _undistort_of(cam: dict[str, Any]) -> list[Any] | None:
    """The ingest summary's lens as item input [intrinsics, coefficients, model] (None: pinhole)."""
    if "distortion" not in cam:
        return None
    return [cam["distortion_intrinsics"], cam["distortion"], cam.get("distortion_model", "OPENCV")]


def _ingest_items(view, p: IngestParams):
    src: Source = view.source
    sel = list(range(len(src.items)))[p.start:p.end:p.stride]
    if len(sel) < 2:
        raise UsageError(f"ingest selects {len(sel)} frame(s) of {len(src.items)} "
                         f"(start={p.start}, end={p.end}, stride={p.stride}); need at least 2")
    cam, _ = _camera(src, p)
    # with a lens distortion each item undistorts its frame: the model, its coefficients and the
    # intrinsics they refer to are part of the item's key (without one the items are keyed as before)
    extra = {} if cam is None or not cam.distorted else {
        "undistort": Const([list(cam.intrinsics), list(cam.coeffs), cam.model])}
    return [{"frame": src.items[i], "source_size": Const(list(src.size)),
             "name": Const(src.names[i] if src.names else str(i)), **extra} for i in sel]


def _ingest_summary(view, p: IngestParams) -> dict[str, Any]:
    src: Source = view.source
    w, h = ingest_mod.working_size(src.size[0], src.size[1], p.long_side, p.min_short_frac)
    given, origin = _camera(src, p)
    cam = ingest_mod.make_camera(src.size[0], src.size[1], w, h, None if given is None else given.intrinsics, origin)
    if given is not None and given.distorted:
        cam["distortion"] = list(given.coeffs)  # frames undistorted at ingest (pinhole K)
        cam["distortion_model"] = given.model  # OPENCV or OPENCV_FISHEYE (stages.frontend.lens)
        cam["distortion_intrinsics"] = list(given.intrinsics)  # what the coefficients refer to (source px)
    cam["frame_indices"] = list(range(len(src.items)))[p.start:p.end:p.stride]
    cam["fps"] = src.fps
    cam["layout"] = src.layout
    return cam


def run_ingest(inputs: dict[str, Any], p: Any, ctx: Any) -> dict[str, Any]:
    """Source frame -> working resolution. Output {image: uint8 (h, w, 3) RGB (PNG)}."""
    rgb = inputs["frame"]
    src_w, src_h = inputs["source_size"]
    if (rgb.shape[1], rgb.shape[0]) != (src_w, src_h):
        raise ingest_mod.FrameError(f"{inputs['name']}: frame size {rgb.shape[1]}x{rgb.shape[0]} differs from "
                         f"the first frame's {src_w}x{src_h}")
    size = ingest_mod.working_size(src_w, src_h, p.long_side, p.min_short_frac)
    if "undistort" in inputs:  # [intrinsics (fx, fy, cx, cy) source px, coefficients, model]
        intr, dist, model = inputs["undistort"]
        rgb = ingest_mod.undistort_frame(ingest_mod.prepare_frame(rgb, (src_w, src_h)), tuple(intr), tuple(dist), model)
    return {"image": ingest_mod.prepare_frame(rgb, size)}


def undistort_source_frame(rgb: np.ndarray, cameras: dict[str, Any]) -> np.ndarray:
    """A source frame as ingest undistorted it, from cameras.json (distortion, distortion_model,
    distortion_intrinsics): for the exports that read the source frames (exports.source_frames)."""
    return ingest_mod.undistort_frame(rgb, tuple(cameras["distortion_intrinsics"]), tuple(cameras["distortion"]),
                                      cameras.get("distortion_model", "OPENCV"))


INGEST = declare(MapStage("ingest", run_ingest, params="ingest", kind="frames", items=_ingest_items,
                  summary=_ingest_summary, summary_kind="camera",
                  selection_params=("start", "end", "stride", "intrinsics"),
                  description="frames at working resolution + camera"))


# ============================================================================== user masks
def _user_mask_items(view, p: Any):
    # Only with --masks (masks.user_dir): the user's mask of each frame, by its content (an
    # ExternalRef), for the stages that run before the masks stage (calibrate). Without: no item.
    # A lens leaving a black border after undistortion: that border alone, as if masked (user_masks.lens_border).
    border = _lens_border(view)
    if not p.user_dir and not border:
        return []
    from gcvd_flow.engine.keys import digest_file

    cam = view.summary(INGEST)
    und = _undistort_of(cam)
    files = _user_mask_files(view.source, p, list(cam["frame_indices"])) if p.user_dir else [None] * view.len(INGEST)
    return [{**({"user_mask": ExternalRef(digest_file(f), _MaskFile(f))} if f else {}),
             "source_size": Const(list(view.source.size)), "size": Const([cam["width"], cam["height"]]),
             **({"undistort": Const(und)} if und else {})} for f in files]


def _lens_border(view) -> list[Any] | None:
    """Ingest's undistortion when it leaves a black border (stages.frontend.user_masks.lens_border), else None."""
    und = _undistort_of(view.summary(INGEST))
    return und if user_masks.lens_border(und, view.source.size) else None


def run_user_masks(inputs: dict[str, Any], p: Any, ctx: Any) -> dict[str, Any]:
    """Frame i's --masks PNG -> {user_keep: uint8 (h, w) at working resolution, 1 = not masked}
    (what the masks stage's items carry as user_keep: _user_keep)."""
    w, h = inputs["size"]
    return {"user_keep": _user_keep(inputs, (h, w))}


USER_MASKS = declare(MapStage("user_masks", run_user_masks, deps=(INGEST,), params="masks", kind="user_mask",
                              items=_user_mask_items,
                              selection_params=tuple(f.name for f in dataclasses.fields(frontend_params.MasksSettings)
                                                     if f.name != "user_dir"),
                              description="the user's --masks at working resolution (no item without --masks)"))


# ============================================================================== calibrate
CalibrateParams = section("calibrate", frontend_params.CalibrateSettings)


class _SampledImages:
    """images[i] -> item i's ``key`` (ingest's image, user_masks' user_keep), decoded only when
    asked (the estimate samples frames)."""

    def __init__(self, frames: Any, key: str = "image"):
        self._frames = frames
        self._key = key

    def __len__(self) -> int:
        return len(self._frames)

    def __getitem__(self, i: int) -> np.ndarray:
        return np.asarray(self._frames[i][self._key])


def run_calibrate(inputs: dict[str, Any], p: CalibrateParams, ctx: Any) -> dict[str, Any]:
    """ingest's camera -> {K (3, 3) at working resolution: the given intrinsics, or one focal length
    estimated from the frames, or the guess; estimated, guessed (bool), origin, focal_source (fx, fy at
    source resolution), rel_sigma (std / f of the estimate, None when not estimated), warning (str,
    '' when none), pairs, rotation_pairs, median_px, unsolvable: [[k, why]] the frames that leave
    nothing to solve (stages.frontend.solvable; the run dir marks their depth invalid)}. Given
    intrinsics: no estimate. Fewer than two solvable frames: FrameError (exit 2)."""
    frames = inputs[INGEST.name]
    cam = frames.summary
    K = np.asarray(cam["K"], np.float64)
    sx, sy = cam["width"] / cam["source_width"], cam["height"] / cam["source_height"]
    user = inputs.get(USER_MASKS.name) or []  # --masks: no feature on the user's pixels; else no item
    keep = _SampledImages(user, "user_keep") if len(user) else None
    out = {"K": K, "estimated": False, "guessed": bool(cam["guessed"]), "origin": cam["origin"],
           "focal_source": [float(K[0, 0] / sx), float(K[1, 1] / sy)], "rel_sigma": None, "warning": "",
           "pairs": 0, "rotation_pairs": 0, "median_px": None,
           "unsolvable": _unsolvable(_SampledImages(frames), keep, list(cam["frame_indices"]))}
    if not cam["guessed"] or p.mode == "off":
        return out
    from gcvd_flow.io.native_output import native_stdout_silenced
    from stages.frontend import calibrate as calibrate_mod

    with native_stdout_silenced():  # gtsam prints cheirality exceptions to stdout
        res = calibrate_mod.estimate_focal(_SampledImages(frames), K, max_frames=p.max_frames,
                                           n_features=p.features, max_rel_sigma=p.max_rel_sigma,
                                           tracks_per_frame=p.tracks_per_frame, pp_frac=p.pp_frac, keep=keep,
                                           pp_mode=p.principal_point, pp_max_sigma=p.pp_max_sigma)
    out.update(pairs=int(res["pairs"]), rotation_pairs=int(res["rotation_pairs"]), method=res["method"],
               median_px=float(res["median_px"]), frames=int(res["frames"]), points=int(res["points"]),
               iterations=int(res["iterations"]))
    rel = float(res["rel_sigma"])
    out["rel_sigma"] = rel if np.isfinite(rel) else None
    if not res["determined"]:
        out["warning"] = f"focal length not estimated, the guess f = {K[0, 0]:.1f} px is kept: {res['reason']}"
        ctx.log("warning: " + out["warning"])
        out["principal_point"] = {"cx": float(K[0, 2]), "cy": float(K[1, 2]), "sigma_px": None, "estimated": False,
                                  "detail": "assumed at the image centre (the focal length is not determined)"}
        return out
    f = float(res["focal"])
    K = K.copy()
    K[0, 0] = K[1, 1] = f
    K[0, 2], K[1, 2] = (float(v) for v in res["principal_point"])
    out.update(K=K, estimated=True, guessed=False, focal_source=[f / sx, f / sy],
               origin=f"estimated from the video: f = {f:.1f} px +- {100 * rel:.1f} % at {cam['width']}x"
                      f"{cam['height']} ({len(frames)} frames, {res['pairs']} pairs)")
    ctx.log(f"focal length estimated: {f:.1f} px +- {100 * rel:.1f} % (guess {cam['K'][0][0]:.1f}; {res['method']}: "
            f"{res['frames']} frames, {res['points']} points, {res['iterations']} LM iterations, {res['pairs']} pairs of which "
            f"{res['rotation_pairs']} "
            f"rotation-only, median residual {res['median_px']:.2f} px)")
    _principal_point_outcome(res, K, (sx, sy), out, ctx)
    return out


def _unsolvable(images: Any, keep: Any, indices: list[int]) -> list[list[Any]]:
    """[[k, why]] of the frames that leave nothing to solve (masked almost entirely, no texture);
    FrameError (exit 2) when fewer than two frames are left to solve."""
    bad = solvable.unsolvable_frames(images, keep)
    if len(images) - len(bad) < 2:
        k, why = bad[0]
        raise ingest_mod.FrameError(
            f"nothing to solve: {len(bad)} of {len(images)} frames are masked almost entirely or have no texture "
            f"(source frames {run_dir.frame_ranges([indices[j] for j, _ in bad])}; frame {indices[k]}: {why})")
    return [[int(k), why] for k, why in bad]


def _principal_point_outcome(res: dict[str, Any], K: np.ndarray, scale: tuple[float, float], out: dict[str, Any],
                             ctx: Any) -> None:
    """The calibrate stage's account of the principal point when the focal length was estimated:
    out's principal_point = {cx, cy (working px), cx_source, cy_source, sigma_px (working, None when
    not estimated), estimated (bool), detail}; a principal point the motion does not determine keeps
    the centre and logs one warning line (out's pp_warning)."""
    sx, sy = scale
    cx, cy = float(K[0, 2]), float(K[1, 2])
    sig = res.get("pp_sigma")
    sig = None if sig is None or not np.all(np.isfinite(sig)) else sig  # artifacts hold finite floats only
    doc = {"cx": cx, "cy": cy, "cx_source": (cx + 0.5) / sx - 0.5, "cy_source": (cy + 0.5) / sy - 0.5,
           "sigma_px": [float(v) for v in sig] if sig is not None else None,
           "sigma_source_px": [float(sig[0]) / sx, float(sig[1]) / sy] if sig is not None else None,
           "estimated": bool(res.get("pp_estimated")),
           "estimate": [float(v) for v in res["pp_estimate"]] if res.get("pp_estimate") is not None else None}
    if doc["estimated"]:
        doc["detail"] = (f"estimated from the video: ({cx:.1f}, {cy:.1f}) px +- ({sig[0]:.1f}, {sig[1]:.1f}) px, "
                         f"{res['pp_z']:.1f} std from the image centre")
        ctx.log(f"principal point {doc['detail']} (focal length {res['focal_centre']:.1f} px with the centre)")
    elif res.get("pp_reason"):
        doc["detail"] = f"assumed at the image centre: {res['pp_reason']}"
        out["pp_warning"] = f"principal point not estimated, the image centre ({cx:.1f}, {cy:.1f}) px is kept: {res['pp_reason']}"
        ctx.log("warning: " + out["pp_warning"])
    else:
        doc["detail"] = "image centre" + (f" ({res['pp_note']})" if res.get("pp_note") else "")
        if res.get("pp_note"):
            ctx.log(f"principal point: {res['pp_note']}")
    out["principal_point"] = doc


CALIBRATE = declare(Stage("calibrate", run_calibrate, deps=(INGEST, USER_MASKS), params="calibrate", kind="calibration",
                          description="one focal length estimated from the video when no intrinsics are given"))


# ============================================================================== flow
FlowParams = section("flow", frontend_params.FlowSettings)


def _flow_items(view, p: FlowParams):
    return [{"a": ItemRef(INGEST, i), "b": ItemRef(INGEST, i + 1)} for i in range(view.len(INGEST) - 1)]


def _open_raft(p: FlowParams) -> Any:
    return open_model("raft", p.weights)


def run_flow(inputs: dict[str, Any], p: FlowParams, ctx: Any) -> dict[str, Any]:
    """Adjacent pair (i, i+1) -> {fwd, bwd (H, W, 2) float32 px, fwd_valid, bwd_valid bool}."""
    model = ctx.resource("model") if p.backend == "raft" else None
    return flow.compute_pair_flow(inputs["a"]["image"], inputs["b"]["image"], backend=p.backend,
                                  preset=p.preset, fb_thresh=p.fb_thresh, model=model)


FLOW = declare(MapStage("flow", run_flow, deps=(INGEST,), params="flow", kind="flow", items=_flow_items,
                resources={"model": _open_raft}, description="forward/backward flow of adjacent pairs + consistency"))


# ============================================================================== flow_far
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


def _far_pairs(n: int, b: Any) -> list[references.FarPair]:
    """The pairs flow_far computes: what priors and depth_fusion (bundle ``b``) ask for."""
    return references.far_pairs(n, [(lambda i: _prior_refs(i, n, b.priors), b.priors.preset, b.priors.fb_thresh),
                                    (lambda i: _fusion_far_refs(i, n, b.depth_fusion), b.depth_fusion.preset,
                                     b.depth_fusion.fb_thresh)])


def _flow_far_items(view, b: Any):
    return [{"a": ItemRef(INGEST, a), "b": ItemRef(INGEST, c), "preset": Const(preset),
             "fb_thresh": Const(fb)} for a, c, preset, fb in _far_pairs(view.len(INGEST), b)]


def _flow_far_summary(view, b: Any) -> dict[str, Any]:
    return {"pairs": [list(pr) for pr in _far_pairs(view.len(INGEST), b)]}


def _far_index(view) -> dict[tuple, int]:
    """flow_far's pairs (a, b, preset, fb_thresh) -> item index, from its summary."""
    return {tuple(pr): k for k, pr in enumerate(view.summary(FLOW_FAR)["pairs"])}


def _far_refs(index: dict[tuple, int], i: int, js: list[int], preset: str, fb_thresh: float) -> dict[str, Any]:
    """Item inputs reading frame i's flows to frames js from flow_far: refs (the pair items)
    and ref_dirs ("fwd": i is the pair's first frame, "bwd": its second)."""
    return {"refs": [ItemRef(FLOW_FAR, index[references.far_pair(i, j, preset, fb_thresh)]) for j in js],
            "ref_dirs": Const(["fwd" if i < j else "bwd" for j in js])}


def run_flow_far(inputs: dict[str, Any], b: Any, ctx: Any) -> dict[str, Any]:
    """Pair (a, b), a < b -> {fwd, bwd (H, W, 2) float32 px, fwd_valid, bwd_valid bool} (DIS)."""
    return flow.compute_pair_flow(inputs["a"]["image"], inputs["b"]["image"], preset=inputs["preset"],
                                  fb_thresh=inputs["fb_thresh"])


def _far_flow(fl: dict[str, Any], direction: str) -> tuple[np.ndarray, np.ndarray]:
    """A flow_far item seen from one of its frames: (flow to the other frame, its valid mask)."""
    if direction == "fwd":
        return np.asarray(fl["fwd"]), np.asarray(fl["fwd_valid"], bool)
    return np.asarray(fl["bwd"]), np.asarray(fl["bwd_valid"], bool)


FLOW_FAR = declare(MapStage("flow_far", run_flow_far, deps=(INGEST,), params=("priors", "depth_fusion"),
                   kind="flow_far", items=_flow_far_items, summary=_flow_far_summary,
                   selection_params=("priors", "depth_fusion"),
                   description="direct flows of the pairs priors and depth_fusion triangulate, once per pair"))


# ============================================================================== masks
MasksParams = section("masks", frontend_params.MasksSettings)


def _chain_refs(i: int, n: int, span: int) -> dict[str, Any]:
    """Flows from frame i toward a reference `span` frames away (stages.graph.references.flow_chain)."""
    direction, flows = references.flow_chain(i, n, span)
    return {"direction": Const(direction), "chain": [ItemRef(FLOW, k) for k in flows]}


def _user_mask_files(src: Source, p: MasksParams, sel: list[int]) -> list[str]:
    """The --masks PNG of each selected source frame: DIR/<frame stem>.png when any PNG of DIR is
    named as a frame (then every PNG must be: one that matches no frame is one line, exit 2, not a
    silent fall-back to frame order), else the k-th PNG of DIR (natural order) when DIR holds one
    per source frame. A missing one: one line, exit 2."""
    from pathlib import Path

    from gcvd_flow.io.sources import natural_key

    d = Path(p.user_dir).expanduser()
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


def _mask_items(view, p: MasksParams):
    # The semantic backend reads the frame itself; the motion backend its flows (only); the user's
    # mask of the frame enters by its content (an ExternalRef: file digest + loader).
    n = view.len(INGEST)
    user, und = [], _lens_border(view)
    if p.user_dir:
        from gcvd_flow.engine.keys import digest_file

        sel = list(view.summary(INGEST)["frame_indices"])  # the source frames ingest selected
        user = [ExternalRef(digest_file(f), _MaskFile(f)) for f in _user_mask_files(view.source, p, sel)]
        cam = view.summary(INGEST)
        und = _undistort_of(cam)
    out = []
    for i in range(n):
        it: dict[str, Any] = {}
        if p.backend != "maskrcnn":
            it = {"K": PartRef(CALIBRATE, ("K",)), **_chain_refs(i, n, p.span)}
        if "maskrcnn" in p.backend or (p.backend != "none" and p.texture_frac > 0):
            it["image"] = ItemRef(INGEST, i)
        if user or und:  # --masks, or the lens' black border alone
            if user:
                it["user_mask"] = user[i]
            it["source_size"] = Const(list(view.source.size))
            if und:  # ingest undistorts the frames: the masks go through the same remap
                it["undistort"] = Const(und)
        out.append(it)
    return out


def _open_maskrcnn(p: MasksParams) -> Any:
    return open_model("maskrcnn", p.weights, min_size=p.min_size)


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


def _with_user_mask(static: np.ndarray, inputs: dict[str, Any]) -> np.ndarray:
    """static uint8 (h, w) with the user's mask (source resolution, True = out) set to 0."""
    if "source_size" not in inputs:
        return static
    return np.where(_user_keep(inputs, static.shape) > 0, static, 0).astype(np.uint8)


def run_masks(inputs: dict[str, Any], p: MasksParams, ctx: Any) -> dict[str, Any]:
    """Frame i -> {static: uint8 (H, W), 1 = static, solve: uint8 (H, W), 1 = static and flow the
    optimisations trust}: the backend's masks with the user's (--masks) pixels set to 0; with
    --masks also user_keep: uint8 (H, W), 1 = not masked by the user (what the later stages
    exclude hard, at every resolution: stages.frontend.user_masks)."""
    masks = _backend_mask(inputs, p, ctx)
    if "source_size" not in inputs:
        return masks
    keep = _user_keep(inputs, masks["static"].shape)
    return {**{k: np.where(keep > 0, v, 0).astype(np.uint8) for k, v in masks.items()}, "user_keep": keep}


def _backend_mask(inputs: dict[str, Any], p: MasksParams, ctx: Any) -> dict[str, Any]:
    """Frame i -> {static, solve}, from its adjacent and chained flows (backend motion), its
    image's Mask R-CNN instances of moving classes (maskrcnn), or both (motion+maskrcnn: static
    where both say static)."""
    semantic = None
    if "maskrcnn" in p.backend:
        from stages.models.maskrcnn import semantic_static_mask

        semantic = semantic_static_mask(ctx.resource("model"), inputs["image"]["image"],
                                        score_thresh=p.score_thresh, dilate=p.dilate)
        if p.backend == "maskrcnn":
            return {"static": semantic, "solve": semantic}
    fwd = inputs["direction"] == "fwd"
    chain = [(fl["fwd"], fl["fwd_valid"]) if fwd else (fl["bwd"], fl["bwd_valid"]) for fl in inputs["chain"]]
    h, w = chain[0][0].shape[:2]
    if p.backend == "none":
        return {"static": np.ones((h, w), np.uint8), "solve": np.ones((h, w), np.uint8)}
    neighbours = [chain[0]]
    if len(chain) > 1:
        neighbours.append(flow.chain_flows(chain))
    image = inputs["image"]["image"] if p.texture_frac > 0 else None
    motion, solve = masks_mod.motion_masks(np.asarray(inputs["K"]), neighbours, image=image, dilate=p.dilate,
                                           sigma_mult=p.sigma_mult, texture_frac=p.texture_frac)
    if semantic is not None:
        motion, solve = np.minimum(motion, semantic), np.minimum(solve, semantic)
    return {"static": motion, "solve": solve}


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


def _mask_summary(view, p: MasksParams) -> dict[str, Any] | None:
    """{"user_masks": True} when the items carry the user's (--masks) kept pixels, else None (the
    stage's manifest as without a summary): what later items functions ask, without loading an item
    (a read-through run from a remote fetches no mask item then)."""
    return {"user_masks": True} if p.user_dir or _lens_border(view) else None


def _has_user_masks(view) -> bool:
    """Whether the masks stage's items carry the user's (--masks) kept pixels (user_keep)."""
    return bool((view.summary(MASKS) or {}).get("user_masks"))


def _user_mask_refs(user: bool, frames: list[int]) -> dict[str, Any]:
    """{"user_masks": the mask items of ``frames``} with --masks (``user``: their user_keep), {}
    without (the items are keyed as before)."""
    return {"user_masks": [ItemRef(MASKS, j) for j in frames]} if user else {}


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


MASKS = declare(MapStage("masks", run_masks, deps=(INGEST, CALIBRATE, FLOW), params="masks", kind="mask",
                 items=_mask_items, summary=_mask_summary, resources={"model": _open_maskrcnn},
                 description="1 = static"))


# ============================================================================== priors
PriorsParams = section("priors", frontend_params.PriorsSettings)


def _prior_items(view, p: PriorsParams):
    # Reference frames span back and span forward (priors.references=symmetric: each pair serves
    # the two frames it joins), or span and span/2 back (references=back): the prior
    # triangulates a direct flow to the reference; chaining adjacent flows drifts ~0.1 px per
    # link, which on ICL turned 2-view poses off by degrees (AbsRel 0.25 vs 0.085 direct).
    # The direct flows are flow_far's items (shared with depth_fusion).
    n = view.len(INGEST)
    index = _far_index(view) if p.backend == "geometric" else {}
    user = p.backend == "geometric" and _has_user_masks(view)
    out = []
    for i in range(n):
        it: dict[str, Any] = {"image": ItemRef(INGEST, i), "K": PartRef(CALIBRATE, ("K",))}
        js = _prior_refs(i, n, p)
        if js:
            it.update(_far_refs(index, i, js, p.preset, p.fb_thresh), **_user_mask_refs(user, [i, *js]))
        out.append(it)
    return out


def _open_midas(p: PriorsParams) -> Any:
    return open_model("midas", p.weights)


def run_priors(inputs: dict[str, Any], p: PriorsParams, ctx: Any) -> dict[str, Any]:
    """Frame i -> {inv_depth float32 (H, W) median 1, confidence float32 (H, W)}."""
    image = inputs["image"]["image"]
    if p.backend == "midas":
        from stages.models.midas import midas_prior

        inv = midas_prior(ctx.resource("model"), image)
        return {"inv_depth": inv.astype(np.float32), "confidence": np.ones_like(inv, np.float32)}
    K = np.asarray(inputs["K"])
    # direct flows to the far reference (more parallax) and the near one (sees what the far
    # one lost); the prior fuses both (stages.frontend.priors.geometric_prior)
    flows = []
    keep = [np.asarray(m["user_keep"]) > 0 for m in inputs.get("user_masks", [])]  # --masks: frame i's, the refs'
    for k, (fl, direction) in enumerate(zip(inputs.get("refs", []), inputs.get("ref_dirs", []))):
        fwd, valid = _far_flow(fl, direction)
        if valid.mean() >= priors_mod.MIN_VALID_FRACTION:
            if keep:  # no triangulation of, or from, a user-masked pixel
                valid = valid & keep[0] & user_masks.flow_target_kept(fwd, keep[k + 1])
            flows.append((fwd, valid))
    out = priors_mod.geometric_prior(image, K, flows[:1], extra=flows[1:]) if flows else None
    if out is None:
        h, w = image.shape[:2]
        out = {"inv_depth": np.ones((h, w), np.float32), "confidence": np.zeros((h, w), np.float32)}
    return {"inv_depth": out["inv_depth"].astype(np.float32),
            "confidence": out["confidence"].astype(np.float32)}


PRIORS = declare(MapStage("priors", run_priors, deps=(INGEST, CALIBRATE, FLOW_FAR, MASKS), params="priors", kind="prior",
                  items=_prior_items, resources={"model": _open_midas},
                  description="MiDaS-shaped relative inverse depth"))


# ============================================================================== keyframes
KeyframesParams = section("keyframes", graph_params.KeyframesSettings)


def run_keyframes(inputs: dict[str, Any], p: Any, ctx: Any) -> dict[str, Any]:
    """All frames -> {indices, accumulated, threshold_px, motion} (JSON)."""
    flows, masks_ = inputs["flow"], inputs["masks"]
    n = len(masks_)
    motion = [keyframes_mod.pair_motion(flows[i]["fwd"], flows[i]["fwd_valid"], _solve_mask(masks_[i]))
              for i in range(n - 1)]
    h, w = masks_[0]["static"].shape
    if not p.enabled:  # ablation "w/o keyframes": every frame is a keyframe
        return {"indices": list(range(n)), "accumulated": [0.0] * n, "threshold_px": 0.0,
                "motion": motion, "enabled": False}
    sel = keyframes_mod.select_keyframes(np.asarray(motion), h, w, delta=p.delta, max_gap=p.max_gap)
    return {"indices": [int(i) for i in sel["indices"]],
            "accumulated": [float(a) for a in sel["accumulated"]],
            "threshold_px": float(sel["threshold_px"]), "motion": [float(m) for m in motion],
            "enabled": True}


KEYFRAMES = declare(Stage("keyframes", run_keyframes, deps=(FLOW, MASKS), params="keyframes", kind="keyframes"))


# ============================================================================== association
AssociationParams = section("association", graph_params.AssociationSettings)


def _open_resnet(p: AssociationParams) -> Any:
    return open_model("resnet18", p.weights)


def run_association(inputs: dict[str, Any], p: Any, ctx: Any) -> dict[str, Any]:
    """Keyframes -> {graph (JSON), edge_flows [{i, j, fwd, bwd, fwd_valid, bwd_valid}]}."""
    # heavy (torch / gtsam / scipy): imported when the stage runs, not when the CLI starts
    from stages.graph import association as association_mod

    kf = inputs["keyframes"]["indices"]
    frames = inputs["ingest"]
    K = np.asarray(inputs["calibrate"]["K"])
    images = [frames[i]["image"] for i in kf]
    kw: dict[str, Any] = dict(nms=p.nms, min_separation=p.min_separation,
                              min_inlier_ratio=p.min_inlier_ratio, min_consistent=p.min_consistent,
                              verify=p.verify, min_inliers=p.min_inliers, min_epipolar=p.min_epipolar,
                              per_keyframe=p.per_keyframe, max_candidates=p.max_candidates, retrieval=p.retrieval,
                              words=p.words, top_k=p.top_k, min_ratio=p.min_ratio, window=p.window,
                              loop_nms=p.loop_nms, min_departure=p.min_departure,
                              prewarp_sequential=p.prewarp_sequential)
    if p.threshold is not None:
        kw["similarity_threshold"] = p.threshold
    if p.backend == "resnet18":
        from stages.models.resnet import resnet_descriptor

        model = ctx.resource("model")
        kw["descriptor_fn"] = lambda img: resnet_descriptor(model, img)
    if not p.enabled:
        kw["descriptors"] = np.eye(len(kf), dtype=np.float32)  # nothing similar: no loop edges
        kw["similarity_threshold"] = 2.0
    graph, edge_flows = association_mod.build_graph(kf, images, K, inputs["keyframes"]["threshold_px"] or 1e9,
                                                    call_map=ctx.map, **kw)
    flows_out = [{"i": int(a), "j": int(b), **{k: v for k, v in fl.items() if k in ("fwd", "bwd", "fwd_valid", "bwd_valid")}}
                 for (a, b), fl in sorted(edge_flows.items())]
    return {"graph": graph, "edge_flows": flows_out}


ASSOCIATION = declare(Stage("association", run_association, deps=(INGEST, CALIBRATE, KEYFRAMES), params="association",
                    kind="graph", resources={"model": _open_resnet}))


# ============================================================================== optimisation: shared
DepthParams = config_section("depth")(section_from_dataclass(opt_params.DepthModel, "DepthParams"))
LossParams = config_section("losses")(section_from_dataclass(opt_params.LossWeights, "LossParams"))
OptimizeKeyframesParams = config_section("optimize_keyframes")(
    section_from_dataclass(opt_params.KeyframeSettings, "OptimizeKeyframesParams"))
OptimizeEdgesParams = config_section("optimize_edges")(section_from_dataclass(opt_params.EdgeSettings, "OptimizeEdgesParams"))
OptimizeSegmentsParams = config_section("optimize_segments")(section_from_dataclass(opt_params.SegmentSettings, "OptimizeSegmentsParams"))

# the sections every optimisation stage reads (optimize_keyframes also holds the shared solver
# settings: pose_lr, mesh_lr_mult, mesh_shape_lr_frac, points, taus, flow_taus, threads, ...)
OPT = ("depth", "losses", "optimize_keyframes")


def _stack(items: Any, indices: list[int], field: str) -> np.ndarray:
    return np.stack([np.asarray(items[i][field]) for i in indices])


def _flow_dict(fl: dict[str, Any]) -> dict[str, np.ndarray]:
    return {k: np.asarray(fl[k]) for k in ("fwd", "bwd", "fwd_valid", "bwd_valid")}


def _inv(T: np.ndarray) -> np.ndarray:
    return np.linalg.inv(np.asarray(T, np.float64))


# ============================================================================== optimize_keyframes
def run_optimize_keyframes(inputs: dict[str, Any], b: Any, ctx: Any) -> dict[str, Any]:
    """Keyframe windows -> {keyframes, poses (K,4,4) T_w_c, depths [K x (H,W)],
    rel_poses [{a, b, tau, T_b_a = inv(T_w_b) @ T_w_a}], state, windows}."""
    # heavy (torch / gtsam / scipy): imported when the stage runs, not when the CLI starts
    from stages.optimize import keyframes as opt_keyframes

    kf = list(inputs["keyframes"]["indices"])
    frames = inputs["ingest"]
    pair_flows = keyframes_mod.keyframe_pair_flows(kf, inputs["association"]["edge_flows"])
    res = opt_keyframes.optimize_keyframes(
        _stack(frames, kf, "image"), _stack(inputs["priors"], kf, "inv_depth"),
        np.stack([_hard_mask(inputs["masks"][i]) for i in kf]), np.asarray(inputs["calibrate"]["K"]), pair_flows,
        depth=b.depth, losses=b.losses, kf=b.optimize_keyframes, seed=ctx.seed, checkpointer=ctx.checkpointer,
        window_map=ctx.map)  # schedule=independent: the windows side by side on the run's workers
    return {"keyframes": kf, "poses": np.asarray(res["poses"], np.float64),
            "depths": [np.asarray(d, np.float32) for d in res["depths"]],
            "rel_poses": [{"a": int(r["a"]), "b": int(r["b"]), "tau": int(r["tau"]),
                           "T_b_a": np.asarray(r["T_b_a"], np.float64)} for r in res["rel_poses"]],
            "state": {k: np.asarray(v) for k, v in res["state"].items()},
            "windows": res["windows"]}  # per window: pairs, points per step, steps run (plateau stop)


OPTIMIZE_KEYFRAMES = declare(Stage("optimize_keyframes", run_optimize_keyframes,
                           deps=(INGEST, CALIBRATE, PRIORS, MASKS, KEYFRAMES, ASSOCIATION), params=OPT,
                           kind="keyframe_solution", uses_seed=True))


# ============================================================================== optimize_edges
def run_optimize_edges(inputs: dict[str, Any], b: Any, ctx: Any) -> dict[str, Any]:
    """Verified non-sequential keyframe pairs -> {edges: [{a, b, i, j, T_b_a, loss}]}, a, b keyframe
    positions, i, j frame indices, T_b_a = inv(T_w_b) @ T_w_a (camera a -> camera b coordinates)."""
    # heavy (torch / gtsam / scipy): imported when the stage runs, not when the CLI starts
    from stages.optimize import edges as opt_edges

    okf = inputs["optimize_keyframes"]
    kf = list(okf["keyframes"])
    pos = {f: k for k, f in enumerate(kf)}
    T_w_k = np.asarray(okf["poses"])
    frames, priors_, masks_ = inputs["ingest"], inputs["priors"], inputs["masks"]
    K = np.asarray(inputs["calibrate"]["K"])
    flows = {(e["i"], e["j"]): _flow_dict(e) for e in inputs["association"]["edge_flows"]}
    graph_edges = [(int(e["i"]), int(e["j"])) for e in inputs["association"]["graph"].get("nonsequential_edges", [])]

    def calls():  # built lazily: only the edges in flight are in memory
        for n, (i, j) in enumerate(graph_edges):
            yield dict(img_a=frames[i]["image"], img_b=frames[j]["image"], prior_a=priors_[i]["inv_depth"],
                       prior_b=priors_[j]["inv_depth"], mask_a=_hard_mask(masks_[i]), mask_b=_hard_mask(masks_[j]), K=K,
                       flow=flows[(i, j)], init_T_b_a=_inv(T_w_k[pos[j]]) @ T_w_k[pos[i]], depth=b.depth,
                       losses=b.losses, kf=b.optimize_keyframes, edge=b.optimize_edges, seed=ctx.seed + n)

    edges = []
    # the edges are independent: side by side on the run's workers (same result wherever)
    for (i, j), res in zip(graph_edges, ctx.map(opt_edges.optimize_edge_call, calls())):
        edges.append({"a": pos[i], "b": pos[j], "i": i, "j": j, "T_b_a": np.asarray(res["T_b_a"], np.float64),
                      "loss": float(res["loss"])})
    return {"edges": edges}


OPTIMIZE_EDGES = declare(Stage("optimize_edges", run_optimize_edges,
                       deps=(INGEST, CALIBRATE, PRIORS, MASKS, ASSOCIATION, OPTIMIZE_KEYFRAMES),
                       params=OPT + ("optimize_edges",), kind="edges", uses_seed=True))


# ============================================================================== pose_graph
PoseGraphParams = section("pose_graph", opt_params.PoseGraphSettings)


def run_pose_graph(inputs: dict[str, Any], p: Any, ctx: Any) -> dict[str, Any]:
    """Keyframe poses + sequential and loop edges -> globally consistent keyframe poses."""
    # heavy (torch / gtsam / scipy): imported when the stage runs, not when the CLI starts
    from stages.geometry import se3
    from stages.optimize import pose_graph as pose_graph_mod

    okf = inputs["optimize_keyframes"]
    T_w_k = np.asarray(okf["poses"], np.float64)
    if not p.enabled or len(T_w_k) < 2:
        return {"poses": T_w_k, "enabled": False, "iterations": 0, "initial_error": 0.0, "final_error": 0.0}
    # edges T_b_a = inv(T_w_b) @ T_w_a as the optimisations give them (the pose graph inverts)
    edges = [{"a": r["a"], "b": r["b"], "T_b_a": r["T_b_a"], "weight": 1.0 / r["tau"]} for r in okf["rel_poses"]]
    rejected = []
    for e in inputs["optimize_edges"]["edges"]:
        # Gate gross outliers: drift bends a trajectory by degrees, not tens of degrees, so a
        # loop measurement that disagrees that much with odometry is a failed edge optimisation.
        angle = se3.loop_disagreement_deg(T_w_k[e["a"]], T_w_k[e["b"]], e["T_b_a"])
        if angle > p.max_loop_rotation_deg:
            rejected.append({"i": e["i"], "j": e["j"], "rotation_disagreement_deg": angle})
            continue
        edges.append({"a": e["a"], "b": e["b"], "T_b_a": e["T_b_a"], "weight": p.loop_weight})
    if rejected:
        ctx.log(f"ignored {len(rejected)} loop edge(s) disagreeing with odometry by > {p.max_loop_rotation_deg} deg")
    res = pose_graph_mod.optimize_pose_graph(T_w_k, edges, kind=p.kind, max_iterations=p.max_iterations)
    return {"poses": np.asarray(res["poses"], np.float64), "enabled": True,
            "iterations": int(res["iterations"]), "initial_error": float(res["initial_error"]),
            "final_error": float(res["final_error"]), "rejected_loops": rejected}


POSE_GRAPH = declare(Stage("pose_graph", run_pose_graph, deps=(OPTIMIZE_KEYFRAMES, OPTIMIZE_EDGES),
                   params="pose_graph", kind="poses"))


# ============================================================================== bundle_adjustment
BundleAdjustmentParams = section("bundle_adjustment", opt_params.BundleAdjustmentSettings)


def run_bundle_adjustment(inputs: dict[str, Any], p: BundleAdjustmentParams, ctx: Any) -> dict[str, Any]:
    """Pose-graph keyframe poses -> {poses (K, 4, 4) T_w_k refined over flow tracks, statistics}."""
    pg = inputs["pose_graph"]
    T_w_k = np.asarray(pg["poses"], np.float64)
    if not p.enabled:
        return {"poses": T_w_k, "enabled": False, "depth_scale": np.ones(len(T_w_k))}
    # heavy (torch / gtsam / scipy): imported when the stage runs, not when the CLI starts
    from threadpoolctl import threadpool_limits

    from gcvd_flow.io.native_output import native_stdout_silenced
    from stages.optimize import bundle_adjustment as ba_mod

    okf = inputs["optimize_keyframes"]
    edges = {(int(e["i"]), int(e["j"])): _flow_dict(e) for e in inputs["association"]["edge_flows"]}
    # numpy's OpenBLAS on one thread: its idle threads spin (OMP_WAIT_POLICY does not reach its
    # pthreads), so two runs adjusting at once on two cores took 55 s instead of 1.6; a second
    # thread bought nothing alone (2.4 vs 2.4 s), and one thread makes the result independent of
    # the machine's core count (OpenBLAS's default thread count changed the poses' bits)
    with native_stdout_silenced(), threadpool_limits(limits=1, user_api="blas"):
        res = ba_mod.bundle_adjust(T_w_k, [np.asarray(d) for d in okf["depths"]], edges, list(okf["keyframes"]),
                                   np.asarray(inputs["calibrate"]["K"]), stride=p.stride,
                                   track_length=p.track_length, min_views=p.min_views, robust_px=p.robust_px,
                                   prior_rot_sigma=p.prior_rot_sigma, prior_trans_frac=p.prior_trans_frac,
                                   max_iterations=p.max_iterations, consistent_px=p.consistent_px,
                                   solver=p.solver, keep=_user_keeps(inputs["masks"], okf["keyframes"]))
    ctx.log(f"{res['landmarks']} tracks, {res['observations']} observations, median reprojection error "
            f"{res['initial_median_px']:.2f} -> {res['final_median_px']:.2f} px"
            + (" (poses kept: already consistent with the tracks)" if res["skipped"] and res["landmarks"] else ""))
    return {"poses": np.asarray(res["poses"], np.float64), "enabled": True, "landmarks": res["landmarks"],
            "observations": res["observations"], "initial_median_px": res["initial_median_px"],
            "final_median_px": res["final_median_px"], "iterations": res["iterations"],
            "skipped": bool(res["skipped"]), "depth_scale": np.asarray(res["depth_scale"], np.float64)}


BUNDLE_ADJUSTMENT = declare(Stage("bundle_adjustment", run_bundle_adjustment,
                                  deps=(INGEST, CALIBRATE, MASKS, ASSOCIATION, OPTIMIZE_KEYFRAMES, POSE_GRAPH),
                                  params="bundle_adjustment", kind="poses"))


# ============================================================================== optimize_segments
class _FlowDicts:
    """flows[i] -> the arrays of pair (i, i+1)'s flow."""

    def __init__(self, items: Any):
        self._items = items

    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, i: int) -> dict[str, np.ndarray]:
        return _flow_dict(self._items[i])


class _ScaledDepths:
    """depths[k] * scale[k] on access: the keyframe depths in bundle adjustment's scale without
    a second copy of all of them."""

    def __init__(self, depths: Any, scale: np.ndarray):
        self._depths, self._scale = depths, scale

    def __len__(self) -> int:
        return len(self._depths)

    def __getitem__(self, k: int) -> np.ndarray:
        return np.asarray(self._depths[k], np.float32) * self._scale[k]


def run_optimize_segments(inputs: dict[str, Any], b: Any, ctx: Any) -> dict[str, Any]:
    """All frames with keyframe poses frozen -> {poses (N,4,4) T_w_c, depths [N x (H,W)]}.

    The windows are solved side by side on the run's worker processes (``ctx.map``; the result
    does not depend on where). Images, priors and masks are read one window at a time (lazily
    stacked fields) and flows through a window-sized cache of decoded items, and each window's
    depth maps go to the store as soon as they are final (``ctx.put``): memory stays flat in the
    clip length (at 256x192 one flow pair is ~0.9 MB, one depth map 0.19 MB)."""
    # heavy (torch / gtsam / scipy): imported when the stage runs, not when the CLI starts
    from stages.optimize import segments as opt_segments

    frames, flows = inputs["ingest"], inputs["flow"]
    okf, ba = inputs["optimize_keyframes"], inputs["bundle_adjustment"]
    masks_ = inputs["masks"]
    hard = _HardMasks(masks_) if "user_keep" in masks_[0] else masks_.field("solve")  # --masks: int8, -1 = user's
    res = opt_segments.optimize_segments(
        frames.field("image"), inputs["priors"].field("inv_depth"), hard,
        np.asarray(inputs["calibrate"]["K"]), _FlowDicts(flows.recent(48)), list(okf["keyframes"]),
        np.asarray(ba["poses"]), _ScaledDepths(okf["depths"], np.asarray(ba["depth_scale"], np.float32)),
        depth=b.depth, losses=b.losses, kf=b.optimize_keyframes, seg=b.optimize_segments,
        seed=ctx.seed, checkpointer=ctx.checkpointer, state=okf["state"], depth_sink=lambda i, d: ctx.put(d),
        window_map=ctx.map)
    # depths: one handle per frame, each depth map stored when its window finished
    return {"poses": np.asarray(res["poses"], np.float64), "depths": res["depths"]}


OPTIMIZE_SEGMENTS = declare(Stage("optimize_segments", run_optimize_segments,
                          deps=(INGEST, CALIBRATE, FLOW, PRIORS, MASKS, OPTIMIZE_KEYFRAMES, BUNDLE_ADJUSTMENT),
                          params=OPT + ("optimize_segments",), kind="segment_solution", uses_seed=True))


# ============================================================================== depth_fusion
# Each frame's fusion references (depth_fusion.references): "baseline" chooses them from the final
# poses and a grid of each frame's depth (fusion_samples) by triangulation angle and overlap
# (stages.graph.references.baseline_references), in the fusion_references stage (a map stage of
# one item, so it reads parts, never a whole clip's depth maps), so they are cached, named in its output and explained by
# plan / why like any stage; the flows of the chosen pairs that no other stage computes are the
# items of fusion_flow (keyed by the two images, preset and threshold only, like flow_far's).
# "offsets" is the fixed-offset rule, its flows flow_far's items.
DepthFusionParams = section("depth_fusion", depth_params.DepthFusionSettings)


FusionReferencesParams = section("fusion_references", depth_params.FusionReferencesSettings)


def _reference_rule(q: FusionReferencesParams) -> references.ReferenceRule:
    return references.ReferenceRule(max_refs=q.max_refs, max_gap=q.max_gap, target_angle_deg=q.target_angle_deg,
                                    min_angle_deg=q.min_angle_deg, max_angle_deg=q.max_angle_deg,
                                    min_overlap=q.min_overlap, new_flow_cost=q.new_flow_cost,
                                    max_new=q.max_new_flows)


def _fusion_samples_items(view, p: DepthFusionParams):
    baseline = p.enabled and p.references == "baseline"
    return [{"K": PartRef(CALIBRATE, ("K",)), "depth": PartRef(OPTIMIZE_SEGMENTS, ("depths", i))}
            for i in range(view.len(INGEST) if baseline else 0)]


def run_fusion_samples(inputs: dict[str, Any], p: DepthFusionParams, ctx: Any) -> dict[str, Any]:
    """Frame i's optimised depth -> {points float32 (M, 3): a grid of its pixels in camera
    coordinates (pose scale), size int [w, h]}: what fusion_references projects, a few KB per frame
    (the whole clip's depth maps are never held at once)."""
    d = np.asarray(inputs["depth"], np.float32)
    return {"points": references.view_samples(d, np.asarray(inputs["K"], np.float64)).astype(np.float32),
            "size": np.asarray([d.shape[1], d.shape[0]], np.int64)}


FUSION_SAMPLES = declare(MapStage("fusion_samples", run_fusion_samples, deps=(INGEST, CALIBRATE, OPTIMIZE_SEGMENTS),
                                  params="depth_fusion", kind="fusion_samples", items=_fusion_samples_items,
                                  description="a grid of each frame's optimised depth, for choosing its "
                                              "fusion references"))


def _fusion_references_items(view, b: Any):
    # one item: the clip's poses, its frames' samples and flow_far's pairs, each read as a part
    # (no stage's whole output is decoded: the clip's depth maps are never held at once)
    p = b.depth_fusion
    baseline = p.enabled and p.references == "baseline"
    return [{"n": Const(view.len(INGEST)), "K": PartRef(CALIBRATE, ("K",)),
             "poses": PartRef(OPTIMIZE_SEGMENTS, ("poses",)),
             "samples": [ItemRef(FUSION_SAMPLES, i) for i in range(view.len(FUSION_SAMPLES))] if baseline else [],
             "far_pairs": PartRef(FLOW_FAR, ("pairs",), summary=True) if baseline else Const([])}]


def run_fusion_references(inputs: dict[str, Any], b: Any, ctx: Any) -> dict[str, Any]:
    """The clip (one item) -> {refs: per frame its reference frames (list of int lists), flows:
    the pairs [a, b], a < b, fusion_flow computes (neither adjacent nor flow_far's)}."""
    p = b.depth_fusion
    n = int(inputs["n"])
    if not p.enabled:
        return {"refs": [[] for _ in range(n)], "flows": []}
    if p.references == "offsets":
        return {"refs": [_fusion_refs(i, n, p) for i in range(n)], "flows": []}
    poses = np.asarray(inputs["poses"], np.float64)
    K = np.asarray(inputs["K"], np.float64)
    samples = [np.asarray(it["points"], np.float64) for it in inputs["samples"]]
    w, h = (int(v) for v in np.asarray(inputs["samples"][0]["size"]))
    free = [(a, c) for a, c, preset, fb in inputs["far_pairs"]
            if preset == p.preset and float(fb) == float(p.fb_thresh)]
    refs, flows = references.baseline_references(poses, samples, K, (w, h), _reference_rule(b.fusion_references),
                                                 free)
    return {"refs": refs, "flows": [list(pr) for pr in flows]}


FUSION_REFERENCES = declare(MapStage("fusion_references", run_fusion_references,
                                     deps=(INGEST, CALIBRATE, FLOW_FAR, OPTIMIZE_SEGMENTS, FUSION_SAMPLES),
                                     params=("depth_fusion", "fusion_references"), kind="fusion_references",
                                     items=_fusion_references_items,
                                     description="each frame's depth_fusion references, chosen by triangulation "
                                                 "angle and overlap at the final poses (one item: the clip)"))


def _fusion_flow_items(view, b: Any):
    p = b.depth_fusion
    return [{"a": ItemRef(INGEST, a), "b": ItemRef(INGEST, c), "preset": Const(p.preset),
             "fb_thresh": Const(float(p.fb_thresh))} for a, c in view.value(FUSION_REFERENCES)[0]["flows"]]


# the same function as flow_far's: one DIS forward + backward per pair
FUSION_FLOW = declare(MapStage("fusion_flow", run_flow_far, deps=(INGEST, FUSION_REFERENCES),
                               params=("depth_fusion",), kind="flow_far", items=_fusion_flow_items,
                               # the section as a bundle, left out of item keys: an item is keyed by
                               # its two images, preset and threshold only
                               selection_params=("depth_fusion",),
                               description="direct flows of the fusion reference pairs no other stage computes"))


def _fusion_items(view, p: DepthFusionParams):
    # a reference's flow: the flow stage's pair (adjacent), flow_far's (shared with priors) or
    # fusion_flow's, seen from frame i ("fwd": i is the pair's first frame, "bwd": its second)
    n = view.len(INGEST)
    chosen = view.value(FUSION_REFERENCES)[0]
    far = _far_index(view) if p.enabled else {}
    own = {tuple(pr): k for k, pr in enumerate(chosen["flows"])}
    user = p.enabled and _has_user_masks(view)
    out = []
    for i in range(n):
        js = [int(j) for j in chosen["refs"][i]]
        refs: list[Any] = []
        for j in js:
            a, c = min(i, j), max(i, j)
            pair = references.far_pair(i, j, p.preset, p.fb_thresh)
            refs.append(ItemRef(FLOW, a) if c - a == 1 else ItemRef(FLOW_FAR, far[pair]) if pair in far
                        else ItemRef(FUSION_FLOW, own[(a, c)]))
        out.append({"index": Const(i), "K": PartRef(CALIBRATE, ("K",)),
                    "poses": PartRef(OPTIMIZE_SEGMENTS, ("poses",)),
                    "depth": PartRef(OPTIMIZE_SEGMENTS, ("depths", i)),
                    "refs": refs, "ref_dirs": Const(["fwd" if i < j else "bwd" for j in js]),
                    "ref_indices": Const(js), **_user_mask_refs(user, [i, *js])})
    return out


def run_depth_fusion(inputs: dict[str, Any], p: DepthFusionParams, ctx: Any) -> dict[str, Any]:
    """Frame i's optimised depth fused with its multi-view triangulation -> {depth float32 (H, W),
    measured float (fraction of pixels triangulated), confidence float32 (H, W) in [0, 1]}."""
    depth = np.asarray(inputs["depth"], np.float32)
    if not p.enabled:
        return {"depth": depth, "measured": 0.0, "confidence": np.zeros_like(depth)}
    poses = np.asarray(inputs["poses"], np.float64)
    i = int(inputs["index"])
    flows = [(*_far_flow(fl, d), poses[int(j)])
             for fl, d, j in zip(inputs["refs"], inputs["ref_dirs"], inputs["ref_indices"])]
    if "user_masks" in inputs:  # --masks: no triangulation of, or from, a user-masked pixel
        keep = [np.asarray(m["user_keep"]) > 0 for m in inputs["user_masks"]]  # frame i's, then the references'
        flows = [(f, v & keep[0] & user_masks.flow_target_kept(f, k), T) for (f, v, T), k in zip(flows, keep[1:])]
    fused, measured, confidence = depth_fusion.fuse_depth_flows(
        depth, poses[i], flows, np.asarray(inputs["K"]), min_angle_deg=p.min_angle_deg,
        max_log_dev=p.max_log_dev, agree_log_dev=p.agree_log_dev, coverage_refs=p.coverage_refs)
    return {"depth": fused, "measured": measured, "confidence": confidence}


DEPTH_FUSION = declare(MapStage("depth_fusion", run_depth_fusion,
                        deps=(INGEST, CALIBRATE, FLOW, FLOW_FAR, MASKS, OPTIMIZE_SEGMENTS, FUSION_REFERENCES,
                              FUSION_FLOW),
                        params="depth_fusion", kind="depth", items=_fusion_items,
                        description="optimised depth fused with multi-view triangulation at the final poses"))


# ============================================================================== depth_filter
DepthFilterParams = section("depth_filter", depth_params.DepthFilterSettings)


def _filter_items(view, p: DepthFilterParams):
    n = view.len(INGEST)
    r = p.radius if p.enabled else 0
    user = r > 0 and _has_user_masks(view)
    out = []
    for i in range(n):
        lo, hi = references.window(i, n, r)
        out.append({"center": Const(i - lo), "depths": [ItemRef(DEPTH_FUSION, j) for j in range(lo, hi + 1)],
                    "flows": [ItemRef(FLOW, j) for j in range(lo, hi)], "image": ItemRef(INGEST, i),
                    **_user_mask_refs(user, list(range(lo, hi + 1)))})
    return out


def run_depth_filter(inputs: dict[str, Any], p: DepthFilterParams, ctx: Any) -> dict[str, Any]:
    """Frame i's depth filtered with its +-radius neighbours -> {depth float32 (H, W),
    confidence float32 (H, W): depth_fusion's, zero where the filter invalidated the depth}."""
    depths = np.stack([np.asarray(d["depth"]) for d in inputs["depths"]])
    center = int(inputs["center"])
    conf = np.asarray(inputs["depths"][center].get("confidence", np.zeros_like(depths[center])), np.float32)
    if not p.enabled or len(depths) == 1:
        return {"depth": depths[center].astype(np.float32), "confidence": conf}
    fwd = np.stack([fl["fwd"] for fl in inputs["flows"]])
    bwd = np.stack([fl["bwd"] for fl in inputs["flows"]])
    if "user_masks" in inputs:  # --masks: nothing at or next to a user-masked pixel is read: the
        # neighbours' depths there are invalid (0), and a track whose flow sample meets one (on
        # its way through any frame, there or back) becomes NaN, which the filter drops
        keep = [_eroded_keep(m) for m in inputs["user_masks"]]
        depths = np.stack([d if j == center else np.where(k, d, 0) for j, (d, k) in enumerate(zip(depths, keep))])
        fwd = np.where(np.stack(keep[:-1])[..., None], fwd, np.nan).astype(np.float32)  # on frame k's grid
        bwd = np.where(np.stack(keep[1:])[..., None], bwd, np.nan).astype(np.float32)  # on frame k+1's grid
    out = np.asarray(depth_filter.filter_depth(depths, fwd, bwd, center, radius=p.radius, border=p.border),
                     np.float32)
    conf = np.where(out > 0, conf, 0.0).astype(np.float32)
    if p.fill_below > 0:
        gray = np.asarray(inputs["image"]["image"], np.float64).mean(axis=2) / 255.0
        out = depth_filter.fill_uncertain(gray, out, conf, source=p.fill_from, full=p.fill_below)
    return {"depth": out, "confidence": conf}


DEPTH_FILTER = declare(MapStage("depth_filter", run_depth_filter, deps=(INGEST, FLOW, MASKS, DEPTH_FUSION), params="depth_filter",
                        kind="depth", items=_filter_items))


# ============================================================================== depth_consensus
DepthConsensusParams = section("depth_consensus", depth_params.DepthConsensusSettings)


def _consensus_items(view, p: DepthConsensusParams):
    n = view.len(INGEST)
    out = []
    for i in range(n):
        refs = references.symmetric_references(i, n, p.offsets) if p.enabled else []
        splat = references.symmetric_references(i, n, p.splat_offsets) if p.enabled and p.splat_offsets else []
        both = refs + [j for j in splat if j not in refs]  # the carry's first, in its order
        out.append({"index": Const(i), "K": PartRef(CALIBRATE, ("K",)),
                    "poses": PartRef(OPTIMIZE_SEGMENTS, ("poses",)), "depth": ItemRef(DEPTH_FILTER, i),
                    "refs": [ItemRef(DEPTH_FILTER, j) for j in both], "ref_indices": Const(both),
                    "static": [ItemRef(MASKS, j) for j in [i, *both]] if both else [],
                    **({"splat_indices": Const(splat), "image": ItemRef(INGEST, i)} if splat else {})})
    return out


def run_depth_consensus(inputs: dict[str, Any], p: DepthConsensusParams, ctx: Any) -> dict[str, Any]:
    """Frame i's filtered depth averaged with the depths its references see at its pixels (moving
    pixels, by the masks stage, left out), then (splat_offsets) corrected with their confident
    depth splatted into it -> {depth float32 (H, W), confidence float32 (H, W): depth_filter's,
    unchanged}."""
    own = inputs["depth"]
    depth = np.asarray(own["depth"], np.float32)
    conf = np.asarray(own.get("confidence", np.zeros_like(depth)), np.float32)
    if not p.enabled or not inputs["refs"]:
        return {"depth": depth, "confidence": conf}
    poses = np.asarray(inputs["poses"], np.float64)
    idx = [int(j) for j in inputs["ref_indices"]]
    refs = [(np.asarray(r["depth"]), np.asarray(r.get("confidence", np.zeros_like(depth))), poses[j])
            for r, j in zip(inputs["refs"], idx)]
    static = [np.asarray(m["static"]) for m in inputs["static"]]  # frame i's, then the references'
    if "user_keep" in inputs["static"][0]:  # --masks: no reference sample mixes a user-masked pixel
        static[1:] = [np.where(_eroded_keep(m), st, 0) for m, st in zip(inputs["static"][1:], static[1:])]
    # with splat_offsets the items add the splat's references: carry only the consensus's own offsets
    carry = ([k for k, j in enumerate(idx) if abs(j - int(inputs["index"])) in set(p.offsets)]
             if "splat_indices" in inputs else list(range(len(idx))))
    pose, K = poses[int(inputs["index"])], np.asarray(inputs["K"])
    out = depth_consensus.consensus_depth(depth, conf, pose, [refs[k] for k in carry], K,
                                          max_log_dev=p.max_log_dev, reproj_sigma_px=p.reproj_sigma_px,
                                          static=static[0], ref_static=[static[1 + k] for k in carry])
    if "splat_indices" in inputs:
        use = set(int(j) for j in inputs["splat_indices"])
        sel = [k for k, j in enumerate(idx) if j in use]
        gray = np.asarray(inputs["image"]["image"], np.float64).mean(axis=2) / 255.0
        out = depth_consensus.splat_consensus(out, conf, pose, [refs[k] for k in sel], K, guide=gray,
                                              min_confidence=p.splat_min_confidence, front=p.splat_front,
                                              static=static[0], ref_static=[static[1 + k] for k in sel],
                                              keep_confidence=p.splat_keep, keep_edges=p.splat_keep_edges or None,
                                              ref_edge_jump=p.splat_ref_edge_jump or None)
    if p.edge_jump > 0:
        conf = depth_consensus.edge_confidence(out, conf, p.edge_jump)
    return {"depth": out, "confidence": conf}


DEPTH_CONSENSUS = declare(MapStage("depth_consensus", run_depth_consensus,
                                   deps=(INGEST, CALIBRATE, MASKS, OPTIMIZE_SEGMENTS, DEPTH_FILTER),
                                   params="depth_consensus",
                                   kind="depth", items=_consensus_items,
                                   description="filtered depth averaged with what confident views of the "
                                               "same points say, carried with the final poses"))


# ============================================================================== the pipeline
# The run's whole configuration: ``seed`` plus one section per declared config section.
GCVDConfig = create_model("GCVDConfig", __config__=ConfigDict(extra="forbid"), seed=(int, 0),
                          **{name: (model, model()) for name, model in _SECTIONS.items()})


PROFILES: dict[str, dict[str, Any]] = {
    # The paper's / authors' settings (GPU-sized), and the paper's method: no bundle adjustment.
    "paper": {
        "bundle_adjustment": {"enabled": False},
        "association": {"verify": "paper", "per_keyframe": 0, "retrieval": "global", "prewarp_sequential": "on"},
        "ingest": {"long_side": 384, "min_short_frac": 0.0},
        "flow": {"preset": "medium"},
        "optimize_keyframes": {"window": 40, "overlap": 8, "steps": 300, "lr": 2e-4, "points": 1024,
                               "points_by_weight": False, "stop_rel": 0.0, "photo_warp": "pixel"},
        "optimize_edges": {"steps": 300, "lr": 1e-4},
        "optimize_segments": {"steps": 100, "lr": 1e-4, "loss_scale": 1.0},
    },
    # Quick look / CI: small images, few steps.
    "fast": {
        "ingest": {"long_side": 160},
        "flow": {"preset": "fast"},
        "optimize_keyframes": {"steps": 60},
        "optimize_edges": {"steps": 40},
        "optimize_segments": {"steps": 25},
    },
}


def limit_threads() -> None:
    """Worker processes share the cores: one torch / OpenCV thread each, idle OpenMP threads
    asleep (``gcvd_flow.runtime.quiet_openmp``; workers not started by our CLI, e.g. Dask's)."""
    from gcvd_flow.runtime import quiet_openmp

    quiet_openmp()
    import cv2
    import torch

    torch.set_num_threads(1)
    cv2.setNumThreads(1)


PIPELINE = Pipeline(
    list(_STAGES),
    packages=("stages", "gcvd_flow.pipeline"),
    # every third-party library whose code computes a stored result (tests/test_keys.py finds
    # them in the stages' imports); the engine adds its codecs (numpy, Pillow, safetensors)
    numeric_libraries=(("torch", ("torch",)), ("opencv", ("opencv-python-headless", "opencv-python")),
                       ("kornia", ("kornia",)), ("gtsam", ("gtsam",)), ("scipy", ("scipy",))),
    numeric_settings=(("device", "cpu"), ("dtype", "float32"), ("deterministic", True)),
    worker_init=limit_threads,
)

STAGE_NAMES = PIPELINE.names()


def open_source(path: str, config: GCVDConfig) -> Source:
    import os
    import stat

    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise UsageError(f"{path}: no such file or directory") from None
    except OSError as exc:
        raise UsageError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise UsageError(f"{path}: not a video file or a folder (a device, FIFO or socket cannot be an input)")
    src = _open_source(path)
    p = config.ingest
    n_sel = len(range(len(src.items))[p.start:p.end:p.stride])
    if n_sel < 2:
        raise UsageError(f"{path}: ingest selects {n_sel} frame(s) of {len(src.items)} "
                         f"(start={p.start}, end={p.end}, stride={p.stride}); need at least 2")
    given, origin = _camera(src, p)  # a camera no lens has: one line, exit 2, before anything runs
    w, h = ingest_mod.working_size(src.size[0], src.size[1], p.long_side, p.min_short_frac)
    cam = ingest_mod.make_camera(src.size[0], src.size[1], w, h, None if given is None else given.intrinsics, origin)
    K = cam["K"]
    note = ("not given: the focal length will be estimated from the video (calibrate stage; or pass "
            "--intrinsics fx,fy,cx,cy)" if cam["guessed"] and config.calibrate.mode == "auto" else
            "GUESSED, pass --intrinsics fx,fy,cx,cy for accurate results" if cam["guessed"] else origin)
    note += "" if given is None or not given.distorted else f"; lens {given.describe()}: undistorted at ingest"
    print(f"camera: {src.layout} input {src.size[0]}x{src.size[1]} -> working {w}x{h}, fx={K[0, 0]:.1f} "
          f"fy={K[1, 1]:.1f} cx={K[0, 2]:.1f} cy={K[1, 2]:.1f} ({note})", file=sys.stderr)
    return src


# The run's three parts as benchmarks report them: pre-processing (up to the keyframe optimisation),
# the paper's optimisation (keyframes .. segments) and the depth post-processing, from the order above
# (a stage added anywhere lands in exactly one of them).
_A, _B = STAGE_NAMES.index(OPTIMIZE_KEYFRAMES.name), STAGE_NAMES.index(OPTIMIZE_SEGMENTS.name)
STAGE_GROUPS = {"pre": tuple(STAGE_NAMES[:_A]), "main": tuple(STAGE_NAMES[_A:_B + 1]), "post": tuple(STAGE_NAMES[_B + 1:])}

# What RUN_DIR is written from (and what its readers look up in the cache): the final frames,
# keyframes, poses and depth of the DAG above.
RUN_DIR_SOURCES = run_dir.RunSources(frames=INGEST, keyframes=KEYFRAMES, poses=OPTIMIZE_SEGMENTS, depth=DEPTH_CONSENSUS,
                                     calibration=CALIBRATE)

SPEC = PipelineSpec("gcvd", PIPELINE, GCVDConfig, PROFILES, open_source=open_source,
                    export=functools.partial(run_dir.write_run_dir, sources=RUN_DIR_SOURCES),
                    schema_dir=artifacts_schema.SCHEMA_DIR)
