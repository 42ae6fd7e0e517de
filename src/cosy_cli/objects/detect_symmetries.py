"""Propose the symmetries of object meshes (``cosy symmetries``).

A symmetry of an object is a proper rotation ``R`` (det +1, no reflections, as in BOP) about an
axis through the centroid ``c`` of the surface (every symmetry maps the surface onto itself, so
it fixes the surface centroid), written as the 4x4 ``S = [R | c - R c]`` (translation in mm) of
``symmetries_discrete``, or a continuous rotation ``{"axis", "offset" (mm)}`` of
``symmetries_continuous`` in ``models_info.json``.

Method
------
1. Exact area moments of the triangles give the centroid and the covariance of the surface.
   Its eigenvalues restrict what can be symmetric: three distinct eigenvalues allow only 180 deg
   rotations about the principal axes; two equal ones (``axial``) allow n-fold or continuous
   rotations about the distinct axis and 180 deg flips about axes perpendicular to it; three
   equal ones (``isotropic``: cube-like) allow anything.
2. Candidate axes for the degenerate cases come from the mesh itself: a rotation axis meets the
   surface where the surface normal is parallel to it (face normals, or the sum of the two
   normals at a crease), or at a corner (directions from the centroid to vertices, edge
   midpoints, face centres). A Fibonacci sphere (or circle of perpendicular directions) adds
   directions for meshes whose triangulation is not itself symmetric.
3. Each candidate rotation (n-fold for n in 2..``max_order``, and 4 generic angles for the
   continuous test) is screened on a few surface points; survivors are verified on
   ``n_points`` seeded surface samples, moved both by S and by S^-1 (both directions), with the
   distance to the surface measured exactly against the mesh triangles (a KD-tree over dense
   surface samples proposes the triangles). S is accepted when the 95th percentile of these
   distances is <= the tolerance and their maximum <= 3 x the tolerance (robust to faceting of
   round parts, strict on features such as handles). A candidate whose axis is slightly off
   (curved or noisy meshes) is refined by ICP restricted to rotations about ``c``, its angle
   snapped back to 2 pi / n, and its axis snapped to a coordinate axis when that also passes.
   An accepted n-fold with 2n, 3n or 5n above ``max_order`` is tried at that order too (16, 24).
4. A continuous symmetry must pass 16 angles that are not multiples of small n-folds. The
   discrete symmetries are the closure (group) of the accepted generators, minus the identity;
   for a continuous axis only the class of the 180 deg flip perpendicular to it is kept (the
   rotations about the axis itself are redundant in BOP's ``C @ D`` expansion). Two continuous
   axes mean a sphere: it is reported as continuous about x, y and z.
5. When the centroid is within half the tolerance of the origin (a BOP model centred up to
   noise) and the symmetries still pass through the origin, the translations are made 0.

The default tolerance is 1 % of the diameter, clipped to [0.5, 2] mm. Meshes split per face
(for colours or flat normals) are welded by position for their topology.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import CosyError
from ..geometry.poses import invert, make_pose, rotation_angle
from ..geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle, rotation_about_axis

DEFAULT_MAX_ORDER = 12
# fractions of a turn for the continuous test (golden-ratio sequence): for every n <= 12 one of them is
# >= 3/4 of half a sector away from the n-fold angles, so no n-fold object passes them all
CONTINUOUS_TEST_TURNS = np.mod(np.arange(1, 17) * (math.sqrt(5.0) - 1.0) / 2.0, 1.0)
SAME_ROTATION_RAD = math.radians(15)  # distinct elements of a group of orders <= 12 are >= 30 deg apart
MAX_RESIDUAL_FACTOR = 3.0  # the max distance may reach 3x the tolerance (the 95th percentile must be under it)


def default_tolerance(diameter_mm: float) -> float:
    """1 % of the diameter, clipped to [0.5, 2] mm."""
    return float(np.clip(0.01 * float(diameter_mm), 0.5, 2.0))


# --------------------------------------------------------------------------------------------
# exact point-to-surface queries
# --------------------------------------------------------------------------------------------
def closest_points_on_triangles(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Closest points (N, 3) on triangles ``tri`` (N, 3, 3) to points ``p`` (N, 3); any unit.

    Vectorised Voronoi-region test (vertex, edge or interior region of each triangle).
    Degenerate (zero-area) triangles fall back to their nearest vertex.
    """
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac = b - a, c - a
    ap, bp, cp = p - a, p - b, p - c
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v_in, w_in = vb / denom, vc / denom
        v_ab = d1 / (d1 - d3)
        w_ac = d2 / (d2 - d6)
        w_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    regions = [
        (d1 <= 0) & (d2 <= 0),  # vertex a
        (d3 >= 0) & (d4 <= d3),  # vertex b
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),  # edge ab
        (d6 >= 0) & (d5 <= d6),  # vertex c
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),  # edge ac
        (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),  # edge bc
    ]
    v = np.select(regions, [0.0, 1.0, v_ab, 0.0, 0.0, 1.0 - w_bc], v_in)
    w = np.select(regions, [0.0, 0.0, 0.0, 1.0, w_ac, w_bc], w_in)
    ok = np.isfinite(v) & np.isfinite(w)
    out = a + np.where(ok, v, 0.0)[:, None] * ab + np.where(ok, w, 0.0)[:, None] * ac
    if not ok.all():  # degenerate triangles: nearest vertex
        bad = ~ok
        V = tri[bad]
        j = np.argmin(np.linalg.norm(V - p[bad, None], axis=-1), axis=1)
        out[bad] = V[np.arange(len(j)), j]
    return out


