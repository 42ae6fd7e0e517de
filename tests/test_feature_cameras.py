"""Cameras from image features (multiview/features.py, refine ``feature_cameras``)."""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import json  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from cosy_cli.evaluation.pose_error import re as angle_deg  # noqa: E402  (rotation error, degrees)
from realdata import LMO, YCBV, gt_cameras, needs  # noqa: E402

warnings.filterwarnings("ignore", message=".*orthonormal only.*")


def _pose(axis, deg, t):
    from cosy_cli.geometry.rotations import rotation_about_axis

    T = np.eye(4)
    T[:3, :3] = rotation_about_axis(np.asarray(axis, float), np.array([np.radians(deg)]))[0]
    T[:3, 3] = t
    return T


def test_feature_camera_takes_rotation_and_direction_from_the_images_and_scale_from_the_objects():
    from cosy_cli.multiview import features as ft

    conf = ft.FeatureConf()
    T_ref_cam = _pose([0, 1, 0], 20.0, [300.0, 20.0, 50.0])  # the true camera of the view, in the reference's
    d = T_ref_cam[:3, 3] / np.linalg.norm(T_ref_cam[:3, 3])
    pair_T = T_ref_cam.copy()
    pair_T[:3, 3] = d  # what the images give: unit translation
    pair = ft.PairPose(pair_T, n_inliers=200, n_matches=400)
    # the object-level estimate: 4 deg and 60 mm off
    T_obj = _pose([1, 0, 0], 4.0, [0, 0, 0]) @ T_ref_cam
    T_obj[:3, 3] += [40.0, -30.0, 30.0]
    # three objects' centres seen in both views (reference and view frames), one of them 10 % off in depth
    X = np.array([[0.0, 0, 900], [150, -50, 1000], [-120, 80, 950]])
    X_cam = (X - T_ref_cam[:3, 3]) @ T_ref_cam[:3, :3]  # the same points in the view's frame
    X_cam[2] *= 1.1
    T = ft.feature_camera(np.eye(4), T_obj, pair, conf, X, X_cam)
    assert T is not None
    assert angle_deg(T[:3, :3], T_ref_cam[:3, :3]) < 1e-6
    assert np.linalg.norm(T[:3, 3] - T_ref_cam[:3, 3]) < 1.0  # the median ignores the one off in depth
    # without object centres: the object-level baseline projected on the direction
    T2 = ft.feature_camera(np.eye(4), T_obj, pair, conf)
    assert abs(np.linalg.norm(T2[:3, 3]) - T_obj[:3, 3] @ d) < 1e-6
    # in another world frame (the reference camera not at the origin) the same relative pose
    W = _pose([0, 0, 1], 30.0, [10.0, 20.0, 30.0])
    T3 = ft.feature_camera(W, W @ T_obj, pair, conf, X, X_cam)
    assert np.allclose(T3, W @ T, atol=1e-6)
    # refused: too few inliers, a rotation far from the objects' one, a direction pointing backwards
    assert ft.feature_camera(np.eye(4), T_obj, ft.PairPose(pair_T, 10, 400), conf, X, X_cam) is None
    assert ft.feature_camera(np.eye(4), _pose([0, 1, 0], 60.0, T_obj[:3, 3]), pair, conf, X, X_cam) is None
    back = pair_T.copy()
    back[:3, 3] = -d
    assert ft.feature_camera(np.eye(4), T_obj, ft.PairPose(back, 200, 400), conf, X, X_cam) is None
    assert ft.feature_camera(np.eye(4), T_obj, None, conf) is None


