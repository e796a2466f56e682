"""Peer comparison: gcvd-flow vs COLMAP (incremental SfM, CPU) on the ICL-NUIM living-room frames.

Both run cold on the same frames (the first ``--frames N`` of ../shared/data/icl_livingroom1_micro,
640x480, intrinsics 525, 525, 319.5, 239.5; or, with ``--data DIR``, of a folder in the generic
layout: ``frames/``, ``intrinsics.txt`` (fx fy cx cy, no distortion) and ``gt/poses.txt``, e.g.
../shared/data/hololens_walk_100_199 or kitti07_first100) and are scored with the project's own metrics
(``gcvd_flow/evaluate/metrics.py``: ATE after Sim(3) Umeyama alignment, RPE over one frame) against the
dataset's ground truth, the same ``*.log`` file ``gcvd-flow eval`` reads.

* gcvd-flow: ``gcvd-flow run DATA --intrinsics ... --cache FRESH --json`` (default profile; for the
  generic layout without ``--intrinsics``: it reads ``intrinsics.txt``), then ``gcvd-flow eval``.
* COLMAP: ``feature_extractor`` (one shared PINHOLE camera with the known intrinsics),
  ``sequential_matcher`` (video order, default overlap 10, loop detection off: it needs a
  vocabulary-tree file), ``mapper`` with the intrinsics fixed, ``model_converter`` of the largest
  model to TXT; all on the CPU with 2 threads. Poses are read from ``images.txt``
  (world-to-camera ``QW QX QY QZ TX TY TZ``) and inverted to camera-to-world; ATE / RPE are over
  the registered frames only, and the table says how many were registered.

Wall time is ``time.perf_counter`` around each whole subprocess (COLMAP: the sum of its four
commands; evaluation is not timed). ``OMP_NUM_THREADS`` and the rest of the environment are
passed through unchanged.

    make bench-peer            # installs Debian's colmap if missing, then runs this on all frames
    .venv/bin/python benchmarks/bench_peer.py --frames 30 [--json] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from gcvd_flow.evaluate.run_eval import load_gt as load_eval_gt, trajectory_metrics  # noqa: E402
from gcvd_flow.exports.colmap import colmap_to_c2w  # noqa: E402
from gcvd_flow.io.formats import read_distortion_txt, read_intrinsics_txt, read_tum_poses, write_tum_poses  # noqa: E402
from gcvd_flow.io.sources import natural_key  # noqa: E402

ICL = ROOT.parent / "shared" / "data" / "icl_livingroom1_micro"
INTRINSICS = "525,525,319.5,239.5"
THREADS = "2"


class BenchError(Exception):
    """A one-line error for the user."""


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def timed(cmd: list[str], log_file: Path, what: str, cwd: Path | None = None) -> tuple[float, str]:
    """Run cmd (environment unchanged), stdout+stderr to log_file; (wall seconds, stdout text)."""
    with open(log_file, "w") as fe:
        t0 = time.perf_counter()
        p = subprocess.run(cmd, cwd=cwd, stdout=subprocess.PIPE, stderr=fe, text=True)
        secs = time.perf_counter() - t0
    with open(log_file, "a") as fe:
        fe.write(p.stdout)
    if p.returncode != 0:
        tail = "".join(log_file.read_text().splitlines(keepends=True)[-30:])
        raise BenchError(f"{what} failed (exit {p.returncode}); last lines of {log_file}:\n{tail}")
    return secs, p.stdout


# ------------------------------------------------------------------------------ input


def data_layout(data: Path) -> tuple[Path, str, bool]:
    """(image folder, COLMAP PINHOLE params "fx,fy,cx,cy", generic?) of an ICL folder (``color/``,
    the fixed INTRINSICS) or a generic-layout one (``frames/`` + ``intrinsics.txt``, read by
    gcvd-flow's own reader; lens distortion is refused: COLMAP gets a PINHOLE camera)."""
    if (data / "color").is_dir():
        return data / "color", INTRINSICS, False
    if (data / "frames").is_dir() and (data / "intrinsics.txt").exists():
        try:
            K = read_intrinsics_txt(data / "intrinsics.txt")
            dist = read_distortion_txt(data / "intrinsics.txt")
        except ValueError as exc:  # DatasetError: one line naming the file
            raise BenchError(str(exc)) from None
        if dist is not None:
            raise BenchError(f"{data / 'intrinsics.txt'}: has lens distortion; this benchmark needs undistorted frames")
        return data / "frames", ",".join(f"{v:.12g}" for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2])), True
    raise BenchError(f"{data}: no color/ folder (ICL-NUIM) and no frames/ + intrinsics.txt (generic layout)")


