"""``RUN_DIR/report.html``: one self-contained page (inline CSS, relative links to PNGs) with the
run's settings and stage timings (``run.json``), single-view vs multi-view metrics
(``evaluate/{single_view,multi_view}/scores.json``), the evaluation plots and every group figure.

Every text that comes from a file is escaped (:func:`html.escape`); every link is relative to
the page and points to a file that exists when the page is written.
"""

from __future__ import annotations

import datetime as _dt
import html
import json
import os
from pathlib import Path
from urllib.parse import quote

from ..io import atomic
from ..pipeline.layout import MANIFEST

EVALS = (("single_view", "single view"), ("multi_view", "multi-view"))
# (key of scores.json, label, unit or None), in display order; other numeric keys follow.
METRICS = [
    ("bop19_average_recall", "BOP19 AR (mean of VSD, MSSD, MSPD)"),
    ("bop19_average_recall_vsd", "AR<sub>VSD</sub>"),
    ("bop19_average_recall_mssd", "AR<sub>MSSD</sub>"),
    ("bop19_average_recall_mspd", "AR<sub>MSPD</sub>"),
    ("bop19_average_recall_mssd_mspd", "AR (mean of MSSD, MSPD)"),
    ("auc_adds", "AUC of ADD-S (0&ndash;10 cm)"),
    ("auc_add_or_adds", "AUC of ADD(-S) (0&ndash;10 cm)"),
    ("recall_adds_0.1d", "recall ADD-S &lt; 0.1 d"),
    ("auc_adds_pooled", "AUC of ADD-S, pooled over objects"),
    ("auc_add_or_adds_pooled", "AUC of ADD(-S), pooled over objects"),
    ("vivo_auc_adds", "ViVo AUC of ADD-S"),
    ("vivo_recall_adds_0.1d", "ViVo recall ADD-S &lt; 0.1 d"),
    ("vivo_map_adds_0.1d", "ViVo mAP ADD-S &lt; 0.1 d"),
]
NOT_METRICS = {"seconds", "symmetry_steps"}

CSS = """
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; margin: 1.5em auto; max-width: 1500px;
       padding: 0 1em; color: #222; line-height: 1.4; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; } h2 { font-size: 1.25em; border-bottom: 1px solid #ddd;
     padding-bottom: 0.2em; margin-top: 1.6em; }
.meta { color: #555; font-size: 0.92em; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.7em; text-align: left; vertical-align: top; }
th { background: #f3f3f3; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
td.better { font-weight: bold; } td.pos { color: #1a7f37; } td.neg { color: #b42318; }
code, pre { font-family: Menlo, Consolas, monospace; font-size: 0.88em; }
pre { background: #f7f7f7; padding: 0.5em; overflow-x: auto; margin: 0.2em 0; }
details { margin: 0.3em 0; } summary { cursor: pointer; }
figure { margin: 1em 0 2em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { color: #444; font-size: 0.92em; margin-top: 0.3em; }
.plots { display: flex; flex-wrap: wrap; gap: 1em; } .plots figure { flex: 1 1 600px; margin: 0.5em 0; }
.warn { color: #b42318; }
"""


def _e(x) -> str:
    return html.escape(str(x), quote=True)


def _href(target: Path, base: Path) -> str:
    rel = os.path.relpath(Path(target).resolve(), Path(base).resolve())
    return _e(quote(Path(rel).as_posix()))


def _read_json(path: Path) -> tuple[dict | None, str | None]:
    if not path.is_file():
        return None, None
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        return None, f"{path}: unreadable ({e})"
    if not isinstance(doc, dict):
        return None, f"{path}: not a JSON object"
    return doc, None


def _num(v) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return float(v)


def _fmt(v, digits: int = 3) -> str:
    x = _num(v)
    if x is None:
        return "&mdash;"
    return f"{x:.{digits}f}"


def metrics_table(scores: dict[str, dict]) -> str:
    """HTML table: one row per metric present in any of ``scores`` ({column label: scores.json}),
    one column per evaluation, and the difference of the last two columns."""
    cols = list(scores)
    keys = [(k, label) for k, label in METRICS if any(_num(s.get(k)) is not None or k in s for s in scores.values())]
    known = {k for k, _ in METRICS}
    extra = sorted({k for s in scores.values() for k, v in s.items()
                    if k not in known and k not in NOT_METRICS and _num(v) is not None})
    keys += [(k, _e(k)) for k in extra]
    if not keys:
        return "<p>No metrics in the scores files.</p>"
    head = "".join(f"<th>{_e(c)}</th>" for c in cols)
    diff = len(cols) >= 2
    rows = [f"<tr><th>metric</th>{head}" + (f"<th>{_e(cols[-1])} &minus; {_e(cols[-2])}</th>" if diff else "")
            + "</tr>"]
    for k, label in keys:
        # compared as shown (3 decimals): no bold winner or signed difference for a tie on the page
        vals = [None if _num(scores[c].get(k)) is None else round(_num(scores[c].get(k)), 3) for c in cols]
        best = max((v for v in vals if v is not None), default=None)
        cells = []
        for v in vals:
            unique_best = diff and v is not None and v == best and sum(x == best for x in vals) == 1
            cls = "num better" if unique_best else "num"
            cells.append(f'<td class="{cls}">{_fmt(v)}</td>')
        row = f"<tr><td>{label} <code>{_e(k)}</code></td>{''.join(cells)}"
        if diff:
            a, b = vals[-2], vals[-1]
            if a is None or b is None:
                row += '<td class="num">&mdash;</td>'
            else:
                d = round(b - a, 3) + 0.0  # + 0.0: no "-0.000"
                row += f'<td class="num {"pos" if d > 0 else "neg" if d < 0 else ""}">{d:+.3f}</td>'
        rows.append(row + "</tr>")
    return "<table>\n" + "\n".join(rows) + "\n</table>"


