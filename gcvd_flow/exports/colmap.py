"""``colmap``: DIR/colmap/{cameras,images,points3D}.txt (+ DIR/images/ when RGB is available).

COLMAP's text model: one ``PINHOLE`` camera; per image the world-to-camera pose as a Hamilton
quaternion ``QW QX QY QZ`` (QW >= 0) and translation ``TX TY TZ`` (x_cam = R(q) x_world + t),
name ``NNNNNN.png``; about ``--max-points`` 3D points sampled on a pixel grid of every N-th
frame's depth, each with a one-observation track (its POINTS2D entry in images.txt). COLMAP
puts the top-left pixel's *centre* at (0.5, 0.5), we (OpenCV) at (0, 0): cx, cy and the 2D
points are ours + 0.5. Files that reference others are written after them (points3D.txt
before images.txt).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from gcvd_flow.exports._common import ExportContext, num, rigid_inverse, uses_images, write_text
from gcvd_flow.exports.clouds import pixels_to_world, valid_depth
from gcvd_flow.io.formats import quat_to_rotmat, rotmat_to_quat

# ------------------------------------------------------------------------------ conventions


def c2w_to_colmap(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """c2w poses (N, 4, 4) -> COLMAP (qvec (N, 4) as QW QX QY QZ with QW >= 0, tvec (N, 3)).

    ``qvec``/``tvec`` describe world-to-camera: x_cam = R(qvec) @ x_world + tvec.
    """
    w2c = rigid_inverse(np.asarray(c2w, np.float64).reshape(-1, 4, 4))
    q = rotmat_to_quat(w2c[:, :3, :3])  # x, y, z, w with w >= 0
    return np.concatenate([q[:, 3:], q[:, :3]], axis=1), w2c[:, :3, 3].copy()


def colmap_to_c2w(qvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """COLMAP (qvec (N, 4) QW QX QY QZ, tvec (N, 3)) world-to-camera -> c2w poses (N, 4, 4)."""
    q = np.asarray(qvec, np.float64).reshape(-1, 4)
    w2c = np.tile(np.eye(4), (len(q), 1, 1))
    w2c[:, :3, :3] = quat_to_rotmat(np.concatenate([q[:, 1:], q[:, :1]], axis=1))
    w2c[:, :3, 3] = np.asarray(tvec, np.float64).reshape(-1, 3)
    return rigid_inverse(w2c)


def sample_tracks(depths: Sequence[np.ndarray], poses: np.ndarray, K: np.ndarray, frames: Sequence[int],
                  max_points: int) -> dict[str, np.ndarray]:
    """A sparse, regular sample of depth pixels as 3D points, each observed by its own frame.

    Pixels on a grid (the same stride in every used frame, chosen so that about
    ``max_points`` points result). Returns {"frame": int64 (M,) index into ``poses``, "uv":
    float64 (M, 2) pixel (u, v) in our convention, "xyz": float64 (M, 3) world}.
    """
    frames = list(frames)
    if not frames:
        return {"frame": np.zeros(0, np.int64), "uv": np.zeros((0, 2)), "xyz": np.zeros((0, 3))}
    h, w = np.asarray(depths[frames[0]]).shape
    per_frame = max(1.0, max_points / len(frames))
    stride = max(1, int(np.ceil(np.sqrt(h * w / per_frame))))
    fr, uv, xyz = [], [], []
    for k in frames:
        d = np.asarray(depths[k], np.float32)
        off = stride // 2
        sub = d[off::stride, off::stride]
        v, u = np.nonzero(valid_depth(sub))
        u = u * stride + off
        v = v * stride + off
        xyz.append(pixels_to_world(u, v, d[v, u].astype(np.float64), K, poses[k]))
        uv.append(np.stack([u, v], axis=1).astype(np.float64))
        fr.append(np.full(len(u), k, np.int64))
    return {"frame": np.concatenate(fr), "uv": np.concatenate(uv), "xyz": np.concatenate(xyz)}


# ------------------------------------------------------------------------------ the writer


def _cameras_txt(ctx: ExportContext) -> str:
    run, K = ctx.run, ctx.run.K
    return ("# Camera list with one line of data per camera:\n"
            "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n# Number of cameras: 1\n"
            f"1 PINHOLE {run.width} {run.height} {num(K[0, 0])} {num(K[1, 1])} "
            f"{num(K[0, 2] + 0.5)} {num(K[1, 2] + 0.5)}\n")


def _point_colors(ctx: ExportContext, tracks: dict[str, np.ndarray]) -> np.ndarray:
    """uint8 (M, 3): each point's pixel colour in its frame, grey without images."""
    colors = np.full((len(tracks["xyz"]), 3), 128, np.uint8)
    if ctx.run.images is not None and len(colors):
        for k in np.unique(tracks["frame"]):
            sel = tracks["frame"] == k
            uv = tracks["uv"][sel].astype(np.int64)
            colors[sel] = ctx.run.images[int(k)][uv[:, 1], uv[:, 0]]
    return colors


