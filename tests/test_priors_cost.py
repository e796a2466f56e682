"""What makes the priors cheaper without changing them (issue 38).

- The chain of adjacent flows (priors.chain_fallback) is read only by the frames whose direct
  flows all failed: priors_direct triangulates the direct flows and flags the frames without a
  usable one; the priors stage passes every other frame's prior on and reads the chain for the
  flagged ones alone. These tests fail if a frame whose direct flow holds reads the chain, if a
  flagged frame does not, or if the priors differ from the single-stage computation.
- The triangulation (angle from the same rays and dot products) and densify (guide statistics
  shared by the two filters of a radius) equal the former code, byte for byte.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import by_stage, cli, cli_json

from gcvd_flow import api, pipeline as gp
from gcvd_flow.engine.store import Store
from gcvd_flow.stages.frontend import priors as priors_mod
from gcvd_flow.stages.graph import references

N = 24


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("clip") / "loop"
    cli("synth", str(out), "--frames", str(N), "--trajectory", "loop", "--size", "96x72", check=True)
    return out


def _run(clip: Path, tmp: Path, *sets: str) -> dict:
    args = [a for s in sets for a in ("--set", s)]
    doc = cli_json("run", str(clip), "--out", str(tmp / "run"), "--cache", str(tmp / "cache"), "--until", "priors", *args)
    return by_stage(doc)


def _item_inputs(tmp: Path) -> list[set[str]]:
    """The input names of each item of the run's priors stage, from the records."""
    import json

    run = json.loads((tmp / "run" / "run.json").read_text())
    store = Store(tmp / "cache")
    rec = store.get_record(run["stages"]["priors"]["key"])
    return [set(store.get_record(k)["inputs"]) for k in rec["children"]]


def _single_stage_prior(tmp: Path, i: int, p) -> dict:
    """Frame i's prior as the single priors stage computed it before: direct flows and the chain
    in one item (gcvd_flow.pipeline.priors.run_priors on both)."""
    cache = str(tmp / "cache")
    frames = api.recorded_output(tmp / "run", "ingest", cache)
    far = api.recorded_output(tmp / "run", "flow_far", cache)
    flows = api.recorded_output(tmp / "run", "flow", cache)
    index = {tuple(pr): k for k, pr in enumerate(far.summary["pairs"])}
    js = gp._prior_refs(i, N, p)
    refs = gp._far_refs(index, i, js, p.preset, p.fb_thresh)
    direction, ks = references.flow_chain(i, N, p.span)
    inputs = {"image": frames[i], "K": np.asarray(frames.summary["K"]),
              "refs": [far[r.index] for r in refs["refs"]], "ref_dirs": refs["ref_dirs"].value,
              "chain_dir": direction, "chain": [flows[k] for k in ks[:p.chain_links]]}
    return gp.run_priors(inputs, p, None)


def test_the_chain_is_read_only_where_no_direct_flow_held(clip, tmp_path):
    # the loop's direct flows hold: no priors item reads the chain, each passes priors_direct's on
    st = _run(clip, tmp_path, "priors.references=back")
    assert st["priors_direct"]["executed"] == N and st["priors"]["executed"] == N
    assert all(names == {"direct"} for names in _item_inputs(tmp_path))
    pri = api.recorded_output(tmp_path / "run", "priors", str(tmp_path / "cache"))
    p = gp.PriorsParams(references="back")
    for i in (2, N - 1):
        assert np.array_equal(pri[i]["inv_depth"], _single_stage_prior(tmp_path, i, p)["inv_depth"])
    # a forward-backward threshold no direct flow passes (the adjacent flows keep theirs): every
    # frame falls back to its chain, and reads it
    st = _run(clip, tmp_path, "priors.references=back", "priors.fb_thresh=0.002")
    direct = api.recorded_output(tmp_path / "run", "priors_direct", str(tmp_path / "cache"))
    flagged = [i for i in range(N) if direct[i]["fallback"]]
    assert len(flagged) >= N // 2
    names = _item_inputs(tmp_path)
    assert all(("chain" in names[i]) == (i in flagged) for i in range(N))
    assert all(names[i] == {"direct"} for i in range(N) if i not in flagged)
    pri = api.recorded_output(tmp_path / "run", "priors", str(tmp_path / "cache"))
    p = gp.PriorsParams(references="back", fb_thresh=0.002)
    for i in flagged[:1] + flagged[-1:]:
        want = _single_stage_prior(tmp_path, i, p)
        assert np.array_equal(pri[i]["inv_depth"], want["inv_depth"])
        assert np.array_equal(pri[i]["confidence"], want["confidence"])
        assert pri[i]["confidence"].mean() > 0  # the chain was triangulated, not a constant prior
    # without the fallback no item reads the chain; the flagged frames keep the constant prior
    _run(clip, tmp_path, "priors.references=back", "priors.fb_thresh=0.002", "priors.chain_fallback=false")
    assert all(names == {"direct"} for names in _item_inputs(tmp_path))
    pri = api.recorded_output(tmp_path / "run", "priors", str(tmp_path / "cache"))
    assert np.all(pri[flagged[0]]["inv_depth"] == 1.0) and np.all(pri[flagged[0]]["confidence"] == 0.0)


def _former_densify(guide, values, weights, radii=(2, 4, 8, 16, 32), eps=1e-3):
    """densify before the guide statistics were shared (two full guided filters per radius)."""
    out = np.zeros_like(values, dtype=np.float64)
    have = np.zeros(values.shape, bool)
    support = np.zeros(values.shape, np.float64)
    for r in radii:
        num = priors_mod.guided_filter(guide, values * weights, r, eps)
        den = priors_mod.guided_filter(guide, weights, r, eps)
        ok = (den > 1e-3) & ~have
        est = num / np.maximum(den, 1e-6)
        out[ok] = est[ok]
        support[ok] = np.clip(den[ok] / max(float(weights.max()), 1e-9), 0, 1)
        have |= ok
        if have.all():
            break
    if not have.all():
        out[~have] = np.median(values[weights > 0]) if (weights > 0).any() else 1.0
    return out, support


def _former_guided_filter(guide, src, r, eps):
    box = priors_mod._box
    I, p = guide.astype(np.float64), src.astype(np.float64)
    mean_I, mean_p = box(I, r), box(p, r)
    cov_Ip = box(I * p, r) - mean_I * mean_p
    var_I = box(I * I, r) - mean_I * mean_I
    a = cov_Ip / (var_I + eps)
    b = mean_p - a * mean_I
    return box(a, r) * I + box(b, r)


def test_densify_equals_the_former_code():
    rng = np.random.default_rng(5)
    guide = rng.uniform(size=(72, 96))
    values = rng.uniform(0.5, 2.0, size=(72, 96))
    weights = np.where(rng.uniform(size=(72, 96)) < 0.05, rng.uniform(0.05, 1, size=(72, 96)), 0.0)
    got = priors_mod.densify(guide, values, weights)
    want = _former_densify(guide, values, weights)
    known = values[weights > 0]  # since 2026-11-29 the fill stays within the known values' range
    want = (np.clip(want[0], known.min(), known.max()), want[1])
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    assert np.array_equal(priors_mod.guided_filter(guide, values, 4, 1e-3),
                          _former_guided_filter(guide, values, 4, 1e-3))
