"""The object database: meshes, surface points, diameters and symmetry sets of a ``models/`` folder."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from ..errors import CosyError, warn
from ..io import bop
from .symmetries import PAPER_CONTINUOUS_STEPS, symmetry_set


class MeshFileError(CosyError):
    """A model file that cannot be used (missing, cut short, NaN vertices, faces out of range, no
    faces). A CosyError (one line, exit 2); stages that tolerate per-item failures (``cosy viz``
    skips a figure it cannot draw) let this one through: every item using the model would fail."""


_WARNED_TEXTURES: set[str] = set()  # mesh files whose missing texture was reported


def forget_reported_textures() -> None:
    """Report missing textures again (``cosy validate`` lists every warning of its own run)."""
    _WARNED_TEXTURES.clear()


def load_mesh(path: str | Path):
    """A trimesh.Trimesh from a PLY/OBJ/... file (vertices in mm), checked, keeping colours and UVs.

    Every stage reads models through this function (or checks its own reads with
    :func:`check_mesh_arrays` / :func:`check_ply_data`), so a broken file stops any stage with one
    line naming it (:class:`CosyError`): a PLY with less data than its header declares (cut
    short), NaN or infinite vertices, face indices past the vertex count, no vertices or no faces.
    Vertex colours and textures (PLY ``comment TextureFile`` + ``texture_u/v``, OBJ + MTL
    ``map_Kd``) are kept; a texture file (or material library) the mesh names but that does not
    exist gives one :func:`~cosy_cli.errors.warn` line and a mesh without colours (rendered in the
    renderer's default grey).
    """
    import logging

    import trimesh

    path = Path(path)
    if not path.is_file():
        raise MeshFileError("model file not found (BOP models are models/obj_XXXXXX.ply)", path=path)
    header = None
    if path.suffix.lower() == ".ply":
        header = check_ply_data(path)
    missing = missing_texture_files(path, header)
    tm_log = logging.getLogger("trimesh")
    level = tm_log.level
    tm_log.setLevel(logging.CRITICAL)  # trimesh logs tracebacks for missing textures: reported below instead
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types on malformed files
        raise MeshFileError(f"cannot read mesh ({type(e).__name__}: {e})", path=path) from None
    finally:
        tm_log.setLevel(level)
    if not isinstance(mesh, trimesh.Trimesh) or (header is not None and header.count("face") == 0):
        # trimesh reads a file without faces as a point cloud, or drops its vertices
        n_vertices = header.count("vertex") if header is not None else len(getattr(mesh, "vertices", ()))
        check_mesh_arrays(np.zeros((n_vertices, 3)), None, path)
    mesh.metadata.pop("_ply_raw", None)  # a second copy of every array: not needed once loaded
    mesh.metadata["file_path"] = str(path)  # named by messages about the mesh (e.g. the renderer's)
    check_mesh_arrays(mesh.vertices, mesh.faces, path)
    if header is not None and len(mesh.vertices) < header.count("vertex"):
        raise MeshFileError(f"the header declares {header.count('vertex')} vertices but {len(mesh.vertices)} "
                            "were read (truncated or malformed file)", path=path)
    if missing:
        if str(path.resolve()) not in _WARNED_TEXTURES:  # once per mesh file and process
            _WARNED_TEXTURES.add(str(path.resolve()))
            warn(f"{missing[0]!r}, a texture named by the mesh, is missing: rendered without texture "
                 f"(grey){f' ({len(missing)} missing files)' if len(missing) > 1 else ''}", path=path)
        mesh.visual = trimesh.visual.ColorVisuals(mesh=mesh)
    return mesh


def check_mesh_arrays(vertices, faces, path: str | Path) -> None:
    """CosyError naming ``path`` unless the mesh has vertices, all finite, and at least one
    triangle whose indices all lie in [0, number of vertices)."""
    V = np.asarray(vertices)
    if V.ndim != 2 or len(V) == 0:
        raise MeshFileError("mesh has no vertices", path=path)
    finite = np.isfinite(V).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise MeshFileError(f"{len(bad)} of {len(V)} vertices are NaN or infinite (first: vertex {bad[0]}, "
                        f"{V[bad[0]].tolist()})", path=path)
    F = None if faces is None else np.asarray(faces)
    if F is None or F.size == 0:
        raise MeshFileError("mesh has no faces (a point cloud cannot be rendered or sampled as a surface)", path=path)
    out = (F < 0) | (F >= len(V))
    if out.any():
        j = int(np.flatnonzero(out.any(axis=1))[0])
        k = int(F[j][out[j]][0])
        raise MeshFileError(f"face {j} uses vertex index {k} but the mesh has {len(V)} vertices "
                        f"({int(out.any(axis=1).sum())} faces out of range)", path=path)


def missing_texture_files(path: str | Path, header: "PlyHeader | None" = None) -> list[str]:
    """Texture images (and OBJ material libraries) a mesh file names that do not exist next to it:
    PLY ``comment TextureFile NAME``; OBJ ``mtllib NAME`` and the ``map_Kd`` images of those MTLs."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext == ".ply":
        names = (header or read_ply_header(path)).texture_files
        return [n for n in names if not (path.parent / n).is_file()]
    if ext != ".obj":
        return []
    missing = []
    with open(path, "rb") as f:
        libs = [ln.split(None, 1)[1].decode("utf-8", "replace").strip() for ln in f
                if ln.startswith(b"mtllib") and len(ln.split()) > 1]
    for lib in libs:
        mtl = path.parent / lib
        if not mtl.is_file():
            missing.append(lib)
            continue
        for ln in mtl.read_text(errors="replace").splitlines():
            w = ln.split()
            if w and w[0].lower() in ("map_kd",) and len(w) > 1 and not (mtl.parent / w[-1]).is_file():
                missing.append(w[-1])
    return missing


# PLY element counts are checked against the data present before trimesh reads a file: trimesh
# reads a truncated ASCII PLY without complaint (fewer faces, or none) and fails on a truncated
# binary one with messages that do not say what is wrong.
_PLY_NUMPY = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}  # PLY type -> numpy type
_PLY_SIZES = {k: np.dtype(v).itemsize for k, v in _PLY_NUMPY.items()}
_PLY_NP = {1: "u1", 2: "u2", 4: "u4"}