@needs(LMO)
def test_relative_pose_of_two_real_lmo_views_matches_the_gt_derived_one():
    """LM-O scene 3, images 266 and 277: rotation and baseline direction from SIFT + essential
    matrix agree with the cameras implied by the GT object poses (rigid within 10 mm)."""
    from cosy_cli.io.dataset import BopDataset
    from cosy_cli.multiview import features as ft

    ds = BopDataset(LMO, "test")
    s, a, b = 3, 266, 277
    T_gt = gt_cameras(ds, s, [a, b])[b]
    cams = ds.scene_camera(s)
    cache = ft.FeatureCache()
    p = ft.relative_pose(cache, a, ds.read_rgb(s, a), cams[a].K, b, ds.read_rgb(s, b), cams[b].K)
    assert p is not None and p.n_inliers >= 100
    assert angle_deg(p.T_a_b[:3, :3], T_gt[:3, :3]) < 2.0
    d_gt = T_gt[:3, 3] / np.linalg.norm(T_gt[:3, 3])
    assert np.degrees(np.arccos(np.clip(p.T_a_b[:3, 3] @ d_gt, -1, 1))) < 5.0
    assert abs(np.linalg.norm(p.T_a_b[:3, 3]) - 1.0) < 1e-9
    # the same image twice: no baseline to speak of, but the rotation is the identity
    q = ft.relative_pose(cache, a, ds.read_rgb(s, a), cams[a].K, a, ds.read_rgb(s, a), cams[a].K)
    assert not q.ok or angle_deg(q.T_a_b[:3, :3], np.eye(3)) < 1.0
    # a blank image: no pose, and a reason instead
    blank = ft.relative_pose(cache, "blank", np.zeros((480, 640, 3), np.uint8), cams[a].K, a, ds.read_rgb(s, a),
                             cams[a].K)
    assert not blank.ok and blank.n_inliers == 0 and "too few features" in blank.failure


DATA = Path(__file__).parent / "data"


def test_the_demo_pair_that_crashed_opencv_51_gives_a_pose_and_degenerate_points_a_reason():
    """The 24 SIFT matches (normalised image coordinates) of a demo image pair on which OpenCV
    5.1.0's classic RANSAC findEssentialMat raised (an assertion in solvePoly) and so crashed
    ``cosy refine`` and ``make demo``: cosy's essential_pose gives a pose for them on every OpenCV
    (4.14, 5.0 and 5.1 give the same one), and degenerate points give a reason, never an error."""
    import cv2

    from cosy_cli.geometry.poses import is_rotation
    from cosy_cli.multiview import features as ft

    d = np.load(DATA / "opencv51_essential_demo.npz")
    xa, xb, thr = d["xa"], d["xb"], float(d["threshold"])
    if cv2.__version__ == "5.1.0":  # the trap itself: this input is the one that crashed
        with pytest.raises(cv2.error, match="solvePoly"):
            cv2.findEssentialMat(xa.reshape(-1, 1, 2), xb.reshape(-1, 1, 2), np.eye(3), method=cv2.RANSAC,
                                 prob=0.999, threshold=thr)
    r = ft.essential_pose(xa, xb, thr)
    assert not isinstance(r, str), r
    T_b_a, n_in = r
    assert 5 <= n_in <= len(xa) and is_rotation(T_b_a[:3, :3]) and abs(np.linalg.norm(T_b_a[:3, 3]) - 1) < 1e-9
    assert ft.essential_pose(xa, xb, thr)[1] == n_in  # reproducible (USAC's fixed seed)
    # a minimal sample of real LM-O matches on which 5.1's 5-point solver asserts: three of view b's
    # points are one keypoint matched three times
    five_a = np.array([[-0.2443, 0.1923], [-0.1591, -0.0042], [0.1584, 0.3829], [-0.2798, -0.0814], [0.4393, -0.0291]])
    five_b = np.array([[-0.3037, 0.1348], [-0.3037, 0.1348], [-0.2060, 0.3846], [-0.1857, 0.3866], [-0.3037, 0.1348]])
    for pts_a, pts_b in [(five_a, five_b), (np.zeros((30, 2)), np.zeros((30, 2))),  # all one point
                         (xa[:4], xb[:4]), (np.full((10, 2), np.nan), xb[:10]),
                         (np.c_[np.linspace(-1, 1, 20), np.zeros(20)], np.c_[np.linspace(-1, 1, 20), np.zeros(20)])]:
        out = ft.essential_pose(pts_a, pts_b, thr)
        assert isinstance(out, str) or is_rotation(out[0][:3, :3])
    assert "5 needed" in ft.essential_pose(xa[:4], xb[:4], thr)
    assert "not all finite" in ft.essential_pose(np.full((10, 2), np.nan), xb[:10], thr)
    # an OpenCV error is a reason naming OpenCV's function, without its source path
    why = ft.opencv_failure("essential matrix", cv2.error(
        "OpenCV(5.1.0) /io/opencv/modules/core/src/mathfuncs.cpp:1601: error: (-215:Assertion failed) "
        "std::abs(coeffs[n].re) + std::abs(coeffs[n].im) > DBL_EPSILON in function 'solvePoly'\n"))
    assert why.startswith("essential matrix: OpenCV refused the input ((-215:Assertion failed)") and "/io/" not in why
    assert "solvePoly" in why and "\n" not in why



