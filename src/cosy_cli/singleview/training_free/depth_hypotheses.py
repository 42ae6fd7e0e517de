"""More rotation hypotheses for the depth path, and a visibility-aware depth score to choose among them.

ICP fixes a pose's depth and refines it locally, but a depth map cannot tell apart rotations under
which the object's surface nearly maps onto itself: a box turned over, a near-square brick turned
by 90 deg, a mug turned about its body's axis (only the handle moves). Template retrieval often
offers one of these instead of the right one, or none near the right one at all. This module

1. finds each object's **near-symmetries** (:func:`near_symmetries`, once per object, cached;
   ~0.7 s per object on this 2-core CPU): rigid motions S = (R, t) of the object frame that carry
   most of its surface within a small distance of itself. Candidates: rotations about the
   object's own axes and its principal axes, in ``ANGLE_STEP_DEG`` steps, each with the
   translation fitted by a few point-to-plane steps (over the nearest ``TRIM_QUANTILE`` of the
   pairs) against ``DENSE_SAMPLES`` surface samples; kept when the ``TRIM_QUANTILE`` quantile of
   the distances is below ``NEAR_FRAC`` x diameter (a mug's handle, a small part of its surface,
   does not count against turning it about its body's axis). True symmetries are found too; they
   are harmless (their variants score the same).
2. **expands** a pose T_cam_obj into its variants T @ S (:func:`expand`).
3. scores poses against the depth with **visibility** (:func:`visible_depth_score`): ``SAMPLES``
   of the model's camera-facing surface samples are projected, a coarse z-buffer (``ZBUF_PX`` px
   cells) drops those hidden by the object's own nearer surface (a mug's inner wall behind its
   front wall), then per visible sample the observed depth d at its pixel: agree (|z - d| <= tol),
   violation (z < d - tol: the model would stand in front of what the camera sees, in free
   space), occluded (z > d + tol: something else is in front), unknown (no measurement). Score =
   (agree - ``VIOLATION_WEIGHT`` x violations) / (visible - unknown): missing depth (a mug's dark
   inside) is neutral; a handle sticking out beside a mug into free space costs its samples
   twice; a handle hidden behind the body is not counted.
4. :func:`refine_and_rank` (what ``cosy estimate`` runs with depth): a short ICP of each
   detection's first ``icp_screen`` hypotheses ranked by depth + image score (the screen), the full
   ICP of the ``top_k`` best of them, :func:`pick_score` (the score above + image_weight x the image score),
   then (:func:`add_variants`) the variants of each detection's ``N_EXPAND`` best, scored as they
   are, the ``VARIANT_KEEP`` best refined by a short ICP and scored again (minus
   ``VARIANT_MARGIN``: a variant must beat where it came from).

Settings chosen on YCB-V frames 1-5 (benchmarks/bench_realdata_singleview.py --data ycbv
--frames 1-5): BOP19 AR 0.365 -> 0.628 (the mug: 0.43 -> 0.73). The untextured gelatin box's
half-turns and the near-square foam brick's quarter-turns stay a guess: their geometry is the same.

Lengths in mm; poses 4x4 T_cam_obj; K (3, 3) px. Vectorised over samples and poses.
"""

from __future__ import annotations

import weakref
from dataclasses import replace

import numpy as np

from ...geometry.rotations import rotation_about_axis

