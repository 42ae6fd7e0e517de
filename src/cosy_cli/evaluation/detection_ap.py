"""2D detection scores: COCO AP / AP50 / AP75 (computed by pycocotools) and label confusion.

Ground truth: the visible boxes (``bbox_visib`` of scene_gt_info.json, px) of every GT instance
of the chosen scenes. Instances with ``visib_fract >= min_visib_fract`` (BOP targets: 0.1) are
the boxes to find; less visible ones (but with some visible pixel) are COCO "crowd" regions: a
detection on them is ignored, neither a true nor a false positive, and missing them costs
nothing. Every image of the scenes is an evaluation image, also one without objects (its
detections are false positives). Category ids are the BOP obj_ids.

As in COCO, an object that never appears in the ground truth gets no AP and its detections do
not lower any other object's AP; :func:`confusion_matrix` shows what such mistakes (look-alike
objects taking each other's labels) look like: for each GT box, the label of the detection that
overlaps it best (IoU >= 0.5), whatever its label.

Mask AP (:func:`coco_mask_ap`, pycocotools' "segm"): when every detection carries a
``segmentation`` and every GT instance of the scenes has its visible mask (``mask_visib/``, as
the BOP datasets publish them; ``cosy gt-info --masks`` renders them), the same protocol on the
masks instead of the boxes.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import CosyError
from ..io.atomic import atomic_path, write_json
from ..io.dataset import BopDataset
from .protocols import CI_LEVEL, bootstrap_weights, percentile_interval, resampling_units

MISSED = "missed"
CI_RESAMPLES = 1000  # bootstrap resamples of AP50 (the pose ARs take 2000: each of these re-ranks detections)


def _gt_boxes(ds: BopDataset, scene_ids) -> pd.DataFrame:
    """Every GT instance with a visible box: scene_id, im_id, gt_index, obj_id, x, y, w, h, visib_fract."""
    rows = []
    for sid in scene_ids:
        if not ds.has_gt(sid):
            raise CosyError("detection scores need ground truth (scene_gt.json, scene_gt_info.json)",
                            path=ds.scene_dir(sid))
        gt, info = ds.scene_gt(sid), ds.scene_gt_info(sid)
        for im in ds.image_ids(sid):
            insts, infos = gt.get(im, []), info.get(im, [])
            if len(insts) != len(infos):
                raise CosyError(f"image {im}: {len(insts)} GT instances but {len(infos)} scene_gt_info entries",
                                path=ds.scene_file(sid, "scene_gt_info"))
            for i, (g, inf) in enumerate(zip(insts, infos)):
                x, y, w, h = (float(v) for v in inf.bbox_visib)
                if w > 0 and h > 0:
                    rows.append((int(sid), int(im), i, int(g.obj_id), x, y, w, h, float(inf.visib_fract)))
    return pd.DataFrame(rows, columns=["scene_id", "im_id", "gt_index", "obj_id", "x", "y", "w", "h", "visib_fract"])


def _image_index(ds: BopDataset, scene_ids) -> dict[tuple[int, int], int]:
    """(scene_id, im_id) -> COCO image id (1-based)."""
    keys = [(int(s), int(i)) for s in scene_ids for i in ds.image_ids(s)]
    return {k: n + 1 for n, k in enumerate(keys)}


def _select(dets: pd.DataFrame, scene_ids) -> pd.DataFrame:
    return dets[dets["scene_id"].isin([int(s) for s in scene_ids]).to_numpy()]


def coco_ap(dets: pd.DataFrame, ds: BopDataset, scene_ids=None, min_visib_fract: float = 0.1) -> dict:
    """COCO box AP of ``dets`` (the detections table: scene_id, im_id, obj_id, score, x, y, w, h
    px) against the visible GT boxes of ``scene_ids`` (default all scenes of the split).

    Returns {"AP" (IoU .50:.05:.95), "AP50", "AP75", "AR100", "per_object": {obj_id: {"AP",
    "AP50", "gt", "detections"}}, "images", "gt", "gt_ignored", "detections", "min_visib_fract",
    "tool"}; APs are in [0, 1], None for an object without GT boxes. Computed by pycocotools
    (max 100 detections per image)."""
    from importlib.metadata import version

    scene_ids = ds.scene_ids if scene_ids is None else [int(s) for s in scene_ids]
    gt = _gt_boxes(ds, scene_ids)
    img = _image_index(ds, scene_ids)
    dets = _select(dets, scene_ids)
    missing = [k for k in zip(dets["scene_id"].astype(int), dets["im_id"].astype(int)) if k not in img]
    if missing:
        raise CosyError(f"{len(missing)} detection(s) name images that are not in their scene (first: scene "
                        f"{missing[0][0]}, image {missing[0][1]})")
    obj_ids = sorted(set(ds.models_info()) | set(gt["obj_id"].tolist()) | set(dets["obj_id"].astype(int).tolist()))
    crowd = (gt["visib_fract"] < min_visib_fract).to_numpy()
    gt_doc = {
        "info": {"description": f"visible GT boxes of {ds.split_dir}"},
        "images": [{"id": n, "file_name": f"{s:06d}/{i:06d}"} for (s, i), n in img.items()],
        "categories": [{"id": int(o), "name": f"obj_{int(o):06d}"} for o in obj_ids],
        "annotations": [{"id": n + 1, "image_id": img[(int(r.scene_id), int(r.im_id))], "category_id": int(r.obj_id),
                         "bbox": [r.x, r.y, r.w, r.h], "area": r.w * r.h, "iscrowd": int(c)}
                        for n, (r, c) in enumerate(zip(gt.itertuples(index=False), crowd))],
    }
    res = [{"image_id": img[(int(s), int(i))], "category_id": int(o), "bbox": [float(x), float(y), float(w), float(h)],
            "score": float(sc)}
           for s, i, o, sc, x, y, w, h in zip(dets["scene_id"], dets["im_id"], dets["obj_id"], dets["score"],
                                              dets["x"], dets["y"], dets["w"], dets["h"])]
    n_gt = gt[~crowd].groupby("obj_id").size()
    n_det = dets.groupby("obj_id").size()
    out = {"AP": 0.0, "AP50": 0.0, "AP75": 0.0, "AR100": 0.0, "per_object": {}, "images": len(img),
           "gt": int((~crowd).sum()), "gt_ignored": int(crowd.sum()), "detections": len(res),
           "min_visib_fract": float(min_visib_fract), "tool": f"pycocotools {version('pycocotools')}"}
    per_ap = per_ap50 = per_ci = {}
    if res and (~crowd).any():
        E = _cocoeval(gt_doc, res, sorted(img.values()), "bbox")
        s = E.stats
        out.update(AP=float(s[0]), AP50=float(s[1]), AP75=float(s[2]), AR100=float(s[8]))
        prec = E.eval["precision"]  # (T iou thresholds, R recall points, K categories, A areas, M max dets)
        iou50 = int(np.argmin(np.abs(E.params.iouThrs - 0.5)))

        def mean_valid(p):
            p = p[p > -1]
            return float(p.mean()) if p.size else None

        per_ap = {int(c): mean_valid(prec[:, :, k, 0, -1]) for k, c in enumerate(E.params.catIds)}
        per_ap50 = {int(c): mean_valid(prec[iou50, :, k, 0, -1]) for k, c in enumerate(E.params.catIds)}
        keys = list(img)  # (scene_id, im_id) in COCO image id order
        unit, u, U = resampling_units([k[0] for k in keys], [k[1] for k in keys])
        ci = ap50_intervals(E, iou50, {img[k]: int(x) for k, x in zip(keys, u)})
        out["AP50_ci"] = {"level": CI_LEVEL, "unit": unit, "units": U, "resamples": CI_RESAMPLES,
                          "AP50": ci.pop("mean", None)}
        per_ci = ci
    for o in obj_ids:
        g = int(n_gt.get(o, 0))
        out["per_object"][str(o)] = {
            "AP": per_ap.get(o) if g else None, "AP50": per_ap50.get(o) if g else None,
            "AP50_ci": per_ci.get(o) if g else None, "gt": g, "detections": int(n_det.get(o, 0))}
        if g and not res:
            out["per_object"][str(o)].update(AP=0.0, AP50=0.0)
    return out


def _cocoeval(gt_doc: dict, res: list, img_ids: list, iou_type: str):
    """pycocotools' COCOeval of results ``res`` against the COCO dataset ``gt_doc`` on images
    ``img_ids``, evaluated, accumulated and summarised (its printing silenced)."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    with contextlib.redirect_stdout(io.StringIO()):
        coco_gt = COCO()
        coco_gt.dataset = gt_doc
        coco_gt.createIndex()
        E = COCOeval(coco_gt, coco_gt.loadRes(res), iou_type)
        E.params.imgIds = img_ids
        E.evaluate()
        E.accumulate()
        E.summarize()
    return E