def test_parallax_tells_one_viewpoint_from_several():
    """parallax_px: matched points of a scene with depth seen from one point under any rotation fit
    one homography (0 px); seen from points 5 % of the depth apart, they do not (tens of px); a
    flat scene is one homography from anywhere (0 px)."""
    from cosy_cli.multiview import features as ft

    rng = np.random.default_rng(0)
    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    X = np.c_[rng.uniform(-300, 300, (300, 2)), rng.uniform(600, 1500, 300)]  # camera a frame, mm
    flat = np.c_[X[:, :2], np.full(300, 1000.0)]

    def project(P, T_b_a):
        q = (P @ T_b_a[:3, :3].T + T_b_a[:3, 3]) @ K.T
        return q[:, :2] / q[:, 2:]

    xa = project(X, np.eye(4))
    turned = _pose([0.2, 1, 0.1], 12.0, [0.0, 0.0, 0.0])
    moved = _pose([0.2, 1, 0.1], 12.0, [50.0, 0.0, 0.0])
    assert ft.parallax_px(xa, project(X, turned)) < 0.5
    assert ft.parallax_px(xa, project(X, moved)) > 10.0
    assert ft.parallax_px(project(flat, np.eye(4)), project(flat, moved)) < 0.5


def test_wide_views_reads_the_parallax_of_the_feature_pairs():
    from cosy_cli.multiview.refine_stage import WIDE_PARALLAX_PX, wide_views

    def stats(*px):
        return {"feature_cameras": {"views": {str(k): {"inliers": 50, "used": True, "parallax_px": p}
                                              for k, p in enumerate(px)}}}

    assert not wide_views({}) and not wide_views(stats(1.0, 2.0))
    assert wide_views(stats(1.0, WIDE_PARALLAX_PX + 1.0))


@needs(LMO, YCBV)
def test_parallax_of_real_views():
    """Real image pairs: two YCB-V frames (the camera moved about 4 mm) stay under the threshold that
    lets views with depth into the leftover check; two LM-O views of one arrangement are far above."""
    from cosy_cli.io.dataset import BopDataset
    from cosy_cli.multiview import features as ft
    from cosy_cli.multiview.refine_stage import WIDE_PARALLAX_PX

    cache = ft.FeatureCache()
    ds = BopDataset(YCBV, "train_real")
    cams = ds.scene_camera(0)
    p = ft.relative_pose(cache, ("y", 1), ds.read_rgb(0, 1), cams[1].K, ("y", 10), ds.read_rgb(0, 10), cams[10].K)
    assert p is not None and p.parallax_px < WIDE_PARALLAX_PX / 2
    ds = BopDataset(LMO, "test")
    cams = ds.scene_camera(3)
    q = ft.relative_pose(cache, ("l", 266), ds.read_rgb(3, 266), cams[266].K, ("l", 277), ds.read_rgb(3, 277),
                         cams[277].K)
    assert q is not None and q.parallax_px > 4 * WIDE_PARALLAX_PX

