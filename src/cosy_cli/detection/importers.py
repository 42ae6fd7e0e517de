"""2D detections in and out: BOP and COCO files, ground-truth boxes, checks against a dataset.

The table every function here takes or returns has one row per detection and the columns
``scene_id, im_id, obj_id, score, x, y, w, h, time, segmentation``: the box ``x, y, w, h`` in
pixels (x, y = top-left corner, pixel-edge coordinates as in BOP and COCO), ``time`` the seconds
spent on the detection's image (-1: unknown), ``segmentation`` an RLE dict or None. The row
index is the detection's position in the file it came from (error messages name it).

Formats read by :func:`read_detections_any` (one file, one format):

* **BOP** (the BOP challenge's detection files, what ``cosy detect`` writes): a JSON list of
  ``{scene_id, image_id, category_id, score, bbox [x, y, w, h], time?, segmentation?}``;
  ``image_id`` is the BOP im_id, ``category_id`` the BOP obj_id.
* **COCO results** (what COCO-style detectors write): a JSON list of ``{image_id,
  category_id, bbox [x, y, w, h], score, segmentation?}``; ``category_id`` is the BOP obj_id.
  COCO has no scene id, so ``image_id`` is mapped to (scene_id, im_id) either by a COCO
  *dataset* file given as ``coco_images`` (``--coco-images``): ``{"images": [{"id", "file_name"},
  ...], ...}`` whose ``file_name`` ends with ``<scene_id>/<image folder>/<im_id>.<ext>`` (e.g.
  ``000001/rgb/000003.png`` or ``test/000001/rgb/000003.png``, as BOP's COCO annotations have
  it); or, without one, by the encoding ``image_id = scene_id * 1000000 + im_id``
  (:func:`coco_image_id`), which :func:`write_coco_results` uses too.
"""

from __future__ import annotations

import math
import re
from numbers import Number
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from ..errors import CosyError, DatasetProblems
from ..io import bop
from ..io.atomic import write_json
from ..io.dataset import BopDataset
from .boxes import clip_xyxy, xywh_to_xyxy

DET_COLUMNS = ["scene_id", "im_id", "obj_id", "score", "x", "y", "w", "h"]
TABLE_COLUMNS = DET_COLUMNS + ["time", "segmentation"]
COCO_IMAGE_ID_FACTOR = 1_000_000  # COCO image_id = scene_id * factor + im_id (without --coco-images)
OVERHANG_PX = 4.0  # a box may leave the image by this much (clipped); more is refused
MAX_PROBLEM_LINES = 20
BOP_KEYS = ("scene_id", "image_id", "category_id", "score", "bbox")
COCO_KEYS = ("image_id", "category_id", "bbox", "score")


# ------------------------------------------------------------------------------------------------
# ground truth
# ------------------------------------------------------------------------------------------------
def detections_from_gt(ds: BopDataset, scene_ids: list[int], min_visib_fract: float = 0.1) -> pd.DataFrame:
    """Visible GT boxes (``bbox_visib`` of scene_gt_info.json, px) of instances with visib_fract >=
    ``min_visib_fract``, as a detections table (score 1). Also returns the GT index (column
    ``gt_index``) for evaluation."""
    rows = []
    for sid in scene_ids:
        if not ds.has_gt(sid):
            raise CosyError("--from-gt needs scene_gt.json and scene_gt_info.json", path=ds.scene_dir(sid))
        if not ds.scene_file(sid, "scene_gt_info").is_file():
            raise CosyError(f"--from-gt needs the visible boxes of scene_gt_info.json, which this split lacks "
                            f"(YCB-V's train_real, for one): compute them with `cosy gt-info --dataset "
                            f"{ds.root} --split {ds.split_name}`", path=ds.scene_file(sid, "scene_gt_info"))
        gt, info = ds.scene_gt(sid), ds.scene_gt_info(sid)
        for im_id in ds.image_ids(sid):
            insts, infos = gt.get(im_id, []), info.get(im_id, [])
            if len(insts) != len(infos):
                raise CosyError(f"image {im_id}: {len(insts)} GT instances but {len(infos)} scene_gt_info entries",
                                path=ds.scene_file(sid, "scene_gt_info"))
            for i, (g, inf) in enumerate(zip(insts, infos)):
                x, y, w, h = (float(v) for v in inf.bbox_visib)
                if inf.visib_fract >= min_visib_fract and w > 0 and h > 0:
                    rows.append((sid, im_id, g.obj_id, 1.0, x, y, w, h, i))
    df = pd.DataFrame(rows, columns=DET_COLUMNS + ["gt_index"])
    for c in ("scene_id", "im_id", "obj_id", "gt_index"):
        df[c] = df[c].astype(np.int64)
    return df


