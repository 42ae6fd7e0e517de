"""Where things are in a BOP dataset folder, for the classic and the BOP-H3 layouts.

Classic::

    DATASET/camera.json, models/, models_eval/, test_targets_bop19.json
    DATASET/<split>[_<split_type>]/<scene_id:06d>/{rgb|gray}/<im_id:06d>.{png|jpg}
                                               depth/, mask/, mask_visib/
                                               scene_camera.json, scene_gt.json, scene_gt_info.json

BOP-H3 (HOT3D, HOPEv2, HANDAL in BOP 2024) adds per-sensor files: ``scene_camera_<sensor>.json``,
``scene_gt_<sensor>.json``, ``scene_gt_info_<sensor>.json`` and image folders named by sensor
(``rgb``, ``gray1``, ``gray2``...). Pass ``sensor`` to pick one; by default it is detected.

Multi-sensor (the BOP industrial datasets since 2024: IPD, XYZ-IBD, ITODD-MV)::

    DATASET/camera_<sensor>.json, dataset_info.json, test_targets_multiview_bop25.json
    DATASET/<split>/<scene_id:06d>/{rgb|gray}_<sensor>/<im_id:06d>.png, depth_<sensor>/,
                                   mask_<sensor>/, mask_visib_<sensor>/,
                                   scene_camera_<sensor>.json, scene_gt_<sensor>.json, ...

The images of one im_id across sensors are one instant seen by a calibrated rig (their
``cam_R_w2c``/``cam_t_w2c`` share the scene's world frame). ``sensor`` picks one; by default the
evaluation sensor: ``eval_sensor`` of ``dataset_info.json`` when it names one, else the one the
BOP toolkit evaluates on for the known datasets (:data:`EVAL_SENSORS`), else the only sensor; else a
CosyError listing the sensors. The sensor ``rig`` (:data:`RIG`) is every sensor at once
(:class:`RigDataset`).

A *split spec* ``SPLIT:SENSOR`` (e.g. ``test:xyz``, ``test:rig``) given as ``split`` is the split
and the sensor together: the stages pass it along as they pass a split (``--sensor`` makes it).

Images read through :class:`BopDataset` (``read_rgb``, ``read_depth``, ``read_mask``,
``image_size``) are checked against what the dataset says about them, so that no stage computes
poses with intrinsics that do not belong to an image (``check_images=False`` turns this off):

* an RGB/gray image has the size of the camera file (``camera.json``; classic layout, when it
  gives a size), else the size of most images of its scene; and its ``cam_K`` puts the principal
  point inside it (within :data:`PP_MARGIN`). A camera file that describes another split is
  tolerated when every image of the scene has the same other size and cam_K's principal point
  lies near their centre (T-LESS ``train_primesense`` is 400x400, its camera file 720x540);
* a depth image has the size of its RGB/gray image; a mask too;
* the first depth image read per scene with GT is compared with the GT poses (the model's
  bounding box projected, no rendering): when most objects sit more than
  :data:`DEPTH_SCALE_RTOL` of their distance off the measured depth, one warning
  (:func:`cosy_cli.errors.warn`) says so (wrong ``depth_scale``?). It stays a warning: depth
  sensors have offsets and holes.

A mismatch is a :class:`~cosy_cli.errors.CosyError` naming the file and both sizes, e.g.
``.../rgb/000003.png: 320x240 image, but camera.json says 640x480 (and cam_K's principal point
(325.3, 242) lies outside it)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from ..errors import CosyError, warn
from . import bop, images

TARGET_FILES = ("test_targets_bop19.json", "test_targets_bop24.json")
MULTIVIEW_TARGETS = "test_targets_multiview_bop25.json"
DATASET_INFO = "dataset_info.json"
# the sensor the BOP toolkit evaluates on (bop_toolkit_lib/dataset_params.py), by dataset folder name
EVAL_SENSORS = {"ipd": "photoneo", "xyzibd": "xyz", "itoddmv": "3dlong", "itodd-mv": "3dlong", "itodd_mv": "3dlong"}
RIG = "rig"  # the sensor name meaning "every sensor of the rig" (RigDataset)
IMAGE_KINDS = ("rgb", "gray")  # image folders of the multi-sensor layout: rgb_<sensor>, gray_<sensor>
PP_MARGIN = 0.1  # cam_K's principal point may lie this fraction of the image size outside it (crops)
PP_CENTRAL = 0.25  # "near the centre": within this fraction of the size from the image centre
DEPTH_SCALE_RTOL = 0.1  # depth vs GT: tolerated offset, fraction of the object's distance (beyond its box)
MIN_DEPTH_PIXELS = 5  # fewer valid depth pixels around an object's centre: not measured


def pp_outside(K: np.ndarray, wh, margin: float = 0.0) -> bool:
    """Whether cam_K's principal point (pixels) lies outside the ``wh`` = (width, height) image,
    more than ``margin`` x its size away from its borders (0: strictly inside is required)."""
    W, H = float(wh[0]), float(wh[1])
    cx, cy = float(K[0, 2]), float(K[1, 2])
    if margin > 0:
        return not (-margin * W <= cx <= (1 + margin) * W and -margin * H <= cy <= (1 + margin) * H)
    return not (0 < cx < W and 0 < cy < H)


def pp_central(K: np.ndarray, wh, fraction: float = PP_CENTRAL) -> bool:
    """Whether cam_K's principal point lies within ``fraction`` of the size from the image centre."""
    W, H = float(wh[0]), float(wh[1])
    return abs(float(K[0, 2]) - 0.5 * W) <= fraction * W and abs(float(K[1, 2]) - 0.5 * H) <= fraction * H


