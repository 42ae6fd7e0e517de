"""cosy evaluate: pose errors vs. brute force, BOP19 scores vs. a literal re-implementation of the
toolkit's loops (eval_calc_errors / pose_matching / score), CosyPose AUC, bad inputs."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import trimesh
from click.testing import CliRunner

from cosy_cli.cli.main import cli
from cosy_cli.errors import CosyError
from cosy_cli.evaluation import evaluate_stage, pose_error as pe, protocols
from cosy_cli.geometry.poses import make_pose
from cosy_cli.geometry.rotations import random_rotations, rotation_about_axis
from cosy_cli.io import bop, images
from cosy_cli.io.dataset import BopDataset
from cosy_cli.objects import continuous_steps_for_max_step, symmetry_set

W, H = 80, 60
K = np.array([[200.0, 0, 39.5], [0, 200.0, 29.5], [0, 0, 1]])
TH = np.arange(0.05, 0.51, 0.05)


def rot(axis, deg):
    return rotation_about_axis(np.asarray(axis, float), np.radians([deg]))[0]


# --------------------------------------------------------------------------------------------
# brute-force references (loops, written from the definitions)
# --------------------------------------------------------------------------------------------
def bf_mssd(Te, Tg, P, S):
    best = np.inf
    for s in S:
        A = Te[:3, :3] @ P.T + Te[:3, 3:4]
        B = (Tg @ s)[:3, :3] @ P.T + (Tg @ s)[:3, 3:4]
        best = min(best, np.linalg.norm(A - B, axis=0).max())
    return best


def bf_proj(T, P):
    x = K @ (T[:3, :3] @ P.T + T[:3, 3:4])
    return (x[:2] / x[2]).T


def bf_mspd(Te, Tg, P, S):
    return min(np.linalg.norm(bf_proj(Te, P) - bf_proj(Tg @ s, P), axis=1).max() for s in S)


def bf_adi(Te, Tg, P):
    A = (Te[:3, :3] @ P.T + Te[:3, 3:4]).T
    B = (Tg[:3, :3] @ P.T + Tg[:3, 3:4]).T
    return np.mean([np.min(np.linalg.norm(A - b, axis=1)) for b in B])


def bf_vsd(d_est, d_gt, d_test, delta, taus, diameter):
    """Pixel loop over the definition (distance images, bop19 visibility, step cost)."""
    def dist(d, v, u):
        x, y = (u - K[0, 2]) / K[0, 0] * d, (v - K[1, 2]) / K[1, 1] * d
        return math.sqrt(x * x + y * y + d * d)
    out = []
    for tau in taus:
        union = inter_bad = comp = 0
        for v in range(d_test.shape[0]):
            for u in range(d_test.shape[1]):
                dt, dg, de = dist(float(d_test[v, u]), v, u), dist(float(d_gt[v, u]), v, u), dist(float(d_est[v, u]), v, u)
                vg = dg > 0 and (np.float32(dg) - np.float32(dt) <= delta or dt == 0)
                ve = de > 0 and ((np.float32(de) - np.float32(dt) <= delta or dt == 0) or vg)
                if vg or ve:
                    union += 1
                    if vg and ve:
                        inter_bad += abs(dg - de) / diameter >= tau
                    else:
                        comp += 1
        out.append(1.0 if union == 0 else (inter_bad + comp) / union)
    return np.array(out)


# --------------------------------------------------------------------------------------------
# the hand-built dataset
# --------------------------------------------------------------------------------------------
def _models():
    """obj 1: cube (20 mm) whose origin is 100 mm off its centre, 180-degree symmetry about z through
    the centre (carries a 200 mm translation); obj 2: cylinder with a continuous symmetry about an
    off-origin axis and a flip; obj 3: asymmetric box."""
    c1 = np.array([100.0, 0, 0])
    m1 = trimesh.creation.box(extents=(20, 20, 20))
    m1.apply_translation(c1)
    S1 = make_pose(np.diag([-1.0, -1, 1]), c1 - np.diag([-1.0, -1, 1]) @ c1)
    c2 = np.array([0.0, 10, 0])
    m2 = trimesh.creation.cylinder(radius=15, height=40, sections=24)
    m2.apply_translation(c2)
    F2 = make_pose(np.diag([1.0, -1, -1]), c2 - np.diag([1.0, -1, -1]) @ c2)
    m3 = trimesh.creation.box(extents=(30, 20, 10))
    m3.apply_translation((5, 0, 0))
    return {
        1: (m1, [S1], []),
        2: (m2, [F2], [{"axis": np.array([0.0, 0, 1]), "offset": c2}]),
        3: (m3, [], []),
    }


def _pose(R, centre_cam, c_model):
    return make_pose(R, np.asarray(centre_cam, float) - R @ np.asarray(c_model, float))


CENTRES = {1: (100.0, 0, 0), 2: (0.0, 10, 0), 3: (5.0, 0, 0)}

# scene -> depth_scale, images: im_id -> [(obj_id, R, centre in camera (mm), visib_fract)]
SCENES = {
    1: (1.0, {
        0: [(1, rot([0, 0, 1], 20), (-40, -20, 500), 0.9), (1, rot([1, 1, 0], 40), (40, -20, 520), 0.6),
            (2, rot([1, 0, 0], 30), (-40, 30, 480), 0.8), (3, rot([0, 1, 0], 15), (40, 30, 510), 0.05)],
        5: [(2, rot([0, 1, 1], 50), (-30, 0, 450), 0.7), (3, rot([1, 0, 0], 60), (35, 0, 470), 0.9)],
    }),
    3: (0.1, {
        2: [(1, rot([1, 0, 1], 70), (-30, 0, 500), 0.95), (3, rot([0, 0, 1], 80), (35, 5, 480), 0.5)],
        17: [(1, rot([0, 1, 0], 10), (-35, -10, 490), 0.04), (1, rot([0, 0, 1], 45), (30, 10, 500), 0.7),
             (3, rot([1, 1, 1], 30), (0, 25, 530), 0.3)],
    }),
}
TARGETS = [(1, 0, 1, 2), (1, 0, 2, 1), (1, 5, 2, 1), (1, 5, 3, 1), (3, 2, 1, 1), (3, 2, 3, 1), (3, 17, 1, 1),
           (3, 17, 3, 1)]


def _gt_pose(scene, im, k):
    o, R, c, _ = SCENES[scene][1][im][k]
    return _pose(R, c, CENTRES[o])


def _predictions():
    """(scene, im, obj, score, T) rows; the comments say what each one tests."""
    models = _models()
    S1 = models[1][1][0]
    F2 = models[2][1][0]
    shift = lambda T, v: make_pose(T[:3, :3], T[:3, 3] + np.asarray(v, float))  # noqa: E731
    c2 = np.array(CENTRES[2])
    spin2 = _pose(rot([0, 0, 1], 57.3), c2, c2)  # continuous symmetry of obj 2 by 1 rad
    rows = [
        (1, 0, 1, 0.9, _gt_pose(1, 0, 0)),  # e0 exact
        (1, 0, 1, 0.8, shift(_gt_pose(1, 0, 1), (0, 0, 7))),  # e1: 7 mm along z
        (1, 0, 1, 0.1, shift(_gt_pose(1, 0, 0), (0, 60, 0))),  # e2: beyond inst_count (dropped)
        (1, 0, 2, 0.7, shift(_gt_pose(1, 0, 2) @ spin2, (3, 0, 0))),  # e3: symmetric + 3 mm
        (1, 0, 3, 0.9, _gt_pose(1, 0, 3)),  # e4: object of the image that is not a target
        (1, 5, 2, 0.5, _gt_pose(1, 5, 0) @ F2),  # e5: discrete flip of obj 2
        (1, 5, 3, 0.6, _gt_pose(1, 5, 1) @ _pose(rot([0, 0, 1], 10), CENTRES[3], CENTRES[3])),  # e6: 10 deg
        (1, 5, 1, 0.9, _gt_pose(1, 0, 0)),  # e7: object absent from the image
        (3, 2, 1, 0.8, _gt_pose(3, 2, 0) @ S1),  # e8: symmetric pose, origin moved 200 mm (sphere shortcut)
        (3, 2, 3, 0.4, shift(_gt_pose(3, 2, 1), (0, 0, 7))),  # e9: tie on score with e10, first in file
        (3, 2, 3, 0.4, shift(_gt_pose(3, 2, 1), (12, 0, 0))),  # e10: dropped by the tie rule
        (3, 17, 1, 0.9, _gt_pose(3, 17, 0)),  # e11: exact pose of the invalid (4 % visible) instance
        (3, 17, 3, 0.3, shift(_gt_pose(3, 17, 2), (20, 0, 0))),  # e12: 20 mm off
    ]
    return rows


def make_dataset(root: Path, with_depth=True, with_targets=True) -> Path:
    from cosy_cli.rendering import SceneRenderer

    root.mkdir(parents=True, exist_ok=True)
    bop.write_camera(root / "camera.json", bop.CameraInfo(K=K, width=W, height=H))
    models = _models()
    infos = {}
    for sub in ("models", "models_eval"):
        for o, (m, disc, cont) in models.items():
            (root / sub).mkdir(exist_ok=True)
            m.export(root / sub / f"obj_{o:06d}.ply")
            V = np.asarray(m.vertices)
            from cosy_cli.objects import diameter_of
            infos[o] = bop.ModelInfo(diameter_of(V), V.min(0), V.max(0) - V.min(0),
                                     np.array(disc) if disc else np.zeros((0, 4, 4)), cont)
        bop.write_models_info(root / sub / "models_info.json", infos)
    with SceneRenderer({o: m for o, (m, _, _) in models.items()}, W, H) as ren:
        for scene, (scale, ims) in SCENES.items():
            d = root / "test" / f"{scene:06d}"
            cams, gts, info = {}, {}, {}
            for im, insts in ims.items():
                cams[im] = bop.SceneCamera(K=K, depth_scale=scale, T_cam_world=make_pose(rot([1, 0, 0], 5 * im), (im, 0, 0)))
                gts[im] = [bop.GtInstance(o, _gt_pose(scene, im, k)) for k, (o, *_r) in enumerate(insts)]
                info[im] = [bop.GtInfo(np.zeros(4), np.zeros(4), 100, 100, int(100 * v), v) for (*_r, v) in insts]
                out = ren.render(K, [g.obj_id for g in gts[im]], np.stack([g.T_cam_obj for g in gts[im]]), with_rgb=True)
                images.write_rgb(d / "rgb" / f"{im:06d}.png", out.rgb)
                if with_depth:
                    images.write_depth(d / "depth" / f"{im:06d}.png", out.depth, scale)
            bop.write_scene_camera(d / "scene_camera.json", cams)
            bop.write_scene_gt(d / "scene_gt.json", gts)
            bop.write_scene_gt_info(d / "scene_gt_info.json", info)
    if with_targets:
        bop.write_targets(root / "test_targets_bop19.json",
                          pd.DataFrame(TARGETS, columns=["scene_id", "im_id", "obj_id", "inst_count"]))
    rows = _predictions()
    res = bop.PoseResults.from_arrays([r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows],
                                      [r[3] for r in rows], np.stack([r[4] for r in rows]))
    bop.write_results(root / "pred.csv", res)
    return root


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("evalds") / "ds")


@pytest.fixture(scope="module")
def evaluated(dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("evalout") / "eval"
    scores = evaluate_stage.main("bop19", dataset, "test", dataset / "pred.csv", out, log=lambda *_: None,
                                 progress=False)
    return out, scores, pd.read_csv(out / "errors.csv")


# --------------------------------------------------------------------------------------------
# metric functions
# --------------------------------------------------------------------------------------------
def test_metric_functions_against_brute_force():
    rng = np.random.default_rng(0)
    m, disc, cont = _models()[2]
    P = np.asarray(m.vertices)
    S = symmetry_set(np.array(disc), cont, continuous_steps_for_max_step(0.01))
    assert len(S) == 2 * 315
    R = random_rotations(6, rng)
    Tg = np.stack([make_pose(r, rng.normal(0, 30, 3) + (0, 0, 500)) for r in R])
    Te = np.stack([T @ make_pose(rot(rng.normal(size=3), rng.uniform(0, 40)), rng.normal(0, 8, 3)) for T in Tg])
    ms, mp, ad = pe.mssd(Te, Tg, P, S), pe.mspd(Te, Tg, K, P, S), pe.adi(Te, Tg, P)
    for i in range(len(Tg)):
        assert ms[i] == pytest.approx(bf_mssd(Te[i], Tg[i], P, S), abs=1e-9)
        assert mp[i] == pytest.approx(bf_mspd(Te[i], Tg[i], P, S), abs=1e-9)
        assert ad[i] == pytest.approx(bf_adi(Te[i], Tg[i], P), abs=1e-9)
    # hand-derived: a 7 mm shift along z; a symmetric pose; a 30-degree rotation
    T7 = Tg[0].copy()
    T7[2, 3] += 7
    assert pe.te(T7, Tg[0])[0] == pytest.approx(7)
    assert pe.add(T7, Tg[0], P)[0] == pytest.approx(7)
    assert pe.mssd(T7, Tg[0], P, S)[0] == pytest.approx(7)
    assert pe.adi(T7, Tg[0], P)[0] <= 7 + 1e-9
    assert pe.re(T7, Tg[0])[0] == pytest.approx(0, abs=1e-6)
    Ts = Tg[0] @ S[100]
    assert pe.mssd(Ts, Tg[0], P, S)[0] == pytest.approx(0, abs=1e-9)
    assert pe.mspd(Ts, Tg[0], K, P, S)[0] == pytest.approx(0, abs=1e-9)
    assert pe.add(Ts, Tg[0], P)[0] > 1
    assert pe.re(make_pose(rot([1, 2, 3], 30), np.zeros(3)), np.eye(4))[0] == pytest.approx(30)


def test_vsd_against_pixel_loop(dataset):
    from cosy_cli.rendering import SceneRenderer

    ds = BopDataset(dataset, "test")
    db = evaluate_stage.load_models(ds, None, print)[0]
    depth = ds.read_depth(3, 2)
    Tg = _gt_pose(3, 2, 1)
    with SceneRenderer({3: db[3].mesh}, W, H) as ren:
        dg = ren.render(K, [3], Tg[None], with_rgb=False).depth
        for dT in (np.zeros(3), (0, 0, 6), (4, 2, 0)):
            Te = make_pose(Tg[:3, :3], Tg[:3, 3] + dT)
            de = ren.render(K, [3], Te[None], with_rgb=False).depth
            got = pe.vsd(de, dg, depth, K, 15, protocols.BOP19_VSD_TAUS, diameter=db[3].diameter)
            assert np.allclose(got, bf_vsd(de, dg, depth, 15, protocols.BOP19_VSD_TAUS, db[3].diameter), atol=1e-12)
    assert got.max() > 0  # the shifted pose is not perfect
    # sphere-projection shortcut: far apart in the image -> no overlap
    assert not pe.sphere_projections_overlap((300, 0, 500), (-300, 0, 500), 20)[0]
    assert pe.sphere_projections_overlap((10, 0, 500), (-10, 0, 500), 20)[0]


def test_auc_posecnn_hand_values():
    # errors 0.01, 0.02 m, two failures: right-end steps 0.01*0.25 + 0.01*0.5 + 0.08*0.5 = 0.0475 -> x10
    assert protocols.auc_posecnn([0.01, 0.02, np.inf, 0.2]) == pytest.approx(0.475)
    assert protocols.auc_posecnn([0.0, 0.0]) == pytest.approx(1.0)
    assert protocols.auc_posecnn([0.05]) == pytest.approx(1.0)  # right-end step: counted from 0, not from 0.05
    assert math.isnan(protocols.auc_posecnn([0.2, np.inf]))
    # duplicates keep the accuracy of the first copy on the interval that ends there
    assert protocols.auc_posecnn([0.01, 0.01]) == pytest.approx(10 * (0.01 * 0.5 + 0.09 * 1.0))


def test_greedy_match_toolkit_order():
    E = np.array([[0.2, 0.1], [0.05, 0.3]])
    assert protocols.greedy_match(E, 0.25).tolist() == [1, 0]
    assert protocols.greedy_match(E, 0.15).tolist() == [1, 0]
    assert protocols.greedy_match(E, 0.1).tolist() == [-1, 0]  # strict threshold
    assert protocols.greedy_match(np.array([[0.1, 0.1]]), 0.5).tolist() == [0]  # ties: first GT


# --------------------------------------------------------------------------------------------
# the toolkit's loops, literally (eval_calc_errors + eval_calc_scores + pose_matching + score)
# --------------------------------------------------------------------------------------------
def toolkit_recalls(ds_root: Path, errors_fn, thresholds, width=W):
    """errors_fn(est_row, scene, im, gt_id) -> normalised error. Returns the recall per threshold."""
    ds = BopDataset(ds_root, "test")
    targets = json.loads((ds_root / "test_targets_bop19.json").read_text())
    res = bop.read_results(ds_root / "pred.csv")
    ests = {}
    for i, r in enumerate(res.table.itertuples()):
        ests.setdefault(r.scene_id, {}).setdefault(r.im_id, {}).setdefault(r.obj_id, []).append((i, r.score))
    targets_org = {}
    for t in targets:
        targets_org.setdefault(t["scene_id"], {}).setdefault(t["im_id"], {})[t["obj_id"]] = t
    recalls = []
    for th in thresholds:
        tps = tars = 0
        for scene_id, st in targets_org.items():
            gt = ds.scene_gt(scene_id)
            info = ds.scene_gt_info(scene_id)
            for im_id, im_targets in st.items():
                # valid GT: inst_count most visible per target object
                order = sorted(range(len(gt[im_id])), key=lambda g: info[im_id][g].visib_fract, reverse=True)
                to_add = {o: t["inst_count"] for o, t in im_targets.items()}
                valid = [False] * len(gt[im_id])
                for g in order:
                    o = gt[im_id][g].obj_id
                    if o in to_add and to_add[o] > 0:
                        valid[g] = True
                        to_add[o] -= 1
                tars += sum(valid)
                for obj_id, t in im_targets.items():
                    obj_ests = ests.get(scene_id, {}).get(im_id, {}).get(obj_id, [])
                    obj_ests = sorted(obj_ests, key=lambda x: x[1], reverse=True)[:t["inst_count"]]
                    matched = []
                    for est_row, _ in obj_ests:
                        best, best_e = -1, th
                        for g, inst in enumerate(gt[im_id]):
                            if inst.obj_id != obj_id or not valid[g] or g in matched:
                                continue
                            e = errors_fn(est_row, scene_id, im_id, g)
                            if e < best_e:
                                best, best_e = g, e
                        if best >= 0:
                            matched.append(best)
                            tps += 1
        recalls.append(tps / tars)
    return np.array(recalls)


def test_bop19_scores_match_toolkit_loops(dataset, evaluated):
    out, scores, err = evaluated
    ds = BopDataset(dataset, "test")
    db = evaluate_stage.load_models(ds, None, print)[0]
    res = bop.read_results(dataset / "pred.csv")
    steps = continuous_steps_for_max_step(0.01)

    def T_gt(scene, im, g):
        return ds.scene_gt(scene)[im][g].T_cam_obj

    def mssd_n(e, scene, im, g):
        o = int(res.table["obj_id"][e])
        Te, Tg = res.T_cam_obj[e], T_gt(scene, im, g)
        if np.linalg.norm(Te[:3, 3] - Tg[:3, 3]) >= db[o].diameter:  # the sphere shortcut
            return np.inf
        return bf_mssd(Te, Tg, db[o].vertices, db[o].symmetries_with_steps(steps)) / db[o].diameter

    def mspd_n(e, scene, im, g):
        o = int(res.table["obj_id"][e])
        return bf_mspd(res.T_cam_obj[e], T_gt(scene, im, g), db[o].vertices,
                       db[o].symmetries_with_steps(steps)) * 640.0 / W

    r_mssd = toolkit_recalls(dataset, mssd_n, TH)
    r_mspd = toolkit_recalls(dataset, mspd_n, np.arange(5, 51, 5))
    assert scores["bop19_average_recall_mssd"] == pytest.approx(r_mssd.mean(), abs=1e-12)
    assert scores["bop19_average_recall_mspd"] == pytest.approx(r_mspd.mean(), abs=1e-12)
    # hand-derived facts: 9 targets (two obj-1 instances in image 0; obj 3 of image 0 is 5 % visible and
    # not a target; image 17 counts one of its two obj-1 instances)
    assert scores["bop19"]["counts"]["targets"] == 9
    # e8 is a perfect symmetric pose whose origin moved 200 mm: MSPD finds it, MSSD (shortcut) does not
    r8 = err[err.est_index == 8].iloc[0]
    assert r8["mssd"] == pytest.approx(0, abs=1e-6) and r8["te"] == pytest.approx(200, abs=1e-4)
    assert r8["mspd"] == pytest.approx(0, abs=1e-4)
    # by hand, MSSD at 0.5 d: e0, e1 (7/34.6), e3 (3/50), e5 (0), e6 (3.1/37.4), e9 (7/37.4) = 6 of 9;
    # e8 is cut by the shortcut, e11 matches only the invalid instance, e12 is at 20/37.4 = 0.53;
    # MSPD at 50 px (x 640/80): the same plus e8 = 7 of 9; at 0.2 d e1 (0.202) fails: 5 of 9
    c = scores["bop19"]["curves"]
    assert c["mssd"]["recall"][-1] == pytest.approx(6 / 9) and c["mspd"]["recall"][-1] == pytest.approx(7 / 9)
    assert c["mssd"]["recall"][3] == pytest.approx(5 / 9) and c["mssd"]["recall"][4] == pytest.approx(6 / 9)
    # e1 against instance 1: exactly 7 mm along z
    r1 = err[(err.est_index == 1) & (err.gt_index == 1)].iloc[0]
    assert (r1["te"], r1["add"], r1["mssd"]) == pytest.approx((7, 7, 7), abs=1e-5)
    # e7 (object absent from its image) has no row; e4 (not a target) has one
    assert 7 not in set(err.est_index) and 4 in set(err.est_index)
    # VSD: the toolkit's loops over our rendered depths and a pixel-loop VSD
    from cosy_cli.rendering import SceneRenderer

    vsd_cache = {}
    with SceneRenderer({o: db[o].mesh for o in db.obj_ids}, W, H) as ren:
        def vsd_n(e, scene, im, g, k):
            key = (e, scene, im, g)
            if key not in vsd_cache:
                o = int(res.table["obj_id"][e])
                Te, Tg = res.T_cam_obj[e], T_gt(scene, im, g)
                if not pe.sphere_projections_overlap(Te[:3, 3], Tg[:3, 3], db[o].diameter / 2)[0]:
                    vsd_cache[key] = np.ones(10)
                else:
                    de = ren.render(K, [o], Te[None], with_rgb=False).depth
                    dg = ren.render(K, [o], Tg[None], with_rgb=False).depth
                    vsd_cache[key] = bf_vsd(de, dg, ds.read_depth(scene, im), 15, protocols.BOP19_VSD_TAUS,
                                            db[o].diameter)
            return vsd_cache[key][k]

        r_vsd = [toolkit_recalls(dataset, lambda e, s, i, g, k=k: vsd_n(e, s, i, g, k), TH) for k in range(10)]
    assert scores["bop19_average_recall_vsd"] == pytest.approx(np.mean(r_vsd), abs=1e-12)
    assert scores["bop19_average_recall"] == pytest.approx(np.mean([np.mean(r_vsd), r_mssd.mean(), r_mspd.mean()]),
                                                           abs=1e-12)
    # VSD filled only for the pairs BOP19 uses (e2 beyond inst_count, e4 not a target: empty)
    vcols = [c for c in err.columns if c.startswith("vsd_tau_")]
    assert len(vcols) == 10
    assert err.loc[err.est_index.isin([2, 4, 10]), vcols].isna().all().all()
    assert err.loc[err.est_index == 0, vcols].notna().any().any()


def test_auc_protocol(dataset, evaluated):
    out, scores, err = evaluated
    ds = BopDataset(dataset, "test")
    db = evaluate_stage.load_models(ds, None, print)[0]
    res = bop.read_results(dataset / "pred.csv")
    # top-1 per (scene, image, object), matched to its closest GT (ADD-S), every GT instance of the
    # target images counts (also obj 3 of image 0, 5 % visible)
    per_obj = {}
    hits, pairs = 0, set()
    for scene, (_, ims) in SCENES.items():
        for im, insts in ims.items():
            for g, (o, *_r) in enumerate(insts):
                pairs.add((scene, im, o))
            for o in set(i[0] for i in insts):
                rows = [i for i, r in enumerate(res.table.itertuples())
                        if (r.scene_id, r.im_id, r.obj_id) == (scene, im, o)]
                gts = [g for g, i in enumerate(insts) if i[0] == o]
                errs = {g: np.inf for g in gts}
                if rows:
                    e = max(rows, key=lambda i: (res.table["score"][i], -i))
                    d = {g: bf_adi(res.T_cam_obj[e], _gt_pose(scene, im, g), db[o].vertices) for g in gts}
                    g_best = min(gts, key=lambda g: (d[g], g))
                    errs[g_best] = d[g_best]
                for g in gts:
                    per_obj.setdefault(o, []).append(errs[g])
                    hits += errs[g] < 0.1 * db[o].diameter
    auc = {o: protocols.auc_posecnn(np.array(v) / 1000) for o, v in per_obj.items()}
    assert scores["auc_adds"] == pytest.approx(np.nanmean(list(auc.values())), abs=1e-9)
    for o in auc:
        assert scores["per_object"][str(o)]["auc_adds"] == pytest.approx(auc[o], abs=1e-9)
    assert scores["recall_adds_0.1d"] == pytest.approx(hits / len(pairs), abs=1e-12)
    # ADD(-S): obj 3 has no symmetry -> ADD; here e6 rotates obj 3 by 10 degrees, so ADD > ADD-S
    assert scores["per_object"]["3"]["auc_add_or_adds"] < scores["per_object"]["3"]["auc_adds"]
    assert scores["per_object"]["1"]["auc_add_or_adds"] == scores["per_object"]["1"]["auc_adds"]
    # outputs
    for f in evaluate_stage.OUTPUT_FILES:
        assert (out / f).is_file()
    curves = pd.read_csv(out / "curves.csv")
    assert set(curves.metric) >= {"adds_top1", "bop19_mssd", "bop19_mspd", "bop19_vsd"}


def _camera_group(scene_id: int, group_id: int, cameras: dict) -> dict:
    """A scene.json group without objects: im_id -> T_world_cam (None: not placed)."""
    return {"scene_id": scene_id, "group_id": group_id, "objects": [],
            "cameras": [{"im_id": im, "T_world_cam": None if T is None else np.asarray(T).tolist()}
                        for im, T in cameras.items()]}


def _evaluate_scene_json(root: Path, tmp_path: Path, doc: dict) -> tuple[Path, dict]:
    """``doc`` written as scene.json, and the scores of evaluating root's pred.csv with it."""
    sj = tmp_path / "scene.json"
    sj.write_text(json.dumps(doc))
    return sj, evaluate_stage.main("bop19", root, "test", root / "pred.csv", tmp_path / "ev", scene_json=sj,
                                   metrics="auc", log=lambda *_: None, progress=False)


