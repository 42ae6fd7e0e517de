"""Synthetic BOP scenes: the procedural objects resting on a table, seen by several cameras.

A scene is N objects (distinct while N <= 8) lying in stable poses on a table (the plane z = 0
of the world frame, mm), with random colours, viewed by V cameras at 400-800 mm from the table
centre, 25-70 deg above it, spread in azimuth and looking at the centre with a small jitter.
Each view has its own light and background image. The table is rendered (it shows in RGB and
depth and occludes nothing) but is not a BOP object: it is absent from the ground truth.

Randomness: scene k of a split is drawn from ``np.random.default_rng([seed, crc32(split), k])``,
so it depends only on (seed, split, k): generating 3 or 30 scenes gives the same first 3.

Ground truth follows the BOP toolkit's conventions (``scripts/calc_gt_info.py``):

- ``mask/``: the full silhouette of each instance (rendered alone), ``mask_visib/``: its
  visible part (the instance map of the whole scene);
- ``bbox_obj``/``bbox_visib``: (x, y, w, h) of these masks with ``w = x_max - x_min`` and
  ``h = y_max - y_min`` like ``bop_toolkit_lib.misc.calc_2d_bbox``; ``[-1, -1, -1, -1]`` for
  an empty mask (the object is outside the image);
- ``px_count_all``: silhouette pixels, ``px_count_visib``: visible pixels,
  ``px_count_valid``: silhouette pixels with a depth measurement (> 0), ``visib_fract`` =
  visib / all (0 when all = 0).
"""

from __future__ import annotations

import colorsys
import math
import os
import shutil
import tempfile
import time
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import CosyError
from ..geometry.poses import invert, look_at, make_pose
from ..geometry.rotations import rotation_about_axis
from ..io import bop, images
from ..io.atomic import atomic_dir
from . import objects as objs

TABLE_ID = 0  # renderer id of the table mesh (BOP object ids start at 1)
TABLE_SIZE_MM = 1400.0
TABLE_THICKNESS_MM = 30.0
DEPTH_SCALE = 0.1  # depth png value x 0.1 = mm (as T-LESS): 0.1 mm steps, up to 6.5 m
FOCAL_PER_WIDTH = 1.3  # fx = fy = 832 px at 640 x 480 (a 42 x 32 deg field of view, close to T-LESS)
CAMERA_DISTANCE_MM = (400.0, 800.0)
CAMERA_ELEVATION_DEG = (25.0, 70.0)
CAMERA_ROLL_DEG = 8.0  # uniform in +-, about the optical axis
TARGET_JITTER_MM = 25.0  # std of the look-at point about the table centre (x, y)
PLACEMENT_MARGIN_MM = 3.0  # least gap between the footprints of two objects
TARGETS_MIN_VISIB = 0.1  # BOP19 test targets: instances at least this visible
SPLITS_WITH_TARGETS = ("test",)


# --------------------------------------------------------------------------------------------
# what a scene is made of (pure numpy, no rendering)
# --------------------------------------------------------------------------------------------
@dataclass
class SceneLayout:
    """Everything random about one scene. Poses are 4x4, mm; colours RGB 0..1.

    obj_ids (N,), T_world_obj (N, 4, 4), colors (N, 3); table_color (3,);
    T_world_cam (V, 4, 4); light_dir_world (V, 3) (direction the light travels);
    light_intensity (V,); ambient (V,); background_seeds (V,) (for :func:`random_background`).
    """

    obj_ids: np.ndarray
    T_world_obj: np.ndarray
    colors: np.ndarray
    table_color: np.ndarray
    T_world_cam: np.ndarray
    light_dir_world: np.ndarray
    light_intensity: np.ndarray
    ambient: np.ndarray
    background_seeds: np.ndarray

    @property
    def T_cam_world(self) -> np.ndarray:
        return invert(self.T_world_cam)

    def T_cam_obj(self, view: int) -> np.ndarray:
        """(N, 4, 4) poses of the objects in camera ``view`` (mm)."""
        return invert(self.T_world_cam[view])[None] @ self.T_world_obj


