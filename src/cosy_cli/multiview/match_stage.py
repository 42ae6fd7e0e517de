"""``cosy match``: object candidate matching over groups of views (CosyPose stage 2).

Inputs: a BOP dataset (``scene_camera.json`` per scene, ``models/`` with ``models_info.json``)
and candidates as a BOP results CSV (pose of the model in the camera, mm). RGB images are not
read. Output folder (built atomically: an interrupted run leaves nothing under ``out``):

``matches.csv``
    ``scene_id,group_id,im_id,obj_id,score,cand_id,object_id,object_obj_id``: one row per input
    candidate, in input order; ``cand_id`` = 0-based data row of the candidates CSV; ``object_id``
    = the physical object within its group (>= 0) or -1 when discarded (no match in another view,
    or a score under ``score_threshold``); ``object_obj_id`` = the label of its object (the vote
    of its members when label groups join candidates of different labels; the candidate's own
    ``obj_id`` when discarded).
``view_pairs.csv``
    ``scene_id,group_id,im_id_a,im_id_b,n_inliers,R,t``: one row per pair of views of a group
    (im_id_a < im_id_b) with ``T_cam_a_cam_b`` (maps points of camera b into camera a; R
    row-major, t in mm). ``n_inliers`` = associations of the best hypothesis; the pair is used
    (linked) when ``n_inliers >= min_inliers`` (any count with known cameras). A pair with no
    hypothesis at all (no common label) has ``n_inliers`` 0 and the identity. With
    ``known_cameras`` R, t are the known relative poses.
``groups.json``
    Self-describing record for ``cosy refine``: version, conf, dataset, split, candidates path,
    known_cameras, and per group its scene, image ids, objects (obj_id, member cand_ids and
    their im_ids; with members of other labels also ``cand_obj_ids``, ``votes`` {obj_id: sum of
    score x fit} and ``vote_only_cand_ids``: members whose pose is not a pose of the object's
    model, see :mod:`cosy_cli.multiview.label_groups`), discarded cand_ids, view pairs (with
    their associations, ``link``: "ransac", "two objects", "one object" or "none", and
    ``threshold_mm``: the inlier threshold used),
    ``threshold`` (the rule, the estimated relative noise ``residual_scale``, min/max mm) and
    timing; ``label_groups``: the setting, the groups and the model fits behind them.
``candidates.csv``
    A copy of the input candidates (same rows, same order: cand_id = row); with ``hypotheses``
    > 1 each row holds the pose hypothesis its detection chose (below).
``manifest.json``
    sha1 and size of the four files above (:mod:`cosy_cli.io.manifest`): ``cosy refine``
    refuses a file changed or truncated since match wrote it.

Several hypotheses per detection (``hypotheses`` K > 1, beyond the paper): the candidates CSV's
sidecar ``NAME.hypotheses.csv`` (:mod:`cosy_cli.io.hypotheses`, written by ``cosy estimate
--hypotheses N`` and listed in its manifest) gives each candidate ranked alternatives; ranks
0..K-1 all enter the matching as mutually exclusive candidates (see
:mod:`cosy_cli.multiview.matching`), each detection takes the hypothesis placed in an object
(unmatched ones keep rank 0), ``matches.csv`` gains a last column ``hyp_rank``, the objects of
groups.json ``hyp_ranks`` (aligned with ``cand_ids``), groups.json ``hypotheses`` (sidecar path,
sha1, K, how many chose rank > 0); ``candidates.csv`` holds the chosen poses, so ``cosy refine``
reads them unchanged. With K = 1 (default) every output is as without hypotheses.

Groups: one per scene holding all its images (sorted by im_id), or with ``views_per_group`` N
consecutive groups of N images (a last group of a single image joins the previous one).
Only scenes with candidates are processed. A group of one view (a scene of one image) has
nothing to match: its candidates pass through, each an object of its own (``object_id`` 0..),
and groups.json marks the group ``"single_view": true`` with a ``note``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from .. import __version__
from ..conf import as_bool, merge_conf
from ..errors import CosyError
from ..io import atomic, bop, cache, manifest
from ..io.cache import file_sha1, reuse_existing_output
from ..io.dataset import BopDataset
from ..objects.symmetries import symmetry_set
from ..geometry.sampling import farthest_point_subset, sample_surface
from . import label_groups
from .matching import LINK_NAMES, GroupResult, LabelTable, MatchParams, match_groups

FORMAT_VERSION = 1
BATCH_CANDIDATES = 2000  # groups are matched together until a batch holds this many candidates
BATCH_GROUPS = 64
OUTPUT_FILES = ("matches.csv", "view_pairs.csv", "groups.json", "candidates.csv")

CONFS: dict[str, dict] = {
    # The paper's values (Sec. 3.2 and the supplementary): 2 cm inlier threshold on D_l,
    # <= 2000 RANSAC iterations per view pair, >= 3 inliers, continuous symmetries in 64 steps.
    # n_points (model points for D_l), refit, sym_candidates and ransac_confidence (adaptive
    # stopping; 1.0 = always draw ransac_iterations) are cosy's choices (see
    # cosy_cli.multiview.matching).
    "paper": {
        "threshold_mm": 20.0,
        "ransac_iterations": 2000,
        "ransac_confidence": 0.99,
        "min_inliers": 3,
        "score_threshold": 0.0,
        "symmetry_steps": 64,
        "n_points": 32,
        "refit": True,
        "sym_candidates": 4,
        "views_per_group": None,
        # the views of a group: "scene" (all of a scene, or views_per_group consecutive ones),
        # "instant" (the sensors' images of one im_id: a rig, dataset sensor 'rig'), "targets"
        # (one group per entry of test_targets_multiview_bop25.json)
        "groups": "scene",
        "known_cameras": False,
        "seed": 0,
        # cosy's additions for real data (issue 16): an inlier threshold that follows the
        # candidates' noise, and views linked through 1-2 objects (see cosy_cli.multiview.matching)
        "threshold_rel": 0.10,
        "adaptive_k": 3.0,
        "weak_links": True,
        # a pair of candidates whose relative rotation is farther than this from its view pair's is
        # no inlier whatever its distance (deg; objects without a continuous symmetry). 180: off --
        # on the odd real LM-O dev scenes with cosy's own candidates multi-view AR 0.420 off, 0.417
        # at 150, 0.412 at 120, 0.407 at 90: wrong rotations at right positions help the refinement
        "max_rotation_deg": 180.0,
        # beyond the paper (issue 19): candidates of look-alike labels may be associated, the object
        # takes the label with most evidence ("auto": look-alike models; "none": same label only;
        # or groups like "6:7,5:8"; see cosy_cli.multiview.label_groups)
        "label_groups": "auto",
        # False: view-pair poses and links from same-label pairs (as the paper), grouped labels
        # only add associations under them; True: grouped labels' pairs make hypotheses too
        "cross_label_hypotheses": False,
        # beyond the paper: pose hypotheses per detection to choose from (the candidates CSV's
        # sidecar NAME.hypotheses.csv written by `cosy estimate --hypotheses N`); 1 = the paper
        "hypotheses": 1,
        # with hypotheses: cost of each rank in units of the inlier threshold when associations and
        # objects are chosen (a runner-up must agree this much better with the other views)
        "hypothesis_penalty": 0.5,  # on the odd lmo_dev scenes with 5 hypotheses, AR 0: 0.298, 0.5: 0.327, 2: 0.328
    },
}
# As published: one candidate pair's hypothesis (no refit), the fixed 2 cm, >= 3 inliers, same label
CONFS["paper-norefit"] = {**CONFS["paper"], "refit": False, "threshold_rel": 0.0, "adaptive_k": 0.0,
                          "weak_links": False, "label_groups": "none", "max_rotation_deg": 180.0}
CONFS["paper-fixed"] = {**CONFS["paper"], "threshold_rel": 0.0, "adaptive_k": 0.0, "weak_links": False,
                        "max_rotation_deg": 180.0}


GROUPINGS = ("scene", "instant", "targets")


def resolve_conf(conf: str | dict | None = "paper", **overrides) -> dict:
    """A full configuration: a named one (or a dict over ``paper``) with overrides (None ignored)."""
    base = merge_conf(CONFS, conf, overrides, default="paper", what="match")
    checks = {
        "threshold_mm": lambda v: v > 0, "ransac_iterations": lambda v: v >= 1, "min_inliers": lambda v: v >= 1,
        "symmetry_steps": lambda v: v >= 1, "n_points": lambda v: v >= 3, "sym_candidates": lambda v: v >= 1,
        "views_per_group": lambda v: v is None or v >= 2, "ransac_confidence": lambda v: 0 < v <= 1,
        "threshold_rel": lambda v: 0 <= v < 10, "adaptive_k": lambda v: 0 <= v < 1000,
        "hypotheses": lambda v: int(v) == v and 1 <= v <= 64, "hypothesis_penalty": lambda v: 0 <= v < 100,
        "max_rotation_deg": lambda v: 0 < v <= 180,
    }
    for k, ok in checks.items():
        try:
            good = ok(base[k])
        except TypeError:
            good = False
        if not good:
            raise CosyError(f"{k} = {base[k]!r} is out of range")
    for k in ("ransac_iterations", "min_inliers", "symmetry_steps", "n_points", "sym_candidates", "seed",
              "hypotheses"):
        base[k] = int(base[k])
    base["threshold_mm"] = float(base["threshold_mm"])
    base["ransac_confidence"] = float(base["ransac_confidence"])
    base["threshold_rel"] = float(base["threshold_rel"])
    base["adaptive_k"] = float(base["adaptive_k"])
    base["hypothesis_penalty"] = float(base["hypothesis_penalty"])
    base["max_rotation_deg"] = float(base["max_rotation_deg"])
    base["weak_links"] = as_bool(base["weak_links"], "weak_links", "match")
    base["score_threshold"] = float(base["score_threshold"])
    base["refit"] = as_bool(base["refit"], "refit", "match")
    base["known_cameras"] = as_bool(base["known_cameras"], "known_cameras", "match")
    if base["groups"] not in GROUPINGS:
        raise CosyError(f"groups = {base['groups']!r}: expected one of {', '.join(GROUPINGS)}")
    base["label_groups"] = label_groups.normalize_setting(base["label_groups"])
    base["cross_label_hypotheses"] = as_bool(base["cross_label_hypotheses"], "cross_label_hypotheses", "match")
    return base


def stale_reasons(out: Path, conf: dict, dataset: str | Path, split: str, candidates_csv: str | Path) -> list[str]:
    """Why a complete ``out`` does not correspond to these inputs and settings (empty: it does)."""
    try:
        doc = json.loads((out / "groups.json").read_text())
    except (OSError, json.JSONDecodeError):
        return ["groups.json unreadable"]
    reasons = []
    if doc.get("conf") != json.loads(json.dumps(conf)):
        changed = sorted(k for k in set(conf) | set(doc.get("conf") or {})
                         if (doc.get("conf") or {}).get(k) != json.loads(json.dumps(conf)).get(k))
        reasons.append(f"settings changed ({', '.join(changed)})")
    if doc.get("dataset") != str(Path(dataset).resolve()) or doc.get("split") != split:
        reasons.append("another dataset or split")
    if Path(candidates_csv).is_file() and doc.get("candidates_sha1") != file_sha1(candidates_csv):
        reasons.append("the candidates file changed")
    if conf.get("hypotheses", 1) > 1:
        side = hypotheses_file(candidates_csv)
        want = (doc.get("hypotheses") or {}).get("sha1")
        if (None if side is None else file_sha1(side)) != want:
            reasons.append("the hypotheses file changed")
    return reasons


def hypotheses_file(candidates_csv: str | Path) -> Path | None:
    """The hypotheses sidecar of a candidates CSV (``cands.hypotheses.csv``, see
    :mod:`cosy_cli.io.hypotheses`) when it exists and belongs to it: a CSV that cosy estimate
    wrote must list it in its manifest (a sidecar left from an earlier run is ignored)."""
    from ..io import hypotheses as hyp_io

    side = hyp_io.sidecar_path(candidates_csv)
    if not side.is_file() or manifest.companion_listed(candidates_csv, side) is False:
        return None
    return side


def load_hypotheses(candidates_csv: str | Path, n_candidates: int, k: int):
    """Pose hypotheses 1..k-1 of every candidate from the sidecar: (T (n, k-1, 4, 4), ok (n, k-1)),
    or None without a sidecar or with k = 1. Rank 0 is always the candidates CSV's row."""
    from ..io import hypotheses as hyp_io

    side = hypotheses_file(candidates_csv) if k > 1 else None
    if side is None:
        return None
    manifest.verify_companion(candidates_csv, side)
    det, rank, _, T = hyp_io.read_hypotheses(side, n_candidates)
    sel = (rank >= 1) & (rank < k)
    alt = np.tile(np.eye(4), (n_candidates, k - 1, 1, 1))
    ok = np.zeros((n_candidates, k - 1), dtype=bool)
    alt[det[sel], rank[sel] - 1] = T[sel]
    ok[det[sel], rank[sel] - 1] = True
    return alt, ok


