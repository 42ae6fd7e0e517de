"""``cosy refine``: one consistent scene per group of views (CosyPose stage 3).

Inputs: what ``cosy match`` wrote (``MATCH_DIR/groups.json``: groups, physical objects and
their candidates, view pairs with relative poses and how they were linked;
``MATCH_DIR/candidates.csv``: the candidate poses) and the dataset's cameras (K, and the camera
poses when match ran with ``--known-cameras``) and models (points, symmetries). Per group:
cameras are placed by chaining the linked view pairs' relative poses over a maximum-inlier
spanning tree (:mod:`cosy_cli.multiview.placement`: RANSAC links first, links through one or
two objects only to reach views RANSAC leaves apart), or taken from the dataset with known
cameras; objects from their most consistent candidate; then cameras and objects are refined
jointly by the object-level bundle adjustment of :mod:`cosy_cli.multiview.bundle_adjustment`.
Candidates that matching left apart are then paired again in 2D with the adjusted cameras
(:func:`rematch_leftovers`, setting ``rematch``): two of one label in two views whose
triangulated object reprojects onto both become one more object (``"rematched": true``).

Output folder (built atomically):

``scene.json``
    ``{"format": "cosy-refine", "version", "conf", "matches", ..., "world_frame",
    "groups": [{"scene_id", "group_id", "gauge_im_id", "cameras": [{"im_id", "T_world_cam",
    "placed_by"}], "unplaced_im_ids", "placed_by": {im_id: how}, "objects": [{"object_id",
    "obj_id", "score", "n_candidates", "cand_ids", "reprojection_error_px", "T_world_obj"}],
    "stats": {...}}], "summary": {...}}``. 4x4 matrices in mm; the world frame is the gauge
    camera's frame (the view with most inliers), or the dataset's world frame when match ran with
    ``--known-cameras``. ``placed_by`` says how each camera was placed: "gauge (world frame)",
    "ransac (N inliers)", "two objects (obj_id A, B)", "one object (obj_id A)", "known",
    "unplaced" (its candidates are kept as predictions), or "unplaced (its candidates disagree
    with the refined scene)" (after the adjustment none of its candidates agrees with a refined
    object: see ``min_agreeing``). Objects found by :func:`rematch_leftovers` carry
    ``"rematched": true``. ``stats``: iterations, converged, n_rematched_objects,
    initial and final cost (px^2: mean truncated squared reprojection error), reprojection error
    per view (px, initial and final), candidates used, fallback candidates output, time.
``predictions.csv``
    BOP results. With ``output`` "scene+candidates" (default; the paper's
    ``ba_output+all_cand``): one row per (refined object, placed camera), the object's pose in
    that camera T_cam_obj = inv(T_world_cam) T_world_obj, score 1 + the object's score (the best
    score of its candidates, clipped to [0, 1]); plus every candidate of the group that no refined
    prediction of its label in its image explains (centres closer than ``explained_frac`` x the
    diameter), unchanged, with half its score (clipped to [0, 1]) -- strictly below every refined
    prediction, so that a BOP top-k per image and object takes a single-view estimate only where
    the scene has none (objects seen in one view, views that could not be placed). With
    ``guard_views`` (default), a view whose own candidates of an object all lie farther than
    ``explained_frac`` x the diameter from the refined object gets no refined row for it: its
    candidates stay (scene.json ``views_keeping_their_candidates``). With
    ``output`` "scene": the refined rows alone. time = seconds spent on the group.

    Image check (setting ``image_check``, default "auto": on when the group's RGB images exist;
    beyond the paper; :mod:`cosy_cli.multiview.image_check`): each refined row is scored against
    its view's image with the single-view verification score as refined, contour-aligned from the
    refined pose (``image_check_align``; refused when it moves the centre more than
    ``image_check_max_move`` x the diameter) and as the view's own candidates of the object; the
    best-scoring pose is the row's pose (a candidate only when it scores more than
    ``image_check_margin`` higher), with the same score 1 + s. scene.json records per object which
    pose each view kept (``"image_check": {im_id: "refined" | "aligned" | "candidate"}``) and per
    group ``stats.image_check`` (counts, seconds). With "none" the output is that of the refinement
    alone, bit for bit. Odd LM-O dev scenes (chosen there), cosy's own RGB candidates: AR (MSSD,
    MSPD) multi-view 0.391 -> 0.399 (single view 0.376); held-out even scenes 0.365 -> 0.369 (single
    view 0.372); synthetic candidates and YCB-V unchanged (the module's docstring).

    Leftovers (``image_check_leftovers``, default on with the image check; RGB views, and views
    with depth when the group's views are distinct viewpoints: :func:`wide_views`):
    the single-view candidates that no refined object explains are clustered across the group's
    placed views (same label; each one's centre, carried through the cameras, projects within
    its size of the other's) and each cluster member's pose is scored in every member's view;
    a member takes the pose with the best mean score when it beats its own by more than
    ``image_check_margin``. scene.json records per group ``leftovers`` (the clusters as cand_ids,
    and per replaced candidate ``pose_of_cand_id``) and ``stats.image_check_leftovers``. Odd LM-O
    dev scenes (chosen there): multi-view 0.399 -> 0.429; held-out even scenes 0.369 -> 0.379.

    Feature cameras (``feature_cameras``, default "leftovers"; beyond the paper;
    :mod:`cosy_cli.multiview.features`): without known cameras and with the RGB images, each placed
    view's rotation and baseline direction relative to the gauge view from SIFT features and an
    essential matrix, the scale from the objects seen in both views; used where the pair is
    trusted. "leftovers": these cameras carry the leftover candidates across views (the refined
    scene is unchanged); "scene": the objects are adjusted again with them held. scene.json: per
    group ``stats.feature_cameras`` (inliers, used, per view) and per camera
    ``T_world_cam_features``. Odd LM-O dev scenes (chosen there; own candidates, then synthetic
    1 %/2 deg, 3 %/5 deg, 5 %/8 deg + gross): none 0.429, 0.898, 0.826, 0.622; leftovers 0.435,
    0.903, 0.829, 0.629; scene 0.439, 0.873, 0.803, 0.630. Held out (leftovers): even scenes 0.379
    -> 0.388 (synthetic unchanged: 0.887, 0.805, 0.641), YCB-V unchanged (depth: no leftover check).
    With cameras from the images alone for views the objects could not place, and the rotation
    guard at 30 deg (odd: 0.444): even scenes **0.399**.
``manifest.json``
    sha1 and size of the two files above (:mod:`cosy_cli.io.manifest`), checked by ``cosy evaluate``.

A group of one view (a scene of one image) has nothing to refine: its candidates pass through
unchanged as its predictions (the camera is the identity, the view being the world frame; the
dataset's pose with known cameras) and its scene.json entry says ``"single_view": true`` with a
``note``. The match folder is checked against its ``manifest.json`` first: a file changed or
truncated since ``cosy match`` wrote it is refused.
"""

from __future__ import annotations

import functools
import json
import time
from pathlib import Path

import numpy as np

from .. import __version__
from ..conf import as_bool, merge_conf
from ..errors import CosyError
from ..geometry.poses import invert
from ..io import atomic, bop, cache, manifest
from ..io.cache import file_sha1, reuse_existing_output
from ..io.dataset import BopDataset
from ..objects.symmetries import symmetry_set
from . import bundle_adjustment as ba
from .features import OPENCV_REFUSED
from . import placement

FORMAT_VERSION = 1
OUTPUT_FILES = ("scene.json", "predictions.csv")
MATCH_FORMAT = ("cosy-match", 1)

