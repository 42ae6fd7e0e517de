"""Label groups for ``cosy match`` (beyond the paper): which labels may be associated across views.

The paper associates only candidates of the same label. A detector that confuses look-alike
objects (cosy's objects 6 and 7: object 7 is object 6 with one notch) then splits one physical
object into two partial objects, or drops the views that named it wrongly. With a label-group
setting, candidates of two different labels ``a``, ``b`` of one group can be associated; the
matched object then takes the label with the most evidence (:func:`vote_labels`).

The setting ``label_groups``:

* ``"none"``: the paper (same label only), exactly;
* ``"auto"`` (default): groups of models that look alike, found from the models
  (:func:`find_lookalikes`): the mean two-way surface distance (chamfer) of their sampled surfaces,
  in their own frames or after the best rigid alignment, is at most ``AUTO_REL`` (2 %) of the
  larger diameter;
* explicit groups: ``"6:7,5:8"`` (pairs or longer groups ``6:7:8``; two labels may be associated
  when some group holds both: the relation is not made transitive across groups), or a JSON list
  of lists ``[[6, 7], [5, 8]]``.

Distance between candidates of different labels ``a`` (the one in the first view of a view pair)
and ``b``: the pose of ``b``'s model is turned into a pose of ``a``'s model with the alignment
``T_a_b`` of the two models (maps points of b's frame into a's; the identity when their frames
agree), ``T_cam_a = T_cam_b inv(T_a_b)``, then the symmetric distance D_a of label ``a`` (its
points and symmetries) as for same-label pairs. For models that do not look alike (explicit groups
of different shapes) the alignment is the best found and D_a includes their shape difference: such
pairs associate only when their poses agree well.

By default the view pairs' relative poses, thresholds and links are those of the same-label
matching (the paper's, unchanged); the grouped labels' candidate pairs then only add associations
under those poses (``cross_label_hypotheses`` lets them make RANSAC hypotheses too).

The vote (:func:`vote_labels`): each member adds ``score x fit`` to its own label, fit =
``exp(-(D / sigma)^2)`` with D the mean symmetric distance of its kept associations and sigma
their inlier threshold (half of it until issue 29: a look-alike that happened to agree closely
outvoted two right candidates); the object takes the label with the largest sum (groups.json records the
votes). What the members' poses are then worth for ``cosy refine``: a member of another label
``b`` in an object voted ``a`` is a measurement of the object's pose when the two models' frames
agree (``frames_agree``: the identity fits them within ``AUTO_REL``; cosy's look-alikes 6/7); it
only votes otherwise (groups.json ``vote_only_cand_ids``; refine should leave it out of the
adjustment and keep it as a single-view candidate).

Lengths in mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import CosyError

AUTO_REL = 0.02  # auto groups: chamfer distance <= this x the larger diameter
PREFILTER_REL = 0.10  # only models whose sorted extents and diameters agree within 10 % are compared
N_QUERY, N_TARGET = 500, 10000  # surface samples for the chamfer distance (query, nearest-neighbour target)
ICP_ITERATIONS = 12


# --------------------------------------------------------------------------------------------
# the setting
# --------------------------------------------------------------------------------------------
def normalize_setting(value) -> str | list[list[int]]:
    """``"auto"`` (also None / ""), ``"none"``, or sorted groups [[5, 8], [6, 7]] from ``"6:7,5:8"``,
    ``"[[6,7]]"`` or a list of lists. Raises CosyError (one line) on malformed input."""
    if value is None:
        return "auto"
    if isinstance(value, str):
        text = value.strip()
        low = text.lower()
        if low in ("", "auto"):
            return "auto"
        if low in ("none", "off", "same-label"):
            return "none"
        if text.startswith("["):
            import json

            try:
                value = json.loads(text)
            except json.JSONDecodeError:
                raise CosyError(f"label_groups: cannot read {text!r} (expected auto, none, pairs like 6:7,5:8 "
                                "or a JSON list of lists)") from None
        else:
            groups = []
            for part in text.split(","):
                ids = [x.strip() for x in part.split(":")]
                try:
                    g = [int(x) for x in ids]
                except ValueError:
                    raise CosyError(f"label_groups: expected groups of obj_ids like 6:7,5:8, got {part.strip()!r}"
                                    ) from None
                groups.append(g)
            value = groups
    if not isinstance(value, (list, tuple)):
        raise CosyError(f"label_groups: expected auto, none or groups like 6:7,5:8, got {value!r}")
    out = []
    for g in value:
        if not isinstance(g, (list, tuple)) or not all(isinstance(x, (int, np.integer)) and not isinstance(x, bool)
                                                       for x in g):
            raise CosyError(f"label_groups: a group must be a list of obj_ids, got {g!r}")
        ids = sorted({int(x) for x in g})
        if len(ids) < 2:
            raise CosyError(f"label_groups: a group needs two different obj_ids, got {list(g)!r}")
        out.append(ids)
    if not out:
        return "none"
    return [list(g) for g in sorted({tuple(g) for g in out})]


def check_obj_ids(groups, known, source: str = "--label-groups") -> None:
    """Explicit groups must name objects of the dataset (one-line CosyError otherwise)."""
    if not isinstance(groups, list):
        return
    known = set(int(k) for k in known)
    for g in groups:
        for o in g:
            if o not in known:
                raise CosyError(f"{source}: obj_id {o} is not a model of the dataset (known: "
                                f"{', '.join(map(str, sorted(known)))})")


# --------------------------------------------------------------------------------------------
# look-alike models
# --------------------------------------------------------------------------------------------
@dataclass(eq=False)
class PairFit:
    """How well model ``b`` fits model ``a``: chamfer distance (mm) in their own frames and after
    the best alignment ``T_a_b`` (maps b's frame into a's), relative to the larger diameter."""

    a: int
    b: int
    chamfer_identity_mm: float
    chamfer_mm: float
    rel: float
    frames_agree: bool  # the identity is the alignment (the models fit in their own frames)
    T_a_b: np.ndarray = field(default_factory=lambda: np.eye(4))

    def record(self) -> dict:
        rec = {"obj_ids": [self.a, self.b], "chamfer_mm": round(self.chamfer_mm, 3),
               "chamfer_rel": round(self.rel, 5), "frames_agree": self.frames_agree}
        if not self.frames_agree:
            rec["T_a_b"] = [[float(f"{v:.8g}") for v in row] for row in self.T_a_b]
            rec["chamfer_identity_mm"] = round(self.chamfer_identity_mm, 3)
        return rec


def _kabsch(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """T (4, 4) minimising sum ||T P - Q||^2."""
    pc, qc = P.mean(0), Q.mean(0)
    H = (P - pc).T @ (Q - qc)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, qc - R @ pc
    return T


def fit_models(a: int, b: int, Xa: tuple, Xb: tuple, diam: float, rel: float = AUTO_REL) -> PairFit:
    """Chamfer fit of model b onto model a. ``Xa``/``Xb``: (query (n, 3), target (m, 3)) surface
    samples, mm. The identity first; when it does not fit within ``rel`` x ``diam``, ICP from the
    4 proper rotations that align the principal axes."""
    from scipy.spatial import cKDTree

    qa, ta = Xa
    qb, tb = Xb
    tree_a, tree_b = cKDTree(ta), cKDTree(tb)
    c_id = 0.5 * (float(tree_b.query(qa)[0].mean()) + float(tree_a.query(qb)[0].mean()))
    if c_id <= rel * diam:
        return PairFit(a, b, c_id, c_id, c_id / diam, True)
    best_T, best_c = np.eye(4), c_id
    ca, cb = ta.mean(0), tb.mean(0)
    _, Va = np.linalg.eigh(np.cov((ta - ca).T))
    _, Vb = np.linalg.eigh(np.cov((tb - cb).T))
    for signs in ([1, 1, 1], [-1, -1, 1], [-1, 1, -1], [1, -1, -1]):
        R = Va @ np.diag(signs) @ Vb.T
        if np.linalg.det(R) < 0:
            R = Va @ np.diag([-s for s in signs]) @ Vb.T
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, ca - R @ cb
        for _ in range(ICP_ITERATIONS):  # b's query points onto a's surface
            Y = qb @ T[:3, :3].T + T[:3, 3]
            _, nn = tree_a.query(Y)
            T = _kabsch(qb, ta[nn])
        Ti = np.linalg.inv(T)
        c = 0.5 * (float(tree_a.query(qb @ T[:3, :3].T + T[:3, 3])[0].mean())
                   + float(tree_b.query(qa @ Ti[:3, :3].T + Ti[:3, 3])[0].mean()))
        if c < best_c:
            best_T, best_c = T, c
    return PairFit(a, b, c_id, best_c, best_c / diam, False, best_T)


def surface_samples(V: np.ndarray, F: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(query points (N_QUERY, 3), target points (N_TARGET, 3)) mm of a mesh for :func:`fit_models`."""
    from ..geometry.sampling import farthest_point_subset, sample_surface

    T = sample_surface(V, F, N_TARGET, seed=1)
    Q = farthest_point_subset(sample_surface(V, F, 2 * N_QUERY, seed=2), N_QUERY)
    return Q, T


