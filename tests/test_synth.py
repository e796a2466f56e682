"""Tests for stages.synth: shapes, determinism, trajectory properties, exact geometry."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gcvd_flow.evaluate.synth import TRAJECTORIES, default_intrinsics, make_trajectory, render_clip

SIZE = (128, 96)


@pytest.fixture(scope="module")
def orbit_clip():
    return render_clip(n_frames=40, trajectory="orbit", size=SIZE, seed=3)


def test_shapes_and_dtypes(orbit_clip):
    c = orbit_clip
    assert c.frames.shape == (40, 96, 128, 3) and c.frames.dtype == np.uint8
    assert c.depth.shape == (40, 96, 128) and c.depth.dtype == np.float32
    assert c.poses.shape == (40, 4, 4) and c.poses.dtype == np.float64
    assert c.K.shape == (3, 3) and c.K.dtype == np.float64
    assert c.dynamic is None
    np.testing.assert_allclose(c.poses[:, 3], np.tile([0, 0, 0, 1.0], (40, 1)))
    # Rotations are orthonormal with det +1.
    R = c.poses[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)


def test_default_intrinsics():
    K = default_intrinsics((256, 192))
    assert K[0, 0] == K[1, 1] == pytest.approx(200.0)
    assert (K[0, 2], K[1, 2]) == (127.5, 95.5)


def test_deterministic_bytes():
    a = render_clip(n_frames=4, trajectory="loop", size=(64, 48), moving_object=True, seed=7)
    b = render_clip(n_frames=4, trajectory="loop", size=(64, 48), moving_object=True, seed=7)
    assert a.frames.tobytes() == b.frames.tobytes()
    assert a.depth.tobytes() == b.depth.tobytes()
    assert a.poses.tobytes() == b.poses.tobytes()
    assert a.dynamic.tobytes() == b.dynamic.tobytes()
    c = render_clip(n_frames=4, trajectory="loop", size=(64, 48), moving_object=True, seed=8)
    assert c.frames.tobytes() != a.frames.tobytes()  # the seed changes the texture
    assert c.depth.tobytes() == a.depth.tobytes()  # but not the geometry


def test_depth_positive_and_plausible(orbit_clip):
    d = orbit_clip.depth
    assert np.all(np.isfinite(d))
    assert (d > 0).mean() > 0.999
    assert 0.3 < d.min() and d.max() < 9.0  # inside a 6 x 3 x 6 m room


def test_texture_has_contrast_everywhere(orbit_clip):
    # Local standard deviation (5x5) of the grey image: DIS needs texture on every surface.
    g = cv2.cvtColor(orbit_clip.frames[0], cv2.COLOR_RGB2GRAY).astype(np.float64)
    mu = cv2.blur(g, (5, 5))
    sd = np.sqrt(np.maximum(cv2.blur(g * g, (5, 5)) - mu * mu, 0))
    assert np.mean(sd > 2.0) > 0.9


@pytest.mark.parametrize("kind", [t for t in TRAJECTORIES if t != "scan"])
def test_trajectory_speed(kind):
    # a hand-held pace at 60 frames; the 3 m walk is made for 300 (its pace there is the same)
    P = make_trajectory(kind, 60 if kind != "walk" else 300)
    step = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1)
    rel = np.einsum("nji,njk->nik", P[:-1, :3, :3], P[1:, :3, :3])
    ang = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert step.max() <= 0.031 and ang.max() < 1.0
    if kind != "rotation":
        assert step.mean() > 0.01
    # Same total motion at twice the frame rate.
    P2 = make_trajectory(kind, 2 * len(P) - 1)
    np.testing.assert_allclose(P2[::2], P, atol=1e-12)


def test_loop_closes_exactly():
    P = make_trajectory("loop", 60)
    assert np.array_equal(P[-1], P[0])
    assert np.linalg.norm(P[30, :3, 3] - P[0, :3, 3]) > 0.3  # it actually went somewhere


def test_rotation_has_zero_translation():
    P = make_trajectory("rotation", 30)
    assert np.array_equal(P[:, :3, 3], np.broadcast_to(P[0, :3, 3], (30, 3)))
    assert not np.allclose(P[0, :3, :3], P[-1, :3, :3])


def test_forward_does_not_revisit():
    P = make_trajectory("forward", 60)
    z = P[:, 2, 3]
    assert np.all(np.diff(z) > 0)


def test_reprojection_consistency(orbit_clip):
    """Back-project frame 0 with K, poses into frame 3: its z must match frame 3's depth."""
    c = orbit_clip
    K, h, w = c.K, *c.depth.shape[1:]
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    z0 = c.depth[0].astype(np.float64)
    X0 = np.stack([(u - K[0, 2]) / K[0, 0] * z0, (v - K[1, 2]) / K[1, 1] * z0, z0], -1).reshape(-1, 3)
    T = np.linalg.inv(c.poses[3]) @ c.poses[0]  # camera 0 -> camera 3
    X3 = X0 @ T[:3, :3].T + T[:3, 3]
    pu = K[0, 0] * X3[:, 0] / X3[:, 2] + K[0, 2]
    pv = K[1, 1] * X3[:, 1] / X3[:, 2] + K[1, 2]
    inside = (pu > 0) & (pu < w - 1) & (pv > 0) & (pv < h - 1)
    # Inverse depth is linear in the image on planes, so bilinear sampling of it is exact
    # (up to edges), unlike sampling depth itself.
    inv3 = (1.0 / c.depth[3]).astype(np.float32)
    samp = cv2.remap(inv3, pu.astype(np.float32).reshape(h, w), pv.astype(np.float32).reshape(h, w), cv2.INTER_LINEAR)
    rel = np.abs(1.0 / samp.ravel()[inside] - X3[inside, 2]) / X3[inside, 2]
    assert inside.mean() > 0.8
    assert np.median(rel) < 1e-4
    assert np.mean(rel < 0.01) > 0.93
    # Failures may only come from (dis)occlusions, i.e. near depth edges of frame 0.
    lz = np.log(z0)
    edge = np.zeros((h, w), bool)
    edge[:, 1:] |= np.abs(np.diff(lz, axis=1)) > 0.05
    edge[1:, :] |= np.abs(np.diff(lz, axis=0)) > 0.05
    near_edge = cv2.dilate(edge.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool).ravel()
    smooth = inside & ~near_edge
    assert smooth.mean() > 0.6
    assert np.mean(rel[smooth[inside]] < 0.01) > 0.995