DEFAULT_CONF = {
    "iterations": ba.DEFAULT_ITERATIONS,  # LM iterations at most (paper: 100)
    "loss_threshold_px": ba.DEFAULT_LOSS_THRESHOLD_PX,  # truncation of the reprojection loss
    "n_points": ba.DEFAULT_N_POINTS,  # surface samples per label: the residuals use their bounding-box corners (as the original)
    "symmetry_steps": ba.DEFAULT_N_CONTINUOUS,  # continuous symmetries, steps per turn (paper: 64)
    # What predictions.csv holds (the paper's ``ba_output+all_cand``): "scene+candidates" = the
    # refined objects in every placed view, plus the single-view candidates that no refined
    # object explains, scored strictly below every refined prediction; "scene" = the refined
    # objects alone.
    "output": "scene+candidates",
    # a candidate is explained by a refined prediction of its label in its image whose centre
    # is closer than this fraction of the object's diameter (two solids cannot be that close)
    "explained_frac": 0.5,
    # an object of the refined scene needs candidates that agree with it (mean reprojection error
    # under half the loss threshold) in this many views, a view one such candidate; others are
    # dropped (0: off)
    "min_agreeing": 2,
    # with min_agreeing > 0: a view whose candidates of an object all disagree with the refined
    # object (centres farther than explained_frac x its diameter) keeps them instead of the
    # refined prediction
    "guard_views": True,
    "nms_mm": 0.0,  # merge objects of one label whose centres are closer (0: off)
    # Two solid objects cannot share the space: objects of any labels whose centres are closer
    # than this fraction of the smaller diameter are one physical object (typically a look-alike
    # whose label was swapped in several views); the weaker one is dropped (0: off).
    "exclusion_frac": 0.5,
    # candidates that matching left apart, paired again after the adjustment: two leftover
    # candidates of one label in two placed views whose triangulated object (cameras fixed)
    # both reproject within rematch_agree_frac x the loss threshold (mean error over the
    # points), and whose depths it confirms within rematch_depth_frac of theirs, become one more
    # object of the scene (rematch_leftovers)
    "rematch": True,
    "rematch_depth_frac": 0.15,
    "rematch_agree_frac": 1.0,  # x loss_threshold_px: the agreement test of rematched pairs
    # image check per view (multiview.image_check, beyond the paper): each refined object in each
    # placed view is scored against the view's RGB image with the single-view verification score,
    # as refined, contour-aligned from the refined pose (image_check_align) and as the view's own
    # candidates; the best is output (a candidate only when it scores more than image_check_margin
    # higher, and only when it disagrees with the refined pose: some model point farther apart than
    # image_check_min_gap x the diameter). "auto": on when the group's RGB images exist; "on":
    # required; "none": off.
    "image_check": "auto",
    "image_check_align": False,
    "image_check_margin": 0.02,
    "image_check_min_gap": 0.1,  # a candidate competes only when farther than this x the diameter from the refined pose
    "image_check_max_move": 0.1,  # > 0: the aligned pose may move at most this x the diameter from the refined one
    "image_check_crop": 64,  # px: side of the verification crops
    "image_check_w_box": 0.5,  # weight of the verification score's box term (the singleview default: 0.5)
    "image_check_box": "union",  # candidate | refined | union (of the two): the projected model box scored in
    # leftovers (image check on): single-view candidates that no refined object explains, in placed
    # views, that may be one object across views (same label; centres carried through the cameras
    # land within the projected size: image_check.LEFTOVER_MAX_OFFSET) are scored in all those
    # views; each takes the member pose with the best mean score when it beats its own by more
    # than image_check_margin
    "image_check_leftovers": True,
    # with a learned scorer (scorer_model, `cosy refine --scorer`): where its score replaces the
    # verification score: leftovers (the cross-view choice among leftovers), all (also the check of
    # the refined poses) or none
    "image_check_scorer": "leftovers",
    # beyond the paper (multiview.features): without known cameras, each view's rotation and
    # baseline direction relative to the gauge view from SIFT features and an essential matrix,
    # the scale from the objects seen in both (median over their candidates' centres), where the
    # pair has feature_min_inliers inliers and agrees with the object-level rotation within 30 deg
    # (views the objects could not place: twice the inliers, the scale from same-label candidates).
    # "leftovers": those cameras carry the leftover candidates of the image check across views
    # (the refined scene keeps the object-level cameras); "scene": the objects are also adjusted
    # again with those cameras held, and views no object placed are placed from their image pair
    # with the gauge view alone (twice the inliers; held too), their candidates joining the scene
    # through the rematch and the leftover check; "none": the objects alone (the paper). Needs the
    # RGB images.
    "feature_cameras": "leftovers",
    "feature_min_inliers": 30,
}

IMAGE_CHECK_MODES = ("auto", "on", "none")
IMAGE_CHECK_BOXES = ("candidate", "refined", "union")
SCORER_USES = ("leftovers", "all", "none")  # = image_check.SCORER_USES (not imported: it loads the verifier)


def resolve_conf(conf: dict | None = None, **overrides) -> dict:
    """The full configuration: defaults, then ``conf``, then overrides (None ignored), checked."""
    conf, overrides = _legacy_keys(conf), _legacy_keys(overrides)
    base = merge_conf({"default": DEFAULT_CONF}, conf or {}, overrides, default="default", what="refine")
    base["iterations"] = int(base["iterations"])
    base["min_agreeing"] = int(base["min_agreeing"])
    base["n_points"] = int(base["n_points"])
    base["symmetry_steps"] = int(base["symmetry_steps"])
    for k in ("rematch", "guard_views", "image_check_align", "image_check_leftovers"):
        base[k] = as_bool(base[k], k, "refine")
    if base["feature_cameras"] not in FEATURE_CAMERAS:
        raise CosyError(f"refine feature_cameras {base['feature_cameras']!r} is not one of {', '.join(FEATURE_CAMERAS)}")
    base["feature_min_inliers"] = int(base["feature_min_inliers"])
    base["image_check_margin"] = float(base["image_check_margin"])
    base["image_check_max_move"] = float(base["image_check_max_move"])
    base["image_check_min_gap"] = float(base["image_check_min_gap"])
    base["image_check_crop"] = int(base["image_check_crop"])
    base["image_check_w_box"] = float(base["image_check_w_box"])
    if base["image_check"] not in IMAGE_CHECK_MODES:
        raise CosyError(f"refine image_check {base['image_check']!r} is not one of {', '.join(IMAGE_CHECK_MODES)}")
    if base["image_check_scorer"] not in SCORER_USES:
        raise CosyError(f"refine image_check_scorer {base['image_check_scorer']!r} is not one of "
                        f"{', '.join(SCORER_USES)}")
    if base["image_check_box"] not in IMAGE_CHECK_BOXES:
        raise CosyError(f"refine image_check_box {base['image_check_box']!r} is not one of "
                        f"{', '.join(IMAGE_CHECK_BOXES)}")
    for k in ("loss_threshold_px", "nms_mm", "exclusion_frac", "explained_frac", "rematch_depth_frac",
              "rematch_agree_frac"):
        base[k] = float(base[k])
    if base["output"] not in OUTPUTS:
        raise CosyError(f"refine output {base['output']!r} is not one of {', '.join(OUTPUTS)}")
    if base["iterations"] < 1 or base["n_points"] < 3 or base["symmetry_steps"] < 1 or base["loss_threshold_px"] <= 0 \
            or base["nms_mm"] < 0 or base["exclusion_frac"] < 0 or base["explained_frac"] < 0 or base["min_agreeing"] < 0:
        raise CosyError("refine settings out of range (iterations >= 1, n_points >= 3, loss threshold > 0, "
                        "distances >= 0)")
    return base


OUTPUTS = ("scene+candidates", "scene")
FEATURE_CAMERAS = ("leftovers", "scene", "none")


WIDE_PARALLAX_PX = 5.0  # views with depth join the leftover check when an image pair shows this much parallax


def wide_views(stats: dict) -> bool:
    """Whether a group's views are distinct viewpoints: an image pair with the gauge view shows a
    parallax (:func:`~cosy_cli.multiview.features.parallax_px`) of at least ``WIDE_PARALLAX_PX``.
    The 10 YCB-V frames (one viewpoint in effect): 0.9-1.3 px; real LM-O dev pairs: 13-455 px."""
    views = stats.get("feature_cameras", {}).get("views", {})
    return any(v.get("parallax_px", 0.0) >= WIDE_PARALLAX_PX for v in views.values())


def leftover_check_on(conf: dict, checker) -> bool:
    """Whether a group with this image checker (None: no image check) gets the leftover check."""
    return checker is not None and conf["image_check_leftovers"] and conf["output"] == "scene+candidates"


def _legacy_keys(conf):
    """``keep_unmatched`` (before issue 16) is ``output``: true -> scene+candidates, false -> scene."""
    if not isinstance(conf, dict) or "keep_unmatched" not in conf:
        return conf
    conf = dict(conf)
    keep = conf.pop("keep_unmatched")
    if keep is not None:
        conf.setdefault("output", "scene+candidates" if as_bool(keep, "keep_unmatched", "refine") else "scene")
    for k in ("unmatched_score_factor", "unmatched_dedup_mm"):
        conf.pop(k, None)
    return conf


def refined_score(s):
    """Score of a refined prediction: 1 + the object's score clipped to [0, 1] (in [1, 2])."""
    return 1.0 + np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)


def fallback_score(s):
    """Score of a single-view candidate no refined object explains: half its score clipped to
    [0, 1] (in [0, 0.5]): strictly below every refined prediction, in the candidates' order."""
    return 0.5 * np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)


# --------------------------------------------------------------------------------------------
# inputs
# --------------------------------------------------------------------------------------------

def read_match_dir(matches: str | Path) -> tuple[dict, bop.PoseResults]:
    """groups.json (checked for format and version) and the candidates copy of a match output."""
    from . import match_stage

    matches = Path(matches)
    if not match_stage.is_complete(matches):
        missing = [f for f in match_stage.OUTPUT_FILES if not (matches / f).is_file()]
        raise CosyError(f"not a complete cosy match output (missing {', '.join(missing)})", path=matches)
    path = matches / "groups.json"
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        manifest.verify(path)  # a truncated groups.json: say so when match's manifest tells
        raise CosyError(f"cannot read ({e})", path=path) from None
    if not isinstance(doc, dict) or (doc.get("format"), doc.get("version")) != MATCH_FORMAT:
        raise CosyError(f"expected format {MATCH_FORMAT[0]!r} version {MATCH_FORMAT[1]}, got "
                        f"{doc.get('format')!r} version {doc.get('version')!r}" if isinstance(doc, dict) else
                        "expected a JSON object", path=path)
    # every file of the folder as cosy match wrote it (a folder without manifest.json, made by
    # hand or by an older cosy, is read as it is, through the validating readers)
    manifest.verify_folder(matches, match_stage.OUTPUT_FILES)
    for k in ("groups", "split", "dataset", "known_cameras"):
        if k not in doc:
            raise CosyError(f"missing key {k!r}", path=path)
    cands = bop.read_results(matches / doc.get("candidates_copy", "candidates.csv"))
    n = len(cands)
    for gi, g in enumerate(doc["groups"]):
        for key in ("scene_id", "group_id", "im_ids", "objects", "view_pairs", "discarded"):
            if key not in g:
                raise CosyError(f"missing key {key!r}", path=path, where=f"groups[{gi}]")
        ids = [c for o in g["objects"] for c in o["cand_ids"]] + list(g["discarded"])
        bad = [c for c in ids if not (0 <= int(c) < n)]
        if bad:
            raise CosyError(f"cand_id {bad[0]} is not a row of the candidates copy ({n} rows)", path=path,
                            where=f"groups[{gi}]")
    return doc, cands