def camera_matrix(width: int, height: int) -> np.ndarray:
    """K (3x3, pixels) of the synthetic camera: fx = fy = 1.3 width, principal point at the
    image centre ((width - 1) / 2, (height - 1) / 2; pixel centres at integers)."""
    f = FOCAL_PER_WIDTH * width
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def scene_rng(seed: int, split: str, index: int) -> np.random.Generator:
    """The generator of scene ``index`` (0-based) of ``split``: depends on these three only."""
    return np.random.default_rng([int(seed), zlib.crc32(split.encode("utf-8")), int(index)])


def choose_objects(rng: np.random.Generator, n: int, obj_ids=objs.OBJECT_IDS) -> np.ndarray:
    """n object ids: distinct while n <= len(obj_ids), then repeats drawn at random."""
    ids = np.asarray(obj_ids, dtype=np.int64)
    first = rng.permutation(ids)[:min(n, len(ids))]
    extra = rng.choice(ids, size=max(0, n - len(ids)))
    return np.sort(np.concatenate([first, extra]))


def footprint(obj_id: int, R: np.ndarray) -> np.ndarray:
    """(M, 2) convex polygon (counter-clockwise, mm) of the object's shadow on the table under
    rotation R, about the object origin."""
    from scipy.spatial import ConvexHull

    xy = (objs.solid_mesh(obj_id).vertices @ R.T)[:, :2]
    return xy[ConvexHull(xy).vertices]


def polygons_apart(a: np.ndarray, b: np.ndarray, gap: float) -> bool:
    """True when convex polygons a, b (M, 2) are separated by at least ``gap`` along some edge
    normal of either (separating axis test; mm)."""
    for poly in (a, b):
        e = np.roll(poly, -1, axis=0) - poly
        n = np.stack([e[:, 1], -e[:, 0]], axis=1)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        pa, pb = a @ n.T, b @ n.T  # (Ma, E), (Mb, E)
        if np.any((pb.min(0) - pa.max(0) >= gap) | (pa.min(0) - pb.max(0) >= gap)):
            return True
    return False


def place_objects(rng: np.random.Generator, obj_ids: np.ndarray, margin: float = PLACEMENT_MARGIN_MM,
                  fill: float | None = None) -> np.ndarray:
    """T_world_obj (N, 4, 4): each object in a stable pose lying on z = 0 with a random yaw, at
    random places where their convex footprints stay ``margin`` mm apart, inside a disc whose
    area is the objects' total footprint area / ``fill`` (random in 0.25-0.5 by default: from
    spread out to cluttered; the disc grows when an object does not fit)."""
    n = len(obj_ids)
    if fill is None:
        fill = rng.uniform(0.25, 0.5)
    Rs = np.stack([objs.resting_rotation(int(o), rng) for o in obj_ids]) if n else np.zeros((0, 3, 3))
    polys = [footprint(int(o), R) for o, R in zip(obj_ids, Rs)]
    # lowest point of each rotated object onto the table
    lift = np.array([-float((objs.solid_mesh(int(o)).vertices @ R.T)[:, 2].min()) for o, R in zip(obj_ids, Rs)])
    areas = [0.5 * abs(float(np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1]))) for p in polys]
    area_r = max(100.0, math.sqrt(sum(areas) / fill / math.pi))
    centres = np.zeros((n, 2))
    order = np.argsort(-np.asarray(areas), kind="stable")  # biggest first
    placed: list[int] = []
    for i in order:
        for attempt in range(100_000):
            if attempt and attempt % 100 == 0:
                area_r *= 1.05
            rho = area_r * math.sqrt(rng.uniform())
            phi = rng.uniform(0, 2 * math.pi)
            c = np.array([rho * math.cos(phi), rho * math.sin(phi)])
            if all(polygons_apart(polys[i] + c, polys[j] + centres[j], margin) for j in placed):
                break
        centres[i] = c
        placed.append(i)
    t = np.concatenate([centres, lift[:, None]], axis=1)
    return make_pose(Rs, t)


