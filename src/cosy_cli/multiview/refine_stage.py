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
    object: see ``min_agreeing``). ``stats``: iterations, converged,
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
    ``output`` "scene": the refined rows alone. time = seconds spent on the group.
``manifest.json``
    sha1 and size of the two files above (:mod:`cosy_cli.io.manifest`), checked by ``cosy evaluate``.

A group of one view (a scene of one image) has nothing to refine: its candidates pass through
unchanged as its predictions (the camera is the identity, the view being the world frame; the
dataset's pose with known cameras) and its scene.json entry says ``"single_view": true`` with a
``note``. The match folder is checked against its ``manifest.json`` first: a file changed or
truncated since ``cosy match`` wrote it is refused.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from .. import __version__
from ..conf import merge_conf
from ..errors import CosyError
from ..geometry.poses import invert
from ..io import atomic, bop, cache, manifest
from ..io.cache import file_sha1, reuse_existing_output
from ..io.dataset import BopDataset
from ..objects.symmetries import symmetry_set
from . import bundle_adjustment as ba
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
    "nms_mm": 0.0,  # merge objects of one label whose centres are closer (0: off)
    # Two solid objects cannot share the space: objects of any labels whose centres are closer
    # than this fraction of the smaller diameter are one physical object (typically a look-alike
    # whose label was swapped in several views); the weaker one is dropped (0: off).
    "exclusion_frac": 0.5,
}


def resolve_conf(conf: dict | None = None, **overrides) -> dict:
    """The full configuration: defaults, then ``conf``, then overrides (None ignored), checked."""
    conf, overrides = _legacy_keys(conf), _legacy_keys(overrides)
    base = merge_conf({"default": DEFAULT_CONF}, conf or {}, overrides, default="default", what="refine")
    base["iterations"] = int(base["iterations"])
    base["min_agreeing"] = int(base["min_agreeing"])
    base["n_points"] = int(base["n_points"])
    base["symmetry_steps"] = int(base["symmetry_steps"])
    for k in ("loss_threshold_px", "nms_mm", "exclusion_frac", "explained_frac"):
        base[k] = float(base[k])
    if base["output"] not in OUTPUTS:
        raise CosyError(f"refine output {base['output']!r} is not one of {', '.join(OUTPUTS)}")
    if base["iterations"] < 1 or base["n_points"] < 3 or base["symmetry_steps"] < 1 or base["loss_threshold_px"] <= 0 \
            or base["nms_mm"] < 0 or base["exclusion_frac"] < 0 or base["explained_frac"] < 0 or base["min_agreeing"] < 0:
        raise CosyError("refine settings out of range (iterations >= 1, n_points >= 3, loss threshold > 0, "
                        "distances >= 0)")
    return base


OUTPUTS = ("scene+candidates", "scene")


def _legacy_keys(conf):
    """``keep_unmatched`` (before issue 16) is ``output``: true -> scene+candidates, false -> scene."""
    if not isinstance(conf, dict) or "keep_unmatched" not in conf:
        return conf
    conf = dict(conf)
    keep = conf.pop("keep_unmatched")
    if keep is not None:
        conf.setdefault("output", "scene+candidates" if keep not in (False, "false", "False", 0, "0") else "scene")
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


SINGLE_VIEW_NOTE = "single view: candidates passed through"


