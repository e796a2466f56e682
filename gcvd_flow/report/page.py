"""The report as one self-contained HTML page: inline CSS, images as data: URIs, no script,
no external reference (it opens from an e-mail attachment, offline, with scripts disabled)."""

from __future__ import annotations

import datetime
import html
from typing import Any

from gcvd_flow.report import figures
from gcvd_flow.report.collect import ReportData

CSP = "default-src 'none'; img-src data:; style-src 'unsafe-inline'; base-uri 'none'; form-action 'none'"
CSS = """
body{font:14px/1.45 system-ui,-apple-system,'Segoe UI',Roboto,'DejaVu Sans',sans-serif;margin:24px auto;
max-width:1100px;color:#1d1d1f;padding:0 16px}
h1{font-size:22px;margin:0 0 4px}h2{font-size:17px;margin:28px 0 8px;border-bottom:1px solid #ddd;padding-bottom:4px}
.sub{color:#666;margin-bottom:16px}
table{border-collapse:collapse;margin:6px 0}td,th{padding:3px 10px;border-bottom:1px solid #eee;text-align:left;
vertical-align:top}th{background:#f5f5f7}td.num{text-align:right;font-variant-numeric:tabular-nums}
.verdict{border:2px solid #ccc;border-radius:8px;padding:10px 16px;background:#fafafa}
.big td{font-size:16px}.badge{display:inline-block;min-width:40px;text-align:center;border-radius:4px;
padding:0 6px;font-size:12px;font-weight:600;color:#fff}.ok{background:#2e7d32}.warn{background:#e65100}
.info{background:#607d8b}.fail{background:#b71c1c}tr.diff td{background:#fff3cd;font-weight:600}.note{color:#8a4b00}
.strip{display:flex;flex-wrap:wrap;gap:10px}.strip figure{margin:0;text-align:center;font-size:12px}
.strip img{display:block;width:150px;height:auto;margin-bottom:2px;image-rendering:auto}
code{background:#f2f2f2;padding:0 3px;border-radius:3px}details summary{cursor:pointer;color:#0b57d0}
img.traj{max-width:100%;height:auto}
"""


def _e(x: Any) -> str:
    return html.escape(str(x))


def _fmt(v: Any) -> str:
    if isinstance(v, bool) or v is None:
        return {True: "true", False: "false", None: "null"}[v]
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return str(v)


VERDICT_TEXT = {
    "good": "every judged health signal is ok: poses, depth and flow agree with each other",
    "suspect": "some health signals warn (below): the run may be off; check them before using it",
    "failed": "a health signal failed (below): the run is not usable as it is",
}


def _banner(d: ReportData) -> str:
    """good / suspect / failed from the self-consistency signals (report/verdict.py)."""
    cls = {"good": "ok", "suspect": "warn", "failed": "fail"}[d.verdict]
    return (f"<p class='overall' id='overall'><span class='badge {cls}'>{_e(d.verdict)}</span> "
            f"<b>Verdict: {_e(d.verdict)}</b> — {_e(VERDICT_TEXT[d.verdict])} (no ground truth used).</p>")


def _verdict(d: ReportData) -> str:
    m, kf = d.metrics, len(d.keyframes)
    if m is None:
        head = ("<p><b>No ground truth given</b> (<code>--gt GT_DIR</code> adds ATE / RPE / depth errors): "
                "the run's own health signals.</p>")
        return f'<div class="verdict" id="verdict">{_banner(d)}{head}{_signals(d)}</div>'
    rows = [("ATE RMSE (Sim(3)-aligned)", f"{m['ate_rmse'] * 100:.2f} cm",
             f"{m['ate_percent_of_path']:.2f} % of the {m['path_length']:.2f} m path"),
            ("RPE", f"{m['rpe_trans'] * 100:.2f} cm", f"{m['rpe_rot']:.3f}° per frame")]
    if "abs_rel" in m:
        rows.append(("depth AbsRel", f"{m['abs_rel']:.4f}", f"over {m.get('depth_frames', 0)} frames, per-frame median scaling"))
        if "abs_rel_confident" in m:
            conf = m["abs_rel_confident"]
            rows.append(("depth AbsRel, confident pixels",
                         f"{conf:.4f}" if isinstance(conf, float) and conf == conf else "no confident pixel",
                         "pixels with confidence >= 0.5 only (what the exports' masks keep)"))
        rows.append(("depth δ<1.25", f"{100 * m['delta1']:.1f} %", "share of pixels within 25 %"))
    rows.append(("frames / keyframes", f"{m['frames']} / {kf}",
                 f"matched to ground truth by {m.get('association', 'frame index')}"))
    body = "".join(f"<tr><th>{_e(a)}</th><td class='num'>{_e(b)}</td><td>{_e(c)}</td></tr>" for a, b, c in rows)
    return (f'<div class="verdict" id="verdict">{_banner(d)}<table class="big" id="metrics">{body}</table>'
            f"<h3>health signals</h3>{_signals(d)}</div>")


def _signals(d: ReportData) -> str:
    rows = "".join(f"<tr><td><span class='badge {s.status}'>{_e(s.status)}</span></td><th>{_e(s.label)}</th>"
                   f"<td>{_e(s.value)}</td><td>{_e(s.detail)}</td></tr>" for s in d.signals)
    return f'<table id="signals">{rows}</table>'


