"""Multi-view pipeline on synthetic BOP datasets: simulated candidates -> cosy match -> cosy refine.

Prints the figures of the multi-view issues, measured against the datasets' ground truth, summed
over every (dataset, candidate seed):

* view pairs (``view_pairs.csv``): pairs linked with >= 3 inliers and the relative rotation error
  of their poses (share over 10 deg, 95th percentile, worst, with its inlier count); where the
  file has a ``link`` column, the same over every linked pair (1-2-object links included);
* refine: recall of ADD-S < 0.1 d over (instance, view) for instances matched in >= 2 views; mean
  ADD-S of the matched input candidates vs the refined predictions in the same views (pairs under
  0.5 d, as in the paper's ablation); median relative camera error; output objects that are not
  a real instance (median centre error over the placed views > 0.1 d): *false objects*;
* wall time of the two commands (whole processes, start-up included), per group.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_pipeline.py [--dataset DIR ...] [--seeds 0 1]
        [--p-gross 0.05] [--src NAME=PATH ...]

Without --dataset it generates 5 scenes x 6 views x 8 objects at 640x480 (seed 1) first.
``--src NAME=PATH``: also run the stages with another checkout's ``src`` folder first on the
``PYTHONPATH`` (e.g. a ``git worktree`` of the commit before a change), interleaved with this one
in the same run, so that quality and timings are compared side by side.
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
from cosy_cli.io import BopDataset, bop, read_results  # noqa: E402
from cosy_cli.objects import ObjectDatabase  # noqa: E402

COSY = [str(Path(sys.executable).parent / "cosy")]


def adds_mm(T_est: np.ndarray, T_gt: np.ndarray, pts: np.ndarray) -> float:
    """ADD-S (mm): mean over model points of the distance to the closest estimated model point."""
    est = transform_points(T_est, pts)
    gt = transform_points(T_gt, pts)
    return float(cKDTree(est).query(gt, k=1)[0].mean())


def run(cmd: list[str], src: str | None = None) -> float:
    env = dict(os.environ)
    if src:
        env["PYTHONPATH"] = src + os.pathsep + env.get("PYTHONPATH", "")
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, env=env)
    return time.perf_counter() - t0


def view_pair_errors(match_dir: Path, ds: BopDataset) -> pd.DataFrame:
    """view_pairs.csv with the rotation (deg) and translation (mm) error of every pair's pose."""
    vp = pd.read_csv(match_dir / "view_pairs.csv")
    rot, tr = [], []
    for r in vp.itertuples():
        cams = ds.scene_camera(int(r.scene_id))
        T_gt = cams[int(r.im_id_a)].T_cam_world @ invert(cams[int(r.im_id_b)].T_cam_world)
        T = bop.pose_from_Rt(np.array(r.R.split(), float), np.array(r.t.split(), float))
        e_r, e_t = relative_pose_error(T_gt, T)
        rot.append(float(e_r))
        tr.append(float(e_t))
    return vp.assign(rot_err_deg=rot, trans_err_mm=tr)


def refine_metrics(data: Path, cands: Path, side: Path, match_dir: Path, refine_dir: Path) -> dict:
    ds = BopDataset(data, "test")
    db = ObjectDatabase.from_models_dir(ds.models_dir)
    pts = {o.obj_id: o.vertices for o in db}
    cand = read_results(cands)
    sidecar = pd.read_csv(side)
    matches = pd.read_csv(match_dir / "matches.csv")
    pred = read_results(refine_dir / "predictions.csv")
    scene = json.loads((refine_dir / "scene.json").read_text())

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

    # cameras: relative poses of every pair of placed cameras vs GT; objects that are no instance
    rot, trans, false_obj = [], [], []
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
            errs = []
            for im, Twc in placed.items():
                Tco = invert(Twc) @ np.array(o["T_world_obj"])
                same = [np.linalg.norm(Tco[:3, 3] - x.T_cam_obj[:3, 3]) for x in gts[im] if x.obj_id == o["obj_id"]]
                errs.append(min(same) if same else np.inf)
            false_obj.append(bool(np.median(errs) > 0.1 * db[o["obj_id"]].diameter))
    return {"groups": len(scene["groups"]), "recall_hits": recall_hits, "targets": n_targets, "in_err": in_err,
            "out_err": out_err, "cam_rot": rot, "cam_trans": trans, "false_obj": false_obj}


