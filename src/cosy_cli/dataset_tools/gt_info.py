"""``cosy gt-info``: a BOP split's ``scene_gt_info.json`` (and optionally ``mask/``, ``mask_visib/``)
computed from its GT poses, meshes and depth, as the BOP toolkit's ``calc_gt_info.py`` and
``calc_gt_masks.py`` define them.

Per GT instance of an image (lengths in mm, pixels with centres at integers):

- the object is rendered alone in its GT pose: depth ``z_obj`` (mm), its *silhouette* is where
  ``z_obj > 0``; depths become distances along the pixel rays (``dist = z * |K^-1 (u, v, 1)|``);
- the *scene distance* ``dist_scene`` is the measured depth image of the split (value x
  ``depth_scale``) when it has one, else the z-buffer of all GT objects of the image rendered
  together (an RGB-only split: occluders that are not GT objects are then unknown);
- visible pixels (the toolkit's ``bop19`` mode): silhouette pixels where ``dist_obj - dist_scene
  <= delta`` (15 mm) or the scene has no depth there (``bop18``: and it has);
- ``px_count_all``: silhouette pixels including the part outside the image (rendered into a canvas
  up to 3x the image, as the toolkit does); ``px_count_valid``: silhouette pixels inside the image
  with scene depth; ``px_count_visib``: visible pixels; ``visib_fract = px_count_visib /
  px_count_all`` (0 when the object projects to nothing);
- ``bbox_obj``: box [x, y, w, h] of the whole silhouette (may extend beyond the image),
  ``bbox_visib``: box of the visible pixels; ``w = x_max - x_min`` as in the toolkit; both are
  -1s when no pixel is visible.

Silhouettes are rasterised with the toolkit's pixel convention by default (its renderers put pixel
centres at half-integers, half a pixel up-left of cosy's OpenCV convention; setting
``toolkit_pixel_centres``): the published LM-O boxes are then reproduced to the pixel.

Masks (``--masks``): ``mask/IMID_GTID.png`` = the silhouette inside the image,
``mask_visib/IMID_GTID.png`` = the visible pixels (0/255 PNGs).

Per scene and resumable: a scene whose ``scene_gt_info.json`` exists and matches its
``scene_gt.json`` (same images, same number of instances; with masks: every mask file present) is
skipped unless ``overwrite``. Every file is written atomically; the info file is written last.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from ..conf import merge_conf
from ..errors import CosyError, warn
from ..io import bop, images
from ..io.dataset import BopDataset

GT_INFO_CONFS: dict[str, dict] = {
    "default": {
        "delta_mm": 15.0,  # visibility tolerance (the toolkit's delta; 5 for ITODD in the toolkit's notes)
        "visib_mode": "bop19",  # 'bop19': missing scene depth counts as visible; 'bop18': as not visible
        "visibility": "auto",  # 'auto': measured depth where the image has one, else GT z-buffer;
        # 'depth': require measured depth; 'zbuffer': always the z-buffer of all GT objects
        "canvas_factor": 3,  # silhouettes are rendered into up to this many image widths/heights
        # The toolkit's renderers put pixel centres at half-integers (a point projecting to u lands in
        # pixel floor(u)), half a pixel up-left of the OpenCV convention (round(u)) that cosy renders
        # with: True reproduces the toolkit's (and the published datasets') silhouettes and boxes.
        "toolkit_pixel_centres": True,
    },
}
VISIB_MODES = ("bop19", "bop18")
VISIBILITY_SOURCES = ("auto", "depth", "zbuffer")
ZNEAR_MM, ZFAR_MM = 1.0, 100_000.0


# --------------------------------------------------------------------------------------------
# pure functions
# --------------------------------------------------------------------------------------------
def ray_lengths(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) float32: |K^-1 (u, v, 1)| per pixel, so that distance along the ray = depth x this."""
    K = np.asarray(K, dtype=np.float64)
    u = np.arange(width, dtype=np.float64)
    v = np.arange(height, dtype=np.float64)
    y = (v - K[1, 2]) / K[1, 1]
    x = (u[None, :] - K[0, 2] - K[0, 1] * y[:, None]) / K[0, 0]
    return np.sqrt(x * x + (y * y)[:, None] + 1.0).astype(np.float32)


