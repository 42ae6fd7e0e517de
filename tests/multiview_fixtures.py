"""Small BOP datasets for the multi-view tests and benchmarks, built without rendering.

``write_simple_models``: trimesh models with known symmetries (a box, a cylinder with many
sections, an asymmetric L shape, a look-alike pair 6/7). ``make_table_dataset``: scenes of
objects resting on a table (z = 0 in the world) seen by cameras on a ring around it, with
``scene_camera.json`` (cam_R_w2c / cam_t_w2c), ``scene_gt.json`` and ``scene_gt_info.json``
(visib_fract 1.0 when the object's centre projects into the image, else 0.0; dummy boxes). No
images. Every object is listed in every view in the same order, so the GT index is also the
physical instance. Lengths in mm.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from cosy_cli.geometry.poses import invert, look_at, make_pose
from cosy_cli.geometry.rotations import rotation_about_axis
from cosy_cli.io import bop
from cosy_cli.io.atomic import atomic_path

SIMPLE_OBJECTS = {1: "box", 2: "cylinder", 3: "l_shape", 6: "boss_block", 7: "boss_block_lookalike"}
K_DEFAULT = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
WIDTH, HEIGHT = 640, 480


def _rot(axis, deg):
    return make_pose(rotation_about_axis(np.asarray(axis, float), np.array([math.radians(deg)]))[0], np.zeros(3))


def _clean(T):
    T = T.copy()
    T[np.abs(T) < 1e-12] = 0.0
    return T


def _simple_mesh(obj_id: int):
    import trimesh

    if obj_id == 1:
        return trimesh.creation.box(extents=(80.0, 50.0, 30.0))
    if obj_id == 2:
        return trimesh.creation.cylinder(radius=25.0, height=70.0, sections=128)
    if obj_id == 3:
        a = trimesh.creation.box(extents=(90.0, 20.0, 20.0))
        b = trimesh.creation.box(extents=(20.0, 50.0, 20.0))
        b.apply_translation((35.0, 35.0, 0.0))
        c = trimesh.creation.box(extents=(20.0, 20.0, 30.0))
        c.apply_translation((-35.0, 0.0, 25.0))
        m = trimesh.util.concatenate([a, b, c])
    elif obj_id in (6, 7):
        base = trimesh.creation.box(extents=(70.0, 45.0, 30.0))
        boss = trimesh.creation.cylinder(radius=8.0, height=16.0, sections=32)
        boss.apply_translation((18.0, 8.0, 23.0))
        parts = [base, boss]
        if obj_id == 7:  # one more small boss: nearly the same shape
            b2 = trimesh.creation.box(extents=(8.0, 8.0, 6.0))
            b2.apply_translation((-25.0, -12.0, 18.0))
            parts.append(b2)
        m = trimesh.util.concatenate(parts)
    else:
        raise KeyError(obj_id)
    m.apply_translation(-(m.bounds[0] + m.bounds[1]) / 2)  # origin at the bbox centre
    return m


def _simple_symmetries(obj_id: int):
    if obj_id == 1:
        return np.stack([_clean(_rot((1, 0, 0), 180)), _clean(_rot((0, 1, 0), 180)), _clean(_rot((0, 0, 1), 180))]), []
    if obj_id == 2:
        return np.stack([_clean(_rot((1, 0, 0), 180))]), [{"axis": np.array([0.0, 0, 1]), "offset": np.zeros(3)}]
    return np.zeros((0, 4, 4)), []


def write_simple_models(root: str | Path, obj_ids=(1, 2, 3, 6, 7)) -> dict[int, bop.ModelInfo]:
    """models/obj_XXXXXX.ply (binary) + models_info.json with the true symmetries."""
    from cosy_cli.objects.database import model_info_from_mesh

    root = Path(root)
    infos = {}
    for o in obj_ids:
        mesh = _simple_mesh(o)
        disc, cont = _simple_symmetries(o)
        infos[o] = model_info_from_mesh(mesh, disc, cont)
        with atomic_path(root / "models" / f"obj_{o:06d}.ply") as tmp:
            tmp.write_bytes(mesh.export(file_type="ply", encoding="binary"))
    bop.write_models_info(root / "models" / "models_info.json", infos)
    return infos


def _vertices(root: Path, obj_id: int) -> np.ndarray:
    import trimesh

    return np.asarray(trimesh.load(root / "models" / f"obj_{obj_id:06d}.ply", force="mesh", process=False).vertices)


def _resting_rotation(obj_id, rng, models):
    if models == "synth":
        from cosy_cli.synth.objects import resting_rotation

        return resting_rotation(obj_id, rng)
    R = np.eye(3)
    if obj_id == 2 and rng.random() < 0.3:  # a lying cylinder
        R = rotation_about_axis(np.array([1.0, 0, 0]), np.array([math.pi / 2]))[0]
    yaw = rotation_about_axis(np.array([0.0, 0, 1]), np.array([rng.uniform(0, 2 * math.pi)]))[0]
    return yaw @ R


def make_table_dataset(root: str | Path, *, n_scenes: int = 1, n_views: int = 6, n_objects: int = 8, seed: int = 0,
                       models: str = "simple", obj_ids=None, split: str = "test", table_radius: float = 220.0,
                       cam_distance=(550.0, 800.0), elevation_deg=(30.0, 60.0), min_gap: float = 15.0) -> Path:
    """Write a BOP dataset of table scenes under ``root`` and return ``root``.

    ``models``: "simple" (this module's trimesh objects) or "synth" (``cosy_cli.synth.objects``,
    the T-LESS-like parts). Objects are drawn from ``obj_ids`` with repetition (identical
    instances), placed without overlap on a disc of ``table_radius`` mm.
    """
    root = Path(root)
    rng = np.random.default_rng(seed)
    if models == "synth":
        from cosy_cli.synth.objects import write_models

        infos = write_models(root)
    else:
        infos = write_simple_models(root, obj_ids or tuple(SIMPLE_OBJECTS))
    obj_ids = list(obj_ids or infos.keys())
    verts = {o: _vertices(root, o) for o in obj_ids}
    bop.write_camera(root / "camera.json", bop.CameraInfo(K=K_DEFAULT, width=WIDTH, height=HEIGHT))
    for s in range(1, n_scenes + 1):
        # objects on the table
        placed = []  # (obj_id, T_world_obj, radius)
        tries = 0
        while len(placed) < n_objects:
            tries += 1
            if tries > 10000:
                raise RuntimeError("cannot place the objects: enlarge table_radius")
            # every model once, then random repeats (identical instances)
            o = obj_ids[len(placed)] if len(placed) < len(obj_ids) else obj_ids[int(rng.integers(len(obj_ids)))]
            R = _resting_rotation(o, rng, models)
            V = verts[o] @ R.T
            rad = float(np.linalg.norm(V[:, :2] - (V[:, :2].max(0) + V[:, :2].min(0)) / 2, axis=1).max())
            xy = rng.uniform(-table_radius, table_radius, 2)
            if np.linalg.norm(xy) > table_radius:
                continue
            c = (V[:, :2].max(0) + V[:, :2].min(0)) / 2
            if any(np.linalg.norm(xy - p[3]) < rad + p[2] + min_gap for p in placed):
                continue
            t = np.array([xy[0] - c[0], xy[1] - c[1], -V[:, 2].min()])  # footprint centred on xy, on the table
            placed.append((o, make_pose(R, t), rad, xy))
        # cameras on a ring
        az0 = rng.uniform(0, 2 * math.pi)
        cams, gts, infos_gt = {}, {}, {}
        for v in range(n_views):
            az = az0 + 2 * math.pi * v / n_views + rng.uniform(-0.2, 0.2)
            el = math.radians(rng.uniform(*elevation_deg))
            dist = rng.uniform(*cam_distance)
            eye = dist * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
            target = np.r_[rng.uniform(-40, 40, 2), 0.0]
            T_world_cam = look_at(eye, target, up=(0.0, 0.0, 1.0))
            T_cam_world = invert(T_world_cam)
            im_id = v
            cams[im_id] = bop.SceneCamera(K=K_DEFAULT.copy(), depth_scale=1.0, T_cam_world=T_cam_world)
            gts[im_id], infos_gt[im_id] = [], []
            for o, T_wo, _, _ in placed:
                T_co = T_cam_world @ T_wo
                p = K_DEFAULT @ T_co[:3, 3]
                u, w = p[:2] / p[2]
                inside = p[2] > 0 and 0 <= u < WIDTH and 0 <= w < HEIGHT
                gts[im_id].append(bop.GtInstance(obj_id=int(o), T_cam_obj=T_co))
                box = np.array([max(0, u - 20), max(0, w - 20), 40, 40]) if inside else -np.ones(4)
                infos_gt[im_id].append(bop.GtInfo(bbox_obj=box, bbox_visib=box, px_count_all=1600,
                                                  px_count_valid=1600, px_count_visib=1600 if inside else 0,
                                                  visib_fract=1.0 if inside else 0.0))
        d = root / split / f"{s:06d}"
        bop.write_scene_camera(d / "scene_camera.json", cams)
        bop.write_scene_gt(d / "scene_gt.json", gts)
        bop.write_scene_gt_info(d / "scene_gt_info.json", infos_gt)
    return root
