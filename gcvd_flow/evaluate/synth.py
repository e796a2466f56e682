"""Synthetic indoor clips with exact ground truth (depth, poses, intrinsics, dynamic mask).

Usage:
    from gcvd_flow.evaluate.synth import render_clip
    clip = render_clip(n_frames=60, trajectory="loop", size=(256, 192), moving_object=False, seed=0)
    clip.frames (N,H,W,3) uint8 RGB | clip.depth (N,H,W) float32 z-depth [m] | clip.K (3,3)
    clip.poses (N,4,4) float64 camera-to-world, OpenCV axes | clip.dynamic (N,H,W) bool or None
    trajectories: "orbit", "loop" (last pose == first pose), "forward", "rotation" (no translation),
    "walk" (a 3 m S-shaped walk that never revisits a place: drift without loops).

Hard clips (real footage's troubles, each switchable, deterministic for a seed): sensor noise
(``noise``, std in 8-bit levels), motion blur along each frame's image motion (``blur``, fraction
of the exposure the shutter is open), exposure changes (``exposure``: relative gain swing
between frames, breaks brightness constancy), low texture (``texture`` < 1 flattens the
surface detail), and an independently moving object. Ground truth is unaffected. A clip where
most frames become keyframes: few frames over a long path (``--trajectory walk --frames 60``).

The scene is a 6 x 3 x 6 m room (world frame: y points DOWN, i.e. gravity is +y, so a level
OpenCV camera has an identity rotation; floor at y = +1.5, ceiling at y = -1.5) with
furniture boxes at various depths. It is ray cast with ``open3d.t.geometry.RaycastingScene``
and textured procedurally at the 3-D hit point (multi-octave value noise for high-frequency
luminance + low-frequency colour blobs + a per-face base colour), shaded by a fixed
directional light (Lambertian, view independent, so brightness constancy holds exactly for
static surfaces). High noise octaves fade out where a lattice cell would be smaller than
~1.5 px, like mip-mapping, so the texture does not alias at far / grazing surfaces.

Pure: no file I/O. Deterministic for a given ``seed`` (byte-identical arrays on a machine).
Geometry and trajectories do not depend on the seed; textures (and colours) do.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import open3d as o3d

log = logging.getLogger(__name__)

TRAJECTORIES = ("orbit", "loop", "forward", "rotation", "walk", "scan")

# Room extents in metres (world frame, y down).
ROOM_MIN = np.array([-3.0, -1.5, -3.0])
ROOM_MAX = np.array([3.0, 1.5, 3.0])

# Static furniture: (min corner, max corner, yaw about the vertical axis in radians).
# Kept out of the volume the camera paths sweep (|x| < 1.2, z < -0.8, y ~ 0).
_FURNITURE: tuple[tuple[tuple[float, float, float], tuple[float, float, float], float], ...] = (
    ((-0.6, 0.75, -0.4), (0.6, 1.5, 0.4), 0.0),  # table in the room centre
    ((-0.2, 0.45, -0.15), (0.15, 0.75, 0.2), 0.35),  # box on the table (rotated)
    ((-2.9, -0.5, 0.5), (-2.3, 1.5, 1.5), 0.0),  # tall cabinet, left
    ((2.2, -0.2, -1.0), (2.9, 1.5, 0.2), 0.0),  # shelf, right
    ((1.0, -1.5, 1.0), (1.3, 1.5, 1.3), 0.0),  # pillar
    ((-1.8, 1.0, 1.6), (-0.6, 1.5, 2.6), 0.0),  # couch-like low box
    ((-0.5, -0.6, 2.6), (0.8, -0.3, 3.0), 0.0),  # wall shelf, back wall
    ((1.0, 1.0, -0.2), (1.4, 1.5, 0.2), 0.5),  # stool (rotated)
    ((-2.0, 0.6, -2.9), (-1.2, 1.5, -2.3), 0.0),  # box behind the start poses (seen on loops)
)

# Moving object: cube edge length (m), placed relative to the current camera.
_OBJ_SIZE = 0.5
# Direction of the fixed light (world, y down: light comes mostly from above).
_LIGHT = np.array([0.35, -0.8, 0.48]) / np.linalg.norm([0.35, -0.8, 0.48])

_TABLE_BITS = 6
_TABLE_N = 1 << _TABLE_BITS  # value-noise lattice period (cells)
_TABLE_MASK = _TABLE_N - 1
# Luminance octaves: lattice cells per metre and relative amplitudes. The high octaves give
# DIS flow texture everywhere; they fade with distance (see _fade).
_LUM_FREQS = (2.0, 5.0, 11.0, 23.0, 47.0)
_LUM_AMPS = (0.7, 0.8, 1.0, 1.0, 0.9)
_BLOB_FREQ = 1.7  # colour blobs (random coloured patches with soft edges)


@dataclass
class SynthClip:
    """A rendered clip with exact ground truth.

    frames:  uint8 (N, H, W, 3) RGB.
    depth:   float32 (N, H, W) z-depth in metres (along the optical axis, not ray length).
    poses:   float64 (N, 4, 4) camera-to-world, OpenCV camera axes (x right, y down, z fwd).
    K:       float64 (3, 3) pinhole intrinsics.
    dynamic: bool (N, H, W), True where the pixel sees the moving object; None without one.
    trajectory, seed: how the clip was made (for records).
    """

    frames: np.ndarray
    depth: np.ndarray
    poses: np.ndarray
    K: np.ndarray
    dynamic: np.ndarray | None
    trajectory: str = "orbit"
    seed: int = 0
    # lens distortion the frames were rendered through (OPENCV: k1, k2, p1, p2[, k3]; OPENCV_FISHEYE:
    # k1..k4, cv2.fisheye); K is the pinhole camera's (the undistorted image), depth and dynamic are registered to
    # the distorted frames, as a real RGB-D dataset's are
    distortion: tuple[float, ...] | None = None
    distortion_model: str = "OPENCV"


def default_intrinsics(size: tuple[int, int]) -> np.ndarray:
    """Default pinhole K (float64 (3, 3)) for ``size = (W, H)`` pixels.

    f = 300/384 * long side (the GCVD authors' guess, ~0.78 W for landscape images),
    principal point at the image centre in pixel-centre coordinates ((W-1)/2, (H-1)/2).
    """
    w, h = int(size[0]), int(size[1])
    f = 300.0 / 384.0 * max(w, h)
    return np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------- trajectories


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world (4, 4) at ``eye`` looking at ``target``, no roll (world y is down)."""
    fwd = target - eye
    fwd = fwd / np.linalg.norm(fwd)
    right = np.cross(np.array([0.0, 1.0, 0.0]), fwd)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = right, down, fwd, eye
    return T


def _yaw_pitch(yaw: float, pitch: float) -> np.ndarray:
    """Rotation (3, 3): yaw about world y (down), then pitch about the camera x axis.

    Positive pitch tilts the view down (towards +y, the floor).
    """
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    Ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cp, sp], [0.0, -sp, cp]])
    return Ry @ Rx


