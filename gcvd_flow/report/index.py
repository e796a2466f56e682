"""`gcvd-flow report DIR` on a sweep (or any folder of runs): an index page.

* the runs table (`gcvd-flow runs`: the parameters that differ, the metrics, stages reused /
  computed), each run's name linking to its own report, written beside it (RUN/report.html);
* per swept parameter, a plot of each headline metric against it (one line per setting of the
  other swept parameters).

The page is as self-contained as a run's report (inline CSS, images as data: URIs, no script,
the same Content-Security-Policy); its only references are the relative links to the runs'
reports, which a browser follows when clicked and never loads by itself.
"""

from __future__ import annotations

import datetime
import html
import io
import json
import math
import os
from pathlib import Path
from typing import Any

from gcvd_flow.engine.errors import StoreError, UsageError
from gcvd_flow.report.page import CSP, CSS

INDEX_FILE = "index.html"
# plotted against each swept parameter, when the runs have them (lower is better except delta1)
PLOT_METRICS = (("ate_rmse", "ATE RMSE (m)"), ("rpe_trans", "RPE trans (m)"), ("abs_rel", "depth AbsRel"),
                ("delta1", "depth δ<1.25"))
TABLE_METRICS = ("ate_rmse", "ate_percent_of_path", "rpe_trans", "rpe_rot", "abs_rel", "delta1", "keyframes")
# the best run of these is highlighted (keyframes is a count, not a quality)
LOWER_IS_BETTER = ("ate_rmse", "ate_percent_of_path", "rpe_trans", "rpe_rot", "abs_rel")
HIGHER_IS_BETTER = ("delta1",)


def is_folder_of_runs(path: str | Path) -> bool:
    """A directory with no run.json of its own that holds run directories."""
    from gcvd_flow.engine.runs import find_run_dirs

    p = Path(path)
    return p.is_dir() and not (p / "run.json").exists() and bool(find_run_dirs([str(p)]))


def _e(x: Any) -> str:
    return html.escape(str(x), quote=True)


def _num(v: Any) -> float | None:
    """A finite number as a float, else None (NaN / infinity are not plotted or ranked)."""
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        return None
    f = float(v)  # jsonio bounds integers: no OverflowError
    return f if math.isfinite(f) else None


def _tex_safe(text: Any) -> str:
    """Text matplotlib shows as is: ``$`` would start mathtext (``$\\foo$`` raises)."""
    return str(text).replace("$", r"\$")


def plot_png(doc: dict[str, Any], param: str, metrics: list[tuple[str, str]], dpi: int = 90) -> bytes:
    """Each metric (one panel each) against ``param``: points of the runs, joined when the other
    swept parameters are equal. Numeric parameters on a numeric axis, others as categories."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    runs = doc["runs"]
    others = [k for k in doc["params"] if k != param]
    xs = [r["params"].get(param) for r in runs]
    numeric = all(_num(x) is not None for x in xs)
    cats = sorted({json.dumps(x, sort_keys=True) for x in xs}) if not numeric else []
    fig = Figure(figsize=(2.6 * len(metrics) + 0.6, 2.7), dpi=dpi)
    for n, (key, label) in enumerate(metrics):
        ax = fig.add_subplot(1, len(metrics), n + 1)
        groups: dict[str, list[tuple[float, float]]] = {}
        for r, x in zip(runs, xs):
            y = _num(r["metrics"].get(key))
            if y is None:
                continue
            xv = _num(x) if numeric else float(cats.index(json.dumps(x, sort_keys=True)))
            if xv is None:
                continue
            g = _tex_safe(", ".join(f"{k}={r['params'].get(k)}" for k in others))
            groups.setdefault(g, []).append((xv, y))
        for g, pts in sorted(groups.items()):
            pts.sort()
            ax.plot([p[0] for p in pts], [p[1] for p in pts], marker="o", lw=1.4, ms=5, label=g or None)
        if not numeric:
            ax.set_xticks(range(len(cats)), [_tex_safe(_cat_label(c)) for c in cats], rotation=30, fontsize=8)
        ax.set_title(label, fontsize=10)
        ax.set_xlabel(_tex_safe(param), fontsize=9)
        ax.grid(True, lw=0.3)
        ax.tick_params(labelsize=8)
        if n == 0 and others and len(groups) > 1:
            ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def _cat_label(c: str) -> str:
    """A category's tick label: a string value as itself, others as JSON (cut at 40 characters)."""
    v = json.loads(c)
    text = v if isinstance(v, str) else c
    return text if len(text) <= 40 else text[:37] + "..."


