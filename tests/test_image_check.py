"""Image check of the refined scene per view (multiview/image_check.py, refine ``image_check``), on
real LM-O images (skipped when ../shared/realdata is absent)."""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import json  # noqa: E402
import warnings  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from realdata import LMO, gt_cameras, needs  # noqa: E402
from realdata import orthonormal as _orthonormal  # noqa: E402

pytestmark = needs(LMO)
warnings.filterwarnings("ignore", message=".*orthonormal only.*")


@pytest.fixture(scope="module")
def lmo():
    from cosy_cli.io.dataset import BopDataset
    from cosy_cli.objects import ObjectDatabase

    ds = BopDataset(LMO, "test")
    return ds, ObjectDatabase.from_models_dir(ds.models_dir)


def _shifted_items(ds, s, v, shift_mm):
    """Every GT object of image v: refined = GT moved shift_mm along its ray, candidate = GT."""
    from cosy_cli.multiview import image_check as ic

    items = []
    for g in ds.scene_gt(s)[v]:
        T = _orthonormal(g.T_cam_obj)
        Tr = T.copy()
        Tr[:3, 3] *= 1 + shift_mm / np.linalg.norm(T[:3, 3])
        items.append(ic.ViewItem(v, g.obj_id, Tr, T[None]))
    return items


def test_refined_pose_off_along_its_ray_loses_to_the_right_candidate(lmo):
    """LM-O scene 17, image 737, obj 6 (the cat): multi-view moved a 4 mm candidate ~60 mm along
    its ray. Scored in the candidate's projected box (its apparent size: the depth cue), with no
    margin, a refined pose shifted 60 mm along the ray loses to the right candidate; the kept pose
    never scores below both inputs, and is the pose its label names."""
    from cosy_cli.multiview import image_check as ic

    ds, db = lmo
    s, v = 17, 737
    rgb, K = ds.read_rgb(s, v), ds.scene_camera(s)[v].K
    items = _shifted_items(ds, s, v, 60.0)
    with ic.ImageChecker(db, ic.ImageCheckConf(align=False, margin=0.0, box="candidate")) as chk:
        r = chk.check(items, {v: rgb}, {v: K})
    k = [it.obj_id for it in items].index(6)
    assert r.choice[k] == "candidate"
    np.testing.assert_array_equal(r.T[k], items[k].T_cands[0])
    assert sum(c == "candidate" for c in r.choice) >= len(items) - 2
    # never below both inputs; the pose output is the one named
    assert np.all(r.s_kept >= np.maximum(r.s_refined, r.s_candidate) - 1e-12)
    for i, it in enumerate(items):
        np.testing.assert_array_equal(r.T[i], it.T_cands[0] if r.choice[i] == "candidate" else it.T_refined)


def test_default_check_keeps_close_refined_poses_and_never_scores_below_the_refined_pose(lmo):
    """Defaults (margin 0.02, min_gap 0.1): a candidate within 0.1 x the diameter of the refined pose
    never replaces it (the multi-view pose is the finer one); a candidate replaces the refined pose
    only when it scores more than the margin higher; the output is one of the inputs."""
    from cosy_cli.geometry.rotations import rotation_about_axis
    from cosy_cli.multiview import image_check as ic

    ds, db = lmo
    s, v = 17, 737
    rgb, K = ds.read_rgb(s, v), ds.scene_camera(s)[v].K
    rng = np.random.default_rng(1)
    items = []
    for g in ds.scene_gt(s)[v]:
        T = _orthonormal(g.T_cam_obj)
        near = T.copy()
        near[:3, 3] += 3.0  # 5 mm from the GT: within min_gap
        far = T.copy()
        axis = rng.normal(size=3)
        far[:3, :3] = rotation_about_axis(axis, np.deg2rad([60.0]))[0] @ T[:3, :3]  # refined pose wrong by 60 deg
        items.append(ic.ViewItem(v, g.obj_id, T, near[None]))
        items.append(ic.ViewItem(v, g.obj_id, far, np.stack([T, near])))
    with ic.ImageChecker(db) as chk:
        r = chk.check(items, {v: rgb}, {v: K})
    assert all(c == "refined" for c in r.choice[0::2])
    for i, it in enumerate(items):
        if r.choice[i] == "candidate":
            assert r.s_candidate[i] > r.s_refined[i] + chk.conf.margin
            assert any(np.array_equal(r.T[i], Tc) for Tc in it.T_cands)
        else:
            assert r.choice[i] == "refined" and np.array_equal(r.T[i], it.T_refined)
    assert np.all(r.s_kept >= r.s_refined - 1e-12)
    assert "candidate" in r.choice[1::2]


