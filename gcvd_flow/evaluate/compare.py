"""`gcvd-flow compare RUN_A RUN_B`: per stage, are two runs' outputs identical, and if not, how
far apart are they (B measured against A).

Equality is the stage's output digest recorded in run.json (content-addressed: equal digests
mean byte-identical outputs). Where digests differ, the outputs are read from the caches the runs
recorded (or ``--cache``) and measured by what they hold:

* poses (N, 4, 4): ATE of B against A after a Sim(3) Umeyama alignment, RPE (delta 1), the scale;
* depth / inverse depth: median |log(B / A)| over pixels valid in both, raw and after removing
  the median log ratio (one global scale: a monocular run is defined up to scale);
* static masks: IoU of the moving (masked) regions, 1 when both are empty;
* flows: end-point error (mean |fB - fA|, px) forward and backward;
* images: mean absolute difference (0-255);
* keyframe indices and loop edges: the sets compared.

Map stages compare only the items whose digests differ (at most ``max_items``, evenly spread).
The run directories' own outputs (poses.txt, depth/*.npy) are compared too, without any cache,
and every file is checked against the digest its run.json records (``files``): "identical"
needs equal stage digests, both run dirs' files matching their run.json, and equal file digests.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from gcvd_flow.engine.errors import StoreError, UsageError
from gcvd_flow.evaluate import metrics

WHOLE_FIELDS = ("poses", "indices", "depths", "graph", "edges", "final_error", "keyframes")


def _doc(run_dir: str | Path) -> dict[str, Any]:
    from gcvd_flow.engine.api import read_run_dir

    if not Path(run_dir).is_dir():
        raise UsageError(f"{run_dir}: no such run directory")
    return read_run_dir(run_dir)


def _store(doc: dict[str, Any], cache: str | None):
    from gcvd_flow.engine.paths import default_cache_dir
    from gcvd_flow.engine.store import Store

    root = Path(cache).expanduser() if cache else Path(doc["cache"]) if isinstance(doc.get("cache"), str) \
        and Path(doc["cache"]).is_dir() else default_cache_dir()
    return Store(root, verify=True) if (root / "objects").is_dir() else None


# ------------------------------------------------------------------------------ measures


def _log_ratio(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    ok = np.isfinite(a) & np.isfinite(b) & (a > 0) & (b > 0)
    return np.log(b[ok] / a[ok])


def depth_difference(pairs: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, float]:
    """median |log(B/A)| over all valid pixels of all pairs, raw and global-scale-aligned."""
    lr = np.concatenate([_log_ratio(a, b) for a, b in pairs]) if pairs else np.zeros(0)
    if not len(lr):
        return {"median_abs_log_ratio": float("nan"), "median_abs_log_ratio_scale_aligned": float("nan")}
    return {"median_abs_log_ratio": float(np.median(np.abs(lr))),
            "median_abs_log_ratio_scale_aligned": float(np.median(np.abs(lr - np.median(lr)))),
            "scale_b_over_a": float(np.exp(np.median(lr)))}


def pose_difference(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """ATE / RPE of B against A (A is the reference), Sim(3)-aligned."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape:
        return {"error": f"pose counts differ: {len(a)} vs {len(b)}"}  # type: ignore[dict-item]
    res = metrics.ate(b, a)
    res.update(metrics.rpe(b, a))
    return {k: res[k] for k in ("ate_rmse", "scale", "rpe_trans", "rpe_rot")}


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """IoU of the moving regions (static == 0) of two static masks; 1 when both are empty."""
    ma, mb = np.asarray(a) == 0, np.asarray(b) == 0
    union = np.count_nonzero(ma | mb)
    return 1.0 if union == 0 else float(np.count_nonzero(ma & mb) / union)


def _field_measures(name: str, a: Any, b: Any) -> dict[str, float]:
    a_arr, b_arr = np.asarray(a), np.asarray(b)
    if a_arr.shape != b_arr.shape:
        return {f"{name}_shape_differs": 1.0}
    if name in ("fwd", "bwd"):
        return {f"{name}_epe_px": float(np.mean(np.linalg.norm(b_arr - a_arr, axis=-1)))}
    if name in ("depth", "inv_depth"):
        lr = _log_ratio(a_arr, b_arr)
        return {f"{name}_median_abs_log_ratio": float(np.median(np.abs(lr))) if len(lr) else float("nan")}
    if name == "static":
        return {"mask_iou": mask_iou(a_arr, b_arr)}
    if name == "image":
        return {"image_mean_abs_diff": float(np.mean(np.abs(b_arr.astype(np.float64) - a_arr)))}
    if a_arr.dtype.kind in "fiub" and a_arr.size:
        return {f"{name}_max_abs_diff": float(np.max(np.abs(b_arr.astype(np.float64) - a_arr)))}
    return {}