class SurfaceIndex:
    """Distances (mm) from points to a triangle mesh surface.

    A KD-tree over face centres plus area-uniform samples (each tagged with its triangle)
    proposes ``k`` triangles per query point; the exact closest point over these triangles is
    returned. The result is an upper bound of the true distance that equals it whenever the
    nearest triangle is among the proposals (always, in practice, for points near the surface).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, n_samples: int = 20000, seed: int = 0):
        from scipy.spatial import cKDTree

        self.triangles = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]  # (F, 3, 3)
        tri = self.triangles
        areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        rng = np.random.default_rng(seed)
        n_extra = max(int(n_samples), 0)
        if areas.sum() > 0 and n_extra:
            fid = rng.choice(len(tri), size=n_extra, p=areas / areas.sum())
            r1, r2 = rng.random((2, n_extra))
            flip = r1 + r2 > 1
            r1, r2 = np.where(flip, 1 - r1, r1), np.where(flip, 1 - r2, r2)
            t = tri[fid]
            pts = t[:, 0] + r1[:, None] * (t[:, 1] - t[:, 0]) + r2[:, None] * (t[:, 2] - t[:, 0])
        else:
            fid, pts = np.zeros(0, dtype=np.int64), np.zeros((0, 3))
        self.sample_face = np.concatenate([np.arange(len(tri)), fid])
        self.spacing = float(np.sqrt(areas.sum() / max(len(self.sample_face), 1)))  # mm between samples
        self.tree = cKDTree(np.concatenate([tri.mean(1), pts]))
        self.neighbours = _edge_neighbours(weld(vertices, faces)[1])

    def _walk(self, P: np.ndarray, best: np.ndarray, cp: np.ndarray, d: np.ndarray, steps: int):
        """Greedy descent over edge-adjacent triangles, for the points that still improve: fixes
        proposals that stopped short (the other half of a split quad, the face across a crease,
        the thin triangles of a fan)."""
        active = np.arange(len(P))
        for _ in range(steps):
            nb = self.neighbours[best[active]]  # (n, 3)
            Pa = P[active]
            cpn = closest_points_on_triangles(np.repeat(Pa, 3, axis=0), self.triangles[nb.ravel()]).reshape(-1, 3, 3)
            dn = np.linalg.norm(cpn - Pa[:, None], axis=-1)
            j = np.argmin(dn, axis=1)
            r = np.arange(len(active))
            better = dn[r, j] < d[active] - 1e-12
            if not better.any():
                break
            idx = active[better]
            best[idx] = nb[r, j][better]
            cp[idx] = cpn[r, j][better]
            d[idx] = dn[r, j][better]
            active = idx
        return cp, d

    def closest(self, points: np.ndarray, k: int = 4, walk: int = 16, bound: float = np.inf,
                recheck_mm: float | None = None, chunk: int = 40000) -> tuple[np.ndarray, np.ndarray]:
        """(closest points (N, 3) mm, distances (N,) mm) for points (N, 3) mm: the best of ``k``
        proposed triangles, then ``walk`` steps over edge-adjacent triangles. Points still farther
        than ``recheck_mm`` are queried again with 8k proposals (the walk can stop at a fold).
        Points with no surface sample within ``bound`` mm get distance inf and closest point nan
        (fast: the KD-tree search of far points is what costs)."""
        cp, d = self._closest(points, k, walk, bound, chunk)
        if recheck_mm is not None:
            again = np.flatnonzero(np.isfinite(d) & (d > recheck_mm))
            if len(again):
                cp2, d2 = self._closest(np.asarray(points, dtype=np.float64)[again], 8 * k, walk, bound, chunk)
                better = d2 < d[again]
                cp[again[better]], d[again[better]] = cp2[better], d2[better]
        return cp, d

    def _closest(self, points, k, walk, bound, chunk):
        points = np.asarray(points, dtype=np.float64)
        k = int(min(k, self.tree.n))
        cp_out = np.full_like(points, np.nan)
        d_out = np.full(len(points), np.inf)
        for s in range(0, len(points), chunk):
            P = points[s:s + chunk]
            _, idx = self.tree.query(P, k=k, distance_upper_bound=bound)
            idx = idx.reshape(len(P), k)
            near = np.flatnonzero(idx[:, 0] < self.tree.n)
            if len(near) == 0:
                continue
            P, idx = P[near], idx[near]
            valid = idx < self.tree.n
            faces = self.sample_face[np.where(valid, idx, idx[:, :1])]  # (n, k); misses repeat the nearest
            Pk = np.repeat(P, k, axis=0)
            cp = closest_points_on_triangles(Pk, self.triangles[faces.ravel()]).reshape(len(P), k, 3)
            d = np.linalg.norm(cp - P[:, None], axis=-1)
            j = np.argmin(d, axis=1)
            r = np.arange(len(P))
            cp_w, d_w = self._walk(P, faces[r, j].copy(), cp[r, j], d[r, j], walk)
            cp_out[s + near], d_out[s + near] = cp_w, d_w
        return cp_out, d_out

    def distance(self, points: np.ndarray, k: int = 4, walk: int = 16, bound: float = np.inf,
                 recheck_mm: float | None = None) -> np.ndarray:
        return self.closest(points, k, walk, bound, recheck_mm)[1]


def weld(vertices: np.ndarray, faces: np.ndarray, rel_tol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (U, 3), faces (F, 3)) where vertices at the same position (within ``rel_tol`` of
    the mesh size) are one: meshes split per face for colours or flat normals keep their topology."""
    V = np.asarray(vertices, dtype=np.float64)
    scale = max(float(np.abs(V).max(initial=0.0)), 1e-12) * rel_tol
    _, first, inverse = np.unique(np.round(V / scale).astype(np.int64), axis=0, return_index=True,
                                  return_inverse=True)
    return V[first], inverse.reshape(-1)[np.asarray(faces)]


def _edge_neighbours(faces: np.ndarray) -> np.ndarray:
    """(F, 3): for each triangle edge (v0v1, v1v2, v2v0) a triangle sharing it (itself if none)."""
    F = len(faces)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    key = edges[:, 0] * (int(faces.max(initial=0)) + 1) + edges[:, 1]
    order = np.argsort(key, kind="stable")
    sl = order  # slot = k * F + f
    same = key[order][1:] == key[order][:-1]
    nb = np.tile(np.arange(F), 3)
    a, b = sl[:-1][same], sl[1:][same]
    nb[a] = b % F
    nb[b] = np.where(nb[b] == b % F, a % F, nb[b])  # non-manifold edges: keep one neighbour
    return nb.reshape(3, F).T


