"""`gcvd-flow`: the engine's verbs (run, plan, why, status, ...) plus the product's own:
`synth` (clips with exact ground truth), `eval`, `demo`, `export`, and `--intrinsics`."""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from gcvd_flow.engine import cli as engine_cli
from gcvd_flow.engine.errors import UsageError


def add_run_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--intrinsics", metavar="FX,FY,CX,CY",
                   help="camera intrinsics at the source resolution (same as --set ingest.intrinsics=...)")


def run_sets(a: argparse.Namespace) -> list[str]:
    return [f"ingest.intrinsics={json.dumps(a.intrinsics)}"] if getattr(a, "intrinsics", None) else []


def add_commands(sub) -> None:
    p = sub.add_parser("synth", help="render a synthetic clip with exact ground truth (generic layout)")
    p.add_argument("out", metavar="OUT")
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--trajectory", choices=["orbit", "loop", "forward", "rotation"], default="orbit")
    p.add_argument("--moving-object", action="store_true")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--size", default="256x192", metavar="WxH")
    p.set_defaults(handler=cmd_synth)

    p = sub.add_parser("eval", help="metrics of a run against ground truth (ATE, RPE, depth errors)")
    p.add_argument("run_dir", metavar="RUN_DIR")
    p.add_argument("--gt", required=True, metavar="GT_DIR",
                   help="generic layout (poses.txt, depth/), a synth OUT folder, or a Redwood/ICL folder")
    p.add_argument("--max-depth", type=float, default=10.0)
    p.add_argument("--json", dest="json_mode", action="store_true")
    p.set_defaults(handler=cmd_eval)

    p = sub.add_parser("demo", help="render a synthetic loop clip, run GCVD on it, print the metrics")
    p.add_argument("--out", default="demo-out", metavar="DIR")
    p.add_argument("--frames", type=int, default=120)
    p.add_argument("--size", default="256x192", metavar="WxH")
    p.add_argument("--cache", metavar="DIR")
    p.add_argument("--profile")
    p.add_argument("--set", dest="sets", action="append", default=[])
    p.add_argument("--json", dest="json_mode", action="store_true")
    p.set_defaults(handler=cmd_demo)

    p = sub.add_parser("export", help="write a finished run as TUM, depth PNGs, COLMAP, PLY, TSDF mesh, "
                       "nerfstudio or MCAP (see gcvd_flow/exports.py)")
    p.add_argument("run_dir", metavar="RUN_DIR")
    p.add_argument("--format", dest="formats", action="append", default=[], metavar="FMT",
                   help="tum, depth-png, colmap, ply, tsdf, nerfstudio, mcap or all (repeatable or comma-separated)")
    p.add_argument("--to", metavar="DIR", help="output directory (default: RUN_DIR/export)")
    p.add_argument("--every", type=int, default=1, metavar="N",
                   help="ply / tsdf / mcap cloud / colmap points: use every N-th frame (default 1)")
    p.add_argument("--voxel", type=float, default=0.0, metavar="M",
                   help="ply: voxel-grid downsampling size in scene units (default 0 = off); the MCAP "
                   "cloud uses it too, else median depth / 100")
    p.add_argument("--tsdf-voxel", type=float, default=None, metavar="M",
                   help="tsdf: voxel length in scene units (default: median depth / 100)")
    p.add_argument("--depth-scale", type=float, default=1.0, metavar="F",
                   help="depth-png: multiply depth by F before converting to millimetres (default 1)")
    p.add_argument("--fps", type=float, default=None,
                   help="mcap: frame rate for log times (default: the input's, else 30)")
    p.add_argument("--mcap-images", default="png", metavar="png|jpeg|raw",
                   help="mcap: RGB as foxglove.CompressedImage png (default) / jpeg, or foxglove.RawImage rgb8")
    p.add_argument("--max-points", type=int, default=20000, metavar="N",
                   help="colmap: about N points in points3D.txt (default 20000)")
    p.add_argument("--cache", metavar="DIR",
                   help="cache holding the run's frames (default: $GCVD_FLOW_CACHE or the user cache dir, as for run)")
    p.add_argument("--no-verify", dest="verify", action="store_false",
                   help="skip re-hashing objects read from the cache")
    p.add_argument("--json", dest="json_mode", action="store_true")
    p.set_defaults(handler=cmd_export)


