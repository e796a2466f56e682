"""`gcvd-flow export RUN_DIR --format FMT ...`: a finished run in the formats other tools read.

Reads RUN_DIR (``poses.txt``, ``depth/NNNNNN.npy``, ``cameras.json``, ``run.json``;
``gcvd_flow.io.run_dir.load_run``) and, for the formats that need colour, the run's RGB frames
at working resolution: the output of its ``ingest`` stage, decoded from the cache by the digest
recorded in ``run.json`` (neither the input video nor the current code is needed, and the
frames are exactly the ones the run used). ``colmap`` and ``nerfstudio`` write their images at the
source resolution (``--full-res``, the default), read again from the run's input when its content
digest is still the one the run recorded (``source_frames.py``). Writes into DIR (default
RUN_DIR/export):

    tum          DIR/poses.txt                    copy of the trajectory (TUM, camera-to-world)   tum.py
    depth-png    DIR/depth/NNNNNN.png             uint16 mm of depth * --depth-scale, 0 = invalid  depth_png.py
                 DIR/confidence/NNNNNN.png        uint16 confidence * 65535 (runs with confidence/)
    colmap       DIR/colmap/sparse/0/{cameras,images,points3D}.txt|.bin, DIR/images/               colmap.py
    ply          DIR/points.ply                   coloured point cloud                             clouds.py
    tsdf         DIR/mesh.ply                     TSDF-fused triangle mesh (open3d VoxelBlockGrid) clouds.py
    nerfstudio   DIR/transforms.json (+ DIR/images/, DIR/depth/, DIR/confidence/, DIR/masks/ PNGs) nerfstudio.py
    mcap         DIR/run.mcap                     foxglove JSON schemas: image, depth, confidence, calibration,
                                                  /tf, trajectory, cloud

Confidence (RUN_DIR/confidence/, optional: older run dirs export without it) in each format:
``confidence.py``.

Every file is written to a temporary name in its folder and renamed into place
(``_common._atomic``), so an interrupted export never leaves a partial file under a final
name; files that reference others (transforms.json, images.txt) are written after what they
reference.

Adding a format: a module with ``write(ctx: ExportContext) -> dict`` (decorated with
``@uses_images(...)`` if it reads the RGB frames) and one line in ``WRITERS`` below.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from gcvd_flow.engine.errors import UsageError
from gcvd_flow.exports import clouds, colmap, depth_png, mcap, nerfstudio, tum
from gcvd_flow.exports._common import ExportContext, Options, Writer, _atomic, images_use  # noqa: F401 - API
from gcvd_flow.exports.depth_png import depth_to_mm16  # noqa: F401 - part of this API
from gcvd_flow.io.run_dir import RunData, attach_images, check_confidence, load_run  # noqa: F401 - part of this API

#: format name -> writer; the order is the write order (nerfstudio refers to points.ply).
WRITERS: dict[str, Writer] = {
    "tum": tum.write,
    "depth-png": depth_png.write,
    "colmap": colmap.write,
    "ply": clouds.write_ply,
    "tsdf": clouds.write_tsdf,
    "nerfstudio": nerfstudio.write,
    "mcap": mcap.write,
}
FORMATS = tuple(WRITERS)


def parse_formats(values: Sequence[str]) -> list[str]:
    """`--format` values (repeatable, comma-separated, `all`) -> formats in write order."""
    asked: set[str] = set()
    for v in values:
        for f in (s.strip().lower() for s in v.split(",")):
            if not f:
                continue
            if f == "all":
                asked.update(FORMATS)
            elif f in FORMATS:
                asked.add(f)
            else:
                raise UsageError(f"unknown export format {f!r}; choose from {', '.join(FORMATS)}, all")
    if not asked:
        raise UsageError(f"no --format given; choose from {', '.join(FORMATS)}, all")
    return [f for f in FORMATS if f in asked]


def export_run(run_dir: str | Path, formats: Sequence[str], to: str | Path | None = None,
               options: Options | None = None, cache: str | None = None, verify: bool = True,
               log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Export a finished run (the Python API of `gcvd-flow export`).

    Returns {"out", "frames", "formats": {fmt: details}, "skipped": {fmt: reason}, "seconds"}.
    Formats that need the run's RGB frames are *skipped* (not an exception) when the cache no
    longer holds them; bad input raises UsageError before anything is written.
    """
    t0 = time.perf_counter()
    log = log or (lambda m: print(m, file=sys.stderr, flush=True))
    opt = options or Options()
    fmts = parse_formats(formats)
    opt.check()
    run = load_run(run_dir)
    check_confidence(run)
    if run.confidence_note:
        log(f"warning: no confidence exported: {run.confidence_note}")
    out = Path(to) if to is not None else Path(run_dir) / "export"
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"{out}: cannot create the export directory ({exc.strerror})") from None
    if any(images_use(WRITERS[f]) for f in fmts):
        from gcvd_flow.pipeline import RUN_DIR_SOURCES

        attach_images(run, cache, verify, frames_stage=RUN_DIR_SOURCES.frames)
    ctx = ExportContext(run, out, opt, log)
    doc: dict[str, Any] = {"out": str(out), "frames": len(run), "formats": {}, "skipped": {}}
    for f in fmts:
        if images_use(WRITERS[f]) == "required" and run.images is None:
            doc["skipped"][f] = run.images_error
            continue
        doc["formats"][f] = WRITERS[f](ctx)
        ctx.written.add(f)
    doc["seconds"] = round(time.perf_counter() - t0, 3)
    return doc


def cmd_export(a: argparse.Namespace) -> int:
    """`gcvd-flow export` (its arguments are declared in gcvd_flow/cli.py, which stays light)."""
    opt = Options(every=a.every, voxel=a.voxel, tsdf_voxel=a.tsdf_voxel, depth_scale=a.depth_scale, fps=a.fps,
                  mcap_images=a.mcap_images, max_points=a.max_points, max_track=a.max_track,
                  colmap_binary=a.colmap_binary, full_res=a.full_res, min_confidence=a.min_confidence)
    doc = export_run(a.run_dir, a.formats, a.to, opt, a.cache, a.verify)
    if a.json_mode:
        print(json.dumps(doc, indent=1))
    else:
        for f, info in doc["formats"].items():
            where = info.get("file") or info.get("dir")
            extra = ", ".join(f"{k} {v}" for k, v in info.items()
                              if k not in ("file", "dir") and not isinstance(v, (dict, type(None))))
            print(f"{f:<11} {where}  ({extra})")
    if doc["skipped"]:
        names = ", ".join(doc["skipped"])
        reason = next(iter(doc["skipped"].values()))
        raise UsageError(f"not exported: {names}: {reason}; pass the run's --cache DIR")
    return 0