# --------------------------------------------------------------------------------------------
# surface moments and candidate axes
# --------------------------------------------------------------------------------------------
def surface_moments(vertices: np.ndarray, faces: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(area mm^2, centroid (3,) mm, covariance (3, 3) mm^2) of the surface, exact for triangles."""
    V = np.asarray(vertices, dtype=np.float64)
    tri = V[np.asarray(faces)]
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    area = float(areas.sum())
    if area <= 0:
        raise ValueError("the mesh has zero surface area")
    centroid = (areas[:, None] * tri.mean(1)).sum(0) / area
    t = tri - centroid
    s = t.sum(1)
    # mean of x x^T over a triangle = (sum_i v_i v_i^T + s s^T) / 12, s = sum of the vertices
    second = np.einsum("f,fvi,fvj->ij", areas, t, t) + np.einsum("f,fi,fj->ij", areas, s, s)
    return area, centroid, second / (12.0 * area)


def _fibonacci_hemisphere(n: int) -> np.ndarray:
    """~n unit directions evenly spread over the upper hemisphere (axes are sign-agnostic)."""
    m = 2 * n
    i = np.arange(m) + 0.5
    z = 1 - 2 * i / m
    phi = np.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(1 - z * z)
    d = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)
    return d[z > 0]


def _feature_directions(vertices: np.ndarray, faces: np.ndarray, centroid: np.ndarray) -> np.ndarray:
    """Unnormalised directions where a symmetry axis may meet the surface (see module doc)."""
    V, F = weld(vertices, faces)  # shared edges between faces split for colours or normals
    V = V - centroid
    tri = V[F]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nn = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(nn > 0, n / np.maximum(nn, 1e-300), 0.0)
    edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    key = edges[:, 0] * len(V) + edges[:, 1]
    order = np.argsort(key, kind="stable")
    f_sorted = np.tile(np.arange(len(F)), 3)[order]
    same = key[order][1:] == key[order][:-1]
    crease = n[f_sorted[:-1][same]] + n[f_sorted[1:][same]]  # normal sums at shared edges
    _, first = np.unique(key, return_index=True)
    return np.concatenate([n, crease, V, V[edges[first]].mean(1), tri.mean(1)])


def _unit(d: np.ndarray, min_norm: float = 1e-9) -> np.ndarray:
    nrm = np.linalg.norm(d, axis=-1)
    keep = nrm > min_norm
    return d[keep] / nrm[keep, None]


def _rank_axes(dirs: np.ndarray, cap: int, resolution: float = 0.01) -> np.ndarray:
    """Distinct axes (sign-agnostic, ~0.6 deg bins), most supported first, at most ``cap``."""
    u = _unit(dirs)
    if len(u) == 0:
        return np.zeros((0, 3))
    outer = np.stack([u[:, 0] ** 2, u[:, 1] ** 2, u[:, 2] ** 2, u[:, 0] * u[:, 1], u[:, 0] * u[:, 2],
                      u[:, 1] * u[:, 2]], 1)
    q = np.round(outer / resolution).astype(np.int64) + int(round(1 / resolution)) + 1  # in [0, 2/res + 2]
    base = 2 * int(round(1 / resolution)) + 3
    keys = q @ (base ** np.arange(6, dtype=np.int64))  # one integer per bin (< 2^63 for res >= 0.001)
    _, first, counts = np.unique(keys, return_index=True, return_counts=True)
    best = first[np.argsort(-counts, kind="stable")][:cap]
    return u[best]


def _rank_perpendicular(dirs: np.ndarray, axis: np.ndarray, cap: int, bin_deg: float = 0.5) -> np.ndarray:
    """Directions perpendicular to ``axis`` (projections of ``dirs``), binned by angle mod 180 deg."""
    e1, e2 = _perpendicular_basis(axis)
    x, y = dirs @ e1, dirs @ e2
    r = np.hypot(x, y)
    keep = r > 1e-6 * max(float(np.abs(dirs).max(initial=0.0)), 1e-9)
    ang = np.mod(np.arctan2(y[keep], x[keep]), np.pi)
    bins = np.round(np.degrees(ang) / bin_deg).astype(np.int64) % int(round(180 / bin_deg))
    if len(bins) == 0:
        return np.zeros((0, 3))
    _, first, counts = np.unique(bins, return_index=True, return_counts=True)
    a = ang[first[np.argsort(-counts, kind="stable")][:cap]]  # an actual direction of each bin, not its centre
    return np.cos(a)[:, None] * e1 + np.sin(a)[:, None] * e2


def _perpendicular_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane perpendicular to ``axis``; the first is the projection
    of the coordinate axis least aligned with ``axis`` (x for z, so flips come out about x)."""
    a = axis / np.linalg.norm(axis)
    e = np.eye(3)[int(np.argmin(np.abs(a)))]
    e1 = e - (e @ a) * a
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(a, e1)


def _canonical_axis(u: np.ndarray) -> np.ndarray:
    """Unit axis with its largest component positive."""
    u = np.asarray(u, dtype=np.float64)
    u = u / np.linalg.norm(u)
    return -u if u[int(np.argmax(np.abs(u)))] < 0 else u


def _snap_to_coordinate_axis(u: np.ndarray, max_deg: float = 1.0) -> np.ndarray | None:
    i = int(np.argmax(np.abs(u)))
    e = np.zeros(3)
    e[i] = np.sign(u[i])
    if np.degrees(np.arccos(np.clip(abs(float(u @ e)), -1, 1))) < max_deg and not np.allclose(u, e, atol=0, rtol=0):
        return e
    return None


def _kabsch(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Rotation R minimising sum ||R a_i - b_i||^2 (no translation)."""
    H = A.T @ B
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def _clean(x: np.ndarray, decimals: int) -> np.ndarray:
    return np.round(x, decimals) + 0.0  # +0.0 turns -0.0 into 0.0


# --------------------------------------------------------------------------------------------
# the detector
# --------------------------------------------------------------------------------------------
@dataclass
class SymmetryProposal:
    """Symmetries proposed for one mesh (model frame, mm)."""

    symmetries_discrete: np.ndarray  # (K, 4, 4), identity excluded, translation mm
    symmetries_continuous: list[dict]  # [{"axis": (3,), "offset": (3,) mm}]
    centroid: np.ndarray  # (3,) mm: the point every symmetry axis passes through
    tolerance_mm: float
    residual_max_mm: float  # worst distance to the surface over the accepted symmetries (0 if none)
    residual_p95_mm: float
    inertia: str  # "distinct" | "axial" | "isotropic" (equal eigenvalues of the surface covariance)
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)


class SymmetryDetector:
    """Proposes the symmetries of one mesh; see the module docstring for the method."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, tolerance_mm: float, *, n_points: int = 1000,
                 seed: int = 0, max_order: int = DEFAULT_MAX_ORDER, degeneracy: float = 0.05,
                 n_index_samples: int = 20000):
        self.V = np.asarray(vertices, dtype=np.float64)
        self.F = np.asarray(faces, dtype=np.int64)
        self.tol = float(tolerance_mm)
        self.max_order = int(max_order)
        self.degeneracy = float(degeneracy)
        self.area, self.c, self.cov = surface_moments(self.V, self.F)
        self.index = SurfaceIndex(self.V, self.F, n_samples=n_index_samples, seed=seed)
        rng = np.random.default_rng(seed)
        self.P = self._sample(rng, n_points)
        self.P_refine = self.P[: min(300, len(self.P))]
        self.P_screen = self._sample(rng, 64)
        self.radius = float(np.linalg.norm(self.V - self.c, axis=1).max())
        self.notes: list[str] = []
        self.n_refined = 0

    def _sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        tri = self.index.triangles
        areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        fid = rng.choice(len(tri), size=n, p=areas / areas.sum())
        r1, r2 = rng.random((2, n))
        flip = r1 + r2 > 1
        r1, r2 = np.where(flip, 1 - r1, r1), np.where(flip, 1 - r2, r2)
        t = tri[fid]
        return t[:, 0] + r1[:, None] * (t[:, 1] - t[:, 0]) + r2[:, None] * (t[:, 2] - t[:, 0])

    # transforms ---------------------------------------------------------------------------
    def about_centroid(self, R: np.ndarray) -> np.ndarray:
        """4x4 transforms (..., 4, 4) of rotations R (..., 3, 3) about axes through the centroid."""
        R = np.asarray(R, dtype=np.float64)
        return make_pose(R, self.c - R @ self.c)

    def residuals(self, T: np.ndarray, points: np.ndarray | None = None, k: int = 4) -> tuple[np.ndarray, np.ndarray]:
        """(max, 95th percentile) distance in mm of T p and T^-1 p to the surface, per T (K, 4, 4)."""
        T = np.asarray(T, dtype=np.float64).reshape(-1, 4, 4)
        P = self.P if points is None else points
        both = np.concatenate([T, invert(T)])
        moved = P[None] @ np.swapaxes(both[:, :3, :3], -1, -2) + both[:, None, :3, 3]
        d = self.index.distance(moved.reshape(-1, 3), k=k).reshape(2, len(T), len(P))
        d = np.concatenate([d[0], d[1]], axis=1)  # (K, 2N)
        # distances are upper bounds: re-query, with more proposals, those that decide the statistics
        again = d > np.maximum(0.05 * self.tol, np.percentile(d, 90, axis=1, keepdims=True))
        if again.any():
            pts = np.concatenate([moved[:len(T)], moved[len(T):]], axis=1)[again]
            d[again] = np.minimum(d[again], self.index.distance(pts, k=8 * k))
        return d.max(1), np.percentile(d, 95, axis=1)

    def passes(self, mx: np.ndarray, p95: np.ndarray) -> np.ndarray:
        return (p95 <= self.tol) & (mx <= MAX_RESIDUAL_FACTOR * self.tol)

    def screen(self, R: np.ndarray, threshold: float) -> np.ndarray:
        """Cheap score (mm) of rotations R (K, 3, 3) about the centroid: the largest forward
        distance of 64 points (a slightly wrong axis moves every point a little, a wrong symmetry
        moves some points far); inf once it exceeds ``threshold``. The first 16 points weed out
        most candidates; the KD-tree search is bounded, as far points are what costs."""
        bound = threshold + 3.0 * self.index.spacing
        scores = np.zeros(len(R))
        alive = np.arange(len(R))
        for part in (self.P_screen[:16], self.P_screen[16:]):
            if len(alive) == 0:
                break
            P = part - self.c
            moved = P[None] @ np.swapaxes(R[alive], -1, -2) + self.c
            d = self.index.distance(moved.reshape(-1, 3), k=1, walk=4, bound=bound).reshape(len(alive), len(P))
            scores[alive] = np.maximum(scores[alive], d.max(axis=1))
            scores[alive[scores[alive] > threshold]] = np.inf
            alive = alive[scores[alive] <= threshold]
        return scores

    def refine(self, R0: np.ndarray, iters: int = 12) -> np.ndarray:
        """ICP over rotations about the centroid, from R0 (3, 3)."""
        self.n_refined += 1
        A = self.P_refine - self.c
        R = R0
        for it in range(iters):
            C, d = self.index.closest(A @ R.T + self.c, k=4)
            if it >= 4 and np.median(d) > 2 * self.tol:
                break  # not converging to a symmetry
            keep = d <= np.quantile(d, 0.9) + 1e-12
            R_new = _kabsch(A[keep], C[keep] - self.c)
            step = float(rotation_angle(R_new @ R.T))
            R = R_new
            if step < 1e-7:
                break
        return R

    # accepting one rotation ---------------------------------------------------------------
    def _try_axes(self, axes: list[np.ndarray], angles: np.ndarray):
        """First axis whose rotations by all ``angles`` pass; (axis, max, p95) or None."""
        for u in axes:
            got = self._evaluate(u, angles)
            if got[3]:
                return got[:3]
        return None

    def accept(self, u: np.ndarray, angles: np.ndarray, refine_angle: float):
        """Verify rotations by ``angles`` about ``u``; returns (axis, max, p95) or None.

        The axis is snapped to a coordinate axis when that passes. Otherwise, unless ``u`` is
        exact (95th percentile ~0), it is refined by ICP and the better of the two is kept.
        """
        u = _canonical_axis(u)
        snapped = _snap_to_coordinate_axis(u)
        if snapped is not None:
            got = self._evaluate(snapped, angles)
            if got[3]:
                return got[:3]
        first = self._evaluate(u, angles)
        if first[3] and first[2] <= 1e-3 * self.tol:
            return first[:3]
        R = self.refine(rotation_about_axis(u, np.array([refine_angle]))[0])
        rv = matrix_to_axis_angle(R)
        options = [first]
        if np.linalg.norm(rv) > 1e-6:
            u2 = _canonical_axis(rv)
            if abs(float(u2 @ u)) > math.cos(math.radians(15)):  # else it drifted to another symmetry
                snapped = _snap_to_coordinate_axis(u2)
                if snapped is not None:
                    got = self._evaluate(snapped, angles)
                    if got[3]:
                        return got[:3]
                options.append(self._evaluate(u2, angles))
        ok = [o for o in options if o[3]]
        return min(ok, key=lambda o: (o[2], o[1]))[:3] if ok else None

    def _evaluate(self, u: np.ndarray, angles: np.ndarray):
        """(axis, max, p95, all pass) for rotations by ``angles`` about ``u``."""
        u = u / np.linalg.norm(u)
        T = self.about_centroid(rotation_about_axis(u, angles))
        for P in (self.P[:250], self.P):  # most failures show on a quarter of the points
            mx, p95 = self.residuals(T, P)
            ok = bool(self.passes(mx, p95).all())
            if not ok:
                break
        return u, float(mx.max()), float(p95.max()), ok

    # main -----------------------------------------------------------------------------------
    def run(self) -> SymmetryProposal:
        t0 = time.perf_counter()
        w, E = np.linalg.eigh(self.cov)
        scale = max(float(w[2]), 1e-12)
        g01, g12 = (w[1] - w[0]) / scale, (w[2] - w[1]) / scale
        screen_thr = max(4 * self.tol, 0.02 * self.radius * 2)
        orders = np.arange(2, self.max_order + 1)
        cont_angles = 2 * np.pi * CONTINUOUS_TEST_TURNS

        # candidate (axis, allowed orders, continuous allowed)
        if g01 < self.degeneracy and g12 < self.degeneracy:
            inertia = "isotropic"
            feats = _feature_directions(self.V, self.F, self.c)
            axes = np.concatenate([E.T, _rank_axes(feats, 200), _fibonacci_hemisphere(60)])
            cands = [(a, orders, True) for a in axes]
        elif g01 < self.degeneracy or g12 < self.degeneracy:
            inertia = "axial"
            a = E[:, 2] if g01 < self.degeneracy else E[:, 0]
            feats = _feature_directions(self.V, self.F, self.c)
            perp = np.concatenate([_rank_perpendicular(feats, a, 120), _rank_perpendicular(
                np.concatenate([E.T, np.eye(3)]), a, 6), _uniform_perpendicular(a, 60)])
            cands = [(a, orders, True)] + [(p, np.array([2]), False) for p in perp]
        else:
            inertia = "distinct"
            cands = [(E[:, i], np.array([2]), False) for i in range(3)]

        # 1. continuous axes
        continuous: list[np.ndarray] = []
        cont_axes = [a for a, _, cont in cands if cont]
        if cont_axes:
            A = np.stack(cont_axes)
            Rs = np.stack([rotation_about_axis(a, cont_angles[:4]) for a in A])  # (N, 4, 3, 3)
            scores = self.screen(Rs.reshape(-1, 3, 3), screen_thr).reshape(len(A), 4).max(1)
            for i in np.argsort(scores):
                if scores[i] > screen_thr or len(continuous) >= 2 or self.n_refined > 40:
                    break
                if any(abs(float(A[i] @ c)) > math.cos(math.radians(3)) for c in continuous):
                    continue
                got = self.accept(A[i], cont_angles, refine_angle=cont_angles[0])
                if got is not None and not any(abs(float(got[0] @ c)) > math.cos(math.radians(1)) for c in continuous):
                    continuous.append(got[0])
        if len(continuous) >= 2:  # a sphere: continuous about every axis
            sphere = [e for e in np.eye(3) if self._try_axes([e], cont_angles) is not None]
            if len(sphere) == 3:
                continuous = list(np.eye(3))
                self.notes.append("sphere-like: continuous about every axis; listed about x, y and z")
            else:
                self.notes.append("continuous about two axes (sphere-like?): listed as found")
            return self._proposal(np.zeros((0, 3, 3)), continuous, inertia, t0)
        if continuous:
            a = continuous[0]
            e1, e2 = _perpendicular_basis(a)
            flip = None
            for b in (e1, e2):
                got = self._try_axes([b], np.array([np.pi]))
                if got is not None:
                    flip = rotation_about_axis(got[0], np.array([np.pi]))[0]
                    break
            return self._proposal(np.zeros((0, 3, 3)) if flip is None else flip[None], continuous, inertia, t0)

        # 2. discrete: screen every (axis, n), verify the best, close the group
        items = [(a, n) for a, ns, _ in cands for n in ns]
        if not items:
            return self._proposal(np.zeros((0, 3, 3)), [], inertia, t0)
        A = np.stack([a for a, _ in items])
        N = np.array([n for _, n in items])
        Rs = axis_angle_to_matrix(A * (2 * np.pi / N)[:, None])
        scores = self.screen(Rs, screen_thr)
        # best scores first (exact candidates ~0 mm), higher orders first among equal scores
        order = [i for i in np.lexsort((-N, np.floor(scores / (0.1 * self.tol)))) if scores[i] <= screen_thr]
        tried: list[tuple[np.ndarray, int]] = []
        group = np.eye(3)[None]
        gens: list[np.ndarray] = []
        for i in order:
            if self.n_refined > 40:
                self.notes.append("stopped after 40 refined candidates")
                break
            if _angle_to_set(Rs[i], group) < SAME_ROTATION_RAD:
                continue
            if any(n == N[i] and abs(float(u @ A[i])) > math.cos(math.radians(3)) for u, n in tried):
                continue
            tried.append((A[i], int(N[i])))
            got = self.accept(A[i], np.array([2 * np.pi / N[i]]), refine_angle=2 * np.pi / N[i])
            if got is None:
                continue
            u, n = got[0], int(N[i])
            n = self._escalate_order(u, n)
            R = rotation_about_axis(u, np.array([2 * np.pi / n]))[0]
            if _angle_to_set(R, group) < SAME_ROTATION_RAD:
                continue  # a looser copy of a symmetry already found
            new_group = _closure(gens + [R])
            if new_group is None:
                self.notes.append(f"{n}-fold rotation about {_axis_name(u)} passes but makes an infinite group: "
                                  "skipped")
                continue
            gens.append(R)
            group = new_group
        return self._proposal(group[1:], [], inertia, t0)

    def _escalate_order(self, u: np.ndarray, n: int, limit: int = 60) -> int:
        """Orders above max_order (16 when 8 passes, 24 when 12 passes): try 2n, 3n, 5n."""
        grown = True
        while grown:
            grown = False
            for k in (2, 3, 5):
                m = n * k
                if self.max_order < m <= limit and self._try_axes([u], np.array([2 * np.pi / m])) is not None:
                    n, grown = m, True
                    break
        return n

    def _final_check(self, group_R: np.ndarray, continuous: list[np.ndarray]):
        """(discrete 4x4 (K, 4, 4), their pass mask, max, p95 over every output symmetry)."""
        U, _, Vt = np.linalg.svd(group_R.reshape(-1, 3, 3))  # re-orthonormalise the products
        R = _clean(U @ Vt, 12)
        if len(R):  # readable order: by angle, then by axis
            rv = matrix_to_axis_angle(R)
            ang = np.round(np.linalg.norm(rv, axis=1), 6)
            ax = np.round(np.stack([_canonical_axis(v) for v in rv]), 6)
            R = R[np.lexsort((-ax[:, 0], -ax[:, 1], -ax[:, 2], ang))]
        T = self.about_centroid(R)
        T[:, :3, 3] = _clean(T[:, :3, 3], 9)
        cont = [self.about_centroid(rotation_about_axis(a, 2 * np.pi * CONTINUOUS_TEST_TURNS)) for a in continuous]
        allT = np.concatenate([T] + cont)
        if len(allT) == 0:
            return T, np.zeros(0, bool), 0.0, 0.0
        mx, p95 = self.residuals(allT)
        ok = self.passes(mx, p95)
        keep = ok[:len(T)]
        use = np.concatenate([keep, ok[len(T):]])
        return T, keep, float(mx[use].max(initial=0.0)), float(p95[use].max(initial=0.0))

    def _proposal(self, group_R: np.ndarray, continuous: list[np.ndarray], inertia: str, t0: float) -> SymmetryProposal:
        T, keep, mx, p95 = self._final_check(group_R, continuous)
        # a model centred at the origin up to noise: let the axes pass through the origin if that passes too
        off = float(np.linalg.norm(self.c))
        if 1e-6 < off <= 0.5 * self.tol and (len(group_R) or continuous):
            c, self.c = self.c, np.zeros(3)
            T0, keep0, mx0, p950 = self._final_check(group_R, continuous)
            if keep0.sum() >= keep.sum() and mx0 <= MAX_RESIDUAL_FACTOR * self.tol and p950 <= self.tol:
                T, keep, mx, p95 = T0, keep0, mx0, p950
                self.notes.append(f"axes moved through the origin (the surface centroid is {off:.2g} mm off it)")
            else:
                self.c = c
        if not keep.all():
            self.notes.append(f"{int((~keep).sum())} products of the found symmetries fail the surface test: dropped")
        conts = []
        for a in continuous:
            a = _clean(_canonical_axis(a), 12)
            a = a / np.linalg.norm(a)
            offset = self.c - (self.c @ a) * a  # the point of the axis closest to the origin
            conts.append({"axis": a, "offset": _clean(offset, 9)})
        return SymmetryProposal(T[keep], conts, self.c.copy(), self.tol, mx, p95, inertia,
                                time.perf_counter() - t0, list(self.notes))


def _uniform_perpendicular(axis: np.ndarray, n: int) -> np.ndarray:
    e1, e2 = _perpendicular_basis(axis)
    a = np.pi * (np.arange(n) + 0.5) / n
    return np.cos(a)[:, None] * e1 + np.sin(a)[:, None] * e2


def _angle_to_set(R: np.ndarray, group: np.ndarray) -> float:
    return float(rotation_angle(np.swapaxes(group, -1, -2) @ R).min())


def _closure(gens: list[np.ndarray], max_size: int = 240, tol_deg: float = 1.5) -> np.ndarray | None:
    """The group (G, 3, 3) generated by rotations ``gens``, identity first; None when it exceeds
    ``max_size`` (generators that do not make a finite group). Products within ``tol_deg`` of an
    element are that element: generators refined on noisy meshes are a little off, and distinct
    elements of a group with orders <= 60 are >= 6 deg apart."""
    G = [np.eye(3)]
    frontier = [np.eye(3)]
    tol = math.radians(tol_deg)
    while frontier:
        new = []
        for g in frontier:
            for h in gens:
                x = h @ g
                if _angle_to_set(x, np.stack(G)) > tol:
                    G.append(x)
                    new.append(x)
                    if len(G) > max_size:
                        return None
        frontier = new
    return np.stack(G)


def diameter_estimate(points: np.ndarray, rounds: int = 4) -> float:
    """A fast lower bound (mm) of the diameter, exact for most shapes: repeated farthest points
    (the exact :func:`diameter_of` is quadratic in the hull size, slow for fine round meshes)."""
    P = np.asarray(points, dtype=np.float64)
    best, p = 0.0, P[int(np.argmax(np.linalg.norm(P - P.mean(0), axis=1)))]
    for _ in range(rounds):
        d = np.linalg.norm(P - p, axis=1)
        i = int(np.argmax(d))
        if d[i] <= best:
            break
        best, p = float(d[i]), P[i]
    return best


def detect_symmetries(mesh, tolerance_mm: float | None = None, *, diameter_mm: float | None = None,
                      n_points: int = 1000, seed: int = 0, max_order: int = DEFAULT_MAX_ORDER) -> SymmetryProposal:
    """Propose the discrete and continuous symmetries of a trimesh mesh (vertices in mm).

    ``tolerance_mm``: largest 95th-percentile distance (mm) between the moved surface samples and
    the surface; default :func:`default_tolerance` of ``diameter_mm`` (computed when not given).
    """
    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.faces, dtype=np.int64)
    if tolerance_mm is None:
        tolerance_mm = default_tolerance(diameter_estimate(V) if diameter_mm is None else diameter_mm)
    if tolerance_mm <= 0:
        raise CosyError(f"the tolerance must be > 0 mm, got {tolerance_mm}")
    return SymmetryDetector(V, F, tolerance_mm, n_points=n_points, seed=seed, max_order=max_order).run()


