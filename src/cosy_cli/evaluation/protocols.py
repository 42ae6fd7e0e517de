"""Evaluation protocols: which estimates count, how they are matched to ground truth, how scores
are aggregated. The error values themselves come from :mod:`.pose_error` (one row per estimate and
GT instance of the same object in the same image, see :mod:`.evaluate_stage`).

BOP19 (``bop_toolkit``: ``scripts/eval_bop19_pose.py`` -> ``eval_calc_errors.py`` ->
``eval_calc_scores.py`` with ``pose_matching.py`` and ``score.py``), as run by the toolkit with
``n_top = -1`` and ``visib_gt_min = -1``:

1. Targets (scene_id, im_id, obj_id, inst_count) come from the targets file. Only images listed
   there are evaluated.
2. Valid GT: in each target image, for each target object, the ``inst_count`` GT instances of
   that object with the highest ``visib_fract`` (ties: lower GT index first); every other GT
   instance of the image is invalid (can neither be matched nor counted).
3. Estimates: for each target, the estimates of its (scene, image, object) sorted by score
   (descending; ties keep the order of the predictions file), the first ``inst_count`` kept.
   Estimates of objects that are not targets of their image are ignored.
4. Errors: MSSD / diameter (infinite where |t_e - t_g| >= diameter: the toolkit's sphere
   shortcut, on the model origins), MSPD x 640 / image width, VSD per tau (1 where the sphere
   projections do not overlap).
5. Matching per image and object, for each threshold: estimates in score order, each one takes
   the still unmatched valid GT instance with the lowest error strictly below the threshold
   (ties: lower GT index).
6. Recall per (metric, threshold[, tau]) = matched valid GT / number of valid GT (the number of
   targets: sum of min(inst_count, GT instances of the object in the image)); AR per metric = mean
   over thresholds (and the 10 taus for VSD: 100 values); AR = mean of AR_VSD, AR_MSSD, AR_MSPD.
   Thresholds are exactly the toolkit's ``np.arange(0.05, 0.51, 0.05)`` and ``np.arange(5, 51, 5)``
   (floating-point values such as 0.15000000000000002 included).

CosyPose / PoseCNN AUC (``cosypose/evaluation/meters/pose_meters.py`` + ``utils.py``, the YCB-Video
setting ``n_top=1``, no targets, ``visib_gt_min=-1``, ``match_threshold=inf``,
``spheres_overlap_check=False``): every GT instance is valid; the top-1 estimate (by score) per
image and object is matched greedily to the GT instance of its object with the lowest error; each
GT gets the error (metres) of its match or infinity; the AUC of accuracy vs. threshold up to
0.1 m is computed with ``compute_auc_posecnn`` (right-end steps, x10), per object, and
``auc_*`` is the mean over objects, skipping objects whose AUC is NaN (no error <= 0.1 m) as
xarray's ``mean`` does there. ADD(-S) uses ADD-S for objects with symmetries, ADD otherwise.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

BOP19_THRESHOLDS = {
    "vsd": np.arange(0.05, 0.51, 0.05),  # fraction of the VSD error (unitless)
    "mssd": np.arange(0.05, 0.51, 0.05),  # fraction of the object diameter
    "mspd": np.arange(5, 51, 5),  # pixels at an image width of 640
}
BOP19_VSD_TAUS = np.arange(0.05, 0.51, 0.05)  # fractions of the diameter
BOP19_VSD_DELTA = 15.0  # mm (the toolkit's value for every dataset but ITODD: 5)

GROUP = ["scene_id", "im_id", "obj_id"]


def vsd_column(tau: float) -> str:
    return f"vsd_tau_{tau:.2f}"


# --------------------------------------------------------------------------------------------
# BOP19
# --------------------------------------------------------------------------------------------
def bop19_valid_gt(gt: pd.DataFrame, targets: pd.DataFrame) -> pd.DataFrame:
    """GT rows of target images with a ``valid`` column (step 2 of the module docstring).

    gt: scene_id, im_id, gt_index, obj_id, visib_fract (one row per GT instance).
    targets: scene_id, im_id, obj_id, inst_count.
    """
    ims = targets[["scene_id", "im_id"]].drop_duplicates()
    g = gt.merge(ims, on=["scene_id", "im_id"], how="inner")
    g = g.merge(targets[GROUP + ["inst_count"]], on=GROUP, how="left")
    order = np.lexsort((g["gt_index"].to_numpy(), -g["visib_fract"].to_numpy(), g["obj_id"].to_numpy(),
                        g["im_id"].to_numpy(), g["scene_id"].to_numpy()))
    g = g.iloc[order].reset_index(drop=True)
    rank = g.groupby(GROUP, sort=False).cumcount().to_numpy()
    inst = g["inst_count"].fillna(0).to_numpy()
    g["valid"] = rank < inst
    g = g.drop(columns=["inst_count"]).sort_values(["scene_id", "im_id", "gt_index"], kind="stable")
    return g.reset_index(drop=True)


def top_estimates(est: pd.DataFrame, counts: pd.DataFrame | None, n_top: int | None = None) -> pd.DataFrame:
    """Estimates kept per (scene, image, object): sorted by score descending (ties: file order,
    i.e. ``est_index``), the first ``inst_count`` (from ``counts``: scene_id, im_id, obj_id,
    inst_count; groups absent from it are dropped) or the first ``n_top``. Adds ``rank``."""
    order = np.lexsort((est["est_index"].to_numpy(), -est["score"].to_numpy(), est["obj_id"].to_numpy(),
                        est["im_id"].to_numpy(), est["scene_id"].to_numpy()))
    e = est.iloc[order].reset_index(drop=True)
    e["rank"] = e.groupby(GROUP, sort=False).cumcount().to_numpy()
    if counts is not None:
        e = e.merge(counts[GROUP + ["inst_count"]], on=GROUP, how="inner")
        e = e[e["rank"] < e["inst_count"]].drop(columns=["inst_count"])
    if n_top is not None:
        e = e[e["rank"] < n_top]
    return e.sort_values(GROUP + ["rank"], kind="stable").reset_index(drop=True)


def greedy_match(err: np.ndarray, threshold: float) -> np.ndarray:
    """Greedy matching of the toolkit's ``match_poses``: rows = estimates in score order, columns =
    valid GT instances in GT order; each estimate takes the unmatched GT with the lowest error
    strictly below ``threshold`` (ties: first column). Returns the matched column per row (-1: none)."""
    n_est, n_gt = err.shape
    taken = np.zeros(n_gt, dtype=bool)
    out = np.full(n_est, -1)
    for i in range(n_est):
        e = np.where(taken, np.inf, err[i])
        j = int(np.argmin(e)) if n_gt else -1
        if j >= 0 and e[j] < threshold:
            taken[j] = True
            out[i] = j
    return out


def _matched_counts(pairs: pd.DataFrame, col: str, thresholds: np.ndarray, group_index: pd.Series) -> np.ndarray:
    """(n_groups, n_thresholds) matched GT counts per group for error column ``col``.

    pairs: rows (group, rank, gcol) = selected estimate x valid GT of its group, with ``col``."""
    n_groups = len(group_index)
    counts = np.zeros((n_groups, len(thresholds)), dtype=np.int64)
    if len(pairs) == 0:
        return counts
    n_est = pairs.groupby("group")["rank"].nunique()
    single = n_est.index[n_est.to_numpy() == 1]
    ps = pairs[pairs["group"].isin(single)]
    if len(ps):
        mins = ps.groupby("group")[col].min()
        counts[mins.index.to_numpy()] = (mins.to_numpy()[:, None] < thresholds[None, :]).astype(np.int64)
    pm = pairs[~pairs["group"].isin(single)]
    for g, sub in pm.groupby("group"):
        ranks = np.unique(sub["rank"].to_numpy())
        cols = np.unique(sub["gcol"].to_numpy())
        E = np.full((len(ranks), len(cols)), np.inf)
        E[np.searchsorted(ranks, sub["rank"].to_numpy()), np.searchsorted(cols, sub["gcol"].to_numpy())] = sub[col]
        for k, th in enumerate(thresholds):
            counts[g, k] = int((greedy_match(E, th) >= 0).sum())
    return counts


CI_LEVEL = 0.95
CI_RESAMPLES = 2000
CI_MIN_SCENES = 10  # intervals resample scenes when there are at least this many, else images


def resampling_units(scene_ids, im_ids) -> tuple[str, np.ndarray, int]:
    """What a bootstrap resamples, for items (n,) of ``scene_ids`` / ``im_ids``: scenes when there
    are at least CI_MIN_SCENES of them (images of one scene share objects and their arrangement),
    else images. Returns (unit name, unit index (n,) in 0..U-1, U)."""
    scene_ids, im_ids = np.asarray(scene_ids, dtype=np.int64), np.asarray(im_ids, dtype=np.int64)
    by_scene = len(np.unique(scene_ids)) >= CI_MIN_SCENES
    keys = np.stack([scene_ids, np.zeros_like(im_ids) if by_scene else im_ids], 1) if len(scene_ids) \
        else np.zeros((0, 2), np.int64)
    _, u = np.unique(keys, axis=0, return_inverse=True)
    u = np.asarray(u).reshape(-1)
    return ("scene" if by_scene else "image"), u, (int(u.max()) + 1 if len(u) else 0)


def bootstrap_weights(n_units: int, resamples: int, seed: int = 0) -> np.ndarray:
    """(resamples, n_units) how often each unit is drawn in each resample (n_units draws with
    replacement; seeded: reproducible)."""
    rng = np.random.default_rng(seed)
    return rng.multinomial(n_units, np.full(n_units, 1.0 / n_units), size=resamples).astype(np.float64)


def percentile_interval(values: np.ndarray, level: float = CI_LEVEL) -> list[float]:
    """[low, high]: the central ``level`` percentile interval of bootstrap values (NaN ignored)."""
    q = [(1 - level) / 2 * 100, (1 + level) / 2 * 100]
    return [float(v) for v in np.nanpercentile(np.asarray(values, dtype=np.float64), q)]


def bootstrap_intervals(unit_counts: dict[str, np.ndarray], unit_targets: np.ndarray, *,
                        resamples: int = CI_RESAMPLES, level: float = CI_LEVEL, seed: int = 0) -> dict[str, list]:
    """Percentile bootstrap intervals of average recalls, resampling units (scenes or images) with
    replacement: ``unit_counts`` {metric: (U, M) matched GT counts of each unit at each of the
    metric's M thresholds (x taus)}, ``unit_targets`` (U,) each unit's number of targets. A
    resample's recall at a threshold is its units' matched counts over their targets; its AR the
    mean over the M columns. Returns {metric: [low, high]} at ``level`` (seeded: reproducible),
    plus ``mssd_mspd`` (and ``bop19`` with ``vsd``) for the means of the metrics' ARs."""
    n = np.asarray(unit_targets, dtype=np.float64)
    U = len(n)
    if U == 0 or not n.sum():
        return {}
    W = bootstrap_weights(U, resamples, seed)  # (B, U) times drawn
    tot = np.maximum(W @ n, 1e-12)
    ar = {m: (W @ np.asarray(c, dtype=np.float64).reshape(U, -1)).mean(1) / tot for m, c in unit_counts.items()}
    if "mssd" in ar and "mspd" in ar:
        ar["mssd_mspd"] = (ar["mssd"] + ar["mspd"]) / 2
        if "vsd" in ar:
            ar["bop19"] = (ar["vsd"] + ar["mssd"] + ar["mspd"]) / 3
    return {m: percentile_interval(a, level) for m, a in ar.items()}


def bop19_scores(gt: pd.DataFrame, targets: pd.DataFrame, est: pd.DataFrame, errors: pd.DataFrame,
                 diameters: dict[int, float], im_widths: dict[int, float], *, with_vsd: bool,
                 vsd_taus=BOP19_VSD_TAUS) -> dict:
    """BOP19 average recalls (see the module docstring).

    gt: scene_id, im_id, gt_index, obj_id, visib_fract. targets: scene_id, im_id, obj_id, inst_count.
    est: est_index, scene_id, im_id, obj_id, score. errors: est_index, gt_index, mssd (mm), mspd (px),
    te (mm) and, with ``with_vsd``, the ``vsd_tau_*`` columns. diameters: obj_id -> mm.
    im_widths: scene_id -> image width in pixels.
    Returns a dict with bop19_average_recall[_vsd|_mssd|_mspd], recall curves, per-object ARs, counts.
    """
    g = bop19_valid_gt(gt, targets)
    valid = g[g["valid"]].copy()
    valid["gcol"] = valid["gt_index"]
    groups = valid.groupby(GROUP, sort=True).size().rename("n_targets").reset_index()
    groups["group"] = np.arange(len(groups))
    sel = top_estimates(est, targets)
    sel = sel.merge(groups[GROUP + ["group"]], on=GROUP, how="inner")
    pairs = sel[["est_index", "group", "rank", "obj_id", "scene_id"]].merge(
        errors.drop(columns=[c for c in ("scene_id", "im_id", "obj_id") if c in errors.columns]), on="est_index")
    valid = valid.merge(groups[GROUP + ["group"]], on=GROUP)
    pairs = pairs.merge(valid[["group", "gt_index", "gcol"]], on=["group", "gt_index"], how="inner")
    diam = pairs["obj_id"].map(diameters).to_numpy(dtype=np.float64)
    pairs["mssd_n"] = np.where(pairs["te"].to_numpy() < diam, pairs["mssd"].to_numpy() / diam, np.inf)
    width = pairs["scene_id"].map(im_widths).to_numpy(dtype=np.float64)
    pairs["mspd_n"] = pairs["mspd"].to_numpy() * (640.0 / width)

    n_targets = groups["n_targets"].to_numpy()
    obj_of_group = groups["obj_id"].to_numpy()
    obj_ids = sorted(set(int(o) for o in obj_of_group))
    total = int(n_targets.sum())

    def recalls(counts: np.ndarray) -> tuple[np.ndarray, dict[int, np.ndarray]]:
        r = counts.sum(0) / total if total else np.zeros(counts.shape[1])
        per_obj = {}
        for o in obj_ids:
            m = obj_of_group == o
            n = n_targets[m].sum()
            per_obj[o] = counts[m].sum(0) / n if n else np.zeros(counts.shape[1])
        return r, per_obj

    out: dict = {"counts": {"targets": total, "target_images": int(len(groups[["scene_id", "im_id"]].drop_duplicates())),
                            "gt_in_target_images": int(len(g)), "estimates_evaluated": int(len(sel)),
                            "estimates_total": int(len(est))}}
    curves: dict = {}
    ar: dict = {}
    ar_obj: dict = {}
    group_counts: dict = {}
    for metric, col in (("mssd", "mssd_n"), ("mspd", "mspd_n")):
        th = BOP19_THRESHOLDS[metric]
        group_counts[metric] = _matched_counts(pairs, col, th, groups)
        r, po = recalls(group_counts[metric])
        curves[metric] = {"thresholds": th.tolist(), "recall": r.tolist()}
        ar[metric] = float(r.mean())
        ar_obj[metric] = {o: float(v.mean()) for o, v in po.items()}
        out["counts"][f"tp_{metric}"] = [int(round(x * total)) for x in r]
    if with_vsd:
        th = BOP19_THRESHOLDS["vsd"]
        rs, pos, per_tau = [], {o: [] for o in obj_ids}, []
        for tau in vsd_taus:
            per_tau.append(_matched_counts(pairs, vsd_column(tau), th, groups))
            r, po = recalls(per_tau[-1])
            rs.append(r)
            for o in obj_ids:
                pos[o].append(po[o])
        R = np.stack(rs)  # (taus, thresholds)
        curves["vsd"] = {"thresholds": th.tolist(), "taus": [float(t) for t in vsd_taus], "recall": R.tolist(),
                         "recall_mean_over_taus": R.mean(0).tolist()}
        ar["vsd"] = float(R.mean())
        ar_obj["vsd"] = {o: float(np.mean(v)) for o, v in pos.items()}
        group_counts["vsd"] = np.concatenate(per_tau, axis=1)
    out["bop19_average_recall_mssd"] = ar["mssd"]
    out["bop19_average_recall_mspd"] = ar["mspd"]
    out["bop19_average_recall_vsd"] = ar.get("vsd")
    out["bop19_average_recall"] = float(np.mean([ar["vsd"], ar["mssd"], ar["mspd"]])) if with_vsd else None
    out["bop19_average_recall_mssd_mspd"] = float(np.mean([ar["mssd"], ar["mspd"]]))
    out["per_object"] = {str(o): {f"bop19_average_recall_{m}": ar_obj[m][o] for m in ar_obj}
                         | {"targets": int(n_targets[obj_of_group == o].sum())} for o in obj_ids}
    out["curves"] = curves
    out["ci"] = _intervals(groups, group_counts, n_targets)
    return out


def _intervals(groups: pd.DataFrame, group_counts: dict, n_targets: np.ndarray) -> dict:
    """Bootstrap intervals of the ARs (:func:`bootstrap_intervals`) over scenes (when there are at
    least CI_MIN_SCENES) or images, with the unit and the number of units."""
    unit, u, U = resampling_units(groups["scene_id"].to_numpy(), groups["im_id"].to_numpy())
    agg = {m: np.zeros((U, c.shape[1])) for m, c in group_counts.items()}
    for m, c in group_counts.items():
        np.add.at(agg[m], u, c)
    targets = np.bincount(u, weights=n_targets, minlength=U)
    iv = bootstrap_intervals(agg, targets)
    return {"level": CI_LEVEL, "unit": unit, "units": U, "resamples": CI_RESAMPLES,
            **{f"bop19_average_recall_{m}" if m != "bop19" else "bop19_average_recall": v for m, v in iv.items()}}


# --------------------------------------------------------------------------------------------
# CosyPose / PoseCNN AUC
# --------------------------------------------------------------------------------------------
def auc_posecnn(errors_m, max_threshold_m: float = 0.1) -> float:
    """Area under the accuracy-threshold curve for thresholds in [0, 0.1 m], normalised to [0, 1],
    computed exactly as CosyPose's ``compute_auc_posecnn`` (from the YCB-Video toolbox): errors
    above 0.1 m are failures; the curve is integrated with right-end steps (each interval between
    consecutive sorted errors takes the accuracy at its right end) plus a last step to 0.1 m at the
    final accuracy. Errors in metres (inf = no match). NaN when no error is <= 0.1 m."""
    d = np.sort(np.asarray(errors_m, dtype=np.float64).ravel())
    n = len(d)
    if n == 0:
        return float("nan")
    d[d > max_threshold_m] = np.inf
    acc = np.arange(1, n + 1, dtype=np.float64) / n
    keep = np.isfinite(d)
    if not keep.any():
        return float("nan")
    d, acc = d[keep], acc[keep]
    mrec = np.concatenate(([0.0], d, [max_threshold_m]))
    mpre = np.maximum.accumulate(np.concatenate(([0.0], acc, [acc[-1]])))
    ids = np.flatnonzero(mrec[1:] != mrec[:-1]) + 1
    return float(((mrec[ids] - mrec[ids - 1]) * mpre[ids]).sum() / max_threshold_m)


def match_top1(gt: pd.DataFrame, est: pd.DataFrame, errors: pd.DataFrame, col: str) -> np.ndarray:
    """CosyPose matching with n_top=1 and no threshold: per (scene, image, object) the best-scored
    estimate is matched to the GT instance of its object with the lowest ``col`` error (ties: lower
    GT index). Returns, aligned with ``gt`` rows, the matched error (inf: none)."""
    top = top_estimates(est, None, n_top=1)
    pairs = top[["est_index"]].merge(errors[["est_index", "gt_index", "scene_id", "im_id", col]], on="est_index")
    pairs = pairs.sort_values(["scene_id", "im_id", "est_index", "gt_index"], kind="stable")
    # one estimate per group: its best GT (first minimum)
    idx = pairs.groupby("est_index", sort=False)[col].idxmin()
    best = pairs.loc[idx.to_numpy()]
    key = gt.set_index(["scene_id", "im_id", "gt_index"]).index
    err = np.full(len(gt), np.inf)
    pos = key.get_indexer(pd.MultiIndex.from_frame(best[["scene_id", "im_id", "gt_index"]]))
    ok = pos >= 0
    err[pos[ok]] = best[col].to_numpy()[ok]
    return err


def auc_scores(gt: pd.DataFrame, est: pd.DataFrame, errors: pd.DataFrame, diameters: dict[int, float],
               symmetric: dict[int, bool]) -> dict:
    """CosyPose AUC protocol (see the module docstring). errors: est_index, gt_index, scene_id,
    im_id, add (mm), adi (mm). Returns auc_adds, auc_add_or_adds (fractions in [0, 1]), pooled
    variants, recall_adds_0.1d and per-object values."""
    errs = errors.copy()
    sym = errs["obj_id"].map(symmetric).fillna(False).to_numpy(dtype=bool)
    errs["add_or_adi"] = np.where(sym, errs["adi"].to_numpy(), errs["add"].to_numpy())
    e_adds = match_top1(gt, est, errs, "adi")
    e_addo = match_top1(gt, est, errs, "add_or_adi")
    objs = gt["obj_id"].to_numpy()
    obj_ids = sorted(set(int(o) for o in objs))
    per_obj = {}
    diam = gt["obj_id"].map(diameters).to_numpy(dtype=np.float64)
    hit = e_adds < 0.1 * diam
    n_im_obj = gt.groupby(GROUP).size()
    for o in obj_ids:
        m = objs == o
        n_pairs = int((n_im_obj.index.get_level_values("obj_id") == o).sum())
        per_obj[str(o)] = {
            "auc_adds": auc_posecnn(e_adds[m] / 1000.0),
            "auc_add_or_adds": auc_posecnn(e_addo[m] / 1000.0),
            "recall_adds_0.1d": float(hit[m].sum() / n_pairs) if n_pairs else 0.0,
            "gt_instances": int(m.sum()),
            "symmetric": bool(symmetric.get(o, False)),
        }

    def nanmean(vals):
        v = np.array([x for x in vals], dtype=np.float64)
        return float(np.nanmean(v)) if np.isfinite(v).any() else float("nan")

    n_pairs_total = int(len(n_im_obj))
    return {
        "auc_adds": nanmean(p["auc_adds"] for p in per_obj.values()),
        "auc_add_or_adds": nanmean(p["auc_add_or_adds"] for p in per_obj.values()),
        "auc_adds_pooled": auc_posecnn(e_adds / 1000.0),
        "auc_add_or_adds_pooled": auc_posecnn(e_addo / 1000.0),
        "recall_adds_0.1d": float(hit.sum() / n_pairs_total) if n_pairs_total else 0.0,
        "per_object": per_obj,
        "counts": {"gt_instances": int(len(gt)), "image_object_pairs": n_pairs_total,
                   "estimates_top1": int(len(top_estimates(est, None, n_top=1)))},
        "errors_adds_mm": e_adds,  # aligned with gt rows (popped by the caller before writing JSON)
    }


# --------------------------------------------------------------------------------------------
# cameras (scene.json)
# --------------------------------------------------------------------------------------------
def camera_pose_errors(groups: list[dict], gt_T_cam_world: dict[tuple[int, int], np.ndarray]) -> dict:
    """Relative camera pose errors of a reconstructed scene against GT camera poses.

    groups: [{"scene_id", "group_id", "im_ids": [all views of the group], "placed": {im_id: T_world_cam
    (4x4, mm)}}]. gt_T_cam_world: (scene_id, im_id) -> T_cam_world (mm), for views with GT.
    For every pair (a, b) of placed views with GT: the relative pose T_a_b = T_a_world T_world_b of
    the estimate vs. GT: rotation error (degrees) and translation error (mm).
    Returns per-pair rows, their means/medians and the fraction of views placed.
    """
    from ..geometry.poses import invert, relative_pose_error

    rows = []
    n_views = n_placed = 0
    for gr in groups:
        ims = list(gr["im_ids"])
        placed = gr["placed"]
        n_views += len(ims)
        n_placed += sum(1 for i in ims if i in placed)
        ids = [i for i in ims if i in placed and (gr["scene_id"], i) in gt_T_cam_world]
        for a_i, a in enumerate(ids):
            for b in ids[a_i + 1:]:
                T_est = invert(placed[a]) @ placed[b]
                T_gt = gt_T_cam_world[(gr["scene_id"], a)] @ invert(gt_T_cam_world[(gr["scene_id"], b)])
                r, t = relative_pose_error(T_est, T_gt)
                rows.append({"scene_id": gr["scene_id"], "group_id": gr["group_id"], "im_id_a": a, "im_id_b": b,
                             "rot_err_deg": float(r), "trans_err_mm": float(t)})
    re_ = np.array([r["rot_err_deg"] for r in rows])
    te_ = np.array([r["trans_err_mm"] for r in rows])
    return {
        "views": n_views, "views_placed": n_placed,
        "fraction_views_placed": n_placed / n_views if n_views else 0.0,
        "pairs": len(rows),
        "rot_err_deg_mean": float(re_.mean()) if len(rows) else None,
        "rot_err_deg_median": float(np.median(re_)) if len(rows) else None,
        "trans_err_mm_mean": float(te_.mean()) if len(rows) else None,
        "trans_err_mm_median": float(np.median(te_)) if len(rows) else None,
        "pairs_table": rows,
    }


def cameras_from_gt_objects(gt: pd.DataFrame, T_gt: np.ndarray, outlier_mm: float = 30.0) -> tuple[dict, dict]:
    """Camera poses implied by the GT object poses, for datasets without camera poses (LM-O):
    per scene, the first image with GT is the world frame, and each image sharing objects with it
    gets T_cam_world = the chordal mean over those objects of T_cam_obj T_ref_obj^-1 (rotation
    projected onto SO(3), translation averaged). Only objects with one instance in both images
    count, and of those the ones that agree (an object annotated in another of its symmetric
    poses, or moved, is left out: farther than max(``outlier_mm``, 3 x the median distance) from
    the median of the objects' implied camera centres). A static scene is assumed: the second dict
    gives, per image but the reference, the largest distance (mm) of a kept object's implied camera centre from their
    mean, which says how far that holds.

    gt: rows (scene_id, im_id, obj_id) aligned with T_gt (n, 4, 4) T_cam_obj (mm). Returns
    ({(scene_id, im_id): T_cam_world (4, 4)}, {(scene_id, im_id): spread_mm})."""
    from ..geometry.poses import invert
    from ..io.bop import nearest_rotation

    cams, spread = {}, {}
    keys = gt[["scene_id", "im_id", "obj_id"]].to_numpy(dtype=np.int64)
    for s in np.unique(keys[:, 0]):
        rows = np.flatnonzero(keys[:, 0] == s)
        ims = np.unique(keys[rows, 1])
        single = {}
        for im in ims:  # objects with one instance in the image
            r = rows[keys[rows, 1] == im]
            o, c = np.unique(keys[r, 2], return_counts=True)
            single[int(im)] = {int(x): int(r[keys[r, 2] == x][0]) for x in o[c == 1]}
        ref = int(ims[0])
        for im in ims:
            shared = sorted(set(single[int(im)]) & set(single[ref]))
            if not shared:
                continue
            M = np.stack([T_gt[single[int(im)][o]] @ invert(T_gt[single[ref][o]]) for o in shared])
            # each object's camera centre in the reference frame; an object whose GT was annotated
            # in another of its symmetric poses, or that moved, lands far from the others: objects
            # farther than max(outlier_mm, 3 x the median distance) from the median centre are left out
            centres = np.einsum("nji,nj->ni", M[:, :3, :3], -M[:, :3, 3])
            d = np.linalg.norm(centres - np.median(centres, 0), axis=1)
            keep = d <= max(outlier_mm, 3.0 * float(np.median(d)))
            M, centres = M[keep], centres[keep]
            T = np.eye(4)
            T[:3, :3] = nearest_rotation(M[:, :3, :3].sum(0))
            T[:3, 3] = M[:, :3, 3].mean(0)
            cams[(int(s), int(im))] = T
            if int(im) != ref:
                spread[(int(s), int(im))] = float(np.linalg.norm(centres - centres.mean(0), axis=1).max())
    return cams, spread


# --------------------------------------------------------------------------------------------
# CosyPose T-LESS ViVo (multi-instance) evaluation
# --------------------------------------------------------------------------------------------
def match_cosypose(valid_gt: pd.DataFrame, preds: pd.DataFrame, errors: pd.DataFrame, diameters: dict[int, float],
                   max_ratio: float, col: str = "adi") -> pd.DataFrame:
    """CosyPose's ``match_poses`` with the sphere check: candidates = (prediction, valid GT of the
    same image and object) with |t_e - t_g| < diameter and error <= max_ratio x diameter; per image
    and object, predictions in score order (ties: file order) take the unmatched candidate GT with
    the lowest error (ties: lower GT index). Returns est_index, gt_index, scene_id, im_id, obj_id, error (mm)."""
    cand = preds[["est_index"]].merge(errors[["est_index", "gt_index", "scene_id", "im_id", "obj_id", "te", col]],
                                      on="est_index")
    cand = cand.merge(valid_gt[["scene_id", "im_id", "gt_index"]], on=["scene_id", "im_id", "gt_index"])
    d = cand["obj_id"].map(diameters).to_numpy(dtype=np.float64)
    cand = cand[(cand["te"].to_numpy() < d) & (cand[col].to_numpy() <= max_ratio * d)]
    score = preds.set_index("est_index")["score"]
    cand = cand.assign(score=cand["est_index"].map(score).to_numpy())
    order = np.lexsort((cand["gt_index"].to_numpy(), cand["est_index"].to_numpy(), -cand["score"].to_numpy(),
                        cand["obj_id"].to_numpy(), cand["im_id"].to_numpy(), cand["scene_id"].to_numpy()))
    cand = cand.iloc[order]
    rows = []
    for _, sub in cand.groupby(GROUP, sort=False):
        taken: set = set()
        for e, g in sub.groupby("est_index", sort=False):
            g = g[~g["gt_index"].isin(taken)]
            if len(g):
                best = g.iloc[int(np.argmin(g[col].to_numpy()))]
                taken.add(int(best["gt_index"]))
                rows.append((int(best["est_index"]), int(best["gt_index"]), int(best["scene_id"]), int(best["im_id"]),
                             int(best["obj_id"]), float(best[col])))
    return pd.DataFrame(rows, columns=["est_index", "gt_index", "scene_id", "im_id", "obj_id", "error"])


def average_precision(tp: np.ndarray, score: np.ndarray, n_gt: int) -> float:
    """AP as CosyPose computes it: sklearn's ``average_precision_score(tp, score)`` (step sum
    sum_k (R_k - R_{k-1}) P_k over distinct score thresholds, recall relative to the true positives
    found) x (true positives found / n_gt), i.e. the same sum with recall relative to n_gt."""
    tp = np.asarray(tp, dtype=bool)
    score = np.asarray(score, dtype=np.float64)
    if n_gt <= 0 or not tp.any():
        return 0.0
    order = np.argsort(-score, kind="stable")
    tp, score = tp[order], score[order]
    last = np.r_[np.flatnonzero(np.diff(score) != 0), len(score) - 1]  # end of each distinct score
    ctp = np.cumsum(tp)[last].astype(np.float64)
    prec = ctp / (last + 1)
    rec = ctp / n_gt
    return float(np.sum(np.diff(np.r_[0.0, rec]) * prec))


def scene_level_targets(gt: pd.DataFrame, images: pd.DataFrame) -> pd.DataFrame:
    """Multi-view targets (the paper's ViVo task): in every image of a scene, each object of the
    scene is a target with ``inst_count`` = its number of instances in the scene (the most in any
    one image's GT), whether or not it is visible in that image.

    gt: scene_id, im_id, gt_index, obj_id (one row per GT instance); images: scene_id, im_id of
    the images to evaluate. Returns scene_id, im_id, obj_id, inst_count.
    """
    per_image = gt.groupby(["scene_id", "im_id", "obj_id"]).size().rename("n").reset_index()
    k = per_image.groupby(["scene_id", "obj_id"])["n"].max().rename("inst_count").reset_index()
    out = images[["scene_id", "im_id"]].drop_duplicates().merge(k, on="scene_id", how="inner")
    return out[["scene_id", "im_id", "obj_id", "inst_count"]].sort_values(["scene_id", "im_id", "obj_id"]) \
        .reset_index(drop=True).astype(np.int64)


def vivo_scores(gt: pd.DataFrame, targets: pd.DataFrame, est: pd.DataFrame, errors: pd.DataFrame,
                diameters: dict[int, float]) -> dict:
    """CosyPose's T-LESS ViVo meters (``run_cosypose_eval.py``, ``tless.primesense.test.bop19``:
    BOP19 targets, ``visib_gt_min=-1``, ADD-S):

    * ``vivo_auc_adds``: top-``inst_count`` predictions per target, matching threshold 0.5 d
      ("matching=OVERLAP"), AUC of ADD-S (0..0.1 m) per object, mean over objects (NaN skipped);
    * ``vivo_recall_adds_0.1d``: the same predictions, matching threshold 0.1 d, matched valid GT
      with ADD-S < 0.1 d / valid GT;
    * ``vivo_map_adds_0.1d``: every prediction of the target images ("ntop=ALL"), matching
      threshold 0.1 d, true positive = matched with ADD-S < 0.1 d, AP per object
      (:func:`average_precision`), mean over the objects with at least one true positive.
    """
    g = bop19_valid_gt(gt, targets)
    valid = g[g["valid"]]
    ims = targets[["scene_id", "im_id"]].drop_duplicates()
    preds_all = est.merge(ims, on=["scene_id", "im_id"])
    preds_top = top_estimates(est, targets)
    obj_ids = sorted(set(int(o) for o in valid["obj_id"]))
    key = ["scene_id", "im_id", "gt_index"]

    def gt_errors(m: pd.DataFrame) -> np.ndarray:
        e = valid[key].merge(m[key + ["error"]], on=key, how="left")["error"].to_numpy(dtype=np.float64)
        return np.where(np.isnan(e), np.inf, e)

    vobj = valid["obj_id"].to_numpy()
    vd = valid["obj_id"].map(diameters).to_numpy(dtype=np.float64)
    e_overlap = gt_errors(match_cosypose(valid, preds_top, errors, diameters, 0.5))
    e_bop = gt_errors(match_cosypose(valid, preds_top, errors, diameters, 0.1))
    m_all = match_cosypose(valid, preds_all, errors, diameters, 0.1)
    d_all = m_all["obj_id"].map(diameters).to_numpy(dtype=np.float64)
    tp_est = set(m_all["est_index"][m_all["error"].to_numpy() < 0.1 * d_all])
    per_obj = {}
    aps = []
    for o in obj_ids:
        m = vobj == o
        p = preds_all[preds_all["obj_id"] == o]
        tp = p["est_index"].isin(tp_est).to_numpy()
        ap = average_precision(tp, p["score"].to_numpy(), int(m.sum())) if len(p) else None
        if ap is not None and tp.any():
            aps.append(ap)
        per_obj[str(o)] = {"vivo_auc_adds": auc_posecnn(e_overlap[m] / 1000.0),
                           "vivo_recall_adds_0.1d": float((e_bop[m] < 0.1 * vd[m]).mean()),
                           "vivo_ap_adds_0.1d": ap, "vivo_valid_gt": int(m.sum())}
    aucs = np.array([v["vivo_auc_adds"] for v in per_obj.values()], dtype=np.float64)
    return {
        "vivo_auc_adds": float(np.nanmean(aucs)) if np.isfinite(aucs).any() else float("nan"),
        "vivo_recall_adds_0.1d": float((e_bop < 0.1 * vd).sum() / len(valid)) if len(valid) else 0.0,
        "vivo_map_adds_0.1d": float(np.mean(aps)) if aps else 0.0,
        "per_object": per_obj,
        "counts": {"valid_gt": int(len(valid)), "predictions_top": int(len(preds_top)),
                   "predictions_all": int(len(preds_all))},
    }
