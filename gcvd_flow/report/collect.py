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
from gcvd_flow.io.run_dir import RunData, load_run


@dataclass
class Signal:
    """One health signal: label, value as text, status ("ok" | "warn" | "info"), explanation."""

    label: str
    value: str
    status: str
    detail: str = ""


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


# ------------------------------------------------------------------------------ the cache


def _open_store(cache: Path | None):
    from gcvd_flow.engine.store import Store

    if cache is None or not (cache / "objects").is_dir():
        return None
    return Store(cache, verify=True)


def recorded_part(doc: dict[str, Any], store: Any, stage: str, path: tuple = ()) -> Any:
    """A sub-tree of the output ``run.json`` recorded for a whole stage, decoding only the objects
    under it (``engine.api.recorded_output`` decodes everything: association's flows too)."""
    from gcvd_flow.engine.artifacts import decode_tree, load_manifest

    digest = ((doc.get("stages") or {}).get(stage) or {}).get("output")
    if not digest or store is None:
        raise UsageError(f"no output of stage {stage!r} recorded or no cache")
    node = load_manifest(store, digest).get("value")
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
    cams = json.loads((Path(run_dir) / "cameras.json").read_text())
    data = ReportData(run=run, doc=doc, cams=cams, cache=resolve_cache(doc, cache))
    store = _open_store(data.cache)
    if store is None:
        data.notes.append(f"the cache {data.cache} is not available: frames, masks and health signals "
                          "from stage outputs are left out (pass --cache DIR)")
    pos = {f: k for k, f in enumerate(run.frame_indices)}
    data.keyframes = [pos[f] for f in cams.get("keyframes") or [] if f in pos]
    _graph_signals(data, store, pos)
    _trajectory(data, gt)
    _frame_signals(data, store)
    _strip(data, store, every, max_frames)
    _stage_table(data, store)
    _settings(data)
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