@needs(LMO)
def test_refine_records_the_feature_cameras_and_none_is_the_objects_alone(tmp_path):
    """cosy refine on synthetic candidates (3 % / 5 deg) of LM-O scenes 1-4: with the default
    ("leftovers") each group's stats say per view how many inliers its image pair had and whether
    it was used, and the cameras used carry T_world_cam_features, while the refined scene is the
    one without feature cameras, bit for bit; "none" records nothing; bad settings are refused."""
    from cosy_cli.errors import CosyError
    from cosy_cli.io import bop
    from cosy_cli.multiview import match_stage, refine_stage
    from cosy_cli.synth import candidates as synth_candidates

    quiet = lambda *a, **k: None  # noqa: E731
    synth_candidates.main(LMO, "test", tmp_path / "all.csv", profile="realistic", seed=5, depth_rel=0.03, rot_deg=5.0,
                          log=quiet)
    res = bop.read_results(tmp_path / "all.csv", check_rotations=False)
    keep = res.table["scene_id"].to_numpy() <= 4
    t = res.table[keep]
    (tmp_path / "c.csv").write_text(bop.format_results(bop.PoseResults.from_arrays(
        t["scene_id"], t["im_id"], t["obj_id"], t["score"], res.T_cam_obj[keep], t["time"])))
    match_stage.main(match_stage.resolve_conf("paper"), LMO, "test", tmp_path / "c.csv", tmp_path / "m", log=quiet,
                     progress=False)
    summary = refine_stage.main(None, LMO, "test", tmp_path / "m", tmp_path / "on", log=quiet, progress=False)
    refine_stage.main(refine_stage.resolve_conf(None, feature_cameras="none"), LMO, "test", tmp_path / "m",
                      tmp_path / "off", log=quiet, progress=False)
    on = json.loads((tmp_path / "on" / "scene.json").read_text())
    off = json.loads((tmp_path / "off" / "scene.json").read_text())
    multi = [g for g in on["groups"] if not g.get("single_view") and len(g["cameras"]) > 1]
    assert multi
    n_used = 0
    for g in multi:
        views = g["stats"]["feature_cameras"]["views"]
        assert set(views) <= set(g["placed_by"])  # im_ids of the group
        for v, info in views.items():
            assert info["inliers"] >= 0 and isinstance(info["used"], bool)
            n_used += info["used"]
        for c in g["cameras"]:
            if views.get(str(c["im_id"]), {}).get("used"):
                T = np.array(c["T_world_cam_features"])
                assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6)
    assert n_used > 0 and summary["feature_cameras_used"] == n_used
    assert not any("feature_cameras" in g["stats"] for g in off["groups"])
    # the refined scene itself is the same (only the leftovers are carried with the feature cameras)
    for ga, gb in zip(on["groups"], off["groups"]):
        assert [c["T_world_cam"] for c in ga["cameras"]] == [c["T_world_cam"] for c in gb["cameras"]]
        assert [o["T_world_obj"] for o in ga["objects"]] == [o["T_world_obj"] for o in gb["objects"]]
    # "scene": the used views' cameras are the feature cameras, held in the adjustment
    refine_stage.main(refine_stage.resolve_conf(None, feature_cameras="scene"), LMO, "test", tmp_path / "m",
                      tmp_path / "scene", log=quiet, progress=False)
    sc = json.loads((tmp_path / "scene" / "scene.json").read_text())
    n_scene = 0
    for g_on, g_sc in zip(on["groups"], sc["groups"]):
        used = {v for v, i in g_on.get("stats", {}).get("feature_cameras", {}).get("views", {}).items() if i["used"]}
        for c_on, c_sc in zip(g_on["cameras"], g_sc["cameras"]):
            if str(c_on["im_id"]) in used and c_on["im_id"] == c_sc["im_id"]:
                assert "image features" in c_sc["placed_by"]
                assert np.allclose(c_sc["T_world_cam"], c_on["T_world_cam_features"], atol=1e-6)
                n_scene += 1
    assert n_scene > 0
    with pytest.raises(CosyError, match="feature_cameras"):
        refine_stage.resolve_conf(None, feature_cameras="sometimes")