def test_scene_json_camera_errors(dataset, tmp_path):
    ds = BopDataset(dataset, "test")
    cam = ds.scene_camera(3)
    T0 = np.linalg.inv(cam[2].T_cam_world)
    T1 = np.linalg.inv(cam[17].T_cam_world)
    T1_bad = T1 @ make_pose(rot([0, 0, 1], 3), (0, 5, 0))  # 3 degrees and 5 mm off, relative to view 2
    world = make_pose(rot([1, 2, 0], 33), (100, -50, 20))  # the reconstruction's own world frame
    doc = {"groups": [_camera_group(3, 0, {2: world @ T0, 17: world @ T1_bad}),
                      _camera_group(1, 1, {0: np.eye(4), 5: None})]}
    sj, s = _evaluate_scene_json(dataset, tmp_path, doc)
    c = s["cameras"]
    assert c["views"] == 4 and c["views_placed"] == 3 and c["fraction_views_placed"] == 0.75
    assert c["pairs"] == 1 and c["reference"] == "scene_camera"
    assert c["rot_err_deg_mean"] == pytest.approx(3, abs=1e-6)
    assert c["trans_err_mm_mean"] == pytest.approx(5, abs=1e-6)
    assert "bop19_average_recall" not in s
    # the cosy refine layout: placed cameras listed, the others in unplaced_im_ids
    doc["groups"][1]["cameras"] = doc["groups"][1]["cameras"][:1]
    doc["groups"][1]["unplaced_im_ids"] = [5]
    sj.write_text(json.dumps(doc))
    groups = evaluate_stage.parse_scene_json(sj, ds)
    assert groups[1]["im_ids"] == [0, 5] and list(groups[1]["placed"]) == [0]
    assert protocols.camera_pose_errors(groups, {(3, 2): cam[2].T_cam_world, (3, 17): cam[17].T_cam_world})[
        "fraction_views_placed"] == 0.75
    doc["groups"][0]["cameras"][0]["T_world_cam"] = [[1, 2], [3, 4]]
    sj.write_text(json.dumps(doc))
    with pytest.raises(CosyError, match="4x4"):
        evaluate_stage.parse_scene_json(sj, ds)


