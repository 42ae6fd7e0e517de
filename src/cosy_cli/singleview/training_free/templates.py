"""Template retrieval: a training-free coarse pose from rendered views (LINEMOD-like gradients).

Building (``cosy templates``, :func:`build_templates`, :func:`main`). Each object is rendered once
per viewpoint: camera positions on a Fibonacci sphere (object frame), each camera at a fixed
distance ``render_distance`` (mm) looking at the object origin, which therefore lands on the
principal point. Viewpoints equivalent under a symmetry S of the object (d ~ R_S d) are dropped
greedily: a viewpoint is kept when no kept one lies within ``dedupe`` x the sphere spacing of its
orbit, so a continuous symmetry about z leaves one meridian. Measured with 600 viewpoints:
``dedupe`` = 0.5 (default) keeps 77 % of the viewpoints under a 2-fold symmetry, 40 % under the
4 of a box, and brings every view closer to a template than for an asymmetric object (mean 2.7 vs
3.2 deg); 0.7 keeps 51 % and 26 % with the asymmetric object's mean distance (retrieval on the
sample images: top-1 within 15 deg 0.70 vs 0.73 with 0.5, within noise). In-plane
rotations are not rendered: a camera turned by a about its optical axis sees the image turned by
a about the principal point, so the 2D features are rotated analytically (``inplane`` angles
2 pi k / inplane).

The descriptor of a render (a neutral-grey object lit by a headlight, on black: the silhouette
plus the creases between faces) is ``features`` points on strong image gradients, spread by
farthest-point sampling, each with its gradient orientation quantised to 8 bins over 0..180 deg
(bin b centred on b x 22.5 deg).
Per template (viewpoint v, in-plane angle a; index t = v * inplane + a) are stored:

- ``xy`` (T, F, 2): feature positions normalised to the template's object box (the bounding box
  of the rotated silhouette, edges at 0 and 1), ``bins`` (T, F) orientation bins;
- ``R`` (T, 3, 3): R_cam_obj of the template camera (object on its optical axis);
- ``origin`` (T, 2): where the object origin projects, in normalised box coordinates;
- ``box_size`` (T, 2): width, height of the object box in template pixels, seen with focal
  ``focal`` (px) at ``render_distance`` (mm): depth from box size z = d_r f_obs / f_r s_t / s_obs;
- ``depth_offset`` (T,): median depth of the visible surface minus the depth of the origin, mm;
- per object: ``directions`` (V, 3) the kept viewpoints, ``hull`` (P, 3) mm the vertices of the
  model's convex hull (their projections bound the silhouette), ``render_distance``, ``focal``.

Matching (:func:`match_templates`). Each detection box (x1, y1, x2, y2 px, pixel edges, BOP
``x2 = x + w``), enlarged by a margin, is resampled to a fixed grid (box side -> ``grid`` cells,
anisotropically: gradient directions are mapped back to the image's metric). Gradient
orientations (per pixel the colour channel of largest gradient) are quantised to 8 bins where the
gradient is strong, spread over a (2r+1)^2 neighbourhood (bitwise OR), and turned into 8 response
maps (cosine between a template orientation and the closest orientation present). Every template
of the object is scored at once, with one gather: the mean response at its features. The pose of
a template placed in a detection: the object origin goes to the normalised ``origin`` mapped into
the box; the rotation is R_ray @ R_template, R_ray turning the optical axis onto the ray through
that pixel (the template was seen on the axis); the distance along the ray comes from the ratio
of box sizes, then is corrected with the box of the projected hull at that pose (the off-axis
magnification, ~3 % of depth in a 640 x 480 image, is otherwise a bias). The box sides: the less
shrunk one (``depth_from="max"``), as a visible box loses a side to occlusion.

Limits: the box must be the whole object's. A detection cut by the image border or an occluded
object gives a box whose normalised coordinates do not match the template's.

Conventions: lengths in mm, poses ``T_cam_obj`` 4x4 (OpenCV camera), K (3, 3) px with the centre
of the top-left pixel at (0, 0).
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from ... import __version__
from ...conf import merge_conf
from ...errors import CosyError
from ...geometry.poses import invert, look_at, make_pose
from ...io import atomic
from ...io.cache import file_sha1

FORMAT = "cosy-templates"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
N_BINS = 8  # orientation bins over 0..180 deg
GREY = 0.7  # albedo of the neutral-grey renders

CONFS: dict[str, dict] = {
    "default": {
        "viewpoints": 600,        # directions on the Fibonacci sphere (before symmetry dedupe)
        "inplane": 36,            # in-plane rotations (10 deg steps)
        "crop": (128, 96),        # template render size (width, height) px
        "features": 64,           # gradient features per template
        "fill": 0.8,              # the object's bounding sphere spans this fraction of the smaller side
        "focal_px": 500.0,        # template camera focal (px); with fill it sets render_distance
        "min_gradient": 40.0,     # Sobel magnitude (grey levels 0..255) of a feature candidate
        "symmetry_steps": 64,     # steps of a continuous symmetry in the viewpoint dedupe
        "dedupe": 0.5,            # drop a viewpoint whose orbit is within this x the sphere spacing of a kept one
    },
}
CONFS["fast"] = {**CONFS["default"], "viewpoints": 300, "inplane": 24}


def resolve_conf(conf: str | Mapping | None = "default", **overrides) -> dict:
    """Full template settings: a named preset (or a dict over ``default``) with overrides (None ignored)."""
    c = merge_conf(CONFS, conf, overrides, default="default", what="templates")
    try:
        c["crop"] = parse_size(c["crop"])
        for k in ("viewpoints", "inplane", "features", "symmetry_steps"):
            c[k] = int(c[k])
        for k in ("fill", "focal_px", "min_gradient", "dedupe"):
            c[k] = float(c[k])
    except (TypeError, ValueError) as e:
        raise CosyError(f"bad templates setting: {e}") from None
    checks = {"viewpoints": c["viewpoints"] >= 1, "inplane": c["inplane"] >= 1, "features": c["features"] >= 4,
              "fill": 0 < c["fill"] <= 1, "focal_px": c["focal_px"] > 0, "min_gradient": c["min_gradient"] >= 0,
              "symmetry_steps": c["symmetry_steps"] >= 1, "crop": min(c["crop"]) >= 16, "dedupe": 0 <= c["dedupe"] <= 2}
    for k, ok in checks.items():
        if not ok:
            raise CosyError(f"templates setting {k} = {c[k]!r} is out of range")
    return c


def parse_size(size) -> tuple[int, int]:
    """(width, height) from "128x96" or a pair; ValueError otherwise."""
    if isinstance(size, str):
        parts = size.lower().replace("×", "x").split("x")
        if len(parts) != 2:
            raise ValueError(f"size {size!r} is not WIDTHxHEIGHT (e.g. 128x96)")
        size = parts
    w, h = (int(v) for v in size)
    return w, h


# ------------------------------------------------------------------------------------------
# viewpoints
# ------------------------------------------------------------------------------------------
def fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere (golden-angle spiral)."""
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = np.pi * (1.0 + 5.0 ** 0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def sphere_spacing(n: int) -> float:
    """Typical angle (radians) between neighbouring points of an n-point Fibonacci sphere."""
    return math.sqrt(4.0 * math.pi / n)


def dedupe_viewpoints(directions: np.ndarray, symmetries: np.ndarray, min_angle: float) -> np.ndarray:
    """Indices of the viewpoints kept (in order): d is dropped when a kept viewpoint lies within
    ``min_angle`` (radians) of its orbit {R_S d} under the symmetries (S, 3, 3) or (S, 4, 4)."""
    D = np.asarray(directions, dtype=np.float64)
    R = np.asarray(symmetries, dtype=np.float64)[:, :3, :3]
    if len(R) <= 1 or len(D) == 0:
        return np.arange(len(D))
    orbits = np.einsum("sij,nj->nsi", R, D)  # (N, S, 3)
    cos_min = math.cos(min_angle)
    kept = np.zeros(len(D), dtype=bool)
    kept_dirs = np.empty((len(D), 3))
    n_kept = 0
    for i in range(len(D)):  # greedy; one (S, n_kept) product per viewpoint
        if n_kept == 0 or (orbits[i] @ kept_dirs[:n_kept].T).max() < cos_min:
            kept[i] = True
            kept_dirs[n_kept] = D[i]
            n_kept += 1
    return np.flatnonzero(kept)


def rotation_z(angles: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotations about the camera's optical axis: image turned by +a about the principal point."""
    a = np.asarray(angles, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1], R[..., 2, 2] = c, -s, s, c, 1.0
    return R


# ------------------------------------------------------------------------------------------
# image gradients (shared by template building and matching)
# ------------------------------------------------------------------------------------------
def sobel(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """3x3 Sobel derivatives (gx, gy) of images (..., H, W), edges replicated."""
    p = np.pad(np.asarray(img, dtype=np.float32), [(0, 0)] * (img.ndim - 2) + [(1, 1), (1, 1)], mode="edge")
    dx = p[..., :, 2:] - p[..., :, :-2]  # (..., H+2, W)
    gx = dx[..., :-2, :] + 2.0 * dx[..., 1:-1, :] + dx[..., 2:, :]
    dy = p[..., 2:, :] - p[..., :-2, :]  # (..., H, W+2)
    gy = dy[..., :, :-2] + 2.0 * dy[..., :, 1:-1] + dy[..., :, 2:]
    return gx, gy


def orientation_bins(angle: np.ndarray) -> np.ndarray:
    """Gradient angles (radians, any range) -> bins 0..7 over 0..180 deg (orientation, sign
    ignored), bin b centred on b x 22.5 deg (horizontal and vertical edges fall mid-bin)."""
    return (np.rint(np.mod(angle, np.pi) * (N_BINS / np.pi)).astype(np.int64) % N_BINS).astype(np.uint8)


# ------------------------------------------------------------------------------------------
# templates of one object
# ------------------------------------------------------------------------------------------
@dataclass
class ObjectTemplates:
    """The templates of one object (see the module docstring for the arrays; T templates, F features)."""

    obj_id: int
    R: np.ndarray             # (T, 3, 3) float32 R_cam_obj of the template camera
    xy: np.ndarray            # (T, F, 2) float16 feature positions, normalised box coordinates
    bins: np.ndarray          # (T, F) uint8 orientation bins 0..7
    origin: np.ndarray        # (T, 2) float32 object-origin projection, normalised box coordinates
    box_size: np.ndarray      # (T, 2) float32 object box (w, h) px in the template render
    depth_offset: np.ndarray  # (T,) float32 mm: median visible depth - origin depth
    viewpoint: np.ndarray     # (T,) int32 index into directions
    inplane: np.ndarray       # (T,) int32 in-plane step k (angle 2 pi k / n_inplane)
    directions: np.ndarray    # (V, 3) float32 unit camera positions in the object frame (kept viewpoints)
    hull: np.ndarray          # (P, 3) float32 mm: vertices of the model's convex hull (silhouette extremes)
    render_distance: float    # mm, camera to object origin
    focal: float              # px, template camera (fx = fy)
    crop: tuple[int, int]     # (w, h) px of the renders
    n_inplane: int
    model_sha1: str = ""
    _index_cache: dict = field(default_factory=dict, repr=False)

    @property
    def n_templates(self) -> int:
        return len(self.R)

    @property
    def n_viewpoints(self) -> int:
        return len(self.directions)

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsics of the template renders (principal point at the crop centre)."""
        w, h = self.crop
        return np.array([[self.focal, 0.0, (w - 1) / 2], [0.0, self.focal, (h - 1) / 2], [0.0, 0.0, 1.0]])

    def T_cam_obj(self, index=None) -> np.ndarray:
        """(n, 4, 4) mm: the template cameras' poses (object origin on the axis at render_distance)."""
        R = self.R if index is None else self.R[np.asarray(index)]
        return make_pose(R.astype(np.float64), np.array([0.0, 0.0, self.render_distance]))

    def feature_pixels(self, index) -> np.ndarray:
        """(..., F, 2) feature positions of templates ``index`` in template-render pixel-centre coordinates."""
        index = np.asarray(index)
        w, h = self.crop
        p0 = np.array([(w - 1) / 2 + 0.5, (h - 1) / 2 + 0.5])  # principal point, pixel-edge coordinates
        size = self.box_size[index].astype(np.float64)[..., None, :]
        rel = self.xy[index].astype(np.float64) - self.origin[index].astype(np.float64)[..., None, :]
        return p0 + rel * size - 0.5

    _ARRAYS = ("R", "xy", "bins", "origin", "box_size", "depth_offset", "viewpoint", "inplane", "directions", "hull")

    def save(self, path: str | Path) -> None:
        """One .npz (written atomically)."""
        meta = {"obj_id": self.obj_id, "render_distance": self.render_distance, "focal": self.focal,
                "crop": list(self.crop), "n_inplane": self.n_inplane, "model_sha1": self.model_sha1,
                "format": FORMAT, "version": FORMAT_VERSION}
        with atomic.atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, meta=np.array(json.dumps(meta)), **{k: getattr(self, k) for k in self._ARRAYS})

    @classmethod
    def load(cls, path: str | Path) -> "ObjectTemplates":
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                meta = json.loads(str(z["meta"]))
                arrays = {k: z[k] for k in cls._ARRAYS}
        except (OSError, KeyError, ValueError) as e:
            raise CosyError(f"cannot read templates ({type(e).__name__}: {e}); rebuild them with cosy templates",
                            path=path) from None
        if meta.get("format") != FORMAT or meta.get("version") != FORMAT_VERSION:
            raise CosyError(f"not {FORMAT} version {FORMAT_VERSION}; rebuild with cosy templates --overwrite",
                            path=path)
        return cls(obj_id=int(meta["obj_id"]), render_distance=float(meta["render_distance"]),
                   focal=float(meta["focal"]), crop=tuple(meta["crop"]), n_inplane=int(meta["n_inplane"]),
                   model_sha1=meta.get("model_sha1", ""), **arrays)

    def grid_indices(self, grid: int, pad: int) -> np.ndarray:
        """(T, F) flat indices (intp: what np.take wants without a copy) into 8 response maps of
        side grid + 2 pad (cached per grid)."""
        key = (grid, pad)
        if key not in self._index_cache:
            side = grid + 2 * pad
            g = np.floor(pad + self.xy.astype(np.float32) * grid).astype(np.int32)
            np.clip(g, 0, side - 1, out=g)
            self._index_cache[key] = (self.bins.astype(np.intp) * (side * side) + g[..., 1] * side + g[..., 0])
        return self._index_cache[key]


def _render_distance(radius: float, conf: dict) -> float:
    """Distance (mm) at which a sphere of ``radius`` (mm) about the origin spans ``fill`` of the
    smaller crop side with focal ``focal_px``."""
    half = conf["fill"] * min(conf["crop"]) / 2
    return radius * math.sqrt(1.0 + (conf["focal_px"] / half) ** 2)


def _farthest_features(pos: np.ndarray, valid: np.ndarray, start: np.ndarray, k: int) -> np.ndarray:
    """Farthest-point sampling batched over B sets: pos (B, M, 2), valid (B, M), start (B,) index.
    Returns (B, k) indices; sets with fewer than k valid points repeat points."""
    B = len(pos)
    rows = np.arange(B)
    out = np.empty((B, k), dtype=np.int64)
    dist = np.where(valid, np.inf, -1.0).astype(np.float32)
    cur = start
    for j in range(k):
        out[:, j] = cur
        d = ((pos - pos[rows, cur][:, None]) ** 2).sum(-1)
        dist = np.minimum(dist, d)
        cur = np.argmax(dist, axis=1)
    return out


def _hull_points(vertices: np.ndarray, max_points: int = 1024) -> np.ndarray:
    """(P, 3) float32: the convex hull's vertices of a model (mm), at most ``max_points``
    (farthest-point subset): their projections bound the silhouette exactly."""
    from scipy.spatial import ConvexHull, QhullError

    from ...geometry.sampling import farthest_point_subset

    V = np.asarray(vertices, dtype=np.float64)
    try:
        V = V[ConvexHull(V).vertices]
    except (QhullError, ValueError):
        pass
    return farthest_point_subset(V, max_points).astype(np.float32)


def _silhouette_hulls(masks: np.ndarray) -> list[np.ndarray]:
    """Per mask (H, W) bool: the convex hull (P, 2) of its pixel squares, pixel-edge coordinates."""
    import cv2

    corners = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], dtype=np.float64)
    hulls = []
    for m in masks:  # one cv2 call per viewpoint
        ys, xs = np.nonzero(m)
        if len(xs) == 0:
            hulls.append(np.zeros((0, 2)))
            continue
        pts = np.stack([xs, ys], 1).astype(np.int32)
        h = cv2.convexHull(pts).reshape(-1, 2).astype(np.float64)
        hulls.append((h[:, None, :] + corners[None]).reshape(-1, 2))
    return hulls