def test_camera_without_objects_needs_more_inliers_and_takes_the_scale_from_the_candidates():
    from cosy_cli.multiview import features as ft

    conf = ft.FeatureConf()
    T_ref_cam = _pose([0, 1, 0], -15.0, [-250.0, 10.0, 40.0])
    d = T_ref_cam[:3, 3] / np.linalg.norm(T_ref_cam[:3, 3])
    pair_T = T_ref_cam.copy()
    pair_T[:3, 3] = d
    X = np.array([[0.0, 0, 900], [150, -50, 1000]])
    X_cam = (X - T_ref_cam[:3, 3]) @ T_ref_cam[:3, :3]
    T = ft.camera_without_objects(np.eye(4), ft.PairPose(pair_T, 100, 300), conf, X, X_cam)
    assert np.allclose(T, T_ref_cam, atol=1e-6)
    # the same pair with only 40 inliers: enough next to an object-level camera, not alone
    assert ft.camera_without_objects(np.eye(4), ft.PairPose(pair_T, 40, 300), conf, X, X_cam) is None
    assert ft.feature_camera(np.eye(4), T_ref_cam, ft.PairPose(pair_T, 40, 300), conf, X, X_cam) is not None
    # no candidate pair to take the scale from
    assert ft.camera_without_objects(np.eye(4), ft.PairPose(pair_T, 100, 300), conf, X[:0], X_cam[:0]) is None


def _second_view_turned(tmp_path):
    """LM-O scene 29 (two views): right candidates (the GT) in the first view, every object turned
    by 90 deg in the second, matched so that nothing links the views (cosy match's folder
    tmp_path / "m"). Returns (dataset, scene, GT, first view, second view)."""
    from cosy_cli.geometry.rotations import rotation_about_axis
    from cosy_cli.io import bop
    from cosy_cli.io.dataset import BopDataset
    from cosy_cli.multiview import match_stage
    from realdata import orthonormal

    ds = BopDataset(LMO, "test")
    s = 29
    gt = ds.scene_gt(s)
    a, b = sorted(gt)[:2]
    turn = np.eye(4)
    turn[:3, :3] = rotation_about_axis(np.array([1.0, 0, 0]), np.array([np.pi / 2]))[0]
    rows = [(s, v, g.obj_id, 1.0, orthonormal(g.T_cam_obj) @ (turn if v == b else np.eye(4)))
            for v in (a, b) for g in gt[v]]
    res = bop.PoseResults.from_arrays([r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows],
                                      [r[3] for r in rows], np.stack([r[4] for r in rows]), [-1.0] * len(rows))
    (tmp_path / "c.csv").write_text(bop.format_results(res))
    # every association of the two views has one rotation wrong: the rotation test refuses them (by
    # default three of them, at 12, 30 and 88 mm under a threshold of 97 mm, link the views)
    match_stage.main(match_stage.resolve_conf("paper", max_rotation_deg=90.0), LMO, "test", tmp_path / "c.csv",
                     tmp_path / "m", log=lambda *x, **k: None, progress=False)
    return ds, s, gt, a, b


def _replaced_rotation_errors(pred_csv, gt, b, obj_ids) -> list:
    """Rotation errors (deg) in view b of the predictions of ``obj_ids`` against the GT."""
    from cosy_cli.io import bop
    from realdata import orthonormal

    pred = bop.read_results(pred_csv, check_rotations=False)
    t = pred.table
    out = []
    for o in obj_ids:
        q = np.flatnonzero((t["im_id"].to_numpy() == b) & (t["obj_id"].to_numpy() == o))
        (g_b,) = [y for y in gt[b] if y.obj_id == o]
        out.append(float(np.ravel(angle_deg(pred.T_cam_obj[q[0]][:3, :3], orthonormal(g_b.T_cam_obj)[:3, :3]))[0]))
    return out


