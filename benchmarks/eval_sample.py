"""Single view vs. multi-view on a dataset (the paper's Table: 1 view, groups of 4 and of 8 views).

Runs `cosy run` (detections: `--from-gt` by default, or the shipped detector with --detector)
once per group size into RUN_ROOT/vpgN: the first run detects and estimates, the others start at
match from its single-view candidates and writes a Markdown table of AUC ADD-S, ADD-S < 0.1 d recall and BOP19
AR to --out.

    python benchmarks/eval_sample.py [--dataset data_samples] [--out results/eval_sample.md]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from cosy_cli.io.dataset import BopDataset  # noqa: E402
from cosy_cli.pipeline import run_stage  # noqa: E402

METRICS = (("bop19_average_recall", "BOP19 AR"), ("bop19_average_recall_mssd_mspd", "AR (MSSD, MSPD)"),
           ("auc_adds", "AUC ADD-S"), ("recall_adds_0.1d", "ADD-S < 0.1 d"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", default=str(ROOT / "data_samples"))
    ap.add_argument("--split", default="test")
    ap.add_argument("--groups", default="4,8", help="group sizes (views per group), comma-separated")
    ap.add_argument("--runs", default=str(ROOT / "results" / "eval_sample"), help="run folders go here")
    ap.add_argument("--out", default=str(ROOT / "results" / "eval_sample.md"))
    ap.add_argument("--detector", action="store_true", help="use the shipped detector instead of GT boxes")
    ap.add_argument("--config", default="default")
    args = ap.parse_args()

    ds = BopDataset(args.dataset, args.split)
    n_views = max(len(ds.image_ids(s)) for s in ds.scene_ids)
    runs = Path(args.runs)
    rows, candidates = [], None
    for g in [int(x) for x in args.groups.split(",")]:
        if g > n_views:
            print(f"skipping groups of {g}: scenes have at most {n_views} views")
            continue
        t0 = time.perf_counter()
        # the first run detects and estimates; the others start at match from its candidates
        source = {"candidates": candidates} if candidates else {"from_gt": not args.detector}
        m = run_stage.main(args.config, args.dataset, args.split, runs / f"vpg{g}", templates_dir=runs / "templates",
                           overrides={"match": {"views_per_group": g}}, last="evaluate", log=lambda s: None,
                           progress=False, **source)
        candidates = candidates or runs / f"vpg{g}" / "estimate" / "candidates.csv"
        dt = time.perf_counter() - t0
        if not rows:
            rows.append(("1 (single view)", m["metrics"]["single_view"], None))
        rows.append((str(g), m["metrics"]["multi_view"], dt))
        print(f"groups of {g} views: done in {dt:.1f} s")
    source = "shipped detector" if args.detector else "GT boxes (visib_fract >= 0.1)"
    lines = [f"# Single view vs. multi-view on `{Path(args.dataset).name}/{args.split}`", "",
             f"{len(ds.scene_ids)} scenes, up to {n_views} views each; detections: {source}; config "
             f"`{args.config}`; `python benchmarks/eval_sample.py` (`make eval-sample`).", "",
             "| views per group | " + " | ".join(name for _, name in METRICS) + " |",
             "| --- |" + " --- |" * len(METRICS)]
    for label, met, _ in rows:
        vals = [met.get(k) for k, _ in METRICS]
        lines.append(f"| {label} | " + " | ".join("-" if v is None else f"{v:.3f}" for v in vals) + " |")
    text = "\n".join(lines) + "\n"
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    print(text)
    print(f"written to {out}")


if __name__ == "__main__":
    main()