def build_object_templates(renderer, obj, conf: dict, model_sha1: str = "") -> ObjectTemplates:
    """Templates of one object (``obj``: an ObjectModel) with settings ``conf`` (:func:`resolve_conf`),
    rendered with ``renderer`` (a SceneRenderer holding ``obj.obj_id``)."""
    w, h = conf["crop"]
    F, I = conf["features"], conf["inplane"]
    dirs = fibonacci_sphere(conf["viewpoints"])
    syms = obj.symmetries_with_steps(conf["symmetry_steps"])
    dirs = dirs[dedupe_viewpoints(dirs, syms, conf["dedupe"] * sphere_spacing(conf["viewpoints"]))]
    V = len(dirs)
    radius = float(np.linalg.norm(obj.vertices, axis=1).max())
    dist = _render_distance(radius, conf)
    T_cam_obj = invert(look_at(dirs * dist, np.zeros(3), up=(0.0, 0.0, 1.0)))
    K = np.array([[conf["focal_px"], 0.0, (w - 1) / 2], [0.0, conf["focal_px"], (h - 1) / 2], [0.0, 0.0, 1.0]])
    out = renderer.render_crops(np.broadcast_to(K, (V, 3, 3)), [obj.obj_id] * V, T_cam_obj, (w, h),
                                colors=np.full((V, 3), GREY))
    mask = out.instance >= 0
    gray = out.rgb.astype(np.float32).mean(-1)
    gx, gy = sobel(gray)
    mag = np.hypot(gx, gy)
    angle = np.arctan2(gy, gx)

    # feature candidates: strong gradients; spread by farthest-point sampling from the strongest
    cand = mag >= conf["min_gradient"]
    counts = cand.reshape(V, -1).sum(1)
    M = max(int(counts.max()), 1)
    vi, ys, xs = np.nonzero(cand)
    slot = np.arange(len(vi)) - np.repeat(np.cumsum(counts) - counts, counts)
    pos = np.zeros((V, M, 2), dtype=np.float32)
    valid = np.zeros((V, M), dtype=bool)
    pos[vi, slot] = np.stack([xs, ys], 1)
    valid[vi, slot] = True
    cmag = np.zeros((V, M), dtype=np.float32)
    cmag[vi, slot] = mag[vi, ys, xs]
    sel = _farthest_features(pos, valid, np.argmax(cmag, axis=1), F)  # (V, F)
    fpos = np.take_along_axis(pos, sel[..., None], axis=1).astype(np.float64)  # pixel-centre coordinates
    fx, fy = fpos[..., 0].astype(np.int64), fpos[..., 1].astype(np.int64)
    fang = angle[np.arange(V)[:, None], fy, fx]  # (V, F)
    empty = counts == 0
    if empty.any():  # object not visible at all (degenerate mesh): a single dummy feature at the centre
        fpos[empty] = [(w - 1) / 2, (h - 1) / 2]
        fang[empty] = 0.0

    # in-plane rotations about the principal point, in pixel-edge coordinates
    p0 = np.array([K[0, 2] + 0.5, K[1, 2] + 0.5])
    alpha = 2 * np.pi * np.arange(I) / I
    rot2 = rotation_z(alpha)[:, :2, :2]  # (I, 2, 2)
    rel = fpos + 0.5 - p0  # (V, F, 2)
    frot = np.einsum("iab,vfb->vifa", rot2, rel) + p0  # (V, I, F, 2)
    hulls = _silhouette_hulls(mask)
    P = max(max(len(hh) for hh in hulls), 1)
    hull = np.empty((V, P, 2))
    for v, hh in enumerate(hulls):
        hull[v] = hh[np.arange(P) % len(hh)] if len(hh) else p0
    hrot = np.einsum("iab,vpb->vipa", rot2, hull - p0) + p0  # (V, I, P, 2)
    lo, hi = hrot.min(2), hrot.max(2)  # (V, I, 2)
    size = np.maximum(hi - lo, 1.0)
    xy = (frot - lo[:, :, None]) / size[:, :, None]
    origin = (p0 - lo) / size
    bins = orientation_bins(fang[:, None, :] + alpha[None, :, None])  # (V, I, F)
    depth_med = np.array([np.median(d[m]) if m.any() else dist for d, m in zip(out.depth, mask)])
    R = rotation_z(alpha)[None] @ T_cam_obj[:, None, :3, :3]  # (V, I, 3, 3)
    T = V * I
    return ObjectTemplates(
        obj_id=int(obj.obj_id), R=R.reshape(T, 3, 3).astype(np.float32),
        xy=xy.reshape(T, F, 2).astype(np.float16), bins=bins.reshape(T, F),
        origin=origin.reshape(T, 2).astype(np.float32), box_size=size.reshape(T, 2).astype(np.float32),
        depth_offset=np.repeat(depth_med - dist, I).astype(np.float32),
        viewpoint=np.repeat(np.arange(V), I).astype(np.int32), inplane=np.tile(np.arange(I), V).astype(np.int32),
        directions=dirs.astype(np.float32), hull=_hull_points(obj.vertices), render_distance=float(dist),
        focal=float(conf["focal_px"]), crop=(int(w), int(h)), n_inplane=int(I), model_sha1=model_sha1)