def _surface_samples(path: Path) -> tuple[np.ndarray, np.ndarray]:
    from ..objects.database import read_ply_mesh

    try:
        V, F = read_ply_mesh(path)
    except (ValueError, KeyError, IndexError, UnicodeDecodeError):
        from ..objects.database import load_mesh

        mesh = load_mesh(path)
        V, F = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    return surface_samples(V, F)


def fit_pairs(ids, extents: dict, sizes: dict, samples_of, fit_diameter, rel: float = AUTO_REL) -> list[PairFit]:
    """:func:`fit_models` of every pair of ``ids`` whose sizes (one length per model, mm) and
    sorted extents (3,) agree within PREFILTER_REL. ``samples_of(o)`` gives a model's
    (query, target) samples (called once per model, only for models in such a pair);
    ``fit_diameter(a, b)`` the diameter (mm) the chamfer distance is relative to."""
    samples: dict = {}
    fits = []
    ids = sorted(ids)
    for i, a in enumerate(ids):
        for b in ids[i + 1:]:
            if abs(sizes[a] - sizes[b]) > PREFILTER_REL * max(sizes[a], sizes[b]) or \
                    np.any(np.abs(extents[a] - extents[b]) > PREFILTER_REL * np.maximum(extents[a], extents[b])):
                continue
            for o in (a, b):
                if o not in samples:
                    samples[o] = samples_of(o)
            fits.append(fit_models(a, b, samples[a], samples[b], fit_diameter(a, b), rel))
    return fits


