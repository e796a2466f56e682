"""RUN_DIR: what a finished run writes for people and other tools, and reading it back.

    poses.txt            TUM trajectory ``t tx ty tz qx qy qz qw``, T_w_c (camera-to-world); ``t`` is
                         the source timestamp in seconds where the input has one (TUM RGB-D
                         ``rgb.txt``; video: frame index / fps), else the source frame index
    depth/NNNNNN.npy     float32 (H, W) depth at working resolution, one global scale, 0 = invalid
    confidence/NNNNNN.npy float32 (H, W) per-pixel confidence of that depth in [0, 1], 0 = unmeasured
    cameras.json         intrinsics at working resolution, sizes, frame indices (NNNNNN),
                         timestamps and what they are, keyframes, fps
    run.json             written by the engine: resolved config, every stage's key and output digest,
                         and the BLAKE3 digest of every file above (``files``: relative path ->
                         digest; ``compare --check`` and the no-op fast path verify them)
    .gcvd-lock           the writer lock a run holds while it writes RUN_DIR (engine/outputs.py)

``write_run_dir`` is the pipeline's export hook, told by the pipeline which stages it reads
(``RunSources``: ``gcvd_flow.pipeline.RUN_DIR_SOURCES``); ``load_run`` reads and checks a RUN_DIR
with one-line errors naming the file; ``attach_images`` adds the run's frames from the cache.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from gcvd_flow.engine.dag import MapValue, Stage, stage_name
from gcvd_flow.engine.errors import UsageError
from gcvd_flow.io.formats import write_tum_poses

if TYPE_CHECKING:
    import numpy as np


# ------------------------------------------------------------------------------ writing a run


@dataclass(frozen=True, init=False)
class RunSources:
    """The stages RUN_DIR is written from, given by their declarations (or names; held by name):
    ``frames`` a map stage, summary = the camera (K, width, height, source size, frame_indices,
    fps, layout, guessed, origin); ``keyframes`` {indices: keyframe positions}; ``poses`` {poses:
    (N, 4, 4) T_w_c}; ``depth`` a map stage of {depth float32 (H, W), confidence float32 (H, W)};
    ``calibration`` (optional) {K (3, 3) every stage used, estimated, guessed, origin, warning,
    rel_sigma}: without it, the frames' camera."""

    frames: str
    keyframes: str
    poses: str
    depth: str
    calibration: str | None

    def __init__(self, frames: str | Stage, keyframes: str | Stage, poses: str | Stage, depth: str | Stage,
                 calibration: str | Stage | None = None) -> None:
        for k, v in (("frames", frames), ("keyframes", keyframes), ("poses", poses), ("depth", depth)):
            object.__setattr__(self, k, stage_name(v))
        object.__setattr__(self, "calibration", None if calibration is None else stage_name(calibration))


def frame_timestamps(source: Any, idx: list[int]) -> tuple[list[float], str]:
    """poses.txt's ``t`` of source frames ``idx``: (stamps, kind) with kind "seconds" when the
    input has timestamps (``Source.timestamps``: TUM RGB-D rgb.txt, video index / fps), else
    ("frame index") the indices themselves."""
    ts = getattr(source, "timestamps", None)
    if ts and all(0 <= i < len(ts) for i in idx):
        return [float(ts[i]) for i in idx], "seconds"
    return [float(i) for i in idx], "frame index"