def make_trajectory(kind: str, n_frames: int) -> np.ndarray:
    """Smooth camera-to-world poses float64 (N, 4, 4) for one of ``TRAJECTORIES``.

    Total motion does not depend on ``n_frames`` (per-frame motion scales as 1/(N-1)); at 60
    frames it is ~1-3 cm and < 1 deg per frame, like a slow hand-held camera.
    """
    if kind not in TRAJECTORIES:
        raise ValueError(f"unknown trajectory {kind!r}; expected one of {TRAJECTORIES}")
    n = int(n_frames)
    if n < 2:
        raise ValueError("n_frames must be >= 2")
    s = np.arange(n, dtype=np.float64) / (n - 1)  # normalised time in [0, 1]
    poses = np.empty((n, 4, 4))
    if kind == "orbit":
        # Arc of radius 1.8 m around the room centre, 38 deg in total (~1.2 m of path).
        centre, radius, span = np.array([0.0, 0.0, 0.0]), 1.8, np.deg2rad(38.0)
        for i, si in enumerate(s):
            a = span * (si - 0.5)
            eye = centre + np.array([radius * np.sin(a), -0.05 + 0.03 * np.sin(2 * np.pi * si), -radius * np.cos(a)])
            poses[i] = _look_at(eye, np.array([0.0, 0.55, 0.6]))
    elif kind == "loop":
        # Closed ellipse (~1.6 m perimeter) with a gentle yaw/pitch sway; periodic in s, so
        # the last frame revisits the first. The last pose is set to the first exactly
        # because sin(2 pi) is not exactly 0 in floating point.
        c = np.array([0.0, -0.05, -1.6])
        for i, si in enumerate(s):
            ph = 2 * np.pi * si
            eye = c + np.array([0.27 * np.sin(ph), 0.04 * np.sin(2 * ph), 0.18 * (1 - np.cos(ph))])
            R = _yaw_pitch(0.12 * np.sin(ph), 0.22 + 0.04 * np.sin(2 * ph))
            poses[i] = np.eye(4)
            poses[i, :3, :3], poses[i, :3, 3] = R, eye
        poses[-1] = poses[0]
    elif kind == "forward":
        # Straight 1.2 m walk along +z with a tiny lateral / vertical bob; never revisits.
        for i, si in enumerate(s):
            eye = np.array([0.25 + 0.02 * np.sin(2 * np.pi * si), -0.05 + 0.01 * np.sin(4 * np.pi * si), -2.5 + 1.2 * si])
            R = _yaw_pitch(-0.05 + 0.04 * np.sin(np.pi * si), 0.2)
            poses[i] = np.eye(4)
            poses[i, :3, :3], poses[i, :3, 3] = R, eye
    elif kind == "walk":
        # S-shaped 3 m walk through the free part of the room, looking along the path (yaw
        # follows the tangent); never revisits a place, so only odometry holds it together.
        for i, si in enumerate(s):
            x, z = 0.9 * np.sin(np.pi * (2 * si - 1) * 0.75), -2.6 + 1.7 * si
            dx = 0.9 * np.cos(np.pi * (2 * si - 1) * 0.75) * np.pi * 1.5
            eye = np.array([x, -0.05 + 0.015 * np.sin(6 * np.pi * si), z])
            R = _yaw_pitch(0.35 * np.arctan2(dx, 1.7), 0.2)
            poses[i] = np.eye(4)
            poses[i, :3, :3], poses[i, :3, 3] = R, eye
    elif kind == "scan":
        # A room scan: 2.5 m along the room while panning +-40 deg four times (yaw ~3 deg per
        # frame at 200 frames, like sweeping a phone across the walls): the keyframe-heavy clip
        # (88 of 200 frames, 44 %, become keyframes; the real clips of issue 13 had 22-60 %).
        for i, si in enumerate(s):
            eye = np.array([0.6 * np.sin(np.pi * si), -0.05 + 0.02 * np.sin(8 * np.pi * si), -2.4 + 2.5 * si])
            R = _yaw_pitch(np.deg2rad(40.0) * np.sin(4 * 2 * np.pi * si), 0.2 + 0.05 * np.sin(3 * np.pi * si))
            poses[i] = np.eye(4)
            poses[i, :3, :3], poses[i, :3, 3] = R, eye
    else:  # rotation: pan 40 deg with a small tilt, camera centre fixed exactly
        eye = np.array([0.0, -0.05, -1.6])
        for i, si in enumerate(s):
            R = _yaw_pitch(np.deg2rad(40.0) * (si - 0.5), 0.22 + 0.05 * np.sin(2 * np.pi * si))
            poses[i] = np.eye(4)
            poses[i, :3, :3], poses[i, :3, 3] = R, eye
    return poses