def _gt_masks(ds: BopDataset, gt: pd.DataFrame) -> list | None:
    """The visible mask (BOP ``mask_visib/`` PNG) of each GT row, as a COCO RLE; None when one is missing."""
    import cv2
    from pycocotools import mask as mask_util

    out = []
    for r in gt.itertuples(index=False):
        p = ds.mask_path(int(r.scene_id), int(r.im_id), int(r.gt_index), visib=True)
        if not p.is_file():
            return None
        m = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if m is None:
            raise CosyError("cannot read this mask image", path=p)
        rle = mask_util.encode(np.asfortranarray(m > 0))
        rle["counts"] = rle["counts"].decode("ascii")
        out.append(rle)
    return out


def coco_mask_ap(dets: pd.DataFrame, ds: BopDataset, scene_ids=None, min_visib_fract: float = 0.1) -> dict | None:
    """COCO mask AP ("segm", pycocotools) of ``dets`` whose every row has a ``segmentation``
    against the GT visible masks (``mask_visib/``) of ``scene_ids``: {"AP", "AP50", "AP75",
    "AR100"}; None when a detection lacks a segmentation or a GT instance its mask. Crowd
    (ignored) instances as in :func:`coco_ap`."""

    from ..io.masks import SegmentationError, decode_segmentation

    scene_ids = ds.scene_ids if scene_ids is None else [int(s) for s in scene_ids]
    dets = _select(dets, scene_ids)
    if "segmentation" not in dets or not len(dets) or dets["segmentation"].isna().any():
        return None
    gt = _gt_boxes(ds, scene_ids)
    masks = _gt_masks(ds, gt)
    if masks is None or not len(gt):
        return None
    from pycocotools import mask as mask_util

    img = _image_index(ds, scene_ids)
    crowd = (gt["visib_fract"] < min_visib_fract).to_numpy()
    obj_ids = sorted(set(ds.models_info()) | set(gt["obj_id"].tolist()) | set(dets["obj_id"].astype(int).tolist()))
    anns = []
    for n, (r, c, m) in enumerate(zip(gt.itertuples(index=False), crowd, masks)):
        anns.append({"id": n + 1, "image_id": img[(int(r.scene_id), int(r.im_id))], "category_id": int(r.obj_id),
                     "segmentation": m, "area": float(mask_util.area(dict(m, counts=m["counts"].encode("ascii")))),
                     "bbox": [r.x, r.y, r.w, r.h], "iscrowd": int(c)})
    shape = {(int(r.scene_id), int(r.im_id)): tuple(m["size"]) for m, r in zip(masks, gt.itertuples(index=False))}
    any_shape = next(iter(shape.values()))  # an image without GT instances: the dataset's image size
    res = []
    for row in dets.itertuples(index=False):
        key = (int(row.scene_id), int(row.im_id))
        seg = row.segmentation
        size = shape.get(key, any_shape)
        try:
            mk = decode_segmentation(seg, size)
        except (SegmentationError, TypeError) as e:
            raise CosyError(f"detection of obj_id {int(row.obj_id)} in scene {key[0]} image {key[1]}: {e}") from None
        rle = mask_util.encode(np.asfortranarray(mk))
        rle["counts"] = rle["counts"].decode("ascii")
        res.append({"image_id": img[key], "category_id": int(row.obj_id), "segmentation": rle,
                    "score": float(row.score)})
    gt_doc = {"images": [{"id": n, "file_name": f"{s:06d}/{i:06d}", "height": shape.get((s, i), any_shape)[0],
                          "width": shape.get((s, i), any_shape)[1]} for (s, i), n in img.items()],
              "categories": [{"id": int(o), "name": f"obj_{int(o):06d}"} for o in obj_ids], "annotations": anns}
    s = _cocoeval(gt_doc, res, sorted(img.values()), "segm").stats
    return {"AP": float(s[0]), "AP50": float(s[1]), "AP75": float(s[2]), "AR100": float(s[8])}


