"""The object database: meshes, surface points, diameters and symmetry sets of a ``models/`` folder."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from ..errors import CosyError
from ..io import bop
from .symmetries import PAPER_CONTINUOUS_STEPS, symmetry_set


def load_mesh(path: str | Path):
    """A trimesh.Trimesh from a PLY/OBJ/... file (vertices in mm), keeping colours and UVs."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise CosyError("model file not found (BOP models are models/obj_XXXXXX.ply)", path=path)
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types on malformed files
        raise CosyError(f"cannot read mesh ({type(e).__name__}: {e})", path=path) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.vertices) == 0:
        raise CosyError("mesh has no vertices", path=path)
    if len(mesh.faces) == 0:
        raise CosyError("mesh has no faces (a point cloud cannot be rendered)", path=path)
    return mesh


def diameter_of(points: np.ndarray) -> float:
    """Largest distance between two points (mm), via the convex hull's vertices."""
    from scipy.spatial import ConvexHull, QhullError

    P = np.asarray(points, dtype=np.float64)
    try:
        P = P[ConvexHull(P).vertices]
    except (QhullError, ValueError):
        pass
    best = 0.0
    for i in range(0, len(P), 1024):  # chunked to bound memory on big hulls
        d = np.linalg.norm(P[i:i + 1024, None] - P[None], axis=-1)
        best = max(best, float(d.max()))
    return best


def model_info_from_mesh(mesh, symmetries_discrete=None, symmetries_continuous=None) -> bop.ModelInfo:
    """A models_info.json entry computed from the mesh vertices (mm)."""
    V = np.asarray(mesh.vertices, dtype=np.float64)
    mins, maxs = V.min(0), V.max(0)
    return bop.ModelInfo(
        diameter=diameter_of(V), min_xyz=mins, size_xyz=maxs - mins,
        symmetries_discrete=np.zeros((0, 4, 4)) if symmetries_discrete is None else np.asarray(symmetries_discrete),
        symmetries_continuous=list(symmetries_continuous or []),
    )


@dataclass
class ObjectModel:
    """One object: its mesh file, metadata from models_info.json, sampled points and symmetries."""

    obj_id: int
    mesh_path: Path
    info: bop.ModelInfo
    n_points: int = 1000
    seed: int = 0
    n_continuous: int = PAPER_CONTINUOUS_STEPS
    _mesh: object = field(default=None, repr=False)

    @property
    def label(self) -> str:
        return f"obj_{self.obj_id:06d}"

    @property
    def diameter(self) -> float:
        """mm"""
        return self.info.diameter

    @property
    def mesh(self):
        if self._mesh is None:
            self._mesh = load_mesh(self.mesh_path)
        return self._mesh

    @cached_property
    def points(self) -> np.ndarray:
        """(n_points, 3) mm: area-uniform samples of the surface, deterministic under ``seed``."""
        import trimesh

        pts, _ = trimesh.sample.sample_surface(self.mesh, self.n_points, seed=self.seed)
        return np.asarray(pts, dtype=np.float64)

    @property
    def vertices(self) -> np.ndarray:
        """(V, 3) mm: the mesh vertices (what BOP metrics average over)."""
        return np.asarray(self.mesh.vertices, dtype=np.float64)

    @cached_property
    def symmetries(self) -> np.ndarray:
        """(S, 4, 4), identity first; continuous symmetries in ``n_continuous`` steps."""
        return symmetry_set(self.info.symmetries_discrete, self.info.symmetries_continuous, self.n_continuous)

    def symmetries_with_steps(self, n_continuous: int) -> np.ndarray:
        return symmetry_set(self.info.symmetries_discrete, self.info.symmetries_continuous, n_continuous)

    @property
    def is_symmetric(self) -> bool:
        return len(self.info.symmetries_discrete) > 0 or len(self.info.symmetries_continuous) > 0

    def surface_distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance (mm) of points (M, 3) in the model frame to the mesh surface."""
        import trimesh

        _, dist, _ = trimesh.proximity.closest_point(self.mesh, np.asarray(points, dtype=np.float64))
        return np.asarray(dist)


class ObjectDatabase:
    """Objects of a BOP models folder, keyed by obj_id (``db[obj_id]``, ``obj_id in db``)."""

    def __init__(self, objects: dict[int, ObjectModel], models_dir: Path | None = None):
        self.objects = dict(sorted(objects.items()))
        self.models_dir = models_dir

    @classmethod
    def from_models_dir(cls, models_dir: str | Path, *, n_points: int = 1000, seed: int = 0,
                        n_continuous: int = PAPER_CONTINUOUS_STEPS, obj_ids=None) -> "ObjectDatabase":
        models_dir = Path(models_dir)
        if not models_dir.is_dir():
            raise CosyError("models folder not found", path=models_dir)
        infos = bop.read_models_info(models_dir / "models_info.json")
        objs = {}
        for obj_id, info in infos.items():
            if obj_ids is not None and obj_id not in obj_ids:
                continue
            path = models_dir / f"obj_{obj_id:06d}.ply"
            if not path.is_file():
                raise CosyError(f"model of object {obj_id} listed in models_info.json is missing", path=path)
            objs[obj_id] = ObjectModel(obj_id, path, info, n_points=n_points, seed=seed, n_continuous=n_continuous)
        return cls(objs, models_dir)

    def __getitem__(self, obj_id: int) -> ObjectModel:
        try:
            return self.objects[int(obj_id)]
        except KeyError:
            raise CosyError(f"object {obj_id} is not in the models (known: {sorted(self.objects)})",
                            path=self.models_dir) from None

    def __contains__(self, obj_id) -> bool:
        return int(obj_id) in self.objects

    def __iter__(self):
        return iter(self.objects.values())

    def __len__(self) -> int:
        return len(self.objects)

    @property
    def obj_ids(self) -> list[int]:
        return list(self.objects)