def write_run_dir(out: Path, runner: Any, config: Any, sources: RunSources) -> dict[str, Any]:
    """Write RUN_DIR from a finished run: poses.txt (TUM, T_w_c), depth/NNNNNN.npy (float32),
    confidence/NNNNNN.npy (float32 in [0, 1]), cameras.json. ``runner`` is the engine's Runner
    (stage values by name), ``sources`` the stages to read (the pipeline binds them)."""
    import numpy as np

    frames = runner.value(sources.frames)
    cam = frames.summary
    idx = list(cam["frame_indices"])
    # only the poses: decoding the whole segment solution would hold every depth map at once
    poses = np.asarray(runner.part(sources.poses, ("poses",)), np.float64)
    stamps, stamp_kind = frame_timestamps(getattr(runner, "source", None), idx)
    write_tum_poses(out / "poses.txt", np.asarray(stamps, np.float64), poses)
    depth_dir, conf_dir = out / "depth", out / "confidence"
    for d in (depth_dir, conf_dir):
        d.mkdir(exist_ok=True)
        for old in d.glob("*.npy"):
            old.unlink()
    final = runner.value(sources.depth)
    calib = _calibration(runner, cam, sources.calibration)
    unsolvable = {int(k): str(why) for k, why in calib.get("unsolvable") or []}
    for k, i in enumerate(idx):
        item = final[k]
        depth = np.asarray(item["depth"], np.float32)
        if k in unsolvable:  # nothing measured this frame's depth: invalid, never the optimiser's guess
            depth = np.zeros_like(depth)
        np.save(depth_dir / f"{i:06d}.npy", depth, allow_pickle=False)
        if "confidence" in item:  # float32 (H, W) in [0, 1], 0 = unmeasured (stages/depth/fusion.py)
            conf = np.asarray(item["confidence"], np.float32)
            np.save(conf_dir / f"{i:06d}.npy", np.zeros_like(conf) if k in unsolvable else conf, allow_pickle=False)
    if unsolvable:
        _warn_unsolvable(unsolvable, idx)
    K = np.asarray(calib["K"])
    doc = {"width": cam["width"], "height": cam["height"], "fx": K[0, 0], "fy": K[1, 1],
           "cx": K[0, 2], "cy": K[1, 2], "K": K.tolist(), "source_width": cam["source_width"],
           "source_height": cam["source_height"], "intrinsics_guessed": calib["guessed"],
           "intrinsics_origin": "estimated" if calib["estimated"] else calib["origin"],
           **_calibration_doc(calib, K, cam), **_distortion_doc(cam), "frame_indices": idx, "fps": cam.get("fps"),
           "timestamps": stamps, "timestamp_kind": stamp_kind, "layout": cam.get("layout"),
           "keyframes": [idx[k] for k in runner.value(sources.keyframes)["indices"]],
           **({"unsolvable_frames": [{"frame": idx[k], "why": why} for k, why in sorted(unsolvable.items())]}
              if unsolvable else {})}
    (out / "cameras.json").write_text(json.dumps(doc, indent=1))
    return {"poses": str(out / "poses.txt"), "depth": str(depth_dir), "confidence": str(conf_dir),
            "cameras": str(out / "cameras.json")}


def _calibration(runner: Any, cam: dict[str, Any], stage: str | None) -> dict[str, Any]:
    """The calibration stage's output (the K every stage used), or the frames' camera for a
    pipeline without such a stage."""
    if stage is not None:
        return runner.value(stage)
    return {"K": cam["K"], "estimated": False, "guessed": cam["guessed"], "origin": cam["origin"],
            "warning": "", "rel_sigma": None}


def frame_ranges(frames: Sequence[int], limit: int = 12) -> str:
    """[3, 4, 5, 9] -> "3-5, 9" (at most ``limit`` ranges, then "... (N frames)")."""
    runs: list[list[int]] = []
    for f in sorted(frames):
        if runs and f == runs[-1][1] + 1:
            runs[-1][1] = f
        else:
            runs.append([f, f])
    parts = [str(a) if a == b else f"{a}-{b}" for a, b in runs]
    return ", ".join(parts[:limit]) + (f", ... ({len(frames)} frames)" if len(parts) > limit else "")