def _best(doc: dict[str, Any], key: str) -> str | None:
    vals = [(v, r["name"]) for r in doc["runs"] if (v := _num(r["metrics"].get(key))) is not None]
    if not vals or key not in LOWER_IS_BETTER + HIGHER_IS_BETTER:
        return None
    return (max(vals) if key in HIGHER_IS_BETTER else min(vals))[1]


def _table(doc: dict[str, Any], links: dict[str, str], metrics: list[str]) -> str:
    best = {m: _best(doc, m) for m in metrics}
    head = ("<tr><th>run (its report)</th>" + "".join(f"<th>{_e(k)}</th>" for k in doc["params"])
            + "".join(f"<th>{_e(m)}</th>" for m in metrics) + "<th>stages reused / computed</th><th>finished</th></tr>")
    rows = []
    for r in doc["runs"]:
        st = r["stages"]
        link = links.get(r["out"])
        name = f"<a href='{_e(link)}'>{_e(r['name'])}</a>" if link else f"{_e(r['name'])} (no report)"
        cells = [f"<td>{name}</td>"]
        cells += [f"<td class='num'>{_e(_fmt(r['params'].get(k)))}</td>" for k in doc["params"]]
        cells += [f"<td class='num{' best' if best[m] == r['name'] else ''}'>{_e(_fmt(r['metrics'].get(m)))}</td>"
                  for m in metrics]
        counts = f"{st['reused']} / {st['computed']}" if st else ""
        cells.append(f"<td class='num'>{_e(counts)}</td>")
        cells.append(f"<td class='when'>{_e(r['when'].removesuffix(' UTC'))}</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table id='runs'>{head}{''.join(rows)}</table>"


def _fmt(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, (list, dict)):
        return json.dumps(v)
    return str(v)


def _sweep_line(folder: Path) -> str:
    """What sweep.json says about the sweep (input, grid, shared settings), if present and of the
    shape `sweep` writes (anything else: nothing; an unreadable one is a note of the runs table)."""
    from gcvd_flow.engine import jsonio

    try:
        doc = jsonio.load_optional(folder / "sweep.json", "sweep record")
    except UsageError:
        return ""
    if not isinstance(doc, dict) or not isinstance(doc.get("grid"), list):
        return ""
    grid = "; ".join(f"{_fmt(g.get('key'))} = {', '.join(_fmt(v) for v in g['values'])}"
                     for g in doc["grid"] if isinstance(g, dict) and isinstance(g.get("values"), list))
    sets: list[Any] = doc["sets"] if isinstance(doc.get("sets"), list) else []
    profile = doc.get("profile") if isinstance(doc.get("profile"), str) else None
    return (f"<p id='sweep'>Sweep of <code>{_e(_fmt(doc.get('input')))}</code>: {_e(grid)}; shared --set "
            f"{_e(' '.join(_fmt(x) for x in sets) or 'none')}; profile {_e(profile or 'none')}.</p>")


def _broken(doc: dict[str, Any]) -> str:
    """The runs that could not be read, each with its one-line error, and notes on the folder."""
    items = [f"<li><code>{_e(b['name'])}</code>: {_e(b['error'])}</li>" for b in doc.get("broken") or []]
    notes = [f"<li>{_e(n)}</li>" for n in doc.get("notes") or []]
    out = ""
    if items:
        out += (f"<h3>Broken runs ({len(items)})</h3><p>These run directories could not be read; "
                f"they are not in the table.</p><ul id='broken'>{''.join(items)}</ul>")
    if notes:
        out += f"<ul class='note'>{''.join(notes)}</ul>"
    return out


def render_index(folder: Path, doc: dict[str, Any], links: dict[str, str], to: Path) -> str:
    from gcvd_flow.report import figures

    metrics = [m for m in TABLE_METRICS if m in doc["metrics"]]
    plotted = [(k, lab) for k, lab in PLOT_METRICS if k in doc["metrics"]]
    plots = []
    for p in doc["params"]:
        if not plotted:
            break
        plots.append(f"<h3>{_e(p)}</h3><img class='plot' alt='metrics against {_e(p)}' "
                     f"src='{figures.data_uri(plot_png(doc, p, plotted))}'>")
    if not plotted:
        plots = ["<p class='note'>No metrics: evaluate the runs (<code>gcvd-flow report DIR --gt GT_DIR</code>, "
                 "or <code>sweep --gt</code>) to plot them against the swept parameters.</p>"]
    elif not doc["params"]:
        plots = ["<p>The runs do not differ in any parameter.</p>"]
    title = f"gcvd-flow runs: {folder.resolve().name}"
    n_broken = f" + {len(doc['broken'])} broken" if doc.get("broken") else ""
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        "<meta name='viewport' content='width=device-width, initial-scale=1'>",
        f'<meta http-equiv="Content-Security-Policy" content="{CSP}">',
        f"<title>{_e(title)}</title><style>{CSS}td.best{{background:#e3f4e4;font-weight:600}}"
        f"img.plot{{max-width:100%;height:auto}}#runs td,#runs th{{font-size:13px;padding:3px 6px}}"
        f"#runs td{{white-space:nowrap}}td.when{{color:#666}}</style></head><body>",
        f"<h1>{_e(title)}</h1><div class='sub'>{_e(folder)} · {len(doc['runs'])} runs{n_broken} · written "
        f"{datetime.datetime.now().strftime('%Y-%m-%d %H:%M')}</div>",
        _sweep_line(folder),
        "<h2>Runs</h2>",
        f"<p>Parameters that differ between the runs; metrics from each run's metrics.json (best in green); "
        f"finished in UTC. A run's name links to its own report.</p>{_table(doc, links, metrics)}{_broken(doc)}",
        "<h2>Metrics against the swept parameters</h2>", "".join(plots),
        "</body></html>"]
    return "\n".join(parts)


