"""Cost of a no-op `run` on an existing run dir: the metadata fast path, the re-hash of RUN_DIR's
files that precedes every stamp (``fastpath.write`` -> ``outputs.check_files``), and a no-op
through the full runner (stamp removed, every stage cached).

    python benchmarks/bench_noop.py CLIP RUN_DIR CACHE [--profile fast] [--repeats 5]

RUN_DIR must hold a finished `run` of CLIP with the same cache and profile (e.g. a 120-frame
`synth` clip). Figures: medians of whole CLI commands (subprocesses), check_files in-process.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path


def _wall(cmd: list[str]) -> tuple[float, dict]:
    t = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    dt = time.perf_counter() - t
    if r.returncode != 0:
        raise SystemExit(r.stderr.strip())
    return dt, json.loads(r.stdout)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("clip")
    ap.add_argument("run_dir")
    ap.add_argument("cache")
    ap.add_argument("--profile", default="fast")
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()
    from gcvd_flow.engine.fastpath import STAMP
    from gcvd_flow.engine.outputs import check_files

    cmd = [sys.executable, "-m", "gcvd_flow", "run", a.clip, "--out", a.run_dir, "--cache", a.cache,
           "--profile", a.profile, "--json"]
    out = Path(a.run_dir)
    files = json.loads((out / "run.json").read_text())["files"]
    nbytes = sum((out / f).stat().st_size for f in files)
    print(f"RUN_DIR: {len(files)} files, {nbytes / 1e6:.2f} MB")
    fast, res = [], {}
    for _ in range(a.repeats):
        dt, res = _wall(cmd)
        if "noop" not in res:
            raise SystemExit("not answered by the fast path: run the same command once first")
        fast.append(dt)
    print(f"no-op fast path: median {statistics.median(fast):.3f} s wall, {res['seconds']:.3f} s in the check")
    rehash = []
    for _ in range(a.repeats):
        t = time.perf_counter()
        problems = check_files(out, files)
        rehash.append(time.perf_counter() - t)
        if problems:
            raise SystemExit("; ".join(problems))
    print(f"re-hash of RUN_DIR (check_files, warm page cache): median {statistics.median(rehash):.3f} s")
    full = []
    for _ in range(max(1, a.repeats // 2)):
        os.unlink(out / STAMP)  # the full runner answers (every stage cached), exports, re-hashes, stamps
        full.append(_wall(cmd)[0])
    print(f"no-op through the full runner: median {statistics.median(full):.3f} s wall")


if __name__ == "__main__":
    main()