# ------------------------------------------------------------------------------------------------
# problems: one CosyError, or many lines at once
# ------------------------------------------------------------------------------------------------
class _Problems:
    """Collects (where, message) of one file; :meth:`raise_if_any` raises a :class:`CosyError`
    for a single problem, :class:`DatasetProblems` (one line each, the first ones) for several."""

    def __init__(self, path, max_lines: int = MAX_PROBLEM_LINES):
        self.path = None if path is None else str(path)
        self.max_lines = max_lines
        self.items: list[tuple[str | None, str]] = []
        self.keys: list[int] = []

    def add(self, where: str | None, message: str, key: int = 0) -> None:
        """One problem; reported in the order of ``key`` (e.g. the detection's index), then added."""
        self.items.append((where, message))
        self.keys.append(int(key))

    def __len__(self) -> int:
        return len(self.items)

    def raise_if_any(self) -> None:
        if not self.items:
            return
        order = sorted(range(len(self.items)), key=lambda i: self.keys[i])
        self.items = [self.items[i] for i in order]
        if len(self.items) == 1:
            where, msg = self.items[0]
            raise CosyError(msg, path=self.path, where=where)
        lines = [": ".join(p for p in (self.path, where, msg) if p) for where, msg in self.items[: self.max_lines]]
        if len(self.items) > self.max_lines:
            lines.append(f"{self.path}: ... and {len(self.items) - self.max_lines} more problem(s) "
                         f"({len(self.items)} in all)")
        raise DatasetProblems(lines)


def _is_int(v: Any) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, Number) and not isinstance(v, bool)


# ------------------------------------------------------------------------------------------------
# COCO image ids
# ------------------------------------------------------------------------------------------------
def coco_image_id(scene_id, im_id):
    """The COCO image_id cosy uses without a ``--coco-images`` file: scene_id * 1000000 + im_id
    (arrays or ints)."""
    return np.asarray(scene_id, dtype=np.int64) * COCO_IMAGE_ID_FACTOR + np.asarray(im_id, dtype=np.int64)


_FILE_NAME = re.compile(r"(?:^|/)(\d+)/[^/]+/(\d+)\.[A-Za-z0-9]+$")


def read_coco_images(path: str | Path) -> dict[int, tuple[int, int]]:
    """COCO image id -> (scene_id, im_id) from a COCO dataset JSON's ``images`` (``id``,
    ``file_name`` ending in ``<scene_id>/<folder>/<im_id>.<ext>``)."""
    path = Path(path)
    data = bop.load_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("images"), list):
        got = type(data).__name__ if not isinstance(data, dict) else f"an object with keys {sorted(data)[:6]}"
        raise CosyError(f"expected a COCO dataset file: an object with a list 'images' of {{id, file_name}}, got {got}",
                        path=path)
    probs = _Problems(path)
    out: dict[int, tuple[int, int]] = {}
    for i, im in enumerate(data["images"]):
        where = f"images[{i}]"
        if not isinstance(im, dict) or "id" not in im or "file_name" not in im:
            probs.add(where, "expected an object with keys 'id' and 'file_name'")
            continue
        if not _is_int(im["id"]):
            probs.add(where, f"id: expected an integer, got {im['id']!r:.40}")
            continue
        m = _FILE_NAME.search(str(im["file_name"]).replace("\\", "/"))
        if m is None:
            probs.add(where, f"file_name {im['file_name']!r:.80} does not end with <scene_id>/<folder>/<im_id>.<ext> "
                      "(e.g. 000001/rgb/000003.png)")
            continue
        key = int(im["id"])
        if key in out:
            probs.add(where, f"id {key} appears twice")
            continue
        out[key] = (int(m.group(1)), int(m.group(2)))
    probs.raise_if_any()
    return out