def is_complete(out: str | Path) -> bool:
    return cache.is_complete(out, OUTPUT_FILES)


# --------------------------------------------------------------------------------------------
# model points without trimesh (start-up time): the numpy PLY reader + area-uniform sampling
# --------------------------------------------------------------------------------------------
def model_points(path: str | Path, n_points: int, seed: int = 0) -> np.ndarray:
    """``n_points`` well-spread surface points (mm) of a model: 2000 area-uniform samples, then
    farthest-point sampling. Reads PLYs with numpy; other files (or odd PLYs) with trimesh."""
    path = Path(path)
    if not path.is_file():
        raise CosyError("model file not found (BOP models are models/obj_XXXXXX.ply)", path=path)
    from ..objects.database import check_mesh_arrays, check_ply_data, load_mesh, read_ply_mesh

    try:
        if path.suffix.lower() != ".ply":
            raise ValueError("not a PLY")
        data = path.read_bytes()  # read once: checked against its header, then parsed
        header = check_ply_data(path, data)  # CosyError when the file holds less than its header declares
        V, F = read_ply_mesh(path, data, header)
    except (ValueError, KeyError, IndexError, UnicodeDecodeError):
        mesh = load_mesh(path)
        V, F = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    check_mesh_arrays(V, F, path)  # the checks every stage makes: finite, faces in range, not empty
    X = farthest_point_subset(sample_surface(V, F, 2000, seed), n_points)
    return X[np.arange(n_points) % len(X)]  # fewer points (a small point cloud): cycled, N for every label


