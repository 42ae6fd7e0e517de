"""``cosy new-dataset``: a BOP dataset from your own images, intrinsics, meshes (and boxes).

Inputs
------
- **images** (one scene per ``--images``): a folder of ``.png/.jpg/.jpeg/.tif/.tiff/.bmp/.webp``
  images (not recursive; sorted in natural order: ``img2`` before ``img10``) or one image file.
  Images become ``SPLIT/SCENE_ID/rgb/000000.png ...`` (PNG and JPEG files are copied byte for
  byte; other formats, and JPEGs whose EXIF orientation turns them, are re-encoded as PNG).
  ``image_names.json`` in each scene folder maps the BOP image id to the original file name.
- **intrinsics** (pixels, OpenCV), in any of these JSON forms: a 3x3 list (or 9 numbers);
  ``{"cam_K": [9 numbers]}`` (BOP ``scene_camera.json`` entry); ``{"fx", "fy", "cx", "cy"}``
  (BOP ``camera.json``; ``width``/``height`` are then checked); ``{"K": 3x3, "resolution": [h, w]}``
  (MegaPose ``camera_data.json``); or an object keyed by image file name (or stem) whose values
  are any of these (one K per image). Where each image's K comes from, most specific first: the
  ``--intrinsics`` file's entry for that image, ``IMAGE_STEM.json`` next to the image, the single
  K of ``--intrinsics``, a ``camera_data.json | camera.json | intrinsics.json | K.json`` in the
  images folder.
- **depth** (optional): a folder with one depth image per image, same file stem; 16-bit PNG/TIFF
  (value x ``depth_scale`` = mm, copied) or float TIFF / ``.npy`` (value x ``depth_scale`` = mm,
  re-encoded as 16-bit PNG in 0.1 mm or 1 mm units).
- **meshes**: files or folders (searched recursively) in any format trimesh reads (PLY, OBJ,
  OFF, STL, GLB/glTF), in ``mesh_units`` (mm, cm, m, in). An object's *name* is its file stem, or
  the name of its folder when the mesh is the only one in a subfolder of a ``--meshes`` folder
  (MegaPose's ``meshes/LABEL/anything.ply``). Objects get ids 1..N in natural order of their
  names; ``models/models_names.json`` maps id -> name.
- **boxes** (optional, one file per ``--images``): a JSON list of ``{"label", "bbox_modal":
  [x1, y1, x2, y2]}`` (MegaPose ``object_data.json``; the folder's one image), or an object keyed
  by image file name (or stem) whose values are such lists. Labels are object names (or obj ids);
  the box may instead be ``bbox_xyxy`` ([x1, y1, x2, y2]) or ``bbox`` / ``bbox_xywh`` ([x, y, w,
  h], as BOP and COCO); ``score`` is optional (1). Written as ``detections.json`` (BOP detections,
  what ``cosy estimate --detections`` and ``cosy detect --from-json`` read).

Outputs (lengths in mm)
-----------------------
``camera.json``, ``models/obj_XXXXXX.ply`` (binary PLY: x y z nx ny nz, vertex colours or
``texture_u texture_v`` with ``comment TextureFile obj_XXXXXX.png``), ``models/models_info.json``
(diameter, extents, and the symmetries proposed by ``cosy symmetries``' detector, marked
``"symmetries_proposed": true``: they are geometric, a texture may break them — review them),
``models/models_names.json``, ``SPLIT/SCENE_ID/{rgb,depth}/``, ``scene_camera.json``,
``image_names.json``, ``detections.json`` (with boxes) and ``new_dataset.json`` (sources,
settings, timings). The whole folder is written atomically.

A BOP dataset has one camera (``camera.json``): all images must have the same size. Per-image K
(``scene_camera.json``) may differ.
"""

from __future__ import annotations

import difflib
import json
import re
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ..conf import merge_conf
from ..errors import CosyError, warn
from ..io import atomic, bop, images
from ..io.atomic import write_json

CONFS: dict[str, dict] = {
    "default": {
        "split": "test",
        "scene_id": 1,  # the first scene's id; one scene per images folder, consecutive ids
        "first_im_id": 0,  # BOP image id of each scene's first image
        "mesh_units": "mm",
        "depth_scale": None,  # mm per stored depth unit; required with depth
        "symmetries": True,  # propose symmetries (cosy symmetries' detector)
        "symmetry_tolerance_mm": None,  # None: 1 % of the diameter, clipped to [0.5, 2] mm
        "symmetry_points": 1000,
        "seed": 0,
    },
}
MESH_UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")
DEPTH_SUFFIXES = (".png", ".tif", ".tiff", ".npy")
MESH_SUFFIXES = (".ply", ".obj", ".off", ".stl", ".glb", ".gltf", ".dae", ".3mf")
FOLDER_CAMERA_FILES = ("camera_data.json", "camera.json", "intrinsics.json", "K.json")
BOX_OVERHANG_PX = 4.0  # a box may leave the image by this much (clipped); more is refused
PLAUSIBLE_DIAMETER_MM = (5.0, 5000.0)  # outside: a warning about --mesh-units


