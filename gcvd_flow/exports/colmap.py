"""``colmap``: a COLMAP model where COLMAP-based tools look for it.

    DIR/colmap/sparse/0/cameras.txt, images.txt, points3D.txt   (``--colmap-binary``: *.bin)
    DIR/images/NNNNNN.png                                        the frames (source resolution
                                                                 with --full-res, the default)

The layout of nerfstudio's ``ns-process-data`` (images/ beside colmap/sparse/0): nerfstudio's
COLMAP dataparser finds both with its defaults (``images_path`` "images", ``colmap_path``
"colmap/sparse/0"), and a nerfstudio export into the same folder shares images/.

One ``PINHOLE`` camera at the images' resolution; per image the world-to-camera pose as a
Hamilton quaternion ``QW QX QY QZ`` (QW >= 0) and translation ``TX TY TZ`` (x_cam = R(q)
x_world + t), name ``NNNNNN.png``. 3D points with multi-view tracks: about ``--max-points``
pixels on a grid of every N-th frame's depth (``--every``) are backprojected at that frame's pose;
a point is observed in every frame where it projects inside the image, in front of the camera,
and agrees with that frame's depth (within ``DEPTH_AGREEMENT``), at most ``max_track``
observations evenly spread over those frames (its own frame always); points fewer than two
frames see are dropped (COLMAP's bundle adjuster aborts on a one-view track). The observations are
the projections of the point (reprojection error ~1e-14 px), not independent measurements: the
model is consistent for bundle adjusters and Gaussian-splatting loaders, but a refinement in
COLMAP starts at its optimum and has nothing to correct. COLMAP puts the top-left pixel's *centre* at
(0.5, 0.5), we (OpenCV) at (0, 0): cx, cy
and the 2D points are ours + 0.5. Files that reference others are written after them.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import Any

import numpy as np

from gcvd_flow.exports._common import ExportContext, num, rigid_inverse, uses_images, write_bytes, write_text
from gcvd_flow.exports.clouds import pixels_to_world, valid_depth
from gcvd_flow.io.formats import quat_to_rotmat, rotmat_to_quat

DEPTH_AGREEMENT = 0.03  # relative: |depth of the frame - depth of the point| <= 3 % of it
PINHOLE_MODEL_ID = 1
MIN_VIEWS = 2  # COLMAP's bundle adjustment needs every track to have two observations at least

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


# ------------------------------------------------------------------------------ tracks


def sample_points(depths: Sequence[np.ndarray], poses: np.ndarray, K: np.ndarray, frames: Sequence[int],
                  max_points: int) -> dict[str, np.ndarray]:
    """A sparse, regular sample of depth pixels as 3D points (the same grid stride in every used
    frame, about ``max_points`` in all). Returns {"frame": int64 (M,) index into ``poses``, "uv":
    float64 (M, 2) pixel (u, v) in our convention, "xyz": float64 (M, 3) world}."""
    frames = list(frames)
    if not frames or max_points == 0:
        return {"frame": np.zeros(0, np.int64), "uv": np.zeros((0, 2)), "xyz": np.zeros((0, 3))}
    h, w = np.asarray(depths[frames[0]]).shape
    per_frame = max(1.0, max_points / len(frames))
    stride = max(1, int(np.ceil(np.sqrt(h * w / per_frame))))
    fr, uv, xyz = [], [], []
    for k in frames:
        d = np.asarray(depths[k], np.float32)
        off = stride // 2
        v, u = np.nonzero(valid_depth(d[off::stride, off::stride]))
        u, v = u * stride + off, v * stride + off
        xyz.append(pixels_to_world(u, v, d[v, u].astype(np.float64), K, poses[k]))
        uv.append(np.stack([u, v], axis=1).astype(np.float64))
        fr.append(np.full(len(u), k, np.int64))
    return {"frame": np.concatenate(fr), "uv": np.concatenate(uv), "xyz": np.concatenate(xyz)}


def project(xyz: np.ndarray, c2w: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points (M, 3) -> (pixels (M, 2) in our convention, z-depth (M,)) in camera c2w."""
    w2c = rigid_inverse(np.asarray(c2w, np.float64))
    pc = xyz @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (pc[:, :2] / z[:, None]) * np.diag(K)[:2] + K[:2, 2]
    return uv, z