class TemplateSet:
    """Templates of several objects (``ts[obj_id]``, ``obj_id in ts``) and the settings that made them."""

    def __init__(self, objects: Mapping[int, ObjectTemplates], conf: dict, manifest: dict | None = None):
        self.objects = dict(sorted((int(k), v) for k, v in objects.items()))
        self.conf = dict(conf)
        self.manifest = manifest

    def __getitem__(self, obj_id: int) -> ObjectTemplates:
        try:
            return self.objects[int(obj_id)]
        except KeyError:
            raise CosyError(f"no templates for object {obj_id} (templates exist for {sorted(self.objects)})") from None

    def __contains__(self, obj_id) -> bool:
        return int(obj_id) in self.objects

    def __len__(self) -> int:
        return len(self.objects)

    @property
    def obj_ids(self) -> list[int]:
        return list(self.objects)

    def save(self, directory: str | Path, models_info_sha1: str = "",
             info_sha1: Mapping[int, str] | None = None) -> Path:
        """Write one npz per object and ``manifest.json`` (each file atomically, the manifest last)."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        entries = {}
        for o, t in self.objects.items():
            t.save(d / _npz_name(o))
            entries[str(o)] = _manifest_entry(t, (info_sha1 or {}).get(o, ""))
        doc = _manifest(self.conf, entries, models_info_sha1, complete=True)
        atomic.write_json(d / MANIFEST, doc)
        self.manifest = doc
        return d

    @classmethod
    def load(cls, directory: str | Path, obj_ids: Sequence[int] | None = None) -> "TemplateSet":
        """Templates listed in ``directory/manifest.json`` (all, or ``obj_ids``)."""
        d = Path(directory)
        doc = read_manifest(d)
        if doc is None:
            raise CosyError(f"no {MANIFEST}: not a templates folder (build it with cosy templates)", path=d)
        if not doc.get("complete", False):
            raise CosyError("templates folder is incomplete (an interrupted build): run cosy templates again", path=d)
        objs = {}
        for key, e in doc["objects"].items():
            o = int(key)
            if obj_ids is not None and o not in set(int(i) for i in obj_ids):
                continue
            t = ObjectTemplates.load(d / e["file"])
            if t.model_sha1 != e.get("model_sha1"):
                raise CosyError(f"{e['file']} does not belong to {MANIFEST} (model hash differs): "
                                "run cosy templates again", path=d)
            objs[o] = t
        return cls(objs, doc["conf"], doc)


def _npz_name(obj_id: int) -> str:
    return f"obj_{int(obj_id):06d}.npz"


def _manifest_entry(t: ObjectTemplates, info_sha1: str, build_s: float | None = None) -> dict:
    e = {"file": _npz_name(t.obj_id), "model_sha1": t.model_sha1, "info_sha1": info_sha1,
         "viewpoints": t.n_viewpoints, "templates": t.n_templates, "render_distance_mm": round(t.render_distance, 3)}
    if build_s is not None:
        e["build_s"] = round(build_s, 3)
    return e


def _manifest(conf: dict, entries: dict, models_info_sha1: str, complete: bool, models_dir: str = "") -> dict:
    return {"format": FORMAT, "version": FORMAT_VERSION, "cosy_version": __version__,
            "conf": json.loads(json.dumps(conf)), "models_dir": models_dir, "models_info_sha1": models_info_sha1,
            "complete": complete, "objects": dict(sorted(entries.items(), key=lambda kv: int(kv[0])))}


def read_manifest(directory: str | Path) -> dict | None:
    """The manifest of a templates folder, or None when there is none."""
    p = Path(directory) / MANIFEST
    if not p.is_file():
        return None
    try:
        doc = json.loads(p.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise CosyError(f"unreadable manifest ({e}); rebuild with --overwrite", path=p) from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or not isinstance(doc.get("objects"), dict):
        raise CosyError(f"not a {FORMAT} manifest; rebuild with --overwrite", path=p)
    return doc


def _open_renderer(objs):
    from ...rendering import SceneRenderer

    return SceneRenderer({o.obj_id: o.mesh for o in objs}, 128, 96, znear=1.0, zfar=100_000.0)


def build_templates(db, conf: str | Mapping | None = None, obj_ids: Sequence[int] | None = None, *,
                    progress: bool = True, model_sha1: Mapping[int, str] | None = None) -> TemplateSet:
    """Templates of the objects of ``db`` (an ObjectDatabase; all objects or ``obj_ids``)."""
    from ...console import progress as progress_bar

    conf = resolve_conf(conf)
    objs = [db[o] for o in (db.obj_ids if obj_ids is None else obj_ids)]
    out = {}
    with _open_renderer(objs) as ren:
        for o in progress_bar(objs, desc="templates", unit="object", enabled=progress):
            sha = (model_sha1 or {}).get(o.obj_id) or file_sha1(o.mesh_path)
            out[o.obj_id] = build_object_templates(ren, o, conf, sha)
    return TemplateSet(out, conf)


# ------------------------------------------------------------------------------------------
# the stage
# ------------------------------------------------------------------------------------------
def _info_digests(models_info_path: Path) -> dict[int, str]:
    """sha1 of each object's models_info.json entry (symmetries change the templates)."""
    data = json.loads(models_info_path.read_text())
    return {int(k): hashlib.sha1(json.dumps(v, sort_keys=True).encode()).hexdigest() for k, v in data.items()}


