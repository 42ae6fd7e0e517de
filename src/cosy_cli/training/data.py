"""On-the-fly training samples for the render-and-compare networks (CosyPose appendix A).

One sample is a pair of crops of the same size (default 128 x 96) seen through the same crop
intrinsics ``K_crop``:

- ``observed``: a target object at a random ground-truth pose ``T_gt`` in front of a random
  camera, rendered with domain randomisation (random flat colour or per-vertex colour noise,
  low-frequency colour noise on the surface, random light direction / intensity / ambient,
  random background: flat + noise, gradients, blobs, or pieces of earlier renders; 0-3 random
  occluders from the same object set in front of or beside the target; contrast, brightness,
  per-channel gain, blur and pixel noise);
- ``rendered``: the object alone at the *input* pose ``T_input`` (neutral grey, light from the
  camera, black background): what the network compares the observation with.

Input poses. Refiner: ``T_gt`` perturbed by :func:`perturb_poses` (rotation vector ~ N(0, 15 deg)
per axis applied in the camera frame about the object centre, translation x/y ~ N(0, 10 mm),
z ~ N(0, 50 mm); all scaled by ``curriculum`` in [0, 1]). Coarse: :func:`canonical_pose` of a
jittered detection box of the target (bounding box of the projected ground-truth model).

Crops (CosyPose's strategy): centred on the projection of the object centre under the input pose;
the half extent is the largest offset of the projected model (convex hull vertices) under the
input pose from that centre (for the coarse model optionally half the detection box instead);
then enlarged by ``crop_scale`` (1.4) and fitted to the crop's aspect ratio
(:func:`cosy_cli.geometry.fit_box_to_aspect`), ``K_crop`` from
:func:`cosy_cli.geometry.crop_intrinsics`. Both crops are rendered straight at ``K_crop``
(:meth:`cosy_cli.rendering.SceneRenderer.render_crops`, several instances per crop for the
occluders), never warped from a full frame.

Symmetric losses: ``batch["obj_index"]`` indexes :attr:`SampleGenerator.obj_ids`,
:attr:`SampleGenerator.points` ((n_obj, P, 3) mm surface samples) and
:attr:`SampleGenerator.symmetries` (list of (S, 4, 4), identity first).

Note: :func:`canonical_pose` here is the training-data definition; ``cosy_cli.singleview`` may
define the same function; the two must agree (fixed view ``CANONICAL_ROTATION``, object origin on
the ray through the box centre at depth ``distance_mm``).

All lengths in mm, poses ``T_cam_obj`` (4x4, OpenCV camera). Deterministic under ``seed``.
"""

from __future__ import annotations

import atexit
import functools
import math
import os
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ..geometry.camera import crop_intrinsics, fit_box_to_aspect, project
from ..geometry.poses import look_at, make_pose, transform_points
from ..geometry.rotations import axis_angle_to_matrix, random_rotations, rotation_about_axis
from ..lifetime import Closing
from ..objects.database import diameter_of

from ..singleview.networks.crops import (  # one definition: train and test agree
    CANONICAL_DEPTH_MM, CANONICAL_ROTATION, canonical_depth_from_boxes, canonical_poses,
)

DEFAULT_COARSE_DISTANCE_MM = CANONICAL_DEPTH_MM
VARIANT_ID_OFFSET = 1_000_000  # renderer ids of the vertex-colour-noise copies of the meshes
NEUTRAL_COLOR = (0.7, 0.7, 0.7)


@dataclass(frozen=True)
class Perturbation:
    """Noise of the refiner's input pose (standard deviations at curriculum 1).

    rot_std_deg: per axis of a rotation vector, camera frame, about the object centre (deg).
    xy_std_mm, z_std_mm: translation noise along the camera axes (mm). z_std_rel: if set, the
    z std is this fraction of the object's depth instead of z_std_mm.
    """

    rot_std_deg: float = 15.0
    xy_std_mm: float = 10.0
    z_std_mm: float = 50.0
    z_std_rel: float | None = None


DEFAULT_PERTURBATION = Perturbation()


def canonical_pose(K: np.ndarray, box: np.ndarray, distance_mm: float = DEFAULT_COARSE_DISTANCE_MM,
                   R: np.ndarray | None = None) -> np.ndarray:
    """The coarse model's input pose(s) (..., 4, 4) for boxes (..., 4) (pixel-edge x1, y1, x2, y2):
    :func:`cosy_cli.singleview.networks.crops.canonical_poses` keeping the boxes' leading shape."""
    box = np.asarray(box, dtype=np.float64)
    return canonical_poses(K, box.reshape(-1, 4), distance_mm, R).reshape(box.shape[:-1] + (4, 4))


def depth_from_box(K: np.ndarray, box: np.ndarray, diameter_mm) -> np.ndarray:
    """Depth (mm) at which an object of ``diameter_mm`` spans about the larger side of ``box``:
    :func:`cosy_cli.singleview.networks.crops.canonical_depth_from_boxes` keeping the boxes' leading shape."""
    box = np.asarray(box, dtype=np.float64)
    return canonical_depth_from_boxes(K, box.reshape(-1, 4), diameter_mm).reshape(box.shape[:-1])