def resolve_conf(conf: str | dict | None = None, **overrides) -> dict:
    c = merge_conf(CONFS, conf, overrides, default="default", what="new-dataset")
    if c["mesh_units"] not in MESH_UNITS_MM:
        raise CosyError(f"mesh units: expected one of {', '.join(MESH_UNITS_MM)}, got {c['mesh_units']!r}")
    if c["depth_scale"] is not None and not (float(c["depth_scale"]) > 0):
        raise CosyError(f"--depth-scale must be > 0 (mm per depth unit), got {c['depth_scale']}")
    if int(c["scene_id"]) < 0 or int(c["first_im_id"]) < 0:
        raise CosyError("scene and image ids must be >= 0")
    if not re.fullmatch(r"[A-Za-z0-9_\-]+", str(c["split"])) or str(c["split"]).startswith("models"):
        raise CosyError(f"split name {c['split']!r}: expected a folder name such as test, val, train")
    if c["symmetry_tolerance_mm"] is not None and not float(c["symmetry_tolerance_mm"]) > 0:
        raise CosyError(f"symmetry tolerance must be > 0 mm, got {c['symmetry_tolerance_mm']}")
    return c


# --------------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------------
def natural_key(s: str) -> list:
    """Sort key: digit runs compare as numbers ('img2' < 'img10')."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", s)]


def _load_json(path: Path, what: str) -> Any:
    if not path.is_file():
        raise CosyError(f"{what} file not found", path=path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CosyError(f"not valid JSON ({e})", path=path) from None


def _as_number_array(v: Any, n: int | None = None) -> np.ndarray | None:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    if a.dtype == object or (n is not None and a.size != n) or not np.isfinite(a).all():
        return None
    return a if n is None else a.reshape(-1)


# --------------------------------------------------------------------------------------------
# intrinsics
# --------------------------------------------------------------------------------------------
K_FORMS = ("a 3x3 list", '{"cam_K": [9 numbers]}', '{"fx", "fy", "cx", "cy"}', '{"K": 3x3, "resolution": [h, w]}',
           "or an object keyed by image file name with one of these per image")


def _is_k_spec(v: Any) -> bool:
    if isinstance(v, dict):
        return bool({"K", "cam_K", "fx", "camera_matrix"} & set(v))
    return _as_number_array(v, 9) is not None


def parse_intrinsics(spec: Any, path: Path, where: str | None = None) -> tuple[np.ndarray, tuple[int, int] | None]:
    """One camera's K (3, 3) px and its image size (width, height) when the spec states one.

    ``spec``: a 3x3 list / 9 numbers, ``{"cam_K"}``, ``{"fx", "fy", "cx", "cy"[, "width", "height"]}``
    or ``{"K"[, "resolution": [h, w]]}`` (also ``"camera_matrix"``)."""
    size = None
    if isinstance(spec, dict):
        if "resolution" in spec:
            r = _as_number_array(spec["resolution"], 2)
            if r is None:
                raise CosyError(f"resolution: expected [height, width], got {spec['resolution']!r:.60}", path=path,
                                where=where)
            size = (int(r[1]), int(r[0]))
        elif "width" in spec and "height" in spec:
            w, h = _as_number_array(spec["width"], 1), _as_number_array(spec["height"], 1)
            if w is None or h is None:
                raise CosyError("width/height: expected numbers", path=path, where=where)
            size = (int(w[0]), int(h[0]))
        for key in ("K", "cam_K", "camera_matrix"):
            if key in spec:
                v = spec[key]
                if isinstance(v, dict) and "data" in v:  # OpenCV FileStorage style
                    v = v["data"]
                K = _as_number_array(v, 9)
                if K is None:
                    raise CosyError(f"{key}: expected 9 numbers (3x3, row-major), got {v!r:.80}", path=path,
                                    where=where)
                return K.reshape(3, 3), size
        if all(k in spec for k in ("fx", "fy", "cx", "cy")):
            vals = [_as_number_array(spec[k], 1) for k in ("fx", "fy", "cx", "cy")]
            if any(v is None for v in vals):
                raise CosyError("fx, fy, cx, cy: expected numbers", path=path, where=where)
            fx, fy, cx, cy = (float(v[0]) for v in vals)
            return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), size
        raise CosyError(f"no intrinsics found (keys {sorted(spec)[:8]}); expected {', '.join(K_FORMS)}", path=path,
                        where=where)
    K = _as_number_array(spec, 9)
    if K is None:
        raise CosyError(f"expected intrinsics: {', '.join(K_FORMS)}; got {json.dumps(spec)[:80]}", path=path,
                        where=where)
    return K.reshape(3, 3), size


def check_intrinsics(K: np.ndarray, size: tuple[int, int], stated: tuple[int, int] | None, k_path: Path,
                     image_path: Path) -> None:
    """K must be an upper-triangular pinhole matrix with fx, fy > 0 whose principal point lies in
    the image; a stated resolution must be the image's."""
    w, h = size
    if stated is not None and tuple(stated) != (w, h):
        if tuple(stated) == (h, w):
            msg = f"is for {stated[0]}x{stated[1]} images but {image_path.name} is {w}x{h} (rotated?)"
        else:
            msg = f"is for {stated[0]}x{stated[1]} images but {image_path.name} is {w}x{h} px"
        raise CosyError(f"the camera {msg}", path=k_path)
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise CosyError(f"fx and fy must be > 0 px, got fx={K[0, 0]:g}, fy={K[1, 1]:g}", path=k_path)
    if abs(K[1, 0]) > 1e-9 or abs(K[2, 0]) > 1e-9 or abs(K[2, 1]) > 1e-9 or abs(K[2, 2] - 1) > 1e-6:
        raise CosyError(f"K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.round(4).tolist()}", path=k_path)
    cx, cy = K[0, 2], K[1, 2]
    if not (0 <= cx <= w and 0 <= cy <= h):
        raise CosyError(f"principal point ({cx:g}, {cy:g}) px is outside the {w}x{h} image {image_path.name} "
                        "(expected 0 <= cx <= width, 0 <= cy <= height: is K for another resolution, or "
                        "normalised?)", path=k_path)