@dataclass
class PlyHeader:
    """What a PLY header declares: ``format`` (ascii / binary_little_endian / binary_big_endian),
    ``elements`` [(name, count, [(prop name, type, list count type or None), ...])], the byte
    offset of the data, and the texture files named by ``comment TextureFile`` lines."""

    format: str
    elements: list
    data_offset: int
    texture_files: list

    def count(self, name: str) -> int:
        return next((c for n, c, _ in self.elements if n == name), 0)


def read_ply_header(path: str | Path, data: bytes | None = None) -> PlyHeader:
    """Parse a PLY header; CosyError naming the file when it is cut short or malformed."""
    path = Path(path)
    if data is None:
        data = path.read_bytes()
    if not data.startswith(b"ply"):
        raise MeshFileError("not a PLY file (it does not start with 'ply')", path=path)
    end = data.find(b"end_header")
    nl = data.find(b"\n", end) if end >= 0 else -1
    if end < 0 or nl < 0:
        raise MeshFileError("truncated PLY file: the header has no end_header line", path=path)
    fmt, elements, textures = None, [], []
    for i, line in enumerate(data[:end].decode("ascii", "replace").splitlines()):
        w = line.split()
        if not w:
            continue
        try:
            if w[0] == "format":
                fmt = w[1]
            elif w[0] == "comment" and len(w) > 2 and w[1].lower() == "texturefile":
                textures.append(line.split(None, 2)[2].strip())
            elif w[0] == "element":
                elements.append((w[1], int(w[2]), []))
                if elements[-1][1] < 0:
                    raise ValueError
            elif w[0] == "property":
                if not elements:
                    raise ValueError
                if w[1] == "list":
                    if w[2] not in _PLY_SIZES or w[3] not in _PLY_SIZES:
                        raise ValueError
                    elements[-1][2].append((w[4], w[3], w[2]))
                else:
                    if w[1] not in _PLY_SIZES:
                        raise ValueError
                    elements[-1][2].append((w[2], w[1], None))
        except (ValueError, IndexError):
            raise MeshFileError(f"malformed PLY header line {i + 1}: {line.strip()!r}", path=path) from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise MeshFileError(f"unknown PLY format {fmt!r} (expected ascii or binary_little/big_endian)", path=path)
    return PlyHeader(fmt, elements, nl + 1, textures)