def perturb_poses(T: np.ndarray, rng: np.random.Generator, perturbation: Perturbation = DEFAULT_PERTURBATION,
                  scale: float = 1.0) -> np.ndarray:
    """Noisy copies (B, 4, 4) of poses T (B, 4, 4) mm: R' = exp(w) R with w ~ N(0, s * rot_std)
    per axis (camera frame, about the object centre); t' = t + N(0, s * (xy, xy, z) std)."""
    T = np.asarray(T, dtype=np.float64)
    B = len(T)
    w = rng.normal(0.0, 1.0, (B, 3)) * math.radians(perturbation.rot_std_deg) * scale
    z_std = (perturbation.z_std_rel * T[:, 2, 3] if perturbation.z_std_rel is not None
             else np.full(B, perturbation.z_std_mm))
    std = np.stack([np.full(B, perturbation.xy_std_mm), np.full(B, perturbation.xy_std_mm), z_std], 1)
    dt = rng.normal(0.0, 1.0, (B, 3)) * std * scale
    out = T.copy()
    out[:, :3, :3] = axis_angle_to_matrix(w) @ T[:, :3, :3]
    out[:, :3, 3] = T[:, :3, 3] + dt
    return out


def _default_camera():
    from ..synth.scenes import camera_matrix

    return camera_matrix(640, 480), (640, 480)


# ---------------------------------------------------------------------- shared randomisation
# Used by SampleGenerator here and by cosy_cli.detection.data.DetectionSampleGenerator.

class RendererOwner(Closing):
    """Base of the generators that own an OpenGL renderer: built on first use by
    ``_make_renderer()`` (so that generators can be made inside worker processes), freed by
    :meth:`close`; pickling is refused (``_pickle_instead`` says what to pickle)."""

    _renderer = None
    _pickle_instead = "its arguments"

    def _make_renderer(self):
        raise NotImplementedError

    @property
    def renderer(self):
        if self._renderer is None:
            self._renderer = self._make_renderer()
        return self._renderer

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __getstate__(self):
        raise TypeError(f"{type(self).__name__} holds an OpenGL context: pickle {self._pickle_instead} instead")


