"""What every export format shares: options, the export context, atomic writes, number text.

A format is a *writer*: ``write(ctx: ExportContext) -> dict`` (the details reported under
``formats[FMT]`` by ``--json``), registered by name in ``gcvd_flow.exports.WRITERS``. A writer
that reads the run's RGB frames says so with ``@uses_images("required")`` (skipped, with the
reason, when the cache no longer holds them) or ``@uses_images("optional")`` (runs either
way; ``ctx.run.images`` is None then).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from gcvd_flow.engine.errors import UsageError
from gcvd_flow.io.formats import png_bytes
from gcvd_flow.io.run_dir import RunData

DEFAULT_FPS = 30.0
#: nerfstudio masks: 255 where the depth confidence is >= this (``--min-confidence``), else 0
DEFAULT_MIN_CONFIDENCE = 0.5
MCAP_IMAGES = ("png", "jpeg", "raw")

Writer = Callable[["ExportContext"], dict[str, Any]]


def uses_images(how: Literal["required", "optional"]) -> Callable[[Writer], Writer]:
    """Mark a writer as reading the run's RGB frames (see the module docstring)."""

    def mark(fn: Writer) -> Writer:
        fn.images = how  # type: ignore[attr-defined]
        return fn

    return mark


def images_use(writer: Writer) -> str | None:
    """"required", "optional" or None (the writer does not read the RGB frames)."""
    return getattr(writer, "images", None)


# ------------------------------------------------------------------------------ options


@dataclass
class Options:
    every: int = 1
    voxel: float = 0.0
    tsdf_voxel: float | None = None
    depth_scale: float = 1.0
    fps: float | None = None
    mcap_images: str = "png"
    max_points: int = 20000
    colmap_binary: bool = False  # colmap: cameras/images/points3D.bin instead of .txt
    # colmap / nerfstudio images (and intrinsics) at the source resolution; None: on for them
    full_res: bool | None = None
    max_track: int = 32  # colmap: observations per 3D point at most (evenly spread over the frames)
    # confidence threshold in [0, 1]: nerfstudio masks (None: DEFAULT_MIN_CONFIDENCE; 0: no masks);
    # the ply / mcap clouds drop pixels below it only when it is given (None: every valid pixel)
    min_confidence: float | None = None

    @property
    def mask_threshold(self) -> float:
        return DEFAULT_MIN_CONFIDENCE if self.min_confidence is None else float(self.min_confidence)

    def check(self) -> None:
        """UsageError naming the flag for any out-of-range option (before anything is written)."""
        if self.every < 1:
            raise UsageError(f"--every {self.every}: must be >= 1")
        if not (math.isfinite(self.voxel) and self.voxel >= 0):
            raise UsageError(f"--voxel {self.voxel}: must be a finite number >= 0 (0 = no downsampling)")
        if self.tsdf_voxel is not None and not (math.isfinite(self.tsdf_voxel) and self.tsdf_voxel > 0):
            raise UsageError(f"--tsdf-voxel {self.tsdf_voxel}: must be a finite number > 0")
        if not (self.depth_scale > 0 and math.isfinite(self.depth_scale)):
            raise UsageError(f"--depth-scale {self.depth_scale}: must be a positive number")
        if self.fps is not None and not (math.isfinite(self.fps) and self.fps > 0):
            raise UsageError(f"--fps {self.fps}: must be > 0")
        if self.max_points < 0:
            raise UsageError(f"--max-points {self.max_points}: must be >= 0")
        if self.max_track < 2:
            raise UsageError(f"--max-track {self.max_track}: must be >= 2")
        if self.min_confidence is not None and not 0.0 <= self.min_confidence <= 1.0:  # NaN fails too
            raise UsageError(f"--min-confidence {self.min_confidence}: must be a number in [0, 1]")
        if self.mcap_images not in MCAP_IMAGES:
            raise UsageError(f"--mcap-images {self.mcap_images!r}: choose one of {', '.join(MCAP_IMAGES)}")


# ------------------------------------------------------------------------------ atomic writes


