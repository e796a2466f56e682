"""File formats: one reader and one writer per format, used by sources, exports, eval and synth.

TUM trajectories, Redwood/Open3D ``.log``, ``intrinsics.txt``, RGB / mask / 16-bit depth PNGs
(``png_bytes`` is the one PNG encoder for files: the artifact store's codec, see below), and
the generic dataset layout.

Generic dataset layout (what ``write_generic_layout`` writes and ``read_generic_layout`` reads)::

    OUT/frames/000000.png ...      RGB frames (PNG, deterministic bytes)
    OUT/intrinsics.txt             one line "fx fy cx cy" (pixels), or with a lens model: read_camera_txt
    OUT/gt/poses.txt               TUM "t tx ty tz qx qy qz qw", camera-to-world, t = frame index
    OUT/gt/depth/000000.png ...    uint16 depth in millimetres (0 = invalid)
    OUT/gt/dynamic/000000.png ...  uint8 0/1, 1 = pixel sees a moving object (only if known)

Pose convention everywhere: float64 (N, 4, 4) camera-to-world, OpenCV camera axes.
Malformed input raises ``DatasetError`` (a ``ValueError``) whose message names the file.

PNG files are encoded with the artifact store's codec (``gcvd_flow.engine.artifacts.png_bytes``:
Pillow at zlib level 3, deterministic bytes), 16-bit depth with Pillow at the same level: one PNG
writer for the cache and every file (issue 29). The engine imports no project package, so this
module calls the engine's codec, not the other way round. Reading stays with OpenCV (inputs may
be JPEG, BMP, ...).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from gcvd_flow.engine.errors import UsageError

PathLike = str | os.PathLike

_DEPTH_MAX_MM = np.iinfo(np.uint16).max


class DatasetError(UsageError):
    """Malformed or missing dataset file; the message names the file.

    A ``UsageError`` (hence a ``ValueError``): the CLI reports it in one line, exit code 2.
    """

    def __init__(self, path: PathLike, message: str) -> None:
        self.path = str(path)
        super().__init__(f"{self.path}: {message}")


# ----------------------------------------------------------------------------- quaternions


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) as (qx, qy, qz, qw) (TUM order, w last) -> rotations (..., 3, 3)."""
    from scipy.spatial.transform import Rotation  # lazy: scipy costs ~0.4 s of CLI start-up

    q = np.asarray(q, dtype=np.float64)
    return Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotations (..., 3, 3) -> unit quaternions (..., 4) as (qx, qy, qz, qw) with qw >= 0
    (q and -q are the same rotation; one sign gives stable text output)."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=np.float64)
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()
    q[q[:, 3] < 0] *= -1.0
    return q.reshape(R.shape[:-2] + (4,))


# ----------------------------------------------------------------------------- text formats


