"""Cost against a reference commit (issue 38): this checkout's code and one or more other
checkouts' run alternately, round by round, on the real clips in ../shared/data (ICL living
room, the HoloLens walk, KITTI 07), each run cold in a fresh cache and its own process.

Per run: wall seconds, per-stage seconds, the share of the wall time with both cores busy
(/proc/stat sampled every 0.2 s: an interval counts when every core was >= 90 % busy; machine-
wide, so it means something only when nothing else runs: use ``cpu-slot --exclusive``), the run's
own CPU seconds over wall (mean cores the run and its workers kept busy), and peak memory (the
run's own max RSS, and the peak of the summed Pss of the run and all its worker processes).
Per clip: the ratio of this code's median wall time to each reference's.

    make bench-cost                      # this code vs 5261f0f (REF) and aaaa9c0 (ALSO)
    .venv/bin/python benchmarks/bench_cost.py --ref /work/wt/ref-5261f0f --also /work/wt/ref-aaaa9c0 \
        --clips icl,holo,kitti --repeat 1

A reference is a checkout (``git worktree add --detach DIR COMMIT``); it needs no venv of its
own: the run uses this interpreter with PYTHONPATH (and the working directory) set to the
checkout, so its code, not this one, is imported.
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
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT.parent / "shared" / "data"
CLIPS = {
    "icl": (DATA / "icl_livingroom1_micro", ["--intrinsics", "525,525,319.5,239.5"]),
    "holo": (DATA / "hololens_walk_100_199", []),
    "kitti": (DATA / "kitti07_first100", []),
}
BUSY = 0.9  # a core counts as busy over a sample interval when >= 90 % of its ticks were not idle


def _cpu_ticks() -> list[tuple[int, int]]:
    """(busy, total) jiffies of each core, from /proc/stat."""
    out = []
    for line in open("/proc/stat"):
        if line.startswith("cpu") and line[3].isdigit():
            v = [int(x) for x in line.split()[1:]]
            idle = v[3] + (v[4] if len(v) > 4 else 0)
            out.append((sum(v) - idle, sum(v)))
    return out


def _tree(root: int) -> list[int]:
    """root and all its descendants (the map stages' workers are children of a forkserver)."""
    children: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                ppid = int(open(f"/proc/{d}/stat").read().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(d))
    out, todo = [], [root]
    while todo:
        p = todo.pop()
        out.append(p)
        todo.extend(children.get(p, []))
    return out


class Sampler:
    """Every 0.2 s: the summed Pss of the process tree (peak kept), each process's CPU ticks
    (utime + stime, the last value seen per pid, summed at the end) and whether all cores were
    busy over the interval."""

    def __init__(self, pid: int, period: float = 0.2) -> None:
        self.pid, self.period = pid, period
        self.peak_kb = 0
        self.cpu_ticks: dict[int, int] = {}
        self.intervals = self.all_busy = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _sample_tree(self) -> None:
        total = 0
        for p in _tree(self.pid):
            try:
                f = open(f"/proc/{p}/stat").read().rsplit(")", 1)[1].split()
                self.cpu_ticks[p] = int(f[11]) + int(f[12])  # utime, stime (fields 14, 15)
                for line in open(f"/proc/{p}/smaps_rollup"):
                    if line.startswith("Pss:"):
                        total += int(line.split()[1])
                        break
            except (OSError, IndexError, ValueError):
                pass
        self.peak_kb = max(self.peak_kb, total)

    def _run(self) -> None:
        prev = _cpu_ticks()
        while not self._stop.wait(self.period):
            self._sample_tree()
            cur = _cpu_ticks()
            fr = [(b1 - b0) / (t1 - t0) if t1 > t0 else 0.0 for (b0, t0), (b1, t1) in zip(prev, cur, strict=True)]
            prev = cur
            self.intervals += 1
            self.all_busy += all(f >= BUSY for f in fr)

    def stop(self) -> dict:
        self._stop.set()
        self._thread.join()
        hz = os.sysconf("SC_CLK_TCK")
        return {"peak_tree_pss_mb": self.peak_kb / 1024, "tree_cpu_s": sum(self.cpu_ticks.values()) / hz,
                "both_cores_busy_share": self.all_busy / max(self.intervals, 1)}


def cold_run(tree: Path, clip: Path, extra: list[str], work: Path) -> dict:
    """One cold run (fresh cache) of the code of checkout ``tree`` on ``clip``."""
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    cmd = [sys.executable, "-m", "gcvd_flow", "run", str(clip), "--out", str(work / "run"), "--cache",
           str(work / "cache"), "--json", *extra]
    env = dict(os.environ, CI="1", PYTHONPATH=str(tree))
    env.pop("GCVD_FLOW_CACHE", None)
    t0 = time.perf_counter()
    with open(work / "out.json", "w") as fo, open(work / "err.txt", "w") as fe:
        p = subprocess.Popen(cmd, cwd=tree, stdout=fo, stderr=fe, env=env)
        s = Sampler(p.pid)
        _, status, usage = os.wait4(p.pid, 0)
        wall = time.perf_counter() - t0
        m = s.stop()
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{tree}: run of {clip} failed:\n" + (work / "err.txt").read_text()[-3000:])
    doc = json.loads((work / "out.json").read_text())
    # workers that exited between two samples are missing from tree_cpu_s; the run's own
    # rusage counts every child it waited for: keep the larger
    own = usage.ru_utime + usage.ru_stime
    cpu = max(m["tree_cpu_s"], own)
    return {"wall_s": wall, "seconds": doc["seconds"], "stages": {st["name"]: st["seconds"] for st in doc["stages"]},
            "peak_rss_mb": usage.ru_maxrss / 1024, "peak_tree_pss_mb": m["peak_tree_pss_mb"],
            "cpu_s": cpu, "cores_used": cpu / wall, "both_cores_busy_share": m["both_cores_busy_share"]}


def summary(runs: list[dict]) -> dict:
    med = statistics.median
    return {"wall_s": med(r["wall_s"] for r in runs), "wall_all": [round(r["wall_s"], 1) for r in runs],
            "stages": {k: med(r["stages"].get(k, 0.0) for r in runs) for k in runs[0]["stages"]},
            "peak_rss_mb": max(r["peak_rss_mb"] for r in runs),
            "peak_tree_pss_mb": max(r["peak_tree_pss_mb"] for r in runs),
            "cores_used": med(r["cores_used"] for r in runs),
            "both_cores_busy_share": med(r["both_cores_busy_share"] for r in runs)}


def print_clip(name: str, trees: dict[str, Path], rows: dict[str, dict]) -> None:
    p = lambda *a: print(*a, file=sys.stderr, flush=True)  # noqa: E731
    p(f"\n== {name}")
    stages = sorted(rows["this"]["stages"], key=lambda k: -rows["this"]["stages"][k])
    p(f"{'stage':<22}" + "".join(f"{t:>14}" for t in trees))
    for st in stages:
        p(f"{st:<22}" + "".join(f"{rows[t]['stages'].get(st, 0.0):14.1f}" for t in trees))
    for key, fmt in (("wall_s", "{:14.1f}"), ("cores_used", "{:14.2f}"), ("both_cores_busy_share", "{:14.2f}"),
                     ("peak_rss_mb", "{:14.0f}"), ("peak_tree_pss_mb", "{:14.0f}")):
        p(f"{key:<22}" + "".join(fmt.format(rows[t][key]) for t in trees))
    for t in trees:
        if t != "this":
            p(f"{name}: this / {t} = {rows['this']['wall_s'] / rows[t]['wall_s']:.3f} (wall, median of "
              f"{len(rows['this']['wall_all'])})")


def round_order(trees: dict[str, Path], r: int) -> list[tuple[str, Path]]:
    """The checkouts in round r's order: as given in even rounds, reversed in odd ones (ABC, CBA):
    with one fixed order "this" always ran last, and a machine drifting over a round fell on it."""
    items = list(trees.items())
    return items if r % 2 == 0 else items[::-1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ref", type=Path, default=Path("/work/wt/ref-5261f0f"),
                    help="checkout of the reference commit (git worktree add --detach DIR 5261f0f)")
    ap.add_argument("--also", type=Path, action="append", default=[],
                    help="another checkout to time in the same rounds (repeatable), e.g. today's main")
    ap.add_argument("--clips", default="icl,holo,kitti", help=f"comma-separated, of {','.join(CLIPS)}")
    ap.add_argument("--repeat", type=int, default=1, help="alternating rounds per clip (median)")
    ap.add_argument("--set", dest="sets", action="append", default=[],
                    help="a --set KEY=VALUE for every run (e.g. ingest.end=20 for a quick check)")
    ap.add_argument("--this-set", dest="this_sets", action="append", default=[],
                    help="a --set KEY=VALUE for this code's runs only (to time an option)")
    ap.add_argument("--keep", type=Path, metavar="DIR",
                    help="keep this code's last run dir of each clip as DIR/<clip> (for `gcvd-flow eval`)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    names = a.clips.split(",")
    if bad := [c for c in names if c not in CLIPS]:
        ap.error(f"--clips: unknown {', '.join(bad)} (of {', '.join(CLIPS)})")
    trees = {"ref": a.ref.resolve(), **{f"also{k}": t.resolve() for k, t in enumerate(a.also)}, "this": ROOT}
    for t, d in trees.items():
        if not (d / "gcvd_flow").is_dir():
            ap.error(f"--{t}: {d} is not a gcvd-flow checkout")
    out = {"trees": {t: str(d) for t, d in trees.items()}, "clips": {}}
    with tempfile.TemporaryDirectory(prefix="bench-cost-") as tmp:
        for name in names:
            clip, extra = CLIPS[name]
            runs: dict[str, list[dict]] = {t: [] for t in trees}
            for r in range(a.repeat):
                for t, d in round_order(trees, r):
                    sets = a.sets + (a.this_sets if t == "this" else [])
                    x = extra + [v for s in sets for v in ("--set", s)]
                    runs[t].append(cold_run(d, clip, x, Path(tmp) / f"{name}-{t}-{r}"))
                    print(f"{name} round {r} {t}: {runs[t][-1]['wall_s']:.1f} s", file=sys.stderr, flush=True)
            if a.keep is not None:  # the run dir (not its cache): what `gcvd-flow eval --gt` scores
                shutil.rmtree(a.keep / name, ignore_errors=True)
                shutil.copytree(Path(tmp) / f"{name}-this-{a.repeat - 1}" / "run", a.keep / name)
            rows = {t: summary(v) for t, v in runs.items()}
            print_clip(name, trees, rows)
            out["clips"][name] = rows
    if a.json:
        print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
