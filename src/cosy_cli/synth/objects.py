"""Eight fixed procedural objects in the spirit of T-LESS: textureless industrial parts (mm).

The set is the same for every seed, so that networks trained on one generated dataset apply to
any other. Each part is built with boolean operations (manifold3d), then moved so that its
origin is the centre of its 3D bounding box, z up (BOP conventions). Its true symmetries are
declared by hand and checked by the tests against the mesh (residual < 0.1 mm).

=====  ====================  ===========================================================
obj_id name                  symmetries
=====  ====================  ===========================================================
1      block                 discrete: 180 deg about x, y, z
2      cylinder              continuous about z + 180 deg flip about x
3      stepped_cylinder      continuous about z (the two ends differ)
4      l_bracket             none
5      square_flange         discrete: 90, 180, 270 deg about z
6      boss_block            none
7      boss_block_notched    none (look-alike of 6: one 8 mm notch more)
8      hex_nut               discrete: 60 k deg about z, 180 deg flips (dihedral, 11 + identity)
=====  ====================  ===========================================================

Round parts use :data:`CIRCLE_SEGMENTS` sections: the largest deviation of the facets from the
true circle (the sagitta ``r (1 - cos(pi / n))``) is < 0.03 mm for radii up to 75 mm, well
under the 0.1 mm tolerance of the declared continuous symmetries.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Callable

import numpy as np

from ..geometry.poses import make_pose
from ..geometry.rotations import rotation_about_axis
from ..io import bop
from ..io.atomic import atomic_path
from ..objects.database import model_info_from_mesh

CIRCLE_SEGMENTS = 128  # sections of every round surface (sagitta 0.009 mm at r = 30 mm)
SHARP_EDGE_DEG = 30.0  # normals are split (flat shading) across edges sharper than this


# --------------------------------------------------------------------------------------------
# rotations used by the symmetry declarations
# --------------------------------------------------------------------------------------------
def _rot(axis, deg: float) -> np.ndarray:
    """4x4 rotation by ``deg`` degrees about ``axis`` through the origin (exact for multiples of 90)."""
    R = rotation_about_axis(np.asarray(axis, dtype=np.float64), np.array([math.radians(deg)]))[0]
    R[np.abs(R) < 1e-15] = 0.0
    return make_pose(R, np.zeros(3))


X, Y, Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)


# --------------------------------------------------------------------------------------------
# specification of one object
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RestPose:
    """A stable way to lay the object on a table: the model axis ``down`` points to -z (world).

    ``roll``: a model axis about which the object may be turned freely before laying it down
    (a cylinder lying on its side), or None.
    """

    down: tuple[float, float, float]
    roll: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class ObjectSpec:
    obj_id: int
    name: str
    description: str
    build: Callable[[], object]  # -> manifold3d.Manifold, any placement (centred afterwards)
    symmetries_discrete: tuple = ()  # 4x4 matrices (mm), identity excluded, the whole group
    symmetries_continuous: tuple = ()  # ({"axis": (3,), "offset": (3,) mm}, ...)
    rest_poses: tuple[RestPose, ...] = (RestPose((0.0, 0.0, -1.0)),)
    color: tuple[float, float, float] = (0.6, 0.6, 0.6)  # base colour of the PLY, 0..1
    lookalike_of: int | None = None
    extra: dict = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# builders (manifold3d); raw coordinates in mm, centred on the bbox afterwards
# --------------------------------------------------------------------------------------------
def _m():
    import manifold3d

    return manifold3d.Manifold


def _box(sx: float, sy: float, sz: float, x0: float = 0.0, y0: float = 0.0, z0: float = 0.0):
    """Axis-aligned box with its minimum corner at (x0, y0, z0)."""
    return _m().cube([sx, sy, sz]).translate([x0, y0, z0])


def _cyl(r: float, h: float, x: float = 0.0, y: float = 0.0, z0: float = 0.0, n: int = CIRCLE_SEGMENTS):
    """Cylinder along z, axis at (x, y), from z0 to z0 + h; one vertex at angle 0."""
    return _m().cylinder(h, r, r, n).translate([x, y, z0])


def _cyl_x(r: float, h: float, y: float, z: float, x0: float = 0.0, n: int = CIRCLE_SEGMENTS):
    """Cylinder along x, axis at (y, z), from x0 to x0 + h."""
    return _m().cylinder(h, r, r, n).rotate([0.0, 90.0, 0.0]).translate([x0, y, z])


def _block():
    return _box(90, 60, 40)


def _cylinder():
    return _cyl(30, 80)


def _stepped_cylinder():
    body = _cyl(35, 45) + _cyl(20, 20, z0=45 - 1e-3)
    return body - _cyl(12, 25 + 1, z0=-1)


def _l_bracket():
    base = _box(85, 50, 10)
    upright = _box(10, 50, 65)
    part = base + upright
    part = part - _cyl(6, 12, x=55, y=15, z0=-1)  # hole through the base, off-centre in y
    part = part - _cyl_x(7, 12, y=32, z=42, x0=-1)  # hole through the upright
    return part


def _square_flange():
    base = _box(70, 70, 25, -35, -35, 0)
    top = _box(40, 40, 25 + 1e-3, -20, -20, 25 - 1e-3)
    return (base + top) - _cyl(10, 52, z0=-1, n=64)


def _boss_block():
    body = _box(90, 60, 30, -45, -30, 0)
    boss = _cyl(12, 18 + 1e-3, x=22, y=8, z0=30 - 1e-3)
    hole = _cyl(7, 32, x=-25, y=-12, z0=-1)
    return (body + boss) - hole


def _boss_block_notched():
    notch = _box(8, 8 + 1, 8 + 1, 5, -30 - 1, 30 - 8)  # 8 mm notch in the top edge of the -y side
    return _boss_block() - notch


def _hex_nut():
    prism = _m().cylinder(26, 32, 32, 6)  # vertices at 0, 60, ... deg: flats face +-y
    return prism - _cyl(14, 28, z0=-1, n=96)


_RX180, _RY180, _RZ180 = _rot(X, 180), _rot(Y, 180), _rot(Z, 180)
_ALL_FACES = tuple(RestPose(d) for d in ((0, 0, -1), (0, 0, 1), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0)))

OBJECTS: tuple[ObjectSpec, ...] = (
    ObjectSpec(1, "block", "plain box 90 x 60 x 40 mm", _block,
               symmetries_discrete=(_RX180, _RY180, _RZ180),
               rest_poses=_ALL_FACES,
               color=(0.62, 0.62, 0.60)),
    ObjectSpec(2, "cylinder", "plain cylinder r 30 mm, 80 mm high", _cylinder,
               symmetries_discrete=(_RX180,), symmetries_continuous=({"axis": Z, "offset": (0.0, 0.0, 0.0)},),
               rest_poses=(RestPose((0, 0, -1)), RestPose((0, 0, 1)), RestPose((1, 0, 0), roll=Z)),
               color=(0.55, 0.56, 0.58)),
    ObjectSpec(3, "stepped_cylinder", "cylinder r 35 mm with a coaxial step r 20 mm on top and a blind hole "
               "r 12 mm from below", _stepped_cylinder,
               symmetries_continuous=({"axis": Z, "offset": (0.0, 0.0, 0.0)},),
               rest_poses=(RestPose((0, 0, -1)), RestPose((1, 0, 0), roll=Z)),
               color=(0.50, 0.50, 0.50)),
    ObjectSpec(4, "l_bracket", "L bracket 85 x 50 x 65 mm, 10 mm plates, one hole in each plate", _l_bracket,
               rest_poses=(RestPose((0, 0, -1)), RestPose((-1, 0, 0)), RestPose((0, 1, 0)), RestPose((0, -1, 0))),
               color=(0.66, 0.64, 0.60)),
    ObjectSpec(5, "square_flange", "square base 70 x 70 x 25 mm under a square top 40 x 40 x 25 mm, centred "
               "through hole r 10 mm", _square_flange,
               symmetries_discrete=(_rot(Z, 90), _RZ180, _rot(Z, 270)),
               rest_poses=_ALL_FACES,
               color=(0.58, 0.57, 0.55)),
    ObjectSpec(6, "boss_block", "block 90 x 60 x 30 mm with an off-centre boss r 12 mm and a through hole", _boss_block,
               rest_poses=tuple(RestPose(d) for d in ((0, 0, -1), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0))),
               color=(0.60, 0.59, 0.57)),
    ObjectSpec(7, "boss_block_notched", "object 6 with one 8 x 8 x 8 mm notch in a top edge (look-alike)",
               _boss_block_notched,
               rest_poses=tuple(RestPose(d) for d in ((0, 0, -1), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0))),
               color=(0.60, 0.59, 0.57), lookalike_of=6),
    ObjectSpec(8, "hex_nut", "hexagonal nut, 64 mm across corners, 26 mm high, hole r 14 mm", _hex_nut,
               symmetries_discrete=tuple(_rot(Z, 60 * k) for k in range(1, 6))
               + tuple(_rot(Z, 60 * k) @ _RX180 for k in range(6)),
               rest_poses=(RestPose((0, 0, -1)), RestPose((0, 0, 1)), RestPose((0, -1, 0)), RestPose((0, 1, 0))),
               color=(0.52, 0.53, 0.55)),
)

OBJECT_IDS: tuple[int, ...] = tuple(o.obj_id for o in OBJECTS)


def object_spec(obj_id: int) -> ObjectSpec:
    for o in OBJECTS:
        if o.obj_id == int(obj_id):
            return o
    raise KeyError(f"no procedural object {obj_id} (known: {list(OBJECT_IDS)})")


# --------------------------------------------------------------------------------------------
# meshes
# --------------------------------------------------------------------------------------------
def _to_trimesh(manifold):
    import trimesh

    mesh = manifold.to_mesh64()
    V = np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3]
    F = np.asarray(mesh.tri_verts, dtype=np.int64)
    tm = trimesh.Trimesh(V, F, process=True)
    tm.vertices -= tm.bounds.mean(axis=0)  # origin at the centre of the 3D bounding box
    tm.vertices[np.abs(tm.vertices) < 1e-9] = 0.0
    return tm


@lru_cache(maxsize=None)
def _solid(obj_id: int):
    """Watertight mesh of one object (merged vertices), origin at its bbox centre, mm."""
    tm = _to_trimesh(object_spec(obj_id).build())
    if not tm.is_watertight:
        raise RuntimeError(f"procedural object {obj_id} is not watertight")
    return tm


def solid_mesh(obj_id: int):
    """A copy of the watertight mesh of object ``obj_id`` (mm, origin at the bbox centre)."""
    return _solid(int(obj_id)).copy()


def _vertex_colors(n: int, color) -> np.ndarray:
    c = np.round(np.asarray(color, dtype=np.float64) * 255).astype(np.uint8)
    return np.tile(np.concatenate([c, [255]]).astype(np.uint8), (n, 1))


def object_mesh(obj_id: int):
    """The mesh written to ``models/``: flat-shaded across sharp edges (vertices split there,
    smooth on round surfaces), with vertex normals and the object's base vertex colour. mm."""
    import trimesh

    solid = _solid(int(obj_id))
    shaded = trimesh.graph.smooth_shade(solid, angle=math.radians(SHARP_EDGE_DEG), facet_minarea=None)
    mesh = trimesh.Trimesh(shaded.vertices, shaded.faces, vertex_normals=shaded.vertex_normals, process=False)
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=_vertex_colors(len(mesh.vertices),
                                                                                object_spec(obj_id).color))
    return mesh


