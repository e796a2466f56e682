"""`gcvd-flow`: the engine's verbs (run, plan, why, status, ...) plus the product's own:
`synth` (clips with exact ground truth), `eval`, `demo`, `export`, and `--intrinsics`."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

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

    # The format names live in gcvd_flow.exports.WRITERS (not imported here: the CLI starts light);
    # an unknown name is an error that lists them.
    p = sub.add_parser("export", help="write a finished run as TUM, depth PNGs, COLMAP, PLY, TSDF mesh, "
                       "nerfstudio or MCAP (see gcvd_flow/exports/)")
    p.add_argument("run_dir", metavar="RUN_DIR")
    p.add_argument("--format", dest="formats", action="append", default=[], metavar="FMT",
                   help="an export format (tum, depth-png, colmap, ply, tsdf, nerfstudio, mcap, ...) or all; "
                   "repeatable or comma-separated")
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


def cmd_eval(a: argparse.Namespace) -> int:
    from gcvd_flow.evaluate.run_eval import evaluate, format_metrics, write_metrics

    res = evaluate(a.run_dir, a.gt, a.max_depth)
    write_metrics(a.run_dir, res)
    print(json.dumps(res, indent=1, sort_keys=True) if a.json_mode else format_metrics(res))
    return 0


# ------------------------------------------------------------------------------ export


def cmd_export(a: argparse.Namespace) -> int:
    from gcvd_flow.exports import cmd_export as run_export

    return run_export(a)


# ------------------------------------------------------------------------------ demo


def cmd_demo(a: argparse.Namespace) -> int:
    from gcvd_flow import api
    from gcvd_flow.evaluate.run_eval import evaluate, format_metrics, write_metrics
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
    write_metrics(out / "run", metrics_)
    total = time.perf_counter() - t0
    if a.json_mode:
        print(json.dumps({"run": res, "metrics": metrics_, "seconds": total}, indent=1))
    else:
        print(f"\nmetrics against the exact ground truth ({out / 'run' / 'metrics.json'}):")
        print(format_metrics(metrics_))
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