@needs(LMO)
def test_a_view_no_object_placed_gets_its_camera_from_the_images_and_its_wrong_candidates_fixed(tmp_path):
    """LM-O scene 29, the second view's candidates turned (:func:`_second_view_turned`): the
    objects place no camera; the images place the second view, and the leftover check gives its
    candidates the first view's poses."""
    from cosy_cli.geometry.poses import invert
    from cosy_cli.multiview import refine_stage

    ds, s, gt, a, b = _second_view_turned(tmp_path)
    quiet = lambda *x, **k: None  # noqa: E731
    summary = refine_stage.main(None, LMO, "test", tmp_path / "m", tmp_path / "r", log=quiet, progress=False)
    doc = json.loads((tmp_path / "r" / "scene.json").read_text())
    (g,) = [x for x in doc["groups"] if x["scene_id"] == s]
    assert not g["objects"] and b in g["unplaced_im_ids"]
    info = g["stats"]["feature_cameras"]["views"][str(b)]
    assert info["used"] and info["unplaced_by_the_objects"] and summary["feature_cameras_used"] >= 1
    assert [c["im_id"] for c in g["feature_only_cameras"]] == [b]
    T_gt = gt_cameras(ds, s, [a, b])
    T_f = np.array(g["feature_only_cameras"][0]["T_world_cam_features"])
    assert angle_deg(T_f[:3, :3], (invert(T_gt[a]) @ T_gt[b])[:3, :3]) < 3.0
    reps = g["leftovers"]["replaced"]
    assert {x["im_id"] for x in reps} == {b} and len(reps) > len(gt[b]) // 2  # 5 of the 7 here
    errs = _replaced_rotation_errors(tmp_path / "r" / "predictions.csv", gt, b, [x["obj_id"] for x in reps])
    assert max(errs) < 10.0, errs


@needs(LMO)
def test_scene_feature_cameras_place_a_view_no_object_placed(tmp_path):
    """The same scene with ``feature_cameras`` "scene": the second view is placed by its image pair
    alone (its camera within 3 deg of the GT's, held in the scene), no longer unplaced, and the
    leftover check fixes its candidates as before."""
    from cosy_cli.geometry.poses import invert
    from cosy_cli.multiview import refine_stage

    ds, s, gt, a, b = _second_view_turned(tmp_path)
    summary = refine_stage.main(refine_stage.resolve_conf(None, feature_cameras="scene"), LMO, "test", tmp_path / "m",
                                tmp_path / "r", log=lambda *x, **k: None, progress=False)
    (g,) = [x for x in json.loads((tmp_path / "r" / "scene.json").read_text())["groups"] if x["scene_id"] == s]
    assert g["unplaced_im_ids"] == [] and g["placed_by"][str(b)].startswith("image features alone")
    info = g["stats"]["feature_cameras"]["views"][str(b)]
    assert info["used"] and info["unplaced_by_the_objects"] and summary["feature_cameras_used"] >= 1
    C = {c["im_id"]: np.array(c["T_world_cam"]) for c in g["cameras"]}
    T_gt = gt_cameras(ds, s, [a, b])
    assert angle_deg((invert(C[a]) @ C[b])[:3, :3], (invert(T_gt[a]) @ T_gt[b])[:3, :3]) < 3.0
    reps = g["leftovers"]["replaced"]
    assert {x["im_id"] for x in reps} == {b} and len(reps) > len(gt[b]) // 2
    errs = _replaced_rotation_errors(tmp_path / "r" / "predictions.csv", gt, b, [x["obj_id"] for x in reps])
    assert max(errs) < 10.0, errs



