"""Whole-dataset checks of a BOP dataset: :func:`validate_dataset` collects every problem it finds.

Each problem is one line ``<file>: <where>: <what is wrong, what was expected>``; the checks go on
after a problem (a file that cannot be read only skips the checks that need it). Warnings are kept
apart: what cosy tolerates, as the BOP toolkit does (rotations orthonormal only to
:data:`~cosy_cli.io.bop.ROTATION_REPAIR_TOL`, repaired at read time, one warning per file;
symmetries that move the surface by up to :data:`SYMMETRY_WARN_FRACTION` of the diameter; a
split without scene_gt_info.json). What is checked:

* files: camera.json, ``models/`` (models_info.json, one PLY per object), the split and its scene
  folders, per scene scene_camera.json (required), scene_gt.json + scene_gt_info.json (optional
  together: a test split without ground truth is reported in the summary, not as a problem), an
  image (rgb/ or gray/) for every image id of scene_camera.json, depth and masks where their
  folders exist;
* numbers: every reader error of :mod:`cosy_cli.io` (JSON syntax, shapes, non-finite values),
  rotations (``cam_R_m2c``, ``cam_R_w2c``, discrete symmetries: within the repair tolerance a
  warning per file, beyond it a problem per row), sane intrinsics;
* images: sizes (read from the file headers) agree with camera.json (classic layout), or within a
  scene when there is none or when every image of the scene has one other size with cam_K's
  principal point near its centre (a camera file of another split: a note); depth images and
  masks have the same size; a sample of images (all with ``full``) is decoded to catch corrupt
  files. The stages' readers apply the same rules (:mod:`cosy_cli.io.dataset`);
* ground truth: scene_gt and scene_gt_info agree on image ids and instance counts, every obj_id
  is a model, every object lies in front of its camera, and (on decoded images with depth and
  visible masks) the measured depth of an object is not grossly off its GT depth; without
  visible masks, the stages' cheaper check (:func:`cosy_cli.io.dataset.depth_vs_gt`: most GT
  objects more than 10 % off the depth at their centre) gives one warning for the split;
* models: the diameter and bounding box of models_info.json agree with the mesh (1 %), every
  declared symmetry maps the surface onto itself (:func:`check_symmetries`; a residual above the
  tolerance but within 5 % of the diameter is a warning with the measured figure, like the
  published approximate symmetries of LM-O's eggbox and glue; downstream stages use the
  declared symmetries as given, like the BOP toolkit);
* targets (test_targets_bop19.json, test split): ids refer to existing scenes, images, objects.

Lengths are millimetres throughout.
"""

from __future__ import annotations

import time
import warnings
from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import console
from ..errors import CosyError, CosyWarning, warn
from ..io import bop, images
from ..io.dataset import DEPTH_SCALE_RTOL, BopDataset, depth_vs_gt, pp_central, pp_outside
from ..objects.database import ObjectModel, diameter_of, forget_reported_textures
from ..objects.symmetries import continuous_symmetry_transforms

PP_MARGIN = 0.1  # principal point may lie this fraction of the image size outside the image
DIAMETER_RTOL = 0.01  # models_info diameter / bbox vs the mesh
DEPTH_RTOL = 0.2  # measured object depth vs GT: tolerated fraction of the object's mean depth
MIN_DEPTH_PIXELS = 20  # fewer valid visible-mask pixels than this: no depth check
MASK_DIRS = ("mask", "mask_visib")
SYMMETRY_WARN_FRACTION = 0.05  # symmetry residual above the tolerance: a warning up to this fraction of the diameter


# --------------------------------------------------------------------------------------------
# report
# --------------------------------------------------------------------------------------------
@dataclass
class ValidationReport:
    """What :func:`validate_dataset` found: problem lines, warning lines, notes and counts for the summary."""

    root: Path
    split: str
    problems: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)  # tolerated (repaired or approximate), one line each
    # the same as {"text", "record"} (see cosy_cli.console.capture_records): the CLI summarises the
    # tolerated input problems that recur file after file (rotations repaired per scene_gt.json)
    warning_records: list[dict] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # worth saying, not wrong (e.g. no GT in a test split)
    n_scenes: int = 0
    n_images: int = 0  # image ids in the scene_camera files
    n_images_checked: int = 0  # of them, whose files were checked (``max_images``)
    n_images_decoded: int = 0
    n_scenes_with_gt: int = 0
    n_gt_instances: int = 0
    n_objects: int = 0
    n_symmetric: int = 0
    has_depth: bool = False
    has_masks: bool = False
    targets_file: str | None = None
    n_targets: int = 0
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        """No problems (warnings allowed; ``strict_ok`` allows none)."""
        return not self.problems

    @property
    def strict_ok(self) -> bool:
        return not self.problems and not self.warnings

    def summary_lines(self) -> list[str]:
        if self.n_scenes == 0:
            gt = "-"
        elif self.n_scenes_with_gt == 0:
            gt = "absent (no scene_gt.json; normal for a test split without ground truth)"
        elif self.n_scenes_with_gt < self.n_scenes:
            gt = f"{self.n_gt_instances} instances, in {self.n_scenes_with_gt} of {self.n_scenes} scenes"
        else:
            gt = f"{self.n_gt_instances} instances"
        checked = f"{self.n_images_checked} checked, {self.n_images_decoded} decoded"
        targets = f"yes ({self.targets_file}, {self.n_targets} entries)" if self.targets_file else "no"
        nw = len(self.warnings)
        warned = f"{nw} warning{'' if nw == 1 else 's'}"
        if not self.ok:
            result = f"{len(self.problems)} problem line(s)" + (f" and {warned}" if nw else "") + ", listed on stderr"
        else:
            result = f"OK, {warned} (on stderr)" if nw else "OK"
        lines = [
            f"dataset:   {self.root}",
            f"split:     {self.split}",
            f"scenes:    {self.n_scenes}",
            f"images:    {self.n_images} ({checked})",
            f"GT:        {gt}",
            f"objects:   {self.n_objects} ({self.n_symmetric} symmetric)",
            f"depth:     {'yes' if self.has_depth else 'no'}",
            f"masks:     {'yes' if self.has_masks else 'no'}",
            f"targets:   {targets}",
            f"time:      {self.seconds:.1f} s",
            f"result:    {result}",
        ]
        return lines + [f"note: {n}" for n in self.notes]

    def summary(self) -> str:
        return "\n".join(self.summary_lines())