def _read_text(path: Path) -> str:
    """A text file's content; a one-line DatasetError naming it if it is missing or unreadable
    (also when it is not a regular file: a FIFO would block, /dev/zero never ends)."""
    from gcvd_flow.engine.jsonio import read_regular

    try:
        return read_regular(path).decode()
    except FileNotFoundError:
        raise DatasetError(path, "file not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise DatasetError(path, f"cannot read: {e}") from None


def _numeric_rows(path: Path) -> list[tuple[int, list[float]]]:
    """(line number, floats) of every non-empty, non-'#' line; DatasetError if unparsable."""
    text = _read_text(path)
    rows = []
    for ln, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        try:
            rows.append((ln, [float(x) for x in s.replace(",", " ").split()]))
        except ValueError:
            raise DatasetError(path, f"line {ln}: not numeric: {s[:80]!r}") from None
    return rows


def read_tum_poses(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory ``t tx ty tz qx qy qz qw`` (camera-to-world).

    Returns (timestamps float64 (N,), poses float64 (N, 4, 4)). Quaternions are renormalised;
    a quaternion far from unit length (|q| outside [0.9, 1.1]) is rejected as malformed.
    """
    path = Path(path)
    rows = _numeric_rows(path)
    if not rows:
        raise DatasetError(path, "no poses")
    for ln, r in rows:
        if len(r) != 8:
            raise DatasetError(path, f"line {ln}: expected 8 values 't tx ty tz qx qy qz qw', got {len(r)}")
    a = np.array([r for _, r in rows], dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise DatasetError(path, "non-finite values")
    qn = np.linalg.norm(a[:, 4:8], axis=1)
    bad = np.nonzero((qn < 0.9) | (qn > 1.1))[0]
    if len(bad):
        raise DatasetError(path, f"line {rows[bad[0]][0]}: quaternion norm {qn[bad[0]]:.4g} is not ~1")
    poses = np.tile(np.eye(4), (len(a), 1, 1))
    poses[:, :3, :3] = quat_to_rotmat(a[:, 4:8])
    poses[:, :3, 3] = a[:, 1:4]
    return a[:, 0].copy(), poses


def write_tum_poses(path: PathLike, timestamps: np.ndarray, poses: np.ndarray) -> None:
    """Write camera-to-world poses T_w_c (N, 4, 4) with timestamps (N,) as TUM text
    ``t tx ty tz qx qy qz qw`` (t %.6f, the rest %.9f). Creates parent folders."""
    path = Path(path)
    ts = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    P = np.asarray(poses, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (4, 4) or len(P) != len(ts):
        raise ValueError(f"poses must be (N, 4, 4) with N = len(timestamps); got {P.shape}, {ts.shape}")
    q = rotmat_to_quat(P[:, :3, :3])
    path.parent.mkdir(parents=True, exist_ok=True)
    # No header line: one line per pose, so `wc -l` counts poses (tools and tests rely on it).
    lines = []
    for t, T, qi in zip(ts, P, q):
        lines.append(f"{t:.6f} " + " ".join(f"{v:.9f}" for v in (*T[:3, 3], *qi)))
    path.write_text("\n".join(lines) + "\n")


def read_tum_stamped_files(path: PathLike) -> tuple[np.ndarray, list[Path]]:
    """Read a TUM RGB-D file list (``rgb.txt`` / ``depth.txt``: ``timestamp filename`` per line,
    ``#`` comments) -> (timestamps float64 (N,) seconds, paths relative to the list's folder)."""
    path = Path(path)
    text = _read_text(path)
    stamps, files = [], []
    for ln, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        try:
            t = float(parts[0])
        except ValueError:
            raise DatasetError(path, f"line {ln}: expected 'timestamp filename', got {s[:80]!r}") from None
        if len(parts) < 2 or not np.isfinite(t):
            raise DatasetError(path, f"line {ln}: expected 'timestamp filename', got {s[:80]!r}")
        stamps.append(t)
        files.append(path.parent / parts[1])
    return np.asarray(stamps, np.float64), files


def read_redwood_log(path: PathLike) -> np.ndarray:
    """Read an Open3D / Redwood ``.log`` trajectory -> camera-to-world float64 (N, 4, 4).

    Format: 5 lines per pose: a metadata line (3 integers, e.g. ``i i i+1``) then the 4x4
    matrix row by row.
    """
    path = Path(path)
    rows = _numeric_rows(path)
    if not rows or len(rows) % 5:
        raise DatasetError(path, f"expected 5 lines per pose, got {len(rows)} non-empty lines")
    poses = np.empty((len(rows) // 5, 4, 4))
    for k in range(len(poses)):
        ln, meta = rows[5 * k]
        if len(meta) != 3:
            raise DatasetError(path, f"line {ln}: expected a 3-integer metadata line, got {len(meta)} values")
        for r in range(4):
            ln, vals = rows[5 * k + 1 + r]
            if len(vals) != 4:
                raise DatasetError(path, f"line {ln}: expected 4 matrix values, got {len(vals)}")
            poses[k, r] = vals
    if not np.all(np.isfinite(poses)):
        raise DatasetError(path, "non-finite values")
    return poses


def read_camera_txt(path: PathLike) -> tuple[np.ndarray, str, tuple[float, ...]]:
    """Read ``intrinsics.txt`` -> (K float64 (3, 3), model, distortion coefficients).

    The grammar is ``--intrinsics``' (stages.frontend.lens.parse_camera: an optional model name
    PINHOLE, OPENCV, OPENCV_FISHEYE or fisheye, then ``fx fy cx cy``, ``fx fy cx cy k1 k2 p1 p2
    [k3]``, ``k1 k2 k3 k4`` for the fisheye, or 9 numbers ending with ``0 0 1``, a 3x3 matrix) over
    the file's lines, '#' lines being comments. Anything it refuses (non-finite values, focal
    lengths <= 0, a wrong count) is a ``DatasetError`` naming the file (a garbage file must not run
    to the end); whether the camera fits the frames is checked at ingest (lens.check_camera).
    """
    from gcvd_flow.stages.frontend.lens import parse_camera

    path = Path(path)
    text = " ".join(line for line in _read_text(path).splitlines() if not line.strip().startswith("#"))
    try:
        cam = parse_camera(text)
    except ValueError as exc:
        raise DatasetError(path, str(exc)) from None
    return cam.K(), cam.model, tuple(cam.coeffs)


def read_intrinsics_txt(path: PathLike) -> np.ndarray:
    """Read ``intrinsics.txt`` -> K float64 (3, 3) (:func:`read_camera_txt`; the distortion is
    :func:`read_distortion_txt`'s)."""
    return read_camera_txt(path)[0]


def read_distortion_txt(path: PathLike) -> tuple[float, ...] | None:
    """The lens distortion coefficients of ``intrinsics.txt`` (OPENCV: k1 k2 p1 p2 [k3];
    OPENCV_FISHEYE: k1 k2 k3 k4; :func:`read_camera_txt` says which model); None for a pinhole
    camera (OPENCV with every coefficient zero included)."""
    _, model, coeffs = read_camera_txt(path)
    if model == "PINHOLE" or (model == "OPENCV" and not any(coeffs)):
        return None
    return coeffs


def write_intrinsics_txt(path: PathLike, K: np.ndarray, distortion: Any = None, model: str = "OPENCV") -> None:
    """Write K (3, 3) as one line ``fx fy cx cy`` (%.9f), followed by ``k1 k2 p1 p2`` when given;
    five OPENCV coefficients and the fisheye's are written with the model's name in front
    (``OPENCV fx fy cx cy k1 k2 p1 p2 k3``, ``OPENCV_FISHEYE fx fy cx cy k1 k2 k3 k4``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    coeffs = [] if distortion is None else [float(v) for v in distortion]
    named = model == "OPENCV_FISHEYE" or len(coeffs) == 5
    vals = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]] + coeffs
    path.write_text((f"{model} " if named else "") + " ".join(f"{float(v):.9f}" for v in vals) + "\n")


# ----------------------------------------------------------------------------- images


def png_bytes(img: np.ndarray) -> bytes:
    """The PNG encoder for files: uint8 (H, W) grey / (H, W, 3) RGB or uint16 (H, W) -> bytes.

    The codec of the stored artifacts (``gcvd_flow.engine.artifacts.png_bytes``: Pillow at zlib
    level 3) for uint8, Pillow at the same level for uint16 (16-bit grey PNG): one PNG writer for
    the cache and every export. Reading stays with OpenCV (inputs may be any image format).
    """
    import io

    from PIL import Image

    from gcvd_flow.engine.artifacts import ArtifactError, png_bytes as artifact_png

    img = np.asarray(img)
    if img.dtype == np.uint16 and img.ndim == 2:
        buf = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(img)).save(buf, format="PNG", compress_level=3)
        return buf.getvalue()
    try:
        return artifact_png(img)
    except ArtifactError as exc:
        raise OSError(f"PNG encoding failed: {exc}") from None


def _write_png(path: Path, img: np.ndarray) -> None:
    try:
        data = png_bytes(img)
    except OSError:
        raise OSError(f"{path}: PNG encoding failed") from None
    path.write_bytes(data)


def write_rgb_png(path: PathLike, rgb: np.ndarray) -> None:
    """Write uint8 (H, W, 3) RGB as PNG."""
    _write_png(Path(path), rgb)


def _imread(path: PathLike, flags: int) -> np.ndarray | None:
    """cv2.imread for any path: the bytes are read by Python (OpenCV's own file functions crash
    on file names that are not valid UTF-8) and decoded from memory; None if not an image."""
    try:
        data = np.fromfile(os.fspath(path), np.uint8)
    except OSError as exc:
        raise DatasetError(path, f"cannot read ({exc.strerror or exc})") from None
    return cv2.imdecode(data, flags) if data.size else None


def read_rgb(path: PathLike) -> np.ndarray:
    """Read an image file -> uint8 (H, W, 3) RGB."""
    img = _imread(path, cv2.IMREAD_COLOR)
    if img is None:
        raise DatasetError(path, "not a readable image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def write_mask_png(path: PathLike, mask: np.ndarray) -> None:
    """Write a boolean / 0-1 mask (H, W) as a uint8 0/1 PNG."""
    _write_png(Path(path), np.asarray(mask).astype(np.uint8))


def read_mask_png(path: PathLike) -> np.ndarray:
    """Read a single-channel mask PNG -> bool (H, W), True where the value is > 0."""
    m = _imread(path, cv2.IMREAD_UNCHANGED)
    if m is None or m.ndim != 2:
        raise DatasetError(path, "expected a single-channel mask PNG")
    return m > 0


_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def read_user_mask_png(path: PathLike) -> np.ndarray:
    """A ``--masks`` PNG -> bool (H, W), True = leave the pixel out, on the *decoded* values of an
    8- or 16-bit grey, grey + alpha, RGB, RGBA or palette PNG (a 16-bit 0/1 mask masks):

    * no alpha channel: out where any channel is non-zero;
    * an alpha channel that varies over the image is the mask: out where alpha is non-zero, whatever
      the colour (a cut-out, a brush layer on a transparent canvas, a mask kept only in alpha);
    * an alpha channel with one value everywhere carries no mask: fully transparent (0) leaves
      nothing out, any other (an opaque export) leaves the colour to decide as without alpha.

    Not a PNG, or not decodable: DatasetError (one line, exit 2)."""
    try:
        with open(os.fspath(path), "rb") as f:
            head = f.read(8)
    except OSError as exc:
        raise DatasetError(path, f"cannot read ({exc.strerror or exc})") from None
    if head != _PNG_MAGIC:
        raise DatasetError(path, "not a PNG (--masks takes PNG files)")
    m = _imread(path, cv2.IMREAD_UNCHANGED)
    if m is None or m.ndim not in (2, 3) or (m.ndim == 3 and m.shape[2] not in (1, 2, 3, 4)):
        raise DatasetError(path, "not a readable grey, RGB or RGBA PNG")
    if m.ndim == 2:
        return m > 0
    colour = m[..., : 1 if m.shape[2] <= 2 else 3].max(axis=2) > 0
    if m.shape[2] not in (2, 4):
        return colour
    alpha = m[..., -1]
    lo, hi = int(alpha.min()), int(alpha.max())
    if lo != hi:
        return alpha > 0
    return colour if hi > 0 else np.zeros(alpha.shape, bool)


def depth_to_png16(depth: np.ndarray, scale: float = 1000.0) -> tuple[np.ndarray, int]:
    """float depth (H, W) -> (uint16 (H, W) of depth * scale, rounded; count of clipped pixels).

    Valid depth (finite, > 0) is clipped to [1, 65535], so it never becomes 0 (0 = invalid) and
    depth beyond 65535 / scale is stored as 65535 and counted; invalid depth is 0. ``scale``:
    stored units per depth unit (1000: millimetres of metres).
    """
    d = np.asarray(depth, np.float64) * scale
    ok = np.isfinite(d) & (d > 0)
    units = np.where(ok, np.round(np.where(ok, d, 0.0)), 0.0)
    clipped = int(np.count_nonzero(units > _DEPTH_MAX_MM))
    return np.where(ok, np.clip(units, 1, _DEPTH_MAX_MM), 0).astype(np.uint16), clipped


def write_depth_png(path: PathLike, depth: np.ndarray, scale: float = 1000.0) -> int:
    """Write float depth (H, W) as a 16-bit PNG in units of 1/scale (default mm of metres);
    returns the number of pixels clipped to 65535 (see ``depth_to_png16``)."""
    png16, clipped = depth_to_png16(depth, scale)
    _write_png(Path(path), png16)
    return clipped


def read_depth_png(path: PathLike, scale: float = 1000.0) -> np.ndarray:
    """Read a 16-bit depth PNG -> float32 (H, W) metres (value / scale; 0 stays 0 = invalid)."""
    img = _imread(path, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(path, "not a readable image")
    if img.dtype != np.uint16 or img.ndim != 2:
        raise DatasetError(path, f"expected a single-channel 16-bit depth PNG, got {img.dtype} {img.shape}")
    return (img.astype(np.float64) / scale).astype(np.float32)


class DepthPngSequence(Sequence):
    """Lazily loaded depth maps: ``seq[i]`` -> float32 (H, W) metres; ``seq.paths`` the files."""

    def __init__(self, paths: list[Path], scale: float = 1000.0) -> None:
        self.paths = paths
        self.scale = float(scale)

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, i: Any) -> Any:
        if isinstance(i, slice):
            return DepthPngSequence(self.paths[i], self.scale)
        return read_depth_png(self.paths[i], self.scale)

    def load_all(self) -> np.ndarray:
        """All depth maps stacked: float32 (N, H, W) metres."""
        return np.stack([self[i] for i in range(len(self))]) if len(self) else np.zeros((0, 0, 0), np.float32)


def _sorted_pngs(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise DatasetError(folder, "folder not found")
    return sorted(p for p in folder.iterdir() if p.suffix.lower() == ".png")


def read_depth_pngs(folder: PathLike, scale: float = 1000.0) -> DepthPngSequence:
    """All ``*.png`` in ``folder`` (sorted by name) as a lazily loading ``DepthPngSequence``.

    ``scale``: stored units per metre (1000 = mm; TUM RGB-D uses 5000).
    """
    return DepthPngSequence(_sorted_pngs(Path(folder)), scale)


# ----------------------------------------------------------------------------- generic layout


def write_generic_layout(out_dir: PathLike, clip: Any) -> Path:
    """Write a clip (e.g. ``stages.synth.SynthClip``) in the generic layout under ``out_dir``.

    ``clip`` needs ``frames`` uint8 (N, H, W, 3), ``K`` (3, 3), and optionally ``poses``
    (N, 4, 4) camera-to-world, ``depth`` float (N, H, W) metres, ``dynamic`` bool (N, H, W).
    Returns the output folder. Files are overwritten; byte-identical for identical input.
    """
    out = Path(out_dir)
    frames = np.asarray(clip.frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ValueError(f"frames must be uint8 (N, H, W, 3), got {frames.dtype} {frames.shape}")
    (out / "frames").mkdir(parents=True, exist_ok=True)
    for i, f in enumerate(frames):
        write_rgb_png(out / "frames" / f"{i:06d}.png", f)
    write_intrinsics_txt(out / "intrinsics.txt", np.asarray(clip.K), getattr(clip, "distortion", None),
                         getattr(clip, "distortion_model", "OPENCV"))
    poses = getattr(clip, "poses", None)
    if poses is not None:
        write_tum_poses(out / "gt" / "poses.txt", np.arange(len(poses), dtype=np.float64), poses)
    depth = getattr(clip, "depth", None)
    if depth is not None:
        (out / "gt" / "depth").mkdir(parents=True, exist_ok=True)
        for i, d in enumerate(depth):
            write_depth_png(out / "gt" / "depth" / f"{i:06d}.png", d)
    dynamic = getattr(clip, "dynamic", None)
    if dynamic is not None:
        (out / "gt" / "dynamic").mkdir(parents=True, exist_ok=True)
        for i, m in enumerate(dynamic):
            write_mask_png(out / "gt" / "dynamic" / f"{i:06d}.png", m)
    return out


@dataclass
class GenericLayout:
    """What ``read_generic_layout`` found. Ground truth fields are None when absent.

    frame_paths: sorted RGB PNGs; K: float64 (3, 3); timestamps (N,), poses (N, 4, 4)
    camera-to-world; depth: lazily loaded metres; dynamic_paths: uint8 0/1 masks.
    """

    root: Path
    frame_paths: list[Path]
    K: np.ndarray
    timestamps: np.ndarray | None = None
    poses: np.ndarray | None = None
    depth: DepthPngSequence | None = None
    dynamic_paths: list[Path] | None = None

    def load_frames(self) -> np.ndarray:
        """uint8 (N, H, W, 3) RGB."""
        return np.stack([read_rgb(p) for p in self.frame_paths])

    def load_dynamic(self) -> np.ndarray | None:
        """bool (N, H, W) or None."""
        if self.dynamic_paths is None:
            return None
        return np.stack([read_mask_png(p) for p in self.dynamic_paths])


def read_generic_layout(root: PathLike, depth_scale: float = 1000.0) -> GenericLayout:
    """Read the generic layout under ``root`` (see module docstring); checks counts agree."""
    root = Path(root)
    frame_paths = _sorted_pngs(root / "frames")
    if not frame_paths:
        raise DatasetError(root / "frames", "no PNG frames")
    lay = GenericLayout(root=root, frame_paths=frame_paths, K=read_intrinsics_txt(root / "intrinsics.txt"))
    n = len(frame_paths)
    if (root / "gt" / "poses.txt").exists():
        lay.timestamps, lay.poses = read_tum_poses(root / "gt" / "poses.txt")
        if len(lay.poses) != n:
            raise DatasetError(root / "gt" / "poses.txt", f"{len(lay.poses)} poses for {n} frames")
    if (root / "gt" / "depth").is_dir():
        lay.depth = read_depth_pngs(root / "gt" / "depth", depth_scale)
        if len(lay.depth) != n:
            raise DatasetError(root / "gt" / "depth", f"{len(lay.depth)} depth maps for {n} frames")
    if (root / "gt" / "dynamic").is_dir():
        lay.dynamic_paths = _sorted_pngs(root / "gt" / "dynamic")
        if len(lay.dynamic_paths) != n:
            raise DatasetError(root / "gt" / "dynamic", f"{len(lay.dynamic_paths)} masks for {n} frames")
    return lay