# --------------------------------------------------------------------------------------------
# bad inputs, fallbacks, CLI
# --------------------------------------------------------------------------------------------
def test_fallbacks_missing_targets_and_depth(tmp_path):
    root = make_dataset(tmp_path / "ds2", with_depth=False, with_targets=False)
    from cosy_cli.errors import CosyWarning

    with pytest.warns(CosyWarning) as said:  # said on stderr by a command, kept in scores.json
        s = evaluate_stage.main("bop19", root, "test", root / "pred.csv", tmp_path / "ev", progress=False)
    text = "\n".join(str(w.message) for w in said)
    assert "no targets file" in text and "VSD skipped" in text
    assert sorted(s["warnings"]) == sorted(str(w.message) for w in said)
    assert s["bop19_average_recall"] is None and s["bop19_average_recall_vsd"] is None
    assert s["bop19_average_recall_mssd"] is not None
    assert s["bop19"]["counts"]["targets"] == sum(len(v) for _, ims in SCENES.values() for v in ims.values())
    assert len(s["warnings"]) == 2
    # the models_eval fallback
    import shutil

    shutil.rmtree(root / "models_eval")
    with pytest.warns(CosyWarning, match="models_eval"):
        evaluate_stage.main("bop19", root, "test", root / "pred.csv", tmp_path / "ev2", metrics="auc",
                            progress=False)