class _Problems:
    """Problem lines, at most ``max_per_check`` per (file or folder, check); the rest counted."""

    def __init__(self, max_per_check: int | None):
        self.max = max_per_check or None
        self.lines: list[str] = []
        self.counts: Counter = Counter()

    def add(self, path, where: str | None, what: str, *, group=None, check: str = "") -> None:
        key = (str(group if group is not None else path), check)
        self.counts[key] += 1
        if self.max is None or self.counts[key] <= self.max:
            self.lines.append(": ".join(str(p) for p in (path, where, what) if p not in (None, "")))

    def error(self, e: CosyError, *, group=None, check: str = "") -> None:
        key = (str(group if group is not None else (e.path or "")), check)
        self.counts[key] += 1
        if self.max is None or self.counts[key] <= self.max:
            self.lines.append(str(e))

    def finish(self) -> list[str]:
        out = list(self.lines)
        for (where, check), n in self.counts.items():
            if self.max is not None and n > self.max:
                out.append(f"{where}: {n - self.max} more problem(s) like the above ({check}) not shown "
                           "(--max-per-check 0 lists all)")
        return out


# --------------------------------------------------------------------------------------------
# symmetries
# --------------------------------------------------------------------------------------------
@dataclass
class SymmetryCheck:
    """Residual of one declared symmetry: how far (mm) it moves the surface off itself."""

    label: str  # "symmetries_discrete[j]" or "symmetries_continuous[j]"
    residual_mm: float  # ``percentile`` of surface-point distances to the surface after the move
    tol_mm: float
    angle_deg: float | None = None  # continuous: the worst of the tested rotation angles

    @property
    def ok(self) -> bool:
        return self.residual_mm <= self.tol_mm


class _SurfaceDistance:
    """Distances (mm) of points to a mesh surface, approximated by the distance to the nearest of
    many area-uniform surface samples (and the mesh vertices), with a k-d tree.

    Sampling ``spacing`` (mm) sets the accuracy: the result over-estimates the true distance by
    about half a spacing. Exact point-to-triangle queries (``ObjectModel.surface_distance``) were
    measured far too slow on CAD meshes with long thin triangles (64 s for 15,000 points on the
    surface of a 131k-face capsule; 45 s for 1,000 points 100 mm off it), this takes < 1 s.
    """

    def __init__(self, model: ObjectModel, spacing: float, max_samples: int = 1_000_000, seed: int = 0):
        import trimesh
        from scipy.spatial import cKDTree

        mesh = model.mesh
        V = np.asarray(mesh.vertices, dtype=np.float64)
        n = int(np.clip(float(mesh.area) / max(spacing, 1e-9) ** 2, 20_000, max_samples))
        dense, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
        self.fine = cKDTree(np.concatenate([np.asarray(dense), V]), balanced_tree=False, compact_nodes=False)
        coarse, _ = trimesh.sample.sample_surface(mesh, 20_000, seed=seed + 1)
        self.coarse = cKDTree(np.concatenate([np.asarray(coarse), V]))

    def __call__(self, points: np.ndarray, near: float) -> np.ndarray:
        """Distances; those beyond ``near`` mm come from coarser samples (far queries in the fine
        tree are slow), which is accurate enough for points that far off the surface."""
        d = self.fine.query(points, distance_upper_bound=near)[0]
        far = ~np.isfinite(d)
        if far.any():
            d[far] = np.maximum(self.coarse.query(points[far])[0], near)
        return d