def load_label_table(ds: BopDataset, obj_ids, n_points: int = 32, symmetry_steps: int = 64,
                     groups: "label_groups.Resolved | None" = None) -> LabelTable:
    """LabelTable of ``obj_ids`` from the dataset's models folder (points and symmetry sets);
    with ``groups`` (label groups resolved on ``ds``) the labels that may be associated."""
    infos = ds.models_info()
    pts, syms, cont, axes = [], [], [], []
    for o in obj_ids:
        info = infos[int(o)]
        X = model_points(ds.model_path(o), n_points)
        pts.append(X)
        syms.append(symmetry_set(info.symmetries_discrete, info.symmetries_continuous, symmetry_steps))
        cont.append(bool(info.symmetries_continuous))
        if info.symmetries_continuous:  # the symmetry axis (direction, a point on it)
            a = np.asarray(info.symmetries_continuous[0]["axis"], dtype=np.float64)
            c = np.asarray(info.symmetries_continuous[0].get("offset", np.zeros(3)), dtype=np.float64)
            axes.append((a / np.linalg.norm(a), c))
        else:
            axes.append(None)
    compat, model_align = label_groups.compat_arrays(groups, obj_ids) if groups is not None else (None, None)
    return LabelTable(obj_ids, pts, syms, continuous=cont, axes=axes, compat=compat,
                      model_align=model_align)


# --------------------------------------------------------------------------------------------
# the stage
# --------------------------------------------------------------------------------------------
def _row(i: int) -> str:
    return f"row {i + 1}"


