"""``cosy detect``: 2D detections of a dataset's objects into a BOP detections file (stage 0).

Exactly one source:

* ``model`` (the default: the detector shipped with cosy, ``assets/detector.onnx``): an
  exported detector (:class:`cosy_cli.detection.network.OnnxDetector`) run on every image of
  the chosen scenes, keeping boxes scored >= ``min_score``, per-class NMS at ``nms_iou``, at
  most ``max_per_image``; then, with a second-stage box classifier (setting ``classifier``:
  ``auto`` = the shipped ``assets/classifier.onnx`` when the detector is the shipped one and the
  classifier knows exactly the dataset's objects, ``none``, or the path of one; see
  :mod:`cosy_cli.detection.classifier`), every box is cropped from the full-resolution image,
  classified, and emitted once per plausible label (score = detector score x the label's
  probability; :func:`~cosy_cli.detection.classifier.rescore`); a classifier with a box head
  first moves each box onto the object (``refine_boxes`` passes, each a crop of the moved box),
  followed by per-class NMS again (``min_score`` then stays the detector's threshold: the labels
  of a kept box may score less); the BOP ``time`` field is the seconds for that image
  (detector + classifier);
* ``from_json``: a detections file made by another tool, BOP or COCO results format (see
  :mod:`cosy_cli.detection.importers`), checked against the dataset (object ids, scene and
  image ids, boxes inside the image), then filtered like the detector's output (``min_score``,
  ``max_per_image``; no NMS);
* ``from_gt``: the visible GT boxes (``bbox_visib`` of instances with visib_fract >=
  ``min_visib_fract``), score 1, time -1.

Output: the BOP detections JSON ``out`` (``cosy estimate --detections`` reads it) and the
sidecar ``<out stem>.meta.json`` (settings, inputs with their sha1, summary: detections per
object, mean seconds per image) and ``<out name>.manifest.json`` (the file's sha1 and size, see
:mod:`cosy_cli.io.manifest`). A current output is reused; one made from other inputs or
settings is refused unless ``overwrite``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pandas as pd

from ..conf import as_bool, merge_conf
from ..errors import CosyError
from ..io import manifest
from ..io.atomic import write_json
from ..io.cache import file_sha1, reuse_existing_file
from ..io.dataset import BopDataset
from ..shipped import model_path, shipped
from . import importers
from .boxes import clip_xyxy, xyxy_to_xywh
from .classifier import RULE_DEFAULTS

SHIPPED_DETECTOR = shipped("detector.onnx")
SHIPPED_CLASSIFIER = shipped("classifier.onnx")
FORMAT_VERSION = 1

CONFS = {
    "default": {
        "min_score": 0.3,        # keep detections scored at least this (model and imported files)
        "max_per_image": 30,     # at most this many per image, best scores first
        "max_per_object": 0,     # at most this many per object and image, best first (0: no limit; 1 suits
                                 # datasets with one instance of each object, e.g. LM-O, YCB-V)
        "nms_iou": 0.5,          # model: per-class NMS, drop a box overlapping a better one by more
        "agnostic_nms_iou": 1.0,  # model: also across labels (one object, two labels); 1.0 = off
        "min_visib_fract": 0.1,  # from_gt: boxes of instances at least this visible (BOP targets: 0.1)
        "providers": "cpu",      # onnxruntime: cpu | cuda
        "classifier": "auto",    # model: second-stage box classifier: auto (the shipped one when it knows the
                                 # dataset's objects) | none | PATH of an exported classifier ONNX
        "label_mix": RULE_DEFAULTS["label_mix"],      # classifier: weight of the detector's label
        "label_ratio": RULE_DEFAULTS["label_ratio"],  # classifier: emit labels with p >= this x the best p
        "background": RULE_DEFAULTS["background"],    # classifier: objectness x (1 - p_background) ** this
        "refine_boxes": 1,       # classifier with a box head: passes that move each box onto its object (0: off)
        "refine_top": 0,         # ... only the boxes ranked this high after the first look (0: all; a cascade)
        "masks": "auto",         # classifier with a mask head: auto = each detection gets its segmentation | none
        "mask_threshold": 0.5,   # a pixel belongs to the mask when the mask head's probability is at least this
        "mask_boxes": False,     # with masks: each box becomes its mask's bounding box (tighter than the box head's)
        "tiles": 0,              # model: also an n x n grid of overlapping windows at n x the zoom (0: the whole image only)
    },
}


def resolve_conf(conf: str | dict | None = None, **overrides) -> dict:
    c = merge_conf(CONFS, conf, overrides, default="default", what="detect")
    if c["providers"] not in ("cpu", "cuda"):
        raise CosyError(f"detect setting providers: expected cpu or cuda, got {c['providers']!r}")
    try:
        c["min_score"], c["nms_iou"] = float(c["min_score"]), float(c["nms_iou"])
        c["agnostic_nms_iou"] = float(c["agnostic_nms_iou"])
        c["min_visib_fract"], c["max_per_image"] = float(c["min_visib_fract"]), int(c["max_per_image"])
        c["max_per_object"] = int(c["max_per_object"])
        c["label_mix"], c["label_ratio"] = float(c["label_mix"]), float(c["label_ratio"])
        c["background"] = float(c["background"])
        c["refine_boxes"] = int(c["refine_boxes"])
        c["refine_top"] = int(c["refine_top"])
        c["tiles"] = int(c["tiles"])
        c["masks"] = "none" if c["masks"] in (None, False) else str(c["masks"]).lower()
        c["mask_threshold"] = float(c["mask_threshold"])
        c["mask_boxes"] = as_bool(c["mask_boxes"], "mask_boxes", "detect")
        c["classifier"] = "none" if c["classifier"] in (None, False) else str(c["classifier"])
    except (TypeError, ValueError) as e:
        raise CosyError(f"detect settings: {e}") from None
    if not (0 <= c["min_score"] <= 1 and 0 < c["nms_iou"] <= 1 and 0 < c["agnostic_nms_iou"] <= 1 and 0 <= c["min_visib_fract"] <= 1
            and c["max_per_image"] >= 1 and c["max_per_object"] >= 0):
        raise CosyError("detect settings out of range (min_score, min_visib_fract in [0, 1], nms_iou in (0, 1], "
                        f"max_per_image >= 1): {c}")
    if c["masks"] not in ("auto", "none") or not 0 < c["mask_threshold"] < 1:
        raise CosyError(f"detect settings: masks must be auto or none and mask_threshold in (0, 1), got "
                        f"{c['masks']!r}, {c['mask_threshold']}")
    if not (0 <= c["label_mix"] <= 1 and 0 < c["label_ratio"] <= 1 and c["background"] >= 0
            and 0 <= c["refine_boxes"] <= 5 and c["tiles"] in (0, 2, 3, 4) and c["refine_top"] >= 0):
        raise CosyError("detect settings out of range (label_mix in [0, 1], label_ratio in (0, 1], background >= 0, "
                        f"refine_boxes 0-5, refine_top >= 0, tiles 0, 2, 3 or 4): {c['label_mix']}, "
                        f"{c['label_ratio']}, {c['background']}, {c['refine_boxes']}, {c['refine_top']}, {c['tiles']}")
    return c


def load_classifier(setting: str, dataset_obj_ids, detector_obj_ids=None, providers=("cpu",), log=print):
    """The box classifier a detect run uses: None for "none"; for "auto" the shipped
    ``assets/classifier.onnx`` when present and its objects are the dataset's (else None, with a
    message); else the ONNX file ``setting`` (:class:`CosyError` if it is missing, not a cosy
    classifier, or lacks objects of the dataset or of the detector)."""
    from .classifier import OnnxClassifier

    wanted = sorted(int(o) for o in dataset_obj_ids)
    if detector_obj_ids is not None:
        wanted = sorted(set(wanted) & {int(o) for o in detector_obj_ids})
    if setting == "none":
        return None
    if setting == "auto":
        if not SHIPPED_CLASSIFIER.is_file():
            return None
        clf = OnnxClassifier(SHIPPED_CLASSIFIER, providers)
        if sorted(clf.obj_ids) != sorted(int(o) for o in dataset_obj_ids):
            log(f"detect: the shipped box classifier knows objects {clf.obj_ids}, the dataset has "
                f"{sorted(int(o) for o in dataset_obj_ids)}: not used (train one with `cosy train classifier`)")
            return None
        return clf
    clf = OnnxClassifier(setting, providers)
    missing = sorted(set(wanted) - set(clf.obj_ids))
    if missing:
        raise CosyError(f"box classifier knows objects {clf.obj_ids}, not {missing} of the dataset/detector "
                        "(use a classifier trained on this dataset's models, or --classifier none)", path=setting)
    return clf


def sidecar_path(out: str | Path) -> Path:
    """``DETS.json`` -> ``DETS.meta.json`` (settings, inputs, summary)."""
    out = Path(out)
    return out.with_name(out.stem + ".meta.json") if out.suffix == ".json" else out.with_name(out.name + ".meta.json")


def keep_best(dets: pd.DataFrame, min_score: float, max_per_image: int, max_per_object: int = 0) -> pd.DataFrame:
    """Rows scored >= ``min_score``, at most ``max_per_object`` per (scene_id, im_id, obj_id) (0: no
    limit) and ``max_per_image`` per (scene_id, im_id) (best first); sorted by scene, image,
    decreasing score."""
    d = dets[dets["score"].to_numpy() >= min_score]
    d = d.sort_values(["scene_id", "im_id", "score"], ascending=[True, True, False], kind="stable")
    if max_per_object > 0:
        d = d[d.groupby(["scene_id", "im_id", "obj_id"]).cumcount().to_numpy() < max_per_object]
    rank = d.groupby(["scene_id", "im_id"]).cumcount().to_numpy()
    return d[rank < max_per_image]


def run_detector(detector, ds: BopDataset, scene_ids: list[int], conf: dict, *, log=print,
                 progress: bool = True, classifier=None, classifier_times: list | None = None
                 ) -> tuple[pd.DataFrame, list[float]]:
    """Run ``detector.detect(rgb, min_score, max_per_image, nms_iou) -> (boxes_xywh (N, 4) px,
    scores (N,), obj_ids (N,))`` on every image of the scenes. Returns the detections table (boxes
    clipped to the image, labels that are not objects of the dataset dropped with a message) and
    the seconds per image. classifier: an object with ``obj_ids`` and ``classify(rgb, boxes_xywh)
    -> (N, C + 1)`` probabilities (:class:`~cosy_cli.detection.classifier.OnnxClassifier`): the
    boxes are rescored with :func:`~cosy_cli.detection.classifier.rescore` (settings label_mix,
    label_ratio, background), then per-class NMS again; its seconds per image are appended to
    ``classifier_times`` and included in the returned times. A classifier with a mask head
    (``has_mask_head``, setting ``masks`` auto) also gives each row its mask head output, in the
    private column ``_mask`` ((S/4, S/4) probabilities, the crop's continuous box, the image's
    (H, W)): :func:`segmentations_of_masks` turns the rows that are kept into segmentations."""
    from ..console import progress as progress_bar

    known = set(ds.models_info())
    with_masks = classifier is not None and conf.get("masks", "auto") == "auto" and bool(
        getattr(classifier, "has_mask_head", False))
    images = [(sid, im) for sid in scene_ids for im in ds.image_ids(sid)]
    tiles = {"tiles": conf["tiles"]} if conf.get("tiles", 0) else {}  # detectors without tiles keep working
    if images:  # one untimed warm-up call: the runtime's first call allocates (seconds), not per-image work
        rgb0 = ds.read_rgb(*images[0])
        b0, _, _ = detector.detect(rgb0, conf["min_score"], conf["max_per_image"], conf["nms_iou"], **tiles)
        if classifier is not None:
            classifier.classify(rgb0, np.asarray(b0, dtype=np.float64).reshape(-1, 4)[:1] if len(b0) else
                                np.array([[0.0, 0.0, 31.0, 31.0]]))
    parts, times, dropped = [], [], {}
    for sid, im in progress_bar(images, desc="detect", unit="image", enabled=progress):
        rgb = ds.read_rgb(sid, im)
        t0 = time.perf_counter()
        boxes, scores, labels = detector.detect(rgb, conf["min_score"], conf["max_per_image"], conf["nms_iou"],
                                                **tiles)
        dt = time.perf_counter() - t0
        times.append(dt)
        boxes = xyxy_to_xywh(clip_xyxy(boxes, rgb.shape[1], rgb.shape[0]))
        scores = np.asarray(scores, dtype=np.float64).reshape(-1)
        labels = np.asarray(labels).reshape(-1).astype(np.int64)
        if not (len(boxes) == len(scores) == len(labels)):
            raise RuntimeError(f"detector returned {len(boxes)} boxes, {len(scores)} scores, {len(labels)} labels")
        mask_info = None
        if classifier is not None:
            from .boxes import nms_per_class
            from .classifier import best_rescored, rescore, xyxy_continuous_to_xywh

            t1 = time.perf_counter()
            passes = conf["refine_boxes"] if getattr(classifier, "has_box_head", False) else 0
            select = None
            if passes and 0 < conf.get("refine_top", 0) < len(boxes):  # only the best boxes after the first look move
                def select(probs, s=scores, lab=labels, top=conf["refine_top"]):
                    best = best_rescored(s, lab, probs, classifier.obj_ids, conf["label_mix"], conf["background"])
                    return np.argsort(-best, kind="stable")[:top]
            if with_masks:
                probs, crop_xyxy, mask_probs = classifier.classify_refine_masks(rgb, boxes, passes, select)
                boxes = xyxy_to_xywh(clip_xyxy(xyxy_continuous_to_xywh(crop_xyxy), rgb.shape[1], rgb.shape[0]))
            elif passes:
                probs, boxes = classifier.classify_refine(rgb, boxes, passes, select)
                boxes = xyxy_to_xywh(clip_xyxy(boxes, rgb.shape[1], rgb.shape[0]))
            else:
                probs = classifier.classify(rgb, boxes)
            boxes, scores, labels, rows = rescore(boxes, scores, labels, probs, classifier.obj_ids,
                                                  conf["label_mix"], conf["label_ratio"], conf["background"])
            # min_score was the detector's (objectness) threshold: a kept box is not dropped for being split
            # between labels (an object seen by a confident detector stays, under its plausible labels)
            keep = nms_per_class(boxes, scores, labels, conf["nms_iou"])[: conf["max_per_image"]]
            boxes, scores, labels, rows = boxes[keep], scores[keep], labels[keep], rows[keep]
            if with_masks:
                mask_info = [(mask_probs[r], crop_xyxy[r], rgb.shape[:2]) for r in rows]
            dt_c = time.perf_counter() - t1
            dt += dt_c
            times[-1] = dt
            if classifier_times is not None:
                classifier_times.append(dt_c)
        ok = (boxes[:, 2] > 0) & (boxes[:, 3] > 0) & np.isin(labels, sorted(known))
        if conf["agnostic_nms_iou"] < 1.0 and len(boxes):
            from .boxes import nms

            keep = np.zeros(len(boxes), bool)
            keep[nms(boxes, scores, conf["agnostic_nms_iou"])] = True
            ok &= keep
        for o in labels[~np.isin(labels, sorted(known))]:
            dropped[int(o)] = dropped.get(int(o), 0) + 1
        n = int(ok.sum())
        part = pd.DataFrame({
            "scene_id": np.full(n, sid, np.int64), "im_id": np.full(n, im, np.int64), "obj_id": labels[ok],
            "score": scores[ok], "x": boxes[ok, 0], "y": boxes[ok, 1], "w": boxes[ok, 2], "h": boxes[ok, 3],
            "time": np.full(n, dt), "segmentation": pd.Series([None] * n, dtype=object)})
        if with_masks:
            part["_mask"] = pd.Series([m for m, k in zip(mask_info, ok) if k], dtype=object)
        parts.append(part)
    if dropped:
        log("detect: dropped detections of labels that are not objects of the dataset: "
            + ", ".join(f"obj_id {o} x{n}" for o, n in sorted(dropped.items())))
    dets = pd.concat(parts, ignore_index=True) if parts else importers._empty_table()
    return dets, times


def segmentations_of_masks(dets: pd.DataFrame, margin: float, threshold: float, mask_boxes: bool = False,
                           min_pixels: int = 20) -> pd.DataFrame:
    """``dets`` with the private ``_mask`` column of :func:`run_detector` turned into each row's
    ``segmentation`` (RLE of the mask head's output pasted into the image, thresholded at
    ``threshold``; :func:`~cosy_cli.detection.classifier.paste_masks`) and dropped. Run it on the
    rows that are kept: pasting and encoding cost about a millisecond per row. ``mask_boxes``:
    each row's box becomes the bounding box of its mask (x, y, w, h px, w = x_max + 1 - x_min),
    where the mask has at least ``min_pixels`` pixels."""
    if "_mask" not in dets:
        return dets
    from ..io.masks import encode_mask
    from .classifier import paste_masks

    dets = dets.copy()
    segs, boxes = [], {}
    for info in dets["_mask"]:
        if not isinstance(info, tuple):
            segs.append(None)
            continue
        probs, xyxy, shape = info
        m = paste_masks(probs[None], np.asarray(xyxy)[None], margin, shape, threshold)[0]
        segs.append(encode_mask(m))
        if mask_boxes and m.sum() >= min_pixels:
            rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
            boxes[len(segs) - 1] = (cols[0], rows[0], cols[-1] + 1 - cols[0], rows[-1] + 1 - rows[0])
    dets["segmentation"] = pd.Series(segs, index=dets.index, dtype=object)
    for i, b in boxes.items():
        dets.iloc[i, [dets.columns.get_loc(c) for c in ("x", "y", "w", "h")]] = [float(v) for v in b]
    return dets.drop(columns=["_mask"])


def add_masks(dets: pd.DataFrame, ds: BopDataset, classifier, threshold: float, *, log=print,
              progress: bool = True) -> tuple[pd.DataFrame, int]:
    """Boxes from elsewhere (GT boxes, another tool's detections) with the masks of a classifier's
    mask head: each row without a ``segmentation`` gets the mask the classifier sees in its box
    (the box, label and score stay). Returns (the table, the number of masks added)."""
    from ..console import progress as progress_bar
    from ..io.masks import encode_mask
    from .classifier import paste_masks

    dets = dets.copy()
    if "segmentation" not in dets:
        dets["segmentation"] = pd.Series([None] * len(dets), index=dets.index, dtype=object)
    todo = dets["segmentation"].isna().to_numpy()
    groups = dets[todo].groupby(["scene_id", "im_id"]).indices
    index = dets.index[todo]
    added = 0
    for (sid, im), rows in progress_bar(sorted(groups.items()), desc="masks", unit="image", enabled=progress):
        rgb = ds.read_rgb(int(sid), int(im))
        sel = dets.loc[index[rows]]
        boxes = sel[["x", "y", "w", "h"]].to_numpy(np.float64)
        _, xyxy, masks = classifier.classify_refine_masks(rgb, boxes, 0)
        pasted = paste_masks(masks, xyxy, classifier.config.margin, rgb.shape[:2], threshold)
        for i, m in zip(index[rows], pasted):
            dets.at[i, "segmentation"] = encode_mask(m)
            added += 1
    log(f"detect: {added} masks from the box classifier {getattr(classifier, 'path', '')} added to the boxes")
    return dets, added


def _source(model, from_json, from_gt: bool) -> str:
    given = [n for n, v in (("--model", model), ("--from-json", from_json)) if v is not None] + \
        (["--from-gt"] if from_gt else [])
    if len(given) > 1:
        raise CosyError(f"give one source of detections, not {' and '.join(given)}")
    if from_json is not None:
        return "json"
    if from_gt:
        return "gt"
    return "model"


def main(conf: str | dict | None, dataset: str | Path, split: str, out: str | Path, overwrite: bool = False, *,
         scene_ids: list[int] | None = None, model: str | Path | None = None, from_json: str | Path | None = None,
         coco_images: str | Path | None = None, from_gt: bool = False, log=print, progress: bool = True,
         detector=None, classifier=None) -> dict | None:
    """Run ``cosy detect``; returns the summary (None when ``out`` is up to date and skipped).

    model: an exported detector ONNX (default: the shipped one; the source when neither
    ``from_json`` nor ``from_gt`` is given). from_json: a BOP or COCO-results detections file;
    coco_images: the COCO dataset file that maps its image ids (else image_id = scene_id * 1e6 +
    im_id). from_gt: the visible GT boxes. detector: an object with ``detect(rgb, min_score,
    max_per_image, nms_iou)`` used instead of loading ``model`` (tests, benchmarks). classifier:
    an object like :class:`~cosy_cli.detection.classifier.OnnxClassifier` used instead of the
    ``classifier`` setting (auto | none | PATH): the second-stage box classifier that relabels and
    rescores the detector's boxes (model source only).
    """
    t_start = time.perf_counter()
    conf = resolve_conf(conf)
    out = Path(out)
    doc_path = sidecar_path(out)
    source = _source(model, from_json, from_gt)
    if coco_images is not None and source != "json":
        raise CosyError("--coco-images goes with --from-json (it maps COCO image ids to BOP scene and image ids)")
    ds = BopDataset(dataset, split)
    scene_ids = ds.select_scenes(scene_ids)
    if not ds.models_info_path.is_file():
        raise CosyError("models_info.json not found (the objects' ids and sizes)", path=ds.models_info_path)

    inputs = {"dataset": str(Path(ds.root).resolve()), "split": split, "scene_ids": scene_ids,
              "models_info_sha1": file_sha1(ds.models_info_path), "source": source}
    clf = None
    if source == "model":
        if detector is None:
            model = model_path(model, SHIPPED_DETECTOR, "detector", needed=True)
            inputs["model"] = {"path": str(Path(model).resolve()), "sha1": file_sha1(model)}
        else:
            inputs["model"] = {"object": f"{type(detector).__module__}.{type(detector).__qualname__}"}
        if detector is None:
            from .network import OnnxDetector  # lazy: onnxruntime is only needed here

            detector = OnnxDetector(model, conf["providers"])  # the CPU is always the fallback
        if classifier is not None:  # an object (tests, benchmarks)
            clf = classifier
            conf["classifier"] = "object"
        elif conf["classifier"] == "auto" and not (
                inputs["model"].get("path") == str(SHIPPED_DETECTOR.resolve())):
            clf = None  # auto: the shipped classifier goes with the shipped detector (its rule was chosen for it)
        else:
            clf = load_classifier(conf["classifier"], ds.models_info(), getattr(detector, "obj_ids", None),
                                  conf["providers"], log=log)
        inputs["classifier"] = None if clf is None else (
            {"path": str(Path(clf.path).resolve()), "sha1": file_sha1(clf.path)} if hasattr(clf, "path")
            else {"object": f"{type(clf).__module__}.{type(clf).__qualname__}"})
    elif source == "json":
        inputs["detections"] = {"path": str(Path(from_json).resolve()), "sha1": file_sha1(from_json)}
        inputs["coco_images"] = None if coco_images is None else {"path": str(Path(coco_images).resolve()),
                                                                  "sha1": file_sha1(coco_images)}
    if source != "model" and (classifier is not None or conf["classifier"] not in ("auto", "none")):
        # boxes from elsewhere: a classifier named explicitly adds the masks of its mask head
        clf = classifier if classifier is not None else load_classifier(conf["classifier"], ds.models_info(),
                                                                       None, conf["providers"], log=log)
        if not getattr(clf, "has_mask_head", False):
            raise CosyError("with --from-gt or --from-json, --classifier adds its masks to the boxes, and this "
                            "classifier has no mask head (train one with `cosy train classifier --preset real`)",
                            path=getattr(clf, "path", None))
        inputs["classifier"] = ({"path": str(Path(clf.path).resolve()), "sha1": file_sha1(clf.path)}
                                if hasattr(clf, "path") else {"object": f"{type(clf).__module__}.{type(clf).__qualname__}"})
    if not getattr(clf, "has_mask_head", False):  # recorded only where they apply: earlier outputs stay up to date
        for k in ("masks", "mask_threshold", "mask_boxes"):
            conf.pop(k, None)
    if source != "model" or not conf["tiles"]:  # recorded only where it applies, as the masks' settings
        conf.pop("tiles", None)
    if source != "model" or not conf["refine_top"]:
        conf.pop("refine_top", None)
    if reuse_existing_file(out, doc_path, "detect", overwrite, conf, inputs, log=log):
        return None

    if source != "gt":  # the detector reads the images; imported boxes are checked against their size
        ds.check_image_files(scene_ids)  # sizes vs camera file/cam_K, from the headers
    times: list[float] = []
    clf_times: list[float] = []
    if source == "gt":
        d = importers.detections_from_gt(ds, scene_ids, conf["min_visib_fract"])
        dets = d.drop(columns=["gt_index"]).assign(time=-1.0, segmentation=None)
        what = f"GT boxes (visib_fract >= {conf['min_visib_fract']:g})"
    elif source == "json":
        raw = importers.read_detections_any(from_json, ds, coco_images=coco_images)
        n_raw = len(raw)
        raw = raw[raw["scene_id"].isin(scene_ids).to_numpy()]
        dets = keep_best(raw, conf["min_score"], conf["max_per_image"], conf["max_per_object"])
        what = f"{raw.attrs.get('format', 'BOP').upper()} file {from_json}"
        log(f"detect: {n_raw} detections read from {from_json}; {len(raw)} in the chosen scenes; kept {len(dets)} "
            f"(score >= {conf['min_score']:g}, at most {conf['max_per_image']} per image)")
    else:
        dets, times = run_detector(detector, ds, scene_ids, conf, log=log, progress=progress, classifier=clf,
                                   classifier_times=clf_times)
        dets = keep_best(dets, 0.0 if clf is not None else conf["min_score"], conf["max_per_image"],
                         conf["max_per_object"])
        dets = segmentations_of_masks(dets, getattr(getattr(clf, "config", None), "margin", 1.0),
                                      conf.get("mask_threshold", 0.5), conf.get("mask_boxes", False))
        what = f"detector {model if model is not None else inputs['model']['object']}"
        if clf is not None:
            what += f" + box classifier {getattr(clf, 'path', type(clf).__qualname__)}"

    n_added = None
    if source != "model" and clf is not None and conf.get("masks") == "auto":
        dets, n_added = add_masks(dets.reset_index(drop=True), ds, clf, conf["mask_threshold"], log=log,
                                  progress=progress)
        what += f" + masks of the box classifier {getattr(clf, 'path', type(clf).__qualname__)}"
    dets = dets.sort_values(["scene_id", "im_id", "score"], ascending=[True, True, False], kind="stable")
    dets = dets.reset_index(drop=True)
    n_images = sum(len(ds.image_ids(s)) for s in scene_ids)
    per_obj = dets.groupby("obj_id").size()
    summary = {
        "version": FORMAT_VERSION, "conf": conf, "inputs": inputs, "source": what, "images": n_images,
        "images_with_detections": int(dets.groupby(["scene_id", "im_id"]).ngroups),
        "detections": int(len(dets)),
        "detections_per_object": {str(int(o)): int(n) for o, n in per_obj.items()},
        "time_per_image_s": float(np.mean(times)) if times else None,
        "time_per_image_median_s": float(np.median(times)) if times else None,
        "classifier": None if clf is None else {
            "model": inputs["classifier"], "label_mix": conf["label_mix"], "label_ratio": conf["label_ratio"],
            "background": conf["background"],
            "refine_boxes": conf["refine_boxes"] if getattr(clf, "has_box_head", False) and source == "model" else 0,
            "masks": bool(getattr(clf, "has_mask_head", False)) and conf.get("masks") == "auto",
            **({"masks_added": n_added} if n_added is not None else {}),
            "time_per_image_s": float(np.mean(clf_times)) if clf_times else None},
        "time_total_s": round(time.perf_counter() - t_start, 3),
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    write_json(doc_path, summary)
    importers.write_detections(out, dets)  # a complete detections file means the stage finished
    manifest.write_file_manifest(out, "cosy detect")  # its sha1 + size, checked by cosy estimate
    ms = f", {summary['time_per_image_s'] * 1e3:.0f} ms per image" if times else ""
    log(f"detect: {len(dets)} detections in {summary['images_with_detections']} of {n_images} images from {what}"
        f"{ms} -> {out}")
    return summary