# ------------------------------------------------------------------------------ evaluation


def load_gt(data: Path) -> np.ndarray:
    """Camera-to-world GT poses by source frame, read as `gcvd-flow eval` reads them."""
    try:
        return np.asarray(load_eval_gt(data)["poses"])
    except ValueError as exc:  # UsageError / DatasetError: one line naming the file
        raise BenchError(str(exc)) from None


def score(frame_idx: list[int], est: np.ndarray, gt_all: np.ndarray) -> dict:
    """ATE (Sim(3)), RPE (delta 1 over consecutive entries), path length: `gcvd-flow eval`'s code."""
    return trajectory_metrics(est, gt_all[frame_idx])


# ------------------------------------------------------------------------------ gcvd-flow


def run_gcvd(data: Path, frames: int, total: int, work: Path, gt_all: np.ndarray, intrinsics: str | None) -> dict:
    """intrinsics: "fx,fy,cx,cy" for --intrinsics, or None (the folder's intrinsics.txt)."""
    run_dir, cache = work / "gcvd-run", work / "gcvd-cache"
    cmd = [sys.executable, "-m", "gcvd_flow", "run", str(data), "--out", str(run_dir), "--cache", str(cache),
           "--json"] + (["--intrinsics", intrinsics] if intrinsics else [])
    if frames < total:
        cmd += ["--set", f"ingest.end={frames}"]
    log(f"gcvd-flow: run on {frames} frames (cold cache {cache})")
    secs, out = timed(cmd, work / "gcvd-run.log", "gcvd-flow run", cwd=ROOT)
    run_doc = json.loads(out)
    _, ev = timed([sys.executable, "-m", "gcvd_flow", "eval", str(run_dir), "--gt", str(data), "--json"],
                  work / "gcvd-eval.log", "gcvd-flow eval", cwd=ROOT)
    m = json.loads(ev)
    stamps, est = read_tum_poses(run_dir / "poses.txt")
    registered = len(stamps)
    # Score gcvd-flow's poses again with the function used for COLMAP: the two paths must agree.
    mine = score([int(round(t)) for t in stamps], est, gt_all)
    if not np.isclose(mine["ate_rmse"], m["ate_rmse"], rtol=1e-6, atol=1e-9):
        raise BenchError(f"internal: ATE of gcvd-flow's poses differs between `gcvd-flow eval` "
                         f"({m['ate_rmse']}) and this script ({mine['ate_rmse']})")
    log(f"gcvd-flow: {secs:.1f} s, ATE {m['ate_rmse']:.4f} m")
    return {"method": "gcvd-flow", "frames": frames, "registered": registered, "ate_rmse": m["ate_rmse"],
            "ate_percent_of_path": m["ate_percent_of_path"], "rpe_trans": m["rpe_trans"], "rpe_rot": m["rpe_rot"],
            "scale": m["scale"], "path_length": m["path_length"], "abs_rel": m.get("abs_rel"),
            "delta1": m.get("delta1"), "seconds": secs, "seconds_per_frame": secs / frames,
            "stage_seconds": {s["name"]: s["seconds"] for s in run_doc.get("stages", [])},
            "settings": "default profile, 256 px long side, DIS flow, weight-free priors; "
                        + (f"--intrinsics {intrinsics}" if intrinsics else "intrinsics.txt") + ", fresh cache",
            "poses": str(run_dir / "poses.txt")}


# ------------------------------------------------------------------------------ COLMAP


def num_registered_bin(model: Path) -> int:
    """Registered images of a binary COLMAP model: images.bin starts with a uint64 count."""
    with open(model / "images.bin", "rb") as f:
        return struct.unpack("<Q", f.read(8))[0]


def parse_images_txt(path: Path) -> tuple[list[int], np.ndarray]:
    """COLMAP images.txt -> (source frame indices, camera-to-world (N, 4, 4)), sorted by frame.

    Each image takes two lines (the second, its 2D points, may be empty):
    IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, world-to-camera x_c = R(q) x_w + t.
    """
    lines = [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]
    recs = []
    for ln in lines[0::2]:
        tok = ln.split()
        if len(tok) != 10:
            raise BenchError(f"{path}: unexpected image line {ln[:80]!r}")
        vals = np.array([float(v) for v in tok[1:8]])
        recs.append((int(Path(tok[9]).stem), colmap_to_c2w(vals[:4], vals[4:])[0]))
    recs.sort(key=lambda r: r[0])
    return [r[0] for r in recs], np.array([r[1] for r in recs]).reshape(-1, 4, 4)