def target_groups(ds: BopDataset, scene_ids) -> dict[int, list[list[int]]]:
    """{scene_id: [im_ids of each group]} from the dataset's ``test_targets_multiview_bop25.json``
    for the scenes ``scene_ids``: the im_ids of a single-sensor dataset (sensor ``default``, or
    the dataset's sensor), rig views of a ``rig`` dataset (:class:`~cosy_cli.io.dataset.RigDataset`).
    A CosyError for a missing file or an image the scene does not have."""
    from ..io.dataset import MULTIVIEW_TARGETS, RigDataset

    path = ds.multiview_targets_path()
    if path is None:
        raise CosyError(f"groups 'targets': no {MULTIVIEW_TARGETS} in the dataset folder", path=ds.root)
    wanted = {int(s) for s in scene_ids}
    rig = isinstance(ds, RigDataset)
    out: dict[int, list[list[int]]] = {}
    for i, t in enumerate(bop.read_multiview_targets(path)):
        if t.scene_id not in wanted:
            continue
        cams = ds.scene_camera(t.scene_id)
        ims = []
        for sensor, im in t.views:
            if rig:
                if sensor not in ds.sensors:
                    raise CosyError(f"sensor {sensor!r} is not a sensor of {ds.split_name} "
                                    f"({', '.join(ds.sensors)})", path=path, where=f"entry {i}")
                v = ds.view_id(sensor, im)
            else:
                if sensor not in (bop.DEFAULT_SENSOR, ds.sensor or ds.eval_sensor):
                    continue  # another sensor's image: not in this single-sensor run
                v = int(im)
            if v not in cams:
                raise CosyError(f"scene {t.scene_id} has no image {im} of sensor {sensor!r}", path=path,
                                where=f"entry {i}")
            ims.append(v)
        if ims:
            out.setdefault(t.scene_id, []).append(sorted(set(ims)))
    return out


def make_groups(ds: BopDataset, scene_ids, views_per_group: int | None, grouping: str = "scene") -> list[dict]:
    """[{scene_id, group_id, im_ids}] for the scenes, images sorted by im_id. ``grouping``: see
    the ``groups`` setting (:data:`CONFS`)."""
    from ..io.dataset import RigDataset

    groups = []
    if grouping == "targets":
        by_scene = target_groups(ds, scene_ids)
        for s in scene_ids:
            for g, c in enumerate(by_scene.get(int(s), [])):
                groups.append({"scene_id": int(s), "group_id": g, "im_ids": [int(x) for x in c]})
        return groups
    if grouping == "instant":
        if not isinstance(ds, RigDataset):
            raise CosyError("groups 'instant' needs the sensors of a multi-sensor dataset as one rig (sensor 'rig')",
                            path=ds.split_dir)
        for s in scene_ids:
            by_im: dict[int, list[int]] = {}
            for v in sorted(ds.scene_camera(s)):
                by_im.setdefault(ds.view_of(v)[1], []).append(int(v))
            for g, (_, c) in enumerate(sorted(by_im.items())):
                groups.append({"scene_id": int(s), "group_id": g, "im_ids": c})
        return groups
    for s in scene_ids:
        ims = sorted(ds.scene_camera(s))
        if views_per_group is None:
            chunks = [ims]
        else:
            chunks = [ims[k:k + views_per_group] for k in range(0, len(ims), views_per_group)]
            if len(chunks) > 1 and len(chunks[-1]) == 1:
                last = chunks.pop()
                chunks[-1] = chunks[-1] + last
        for g, c in enumerate(chunks):
            groups.append({"scene_id": int(s), "group_id": g, "im_ids": [int(x) for x in c]})
    return groups


def _check_inputs(ds: BopDataset, cands: bop.PoseResults, csv_path: Path, known_cameras: bool) -> None:
    tab = cands
    infos = ds.models_info()
    obj = tab.column("obj_id")
    bad = np.flatnonzero(~np.isin(obj, np.array(sorted(infos), dtype=np.int64)))
    if len(bad):
        i = int(bad[0])
        raise CosyError(f"obj_id {obj[i]} is not in the dataset's models ({ds.models_info_path} has "
                        f"{', '.join(map(str, sorted(infos)))})", path=csv_path, where=_row(i))
    scenes = tab.column("scene_id")
    ims = tab.column("im_id")
    known_scenes = set(ds.scene_ids)
    order = np.argsort(scenes, kind="stable")
    uniq, starts = np.unique(scenes[order], return_index=True)
    for s, a, b in zip(uniq.tolist(), starts.tolist(), np.r_[starts[1:], len(order)].tolist()):
        rows = order[a:b]  # the scene's rows, in file order
        first = int(rows[0])
        if int(s) not in known_scenes:
            known = ", ".join(map(str, sorted(known_scenes)))
            raise CosyError(f"scene_id {s} is not in {ds.split_dir} (scenes: {known})",
                            path=csv_path, where=_row(first))
        cams = ds.scene_camera(int(s))
        badim = rows[~np.isin(ims[rows], np.array(sorted(cams), dtype=np.int64))]
        if len(badim):
            i = int(badim[0])
            raise CosyError(f"im_id {ims[i]} is not an image of scene {s} ({ds.scene_file(int(s), 'scene_camera')} "
                            f"has {len(cams)} images)", path=csv_path, where=_row(i))
        if known_cameras:
            for im, c in cams.items():
                if c.T_cam_world is None:
                    raise CosyError("--known-cameras needs cam_R_w2c and cam_t_w2c for every image",
                                    path=ds.scene_file(int(s), "scene_camera"), where=f"image {im}")