def visible_mask(dist_scene: np.ndarray, dist_obj: np.ndarray, delta_mm: float, mode: str = "bop19") -> np.ndarray:
    """(…, H, W) bool: silhouette pixels (``dist_obj > 0``) where the object is not behind the scene
    by more than ``delta_mm``; pixels without scene distance (0) count as visible in 'bop19' and
    not visible in 'bop18'. Distances in mm along the pixel rays."""
    dist_scene = np.asarray(dist_scene, dtype=np.float32)
    dist_obj = np.asarray(dist_obj, dtype=np.float32)
    close = (dist_obj - dist_scene) <= np.float32(delta_mm)
    if mode == "bop19":
        ok = close | (dist_scene == 0)
    elif mode == "bop18":
        ok = close & (dist_scene > 0)
    else:
        raise ValueError(f"visib_mode must be one of {VISIB_MODES}, got {mode!r}")
    return ok & (dist_obj > 0)


def bbox_xywh(mask: np.ndarray, offset=(0, 0)) -> np.ndarray:
    """(4,) int [x, y, w, h] of a (H, W) bool mask, with w = x_max - x_min (the toolkit's
    convention), shifted by ``offset`` = (x, y) of the mask's top-left pixel; -1s when empty."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return np.full(4, -1, dtype=np.int64)
    cols = np.flatnonzero(mask.any(axis=0))
    x0, y0 = cols[0] + offset[0], rows[0] + offset[1]
    return np.array([x0, y0, cols[-1] - cols[0], rows[-1] - rows[0]], dtype=np.int64)


def silhouette_canvas(K: np.ndarray, vertices: np.ndarray, T_cam_obj: np.ndarray, width: int, height: int,
                      factor: int = 3) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) image-pixel rectangle holding the image and the object's whole projection,
    within the toolkit's canvas [-(f-1)/2 W, (f+1)/2 W) (f = ``factor``; same for rows). Vertices
    (V, 3) in mm; an object reaching behind the camera gets the whole canvas."""
    mx, my = (factor - 1) // 2 * width, (factor - 1) // 2 * height
    full = (-mx, -my, width + mx, height + my)
    P = vertices @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    z = P[:, 2]
    if z.size == 0 or z.min() <= ZNEAR_MM:
        return full
    uv = (P @ np.asarray(K, dtype=np.float64).T)[:, :2] / z[:, None]
    lo = np.floor(uv.min(0)).astype(np.int64) - 1
    hi = np.ceil(uv.max(0)).astype(np.int64) + 2
    return (int(np.clip(min(0, lo[0]), full[0], 0)), int(np.clip(min(0, lo[1]), full[1], 0)),
            int(np.clip(max(width, hi[0]), width, full[2])), int(np.clip(max(height, hi[1]), height, full[3])))


@dataclass
class ImageGt:
    """What :func:`image_gt_info` computes for one image: info per GT instance, and the masks."""

    infos: list[bop.GtInfo]
    masks: np.ndarray  # (n, H, W) bool: silhouettes inside the image
    masks_visib: np.ndarray  # (n, H, W) bool: visible pixels
    used_depth: bool