# --------------------------------------------------------------------------------------------
# describing and comparing symmetry sets
# --------------------------------------------------------------------------------------------
def _axis_name(u: np.ndarray) -> str:
    u = _canonical_axis(u)
    for i, name in enumerate("xyz"):
        if abs(u[i]) > 1 - 1e-9:
            return name
    return "[" + ",".join(f"{x:.3g}" for x in u) + "]"


def rotation_axes(S: np.ndarray) -> list[tuple[np.ndarray, int]]:
    """The distinct rotation axes of symmetries S (K, 4, 4) with their order (elements about the
    axis + 1), highest order first."""
    axes: list[list] = []
    for R in np.asarray(S).reshape(-1, 4, 4)[:, :3, :3]:
        rv = matrix_to_axis_angle(R)
        if np.linalg.norm(rv) < 1e-6:
            continue
        u = _canonical_axis(rv)
        for entry in axes:
            if abs(float(entry[0] @ u)) > 1 - 1e-6:
                entry[1] += 1
                break
        else:
            axes.append([u, 1])
    return sorted([(u, k + 1) for u, k in axes], key=lambda e: -e[1])


def describe_discrete(S: np.ndarray, max_listed: int = 4) -> str:
    """'3: 2-fold x, 2-fold y, 2-fold z'; for many axes '7: 4-fold z, 4 x 2-fold' or
    '23: 3 x 4-fold, 4 x 3-fold, 6 x 2-fold'."""
    S = np.asarray(S).reshape(-1, 4, 4)
    if len(S) == 0:
        return "-"
    axes = rotation_axes(S)
    if len(axes) <= max_listed:
        body = ", ".join(f"{n}-fold {_axis_name(u)}" for u, n in axes)
    else:  # an axis alone with its order is named, the others counted
        parts = []
        for n in sorted({n for _, n in axes}, reverse=True):
            same = [u for u, m in axes if m == n]
            parts.append(f"{n}-fold {_axis_name(same[0])}" if len(same) == 1 else f"{len(same)} x {n}-fold")
        body = ", ".join(parts)
    return f"{len(S)}: {body}"