def depth_tracks(depths: Sequence[np.ndarray], poses: np.ndarray, K: np.ndarray, pts: dict[str, np.ndarray],
                 max_track: int, agreement: float = DEPTH_AGREEMENT,
                 min_views: int = MIN_VIEWS) -> list[tuple[np.ndarray, np.ndarray]]:
    """The observations of every frame k: (point ids int64 (Mk,) ascending, pixels float64 (Mk, 2)
    in our convention). Frame k observes a point that projects inside it (nearest pixel in the
    image), in front of the camera, where the frame's depth agrees within ``agreement``; its own
    frame observes it at its sampled pixel. A point seen by fewer than ``min_views`` frames is
    observed by none (the caller drops it); a point keeps at most ``max_track`` frames, evenly
    spread over those that see it (its own frame always)."""
    n, m = len(poses), len(pts["xyz"])
    own = pts["frame"]
    seen = np.zeros((n, m), bool)
    pix: list[np.ndarray] = []
    for k in range(n):
        d = np.asarray(depths[k], np.float32)
        h, w = d.shape
        uv, z = project(pts["xyz"], poses[k], K)
        ui, vi = np.round(uv[:, 0]), np.round(uv[:, 1])
        inside = (z > 0) & (ui >= 0) & (ui <= w - 1) & (vi >= 0) & (vi <= h - 1)
        dk = np.zeros(m)
        dk[inside] = d[vi[inside].astype(np.int64), ui[inside].astype(np.int64)]
        seen[k] = (inside & (dk > 0) & (np.abs(dk - z) <= agreement * np.abs(z))) | (own == k)
        uv[own == k] = pts["uv"][own == k]
        pix.append(uv[seen[k]])
    # a point only its own frame sees has a one-view track: COLMAP's bundle adjuster aborts on it
    # (SIGABRT in `colmap bundle_adjuster`, an exception in pycolmap.bundle_adjustment)
    kept = seen.copy()
    kept[:, seen.sum(0) < min_views] = False
    for j in np.nonzero(seen.sum(0) > max_track)[0]:
        ks = np.nonzero(seen[:, j])[0]
        keep = ks[np.linspace(0, len(ks) - 1, max_track - 1).round().astype(int)]
        kept[:, j] = False
        kept[keep, j] = kept[own[j], j] = True
    out = []
    for k in range(n):
        ids = np.nonzero(seen[k])[0]
        sel = kept[k, ids]
        out.append((ids[sel], pix[k][sel]))
    return out


# ------------------------------------------------------------------------------ the model


def _model(ctx: ExportContext) -> dict[str, Any]:
    """Everything the files hold, at the export view's resolution (COLMAP pixel convention)."""
    run, view = ctx.run, ctx.view()
    pts = sample_points(run.depths, run.poses, run.K, range(0, len(run), ctx.opt.every), ctx.opt.max_points)
    obs = depth_tracks(run.depths, run.poses, run.K, pts, ctx.opt.max_track)
    # keep the points some frame observes (depth_tracks leaves one-view points unobserved) and
    # number them 0..m-1 in their original order
    used = np.zeros(len(pts["xyz"]), bool)
    for ids, _ in obs:
        used[ids] = True
    new_id = np.cumsum(used) - 1
    pts = {k: v[used] for k, v in pts.items()}
    obs = [(new_id[ids], uv) for ids, uv in obs]
    m = len(pts["xyz"])
    track: list[list[tuple[int, int]]] = [[] for _ in range(m)]
    images = []
    qvec, tvec = c2w_to_colmap(run.poses)
    for k in range(len(run)):
        ids, uv = obs[k]
        xy = view.to_view(uv) + 0.5
        for idx, pid in enumerate(ids):
            track[pid].append((k + 1, idx))
        images.append({"id": k + 1, "q": qvec[k], "t": tvec[k], "name": f"{run.name(k)}.png", "xy": xy,
                       "pid": ids + 1})
    colors = _point_colors(ctx, pts)
    K = view.K
    return {"camera": (view.width, view.height, K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5),
            "images": images, "xyz": pts["xyz"], "rgb": colors, "tracks": track}


def _point_colors(ctx: ExportContext, pts: dict[str, np.ndarray]) -> np.ndarray:
    """uint8 (M, 3): each point's pixel colour in its frame (working resolution), grey without images."""
    colors = np.full((len(pts["xyz"]), 3), 128, np.uint8)
    if ctx.run.images is not None and len(colors):
        for k in np.unique(pts["frame"]):
            sel = pts["frame"] == k
            uv = pts["uv"][sel].astype(np.int64)
            colors[sel] = ctx.run.images[int(k)][uv[:, 1], uv[:, 0]]
    return colors