ANGLE_STEP_DEG = 30.0   # candidate near-symmetry rotations: multiples of this about each axis
NEAR_FRAC = 0.03        # kept when the TRIM_QUANTILE surface distance after the motion < this x diameter
TRIM_QUANTILE = 0.8
DENSE_SAMPLES = 20000   # surface samples the near-symmetry distances are measured against
MAX_NEAR = 16           # at most this many near-symmetries per object (the closest ones)
ZBUF_PX = 3             # z-buffer cell side, px (adaptive cells of 2x the samples' spacing lost 0.24 AR on the mug)
VIOLATION_WEIGHT = 2.0  # free-space violations count against a pose this many times an agreement
N_EXPAND = 2            # estimate: the near-symmetry variants of each detection's this many best ICP results
VARIANT_KEEP = 2        # ... of which only each detection's this many best (depth score before ICP) are refined
VARIANT_MARGIN = 0.02   # a variant is picked only when it beats the hypotheses it came from by this much
VARIANT_ICP_ITERATIONS = 10  # the variants' ICP iterations
SCREEN_ITERATIONS = 6    # estimate (icp_screen > top_k): the short ICP that screens the hypotheses: iterations
SCREEN_POINTS = 500      # ... and observed points per box
SCREEN_ALIGN_POINTS = 150  # ... and model samples in its depth alignment
SCREEN_SAMPLES = 500     # ... and surface samples of the depth score that ranks its results
RETRY_BELOW = None      # estimate: detections whose best depth score is below this ICP their next top_k hypotheses
                        # too (None: off; 0.25 cost 0.04 BOP19 AR on YCB-V frames 1-5: one brick turned by 90 deg)
PICK = "visible"        # estimate: pick by visible_depth_score ("fit": the ICP module's depth_fit_score)
SAMPLES = 1500          # surface samples used by the score (of the ICP module's 3000, a uniform subset)

_NEAR: dict[int, tuple[weakref.ref, np.ndarray]] = {}