def label_geometry(ds: BopDataset, obj_id: int, n_points: int, symmetry_steps: int) -> ba.LabelGeometry:
    """Residual points (the 8 corners of the bounding box of ``n_points`` surface samples, as the
    original; rods add the samples) and symmetries of one object label."""
    from .match_stage import model_points

    info = ds.models_info()[int(obj_id)]
    X = model_points(ds.model_path(obj_id), n_points)
    S = symmetry_set(info.symmetries_discrete, info.symmetries_continuous, symmetry_steps)
    axis = offset = None
    if len(info.symmetries_continuous) == 1:
        axis = info.symmetries_continuous[0]["axis"]
        offset = info.symmetries_continuous[0].get("offset", np.zeros(3))
    return ba.LabelGeometry.create(X, S, axis, offset, n_points=n_points)


# --------------------------------------------------------------------------------------------
# one group
# --------------------------------------------------------------------------------------------

def _nms(T_world_obj: np.ndarray, obj_ids: np.ndarray, n_cands: np.ndarray, scores: np.ndarray, d_mm: float,
         diameters: np.ndarray | None = None, exclusion_frac: float = 0.0):
    """Greedy suppression of objects that cannot both be real, strongest first (most candidates,
    then best score):

    * same label, centres closer than ``d_mm``: merged into the stronger (3D NMS);
    * any labels, centres closer than ``exclusion_frac`` x the smaller diameter (mm): two solids
      cannot overlap that much, the weaker is dropped (into = -1).

    Returns (keep mask (N,), into (N,): the kept object each one was merged into, -1 if dropped)."""
    N = len(obj_ids)
    order = np.lexsort((np.arange(N), -scores, -n_cands))
    keep = np.zeros(N, dtype=bool)
    into = np.arange(N)
    c = T_world_obj[:, :3, 3]
    dist = np.linalg.norm(c[:, None] - c[None], axis=-1)
    same = obj_ids[:, None] == obj_ids[None]
    merge = same & (dist < d_mm)
    exclude = np.zeros_like(merge)
    if diameters is not None and exclusion_frac > 0:
        exclude = dist < exclusion_frac * np.minimum(diameters[:, None], diameters[None])
    for i in order:  # a loop over objects (tens), not points
        kept = np.flatnonzero(keep)
        m = kept[merge[i, kept]]
        if len(m):
            into[i] = m[np.argmin(dist[i, m])]
            continue
        if exclude[i, kept].any():
            into[i] = -1
            continue
        keep[i] = True
    return keep, into


def rematch_leftovers(Twc: np.ndarray, K: np.ndarray, left_view: np.ndarray, left_label: np.ndarray,
                      T_cam_left: np.ndarray, geo: list, conf: dict, kept_world: np.ndarray | None = None,
                      kept_diam: np.ndarray | None = None, diam_of_label: np.ndarray | None = None):
    """Objects seen in two views that matching left apart, found again with the adjusted cameras.

    Candidates that cosy match could not associate (typically: their depths disagree by more
    than the inlier threshold, which the refined cameras do not change) are paired again in 2D,
    the paper's reprojection loss being the test: for every pair of leftover candidates of one
    label in two placed views, the object is triangulated by the bundle adjustment with the
    cameras held fixed (``Twc`` (V, 4, 4), ``K`` (V, 3, 3); one batched problem for all pairs);
    a pair is accepted when both candidates agree with it (mean reprojection error under
    ``rematch_agree_frac`` x the loss threshold: 25 px by default, twice the ``min_agreeing``
    test, for the rotation errors of real candidates) and the object's depth in each view is within
    ``rematch_depth_frac`` of the candidate's (what a single-view estimate is expected to get
    right). A closed-form test first drops pairs whose viewing rays pass too far apart to pass.
    Pairs are taken greedily by cost, each candidate once; an accepted object must not
    overlap an object of the scene (``kept_world`` (N, 4, 4), ``kept_diam`` (N,): centres closer
    than ``exclusion_frac`` x the smaller diameter) or another accepted one. Leftover candidates of
    further views that agree with an accepted object join it (one more fixed-camera adjustment).

    left_view (L,) view indices, left_label (L,) indices into ``geo``, T_cam_left (L, 4, 4) mm;
    ``diam_of_label`` (n_labels,) mm. Returns a list of (member indices into the leftovers,
    T_world_obj (4, 4), mean reprojection error px).
    """
    L = len(left_view)
    tau = conf["loss_threshold_px"]
    if L < 2:
        return []
    i, j = np.triu_indices(L, 1)
    ok = (left_label[i] == left_label[j]) & (left_view[i] != left_view[j])
    i, j = i[ok], j[ok]
    agree = conf["rematch_agree_frac"] * tau
    if len(i):
        # prefilter (closed form): the rays through the two candidates' origins must pass closer
        # than what two reprojection errors under ``agree`` px allow at their depths (x 1.5)
        C = Twc[:, :3, 3]
        d = (Twc[left_view, :3, :3] @ T_cam_left[:, :3, 3, None])[..., 0]
        z = np.linalg.norm(d, axis=1)
        d = d / np.maximum(z, 1e-9)[:, None]
        f = np.sqrt(K[left_view, 0, 0] * K[left_view, 1, 1])
        n = np.cross(d[i], d[j])
        nn = np.linalg.norm(n, axis=1)
        w = C[left_view[j]] - C[left_view[i]]
        gap = np.where(nn > 1e-9, np.abs(np.einsum("ij,ij->i", w, n)) / np.maximum(nn, 1e-9),
                       np.linalg.norm(np.cross(w, d[i]), axis=1))
        near = gap <= 1.5 * agree * (z[i] / f[i] + z[j] / f[j])
        i, j = i[near], j[near]
    if not len(i):
        return []
    H = len(i)
    cv = np.r_[left_view[i], left_view[j]]
    co = np.r_[np.arange(H), np.arange(H)]
    Tc = np.concatenate([T_cam_left[i], T_cam_left[j]])
    lab = left_label[i]
    Two, sym, _ = ba.initialise_objects(Twc, cv, co, Tc, lab, geo, None)
    S0 = np.stack([geo[lab[o]].symmetries[k] for o, k in zip(co, sym)])
    res = ba.bundle_adjust(Twc, Two, cv, co, Tc, K, lab, geo, iterations=min(conf["iterations"], 20),
                           loss_threshold_px=tau, fixed_views="all", symmetries=S0)
    err = np.nan_to_num(res.cand_error_px, nan=np.inf).reshape(2, H)
    T_cam = invert(Twc[cv]) @ res.T_world_obj[co]
    z_est = np.linalg.norm(T_cam[:, :3, 3], axis=1)
    z_cand = np.linalg.norm(Tc[:, :3, 3], axis=1)
    depth_ok = (np.abs(z_est - z_cand) <= conf["rematch_depth_frac"] * z_cand).reshape(2, H).all(0)
    good = (err < agree).all(0) & depth_ok
    cost = err.mean(0)
    used = np.zeros(L, dtype=bool)
    centres = [] if kept_world is None else list(kept_world[:, :3, 3])
    diams = [] if kept_diam is None else list(kept_diam)
    out = []
    for h in np.flatnonzero(good)[np.argsort(cost[good], kind="stable")]:  # tens of pairs at most
        if used[i[h]] or used[j[h]]:
            continue
        c, d = res.T_world_obj[h, :3, 3], diam_of_label[lab[h]]
        if centres and (np.linalg.norm(np.asarray(centres) - c, axis=1)
                        < conf["exclusion_frac"] * np.minimum(np.asarray(diams), d)).any():
            continue
        used[i[h]] = used[j[h]] = True
        centres.append(c)
        diams.append(d)
        out.append(([int(i[h]), int(j[h])], res.T_world_obj[h], float(cost[h])))
    if not out:
        return out
    # leftovers of other views that agree with an accepted object join it
    rest = np.flatnonzero(~used)
    if len(rest):
        obj_lab = np.array([left_label[m[0]] for m, _, _ in out])
        obj_views = [set(left_view[m].tolist()) for m, _, _ in out]
        oi, ri = np.meshgrid(np.arange(len(out)), rest, indexing="ij")
        oi, ri = oi.ravel(), ri.ravel()
        sel = np.array([obj_lab[o] == left_label[r] and left_view[r] not in obj_views[o] for o, r in zip(oi, ri)],
                       dtype=bool)
        oi, ri = oi[sel], ri[sel]
        if len(oi):
            Tw = np.stack([T for _, T, _ in out])
            r2 = ba.bundle_adjust(Twc, Tw[oi], left_view[ri], np.arange(len(oi)), T_cam_left[ri], K, obj_lab[oi], geo,
                                  iterations=1, loss_threshold_px=tau, fixed_views="all")
            e0 = np.nan_to_num(r2.initial_cand_error_px, nan=np.inf)
            for k in np.argsort(e0, kind="stable"):
                o, r = oi[k], ri[k]
                if e0[k] < agree and not used[r] and left_view[r] not in obj_views[o]:
                    used[r] = True
                    obj_views[o].add(int(left_view[r]))
                    out[o][0].append(int(r))
            grown = [k for k, (m, _, _) in enumerate(out) if len(m) > 2]
            pairs = {k: out[k][0][:2] for k in grown}
            if grown:
                mem = [m for k in grown for m in out[k][0]]
                mo = np.concatenate([[n] * len(out[k][0]) for n, k in enumerate(grown)])
                r3 = ba.bundle_adjust(Twc, np.stack([out[k][1] for k in grown]), left_view[mem], mo, T_cam_left[mem], K,
                                      obj_lab[grown], geo, iterations=conf["iterations"], loss_threshold_px=tau,
                                      fixed_views="all")
                e3 = np.nan_to_num(r3.cand_error_px, nan=np.inf)
                for n, k in enumerate(grown):
                    if (e3[mo == n] < agree).all():
                        out[k] = (out[k][0], r3.T_world_obj[n], float(e3[mo == n].mean()))
                    else:  # the joint object does not fit them all: the pair alone
                        out[k] = (pairs[k], out[k][1], out[k][2])
    return out