def single_view_group(g: dict, cands: bop.PoseResults, T_world_cam: np.ndarray, t0: float) -> dict:
    """A group of one view: nothing to refine. Each object's best candidate is its prediction,
    unchanged (T_cam_obj and score of the candidate); the camera is ``T_world_cam`` (the
    identity: the view is the world frame, or the dataset's pose with known cameras). Same
    entry as :func:`refine_group`, with ``"single_view": true`` and a ``note``."""
    s, v = int(g["scene_id"]), int(g["im_ids"][0])
    c_score = cands.table["score"].to_numpy()
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
                 known_cameras: bool) -> dict:
    """Refine one group of groups.json. ``geometry``: {obj_id: LabelGeometry}. Returns the
    group's scene.json entry plus private keys: "_pred" (rows of predictions) and "_unused"
    (cand_ids not used in the scene). A group of one view: :func:`single_view_group`."""
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
        c_obj = cands.table["obj_id"].to_numpy()
        links = [placement.Link(int(p["im_id_a"]), int(p["im_id_b"]), np.asarray(p["T_cam_a_cam_b"], dtype=np.float64),
                                int(p["n_inliers"]), p.get("link", "ransac"),
                                [int(c_obj[int(e[0])]) for e in p.get("associations", [])])
                 for p in g["view_pairs"] if p.get("linked")]
        placed, placed_by, _, gauge = placement.place_cameras(im_ids, links)
        unplaced = [v for v in im_ids if v not in placed]
    views = list(placed)
    vidx = {v: k for k, v in enumerate(views)}
    tab = cands.table
    c_im = tab["im_id"].to_numpy()
    c_score = tab["score"].to_numpy()

    # candidates of objects, in placed views
    cand_ids, cand_obj, objs = [], [], []
    unused = [int(c) for c in g["discarded"]]
    for o in g["objects"]:
        members = [int(c) for c in o["cand_ids"] if int(c_im[int(c)]) in vidx]
        unused += [int(c) for c in o["cand_ids"] if int(c_im[int(c)]) not in vidx]
        if not members:
            continue
        cand_obj += [len(objs)] * len(members)
        cand_ids += members
        objs.append(o)
    cand_ids = np.array(cand_ids, dtype=np.int64)
    cand_obj = np.array(cand_obj, dtype=np.int64)
    Twc = np.stack([placed[v] for v in views])
    K = np.stack([cams[v].K for v in views])
    stats: dict = {"iterations": 0, "converged": True, "initial_cost_px2": 0.0, "final_cost_px2": 0.0,
                   "n_candidates": int(len(cand_ids)), "n_unused_candidates": len(unused)}
    objects_out = []
    T_world_obj = np.zeros((0, 4, 4))
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
                               fixed_views="all" if known_cameras else 0, symmetries=S0)
        Twc, T_world_obj = res.T_world_cam, res.T_world_obj
        n_c = np.bincount(cand_obj, minlength=len(objs))
        score = np.full(len(objs), -np.inf)
        np.maximum.at(score, cand_obj, c_score[cand_ids])
        err = np.bincount(cand_obj, weights=np.nan_to_num(res.cand_error_px), minlength=len(objs)) / n_c
        o_ids = np.array([int(o["obj_id"]) for o in objs])
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
            mk = np.isin(cand_obj, np.flatnonzero(into == k))
            if len(np.unique(cv[mk & agree])) < conf["min_agreeing"]:
                keep[k] = False
                into[into == k] = -1
                n_unsupported += 1
        view_ok = np.zeros(len(views), dtype=bool)
        view_ok[cv[agree & np.isin(cand_obj, np.flatnonzero(keep))]] = True
        for k, o in enumerate(objs):
            if not keep[k]:
                continue
            merged = np.flatnonzero(into == k)
            ids = cand_ids[np.isin(cand_obj, merged)]
            entry = {"object_id": int(o["object_id"]), "obj_id": int(o["obj_id"]), "score": float(score[merged].max()),
                     "n_candidates": int(len(ids)), "cand_ids": [int(c) for c in ids],
                     "reprojection_error_px": round(float(err[k]), 4),
                     "T_world_obj": _mat(T_world_obj[k])}
            if len(merged) > 1:
                entry["merged_object_ids"] = [int(objs[m]["object_id"]) for m in merged if m != k]
            objects_out.append(entry)
        T_world_obj = T_world_obj[keep]
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
            views = [v for k, v in enumerate(views) if view_ok[k]]
    dt = time.perf_counter() - t0
    stats["time_s"] = round(dt, 6)
    # predictions: every kept object in every placed camera
    pred = []
    if len(objects_out):
        T_cam_obj = ba.predictions_from_scene(Twc, T_world_obj)  # (V, N', 4, 4)
        for k, v in enumerate(views):
            for j, o in enumerate(objects_out):
                pred.append((s, v, o["obj_id"], o["score"], T_cam_obj[k, j]))
    return {
        "scene_id": s, "group_id": int(g["group_id"]), "gauge_im_id": gauge,
        "cameras": [{"im_id": int(v), "T_world_cam": _mat(Twc[k]), "placed_by": placed_by[v]}
                    for k, v in enumerate(views)],
        "unplaced_im_ids": [int(v) for v in unplaced], "placed_by": {str(v): placed_by[v] for v in im_ids},
        "objects": objects_out, "stats": stats,
        "_pred": pred, "_unused": sorted(set(unused)), "_time": dt,
        "_all_cands": sorted({int(c) for o in g["objects"] for c in o["cand_ids"]} | {int(c) for c in g["discarded"]}),
    }


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
    tab = cands.table
    ids = np.array(sorted(r["_all_cands"]), dtype=np.int64)
    if not len(ids):
        return rows, 0
    ims, objs, scores = tab["im_id"].to_numpy()[ids], tab["obj_id"].to_numpy()[ids], tab["score"].to_numpy()[ids]
    keep = scores >= score_min
    near: dict = {}
    for (_, v, o, _, T) in r["_pred"]:
        near.setdefault((int(v), int(o)), []).append(T[:3, 3])
    n_fb = 0
    for c, v, o, sc, k in zip(ids.tolist(), ims.tolist(), objs.tolist(), scores.tolist(), keep.tolist()):
        if not k:
            continue
        t = cands.T_cam_obj[c][:3, 3]
        centres = near.get((v, o))
        if centres is not None and np.linalg.norm(np.asarray(centres) - t, axis=1).min() < \
                conf["explained_frac"] * diameters.get(o, 0.0):
            continue
        rows.append((int(r["scene_id"]), v, o, float(fallback_score(sc)), cands.T_cam_obj[c]))
        n_fb += 1
    return rows, n_fb


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


