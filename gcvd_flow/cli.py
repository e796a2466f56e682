"""`gcvd-flow`: the engine's verbs (run, plan, why, status, ...) plus the product's own:
`synth` (clips with exact ground truth), `eval`, `demo`, `export`, and `--intrinsics`."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from gcvd_flow.engine import cli as engine_cli
from gcvd_flow.engine.errors import UsageError
from gcvd_flow.runtime import quiet_openmp


def add_run_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--intrinsics", metavar="FX,FY,CX,CY[,K1,K2,P1,P2[,K3]]",
                   help="camera intrinsics at the source resolution, optionally with the lens distortion "
                   "(OpenCV order), or OPENCV_FISHEYE:FX,FY,CX,CY,K1,K2,K3,K4 (cv2.fisheye); frames are "
                   "undistorted at ingest; values no lens has are refused (same as --set ingest.intrinsics=...)")
    p.add_argument("--masks", metavar="DIR",
                   help="your own masks: one PNG per frame (the frame's name, or frame order), non-zero = leave "
                   "the pixel out of every loss and of the depth consensus (same as --set masks.user_dir=DIR)")


def run_sets(a: argparse.Namespace) -> list[str]:
    sets = [f"ingest.intrinsics={json.dumps(a.intrinsics)}"] if getattr(a, "intrinsics", None) else []
    if getattr(a, "masks", None):
        if not os.path.isdir(a.masks):
            raise UsageError(f"--masks {a.masks}: not a folder")
        sets.append(f"masks.user_dir={json.dumps(os.path.abspath(a.masks))}")
    return sets


def add_commands(sub) -> None:
    for add in (_add_synth, _add_eval, _add_report, _add_compare, _add_demo, _add_export):
        add(sub)


def _add_synth(sub) -> None:
    p = sub.add_parser("synth", help="render a synthetic clip with exact ground truth (generic layout)")
    p.add_argument("out", metavar="OUT", help="folder to write the clip to (frames/, intrinsics.txt, gt/)")
    p.add_argument("--frames", type=int, default=60, help="number of frames (default 60)")
    p.add_argument("--trajectory", choices=["orbit", "loop", "forward", "rotation", "walk", "scan"], default="orbit",
                   help="camera path (default orbit; walk: a 3 m path that never revisits, for 300 frames; "
                   "scan: 2.5 m while panning +-40 deg four times, keyframe-heavy at 200 frames)")
    p.add_argument("--moving-object", action="store_true", help="add an independently moving object (gt/dynamic/)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the scene (default 0)")
    p.add_argument("--size", default="256x192", metavar="WxH", help="image size (default 256x192)")
    p.add_argument("--noise", type=float, default=0.0, metavar="STD",
                   help="sensor noise, std in 8-bit levels (default 0)")
    p.add_argument("--blur", type=float, default=0.0, metavar="F",
                   help="motion blur: fraction of each frame's image motion smeared (default 0; 1 = a full frame)")
    p.add_argument("--exposure", type=float, default=0.0, metavar="F",
                   help="exposure swings between frames, relative gain (default 0; e.g. 0.2)")
    p.add_argument("--texture", type=float, default=1.0, metavar="F",
                   help="surface detail contrast (default 1; e.g. 0.2 for low texture)")
    lens = p.add_mutually_exclusive_group()
    lens.add_argument("--distortion", default=None, metavar="K1,K2,P1,P2[,K3]",
                      help="render through this lens distortion (OpenCV order; written to intrinsics.txt, "
                      "the ground truth stays pinhole)")
    lens.add_argument("--fisheye", default=None, metavar="K1,K2,K3,K4",
                      help="render through OpenCV's fisheye model (cv2.fisheye) with these coefficients "
                      "(written to intrinsics.txt as OPENCV_FISHEYE; the ground truth stays pinhole)")
    p.add_argument("--focal", type=float, default=None, metavar="PX",
                   help="focal length fx = fy in px (default 300/384 x long side, the guess used without intrinsics)")
    p.add_argument("--principal-point", default=None, metavar="CX,CY",
                   help="principal point in px (default the image centre ((W-1)/2, (H-1)/2); written to "
                   "intrinsics.txt; not with --distortion)")
    p.set_defaults(handler=cmd_synth)


def _add_eval(sub) -> None:
    p = sub.add_parser("eval", help="metrics of a run against ground truth (ATE, RPE, depth errors); "
                       "with --baseline, exit 1 when a metric got worse (CI)")
    p.add_argument("run_dir", metavar="RUN_DIR", help="a finished `gcvd-flow run` directory")
    p.add_argument("--gt", required=True, metavar="GT_DIR",
                   help="generic layout (gt/poses.txt, gt/depth/), a synth OUT folder, a Redwood/ICL folder "
                   "(*.log, depth/) or a TUM RGB-D folder (groundtruth.txt, depth.txt; matched by timestamp)")
    p.add_argument("--max-depth", type=float, default=10.0, metavar="M",
                   help="ignore ground-truth depth beyond M metres (default 10)")
    p.add_argument("--baseline", metavar="METRICS_JSON",
                   help="a metrics.json to compare with: exit 1 with one line per metric that got worse "
                   "beyond --tolerance")
    p.add_argument("--tolerance", default="5%", metavar="PCT",
                   help="relative tolerance of --baseline, e.g. 5%% (default) or 0.05; delta1 is compared "
                   "as its failing share 1 - delta1")
    p.add_argument("--no-write", dest="write", action="store_false",
                   help="do not write RUN_DIR/metrics.json")
    p.add_argument("--json", dest="json_mode", action="store_true",
                   help="print the metrics (and regressions) as one JSON object")
    p.set_defaults(handler=cmd_eval)


def _add_report(sub) -> None:
    p = sub.add_parser("report", help="one self-contained HTML page: verdict, trajectory, depth strip, "
                       "stages, settings")
    p.add_argument("run_dir", metavar="RUN_DIR", help="a finished `gcvd-flow run` directory, or a sweep / folder "
                   "of runs: an index page (DIR/index.html) linking each run's report")
    p.add_argument("--gt", metavar="GT_DIR", help="ground truth (as for eval): adds the metrics and aligns "
                   "the trajectory to it")
    p.add_argument("--to", metavar="FILE", help="where to write the page (default RUN_DIR/report.html, "
                   "DIR/index.html)")
    p.add_argument("--every", type=int, default=None, metavar="N",
                   help="frame strip: every N-th frame (default: about 8 frames)")
    p.add_argument("--cache", metavar="DIR",
                   help="cache holding the run's stage outputs (default: the one run.json records)")
    p.add_argument("--json", dest="json_mode", action="store_true", help='print {"report": FILE, "verdict": good|suspect|failed, '
                   '"health": [{"name", "value", "status"}]} as JSON')
    p.set_defaults(handler=cmd_report)


def _add_compare(sub) -> None:
    p = sub.add_parser("compare", help="per stage: are two runs' outputs identical, and if not, how far apart")
    p.add_argument("run_a", metavar="RUN_A", help="the reference run directory")
    p.add_argument("run_b", metavar="RUN_B", help="the run compared with it")
    p.add_argument("--cache", metavar="DIR",
                   help="cache holding both runs' outputs (default: the one each run.json records)")
    p.add_argument("--cache-b", metavar="DIR", help="RUN_B's cache when it differs from RUN_A's")
    p.add_argument("--max-items", type=int, default=24, metavar="N",
                   help="per map stage, compare at most N of the differing items, evenly spread (default 24)")
    p.add_argument("--check", action="store_true", help="exit 1 when any stage output differs (like cmp)")
    p.add_argument("--json", dest="json_mode", action="store_true", help="print the comparison as one JSON object")
    p.set_defaults(handler=cmd_compare)


def _add_demo(sub) -> None:
    p = sub.add_parser("demo", help="render a synthetic loop clip, run GCVD on it, print the metrics")
    p.add_argument("--out", default="demo-out", metavar="DIR", help="output folder (default demo-out)")
    p.add_argument("--frames", type=int, default=120, help="number of frames (default 120)")
    p.add_argument("--size", default="256x192", metavar="WxH", help="image size (default 256x192)")
    p.add_argument("--cache", metavar="DIR", help="cache directory (default: $GCVD_FLOW_CACHE, else DIR/cache)")
    p.add_argument("--profile", metavar="NAME", help="named parameter profile: quality (the paper's 384 px working "
                                                     "size: more accurate, 1.6-2x the time), paper, fast")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override one parameter (repeatable)")
    p.add_argument("--json", dest="json_mode", action="store_true", help="machine-readable output on stdout")
    p.set_defaults(handler=cmd_demo)


def _add_export(sub) -> None:
    # The format names live in gcvd_flow.exports.WRITERS (not imported here: the CLI starts light);
    # an unknown name is an error that lists them.
    p = sub.add_parser("export", help="write a finished run as TUM, depth PNGs, COLMAP, PLY, TSDF mesh, "
                       "nerfstudio or MCAP (see gcvd_flow/exports/)")
    p.add_argument("run_dir", metavar="RUN_DIR", help="a finished `gcvd-flow run` directory")
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
                   help="mcap: log times = frame index / F (default: the source timestamps when the input has them, "
                   "e.g. TUM RGB-D; else the input's frame rate, else 30)")
    p.add_argument("--mcap-images", default="png", metavar="png|jpeg|raw",
                   help="mcap: RGB as foxglove.CompressedImage png (default) / jpeg, or foxglove.RawImage rgb8")
    p.add_argument("--max-points", type=int, default=20000, metavar="N",
                   help="colmap: about N 3D points, sampled on every --every-th frame's depth (default 20000)")
    p.add_argument("--max-track", type=int, default=32, metavar="N",
                   help="colmap: observations per 3D point at most, evenly spread over the frames that see it "
                   "(default 32)")
    p.add_argument("--colmap-binary", action="store_true",
                   help="colmap: write cameras.bin, images.bin, points3D.bin instead of the text model")
    p.add_argument("--min-confidence", type=float, default=None, metavar="C",
                   help="depth confidence threshold in [0, 1] (runs with confidence/): nerfstudio masks are "
                   "255 where confidence >= C, else 0 (default 0.5; 0 = no masks); when given, ply and the "
                   "mcap cloud also drop pixels below C (default: they keep every valid pixel)")
    p.add_argument("--full-res", action=argparse.BooleanOptionalAction, default=None,
                   help="colmap / nerfstudio: images at the source resolution (read from the run's input, "
                   "intrinsics scaled); default on; --no-full-res: the working resolution")
    p.add_argument("--cache", metavar="DIR",
                   help="cache holding the run's frames (default: the one run.json records, else "
                   "$GCVD_FLOW_CACHE or the user cache dir)")
    p.add_argument("--no-verify", dest="verify", action="store_false",
                   help="skip re-hashing objects read from the cache")
    p.add_argument("--json", dest="json_mode", action="store_true", help="print a summary as one JSON object")
    p.set_defaults(handler=cmd_export)


def _parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UsageError(f"--size {text!r}: expected WxH, e.g. 256x192") from None
    if w < 16 or h < 16:
        raise UsageError(f"--size {text!r}: too small (minimum 16x16)")
    return w, h


def _synth_lens(a: argparse.Namespace) -> tuple[tuple[float, ...] | None, str]:
    """(coefficients, model) of synth's --distortion (4 or 5) / --fisheye (4); None: pinhole."""
    opt, text, counts, model = (("fisheye", a.fisheye, (4,), "OPENCV_FISHEYE") if a.fisheye is not None else
                                ("distortion", a.distortion, (4, 5), "OPENCV"))
    if text is None:
        return None, "OPENCV"
    try:
        dist = tuple(float(v) for v in text.replace(",", " ").split())
    except ValueError:
        dist = ()
    if len(dist) not in counts or not all(abs(v) < 1e6 for v in dist):
        names = "k1,k2,k3,k4" if model == "OPENCV_FISHEYE" else "k1,k2,p1,p2[,k3]"
        raise UsageError(f"--{opt} {text!r}: expected {' or '.join(map(str, counts))} numbers {names}")
    return dist, model