SINGLE_VIEW_NOTE = "single view: candidates passed through (nothing to match)"


def single_view_result(n: int) -> GroupResult:
    """The matching of a group of one view: each of its ``n`` candidates is an object of its own
    (object ids 0..n-1 in input order); no view pairs, no associations."""
    z = np.zeros(0, dtype=np.int64)
    return GroupResult(object_id=np.arange(n, dtype=np.int64), pair_views=np.zeros((0, 2), dtype=np.int64),
                       n_inliers=z, T_ab=np.zeros((0, 4, 4)), linked=np.zeros(0, dtype=bool), n_hypotheses=z,
                       edges=np.zeros((0, 2), dtype=np.int64), edge_dist=np.zeros(0), edge_pair=z,
                       edge_kept=np.zeros(0, dtype=bool))


def _threshold_record(conf: dict, res: GroupResult) -> dict:
    """What groups.json says of a group's inlier threshold: the rule, the noise estimated from
    the candidates and the threshold of its view pairs (mm)."""
    thr = res.threshold_mm if res.threshold_mm is not None else np.full(len(res.pair_views), conf["threshold_mm"])
    rec = {"min_mm": round(float(thr.min()), 3), "max_mm": round(float(thr.max()), 3)}
    if conf["threshold_rel"] > 0 or conf["adaptive_k"] > 0:
        est = bool(np.isfinite(res.residual_scale)) and conf["adaptive_k"] > 0
        rec["rule"] = (f"clip({conf['adaptive_k']:g} x residual scale x distance, {conf['threshold_mm']:g} mm, "
                       f"ceiling)" if est else "ceiling (noise not estimated: too few associations)")
        rec["ceiling"] = f"max({conf['threshold_mm']:g} mm, {conf['threshold_rel']:g} x distance)"
        rec["residual_scale"] = round(float(res.residual_scale), 5) if est else None
    else:
        rec["rule"] = f"fixed {conf['threshold_mm']:g} mm"
    return rec


def _fmt_pose(T: np.ndarray) -> tuple[str, str]:
    return " ".join(f"{v:.9g}" for v in T[:3, :3].reshape(-1)), " ".join(f"{v:.6f}" for v in T[:3, 3])


def _vote(g: dict, res: GroupResult, objs: np.ndarray, score: np.ndarray) -> None:
    """The label of each object of a matched group (``g["labels"]``, ``g["votes"]``): the vote of
    its members, score x geometric fit (a single view: each candidate its own label)."""
    idx = g["cand_idx"]
    fit = res.cand_fit if res.cand_fit is not None else np.ones(len(idx))
    g["labels"], g["votes"] = label_groups.vote_labels(res.object_id, objs[idx], score[idx], fit)


def _expand(idx: np.ndarray, view: np.ndarray, T: np.ndarray, hyps):
    """The candidates ``idx`` of a group (their views ``view``, aligned with idx; T: the poses of
    all candidates) with their hypotheses, detection-major (rank 0 first): (cand
    index (h,), rank (h,), view (h,), T (h, 4, 4), det (h,) = position in ``idx``)."""
    alt, ok = hyps
    k = alt.shape[1] + 1
    n = len(idx)
    has = np.concatenate([np.ones((n, 1), dtype=bool), ok[idx]], 1).reshape(-1)
    pos = np.repeat(np.arange(n), k)[has]
    rank = np.tile(np.arange(k), n)[has]
    TT = np.concatenate([T[idx][:, None], alt[idx]], 1).reshape(-1, 4, 4)[has]
    return idx[pos], rank, view[pos], TT, pos


def _collapse(res: GroupResult, rank: np.ndarray, det: np.ndarray,
              n: int) -> tuple[GroupResult, np.ndarray, np.ndarray]:
    """The matching of a group's hypotheses as a matching of its ``n`` detections: each takes
    the hypothesis placed in an object (at most one is), else its rank 0. Returns (result per
    detection, chosen hypothesis (n,) as an index into the hypotheses, its rank (n,))."""
    first = np.flatnonzero(np.r_[True, det[1:] != det[:-1]]) if len(det) else np.zeros(0, np.int64)
    chosen = first.copy()  # rank 0 (detection-major, rank order)
    inside = np.flatnonzero(res.object_id >= 0)
    chosen[det[inside]] = inside
    return GroupResult(
        object_id=res.object_id[chosen], pair_views=res.pair_views, n_inliers=res.n_inliers, T_ab=res.T_ab,
        linked=res.linked, n_hypotheses=res.n_hypotheses, edges=det[res.edges] if len(res.edges) else res.edges,
        edge_dist=res.edge_dist, edge_pair=res.edge_pair, edge_kept=res.edge_kept, threshold_mm=res.threshold_mm,
        link_kind=res.link_kind, residual_scale=res.residual_scale,
        cand_fit=None if res.cand_fit is None else res.cand_fit[chosen],
        fit_residual_mm=res.fit_residual_mm), chosen, rank[chosen]