def test_bad_inputs_cli(dataset, tmp_path):
    runner = CliRunner()
    base = ["evaluate", "--dataset", str(dataset), "--out", str(tmp_path / "ev"), "--metrics", "auc"]
    text = (dataset / "pred.csv").read_text().splitlines()

    def run(lines, extra=()):
        p = tmp_path / "p.csv"
        p.write_text("\n".join(lines) + "\n")
        return runner.invoke(cli, base + ["--predictions", str(p), *extra])

    bad_scene = [text[0], "9" + text[1][1:]]
    r = run(bad_scene)
    assert r.exit_code == 2 and "scene_id 9" in r.output and "row 1" in r.output
    bad_im = [text[0], text[1].replace("1,0,1,", "1,3,1,", 1)]
    r = run(bad_im)
    assert r.exit_code == 2 and "im_id 3" in r.output
    bad_obj = [text[0], text[1].replace("1,0,1,", "1,0,42,", 1)]
    r = run(bad_obj)
    assert r.exit_code == 2 and "obj_id 42" in r.output
    parts = text[1].split(",")
    parts[5] = "nan 0 500"
    r = run([text[0], ",".join(parts)])
    assert r.exit_code == 2 and "row 1" in r.output and "non-finite" in r.output
    r = run(text, ["--targets", str(tmp_path / "nope.json")])
    assert r.exit_code == 2 and "targets file not found" in r.output
    r = run(text, ["--metrics", "bop19,foo"])
    assert r.exit_code == 2 and "unknown metric" in r.output
    r = run(text)
    assert r.exit_code == 0, r.output
    r = run(text)  # complete and up to date: skipped
    assert r.exit_code == 0 and "skipping" in r.output
    r = run(text, ["--vsd-delta", "5"])  # other settings: refused without --overwrite
    assert r.exit_code == 2 and "--overwrite" in r.output
    r = run(text, ["--scene-id", "7", "--overwrite"])  # a scene the split does not have
    assert r.exit_code == 2 and "scene(s) [7] not in the split" in r.output


