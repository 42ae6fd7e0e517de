"""Training images for the detector, rendered on the fly: random scenes of a dataset's objects
with domain randomisation, rendered straight at the network's input size.

One image (:meth:`DetectionSampleGenerator.batch`):

- objects: ``min_objects`` (1)..``max_objects`` instances of the dataset's objects (distinct while possible),
  drawn with probabilities ``class_weights`` (default uniform: class-balanced sampling can favour
  the objects the detector finds worst); with probability ``p_pair`` the image holds one of the
  ``confusable`` pairs of look-alike objects (picked with probability proportional to its
  weight; hard examples), placed side by side on the table (or near each other, at a similar
  depth, when floating);
- layout, "table" (probability ``p_table``): the objects rest on the plane z = 0 (each on a
  face of its convex hull picked with probability proportional to the face's area, a random
  yaw) at random places in a disc (footprints kept about apart: from spread out to cluttered),
  seen by a camera ``camera_distance`` (300-1100) mm from the cluster at 12-85 deg elevation, any azimuth, a roll of
  +-15 deg, looking at a point jittered about the cluster (so objects also fall partly outside
  the image); a table (a 1400 mm box, random colour) is drawn under them with probability 0.85.
  "Floating": every object at a uniformly random orientation, depth ``float_depth`` (250-1200) mm, centre
  projecting anywhere in the image +-10 %, free to overlap (heavy occlusion).
- camera: the dataset's intrinsics (``camera.json``) scaled to the input size, focal x U(0.9, 1.1);
- clutter (optional): up to ``max_distractors`` unlabelled ``distractors`` meshes placed like the
  objects (random colours), hiding them as real clutter does;
- appearance: random flat object colours (greys, browns, any hue; with ``p_mesh_colors`` > 0 an
  instance of a coloured mesh keeps the mesh's own colours with that probability), one light per group of
  images (direction, intensity, ambient random), smooth colour noise on the objects, a random
  background (flat, gradient, blobs, coarse noise or random rectangles and discs; with ``photos``, a
  random window of one of those photographs with probability ``p_photo``) where nothing is drawn,
  contrast / brightness / per-channel gain (``gain_jitter``), optionally saturation, sensor noise,
  blur (``blur``: probability, sigma range).

Ground truth, as the BOP toolkit's ``bbox_visib``: the box of each instance's visible pixels;
instances with ``visib_fract`` < ``min_visib`` (visible / silhouette pixels in the image, the
silhouette rendered alone at half resolution) or fewer than ``min_pixels`` visible pixels are
returned as "ignore" boxes (no loss inside them on their class channel).

Boxes are [x1, y1, x2, y2] in continuous coordinates of the input image whose pixel (u, v)
covers [u, u + 1) x [v, v + 1): the box of a mask with columns x_min..x_max is x1 = x_min,
x2 = x_max + 1.

Probe points (optional, ``probe_points``: {obj_id: [(n_k, 3) points in the object's frame, mm],
e.g. the regions that tell a look-alike pair apart}): each kept instance of such an object also gets
the number of image pixels where its probe points, placed with the instance's pose, are seen
(:func:`visible_probe_pixels`: inside the image and not behind the rendered depth by more than a
tolerance), one count per probe set, in ``batch()["probe_px"]``. Without probe points the images
and the random stream are those of before.

Deterministic under ``seed``. The OpenGL renderer is created on first use: build generators
inside worker processes (:class:`DetectionStream` does).
"""

from __future__ import annotations

import atexit
import math

import numpy as np

from ..geometry.poses import invert, look_at, make_pose
from ..geometry.rotations import random_rotations, rotation_about_axis
from ..training.data import (
    RendererOwner, flat_background, gradient_background, grid_background, hsv_to_rgb, multiply_field, noise_bank,
    paste_background, photometric, random_colors, render_in_light_groups,
)

TABLE_ID = 0
TABLE_SIZE_MM = 1400.0


