"""What a report shows, gathered from RUN_DIR, its run.json and the cache the run used.

Everything the cache provides is optional: a run directory whose cache objects were collected
still gets a report (poses, depth, stage digests, settings), with a note saying what is missing.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gcvd_flow.engine.errors import StoreError, UsageError
from gcvd_flow.io.run_dir import RunData, load_run, read_cameras
from gcvd_flow.report import verdict as V
from gcvd_flow.report.verdict import Signal


@dataclass
class ReportData:
    run: RunData
    doc: dict[str, Any]  # run.json
    cams: dict[str, Any]  # cameras.json
    cache: Path | None
    keyframes: list[int] = field(default_factory=list)  # positions in the run
    loops: list[dict[str, Any]] = field(default_factory=list)  # {a, b (positions), used (bool)}
    metrics: dict[str, Any] | None = None
    gt_positions: np.ndarray | None = None  # (N, 3) ground-truth camera centres (NaN: no GT)
    est_positions: np.ndarray | None = None  # (N, 3) estimate, Sim(3)-aligned to GT when given
    signals: list[Signal] = field(default_factory=list)
    stages: list[dict[str, Any]] = field(default_factory=list)
    settings: list[dict[str, Any]] = field(default_factory=list)
    versions: dict[str, str] = field(default_factory=dict)
    strip: list[dict[str, Any]] = field(default_factory=list)  # {frame, rgb, depth, static}
    notes: list[str] = field(default_factory=list)
    verdict: str = "good"  # good | suspect | failed, from the judged signals (report/verdict.py)


# ------------------------------------------------------------------------------ the cache


def _open_store(cache: Path | None):
    from gcvd_flow.engine.paths import is_cache_dir
    from gcvd_flow.engine.store import Store

    if cache is None or not is_cache_dir(cache):  # only read: never made where run.json points
        return None
    return Store(cache, verify=True)


def recorded_part(doc: dict[str, Any], store: Any, stage: str, path: tuple = ()) -> Any:
    """A sub-tree of the output ``run.json`` recorded for a whole stage, decoding only the objects
    under it (``engine.api.recorded_output`` decodes everything: association's flows too)."""
    from gcvd_flow.engine.artifacts import decode_tree, load_manifest

    digest = ((doc.get("stages") or {}).get(stage) or {}).get("output")
    if not digest or store is None:
        raise UsageError(f"no output of stage {stage!r} recorded or no cache")
    node: Any = load_manifest(store, digest).get("value")
    for p in path:
        node = node[p]
    return decode_tree(store, node)


def _map_output(run_dir: Path, stage: str, cache: Path | None) -> Any:
    from gcvd_flow.engine import api

    return api.recorded_output(run_dir, stage, str(cache) if cache else None)


CACHE_ERRORS = (UsageError, StoreError, ValueError, KeyError, OSError)


# ------------------------------------------------------------------------------ gathering


def resolve_cache(doc: dict[str, Any], cache: str | None) -> Path | None:
    """--cache, else the cache run.json records, else the default cache directory."""
    from gcvd_flow.engine.paths import default_cache_dir

    if cache:
        return Path(cache).expanduser()
    rec = doc.get("cache")
    if isinstance(rec, str) and Path(rec).is_dir():
        return Path(rec)
    return default_cache_dir()


def collect(run_dir: str | Path, gt: str | Path | None = None, cache: str | None = None,
            every: int | None = None, max_frames: int = 8) -> ReportData:
    """Everything the report shows; missing cache content becomes a note, not an error."""
    from gcvd_flow.engine.api import read_run_dir

    run = load_run(run_dir)  # one-line UsageError naming the file
    doc = read_run_dir(run_dir)
    cams = read_cameras(Path(run_dir))  # checked by load_run: an object
    data = ReportData(run=run, doc=doc, cams=cams, cache=resolve_cache(doc, cache))
    store = _open_store(data.cache)
    if store is None:
        data.notes.append(f"the cache {data.cache} is not available: frames, masks and health signals "
                          "from stage outputs are left out (pass --cache DIR)")
        # the verdict cannot be "good" on half its checks (flow, bundle adjustment, loop edges)
        data.signals.append(Signal("cache", "not available", "warn",
                                   "flow, loop-edge and bundle-adjustment checks need the run's cache (--cache DIR)"))
    pos = {f: k for k, f in enumerate(run.frame_indices)}
    kf = cams.get("keyframes")
    data.keyframes = [pos[f] for f in kf if isinstance(f, int) and f in pos] if isinstance(kf, list) else []
    _graph_signals(data, store)
    _trajectory(data, gt)
    _frame_signals(data, store)
    _strip(data, store, every, max_frames)
    _stage_table(data, store)
    _settings(data)
    data.verdict = V.overall(data.signals)
    return data


def _trajectory(data: ReportData, gt: str | Path | None) -> None:
    from gcvd_flow.evaluate import metrics as M
    from gcvd_flow.evaluate.run_eval import evaluate, match_gt

    poses = data.run.poses
    data.est_positions = poses[:, :3, 3].copy()
    if gt is None:
        return
    data.metrics = evaluate(data.run.run_dir, gt)
    m = match_gt(data.run.run_dir, gt)
    s, R, t = M.umeyama_alignment(m.est[:, :3, 3], m.gt[:, :3, 3], with_scale=True)
    data.est_positions = (s * (R @ poses[:, :3, 3].T)).T + t
    g = np.full((len(poses), 3), np.nan)
    g[m.run_pos] = m.gt[:, :3, 3]
    data.gt_positions = g


def loop_edges(edges: list[dict[str, Any]], rejected: list[dict[str, Any]] | None, n: int,
               pose_graph_on: bool) -> list[dict[str, Any]]:
    """optimize_edges' loop edges as {a, b, used}: a, b the run positions of the edge's frames
    and used = kept by the pose graph (not in its ``rejected_loops``). The edges' i, j are ingest
    positions, i.e. run positions: not source frame indices (cameras.json's ``frame_indices``),
    which differ from them under ingest.start / stride (read as source indices, the edges of
    such a run were dropped or drawn at the wrong frames, and the report said "0 used")."""
    bad = {(int(r["i"]), int(r["j"])) for r in rejected or []}
    out = []
    for e in edges:
        i, j = int(e["i"]), int(e["j"])
        if 0 <= i < n and 0 <= j < n:
            out.append({"a": i, "b": j, "used": pose_graph_on and (i, j) not in bad})
    return out


def _graph_signals(data: ReportData, store: Any) -> None:
    """Keyframes and gaps, loop edges found / verified / used, pose-graph residual."""
    from gcvd_flow import pipeline as G  # the stage names as the pipeline declares them

    n, kf = len(data.run), data.keyframes
    if kf:
        gaps = np.diff([data.run.frame_indices[k] for k in kf]) if len(kf) > 1 else np.array([0])
        max_gap = int((data.doc.get("config") or {}).get("keyframes", {}).get("max_gap", G.KeyframesParams().max_gap))
        status = V.keyframe_status(n, len(kf), int(gaps.max()), max_gap)
        why = ("fewer than 3 keyframes: nothing to check the poses against" if len(kf) < V.MIN_KEYFRAMES else
               "some gaps hit keyframes.max_gap: the camera barely moved there, or flow failed"
               if gaps.max() >= max_gap else
               f"a gap of {int(gaps.max())} frames is half the clip or more: keyframes.delta too large?"
               if gaps.max() >= V.MAX_GAP_SHARE * n else "every gap from accumulated motion")
        data.signals.append(Signal(
            "keyframes", f"{len(kf)} of {n} frames, largest gap {int(gaps.max())}", status,
            f"gaps {int(gaps.min())}-{int(gaps.max())} frames (mean {gaps.mean():.1f}); {why}"))
    if store is None:
        return
    try:
        graph = recorded_part(data.doc, store, G.ASSOCIATION.name, ("graph",))
        edges = recorded_part(data.doc, store, G.OPTIMIZE_EDGES.name, ("edges",))
        pg = {k: recorded_part(data.doc, store, G.POSE_GRAPH.name, (k,))
              for k in ("enabled", "initial_error", "final_error")}
        rejected = recorded_part(data.doc, store, G.POSE_GRAPH.name, ("rejected_loops",)) if pg["enabled"] else []
    except CACHE_ERRORS + (IndexError,) as exc:
        data.notes.append(f"loop edges and pose graph: not readable from the cache ({exc})")
        return
    data.loops = loop_edges(edges, rejected, len(data.run), bool(pg["enabled"]))
    found = len(graph.get("nonsequential_edges", [])) + len(graph.get("rejected", []))
    used = sum(lp["used"] for lp in data.loops)
    data.signals.append(Signal(
        "loop edges", f"{found} found, {len(graph.get('nonsequential_edges', []))} verified, {used} used",
        "warn" if edges and not used else "ok" if used else "info",
        "candidates by descriptor similarity; verified by geometry and flow; used = kept by the pose graph"
        if found else "no revisited place detected (fine for a clip without loops)"))
    if pg["enabled"] and not used:  # without loop edges the windows' own edges are all it has
        data.signals.append(Signal("pose-graph residual", f"{float(pg['final_error']):.3g}", "info",
                                   "no loop edge used: the residual only says the windows agree with "
                                   "themselves, not that the trajectory is right"))
    elif pg["enabled"]:
        ini, fin = float(pg["initial_error"]), float(pg["final_error"])
        data.signals.append(Signal("pose-graph residual", f"{ini:.3g} → {fin:.3g}",
                                   "ok" if fin <= ini + 1e-12 else "warn",
                                   "error of all edges (loop edges included) before / after optimisation"))
    else:
        data.signals.append(Signal("pose-graph residual", "pose graph off", "info", "pose_graph.enabled=false"))
    _ba_signals(data, store)


def _ba_signals(data: ReportData, store: Any) -> None:
    """Bundle adjustment: tracks and median reprojection error; the depth-scale spread."""
    from gcvd_flow import pipeline as G  # the stage names as the pipeline declares them

    try:
        ba = {k: recorded_part(data.doc, store, G.BUNDLE_ADJUSTMENT.name, (k,)) for k in ("enabled",)}
        if ba["enabled"]:
            ba.update({k: recorded_part(data.doc, store, G.BUNDLE_ADJUSTMENT.name, (k,))
                       for k in ("landmarks", "initial_median_px", "final_median_px", "depth_scale")})
    except CACHE_ERRORS + (IndexError,) as exc:
        data.notes.append(f"bundle adjustment: not readable from the cache ({exc})")
        return
    if not ba["enabled"]:
        data.signals.append(Signal("bundle adjustment", "off", "info",
                                   "bundle_adjustment.enabled=false: no reprojection check of the poses"))
        return
    n, ini, fin = int(ba["landmarks"]), float(ba["initial_median_px"]), float(ba["final_median_px"])
    fx = float(data.run.K[0, 0])
    b, a = 1000 * ini / fx, 1000 * fin / fx  # px -> mrad: the same at every resolution
    data.signals.append(Signal(
        "bundle adjustment", f"{n} tracks, median reprojection {ini:.2f} → {fin:.2f} px ({b:.1f} → {a:.1f} mrad)",
        V.ba_status(n, b, a), f"flow tracks over 3+ keyframes (fewer than {V.BA_MIN_TRACKS}: the poses are not "
        f"checked); before: how far the optimised poses and depth are from the measured tracks (over "
        f"{V.BA_BEFORE_MRAD[0]:g} mrad: suspect), after: what adjustment could not explain"))
    scale = np.asarray(ba["depth_scale"], np.float64)
    scale = scale[np.isfinite(scale) & (scale > 0)]
    if len(scale):
        spread = float(scale.max() / scale.min())
        data.signals.append(Signal("scale spread", f"{spread:.3f}", "info",
                                   "largest / smallest depth scale bundle adjustment gave a keyframe: how much "
                                   "scale drift of the keyframe chain it corrected (shown, not judged: a good "
                                   "walk needs 6.8, see gcvd_flow/report/verdict.py)", judged=False))


def _sample(n: int, k: int) -> list[int]:
    return sorted(set(np.linspace(0, n - 1, min(n, k)).round().astype(int).tolist())) if n else []


AGREE_TOL = 0.05


def depth_agreement(run: RunData, keyframes: list[int], pairs: int = 12, stride: int = 2) -> float | None:
    """Share of keyframe depth pixels (every ``stride``-th) that, projected with the poses into
    the next keyframe, land inside it on a valid depth within AGREE_TOL of their own z; None if
    there is no pair. A self-consistency check needing no ground truth."""
    kf = keyframes if len(keyframes) >= 2 else list(range(len(run)))
    if len(kf) < 2:
        return None
    K, hits, total = run.K, 0, 0
    for m in _sample(len(kf) - 1, pairs):
        a, b = kf[m], kf[m + 1]
        da, db = run.depth(a)[::stride, ::stride], run.depth(b)
        v, u = np.nonzero(np.isfinite(da) & (da > 0))
        z = da[v, u].astype(np.float64)
        cam = np.stack([(u * stride - K[0, 2]) / K[0, 0] * z, (v * stride - K[1, 2]) / K[1, 1] * z, z], 1)
        T = np.linalg.inv(run.poses[b]) @ run.poses[a]
        pb = cam @ T[:3, :3].T + T[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            ub = np.round(pb[:, 0] / pb[:, 2] * K[0, 0] + K[0, 2])
            vb = np.round(pb[:, 1] / pb[:, 2] * K[1, 1] + K[1, 2])
        h, w = db.shape
        inside = (pb[:, 2] > 0) & (ub >= 0) & (ub <= w - 1) & (vb >= 0) & (vb <= h - 1)
        zb = db[vb[inside].astype(np.int64), ub[inside].astype(np.int64)]
        ok = zb > 0
        hits += int(np.count_nonzero(np.abs(zb[ok] - pb[inside, 2][ok]) <= AGREE_TOL * pb[inside, 2][ok]))
        total += int(np.count_nonzero(ok))
    return hits / total if total else None


def _frame_signals(data: ReportData, store: Any) -> None:
    """Share of pixels passing flow consistency, static share, valid depth share, intrinsics."""
    from gcvd_flow import pipeline as G  # the stage names as the pipeline declares them

    run = data.run
    valid = [float(np.mean(run.depth(k) > 0)) for k in _sample(len(run), 24)]
    v = float(np.mean(valid))
    data.signals.insert(0, Signal("valid depth", f"{100 * v:.1f} % of pixels", "ok" if v >= 0.5 else "warn",
                                  "pixels of depth/*.npy with a depth (> 0) after filtering"))
    bad = data.cams.get("unsolvable_frames")
    if isinstance(bad, list) and bad:  # frames the run marked invalid (masked almost entirely, no texture)
        first = bad[0] if isinstance(bad[0], dict) else {}
        data.signals.insert(1, Signal(
            "frames with nothing to solve", f"{len(bad)} of {len(run)}", "warn",
            "masked almost entirely (--masks) or without texture (black / blank): no depth or flow is "
            f"measured there, their depth is marked invalid (e.g. frame {first.get('frame')}: {first.get('why')})"))
    agree = depth_agreement(run, data.keyframes)
    if agree is not None:
        data.signals.insert(1, Signal(
            "multi-view depth agreement", f"{100 * agree:.1f} % of pixels", V.low_is_bad(agree, V.AGREEMENT),
            f"depth of each keyframe, moved by the poses into the next keyframe, within {100 * AGREE_TOL:g} % "
            "of that frame's depth (where it lands inside): poses and depth that fit each other"))
    if data.cams.get("intrinsics_warning"):  # the calibrate stage could not estimate the focal length
        data.signals.append(Signal("intrinsics", "guessed (not determined by the motion)", "warn",
                                   f"{data.cams['intrinsics_warning']}; pass --intrinsics "
                                   "(not part of the verdict: the run cannot check them)", judged=False))
    elif data.cams.get("intrinsics_guessed"):
        data.signals.append(Signal("intrinsics", "guessed", "warn",
                                   "no intrinsics given: f = 300/384 x long side; pass --intrinsics "
                                   "(not part of the verdict: the run cannot check them)", judged=False))
    elif data.cams.get("intrinsics_origin") == "estimated":
        est = data.cams.get("intrinsics_estimate")
        est = est if isinstance(est, dict) else {}
        rel = est.get("rel_sigma") if isinstance(est.get("rel_sigma"), (int, float)) else None
        fx = est.get("fx_source") if isinstance(est.get("fx_source"), (int, float)) else float("nan")
        pp = data.cams.get("principal_point")
        pp_text = ""
        if isinstance(pp, dict) and isinstance(pp.get("detail"), str):
            pp_text = f"; principal point {pp['detail']}"
        pp_warn = data.cams.get("principal_point_warning")
        data.signals.append(Signal("intrinsics", f"estimated fx {fx:.1f} px (source)"
                                   + (", principal point estimated" if isinstance(pp, dict) and pp.get("estimated")
                                      else ""), "warn" if pp_warn else "info",
                                   "focal length estimated from the video (calibrate stage)"
                                   + (f" +- {100 * rel:.1f} % (spread over frame blocks and a principal point "
                                      "2 % off)" if rel is not None else "") + pp_text, judged=False))
    if store is None:
        return
    try:
        flows = _map_output(run.run_dir, G.FLOW.name, data.cache)
        fwd = [flows[i] for i in _sample(len(flows), 24)]
        share = float(np.mean([np.mean(f["fwd_valid"]) * 0.5 + np.mean(f["bwd_valid"]) * 0.5 for f in fwd]))
        masks = _map_output(run.run_dir, G.MASKS.name, data.cache)
        static = float(np.mean([np.mean(masks[i]["static"] > 0) for i in _sample(len(masks), 24)]))
    except CACHE_ERRORS as exc:
        data.notes.append(f"flow and masks: not readable from the cache ({exc})")
        return
    data.signals.insert(0, Signal("flow consistency", f"{100 * share:.1f} % of pixels",
                                  V.low_is_bad(share, V.FLOW_CONSISTENCY),
                                  "forward-backward consistent flow between adjacent frames; low values "
                                  "mean fast motion, blur or little texture"))
    data.signals.insert(1, Signal("static pixels", f"{100 * static:.1f} %", "ok" if static >= 0.5 else "warn",
                                  "pixels the masks stage keeps as static scene (the rest is treated as moving)"))


def _strip(data: ReportData, store: Any, every: int | None, max_frames: int) -> None:
    """Every N-th frame: RGB (from the cache), depth (RUN_DIR), static mask (cache)."""
    from gcvd_flow import pipeline as G  # the stage names as the pipeline declares them

    n = len(data.run)
    step = every or max(1, -(-n // max_frames))
    frames = masks = None
    if store is not None:
        try:
            frames = _map_output(data.run.run_dir, G.RUN_DIR_SOURCES.frames, data.cache)
            masks = _map_output(data.run.run_dir, G.MASKS.name, data.cache)
        except CACHE_ERRORS as exc:
            data.notes.append(f"frames and masks: not readable from the cache ({exc})")
            frames = masks = None
    for k in range(0, n, step):
        item = {"frame": data.run.frame_indices[k], "depth": data.run.depth(k), "rgb": None, "static": None}
        if frames is not None and masks is not None:
            try:
                item["rgb"], item["static"] = frames[k]["image"], masks[k]["static"]
            except CACHE_ERRORS as exc:
                data.notes.append(f"frame {item['frame']}: not readable from the cache ({exc})")
        data.strip.append(item)


def _stage_table(data: ReportData, store: Any) -> None:
    """Per stage: output digest, items, compute seconds (cache record) and, when the run was
    started by `gcvd-flow run`, this run's seconds and executed / cached counts (its stamp)."""
    stages = data.doc.get("stages") or {}
    order = data.doc.get("stage_order") or list(stages)
    last = _last_invocation(data.run.run_dir, stages)
    for name in order:
        rec = stages.get(name) or {}
        row: dict[str, Any] = {"name": name, "digest": (rec.get("output") or "")[:12], "items": None,
                               "compute_seconds": None, **(last.get(name) or {})}
        if store is not None and rec.get("key"):
            r = store.read_record(rec["key"])
            if r is not None:
                row["items"] = len(r.get("children") or []) or 1
                row["compute_seconds"] = r.get("seconds")
        data.stages.append(row)


def _last_invocation(run_dir: Path, stages: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """executed / cached / seconds per stage from RUN_DIR/.gcvd-stamp.json when it belongs to
    the run.json at hand (the same stage records), else {}."""
    try:
        from gcvd_flow.engine import jsonio

        stamp = jsonio.loads(jsonio.read_regular(run_dir / ".gcvd-stamp.json"))
        recs = " ".join(str(r) for r in stamp.get("records") or [])
        out = {s["name"]: {"seconds": s["seconds"], "executed": s["executed"], "cached": s["cached"]}
               for s in stamp["result"]["stages"]}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):  # a stamp of another shape: none
        return {}
    if any(r.get("key") and r["key"] not in recs for r in stages.values()):
        return {}
    return out


def _settings(data: ReportData) -> None:
    """The resolved config, flattened, each with its default (differences are highlighted)."""
    from gcvd_flow.engine.api import load_spec

    config = data.doc.get("config") or {}
    defaults: dict[str, Any] = {}
    try:
        name = (data.doc.get("invocation") or {}).get("pipeline") or "gcvd"
        defaults = json.loads(load_spec(name).config_model().model_dump_json())
    except (UsageError, ValueError, TypeError) as exc:
        data.notes.append(f"defaults of the pipeline's config unavailable ({exc})")
    flat_d = dict(_flatten(defaults))
    for key, value in _flatten(config):
        d = flat_d.get(key, "?")
        data.settings.append({"key": key, "value": value, "default": d, "differs": bool(defaults) and d != value})
    data.versions = {"gcvd-flow": str(data.doc.get("gcvd_flow", "?")),
                     **{k: str(v) for k, v in (data.doc.get("env") or {}).items()}}


def _flatten(d: Any, prefix: str = "") -> list[tuple[str, Any]]:
    if isinstance(d, dict):
        return [kv for k in sorted(d) for kv in _flatten(d[k], f"{prefix}{k}.")]
    return [(prefix[:-1], d)]