SINGLE_VIEW_NOTE = "single view: candidates passed through"


def single_view_group(g: dict, cands: bop.PoseResults, T_world_cam: np.ndarray, t0: float) -> dict:
    """A group of one view: nothing to refine. Each object's best candidate is its prediction,
    unchanged (T_cam_obj and score of the candidate); the camera is ``T_world_cam`` (the
    identity: the view is the world frame, or the dataset's pose with known cameras). Same
    entry as :func:`refine_group`, with ``"single_view": true`` and a ``note``."""
    s, v = int(g["scene_id"]), int(g["im_ids"][0])
    c_score = cands.column("score")
    objects_out, pred, unused = [], [], [int(c) for c in g["discarded"]]
    for o in g["objects"]:
        ids = [int(c) for c in o["cand_ids"]]
        if not ids:
            continue
        best = ids[int(np.argmax(c_score[ids]))]
        unused += [c for c in ids if c != best]
        T_cam_obj = cands.T_cam_obj[best]
        objects_out.append({"object_id": int(o["object_id"]), "obj_id": int(o["obj_id"]), "score": float(c_score[best]),
                            "n_candidates": 1, "cand_ids": [best], "reprojection_error_px": None,
                            "T_world_obj": _mat(T_world_cam @ T_cam_obj)})
        pred.append((s, v, int(o["obj_id"]), float(c_score[best]), T_cam_obj))
    dt = time.perf_counter() - t0
    stats = {"iterations": 0, "converged": True, "initial_cost_px2": 0.0, "final_cost_px2": 0.0,
             "n_candidates": len(objects_out), "n_unused_candidates": len(unused), "time_s": round(dt, 6)}
    return {
        "scene_id": s, "group_id": int(g["group_id"]), "gauge_im_id": v,
        "cameras": [{"im_id": v, "T_world_cam": _mat(T_world_cam), "placed_by": "single view"}], "unplaced_im_ids": [],
        "placed_by": {str(v): "single view"}, "objects": objects_out,
        "stats": stats, "single_view": True, "note": SINGLE_VIEW_NOTE,
        "_pred": pred, "_unused": sorted(set(unused)), "_time": dt,
    }


