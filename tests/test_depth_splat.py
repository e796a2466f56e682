"""Forward-splatting consensus (stages.depth.consensus.splat_consensus, depth_consensus.splat_offsets):
a region whose depth is far off (beyond the carry's occlusion test) takes the depth confident
views see there, the correction spreads to what no view covers, and occluded points do not
count."""

from __future__ import annotations

import numpy as np
from test_depth_consensus import REGION, H, K, W, _log_err, _plane, _pose, _refs

from gcvd_flow.stages.depth.consensus import consensus_depth, splat_consensus, splat_points


def _far_off_frame(factor: float = 1.4) -> tuple[np.ndarray, np.ndarray]:
    """Frame i: the plane, its REGION 40 % too far and unconfident (a texture-less wall)."""
    depth = _plane(0.0)
    depth[REGION] *= factor
    conf = np.full((H, W), 0.9, np.float32)
    conf[REGION] = 0.0
    return depth, conf


def _wall_guide() -> np.ndarray:
    """The grey image: the wrong region is a darker wall (its edges bound the spread)."""
    g = np.full((H, W), 0.7)
    g[REGION] = 0.3
    return g


def test_splatted_points_land_where_the_poses_say():
    T_i_j = np.linalg.inv(_pose(0.0)) @ _pose(0.1)
    idx, z, w = splat_points(K, (H, W), T_i_j, _plane(0.1), np.ones((H, W)))
    est = np.full(H * W, np.nan)
    est[idx] = z  # any of a pixel's landings: on one plane they agree to the footprint's px
    ok = np.isfinite(est).reshape(H, W)
    assert ok.mean() > 0.8 and not ok[:, :2].any()  # frame j is right of i: i's left edge unseen
    np.testing.assert_allclose(est.reshape(H, W)[ok], _plane(0.0)[ok], rtol=0.02)
    assert np.all(w == 1)


def test_a_far_off_region_takes_the_depth_confident_views_see():
    """40 % off is beyond the carry's max_log_dev (0.2): consensus_depth leaves the region wrong,
    the splat corrects it to a few %."""
    depth, conf = _far_off_frame()
    refs = _refs([-0.1, 0.1])
    mask = np.zeros((H, W), bool)
    mask[REGION] = True
    before = _log_err(depth, mask)
    carried = consensus_depth(depth, conf, _pose(0.0), refs, K)
    assert _log_err(carried, mask) > 0.9 * before  # the carry rejects it as another surface
    out = splat_consensus(depth, conf, _pose(0.0), refs, K)
    assert _log_err(out, mask) < 0.05 * before
    assert _log_err(out, ~mask) < 0.01  # the confident rest stays put


def test_the_correction_spreads_to_pixels_no_view_covers():
    """The reference is sure of only the left part of the wrong region; with the image as a guide
    the rest of that wall (uncovered, unconfident) gets the same correction; without one it keeps
    its error."""
    depth, conf = _far_off_frame()
    ref_depth, ref_conf, ref_pose = _refs([0.0])[0]
    ref_conf = ref_conf.copy()
    ref_conf[:, 60:] = 0.0  # the reference is sure of its left part only
    half = np.zeros((H, W), bool)
    half[REGION[0], 64:80] = True  # frame i's pixels only the unconfident part of the reference sees
    no_guide = splat_consensus(depth, conf, _pose(0.0), [(ref_depth, ref_conf, ref_pose)], K)
    guided = splat_consensus(depth, conf, _pose(0.0), [(ref_depth, ref_conf, ref_pose)], K, guide=_wall_guide())
    before = _log_err(depth, half)
    assert _log_err(no_guide, half) > 0.9 * before
    assert _log_err(guided, half) < 0.75 * before  # (the far side of the wall also borders the
    # confident, uncorrected plane: the guided fill mixes some of that in)
    assert _log_err(guided, ~np.pad(np.ones((30, 40), bool), ((30, 36), (40, 48)))) < 0.01


def test_occluded_points_do_not_count():
    """Two references: one sees the plane, one (wrongly confident) a surface twice as far at the
    same pixels; the z-buffer keeps the nearer (the visible surface), the far one is not averaged in."""
    depth, conf = _far_off_frame()
    near = _refs([0.0])[0]
    far = (near[0] * 2.0, near[1], near[2])
    mask = np.zeros((H, W), bool)
    mask[REGION] = True
    out = splat_consensus(depth, conf, _pose(0.0), [near, far], K)
    assert _log_err(out, mask) < 0.01