def test_scene_id_restricts_the_evaluation(dataset, evaluated, tmp_path):
    """``--scene-id``: only that scene's targets count (the other scene's predictions are ignored)."""
    _, full, _ = evaluated
    r = CliRunner().invoke(cli, ["evaluate", "--dataset", str(dataset), "--predictions", str(dataset / "pred.csv"),
                                 "--out", str(tmp_path / "one"), "--metrics", "bop19", "--no-vsd", "--scene-id", "1"])
    assert r.exit_code == 0, r.output
    one = json.loads((tmp_path / "one" / "scores.json").read_text())
    assert one["inputs"]["scene_ids"] == [1]
    tgt = json.loads((dataset / "test_targets_bop19.json").read_text())
    assert one["counts"]["targets"] == sum(t["inst_count"] for t in tgt if t["scene_id"] == 1) \
        < full["counts"]["targets"]


def test_speed_1000_estimates(dataset, tmp_path):
    """1,000 estimates (no VSD) well under 10 s on this machine."""
    import time

    rng = np.random.default_rng(1)
    gt = []
    for scene, (_, ims) in SCENES.items():
        for im, insts in ims.items():
            for g, (o, *_r) in enumerate(insts):
                gt.append((scene, im, o, _gt_pose(scene, im, g)))
    pick = rng.integers(0, len(gt), 1000)
    T = np.stack([gt[i][3] @ make_pose(rot(rng.normal(size=3), rng.uniform(0, 20)), rng.normal(0, 5, 3))
                  for i in pick])
    res = bop.PoseResults.from_arrays([gt[i][0] for i in pick], [gt[i][1] for i in pick], [gt[i][2] for i in pick],
                                      rng.random(1000), T)
    bop.write_results(tmp_path / "p.csv", res)
    t = time.time()
    evaluate_stage.main("bop19", dataset, "test", tmp_path / "p.csv", tmp_path / "ev",
                        log=lambda *_: None, progress=False)
    assert time.time() - t < 10