def run(conf: dict, ds: BopDataset, cands: bop.PoseResults, *, progress: bool = True, hyps=None):
    """Match every group; returns (groups (list of dicts with results, object labels and votes),
    object_id (n,), group_of (n,), the resolved label groups). ``hyps``: (T (n, k-1, 4, 4), ok
    (n, k-1)) pose hypotheses 1..k-1 of the candidates (:func:`load_hypotheses`); then each
    group also has ``hyp_rank`` (rank chosen per candidate) and ``T_chosen`` (their poses)."""
    from threadpoolctl import threadpool_limits

    tab = cands
    n = len(tab)
    scenes = tab.column("scene_id")
    ims = tab.column("im_id")
    objs = tab.column("obj_id")
    score = tab.column("score")
    object_id = np.full(n, -1, dtype=np.int64)
    group_of = np.full(n, -1, dtype=np.int64)
    groups = make_groups(ds, sorted(int(s) for s in np.unique(scenes)), conf["views_per_group"],
                         conf.get("groups", "scene"))
    used = sorted(int(o) for o in np.unique(objs))
    resolved = label_groups.resolve(conf["label_groups"], ds)
    table = load_label_table(ds, used, conf["n_points"], conf["symmetry_steps"], resolved) if used else None
    params = MatchParams(threshold_mm=conf["threshold_mm"], ransac_iterations=conf["ransac_iterations"],
                         min_inliers=conf["min_inliers"], refit=conf["refit"], sym_candidates=conf["sym_candidates"],
                         ransac_confidence=conf["ransac_confidence"], threshold_rel=conf["threshold_rel"],
                         adaptive_k=conf["adaptive_k"], weak_links=conf["weak_links"],
                         max_rotation_deg=conf["max_rotation_deg"],
                         cross_label_hypotheses=conf["cross_label_hypotheses"])
    lab_all = table.index_of(objs) if used else np.zeros(0, dtype=np.int64)
    diameters = {o: float(ds.models_info()[o].diameter) for o in used} if resolved.pairs else {}
    # candidates of each (scene, im)
    key = scenes * (1 << 32) + ims
    order = np.argsort(key, kind="stable")
    skey = key[order]
    bar = None
    if progress and n > 5000:  # about a second or more
        from ..console import progress as progress_bar

        bar = progress_bar(total=len(groups), desc="match", unit="group")
    # groups are matched in batches (same results as one by one, less overhead per group)
    batch: list[int] = []
    n_batch = 0

    def pass_through(k: int) -> None:
        """A group of one view: nothing to match; every candidate is an object of its own."""
        g = groups[k]
        n_k = len(g["cand_idx"])
        g["result"] = single_view_result(n_k)
        _vote(g, g["result"], objs, score)
        g["time_s"] = 0.0
        if hyps is not None:
            g["hyp_rank"] = np.zeros(n_k, dtype=np.int64)
            g["T_chosen"] = cands.T_cam_obj[g["cand_idx"]]
        object_id[g["cand_idx"]] = g["result"].object_id
        del g["view"], g["T_cw"]

    def flush():
        if not batch:
            return
        t0 = time.perf_counter()
        if hyps is None:
            inputs = [(groups[k]["view"], lab_all[groups[k]["cand_idx"]], cands.T_cam_obj[groups[k]["cand_idx"]],
                       len(groups[k]["im_ids"]), groups[k]["T_cw"]) for k in batch]
        else:  # every hypothesis a candidate; those of one detection mutually exclusive
            inputs, expanded = [], []
            for k in batch:
                ci, rk, vw, TT, det = _expand(groups[k]["cand_idx"], groups[k]["view"], cands.T_cam_obj, hyps)
                inputs.append((vw, lab_all[ci], TT, len(groups[k]["im_ids"]), groups[k]["T_cw"], det,
                               conf["hypothesis_penalty"] * rk))
                expanded.append((rk, det, TT))
        seeds = [[conf["seed"], groups[k]["scene_id"], groups[k]["group_id"]] for k in batch]
        results = match_groups(inputs, table, params, seeds)
        if hyps is not None:
            for q, k in enumerate(batch):
                rk, det, TT = expanded[q]
                results[q], chosen, groups[k]["hyp_rank"] = _collapse(results[q], rk, det, len(groups[k]["cand_idx"]))
                groups[k]["T_chosen"] = TT[chosen]
        dt = (time.perf_counter() - t0) / len(batch)
        for k, res in zip(batch, results):
            groups[k]["result"] = res
            _vote(groups[k], res, objs, score)
            groups[k]["time_s"] = dt
            object_id[groups[k]["cand_idx"]] = res.object_id
            del groups[k]["view"], groups[k]["T_cw"]
        if bar is not None:
            bar.update(len(batch))
        batch.clear()

    with threadpool_limits(1):
        for gi, g in enumerate(groups):
            s = g["scene_id"]
            gkeys = s * (1 << 32) + np.array(g["im_ids"], dtype=np.int64)
            lo = np.searchsorted(skey, gkeys, "left")
            hi = np.searchsorted(skey, gkeys, "right")
            idx = np.sort(np.concatenate([order[a:b] for a, b in zip(lo, hi)]))
            group_of[idx] = gi
            idx = idx[score[idx] >= conf["score_threshold"]]
            view = np.searchsorted(np.array(g["im_ids"]), ims[idx])
            dup = label_groups.same_detection_duplicates(view, objs[idx], cands.T_cam_obj[idx], score[idx], resolved,
                                                         diameters)
            g["duplicate_labels"] = [int(c) for c in idx[dup]]  # one box under two labels: the weaker left out
            idx, view = idx[~dup], view[~dup]
            g["cand_idx"] = idx
            g["view"] = view
            g["T_cw"] = None
            if conf["known_cameras"]:
                cams = ds.scene_camera(s)
                g["T_cw"] = np.stack([cams[i].T_cam_world for i in g["im_ids"]])
            if len(g["im_ids"]) == 1:
                pass_through(gi)
                continue
            batch.append(gi)
            n_batch += len(idx)
            if n_batch >= BATCH_CANDIDATES or len(batch) >= BATCH_GROUPS:
                flush()
                n_batch = 0
        flush()
    if bar is not None:
        bar.close()
    return groups, object_id, group_of, resolved


