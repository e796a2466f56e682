"""Scale benchmark: throughput of the map stages with 1 vs 2 Dask workers, and a projection.

Renders a synthetic clip once, then for each worker count runs the GCVD pipeline up to the last
map stage before keyframe selection (``--until priors``: ingest, flow, masks, priors are map
stages; ``--until keyframes`` then ``--until priors``, since priors needs only ingest) with
``--executor dask --jobs W`` on a fresh cache, REPEATS times; per map stage it
reports items/s (stage seconds from ``run.json``: the cluster's start-up is not counted) and the
speed-up over one worker. One full run (in-process) measures the serial part: the whole stages
(keyframes, association, the optimisations, the pose graph), which run in the client process.
From both, a projection of a run's time on W workers for 1000 and 10 000 frames
(T(W) = serial + parallel / W; per-frame costs scaled linearly from the measured clip).

    make bench-scale                      # or: .venv/bin/python benchmarks/bench_scale.py [--frames N]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PY = sys.executable


def gcvd(*args: str) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    p = subprocess.run([PY, "-m", "gcvd_flow", *args], capture_output=True, text=True, cwd=ROOT, env=env)
    if p.returncode != 0:
        sys.exit(f"gcvd-flow {' '.join(args)} failed:\n{p.stderr}")
    return json.loads(p.stdout) if "--json" in args else {}


def stage_seconds(doc: dict) -> dict[str, tuple[int, float]]:
    return {s["name"]: (s["executed"] + s["cached"], s["seconds"]) for s in doc["stages"]}


def measure(clip: Path, tmp: Path, workers: int, repeats: int, extra: list[str]) -> dict[str, tuple[int, float]]:
    """Median stage seconds of ``repeats`` cold runs up to priors on ``workers`` Dask workers."""
    runs = []
    for r in range(repeats):
        cache, out = tmp / f"cache-w{workers}-{r}", tmp / f"out-w{workers}-{r}"
        # priors needs only ingest; flow and masks are needed by keyframes: two targets, one cache
        merged: dict[str, tuple[int, float]] = {}
        for target in ("keyframes", "priors"):
            doc = gcvd("run", str(clip), "--out", str(out), "--cache", str(cache), "--until", target,
                       "--executor", "dask", "--jobs", str(workers), "--json", *extra)
            for name, (n, secs) in stage_seconds(doc).items():
                if name != "keyframes" and secs >= merged.get(name, (0, 0.0))[1]:
                    merged[name] = (n, secs)  # a stage computed in the first pass is cached in the second
        runs.append(merged)
        shutil.rmtree(cache, ignore_errors=True)
    return {name: (runs[0][name][0], statistics.median(r[name][1] for r in runs)) for name in runs[0]}


def projection(serial_per_frame: float, parallel_per_frame: float, frames: int, workers: list[int]) -> str:
    t1 = (serial_per_frame + parallel_per_frame) * frames
    cells = []
    for w in workers:
        t = serial_per_frame * frames + parallel_per_frame * frames / w
        cells.append(f"W={w}: {t / 60:.1f} min (x{t1 / t:.2f})")
    return f"{frames:>6} frames  " + "  ".join(cells)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--size", default="256x192")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--workers", default="1,2", help="worker counts to measure (comma-separated)")
    ap.add_argument("--profile", default=None, help="parameter profile (default: the defaults)")
    a = ap.parse_args()
    extra = ["--profile", a.profile] if a.profile else []
    counts = [int(w) for w in a.workers.split(",")]
    with tempfile.TemporaryDirectory(prefix="bench-scale-") as d:
        tmp = Path(d)
        clip = tmp / "clip"
        gcvd("synth", str(clip), "--frames", str(a.frames), "--trajectory", "loop", "--size", a.size)
        print(f"clip: {a.frames} frames {a.size}; {os.cpu_count()} cores; median of {a.repeats} cold runs\n")
        res = {w: measure(clip, tmp, w, a.repeats, extra) for w in counts}
        base = res[counts[0]]
        head = f"{'stage':<10} {'items':>6} " + " ".join(f"{f'W={w} items/s':>14}" for w in counts)
        head += "  " + " ".join(f"{f'speed-up W={w}':>13}" for w in counts[1:])
        print(head)
        print("-" * len(head))
        for name, (n, _) in base.items():
            rates = [n / max(res[w][name][1], 1e-9) for w in counts]
            line = f"{name:<10} {n:>6} " + " ".join(f"{r:>14.1f}" for r in rates)
            line += "  " + " ".join(f"{rates[i] / rates[0]:>13.2f}" for i in range(1, len(counts)))
            print(line)
        # the serial part: one full in-process run (whole stages run in the client process)
        t0 = time.perf_counter()
        doc = gcvd("run", str(clip), "--out", str(tmp / "full"), "--cache", str(tmp / "cache-full"), "--json", *extra)
        total = time.perf_counter() - t0
        st = stage_seconds(doc)
        maps = {s["name"] for s in gcvd("dag", "--json")["stages"] if s["map"]}
        parallel = sum(sec for name, (_, sec) in st.items() if name in maps)
        serial = sum(sec for name, (_, sec) in st.items() if name not in maps)
        print(f"\nfull in-process run: {total:.1f} s wall; map stages {parallel:.1f} s (parallel), "
              f"whole stages {serial:.1f} s (serial: {', '.join(n for n in st if n not in maps)})")
        print("projection, T(W) = serial + parallel / W, per-frame costs of this clip scaled linearly:")
        for frames in (1000, 10_000):
            print(projection(serial / a.frames, parallel / a.frames, frames, [1, 2, 4, 8, 16, 32]))


if __name__ == "__main__":
    main()
