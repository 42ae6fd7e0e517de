"""Image check of the refined scene, per view (``cosy refine --image-check``; beyond the paper).

The object-level bundle adjustment (:mod:`~cosy_cli.multiview.bundle_adjustment`) fixes objects
whose rotation was wrong in one view, but with two or three close views the depth of an object
along a view's ray barely shows in the reprojection error: where the other views' candidates are
off in depth, the adjustment can move a right single-view candidate 30-70 mm along its ray (LM-O
dev scenes). The images say which is right. For each placed view and each refined object
predicted in it, this module scores with the single-view verification score
(:class:`~cosy_cli.singleview.training_free.verify.Verifier`, no template prior):

- ``refined``: the refined pose in that view, T_cam_obj = inv(T_world_cam) T_world_obj;
- ``aligned`` (``align``): the contour alignment (:func:`~cosy_cli.singleview.training_free.contour.refine_contour`,
  with its accept test) started from the refined pose -- it keeps the multi-view rotation and
  moves the outline onto the image; kept only when it scores strictly higher than the refined pose;
- ``candidate``: the view's own candidates of that object (the object's candidates in that view).

and outputs the best-scoring pose. A candidate competes only when it disagrees with the refined
pose (some model point more than ``min_gap`` x the diameter apart: closer, the multi-view pose is
the finer one) and replaces the refined (or aligned) pose only when it scores more than ``margin``
higher (the refined pose carries the other views' support). The output therefore never scores
lower than the refined pose nor (beyond ``margin``) than a competing candidate. The observation
window of an object in a view is a projected model box (``box``: by default the union of the
refined pose's and the nearest candidate's) grown by the verifier's margin; the score
convention of the refined rows (1 + the object's score) is unchanged.

What the score can and cannot see (measured on the real odd LM-O dev images, GT poses as the
candidates, objects ~1 m away, 64 px crops): it barely sees depth -- a refined pose 60 mm along
its ray (6 %) loses to the GT pose in 59 % of the objects with margin 0 (22 of 162 with the
default margin 0.02; 88 of 162 at 120 mm); only the box term, when the box is the candidate's
own projection (``box: candidate``), makes it lose in 91 % -- but on the pipeline's candidates
that setting did no better (odd scenes, margin 0, alignment on: 0.404 vs 0.407 with the union). A 30 deg rotation error loses in 57 % (default).
So the check is a tie-breaker for gross disagreements, not a depth sensor.

Settings (chosen on the odd LM-O dev scenes, benchmarks/bench_realdata_multiview.py): BOP AR
(MSSD, MSPD) of multi-view on cosy's own candidates, and on synthetic candidates (odd scenes,
seed 100: 1 %/2 deg, 3 %/5 deg, 5 %/8 deg + 10 % gross), against no check (0.391; 0.901, 0.830,
0.621): the defaults (no alignment, margin 0.02, min_gap 0.1) 0.399; 0.901, 0.831, 0.622.
Letting candidates win on any higher score with the alignment (margin 0, min_gap 0, align,
align_max_move 0.1) 0.407 on the own candidates but 0.874, 0.803, 0.607 on the synthetic ones
(and YCB-V 1 %/2 deg 0.944 -> 0.850): where the multi-view pose is good, the score picks noise.
The alignment never added anything once the margin protects the refined pose. Held out (the
defaults): even LM-O dev scenes 0.365 -> 0.369 (single view 0.372); synthetic candidates on the
even scenes (seeds 0-2) and YCB-V (cosy's own RGB-D candidates 0.410, 1 %/2 deg 0.944) unchanged;
the synthetic data_samples demo (cosy run) BOP19 AR 0.986 unchanged.

Leftovers (:meth:`ImageChecker.check_leftovers`, refine ``image_check_leftovers``): most
single-view candidates never join a refined object -- on the LM-O dev scenes 171 of 293 --
because the views disagree: one of them has the rotation wrong, and matching links only poses
that agree. The cameras placed by the other objects say where each view's pose would stand in
the other views; the images say which pose explains them all. Leftovers of one label in several
placed views are clustered (:func:`cluster_leftovers`: each one's model centre carried into the
other's view lands within ``LEFTOVER_MAX_OFFSET`` x its projected size of it; a depth error along
a ray moves that projection little, another object far), every member's pose is scored in
every member's view, and a member takes the pose with the best mean score over the views when
it beats the mean of its own by more than ``margin``. Only views without depth: with depth the
single-view pick (depth fit + image) is the better judge -- on the YCB-V frames (one viewpoint in
effect, cameras placed from disagreeing candidates) the check cost 0.029 AR (MSSD, MSPD) with
the image score and 0.057 with the depth path's score. Chosen on the odd LM-O dev scenes (cosy's
own RGB candidates, multi-view AR (MSSD, MSPD) 0.399 without): margin 0 / 0.02 / 0.05 / 0.1
0.428 / 0.428 / 0.423 / 0.410 (prototype); LEFTOVER_MAX_OFFSET 0.25 / 0.5 / 1 / 2 0.418 / 0.422 /
**0.429** / 0.427. Held out: even scenes 0.369 -> **0.379** (single view 0.372); synthetic
candidates on the even scenes (seeds 0-2) 0.882 -> 0.887 (1 %/2 deg), 0.801 -> 0.805
(3 %/5 deg), 0.640 -> 0.641 (5 %/8 deg + 10 % gross); YCB-V unchanged (depth).

Cost (2-core CPU, LM-O dev, ~7 objects per view, no alignment): one batched verification render
per group (the images read once per view). Lengths in mm; T 4x4 (OpenCV camera); K (3, 3) px.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ..geometry.camera import project
from ..lifetime import Closing

MODES = ("auto", "none", "on")
LEFTOVER_MAX_OFFSET = 1.0  # leftovers are clustered when their centres, carried across views, land this close
CHOICES = ("refined", "aligned", "candidate")
SCORER_USES = ("leftovers", "all", "none")


@dataclass
class ImageCheckConf:
    """Settings of the image check (chosen on the odd LM-O dev scenes)."""

    align: bool = False       # also try the contour alignment started from the refined pose
    align_max_move: float = 0.1  # > 0: an aligned pose whose centre moved more than this x the diameter is refused
    margin: float = 0.02      # a candidate must beat the refined/aligned pose's score by more than this
    min_gap: float = 0.1      # a candidate is considered only when some model point lies farther than this x
                              # the diameter from where the refined pose puts it (closer: the multi-view pose
                              # is the finer one)
    box: str = "union"        # window/box: projected model box of the view's best candidate ("candidate"),
                              # of the refined pose ("refined") or the union of both ("union")
    w_box: float | None = None  # override of the verifier's box weight (None: its default)
    scorer_use: str = "leftovers"  # with a learned scorer: where its score replaces the verification score
                              # ("leftovers": the cross-view choice among leftovers; "all": also the check of
                              # the refined poses; "none")
    verify: dict = field(default_factory=dict)   # further VerifyConf overrides
    contour: dict = field(default_factory=dict)  # ContourConf overrides


def projected_boxes(points: list, K: np.ndarray, T: np.ndarray, wh: tuple[int, int]) -> np.ndarray:
    """Boxes (n, 4) x1, y1, x2, y2 px (pixel edges, clipped to the image wh = (W, H)) of model
    points (list of n (P, 3) arrays, mm) posed by T (n, 4, 4) and projected with K (3, 3) or (n, 3, 3)."""
    n = len(T)
    out = np.zeros((n, 4))
    K = np.broadcast_to(np.asarray(K, dtype=np.float64), (n, 3, 3))
    W, H = wh
    for i in range(n):  # one (P, 3) projection per object (P ~ 1000): cheap
        X = points[i] @ T[i, :3, :3].T + T[i, :3, 3]
        uv = project(X[X[:, 2] > 1.0], K[i])
        if not len(uv):
            out[i] = (0, 0, W, H)
            continue
        out[i] = (uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max())
    out[:, [0, 2]] = np.clip(out[:, [0, 2]], 0, W)
    out[:, [1, 3]] = np.clip(out[:, [1, 3]], 0, H)
    small = (out[:, 2] - out[:, 0] < 2) | (out[:, 3] - out[:, 1] < 2)
    if small.any():  # off the image: a tiny box at the clipped centre (the verifier grows it)
        c = np.stack([(out[:, 0] + out[:, 2]) / 2, (out[:, 1] + out[:, 3]) / 2], 1)
        out[small] = np.concatenate([c[small] - 1, c[small] + 1], 1)
    return out


@dataclass
class ViewItem:
    """One refined object predicted in one view: T_refined (4, 4) mm, T_cands (k, 4, 4) the view's
    own candidates of it (k >= 0)."""

    im_id: int
    obj_id: int
    T_refined: np.ndarray
    T_cands: np.ndarray


@dataclass
class CheckResult:
    """Per item: the pose kept (n, 4, 4), which ("refined" | "aligned" | "candidate"), the
    verification scores of the refined pose, of the aligned one (= refined where not aligned),
    of the best competing candidate (-1 without one: none, or all within ``min_gap``) and of the
    pose kept (-1 for items whose view has no image)."""

    T: np.ndarray
    choice: list
    s_refined: np.ndarray
    s_aligned: np.ndarray
    s_candidate: np.ndarray
    s_kept: np.ndarray


class LazyImages(Mapping):
    """{im_id: image} for the views ``im_ids``, each read by ``read(im_id)`` when first asked
    for (the reader caches: a view's image is read once per group)."""

    def __init__(self, im_ids, read):
        self._ids = [int(v) for v in im_ids]
        self._read = read

    def __getitem__(self, v):
        if int(v) not in self._ids:
            raise KeyError(v)
        return self._read(int(v))

    def __iter__(self):
        return iter(self._ids)

    def __len__(self) -> int:
        return len(self._ids)

    def __contains__(self, v) -> bool:
        return int(v) in self._ids


class ImageChecker(Closing):
    """Image check of refined poses (module docstring). db: ObjectDatabase of the labels to check;
    conf: ImageCheckConf; scorer: a learned hypothesis scorer
    (:class:`~cosy_cli.singleview.scorer.runtime.OnnxScorer`) whose score replaces the verification
    score where ``conf.scorer_use`` says. Renderers are made on first use; use as a context
    manager or close()."""

    def __init__(self, db, conf: ImageCheckConf | None = None, scorer=None):
        from ..singleview.training_free.contour import ContourConf, ContourRefiner
        from ..singleview.training_free.verify import Verifier, VerifyConf

        self.db = db
        self.conf = conf or ImageCheckConf()
        vk = dict(self.conf.verify)
        if self.conf.w_box is not None:
            vk["w_box"] = float(self.conf.w_box)
        if self.conf.scorer_use not in SCORER_USES:
            raise ValueError(f"image check scorer_use: expected one of {', '.join(SCORER_USES)}, "
                             f"got {self.conf.scorer_use!r}")
        self.scorer_use = self.conf.scorer_use if scorer is not None else "none"
        self.verifier = Verifier(db, VerifyConf(**vk), scorer=scorer)
        self.refiner = ContourRefiner(db, ContourConf(**self.conf.contour))
        self._points = {o.obj_id: np.asarray(o.points, dtype=np.float64) for o in db}

    def close(self):
        self.verifier.close()
        self.refiner.close()

    def _disagrees(self, obj_id: int, T_cand: np.ndarray, T_refined: np.ndarray) -> bool:
        """Whether a candidate may compete with the refined pose: some model point farther apart
        than ``min_gap`` x the diameter (any candidate when min_gap is 0)."""
        return self.conf.min_gap <= 0 or _max_displacement(self._points[int(obj_id)], T_cand, T_refined) > \
            self.conf.min_gap * self.db[int(obj_id)].diameter

    def _competes(self, it: ViewItem) -> bool:
        """Whether some candidate of the item disagrees with its refined pose (only such a
        candidate may replace it)."""
        return any(self._disagrees(it.obj_id, T, it.T_refined) for T in np.asarray(it.T_cands).reshape(-1, 4, 4))

    def check(self, items: list[ViewItem], images, Ks: dict) -> CheckResult:
        """Check items of one group: images {im_id: (H, W, 3) uint8} (any mapping, e.g.
        :class:`LazyImages`: only the views that need scoring are read), Ks {im_id: (3, 3)}. Views
        missing from ``images`` keep their refined poses. One verification render for all
        hypotheses, one contour alignment per view. Without the alignment, items that no
        candidate competes with are not scored (the refined pose is kept whatever the scores)."""
        from ..singleview.training_free.contour import refine_contour
        from ..singleview.training_free.verify import observe

        c = self.conf
        n = len(items)
        T_ref = np.stack([it.T_refined for it in items]) if n else np.zeros((0, 4, 4))
        T_out = T_ref.copy()
        choice = ["refined"] * n
        s_ref, s_al, s_cd = np.full(n, -1.0), np.full(n, -1.0), np.full(n, -1.0)
        ok = [i for i, it in enumerate(items) if it.im_id in images]
        if not c.align:
            # without the alignment an item can only change when one of its candidates competes
            # (disagrees with the refined pose by more than min_gap x the diameter): the others
            # keep the refined pose whatever the scores, so they are not scored (-1)
            ok = [i for i in ok if self._competes(items[i])]
        if not ok:
            return CheckResult(T_out, choice, s_ref, s_al, s_cd, s_ref.copy())
        obj = np.array([items[i].obj_id for i in ok])
        boxes = np.zeros((len(ok), 4))
        obs = []
        for j, i in enumerate(ok):
            it = items[i]
            rgb = images[it.im_id]
            wh = (rgb.shape[1], rgb.shape[0])
            K = Ks[it.im_id]
            pts = [self._points[it.obj_id]]
            b_ref = projected_boxes(pts, K, it.T_refined[None], wh)[0]
            if len(it.T_cands):
                # the best candidate's box: the candidate nearest the refined pose stands for the view
                k0 = int(np.argmin(np.linalg.norm(it.T_cands[:, :3, 3] - it.T_refined[:3, 3], axis=1)))
                b_c = projected_boxes(pts, K, it.T_cands[k0][None], wh)[0]
            else:
                b_c = b_ref
            if c.box == "refined":
                b = b_ref
            elif c.box == "union":
                b = np.array([min(b_ref[0], b_c[0]), min(b_ref[1], b_c[1]), max(b_ref[2], b_c[2]), max(b_ref[3], b_c[3])])
            else:
                b = b_c
            boxes[j] = b
            obs.append(observe(rgb, K, b, self.verifier.conf))
        # one render: the refined poses and every candidate
        det = [np.arange(len(ok))]
        Ts = [T_ref[ok]]
        for j, i in enumerate(ok):
            k = len(items[i].T_cands)
            if k:
                det.append(np.full(k, j))
                Ts.append(np.asarray(items[i].T_cands, dtype=np.float64).reshape(k, 4, 4))
        det = np.concatenate(det)
        Ts = np.concatenate(Ts)
        valid = np.all(np.isfinite(Ts.reshape(len(Ts), -1)), 1) & (Ts[:, 2, 3] > 0)
        sc = np.full(len(Ts), -1.0)
        if valid.any():
            sc[valid] = self.verifier.score(obs, det[valid], obj[det[valid]], Ts[valid],
                                            learned=self.scorer_use == "all")
        m = len(ok)
        sr = sc[:m]
        cand_best = np.full(m, -1.0)
        cand_arg = np.full(m, -1)
        diam = np.array([self.db[int(o)].diameter for o in obj])
        for q in range(m, len(Ts)):  # few candidates per item
            j = det[q]
            if not self._disagrees(obj[j], Ts[q], Ts[j]):
                continue
            if sc[q] > cand_best[j]:
                cand_best[j], cand_arg[j] = sc[q], q
        T0 = T_ref[ok]
        T_al, sa = T0.copy(), sr.copy()
        moved = np.zeros(m, bool)
        if c.align:
            ims = np.array([items[i].im_id for i in ok])
            for v in np.unique(ims):
                js = np.flatnonzero((ims == v) & (T0[:, 2, 3] > 0))
                if not len(js):
                    continue
                r = refine_contour(self.refiner, self.verifier, [obs[j] for j in js], images[int(v)], Ks[int(v)],
                                   boxes[js], obj[js], T0[js], None, sr[js])
                T_al[js], sa[js], moved[js] = r.T, r.score, r.moved
            if c.align_max_move > 0:  # a local correction only: the refined pose has the other views' support
                far = moved & (np.linalg.norm(T_al[:, :3, 3] - T0[:, :3, 3], axis=1) > c.align_max_move * diam)
                T_al[far], sa[far], moved[far] = T0[far], sr[far], False
        for j, i in enumerate(ok):
            s_ref[i], s_al[i], s_cd[i] = sr[j], sa[j], cand_best[j]
            best, which, T = sa[j], ("aligned" if moved[j] else "refined"), T_al[j]
            if cand_arg[j] >= 0 and cand_best[j] > best + c.margin:
                best, which, T = cand_best[j], "candidate", Ts[cand_arg[j]]
            T_out[i], choice[i] = T, which
        s_kept = np.where(np.array([ch == "candidate" for ch in choice]), s_cd, s_al)
        return CheckResult(T_out, choice, s_ref, s_al, s_cd, s_kept)

    def check_leftovers(self, items: list[Leftover], images: dict, Ks: dict, T_world_cam: dict) -> LeftoverResult:
        """Cross-view check of leftover candidates of one group (module docstring): clusters of
        leftovers that may be one object (:func:`cluster_leftovers`); in each, every member's pose,
        carried through the cameras into every member's view, is scored against that view's
        image (window: the member's own projected model box); a member takes the pose with the
        best mean score over the cluster's views when it beats the mean of its own pose by more
        than ``margin``. images {im_id: (H, W, 3) uint8}; Ks {im_id: (3, 3)}; T_world_cam {im_id:
        (4, 4)} mm. One verification render for all clusters."""
        from ..singleview.training_free.verify import observe

        n = len(items)
        T_out = np.stack([np.asarray(it.T_cam_obj, dtype=np.float64) for it in items]) if n else np.zeros((0, 4, 4))
        source, cluster = np.arange(n), np.full(n, -1)
        usable = [k for k, it in enumerate(items) if it.im_id in images and it.im_id in T_world_cam]
        sub = [items[k] for k in usable]
        wh = {v: (images[v].shape[1], images[v].shape[0]) for v in images}
        clusters = [[usable[q] for q in c] for c in cluster_leftovers(sub, T_world_cam, Ks, self._points, wh)]
        if not clusters:
            return LeftoverResult(T_out, source, cluster, [])
        obs, det, hyp_T, obj, owner = [], [], [], [], []
        for ci, members in enumerate(clusters):
            Tw = np.stack([T_world_cam[items[k].im_id] @ T_out[k] for k in members])
            for k in members:
                it = items[k]
                K = Ks[it.im_id]
                box = projected_boxes([self._points[it.obj_id]], K, T_out[k][None], wh[it.im_id])[0]
                obs.append(observe(images[it.im_id], K, box, self.verifier.conf))
                T_cw = np.linalg.inv(T_world_cam[it.im_id])
                hyp_T.append(T_cw[None] @ Tw)  # every member's pose in this member's view
                det.append(np.full(len(members), len(obs) - 1))
                obj.append(np.full(len(members), it.obj_id))
            owner.append(len(members))
            cluster[members] = ci
        hyp_T = np.concatenate(hyp_T)
        det, obj = np.concatenate(det), np.concatenate(obj)
        valid = np.all(np.isfinite(hyp_T.reshape(len(hyp_T), -1)), 1) & (hyp_T[:, 2, 3] > 0)
        sc = np.full(len(hyp_T), -1.0)
        if valid.any():
            sc[valid] = self.verifier.score(obs, det[valid], obj[valid], hyp_T[valid],
                                            learned=self.scorer_use in ("leftovers", "all"))
        scores, q0 = [], 0
        for ci, members in enumerate(clusters):
            m = owner[ci]
            S = sc[q0:q0 + m * m].reshape(m, m)  # [view of member a, pose of member b]
            mean = S.mean(0)
            w = int(np.argmax(mean))
            for a, k in enumerate(members):
                if a != w and mean[w] > mean[a] + self.conf.margin:
                    T_out[k] = hyp_T[q0 + a * m + w]
                    source[k] = members[w]
            scores.append(mean)
            q0 += m * m
        return LeftoverResult(T_out, source, cluster, scores)


@dataclass
class Leftover:
    """A single-view candidate that no refined object explains, in a placed view: T_cam_obj (4, 4) mm."""

    im_id: int
    obj_id: int
    T_cam_obj: np.ndarray


@dataclass
class LeftoverResult:
    """Per leftover: the pose kept (n, 4, 4), the index of the leftover whose pose it is (itself
    when unchanged), its cluster (-1: none), and per cluster the mean scores of its hypotheses."""

    T: np.ndarray
    source: np.ndarray
    cluster: np.ndarray
    cluster_scores: list


def cluster_leftovers(items: list[Leftover], T_world_cam: dict, Ks: dict, points: dict, wh: dict,
                      max_offset: float = LEFTOVER_MAX_OFFSET) -> list[list[int]]:
    """Which leftovers of different views may be one physical object: same label, and each one's
    model centre, carried into the other's view through the cameras, projects within ``max_offset``
    x the other's projected model box (larger side) of the other's projected centre (depth errors
    along a ray move a projection little in a close view, a wrong object far). Greedy in increasing
    offset; a cluster holds at most one leftover per view. T_world_cam {im_id: (4, 4)}; Ks {im_id:
    (3, 3)}; points {obj_id: (P, 3)} model points (mm); wh {im_id: (W, H)}. Returns clusters of
    two or more indices into ``items``."""
    n = len(items)
    if n < 2:
        return []
    view = np.array([it.im_id for it in items])
    lab = np.array([it.obj_id for it in items])
    Kn = np.stack([np.asarray(Ks[int(v)], dtype=np.float64) for v in view])  # (n, 3, 3)
    Tco = np.stack([np.asarray(it.T_cam_obj, dtype=np.float64) for it in items])
    T_wc = np.stack([np.asarray(T_world_cam[int(v)], dtype=np.float64) for v in view])
    T_cw = np.linalg.inv(T_wc)
    centre = np.stack([np.asarray(points[int(o)]).mean(0) for o in lab])  # model frame (mm)
    c_cam = np.einsum("nij,nj->ni", Tco[:, :3, :3], centre) + Tco[:, :3, 3]
    c_w = np.einsum("nij,nj->ni", T_wc[:, :3, :3], c_cam) + T_wc[:, :3, 3]
    own = project(c_cam[:, None], Kn)[:, 0]
    size = np.array([np.ptp(projected_boxes([points[int(o)]], Kn[k], Tco[k][None], wh[int(view[k])])[0]
                            .reshape(2, 2), axis=0).max() for k, o in enumerate(lab)])
    i, j = np.triu_indices(n, 1)
    ok = (lab[i] == lab[j]) & (view[i] != view[j])
    i, j = i[ok], j[ok]
    if not len(i):
        return []

    def carried(a, b):  # centre of a projected into b's view, offset from b's own, / b's size
        pc = np.einsum("nij,nj->ni", T_cw[b, :3, :3], c_w[a]) + T_cw[b, :3, 3]
        uv = project(pc[:, None], Kn[b])[:, 0]
        off = np.linalg.norm(uv - own[b], axis=1) / np.maximum(size[b], 1.0)
        return np.where(pc[:, 2] > 1e-6, off, np.inf)

    d = np.maximum(carried(i, j), carried(j, i))
    parent = np.arange(n)
    views_of = {k: {int(view[k])} for k in range(n)}

    def root(k):
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for q in np.argsort(d, kind="stable"):
        if not d[q] <= max_offset:
            break
        a, b = root(i[q]), root(j[q])
        if a == b or views_of[a] & views_of[b]:
            continue
        parent[b] = a
        views_of[a] |= views_of.pop(b)
    roots = np.array([root(k) for k in range(n)])
    return [list(map(int, np.flatnonzero(roots == r))) for r in np.unique(roots) if (roots == r).sum() > 1]


def _max_displacement(points: np.ndarray, T_a: np.ndarray, T_b: np.ndarray) -> float:
    """Largest distance (mm) between the model points (P, 3) posed by T_a and by T_b (4, 4)."""
    d = points @ (T_a[:3, :3] - T_b[:3, :3]).T + (T_a[:3, 3] - T_b[:3, 3])
    return float(np.sqrt((d * d).sum(1).max())) if len(d) else 0.0


def images_available(ds, scene_id: int, im_ids) -> bool:
    """Whether every view of ``im_ids`` has its RGB image in the dataset."""
    from ..errors import CosyError

    try:
        for v in im_ids:
            ds.rgb_path(scene_id, v)
    except CosyError:
        return False
    return True