def describe_continuous(conts: list[dict]) -> str:
    if not conts:
        return "-"
    out = []
    for c in conts:
        s = _axis_name(c["axis"])
        off = np.asarray(c.get("offset", np.zeros(3)), dtype=np.float64)
        if np.abs(off).max() > 1e-6:
            s += " @(" + ",".join(f"{x:.3g}" for x in off) + ")"
        out.append(s)
    return ", ".join(out)


def _same_line(a1, o1, a2, o2, tol_mm: float) -> bool:
    a1 = np.asarray(a1, float) / np.linalg.norm(a1)
    a2 = np.asarray(a2, float) / np.linalg.norm(a2)
    if abs(float(a1 @ a2)) < math.cos(math.radians(1.0)):
        return False
    d = np.asarray(o2, float) - np.asarray(o1, float)
    return float(np.linalg.norm(d - (d @ a1) * a1)) <= tol_mm


def compare_symmetries(disc_a: np.ndarray, cont_a: list[dict], disc_b: np.ndarray, cont_b: list[dict],
                       tol_mm: float) -> bool:
    """Whether two symmetry descriptions give the same set C @ D (rotations within 1 deg,
    translations within ``tol_mm``), whatever representatives of the discrete classes they list."""
    if len(cont_a) != len(cont_b):
        return False
    for ca in cont_a:
        if not any(_same_line(ca["axis"], ca.get("offset", np.zeros(3)), cb["axis"], cb.get("offset", np.zeros(3)),
                              tol_mm) for cb in cont_b):
            return False
    Da = np.concatenate([np.eye(4)[None], np.asarray(disc_a, float).reshape(-1, 4, 4)])
    Db = np.concatenate([np.eye(4)[None], np.asarray(disc_b, float).reshape(-1, 4, 4)])

    if cont_a:
        a = np.asarray(cont_a[0]["axis"], float)
        a = a / np.linalg.norm(a)
        o = np.asarray(cont_a[0].get("offset", np.zeros(3)), float)

        def same(g, h):  # g^-1 h is a rotation about the continuous axis
            T = invert(g) @ h
            return (np.degrees(np.arccos(np.clip(float(T[:3, :3] @ a @ a), -1, 1))) < 1.0
                    and np.linalg.norm(T[:3, :3] @ o + T[:3, 3] - o) <= tol_mm)
    else:
        def same(g, h):
            return (np.degrees(rotation_angle(g[:3, :3].T @ h[:3, :3])) < 1.0
                    and np.linalg.norm(g[:3, 3] - h[:3, 3]) <= tol_mm)

    return all(any(same(g, h) for h in Db) for g in Da) and all(any(same(h, g) for g in Da) for h in Db)