class IntrinsicsSource:
    """Finds each image's K (see the module docstring for the order)."""

    def __init__(self, intrinsics: Path | None, folder: Path | None):
        self.path = intrinsics
        self.single: tuple[np.ndarray, tuple | None] | None = None
        self.per_name: dict[str, Any] = {}
        self.folder_file: Path | None = None
        if intrinsics is not None:
            data = _load_json(intrinsics, "intrinsics")
            if isinstance(data, dict) and not _is_k_spec(data) and data \
                    and all(isinstance(v, (dict, list)) for v in data.values()):
                self.per_name = dict(data)  # keyed by image file name or stem
                if not self.per_name:
                    raise CosyError(f"empty object: expected {', '.join(K_FORMS)}", path=intrinsics)
            else:
                self.single = parse_intrinsics(data, intrinsics)
        self.folder_K: tuple[np.ndarray, tuple | None] | None = None
        if folder is not None and self.single is None and not self.per_name:
            self.folder_file = next((folder / n for n in FOLDER_CAMERA_FILES if (folder / n).is_file()), None)
        self.used_names: set[str] = set()

    def for_image(self, image: Path) -> tuple[np.ndarray, tuple | None, Path, str]:
        """(K, stated size or None, the file it came from, a short description)."""
        for key in (image.name, image.stem):
            if key in self.per_name:
                self.used_names.add(key)
                K, size = parse_intrinsics(self.per_name[key], self.path, where=key)
                return K, size, self.path, f"{self.path.name}[{key}]"
        own = image.with_suffix(".json")
        if own.is_file() and own != self.path:
            K, size = parse_intrinsics(_load_json(own, "intrinsics"), own)
            return K, size, own, own.name
        if self.single is not None:
            return self.single[0], self.single[1], self.path, self.path.name
        if self.folder_file is not None:
            if self.folder_K is None:
                self.folder_K = parse_intrinsics(_load_json(self.folder_file, "intrinsics"), self.folder_file)
            return self.folder_K[0], self.folder_K[1], self.folder_file, self.folder_file.name
        if self.per_name:
            raise CosyError(f"no entry for image {image.name} (keys are image file names or stems; has "
                            f"{', '.join(sorted(self.per_name)[:6])}{' ...' if len(self.per_name) > 6 else ''})",
                            path=self.path)
        raise CosyError(f"no intrinsics for this image: give --intrinsics K.json, or put {own.name} next to it, or "
                        f"{' / '.join(FOLDER_CAMERA_FILES)} in its folder", path=image)


# --------------------------------------------------------------------------------------------
# images and depth
# --------------------------------------------------------------------------------------------
@dataclass
class SourceImage:
    path: Path
    im_id: int
    width: int
    height: int
    K: np.ndarray
    K_source: str
    reencode: bool = False  # True: decode (orientation applied) and write PNG
    depth_path: Path | None = None


def list_images(src: Path) -> tuple[Path, list[Path]]:
    """(the folder, its image files in natural order) of an images folder or one image file."""
    if src.is_file():
        if src.suffix.lower() not in IMAGE_SUFFIXES:
            raise CosyError(f"not an image file (expected {', '.join(IMAGE_SUFFIXES)})", path=src)
        return src.parent, [src]
    if not src.is_dir():
        raise CosyError("images folder (or image file) not found", path=src)
    files = [p for p in src.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
             and not p.name.startswith(".")]
    if not files:
        raise CosyError(f"no images here (expected {', '.join(IMAGE_SUFFIXES)} files; subfolders are not searched)",
                        path=src)
    return src, sorted(files, key=lambda p: natural_key(p.name))


def _image_size(path: Path) -> tuple[tuple[int, int], bool]:
    """((width, height) as cosy will read the image, whether it must be re-encoded)."""
    import cv2

    suffix = path.suffix.lower()
    if suffix == ".png":
        return images.image_size(path), False
    if suffix in (".jpg", ".jpeg"):
        data = np.fromfile(str(path), dtype=np.uint8)
        oriented = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
        raw = cv2.imdecode(data, cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION) if data.size else None
        if oriented is None or raw is None:
            raise CosyError("unreadable image (not a valid jpg)", path=path)
        return (oriented.shape[1], oriented.shape[0]), oriented.shape != raw.shape
    img = images.read_rgb(path)
    return (img.shape[1], img.shape[0]), True