def _declared(header: PlyHeader) -> str:
    names = {"vertex": "vertices", "face": "faces"}
    return " and ".join(f"{c} {names.get(n, n)}" for n, c, _ in header.elements)


def read_ply_mesh(path: str | Path, data: bytes | None = None, header: PlyHeader | None = None
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """Vertices (V, 3) mm and triangles (F, 3) of a PLY file (binary or ASCII) read with numpy,
    without trimesh (start-up time): ``data`` the file's bytes, ``header`` its
    :func:`read_ply_header`, when the caller has them. Handles the common layouts (scalar vertex
    properties, triangle faces as one list property); anything else raises ``ValueError`` (callers
    fall back to :func:`load_mesh`); a malformed header is a :class:`MeshFileError`."""
    path = Path(path)
    if data is None:
        data = path.read_bytes()
    h = header or read_ply_header(path, data)
    names = [n for n, _, _ in h.elements]
    if "vertex" not in names:
        raise ValueError("no vertex element")
    body = data[h.data_offset:]
    verts, faces = None, None
    if h.format == "ascii":
        lines = body.decode("ascii").split("\n")
        pos = 0
        for name, count, props in h.elements:
            block = lines[pos:pos + count]
            pos += count
            if name == "vertex":
                pn = [p[0] for p in props]
                arr = np.array(" ".join(block).split(), dtype=np.float64).reshape(count, len(pn))
                verts = arr[:, [pn.index(a) for a in "xyz"]]
            elif name == "face":
                if len(props) != 1 or props[0][2] is None:
                    raise ValueError("face element layout not handled")
                arr = np.array(" ".join(block).split(), dtype=np.int64)
                if count and (len(arr) != 4 * count or np.any(arr.reshape(-1, 4)[:, 0] != 3)):
                    raise ValueError("non-triangle faces")
                faces = arr.reshape(-1, 4)[:, 1:]
        return verts, faces
    bo = "<" if h.format == "binary_little_endian" else ">"
    off = 0
    for name, count, props in h.elements:
        if all(lt is None for _, _, lt in props):
            dt = np.dtype([(pn, bo + _PLY_NUMPY[t]) for pn, t, _ in props])
            arr = np.frombuffer(body, dtype=dt, count=count, offset=off)
            off += dt.itemsize * count
            if name == "vertex":
                verts = np.stack([arr[a].astype(np.float64) for a in "xyz"], axis=1)
        elif name == "face" and sum(lt is not None for _, _, lt in props) == 1:
            fields = []
            for pn, t, lt in props:
                if lt is not None:
                    fields += [("n", bo + _PLY_NUMPY[lt]), ("idx", bo + _PLY_NUMPY[t], (3,))]
                else:
                    fields.append((pn, bo + _PLY_NUMPY[t]))
            dt = np.dtype(fields)
            arr = np.frombuffer(body, dtype=dt, count=count, offset=off)
            if count and np.any(arr["n"] != 3):
                raise ValueError("non-triangle faces")
            faces = arr["idx"].astype(np.int64)
            off += dt.itemsize * count
        else:
            if name in ("vertex", "face") or verts is None or faces is None:
                raise ValueError(f"element {name} layout not handled")
            break  # elements after vertex and face are not needed
    return verts, faces


def check_ply_data(path: str | Path, data: bytes | None = None) -> PlyHeader:
    """CosyError naming the file when a PLY holds less data than its header declares (a file cut
    short: binary sizes are summed element by element, ASCII files need one line per element)."""
    path = Path(path)
    if data is None:
        data = path.read_bytes()
    h = read_ply_header(path, data)
    body = memoryview(data)[h.data_offset:]
    if h.format == "ascii":
        lines = [ln for ln in bytes(body).split(b"\n") if ln.strip()]
        need = sum(c for _, c, _ in h.elements)
        if len(lines) < need:
            raise MeshFileError(f"truncated PLY file: the header declares {_declared(h)} ({need} data lines) but "
                            f"only {len(lines)} lines follow it", path=path)
        pos = 0
        for name, count, props in h.elements:
            pos += count
            if count == 0 or not props:
                continue
            tokens = lines[pos - 1].split()  # a file cut mid-line: its last row is short
            try:
                n = _ascii_row_tokens(props, tokens)
            except (ValueError, IndexError):
                n = len(props) + 1
            if len(tokens) < n:
                raise MeshFileError(f"truncated PLY file: data line {pos} ({name} {count - 1}, the last one) has "
                                f"{len(tokens)} values, expected {n}", path=path)
        return h
    bo = "<" if h.format == "binary_little_endian" else ">"
    off = 0
    for name, count, props in h.elements:
        if all(lt is None for _, _, lt in props):
            off += count * sum(_PLY_SIZES[t] for _, t, _ in props)
        else:
            off = _binary_list_element_end(body, off, count, props, bo)
        if off is None or off > len(body):
            raise MeshFileError(f"truncated PLY file: the header declares {_declared(h)} but the data ends after "
                            f"{len(body)} bytes, within element '{name}'", path=path)
    return h


def _ascii_row_tokens(props, tokens) -> int:
    """How many values an ASCII row of these properties holds (list lengths read from the row)."""
    n = 0
    for _, _, lt in props:
        n += 1 + int(float(tokens[n])) if lt is not None else 1
    return n


def _binary_list_element_end(body, off: int, count: int, props, bo: str) -> int | None:
    """Byte offset where a binary element with list properties ends, or None if the data stops
    first. Fast path: every row's lists as long as the first row's (triangles); else row by row."""
    n, order = len(body), ("little" if bo == "<" else "big")

    def row(p):  # (size, [(offset of a list count, its size, its value)]) of the row at p; None past the data
        size, counts = 0, []
        for _, t, lt in props:
            if lt is None:
                size += _PLY_SIZES[t]
                continue
            cs = _PLY_SIZES[lt]
            if p + size + cs > n:
                return None
            k = int.from_bytes(body[p + size:p + size + cs], order)
            counts.append((size, cs, k))
            size += cs + k * _PLY_SIZES[t]
        return size, counts

    if count == 0:
        return off
    first = row(off)
    if first is None:
        return None
    size, counts = first
    if off + count * size <= n:
        dt = np.dtype({"names": [f"n{i}" for i in range(len(counts))],
                       "formats": [bo + _PLY_NP[cs] if cs in _PLY_NP else "V%d" % cs for _, cs, _ in counts],
                       "offsets": [o for o, _, _ in counts], "itemsize": size})
        rows = np.frombuffer(body, dtype=dt, count=count, offset=off)
        if all(cs not in _PLY_NP or np.all(rows[f"n{i}"] == k) for i, (_, cs, k) in enumerate(counts)):
            return off + count * size
    for _ in range(count):  # lists of varying length (quads among triangles): walk the rows
        r = row(off)
        if r is None or off + r[0] > n:
            return None
        off += r[0]
    return off


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
