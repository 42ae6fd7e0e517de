"""Pose error functions, one per metric, as defined by the BOP toolkit (``bop_toolkit_lib/pose_error.py``).

Every function is pure and batched over N (estimate, ground truth) pairs of ONE object:
``T_est`` and ``T_gt`` are (N, 4, 4) or (4, 4) poses ``T_cam_obj`` with translations in mm,
``points`` are (V, 3) model points in mm (BOP: all vertices of the evaluation model),
``symmetries`` are (S, 4, 4) symmetry transforms of the model frame (identity included; see
:func:`cosy_cli.objects.symmetry_set`, continuous symmetries discretised like the toolkit's
``get_symmetry_transformations``). Errors come back as float64 arrays of shape (N,).

Definitions (u = estimate, g = ground truth, p a model point, S a symmetry):

* ``add``  = mean_p |T_e p - T_g p|                                   (mm)
* ``adi``  = mean_p min_q |T_g p - T_e q|  (ADD-S; nearest estimated point to each GT point)  (mm)
* ``mssd`` = min_S max_p |T_e p - T_g S p|                             (mm)
* ``mspd`` = min_S max_p |proj(K, T_e p) - proj(K, T_g S p)|           (px)
* ``re``   = arccos((tr(R_e R_g^-1) - 1) / 2), clipped                 (degrees)
* ``te``   = |t_e - t_g|                                               (mm)
* ``vsd``  = Visible Surface Discrepancy per tau (unitless, in [0, 1]) from rendered depths.

MSSD and MSPD are exact minima over the given symmetry set: symmetries are ranked by a lower
bound computed on a subset of the points and evaluated in full until the bound exceeds the best
value found (branch and bound), which returns the same value as evaluating every symmetry.
"""

from __future__ import annotations

import numpy as np

__all__ = ["add", "adi", "mssd", "mspd", "re", "te", "vsd", "depth_to_distance", "visibility_mask_gt",
           "visibility_mask_est", "sphere_projections_overlap", "spheres_overlap"]

_SUBSET = 48  # points used for the lower bound of MSSD/MSPD per symmetry


def _poses(T) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    return T.reshape(-1, 4, 4)


def _apply(T: np.ndarray, P: np.ndarray) -> np.ndarray:
    """T (..., 4, 4) applied to P (..., V, 3)."""
    return P @ np.swapaxes(T[..., :3, :3], -1, -2) + T[..., None, :3, 3]


def add(T_est, T_gt, points) -> np.ndarray:
    """ADD (Hinterstoisser et al. 2012): average distance of corresponding model points, mm."""
    Te, Tg = np.broadcast_arrays(_poses(T_est), _poses(T_gt))
    P = np.asarray(points, dtype=np.float64)
    # |T_e p - T_g p| = |T_g^-1 T_e p - p|: one transform per pair
    A = np.linalg.inv(Tg) @ Te
    return np.linalg.norm(_apply(A, P[None]) - P[None], axis=-1).mean(axis=-1)


def adi(T_est, T_gt, points, tree=None) -> np.ndarray:
    """ADD-S / ADI (Hinterstoisser et al. 2012): mean over GT-posed points of the distance to the
    nearest estimate-posed point, mm. ``tree``: an optional ``scipy.spatial.cKDTree(points)``."""
    from scipy.spatial import cKDTree

    Te, Tg = np.broadcast_arrays(_poses(T_est), _poses(T_gt))
    P = np.asarray(points, dtype=np.float64)
    tree = cKDTree(P) if tree is None else tree
    # |T_g p - T_e q| = |T_e^-1 T_g p - q|: query the model's own tree with moved points
    A = np.linalg.inv(Te) @ Tg
    Q = _apply(A, P[None])  # (N, V, 3)
    d, _ = tree.query(Q.reshape(-1, 3), k=1)
    return d.reshape(len(A), len(P)).mean(axis=-1)


def _subset_indices(P: np.ndarray, m: int = _SUBSET) -> np.ndarray:
    """Farthest-point subset of P (deterministic), used only for lower bounds."""
    n = len(P)
    if n <= m:
        return np.arange(n)
    idx = [int(np.argmax(np.linalg.norm(P - P.mean(0), axis=1)))]
    d = np.linalg.norm(P - P[idx[0]], axis=1)
    for _ in range(m - 1):
        i = int(np.argmax(d))
        idx.append(i)
        d = np.minimum(d, np.linalg.norm(P - P[i], axis=1))
    return np.array(idx)


def _min_over_symmetries(dist_fn, n_sym: int, sub: np.ndarray, n_pts: int) -> float:
    """min_s max_p dist_fn(s_ids, p_ids) by branch and bound (exact).

    dist_fn(s_ids, p_ids) -> (len(s_ids), len(p_ids)) distances."""
    lb = dist_fn(np.arange(n_sym), sub).max(axis=1)
    order = np.argsort(lb, kind="stable")
    best = np.inf
    all_p = np.arange(n_pts)
    for start in range(0, n_sym, 8):
        chunk = order[start:start + 8]
        chunk = chunk[lb[chunk] < best]
        if len(chunk) == 0:
            break
        e = dist_fn(chunk, all_p).max(axis=1)
        best = min(best, float(e.min()))
    return best