def eval_mesh(obj_id: int):
    """The mesh written to ``models_eval/``: the watertight mesh (merged vertices, no duplicates
    at sharp edges) with vertex normals and colours, mm. Its vertices include every extreme point
    of the part, so maxima over vertices (BOP's MSSD/MSPD) are exact; averages (ADD) should use
    area-uniform surface samples (``ObjectModel.points``) rather than these vertices."""
    import trimesh

    solid = _solid(int(obj_id))
    mesh = trimesh.Trimesh(solid.vertices, solid.faces, vertex_normals=solid.vertex_normals, process=False)
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=_vertex_colors(len(mesh.vertices),
                                                                                object_spec(obj_id).color))
    return mesh


def object_meshes() -> dict:
    """{obj_id: trimesh.Trimesh} of the models/ meshes (mm)."""
    return {o.obj_id: object_mesh(o.obj_id) for o in OBJECTS}


def model_info(obj_id: int, mesh=None) -> bop.ModelInfo:
    """models_info.json entry: diameter (mm, over the vertices), bbox, true symmetries."""
    spec = object_spec(obj_id)
    mesh = _solid(int(obj_id)) if mesh is None else mesh
    disc = np.stack(spec.symmetries_discrete) if spec.symmetries_discrete else np.zeros((0, 4, 4))
    cont = [{"axis": np.asarray(c["axis"], dtype=np.float64), "offset": np.asarray(c["offset"], dtype=np.float64)}
            for c in spec.symmetries_continuous]
    return model_info_from_mesh(mesh, disc, cont)