def chosen_hypotheses(cands: bop.PoseResults, groups) -> tuple[bop.PoseResults, np.ndarray]:
    """The candidates with the pose each chose among its hypotheses (rank 0 where it chose none)
    and the rank chosen (n,)."""
    rank = np.zeros(len(cands), dtype=np.int64)
    T = cands.T_cam_obj.copy()
    for g in groups:
        if "hyp_rank" in g:
            rank[g["cand_idx"]] = g["hyp_rank"]
            T[g["cand_idx"]] = g["T_chosen"]
    tab = cands
    out = bop.PoseResults.from_arrays(tab.column("scene_id"), tab.column("im_id"), tab.column("obj_id"), tab.column("score"), T, tab.column("time"))
    return out, rank


def _write_outputs(tmp: Path, conf: dict, ds: BopDataset, csv_path: Path, cands: bop.PoseResults, groups,
                   object_id, group_of, summary: dict, resolved: "label_groups.Resolved | None" = None,
                   hyp_file: Path | None = None) -> None:
    tab = cands
    ims = tab.column("im_id")
    with_hyp = conf.get("hypotheses", 1) > 1
    if with_hyp:  # candidates.csv carries the chosen poses (cosy refine reads it)
        cands, hyp_rank = chosen_hypotheses(cands, groups)
    lines = ["scene_id,group_id,im_id,obj_id,score,cand_id,object_id,object_obj_id"
             + (",hyp_rank" if with_hyp else "")]
    sc, ob, scr = tab.column("scene_id"), tab.column("obj_id"), tab.column("score")
    gid = [groups[g]["group_id"] if g >= 0 else -1 for g in group_of]
    obj_label = ob.copy()  # the label of each candidate's object (its own when discarded)
    for g in groups:
        idx, oid = g["cand_idx"], g["result"].object_id
        inside = oid >= 0
        obj_label[idx[inside]] = g["labels"][oid[inside]]
    agree = {(f.a, f.b) for f in (resolved.pairs if resolved is not None else []) if f.frames_agree}
    n_relabelled = 0
    for i in range(len(tab)):
        lines.append(f"{sc[i]},{gid[i]},{ims[i]},{ob[i]},{scr[i]:.9g},{i},{object_id[i]},{obj_label[i]}"
                     + (f",{hyp_rank[i]}" if with_hyp else ""))
    # plain writes: the whole folder is renamed into place at the end (atomic_dir)
    (tmp / "matches.csv").write_text("\n".join(lines) + "\n")
    vlines = ["scene_id,group_id,im_id_a,im_id_b,n_inliers,R,t,link,fit_residual_mm"]
    out_groups = []
    for gi, g in enumerate(groups):
        res, idx, im_ids = g["result"], g["cand_idx"], g["im_ids"]
        pairs = []
        for p, (a, b) in enumerate(res.pair_views):
            R, t = _fmt_pose(res.T_ab[p])
            link = LINK_NAMES[int(res.link_kind[p])] if res.link_kind is not None else \
                ("ransac" if res.linked[p] else "none")
            fr = np.nan if res.fit_residual_mm is None else float(res.fit_residual_mm[p])
            vlines.append(f"{g['scene_id']},{g['group_id']},{im_ids[a]},{im_ids[b]},{res.n_inliers[p]},{R},{t},{link},"
                          + (f"{fr:.3f}" if np.isfinite(fr) else ""))
            e = np.flatnonzero(res.edge_pair == p)
            pairs.append({
                "im_id_a": im_ids[a], "im_id_b": im_ids[b], "n_inliers": int(res.n_inliers[p]),
                "linked": bool(res.linked[p]), "link": LINK_NAMES[int(res.link_kind[p])] if res.link_kind is not None
                else ("ransac" if res.linked[p] else "none"),
                "threshold_mm": None if res.threshold_mm is None else round(float(res.threshold_mm[p]), 3),
                "n_hypotheses": int(res.n_hypotheses[p]),
                "T_cam_a_cam_b": [[float(f"{v:.10g}") for v in row] for row in res.T_ab[p]],
                "associations": [[int(idx[res.edges[k, 0]]), int(idx[res.edges[k, 1]]),
                                  float(f"{res.edge_dist[k]:.4f}"), bool(res.edge_kept[k])] for k in e],
            })
        objects = []
        for o in range(res.n_objects):
            members = idx[res.object_id == o]
            lab = int(g["labels"][o])
            entry_o = {"object_id": o, "obj_id": lab,
                       "cand_ids": [int(c) for c in members], "im_ids": [int(ims[c]) for c in members]}
            if with_hyp:
                entry_o["hyp_ranks"] = [int(hyp_rank[c]) for c in members]
            own = ob[members]
            if np.any(own != lab):  # members of other labels (label groups): the vote, and their use
                n_relabelled += int(np.sum(own != lab))
                entry_o["cand_obj_ids"] = [int(x) for x in own]
                entry_o["votes"] = {str(k): round(v, 6) for k, v in sorted(g["votes"][o].items())}
                entry_o["vote_only_cand_ids"] = [int(c) for c, x in zip(members, own)
                                                 if x != lab and (min(x, lab), max(x, lab)) not in agree]
            objects.append(entry_o)
        members_all = np.flatnonzero(group_of == gi)
        entry = {
            "scene_id": g["scene_id"], "group_id": g["group_id"], "im_ids": im_ids,
            "n_candidates": int(len(members_all)), "objects": objects,
            "discarded": [int(c) for c in members_all if object_id[c] < 0],
            "duplicate_labels": g.get("duplicate_labels", []),  # discarded: one box under two grouped labels
            "view_pairs": pairs, "time_s": round(g["time_s"], 6),
        }
        if len(res.pair_views):
            entry["threshold"] = _threshold_record(conf, res)
        if len(im_ids) == 1:
            entry["single_view"] = True
            entry["note"] = SINGLE_VIEW_NOTE
        out_groups.append(entry)
    (tmp / "view_pairs.csv").write_text("\n".join(vlines) + "\n")
    (tmp / "candidates.csv").write_text(bop.format_results(cands))
    doc = {
        "format": "cosy-match", "version": FORMAT_VERSION, "cosy_version": __version__, "conf": conf,
        "dataset": str(Path(ds.root).resolve()), "split": ds.split_spec, "candidates": str(Path(csv_path).resolve()),
        "candidates_sha1": file_sha1(csv_path),
        "candidates_copy": "candidates.csv", "known_cameras": conf["known_cameras"],
        "units": {"t": "mm", "poses": "T_cam_a_cam_b maps points of camera b into camera a"},
        "association_fields": ["cand_id_a", "cand_id_b", "D_l_mm", "kept_in_graph"],
        "label_groups": (resolved.record() if resolved is not None else None),
        "summary": {**summary, "relabelled_candidates": n_relabelled}, "groups": out_groups,
    }
    if with_hyp:
        doc["hypotheses"] = {"path": None if hyp_file is None else str(Path(hyp_file).resolve()),
                             "sha1": None if hyp_file is None else file_sha1(hyp_file),
                             "per_candidate": conf["hypotheses"],
                             "chosen_not_rank0": int((hyp_rank > 0).sum()),
                             "note": "candidates.csv holds the chosen poses; hyp_rank in matches.csv and "
                                     "hyp_ranks per object say which (0 = the candidates CSV's row)"}
    (tmp / "groups.json").write_text(json.dumps(doc, separators=(",", ":")) + "\n")  # compact: C encoder
    manifest.write_folder_manifest(tmp, "cosy match", OUTPUT_FILES)  # checked by cosy refine