def _parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UsageError(f"--size {text!r}: expected WxH, e.g. 256x192") from None
    if w < 16 or h < 16:
        raise UsageError(f"--size {text!r}: too small (minimum 16x16)")
    return w, h


def cmd_synth(a: argparse.Namespace) -> int:
    from gcvd_flow.evaluate.synth import render_clip

    from gcvd_flow.io.formats import write_generic_layout

    if a.frames < 2:
        raise UsageError("--frames must be at least 2")
    size = _parse_size(a.size)
    t0 = time.perf_counter()
    clip = render_clip(n_frames=a.frames, trajectory=a.trajectory, size=size,
                       moving_object=a.moving_object, seed=a.seed)
    write_generic_layout(a.out, clip)
    print(f"wrote {a.frames} frames ({size[0]}x{size[1]}, {a.trajectory}"
          f"{', moving object' if a.moving_object else ''}) to {a.out} in {time.perf_counter() - t0:.1f} s")
    return 0


# ------------------------------------------------------------------------------ evaluation


def _load_gt(gt: Path) -> dict[str, Any]:
    """Ground truth of a dataset folder: {poses (M,4,4) c2w by source frame, depth_files, scale}."""
    import numpy as np  # noqa: F401 - heavy imports stay out of CLI start-up
    from gcvd_flow.io.formats import read_redwood_log, read_tum_poses

    if not gt.exists():
        raise UsageError(f"{gt}: no such directory")
    if (gt / "gt").is_dir():  # a synth OUT folder
        gt = gt / "gt"
    out: dict[str, Any] = {"depth_files": [], "depth_scale": 1000.0}
    if (gt / "poses.txt").exists():
        _, out["poses"] = read_tum_poses(gt / "poses.txt")
    else:
        logs = sorted(gt.glob("*.log"))
        if not logs:
            raise UsageError(f"{gt}: no poses.txt (TUM) or *.log (Redwood) ground truth")
        out["poses"] = read_redwood_log(logs[0])
    if (gt / "depth").is_dir():
        from gcvd_flow.io.sources import natural_key

        out["depth_files"] = sorted((p for p in (gt / "depth").iterdir() if p.suffix.lower() == ".png"),
                                    key=lambda p: natural_key(p.name))
    if (gt / "depth_scale").exists():
        out["depth_scale"] = float((gt / "depth_scale").read_text().split()[0])
    return out


def evaluate(run_dir: str | Path, gt_dir: str | Path, max_depth: float = 10.0) -> dict[str, Any]:
    """ATE / RPE of poses.txt and depth errors of depth/*.npy against a ground-truth folder."""
    import cv2
    import numpy as np

    from gcvd_flow.evaluate import metrics

    from gcvd_flow.io.formats import read_tum_poses

    run = Path(run_dir)
    if not (run / "poses.txt").exists():
        raise UsageError(f"{run / 'poses.txt'}: missing (is {run} a finished run?)")
    cams = json.loads((run / "cameras.json").read_text())
    stamps, est = read_tum_poses(run / "poses.txt")
    idx = [int(round(t)) for t in stamps]
    gt = _load_gt(Path(gt_dir))
    if max(idx) >= len(gt["poses"]):
        raise UsageError(f"{gt_dir}: ground truth has {len(gt['poses'])} poses, the run uses frame {max(idx)}")
    gt_poses = np.asarray(gt["poses"])[idx]
    res: dict[str, Any] = {"frames": len(idx)}
    res.update(metrics.ate(est, gt_poses))
    res.update(metrics.rpe(est, gt_poses, delta=1))
    res["path_length"] = float(metrics.path_length(gt_poses))
    res["ate_percent_of_path"] = 100.0 * res["ate_rmse"] / max(res["path_length"], 1e-12)
    if gt["depth_files"]:
        per_frame = []
        for i in idx:
            pred_path = run / "depth" / f"{i:06d}.npy"
            if not pred_path.exists() or i >= len(gt["depth_files"]):
                continue
            pred = np.load(pred_path, allow_pickle=False)
            g = cv2.imread(str(gt["depth_files"][i]), cv2.IMREAD_UNCHANGED)
            if g is None:
                raise UsageError(f"{gt['depth_files'][i]}: cannot read depth PNG")
            g = g.astype(np.float32) / gt["depth_scale"]
            if g.shape != pred.shape:  # compare at the run's working resolution
                g = cv2.resize(g, (pred.shape[1], pred.shape[0]), interpolation=cv2.INTER_NEAREST)
            per_frame.append(metrics.depth_metrics(pred, g, max_depth=max_depth))
        if per_frame:
            res.update(metrics.aggregate_depth_metrics(per_frame))
            res["depth_frames"] = len(per_frame)
    res["width"], res["height"] = cams.get("width"), cams.get("height")
    return res


