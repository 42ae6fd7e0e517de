"""Point sets: area-uniform samples of a triangle mesh, farthest-point subsets (numpy)."""

from __future__ import annotations

import numpy as np


def farthest_point_indices(X: np.ndarray, k: int) -> np.ndarray:
    """Indices (k,) of k well-spread points of X (N, 3), N >= k: farthest-point sampling started
    at the point farthest from the centroid (deterministic)."""
    X = np.asarray(X, dtype=np.float64)
    d = np.linalg.norm(X - X.mean(0), axis=1)
    idx = np.empty(k, dtype=np.int64)
    idx[0] = int(np.argmax(d))
    dist = np.linalg.norm(X - X[idx[0]], axis=1)
    for i in range(1, k):  # k vector operations, once per object label (not a hot path)
        idx[i] = int(np.argmax(dist))
        dist = np.minimum(dist, np.linalg.norm(X - X[idx[i]], axis=1))
    return idx


def farthest_point_subset(X: np.ndarray, k: int) -> np.ndarray:
    """k well-spread points of X (N, 3), a copy of all of X when N <= k."""
    X = np.asarray(X, dtype=np.float64)
    if len(X) <= k:
        return X.copy()
    return X[farthest_point_indices(X, k)]


def sample_surface(vertices: np.ndarray, faces: np.ndarray | None, n: int, seed: int = 0) -> np.ndarray:
    """n area-uniform points (mm) on the triangles (deterministic); the vertices without faces."""
    V = np.asarray(vertices, dtype=np.float64)
    if faces is None or len(faces) == 0:
        return V
    tri = V[faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if area.sum() <= 0:
        return V
    rng = np.random.default_rng(seed)
    f = rng.choice(len(faces), size=n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tri[f]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