def _find_depth(folder: Path, stem: str) -> Path | None:
    for suf in DEPTH_SUFFIXES:
        for s in (suf, suf.upper()):
            p = folder / f"{stem}{s}"
            if p.is_file():
                return p
    return None


def _read_depth_raw(path: Path) -> np.ndarray:
    import cv2

    if path.suffix.lower() == ".npy":
        try:
            d = np.load(path, allow_pickle=False)
        except Exception as e:
            raise CosyError(f"cannot read depth array ({type(e).__name__}: {e})", path=path) from None
    else:
        data = np.fromfile(str(path), dtype=np.uint8)
        d = cv2.imdecode(data, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_UNCHANGED) if data.size else None
        if d is None:
            raise CosyError("unreadable depth image", path=path)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[..., 0]
    if d.ndim != 2:
        raise CosyError(f"depth must have one channel, got shape {d.shape}", path=path)
    if d.dtype not in (np.uint16, np.float32, np.float64, np.int32, np.uint32):
        raise CosyError(f"depth must be 16-bit integers (png/tif) or floats (tif/npy), got {d.dtype}", path=path)
    return d


def write_depth(src: Path, dst: Path, depth_scale: float) -> float:
    """Copy (16-bit PNG) or convert one depth image to a BOP 16-bit PNG; returns its depth_scale
    (mm per unit)."""
    if src.suffix.lower() == ".png":
        d = _read_depth_raw(src)
        if d.dtype == np.uint16:
            shutil.copyfile(src, dst)
            return depth_scale
    else:
        d = _read_depth_raw(src)
    mm = d.astype(np.float64) * depth_scale
    mm[~np.isfinite(mm) | (mm < 0)] = 0.0
    top = float(mm.max(initial=0.0))
    if d.dtype == np.uint16:
        out_scale = depth_scale
    else:
        out_scale = 0.1 if top < 6553.0 else 1.0
    if top / out_scale > 65535:
        raise CosyError(f"depth reaches {top:.0f} mm: does not fit a 16-bit PNG in 1 mm units (wrong --depth-scale?)",
                        path=src)
    images.write_depth(dst, mm, out_scale)
    return out_scale


# --------------------------------------------------------------------------------------------
# meshes
# --------------------------------------------------------------------------------------------
@dataclass
class MeshSource:
    name: str
    path: Path
    obj_id: int = 0


def collect_meshes(sources: Sequence[Path]) -> list[MeshSource]:
    """Mesh files of ``sources`` (files, or folders searched recursively) with their object
    names, sorted by name (natural order) and numbered 1..N."""
    found: list[MeshSource] = []
    for src in sources:
        src = Path(src)
        if src.is_file():
            if src.suffix.lower() not in MESH_SUFFIXES:
                raise CosyError(f"not a mesh file (expected {', '.join(MESH_SUFFIXES)})", path=src)
            found.append(MeshSource(src.stem, src))
            continue
        if not src.is_dir():
            raise CosyError("meshes folder (or mesh file) not found", path=src)
        files = sorted((p for p in src.rglob("*") if p.is_file() and p.suffix.lower() in MESH_SUFFIXES
                        and not any(part.startswith(".") for part in p.relative_to(src).parts)),
                       key=lambda p: natural_key(str(p)))
        if not files:
            raise CosyError(f"no mesh files here or below (expected {', '.join(MESH_SUFFIXES)})", path=src)
        per_folder: dict[Path, int] = {}
        for f in files:
            per_folder[f.parent] = per_folder.get(f.parent, 0) + 1
        for f in files:
            alone_in_subfolder = f.parent != src and per_folder[f.parent] == 1
            found.append(MeshSource(f.parent.name if alone_in_subfolder else f.stem, f))
    by_name: dict[str, MeshSource] = {}
    for m in found:
        if m.name in by_name and by_name[m.name].path.resolve() != m.path.resolve():
            raise CosyError(f"two meshes are named {m.name!r}: {by_name[m.name].path} and {m.path} (object names "
                            "come from file stems, or from the folder of a mesh alone in a subfolder)")
        by_name[m.name] = m
    out = sorted(by_name.values(), key=lambda m: natural_key(m.name))
    for i, m in enumerate(out, start=1):
        m.obj_id = i
    return out


def mesh_appearance(mesh) -> str:
    """'texture', 'vertex colours', 'face colours', 'material colour' or 'none'."""
    v = mesh.visual
    if v.kind == "texture":
        img = getattr(getattr(v, "material", None), "image", None)
        if img is not None and v.uv is not None and len(v.uv) == len(mesh.vertices):
            return "texture"
        return "material colour"
    if v.kind == "vertex":
        return "vertex colours"
    if v.kind == "face":
        return "face colours"
    return "none"