def test_moving_object_is_marked_dynamic():
    c = render_clip(n_frames=6, trajectory="forward", size=SIZE, moving_object=True, seed=0)
    s = render_clip(n_frames=6, trajectory="forward", size=SIZE, moving_object=False, seed=0)
    assert c.dynamic is not None and c.dynamic.shape == c.depth.shape and c.dynamic.dtype == bool
    frac = c.dynamic.mean(axis=(1, 2))
    assert np.all((frac > 0.03) & (frac < 0.25))
    # Exactly the dynamic pixels differ in depth from the static render (object in front).
    assert np.array_equal(c.depth != s.depth, c.dynamic)
    assert np.all(c.depth[c.dynamic] < s.depth[c.dynamic])
    # Static pixels are identical, bytes and all.
    assert np.array_equal(c.frames[~c.dynamic], s.frames[~c.dynamic])
    # It moves independently: its image position changes beyond the camera's motion.
    cols = [np.nonzero(m.any(axis=0))[0].mean() for m in c.dynamic]
    assert cols[-1] - cols[0] > 20


# ----------------------------------------------------------------------------- hard clips


def test_walk_is_long_and_never_revisits():
    from gcvd_flow.evaluate.metrics import path_length
    from gcvd_flow.evaluate.synth import make_trajectory

    P = make_trajectory("walk", 300)
    assert 2.8 < path_length(P) < 3.3
    c = P[:, :3, 3]
    d = np.linalg.norm(c[:, None] - c[None], axis=-1)
    far_in_time = np.abs(np.arange(300)[:, None] - np.arange(300)[None]) > 100  # > 1 m of path apart
    assert d[far_in_time].min() > 0.3  # never back where it was: no loop closure opportunity