CACHE_VERSION = 1
_memo: dict[str, tuple] = {}


def cache_dir() -> Path:
    """Where fits are kept: ``$COSY_CACHE_DIR/label_groups`` (default ``$XDG_CACHE_HOME/cosy``,
    else ``~/.cache/cosy``)."""
    from ..io.cache import user_cache_dir

    return user_cache_dir("label_groups")


def _models_key(ds, rel: float) -> str:
    """sha1 of the dataset's models (models_info and every model file) and of the settings."""
    import hashlib

    from ..io.cache import file_sha1

    infos = ds.models_info()
    h = hashlib.sha1(f"v{CACHE_VERSION} {rel!r} {PREFILTER_REL!r} {N_QUERY} {N_TARGET} {ICP_ITERATIONS}".encode())
    h.update(file_sha1(ds.models_info_path).encode())
    for o in sorted(infos):
        p = Path(ds.model_path(o))
        h.update(f" {o}:{file_sha1(p) if p.is_file() else 'missing'}".encode())
    return h.hexdigest()


def _fit_from_json(d: dict) -> PairFit:
    return PairFit(int(d["a"]), int(d["b"]), float(d["chamfer_identity_mm"]), float(d["chamfer_mm"]), float(d["rel"]),
                   bool(d["frames_agree"]), np.asarray(d["T_a_b"], dtype=np.float64))


def _fit_to_json(f: PairFit) -> dict:
    return {"a": f.a, "b": f.b, "chamfer_identity_mm": f.chamfer_identity_mm, "chamfer_mm": f.chamfer_mm, "rel": f.rel,
            "frames_agree": f.frames_agree, "T_a_b": f.T_a_b.tolist()}


def _compute_lookalikes(ds, rel: float) -> tuple:
    infos = ds.models_info()
    ext = {o: np.sort(np.asarray(i.size_xyz, dtype=np.float64)) for o, i in infos.items()}
    diam = {o: float(i.diameter) for o, i in infos.items()}
    return tuple(fit_pairs(infos, ext, diam, lambda o: _surface_samples(ds.model_path(o)),
                           lambda a, b: max(diam[a], diam[b]), rel))