def main(conf: str | dict | None, dataset: str | Path, split: str, candidates_csv: str | Path, out: str | Path,
         overwrite: bool = False, *, log=print, progress: bool = True) -> dict | None:
    """Run ``cosy match``; returns the summary dict (None when skipped because ``out`` is complete)."""
    t_start = time.perf_counter()
    conf = resolve_conf(conf)
    out = Path(out)
    if reuse_existing_output(out, "match", OUTPUT_FILES, overwrite,
                             lambda: stale_reasons(out, conf, dataset, split, candidates_csv), log):
        return None
    csv_path = Path(candidates_csv)
    ds = BopDataset(dataset, split)
    manifest.verify(csv_path)  # a file written by cosy estimate: refused if changed since
    cands = bop.read_results(csv_path)
    _check_inputs(ds, cands, csv_path, conf["known_cameras"])
    t0 = time.perf_counter()
    label_groups.check_obj_ids(conf["label_groups"], ds.models_info())
    hyp_file = hypotheses_file(csv_path) if conf["hypotheses"] > 1 else None
    hyps = load_hypotheses(csv_path, len(cands), conf["hypotheses"])
    if conf["hypotheses"] > 1 and hyps is None:
        log(f"match: hypotheses = {conf['hypotheses']} but {csv_path} has no hypotheses sidecar "
            "(cosy estimate --hypotheses N writes one): one pose per candidate")
    groups, object_id, group_of, resolved = run(conf, ds, cands, progress=progress, hyps=hyps)
    t_match = time.perf_counter() - t0
    times = np.array([g["time_s"] for g in groups]) if groups else np.zeros(0)
    n_obj = sum(g["result"].n_objects for g in groups)
    kept = int((object_id >= 0).sum())
    summary = {
        "groups": len(groups), "candidates": len(cands), "kept": kept, "discarded": len(cands) - kept,
        "objects": int(n_obj), "linked_view_pairs": int(sum(g["result"].linked.sum() for g in groups)),
        "view_pairs": int(sum(len(g["result"].linked) for g in groups)),
        "time_per_group_ms": float(times.mean() * 1e3) if len(times) else 0.0,
        "max_time_per_group_ms": float(times.max() * 1e3) if len(times) else 0.0,
        "time_matching_s": round(t_match, 4),
        "single_view_groups": int(sum(len(g["im_ids"]) == 1 for g in groups)),
    }
    with atomic.atomic_dir(out, overwrite=overwrite) as tmp:
        _write_outputs(tmp, conf, ds, csv_path, cands, groups, object_id, group_of, summary, resolved, hyp_file)
    log(f"match: {summary['groups']} groups, {summary['candidates']} candidates: {kept} kept in {n_obj} objects, "
        f"{summary['discarded']} discarded; {summary['linked_view_pairs']}/{summary['view_pairs']} view pairs linked; "
        f"{summary['time_per_group_ms']:.2f} ms per group (max {summary['max_time_per_group_ms']:.2f}); "
        + (f"{summary['single_view_groups']} single-view group(s): candidates passed through; "
           if summary["single_view_groups"] else "")
        + f"total {time.perf_counter() - t_start:.2f} s -> {out}")
    return summary
