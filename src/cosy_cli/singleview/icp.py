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

All lengths in mm. Vectorised over points; plain Python loops over candidates and iterations.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np

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


@dataclass
class IcpConf:
    iterations: int = 20            # ICP iterations
    max_points: int = 1500          # observed points kept per box (seeded uniform subsample)
    trim_start: float = 0.2         # initial inlier distance, fraction of the object diameter
    trim_end_mm: float = 4.0        # final inlier distance (mm); geometric decay start->end over the iterations
    align_depth: bool = True        # first slide the pose along its camera ray to match the observed depth
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
        self.points_t = np.ascontiguousarray(self.points.T)  # (3, N) for the ICP loop
        self.normals_t = np.ascontiguousarray(self.normals.T)
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
    over the model's box grown by ``reach`` mm: a lookup replaces the tree query in the ICP loop.
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
        self.top = (self.shape - 1).astype(np.float64)[:, None]

    def lookup(self, Q: np.ndarray) -> np.ndarray:
        """Nearest-sample indices (n,) of points Q (3, n) in the object frame (mm)."""
        ijk = np.rint((Q - self.origin[:, None]) * (1.0 / self.h))
        np.clip(ijk, 0.0, self.top, out=ijk)
        return self.index.take((self.strides @ ijk).astype(np.intp))


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
    uniq: dict[int, int] = {}
    rows = np.array([uniq.setdefault(id(s), len(uniq)) for s in surfaces])
    by_id = {id(s): s for s in surfaces}
    P = np.stack([by_id[k].points for k in uniq])[rows]  # (M, N, 3)
    NP = np.stack([by_id[k].n_dot_p for k in uniq])[rows]  # (M, N)
    Nrm = np.stack([by_id[k].normals for k in uniq])[rows]
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


def _align_depth(T: np.ndarray, surf: _Surface, K: np.ndarray, depth: np.ndarray, tol: float) -> np.ndarray:
    """T slid along the camera ray through its origin by the shift (|shift| < diameter) with the
    best score a^2 / (a + v) over the camera-facing model points (``ALIGN_POINTS`` of them) at
    their pixels: a points agree with the observed depth within ``tol`` mm, v lie in front of it
    by more than tol (the model would hide observed surface; points behind it are occluded and
    neutral). Weighting the agreement by its precision keeps a partly occluded object from being
    pulled onto its occluder. A coarse search in steps of tol, then a fine one in steps of tol / 8.
    T itself when the pose is behind the camera or no shift gives any agreement."""
    t = T[:3, 3]
    if t[2] <= 0:
        return T
    H, W = depth.shape
    X = surf.points @ T[:3, :3].T + t
    facing = np.einsum("ij,ij->i", surf.normals @ T[:3, :3].T, X) < -VISIBLE_COS * X[:, 2]
    X = X[facing][:ALIGN_POINTS]  # the samples are in random order: a uniform subset
    if len(X) < 10:
        return T
    ray = t / t[2]
    flat_depth = depth.ravel()

    def agreement(shifts):
        Xs = X[None] + shifts[:, None, None] * ray  # (S, n, 3)
        z = Xs[..., 2]
        ok = z > 1e-6
        zs = np.where(ok, z, 1.0)
        u = np.rint((K[0, 0] * Xs[..., 0] + K[0, 1] * Xs[..., 1]) / zs + K[0, 2])
        v = np.rint(K[1, 1] * Xs[..., 1] / zs + K[1, 2])
        ok &= (u >= 0) & (u < W) & (v >= 0) & (v < H)
        d = flat_depth.take(np.where(ok, v * W + u, 0).astype(np.intp))
        ok &= d > 0
        agree = (ok & (np.abs(d - z) <= tol)).sum(1)
        violate = (ok & (z < d - tol)).sum(1)  # the model would hide observed surface
        return agree * agree / np.maximum(agree + violate, 1)  # agreement x its precision

    half = surf.diameter - tol
    coarse = np.arange(-half, half + 1e-9, tol)
    score = agreement(coarse)
    if score.max() <= 0:
        return T
    best = coarse[np.argmax(score)]
    fine = best + np.arange(-tol, tol + 1e-9, tol / 8)
    score = agreement(fine)
    top = fine[score == score.max()]
    shift = float(np.median(top))
    out = T.copy()
    out[:3, 3] = t + shift * ray
    return out