def refine_group(g: dict, cands: bop.PoseResults, ds: BopDataset, geometry: dict, conf: dict,
                 known_cameras: bool, checker=None) -> dict:
    """Refine one group of groups.json. ``geometry``: {obj_id: LabelGeometry}. Returns the
    group's scene.json entry plus private keys: "_pred" (rows of predictions) and "_unused"
    (cand_ids not used in the scene). A group of one view: :func:`single_view_group`.
    ``checker``: an :class:`~cosy_cli.multiview.image_check.ImageChecker` (None: no image check)."""
    t0 = time.perf_counter()
    s = int(g["scene_id"])
    im_ids = [int(i) for i in g["im_ids"]]
    cams = ds.scene_camera(s)
    missing = [i for i in im_ids if i not in cams]
    if missing:
        raise CosyError(f"image {missing[0]} of scene {s} (group {g['group_id']} in groups.json) is not in "
                        "the dataset's scene_camera.json", path=ds.scene_file(s, "scene_camera"))
    if len(im_ids) == 1:
        T_world_cam = np.eye(4)
        if known_cameras:
            if cams[im_ids[0]].T_cam_world is None:
                raise CosyError("match ran with --known-cameras but the camera pose (cam_R_w2c, cam_t_w2c) is missing",
                                path=ds.scene_file(s, "scene_camera"), where=f"image {im_ids[0]}")
            T_world_cam = invert(cams[im_ids[0]].T_cam_world)
        return single_view_group(g, cands, T_world_cam, t0)
    if known_cameras:
        no_pose = [i for i in im_ids if cams[i].T_cam_world is None]
        if no_pose:
            raise CosyError("match ran with --known-cameras but the camera pose (cam_R_w2c, cam_t_w2c) is missing",
                            path=ds.scene_file(s, "scene_camera"), where=f"image {no_pose[0]}")
        placed = {i: invert(cams[i].T_cam_world) for i in im_ids}
        placed_by = {i: "known" for i in im_ids}
        unplaced: list[int] = []
        gauge = None
    else:
        c_obj = cands.column("obj_id")
        links = [placement.Link(int(p["im_id_a"]), int(p["im_id_b"]), np.asarray(p["T_cam_a_cam_b"], dtype=np.float64),
                                int(p["n_inliers"]), p.get("link", "ransac"),
                                [int(c_obj[int(e[0])]) for e in p.get("associations", [])])
                 for p in g["view_pairs"] if p.get("linked")]
        placed, placed_by, _, gauge = placement.place_cameras(im_ids, links)
        unplaced = [v for v in im_ids if v not in placed]
    # feature cameras: for the scene ("scene"), or for the leftover check ("leftovers"; with depth
    # they also tell whether the views are distinct viewpoints: wide_views)
    wanted = not known_cameras and (conf["feature_cameras"] == "scene" or (
        conf["feature_cameras"] == "leftovers" and leftover_check_on(conf, checker)))
    from .image_check import images_available

    pending: list = []  # feature cameras for the leftover check, computed only if it needs them
    rgb = functools.cache(lambda v: ds.read_rgb(s, v))  # the group's images, each read once
    features = functools.cache(lambda: _feature_cache(conf))  # SIFT per image, computed once (made when needed)
    tab = cands
    c_im = tab.column("im_id")
    c_score = tab.column("score")
    stats: dict = {}
    all_cands = sorted({int(c) for o in g["objects"] for c in o["cand_ids"]} | {int(c) for c in g["discarded"]})
    image_placed: set = set()  # views placed by their image pair with the gauge view alone ("scene")
    if (wanted and conf["feature_cameras"] == "scene" and unplaced and gauge in placed
            and images_available(ds, s, [gauge] + unplaced)):
        # the views no object placed, from the images alone: their cameras are held in the
        # adjustment, and their candidates join the scene through the rematch below
        got = _image_only_cameras(rgb, features(), gauge, placed[gauge], unplaced, cams, cands, all_cands, stats)
        for v, T in got.items():
            placed[v] = T
            placed_by[v] = f"image features alone ({stats['feature_cameras']['views'][str(v)]['inliers']} inliers)"
            image_placed.add(v)
        unplaced = [v for v in unplaced if v not in image_placed]
    views = list(placed)
    vidx = {v: k for k, v in enumerate(views)}
    use_features = wanted and len(views) > 1 and images_available(ds, s, views)

    # candidates of objects, in placed views
    cand_ids, cand_obj, objs = [], [], []
    unused = [int(c) for c in g["discarded"]]
    for o in g["objects"]:
        # candidates of a look-alike label whose model is not in the object's frame only voted for
        # its label (cosy match's label groups): not a measurement of the object's pose
        vote_only = {int(c) for c in o.get("vote_only_cand_ids", [])}
        members = [int(c) for c in o["cand_ids"] if int(c_im[int(c)]) in vidx and int(c) not in vote_only]
        unused += [int(c) for c in o["cand_ids"] if int(c_im[int(c)]) not in vidx or int(c) in vote_only]
        if not members:
            continue
        cand_obj += [len(objs)] * len(members)
        cand_ids += members
        objs.append(o)
    cand_ids = np.array(cand_ids, dtype=np.int64)
    cand_obj = np.array(cand_obj, dtype=np.int64)
    Twc = np.stack([placed[v] for v in views])
    K = np.stack([cams[v].K for v in views])
    stats.update({"iterations": 0, "converged": True, "initial_cost_px2": 0.0, "final_cost_px2": 0.0,
                  "n_candidates": int(len(cand_ids)), "n_unused_candidates": len(unused)})
    held = sorted({0} | {vidx[v] for v in image_placed})  # the gauge, and the views only the images placed
    objects_out = []
    T_world_obj = np.zeros((0, 4, 4))
    keep = np.zeros(0, dtype=bool)
    if len(objs):
        labels = sorted({int(o["obj_id"]) for o in objs})
        lab_index = {o: k for k, o in enumerate(labels)}
        geo = [geometry[o] for o in labels]
        obj_label = np.array([lab_index[int(o["obj_id"])] for o in objs])
        cv = np.array([vidx[int(c_im[c])] for c in cand_ids])
        T_cam_cand = cands.T_cam_obj[cand_ids]
        Two, sym, _ = ba.initialise_objects(Twc, cv, cand_obj, T_cam_cand, obj_label, geo, c_score[cand_ids])
        S0 = np.stack([geo[obj_label[o]].symmetries[k] for o, k in zip(cand_obj, sym)])
        res = ba.bundle_adjust(Twc, Two, cv, cand_obj, T_cam_cand, K, obj_label, geo,
                               iterations=conf["iterations"], loss_threshold_px=conf["loss_threshold_px"],
                               fixed_views="all" if known_cameras else held, symmetries=S0)
        if use_features and gauge in vidx and len(views) > 1:
            # the cameras' rotations and baseline directions from the images (multiview.features),
            # the scale from the objects; then the objects again with those cameras held
            # ("scene"); for the leftover check alone ("leftovers") only when it needs them
            # (see _check_leftovers), the objects' cameras as they are now
            args = (res, rgb, list(views), dict(vidx), gauge, cams, cv, cand_obj, T_cam_cand, K, obj_label, geo,
                    c_score[cand_ids], conf, stats, placed_by, image_placed)
            run_features = functools.partial(lambda a: _feature_cameras(a[0], a[1], features(), *a[2:]), args)
            if conf["feature_cameras"] == "leftovers":
                pending.append(run_features)
            else:
                res = run_features()
        Twc, T_world_obj = res.T_world_cam, res.T_world_obj
        n_c = np.bincount(cand_obj, minlength=len(objs))
        score = np.full(len(objs), -np.inf)
        np.maximum.at(score, cand_obj, c_score[cand_ids])
        err = np.bincount(cand_obj, weights=np.nan_to_num(res.cand_error_px), minlength=len(objs)) / n_c
        o_ids = np.array([int(o["obj_id"]) for o in objs])
        diam_of = {int(o): ds.models_info()[int(o)].diameter for o in o_ids}
        keep, into = _nms(T_world_obj, o_ids, n_c, score, conf["nms_mm"],
                          np.array([ds.models_info()[int(o)].diameter for o in o_ids]), conf["exclusion_frac"])
        # support: a candidate agrees with the refined scene when its mean reprojection error is
        # under half the loss threshold; an object needs agreeing candidates in min_agreeing views
        # (else its candidates were a consistent mistake, or the cameras are wrong: it is dropped
        # and its candidates stay single-view estimates), a view at least one (else it gets no
        # refined predictions: its camera is not supported)
        agree = np.nan_to_num(res.cand_error_px, nan=np.inf) < 0.5 * conf["loss_threshold_px"]
        n_unsupported, n_merged, n_overlap = 0, int((~keep & (into >= 0)).sum()), int((into < 0).sum())
        for k in np.flatnonzero(keep):
            mk = (into == k)[cand_obj]
            if len(np.unique(cv[mk & agree])) < conf["min_agreeing"]:
                keep[k] = False
                into[into == k] = -1
                n_unsupported += 1
        view_ok = np.zeros(len(views), dtype=bool)
        view_ok[cv[agree & keep[cand_obj]]] = True
        for v in image_placed:  # placed by the images, not by the objects: no candidate needs to agree
            view_ok[vidx[v]] = True
        T_cam_world = np.linalg.inv(Twc)  # (V, 4, 4): the views' extrinsics, for the view guard
        for k, o in enumerate(objs):
            if not keep[k]:
                continue
            merged = np.flatnonzero(into == k)
            in_k = (into == k)[cand_obj]  # the candidates of this object and of those merged into it
            ids = cand_ids[in_k]
            entry = {"object_id": int(o["object_id"]), "obj_id": int(o["obj_id"]), "score": float(score[merged].max()),
                     "n_candidates": int(len(ids)), "cand_ids": [int(c) for c in ids],
                     "reprojection_error_px": round(float(err[k]), 4),
                     "T_world_obj": _mat(T_world_obj[k])}
            if len(merged) > 1:
                entry["merged_object_ids"] = [int(objs[m]["object_id"]) for m in merged if m != k]
            if conf["min_agreeing"] > 0 and conf["guard_views"]:
                # a view whose own candidates of this object all lie farther than explained_frac x
                # the diameter from the refined object keeps them: the scene does not overrule what
                # a view saw (a consistent mistake of the other views cannot replace a right pose)
                mk = in_k
                c_cam = T_cam_cand[mk, :3, 3]
                o_cam = np.einsum("vij,j->vi", T_cam_world, T_world_obj[k][:, 3])[cv[mk], :3]
                near = np.linalg.norm(c_cam - o_cam, axis=1) < conf["explained_frac"] * diam_of[int(o["obj_id"])]
                seen, explained = set(cv[mk].tolist()), set(cv[mk][near].tolist())
                entry["_overruled_im_ids"] = sorted(int(views[x]) for x in seen - explained)
            objects_out.append(entry)
        stats.update({
            "iterations": int(res.iterations), "converged": bool(res.converged),
            "initial_cost_px2": float(res.initial_cost), "final_cost_px2": float(res.final_cost),
            "reprojection_error_px": {str(v): {"initial": _num(res.initial_view_error_px[k]),
                                               "final": _num(res.view_error_px[k])} for k, v in enumerate(views)},
            "n_merged_objects": n_merged,
            "n_dropped_overlapping_objects": n_overlap,
            "n_dropped_unsupported_objects": n_unsupported,
        })
        if not known_cameras and conf["min_agreeing"] > 0:
            for k, v in enumerate(views):
                if not view_ok[k]:
                    placed_by[v] = "unplaced (its candidates disagree with the refined scene)"
            unplaced = [v for v in im_ids if v not in placed or not view_ok[vidx[v]]]
            Twc = Twc[view_ok]
            K = K[view_ok]
            views = [v for k, v in enumerate(views) if view_ok[k]]
        T_world_obj = T_world_obj[keep]
    if len(objs) or image_placed:
        n_rematched = 0
        if conf["rematch"] and len(views) > 1:
            # candidates matching left apart, paired again in 2D with the adjusted cameras
            vi = {v: k for k, v in enumerate(views)}
            left = np.array([c for c in g["discarded"] if int(c_im[int(c)]) in vi], dtype=np.int64)
            if len(left) > 1:
                c_obj_all = tab.column("obj_id")
                l_labels = sorted({int(c_obj_all[c]) for c in left})
                l_geo = [geometry[o] for o in l_labels]
                l_index = {o: k for k, o in enumerate(l_labels)}
                infos = ds.models_info()
                kept_o = [o for k, o in enumerate(objs) if keep[k]]
                new = rematch_leftovers(
                    Twc, K, np.array([vi[int(c_im[c])] for c in left]), np.array([l_index[int(c_obj_all[c])] for c in left]),
                    cands.T_cam_obj[left], l_geo, conf, T_world_obj,
                    np.array([infos[int(o["obj_id"])].diameter for o in kept_o]),
                    np.array([infos[o].diameter for o in l_labels]))
                next_id = max([int(o["object_id"]) for o in g["objects"]] + [-1]) + 1
                add = []
                for members, T, e in new:
                    ids = left[members]
                    objects_out.append({"object_id": next_id, "obj_id": int(c_obj_all[ids[0]]),
                                        "score": float(c_score[ids].max()), "n_candidates": int(len(ids)),
                                        "cand_ids": [int(c) for c in ids], "reprojection_error_px": round(e, 4),
                                        "T_world_obj": _mat(T), "rematched": True})
                    next_id += 1
                    add.append(T)
                    unused = [c for c in unused if c not in set(ids.tolist())]
                n_rematched = len(add)
                if add:
                    T_world_obj = np.concatenate([T_world_obj, np.stack(add)])
        stats["n_rematched_objects"] = n_rematched
    never = [v for v in im_ids if v not in placed]
    if (wanted and conf["feature_cameras"] == "leftovers" and gauge in placed and never
            and images_available(ds, s, [gauge] + never)):
        # views the objects could not place at all: cameras from the images alone, for the leftovers
        args = (rgb, gauge, placed[gauge], never, cams, cands, all_cands, stats)
        pending.append(functools.partial(lambda a: _unplaced_feature_cameras(a[0], features(), *a[1:]), args))
    feature_cams = stats.pop("_feature_T_world_cam", {})  # the leftovers' cameras (none yet: see pending)
    dt = time.perf_counter() - t0
    stats["time_s"] = round(dt, 6)
    # predictions: every kept object in every placed camera
    pred = []
    if len(objects_out):
        T_cam_obj = ba.predictions_from_scene(Twc, T_world_obj)  # (V, N', 4, 4)
        pred_obj = []
        for k, v in enumerate(views):
            for j, o in enumerate(objects_out):
                if v not in o.get("_overruled_im_ids", ()):
                    pred.append((s, v, o["obj_id"], o["score"], T_cam_obj[k, j]))
                    pred_obj.append(j)
        if checker is not None and pred:
            pred = _image_check(checker, rgb, pred, pred_obj, objects_out, cands, cams, stats)
            dt = time.perf_counter() - t0
            stats["time_s"] = round(dt, 6)
    for o in objects_out:  # scene.json says where the object's candidates stay instead
        keep_views = o.pop("_overruled_im_ids", [])
        if keep_views:
            o["views_keeping_their_candidates"] = keep_views
    return {
        "scene_id": s, "group_id": int(g["group_id"]), "gauge_im_id": gauge,
        "cameras": [{"im_id": int(v), "T_world_cam": _mat(Twc[k]), "placed_by": placed_by[v],
                     **({"T_world_cam_features": _mat(feature_cams[v])} if v in feature_cams else {})}
                    for k, v in enumerate(views)],
        "unplaced_im_ids": [int(v) for v in unplaced], "placed_by": {str(v): placed_by[v] for v in im_ids},
        **({"feature_only_cameras": [{"im_id": int(v), "T_world_cam_features": _mat(feature_cams[v])}
                                     for v in sorted(feature_cams) if v not in views]}
           if any(v not in views for v in feature_cams) else {}),
        "objects": objects_out, "stats": stats,
        "_pred": pred, "_unused": sorted(set(unused)), "_time": dt, "_feature_cams": feature_cams,
        "_all_cands": all_cands, "_rgb": rgb, "_features_pending": pending,
    }