def _object_poses(cam_poses: np.ndarray) -> np.ndarray:
    """Object-to-world (N, 4, 4) of the moving cube.

    Defined relative to each camera so it stays in view in most frames: 1.6 m ahead, sweeping
    from left to right across the image over the clip while spinning about its own axis.
    Its world motion is therefore unrelated to the static scene's apparent motion.
    """
    n = len(cam_poses)
    s = np.arange(n, dtype=np.float64) / max(n - 1, 1)
    out = np.empty((n, 4, 4))
    for i, si in enumerate(s):
        local = np.array([-0.85 + 1.7 * si, 0.05 + 0.12 * np.sin(np.pi * si), 1.6])
        spin = _yaw_pitch(0.4 + 2.0 * si, 0.3)
        out[i] = np.eye(4)
        out[i, :3, :3] = cam_poses[i, :3, :3] @ spin
        out[i, :3, 3] = cam_poses[i, :3, :3] @ local + cam_poses[i, :3, 3]
    return out


# ----------------------------------------------------------------------------- scene


def _box_mesh(lo, hi, yaw: float = 0.0, inward: bool = False) -> o3d.t.geometry.TriangleMesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    m = o3d.geometry.TriangleMesh.create_box(*(hi - lo))
    v = np.asarray(m.vertices) + lo
    if yaw:
        c = (lo + hi) / 2
        v = (v - c) @ _yaw_pitch(yaw, 0.0).T + c
    t = np.asarray(m.triangles)
    if inward:  # flip winding so the room's normals face inwards
        t = t[:, [0, 2, 1]]
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(v.astype(np.float32))  # type: ignore[call-overload]  # open3d's stubs make dtype and device required
    mesh.triangle.indices = o3d.core.Tensor(t.astype(np.int32))  # type: ignore[call-overload]  # open3d's stubs make dtype and device required
    return mesh


