"""Object-level bundle adjustment (CosyPose stage 3): one consistent scene from matched candidates.

Pure, batched numpy. Lengths in mm, angles in radians, pixels for reprojections. Poses are 4x4
``T_a_b`` matrices (frame b -> frame a), cameras OpenCV (x right, y down, z forward).

The problem (paper Eq. 4-5). Unknowns: ``T_world_cam`` of every placed view (one or more held
fixed: the gauge) and ``T_world_obj`` of every physical object. Each candidate m (an object n
seen in view v with single-view pose ``T_cam_cand``) contributes, for each model point x of the
object's label, the 2D residual

    r_m(x) = pi_v(inv(T_world_cam[v]) T_world_obj[n] x) - pi_v(T_cam_cand[m] S_m x)

(scene estimate minus measurement), where pi_v projects with view v's K and S_m is the
symmetry of the label that best explains the candidate. The cost is

    F = mean_m  sum_x w_x rho(|r_m(x)|^2),    rho(e^2) = min(e^2, tau^2)   (px^2)

with w_x = 1 / (number of model points) (a mean over points), i.e. the paper's truncated L2
loss averaged over candidates: sqrt(F) is an RMS reprojection error in pixels.

Choices (documented because the paper leaves them open):

* **Truncation.** The loss is the hard-truncated quadratic itself, optimised by Gauss-Newton/LM
  with IRLS weights 1 (|r| < tau) or 0 (|r| >= tau): that is exactly the Gauss-Newton model of
  the truncated cost (an outlier point has zero gradient). LM accepts a step only when the
  true truncated cost decreases, so the discontinuity of the weights cannot make it diverge.
  Points behind a camera (z < ``z_min_mm``) in the estimate or the measurement count as
  outliers (cost tau^2, weight 0): no division by a tiny depth ever reaches the Jacobian.
* **Manifold.** Right perturbations: ``T <- T [Exp(w), rho]`` for cameras (camera frame) and
  objects (object frame: rotations about the object's own origin, well conditioned). Analytic
  Jacobians; LM with Marquardt scaling ``(H + lambda diag H) delta = -g`` and Nielsen's damping
  update; one dense normal-equation solve per iteration (the system has 6 (V - fixed + N) +
  (continuous-symmetry angles) unknowns: 60 for 4 views x 6 objects).
* **Symmetries.** Each candidate re-selects, among its label's discrete symmetry set
  (continuous axes discretised, 64 steps by default), the S of least truncated 2D cost, and
  switches only when that is strictly lower than its current S's (so the cost never rises).
  The 2D cost is evaluated exactly, batched, for the ``symmetry_shortlist`` (default 4)
  symmetries that best align the candidate with the estimate in 3D (mean squared point
  distance, in closed form from the points' second moments: 48 flops per symmetry), or for
  the whole set with ``symmetry_shortlist=None``. Re-selection runs before the first
  iteration, after every LM step that lowers the cost by more than 0.1 % (the poses still
  move), and again whenever the optimisation stops -- iterations resume if it switched any
  candidate, so the result is stable under re-selection. For a label with exactly one
  continuous axis the angle about the axis is, in addition, refined continuously: each
  candidate (but one reference candidate per object, which fixes the otherwise free spin of
  the object about its own axis) gets an angle unknown phi_m in the LM, S_m <- C(phi_m) S_m.
  So a cylinder seen with arbitrary rotations about its axis converges to zero cost on exact
  data instead of stopping at the 64-step discretisation floor.
* **Poor starts.** A truncated loss has a basin no wider than its threshold. When the
  initial reprojection errors exceed tau -- twice the largest per-view (lower) median of the
  candidates' mean point errors is > 1.5 tau --, the threshold starts there (at most
  ``anneal_max_factor`` tau = 200 px by default) and is halved stage by stage down to tau
  (intermediate stages stop at a 0.1 % relative decrease). With a good start (the usual case)
  there is a single stage at tau. Per-view medians, not a high percentile of all point errors:
  a camera placed poorly moves all of its view's candidates and needs the schedule, while a few
  gross outlier candidates must not start the threshold high, where they would pull the scene
  before being truncated.
* **Model points.** The 8 corners of the label's bounding box (model frame), as the original
  CosyPose code (``point_set="box"``; ``"surface"``: ``n_points`` farthest-point surface
  samples). The points' spread sets how the reprojection loss weighs each candidate's rotation
  and depth (their image evidence grows with the spread) against its lateral position; the
  corners spread ~1.5x wider than surface points and, on the simulated scenes of
  benchmarks/bench_refine.py (6 views x 8 objects), lower the refined ADD-S by 5-9 % relative
  to 64 surface points (and the relative camera errors by 5-15 %), with an eighth of the
  residuals. Residuals are M x P x 2 arrays.

Stage helpers: :func:`initialise_cameras` (chains pairwise relative poses over a maximum-inlier
spanning tree), :func:`initialise_objects` (each object from its most consistent candidate: the medoid of
its candidates under a truncated symmetric distance, then the best score),
:func:`predictions_from_scene` (every object in every camera).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Hashable, Mapping, Sequence

import numpy as np

from ..geometry.poses import invert
from ..geometry.sampling import farthest_point_subset

DEFAULT_POINT_SET = "box"  # residual points: the 8 bounding-box corners (as the original CosyPose); "surface"
DEFAULT_N_POINTS = 64  # surface points per label with point_set="surface"
DEFAULT_LOSS_THRESHOLD_PX = 25.0  # truncation of the per-point reprojection error (px)
DEFAULT_ITERATIONS = 100  # LM iterations at most (paper: <= 100, converges in < 10)
DEFAULT_N_CONTINUOUS = 64  # discretisation of continuous symmetries for re-selection (paper: 64)
_COST_EPS = 1e-20  # px^2: cost differences below this are rounding (exact data reach ~1e-27)
DEFAULT_CONSENSUS_MM = 20.0  # initialise_objects: truncation of the candidates' mutual distances (RANSAC's 2 cm)
DEFAULT_SHORTLIST = 4  # symmetries per candidate given the exact 2D cost at each re-selection


# --------------------------------------------------------------------------------------------
# Object geometry
# --------------------------------------------------------------------------------------------

farthest_point_sample = farthest_point_subset  # n of the points, spread over the object


@dataclass(frozen=True)
class LabelGeometry:
    """What the optimiser needs of an object label.

    points: (P, 3) model points in mm (the residuals' x); symmetries: (S, 4, 4) the discrete
    symmetry set, identity first (continuous axes discretised); axis/offset: the continuous
    symmetry axis (unit, model frame) through ``offset`` (mm) when the label has exactly one,
    enabling continuous refinement of the angle about it; None otherwise.
    """

    points: np.ndarray
    symmetries: np.ndarray = field(default_factory=lambda: np.eye(4)[None])
    axis: np.ndarray | None = None
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @classmethod
    def from_model(cls, model, n_points: int = DEFAULT_N_POINTS,
                   n_continuous: int = DEFAULT_N_CONTINUOUS, point_set: str = DEFAULT_POINT_SET) -> "LabelGeometry":
        """From an :class:`cosy_cli.objects.ObjectModel` (its surface points and models_info symmetries)."""
        cont = list(model.info.symmetries_continuous)
        axis = offset = None
        if len(cont) == 1:
            axis = cont[0]["axis"]
            offset = cont[0].get("offset", np.zeros(3))
        return cls.create(model.points, model.symmetries_with_steps(n_continuous), axis, offset, n_points=n_points,
                          point_set=point_set)

    @classmethod
    def create(cls, points: np.ndarray, symmetries: np.ndarray | None = None, axis=None, offset=None,
               n_points: int = DEFAULT_N_POINTS, point_set: str = DEFAULT_POINT_SET) -> "LabelGeometry":
        """The residuals' model points from the object's surface ``points`` (mm), and checks the
        symmetry set. ``point_set``: "box" (default) -- the 8 corners of the points' axis-aligned
        bounding box (model frame), as the original CosyPose; "surface" -- ``n_points``
        farthest-point samples of ``points``. See :func:`residual_points`."""
        S = np.eye(4)[None] if symmetries is None else np.asarray(symmetries, dtype=np.float64).reshape(-1, 4, 4)
        if not np.allclose(S[0], np.eye(4)):
            raise ValueError("the symmetry set must start with the identity")
        if axis is not None:
            axis = np.asarray(axis, dtype=np.float64)
            axis = axis / np.linalg.norm(axis)
        off = np.zeros(3) if offset is None else np.asarray(offset, dtype=np.float64).reshape(3)
        return cls(residual_points(points, n_points, point_set), S, axis, off)


def box_corners(points: np.ndarray) -> np.ndarray:
    """The 8 corners (8, 3) of the axis-aligned bounding box of ``points`` (P, 3) (mm)."""
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    lo, hi = P.min(0), P.max(0)
    sel = (np.arange(8)[:, None] >> np.arange(3)[None]) & 1  # (8, 3) 0/1: which end per axis
    return np.where(sel == 1, hi, lo)


def residual_points(points: np.ndarray, n_points: int = DEFAULT_N_POINTS, point_set: str = DEFAULT_POINT_SET
                    ) -> np.ndarray:
    """The model points x of the reprojection residuals (mm).

    "box": the 8 bounding-box corners (what the original CosyPose code uses). They lie farther
    from the object's centre than its surface points (RMS radius ~1.3-1.7x), which weights the
    image-plane evidence of each candidate's rotation and depth (both grow with the points'
    spread) more against its lateral position: on the simulated 6-view scenes of
    benchmarks/bench_refine.py this lowers the refined ADD-S by 5-9 % relative to 64 surface
    points (and costs 8 instead of 64 points per candidate). A degenerate box (a rod: fewer than
    two extents above 1e-3 of the largest) cannot fix the rotation about its long axis: the
    ``n_points`` surface samples are then appended. "surface": ``n_points`` farthest-point
    samples of ``points``."""
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if point_set == "surface":
        return farthest_point_sample(P, n_points)
    if point_set != "box":
        raise ValueError(f"point_set must be 'box' or 'surface', not {point_set!r}")
    ext = P.max(0) - P.min(0)
    C = box_corners(P)
    if np.sum(ext > 1e-3 * max(ext.max(), 1e-300)) < 2:
        C = np.r_[C, farthest_point_sample(P, n_points)]
    return C


# --------------------------------------------------------------------------------------------
# Initialisation
# --------------------------------------------------------------------------------------------

def initialise_cameras(im_ids: Sequence[Hashable], pair_poses: Mapping[tuple, np.ndarray],
                       pair_inliers: Mapping[tuple, float] | None = None, gauge: Hashable | None = None
                       ) -> tuple[dict, list]:
    """Place views by chaining relative poses over a maximum-inlier spanning tree.

    ``pair_poses[(a, b)]`` = T_cam_a_cam_b (4, 4, mm) for view pairs that were matched (either
    orientation may be given); ``pair_inliers[(a, b)]`` its support (number of inlier pairs;
    all 1 when None). The largest connected set of views is placed (ties: the one holding the
    earliest view of ``im_ids``); its gauge view -- ``gauge`` if given, else the view with most
    total inliers (ties: earliest in ``im_ids``) -- gets the identity, so the world frame is
    the gauge camera's frame. The tree is grown from the gauge by Prim's algorithm taking the
    highest-inlier edge first (ties: earliest views), which yields a maximum spanning tree.

    Returns ({im_id: T_world_cam (4, 4)} in tree order, gauge first; [unplaced im_ids]).
    """
    edges = []
    for (a, b), T in pair_poses.items():
        w = 1.0 if pair_inliers is None else float(pair_inliers.get((a, b), pair_inliers.get((b, a), 0.0)))
        edges.append((a, b, w, T, None))
    placed, _, _ = spanning_tree_poses(im_ids, edges, gauge)
    unplaced = [v for v in im_ids if v not in placed]
    return placed, unplaced


def spanning_tree_poses(im_ids: Sequence[Hashable], edges, gauge: Hashable | None = None):
    """Chain relative poses over a maximum-weight spanning tree (the rule of
    :func:`initialise_cameras`).

    ``edges``: (a, b, weight, T_a_b (4, 4, mm), payload) tuples; of several edges between two
    views the heaviest counts; self-loops and unknown views are ignored. Returns ({im_id:
    T_world_cam} in tree order, gauge first; {im_id: (the placed view it was reached from,
    the payload of that edge)} for every placed view but the gauge; the gauge im_id).
    """
    order = {v: i for i, v in enumerate(im_ids)}
    if len(order) != len(im_ids):
        raise ValueError("im_ids must be unique")
    adj: dict = {v: {} for v in im_ids}
    for a, b, w, T, payload in edges:
        if a not in order or b not in order or a == b:
            continue
        T = np.asarray(T, dtype=np.float64)
        if b not in adj[a] or w > adj[a][b][0]:
            adj[a][b] = (w, T, payload)
            adj[b][a] = (w, invert(T), payload)
    comp: dict = {}
    comps = []
    for v in im_ids:  # connected components
        if v in comp:
            continue
        stack, members = [v], []
        comp[v] = len(comps)
        while stack:
            x = stack.pop()
            members.append(x)
            for y in adj[x]:
                if y not in comp:
                    comp[y] = len(comps)
                    stack.append(y)
        comps.append(sorted(members, key=order.__getitem__))
    strength = {v: sum(e[0] for e in adj[v].values()) for v in im_ids}
    if gauge is not None:
        if gauge not in order:
            raise ValueError(f"gauge view {gauge!r} is not in im_ids")
        main = comps[comp[gauge]]
    else:
        main = max(comps, key=lambda c: (len(c), -order[c[0]]))
        gauge = max(main, key=lambda v: (strength[v], -order[v]))
    placed = {gauge: np.eye(4)}
    via: dict = {}
    while len(placed) < len(main):  # Prim: the heaviest edge out of the placed set first
        best = None
        for a in placed:
            for b, (w, T, payload) in adj[a].items():
                if b in placed:
                    continue
                key = (w, -order[a], -order[b])
                if best is None or key > best[0]:
                    best = (key, a, b, T, payload)
        _, a, b, T_a_b, payload = best
        placed[b] = placed[a] @ T_a_b
        via[b] = (a, payload)
    return placed, via, gauge


def _second_moments(points: np.ndarray) -> np.ndarray:
    """E[x~ x~^T] (4, 4) of homogeneous points x~ = (x, 1): mean ||G x - H x||^2 over the
    points is then tr((G - H)[:3] M (G - H)[:3]^T) for any 4x4 G, H (mm^2)."""
    Xh = np.c_[points, np.ones(len(points))]
    return Xh.T @ Xh / len(points)


def _exp_so3(w: np.ndarray) -> np.ndarray:
    """Rodrigues for small batches (B, 3) -> (B, 3, 3); exact, stable at 0."""
    th2 = np.einsum("bi,bi->b", w, w)
    th = np.sqrt(th2)
    small = th2 < 1e-16
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(ths)) / np.where(small, 1.0, th2))
    R = w[:, :, None] * w[:, None, :] * b[:, None, None]  # b w w^T
    R[:, 0, 0] += 1.0 - b * th2
    R[:, 1, 1] += 1.0 - b * th2
    R[:, 2, 2] += 1.0 - b * th2  # (1 - b th^2) I + b w w^T = I + b [w]x^2
    aw = a[:, None] * w
    R[:, 0, 1] -= aw[:, 2]
    R[:, 1, 0] += aw[:, 2]
    R[:, 0, 2] += aw[:, 1]
    R[:, 2, 0] -= aw[:, 1]
    R[:, 1, 2] -= aw[:, 0]
    R[:, 2, 1] += aw[:, 0]
    return R


def _worst_view_median(err: np.ndarray, view: np.ndarray) -> float:
    """max over views of the lower median of ``err`` (per-candidate errors) within the view."""
    order = np.lexsort((err, view))
    v = view[order]
    start = np.flatnonzero(np.r_[True, v[1:] != v[:-1]])
    count = np.diff(np.r_[start, len(v)])
    return float(err[order[start + (count - 1) // 2]].max())


class _SymmetryTable:
    """The discrete symmetry sets of the candidates, one block per label with more than one
    symmetry: cands (n_l,) candidate indices, S (S_l, 4, 4), with what the closed-form mean
    squared distance mean_x ||S x - B x||^2 = SS - 2 <S M2, B> + <B M2, B> needs."""

    def __init__(self, cand_label: np.ndarray, geometry: Sequence[LabelGeometry]):
        self.blocks = []
        for lab in np.unique(cand_label):  # a loop over labels (each has its own set)
            g = geometry[lab]
            if len(g.symmetries) < 2:
                continue
            S = np.asarray(g.symmetries, dtype=np.float64)
            M2 = _second_moments(g.points)
            S3 = S[:, :3, :]
            self.blocks.append(dict(
                label=int(lab), cands=np.flatnonzero(cand_label == lab), S=S, M2=M2,
                S12=S3.reshape(-1, 12), SS=np.sum((S3 @ M2) * S3, axis=(1, 2))))

    @staticmethod
    def mean_sq(block: dict, B: np.ndarray) -> np.ndarray:
        """(n_l, S_l) mean_x ||S x - B_m x||^2 (mm^2) for B (n_l, 4, 4) (the object estimate in
        each candidate's frame)."""
        B3 = B[:, :3, :]
        BM = B3 @ block["M2"]
        BB = np.sum(BM * B3, axis=(1, 2))
        return block["SS"][None] - 2.0 * (BM.reshape(len(B), 12) @ block["S12"].T) + BB[:, None]


def _pair_sym_rms(B: np.ndarray, pair_label: np.ndarray, geometry: Sequence[LabelGeometry]) -> np.ndarray:
    """min_S sqrt(mean_x ||S x - B x||^2) (mm) per pose B (K, 4, 4) of label ``pair_label`` (K,):
    the RMS symmetric distance between two poses T_i, T_j with B = inv(T_i) T_j."""
    out = np.empty(len(B))
    for lab in np.unique(pair_label):  # a loop over labels
        k = np.flatnonzero(pair_label == lab)
        g = geometry[lab]
        S3 = np.asarray(g.symmetries, dtype=np.float64)[:, :3, :]
        M2 = _second_moments(g.points)
        SS = np.sum((S3 @ M2) * S3, axis=(1, 2))
        B3 = B[k, :3, :]
        BM = B3 @ M2
        d2 = SS[None] - 2.0 * (BM.reshape(len(k), 12) @ S3.reshape(len(S3), 12).T) + np.sum(BM * B3, axis=(1, 2))[:, None]
        out[k] = np.sqrt(np.maximum(d2.min(1), 0.0))
    return out


def initialise_objects(T_world_cam: np.ndarray, cand_view: np.ndarray, cand_obj: np.ndarray,
                       T_cam_cand: np.ndarray, obj_label: np.ndarray, geometry: Sequence[LabelGeometry],
                       cand_score: np.ndarray | None = None, consensus_mm: float | None = DEFAULT_CONSENSUS_MM
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each object's world pose from its most consistent candidate; each candidate's best symmetry.

    T_world_cam: (V, 4, 4) placed views; cand_view (M,) indices into them; cand_obj (M,)
    object indices 0..N-1 (N = len(obj_label)); T_cam_cand (M, 4, 4) mm; obj_label (N,)
    indices into ``geometry``; cand_score (M,) (higher is better; None: all equal).

    The object is initialised from the candidate, mapped to the world, with the least summed
    truncated distance min(d, ``consensus_mm``) to the object's other candidates (d: the RMS
    symmetric distance over the label's points, mm) -- their medoid, so that a gross outlier
    candidate is not the start when the others agree (a truncated loss cannot leave a start
    beyond its threshold). Ties (within 1e-6 mm: an object seen twice, exact data) go to the
    highest score, then the first candidate. ``consensus_mm=None``: the highest score alone.

    Returns T_world_obj (N, 4, 4) (NaN for an object without candidates); the symmetry index
    (M,) into its label's set that best aligns the candidate with the object's initial pose,
    argmin_S mean_x ||T_cam_cand S x - inv(T_world_cam) T_world_obj x||^2 (the RMS version of
    D_l, in closed form from the points' second moments); and the index (N,) of the candidate
    each object was initialised from (-1 when none).
    """
    T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
    T_cam_cand = np.asarray(T_cam_cand, dtype=np.float64)
    cand_view = np.asarray(cand_view, dtype=np.int64)
    cand_obj = np.asarray(cand_obj, dtype=np.int64)
    obj_label = np.asarray(obj_label, dtype=np.int64)
    M, N = len(cand_obj), len(obj_label)
    score = np.zeros(M) if cand_score is None else np.asarray(cand_score, dtype=np.float64)
    consensus = np.zeros(M)
    if consensus_mm is not None and M:
        # every ordered pair (i, j != i) of candidates of one object
        T_w = T_world_cam[cand_view] @ T_cam_cand
        by_obj = np.argsort(cand_obj, kind="stable")
        counts = np.bincount(cand_obj, minlength=N)
        starts = np.r_[0, np.cumsum(counts)[:-1]]
        n_i = counts[cand_obj[by_obj]]  # each candidate's group size, in group order
        i = np.repeat(by_obj, n_i)
        j = by_obj[np.repeat(starts[cand_obj[by_obj]], n_i) + np.arange(n_i.sum()) - np.repeat(np.cumsum(n_i) - n_i, n_i)]
        i, j = i[i != j], j[i != j]
        if len(i):
            d = _pair_sym_rms(invert(T_w[i]) @ T_w[j], obj_label[cand_obj[i]], geometry)
            consensus = np.bincount(i, weights=np.minimum(d, float(consensus_mm)), minlength=M)
        consensus = np.round(consensus * 1e6)  # ties within 1e-6 mm go to the score
    # initial candidate per object: sort by (object, consensus, -score, index), each group's first
    order = np.lexsort((np.arange(M), -score, consensus, cand_obj))
    first = np.ones(M, dtype=bool)
    first[1:] = cand_obj[order[1:]] != cand_obj[order[:-1]]
    init_cand = np.full(N, -1, dtype=np.int64)
    init_cand[cand_obj[order[first]]] = order[first]
    T_world_obj = np.full((N, 4, 4), np.nan)
    has = init_cand >= 0
    c = init_cand[has]
    T_world_obj[has] = T_world_cam[cand_view[c]] @ T_cam_cand[c]
    sym = np.zeros(M, dtype=np.int64)
    if M:
        # the object estimate in each candidate's frame
        B = invert(T_cam_cand) @ invert(T_world_cam[cand_view]) @ T_world_obj[cand_obj]
        for blk in _SymmetryTable(obj_label[cand_obj], geometry).blocks:
            sym[blk["cands"]] = np.argmin(_SymmetryTable.mean_sq(blk, B[blk["cands"]]), axis=1)
    return T_world_obj, sym, init_cand


def predictions_from_scene(T_world_cam: np.ndarray, T_world_obj: np.ndarray) -> np.ndarray:
    """Every object in every camera: T_cam_obj (V, N, 4, 4) = inv(T_world_cam[v]) T_world_obj[n]."""
    return invert(np.asarray(T_world_cam, dtype=np.float64))[:, None] @ np.asarray(T_world_obj, dtype=np.float64)[None]


# --------------------------------------------------------------------------------------------
# Bundle adjustment
# --------------------------------------------------------------------------------------------

@dataclass
class BundleResult:
    """Refined scene and diagnostics. Costs in px^2 (mean over candidates of the mean truncated
    squared reprojection error over model points); errors in px."""

    T_world_cam: np.ndarray  # (V, 4, 4) mm
    T_world_obj: np.ndarray  # (N, 4, 4) mm
    symmetries: np.ndarray  # (M, 4, 4): S_m per candidate (continuous angle refined)
    symmetry_index: np.ndarray  # (M,) nearest member of the label's discrete set
    cost_history: np.ndarray  # cost before each linearisation (at the threshold then in force), then the final cost
    iterations: int  # LM iterations run (one linear solve each)
    converged: bool
    initial_cost: float
    final_cost: float
    cand_error_px: np.ndarray  # (M,) mean |r| over the candidate's points (untruncated), final
    initial_cand_error_px: np.ndarray  # (M,) same, before optimisation (with the first re-selected S)
    inlier_fraction: np.ndarray  # (M,) fraction of points with |r| < threshold, final
    view_error_px: np.ndarray  # (V,) mean of cand_error_px over the view's candidates (NaN: none)
    initial_view_error_px: np.ndarray  # (V,)
    time_s: float


class _Problem:
    """Precomputed per-candidate arrays and the column layout of the normal equations.

    Layout: points are (M, 3, P) (coordinates, then points: contiguous rows for numpy), pixels
    (M, 2, P), the Jacobian (M, 13, 2, P)."""

    def __init__(self, V, N, cand_view, cand_obj, T_cam_cand, K, obj_label, geometry, fixed_views, tau, z_min,
                 continuous):
        self.V, self.N = V, N
        self.cand_view = np.asarray(cand_view, dtype=np.int64).reshape(-1)
        self.cand_obj = np.asarray(cand_obj, dtype=np.int64).reshape(-1)
        M = self.M = len(self.cand_view)
        if M == 0 or len(self.cand_obj) != M:
            raise ValueError("bundle adjustment needs at least one candidate, with a view and an object each")
        if self.cand_view.min() < 0 or self.cand_view.max() >= V or self.cand_obj.min() < 0 or self.cand_obj.max() >= N:
            raise ValueError("cand_view / cand_obj index outside the cameras / objects")
        self.T_cam_cand = np.asarray(T_cam_cand, dtype=np.float64).reshape(M, 4, 4)
        self.T_cand_cam = invert(self.T_cam_cand)
        K = np.asarray(K, dtype=np.float64)
        K = np.broadcast_to(K, (V, 3, 3)) if K.ndim == 2 else K.reshape(V, 3, 3)
        self.Km = np.ascontiguousarray(K[self.cand_view])  # (M, 3, 3)
        self.tau2 = float(tau) ** 2
        self.z_min = float(z_min)
        labels = np.asarray(obj_label, dtype=np.int64).reshape(N)
        if labels.min() < 0 or labels.max() >= len(geometry):
            raise ValueError("obj_label index outside geometry")
        self.cand_label = labels[self.cand_obj]

        # model points per label, padded to a common P with zero weights
        P = max(len(g.points) for g in geometry)
        L = len(geometry)
        X = np.zeros((L, 3, P))
        W = np.zeros((L, P))
        for i, g in enumerate(geometry):
            X[i, :, :len(g.points)] = np.asarray(g.points, dtype=np.float64).T
            W[i, :len(g.points)] = 1.0 / len(g.points)
        self.P = P
        self.Xm = X[self.cand_label]  # (M, 3, P)
        self.mask = W[self.cand_label] > 0  # (M, P) real points
        self.Wm = W[self.cand_label] / M  # (M, P): a mean over points, then over candidates
        self.sym = _SymmetryTable(self.cand_label, geometry)

        # continuous axes per candidate (labels with exactly one axis)
        has_axis = np.array([g.axis is not None for g in geometry])
        axes = np.array([g.axis if g.axis is not None else np.zeros(3) for g in geometry],
                        dtype=np.float64).reshape(L, 3)
        offs = np.array([g.offset for g in geometry], dtype=np.float64).reshape(L, 3)
        self.cont = has_axis[self.cand_label] & bool(continuous)  # (M,)
        self.axis_m = axes[self.cand_label]
        self.off_m = offs[self.cand_label]

        # columns: free cameras, objects, then continuous angles (set_phi_columns)
        fixed = np.zeros(V, dtype=bool)
        if isinstance(fixed_views, str):
            if fixed_views != "all":
                raise ValueError("fixed_views: an index, indices, 'all' or None")
            fixed[:] = True
        elif fixed_views is not None:
            fixed[np.atleast_1d(np.asarray(fixed_views, dtype=np.int64))] = True
        self.fixed = fixed
        self.n_free_cams = int((~fixed).sum())
        self.cam_col = np.full(V, -1, dtype=np.int64)
        self.cam_col[~fixed] = 6 * np.arange(self.n_free_cams)
        self.obj_col = 6 * self.n_free_cams + 6 * np.arange(N)
        self.n_pose = 6 * (self.n_free_cams + N)
        self.set_phi_columns(np.zeros(M, dtype=bool))

    def set_phi_columns(self, free_phi: np.ndarray) -> None:
        self.free_phi = free_phi
        self.phi_idx = np.flatnonzero(free_phi)
        self.phi_col = np.full(self.M, -1, dtype=np.int64)
        self.phi_col[self.phi_idx] = self.n_pose + np.arange(len(self.phi_idx))
        self.n = self.n_pose + len(self.phi_idx)
        dummy = self.n  # a row/column that is dropped: fixed cameras, candidates without an angle
        cam = self.cam_col[self.cand_view]
        ar6 = np.arange(6)
        idx = np.empty((self.M, 13), dtype=np.int64)
        idx[:, :6] = np.where(cam[:, None] >= 0, cam[:, None] + ar6, dummy)
        idx[:, 6:12] = self.obj_col[self.cand_obj][:, None] + ar6
        idx[:, 12] = np.where(self.phi_col >= 0, self.phi_col, dummy)
        self.block_idx = idx
        self.lin_idx = (idx[:, :, None] * (self.n + 1) + idx[:, None, :]).ravel()

    def project(self, p: np.ndarray, K: np.ndarray):
        """Camera-frame points (B, 3, P), K (B, 3, 3) -> pixels (B, 2, P), valid (B, P), z (B, P)."""
        q = K @ p
        valid = (p[:, 2] > self.z_min) & (q[:, 2] > 0)
        z = np.where(valid, q[:, 2], 1.0)
        return q[:, :2] / z[:, None], valid, z

    # ---- state evaluation ------------------------------------------------------------------
    def estimate(self, T_world_cam, T_world_obj):
        A = invert(T_world_cam)[self.cand_view] @ T_world_obj[self.cand_obj]  # (M, 4, 4) T_cam_obj
        p = A[:, :3, :3] @ self.Xm + A[:, :3, 3:]
        u, valid, z = self.project(p, self.Km)
        return dict(A=A, p=p, u=u, valid=valid, z=z)

    def measure(self, S):
        SX = S[:, :3, :3] @ self.Xm + S[:, :3, 3:]  # S x, model frame
        y = self.T_cam_cand[:, :3, :3] @ SX + self.T_cam_cand[:, :3, 3:]
        u, valid, z = self.project(y, self.Km)
        return dict(SX=SX, u=u, valid=valid, z=z)

    def point_costs(self, est, meas):
        d = est["u"] - meas["u"]
        e2 = d[:, 0] ** 2 + d[:, 1] ** 2
        ok = est["valid"] & meas["valid"]
        return np.where(ok, np.minimum(e2, self.tau2), self.tau2), e2, ok

    def cand_costs(self, est, meas):
        rho, _, _ = self.point_costs(est, meas)
        return np.einsum("mp,mp->m", self.Wm, rho)

    def reselect(self, est, S, cand_cost, shortlist):
        """Per candidate, the discrete symmetry of least truncated 2D cost among the
        ``shortlist`` best by the closed-form 3D proxy (all when None); replaces the current S
        only where strictly better. Returns (S, switched (M,) bool)."""
        switched = np.zeros(self.M, dtype=bool)
        if not self.sym.blocks:
            return S, switched
        B = self.T_cand_cam @ est["A"]  # the estimate in each candidate's frame
        cs, Ss, ks = [], [], []
        for blk in self.sym.blocks:
            c = blk["cands"]
            n_s = len(blk["S"])
            if shortlist is None or shortlist >= n_s:
                sl = np.broadcast_to(np.arange(n_s), (len(c), n_s))
            else:
                d3 = _SymmetryTable.mean_sq(blk, B[c])
                sl = np.argpartition(d3, shortlist - 1, axis=1)[:, :shortlist]
            cs.append(np.repeat(c, sl.shape[1]))
            Ss.append(blk["S"][sl.ravel()])
            ks.append(sl.shape[1])
        c = np.concatenate(cs)
        Sq = np.concatenate(Ss)
        T = self.T_cam_cand[c] @ Sq
        y = T[:, :3, :3] @ self.Xm[c] + T[:, :3, 3:]
        U, valid, _ = self.project(y, self.Km[c])
        dd = est["u"][c] - U
        e2 = dd[:, 0] ** 2 + dd[:, 1] ** 2
        rho = np.where(est["valid"][c] & valid, np.minimum(e2, self.tau2), self.tau2)
        cost = np.einsum("qp,qp->q", self.Wm[c], rho)
        start = 0
        for blk, k in zip(self.sym.blocks, ks):
            n = len(blk["cands"]) * k
            cb = cost[start:start + n].reshape(-1, k)
            j = np.argmin(cb, axis=1)
            best = cb[np.arange(len(cb)), j]
            m = blk["cands"]
            better = best < cand_cost[m] - np.maximum(1e-9 * cand_cost[m], _COST_EPS)
            if np.any(better):
                if not switched.any():
                    S = S.copy()
                pos = start + np.arange(len(cb)) * k + j
                S[m[better]] = Sq[pos[better]]
                switched[m[better]] = True
            start += n
        return S, switched

    def nearest_symmetry_index(self, S):
        out = np.zeros(self.M, dtype=np.int64)
        for blk in self.sym.blocks:
            c = blk["cands"]
            d = np.sum((blk["S"][None, :, :3, :] - S[c][:, None, :3, :]) ** 2, axis=(2, 3))
            out[c] = np.argmin(d, axis=1)
        return out

    def apply_step(self, T_world_cam, T_world_obj, S, delta):
        """Retract an LM step: cameras and objects T <- T [Exp(w), rho], angles S <- C(phi) S.
        One batched Rodrigues for all rotations. Returns new (T_world_cam, T_world_obj, S); S
        is returned as is when no angle is free."""
        nf, N, F = self.n_free_cams, self.N, len(self.phi_idx)
        xi = delta[:self.n_pose].reshape(-1, 6)
        w = xi[:, 3:]
        if F:
            w = np.concatenate([w, self.axis_m[self.phi_idx] * delta[self.n_pose:, None]])
        R = _exp_so3(w)
        T = np.concatenate([T_world_cam[~self.fixed], T_world_obj])
        Tn = T.copy()
        Tn[:, :3, :3] = T[:, :3, :3] @ R[:nf + N]
        Tn[:, :3, 3] += (T[:, :3, :3] @ xi[:, :3, None])[..., 0]
        Twc = T_world_cam.copy()
        Twc[~self.fixed] = Tn[:nf]
        if not F:
            return Twc, Tn[nf:], S
        f = self.phi_idx
        Rp = R[nf + N:]
        C = np.zeros((F, 4, 4))
        C[:, 3, 3] = 1.0
        C[:, :3, :3] = Rp
        o = self.off_m[f]
        C[:, :3, 3] = o - (Rp @ o[..., None])[..., 0]
        S = S.copy()
        S[f] = C @ S[f]
        return Twc, Tn[nf:], S

    # ---- linearisation ---------------------------------------------------------------------
    @staticmethod
    def _dproj(K, u, z):
        """d pixel / d camera point (B, 2, 3, P) at pixels u (B, 2, P) with depths z (B, P)."""
        D = K[:, :2, :, None] - u[:, :, None, :] * K[:, None, 2, :, None]
        return D / z[:, None, None, :]

    def jacobian(self, est, meas):
        """J (M, 13, 2, P): residual derivatives w.r.t. [camera xi (rho, w), object xi (rho, w), phi]."""
        M, P = self.M, self.P
        D = self._dproj(self.Km, est["u"], est["z"])  # (M, 2, 3, P)
        p = est["p"][:, None]  # (M, 1, 3, P)
        J = np.empty((M, 13, 2, P))
        J[:, 0:3] = -np.swapaxes(D, 1, 2)
        # D [p]x: rows d_k x p
        J[:, 3] = D[:, :, 1] * p[:, :, 2] - D[:, :, 2] * p[:, :, 1]
        J[:, 4] = D[:, :, 2] * p[:, :, 0] - D[:, :, 0] * p[:, :, 2]
        J[:, 5] = D[:, :, 0] * p[:, :, 1] - D[:, :, 1] * p[:, :, 0]
        # D R: (R^T @ D) per row k
        DR = np.swapaxes(est["A"][:, :3, :3], 1, 2)[:, None] @ D  # (M, 2, 3, P)
        x = self.Xm[:, None]
        J[:, 6:9] = np.swapaxes(DR, 1, 2)
        # -D R [x]x: rows x cross (D R)_k
        J[:, 9] = x[:, :, 1] * DR[:, :, 2] - x[:, :, 2] * DR[:, :, 1]
        J[:, 10] = x[:, :, 2] * DR[:, :, 0] - x[:, :, 0] * DR[:, :, 2]
        J[:, 11] = x[:, :, 0] * DR[:, :, 1] - x[:, :, 1] * DR[:, :, 0]
        J[:, 12] = 0.0
        f = self.phi_idx
        if len(f):
            Dm = self._dproj(self.Km[f], meas["u"][f], meas["z"][f])  # (F, 2, 3, P)
            a = self.axis_m[f][:, :, None]
            v = meas["SX"][f] - self.off_m[f][:, :, None]
            dy = np.stack([a[:, 1] * v[:, 2] - a[:, 2] * v[:, 1],
                           a[:, 2] * v[:, 0] - a[:, 0] * v[:, 2],
                           a[:, 0] * v[:, 1] - a[:, 1] * v[:, 0]], 1)  # d(S x)/d phi, model frame
            dy = self.T_cam_cand[f][:, :3, :3] @ dy  # in the camera frame
            J[f, 12] = -np.sum(Dm * dy[:, None], axis=2)
        return J

    def normal_equations(self, est, meas, J):
        """H = sum w J^T J, g = sum w J^T r (dense, over the free unknowns)."""
        rho, e2, ok = self.point_costs(est, meas)
        w = self.Wm * (ok & (e2 < self.tau2))  # IRLS weights of the truncated quadratic
        r = (est["u"] - meas["u"]).reshape(self.M, -1, 1)
        Jf = J.reshape(self.M, 13, -1)
        JW = (J * w[:, None, None, :]).reshape(self.M, 13, -1)
        Hm = JW @ np.swapaxes(Jf, 1, 2)
        gm = (JW @ r)[..., 0]
        n1 = self.n + 1
        H = np.bincount(self.lin_idx, weights=Hm.ravel(), minlength=n1 * n1).reshape(n1, n1)[:-1, :-1]
        g = np.bincount(self.block_idx.ravel(), weights=gm.ravel(), minlength=n1)[:-1]
        return H, g


def bundle_adjust(T_world_cam: np.ndarray, T_world_obj: np.ndarray, cand_view: np.ndarray, cand_obj: np.ndarray,
                  T_cam_cand: np.ndarray, K: np.ndarray, obj_label: np.ndarray, geometry: Sequence[LabelGeometry],
                  *, iterations: int = DEFAULT_ITERATIONS, loss_threshold_px: float = DEFAULT_LOSS_THRESHOLD_PX,
                  fixed_views=0, symmetries: np.ndarray | None = None, reselect_symmetries: bool = True,
                  symmetry_shortlist: int | None = DEFAULT_SHORTLIST, continuous_symmetries: bool = True,
                  ftol: float = 1e-6, anneal_max_factor: float = 8.0, z_min_mm: float = 1.0) -> BundleResult:
    """Jointly refine cameras and objects by Levenberg-Marquardt on the truncated reprojection loss.

    T_world_cam (V, 4, 4) and T_world_obj (N, 4, 4): initial poses (mm); cand_view (M,),
    cand_obj (M,): each candidate's view and object indices; T_cam_cand (M, 4, 4) mm: the
    single-view candidate poses (the measurements); K: (V, 3, 3) or one (3, 3); obj_label (N,):
    index of each object's :class:`LabelGeometry` in ``geometry``.

    ``fixed_views``: index or indices of views held fixed (the gauge; "all" for known
    cameras: only objects move; None: nothing fixed -- gauge-free, damping keeps it solvable).
    ``symmetries``: optional initial S per candidate (M, 4, 4), identity otherwise (the first
    re-selection improves on them). ``symmetry_shortlist``: how many symmetries per candidate
    (best by the 3D proxy) get the exact 2D cost at each re-selection; None: all of them.
    ``continuous_symmetries``: refine the angle about a label's single continuous axis.
    ``iterations`` bounds the LM iterations (linear solves); ``ftol`` stops when an accepted
    step lowers the cost by less than this fraction. ``anneal_max_factor``: with a poor start
    the truncation threshold begins at up to this multiple of ``loss_threshold_px`` and is
    halved down to it (1: no annealing). See the module docstring for the cost.
    """
    t0 = time.perf_counter()
    Twc = np.array(T_world_cam, dtype=np.float64).reshape(-1, 4, 4)
    Two = np.array(T_world_obj, dtype=np.float64).reshape(-1, 4, 4)
    if not (np.isfinite(Twc).all() and np.isfinite(Two).all()):
        raise ValueError("initial poses must be finite")
    pr = _Problem(len(Twc), len(Two), cand_view, cand_obj, T_cam_cand, K, obj_label, geometry, fixed_views,
                  loss_threshold_px, z_min_mm, continuous_symmetries)
    M = pr.M
    S = np.tile(np.eye(4), (M, 1, 1)) if symmetries is None else np.array(symmetries, dtype=np.float64).reshape(M, 4, 4)

    def errors(est, meas):
        d = est["u"] - meas["u"]
        e = np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2)
        ok = est["valid"] & meas["valid"] & pr.mask
        n_ok = ok.sum(1)
        ce = np.where(n_ok > 0, np.sum(np.where(ok, e, 0.0), 1) / np.maximum(n_ok, 1), np.nan)
        inl = np.sum(ok & (e < tau), 1) / np.maximum(pr.mask.sum(1), 1)
        cnt = np.bincount(pr.cand_view, weights=np.isfinite(ce), minlength=pr.V)
        ve = np.bincount(pr.cand_view, weights=np.nan_to_num(ce), minlength=pr.V)
        ve = np.where(cnt > 0, ve / np.maximum(cnt, 1), np.nan)
        return ce, inl, ve, e[ok]

    tau = float(loss_threshold_px)
    est = pr.estimate(Twc, Two)
    meas = pr.measure(S)
    # Threshold schedule: when the initial reprojection errors exceed tau (a poor start), begin at
    # twice the largest per-view (lower) median of the candidates' mean point errors (at most
    # ``anneal_max_factor`` tau) and halve it stage by stage down to tau, so that points are not
    # cut off before they can pull. Per-view medians: a camera placed poorly moves all of its
    # view's candidates (it needs the schedule), a gross outlier candidate only itself (it must
    # neither start the threshold high nor pull the scene while the threshold is high).
    schedule = [tau]
    if anneal_max_factor > 1.0:
        ce0 = errors(est, meas)[0]
        ok = np.isfinite(ce0)
        t = min(2.0 * _worst_view_median(ce0[ok], pr.cand_view[ok]), anneal_max_factor * tau) if ok.any() else tau
        while t > 1.5 * tau:
            schedule.insert(-1, t)
            t /= 2.0
    pr.tau2 = schedule[0] ** 2
    cc = pr.cand_costs(est, meas)
    if reselect_symmetries:
        S, sw = pr.reselect(est, S, cc, symmetry_shortlist)
        if sw.any():
            meas = pr.measure(S)
            cc = pr.cand_costs(est, meas)
    # continuous angles: free for every candidate of a continuous label but one reference per
    # object (its best-fitting candidate), which fixes the object's spin about its own axis
    if pr.cont.any():
        free = pr.cont.copy()
        ref_order = np.lexsort((np.arange(M), cc, pr.cand_obj))
        first = np.ones(M, dtype=bool)
        first[1:] = pr.cand_obj[ref_order[1:]] != pr.cand_obj[ref_order[:-1]]
        free[ref_order[first]] = False
        pr.set_phi_columns(free)

    init_ce, _, init_ve, _ = errors(est, meas)
    pr.tau2 = tau ** 2
    initial_cost = float(pr.cand_costs(est, meas).sum())
    history = []
    lam, nu = 1e-4, 2.0
    it = 0
    converged = False
    rounds = 0
    for stage, tau_k in enumerate(schedule):
        last = stage == len(schedule) - 1
        pr.tau2 = tau_k ** 2
        cc = pr.cand_costs(est, meas)
        F = float(cc.sum())
        ftol_k = ftol if last else 1e-3
        converged = False
        while it < iterations and rounds <= iterations:  # rounds: re-selection may loop without a solve
            rounds += 1
            history.append(F)
            stop = F <= _COST_EPS
            F_start = F
            if not stop:
                J = pr.jacobian(est, meas)
                H, g = pr.normal_equations(est, meas, J)
                dg = np.diag(H).copy()
                dg = np.maximum(dg, 1e-12 * max(dg.max(), 1e-300))
                accepted = False
                while it < iterations:
                    it += 1
                    A = H.copy()
                    A[np.diag_indices_from(A)] += lam * dg
                    try:
                        delta = -np.linalg.solve(A, g)
                    except np.linalg.LinAlgError:
                        lam, nu = lam * nu, nu * 2.0
                        continue
                    pred = -(2.0 * g @ delta + delta @ H @ delta)
                    Twc_n, Two_n, S_n = pr.apply_step(Twc, Two, S, delta)
                    est_n = pr.estimate(Twc_n, Two_n)
                    meas_n = pr.measure(S_n) if S_n is not S else meas
                    cc_n = pr.cand_costs(est_n, meas_n)
                    F_n = float(cc_n.sum())
                    if F_n < F:
                        gain = (F - F_n) / pred if pred > 0 else 1.0
                        lam *= max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
                        nu = 2.0
                        stop = np.max(np.abs(delta)) < 1e-12 or (F - F_n) <= ftol_k * F or F_n <= _COST_EPS
                        Twc, Two, S, est, meas, cc, F = Twc_n, Two_n, S_n, est_n, meas_n, cc_n, F_n
                        accepted = True
                        break
                    lam, nu = lam * nu, nu * 2.0
                    if lam > 1e16:
                        break
                if not accepted:
                    if it >= iterations and lam <= 1e16:
                        break  # out of iterations
                    stop = True  # no step lowers the cost: a (local) minimum
                    lam, nu = 1e-4, 2.0
            # Symmetry re-selection: while the poses still move (the last step lowered the cost
            # by more than 0.1 %), and always once more when the optimisation has stopped
            # (continue if that switches any candidate: the result is stable under re-selection).
            switched = False
            if reselect_symmetries and (stop or F < F_start * (1.0 - 1e-3)):
                S, sw = pr.reselect(est, S, cc, symmetry_shortlist)
                if sw.any():
                    switched = True
                    meas = pr.measure(S)
                    cc = pr.cand_costs(est, meas)
                    F = float(cc.sum())
            if stop and not switched:
                converged = True
                break
    history.append(F)
    ce, inl, ve, _ = errors(est, meas)
    return BundleResult(
        T_world_cam=Twc, T_world_obj=Two, symmetries=S, symmetry_index=pr.nearest_symmetry_index(S),
        cost_history=np.array(history), iterations=it, converged=bool(converged), initial_cost=initial_cost,
        final_cost=F, cand_error_px=ce, initial_cand_error_px=init_ce, inlier_fraction=inl, view_error_px=ve,
        initial_view_error_px=init_ve, time_s=time.perf_counter() - t0,
    )
