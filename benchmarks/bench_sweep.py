"""Sweep benchmark: the cost of a 3-value `sweep` against one `run` alone, from a cold cache.

Two sweeps: a late-stage parameter (default ``depth_filter.radius=2,3,4``: everything before
depth_filter is shared) and ``keyframes.delta=0.05,0.1,0.15`` (ingest, flow, flow_far, masks and
priors are shared; keyframes and every later stage run three times). Three separate runs would
cost 3x; the goals are <= 1.4x and <= 2.3x.

The measurements alternate (one run, late sweep, keyframe sweep, then the same in reverse order;
repeated) so that a machine whose load drifts affects both sides alike; the figure is the median over the repeats of each
repeat's ratio (sweep seconds / one-run seconds of the same repeat). Every command is the whole
CLI (`python -m gcvd_flow ...`) with its own fresh cache. Wall and CPU seconds are both measured
(CPU: user + system of the command and of the item workers it waited for); the load average is
printed with each measurement. On a busy machine quote the ratios, not the seconds, and prefer
the CPU ratio: the wall ratio follows the other jobs' load, which changes within a repeat.

    .venv/bin/python benchmarks/bench_sweep.py [--frames 40] [--size 192x144] [--profile fast]
                                               [--repeats 3] [--jobs 1] [--json]

``--jobs 1`` (the default) keeps every item in the command's own process: the CPU seconds then
include everything (worker processes started through the forkserver are not counted).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PY = sys.executable


def _cli(*args: str, jobs: str | None) -> tuple[float, float]:
    """Wall seconds and CPU seconds (user + system of the command and the processes it waited
    for: its item workers) of one `python -m gcvd_flow ARGS` (must succeed)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    if jobs:
        env["GCVD_FLOW_JOBS"] = jobs
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run([PY, "-m", "gcvd_flow", *args], cwd=ROOT, env=env, capture_output=True, text=True)
    sec = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        sys.exit(f"bench_sweep: gcvd-flow {' '.join(args)} failed ({p.returncode}): {p.stderr.strip()[-800:]}")
    return sec, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--size", default="192x144")
    ap.add_argument("--trajectory", default="orbit")
    ap.add_argument("--profile", default="fast", help="parameter profile of every run ('' for the defaults)")
    ap.add_argument("--late", default="depth_filter.radius=2,3,4", help="the late-stage grid")
    ap.add_argument("--keyframes", default="keyframes.delta=0.05,0.1,0.15", help="the keyframe grid")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--jobs", default="1", help="GCVD_FLOW_JOBS for every command (default 1: every item in "
                    "the command's own process, so that its CPU seconds are all counted; with worker processes "
                    "their CPU time is lost to the forkserver, and only the wall ratio holds)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="bench-sweep-"))
    prof = ["--profile", a.profile] if a.profile else []
    try:
        clip = tmp / "clip"
        _cli("synth", str(clip), "--frames", str(a.frames), "--size", a.size, "--trajectory", a.trajectory,
             jobs=a.jobs)
        rows = []
        for rep in range(a.repeats):
            row = {}
            order = [("one", ["run", str(clip), "--out", str(tmp / "one")]),
                     ("late", ["sweep", str(clip), "--out", str(tmp / "late"), "--grid", a.late]),
                     ("keyframes", ["sweep", str(clip), "--out", str(tmp / "kf"), "--grid", a.keyframes])]
            # every other repeat in reverse (ABBA): a load that rises or falls steadily biases
            # the ratios one way in one repeat and the other way in the next
            for what, args in (order if rep % 2 == 0 else order[::-1]):
                cache = tmp / "cache"
                shutil.rmtree(cache, ignore_errors=True)
                for d in ("one", "late", "kf"):
                    shutil.rmtree(tmp / d, ignore_errors=True)
                load = os.getloadavg()[0]
                row[what], row[f"{what}_cpu"] = _cli(*args, "--cache", str(cache), *prof, jobs=a.jobs)
                row[f"{what}_load"] = round(load, 2)
                print(f"repeat {rep + 1}: {what:<10} {row[what]:7.1f} s wall, {row[what + '_cpu']:7.1f} s CPU "
                      f"(load average before: {load:.2f})", file=sys.stderr, flush=True)
            for k in ("late", "keyframes"):
                row[f"{k}_ratio"] = row[k] / row["one"]
                row[f"{k}_cpu_ratio"] = row[f"{k}_cpu"] / row["one_cpu"]
            rows.append(row)
        res = {"clip": {"frames": a.frames, "size": a.size, "trajectory": a.trajectory, "profile": a.profile},
               "late_grid": a.late, "keyframes_grid": a.keyframes, "repeats": rows,
               "late_ratio_median": round(statistics.median(r["late_ratio"] for r in rows), 3),
               "keyframes_ratio_median": round(statistics.median(r["keyframes_ratio"] for r in rows), 3),
               "late_cpu_ratio_median": round(statistics.median(r["late_cpu_ratio"] for r in rows), 3),
               "keyframes_cpu_ratio_median": round(statistics.median(r["keyframes_cpu_ratio"] for r in rows), 3),
               "cpus": os.cpu_count()}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if a.json:
        print(json.dumps(res, indent=1))
    else:
        print(f"{a.frames} frames {a.size} {a.trajectory}, profile {a.profile or 'default'}, {a.repeats} repeats")
        for r in rows:
            print(f"one run {r['one']:6.1f} s ({r['one_cpu']:.1f} CPU) | {a.late}: {r['late']:6.1f} s "
                  f"({r['late_ratio']:.2f}x; CPU {r['late_cpu_ratio']:.2f}x) | {a.keyframes}: {r['keyframes']:6.1f} s "
                  f"({r['keyframes_ratio']:.2f}x; CPU {r['keyframes_cpu_ratio']:.2f}x)")
        print(f"median ratio, wall: late-stage sweep {res['late_ratio_median']:.2f}x (goal <= 1.4x), "
              f"keyframes.delta sweep {res['keyframes_ratio_median']:.2f}x (goal <= 2.3x); three runs: 3x")
        print(f"median ratio, CPU:  late-stage sweep {res['late_cpu_ratio_median']:.2f}x, "
              f"keyframes.delta sweep {res['keyframes_cpu_ratio_median']:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