def _static_scene() -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(_box_mesh(ROOM_MIN, ROOM_MAX, inward=True))  # geometry id 0
    for lo, hi, yaw in _FURNITURE:
        scene.add_triangles(_box_mesh(lo, hi, yaw))
    return scene


def _object_scene() -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    h = _OBJ_SIZE / 2
    scene.add_triangles(_box_mesh((-h, -h, -h), (h, h, h)))
    return scene


# ----------------------------------------------------------------------------- texture


@dataclass
class _Texture:
    table: np.ndarray  # float32 (TABLE_N**3,) lattice values in [0, 1)
    rots: np.ndarray  # float32 (n_octaves, 3, 3) per-octave rotations (decorrelate octaves)
    offs: np.ndarray  # float32 (n_octaves, 3) per-octave lattice offsets
    palette: np.ndarray  # float32 (n_geoms, 6, 2, 3) two base colours per box face


def _make_texture(seed: int, n_geoms: int) -> _Texture:
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5EED]))
    table = rng.random(_TABLE_N**3, dtype=np.float32)
    n_oct = len(_LUM_FREQS) + 3  # luminance octaves + 3 colour-blob channels
    q = np.linalg.qr(rng.standard_normal((n_oct, 3, 3)))[0]
    offs = rng.uniform(0, _TABLE_N, (n_oct, 3))
    # Base colours: moderately saturated, never dark, so every face has texture contrast.
    palette = rng.uniform(0.35, 1.0, (n_geoms, 6, 2, 3))
    return _Texture(table, q.astype(np.float32), offs.astype(np.float32), palette.astype(np.float32))


def _value_noise(tex: _Texture, p: np.ndarray, k: int, freq: float) -> np.ndarray:
    """Smooth value noise in [0, 1] at points p (M, 3) [m]; octave k sets rotation/offset."""
    q = (p @ tex.rots[k].T) * np.float32(freq) + tex.offs[k]
    f = np.floor(q)
    w = q - f
    w = w * w * (3.0 - 2.0 * w)  # smoothstep weights: C1-continuous noise
    i = f.astype(np.int64)
    ix0, iy0, iz0 = (i[:, 0] & _TABLE_MASK) << (2 * _TABLE_BITS), (i[:, 1] & _TABLE_MASK) << _TABLE_BITS, i[:, 2] & _TABLE_MASK
    ix1 = ((i[:, 0] + 1) & _TABLE_MASK) << (2 * _TABLE_BITS)
    iy1 = ((i[:, 1] + 1) & _TABLE_MASK) << _TABLE_BITS
    iz1 = (i[:, 2] + 1) & _TABLE_MASK
    t = tex.table
    wx, wy, wz = w[:, 0], w[:, 1], w[:, 2]
    c00 = t[ix0 | iy0 | iz0] + wx * (t[ix1 | iy0 | iz0] - t[ix0 | iy0 | iz0])
    c10 = t[ix0 | iy1 | iz0] + wx * (t[ix1 | iy1 | iz0] - t[ix0 | iy1 | iz0])
    c01 = t[ix0 | iy0 | iz1] + wx * (t[ix1 | iy0 | iz1] - t[ix0 | iy0 | iz1])
    c11 = t[ix0 | iy1 | iz1] + wx * (t[ix1 | iy1 | iz1] - t[ix0 | iy1 | iz1])
    c0 = c00 + wy * (c10 - c00)
    c1 = c01 + wy * (c11 - c01)
    return c0 + wz * (c1 - c0)


