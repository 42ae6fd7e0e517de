"""Depth refinement of single-view pose candidates: trimmed point-to-plane ICP against a depth map.

The RGB-D variant of CosyPose's single-view stage: each candidate pose ``T_cam_obj`` (mm) is
refined by aligning the object's surface to the depth pixels inside its detection box.

Per object (once, cached per ``ObjectModel``): ``N_SURFACE`` area-uniform surface samples with
outward face normals (object frame, mm), a scipy cKDTree over them, and the tree's answers
tabulated on a voxel grid around the model (the ICP loop looks nearest samples up there: a few
microseconds for 1500 points instead of a millisecond of tree queries).

Per candidate (:func:`refine_with_depth`):

1. Observed points: the valid depth pixels (> 0) inside the box (clipped to the image) that have
   a surface normal (from their neighbours, not across a depth jump), back-projected into the
   camera frame (mm), in a seeded random order; shared by the candidates of one box.
2. Depth alignment (``IcpConf.align_depth``): the pose slides along the camera ray through the
   object origin by the shift, |shift| < diameter, under which the camera-facing model points
   best agree with the observed depth at their pixels (a 1-D search, coarse then fine, scored by
   agreement x precision, see :func:`_align_depth`). This fixes the depth error of
   box-size-based coarse poses (5-10 %), larger than ICP's basin.
3. Observed points within ``radius + trim_start * diameter`` of the aligned object centre (most of
   the table and of other objects are dropped), the first ``max_points`` of them (a uniform
   subsample thanks to the random order).
4. ICP, at most ``iterations`` steps: observed points into the object frame, nearest model
   sample; a pair counts if closer than the current trim distance (geometric decay from
   ``trim_start * diameter`` to ``trim_end_mm``), the model normal faces the camera and the
   observed and model normals agree within 60 deg (this rejects the table next to an object's
   side faces); pairs weighted by a biweight of their distance; damped 6x6 normal equations of
   the linearised point-to-plane residual; exact rigid update about the pairs' weighted centroid.
   When a step moves the model by less than ``STEP_TOL`` x trim, the trim schedule skips ahead;
   at the final trim such a step ends the loop.
5. Acceptance: at least ``min_inliers`` pairs at the final trim, and (modulo the object's
   symmetries) a rotation change from the input pose of at most ``max_rotation_deg`` and an ICP
   translation drift from the depth-aligned pose of at most ``max_translation_frac * diameter``;
   otherwise the input pose is returned with ``ok = False``.
6. Scores of the returned poses (:func:`depth_fit_score` and the inlier fraction), vectorised.

All lengths in mm. Vectorised over points and candidates (the ICP steps of ``ICP_CHUNK``
candidates are solved together, each on its own trim schedule); Python loops run over distinct
boxes, objects and iterations only.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from ...geometry.rotations import axis_angle_to_matrix

N_SURFACE = 3000  # surface samples per object
SURFACE_SEED = 0
VISIBLE_COS = 0.2  # visible = cos(normal, direction to the camera) above this (grazing faces left out)
FACING_COS_ICP = -0.1  # ICP pairs need cos(model normal, direction to the camera) above this (grazing edges kept)
MIN_PAIRS = 6  # below this an ICP step is not solved
ALIGN_POINTS = 400  # camera-facing model samples used by the depth alignment
NORMAL_STEP = 2  # px: observed normals from the points this far left/right and up/down
NORMAL_MAX_JUMP = 0.05  # neighbours whose depth differs by more than this fraction are across an edge
NORMAL_COS = 0.5  # pairs need cos(observed normal, model normal) above this (60 deg)
GRID_STEPS = 48  # nearest-sample lookup grid: voxel side = diameter / GRID_STEPS
GRID_MARGIN = 0.25  # ... covering the model's box grown by this fraction of the diameter (at least)
STEP_TOL = 0.02  # a step moving the model less than this fraction of the trim distance has converged
STEP_SKIP = 3  # ... and the trim schedule then skips this many levels
ALIGN_CHUNK = 200_000  # depth alignment: poses per batch such that poses x shifts x points stays below this
ICP_CHUNK = 32  # ICP problems solved together (their arrays stay in cache)
ICP_DTYPE = np.float32  # the ICP's point arrays (the poses and the 6x6 systems stay float64)


@dataclass
class IcpConf:
    iterations: int = 20            # ICP iterations
    max_points: int = 1500          # observed points kept per box (seeded uniform subsample)
    trim_start: float = 0.2         # initial inlier distance, fraction of the object diameter
    trim_end_mm: float = 4.0        # final inlier distance (mm); geometric decay start->end over the iterations
    align_depth: bool = True        # first slide the pose along its camera ray to match the observed depth
    align_points: int = ALIGN_POINTS  # camera-facing model samples the depth alignment uses
    max_rotation_deg: float = 30.0  # divergence check: larger total change => keep the input pose, ok=False
    max_translation_frac: float = 0.5  # ... or translation change > this * diameter
    min_inliers: int = 30           # fewer final inliers => ok=False, input pose kept
    seed: int = 0


@dataclass
class DepthRefineResult:
    """Per candidate: T_cam_obj (M, 4, 4) mm refined poses (the input pose where ok is False);
    ok (M,) converged and accepted; inlier_frac (M,) fraction of the model's visible points
    (camera-facing, inside the image) that agree with the depth, occluded ones included in the
    denominator; rmse_mm (M,) RMS point-to-plane residual (mm) of the final ICP inliers (nan if ICP
    found none); fit_score (M,) :func:`depth_fit_score` of the returned pose."""

    T_cam_obj: np.ndarray
    ok: np.ndarray
    inlier_frac: np.ndarray
    rmse_mm: np.ndarray
    fit_score: np.ndarray


# ---------------------------------------------------------------------------- model surfaces


class _Surface:
    """Surface samples (N, 3) mm with unit outward normals (N, 3) of one object, object frame."""

    def __init__(self, model):
        import trimesh
        from scipy.spatial import cKDTree

        src = model.mesh
        mesh = trimesh.Trimesh(np.asarray(src.vertices, np.float64), np.asarray(src.faces), process=True)
        watertight = mesh.is_watertight
        if watertight:
            if not mesh.is_winding_consistent:
                trimesh.repair.fix_winding(mesh)
            if mesh.volume < 0:
                mesh.invert()
        pts, face = trimesh.sample.sample_surface(mesh, N_SURFACE, seed=SURFACE_SEED)
        self.points = np.ascontiguousarray(pts, dtype=np.float64)
        normals = np.asarray(mesh.face_normals, dtype=np.float64)[face]
        if not watertight:  # open mesh: no inside/outside, orient normals away from the centre
            c = self.points.mean(0)
            normals = np.where((np.einsum("ij,ij->i", normals, self.points - c) < 0)[:, None], -normals, normals)
        self.normals = np.ascontiguousarray(normals)
        self.centre = (self.points.min(0) + self.points.max(0)) / 2
        self.radius = float(np.linalg.norm(self.points - self.centre, axis=1).max())
        self.n_dot_p = np.einsum("ij,ij->i", self.normals, self.points)
        self.diameter = float(model.diameter)
        self.tree = cKDTree(self.points)
        self.symmetries = np.asarray(model.symmetries, dtype=np.float64)
        self._grids: dict[float, _NearestGrid] = {}

    def grid(self, reach_mm: float) -> "_NearestGrid":
        """Nearest-sample lookup covering at least ``reach_mm`` around the model (cached)."""
        reach = max(GRID_MARGIN * self.diameter, float(reach_mm))
        for r, g in self._grids.items():
            if r >= reach:
                return g
        g = _NearestGrid(self, reach)
        self._grids[reach] = g
        return g


class _NearestGrid:
    """The KD-tree's nearest surface sample, tabulated at voxel centres (voxel = diameter / GRID_STEPS)
    over the model's box grown by ``reach`` mm: a lookup (:meth:`_Batch.nearest`, for the grids of
    a batch of ICP problems) replaces the tree query in the ICP loop.
    The looked-up sample's distance exceeds the exact nearest distance by at most h*sqrt(3) mm
    (h = voxel side). Points outside the grid get the sample of the closest border voxel, which is
    farther than ``reach`` from them (callers trim by the exact distance)."""

    def __init__(self, surf: _Surface, reach: float):
        self.h = surf.diameter / GRID_STEPS
        lo = surf.points.min(0) - reach
        hi = surf.points.max(0) + reach
        self.shape = np.ceil((hi - lo) / self.h).astype(np.int64) + 1
        self.origin = lo
        axes = [lo[i] + self.h * np.arange(self.shape[i]) for i in range(3)]
        centres = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        _, idx = surf.tree.query(centres)
        self.index = idx.astype(np.int16 if len(surf.points) < 2 ** 15 else np.int32)  # small: one per voxel
        self.strides = np.array([self.shape[1] * self.shape[2], self.shape[2], 1], dtype=np.float64)
        self.top = (self.shape - 1).astype(np.float64)  # the last voxel index per axis


_SURFACES: dict[int, tuple[weakref.ref, _Surface]] = {}


def _surface(model) -> _Surface:
    """The cached :class:`_Surface` of an ObjectModel (computed once per model object)."""
    key = id(model)
    hit = _SURFACES.get(key)
    if hit is not None and hit[0]() is model:
        return hit[1]
    surf = _Surface(model)

    def forget(ref, key=key):
        if _SURFACES.get(key, (None,))[0] is ref:
            del _SURFACES[key]

    _SURFACES[key] = (weakref.ref(model, forget), surf)
    return surf


# ---------------------------------------------------------------------------- depth consistency


def _agreement(depth_mm, K, surfaces, T_cam_obj, tol):
    """Counts per row: (agree, visible, occluded) over the camera-facing model points inside the image."""
    depth = np.asarray(depth_mm)
    H, W = depth.shape
    uniq, rows = _stacked(surfaces)
    P = np.stack([s.points for s in uniq])[rows]  # (M, N, 3)
    NP = np.stack([s.n_dot_p for s in uniq])[rows]  # (M, N)
    Nrm = np.stack([s.normals for s in uniq])[rows]
    R, t = T_cam_obj[:, :3, :3], T_cam_obj[:, :3, 3]
    KR = K @ R
    X = np.matmul(P, np.swapaxes(KR, 1, 2)) + (t @ K.T)[:, None]  # (M, N, 3): (u z, v z, z)
    z = X[..., 2]
    # facing: (R n) . (R p + t) = n . p + n . (R^T t) < -VISIBLE_COS |X|, with |X| ~ z
    facing = NP + np.matmul(Nrm, np.einsum("mji,mj->mi", R, t)[..., None])[..., 0] < -VISIBLE_COS * z
    zs = np.where(z > 1e-6, z, 1.0)
    u = np.rint(X[..., 0] / zs)
    v = np.rint(X[..., 1] / zs)
    vis = facing & (z > 1e-6) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    flat = np.where(vis, v * W + u, 0).astype(np.intp)
    d = depth.ravel().take(flat)
    measured = vis & (d > 0) & np.isfinite(d)
    tol = np.asarray(tol, dtype=np.float64)[:, None]
    agree = measured & (np.abs(z - d) <= tol)
    occluded = measured & (z > d + tol)
    return agree.sum(1), vis.sum(1), occluded.sum(1)


def _default_tol(surfaces) -> np.ndarray:
    return np.array([max(0.02 * s.diameter, 3.0) for s in surfaces])


def depth_fit_score(depth_mm, K, obj_ids, T_cam_obj, db, tol_mm=None) -> np.ndarray:
    """Depth consistency of poses, (M,) in [0, 1], higher = better.

    depth_mm (H, W) mm (0 = no measurement); K (3, 3); obj_ids (M,); T_cam_obj (M, 4, 4) mm;
    db an ObjectDatabase; tol_mm None (per object max(0.02 * diameter, 3 mm)), a number or (M,).
    Over the model's surface samples that face the camera (at less than acos(VISIBLE_COS) = 78 deg
    from the viewing ray: grazing faces, whose depth changes by several mm per pixel, are left
    out) and project inside the image (to pixel round(u), round(v)): points
    within tol of the measured depth at their pixel agree; points in front of it by more than tol
    are violations (the model would hide observed surface); pixels without a measurement count
    against the pose; points behind the measurement by more than tol are occluded and ignored.
    Score = agree / (visible - occluded), 0 where nothing is left.
    """
    K = np.asarray(K, dtype=np.float64)
    T = np.asarray(T_cam_obj, dtype=np.float64).reshape(-1, 4, 4)
    ids = np.asarray(obj_ids).reshape(-1)
    if len(ids) != len(T):
        raise ValueError(f"obj_ids ({len(ids)}) and T_cam_obj ({len(T)}) differ in length")
    if len(T) == 0:
        return np.zeros(0)
    surfaces = [_surface(db[int(i)]) for i in ids]
    tol = _default_tol(surfaces) if tol_mm is None else np.broadcast_to(np.asarray(tol_mm, float), (len(T),))
    agree, visible, occluded = _agreement(depth_mm, K, surfaces, T, tol)
    denom = visible - occluded
    return np.where(denom > 0, agree / np.maximum(denom, 1), 0.0)


# ---------------------------------------------------------------------------- observed points


def _pixel_range(lo: float, hi: float, n: int) -> tuple[int, int]:
    """Pixels whose centres (i + 0.5) lie in [lo, hi) of pixel-edge coordinates, clipped to 0..n."""
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return 0, 0
    a = int(np.clip(np.ceil(lo - 0.5), 0, n))
    b = int(np.clip(np.ceil(hi - 0.5), 0, n))
    return a, max(a, b)


def _box_points(depth: np.ndarray, K: np.ndarray, box) -> np.ndarray:
    """The valid pixels in the box (clipped to the image) with a surface normal: (6, n) rows
    x, y, z (camera frame, mm) and the unit normal facing the camera. Normals come from the cross
    product of the differences between the pixels NORMAL_STEP px left/right and up/down; pixels
    where a neighbour is missing or lies across a depth jump are left out."""
    H, W = depth.shape
    x1, y1, x2, y2 = (float(b) for b in box)
    c0, c1 = _pixel_range(x1, x2, W)
    r0, r1 = _pixel_range(y1, y2, H)
    if c1 <= c0 or r1 <= r0:
        return np.zeros((6, 0))
    s = NORMAL_STEP
    # the crop grown by s pixels, zero (= no measurement) outside the image
    z = np.zeros((r1 - r0 + 2 * s, c1 - c0 + 2 * s))
    ra, rb, ca, cb = max(r0 - s, 0), min(r1 + s, H), max(c0 - s, 0), min(c1 + s, W)
    z[ra - (r0 - s):rb - (r0 - s), ca - (c0 - s):cb - (c0 - s)] = depth[ra:rb, ca:cb]
    z[~np.isfinite(z)] = 0.0
    v, u = np.mgrid[r0 - s:r1 + s, c0 - s:c1 + s].astype(np.float64)
    y = (v - K[1, 2]) * z / K[1, 1]
    x = ((u - K[0, 2]) * z - K[0, 1] * y) / K[0, 0]
    P = np.stack([x, y, z])  # (3, h + 2s, w + 2s)
    c = P[:, s:-s, s:-s]
    left, right, up, down = P[:, s:-s, :-2 * s], P[:, s:-s, 2 * s:], P[:, :-2 * s, s:-s], P[:, 2 * s:, s:-s]
    zc = c[2]
    jump = NORMAL_MAX_JUMP * zc
    ok = zc > 0
    for nb in (left, right, up, down):
        ok &= (nb[2] > 0) & (np.abs(nb[2] - zc) < jump)
    dx, dy = right - left, down - up
    n = np.stack([dx[1] * dy[2] - dx[2] * dy[1], dx[2] * dy[0] - dx[0] * dy[2], dx[0] * dy[1] - dx[1] * dy[0]])
    idx = np.flatnonzero(ok)
    n = n.reshape(3, -1).take(idx, axis=1)
    pts = c.reshape(3, -1).take(idx, axis=1)
    norm = np.sqrt(np.einsum("ij,ij->j", n, n))
    good = norm > 0
    n = n[:, good] / norm[good]
    pts = pts[:, good]
    n *= -np.sign(np.einsum("ij,ij->j", n, pts))  # facing the camera
    return np.concatenate([pts, n])


def _stacked(surfaces) -> tuple[list, np.ndarray]:
    """The distinct surfaces of a list (in first-seen order) and each entry's index among them."""
    uniq: dict[int, int] = {}
    rows = np.array([uniq.setdefault(id(s), len(uniq)) for s in surfaces], dtype=np.intp)
    by_id = {id(s): s for s in surfaces}
    return [by_id[k] for k in uniq], rows