def _image_check(checker, rgb, pred: list, pred_obj: list, objects_out: list, cands: bop.PoseResults,
                 cams: dict, stats: dict) -> list:
    """The image check of a group's refined predictions (:mod:`~cosy_cli.multiview.image_check`):
    each row's pose replaced by the best-scoring of refined / aligned / the view's own candidates;
    each object's entry records per view which was kept (``"image_check": {im_id: choice}``)."""
    from . import image_check as ic

    t0 = time.perf_counter()
    c_im = cands.column("im_id")
    items = []
    for (_, v, o, _, T), j in zip(pred, pred_obj):
        ids = [int(c) for c in objects_out[j]["cand_ids"] if int(c_im[int(c)]) == int(v)]
        items.append(ic.ViewItem(int(v), int(o), T, cands.T_cam_obj[ids] if ids else np.zeros((0, 4, 4))))
    views = sorted({int(x[1]) for x in pred})
    res = checker.check(items, ic.LazyImages(views, rgb), {v: cams[v].K for v in views})
    out = []
    counts = dict.fromkeys(ic.CHOICES, 0)
    for q, ((sc_id, v, o, sc, _), j) in enumerate(zip(pred, pred_obj)):
        out.append((sc_id, v, o, sc, res.T[q]))
        objects_out[j].setdefault("image_check", {})[str(int(v))] = res.choice[q]
        counts[res.choice[q]] += 1
    stats["image_check"] = {**counts, "time_s": round(time.perf_counter() - t0, 6)}
    return out


def _feature_cache(conf: dict):
    """One :class:`~cosy_cli.multiview.features.FeatureCache` per group, with the refine settings."""
    from . import features as ft

    m = int(conf["feature_min_inliers"])
    return ft.FeatureCache(ft.FeatureConf(min_inliers=m, min_inliers_alone=2 * m))


def _feature_cameras(res, rgb, cache, views: list, vidx: dict, gauge: int, cams: dict, cv, cand_obj,
                     T_cam_cand, K, obj_label, geo, cand_score, conf: dict, stats: dict, placed_by: dict,
                     image_placed=()):
    """Replace the object-level cameras of the views whose image pair with the gauge view is
    trusted (:func:`~cosy_cli.multiview.features.feature_camera`) and adjust the objects again
    with those cameras held fixed. Returns the new bundle result (``res`` when no view changed);
    stats["feature_cameras"] records per view the inliers and whether it was used. The views of
    ``image_placed`` already have cameras from their images alone: held as they are."""
    from . import features as ft

    t0 = time.perf_counter()
    Twc = res.T_world_cam.copy()
    g = vidx[gauge]
    fixed = [g] + [vidx[v] for v in image_placed]
    info = dict(stats.get("feature_cameras", {}).get("views", {}))
    for v in views:
        if v == gauge or v in image_placed:
            continue
        pair = ft.relative_pose(cache, gauge, rgb(gauge), cams[gauge].K, v, rgb(v), cams[v].K)
        # the scale from the objects seen in both views: their candidates' centres
        k = vidx[v]
        both = [o for o in np.unique(cand_obj) if (g in cv[cand_obj == o]) and (k in cv[cand_obj == o])]
        c_ref = np.array([T_cam_cand[np.flatnonzero((cand_obj == o) & (cv == g))[0], :3, 3] for o in both]).reshape(-1, 3)
        c_cam = np.array([T_cam_cand[np.flatnonzero((cand_obj == o) & (cv == k))[0], :3, 3] for o in both]).reshape(-1, 3)
        T = ft.feature_camera(Twc[g], Twc[k], pair, cache.conf, c_ref, c_cam)
        info[str(v)] = _pair_record(pair, T is not None)
        if T is not None:
            Twc[vidx[v]] = T
            fixed.append(vidx[v])
            if conf["feature_cameras"] == "scene":
                placed_by[v] = f"{placed_by[v]} + image features ({pair.n_inliers} inliers)"
    stats["feature_cameras"] = {"views": info, "time_s": round(stats.get("feature_cameras", {}).get("time_s", 0.0)
                                                            + time.perf_counter() - t0, 6)}
    if conf["feature_cameras"] == "leftovers":
        stats["_feature_T_world_cam"] = {v: Twc[vidx[v]] for v in views if v == gauge or info[str(v)]["used"]}
        return res
    if len(fixed) == 1:
        return res
    Two, sym, _ = ba.initialise_objects(Twc, cv, cand_obj, T_cam_cand, obj_label, geo, cand_score)
    S0 = np.stack([geo[obj_label[o]].symmetries[k] for o, k in zip(cand_obj, sym)])
    return ba.bundle_adjust(Twc, Two, cv, cand_obj, T_cam_cand, K, obj_label, geo, iterations=conf["iterations"],
                            loss_threshold_px=conf["loss_threshold_px"], fixed_views=sorted(fixed), symmetries=S0)


def _pair_record(pair, used: bool) -> dict:
    """scene.json's record of a view's image pair with the gauge view (``stats.feature_cameras``)."""
    rec = {"inliers": pair.n_inliers, "used": used, "parallax_px": round(pair.parallax_px, 2)}
    if pair.failure:
        rec["no_pose"] = pair.failure  # why the images gave no relative pose (too few matches, OpenCV refused)
    return rec


def _image_only_cameras(rgb, cache, gauge: int, T_world_gauge: np.ndarray, never: list, cams: dict,
                        cands: bop.PoseResults, all_cands: list, stats: dict) -> dict:
    """Cameras {im_id: T_world_cam} of the group's views that the objects could not place, from
    their image pair with the gauge view (:func:`~cosy_cli.multiview.features.camera_without_objects`;
    the scale from the candidates of labels seen once in each of the two views); every pair tried is
    recorded in stats["feature_cameras"]["views"]."""
    from . import features as ft

    t0 = time.perf_counter()
    tab = cands
    c_im, c_obj = tab.column("im_id"), tab.column("obj_id")
    ids = np.array(all_cands, dtype=np.int64)

    def once(v):  # label -> the candidate of a label seen once in view v
        labs, n = np.unique(c_obj[ids][c_im[ids] == v], return_counts=True)
        return {int(o): int(ids[(c_im[ids] == v) & (c_obj[ids] == o)][0]) for o in labs[n == 1]}

    ref = once(gauge)
    fc = stats.setdefault("feature_cameras", {"views": {}, "time_s": 0.0})
    out = {}
    for v in never:
        here = once(v)
        both = sorted(set(ref) & set(here))
        c_ref = np.array([cands.T_cam_obj[ref[o]][:3, 3] for o in both]).reshape(-1, 3)
        c_cam = np.array([cands.T_cam_obj[here[o]][:3, 3] for o in both]).reshape(-1, 3)
        pair = ft.relative_pose(cache, gauge, rgb(gauge), cams[gauge].K, v, rgb(v), cams[v].K)
        T = ft.camera_without_objects(T_world_gauge, pair, cache.conf, c_ref, c_cam)
        fc["views"][str(v)] = {**_pair_record(pair, T is not None), "unplaced_by_the_objects": True}
        if T is not None:
            out[v] = T
    fc["time_s"] = round(fc["time_s"] + time.perf_counter() - t0, 6)
    return out


def _unplaced_feature_cameras(rgb, cache, gauge: int, T_world_gauge: np.ndarray, never: list, cams: dict,
                              cands: bop.PoseResults, all_cands: list, stats: dict) -> None:
    """:func:`_image_only_cameras` for the leftover check only: added to stats["_feature_T_world_cam"]."""
    got = _image_only_cameras(rgb, cache, gauge, T_world_gauge, never, cams, cands, all_cands, stats)
    out = stats.setdefault("_feature_T_world_cam", {})
    for v, T in got.items():
        out[v] = T
        out.setdefault(gauge, T_world_gauge)