def test_aligned_poses_score_at_least_the_refined_ones_and_stay_local(lmo):
    """With the contour alignment: a refined pose 5 deg / 10 mm off may be aligned; the kept pose
    scores at least the refined one and the candidate, an aligned pose moved at most
    align_max_move x the diameter; a view without images keeps its refined poses."""
    from cosy_cli.geometry.rotations import rotation_about_axis
    from cosy_cli.multiview import image_check as ic

    ds, db = lmo
    s, v = 21, 850
    rgb, K = ds.read_rgb(s, v), ds.scene_camera(s)[v].K
    rng = np.random.default_rng(0)
    items = []
    for g in ds.scene_gt(s)[v]:
        T = _orthonormal(g.T_cam_obj)
        Tr = T.copy()
        axis = rng.normal(size=3)
        Tr[:3, :3] = rotation_about_axis(axis / np.linalg.norm(axis), np.deg2rad([5.0]))[0] @ T[:3, :3]
        Tr[:3, 3] += rng.normal(size=3) * 10.0 / np.sqrt(3)
        Tc = T.copy()
        Tc[:3, 3] *= 1.05  # a candidate off in depth
        items.append(ic.ViewItem(v, g.obj_id, Tr, Tc[None]))
    items.append(ic.ViewItem(999, 6, items[0].T_refined, np.zeros((0, 4, 4))))  # no image for view 999
    conf = ic.ImageCheckConf(align=True, align_max_move=0.1)
    with ic.ImageChecker(db, conf) as chk:
        r = chk.check(items, {v: rgb}, {v: K})
    assert r.choice[-1] == "refined" and np.array_equal(r.T[-1], items[-1].T_refined)
    assert set(r.choice) <= set(ic.CHOICES)
    assert "aligned" in r.choice
    # never below the refined pose, nor below a candidate by more than the margin
    assert np.all(r.s_kept[:-1] >= np.maximum(r.s_refined, r.s_candidate - conf.margin)[:-1] - 1e-12)
    assert np.all(r.s_aligned[:-1] >= r.s_refined[:-1])
    for i, it in enumerate(items[:-1]):
        if r.choice[i] == "aligned":
            move = np.linalg.norm(r.T[i][:3, 3] - it.T_refined[:3, 3])
            assert move <= conf.align_max_move * db[it.obj_id].diameter + 1e-9


@pytest.fixture(scope="module")
def lmo_match(tmp_path_factory):
    """cosy match on synthetic candidates (3 % / 5 deg) of the real LM-O scenes 1-6."""
    from cosy_cli.io import bop
    from cosy_cli.multiview import match_stage
    from cosy_cli.synth import candidates as synth_candidates

    w = tmp_path_factory.mktemp("ic")
    synth_candidates.main(LMO, "test", w / "all.csv", profile="realistic", seed=3, depth_rel=0.03, rot_deg=5.0,
                          log=lambda *a, **k: None)
    res = bop.read_results(w / "all.csv", check_rotations=False)
    keep = res.table["scene_id"].to_numpy() <= 6
    t = res.table[keep]
    sub = bop.PoseResults.from_arrays(t["scene_id"], t["im_id"], t["obj_id"], t["score"], res.T_cam_obj[keep],
                                      t["time"])
    (w / "cands.csv").write_text(bop.format_results(sub))
    match_stage.main(match_stage.resolve_conf("paper"), LMO, "test", w / "cands.csv", w / "match", log=lambda *a: None,
                     progress=False)
    return w


def _rows(path):
    """predictions.csv without its time column."""
    return [",".join(line.split(",")[:6]) for line in path.read_text().splitlines()]


