"""BOP 2024 6D detection: average precision over MSSD and MSPD thresholds.

What the BOP toolkit computes (``scripts/eval_bop24_pose.py`` -> ``eval_calc_errors.py`` ->
``eval_calc_scores.py --eval_mode=detection`` with ``pose_matching.py`` and
``score.calc_pose_detection_scores`` / ``score.calc_ap``), and this module with it:

1. Images: those of the targets file (``test_targets_bop24.json``: scene_id, im_id; no object and
   no instance count). Estimates of other images are not evaluated.
2. Estimates: at most :data:`MAX_ESTIMATES_PER_IMAGE` per image (200 for XYZ-IBD, whose dataset
   folder is named ``xyzibd``), the highest-scored (ties: file order), counted over all objects,
   before anything else. An estimate whose object has no GT
   instance in its image is not evaluated at all (neither true nor false positive).
3. Errors: MSSD / diameter (infinite where |t_e - t_g| >= diameter, the toolkit's sphere
   shortcut), the same MSSD in mm, and MSPD x 640 / image width; against every GT instance of
   the object in the image, however little of it is visible.
4. Matching, per image, object and threshold: the estimates in score order (ties: file order)
   each take the still unmatched GT instance with the lowest error strictly below the threshold
   (ties: lower GT index). Every GT instance can be matched, visible or not.
5. Outcome of an estimate: matched to a GT instance with ``visib_fract >= visib_gt_min`` (0.1):
   true positive; matched to a less visible one: ignored (neither true nor false positive);
   unmatched: false positive. Duplicates of a matched estimate are therefore false positives.
6. AP per object and threshold: the object's evaluated, not ignored estimates of all images
   sorted by score (ties: the order of the images in the targets file, then file order);
   recall = cumulated TP / number of GT instances of the object with ``visib_fract >=
   visib_gt_min``, precision = cumulated TP / rank; AP = the mean over the 101 recall levels
   0, 0.01 .. 1 of the highest precision at a recall at least that level (0 where there is none),
   as COCO interpolates.
7. AP of an object = mean over the thresholds; AP of a metric = mean over the objects that have
   at least one such GT instance (the others, estimated or not, are left out); the BOP 2024 score
   ``bop24_ap`` = mean of the MSSD and MSPD APs. The toolkit also reports MSSD with thresholds in
   mm (2, 4 .. 20; ``bop25_mAP_mm``), here ``bop24_ap_mssd_mm``; it is not part of ``bop24_ap``.

The thresholds are exactly the toolkit's ``np.arange(0.05, 0.51, 0.05)``, ``np.arange(5, 51, 5)``
and ``range(2, 21, 2)``.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

BOP24_THRESHOLDS = {
    "mssd": np.arange(0.05, 0.51, 0.05),  # fraction of the object diameter
    "mspd": np.arange(5, 51, 5).astype(np.float64),  # pixels at an image width of 640
    "mssd_mm": np.arange(2, 21, 2).astype(np.float64),  # mm
}
BOP24_METRICS = ("mssd", "mspd", "mssd_mm")
VISIB_GT_MIN = 0.1
MAX_ESTIMATES_PER_IMAGE = 100
MAX_ESTIMATES_PER_IMAGE_BY_DATASET = {"xyzibd": 200}  # the toolkit's exceptions, by dataset name
RECALL_LEVELS = np.linspace(0.0, 1.0, 101)

GROUP = ["scene_id", "im_id", "obj_id"]


def max_estimates_per_image(dataset_name: str) -> int:
    """How many estimates per image the toolkit keeps for a dataset (named as its BOP folder)."""
    return MAX_ESTIMATES_PER_IMAGE_BY_DATASET.get(str(dataset_name), MAX_ESTIMATES_PER_IMAGE)


def keep_top_per_image(est: pd.DataFrame, max_per_image: int = MAX_ESTIMATES_PER_IMAGE) -> pd.DataFrame:
    """The ``max_per_image`` highest-scored rows of each (scene_id, im_id) of ``est`` (columns
    est_index, scene_id, im_id, score; ties: lower est_index first), in the order of ``est``."""
    order = np.lexsort((est["est_index"].to_numpy(), -est["score"].to_numpy(), est["im_id"].to_numpy(),
                        est["scene_id"].to_numpy()))
    e = est.iloc[order]
    rank = e.groupby(["scene_id", "im_id"], sort=False).cumcount().to_numpy()
    keep = set(e["est_index"].to_numpy()[rank < max_per_image].tolist())
    return est[est["est_index"].isin(keep)]


def greedy_match_thresholds(err: np.ndarray, thresholds) -> np.ndarray:
    """The toolkit's ``match_poses`` at every threshold at once: ``err`` (n_est, n_gt) with rows =
    estimates in score order and columns = GT instances in GT order; each estimate takes the still
    unmatched GT with the lowest error strictly below the threshold (ties: first column).
    Returns (n_thresholds, n_est): the matched column, -1 for none."""
    th = np.asarray(thresholds, dtype=np.float64)
    err = np.asarray(err, dtype=np.float64)
    n_est, n_gt = err.shape
    out = np.full((len(th), n_est), -1, dtype=np.int64)
    if n_gt == 0:
        return out
    taken = np.zeros((len(th), n_gt), dtype=bool)
    rows = np.arange(len(th))
    for i in range(n_est):
        e = np.where(taken, np.inf, err[i][None, :])
        j = np.argmin(e, axis=1)
        ok = e[rows, j] < th
        out[ok, i] = j[ok]
        taken[rows[ok], j[ok]] = True
    return out


def average_precision(tp, n_gt: int) -> float:
    """AP of detections ``tp`` (bool, in ranking order: best score first; ignored detections
    already left out) against ``n_gt`` GT instances: the toolkit's ``calc_ap``: precision and recall
    after each detection, with (recall 0, precision 0) and (recall 1, precision 0) added; the mean
    over the recall levels 0, 0.01 .. 1 of the highest precision at a recall >= the level.
    NaN when ``n_gt`` is 0 (the object is left out of the means)."""
    if n_gt <= 0:
        return float("nan")
    tp = np.asarray(tp, dtype=bool)
    tp_c = np.cumsum(tp)
    fp_c = np.cumsum(~tp)
    rec = tp_c / float(n_gt)
    with np.errstate(invalid="ignore", divide="ignore"):
        pre = tp_c / (tp_c + fp_c)
    pre = np.where(np.isfinite(pre), pre, 0.0)
    mrec = np.concatenate(([0.0], rec, [1.0]))
    mpre = np.concatenate(([0.0], pre, [0.0]))
    order = np.argsort(mrec, kind="stable")  # rec never decreases; kept for safety
    mrec, mpre = mrec[order], mpre[order]
    best_from = np.maximum.accumulate(mpre[::-1])[::-1]  # highest precision at index >= i
    first = np.searchsorted(mrec, RECALL_LEVELS, side="left")  # first point with recall >= level
    vals = np.where(first < len(mrec), best_from[np.minimum(first, len(mrec) - 1)], 0.0)
    return float(vals.mean())


def outcomes(matched_visib: np.ndarray, visib_gt_min: float = VISIB_GT_MIN) -> np.ndarray:
    """Outcome codes from the visib_fract of the matched GT (NaN: unmatched): 1 true positive,
    0 false positive, -1 ignored (matched to a GT instance visible less than ``visib_gt_min``)."""
    v = np.asarray(matched_visib, dtype=np.float64)
    return np.where(np.isnan(v), 0, np.where(v >= visib_gt_min, 1, -1)).astype(np.int64)


def normalized_errors(errors: pd.DataFrame, diameters: dict[int, float], im_widths: dict[int, float]) -> pd.DataFrame:
    """Columns mssd (/ diameter), mssd_mm and mspd (x 640 / width) for rows of ``errors`` (obj_id,
    scene_id, mssd (mm), mspd (px), te (mm)), with the toolkit's sphere shortcut on MSSD."""
    diam = errors["obj_id"].map(diameters).to_numpy(dtype=np.float64)
    near = errors["te"].to_numpy(dtype=np.float64) < diam
    mssd = errors["mssd"].to_numpy(dtype=np.float64)
    width = errors["scene_id"].map(im_widths).to_numpy(dtype=np.float64)
    return pd.DataFrame({"mssd": np.where(near, mssd / diam, np.inf), "mssd_mm": np.where(near, mssd, np.inf),
                         "mspd": errors["mspd"].to_numpy(dtype=np.float64) * (640.0 / width)}, index=errors.index)