def cmd_synth(a: argparse.Namespace) -> int:
    from gcvd_flow.evaluate.synth import render_clip
    from gcvd_flow.io.formats import write_generic_layout

    if a.frames < 2:
        raise UsageError("--frames must be at least 2")
    size = _parse_size(a.size)
    t0 = time.perf_counter()
    for name in ("noise", "blur", "exposure", "texture"):
        if not 0.0 <= getattr(a, name) < 1e3:
            raise UsageError(f"--{name} {getattr(a, name)}: must be a non-negative number")
    if a.focal is not None and not 0 < a.focal < 1e6:
        raise UsageError(f"--focal {a.focal}: must be a positive number of pixels")
    dist, model = _synth_lens(a)
    pp = _parse_principal_point(a.principal_point, size, dist)
    try:
        clip = render_clip(n_frames=a.frames, trajectory=a.trajectory, size=size,
                           moving_object=a.moving_object, seed=a.seed, noise=a.noise, blur=a.blur,
                           exposure=a.exposure, texture=a.texture, focal=a.focal,
                           distortion=dist, distortion_model=model, principal_point=pp)
    except ValueError as exc:  # a lens that sees beyond what the renderer pads
        raise UsageError(f"--{'fisheye' if a.fisheye is not None else 'distortion'}: {exc}") from None
    write_generic_layout(a.out, clip)
    print(f"wrote {a.frames} frames ({size[0]}x{size[1]}, {a.trajectory}"
          f"{', moving object' if a.moving_object else ''}) to {a.out} in {time.perf_counter() - t0:.1f} s")
    return 0