def test_moving_and_invalid_pixels():
    depth, conf = _far_off_frame()
    depth[0:5, 0:5] = 0.0
    refs = _refs([0.1])
    static = np.ones((H, W), np.uint8)
    static[REGION] = 0  # frame i's region is a moving object: it keeps its depth
    out = splat_consensus(depth, conf, _pose(0.0), refs, K, static=static)
    np.testing.assert_array_equal(out[REGION], depth[REGION])
    assert (out[0:5, 0:5] == 0).all()
    still = splat_consensus(depth, conf, _pose(0.0), refs, K, ref_static=[np.zeros((H, W), np.uint8)])
    np.testing.assert_array_equal(still, depth)  # nothing static in the reference: nothing splatted
    np.testing.assert_array_equal(splat_consensus(depth, conf, _pose(0.0), [], K), depth)


def _stage_inputs(depth: np.ndarray, conf: np.ndarray, splat: bool) -> dict:
    """depth_consensus's item for frame 0 of a 2-frame clip (frame 1 the plane seen from x = 0.1)."""
    ref_depth, ref_conf, ref_pose = _refs([0.1])[0]
    static = [{"static": np.ones((H, W), np.uint8)} for _ in range(2)]
    inputs = {"index": 0, "K": K, "poses": np.stack([_pose(0.0), ref_pose]),
              "depth": {"depth": depth, "confidence": conf},
              "refs": [{"depth": ref_depth, "confidence": ref_conf}], "ref_indices": [1], "static": static}
    if splat:
        img = np.repeat((_wall_guide() * 255).astype(np.uint8)[..., None], 3, axis=2)
        inputs.update(splat_indices=[1], image={"image": img})
    return inputs


def test_the_stage_splats_only_with_splat_offsets():
    """pipeline.run_depth_consensus: the item of depth_consensus.splat_offsets=[1] corrects the
    far-off region; an item without splat_indices (splat_offsets=()) leaves it; the confidence is
    passed through either way."""
    from gcvd_flow.pipeline import DepthConsensusParams, run_depth_consensus

    depth, conf = _far_off_frame()
    mask = np.zeros((H, W), bool)
    mask[REGION] = True
    before = _log_err(depth, mask)
    off = run_depth_consensus(_stage_inputs(depth, conf, False), DepthConsensusParams(offsets=(1,)), None)
    on = run_depth_consensus(_stage_inputs(depth, conf, True), DepthConsensusParams(offsets=(8,), splat_offsets=(1,), splat_keep_edges=0.0,
                                                                            smooth_lambda=0.0),
                             None)
    assert _log_err(off["depth"], mask) > 0.9 * before
    assert _log_err(on["depth"], mask) < 0.05 * before
    np.testing.assert_array_equal(on["confidence"], conf)


def test_confident_pixels_keep_their_depth_the_unconfident_take_the_splat():
    """Ten references each 3 % too far (their own small errors): with keep_confidence the frame's
    confident pixels keep their exact depth (without it they are outvoted and move), the
    unconfident region is still corrected, and a pixel at half the keep confidence takes 3/4 of
    the correction ((c / keep)^2 of its own depth)."""
    depth, conf = _far_off_frame()
    conf[5:10, 5:120] = 0.25
    refs = [(d * 1.03, c, p) for d, c, p in _refs([-0.05, -0.04, -0.03, -0.02, -0.01, 0.01, 0.02, 0.03, 0.04, 0.05])]
    mask = np.zeros((H, W), bool)
    mask[REGION] = True
    sure = conf >= 0.5
    free = splat_consensus(depth, conf, _pose(0.0), refs, K)
    kept = splat_consensus(depth, conf, _pose(0.0), refs, K, keep_confidence=0.5)
    assert _log_err(free, sure) > 0.02  # outvoted: the references' 3 %
    np.testing.assert_array_equal(kept[sure], depth[sure])
    assert _log_err(kept, mask) < 0.1 * _log_err(depth, mask)
    half = np.log(kept[5:10, 20:100] / depth[5:10, 20:100])
    np.testing.assert_allclose(half, 0.75 * np.log(1.03), atol=0.004)


