"""Oracle poses: an estimate with one part of its pose taken from the ground truth it is compared
with. Evaluating them (``cosy evaluate --oracle``) says how much of what an estimate misses is
depth, rotation or translation: the average recall it would reach if that part were exact. A
diagnostic, not a BOP score.

Every function is pure and batched over N (estimate, ground truth) pairs, ``T_est`` and ``T_gt``
(N, 4, 4) or (4, 4) poses ``T_cam_obj`` with translations in mm, and returns the oracle poses
(N, 4, 4) float64:

* ``depth``: the estimate moved along the ray through its origin until its distance along the
  camera's z axis is the GT's (t_e x z_g / z_e): its projection, and so its image position, is
  kept; an estimate at z_e <= 0 (behind the camera) takes the GT translation;
* ``rotation``: the GT rotation, the estimate's translation;
* ``translation``: the estimate's rotation, the GT translation.
"""

from __future__ import annotations

import numpy as np

PARTS = {"depth": "distance along its ray", "rotation": "rotation", "translation": "translation"}  # what each takes
ORACLES = tuple(PARTS)


def _pairs(T_est, T_gt) -> tuple[np.ndarray, np.ndarray]:
    Te = np.array(T_est, dtype=np.float64).reshape(-1, 4, 4)
    Tg = np.asarray(T_gt, dtype=np.float64).reshape(-1, 4, 4)
    if len(Te) != len(Tg):
        raise ValueError(f"oracle: {len(Te)} estimates and {len(Tg)} GT poses")
    return Te, Tg


def with_gt_depth(T_est, T_gt) -> np.ndarray:
    Te, Tg = _pairs(T_est, T_gt)
    z = Te[:, 2, 3]
    ok = z > 0
    Te[ok, :3, 3] *= (Tg[ok, 2, 3] / z[ok])[:, None]
    Te[~ok, :3, 3] = Tg[~ok, :3, 3]
    return Te


def with_gt_rotation(T_est, T_gt) -> np.ndarray:
    Te, Tg = _pairs(T_est, T_gt)
    Te[:, :3, :3] = Tg[:, :3, :3]
    return Te


def with_gt_translation(T_est, T_gt) -> np.ndarray:
    Te, Tg = _pairs(T_est, T_gt)
    Te[:, :3, 3] = Tg[:, :3, 3]
    return Te


def oracle_poses(kind: str, T_est, T_gt) -> np.ndarray:
    """The ``kind`` (one of :data:`ORACLES`) oracle poses of the pairs (see the module docstring)."""
    fn = {"depth": with_gt_depth, "rotation": with_gt_rotation, "translation": with_gt_translation}.get(kind)
    if fn is None:
        raise ValueError(f"oracle: expected one of {', '.join(ORACLES)}, got {kind!r}")
    return fn(T_est, T_gt)


__all__ = ["ORACLES", "PARTS", "oracle_poses", "with_gt_depth", "with_gt_rotation", "with_gt_translation"]