def check_symmetries(model: ObjectModel, *, steps: int = 16, percentile: float = 99.0,
                     tol_mm: float | None = None, diameter_mm: float | None = None) -> list[SymmetryCheck]:
    """Test each declared symmetry of ``model`` (models_info.json) against its mesh.

    Surface points (``model.points``) are moved by the symmetry; its residual is the
    ``percentile`` of their distances to the surface (a high percentile, not the max, tolerates
    faceting), measured against dense surface samples spaced ``tol / 6`` apart (so a residual
    over-estimates the true one by up to about ``tol / 5``). Continuous symmetries are tried at
    ``steps`` angles over a full turn and the worst angle is kept. ``tol_mm`` defaults to max(1 mm, 1 % of the diameter). Discrete symmetries
    whose 3x3 part is not a rotation are left out here (:func:`validate_dataset` reports them).
    """
    info = model.info
    diam = float(diameter_mm if diameter_mm is not None else info.diameter)
    tol = float(tol_mm) if tol_mm is not None else max(1.0, 0.01 * diam)
    labels, transforms, angles = [], [], []
    S = np.asarray(info.symmetries_discrete, dtype=np.float64).reshape(-1, 4, 4)
    rot_ok = bop.rotation_errors(S[:, :3, :3]) <= bop.ROTATION_REPAIR_TOL if len(S) else np.zeros(0, bool)
    for j in range(len(S)):
        if rot_ok[j]:
            labels.append(f"symmetries_discrete[{j}]")
            transforms.append(S[j][None])
            angles.append(None)
    for j, c in enumerate(info.symmetries_continuous):
        C = continuous_symmetry_transforms(c["axis"], c.get("offset", np.zeros(3)), steps, include_identity=False)
        labels.append(f"symmetries_continuous[{j}]")
        transforms.append(C)
        angles.append(360.0 * np.arange(1, steps) / steps)
    if not labels:
        return []
    P = model.points
    T = np.concatenate(transforms)
    moved = (P[None] @ np.swapaxes(T[:, :3, :3], -1, -2) + T[:, None, :3, 3]).reshape(-1, 3)
    dist = _SurfaceDistance(model, spacing=tol / 6)(moved, near=2 * tol).reshape(len(T), len(P))
    res = np.percentile(dist, percentile, axis=1)
    out, i = [], 0
    for label, tr, ang in zip(labels, transforms, angles):
        r = res[i:i + len(tr)]
        i += len(tr)
        k = int(np.argmax(r))
        out.append(SymmetryCheck(label, float(r[k]), tol, None if ang is None else float(ang[k])))
    return out


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------
@dataclass
class _Object:
    info: bop.ModelInfo
    corners: np.ndarray  # (8, 3) mm, bounding box from models_info
    model: ObjectModel | None  # None when the mesh is missing or unreadable
    _hull: np.ndarray | None = None

    def hull_vertices(self) -> np.ndarray | None:
        if self.model is None:
            return None
        if self._hull is None:
            try:
                self._hull = np.asarray(self.model.mesh.convex_hull.vertices, dtype=np.float64)
            except Exception:  # flat or degenerate mesh: all its vertices then
                self._hull = np.asarray(self.model.mesh.vertices, dtype=np.float64)
        return self._hull


def _box_corners(mins: np.ndarray, size: np.ndarray) -> np.ndarray:
    c = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.float64)
    return mins[None] + c * size[None]


def _ids(ids, limit: int = 12) -> str:
    ids = sorted(int(i) for i in ids)
    s = ", ".join(str(i) for i in ids[:limit])
    return s + (f", ... ({len(ids)} in all)" if len(ids) > limit else "")


def _find_image(folder: Path, im_id: int) -> Path | None:
    for ext in images.IMAGE_EXTENSIONS:
        p = folder / f"{int(im_id):06d}{ext}"
        if p.is_file():
            return p
    return None