def find_lookalikes(ds, rel: float = AUTO_REL) -> list[PairFit]:
    """Fits of the dataset's model pairs whose sizes agree; pairs with ``fit.rel <= rel`` look
    alike. Computed once per set of models (~1 s for 8 models) and cached in memory and under
    :func:`cache_dir` (keyed by the models' sha1)."""
    import json

    from ..io.atomic import write_text

    key = _models_key(ds, float(rel))
    if key in _memo:
        return list(_memo[key])
    path = cache_dir() / f"{key}.json"
    fits = None
    if path.is_file():
        try:
            fits = tuple(_fit_from_json(d) for d in json.loads(path.read_text())["fits"])
        except (OSError, ValueError, KeyError, TypeError):
            fits = None  # unreadable: recomputed
    if fits is None:
        fits = _compute_lookalikes(ds, float(rel))
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            write_text(path, json.dumps({"format": "cosy-label-groups", "version": CACHE_VERSION,
                                         "fits": [_fit_to_json(f) for f in fits]}) + "\n")
        except OSError:
            pass  # a read-only cache: computed again next time
    _memo[key] = fits
    return list(fits)


def pair_fits(ds, pairs) -> list[PairFit]:
    """Fits of explicit (a, b) pairs (computed where the auto search did not)."""
    known = {(f.a, f.b): f for f in find_lookalikes(ds)}
    infos = ds.models_info()
    out, samples = [], {}
    for a, b in pairs:
        if (a, b) in known:
            out.append(known[(a, b)])
            continue
        for o in (a, b):
            if o not in samples:
                samples[o] = _surface_samples(ds.model_path(o))
        out.append(fit_models(a, b, samples[a], samples[b], max(float(infos[a].diameter), float(infos[b].diameter))))
    return out


@dataclass
class Resolved:
    """The label groups of a run: allowed label pairs with their fits, and the record for groups.json."""

    setting: object
    pairs: list  # [PairFit] of the allowed (a < b) pairs
    fits: list  # every fit computed (auto: the candidates examined)
    time_s: float = 0.0

    def groups(self) -> list[list[int]]:
        """Connected groups of the allowed pairs (for display)."""
        parent: dict = {}

        def find(x):
            parent.setdefault(x, x)
            while parent[x] != x:
                parent[x] = parent[parent[x]]
                x = parent[x]
            return x

        for f in self.pairs:
            parent[find(f.b)] = find(f.a)
        comp: dict = {}
        for x in list(parent):
            comp.setdefault(find(x), []).append(x)
        return sorted(sorted(v) for v in comp.values())

    def record(self) -> dict:
        return {"setting": self.setting, "groups": self.groups(),
                "pairs": [f.record() for f in self.pairs],
                "rule": (f"auto: chamfer <= {AUTO_REL:g} x diameter (models with sizes within {PREFILTER_REL:g} "
                         "compared)"
                         if self.setting == "auto" else "none: same label only (the paper)"
                         if self.setting == "none" else "explicit groups"),
                "measurement": "a member of another label is used as a measurement of the object's pose only "
                               "when the two models' frames agree (frames_agree); otherwise it only votes",
                "not_grouped": [{"obj_ids": [f.a, f.b], "chamfer_rel": round(f.rel, 5)} for f in self.fits
                                if all(f is not q for q in self.pairs)],
                "time_s": round(self.time_s, 4)}


def resolve(setting, ds) -> Resolved:
    """The allowed cross-label pairs for ``setting`` (normalised) on dataset ``ds``."""
    import time

    t0 = time.perf_counter()
    if setting == "none":
        return Resolved("none", [], [])
    if setting == "auto":
        fits = find_lookalikes(ds)
        return Resolved("auto", [f for f in fits if f.rel <= AUTO_REL], fits, time.perf_counter() - t0)
    check_obj_ids(setting, ds.models_info())
    pairs = sorted({(g[i], g[j]) for g in setting for i in range(len(g)) for j in range(i + 1, len(g))})
    fits = pair_fits(ds, pairs)
    return Resolved(setting, fits, fits, time.perf_counter() - t0)