def _parse_principal_point(text: str | None, size: tuple[int, int], dist: Any) -> tuple[float, float] | None:
    """synth's --principal-point CX,CY (px, inside the image) -> (cx, cy), or None without it."""
    if text is None:
        return None
    try:
        pp = tuple(float(v) for v in text.replace(",", " ").split())
    except ValueError:
        pp = ()
    if len(pp) != 2 or not (0 <= pp[0] <= size[0] - 1 and 0 <= pp[1] <= size[1] - 1):
        raise UsageError(f"--principal-point {text!r}: expected CX,CY in px inside the {size[0]}x{size[1]} image")
    if dist is not None and any(dist):
        raise UsageError("--principal-point: not with --distortion (the distorted render keeps the centre)")
    return (pp[0], pp[1])


# ------------------------------------------------------------------------------ evaluation


def cmd_eval(a: argparse.Namespace) -> int:
    from gcvd_flow.evaluate.run_eval import compare_to_baseline, evaluate, format_metrics, parse_tolerance, read_baseline, write_metrics

    tol = parse_tolerance(a.tolerance)
    base = read_baseline(a.baseline) if a.baseline else None
    res = evaluate(a.run_dir, a.gt, a.max_depth)
    if a.write:
        write_metrics(a.run_dir, res)
    worse = compare_to_baseline(res, base, tol, a.baseline) if base is not None else []
    if a.json_mode:
        doc = dict(res)
        if base is not None:
            doc = {"metrics": res, "baseline": a.baseline, "tolerance": tol, "regressions": worse}
        print(json.dumps(doc, indent=1, sort_keys=True))
    else:
        print(format_metrics(res))
        if base is not None and not worse:
            print(f"no metric worse than {a.baseline} beyond {tol * 100:g}%")
    for line in worse:
        print(f"regression: {line}", file=sys.stderr)
    return 1 if worse else 0