def _header_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header (png by cosy's reader, other formats by PIL)."""
    if path.suffix.lower() == ".png":
        return images.image_size(path)
    try:
        from PIL import Image

        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except Exception:  # PIL raises several types on bad files: fall back to decoding
        return images.image_size(path)


def _sensor_suffix(path: Path, kind: str) -> str | None:
    stem = path.stem
    return stem[len(kind) + 1:] if stem.startswith(kind + "_") else None


def _fmt_size(wh) -> str:
    return f"{wh[0]}x{wh[1]}"


# --------------------------------------------------------------------------------------------
# the checks
# --------------------------------------------------------------------------------------------
class _Validator:
    def __init__(self, ds: BopDataset, report: ValidationReport, probs: _Problems, *, max_images, full,
                 sample_per_scene, symmetry_tol_mm, symmetry_steps, symmetry_percentile, progress):
        self.ds, self.rep, self.p = ds, report, probs
        self.max_images = max_images
        self.full = full
        self.sample_per_scene = sample_per_scene
        self.sym_tol = symmetry_tol_mm
        self.sym_steps = symmetry_steps
        self.sym_pct = symmetry_percentile
        self.progress = progress
        self.camera: bop.CameraInfo | None = None
        self.camera_name = "camera.json"
        self.objects: dict[int, _Object] | None = None  # None: models unreadable (obj ids not checked)
        self.scene_ids: list[int] = []
        self.scene_images: dict[int, set[int]] = {}
        self.gt_counts: dict[int, Counter] = {}  # scene -> Counter[(im_id, obj_id)]
        self.no_gt_info: list[int] = []  # scenes with scene_gt.json but no scene_gt_info.json
        self.other_split_scenes: list[tuple[int, tuple[int, int]]] = []  # images uniform, not the camera's size
        self.depth_scale_done: set[int] = set()  # scenes whose depth was compared with the GT boxes
        self.depth_scale_off: list[tuple] = []  # (depth path, im, ratio, n off, n, depth_scale)

    # ---- camera.json ---------------------------------------------------------------------
    def check_camera(self) -> None:
        ds, p = self.ds, self.p
        names = ([f"camera_{ds.split_type}.json"] if ds.split_type else []) + ["camera.json"]
        try:
            path = ds.camera_path
        except CosyError as e:  # an explicit camera file that is not there
            p.error(e)
            return
        if path is None:
            others = sorted(q.name for q in ds.root.glob("camera_*.json"))
            if others:
                self.rep.notes.append(f"no {' or '.join(names)} (found {', '.join(others)}; choose one with --camera): "
                                      "image sizes are only checked for agreement within each scene")
            else:
                p.add(ds.root / "camera.json", None, "file not found (expected the dataset camera: fx, fy, cx, cy, "
                      "width, height, depth_scale; image sizes are checked against it)")
            return
        sensor = ds.sensor or (ds.eval_sensor if ds.is_multi_sensor else None)
        if sensor and path.name == f"camera_{sensor}.json":
            self.rep.notes.append(f"sensor {sensor} of {', '.join(ds.sensors)}: camera file {path.name}")
        elif ds.camera_file is None and path.name not in names:
            self.rep.notes.append(f"camera file: {path.name} (the only camera_*.json; no {' or '.join(names)})")
        self.camera_name = path.name
        try:
            cam = bop.read_camera(path)
        except CosyError as e:
            p.error(e)
            return
        bad = []
        if cam.width <= 0 or cam.height <= 0:
            bad.append(f"width and height must be > 0, got {cam.width}x{cam.height}")
        if cam.K[0, 0] <= 0 or cam.K[1, 1] <= 0:
            bad.append(f"fx and fy must be > 0, got fx={cam.K[0, 0]:g}, fy={cam.K[1, 1]:g}")
        if cam.depth_scale <= 0:
            bad.append(f"depth_scale must be > 0, got {cam.depth_scale:g}")
        for b in bad:
            p.add(path, "camera", b)
        if bad:
            return
        msg = self._pp_problem(cam.K, (cam.width, cam.height))
        if msg:
            p.add(path, "camera", msg)
        self.camera = cam

    @staticmethod
    def _pp_problem(K: np.ndarray, wh) -> str | None:
        W, H = wh
        cx, cy = K[0, 2], K[1, 2]
        if not (-PP_MARGIN * W <= cx <= (1 + PP_MARGIN) * W and -PP_MARGIN * H <= cy <= (1 + PP_MARGIN) * H):
            return (f"principal point ({cx:g}, {cy:g}) px is far outside the {W}x{H} image (expected within "
                    f"{PP_MARGIN:.0%} of its borders)")
        return None

    # ---- models --------------------------------------------------------------------------
    def check_models(self) -> None:
        from ..console import progress as progress_bar

        ds, p, rep = self.ds, self.p, self.rep
        if not ds.models_dir.is_dir():
            p.add(ds.models_dir, None, "models folder not found (expected models_info.json and obj_XXXXXX.ply files)")
            return
        try:
            infos = bop.read_models_info(ds.models_info_path, rotations="keep_bad")
        except CosyError as e:
            p.error(e)
            return
        info_path = ds.models_info_path
        self.objects = {}
        rep.n_objects = len(infos)
        rep.n_symmetric = sum(1 for i in infos.values() if len(i.symmetries_discrete) or i.symmetries_continuous)
        for obj_id, info in progress_bar(infos.items(), total=len(infos), desc="objects", unit="obj", enabled=bool(self.progress)):
            where = f"object {obj_id}"
            model = None
            try:
                model = ObjectModel(obj_id, ds.model_path(obj_id), info)
                _ = model.mesh  # loads, raises CosyError when missing or unreadable
            except CosyError as e:
                p.error(e)
                model = None
            self.objects[obj_id] = _Object(info, _box_corners(info.min_xyz, info.size_xyz), model)
            S = np.asarray(info.symmetries_discrete).reshape(-1, 4, 4)
            if len(S):
                err = bop.rotation_errors(S[:, :3, :3])  # within the repair tolerance: repaired by the reader
                for j in np.flatnonzero(err > bop.ROTATION_REPAIR_TOL):
                    p.add(info_path, where, f"symmetries_discrete[{j}] is not a rigid transform "
                          f"(|R^T R - I| = {err[j]:.3g} or det <= 0; expected a rotation, tolerated up to "
                          f"{bop.ROTATION_REPAIR_TOL:g})")
            if model is None:
                continue
            try:
                self._check_mesh(obj_id, info, model)
            except CosyError as e:
                p.error(e)
            except Exception as e:  # a degenerate mesh (no area...) must not end the whole check
                p.add(model.mesh_path, None, f"could not check the mesh ({type(e).__name__}: {e})")

    def _check_mesh(self, obj_id: int, info: bop.ModelInfo, model: ObjectModel) -> None:
        p, info_path, where = self.p, self.ds.models_info_path, f"object {obj_id}"
        V = model.vertices
        d_mesh = diameter_of(V)
        if abs(info.diameter - d_mesh) > DIAMETER_RTOL * d_mesh:
            p.add(info_path, where, f"diameter {info.diameter:.6g} mm but the mesh {model.mesh_path.name} "
                  f"measures {d_mesh:.6g} mm (expected within {DIAMETER_RTOL:.0%})")
        mins, size = V.min(0), V.max(0) - V.min(0)
        dev = max(np.abs(mins - info.min_xyz).max(), np.abs(size - info.size_xyz).max())
        if dev > DIAMETER_RTOL * d_mesh:
            p.add(info_path, where, f"min_xyz/size_xyz ({_vec(info.min_xyz)} / {_vec(info.size_xyz)}) "
                  f"disagree with the mesh bounding box ({_vec(mins)} / {_vec(size)}) by {dev:.3g} mm")
        for sc in check_symmetries(model, steps=self.sym_steps, percentile=self.sym_pct,
                                   tol_mm=self.sym_tol, diameter_mm=d_mesh):
            if sc.ok:
                continue
            how = f" rotated by {sc.angle_deg:g}°" if sc.angle_deg is not None else ""
            frac = sc.residual_mm / d_mesh
            limit = max(sc.tol_mm, SYMMETRY_WARN_FRACTION * d_mesh)
            if sc.residual_mm <= limit:
                warn(f"approximate symmetry: the surface{how} lies {sc.residual_mm:.3g} mm off the mesh "
                     f"({frac:.1%} of the {d_mesh:.4g} mm diameter, {self.sym_pct:g}th percentile; exact would be "
                     f"<= {sc.tol_mm:.3g} mm); used as declared, like the BOP toolkit",
                     path=info_path, where=f"{where}, {sc.label}")
                continue
            p.add(info_path, f"{where}, {sc.label}",
                  f"does not map the model onto itself: the surface{how} lies {sc.residual_mm:.3g} mm off the mesh "
                  f"({frac:.1%} of the diameter, {self.sym_pct:g}th percentile; expected <= {sc.tol_mm:.3g} mm, "
                  f"tolerated with a warning up to {limit:.3g} mm = {limit / d_mesh:.0%} of the diameter)")

    # ---- scenes ---------------------------------------------------------------------------
    def check_scenes(self) -> None:
        from ..console import progress as progress_bar

        try:
            self.scene_ids = self.ds.scene_ids
        except CosyError as e:
            self.p.error(e)
            return
        self.rep.n_scenes = len(self.scene_ids)
        for scene_id in progress_bar(self.scene_ids, desc="scenes", unit="scene", enabled=bool(self.progress)):
            self.check_scene(scene_id)
        if self.depth_scale_off:
            path, im, ratio, n_off, n, scale = self.depth_scale_off[0]
            more = len(self.depth_scale_off) - 1
            warn(f"image {im}: the measured depth at the GT objects is {ratio:.3g} times their GT distance ({n_off} of "
                 f"{n} object(s) more than {DEPTH_SCALE_RTOL:.0%} off{f'; the same in {more} other scene(s)' if more else ''}"
                 f"): wrong depth_scale ({scale:g})?", path=path)
        if self.other_split_scenes:
            sids = [s for s, _ in self.other_split_scenes]
            sizes = sorted(set(_fmt_size(wh) for _, wh in self.other_split_scenes))
            cam = self.camera
            self.rep.notes.append(f"scene(s) {_ids(sids)}: every image is {' or '.join(sizes)} (cam_K's principal point "
                                  f"near the centre), {self.camera_name} says {cam.width}x{cam.height}: it describes "
                                  "another split? Images checked against the others of their scene")
        if self.no_gt_info:
            n, first = len(self.no_gt_info), self.no_gt_info[0]
            warn(f"no scene_gt_info.json in {n} of {self.rep.n_scenes_with_gt} scene(s) with scene_gt.json "
                 f"({'scene' if n == 1 else 'scenes'} {_ids(self.no_gt_info)}): the checks against it were skipped; detection scores and "
                 "visibility filters need it (the BOP toolkit's calc_gt_info.py computes it)",
                 path=self.ds.scene_file(first, "scene_gt_info"))

    def _read(self, reader, path: Path, **kwargs):
        try:
            return reader(path, **kwargs)
        except CosyError as e:
            self.p.error(e)
            return None

    def check_scene(self, scene_id: int) -> None:
        ds, p, rep = self.ds, self.p, self.rep
        sdir = ds.scene_dir(scene_id)
        cam_path = ds.scene_file(scene_id, "scene_camera")
        sensor = _sensor_suffix(cam_path, "scene_camera")
        gt_path, info_path = ds.scene_file(scene_id, "scene_gt"), ds.scene_file(scene_id, "scene_gt_info")
        cams = self._read(bop.read_scene_camera, cam_path, rotations="keep_bad", check_intrinsics=False)
        gt = info = None
        has_gt, has_info = gt_path.is_file(), info_path.is_file()
        if has_gt or has_info:
            rep.n_scenes_with_gt += 1
            if has_gt:
                gt = self._read(bop.read_scene_gt, gt_path, rotations="keep_bad")
            else:
                p.add(gt_path, None, f"file not found ({info_path.name} is there; the two come together)")
            if has_info:
                info = self._read(bop.read_scene_gt_info, info_path)
            else:
                self.no_gt_info.append(scene_id)  # one warning for the split, after the scenes

        if cams is not None and not cams:
            p.add(cam_path, None, "no images (expected one entry per image id)")
            cams = None
        if cams is not None:
            self.scene_images[scene_id] = set(cams)
            rep.n_images += len(cams)
        if gt is not None:
            rep.n_gt_instances += sum(len(v) for v in gt.values())
            self.gt_counts[scene_id] = Counter((im, g.obj_id) for im, lst in gt.items() for g in lst)
        if gt is not None and info is not None:
            self._gt_vs_info(gt, info, gt_path, info_path)
        if gt is not None and cams is not None:
            for im in sorted(set(gt) - set(cams)):
                p.add(gt_path, f"image {im}", f"has ground truth but no camera in {cam_path.name}", check="ids")
            for im in sorted(set(cams) - set(gt)):
                p.add(gt_path, f"image {im}", f"no entry (expected one per image of {cam_path.name}; [] when no "
                      "object is annotated)", check="ids")
        poses_ok = self._check_gt_poses(gt, gt_path) if gt is not None else {}
        if cams is None:
            return

        # per-image files
        ids = sorted(cams)
        if self.max_images:
            ids = ids[:self.max_images]
        rep.n_images_checked += len(ids)
        try:
            img_dir = ds.image_dir(scene_id)
        except CosyError as e:
            p.error(e)
            img_dir = None
        depth_dir = next((sdir / n for n in ([f"depth_{sensor}"] if sensor else []) + ["depth"] if (sdir / n).is_dir()),
                         None)
        mask_dirs = [ds.mask_path(scene_id, 0, 0, visib=v).parent for v in (False, True)]
        mask_dirs = [d for d in mask_dirs if d.is_dir()]
        rep.has_depth |= depth_dir is not None
        rep.has_masks |= bool(mask_dirs)
        n_inst = {im: len(v) for im, v in (gt if gt is not None else info if info is not None else {}).items()}

        rgb: dict[int, Path] = {}
        sizes: dict[int, tuple[int, int]] = {}
        if img_dir is not None:
            for im in ids:
                path = _find_image(img_dir, im)
                if path is None:
                    p.add(img_dir / f"{im:06d}.png", f"image {im}", f"not found (expected an image "
                          f"{img_dir.name}/{im:06d}.png or .jpg for every image id of {cam_path.name})",
                          group=img_dir, check="missing image")
                    continue
                rgb[im] = path
                try:
                    sizes[im] = _header_size(path)
                except CosyError as e:
                    p.error(e, group=img_dir, check="unreadable image")

        # expected size: the camera file's (classic layout; BOP-H3 sensors differ), else the most
        # common one of the scene; the rules of the stages' readers (cosy_cli.io.dataset)
        if self.camera is not None and sensor is None:
            expected, source = (self.camera.width, self.camera.height), self.camera_name
            other = set(sizes.values())
            if len(other) == 1 and len(sizes) == len(ids) and tuple(next(iter(other))) != tuple(expected):
                wh = next(iter(other))
                if all(pp_central(cams[im].K, wh) for im in ids):  # the camera file describes another split
                    self.other_split_scenes.append((scene_id, wh))
                    expected, source = wh, f"the other images of scene {scene_id}"
        elif sizes:
            expected = Counter(sizes.values()).most_common(1)[0][0]
            source = f"the other images of scene {scene_id}"
        else:
            expected, source = None, ""
        if expected is not None:
            for im, wh in sizes.items():
                if tuple(wh) != tuple(expected):
                    K = cams[im].K
                    also = f"; cam_K's principal point ({K[0, 2]:.6g}, {K[1, 2]:.6g}) lies outside it" \
                        if pp_outside(K, wh) else ""
                    p.add(rgb[im], f"image {im}", f"image is {_fmt_size(wh)} px, expected {_fmt_size(expected)} "
                          f"({source}{also})", group=img_dir, check="image size")
        self._check_scene_camera(cams, cam_path, expected)

        def size_check(path: Path, im: int, what: str, group: Path) -> bool:
            try:
                wh = _header_size(path)
            except CosyError as e:
                p.error(e, group=group, check=f"unreadable {what}")
                return False
            ref, src = (expected, source) if expected is not None else (sizes.get(im), "its image")
            if ref is not None and tuple(wh) != tuple(ref):
                p.add(path, f"image {im}", f"{what} is {_fmt_size(wh)} px, expected {_fmt_size(ref)} ({src})",
                      group=group, check=f"{what} size")
                return False
            return True

        depth: dict[int, Path] = {}
        if depth_dir is not None:
            for im in ids:
                path = _find_image(depth_dir, im)
                if path is None:
                    p.add(depth_dir / f"{im:06d}.png", f"image {im}", f"depth image not found (the scene has a "
                          f"{depth_dir.name}/ folder: expected one depth image per image id)",
                          group=depth_dir, check="missing depth")
                elif size_check(path, im, "depth image", depth_dir):
                    depth[im] = path
        masks: dict[tuple[str, int, int], Path] = {}
        for mdir in mask_dirs:
            for im in ids:
                for k in range(n_inst.get(im, 0)):
                    path = mdir / f"{im:06d}_{k:06d}.png"
                    if not path.is_file():
                        p.add(path, f"image {im}, instance {k}", f"mask not found (the scene has a {mdir.name}/ "
                              "folder: expected one mask per GT instance)", group=mdir, check="missing mask")
                    elif size_check(path, im, "mask", mdir):
                        masks[(mdir.name, im, k)] = path

        # decode a sample (or everything) to catch corrupt files, and compare depth with GT
        if self.full or len(ids) <= self.sample_per_scene:
            sample = ids
        else:
            sample = [ids[i] for i in np.unique(np.linspace(0, len(ids) - 1, self.sample_per_scene).round().astype(int))]
        for im in sample:
            if im not in rgb or im not in sizes:  # missing or unreadable header: already reported
                continue
            rep.n_images_decoded += 1
            try:
                images.read_rgb(rgb[im])
            except CosyError as e:
                p.error(e, group=img_dir, check="corrupt image")
            dmm = None
            if im in depth:
                try:
                    dmm = images.read_depth(depth[im], cams[im].depth_scale)
                except CosyError as e:
                    p.error(e, group=depth_dir, check="corrupt depth")
            for k in range(n_inst.get(im, 0)):
                for mdir in mask_dirs:
                    mp = masks.get((mdir.name, im, k))
                    if mp is None:
                        continue
                    try:
                        m = images.read_mask(mp)
                    except CosyError as e:
                        p.error(e, group=mdir, check="corrupt mask")
                        continue
                    if mdir.name.startswith("mask_visib") and dmm is not None and (im, k) in poses_ok \
                            and m.shape == dmm.shape:
                        self._depth_vs_gt(dmm, m, depth[im], im, k, poses_ok[(im, k)])
            if dmm is not None and gt is not None and not any(d.name.startswith("mask_visib") for d in mask_dirs):
                self._depth_scale(dmm, cams[im], gt.get(im, []), poses_ok, depth[im], scene_id, im)

    def _depth_scale(self, depth_mm, cam, insts, poses_ok, depth_path: Path, scene_id: int, im: int) -> None:
        """Without visible masks: the stages' check (:func:`cosy_cli.io.dataset.depth_vs_gt`, the GT
        boxes' centres against the measured depth); one warning for the split (see check_scenes)."""
        if self.objects is None or scene_id in self.depth_scale_done:
            return
        keep = [k for k in range(len(insts)) if (im, k) in poses_ok]
        if not keep:
            return
        T = np.stack([insts[k].T_cam_obj for k in keep])
        corners = np.stack([self.objects[insts[k].obj_id].corners for k in keep])
        measured, z_min, z_max = depth_vs_gt(depth_mm, cam.K, T, corners)
        ok = np.isfinite(measured)
        if not ok.any():
            return
        self.depth_scale_done.add(scene_id)
        zc = T[ok, 2, 3]
        tol = DEPTH_SCALE_RTOL * zc
        off = (measured[ok] < z_min[ok] - tol) | (measured[ok] > z_max[ok] + tol)
        if 2 * int(off.sum()) > len(off):
            self.depth_scale_off.append((depth_path, im, float(np.median(measured[ok] / zc)), int(off.sum()),
                                         len(off), cam.depth_scale))

    def _gt_vs_info(self, gt, info, gt_path: Path, info_path: Path) -> None:
        p = self.p
        for im in sorted(set(gt) - set(info)):
            p.add(info_path, f"image {im}", f"no entry, but {gt_path.name} has one (expected the same image ids)",
                  check="ids")
        for im in sorted(set(info) - set(gt)):
            p.add(info_path, f"image {im}", f"entry for an image that {gt_path.name} does not have", check="ids")
        for im in sorted(set(gt) & set(info)):
            if len(gt[im]) != len(info[im]):
                p.add(info_path, f"image {im}", f"{len(info[im])} instance(s), {gt_path.name} has {len(gt[im])} "
                      "(expected the same instances in the same order)", check="counts")
            for k, g in enumerate(info[im]):
                if not (0.0 <= g.visib_fract <= 1.0):
                    p.add(info_path, f"image {im}, instance {k}", f"visib_fract {g.visib_fract:g} outside [0, 1]",
                          check="visib_fract")

    def _check_gt_poses(self, gt, gt_path: Path) -> dict[tuple[int, int], tuple[float, float]]:
        """Rotations, known objects, objects in front of the camera. Returns {(im, k): (z_min, z_max) mm}
        of the instances that passed (for the depth check)."""
        p = self.p
        flat = [(im, k, g) for im, lst in gt.items() for k, g in enumerate(lst)]
        if not flat:
            return {}
        ims = np.array([f[0] for f in flat])
        ks = np.array([f[1] for f in flat])
        obj_ids = np.array([f[2].obj_id for f in flat])
        T = np.stack([f[2].T_cam_obj for f in flat])
        err = bop.rotation_errors(T[:, :3, :3])

        def where(i):
            return f"image {ims[i]}, instance {ks[i]} (obj_id {obj_ids[i]})"

        good = err <= bop.ROTATION_REPAIR_TOL  # the reader repaired those (one warning for the file)
        for i in np.flatnonzero(~good):
            det = np.linalg.det(T[i, :3, :3])
            p.add(gt_path, where(i), f"cam_R_m2c is not a rotation matrix (|R^T R - I| = {err[i]:.3g}, "
                  f"det = {det:.3g}; expected orthonormal with det +1, tolerated up to {bop.ROTATION_REPAIR_TOL:g})",
                  check="rotation")
        if self.objects is None:
            return {}
        known = np.isin(obj_ids, list(self.objects))
        for i in np.flatnonzero(~known):
            p.add(gt_path, where(i), f"obj_id {obj_ids[i]} is not in {self.ds.models_info_path.name} "
                  f"(known: {_ids(self.objects)})", check="obj_id")
        out = {}
        for i in np.flatnonzero(good & known):
            obj = self.objects[int(obj_ids[i])]
            z = obj.corners @ T[i, 2, :3] + T[i, 2, 3]
            if (z <= 0).any():
                hull = obj.hull_vertices()
                if hull is not None:
                    z = hull @ T[i, 2, :3] + T[i, 2, 3]
            if (z <= 0).all():
                p.add(gt_path, where(i), f"object behind the camera (t_z = {T[i, 2, 3]:.6g} mm, model z from "
                      f"{z.min():.6g} to {z.max():.6g} mm; expected the whole model at z > 0)", check="behind")
            elif (z <= 0).any():
                p.add(gt_path, where(i), f"object straddles the camera plane (t_z = {T[i, 2, 3]:.6g} mm, model z from "
                      f"{z.min():.6g} to {z.max():.6g} mm; expected the whole model at z > 0)", check="behind")
            else:
                out[(int(ims[i]), int(ks[i]))] = (float(z.min()), float(z.max()))
        return out

    def _check_scene_camera(self, cams, cam_path: Path, size) -> None:
        p = self.p
        ids = np.array(list(cams))
        K = np.stack([c.K for c in cams.values()])
        ds_ = np.array([c.depth_scale for c in cams.values()])
        for problem in (bop.focal_problem, bop.last_row_problem):  # the reader's checks, here for every image
            for i in range(len(ids)):
                msg = problem(K[i])
                if msg:
                    p.add(cam_path, f"image {ids[i]}", msg, check="cam_K")
        if size is not None:
            for i in range(len(ids)):
                msg = self._pp_problem(K[i], size)
                if msg:
                    p.add(cam_path, f"image {ids[i]}", "cam_K: " + msg, check="principal point")
        for i in range(len(ids)):
            msg = bop.depth_scale_problem(ds_[i])
            if msg:
                p.add(cam_path, f"image {ids[i]}", msg, check="depth_scale")
        posed = [(im, c.T_cam_world) for im, c in cams.items() if c.T_cam_world is not None]
        if posed:
            R = np.stack([T[:3, :3] for _, T in posed])
            err = bop.rotation_errors(R)
            for i in np.flatnonzero(err > bop.ROTATION_REPAIR_TOL):  # within it: repaired by the reader
                p.add(cam_path, f"image {posed[i][0]}", f"cam_R_w2c is not a rotation matrix (|R^T R - I| = {err[i]:.3g}, "
                      f"det = {np.linalg.det(R[i]):.3g}; expected orthonormal with det +1, tolerated up to "
                      f"{bop.ROTATION_REPAIR_TOL:g})", check="rotation")

    def _depth_vs_gt(self, depth_mm: np.ndarray, mask: np.ndarray, depth_path: Path, im: int, k: int, zrange) -> None:
        vals = depth_mm[mask & (depth_mm > 0)]
        if vals.size < MIN_DEPTH_PIXELS:
            return
        z_obs = float(np.median(vals))
        z_min, z_max = zrange
        margin = DEPTH_RTOL * 0.5 * (z_min + z_max)
        if z_obs < z_min - margin or z_obs > z_max + margin:
            self.p.add(depth_path, f"image {im}, instance {k}",
                       f"median depth {z_obs:.6g} mm in the object's visible mask, but its GT pose puts it between "
                       f"{z_min:.6g} and {z_max:.6g} mm (expected within {DEPTH_RTOL:.0%}; wrong depth_scale or GT?)",
                       group=depth_path.parent, check="depth vs GT")

    # ---- targets --------------------------------------------------------------------------
    def check_targets(self) -> None:
        ds, p, rep = self.ds, self.p, self.rep
        path = ds.targets_path()
        if path is None or ds.split != "test":
            return
        rep.targets_file = path.name
        try:
            tg = bop.read_targets(path)
        except CosyError as e:
            p.error(e)
            return
        rep.n_targets = len(tg)
        scenes = set(self.scene_ids)
        if not scenes:
            return  # the split itself is missing: already reported
        for i, (s, im, o, n) in enumerate(tg[["scene_id", "im_id", "obj_id", "inst_count"]].itertuples(index=False)):
            where = f"entry {i} (scene {s}, image {im}, obj_id {o})"
            if s not in scenes:
                p.add(path, where, f"scene {s} is not in {ds.split_name}/ (scenes: {_ids(scenes)})", check="scene")
                continue
            if self.objects is not None and o not in self.objects:
                p.add(path, where, f"obj_id {o} is not in {ds.models_info_path.name} (known: {_ids(self.objects)})",
                      check="obj_id")
            if s in self.scene_images and im not in self.scene_images[s]:
                p.add(path, where, f"image {im} is not in scene {s}'s scene_camera.json", check="image")
                continue
            if s in self.gt_counts:
                have = self.gt_counts[s][(im, o)]
                if n > have:
                    p.add(path, where, f"inst_count {n}, but scene_gt.json has {have} instance(s) of obj_id {o} "
                          "in that image (expected inst_count <= GT instances)", check="inst_count")


@contextmanager
def _quiet_opencv():
    import cv2

    log = cv2.utils.logging
    level = log.getLogLevel()
    log.setLogLevel(log.LOG_LEVEL_ERROR)
    try:
        yield
    finally:
        log.setLogLevel(level)


def _vec(v) -> str:
    return " ".join(f"{float(x):.6g}" for x in np.asarray(v).reshape(-1))


def validate_dataset(root: str | Path, split: str = "test", split_type: str | None = None, *,
                     models_dir: str = "models", max_images: int | None = None, full: bool = False,
                     sample_per_scene: int = 2, symmetry_tol_mm: float | None = None, symmetry_steps: int = 16,
                     symmetry_percentile: float = 99.0, max_per_check: int | None = 20,
                     progress: bool = True, camera: str | Path | None = None) -> ValidationReport:
    """Check the BOP dataset at ``root`` (split ``split[_split_type]``) and collect its problems.

    ``models_dir``: the models folder, relative to ``root`` (or absolute). ``max_images``: check
    the files of at most this many images per scene (None: all; JSON checks always cover all).
    ``full``: decode every checked image, depth and mask (default: ``sample_per_scene`` images
    per scene, spread over the scene). ``symmetry_tol_mm``: tolerated symmetry residual (default
    max(1 mm, 1 % of the diameter)); continuous symmetries are tried at ``symmetry_steps`` angles.
    ``max_per_check``: problem lines per file and kind of check before the rest are only counted
    (None or 0: all). ``camera``: the dataset camera file, relative to ``root`` or absolute
    (default: camera_<split_type>.json, camera.json, or the only camera_*.json there).
    Tolerated problems (:class:`~cosy_cli.errors.CosyWarning`: rotations repaired at read time,
    approximate symmetries, no scene_gt_info.json) go to ``report.warnings``, one line each, not
    to ``report.problems``. Raises :class:`CosyError` only when ``root`` is not a folder.
    """
    t0 = time.perf_counter()
    ds = BopDataset(Path(root), split, split_type or None, models_subdir=str(models_dir), camera_file=camera)
    rep = ValidationReport(root=ds.root, split=ds.split_name)
    probs = _Problems(max_per_check)
    v = _Validator(ds, rep, probs, max_images=max_images, full=full, sample_per_scene=max(1, int(sample_per_scene)),
                   symmetry_tol_mm=symmetry_tol_mm, symmetry_steps=max(2, int(symmetry_steps)),
                   symmetry_percentile=float(symmetry_percentile), progress=progress)
    with _quiet_opencv(), warnings.catch_warnings(record=True) as caught:  # opencv: would interleave with the lines
        warnings.simplefilter("always", CosyWarning)
        forget_reported_textures()  # this run's report lists them, even if an earlier load reported them
        v.check_camera()
        v.check_models()
        v.check_scenes()
        v.check_targets()
    rep.warning_records = console.capture_records(caught)  # passes on the warnings that are not ours
    rep.warnings = [w["text"] for w in rep.warning_records]
    rep.problems = probs.finish()
    rep.seconds = time.perf_counter() - t0
    return rep