def ap_from_matches(scores: np.ndarray, tp: np.ndarray, fp: np.ndarray, n_gt: float, weights: np.ndarray | None = None,
                    rec_thrs: np.ndarray = np.linspace(0.0, 1.0, 101)) -> float:
    """COCO's interpolated AP of one category at one IoU threshold (``COCOeval.accumulate``):
    detections already in descending score order (mergesort, as COCO), ``tp`` / ``fp`` flags (a
    detection on an ignored region is neither), ``n_gt`` the non-ignored GT boxes; ``weights``
    repeat detections (a bootstrap resample: each image's detections counted as often as the
    image is drawn). Precision made non-increasing in recall, read at the 101 recall thresholds
    (0 beyond the last recall), averaged. -1 when there is no GT."""
    if n_gt <= 0:
        return -1.0
    w = np.ones(len(tp)) if weights is None else np.asarray(weights, dtype=np.float64)
    tps = np.cumsum(tp * w)
    fps = np.cumsum(fp * w)
    rc = tps / n_gt
    pr = tps / (tps + fps + np.spacing(1))
    drawn = w > 0  # detections of images not drawn are not there at all
    rc, pr = rc[drawn], pr[drawn]
    if not len(rc):
        return 0.0
    pr = np.maximum.accumulate(pr[::-1])[::-1]
    idx = np.searchsorted(rc, rec_thrs, side="left")
    q = np.where(idx < len(pr), pr[np.minimum(idx, len(pr) - 1)], 0.0)
    return float(q.mean())