def group_predictions(r: dict, cands: bop.PoseResults, diameters: dict, conf: dict, score_min: float = -np.inf
                      ) -> tuple[list, int]:
    """Prediction rows (scene_id, im_id, obj_id, score, T_cam_obj) of one refined group and how
    many of them are single-view fallbacks.

    A single-view group passes its candidates through unchanged. Otherwise: every refined object
    in every placed view, scored :func:`refined_score`; with ``output`` "scene+candidates" also
    every candidate of the group (scoring at least match's ``score_min``) that no refined
    prediction of its label in its image explains (centres closer than ``explained_frac`` x the
    diameter), scored :func:`fallback_score` -- strictly lower, so that a BOP top-k per image and
    object takes a single-view estimate only where the scene has none (views that could not be
    placed keep all their candidates).
    """
    if r.get("single_view"):
        return [tuple(x) for x in r["_pred"]], 0
    rows = [(s, v, o, float(refined_score(sc)), T) for (s, v, o, sc, T) in r["_pred"]]
    if conf["output"] != "scene+candidates":
        return rows, 0
    fb = fallback_candidates(r, cands, diameters, conf, score_min)
    repl = r.get("_leftover_T", {})
    rows += [(int(r["scene_id"]), v, o, float(fallback_score(sc)), repl.get(c, cands.T_cam_obj[c])) for c, v, o, sc in fb]
    return rows, len(fb)


def fallback_candidates(r: dict, cands: bop.PoseResults, diameters: dict, conf: dict,
                        score_min: float = -np.inf) -> list:
    """The group's candidates that no refined prediction of their label in their image explains
    (centres closer than ``explained_frac`` x the diameter), as (cand_id, im_id, obj_id, score)."""
    tab = cands
    ids = np.array(sorted(r["_all_cands"]), dtype=np.int64)
    if not len(ids):
        return []
    ims, objs, scores = tab.column("im_id")[ids], tab.column("obj_id")[ids], tab.column("score")[ids]
    keep = scores >= score_min
    near: dict = {}
    for (_, v, o, _, T) in r["_pred"]:
        near.setdefault((int(v), int(o)), []).append(T[:3, 3])
    out = []
    for c, v, o, sc, k in zip(ids.tolist(), ims.tolist(), objs.tolist(), scores.tolist(), keep.tolist()):
        if not k:
            continue
        t = cands.T_cam_obj[c][:3, 3]
        centres = near.get((v, o))
        if centres is not None and np.linalg.norm(np.asarray(centres) - t, axis=1).min() < \
                conf["explained_frac"] * diameters.get(o, 0.0):
            continue
        out.append((c, v, o, sc))
    return out


def _check_leftovers(checker, ds: BopDataset, r: dict, cands: bop.PoseResults, diameters: dict, conf: dict,
                     score_min: float) -> None:
    """The image check of a group's leftover candidates across its placed views
    (:meth:`~cosy_cli.multiview.image_check.ImageChecker.check_leftovers`): r["_leftover_T"]
    {cand_id: new T_cam_obj} for group_predictions, r["leftovers"] for scene.json."""
    from . import image_check as ic

    t0 = time.perf_counter()
    s = int(r["scene_id"])
    # RGB views, and views with depth when the group's views are distinct viewpoints (wide_views):
    # from one viewpoint the single-view pick (depth fit + image) is the stronger judge (on the YCB-V
    # frames the check cost 0.03 AR with the image score, 0.06 with depth + image); from several, the
    # views' images settle what one view's depth cannot (a proxy RGB-D LM-O, see docs/results.md).
    # Cameras: those from image features where refine finds them (feature_cameras "leftovers"),
    # computed here, and only when the check can use them: some label has leftovers in two views
    # (a leftover alone in its label cannot take another view's pose, whatever the cameras)
    pending = r.pop("_features_pending", None) or []
    if pending:
        fb_all = fallback_candidates(r, cands, diameters, conf, score_min)
        views_of: dict = {}
        for _, v, o, _ in fb_all:
            views_of.setdefault(o, set()).add(v)
        if any(len(vs) > 1 for vs in views_of.values()):
            t_f = time.perf_counter()
            for f in pending:
                f()
            _record_feature_cameras(r, r["stats"].pop("_feature_T_world_cam", {}))
            r["_time"] += time.perf_counter() - t_f
        else:
            r["stats"]["feature_cameras"] = {"views": {}, "skipped": FEATURES_SKIPPED}
    lc = r.get("_feature_cams") or {}
    placed = {int(c["im_id"]): np.asarray(lc.get(int(c["im_id"]), c["T_world_cam"]), dtype=np.float64)
              for c in r["cameras"]}
    placed.update({int(v): np.asarray(T, dtype=np.float64) for v, T in lc.items()})  # views only features placed
    wide = wide_views(r.get("stats", {}))
    placed = {v: T for v, T in placed.items() if wide or ds.depth_path(s, v) is None}
    fb = [x for x in fallback_candidates(r, cands, diameters, conf, score_min) if x[1] in placed]
    if len({v for _, v, _, _ in fb}) < 2:
        return
    items = [ic.Leftover(v, o, cands.T_cam_obj[c]) for c, v, o, _ in fb]
    views = sorted({v for _, v, _, _ in fb})
    cams = ds.scene_camera(s)
    rgb = r.get("_rgb") or (lambda v: ds.read_rgb(s, v))
    res = checker.check_leftovers(items, {v: rgb(v) for v in views}, {v: cams[v].K for v in views}, placed)
    changed = np.flatnonzero(res.source != np.arange(len(fb)))
    r["_leftover_T"] = {fb[k][0]: res.T[k] for k in changed}
    r["leftovers"] = {"clusters": [[fb[k][0] for k in np.flatnonzero(res.cluster == ci)]
                                   for ci in range(len(res.cluster_scores))],
                      "replaced": [{"cand_id": int(fb[k][0]), "im_id": int(fb[k][1]), "obj_id": int(fb[k][2]),
                                    "pose_of_cand_id": int(fb[res.source[k]][0])} for k in changed]}
    r["stats"]["image_check_leftovers"] = {"clusters": len(res.cluster_scores), "replaced": int(len(changed)),
                                           "time_s": round(time.perf_counter() - t0, 6)}


FEATURES_SKIPPED = "no label has leftover candidates in two views: image features could not change the leftover check"


def _record_feature_cameras(r: dict, feature_cams: dict) -> None:
    """scene.json's record of the cameras from image features found for the leftover check: per
    camera ``T_world_cam_features``, and ``feature_only_cameras`` for views only they placed."""
    r["_feature_cams"] = feature_cams
    placed = set()
    for cam in r["cameras"]:
        placed.add(int(cam["im_id"]))
        if int(cam["im_id"]) in feature_cams:
            cam["T_world_cam_features"] = _mat(feature_cams[int(cam["im_id"])])
    extra = [v for v in sorted(feature_cams) if int(v) not in placed]
    if extra:
        r["feature_only_cameras"] = [{"im_id": int(v), "T_world_cam_features": _mat(feature_cams[v])} for v in extra]


def _count_placed_by(results: list) -> dict:
    """How many views were placed which way ("ransac", "two objects", "one object", ...)."""
    out: dict = {}
    for r in results:
        for text in (r.get("placed_by") or {}).values():
            k = text.split(" (")[0]
            out[k] = out.get(k, 0) + 1
    return out


def _mat(T: np.ndarray) -> list:
    return [[float(f"{v:.10g}") for v in row] for row in np.asarray(T)]


def _num(x: float):
    return None if not np.isfinite(x) else round(float(x), 4)


# --------------------------------------------------------------------------------------------
# the stage
# --------------------------------------------------------------------------------------------

def is_complete(out: str | Path) -> bool:
    return cache.is_complete(out, OUTPUT_FILES)


def stale_reasons(out: Path, conf: dict, dataset: str | Path, split: str, matches: str | Path,
                  scorer_model: str | Path | None = None) -> list[str]:
    """Why a complete ``out`` does not correspond to these inputs and settings (empty: it does)."""

    try:
        doc = json.loads((Path(out) / "scene.json").read_text())
    except (OSError, json.JSONDecodeError):
        return ["scene.json unreadable"]
    reasons = []
    old = doc.get("conf") or {}
    changed = sorted(k for k in set(conf) | set(old) if old.get(k) != conf.get(k))
    if changed:
        reasons.append(f"settings changed ({', '.join(changed)})")
    if doc.get("dataset") != str(Path(dataset).resolve()) or doc.get("split") != split:
        reasons.append("another dataset or split")
    g = Path(matches) / "groups.json"
    if doc.get("matches") != str(Path(matches).resolve()) or (g.is_file() and doc.get("groups_sha1") != file_sha1(g)):
        reasons.append("the match output changed")
    if (doc.get("scorer_model") or {}).get("sha1") != (file_sha1(scorer_model) if scorer_model else None):
        reasons.append("the scorer changed")
    return reasons