def _counts_table(scores: dict[str, dict]) -> str:
    keys = sorted({k for s in scores.values() for k, v in (s.get("counts") or {}).items() if _num(v) is not None})
    if not keys:
        return ""
    rows = ["<tr><th>counts</th>" + "".join(f"<th>{_e(c)}</th>" for c in scores) + "</tr>"]
    for k in keys:
        rows.append(f"<tr><td>{_e(k)}</td>" + "".join(
            f'<td class="num">{_e((s.get("counts") or {}).get(k, "-"))}</td>' for s in scores.values()) + "</tr>")
    return "<table>\n" + "\n".join(rows) + "\n</table>"


def _cameras_table(cams: dict) -> str:
    items = [("fraction_views_placed", "views placed (fraction)", 3), ("views_placed", "views placed", 0),
             ("views", "views", 0), ("rot_err_deg_median", "relative camera rotation error, median (deg)", 2),
             ("rot_err_deg_mean", "relative camera rotation error, mean (deg)", 2),
             ("trans_err_mm_median", "relative camera translation error, median (mm)", 1),
             ("trans_err_mm_mean", "relative camera translation error, mean (mm)", 1)]
    rows = [f"<tr><td>{label}</td><td class=\"num\">{_fmt(cams.get(k), d)}</td></tr>"
            for k, label, d in items if k in cams]
    if cams.get("reference") == "gt_objects" and rows:
        rows.append("<tr><td>errors against</td><td>the cameras the GT object poses imply (no camera poses in the "
                    "dataset)</td></tr>")
    if not rows:
        return ""
    return "<table>\n<tr><th>cameras (multi-view)</th><th>value</th></tr>\n" + "\n".join(rows) + "\n</table>"


def _settings_html(confs) -> str:
    if not isinstance(confs, dict) or not confs:
        return "<p>No settings recorded in run.json.</p>"
    parts = []
    for stage, conf in confs.items():
        if isinstance(conf, dict):
            rows = "".join(
                f"<tr><td><code>{_e(k)}</code></td><td><code>{_e(json.dumps(v) if not isinstance(v, str) else v)}"
                "</code></td></tr>" for k, v in conf.items())
            body = f"<table>{rows}</table>" if rows else "<p>(defaults)</p>"
        else:
            body = f"<pre>{_e(json.dumps(conf, indent=1))}</pre>"
        parts.append(f"<details><summary><b>{_e(stage)}</b></summary>{body}</details>")
    return "\n".join(parts)


def _stages_html(stages) -> str:
    if not isinstance(stages, dict) or not stages:
        return "<p>No stage timings recorded in run.json.</p>"
    rows = ["<tr><th>stage</th><th>status</th><th>time (s)</th></tr>"]
    total = 0.0
    for name, st in stages.items():
        st = st if isinstance(st, dict) else {"status": st}
        t = _num(st.get("time_s"))
        total += t or 0.0
        extra = {k: v for k, v in st.items() if k not in ("status", "time_s", "scenes_run", "scenes")}
        note = f" ({_e(st['scenes_run'])}/{_e(st['scenes'])} scenes run)" if "scenes_run" in st and "scenes" in st else ""
        note += f" <span class=\"meta\">{_e(json.dumps(extra))}</span>" if extra else ""
        rows.append(f"<tr><td>{_e(name)}</td><td>{_e(st.get('status', '?'))}{note}</td>"
                    f"<td class=\"num\">{_fmt(t, 2)}</td></tr>")
    rows.append(f"<tr><th>total</th><th></th><th class=\"num\">{total:.2f}</th></tr>")
    return "<table>\n" + "\n".join(rows) + "\n</table>"


