"""Focal self-calibration alone (stages/frontend/calibrate.estimate_focal) on a folder's frames.

    PYTHONPATH=. python benchmarks/bench_calibrate.py DIR TRUE_FX [--long-side 256] [--set key=value ...]

DIR: a generic (``frames/``), Redwood/ICL (``color/``) folder or any folder of images. The frames
are loaded at the working resolution as ``ingest`` does (``long_side``, area resampling), the guess
is f = 300/384 x long side at the image centre (what a run without intrinsics starts from), and one
JSON line is printed: the estimate at the source resolution, its error against TRUE_FX, rel_sigma
and its terms (blocks / principal point / formal), forward_share, whether it is determined, the
work proxies (frames, points, tracks, LM iterations) and the seconds (contaminated on a shared
machine). ``--set`` passes estimate_focal keyword arguments (e.g. ``tracks_per_frame=100``).
Numbers of docs/benchmarks.md ("Issue 27, second round") come from this script.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

from stages.frontend import calibrate
from stages.frontend.ingest import prepare_frame, working_size

EXTS = {".png", ".jpg", ".jpeg"}


def load(folder: Path, long_side: int) -> tuple[list[np.ndarray], tuple[int, int], tuple[int, int]]:
    """Frames (N x uint8 (H, W, 3) RGB at working resolution), source (w, h), working (W, H)."""
    d = next((folder / s for s in ("frames", "color") if (folder / s).is_dir()), folder)
    files = sorted(p for p in d.iterdir() if p.suffix.lower() in EXTS)
    ims, src, work = [], (0, 0), (0, 0)
    for f in files:
        im = cv2.imread(str(f), cv2.IMREAD_COLOR)[:, :, ::-1]
        src = (im.shape[1], im.shape[0])
        work = working_size(src[0], src[1], long_side)
        ims.append(prepare_frame(im, work))
    return ims, src, work


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("true_fx", type=float, help="the true fx at the source resolution (px)")
    ap.add_argument("--long-side", type=int, default=256)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    a = ap.parse_args()
    ims, (w, _), (W, H) = load(a.folder, a.long_side)
    s = W / w
    f0 = 300 / 384 * max(W, H)
    K = np.array([[f0, 0, (W - 1) / 2], [0, f0, (H - 1) / 2], [0, 0, 1.0]])
    kw = {k: (float(v) if "." in v else int(v)) for k, v in (item.split("=", 1) for item in a.set)}
    t = time.time()
    res = calibrate.estimate_focal(ims, K, **kw)
    f = res.get("estimate", res["focal"]) / s
    out = {k: v for k, v in res.items() if isinstance(v, (int, float, str, bool))}
    out.update(f_source=f, error_pct=100 * (f / a.true_fx - 1), seconds=round(time.time() - t, 1),
               n=len(ims), size=[W, H])
    print(json.dumps(out))


if __name__ == "__main__":
    main()