def scaled_intrinsics(K: np.ndarray, image_size, input_size) -> np.ndarray:
    """K (3x3, pixel centres at integers) of ``image_size`` (w, h) resized to ``input_size``."""
    sx, sy = input_size[0] / image_size[0], input_size[1] / image_size[1]
    K = np.asarray(K, dtype=np.float64)
    out = K.copy()
    out[0, 0], out[0, 1], out[1, 1] = K[0, 0] * sx, K[0, 1] * sx, K[1, 1] * sy
    out[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    out[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return out


def _rotation_to_down(n: np.ndarray) -> np.ndarray:
    """R (3, 3) with R @ n = (0, 0, -1) for the unit vector n."""
    target = np.array([0.0, 0.0, -1.0])
    c = float(np.clip(n @ target, -1.0, 1.0))
    if c > 1 - 1e-9:
        return np.eye(3)
    if c < -1 + 1e-9:
        return np.diag([1.0, -1.0, -1.0])
    axis = np.cross(n, target)
    return rotation_about_axis(axis / np.linalg.norm(axis), np.array([math.acos(c)]))[0]


class _RestPoses:
    """Resting faces of one object: the convex hull's faces grouped by normal, picked with
    probability proportional to their area."""

    def __init__(self, mesh):
        hull = mesh.convex_hull
        normals = np.asarray(hull.face_normals)
        areas = np.asarray(hull.area_faces)
        keys, inv = np.unique(np.round(normals, 3), axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        area = np.bincount(inv, weights=areas, minlength=len(keys))
        n = np.stack([np.bincount(inv, weights=normals[:, k] * areas, minlength=len(keys)) for k in range(3)], 1)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        self.rotations = np.stack([_rotation_to_down(v) for v in n])
        self.prob = area / area.sum()
        self.hull = np.asarray(hull.vertices, dtype=np.float64)

    def sample(self, rng: np.random.Generator) -> tuple[np.ndarray, float, float]:
        """(R_world_obj (3, 3), lift mm so the lowest point is at z = 0, footprint radius mm)."""
        R = self.rotations[rng.choice(len(self.prob), p=self.prob)]
        yaw = rotation_about_axis(np.array([0.0, 0.0, 1.0]), np.array([rng.uniform(0, 2 * np.pi)]))[0]
        R = yaw @ R
        p = self.hull @ R.T
        return R, -float(p[:, 2].min()), float(np.linalg.norm(p[:, :2], axis=1).max())


DISTRACTOR_ID0 = 900_000  # renderer ids of clutter meshes (their own ids + this), apart from the objects'
CLUTTER_ID0 = 910_000  # renderer ids of the random clutter shapes (clutter_meshes), apart from both


def clutter_meshes(n: int = 32, seed: int = 0) -> dict:
    """{k: trimesh.Trimesh (mm)} for k = 1..n: unlabelled clutter of many shapes and sizes, as real
    scenes hold (boxes, cylinders, cones, spheres, capsules, rings and lumpy convex hulls; each side
    25-400 mm, log-uniform), the same for a given seed."""
    import trimesh

    rng = np.random.default_rng([seed, 31337])
    out = {}
    for k in range(1, n + 1):
        size = np.exp(rng.uniform(np.log(25.0), np.log(400.0), 3))
        kind = k % 7
        if kind == 0:
            m = trimesh.creation.box(extents=size)
        elif kind == 1:
            m = trimesh.creation.cylinder(radius=size[0] / 2, height=size[2], sections=24)
        elif kind == 2:
            m = trimesh.creation.cone(radius=size[0] / 2, height=size[2], sections=24)
        elif kind == 3:
            m = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
            m.apply_scale(size)
        elif kind == 4:
            m = trimesh.creation.capsule(height=size[2], radius=size[0] / 4, count=[12, 12])
        elif kind == 5:
            m = trimesh.creation.annulus(r_min=size[0] / 4, r_max=size[0] / 2, height=size[2] / 3, sections=24)
        else:
            m = trimesh.PointCloud(rng.normal(0, 1, (24, 3)) * size / 4).convex_hull
        m.apply_translation(-m.bounds.mean(0))
        out[k] = m
    return out


def photo_window(photo: np.ndarray, h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """(h, w, 3) float32: a random window of ``photo`` ((H, W, 3) uint8) with the output's aspect,
    25-100 % of the largest such window (log-uniform), mirrored half the time, resized to (w, h)."""
    import cv2

    H, W = photo.shape[:2]
    full = min(W, H * w / h)  # width of the largest window of aspect w / h
    ww = full * float(np.exp(rng.uniform(np.log(0.25), 0.0)))
    wh = ww * h / w
    x0, y0 = rng.uniform(0, W - ww), rng.uniform(0, H - wh)
    x0i, y0i = int(x0), int(y0)
    x1i, y1i = max(x0i + 1, min(W, int(round(x0 + ww)))), max(y0i + 1, min(H, int(round(y0 + wh))))
    win = photo[y0i:y1i, x0i:x1i]
    if rng.random() < 0.5:
        win = win[:, ::-1]
    return cv2.resize(np.ascontiguousarray(win), (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)


class DetectionSampleGenerator(RendererOwner):
    """Random rendered training images of the objects ``meshes`` ({obj_id: trimesh.Trimesh, mm}).

    K, image_size: the dataset camera (3x3 px; (w, h)); input_size: (w, h) rendered. obj_ids:
    the class order (default sorted ids). See the module docstring for the rest."""

    def __init__(self, meshes: dict, K: np.ndarray, image_size, input_size=(320, 240), seed=0, *,
                 obj_ids=None, max_objects: int = 10, p_table: float = 0.75, min_visib: float = 0.1,
                 min_pixels: int = 12, light_groups: int = 4, smooth: bool = True, class_weights=None,
                 confusable=None, p_pair: float = 0.0, probe_points=None, p_mesh_colors: float = 0.0,
                 distractors: dict | None = None, max_distractors: int = 0, gain_jitter: float = 0.1,
                 saturation=(1.0, 1.0), blur=(0.25, 0.3, 1.0), min_objects: int = 1, backdrop=(0.0, 0, 0),
                 photos=None, p_photo: float = 0.0, p_photo_texture: float = 0.0,
                 camera_distance=(300.0, 1100.0), float_depth=(250.0, 1200.0)):
        self.meshes = {int(k): v for k, v in meshes.items()}
        self.obj_ids = np.array(sorted(self.meshes) if obj_ids is None else [int(o) for o in obj_ids], np.int64)
        self.K = np.asarray(K, dtype=np.float64)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.input_size = (int(input_size[0]), int(input_size[1]))
        self.K_input = scaled_intrinsics(self.K, self.image_size, self.input_size)
        self.rng = np.random.default_rng(seed)
        self.max_objects = int(max_objects)
        self.min_objects = max(1, min(int(min_objects), self.max_objects))
        self.p_table = float(p_table)
        self.min_visib = float(min_visib)
        self.min_pixels = int(min_pixels)
        self.light_groups = max(1, int(light_groups))
        self.smooth = smooth
        self.class_p = normalised_weights(class_weights, self.obj_ids)
        self.pairs, self.pair_p = pair_table(confusable, self.obj_ids)
        self.p_pair = float(p_pair) if len(self.pairs) else 0.0
        # distractors: unlabelled meshes ({id: mesh}, ids apart from the objects') placed among them as clutter
        self.distractors = {int(k): v for k, v in (distractors or {}).items()}
        self.distractor_ids = np.array(sorted(self.distractors), np.int64)
        self.max_distractors = int(max_distractors) if len(self.distractor_ids) else 0
        self.gain_jitter = float(gain_jitter)  # per-channel gain U(1 -+ this) (white balance)
        self.saturation = (float(saturation[0]), float(saturation[1]))  # (1, 1): no saturation change
        self.blur = tuple(float(v) for v in blur)  # (probability, sigma range) of a Gaussian blur
        # (probability, fewest, most): a backdrop of clutter behind the objects instead of a flat background
        self.backdrop = (float(backdrop[0]), int(backdrop[1]), int(backdrop[2])) if len(self.distractor_ids) \
            else (0.0, 0, 0)
        # background photographs ([(h, w, 3) uint8 RGB]): a random window of one, with probability p_photo
        self.photos = list(photos or [])
        self.p_photo = float(p_photo) if self.photos else 0.0
        # with photos: each unlabelled surface (table, clutter) wears a window of one, shaded, with this probability
        self.p_photo_texture = float(p_photo_texture) if self.photos else 0.0
        every = {**self.meshes, **self.distractors}
        self.rest = {int(o): _RestPoses(every[int(o)]) for o in list(self.obj_ids) + list(self.distractor_ids)}
        self.radius = {int(o): float(np.linalg.norm(r.hull, axis=1).max()) for o, r in self.rest.items()}
        # instances of meshes with their own colours keep them with this probability (the scorer's data)
        self.p_mesh_colors = float(p_mesh_colors)
        # mm: the camera's distance from a table scene's cluster, the depth range of floating objects
        self.camera_distance = (float(camera_distance[0]), float(camera_distance[1]))
        self.float_depth = (float(float_depth[0]), float(float_depth[1]))
        self.coloured = {int(o): bool(getattr(self.meshes[int(o)].visual, "defined", False)) for o in self.obj_ids}
        self.probe_points = {int(o): [np.asarray(p, np.float64).reshape(-1, 3) for p in sets]
                             for o, sets in (probe_points or {}).items()}
        self._renderer = None

    # ------------------------------------------------------------------ renderer
    _pickle_instead = "DetectionStream"

    def _make_renderer(self):
        from ..rendering import SceneRenderer
        from ..synth.scenes import table_mesh

        meshes = dict(self.meshes)
        meshes.update(self.distractors)
        meshes[TABLE_ID] = table_mesh()
        w, h = self.input_size
        return SceneRenderer(meshes, w, h, znear=10.0, zfar=20_000.0, smooth=self.smooth)

    # ------------------------------------------------------------------ scenes
    def _choose(self, n: int) -> tuple[np.ndarray, bool]:
        """(n object ids, whether the first two are a confusable pair to place side by side)."""
        rng = self.rng
        if self.p_pair > 0 and rng.random() < self.p_pair:
            pair = self.pairs[rng.choice(len(self.pairs), p=self.pair_p)]
            pair = pair[rng.permutation(2)]
            n = max(n, 2)
            rest = self.obj_ids[~np.isin(self.obj_ids, pair)]
            p = self.class_p[~np.isin(self.obj_ids, pair)] if self.class_p is not None else None
            p = None if p is None else p / p.sum()
            k = min(n - 2, len(rest))
            first = rng.choice(rest, size=k, replace=False, p=p) if k else rest[:0]
            extra = rng.choice(self.obj_ids, size=max(0, n - 2 - k), p=self.class_p)
            return np.concatenate([pair, first, extra]).astype(np.int64), True
        if self.class_p is None:
            first = rng.permutation(self.obj_ids)[:min(n, len(self.obj_ids))]
            extra = rng.choice(self.obj_ids, size=max(0, n - len(self.obj_ids)))
        else:
            first = rng.choice(self.obj_ids, size=min(n, len(self.obj_ids)), replace=False, p=self.class_p)
            extra = rng.choice(self.obj_ids, size=max(0, n - len(self.obj_ids)), p=self.class_p)
        return np.concatenate([first, extra]).astype(np.int64), False

    def _table_scene(self, ids: np.ndarray, pair: bool = False):
        """(T_cam_obj (n, 4, 4), T_cam_world (4, 4), kept ids) of objects resting on a table;
        pair: the second object is placed touching-close to the first."""
        rng = self.rng
        n = len(ids)
        Rs, lifts, radii = zip(*(self.rest[int(o)].sample(rng) for o in ids))
        radii = np.array(radii)
        fill = rng.uniform(0.15, 0.6)
        disc = max(60.0, math.sqrt(float(np.sum(np.pi * radii ** 2)) / fill / math.pi))
        centres = np.zeros((n, 2))
        keep = np.ones(n, bool)
        slack = rng.uniform(0.75, 1.0)  # footprint radii overestimate: a little overlap of circles is fine
        for i in range(n):
            for attempt in range(60):
                if pair and i == 1 and attempt < 30:  # side by side with the first object
                    r = slack * (radii[0] + radii[1]) * rng.uniform(1.0, 1.25) * (1 + attempt / 30)
                    phi = rng.uniform(0, 2 * np.pi)
                    c = centres[0] + np.array([r * math.cos(phi), r * math.sin(phi)])
                else:
                    r = disc * math.sqrt(rng.uniform()) * (1 + attempt / 30)
                    phi = rng.uniform(0, 2 * np.pi)
                    c = np.array([r * math.cos(phi), r * math.sin(phi)])
                if i == 0 or np.all(np.linalg.norm(centres[:i][keep[:i]] - c, axis=1)
                                    >= slack * (radii[:i][keep[:i]] + radii[i])):
                    break
            else:
                keep[i] = False
            centres[i] = c
        T_world_obj = make_pose(np.stack(Rs), np.concatenate([centres, np.array(lifts)[:, None]], 1))[keep]
        centre = centres[keep].mean(0)
        spread = float(np.ptp(centres[keep], axis=0).max()) / 2 + 50.0 if keep.sum() > 1 else 60.0
        dist = rng.uniform(*self.camera_distance)
        el = math.radians(rng.uniform(12.0, 85.0))
        az = rng.uniform(0, 2 * np.pi)
        target = np.array([*(centre + rng.normal(0, 0.5 * spread, 2)), rng.uniform(0, 40)])
        eye = target + dist * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        T_world_cam = look_at(eye, target, up=(0.0, 0.0, 1.0))
        roll = rotation_about_axis(np.array([0.0, 0.0, 1.0]), np.array([math.radians(rng.uniform(-15, 15))]))[0]
        T_world_cam[:3, :3] = T_world_cam[:3, :3] @ roll
        T_cam_world = invert(T_world_cam)
        return T_cam_world[None] @ T_world_obj, T_cam_world, ids[keep]

    def _floating_scene(self, ids: np.ndarray, K: np.ndarray, pair: bool = False):
        rng = self.rng
        n = len(ids)
        w, h = self.input_size
        z = rng.uniform(*self.float_depth, n)
        u = rng.uniform(-0.1 * w, 1.1 * w, n)
        v = rng.uniform(-0.1 * h, 1.1 * h, n)
        if pair and n >= 2:  # the second object next to the first, at about its depth
            z[1] = z[0] * rng.uniform(0.9, 1.1)
            span = (self.radius[int(ids[0])] + self.radius[int(ids[1])]) * K[0, 0] / z[0]
            phi = rng.uniform(0, 2 * np.pi)
            u[1] = u[0] + span * rng.uniform(0.6, 1.0) * math.cos(phi)
            v[1] = v[0] + span * rng.uniform(0.6, 1.0) * math.sin(phi)
        y = (v - K[1, 2]) / K[1, 1]
        x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
        return make_pose(random_rotations(n, rng), np.stack([x, y, np.ones(n)], 1) * z[:, None])

    def _add_backdrop(self, ids: np.ndarray, T: np.ndarray, K: np.ndarray):
        """Clutter behind the scene: distractors at random orientations, 0.1-3 m behind the farthest
        labelled object, spread over the image (they hide whatever background would be pasted)."""
        rng = self.rng
        w, h = self.input_size
        labelled = np.isin(ids, self.obj_ids)
        far = float(T[labelled, 2, 3].max()) if labelled.any() else 600.0
        n = int(rng.integers(self.backdrop[1], self.backdrop[2] + 1))
        z = far + rng.uniform(100.0, 3000.0, n)
        u, v = rng.uniform(-0.1 * w, 1.1 * w, n), rng.uniform(-0.1 * h, 1.1 * h, n)
        y = (v - K[1, 2]) / K[1, 1]
        x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
        Tb = make_pose(random_rotations(n, rng), np.stack([x, y, np.ones(n)], 1) * z[:, None])
        return (np.concatenate([ids, rng.choice(self.distractor_ids, n)]).astype(np.int64),
                np.concatenate([T, Tb]))

    def _colors(self, n: int) -> np.ndarray:
        return random_colors(self.rng, n, p=(0.5, 0.2, 0.3), brown_hue=(0.04, 0.13), brown_sat=(0.2, 0.65),
                             sat=(0.2, 0.9), val=(0.3, 0.95))

    # ------------------------------------------------------------------ batches
    def batch(self, B: int) -> dict:
        """B images: {"images": (B, H, W, 3) uint8, "boxes": [ (n_b, 4) xyxy input px ],
        "labels": [ (n_b,) class indices ], "ignore_boxes", "ignore_labels": the same for
        barely visible instances, "visib_fract": [ (n_b,) ], "T_cam_obj": [ (n_b, 4, 4) mm ] of the
        kept instances, "K": (B, 3, 3) the images' intrinsics (input px), "instance": (B, H, W)
        int instance map (-1: nothing drawn), "instance_ids": [ (n_b,) ] the values of the kept
        instances in it (the visible mask of box j of image b is instance[b] == instance_ids[b][j])}."""
        rng = self.rng
        w, h = self.input_size
        ids_all, T_all, tile_all, Ks, is_table = [], [], [], [], []
        for b in range(B):
            K = self.K_input.copy()
            f = rng.uniform(0.9, 1.1)
            K[0, 0] *= f
            K[1, 1] *= f
            K[0, 1] *= f
            Ks.append(K)
            ids, pair = self._choose(int(rng.integers(self.min_objects, self.max_objects + 1)))
            if self.max_distractors:  # drawn only then: the detector's random stream stays as it was
                nd = int(rng.integers(0, self.max_distractors + 1))
                ids = np.concatenate([ids, rng.choice(self.distractor_ids, nd)]).astype(np.int64)
            if rng.random() < self.p_table:
                T, T_cam_world, ids = self._table_scene(ids, pair)
                if rng.random() < 0.85:
                    ids = np.concatenate([ids, [TABLE_ID]])
                    T = np.concatenate([T, T_cam_world[None]])
            else:
                T = self._floating_scene(ids, K, pair)
            if self.backdrop[0] > 0 and rng.random() < self.backdrop[0]:  # drawn only then
                ids, T = self._add_backdrop(ids, T, K)
            ids_all.append(ids)
            T_all.append(T)
            tile_all.append(np.full(len(ids), b))
            is_table.append((ids == TABLE_ID) | np.isin(ids, self.distractor_ids))  # unlabelled: table, clutter
        ids = np.concatenate(ids_all).astype(np.int64)
        T = np.concatenate(T_all)
        tiles = np.concatenate(tile_all)
        is_table = np.concatenate(is_table)
        Ks = np.stack(Ks)
        n = len(ids)
        colors = self._colors(n)
        if is_table.any():  # table colours as cosy synth draws them, a little wider
            k = int(is_table.sum())
            colors[is_table] = hsv_to_rgb(rng.uniform(0, 1, k), rng.uniform(0, 0.6, k), rng.uniform(0.1, 0.95, k))
        if self.p_mesh_colors > 0:  # drawn only then: the detector's random stream stays as it was
            own = (rng.random(n) < self.p_mesh_colors) & ~is_table
            own &= np.array([self.coloured.get(int(o), False) for o in ids], bool)
            colors[own] = np.nan

        r = self.renderer
        probes = bool(self.probe_points)
        rendered = render_in_light_groups(r, rng, Ks, ids, T, tiles, (w, h), colors, self.light_groups,
                                          intensity=(0.35, 0.95), ambient=(0.1, 0.5), with_depth=probes)
        rgb, inst = rendered[:2]
        n_sets = max((len(v) for v in self.probe_points.values()), default=0)
        probe_px = np.full((n, n_sets), -1, np.int64)
        if probes:
            for o, sets in self.probe_points.items():
                sel = np.flatnonzero(ids == o)
                for k, pts in enumerate(sets):
                    if len(sel) and len(pts):
                        probe_px[sel, k] = visible_probe_pixels(Ks[tiles[sel]], T[sel], pts, rendered[2][tiles[sel]])

        # silhouettes of the objects alone, at half resolution (visible fraction only)
        objs = np.flatnonzero(~is_table)
        hw, hh = max(1, w // 2), max(1, h // 2)
        Kh = np.array([scaled_intrinsics(K, (w, h), (hw, hh)) for K in Ks])
        sil = r.render_crops(Kh[tiles[objs]], ids[objs], T[objs], (hw, hh), with_rgb=False).instance >= 0
        full_px = np.zeros(n)
        full_px[objs] = sil.reshape(len(objs), -1).sum(1) * (w * h) / (hw * hh)

        out = {"boxes": [], "labels": [], "ignore_boxes": [], "ignore_labels": [], "visib_fract": [], "T_cam_obj": [],
               "K": Ks, "instance": inst, "instance_ids": []}
        if probes:
            out["probe_px"] = []
        class_of = {int(o): k for k, o in enumerate(self.obj_ids)}
        for b in range(B):
            i0, i1 = np.searchsorted(tiles, [b, b + 1])
            members = [i for i in range(i0, i1) if not is_table[i]]
            boxes, labels, ign, ign_l, vis, kept = [], [], [], [], [], []
            if members:
                m = inst[b][None] == np.array(members)[:, None, None]  # (k, h, w)
                px = m.sum((1, 2))
                rows, cols = m.any(2), m.any(1)
                for k, i in enumerate(members):
                    if px[k] == 0:
                        continue
                    ys, xs = np.flatnonzero(rows[k]), np.flatnonzero(cols[k])
                    box = [xs[0], ys[0], xs[-1] + 1, ys[-1] + 1]
                    vf = min(1.0, px[k] / max(full_px[i], 1.0))
                    if vf < self.min_visib or px[k] < self.min_pixels:
                        ign.append(box)
                        ign_l.append(class_of[int(ids[i])])
                    else:
                        boxes.append(box)
                        labels.append(class_of[int(ids[i])])
                        vis.append(vf)
                        kept.append(i)
            out["boxes"].append(np.array(boxes, np.float64).reshape(-1, 4))
            out["labels"].append(np.array(labels, np.int64))
            out["ignore_boxes"].append(np.array(ign, np.float64).reshape(-1, 4))
            out["ignore_labels"].append(np.array(ign_l, np.int64))
            out["visib_fract"].append(np.array(vis))
            out["T_cam_obj"].append(T[np.array(kept, np.int64)].reshape(len(kept), 4, 4))
            out["instance_ids"].append(np.array(kept, np.int64))
            if probes:
                out["probe_px"].append(probe_px[np.array(kept, np.int64)].reshape(len(kept), n_sets))
        if self.p_photo_texture > 0:  # drawn only then: the stream of earlier runs stays as it was
            self._photo_textures(rgb, inst, is_table)
        out["images"] = self._compose(rgb, inst >= 0)
        return out

    # ------------------------------------------------------------------ appearance
    def _noise(self, h: int, w: int) -> np.ndarray:
        """(h, w, 3) float32 unit Gaussian noise: a random window of the fixed :func:`noise_bank`."""
        y, x = int(self.rng.integers(h)), int(self.rng.integers(w))
        return noise_bank(h, w)[y:y + h, x:x + w]

    def _photo_textures(self, rgb: np.ndarray, inst: np.ndarray, unlabelled: np.ndarray) -> None:
        """In place: each unlabelled instance (table, clutter; ``unlabelled`` (n,) over the instance
        ids of ``inst`` (B, h, w), -1 = nothing) takes, with probability ``p_photo_texture``, the
        pixels of one of two random photograph windows of its image, times its own shading (its
        rendered luminance over the instance's mean): real textures on surfaces that are no object."""
        rng = self.rng
        B, h, w, _ = rgb.shape
        n = len(unlabelled)
        # per instance: 0 keeps its colour, 1 or 2 wears texture 1 or 2 of its image
        choice = np.where(unlabelled & (rng.random(n) < self.p_photo_texture), rng.integers(1, 3, n), 0)
        if not choice.any():
            return
        lum = rgb.astype(np.float32).mean(3)  # (B, h, w)
        flat = inst.reshape(-1)
        on = flat >= 0
        sums = np.bincount(flat[on], weights=lum.reshape(-1)[on], minlength=n)
        counts = np.bincount(flat[on], minlength=n)
        mean = sums / np.maximum(counts, 1)
        for b in range(B):
            ib = inst[b]
            which = np.where(ib >= 0, choice[np.maximum(ib, 0)], 0)
            if not which.any():
                continue
            shade = np.clip(lum[b] / np.maximum(mean[np.maximum(ib, 0)], 1.0), 0.0, 2.5)[..., None]
            for t in (1, 2):
                m = which == t
                if m.any():
                    tex = photo_window(self.photos[int(rng.integers(len(self.photos)))], h, w, rng)
                    rgb[b][m] = np.clip(tex[m] * shade[m], 0, 255).astype(rgb.dtype)

    def _compose(self, rgb: np.ndarray, foreground: np.ndarray) -> np.ndarray:
        """Backgrounds where nothing was drawn, colour noise on the surfaces, image augmentations."""
        import cv2

        rng = self.rng
        B, h, w, _ = rgb.shape
        out = np.empty_like(rgb)
        for b in range(B):
            img = rgb[b].astype(np.float32)
            field = rng.uniform(0.85, 1.15, (int(rng.integers(2, 6)), int(rng.integers(2, 8)), 3)).astype(np.float32)
            multiply_field(img, field, cv2.INTER_CUBIC)
            if not foreground[b].all():
                photo = self.p_photo > 0 and rng.random() < self.p_photo  # drawn only then
                kind = -1 if photo else int(rng.integers(0, 5))
                c0, c1 = (None, None) if photo else (rng.uniform(0, 255, 3), rng.uniform(0, 255, 3))
                if photo:
                    bg = photo_window(self.photos[int(rng.integers(len(self.photos)))], h, w, rng)
                elif kind == 0:
                    bg = flat_background(h, w, c0)
                elif kind == 1:
                    bg = gradient_background(h, w, c0, c1, rng.uniform(0, 2 * np.pi))
                elif kind == 2:
                    grid = rng.uniform(0, 255, (int(rng.integers(2, 8)), int(rng.integers(2, 10)), 3))
                    bg = grid_background(grid, h, w, cv2.INTER_CUBIC)
                elif kind == 3:
                    small = rng.uniform(0, 255, (h // 8 + 1, w // 8 + 1, 3))
                    bg = grid_background(small, h, w, cv2.INTER_NEAREST if rng.random() < 0.5 else cv2.INTER_LINEAR)
                else:  # random flat rectangles and discs: clutter with edges, never an object
                    bg = flat_background(h, w, c0)
                    for _ in range(int(rng.integers(5, 30))):
                        col = tuple(float(v) for v in rng.uniform(0, 255, 3))
                        x, y = int(rng.integers(-w // 4, w)), int(rng.integers(-h // 4, h))
                        if rng.random() < 0.6:
                            cv2.rectangle(bg, (x, y), (x + int(rng.integers(4, w // 2)), y + int(rng.integers(4, h // 2))),
                                          col, -1)
                        else:
                            cv2.circle(bg, (x, y), int(rng.integers(3, h // 4)), col, -1)
                noise, std = None, 0.0
                if rng.random() < 0.5:
                    noise = self._noise(h, w)
                    std = float(rng.uniform(0, 12))
                paste_background(img, bg, foreground[b], noise, std)
            contrast, bright = rng.uniform(0.7, 1.3), rng.normal(0, 12)
            gain = rng.uniform(1 - self.gain_jitter, 1 + self.gain_jitter, 3)
            img = photometric(img, contrast, gain, bright)
            if self.saturation != (1.0, 1.0):  # drawn only then (the detector's stream stays as it was)
                grey = img.mean(2, keepdims=True)
                img = grey + np.float32(rng.uniform(*self.saturation)) * (img - grey)
            if rng.random() < 0.5:
                cv2.scaleAdd(self._noise(h, w), float(rng.uniform(1, 6)), img, dst=img)
            if rng.random() < self.blur[0]:
                img = cv2.GaussianBlur(img, (0, 0), float(rng.uniform(self.blur[1], self.blur[2])))
            out[b] = np.clip(img + 0.5, 0, 255).astype(np.uint8)
        return out


def visible_probe_pixels(Ks: np.ndarray, T_cam_obj: np.ndarray, points: np.ndarray, depth: np.ndarray,
                         tol_mm: float = 2.0, tol_px: float = 2.0) -> np.ndarray:
    """Per instance, the number of distinct pixels showing one of ``points`` (M, 3) mm (object frame).

    Ks (n, 3, 3) and depth (n, h, w) (camera z mm of the visible surface, 0 = nothing drawn) of
    each instance's image, T_cam_obj (n, 4, 4). A point counts where it projects inside the image
    (nearest pixel centre, pixel centres at integers), in front of the camera, and no surface of
    the rendered depth is nearer than the point by more than ``tol_mm`` + ``tol_px`` pixel
    footprints (z / f): not hidden by the object itself nor by others. Where nothing is drawn
    the point counts (e.g. a missing part seen against the background). Returns (n,) int64."""
    Ks = np.asarray(Ks, np.float64)
    T = np.asarray(T_cam_obj, np.float64)
    n, h, w = depth.shape
    P = np.asarray(points, np.float64).reshape(-1, 3)
    if n == 0 or len(P) == 0:
        return np.zeros(n, np.int64)
    X = np.einsum("nij,mj->nmi", T[:, :3, :3], P) + T[:, None, :3, 3]  # (n, M, 3) camera frame
    z = X[..., 2]
    uvw = np.einsum("nij,nmj->nmi", Ks, X)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(uvw[..., 0] / uvw[..., 2])
        v = np.rint(uvw[..., 1] / uvw[..., 2])
    ok = (z > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    ui, vi = np.where(ok, u, 0).astype(np.int64), np.where(ok, v, 0).astype(np.int64)
    inst = np.broadcast_to(np.arange(n)[:, None], z.shape)
    d = depth[inst, vi, ui].astype(np.float64)
    tol = tol_mm + tol_px * z / Ks[:, None, 0, 0]
    ok &= (d <= 0) | (z <= d + tol)
    key = (inst[ok] * h + vi[ok]) * w + ui[ok]
    key = np.unique(key)
    return np.bincount(key // (h * w), minlength=n).astype(np.int64)


def normalised_weights(weights, obj_ids) -> np.ndarray | None:
    """Sampling probabilities (len(obj_ids),) of ``weights`` ({obj_id: weight >= 0}; objects not
    named weigh 1), None for uniform (None or empty)."""
    if not weights:
        return None
    w = np.array([float(weights.get(int(o), weights.get(str(int(o)), 1.0))) for o in obj_ids])
    unknown = set(int(k) for k in weights) - set(int(o) for o in obj_ids)
    if unknown or np.any(w < 0) or not np.isfinite(w).all() or w.sum() <= 0:
        raise ValueError(f"class weights must be >= 0 for known objects {list(map(int, obj_ids))}, got {weights}")
    return w / w.sum()


def pair_table(confusable, obj_ids) -> tuple[np.ndarray, np.ndarray]:
    """(pairs (P, 2) obj_ids, probabilities (P,)) of ``confusable``: [[a, b], ...] or
    [[a, b, weight], ...] (weight default 1)."""
    rows = [] if not confusable else list(confusable)
    known = set(int(o) for o in obj_ids)
    pairs, w = [], []
    for r in rows:
        a, b = int(r[0]), int(r[1])
        if a == b or a not in known or b not in known or len(r) not in (2, 3):
            raise ValueError(f"a confusable pair is two different known objects [a, b] or [a, b, weight], got {r}")
        pairs.append((a, b))
        w.append(float(r[2]) if len(r) == 3 else 1.0)
    if not pairs:
        return np.zeros((0, 2), np.int64), np.zeros(0)
    w = np.array(w)
    if np.any(w < 0) or w.sum() <= 0:
        raise ValueError(f"confusable pair weights must be >= 0 and not all 0, got {rows}")
    return np.array(pairs, np.int64), w / w.sum()


# ---------------------------------------------------------------------- torch stream
def _iterable_base():
    try:
        from torch.utils.data import IterableDataset

        return IterableDataset
    except ImportError:  # pragma: no cover
        return object


def batch_targets(batch: dict, config) -> dict:
    """numpy training tensors of a generator batch: images (B, 3, H, W) float32 [0, 1] and the
    stacked :func:`~cosy_cli.detection.model.encode_targets`."""
    from .model import encode_targets, stack_targets

    t = stack_targets([encode_targets(bx, lb, config, ib, il) for bx, lb, ib, il in
                       zip(batch["boxes"], batch["labels"], batch["ignore_boxes"], batch["ignore_labels"])])
    t["images"] = np.ascontiguousarray(batch["images"].transpose(0, 3, 1, 2), dtype=np.float32) / 255.0
    return t


class DetectionStream(_iterable_base()):
    """Endless torch IterableDataset of encoded training batches (use ``batch_size=None``); each
    worker builds its own generator seeded by (seed, worker id)."""

    def __init__(self, meshes: dict, K, image_size, config, batch_size: int, seed: int = 0, **kw):
        super().__init__()
        self.meshes, self.K, self.image_size, self.config = meshes, K, image_size, config
        self.batch_size, self.seed, self.kw = int(batch_size), int(seed), kw

    def __iter__(self):
        from torch.utils.data import get_worker_info

        info = get_worker_info()
        worker = 0 if info is None else info.id
        gen = DetectionSampleGenerator(self.meshes, self.K, self.image_size, self.config.input_size,
                                       seed=np.random.SeedSequence([self.seed, worker]),
                                       obj_ids=self.config.obj_ids, **self.kw)
        if info is not None:
            atexit.register(gen.close)
        try:
            while True:
                yield batch_targets(gen.batch(self.batch_size), self.config)
        finally:
            gen.close()


__all__ = ["DetectionSampleGenerator", "DetectionStream", "batch_targets", "scaled_intrinsics", "normalised_weights",
           "pair_table", "photo_window", "visible_probe_pixels"]