def write_report(run_dir: str | Path, figures: list[Path], out_html: str | Path | None = None, *,
                 captions: dict | None = None, notes: list[str] | None = None, manifest: dict | None = None) -> Path:
    """Write the HTML report of ``run_dir`` (default ``RUN_DIR/report.html``) atomically; returns it.

    ``figures``: PNG paths (group figures) to show, in order; those that do not exist are left
    out. ``captions``: {figure path (str or Path): caption text}. ``notes``: lines shown under a
    "notes" heading (e.g. figures that could not be made). ``manifest``: the run's manifest to show
    instead of ``RUN_DIR/run.json`` (e.g. ``cosy run`` before it writes its final stage timings)."""
    run_dir = Path(run_dir)
    out_html = Path(out_html) if out_html is not None else run_dir / "report.html"
    base = out_html.parent
    run, err = (manifest, None) if manifest is not None else _read_json(run_dir / MANIFEST)
    run = run or {}
    notes = list(notes or [])
    if err:
        notes.append(err)
    caps = {str(Path(k).resolve()): v for k, v in (captions or {}).items()}

    ds = run.get("dataset", "?")
    title = f"cosy run: {Path(str(ds)).name} / {run.get('split', '?')}"
    meta = [f"dataset <code>{_e(ds)}</code>", f"split <code>{_e(run.get('split', '?'))}</code>"]
    sids = run.get("scene_ids")
    if isinstance(sids, list):
        shown = ", ".join(str(s) for s in sids[:30]) + (" ..." if len(sids) > 30 else "")
        meta.append(f"{len(sids)} scene(s): {_e(shown)}")
    for k, label in (("config", "config"), ("code_version", "code version")):
        if k in run:
            meta.append(f"{label} <code>{_e(run[k])}</code>")
    meta.append(f"report written {_e(_dt.datetime.now().isoformat(timespec='seconds'))}")
    meta.append(f"run folder <code>{_e(run_dir.resolve())}</code>")

    body = [f"<h1>{_e(title)}</h1>", f"<p class=\"meta\">{' &middot; '.join(meta)}</p>"]

    # metrics
    scores: dict[str, dict] = {}
    plots = []
    for sub, label in EVALS:
        d = run_dir / "evaluate" / sub
        doc, e = _read_json(d / "scores.json")
        if e:
            notes.append(e)
        if doc is not None:
            scores[label] = doc
        if (d / "report.png").is_file():
            plots.append((d / "report.png", label))
    body.append("<h2>Metrics</h2>")
    if scores:
        body.append(metrics_table(scores))
        body.append("<p class=\"meta\">Recalls and AUCs are fractions in [0, 1]; d = object diameter. "
                    "BOP19 AR as in the BOP challenge (bop_toolkit definitions); AUC of ADD-S as in CosyPose / "
                    "PoseCNN (thresholds 0&ndash;10 cm, mean over objects).</p>")
        cams = (scores.get("multi-view") or {}).get("cameras")
        if isinstance(cams, dict):
            body.append(_cameras_table(cams))
        body.append(_counts_table(scores))
        for label, s in scores.items():
            for w in s.get("warnings") or []:
                body.append(f"<p class=\"warn\">{_e(label)}: {_e(w)}</p>")
    else:
        body.append("<p>No evaluation in this run (the dataset has no ground truth, or the evaluate stage did not "
                    "run).</p>")
    if plots:
        body.append("<div class=\"plots\">")
        for p, label in plots:
            body.append(f"<figure><a href=\"{_href(p, base)}\"><img src=\"{_href(p, base)}\" "
                        f"alt=\"evaluation plots, {_e(label)}\"></a><figcaption>{_e(label)}: recall vs. threshold "
                        f"and per-object ADD-S (<code>{_e(p.relative_to(run_dir) if p.is_relative_to(run_dir) else p)}"
                        f"</code>)</figcaption></figure>")
        body.append("</div>")

    # stages and settings
    body.append("<h2>Stages</h2>")
    body.append(_stages_html(run.get("stages")))
    body.append("<h2>Settings</h2>")
    body.append(_settings_html(run.get("confs")))

    # figures
    figs = [Path(f) for f in figures if Path(f).is_file()]
    body.append("<h2>Scenes</h2>")
    if figs:
        body.append("<p class=\"meta\">Per group of views. Row 1: each view with its single-view candidates "
                    "(contours of their silhouettes, coloured by the physical object they were matched to; red dashed: "
                    "discarded). Row 2: the refined scene re-projected through each recovered camera. Bottom: the "
                    "recovered cameras and objects seen from above, looking down the normal of the plane the objects "
                    "rest on, or down the cameras' mean up when no such plane is found (the plot's title says which), "
                    "in mm from the gauge camera; ground truth dashed (aligned through the gauge camera). "
                    "Click a figure for full size.</p>")
        toc = " &middot; ".join(f"<a href=\"#fig{k}\">{_e(f.stem)}</a>" for k, f in enumerate(figs))
        body.append(f"<p>{toc}</p>")
        for k, f in enumerate(figs):
            cap = caps.get(str(f.resolve()), f.stem)
            body.append(f"<figure id=\"fig{k}\"><a href=\"{_href(f, base)}\"><img loading=\"lazy\" "
                        f"src=\"{_href(f, base)}\" alt=\"{_e(f.stem)}\"></a>"
                        f"<figcaption>{_e(cap)}</figcaption></figure>")
    else:
        body.append("<p>No figures.</p>")
    if notes:
        body.append("<h2>Notes</h2><ul>" + "".join(f"<li class=\"warn\">{_e(n)}</li>" for n in notes) + "</ul>")

    page = ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f"<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n<title>{_e(title)}</title>\n"
            f"<style>{CSS}</style>\n</head>\n<body>\n" + "\n".join(b for b in body if b) + "\n</body>\n</html>\n")
    atomic.write_text(out_html, page)
    return out_html