def symmetry_transforms(obj_id: int) -> tuple[np.ndarray, list[dict]]:
    """(discrete (K, 4, 4) without identity, continuous [{axis, offset}]) of an object, mm."""
    info = model_info(obj_id)
    return info.symmetries_discrete, info.symmetries_continuous


def _export_ply(mesh, path: Path) -> None:
    with atomic_path(path) as tmp:
        data = mesh.export(file_type="ply", encoding="binary", vertex_normal=True)
        tmp.write_bytes(data)


def write_models(root: str | Path) -> dict[int, bop.ModelInfo]:
    """Write ``root/models/`` (obj_XXXXXX.ply + models_info.json) and ``root/models_eval/``.

    Meshes are binary PLY in mm with vertex normals and vertex colours. Returns the infos.
    Every file is byte-identical between calls (no seed involved).
    """
    root = Path(root)
    infos: dict[int, bop.ModelInfo] = {}
    for o in OBJECTS:
        infos[o.obj_id] = model_info(o.obj_id)
        _export_ply(object_mesh(o.obj_id), root / "models" / f"obj_{o.obj_id:06d}.ply")
        _export_ply(eval_mesh(o.obj_id), root / "models_eval" / f"obj_{o.obj_id:06d}.ply")
    bop.write_models_info(root / "models" / "models_info.json", infos)
    bop.write_models_info(root / "models_eval" / "models_info.json", infos)
    return infos


