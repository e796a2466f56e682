"""Loop-closure retrieval against ground-truth revisits (issue 28 item 1).

For a finished run on a clip in the generic layout with ground-truth poses and depth
(``frames/``, ``intrinsics.txt``, ``gt/poses.txt``, ``gt/depth/``), e.g. the HoloLens walk-through:

    python -m gcvd_flow run /work/shared/data/hololens_walk_100_199 --out R --cache C
    python benchmarks/bench_retrieval.py R /work/shared/data/hololens_walk_100_199 [--json]

reports, over the run's keyframes (``gcvd_flow/evaluate/revisits.py`` defines the revisits):
- recall of the association's candidates (verified + rejected, i.e. at its candidate budget
  ``association.max_candidates``) over the revisit pairs: keyframe pairs more than 15 frames and
  more than ``association.min_separation`` keyframes apart that share >= 30 % of their
  ground-truth depth points (both ways), and over the previous round's definition (camera
  centres within 0.5 m, optical axes within 30 deg);
- precision of the verified loop edges: verified pairs whose views share >= 10 % of their depth
  points (any distance in time) over all verified;
- loop edges found / verified / used (kept by ``association.loop_nms`` and not rejected by the
  pose graph), and how many of the kept ones are revisit pairs.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def measure(run_dir: Path, data: Path, min_frames: int = 15, min_overlap: float = 0.3,
            true_overlap: float = 0.1) -> dict:
    from bench_accuracy import loop_counts

    from gcvd_flow.engine.store import Store
    from gcvd_flow.evaluate import revisits
    from gcvd_flow.io.formats import read_generic_layout
    from gcvd_flow.report.collect import recorded_part

    doc = json.loads((run_dir / "run.json").read_text())
    store = Store(Path(doc["cache"]), verify=False)
    kfs = [int(i) for i in recorded_part(doc, store, "keyframes", ("indices",))]
    graph = recorded_part(doc, store, "association", ("graph",))
    sep = int(doc["config"]["association"]["min_separation"])
    lay = read_generic_layout(data)
    if lay.poses is None or lay.depth is None:
        raise SystemExit(f"{data}: needs gt/poses.txt and gt/depth/")
    depths = [lay.depth[i] if i in set(kfs) else None for i in range(len(lay.poses))]
    rev = revisits.revisit_pairs(kfs, lay.poses, depths, lay.K, min_frames=min_frames, min_separation=sep,
                                 min_overlap=min_overlap)
    pose_rev = revisits.pose_revisit_pairs(kfs, lay.poses, min_frames=min_frames, min_separation=sep)
    true = revisits.revisit_pairs(kfs, lay.poses, depths, lay.K, min_frames=0, min_separation=0,
                                  min_overlap=true_overlap)
    kept = [(e["i"], e["j"]) for e in graph.get("nonsequential_edges", [])]
    verified = kept + [(e["i"], e["j"]) for e in graph.get("suppressed", [])]
    cands = verified + [(e["i"], e["j"]) for e in graph.get("rejected", [])]
    out = {"run": str(run_dir), "keyframes": len(kfs), "retrieval": graph.get("retrieval", "global"),
           "overlap": revisits.retrieval_report(rev, cands, verified, true),
           "pose": revisits.retrieval_report(pose_rev, cands, verified, true),
           "kept": len(kept), "kept_revisits": len(set(kept) & set(rev)), "kept_pose_revisits": len(set(kept) & pose_rev)}
    out.update(loop_counts(run_dir))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("data", type=Path)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    m = measure(a.run, a.data)
    if a.json:
        print(json.dumps(m, indent=1))
        return
    for name in ("overlap", "pose"):
        r = m[name]
        print(f"{name:8s} revisits {r['revisits']:3d}  candidates {r['candidates']:3d}  found {r['found']:3d} "
              f"(recall {r['recall'] if r['recall'] is None else round(r['recall'], 3)})  verified {r['verified']:3d} "
              f"(of them revisits {r['verified_revisits']}, precision {r['precision']})  false {r['false_verified']}")
    print(f"loops found / verified / used: {m['loops_found']} / {m['loops_verified']} / {m['loops_used']}  "
          f"(kept {m['kept']}: revisits {m['kept_revisits']}, pose revisits {m['kept_pose_revisits']})")


if __name__ == "__main__":
    main()
