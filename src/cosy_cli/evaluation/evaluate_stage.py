"""``cosy evaluate``: pose errors of predictions against a BOP dataset's GT, BOP19, BOP24 and CosyPose scores.

Inputs: a BOP dataset (scene_camera/scene_gt/scene_gt_info per scene, ``models_eval/`` (or
``models/``) with models_info.json, depth images for VSD), predictions as a BOP results CSV
(``T_cam_obj``, mm), optionally a targets file and a ``scene.json`` of ``cosy refine``.

Output folder (built atomically):

``errors.csv``
    One row per (estimate, GT instance of the same obj_id in the same image):
    ``scene_id,im_id,obj_id,est_index,gt_index,add,adi,mssd,mspd,re,te[,vsd_tau_0.05..vsd_tau_0.50]``.
    ``est_index`` = 0-based data row of the predictions CSV, ``gt_index`` = position in the image's
    scene_gt.json list. add, adi, mssd, te in mm, mspd in px, re in degrees; raw values (the
    toolkit's sphere shortcut is applied by the BOP19 protocol, from ``te``). Model points = all
    vertices of the evaluation models; MSSD/MSPD minimise over the symmetry set with continuous
    symmetries in ceil(pi / 0.01) = 315 steps (the toolkit's ``max_sym_disc_step``). VSD columns
    (only when every target image has depth) are filled for the pairs the BOP19 protocol uses
    (top ``inst_count`` estimates of each target; empty elsewhere), with the toolkit's values:
    1.0 when the sphere projections do not overlap (nothing rendered).
``scores.json``
    BOP19 (``bop19_average_recall[_vsd|_mssd|_mspd]``), with ``bop24`` the BOP 2024 detection APs
    (``bop24_ap[_mssd|_mspd|_mssd_mm]``, :mod:`.bop24`), CosyPose AUC (``auc_adds``,
    ``auc_add_or_adds``, ``recall_adds_0.1d``), per-object breakdowns, counts, camera errors
    (with a scene.json), warnings, the settings and the inputs (hashes).
``curves.csv``, ``gt_errors.csv``
    The data behind the plots: recall per (metric, tau, threshold); per GT instance the ADD-S (mm)
    of its top-1 match (inf: none).
``report.png``
    Recall vs. threshold (ADD-S, MSSD, MSPD, VSD) and per-object ADD-S histograms.
``manifest.json``
    sha1 and size of the files above (:mod:`cosy_cli.io.manifest`).

With ``oracle`` (``cosy evaluate --oracle depth|rotation|translation``), every (estimate, GT) pair is
scored with the estimate's distance along its ray, its rotation or its translation taken from that
pair's GT (:mod:`.oracle`): the scores the estimates would reach were that part exact, recorded
under ``scores.json`` ``oracle`` and in the report's title. A diagnostic, not a BOP score.

Predictions (and scene.json) written by a cosy stage are checked against that stage's
manifest first: a file changed or truncated since is refused.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pandas as pd

from .. import __version__
from ..conf import as_bool, merge_conf
from ..errors import CosyError
from ..io import atomic, bop, cache, manifest
from ..io.dataset import BopDataset
from . import bop24 as bop24_protocol, oracle as oracle_poses, pose_error, protocols

OUTPUT_FILES = ("errors.csv", "scores.json", "curves.csv", "gt_errors.csv", "report.png")
KNOWN_METRICS = ("bop19", "bop24", "auc", "vivo")
DEFAULT_METRICS = ("bop19", "auc")
BOP24_KEYS = ("bop24_ap", "bop24_ap_mssd", "bop24_ap_mspd", "bop24_ap_mssd_mm")

CONFS: dict[str, dict] = {
    # BOP19 (bop_toolkit eval_bop19_pose.py defaults) and the CosyPose AUC protocol.
    "bop19": {
        "vsd_delta": protocols.BOP19_VSD_DELTA,  # mm
        "max_sym_disc_step": 0.01,  # rad: continuous symmetries in ceil(pi / step) steps
        "vsd": True,  # False: skip VSD (no rendering; bop19_average_recall is then null)
    },
}


def resolve_conf(conf: str | dict | None = "bop19", **overrides) -> dict:
    base = merge_conf(CONFS, conf, overrides, default="bop19", what="evaluate")
    if not (float(base["vsd_delta"]) > 0 and float(base["max_sym_disc_step"]) > 0):
        raise CosyError("vsd_delta and max_sym_disc_step must be > 0")
    base["vsd_delta"] = float(base["vsd_delta"])
    base["max_sym_disc_step"] = float(base["max_sym_disc_step"])
    base["vsd"] = as_bool(base["vsd"], "vsd", "evaluate")
    return base


def parse_metrics(metrics) -> list[str]:
    if metrics is None:
        return list(DEFAULT_METRICS)
    if isinstance(metrics, str):
        metrics = [m.strip() for m in metrics.split(",") if m.strip()]
    bad = [m for m in metrics if m not in KNOWN_METRICS]
    if bad:
        raise CosyError(f"unknown metric(s) {', '.join(bad)} (known: {', '.join(KNOWN_METRICS)})")
    if not metrics:
        raise CosyError(f"no metric selected (known: {', '.join(KNOWN_METRICS)})")
    return list(dict.fromkeys(metrics))


def _sha1(path: Path | None) -> str | None:
    return None if path is None or not Path(path).is_file() else cache.file_sha1(path)


def is_complete(out: Path) -> bool:
    return cache.is_complete(out, OUTPUT_FILES)


# --------------------------------------------------------------------------------------------
# inputs
# --------------------------------------------------------------------------------------------
def load_models(ds: BopDataset, models_dir: str | Path | None, warn) -> tuple:
    """ObjectDatabase of the evaluation models (``models_eval`` by default, ``models`` as fallback)."""
    from ..objects import ObjectDatabase

    name = Path(models_dir) if models_dir is not None else Path("models_eval")
    path = name if name.is_absolute() else ds.root / name
    if not (path / "models_info.json").is_file():
        if models_dir is not None and str(models_dir) != "models_eval":
            raise CosyError("models folder with models_info.json not found", path=path)
        fallback = ds.root / "models"
        if not (fallback / "models_info.json").is_file():
            raise CosyError("neither models_eval/ nor models/ has a models_info.json", path=ds.root)
        warn(f"{path} not found: using {fallback} (BOP evaluates with the models_eval meshes)")
        path = fallback
    return ObjectDatabase.from_models_dir(path), path


def _check_predictions(res: bop.PoseResults, path: Path, ds: BopDataset, db) -> None:
    tab = res.table
    scenes = set(ds.scene_ids)
    for col, ok in (("scene_id", lambda v: v in scenes),):
        bad = ~tab[col].map(ok).to_numpy(dtype=bool)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise CosyError(f"scene_id {int(tab[col].iloc[i])} is not a scene of {ds.split_dir} "
                            f"(scenes: {', '.join(str(s) for s in sorted(scenes))})", path=path, where=f"row {i + 1}")
    for scene_id, sub in tab.groupby("scene_id"):
        ims = set(ds.image_ids(int(scene_id)))
        bad = ~sub["im_id"].isin(ims).to_numpy()
        if bad.any():
            i = int(sub.index[np.flatnonzero(bad)[0]])
            raise CosyError(f"im_id {int(tab['im_id'].iloc[i])} is not an image of scene {int(scene_id)}",
                            path=path, where=f"row {i + 1}")
    bad = ~tab["obj_id"].isin(set(db.obj_ids)).to_numpy()
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise CosyError(f"obj_id {int(tab['obj_id'].iloc[i])} is not a model (known: {db.obj_ids})",
                        path=path, where=f"row {i + 1}")


def load_gt(ds: BopDataset, warn) -> tuple[pd.DataFrame, np.ndarray, dict]:
    """GT table (scene_id, im_id, gt_index, obj_id, visib_fract), poses (n, 4, 4) mm, cameras."""
    rows, poses, cams = [], [], {}
    for scene_id in ds.scene_ids:
        if not ds.has_gt(scene_id):
            continue
        gt = ds.scene_gt(scene_id)
        cam = ds.scene_camera(scene_id)
        info_path = ds.scene_file(scene_id, "scene_gt_info")
        info = ds.scene_gt_info(scene_id) if info_path.is_file() else None
        if info is None:
            warn(f"{info_path} not found: visib_fract taken as 1 (BOP19 valid GT are then chosen by GT order)")
        for im_id, insts in gt.items():
            if im_id not in cam:
                raise CosyError(f"image {im_id} has GT but no camera in scene_camera.json",
                                path=ds.scene_file(scene_id, "scene_gt"))
            cams[(scene_id, im_id)] = cam[im_id]
            im_info = info.get(im_id) if info is not None else None
            if info is not None and (im_info is None or len(im_info) != len(insts)):
                raise CosyError(f"image {im_id}: {len(insts)} GT instances but "
                                f"{0 if im_info is None else len(im_info)} entries in scene_gt_info.json", path=info_path)
            for k, g in enumerate(insts):
                rows.append((scene_id, im_id, k, g.obj_id, 1.0 if im_info is None else float(im_info[k].visib_fract)))
                poses.append(g.T_cam_obj)
    if not rows:
        raise CosyError("no ground truth (scene_gt.json) in any scene", path=ds.split_dir)
    df = pd.DataFrame(rows, columns=["scene_id", "im_id", "gt_index", "obj_id", "visib_fract"])
    for c in ("scene_id", "im_id", "gt_index", "obj_id"):
        df[c] = df[c].astype(np.int64)
    return df, np.stack(poses), cams


def load_targets(ds: BopDataset, targets_path, gt: pd.DataFrame, warn) -> tuple[pd.DataFrame, str]:
    path = Path(targets_path) if targets_path is not None else ds.targets_path()
    if targets_path is not None and not path.is_file():
        raise CosyError("targets file not found", path=path)
    if path is None:
        warn("no targets file (test_targets_bop19.json): every GT instance of every image is a target")
        t = gt.groupby(["scene_id", "im_id", "obj_id"]).size().rename("inst_count").reset_index()
        return t, "all GT (no targets file)"
    listed, with_counts = bop.read_target_images(path)
    if not with_counts:  # a BOP 2024 file: images only
        _check_target_images(listed, gt, ds, path)
        warn(f"{path.name} lists images without inst_count: BOP19 takes every GT instance of them as a target")
        t = gt.merge(listed, on=["scene_id", "im_id"]).groupby(["scene_id", "im_id", "obj_id"]).size() \
            .rename("inst_count").reset_index()
        return t, f"{path} (images; every GT instance a target)"
    t = bop.read_targets(path)
    _check_target_images(t, gt, ds, path)
    dup = t.duplicated(["scene_id", "im_id", "obj_id"])
    if dup.any():
        i = int(np.flatnonzero(dup.to_numpy())[0])
        raise CosyError("duplicate target (same scene, image and object)", path=path, where=f"entry {i}")
    return t, str(path)


def _check_target_images(listed: pd.DataFrame, gt: pd.DataFrame, ds: BopDataset, path: Path) -> None:
    """Every (scene_id, im_id) of ``listed`` (indexed by entry number) has GT, else a CosyError."""
    ims = gt[["scene_id", "im_id"]].drop_duplicates()
    known = set(zip(ims["scene_id"], ims["im_id"]))
    for i, s, im in zip(listed.index, listed["scene_id"], listed["im_id"]):
        if (int(s), int(im)) not in known:
            raise CosyError(f"target scene {int(s)} image {int(im)} has no ground truth in {ds.split_dir}",
                            path=path, where=f"entry {i}")


BOP24_TARGETS = "test_targets_bop24.json"


def load_bop24_images(ds: BopDataset, targets_path, gt: pd.DataFrame, warn) -> tuple[pd.DataFrame, str]:
    """The images BOP 2024 evaluates, in the targets file's order: those of ``targets_path`` (either
    format), else of the dataset's test_targets_bop24.json, else of its test_targets_bop19.json
    (a warning), else every image with GT (a warning)."""
    if targets_path is not None:
        path = Path(targets_path)
        if not path.is_file():
            raise CosyError("targets file not found", path=path)
    elif (ds.root / BOP24_TARGETS).is_file():
        path = ds.root / BOP24_TARGETS
    else:
        path = ds.targets_path()
        if path is None:
            warn(f"no targets file ({BOP24_TARGETS}): BOP24 evaluates every image with GT")
            ims = gt[["scene_id", "im_id"]].drop_duplicates().sort_values(["scene_id", "im_id"])
            return ims.reset_index(drop=True), "all images with GT (no targets file)"
        warn(f"no {BOP24_TARGETS}: BOP24 evaluates the images of {path.name}")
    listed, _ = bop.read_target_images(path)
    _check_target_images(listed, gt, ds, path)
    return listed.reset_index(drop=True), str(path)


def parse_scene_json(path: Path, ds: BopDataset) -> list[dict]:
    """Groups of a ``cosy refine`` scene.json: [{"scene_id", "group_id", "im_ids", "placed": {im_id: T_world_cam}}].

    A group's views are its ``im_ids`` when given, else the im_ids of its cameras plus its
    ``unplaced_im_ids`` (what ``cosy refine`` writes); a camera is placed when its ``T_world_cam``
    (4x4, mm) is not null."""
    doc = bop.load_json(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("groups"), list):
        raise CosyError('expected {"groups": [{"scene_id", "group_id", "cameras": [{"im_id", "T_world_cam"}], ...}]}',
                        path=path)
    out = []
    for gi, g in enumerate(doc["groups"]):
        where = f"groups[{gi}]"
        if not isinstance(g, dict) or not isinstance(g.get("cameras"), list):
            raise CosyError("expected an object with scene_id, group_id and a cameras list", path=path, where=where)
        try:
            scene_id = int(g["scene_id"])
        except (KeyError, TypeError, ValueError):
            raise CosyError("scene_id: expected an integer", path=path, where=where) from None
        if scene_id not in ds.scene_ids:
            raise CosyError(f"scene_id {scene_id} is not a scene of {ds.split_dir}", path=path, where=where)
        placed, ims = {}, []
        for ci, c in enumerate(g["cameras"]):
            w = f"{where}.cameras[{ci}]"
            if not isinstance(c, dict) or not isinstance(c.get("im_id"), int):
                raise CosyError("expected {im_id: int, T_world_cam: 4x4 or null}", path=path, where=w)
            ims.append(c["im_id"])
            T = c.get("T_world_cam")
            if T is None:
                continue
            try:
                T = np.asarray(T, dtype=np.float64).reshape(4, 4)
            except (TypeError, ValueError):
                raise CosyError("T_world_cam: expected a 4x4 matrix (mm)", path=path, where=w) from None
            if not np.all(np.isfinite(T)):
                raise CosyError("T_world_cam: not a finite rigid transform", path=path, where=w)
            # tolerated like the rotations of the BOP files: nearest rotation within 0.05, else an error
            T[:3, :3] = bop.repair_rotations(T[:3, :3], lambda _: w, path=path, what="T_world_cam rotation")[0][0]
            placed[c["im_id"]] = T
        extra = g.get("unplaced_im_ids", [])  # cosy refine lists the views it could not place there
        if not isinstance(extra, list) or not all(isinstance(i, int) for i in extra):
            raise CosyError("unplaced_im_ids: expected a list of integers", path=path, where=where)
        all_ims = g.get("im_ids", ims + [i for i in extra if i not in ims])
        out.append({"scene_id": scene_id, "group_id": g.get("group_id", gi), "im_ids": [int(i) for i in all_ims],
                    "placed": placed})
    return out


def image_widths(ds: BopDataset, scene_ids) -> dict[int, float]:
    """Image width (px) per scene: camera.json's, else the first RGB image's."""
    cam = ds.camera()
    out = {}
    for s in scene_ids:
        if cam is not None:
            out[int(s)] = float(cam.width)
        else:
            im = ds.image_ids(int(s))[0]
            out[int(s)] = float(ds.image_size(int(s), im)[0])  # checked against cam_K
    return out


# --------------------------------------------------------------------------------------------
# errors
# --------------------------------------------------------------------------------------------
def compute_errors(pairs: pd.DataFrame, T_est: np.ndarray, T_gt: np.ndarray, K: np.ndarray, db, n_steps: int,
                   progress: bool = True) -> pd.DataFrame:
    """add, adi, mssd, mspd, re, te for rows of ``pairs`` (columns est_row, gt_row, obj_id) with
    poses T_est[est_row], T_gt[gt_row] and intrinsics K (len(pairs), 3, 3)."""
    from scipy.spatial import cKDTree
    from ..console import progress as progress_bar

    out = {k: np.full(len(pairs), np.nan) for k in ("add", "adi", "mssd", "mspd", "re", "te")}
    objs = pairs["obj_id"].to_numpy()
    bar = progress_bar(total=len(pairs), desc="errors", unit="pair", enabled=progress and len(pairs) >= 200)
    for obj_id in np.unique(objs):
        idx = np.flatnonzero(objs == obj_id)
        model = db[int(obj_id)]
        P = model.vertices
        S = model.symmetries_with_steps(n_steps)
        Te = T_est[pairs["est_row"].to_numpy()[idx]]
        Tg = T_gt[pairs["gt_row"].to_numpy()[idx]]
        out["add"][idx] = pose_error.add(Te, Tg, P)
        out["adi"][idx] = pose_error.adi(Te, Tg, P, tree=cKDTree(P))
        out["re"][idx] = pose_error.re(Te, Tg)
        out["te"][idx] = pose_error.te(Te, Tg)
        for start in range(0, len(idx), 256):
            sl = idx[start:start + 256]
            out["mssd"][sl] = pose_error.mssd(Te[start:start + 256], Tg[start:start + 256], P, S)
            out["mspd"][sl] = pose_error.mspd(Te[start:start + 256], Tg[start:start + 256], K[sl], P, S)
            bar.update(len(sl))
    bar.close()
    return pd.DataFrame(out, index=pairs.index)


def compute_vsd(pairs: pd.DataFrame, T_est: np.ndarray, T_gt: np.ndarray, cams: dict, ds: BopDataset, db,
                delta: float, taus, progress: bool = True) -> np.ndarray:
    """(len(pairs), len(taus)) VSD errors for pairs (est_row, gt_row, obj_id, scene_id, im_id, gt_index),
    rendering the evaluation models with :class:`cosy_cli.rendering.SceneRenderer` (exact depth, mm)."""
    from ..console import progress as progress_bar

    taus = np.asarray(taus, dtype=np.float64)
    out = np.ones((len(pairs), len(taus)))
    if len(pairs) == 0:
        return out
    te_ = T_est[pairs["est_row"].to_numpy()][:, :3, 3]
    tg_ = T_gt[pairs["gt_row"].to_numpy()][:, :3, 3]
    radius = 0.5 * pairs["obj_id"].map(lambda o: db[int(o)].diameter).to_numpy(dtype=np.float64)
    overlap = np.array([pose_error.sphere_projections_overlap(a, b, r)[0] for a, b, r in zip(te_, tg_, radius)])
    todo = pairs[overlap]
    if len(todo) == 0:
        return out
    from ..rendering import SceneRenderer

    obj_needed = sorted(set(int(o) for o in todo["obj_id"]))
    pos = {k: i for i, k in enumerate(pairs.index)}
    with SceneRenderer({o: db[o].mesh for o in obj_needed}, 64, 64) as ren:
        groups = list(todo.groupby(["scene_id", "im_id"], sort=True))
        for (scene_id, im_id), sub in progress_bar(groups, desc="VSD", unit="image", enabled=progress):
            depth_test = ds.read_depth(int(scene_id), int(im_id))
            H, W = depth_test.shape
            K = cams[(int(scene_id), int(im_id))].K
            gt_cache: dict = {}
            for key, r in sub.iterrows():
                o = int(r["obj_id"])
                d_est = ren.render(K, [o], T_est[int(r["est_row"])][None], with_rgb=False, size=(W, H)).depth
                g = int(r["gt_row"])
                if g not in gt_cache:
                    gt_cache[g] = ren.render(K, [o], T_gt[g][None], with_rgb=False, size=(W, H)).depth
                out[pos[key]] = pose_error.vsd(d_est, gt_cache[g], depth_test, K, delta, taus,
                                               diameter=db[o].diameter, normalized_by_diameter=True, cost="step")
    return out


# --------------------------------------------------------------------------------------------
# main
# --------------------------------------------------------------------------------------------
def _clean(x):
    """JSON-safe: NaN/inf -> None, numpy scalars -> Python."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def main(conf, dataset: str | Path, split: str, predictions: str | Path, out: str | Path, overwrite: bool = False, *,
         targets: str | Path | None = None, metrics=None, scene_json: str | Path | None = None,
         models_dir: str | Path | None = None, scene_ids=None, oracle: str | None = None, log=print,
         progress: bool = True) -> dict | None:
    """Run ``cosy evaluate``; returns the scores dict (None when skipped: ``out`` complete and up to date).
    ``scene_ids``: evaluate only these scenes (GT and targets of the others are ignored). ``oracle``
    (one of :data:`~cosy_cli.evaluation.oracle.ORACLES`): each estimate is scored with that part of its
    pose taken from the GT instance it is compared with (a diagnostic: :mod:`.oracle`)."""
    t0 = time.time()
    conf = resolve_conf(conf)
    metrics = parse_metrics(metrics)
    if oracle is not None and oracle not in oracle_poses.ORACLES:
        raise CosyError(f"oracle: expected one of {', '.join(oracle_poses.ORACLES)}, got {oracle!r}")
    out = Path(out)
    predictions = Path(predictions)
    inputs = {"version": __version__, "dataset": str(Path(dataset).resolve()), "split": split,
              "predictions": str(predictions.resolve()), "predictions_sha1": _sha1(predictions),
              "targets": None if targets is None else str(Path(targets).resolve()), "targets_sha1": _sha1(targets),
              "scene_json": None if scene_json is None else str(Path(scene_json).resolve()),
              "scene_json_sha1": _sha1(scene_json), "models_dir": None if models_dir is None else str(models_dir),
              "metrics": metrics, "conf": conf}
    if scene_ids is not None:
        inputs["scene_ids"] = sorted(int(x) for x in scene_ids)
    if oracle is not None:
        inputs["oracle"] = oracle
    # the settings are part of ``inputs`` (recorded under scores.json "inputs")
    if cache.reuse_existing_output(out, "evaluate", OUTPUT_FILES, overwrite,
                                   lambda: cache.sidecar_stale_reasons(out / "scores.json", None, inputs), log):
        return None

    from ..errors import warn as warn_user

    warnings: list[str] = []

    def warn(msg: str) -> None:  # kept in scores.json, and said (once per command) on stderr
        warnings.append(msg)
        warn_user(msg)

    from ..objects import continuous_steps_for_max_step

    ds = BopDataset(dataset, split)
    if scene_ids is not None:
        ds.select_scenes(scene_ids)  # CosyError for a scene the split does not have
    db, models_path = load_models(ds, models_dir, warn)
    manifest.verify(predictions)  # written by cosy refine / estimate: refused if changed since
    if scene_json is not None:
        manifest.verify(scene_json)
    res = bop.read_results(predictions)
    _check_predictions(res, predictions, ds, db)
    gt, T_gt, cams = load_gt(ds, warn)
    unknown_gt = sorted(set(gt["obj_id"]) - set(db.obj_ids))
    if unknown_gt:
        raise CosyError(f"GT objects {unknown_gt} have no model in {models_path}", path=models_path)
    tgt = ims24 = None  # BOP19 targets (bop19, auc, vivo); the images BOP24 evaluates
    if any(m in metrics for m in ("bop19", "auc", "vivo")):
        tgt, targets_desc = load_targets(ds, targets, gt, warn)
    if "bop24" in metrics:
        ims24, ims24_desc = load_bop24_images(ds, targets, gt, warn)
    if scene_ids is not None:
        keep = gt["scene_id"].isin(set(int(x) for x in scene_ids)).to_numpy()
        gt, T_gt = gt[keep].reset_index(drop=True), T_gt[keep]
        if tgt is not None:
            tgt = tgt[tgt["scene_id"].isin(set(int(x) for x in scene_ids))].reset_index(drop=True)
        if ims24 is not None:
            ims24 = ims24[ims24["scene_id"].isin(set(int(x) for x in scene_ids))].reset_index(drop=True)
    n_steps = continuous_steps_for_max_step(conf["max_sym_disc_step"])

    est = res.table[["scene_id", "im_id", "obj_id", "score"]].copy()
    est["est_index"] = np.arange(len(est))
    est_gt = est.merge(gt[["scene_id", "im_id", "obj_id", "gt_index"]].assign(gt_row=np.arange(len(gt))),
                       on=["scene_id", "im_id", "obj_id"], how="inner")
    est_gt = est_gt.sort_values(["est_index", "gt_index"], kind="stable").reset_index(drop=True)
    est_gt["est_row"] = est_gt["est_index"]
    K = np.stack([cams[(s, i)].K for s, i in zip(est_gt["scene_id"], est_gt["im_id"])]) if len(est_gt) \
        else np.zeros((0, 3, 3))
    log(f"evaluate: {len(est)} estimates, {len(gt)} GT instances, {len(est_gt)} (estimate, GT) pairs")
    T_est = res.T_cam_obj
    if oracle is not None:  # one pose per pair: the estimate with the oracle's part from that pair's GT
        T_est = oracle_poses.oracle_poses(oracle, T_est[est_gt["est_row"].to_numpy()], T_gt[est_gt["gt_row"].to_numpy()])
        est_gt["est_row"] = np.arange(len(est_gt))
        log(f"evaluate: oracle {oracle}: each estimate's {oracle_poses.PARTS[oracle]} from the GT it is compared with "
            "(a diagnostic, not a BOP score)")
    errs = compute_errors(est_gt, T_est, T_gt, K, db, n_steps, progress=progress)
    table = pd.concat([est_gt[["scene_id", "im_id", "obj_id", "est_index", "gt_index"]], errs], axis=1)

    scores: dict = {}
    with_vsd = False
    if "bop19" in metrics:
        ims = tgt[["scene_id", "im_id"]].drop_duplicates()
        missing = [(int(s), int(i)) for s, i in zip(ims["scene_id"], ims["im_id"]) if ds.depth_path(int(s), int(i)) is None]
        if not conf["vsd"]:
            warn("VSD switched off (--no-vsd): bop19_average_recall is null (see bop19_average_recall_mssd_mspd)")
        elif missing:
            warn(f"no depth image for {len(missing)} target image(s) (e.g. scene {missing[0][0]} image "
                 f"{missing[0][1]}): VSD skipped, bop19_average_recall is null (see bop19_average_recall_mssd_mspd)")
        else:
            with_vsd = True
            valid = protocols.bop19_valid_gt(gt, tgt)
            sel = protocols.top_estimates(est, tgt)
            vkeys = set(zip(*(valid.loc[valid["valid"], c] for c in ("scene_id", "im_id", "gt_index"))))
            mask = est_gt["est_index"].isin(set(sel["est_index"])).to_numpy() & np.array(
                [k in vkeys for k in zip(est_gt["scene_id"], est_gt["im_id"], est_gt["gt_index"])], dtype=bool)
            need = est_gt[mask]  # index = row of the errors table
            vsd_vals = compute_vsd(need, T_est, T_gt, cams, ds, db, conf["vsd_delta"], protocols.BOP19_VSD_TAUS,
                                   progress=progress)
            for k, tau in enumerate(protocols.BOP19_VSD_TAUS):
                col = np.full(len(table), np.nan)
                col[need.index.to_numpy()] = vsd_vals[:, k]
                table[protocols.vsd_column(tau)] = col
        widths = image_widths(ds, sorted(set(tgt["scene_id"])))
        b = protocols.bop19_scores(gt, tgt, est, table, {o: db[o].diameter for o in db.obj_ids}, widths,
                                   with_vsd=with_vsd)
        scores.update({k: b[k] for k in ("bop19_average_recall", "bop19_average_recall_vsd", "bop19_average_recall_mssd",
                                         "bop19_average_recall_mspd", "bop19_average_recall_mssd_mspd")})
        scores["bop19"] = {"targets": targets_desc, "counts": b["counts"], "curves": b["curves"],
                           "vsd_delta_mm": conf["vsd_delta"], "vsd_taus": protocols.BOP19_VSD_TAUS.tolist(),
                           "image_width_px": widths, "per_object": b["per_object"]}
        scores["bop19_ci"] = b["ci"]
    if "bop24" in metrics:
        widths24 = image_widths(ds, sorted(set(ims24["scene_id"])))
        cap = bop24_protocol.max_estimates_per_image(Path(dataset).resolve().name)
        b24 = bop24_protocol.bop24_scores(gt, ims24, est, table, {o: db[o].diameter for o in db.obj_ids}, widths24,
                                          max_per_image=cap)
        scores.update({k: b24[k] for k in BOP24_KEYS})
        scores["bop24"] = {"images": ims24_desc, "visib_gt_min": bop24_protocol.VISIB_GT_MIN,
                           "max_estimates_per_image": cap,
                           "counts": b24["counts"], "curves": b24["curves"], "image_width_px": widths24,
                           "per_object": b24["per_object"]}
        if not b24["counts"]["objects"]:
            warn(f"BOP24: no GT instance at least {bop24_protocol.VISIB_GT_MIN:.0%} visible in the evaluated images: "
                 "no AP")
    gt_err = gt[["scene_id", "im_id", "gt_index", "obj_id", "visib_fract"]].copy()
    if "auc" in metrics:
        ims = tgt[["scene_id", "im_id"]].drop_duplicates()
        gt_set = gt.merge(ims, on=["scene_id", "im_id"])
        a = protocols.auc_scores(gt_set, est.merge(ims, on=["scene_id", "im_id"]), table,
                                 {o: db[o].diameter for o in db.obj_ids}, {o: db[o].is_symmetric for o in db.obj_ids})
        e_adds = a.pop("errors_adds_mm")
        gt_err = gt_err.merge(gt_set[["scene_id", "im_id", "gt_index"]].assign(adds_top1_mm=e_adds),
                              on=["scene_id", "im_id", "gt_index"], how="left")
        scores.update({k: a[k] for k in ("auc_adds", "auc_add_or_adds", "auc_adds_pooled", "auc_add_or_adds_pooled",
                                         "recall_adds_0.1d")})
        scores["auc"] = {"images": "the target images", "counts": a["counts"], "per_object": a["per_object"]}
    if "vivo" in metrics:
        v = protocols.vivo_scores(gt, tgt, est, table, {o: db[o].diameter for o in db.obj_ids})
        scores.update({k: v[k] for k in ("vivo_auc_adds", "vivo_recall_adds_0.1d", "vivo_map_adds_0.1d")})
        scores["vivo"] = {"protocol": "CosyPose T-LESS ViVo meters (per-image BOP19 targets, ADD-S)",
                          "counts": v["counts"], "per_object": v["per_object"]}
        # the multi-view task: every object of the scene is a target in every image of it
        tgt_scene = protocols.scene_level_targets(gt, tgt[["scene_id", "im_id"]])
        vs = protocols.vivo_scores(gt, tgt_scene, est, table, {o: db[o].diameter for o in db.obj_ids})
        scores.update({f"{k}_scene_targets": vs[k]
                       for k in ("vivo_auc_adds", "vivo_recall_adds_0.1d", "vivo_map_adds_0.1d")})
        scores["vivo_scene_targets"] = {
            "protocol": "ViVo with multi-view targets: each object of the scene in every target image of it "
                        "(inst_count = its instances in the scene), visible or not", "counts": vs["counts"]}
    per_object: dict = {}
    for part in ("bop19", "bop24", "auc", "vivo"):
        for o, v in scores.get(part, {}).get("per_object", {}).items():
            per_object.setdefault(str(o), {}).update(v)
    scores["per_object"] = dict(sorted(per_object.items(), key=lambda kv: int(kv[0])))
    scores["counts"] = {"estimates": int(len(est)), "gt_instances": int(len(gt)), "pairs": int(len(est_gt))}
    if tgt is not None:
        scores["counts"].update({"targets": int(tgt["inst_count"].sum()),
                                 "target_images": int(len(tgt[["scene_id", "im_id"]].drop_duplicates()))})
    else:
        scores["counts"]["target_images"] = int(len(ims24))
    if scene_json is not None:
        groups = parse_scene_json(Path(scene_json), ds)
        gt_cams = {k: c.T_cam_world for k, c in cams.items() if c.T_cam_world is not None}
        for s in ds.scene_ids:  # views without GT objects still have cameras
            for im_id, c in ds.scene_camera(s).items():
                if c.T_cam_world is not None:
                    gt_cams[(s, im_id)] = c.T_cam_world
        reference, spread = "scene_camera", {}
        if not gt_cams:  # LM-O: the cameras the GT objects imply (a static scene assumed)
            gt_cams, spread = protocols.cameras_from_gt_objects(gt, T_gt)
            reference = "gt_objects"
            if gt_cams:
                warn("no GT camera poses (cam_R_w2c/cam_t_w2c) in scene_camera.json: camera errors against the "
                     "cameras the GT object poses imply (static scenes assumed; scores.json cameras.gt_objects_spread_mm "
                     "says how far each view's objects agree)")
            else:
                warn("no GT camera poses (cam_R_w2c/cam_t_w2c) in scene_camera.json and no object seen in two views: "
                     "only the fraction of views placed")
        scores["cameras"] = protocols.camera_pose_errors(groups, gt_cams)
        scores["cameras"]["reference"] = reference
        if spread:
            v = np.array(list(spread.values()))
            scores["cameras"]["gt_objects_spread_mm"] = {"median": float(np.median(v)), "max": float(v.max()),
                                                         "views": int(len(v))}
    if oracle is not None:
        scores["oracle"] = {"kind": oracle, "what": f"each estimate's {oracle_poses.PARTS[oracle]} taken from the GT "
                            "instance it is compared with: a diagnostic, not a BOP score"}
    scores["warnings"] = warnings
    scores["models_dir"] = str(models_path)
    scores["symmetry_steps"] = n_steps
    scores["inputs"] = inputs
    scores["seconds"] = round(time.time() - t0, 3)

    from . import plots

    with atomic.atomic_dir(out, overwrite=overwrite) as tmp:
        write_errors_csv(tmp / "errors.csv", table)
        curves = plots.curves_table(scores, gt_err, {o: db[o].diameter for o in db.obj_ids})
        curves.to_csv(tmp / "curves.csv", index=False)
        gt_err.to_csv(tmp / "gt_errors.csv", index=False)
        plots.write_report(tmp / "report.png", scores, curves, gt_err, {o: db[o].diameter for o in db.obj_ids})
        atomic.write_json(tmp / "scores.json", _clean(scores))
        manifest.write_folder_manifest(tmp, "cosy evaluate", OUTPUT_FILES)
    for k in ("bop19_average_recall", "bop19_average_recall_vsd", "bop19_average_recall_mssd",
              "bop19_average_recall_mspd", "bop19_average_recall_mssd_mspd", *BOP24_KEYS, "auc_adds", "auc_add_or_adds",
              "recall_adds_0.1d", "vivo_auc_adds", "vivo_recall_adds_0.1d", "vivo_map_adds_0.1d",
              "vivo_auc_adds_scene_targets", "vivo_recall_adds_0.1d_scene_targets", "vivo_map_adds_0.1d_scene_targets"):
        if k in scores:
            v = scores[k]
            b_ci = scores.get("bop19_ci", {})
            ci = b_ci.get(k)
            log(f"  {k}: {'n/a' if v is None or (isinstance(v, float) and not math.isfinite(v)) else f'{v:.4f}'}"
                + (f"  ({b_ci['level']:.0%} interval {ci[0]:.3f}-{ci[1]:.3f} over {b_ci['units']} {b_ci['unit']}s)"
                   if ci and v is not None else ""))
    log(f"evaluate: wrote {out} in {time.time() - t0:.1f} s")
    return _clean(scores)


def write_errors_csv(path: Path, table: pd.DataFrame) -> None:
    """errors.csv with ids as integers and errors with 6 decimals (empty = not computed)."""
    t = table.copy()
    fmt = {c: "{:.6f}" for c in t.columns if c not in ("scene_id", "im_id", "obj_id", "est_index", "gt_index")}
    lines = [",".join(t.columns)]
    cols = [t[c].to_numpy() for c in t.columns]
    for row in zip(*cols):
        parts = []
        for c, v in zip(t.columns, row):
            if c in fmt:
                parts.append("" if not np.isfinite(v) else fmt[c].format(v))
            else:
                parts.append(str(int(v)))
        lines.append(",".join(parts))
    atomic.write_text(path, "\n".join(lines) + "\n")