# --------------------------------------------------------------------------------------------
# resting on a table
# --------------------------------------------------------------------------------------------
def _rotation_to_down(down: np.ndarray) -> np.ndarray:
    """A rotation R with R @ down = (0, 0, -1); exact for the coordinate axes."""
    d = np.asarray(down, dtype=np.float64)
    d = d / np.linalg.norm(d)
    target = np.array([0.0, 0.0, -1.0])
    c = float(d @ target)
    if c > 1 - 1e-12:
        return np.eye(3)
    if c < -1 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])  # 180 deg about x
    axis = np.cross(d, target)
    R = rotation_about_axis(axis, np.array([math.acos(max(-1.0, min(1.0, c)))]))[0]
    R[np.abs(R) < 1e-15] = 0.0
    return R


def resting_rotation(obj_id: int, rng: np.random.Generator) -> np.ndarray:
    """A random stable orientation R_world_obj (3x3) of an object on a horizontal table:
    one of its rest poses, a free roll where the pose allows it, and a uniform yaw about z."""
    spec = object_spec(obj_id)
    pose = spec.rest_poses[int(rng.integers(len(spec.rest_poses)))]
    R = _rotation_to_down(np.asarray(pose.down))
    if pose.roll is not None:
        R = R @ rotation_about_axis(np.asarray(pose.roll, dtype=np.float64), np.array([rng.uniform(0, 2 * np.pi)]))[0]
    yaw = rotation_about_axis(np.array(Z), np.array([rng.uniform(0, 2 * np.pi)]))[0]
    return yaw @ R