# ------------------------------------------------------------------------------ stages


def _map_diff(sa: Any, sb: Any, da: str, db: str, max_items: int) -> dict[str, Any]:
    from gcvd_flow.engine.artifacts import load_manifest, load_value

    ia, ib = list(load_manifest(sa, da)["items"]), list(load_manifest(sb, db)["items"])
    res: dict[str, Any] = {"items_a": len(ia), "items_b": len(ib)}
    differing = [k for k in range(min(len(ia), len(ib))) if ia[k] != ib[k]]
    res["items_differing"] = len(differing)
    if not differing:
        return res
    pick = [differing[int(round(x))] for x in np.linspace(0, len(differing) - 1, min(max_items, len(differing)))]
    acc: dict[str, list[float]] = {}
    for k in sorted(set(pick)):
        va, vb = load_value(sa, ia[k]), load_value(sb, ib[k])
        for name in sorted(set(va) & set(vb)) if isinstance(va, dict) and isinstance(vb, dict) else []:
            for m, v in _field_measures(name, va[name], vb[name]).items():
                acc.setdefault(m, []).append(v)
    res["items_compared"] = len(set(pick))
    for m, vals in acc.items():
        arr = np.asarray(vals, np.float64)
        res[m] = float(np.nanmean(arr)) if np.isfinite(arr).any() else float("nan")
        worst = np.nanmin(arr) if m == "mask_iou" else np.nanmax(arr)
        res[m + ("_min" if m == "mask_iou" else "_max")] = float(worst)
    return res


def _part(store: Any, digest: str, key: str) -> Any:
    from gcvd_flow.engine.artifacts import decode_tree, load_manifest

    node = load_manifest(store, digest).get("value")
    if not isinstance(node, dict) or key not in node:
        raise KeyError(key)
    return decode_tree(store, node[key])


def _whole_diff(sa: Any, sb: Any, da: str, db: str) -> dict[str, Any]:
    res: dict[str, Any] = {}
    for key in WHOLE_FIELDS:
        try:
            a, b = _part(sa, da, key), _part(sb, db, key)
        except KeyError:
            continue
        if key == "poses":
            res.update({f"poses_{k}": v for k, v in pose_difference(a, b).items()})
        elif key == "depths":
            res.update({f"depths_{k}": v for k, v in depth_difference(list(zip(a, b))).items()})
        elif key in ("indices", "keyframes"):
            sa_, sb_ = set(int(i) for i in a), set(int(i) for i in b)
            res[key] = {"a": len(sa_), "b": len(sb_), "common": len(sa_ & sb_)}
        elif key == "graph":
            ea = {(e["i"], e["j"]) for e in a.get("nonsequential_edges", [])}
            eb = {(e["i"], e["j"]) for e in b.get("nonsequential_edges", [])}
            res["loop_edges"] = {"a": len(ea), "b": len(eb), "common": len(ea & eb)}
        elif key == "edges":
            res["edges"] = {"a": len(a), "b": len(b)}
        elif key == "final_error":
            res["final_error"] = {"a": float(a), "b": float(b)}
    return res


def _stage_diff(name: str, ra: dict, rb: dict, sa: Any, sb: Any, max_items: int) -> dict[str, Any]:
    from gcvd_flow.engine.artifacts import ArtifactError, load_manifest

    da, db = ra.get("output"), rb.get("output")
    row: dict[str, Any] = {"stage": name, "equal": bool(da) and da == db,
                           "digest_a": (da or "")[:12], "digest_b": (db or "")[:12]}
    if row["equal"] or not (da and db):
        if not (da and db):
            row["note"] = f"not recorded in run {'A' if not da else 'B'}"
        return row
    if sa is None or sb is None:
        row["note"] = "outputs not in the cache (pass --cache): only the digests are compared"
        return row
    try:
        is_map = "items" in load_manifest(sa, da)
        row.update(_map_diff(sa, sb, da, db, max_items) if is_map else _whole_diff(sa, sb, da, db))
    except (StoreError, ArtifactError, OSError, ValueError) as exc:
        row["note"] = f"outputs not readable from the cache ({exc})"
    return row