def sample_cameras(rng: np.random.Generator, n_views: int, target=(0.0, 0.0, 0.0)) -> np.ndarray:
    """T_world_cam (V, 4, 4) of OpenCV cameras around ``target`` (mm): distance 400-800 mm,
    elevation 25-70 deg, azimuths stratified over the full turn, looking at the target with a
    jitter of ~25 mm and a small roll."""
    target = np.asarray(target, dtype=np.float64)
    az0 = rng.uniform(0, 2 * math.pi)
    az = az0 + (np.arange(n_views) + rng.uniform(0.15, 0.85, n_views)) * 2 * math.pi / max(n_views, 1)
    el = np.radians(rng.uniform(*CAMERA_ELEVATION_DEG, n_views))
    dist = rng.uniform(*CAMERA_DISTANCE_MM, n_views)
    look = target + np.concatenate([rng.normal(0, TARGET_JITTER_MM, (n_views, 2)),
                                    rng.uniform(0, 40, (n_views, 1))], axis=1)
    eye = target + dist[:, None] * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    T = look_at(eye, look, up=(0.0, 0.0, 1.0))
    roll = np.radians(rng.uniform(-CAMERA_ROLL_DEG, CAMERA_ROLL_DEG, n_views))
    R_roll = rotation_about_axis(np.array([0.0, 0.0, 1.0]), roll)  # about the camera's optical axis
    T[:, :3, :3] = T[:, :3, :3] @ R_roll
    return T


def _hsv(h, s, v) -> np.ndarray:
    return np.array(colorsys.hsv_to_rgb(float(h) % 1.0, float(np.clip(s, 0, 1)), float(np.clip(v, 0, 1))))