def _warn_unsolvable(unsolvable: dict[int, str], idx: list[int]) -> None:
    """One ``warning:`` line naming the frames whose depth the run marked invalid."""
    import sys

    k, why = next(iter(sorted(unsolvable.items())))
    print(f"warning: {len(unsolvable)} of {len(idx)} frames leave nothing to solve, their depth is marked invalid "
          f"(depth 0, confidence 0): source frames {frame_ranges([idx[j] for j in unsolvable])} (frame {idx[k]}: {why})",
          file=sys.stderr)


def _distortion_doc(cam: dict[str, Any]) -> dict[str, Any]:
    """cameras.json's account of a lens distortion the frames were undistorted with at ingest: the
    model (OPENCV: k1, k2, p1, p2[, k3]; OPENCV_FISHEYE: k1..k4), its coefficients and the source
    intrinsics they refer to. K above is the pinhole camera of the undistorted frames (what every
    stage and export uses)."""
    if cam.get("distortion") is None:
        return {}
    return {"distortion_model": str(cam.get("distortion_model", "OPENCV")), "distortion": [float(v) for v in cam["distortion"]],
            "distortion_intrinsics": [float(v) for v in cam["distortion_intrinsics"]], "frames_undistorted": True}


def _calibration_doc(calib: dict[str, Any], K: Any, cam: dict[str, Any]) -> dict[str, Any]:
    """cameras.json's account of the focal length: estimated (value at source resolution,
    relative uncertainty, what it was estimated from) and any warning; with an estimated focal
    length the principal point's (cx, cy, their std, estimated or assumed at the centre, and a
    warning when the motion did not determine it)."""
    doc: dict[str, Any] = {}
    if calib.get("estimated"):
        fs = calib["focal_source"]
        doc["intrinsics_estimate"] = {
            "fx_source": float(fs[0]), "fy_source": float(fs[1]), "focal": float(K[0, 0]),
            "rel_sigma": calib["rel_sigma"], "sigma_source_px": float(fs[0]) * float(calib["rel_sigma"] or 0.0),
            "pairs": calib["pairs"], "rotation_pairs": calib["rotation_pairs"], "detail": calib["origin"]}
    if calib.get("warning"):
        doc["intrinsics_warning"] = calib["warning"]
    if isinstance(calib.get("principal_point"), dict):  # with an estimated focal length: estimated or assumed
        doc["principal_point"] = calib["principal_point"]
    if calib.get("pp_warning"):
        doc["principal_point_warning"] = calib["pp_warning"]
    return doc


# ------------------------------------------------------------------------------ reading a run