def _step_frame() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A box 1.5 m in front of the plane (cols 60+ of frame i, and where the references see it),
    all of frame i unconfident, 8 % too far; the references confident and right."""
    truth = _plane(0.0)
    truth[:, 60:] = 1.5
    conf = np.zeros((H, W), np.float32)
    return truth, truth * 1.08, conf


def test_pixels_at_a_depth_edge_of_the_frame_keep_their_depth():
    """keep_edges: pixels within 2 px of a jump of the frame's own log depth keep their depth (the
    2x2 footprint puts the box's points over the plane there); elsewhere the splat corrects."""
    truth, depth, conf = _step_frame()
    ref = (truth, np.full((H, W), 0.9, np.float32), _pose(0.0))
    out = splat_consensus(depth, conf, _pose(0.0), [ref], K, keep_edges=0.05)
    edge = np.zeros((H, W), bool)
    edge[:, 58:62] = True
    np.testing.assert_array_equal(out[edge], depth[edge])
    np.testing.assert_allclose(out[:, 10:50], truth[:, 10:50], rtol=3e-3)
    np.testing.assert_allclose(out[:, 70:120], truth[:, 70:120], rtol=3e-3)
    free = splat_consensus(depth, conf, _pose(0.0), [ref], K)
    assert not np.array_equal(free[edge], depth[edge])


def test_confidence_drops_at_depth_edges_only():
    """edge_confidence: within 2 px of a 10 % jump of the depth (the box in front of the plane) or
    of an invalid pixel the confidence falls below 0.5; a smoothly tilted plane keeps all of its."""
    from gcvd_flow.stages.depth.consensus import edge_confidence

    truth, _, _ = _step_frame()
    truth[90:, :10] = 0.0
    conf = np.full((H, W), 0.9, np.float32)
    conf[0, 0] = 1.0
    out = edge_confidence(truth, conf, 0.1)
    assert (out[:, 58:62] < 0.5).all() and (out[:88, 8:12] < 0.5).sum() == 0
    assert (out[88:90, :12] < 0.5).all() and (out[90:, 10:12] < 0.5).all()  # next to the invalid corner
    np.testing.assert_array_equal(out[:80, 12:56], conf[:80, 12:56])
    np.testing.assert_array_equal(out[:, 64:], conf[:, 64:])
    assert out[0, 0] == 1.0
    np.testing.assert_array_equal(edge_confidence(_plane(0.0), conf, 0.1), conf)
    one = np.ones((H, W), np.float32)
    assert edge_confidence(truth, one, 0.1)[:, 59].max() < 0.5  # even confidence 1 is unconfident there


def test_the_stage_lowers_the_confidence_at_its_output_depth_edges():
    """pipeline.run_depth_consensus with edge_jump (default 0.1): the box's boundary is unconfident
    in the output; edge_jump=0 passes the confidence through."""
    from gcvd_flow.pipeline import DepthConsensusParams, run_depth_consensus

    truth, _, _ = _step_frame()
    conf = np.full((H, W), 0.9, np.float32)
    inputs = _stage_inputs(truth, conf, False)
    on = run_depth_consensus(inputs, DepthConsensusParams(offsets=(1,)), None)
    off = run_depth_consensus(inputs, DepthConsensusParams(offsets=(1,), edge_jump=0.0), None)
    assert (on["confidence"][:, 58:62] < 0.5).all()
    np.testing.assert_array_equal(on["confidence"][:, 64:], conf[:, 64:])
    np.testing.assert_array_equal(off["confidence"], conf)


def test_references_pixels_at_their_depth_edges_are_not_splatted():
    """ref_edge_jump: the reference's confident pixels straddling the box's boundary carry a mix of
    the two depths (as a flow patch or a 3x3 median leaves them); splatted, they put that mix into
    frame i; left out (within 2 px of a > 10 % jump of the reference's own depth), frame i keeps its
    depth there and the rest is corrected as before."""
    truth, depth, conf = _step_frame()
    ref_depth = truth.copy()
    ref_depth[:, 59:61] = np.sqrt(truth[:, 50:51] * 1.5)  # the boundary's mixed depth
    ref = (ref_depth, np.full((H, W), 0.9, np.float32), _pose(0.0))
    free = splat_consensus(depth, conf, _pose(0.0), [ref], K)
    clean = splat_consensus(depth, conf, _pose(0.0), [ref], K, ref_edge_jump=0.1)
    mixed = np.zeros((H, W), bool)
    mixed[:, 59:61] = True
    assert np.abs(np.log(free[mixed] / truth[mixed])).mean() > 0.1  # the mix splatted in
    np.testing.assert_array_equal(clean[mixed], depth[mixed])  # nothing lands there: its own depth
    np.testing.assert_allclose(clean[:, 10:50], truth[:, 10:50], rtol=3e-3)
    np.testing.assert_allclose(clean[:, 70:120], truth[:, 70:120], rtol=3e-3)