def test_refine_image_check_none_is_the_plain_refinement_and_auto_records_choices(lmo_match):
    from cosy_cli.multiview import refine_stage

    w = lmo_match
    quiet = lambda *a: None  # noqa: E731
    refine_stage.main(refine_stage.resolve_conf(None, image_check="none"), LMO, "test", w / "match", w / "none",
                      log=quiet, progress=False)
    # the check wired in but never leaving the refined pose (no alignment, candidates never win):
    # the same predictions as without it, bit for bit
    refine_stage.main(refine_stage.resolve_conf(None, image_check="on", image_check_align=False,
                                                image_check_margin=10.0),
                      LMO, "test", w / "match", w / "kept", log=quiet, progress=False)
    assert _rows(w / "none" / "predictions.csv") == _rows(w / "kept" / "predictions.csv")
    doc = json.loads((w / "none" / "scene.json").read_text())
    assert doc["summary"]["image_check"] is None
    assert not any("image_check" in o for g in doc["groups"] for o in g["objects"])
    # auto (the default): on, since the images exist; every refined row's choice recorded per view
    summary = refine_stage.main(None, LMO, "test", w / "match", w / "auto", log=quiet, progress=False)
    assert refine_stage.resolve_conf(None)["image_check"] == "auto"
    doc = json.loads((w / "auto" / "scene.json").read_text())
    n = sum(summary["image_check"].values())
    assert n == summary["refined_predictions"] > 0
    for g in doc["groups"]:
        placed = {c["im_id"] for c in g["cameras"]}
        for o in g["objects"]:
            if g.get("single_view"):
                continue
            views = set(placed) - set(o.get("views_keeping_their_candidates", []))
            assert {int(v) for v in o["image_check"]} == views
            assert set(o["image_check"].values()) <= {"refined", "aligned", "candidate"}
        if not g.get("single_view"):
            assert g["stats"]["image_check"]["time_s"] >= 0
    # refined rows keep the refined score convention (1 + s)
    rows = [line.split(",") for line in (w / "auto" / "predictions.csv").read_text().splitlines()[1:]]
    assert sum(float(r[3]) >= 1.0 for r in rows) == n


def test_bad_image_check_settings_are_refused():
    from cosy_cli.errors import CosyError
    from cosy_cli.multiview import refine_stage

    with pytest.raises(CosyError, match="image_check"):
        refine_stage.resolve_conf(None, image_check="sometimes")
    with pytest.raises(CosyError, match="image_check_box"):
        refine_stage.resolve_conf(None, image_check_box="everything")


# ---------------------------------------------------------------------------------------------
# leftovers: candidates no refined object explains, checked across the views
# ---------------------------------------------------------------------------------------------

def test_cluster_leftovers_links_one_object_across_views_and_nothing_else():
    """Two cameras 300 mm apart looking at a 100 mm cube 1 m away: the same label whose centres,
    carried through the cameras, land on each other clusters; another label, a candidate far off
    and a second candidate in one view do not join."""
    from cosy_cli.geometry.poses import invert, look_at
    from cosy_cli.multiview import image_check as ic

    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    pts = {1: np.array([[x, y, z] for x in (-50, 50) for y in (-50, 50) for z in (-50, 50)], float),
           2: np.array([[x, y, z] for x in (-30, 30) for y in (-30, 30) for z in (-30, 30)], float)}
    Twc = {10: look_at(np.array([0.0, 0, -1000]), np.zeros(3)), 11: look_at(np.array([300.0, 0, -950]), np.zeros(3))}
    T_wo = np.eye(4)
    T_wo2 = np.eye(4)
    T_wo2[:3, 3] = [250.0, 0, 0]
    items = [ic.Leftover(10, 1, invert(Twc[10]) @ T_wo), ic.Leftover(11, 1, invert(Twc[11]) @ T_wo),
             ic.Leftover(10, 2, invert(Twc[10]) @ T_wo2)]
    far = invert(Twc[11]) @ T_wo2  # label 1 where label 2 stands: 250 mm off
    items.append(ic.Leftover(11, 1, far))
    wh = {10: (640, 480), 11: (640, 480)}
    clusters = ic.cluster_leftovers(items, Twc, {10: K, 11: K}, pts, wh)
    assert clusters == [[0, 1]]
    # a depth error along the ray (15 %) keeps the pair together: the carried centre moves little
    T_deep = items[1].T_cam_obj.copy()
    T_deep[:3, 3] *= 1.15
    assert ic.cluster_leftovers([items[0], ic.Leftover(11, 1, T_deep)], Twc, {10: K, 11: K}, pts, wh) == [[0, 1]]
    assert ic.cluster_leftovers(items[:1], Twc, {10: K, 11: K}, pts, wh) == []
    # two instances of one label 250 mm apart, seen in both views (listed in another order in the
    # second view): each pairs with itself, never across
    T_b = np.eye(4)
    T_b[:3, 3] = [-250.0, 0, 0]
    two = [ic.Leftover(10, 1, invert(Twc[10]) @ T_wo), ic.Leftover(10, 1, invert(Twc[10]) @ T_b),
           ic.Leftover(11, 1, invert(Twc[11]) @ T_b), ic.Leftover(11, 1, invert(Twc[11]) @ T_wo)]
    assert sorted(ic.cluster_leftovers(two, Twc, {10: K, 11: K}, pts, wh)) == [[0, 3], [1, 2]]