def write_index(folder: str | Path, to: str | Path | None = None, gt: str | Path | None = None,
                cache: str | None = None, every: int | None = None, log: Any = None) -> Path:
    """Write each run's report (RUN/report.html) and the index page (default DIR/index.html).
    With ``gt`` every run is evaluated first (its metrics.json is written). A run that cannot be
    read, evaluated or reported is listed as such (and said through ``log``); the others are shown."""
    from gcvd_flow.engine.runs import collect
    from gcvd_flow.report import check_page_path, write_page, write_report

    say = log or (lambda m: None)
    folder = Path(folder)
    out = check_page_path(Path(to) if to else folder / INDEX_FILE)
    if gt is not None:
        _evaluate_all(folder, gt, say)
    doc = collect([str(folder)], keep_broken=True)
    for b in doc["broken"]:
        say(f"warning: {b['name']}: broken, left out: {b['error']}")
    for n in doc["notes"]:
        say(f"warning: {n}")
    if not doc["runs"] and not doc["broken"]:
        raise UsageError(f"{folder}: no run directories found")
    sort = next((m for m in ("ate_rmse", "abs_rel") if m in doc["metrics"]), None)
    if sort is not None:
        from gcvd_flow.engine.runs import sort_rows

        doc["runs"] = sort_rows(doc["runs"], sort)
    links: dict[str, str] = {}
    for r in doc["runs"]:
        try:
            page = write_report(r["out"], gt=gt, cache=cache, every=every)
        except (UsageError, StoreError, OSError) as exc:  # one broken run must not hide the others
            say(f"{r['name']}: no report: {_line(exc)}")
            continue
        links[r["out"]] = Path(os.path.relpath(page.resolve(), out.resolve().parent)).as_posix()
    write_page(out, render_index(folder, doc, links, out))
    return out


def _evaluate_all(folder: Path, gt: str | Path, say: Any) -> None:
    """metrics.json of every readable run (a run that cannot be evaluated is said and skipped)."""
    from gcvd_flow.engine.runs import collect
    from gcvd_flow.evaluate.run_eval import evaluate, write_metrics

    for r in collect([str(folder)], keep_broken=True)["runs"]:
        try:
            write_metrics(r["out"], evaluate(r["out"], gt))
        except (UsageError, StoreError, OSError) as exc:
            say(f"warning: {r['name']}: not evaluated: {_line(exc)}")


def _line(exc: BaseException) -> str:
    text = (str(exc).splitlines() or [""])[0]
    if isinstance(exc, OSError) and exc.strerror:
        text = f"{exc.filename}: {exc.strerror}" if exc.filename else exc.strerror
    return text or type(exc).__name__