def _graph_signals(data: ReportData, store: Any, pos: dict[int, int]) -> None:
    """Keyframes and gaps, loop edges found / verified / used, pose-graph residual."""
    n, kf = len(data.run), data.keyframes
    if kf:
        gaps = np.diff([data.run.frame_indices[k] for k in kf]) if len(kf) > 1 else np.array([0])
        max_gap = int((data.doc.get("config") or {}).get("keyframes", {}).get("max_gap", 39))
        data.signals.append(Signal(
            "keyframes", f"{len(kf)} of {n} frames", "ok" if len(kf) >= 3 else "warn",
            f"gaps {int(gaps.min())}-{int(gaps.max())} frames (mean {gaps.mean():.1f}); "
            + ("some gaps hit keyframes.max_gap: the camera barely moved there, or flow failed"
               if gaps.max() >= max_gap else "every gap from accumulated motion")))
    if store is None:
        return
    try:
        graph = recorded_part(data.doc, store, "association", ("graph",))
        edges = recorded_part(data.doc, store, "optimize_edges", ("edges",))
        pg = {k: recorded_part(data.doc, store, "pose_graph", (k,))
              for k in ("enabled", "initial_error", "final_error")}
        rejected = recorded_part(data.doc, store, "pose_graph", ("rejected_loops",)) if pg["enabled"] else []
    except CACHE_ERRORS + (IndexError,) as exc:
        data.notes.append(f"loop edges and pose graph: not readable from the cache ({exc})")
        return
    bad = {(int(r["i"]), int(r["j"])) for r in rejected or []}
    for e in edges:
        i, j = int(e["i"]), int(e["j"])
        if i in pos and j in pos:
            data.loops.append({"a": pos[i], "b": pos[j], "used": (i, j) not in bad and bool(pg["enabled"])})
    found = len(graph.get("nonsequential_edges", [])) + len(graph.get("rejected", []))
    used = sum(lp["used"] for lp in data.loops)
    data.signals.append(Signal(
        "loop edges", f"{found} found, {len(graph.get('nonsequential_edges', []))} verified, {used} used",
        "warn" if edges and not used else "ok" if used else "info",
        "candidates by descriptor similarity; verified by geometry and flow; used = kept by the pose graph"
        if found else "no revisited place detected (fine for a clip without loops)"))
    if pg["enabled"]:
        ini, fin = float(pg["initial_error"]), float(pg["final_error"])
        data.signals.append(Signal("pose-graph residual", f"{ini:.3g} → {fin:.3g}",
                                   "ok" if fin <= ini + 1e-12 else "warn",
                                   "error of all edges before / after optimisation"))
    else:
        data.signals.append(Signal("pose-graph residual", "pose graph off", "info", "pose_graph.enabled=false"))


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
    run = data.run
    valid = [float(np.mean(run.depth(k) > 0)) for k in _sample(len(run), 24)]
    v = float(np.mean(valid))
    data.signals.insert(0, Signal("valid depth", f"{100 * v:.1f} % of pixels", "ok" if v >= 0.5 else "warn",
                                  "pixels of depth/*.npy with a depth (> 0) after filtering"))
    agree = depth_agreement(run, data.keyframes)
    if agree is not None:
        data.signals.insert(1, Signal(
            "multi-view depth agreement", f"{100 * agree:.1f} % of pixels", "ok" if agree >= 0.6 else "warn",
            f"depth of each keyframe, moved by the poses into the next keyframe, within {100 * AGREE_TOL:g} % "
            "of that frame's depth (where it lands inside): poses and depth that fit each other"))
    if data.cams.get("intrinsics_warning"):  # the calibrate stage could not estimate the focal length
        data.signals.append(Signal("intrinsics", "guessed (not determined by the motion)", "warn",
                                   data.cams["intrinsics_warning"] + "; pass --intrinsics"))
    elif data.cams.get("intrinsics_guessed"):
        data.signals.append(Signal("intrinsics", "guessed", "warn",
                                   "no intrinsics given: f = 300/384 x long side; pass --intrinsics"))
    elif data.cams.get("intrinsics_origin") == "estimated":
        est = data.cams.get("intrinsics_estimate", {})
        rel = est.get("rel_sigma")
        data.signals.append(Signal("intrinsics", f"estimated fx {est.get('fx_source', 0.0):.1f} px (source)", "info",
                                   "focal length estimated from the video (calibrate stage)"
                                   + (f", formal +- {100 * rel:.2f} %" if rel is not None else "")))
    if store is None:
        return
    try:
        flows = _map_output(run.run_dir, "flow", data.cache)
        fwd = [flows[i] for i in _sample(len(flows), 24)]
        share = float(np.mean([np.mean(f["fwd_valid"]) * 0.5 + np.mean(f["bwd_valid"]) * 0.5 for f in fwd]))
        masks = _map_output(run.run_dir, "masks", data.cache)
        static = float(np.mean([np.mean(masks[i]["static"] > 0) for i in _sample(len(masks), 24)]))
    except CACHE_ERRORS as exc:
        data.notes.append(f"flow and masks: not readable from the cache ({exc})")
        return
    data.signals.insert(0, Signal("flow consistency", f"{100 * share:.1f} % of pixels",
                                  "ok" if share >= 0.6 else "warn",
                                  "forward-backward consistent flow between adjacent frames; low values "
                                  "mean fast motion, blur or little texture"))
    data.signals.insert(1, Signal("static pixels", f"{100 * static:.1f} %", "ok" if static >= 0.5 else "warn",
                                  "pixels the masks stage keeps as static scene (the rest is treated as moving)"))


def _strip(data: ReportData, store: Any, every: int | None, max_frames: int) -> None:
    """Every N-th frame: RGB (from the cache), depth (RUN_DIR), static mask (cache)."""
    n = len(data.run)
    step = every or max(1, -(-n // max_frames))
    frames = masks = None
    if store is not None:
        try:
            frames = _map_output(data.run.run_dir, "ingest", data.cache)
            masks = _map_output(data.run.run_dir, "masks", data.cache)
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
        stamp = json.loads((run_dir / ".gcvd-stamp.json").read_text())
        recs = " ".join(stamp.get("records") or [])
        out = {s["name"]: {"seconds": s["seconds"], "executed": s["executed"], "cached": s["cached"]}
               for s in stamp["result"]["stages"]}
    except (OSError, ValueError, KeyError, TypeError):
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