def test_refine_records_an_image_pair_opencv_refuses_and_goes_on(tmp_path, monkeypatch):
    """When OpenCV raises on an image pair's matches (as 5.1.0's RANSAC did on the demo's), cosy
    refine still refines every group: that pair has no pose, scene.json says why (the OpenCV
    assertion, per view), the summary counts such pairs, and the refined scene is the same as
    without feature cameras (the default uses them only for leftovers)."""
    import cv2

    from cosy_cli.io import bop
    from cosy_cli.multiview import match_stage, refine_stage
    from cosy_cli.synth import candidates as synth_candidates

    data = Path(__file__).resolve().parents[1] / "data_samples"
    quiet = lambda *a, **k: None  # noqa: E731
    synth_candidates.main(data, "test", tmp_path / "all.csv", profile="realistic", seed=7, log=quiet)
    res = bop.read_results(tmp_path / "all.csv", check_rotations=False)
    keep = res.table["scene_id"].to_numpy() == res.table["scene_id"].min()
    t = res.table[keep]
    (tmp_path / "c.csv").write_text(bop.format_results(bop.PoseResults.from_arrays(
        t["scene_id"], t["im_id"], t["obj_id"], t["score"], res.T_cam_obj[keep], t["time"])))
    match_stage.main(match_stage.resolve_conf("paper"), data, "test", tmp_path / "c.csv", tmp_path / "m", log=quiet,
                     progress=False)
    refine_stage.main(refine_stage.resolve_conf(None, feature_cameras="none"), data, "test", tmp_path / "m",
                      tmp_path / "none", log=quiet, progress=False)

    def refuse(*args, **kwargs):
        raise cv2.error("OpenCV(5.1.0) /io/opencv/modules/core/src/mathfuncs.cpp:1601: error: (-215:Assertion "
                        "failed) std::abs(coeffs[n].re) + std::abs(coeffs[n].im) > DBL_EPSILON in function 'solvePoly'\n")

    monkeypatch.setattr(cv2, "findEssentialMat", refuse)
    lines = []
    summary = refine_stage.main(None, data, "test", tmp_path / "m", tmp_path / "r", log=lines.append, progress=False)
    doc = json.loads((tmp_path / "r" / "scene.json").read_text())
    views = [v for g in doc["groups"] for v in g["stats"].get("feature_cameras", {}).get("views", {}).values()]
    refused = [v for v in views if "OpenCV refused" in v.get("no_pose", "")]
    assert refused and all("solvePoly" in v["no_pose"] and not v["used"] and v["inliers"] == 0 for v in refused)
    assert summary["feature_pairs_refused"] == len(refused) and summary["feature_cameras_used"] == 0
    assert "could not estimate a pose from" in lines[-1]
    none = json.loads((tmp_path / "none" / "scene.json").read_text())
    for ga, gb in zip(doc["groups"], none["groups"]):
        assert [o["T_world_obj"] for o in ga["objects"]] == [o["T_world_obj"] for o in gb["objects"]]


def test_refine_skips_image_work_that_cannot_change_its_output(tmp_path, monkeypatch):
    """Exact candidates of one demo scene: every candidate is explained by the refined scene and
    none disagrees with it, so neither the image features (for the leftover check) nor the image
    check's verification renders can change the output: they are not computed (SIFT and the
    verifier would raise here), scene.json says why, and the predictions are those without the
    image check."""
    import cv2

    from cosy_cli.io import bop
    from cosy_cli.multiview import match_stage, refine_stage
    from cosy_cli.singleview.training_free import verify
    from cosy_cli.synth import candidates as synth_candidates

    data = Path(__file__).resolve().parents[1] / "data_samples"
    quiet = lambda *a, **k: None  # noqa: E731
    synth_candidates.main(data, "test", tmp_path / "all.csv", profile="clean", seed=0, log=quiet)
    res = bop.read_results(tmp_path / "all.csv", check_rotations=False)
    keep = res.column("scene_id") == res.column("scene_id").min()
    (tmp_path / "c.csv").write_text(bop.format_results(bop.PoseResults.from_arrays(
        res.column("scene_id")[keep], res.column("im_id")[keep], res.column("obj_id")[keep],
        res.column("score")[keep], res.T_cam_obj[keep], res.column("time")[keep])))
    match_stage.main(match_stage.resolve_conf("paper"), data, "test", tmp_path / "c.csv", tmp_path / "m", log=quiet,
                     progress=False)
    refine_stage.main(refine_stage.resolve_conf(None, image_check="none"), data, "test", tmp_path / "m",
                      tmp_path / "none", log=quiet, progress=False)

    def never(*args, **kwargs):
        raise AssertionError("computed, though it cannot change the output")

    monkeypatch.setattr(cv2, "SIFT_create", never)
    monkeypatch.setattr(verify.Verifier, "score", never)
    summary = refine_stage.main(None, data, "test", tmp_path / "m", tmp_path / "r", log=quiet, progress=False)
    doc = json.loads((tmp_path / "r" / "scene.json").read_text())
    (g,) = doc["groups"]
    assert g["stats"]["feature_cameras"] == {"views": {}, "skipped": refine_stage.FEATURES_SKIPPED}
    assert summary["image_check"]["refined"] > 0 and summary["image_check"]["candidate"] == 0
    a, b = (tmp_path / "r" / "predictions.csv").read_text(), (tmp_path / "none" / "predictions.csv").read_text()
    strip = lambda t: [line.rsplit(",", 1)[0] for line in t.splitlines()]  # noqa: E731  (the time column differs)
    assert strip(a) == strip(b)