def object_colors(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) RGB 0..1, T-LESS-like: mostly greys, some browns/beiges, some random colours."""
    out = np.zeros((n, 3))
    kinds = rng.choice(3, size=n, p=[0.55, 0.25, 0.20])
    for i, k in enumerate(kinds):
        if k == 0:
            out[i] = np.clip(rng.uniform(0.35, 0.85) + rng.normal(0, 0.02, 3), 0, 1)
        elif k == 1:
            out[i] = _hsv(rng.uniform(0.05, 0.12), rng.uniform(0.25, 0.6), rng.uniform(0.4, 0.85))
        else:
            out[i] = _hsv(rng.uniform(0, 1), rng.uniform(0.3, 0.8), rng.uniform(0.4, 0.9))
    return out


def sample_scene(rng: np.random.Generator, n_objects: int, n_views: int) -> SceneLayout:
    """All random choices of one scene (objects, poses, colours, cameras, lights, backgrounds)."""
    obj_ids = choose_objects(rng, n_objects)
    T_world_obj = place_objects(rng, obj_ids)
    colors = object_colors(rng, len(obj_ids))
    table_color = _hsv(rng.uniform(0, 1), rng.uniform(0.0, 0.5), rng.uniform(0.15, 0.9))
    T_world_cam = sample_cameras(rng, n_views)
    az = rng.uniform(0, 2 * math.pi, n_views)
    el = np.radians(rng.uniform(35, 90, n_views))
    light = -np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    return SceneLayout(
        obj_ids=obj_ids, T_world_obj=T_world_obj, colors=colors, table_color=table_color,
        T_world_cam=T_world_cam, light_dir_world=light, light_intensity=rng.uniform(0.5, 0.85, n_views),
        ambient=rng.uniform(0.2, 0.45, n_views), background_seeds=rng.integers(0, 2**31, n_views),
    )


def random_background(seed: int, width: int, height: int) -> np.ndarray:
    """(H, W, 3) uint8: a flat colour, a linear gradient or smooth low-frequency blobs."""
    import cv2

    rng = np.random.default_rng(int(seed))
    kind = int(rng.integers(3))
    c0, c1 = rng.uniform(0, 255, 3), rng.uniform(0, 255, 3)
    if kind == 0:
        img = np.broadcast_to(c0, (height, width, 3))
    elif kind == 1:
        a = rng.uniform(0, 2 * math.pi)
        yy, xx = np.mgrid[0:height, 0:width]
        s = (np.cos(a) * xx / width + np.sin(a) * yy / height)
        s = (s - s.min()) / max(np.ptp(s), 1e-9)
        img = c0 + s[..., None] * (c1 - c0)
    else:
        grid = rng.uniform(0, 255, (int(rng.integers(3, 7)), int(rng.integers(4, 9)), 3)).astype(np.float32)
        img = cv2.resize(grid, (width, height), interpolation=cv2.INTER_CUBIC)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def table_mesh():
    """The table: a flat box (mm), top face at z = 0, normals split at its edges."""
    import trimesh

    box = trimesh.creation.box((TABLE_SIZE_MM, TABLE_SIZE_MM, TABLE_THICKNESS_MM))
    box.apply_translation((0.0, 0.0, -TABLE_THICKNESS_MM / 2))
    shaded = trimesh.graph.smooth_shade(box, angle=math.radians(30), facet_minarea=None)
    return trimesh.Trimesh(shaded.vertices, shaded.faces, vertex_normals=shaded.vertex_normals, process=False)


# --------------------------------------------------------------------------------------------
# rendering one view and its ground truth
# --------------------------------------------------------------------------------------------
@dataclass
class RenderedView:
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32 mm, 0 = nothing
    masks: np.ndarray  # (N, H, W) bool full silhouettes
    masks_visib: np.ndarray  # (N, H, W) bool visible parts
    T_cam_obj: np.ndarray  # (N, 4, 4) mm
    gt_info: list  # [bop.GtInfo] * N


def mask_bbox(mask: np.ndarray) -> np.ndarray:
    """(4,) x, y, w, h of a mask as the BOP toolkit (w = x_max - x_min); -1s when empty."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return np.array([-1, -1, -1, -1])
    cols = np.flatnonzero(mask.any(axis=0))
    return np.array([cols[0], rows[0], cols[-1] - cols[0], rows[-1] - rows[0]])


def gt_infos(masks: np.ndarray, masks_visib: np.ndarray, depth: np.ndarray) -> list[bop.GtInfo]:
    """scene_gt_info entries of N instances from their masks (N, H, W) and the depth (H, W, mm)."""
    n = len(masks)
    flat = masks.reshape(n, -1)
    all_ = flat.sum(1)
    visib = masks_visib.reshape(n, -1).sum(1)
    valid = (flat & (depth.reshape(1, -1) > 0)).sum(1)
    return [bop.GtInfo(bbox_obj=mask_bbox(masks[i]), bbox_visib=mask_bbox(masks_visib[i]),
                       px_count_all=int(all_[i]), px_count_valid=int(valid[i]), px_count_visib=int(visib[i]),
                       visib_fract=float(visib[i] / all_[i]) if all_[i] > 0 else 0.0)
            for i in range(n)]


def render_view(renderer, K: np.ndarray, layout: SceneLayout, view: int, width: int, height: int) -> RenderedView:
    """Render RGB, depth (mm) and masks of one view; the table is drawn but gets no GT."""
    n = len(layout.obj_ids)
    T_cam_world = invert(layout.T_world_cam[view])
    T_cam_obj = T_cam_world[None] @ layout.T_world_obj
    ids = [int(o) for o in layout.obj_ids] + [TABLE_ID]
    poses = np.concatenate([T_cam_obj, T_cam_world[None]])  # the table mesh is in the world frame
    colors = np.concatenate([layout.colors, layout.table_color[None]])
    light = T_cam_world[:3, :3] @ layout.light_dir_world[view]
    out = renderer.render(K, ids, poses, colors=colors,
                          background=random_background(layout.background_seeds[view], width, height),
                          light_dir=light, light_intensity=float(layout.light_intensity[view]),
                          ambient=float(layout.ambient[view]))
    masks = renderer.render_silhouettes(K, ids[:n], T_cam_obj) if n else np.zeros((0, height, width), bool)
    masks_visib = out.instance[None] == np.arange(n)[:, None, None]
    # Silhouettes are rasterised in tiles of another framebuffer: an edge pixel can fall on the
    # other side of a triangle edge there. A visible pixel is part of the silhouette by definition.
    masks |= masks_visib
    return RenderedView(rgb=out.rgb, depth=out.depth, masks=masks, masks_visib=masks_visib, T_cam_obj=T_cam_obj,
                        gt_info=gt_infos(masks, masks_visib, out.depth))