@dataclass
class RunData:
    """What an export needs from RUN_DIR; depth (and images, when available) are read lazily."""

    run_dir: Path
    K: np.ndarray  # (3, 3) at working resolution
    width: int
    height: int
    frame_indices: list[int]  # source frame index of each exported frame
    poses: np.ndarray  # (N, 4, 4) camera-to-world, OpenCV axes
    depth_paths: list[Path]
    fps: float | None = None
    # source timestamp of each frame in seconds (cameras.json "timestamps" when its
    # "timestamp_kind" is "seconds": TUM RGB-D rgb.txt, video index / fps), else None
    timestamps: list[float] | None = None
    images: Sequence[np.ndarray] | None = None  # uint8 (H, W, 3) RGB per frame
    images_error: str | None = None
    # confidence/NNNNNN.npy of every frame, or None: a run dir from before confidence existed, or
    # one where some frames lack the file (``confidence_note`` then says which)
    confidence_paths: list[Path] | None = None
    confidence_note: str | None = None
    _median: float | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.poses)

    def depth(self, k: int) -> np.ndarray:
        import numpy as np

        return np.asarray(self._load_map(self.depth_paths[k], "depth"), np.float32)

    def _load_map(self, p: Path, what: str) -> "np.ndarray":
        """One per-frame .npy map (no pickle), checked against cameras.json's size; one-line
        UsageError naming the file otherwise."""
        import numpy as np

        try:
            m = np.load(p, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise UsageError(f"{p}: not a readable .npy {what} map ({exc})") from None
        if m.shape != (self.height, self.width):
            raise UsageError(f"{p}: {what} is {m.shape}, cameras.json says {self.height}x{self.width}")
        return m

    @property
    def depths(self) -> Sequence[np.ndarray]:
        return MapValue(self.depth, len(self), None)

    @property
    def has_confidence(self) -> bool:
        return self.confidence_paths is not None

    def confidence(self, k: int) -> np.ndarray:
        """float32 (H, W) confidence of frame k's depth in [0, 1] (0 = unmeasured; NaN read as 0,
        values outside [0, 1] clipped). Only when ``has_confidence``."""
        import numpy as np

        assert self.confidence_paths is not None, "the run has no confidence/"
        c = self._load_map(self.confidence_paths[k], "confidence")
        return np.clip(np.nan_to_num(np.asarray(c, np.float32), nan=0.0), 0.0, 1.0)

    def name(self, k: int) -> str:
        return f"{self.frame_indices[k]:06d}"

    def median_depth(self) -> float:
        """Median valid depth over (at most ~50 evenly spread) frames; UsageError if none."""
        if self._median is None:
            from gcvd_flow.io.depth_maps import median_depth  # numpy: imported when used

            step = max(1, len(self) // 50)
            self._median = median_depth(self.depth(k) for k in range(0, len(self), step))
            if not self._median > 0:
                raise UsageError(f"{self.run_dir / 'depth'}: no valid (positive, finite) depth in any frame")
        return self._median


def read_cameras(run: Path) -> dict[str, Any]:
    """RUN_DIR/cameras.json as an object (depth-limited JSON); one-line UsageError otherwise."""
    from gcvd_flow.engine import jsonio

    p = run / "cameras.json"
    cams = jsonio.load_file(p, "cameras file", missing=f"missing (is {run} a finished `gcvd-flow run` directory?)",
                            limit=jsonio.RUN_FILE_BYTES)
    if not isinstance(cams, dict):
        raise UsageError(f"{p}: not an object of camera fields")
    return cams


def load_run(run_dir: str | Path) -> RunData:
    """Read and check RUN_DIR; every problem is a one-line UsageError naming the file."""
    import numpy as np

    from gcvd_flow.io.formats import read_tum_poses

    run = Path(run_dir)
    if not run.exists():
        raise UsageError(f"{run}: no such run directory")
    if not run.is_dir():
        raise UsageError(f"{run}: not a directory (expected a `gcvd-flow run` output directory)")
    cams_path = run / "cameras.json"
    cams = read_cameras(run)
    try:
        K = np.asarray(cams["K"], np.float64)
        width, height = int(cams["width"]), int(cams["height"])
        idx = [int(i) for i in cams["frame_indices"]]
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or width < 1 or height < 1:
            raise ValueError("bad K / width / height")
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise UsageError(f"{cams_path}: missing or malformed K / width / height / frame_indices ({exc})") from None
    _, poses = read_tum_poses(run / "poses.txt")  # DatasetError (a UsageError) names the file
    if len(poses) != len(idx):
        raise UsageError(f"{run / 'poses.txt'}: {len(poses)} poses, but cameras.json lists {len(idx)} frames")
    paths = []
    for i in idx:
        p = run / "depth" / f"{i:06d}.npy"
        if not p.is_file():
            raise UsageError(f"{p}: depth file missing")
        try:  # header only: dtype and shape, before anything is written
            d = np.load(p, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise UsageError(f"{p}: not a readable .npy depth map ({exc})") from None
        if d.shape != (height, width) or d.dtype.kind != "f":
            raise UsageError(f"{p}: depth is {d.dtype} {d.shape}, expected float ({height}, {width})")
        paths.append(p)
    conf_paths, conf_note = _confidence_paths(run, idx)
    fps = cams.get("fps")
    stamps = cams.get("timestamps")
    if not (cams.get("timestamp_kind") == "seconds" and isinstance(stamps, list) and len(stamps) == len(idx)
            and all(isinstance(t, (int, float)) and not isinstance(t, bool) for t in stamps)):
        stamps = None
    return RunData(run, K, width, height, idx, poses, paths,
                   fps=float(fps) if isinstance(fps, (int, float)) and fps > 0 else None,
                   timestamps=[float(t) for t in stamps] if stamps else None,
                   confidence_paths=conf_paths, confidence_note=conf_note)


def _confidence_paths(run: Path, idx: list[int]) -> tuple[list[Path] | None, str | None]:
    """(confidence/NNNNNN.npy of every frame, None) when all are there; (None, None) without
    confidence/ (a run from before it existed); (None, why) when only some frames have one (the
    exports then carry no confidence). Contents are checked by ``check_confidence`` (exports),
    not here: commands that do not read confidence must not fail on it."""
    paths = [run / "confidence" / f"{i:06d}.npy" for i in idx]
    present = [p.is_file() for p in paths]
    if not any(present):
        return None, None
    if not all(present):
        missing = paths[present.index(False)]
        return None, f"{missing}: missing ({present.count(False)} of {len(paths)} frames have no confidence)"
    return paths, None


def check_confidence(run: RunData) -> None:
    """One-line UsageError naming the first confidence/NNNNNN.npy that is not a float (H, W) array
    (headers only), so that an export fails before it writes anything."""
    import numpy as np

    for p in run.confidence_paths or []:
        try:
            c = np.load(p, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise UsageError(f"{p}: not a readable .npy confidence map ({exc})") from None
        if c.shape != (run.height, run.width) or c.dtype.kind != "f":
            raise UsageError(f"{p}: confidence is {c.dtype} {c.shape}, expected float ({run.height}, {run.width})")


def recorded_cache(run_dir: str | Path) -> str | None:
    """The cache directory run.json records (``"cache"``) if it still exists, else None."""
    from gcvd_flow.engine import jsonio
    from gcvd_flow.engine.paths import is_cache_dir

    try:
        doc = jsonio.load_optional(Path(run_dir) / "run.json", "run record")
    except UsageError:
        return None
    rec = doc.get("cache") if isinstance(doc, dict) else None
    return rec if isinstance(rec, str) and is_cache_dir(rec) else None


def attach_images(run: RunData, cache: str | None, verify: bool = True, *, frames_stage: str | Stage) -> None:
    """Set ``run.images`` from the run's recorded output of ``frames_stage`` (``RunSources.frames``),
    or ``run.images_error``."""
    from gcvd_flow.engine import api
    from gcvd_flow.engine.artifacts import ArtifactError
    from gcvd_flow.engine.store import StoreError

    cache = cache or recorded_cache(run.run_dir)
    where = cache or str(api.default_cache_dir())
    try:
        frames = api.recorded_output(run.run_dir, stage_name(frames_stage), cache, verify)
    except (UsageError, StoreError, ArtifactError) as exc:
        run.images_error = f"the run's RGB frames are not available from the cache {where} ({exc})"
        return
    if len(frames) != len(run):
        run.images_error = f"the cache's ingest output has {len(frames)} frames, the run {len(run)}"
        return
    summary = frames.summary or {}
    if run.fps is None and isinstance(summary.get("fps"), (int, float)) and summary["fps"] > 0:
        run.fps = float(summary["fps"])

    def get(k: int) -> np.ndarray:
        try:
            img = frames[k]["image"]
        except (StoreError, ArtifactError) as exc:
            raise UsageError(f"RGB frame {run.frame_indices[k]} from the cache {where}: {exc}") from None
        if img.shape != (run.height, run.width, 3):
            raise UsageError(f"RGB frame {run.frame_indices[k]} from the cache {where} is {img.shape}, "
                             f"expected ({run.height}, {run.width}, 3)")
        return img

    run.images = MapValue(get, len(run), None)
