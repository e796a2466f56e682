"""depth_fusion's references chosen from the final poses (depth_fusion.references=baseline, issue 28).

Fixed index offsets give tiny baselines where the camera pauses or crawls and views that no
longer overlap where it moves fast; the default chooses each frame's references by median
triangulation angle and overlap (stages.graph.references.baseline_references), preferring pairs
whose flow exists, and computes the few new pairs in the fusion_flow stage. These tests fail if
the choice falls back to offsets, if references outside the usable range are taken, if the new
flows are not bounded or shared, or if the pipeline reads a reference's flow from the wrong item.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import by_stage, cli, cli_json

from gcvd_flow import api, pipeline as gp
from gcvd_flow.stages.depth import fusion
from gcvd_flow.stages.depth.params import FusionReferencesSettings
from gcvd_flow.stages.frontend import flow as flow_mod
from gcvd_flow.stages.graph import references as R

K = np.array([[100.0, 0, 63.5], [0, 100.0, 47.5], [0, 0, 1]])
SIZE = (128, 96)


def _poses(xs: np.ndarray) -> np.ndarray:
    """Cameras looking down +z, moved along x by xs (metres)."""
    P = np.tile(np.eye(4), (len(xs), 1, 1))
    P[:, 0, 3] = xs
    return P


def _samples(n: int, depth: float = 2.0) -> list[np.ndarray]:
    return [R.view_samples(np.full((96, 128), depth), K) for _ in range(n)]


def _geometry(poses, i, j):
    ov, ang = R.view_geometry(poses, _samples(len(poses)), K, SIZE, i, [j])
    return ov[0], ang[0]


def test_view_geometry_angle_and_overlap():
    poses = _poses(np.array([0.0, 0.1, 3.0]))
    ov, ang = _geometry(poses, 0, 1)
    # a 0.1 m baseline at 2 m: about 2.9 deg at the centre, a little less off-axis
    assert ov > 0.9 and 2.0 < ang < 2.9
    ov_far, _ = _geometry(poses, 0, 2)  # 3 m to the side at 2 m depth (the view is 2.6 m wide): no overlap
    assert ov_far == 0.0
    assert _geometry(_poses(np.zeros(2)), 0, 1)[1] == 0.0  # no baseline, no angle


def test_a_pause_gets_references_outside_it_not_fixed_offsets():
    # 10 frames moving 2 cm each, a 20-frame pause, then 10 frames moving again
    xs = np.concatenate([np.arange(10) * 0.02, np.full(20, 0.18), 0.18 + np.arange(1, 11) * 0.02])
    poses = _poses(xs)
    rule = FusionReferencesSettings(max_new_flows=2)
    refs, new = R.baseline_references(poses, _samples(len(xs)), K, SIZE, rule)
    for i, js in enumerate(refs):
        assert 0 < len(js) <= rule.max_refs, (i, js)
        for j in js:
            ov, ang = _geometry(poses, i, j)
            assert ov >= rule.min_overlap and rule.min_angle_deg <= ang <= rule.max_angle_deg, (i, j, ov, ang)
    # inside the pause, every frame 1..8 apart has no baseline: the references lie outside it
    mid = 20
    assert all(xs[j] != xs[mid] for j in refs[mid]) and all(abs(j - mid) > 8 for j in refs[mid])
    assert refs[mid] != R.offset_references(mid, len(xs), gp.DepthFusionParams().offsets)
    # spread on both sides when both sides move
    assert min(refs[mid]) < mid < max(refs[mid])
    # the number of flows is bounded and every new pair is used by a frame
    assert len(new) <= rule.max_new_flows * len(xs) and len(set(new)) == len(new)
    used = {(min(i, j), max(i, j)) for i, js in enumerate(refs) for j in js}
    assert set(new) <= used and all(b - a > 1 for a, b in new)


def test_slow_motion_reaches_further_and_fast_motion_stays_near():
    slow = _poses(np.arange(40) * 0.004)  # 0.1 deg per frame at 2 m
    fast = _poses(np.arange(40) * 0.06)  # 1.7 deg per frame
    rs, _ = R.baseline_references(slow, _samples(40), K, SIZE, FusionReferencesSettings())
    rf, _ = R.baseline_references(fast, _samples(40), K, SIZE, FusionReferencesSettings())
    gap_slow = np.median([abs(j - 20) for j in rs[20]])
    gap_fast = np.median([abs(j - 20) for j in rf[20]])
    assert gap_slow >= 10 and gap_fast <= 4, (rs[20], rf[20])


def test_existing_flows_are_preferred_and_shared():
    xs = np.arange(60) * 0.01
    poses, samples = _poses(xs), _samples(60)
    free = [(a, a + k) for k in (4, 8) for a in range(60 - k)]  # the priors' pairs
    rule = FusionReferencesSettings()
    _, new_free = R.baseline_references(poses, samples, K, SIZE, rule, free)
    refs, new_none = R.baseline_references(poses, samples, K, SIZE, rule)
    assert len(new_free) < len(new_none) and not set(new_free) & set(free)
    # at most max_new per frame, each new pair computed once and read by both its frames
    assert len(new_none) <= len(xs) * rule.max_new_flows and len(set(new_none)) == len(new_none)
    assert sum(i in refs[j] for i, js in enumerate(refs) for j in js if j > i) > len(xs) // 2
    zero = FusionReferencesSettings(max_new_flows=0)
    refs0, new0 = R.baseline_references(poses, samples, K, SIZE, zero, free)
    assert new0 == [] and all((min(i, j), max(i, j)) in set(free) or abs(i - j) == 1
                              for i, js in enumerate(refs0) for j in js)


def test_deterministic():
    rng = np.random.default_rng(3)
    poses = _poses(np.cumsum(rng.uniform(0, 0.03, 30)))
    a = R.baseline_references(poses, _samples(30), K, SIZE, FusionReferencesSettings())
    b = R.baseline_references(poses.copy(), _samples(30), K, SIZE, FusionReferencesSettings())
    assert a == b


# ------------------------------------------------------------------------------ the pipeline
N = 32


@pytest.fixture(scope="module")
def walk_clip(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("clip") / "walk"
    cli("synth", str(out), "--frames", str(N), "--trajectory", "walk", "--size", "128x96", check=True)
    return out


# priors.references=back: flow_far's pair counts below are those of the back-looking prior rule
QUICK = ["--profile", "fast", "--set", "optimize_keyframes.steps=10", "--set", "optimize_edges.steps=5",
         "--set", "optimize_segments.steps=5", "--set", "priors.references=back"]


def _run(clip: Path, tmp: Path, name: str, *sets: str) -> dict:
    args = [a for s in sets for a in ("--set", s)]
    return by_stage(cli_json("run", str(clip), "--out", str(tmp / name), "--cache", str(tmp / "cache"), *QUICK,
                             *args))


@pytest.fixture(scope="module")
def walk_run(walk_clip, tmp_path_factory) -> tuple[Path, dict]:
    """One default run of the clip (its cache shared by the tests below): (folder, stage rows)."""
    tmp = tmp_path_factory.mktemp("walk_run")
    return tmp, _run(walk_clip, tmp, "run")


def test_pipeline_reads_each_reference_from_its_flow(walk_run):
    tmp_path, st = walk_run
    cache = str(tmp_path / "cache")
    chosen = api.recorded_output(tmp_path / "run", "fusion_references", cache)[0]
    refs, new = chosen["refs"], [tuple(p) for p in chosen["flows"]]
    far = {tuple(p[:2]) for p in api.recorded_output(tmp_path / "run", "flow_far", cache).summary["pairs"]}
    # fusion_flow computes exactly the chosen pairs no other stage has, each once
    assert st["fusion_flow"]["executed"] == len(new) and not set(new) & far
    assert all(b - a > 1 for a, b in new) and len(new) <= gp.FusionReferencesParams().max_new_flows * N
    assert all(len(js) <= gp.FusionReferencesParams().max_refs for js in refs)
    assert sum(len(js) > 0 for js in refs) >= 0.8 * N
    # flow_far holds the priors' pairs only: no fusion pair is computed there any more
    assert len(far) == st["flow_far"]["executed"]
    # a frame's fused depth equals fusing the flows computed directly to its chosen references
    frames = api.recorded_output(tmp_path / "run", "ingest", cache)
    seg = api.recorded_output(tmp_path / "run", "optimize_segments", cache)
    fused = api.recorded_output(tmp_path / "run", "depth_fusion", cache)
    Kc = np.asarray(api.recorded_output(tmp_path / "run", "calibrate", cache)["K"])
    poses = np.asarray(seg["poses"])
    i = next(i for i, js in enumerate(refs) if any((min(i, j), max(i, j)) in set(new) for j in js)
             and any((min(i, j), max(i, j)) in far for j in js))
    flows = []
    for j in refs[i]:  # an adjacent reference is the flow stage's pair (the fast profile's preset)
        fl = flow_mod.compute_pair_flow(frames[i]["image"], frames[j]["image"], fb_thresh=1.0,
                                        preset="fast" if abs(i - j) == 1 else "fine")
        flows.append((fl["fwd"], fl["fwd_valid"], poses[j]))
    d, _, c = fusion.fuse_depth_flows(np.asarray(seg["depths"][i]), poses[i], flows, Kc)
    assert np.array_equal(fused[i]["depth"], d) and np.array_equal(fused[i]["confidence"], c)
    # chosen by view geometry at the run's poses and depths: every reference sees 80 % of the
    # frame at a usable angle (fixed offsets do not: compared below)
    rule = gp.FusionReferencesParams()
    samples = [R.view_samples(np.asarray(seg["depths"][k]), Kc) for k in range(N)]
    size = (fused[0]["depth"].shape[1], fused[0]["depth"].shape[0])
    for k, js in enumerate(refs):
        ov, ang = R.view_geometry(poses, samples, Kc, size, k, js)
        assert np.all(ov >= rule.min_overlap) and np.all((ang >= rule.min_angle_deg) & (ang <= rule.max_angle_deg))
    off = [R.offset_references(k, N, (-8, -4, -2, -1, 1, 2, 4, 8)) for k in range(N)]
    geo = [R.view_geometry(poses, samples, Kc, size, k, js) for k, js in enumerate(off)]
    bad = sum(int(np.sum((o < rule.min_overlap) | (a < rule.min_angle_deg))) for o, a in geo)
    assert bad > N // 2  # measured 96 of 226: too small an angle or too little overlap


def test_offsets_mode_and_what_a_change_recomputes(walk_clip, walk_run):
    tmp_path, base = walk_run
    n_new = base["fusion_flow"]["executed"]
    # the old rule is one setting away: flow_far then computes the +-2 pairs, fusion_flow none
    old = _run(walk_clip, tmp_path, "old", "depth_fusion.references=offsets")
    chosen = api.recorded_output(tmp_path / "old", "fusion_references", str(tmp_path / "cache"))[0]
    assert chosen["flows"] == [] and old["fusion_flow"]["executed"] == old["fusion_flow"]["cached"] == 0
    assert chosen["refs"][10] == [2, 6, 8, 9, 11, 12, 14, 18]
    assert old["flow_far"]["executed"] == N - 2 and old["optimize_segments"]["executed"] == 0
    # a different target angle re-chooses; pairs already computed are not computed again
    again = _run(walk_clip, tmp_path, "again", "fusion_references.target_angle_deg=3.0")
    assert again["fusion_references"]["executed"] == 1 and again["flow_far"]["executed"] == 0
    new2 = api.recorded_output(tmp_path / "again", "fusion_references", str(tmp_path / "cache"))[0]["flows"]
    new1 = api.recorded_output(tmp_path / "run", "fusion_references", str(tmp_path / "cache"))[0]["flows"]
    assert again["fusion_flow"]["cached"] == len({tuple(p) for p in new2} & {tuple(p) for p in new1}) <= n_new
    # plan names the stage that re-chooses, the setting that changed, and what waits on it
    plan = cli_json("plan", str(walk_clip), "--out", str(tmp_path / "run"), "--cache", str(tmp_path / "cache"),
                    *QUICK, "--set", "fusion_references.target_angle_deg=8.0")
    rows = {r["name"]: r for r in plan["stages"]}
    # the reference rule is its own section: nothing before fusion_references is touched
    assert all(rows[name]["action"] == "cached" for name in ("flow_far", "priors", "optimize_segments"))
    assert rows["fusion_references"]["action"] == "run"
    assert any("fusion_references.target_angle_deg changed" in r for r in rows["fusion_references"]["reasons"])
    assert any("fusion_references" in r for r in rows["fusion_flow"]["reasons"])