def _pp_text(K: np.ndarray) -> str:
    return f"({float(K[0, 2]):.6g}, {float(K[1, 2]):.6g})"


def image_size_problem(wh, K: np.ndarray | None, *, camera: tuple | None = None, scene: tuple | None = None,
                       scene_uniform: bool = False, what: str = "image") -> str | None:
    """What is wrong with an image of ``wh`` = (width, height) px, or None.

    ``K``: its cam_K (None: unknown). ``camera``: ((w, h), name) of the dataset camera file (None:
    no size there). ``scene``: ((w, h), text) the size most images of the scene have, e.g.
    (``(640, 480)``, "the other images of scene 3"), or None. ``scene_uniform``: every image of the
    scene has size ``wh`` (then a camera file of another size describes another split, and is
    overruled when cam_K's principal point lies near the image centre).
    Rules: the camera file's size, else the scene's; cam_K's principal point inside the image
    (within :data:`PP_MARGIN`)."""
    wh = (int(wh[0]), int(wh[1]))
    outside = K is not None and pp_outside(K, wh)
    also = f" (and cam_K's principal point {_pp_text(K)} lies outside it)" if outside else ""
    if camera is not None and wh != tuple(camera[0]):
        if not (scene_uniform and K is not None and pp_central(K, wh)):
            return f"{images.fmt_size(wh)} {what}, but {camera[1]} says {images.fmt_size(camera[0])}{also}"
    elif camera is None and scene is not None and wh != tuple(scene[0]):
        return f"{images.fmt_size(wh)} {what}, but {scene[1]} are {images.fmt_size(scene[0])}{also}"
    if K is not None and pp_outside(K, wh, PP_MARGIN):
        return (f"{images.fmt_size(wh)} {what}, but its cam_K puts the principal point at {_pp_text(K)}, "
                f"outside it (more than {PP_MARGIN:.0%} of its size past its borders)")
    return None