def _align_depth(T: np.ndarray, surfaces, K: np.ndarray, depth: np.ndarray, tols: np.ndarray,
                 n_points: int = ALIGN_POINTS) -> np.ndarray:
    """Each pose of T (M, 4, 4) slid along the camera ray through its origin by the shift
    (|shift| < diameter) with the best score a^2 / (a + v) over its camera-facing model points
    (the first ``n_points`` of them) at their pixels: a points agree with the observed depth
    within ``tols`` (M,) mm, v lie in front of it by more than tol (the model would hide observed
    surface; points behind it are occluded and neutral). Weighting the agreement by its precision
    keeps a partly occluded object from being pulled onto its occluder. A coarse search in steps
    of tol, then a fine one in steps of tol / 8 (the median of its best shifts). A pose is kept as
    it is when it is behind the camera, shows fewer than 10 facing points or no shift gives any
    agreement. Batched over poses (in chunks), shifts and points."""
    T = np.asarray(T, dtype=np.float64)
    out = T.copy()
    if len(T) == 0:
        return out
    H, W = depth.shape
    flat_depth = depth.ravel()
    uniq, rows = _stacked(surfaces)
    R, t = T[:, :3, :3], T[:, :3, 3]
    Rt = np.swapaxes(R, 1, 2)
    X = np.matmul(np.stack([s.points for s in uniq])[rows], Rt) + t[:, None]  # (M, N, 3)
    facing = np.einsum("mni,mni->mn", np.matmul(np.stack([s.normals for s in uniq])[rows], Rt), X) \
        < -VISIBLE_COS * X[..., 2]
    # the first n_points facing samples (the samples are in random order: a uniform subset)
    first = np.argsort(~facing, axis=1, kind="stable")[:, :n_points]
    X = np.take_along_axis(X, first[..., None], 1)  # (M, A, 3)
    pmask = np.take_along_axis(facing, first, 1)
    tols = np.asarray(tols, dtype=np.float64)
    live = (t[:, 2] > 0) & (pmask.sum(1) >= 10)
    ray = t / np.where(live, t[:, 2], 1.0)[:, None]
    half = np.array([s.diameter for s in uniq])[rows] - tols
    n_coarse = np.where(live, np.ceil((2 * half + 1e-9) / tols), 1).astype(np.int64)

    def agreement(idx, shifts, valid):  # poses idx (m,), shifts (m, S) mm -> scores (m, S), -inf where not valid
        x, y, z0 = (X[idx][:, None, :, i] for i in range(3))  # (m, 1, A)
        sh = shifts[..., None]  # (m, S, 1)
        r = ray[idx][:, None, None]
        z = z0 + sh  # the ray's z component is 1
        ok = (z > 1e-6) & pmask[idx][:, None]
        zs = np.where(ok, z, 1.0)
        ys = y + sh * r[..., 1]
        u = np.rint((K[0, 0] * (x + sh * r[..., 0]) + K[0, 1] * ys) / zs + K[0, 2])
        v = np.rint(K[1, 1] * ys / zs + K[1, 2])
        ok &= (u >= 0) & (u < W) & (v >= 0) & (v < H)
        d = flat_depth.take(np.where(ok, v * W + u, 0).astype(np.intp))
        ok &= d > 0
        tol = tols[idx][:, None, None]
        agree = (ok & (np.abs(d - z) <= tol)).sum(2)
        violate = (ok & (z < d - tol)).sum(2)  # the model would hide observed surface
        return np.where(valid, agree * agree / np.maximum(agree + violate, 1), -np.inf)  # agreement x precision

    todo = np.flatnonzero(live)
    chunk = max(1, ALIGN_CHUNK // (max(int(n_coarse.max()), 17) * X.shape[1]))
    for c0 in range(0, len(todo), chunk):
        idx = todo[c0:c0 + chunk]
        steps = np.arange(int(n_coarse[idx].max()))
        coarse = -half[idx][:, None] + steps * tols[idx][:, None]
        score = agreement(idx, coarse, steps < n_coarse[idx][:, None])
        found = score.max(1) > 0
        idx, coarse, score = idx[found], coarse[found], score[found]
        if len(idx) == 0:
            continue
        m = np.arange(len(idx))
        best = coarse[m, score.argmax(1)]
        tol = tols[idx][:, None]
        fine = best[:, None] + (-tol + np.arange(17) * (tol / 8))
        score = agreement(idx, fine, True)
        top = score == score.max(1, keepdims=True)
        n_top = top.sum(1)
        order = np.argsort(~top, axis=1, kind="stable")  # the best shifts first, in increasing order
        shift = (fine[m, order[m, (n_top - 1) // 2]] + fine[m, order[m, n_top // 2]]) / 2  # their median
        out[idx, :3, 3] = t[idx] + shift[:, None] * ray[idx]
    return out


# ---------------------------------------------------------------------------- ICP


class _Batch:
    """The model data of M ICP problems gathered for vectorised steps: each row's surface samples,
    normals and n . p (by index into the packed rows of the distinct surfaces) and its
    nearest-sample grid (the distinct grids' tables concatenated, with per-row origin, voxel side,
    strides and offset)."""

    def __init__(self, surfaces, reach: np.ndarray):
        uniq, rows = _stacked(surfaces)
        sizes = [len(s.points) for s in uniq]
        self.start = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.intp)[rows]  # each row's first sample
        # per sample one row of 8: point (3), normal (3), n . p, padding: one gather fetches all of them
        self.packed = np.zeros((sum(sizes), 8), ICP_DTYPE)  # (U * N, 8)
        self.packed[:, :3] = np.concatenate([s.points for s in uniq])
        self.packed[:, 3:6] = np.concatenate([s.normals for s in uniq])
        self.packed[:, 6] = np.concatenate([s.n_dot_p for s in uniq])
        first = np.unique(rows, return_index=True)[1]
        grids = [uniq[u].grid(reach[i]) for u, i in enumerate(first)]
        offsets = np.cumsum([0] + [g.index.size for g in grids[:-1]])
        self.index = np.concatenate([g.index.astype(np.intp) for g in grids])
        self.origin = np.stack([g.origin for g in grids])[rows]  # (M, 3)
        self.inv_h = (1.0 / np.array([g.h for g in grids]))[rows]
        self.strides = np.stack([g.strides for g in grids])[rows]
        self.top = np.stack([g.top for g in grids])[rows]
        self.offset = offsets[rows]

    def nearest(self, sel: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """Nearest-sample indices (m, n) into ``packed`` of points Q (m, 3, n) (object frames) of rows sel."""
        ijk = np.rint((Q - self.origin[sel][:, :, None]) * self.inv_h[sel][:, None, None])
        np.clip(ijk, 0.0, self.top[sel][:, :, None], out=ijk)
        cell = np.einsum("mi,min->mn", self.strides[sel], ijk).astype(np.intp) + self.offset[sel][:, None]
        return self.index.take(cell) + self.start[sel][:, None]


def _pairs(T, Qc, valid, batch: _Batch, sel, trim):
    """Observed points and normals Qc (m, 6, n) (camera frame; ``valid`` (m, n) marks the real ones)
    of rows ``sel`` in their object frames, paired with their nearest model samples: (Q (m, 3, n),
    e = Q - p, model normals (m, 3, n), s (m, n)) with s = squared distance / trim^2 (trim (m,) mm),
    set to 1 (rejected) where it exceeds 1, where the model normal faces away from the camera,
    where the two normals differ by more than acos(NORMAL_COS) and for padding."""
    Rt = np.swapaxes(T[:, :3, :3], 1, 2).astype(Qc.dtype)  # R^T
    t = T[:, :3, 3].astype(Qc.dtype)
    Q = np.matmul(Rt, Qc[:, :3] - t[:, :, None])
    g = np.moveaxis(batch.packed.take(batch.nearest(sel, Q), axis=0), 2, 1)  # (m, 8, n) view
    e = Q - g[:, :3]
    nn = np.ascontiguousarray(g[:, 3:6])
    s = np.einsum("min,min->mn", e, e) / (trim * trim).astype(Qc.dtype)[:, None]
    cam = -np.einsum("mij,mj->mi", Rt, t)  # camera centre in the object frame; |cam - p| ~ |cam| for the facing test
    facing = np.einsum("mi,min->mn", cam, nn) - g[:, 6] > FACING_COS_ICP * np.linalg.norm(cam, axis=1)[:, None]
    same = np.einsum("min,min->mn", np.matmul(Rt, Qc[:, 3:]), nn) > NORMAL_COS
    s[(s > 1.0) | ~facing | ~same | ~valid] = 1.0
    return Q, e, nn, s


def _icp(T0: np.ndarray, Qc: np.ndarray, valid: np.ndarray, surfaces, conf: IcpConf):
    """Trimmed point-to-plane ICP of M problems at once: observed camera points and normals Qc
    (M, 6, n) (mm; ``valid`` (M, n) marks the real columns) onto the models ``surfaces``, starting
    from T0 (M, 4, 4). Each row follows its own trim schedule and stops on its own. Returns
    (T_cam_obj (M, 4, 4), final inliers (M,), rmse_mm (M,))."""
    M = len(T0)
    T = T0.copy()
    diam = np.array([s.diameter for s in surfaces])
    d0 = np.maximum(conf.trim_start * diam, conf.trim_end_mm)
    n_it = max(int(conf.iterations), 1)
    trims = np.geomspace(d0, conf.trim_end_mm, n_it, axis=1) if n_it > 1 else np.full((M, 1), conf.trim_end_mm)
    batch = _Batch(surfaces, d0)
    scale = diam / 2  # makes rotation columns commensurate with translation (mm)
    k = np.zeros(M, np.int64)
    running = np.ones(M, bool)
    n_in = np.zeros(M, np.int64)
    rmse = np.full(M, np.nan)
    final = np.ones(M, bool)  # rows whose final inliers are counted after the loop
    while running.any():
        sel = np.flatnonzero(running)
        trim = trims[sel, k[sel]]
        Q, e, nn, s = _pairs(T[sel], Qc[sel], valid[sel], batch, sel, trim)
        w = 1.0 - s
        w *= w  # biweight of the distance; 0 for rejected pairs
        cnt = np.count_nonzero(w, axis=1)
        few = cnt < MIN_PAIRS
        if few.any():  # too few pairs to solve a step: stop there
            n_in[sel[few]] = cnt[few]
            running[sel[few]] = final[sel[few]] = False
            keep = ~few
            sel, trim, Q, e, nn, w = sel[keep], trim[keep], Q[keep], e[keep], nn[keep], w[keep]
            if len(sel) == 0:
                break
        sw = w.sum(1, dtype=np.float64)
        c = np.einsum("min,mn->mi", Q, w).astype(np.float64) / sw[:, None]
        a = Q - c.astype(Q.dtype)[:, :, None]
        r = np.einsum("min,min->mn", e, nn)
        sc = scale[sel][:, None].astype(Q.dtype)
        A = np.empty((len(sel), 6, a.shape[2]), Q.dtype)
        A[:, 0] = (a[:, 1] * nn[:, 2] - a[:, 2] * nn[:, 1]) / sc
        A[:, 1] = (a[:, 2] * nn[:, 0] - a[:, 0] * nn[:, 2]) / sc
        A[:, 2] = (a[:, 0] * nn[:, 1] - a[:, 1] * nn[:, 0]) / sc
        A[:, 3:] = nn
        Aw = A * w[:, None]
        Hm = np.matmul(Aw, np.swapaxes(A, 1, 2)).astype(np.float64)
        g = np.einsum("min,mn->mi", Aw, r).astype(np.float64)
        Hm[:, np.arange(6), np.arange(6)] += 1e-6 * sw[:, None]  # directions the data leave free (symmetries) stay put
        x = -np.linalg.solve(Hm, g[..., None])[..., 0]
        omega, vel = x[:, :3] / scale[sel][:, None], x[:, 3:]
        Rw = axis_angle_to_matrix(omega)
        # the step moves the observed points in the object frame: q -> Rw (q - c) + c + vel
        D_inv = np.tile(np.eye(4), (len(sel), 1, 1))
        D_inv[:, :3, :3] = np.swapaxes(Rw, 1, 2)
        D_inv[:, :3, 3] = c - np.einsum("mji,mj->mi", Rw, c + vel)
        T[sel] = np.matmul(T[sel], D_inv)
        step = np.linalg.norm(omega, axis=1) * scale[sel] + np.linalg.norm(vel, axis=1)  # mm, ~ the largest point motion
        conv = step < STEP_TOL * trim  # converged at this trim: go on with the final one, or stop there
        ks = k[sel]
        k[sel] = np.where(conv, np.where(ks >= n_it - 1, n_it, np.maximum(ks + 1, np.minimum(n_it - 1, ks + STEP_SKIP))),
                          ks + 1)
        running[sel] = k[sel] < n_it
    sel = np.flatnonzero(final)
    if len(sel):
        _, e, nn, s = _pairs(T[sel], Qc[sel], valid[sel], batch, sel, np.full(len(sel), conf.trim_end_mm))
        keep = s < 1.0
        n_in[sel] = keep.sum(1)
        r2 = np.where(keep, np.einsum("min,min->mn", e, nn) ** 2, 0.0)
        rmse[sel] = np.where(n_in[sel] > 0, np.sqrt(r2.sum(1, dtype=np.float64) / np.maximum(n_in[sel], 1)), np.nan)
    return T, n_in, rmse


def _within_change(T0: np.ndarray, Ta: np.ndarray, T: np.ndarray, surfaces, conf: IcpConf) -> np.ndarray:
    """Divergence check (M,), modulo the objects' symmetries: some pose T S equivalent to the result
    is within ``max_rotation_deg`` of the input rotation and ``max_translation_frac * diameter``
    of the depth-aligned translation. Batched per distinct object."""
    ok = np.zeros(len(T), bool)
    uniq, rows = _stacked(surfaces)
    for u, surf in enumerate(uniq):
        i = np.flatnonzero(rows == u)
        S = surf.symmetries  # (S, 4, 4), identity first; continuous ones discretised
        R = np.einsum("mij,sjk->msik", T[i, :3, :3], S[:, :3, :3])
        t = np.einsum("msj,mij->msi", np.broadcast_to(S[:, :3, 3], (len(i),) + S[:, :3, 3].shape), T[i, :3, :3]) \
            + T[i, None, :3, 3]
        cos = (np.einsum("mij,msij->ms", T0[i, :3, :3], R) - 1.0) / 2.0
        ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        dt = np.linalg.norm(t - Ta[i, None, :3, 3], axis=2)
        ok[i] = np.any((ang <= conf.max_rotation_deg) & (dt <= conf.max_translation_frac * surf.diameter), axis=1)
    return ok


def refine_with_depth(depth_mm, K, boxes, obj_ids, T_init, db, conf: IcpConf = IcpConf(), *,
                      scores: bool = True) -> DepthRefineResult:
    """Refine candidate poses with a depth map (trimmed point-to-plane ICP, see the module doc).

    depth_mm (H, W) float mm (0 = no measurement); K (3, 3); boxes (M, 4) x1, y1, x2, y2 px in
    pixel-edge coordinates (BOP bbox convention, x2 = x + w); obj_ids (M,); T_init (M, 4, 4)
    T_cam_obj mm; db: cosy_cli.objects.ObjectDatabase. Several rows may share a box (hypotheses
    of one detection). Deterministic under ``conf.seed``. ``scores`` False: inlier_frac and
    fit_score are left NaN (callers that score the poses their own way). All candidates are refined together
    (vectorised over candidates and points; the loops are over distinct boxes and iterations).
    """
    depth = np.asarray(depth_mm)
    if depth.ndim != 2:
        raise ValueError(f"depth_mm must be (H, W), got shape {depth.shape}")
    K = np.asarray(K, dtype=np.float64)
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    ids = np.asarray(obj_ids).reshape(-1)
    T_in = np.asarray(T_init, dtype=np.float64).reshape(-1, 4, 4)
    M = len(T_in)
    if not (len(boxes) == len(ids) == M):
        raise ValueError(f"boxes ({len(boxes)}), obj_ids ({len(ids)}) and T_init ({M}) differ in length")
    T_out = T_in.copy()
    ok = np.zeros(M, bool)
    rmse = np.full(M, np.nan)
    if M == 0:
        return DepthRefineResult(T_out, ok, np.zeros(0), rmse, np.zeros(0))
    surfaces = [_surface(db[int(i)]) for i in ids]
    need = max(conf.min_inliers, MIN_PAIRS)
    tols = _default_tol(surfaces)
    # each distinct box's points and normals (6, n), in a seeded random order
    keys, box_of = np.unique(boxes, axis=0, return_inverse=True)
    box_of = box_of.reshape(-1)
    pts_of = {}
    for seed, b in enumerate(np.argsort(np.unique(box_of, return_index=True)[1], kind="stable")):  # by first row
        pts = _box_points(depth, K, keys[b])
        pts_of[b] = pts.take(np.random.default_rng([conf.seed, seed]).permutation(pts.shape[1]), axis=1)
    n_box = np.array([pts_of[b].shape[1] for b in box_of])
    cand = np.flatnonzero((n_box >= need) & np.all(np.isfinite(T_in), axis=(1, 2)) & (T_in[:, 2, 3] > 0))
    if len(cand):
        cs = [surfaces[i] for i in cand]
        Ta = _align_depth(T_in[cand], cs, K, depth, tols[cand], conf.align_points) if conf.align_depth \
            else T_in[cand].copy()
        # the observed points near each aligned object: the first max_points of them (a uniform subsample)
        radius = np.array([s.radius + max(conf.trim_start * s.diameter, conf.trim_end_mm) for s in cs])
        centre = np.einsum("mij,mj->mi", Ta[:, :3, :3], np.array([s.centre for s in cs])) + Ta[:, :3, 3]
        near_of = []
        for b in np.unique(box_of[cand]):
            i = np.flatnonzero(box_of[cand] == b)
            d = pts_of[b][:3][None] - centre[i][:, :, None]  # (m, 3, n)
            near = np.einsum("min,min->mn", d, d) <= (radius[i] ** 2)[:, None]
            near &= np.cumsum(near, axis=1) <= conf.max_points
            near_of += [(r, pts_of[b][:, near[j]]) for j, r in enumerate(i)]
        near_of.sort(key=lambda x: x[0])
        counts = np.array([p.shape[1] for _, p in near_of])
        go = np.flatnonzero(counts >= need)
        if len(go):
            n = int(counts[go].max())
            Qc = np.zeros((len(go), 6, n), ICP_DTYPE)
            valid = np.arange(n)[None] < counts[go][:, None]
            for j, r in enumerate(go):
                Qc[j, :, :counts[r]] = near_of[r][1]
            rows, Tg = cand[go], Ta[go]
            gs = [surfaces[i] for i in rows]
            T, n_in, rms = np.empty((len(go), 4, 4)), np.zeros(len(go), np.int64), np.full(len(go), np.nan)
            for c0 in range(0, len(go), ICP_CHUNK):  # a few dozen problems at a time: their arrays stay in cache
                c = slice(c0, c0 + ICP_CHUNK)
                T[c], n_in[c], rms[c] = _icp(Tg[c], Qc[c], valid[c], gs[c], conf)
            rmse[rows] = rms
            good = (n_in >= conf.min_inliers) & np.all(np.isfinite(T), axis=(1, 2))
            good &= _within_change(T_in[rows], Tg, T, gs, conf)
            T_out[rows[good]], ok[rows[good]] = T[good], True

    if not scores:
        return DepthRefineResult(T_out, ok, np.full(M, np.nan), rmse, np.full(M, np.nan))
    agree, visible, occluded = _agreement(depth, K, surfaces, T_out, tols)
    inlier_frac = np.where(visible > 0, agree / np.maximum(visible, 1), 0.0)
    denom = visible - occluded
    fit = np.where(denom > 0, agree / np.maximum(denom, 1), 0.0)
    return DepthRefineResult(T_out, ok, inlier_frac, rmse, fit)