def test_average_precision_hand_values():
    # TP at ranks 2, 3, 5 of 6 distinct scores, 4 GT: (1/4) (1/2 + 2/3 + 3/5)
    tp = np.array([0, 1, 1, 0, 1, 0], bool)
    assert protocols.average_precision(tp, np.linspace(1, 0.1, 6), 4) == pytest.approx((1 / 2 + 2 / 3 + 3 / 5) / 4)
    # equal scores form one threshold: precision 1/2 at recall 1
    assert protocols.average_precision(np.array([True, False]), np.array([0.5, 0.5]), 1) == pytest.approx(0.5)
    assert protocols.average_precision(np.array([False]), np.array([0.5]), 1) == 0.0


def test_vivo_against_loops(dataset, tmp_path):
    """CosyPose's T-LESS ViVo meters, re-done with loops over the definitions."""
    s = evaluate_stage.main("bop19", dataset, "test", dataset / "pred.csv", tmp_path / "ev", metrics="vivo",
                            log=lambda *_: None, progress=False)
    ds = BopDataset(dataset, "test")
    db = evaluate_stage.load_models(ds, None, print)[0]
    res = bop.read_results(dataset / "pred.csv")
    tab = res.table
    tinfo = {(t[0], t[1], t[2]): t[3] for t in TARGETS}
    valid = {}  # (scene, im) -> valid GT indices (inst_count most visible per target object)
    for scene, (_, ims) in SCENES.items():
        for im, insts in ims.items():
            order = sorted(range(len(insts)), key=lambda g: insts[g][3], reverse=True)
            left = {o: c for (s_, i_, o), c in tinfo.items() if (s_, i_) == (scene, im)}
            valid[(scene, im)] = [g for g in order if left.get(insts[g][0], 0) > 0 and not left.update(
                {insts[g][0]: left[insts[g][0]] - 1})]

    def match(est_rows, ratio):
        out = {}  # (scene, im, gt) -> (est, err)
        by_group = {}
        for e in est_rows:
            by_group.setdefault((tab.scene_id[e], tab.im_id[e], tab.obj_id[e]), []).append(e)
        for (scene, im, o), es in by_group.items():
            es = sorted(es, key=lambda e: (-tab.score[e], e))
            taken = set()
            for e in es:
                best, best_err = None, np.inf
                for g in sorted(valid.get((scene, im), [])):
                    if SCENES[scene][1][im][g][0] != o or g in taken:
                        continue
                    Tg = _gt_pose(scene, im, g)
                    err = bf_adi(res.T_cam_obj[e], Tg, db[o].vertices)
                    if np.linalg.norm(res.T_cam_obj[e][:3, 3] - Tg[:3, 3]) >= db[o].diameter or \
                            err > ratio * db[o].diameter:
                        continue
                    if err < best_err:
                        best, best_err = g, err
                if best is not None:
                    taken.add(best)
                    out[(scene, im, best)] = (e, best_err)
        return out

    target_ims = {(t[0], t[1]) for t in TARGETS}
    on_targets = [e for e in range(len(tab)) if (tab.scene_id[e], tab.im_id[e]) in target_ims]
    top = []
    for (scene, im, o), c in tinfo.items():
        es = sorted([e for e in on_targets if (tab.scene_id[e], tab.im_id[e], tab.obj_id[e]) == (scene, im, o)],
                    key=lambda e: (-tab.score[e], e))
        top += es[:c]
    m_bop, m_all = match(top, 0.1), match(on_targets, 0.1)
    n_valid = sum(len(v) for v in valid.values())
    hits = sum(err < 0.1 * db[SCENES[k[0]][1][k[1]][k[2]][0]].diameter for k, (_, err) in m_bop.items())
    assert s["vivo_recall_adds_0.1d"] == pytest.approx(hits / n_valid)
    tp_est = {e for k, (e, err) in m_all.items() if err < 0.1 * db[SCENES[k[0]][1][k[1]][k[2]][0]].diameter}
    aps = []
    for o in (1, 2, 3):
        es = sorted([e for e in on_targets if tab.obj_id[e] == o], key=lambda e: -tab.score[e])
        n_gt = sum(1 for (sc, im), gs in valid.items() for g in gs if SCENES[sc][1][im][g][0] == o)
        if not any(e in tp_est for e in es):
            continue
        ap, tp_count, prev_r = 0.0, 0, 0.0
        scores_ = [tab.score[e] for e in es]
        for k, e in enumerate(es):  # precision/recall at the end of each distinct score
            tp_count += e in tp_est
            if k + 1 < len(es) and scores_[k + 1] == scores_[k]:
                continue
            r = tp_count / n_gt
            ap += (r - prev_r) * tp_count / (k + 1)
            prev_r = r
        aps.append(ap)
        assert s["per_object"][str(o)]["vivo_ap_adds_0.1d"] == pytest.approx(ap)
    assert s["vivo_map_adds_0.1d"] == pytest.approx(np.mean(aps))
    assert len(aps) >= 2 and 0 < s["vivo_map_adds_0.1d"] < 1
    m_ov = match(top, 0.5)
    aucs = []
    for o in (1, 2, 3):
        errs = [m_ov[(sc, im, g)][1] if (sc, im, g) in m_ov else np.inf
                for (sc, im), gs in valid.items() for g in gs if SCENES[sc][1][im][g][0] == o]
        aucs.append(protocols.auc_posecnn(np.array(errs) / 1000))
    assert s["vivo_auc_adds"] == pytest.approx(np.nanmean(aucs))