def depth_vs_gt(depth_mm: np.ndarray, K: np.ndarray, T_cam_obj: np.ndarray, corners: np.ndarray,
                window: float = 0.15) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Measured depth at each GT object against its GT distance, without rendering.

    ``depth_mm`` (H, W) mm (0: no measurement); ``K`` (3, 3); ``T_cam_obj`` (N, 4, 4) mm;
    ``corners`` (N, 8, 3) mm, each model's bounding box. For each object, the median valid depth
    in a window around its projected centre (``window`` x its projected box, at least 5x5 px).
    Returns (measured (N,), z_min (N,), z_max (N,)) mm: measured is NaN where the object is not in
    front of the camera, its centre is outside the image or fewer than :data:`MIN_DEPTH_PIXELS`
    pixels there have depth; z_min/z_max: the depth range of its box."""
    H, W = depth_mm.shape
    T = np.asarray(T_cam_obj, np.float64).reshape(-1, 4, 4)
    pts = np.einsum("nij,nkj->nki", T[:, :3, :3], np.asarray(corners, np.float64)) + T[:, None, :3, 3]  # (N, 8, 3)
    z = pts[..., 2]
    z_min, z_max = z.min(1), z.max(1)
    measured = np.full(len(T), np.nan)
    for n in np.flatnonzero(z_min > 0):  # a few objects per image
        uv = pts[n, :, :2] / z[n, :, None] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        c = T[n, :3, 3]
        cu, cv = K[0, 0] * c[0] / c[2] + K[0, 2], K[1, 1] * c[1] / c[2] + K[1, 2]
        hw = np.maximum(window * 0.5 * (uv.max(0) - uv.min(0)), 2.0)
        u0, u1 = int(np.floor(max(cu - hw[0], 0))), int(np.ceil(min(cu + hw[0], W)))
        v0, v1 = int(np.floor(max(cv - hw[1], 0))), int(np.ceil(min(cv + hw[1], H)))
        if not (0 <= cu < W and 0 <= cv < H) or u1 <= u0 or v1 <= v0:
            continue
        vals = depth_mm[v0:v1, u0:u1]
        vals = vals[vals > 0]
        if vals.size >= MIN_DEPTH_PIXELS:
            measured[n] = float(np.median(vals))
    return measured, z_min, z_max


def parse_split_spec(spec: str) -> tuple[str, str | None]:
    """``"test:xyz"`` -> ("test", "xyz"); ``"test"`` -> ("test", None) (module doc)."""
    split, sep, sensor = str(spec).partition(":")
    if sep and not sensor:
        raise CosyError(f"split {spec!r}: expected SPLIT or SPLIT:SENSOR")
    return split, (sensor or None)


def split_spec_sensor(spec: str) -> str | None:
    return str(spec).partition(":")[2] or None


def with_sensor(split: str, sensor: str | None) -> str:
    """The split spec of ``split`` with ``sensor`` (None: ``split`` as it is); what ``--sensor`` makes."""
    if not sensor:
        return split
    base, old = parse_split_spec(split)
    if old is not None and old != sensor:
        raise CosyError(f"split {split!r} already names sensor {old!r}, and --sensor says {sensor!r}")
    return f"{base}:{sensor}"


@dataclass
class BopDataset:
    root: Path
    split: str = "test"
    split_type: str | None = None
    sensor: str | None = None
    models_subdir: str = "models"
    camera_file: str | Path | None = None  # the dataset camera file, relative to root (or absolute); see camera_path
    check_images: bool = True  # check what read_rgb/read_depth/read_mask read against the dataset (module doc)
    _cache: dict = field(default_factory=dict, repr=False)

    def __new__(cls, root=None, split: str = "test", *args, **kwargs):
        sensor = kwargs.get("sensor", args[1] if len(args) > 1 else None)
        if cls is BopDataset and (sensor == RIG or (sensor is None and split_spec_sensor(split) == RIG)):
            cls = RigDataset
        return object.__new__(cls)

    def __post_init__(self) -> None:
        self.root = Path(self.root)
        split, sensor = parse_split_spec(self.split)
        self.split = split
        if sensor is not None and self.sensor is None:
            self.sensor = sensor
        if not self.root.is_dir():
            raise CosyError("dataset folder not found", path=self.root)
        if self.sensor is not None and self.sensor != RIG and self.is_multi_sensor:
            if self.sensor not in self.sensors:
                raise CosyError(f"no sensor {self.sensor!r} in {self.split_name} (sensors: {', '.join(self.sensors)})",
                                path=self.split_dir)

    @property
    def split_spec(self) -> str:
        """The split with its sensor (``test:xyz``) when one was chosen, else the split: what the
        stages pass along and record (:func:`parse_split_spec` reads it back)."""
        return f"{self.split}:{self.sensor}" if self.sensor else self.split

    # ---- sensors (multi-sensor layout) -----------------------------------------------------
    @cached_property
    def sensors(self) -> list[str]:
        """The sensors of the split's multi-sensor layout (the names of its image folders
        ``rgb_<sensor>``/``gray_<sensor>`` next to ``scene_camera_<sensor>.json``), sorted; [] for
        the classic and BOP-H3 layouts."""
        found: set[str] = set()
        if self.split_dir.is_dir():
            for d in self.split_dir.iterdir():
                if not (d.is_dir() and d.name.isdigit()):
                    continue
                for f in d.glob("scene_camera_*.json"):
                    s = f.name[len("scene_camera_"):-len(".json")]
                    if any((d / f"{k}_{s}").is_dir() for k in IMAGE_KINDS):
                        found.add(s)
        return sorted(found)

    @property
    def is_multi_sensor(self) -> bool:
        return bool(self.sensors)

    def dataset_info(self) -> dict:
        """``dataset_info.json`` of the dataset root as a dict ({} when absent or not an object)."""
        if "dataset_info" not in self._cache:
            p = self.root / DATASET_INFO
            d = bop.load_json(p) if p.is_file() else {}
            self._cache["dataset_info"] = d if isinstance(d, dict) else {}
        return self._cache["dataset_info"]

    @cached_property
    def eval_sensor(self) -> str | None:
        """The sensor predictions are evaluated on (module doc); None for single-sensor layouts.
        A CosyError listing the sensors when nothing says which."""
        sensors = self.sensors
        if not sensors:
            return None
        named = self.dataset_info().get("eval_sensor")
        if isinstance(named, str) and named:
            if named not in sensors:
                raise CosyError(f"eval_sensor {named!r} is not a sensor of {self.split_name} "
                                f"(sensors: {', '.join(sensors)})", path=self.root / DATASET_INFO)
            return named
        known = EVAL_SENSORS.get(self.root.name.lower())
        if known in sensors:
            return known
        if len(sensors) == 1:
            return sensors[0]
        raise CosyError(f"several sensors ({', '.join(sensors)}) and no evaluation sensor known for this dataset: "
                        f"choose one with --sensor NAME (or name it as eval_sensor in {DATASET_INFO})",
                        path=self.split_dir)

    def is_gray(self, scene_id: int) -> bool:
        """Whether the scene's images are grey (a ``gray`` or ``gray_<sensor>`` folder)."""
        return self.image_dir(scene_id).name.split("_")[0] == "gray"

    # ---- folders ---------------------------------------------------------------------------
    @property
    def split_name(self) -> str:
        return f"{self.split}_{self.split_type}" if self.split_type else self.split

    @property
    def split_dir(self) -> Path:
        return self.root / self.split_name

    @property
    def models_dir(self) -> Path:
        return self.root / self.models_subdir

    @property
    def models_info_path(self) -> Path:
        return self.models_dir / "models_info.json"

    def model_path(self, obj_id: int) -> Path:
        return self.models_dir / f"obj_{int(obj_id):06d}.ply"

    @cached_property
    def scene_ids(self) -> list[int]:
        if not self.split_dir.is_dir():
            splits = sorted(p.name for p in self.root.iterdir() if p.is_dir() and not p.name.startswith("models"))
            raise CosyError(f"split folder '{self.split_name}' not found (folders here: {', '.join(splits) or 'none'})",
                            path=self.root)
        ids = sorted(int(p.name) for p in self.split_dir.iterdir() if p.is_dir() and p.name.isdigit())
        if not ids:
            raise CosyError("no scene folders (expected 6-digit names such as 000001)", path=self.split_dir)
        return ids

    def select_scenes(self, scene_ids=None) -> list[int]:
        """``scene_ids`` as ints, checked to be scenes of the split (None: all of them)."""
        if scene_ids is None:
            return list(self.scene_ids)
        missing = sorted(set(int(s) for s in scene_ids) - set(self.scene_ids))
        if missing:
            raise CosyError(f"scene(s) {missing} not in the split (has {self.scene_ids})", path=self.split_dir)
        return [int(s) for s in scene_ids]

    def scene_dir(self, scene_id: int) -> Path:
        return self.split_dir / f"{int(scene_id):06d}"

    def _sensor_for(self, scene_id: int) -> str | None:
        """The sensor suffix of the scene's JSON files (None: classic layout)."""
        if self.sensor is not None:
            return self.sensor
        if self.is_multi_sensor:
            return self.eval_sensor
        d = self.scene_dir(scene_id)
        if (d / "scene_camera.json").is_file():
            return None
        found = sorted(p.name[len("scene_camera_"):-len(".json")] for p in d.glob("scene_camera_*.json"))
        if not found:
            return None
        return "rgb" if "rgb" in found else found[0]

    def scene_file(self, scene_id: int, kind: str) -> Path:
        """``kind`` in {'scene_camera', 'scene_gt', 'scene_gt_info'}."""
        s = self._sensor_for(scene_id)
        return self.scene_dir(scene_id) / (f"{kind}_{s}.json" if s else f"{kind}.json")

    def image_dir(self, scene_id: int) -> Path:
        d = self.scene_dir(scene_id)
        s = self._sensor_for(scene_id)
        names = ([f"{k}_{s}" for k in IMAGE_KINDS] + [s] if s else []) + list(IMAGE_KINDS)
        for name in names:
            if (d / name).is_dir():
                return d / name
        raise CosyError(f"no image folder ({'/'.join(names)})", path=d)

    # ---- files -----------------------------------------------------------------------------
    def scene_camera(self, scene_id: int) -> dict[int, bop.SceneCamera]:
        key = ("cam", scene_id)
        if key not in self._cache:
            self._cache[key] = bop.read_scene_camera(self.scene_file(scene_id, "scene_camera"))
        return self._cache[key]

    def has_gt(self, scene_id: int) -> bool:
        return self.scene_file(scene_id, "scene_gt").is_file()

    def scene_gt(self, scene_id: int) -> dict[int, list[bop.GtInstance]]:
        key = ("gt", scene_id)
        if key not in self._cache:
            self._cache[key] = bop.read_scene_gt(self.scene_file(scene_id, "scene_gt"))
        return self._cache[key]

    def scene_gt_info(self, scene_id: int) -> dict[int, list[bop.GtInfo]]:
        key = ("gt_info", scene_id)
        if key not in self._cache:
            self._cache[key] = bop.read_scene_gt_info(self.scene_file(scene_id, "scene_gt_info"))
        return self._cache[key]

    def image_ids(self, scene_id: int) -> list[int]:
        return list(self.scene_camera(scene_id).keys())

    def models_info(self) -> dict[int, bop.ModelInfo]:
        if "models_info" not in self._cache:
            self._cache["models_info"] = bop.read_models_info(self.models_info_path)
        return self._cache["models_info"]

    @property
    def camera_path(self) -> Path | None:
        """The dataset camera file: ``camera_file`` when given (a CosyError when missing), else
        ``camera_<split_type>.json``, ``camera.json``, or the only ``camera_*.json`` of the folder
        (YCB-V ships ``camera_uw.json`` and ``camera_cmu.json``; a copy of one of its splits often
        only the one it needs). None when there is none, or several and no way to choose."""
        if self.camera_file is not None:
            p = Path(self.camera_file)
            p = p if p.is_absolute() else self.root / p
            if not p.is_file():
                raise CosyError("camera file not found", path=p)
            return p
        names = ([f"camera_{self.sensor}.json"] if self.sensor and self.sensor != RIG else []) + \
            ([f"camera_{self.eval_sensor}.json"] if self.sensor is None and self.is_multi_sensor else []) + \
            ([f"camera_{self.split_type}.json"] if self.split_type else []) + ["camera.json"]
        for n in names:
            if (self.root / n).is_file():
                return self.root / n
        others = sorted(self.root.glob("camera_*.json"))
        return others[0] if len(others) == 1 else None

    def camera(self) -> bop.CameraInfo | None:
        p = self.camera_path
        return bop.read_camera(p) if p is not None else None

    def multiview_targets_path(self) -> Path | None:
        """``test_targets_multiview_bop25.json`` of the dataset root, or None."""
        p = self.root / MULTIVIEW_TARGETS
        return p if p.is_file() else None

    def targets_path(self) -> Path | None:
        for name in TARGET_FILES:
            p = self.root / name
            if p.is_file():
                return p
        return None

    def _find_image(self, folder: Path, im_id: int) -> Path | None:
        for ext in images.IMAGE_EXTENSIONS:
            p = folder / f"{int(im_id):06d}{ext}"
            if p.is_file():
                return p
        return None

    def rgb_path(self, scene_id: int, im_id: int) -> Path:
        folder = self.image_dir(scene_id)
        p = self._find_image(folder, im_id)
        if p is None:
            raise CosyError(f"image {int(im_id):06d}.png/.jpg not found", path=folder)
        return p

    def depth_path(self, scene_id: int, im_id: int) -> Path | None:
        s = self._sensor_for(scene_id)
        d = self.scene_dir(scene_id)
        for name in ([f"depth_{s}"] if s else []) + ["depth"]:
            if (d / name).is_dir():
                return self._find_image(d / name, im_id)
        return None

    def mask_path(self, scene_id: int, im_id: int, gt_index: int, visib: bool = False) -> Path:
        s = self._sensor_for(scene_id)
        base = "mask_visib" if visib else "mask"
        d = self.scene_dir(scene_id)
        folder = d / f"{base}_{s}" if s and ((d / f"{base}_{s}").is_dir() or self.is_multi_sensor) else d / base
        return folder / f"{int(im_id):06d}_{int(gt_index):06d}.png"

    # ---- checked image reads ---------------------------------------------------------------
    def camera_size(self) -> tuple[tuple[int, int], str] | None:
        """((width, height), file name) of the dataset camera file when it states a size (None:
        no camera file, no width/height in it, or unreadable: ``cosy validate`` reports that)."""
        if "camera_size" not in self._cache:
            val = None
            p = self.camera_path
            if p is not None:
                try:
                    d = bop.load_json(p)
                except CosyError:
                    d = None
                w, h = (d.get("width"), d.get("height")) if isinstance(d, dict) else (None, None)
                if all(isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 and float(v).is_integer()
                       for v in (w, h)):
                    val = ((int(w), int(h)), p.name)
            self._cache["camera_size"] = val
        return self._cache["camera_size"]

    def scene_image_sizes(self, scene_id: int) -> dict[int, tuple[int, int]]:
        """{im_id: (width, height)} of the scene's RGB/gray images, from their file headers (cached;
        images that are missing or unreadable are left out)."""
        key = ("sizes", int(scene_id))
        if key not in self._cache:
            folder = self.image_dir(scene_id)
            out = {}
            for im in self.image_ids(scene_id):
                p = self._find_image(folder, im)
                if p is not None:
                    try:
                        out[im] = images.image_size(p)
                    except CosyError:
                        pass
            self._cache[key] = out
        return self._cache[key]

    def _K(self, scene_id: int, im_id: int) -> np.ndarray | None:
        cam = self.scene_camera(scene_id).get(int(im_id))
        return None if cam is None else cam.K

    def check_image_size(self, scene_id: int, im_id: int, wh, path: Path, what: str = "image") -> None:
        """Refuse an image of ``wh`` = (width, height) px at ``path`` that disagrees with the camera
        file or its cam_K (rules: :func:`image_size_problem`): a CosyError naming the file and both sizes."""
        wh = (int(wh[0]), int(wh[1]))
        K = self._K(scene_id, im_id)
        # BOP-H3: per-sensor sizes; multi-sensor: camera_<sensor>.json is the sensor's
        camera = self.camera_size() if self._sensor_for(scene_id) is None or self.is_multi_sensor else None
        scene, uniform = None, False
        if camera is None or wh != tuple(camera[0]):
            try:
                sizes = self.scene_image_sizes(scene_id)
            except CosyError:  # no image folder (a depth-only split): cam_K decides
                sizes = {}
            if sizes:
                from collections import Counter

                common = Counter(sizes.values()).most_common(1)[0][0]
                scene = (common, f"the other images of scene {int(scene_id)}")
                uniform = all(tuple(v) == wh for v in sizes.values())
        msg = image_size_problem(wh, K, camera=camera, scene=scene, scene_uniform=uniform, what=what)
        if msg:
            raise CosyError(msg, path=path)

    def image_size(self, scene_id: int, im_id: int) -> tuple[int, int]:
        """(width, height) px of the RGB/gray image, from its header, checked (:meth:`check_image_size`)."""
        key = ("size", int(scene_id), int(im_id))
        if key not in self._cache:
            p = self.rgb_path(scene_id, im_id)
            wh = images.image_size(p)
            if self.check_images:
                self.check_image_size(scene_id, im_id, wh, p)
            self._cache[key] = wh
        return self._cache[key]

    def check_image_files(self, scene_ids=None, *, depth: bool = False) -> None:
        """Check, from the file headers (fast: no decoding), every RGB/gray image of the scenes
        (and their depth images with ``depth``) as the readers do: stages call it before their
        slow work so that a wrong image is refused at once (a CosyError naming the file)."""
        if not self.check_images:
            return
        for sid in self.select_scenes(scene_ids):
            for im in self.image_ids(sid):
                self.image_size(sid, im)
                p = self.depth_path(sid, im) if depth else None
                if p is not None:
                    self._check_against_image(sid, im, images.image_size(p), p, "depth image")

    def read_rgb(self, scene_id: int, im_id: int) -> np.ndarray:
        """(H, W, 3) uint8, checked against the camera file and cam_K (module doc)."""
        p = self.rgb_path(scene_id, im_id)
        img = images.read_rgb(p)
        if self.check_images:
            key = ("size", int(scene_id), int(im_id))
            wh = (img.shape[1], img.shape[0])
            if self._cache.get(key) != wh:
                self.check_image_size(scene_id, im_id, wh, p)
                self._cache[key] = wh
        return img

    def _check_against_image(self, scene_id: int, im_id: int, wh, path: Path, what: str) -> None:
        """A depth image or mask of ``wh`` must have its RGB/gray image's size (or, without one, the camera's)."""
        try:
            ref_path = self.rgb_path(scene_id, im_id)
        except CosyError:
            ref_path = None
        if ref_path is None:
            self.check_image_size(scene_id, im_id, wh, path, what=what)
            return
        ref = self.image_size(scene_id, im_id)
        if tuple(wh) != tuple(ref):
            raise CosyError(f"{images.fmt_size(wh)} {what}, but its image {ref_path.parent.name}/{ref_path.name} "
                            f"is {images.fmt_size(ref)}", path=path)

    def read_depth(self, scene_id: int, im_id: int) -> np.ndarray | None:
        """Depth in mm, or None when the dataset has no depth for this image. Checked: its size is
        its image's; the first depth read per scene with GT is compared with the GT poses (a
        warning when most objects sit far from their measured depth: wrong depth_scale?)."""
        p = self.depth_path(scene_id, im_id)
        if p is None:
            return None
        d = images.read_depth(p, self.scene_camera(scene_id)[im_id].depth_scale)
        if self.check_images:
            self._check_against_image(scene_id, im_id, (d.shape[1], d.shape[0]), p, "depth image")
            self._check_depth_scale(scene_id, im_id, d, p)
        return d

    def read_mask(self, scene_id: int, im_id: int, gt_index: int, visib: bool = False) -> np.ndarray:
        """(H, W) bool mask of a GT instance, checked to have its image's size."""
        p = self.mask_path(scene_id, im_id, gt_index, visib=visib)
        m = images.read_mask(p)
        if self.check_images:
            self._check_against_image(scene_id, im_id, (m.shape[1], m.shape[0]), p, "mask")
        return m

    def _check_depth_scale(self, scene_id: int, im_id: int, depth_mm: np.ndarray, path: Path) -> None:
        """Once per scene (the first depth image whose GT objects can be measured), and until one
        warning was given: warn when most GT objects sit off their measured depth."""
        done = self._cache.setdefault("depth_scale_checked", set())
        if self._cache.get("depth_scale_warned") or int(scene_id) in done:
            return
        try:
            if not self.has_gt(scene_id):
                done.add(int(scene_id))
                return
            gts = self.scene_gt(scene_id).get(int(im_id), [])
            infos = self.models_info()
            visib = None
            if self.scene_file(scene_id, "scene_gt_info").is_file():
                visib = [g.visib_fract for g in self.scene_gt_info(scene_id).get(int(im_id), [])]
        except CosyError:  # unreadable GT or models_info: the stage reports it if it needs them
            done.add(int(scene_id))
            return
        keep = [k for k, g in enumerate(gts) if g.obj_id in infos
                and (visib is None or len(visib) != len(gts) or visib[k] >= 0.5)]
        if not keep:
            return
        T = np.stack([gts[k].T_cam_obj for k in keep])
        unit = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], np.float64)
        corners = np.stack([infos[gts[k].obj_id].min_xyz + unit * infos[gts[k].obj_id].size_xyz for k in keep])
        K = self._K(scene_id, im_id)
        if K is None:
            return
        measured, z_min, z_max = depth_vs_gt(depth_mm, K, T, corners)
        ok = np.isfinite(measured)
        if not ok.any():
            return
        done.add(int(scene_id))
        measured, z_min, z_max, zc = measured[ok], z_min[ok], z_max[ok], T[ok, 2, 3]
        off = (measured < z_min - DEPTH_SCALE_RTOL * zc) | (measured > z_max + DEPTH_SCALE_RTOL * zc)
        if 2 * int(off.sum()) > len(off):
            self._cache["depth_scale_warned"] = True
            ratio = float(np.median(measured / zc))
            i = int(np.flatnonzero(off)[0])
            scale = self.scene_camera(scene_id)[int(im_id)].depth_scale
            warn(f"the measured depth at the GT objects is {ratio:.3g} times their GT distance ({int(off.sum())} of "
                 f"{len(off)} object(s) more than {DEPTH_SCALE_RTOL:.0%} off, e.g. {measured[i]:.0f} mm measured, "
                 f"{zc[i]:.0f} mm from the GT pose): wrong depth_scale ({scale:g} in "
                 f"{self.scene_file(scene_id, 'scene_camera').name}) or wrong GT?", path=path)