def main(conf: str | Mapping | None, models_dir: str | Path, out: str | Path, overwrite: bool = False, *,
         log=print, progress: bool = True) -> Path:
    """``cosy templates``: build (or bring up to date) the templates of every object of ``models_dir``
    in the folder ``out``. Objects whose model file or models_info entry is unchanged are kept;
    changed, new or unfinished ones are (re)built, each npz and then the manifest written
    atomically (an interrupted build resumes). Other settings than those of an existing ``out``
    are refused unless ``overwrite`` (which rebuilds everything). Returns ``out``."""
    from ...objects.database import ObjectDatabase
    from ...console import progress as progress_bar

    t_start = time.perf_counter()
    conf = resolve_conf(conf)
    models_dir, out = Path(models_dir), Path(out)
    db = ObjectDatabase.from_models_dir(models_dir)
    if len(db) == 0:
        raise CosyError("models_info.json lists no objects", path=models_dir / "models_info.json")
    info_path = models_dir / "models_info.json"
    info_sha = _info_digests(info_path)
    models_info_sha1 = file_sha1(info_path)
    model_sha = {o.obj_id: file_sha1(o.mesh_path) for o in db}

    if out.exists() and not out.is_dir():
        raise CosyError("exists and is not a folder", path=out)
    old = read_manifest(out) if out.is_dir() else None
    if old is None and out.is_dir() and any(out.iterdir()) and not overwrite:
        raise CosyError(f"exists, is not empty and has no {MANIFEST} (not a templates folder; "
                        "use --overwrite to build into it)", path=out)
    entries: dict[str, dict] = {}
    if old is not None and not overwrite:
        if old.get("conf") != json.loads(json.dumps(conf)):
            changed = sorted(k for k in set(conf) | set(old.get("conf") or {})
                             if (old.get("conf") or {}).get(k) != json.loads(json.dumps(conf)).get(k))
            raise CosyError(f"templates made with other settings ({', '.join(changed)}); use --overwrite to rebuild",
                            path=out)
        for o in db.obj_ids:
            e = old["objects"].get(str(o))
            if (e and e.get("model_sha1") == model_sha[o] and e.get("info_sha1") == info_sha.get(o)
                    and (out / e.get("file", "")).is_file()):
                entries[str(o)] = e
    todo = [o for o in db.obj_ids if str(o) not in entries]
    stale = sorted(set((old or {}).get("objects", {})) - {str(o) for o in db.obj_ids}, key=int)
    if not todo and not stale and old is not None and old.get("complete") and not overwrite \
            and old.get("models_info_sha1") == models_info_sha1:
        log(f"templates: {out} is up to date ({len(entries)} objects), skipping (use --overwrite to rebuild)")
        return out
    out.mkdir(parents=True, exist_ok=True)
    if old is not None and not overwrite:
        changed = [o for o in todo if str(o) in old["objects"]]
        if changed:
            log(f"templates: rebuilding object(s) {', '.join(map(str, changed))} (model or models_info entry changed)")
    resolved = str(models_dir.resolve())
    if todo:
        with _open_renderer([db[o] for o in todo]) as ren:
            for o in progress_bar(todo, desc="templates", unit="object", enabled=progress):
                t0 = time.perf_counter()
                t = build_object_templates(ren, db[o], conf, model_sha[o])
                t.save(out / _npz_name(o))
                entries[str(o)] = _manifest_entry(t, info_sha.get(o, ""), time.perf_counter() - t0)
                atomic.write_json(out / MANIFEST, _manifest(conf, entries, models_info_sha1, False, resolved))
                log(f"templates: object {o}: {t.n_viewpoints} viewpoints x {t.n_inplane} in-plane = "
                    f"{t.n_templates} templates ({time.perf_counter() - t0:.1f} s)")
    atomic.write_json(out / MANIFEST, _manifest(conf, entries, models_info_sha1, True, resolved))
    for key in stale:  # objects no longer in the models folder: the manifest no longer lists them
        (out / _npz_name(int(key))).unlink(missing_ok=True)
    log(f"templates: {len(todo)} object(s) built, {len(entries) - len(todo)} kept, in "
        f"{time.perf_counter() - t_start:.1f} s -> {out}")
    return out


