"""Accuracy and ablations (rows as in the GCVD paper's Table 3) on exact-ground-truth clips.

Datasets: a synthetic `loop` clip (120 frames, 256x192, rendered here) and the ICL-NUIM
living-room frames in ../shared/data (211 frames, intrinsics 525, 525, 319.5, 239.5).
Every row is a full `gcvd-flow run` with one switch flipped, sharing one cache (so the
pre-processing is computed once per dataset), then `gcvd-flow eval`.

    make bench-accuracy        # or: .venv/bin/python benchmarks/bench_accuracy.py [--only loop]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
ICL = ROOT.parent / "shared" / "data" / "icl_livingroom1_micro"

ROWS = [
    ("full (GCVD)", []),
    ("w/o keyframes", ["keyframes.enabled=false"]),
    ("w/o LayerNorm", ["depth.layer_norm=false"]),
    ("w/o mesh deformation", ["depth.mesh=false"]),
    ("w/o depth-gradient loss", ["losses.grad=false"]),
    ("w/o pose graph", ["pose_graph.enabled=false"]),
    ("+ bundle adjustment", ["bundle_adjustment.enabled=true"]),
]


def gcvd(*args: str) -> dict:
    env = dict(os.environ, CI="1")
    p = subprocess.run([sys.executable, "-m", "gcvd_flow", *args, "--json"], cwd=ROOT, env=env,
                       capture_output=True, text=True)
    if p.returncode != 0:
        raise SystemExit(f"gcvd-flow {' '.join(args)} failed:\n{p.stderr[-3000:]}")
    return json.loads(p.stdout)


def run_rows(name: str, inp: Path, gt: Path, work: Path, cache: str, extra: list[str], rows) -> list[dict]:
    out = []
    for label, sets in rows:
        run_dir = work / f"{name}-{len(out)}"
        args = ["run", str(inp), "--out", str(run_dir), "--cache", cache, *extra]
        for s in sets:
            args += ["--set", s]
        t0 = time.perf_counter()
        gcvd(*args)
        secs = time.perf_counter() - t0
        m = gcvd("eval", str(run_dir), "--gt", str(gt))
        m.update(row=label, dataset=name, seconds=secs)
        out.append(m)
        print(f"  {name:<5} {label:<26} ATE {m['ate_rmse']:.5f} m ({m['ate_percent_of_path']:.2f}% of path)  "
              f"AbsRel {m.get('abs_rel', float('nan')):.4f}  ({secs:.0f} s)", file=sys.stderr, flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--only", choices=["loop", "icl"])
    ap.add_argument("--rows", type=int, default=len(ROWS), help="first N rows only")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    rows = ROWS[: a.rows]
    results = []
    with tempfile.TemporaryDirectory(prefix="bench-acc-") as tmp:
        work = Path(tmp)
        cache = str(work / "cache")
        if a.only in (None, "loop"):
            clip = work / "loop"
            subprocess.run([sys.executable, "-m", "gcvd_flow", "synth", str(clip), "--frames", "120",
                            "--trajectory", "loop", "--size", "256x192"], cwd=ROOT, check=True,
                           stdout=sys.stderr)  # stdout is for the table / --json
            results += run_rows("loop", clip, clip, work, cache, [], rows)
        if a.only in (None, "icl"):
            if ICL.exists():
                results += run_rows("icl", ICL, ICL, work, cache, ["--intrinsics", "525,525,319.5,239.5"], rows)
            else:
                print(f"(skipping ICL: {ICL} is absent)", file=sys.stderr)
    if a.json:
        print(json.dumps(results, indent=1))
        return
    print(f"\n{'dataset':<6} {'setting':<26} {'ATE[m]':>8} {'ATE%path':>9} {'RPEt[m]':>9} {'RPEr[deg]':>10} "
          f"{'AbsRel':>7} {'d<1.25':>7} {'time[s]':>8}")
    for m in results:
        print(f"{m['dataset']:<6} {m['row']:<26} {m['ate_rmse']:8.5f} {m['ate_percent_of_path']:9.3f} "
              f"{m['rpe_trans']:9.4f} {m['rpe_rot']:10.3f} {m.get('abs_rel', float('nan')):7.4f} "
              f"{m.get('delta1', float('nan')):7.3f} {m['seconds']:8.0f}")


if __name__ == "__main__":
    main()