def colmap_version(colmap: str) -> str:
    p = subprocess.run([colmap, "-h"], capture_output=True, text=True)
    first = (p.stdout or p.stderr).strip().splitlines()
    return first[0] if first else "unknown"


def run_colmap(colmap: str, image_dir: Path, intrinsics: str, names: list[str], work: Path, overlap: int) -> dict:
    """COLMAP's four commands on ``names`` in image_dir, one PINHOLE camera "fx,fy,cx,cy" = intrinsics."""
    cw = work / "colmap"
    cw.mkdir()
    db, sparse, txt = cw / "database.db", cw / "sparse", cw / "txt"
    sparse.mkdir()
    image_list = cw / "images.list"
    image_list.write_text("\n".join(names) + "\n")
    steps: dict[str, float] = {}
    log(f"colmap: feature_extractor on {len(names)} frames")
    steps["feature_extractor"], _ = timed(
        [colmap, "feature_extractor", "--database_path", str(db), "--image_path", str(image_dir),
         "--image_list_path", str(image_list), "--ImageReader.single_camera", "1",
         "--ImageReader.camera_model", "PINHOLE", "--ImageReader.camera_params", intrinsics,
         "--SiftExtraction.use_gpu", "0", "--SiftExtraction.num_threads", THREADS],
        cw / "feature_extractor.log", "colmap feature_extractor")
    log(f"colmap: sequential_matcher (overlap {overlap}) [{steps['feature_extractor']:.0f} s so far]")
    steps["sequential_matcher"], _ = timed(
        [colmap, "sequential_matcher", "--database_path", str(db), "--SiftMatching.use_gpu", "0",
         "--SiftMatching.num_threads", THREADS, "--SequentialMatching.overlap", str(overlap),
         "--SequentialMatching.loop_detection", "0"],
        cw / "sequential_matcher.log", "colmap sequential_matcher")
    log(f"colmap: mapper [{sum(steps.values()):.0f} s so far]")
    steps["mapper"], _ = timed(
        [colmap, "mapper", "--database_path", str(db), "--image_path", str(image_dir), "--output_path", str(sparse),
         "--Mapper.ba_refine_focal_length", "0", "--Mapper.ba_refine_principal_point", "0",
         "--Mapper.ba_refine_extra_params", "0", "--Mapper.num_threads", THREADS],
        cw / "mapper.log", "colmap mapper")
    models = [m for m in sorted(sparse.iterdir(), key=lambda p: natural_key(p.name)) if (m / "images.bin").exists()]
    if not models:
        raise BenchError(f"colmap mapper reconstructed no model (see {cw / 'mapper.log'})")
    sizes = {m.name: num_registered_bin(m) for m in models}
    best = max(models, key=lambda m: sizes[m.name])
    txt.mkdir()
    steps["model_converter"], _ = timed(
        [colmap, "model_converter", "--input_path", str(best), "--output_path", str(txt), "--output_type", "TXT"],
        cw / "model_converter.log", "colmap model_converter")
    idx, c2w = parse_images_txt(txt / "images.txt")
    if len(idx) < 3:
        raise BenchError(f"colmap registered only {len(idx)} frames in its largest model: too few to align")
    poses_txt = cw / "poses.txt"
    write_tum_poses(poses_txt, np.array(idx, np.float64), c2w)
    secs = sum(steps.values())
    log(f"colmap: {secs:.1f} s, {len(idx)}/{len(names)} frames registered in model {best.name} "
        f"(models: {sizes})")
    gaps = int(np.sum(np.diff(idx) > 1))
    return {"method": "colmap", "frames": len(names), "registered": len(idx), "frame_idx": idx, "c2w": c2w,
            "seconds": secs, "seconds_per_frame": secs / len(names), "step_seconds": steps,
            "models": sizes, "gaps_in_registered": gaps, "version": colmap_version(colmap),
            "settings": "SIFT (CPU, max 8192 features, 3200 px), single PINHOLE camera "
                        f"{intrinsics}, sequential_matcher overlap {overlap} (quadratic), no loop detection, "
                        "mapper with focal length / principal point / extra params fixed, 2 threads",
            "poses": str(poses_txt)}


# ------------------------------------------------------------------------------ main