def _strip(d: ReportData) -> str:
    figs = []
    for it in d.strip:
        imgs = []
        if it["rgb"] is not None:
            imgs.append(f'<img class="rgb" alt="frame {it["frame"]}" src="{figures.data_uri(figures.rgb_tile(it["rgb"]))}">')
        imgs.append(f'<img class="depth" alt="depth {it["frame"]}" src="{figures.data_uri(figures.depth_tile(it["depth"]))}">')
        if it["static"] is not None:
            imgs.append(f'<img class="mask" alt="mask {it["frame"]}" '
                        f'src="{figures.data_uri(figures.mask_tile(it["static"], it["rgb"]))}">')
        figs.append(f"<figure>{''.join(imgs)}<figcaption>frame {it['frame']}</figcaption></figure>")
    return (f'<p>{_every(max(1, _step(d)))}: RGB, depth (turbo, inverse depth: near = red, invalid = black), '
            f'motion mask (magenta = treated as moving).</p><div class="strip" id="strip">{"".join(figs)}</div>')


def _every(n: int) -> str:
    """1 -> "Every frame", 2 -> "Every 2nd frame", 3 -> "Every 3rd frame", 11 -> "Every 11th frame"."""
    if n == 1:
        return "Every frame"
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"Every {n}{suffix} frame"


def _step(d: ReportData) -> int:
    fr = [it["frame"] for it in d.strip]
    idx = d.run.frame_indices
    return (idx.index(fr[1]) - idx.index(fr[0])) if len(fr) > 1 else 1


def _stages(d: ReportData) -> str:
    def num(v: Any, f: str = "{:.2f}") -> str:
        return "" if v is None else f.format(v)

    rows = "".join(
        f"<tr><td>{_e(s['name'])}</td><td class='num'>{num(s.get('seconds'))}</td>"
        f"<td class='num'>{num(s.get('items'), '{}')}</td><td class='num'>{num(s.get('executed'), '{}')}</td>"
        f"<td class='num'>{num(s.get('cached'), '{}')}</td><td class='num'>{num(s.get('compute_seconds'))}</td>"
        f"<td><code>{_e(s['digest'])}</code></td></tr>" for s in d.stages)
    return ("<table id='stages'><tr><th>stage</th><th>seconds (last run)</th><th>items</th><th>executed</th>"
            "<th>cached</th><th>compute s (cache record)</th><th>output digest</th></tr>" + rows + "</table>"
            "<p>seconds (last run): wall time of the stage in the last <code>gcvd-flow run</code> of this "
            "directory (near 0 when its outputs came from the cache); compute s: the time the cache record "
            "says computing the outputs took, whenever and wherever that was.</p>")


def _settings(d: ReportData) -> str:
    diff = [s for s in d.settings if s["differs"]]

    def rows(items: list[dict[str, Any]]) -> str:
        return "".join(f"<tr class='{'diff' if s['differs'] else ''}'><td><code>{_e(s['key'])}</code></td>"
                       f"<td>{_e(_fmt(s['value']))}</td><td>{_e(_fmt(s['default']))}</td></tr>" for s in items)

    head = "<tr><th>setting</th><th>value</th><th>default</th></tr>"
    inv = d.doc.get("invocation") or {}
    lines = [f"<p>Input <code>{_e(inv.get('input'))}</code>; profile {_e(inv.get('profile') or 'none')}; "
             f"--set {_e(' '.join(inv.get('sets') or []) or 'none')}.</p>",
             f"<p>{len(diff)} setting(s) differ from the defaults (highlighted):</p>",
             f"<table id='settings-diff'>{head}{rows(diff)}</table>" if diff else "",
             f"<details><summary>all {len(d.settings)} settings</summary><table id='settings'>{head}"
             f"{rows(d.settings)}</table></details>",
             "<h3>library versions</h3><table id='versions'>"
             + "".join(f"<tr><td>{_e(k)}</td><td>{_e(v)}</td></tr>" for k, v in d.versions.items()) + "</table>"]
    return "".join(lines)


def render(d: ReportData) -> str:
    """The whole page (a str of HTML)."""
    cams = d.cams
    title = f"gcvd-flow report: {d.run.run_dir.name}"
    unit = "m, ground truth's" if d.gt_positions is not None else "run units: one unknown global scale"
    assert d.est_positions is not None  # collect() sets it
    traj = figures.trajectory_png(d.est_positions, d.gt_positions, d.keyframes, d.loops, unit=unit)
    sub = (f"{_e(d.run.run_dir)} · {len(d.run)} frames at {cams.get('width')}x{cams.get('height')} · "
           f"fx {cams.get('fx', float(d.run.K[0, 0])):.1f}{' (guessed)' if cams.get('intrinsics_guessed') else ''}"
           f" · written {datetime.datetime.now().strftime('%Y-%m-%d %H:%M')}")
    notes = "".join(f"<p class='note'>note: {_e(n)}</p>" for n in d.notes)
    loops = (f" {sum(lp['used'] for lp in d.loops)} loop edge(s) used (red), "
             f"{sum(not lp['used'] for lp in d.loops)} rejected (dashed).") if d.loops else ""
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        "<meta name='viewport' content='width=device-width, initial-scale=1'>",
        # the page itself forbids scripts and every load that is not inline (images: data: URIs)
        f'<meta http-equiv="Content-Security-Policy" content="{CSP}">',
        f"<title>{_e(title)}</title><style>{CSS}</style></head><body>",
        f"<h1>{_e(title)}</h1><div class='sub'>{sub}</div>", _verdict(d), notes,
        "<h2>Trajectory</h2>",
        "<p>Camera centres, "
        f"{'aligned to the ground truth (Sim(3), Umeyama)' if d.gt_positions is not None else 'as estimated (one global scale)'};"
        f" {len(d.keyframes)} keyframes (orange).{loops}</p>",
        f"<img class='traj' id='trajectory' alt='trajectory' width='864' height='396' src='{figures.data_uri(traj)}'>",
        "<h2>Frames, depth and motion masks</h2>", _strip(d),
        "<h2>Stages</h2>", _stages(d),
        "<h2>Settings</h2>", _settings(d),
        "</body></html>",
    ]
    return "\n".join(parts)

