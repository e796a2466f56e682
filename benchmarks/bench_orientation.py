"""The same footage turned by quarter turns: how much of a real clip's row is the footage, how much chance.

A clip turned by 90, 180 or 270 degrees (portrait, upside down) holds the same images, motion and
scene. A method that does not care which way up the camera is held scores the same on each within
its numeric noise; the spread of the four rows is a measure of how chaotic the clip's result is
(on the HoloLens walk: 5.4-12.8 cm, 2026-11-29, docs/benchmarks.md "Accuracy"), a sample of four
that costs no new footage. Each turned clip gets its frames, its intrinsics (fx, fy swapped and the
principal point moved where the turn sends it), its ground-truth poses (the camera's axes turned
about its optical axis: R_new = R_old M) and its ground-truth depth turned alike.

    .venv/bin/python benchmarks/bench_orientation.py CLIP [--turns 0,1,2,3] [--work DIR] [--cache DIR]
        [--set k=v ...] [--json]

CLIP: the generic layout (frames/*.png, intrinsics.txt ``fx fy cx cy``, gt/poses.txt in TUM
format, optional gt/depth/*.png). Every run is a full `gcvd-flow run` + `eval --gt`, one after
the other, sharing one cache.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import cv2  # noqa: E402

from gcvd_flow.io.formats import read_tum_poses, write_tum_poses  # noqa: E402

# cv2.rotate codes for 1, 2, 3 quarter turns clockwise
_CODES = {1: cv2.ROTATE_90_CLOCKWISE, 2: cv2.ROTATE_180, 3: cv2.ROTATE_90_COUNTERCLOCKWISE}


def turn_pixel(u: np.ndarray, v: np.ndarray, w: int, h: int, turns: int) -> tuple[np.ndarray, np.ndarray]:
    """Where pixel (u, v) of a w x h image lands after ``turns`` quarter turns clockwise (pixel
    centres at integers, as cv2.rotate moves them)."""
    turns %= 4
    if turns == 0:
        return u, v
    if turns == 1:
        return h - 1 - v, u
    if turns == 2:
        return w - 1 - u, h - 1 - v
    return v, w - 1 - u


def turned_intrinsics(fx: float, fy: float, cx: float, cy: float, w: int, h: int, turns: int) -> tuple[float, ...]:
    """fx, fy, cx, cy of the turned image (turn_pixel of the principal point; axes swapped on odd turns)."""
    cu, cv_ = turn_pixel(np.float64(cx), np.float64(cy), w, h, turns)
    if turns % 2:
        return fy, fx, float(cu), float(cv_)
    return fx, fy, float(cu), float(cv_)


def camera_turn(turns: int) -> np.ndarray:
    """M (3, 3) with p_old = M p_new: a point's coordinates in the original camera from those in
    the turned one (x right, y down, z forward; the turn is about z). Camera-to-world rotations
    become R_old M."""
    turns %= 4
    c = [np.eye(3), np.array([[0, 1, 0], [-1, 0, 0], [0, 0, 1.0]]),
         np.diag([-1.0, -1.0, 1.0]), np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])]
    return c[turns]


def turn_clip(src: Path, dst: Path, turns: int) -> Path:
    """Write ``src`` (generic layout with gt/) turned by ``turns`` quarter turns clockwise to ``dst``."""
    if turns % 4 == 0:
        return src
    code = _CODES[turns % 4]
    size = None  # (h, w) of the source frames
    for sub in ("frames", "gt/depth"):
        if not (src / sub).is_dir():
            continue
        (dst / sub).mkdir(parents=True, exist_ok=True)
        for f in sorted((src / sub).glob("*.png")):
            img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise SystemExit(f"bench_orientation: cannot read {f}")
            size = size or img.shape[:2]
            cv2.imwrite(str(dst / sub / f.name), cv2.rotate(img, code))
    if size is None:
        raise SystemExit(f"bench_orientation: no frames in {src / 'frames'}")
    h, w = size
    fx, fy, cx, cy = (float(x) for x in (src / "intrinsics.txt").read_text().split()[:4])
    (dst / "intrinsics.txt").write_text(" ".join(f"{x:.6f}" for x in turned_intrinsics(fx, fy, cx, cy, w, h, turns)) + "\n")
    stamps, poses = read_tum_poses(src / "gt" / "poses.txt")
    poses[:, :3, :3] = poses[:, :3, :3] @ camera_turn(turns)
    write_tum_poses(dst / "gt" / "poses.txt", stamps, poses)
    return dst


def gcvd(*args: str) -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "CI": "1"}
    p = subprocess.run([sys.executable, "-m", "gcvd_flow", *args, "--json"], cwd=ROOT, env=env,
                       capture_output=True, text=True)
    if p.returncode != 0:
        raise SystemExit(f"bench_orientation: gcvd-flow {args[0]} failed: {p.stderr.strip().splitlines()[-1:]}")
    return json.loads(p.stdout)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("clip", type=Path)
    ap.add_argument("--turns", default="0,1,2,3", help="quarter turns clockwise to run (comma-separated)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_orientation"))
    ap.add_argument("--cache", default=os.environ.get("GCVD_FLOW_CACHE", str(Path.home() / ".cache" / "gcvd-flow")))
    ap.add_argument("--set", action="append", default=[], metavar="K=V")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    rows = []
    for turns in (int(t) for t in a.turns.split(",")):
        clip = turn_clip(a.clip, a.work / f"clip-{turns}", turns)
        out = a.work / f"run-{turns}"
        sets = [x for kv in a.set for x in ("--set", kv)]
        gcvd("run", str(clip), "--out", str(out), "--cache", a.cache, *sets)
        m = gcvd("eval", str(out), "--gt", str(clip))
        rows.append({"turns": turns, "ate_m": m["ate_rmse"], "abs_rel": m.get("abs_rel"),
                     "scale_window": [m.get("scale_window_min"), m.get("scale_window_max")],
                     "rpe_trans_m": m.get("rpe_trans"), "rpe_rot_deg": m.get("rpe_rot")})
        if not a.json:
            r = rows[-1]
            ar = "-" if r["abs_rel"] is None else f"{r['abs_rel']:.4f}"
            print(f"{90 * turns:3d} deg: ATE {r['ate_m']:.4f} m  AbsRel {ar}  window scales "
                  f"{r['scale_window'][0]:.3f}-{r['scale_window'][1]:.3f}  RPE {r['rpe_trans_m']:.4f} m "
                  f"{r['rpe_rot_deg']:.3f} deg", flush=True)
    ate = np.array([r["ate_m"] for r in rows])
    summary = {"ate_mean_m": float(ate.mean()), "ate_min_m": float(ate.min()), "ate_max_m": float(ate.max())}
    if all(r["abs_rel"] is not None for r in rows):
        summary["abs_rel_mean"] = float(np.mean([r["abs_rel"] for r in rows]))
    if a.json:
        print(json.dumps({"rows": rows, **summary}, indent=1))
    else:
        print(f"ATE mean {summary['ate_mean_m']:.4f} m ({summary['ate_min_m']:.4f}-{summary['ate_max_m']:.4f})"
              + (f", AbsRel mean {summary['abs_rel_mean']:.4f}" if "abs_rel_mean" in summary else ""))


if __name__ == "__main__":
    main()