# ------------------------------------------------------------------------------------------
# matching
# ------------------------------------------------------------------------------------------
@dataclass
class MatchParams:
    """Matching settings (defaults chosen on the 192 GT boxes of data_samples/test).

    grid: cells across the detection box (64); pad: extra cells on each side (8); spread: radius
    in cells of the orientation spreading (1; 2 and 3 were worse); min_gradient: Sobel magnitude
    (grey levels, per crop cell) of a gradient that counts (20; 40 and 80 were worse);
    depth_from: how the two box sides give the distance: "max" (the larger of the width and height
    scales, i.e. the less shrunk side of an occluded visible box; the best), "mean", "width",
    "height", "diag"; refine_depth: corrections of the distance with the box of the projected
    convex hull at the current pose (2; removes the off-axis magnification, -3 % -> 0 % median
    depth error); nms_deg: > 0 keeps only hypotheses that many degrees apart (0: plain top-k,
    which gave the better best-of-5)."""

    grid: int = 64
    pad: int = 8
    spread: int = 1
    min_gradient: float = 20.0
    depth_from: str = "max"
    refine_depth: int = 2
    nms_deg: float = 0.0
    mask_band: int = 0         # with a detection mask: keep the image's gradients within this many cells of the
                               # mask (0: the mask is not used here); its outline also counts as an edge
    mask_outline: bool = True


