"""Object candidate matching across views (CosyPose stage 2, Sec. 3.2): pure, batched numpy.

Input of :func:`match_group`: the object candidates of one group of views (view index, object
label, pose ``T_cam_obj`` in mm) and a :class:`LabelTable` with, per label, a few model points
and the symmetry set S(l). Output (:class:`GroupResult`): for every pair of views its best
relative camera pose ``T_cam_a_cam_b`` and inlier count, the accepted candidate associations,
and for every candidate the physical object it belongs to (-1: discarded).
:func:`match_groups` matches many groups in one batch (same results, less overhead).

The algorithm, as in the paper
------------------------------
A. 2-view candidate pair selection, for every pair of views (a, b), a < b:

* Candidate pairs ``(alpha, beta)``: one candidate in a, one in b, same label.
* Hypotheses (RANSAC): a first pair ``(alpha, beta)`` fixes T_ab up to the symmetries of its
  object, a second pair ``(gamma, delta)`` picks the symmetry::

      T_ab = T_a_alpha S* inv(T_b_beta),
      S*   = argmin_S D_l(T_a_gamma, T_a_alpha S inv(T_b_beta) T_b_delta)

* Score: for every candidate of a, the same-label candidate of b closest under the hypothesis
  in symmetric distance ``D_l(T_a_alpha, T_ab T_b_beta)``; an inlier when below
  ``threshold_mm`` (2 cm). The hypothesis with most inliers wins; a view pair is *linked*
  with >= ``min_inliers`` (3) inliers.

B. Scene-level matching: the associations of linked view pairs are the edges of a graph over
candidates; each connected component is one physical object; candidates without an edge are
discarded.

Which hypotheses (at most ``ransac_iterations`` per view pair)
---------------------------------------------------------------
* A first pair whose object has no symmetry gives one hypothesis whatever the second pair:
  every such first pair is used (exhaustive; each counts as one iteration).
* First pairs of symmetric objects are combined with second pairs (any label, other
  candidates). When a view pair has at most 128 such ordered combinations (or at most the
  remaining budget with ``ransac_confidence`` = 1) they are all enumerated (deterministic,
  exhaustive). Otherwise combinations are drawn at random (with replacement) in rounds of 128,
  128, 256, ... until the budget is spent or, adaptive RANSAC, until enough were drawn to
  have drawn two inlier pairs with probability ``ransac_confidence`` (0.99):
  ``n >= log(1 - confidence) / log(1 - w^2)`` with ``w`` = best inlier count / candidate
  pairs. Each view pair draws from its own generator, seeded by (group seed, view-pair
  index), so results do not depend on which groups are matched together.
* ``S*`` of a combination: the symmetries S that bring the second object's centre within
  ``threshold + r_l2`` of its partner are the only ones under which the second pair can be an
  inlier (centre bound below). With one such S, it is S*; with several, D_l is computed for
  the ``sym_candidates`` (4) of them with the closest centres and the smallest wins (the one
  approximation: a farther S is not tried); with none, or when the second pair is no inlier
  even under S*, the combination gives no hypothesis (its own sample does not support it).
* Duplicate hypotheses (same first pair and S*) are scored once.
* Ties: hypotheses are scored in decreasing order of an upper bound of their inlier count
  (branch and bound, below); a later hypothesis must have strictly more inliers, or as many
  and a smaller sum of inlier distances when scored in the same batch.

Exactness-preserving shortcuts (same counts as brute force over the same hypotheses)
------------------------------------------------------------------------------------
* D_l is evaluated on the relative transform ``M = inv(T1) T2`` (model frame):
  ``D_l(T1, T2) = min_S mean_x ||S x - M x||`` with ``S x`` precomputed per label, all
  symmetries of a label at once with one matrix product per label.
* Lower bounds prune: by the triangle inequality (Jensen), ``mean_x ||S x - M x|| >=
  sum_k w_k ||S c_k - M c_k||`` for any partition of the points into clusters with centroids
  ``c_k`` and weights ``w_k``; with one cluster this is the distance between the two object
  centres minus ``r_l = max_S ||S c - c||``. Candidate pairs whose centres are farther apart
  than ``threshold + r_l`` are never inliers, so D_l is computed only for the others; for big
  symmetry sets (continuous symmetries: 64 steps or more) D_l is computed for the few
  symmetries with the smallest cluster bounds and certified by the next bound (else all).
  Above the threshold, D_l values are only known to be above it.
* Second pairs: the distance between the two objects must agree in both views
  (``|d_a(alpha, gamma) - d_b(beta, delta)| <= threshold + r_l1 + r_l2``), and for objects with
  a symmetry axis, the height along and the distance to the axis of the second object's centre
  (invariant under the symmetries) must agree too; other combinations cannot make their
  second pair an inlier.
* Branch and bound: the number of candidates of a with a same-label centre within reach is an
  upper bound of a hypothesis' inlier count; hypotheses are scored exactly in decreasing order
  of the bound (1, 2, 4... per view pair) until no bound exceeds the best exact count.

Additions to the paper (documented choices)
-------------------------------------------
* One-to-one associations: each candidate of a keeps its closest inlier in b; when several
  candidates of a claim the same candidate of b, the closest one wins. ``n_inliers`` counts
  these associations.
* ``refit`` (on by default): the pose of every view pair with >= ``min_inliers`` associations
  is the least-squares fit on its final inliers (``_Group.fit``): the rotation that best aligns,
  in one weighted Wahba problem, the axes of the associations' relative rotations (objects
  without a continuous symmetry, under the symmetry each association chose), the symmetry axes
  of the others, and the layout of the object centres, weighted by the rotation spread the pair
  shows and by the centres' noise (the group's estimated noise once known); an association whose
  rotation is more than ``ROT_OUTLIER_DEG`` (45) from the pair's current pose or the mean of the
  relative rotations (whichever more agree with) gives only its centres; the translation from
  the centres. The associations are then recomputed under the fit and the fit repeated
  until they do not change, so an association that disagrees with the fit beyond the view
  pair's threshold (which follows the group's noise) is not an inlier, and a pair left with
  fewer than ``min_inliers`` is not a RANSAC link. ``GroupResult.fit_residual_mm``: the RMS of
  D_l over each pair's final associations. The paper keeps the hypothesis of one candidate pair;
  the fit averages the candidates' noise (simulated 6 x 8 table scenes, 3 % depth / 5 deg + 5 %
  gross, 18 runs: 2.6 % of the linked pairs off by more than 10 deg before, none with the fit).
* Conflicts in the graph: edges are added in increasing order of symmetric distance
  (Kruskal-like union-find); an edge that would put two candidates of one view into one
  object is dropped. Without conflicts this is exactly the connected components.
* Known cameras: T_ab comes from the given camera poses, there is no RANSAC, and every inlier
  association is an edge (``min_inliers`` guards against wrong camera hypotheses; there are
  none).

For real data (issue 16; all off with ``threshold_rel = adaptive_k = 0``, ``weak_links`` False)
----------------------------------------------------------------------------------------------
* An inlier threshold that follows the candidates' noise. A fixed 2 cm fails when the error
  grows with distance (an RGB method's depth error is ~1-5 % of it: 10-50 mm at 1 m). Each view
  pair gets the ceiling ``max(threshold_mm, threshold_rel x z)``, z = the mean over its two views
  of the median distance of their candidates' centres to the camera; RANSAC, the associations
  and the refit run with it. Then, with ``adaptive_k`` > 0, the group's noise is estimated from
  its own inliers: s = median over the associations of view pairs with >= ``min_inliers`` of
  them of D_l / distance (a robust relative scale), and the final threshold of each view pair
  is ``clip(adaptive_k x s x z, threshold_mm, ceiling)`` (the ceiling where fewer than 3
  associations give s); associations and refit are redone under it. Exact or clean candidates
  get threshold_mm back; :class:`GroupResult` carries the threshold of every view pair and s.
* Weak links (``weak_links``): a view pair with 1-2 associations is linked when RANSAC links
  leave its views apart and the associations determine the relative pose -- two objects (the
  hypothesis of one verified by the other), or one object without any symmetry -- and no label
  seen exactly once in both views is left unassociated (that would contradict the pose). See
  :meth:`_Group.weak_links`; ``GroupResult.link_kind`` says how each pair was linked.

Label groups (issue 19, beyond the paper; off with the default LabelTable)
-------------------------------------------------------------------------
``LabelTable.compat[a, b]``: candidates of labels a != b may be associated (look-alikes that a
detector confuses; see :mod:`cosy_cli.multiview.label_groups`). A candidate pair (i in view a,
j in view b) of labels (l_i, l_j) is measured as a pair of label l_i: j's pose is turned into a
pose of l_i's model, ``T_j inv(model_align[l_i, l_j])`` (the identity where the models' frames
agree), then D_{l_i} with l_i's points and symmetries. By default (``cross_label_hypotheses``
False) the view pairs' poses, thresholds and links are those of the same-label matching (exactly
the paper's), and the grouped labels' pairs only add associations of the linked pairs under those
poses; with True they also make and score hypotheses. :class:`GroupResult` carries each
candidate's geometric fit with its object (``cand_fit``) for the label vote. Without groups the
results are bit-identical to same-label matching.

Several hypotheses per detection (beyond the paper; off without ``det``)
----------------------------------------------------------------------
A single-view method may give each detection a few ranked pose hypotheses (``cosy estimate
--hypotheses``): each is a candidate of its own, and the hypotheses of one detection are mutually
exclusive. RANSAC counts inliers per detection (distinct detections of view a), second pairs
must be other detections, an association pairs at most one hypothesis of a detection with one of
another (one-to-one over detections), and the graph keeps at most one hypothesis per detection
in at most one object (an edge that would place a second hypothesis of a detection, or the same
detection in a second object, is dropped; edges in increasing distance, so the hypothesis that
agrees best with the other views wins). A ``prior`` per candidate (the stage gives
``hypothesis_penalty`` x rank) is added, in units of the view pair's threshold, to D / threshold
when associations and edges are chosen: a runner-up must agree clearly better than the first.
Measured on real LM-O (lmo_dev, cosy's RGB candidates, 2-3 close views): with 5 hypotheses
more detections are matched (456 vs 221) but the hypotheses chosen have a right rotation (< 15
deg) no more often than rank 0 (28 % vs 30 % of the matched ones; choosing by orientation
agreement alone: 23 %): wrong hypotheses of close views agree with each other about as well as
right ones, so held-out multi-view AR does not rise (0.318 -> 0.317). View distances (threshold) and the weak-link label
counts use one hypothesis per detection. With one hypothesis per detection: bit-identical.

Units: mm. Poses are 4x4 ``T_a_b`` matrices (maps frame b into frame a).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.poses import invert
from ..geometry.sampling import farthest_point_indices


# --------------------------------------------------------------------------------------------
# parameters, per-label geometry
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MatchParams:
    threshold_mm: float = 20.0  # inlier threshold C on the symmetric distance D_l (paper: 2 cm)
    ransac_iterations: int = 2000  # max (first, second) pair combinations per view pair
    min_inliers: int = 3  # a view pair is linked with at least this many associations
    refit: bool = True  # least-squares refit of the winning T_ab on its inliers
    sym_candidates: int = 4  # symmetries S tried with the full D_l when choosing S* of a hypothesis
    ransac_confidence: float = 0.99  # stop drawing once two inlier pairs were drawn with this probability
    # inlier threshold that follows the candidates' noise (0, 0: the fixed threshold_mm)
    threshold_rel: float = 0.0  # ceiling: max(threshold_mm, threshold_rel x distance of the objects to the cameras)
    adaptive_k: float = 0.0  # final: clip(adaptive_k x robust residual scale of the group, threshold_mm, ceiling)
    # views linked by 1-2 objects (fewer than min_inliers), with stricter checks (see weak links)
    weak_links: bool = False
    # label groups (LabelTable.compat): False = view-pair hypotheses, thresholds and links from
    # same-label pairs as in the paper, pairs of grouped labels only add associations under them;
    # True = pairs of grouped labels also make and score hypotheses
    cross_label_hypotheses: bool = False
    # associations: a pair of candidates whose relative rotation disagrees with the view pair's by
    # more than this is no inlier (objects without a continuous symmetry; 180: off, the default)
    max_rotation_deg: float = 180.0


class LabelTable:
    """Per-label geometry for D_l: model points, symmetry sets, bounds.

    ``points[l]``: (N, 3) mm, the same N for every label (the paper's D_l is a mean over the
    model's points; a few dozen well-spread points are enough to rank hypotheses).
    ``symmetries[l]``: (K_l, 4, 4), identity first, continuous symmetries discretised.
    ``continuous[l]``: the object has a continuous symmetry (default: K_l >= 64).
    ``axes[l]``: None or (axis (3,), point on the axis (3,) mm) of its continuous symmetry,
    for the invariant-based bound on second pairs (used only if every symmetry of the set maps
    that axis onto itself).
    """

    def __init__(self, obj_ids, points, symmetries, continuous=None, axes=None,
                 n_clusters: int = 8, compat=None, model_align=None):
        self.obj_ids = np.asarray(obj_ids, dtype=np.int64)
        L = len(self.obj_ids)
        if L == 0:
            raise ValueError("LabelTable needs at least one label")
        # label groups (beyond the paper): compat[a, b] when candidates of labels a, b may be
        # associated (the diagonal: same label); model_align[a, b] = T_a_b maps model b's frame
        # into model a's (see cosy_cli.multiview.label_groups)
        self.compat = np.eye(L, dtype=bool) if compat is None else np.asarray(compat, dtype=bool).reshape(L, L)
        self.compat = self.compat | self.compat.T | np.eye(L, dtype=bool)
        self.model_align = np.tile(np.eye(4), (L, L, 1, 1)) if model_align is None else \
            np.asarray(model_align, dtype=np.float64).reshape(L, L, 4, 4)
        self.cross = bool((self.compat & ~np.eye(L, dtype=bool)).any())
        X = np.stack([np.asarray(p, dtype=np.float64) for p in points])  # (L, N, 3)
        if X.ndim != 3 or X.shape[0] != L or X.shape[2] != 3:
            raise ValueError(f"points: expected {L} arrays of shape (N, 3), got {X.shape}")
        self.points = X
        self.n_sym = np.array([len(s) for s in symmetries], dtype=np.int64)
        # labels with a continuous symmetry (their rotation about the axis is not observable)
        self.continuous = (self.n_sym >= 64) if continuous is None else np.asarray(continuous, dtype=bool)
        Kmax = int(self.n_sym.max())
        S = np.empty((L, Kmax, 4, 4))
        for l, s in enumerate(symmetries):
            s = np.asarray(s, dtype=np.float64)
            S[l, :len(s)] = s
            S[l, len(s):] = s[0]  # padding repeats the identity: mins are unaffected
        self.S = S
        self.XS = np.einsum("lkij,lnj->lkni", S[..., :3, :3], X) + S[:, :, None, :3, 3]  # (L, K, N, 3)
        self.centers = X.mean(axis=1)  # (L, 3)
        Sc = np.einsum("lkij,lj->lki", S[..., :3, :3], self.centers) + S[..., :3, 3]
        self.sym_radius = np.linalg.norm(Sc - self.centers[:, None], axis=-1).max(axis=1)  # (L,) mm
        # Partition of each label's points into clusters (farthest-point seeds + nearest seed):
        # the cluster centroids give the lower bound sum_k w_k ||S c_k - M c_k|| of D_S.
        nc = max(1, min(n_clusters, X.shape[1]))
        C = np.empty((L, nc, 3))
        W = np.empty((L, nc))
        for l in range(L):
            seeds = farthest_point_indices(X[l], nc)
            assign = np.argmin(np.linalg.norm(X[l][:, None] - X[l][seeds][None], axis=-1), axis=1)
            for k in range(nc):  # a cluster with no point (coincident points): weight 0, centre its seed, not NaN
                members = assign == k
                C[l, k] = X[l][members].mean(axis=0) if members.any() else X[l][seeds[k]]
                W[l, k] = np.mean(members)
        self.cluster_centers, self.cluster_w = C, W
        # symmetry axes (continuous symmetries): direction, a point, and whether some symmetry
        # reverses the axis; used only where every symmetry maps the axis onto itself
        self.has_axis = np.zeros(L, dtype=bool)
        self.axis_dir = np.zeros((L, 3))
        self.axis_dir[:, 2] = 1.0
        self.axis_off = np.zeros((L, 3))
        self.axis_flip = np.zeros(L, dtype=bool)
        self.axis_steps: list = [None] * L  # (e1, e2, [(F, indices by step)]) when the set is regular
        for l in range(L):
            ax = None if axes is None else axes[l]
            if ax is None:
                continue
            a = np.asarray(ax[0], dtype=np.float64)
            a = a / np.linalg.norm(a)
            o = np.asarray(ax[1], dtype=np.float64)
            k = self.n_sym[l]
            Ra = S[l, :k, :3, :3] @ a
            sgn = Ra @ a
            fixes = np.all(np.abs(np.abs(sgn) - 1) < 1e-6) and np.allclose(S[l, :k, :3, :3] @ o + S[l, :k, :3, 3], o,
                                                                           atol=1e-6 * max(1.0, np.abs(X[l]).max()))
            if fixes:
                self.has_axis[l] = True
                self.axis_dir[l], self.axis_off[l] = a, o
                self.axis_flip[l] = bool(np.any(sgn < 0))
                self.axis_steps[l] = _axis_steps(S[l, :k], a, o, sgn)
        self.SC = np.einsum("lkij,lcj->lkci", S[..., :3, :3], C) + S[:, :, None, :3, 3]  # (L, K, nc, 3)
        # per label, layouts for _dists: S x as (N, K_l, 3) with squared norms (N, K_l); same for
        # the cluster centroids (nc, K_l, 3)
        self.XSn = [np.ascontiguousarray(self.XS[l, :k].transpose(1, 0, 2)) for l, k in enumerate(self.n_sym)]
        self.XS2n = [np.einsum("nki,nki->nk", a, a) for a in self.XSn]
        self.SCn = [np.ascontiguousarray(self.SC[l, :k].transpose(1, 0, 2)) for l, k in enumerate(self.n_sym)]
        self.SC2n = [np.einsum("cki,cki->ck", a, a) for a in self.SCn]

    def __len__(self) -> int:
        return len(self.obj_ids)

    def index_of(self, obj_ids) -> np.ndarray:
        """Label indices of obj_ids (all must be in the table)."""
        lut = {int(o): i for i, o in enumerate(self.obj_ids)}
        return np.array([lut[int(o)] for o in np.asarray(obj_ids).reshape(-1)], dtype=np.int64)


_FULL_MAX_WORK = 256  # symmetries x rows below which D_l is computed for every symmetry directly
_GATHER_MAX = 512  # below this many rows, D_l of small symmetry sets is computed by gathering
_FIRST_ROUND = 128  # RANSAC draws of symmetric first pairs per view pair in the first round


def _axis_steps(S: np.ndarray, a: np.ndarray, o: np.ndarray, sgn: np.ndarray):
    """Structure of a symmetry set made of rotations about an axis (through o, direction a),
    possibly composed with axis-reversing elements: returns (e1, e2, parts) where e1, e2 span
    the plane normal to a and each part is (F (4, 4), idx (n,)) such that ``S[idx[k]] =
    R(2 pi k / n) F`` (R: rotation about the axis). None when the set is not of that form."""
    e1 = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    parts = []
    for flip in (False, True):
        members = np.flatnonzero((sgn < 0) == flip)
        if not len(members):
            continue
        F = S[members[0]]
        Finv = np.linalg.inv(F)
        n = len(members)
        idx = np.full(n, -1, dtype=np.int64)
        for m in members:
            Rm = (S[m] @ Finv)[:3, :3]  # a rotation about the axis
            v = Rm @ e1
            phi = np.arctan2(v @ e2, v @ e1) % (2 * np.pi)
            kf = phi / (2 * np.pi / n)
            k = int(round(kf)) % n
            if abs(kf - round(kf)) > 1e-6 or idx[k] >= 0:
                return None
            idx[k] = m
        parts.append((F, idx))
    return e1, e2, parts


# --------------------------------------------------------------------------------------------
# symmetric distance on relative transforms
# --------------------------------------------------------------------------------------------
def _norm3(v: np.ndarray) -> np.ndarray:
    """Euclidean norms over the last axis (of size 3)."""
    return np.sqrt(v[..., 0] * v[..., 0] + v[..., 1] * v[..., 1] + v[..., 2] * v[..., 2])


def _transform_many(X: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Points X (n, 3) under p transforms (R (p, 3, 3), t (p, 3)): (n, p, 3), in one matmul."""
    p = len(R)
    Y = (X @ R.transpose(2, 0, 1).reshape(3, 3 * p)).reshape(len(X), p, 3)
    Y += t
    return Y


def _dists(A: np.ndarray, A2: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """||A[n, k] - Y[n, p]|| for all (n, k, p): A (n, k, 3) with squared norms A2 (n, k), Y (n, p, 3).

    ||a - b||^2 = |a|^2 + |b|^2 - 2 a.b with one batched matmul over the n points.
    """
    G = np.matmul(A, Y.transpose(0, 2, 1))  # (n, k, p)
    G *= -2.0
    G += A2[:, :, None]
    G += (Y[..., 0] * Y[..., 0] + Y[..., 1] * Y[..., 1] + Y[..., 2] * Y[..., 2])[:, None, :]
    np.maximum(G, 0.0, out=G)
    np.sqrt(G, out=G)
    return G


def symmetric_distance_rel(table: LabelTable, lab: np.ndarray, M: np.ndarray, *, cap: float = np.inf,
                           top: int = 4, full_max: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """D_l for relative transforms ``M = inv(T1) T2`` (P, 4, 4) of labels ``lab`` (P,).

    Returns (D (P,) mm, index of the minimising symmetry (P,)): D = min_S mean_x ||S x - M x||
    = D_l(T1, T2), exact over the discretised symmetry set (see the module docstring) wherever
    it is below ``cap``; where the true D_l >= ``cap`` the value returned is only known to be
    >= ``cap`` (a lower bound, or an upper bound's evaluation), which is all an inlier test
    with threshold ``cap`` needs.
    """
    lab = np.asarray(lab, dtype=np.int64)
    P = len(lab)
    D = np.empty(P)
    s_out = np.zeros(P, dtype=np.int64)
    if P == 0:
        return D, s_out
    K = table.n_sym[lab]
    small = K <= full_max
    n_small = int(small.sum())
    if 0 < n_small <= _GATHER_MAX:  # few rows: all small-set labels at once (padded with the identity)
        idx = np.flatnonzero(small) if n_small < P else np.arange(P)
        l = lab[idx]
        ks = int(K[idx].max())
        Y = np.matmul(table.points[l], np.swapaxes(M[idx, :3, :3], -1, -2)) + M[idx, None, :3, 3]  # (p, N, 3)
        d = _norm3(table.XS[l, :ks] - Y[:, None]).mean(-1)  # (p, ks)
        s0 = d.argmin(1)
        D[idx], s_out[idx] = d[np.arange(len(idx)), s0], s0
        labels = np.unique(lab[~small])
    else:
        labels = np.unique(lab)
    for l in labels:
        idx = np.flatnonzero(lab == l) if len(labels) > 1 or n_small else np.arange(P)
        k = int(table.n_sym[l])
        R, t = M[idx, :3, :3], M[idx, :3, 3]
        ar = np.arange(len(idx))
        Y = _transform_many(table.points[l], R, t)  # M x: (N, p, 3)
        if k <= full_max or k * len(idx) <= _FULL_MAX_WORK:  # every symmetry: few of them, or few rows
            d = _dists(table.XSn[l], table.XS2n[l], Y).mean(axis=0)  # (k, p)
            s0 = d.argmin(0)
            D[idx], s_out[idx] = d[s0, ar], s0
            continue
        # cluster lower bounds of every symmetry, full D for the `top` most promising ones,
        # certified by the next bound (else all symmetries)
        Yc = _transform_many(table.cluster_centers[l], R, t)  # (nc, p, 3)
        lb = np.tensordot(table.cluster_w[l], _dists(table.SCn[l], table.SC2n[l], Yc), axes=1).T  # (p, k)
        s0 = lb.argmin(1)
        dmin, smin = lb[ar, s0], s0  # rows whose best bound is >= cap keep it (D >= cap)
        go = np.flatnonzero(dmin < cap)
        if len(go):
            tt = min(top, k - 1)
            lbg = lb[go]
            gr = np.arange(len(go))
            part = np.argpartition(lbg, tt, axis=1)[:, :tt + 1]
            part = part[gr[:, None], np.argsort(lbg[gr[:, None], part], axis=1)]
            cand, bound = part[:, :tt], lbg[gr, part[:, tt]]
            Yg = Y[:, go].transpose(1, 0, 2)  # (g, N, 3)
            d = _norm3(table.XS[l][cand] - Yg[:, None]).mean(-1)  # (g, tt)
            j = d.argmin(1)
            dg, sg = d[gr, j], cand[gr, j]
            bad = np.flatnonzero((dg > bound) & (bound < cap))  # another symmetry might be closer
            if len(bad):
                dfull = _dists(table.XSn[l], table.XS2n[l], Y[:, go[bad]]).mean(axis=0)  # (k, b)
                sj = dfull.argmin(0)
                dg[bad], sg[bad] = dfull[sj, np.arange(len(bad))], sj
            dmin[go], smin[go] = dg, sg
        D[idx], s_out[idx] = dmin, smin
    return D, s_out


# --------------------------------------------------------------------------------------------
# results
# --------------------------------------------------------------------------------------------
@dataclass
class GroupResult:
    """Matching of one group. Candidate indices refer to the input order of :func:`match_group`.

    ``object_id`` (n,): physical object of each candidate (0.. in order of first member), -1 =
    discarded. ``pair_views`` (P, 2): view indices (a, b), a < b, for every pair of views;
    ``n_inliers`` (P,); ``T_ab`` (P, 4, 4) ``T_cam_a_cam_b`` in mm (identity where no hypothesis);
    ``linked`` (P,) whether the pair's associations are edges; ``n_hypotheses`` (P,) distinct
    hypotheses scored. ``edges`` (E, 2): associations (candidate in a, candidate in b) of linked
    pairs, ``edge_dist`` (E,) their D_l in mm, ``edge_pair`` (E,) view-pair index,
    ``edge_kept`` (E,) False where the conflict rule dropped the edge.
    """

    object_id: np.ndarray
    pair_views: np.ndarray
    n_inliers: np.ndarray
    T_ab: np.ndarray
    linked: np.ndarray
    n_hypotheses: np.ndarray
    edges: np.ndarray
    edge_dist: np.ndarray
    edge_pair: np.ndarray
    edge_kept: np.ndarray
    threshold_mm: np.ndarray | None = None  # (P,) the inlier threshold used for each view pair, mm
    link_kind: np.ndarray | None = None  # (P,) LINK_* code: how the pair is linked (LINK_NONE: not)
    residual_scale: float = float("nan")  # robust scale of the inlier distances / distance (NaN: not estimated)
    # (n,) geometric fit of each candidate with its object: exp(-(D / sigma)^2), D = mean D_l of its
    # kept associations, sigma = their inlier threshold (0 for discarded candidates); the
    # weight of its label in the object's vote (with its score, see label_groups.vote_labels)
    cand_fit: np.ndarray | None = None
    fit_residual_mm: np.ndarray | None = None  # (P,) RMS of D_l over the pair's final associations, mm (NaN: none)

    @property
    def n_objects(self) -> int:
        return int(self.object_id.max()) + 1 if len(self.object_id) and self.object_id.max() >= 0 else 0


LINK_NONE, LINK_RANSAC, LINK_TWO, LINK_ONE, LINK_KNOWN = 0, 1, 2, 3, 4
LINK_NAMES = {LINK_NONE: "none", LINK_RANSAC: "ransac", LINK_TWO: "two objects", LINK_ONE: "one object",
              LINK_KNOWN: "known cameras"}


FIT_ROUNDS = 4  # fit -> associations under the fit, until the associations no longer change


def _refit_pairs(g: "_Group", T_ab: np.ndarray, assoc: tuple, n_vp: np.ndarray) -> tuple[tuple, np.ndarray]:
    """The pose of every view pair with at least ``min_inliers`` associations becomes the
    least-squares fit on them (:meth:`_Group.fit`, in place in ``T_ab``), then its associations
    are those of the fit; repeated until they no longer change (at most ``FIT_ROUNDS``), so that
    each pose is the fit of its final inliers. Returns the associations and counts after it."""
    for _ in range(FIT_ROUNDS):
        vps, T_fit = g.fit(assoc, n_vp, g.sigma_t, min_n=g.params.min_inliers, T_ref=T_ab)
        if not len(vps):
            break
        a2 = g.associate_with(vps, T_fit)
        T_ab[vps] = T_fit
        keep_old = ~np.isin(assoc[4], vps)
        new = tuple(np.concatenate([x[keep_old], y]) for x, y in zip(assoc, a2))
        o = np.lexsort((new[2], new[4]))
        new = tuple(x[o] for x in new)
        same = len(new[0]) == len(assoc[0]) and np.array_equal(new[0], assoc[0]) and np.array_equal(new[1], assoc[1])
        assoc, n_vp = new, np.bincount(new[4], minlength=g.nvp)
        if same:
            break
    return assoc, n_vp


_TRIU: dict[int, tuple[np.ndarray, np.ndarray]] = {}


def _triu(n: int) -> tuple[np.ndarray, np.ndarray]:
    """np.triu_indices(n, 1), cached."""
    if n not in _TRIU:
        _TRIU[n] = np.triu_indices(n, 1)
    return _TRIU[n]


def _axis_candidates(steps, a, o, u, w):
    """For symmetries about an axis (see :func:`_axis_steps`): the distances ||S u - w|| (c, m)
    of the 4 steps nearest the angle that aligns u with w, in each part, and their indices."""
    e1, e2, parts = steps
    cds, idxs = [], []
    wo = w - o
    hw, wx, wy = wo @ a, wo @ e1, wo @ e2
    rw = np.hypot(wx, wy)
    for F, idx in parts:
        uf = u @ F[:3, :3].T + F[:3, 3] - o
        hu, ux, uy = uf @ a, uf @ e1, uf @ e2
        ru = np.hypot(ux, uy)
        n = len(idx)
        step = 2 * np.pi / n
        phi = (np.arctan2(wy, wx) - np.arctan2(uy, ux)) % (2 * np.pi)  # rotation taking u to w
        k0 = np.floor(phi / step).astype(np.int64)
        ks = (k0[:, None] + np.array([-1, 0, 1, 2])) % n  # the 4 nearest steps
        ang = ks * step - phi[:, None]
        d2 = (hu - hw)[:, None] ** 2 + ru[:, None] ** 2 + rw[:, None] ** 2 - 2 * (ru * rw)[:, None] * np.cos(ang)
        cds.append(np.sqrt(np.maximum(d2, 0.0)))
        idxs.append(idx[ks])
    return np.concatenate(cds, axis=1), np.concatenate(idxs, axis=1)


def _cat_rows(rows: list) -> tuple:
    """Concatenate row chunks (rh, rp, D, s)."""
    if not rows:
        return (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64))
    return tuple(np.concatenate(x) for x in zip(*rows))


def _ragged_arange(counts: np.ndarray) -> np.ndarray:
    """Concatenation of arange(c) for c in counts."""
    counts = np.asarray(counts, dtype=np.int64)
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    starts = np.repeat(np.cumsum(counts) - counts, counts)
    return np.arange(total, dtype=np.int64) - starts


def _median_by(values: np.ndarray, keys: np.ndarray, n: int) -> np.ndarray:
    """Median of ``values`` for each key in [0, n) (0 where a key has no value)."""
    out = np.zeros(n)
    if len(values) == 0:
        return out
    o = np.lexsort((values, keys))
    k, v = keys[o], values[o]
    starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    cnt = np.diff(np.r_[starts, len(k)])
    lo, hi = starts + (cnt - 1) // 2, starts + cnt // 2
    out[k[starts]] = 0.5 * (v[lo] + v[hi])
    return out


def _apply(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """T (n, 4, 4) applied to points p (n, 3)."""
    return np.einsum("nij,nj->ni", T[:, :3, :3], p) + T[:, :3, 3]


# --------------------------------------------------------------------------------------------
# the matcher of one group
# --------------------------------------------------------------------------------------------
class _Group:
    """Arrays of one or several groups matched together (views numbered across the groups;
    view pairs only within a group). Candidates sorted by (view, label, input index)."""

    def __init__(self, view, lab, T, group_of_view, table: LabelTable, params: MatchParams, det=None, prior=None):
        self.table, self.params = table, params
        gv = np.asarray(group_of_view, dtype=np.int64)
        self.n_views = len(gv)
        if det is None:
            order = np.lexsort((np.arange(len(view)), lab, view))
        else:  # hypotheses of a detection next to each other
            order = np.lexsort((np.arange(len(view)), det, lab, view))
        self.order = order
        self.view, self.lab, self.T = view[order], lab[order], T[order]
        self.n = len(order)
        # detection of each candidate (several hypotheses of one detection: mutually exclusive),
        # numbered 0.. in sorted order (without hypotheses: the candidate itself); primary = the
        # first hypothesis of each detection (its rank 0 when given in rank order)
        if det is None:
            self.det = np.arange(self.n, dtype=np.int64)
            self.primary = np.ones(self.n, dtype=bool)
        else:
            d = np.asarray(det, dtype=np.int64)[order]
            self.primary = np.r_[True, d[1:] != d[:-1]] if self.n else np.zeros(0, dtype=bool)
            self.det = np.cumsum(self.primary) - 1
            if self.n and len(np.unique(d)) != int(self.primary.sum()):
                raise ValueError("hypotheses of one detection must share its view and label")
        # cost of choosing each hypothesis, in units of the inlier threshold, added to D / threshold
        # when associations and graph edges are chosen (None: D alone, as the paper)
        self.prior = None if prior is None else np.asarray(prior, dtype=np.float64)[order]
        self.Tinv = invert(self.T) if self.n else np.zeros((0, 4, 4))
        self.cc = _apply(self.T, table.centers[self.lab]) if self.n else np.zeros((0, 3))  # centres in own camera
        self.r = table.sym_radius  # (L,)
        # view pairs (a < b) within each group, group-major
        starts = np.flatnonzero(np.r_[True, gv[1:] != gv[:-1]]) if len(gv) else np.zeros(0, np.int64)
        sizes = np.diff(np.r_[starts, len(gv)])
        parts = []
        for st, sz in zip(starts.tolist(), sizes.tolist()):
            a, b = _triu(sz)
            parts.append(np.stack([a + st, b + st], 1))
        self.pair_views = np.concatenate(parts) if parts else np.zeros((0, 2), np.int64)
        self.vp_group = gv[self.pair_views[:, 0]]
        self.nvp = len(self.pair_views)
        # index of view pair (a, b) = first pair of the group + row-major position in its triu
        g_first_view = np.repeat(starts, sizes)  # per view
        g_size = np.repeat(sizes, sizes)
        g_first_vp = np.repeat(np.cumsum(sizes * (sizes - 1) // 2) - sizes * (sizes - 1) // 2, sizes)

        def vp_index(a, b):
            al, bl, n = a - g_first_view[a], b - g_first_view[a], g_size[a]
            return g_first_vp[a] + al * (2 * n - al - 1) // 2 + (bl - al - 1)
        # candidate pairs: same group and label, view_i < view_j (buckets of (group, label))
        g = gv[self.view] if self.n else np.zeros(0, np.int64)
        o = np.lexsort((self.view, self.lab, g))
        key = g[o] * (len(table) + 1) + self.lab[o]
        bstart = np.flatnonzero(np.r_[True, key[1:] != key[:-1]]) if self.n else np.zeros(0, np.int64)
        bsize = np.diff(np.r_[bstart, self.n])
        pos = np.arange(self.n) - np.repeat(bstart, bsize)  # position in its bucket
        cnt = np.repeat(bsize, bsize) - 1 - pos  # partners after it in the bucket
        first = np.repeat(np.arange(self.n), cnt)
        second = first + 1 + _ragged_arange(cnt)
        pI, pJ = o[first], o[second]
        ok = self.view[pI] < self.view[pJ]
        pI, pJ = pI[ok], pJ[ok]
        if table.cross and self.n:  # label groups: pairs of compatible different labels too
            xI, xJ = self._cross_pairs(g)
            pI, pJ = np.concatenate([pI, xI]), np.concatenate([pJ, xJ])
        pvp = vp_index(self.view[pI], self.view[pJ])
        o = np.lexsort((pJ, pI, pvp))
        self.pI, self.pJ, self.pvp = pI[o], pJ[o], pvp[o]
        self.plab = self.lab[self.pI]
        # the partner's pose as a pose of the first candidate's model (T_cam_b inv(T_a_b) for
        # labels a != b of a group; the candidate's own pose otherwise), its inverse and centre
        self.pTJ, self.pTJinv, self.pccJ = self.T[self.pJ], self.Tinv[self.pJ], self.cc[self.pJ]
        self.pcross = self.lab[self.pJ] != self.plab
        if self.pcross.any():
            x = np.flatnonzero(self.pcross)
            A_ba = table.model_align[self.lab[self.pJ[x]], self.plab[x]]  # T_b_a = inv(T_a_b)
            self.pTJ[x] = self.T[self.pJ[x]] @ A_ba
            self.pTJinv[x] = invert(self.pTJ[x])
            self.pccJ[x] = _apply(self.pTJ[x], table.centers[self.plab[x]])
        self.m = np.bincount(self.pvp, minlength=self.nvp)
        self.off = np.cumsum(self.m) - self.m
        # distance of each view's objects to its camera (median over its candidates, mm) and of
        # each view pair (mean of its two views): the scale of depth errors
        self.dist = _norm3(self.cc) if self.n else np.zeros(0)
        pm = self.primary  # one distance per detection (hypotheses would weigh it several times)
        zv = _median_by(self.dist[pm], self.view[pm], self.n_views)
        self.z_vp = 0.5 * (zv[self.pair_views[:, 0]] + zv[self.pair_views[:, 1]]) if self.nvp else np.zeros(0)
        self.thr_ceiling = np.maximum(float(params.threshold_mm), float(params.threshold_rel) * self.z_vp)
        self.set_thresholds(self.thr_ceiling)
        # noise of the objects' centres (mm) for the fit: a third of the threshold until the
        # group's own noise is estimated (adaptive threshold)
        self.sigma_t = self.thr_ceiling / 3

    def _cross_pairs(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Candidate pairs (i, j) of different but compatible labels (label groups), same group,
        view_i < view_j."""
        tab = self.table
        part = (tab.compat & ~np.eye(len(tab), dtype=bool)).any(1)
        c = np.flatnonzero(part[self.lab])
        if len(c) < 2:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        o = c[np.argsort(g[c], kind="stable")]
        key = g[o]
        bstart = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        bsize = np.diff(np.r_[bstart, len(o)])
        pos = np.arange(len(o)) - np.repeat(bstart, bsize)
        cnt = np.repeat(bsize, bsize) - 1 - pos
        first = np.repeat(np.arange(len(o)), cnt)
        second = first + 1 + _ragged_arange(cnt)
        i, j = o[first], o[second]
        li, lj = self.lab[i], self.lab[j]
        ok = (li != lj) & tab.compat[li, lj] & (self.view[i] != self.view[j])
        i, j = i[ok], j[ok]
        swap = self.view[i] > self.view[j]
        return np.where(swap, j, i), np.where(swap, i, j)

    def set_thresholds(self, thr_vp: np.ndarray) -> None:
        """The inlier threshold on D_l of every view pair (nvp,) mm."""
        self.thr_vp = np.asarray(thr_vp, dtype=np.float64).reshape(self.nvp)
        self.thr_max = float(self.thr_vp.max()) if self.nvp else float(self.params.threshold_mm)

    # ---- hypotheses ------------------------------------------------------------------------
    def ransac(self, seeds):
        """Adaptive RANSAC over all view pairs at once.

        Returns (best_T (nvp, 4, 4), best_cnt (nvp,), n_hyp (nvp,), rows): per view pair the
        best hypothesis found (identity where none), its inlier count, the number of distinct
        hypotheses scored, and the evaluated rows (pair, D_l, symmetry) of the best hypotheses.
        """
        tab, p = self.table, self.params
        iters = int(p.ransac_iterations)
        pvp, plab, m, nvp = self.pvp, self.plab, self.m, self.nvp
        Ksym = tab.n_sym[plab]
        usable = m[pvp] >= 2
        # one candidate pair of an object without symmetry is a hypothesis of its own (it can
        # only make a weak link: one inlier)
        asym_p = np.flatnonzero((usable | (p.weak_links & (m[pvp] >= 1))) & (Ksym == 1))
        sym_p = np.flatnonzero(usable & (Ksym > 1))  # sorted by view pair
        n_sym = np.bincount(pvp[sym_p], minlength=nvp)
        sym_off = np.cumsum(n_sym) - n_sym
        n_asym = np.bincount(pvp[asym_p], minlength=nvp)
        budget = np.maximum(iters - n_asym, 0)  # a first pair without symmetry is one iteration
        space = n_sym * (m - 1)  # (symmetric first pair, second pair) combinations
        enum = space <= (budget if p.ransac_confidence >= 1.0 else np.minimum(budget, _FIRST_ROUND))
        best_T = np.tile(np.eye(4), (nvp, 1, 1))
        best_cnt = np.zeros(nvp, dtype=np.int64)
        best_res = np.full(nvp, np.inf)
        n_hyp = np.zeros(nvp, dtype=np.int64)
        drawn = np.zeros(nvp, dtype=np.int64)
        # round 0: every first pair without symmetry, all combinations where there are few
        p1s = sym_p[enum[pvp[sym_p]]]
        cnt = m[pvp[p1s]]
        c1 = np.repeat(p1s, cnt)
        c2 = self.off[pvp[c1]] + _ragged_arange(cnt)
        drawn[enum] = space[enum]
        size = np.where(enum, 0, np.minimum(budget, _FIRST_ROUND))
        first = True
        seen = np.zeros(0, dtype=np.int64)
        rows, gid_base = [], 0  # evaluated rows, hypothesis ids over all rounds
        best_gid = np.full(nvp, -1, dtype=np.int64)
        while True:
            vs = np.repeat(np.arange(nvp), size)
            if len(vs):
                r = self._draws(seeds, size)
                a = sym_off[vs] + np.minimum((r[0] * n_sym[vs]).astype(np.int64), n_sym[vs] - 1)
                b = self.off[vs] + np.minimum((r[1] * m[vs]).astype(np.int64), m[vs] - 1)
                c1 = np.concatenate([c1, sym_p[a]])
                c2 = np.concatenate([c2, b])
                drawn += size
            hp, hs = self._second_pairs(c1, c2) if len(c1) else (np.zeros(0, np.int64), np.zeros(0, np.int64))
            if first:
                hp = np.concatenate([asym_p, hp])
                hs = np.concatenate([np.zeros(len(asym_p), dtype=np.int64), hs])
                first = False
            Kmax = tab.S.shape[1]
            key = np.setdiff1d(np.unique(hp * Kmax + hs), seen, assume_unique=True)
            seen = np.union1d(seen, key)
            hp, hs = key // Kmax, key % Kmax
            hvp = pvp[hp]
            n_hyp += np.bincount(hvp, minlength=nvp)
            if len(hp):
                T_h = self.T[self.pI[hp]] @ tab.S[plab[hp], hs] @ self.pTJinv[hp]
                best, bc, br, ev = self.score(hvp, T_h, best_cnt, best_res)
                upd = np.flatnonzero(best >= 0)
                best_T[upd], best_cnt[upd], best_res[upd] = T_h[best[upd]], bc[upd], br[upd]
                best_gid[upd] = gid_base + best[upd]
                rows.append((ev[0] + gid_base,) + ev[1:])
                gid_base += len(hp)
            # stop when all combinations were drawn or enough were drawn to have sampled two
            # inlier pairs with the given confidence (w = inlier fraction of candidate pairs)
            w = best_cnt / np.maximum(m, 1)
            with np.errstate(divide="ignore"):
                need = np.where(w > 0, np.log1p(-p.ransac_confidence) / np.log1p(-np.minimum(w * w, 1 - 1e-12)), np.inf)
            active = ~enum & (drawn < budget) & (drawn < need)
            if not active.any():
                break
            size = np.where(active, np.minimum(drawn, budget - drawn), 0)  # doubling rounds
            c1 = c2 = np.zeros(0, dtype=np.int64)
        rh, rp, D, sy = _cat_rows(rows)
        keep = rh == best_gid[self.pvp[rp]]
        return best_T, best_cnt, n_hyp, (rp[keep], D[keep], sy[keep])

    def _draws(self, seeds, size: np.ndarray) -> np.ndarray:
        """(2, size.sum()) uniform numbers: ``size[vp]`` pairs for each view pair, from a
        generator per view pair seeded by (its group's seed, the pair's index in the group), so
        that a group's result does not depend on the other groups matched with it."""
        if not hasattr(self, "_rngs"):
            self._rngs = {}
            vp_first = np.searchsorted(self.vp_group, self.vp_group)
            self._vp_local = np.arange(self.nvp) - vp_first
        out = []
        for vp in np.flatnonzero(size).tolist():
            if vp not in self._rngs:
                gs = seeds[int(self.vp_group[vp])]
                gs = list(gs) if isinstance(gs, (list, tuple)) else [int(gs)]
                self._rngs[vp] = np.random.default_rng(gs + [int(self._vp_local[vp])])
            out.append(self._rngs[vp].random((2, int(size[vp]))))
        return np.concatenate(out, axis=1)

    def _second_pairs(self, c1: np.ndarray, c2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """S* of (first pair c1, second pair c2) combinations that can be consistent."""
        tab = self.table
        pI, pJ, plab = self.pI, self.pJ, self.plab
        al, be, ga, de = pI[c1], pJ[c1], pI[c2], pJ[c2]
        ok = (self.det[al] != self.det[ga]) & (self.det[be] != self.det[de])
        l1, l2 = plab[c1], plab[c2]
        thr = self.thr_vp[self.pvp[c1]]  # the view pair's inlier threshold, per combination
        da = _norm3(self.cc[al] - self.cc[ga])
        db = _norm3(self.pccJ[c1] - self.pccJ[c2])
        ok &= np.abs(da - db) <= thr + self.r[l1] + self.r[l2]
        c1, c2, al, be, ga, de, l1, l2, thr = (x[ok] for x in (c1, c2, al, be, ga, de, l1, l2, thr))
        if len(c1) == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        u = _apply(self.pTJinv[c1], self.pccJ[c2])  # delta's centre in beta's model frame
        w = _apply(self.Tinv[al], self.cc[ga])  # gamma's centre in alpha's model frame
        ax = tab.has_axis[l1]
        if ax.any():  # objects with a symmetry axis: height along and distance to the axis are invariant
            a, o = tab.axis_dir[l1], tab.axis_off[l1]
            hu, hw = np.einsum("ci,ci->c", u - o, a), np.einsum("ci,ci->c", w - o, a)
            ru = _norm3(u - o - hu[:, None] * a)
            rw = _norm3(w - o - hw[:, None] * a)
            dh = np.where(tab.axis_flip[l1], np.minimum(np.abs(hu - hw), np.abs(hu + hw)), np.abs(hu - hw))
            ok = ~ax | (np.hypot(dh, ru - rw) <= thr + self.r[l2])
            c1, c2, al, be, ga, de, l1, l2, u, w, thr = (x[ok] for x in (c1, c2, al, be, ga, de, l1, l2, u, w, thr))
        ns = int(self.params.sym_candidates)
        cand_s, cand_ok = [], []
        rows = []
        for l in np.unique(l1):
            idx = np.flatnonzero(l1 == l)
            k = int(tab.n_sym[l])
            steps = tab.axis_steps[l] if tab.has_axis[l] else None
            if steps is not None:  # rotations about an axis: the 4 steps nearest the aligning angle, per part
                cd, sidx = _axis_candidates(steps, tab.axis_dir[l], tab.axis_off[l], u[idx], w[idx])
            else:
                S = tab.S[l, :k]
                Su = np.matmul(u[idx][None], np.swapaxes(S[:, :3, :3], -1, -2)) + S[:, None, :3, 3]  # (k, c, 3)
                cd = _norm3(Su - w[idx][None]).T  # (c, k)
                sidx = None
            kk = cd.shape[1]
            q = min(ns, kk)
            if q < kk:
                top = np.argpartition(cd, q - 1, axis=1)[:, :q]
                top = np.take_along_axis(top, np.argsort(np.take_along_axis(cd, top, 1), axis=1, kind="stable"), 1)
            else:
                top = np.argsort(cd, axis=1, kind="stable")
            good = np.take_along_axis(cd, top, 1) <= (thr[idx] + self.r[l2[idx]])[:, None]
            if sidx is not None:
                top = np.take_along_axis(sidx, top, 1)
            if q < ns:
                top = np.pad(top, ((0, 0), (0, ns - q)))
                good = np.pad(good, ((0, 0), (0, ns - q)))
            rows.append(idx)
            cand_s.append(top)
            cand_ok.append(good)
        rows = np.concatenate(rows)
        cand_s = np.concatenate(cand_s)
        cand_ok = np.concatenate(cand_ok)
        n_ok = cand_ok.sum(1)
        # one symmetry brings the second pair within reach: it is S* whenever the second pair
        # can be an inlier at all (every other S has D_l > threshold)
        one = np.flatnonzero(n_ok == 1)
        p_one, s_one = c1[rows[one]], cand_s[one, np.argmax(cand_ok[one], axis=1)]
        multi = n_ok >= 2
        ci, cj = np.nonzero(cand_ok & multi[:, None])
        if len(ci) == 0:
            return p_one, s_one
        c = rows[ci]
        s = cand_s[ci, cj]
        A = self.Tinv[ga[c]] @ self.T[al[c]]
        B = self.pTJinv[c1[c]] @ self.pTJ[c2[c]]
        M = A @ tab.S[l1[c], s] @ B
        D, _ = symmetric_distance_rel(tab, l2[c], M, cap=self.thr_max)
        # per combination (row index c): argmin D over its candidate symmetries; a hypothesis
        # under which its own second pair is not an inlier is dropped
        o = np.lexsort((D, c))
        c, s, D = c[o], s[o], D[o]
        first = np.flatnonzero(np.r_[True, c[1:] != c[:-1]])
        first = first[D[first] < thr[c[first]]]
        return np.concatenate([p_one, c1[c[first]]]), np.concatenate([s_one, s[first]])

    # ---- scoring ---------------------------------------------------------------------------
    def expand(self, hvp: np.ndarray, T_ab: np.ndarray):
        """Candidate pairs (i in a, j in b) of every hypothesis whose centres are within reach.

        Returns (rows_h, rows_p, UB): hypothesis and pair index of each such row, in order of
        (hypothesis, i, j), and the upper bound of each hypothesis' inlier count.
        """
        H = len(hvp)
        cnt = self.m[hvp]
        hf = np.repeat(np.arange(H), cnt)
        pf = np.repeat(self.off[hvp], cnt) + _ragged_arange(cnt)
        if self.n * H <= 8 * len(hf):  # all centres under all hypotheses in one matmul, then gather
            pred = _transform_many(self.cc, T_ab[:, :3, :3], T_ab[:, :3, 3])[self.pJ[pf], hf]
            x = np.flatnonzero(self.pcross[pf])
            if len(x):  # pairs of different labels: the partner's centre as the first's model
                pred[x] = _apply(T_ab[hf[x]], self.pccJ[pf[x]])
        else:  # many groups matched together: per row
            pred = _apply(T_ab[hf], self.pccJ[pf])  # centre of j under the hypothesis
        lab = self.plab[pf]
        poss = _norm3(self.cc[self.pI[pf]] - pred) <= self.thr_vp[self.pvp[pf]] + self.r[lab]
        rh, rp = hf[poss], pf[poss]
        key = rh * max(self.n, 1) + self.det[self.pI[rp]]
        first = np.r_[True, key[1:] != key[:-1]] if len(key) else np.zeros(0, bool)
        UB = np.bincount(rh[first], minlength=H)
        return rh, rp, UB

    def evaluate(self, rh, rp, T_ab):
        """Exact D_l (and symmetry index) for rows (hypothesis rh, pair rp)."""
        M = self.Tinv[self.pI[rp]] @ T_ab[rh] @ self.pTJ[rp]
        return symmetric_distance_rel(self.table, self.plab[rp], M, cap=self.thr_max)

    def counts(self, rh, rp, D, H):
        """Inlier count and sum of inlier distances per hypothesis (distinct candidates of a)."""
        inl = np.flatnonzero(D < self.thr_vp[self.pvp[rp]])
        cnt = np.zeros(H, dtype=np.int64)
        res = np.zeros(H)
        if len(inl) == 0:
            return cnt, res
        h, i, d = rh[inl], self.pI[rp[inl]], D[inl]
        key = h * max(self.n, 1) + self.det[i]
        starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        dmin = np.minimum.reduceat(d, starts)
        cnt = np.bincount(h[starts], minlength=H)
        res = np.bincount(h[starts], weights=dmin, minlength=H)
        return cnt, res

    def score(self, hvp, T_ab, bar_cnt=None, bar_res=None, branch_and_bound: bool = True):
        """Best hypothesis per view pair among (hvp (H,), T_ab (H, 4, 4)).

        Hypotheses must beat (count, then smaller residual) ``bar_cnt``/``bar_res`` (nvp,) to be
        chosen. Returns best (nvp,) hypothesis index (-1: none better), its count and residual.
        With ``branch_and_bound``, hypotheses are scored in decreasing order of their upper bound
        (1, 2, 4... per view pair at a time) until no remaining bound exceeds the best count: the
        count is the same as scoring all of them; among hypotheses with the same count the
        earlier scored one (then smaller residual) wins.
        """
        H = len(hvp)
        best = np.full(self.nvp, -1, dtype=np.int64)
        best_cnt = np.zeros(self.nvp, dtype=np.int64) if bar_cnt is None else bar_cnt.copy()
        best_res = np.full(self.nvp, np.inf) if bar_res is None else bar_res.copy()
        ev = []  # evaluated rows: (rh, rp, D, s)
        if H == 0:
            return best, best_cnt, best_res, _cat_rows(ev)
        rh, rp, UB = self.expand(hvp, T_ab)
        if not branch_and_bound:
            D, s = self.evaluate(rh, rp, T_ab)
            cnt, res = self.counts(rh, rp, D, H)
            self._update_best(np.arange(H), hvp, cnt, res, best, best_cnt, best_res)
            return best, best_cnt, best_res, (rh, rp, D, s)
        order = np.lexsort((np.arange(H), -UB, hvp))
        vp_sorted = hvp[order]
        vp_start = np.searchsorted(vp_sorted, np.arange(self.nvp))
        rank = np.empty(H, dtype=np.int64)
        rank[order] = np.arange(H) - vp_start[vp_sorted]
        lo, chunk = 0, 1
        while True:
            open_ = (rank >= lo) & (UB > best_cnt[hvp])
            if not open_.any():
                break
            sel = open_ & (rank < lo + chunk)
            lo, chunk = lo + chunk, chunk * 2
            if not sel.any():
                continue
            rows = np.flatnonzero(sel[rh])
            D, s = self.evaluate(rh[rows], rp[rows], T_ab)
            ev.append((rh[rows], rp[rows], D, s))
            hs = np.flatnonzero(sel)
            cnt, res = self.counts(rh[rows], rp[rows], D, H)
            self._update_best(hs, hvp, cnt[hs], res[hs], best, best_cnt, best_res)
        return best, best_cnt, best_res, _cat_rows(ev)

    def rows_of(self, hvp, T_ab):
        """All rows (within reach) of the hypotheses with exact D and symmetry index."""
        rh, rp, _ = self.expand(hvp, T_ab)
        D, s = self.evaluate(rh, rp, T_ab)
        return rh, rp, D, s

    @staticmethod
    def _update_best(hs, hvp, cnt, res, best, best_cnt, best_res):
        """Fold hypotheses hs (with counts/residuals) into the per-view-pair best (in place):
        more inliers wins, then a smaller sum of inlier distances, then the earlier index."""
        keep = cnt > 0
        hs, cnt, res = hs[keep], cnt[keep], res[keep]
        if len(hs) == 0:
            return
        o = np.lexsort((hs, res, -cnt, hvp[hs]))
        hs, cnt, res = hs[o], cnt[o], res[o]
        v = hvp[hs]
        first = np.r_[True, v[1:] != v[:-1]]
        hs, cnt, res, v = hs[first], cnt[first], res[first], v[first]
        better = (cnt > best_cnt[v]) | ((cnt == best_cnt[v]) & (res < best_res[v]))
        v, hs, cnt, res = v[better], hs[better], cnt[better], res[better]
        best[v], best_cnt[v], best_res[v] = hs, cnt, res

    def associate_with(self, vps, T_ab):
        """One-to-one inlier associations of one hypothesis per view pair (vps (k,), T_ab (k, 4, 4)).

        With ``max_rotation_deg`` < 180, a pair of candidates of an object without a continuous
        symmetry whose relative rotation (under the symmetry D_l chose) is farther than that from
        the hypothesis' is no inlier, whatever D_l: one of the two has its rotation wrong (a
        loose threshold at 1 m admits a 160 deg error of a small object)."""
        rh, rp, D, s = self.rows_of(vps, T_ab)
        return self.associate(rp, self.rotation_gate(rp, D, s, T_ab[rh]), s)

    def rotation_gate(self, rp, D, s, T_rows):
        """D (rows rp with symmetry index s) with inf where the pair's relative rotation is farther
        than ``max_rotation_deg`` from that of ``T_rows`` (the hypothesis of each row's view pair;
        objects without a continuous symmetry, rows under their threshold only)."""
        lim = float(self.params.max_rotation_deg)
        if lim >= 180.0 or not len(rp):
            return D
        cand = np.flatnonzero((D < self.thr_vp[self.pvp[rp]]) & ~self.table.continuous[self.plab[rp]])
        if not len(cand):
            return D
        r = rp[cand]
        Ri = np.matmul(self.T[self.pI[r], :3, :3], self.table.S[self.plab[r], s[cand], :3, :3])
        Rk = np.matmul(Ri, np.swapaxes(self.pTJ[r, :3, :3], -1, -2))
        ang = _rot_angle(np.matmul(np.swapaxes(T_rows[cand, :3, :3], -1, -2), Rk))
        D = D.copy()
        D[cand[ang > np.deg2rad(lim)]] = np.inf
        return D

    def associate(self, rp, D, s):
        """One-to-one inlier associations from rows (pair rp, D_l, symmetry index) of one
        hypothesis per view pair. Returns (i, j, D, s, vp, pair row) arrays sorted by view pair
        then D."""
        sel = np.flatnonzero(D < self.thr_vp[self.pvp[rp]])
        i, j, d, ss, pr = self.pI[rp[sel]], self.pJ[rp[sel]], D[sel], s[sel], rp[sel]
        vp = self.pvp[rp[sel]]
        if self.prior is None:
            o = np.lexsort((j, i, d, vp))
        else:  # hypotheses: the closest after the cost of choosing them
            o = np.lexsort((j, i, d / self.thr_vp[vp] + self.prior[i] + self.prior[j], vp))
        i, j, d, ss, vp, pr = i[o], j[o], d[o], ss[o], vp[o], pr[o]
        _, fi = np.unique(vp * max(self.n, 1) + self.det[i], return_index=True)  # closest j of each i (detection)
        fi = np.sort(fi)
        i, j, d, ss, vp, pr = i[fi], j[fi], d[fi], ss[fi], vp[fi], pr[fi]
        _, fj = np.unique(vp * max(self.n, 1) + self.det[j], return_index=True)  # closest i of each j (detection)
        fj = np.sort(fj)
        return i[fj], j[fj], d[fj], ss[fj], vp[fj], pr[fj]

    def fit(self, assoc, n_vp, sigma_t: np.ndarray, min_n: int = 1, T_ref: np.ndarray | None = None):
        """Least-squares T_ab per view pair from its associations (symmetry-aware, all of them).

        Rotation: the weighted Wahba problem over the directions the candidates agree on: the
        three axes of each association's relative rotation ``R(T_a_i S) R(T_b_j)^T`` (objects
        without a continuous symmetry), the symmetry axis of objects with one, both weighted by
        1 / sigma_r^2 (sigma_r: the spread of the pair's relative rotations, from >= 3 objects,
        else ``SIGMA_R_DEFAULT``), and the layout of the object centres, ``sum (c_a - mean)(c_b -
        mean)^T / sigma_t^2`` (sigma_t (nvp,) mm: the noise of the centres). Translation: the mean
        of ``c_a - R c_b``. Returns (view pairs fitted (k,), T_ab (k, 4, 4)); a pair whose
        directions do not fix the rotation is not fitted. ``T_ref`` (nvp, 4, 4): the pairs' current
        poses; an association whose rotation (or axis) is more than ``ROT_OUTLIER_DEG`` from it
        gives no direction (one of its candidates has the rotation wrong), only its centres.
        """
        i, j, d, ss, vp, pr = assoc
        ok = n_vp[vp] >= max(1, int(min_n))
        i, j, ss, vp, pr = i[ok], j[ok], ss[ok], vp[ok], pr[ok]
        if len(i) == 0:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4))
        tab = self.table
        l = self.lab[i]
        TS = self.T[i] @ tab.S[l, ss]
        Tj = self.pTJ[pr]
        starts = np.flatnonzero(np.r_[True, vp[1:] != vp[:-1]])
        vps = vp[starts]
        cnt = np.diff(np.r_[starts, len(vp)])
        seg = np.repeat(np.arange(len(vps)), cnt)
        Ra, Rb = TS[:, :3, :3], Tj[:, :3, :3]
        Rk = np.matmul(Ra, np.swapaxes(Rb, -1, -2))
        ax = tab.continuous[l] & tab.has_axis[l]
        a = tab.axis_dir[l]
        ua = np.einsum("eij,ej->ei", Ra, a)
        ub = np.einsum("eij,ej->ei", Rb, a)
        full = ~tab.continuous[l]
        if T_ref is not None:
            # rotation outliers give their centres only: far from the reference, the current pose
            # or the chordal mean of the relative rotations, whichever more of them agree with
            lim = np.deg2rad(ROT_OUTLIER_DEG)
            R_mean = _project_so3(np.add.reduceat(Rk * full[:, None, None], starts) + 1e-9 * np.eye(3))
            best_ok, best_n = None, None
            for Rr in (T_ref[vps, :3, :3], R_mean):
                Re = Rr[seg]
                ok_r = full & (_rot_angle(np.matmul(np.swapaxes(Re, -1, -2), Rk)) <= lim)
                ok_a = ax & (np.einsum("ei,ei->e", ua, np.einsum("eij,ej->ei", Re, ub)) >= np.cos(lim))
                n_ok = np.add.reduceat((ok_r | ok_a).astype(np.int64), starts)
                if best_ok is None:
                    best_ok, best_n = (ok_r, ok_a), n_ok
                    continue
                take = (n_ok > best_n)[seg]
                best_ok = (np.where(take, ok_r, best_ok[0]), np.where(take, ok_a, best_ok[1]))
                best_n = np.maximum(n_ok, best_n)
            full, ax = best_ok
        ua = ua * ax[:, None]
        Rfull = Rk * full[:, None, None]
        Bfull = np.add.reduceat(Rfull, starts)
        n_full = np.add.reduceat(full.astype(np.int64), starts)
        sig_r = np.full(len(vps), SIGMA_R_DEFAULT)
        spread_from = np.flatnonzero(n_full >= 3)  # the pair's own rotation spread where 3 objects show it
        if len(spread_from):
            R0 = _project_so3(Bfull[spread_from])
            pos = np.full(len(vps), -1)
            pos[spread_from] = np.arange(len(spread_from))
            e = np.flatnonzero(full & (pos[seg] >= 0))
            ang = _rot_angle(np.matmul(np.swapaxes(R0[pos[seg[e]]], -1, -2), Rk[e]))
            spread = _median_by(ang, seg[e], len(vps)) / 1.5
            sig_r[spread_from] = np.clip(spread[spread_from], SIGMA_R_MIN, SIGMA_R_MAX)
        B = (Bfull + np.add.reduceat(ua[:, :, None] * ub[:, None, :], starts)) / (sig_r ** 2)[:, None, None]
        c = tab.centers[l]
        ca = np.einsum("eij,ej->ei", Ra, c) + TS[:, :3, 3]
        cb = np.einsum("eij,ej->ei", Rb, c) + Tj[:, :3, 3]
        ma = np.add.reduceat(ca, starts) / cnt[:, None]
        mb = np.add.reduceat(cb, starts) / cnt[:, None]
        da, db = ca - ma[seg], cb - mb[seg]
        H = np.add.reduceat(da[:, :, None] * db[:, None, :], starts)
        B += H / (np.maximum(sigma_t[vps], 1e-6) ** 2)[:, None, None]
        U, sv, Vt = np.linalg.svd(B)
        good = sv[:, 1] > 1e-9 * np.maximum(sv[:, 0], 1e-300)  # two independent directions at least
        R = _project_so3(B, (U, Vt))
        t = ma - np.einsum("kij,kj->ki", R, mb)
        T = np.tile(np.eye(4), (len(vps), 1, 1))
        T[:, :3, :3], T[:, :3, 3] = R, t
        return vps[good], T[good]

    def residual_scale(self, assoc, n_vp, n_groups: int) -> np.ndarray:
        """Robust scale of the candidates' noise per group: the median, over the associations of
        view pairs with at least ``min_inliers`` of them, of D_l divided by the objects' distance
        to the cameras (a relative error, like the depth error of an RGB method); NaN for a
        group with fewer than 3 such associations. (n_groups,)."""
        i, j, d, _, vp, _ = assoc
        ok = n_vp[vp] >= max(2, int(self.params.min_inliers))
        i, j, d, vp = i[ok], j[ok], d[ok], vp[ok]
        rel = d / np.maximum(0.5 * (self.dist[i] + self.dist[j]), 1e-9)
        grp = self.vp_group[vp]
        out = _median_by(rel, grp, n_groups)
        out[np.bincount(grp, minlength=n_groups) < 3] = np.nan
        return out

    def weak_links(self, assoc, n_vp, link_kind):
        """View pairs with 1 or 2 associations (fewer than ``min_inliers``) that link views which
        the RANSAC links leave apart, when they determine the relative pose and nothing
        contradicts them (the paper's Limitation III):

        * two objects: the hypothesis from one was verified by the other;
        * one object: only an object without symmetry (its pair alone fixes T_ab);
        * no contradiction: every label seen exactly once in each of the two views is associated
          (a label once in both views but not associated contradicts the pose).

        Accepted greedily (two objects first, then smaller sum of distances), each only if it
        joins two sets of views not linked otherwise. Returns the updated ``link_kind`` (nvp,)."""
        link_kind = link_kind.copy()
        mi = max(1, int(self.params.min_inliers))
        weak = np.flatnonzero((n_vp >= 1) & (n_vp < mi))
        if not len(weak):
            return link_kind
        i, j, d, _, vp, _ = assoc
        L = len(self.table)
        pm = self.primary  # detections, not hypotheses
        cnt = np.bincount(self.view[pm] * L + self.lab[pm], minlength=self.n_views * L).reshape(self.n_views, L)
        parent = list(range(self.n_views))

        def find(x):
            while parent[x] != x:
                parent[x] = parent[parent[x]]
                x = parent[x]
            return x

        for p in np.flatnonzero(link_kind != LINK_NONE).tolist():
            a, b = find(int(self.pair_views[p, 0])), find(int(self.pair_views[p, 1]))
            if a != b:
                parent[b] = a
        cands = []
        for p in weak.tolist():
            rows = np.flatnonzero(vp == p)
            labs = self.lab[i[rows]]
            a, b = self.pair_views[p]
            shared = np.flatnonzero((cnt[a] == 1) & (cnt[b] == 1))
            if np.setdiff1d(shared, np.union1d(labs, self.lab[j[rows]])).size:
                continue  # a label once in each view, not associated: contradicts the pose
            if len(rows) == 1 and self.table.n_sym[labs[0]] > 1:
                continue  # one symmetric object does not fix the relative pose
            cands.append((0 if len(rows) >= 2 else 1, float(d[rows].sum()), p))
        for rank, _, p in sorted(cands):
            a, b = find(int(self.pair_views[p, 0])), find(int(self.pair_views[p, 1]))
            if a == b:
                continue
            parent[b] = a
            link_kind[p] = LINK_TWO if rank == 0 else LINK_ONE
        return link_kind


SIGMA_R_DEFAULT = np.deg2rad(3.0)  # rad: relative rotation noise assumed when fewer than 3 objects show it
SIGMA_R_MIN, SIGMA_R_MAX = np.deg2rad(0.2), np.deg2rad(30.0)
ROT_OUTLIER_DEG = 45.0  # an association this far in rotation from its pair's pose gives the fit no direction


def _rot_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angles (rad) of rotation matrices (k, 3, 3)."""
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arccos(np.clip(c, -1.0, 1.0))


def _project_so3(A: np.ndarray, svd=None) -> np.ndarray:
    """Closest rotations (Frobenius) to matrices A (k, 3, 3) (``svd``: their (U, Vt) if known)."""
    U, Vt = svd if svd is not None else np.linalg.svd(A)[::2]
    d = np.where(np.linalg.det(U @ Vt) < 0, -1.0, 1.0)
    U = U * np.stack([np.ones_like(d), np.ones_like(d), d], -1)[:, None, :]
    return U @ Vt


def match_group(view: np.ndarray, lab: np.ndarray, T_cam_obj: np.ndarray, n_views: int, table: LabelTable,
                params: MatchParams = MatchParams(), seed=0, T_cam_world: np.ndarray | None = None,
                det: np.ndarray | None = None) -> GroupResult:
    """Match the object candidates of one group of views.

    view (n,): view index in [0, n_views) of each candidate; lab (n,): label index into
    ``table``; T_cam_obj (n, 4, 4): candidate poses in their camera, mm. ``seed`` (an int or a
    list of ints) seeds the RANSAC sampling, used only for view pairs with more candidate-pair
    combinations than a first round holds. ``T_cam_world`` (n_views, 4, 4): known camera poses;
    then there is no RANSAC (see the module docstring). ``det`` (n,): detection of each
    candidate when a detection has several pose hypotheses (see :func:`match_groups`).
    """
    return match_groups([(view, lab, T_cam_obj, n_views, T_cam_world, det)], table, params, [seed])[0]


def match_groups(groups, table: LabelTable, params: MatchParams = MatchParams(), seeds=None) -> list[GroupResult]:
    """Match several groups at once (same result as one by one, with less overhead per group).

    ``groups``: list of (view (n,), lab (n,), T_cam_obj (n, 4, 4), n_views, T_cam_world or None
    [, det (n,) or None[, prior (n,) or None]]) as in :func:`match_group` (all with known cameras
    or none); ``seeds``: one per group. ``det``: several pose hypotheses per detection -- candidates with the same
    det (same view and label) are hypotheses of one detection and mutually exclusive: an
    association, an inlier count and an object take at most one of them (at most one
    hypothesis per detection is given an object; see :class:`_Group`). Without det (or with
    distinct values) the results are those of one hypothesis per detection, bit-identical.
    ``prior``: the cost of choosing each candidate (e.g. proportional to its hypothesis rank), in
    units of the view pair's inlier threshold: associations and graph edges are chosen in
    increasing ``D / threshold + prior_i + prior_j`` instead of D (inlier tests unchanged).
    """
    seeds = [0] * len(groups) if seeds is None else list(seeds)
    known_flags = {g[4] is not None for g in groups}
    if len(known_flags) > 1:
        raise ValueError("all groups must have known cameras, or none")
    known = known_flags == {True}
    views, labs, Ts, gv, Tcws, dets, priors = [], [], [], [], [], [], []
    with_prior = any(len(g) > 6 and g[6] is not None for g in groups)
    with_det = any(len(g) > 5 and g[5] is not None for g in groups)
    v0, d0 = 0, 0
    for k, grp in enumerate(groups):
        view, lab, T_cam_obj, n_views, T_cw = grp[:5]
        view = np.asarray(view, dtype=np.int64).reshape(-1)
        lab = np.asarray(lab, dtype=np.int64).reshape(-1)
        T_cam_obj = np.asarray(T_cam_obj, dtype=np.float64).reshape(-1, 4, 4)
        if not (len(view) == len(lab) == len(T_cam_obj)):
            raise ValueError("view, lab and T_cam_obj must have the same length")
        if len(view) and (view.min() < 0 or view.max() >= n_views):
            raise ValueError("view index out of range")
        if with_det:  # detection ids (hypotheses of one detection), made unique across groups
            d = np.arange(len(view)) if len(grp) <= 5 or grp[5] is None else np.asarray(grp[5], np.int64).reshape(-1)
            if len(d) != len(view):
                raise ValueError("det must have one entry per candidate")
            dets.append(d - (d.min() if len(d) else 0) + d0)
            d0 += int(d.max() - d.min() + 1) if len(d) else 0
        if with_prior:
            pr = np.zeros(len(view)) if len(grp) <= 6 or grp[6] is None else np.asarray(grp[6], np.float64).reshape(-1)
            if len(pr) != len(view):
                raise ValueError("prior must have one entry per candidate")
            priors.append(pr)
        views.append(view + v0)
        labs.append(lab)
        Ts.append(T_cam_obj)
        gv.append(np.full(int(n_views), k, dtype=np.int64))
        if known:
            Tcws.append(np.asarray(T_cw, dtype=np.float64).reshape(int(n_views), 4, 4))
        v0 += int(n_views)
    det_all = (np.concatenate(dets) if dets else np.zeros(0, np.int64)) if with_det else None
    prior_all = (np.concatenate(priors) if priors else np.zeros(0)) if with_prior else None
    cand_group = np.repeat(np.arange(len(groups)), [len(v) for v in views])
    view = np.concatenate(views) if views else np.zeros(0, np.int64)
    g_args = (view, np.concatenate(labs) if labs else np.zeros(0, np.int64),
              np.concatenate(Ts) if Ts else np.zeros((0, 4, 4)), np.concatenate(gv) if gv else np.zeros(0, np.int64))
    # label groups: the view pairs' poses, thresholds and links come from same-label pairs (the
    # paper's matching, unchanged) unless cross_label_hypotheses; pairs of grouped labels then only
    # add associations under those poses
    grouped = table.cross and int((table.compat & ~np.eye(len(table), dtype=bool)).any(1)[g_args[1]].sum()) >= 2
    two_pass = grouped and not params.cross_label_hypotheses
    g = _Group(*g_args, _same_label_table(table) if two_pass or not grouped else table, params, det=det_all,
               prior=prior_all)
    if known:
        Tcw = np.concatenate(Tcws)
        T_ab = Tcw[g.pair_views[:, 0]] @ invert(Tcw[g.pair_views[:, 1]])
        n_hyp = (g.m > 0).astype(np.int64)
        vps = np.flatnonzero(g.m > 0)
        assoc = g.associate_with(vps, T_ab[vps])
    else:
        T_ab, best_cnt, n_hyp, (b_rp, b_D, b_s) = g.ransac(seeds)
        assoc = g.associate(b_rp, g.rotation_gate(b_rp, b_D, b_s, T_ab[g.pvp[b_rp]]), b_s)
    n_vp = np.bincount(assoc[4], minlength=g.nvp)
    if params.refit and not known:
        assoc, n_vp = _refit_pairs(g, T_ab, assoc, n_vp)
    scale = np.full(len(groups), np.nan)
    if params.adaptive_k > 0 and g.nvp:
        # the threshold that fits the candidates' noise: k x the robust residual scale of the
        # group (relative to the distance), between threshold_mm and the ceiling; then the
        # associations again under the final threshold (and the refit on them)
        scale = g.residual_scale(assoc, n_vp, len(groups))
        s_vp = scale[g.vp_group]
        thr = np.where(np.isfinite(s_vp), np.clip(float(params.adaptive_k) * s_vp * g.z_vp,
                                                   float(params.threshold_mm), g.thr_ceiling), g.thr_ceiling)
        g.set_thresholds(thr)
        g.sigma_t = np.where(np.isfinite(s_vp), np.maximum(s_vp * g.z_vp, 1e-3), thr / 3)
        vps = np.flatnonzero(n_vp > 0)
        assoc = g.associate_with(vps, T_ab[vps])
        n_vp = np.bincount(assoc[4], minlength=g.nvp)
        if params.refit and not known:
            assoc, n_vp = _refit_pairs(g, T_ab, assoc, n_vp)
    # the fit residual of each view pair: RMS of D_l over its final associations (mm)
    with np.errstate(invalid="ignore", divide="ignore"):
        fit_res = np.sqrt(np.bincount(assoc[4], weights=assoc[2] ** 2, minlength=g.nvp) / n_vp)
    link_kind = np.where(n_vp >= (1 if known else max(1, int(params.min_inliers))), LINK_RANSAC, LINK_NONE)
    if known:
        link_kind[(n_vp > 0)] = LINK_KNOWN
    elif params.weak_links:
        link_kind = g.weak_links(assoc, n_vp, link_kind)
    linked = link_kind != LINK_NONE
    if two_pass:  # associations of the linked pairs with the grouped labels' pairs too
        gx = _Group(*g_args, table, params, det=det_all, prior=prior_all)
        gx.set_thresholds(g.thr_vp)
        if known:  # known cameras: every pair with candidate pairs
            vps = np.flatnonzero(gx.m > 0)
            assoc = gx.associate_with(vps, T_ab[vps])
            n_vp = np.bincount(assoc[4], minlength=gx.nvp)
            link_kind = np.where(n_vp > 0, LINK_KNOWN, LINK_NONE)
            linked = link_kind != LINK_NONE
            n_hyp = (gx.m > 0).astype(np.int64)
        else:
            vps = np.flatnonzero(linked)
            assoc = gx.associate_with(vps, T_ab[vps])
        g = gx
    ei, ej, ed, _, evp, _ = assoc
    use = linked[evp]
    ei, ej, ed, evp = ei[use], ej[use], ed[use], evp[use]
    ekey = None if g.prior is None else ed / g.thr_vp[evp] + g.prior[ei] + g.prior[ej]
    comp, kept = _components(g.n, g.view, ei, ej, ed if ekey is None else ekey, g.det)
    # geometric fit of each candidate with its object (for the label vote)
    ke = np.flatnonzero(kept)
    ends = np.concatenate([ei[ke], ej[ke]])
    n_e = np.bincount(ends, minlength=g.n)
    d_sum = np.bincount(ends, weights=np.tile(ed[ke], 2), minlength=g.n)
    t_sum = np.bincount(ends, weights=np.tile(g.thr_vp[evp[ke]], 2), minlength=g.n)
    with np.errstate(invalid="ignore", divide="ignore"):
        fit = np.where(n_e > 0, np.exp(-(d_sum / np.maximum(t_sum, 1e-9)) ** 2), 0.0)
    fit_in = np.zeros(g.n)
    fit_in[g.order] = fit
    # back to input order (of the concatenated groups)
    inv = g.order
    comp_in = np.full(g.n, -1, dtype=np.int64)
    comp_in[inv] = comp
    e_in = np.stack([inv[ei], inv[ej]], 1) if len(ei) else np.zeros((0, 2), dtype=np.int64)
    results = []
    c0, vp0, f0 = 0, 0, 0
    e_group = cand_group[e_in[:, 0]] if len(e_in) else np.zeros(0, np.int64)
    for k, v in enumerate(views):
        n_k, nv_k = len(v), len(gv[k])
        n_vp_k = nv_k * (nv_k - 1) // 2
        # objects numbered by their first member in input order
        c = comp_in[c0:c0 + n_k]
        uniq, first, inv_c = np.unique(c, return_index=True, return_inverse=True)
        valid = np.flatnonzero(uniq >= 0)
        ids = np.full(len(uniq), -1, dtype=np.int64)
        ids[valid[np.argsort(first[valid])]] = np.arange(len(valid))
        sel = np.flatnonzero(e_group == k)
        sl = slice(vp0, vp0 + n_vp_k)
        results.append(GroupResult(
            object_id=ids[inv_c].reshape(-1), pair_views=g.pair_views[sl] - f0, n_inliers=n_vp[sl], T_ab=T_ab[sl],
            linked=linked[sl], n_hypotheses=n_hyp[sl], edges=e_in[sel] - c0, edge_dist=ed[sel],
            edge_pair=evp[sel] - vp0, edge_kept=kept[sel], threshold_mm=g.thr_vp[sl].copy(),
            link_kind=link_kind[sl].copy(), residual_scale=float(scale[k]), cand_fit=fit_in[c0:c0 + n_k],
            fit_residual_mm=fit_res[sl].copy()))
        c0, vp0, f0 = c0 + n_k, vp0 + n_vp_k, f0 + nv_k
    return results


def _same_label_table(table: LabelTable) -> LabelTable:
    """The table without label groups (a shallow copy: same geometry, same-label pairs only)."""
    import copy

    t = copy.copy(table)
    t.compat = np.eye(len(table), dtype=bool)
    t.cross = False
    return t


def _components(n: int, view: np.ndarray, ei: np.ndarray, ej: np.ndarray, ed: np.ndarray, det=None):
    """Union-find over edges in increasing distance; an edge joining two components that share
    a view is dropped, and so is one that would put a detection (``det`` (n,): several
    hypotheses of one detection) into a second component. Returns (component root per
    candidate, -1 for isolated; kept (E,))."""
    parent = list(range(n))
    views = [1 << int(v) for v in view]
    kept = np.zeros(len(ei), dtype=bool)
    detl = list(range(n)) if det is None else [int(d) for d in det]
    claim = [-1] * (max(detl) + 1 if detl else 0)  # a member of the component holding each detection

    def find(x):
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    order = np.lexsort((np.arange(len(ed)), ed))
    eil, ejl = ei.tolist(), ej.tolist()
    for e in order.tolist():
        a, b = find(eil[e]), find(ejl[e])
        if a == b:
            kept[e] = True
            continue
        if views[a] & views[b]:
            continue
        di, dj = detl[eil[e]], detl[ejl[e]]
        if (claim[di] >= 0 and find(claim[di]) != a) or (claim[dj] >= 0 and find(claim[dj]) != b):
            continue  # another hypothesis of one of these detections is in another object
        claim[di], claim[dj] = eil[e], ejl[e]
        if a > b:
            a, b = b, a
        parent[b] = a
        views[a] |= views[b]
        kept[e] = True
    comp = np.full(n, -1, dtype=np.int64)
    if kept.any():
        members = np.unique(np.concatenate([ei[kept], ej[kept]]))
        comp[members] = [find(int(x)) for x in members]
    return comp, kept
