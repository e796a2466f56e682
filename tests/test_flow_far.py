"""flow_far: the direct flows priors and depth_fusion triangulate, computed once per pair.

priors (frame i vs i-8 and i-4, forward for the first frames) and depth_fusion (frame i vs i-8
and i+8) used to run DIS forward + backward on the same pairs each; now both read the items of
one map stage. These tests fail if a pair is computed twice, if a consumer reads the wrong
direction of a pair (results must equal computing the flow directly), or if changing one
consumer's pairs invalidates the other consumer.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from conftest import by_stage, cli, cli_json

from gcvd_flow import api, pipeline as gp
from gcvd_flow.stages.frontend import flow as flow_mod, priors as priors_mod

N = 24


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("clip") / "loop"
    cli("synth", str(out), "--frames", str(N), "--trajectory", "loop", "--size", "96x72", check=True)
    return out


def _pairs(n: int, **sections) -> list[tuple]:
    """flow_far's pairs; depth_fusion's fixed-offset references unless a test says otherwise
    (with the default references=baseline fusion's pairs are chosen from the poses, in
    fusion_flow: tests/test_fusion_references.py)."""
    sections["depth_fusion"] = {"references": "offsets", **sections.get("depth_fusion", {})}
    sections["priors"] = {"references": "back", **sections.get("priors", {})}  # unless a test says otherwise
    cfg = gp.GCVDConfig(**sections)
    return gp._far_pairs(n, type("B", (), {"priors": cfg.priors, "depth_fusion": cfg.depth_fusion}))


def test_graph_priors_and_fusion_read_flow_far():
    names = gp.PIPELINE.names()
    assert names.index("flow_far") < names.index("priors_direct") < names.index("priors")
    assert "flow_far" in gp.PIPELINE.get("priors_direct").deps and "priors_direct" in gp.PIPELINE.get("priors").deps
    assert "flow_far" in gp.PIPELINE.get("depth_fusion").deps


def test_pairs_are_the_union_of_both_consumers():
    two = {"offsets": (-8, 8), "references": "offsets"}  # fusion's references until 2026-11-25
    pairs = _pairs(N, depth_fusion=two)
    assert len(pairs) == len(set(pairs)) and all(a < b for a, b, _, _ in pairs)
    spans = Counter(b - a for a, b, _, _ in pairs)
    # i-8 / i+8 of fusion and the span-8 prior share one set of pairs; the span-4 prior its own
    assert spans == {8: N - 8, 4: N - 4}
    # a consumer of each kind asks for 2 flows per frame: 4 per frame before, ~2 per frame now
    asked = sum(len(gp._prior_refs(i, N, gp.PriorsParams(references="back"))) + len(gp._fusion_refs(i, N, gp.DepthFusionParams(**two)))
                for i in range(N))
    assert asked == 2 * N + 2 * (N - 8) and len(pairs) == 2 * N - 12
    # the default references (+-1, 2, 4, 8): +-8 and +-4 shared with the priors, +-1 the flow
    # stage's own pairs; only the +-2 pairs are new
    assert Counter(b - a for a, b, _, _ in _pairs(N)) == {8: N - 8, 4: N - 4, 2: N - 2}
    # references=baseline (the default): flow_far holds the priors' pairs only
    assert _pairs(N, depth_fusion={"references": "baseline"}) == _pairs(N, depth_fusion={"enabled": False})
    pairs = _pairs(N, depth_fusion=two)
    # sections disagreeing on the DIS settings get separate pairs, nothing shared by mistake
    apart = _pairs(N, depth_fusion={"preset": "medium", **two})
    assert len(apart) == len(pairs) + (N - 8)
    assert _pairs(N, priors={"backend": "midas", "weights": __file__}, depth_fusion={"enabled": False}) == []


def test_a_reversed_pair_is_the_direct_flow_of_the_other_frame():
    from gcvd_flow.evaluate.synth import render_clip

    c = render_clip(9, "loop", size=(96, 72), seed=1)
    item = flow_mod.compute_pair_flow(c.frames[0], c.frames[8], preset="fine")
    for direction, (a, b) in (("fwd", (0, 8)), ("bwd", (8, 0))):
        direct = flow_mod.compute_pair_flow(c.frames[a], c.frames[b], preset="fine")
        f, v = gp._far_flow(item, direction)
        assert np.array_equal(f, direct["fwd"]) and np.array_equal(v, direct["fwd_valid"])


def _run(clip: Path, tmp: Path, *sets: str, until: str = "priors") -> dict:
    # the back-looking prior references (span, span / 2) unless a test sets them
    back = () if any(s.startswith("priors.references=") for s in sets) else ("priors.references=back",)
    args = [a for s in ("depth_fusion.references=offsets", *back, *sets) for a in ("--set", s)]
    return by_stage(cli_json("run", str(clip), "--out", str(tmp / "run"), "--cache", str(tmp / "cache"),
                             "--until", until, *args))


def test_each_pair_once_and_offsets_do_not_invalidate_priors(clip, tmp_path):
    first = _run(clip, tmp_path)
    assert first["flow_far"]["executed"] == len(_pairs(N)) and first["priors"]["executed"] == N
    # the items equal the flows computed directly, and the priors equal the prior computed
    # from direct flows (what the stage did before it read flow_far)
    far = api.recorded_output(tmp_path / "run", "flow_far", str(tmp_path / "cache"))
    frames = api.recorded_output(tmp_path / "run", "ingest", str(tmp_path / "cache"))
    pri = api.recorded_output(tmp_path / "run", "priors", str(tmp_path / "cache"))
    pairs = [tuple(p) for p in far.summary["pairs"]]
    assert pairs == _pairs(N)
    for k in (0, len(pairs) - 1):
        a, b, preset, fb = pairs[k]
        direct = flow_mod.compute_pair_flow(frames[a]["image"], frames[b]["image"], preset=preset, fb_thresh=fb)
        assert all(np.array_equal(far[k][n], direct[n]) for n in ("fwd", "bwd", "fwd_valid", "bwd_valid"))
    K = np.asarray(frames.summary["K"])
    for i in (2, N - 1):  # a frame looking forward, one looking back
        fl = [flow_mod.compute_pair_flow(frames[i]["image"], frames[j]["image"], preset="fine")
              for j in gp._prior_refs(i, N, gp.PriorsParams(references="back"))]
        fl = [(f["fwd"], f["fwd_valid"]) for f in fl if f["fwd_valid"].mean() >= priors_mod.MIN_VALID_FRACTION]
        ref = priors_mod.geometric_prior(frames[i]["image"], K, fl[:1], extra=fl[1:])
        assert np.array_equal(pri[i]["inv_depth"], ref["inv_depth"].astype(np.float32))
    # a further fusion reference computes only its new pairs; the priors stay cached
    more = _run(clip, tmp_path, "depth_fusion.offsets=[-8, 8, 12]")
    assert more["flow_far"]["executed"] == N - 12
    assert more["flow_far"]["cached"] == len(_pairs(N, depth_fusion={"offsets": (-8, 8)}))
    assert more["priors"]["executed"] == 0 and more["priors"]["cached"] == N
    # fusion at +-4 needs no new flow: the span-4 prior computed those pairs already
    near = _run(clip, tmp_path, "depth_fusion.offsets=[-8, -4, 4, 8]")
    assert near["flow_far"]["executed"] == 0 and near["priors"]["executed"] == 0
    # fusion at +-1 reads the flow stage's adjacent pairs: no flow_far item either
    adj = _run(clip, tmp_path, "depth_fusion.offsets=[-8, -1, 1, 8]")
    assert adj["flow_far"]["executed"] == 0
    assert all(abs(a - b) != 1 for a, b, *_ in gp._far_pairs(N, type("B", (), {
        "priors": gp.PriorsParams(references="back"),
        "depth_fusion": gp.DepthFusionParams(offsets=(-8, -1, 1, 8), references="offsets")})))


def test_a_full_run_computes_each_pair_once(clip, tmp_path, monkeypatch):
    """In process (--jobs 1): every DIS pair flow of the run is counted by its images."""
    calls: Counter = Counter()
    real = flow_mod.compute_pair_flow

    def counting(img_a, img_b, *a, **kw):
        calls[(img_a.tobytes(), img_b.tobytes())] += 1
        return real(img_a, img_b, *a, **kw)

    monkeypatch.setattr(flow_mod, "compute_pair_flow", counting)
    quick = ["optimize_keyframes.steps=10", "optimize_edges.steps=5", "optimize_segments.steps=5",
             "priors.references=back"]
    res = api.run(api.Invocation(input=str(clip), out=str(tmp_path / "run"), cache=str(tmp_path / "cache"),
                                 sets=quick, json_mode=True), log=lambda m: None)
    st = {s["name"]: s for s in res["stages"]}
    # references=baseline (the default): flow_far the priors' pairs, fusion_flow the new ones
    far = _pairs(N, depth_fusion={"references": "baseline"})
    new = api.recorded_output(tmp_path / "run", "fusion_references", str(tmp_path / "cache"))[0]["flows"]
    assert st["depth_fusion"]["executed"] == N and st["flow_far"]["executed"] == len(far)
    assert st["fusion_flow"]["executed"] == len(new) and not {(a, b) for a, b, *_ in far} & {tuple(p) for p in new}
    # adjacent pairs (flow) + far pairs (flow_far) + fusion's own (fusion_flow), each once, none
    # also in reverse
    assert sum(calls.values()) == (N - 1) + len(far) + len(new)
    # (the loop clip's last frame repeats its first: a pair through it may equal another reversed)
    frames = api.recorded_output(tmp_path / "run", "ingest", str(tmp_path / "cache"))
    seen = Counter(frames[i]["image"].tobytes() for i in range(N))
    dup = {img for img, k in seen.items() if k > 1}
    assert max(calls.values()) == 1
    assert not any((b, a) in calls for a, b in calls if a not in dup and b not in dup)


def test_symmetric_prior_references_share_each_pair(clip, tmp_path):
    """priors.references=symmetric: frame i reads i - span and i + span, so the pair (i, i + span)
    is read by both frames it joins (frame i forward, frame i + span backward) and computed
    once; the priors equal those triangulated from flows computed directly."""
    sym = {"references": "symmetric"}
    pairs = _pairs(N, priors=sym, depth_fusion={"references": "baseline"})
    readers: Counter = Counter()
    for i in range(N):
        for j in gp._prior_refs(i, N, gp.PriorsParams(**sym)):
            readers[(min(i, j), max(i, j))] += 1
    assert set(readers) == {(a, b) for a, b, _, _ in pairs}
    assert all(readers[(i, i + 8)] == 2 for i in range(N - 8))  # each span pair: two consumers
    assert len(pairs) < len(_pairs(N, depth_fusion={"references": "baseline"}))
    n = 211  # ICL: 215 pairs instead of 410
    # about n - span + 2 span (the ends); 410 with references=back
    assert len(_pairs(n, priors=sym, depth_fusion={"references": "baseline"})) <= n + 8
    run = _run(clip, tmp_path, "priors.references=symmetric", "depth_fusion.references=baseline")
    assert run["flow_far"]["executed"] == len(pairs) and run["priors"]["executed"] == N
    frames = api.recorded_output(tmp_path / "run", "ingest", str(tmp_path / "cache"))
    pri = api.recorded_output(tmp_path / "run", "priors", str(tmp_path / "cache"))
    K = np.asarray(frames.summary["K"])
    for i in (3, 12, N - 1):  # forward only, both ways, backward only
        fl = [flow_mod.compute_pair_flow(frames[i]["image"], frames[j]["image"], preset="fine")
              for j in gp._prior_refs(i, N, gp.PriorsParams(**sym))]
        fl = [(f["fwd"], f["fwd_valid"]) for f in fl if f["fwd_valid"].mean() >= priors_mod.MIN_VALID_FRACTION]
        ref = priors_mod.geometric_prior(frames[i]["image"], K, fl[:1], extra=fl[1:])
        assert np.array_equal(pri[i]["inv_depth"], ref["inv_depth"].astype(np.float32))