def _points3d_txt(tracks: dict[str, np.ndarray], colors: np.ndarray) -> tuple[str, dict[int, list[str]]]:
    """points3D.txt, and each image's POINTS2D entries (its own sampled pixels, in point-id order)."""
    n_pts = len(tracks["xyz"])
    obs: dict[int, list[str]] = {}
    p2d_idx = np.zeros(n_pts, np.int64)
    for pid in range(n_pts):
        k = int(tracks["frame"][pid])
        lst = obs.setdefault(k, [])
        p2d_idx[pid] = len(lst)
        u, v = tracks["uv"][pid]
        lst.append(f"{num(u + 0.5)} {num(v + 0.5)} {pid + 1}")
    lines = ["# 3D point list with one line of data per point:",
             "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
             f"# Number of points: {n_pts}, mean track length: {1 if n_pts else 0}"]
    for pid in range(n_pts):
        x, y, z = tracks["xyz"][pid]
        r, g, b = colors[pid]
        lines.append(f"{pid + 1} {num(x)} {num(y)} {num(z)} {r} {g} {b} 0 {int(tracks['frame'][pid]) + 1} "
                     f"{p2d_idx[pid]}")
    return "\n".join(lines) + "\n", obs


def _images_txt(ctx: ExportContext, obs: dict[int, list[str]], n_pts: int) -> str:
    run = ctx.run
    qvec, tvec = c2w_to_colmap(run.poses)
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)",
             f"# Number of images: {len(run)}, mean observations per image: {n_pts / max(len(run), 1):g}"]
    for k in range(len(run)):
        lines.append(f"{k + 1} " + " ".join(num(v) for v in (*qvec[k], *tvec[k])) + f" 1 {run.name(k)}.png")
        lines.append(" ".join(obs.get(k, [])))
    return "\n".join(lines) + "\n"


@uses_images("optional")
def write(ctx: ExportContext) -> dict[str, Any]:
    run, d = ctx.run, ctx.out / "colmap"
    have_images = run.images is not None
    if have_images:
        ctx.images_dir()
    else:
        ctx.log(f"warning: colmap: {run.images_error}; writing the model without images/")
    write_text(d / "cameras.txt", _cameras_txt(ctx))
    tracks = sample_tracks(run.depths, run.poses, run.K, range(0, len(run), ctx.opt.every), ctx.opt.max_points)
    points3d, obs = _points3d_txt(tracks, _point_colors(ctx, tracks))
    write_text(d / "points3D.txt", points3d)
    write_text(d / "images.txt", _images_txt(ctx, obs, len(tracks["xyz"])))
    return {"dir": str(d), "images": len(run), "points3D": len(tracks["xyz"]),
            "image_dir": str(ctx.out / "images") if have_images else None}
