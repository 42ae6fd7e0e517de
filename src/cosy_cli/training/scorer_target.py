"""What the scorer learns to predict: the part of the BOP 2019 recall a pose earns.

A pose with errors e_MSSD (mm) and e_MSPD (px) counts as correct at the MSSD thresholds
0.05..0.5 x the object diameter and at the MSPD thresholds 5..50 px x (image width / 640)
(:data:`cosy_cli.evaluation.protocols` lists both, as the BOP toolkit does). Its contribution to
AR (MSSD, MSPD) is the mean of the two fractions of thresholds met: 1 for a pose within the
tightest thresholds, 0 beyond the loosest.

:func:`max_errors` computes both errors for many poses of one object at once over a fixed subset
of the surface points (the BOP toolkit uses all model vertices; the subset's maximum is a little
lower, which for a training target is immaterial) and over the object's symmetries.
"""

from __future__ import annotations

import numpy as np

from ..evaluation.protocols import BOP19_THRESHOLDS


def ar_contribution(e_mssd: np.ndarray, e_mspd: np.ndarray, diameter_mm, image_width) -> np.ndarray:
    """(n,) in [0, 1]: mean of the fraction of MSSD thresholds (x ``diameter_mm``) that e_mssd (mm)
    meets and the fraction of MSPD thresholds (x ``image_width`` / 640) that e_mspd (px) meets."""
    e_mssd = np.asarray(e_mssd, np.float64).reshape(-1, 1)
    e_mspd = np.asarray(e_mspd, np.float64).reshape(-1, 1)
    d = np.asarray(diameter_mm, np.float64).reshape(-1, 1)
    r = np.asarray(image_width, np.float64).reshape(-1, 1) / 640.0
    a = (e_mssd < BOP19_THRESHOLDS["mssd"][None] * d).mean(1)
    b = (e_mspd < BOP19_THRESHOLDS["mspd"][None] * r).mean(1)
    return 0.5 * (a + b)


def max_errors(T_est: np.ndarray, T_gt: np.ndarray, K: np.ndarray, points: np.ndarray,
               symmetries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(e_mssd (n,) mm, e_mspd (n,) px) of poses T_est (n, 4, 4) against T_gt (n, 4, 4) with
    intrinsics K (n, 3, 3), over ``points`` (P, 3) mm of the object and its ``symmetries``
    (S, 4, 4): min over S of the max over the points, batched (n x S x P)."""
    Te = np.asarray(T_est, np.float64).reshape(-1, 4, 4)
    Tg = np.broadcast_to(np.asarray(T_gt, np.float64).reshape(-1, 4, 4), Te.shape)
    K = np.broadcast_to(np.asarray(K, np.float64).reshape(-1, 3, 3), (len(Te), 3, 3))
    P = np.asarray(points, np.float64)
    S = np.asarray(symmetries, np.float64).reshape(-1, 4, 4)
    SP = P[None] @ S[:, :3, :3].transpose(0, 2, 1) + S[:, None, :3, 3]  # (S, P, 3) symmetric copies
    Pe = P[None] @ Te[:, :3, :3].transpose(0, 2, 1) + Te[:, None, :3, 3]  # (n, P, 3) camera frame
    Pg = np.einsum("nij,spj->nspi", Tg[:, :3, :3], SP) + Tg[:, None, None, :3, 3]  # (n, S, P, 3)
    e_mssd = np.linalg.norm(Pe[:, None] - Pg, axis=-1).max(-1).min(-1)

    def proj(X, Kn):
        h = np.einsum("nij,n...j->n...i", Kn, X)
        return h[..., :2] / np.maximum(h[..., 2:3], 1e-6)

    ue = proj(Pe, K)
    ug = proj(Pg, K)
    e_mspd = np.linalg.norm(ue[:, None] - ug, axis=-1).max(-1).min(-1)
    return e_mssd, e_mspd
