"""Depth refinement of single-view candidates (cosy_cli.singleview.training_free.icp): trimmed point-to-plane ICP
against rendered depth maps of the data_samples objects on a table, and the depth fit score."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cosy_cli.rendering import SceneRenderer  # noqa: I001  (before anything imports OpenGL)

import trimesh  # noqa: E402

from cosy_cli.geometry import (  # noqa: E402
    invert, look_at, make_pose, relative_pose_error, rotation_about_axis, symmetric_distance,
)
from cosy_cli.io.dataset import BopDataset  # noqa: E402
from cosy_cli.objects import ObjectDatabase  # noqa: E402
from cosy_cli.singleview.training_free.icp import DepthRefineResult, IcpConf, depth_fit_score, refine_with_depth  # noqa: E402

SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"
W, H = 320, 240
K = np.array([[416.0, 0.0, 159.5], [0.0, 416.0, 119.5], [0.0, 0.0, 1.0]])  # data_samples' camera at half size
TABLE = 999
ASYM = (4, 6)  # no symmetry
CYLINDER, HEX = 2, 8  # continuous symmetry about z / 12 discrete symmetries


@pytest.fixture(scope="module")
def db():
    return ObjectDatabase.from_models_dir(SAMPLES / "models", obj_ids=[2, 4, 6, 8])


@pytest.fixture(scope="module")
def renderer(db):
    meshes = {o.obj_id: o.mesh for o in db}
    meshes[TABLE] = trimesh.creation.box((2000.0, 2000.0, 10.0))
    r = SceneRenderer(meshes, W, H)
    yield r
    r.close()


def _rz(deg):
    return rotation_about_axis([0.0, 0.0, 1.0], [np.radians(deg)])[0]


def _render_scene(renderer, db, placements, eye):
    """Objects resting on a table (top at world z = 0): placements [(obj_id, x, y, yaw_deg)].
    Returns depth (H, W) mm, the GT poses T_cam_obj (n, 4, 4), visible boxes (n, 4) and the
    visible fraction of each object."""
    T_cam_world = invert(look_at(np.asarray(eye, float), np.zeros(3)))
    ids, T_world = [], []
    for obj_id, x, y, yaw in placements:
        z = -db[obj_id].info.min_xyz[2]
        ids.append(obj_id)
        T_world.append(make_pose(_rz(yaw), [x, y, z]))
    T_cam = T_cam_world @ np.array(T_world)
    table = T_cam_world @ make_pose(np.eye(3), [0.0, 0.0, -5.0])
    out = renderer.render(K, ids + [TABLE], np.concatenate([T_cam, table[None]]), with_rgb=False)
    alone = renderer.render_silhouettes(K, ids, T_cam)
    boxes, visib = [], []
    for i in range(len(ids)):
        rows, cols = np.nonzero(out.instance == i)
        boxes.append([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1])
        visib.append(len(rows) / alone[i].sum())
    return out.depth, np.array(ids), T_cam, np.array(boxes, float), np.array(visib)


def _perturb(T, rng, deg=5.0, mm=8.0, depth_frac=0.05):
    """T_cam_obj rotated by ``deg`` about a random axis (about the object origin), moved ``mm``
    in a random direction and its translation scaled by 1 +- depth_frac."""
    axis = rng.normal(size=3)
    out = T.copy()
    out[:3, :3] = rotation_about_axis(axis / np.linalg.norm(axis), [np.radians(deg)])[0] @ T[:3, :3]
    d = rng.normal(size=3)
    out[:3, 3] = (T[:3, 3] + mm * d / np.linalg.norm(d)) * (1 + depth_frac * rng.choice([-1.0, 1.0]))
    return out


def _err(db, obj_id, T1, T2):
    """Mean model-point distance modulo the object's symmetries (CosyPose's D_l), mm."""
    obj = db[obj_id]
    return float(symmetric_distance(T1[None], T2[None], obj.points, obj.symmetries_with_steps(360))[0])


@pytest.fixture(scope="module")
def scene(renderer, db):
    """Four objects apart on a table, seen from 52 deg above the table at ~0.5 m."""
    placements = [(4, -70, 40, 30), (6, 70, 30, -20), (CYLINDER, -40, -70, 0), (HEX, 60, -70, 10)]
    return _render_scene(renderer, db, placements, eye=(0.0, -320.0, 400.0))


def test_recovers_perturbed_poses(scene, db):
    depth, ids, T_gt, boxes, _ = scene
    rng = np.random.default_rng(1)
    rows = [i for i, o in enumerate(ids) if o in ASYM for _ in range(3)]  # three hypotheses per box
    T0 = np.array([_perturb(T_gt[i], rng) for i in rows])
    res = refine_with_depth(depth, K, boxes[rows], ids[rows], T0, db)
    assert isinstance(res, DepthRefineResult)
    assert res.T_cam_obj.shape == (len(rows), 4, 4) and res.ok.shape == (len(rows),)
    assert res.ok.all()
    for k, i in enumerate(rows):
        diam = db[ids[i]].diameter
        before, after = _err(db, ids[i], T0[k], T_gt[i]), _err(db, ids[i], res.T_cam_obj[k], T_gt[i])
        assert before > 0.1 * diam
        assert after < 0.02 * diam, (ids[i], before, after)
        dr, dt = relative_pose_error(res.T_cam_obj[k], T_gt[i])
        assert dr < 1.0 and dt < 2.0
    assert np.all(res.rmse_mm < 1.0)  # exact rendered depth
    assert np.all(res.fit_score > 0.9) and np.all(res.inlier_frac > 0.8)
    assert np.all((res.inlier_frac >= 0) & (res.inlier_frac <= res.fit_score + 1e-12))
    # deterministic
    again = refine_with_depth(depth, K, boxes[rows], ids[rows], T0, db)
    np.testing.assert_array_equal(again.T_cam_obj, res.T_cam_obj)


def test_without_depth_alignment_only_small_errors_are_fixed(scene, db):
    depth, ids, T_gt, boxes, _ = scene
    i = int(np.flatnonzero(ids == 6)[0])
    rng = np.random.default_rng(2)
    T_small = _perturb(T_gt[i], rng, deg=3.0, mm=4.0, depth_frac=0.0)
    res = refine_with_depth(depth, K, boxes[[i]], ids[[i]], T_small[None], db, IcpConf(align_depth=False))
    assert res.ok[0] and _err(db, 6, res.T_cam_obj[0], T_gt[i]) < 0.02 * db[6].diameter


def test_symmetric_objects(scene, db):
    depth, ids, T_gt, boxes, _ = scene
    rng = np.random.default_rng(3)
    rows = [i for i, o in enumerate(ids) if o in (CYLINDER, HEX) for _ in range(2)]
    T0 = np.array([_perturb(T_gt[i], rng) for i in rows])
    res = refine_with_depth(depth, K, boxes[rows], ids[rows], T0, db)
    assert res.ok.all()  # the divergence check works modulo symmetries: sliding about the axis is fine
    for k, i in enumerate(rows):
        after = _err(db, ids[i], res.T_cam_obj[k], T_gt[i])
        assert after < 0.02 * db[ids[i]].diameter, (ids[i], after)


def test_occluded_object(renderer, db):
    # object 6 stands in front of object 4, seen from a low camera
    depth, ids, T_gt, boxes, visib = _render_scene(renderer, db, [(4, 0, 40, 25), (6, 15, -45, -10)],
                                                   eye=(0.0, -420.0, 200.0))
    assert 0.3 < visib[0] < 0.8 and visib[1] > 0.99
    rng = np.random.default_rng(4)
    T0 = np.array([_perturb(T_gt[0], rng) for _ in range(3)])
    res = refine_with_depth(depth, K, boxes[[0, 0, 0]], ids[[0, 0, 0]], T0, db)
    assert res.ok.all()
    for k in range(3):
        assert _err(db, 4, res.T_cam_obj[k], T_gt[0]) < 0.03 * db[4].diameter
    # the occluder's depth is in front of the hidden part: it counts as occluded, not as a violation
    fit = depth_fit_score(depth, K, [4], T_gt[:1], db)
    assert fit[0] > 0.95
    assert res.inlier_frac.max() < 0.9  # ... but the hidden part does not support the pose


def test_divergence_keeps_input_pose(scene, db):
    depth, ids, T_gt, boxes, _ = scene
    i = int(np.flatnonzero(ids == 4)[0])
    rng = np.random.default_rng(5)
    # a hopeless start: two diameters beside the object and turned 60 deg
    hopeless = _perturb(T_gt[i], rng, deg=60.0, mm=0.0, depth_frac=0.0)
    hopeless[:3, 3] += [2 * db[4].diameter, 0.0, 0.0]
    # a good start, but a check that allows no rotation change
    fine = _perturb(T_gt[i], rng)
    T0 = np.array([hopeless, fine])
    res = refine_with_depth(depth, K, boxes[[i]], ids[[i]], T0[:1], db)
    assert not res.ok[0]
    np.testing.assert_array_equal(res.T_cam_obj[0], hopeless)
    res = refine_with_depth(depth, K, boxes[[i]], ids[[i]], T0[1:], db, IcpConf(max_rotation_deg=1.0))
    assert not res.ok[0]
    np.testing.assert_array_equal(res.T_cam_obj[0], fine)
    res = refine_with_depth(depth, K, boxes[[i]], ids[[i]], T0[1:], db, IcpConf(min_inliers=10**6))
    assert not res.ok[0]
    np.testing.assert_array_equal(res.T_cam_obj[0], fine)


def test_depth_fit_score(scene, db):
    depth, ids, T_gt, boxes, _ = scene
    rng = np.random.default_rng(6)
    wrong = np.array([_perturb(T, rng, deg=10.0, mm=10.0, depth_frac=0.0) for T in T_gt])
    s_true = depth_fit_score(depth, K, ids, T_gt, db)
    s_wrong = depth_fit_score(depth, K, ids, wrong, db)
    assert s_true.shape == (len(ids),)
    assert np.all(s_true > 0.95)
    assert np.all(s_wrong < s_true - 0.3)
    assert np.all((s_wrong >= 0) & (s_wrong <= 1))
    # a tolerance of a few diameters accepts anything in front of the table
    assert np.all(depth_fit_score(depth, K, ids, wrong, db, tol_mm=500.0) > 0.95)
    # a model floating in front of the camera hides observed surface: violations
    floating = T_gt.copy()
    floating[:, :3, 3] *= 0.7
    assert np.all(depth_fit_score(depth, K, ids, floating, db) < 0.05)
    # a model behind the table is occluded everywhere: nothing left to judge
    behind = T_gt.copy()
    behind[:, :3, 3] *= 1.5
    assert np.all(depth_fit_score(depth, K, ids, behind, db) == 0.0)


def test_no_depth(scene, db):
    _, ids, T_gt, boxes, _ = scene
    res = refine_with_depth(np.zeros((H, W), np.float32), K, boxes, ids, T_gt, db)
    assert not res.ok.any()
    np.testing.assert_array_equal(res.T_cam_obj, T_gt)
    assert np.all(res.fit_score == 0) and np.all(res.inlier_frac == 0) and np.all(np.isnan(res.rmse_mm))
    empty = refine_with_depth(np.zeros((H, W)), K, np.zeros((0, 4)), [], np.zeros((0, 4, 4)), db)
    assert empty.T_cam_obj.shape == (0, 4, 4) and empty.ok.shape == (0,)
    # boxes outside the image, NaN poses
    bad = T_gt[:2].copy()
    bad[1] = np.nan
    res = refine_with_depth(np.ones((H, W)) * 500, K, [[-50, -50, -10, -10], boxes[1]], ids[:2], bad, db)
    assert not res.ok.any()


def test_real_sample_image(db):
    """data_samples scene 1, image 0 (synthetic depth, 0.1 mm steps): perturbed GT poses of the
    four loaded objects come back to a fraction of their error."""
    ds = BopDataset(SAMPLES)
    cam = ds.scene_camera(1)[0]
    depth = ds.read_depth(1, 0)
    gts = [(g, info) for g, info in zip(ds.scene_gt(1)[0], ds.scene_gt_info(1)[0]) if g.obj_id in db]
    rng = np.random.default_rng(7)
    T_gt = np.array([g.T_cam_obj for g, _ in gts])
    ids = np.array([g.obj_id for g, _ in gts])
    boxes = np.array([[x, y, x + w, y + h] for x, y, w, h in (info.bbox_visib for _, info in gts)], float)
    T0 = np.array([_perturb(T, rng) for T in T_gt])
    res = refine_with_depth(depth, cam.K, boxes, ids, T0, db)
    before = np.array([_err(db, o, a, b) / db[o].diameter for o, a, b in zip(ids, T0, T_gt)])
    after = np.array([_err(db, o, a, b) / db[o].diameter for o, a, b in zip(ids, res.T_cam_obj, T_gt)])
    assert res.ok.all()
    assert np.median(after) < 0.01 and np.all(after < 0.5 * before)