def ap50_intervals(E, iou_index: int, unit_of_image: dict, *, resamples: int = CI_RESAMPLES, level: float = CI_LEVEL,
                   seed: int = 0) -> dict:
    """Percentile bootstrap intervals of each category's AP50 and of their mean, resampling units
    (images, or scenes: ``unit_of_image`` COCO image id -> unit) with replacement, from an
    evaluated and accumulated ``COCOeval`` ``E`` (its per-image matches at IoU index
    ``iou_index``, area "all", the last maxDets). Returns {category id: [low, high], "mean": [low,
    high]} (categories without GT left out); seeded: reproducible."""
    p = E.params
    I0, A0 = len(p.imgIds), len(p.areaRng)
    max_det = p.maxDets[-1]
    units = sorted(set(unit_of_image.values()))
    u_index = {u: n for n, u in enumerate(units)}
    W = bootstrap_weights(len(units), resamples, seed)
    per_cat, aps = {}, []
    for k, cat in enumerate(p.catIds):
        ev = [(E.evalImgs[k * A0 * I0 + i], u_index[unit_of_image[img_id]]) for i, img_id in enumerate(p.imgIds)]
        ev = [(e, u) for e, u in ev if e is not None]
        if not ev:
            continue
        n_gt_unit = np.zeros(len(units))
        for e, u in ev:
            n_gt_unit[u] += np.count_nonzero(np.asarray(e["gtIgnore"]) == 0)
        if n_gt_unit.sum() == 0:
            continue
        sc = np.concatenate([np.asarray(e["dtScores"][:max_det], dtype=np.float64) for e, _ in ev])
        dtm = np.concatenate([np.asarray(e["dtMatches"][iou_index, :max_det]) for e, _ in ev])
        dig = np.concatenate([np.asarray(e["dtIgnore"][iou_index, :max_det]) for e, _ in ev]).astype(bool)
        du = np.concatenate([np.full(len(e["dtScores"][:max_det]), u) for e, u in ev]).astype(np.int64)
        order = np.argsort(-sc, kind="mergesort")
        tp = (dtm[order] > 0) & ~dig[order]
        fp = (dtm[order] == 0) & ~dig[order]
        du = du[order]
        a = np.array([ap_from_matches(sc[order], tp, fp, float(W[b] @ n_gt_unit), W[b, du]) for b in range(resamples)])
        per_cat[int(cat)] = percentile_interval(a, level)
        aps.append(a)
    if aps:  # COCO's mean over the categories with GT (in that resample)
        A = np.stack(aps)
        per_cat["mean"] = percentile_interval(np.nanmean(np.where(A < 0, np.nan, A), axis=0), level)
    return per_cat


