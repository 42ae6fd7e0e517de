"""Multi-view pipeline on a synthetic BOP dataset: simulated candidates -> cosy match -> cosy refine.

Prints the figures of the `cosy refine` issue, measured against the dataset's ground truth:
recall of ADD-S < 0.1 diameter over (instance, view) for instances matched in >= 2 views,
mean ADD-S of the matched input candidates vs the refined predictions in the same views (only
pairs under 0.5 diameter count, as in the paper's ablation), median relative camera error, the
share of output objects that are not a real instance, and the wall time of the two stages.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_pipeline.py [--dataset DIR] [--seed 0]

Without --dataset it generates 5 scenes x 6 views x 8 objects at 640x480 (seed 1) first.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from itertools import combinations  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

from cosy_cli.geometry import invert, relative_pose_error, transform_points  # noqa: E402
from cosy_cli.io import BopDataset, read_results  # noqa: E402
from cosy_cli.objects import ObjectDatabase  # noqa: E402

COSY = [str(Path(sys.executable).parent / "cosy")]


def adds_mm(T_est: np.ndarray, T_gt: np.ndarray, pts: np.ndarray) -> float:
    """ADD-S (mm): mean over model points of the distance to the closest estimated model point."""
    est = transform_points(T_est, pts)
    gt = transform_points(T_gt, pts)
    return float(cKDTree(est).query(gt, k=1)[0].mean())


def run(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", type=Path)
    ap.add_argument("--seed", type=int, default=0, help="seed of the simulated candidates")
    ap.add_argument("--profile", default="realistic")
    args = ap.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="bench_pipeline_"))
    data = args.dataset
    if data is None:
        data = work / "synth"
        run(COSY + ["synth", "--out", str(data), "--scenes", "5", "--views", "6", "--objects", "8", "--seed", "1",
                    "--quiet"])
    cands, side = work / "cands.csv", work / "cands_gt.csv"
    run(COSY + ["synth-candidates", "--dataset", str(data), "--out", str(cands), "--gt-out", str(side),
                "--seed", str(args.seed), "--profile", args.profile])
    t_match = run(COSY + ["match", "--dataset", str(data), "--candidates", str(cands), "--out", str(work / "match")])
    t_refine = run(COSY + ["refine", "--dataset", str(data), "--matches", str(work / "match"),
                           "--out", str(work / "refine")])

    ds = BopDataset(data, "test")
    db = ObjectDatabase.from_models_dir(ds.models_dir)
    pts = {o.obj_id: o.vertices for o in db}
    cand = read_results(cands)
    sidecar = pd.read_csv(side)
    matches = pd.read_csv(work / "match" / "matches.csv")
    pred = read_results(work / "refine" / "predictions.csv")
    scene = json.loads((work / "refine" / "scene.json").read_text())

    # instances matched in >= 2 views: their correct candidates share one object id
    m = matches.merge(sidecar[["cand_id", "instance_id", "gt_index", "gt_obj_id", "kind"]], on="cand_id")
    good = m[(m.object_id >= 0) & (m.kind != "fp") & (m.obj_id == m.gt_obj_id)]
    views_per_inst = good.groupby(["scene_id", "instance_id"]).im_id.nunique()
    matched = set(views_per_inst[views_per_inst >= 2].index)

    pred_tab = pred.table.reset_index(drop=True)
    recall_hits, n_targets, in_err, out_err = 0, 0, [], []
    for s in ds.scene_ids:
        gt = ds.scene_gt(s)
        for im, insts in gt.items():
            P = pred_tab[(pred_tab.scene_id == s) & (pred_tab.im_id == im)]
            for gi, g in enumerate(insts):
                if (s, gi) not in matched:  # synth instance ids are the GT index (same order in every view)
                    continue
                n_targets += 1
                d = pts[g.obj_id]
                diam = db[g.obj_id].diameter
                cands_here = [adds_mm(P_T, g.T_cam_obj, d) for P_T in pred.T_cam_obj[P.index[P.obj_id == g.obj_id]]]
                best = min(cands_here) if cands_here else np.inf
                recall_hits += best < 0.1 * diam
                c_rows = good[(good.scene_id == s) & (good.im_id == im) & (good.gt_index == gi)].cand_id.to_numpy()
                for c in c_rows:
                    e_in = adds_mm(cand.T_cam_obj[c], g.T_cam_obj, d)
                    if e_in < 0.5 * diam and best < 0.5 * diam:
                        in_err.append(e_in)
                        out_err.append(best)

    # cameras: relative poses of every pair of placed cameras vs GT
    rot, trans, not_real, n_obj = [], [], 0, 0
    for g in scene["groups"]:
        cams = ds.scene_camera(g["scene_id"])
        placed = {c["im_id"]: np.array(c["T_world_cam"]) for c in g["cameras"]}
        for a, b in combinations(sorted(placed), 2):
            est = invert(placed[a]) @ placed[b]
            ref = cams[a].T_cam_world @ invert(cams[b].T_cam_world)
            r, t = relative_pose_error(est, ref)
            rot.append(r)
            trans.append(t)
        gts = ds.scene_gt(g["scene_id"])
        for o in g["objects"]:
            n_obj += 1
            errs = []
            for im, Twc in placed.items():
                Tco = invert(Twc) @ np.array(o["T_world_obj"])
                same = [np.linalg.norm(Tco[:3, 3] - x.T_cam_obj[:3, 3]) for x in gts[im] if x.obj_id == o["obj_id"]]
                errs.append(min(same) if same else np.inf)
            not_real += np.median(errs) > 0.1 * db[o["obj_id"]].diameter

    n_groups = len(scene["groups"])
    print(f"# pipeline on {data} ({n_groups} groups, {len(cand)} {args.profile} candidates, seed {args.seed})")
    print(f"recall ADD-S < 0.1 d over (instance, view), instances matched in >= 2 views: "
          f"{recall_hits / max(n_targets, 1):.3f} ({recall_hits}/{n_targets})")
    print(f"mean ADD-S, matched input candidates -> refined predictions, same views: "
          f"{np.mean(in_err):.2f} -> {np.mean(out_err):.2f} mm ({100 * (1 - np.mean(out_err) / np.mean(in_err)):.0f} % lower; "
          f"medians {np.median(in_err):.2f} -> {np.median(out_err):.2f})")
    print(f"relative camera error, median: {np.median(rot):.2f} deg, {np.median(trans):.1f} mm "
          f"(90th pct {np.percentile(rot, 90):.2f} deg, {np.percentile(trans, 90):.1f} mm; {len(rot)} pairs)")
    print(f"output objects that are not a real instance: {not_real}/{n_obj} ({100 * not_real / max(n_obj, 1):.1f} %)")
    print(f"wall time, whole commands with start-up: match {t_match:.2f} s, refine {t_refine:.2f} s")


if __name__ == "__main__":
    main()