def test_kept_pixels_take_no_landings_and_the_output_is_the_same_bits(monkeypatch):
    """The pixels that keep their own depth (confident) are left out of the splat's work: the
    output is bit-identical to splatting every landing, and the points splatted are fewer."""
    import gcvd_flow.stages.depth.consensus as consensus

    depth, conf = _far_off_frame()
    rng = np.random.default_rng(3)
    conf = np.where(rng.random((H, W)) < 0.3, rng.random((H, W)) * 0.6, conf).astype(np.float32)
    depth = (depth * (1 + 0.05 * rng.standard_normal((H, W)))).astype(np.float32)
    refs = _refs([-0.2, -0.1, 0.1, 0.2])
    args = dict(guide=_wall_guide(), keep_confidence=0.5, ref_edge_jump=0.1)
    landed = []
    real = consensus.project_source

    def counting(*a, **k):
        out = real(*a, **k)
        landed.append(len(out[0]))
        return out

    monkeypatch.setattr(consensus, "project_source", counting)
    fast = splat_consensus(depth, conf, _pose(0.0), refs, K, **args)
    n_fast = sum(landed)
    monkeypatch.setattr(consensus, "_splat_targets", lambda *a, **k: None)
    landed.clear()
    full = splat_consensus(depth, conf, _pose(0.0), refs, K, **args)
    assert fast.tobytes() == full.tobytes()
    assert n_fast < 0.6 * sum(landed)
    assert np.abs(np.log(fast[REGION]) - np.log(depth[REGION])).mean() > 0.05  # the splat did change the region


def _noisy_clip(n: int = 6) -> tuple[list, list]:
    """n frames along x of the plane with the far-off region, noisy depth and mixed confidence:
    (depth, confidence) per frame and the refs tuples (depth, confidence, pose)."""
    rng = np.random.default_rng(5)
    frames, refs = [], []
    for k in range(n):
        depth, conf = _far_off_frame() if k == 0 else (_plane(0.05 * k), np.full((H, W), 0.9, np.float32))
        conf = np.where(rng.random((H, W)) < 0.3, rng.random((H, W)), conf).astype(np.float32)
        depth = (depth * (1 + 0.03 * rng.standard_normal((H, W)))).astype(np.float32)
        frames.append((depth, conf))
        refs.append((depth, conf, _pose(0.05 * k)))
    return frames, refs


def test_reference_sources_computed_once_serve_every_target_with_the_same_bits():
    """A reference's splat source (its edge-lowered confident static pixels, back-projected) does
    not depend on the target: sources computed once through a SourceCache and reused for every
    target give the same bits as splat_consensus computing its own, and the cache serves repeats."""
    from gcvd_flow.stages.depth.consensus import SourceCache, reference_sources

    frames, refs = _noisy_clip()
    static = [np.ones((H, W), np.uint8) for _ in refs]
    static[2][:10] = 0
    args = dict(guide=_wall_guide(), keep_confidence=0.5, ref_edge_jump=0.1, min_confidence=0.5)
    cache = SourceCache()
    for i in (0, 3, 5):
        sel = [j for j in range(len(refs)) if j != i]
        own = splat_consensus(*frames[i], refs[i][2], [refs[j] for j in sel], K, ref_static=[static[j] for j in sel], **args)
        src = reference_sources([refs[j] for j in sel], [static[j] for j in sel], K, 0.5, 0.1, cache=cache)
        shared = splat_consensus(*frames[i], refs[i][2], [refs[j] for j in sel], K, ref_static=[static[j] for j in sel],
                                 sources=src, **args)
        assert shared.tobytes() == own.tobytes()
        assert not np.array_equal(own, frames[i][0])  # the splat did change the frame
    assert cache.hits == 3 * 5 - len(refs)  # 15 requests, each of the 6 references computed once