def _run_dir_diff(a: Path, b: Path) -> dict[str, Any]:
    """poses.txt and depth/*.npy of the two run directories (common source frames)."""
    from gcvd_flow.io.run_dir import load_run

    ra, rb = load_run(a), load_run(b)
    pos_b = {f: k for k, f in enumerate(rb.frame_indices)}
    common = [(k, pos_b[f]) for k, f in enumerate(ra.frame_indices) if f in pos_b]
    res: dict[str, Any] = {"frames_a": len(ra), "frames_b": len(rb), "frames_common": len(common)}
    if len(common) >= 3:
        ka, kb = [c[0] for c in common], [c[1] for c in common]
        res["poses"] = pose_difference(ra.poses[ka], rb.poses[kb])
        step = max(1, len(common) // 24)
        same_size = (ra.width, ra.height) == (rb.width, rb.height)
        if same_size:
            res["depth"] = depth_difference([(ra.depth(i), rb.depth(j)) for i, j in common[::step]])
    return res


def _files_check(run_a: str | Path, run_b: str | Path, doc_a: dict[str, Any], doc_b: dict[str, Any]) -> dict[str, Any]:
    """The run directories' own files: each checked against the digests its run.json records
    (a file swapped, edited or missing is found even when every stage digest is equal), and the
    two runs' digests compared. {a: [problems], b: [problems], differing: [paths], equal}."""
    from gcvd_flow.engine.outputs import check_files

    fa, fb = doc_a.get("files"), doc_b.get("files")
    out: dict[str, Any] = {"a": check_files(run_a, fa), "b": check_files(run_b, fb)}
    fa, fb = fa or {}, fb or {}
    out["differing"] = sorted(k for k in set(fa) | set(fb) if fa.get(k) != fb.get(k))
    out["equal"] = not out["a"] and not out["b"] and not out["differing"]
    return out


def compare_runs(run_a: str | Path, run_b: str | Path, cache: str | None = None, cache_b: str | None = None,
                 max_items: int = 24) -> dict[str, Any]:
    """{stages: [{stage, equal, digest_a, digest_b, ...measures}], identical, outputs: {...}}."""
    doc_a, doc_b = _doc(run_a), _doc(run_b)
    sa, sb = _store(doc_a, cache), _store(doc_b, cache_b or cache)
    st_a, st_b = doc_a.get("stages") or {}, doc_b.get("stages") or {}
    order = list(doc_a.get("stage_order") or st_a) + [s for s in (doc_b.get("stage_order") or st_b) if s not in st_a]
    rows = [_stage_diff(n, st_a.get(n) or {}, st_b.get(n) or {}, sa, sb, max_items) for n in order]
    files = _files_check(run_a, run_b, doc_a, doc_b)
    res: dict[str, Any] = {"run_a": str(run_a), "run_b": str(run_b),
                           "identical": all(r["equal"] for r in rows) and files["equal"],
                           "stages": rows, "files": files}
    try:
        res["outputs"] = _run_dir_diff(Path(run_a), Path(run_b))
    except UsageError as exc:
        res["outputs"] = {"error": str(exc)}
    return res


def _fmt_row(r: dict[str, Any]) -> str:
    if r["equal"]:
        return f"{r['stage']:<20} equal      {r['digest_a']}"
    skip = {"stage", "equal", "digest_a", "digest_b"}
    parts = []
    for k, v in r.items():
        if k in skip:
            continue
        parts.append(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {json.dumps(v)}" if isinstance(v, dict)
                     else f"{k} {v}")
    return f"{r['stage']:<20} DIFFERS    {r['digest_a']} vs {r['digest_b']}: " + ", ".join(parts)


def format_comparison(res: dict[str, Any]) -> str:
    lines = [_fmt_row(r) for r in res["stages"]]
    out = res.get("outputs") or {}
    if "poses" in out:
        p = out["poses"]
        lines.append(f"{'RUN_DIR poses.txt':<20} ATE {p.get('ate_rmse', float('nan')):.4g} (B vs A, Sim(3)), "
                     f"RPE {p.get('rpe_trans', float('nan')):.4g} / {p.get('rpe_rot', float('nan')):.4g} deg, "
                     f"{out['frames_common']} common frames")
    if "depth" in out:
        lines.append(f"{'RUN_DIR depth/':<20} median |log ratio| {out['depth']['median_abs_log_ratio']:.4g} "
                     f"(scale-aligned {out['depth']['median_abs_log_ratio_scale_aligned']:.4g})")
    if "error" in out:
        lines.append(f"RUN_DIR outputs: {out['error']}")
    files = res.get("files") or {}
    for tag in ("a", "b"):
        for problem in files.get(tag, [])[:8]:
            lines.append(f"RUN_{tag.upper()} files: {problem}")
    if files.get("differing"):
        d = files["differing"]
        lines.append(f"{'RUN_DIR files':<20} {len(d)} differ: {', '.join(d[:5])}{' ...' if len(d) > 5 else ''}")
    n_stages = sum(not r["equal"] for r in res["stages"])
    if res["identical"]:
        lines.append("identical: every stage output and every run-directory file is byte-identical")
    else:
        why = [f"{n_stages} stage(s) differ"] if n_stages else []
        if not files.get("equal", True):
            why.append("the run directories' files differ" if not (files.get("a") or files.get("b"))
                       else "a run directory's files are not what its run.json records")
        lines.append("; ".join(why))
    return "\n".join(lines)