def confusion_matrix(dets: pd.DataFrame, ds: BopDataset, scene_ids=None, min_visib_fract: float = 0.1,
                     iou_threshold: float = 0.5) -> pd.DataFrame:
    """Label confusion of the detections: rows = GT obj_id (instances with visib_fract >=
    ``min_visib_fract``), columns = the label of the detection (any label, any score) whose box
    overlaps the GT box best, provided IoU >= ``iou_threshold``, and ``missed`` when none does.
    Counts of GT instances; off-diagonal counts are look-alike mistakes."""
    from ..detection.boxes import box_iou

    scene_ids = ds.scene_ids if scene_ids is None else [int(s) for s in scene_ids]
    gt = _gt_boxes(ds, scene_ids)
    gt = gt[(gt["visib_fract"] >= min_visib_fract).to_numpy()]
    dets = _select(dets, scene_ids)
    det_groups = dets.groupby(["scene_id", "im_id"]).indices
    pred = np.full(len(gt), -1, np.int64)
    gxy = gt[["x", "y", "w", "h"]].to_numpy(np.float64)
    dxy = dets[["x", "y", "w", "h"]].to_numpy(np.float64)
    dlab = dets["obj_id"].to_numpy(np.int64)
    for (sid, im), gidx in gt.groupby(["scene_id", "im_id"]).indices.items():
        didx = det_groups.get((sid, im))
        if didx is None:
            continue
        iou = box_iou(gxy[gidx], dxy[didx])  # (G, D)
        best = iou.argmax(1)
        ok = iou[np.arange(len(gidx)), best] >= iou_threshold
        pred[gidx[ok]] = dlab[didx[best[ok]]]
    labels = sorted(set(ds.models_info()) | set(gt["obj_id"].tolist()))
    extra = sorted(set(pred[pred >= 0].tolist()) - set(labels))
    cols = labels + extra + [MISSED]
    pred_col = pd.Categorical(np.where(pred >= 0, pred, -1).astype(object), categories=labels + extra + [-1])
    table = pd.crosstab(pd.Categorical(gt["obj_id"].to_numpy(), categories=labels), pred_col, dropna=False)
    table.columns = cols
    table.index = pd.Index(labels, name="gt_obj_id")
    return table.astype(np.int64)


def confusion_summary(table: pd.DataFrame) -> dict:
    """Per GT object: {"gt", "correct", "other_label", "missed", "confused_with": {label: count}}."""
    out = {}
    for o, row in table.iterrows():
        n = int(row.sum())
        wrong = {str(c): int(v) for c, v in row.items() if c not in (o, MISSED) and v > 0}
        out[str(o)] = {"gt": n, "correct": int(row.get(o, 0)), "other_label": int(sum(wrong.values())),
                       "missed": int(row[MISSED]),
                       "confused_with": dict(sorted(wrong.items(), key=lambda kv: -kv[1]))}
    return out