def main(conf: dict | None, dataset: str | Path, split: str, matches: str | Path, out: str | Path,
         overwrite: bool = False, *, scorer_model: str | Path | None = None, log=print,
         progress: bool = True) -> dict | None:
    """Run ``cosy refine``; returns the summary (None when skipped because ``out`` is up to date).
    ``scorer_model``: a learned hypothesis scorer (``cosy train scorer``, ONNX) for the image check
    (setting ``image_check_scorer``)."""
    from threadpoolctl import threadpool_limits


    t_start = time.perf_counter()
    conf = resolve_conf(conf)
    out = Path(out)
    if reuse_existing_output(out, "refine", OUTPUT_FILES, overwrite,
                             lambda: stale_reasons(out, conf, dataset, split, matches, scorer_model), log):
        return None
    ds = BopDataset(dataset, split)
    doc, cands = read_match_dir(matches)
    gpath = Path(matches) / "groups.json"
    if doc["split"] != split:
        raise CosyError(f"was made for split {doc['split']!r}, not {split!r}", path=gpath)
    if doc["dataset"] != str(Path(dataset).resolve()):
        raise CosyError(f"was made from the dataset {doc['dataset']}, not {Path(dataset).resolve()}", path=gpath)
    known = bool(doc["known_cameras"])
    infos = ds.models_info()
    used = sorted({int(o["obj_id"]) for g in doc["groups"] for o in g["objects"]})
    bad = [o for o in used if o not in infos]
    if bad:
        raise CosyError(f"object {bad[0]} of {gpath} is not in the dataset's models", path=ds.models_info_path)
    c_obj = cands.column("obj_id")
    used = sorted({int(o["obj_id"]) for g in doc["groups"] if len(g["im_ids"]) > 1 for o in g["objects"]}
                  | {int(c_obj[int(c)]) for g in doc["groups"] if len(g["im_ids"]) > 1 for c in g["discarded"]})
    geometry = {o: label_geometry(ds, o, conf["n_points"], conf["symmetry_steps"]) for o in used}

    groups = doc["groups"]
    checker = None
    if conf["image_check"] != "none":
        from . import image_check as ic

        multi = [g for g in groups if len(g["im_ids"]) > 1]
        with_images = [g for g in multi if ic.images_available(ds, int(g["scene_id"]), [int(v) for v in g["im_ids"]])]
        if conf["image_check"] == "on" and len(with_images) < len(multi):
            g = next(g for g in multi if g not in with_images)
            raise CosyError(f"image_check on: the RGB images of scene {g['scene_id']} are missing",
                            path=ds.image_dir(int(g["scene_id"])))
        if with_images:
            from ..objects import ObjectDatabase

            labels = set(used)
            if conf["image_check_leftovers"]:  # leftover candidates may carry labels no object has
                labels |= {int(o) for o in np.unique(cands.column("obj_id"))} & set(infos)
            db = ObjectDatabase.from_models_dir(ds.models_dir, obj_ids=labels)
            scorer = None
            if scorer_model is not None and conf["image_check_scorer"] != "none":
                from ..onnxrt import provider_names
                from ..singleview.scorer.runtime import OnnxScorer

                scorer = OnnxScorer(scorer_model, provider_names("cpu"))  # of any crop side (see verify.Verifier)
                unseen = scorer.unseen(labels)
                if unseen:
                    log(f"refine: note: the scorer was not trained on obj_id {', '.join(map(str, unseen))}; it still "
                        "compares their renders with the images")
            checker = ic.ImageChecker(db, ic.ImageCheckConf(align=conf["image_check_align"],
                                                            margin=conf["image_check_margin"],
                                                            align_max_move=conf["image_check_max_move"],
                                                            min_gap=conf["image_check_min_gap"],
                                                            verify={"crop": conf["image_check_crop"]},
                                                            w_box=conf["image_check_w_box"],
                                                            box=conf["image_check_box"],
                                                            scorer_use=conf["image_check_scorer"]), scorer=scorer)
            checked = {id(g) for g in with_images}
    bar = None
    if progress and (len(groups) > 50 or checker is not None):
        from ..console import progress as progress_bar

        bar = progress_bar(total=len(groups), desc="refine", unit="group")
    results = []
    diam = {int(o): float(i.diameter) for o, i in infos.items()}
    score_min = float((doc.get("conf") or {}).get("score_threshold", -np.inf))
    try:
        with threadpool_limits(1):
            for g in groups:
                chk = checker if checker is not None and id(g) in checked else None
                r = refine_group(g, cands, ds, geometry, conf, known, chk)
                if leftover_check_on(conf, chk) and not r.get("single_view"):
                    _check_leftovers(chk, ds, r, cands, diam, conf, score_min)
                r.pop("_rgb", None)  # the group's images: not kept past it
                results.append(r)
                if bar is not None:
                    bar.update(1)
    finally:
        if bar is not None:
            bar.close()
        if checker is not None:
            checker.close()

    # predictions: the refined scene (+ the candidates it does not explain)
    rows, n_refined, n_unmatched = [], 0, 0
    for r in results:
        part, n_fb = group_predictions(r, cands, diam, conf, score_min)
        rows += [x + (r["_time"],) for x in part]
        n_refined += len(part) - n_fb
        n_unmatched += n_fb
        r["stats"]["n_fallback_candidates"] = n_fb
    rows.sort(key=lambda x: (x[0], x[1], -x[3], x[2]))
    if rows:
        preds = bop.PoseResults.from_arrays([x[0] for x in rows], [x[1] for x in rows], [x[2] for x in rows],
                                            [x[3] for x in rows], np.stack([x[4] for x in rows]),
                                            [x[5] for x in rows])
    else:
        preds = bop.PoseResults.empty()

    times = np.array([r["_time"] for r in results]) if results else np.zeros(0)
    n_views = sum(len(g["im_ids"]) for g in groups)
    n_placed = sum(len(r["cameras"]) for r in results)
    finals = [v["final"] for r in results for v in r["stats"].get("reprojection_error_px", {}).values()
              if v["final"] is not None]
    summary = {
        "groups": len(results), "objects": int(sum(len(r["objects"]) for r in results)),
        "views": int(n_views), "views_placed": int(n_placed),
        "predictions": len(preds), "refined_predictions": n_refined, "unmatched_predictions": n_unmatched,
        "output": conf["output"], "placed_by": _count_placed_by(results),
        "median_reprojection_error_px": float(np.median(finals)) if finals else None,
        "not_converged": int(sum(not r["stats"]["converged"] for r in results)),
        "single_view_groups": int(sum(bool(r.get("single_view")) for r in results)),
        "rematched_objects": int(sum(r["stats"].get("n_rematched_objects", 0) for r in results)),
        "image_check": ({k: int(sum(r["stats"].get("image_check", {}).get(k, 0) for r in results))
                         for k in ("refined", "aligned", "candidate")} if checker is not None else None),
        "leftovers_replaced": int(sum(r["stats"].get("image_check_leftovers", {}).get("replaced", 0) for r in results)),
        "feature_cameras_used": int(sum(v["used"] for r in results
                                        for v in r["stats"].get("feature_cameras", {}).get("views", {}).values())),
        # image pairs on which OpenCV refused the features (degenerate matches): no pose, the reason in scene.json
        "feature_pairs_refused": int(sum(OPENCV_REFUSED in v.get("no_pose", "") for r in results
                                         for v in r["stats"].get("feature_cameras", {}).get("views", {}).values())),
        "time_per_group_ms": float(times.mean() * 1e3) if len(times) else 0.0,
        "max_time_per_group_ms": float(times.max() * 1e3) if len(times) else 0.0,
    }
    out_doc = {
        "format": "cosy-refine", "version": FORMAT_VERSION, "cosy_version": __version__, "conf": conf,
        "dataset": str(Path(dataset).resolve()), "split": split, "matches": str(Path(matches).resolve()),
        "groups_sha1": file_sha1(gpath), "known_cameras": known,
        **({"scorer_model": {"path": str(Path(scorer_model).resolve()), "sha1": file_sha1(scorer_model)}}
           if scorer_model is not None else {}),
        "world_frame": "dataset world (known cameras)" if known else "gauge camera (gauge_im_id) of each group",
        "units": {"T": "mm, T_world_cam maps camera points into the world, T_world_obj model points",
                  "cost": "px^2", "reprojection_error": "px"},
        "summary": summary,
        "groups": [{k: v for k, v in r.items() if not k.startswith("_")} for r in results],
    }
    with atomic.atomic_dir(out, overwrite=overwrite) as tmp:
        (tmp / "scene.json").write_text(json.dumps(out_doc, separators=(",", ":")) + "\n")
        (tmp / "predictions.csv").write_text(bop.format_results(preds))
        manifest.write_folder_manifest(tmp, "cosy refine", OUTPUT_FILES)  # checked by cosy evaluate
    med = summary["median_reprojection_error_px"]
    log(f"refine: {summary['groups']} groups, {summary['views_placed']}/{summary['views']} views placed, "
        f"{summary['objects']} objects, {summary['predictions']} predictions"
        + (f" ({n_unmatched} single-view candidates no refined object explains, scored below)"
           if conf["output"] == "scene+candidates" else "")
        + (f"; median reprojection error {med:.2f} px" if med is not None else "")
        + (f"; {summary['single_view_groups']} single-view group(s): candidates passed through"
           if summary["single_view_groups"] else "")
        + ("; image check kept " + ", ".join(f"{n} {k}" for k, n in summary["image_check"].items())
           if summary["image_check"] else "")
        + (f"; {summary['leftovers_replaced']} leftover candidates took another view's pose"
           if summary["leftovers_replaced"] else "")
        + (f"; feature cameras for {summary['feature_cameras_used']} views" if summary["feature_cameras_used"] else "")
        + (f"; {summary['feature_pairs_refused']} image pair(s) OpenCV could not estimate a pose from (scene.json "
           "stats.feature_cameras: no_pose)" if summary["feature_pairs_refused"] else "")
        + f"; {summary['time_per_group_ms']:.2f} ms per group (max {summary['max_time_per_group_ms']:.2f}); "
        f"total {time.perf_counter() - t_start:.2f} s -> {out}")
    return summary