def near_symmetries(model) -> np.ndarray:
    """(S, 4, 4) object-frame motions p -> R p + t (mm) that map the object's surface nearly onto
    itself (see the module docstring), identity excluded, closest first (cached per model)."""
    key = id(model)
    hit = _NEAR.get(key)
    if hit is not None and hit[0]() is model:
        return hit[1]
    import trimesh
    from scipy.spatial import cKDTree

    from .icp import _surface

    surf = _surface(model)
    P = surf.points
    mesh = trimesh.Trimesh(np.asarray(model.mesh.vertices, np.float64), np.asarray(model.mesh.faces), process=False)
    dense, face = trimesh.sample.sample_surface(mesh, DENSE_SAMPLES, seed=1)  # distances to the surface, ~1 mm off
    dn = np.asarray(mesh.face_normals)[face]
    tree = cKDTree(dense)
    c0 = P.mean(0)
    _, evecs = np.linalg.eigh(np.cov((P - c0).T))
    axes = np.concatenate([np.eye(3), evecs.T])
    angles = np.radians(np.arange(ANGLE_STEP_DEG, 360.0 - 1e-6, ANGLE_STEP_DEG))
    R = np.concatenate([rotation_about_axis(a, angles) for a in axes])  # (6 * n, 3, 3)
    sub = P[:: max(1, len(P) // 400)]  # (n, 3)
    C, n = len(R), len(sub)
    t = c0[None] - R @ c0  # (C, 3): about the samples' centroid first
    keep_c = np.arange(C)
    for it in range(8):  # translation-only point-to-plane steps over the nearest TRIM_QUANTILE of the pairs
        Q = sub[None] @ np.swapaxes(R[keep_c], 1, 2) + t[keep_c, None]  # (c, n, 3)
        d, j = tree.query(Q.reshape(-1, 3))
        d, j = d.reshape(-1, n), j.reshape(-1, n)
        q = np.quantile(d, TRIM_QUANTILE, axis=1)
        if it == 3:  # far from a near-symmetry after a few steps: given up
            alive = q < 3 * NEAR_FRAC * surf.diameter
            keep_c, d, j, q, Q = keep_c[alive], d[alive], j[alive], q[alive], Q[alive]
        w = (d <= q[:, None]).astype(np.float64)
        nrm = dn[j]  # (c, n, 3)
        r = np.einsum("cnk,cnk->cn", nrm, Q - dense[j]) * w
        A = np.einsum("cni,cnj,cn->cij", nrm, nrm, w) + 1e-3 * w.sum(1)[:, None, None] * np.eye(3)
        t[keep_c] -= np.linalg.solve(A, np.einsum("cni,cn->ci", nrm, r)[..., None])[..., 0]
    d, _ = tree.query((sub[None] @ np.swapaxes(R[keep_c], 1, 2) + t[keep_c, None]).reshape(-1, 3))
    dists = np.full(C, np.inf)
    dists[keep_c] = np.quantile(d.reshape(-1, n), TRIM_QUANTILE, axis=1)
    motions = np.tile(np.eye(4), (C, 1, 1))
    motions[:, :3, :3], motions[:, :3, 3] = R, t
    dists = np.array(dists)
    keep = np.flatnonzero(dists < NEAR_FRAC * surf.diameter)
    keep = keep[np.argsort(dists[keep], kind="stable")]
    out = []
    for i in keep:  # drop duplicates (the same rotation found about two axes)
        if all(np.linalg.norm(motions[i][:3, :3] - o[:3, :3]) > 0.5 for o in out):  # 20 deg apart
            out.append(motions[i])
        if len(out) >= MAX_NEAR:
            break
    res = np.stack(out) if out else np.zeros((0, 4, 4))

    def forget(ref, key=key):
        if _NEAR.get(key, (None,))[0] is ref:
            del _NEAR[key]

    _NEAR[key] = (weakref.ref(model, forget), res)
    return res


def expand(T_cam_obj: np.ndarray, obj_ids: np.ndarray, db) -> tuple[np.ndarray, np.ndarray]:
    """Variants T @ S of poses T_cam_obj (M, 4, 4) under their objects' near-symmetries S.
    Returns (variants (V, 4, 4), source row (V,) into the input)."""
    T = np.asarray(T_cam_obj, dtype=np.float64).reshape(-1, 4, 4)
    ids = np.asarray(obj_ids).reshape(-1)
    outs, rows = [], []
    for o in np.unique(ids):
        S = near_symmetries(db[int(o)])
        r = np.flatnonzero(ids == o)
        if len(S) == 0 or len(r) == 0:
            continue
        outs.append((T[r][:, None] @ S[None]).reshape(-1, 4, 4))
        rows.append(np.repeat(r, len(S)))
    if not outs:
        return np.zeros((0, 4, 4)), np.zeros(0, np.intp)
    return np.concatenate(outs), np.concatenate(rows)


def visible_depth_score(depth_mm, K, obj_ids, T_cam_obj, db, tol_mm=None, terms: bool = False,
                        samples: int = SAMPLES):
    """Visibility-aware depth consistency (see the module docstring), (M,), higher = better, at most 1.

    depth_mm (H, W) mm (0 = none); K (3, 3); obj_ids (M,); T_cam_obj (M, 4, 4) mm; tol_mm: None
    (per object max(0.02 x diameter, 3 mm)), a number or (M,). With ``terms`` also a dict of the
    per-pose counts (agree, violation, occluded, unknown, visible). ``samples``: surface samples
    used (a uniform subset of the ICP module's)."""
    from .icp import VISIBLE_COS, _surface

    depth = np.asarray(depth_mm, dtype=np.float64)
    H, W = depth.shape
    K = np.asarray(K, dtype=np.float64)
    T = np.asarray(T_cam_obj, dtype=np.float64).reshape(-1, 4, 4)
    ids = np.asarray(obj_ids).reshape(-1)
    M = len(T)
    if M == 0:
        z0 = np.zeros(0)
        return (z0, {}) if terms else z0
    surfs = [_surface(db[int(o)]) for o in ids]
    step = max(1, len(surfs[0].points) // samples)
    P = np.stack([s.points[::step][:samples] for s in surfs])  # (M, n, 3)
    Nr = np.stack([s.normals[::step][:samples] for s in surfs])
    if tol_mm is None:
        tol = np.array([max(0.02 * s.diameter, 3.0) for s in surfs])
    else:
        tol = np.broadcast_to(np.asarray(tol_mm, float), (M,))
    R, t = T[:, :3, :3], T[:, :3, 3]
    X = P @ np.swapaxes(R, 1, 2) + t[:, None]  # (M, n, 3) camera frame
    Nc = Nr @ np.swapaxes(R, 1, 2)
    z = X[..., 2]
    facing = np.einsum("mnk,mnk->mn", Nc, X) < -VISIBLE_COS * np.linalg.norm(X, axis=-1)
    zs = np.where(z > 1e-6, z, 1.0)
    u = (K[0, 0] * X[..., 0] + K[0, 1] * X[..., 1]) / zs + K[0, 2]
    v = K[1, 1] * X[..., 1] / zs + K[1, 2]
    inside = facing & (z > 1e-6) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    # coarse z-buffer per pose: samples more than tol behind the nearest one of their ZBUF_PX cell are
    # hidden (cells as large as the samples' spacing would hide a handle beside the body behind it)
    gw, gh = (W + ZBUF_PX - 1) // ZBUF_PX, (H + ZBUF_PX - 1) // ZBUF_PX
    cell = (np.floor(v / ZBUF_PX).clip(0, gh - 1) * gw + np.floor(u / ZBUF_PX).clip(0, gw - 1)).astype(np.int64)
    cell = np.where(inside, cell * M + np.arange(M)[:, None], -1)  # unique per pose
    flat = cell[inside]
    zin = z[inside]
    order = np.lexsort((zin, flat))
    fs = flat[order]
    first = np.ones(len(fs), bool)
    first[1:] = fs[1:] != fs[:-1]
    starts = np.flatnonzero(first)
    grp = np.cumsum(first) - 1
    zmin_sorted = zin[order][starts][grp]
    zmin = np.empty_like(zin)
    zmin[order] = zmin_sorted
    tol_in = np.broadcast_to(tol[:, None], z.shape)[inside]
    vis_in = zin <= zmin + tol_in
    vis = np.zeros_like(inside)
    vis[inside] = vis_in
    ui = np.rint(u).clip(0, W - 1).astype(np.intp)
    vi = np.rint(v).clip(0, H - 1).astype(np.intp)
    d = depth.ravel().take(np.where(vis, vi * W + ui, 0))
    meas = vis & (d > 0) & np.isfinite(d)
    tl = tol[:, None]
    agree = (meas & (np.abs(z - d) <= tl)).sum(1)
    viol = (meas & (z < d - tl)).sum(1)
    occl = (meas & (z > d + tl)).sum(1)
    unknown = (vis & ~meas).sum(1)
    nvis = vis.sum(1)
    score = np.where(nvis > 0, (agree - VIOLATION_WEIGHT * viol) / np.maximum(nvis - unknown, 1), -1.0)
    if terms:
        return score, {"agree": agree, "violation": viol, "occluded": occl, "unknown": unknown, "visible": nvis}
    return score


def pick_score(depth_mm, K, obj_ids, T_cam_obj, db, image_score=None, image_weight: float = 1.0,
               samples: int = SAMPLES) -> np.ndarray:
    """The depth path's ranking score of poses (M,): :func:`visible_depth_score` (``PICK`` "fit":
    the ICP module's depth_fit_score) plus ``image_weight`` x the image score (M,) (NaN counts 0)
    when given."""
    if PICK == "fit":
        from .icp import depth_fit_score

        s = depth_fit_score(depth_mm, K, obj_ids, T_cam_obj, db)
    else:
        s = visible_depth_score(depth_mm, K, obj_ids, T_cam_obj, db, samples=samples)
    if image_score is not None:
        img = np.asarray(image_score, dtype=np.float64).reshape(-1)
        s = s + image_weight * np.where(np.isfinite(img), img, 0.0)
    return s


def add_variants(depth_mm, K, boxes, obj_ids, T, score, db, *, image_score=None, image_weight: float = 1.0,
                 n_expand: int = 2, icp_conf=None):
    """Grow each detection's refined hypotheses by the near-symmetry variants of its best ones.

    T (N, k, 4, 4) mm: hypotheses already refined by ICP, score (N, k) their :func:`pick_score`;
    boxes (N, 4) px; obj_ids (N,); image_score: None or a function (det (n,), T (n, 4, 4),
    src (n,)) -> (n,) image scores of poses of detections ``det`` derived from hypotheses ``src``
    (indices into k). The variants (:func:`expand`) of each detection's ``n_expand`` best are
    scored as they are; its ``VARIANT_KEEP`` best are refined by a short ICP (``icp_conf``, default
    ``VARIANT_ICP_ITERATIONS`` iterations from a 0.08 x diameter trim, after the usual depth
    alignment: without it YCB-V frames 1-5 lost 0.04 BOP19 AR) and scored the same way, minus
    ``VARIANT_MARGIN``. Returns (T (N, k + m, 4, 4), score (N, k + m)): the inputs first, then the
    variants; detections with fewer than m variants padded with their first hypothesis and a NaN
    score."""
    from .icp import IcpConf, refine_with_depth

    T = np.asarray(T, dtype=np.float64)
    score = np.asarray(score, dtype=np.float64)
    N, k = T.shape[:2]
    ids = np.asarray(obj_ids).reshape(-1)
    n_expand = min(int(n_expand), k)
    if N == 0 or n_expand <= 0:
        return T, score
    top = np.argsort(-np.nan_to_num(score, nan=-np.inf), axis=1, kind="stable")[:, :n_expand]  # (N, e)
    base = T[np.arange(N)[:, None], top].reshape(-1, 4, 4)
    V, src = expand(base, np.repeat(ids, n_expand), db)
    if len(V) == 0:
        return T, score
    det = src // n_expand
    if VARIANT_KEEP and VARIANT_KEEP > 0:  # each detection's VARIANT_KEEP best, by depth score before ICP
        raw = visible_depth_score(depth_mm, K, ids[det], V, db)
        order = np.lexsort((-raw, det))
        start = np.searchsorted(det[order], det[order])  # first position of each detection (det sorted)
        order = order[np.arange(len(order)) - start < VARIANT_KEEP]
    else:
        order = np.argsort(src, kind="stable")  # grouped by detection
    V, src, det = V[order], src[order], det[order]
    hsrc = top.reshape(-1)[src]
    conf = icp_conf or IcpConf(iterations=VARIANT_ICP_ITERATIONS, trim_start=0.08)
    r = refine_with_depth(depth_mm, K, np.asarray(boxes, dtype=np.float64)[det], ids[det], V, db, conf, scores=False)
    img = None if image_score is None else image_score(det, r.T_cam_obj, hsrc)
    sv = pick_score(depth_mm, K, ids[det], r.T_cam_obj, db, img, image_weight) - VARIANT_MARGIN
    counts = np.bincount(det, minlength=N)
    m = int(counts.max())
    slot = np.arange(len(det)) - np.repeat(np.cumsum(counts) - counts, counts)  # position within its detection
    Tv = np.repeat(T[:, :1], m, 1).copy()
    Sv = np.full((N, m), np.nan)
    Tv[det, slot] = r.T_cam_obj
    Sv[det, slot] = sv
    return np.concatenate([T, Tv], 1), np.concatenate([score, Sv], 1)


def refine_and_rank(depth_mm, K, boxes, obj_ids, hyp, k: int, db, icp_conf, *, image_score=None,
                    image_weight: float = 1.0, tiebreak=None, prior_score=None, screen: int = 0):
    """The depth path's choice among ranked hypotheses: ICP, scores, more hypotheses where needed.

    hyp (N, n, 4, 4) mm: each detection's hypotheses, best first (n >= k); the first ``k`` are
    refined by ICP (:func:`~cosy_cli.singleview.training_free.icp.refine_with_depth` under ``icp_conf``) and
    scored by :func:`pick_score` (``image_score`` as in :func:`add_variants`, its ``src`` an index
    into n; ``tiebreak`` (N, n) or None: added to the score, e.g. a small multiple of the hypotheses'
    own scores). With ``screen`` > k the first ``screen`` hypotheses are screened instead: a short
    ICP (``SCREEN_ITERATIONS`` iterations on ``SCREEN_POINTS`` points per box), ranked by
    :func:`pick_score` + image_weight x ``prior_score`` (N, n) (their image scores before ICP, when
    given), and the k best go on to the full ICP from where the short one left them (proxy RGB-D
    LM-O odd scenes: BOP19 AR 0.671 -> 0.703 with 32 screened and 12 kept, about the same time;
    synthetic dev scenes 0.920 -> 0.937; YCB-V frames 1-5 0.625 -> 0.554: one mug and two brick
    flips, one box flip the other way). Detections whose best depth score stays below ``RETRY_BELOW`` (no hypothesis fits
    the depth: all of them wrong, or ICP lost them) refine and score their next ``k`` hypotheses
    too; then the near-symmetry variants of every detection's ``N_EXPAND`` best are added
    (:func:`add_variants`). Returns (T (N, m, 4, 4), score (N, m)), m >= k; NaN scores mark padding.
    """
    from .icp import refine_with_depth

    hyp = np.asarray(hyp, dtype=np.float64)
    N, n = hyp.shape[:2]
    k = min(int(k), n)
    ids = np.asarray(obj_ids).reshape(-1)
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    tb = np.zeros((N, n)) if tiebreak is None else np.asarray(tiebreak, dtype=np.float64)

    def run(rows, cols, start=None):  # ICP + scores of hypotheses (rows, cols) -> (T (len, 4, 4), depth score, total)
        r = refine_with_depth(depth_mm, K, boxes[rows], ids[rows], hyp[rows, cols] if start is None else start, db,
                              icp_conf if start is None else replace(icp_conf, align_depth=False), scores=False)
        d = pick_score(depth_mm, K, ids[rows], r.T_cam_obj, db)
        img = None if image_score is None else image_score(rows, r.T_cam_obj, cols)
        tot = d + (0.0 if img is None else image_weight * np.where(np.isfinite(img), img, 0.0)) + tb[rows, cols]
        return r.T_cam_obj, d, tot

    start = None
    rows, cols = np.repeat(np.arange(N), k), np.tile(np.arange(k), N)
    if screen > k and n > k:  # a short ICP of the first `screen` hypotheses; the k best go on from there
        ks = min(int(screen), n)
        rs, cs = np.repeat(np.arange(N), ks), np.tile(np.arange(ks), N)
        short = refine_with_depth(depth_mm, K, boxes[rs], ids[rs], hyp[rs, cs], db,
                                  replace(icp_conf, iterations=SCREEN_ITERATIONS, max_points=SCREEN_POINTS,
                                          align_points=SCREEN_ALIGN_POINTS), scores=False)
        pre = pick_score(depth_mm, K, ids[rs], short.T_cam_obj, db, samples=SCREEN_SAMPLES).reshape(N, ks)
        if prior_score is not None:
            pre = pre + image_weight * np.nan_to_num(np.asarray(prior_score, dtype=np.float64)[:, :ks], nan=-1.0)
        cols = np.argsort(-pre, axis=1, kind="stable")[:, :k].reshape(-1)
        start = short.T_cam_obj.reshape(N, ks, 4, 4)[rows, cols]
    Tr, d, tot = run(rows, cols, start)
    T, score = Tr.reshape(N, k, 4, 4), tot.reshape(N, k)
    col_of = cols.reshape(N, k)  # the hypothesis of hyp behind each column of T
    weak = np.flatnonzero(d.reshape(N, k).max(1) < RETRY_BELOW) if RETRY_BELOW is not None else np.zeros(0, int)
    if len(weak) and n > k:
        k2 = min(k, n - k)
        rows, cols = np.repeat(weak, k2), np.tile(np.arange(k, k + k2), len(weak))
        Tr, _, tot = run(rows, cols)
        T2 = np.repeat(T[:, :1], k2, 1).copy()
        S2 = np.full((N, k2), np.nan)
        T2[weak], S2[weak] = Tr.reshape(len(weak), k2, 4, 4), tot.reshape(len(weak), k2)
        T, score = np.concatenate([T, T2], 1), np.concatenate([score, S2], 1)
        col_of = np.concatenate([col_of, np.tile(np.arange(k, k + k2), (N, 1))], 1)
    if N_EXPAND > 0:
        if image_score is not None:
            base_score = image_score

            def image_score(det, T_, src):  # src: a column of T, i.e. hypothesis col_of[det, src] of hyp
                return base_score(det, T_, col_of[det, src])
        T, score = add_variants(depth_mm, K, boxes, ids, T, score, db, image_score=image_score,
                                image_weight=image_weight, n_expand=N_EXPAND)
    return T, score