def _shade(
    tex: _Texture,
    p_tex: np.ndarray,
    n_tex: np.ndarray,
    n_world: np.ndarray,
    geom: np.ndarray,
    footprint: np.ndarray,
    texture: float = 1.0,
) -> np.ndarray:
    """RGB float32 (M, 3) in [0, 1].

    p_tex (M,3): texture-space hit points [m] (object-local for the moving object);
    n_tex (M,3): normals in texture space (picks the face's base colour);
    n_world (M,3): world normals (lighting); geom (M,) palette index;
    footprint (M,): metres per pixel on the surface (for octave fading);
    texture: contrast of the surface detail (1 = full, 0 = flat faces).
    """
    # Luminance: fBm whose octaves fade to their mean (0.5) where a cell spans < ~1.5-3 px.
    acc = np.zeros(len(p_tex), np.float32)
    for k, (fr, amp) in enumerate(zip(_LUM_FREQS, _LUM_AMPS)):
        px_per_cell = 1.0 / (fr * footprint)
        fade = np.clip((px_per_cell - 1.5) / 1.5, 0.0, 1.0).astype(np.float32)
        acc += np.float32(amp) * (0.5 + fade * (_value_noise(tex, p_tex, k, fr) - 0.5))
    lum = acc / np.float32(sum(_LUM_AMPS))
    # Sum of octaves squeezes contrast towards 0.5; stretch it back.
    lum = np.clip(0.6 + 2.2 * np.float32(texture) * (lum - 0.5), 0.1, 1.0)
    # Colour blobs: per-channel low-frequency noise, sharpened into soft-edged patches,
    # mixing the face's two base colours.
    k0 = len(_LUM_FREQS)
    blob = np.stack([_value_noise(tex, p_tex, k0 + c, _BLOB_FREQ) for c in range(3)], axis=1)
    blob = np.clip((blob - 0.5) * 4.0 * np.float32(texture) + 0.5, 0.0, 1.0)
    face = np.argmax(np.abs(n_tex), axis=1) * 2 + (np.take_along_axis(n_tex, np.argmax(np.abs(n_tex), axis=1)[:, None], 1)[:, 0] > 0)
    cols = tex.palette[geom, face]  # (M, 2, 3)
    base = cols[:, 0] + blob * (cols[:, 1] - cols[:, 0])
    light = 0.6 + 0.4 * np.abs(n_world @ _LIGHT.astype(np.float32))
    return np.clip(base * (lum * light)[:, None], 0.0, 1.0)


# ----------------------------------------------------------------------------- rendering


