"""Symmetric model distances between poses (numpy, batched).

D_l(T1, T2) = min over S in S(l) of mean_x || T1 S x - T2 x ||  (CosyPose Eq. 1), with
points x in the model frame (mm) and symmetries S as 4x4 transforms (translation in mm).
"""

from __future__ import annotations

import numpy as np


def symmetric_distances_all(T1: np.ndarray, T2: np.ndarray, points: np.ndarray, symmetries: np.ndarray,
                            chunk: int = 4096) -> np.ndarray:
    """Mean point distance for every symmetry: (P, S) array in mm.

    T1, T2: (P, 4, 4) poses (broadcastable to a common P); points: (N, 3) mm; symmetries:
    (S, 4, 4). Entry [p, s] = mean_x ||T1[p] S[s] x - T2[p] x||.
    """
    T1 = np.asarray(T1, dtype=np.float64)
    T2 = np.asarray(T2, dtype=np.float64)
    P = np.broadcast_shapes(T1.shape[:-2], T2.shape[:-2])
    T1 = np.broadcast_to(T1, P + (4, 4)).reshape(-1, 4, 4)
    T2 = np.broadcast_to(T2, P + (4, 4)).reshape(-1, 4, 4)
    X = np.asarray(points, dtype=np.float64)
    S = np.asarray(symmetries, dtype=np.float64)
    XS = X @ np.swapaxes(S[:, :3, :3], -1, -2) + S[:, None, :3, 3]  # (S, N, 3): S x
    n_sym, n_pts = XS.shape[:2]
    XS_flat = XS.reshape(-1, 3)
    out = np.empty((T1.shape[0], n_sym))
    for i in range(0, T1.shape[0], chunk):
        a, b = T1[i:i + chunk], T2[i:i + chunk]
        # matmul + one fused reduction: ~10x the einsum "pij,snj->psni" and norm it replaces
        p1 = np.matmul(XS_flat, np.swapaxes(a[:, :3, :3], -1, -2)) + a[:, None, :3, 3]  # (p, S N, 3)
        p2 = X @ np.swapaxes(b[:, :3, :3], -1, -2) + b[:, None, :3, 3]  # (p, N, 3)
        d = p1.reshape(len(a), n_sym, n_pts, 3) - p2[:, None]
        out[i:i + chunk] = np.sqrt(np.einsum("psni,psni->psn", d, d)).mean(axis=-1)
    return out.reshape(P + (n_sym,))


def symmetric_distance(T1: np.ndarray, T2: np.ndarray, points: np.ndarray, symmetries: np.ndarray,
                       return_index: bool = False):
    """D_l(T1, T2) in mm for batches of pose pairs (..., 4, 4); optionally the argmin symmetry."""
    d = symmetric_distances_all(T1, T2, points, symmetries)
    if return_index:
        return d.min(axis=-1), d.argmin(axis=-1)
    return d.min(axis=-1)


def mean_point_distance(T1: np.ndarray, T2: np.ndarray, points: np.ndarray) -> np.ndarray:
    """ADD-like mean distance in mm without symmetries: (...)."""
    return symmetric_distance(T1, T2, points, np.eye(4)[None])
