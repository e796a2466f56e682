"""Loop-candidate retrieval from the clip's own visual vocabulary (stages/graph/retrieval.py) and
the ground-truth revisit helper (gcvd_flow/evaluate/revisits.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import gcvd_flow.evaluate.synth as synth
from gcvd_flow.evaluate import revisits
from gcvd_flow.stages.graph import retrieval
from gcvd_flow.stages.graph.association import _sift_features, build_graph, candidate_pairs, global_descriptor, suppress_loops

SIZE = (160, 120)


def _revisit_poses(n: int = 48) -> np.ndarray:
    """Camera-to-world (n, 4, 4): leg 1 (frames 0-11) looks at the table from the left; leg 2
    (12-35) walks right while turning away to the right wall and back; leg 3 (36-47) sees the
    table again from the right, ~0.8 m to the side and 25-35 deg yawed (a revisit from another
    viewpoint: the whole-image descriptor, which keeps where structure is, misses it)."""
    P = np.empty((n, 4, 4))
    for i in range(n):
        if i < 12:
            eye, yaw = np.array([-0.45 + 0.15 * i / 11, -0.05, -1.7]), np.deg2rad(12 - 4 * i / 11)
        elif i < 36:
            u = (i - 12) / 23
            eye = np.array([-0.3 + 0.8 * u, -0.05, -1.7 - 0.1 * np.sin(np.pi * u)])
            yaw = np.deg2rad(8 + 70 * np.sin(np.pi * u) - 28 * u)
        else:
            u = (i - 36) / 11
            eye, yaw = np.array([0.5 + 0.1 * u, -0.05, -1.75]), np.deg2rad(-20 - 6 * u)
        P[i] = np.eye(4)
        P[i, :3, :3], P[i, :3, 3] = synth._yaw_pitch(yaw, 0.25), eye
    return P


@pytest.fixture(scope="module")
def revisit_clip():
    mp = pytest.MonkeyPatch()
    mp.setattr(synth, "make_trajectory", lambda kind, n: _revisit_poses(n))
    try:
        return synth.render_clip(48, "orbit", size=SIZE)
    finally:
        mp.undo()


def test_vocabulary_finds_a_revisit_from_another_viewpoint(revisit_clip) -> None:
    """The third leg sees the first leg's place 0.8 m aside and ~30 deg yawed: the vocabulary
    retrieval proposes those pairs (most of the ground-truth revisits among its candidates),
    verification accepts them and rejects what does not overlap; the whole-image descriptor
    proposes none of them (its best similarity for them, ~0.6-0.7, is below its threshold)."""
    c = revisit_clip
    kfs = list(range(0, 48, 2))
    imgs = [c.frames[i] for i in kfs]
    rev = revisits.revisit_pairs(kfs, c.poses, c.depth, c.K, min_frames=15, min_separation=8, min_overlap=0.3)
    assert len(rev) >= 40  # leg 1 x leg 3 (+ the end of leg 2)
    assert all(i <= 16 and j >= 30 for i, j in rev)

    feats = [_sift_features(im) for im in imgs]
    raw = [f[1] for f in feats]
    descs = [retrieval.vlad_descriptors(raw), retrieval.bow_descriptors(raw)]
    cands = retrieval.relative_candidates(descs, min_separation=8)[:40]
    found = {(kfs[a], kfs[b]) for a, b, _ in cands} & set(rev)
    assert len(found) >= 0.6 * min(len(rev), 40), (len(found), len(rev))
    old = np.stack([global_descriptor(im) for im in imgs])
    old_found = {(kfs[a], kfs[b]) for a, b, _ in candidate_pairs(old, min_separation=8, per_keyframe=1)} & set(rev)
    assert not old_found

    thr = 12.0
    graph, flows = build_graph(kfs, imgs, c.K, thr, max_candidates=40, loop_nms=0, retrieval="vocabulary")
    assert graph["retrieval"] == "vocabulary" and graph["candidates"] >= 20
    loops = [(e["i"], e["j"]) for e in graph["nonsequential_edges"]]
    closing = [p for p in loops if p in rev]
    assert len(closing) >= 10, graph["rejected"]
    assert all(p in flows for p in loops)
    # precision: every verified loop edge links views that share >= 10 % of their points
    for i, j in loops:
        o = min(revisits.view_overlap(c.depth[i], c.poses[i], c.poses[j], c.K, c.depth[j]),
                revisits.view_overlap(c.depth[j], c.poses[j], c.poses[i], c.K, c.depth[i]))
        assert o >= 0.1, (i, j, o)
    json.dumps(graph)
    # the default (loop_nms 8) keeps one loop edge per revisited stretch: the one with most inliers
    kept, suppressed = suppress_loops(graph["nonsequential_edges"], kfs, 8)
    assert 1 <= len(kept) <= 4 and any((e["i"], e["j"]) in rev for e in kept)
    assert len(kept) + len(suppressed) == len(loops)
    best = max(graph["nonsequential_edges"], key=lambda e: e["n_inliers"])
    assert best in kept
    old_graph, _ = build_graph(kfs, imgs, c.K, thr, retrieval="global", per_keyframe=1)
    assert not [(e["i"], e["j"]) for e in old_graph["nonsequential_edges"] if (e["i"], e["j"]) in rev]


def test_vocabulary_is_deterministic_and_learns_the_words() -> None:
    rng = np.random.default_rng(3)
    centres = rng.normal(size=(6, 128)) * 5
    x = np.concatenate([c + 0.1 * rng.normal(size=(200, 128)) for c in centres]).astype(np.float32)
    words = retrieval.build_vocabulary([x], words=6, iters=10, seed=0)
    # each true centre has a learned word within the noise
    d = np.sqrt(((centres[:, None, :] - words[None].astype(np.float64)) ** 2).sum(-1))
    assert d.min(1).max() < 0.5
    assert np.array_equal(words, retrieval.build_vocabulary([x], words=6, iters=10, seed=0))
    raw = [np.abs(rng.normal(size=(50, 128))).astype(np.float32) * 40 for _ in range(5)]
    v1, v2 = retrieval.vlad_descriptors(raw, words=8), retrieval.vlad_descriptors(raw, words=8)
    b1, b2 = retrieval.bow_descriptors(raw, branch=4), retrieval.bow_descriptors(raw, branch=4)
    assert v1.tobytes() == v2.tobytes() and b1.tobytes() == b2.tobytes()
    assert v1.shape == (5, 8 * 128) and b1.shape == (5, 16)
    np.testing.assert_allclose(np.linalg.norm(v1, axis=1), 1.0, atol=1e-5)
    # an image with no descriptors: zeros, no crash
    assert not retrieval.vlad_descriptors([*raw, None], words=8)[-1].any()


def test_sequence_scores_prefer_a_streak_over_a_spike() -> None:
    """A revisit lasting several keyframes (a diagonal streak, same or opposite direction)
    outranks an isolated look-alike of the same similarity."""
    n = 30
    s = np.full((n, n), 0.1)
    for d in range(-2, 3):
        s[5 + d, 20 + d] = s[20 + d, 5 + d] = 0.6  # same direction
        s[10 + d, 27 - d] = s[27 - d, 10 + d] = 0.6  # walked back the other way
    s[2, 14] = s[14, 2] = 0.6  # lone spike
    out = retrieval.sequence_scores(s, 1)
    assert out[5, 20] == pytest.approx(0.6) and out[10, 27] == pytest.approx(0.6)
    assert out[2, 14] < 0.3
    assert np.array_equal(retrieval.sequence_scores(s, 0), s)
    # departure: forward motion (similarity decaying with distance) never left; a revisit did
    idx = np.arange(n)
    decay = np.exp(-np.abs(idx[:, None] - idx[None, :]) / 5.0)
    assert (retrieval.departure(decay)[np.triu_indices(n, 2)] < 0).all()
    back = decay.copy()
    back[3, 25] = back[25, 3] = 0.8
    assert retrieval.departure(back)[3, 25] > 0.5
    desc = np.eye(n)  # no similarity at all: nothing passes the neighbour-relative threshold
    assert retrieval.relative_candidates(desc, min_separation=8) == []


def test_revisit_helper() -> None:
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    depth = np.full((48, 64), 2.0)
    T = np.eye(4)
    assert revisits.view_overlap(depth, T, T, K, depth, stride=4) == 1.0
    away = np.eye(4)
    away[:3, :3] = np.diag([-1.0, 1.0, -1.0])  # looking backwards
    assert revisits.view_overlap(depth, T, away, K, stride=4) == 0.0
    side = np.eye(4)
    side[0, 3] = 0.64  # half the 1.28 m wide view at 2 m: half the points
    assert revisits.view_overlap(depth, T, side, K, stride=4) == pytest.approx(0.5, abs=0.05)
    hidden = np.full((48, 64), 1.0)  # b sees a nearer surface everywhere: a's points are occluded
    assert revisits.view_overlap(depth, T, T, K, hidden, stride=4) == 0.0
    poses = np.stack([np.eye(4)] * 30)
    poses[10:20, 0, 3] = 3.0  # elsewhere in the middle
    kfs = list(range(0, 30, 2))
    pairs = revisits.pose_revisit_pairs(kfs, poses, min_frames=15, min_separation=3)
    assert pairs and all(j - i > 15 and not 10 <= i < 20 and not 10 <= j < 20 for i, j in pairs)
    dense = revisits.revisit_pairs(kfs, poses, [depth] * 30, K, min_frames=15, min_separation=3, stride=4)
    assert set(dense) == pairs
    rep = revisits.retrieval_report(pairs, [(0, 20), (0, 12)], [(0, 20), (0, 12)])
    assert rep["found"] == 1 and rep["precision"] == 0.5 and rep["false_verified"] == [[0, 12]]