# ------------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------------
def _empty_table() -> pd.DataFrame:
    df = pd.DataFrame({c: pd.Series(dtype=np.int64 if c in ("scene_id", "im_id", "obj_id") else
                                    (object if c == "segmentation" else np.float64)) for c in TABLE_COLUMNS})
    return df


def detection_format(data: Any) -> str:
    """'bop' or 'coco' for the parsed JSON of a detections file (BOP when any entry has a
    scene_id); 'empty' for an empty list; a ValueError with the message for a CosyError otherwise."""
    if not isinstance(data, list):
        if isinstance(data, dict) and "annotations" in data and "images" in data:
            raise ValueError("this is a COCO dataset file (images + annotations), not detections: cosy reads a "
                             "JSON list of detections (BOP {scene_id, image_id, category_id, score, bbox} or COCO "
                             "results {image_id, category_id, bbox, score}); give a dataset file as --coco-images")
        raise ValueError(f"expected a JSON list of detections (BOP {{scene_id, image_id, category_id, score, bbox}} "
                         f"or COCO results {{image_id, category_id, bbox, score}}), got a JSON {type(data).__name__}")
    if not data:
        return "empty"
    return "bop" if any(isinstance(d, dict) and "scene_id" in d for d in data) else "coco"


def read_detections_any(path: str | Path, ds: BopDataset | None = None, *, coco_images: str | Path | None = None,
                        overhang_px: float = OVERHANG_PX) -> pd.DataFrame:
    """Read a BOP or COCO-results detections file (see the module docstring) into the detections
    table. Problems (wrong JSON shape, missing keys, non-integer ids, NaN scores, empty boxes) are
    reported all at once, each with the file and the detection's index. With ``ds`` the
    detections are also checked against the dataset (:func:`check_detections_against_dataset`)
    and their boxes clipped to the image."""
    path = Path(path)
    data = bop.load_json(path)
    try:
        fmt = detection_format(data)
    except ValueError as e:
        raise CosyError(str(e), path=path) from None
    if fmt == "empty":
        df = _empty_table()
    else:
        image_map = read_coco_images(coco_images) if (fmt == "coco" and coco_images is not None) else None
        df = _parse(data, fmt, path, image_map, coco_images)
    df.attrs["format"] = fmt
    if ds is not None:
        df = check_detections_against_dataset(df, ds, path, overhang_px=overhang_px)
    return df