# ------------------------------------------------------------------------------ report / compare


def cmd_report(a: argparse.Namespace) -> int:
    from gcvd_flow.report import write_report_doc

    if a.every is not None and a.every < 1:
        raise UsageError("--every must be at least 1")
    from gcvd_flow.report.index import is_folder_of_runs, write_index

    if is_folder_of_runs(a.run_dir):  # a sweep: an index page + each run's report
        out = write_index(a.run_dir, to=a.to, gt=a.gt, cache=a.cache, every=a.every,
                          log=lambda m: print(m, file=sys.stderr))
        print(json.dumps({"report": str(out)}) if a.json_mode else f"wrote {out}")
        return 0
    doc = write_report_doc(a.run_dir, to=a.to, gt=a.gt, cache=a.cache, every=a.every)
    print(json.dumps(doc) if a.json_mode else f"wrote {doc['report']} (verdict: {doc['verdict']})")
    return 0


def cmd_compare(a: argparse.Namespace) -> int:
    from gcvd_flow.evaluate.compare import compare_runs, format_comparison

    if a.max_items < 1:
        raise UsageError("--max-items must be at least 1")
    res = compare_runs(a.run_a, a.run_b, cache=a.cache, cache_b=a.cache_b, max_items=a.max_items)
    print(json.dumps(res, indent=1) if a.json_mode else format_comparison(res))
    return 1 if a.check and not res["identical"] else 0


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