def image_gt_info(renderer, K: np.ndarray, obj_ids: Sequence[int], T_cam_obj: np.ndarray, vertices: Mapping,
                  width: int, height: int, depth_mm: np.ndarray | None, conf: Mapping) -> ImageGt:
    """GT info of the instances ``obj_ids[i]`` at ``T_cam_obj[i]`` (n, 4, 4; mm) of one image.

    renderer: a :class:`~cosy_cli.rendering.SceneRenderer` holding the meshes; vertices: obj_id ->
    (V, 3) mesh vertices (mm), used to size the canvas of objects leaving the image; depth_mm:
    (H, W) measured depth (0 = none) or None (then visibility is against the GT z-buffer)."""
    n = len(obj_ids)
    K = np.asarray(K, dtype=np.float64)
    T = np.asarray(T_cam_obj, dtype=np.float64).reshape(n, 4, 4)
    if n == 0:
        empty = np.zeros((0, height, width), dtype=bool)
        return ImageGt([], empty, empty.copy(), depth_mm is not None)
    rays = ray_lengths(K, width, height)
    if conf.get("toolkit_pixel_centres", False):
        K = K.copy()
        K[:2, 2] -= 0.5  # round(u - 0.5) = floor(u): the toolkit's rasterisation
    factor = int(conf["canvas_factor"])
    canvases = [silhouette_canvas(K, vertices[o], T[i], width, height, factor) for i, o in enumerate(obj_ids)]
    inside = [i for i, c in enumerate(canvases) if c == (0, 0, width, height)]

    depth_obj = np.zeros((n, height, width), np.float32)
    px_all = np.zeros(n, np.int64)
    bbox_obj = np.full((n, 4), -1, np.int64)
    if inside:
        out = renderer.render_crops(np.repeat(K[None], len(inside), 0), [obj_ids[i] for i in inside], T[inside],
                                    size=(width, height), with_rgb=False)
        depth_obj[inside] = out.depth
        sil = out.instance >= 0
        px_all[inside] = sil.sum(axis=(1, 2))
        bbox_obj[inside] = [bbox_xywh(s) for s in sil]
    for i, (x0, y0, x1, y1) in enumerate(canvases):
        if i in inside:
            continue
        Kc = K.copy()
        Kc[0, 2] -= x0
        Kc[1, 2] -= y0
        out = renderer.render_crops(Kc[None], [obj_ids[i]], T[i:i + 1], size=(x1 - x0, y1 - y0), with_rgb=False)
        sil = out.instance[0] >= 0
        px_all[i] = int(sil.sum())
        bbox_obj[i] = bbox_xywh(sil, offset=(x0, y0))
        depth_obj[i] = out.depth[0, -y0:height - y0, -x0:width - x0]

    if depth_mm is None:
        scene = renderer.render(K, list(obj_ids), T, with_rgb=False, size=(width, height)).depth
    else:
        scene = np.asarray(depth_mm, dtype=np.float32)
        if scene.shape != (height, width):
            raise ValueError(f"depth image is {scene.shape[1]} x {scene.shape[0]}, expected {width} x {height}")
    dist_scene = scene * rays
    masks = depth_obj > 0
    visib = visible_mask(dist_scene[None], depth_obj * rays[None], conf["delta_mm"], conf["visib_mode"])
    px_valid = (masks & (dist_scene > 0)[None]).sum(axis=(1, 2))
    px_visib = visib.sum(axis=(1, 2))
    infos = []
    for i in range(n):
        seen = px_visib[i] > 0
        infos.append(bop.GtInfo(
            bbox_obj=bbox_obj[i] if seen else np.full(4, -1, np.int64),
            bbox_visib=bbox_xywh(visib[i]),
            px_count_all=int(px_all[i]), px_count_valid=int(px_valid[i]), px_count_visib=int(px_visib[i]),
            visib_fract=float(px_visib[i] / px_all[i]) if px_all[i] > 0 else 0.0,
        ))
    return ImageGt(infos, masks, visib, depth_mm is not None)


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) IoU of boxes (N, 4) [x, y, w, h] in the toolkit's convention (pixels x..x+w inclusive);
    a pair where both are -1s (nothing visible) has IoU 1, one of them -1s: 0."""
    a, b = np.asarray(a, np.float64).reshape(-1, 4), np.asarray(b, np.float64).reshape(-1, 4)
    ea, eb = (a < 0).all(1), (b < 0).all(1)
    lo, hi = np.maximum(a[:, :2], b[:, :2]), np.minimum(a[:, :2] + a[:, 2:], b[:, :2] + b[:, 2:])
    inter = np.prod(np.clip(hi - lo + 1, 0, None), axis=1)
    union = np.prod(a[:, 2:] + 1, axis=1) + np.prod(b[:, 2:] + 1, axis=1) - inter
    iou = np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)
    return np.where(ea & eb, 1.0, np.where(ea | eb, 0.0, iou))


def compare_gt_info(reference: Mapping[int, list[bop.GtInfo]], ours: Mapping[int, list[bop.GtInfo]]) -> dict:
    """Per-instance agreement of two scene_gt_info contents of the same scene_gt (same images and
    instance counts): arrays 'iou_bbox_visib', 'iou_bbox_obj', 'd_visib_fract' (ours - reference)."""
    pairs = [(r, o) for im in reference for r, o in zip(reference[im], ours.get(im, []), strict=True)]
    if not pairs:
        return {"iou_bbox_visib": np.zeros(0), "iou_bbox_obj": np.zeros(0), "d_visib_fract": np.zeros(0)}
    R, O = zip(*pairs)
    return {
        "iou_bbox_visib": box_iou([r.bbox_visib for r in R], [o.bbox_visib for o in O]),
        "iou_bbox_obj": box_iou([r.bbox_obj for r in R], [o.bbox_obj for o in O]),
        "d_visib_fract": np.array([o.visib_fract - r.visib_fract for r, o in pairs]),
    }


# --------------------------------------------------------------------------------------------
# the stage
# --------------------------------------------------------------------------------------------
@dataclass
class GtInfoSummary:
    scenes_done: list[int] = field(default_factory=list)
    scenes_skipped: list[int] = field(default_factory=list)
    images: int = 0
    instances: int = 0
    images_with_depth: int = 0

    def line(self) -> str:
        src = (f"{self.images_with_depth} against measured depth, {self.images - self.images_with_depth} "
               f"against the GT z-buffer")
        return (f"gt-info: {len(self.scenes_done)} scene(s) written ({self.images} images, {self.instances} "
                f"instances; {src}), {len(self.scenes_skipped)} already done")


def check_conf(conf: Mapping) -> dict:
    c = dict(conf)
    if not (np.isfinite(c["delta_mm"]) and c["delta_mm"] >= 0):
        raise CosyError(f"delta must be a length in mm >= 0, got {c['delta_mm']}")
    if c["visib_mode"] not in VISIB_MODES:
        raise CosyError(f"visib_mode must be one of {', '.join(VISIB_MODES)}, got {c['visib_mode']!r}")
    if c["visibility"] not in VISIBILITY_SOURCES:
        raise CosyError(f"visibility must be one of {', '.join(VISIBILITY_SOURCES)}, got {c['visibility']!r}")
    if int(c["canvas_factor"]) < 1 or int(c["canvas_factor"]) % 2 != 1:
        raise CosyError(f"canvas_factor must be an odd integer >= 1, got {c['canvas_factor']}")
    return c


def _scene_gt(ds: BopDataset, scene_id: int) -> dict[int, list[bop.GtInstance]]:
    path = ds.scene_file(scene_id, "scene_gt")
    if not path.is_file():
        raise CosyError("scene_gt.json not found: gt-info needs the GT poses of every scene", path=path)
    return ds.scene_gt(scene_id)


def scene_is_done(ds: BopDataset, scene_id: int, gt: Mapping[int, list], masks: bool) -> bool:
    """True when the scene's scene_gt_info.json exists, reads, and has one entry per GT instance
    of every image of ``gt`` (and with ``masks``, every mask and mask_visib file exists)."""
    path = ds.scene_file(scene_id, "scene_gt_info")
    if not path.is_file():
        return False
    try:
        info = bop.read_scene_gt_info(path)
    except CosyError as e:
        warn(f"unreadable ({e.detail}): recomputed", path=path)
        return False
    if sorted(info) != sorted(gt) or any(len(info[i]) != len(gt[i]) for i in gt):
        warn("does not match scene_gt.json (other images or instance counts): recomputed", path=path)
        return False
    if masks:
        for im_id, insts in gt.items():
            for k in range(len(insts)):
                if not (ds.mask_path(scene_id, im_id, k).is_file()
                        and ds.mask_path(scene_id, im_id, k, visib=True).is_file()):
                    return False
    return True


def _image_size(ds: BopDataset, scene_id: int, im_id: int) -> tuple[int, int]:
    """(width, height) of an image: from its RGB/gray file, else its depth file, else camera*.json."""
    try:
        ds.rgb_path(scene_id, im_id)
    except CosyError:  # no RGB/gray image: the depth's size, else the camera file's
        pass
    else:
        return ds.image_size(scene_id, im_id)  # checked against the camera file and cam_K
    p = ds.depth_path(scene_id, im_id)
    if p is not None:
        return images.image_size(p)
    cams = sorted(ds.root.glob("camera*.json"))
    if len(cams) == 1 or (ds.root / "camera.json").is_file():
        cam = bop.read_camera(ds.root / "camera.json" if (ds.root / "camera.json").is_file() else cams[0])
        return int(cam.width), int(cam.height)
    raise CosyError(f"image {im_id}: no image or depth file and no single camera*.json to take the image size from",
                    path=ds.scene_dir(scene_id))


def main(conf: str | Mapping | None, dataset: str | Path, split: str = "test", *, scene_ids=None,
         masks: bool = False, split_type: str | None = None, models_dir: str = "models", delta_mm: float | None = None,
         overwrite: bool = False, progress: bool = True) -> GtInfoSummary:
    """Write ``scene_gt_info.json`` (and with ``masks`` the ``mask/`` and ``mask_visib/`` PNGs) of
    every scene of ``dataset``/``split`` (or of ``scene_ids``), in place.

    conf: a preset name of :data:`GT_INFO_CONFS` or a dict of its keys; ``delta_mm`` overrides it.
    models_dir: the meshes, relative to the dataset folder or absolute (T-LESS: models_cad).
    Scenes already done (see :func:`scene_is_done`) are skipped unless ``overwrite``."""
    from ..console import progress as progress_bar

    conf = check_conf(merge_conf(GT_INFO_CONFS, conf, {"delta_mm": delta_mm}, default="default", what="gt-info"))
    ds = BopDataset(Path(dataset), split, split_type=split_type, models_subdir=str(models_dir))
    summary = GtInfoSummary()
    todo: list[tuple[int, dict]] = []
    for sid in ds.select_scenes(scene_ids):
        gt = _scene_gt(ds, sid)
        if not overwrite and scene_is_done(ds, sid, gt, masks):
            summary.scenes_skipped.append(sid)
        else:
            todo.append((sid, gt))
    if not todo:
        return summary

    from ..objects import ObjectDatabase
    from ..rendering import SceneRenderer

    needed = sorted({g.obj_id for _, gt in todo for insts in gt.values() for g in insts})
    db = ObjectDatabase.from_models_dir(ds.models_dir, obj_ids=set(needed))
    missing = [o for o in needed if o not in db]
    if missing:
        raise CosyError(f"GT instances of object(s) {missing} but no such model in models_info.json",
                        path=ds.models_info_path)
    vertices = {o: db[o].vertices for o in needed}
    n_images = sum(len(gt) for _, gt in todo)
    with SceneRenderer({o: db[o].mesh for o in needed}, 640, 480, znear=ZNEAR_MM, zfar=ZFAR_MM) as ren, \
            progress_bar(total=n_images, desc="gt-info", unit="img", enabled=progress) as bar:
        for sid, gt in todo:
            cams = ds.scene_camera(sid)
            info: dict[int, list[bop.GtInfo]] = {}
            bar.set_postfix_str(f"scene {sid}")
            for im_id, insts in gt.items():
                if im_id not in cams:
                    raise CosyError(f"image {im_id} has GT but no camera in scene_camera.json",
                                    path=ds.scene_file(sid, "scene_camera"))
                width, height = _image_size(ds, sid, im_id)
                depth = None if conf["visibility"] == "zbuffer" else ds.read_depth(sid, im_id)
                if depth is None and conf["visibility"] == "depth":
                    raise CosyError(f"image {im_id}: no depth image (visibility 'depth' needs one)",
                                    path=ds.scene_dir(sid))
                if depth is not None and depth.shape != (height, width):
                    raise CosyError(f"depth image is {depth.shape[1]} x {depth.shape[0]}, the image {width} x {height}",
                                    path=ds.depth_path(sid, im_id))
                res = image_gt_info(ren, cams[im_id].K, [g.obj_id for g in insts],
                                    np.array([g.T_cam_obj for g in insts]).reshape(-1, 4, 4),
                                    vertices, width, height, depth, conf)
                info[im_id] = res.infos
                if masks:
                    for k in range(len(insts)):
                        images.write_mask(ds.mask_path(sid, im_id, k), res.masks[k])
                        images.write_mask(ds.mask_path(sid, im_id, k, visib=True), res.masks_visib[k])
                summary.images += 1
                summary.instances += len(insts)
                summary.images_with_depth += int(res.used_depth)
                bar.update(1)
            bop.write_scene_gt_info(ds.scene_file(sid, "scene_gt_info"), info)
            summary.scenes_done.append(sid)
    return summary