@dataclass
class TemplateHypotheses:
    """Top-k templates per detection. T_cam_obj (N, k, 4, 4) mm; scores (N, k) mean responses in
    [0, 1] (NaN where an object has fewer than k templates); template_index (N, k) into the
    object's templates (-1 there)."""

    T_cam_obj: np.ndarray
    scores: np.ndarray
    template_index: np.ndarray


def _response_lut() -> np.ndarray:
    """(8, 256) uint8: response of template orientation o to a pixel whose spread bitmask is m:
    255 x the max over the orientations p present in m of |cos(angle(o) - angle(p))|, 0 for m = 0."""
    d = np.abs(np.arange(N_BINS)[:, None] - np.arange(N_BINS)[None])
    d = np.minimum(d, N_BINS - d)
    cos = np.abs(np.cos(d * np.pi / N_BINS))  # (o, p)
    masks = np.arange(256)
    present = ((masks[:, None] >> np.arange(N_BINS)[None]) & 1).astype(bool)  # (256, p)
    lut = np.where(present[None], cos[:, None, :], 0.0).max(-1)
    return np.round(255 * lut).astype(np.uint8)


_LUT = _response_lut()


def response_maps(rgb: np.ndarray, box: np.ndarray, params: MatchParams, mask: np.ndarray | None = None) -> np.ndarray:
    """(8, S, S) uint8 response maps (255: an orientation present that is the template's) of a
    detection box (x1, y1, x2, y2 px, pixel edges) of an RGB (H, W, 3) image, S = grid + 2 pad:
    the box's edges land on the edges of cells pad and pad + grid. ``mask`` (H, W) bool, the
    detection's segmentation, with ``params.mask_band`` > 0: gradients farther than that many
    cells from the mask are dropped (clutter), and with ``mask_outline`` the mask's own outline
    counts as gradients too (a silhouette edge against a background of the same colour)."""
    import cv2

    G, pad = params.grid, params.pad
    S = G + 2 * pad
    x1, y1, x2, y2 = (float(v) for v in box)
    bw, bh = max(x2 - x1, 1.0), max(y2 - y1, 1.0)
    sx, sy = G / bw, G / bh  # cells per image pixel
    ex1, ey1 = x1 - pad / sx, y1 - pad / sy  # the enlarged window, pixel-edge coordinates
    ex2, ey2 = x2 + pad / sx, y2 + pad / sy
    H, W = rgb.shape[:2]
    blur = [0.5 / s if s < 0.7 else 0.0 for s in (sx, sy)]  # anti-aliasing when shrinking
    m = int(math.ceil(3 * max(blur))) + 2
    X0, Y0 = max(int(math.floor(ex1)) - m, 0), max(int(math.floor(ey1)) - m, 0)
    X1, Y1 = min(int(math.ceil(ex2)) + m, W), min(int(math.ceil(ey2)) + m, H)
    if X1 <= X0 or Y1 <= Y0:  # the window is outside the image
        return np.zeros((N_BINS, S, S), np.uint8)
    sub = np.ascontiguousarray(rgb[Y0:Y1, X0:X1])
    if max(blur) > 0:
        sub = cv2.GaussianBlur(sub, (0, 0), sigmaX=max(blur[0], 1e-3), sigmaY=max(blur[1], 1e-3))
    # pixel-edge x -> cell edge (x - ex1) * sx; with pixel centres: c = (x + 0.5 - ex1) * sx - 0.5
    A = np.array([[sx, 0.0, (X0 + 0.5 - ex1) * sx - 0.5], [0.0, sy, (Y0 + 0.5 - ey1) * sy - 0.5]])
    crop = cv2.warpAffine(sub, A, (S, S), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    channels = np.moveaxis(crop.astype(np.float32), -1, 0)
    band = None
    if mask is not None and params.mask_band > 0:
        msub = np.ascontiguousarray(np.asarray(mask)[Y0:Y1, X0:X1], dtype=np.float32) * 255.0
        mcrop = cv2.warpAffine(msub, A, (S, S), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                               borderValue=0.0)
        inside = (mcrop >= 127.5).astype(np.uint8)
        k = 2 * params.mask_band + 1
        band = cv2.dilate(inside, np.ones((k, k), np.uint8)) > 0
        if params.mask_outline:  # a fourth channel: the mask itself, an edge wherever its outline runs
            channels = np.concatenate([channels, mcrop[None]], 0)
    gx, gy = sobel(channels)  # (3 or 4, S, S)
    mag2 = gx * gx + gy * gy
    c = np.argmax(mag2, axis=0)[None]
    gx, gy = np.take_along_axis(gx, c, 0)[0], np.take_along_axis(gy, c, 0)[0]
    strong = np.take_along_axis(mag2, c, 0)[0] >= params.min_gradient ** 2
    if band is not None:
        strong &= band
    # directions in the image's metric: d/dx_image = sx d/dx_cell
    bins = orientation_bins(np.arctan2(gy * sy, gx * sx))
    mask = np.where(strong, np.left_shift(1, bins), 0).astype(np.uint8)
    r = params.spread
    if r > 0:
        p = np.pad(mask, r)
        acc = np.zeros((S + 2 * r, S), np.uint8)
        for k in range(2 * r + 1):
            acc |= p[:, k:k + S]
        mask = np.zeros((S, S), np.uint8)
        for k in range(2 * r + 1):
            mask |= acc[k:k + S]
    return _LUT[:, mask]


def score_templates(t: ObjectTemplates, responses: np.ndarray, params: MatchParams) -> np.ndarray:
    """(T,) float32 mean response in [0, 1] of every template of ``t`` to response maps (8, S, S) uint8."""
    import cv2

    idx = t.grid_indices(params.grid, params.pad)
    gathered = np.take(responses.reshape(-1), idx)  # (T, F) uint8
    total = cv2.reduce(gathered, 1, cv2.REDUCE_SUM, dtype=cv2.CV_32S).reshape(-1)  # exact, ~15x numpy's sum
    return total.astype(np.float32) / np.float32(255 * idx.shape[1])


def _rotation_to_rays(rays: np.ndarray) -> np.ndarray:
    """(..., 3, 3) smallest rotations taking the optical axis (0, 0, 1) onto unit ``rays`` (..., 3)."""
    r = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    x, y, z = r[..., 0], r[..., 1], r[..., 2]
    # Rodrigues with axis e_z x r = (-y, x, 0), sin = |(x, y)|, cos = z: closed form (valid for z > -1)
    k = 1.0 / (1.0 + z)
    R = np.empty(r.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - k * x * x
    R[..., 0, 1] = -k * x * y
    R[..., 0, 2] = x
    R[..., 1, 0] = -k * x * y
    R[..., 1, 1] = 1 - k * y * y
    R[..., 1, 2] = y
    R[..., 2, 0] = -x
    R[..., 2, 1] = -y
    R[..., 2, 2] = z
    return R


DEPTH_MODES = ("max", "mean", "width", "height", "diag")


def _distance_update(dist: np.ndarray, pred: np.ndarray, obs: np.ndarray, mode: str) -> np.ndarray:
    """New distances (mm) from distances ``dist`` (...,) at which the object's box would be
    ``pred`` (..., 2) px (w, h), given the observed box sizes ``obs`` (..., 2): size ~ 1 / distance."""
    zw = dist * pred[..., 0] / obs[..., 0]
    zh = dist * pred[..., 1] / obs[..., 1]
    if mode == "max":  # the larger of the two scales (the less shrunk side of a visible box): the nearer
        return np.minimum(zw, zh)
    if mode == "mean":  # mean of the two scales
        return 2.0 / (1.0 / zw + 1.0 / zh)
    if mode == "width":
        return zw
    if mode == "height":
        return zh
    if mode == "diag":
        return dist * np.hypot(pred[..., 0], pred[..., 1]) / np.hypot(obs[..., 0], obs[..., 1])
    raise ValueError(f"depth_from must be one of {', '.join(DEPTH_MODES)}, got {mode!r}")


def poses_from_templates(t: ObjectTemplates, index: np.ndarray, K: np.ndarray, boxes: np.ndarray,
                         depth_from: str = "max", refine: int = 2) -> np.ndarray:
    """T_cam_obj (..., 4, 4) mm of templates ``index`` (...,) placed in detection ``boxes`` (..., 4)
    (x1, y1, x2, y2 px, pixel edges) of a camera K (3, 3).

    The object origin goes on the ray through its normalised box position mapped into the box;
    R = R_ray @ R_template; the distance along the ray first from the template's box size
    (z = d_r f_obs / f_r s_t / s_obs), then ``refine`` times corrected with the box of the
    projected convex hull at the current pose (exact off-axis and perspective magnification)."""
    index = np.asarray(index)
    b = np.asarray(boxes, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    obs = np.stack([np.maximum(b[..., 2] - b[..., 0], 1e-6), np.maximum(b[..., 3] - b[..., 1], 1e-6)], -1)
    o = t.origin[index].astype(np.float64)
    u = b[..., 0] + o[..., 0] * obs[..., 0] - 0.5  # pixel-centre coordinates
    v = b[..., 1] + o[..., 1] * obs[..., 1] - 0.5
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
    rhat = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    R = _rotation_to_rays(rhat) @ t.R[index].astype(np.float64)
    pred = t.box_size[index].astype(np.float64) * (np.array([K[0, 0], K[1, 1]]) / t.focal)
    dist = _distance_update(np.full(index.shape, t.render_distance), pred, obs, depth_from)
    hull = t.hull.astype(np.float64)
    if refine and len(hull) and index.size:
        shape = index.shape
        m = index.size
        # the rotated hull of every pose in one product: (3, P, m) camera axes x hull points x poses
        X, Y, Z = np.moveaxis((hull @ R.reshape(m * 3, 3).T).reshape(len(hull), m, 3), -1, 0)
        rh = rhat.reshape(m, 3)
        ob = np.broadcast_to(obs, shape + (2,)).reshape(m, 2)
        d = dist.reshape(m)
        for _ in range(refine):
            c = rh * d[:, None]
            z = np.maximum(Z + c[:, 2], 1e-6)
            y = (Y + c[:, 1]) / z
            u = K[0, 0] * ((X + c[:, 0]) / z) + K[0, 1] * y
            v = K[1, 1] * y
            pred = np.maximum(np.stack([u.max(0) - u.min(0), v.max(0) - v.min(0)], -1), 1e-6)
            d = _distance_update(d, pred, ob, depth_from)
        dist = d.reshape(shape)
    return make_pose(R, rhat * dist[..., None])


def at_distances(h: TemplateHypotheses, factors) -> TemplateHypotheses:
    """Every hypothesis of ``h`` also at other distances: its translation times each factor of
    ``factors`` (the object slides along its line of sight: its projected centre stays, its image
    size scales by 1 / factor). Template retrieval takes the distance from the detection box's
    size, so a box 15 % too large puts the object 15 % too close; the verification by rendering
    then chooses among the distances. Returns (N, k x F) hypotheses, each hypothesis's variants
    side by side (in the order of ``factors``), its template score and index repeated."""
    f = np.asarray(list(factors), dtype=np.float64)
    N, k = h.T_cam_obj.shape[:2]
    T = np.repeat(h.T_cam_obj[:, :, None], len(f), 2)  # (N, k, F, 4, 4)
    T[..., :3, 3] *= f[None, None, :, None]
    return TemplateHypotheses(T.reshape(N, k * len(f), 4, 4), np.repeat(h.scores, len(f), 1),
                              np.repeat(h.template_index, len(f), 1))


def interleave(a: TemplateHypotheses, b: TemplateHypotheses, k: int) -> TemplateHypotheses:
    """``k`` hypotheses per detection taken in turn from ``a`` and ``b`` (a's first, then b's first,
    ...; a template already taken is skipped, and what one side lacks the other fills): e.g. the
    matches of a detection with and without its mask, for the verification to choose from."""
    N = a.T_cam_obj.shape[0]
    T = np.tile(np.eye(4), (N, k, 1, 1))
    sc = np.full((N, k), np.nan)
    idx = np.full((N, k), -1, np.int64)
    for n in range(N):
        order = [(src, j) for j in range(max(a.scores.shape[1], b.scores.shape[1])) for src in (a, b)
                 if j < src.scores.shape[1] and src.template_index[n, j] >= 0]
        seen, m = set(), 0
        for src, j in order:
            t = int(src.template_index[n, j])
            if t in seen:
                continue
            seen.add(t)
            T[n, m], sc[n, m], idx[n, m] = src.T_cam_obj[n, j], src.scores[n, j], t
            m += 1
            if m == k:
                break
    return TemplateHypotheses(T, sc, idx)


def select_top(t: ObjectTemplates, scores: np.ndarray, k: int, nms_deg: float = 0.0, pool: int = 256) -> np.ndarray:
    """Indices of the ``k`` best templates by score, best first. With ``nms_deg`` > 0, a template is
    skipped when its rotation is within ``nms_deg`` degrees of a better one already taken (among
    the ``pool`` best), so that the k hypotheses are distinct poses."""
    n = len(scores)
    m = min(n, max(pool, k) if nms_deg > 0 else k)
    cand = np.argpartition(-scores, m - 1)[:m] if m < n else np.arange(n)
    cand = cand[np.argsort(-scores[cand], kind="stable")]
    if nms_deg <= 0:
        return cand[:k]
    R = t.R[cand].astype(np.float32).reshape(m, 9)
    close = (R @ R.T - 1.0) / 2.0 > math.cos(math.radians(nms_deg))  # cos of the relative angle
    taken = []
    for i in range(m):  # greedy, stops after k
        if not taken or not close[i, taken].any():
            taken.append(i)
            if len(taken) == k:
                break
    return cand[taken]


def match_templates(templates: TemplateSet, rgb: np.ndarray, K: np.ndarray, boxes: np.ndarray,
                    obj_ids: Sequence[int], top_k: int = 5, params: MatchParams | None = None,
                    masks=None) -> TemplateHypotheses:
    """The ``top_k`` best templates of each detection and their poses.

    rgb (H, W, 3) uint8; K (3, 3) px; boxes (N, 4) x1, y1, x2, y2 px (pixel edges: x2 = x + w);
    obj_ids (N,); masks: None or per detection an (H, W) bool segmentation or None (used with
    ``params.mask_band`` > 0, see :func:`response_maps`). Returns T_cam_obj (N, k, 4, 4) mm,
    scores (N, k), template_index (N, k)."""
    params = params or MatchParams()
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb must be (H, W, 3), got {rgb.shape}")
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    obj_ids = np.asarray(obj_ids).reshape(-1)
    if len(obj_ids) != len(boxes):
        raise ValueError(f"{len(boxes)} boxes but {len(obj_ids)} obj_ids")
    N, k = len(boxes), int(top_k)
    T_out = np.tile(np.eye(4), (N, k, 1, 1))
    scores = np.full((N, k), np.nan)
    index = np.full((N, k), -1, dtype=np.int64)
    for n in range(N):  # one gather over all templates per detection
        t = templates[obj_ids[n]]
        m = None if masks is None else masks[n]
        s = score_templates(t, response_maps(rgb, boxes[n], params, m), params)
        top = select_top(t, s, k, params.nms_deg)
        kk = len(top)
        index[n, :kk] = top
        scores[n, :kk] = s[top]
        T_out[n, :kk] = poses_from_templates(t, top, K, np.broadcast_to(boxes[n], (kk, 4)), params.depth_from,
                                             params.refine_depth)
    return TemplateHypotheses(T_out, scores, index)
