"""Rigid transforms as 4x4 homogeneous matrices (numpy, batched over leading axes).

Naming: ``T_a_b`` maps points of frame b into frame a, so ``T_a_c = T_a_b @ T_b_c``.
Translations carry the unit of the points they act on (mm everywhere in cosy).
"""

from __future__ import annotations

import numpy as np


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(..., 4, 4) from rotations (..., 3, 3) and translations (..., 3)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    shape = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros(shape + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4): ``T_b_a = invert(T_a_b)``."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    return make_pose(Rt, -np.einsum("...ij,...j->...i", Rt, t))


def compose(*Ts: np.ndarray) -> np.ndarray:
    """Product of transforms, broadcasting over leading axes: compose(T_a_b, T_b_c) = T_a_c."""
    out = np.asarray(Ts[0], dtype=np.float64)
    for T in Ts[1:]:
        out = out @ np.asarray(T, dtype=np.float64)
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply T (..., 4, 4) to points (..., N, 3): returns (..., N, 3) = R p + t."""
    T = np.asarray(T, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    return points @ np.swapaxes(T[..., :3, :3], -1, -2) + T[..., None, :3, 3]


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle in radians of rotations (..., 3, 3), in [0, pi]."""
    R = np.asarray(R, dtype=np.float64)
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))


def relative_pose_error(T_a: np.ndarray, T_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rotation error in degrees, translation error in the unit of t) between poses (..., 4, 4)."""
    T_a = np.asarray(T_a, dtype=np.float64)
    T_b = np.asarray(T_b, dtype=np.float64)
    dR = np.swapaxes(T_a[..., :3, :3], -1, -2) @ T_b[..., :3, :3]
    return np.degrees(rotation_angle(dR)), np.linalg.norm(T_a[..., :3, 3] - T_b[..., :3, 3], axis=-1)


def is_rotation(R: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """True where R (..., 3, 3) is orthonormal (|R^T R - I| <= tol) with det +1."""
    R = np.asarray(R, dtype=np.float64)
    dev = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(axis=(-1, -2))
    return (dev <= tol) & (np.linalg.det(R) > 0)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """``T_world_cam`` of an OpenCV camera at ``eye`` looking at ``target`` (world units).

    The camera's +z looks at the target, +x is right and +y points down in the image, so that
    the world ``up`` direction appears upward in the image. Batched over leading axes.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    up = np.broadcast_to(np.asarray(up, dtype=np.float64), eye.shape)
    z = target - eye
    z = z / np.linalg.norm(z, axis=-1, keepdims=True)
    x = np.cross(z, up)
    nx = np.linalg.norm(x, axis=-1, keepdims=True)
    # Looking straight along `up`: any x orthogonal to z will do.
    alt = np.cross(z, np.broadcast_to([1.0, 0.0, 0.0], z.shape))
    x = np.where(nx > 1e-9, x / np.maximum(nx, 1e-12), alt / np.linalg.norm(alt, axis=-1, keepdims=True))
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=-1)
    return make_pose(R, eye)
