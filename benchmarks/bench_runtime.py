"""Per-frame runtime and peak memory on synthetic clips of 50/200/500/1000 frames.

Split like the GCVD paper's Table 4: pre-processing (ingest, flow, flow_far, masks, priors,
keyframes, association), main (optimize_keyframes, optimize_edges, pose_graph,
bundle_adjustment, optimize_segments) and post-processing (depth_fusion, depth_filter,
depth_consensus). Each clip runs cold in a fresh cache
in its own process; peak memory is that process's max RSS.

    make bench-runtime         # or: .venv/bin/python benchmarks/bench_runtime.py --frames 50 200

``--side-by-side N``: load collapse. An N-frame clip runs alone (cold cache), then two copies
start at the same moment (separate caches and run dirs); the ratio is the slower of the two
against the run alone, with OpenMP's idle threads sleeping (the default since this change:
``OMP_WAIT_POLICY=PASSIVE``) and with OpenMP's own default (``OMP_WAIT_POLICY=`` empty: spin,
then sleep) as the peer, median of ``--repeat`` rounds.

``--real``: the issue-13 clips, each run ``--repeat`` times cold: the ICL-NUIM living room
(../shared/data, 211 frames 640x480) and a keyframe-heavy synthetic scan (200 frames rendered
at 640x480, ``synth --trajectory scan``); median seconds per frame, per-stage medians, keyframe
share and peak RSS. ``--peer CHECKOUT`` times another commit's code too, alternating with this
one round by round, and reports the ratio (the machine's speed drifts between runs).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_cost import Sampler  # noqa: E402 - the sibling benchmark's process-tree sampler

from gcvd_flow.pipeline import STAGE_GROUPS  # noqa: E402 - the checkout's pipeline, not an installed one

PRE, MAIN, POST = STAGE_GROUPS["pre"], STAGE_GROUPS["main"], STAGE_GROUPS["post"]


class TreeMemory:
    """Peak memory of a process and all its descendants (the map stages' worker processes are
    children of multiprocessing's forkserver, which wait4 does not count): the peak summed Pss
    sampled by bench_cost.Sampler (one process-tree sampler for both benchmarks)."""

    def __init__(self, pid: int) -> None:
        self._sampler = Sampler(pid)

    def stop(self) -> float:
        """Peak in MB."""
        return float(self._sampler.stop()["peak_tree_pss_mb"])


def _timed_runs(tmp: Path, clip: Path, tag: str, copies: int, policy: str, run_args: tuple[str, ...] = ()) -> list[float]:
    """Wall seconds of ``copies`` cold runs of ``clip`` started together (``run_args``: more
    ``gcvd-flow run`` options)."""
    import time

    env = dict(os.environ, CI="1", OMP_WAIT_POLICY=policy)
    procs, t0 = [], time.perf_counter()
    for c in range(copies):
        d = tmp / f"{tag}-{c}"
        shutil.rmtree(d, ignore_errors=True)
        cmd = [sys.executable, "-m", "gcvd_flow", "run", str(clip), "--out", str(d / "run"), "--cache",
               str(d / "cache"), "--json", *run_args]
        procs.append(subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE))
    ends = []
    for p in procs:
        _, err = p.communicate()
        if p.returncode != 0:
            raise SystemExit(err.decode()[-3000:])
        ends.append(time.perf_counter() - t0)
    return ends


def side_by_side(frames: int, size: str, trajectory: str, repeat: int,
                 policies: tuple[str, ...] = ("passive", "openmp_default"), run_args: tuple[str, ...] = ()) -> dict:
    import statistics

    with tempfile.TemporaryDirectory(prefix="bench-sbs-") as tmp_s:
        tmp = Path(tmp_s)
        clip = tmp / "clip"
        subprocess.run([sys.executable, "-m", "gcvd_flow", "synth", str(clip), "--frames", str(frames),
                        "--trajectory", trajectory, "--size", size], cwd=ROOT, check=True, capture_output=True)
        out = {"frames": frames, "size": size, "trajectory": trajectory, "repeat": repeat, "run_args": list(run_args)}
        for name, policy in (("passive", "PASSIVE"), ("openmp_default", "")):
            if name not in policies:
                continue
            alone = [_timed_runs(tmp, clip, "alone", 1, policy, run_args)[0] for _ in range(repeat)]
            pair = [max(_timed_runs(tmp, clip, "pair", 2, policy, run_args)) for _ in range(repeat)]
            a, b = statistics.median(alone), statistics.median(pair)
            out[name] = {"alone_s": a, "side_by_side_s": b, "ratio": b / a, "alone_all": alone, "pair_all": pair}
            print(f"{name:>15}: alone {a:7.1f} s, two side by side {b:7.1f} s (slower of the two): "
                  f"ratio {b / a:.2f}", file=sys.stderr, flush=True)
    return out


ICL = ROOT.parent / "shared" / "data" / "icl_livingroom1_micro"


def _cold_run(clip: Path, work: Path, extra: list[str], tree: Path = ROOT) -> dict:
    """One cold run in its own process of the code in ``tree`` (this checkout, or a peer's):
    {seconds, stages {name: s}, peak_rss_mb, keyframes, frames}."""
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    cmd = [sys.executable, "-m", "gcvd_flow", "run", str(clip), "--out", str(work / "run"), "--cache",
           str(work / "cache"), "--json", *extra]
    with open(work / "out.json", "w") as fo, open(work / "err.txt", "w") as fe:
        # cwd first on sys.path: ``-m gcvd_flow`` imports the code of ``tree``
        p = subprocess.Popen(cmd, cwd=tree, stdout=fo, stderr=fe, env=dict(os.environ, CI="1"))
        mem = TreeMemory(p.pid)
        _, status, usage = os.wait4(p.pid, 0)  # this child's own peak RSS (KiB on Linux)
        tree_mb = mem.stop()
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit((work / "err.txt").read_text()[-3000:])
    doc = json.loads((work / "out.json").read_text())
    cams = json.loads((work / "run" / "cameras.json").read_text())
    return {"seconds": doc["seconds"], "stages": {s["name"]: s["seconds"] for s in doc["stages"]},
            "peak_rss_mb": usage.ru_maxrss / 1024, "peak_tree_pss_mb": tree_mb, "keyframes": len(cams["keyframes"]),
            "frames": len((work / "run" / "poses.txt").read_text().splitlines())}


def _summary(name: str, runs: list[dict]) -> dict:
    import statistics

    n = runs[0]["frames"]
    med = statistics.median(r["seconds"] for r in runs)
    return {"clip": name, "frames": n, "keyframes": runs[0]["keyframes"],
            "keyframe_share": runs[0]["keyframes"] / n, "total_s_all": [r["seconds"] for r in runs],
            "s_per_frame": med / n, "peak_rss_mb": max(r["peak_rss_mb"] for r in runs),
            "peak_tree_pss_mb": max(r["peak_tree_pss_mb"] for r in runs),
            "stages_s": {k: statistics.median(r["stages"][k] for r in runs) for k in runs[0]["stages"]}}


def _print_row(row: dict, tag: str = "") -> None:
    top = sorted(row["stages_s"].items(), key=lambda kv: -kv[1])[:5]
    print(f"{row['clip']}{tag}: {row['frames']} frames, {row['keyframes']} keyframes "
          f"({100 * row['keyframe_share']:.0f} %), median {row['s_per_frame'] * row['frames']:.1f} s = "
          f"{row['s_per_frame']:.3f} s/frame (runs {', '.join(f'{r:.1f}' for r in row['total_s_all'])} s), "
          f"peak {row['peak_rss_mb']:.0f} MB (with workers {row['peak_tree_pss_mb']:.0f} MB Pss); "
          + ", ".join(f"{k} {v:.1f} s" for k, v in top), file=sys.stderr, flush=True)


def real_clips(repeat: int, peer: Path | None = None, only: str | None = None) -> list[dict]:
    """ICL and the scan, ``repeat`` cold runs each; with ``peer`` (a checkout of another commit)
    each round runs the peer's code and then this checkout's, alternately, so that both see the
    same machine (its speed drifts by tens of percent over an hour here), and reports the ratio
    of the medians."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-real-") as tmp_s:
        tmp = Path(tmp_s)
        scan = tmp / "scan"
        if only != "icl":
            subprocess.run([sys.executable, "-m", "gcvd_flow", "synth", str(scan), "--frames", "200",
                            "--trajectory", "scan", "--size", "640x480"], cwd=ROOT, check=True, capture_output=True)
        clips = (("icl", ICL, ["--intrinsics", "525,525,319.5,239.5"]), ("scan-640x480", scan, []))
        for name, clip, extra in [c for c in clips if only is None or c[0].startswith(only)]:
            runs, peer_runs = [], []
            for r in range(repeat):
                if peer is not None:
                    peer_runs.append(_cold_run(clip, tmp / f"{name}-peer-{r}", extra, peer))
                runs.append(_cold_run(clip, tmp / f"{name}-{r}", extra))
            row = _summary(name, runs)
            if peer is not None:
                row["peer"] = _summary(name, peer_runs)
                row["peer"]["tree"] = str(peer)
                row["ratio_to_peer"] = row["s_per_frame"] / row["peer"]["s_per_frame"]
                _print_row(row["peer"], " (peer)")
            _print_row(row)
            if peer is not None:
                print(f"{name}: this / peer = {row['ratio_to_peer']:.3f}", file=sys.stderr, flush=True)
            rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--side-by-side", type=int, metavar="FRAMES", default=0,
                    help="measure two runs started together vs one alone (load collapse) instead")
    ap.add_argument("--repeat", type=int, default=3, help="rounds for --side-by-side / --real (median)")
    ap.add_argument("--policies", default="passive,openmp_default",
                    help="with --side-by-side: OpenMP idle-thread policies to measure (passive = ours; "
                         "openmp_default = the spinning peer, slow)")
    ap.add_argument("--run-args", default="", help="with --side-by-side: more `gcvd-flow run` options, one string "
                    "(e.g. \"--set optimize_keyframes.pair_blocks=1\")")
    ap.add_argument("--frames", type=int, nargs="+", default=[50, 200, 500, 1000])
    ap.add_argument("--size", default="256x192")
    ap.add_argument("--trajectory", default="loop")
    ap.add_argument("--real", action="store_true",
                    help="the ICL clip and a keyframe-heavy 640x480 scan, --repeat cold runs each, instead")
    ap.add_argument("--peer", type=Path, metavar="CHECKOUT",
                    help="with --real: also time the code of this checkout (e.g. `git worktree add /tmp/peer "
                         "HEAD~1`), alternating runs, and report the ratio")
    ap.add_argument("--only", choices=["icl", "scan"], help="with --real: one of the two clips")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    if a.real:
        doc = real_clips(a.repeat, a.peer.resolve() if a.peer else None, a.only)
        print(json.dumps(doc, indent=1) if a.json else "")
        return
    if a.side_by_side:
        unknown = set(a.policies.split(",")) - {"passive", "openmp_default"}
        if unknown:
            ap.error(f"--policies: unknown {', '.join(sorted(unknown))} (passive, openmp_default)")
        doc = side_by_side(a.side_by_side, a.size, a.trajectory, a.repeat, tuple(a.policies.split(",")),
                           tuple(shlex.split(a.run_args)))
        print(json.dumps(doc, indent=1) if a.json else "")
        return
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-rt-") as tmp:
        for n in a.frames:
            clip = Path(tmp) / f"clip{n}"
            subprocess.run([sys.executable, "-m", "gcvd_flow", "synth", str(clip), "--frames", str(n),
                            "--trajectory", a.trajectory, "--size", a.size], cwd=ROOT, check=True,
                           capture_output=True)
            cmd = [sys.executable, "-m", "gcvd_flow", "run", str(clip), "--out", str(Path(tmp) / f"run{n}"),
                   "--cache", str(Path(tmp) / f"cache{n}"), "--json"]
            out_f, err_f = Path(tmp) / f"out{n}.json", Path(tmp) / f"err{n}.txt"
            with open(out_f, "w") as fo, open(err_f, "w") as fe:
                p = subprocess.Popen(cmd, cwd=ROOT, stdout=fo, stderr=fe, env=dict(os.environ, CI="1"))
                tree = TreeMemory(p.pid)
                # wait4 gives this child's own peak RSS (KiB on Linux)
                _, status, usage = os.wait4(p.pid, 0)
                tree_mb = tree.stop()
            if os.waitstatus_to_exitcode(status) != 0:
                raise SystemExit(err_f.read_text()[-3000:])
            peak_kb = usage.ru_maxrss
            doc = json.loads(out_f.read_text())
            secs = {s["name"]: s["seconds"] for s in doc["stages"]}
            row = {"frames": n, "pre_s_per_frame": sum(secs.get(k, 0.0) for k in PRE) / n,
                   "main_s_per_frame": sum(secs.get(k, 0.0) for k in MAIN) / n,
                   "post_s_per_frame": sum(secs.get(k, 0.0) for k in POST) / n,
                   "total_s_per_frame": doc["seconds"] / n,
                   "peak_rss_mb": peak_kb / 1024, "peak_tree_pss_mb": tree_mb,
                   "stages": secs}
            rows.append(row)
            print(f"{n:5d} frames: pre {row['pre_s_per_frame']:.3f}  main {row['main_s_per_frame']:.3f}  "
                  f"post {row['post_s_per_frame']:.3f}  total {row['total_s_per_frame']:.3f} s/frame  "
                  f"peak {row['peak_rss_mb'] or float('nan'):.0f} MB (with workers {tree_mb:.0f} MB Pss)", file=sys.stderr, flush=True)
    if a.json:
        print(json.dumps(rows, indent=1))
        return
    print(f"\n{'frames':>6} {'pre':>8} {'main':>8} {'post':>8} {'total':>8}  {'peak RSS':>9}   (s per frame, 2 CPU cores)")
    for r in rows:
        pk = f"{r['peak_rss_mb']:.0f} MB" if r["peak_rss_mb"] else "n/a"
        print(f"{r['frames']:6d} {r['pre_s_per_frame']:8.3f} {r['main_s_per_frame']:8.3f} "
              f"{r['post_s_per_frame']:8.3f} {r['total_s_per_frame']:8.3f}  {pk:>9}")


if __name__ == "__main__":
    main()