def one_run(data: Path, work: Path, seed: int, args, src: str | None) -> dict:
    """synth-candidates (shared by every implementation), then match and refine with ``src``."""
    tag = f"{data.name}_{seed}"
    cands, side = work / f"cands_{tag}.csv", work / f"cands_{tag}_gt.csv"
    if not cands.exists():
        knobs = ["--p-gross", str(args.p_gross)] if args.p_gross is not None else []
        run(COSY + ["synth-candidates", "--dataset", str(data), "--out", str(cands), "--gt-out", str(side),
                    "--seed", str(seed), "--profile", args.profile] + knobs)
    name = "head" if src is None else Path(src).parent.name
    md, rd = work / f"match_{tag}_{name}", work / f"refine_{tag}_{name}"
    t_match = run(COSY + ["match", "--dataset", str(data), "--candidates", str(cands), "--out", str(md),
                          "--overwrite"], src)
    t_refine = run(COSY + ["refine", "--dataset", str(data), "--matches", str(md), "--out", str(rd),
                           "--overwrite"], src)
    met = refine_metrics(data, cands, side, md, rd)
    met["vp"] = view_pair_errors(md, BopDataset(data, "test"))
    met["t_match"], met["t_refine"] = t_match, t_refine
    return met


def summarise(name: str, runs: list[dict]) -> None:
    vp = pd.concat([r["vp"] for r in runs], ignore_index=True)
    n_groups = sum(r["groups"] for r in runs)
    print(f"== {name}: {len(runs)} runs, {n_groups} groups")
    sets = [("linked with >= 3 inliers", vp[vp.n_inliers >= 3])]
    if "link" in vp:
        sets.append(("every linked pair", vp[vp.link != "none"]))
    for what, lk in sets:
        r = lk.rot_err_deg.to_numpy()
        worst = lk.iloc[int(np.argmax(r))] if len(r) else None
        print(f"view pairs {what}: {len(lk)} of {len(vp)}; over 10 deg {(r > 10).sum()} "
              f"({100 * (r > 10).mean() if len(r) else 0:.1f} %), 95th pct {np.percentile(r, 95) if len(r) else 0:.1f} "
              f"deg, worst {r.max() if len(r) else 0:.1f} deg"
              + (f" ({int(worst.n_inliers)} inliers)" if worst is not None else ""))
    hits, tg = sum(r["recall_hits"] for r in runs), sum(r["targets"] for r in runs)
    a, b = np.concatenate([r["in_err"] for r in runs]), np.concatenate([r["out_err"] for r in runs])
    rot, tr = np.concatenate([r["cam_rot"] for r in runs]), np.concatenate([r["cam_trans"] for r in runs])
    fo = np.concatenate([r["false_obj"] for r in runs])
    print(f"recall ADD-S < 0.1 d, instances matched in >= 2 views: {hits / max(tg, 1):.3f} ({hits}/{tg})")
    print(f"mean ADD-S, matched input candidates -> refined, same views: {a.mean():.2f} -> {b.mean():.2f} mm "
          f"({100 * (1 - b.mean() / a.mean()):.1f} % lower)")
    print(f"relative camera error, median: {np.median(rot):.2f} deg, {np.median(tr):.1f} mm ({len(rot)} pairs)")
    print(f"false objects: {int(fo.sum())}/{len(fo)} ({100 * fo.mean():.1f} %)")
    tm = np.array([r["t_match"] / r["groups"] for r in runs]) * 1e3
    trf = np.array([r["t_refine"] / r["groups"] for r in runs]) * 1e3
    print(f"wall time per group, whole commands with start-up: match {np.median(tm):.1f} ms, "
          f"refine {np.median(trf):.1f} ms (medians over runs)")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", type=Path, nargs="*")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="seeds of the simulated candidates")
    ap.add_argument("--profile", default="realistic")
    ap.add_argument("--p-gross", type=float, default=None, help="probability of a gross error (profile default)")
    ap.add_argument("--src", action="append", default=[], help="NAME=PATH of another checkout's src folder")
    ap.add_argument("--work", type=Path, help="keep the work files here")
    args = ap.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_pipeline_"))
    work.mkdir(parents=True, exist_ok=True)
    datasets = args.dataset
    if not datasets:
        data = work / "synth"
        if not data.exists():
            run(COSY + ["synth", "--out", str(data), "--scenes", "5", "--views", "6", "--objects", "8", "--seed", "1",
                        "--quiet"])
        datasets = [data]
    impls = [("this checkout", None)] + [tuple(s.split("=", 1)) for s in args.src]
    runs: dict[str, list] = {n: [] for n, _ in impls}
    for data in datasets:
        for seed in args.seeds:
            for name, src in impls:  # interleaved: the same machine load for every implementation
                runs[name].append(one_run(Path(data), work, seed, args, src))
    print(f"# pipeline on {', '.join(str(d) for d in datasets)}; candidates {args.profile}"
          + (f" p_gross={args.p_gross}" if args.p_gross is not None else "") + f", seeds {args.seeds}")
    for name, _ in impls:
        summarise(name, runs[name])


if __name__ == "__main__":
    main()