@contextmanager
def _atomic(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix, for writers that go by it); rename
    it onto ``path`` only when the block succeeds."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_bytes(path: Path, data: bytes) -> None:
    with _atomic(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: Path, text: str) -> None:
    write_bytes(path, text.encode())


def _link(src: Path, dst: Path) -> bool:
    """Hard-link ``src`` to ``dst`` (replacing it) where the file system allows; else False."""
    try:
        dst.parent.mkdir(parents=True, exist_ok=True)
        tmp = dst.with_name(f".{dst.stem}.tmp-{os.getpid()}{dst.suffix}")
        tmp.unlink(missing_ok=True)
        os.link(src, tmp)
        os.replace(tmp, dst)
        return True
    except OSError:
        return False


def clean_stale(folder: Path, keep: set[str], suffix: str) -> None:
    """Drop NNNNNN<suffix> files of an earlier export that this one does not write."""
    if folder.is_dir():
        for p in folder.glob(f"[0-9][0-9][0-9][0-9][0-9][0-9]{suffix}"):
            if p.name not in keep:
                p.unlink()


def num(x: float) -> str:
    """Shortest text that reads back to the same float (and no "-0.0")."""
    return repr(float(x) + 0.0)


def rigid_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4): T_b_a -> T_a_b (e.g. T_w_c -> T_c_w)."""
    R, t = T[..., :3, :3], T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


# ------------------------------------------------------------------------------ the context


@dataclass
class ExportContext:
    """One export: the run, the output folder, the options, and outputs shared by formats."""

    run: RunData
    out: Path
    opt: Options
    log: Callable[[str], None]
    written: set[str] = field(default_factory=set)  # formats written so far, in write order
    _shared: dict[Any, Any] = field(default_factory=dict, repr=False)

    def shared(self, key: Any, make: Callable[[], Any]) -> Any:
        """``make()`` once per export (e.g. images/ for colmap and nerfstudio, a fused cloud)."""
        if key not in self._shared:
            self._shared[key] = make()
        return self._shared[key]

    def view(self) -> Any:
        """The frames colmap / nerfstudio write (a ``source_frames.FrameView``): at the source
        resolution with ``--full-res`` (the default) when the run's input is still there and
        unchanged, else at working resolution (with a warning, once)."""
        from gcvd_flow.exports import source_frames

        def make() -> Any:
            if self.opt.full_res is False:
                return source_frames.working_view(self.run)
            v = source_frames.source_view(self.run)
            if isinstance(v, str):
                self.log(f"warning: images at working resolution {self.run.width}x{self.run.height}: {v}")
                return source_frames.working_view(self.run)
            return v

        return self.shared("view", make)

    def images_dir(self, sub: str = "images") -> dict[str, Any]:
        """DIR/<sub>/NNNNNN.png: the frames of ``view()`` (written once per folder and export)."""

        def make() -> dict[str, Any]:
            run, d, view = self.run, self.out / sub, self.view()
            assert view.images is not None
            names = set()
            done = [Path(v["dir"]) for key, v in self._shared.items() if isinstance(key, tuple) and key[0] == "images"]
            for k in range(len(run)):
                name = f"{run.name(k)}.png"
                if not (done and _link(done[0] / name, d / name)):  # the same PNG in another folder
                    write_bytes(d / name, png_bytes(view.images[k]))
                names.add(name)
            clean_stale(d, names, ".png")
            return {"dir": str(d), "files": len(run), "width": view.width, "height": view.height}

        return self.shared(("images", sub), make)

    def time_ns(self, k: int) -> int:
        """Log time of frame k (ns): the source timestamp when the run has one (TUM RGB-D rgb.txt,
        video index / fps) and --fps is not given, else source frame index / fps (--fps, else the
        input's, else 30)."""
        if self.opt.fps is None and self.run.timestamps is not None:
            return int(round(self.run.timestamps[k] * 1e9))
        fps = self.opt.fps or self.run.fps or DEFAULT_FPS
        return int(round(self.run.frame_indices[k] / fps * 1e9))