def test_impairments_change_pixels_not_ground_truth():
    import cv2

    base = render_clip(n_frames=6, trajectory="orbit", size=(96, 72), seed=3)
    hard = render_clip(n_frames=6, trajectory="orbit", size=(96, 72), seed=3, noise=4.0, blur=1.0, exposure=0.25)
    np.testing.assert_array_equal(hard.depth, base.depth)
    np.testing.assert_array_equal(hard.poses, base.poses)
    diff = np.abs(hard.frames.astype(np.int16) - base.frames)
    assert diff.mean() > 3.0
    gains = hard.frames.reshape(6, -1).mean(1) / base.frames.reshape(6, -1).mean(1)
    assert gains.max() - gains.min() > 0.1  # exposure changes between frames
    again = render_clip(n_frames=6, trajectory="orbit", size=(96, 72), seed=3, noise=4.0, blur=1.0, exposure=0.25)
    np.testing.assert_array_equal(again.frames, hard.frames)  # deterministic

    def grad(f):
        return float(np.mean(np.abs(cv2.Sobel(cv2.cvtColor(f, cv2.COLOR_RGB2GRAY), cv2.CV_32F, 1, 0))))

    flat = render_clip(n_frames=2, trajectory="orbit", size=(96, 72), seed=3, texture=0.2)
    assert grad(flat.frames[0]) < 0.5 * grad(base.frames[0])


def test_scan_is_keyframe_heavy():
    """The scan pans fast (as a phone sweeping the walls): at 200 frames ~3 deg of yaw per
    frame, about 6 px of flow at 256 px wide, where the keyframe threshold (19 px) is crossed
    every 2-3 frames (44 % keyframes, docs/benchmarks.md)."""
    from gcvd_flow.evaluate.synth import make_trajectory

    P = make_trajectory("scan", 200)
    rel = np.einsum("nji,njk->nik", P[:-1, :3, :3], P[1:, :3, :3])
    ang = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert 1.5 < ang.mean() < 4.0 and ang.max() < 6.0
    yaw = np.degrees(np.arctan2(P[:, 0, 2], P[:, 2, 2]))
    assert yaw.max() - yaw.min() > 70  # sweeps the walls, not one view


# ----------------------------------------------------------------------------- principal point


def test_principal_point_off_centre_shifts_the_image_and_is_the_ground_truth():
    """A principal point moved by whole pixels (dx, dy) renders the same rays dx, dy pixels later:
    the image is the centred one shifted (exactly, on the overlap), and K carries it."""
    size, dx, dy = (64, 48), 3, 2
    c = default_intrinsics(size)
    base = render_clip(n_frames=2, trajectory="loop", size=size, seed=1)
    off = render_clip(n_frames=2, trajectory="loop", size=size, seed=1,
                      principal_point=(c[0, 2] + dx, c[1, 2] + dy))
    np.testing.assert_allclose(off.K[:2, 2], c[:2, 2] + [dx, dy])
    assert off.K[0, 0] == base.K[0, 0]
    np.testing.assert_array_equal(off.frames[:, dy:, dx:], base.frames[:, :-dy, :-dx])
    np.testing.assert_allclose(off.depth[:, dy:, dx:], base.depth[:, :-dy, :-dx], rtol=1e-6)
    assert not np.array_equal(off.frames, base.frames)


def test_synth_cli_writes_the_principal_point_and_rejects_a_bad_one(tmp_path):
    from conftest import cli

    from gcvd_flow.io.formats import read_intrinsics_txt

    r = cli("synth", str(tmp_path / "c"), "--frames", "2", "--size", "64x48", "--principal-point", "34.5,26")
    assert r.returncode == 0, r.stderr
    K = read_intrinsics_txt(tmp_path / "c" / "intrinsics.txt")
    np.testing.assert_allclose([K[0, 2], K[1, 2]], [34.5, 26.0])
    for bad in ("34.5", "70,20", "a,b"):
        r = cli("synth", str(tmp_path / "x"), "--frames", "2", "--size", "64x48", "--principal-point", bad)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "--principal-point" in r.stderr, r.stderr
    r = cli("synth", str(tmp_path / "x"), "--frames", "2", "--principal-point", "130,100", "--distortion", "0.1,0,0,0")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
