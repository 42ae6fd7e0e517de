"""report.png of ``cosy evaluate``: recall vs. threshold curves and per-object error histograms.

The data behind the figure is written next to it: ``curves.csv`` (:func:`curves_table`) and
``gt_errors.csv`` (per GT instance, the ADD-S in mm of its top-1 match; inf = no match).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd

ADDS_THRESHOLDS_MM = np.linspace(0.0, 100.0, 101)  # the AUC range of CosyPose / PoseCNN: 0..0.1 m


def curves_table(scores: dict, gt_err: pd.DataFrame, diameters: dict[int, float]) -> pd.DataFrame:
    """Rows (metric, tau, threshold, unit, recall): ADD-S accuracy of the top-1 protocol vs. a
    threshold in mm (0..100), BOP19 recall vs. the MSSD (fraction of diameter), MSPD (px at width
    640) and VSD (mean over taus, and per tau) thresholds."""
    rows = []
    if "adds_top1_mm" in gt_err:
        e = gt_err["adds_top1_mm"].to_numpy(dtype=np.float64)
        e = e[~np.isnan(e)]
        for th in ADDS_THRESHOLDS_MM:
            rows.append(("adds_top1", np.nan, th, "mm", float((e <= th).mean()) if len(e) else 0.0))
    curves = scores.get("bop19", {}).get("curves", {})
    units = {"mssd": "diameter", "mspd": "px@640", "vsd": "vsd"}
    for m in ("mssd", "mspd"):
        if m in curves:
            for th, r in zip(curves[m]["thresholds"], curves[m]["recall"]):
                rows.append((f"bop19_{m}", np.nan, th, units[m], r))
    if "vsd" in curves:
        c = curves["vsd"]
        for th, r in zip(c["thresholds"], c["recall_mean_over_taus"]):
            rows.append(("bop19_vsd", np.nan, th, "vsd", r))
        for tau, rr in zip(c["taus"], c["recall"]):
            for th, r in zip(c["thresholds"], rr):
                rows.append(("bop19_vsd_tau", tau, th, "vsd", r))
    return pd.DataFrame(rows, columns=["metric", "tau", "threshold", "unit", "recall"])


def _fmt(v) -> str:
    return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{100 * v:.1f}"


def write_report(path: Path, scores: dict, curves: pd.DataFrame, gt_err: pd.DataFrame,
                 diameters: dict[int, float]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    objs = sorted(set(int(o) for o in gt_err["obj_id"])) if "adds_top1_mm" in gt_err else []
    ncol_h = 4
    nrow_h = max(1, math.ceil(len(objs) / ncol_h)) if objs else 0
    fig = plt.figure(figsize=(16, 4.2 + 2.6 * nrow_h), dpi=100)
    gs = fig.add_gridspec(1 + nrow_h, 4, height_ratios=[1.6] + [1.0] * nrow_h, hspace=0.55, wspace=0.28)
    title = (f"BOP19 AR {_fmt(scores.get('bop19_average_recall'))}  (VSD {_fmt(scores.get('bop19_average_recall_vsd'))}, "
             f"MSSD {_fmt(scores.get('bop19_average_recall_mssd'))}, MSPD {_fmt(scores.get('bop19_average_recall_mspd'))})"
             f"    AUC ADD-S {_fmt(scores.get('auc_adds'))}   AUC ADD(-S) {_fmt(scores.get('auc_add_or_adds'))}"
             f"   ADD-S<0.1d {_fmt(scores.get('recall_adds_0.1d'))}    [%]")
    if scores.get("oracle"):
        title = f"ORACLE {scores['oracle']['kind']} (a diagnostic)   " + title
    fig.suptitle(title, fontsize=12, y=0.995)

    panels = [
        ("adds_top1", "ADD-S accuracy (top-1 per image & object)", "threshold (mm)", scores.get("auc_adds"), "AUC"),
        ("bop19_mssd", "BOP19 recall, MSSD", "threshold (x diameter)", scores.get("bop19_average_recall_mssd"), "AR"),
        ("bop19_mspd", "BOP19 recall, MSPD", "threshold (px at width 640)", scores.get("bop19_average_recall_mspd"), "AR"),
        ("bop19_vsd", "BOP19 recall, VSD (mean over taus)", "threshold on e_VSD", scores.get("bop19_average_recall_vsd"),
         "AR"),
    ]
    for k, (metric, name, xlabel, value, what) in enumerate(panels):
        ax = fig.add_subplot(gs[0, k])
        c = curves[curves["metric"] == metric]
        if len(c):
            ax.plot(c["threshold"], c["recall"], "-o" if len(c) < 30 else "-", ms=3, lw=2, color="C0")
            if metric == "bop19_vsd":
                taus = curves[curves["metric"] == "bop19_vsd_tau"]
                for i, (tau, sub) in enumerate(taus.groupby("tau")):
                    ax.plot(sub["threshold"], sub["recall"], lw=0.8, alpha=0.5,
                            color=plt.cm.viridis(i / max(1, taus["tau"].nunique() - 1)),
                            label=f"tau {tau:.2f}" if i in (0, taus["tau"].nunique() - 1) else None)
                ax.legend(fontsize=7, loc="lower right")
            ax.set_title(f"{name}\n{what} = {_fmt(value)} %", fontsize=10)
        else:
            ax.text(0.5, 0.5, "not computed\n(see warnings in scores.json)", ha="center", va="center",
                    transform=ax.transAxes, fontsize=10, color="0.4")
            ax.set_title(name, fontsize=10)
        ax.set_xlabel(xlabel, fontsize=9)
        ax.set_ylabel("fraction of targets", fontsize=9)
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=8)

    for i, o in enumerate(objs):
        ax = fig.add_subplot(gs[1 + i // ncol_h, i % ncol_h])
        sub = gt_err[gt_err["obj_id"] == o]
        e = sub["adds_top1_mm"].to_numpy(dtype=np.float64)
        e = e[~np.isnan(e)]
        found = e[np.isfinite(e)]
        d = float(diameters.get(o, np.nan))
        hi = max(0.3 * d, float(np.percentile(found, 95)) if len(found) else 1.0) if math.isfinite(d) else 50.0
        bins = np.linspace(0, hi, 30)
        ax.hist(np.clip(found, 0, hi), bins=bins, color="C1", alpha=0.85)
        if not len(found):
            ax.set_ylim(0, 1)
            ax.text(0.5, 0.5, "no GT instance matched", ha="center", va="center", transform=ax.transAxes,
                    fontsize=9, color="0.4")
        if math.isfinite(d):
            ax.axvline(0.1 * d, color="k", ls="--", lw=1)
            ax.text(0.1 * d, ax.get_ylim()[1] * 0.92, " 0.1d", fontsize=8)
        pobj = scores.get("per_object", {}).get(str(o), {})
        ax.set_title(f"obj {o}: ADD-S of top-1 match (mm)\n{len(found)}/{len(e)} GT matched, "
                     f"AUC {_fmt(pobj.get('auc_adds'))} %, <0.1d {_fmt(pobj.get('recall_adds_0.1d'))} %", fontsize=9)
        ax.tick_params(labelsize=8)
        ax.set_ylabel("GT instances", fontsize=8)
    fig.subplots_adjust(left=0.05, right=0.98, bottom=0.06 if nrow_h else 0.12, top=0.9 if nrow_h < 2 else 0.93)
    fig.savefig(path, format="png")  # no bbox_inches="tight": it draws the figure twice
    plt.close(fig)