# --------------------------------------------------------------------------------------------
# writing a dataset
# --------------------------------------------------------------------------------------------
@dataclass
class SynthSummary:
    """What :func:`generate_dataset` wrote."""

    out: Path
    split: str
    n_scenes: int
    n_images: int
    n_instances: int
    n_objects: int  # object models
    bytes_on_disk: int
    seconds: float
    mode: str  # "created", "replaced", "added split", "replaced split", "models only", "models exist"


def _dir_size(path: Path) -> int:
    return sum(p.stat().st_size for p in Path(path).rglob("*") if p.is_file())


def _write_scene(scene_dir: Path, scene_id: int, layout: SceneLayout, renderer, K: np.ndarray, width: int,
                 height: int, rgb_ext: str, progress_bar, pool, sensor: str | None = None,
                 gray: bool = False) -> list[dict]:
    """Render and write one scene folder; returns its BOP19 target rows. Image files are
    encoded by the thread ``pool`` while the next view renders (one view in flight).
    ``sensor``: write the multi-sensor layout's folders and files of this sensor
    (``rgb_<sensor>/`` or, with ``gray``, ``gray_<sensor>/``; ``scene_camera_<sensor>.json``...)."""
    suffix = f"_{sensor}" if sensor else ""
    image_folder = ("gray" if gray else "rgb") + suffix
    cams, gts, infos, targets = {}, {}, {}, []
    pending: list = []
    for v in range(len(layout.T_world_cam)):
        r = render_view(renderer, K, layout, v, width, height)
        for f in pending:  # the previous view's files: errors surface here
            f.result()
        write_image = images.write_gray if gray else images.write_rgb
        pending = [pool.submit(write_image, scene_dir / image_folder / f"{v:06d}{rgb_ext}", r.rgb),
                   pool.submit(images.write_depth, scene_dir / f"depth{suffix}" / f"{v:06d}.png", r.depth,
                               DEPTH_SCALE)]
        for i in range(len(layout.obj_ids)):
            pending.append(pool.submit(images.write_mask, scene_dir / f"mask{suffix}" / f"{v:06d}_{i:06d}.png",
                                       r.masks[i]))
            pending.append(pool.submit(images.write_mask, scene_dir / f"mask_visib{suffix}" / f"{v:06d}_{i:06d}.png",
                                       r.masks_visib[i]))
        cams[v] = bop.SceneCamera(K=K, depth_scale=DEPTH_SCALE, T_cam_world=invert(layout.T_world_cam[v]))
        gts[v] = [bop.GtInstance(int(o), T) for o, T in zip(layout.obj_ids, r.T_cam_obj)]
        infos[v] = r.gt_info
        counts: dict[int, int] = {}
        for o, g in zip(layout.obj_ids, r.gt_info):
            if g.visib_fract >= TARGETS_MIN_VISIB:
                counts[int(o)] = counts.get(int(o), 0) + 1
        targets += [{"scene_id": scene_id, "im_id": v, "obj_id": o, "inst_count": c} for o, c in sorted(counts.items())]
        if progress_bar is not None:
            progress_bar.update(1)
    for f in pending:
        f.result()
    scene_dir.mkdir(parents=True, exist_ok=True)
    bop.write_scene_camera(scene_dir / f"scene_camera{suffix}.json", cams)
    bop.write_scene_gt(scene_dir / f"scene_gt{suffix}.json", gts)
    bop.write_scene_gt_info(scene_dir / f"scene_gt_info{suffix}.json", infos)
    return targets