def bop24_scores(gt: pd.DataFrame, images: pd.DataFrame, est: pd.DataFrame, errors: pd.DataFrame,
                 diameters: dict[int, float], im_widths: dict[int, float], *, visib_gt_min: float = VISIB_GT_MIN,
                 max_per_image: int = MAX_ESTIMATES_PER_IMAGE) -> dict:
    """BOP 2024 6D detection scores (see the module docstring).

    gt: scene_id, im_id, gt_index, obj_id, visib_fract (one row per GT instance). images: scene_id,
    im_id of the evaluated images, in the targets file's order. est: est_index, scene_id, im_id,
    obj_id, score. errors: est_index, gt_index, scene_id, im_id, obj_id, mssd (mm), mspd (px), te (mm)
    for (at least) every estimate and GT instance of its object in its image. diameters: obj_id -> mm;
    im_widths: scene_id -> px.
    Returns bop24_ap[_mssd|_mspd|_mssd_mm], per-object APs, AP per threshold and counts.
    """
    ims = images[["scene_id", "im_id"]].drop_duplicates().reset_index(drop=True)
    ims["im_rank"] = np.arange(len(ims))
    g = gt.merge(ims, on=["scene_id", "im_id"], how="inner")
    capped = keep_top_per_image(est, max_per_image)
    e = capped.merge(ims, on=["scene_id", "im_id"], how="inner")
    gt_objs = g[GROUP].drop_duplicates()
    e = e.merge(gt_objs, on=GROUP, how="inner")  # estimates of objects present in their image
    e = e.sort_values(["im_rank", "obj_id", "score", "est_index"], ascending=[True, True, False, True],
                      kind="stable").reset_index(drop=True)

    valid_gt = g[g["visib_fract"].to_numpy() >= visib_gt_min].groupby("obj_id").size()
    obj_ids = sorted(int(o) for o in valid_gt.index)
    n_valid = {o: int(valid_gt[o]) for o in obj_ids}

    # groups = (image, object), contiguous in ``e``; rows = estimates in score order, columns = GT
    # instances of the object in the image in GT order
    n_e = len(e)
    e["group"] = e.groupby(GROUP, sort=False).ngroup()
    n_groups = int(e["group"].max()) + 1 if n_e else 0
    gg = g.merge(e[GROUP + ["group"]].drop_duplicates(), on=GROUP).sort_values(["group", "gt_index"], kind="stable")
    gg["col"] = gg.groupby("group").cumcount()
    start_e = e.groupby("group").cumcount().to_numpy()
    pairs = errors[["est_index", "gt_index", "scene_id", "im_id", "obj_id", "mssd", "mspd", "te"]].merge(
        e[["est_index", "group"]].assign(row=start_e), on="est_index", how="inner")
    pairs = pairs.merge(gg[["scene_id", "im_id", "gt_index", "col"]], on=["scene_id", "im_id", "gt_index"], how="inner")
    pairs = pd.concat([pairs[["group", "row", "col"]], normalized_errors(pairs, diameters, im_widths)], axis=1)
    pairs = pairs.sort_values("group", kind="stable")
    bounds = np.arange(n_groups + 1)
    e_at = np.searchsorted(e["group"].to_numpy(), bounds)
    g_at = np.searchsorted(gg["group"].to_numpy(), bounds)
    p_at = np.searchsorted(pairs["group"].to_numpy(), bounds)
    p_row, p_col = pairs["row"].to_numpy(), pairs["col"].to_numpy()
    p_val = {m: pairs[m].to_numpy(dtype=np.float64) for m in BOP24_METRICS}
    g_vis = gg["visib_fract"].to_numpy(dtype=np.float64)

    # outcome per (metric, threshold, estimate): matching within each (image, object)
    res = {m: np.zeros((len(BOP24_THRESHOLDS[m]), n_e), dtype=np.int64) for m in BOP24_METRICS}
    for k in range(n_groups):
        r0, r1, c0, c1, q0, q1 = e_at[k], e_at[k + 1], g_at[k], g_at[k + 1], p_at[k], p_at[k + 1]
        vis = g_vis[c0:c1]
        for m in BOP24_METRICS:
            E = np.full((r1 - r0, c1 - c0), np.inf)
            E[p_row[q0:q1], p_col[q0:q1]] = p_val[m][q0:q1]
            match = greedy_match_thresholds(E, BOP24_THRESHOLDS[m])
            mv = vis[np.maximum(match, 0)] if c1 > c0 else np.zeros(match.shape)
            res[m][:, r0:r1] = outcomes(np.where(match >= 0, mv, np.nan), visib_gt_min)

    # ranking per object: score, then the images' order, then file order
    rank_order = np.lexsort((e["est_index"].to_numpy(), e["im_rank"].to_numpy(), -e["score"].to_numpy()))
    e_obj = e["obj_id"].to_numpy()
    ap: dict = {m: {} for m in BOP24_METRICS}
    counts_out: dict = {m: {"tp": [], "fp": [], "ignored": []} for m in BOP24_METRICS}
    for m in BOP24_METRICS:
        R = res[m]
        for k in range(R.shape[0]):
            counts_out[m]["tp"].append(int((R[k] == 1).sum()))
            counts_out[m]["fp"].append(int((R[k] == 0).sum()))
            counts_out[m]["ignored"].append(int((R[k] == -1).sum()))
        for o in obj_ids:
            idx = rank_order[e_obj[rank_order] == o]
            ap[m][o] = [average_precision(R[k, idx][R[k, idx] >= 0] == 1, n_valid[o]) for k in range(R.shape[0])]

    out: dict = {}
    per_object: dict = {}
    curves: dict = {}
    for m in BOP24_METRICS:
        obj_ap = {o: float(np.mean(ap[m][o])) for o in obj_ids}
        out[f"bop24_ap_{m}"] = float(np.mean(list(obj_ap.values()))) if obj_ids else float("nan")
        for o in obj_ids:
            per_object.setdefault(str(o), {})[f"bop24_ap_{m}"] = obj_ap[o]
        A = np.array([ap[m][o] for o in obj_ids], dtype=np.float64).reshape(len(obj_ids), len(BOP24_THRESHOLDS[m]))
        curves[m] = {"thresholds": BOP24_THRESHOLDS[m].tolist(),
                     "ap": (A.mean(0) if obj_ids else np.full(A.shape[1], np.nan)).tolist(),
                     "per_object": {str(o): ap[m][o] for o in obj_ids}, **counts_out[m]}
    for o in obj_ids:
        per_object[str(o)]["bop24_valid_gt"] = n_valid[o]
    out["bop24_ap"] = float(np.mean([out["bop24_ap_mssd"], out["bop24_ap_mspd"]]))
    in_ims = est.merge(ims[["scene_id", "im_id"]], on=["scene_id", "im_id"], how="inner")
    skipped = sorted(set(int(x) for x in pd.concat([g["obj_id"], e["obj_id"]])) - set(obj_ids))
    out["counts"] = {
        "images": int(len(ims)), "gt_in_images": int(len(g)), "valid_gt": int(sum(n_valid.values())),
        "estimates_total": int(len(est)), "estimates_in_images": int(len(in_ims)),
        "estimates_over_cap": int(len(est) - len(capped)), "estimates_evaluated": int(n_e),
        "objects": len(obj_ids), "objects_without_valid_gt": skipped,
    }
    out["per_object"] = per_object
    out["curves"] = curves
    return out
