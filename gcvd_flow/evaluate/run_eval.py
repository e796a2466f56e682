"""`gcvd-flow eval`: a finished run (RUN_DIR) against a ground-truth folder.

Ground truth (``load_gt``):

* the generic layout's ``gt/`` (a ``gcvd-flow synth`` OUT folder or its ``gt/``): ``poses.txt``
  (TUM, ``t`` = frame index) and ``depth/*.png``;
* a Redwood / ICL-NUIM folder: the first ``*.log`` and ``depth/*.png``;
* a TUM RGB-D folder: ``groundtruth.txt`` (TUM, ``t`` = seconds) and ``depth.txt`` (depth PNGs
  in 1/5000 m, stamped).

Depth PNGs are uint16 in 1/``depth_scale`` metres (1000, TUM RGB-D 5000, or the number in a
``depth_scale`` file). Generic and Redwood ground truth is matched by *source frame index*
(``frame_indices`` of the run's cameras.json); TUM RGB-D ground truth by *timestamp*, as evo
does: each of the run's stamps (the ``t`` column of its poses.txt, the ``rgb.txt`` stamps) takes
the nearest ground-truth stamp within 0.01 s (evo's default ``max_diff``); frames without one are
left out.

Metrics (``gcvd_flow.evaluate.metrics``): ATE RMSE after Sim(3) Umeyama alignment, RPE
trans / rot over consecutive frames, depth AbsRel / SqRel / RMSE / delta < 1.25 with per-frame
median scaling at the run's working resolution.

``compare_to_baseline`` is the CI check of ``gcvd-flow eval --baseline``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gcvd_flow.engine.errors import UsageError
from gcvd_flow.evaluate import metrics
from gcvd_flow.io.formats import read_depth_png, read_redwood_log, read_tum_poses, read_tum_stamped_files
from gcvd_flow.io.sources import natural_key

MAX_STAMP_DIFF = 0.01  # s, evo's default (evo.core.sync.associate_trajectories max_diff=0.01)
TUM_DEPTH_SCALE = 5000.0  # TUM RGB-D depth PNGs: 5000 units per metre


def load_gt(gt: str | Path) -> dict[str, Any]:
    """Ground truth of a dataset folder: {poses (M, 4, 4) T_w_c, stamps (M,) seconds or None
    (None: ``poses[i]`` is source frame i), depth_files (PNG paths, possibly empty; by frame
    index, or stamped by ``depth_stamps``), depth_stamps (None or (D,)), depth_scale (stored
    units per metre)}."""
    gt = Path(gt)
    if not gt.exists():
        raise UsageError(f"{gt}: no such directory")
    if (gt / "gt").is_dir():  # a synth OUT folder
        gt = gt / "gt"
    out: dict[str, Any] = {"depth_files": [], "depth_scale": 1000.0, "stamps": None, "depth_stamps": None}
    if (gt / "groundtruth.txt").exists():  # TUM RGB-D
        out["stamps"], out["poses"] = read_tum_poses(gt / "groundtruth.txt")
        out["depth_scale"] = TUM_DEPTH_SCALE
        if (gt / "depth.txt").exists():
            out["depth_stamps"], out["depth_files"] = read_tum_stamped_files(gt / "depth.txt")
    elif (gt / "poses.txt").exists():
        _, out["poses"] = read_tum_poses(gt / "poses.txt")
    else:
        logs = sorted(gt.glob("*.log"))
        if not logs:
            raise UsageError(f"{gt}: no poses.txt (TUM), groundtruth.txt (TUM RGB-D) or *.log (Redwood) ground truth")
        out["poses"] = read_redwood_log(logs[0])
    if out["depth_stamps"] is None and (gt / "depth").is_dir():
        out["depth_files"] = sorted((p for p in (gt / "depth").iterdir() if p.suffix.lower() == ".png"),
                                    key=lambda p: natural_key(p.name))
    if (gt / "depth_scale").exists():
        try:
            out["depth_scale"] = float((gt / "depth_scale").read_text().split()[0])
        except (IndexError, ValueError):
            raise UsageError(f"{gt / 'depth_scale'}: expected one number (stored units per metre)") from None
        if not (np.isfinite(out["depth_scale"]) and out["depth_scale"] > 0):
            raise UsageError(f"{gt / 'depth_scale'}: must be a positive number")
    return out


def associate(stamps: np.ndarray, ref_stamps: np.ndarray, max_diff: float = MAX_STAMP_DIFF) -> np.ndarray:
    """For each of ``stamps`` the index of the nearest of ``ref_stamps`` if within ``max_diff``
    seconds, else -1 (evo's ``associate_trajectories``: nearest stamp, |dt| <= max_diff)."""
    stamps = np.asarray(stamps, np.float64)
    ref = np.asarray(ref_stamps, np.float64)
    if not len(ref):
        return np.full(len(stamps), -1)
    order = np.argsort(ref, kind="stable")
    rs = ref[order]
    pos = np.clip(np.searchsorted(rs, stamps), 1, max(len(rs) - 1, 1))
    lo = np.clip(pos - 1, 0, len(rs) - 1)
    hi = np.clip(pos, 0, len(rs) - 1)
    best = np.where(np.abs(rs[lo] - stamps) <= np.abs(rs[hi] - stamps), lo, hi)
    ok = np.abs(rs[best] - stamps) <= max_diff
    return np.where(ok, order[best], -1)


@dataclass
class Matched:
    """A run's frames paired with ground truth: ``est[m]`` (T_w_c, pose units) and ``gt[m]``
    (metres) are frame ``frame_indices[m]`` (position ``run_pos[m]`` in the run);
    ``depth_files[m]`` its ground-truth depth PNG or None."""

    est: np.ndarray
    gt: np.ndarray
    run_pos: list[int]
    frame_indices: list[int]
    depth_files: list[Path | None]
    depth_scale: float
    association: str  # "frame index" | "timestamp"
    run_frames: int


def _run_frames(run: Path) -> tuple[np.ndarray, np.ndarray, list[int], dict[str, Any]]:
    if not (run / "poses.txt").exists():
        raise UsageError(f"{run / 'poses.txt'}: missing (is {run} a finished run?)")
    from gcvd_flow.io.run_dir import read_cameras

    cams = read_cameras(run)
    stamps, est = read_tum_poses(run / "poses.txt")
    idx = cams.get("frame_indices")
    if not isinstance(idx, list) or len(idx) != len(est):
        idx = [int(round(t)) for t in stamps]  # a run dir written before cameras.json had them
    return stamps, est, [int(i) for i in idx], cams


def match_gt(run_dir: str | Path, gt_dir: str | Path) -> Matched:
    """Pair the run's poses (and depth files) with a ground-truth folder's (see the module doc)."""
    run = Path(run_dir)
    stamps, est, idx, _ = _run_frames(run)
    gt = load_gt(gt_dir)
    poses = np.asarray(gt["poses"])
    if gt["stamps"] is not None:
        hit = associate(stamps, gt["stamps"])
        pos = [k for k in range(len(est)) if hit[k] >= 0]
        if len(pos) < 3:
            raise UsageError(f"{gt_dir}: only {len(pos)} of the run's {len(est)} timestamps have a ground-truth "
                             f"pose within {MAX_STAMP_DIFF} s (is poses.txt's t the rgb.txt stamp?)")
        gt_sel = poses[hit[pos]]
        dfiles: list[Path | None] = [None] * len(pos)
        if gt["depth_stamps"] is not None:
            dh = associate(stamps[pos], gt["depth_stamps"])
            dfiles = [Path(gt["depth_files"][j]) if j >= 0 else None for j in dh]
        assoc = "timestamp"
    else:
        if max(idx) >= len(poses):
            raise UsageError(f"{gt_dir}: ground truth has {len(poses)} poses, the run uses frame {max(idx)}")
        pos = list(range(len(est)))
        gt_sel = poses[idx]
        files = gt["depth_files"]
        dfiles = [Path(files[i]) if i < len(files) else None for i in idx]
        assoc = "frame index"
    return Matched(est[pos], gt_sel, pos, [idx[k] for k in pos], dfiles, float(gt["depth_scale"]), assoc, len(est))


def trajectory_metrics(est: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """ATE (Sim(3)-aligned), RPE (delta 1) and path length of est vs gt, both (N, 4, 4) T_w_c."""
    res: dict[str, float] = {}
    res.update(metrics.ate(est, gt))
    res.update(metrics.rpe(est, gt, delta=1))
    res["path_length"] = float(metrics.path_length(gt))
    res["ate_percent_of_path"] = 100.0 * res["ate_rmse"] / max(res["path_length"], 1e-12)
    ws = metrics.window_scales(est, gt, window=20)
    if len(ws):  # scale drift between 20-frame windows (1 = none)
        res["scale_window_min"], res["scale_window_max"] = float(ws.min()), float(ws.max())
    return res


def _cached_maps(run: Path, n: int) -> tuple[Any, Any]:
    """The run's working-resolution frames (ingest) and static masks (masks stage) from the cache
    run.json records, each None when not readable there (the breakdown then leaves out the
    texture / dynamic classes)."""
    from gcvd_flow.engine import api
    from gcvd_flow.engine.artifacts import ArtifactError
    from gcvd_flow.engine.dag import stage_name
    from gcvd_flow.engine.store import StoreError
    from gcvd_flow.io.run_dir import recorded_cache

    cache = recorded_cache(run)
    if cache is None or not (run / "run.json").exists():
        return None, None
    from gcvd_flow import pipeline as G  # the stage names as the pipeline declares them

    out = []
    for stage in (G.RUN_DIR_SOURCES.frames, G.MASKS):
        try:
            value = api.recorded_output(run, stage_name(stage), cache)
            out.append(value if len(value) == n else None)
        except (UsageError, StoreError, ArtifactError, TypeError):
            out.append(None)
    return out[0], out[1]


def _frame_maps(frames: Any, masks: Any, k: int, shape: tuple[int, ...]) -> tuple[Any, Any]:
    """Frame k's grey image (0..255) and static mask at ``shape``, or None each."""
    import cv2

    gray = static = None
    if frames is not None:
        img = np.asarray(frames[k]["image"])
        if img.shape[:2] == shape:
            gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float32)
    if masks is not None:
        st = np.asarray(masks[k]["static"])
        if st.shape == shape:
            static = st
    return gray, static


def depth_errors(run: Path, m: Matched, max_depth: float, min_confidence: float = 0.5) -> dict[str, Any]:
    """Aggregated depth metrics of run/depth/NNNNNN.npy against the ground-truth PNGs (frames
    without either are skipped); {} when no frame has both.

    Where the run has confidence maps, also the errors of its confident pixels only
    (confidence >= ``min_confidence``, the default of the exports' masks): ``abs_rel_confident``
    and ``delta1_confident`` (per-frame median scaling over those pixels, as a user who masks
    by confidence would see them) and ``confident_fraction`` (mean share of the frame's pixels
    with valid ground truth that are kept).

    ``abs_rel_most_confident``: {"top25": AbsRel, "top50", "top75"} of the most confident quarter,
    half, three quarters of each frame's pixels (``metrics.sparsification_abs_rel``): how well the
    confidence ranks the error, independent of where its threshold lies.

    ``regions``: AbsRel split by region classes (``gcvd_flow.evaluate.regions``: confident,
    texture-less, depth edges, near / far, border, dynamic); the texture and dynamic classes need
    the run's frames and masks from the cache run.json records."""
    import cv2

    from gcvd_flow.evaluate.regions import RegionBreakdown

    frames, masks = _cached_maps(run, m.run_frames)
    breakdown = RegionBreakdown(max_depth=max_depth, min_confidence=min_confidence)
    per_frame, confident, kept, ranked = [], [], [], []
    from gcvd_flow.io.run_dir import read_cameras

    cams, lens_positions = read_cameras(run), None
    for k, i, gpath in zip(m.run_pos, m.frame_indices, m.depth_files):
        pred_path = run / "depth" / f"{i:06d}.npy"
        if gpath is None or not pred_path.exists():
            continue
        pred = np.load(pred_path, allow_pickle=False)
        g = read_depth_png(gpath, m.depth_scale)  # DatasetError names the file
        if cams.get("distortion"):  # ground truth registered to the source frame, seen through the lens
            if lens_positions is None:
                from gcvd_flow.pipeline import source_positions

                lens_positions = source_positions(cams, pred.shape)
            if lens_positions is not None:
                g = sample_source_map(g, lens_positions, (int(cams["source_width"]), int(cams["source_height"])))
        elif g.shape != pred.shape:  # compare at the run's working resolution
            g = cv2.resize(g, (pred.shape[1], pred.shape[0]), interpolation=cv2.INTER_NEAREST)
        per_frame.append(metrics.depth_metrics(pred, g, max_depth=max_depth))
        conf_path = run / "confidence" / f"{i:06d}.npy"
        conf = np.load(conf_path, allow_pickle=False) if conf_path.exists() else None
        if conf is not None:
            ok = conf >= min_confidence
            confident.append(metrics.depth_metrics(np.where(ok, pred, 0.0), g, max_depth=max_depth))
            valid = (g > 0) & (g <= max_depth)
            kept.append(float((ok & valid).sum() / max(valid.sum(), 1)))
            ranked.append(metrics.sparsification_abs_rel(pred, g, conf, max_depth=max_depth))
        gray, static = _frame_maps(frames, masks, k, pred.shape)
        breakdown.add(pred, g, gray=gray, confidence=conf, static=static)
    if not per_frame:
        return {}
    out = {**metrics.aggregate_depth_metrics(per_frame), "depth_frames": len(per_frame)}
    if confident and len(confident) == len(per_frame):
        agg = metrics.aggregate_depth_metrics(confident)
        out.update(abs_rel_confident=agg["abs_rel"], delta1_confident=agg["delta1"],
                   confident_fraction=float(np.mean(kept)), min_confidence=min_confidence)
        out["abs_rel_most_confident"] = {k: float(np.nanmean([r[k] for r in ranked])) for k in ranked[0]}
    regions = breakdown.result()
    if regions:
        out["regions"] = regions
    return out


def sample_source_map(g: np.ndarray, positions: np.ndarray, source_size: tuple[int, int]) -> np.ndarray:
    """A map registered to the source frame (ground-truth depth (Hg, Wg), any resolution of the
    source's (W, H) = ``source_size``) read at ``positions`` (h, w, 2) source px (x, y), nearest
    pixel (depth is not interpolated across edges); 0 (invalid) where a position lies outside it.

    A run that undistorted its frames at ingest writes maps of the pinhole camera: their pixel
    (u, v) saw the source pixel the lens sends it to, pixels off at a strong lens' corners (TUM
    fr1's Kinect), so comparing pixel by pixel after a resize would compare different surfaces."""
    hg, wg = g.shape
    x = np.rint((positions[..., 0] + 0.5) * (wg / source_size[0]) - 0.5)
    y = np.rint((positions[..., 1] + 0.5) * (hg / source_size[1]) - 0.5)
    inside = (x >= 0) & (x <= wg - 1) & (y >= 0) & (y <= hg - 1)
    xi, yi = np.where(inside, x, 0).astype(np.intp), np.where(inside, y, 0).astype(np.intp)
    return np.where(inside, g[yi, xi], 0).astype(g.dtype)


def evaluate(run_dir: str | Path, gt_dir: str | Path, max_depth: float = 10.0) -> dict[str, Any]:
    """ATE / RPE of poses.txt and depth errors of depth/*.npy against a ground-truth folder."""
    run = Path(run_dir)
    m = match_gt(run, gt_dir)
    from gcvd_flow.io.run_dir import read_cameras

    cams = read_cameras(run)
    res: dict[str, Any] = {"frames": len(m.run_pos)}
    if len(m.run_pos) != m.run_frames:
        res["run_frames"] = m.run_frames
    res.update(trajectory_metrics(m.est, m.gt))
    if any(f is not None for f in m.depth_files):
        res.update(depth_errors(run, m, max_depth))
    res["width"], res["height"] = cams.get("width"), cams.get("height")
    kf = cams.get("keyframes")
    if isinstance(kf, list):
        res["keyframes"] = len(kf)
    res["association"] = m.association
    return res


def format_metrics(res: dict[str, Any]) -> str:
    """The metrics as a small table (what `gcvd-flow eval` prints without --json)."""
    rows = [("ATE RMSE", "ate_rmse", "m"), ("ATE / path", "ate_percent_of_path", "%"),
            ("RPE trans", "rpe_trans", "m"), ("RPE rot", "rpe_rot", "deg"), ("AbsRel", "abs_rel", ""),
            ("SqRel", "sq_rel", ""), ("RMSE", "rmse", "m"), ("delta<1.25", "delta1", ""),
            ("AbsRel conf", "abs_rel_confident", ""), ("conf. share", "confident_fraction", "")]
    lines = [f"{label:<12} {res[k]:10.4f} {unit}" for label, k, unit in rows if k in res]
    lines.append(f"{'frames':<12} {res['frames']:10d}")
    if "keyframes" in res:
        lines.append(f"{'keyframes':<12} {res['keyframes']:10d}")
    if res.get("regions"):
        from gcvd_flow.evaluate.regions import format_regions

        lines += ["", "depth by region (pixels: share of valid ones; of error: share of the summed AbsRel; "
                  "bias: median log(pred / gt))", format_regions(res["regions"])]
    return "\n".join(lines)


def write_metrics(run_dir: str | Path, res: dict[str, Any]) -> Path:
    """RUN_DIR/metrics.json."""
    path = Path(run_dir) / "metrics.json"
    path.write_text(json.dumps(res, indent=1, sort_keys=True))
    return path


# ------------------------------------------------------------------------------ CI: --baseline

# lower is better; delta1 is compared as its complement (the share of pixels failing delta < 1.25)
LOWER_IS_BETTER = ("ate_rmse", "ate_mean", "ate_median", "ate_percent_of_path", "rpe_trans", "rpe_rot",
                   "abs_rel", "sq_rel", "rmse", "abs_rel_confident")
HIGHER_IS_BETTER = ("delta1", "delta1_confident")


def parse_tolerance(text: str) -> float:
    """'5%' or '0.05' -> 0.05 (a relative tolerance)."""
    t = str(text).strip()
    try:
        v = float(t[:-1]) / 100.0 if t.endswith("%") else float(t)
    except ValueError:
        raise UsageError(f"--tolerance {text!r}: expected a percentage such as 5% (or a fraction such as 0.05)") from None
    if not (np.isfinite(v) and v >= 0):
        raise UsageError(f"--tolerance {text!r}: must be >= 0")
    return v


def read_baseline(path: str | Path) -> dict[str, Any]:
    """A metrics.json (what `gcvd-flow eval` writes) or {"metrics": {...}, ...}, checked so that
    the gate fails closed: every known metric it holds must be a number (a string, null, a list
    or an integer too large for a float is a one-line UsageError naming the file and the metric,
    never a silent "no metric worse"), and it must hold at least one. NaN / infinity pass here:
    ``compare_to_baseline`` accepts them only where the run's metric is not finite either."""
    from gcvd_flow.engine import jsonio

    p = Path(path)
    doc = jsonio.load_file(p, "baseline", missing="baseline file not found")
    if isinstance(doc, dict) and isinstance(doc.get("metrics"), dict):
        doc = doc["metrics"]
    if not isinstance(doc, dict) or not any(k in doc for k in LOWER_IS_BETTER + HIGHER_IS_BETTER):
        raise UsageError(f"{p}: no metrics (expected the metrics.json of `gcvd-flow eval`)")
    for k in LOWER_IS_BETTER + HIGHER_IS_BETTER:
        if k in doc and not _number(doc[k]):
            raise UsageError(f"{p}: baseline metric {k} is {_show(doc[k])}, not a number: the gate cannot "
                             f"compare it")
    if "frames" in doc and not (isinstance(doc["frames"], int) and not isinstance(doc["frames"], bool)
                                and 0 <= doc["frames"] < 1 << 53):
        raise UsageError(f"{p}: baseline frames is {_show(doc['frames'])}, not a frame count")
    return doc


def _number(v: Any) -> bool:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    try:
        float(v)
    except OverflowError:  # an integer beyond float's range (10**400)
        return False
    return True


def _show(v: Any) -> str:
    text = repr(v) if isinstance(v, (float, int)) and not isinstance(v, bool) else json.dumps(v)
    return text if len(text) <= 24 else text[:21] + "..."


def compare_to_baseline(res: dict[str, Any], base: dict[str, Any], tolerance: float,
                        where: str = "baseline") -> list[str]:
    """One line per metric of ``res`` worse than ``base`` by more than ``tolerance`` (relative);
    a metric that is 0 in the baseline may grow by 1e-9 (rounding). Also a line when the frame
    count differs (the metrics would not be comparable).

    Fails closed (UsageError naming ``where``): a baseline metric that is NaN or infinite while
    the run's is finite cannot be compared (it would pass any run), and a baseline of which no
    metric could be compared at all gates nothing. A metric that is not finite in both (e.g.
    abs_rel_confident of a run without confident pixels) is the same state and is skipped."""
    lines = []
    if "frames" in base and res.get("frames") != base["frames"]:
        lines.append(f"frames: {base['frames']} -> {res.get('frames')} (the run covers other frames than the baseline)")
    compared = 0
    for k in LOWER_IS_BETTER + HIGHER_IS_BETTER:
        if k not in base:
            continue
        if not _number(base[k]):
            raise UsageError(f"{where}: baseline metric {k} is {_show(base[k])}, not a number")
        new: Any = res.get(k)  # float() only where _number(new) holds
        new_ok = _number(new) and bool(np.isfinite(float(new)))
        if not np.isfinite(float(base[k])):
            if new_ok:
                raise UsageError(f"{where}: baseline metric {k} is {float(base[k])}, the run's {float(new):.6g}: "
                                 f"the gate cannot compare them")
            continue
        compared += 1
        if not new_ok:
            lines.append(f"{k}: {base[k]:.6g} -> {new} (missing or not finite)")
            continue
        b, n = float(base[k]), float(new)
        if k in HIGHER_IS_BETTER:  # compare the failing share 1 - delta1
            b, n = 1.0 - b, 1.0 - n
        limit = b * (1.0 + tolerance) + 1e-9
        if n > limit:
            rel = (n - b) / b * 100 if b > 0 else float("inf")
            what = f"1-{k}" if k in HIGHER_IS_BETTER else k
            lines.append(f"{k}: {float(base[k]):.6g} -> {float(new):.6g} ({what} {rel:+.1f}%, tolerance "
                         f"{tolerance * 100:g}%)")
    if not compared:
        raise UsageError(f"{where}: no metric of the baseline could be compared (none is a finite number)")
    return lines


def evaluate_run(run_dir: Path, gt: str) -> dict:
    """`sweep --gt`: one run's metrics against ground truth, written to RUN_DIR/metrics.json."""
    res = evaluate(run_dir, gt)
    write_metrics(run_dir, res)
    return res