# ---------------------------------------------------------------------------- ICP


def _icp(T0: np.ndarray, Qc: np.ndarray, surf: _Surface, conf: IcpConf):
    """Trimmed point-to-plane ICP of observed camera points and normals Qc (6, n) (mm) onto the model.
    Returns (T_cam_obj, n_final_inliers, rmse_mm)."""
    T = T0.copy()
    d0 = max(conf.trim_start * surf.diameter, conf.trim_end_mm)
    n_it = max(int(conf.iterations), 1)
    trims = np.geomspace(d0, conf.trim_end_mm, n_it) if n_it > 1 else np.array([conf.trim_end_mm])
    grid = surf.grid(d0)
    scale = surf.diameter / 2  # makes rotation columns commensurate with translation (mm)
    A = np.empty((6, Qc.shape[1]))
    k = 0
    while k < n_it:
        trim = trims[k]
        Q, e, nn, s = _pairs(T, Qc, surf, grid, trim)
        w = 1.0 - s
        w *= w  # biweight of the distance; 0 for rejected pairs
        sw = w.sum()
        if np.count_nonzero(w) < MIN_PAIRS:
            return T, int(np.count_nonzero(w)), np.nan
        c = (Q @ w) / sw
        a = Q - c[:, None]
        r = np.einsum("ij,ij->j", e, nn)
        A[0] = (a[1] * nn[2] - a[2] * nn[1]) / scale
        A[1] = (a[2] * nn[0] - a[0] * nn[2]) / scale
        A[2] = (a[0] * nn[1] - a[1] * nn[0]) / scale
        A[3:] = nn
        Aw = A * w
        Hm = Aw @ A.T
        g = Aw @ r
        Hm.flat[::7] += 1e-6 * sw  # slight damping: directions the data leave free (symmetries) stay put
        x = -np.linalg.solve(Hm, g)
        omega, vel = x[:3] / scale, x[3:]
        Rw = _rodrigues(omega)
        # the step moves the observed points in the object frame: q -> Rw (q - c) + c + vel
        D_inv = np.eye(4)
        D_inv[:3, :3] = Rw.T
        D_inv[:3, 3] = c - Rw.T @ (c + vel)
        T = T @ D_inv
        step = math.sqrt(omega @ omega) * scale + math.sqrt(vel @ vel)  # mm, about the largest point motion
        if step < STEP_TOL * trim:  # converged at this trim: go on with the final one, or stop there
            if k >= n_it - 1:
                break
            k = max(k + 1, min(n_it - 1, k + STEP_SKIP))
        else:
            k += 1
    Q, e, nn, s = _pairs(T, Qc, surf, grid, conf.trim_end_mm)
    keep = s < 1.0
    if not keep.any():
        return T, 0, np.nan
    r = np.einsum("ij,ij->j", e[:, keep], nn[:, keep])
    return T, int(keep.sum()), float(np.sqrt(np.mean(r ** 2)))


def _pairs(T, Qc, surf: _Surface, grid: _NearestGrid, trim: float):
    """Observed points and normals Qc (6, n) (camera frame) in the object frame, paired with their
    nearest model samples: (Q (3, n), e = Q - p (3, n), model normals (3, n), s (n,)) with
    s = squared distance / trim^2, set to 1 (rejected) where it exceeds 1, where the model normal
    faces away from the camera or where the two normals differ by more than acos(NORMAL_COS)."""
    R, t = T[:3, :3], T[:3, 3]
    Q = R.T @ (Qc[:3] - t[:, None])
    j = grid.lookup(Q)
    e = Q - surf.points_t.take(j, axis=1)
    nn = surf.normals_t.take(j, axis=1)
    s = np.einsum("ij,ij->j", e, e) * (1.0 / trim ** 2)
    cam = -R.T @ t  # camera centre in the object frame; |cam - p| ~ |cam| for the facing test
    facing = (cam @ surf.normals_t - surf.n_dot_p) > FACING_COS_ICP * np.linalg.norm(cam)
    same = np.einsum("ij,ij->j", R.T @ Qc[3:], nn) > NORMAL_COS
    s[(s > 1.0) | ~facing.take(j) | ~same] = 1.0
    return Q, e, nn, s