def test_scene_level_targets_for_the_multiview_task():
    """ViVo targets: every object of the scene in every image, with its instance count in the
    scene, including images where it is not annotated or not visible."""
    import pandas as pd

    from cosy_cli.evaluation import protocols

    gt = pd.DataFrame({"scene_id": [1, 1, 1, 1, 2], "im_id": [0, 0, 0, 3, 5], "gt_index": [0, 1, 2, 0, 0],
                       "obj_id": [4, 4, 7, 7, 4]})
    images = pd.DataFrame({"scene_id": [1, 1, 2], "im_id": [0, 3, 5]})
    t = protocols.scene_level_targets(gt, images)
    assert t.values.tolist() == [[1, 0, 4, 2], [1, 0, 7, 1], [1, 3, 4, 2], [1, 3, 7, 1], [2, 5, 4, 1]]


# --------------------------------------------------------------------------------------------
# bootstrap intervals of the average recalls
# --------------------------------------------------------------------------------------------
def test_bootstrap_intervals_by_hand():
    """Identical units give a zero-width interval at their AR; units without targets change
    nothing; a resample's AR weights units by their targets; seeded, so reproducible."""
    same = {"mssd": np.tile([[1, 2, 3, 4]], (5, 1)), "mspd": np.tile([[4, 4, 4, 4]], (5, 1))}
    iv = protocols.bootstrap_intervals(same, np.full(5, 4.0))
    assert iv["mssd"] == pytest.approx([10 / 16, 10 / 16]) and iv["mspd"] == pytest.approx([1.0, 1.0])
    assert iv["mssd_mspd"] == pytest.approx([(10 / 16 + 1) / 2] * 2) and "bop19" not in iv
    # one unit all found (1 target), one unit nothing found (3 targets): AR in {0, 1/4 (both), 1}
    c = {"mssd": np.array([[1.0], [0.0]]), "mspd": np.array([[1.0], [0.0]])}
    a = protocols.bootstrap_intervals(c, np.array([1.0, 3.0]), resamples=4000)
    assert a["mssd"] == [0.0, 1.0]  # both extremes are drawn (each with probability 1/4)
    assert protocols.bootstrap_intervals(c, np.array([1.0, 3.0]), resamples=4000) == a
    empty = {m: np.vstack([v, [[0.0]]]) for m, v in c.items()}  # a unit without targets
    b = protocols.bootstrap_intervals(empty, np.array([1.0, 3.0, 0.0]), resamples=4000)
    assert 0.0 <= b["mssd"][0] <= 0.25 <= b["mssd"][1] <= 1.0
    assert protocols.bootstrap_intervals({"mssd": np.zeros((0, 3))}, np.zeros(0)) == {}
    v = protocols.bootstrap_intervals({"vsd": np.ones((3, 2)), "mssd": np.ones((3, 2)), "mspd": np.zeros((3, 2))},
                                      np.ones(3))
    assert v["bop19"] == pytest.approx([2 / 3, 2 / 3])


def test_evaluate_reports_intervals(dataset, evaluated):
    """scores.json: a 95 % interval per BOP19 average recall, over images here (fewer than 10
    scenes), that holds the point value."""
    out, scores, _ = evaluated
    ci = scores["bop19_ci"]
    assert ci["unit"] == "image" and ci["units"] == scores["bop19"]["counts"]["target_images"]
    assert ci["level"] == 0.95 and ci["resamples"] == protocols.CI_RESAMPLES
    for k in ("bop19_average_recall", "bop19_average_recall_vsd", "bop19_average_recall_mssd",
              "bop19_average_recall_mspd", "bop19_average_recall_mssd_mspd"):
        lo, hi = ci[k]
        assert 0 <= lo <= scores[k] <= hi <= 1, (k, lo, scores[k], hi)
    assert json.loads((out / "scores.json").read_text())["bop19_ci"] == ci


# --------------------------------------------------------------------------------------------
# oracle poses (cosy evaluate --oracle)
# --------------------------------------------------------------------------------------------
def test_oracle_poses_by_hand():
    from cosy_cli.evaluation import oracle

    Tg = make_pose(rot([1, 2, 3], 40), (30.0, -20.0, 800.0))
    Te = make_pose(rot([0, 1, 0], 25), (36.0, -21.0, 880.0))
    Td = oracle.with_gt_depth(Te, Tg)[0]
    assert Td[2, 3] == pytest.approx(800.0)
    assert Td[:2, 3] / Td[2, 3] == pytest.approx(Te[:2, 3] / Te[2, 3])  # the origin's projection kept
    assert np.array_equal(Td[:3, :3], Te[:3, :3])
    behind = make_pose(np.eye(3), (0.0, 0.0, -5.0))
    assert np.array_equal(oracle.with_gt_depth(behind, Tg)[0][:3, 3], Tg[:3, 3])
    Tr = oracle.oracle_poses("rotation", Te, Tg)[0]
    assert np.array_equal(Tr[:3, :3], Tg[:3, :3]) and np.array_equal(Tr[:3, 3], Te[:3, 3])
    Tt = oracle.oracle_poses("translation", np.stack([Te, Te]), np.stack([Tg, Tg]))
    assert Tt.shape == (2, 4, 4) and np.array_equal(Tt[1][:3, 3], Tg[:3, 3]) and np.array_equal(Tt[1][:3, :3], Te[:3, :3])
    assert np.array_equal(Te[2, 3], 880.0)  # the inputs are not modified
    with pytest.raises(ValueError, match="expected one of depth, rotation, translation"):
        oracle.oracle_poses("scale", Te, Tg)