def test_the_source_cache_keys_on_content_not_on_the_frame():
    """A reference whose depth, confidence, static mask or splat settings differ is a new source:
    a cache keyed by anything less would splat a stale reference."""
    from gcvd_flow.stages.depth.consensus import SourceCache, reference_sources

    _, refs = _noisy_clip(2)
    cache = SourceCache()
    first = reference_sources(refs[1:], None, K, 0.5, 0.1, cache=cache)[0]
    moved = (refs[1][0] * np.float32(1.1), refs[1][1], refs[1][2])
    again = reference_sources([moved], None, K, 0.5, 0.1, cache=cache)[0]
    assert cache.hits == 0 and first is not None and again is not None
    np.testing.assert_allclose(again.X, first.X * 1.1, rtol=1e-6)
    mask = np.ones((H, W), np.uint8)
    mask[:20] = 0
    for variant in (reference_sources(refs[1:], [mask], K, 0.5, 0.1, cache=cache)[0],
                    reference_sources(refs[1:], None, K, 0.7, 0.1, cache=cache)[0],
                    reference_sources(refs[1:], None, K, 0.5, None, cache=cache)[0]):
        assert cache.hits == 0 and variant is not None and len(variant.weight) != len(first.weight)
    assert reference_sources(refs[1:], None, K, 0.5, 0.1, cache=cache)[0] is first and cache.hits == 1
    small = SourceCache(capacity=1)
    reference_sources(refs, None, K, 0.5, 0.1, cache=small)
    reference_sources(refs[:1], None, K, 0.5, 0.1, cache=small)
    assert small.hits == 0  # evicted: at most ``capacity`` sources are held


def test_the_stage_reuses_sources_across_items_with_the_same_bits():
    """pipeline.run_depth_consensus with its splat_sources resource (one SourceCache per worker):
    the same bits as without it, and a second item reading the same reference hits the cache."""
    from gcvd_flow.pipeline import DepthConsensusParams, run_depth_consensus
    from gcvd_flow.stages.depth.consensus import SourceCache

    class Ctx:
        def __init__(self) -> None:
            self.cache = SourceCache()

        def resource(self, name: str) -> SourceCache:
            assert name == "splat_sources"
            return self.cache

    depth, conf = _far_off_frame()
    p = DepthConsensusParams(offsets=(8,), splat_offsets=(1,))
    ctx = Ctx()
    plain = run_depth_consensus(_stage_inputs(depth, conf, True), p, None)
    for hits in (0, 1):
        shared = run_depth_consensus(_stage_inputs(depth, conf, True), p, ctx)
        assert shared["depth"].tobytes() == plain["depth"].tobytes() and ctx.cache.hits == hits


def test_the_stage_names_sources_by_their_input_digests_and_hashes_no_array(monkeypatch):
    """With the digests of its inputs (the engine's ctx.input_digest), run_depth_consensus names a
    splat reference's source by the digests of its depth_filter and masks items: the items that
    read one reference compute its source once and hash none of its arrays; a reference whose
    depth or mask item differs is a new source; the bits are those without the cache."""
    import gcvd_flow.stages.depth.consensus as consensus
    from gcvd_flow.pipeline import DepthConsensusParams, run_depth_consensus
    from gcvd_flow.stages.depth.consensus import SourceCache

    class Ctx:
        def __init__(self, digests: dict) -> None:
            self.cache, self.digests = SourceCache(), digests

        def resource(self, name: str) -> SourceCache:
            return self.cache

        def input_digest(self, name: str) -> list[str]:
            return self.digests[name]

    computed = []
    real = consensus.splat_source
    monkeypatch.setattr(consensus, "splat_source", lambda *a: computed.append(1) or real(*a))
    depth, conf = _far_off_frame()
    p = DepthConsensusParams(offsets=(8,), splat_offsets=(1,))
    plain = run_depth_consensus(_stage_inputs(depth, conf, True), p, None)
    assert len(computed) == 1
    ctx = Ctx({"refs": ["filter-1"], "static": ["masks-0", "masks-1"]})
    for _ in range(3):  # three items reading frame 1
        shared = run_depth_consensus(_stage_inputs(depth, conf, True), p, ctx)
        assert shared["depth"].tobytes() == plain["depth"].tobytes()
    assert len(computed) == 2 and ctx.cache.hits == 2 and ctx.cache.hashed == 0
    for digests in ({"refs": ["filter-1b"], "static": ["masks-0", "masks-1"]},
                    {"refs": ["filter-1"], "static": ["masks-0", "masks-1b"]}):
        ctx.digests = digests
        run_depth_consensus(_stage_inputs(depth, conf, True), p, ctx)
    assert len(computed) == 4 and ctx.cache.hashed == 0