def _text_files(model: dict[str, Any]) -> dict[str, str]:
    w, h, fx, fy, cx, cy = model["camera"]
    cams = ("# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
            f"# Number of cameras: 1\n1 PINHOLE {w} {h} {num(fx)} {num(fy)} {num(cx)} {num(cy)}\n")
    tracks = model["tracks"]
    n_obs = sum(len(t) for t in tracks)
    pts = ["# 3D point list with one line of data per point:",
           "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
           f"# Number of points: {len(tracks)}, mean track length: {n_obs / max(len(tracks), 1):g}"]
    for pid, (x, c, t) in enumerate(zip(model["xyz"], model["rgb"], tracks)):
        pts.append(f"{pid + 1} {num(x[0])} {num(x[1])} {num(x[2])} {c[0]} {c[1]} {c[2]} 0 "
                   + " ".join(f"{i} {j}" for i, j in t))
    ims = ["# Image list with two lines of data per image:",
           "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)",
           f"# Number of images: {len(model['images'])}, mean observations per image: "
           f"{n_obs / max(len(model['images']), 1):g}"]
    for im in model["images"]:
        ims.append(f"{im['id']} " + " ".join(num(v) for v in (*im["q"], *im["t"])) + f" 1 {im['name']}")
        ims.append(" ".join(f"{num(x)} {num(y)} {p}" for (x, y), p in zip(im["xy"], im["pid"])))
    return {"cameras.txt": cams, "points3D.txt": "\n".join(pts) + "\n", "images.txt": "\n".join(ims) + "\n"}


def _binary_files(model: dict[str, Any]) -> dict[str, bytes]:
    """COLMAP's binary model (little-endian, as colmap/src/colmap/scene/reconstruction_io.cc)."""
    w, h, fx, fy, cx, cy = model["camera"]
    cams = struct.pack("<Q", 1) + struct.pack("<iiQQ", 1, PINHOLE_MODEL_ID, w, h) + struct.pack("<4d", fx, fy, cx, cy)
    pts = [struct.pack("<Q", len(model["tracks"]))]
    for pid, (x, c, t) in enumerate(zip(model["xyz"], model["rgb"], model["tracks"])):
        pts.append(struct.pack("<Q3d3Bd", pid + 1, *map(float, x), *map(int, c), 0.0))
        pts.append(struct.pack("<Q", len(t)) + np.asarray(t, "<u4").reshape(-1).tobytes())
    ims = [struct.pack("<Q", len(model["images"]))]
    for im in model["images"]:
        ims.append(struct.pack("<i7di", im["id"], *map(float, im["q"]), *map(float, im["t"]), 1))
        ims.append(im["name"].encode() + b"\0" + struct.pack("<Q", len(im["pid"])))
        rec = np.zeros(len(im["pid"]), dtype=[("x", "<f8"), ("y", "<f8"), ("p", "<i8")])
        rec["x"], rec["y"], rec["p"] = im["xy"][:, 0], im["xy"][:, 1], im["pid"]
        ims.append(rec.tobytes())
    return {"cameras.bin": cams, "points3D.bin": b"".join(pts), "images.bin": b"".join(ims)}


@uses_images("optional")
def write(ctx: ExportContext) -> dict[str, Any]:
    d = ctx.out / "colmap"
    sparse = d / "sparse" / "0"
    view = ctx.view()
    if view.images is not None:
        ctx.images_dir("images")
    else:
        ctx.log(f"warning: colmap: {ctx.run.images_error}; writing the model without images/")
    model = _model(ctx)
    files: dict[str, Any] = _binary_files(model) if ctx.opt.colmap_binary else _text_files(model)
    other = (".txt" if ctx.opt.colmap_binary else ".bin")
    for name in ("cameras", "images", "points3D"):  # a stale model of the other kind would be read too
        (sparse / (name + other)).unlink(missing_ok=True)
    for name in ("cameras", "points3D", "images"):  # images refers to points3D
        fn = name + (".bin" if ctx.opt.colmap_binary else ".txt")
        (write_bytes if ctx.opt.colmap_binary else write_text)(sparse / fn, files[fn])
    n_obs = sum(len(t) for t in model["tracks"])
    return {"dir": str(sparse), "images": len(ctx.run), "points3D": len(model["tracks"]),
            "mean_track_length": round(n_obs / max(len(model["tracks"]), 1), 3),
            "binary": ctx.opt.colmap_binary, "width": view.width, "height": view.height,
            "resolution": view.resolution, "image_dir": str(ctx.out / "images") if view.images is not None else None}
