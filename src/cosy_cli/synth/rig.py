"""Synthetic multi-sensor datasets: the scenes of :mod:`.scenes` seen by a calibrated rig.

``cosy synth --sensors N`` writes the layout of the BOP industrial datasets (IPD, XYZ-IBD,
ITODD-MV; see :mod:`cosy_cli.io.dataset`): N sensors ``cam0`` .. ``cam<N-1>`` mounted on one
rig, each with its own intrinsics and image size; the last one is grey (``gray_<sensor>/``, one
channel), the others RGB (``rgb_<sensor>/``). ``cam0`` is the evaluation sensor (named in
``dataset_info.json``); it has the ``--width`` x ``--height`` images.

The rig: the sensors sit on a horizontal bar, :data:`BASELINE_MM` apart (alternately
:data:`DROP_MM` lower), each turned to look at the point :data:`CONVERGE_MM` in front of the
bar's centre. Each instant (``im_id``) of a scene places the rig as :func:`.scenes.sample_cameras`
places a camera; every sensor's ``scene_camera_<sensor>.json`` holds its ``cam_R_w2c`` and
``cam_t_w2c`` in the scene's world frame (the rig pose times the sensor's mounting).

Also written: ``camera_<sensor>.json`` per sensor, the evaluation sensor's test targets
(``test_targets_bop19.json`` and ``test_targets_bop24.json``) and
``test_targets_multiview_bop25.json`` with one entry per instant:
``{"scene_id": S, "im_id": [[SENSOR, IM_ID], ...]}`` (every sensor's image of the instant).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from ..errors import CosyError
from ..geometry.poses import look_at
from ..io import atomic, bop
from ..io.atomic import atomic_dir
from . import objects as objs
from .scenes import (
    DEPTH_SCALE, FOCAL_PER_WIDTH, SPLITS_WITH_TARGETS, TABLE_ID, SynthSummary, _check_args, _copy_models, _dir_size,
    _write_scene, sample_scene, scene_rng, table_mesh,
)

BASELINE_MM = 250.0
DROP_MM = 60.0
CONVERGE_MM = 600.0
SIZE_FACTORS = (1.0, 0.75, 1.25, 0.875, 1.125)  # image size of sensor k vs --width x --height (cycled)
FOCAL_FACTORS = (1.0, 0.85, 1.15)  # fx = fy = 1.3 width x this (cycled)
EVAL_SENSOR = "cam0"


@dataclasses.dataclass
class Sensor:
    name: str
    width: int
    height: int
    K: np.ndarray
    gray: bool
    T_rig_sensor: np.ndarray  # (4, 4) mm


def rig_sensors(n: int, width: int, height: int) -> list[Sensor]:
    """The ``n`` sensors of the synthetic rig for an evaluation sensor of ``width`` x ``height``."""
    out = []
    for k in range(n):
        s = SIZE_FACTORS[k % len(SIZE_FACTORS)]
        w, h = max(16, 2 * round(width * s / 2)), max(16, 2 * round(height * s / 2))
        f = FOCAL_PER_WIDTH * w * FOCAL_FACTORS[k % len(FOCAL_FACTORS)]
        K = np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
        eye = np.array([(k - (n - 1) / 2.0) * BASELINE_MM, DROP_MM * (k % 2), 0.0])
        T = look_at(eye, np.array([0.0, 0.0, CONVERGE_MM]), up=(0.0, -1.0, 0.0))  # rig frame: OpenCV, y down
        out.append(Sensor(f"cam{k}", w, h, K, gray=(k == n - 1), T_rig_sensor=T))
    return out


def generate_rig_dataset(out, n_sensors: int, scenes: int, views: int, objects_per_scene: int, seed: int = 0,
                         width: int = 640, height: int = 480, split: str = "test", overwrite: bool = False,
                         progress: bool = True) -> SynthSummary:
    """Write a multi-sensor BOP dataset (module doc) to ``out``: ``views`` instants per scene,
    each seen by every sensor. Atomic like :func:`.scenes.generate_dataset`; an existing
    non-empty ``out`` is refused unless ``overwrite`` (then replaced)."""
    from concurrent.futures import ThreadPoolExecutor

    from ..console import progress as progress_bar
    from ..rendering import SceneRenderer

    t0 = time.perf_counter()
    _check_args(scenes, views, objects_per_scene, seed, width, height, split)
    if not isinstance(n_sensors, (int, np.integer)) or n_sensors < 2:
        raise CosyError(f"--sensors must be an integer >= 2, got {n_sensors!r}")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise CosyError("--out exists and is not a folder", path=out)
    existing = out.is_dir() and any(out.iterdir())
    if existing and not overwrite:
        raise CosyError("output folder exists and is not empty (use --overwrite to replace it)", path=out)
    sensors = rig_sensors(int(n_sensors), width, height)
    meshes = objs.object_meshes()
    meshes[TABLE_ID] = table_mesh()
    targets, multiview = [], []
    bar = progress_bar(total=scenes * views * len(sensors), desc=f"synth {split}", unit="img", enabled=progress)
    renderers = {}
    try:
        with atomic_dir(out, overwrite=True) as tmp:
            import tempfile

            with tempfile.TemporaryDirectory(prefix=".cosy-synth-models.", dir=tmp) as ref:
                objs.write_models(Path(ref))
                _copy_models(Path(ref), tmp)
            for s in sensors:
                bop.write_camera(tmp / f"camera_{s.name}.json",
                                 bop.CameraInfo(K=s.K, width=s.width, height=s.height, depth_scale=DEPTH_SCALE))
                renderers[s.name] = SceneRenderer(meshes, s.width, s.height, znear=10.0, zfar=20_000.0, smooth=True)
            with ThreadPoolExecutor(max_workers=2, thread_name_prefix="synth-write") as pool:
                for k in range(scenes):
                    sid = k + 1
                    layout = sample_scene(scene_rng(seed, split, k), objects_per_scene, views)  # T_world_cam: the rig
                    for s in sensors:
                        lay = dataclasses.replace(layout, T_world_cam=layout.T_world_cam @ s.T_rig_sensor)
                        rows = _write_scene(tmp / split / f"{sid:06d}", sid, lay, renderers[s.name], s.K, s.width,
                                            s.height, ".png", bar, pool, sensor=s.name, gray=s.gray)
                        if s.name == EVAL_SENSOR:
                            targets += rows
                    multiview += [{"scene_id": sid, "im_id": [[s.name, v] for s in sensors]} for v in range(views)]
            atomic.write_json(tmp / "dataset_info.json", {
                "name": "cosy synth rig", "sensors": [s.name for s in sensors], "eval_sensor": EVAL_SENSOR,
                "modalities": {s.name: ["gray" if s.gray else "rgb", "depth"] for s in sensors},
                "image_sizes": {s.name: [s.width, s.height] for s in sensors}})
            if split in SPLITS_WITH_TARGETS:
                import pandas as pd

                t = pd.DataFrame(targets, columns=bop.TARGET_COLUMNS, dtype=np.int64)
                bop.write_targets(tmp / "test_targets_bop19.json", t)
                ims = t[["scene_id", "im_id"]].drop_duplicates()
                atomic.write_json(tmp / "test_targets_bop24.json",
                                  [{"im_id": int(i), "scene_id": int(s)} for s, i in zip(ims["scene_id"], ims["im_id"])],
                                  indent=None)
                atomic.write_json(tmp / "test_targets_multiview_bop25.json", multiview, indent=None)
    finally:
        for r in renderers.values():
            r.close()
        bar.close()
    n_images = scenes * views * len(sensors)
    return SynthSummary(out, split, scenes, n_images, n_images * objects_per_scene, len(objs.OBJECTS),
                        _dir_size(out), time.perf_counter() - t0, "replaced" if existing else "created")