def write_split(split_dir: Path, n_scenes: int, n_views: int, n_objects: int, *, seed: int, split: str,
                width: int, height: int, progress: bool = True, rgb_ext: str = ".png") -> pd.DataFrame:
    """Render ``n_scenes`` scenes (ids 1..n_scenes) into ``split_dir``; returns the BOP19
    targets (columns scene_id, im_id, obj_id, inst_count) of all images."""
    from concurrent.futures import ThreadPoolExecutor

    from ..console import progress as progress_bar

    from ..rendering import SceneRenderer

    K = camera_matrix(width, height)
    meshes = objs.object_meshes()
    meshes[TABLE_ID] = table_mesh()
    rows: list[dict] = []
    bar = progress_bar(total=n_scenes * n_views, desc=f"synth {split}", unit="img", enabled=progress)
    renderer = SceneRenderer(meshes, width, height, znear=10.0, zfar=20_000.0, smooth=True)
    try:
        with ThreadPoolExecutor(max_workers=2, thread_name_prefix="synth-write") as pool:  # png encoding frees the GIL
            for k in range(n_scenes):
                layout = sample_scene(scene_rng(seed, split, k), n_objects, n_views)
                rows += _write_scene(split_dir / f"{k + 1:06d}", k + 1, layout, renderer, K, width, height, rgb_ext,
                                     bar, pool)
    finally:
        renderer.close()
        bar.close()
    return pd.DataFrame(rows, columns=bop.TARGET_COLUMNS, dtype=np.int64)


def _camera_info(width: int, height: int) -> bop.CameraInfo:
    return bop.CameraInfo(K=camera_matrix(width, height), width=width, height=height, depth_scale=DEPTH_SCALE)


def _same_models(root: Path, reference: Path) -> bool:
    """True when root/models and root/models_eval hold exactly the files of ``reference``."""
    import filecmp

    for sub in ("models", "models_eval"):
        a, b = root / sub, reference / sub
        if not a.is_dir():
            return False
        names = sorted(p.name for p in b.iterdir())
        if sorted(p.name for p in a.iterdir() if not p.name.startswith(".")) != names:
            return False
        _, mismatch, errors = filecmp.cmpfiles(a, b, names, shallow=False)
        if mismatch or errors:
            return False
    return True


def _same_camera(root: Path, width: int, height: int) -> bool:
    p = root / "camera.json"
    if not p.is_file():
        return False
    try:
        cam = bop.read_camera(p)
    except CosyError:
        return False
    want = _camera_info(width, height)
    return (cam.width, cam.height) == (want.width, want.height) and np.allclose(cam.K, want.K) \
        and math.isclose(cam.depth_scale, want.depth_scale)


def _check_args(scenes: int, views: int, objects_per_scene: int, seed: int, width: int, height: int, split: str):
    for name, v, lo in (("scenes", scenes, 1), ("views", views, 1), ("objects", objects_per_scene, 1),
                        ("width", width, 16), ("height", height, 16), ("seed", seed, 0)):
        if not isinstance(v, (int, np.integer)) or v < lo:
            raise CosyError(f"--{name} must be an integer >= {lo}, got {v!r}")
    if not split or any(c in split for c in "/\\") or split.startswith(".") or split.startswith("models"):
        raise CosyError(f"--split must be a folder name such as test or train_pbr, got {split!r}")