def _rodrigues(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector w (3,) (radians)."""
    x, y, z = (float(c) for c in w)
    th = math.sqrt(x * x + y * y + z * z)
    if th < 1e-12:
        return np.eye(3)
    x, y, z = x / th, y / th, z / th
    s, c = math.sin(th), math.cos(th)
    C = 1.0 - c
    return np.array([[c + x * x * C, x * y * C - z * s, x * z * C + y * s],
                     [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
                     [z * x * C - y * s, z * y * C + x * s, c + z * z * C]])


def _within_change(T0: np.ndarray, Ta: np.ndarray, T: np.ndarray, surf: _Surface, conf: IcpConf) -> bool:
    """Divergence check, modulo the object's symmetries: some pose T S equivalent to the result
    is within ``max_rotation_deg`` of the input rotation and ``max_translation_frac * diameter``
    of the depth-aligned translation."""
    S = surf.symmetries  # (S, 4, 4), identity first; continuous ones discretised
    R = T[:3, :3] @ S[:, :3, :3]
    t = S[:, :3, 3] @ T[:3, :3].T + T[:3, 3]
    cos = (np.einsum("ij,sij->s", T0[:3, :3], R) - 1.0) / 2.0
    ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    dt = np.linalg.norm(t - Ta[:3, 3], axis=1)
    return bool(np.any((ang <= conf.max_rotation_deg) & (dt <= conf.max_translation_frac * surf.diameter)))


def refine_with_depth(depth_mm, K, boxes, obj_ids, T_init, db, conf: IcpConf = IcpConf()) -> DepthRefineResult:
    """Refine candidate poses with a depth map (trimmed point-to-plane ICP, see the module doc).

    depth_mm (H, W) float mm (0 = no measurement); K (3, 3); boxes (M, 4) x1, y1, x2, y2 px in
    pixel-edge coordinates (BOP bbox convention, x2 = x + w); obj_ids (M,); T_init (M, 4, 4)
    T_cam_obj mm; db: cosy_cli.objects.ObjectDatabase. Several rows may share a box (hypotheses
    of one detection). Deterministic under ``conf.seed``.
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
    box_cache: dict[tuple, np.ndarray] = {}
    for i in range(M):
        surf, T0 = surfaces[i], T_in[i]
        key = tuple(boxes[i])
        if key not in box_cache:  # the box's points and normals in a seeded random order, (6, n)
            pts = _box_points(depth, K, boxes[i])
            order = np.random.default_rng([conf.seed, len(box_cache)]).permutation(pts.shape[1])
            box_cache[key] = pts.take(order, axis=1)
        pts = box_cache[key]
        if pts.shape[1] < need or not np.all(np.isfinite(T0)) or T0[2, 3] <= 0:
            continue
        Ta = _align_depth(T0, surf, K, depth, tols[i]) if conf.align_depth else T0
        # the observed points near the object: the first max_points of them (a uniform subsample)
        radius = surf.radius + max(conf.trim_start * surf.diameter, conf.trim_end_mm)
        centre = Ta[:3, :3] @ surf.centre + Ta[:3, 3]
        d = pts[:3] - centre[:, None]
        near = np.flatnonzero(np.einsum("ij,ij->j", d, d) <= radius ** 2)[:conf.max_points]
        if len(near) < need:
            continue
        T, n_in, rms = _icp(Ta, pts.take(near, axis=1), surf, conf)
        rmse[i] = rms
        good = (n_in >= conf.min_inliers and np.all(np.isfinite(T))
                and _within_change(T0, Ta, T, surf, conf))
        if good:
            T_out[i], ok[i] = T, True

    agree, visible, occluded = _agreement(depth, K, surfaces, T_out, tols)
    inlier_frac = np.where(visible > 0, agree / np.maximum(visible, 1), 0.0)
    denom = visible - occluded
    fit = np.where(denom > 0, agree / np.maximum(denom, 1), 0.0)
    return DepthRefineResult(T_out, ok, inlier_frac, rmse, fit)