def write_ply(path: Path, mesh, *, texture_name: str | None = None, comments: Sequence[str] = ()) -> str:
    """Write a trimesh mesh (mm) as a binary BOP PLY: x y z nx ny nz, then ``red green blue alpha``
    (vertex, face or material colours) or ``texture_u texture_v`` (+ ``comment TextureFile``,
    the texture image written next to it as ``texture_name``). Returns the appearance kept."""
    kind = mesh_appearance(mesh)
    if kind == "face colours":  # BOP PLYs carry vertex colours only: one vertex per face corner
        mesh = mesh.copy()
        mesh.unmerge_vertices()
        fc = np.asarray(mesh.visual.face_colors)
        colors = np.repeat(fc, 3, axis=0)[np.argsort(mesh.faces.reshape(-1), kind="stable")]
        colors = np.asarray(colors)
    elif kind == "vertex colours":
        colors = np.asarray(mesh.visual.vertex_colors)
    elif kind == "material colour":
        main = np.asarray(getattr(mesh.visual.material, "main_color", [102, 102, 102, 255]), dtype=np.uint8)
        colors = np.tile(main.reshape(1, -1)[:, :4], (len(mesh.vertices), 1))
    else:
        colors = None
    V = np.asarray(mesh.vertices, dtype=np.float32)
    N = np.asarray(mesh.vertex_normals, dtype=np.float32)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if kind == "texture":
        fields += [("texture_u", "<f4"), ("texture_v", "<f4")]
    elif colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1"), ("alpha", "u1")]
    vert = np.zeros(len(V), dtype=fields)
    for i, a in enumerate("xyz"):
        vert[a] = V[:, i]
        vert["n" + a] = N[:, i]
    if kind == "texture":
        uv = np.asarray(mesh.visual.uv, dtype=np.float32)
        vert["texture_u"], vert["texture_v"] = uv[:, 0], uv[:, 1]
    elif colors is not None:
        for i, c in enumerate(("red", "green", "blue", "alpha")):
            vert[c] = colors[:, i] if colors.shape[1] > i else 255
    F = np.asarray(mesh.faces)
    face = np.zeros(len(F), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face["n"] = 3
    face["v"] = F
    header = ["ply", "format binary_little_endian 1.0"]
    header += [f"comment {c}" for c in comments]
    if kind == "texture":
        header.append(f"comment TextureFile {texture_name}")
    header.append(f"element vertex {len(V)}")
    header += [f"property {'float' if t == '<f4' else 'uchar'} {n}" for n, t in fields]
    header += [f"element face {len(F)}", "property list uchar int vertex_indices", "end_header"]
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(vert.tobytes())
        f.write(face.tobytes())
    if kind == "texture":
        img = mesh.visual.material.image
        if img.mode not in ("RGB", "RGBA", "L"):
            img = img.convert("RGBA" if "A" in img.mode else "RGB")
        img.save(path.with_name(texture_name), format="PNG", compress_level=1)
    return kind


# --------------------------------------------------------------------------------------------
# boxes
# --------------------------------------------------------------------------------------------
BOX_XYXY_KEYS = ("bbox_modal", "bbox_xyxy", "xyxy")
BOX_XYWH_KEYS = ("bbox", "bbox_xywh", "xywh")
LABEL_KEYS = ("label", "name", "object", "obj_id", "category_id")


def read_boxes(path: Path, scene_id: int, scene_images: list[SourceImage], name_to_id: dict[str, int]) -> list[dict]:
    """Detection rows {scene_id, im_id, obj_id, score, x, y, w, h, time} from a boxes file (see
    the module docstring), checked against the images and the object names."""
    data = _load_json(path, "boxes")
    by_key = {}
    for im in scene_images:
        by_key[im.path.name] = im
        by_key.setdefault(im.path.stem, im)
    if isinstance(data, list):
        if len(scene_images) != 1:
            raise CosyError(f"a list of boxes is for a folder with one image; these images are "
                            f"{len(scene_images)}: key the boxes by image file name, {{\"{scene_images[0].path.name}\": "
                            "[{\"label\": ..., \"bbox_modal\": [x1, y1, x2, y2]}], ...}", path=path)
        groups = [(scene_images[0], data, "")]
    elif isinstance(data, dict):
        groups = []
        for key, lst in data.items():
            if key not in by_key:
                raise CosyError(f"{key!r} is not one of the images ({', '.join(sorted(by_key)[:6])}...)", path=path)
            if not isinstance(lst, list):
                raise CosyError(f"expected a list of boxes, got {type(lst).__name__}", path=path, where=key)
            groups.append((by_key[key], lst, f"{key}: "))
    else:
        raise CosyError("expected a JSON list of {\"label\", \"bbox_modal\": [x1, y1, x2, y2]} (or an object keyed "
                        "by image file name)", path=path)
    ids = set(name_to_id.values())
    rows = []
    for im, lst, prefix in groups:
        for i, b in enumerate(lst):
            where = f"{prefix}box {i}"
            if not isinstance(b, dict):
                raise CosyError(f"expected an object {{label, bbox_modal}}, got {type(b).__name__}", path=path,
                                where=where)
            label_key = next((k for k in LABEL_KEYS if k in b), None)
            if label_key is None:
                raise CosyError(f"no label (expected one of {', '.join(LABEL_KEYS)})", path=path, where=where)
            label = b[label_key]
            if isinstance(label, str) and label in name_to_id:
                obj_id = name_to_id[label]
            elif isinstance(label, int) and not isinstance(label, bool) and label in ids:
                obj_id = int(label)
            else:
                close = difflib.get_close_matches(str(label), list(name_to_id), n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise CosyError(f"label {label!r} is not an object name{hint}; objects: "
                                f"{', '.join(list(name_to_id)[:10])}{' ...' if len(name_to_id) > 10 else ''}",
                                path=path, where=where)
            xyxy_key = next((k for k in BOX_XYXY_KEYS if k in b), None)
            xywh_key = next((k for k in BOX_XYWH_KEYS if k in b), None)
            key = xyxy_key or xywh_key
            if key is None:
                raise CosyError(f"no box (expected {' or '.join(BOX_XYXY_KEYS)} [x1, y1, x2, y2], or "
                                f"{' or '.join(BOX_XYWH_KEYS)} [x, y, w, h] px)", path=path, where=where)
            box = _as_number_array(b[key], 4)
            if box is None:
                raise CosyError(f"{key}: expected 4 numbers (px), got {b[key]!r:.60}", path=path, where=where)
            x1, y1 = box[0], box[1]
            x2, y2 = (box[2], box[3]) if xyxy_key else (box[0] + box[2], box[1] + box[3])
            if not (x2 > x1 and y2 > y1):
                form = "[x1, y1, x2, y2] with x2 > x1, y2 > y1" if xyxy_key else "[x, y, w, h] with w, h > 0"
                raise CosyError(f"{key} {box.tolist()}: expected {form}", path=path, where=where)
            W, H, o = im.width, im.height, BOX_OVERHANG_PX
            if x1 < -o or y1 < -o or x2 > W + o or y2 > H + o:
                raise CosyError(f"{key} {box.tolist()} leaves the {W}x{H} image {im.path.name} by more than {o:g} px",
                                path=path, where=where)
            x1, x2 = np.clip([x1, x2], 0, W)
            y1, y2 = np.clip([y1, y2], 0, H)
            score = b.get("score", 1.0)
            sc = _as_number_array(score, 1)
            if sc is None:
                raise CosyError(f"score: expected a number, got {score!r:.40}", path=path, where=where)
            rows.append({"scene_id": scene_id, "im_id": im.im_id, "obj_id": obj_id, "score": float(sc[0]),
                         "x": float(x1), "y": float(y1), "w": float(x2 - x1), "h": float(y2 - y1), "time": -1.0})
    return rows


# --------------------------------------------------------------------------------------------
# the stage
# --------------------------------------------------------------------------------------------
@dataclass
class _Scene:
    scene_id: int
    source: Path
    folder: Path
    images: list[SourceImage] = field(default_factory=list)
    boxes: Path | None = None
    depth: Path | None = None


def _per_scene(values: Sequence | None, n: int, option: str, allow_one: bool) -> list:
    values = list(values or [])
    if not values:
        return [None] * n
    if len(values) == n:
        return values
    if len(values) == 1 and allow_one:
        return values * n
    raise CosyError(f"{option} given {len(values)} times for {n} --images: give it once per --images, in the same "
                    f"order{' (or once for all)' if allow_one else ''}")


def main(conf: str | dict | None, images_src: Sequence[str | Path], meshes: Sequence[str | Path], out: str | Path,
         overwrite: bool = False, *, intrinsics: Sequence[str | Path] | None = None,
         depth: Sequence[str | Path] | None = None, boxes: Sequence[str | Path] | None = None,
         log: Callable[[str], None] = print, progress: bool = True) -> dict:
    """Write the BOP dataset ``out`` from images folders (one scene each), intrinsics, meshes and
    optional depth folders and box files (``intrinsics``: none, one, or one per images folder;
    ``depth`` and ``boxes``: none or one per images folder). Returns the summary written to
    ``new_dataset.json`` (objects, scenes, timings in s)."""
    from ..console import progress as progress_bar

    t_all = time.perf_counter()
    timings: dict[str, float] = {}
    c = resolve_conf(conf)
    out = Path(out)
    if out.exists() and not overwrite:
        raise CosyError("output exists (use --overwrite to replace it)", path=out)
    if out.exists() and not out.is_dir():
        raise CosyError("output exists and is not a folder", path=out)
    if not images_src:
        raise CosyError("give at least one --images folder")
    if not meshes:
        raise CosyError("give the objects' meshes (--meshes DIR or files)")
    n = len(images_src)
    k_files = _per_scene(intrinsics, n, "--intrinsics", allow_one=True)
    d_dirs = _per_scene(depth, n, "--depth", allow_one=False)
    b_files = _per_scene(boxes, n, "--boxes", allow_one=False)
    if any(d is not None for d in d_dirs) and c["depth_scale"] is None:
        raise CosyError("--depth needs --depth-scale: millimetres per stored depth unit (1 for depth in mm, 0.1 for "
                        "0.1 mm units, 1000 for float depth in metres)")
    depth_scale = float(c["depth_scale"]) if c["depth_scale"] is not None else 1.0

    # ---- images, intrinsics, depth: checked before anything is written
    t0 = time.perf_counter()
    scenes: list[_Scene] = []
    for i, (src, kf, dd, bf) in enumerate(zip(images_src, k_files, d_dirs, b_files)):
        src = Path(src)
        folder, files = list_images(src)
        sc = _Scene(int(c["scene_id"]) + i, src, folder, boxes=None if bf is None else Path(bf),
                    depth=None if dd is None else Path(dd))
        ks = IntrinsicsSource(None if kf is None else Path(kf), folder)
        if sc.depth is not None and not sc.depth.is_dir():
            raise CosyError("depth folder not found", path=sc.depth)
        for j, f in enumerate(files):
            (w, h), reencode = _image_size(f)
            K, stated, k_path, k_desc = ks.for_image(f)
            check_intrinsics(K, (w, h), stated, k_path, f)
            im = SourceImage(f, int(c["first_im_id"]) + j, w, h, K, k_desc, reencode)
            if sc.depth is not None:
                dp = _find_depth(sc.depth, f.stem)
                if dp is None:
                    raise CosyError(f"no depth image for {f.name} (expected {f.stem}.png/.tif/.npy)", path=sc.depth)
                if dp.suffix.lower() == ".png":
                    dw, dh = images.image_size(dp)
                else:
                    dr = _read_depth_raw(dp)
                    dw, dh = dr.shape[1], dr.shape[0]
                if (dw, dh) != (w, h):
                    raise CosyError(f"depth is {dw}x{dh} px but its image {f.name} is {w}x{h} px (expected the same "
                                    "size: depth registered to the colour camera)", path=dp)
                im.depth_path = dp
            sc.images.append(im)
        if ks.per_name:
            unused = sorted(set(ks.per_name) - ks.used_names)
            if unused and len(unused) == len(ks.per_name):
                raise CosyError(f"none of its keys ({', '.join(unused[:4])}...) names an image of {folder}", path=kf)
        scenes.append(sc)
    sizes = {(im.width, im.height): (sc, im) for sc in scenes for im in sc.images}
    if len(sizes) > 1:
        (a, (sa, ia)), (b, (sb, ib)) = list(sizes.items())[:2]
        raise CosyError(f"images have different sizes ({a[0]}x{a[1]}: {ia.path}; {b[0]}x{b[1]}: {ib.path}): a BOP "
                        "dataset has one camera (camera.json); make one dataset per camera")
    timings["check_images_s"] = time.perf_counter() - t0

    # ---- meshes
    mesh_list = collect_meshes([Path(m) for m in meshes])
    name_to_id = {m.name: m.obj_id for m in mesh_list}

    # ---- boxes (read before writing anything: a wrong label fails fast)
    det_rows: list[dict] = []
    for sc in scenes:
        if sc.boxes is not None:
            det_rows += read_boxes(sc.boxes, sc.scene_id, sc.images, name_to_id)

    from ..objects.database import load_mesh, model_info_from_mesh

    scale = MESH_UNITS_MM[c["mesh_units"]]
    objects_doc = []
    with atomic.atomic_dir(out, overwrite=overwrite) as tmp:
        models_dir = tmp / "models"
        models_dir.mkdir()
        infos: dict[int, bop.ModelInfo] = {}
        t_mesh = t_sym = 0.0
        for m in progress_bar(mesh_list, desc="meshes", unit="mesh", enabled=progress and len(mesh_list) >= 2):
            t0 = time.perf_counter()
            mesh = load_mesh(m.path)
            if scale != 1.0:
                mesh.apply_scale(scale)
            label = f"obj_{m.obj_id:06d}"
            kind = write_ply(models_dir / f"{label}.ply", mesh, texture_name=f"{label}.png",
                             comments=[f"cosy new-dataset: {m.name} from {m.path.name} ({c['mesh_units']} -> mm)"])
            info = model_info_from_mesh(mesh)
            lo, hi = PLAUSIBLE_DIAMETER_MM
            if not lo <= info.diameter <= hi:
                guess = min(MESH_UNITS_MM, key=lambda u: abs(np.log(info.diameter / scale * MESH_UNITS_MM[u] / 150.0)))
                warn(f"object {m.name} is {info.diameter:.3g} mm across with --mesh-units {c['mesh_units']}: "
                     f"are the units right? (--mesh-units {guess} would make it "
                     f"{info.diameter / scale * MESH_UNITS_MM[guess]:.3g} mm)", path=m.path)
            t_mesh += time.perf_counter() - t0
            sym_doc = None
            if c["symmetries"]:
                from ..objects.detect_symmetries import default_tolerance, detect_symmetries

                t0 = time.perf_counter()
                tol = c["symmetry_tolerance_mm"] or default_tolerance(info.diameter)
                try:
                    prop = detect_symmetries(mesh, tol, diameter_mm=info.diameter, n_points=int(c["symmetry_points"]),
                                             seed=int(c["seed"]))
                except ValueError as e:
                    raise CosyError(f"cannot analyse the mesh's symmetries: {e} (--no-symmetries skips this)",
                                    path=m.path) from None
                info.symmetries_discrete = prop.symmetries_discrete
                info.symmetries_continuous = [dict(x) for x in prop.symmetries_continuous]
                info.extra["symmetries_proposed"] = True
                dt = time.perf_counter() - t0
                t_sym += dt
                sym_doc = {"discrete": len(prop.symmetries_discrete), "continuous": len(prop.symmetries_continuous),
                           "tolerance_mm": round(float(tol), 4), "seconds": round(dt, 3)}
            infos[m.obj_id] = info
            objects_doc.append({"obj_id": m.obj_id, "name": m.name, "source": str(m.path.resolve()),
                                "units": c["mesh_units"], "appearance": kind, "vertices": int(len(mesh.vertices)),
                                "faces": int(len(mesh.faces)), "diameter_mm": round(float(info.diameter), 3),
                                "size_mm": [round(float(s), 3) for s in info.size_xyz], "symmetries": sym_doc})
        bop.write_models_info(models_dir / "models_info.json", infos)
        write_json(models_dir / "models_names.json", {str(m.obj_id): m.name for m in mesh_list})
        timings["meshes_s"] = t_mesh
        timings["symmetries_s"] = t_sym

        # ---- scenes
        t0 = time.perf_counter()
        first = scenes[0].images[0]
        scenes_doc = []
        n_images = sum(len(sc.images) for sc in scenes)
        bar = progress_bar(total=n_images, desc="images", unit="img", enabled=progress and n_images >= 20)
        for sc in scenes:
            sdir = tmp / c["split"] / f"{sc.scene_id:06d}"
            (sdir / "rgb").mkdir(parents=True)
            if sc.depth is not None:
                (sdir / "depth").mkdir()
            cams = {}
            for im in sc.images:
                suffix = im.path.suffix.lower()
                if im.reencode or suffix not in (".png", ".jpg", ".jpeg"):
                    images.write_rgb(sdir / "rgb" / f"{im.im_id:06d}.png", images.read_rgb(im.path))
                else:
                    shutil.copyfile(im.path, sdir / "rgb" / f"{im.im_id:06d}{'.jpg' if suffix == '.jpeg' else suffix}")
                ds_im = 1.0
                if im.depth_path is not None:
                    ds_im = write_depth(im.depth_path, sdir / "depth" / f"{im.im_id:06d}.png", depth_scale)
                cams[im.im_id] = bop.SceneCamera(K=im.K, depth_scale=ds_im)
                bar.update(1)
            bop.write_scene_camera(sdir / "scene_camera.json", cams)
            write_json(sdir / "image_names.json", {str(im.im_id): im.path.name for im in sc.images})
            scenes_doc.append({"scene_id": sc.scene_id, "images": str(sc.folder.resolve()),
                               "depth": None if sc.depth is None else str(sc.depth.resolve()),
                               "boxes": None if sc.boxes is None else str(sc.boxes.resolve()),
                               "n_images": len(sc.images),
                               "intrinsics": sorted({im.K_source for im in sc.images})})
        bar.close()
        first_ds = 1.0
        if scenes[0].depth is not None:
            first_ds = bop.read_scene_camera(tmp / c["split"] / f"{scenes[0].scene_id:06d}" / "scene_camera.json")[
                first.im_id].depth_scale
        bop.write_camera(tmp / "camera.json", bop.CameraInfo(K=first.K, width=first.width, height=first.height,
                                                             depth_scale=first_ds))
        timings["images_s"] = time.perf_counter() - t0

        if det_rows:
            import pandas as pd

            bop.write_detections(tmp / "detections.json", pd.DataFrame(det_rows))
        timings["total_s"] = time.perf_counter() - t_all
        summary = {
            "command": "cosy new-dataset", "split": c["split"], "settings": {k: v for k, v in c.items()},
            "objects": objects_doc, "scenes": scenes_doc, "detections": len(det_rows),
            "timings_s": {k: round(v, 3) for k, v in timings.items()},
        }
        write_json(tmp / "new_dataset.json", summary)

    # ---- report
    log(f"new-dataset: wrote {out} ({len(mesh_list)} object(s), {len(scenes)} scene(s), {n_images} image(s)"
        f"{', depth' if any(sc.depth for sc in scenes) else ''}{f', {len(det_rows)} box(es)' if det_rows else ''}) "
        f"in {timings['total_s']:.1f} s")
    width = max(len(m.name) for m in mesh_list)
    log(f"  {'obj_id':>6}  {'name':<{width}}  {'diameter mm':>11}  {'symmetries':<14}  appearance")
    for o in objects_doc:
        s = o["symmetries"]
        sym = "not proposed" if s is None else f"{s['discrete']} disc, {s['continuous']} cont"
        log(f"  {o['obj_id']:>6}  {o['name']:<{width}}  {o['diameter_mm']:>11.1f}  {sym:<14}  {o['appearance']}")
    log(f"  object ids: {out / 'models' / 'models_names.json'}; image ids: "
        f"{out / c['split'] / f'{scenes[0].scene_id:06d}' / 'image_names.json'}")
    if c["symmetries"]:
        log("  symmetries are proposed from the geometry alone (a texture may break them): review them with "
            f"`cosy symmetries --models {out / 'models'}`")
    else:
        log(f"  symmetries not proposed: `cosy symmetries --models {out / 'models'} --write` adds them")
    turned = [im.path.name for sc in scenes for im in sc.images
              if im.reencode and im.path.suffix.lower() in (".jpg", ".jpeg")]
    if turned:
        log(f"  {len(turned)} JPEG(s) turned by their EXIF orientation (e.g. {turned[0]}): written as PNG, upright "
            "(the intrinsics must be those of the upright image)")
    if det_rows:
        log(f"  boxes: {out / 'detections.json'} (`cosy estimate --dataset {out} --detections "
            f"{out / 'detections.json'} --out candidates.csv`)")
    return summary
