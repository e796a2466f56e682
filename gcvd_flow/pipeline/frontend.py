"""Blocks ingest, user_masks, calibrate, flow and flow_far (stages/frontend)."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

import numpy as np

from gcvd_flow.engine.dag import Const, ExternalRef, ItemRef, MapStage, Stage
from gcvd_flow.engine.errors import UsageError
from gcvd_flow.io import run_dir
from gcvd_flow.io.sources import Source
from gcvd_flow.io.weights import open_model
from gcvd_flow.pipeline.context import ItemContext, StageContext
from gcvd_flow.pipeline.registry import declare, section
from gcvd_flow.pipeline.shared import _fusion_far_refs, _MaskFile, _prior_refs, _undistort_of, _user_keep, _user_mask_files
from gcvd_flow.stages.frontend import (
    flow,
    ingest as ingest_mod,
    lens,
    params as frontend_params,
    solvable,
    user_masks,
)
from gcvd_flow.stages.graph import references

if TYPE_CHECKING:  # calibrate itself is imported when the stage runs
    from gcvd_flow.stages.frontend.calibrate import FocalEstimate

# ============================================================================== ingest
IngestParams = section("ingest", frontend_params.IngestSettings)


def _camera(src: Source, p: frontend_params.IngestSettings) -> tuple[lens.Camera | None, str]:
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


def _ingest_items(view, p: frontend_params.IngestSettings):
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


def _ingest_summary(view, p: frontend_params.IngestSettings) -> dict[str, Any]:
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


def run_ingest(inputs: dict[str, Any], p: Any, ctx: ItemContext) -> dict[str, Any]:
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


def source_positions(cameras: dict[str, Any], shape: tuple[int, int]) -> np.ndarray | None:
    """For a run whose frames ingest undistorted (cameras.json: distortion, distortion_model,
    distortion_intrinsics, source_width, source_height): where each pixel of its (h, w) =
    ``shape`` maps was seen in the source frame, float64 (h, w, 2) source px (x, y); None when the
    frames were not undistorted (the maps and the source frame share their geometry)."""
    if not cameras.get("distortion"):
        return None
    fx, fy, cx, cy = (float(v) for v in cameras["distortion_intrinsics"])
    cam = lens.Camera(fx, fy, cx, cy, cameras.get("distortion_model", "OPENCV"),
                      tuple(float(v) for v in cameras["distortion"]))
    return lens.source_positions(cam, (shape[1], shape[0]),
                                 (int(cameras["source_width"]), int(cameras["source_height"])))


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


def run_user_masks(inputs: dict[str, Any], p: Any, ctx: ItemContext) -> dict[str, Any]:
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


def run_calibrate(inputs: dict[str, Any], p: frontend_params.CalibrateSettings, ctx: StageContext) -> dict[str, Any]:
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
    from gcvd_flow.stages.frontend import calibrate as calibrate_mod

    # pixels are square at the source: the working resize (sx, sy) makes fy / fx = sy / sx
    res = calibrate_mod.estimate_focal(_SampledImages(frames), K, p, keep=keep, aspect=sy / sx,
                                       start_map=getattr(ctx, "map", map))  # the starts side by side on the workers
    out.update(pairs=int(res.pairs), rotation_pairs=int(res.rotation_pairs), method=res.method,
               median_px=float(res.median_px), frames=int(res.frames), points=int(res.points),
               iterations=int(res.iterations))
    rel = float(res.rel_sigma)
    out["rel_sigma"] = rel if np.isfinite(rel) else None
    if not res.determined:
        out["warning"] = f"focal length not estimated, the guess f = {K[0, 0]:.1f} px is kept: {res.reason}"
        ctx.log("warning: " + out["warning"])
        out["principal_point"] = {"cx": float(K[0, 2]), "cy": float(K[1, 2]), "sigma_px": None, "estimated": False,
                                  "detail": "assumed at the image centre (the focal length is not determined)"}
        return out
    f = float(res.focal)
    K = K.copy()
    K[0, 0], K[1, 1] = f, f * sy / sx
    K[0, 2], K[1, 2] = (float(v) for v in res.principal_point)
    out.update(K=K, estimated=True, guessed=False, focal_source=[f / sx, f / sx],
               origin=f"estimated from the video: f = {f:.1f} px +- {100 * rel:.1f} % at {cam['width']}x"
                      f"{cam['height']} ({len(frames)} frames, {res.pairs} pairs)")
    ctx.log(f"focal length estimated: {f:.1f} px +- {100 * rel:.1f} % (guess {cam['K'][0][0]:.1f}; {res.method}: "
            f"{res.frames} frames, {res.points} points, {res.iterations} LM iterations, {res.pairs} pairs of which "
            f"{res.rotation_pairs} "
            f"rotation-only, median residual {res.median_px:.2f} px)")
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


def _principal_point_outcome(res: FocalEstimate, K: np.ndarray, scale: tuple[float, float], out: dict[str, Any],
                             ctx: Any) -> None:
    """The calibrate stage's account of the principal point when the focal length was estimated:
    out's principal_point = {cx, cy (working px), cx_source, cy_source, sigma_px (working, None when
    not estimated), estimated (bool), detail}; a principal point the motion does not determine keeps
    the centre and logs one warning line (out's pp_warning)."""
    sx, sy = scale
    cx, cy = float(K[0, 2]), float(K[1, 2])
    sig = res.pp_sigma
    sig = None if sig is None or not np.all(np.isfinite(sig)) else sig  # artifacts hold finite floats only
    doc: dict[str, Any] = {"cx": cx, "cy": cy, "cx_source": (cx + 0.5) / sx - 0.5, "cy_source": (cy + 0.5) / sy - 0.5,
           "sigma_px": [float(v) for v in sig] if sig is not None else None,
           "sigma_source_px": [float(sig[0]) / sx, float(sig[1]) / sy] if sig is not None else None,
           "estimated": bool(res.pp_estimated),
           "estimate": [float(v) for v in res.pp_estimate] if res.pp_estimate is not None else None}
    if doc["estimated"]:
        est, w = res.pp_estimate or [cx, cy], res.pp_weight or [1.0, 1.0]
        doc["detail"] = (f"estimated from the video: ({cx:.1f}, {cy:.1f}) px, the estimate ({est[0]:.1f}, {est[1]:.1f}) "
                         f"+- ({sig[0]:.1f}, {sig[1]:.1f}) px ({res.pp_z:.1f} std from the image centre) moved "
                         f"towards the centre by its uncertainty (weight {w[0]:.2f}, {w[1]:.2f})")
        ctx.log(f"principal point {doc['detail']} (focal length {res.focal_centre:.1f} px with the centre)")
    elif res.pp_reason:
        doc["detail"] = f"assumed at the image centre: {res.pp_reason}"
        out["pp_warning"] = f"principal point not estimated, the image centre ({cx:.1f}, {cy:.1f}) px is kept: {res.pp_reason}"
        ctx.log("warning: " + out["pp_warning"])
    else:
        doc["detail"] = "image centre" + (f" ({res.pp_note})" if res.pp_note else "")
        if res.pp_note:
            ctx.log(f"principal point: {res.pp_note}")
    out["principal_point"] = doc


CALIBRATE = declare(Stage("calibrate", run_calibrate, deps=(INGEST, USER_MASKS), params="calibrate", kind="calibration",
                          description="one focal length estimated from the video when no intrinsics are given"))


# ============================================================================== flow
FlowParams = section("flow", frontend_params.FlowSettings)


def _flow_items(view, p: frontend_params.FlowSettings):
    return [{"a": ItemRef(INGEST, i), "b": ItemRef(INGEST, i + 1)} for i in range(view.len(INGEST) - 1)]


def _open_raft(p: frontend_params.FlowSettings) -> Any:
    return open_model("raft", p.weights)


def run_flow(inputs: dict[str, Any], p: frontend_params.FlowSettings, ctx: ItemContext) -> dict[str, Any]:
    """Adjacent pair (i, i+1) -> {fwd, bwd (H, W, 2) float32 px, fwd_valid, bwd_valid bool}."""
    model = ctx.resource("model") if p.backend == "raft" else None
    return flow.compute_pair_flow(inputs["a"]["image"], inputs["b"]["image"], backend=p.backend,
                                  preset=p.preset, fb_thresh=p.fb_thresh, model=model)


FLOW = declare(MapStage("flow", run_flow, deps=(INGEST,), params="flow", kind="flow", items=_flow_items,
                resources={"model": _open_raft}, description="forward/backward flow of adjacent pairs + consistency"))


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


def run_flow_far(inputs: dict[str, Any], b: Any, ctx: ItemContext) -> dict[str, Any]:
    """Pair (a, b), a < b -> {fwd, bwd (H, W, 2) float32 px, fwd_valid, bwd_valid bool} (DIS)."""
    return flow.compute_pair_flow(inputs["a"]["image"], inputs["b"]["image"], preset=inputs["preset"],
                                  fb_thresh=inputs["fb_thresh"])


FLOW_FAR = declare(MapStage("flow_far", run_flow_far, deps=(INGEST,), params=("priors", "depth_fusion"),
                   kind="flow_far", items=_flow_far_items, summary=_flow_far_summary,
                   selection_params=("priors", "depth_fusion"),
                   description="direct flows of the pairs priors and depth_fusion triangulate, once per pair"))
