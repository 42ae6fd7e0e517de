"""``cosy estimate``: single-view object candidates (CosyPose stage 1, paper Section 3.1).

For every image of the scenes, every 2D detection (a BOP detections file, or the visible GT boxes
with ``from_gt``) becomes one object candidate: label, the detector's score and a pose T_cam_obj
(mm) in that image's camera. The pose comes from a chain of steps, each optional:

1. **coarse**: ``network`` (the paper's coarse render-and-compare model, one step from the
   canonical pose) or ``templates`` (training-free retrieval of the top-k rendered views,
   :mod:`~cosy_cli.singleview.training_free.templates`);
   With templates, ``verify_top`` hypotheses are first re-ranked by rendering them against the
   image (:mod:`~cosy_cli.singleview.training_free.verify`) and the ``top_k`` best kept (with depth and
   ``icp_screen`` > ``top_k``: the ``top_k`` best of the first ``icp_screen`` after a short ICP);
2. with depth, ``depth_refine: icp`` first refines every coarse hypothesis against the observed
   depth (:mod:`~cosy_cli.singleview.training_free.icp`), adds the near-symmetry variants of the best (a box
   turned over, a mug turned about its body; :mod:`~cosy_cli.singleview.training_free.depth_hypotheses`) and
   keeps, per detection, the one with the best visibility-aware depth fit (free space counted)
   plus ``image_weight`` x its image score re-evaluated at the refined pose (when verified);
   without depth the best-scoring hypothesis is kept, then (``rgb_refine: search``) refined on the
   image by a local search on the same image score, and/or (``contour``) by aligning the rendered
   outline of it and of the runner-up with the image (:mod:`~cosy_cli.singleview.training_free.contour`), kept
   where the image score improves;
3. **refiner**: ``network``, the refiner iterated ``refiner_iterations`` times (paper: 4);
4. with depth, a last ICP pass after the refiner.

``"auto"`` picks, per setting, what is available: a coarse network if one is given or shipped,
else templates; the shipped (or given) refiner if any; ICP when the dataset has depth. The
summary says which combination ran. Output: a BOP results CSV (scene_id, im_id, obj_id, score,
R, t mm, time s per image) that ``cosy match`` reads, ``<out>.timing.csv`` (per image: detections
and seconds per step), ``<out>.json`` (settings, inputs, what ran, totals) and
``<out name>.manifest.json`` (the CSV's sha1 and size, checked by ``cosy match``). With
``hypotheses`` N > 1 (``--hypotheses``) also ``<out stem>.hypotheses.csv``: per detection its pose
(rank 0) and up to N-1 runners-up of the ranking it already made (verification by rendering, or
depth + image fit with ICP; see :mod:`cosy_cli.io.hypotheses`), listed in the same manifest; the
CSV itself is unchanged (one pose per detection). ``cosy match --hypotheses`` chooses among them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from ..conf import merge_conf
from ..detection.boxes import clip_xyxy
from ..detection.importers import DET_COLUMNS, detections_from_gt  # noqa: F401 (DET_COLUMNS: re-exported)
from ..errors import CosyError
from ..io import bop
from ..io import manifest
from ..io.atomic import atomic_path, write_json, write_text
from ..io.cache import file_sha1
from ..io.cache import reuse_existing_file
from ..io.dataset import BopDataset
from ..onnxrt import provider_names
from ..shipped import ASSETS, shipped  # noqa: F401 (ASSETS: re-exported)
from ..shipped import model_path as _model_path

SHIPPED_COARSE = shipped("coarse.onnx")
SHIPPED_REFINER = shipped("refiner.onnx")

VERIFY_TOP_RGB = 48    # hypotheses verified by rendering without depth (speed: 64 gave +0.006 AR for 1.1x the time)
RGB_REFINE_AUTO = "contour"  # rgb_refine auto without depth (odd LM-O dev scenes: AR 0.313 search, 0.376 contour)
CONTOUR_TOP = 2        # rgb_refine contour: hypotheses per detection aligned (the best after search, the runner-up)
VERIFY_TOP_DEPTH = 64  # with ICP (which dominates the time there; 48 lost 0.04-0.05 BOP19 AR on YCB-V frames)

CONFS = {
    # The most accurate combination available (see the module docstring).
    "default": {
        "coarse": "auto",             # network | templates | auto
        "refiner": "auto",            # network | none | auto
        "depth_refine": "auto",       # icp | none | auto
        "refiner_iterations": 4,      # paper: 4 at test time
        "top_k": 12,                  # hypotheses per detection given the full ICP (5 before verification, 16 before the screen)
        "icp_screen": 32,             # with depth: the first this many verified hypotheses get a short ICP; the top_k best go on (0: off)
        "batch_size": 32,             # crops per network call
        "providers": "cpu",           # onnxruntime: cpu | cuda
        "min_visib_fract": 0.1,       # from_gt: boxes of instances at least this visible
        "icp_iterations": 12,         # ICP steps per hypothesis (20 before 2026-12-02: the same AR on the chosen-on data, 0.15 s more per image)
        "verify_top": "auto",         # templates: hypotheses scored by rendering (0: none; auto: 64 with ICP, else 48)
        "rgb_refine": "auto",         # search | contour | search+contour | none | auto (see RGB_REFINE_AUTO)
        "image_weight": 1.0,          # with depth and verification: pick by depth fit + this x image score
        "hypotheses": 1,              # poses per detection written (>1: the verified runners-up in a sidecar CSV)
        "masks": "auto",              # auto: use the detections' segmentations where they have them | none
        "box_scales": [1.0],          # templates: each hypothesis also at these factors of its distance (loose boxes)
        "mask_weight": 2.0,           # verification: weight of the silhouette's IoU with a detection's mask (where it
                                      # has one; 2 chosen for exact masks)
        "mask_band": 0,               # templates: with a detection's mask, only gradients within this many cells of
                                      # it (of 64 across the box) count, and its outline does (0: off)
        "scorer_scope": "rank",       # with --scorer: rank (it orders each detection's best scorer_keep hypotheses;
                                      # the refinement stays training-free) | all (every verification score is its
                                      # prediction); rank chosen on the odd LM-O scenes (as good, 3.5x faster)
        "scorer_keep": 16,            # scope rank: hypotheses per detection the scorer orders (16 chosen on the odd
                                      # LM-O scenes against 8: 0.401 -> 0.420)
        "max_per_object": 0,          # keep the best this many candidates of each object per image, by score (0: all;
                                      # with score pose: the boxes whose poses fit best)
        "score": "detection",         # a candidate's score: detection (the detector's) | pose (the detector's x the
                                      # verification score of the final pose: the learned scorer's probability with
                                      # --scorer, else the training-free score in [0, 1]; needs verification)
        "rebox": "auto",              # passes that re-run a kept candidate from the box its pose projects to (the
                                      # model's silhouette extent, clipped to the image) and keep the pose whose
                                      # verification score is higher (0: off; auto: REBOX_WITH_SCORER with a learned
                                      # scorer on RGB, else 0: with ICP on depth not measured)
    },
    # The paper's RGB-only chain: coarse network, 4 refiner iterations, no depth.
    "paper": {"coarse": "network", "refiner": "network", "depth_refine": "none", "refiner_iterations": 4, "top_k": 1,
              "icp_screen": 0, "batch_size": 32, "providers": "cpu", "min_visib_fract": 0.1, "icp_iterations": 12,
              "verify_top": "auto", "rgb_refine": "auto", "image_weight": 1.0, "hypotheses": 1, "masks": "auto",
              "box_scales": [1.0], "mask_weight": 2.0, "mask_band": 0, "scorer_scope": "rank",
              "scorer_keep": 16, "score": "detection", "max_per_object": 0, "rebox": "auto"},
    # Training-free: templates, then ICP on depth.
    "templates-icp": {"coarse": "templates", "refiner": "none", "depth_refine": "icp", "refiner_iterations": 4,
                      "top_k": 12, "icp_screen": 32, "batch_size": 32, "providers": "cpu", "min_visib_fract": 0.1,
                      "icp_iterations": 12,
                      "verify_top": "auto", "rgb_refine": "auto", "image_weight": 1.0, "hypotheses": 1,
                      "masks": "auto", "box_scales": [1.0], "mask_weight": 2.0, "mask_band": 0,
                      "scorer_scope": "rank", "scorer_keep": 16, "score": "detection", "max_per_object": 0,
                      "rebox": "auto"},
}


# rebox "auto" with a learned scorer: 2 passes, chosen on the odd LM-O dev scenes (GT boxes, scorer: 0 / 1 / 2
# passes 0.408 / 0.438 / 0.453 single view, 0.479 / 0.525 / 0.529 multi-view; docs/estimate.md)
REBOX_WITH_SCORER = 2


def resolve_conf(conf: str | dict | None = None, **overrides) -> dict:
    c = merge_conf(CONFS, conf, overrides, default="default", what="estimate")
    choices = {"coarse": ("network", "templates", "auto"), "refiner": ("network", "none", "auto"),
               "depth_refine": ("icp", "none", "auto"), "providers": ("cpu", "cuda"),
               "rgb_refine": ("search", "contour", "search+contour", "none", "auto"), "masks": ("auto", "none"),
               "scorer_scope": ("all", "rank"), "score": ("detection", "pose")}
    for k, allowed in choices.items():
        if c[k] not in allowed:
            raise CosyError(f"estimate setting {k}: expected one of {', '.join(allowed)}, got {c[k]!r}")
    for k in ("refiner_iterations", "top_k", "icp_screen", "batch_size", "icp_iterations", "hypotheses",
              "mask_band", "scorer_keep", "max_per_object") + (() if c["rebox"] == "auto" else ("rebox",)):
        try:
            c[k] = int(c[k])
        except (TypeError, ValueError):
            raise CosyError(f"estimate setting {k}: expected a whole number, got {c[k]!r}") from None
    if c["verify_top"] != "auto":
        try:
            c["verify_top"] = int(c["verify_top"])
        except (TypeError, ValueError):
            raise CosyError(f"estimate setting verify_top: expected auto or a number >= 0, got {c['verify_top']!r}") \
                from None
    c["min_visib_fract"] = float(c["min_visib_fract"])
    c["image_weight"] = float(c["image_weight"])
    try:
        c["mask_weight"] = float(c["mask_weight"])
    except (TypeError, ValueError):
        raise CosyError(f"estimate setting mask_weight: expected a number >= 0, got {c['mask_weight']!r}") from None
    if c["mask_weight"] < 0:
        raise CosyError("estimate setting mask_weight must be >= 0")
    bs = c["box_scales"]
    try:
        bs = [float(v) for v in (bs.split(",") if isinstance(bs, str) else (bs if isinstance(bs, (list, tuple)) else [bs]))]
    except (TypeError, ValueError):
        raise CosyError(f"estimate setting box_scales: expected distance factors such as 0.87,1,1.15, got {bs!r}") \
            from None
    if not bs or len(bs) > 9 or not all(0.3 <= v <= 3.0 for v in bs) or len(set(bs)) != len(bs):
        raise CosyError(f"estimate setting box_scales: 1 to 9 distinct factors in [0.3, 3], got {bs}")
    c["box_scales"] = bs
    if c["image_weight"] < 0:
        raise CosyError("estimate setting image_weight must be >= 0")
    if c["verify_top"] != "auto" and c["verify_top"] < 0:
        raise CosyError("estimate setting verify_top must be >= 0 (0: no verification by rendering)")
    if not 0 <= c["mask_band"] <= 32:
        raise CosyError("estimate setting mask_band must be 0 (off) to 32 cells")
    if c["max_per_object"] < 0:
        raise CosyError("estimate setting max_per_object must be >= 0 (0: every candidate)")
    if c["rebox"] != "auto" and not 0 <= c["rebox"] <= 3:
        raise CosyError("estimate setting rebox must be auto, or 0 (off) to 3 passes")
    if not 1 <= c["scorer_keep"] <= 256:
        raise CosyError("estimate setting scorer_keep must be 1 to 256 hypotheses per detection")
    if c["hypotheses"] < 1:
        raise CosyError("estimate setting hypotheses must be >= 1 (1: one pose per detection, no sidecar)")
    if c["refiner_iterations"] < 0 or c["top_k"] < 1 or c["batch_size"] < 1 or c["icp_iterations"] < 1 \
            or c["icp_screen"] < 0:
        raise CosyError("estimate settings out of range (refiner iterations, ICP screen >= 0; top-k, batch size, "
                        "ICP iterations >= 1)")
    return c


# ------------------------------------------------------------------------------------------------
# detections
# ------------------------------------------------------------------------------------------------
# DET_COLUMNS and detections_from_gt live in cosy_cli.detection.importers (imported above).


def detection_masks(d: pd.DataFrame, shape: tuple[int, int], source: str) -> list | None:
    """Per row of one image's detections, its (H, W) bool segmentation or None (no segmentation);
    None when no row has one. A malformed segmentation is an error naming the detection."""
    from ..io.masks import SegmentationError, decode_segmentation

    out = []
    for i, row in zip(d.index, d.itertuples(index=False)):
        seg = getattr(row, "segmentation", None)
        if seg is None or (isinstance(seg, float) and np.isnan(seg)):
            out.append(None)
            continue
        try:
            out.append(decode_segmentation(seg, shape))
        except SegmentationError as e:
            raise CosyError(f"detection {i} (scene_id {row.scene_id}, im_id {row.im_id}, obj_id {row.obj_id}): "
                            f"{e}", path=source) from None
    return out if any(m is not None for m in out) else None


def check_detections(dets: pd.DataFrame, ds: BopDataset, scene_ids: list[int], obj_ids: set[int], source: str,
                     log=print) -> pd.DataFrame:
    """Keep the detections that can be estimated; report (one line each) the skipped ones: labels
    not in the models, images not in the scenes, boxes with no area inside the image."""
    keep = np.ones(len(dets), bool)
    unknown = ~dets["obj_id"].isin(sorted(obj_ids)).to_numpy()
    if unknown.any():
        labels = sorted(set(dets.loc[unknown, "obj_id"].tolist()))
        log(f"estimate: skipping {int(unknown.sum())} detection(s) of {source} whose label is not in the models: "
            f"obj_id {', '.join(map(str, labels[:10]))}{' ...' if len(labels) > 10 else ''} "
            f"(known: {', '.join(map(str, sorted(obj_ids)))})")
        keep &= ~unknown
    in_scenes = dets["scene_id"].isin(scene_ids).to_numpy()
    keep &= in_scenes
    known_images = set()
    for sid in scene_ids:
        known_images.update((sid, i) for i in ds.image_ids(sid))
    has_image = np.array([(s, i) in known_images for s, i in zip(dets["scene_id"], dets["im_id"])], bool)
    missing = in_scenes & ~has_image
    if missing.any():
        first = dets[missing].iloc[0]
        raise CosyError(f"{int(missing.sum())} detection(s) name images that scene {int(first.scene_id)} does not "
                        f"have (first: row {int(np.flatnonzero(missing)[0])}, im_id {int(first.im_id)})", path=source)
    return dets[keep].reset_index(drop=True)


clip_boxes = clip_xyxy  # (N, 4) x, y, w, h px -> x1, y1, x2, y2 clipped to the image (pixel-edge coords)


# ------------------------------------------------------------------------------------------------
# the estimator
# ------------------------------------------------------------------------------------------------
@dataclass
class ImageEstimate:
    """The chain's result for one image: ``T`` (N, 4, 4) final poses (mm); ``steps``: name ->
    (N, 4, 4) poses after each step ("coarse", "refiner_1".., "icp"); ``times``: step -> s;
    ``alternatives`` (N, k-1, 4, 4) the other hypotheses the chain ranked (best first, the one
    that became ``T`` left out; k-1 = 0 without templates), ``alt_score`` (N, k-1) their
    ranking scores (verification score, or depth + image fit with ICP), ``best_score`` (N,)
    that of the one that became ``T``."""

    T: np.ndarray
    steps: dict = field(default_factory=dict)
    times: dict = field(default_factory=dict)
    alternatives: np.ndarray | None = None
    alt_score: np.ndarray | None = None
    best_score: np.ndarray | None = None  # (N,) the ranking score of the hypothesis that became T
    pose_score: np.ndarray | None = None  # (N,) with conf score "pose": the verification score of T, in [0, 1]


class Estimator:
    """The single-view chain for one set of objects; reusable over images.

    db: ObjectDatabase; conf: a resolved configuration whose "auto" entries have been decided
    (see :func:`decide`); coarse_model / refiner_model: ONNX paths (when used); templates: a
    TemplateSet (when coarse is "templates")."""

    def __init__(self, conf: dict, db, *, coarse_model: Path | None = None, refiner_model: Path | None = None,
                 templates=None, scorer_model: Path | None = None):
        self.conf = conf
        self.db = db
        self.templates = templates
        self.scorer = None
        if scorer_model is not None:
            from .scorer.runtime import OnnxScorer

            self.scorer = OnnxScorer(scorer_model, provider_names(conf["providers"]))
        self._renderer = None
        self._verifier = None
        self._contour = None
        self.coarse_net = self.refiner_net = None
        providers = provider_names(conf["providers"])  # onnxruntime names; the CPU is always the fallback
        if conf["coarse"] == "network":
            self.coarse_net = self._runner(coarse_model, "coarse", providers)
        if conf["refiner"] == "network":
            self.refiner_net = self._runner(refiner_model, "refiner", providers)

    def _runner(self, path, kind, providers):
        from .networks import cosypose_compat
        from .networks.onnx import OnnxPoseNet

        if cosypose_compat.is_cosypose_model(path):  # CosyPose's published networks (run dir or its ONNX)
            return cosypose_compat.make_runner(path, kind, self.db, self.renderer, providers, self.conf["batch_size"])
        from .networks.render_compare import RenderAndCompare

        net = OnnxPoseNet(path, providers=providers)
        if net.kind != kind:
            raise CosyError(f"expected a {kind} model, this one is a {net.kind} model", path=path)
        hulls = {o.obj_id: np.asarray(o.mesh.convex_hull.vertices, dtype=np.float64) for o in self.db}
        return RenderAndCompare(net, self.renderer, hulls, batch_size=self.conf["batch_size"])

    @property
    def renderer(self):
        if self._renderer is None:
            from ..rendering import SceneRenderer

            self._renderer = SceneRenderer({o.obj_id: o.mesh for o in self.db}, 64, 64)
        return self._renderer

    @property
    def verifier(self):
        if self._verifier is None:
            from .training_free.verify import Verifier, VerifyConf

            self._verifier = Verifier(self.db, VerifyConf(w_mask=float(self.conf.get("mask_weight", 2.0)),
                                                          scorer_scope=self.conf.get("scorer_scope", "rank"),
                                                          scorer_keep=int(self.conf.get("scorer_keep", 16))),
                                      scorer=self.scorer)
        return self._verifier

    @property
    def contour(self):
        if self._contour is None:
            from .training_free.contour import ContourRefiner

            self._contour = ContourRefiner(self.db)
        return self._contour

    def close(self):
        if self._contour is not None:
            self._contour.close()
            self._contour = None
        if self._verifier is not None:
            self._verifier.close()
            self._verifier = None
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def estimate(self, rgb: np.ndarray, depth: np.ndarray | None, K: np.ndarray, boxes: np.ndarray,
                 obj_ids: np.ndarray, masks=None) -> ImageEstimate:
        """Poses of N detections of one image: rgb (H, W, 3) uint8, depth (H, W) mm or None, K (3, 3),
        boxes (N, 4) x1, y1, x2, y2 px (pixel-edge), obj_ids (N,); masks: None or per detection an
        (H, W) bool segmentation or None. The training-free path uses them in the verification (the
        silhouette's IoU with the mask joins the score); ICP and the networks use the boxes."""
        c = self.conf
        N = len(boxes)
        res = ImageEstimate(np.zeros((N, 4, 4)))
        if N == 0:
            return res
        use_depth = c["depth_refine"] == "icp"
        if use_depth and depth is None:
            raise CosyError("depth refinement (icp) needs depth images; this dataset has none (use --depth-refine none)")
        t0 = time.perf_counter()
        verified = False
        if c["coarse"] == "network":
            hyp = self.coarse_net.coarse(rgb, K, boxes, obj_ids)[:, None]
            hyp_score = np.ones((N, 1))
        else:
            from .training_free.templates import MatchParams, at_distances, interleave, match_templates

            nv = c.get("verify_top", 0)
            verified = nv > 0
            if verified:  # many distinct templates, re-ranked by rendering them against the image
                kt = max(nv, c["top_k"])
                h = match_templates(self.templates, rgb, K, boxes, obj_ids, top_k=kt, params=MatchParams(nms_deg=10.0))
                if c.get("mask_band", 0) and masks is not None and any(m is not None for m in masks):
                    # half the hypotheses from the gradients near the detection's mask (less clutter): an
                    # exact mask makes those right, a wrong one costs only half the candidates
                    hm = match_templates(self.templates, rgb, K, boxes, obj_ids, top_k=kt, masks=masks,
                                         params=MatchParams(nms_deg=10.0, mask_band=int(c["mask_band"])))
                    h = interleave(hm, h, kt)
                if c.get("box_scales", [1.0]) != [1.0]:  # a loose box: its size says the distance only roughly
                    h = at_distances(h, c["box_scales"])
                # the cascade (coarse copies first) with depth too: see verify's module docstring
                ranked = self.verifier.rank(rgb, K, boxes, obj_ids, h.T_cam_obj, h.scores, masks=masks)
                hyp, hyp_score = ranked.T_cam_obj[:, :c["top_k"]], ranked.score[:, :c["top_k"]]
                res.steps["templates"] = h.T_cam_obj[:, 0].copy()
            else:
                h = match_templates(self.templates, rgb, K, boxes, obj_ids, top_k=c["top_k"])
                hyp, hyp_score = h.T_cam_obj, h.scores
        k = hyp.shape[1]
        hs = np.asarray(hyp_score, dtype=np.float64).reshape(N, -1)
        res.alternatives, res.alt_score, res.best_score = hyp[:, 1:].copy(), hs[:, 1:].copy(), hs[:, 0].copy()
        res.times["coarse"] = time.perf_counter() - t0
        res.steps["coarse"] = hyp[:, 0].copy()
        T = hyp[:, 0].copy()
        rgb_refine = c.get("rgb_refine") if verified and not use_depth else "none"
        # the first hypothesis' score, unless the scorer ranked (scope "rank") and the steps below are training-free
        s_first = ranked.score[:, 0] if verified and (self.scorer is None or self.verifier.conf.scorer_scope == "all") \
            else None
        if rgb_refine in ("search", "search+contour"):
            t0 = time.perf_counter()
            T, s_T = self.verifier.refine(ranked.obs, obj_ids, T, ranked.prior[:, 0], s_first)
            res.times["rgb_refine"] = time.perf_counter() - t0
            res.steps["rgb_refine"] = T.copy()
        if rgb_refine in ("contour", "search+contour"):  # contour alignment of the best CONTOUR_TOP hypotheses
            from .training_free.contour import refine_contour

            t0 = time.perf_counter()
            H = ranked.T_cam_obj[:, :CONTOUR_TOP].copy()
            H[:, 0] = T
            s0 = s_T if rgb_refine == "search+contour" else s_first
            T = refine_contour(self.contour, self.verifier, ranked.obs, rgb, K, boxes, obj_ids, H,
                               ranked.prior[:, :CONTOUR_TOP], s0).T
            res.times["contour"] = time.perf_counter() - t0
            res.steps["contour"] = T.copy()
        if use_depth:
            from .training_free.icp import IcpConf, refine_with_depth

            t0 = time.perf_counter()
            icp_conf = IcpConf(iterations=c["icp_iterations"])
            from .training_free import depth_hypotheses as dh

            # ICP, then pick by depth fit (visibility-aware) + image_weight x the image score re-evaluated
            # at the refined poses (when verified); more hypotheses where none fits the depth, and the
            # near-symmetry variants of the best (a turned-over box, a turned mug): dh.refine_and_rank
            img_of, tiebreak, pool, pool_score = None, None, hyp, None
            if verified:
                def img_of(det, T_, src):
                    return self.verifier.score(ranked.obs, det, obj_ids[det], T_, ranked.prior[det, src])
                pool, pool_score = ranked.T_cam_obj, ranked.score
            else:
                tiebreak = 1e-3 * hyp_score / max(float(np.abs(hyp_score).max()), 1e-9)
            Tk, fit = dh.refine_and_rank(depth, K, boxes, obj_ids, pool, k, self.db, icp_conf, image_score=img_of,
                                         image_weight=c.get("image_weight", 1.0), tiebreak=tiebreak,
                                         prior_score=pool_score, screen=c.get("icp_screen", 0) if verified else 0)
            fit = np.where(np.isfinite(fit), fit, -np.inf)
            best = fit.argmax(1)
            T = Tk[np.arange(N), best]
            rk = np.argsort(-fit, axis=1, kind="stable")[:, 1:]  # the others, best fit first
            res.alternatives = np.take_along_axis(Tk, rk[:, :, None, None], 1)
            res.alt_score = np.take_along_axis(fit, rk, 1)
            res.alt_score[~np.isfinite(res.alt_score)] = np.nan  # padding (fewer variants): no hypothesis
            res.best_score = fit[np.arange(N), best]
            res.times["icp"] = time.perf_counter() - t0
            res.steps["icp"] = T.copy()
        if self.refiner_net is not None and c["refiner_iterations"] > 0:
            t0 = time.perf_counter()
            for i, Ti in enumerate(self.refiner_net.iterate(rgb, K, T, obj_ids, c["refiner_iterations"]), 1):
                res.steps[f"refiner_{i}"] = Ti
            T = Ti
            res.times["refiner"] = time.perf_counter() - t0
            if use_depth:
                t0 = time.perf_counter()
                r = refine_with_depth(depth, K, boxes, obj_ids, T, self.db, icp_conf)
                T = r.T_cam_obj
                res.times["icp"] += time.perf_counter() - t0
                res.steps["refiner_icp"] = T.copy()
        res.T = T
        if c.get("score", "detection") == "pose" or c.get("rebox", 0) not in (0, "auto"):  # (auto: not resolved)
            t0 = time.perf_counter()
            res.pose_score = self.pose_score(rgb, K, boxes, obj_ids, T, masks, ranked if verified else None)
            res.times["pose_score"] = time.perf_counter() - t0
        return res

    def pose_score(self, rgb, K, boxes, obj_ids, T, masks=None, ranked=None) -> np.ndarray:
        """(N,) the verification score in [0, 1] of the final poses T (N, 4, 4): the learned
        scorer's probability that a pose is within the BOP tolerances when there is one, else the
        training-free image score; one render of the N poses. ``ranked``: the verification's
        observations (and template scores) of these detections, reused when given."""
        from .training_free.verify import observe

        N = len(T)
        if ranked is not None:
            obs, prior = ranked.obs, ranked.prior[:, 0]
        else:
            masks = [None] * N if masks is None else list(masks)
            obs = [observe(rgb, K, b, self.verifier.conf, m) for b, m in zip(np.asarray(boxes, float), masks)]
            prior = None
        prior = None if prior is None else np.nan_to_num(np.asarray(prior, np.float64), nan=0.0)
        ok = np.all(np.isfinite(T.reshape(N, -1)), 1) & (T[:, 2, 3] > 0)
        out = np.zeros(N)
        if ok.any():
            det = np.flatnonzero(ok)
            out[det] = self.verifier.score(obs, det, np.asarray(obj_ids)[det], T[det],
                                           None if prior is None else prior[det], learned=self.scorer is not None)
        return np.clip(out, 0.0, 1.0)


def decide(conf: dict, *, coarse_model: Path | None, refiner_model: Path | None, has_depth: bool) -> dict:
    """Replace the "auto" entries of ``conf`` by what is available (a copy)."""
    c = dict(conf)
    if c["coarse"] == "auto":
        c["coarse"] = "network" if coarse_model is not None and Path(coarse_model).exists() else "templates"
    if c["refiner"] == "auto":
        c["refiner"] = "network" if refiner_model is not None and Path(refiner_model).exists() else "none"
    if c["depth_refine"] == "auto":
        c["depth_refine"] = "icp" if has_depth else "none"
    if c.get("verify_top") == "auto":  # chosen on the odd LM-O dev scenes (RGB) and YCB-V frames 1-5 (RGB-D)
        c["verify_top"] = VERIFY_TOP_DEPTH if c["depth_refine"] == "icp" else VERIFY_TOP_RGB
    if c.get("rgb_refine", "none") == "auto":
        c["rgb_refine"] = RGB_REFINE_AUTO if c["coarse"] == "templates" and c["depth_refine"] == "none" \
            and c.get("verify_top", 0) > 0 else "none"
    return c


def describe(conf: dict) -> str:
    parts = [f"coarse {conf['coarse']}" + (f" (top {conf['top_k']})" if conf["coarse"] == "templates" else "")]
    if conf["coarse"] == "templates" and conf.get("verify_top", 0) > 0:
        parts[0] += (f", {conf['verify_top']}" + (f" x {len(conf['box_scales'])} distances"
                                                  if len(conf.get("box_scales", [1.0])) > 1 else "")
                     + " verified by rendering" + (" (learned scorer)" if conf.get("scorer") else ""))
    if conf.get("rgb_refine") in ("search", "contour", "search+contour"):
        parts.append({"search": "RGB refinement", "contour": "contour alignment",
                      "search+contour": "RGB refinement + contour alignment"}[conf["rgb_refine"]])
    if conf["depth_refine"] == "icp":
        screened = conf["coarse"] == "templates" and conf.get("verify_top", 0) > 0 \
            and conf.get("icp_screen", 0) > conf["top_k"]
        parts.append(f"short ICP of {conf['icp_screen']}, the best {conf['top_k']} ICP on depth" if screened
                     else "ICP on depth")
    if conf["refiner"] == "network" and conf["refiner_iterations"] > 0:
        parts.append(f"refiner x{conf['refiner_iterations']}")
    return " -> ".join(parts)


# ------------------------------------------------------------------------------------------------
# the stage
# ------------------------------------------------------------------------------------------------
def uses_templates(conf: dict) -> bool:
    """Whether the settings ``conf`` make the coarse step use templates (with the shipped models)."""
    return conf["coarse"] == "templates" or (conf["coarse"] == "auto" and not Path(SHIPPED_COARSE).is_file())


def ensure_templates(models_dir: str | Path, templates_dir: str | Path, log=print) -> Path:
    """Build or bring up to date the templates of ``models_dir`` in ``templates_dir``. An existing
    folder keeps the settings it was built with (``cosy templates --viewpoints ...``); a new one
    gets the default settings."""
    from .training_free import templates as tpl

    tdir = Path(templates_dir)
    old = tpl.read_manifest(tdir) if tdir.is_dir() else None
    return tpl.main(old["conf"] if old and old.get("conf") else None, models_dir, tdir, log=log)


def _given_model(given, shipped_path: Path, kind: str, needed: bool) -> Path | None:
    """:func:`cosy_cli.shipped.model_path`, also accepting a CosyPose run directory."""
    from .networks.cosypose_compat import is_cosypose_run, read_run

    if given is not None and Path(given).is_dir():
        if not is_cosypose_run(given):
            read_run(given)  # raises, naming what the directory lacks
        return Path(given)
    return _model_path(given, shipped_path, kind, needed)


def model_sha1(path) -> str:
    from .networks.cosypose_compat import model_sha1 as sha1

    return sha1(path)


def best_per_object(obj_ids: np.ndarray, score: np.ndarray, n: int) -> np.ndarray:
    """(N,) bool: the ``n`` best-scored rows of each obj_id (ties: the first rows)."""
    obj_ids, score = np.asarray(obj_ids), np.asarray(score, np.float64)
    order = np.lexsort((np.arange(len(score)), -score, obj_ids))  # by object, best score first, then row
    sorted_ids = obj_ids[order]
    start = np.r_[0, np.flatnonzero(sorted_ids[1:] != sorted_ids[:-1]) + 1] if len(order) else np.zeros(0, int)
    rank = np.arange(len(order)) - np.repeat(start, np.diff(np.r_[start, len(order)]))
    keep = np.zeros(len(score), bool)
    keep[order[rank < n]] = True
    return keep


def _alternatives(r: ImageEstimate, m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ranking score of each detection's pose (N,), its first ``m`` alternatives (N, m, 4, 4)
    and their scores (N, m); missing ones (fewer ranked hypotheses) have a NaN score."""
    N = len(r.T)
    T = np.tile(np.eye(4), (N, m, 1, 1))
    s = np.full((N, m), np.nan)
    if r.alternatives is not None and r.alternatives.shape[1]:
        k = min(m, r.alternatives.shape[1])
        T[:, :k], s[:, :k] = r.alternatives[:, :k], r.alt_score[:, :k]
    s0 = r.best_score if r.best_score is not None else np.zeros(N)
    return np.asarray(s0, dtype=np.float64), T, s


def rebox_pass(est: "Estimator", rgb: np.ndarray, depth, K: np.ndarray, boxes: np.ndarray, obj_ids: np.ndarray,
               masks, r: ImageEstimate, idx: np.ndarray) -> np.ndarray:
    """One ``rebox`` pass over the detections ``idx`` of an image (their boxes (N, 4) x1, y1, x2,
    y2 px and estimates ``r``, with pose scores): each pose's projected extent (the model's surface
    samples, clipped to the image) becomes a box that goes through stage 1 again, and a detection
    takes the new pose where its verification score is higher. A detector whose boxes are loose
    (on real LM-O the onboarded one cuts the thin top of the watering can and the glue) gives
    templates and verification a crop that fits no pose; the box of a roughly right pose fits the
    object better. ``r.T``, ``r.pose_score``, ``r.best_score`` and the runners-up (``r.alternatives``,
    ``r.alt_score``: those of the ranking the new pose came from) are updated in place; returns the
    replaced indices."""
    from ..geometry.camera import projected_boxes

    idx = np.asarray(idx, dtype=np.int64)
    if not len(idx):
        return idx
    H, W = rgb.shape[:2]
    nb = projected_boxes([est.db[int(o)].points for o in obj_ids[idx]], r.T[idx], K, W, H)
    ok = np.all(np.isfinite(nb), 1) & (nb[:, 2] - nb[:, 0] >= 2) & (nb[:, 3] - nb[:, 1] >= 2)
    j = idx[ok]
    if not len(j):
        return j
    r2 = est.estimate(rgb, depth, K, nb[ok], obj_ids[j], masks=None if masks is None else [masks[i] for i in j])
    better = r2.pose_score > r.pose_score[j]
    moved = j[better]
    r.T[moved], r.pose_score[moved] = r2.T[better], r2.pose_score[better]
    if r.best_score is not None and r2.best_score is not None:  # the sidecar's rank 0 is the row's pose
        r.best_score[moved] = r2.best_score[better]
    if r.alternatives is not None and r2.alternatives is not None \
            and r.alternatives.shape[1:] == r2.alternatives.shape[1:]:  # its runners-up: the same ranking's
        r.alternatives[moved], r.alt_score[moved] = r2.alternatives[better], r2.alt_score[better]
    return moved


def _hypotheses_text(T: np.ndarray, s0: np.ndarray, alt_T: np.ndarray, alt_s: np.ndarray) -> str:
    """The sidecar CSV (:mod:`cosy_cli.io.hypotheses`): per detection rank 0 = its CSV row's pose
    (with the ranking score of the hypothesis it came from), then the alternatives that exist."""
    from ..io import hypotheses as hyp_io

    n, m = alt_s.shape
    det = np.repeat(np.arange(n), m + 1)
    rank = np.tile(np.arange(m + 1), n)
    allT = np.concatenate([T[:, None], alt_T], 1).reshape(-1, 4, 4)
    score = np.concatenate([s0[:, None], alt_s], 1).reshape(-1)
    keep = ~np.isnan(score) | (rank == 0)
    score = np.nan_to_num(score, nan=0.0)
    return hyp_io.format_hypotheses(det[keep], rank[keep], score[keep], allT[keep])


def output_paths(out: Path) -> tuple[Path, Path]:
    return out.with_suffix(".timing.csv"), out.with_suffix(".json")


def _inputs_doc(ds: BopDataset, split: str, scene_ids, detections, models_dir: Path, coarse, refiner,
                scorer=None) -> dict:
    doc = {
        "dataset": str(Path(ds.root).resolve()), "split": split, "scene_ids": [int(s) for s in scene_ids],
        "detections": "gt" if detections is None else {"path": str(Path(detections).resolve()),
                                                       "sha1": file_sha1(detections)},
        "models": {"dir": str(models_dir.resolve()), "models_info_sha1": file_sha1(models_dir / "models_info.json")},
        "coarse_model": None if coarse is None else {"path": str(coarse), "sha1": model_sha1(coarse)},
        "refiner_model": None if refiner is None else {"path": str(refiner), "sha1": model_sha1(refiner)},
    }
    if scorer is not None:  # recorded only when used: outputs of earlier versions stay up to date
        doc["scorer_model"] = {"path": str(Path(scorer).resolve()), "sha1": file_sha1(scorer)}
    return doc


def main(conf: str | dict | None, dataset: str | Path, split: str, out: str | Path, overwrite: bool = False, *,
         scene_ids: list[int] | None = None, detections: str | Path | None = None, from_gt: bool = False,
         models_dir: str | Path | None = None, coarse_model: str | Path | None = None,
         refiner_model: str | Path | None = None, templates_dir: str | Path | None = None,
         split_type: str | None = None, scorer_model: str | Path | None = None, log=print, progress: bool = True,
         keep_steps: bool = False) -> dict | None:
    """Run ``cosy estimate``; returns the summary (None when ``out`` is up to date and skipped).

    detections: a BOP detections JSON, or ``from_gt`` for the visible GT boxes. models_dir: the
    objects (default the dataset's models/). coarse_model / refiner_model: ONNX files (default the
    shipped ones). templates_dir: where templates are built/reused (default ``<out dir>/templates``).
    scorer_model: a learned hypothesis scorer (``cosy train scorer``; ONNX) that replaces the
    training-free verification score (used where hypotheses are verified: templates with
    ``verify_top`` > 0). keep_steps: also return the poses after every step (``summary["steps"]``,
    for benchmarks).
    """
    from ..console import progress as progress_bar

    from ..objects import ObjectDatabase

    t_start = time.perf_counter()
    conf = resolve_conf(conf)
    out = Path(out)
    timing_path, doc_path = output_paths(out)
    if (detections is None) == (not from_gt):
        raise CosyError("give either a detections file (--detections) or --from-gt")
    ds = BopDataset(dataset, split, split_type=split_type) if split_type else BopDataset(dataset, split)
    scene_ids = ds.select_scenes(scene_ids)
    models_dir = Path(models_dir) if models_dir is not None else ds.models_dir
    first_scene = scene_ids[0] if scene_ids else None
    has_depth = first_scene is not None and bool(ds.image_ids(first_scene)) and \
        ds.depth_path(first_scene, ds.image_ids(first_scene)[0]) is not None
    wants = {k: conf[k] for k in ("coarse", "refiner")}
    coarse_model = _given_model(coarse_model, SHIPPED_COARSE, "coarse", wants["coarse"] == "network")
    refiner_model = _given_model(refiner_model, SHIPPED_REFINER, "refiner", wants["refiner"] == "network")
    run_conf = decide(conf, coarse_model=coarse_model, refiner_model=refiner_model, has_depth=has_depth)
    # recorded only when changed
    for k in ("mask_weight", "mask_band", "scorer_scope", "scorer_keep", "score", "max_per_object"):
        if run_conf.get(k) == CONFS["default"][k]:
            run_conf.pop(k)
    n_hyp = int(run_conf.pop("hypotheses", 1))
    if n_hyp > 1:  # recorded only when used: outputs of earlier versions stay up to date
        run_conf["hypotheses"] = n_hyp
    if run_conf["depth_refine"] == "icp" and not has_depth:
        raise CosyError("--depth-refine icp needs depth images, and this split has none "
                        "(use --depth-refine none)", path=ds.split_dir)
    ds.check_image_files(scene_ids, depth=run_conf["depth_refine"] == "icp")  # sizes vs camera/cam_K, from headers
    used_coarse = coarse_model if run_conf["coarse"] == "network" else None
    used_refiner = refiner_model if run_conf["refiner"] == "network" else None
    used_scorer = None
    if scorer_model is not None:
        scorer_model = Path(scorer_model)
        if not scorer_model.is_file():
            raise CosyError("scorer model not found (train one with `cosy train scorer`)", path=scorer_model)
        if run_conf["coarse"] == "templates" and run_conf.get("verify_top", 0) > 0:
            used_scorer = scorer_model
            run_conf["scorer"] = True
        else:
            from ..errors import warn

            warn("--scorer is used only where template hypotheses are verified by rendering "
                 "(coarse templates, verify_top > 0): ignored")
    if run_conf.get("rebox") == "auto":
        run_conf["rebox"] = REBOX_WITH_SCORER if used_scorer is not None and run_conf["depth_refine"] != "icp" else 0
    if not run_conf.get("rebox"):  # recorded only when used: outputs of earlier versions stay up to date
        run_conf.pop("rebox", None)
    inputs = _inputs_doc(ds, split, scene_ids, detections, models_dir, used_coarse, used_refiner, used_scorer)

    if not keep_steps and reuse_existing_file(out, doc_path, "estimate", overwrite, run_conf, inputs, log):
        return None

    db = ObjectDatabase.from_models_dir(models_dir)
    if from_gt:
        dets = detections_from_gt(ds, scene_ids, conf["min_visib_fract"])
        source = f"GT boxes of {ds.split_dir}"
    else:
        manifest.verify(detections)  # refuses a file changed since cosy detect wrote it
        dets = bop.read_detections(detections)
        source = str(detections)
    dets = check_detections(dets, ds, scene_ids, set(db.obj_ids), source, log)
    use_masks = conf["masks"] == "auto" and "segmentation" in dets and bool(dets["segmentation"].notna().any())
    if use_masks:  # recorded only when used: outputs of earlier versions stay up to date
        run_conf["masks"] = "detections"
        log(f"estimate: {int(dets['segmentation'].notna().sum())} of {len(dets)} detections have a segmentation: "
            "used in the verification (--masks none: boxes only)")

    templates = None
    if run_conf["coarse"] == "templates":
        from .training_free import templates as tpl

        tdir = Path(templates_dir) if templates_dir is not None else out.parent / "templates"
        ensure_templates(models_dir, tdir, log=log)
        templates = tpl.TemplateSet.load(tdir)
    log(f"estimate: {describe(run_conf)}; {len(dets)} detections in {len(scene_ids)} scene(s)")

    est = Estimator(run_conf, db, coarse_model=used_coarse, refiner_model=used_refiner, templates=templates,
                    scorer_model=used_scorer)
    unseen = est.scorer.unseen(db.obj_ids) if est.scorer is not None else []
    if unseen:
        log(f"estimate: note: the scorer was not trained on obj_id {', '.join(map(str, unseen))} (it was on "
            f"{', '.join(map(str, est.scorer.obj_ids))}); it still compares their renders with the image")
    images = [(sid, im) for sid in scene_ids for im in ds.image_ids(sid)]
    groups = dets.groupby(["scene_id", "im_id"]).indices
    rows_T, rows_meta, timing, steps, rows_alt = [], [], [], {}, []
    skipped_boxes = dropped_by_object = reboxed = 0
    try:
        for sid, im_id in progress_bar(images, desc="estimate", unit="image", enabled=progress):
            idx = groups.get((sid, im_id))
            if idx is None:
                timing.append({"scene_id": sid, "im_id": im_id, "detections": 0, "time_s": 0.0})
                continue
            t0 = time.perf_counter()
            d = dets.iloc[idx]
            rgb_path = ds.rgb_path(sid, im_id)
            rgb = ds.read_rgb(sid, im_id)
            depth = ds.read_depth(sid, im_id) if run_conf["depth_refine"] == "icp" else None
            if run_conf["depth_refine"] == "icp" and depth is None:
                raise CosyError("depth image missing (needed by --depth-refine icp)", path=rgb_path)
            K = ds.scene_camera(sid)[im_id].K
            H, W = rgb.shape[:2]
            boxes = clip_boxes(d[["x", "y", "w", "h"]].to_numpy(), W, H)
            ok = ((boxes[:, 2] - boxes[:, 0]) >= 2) & ((boxes[:, 3] - boxes[:, 1]) >= 2)
            skipped_boxes += int((~ok).sum())
            d, boxes = d[ok], boxes[ok]
            masks = detection_masks(d, (H, W), source) if use_masks else None
            r = est.estimate(rgb, depth, K, boxes, d["obj_id"].to_numpy(), masks=masks)
            dt = time.perf_counter() - t0
            n_estimated = len(d)
            det_score = score = d["score"].to_numpy(np.float64)
            pose_scored = run_conf.get("score", "detection") == "pose"
            if pose_scored:  # score "pose": the detection's x its pose's verification score
                score = det_score * r.pose_score
            keep = np.ones(len(d), bool)
            if run_conf.get("max_per_object", 0):  # the best candidates of each object in this image
                keep = best_per_object(d["obj_id"].to_numpy(), score, run_conf["max_per_object"])
                dropped_by_object += int((~keep).sum())
            moved = np.flatnonzero(keep)
            for _ in range(run_conf.get("rebox", 0)):  # kept candidates again from the boxes their poses project to
                t1 = time.perf_counter()  # (after the first pass only the moved ones: the others' boxes are the same)
                moved = rebox_pass(est, rgb, depth, K, boxes, d["obj_id"].to_numpy(), masks, r, moved)
                reboxed += len(moved)
                if pose_scored and len(moved):
                    score[moved] = det_score[moved] * r.pose_score[moved]
                r.times["rebox"] = r.times.get("rebox", 0.0) + time.perf_counter() - t1
                dt += time.perf_counter() - t1
            rows_T.append(r.T[keep])
            if n_hyp > 1:
                rows_alt.append(tuple(a[keep] for a in _alternatives(r, n_hyp - 1)))
            d, score = d[keep], score[keep]
            rows_meta.append(pd.DataFrame({"scene_id": sid, "im_id": im_id, "obj_id": d["obj_id"].to_numpy(),
                                           "score": score, "time": dt,
                                           "det_index": d.index.to_numpy()}))
            timing.append({"scene_id": sid, "im_id": im_id, "detections": n_estimated, "time_s": dt,
                           **{f"{k}_s": v for k, v in r.times.items()}})
            if keep_steps:
                for name, T in r.steps.items():
                    steps.setdefault(name, []).append(T)
    finally:
        est.close()
    if skipped_boxes:
        log(f"estimate: skipped {skipped_boxes} detection(s) whose box has less than 2 px inside the image")
    if run_conf.get("rebox", 0):
        log(f"estimate: rebox: {reboxed} pose(s) replaced by the estimate from the box of their own projection")
    if dropped_by_object:
        log(f"estimate: kept the best {run_conf['max_per_object']} candidate(s) of each object per image by "
            f"{'pose score' if run_conf.get('score') == 'pose' else 'score'}: {dropped_by_object} dropped")
    meta = pd.concat(rows_meta, ignore_index=True) if rows_meta else pd.DataFrame(
        columns=["scene_id", "im_id", "obj_id", "score", "time", "det_index"])
    T_all = np.concatenate(rows_T) if rows_T else np.zeros((0, 4, 4))
    res = bop.PoseResults.from_arrays(meta["scene_id"], meta["im_id"], meta["obj_id"], meta["score"], T_all,
                                      meta["time"])
    timing_df = pd.DataFrame(timing).fillna(0.0)
    n_img = int((timing_df["detections"] > 0).sum()) if len(timing_df) else 0
    busy = timing_df[timing_df["detections"] > 0] if len(timing_df) else timing_df
    summary = {
        "method": describe(run_conf), "conf": run_conf, "inputs": inputs, "images": len(images),
        "images_with_detections": n_img, "detections": int(len(res)), "skipped_boxes": skipped_boxes,
        "time_per_image_s": float(busy["time_s"].mean()) if n_img else 0.0,
        "time_per_detection_s": float(busy["time_s"].sum() / max(int(busy["detections"].sum()), 1)) if n_img else 0.0,
        "time_total_s": round(time.perf_counter() - t_start, 3),
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(timing_path) as tmp:
        timing_df.to_csv(tmp, index=False, float_format="%.6g")
    write_json(doc_path, summary)
    text = bop.format_results(res)
    from ..io import hypotheses as hyp_io

    hyp_path = hyp_io.sidecar_path(out)
    extra = {}
    if n_hyp > 1:  # the runners-up of every detection, rank 0 = its row of the CSV
        s0 = np.concatenate([a[0] for a in rows_alt]) if rows_alt else np.zeros(0)
        alt_T = np.concatenate([a[1] for a in rows_alt]) if rows_alt else np.zeros((0, n_hyp - 1, 4, 4))
        alt_s = np.concatenate([a[2] for a in rows_alt]) if rows_alt else np.zeros((0, n_hyp - 1))
        hyp_text = _hypotheses_text(T_all, s0, alt_T, alt_s)
        extra[hyp_path.name] = hyp_text.encode("utf-8")
        summary["hypotheses_file"] = str(hyp_path)
    # the manifest first (it lists the sidecar too), then the sidecar, the CSV last
    manifest.write_file_manifest(out, "cosy estimate", text.encode("utf-8"), extra=extra)  # checked by cosy match
    if n_hyp > 1:
        write_text(hyp_path, hyp_text)
    else:
        hyp_path.unlink(missing_ok=True)  # a stale sidecar of an earlier run would not match this CSV
    write_text(out, text)  # last: a complete CSV means the whole stage finished
    log(f"estimate: {len(res)} candidates from {n_img} images, {summary['time_per_image_s'] * 1e3:.0f} ms per image "
        f"({summary['time_per_detection_s'] * 1e3:.0f} ms per detection) -> {out}")
    if keep_steps:
        summary["steps"] = {k: np.concatenate(v) for k, v in steps.items()}
        summary["det_index"] = meta["det_index"].to_numpy()
        summary["detections_table"] = dets
    return summary
