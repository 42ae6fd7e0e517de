"""Symmetry sets S(l) of objects, from the BOP ``models_info.json`` description.

A symmetry is a rigid transform S (4x4, translation in mm, model frame) such that the object
looks the same under T and T @ S. The set always holds the identity first; continuous
symmetries (an axis through an ``offset`` point) are discretised into ``n_continuous`` rotation
steps over a full turn, and combined with the discrete ones as C @ D like the BOP toolkit.
"""

from __future__ import annotations

import math

import numpy as np

from ..geometry.poses import make_pose
from ..geometry.rotations import rotation_about_axis

PAPER_CONTINUOUS_STEPS = 64  # CosyPose: 64 angles per symmetry axis (RANSAC and bundle adjustment)
BOP_MAX_SYM_DISC_STEP = 0.01  # bop_toolkit default, in radians (evaluation: MSSD, MSPD)


def continuous_steps_for_max_step(max_step_rad: float = BOP_MAX_SYM_DISC_STEP) -> int:
    """Number of steps over a full turn the BOP toolkit uses for a maximum step (ceil(pi / step))."""
    return int(math.ceil(math.pi / max_step_rad))


def continuous_symmetry_transforms(axis: np.ndarray, offset: np.ndarray, n_steps: int,
                                   include_identity: bool = True) -> np.ndarray:
    """(n_steps, 4, 4) rotations by 2*pi*k/n_steps about ``axis`` through ``offset`` (mm)."""
    k0 = 0 if include_identity else 1
    angles = 2.0 * np.pi * np.arange(k0, n_steps) / n_steps
    R = rotation_about_axis(np.asarray(axis, dtype=np.float64), angles)
    offset = np.asarray(offset, dtype=np.float64)
    t = offset[None] - R @ offset
    return make_pose(R, t)


def symmetry_set(symmetries_discrete: np.ndarray, symmetries_continuous: list[dict],
                 n_continuous: int = PAPER_CONTINUOUS_STEPS) -> np.ndarray:
    """All symmetries (S, 4, 4), identity first, no duplicates.

    ``symmetries_discrete``: (K, 4, 4) as in models_info.json (translation in mm).
    ``symmetries_continuous``: [{"axis": (3,), "offset": (3,) mm}].
    """
    disc = [np.eye(4)] + [np.asarray(S, dtype=np.float64) for S in symmetries_discrete]
    D = np.stack(disc)
    if not symmetries_continuous:
        out = D
    else:
        parts = []
        for c in symmetries_continuous:
            C = continuous_symmetry_transforms(c["axis"], c.get("offset", np.zeros(3)), n_continuous)
            parts.append((C[:, None] @ D[None]).reshape(-1, 4, 4))  # C @ D for every pair
        out = np.concatenate(parts)
    return _unique_transforms(out)


def _unique_transforms(T: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    keep = []
    flat = T.reshape(len(T), -1)
    if len(T) <= 1024:  # same greedy rule, with the pairwise closeness computed at once
        close = np.abs(flat[:, None] - flat[None]).max(axis=-1) < tol
        for i in range(len(T)):
            if not close[i, keep].any():
                keep.append(i)
        return T[keep]
    for i in range(len(T)):
        if not any(np.abs(flat[i] - flat[j]).max() < tol for j in keep):
            keep.append(i)
    return T[keep]


def symmetry_residuals(points: np.ndarray, symmetries: np.ndarray, surface_distance) -> np.ndarray:
    """For each symmetry, the max distance (mm) from the transformed points to the surface.

    ``surface_distance(points (M, 3)) -> (M,)`` gives unsigned distances to the model surface
    (e.g. from :meth:`ObjectModel.surface_distance`). A true symmetry gives ~0.
    """
    S = np.asarray(symmetries, dtype=np.float64)
    P = np.asarray(points, dtype=np.float64)
    moved = P[None] @ np.swapaxes(S[:, :3, :3], -1, -2) + S[:, None, :3, 3]
    d = surface_distance(moved.reshape(-1, 3)).reshape(len(S), len(P))
    return d.max(axis=1)