def main(dataset: str | Path, split: str, detections: str | Path, out: str | Path, *, scene_ids=None,
         coco_images: str | Path | None = None, min_visib_fract: float = 0.1, log=print) -> dict:
    """``cosy evaluate-detections``: COCO AP of a detections file (BOP or COCO results format,
    checked against the dataset) and the label confusion; writes ``out/scores.json`` and
    ``out/confusion.csv``. Returns the scores."""
    from ..detection.importers import read_detections_any

    ds = BopDataset(dataset, split)
    scene_ids = ds.select_scenes(scene_ids or None)
    dets = read_detections_any(detections, ds, coco_images=coco_images)
    uncovered = sorted(set(scene_ids) - set(dets["scene_id"].astype(int).tolist()))
    if uncovered:
        log(f"evaluate-detections: no detections at all in scene(s) {uncovered} (restrict with --scene-id if they "
            "were not meant to be detected)")
    scores = coco_ap(dets, ds, scene_ids, min_visib_fract)
    scores["mask"] = coco_mask_ap(dets, ds, scene_ids, min_visib_fract)
    table = confusion_matrix(dets, ds, scene_ids, min_visib_fract)
    scores["confusion"] = confusion_summary(table)
    scores["inputs"] = {"dataset": str(Path(dataset).resolve()), "split": split, "scene_ids": scene_ids,
                        "detections": str(Path(detections).resolve())}
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "confusion.csv") as tmp:
        table.to_csv(tmp)
    write_json(out / "scores.json", json.loads(json.dumps(scores)))
    log(format_scores(scores))
    log(f"evaluate-detections: -> {out / 'scores.json'}, {out / 'confusion.csv'}")
    return scores


def format_scores(scores: dict) -> str:
    """A few lines for the terminal: AP, AP50, AP75, per-object AP50 and the label mistakes."""
    ci = scores.get("AP50_ci") or {}
    iv = f" ({ci['AP50'][0]:.3f}-{ci['AP50'][1]:.3f})" if ci.get("AP50") else ""
    lines = [f"AP {scores['AP']:.3f}  AP50 {scores['AP50']:.3f}{iv}  AP75 {scores['AP75']:.3f}  AR100 "
             f"{scores['AR100']:.3f}  ({scores['images']} images, {scores['gt']} GT boxes + {scores['gt_ignored']} "
             f"ignored (visib < {scores['min_visib_fract']:g}), {scores['detections']} detections; {scores['tool']})"]
    if ci:
        lines.append(f"(AP50 intervals: {ci['level']:.0%}, bootstrap over {ci['units']} {ci['unit']}s)")
    mk = scores.get("mask")
    if mk:
        lines.append(f"mask AP {mk['AP']:.3f}  AP50 {mk['AP50']:.3f}  AP75 {mk['AP75']:.3f}  AR100 {mk['AR100']:.3f}  "
                     "(the detections' segmentations against the GT visible masks, mask_visib/)")
    per = scores["per_object"]
    conf = scores.get("confusion", {})
    lines.append(f"{'obj_id':>7s} {'GT':>5s} {'dets':>5s} {'AP50':>6s} {'interval':>11s} {'AP':>6s}  label mistakes "
                 "(GT -> detected as)")
    for o, v in per.items():
        if not v["gt"] and not v["detections"]:
            continue
        c = conf.get(o, {})
        wrong = ", ".join(f"{lab} x{n}" for lab, n in c.get("confused_with", {}).items()) or "-"
        missed = f"; missed {c['missed']}" if c.get("missed") else ""
        i = v.get("AP50_ci")
        lines.append(f"{o:>7s} {v['gt']:5d} {v['detections']:5d} {_ap(v['AP50'])} "
                     f"{f'{i[0]:.2f}-{i[1]:.2f}' if i else '-':>11s} {_ap(v['AP'])}  {wrong}{missed}")
    return "\n".join(lines)


def _ap(a) -> str:
    return "     -" if a is None else f"{a:6.3f}"
