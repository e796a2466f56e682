"""Opening a run's INPUT: video files, image folders and dataset layouts.

A source lists the input's frames as :class:`~gcvd_flow.dag.ExternalRef` s (a content digest
plus a picklable loader) so that the ``ingest`` map stage caches each frame by its own bytes.
Layouts recognised, in this order:

* a video file (``.mp4 .avi .mov .mkv .webm .m4v``) through OpenCV's FFmpeg backend; a frame's
  digest is BLAKE3(video bytes digest, frame index);
* the generic layout written by ``gcvd-flow synth``: ``frames/`` (+ ``intrinsics.txt``, ``gt/``);
* TUM RGB-D: ``rgb.txt`` (+ ``groundtruth.txt``);
* 7-Scenes: ``frame-XXXXXX.color.png`` (in the folder or its ``seq-XX`` sub-folders);
* Redwood / ICL-NUIM (Open3D layout): ``color/`` (+ ``depth/``, ``*.log``);
* any folder of images (natural sort).

Bad input raises :class:`UsageError` with one line naming the file: missing or unreadable
files, a corrupt or truncated video (the frames that fail to decode are named), fewer than
two frames, frames of mixed sizes (found when that frame is ingested; nothing of it is cached).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gcvd_flow.engine.dag import ExternalRef
from gcvd_flow.engine.errors import UsageError
from gcvd_flow.engine.keys import digest_file, key_of
from gcvd_flow.io.formats import read_camera_txt, read_rgb, read_tum_stamped_files

# FFmpeg's own log lines would break the one-line error contract; we report failures ourselves.
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")

VIDEO_EXTS = {".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg"}
IMAGE_EXTS = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp"}

# Known intrinsics of dataset layouts, at their native resolution (fx, fy, cx, cy).
REDWOOD_PRIMESENSE = (525.0, 525.0, 319.5, 239.5)  # Redwood / Augmented ICL-NUIM synthetic sets
SEVEN_SCENES = (585.0, 585.0, 320.0, 240.0)  # Kinect v1 defaults used by 7-Scenes


def natural_key(s: str) -> list[Any]:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", s)]


@dataclass(frozen=True)
class ImageFile:
    """Picklable loader: one image file -> uint8 (H, W, 3) RGB."""

    path: str

    def __call__(self) -> np.ndarray:
        return read_rgb(self.path)  # DatasetError (a UsageError) names the file


_VIDEO_CACHE: dict[str, Any] = {}


@dataclass(frozen=True)
class VideoFrame:
    """Picklable loader: frame ``index`` of a video -> uint8 (H, W, 3) RGB.

    Keeps one capture per process and reads forward when frames are requested in order
    (the usual case), seeking only when they are not.
    """

    path: str
    index: int

    def __call__(self) -> np.ndarray:
        import cv2

        state = _VIDEO_CACHE.get(self.path)
        if state is None or state["next"] > self.index:
            if state is not None:
                state["cap"].release()
            cap = cv2.VideoCapture(self.path)
            state = _VIDEO_CACHE[self.path] = {"cap": cap, "next": 0}
        cap = state["cap"]
        while state["next"] < self.index:
            if not cap.grab():
                raise UsageError(f"{self.path}: frame {state['next']} failed to decode")
            state["next"] += 1
        ok, img = cap.read()
        state["next"] += 1
        if not ok or img is None:
            raise UsageError(f"{self.path}: frame {self.index} failed to decode")
        return np.ascontiguousarray(img[..., ::-1])


@dataclass
class Source:
    """The frames of an input plus what the layout says about the camera and ground truth."""

    path: str
    layout: str
    items: list[ExternalRef]
    size: tuple[int, int]  # (w, h) of the first frame
    fps: float | None = None
    intrinsics: tuple[float, float, float, float] | None = None  # at source resolution
    intrinsics_origin: str | None = None
    distortion: tuple[float, ...] | None = None  # lens distortion coefficients of intrinsics.txt
    distortion_model: str = "OPENCV"  # their model (formats.read_camera_txt): OPENCV or OPENCV_FISHEYE
    gt: dict[str, str] = field(default_factory=dict)  # e.g. {"poses": path, "depth": folder}
    names: list[str] = field(default_factory=list)
    # source timestamp (seconds) of every frame where the input has one: TUM RGB-D rgb.txt
    # stamps, video frame index / fps; None: frames are known by index only
    timestamps: list[float] | None = None

    @property
    def digest(self) -> str:
        """What the ``ingest`` stage's key takes from the input: every frame's content, and
        what the layout says about the camera (intrinsics read from a file such as
        ``intrinsics.txt``, and where they came from), so editing that file re-runs ingest."""
        return key_of([[r.digest for r in self.items], self.layout,
                       None if self.intrinsics is None else [float(v) for v in self.intrinsics],
                       self.intrinsics_origin]
                      + ([] if self.distortion is None else [[float(v) for v in self.distortion]])
                      + ([] if self.distortion_model == "OPENCV" else [self.distortion_model]))


def _image_files(folder: Path) -> list[Path]:
    return sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTS and p.is_file()),
                  key=lambda p: natural_key(p.name))


def _first_size(path: Path) -> tuple[int, int]:
    img = ImageFile(str(path))()
    return img.shape[1], img.shape[0]


def _from_images(root: Path, files: list[Path], layout: str, **kw: Any) -> Source:
    if len(files) < 2:
        raise UsageError(f"{root}: found {len(files)} frame(s); need at least 2")
    refs = []
    for f in files:
        try:
            refs.append(ExternalRef(digest_file(f), ImageFile(str(f))))
        except OSError as exc:
            raise UsageError(f"{f}: cannot read ({exc.strerror})") from None
    return Source(str(root), layout, refs, _first_size(files[0]), names=[f.name for f in files], **kw)


def _camera_of(path: Path) -> dict[str, Any]:
    """Source fields of an ``intrinsics.txt`` (formats.read_camera_txt checks it): intrinsics
    (fx, fy, cx, cy), distortion (None: pinhole) and its model."""
    K, model, coeffs = read_camera_txt(path)
    dist = None if model == "PINHOLE" or (model == "OPENCV" and not any(coeffs)) else tuple(coeffs)
    return {"intrinsics": (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])),
            "intrinsics_origin": "intrinsics.txt", "distortion": dist,
            "distortion_model": model if dist is not None else "OPENCV"}


def open_video(path: Path) -> Source:
    import cv2

    try:  # OpenCV's FFmpeg reader takes a UTF-8 path and crashes on anything else
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        raise UsageError(f"{os.fsencode(path)!r}: the video's path is not valid UTF-8; rename it "
                         "(or link it under a UTF-8 name)") from None
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise UsageError(f"{path}: cannot open video (unsupported or corrupt file)")
    fps = float(cap.get(cv2.CAP_PROP_FPS)) or None
    expected = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    size = None
    n = 0
    # Decode once to count frames and to find broken ones now, rather than mid-run.
    while True:
        ok = cap.grab()
        if not ok:
            break
        if size is None:
            ok, img = cap.retrieve()
            if not ok:
                raise UsageError(f"{path}: frame 0 failed to decode")
            size = (img.shape[1], img.shape[0])
        n += 1
    cap.release()
    if expected > 0 and n < expected:
        raise UsageError(f"{path}: truncated or corrupt video: frames {n}..{expected - 1} failed to decode "
                         f"(decoded {n} of {expected})")
    if n < 2 or size is None:
        raise UsageError(f"{path}: found {n} decodable frame(s); need at least 2")
    vd = digest_file(path)
    refs = [ExternalRef(key_of(["video-frame", vd, i]), VideoFrame(str(path), i)) for i in range(n)]
    return Source(str(path), "video", refs, size, fps=fps, names=[f"frame {i}" for i in range(n)],
                  timestamps=[i / fps for i in range(n)] if fps else None)


def open_source(path_str: str) -> Source:
    path = Path(path_str).expanduser()
    if not path.exists():
        raise UsageError(f"{path}: no such file or directory")
    if path.is_file():
        if path.suffix.lower() in VIDEO_EXTS:
            return open_video(path)
        raise UsageError(f"{path}: not a video ({', '.join(sorted(VIDEO_EXTS))}) or a folder")
    # generic layout (gcvd-flow synth)
    if (path / "frames").is_dir():
        camera = _camera_of(path / "intrinsics.txt") if (path / "intrinsics.txt").exists() else {}
        gt = {}
        if (path / "gt" / "poses.txt").exists():
            gt["poses"] = str(path / "gt" / "poses.txt")
        if (path / "gt" / "depth").is_dir():
            gt["depth"] = str(path / "gt" / "depth")
        return _from_images(path, _image_files(path / "frames"), "generic", gt=gt, **camera)
    # TUM RGB-D
    if (path / "rgb.txt").exists():
        stamps, files = read_tum_stamped_files(path / "rgb.txt")  # DatasetError names the line
        missing = [f for f in files if not f.exists()]
        if missing:
            raise UsageError(f"{missing[0]}: listed in rgb.txt but missing")
        gt = {"poses": str(path / "groundtruth.txt")} if (path / "groundtruth.txt").exists() else {}
        return _from_images(path, files, "tum", gt=gt, timestamps=[float(t) for t in stamps])
    # 7-Scenes
    seven = sorted(path.glob("frame-*.color.png"), key=lambda p: natural_key(p.name))
    if not seven:
        seven = sorted(path.glob("seq-*/frame-*.color.png"), key=lambda p: natural_key(str(p.relative_to(path))))
    if seven:
        return _from_images(path, seven, "7scenes", intrinsics=SEVEN_SCENES,
                            intrinsics_origin="7-Scenes default (585, 585, 320, 240)")
    # Redwood / ICL-NUIM (Open3D layout)
    if (path / "color").is_dir():
        logs = sorted(path.glob("*.log"))
        gt = {}
        if logs:
            gt["poses_log"] = str(logs[0])
        if (path / "depth").is_dir():
            gt["depth"] = str(path / "depth")
        return _from_images(path, _image_files(path / "color"), "redwood", intrinsics=REDWOOD_PRIMESENSE,
                            intrinsics_origin="Redwood/ICL PrimeSense default (525, 525, 319.5, 239.5)", gt=gt)
    files = _image_files(path)
    if not files:
        raise UsageError(f"{path}: no images, video or known dataset layout found")
    return _from_images(path, files, "images")