def _turned_leftovers(ds):
    """Real LM-O scene 17 (three views): each GT object of labels 1, 5, 6, 8 seen in all views as a
    leftover in every view, in one view (a different one per object) turned by 90 deg about x.
    Returns (scene, views, T_world_cam of the views, GT {view: {obj_id: T}}, objects, leftovers,
    which are turned)."""
    from cosy_cli.geometry.rotations import rotation_about_axis
    from cosy_cli.multiview import image_check as ic

    s = 17
    views = sorted(ds.scene_gt(s))
    Twc = gt_cameras(ds, s, views)
    gt = {v: {g.obj_id: _orthonormal(g.T_cam_obj) for g in ds.scene_gt(s)[v]} for v in views}
    objs = [o for o in gt[views[0]] if all(o in gt[v] for v in views) and o in (1, 5, 6, 8)]
    turn = np.eye(4)
    turn[:3, :3] = rotation_about_axis(np.array([1.0, 0, 0]), np.array([np.pi / 2]))[0]
    items, wrong = [], []
    for o in objs:
        for k, v in enumerate(views):
            bad = k == objs.index(o) % len(views)
            items.append(ic.Leftover(v, o, gt[v][o] @ turn if bad else gt[v][o]))
            wrong.append(bad)
    return s, views, Twc, gt, objs, items, wrong


def test_leftover_with_a_wrong_rotation_takes_the_pose_that_explains_both_views(lmo):
    """Real LM-O scene 17 (three views): each GT object is a leftover in every view, in one view
    turned by 90 deg. The turned one takes a pose carried from another view (close to its GT),
    the right ones keep theirs (or take an equally right one)."""
    from cosy_cli.evaluation.pose_error import re as rot_err
    from cosy_cli.multiview import image_check as ic

    ds, db = lmo
    s, views, Twc, gt, objs, items, wrong = _turned_leftovers(ds)
    cams = ds.scene_camera(s)
    with ic.ImageChecker(db) as chk:
        r = chk.check_leftovers(items, {v: ds.read_rgb(s, v) for v in views}, {v: cams[v].K for v in views}, Twc)
    assert (r.cluster >= 0).all() and len(r.cluster_scores) == len(objs)
    for k, it in enumerate(items):
        err = float(np.ravel(rot_err(r.T[k][:3, :3], gt[it.im_id][it.obj_id][:3, :3]))[0])
        if wrong[k]:
            assert r.source[k] != k and err < 10.0, (it, err)
        else:
            assert err < 10.0, (it, err)
        assert np.isfinite(r.T[k]).all()
    # nothing to do with a single view
    one = [it for it in items if it.im_id == views[0]]
    with ic.ImageChecker(db) as chk:
        r1 = chk.check_leftovers(one, {views[0]: ds.read_rgb(s, views[0])}, {views[0]: cams[views[0]].K},
                                 {views[0]: Twc[views[0]]})
    assert (r1.source == np.arange(len(one))).all() and (r1.cluster == -1).all()