# --------------------------------------------------------------------------------------------
# the command: a models folder in, a report (and models_info.json) out
# --------------------------------------------------------------------------------------------
@dataclass
class ObjectReport:
    obj_id: int
    proposal: SymmetryProposal
    existing: str  # "agree" | "differ" | "none" (no models_info.json entry to compare with)
    existing_failing: int = 0  # existing discrete symmetries that fail the surface test
    existing_residual_mm: float = 0.0


def _list_models(models_dir: Path) -> dict[int, Path]:
    out = {}
    for p in sorted(models_dir.glob("obj_*.ply")):
        try:
            out[int(p.stem[4:])] = p
        except ValueError:
            continue
    return out


def main(models_dir: str | Path, *, write: bool = False, tolerance_mm: float | None = None,
         obj_ids: list[int] | None = None, n_points: int = 1000, seed: int = 0,
         echo: Callable[[str], None] = print, progress: bool | None = None) -> list[ObjectReport]:
    """Propose the symmetries of every (or the chosen) object of a BOP ``models/`` folder, print
    a table and a comparison with ``models_info.json``, and with ``write`` update that file
    (only the two symmetry fields of the processed objects change; the file is created from the
    meshes when missing)."""
    from ..console import progress as progress_bar

    from ..io import bop
    from .database import load_mesh, model_info_from_mesh

    models_dir = Path(models_dir)
    if not models_dir.is_dir():
        raise CosyError("models folder not found", path=models_dir)
    if tolerance_mm is not None and not tolerance_mm > 0:
        raise CosyError(f"--tolerance-mm must be > 0 mm, got {tolerance_mm}")
    info_path = models_dir / "models_info.json"
    meshes_on_disk = _list_models(models_dir)
    have_info = info_path.is_file()
    # keep_bad: a declared symmetry that is not a rotation is reported and replaced here, not refused
    infos = bop.read_models_info(info_path, rotations="keep_bad") if have_info else {}
    if not have_info and not meshes_on_disk:
        raise CosyError("no models_info.json and no obj_XXXXXX.ply meshes in the models folder", path=models_dir)
    known = sorted(infos) if have_info else sorted(meshes_on_disk)
    if obj_ids:
        missing = sorted(set(int(i) for i in obj_ids) - set(known))
        if missing:
            src = info_path if have_info else models_dir
            raise CosyError(f"object(s) {missing} not found (known: {known})", path=src)
        todo = sorted(set(int(i) for i in obj_ids))
    else:
        todo = known
    if have_info:
        unlisted = sorted(set(meshes_on_disk) - set(infos))
        if unlisted:
            echo(f"note: meshes of objects {unlisted} are not in models_info.json: skipped")

    reports: list[ObjectReport] = []
    new_infos = dict(infos)
    meshes = {}
    if not have_info:  # every object needs a models_info entry (diameter, extent) computed from its mesh
        for obj_id in known:
            meshes[obj_id] = load_mesh(meshes_on_disk[obj_id])
            new_infos[obj_id] = model_info_from_mesh(meshes[obj_id])
    for obj_id in progress_bar(todo, desc="symmetries", unit="obj", enabled=progress is not False):
        path = models_dir / f"obj_{obj_id:06d}.ply"
        mesh = meshes[obj_id] if obj_id in meshes else load_mesh(path)
        info = new_infos[obj_id]
        tol = tolerance_mm if tolerance_mm is not None else default_tolerance(info.diameter)
        if info.diameter < 5.0:
            from ..errors import warn

            warn(f"object {obj_id} is {info.diameter:.3g} mm across: are its units mm? (tolerance {tol:.2g} mm)")
        try:
            det = SymmetryDetector(mesh.vertices, mesh.faces, tol, n_points=n_points, seed=seed)
        except ValueError as e:
            raise CosyError(f"cannot analyse mesh: {e}", path=path) from None
        prop = det.run()
        rep = ObjectReport(obj_id, prop, "none")
        if have_info:
            old = infos[obj_id]
            same = compare_symmetries(old.symmetries_discrete, old.symmetries_continuous, prop.symmetries_discrete,
                                      prop.symmetries_continuous, tol)
            rep.existing = "agree" if same else "differ"
            rep.existing_failing, rep.existing_residual_mm = _check_existing(det, old)
            if not same:
                new_infos[obj_id] = _with_symmetries(info, prop)
        else:
            new_infos[obj_id] = _with_symmetries(info, prop)
        reports.append(rep)

    for line in format_table(reports, infos):
        echo(line)
    if write:
        changes = []
        for rep in reports:
            old = infos.get(rep.obj_id)
            p = rep.proposal
            if old is None:
                changes.append(f"obj {rep.obj_id}: {len(p.symmetries_discrete)} discrete, "
                               f"{len(p.symmetries_continuous)} continuous")
            elif rep.existing == "differ":
                parts = [f"{what} {len(a)} -> {len(b)}" for what, a, b in (
                    ("discrete", old.symmetries_discrete, p.symmetries_discrete),
                    ("continuous", old.symmetries_continuous, p.symmetries_continuous)) if len(a) != len(b)]
                changes.append(f"obj {rep.obj_id}: " + (", ".join(parts) if parts else "symmetries replaced"))
        bop.write_models_info(info_path, new_infos)
        verb = "updated" if have_info else "created"
        echo(f"{verb} {info_path}" + (": " + "; ".join(changes) if changes else " (no symmetry changes)"))
    else:
        echo("(report only: pass --write to store these symmetries in models_info.json)")
    return reports