def stale_reasons(out: Path, conf: dict, dataset: str | Path, split: str, matches: str | Path) -> list[str]:
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
    return reasons


def main(conf: dict | None, dataset: str | Path, split: str, matches: str | Path, out: str | Path,
         overwrite: bool = False, *, log=print, progress: bool = True) -> dict | None:
    """Run ``cosy refine``; returns the summary (None when skipped because ``out`` is up to date)."""
    from threadpoolctl import threadpool_limits


    t_start = time.perf_counter()
    conf = resolve_conf(conf)
    out = Path(out)
    if reuse_existing_output(out, "refine", OUTPUT_FILES, overwrite,
                             lambda: stale_reasons(out, conf, dataset, split, matches), log):
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
    used = sorted({int(o["obj_id"]) for g in doc["groups"] if len(g["im_ids"]) > 1 for o in g["objects"]})
    geometry = {o: label_geometry(ds, o, conf["n_points"], conf["symmetry_steps"]) for o in used}

    groups = doc["groups"]
    bar = None
    if progress and len(groups) > 50:
        from tqdm import tqdm

        bar = tqdm(total=len(groups), desc="refine", unit="group", leave=False, disable=None)
    results = []
    with threadpool_limits(1):
        for g in groups:
            results.append(refine_group(g, cands, ds, geometry, conf, known))
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()

    # predictions: the refined scene (+ the candidates it does not explain)
    diam = {int(o): float(i.diameter) for o, i in infos.items()}
    score_min = float((doc.get("conf") or {}).get("score_threshold", -np.inf))
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
        "time_per_group_ms": float(times.mean() * 1e3) if len(times) else 0.0,
        "max_time_per_group_ms": float(times.max() * 1e3) if len(times) else 0.0,
    }
    out_doc = {
        "format": "cosy-refine", "version": FORMAT_VERSION, "cosy_version": __version__, "conf": conf,
        "dataset": str(Path(dataset).resolve()), "split": split, "matches": str(Path(matches).resolve()),
        "groups_sha1": file_sha1(gpath), "known_cameras": known,
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
        + f"; {summary['time_per_group_ms']:.2f} ms per group (max {summary['max_time_per_group_ms']:.2f}); "
        f"total {time.perf_counter() - t_start:.2f} s -> {out}")
    return summary