def _rays(K: np.ndarray, pose: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Ray origins (M,3) and world directions (M,3) whose camera-frame z component is 1.

    With that normalisation open3d's t_hit (in units of the direction length) is z-depth.
    """
    w, h = size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
    d_world = d_cam @ pose[:3, :3].T
    o = np.broadcast_to(pose[:3, 3], d_world.shape)
    return o, d_world


def _cast(scene: o3d.t.geometry.RaycastingScene, o: np.ndarray, d: np.ndarray) -> dict[str, np.ndarray]:
    rays = np.concatenate([o, d], axis=1).astype(np.float32)
    r = scene.cast_rays(o3d.core.Tensor(rays))  # type: ignore[call-overload]  # open3d's stubs make dtype and device required
    return {k: r[k].numpy() for k in ("t_hit", "geometry_ids", "primitive_normals")}


@dataclass
class _Scenes:
    """What every frame is ray cast against and shaded with."""

    static: o3d.t.geometry.RaycastingScene  # the room and its furniture, world frame
    tex: _Texture
    obj: o3d.t.geometry.RaycastingScene | None  # the moving cube in its own frame, or None
    obj_poses: np.ndarray | None  # (N, 4, 4) the cube's poses, or None


@dataclass
class _Hits:
    """One frame's surface hits, one per ray (M rays)."""

    t: np.ndarray  # (M,) float32 z-depth (t_hit)
    geom: np.ndarray  # (M,) int64 palette index
    n_world: np.ndarray  # (M, 3) float32 world normals (lighting)
    n_tex: np.ndarray  # (M, 3) float32 normals in texture space (the face's base colour)
    p_tex: np.ndarray  # (M, 3) float32 texture-space points [m]


def _static_hits(scene: o3d.t.geometry.RaycastingScene, o: np.ndarray, d: np.ndarray) -> _Hits:
    hit = _cast(scene, o, d)
    t = hit["t_hit"]
    n_world = hit["primitive_normals"]
    # World-space texture coordinates for the static scene.
    p_tex = (o + t[:, None].astype(np.float64) * d).astype(np.float32)
    return _Hits(t, hit["geometry_ids"].astype(np.int64), n_world, n_world, p_tex)


def _add_object(hits: _Hits, obj_scene: o3d.t.geometry.RaycastingScene, To: np.ndarray, o: np.ndarray,
                d: np.ndarray, geom_id: int) -> np.ndarray:
    """The cube at pose ``To`` takes the rays it hits before the static scene (palette ``geom_id``,
    object-local texture); returns that mask (M,) bool.

    Ray cast the cube in its own frame: a rigid transform of (o, d) keeps the direction length,
    so t_hit stays comparable (z-depth) with the static hits."""
    o_l = (o - To[:3, 3]) @ To[:3, :3]
    d_l = d @ To[:3, :3]
    oh = _cast(obj_scene, o_l, d_l)
    m = oh["t_hit"] < hits.t
    hits.t = np.where(m, oh["t_hit"], hits.t)
    hits.geom = np.where(m, geom_id, hits.geom)
    n_obj_local = oh["primitive_normals"]
    hits.p_tex[m] = (o_l[m] + oh["t_hit"][m, None].astype(np.float64) * d_l[m]).astype(np.float32)
    hits.n_tex = np.where(m[:, None], n_obj_local, hits.n_world)
    hits.n_world = np.where(m[:, None], (n_obj_local.astype(np.float64) @ To[:3, :3].T).astype(np.float32),
                            hits.n_world)
    return m


def _shade_hits(tex: _Texture, hits: _Hits, d: np.ndarray, f: np.float32, texture: float) -> np.ndarray:
    """uint8 (M, 3) colours of the hits seen along directions d (M, 3); f: focal length [px]."""
    if not np.all(np.isfinite(hits.t)):
        raise RuntimeError("a ray left the closed room; camera outside the scene?")
    # Metres per pixel across the surface: z / f, stretched at grazing angles.
    d_unit = d / np.linalg.norm(d, axis=1, keepdims=True)
    cos = np.abs(np.sum(d_unit * hits.n_world, axis=1)).astype(np.float32)
    footprint = hits.t / f / np.maximum(cos, 0.25)
    rgb = _shade(tex, hits.p_tex, hits.n_tex, hits.n_world, hits.geom, footprint, texture)
    return np.round(rgb * 255.0).astype(np.uint8)


def _render_frames(K: np.ndarray, poses: np.ndarray, size: tuple[int, int], scenes: _Scenes,
                   texture: float) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Ray cast and shade every pose: (frames uint8 (N, H, W, 3), depth float32 (N, H, W),
    dynamic bool (N, H, W) or None without a moving object)."""
    w, h = size
    n = len(poses)
    frames = np.empty((n, h, w, 3), np.uint8)
    depth = np.empty((n, h, w), np.float32)
    dynamic = np.zeros((n, h, w), bool) if scenes.obj is not None else None
    f = np.float32(K[0, 0])
    n_static = 1 + len(_FURNITURE)  # the moving object's palette entry
    for i in range(n):
        o, d = _rays(K, poses[i], (w, h))
        hits = _static_hits(scenes.static, o, d)
        if scenes.obj is not None and scenes.obj_poses is not None and dynamic is not None:
            m = _add_object(hits, scenes.obj, scenes.obj_poses[i], o, d, n_static)
            dynamic[i] = m.reshape(h, w)
        rgb = _shade_hits(scenes.tex, hits, d, f, texture)
        depth[i] = hits.t.reshape(h, w)
        frames[i] = rgb.reshape(h, w, 3)
    return frames, depth, dynamic


def render_clip(
    n_frames: int = 60,
    trajectory: str = "orbit",
    size: tuple[int, int] = (256, 192),
    moving_object: bool = False,
    seed: int = 0,
    noise: float = 0.0,
    blur: float = 0.0,
    exposure: float = 0.0,
    texture: float = 1.0,
    focal: float | None = None,
    distortion: tuple[float, ...] | None = None,
    distortion_model: str = "OPENCV",
    principal_point: tuple[float, float] | None = None,
) -> SynthClip:
    """Render a synthetic clip of the textured room.

    n_frames: number of frames N (>= 2); trajectory: one of ``TRAJECTORIES``;
    size: (W, H) in pixels; moving_object: add one independently moving textured cube and
    return its per-pixel mask in ``dynamic``; seed: texture/colour seed; noise, blur, exposure,
    texture: camera impairments (module docstring; 0, 0, 0, 1 = a perfect camera); focal: fx = fy
    in px (None: ``default_intrinsics``' 300/384 x long side), principal point at the centre;
    distortion: the lens the frames are seen through, ``distortion_model`` "OPENCV" (k1, k2, p1, p2[, k3])
    or "OPENCV_FISHEYE" (k1..k4, cv2.fisheye); the ground truth stays pinhole; principal_point: (cx, cy)
    in px (None: the centre ((W-1)/2, (H-1)/2)), not with ``distortion``.
    Returns a ``SynthClip`` (see its docstring for shapes and units).
    """
    w, h = int(size[0]), int(size[1])
    lensed = distortion is not None and (any(distortion) or distortion_model != "OPENCV")
    if principal_point is not None and lensed:
        raise ValueError("a principal point off the centre is not rendered with lens distortion")
    if lensed:
        assert distortion is not None  # lensed implies it
        return _distorted_clip(n_frames, trajectory, (w, h), moving_object, seed, noise, blur, exposure, texture,
                               focal, tuple(float(v) for v in distortion), distortion_model)
    K = default_intrinsics((w, h))
    if focal is not None:
        K[0, 0] = K[1, 1] = float(focal)
    if principal_point is not None:
        K[0, 2], K[1, 2] = float(principal_point[0]), float(principal_point[1])
    poses = make_trajectory(trajectory, n_frames)
    n_static = 1 + len(_FURNITURE)
    scenes = _Scenes(_static_scene(), _make_texture(seed, n_static + 1),  # last palette entry: the moving object
                     _object_scene() if moving_object else None, _object_poses(poses) if moving_object else None)
    frames, depth, dynamic = _render_frames(K, poses, (w, h), scenes, texture)
    if noise or blur or exposure:
        frames = impair(frames, depth, poses, K, noise=noise, blur=blur, exposure=exposure, seed=seed)
    log.debug("rendered %d frames (%s, %dx%d, moving_object=%s)", len(poses), trajectory, w, h, moving_object)
    return SynthClip(frames=frames, depth=depth, poses=poses, K=K, dynamic=dynamic, trajectory=trajectory, seed=int(seed))


def _distorted_clip(n_frames: int, trajectory: str, size: tuple[int, int], moving_object: bool, seed: int,
                    noise: float, blur: float, exposure: float, texture: float, focal: float | None,
                    distortion: tuple[float, ...], model: str = "OPENCV") -> SynthClip:
    """A clip seen through a lens (OpenCV's radial-tangential model, or cv2.fisheye's): the pinhole
    clip is rendered on a canvas padded to hold where every distorted pixel's ray lands (same
    focal length, principal point moved by the pad), and each distorted pixel samples it there
    (bilinear). Depth and dynamic masks are registered to the distorted frames, as a real RGB-D
    dataset's are (each distorted pixel's ray's z-depth, nearest), so evaluation must map them
    through the lens as it does a dataset's (``run_eval.sample_source_map``)."""
    import cv2

    w, h = size
    f = float(focal) if focal is not None else float(default_intrinsics(size)[0, 0])
    K = default_intrinsics(size)
    K[0, 0] = K[1, 1] = f
    und = undistort_pixels(K, distortion, model, size)
    reach = max(-und[..., 0].min(), und[..., 0].max() - (w - 1), -und[..., 1].min(), und[..., 1].max() - (h - 1))
    if not np.isfinite(reach) or reach > 2 * max(w, h):
        raise ValueError(f"distortion {model} {distortion}: the lens sees beyond 2x the image size (too strong)")
    pad = max(max(w, h) // 3, int(np.ceil(reach)) + 2)
    big = render_clip(n_frames, trajectory, (w + 2 * pad, h + 2 * pad), moving_object, seed, noise, blur,
                      exposure, texture, focal=f)
    mx = (und[..., 0] + pad).astype(np.float32)
    my = (und[..., 1] + pad).astype(np.float32)
    frames = np.stack([cv2.remap(fr, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT) for fr in big.frames])

    def seen(maps: np.ndarray) -> np.ndarray:  # nearest: a depth or a mask is not blended across an edge
        return np.stack([cv2.remap(m, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT) for m in maps])

    dynamic = None if big.dynamic is None else seen(big.dynamic.astype(np.uint8)).astype(big.dynamic.dtype)
    return SynthClip(frames=frames, depth=seen(big.depth), poses=big.poses, K=K, dynamic=dynamic,
                     trajectory=trajectory, seed=int(seed), distortion=distortion, distortion_model=model)


def undistort_pixels(K: np.ndarray, distortion: tuple[float, ...], model: str, size: tuple[int, int]) -> np.ndarray:
    """Every pixel (u, v) of a distorted image of ``size`` = (w, h) -> where its ray meets the
    pinhole image of K: float64 (h, w, 2) (OpenCV's iterative undistortPoints, 50 iterations)."""
    import cv2

    w, h = size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([u.ravel(), v.ravel()], -1)[:, None, :]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-9)
    D = np.asarray(distortion, np.float64)
    if model == "OPENCV_FISHEYE":
        und = cv2.fisheye.undistortPoints(pts, K, D, None, K, criteria=crit)
    elif model == "OPENCV":
        und = cv2.undistortPoints(pts, K, D, None, K, criteria=crit)
    else:
        raise ValueError(f"unknown distortion model {model!r} (OPENCV, OPENCV_FISHEYE)")
    return und.reshape(h, w, 2)


# ----------------------------------------------------------------------------- camera impairments


def _image_motion(depth: np.ndarray, T_w_a: np.ndarray, T_w_b: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Median image motion (dx, dy) px of frame a's pixels in frame b (exact, from depth)."""
    h, w = depth.shape
    v, u = np.mgrid[0:h:8, 0:w:8]
    z = depth[v, u].astype(np.float64)
    X = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1).reshape(-1, 3)
    T_b_a = np.linalg.inv(T_w_b) @ T_w_a
    Y = X @ T_b_a[:3, :3].T + T_b_a[:3, 3]
    ok = Y[:, 2] > 1e-3
    uv = np.stack([K[0, 0] * Y[ok, 0] / Y[ok, 2] + K[0, 2], K[1, 1] * Y[ok, 1] / Y[ok, 2] + K[1, 2]], -1)
    return np.median(uv - np.stack([u.reshape(-1)[ok], v.reshape(-1)[ok]], -1), axis=0)


def impair(frames: np.ndarray, depth: np.ndarray, poses: np.ndarray, K: np.ndarray, noise: float = 0.0,
           blur: float = 0.0, exposure: float = 0.0, seed: int = 0) -> np.ndarray:
    """Camera impairments on rendered frames uint8 (N, H, W, 3): motion blur (a line kernel along
    each frame's image motion to the next frame, ``blur`` x its length), exposure gain
    (a smooth random walk of +-``exposure``), Gaussian sensor noise (std ``noise`` levels)."""
    import cv2

    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xCA3E]))
    n = len(frames)
    gain = 1.0 + exposure * np.sin(np.cumsum(rng.uniform(0.2, 0.9, n)))  # smooth swings, seeded
    out = np.empty_like(frames)
    for i in range(n):
        img = frames[i].astype(np.float32)
        if blur > 0:
            j = i + 1 if i + 1 < n else i - 1
            dx, dy = _image_motion(depth[i], poses[i], poses[j], K) * blur
            length = int(np.ceil(np.hypot(dx, dy)))
            if length >= 2:
                ker = np.zeros((2 * length + 1, 2 * length + 1), np.float32)
                for s in np.linspace(-0.5, 0.5, 4 * length + 1):
                    ker[int(round(length + s * dy)), int(round(length + s * dx))] += 1.0
                img = cv2.filter2D(img, -1, ker / ker.sum(), borderType=cv2.BORDER_REFLECT)
        img = img * np.float32(gain[i])
        if noise > 0:
            img = img + rng.normal(0.0, noise, img.shape).astype(np.float32)
        out[i] = np.clip(np.round(img), 0, 255).astype(np.uint8)
    return out
