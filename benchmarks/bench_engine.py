"""Engine benchmark: the 5-stage toy pipeline with 1000-item map stages (~100 KB per item).

Prints cold run, no-op re-run and re-run after a parameter change at the 4th stage for
gcvd-flow and, in the same command, for `dvc repro` on the equivalent dvc.yaml (DVC lives in
its own venv, .venv-bench, so that it never touches the product's pins); then BLAKE3 hashing
throughput. Every figure is the median of REPEATS runs of the whole CLI command.

    make bench-engine            # or: .venv/bin/python benchmarks/bench_engine.py [--items N]
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

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
PY = sys.executable
BENCH_VENV = ROOT / ".venv-bench"

# The same work as stages/toy.py, as stand-alone scripts for DVC.
DVC_STAGE = r'''
import json, sys
from pathlib import Path
import numpy as np, yaml
stage, src, dst = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3])
params = yaml.safe_load(open("params.yaml"))
if stage == "decode":
    dst.mkdir(exist_ok=True)
    for f in sorted(src.glob("*.bin")):
        np.save(dst / (f.stem + ".npy"), np.frombuffer(f.read_bytes(), np.uint8).astype(np.float32))
elif stage == "transform":
    dst.mkdir(exist_ok=True)
    s = np.float32(params["transform"]["scale"])
    for f in sorted(src.glob("*.npy")):
        np.save(dst / f.name, (np.load(f) * s).astype(np.float32))
elif stage == "summarize":
    means = [float(np.load(f).mean()) for f in sorted(src.glob("*.npy"))]
    json.dump({"means": means, "total": round(sum(means), params["summarize"]["digits"])}, open(dst, "w"))
elif stage == "threshold":
    means = np.asarray(json.load(open(src))["means"])
    json.dump({"above": (means > params["threshold"]["cut"]).astype(int).tolist()}, open(dst, "w"))
elif stage == "report":
    above = json.load(open(src))["above"]
    json.dump({"count": sum(above), "n": len(above)}, open(dst, "w"))
'''

DVC_YAML = """stages:
  decode:
    cmd: {py} stage.py decode input decoded
    deps: [stage.py, input]
    outs: [decoded]
  transform:
    cmd: {py} stage.py transform decoded transformed
    deps: [stage.py, decoded]
    params: [transform.scale]
    outs: [transformed]
  summarize:
    cmd: {py} stage.py summarize transformed summary.json
    deps: [stage.py, transformed]
    params: [summarize.digits]
    outs: [summary.json]
  threshold:
    cmd: {py} stage.py threshold summary.json threshold.json
    deps: [stage.py, summary.json]
    params: [threshold.cut]
    outs: [threshold.json]
  report:
    cmd: {py} stage.py report threshold.json report.json
    deps: [stage.py, threshold.json]
    outs: [report.json]
"""


def timed(cmd: list[str], cwd: Path, env: dict | None = None) -> float:
    t0 = time.perf_counter()
    p = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit(f"command failed: {' '.join(cmd)}\n{p.stderr[-2000:]}")
    return dt


def make_input(folder: Path, n: int, size: int) -> None:
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        (folder / f"{i:05d}.bin").write_bytes(rng.integers(0, 256, size, dtype=np.uint8).tobytes())


def bench_gcvd(work: Path, repeats: int) -> dict[str, float]:
    inp, out, cache = work / "input", work / "out", work / "cache"
    base = [PY, "-m", "gcvd_flow", "run", str(inp), "--out", str(out), "--cache", str(cache),
            "--pipeline", "toy", "--json"]
    env = dict(os.environ, CI="1")
    res = {"cold": timed(base, ROOT, env)}
    res["noop"] = statistics.median(timed(base, ROOT, env) for _ in range(repeats))
    changes = []
    for i in range(repeats):
        changes.append(timed(base + ["--set", f"threshold.cut={100 + i}"], ROOT, env))
    res["param_change_stage4"] = statistics.median(changes)
    return res


def bench_dvc(work: Path, repeats: int) -> dict[str, float] | None:
    dvc = BENCH_VENV / "bin" / "dvc"
    if not dvc.exists():
        print("(dvc not installed in .venv-bench; skipping the DVC peer)", file=sys.stderr)
        return None
    proj = work / "dvcproj"
    proj.mkdir()
    shutil.copytree(work / "input", proj / "input")
    (proj / "stage.py").write_text(DVC_STAGE)
    (proj / "dvc.yaml").write_text(DVC_YAML.format(py=PY))
    env = dict(os.environ, DVC_NO_ANALYTICS="1", GIT_AUTHOR_NAME="b", GIT_AUTHOR_EMAIL="b@b",
               GIT_COMMITTER_NAME="b", GIT_COMMITTER_EMAIL="b@b")

    def params(cut: float) -> None:
        (proj / "params.yaml").write_text(
            f"transform:\n  scale: 2.0\nsummarize:\n  digits: 6\nthreshold:\n  cut: {cut}\n")

    params(200.0)
    subprocess.run(["git", "init", "-q"], cwd=proj, check=True, env=env)
    subprocess.run([str(dvc), "init", "-q"], cwd=proj, check=True, env=env)
    res = {"cold": timed([str(dvc), "repro", "-q"], proj, env)}
    res["noop"] = statistics.median(timed([str(dvc), "repro", "-q"], proj, env) for _ in range(repeats))
    changes = []
    for i in range(repeats):
        params(100.0 + i)
        changes.append(timed([str(dvc), "repro", "-q"], proj, env))
    res["param_change_stage4"] = statistics.median(changes)
    return res


def bench_hashing(total_mb: int = 1024) -> dict[str, float]:
    import blake3

    from gcvd_flow.engine.keys import digest_bytes

    data = np.random.default_rng(1).integers(0, 256, total_mb << 20, dtype=np.uint8).tobytes()
    times_mt, times_1 = [], []
    for _ in range(3):
        t0 = time.perf_counter()
        digest_bytes(data)
        times_mt.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        blake3.blake3(data).hexdigest()
        times_1.append(time.perf_counter() - t0)
    gb = len(data) / 1e9
    return {"GB/s (store, multithreaded)": gb / statistics.median(times_mt),
            "GB/s (single thread)": gb / statistics.median(times_1)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--items", type=int, default=1000)
    ap.add_argument("--item-kb", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-engine-") as tmp:
        work = Path(tmp)
        make_input(work / "input", a.items, a.item_kb * 1000)
        g = bench_gcvd(work, a.repeats)
        d = bench_dvc(work, a.repeats)
    h = bench_hashing()
    doc = {"items": a.items, "item_kb": a.item_kb, "gcvd_flow_s": g, "dvc_s": d, "hashing": h}
    if a.json:
        print(json.dumps(doc, indent=1))
        return
    print(f"toy pipeline: 5 stages, 2 map stages x {a.items} items x {a.item_kb} KB; median of {a.repeats}")
    print(f"{'':24}{'gcvd-flow':>12}{'dvc repro':>12}{'ratio':>9}")
    for k in ("cold", "noop", "param_change_stage4"):
        dv = d[k] if d else float("nan")
        print(f"{k:24}{g[k]:11.2f}s{dv:11.2f}s{dv / g[k]:8.1f}x")
    for k, v in h.items():
        print(f"hashing {k}: {v:.2f}")


if __name__ == "__main__":
    main()