def _parse(data: list, fmt: str, path: Path, image_map: dict | None, coco_images) -> pd.DataFrame:
    keys = BOP_KEYS if fmt == "bop" else COCO_KEYS
    other = "COCO results" if fmt == "bop" else "BOP"
    probs = _Problems(path)
    n = len(data)
    ids = np.zeros((n, 3), np.int64)  # scene_id, im_id, obj_id
    num = np.full((n, 6), np.nan)  # score, x, y, w, h, time
    segs: list = [None] * n
    ok = np.zeros(n, bool)
    for i, d in enumerate(data):
        where = f"detection {i}"
        if not isinstance(d, dict):
            probs.add(where, f"expected an object {{{', '.join(keys)}}}, got {type(d).__name__}")
            continue
        missing = [k for k in keys if k not in d]
        if missing:
            hint = f" (other entries of the file are {fmt.upper()}; this one looks like {other})" \
                if fmt == "bop" and "scene_id" not in d else ""
            probs.add(where, f"missing key(s) {', '.join(repr(k) for k in missing)}{hint}")
            continue
        bad = [k for k in ("scene_id", "image_id", "category_id") if k in keys and not _is_int(d[k])]
        if bad:
            probs.add(where, "; ".join(f"{k}: expected an integer, got {d[k]!r:.40}" for k in bad))
            continue
        if not _is_number(d["score"]) or not math.isfinite(float(d["score"])):
            probs.add(where, f"score: expected a finite number, got {d['score']!r:.40}")
            continue
        box = d["bbox"]
        if not isinstance(box, (list, tuple)) or len(box) != 4 or not all(_is_number(v) for v in box):
            probs.add(where, f"bbox: expected [x, y, w, h] (4 numbers, px), got {box!r:.60}")
            continue
        box = [float(v) for v in box]
        if not all(math.isfinite(v) for v in box):
            probs.add(where, f"bbox: non-finite value in {box}")
            continue
        if box[2] <= 0 or box[3] <= 0:
            probs.add(where, f"bbox [x, y, w, h] = {box}: width and height must be > 0")
            continue
        t = d.get("time", -1.0)
        if t is None:
            t = -1.0
        if not _is_number(t) or not math.isfinite(float(t)):
            probs.add(where, f"time: expected a number of seconds, got {t!r:.40}")
            continue
        if fmt == "bop":
            sid, im = int(d["scene_id"]), int(d["image_id"])
        elif image_map is not None:
            if int(d["image_id"]) not in image_map:
                probs.add(where, f"image_id {d['image_id']} is not in the images of {coco_images}")
                continue
            sid, im = image_map[int(d["image_id"])]
        else:
            if int(d["image_id"]) < 0:
                probs.add(where, f"image_id {d['image_id']}: expected scene_id * {COCO_IMAGE_ID_FACTOR} + im_id >= 0 "
                          "(or give the COCO dataset file with --coco-images)")
                continue
            sid, im = divmod(int(d["image_id"]), COCO_IMAGE_ID_FACTOR)
        ids[i] = sid, im, int(d["category_id"])
        num[i] = [float(d["score"]), *box, float(t)]
        segs[i] = d.get("segmentation")
        ok[i] = True
    probs.raise_if_any()
    df = pd.DataFrame({"scene_id": ids[:, 0], "im_id": ids[:, 1], "obj_id": ids[:, 2], "score": num[:, 0],
                       "x": num[:, 1], "y": num[:, 2], "w": num[:, 3], "h": num[:, 4], "time": num[:, 5],
                       "segmentation": pd.Series(segs, dtype=object)})
    return df


# ------------------------------------------------------------------------------------------------
# checks against a dataset
# ------------------------------------------------------------------------------------------------
def _short(ids, n: int = 12) -> str:
    ids = sorted(int(i) for i in ids)
    return ", ".join(map(str, ids[:n])) + (" ..." if len(ids) > n else "")


def image_sizes(ds: BopDataset, scene_ids) -> dict[int, tuple[int, int]]:
    """(width, height) px of each scene's images (read from its first image's header)."""
    out = {}
    for sid in scene_ids:
        ims = ds.image_ids(sid)
        if ims:
            out[int(sid)] = ds.image_size(sid, ims[0])  # checked against the camera file / cam_K
    return out


