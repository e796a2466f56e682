"""Focal self-calibration alone (stages/frontend/calibrate.estimate_focal) on a folder's frames.

    PYTHONPATH=. python benchmarks/bench_calibrate.py DIR TRUE_FX [--true-pp CX,CY] [--long-side 256] [--set key=value ...]

DIR: a generic (``frames/``), Redwood/ICL (``color/``) folder or any folder of images. The frames
are loaded at the working resolution as ``ingest`` does (``long_side``, area resampling), the guess
is f = 300/384 x long side at the image centre (what a run without intrinsics starts from), and one
JSON line is printed: the estimate at the source resolution, its error against TRUE_FX, rel_sigma
and its terms (blocks / principal point / formal), forward_share, whether it is determined, the
work proxies (frames, points, tracks, LM iterations) and the seconds (contaminated on a shared
machine). ``--set`` passes estimate_focal keyword arguments (e.g. ``tracks_per_frame=100``,
``principal_point=centre``, ``starts=1.0,``). The principal point the stage ends with (``pp_source``: estimated or the centre)
and its estimate (``pp_estimate_source``, std ``pp_sigma_source``) at the source resolution; with
``--true-pp`` (source px) their errors in px and in % of the image size (``pp_error_pct``: the
larger of x / width and y / height).
Numbers of docs/benchmarks.md ("Issue 27, second round") come from this script.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from gcvd_flow.stages.frontend import calibrate
from gcvd_flow.stages.frontend.ingest import prepare_frame, working_size

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
    ap.add_argument("--true-pp", default=None, metavar="CX,CY", help="the true principal point (source px)")
    ap.add_argument("--long-side", type=int, default=256)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    a = ap.parse_args()
    ims, (w, h), (W, H) = load(a.folder, a.long_side)
    s = W / w
    f0 = 300 / 384 * max(W, H)
    K = np.array([[f0, 0, (W - 1) / 2], [0, f0, (H - 1) / 2], [0, 0, 1.0]])
    kw = {k: _value(v) for k, v in (item.split("=", 1) for item in a.set)}
    t = time.time()
    aspect = (H / h) / (W / w)  # fy / fx of the working pixels (square at the source), as the stage passes it
    K[1, 1] = f0 * aspect
    res = calibrate.estimate_focal(ims, K, aspect=aspect, **kw)
    f = (res.estimate if res.estimate is not None else res.focal) / s
    out = {k: v for k, v in asdict(res).items() if isinstance(v, (int, float, str, bool))}
    out["start_focals"] = [[st, f_s / s, px, n] for st, f_s, px, n in res.start_focals]  # source px
    out.update(f_source=f, error_pct=100 * (f / a.true_fx - 1), seconds=round(time.time() - t, 1),
               n=len(ims), size=[W, H])
    out.update(_pp_fields(res, s, (w, h), a.true_pp))
    print(json.dumps(out))


def _value(v: str) -> Any:
    if "," in v:  # a tuple setting: starts=1.0,0.8 (one value: starts=1.0,)
        return tuple(float(x) for x in v.split(",") if x)
    try:
        return int(v)
    except ValueError:
        try:
            return float(v)
        except ValueError:
            return v


def _pp_fields(res: calibrate.FocalEstimate, s: float, src: tuple[int, int], true_pp: str | None) -> dict[str, Any]:
    """The principal point at the source resolution (pixel-centre scaling, as ingest) and its errors."""
    def source(c):
        return [(float(v) + 0.5) / s - 0.5 for v in c]

    out: dict[str, Any] = {"pp_source": source(res.principal_point), "pp_estimated": res.pp_estimated,
                           "pp_reason": res.pp_reason, "pp_z": res.pp_z}
    if res.pp_estimate is not None:
        out["pp_estimate_source"] = source(res.pp_estimate)
        out["pp_sigma_source"] = [float(v) / s for v in res.pp_sigma]
        out["pp_sigma_blocks_source"] = (None if res.pp_sigma_blocks is None  # not computed: formal std too large
                                         else [float(v) / s for v in res.pp_sigma_blocks])
        out["pp_sigma_formal_source"] = [float(v) / s for v in res.pp_sigma_formal]
    if true_pp:
        t = np.asarray([float(v) for v in true_pp.split(",")])
        for name in ("pp_source", "pp_estimate_source"):
            if name in out:
                e = np.asarray(out[name]) - t
                out[name.replace("source", "error_px")] = e.tolist()
                out[name.replace("source", "error_pct")] = float(100 * np.max(np.abs(e) / np.asarray(src)))
    return out


if __name__ == "__main__":
    main()