def mssd(T_est, T_gt, points, symmetries) -> np.ndarray:
    """MSSD (BOP 2019): min over symmetries S of the max distance |T_e p - T_g S p|, mm."""
    Te, Tg = np.broadcast_arrays(_poses(T_est), _poses(T_gt))
    P = np.asarray(points, dtype=np.float64)
    S = np.asarray(symmetries, dtype=np.float64).reshape(-1, 4, 4)
    SP = _apply(S, P[None])  # (S, V, 3) symmetric copies of the points, model frame
    sub = _subset_indices(P)
    out = np.empty(len(Te))
    A = np.linalg.inv(Tg) @ Te  # |T_e p - T_g S p| = |A p - S p|
    for i in range(len(Te)):
        Q = _apply(A[i], P)  # (V, 3)
        out[i] = _min_over_symmetries(
            lambda s, p: np.linalg.norm(Q[p][None] - SP[s][:, p], axis=-1), len(S), sub, len(P))
    return out


def _project(Pc: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pinhole projection of camera-frame points (..., 3) like the toolkit's project_pts (divide by z)."""
    h = Pc @ K.T
    return h[..., :2] / h[..., 2:3]


def mspd(T_est, T_gt, K, points, symmetries) -> np.ndarray:
    """MSPD (BOP 2019): min over symmetries S of the max image distance between the projections of
    T_e p and T_g S p with intrinsics K ((3, 3) or (N, 3, 3)), pixels."""
    Te, Tg = np.broadcast_arrays(_poses(T_est), _poses(T_gt))
    K = np.broadcast_to(np.asarray(K, dtype=np.float64).reshape(-1, 3, 3), (len(Te), 3, 3))
    P = np.asarray(points, dtype=np.float64)
    S = np.asarray(symmetries, dtype=np.float64).reshape(-1, 4, 4)
    SP = _apply(S, P[None])  # (S, V, 3)
    sub = _subset_indices(P)
    out = np.empty(len(Te))
    for i in range(len(Te)):
        ue = _project(_apply(Te[i], P), K[i])  # (V, 2)
        Rg, tg, Ki = Tg[i, :3, :3], Tg[i, :3, 3], K[i]

        def dist(s, p, ue=ue, Rg=Rg, tg=tg, Ki=Ki):
            ug = _project(SP[s][:, p] @ Rg.T + tg, Ki)
            return np.linalg.norm(ue[p][None] - ug, axis=-1)

        out[i] = _min_over_symmetries(dist, len(S), sub, len(P))
    return out


def re(R_est, R_gt) -> np.ndarray:
    """Rotation error, degrees: arccos((trace(R_e R_g^-1) - 1) / 2) with the cosine clipped to [-1, 1].
    R_est, R_gt: (N, 3, 3) or (3, 3) (4x4 poses are accepted: their rotation part is used)."""
    Re_ = np.asarray(R_est, dtype=np.float64)
    Rg_ = np.asarray(R_gt, dtype=np.float64)
    if Re_.shape[-1] == 4:
        Re_ = Re_[..., :3, :3]
    if Rg_.shape[-1] == 4:
        Rg_ = Rg_[..., :3, :3]
    Re_, Rg_ = np.broadcast_arrays(Re_.reshape(-1, 3, 3), Rg_.reshape(-1, 3, 3))
    c = 0.5 * (np.trace(Re_ @ np.linalg.inv(Rg_), axis1=-2, axis2=-1) - 1.0)
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def te(t_est, t_gt) -> np.ndarray:
    """Translation error |t_e - t_g|, mm. t: (N, 3), (3,), or 4x4 poses (their translation is used)."""
    a = np.asarray(t_est, dtype=np.float64)
    b = np.asarray(t_gt, dtype=np.float64)
    if a.shape[-2:] == (4, 4):
        a = a[..., :3, 3]
    if b.shape[-2:] == (4, 4):
        b = b[..., :3, 3]
    return np.linalg.norm(a.reshape(-1, 3) - b.reshape(-1, 3), axis=-1)


# ------------------------------------------------------------------------------------------
# shortcuts used by the toolkit's eval_calc_errors.py
# ------------------------------------------------------------------------------------------
def spheres_overlap(t_est, t_gt, diameter: float) -> np.ndarray:
    """True where |t_e - t_g| < diameter (mm): the toolkit computes ADD/ADI/MSSD only there
    (infinite error elsewhere). Uses the model ORIGINS, as the toolkit does, not the model centres."""
    return te(t_est, t_gt) < float(diameter)


def sphere_projections_overlap(t_est, t_gt, radius: float) -> np.ndarray:
    """The toolkit's approximate test of overlapping silhouettes of two spheres of ``radius`` (mm)
    centred on the model origins t_est, t_gt (N, 3) mm; VSD is 1 for every tau where False.
    Compares the distance of the normalised projections (x/z, y/z) with radius (1/z_e + 1/z_g);
    False where a depth is 0."""
    a = np.asarray(t_est, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(t_gt, dtype=np.float64).reshape(-1, 3)
    ok = (a[:, 2] != 0) & (b[:, 2] != 0)
    za = np.where(ok, a[:, 2], 1.0)
    zb = np.where(ok, b[:, 2], 1.0)
    d = np.linalg.norm(a[:, :2] / za[:, None] - b[:, :2] / zb[:, None], axis=1)
    return ok & (d < radius * (1.0 / za + 1.0 / zb))


# ------------------------------------------------------------------------------------------
# VSD
# ------------------------------------------------------------------------------------------
def depth_to_distance(depth_mm: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Distance image (mm, float64): |X| of the 3D point seen at each pixel, from a depth image
    (z, mm; 0 = none) and the pinhole K. Pixel centres at integer coordinates."""
    d = np.asarray(depth_mm, dtype=np.float64)
    H, W = d.shape
    x = (np.arange(W, dtype=np.float64) - K[0, 2]) / np.float64(K[0, 0])
    y = (np.arange(H, dtype=np.float64) - K[1, 2]) / np.float64(K[1, 1])
    return np.sqrt((x[None, :] * d) ** 2 + (y[:, None] * d) ** 2 + d ** 2)


def _visib_bop19(dist_test: np.ndarray, dist_model: np.ndarray, delta: float) -> np.ndarray:
    """Visible where the model is rendered and (it is at most delta mm behind the scene or the scene
    has no measurement): the toolkit's 'bop19' mode (differences in float32, as the toolkit)."""
    diff = dist_model.astype(np.float32) - dist_test.astype(np.float32)
    return ((diff <= delta) | (dist_test == 0)) & (dist_model > 0)


def visibility_mask_gt(dist_test: np.ndarray, dist_gt: np.ndarray, delta: float) -> np.ndarray:
    """Visible surface of the model in the GT pose (distance images in mm, delta in mm)."""
    return _visib_bop19(dist_test, dist_gt, delta)


def visibility_mask_est(dist_test: np.ndarray, dist_est: np.ndarray, visib_gt: np.ndarray, delta: float) -> np.ndarray:
    """Visible surface in the estimated pose: visible by the depth test, or rendered where the GT
    surface is visible (Hodan et al. 2016, eq. 14)."""
    return _visib_bop19(dist_test, dist_est, delta) | (visib_gt & (dist_est > 0))


def vsd(depth_est: np.ndarray, depth_gt: np.ndarray, depth_test: np.ndarray, K: np.ndarray, delta: float,
        taus, diameter: float | None = None, normalized_by_diameter: bool = True, cost: str = "step") -> np.ndarray:
    """Visible Surface Discrepancy (Hodan, Michel et al. 2018), one error per tau, unitless in [0, 1].

    depth_est, depth_gt: (H, W) depth (mm, 0 = background) of the model rendered alone in the
    estimated and the GT pose; depth_test: (H, W) measured depth in mm (0 = missing); K: (3, 3).
    delta: visibility tolerance, mm. taus: misalignment tolerances, fractions of the diameter when
    ``normalized_by_diameter`` (BOP19: 0.05..0.5), else mm. cost: 'step' (BOP) or 'tlinear'.
    Errors are computed on distance images (not depth), as the toolkit does.
    """
    dist_test = depth_to_distance(depth_test, K)
    dist_gt = depth_to_distance(depth_gt, K)
    dist_est = depth_to_distance(depth_est, K)
    visib_gt = visibility_mask_gt(dist_test, dist_gt, delta)
    visib_est = visibility_mask_est(dist_test, dist_est, visib_gt, delta)
    inter = visib_gt & visib_est
    union_count = int((visib_gt | visib_est).sum())
    taus = np.asarray(list(taus), dtype=np.float64)
    if union_count == 0:
        return np.ones(len(taus))
    comp_count = union_count - int(inter.sum())
    dists = np.abs(dist_gt[inter] - dist_est[inter])
    if normalized_by_diameter:
        if diameter is None:
            raise ValueError("normalized_by_diameter needs the diameter (mm)")
        dists = dists / float(diameter)
    if cost == "step":
        costs = (dists[None, :] >= taus[:, None]).sum(axis=1).astype(np.float64)
    elif cost == "tlinear":
        costs = np.minimum(dists[None, :] / taus[:, None], 1.0).sum(axis=1)
    else:
        raise ValueError(f"unknown VSD cost {cost!r} (step, tlinear)")
    return (costs + comp_count) / float(union_count)