def _check_existing(det: SymmetryDetector, info) -> tuple[int, float]:
    """(how many of the listed symmetries fail the surface test, their worst max distance mm);
    a continuous axis is tested at the 16 angles of the continuous test and counts once."""
    groups = [np.asarray(S, dtype=np.float64)[None] for S in info.symmetries_discrete]
    groups += [_continuous_test_transforms(c) for c in info.symmetries_continuous]
    if not groups:
        return 0, 0.0
    T = np.concatenate(groups)
    mx, p95 = det.residuals(T)
    ok = det.passes(mx, p95)
    failing, s = 0, 0
    for g in groups:
        failing += int(not ok[s:s + len(g)].all())
        s += len(g)
    return failing, float(mx.max())


def _continuous_test_transforms(c: dict) -> np.ndarray:
    axis = np.asarray(c["axis"], dtype=np.float64)
    offset = np.asarray(c.get("offset", np.zeros(3)), dtype=np.float64)
    R = rotation_about_axis(axis, 2 * np.pi * CONTINUOUS_TEST_TURNS)
    return make_pose(R, offset - R @ offset)


def _with_symmetries(info, prop: SymmetryProposal):
    from dataclasses import replace

    return replace(info, symmetries_discrete=prop.symmetries_discrete,
                   symmetries_continuous=[dict(c) for c in prop.symmetries_continuous])


