"""Reading and writing dataset files: the generic layout, TUM trajectories, Redwood logs.

Generic layout (written by ``gcvd-flow synth``, read by ``run`` and ``eval``)::

    OUT/frames/000000.png ...     RGB
    OUT/intrinsics.txt            fx fy cx cy
    OUT/gt/poses.txt              TUM: t tx ty tz qx qy qz qw (camera-to-world)
    OUT/gt/depth/000000.png ...   uint16 millimetres
    OUT/gt/dynamic/000000.png ... uint8 0/1 (1 = moving object), with --moving-object
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .errors import UsageError


class DatasetError(UsageError):
    """A dataset file is malformed; the message names the file (and line)."""


# ------------------------------------------------------------------------------ rotations


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(x, y, z, w) unit quaternion -> (3, 3) rotation."""
    x, y, z, w = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (x, y, z, w) with w >= 0 (Shepperd's method: stable for all angles)."""
    R = np.asarray(R, np.float64)
    t = np.trace(R)
    if t > 0:
        s = np.sqrt(t + 1.0) * 2
        q = np.array([(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s])
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = np.array([0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s])
    elif R[1, 1] > R[2, 2]:
        s = np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = np.array([(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s])
    else:
        s = np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = np.array([(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s])
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


# ------------------------------------------------------------------------------ trajectories


def read_tum_poses(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """TUM trajectory -> (timestamps (N,), camera-to-world poses (N, 4, 4))."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror})") from None
    stamps, poses = [], []
    for n, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        try:
            vals = [float(v) for v in parts]
        except ValueError:
            raise DatasetError(f"{path}:{n}: not numbers: {line[:60]!r}") from None
        if len(vals) != 8:
            raise DatasetError(f"{path}:{n}: expected 8 values 't tx ty tz qx qy qz qw', got {len(vals)}")
        q = np.array(vals[4:8])
        if not 0.5 < np.linalg.norm(q) < 2.0:
            raise DatasetError(f"{path}:{n}: quaternion is not unit length")
        T = np.eye(4)
        T[:3, :3] = quat_to_matrix(q)
        T[:3, 3] = vals[1:4]
        stamps.append(vals[0])
        poses.append(T)
    if not poses:
        raise DatasetError(f"{path}: no poses")
    return np.asarray(stamps), np.stack(poses)


def write_tum_poses(path: str | Path, timestamps: np.ndarray, poses: np.ndarray) -> None:
    lines = []
    for t, T in zip(timestamps, poses):
        q = matrix_to_quat(T[:3, :3])
        lines.append(f"{float(t):.6f} " + " ".join(f"{v:.9f}" for v in (*T[:3, 3], *q)))
    Path(path).write_text("\n".join(lines) + "\n")


def read_redwood_log(path: str | Path) -> np.ndarray:
    """Open3D/Redwood .log: per pose a metadata line then a row-major 4x4 camera-to-world."""
    path = Path(path)
    try:
        lines = [l for l in path.read_text().splitlines() if l.strip()]
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror})") from None
    if len(lines) % 5:
        raise DatasetError(f"{path}: {len(lines)} lines is not a multiple of 5 (metadata + 4 matrix rows)")
    poses = []
    for k in range(0, len(lines), 5):
        try:
            M = np.array([[float(v) for v in lines[k + r].split()] for r in range(1, 5)])
        except ValueError:
            raise DatasetError(f"{path}:{k + 2}: matrix rows must be numbers") from None
        if M.shape != (4, 4):
            raise DatasetError(f"{path}:{k + 2}: expected 4 numbers per matrix row")
        poses.append(M)
    return np.stack(poses)


def read_intrinsics_txt(path: str | Path) -> tuple[float, float, float, float]:
    path = Path(path)
    vals = path.read_text().split()
    try:
        fx, fy, cx, cy = (float(v) for v in vals)
    except ValueError:
        raise DatasetError(f"{path}: expected 'fx fy cx cy'") from None
    return fx, fy, cx, cy


def read_depth_png(path: str | Path, scale: float = 1000.0) -> np.ndarray:
    """uint16 PNG (millimetres by default) -> float32 metres, 0 = invalid."""
    d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if d is None or d.dtype != np.uint16:
        raise DatasetError(f"{path}: not a 16-bit depth PNG")
    return d.astype(np.float32) / scale


# ------------------------------------------------------------------------------ generic layout


def write_generic_layout(out_dir: str | Path, clip: Any) -> None:
    """Write a SynthClip (frames, depth, poses, K, dynamic) in the generic layout."""
    out = Path(out_dir)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    (out / "gt" / "depth").mkdir(parents=True, exist_ok=True)
    n = len(clip.frames)
    for i in range(n):
        cv2.imwrite(str(out / "frames" / f"{i:06d}.png"), np.ascontiguousarray(clip.frames[i][..., ::-1]))
        mm = np.clip(np.round(np.asarray(clip.depth[i], np.float64) * 1000.0), 0, 65535).astype(np.uint16)
        cv2.imwrite(str(out / "gt" / "depth" / f"{i:06d}.png"), mm)
    if getattr(clip, "dynamic", None) is not None:
        (out / "gt" / "dynamic").mkdir(parents=True, exist_ok=True)
        for i in range(n):
            cv2.imwrite(str(out / "gt" / "dynamic" / f"{i:06d}.png"), np.asarray(clip.dynamic[i], np.uint8))
    K = np.asarray(clip.K)
    (out / "intrinsics.txt").write_text(f"{K[0, 0]:.9f} {K[1, 1]:.9f} {K[0, 2]:.9f} {K[1, 2]:.9f}\n")
    write_tum_poses(out / "gt" / "poses.txt", np.arange(n, dtype=np.float64), np.asarray(clip.poses))
