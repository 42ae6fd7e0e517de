"""Where things are in a BOP dataset folder, for the classic and the BOP-H3 layouts.

Classic::

    DATASET/camera.json, models/, models_eval/, test_targets_bop19.json
    DATASET/<split>[_<split_type>]/<scene_id:06d>/{rgb|gray}/<im_id:06d>.{png|jpg}
                                               depth/, mask/, mask_visib/
                                               scene_camera.json, scene_gt.json, scene_gt_info.json

BOP-H3 (HOT3D, HOPEv2, HANDAL in BOP 2024) adds per-sensor files: ``scene_camera_<sensor>.json``,
``scene_gt_<sensor>.json``, ``scene_gt_info_<sensor>.json`` and image folders named by sensor
(``rgb``, ``gray1``, ``gray2``...). Pass ``sensor`` to pick one; by default it is detected.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from ..errors import CosyError
from . import bop, images

TARGET_FILES = ("test_targets_bop19.json", "test_targets_bop24.json")


@dataclass
class BopDataset:
    root: Path
    split: str = "test"
    split_type: str | None = None
    sensor: str | None = None
    models_subdir: str = "models"
    camera_file: str | Path | None = None  # the dataset camera file, relative to root (or absolute); see camera_path
    _cache: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        self.root = Path(self.root)
        if not self.root.is_dir():
            raise CosyError("dataset folder not found", path=self.root)

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
        for name in ([s] if s else []) + ["rgb", "gray"]:
            if (d / name).is_dir():
                return d / name
        raise CosyError(f"no image folder ({'/'.join(([s] if s else []) + ['rgb', 'gray'])})", path=d)

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
        names = ([f"camera_{self.split_type}.json"] if self.split_type else []) + ["camera.json"]
        for n in names:
            if (self.root / n).is_file():
                return self.root / n
        others = sorted(self.root.glob("camera_*.json"))
        return others[0] if len(others) == 1 else None

    def camera(self) -> bop.CameraInfo | None:
        p = self.camera_path
        return bop.read_camera(p) if p is not None else None

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
        folder = d / f"{base}_{s}" if s and (d / f"{base}_{s}").is_dir() else d / base
        return folder / f"{int(im_id):06d}_{int(gt_index):06d}.png"

    def read_rgb(self, scene_id: int, im_id: int) -> np.ndarray:
        return images.read_rgb(self.rgb_path(scene_id, im_id))

    def read_depth(self, scene_id: int, im_id: int) -> np.ndarray | None:
        """Depth in mm, or None when the dataset has no depth for this image."""
        p = self.depth_path(scene_id, im_id)
        if p is None:
            return None
        return images.read_depth(p, self.scene_camera(scene_id)[im_id].depth_scale)