def format_table(reports: list[ObjectReport], infos: dict) -> list[str]:
    """Readable lines: one row per object, then notes."""
    rows = [("obj", "continuous", "discrete", "max res. mm", "tol mm", "time s", "models_info.json")]
    notes = []
    for r in reports:
        p = r.proposal
        cmp = r.existing
        if cmp == "differ":
            old = infos[r.obj_id]
            cmp += f" (has {len(old.symmetries_discrete)} discrete, {len(old.symmetries_continuous)} continuous"
            if r.existing_failing:
                cmp += f"; {r.existing_failing} fail the surface test, max {r.existing_residual_mm:.2f} mm"
            cmp += ")"
        elif cmp == "agree" and r.existing_failing:  # same set, but the listed ones do not fit this mesh
            cmp += f" ({r.existing_failing} fail the surface test, max {r.existing_residual_mm:.2f} mm)"
        rows.append((str(r.obj_id), describe_continuous(p.symmetries_continuous),
                     describe_discrete(p.symmetries_discrete), f"{p.residual_max_mm:.3f}", f"{p.tolerance_mm:.2f}",
                     f"{p.seconds:.1f}", cmp))
        notes += [f"obj {r.obj_id}: {n}" for n in p.notes]
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip() for row in rows]
    return lines + notes