def hsv_to_rgb(h, s, v) -> np.ndarray:
    """Vectorised HSV (each (n,), 0..1) -> (n, 3) RGB 0..1."""
    h = np.asarray(h) % 1.0
    i = np.floor(h * 6).astype(int) % 6
    f = h * 6 - np.floor(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    table = np.stack([np.stack(c, -1) for c in ((v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q))])
    return table[i, np.arange(len(h))]


def random_colors(rng: np.random.Generator, n: int, p=(0.4, 0.2, 0.4), brown_hue=(0.05, 0.12),
                  brown_sat=(0.25, 0.6), sat=(0.3, 0.9), val=(0.35, 0.95)) -> np.ndarray:
    """(n, 3) RGB 0..1 flat object colours: greys, browns or any hue, with probabilities ``p``;
    hue, saturation and value ranges of the browns and of the others."""
    kind = rng.choice(3, size=n, p=list(p))
    grey = np.clip(rng.uniform(0.2, 0.95, (n, 1)) + rng.normal(0, 0.03, (n, 3)), 0, 1)
    hue = np.where(kind == 1, rng.uniform(*brown_hue, n), rng.uniform(0, 1, n))
    s = np.where(kind == 1, rng.uniform(*brown_sat, n), rng.uniform(*sat, n))
    v = rng.uniform(*val, n)
    return np.where((kind == 0)[:, None], grey, hsv_to_rgb(hue, s, v))


def random_light_dirs(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) unit directions the light travels (camera frame): into the scene, within ~75 deg
    of the optical axis."""
    theta = np.radians(rng.uniform(0, 75, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1)


def render_in_light_groups(renderer, rng: np.random.Generator, Ks: np.ndarray, ids: np.ndarray, T: np.ndarray,
                           tiles: np.ndarray, size, colors: np.ndarray, light_groups: int,
                           intensity=(0.35, 1.0), ambient=(0.05, 0.5), with_depth: bool = False) -> tuple:
    """Render B = len(Ks) images (size (w, h), intrinsics Ks (B, 3, 3)) of the instances ``ids``
    at poses ``T`` (n, 4, 4) mm, in image order ``tiles`` (n,), with flat ``colors`` (n, 3) (NaN:
    the mesh's own), in ``min(light_groups, B)`` groups of consecutive images that share a random
    light (:func:`random_light_dirs`, intensity and ambient uniform in the given ranges), one
    render call each. Returns (rgb (B, h, w, 3) uint8, instance (B, h, w) int32: index into
    ``ids`` of the visible instance, -1 where nothing is drawn). ``with_depth``: also depth (B, h, w)
    float32, camera z in mm of the visible surface, 0 where nothing is drawn (a third element)."""
    w, h = size
    B = len(Ks)
    rgb = np.empty((B, h, w, 3), np.uint8)
    inst = np.empty((B, h, w), np.int32)
    depth = np.empty((B, h, w), np.float32) if with_depth else None
    G = min(light_groups, B)
    edges = np.linspace(0, B, G + 1).astype(int)
    light_dirs = random_light_dirs(rng, G)
    light_intensity = rng.uniform(*intensity, G)
    light_ambient = rng.uniform(*ambient, G)
    for g in range(G):
        b0, b1 = edges[g], edges[g + 1]
        if b1 <= b0:
            continue
        i0, i1 = np.searchsorted(tiles, [b0, b1])
        out = renderer.render_crops(Ks[b0:b1], ids[i0:i1], T[i0:i1], (w, h), colors=colors[i0:i1],
                                    light_dir=light_dirs[g], light_intensity=float(light_intensity[g]),
                                    ambient=float(light_ambient[g]), tiles=tiles[i0:i1] - b0)
        rgb[b0:b1] = out.rgb
        inst[b0:b1] = np.where(out.instance >= 0, out.instance + i0, -1)
        if with_depth:
            depth[b0:b1] = out.depth
    return (rgb, inst, depth) if with_depth else (rgb, inst)


@functools.lru_cache(maxsize=4)
def noise_bank(h: int, w: int) -> np.ndarray:
    """(2h, 2w, 3) float32 unit Gaussian noise, fixed (seed 987) and read-only: windows of it at
    random offsets stand for fresh noise per image, which costs more than the rest of the
    compositing together."""
    bank = np.random.default_rng(987).standard_normal((2 * h, 2 * w, 3), dtype=np.float32)
    bank.flags.writeable = False
    return bank


def multiply_field(img: np.ndarray, field: np.ndarray, interpolation: int) -> None:
    """``img`` (h, w, 3) float32 *= the small colour field (gh, gw, 3) resized to it, in place."""
    import cv2

    h, w = img.shape[:2]
    cv2.multiply(img, cv2.resize(field, (w, h), interpolation=interpolation), dst=img)


def flat_background(h: int, w: int, color) -> np.ndarray:
    """(h, w, 3) float32 image of one colour (0..255)."""
    bg = np.empty((h, w, 3), np.float32)
    bg[:] = color
    return bg


def gradient_background(h: int, w: int, c0, c1, angle: float) -> np.ndarray:
    """(h, w, 3) float32 linear gradient from colour ``c0`` to ``c1`` (0..255) along direction
    ``angle`` (rad, image x towards y): the colours of the four corners, resized bilinearly
    (exact for a linear ramp)."""
    import cv2

    corners = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])  # (x, y)
    ramp = corners @ np.array([np.cos(angle), np.sin(angle)])
    ramp = (ramp - ramp.min()) / max(np.ptp(ramp), 1e-6)
    cg = (c0 + ramp[:, None] * (c1 - c0)).reshape(2, 2, 3).astype(np.float32)
    return cv2.resize(cg, (w, h), interpolation=cv2.INTER_LINEAR)


def grid_background(grid: np.ndarray, h: int, w: int, interpolation: int) -> np.ndarray:
    """(h, w, 3) float32: the small random colour grid (gh, gw, 3) resized (smooth blobs, or
    coarse blocks with nearest-neighbour interpolation)."""
    import cv2

    return cv2.resize(grid.astype(np.float32), (w, h), interpolation=interpolation)


def paste_background(img: np.ndarray, bg: np.ndarray, foreground: np.ndarray, noise: np.ndarray | None = None,
                     noise_std: float = 0.0) -> None:
    """Copy ``bg`` (h, w, 3) float32, plus ``noise_std`` x ``noise`` (a noise-bank window) if
    given, into ``img`` where ``foreground`` (h, w) bool is False, in place (``bg`` too)."""
    import cv2

    if noise is not None:
        cv2.scaleAdd(noise, float(noise_std), bg, dst=bg)
    cv2.copyTo(bg, (~foreground).view(np.uint8), img)


def photometric(img: np.ndarray, contrast: float, gain, bright: float, offset: float = 0.0) -> np.ndarray:
    """``((img - mean) * contrast + mean) * gain + bright + offset`` (gain per channel, mean over
    the image) as one affine colour map; float32 (h, w, 3) in and out."""
    import cv2

    mean = float(img.mean())
    M = np.zeros((3, 4), np.float32)
    M[[0, 1, 2], [0, 1, 2]] = contrast * gain
    M[:, 3] = mean * (1 - contrast) * gain + bright + offset
    return cv2.transform(img, M)


class SampleGenerator(RendererOwner):
    """Batches of training samples for the ``kind`` = "refiner" or "coarse" network.

    meshes_or_db: {obj_id: trimesh.Trimesh (mm)} or an ObjectDatabase (its meshes, surface
    points and symmetries are used). symmetries: {obj_id: (S, 4, 4)} for a mesh dict (default:
    identity only). crop_size: (width, height). K, image_size: the dataset camera (default: the
    synthetic one, 640 x 480) that random cameras jitter (focal x U(0.85, 1.15), principal point
    +- 2 % of the size). distance_mm: range of object depths. perturbation / curriculum: the
    refiner's input noise (see :class:`Perturbation`; ``curriculum`` in [0, 1] scales it, may be
    changed between batches). coarse_distance_mm: depth of the coarse model's canonical input
    pose: a fixed value (CosyPose: 1 m) or "box": :func:`depth_from_box` with the object's
    diameter (the rendered object then about fills the crop). resting: orientations are, with
    probability 0.5, stable rest poses of the synthetic objects seen from a random camera
    (cosy_cli.synth), else uniform. coarse_crop: "pose" (the paper: the crop follows the projected
    canonical pose, like the refiner's) or "detection" (half the detection box, x crop_scale).
    canonical_rotation: the coarse input orientation (default ``CANONICAL_ROTATION``).
    occluder_probs: probabilities of 0, 1, 2, 3... occluders. render_colors: "neutral" (grey
    rendered crops) or "mesh" (the meshes' own colours/textures). light_groups: samples of a
    batch share lighting in this many groups (one render call each). with_visibility: also
    return ``visib_fract`` (costs one silhouette render).

    The renderer (one OpenGL context) is created on first use: create generators inside worker
    processes (see :class:`TrainingStream`).
    """

    def __init__(self, meshes_or_db, kind: str = "refiner", crop_size: tuple[int, int] = (128, 96), seed=0, *,
                 perturbation: Perturbation = DEFAULT_PERTURBATION, curriculum: float = 1.0,
                 symmetries: Mapping[int, np.ndarray] | None = None, K: np.ndarray | None = None,
                 image_size: tuple[int, int] | None = None, distance_mm: tuple[float, float] = (300.0, 1000.0),
                 coarse_distance_mm: float | str = DEFAULT_COARSE_DISTANCE_MM, coarse_crop: str = "pose",
                 canonical_rotation: np.ndarray | None = None, crop_scale: float = 1.4,
                 box_jitter: float = 0.05, occluder_probs=(0.4, 0.3, 0.2, 0.1), p_vertex_colors: float = 0.3,
                 n_color_variants: int = 2, resting: bool = False, render_colors: str = "neutral",
                 light_groups: int = 4, augment: bool = True, with_visibility: bool = False, n_points: int = 1000):
        import trimesh

        if kind not in ("refiner", "coarse"):
            raise ValueError(f"kind must be 'refiner' or 'coarse', got {kind!r}")
        if render_colors not in ("neutral", "mesh"):
            raise ValueError(f"render_colors must be 'neutral' or 'mesh', got {render_colors!r}")
        self.kind = kind
        self.crop_size = (int(crop_size[0]), int(crop_size[1]))
        self.perturbation = perturbation
        self.curriculum = float(curriculum)
        if K is None:
            K0, size0 = _default_camera()
            K, image_size = K0, image_size or size0
        self.K = np.asarray(K, dtype=np.float64)
        if image_size is None:  # principal point at the image centre
            image_size = (int(round(2 * (self.K[0, 2] + 0.5))), int(round(2 * (self.K[1, 2] + 0.5))))
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.distance_mm = tuple(map(float, distance_mm))
        if coarse_distance_mm != "box":
            coarse_distance_mm = float(coarse_distance_mm)
        self.coarse_distance_mm = coarse_distance_mm
        if coarse_crop not in ("pose", "detection"):
            raise ValueError(f"coarse_crop must be 'pose' or 'detection', got {coarse_crop!r}")
        self.coarse_crop = coarse_crop
        self.canonical_rotation = CANONICAL_ROTATION if canonical_rotation is None else np.asarray(canonical_rotation)
        self.crop_scale = float(crop_scale)
        self.box_jitter = float(box_jitter)
        p = np.asarray(occluder_probs, dtype=np.float64)
        self.occluder_probs = p / p.sum()
        self.p_vertex_colors = float(p_vertex_colors) if n_color_variants > 0 else 0.0
        self.n_color_variants = int(n_color_variants)
        self.resting = bool(resting)
        self.render_colors = render_colors
        self.light_groups = max(1, int(light_groups))
        self.augment = bool(augment)
        self.with_visibility = bool(with_visibility)
        self._source = meshes_or_db
        self._seed = seed
        self.rng = np.random.default_rng(seed)

        meshes, pts, syms = {}, [], []
        if hasattr(meshes_or_db, "objects") and hasattr(meshes_or_db, "obj_ids"):  # ObjectDatabase
            for obj in meshes_or_db:
                meshes[obj.obj_id] = obj.mesh
                pts.append(obj.points)
                syms.append(np.asarray(obj.symmetries, dtype=np.float64))
        else:
            for obj_id in sorted(meshes_or_db):
                m = meshes_or_db[obj_id]
                meshes[int(obj_id)] = m
                pts.append(np.asarray(trimesh.sample.sample_surface(m, n_points, seed=0)[0], dtype=np.float64))
                S = None if symmetries is None else symmetries.get(obj_id)
                syms.append(np.eye(4)[None] if S is None else np.asarray(S, dtype=np.float64))
        if not meshes:
            raise ValueError("no objects to train on")
        self.meshes = meshes
        self.obj_ids = np.array(sorted(meshes), dtype=np.int64)
        self.points = np.stack(pts)  # (n_obj, P, 3) mm
        self.symmetries = syms
        hulls = [np.asarray(meshes[o].convex_hull.vertices, dtype=np.float64) for o in self.obj_ids]
        n_hull = max(len(h) for h in hulls)
        # (n_obj, H, 3): convex-hull vertices, padded by repeating the first (exact projected extremes)
        self.hull = np.stack([np.concatenate([h, np.repeat(h[:1], n_hull - len(h), 0)]) for h in hulls])
        self.diameters = np.array([diameter_of(h) for h in hulls])  # mm, over the convex hull (= over the mesh)
        self._renderer = None
        self._pool = None  # earlier observed crops, reused as backgrounds

    # ------------------------------------------------------------------ renderer

    _pickle_instead = "its arguments (TrainingStream)"

    def _make_renderer(self):
        from ..rendering import SceneRenderer

        w, h = self.crop_size
        r = SceneRenderer(self.meshes, w, h)
        if self.n_color_variants > 0:
            vrng = np.random.default_rng(12345)  # fixed: the variants are the same for every seed
            for v in range(self.n_color_variants):
                for obj_id in self.obj_ids:
                    m = self.meshes[int(obj_id)].copy()
                    n = len(m.vertices)
                    base = vrng.uniform(0.15, 0.95, 3)
                    noise = vrng.normal(0.0, vrng.uniform(0.05, 0.2), (n, 1)) + vrng.normal(0.0, 0.04, (n, 3))
                    c = np.clip(base + noise, 0, 1)
                    rgba = np.concatenate([np.round(c * 255), np.full((n, 1), 255)], 1).astype(np.uint8)
                    m.visual = __import__("trimesh").visual.ColorVisuals(m, vertex_colors=rgba)
                    r.add_mesh(int(obj_id) + VARIANT_ID_OFFSET * (v + 1), m)
        return r

    # ------------------------------------------------------------------ sampling

    def sample_cameras(self, B: int) -> np.ndarray:
        """(B, 3, 3) random intrinsics around ``self.K``."""
        rng = self.rng
        Ks = np.repeat(self.K[None], B, 0)
        f = rng.uniform(0.85, 1.15, B)
        Ks[:, 0, 0] *= f
        Ks[:, 1, 1] *= f * rng.uniform(0.98, 1.02, B)
        Ks[:, 0, 2] += rng.uniform(-0.02, 0.02, B) * self.image_size[0]
        Ks[:, 1, 2] += rng.uniform(-0.02, 0.02, B) * self.image_size[1]
        return Ks

    def sample_gt_poses(self, obj_index: np.ndarray, Ks: np.ndarray) -> np.ndarray:
        """(B, 4, 4) random T_cam_obj (mm): depth U(distance_mm), object centre projecting inside
        the central 80 % of the image, orientation uniform (or resting + random view)."""
        rng = self.rng
        B = len(obj_index)
        R = random_rotations(B, rng)
        if self.resting:
            from ..synth.objects import OBJECT_IDS, resting_rotation

            use = rng.random(B) < 0.5
            el = np.radians(rng.uniform(20, 75, B))
            az = rng.uniform(0, 2 * np.pi, B)
            roll = np.radians(rng.uniform(-20, 20, B))
            for b in np.flatnonzero(use):
                obj_id = int(self.obj_ids[obj_index[b]])
                if obj_id not in OBJECT_IDS:
                    continue
                R_world_obj = resting_rotation(obj_id, rng)
                eye = np.array([np.cos(el[b]) * np.cos(az[b]), np.cos(el[b]) * np.sin(az[b]), np.sin(el[b])])
                R_world_cam = look_at(eye, np.zeros(3), up=(0.0, 0.0, 1.0))[:3, :3]
                R_roll = rotation_about_axis(np.array([0.0, 0.0, 1.0]), roll[b:b + 1])[0]
                R[b] = R_roll.T @ R_world_cam.T @ R_world_obj
        z = rng.uniform(*self.distance_mm, B)
        W, H = self.image_size
        u = rng.uniform(0.1 * W, 0.9 * W, B)
        v = rng.uniform(0.1 * H, 0.9 * H, B)
        y = (v - Ks[:, 1, 2]) / Ks[:, 1, 1]
        x = (u - Ks[:, 0, 2] - Ks[:, 0, 1] * y) / Ks[:, 0, 0]
        return make_pose(R, np.stack([x, y, np.ones(B)], 1) * z[:, None])

    def projected_boxes(self, obj_index: np.ndarray, Ks: np.ndarray, T: np.ndarray) -> np.ndarray:
        """(B, 4) pixel-edge bounding boxes (x1, y1, x2, y2) of the projected models."""
        uv = project(transform_points(T, self.hull[obj_index]), Ks)
        return np.concatenate([uv.min(1) + 0.5, uv.max(1) + 0.5], 1)

    def crop_boxes(self, obj_index: np.ndarray, Ks: np.ndarray, T_input: np.ndarray,
                   det_boxes: np.ndarray | None = None) -> np.ndarray:
        """(B, 4) crop boxes (pixel-edge coords) centred on the projection of the input pose's
        origin, half extent from the projected model (or the detection box), x crop_scale,
        fitted to the crop aspect."""
        c = project(T_input[:, None, :3, 3], Ks)[:, 0] + 0.5  # edge coords of the centre
        if det_boxes is None:
            uv = project(transform_points(T_input, self.hull[obj_index]), Ks) + 0.5
            half = np.abs(uv - c[:, None]).max(1)
        else:
            half = (det_boxes[:, 2:] - det_boxes[:, :2]) / 2
        half = np.maximum(half, 2.0)
        boxes = np.concatenate([c - half, c + half], 1)
        w, h = self.crop_size
        return fit_box_to_aspect(boxes, w / h, self.crop_scale)

    def batch(self, B: int) -> dict:
        """B samples: a dict of numpy arrays (see the module docstring).

        observed, rendered: (B, h, w, 3) uint8; observed_mask (visible target pixels),
        rendered_mask: (B, h, w) bool; K_crop, K (full camera): (B, 3, 3); box: (B, 4) crop box in
        the full image (pixel-edge coords); T_input, T_gt: (B, 4, 4) mm; obj_id, obj_index,
        n_occluders: (B,) int64; visib_fract (B,) float if ``with_visibility``.
        """
        rng = self.rng
        w, h = self.crop_size
        n_obj = len(self.obj_ids)
        obj_index = rng.integers(0, n_obj, B)
        Ks = self.sample_cameras(B)
        T_gt = self.sample_gt_poses(obj_index, Ks)
        if self.kind == "refiner":
            T_input = perturb_poses(T_gt, rng, self.perturbation, self.curriculum)
            boxes = self.crop_boxes(obj_index, Ks, T_input)
        else:
            det = self.projected_boxes(obj_index, Ks, T_gt)
            size = det[:, 2:] - det[:, :2]
            det = det + np.concatenate([size, size], 1) * rng.normal(0, self.box_jitter, (B, 4))
            det[:, 2:] = np.maximum(det[:, 2:], det[:, :2] + 2.0)
            dist = (depth_from_box(Ks, det, self.diameters[obj_index]) if self.coarse_distance_mm == "box"
                    else self.coarse_distance_mm)
            T_input = canonical_pose(Ks, det, dist, self.canonical_rotation)
            boxes = self.crop_boxes(obj_index, Ks, T_input, det if self.coarse_crop == "detection" else None)
        K_crop = crop_intrinsics(Ks, boxes, (w, h))

        # --- occluders: other objects in front of / beside the target, near it in the crop
        n_occ = rng.choice(len(self.occluder_probs), size=B, p=self.occluder_probs)
        n_tot = int(n_occ.sum())
        occ_of = np.repeat(np.arange(B), n_occ)
        occ_index = rng.integers(0, n_obj, n_tot)
        z_occ = T_gt[occ_of, 2, 3] * rng.uniform(0.75, 1.2, n_tot)
        phi = rng.uniform(0, 2 * np.pi, n_tot)
        r = rng.uniform(0.45, 1.2, n_tot)
        c_px = (boxes[occ_of, :2] + boxes[occ_of, 2:]) / 2 - 0.5
        half_px = (boxes[occ_of, 2:] - boxes[occ_of, :2]) / 2
        uv = c_px + np.stack([np.cos(phi), np.sin(phi)], 1) * r[:, None] * half_px
        Ko = Ks[occ_of]
        yo = (uv[:, 1] - Ko[:, 1, 2]) / Ko[:, 1, 1]
        xo = (uv[:, 0] - Ko[:, 0, 2] - Ko[:, 0, 1] * yo) / Ko[:, 0, 0]
        T_occ = make_pose(random_rotations(n_tot, rng), np.stack([xo, yo, np.ones(n_tot)], 1) * z_occ[:, None])

        # instances in tile order: target of sample b, then its occluders
        tiles = np.concatenate([np.arange(B), occ_of])
        is_target = np.concatenate([np.ones(B, bool), np.zeros(n_tot, bool)])
        order = np.argsort(tiles, kind="stable")
        tiles, is_target = tiles[order], is_target[order]
        all_index = np.concatenate([obj_index, occ_index])[order]
        all_T = np.concatenate([T_gt, T_occ])[order]
        target_pos = np.flatnonzero(is_target)  # (B,) position of each sample's target
        n_inst = len(tiles)

        # --- colours: flat random colours, or a vertex-colour-noise copy of the mesh
        colors = random_colors(rng, n_inst)  # greys, browns, saturated colours (T-LESS-like and beyond)
        render_ids = self.obj_ids[all_index].copy()
        if self.p_vertex_colors > 0:
            use_var = rng.random(n_inst) < self.p_vertex_colors
            var = rng.integers(1, self.n_color_variants + 1, n_inst)
            render_ids[use_var] += VARIANT_ID_OFFSET * var[use_var]
            colors[use_var] = np.nan

        # --- observed crops, in light groups
        renderer = self.renderer
        rgb, inst = render_in_light_groups(renderer, rng, K_crop, render_ids, all_T, tiles, (w, h), colors,
                                           self.light_groups, intensity=(0.35, 1.0), ambient=(0.05, 0.5))
        observed_mask = inst == target_pos[:, None, None]
        foreground = inst >= 0

        # --- rendered crops at the input pose
        ren = renderer.render_crops(K_crop, self.obj_ids[obj_index], T_input, (w, h),
                                    colors=np.tile(NEUTRAL_COLOR, (B, 1)) if self.render_colors == "neutral" else None)
        rendered = ren.rgb
        rendered_mask = ren.instance >= 0

        observed = self._compose(rgb, foreground)
        self._pool = observed[rng.permutation(B)[: min(B, 64)]].copy()
        out = {
            "observed": observed, "rendered": rendered, "observed_mask": observed_mask,
            "rendered_mask": rendered_mask, "K_crop": K_crop, "K": Ks, "box": boxes, "T_input": T_input,
            "T_gt": T_gt, "obj_id": self.obj_ids[obj_index], "obj_index": obj_index.astype(np.int64),
            "n_occluders": n_occ.astype(np.int64),
        }
        if self.with_visibility:
            sil = renderer.render_crops(K_crop, self.obj_ids[obj_index], T_gt, (w, h), with_rgb=False).instance >= 0
            out["visib_fract"] = observed_mask.sum((1, 2)) / np.maximum(sil.sum((1, 2)), 1)
        return out

    # ------------------------------------------------------------------ compositing

    def _compose(self, rgb: np.ndarray, foreground: np.ndarray) -> np.ndarray:
        """Backgrounds behind, low-frequency colour noise on the objects, image augmentations.

        Random numbers are drawn for the whole batch; the pixels are processed one sample at a
        time with OpenCV (small arrays that stay in cache: ~10x faster than whole-batch numpy)."""
        import cv2

        rng = self.rng
        B, h, w, _ = rgb.shape
        bank = noise_bank(h, w)
        field = rng.uniform(0.8, 1.2, (B, 4, 5, 3)).astype(np.float32)  # colour noise on the objects
        kinds = rng.integers(0, 4 if self._pool is not None else 3, B)
        c0 = rng.uniform(0, 255, (B, 3))
        c1 = rng.uniform(0, 255, (B, 3))
        a = rng.uniform(0, 2 * np.pi, B)
        grid_hw = rng.integers(2, 8, (B, 2))
        grids = rng.uniform(0, 255, (B, 7, 7, 3)).astype(np.float32)
        pool_pick = rng.integers(0, len(self._pool) if self._pool is not None else 1, B)
        flips = rng.random((B, 2)) < 0.5
        shifts = np.stack([rng.integers(0, h, B), rng.integers(0, w, B)], 1)
        noise_at = np.stack([rng.integers(0, h, (B, 2)), rng.integers(0, w, (B, 2))], 2)  # (B, 2, yx)
        bg_noise = rng.uniform(0, 25, B)  # std, texture of the background
        img_noise = rng.uniform(0, 8, B) if self.augment else np.zeros(B)  # std, sensor noise
        contrast = rng.uniform(0.7, 1.3, B)
        gain = rng.uniform(0.9, 1.1, (B, 3))
        bright = rng.normal(0, 15, B)
        blur = rng.random(B) < 0.3
        sigma = rng.uniform(0.3, 1.2, B)

        out = np.empty((B, h, w, 3), np.uint8)
        for b in range(B):
            img = rgb[b].astype(np.float32)
            multiply_field(img, field[b], cv2.INTER_LINEAR)
            k = kinds[b]
            if k == 0:
                bg = flat_background(h, w, c0[b])
            elif k == 1:
                bg = gradient_background(h, w, c0[b], c1[b], a[b])
            elif k == 2:
                gh, gw = grid_hw[b]
                bg = grid_background(grids[b, :gh, :gw], h, w, cv2.INTER_LINEAR)
            else:
                src = self._pool[pool_pick[b]]
                if flips[b, 0]:
                    src = src[:, ::-1]
                if flips[b, 1]:
                    src = src[::-1]
                bg = np.roll(src, tuple(shifts[b]), (0, 1)).astype(np.float32)
            y, x = noise_at[b, 0]
            paste_background(img, bg, foreground[b], bank[y:y + h, x:x + w], bg_noise[b])
            if img_noise[b] > 0:
                y, x = noise_at[b, 1]
                cv2.scaleAdd(bank[y:y + h, x:x + w], float(img_noise[b]), img, dst=img)
            if self.augment:
                img = photometric(img, contrast[b], gain[b], bright[b], 0.5)  # + 0.5: round below
                if blur[b]:
                    img = cv2.GaussianBlur(img, (0, 0), float(sigma[b]))
            else:
                img += 0.5
            np.clip(img, 0, 255, out=img)
            out[b] = img
        return out


# ---------------------------------------------------------------------- torch wrapper

def _torch_iterable_base():
    try:
        from torch.utils.data import IterableDataset

        return IterableDataset
    except ImportError:  # pragma: no cover - torch is a dependency of training
        return object


class TrainingStream(_torch_iterable_base()):
    """An endless (or ``n_batches``-long per worker) torch IterableDataset of whole batches.

    Each worker process builds its own :class:`SampleGenerator` (and OpenGL context) from
    ``source`` and ``generator_kwargs``, seeded by (seed, worker id): workers never repeat each
    other. Use with ``batch_size=None`` (see :func:`make_loader`); batches come out as dicts of
    torch tensors. ``curriculum`` is fixed for the life of the workers: make a new loader to change it.
    """

    def __init__(self, source, batch_size: int, seed: int = 0, n_batches: int | None = None, **generator_kwargs):
        super().__init__()
        self.source = source
        self.batch_size = int(batch_size)
        self.seed = int(seed)
        self.n_batches = n_batches
        self.generator_kwargs = generator_kwargs

    def __iter__(self):
        try:
            from torch.utils.data import get_worker_info

            info = get_worker_info()
        except ImportError:  # pragma: no cover
            info = None
        worker = 0 if info is None else info.id
        gen = SampleGenerator(self.source, seed=np.random.SeedSequence([self.seed, worker]), **self.generator_kwargs)
        if info is not None:
            # a worker's iterator is dropped, not closed, at shutdown: free the OpenGL context
            # before the interpreter tears down (else Mesa/LLVM threads may abort the process)
            atexit.register(gen.close)
        try:
            i = 0
            while self.n_batches is None or i < self.n_batches:
                yield gen.batch(self.batch_size)
                i += 1
        finally:
            gen.close()


def _worker_init(_worker_id: int, output: dict | None = None) -> None:
    """One llvmpipe thread and one torch thread per rendering worker (2-core machines); warnings
    printed as the command prints them (``output``: :func:`cosy_cli.console.worker_state`).

    Also ends the worker with ``os._exit(0)`` once Python's exit handlers have run (its queues
    are flushed by then): interpreter teardown with a live Mesa/LLVM context sometimes aborts
    ("terminate called without an active exception"), which torch reports as a dead worker."""
    atexit.register(os._exit, 0)  # registered first: runs last, after the generators are closed
    from .. import console

    console.enter_worker(output)
    os.environ.setdefault("LP_NUM_THREADS", "1")
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # pragma: no cover
        pass


def make_loader(stream: TrainingStream, num_workers: int = 2, prefetch_factor: int = 2):
    """A torch DataLoader over ``stream`` with ``num_workers`` spawned rendering workers (EGL
    contexts do not survive fork); 0 workers renders in the calling process."""
    from torch.utils.data import DataLoader

    kw = {}
    if num_workers > 0:
        import functools

        from .. import console

        init = functools.partial(_worker_init, output=console.worker_state())
        kw = dict(multiprocessing_context="spawn", worker_init_fn=init, persistent_workers=True,
                  prefetch_factor=prefetch_factor)
    return DataLoader(stream, batch_size=None, num_workers=num_workers, **kw)


def synthetic_source(n_points: int = 1000):
    """({obj_id: mesh}, {obj_id: symmetries (S, 4, 4)}) of the fixed synthetic objects, for
    ``SampleGenerator(meshes, symmetries=syms, resting=True)``."""
    from ..objects.symmetries import symmetry_set
    from ..synth.objects import object_meshes, symmetry_transforms

    meshes = object_meshes()
    syms = {o: symmetry_set(*symmetry_transforms(o)) for o in meshes}
    return meshes, syms


__all__ = ["SampleGenerator", "TrainingStream", "make_loader", "canonical_pose", "depth_from_box", "perturb_poses",
           "Perturbation", "DEFAULT_PERTURBATION", "CANONICAL_ROTATION", "synthetic_source", "RendererOwner",
           "hsv_to_rgb", "random_colors", "random_light_dirs", "render_in_light_groups", "noise_bank", "multiply_field", "flat_background",
           "gradient_background", "grid_background", "paste_background", "photometric"]