def _print_metrics(res: dict[str, Any]) -> None:
    rows = [("ATE RMSE", "ate_rmse", "m"), ("ATE / path", "ate_percent_of_path", "%"),
            ("RPE trans", "rpe_trans", "m"), ("RPE rot", "rpe_rot", "deg"), ("AbsRel", "abs_rel", ""),
            ("SqRel", "sq_rel", ""), ("RMSE", "rmse", "m"), ("delta<1.25", "delta1", "")]
    for label, k, unit in rows:
        if k in res:
            print(f"{label:<12} {res[k]:10.4f} {unit}")
    print(f"{'frames':<12} {res['frames']:10d}")


def cmd_eval(a: argparse.Namespace) -> int:
    res = evaluate(a.run_dir, a.gt, a.max_depth)
    (Path(a.run_dir) / "metrics.json").write_text(json.dumps(res, indent=1, sort_keys=True))
    if a.json_mode:
        print(json.dumps(res, indent=1, sort_keys=True))
    else:
        _print_metrics(res)
    return 0


# ------------------------------------------------------------------------------ export


def cmd_export(a: argparse.Namespace) -> int:
    from gcvd_flow.exports import cmd_export as run_export

    return run_export(a)


# ------------------------------------------------------------------------------ demo


def cmd_demo(a: argparse.Namespace) -> int:
    from gcvd_flow import api
    from gcvd_flow.evaluate.synth import render_clip

    from gcvd_flow.io.formats import write_generic_layout

    t0 = time.perf_counter()
    out = Path(a.out)
    clip_dir = out / "clip"
    size = _parse_size(a.size)
    if not (clip_dir / "frames").is_dir():
        print(f"[demo] rendering a {a.frames}-frame synthetic loop ({size[0]}x{size[1]}) into {clip_dir}", file=sys.stderr)
        clip = render_clip(n_frames=a.frames, trajectory="loop", size=size, seed=0)
        write_generic_layout(clip_dir, clip)
    cache = a.cache or os.environ.get("GCVD_FLOW_CACHE") or str(out / "cache")
    print(f"[demo] running GCVD (cache: {cache})", file=sys.stderr)
    inv = api.Invocation(input=str(clip_dir), out=str(out / "run"), profile=a.profile, sets=list(a.sets),
                         cache=cache, json_mode=a.json_mode)
    res = api.run(inv)
    res.pop("_record_paths", None)
    if not a.json_mode:
        for s in res["stages"]:
            print(f"  {s['name']:<20} executed {s['executed']:>4}  cached {s['cached']:>4}  {s['seconds']:7.2f} s")
    metrics_ = evaluate(out / "run", clip_dir)
    (out / "run" / "metrics.json").write_text(json.dumps(metrics_, indent=1, sort_keys=True))
    total = time.perf_counter() - t0
    if a.json_mode:
        print(json.dumps({"run": res, "metrics": metrics_, "seconds": total}, indent=1))
    else:
        print(f"\nmetrics against the exact ground truth ({out / 'run' / 'metrics.json'}):")
        _print_metrics(metrics_)
        print(f"\ndemo finished in {total:.0f} s; outputs in {out / 'run'} (poses.txt, depth/, cameras.json)")
    return 0


# ------------------------------------------------------------------------------ entry point


def _version() -> str:
    try:
        import importlib.metadata

        return importlib.metadata.version("gcvd-flow")
    except Exception:  # noqa: BLE001 - a source checkout that is not installed
        return "0+unknown"


PRODUCT = engine_cli.Product(
    prog="gcvd-flow", pipeline="gcvd", version=_version(),
    description="Globally consistent video depth and camera poses (GCVD), as a stage-cached pipeline.",
    add_run_args=add_run_args, run_sets=run_sets, add_commands=add_commands)


def main(argv: list[str] | None = None) -> int:
    return engine_cli.main(PRODUCT, argv)


if __name__ == "__main__":
    sys.exit(main())