def compat_arrays(resolved: Resolved, obj_ids) -> tuple[np.ndarray, np.ndarray]:
    """(compat (L, L) bool, align (L, L, 4, 4)) over the label table's ``obj_ids``: compat[a, b]
    when labels a, b may be associated (the diagonal always), align[a, b] = T_a_b (maps b's model
    frame into a's)."""
    ids = [int(o) for o in obj_ids]
    L = len(ids)
    pos = {o: k for k, o in enumerate(ids)}
    compat = np.eye(L, dtype=bool)
    align = np.tile(np.eye(4), (L, L, 1, 1))
    for f in resolved.pairs:
        if f.a in pos and f.b in pos:
            i, j = pos[f.a], pos[f.b]
            compat[i, j] = compat[j, i] = True
            align[i, j] = f.T_a_b
            align[j, i] = np.linalg.inv(f.T_a_b)
    return compat, align


DUPLICATE_FRAC = 0.1  # same-view candidates of grouped labels closer than this x diameter: one detection


def same_detection_duplicates(view: np.ndarray, obj_id: np.ndarray, T_cam_obj: np.ndarray, score: np.ndarray,
                              resolved: Resolved, diameter: dict, frac: float = DUPLICATE_FRAC) -> np.ndarray:
    """(n,) bool: candidates that repeat a better-scored candidate of the same view under another
    label of its group. A detector that is unsure between look-alikes emits one box under both
    labels (``cosy detect``'s box classifier does so on purpose), and stage 1 gives both nearly the
    same pose; matched as two candidates, they would link the look-alikes' objects to each other
    through one view and split the views' associations. The better-scored one stays; the label
    vote across views then decides. Two candidates are the same detection when their labels form
    an allowed pair and their model origins (b's mapped into a's frame by the pair's alignment)
    are closer than ``frac`` x the larger diameter (mm)."""
    n = len(obj_id)
    drop = np.zeros(n, dtype=bool)
    if n < 2 or not resolved.pairs:
        return drop
    for f in resolved.pairs:
        ia = np.flatnonzero(obj_id == f.a)
        ib = np.flatnonzero(obj_id == f.b)
        if not len(ia) or not len(ib):
            continue
        # b's pose as a pose of a's model: T_cam_a = T_cam_b inv(T_a_b); its origin is where a's would be
        Tb_as_a = T_cam_obj[ib] @ np.linalg.inv(f.T_a_b)
        d = np.linalg.norm(T_cam_obj[ia][:, None, :3, 3] - Tb_as_a[None, :, :3, 3], axis=2)
        same = (view[ia][:, None] == view[ib][None, :]) & (d < frac * max(diameter[f.a], diameter[f.b]))
        a_i, b_j = np.nonzero(same)
        worse_a = score[ia[a_i]] < score[ib[b_j]]
        drop[ia[a_i[worse_a]]] = True
        drop[ib[b_j[~worse_a]]] = True
    return drop


# --------------------------------------------------------------------------------------------
# the vote
# --------------------------------------------------------------------------------------------
def vote_labels(object_id: np.ndarray, obj_id: np.ndarray, score: np.ndarray, fit: np.ndarray):
    """The label of every object: the obj_id with the largest sum of ``score x fit`` over its
    members (ties: the label of the best-scoring member, then the smaller obj_id).

    object_id (n,) (-1: discarded), obj_id (n,), score (n,), fit (n,) in [0, 1]. Returns
    (label per object (n_objects,), votes: list of {obj_id: weight} per object).
    """
    object_id = np.asarray(object_id)
    n_obj = int(object_id.max()) + 1 if len(object_id) and object_id.max() >= 0 else 0
    labels = np.zeros(n_obj, dtype=np.int64)
    votes: list[dict] = [dict() for _ in range(n_obj)]
    w = np.clip(np.nan_to_num(np.asarray(score, dtype=np.float64)), 0.0, None) * np.asarray(fit, dtype=np.float64)
    best_score = np.full(n_obj, -np.inf)
    best_label = np.zeros(n_obj, dtype=np.int64)
    for c in np.flatnonzero(object_id >= 0).tolist():
        o, lab = int(object_id[c]), int(obj_id[c])
        votes[o][lab] = votes[o].get(lab, 0.0) + float(w[c])
        if score[c] > best_score[o]:
            best_score[o], best_label[o] = score[c], lab
    for o in range(n_obj):
        v = votes[o]
        top = max(v.values())
        tied = [lab for lab, x in v.items() if x >= top - 1e-12 * max(1.0, abs(top))]
        labels[o] = best_label[o] if best_label[o] in tied else min(tied)
    return labels, votes