class RigDataset(BopDataset):
    """Every sensor of a multi-sensor split at once, as one dataset whose images are *rig views*:
    the image ``im_id`` of the ``k``-th sensor (of :attr:`sensors`, sorted) is the view
    ``im_id * N + k`` (N sensors), so that the views of one instant are consecutive
    (:meth:`view_id`, :meth:`view_of`). Every file is read through the sensor's own
    :class:`BopDataset`; cameras keep their ``cam_R_w2c``/``cam_t_w2c`` (the rig's extrinsics in
    the scene's world frame). The files of the evaluation sensor stand for the scene where one
    file is asked for (``scene_file``, ``camera``)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        self.sensor = RIG
        if not self.is_multi_sensor:
            raise CosyError(f"sensor {RIG!r}: {self.split_name} has no multi-sensor layout "
                            f"(rgb_SENSOR/ or gray_SENSOR/ with scene_camera_SENSOR.json)", path=self.split_dir)
        self._subs = {s: BopDataset(self.root, self.split, self.split_type, s, self.models_subdir, None,
                                    self.check_images) for s in self.sensors}

    def sub(self, sensor: str) -> BopDataset:
        return self._subs[sensor]

    @property
    def n_sensors(self) -> int:
        return len(self.sensors)

    def view_id(self, sensor: str, im_id: int) -> int:
        return int(im_id) * self.n_sensors + self.sensors.index(sensor)

    def view_of(self, view_id: int) -> tuple[str, int]:
        """A rig view -> (sensor, im_id)."""
        im, k = divmod(int(view_id), self.n_sensors)
        return self.sensors[k], im

    def _merged(self, scene_id: int, what: str) -> dict:
        key = ("rig", what, int(scene_id))
        if key not in self._cache:
            out = {}
            for k, s in enumerate(self.sensors):
                sub = self._subs[s]
                if what != "cam" and not sub.has_gt(scene_id):
                    continue
                data = {"cam": sub.scene_camera, "gt": sub.scene_gt, "gt_info": sub.scene_gt_info}[what](scene_id)
                for im, v in data.items():
                    out[int(im) * self.n_sensors + k] = v
            self._cache[key] = dict(sorted(out.items()))
        return self._cache[key]

    def scene_camera(self, scene_id: int):
        return self._merged(scene_id, "cam")

    def scene_gt(self, scene_id: int):
        return self._merged(scene_id, "gt")

    def scene_gt_info(self, scene_id: int):
        return self._merged(scene_id, "gt_info")

    def has_gt(self, scene_id: int) -> bool:
        return all(sub.has_gt(scene_id) for sub in self._subs.values())

    def scene_file(self, scene_id: int, kind: str) -> Path:
        return self._subs[self.eval_sensor].scene_file(scene_id, kind)

    def image_dir(self, scene_id: int) -> Path:
        return self._subs[self.eval_sensor].image_dir(scene_id)

    @property
    def camera_path(self) -> Path | None:
        return self._subs[self.eval_sensor].camera_path

    def camera_size(self):
        return None

    def is_gray(self, scene_id: int, view_id: int | None = None) -> bool:
        s = self.eval_sensor if view_id is None else self.view_of(view_id)[0]
        return self._subs[s].is_gray(scene_id)

    def rgb_path(self, scene_id: int, im_id: int) -> Path:
        s, im = self.view_of(im_id)
        return self._subs[s].rgb_path(scene_id, im)

    def depth_path(self, scene_id: int, im_id: int) -> Path | None:
        s, im = self.view_of(im_id)
        return self._subs[s].depth_path(scene_id, im)

    def mask_path(self, scene_id: int, im_id: int, gt_index: int, visib: bool = False) -> Path:
        s, im = self.view_of(im_id)
        return self._subs[s].mask_path(scene_id, im, gt_index, visib=visib)

    def scene_image_sizes(self, scene_id: int) -> dict[int, tuple[int, int]]:
        return {self.view_id(s, im): wh for s in self.sensors
                for im, wh in self._subs[s].scene_image_sizes(scene_id).items()}

    def image_size(self, scene_id: int, im_id: int) -> tuple[int, int]:
        s, im = self.view_of(im_id)
        return self._subs[s].image_size(scene_id, im)

    def check_image_size(self, scene_id: int, im_id: int, wh, path: Path, what: str = "image") -> None:
        s, im = self.view_of(im_id)
        self._subs[s].check_image_size(scene_id, im, wh, path, what)

    def check_image_files(self, scene_ids=None, *, depth: bool = False) -> None:
        for sub in self._subs.values():
            sub.check_image_files(scene_ids, depth=depth)

    def read_rgb(self, scene_id: int, im_id: int) -> np.ndarray:
        s, im = self.view_of(im_id)
        return self._subs[s].read_rgb(scene_id, im)

    def read_depth(self, scene_id: int, im_id: int) -> np.ndarray | None:
        s, im = self.view_of(im_id)
        return self._subs[s].read_depth(scene_id, im)

    def read_mask(self, scene_id: int, im_id: int, gt_index: int, visib: bool = False) -> np.ndarray:
        s, im = self.view_of(im_id)
        return self._subs[s].read_mask(scene_id, im, gt_index, visib=visib)