def evaluate_run(run_dir: Path, gt: str) -> dict:
    """`sweep --gt`: one run's metrics, written to RUN_DIR/metrics.json (imported when used)."""
    from gcvd_flow.evaluate.run_eval import evaluate_run as evaluate_and_write

    return evaluate_and_write(run_dir, gt)


# the columns `runs` and `sweep` print (--json / --csv: every metric of metrics.json)
METRIC_COLUMNS = ("ate_rmse", "ate_percent_of_path", "rpe_trans", "rpe_rot", "abs_rel", "delta1", "keyframes")

PRODUCT = engine_cli.Product(
    prog="gcvd-flow", pipeline="gcvd", version=_version(),
    description="Globally consistent video depth and camera poses (GCVD), as a stage-cached pipeline.",
    add_run_args=add_run_args, run_sets=run_sets, add_commands=add_commands,
    evaluate=evaluate_run, metric_columns=METRIC_COLUMNS)


# options whose value is a list of numbers that may start with a minus sign (k1 < 0 for most
# lenses): argparse takes '-0.28,0.09,0,0' for an option and says "expected one argument"
NUMBER_LIST_OPTIONS = ("--intrinsics", "--distortion", "--fisheye")


def glue_negative_values(argv: list[str], options: tuple[str, ...] = NUMBER_LIST_OPTIONS) -> list[str]:
    """argv with ``OPT -0.28,...`` written as ``OPT=-0.28,...`` for the number-list options, so
    argparse reads a value that starts with a minus sign as the option's value (not after '--')."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        tok = argv[i]
        if tok == "--":
            return out + list(argv[i:])
        nxt = argv[i + 1] if i + 1 < len(argv) else None
        if tok in options and nxt is not None and len(nxt) > 1 and nxt[0] == "-" and (nxt[1].isdigit() or nxt[1] == "."):
            out.append(f"{tok}={nxt}")
            i += 2
            continue
        out.append(tok)
        i += 1
    return out


def main(argv: list[str] | None = None) -> int:
    quiet_openmp()  # before any verb loads torch / OpenCV (and so in every worker it starts)
    return engine_cli.main(PRODUCT, glue_negative_values(list(sys.argv[1:] if argv is None else argv)))


if __name__ == "__main__":
    sys.exit(main())
