"""Paper-style figures of one group of views of a ``cosy run`` (CosyPose Fig. 1 / Fig. 5 style).

One PNG per group (:func:`group_figure`):

* row 1 - each input view with its single-view candidates drawn as object contours (silhouettes
  rendered at the candidate poses with the dataset intrinsics), coloured by the physical object
  that ``cosy match`` assigned them to; discarded candidates thin, dashed and red;
* row 2 - the same views with the refined scene of ``cosy refine`` re-projected through each
  placed camera (``T_cam_obj = inv(T_world_cam) @ T_world_obj``): a shaded render blended over
  the image and the contours of each object's visible region; views that could not be placed are
  dimmed and marked; the row is left out when the scene has no refine output;
* row 3 - a top view of the recovered cameras (frusta, labelled by im_id) and objects (footprints:
  convex hull of the model seen from above, labelled by obj_id), looking down the scene's up
  direction (the normal of the plane the objects rest on, else the cameras' mean up; the title
  says which, see :mod:`cosy_cli.viz.topview`), in mm with the gauge camera at the origin, the
  gauge camera's right along +x; with the ground truth aligned through the gauge camera (dashed)
  when the dataset has it, and a legend with the group's numbers.

Views wrap after ``max_cols`` per row (a candidates row above its refined row, chunk by chunk).
Images are downscaled to the panel size, so a figure of 8 views stays under ~1.5 MB (it is
re-encoded with a 256-colour palette when it would not).

The run folder layout read here is the one ``cosy run`` writes (see :mod:`cosy_cli.viz`).
Lengths in mm, poses ``T_a_b`` (4x4), OpenCV cameras.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import CosyError
from ..geometry.poses import invert
from ..io import atomic, bop
from ..io.dataset import BopDataset
from ..lifetime import Closing
from ..pipeline.layout import MANIFEST, RUN_FORMAT, scene_dir
from .topview import SUPPORT_PLANE, top_view_frame

MAX_PNG_BYTES = 1_500_000
PANEL_WIDTH_IN = 1.75  # inches per view panel
DPI = 150
DISCARDED_COLOR = "#e41a1c"
CAMERA_COLOR = "#1b2a49"
GT_COLOR = "#444444"
# Qualitative palette without red (red marks discarded candidates): tab10 minus red and grey,
# then the light halves of tab20 for groups with many objects.
PALETTE = ["#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#bcbd22", "#17becf",
           "#aec7e8", "#ffbb78", "#98df8a", "#c5b0d5", "#c49c94", "#f7b6d2", "#dbdb8d", "#9edae5"]


def object_color(object_id: int) -> str:
    """The colour of physical object ``object_id`` (>= 0) of a group; discarded (-1): red."""
    if object_id < 0:
        return DISCARDED_COLOR
    return PALETTE[int(object_id) % len(PALETTE)]


def _rgb01(color: str) -> np.ndarray:
    from matplotlib.colors import to_rgb

    return np.array(to_rgb(color))


# --------------------------------------------------------------------------------------------
# the run folder
# --------------------------------------------------------------------------------------------

def read_run(run_dir: str | Path) -> dict:
    """``RUN_DIR/run.json`` checked: a dict with at least dataset (a Path that exists), split and
    scene_ids (list of int). Raises :class:`CosyError` naming the file and what was expected."""
    run_dir = Path(run_dir)
    path = run_dir / MANIFEST
    if not run_dir.is_dir():
        raise CosyError("run folder not found (expected the output folder of cosy run)", path=run_dir)
    if not path.is_file():
        raise CosyError("not a cosy run folder: run.json is missing (expected the output folder of cosy run)",
                        path=run_dir)
    doc = _load_json(path, "the manifest of cosy run")
    if "format" in doc and doc["format"] != RUN_FORMAT[0]:
        raise CosyError(f"expected format {RUN_FORMAT[0]!r}, got {doc['format']!r}", path=path)
    for k in ("dataset", "split", "scene_ids"):
        if k not in doc:
            raise CosyError(f"missing key {k!r} (expected dataset, split, scene_ids)", path=path)
    ids = doc["scene_ids"]
    if not isinstance(ids, list) or not all(isinstance(s, int) and not isinstance(s, bool) for s in ids):
        raise CosyError(f"scene_ids: expected a list of integers, got {ids!r}", path=path)
    if not isinstance(doc["split"], str):
        raise CosyError(f"split: expected a string, got {doc['split']!r}", path=path)
    ds = Path(doc["dataset"])
    if not ds.is_absolute() and not ds.is_dir():
        ds = run_dir / ds
    if not ds.is_dir():
        raise CosyError(f"the dataset of this run is not found: {doc['dataset']}", path=path, where="dataset")
    out = dict(doc)
    out["dataset"] = ds
    return out


def _load_json(path: Path, what: str = "") -> dict | None:
    """The JSON object in ``path`` (None when there is no such file); CosyError when unreadable."""
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CosyError(f"cannot read ({e})", path=path) from None
    if not isinstance(doc, dict):
        raise CosyError("expected a JSON object" + (f" ({what})" if what else ""), path=path)
    return doc


def _refine_doc(run_dir: Path, scene_id: int) -> dict | None:
    """scene.json of the scene (its own refine output, else the run's merged one), or None."""
    for p in (scene_dir(run_dir, scene_id) / "refine" / "scene.json", Path(run_dir) / "refine" / "scene.json"):
        doc = _load_json(p)
        groups = doc.get("groups") if doc is not None else None
        if isinstance(groups, list) and any(isinstance(g, dict) and g.get("scene_id") == int(scene_id) for g in groups):
            return doc
    return None


def _match_doc(run_dir: Path, scene_id: int) -> dict | None:
    return _load_json(scene_dir(run_dir, scene_id) / "match" / "groups.json")


def input_files(run_dir: str | Path, scene_id: int) -> list[Path]:
    """The files a scene's figures are made from (for staleness checks)."""
    d = scene_dir(run_dir, scene_id)
    paths = [d / "candidates.csv", d / "match" / "groups.json", d / "match" / "matches.csv",
             d / "match" / "candidates.csv", d / "refine" / "scene.json"]
    return [p for p in paths if p.is_file()]


def scene_group_ids(run_dir: str | Path, scene_id: int) -> list[int]:
    """Group ids of a scene: from its refine output, else its match output, else [0] when it has
    candidates (one group of all its images), else [] (nothing to draw yet)."""
    run_dir = Path(run_dir)
    ids: set[int] = set()
    for doc in (_refine_doc(run_dir, scene_id), _match_doc(run_dir, scene_id)):
        if doc is not None:
            try:
                ids |= {int(g["group_id"]) for g in doc.get("groups", [])
                        if int(g.get("scene_id", -1)) == int(scene_id)}
            except (KeyError, TypeError, ValueError, AttributeError) as e:
                raise CosyError(f"unexpected content in the match/refine outputs ({type(e).__name__}: {e})",
                                path=scene_dir(run_dir, scene_id)) from None
    if ids or _match_doc(run_dir, scene_id) is not None:
        return sorted(ids)  # match ran: its groups (none when the scene had no candidates)
    cpath = _candidates_path(run_dir, scene_id)
    if cpath is None:
        return []
    tab = bop.read_results(cpath, check_rotations=False).table
    return [0] if (tab["scene_id"] == int(scene_id)).any() else []


def _candidates_path(run_dir: Path, scene_id: int) -> Path | None:
    d = scene_dir(run_dir, scene_id)
    for p in (d / "match" / "candidates.csv", d / "candidates.csv"):
        if p.is_file():
            return p
    return None


# --------------------------------------------------------------------------------------------
# one group's data
# --------------------------------------------------------------------------------------------

@dataclass
class ViewData:
    """One view of a group: camera, image and candidates (poses T_cam_obj in mm)."""

    im_id: int
    K: np.ndarray  # (3, 3) pixels
    size: tuple[int, int]  # (width, height) pixels
    cand_obj_ids: np.ndarray  # (n,) labels
    cand_T: np.ndarray  # (n, 4, 4) T_cam_obj, mm
    cand_object: np.ndarray  # (n,) physical object of the group (match), -1: discarded
    cand_score: np.ndarray  # (n,)
    T_world_cam: np.ndarray | None = None  # refined camera; None: unplaced or no refine output


@dataclass
class GroupData:
    """Everything the figure of one group shows. ``objects``: refined objects, dicts with
    object_id, obj_id, T_world_obj (4x4 mm), n_candidates, reprojection_error_px."""

    scene_id: int
    group_id: int
    dataset: BopDataset
    views: list[ViewData]
    matched: bool  # match output present (candidates coloured by physical object)
    refined: bool  # refine output present
    objects: list[dict] = field(default_factory=list)
    match_objects: dict = field(default_factory=dict)  # object_id -> obj_id (match)
    unplaced_im_ids: list[int] = field(default_factory=list)
    gauge_im_id: int | None = None
    known_cameras: bool = False
    stats: dict = field(default_factory=dict)

    @property
    def im_ids(self) -> list[int]:
        return [v.im_id for v in self.views]


def _find_group(doc: dict | None, scene_id: int, group_id: int) -> dict | None:
    if doc is None:
        return None
    return next((g for g in doc.get("groups", [])
                 if int(g["scene_id"]) == scene_id and int(g["group_id"]) == group_id), None)


def load_group(run_dir: str | Path, scene_id: int, group_id: int, dataset: BopDataset | None = None) -> GroupData:
    """Read the candidates, match and refine outputs of one group of ``run_dir``."""
    try:
        return _load_group(Path(run_dir), scene_id, group_id, dataset)
    except (KeyError, TypeError, ValueError, IndexError) as e:
        raise CosyError(f"unexpected content in the match/refine outputs of scene {int(scene_id)} "
                        f"({type(e).__name__}: {e})", path=scene_dir(run_dir, scene_id)) from None


def _load_group(run_dir: Path, scene_id: int, group_id: int, dataset: BopDataset | None) -> GroupData:
    if dataset is None:
        run = read_run(run_dir)
        dataset = BopDataset(run["dataset"], run["split"])
    s, gid = int(scene_id), int(group_id)
    cpath = _candidates_path(run_dir, s)
    if cpath is None:
        raise CosyError(f"scene {s} has no candidates yet (expected scenes/{s:06d}/candidates.csv)", path=run_dir)
    cands = bop.read_results(cpath)
    tab = cands.table
    n = len(cands)
    c_scene = tab["scene_id"].to_numpy()
    c_im = tab["im_id"].to_numpy()
    object_id = np.full(n, -1, dtype=np.int64)
    in_group = c_scene == s

    mdoc = _match_doc(run_dir, s)
    rdoc = _refine_doc(run_dir, s)
    mgroup, rgroup = _find_group(mdoc, s, gid), _find_group(rdoc, s, gid)
    if mgroup is None and rgroup is None and gid != 0:
        raise CosyError(f"scene {s} has no group {gid} (groups: {scene_group_ids(run_dir, s)})", path=run_dir)

    match_objects: dict[int, int] = {}
    if mgroup is not None:
        in_group = np.zeros(n, dtype=bool)
        for o in mgroup.get("objects", []):
            ids = np.asarray(o["cand_ids"], dtype=np.int64)
            ids = ids[(ids >= 0) & (ids < n)]
            object_id[ids] = int(o["object_id"])
            in_group[ids] = True
            match_objects[int(o["object_id"])] = int(o["obj_id"])
        disc = np.asarray(mgroup.get("discarded", []), dtype=np.int64)
        in_group[disc[(disc >= 0) & (disc < n)]] = True
        im_ids = [int(i) for i in mgroup["im_ids"]]
    elif rgroup is not None:
        im_ids = sorted({int(c["im_id"]) for c in rgroup["cameras"]}
                        | {int(i) for i in rgroup.get("unplaced_im_ids", [])})
    else:
        im_ids = sorted({int(i) for i in c_im[in_group]})
    in_group &= np.isin(c_im, im_ids)

    cams = dataset.scene_camera(s)
    missing = [i for i in im_ids if i not in cams]
    if missing:
        raise CosyError(f"image {missing[0]} of scene {s} is not in the dataset's scene_camera.json",
                        path=dataset.scene_file(s, "scene_camera"))
    placed: dict[int, np.ndarray] = {}
    objects: list[dict] = []
    if rgroup is not None:
        placed = {int(c["im_id"]): np.asarray(c["T_world_cam"], dtype=np.float64) for c in rgroup["cameras"]}
        for o in rgroup.get("objects", []):
            objects.append({"object_id": int(o.get("object_id", len(objects))), "obj_id": int(o["obj_id"]),
                            "T_world_obj": np.asarray(o["T_world_obj"], dtype=np.float64),
                            "n_candidates": int(o.get("n_candidates", 0)),
                            "reprojection_error_px": o.get("reprojection_error_px"),
                            "merged_object_ids": [int(m) for m in o.get("merged_object_ids", [])],
                            "rematched": bool(o.get("rematched", False)),
                            "cand_ids": [int(c) for c in o.get("cand_ids", [])]})
        # candidates of objects merged by refine take the colour of the object they were merged into;
        # candidates match discarded and refine re-matched into an object take that object's colour
        for o in objects:
            for m in o["merged_object_ids"]:
                object_id[(object_id == m) & in_group] = o["object_id"]
            if o["rematched"]:
                ids = np.asarray(o["cand_ids"], dtype=np.int64)
                ids = ids[(ids >= 0) & (ids < n)]
                object_id[ids[in_group[ids]]] = o["object_id"]

    views = []
    T_all = cands.T_cam_obj
    for i in im_ids:
        sel = np.flatnonzero(in_group & (c_im == i))
        sel = sel[np.argsort(-tab["score"].to_numpy()[sel], kind="stable")]
        size = dataset.image_size(s, i)  # checked against the camera file / cam_K
        views.append(ViewData(im_id=i, K=cams[i].K, size=size, cand_obj_ids=tab["obj_id"].to_numpy()[sel],
                              cand_T=T_all[sel], cand_object=object_id[sel] if mgroup is not None else
                              np.zeros(len(sel), dtype=np.int64) - 2, cand_score=tab["score"].to_numpy()[sel],
                              T_world_cam=placed.get(i)))
    return GroupData(
        scene_id=s, group_id=gid, dataset=dataset, views=views, matched=mgroup is not None,
        refined=rgroup is not None, objects=objects, match_objects=match_objects,
        unplaced_im_ids=[int(i) for i in rgroup.get("unplaced_im_ids", [])] if rgroup is not None else [],
        gauge_im_id=(None if rgroup is None or rgroup.get("gauge_im_id") is None else int(rgroup["gauge_im_id"])),
        known_cameras=bool(rdoc.get("known_cameras", False)) if rdoc is not None else False,
        stats=dict(rgroup.get("stats", {})) if rgroup is not None else {},
    )


# --------------------------------------------------------------------------------------------
# rendering
# --------------------------------------------------------------------------------------------

class MeshRenderer(Closing):
    """A :class:`~cosy_cli.rendering.SceneRenderer` that loads a dataset's meshes on demand.
    Use as a context manager (or call :meth:`close`)."""

    def __init__(self, dataset: BopDataset):
        self.dataset = dataset
        self._renderer = None
        self.meshes: dict[int, object] = {}

    def mesh(self, obj_id: int):
        from ..objects.database import load_mesh

        obj_id = int(obj_id)
        if obj_id not in self.meshes:
            self.meshes[obj_id] = load_mesh(self.dataset.model_path(obj_id))
        return self.meshes[obj_id]

    def renderer(self, obj_ids):
        if self._renderer is None:
            from ..rendering import SceneRenderer

            self._renderer = SceneRenderer({}, 640, 480)
        for o in {int(o) for o in obj_ids}:
            if o not in self._renderer.obj_ids:
                self._renderer.add_mesh(o, self.mesh(o))
        return self._renderer

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


@dataclass
class ViewRender:
    silhouettes: np.ndarray  # (n, H, W) bool: candidate silhouettes (each alone)
    rgb: np.ndarray | None = None  # (H, W, 3) uint8: refined scene, shaded in object colours
    instance: np.ndarray | None = None  # (H, W) int: index into GroupData.objects, -1 none


def render_view(mr: MeshRenderer, data: GroupData, view: ViewData) -> ViewRender:
    """Candidate silhouettes and (when the view is placed) the refined scene seen by ``view``."""
    w, h = view.size
    sil = np.zeros((0, h, w), dtype=bool)
    if len(view.cand_obj_ids):
        r = mr.renderer(view.cand_obj_ids)
        sil = r.render_silhouettes(view.K, view.cand_obj_ids, view.cand_T, size=(w, h))
    out = ViewRender(sil)
    if view.T_world_cam is not None and data.objects:
        ids = [o["obj_id"] for o in data.objects]
        T_world_obj = np.stack([o["T_world_obj"] for o in data.objects])
        T_cam_obj = invert(view.T_world_cam)[None] @ T_world_obj
        colors = np.stack([_rgb01(object_color(o["object_id"])) for o in data.objects])
        res = mr.renderer(ids).render(view.K, ids, T_cam_obj, colors=colors, size=(w, h), ambient=0.45)
        out.rgb, out.instance = res.rgb, res.instance
    return out


def visible_mask_ious(instance: np.ndarray, inst_obj_ids, gt_masks: np.ndarray, gt_obj_ids) -> np.ndarray:
    """IoU of each GT visible mask with the best-overlapping rendered visible region of the same label.

    instance: (H, W) int, index i into ``inst_obj_ids`` of the visible rendered instance (-1 none);
    gt_masks: (m, H, W) bool visible masks with labels ``gt_obj_ids`` (m,). Returns (m,) IoUs in
    [0, 1] (0 when no rendered instance of that label overlaps)."""
    inst_obj_ids = np.asarray(inst_obj_ids, dtype=np.int64).reshape(-1)
    gt_obj_ids = np.asarray(gt_obj_ids, dtype=np.int64).reshape(-1)
    n, m = len(inst_obj_ids), len(gt_obj_ids)
    if n == 0 or m == 0:
        return np.zeros(m)
    gt = np.asarray(gt_masks, dtype=bool).reshape(m, -1)
    inst = np.asarray(instance).reshape(-1).astype(np.int64)
    if inst.shape[0] != gt.shape[1]:
        raise ValueError(f"instance map has {inst.shape[0]} pixels, GT masks {gt.shape[1]}")
    if inst.max() >= n:
        raise ValueError(f"instance map holds index {inst.max()} but only {n} instance labels were given")
    valid = inst >= 0
    gi, pi = np.nonzero(gt[:, valid])  # GT pixels that show a rendered instance
    inter = np.bincount(gi * n + inst[valid][pi], minlength=m * n).reshape(m, n).astype(np.float64)
    area_inst = np.bincount(inst[valid], minlength=n)[:n].astype(np.float64)
    union = gt.sum(1, dtype=np.float64)[:, None] + area_inst[None] - inter
    iou = np.where(union > 0, inter / np.maximum(union, 1), 0.0)
    iou[gt_obj_ids[:, None] != inst_obj_ids[None]] = 0.0
    return iou.max(axis=1)


def _gt_visible_masks(data: GroupData, im_id: int, min_visib: float = 0.1):
    """(masks (m, H, W) bool, obj_ids (m,), gt indices) of the GT instances visible in a view,
    or None when the dataset has no GT masks for it."""
    ds, s = data.dataset, data.scene_id
    if not ds.has_gt(s):
        return None
    gts = ds.scene_gt(s).get(im_id, [])
    info = ds.scene_gt_info(s).get(im_id) if ds.scene_file(s, "scene_gt_info").is_file() else None
    keep = [k for k in range(len(gts)) if info is None or k >= len(info) or info[k].visib_fract >= min_visib]
    paths = [ds.mask_path(s, im_id, k, visib=True) for k in keep]
    if not keep or not all(p.is_file() for p in paths):
        return None
    masks = np.stack([ds.read_mask(s, im_id, k, visib=True) for k in keep])  # checked: image size
    return masks, np.array([gts[k].obj_id for k in keep]), keep


def group_reprojection_ious(data: GroupData, renders: dict[int, ViewRender]) -> list[dict]:
    """Per (placed view, visible GT instance): IoU of the GT visible mask with the re-projected
    refined object of the same label (:func:`visible_mask_ious`). Empty without GT masks."""
    rows = []
    if not data.objects:
        return rows
    ids = [o["obj_id"] for o in data.objects]
    for v in data.views:
        r = renders.get(v.im_id)
        if r is None or r.instance is None:
            continue
        gt = _gt_visible_masks(data, v.im_id)
        if gt is None:
            continue
        masks, gt_ids, keep = gt
        if masks.shape[1:] != r.instance.shape:
            continue
        iou = visible_mask_ious(r.instance, ids, masks, gt_ids)
        rows += [{"im_id": v.im_id, "gt_index": int(k), "obj_id": int(o), "iou": float(x)}
                 for k, o, x in zip(keep, gt_ids, iou)]
    return rows


def reprojection_ious(run_dir: str | Path, scene_id: int, group_id: int = 0) -> list[dict]:
    """:func:`group_reprojection_ious` of one group of a run (renders it)."""
    data = load_group(run_dir, scene_id, group_id)
    with MeshRenderer(data.dataset) as mr:
        renders = {v.im_id: render_view(mr, data, v) for v in data.views if v.T_world_cam is not None}
        return group_reprojection_ious(data, renders)


# --------------------------------------------------------------------------------------------
# ground truth in the recovered frame
# --------------------------------------------------------------------------------------------

def gt_in_group_frame(data: GroupData) -> tuple[dict[int, np.ndarray], list[tuple[int, np.ndarray]]]:
    """GT cameras {im_id: T_world_cam} and objects [(obj_id, T_world_obj)] of the group's views,
    expressed in the group's recovered world frame (mm).

    Without known cameras the recovered world is the gauge camera's frame; GT is aligned by
    the gauge camera: ``T_rec_gtworld = T_world_cam_rec[gauge] @ T_cam_world_gt[gauge]``. With
    known cameras the recovered world is the dataset's. Objects seen in several views are listed
    once (same label, centres within a fifth of the diameter). Without GT camera poses only the
    objects seen by the gauge view are given. Empty when the dataset has no GT."""
    ds, s = data.dataset, data.scene_id
    cams = ds.scene_camera(s)
    placed = {v.im_id: v.T_world_cam for v in data.views if v.T_world_cam is not None}
    if not placed:
        return {}, []
    have_poses = all(cams[i].T_cam_world is not None for i in data.im_ids)
    if data.known_cameras:
        A = np.eye(4)
    else:
        g = data.gauge_im_id if data.gauge_im_id in placed else next(iter(placed))
        if have_poses:
            A = placed[g] @ cams[g].T_cam_world
        else:
            A = None
    gt_cams: dict[int, np.ndarray] = {}
    if have_poses and A is not None:
        gt_cams = {i: A @ invert(cams[i].T_cam_world) for i in data.im_ids}
    objs: list[tuple[int, np.ndarray]] = []
    if not ds.has_gt(s):
        return gt_cams, objs
    gt = ds.scene_gt(s)
    infos = ds.models_info()
    if gt_cams:
        sources = [(i, gt_cams[i]) for i in data.im_ids]
    else:
        g = data.gauge_im_id if data.gauge_im_id in placed else next(iter(placed))
        sources = [(g, placed[g])]
    for i, T_world_cam in sources:
        for inst in gt.get(i, []):
            T = T_world_cam @ inst.T_cam_obj
            diam = infos[inst.obj_id].diameter if inst.obj_id in infos else 50.0
            if any(o == inst.obj_id and np.linalg.norm(T0[:3, 3] - T[:3, 3]) < 0.2 * diam for o, T0 in objs):
                continue
            objs.append((int(inst.obj_id), T))
    return gt_cams, objs


# --------------------------------------------------------------------------------------------
# drawing
# --------------------------------------------------------------------------------------------

def _contours(mask: np.ndarray, min_area: float = 15.0) -> list[np.ndarray]:
    """Outer boundaries of a bool mask as (k, 2) arrays of pixel coordinates (x, y), closed."""
    import cv2

    cs, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    out = []
    for c in cs:
        if len(c) < 3 or cv2.contourArea(c) < min_area:
            continue
        c = c[:, 0, :].astype(np.float64)
        out.append(np.vstack([c, c[:1]]))
    return out


def _downscale(img: np.ndarray, width_px: int) -> np.ndarray:
    import cv2

    h, w = img.shape[:2]
    if w <= width_px:
        return img
    return cv2.resize(img, (width_px, max(1, round(h * width_px / w))), interpolation=cv2.INTER_AREA)


def _outline(lw: float):
    import matplotlib.patheffects as pe

    return [pe.Stroke(linewidth=lw + 1.3, foreground="black", alpha=0.75), pe.Normal()]


def _label(ax, x, y, text, color, fontsize=6.0):
    lum = float(_rgb01(color) @ np.array([0.299, 0.587, 0.114]))
    ax.text(x, y, text, color="black" if lum > 0.65 else "white", fontsize=fontsize,
            ha="center", va="center", fontweight="bold", zorder=5,
            bbox=dict(boxstyle="round,pad=0.15", facecolor=color, edgecolor="black", linewidth=0.4, alpha=0.9))


def _image_axes(ax, img_small, size):
    w, h = size
    ax.imshow(img_small, extent=(-0.5, w - 0.5, h - 0.5, -0.5), interpolation="antialiased")
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_xticks([])
    ax.set_yticks([])
    for sp in ax.spines.values():
        sp.set_linewidth(0.5)


def _draw_candidates(ax, view: ViewData, render: ViewRender, matched: bool):
    order = np.argsort(view.cand_object >= 0, kind="stable")  # discarded first, under the others
    for k in order:
        cs = _contours(render.silhouettes[k])
        if not cs:
            continue
        obj = int(view.cand_object[k])
        if not matched:
            color, lw, ls = PALETTE[int(view.cand_obj_ids[k]) % len(PALETTE)], 1.1, "-"
        elif obj < 0:
            color, lw, ls = DISCARDED_COLOR, 0.7, (0, (2.5, 1.5))
        else:
            color, lw, ls = object_color(obj), 1.1, "-"
        for c in cs:
            ax.plot(c[:, 0], c[:, 1], color=color, lw=lw, ls=ls, path_effects=_outline(lw), zorder=3)
        ys, xs = np.nonzero(render.silhouettes[k])
        if len(xs):
            _label(ax, float(np.median(xs)), float(np.median(ys)), str(int(view.cand_obj_ids[k])), color,
                   fontsize=5.0 if obj < 0 and matched else 5.5)


def _draw_refined(ax, data: GroupData, view: ViewData, render: ViewRender):
    for j, o in enumerate(data.objects):
        m = render.instance == j
        if m.sum() < 15:
            continue
        color = object_color(o["object_id"])
        for c in _contours(m):
            ax.plot(c[:, 0], c[:, 1], color=color, lw=1.1, path_effects=_outline(1.1), zorder=3)
        ys, xs = np.nonzero(m)
        # label on a pixel of the region (median of a region can fall outside an L shape)
        k = np.argmin((xs - np.median(xs)) ** 2 + (ys - np.median(ys)) ** 2)
        _label(ax, float(xs[k]), float(ys[k]), str(o["obj_id"]), color, fontsize=5.5)


def _blend(img: np.ndarray, render: ViewRender, alpha: float = 0.55) -> np.ndarray:
    out = img.astype(np.float32)
    m = render.instance >= 0
    out[m] = (1 - alpha) * out[m] + alpha * render.rgb[m].astype(np.float32)
    return np.clip(out, 0, 255).astype(np.uint8)


def _footprint(points_world: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Convex hull (closed polygon (k, 2)) of points projected by P (2, 3)."""
    from scipy.spatial import ConvexHull, QhullError

    xy = points_world @ P.T
    try:
        hull = ConvexHull(xy)
        poly = xy[hull.vertices]
    except (QhullError, ValueError):
        poly = xy[:1]
    return np.vstack([poly, poly[:1]])


def _frustum_lines(T_world_cam, K, size, depth, P):
    w, h = size
    corners = np.array([[-0.5, -0.5, 1], [w - 0.5, -0.5, 1], [w - 0.5, h - 0.5, 1], [-0.5, h - 0.5, 1]])
    rays = corners @ np.linalg.inv(K).T
    X = depth * rays / rays[:, 2:3]
    Xw = X @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    c = T_world_cam[:3, 3] @ P.T
    q = Xw @ P.T
    return c, q


LABEL_BOX = dict(boxstyle="round,pad=0.15", facecolor="white", edgecolor="none", alpha=0.75)


def _clusters(points: list[np.ndarray], dist: float) -> list[list[int]]:
    """Indices of ``points`` grouped greedily: a point joins the first group whose first point is
    within ``dist``."""
    groups: list[list[int]] = []
    for k, p in enumerate(points):
        for g in groups:
            if np.linalg.norm(points[g[0]] - p) <= dist:
                g.append(k)
                break
        else:
            groups.append([k])
    return groups


def _id_list(ids: list[int]) -> str:
    """'1, 2, 6–10' for [1, 2, 6, 7, 8, 9, 10]."""
    out, k = [], 0
    ids = sorted(ids)
    while k < len(ids):
        j = k
        while j + 1 < len(ids) and ids[j + 1] == ids[j] + 1:
            j += 1
        out.append(f"{ids[k]}–{ids[j]}" if j >= k + 2 else ", ".join(map(str, ids[k:j + 1])))
        k = j + 1
    return ", ".join(out)


def _wrap(text: str, width: int) -> str:
    import textwrap

    return "\n".join(textwrap.wrap(text, width, break_on_hyphens=False)) or text


def _draw_top_view(ax, data: GroupData, mr: MeshRenderer, legend_ax=None):
    cams = {v.im_id: v.T_world_cam for v in data.views if v.T_world_cam is not None}
    views = {v.im_id: v for v in data.views}
    objs = data.objects
    gt_cams, gt_objs = gt_in_group_frame(data)
    pts = []

    def model_pts(obj_id):
        V = np.asarray(mr.mesh(obj_id).vertices, dtype=np.float64)
        if len(V) > 3000:
            V = V[np.random.default_rng(0).choice(len(V), 3000, replace=False)]
        return V

    def posed(obj_id, T):
        return model_pts(obj_id) @ T[:3, :3].T + T[:3, 3]

    # up: the plane the refined objects rest on, else the one the GT objects rest on, else the cameras'
    cam_ids = sorted(cams) or sorted(gt_cams)
    cam_list = [cams[i] for i in cam_ids] if cams else [gt_cams[i] for i in cam_ids]
    ref_id = data.gauge_im_id if data.gauge_im_id in cam_ids else (cam_ids[0] if cam_ids else None)
    ref = cam_ids.index(ref_id) if ref_id is not None else 0
    frame3 = top_view_frame(cam_list, [posed(o["obj_id"], o["T_world_obj"]) for o in objs], ref=ref)
    gt_plane = False
    if frame3.source != SUPPORT_PLANE and gt_objs:
        f_gt = top_view_frame(cam_list, [posed(oid, T) for oid, T in gt_objs], ref=ref)
        if f_gt.source == SUPPORT_PLANE:
            frame3, gt_plane = f_gt, True
    P = frame3.P

    centres = [o["T_world_obj"][:3, 3] for o in objs] + [T[:3, 3] for _, T in gt_objs]
    centre = np.mean(centres, 0) if centres else np.zeros(3)
    dists = [np.linalg.norm(T[:3, 3] - centre) for T in list(cams.values()) + list(gt_cams.values())]
    depth = 0.18 * (np.median(dists) if dists else 500.0)

    for obj_id, T in gt_objs:
        poly = _footprint(posed(obj_id, T), P)
        ax.plot(poly[:, 0], poly[:, 1], color=GT_COLOR, lw=0.9, ls=(0, (3, 2)), zorder=2)
        pts.append(poly)
    for o in objs:
        T = o["T_world_obj"]
        color = object_color(o["object_id"])
        poly = _footprint(posed(o["obj_id"], T), P)
        ax.fill(poly[:, 0], poly[:, 1], color=color, alpha=0.45, lw=0, zorder=3)
        ax.plot(poly[:, 0], poly[:, 1], color=color, lw=1.2, zorder=4, path_effects=_outline(1.2))
        c = T[:3, 3] @ P.T
        _label(ax, c[0], c[1], str(o["obj_id"]), color, fontsize=7)
        pts.append(poly)
    labels = []  # (camera centre in the plot, im_id, placed)
    for i, T in gt_cams.items():
        c, q = _frustum_lines(T, views[i].K, views[i].size, depth, P)
        for k in range(4):
            ax.plot([c[0], q[k, 0]], [c[1], q[k, 1]], color=GT_COLOR, lw=0.7, ls=(0, (3, 2)), zorder=2)
        ax.plot(np.r_[q[:, 0], q[0, 0]], np.r_[q[:, 1], q[0, 1]], color=GT_COLOR, lw=0.7, ls=(0, (3, 2)), zorder=2)
        pts.append(np.vstack([c, q]))
        if i not in cams:  # a view the pipeline could not place: only its GT camera is drawn
            labels.append((c, i, False))
    for i, T in cams.items():
        c, q = _frustum_lines(T, views[i].K, views[i].size, depth, P)
        lw = 1.5 if i == data.gauge_im_id else 1.0
        for k in range(4):
            ax.plot([c[0], q[k, 0]], [c[1], q[k, 1]], color=CAMERA_COLOR, lw=lw, zorder=5)
        ax.fill(q[:, 0], q[:, 1], color=CAMERA_COLOR, alpha=0.12, lw=0, zorder=4)
        ax.plot(np.r_[q[:, 0], q[0, 0]], np.r_[q[:, 1], q[0, 1]], color=CAMERA_COLOR, lw=lw, zorder=5)
        pts.append(np.vstack([c, q]))
        labels.append((c, i, True))
    # im_ids behind the cameras, away from the scene; cameras closer than 1.2 x the frusta's depth share a label
    c2 = centre @ P.T
    for members in _clusters([c for c, _, _ in labels], 1.2 * depth):
        c = np.mean([labels[k][0] for k in members], axis=0)
        d = c - c2
        d = d / (np.linalg.norm(d) + 1e-9)
        placed = sorted(labels[k][1] for k in members if labels[k][2])
        lost = sorted(labels[k][1] for k in members if not labels[k][2])
        p = c + d * depth * 0.45
        if placed:
            gauge = data.gauge_im_id in placed
            others = [i for i in placed if i != data.gauge_im_id]
            text = (f"{data.gauge_im_id} (gauge)" + (", " if others else "") if gauge else "") + _id_list(others)
            ax.text(p[0], p[1], _wrap(text, 18), fontsize=7, ha="center", va="center", color=CAMERA_COLOR,
                    fontweight="bold" if gauge else "normal", zorder=6, bbox=LABEL_BOX)
            pts.append(p[None])
            p = p + d * depth * 0.45
        if lost:
            ax.text(p[0], p[1], _wrap(_id_list(lost), 18) + "\n(not placed)", fontsize=6.5, ha="center",
                    va="center", color=DISCARDED_COLOR, zorder=6, bbox=LABEL_BOX)
            pts.append(p[None])
    if pts:
        allp = np.vstack(pts)
        lo, hi = allp.min(0), allp.max(0)
        pad = 0.1 * max(hi - lo) + 10
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal", adjustable="box")
    ax.grid(True, lw=0.3, alpha=0.5)
    ax.tick_params(labelsize=7)
    cam_name = f"camera {ref_id}" if ref_id is not None else "the camera"
    ax.set_xlabel(f"to the right of {cam_name}, levelled (mm)", fontsize=7.5)
    ax.set_ylabel(f"ahead of {cam_name}, levelled (mm)", fontsize=7.5)
    how = frame3.describe(cam_name, "GT objects" if gt_plane else "objects")
    origin = ("origin: the dataset's world origin" if data.known_cameras else
              f"origin: camera {data.gauge_im_id}" if data.gauge_im_id is not None else "origin: the world's origin")
    ax.set_title(f"top view, {how}\n{origin}", fontsize=8, linespacing=1.25)
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles = [Line2D([], [], color=CAMERA_COLOR, lw=1.0, label="cameras (refined)"),
               Patch(facecolor="#999999", alpha=0.6, edgecolor="black", lw=0.5, label="objects (refined)")]
    if gt_cams or gt_objs:
        handles.append(Line2D([], [], color=GT_COLOR, lw=0.9, ls=(0, (3, 2)), label="ground truth"))
    if legend_ax is None:
        ax.legend(handles=handles, fontsize=6.5, loc="best", framealpha=0.85)
    else:  # under the plot, where it hides nothing
        legend_ax.axis("off")
        legend_ax.legend(handles=handles, fontsize=6.5, loc="lower center", ncol=len(handles), frameon=False,
                         handlelength=2.2, columnspacing=1.2, borderaxespad=0.0)
    return {"gt_cameras": len(gt_cams), "gt_objects": len(gt_objs),
            "top_view_up": frame3.source + (" (ground truth)" if gt_plane else "")}


LINE_IN = 0.2  # inches per text line in the legend panel
TOP_VIEW_IN = 3.9  # height of the top view's plot (inches)
TOP_LEGEND_IN = 0.7  # under it: its axis labels and the legend of its line styles


def _text_width_in(text: str, size: float) -> float:
    """Width (inches) of ``text`` in matplotlib's default font at ``size`` points."""
    from matplotlib.textpath import TextPath

    return TextPath((0, 0), text, size=size).get_extents().width / 72.0 if text.strip() else 0.0


def _wrap_lines(text: str, width_in: float, size: float = 7.5) -> list[str]:
    """``text`` broken at spaces into lines at most ``width_in`` wide (continuations indented)."""
    out, cur = [], ""
    for word in text.split(" "):
        trial = f"{cur} {word}" if cur else ("    " + word if out else word)
        if cur and _text_width_in(trial, size) > width_in:
            out.append(cur)
            cur = "    " + word
        else:
            cur = trial
    return out + [cur]


def _info_lines(data: GroupData, ious: list[dict]) -> list[str]:
    lines = []
    n_c = sum(len(v.cand_obj_ids) for v in data.views)
    n_kept = sum(int((v.cand_object >= 0).sum()) for v in data.views)
    lines.append(f"scene {data.scene_id}, group {data.group_id}: {len(data.views)} views "
                 f"(im_id {', '.join(map(str, data.im_ids[:12]))}{' ...' if len(data.views) > 12 else ''})")
    if data.matched:
        re_ids = {o["object_id"] for o in data.objects if o.get("rematched")}
        n_re = sum(int(np.isin(v.cand_object, list(re_ids)).sum()) for v in data.views) if re_ids else 0
        lines.append(f"candidates: {n_c}; matched {n_kept - n_re} into {len(data.match_objects)} objects, "
                     f"{n_c - n_kept} discarded (red dashed)"
                     + (f"; refine re-matched {n_re} discarded into {len(re_ids)} objects" if re_ids else ""))
    else:
        lines.append(f"candidates: {n_c} (no match output yet: coloured by label)")
    if data.refined:
        st = data.stats
        placed = sum(v.T_world_cam is not None for v in data.views)
        lines.append(f"refined scene: {placed}/{len(data.views)} views placed, {len(data.objects)} objects"
                     + (f"; not placed: im_id {', '.join(map(str, data.unplaced_im_ids))}" if data.unplaced_im_ids
                        else ""))
        errs = [e.get("final") for e in (st.get("reprojection_error_px") or {}).values() if e.get("final") is not None]
        if "iterations" in st:
            lines.append(f"bundle adjustment: {st['iterations']} iterations, "
                         + (f"median reprojection error {np.median(errs):.2f} px" if errs else "no residuals"))
    else:
        lines.append("no refine output for this scene yet (only the candidates are shown)")
    if ious:
        v = np.array([r["iou"] for r in ious])
        lines.append(f"visible-mask IoU of the re-projection with GT: mean {v.mean():.2f}, median {np.median(v):.2f} "
                     f"({int((v > 0.5).sum())}/{len(v)} GT instances > 0.5)")
    return lines


def _legend_entries(data: GroupData) -> list[tuple[str, str]]:
    """(colour, text) per physical object of the group."""
    refined = {o["object_id"]: o for o in data.objects}
    out = []
    if not data.matched:
        labels = sorted({int(o) for v in data.views for o in v.cand_obj_ids})
        return [(PALETTE[o % len(PALETTE)], f"obj_id {o}: "
                 f"{sum(int((v.cand_obj_ids == o).sum()) for v in data.views)} candidates") for o in labels]
    for oid in sorted(set(data.match_objects) | set(refined)):
        label = refined[oid]["obj_id"] if oid in refined else data.match_objects.get(oid)
        ncand = sum(int((v.cand_object == oid).sum()) for v in data.views)
        txt = f"obj_id {label}: {ncand} candidates"
        if oid in refined and refined[oid].get("reprojection_error_px") is not None:
            txt += f", {float(refined[oid]['reprojection_error_px']):.2f} px"
        if data.refined and oid not in refined:
            txt += " (dropped by refine)"
        elif oid in refined and refined[oid].get("rematched"):
            txt += " (re-matched)"
        out.append((object_color(oid), txt))
    return out


def _legend_height(n_lines: int, n_entries: int, ncol: int) -> float:
    """Inches the legend panel needs."""
    return LINE_IN * (n_lines + 1.6 + -(-n_entries // max(ncol, 1))) + 0.1


def _legend_panel(ax, lines: list[str], entries: list[tuple[str, str]], ncol: int, height_in: float, title: str):
    from matplotlib.patches import Rectangle

    ax.axis("off")
    step = LINE_IN / height_in
    y = 1.0
    for ln in lines:
        ax.text(0.02, y, ln, fontsize=7.5, va="top", ha="left", transform=ax.transAxes)
        y -= step
    y -= 0.4 * step
    ax.text(0.02, y, title if entries else f"{title} none", fontsize=7.5, va="top", transform=ax.transAxes,
            fontweight="bold")
    y -= step
    per_col = -(-len(entries) // max(ncol, 1)) if entries else 0
    box_w = 0.12 / ax.get_position().width / ax.figure.get_figwidth()  # 0.12 inch
    for k, (color, txt) in enumerate(entries):
        col, row = divmod(k, per_col)
        x0, yy = 0.02 + col / ncol, y - row * step
        ax.add_patch(Rectangle((x0, yy - 0.7 * step), box_w, 0.65 * step, transform=ax.transAxes, facecolor=color,
                               edgecolor="black", lw=0.4, clip_on=False))
        ax.text(x0 + 1.6 * box_w, yy - 0.375 * step, txt, fontsize=7, va="center", transform=ax.transAxes)


def build_group_figure(data: GroupData, mr: MeshRenderer, *, max_cols: int = 8, dpi: int = DPI):
    """(matplotlib Figure, info dict) of one group (see the module docstring)."""
    from matplotlib.figure import Figure
    from matplotlib.gridspec import GridSpec

    t0 = time.perf_counter()
    views = data.views
    n = len(views)
    renders: dict[int, ViewRender] = {v.im_id: render_view(mr, data, v) for v in views}
    ious = group_reprojection_ious(data, renders) if data.refined else []
    t_render = time.perf_counter() - t0

    ncols = max(1, min(n, max_cols))
    nrows_block = -(-n // ncols)
    w0, h0 = views[0].size if views else (640, 480)
    fig_w = max(ncols * PANEL_WIDTH_IN, 9.0)
    panel_w = fig_w / ncols
    panel_h = panel_w * h0 / w0
    show_refined = data.refined
    show_top = show_refined and any(v.T_world_cam is not None for v in views)
    blocks = 2 if show_refined else 1
    lines, entries = _info_lines(data, ious), _legend_entries(data)
    top_h = TOP_VIEW_IN + TOP_LEGEND_IN
    top_w = 1.25 * TOP_VIEW_IN
    side_w = fig_w - top_w - 0.6
    side = False
    if show_top and side_w >= 3.3:  # the legend panel beside the top view, its lines wrapped to fit
        wrapped = [w for ln in lines for w in _wrap_lines(ln, side_w - 0.25)]
        longest = max((_text_width_in(t, 7.0) for _, t in entries), default=0.0) + 0.35  # + colour box
        for ncol in (1, 2):
            if longest * ncol <= side_w - 0.1 and _legend_height(len(wrapped), len(entries), ncol) <= top_h:
                side, lines = True, wrapped
                break
    if side:
        bottom_heights = [top_h]
    else:
        ncol = 2 if fig_w >= 8 and len(entries) > 4 else 1
        leg_h = _legend_height(len(lines), len(entries), ncol)
        bottom_heights = ([top_h, 0.45] if show_top else []) + [leg_h]
    heights = [panel_h] * (blocks * nrows_block) + ([0.15] if show_top else []) + bottom_heights  # room: title
    gap = 0.28  # inches between rows (their titles)
    fig_h = sum(heights) + gap * (len(heights) - 1) + 0.82
    fig = Figure(figsize=(fig_w, fig_h), dpi=dpi)
    gs = GridSpec(len(heights), ncols, figure=fig, height_ratios=heights, hspace=gap / np.mean(heights), wspace=0.03,
                  left=0.035, right=0.995, top=1 - 0.42 / fig_h, bottom=0.4 / fig_h)
    px = int(round(panel_w * dpi * 1.1))

    for k, v in enumerate(views):
        r, c = divmod(k, ncols)
        img = data.dataset.read_rgb(data.scene_id, v.im_id)
        ax = fig.add_subplot(gs[blocks * r, c])  # wrapped rows: candidates above refined, chunk by chunk
        _image_axes(ax, _downscale(img, px), v.size)
        _draw_candidates(ax, v, renders[v.im_id], data.matched)
        ax.set_title(f"view {v.im_id}: {len(v.cand_obj_ids)} candidates", fontsize=7, pad=2)
        if c == 0:
            ax.set_ylabel("single-view\ncandidates", fontsize=8)
        if show_refined:
            ax2 = fig.add_subplot(gs[blocks * r + 1, c])
            rv = renders[v.im_id]
            if v.T_world_cam is None:
                dim = (img.astype(np.float32) * 0.35 + 255 * 0.65 * 0.6).astype(np.uint8)
                _image_axes(ax2, _downscale(dim, px), v.size)
                ax2.text(v.size[0] / 2, v.size[1] / 2, "not placed", ha="center", va="center", fontsize=9,
                         color=DISCARDED_COLOR, fontweight="bold")
                ax2.set_title(f"view {v.im_id}: not placed", fontsize=7, pad=2, color=DISCARDED_COLOR)
            else:
                shown = _blend(img, rv) if rv.rgb is not None else img
                _image_axes(ax2, _downscale(shown, px), v.size)
                if rv.instance is not None:
                    _draw_refined(ax2, data, v, rv)
                err = ((data.stats.get("reprojection_error_px") or {}).get(str(v.im_id)) or {}).get("final")
                title = f"view {v.im_id}" + (" (gauge)" if v.im_id == data.gauge_im_id else "")
                if err is not None:
                    title += f": {err:.2f} px"
                ax2.set_title(title, fontsize=7, pad=2)
            if c == 0:
                ax2.set_ylabel("refined scene\n(multi-view)", fontsize=8)

    info = {"scene_id": data.scene_id, "group_id": data.group_id, "views": n,
            "views_placed": sum(v.T_world_cam is not None for v in views), "objects": len(data.objects),
            "candidates": int(sum(len(v.cand_obj_ids) for v in views)), "refined": data.refined,
            "matched": data.matched}
    first = blocks * nrows_block + 1
    title = "objects (colour = physical object found by match):" if data.matched else "labels:"
    if show_top:
        rest = side_w if side else max(fig_w - top_w - 0.45, 0.1)
        bottom = gs[first, :].subgridspec(1, 3, width_ratios=[0.45, top_w, rest], wspace=0.04)
        slot = bottom[0, 1].subgridspec(2, 1, height_ratios=[TOP_VIEW_IN, TOP_LEGEND_IN], hspace=0.0)
        info.update(_draw_top_view(fig.add_subplot(slot[0, 0]), data, mr, legend_ax=fig.add_subplot(slot[1, 0])))
    if side:
        _legend_panel(fig.add_subplot(bottom[0, 2]), lines, entries, ncol, top_h, title)
    else:
        leg = gs[len(heights) - 1, :].subgridspec(1, 2, width_ratios=[0.2, fig_w - 0.2], wspace=0.0)
        _legend_panel(fig.add_subplot(leg[0, 1]), lines, entries, ncol, bottom_heights[-1], title)
    what = "single-view candidates, refined scene and recovered cameras" if show_refined else "single-view candidates"
    fig.suptitle(f"scene {data.scene_id}, group {data.group_id}: {what}", fontsize=10, y=1 - 0.08 / fig_h, va="top")
    if ious:
        v = np.array([r["iou"] for r in ious])
        info["mask_iou_mean"] = float(v.mean())
        info["mask_iou_median"] = float(np.median(v))
        info["mask_iou_n"] = int(len(v))
    info["ious"] = ious
    info["render_s"] = t_render
    return fig, info


def _quantize(im):
    """A 256-colour palette image of ``im`` (RGB) whose palette holds the figure's own colours
    exactly (objects, cameras, ground truth, black, white), so legend boxes and contours keep their
    colours; the rest of the palette adapts to the photos (dithered)."""
    from PIL import Image

    fixed = list(dict.fromkeys(PALETTE + [DISCARDED_COLOR, CAMERA_COLOR, GT_COLOR, "#000000", "#ffffff"]))
    n = 256 - len(fixed)
    exact = np.array([np.round(_rgb01(c) * 255) for c in fixed])
    adaptive = np.array(im.quantize(colors=n, method=Image.Quantize.MEDIANCUT).getpalette()[:3 * n]).reshape(-1, 3)
    # adaptive colours close to a fixed one would take its pixels (PIL looks colours up coarsely)
    far = np.abs(adaptive[:, None, :] - exact[None]).max(-1).min(1) > 12
    holder = Image.new("P", (1, 1))
    holder.putpalette([int(v) for v in np.vstack([exact, adaptive[far]]).ravel()])
    return im.quantize(palette=holder, dither=Image.Dither.FLOYDSTEINBERG)


def save_png(fig, out_png: str | Path, *, dpi: int = DPI, max_bytes: int = MAX_PNG_BYTES) -> Path:
    """Save a figure as PNG atomically; re-encode with a 256-colour palette (then lower dpi) when
    larger than ``max_bytes``."""
    import io

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from PIL import Image

    out_png = Path(out_png)
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, facecolor="white")
    data = buf.getvalue()
    if len(data) > max_bytes:
        buf.seek(0)
        im = Image.open(buf).convert("RGB")
        for scale in (1.0, 0.85, 0.7, 0.55):
            im2 = im if scale == 1.0 else im.resize((int(im.width * scale), int(im.height * scale)), Image.LANCZOS)
            b = io.BytesIO()
            _quantize(im2).save(b, format="PNG", optimize=True)
            data = b.getvalue()
            if len(data) <= max_bytes:
                break
    atomic.write_bytes(out_png, data)
    return out_png


def group_figure(run_dir: str | Path, scene_id: int, group_id: int, out_png: str | Path, *,
                 renderer: MeshRenderer | None = None, max_cols: int = 8, dpi: int = DPI,
                 info: dict | None = None) -> Path:
    """Write the paper-style figure of one group of a run to ``out_png`` (atomically); returns it.

    ``renderer``: a :class:`MeshRenderer` of the run's dataset to reuse across figures (one is
    made and closed otherwise). ``info``: a dict filled with what the figure shows (views placed,
    objects, visible-mask IoUs with GT, times)."""
    t0 = time.perf_counter()
    run = read_run(run_dir)
    ds = BopDataset(run["dataset"], run["split"])
    data = load_group(run_dir, scene_id, group_id, ds)
    own = renderer is None
    mr = MeshRenderer(ds) if own else renderer
    try:
        fig, inf = build_group_figure(data, mr, max_cols=max_cols, dpi=dpi)
    finally:
        if own:
            mr.close()
    path = save_png(fig, out_png, dpi=dpi)
    inf["time_s"] = time.perf_counter() - t0
    inf["bytes"] = path.stat().st_size
    if info is not None:
        info.update(inf)
    return path