def test_refine_records_leftover_replacements_and_can_turn_them_off(lmo_match):
    """cosy refine (image check auto) on the synthetic candidates: scene.json says which leftover
    candidates took which other candidate's pose, and the predictions hold those poses; with
    image_check_leftovers off nothing is recorded and the leftovers keep their own poses."""
    from cosy_cli.io import bop
    from cosy_cli.multiview import refine_stage

    w = lmo_match
    quiet = lambda *a: None  # noqa: E731
    on = refine_stage.main(None, LMO, "test", w / "match", w / "lo_on", log=quiet, progress=False)
    off = refine_stage.main(refine_stage.resolve_conf(None, image_check_leftovers=False), LMO, "test", w / "match",
                            w / "lo_off", log=quiet, progress=False)
    assert refine_stage.resolve_conf(None)["image_check_leftovers"] is True
    assert off["leftovers_replaced"] == 0
    doc_on = json.loads((w / "lo_on" / "scene.json").read_text())
    doc_off = json.loads((w / "lo_off" / "scene.json").read_text())
    assert not any("leftovers" in g for g in doc_off["groups"])
    reps = [x for g in doc_on["groups"] for x in g.get("leftovers", {}).get("replaced", [])]
    assert on["leftovers_replaced"] == len(reps)
    cands = bop.read_results(w / "match" / "candidates.csv", check_rotations=False)
    pred = bop.read_results(w / "lo_on" / "predictions.csv", check_rotations=False)
    tab = pred.table
    for x in reps:  # the replaced row is no longer the candidate's own pose
        rows = np.flatnonzero((tab["im_id"].to_numpy() == x["im_id"]) & (tab["obj_id"].to_numpy() == x["obj_id"])
                              & (tab["score"].to_numpy() < 1.0))
        own = cands.T_cam_obj[x["cand_id"]]
        assert len(rows) and not any(np.allclose(pred.T_cam_obj[q][:3, 3], own[:3, 3], atol=1e-3) for q in rows)
    # the refined rows are the same either way
    def refined(p):
        return sorted(line for line in (p / "predictions.csv").read_text().splitlines()[1:]
                      if float(line.split(",")[3]) >= 1.0)
    assert [r.rsplit(",", 1)[0] for r in refined(w / "lo_on")] == [r.rsplit(",", 1)[0] for r in refined(w / "lo_off")]


class _TermScorer:
    """Stands in for a learned scorer (crop and margin of the verifier's): the training-free total
    (the verifier's own choice) or, ``flip``ped, its opposite; records the hypotheses it scored."""

    crop, margin = 64, 0.2

    def __init__(self, flip: bool = False):
        self.flip = flip
        self.calls = []

    def __call__(self, image, terms, ridx=None):
        self.calls.append(len(image))
        total = terms[:, 6].astype(np.float64)  # TERM_NAMES: ... "total" ...
        return 1.0 - total if self.flip else total


def test_the_scorer_decides_the_leftovers_and_with_all_the_refined_check_too(lmo):
    """ImageChecker(scorer=...): with scorer_use "leftovers" (the default) the cross-view choice
    among leftovers is the scorer's (a scorer that agrees with the verification changes nothing,
    its opposite turns right poses wrong) and the check of refined poses stays training-free;
    "all" puts it there too; "none" never calls it."""
    from cosy_cli.multiview import image_check as ic

    ds, db = lmo
    s, views, Twc, _, _, items, _ = _turned_leftovers(ds)
    cams = ds.scene_camera(s)
    images, Ks = {v: ds.read_rgb(s, v) for v in views}, {v: cams[v].K for v in views}
    assert ic.ImageCheckConf().scorer_use == "leftovers"
    with ic.ImageChecker(db) as chk:
        free = chk.check_leftovers(items, images, Ks, Twc)
    same, flip = _TermScorer(), _TermScorer(flip=True)
    with ic.ImageChecker(db, scorer=same) as chk:
        r = chk.check_leftovers(items, images, Ks, Twc)
    assert same.calls and (r.source == free.source).all()
    np.testing.assert_allclose(r.T, free.T)
    with ic.ImageChecker(db, scorer=flip) as chk:
        r = chk.check_leftovers(items, images, Ks, Twc)
    assert flip.calls and (r.source != free.source).any()
    unused = _TermScorer(flip=True)
    with ic.ImageChecker(db, ic.ImageCheckConf(scorer_use="none"), scorer=unused) as chk:
        r = chk.check_leftovers(items, images, Ks, Twc)
    assert not unused.calls and (r.source == free.source).all()
    # the check of refined poses (refined 60 mm off along the ray, the GT as the candidate)
    v = views[0]
    shifted = _shifted_items(ds, s, v, 60.0)
    with ic.ImageChecker(db) as chk:
        base = chk.check(shifted, {v: images[v]}, {v: Ks[v]})
    for use, called in (("leftovers", False), ("all", True)):
        sc = _TermScorer()
        with ic.ImageChecker(db, ic.ImageCheckConf(scorer_use=use), scorer=sc) as chk:
            r = chk.check(shifted, {v: images[v]}, {v: Ks[v]})
        assert bool(sc.calls) == called and r.choice == base.choice
    with pytest.raises(ValueError, match="scorer_use"):
        ic.ImageChecker(db, ic.ImageCheckConf(scorer_use="some"))