def fmt(v, spec: str) -> str:
    return format(v, spec) if isinstance(v, (int, float)) and v == v else "n/a"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=None, help="first N frames (default: all)")
    ap.add_argument("--data", type=Path, default=ICL, help="ICL-NUIM/Redwood folder (color/, *.log) or "
                    "generic layout (frames/, intrinsics.txt, gt/poses.txt)")
    ap.add_argument("--overlap", type=int, default=10, help="COLMAP SequentialMatching.overlap (default 10)")
    ap.add_argument("--colmap", default="colmap", help="COLMAP executable (default: colmap on PATH)")
    ap.add_argument("--out", type=Path, help="keep the work folder (runs, COLMAP model, logs, rows.json) here "
                    "(default: a temporary one)")
    ap.add_argument("--json", action="store_true", help="print the rows as JSON")
    a = ap.parse_args()

    colmap = shutil.which(a.colmap)
    if colmap is None:
        raise BenchError(f"{a.colmap}: not found on PATH; `make bench-peer` installs it (Debian package colmap)")
    data = a.data.resolve()
    image_dir, intrinsics, generic = data_layout(data)
    names = sorted((p.name for p in image_dir.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png")),
                   key=natural_key)
    total = len(names)
    frames = total if a.frames is None else a.frames
    if not 3 <= frames <= total:
        raise BenchError(f"--frames must be in [3, {total}], got {frames}")
    names = names[:frames]
    gt_all = load_gt(data)
    if len(gt_all) < frames:
        raise BenchError(f"{data}: ground truth has {len(gt_all)} poses for {frames} frames")

    if a.out:
        if a.out.exists() and any(a.out.iterdir()):
            raise BenchError(f"{a.out}: exists and is not empty (the benchmark runs cold)")
        a.out.mkdir(parents=True, exist_ok=True)
        tmp = None
        work = a.out.resolve()
    else:
        tmp = tempfile.TemporaryDirectory(prefix="bench-peer-")
        work = Path(tmp.name)
    try:
        g = run_gcvd(data, frames, total, work, gt_all, None if generic else intrinsics)
        c = run_colmap(colmap, image_dir, intrinsics, names, work, a.overlap)
    finally:
        if tmp is not None:
            tmp.cleanup()

    cm = score(c.pop("frame_idx"), c.pop("c2w"), gt_all)
    c.update({k: cm[k] for k in ("ate_rmse", "ate_percent_of_path", "rpe_trans", "rpe_rot", "scale", "path_length")})
    for row in (g, c):
        row["time_ratio_vs_gcvd_flow"] = row["seconds"] / g["seconds"]
        if tmp is not None:
            row.pop("poses", None)
    rows = [g, c]
    if tmp is None:
        (work / "rows.json").write_text(json.dumps(rows, indent=1) + "\n")

    if a.json:
        print(json.dumps(rows, indent=1))
        return 0
    print(f"\n{data.name}, {frames} frames, 2 CPU cores "
          f"(ATE after Sim(3) alignment over the registered frames)\n")
    print(f"{'method':<10} {'registered':>10} {'ATE[m]':>8} {'ATE%path':>9} {'RPEt[m]':>8} {'RPEr[deg]':>9} "
          f"{'wall[s]':>8} {'s/frame':>8} {'time/gcvd':>9}")
    for r in rows:
        print(f"{r['method']:<10} {str(r['registered']) + '/' + str(r['frames']):>10} {fmt(r['ate_rmse'], '8.4f')} "
              f"{fmt(r['ate_percent_of_path'], '9.2f')} {fmt(r['rpe_trans'], '8.4f')} {fmt(r['rpe_rot'], '9.3f')} "
              f"{r['seconds']:8.1f} {r['seconds_per_frame']:8.2f} {r['time_ratio_vs_gcvd_flow']:8.1f}x")
    steps = ", ".join(f"{k} {v:.1f} s" for k, v in c["step_seconds"].items())
    print(f"\ncolmap / gcvd-flow time: {c['time_ratio_vs_gcvd_flow']:.1f}x   (COLMAP: {steps})")
    if c["registered"] < frames or c["gaps_in_registered"]:
        print(f"note: COLMAP registered {c['registered']} of {frames} frames ({c['gaps_in_registered']} gaps); "
              "its ATE/RPE cover only those (RPE pairs span the gaps)")
    return 0


def _terminated(signum, frame):  # SIGTERM: unwind so the temporary work folder is removed
    raise KeyboardInterrupt


if __name__ == "__main__":
    signal.signal(signal.SIGTERM, _terminated)
    try:
        sys.exit(main())
    except BenchError as e:
        print(f"bench-peer: {e}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        sys.exit(130)
