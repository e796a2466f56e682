"""Flow stage: DIS accuracy against exact rigid flow, determinism, fb consistency, chaining."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_ref import rigid_flow

from gcvd_flow.evaluate.synth import render_clip
from gcvd_flow.stages.frontend.flow import chain_flows, compute_pair_flow, fb_consistency, warp_sample


@pytest.fixture(scope="module")
def orbit():
    return render_clip(16, "orbit", size=(256, 192), seed=0)


def test_dis_epe_vs_rigid_flow(orbit):
    epes = []
    for i in (2, 8, 12):
        r = compute_pair_flow(orbit.frames[i], orbit.frames[i + 1])
        gt = rigid_flow(orbit.depth[i], orbit.K, orbit.poses[i], orbit.poses[i + 1])
        m = r["fwd_valid"] & np.isfinite(gt).all(-1)
        assert m.mean() > 0.7
        epes.append(float(np.linalg.norm(r["fwd"] - gt, axis=-1)[m].mean()))
        gtb = rigid_flow(orbit.depth[i + 1], orbit.K, orbit.poses[i + 1], orbit.poses[i])
        mb = r["bwd_valid"] & np.isfinite(gtb).all(-1)
        epes.append(float(np.linalg.norm(r["bwd"] - gtb, axis=-1)[mb].mean()))
    print(f"DIS medium mean EPE over fb-valid pixels (256x192 orbit): {np.mean(epes):.3f} px")
    assert np.mean(epes) < 1.0


def test_determinism(orbit):
    a = compute_pair_flow(orbit.frames[3], orbit.frames[4])
    b = compute_pair_flow(orbit.frames[3], orbit.frames[4])
    for k in ("fwd", "bwd", "fwd_valid", "bwd_valid"):
        assert a[k].tobytes() == b[k].tobytes()
    assert a["fwd"].dtype == np.float32 and a["fwd"].shape == (192, 256, 2)
    assert a["fwd_valid"].dtype == bool


def test_fb_rejects_out_of_view_and_occlusion():
    h, w = 40, 50
    fwd = np.zeros((h, w, 2), np.float32)
    fwd[..., 0] = 5.0  # everything moves right by 5 px
    bwd = np.zeros((h, w, 2), np.float32)
    bwd[..., 0] = -5.0
    valid = fb_consistency(fwd, bwd, 1.0)
    assert not valid[:, w - 5 :].any()  # leaves the image
    assert valid[:, : w - 5].all()
    # occlusion: a region whose backward flow points elsewhere (it was covered in frame b)
    bwd2 = bwd.copy()
    bwd2[10:20, 20:30] = (3.0, 0.0)
    valid2 = fb_consistency(fwd, bwd2, 1.0)
    assert not valid2[12:18, 16:24].any()
    assert valid2[30:, :20].all()
    # non-finite flow (a backend's failure) is never valid, nor are pixels whose target lands on it
    fwd3 = fwd.copy()
    fwd3[0, 0, 0], fwd3[1, 1, 1], fwd3[2, 2, 0], fwd3[3, 3, 1] = np.nan, np.inf, -np.inf, np.nan
    valid3 = fb_consistency(fwd3, bwd, 1.0)
    assert not valid3[[0, 1, 2, 3], [0, 1, 2, 3]].any() and valid3[4:, : w - 5].all()


def test_fb_on_real_clip_rejects_occluded(orbit):
    """Pixels that GT says become occluded / leave the view must be mostly fb-invalid."""
    i = 5
    r = compute_pair_flow(orbit.frames[i], orbit.frames[i + 1])
    gt = rigid_flow(orbit.depth[i], orbit.K, orbit.poses[i], orbit.poses[i + 1])
    h, w = gt.shape[:2]
    v, u = np.mgrid[0:h, 0:w]
    tx, ty = u + gt[..., 0], v + gt[..., 1]
    out = ~((tx >= 0) & (tx <= w - 1) & (ty >= 0) & (ty <= h - 1))
    assert out.sum() > 50
    assert r["fwd_valid"][out].mean() < 0.1


def test_warp_sample_bilinear():
    f = np.arange(12, dtype=np.float32).reshape(3, 4)
    c = np.array([[[1.5, 0.5]]])
    assert warp_sample(f, c)[0, 0] == pytest.approx(0.5 * (1.5 + 5.5))


def test_chain_flows(orbit):
    i = 4
    links = []
    for j in range(i, i + 3):
        r = compute_pair_flow(orbit.frames[j], orbit.frames[j + 1])
        links.append((r["fwd"], r["fwd_valid"]))
    f, v = chain_flows(links)
    gt = rigid_flow(orbit.depth[i], orbit.K, orbit.poses[i], orbit.poses[i + 3])
    m = v & np.isfinite(gt).all(-1)
    epe = float(np.linalg.norm(f - gt, axis=-1)[m].mean())
    print(f"3-link chained EPE {epe:.3f} px, valid {m.mean():.3f}")
    assert m.mean() > 0.5 and epe < 1.5


def _warp_reference(f: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """warp_sample as first written (2-D fancy index, trailing channel axis), float64."""
    f = f[..., None] if f.ndim == 2 else f
    h, w = f.shape[:2]
    x = np.clip(coords[..., 0].astype(np.float64), 0.0, w - 1.0)
    y = np.clip(coords[..., 1].astype(np.float64), 0.0, h - 1.0)
    x0, y0 = np.minimum(np.floor(x).astype(np.int64), w - 2), np.minimum(np.floor(y).astype(np.int64), h - 2)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    ax, ay = (x - x0)[..., None], (y - y0)[..., None]
    ff = f.astype(np.float64)
    return (ff[y0, x0] * (1 - ax) * (1 - ay) + ff[y0, x1] * ax * (1 - ay)
            + ff[y1, x0] * (1 - ax) * ay + ff[y1, x1] * ax * ay)


def test_warp_sample_and_chain_are_bit_identical_to_the_plain_formula():
    # the fast paths (channels first, take, in-place terms, flow and validity sampled together)
    # must not change a bit: stage outputs are compared by digest
    rng = np.random.default_rng(3)
    h, w = 48, 64
    flows = [((rng.standard_normal((h, w, 2)) * 2 + 0.7).astype(np.float32), rng.random((h, w)) > 0.1)
             for _ in range(4)]
    coords = rng.random((9, 11, 2)) * [w + 10, h + 10] - 5
    for f in (flows[0][0], flows[0][1].astype(np.float64), rng.random((h, w, 3))):
        ref = _warp_reference(f, coords)
        got = warp_sample(f, coords)
        assert got.dtype == (np.float64 if f.dtype == np.float64 else np.float32)
        assert np.array_equal(got, ref[..., 0] if f.ndim == 2 else ref.astype(got.dtype))
    total, valid = flows[0][0].astype(np.float64), flows[0][1].copy()
    v, u = np.mgrid[0:h, 0:w]
    base = np.stack([u, v], -1).astype(np.float64)
    inside = lambda t: np.isfinite(t).all(-1) & (t[..., 0] >= 0) & (t[..., 0] <= w - 1) & (t[..., 1] >= 0) & (t[..., 1] <= h - 1)
    valid &= inside(base + total)
    for f, vm in flows[1:]:
        pos = base + total
        total = total + _warp_reference(f, pos)
        valid &= _warp_reference(vm.astype(np.float64), pos)[..., 0] > 0.999
        valid &= inside(base + total)
    got_f, got_v = chain_flows(flows)
    assert np.array_equal(got_f, total.astype(np.float32)) and np.array_equal(got_v, valid)


def test_the_initialisations_sampler_is_warp_sample_with_its_clamp():
    # stages.optimize.init.sample_np was a copy of warp_sample's arithmetic with its own clamp;
    # it now calls warp_sample and must give the copy's bits (results unchanged by the merge)
    from gcvd_flow.stages.optimize.init import sample_np

    def copy(img, uv):  # the former body
        h, w = img.shape
        u, v = np.clip(uv[:, 0], 0, w - 1.001), np.clip(uv[:, 1], 0, h - 1.001)
        u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
        fu, fv = u - u0, v - v0
        return (img[v0, u0] * (1 - fu) * (1 - fv) + img[v0, u0 + 1] * fu * (1 - fv)
                + img[v0 + 1, u0] * (1 - fu) * fv + img[v0 + 1, u0 + 1] * fu * fv)

    rng = np.random.default_rng(0)
    for dtype in (np.float32, np.float64):
        img = (rng.random((24, 32)) * 5).astype(dtype)
        uv = np.c_[rng.uniform(-2, 34, 4000), rng.uniform(-2, 26, 4000)]
        got, want = sample_np(img, uv), copy(img, uv)
        assert got.dtype == want.dtype and np.array_equal(got, want)


def test_fine_fast_preset_runs_fewer_iterations_at_the_accuracy_of_fine(orbit):
    """'fine-fast' = 'fine' (full-resolution finest level) with 12 gradient-descent iterations: a
    different flow (the setting reaches DIS), as close to the exact rigid flow as 'fine' on 4-frame
    pairs, and deterministic."""
    errs: dict[str, list[float]] = {"fine": [], "fine-fast": []}
    diffs = []
    for i in (2, 8):
        gt = rigid_flow(orbit.depth[i], orbit.K, orbit.poses[i], orbit.poses[i + 4])
        flows = {p: compute_pair_flow(orbit.frames[i], orbit.frames[i + 4], preset=p) for p in errs}
        m = flows["fine"]["fwd_valid"] & np.isfinite(gt).all(-1)
        for p, r in flows.items():
            errs[p].append(float(np.median(np.linalg.norm(r["fwd"] - gt, axis=-1)[m])))
        diffs.append(float(np.abs(flows["fine"]["fwd"] - flows["fine-fast"]["fwd"]).max()))
    assert min(diffs) > 1e-3  # the iteration count reached DIS: not the 'fine' flow
    assert np.mean(errs["fine-fast"]) < 1.25 * np.mean(errs["fine"]) + 0.02, errs
    again = compute_pair_flow(orbit.frames[2], orbit.frames[6], preset="fine-fast")
    first = compute_pair_flow(orbit.frames[2], orbit.frames[6], preset="fine-fast")
    assert again["fwd"].tobytes() == first["fwd"].tobytes()


def _homography_pair(shift_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A synthetic frame and the same frame seen through a homography (a rotation of the camera:
    about ``shift_px`` of image motion), with the exact flow a -> b (H, W, 2)."""
    import cv2

    a = render_clip(2, "loop", size=(256, 192), seed=0).frames[0]
    h, w = a.shape[:2]
    K = np.array([[200.0, 0, (w - 1) / 2], [0, 200.0, (h - 1) / 2], [0, 0, 1]])
    ang = np.arctan(shift_px / 200.0)
    R = cv2.Rodrigues(np.array([0.15 * ang, ang, 0.05]))[0]
    H = K @ R @ np.linalg.inv(K)
    b = cv2.warpPerspective(a, H, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    p = np.stack([u, v, np.ones_like(u)], -1) @ H.T
    return a, b, p[..., :2] / p[..., 2:] - np.stack([u, v], -1)


def test_fine_wide_recovers_a_motion_beyond_dis_reach_and_keeps_fine_where_it_holds():
    """A 45 px camera rotation: DIS from zero ("fine") loses most of the frame, "fine-wide" starts
    it from the homography of the pair's SIFT matches and finds the flow (the fallback is what
    makes the difference: without it the error stays). The pair asked the other way round gives
    the same flows swapped; a small motion gives exactly "fine"'s result."""
    a, b, gt = _homography_pair(45.0)
    inside = np.zeros(gt.shape[:2], bool)
    inside[30:-30, 30:-30] = True

    def epe(f):
        return float(np.median(np.linalg.norm(f - gt, axis=-1)[inside]))

    fine = compute_pair_flow(a, b, preset="fine")
    wide = compute_pair_flow(a, b, preset="fine-wide")
    assert epe(fine["fwd"]) > 5.0, epe(fine["fwd"])
    assert epe(wide["fwd"]) < 0.5, epe(wide["fwd"])
    assert wide["fwd_valid"].mean() > fine["fwd_valid"].mean() + 0.2
    back = compute_pair_flow(b, a, preset="fine-wide")
    assert np.array_equal(back["fwd"], wide["bwd"]) and np.array_equal(back["bwd_valid"], wide["fwd_valid"])
    a2, b2, _ = _homography_pair(2.0)
    small_fine, small_wide = compute_pair_flow(a2, b2, preset="fine"), compute_pair_flow(a2, b2, preset="fine-wide")
    assert all(np.array_equal(small_fine[k], small_wide[k]) for k in small_fine)


def test_chain_flows_channels_first_keeps_the_bits_of_the_pixel_layout():
    """chain_flows composes in a channels-first layout: the result is f0(p) + f1(p + f0(p)) with
    warp_sample's bilinear arithmetic, bit for bit, as composing in the (H, W, 2) layout does."""
    from gcvd_flow.stages.frontend.flow import _inside, chain_flows, pixel_grid, warp_sample

    rng = np.random.default_rng(5)
    h, w = 24, 32
    f0 = (rng.normal(size=(h, w, 2)) * 2).astype(np.float32)
    f1 = (rng.normal(size=(h, w, 2)) * 2).astype(np.float32)
    v0, v1 = rng.random((h, w)) > 0.1, rng.random((h, w)) > 0.1
    pos = pixel_grid(h, w) + f0.astype(np.float64)
    total = f0.astype(np.float64) + warp_sample(f1.astype(np.float64), pos)
    valid = v0 & _inside(pos, h, w) & (warp_sample(v1.astype(np.float64), pos) > 0.999)
    valid &= _inside(pixel_grid(h, w) + total, h, w)
    got, ok = chain_flows([(f0, v0), (f1, v1)])
    assert got.tobytes() == total.astype(np.float32).tobytes()
    assert np.array_equal(ok, valid)