def generate_dataset(out: str | os.PathLike, scenes: int, views: int, objects_per_scene: int, seed: int = 0,
                     width: int = 640, height: int = 480, split: str = "test", overwrite: bool = False,
                     models_only: bool = False, progress: bool = True) -> SynthSummary:
    """Write a complete BOP dataset of the procedural objects to ``out``.

    ``out`` gets ``models/``, ``models_eval/``, ``camera.json``, ``<split>/<scene_id>/`` with
    ``rgb/`` (png), ``depth/`` (16-bit png, x 0.1 = mm), ``mask/``, ``mask_visib/``,
    ``scene_camera.json`` (cam_K, depth_scale, cam_R_w2c, cam_t_w2c), ``scene_gt.json``,
    ``scene_gt_info.json`` and, for ``split == "test"``, ``test_targets_bop19.json``.
    ``objects_per_scene`` objects per scene, ``views`` images per scene of ``width`` x
    ``height`` pixels. Deterministic under ``seed``.

    Writing is atomic: the dataset (or the new split) is built in a temporary folder and renamed
    into place. An existing non-empty ``out`` is refused unless ``overwrite``, except that a new
    split is added to a dataset of these same objects and camera (e.g. ``train_pbr`` beside
    ``test``); with ``overwrite`` such a dataset keeps its other splits and only ``split`` is
    replaced, any other folder is replaced entirely.
    """
    t0 = time.perf_counter()
    _check_args(scenes, views, objects_per_scene, seed, width, height, split)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise CosyError("--out exists and is not a folder", path=out)
    existing = out.is_dir() and any(out.iterdir())
    n_objects = len(objs.OBJECTS)

    tmp_parent = out.parent if out.parent.is_dir() else None
    with tempfile.TemporaryDirectory(prefix=".cosy-synth-models.", dir=tmp_parent) as ref:
        ref = Path(ref)
        objs.write_models(ref)
        compatible = existing and _same_models(out, ref) and _same_camera(out, width, height)
        split_exists = compatible and (out / split).exists()

        if existing and not overwrite and not (compatible and (models_only or not split_exists)):
            if compatible:
                raise CosyError(f"split '{split}' exists already (use --overwrite to replace it)", path=out / split)
            if (out / "models" / "models_info.json").is_file():
                raise CosyError(f"output folder holds a dataset with other models or another camera than "
                                f"{width} x {height} (use --overwrite to replace it all, or another --out)", path=out)
            raise CosyError("output folder exists and is not empty (use --overwrite to replace it)", path=out)

        if models_only:
            if compatible:
                mode = "models exist"
            else:
                with atomic_dir(out, overwrite=True) as tmp:
                    _copy_models(ref, tmp)
                    bop.write_camera(tmp / "camera.json", _camera_info(width, height))
                mode = "replaced" if existing else "created"
            return SynthSummary(out, split, 0, 0, 0, n_objects, _dir_size(out), time.perf_counter() - t0, mode)

        if compatible:
            with atomic_dir(out / split, overwrite=True) as tmp:
                targets = write_split(tmp, scenes, views, objects_per_scene, seed=seed, split=split, width=width,
                                      height=height, progress=progress)
            if split in SPLITS_WITH_TARGETS:
                bop.write_targets(out / "test_targets_bop19.json", targets)
            mode = "replaced split" if split_exists else "added split"
        else:
            with atomic_dir(out, overwrite=True) as tmp:  # `out` is absent, empty, or --overwrite was given
                _copy_models(ref, tmp)
                bop.write_camera(tmp / "camera.json", _camera_info(width, height))
                targets = write_split(tmp / split, scenes, views, objects_per_scene, seed=seed, split=split,
                                      width=width, height=height, progress=progress)
                if split in SPLITS_WITH_TARGETS:
                    bop.write_targets(tmp / "test_targets_bop19.json", targets)
            mode = "replaced" if existing else "created"

    n_images = scenes * views
    return SynthSummary(out, split, scenes, n_images, n_images * objects_per_scene, n_objects, _dir_size(out),
                        time.perf_counter() - t0, mode)


def _copy_models(ref: Path, dest: Path) -> None:
    for sub in ("models", "models_eval"):
        shutil.copytree(ref / sub, dest / sub)