def check_detections_against_dataset(dets: pd.DataFrame, ds: BopDataset, source, *,
                                     overhang_px: float = OVERHANG_PX) -> pd.DataFrame:
    """Check a detections table against the dataset; return it with the boxes clipped to the image.

    Refused (all problems reported at once, each with ``source`` and the detection's index):
    category ids that are not objects of the dataset (models_info.json), scene ids not in the
    split, image ids not in their scene (scene_camera.json), NaN scores, boxes with w or h <= 0,
    boxes that leave the image by more than ``overhang_px`` pixels (wrong image size or ids?) or
    have no area inside it. Boxes overhanging by up to ``overhang_px`` are clipped."""
    probs = _Problems(source)
    dets = dets.copy()
    if len(dets) == 0:
        return dets
    idx = dets.index.to_numpy()

    def bad(i: int, message: str) -> None:
        probs.add(f"detection {idx[i]}", message, key=i)

    obj_ids = set(ds.models_info())
    unknown = ~dets["obj_id"].isin(sorted(obj_ids)).to_numpy()
    for i in np.flatnonzero(unknown):
        bad(i, f"category_id {int(dets['obj_id'].iloc[i])} is not an object of the dataset "
               f"(models_info.json has obj_id {_short(obj_ids)})")
    scenes = set(ds.scene_ids)
    sid = dets["scene_id"].to_numpy()
    im = dets["im_id"].to_numpy()
    bad_scene = ~np.isin(sid, sorted(scenes))
    for i in np.flatnonzero(bad_scene):
        bad(i, f"scene_id {int(sid[i])} is not a scene of {ds.split_dir} "
               f"(has {_short(scenes)})")
    used = sorted(set(sid[~bad_scene].tolist()))
    known = {s: set(ds.image_ids(s)) for s in used}
    bad_image = np.array([not b and int(i) not in known[int(s)] for s, i, b in zip(sid, im, bad_scene)], bool)
    for i in np.flatnonzero(bad_image):
        bad(i, f"image_id {int(im[i])} is not an image of scene {int(sid[i])} "
               f"({ds.scene_file(int(sid[i]), 'scene_camera').name} has {_short(known[int(sid[i])])})")
    score = dets["score"].to_numpy(np.float64)
    for i in np.flatnonzero(~np.isfinite(score)):
        bad(i, f"score is {score[i]}: expected a finite number")
    xywh = dets[["x", "y", "w", "h"]].to_numpy(np.float64)
    for i in np.flatnonzero(~np.isfinite(xywh).all(1) | (xywh[:, 2] <= 0) | (xywh[:, 3] <= 0)):
        bad(i, f"bbox [x, y, w, h] = {xywh[i].tolist()}: width and height must be > 0")
    sizes = image_sizes(ds, used)
    has_size = np.array([int(s) in sizes for s in sid], bool) & ~bad_scene & ~bad_image
    W = np.array([sizes[int(s)][0] if h else np.inf for s, h in zip(sid, has_size)], np.float64)
    H = np.array([sizes[int(s)][1] if h else np.inf for s, h in zip(sid, has_size)], np.float64)
    x1, y1, x2, y2 = xywh_to_xyxy(xywh).T
    over = np.maximum.reduce([-x1, -y1, x2 - W, y2 - H, np.zeros_like(x1)])
    cx1, cy1, cx2, cy2 = clip_xyxy(xywh, W, H).T
    empty = ((cx2 - cx1) <= 0) | ((cy2 - cy1) <= 0)
    bad_box = has_size & np.isfinite(xywh).all(1) & (xywh[:, 2] > 0) & (xywh[:, 3] > 0) & \
        ((over > overhang_px) | empty)
    for i in np.flatnonzero(bad_box):
        w, h = int(W[i]), int(H[i])
        what = "lies outside" if empty[i] else f"leaves by {over[i]:.1f} px (more than {overhang_px:g} px)"
        bad(i, f"bbox [x, y, w, h] = {xywh[i].tolist()} {what} the {w}x{h} image "
               f"{int(im[i])} of scene {int(sid[i])} (boxes in pixels of the full image?)")
    probs.raise_if_any()
    dets["x"], dets["y"], dets["w"], dets["h"] = cx1, cy1, cx2 - cx1, cy2 - cy1
    return dets


# ------------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------------
def write_detections(path: str | Path, dets: pd.DataFrame) -> None:
    """BOP detections JSON (atomic): see :func:`cosy_cli.io.bop.write_detections`."""
    bop.write_detections(path, dets)


def coco_results(dets: pd.DataFrame, image_ids=None) -> list[dict]:
    """Detections as COCO results dicts; ``image_ids``: COCO ids per row (default
    :func:`coco_image_id`)."""
    if image_ids is None:
        image_ids = coco_image_id(dets["scene_id"].to_numpy(), dets["im_id"].to_numpy())
    out = []
    segs = dets["segmentation"] if "segmentation" in dets else [None] * len(dets)
    for iid, o, s, x, y, w, h, seg in zip(image_ids, dets["obj_id"], dets["score"], dets["x"], dets["y"], dets["w"],
                                          dets["h"], segs):
        d = {"image_id": int(iid), "category_id": int(o), "bbox": [bop._fmt(v) for v in (x, y, w, h)],
             "score": bop._fmt(s)}
        if seg is not None and not (isinstance(seg, float) and math.isnan(seg)):
            d["segmentation"] = seg
        out.append(d)
    return out


def write_coco_results(path: str | Path, dets: pd.DataFrame) -> None:
    """COCO results JSON (atomic), image_id = scene_id * 1000000 + im_id (see the module docstring)."""
    write_json(path, coco_results(dets), indent=None)