def test_evaluate_oracle(dataset, evaluated, tmp_path):
    """--oracle: each pair is scored with that part of the estimate from its GT; e1 (7 mm along z)
    is almost exact with the GT depth, e6 (10 degrees about the box's centre) with the GT rotation,
    e12 (20 mm along x) exact with the GT translation; recorded, and another oracle is another output."""
    _, plain, errs = evaluated

    def pair(table, e, g):
        return table[(table["est_index"] == e) & (table["gt_index"] == g)].iloc[0]

    got = {}
    for kind in ("depth", "rotation", "translation"):
        r = CliRunner().invoke(cli, ["evaluate", "--dataset", str(dataset), "--predictions", str(dataset / "pred.csv"),
                                     "--out", str(tmp_path / kind), "--oracle", kind]
                               + ([] if kind == "translation" else ["--no-vsd"]))
        assert r.exit_code == 0, r.output
        assert f"oracle {kind}" in r.output
        got[kind] = pd.read_csv(tmp_path / kind / "errors.csv")
        s = json.loads((tmp_path / kind / "scores.json").read_text())
        assert s["oracle"]["kind"] == kind and s["inputs"]["oracle"] == kind
        assert len(got[kind]) == len(errs)
    assert pair(errs, 1, 1)["mssd"] == pytest.approx(7.0, abs=1e-6)
    assert pair(got["depth"], 1, 1)["mssd"] < 1.0
    assert pair(got["depth"], 12, 2)["mssd"] > 19.0  # a lateral error stays
    assert pair(got["rotation"], 6, 1)["mssd"] < 1.0 < pair(errs, 6, 1)["mssd"]
    assert pair(got["translation"], 12, 2)["mssd"] == pytest.approx(0.0, abs=1e-9)
    assert pair(got["translation"], 12, 2)["re"] == pytest.approx(pair(errs, 12, 2)["re"])
    vsd = [c for c in errs.columns if c.startswith("vsd_")]  # VSD renders the oracle's pose too
    assert vsd and pair(errs, 12, 2)[vsd].max() > 0.5 and pair(got["translation"], 12, 2)[vsd].max() == 0.0
    assert json.loads((tmp_path / "translation" / "scores.json").read_text())["bop19_average_recall_mssd"] \
        > plain["bop19_average_recall_mssd"]
    # the same folder with another oracle is stale: refused without --overwrite
    r = CliRunner().invoke(cli, ["evaluate", "--dataset", str(dataset), "--predictions", str(dataset / "pred.csv"),
                                 "--out", str(tmp_path / "depth"), "--no-vsd", "--oracle", "rotation"])
    assert r.exit_code == 2 and "--overwrite" in r.output
    r = CliRunner().invoke(cli, ["evaluate", "--dataset", str(dataset), "--predictions", str(dataset / "pred.csv"),
                                 "--out", str(tmp_path / "x"), "--oracle", "scale"])
    assert r.exit_code == 2 and "scale" in r.output


def test_cameras_from_gt_objects():
    """Static scene: every image's camera relative to the first comes back exactly from the GT object
    poses; an object with two instances is not used; one annotated in a symmetric pose (turned
    180 degrees) in one image is left out; a scene whose images share no object gives no camera."""
    rng = np.random.default_rng(3)
    world_obj = {o: make_pose(rot(rng.normal(size=3), 40 * o), rng.normal(0, 100, 3)) for o in (1, 2, 3, 4, 5)}
    cams = {im: make_pose(rot(rng.normal(size=3), 20), rng.normal(0, 50, 3) + (0, 0, 900)) for im in (4, 7, 9)}
    rows, T = [], []
    for im, T_cw in cams.items():
        for o in (1, 2, 3, 4, 4, 5):
            Tco = T_cw @ world_obj[o]
            if o == 5 and im == 9:  # annotated turned about its z axis: another camera implied
                Tco = Tco @ make_pose(rot([0, 0, 1], 180), (0, 0, 0))
            rows.append((1, im, o))
            T.append(Tco)
    rows.append((2, 0, 1)), T.append(np.eye(4))
    rows.append((2, 1, 2)), T.append(np.eye(4))
    gt = pd.DataFrame(rows, columns=["scene_id", "im_id", "obj_id"])
    got, spread = protocols.cameras_from_gt_objects(gt, np.stack(T))
    assert set(got) == {(1, 4), (1, 7), (1, 9), (2, 0)}  # (2, 1) shares nothing with (2, 0)
    for im in (4, 7, 9):  # world = the first image's camera
        np.testing.assert_allclose(got[(1, im)], cams[im] @ np.linalg.inv(cams[4]), atol=1e-9)
    assert set(spread) == {(1, 7), (1, 9)} and max(spread.values()) < 1e-6
    # without the outlier test the turned object would have moved camera 9
    got_all, _ = protocols.cameras_from_gt_objects(gt, np.stack(T), outlier_mm=1e9)
    assert np.abs(got_all[(1, 9)][:3, 3] - got[(1, 9)][:3, 3]).max() > 1.0


def test_scene_json_camera_errors_without_gt_cameras(dataset, tmp_path):
    """A dataset without camera poses (LM-O): the camera errors are measured against the cameras the
    GT object poses imply, and scores.json says so."""
    import shutil

    root = tmp_path / "nocams"
    shutil.copytree(dataset, root)
    ds = BopDataset(root, "test")
    for s in (1, 3):
        cams = {im: bop.SceneCamera(K=c.K, depth_scale=c.depth_scale) for im, c in ds.scene_camera(s).items()}
        bop.write_scene_camera(root / "test" / f"{s:06d}" / "scene_camera.json", cams)
    T_17_2 = _gt_pose(3, 17, 2) @ np.linalg.inv(_gt_pose(3, 2, 1))  # object 3, the one single in both
    off = make_pose(rot([0, 1, 0], 3), (0, 0, 5))  # 3 degrees and 5 mm off, in view 17
    _, s = _evaluate_scene_json(root, tmp_path, {"groups": [_camera_group(3, 0, {2: np.eye(4),
                                                                            17: np.linalg.inv(off @ T_17_2)})]})
    c = s["cameras"]
    assert c["reference"] == "gt_objects" and c["pairs"] == 1
    assert c["rot_err_deg_mean"] == pytest.approx(3, abs=1e-6)
    assert c["trans_err_mm_mean"] == pytest.approx(5, abs=1e-6)
    assert any("GT object poses imply" in w for w in s["warnings"])
