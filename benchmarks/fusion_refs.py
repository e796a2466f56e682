"""depth_fusion alone, for several sets of reference offsets, from a finished run's cache (issue 28).

Reads the run's optimised depth and poses (optimize_segments), K (calibrate), its flows (flow for
+-1, flow_far for the pairs it holds; any other pair is computed here with the same DIS preset)
and scores ``stages.depth.fusion.fuse_depth_flows`` (before depth_filter / consensus) against the
clip's ground-truth depth: mean per-frame AbsRel with per-frame median scaling, GT in (0, 10 m].

    PYTHONPATH=$PWD python benchmarks/fusion_refs.py RUN_DIR CACHE CLIP [--step 8] [--far]

CLIP is a ``gcvd-flow synth`` folder (gt/depth/*.png, one per frame of the run).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from gcvd_flow.engine import api
from gcvd_flow.io.formats import read_depth_png
from gcvd_flow.pipeline import _far_flow
from gcvd_flow.stages.depth import fusion
from gcvd_flow.stages.frontend import flow as flow_mod

NEAR = {"none (optimised depth)": [], "+-8": [-8, 8], "+-4,8": [-8, -4, 4, 8], "+-2,4,8": [-8, -4, -2, 2, 4, 8],
        "+-1,2,4,8": [-8, -4, -2, -1, 1, 2, 4, 8], "+-4": [-4, 4], "+-2": [-2, 2], "+-1": [-1, 1]}
FAR = {"+-8": [-8, 8], "+-16": [-16, 16], "+-8,16": [-16, -8, 8, 16], "+-24": [-24, 24], "+-32": [-32, 32]}


def abs_rel(d: np.ndarray, g: np.ndarray) -> float:
    m = (g > 0) & (g <= 10) & (d > 0)
    s = np.median(g[m]) / np.median(d[m])
    return float(np.mean(np.abs(d[m] * s - g[m]) / g[m]))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("run")
    ap.add_argument("cache")
    ap.add_argument("clip", type=Path)
    ap.add_argument("--step", type=int, default=8, help="every step-th frame")
    ap.add_argument("--far", action="store_true", help="references up to +-32 frames (frames 32 .. n-33)")
    a = ap.parse_args()
    seg = api.recorded_output(a.run, "optimize_segments", a.cache)
    poses = np.asarray(seg["poses"], np.float64)
    K = np.asarray(api.recorded_output(a.run, "calibrate", a.cache)["K"])
    far, adjacent = api.recorded_output(a.run, "flow_far", a.cache), api.recorded_output(a.run, "flow", a.cache)
    images = api.recorded_output(a.run, "ingest", a.cache)
    index = {tuple(p[:2]): k for k, p in enumerate(far.summary["pairs"])}
    gts = sorted((a.clip / "gt" / "depth").glob("*.png"))

    def flow_to(i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
        if abs(i - j) == 1:
            return _far_flow(adjacent[min(i, j)], "fwd" if j > i else "bwd")
        if (min(i, j), max(i, j)) in index:
            return _far_flow(far[index[(min(i, j), max(i, j))]], "fwd" if i < j else "bwd")
        fl = flow_mod.compute_pair_flow(np.asarray(images[i]["image"]), np.asarray(images[j]["image"]),
                                        preset="fine", fb_thresh=1.0)
        return fl["fwd"], fl["fwd_valid"]

    sets, lo = (FAR, 32) if a.far else (NEAR, 8)
    res: dict[str, list[float]] = {k: [] for k in sets}
    for i in range(lo, len(poses) - lo, a.step):
        g, d = read_depth_png(gts[i]), np.asarray(seg["depths"][i], np.float32)
        for name, offs in sets.items():
            flows = [(*flow_to(i, i + o), poses[i + o]) for o in offs]
            res[name].append(abs_rel(fusion.fuse_depth_flows(d, poses[i], flows, K)[0] if flows else d, g))
    print(json.dumps({k: round(float(np.mean(v)), 4) for k, v in res.items()}, indent=1))


if __name__ == "__main__":
    main()
