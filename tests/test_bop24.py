"""cosy evaluate --metrics bop24: BOP 2024 6D detection AP (MSSD, MSPD), its pure functions by hand,
and the whole protocol against reference numbers of the BOP toolkit on a generated dataset."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import trimesh

from cosy_cli.geometry.poses import make_pose
from cosy_cli.geometry.rotations import rotation_about_axis
from cosy_cli.io import bop

# --------------------------------------------------------------------------------------------
# the generated dataset (T-LESS-like layout: test_primesense/, 720x540 images, objects 1..30)
# --------------------------------------------------------------------------------------------
W, H = 720, 540
K = np.array([[900.0, 0, 359.5], [0, 900.0, 269.5], [0, 0, 1]])
N_OBJECTS = 30  # the toolkit knows T-LESS by its 30 objects
SPLIT = "test_primesense"


def rot(axis, deg):
    return rotation_about_axis(np.asarray(axis, float), np.radians([deg]))[0]


def _models():
    """obj 1: 60x60x30 box, declared symmetric by 180 degrees about z; obj 2: cylinder with a
    continuous symmetry about z and a flip; obj 3: asymmetric box off its origin; the others: cubes."""
    m2 = trimesh.creation.cylinder(radius=20, height=60, sections=16)
    m3 = trimesh.creation.box(extents=(70, 40, 20))
    m3.apply_translation((10, 0, 0))
    out = {1: (trimesh.creation.box(extents=(60, 60, 30)), [make_pose(np.diag([-1.0, -1, 1]), np.zeros(3))], []),
           2: (m2, [make_pose(np.diag([1.0, -1, -1]), np.zeros(3))], [{"axis": np.array([0.0, 0, 1]),
                                                                     "offset": np.zeros(3)}]),
           3: (m3, [], [])}
    for o in range(4, N_OBJECTS + 1):
        out[o] = (trimesh.creation.box(extents=(30, 30, 30)), [], [])
    return out


# (scene, im) -> GT instances [(obj_id, rotation axis, degrees, model origin in the camera (mm), visib_fract)]
GT = {
    (1, 0): [(1, (0, 0, 1), 10, (-150, -80, 650), 0.9), (1, (1, 0, 0), 30, (0, -80, 660), 0.6),
             (2, (1, 0, 0), 20, (150, -80, 640), 0.8), (3, (0, 1, 0), 15, (-150, 80, 700), 0.7),
             (3, (0, 0, 1), 40, (0, 80, 690), 0.05), (2, (0, 1, 0), 60, (150, 80, 680), 0.1)],
    (1, 1): [(1, (1, 1, 0), 35, (-100, 0, 600), 0.95), (3, (1, 0, 0), 25, (60, 0, 620), 0.4),
             (3, (0, 0, 1), 10, (110, 0, 625), 0.08)],
    (1, 2): [(2, (0, 0, 1), 0, (-120, 0, 700), 0.5), (6, (0, 1, 0), 20, (0, 0, 700), 0.8),
             (1, (1, 0, 0), 80, (120, 0, 710), 0.3), (5, (0, 0, 1), 5, (0, 120, 720), 0.05)],
    (1, 3): [(1, (0, 1, 0), 25, (-60, 0, 650), 0.9), (3, (1, 1, 1), 30, (60, 0, 650), 0.9)],
    (2, 0): [(3, (0, 1, 0), 5, (-150, 0, 600), 0.85), (3, (1, 0, 0), 45, (0, 0, 610), 0.75),
             (3, (0, 0, 1), 70, (150, 0, 620), 0.65), (2, (1, 1, 0), 15, (0, 120, 630), 0.9)],
    (2, 1): [(1, (0, 0, 1), 50, (-120, -60, 640), 0.7), (2, (0, 1, 0), 30, (0, -60, 650), 0.6),
             (3, (1, 0, 1), 20, (120, -60, 660), 0.9), (1, (0, 1, 1), 15, (0, 90, 670), 0.4)],
    (2, 2): [(2, (1, 0, 0), 45, (-80, 0, 720), 0.33), (1, (0, 0, 1), 5, (80, 0, 730), 0.2)],
}
# the images of test_targets_bop24.json, in its order (scene 2 first: the order breaks ties of scores)
TARGET_IMAGES = [(2, 0), (2, 1), (2, 2), (1, 0), (1, 1), (1, 2)]


def gt_pose(scene, im, k):
    _, axis, deg, t, _ = GT[(scene, im)][k]
    return make_pose(rot(axis, deg), np.asarray(t, float))


def moved(T, dt=(0, 0, 0), axis=(0, 0, 1), deg=0.0):
    """T rotated by ``deg`` about ``axis`` (model frame, at the model origin), then shifted by ``dt`` (camera, mm)."""
    out = T @ make_pose(rot(axis, deg), np.zeros(3))
    out[:3, 3] += np.asarray(dt, float)
    return out


def predictions():
    """(scene, im, obj, score, T) rows; the comments say what each one tests."""
    g = gt_pose
    S1 = make_pose(np.diag([-1.0, -1, 1]), np.zeros(3))
    spin2 = make_pose(rot((0, 0, 1), 57.3), np.zeros(3))
    rows = [
        # scene 1 image 0
        (1, 0, 1, 0.96, g(1, 0, 0) @ S1),  # symmetric pose of obj 1: exact
        (1, 0, 1, 0.62, moved(g(1, 0, 1), (6, 0, 0))),  # 6 mm sideways
        (1, 0, 1, 0.55, moved(g(1, 0, 1), (6, 0, 0))),  # duplicate of the one above: FP where it matched
        (1, 0, 2, 0.999, g(1, 0, 2) @ spin2),  # continuous symmetry: exact; tied with FPs of scene 2 (listed first)
        (1, 0, 2, 0.71, moved(g(1, 0, 2), (0, 0, 12))),  # 12 mm along the ray, its GT already taken: FP
        (1, 0, 3, 0.83, moved(g(1, 0, 3), axis=(0, 1, 0), deg=8)),  # 8 degrees
        (1, 0, 3, 0.91, g(1, 0, 4)),  # exact pose of a 5 % visible GT: ignored
        (1, 0, 2, 0.47, moved(g(1, 0, 5), (15, 0, 0))),  # 10 % visible (the boundary is valid), 15 mm
        (1, 0, 3, 0.66, moved(g(1, 0, 3), (300, 0, 0))),  # far from any obj 3: FP
        # scene 1 image 1: the two obj 3 are 50 mm apart, the second one 8 % visible
        (1, 1, 1, 0.58, moved(g(1, 1, 0), (0, 0, 90))),  # 90 mm along the ray: MSSD off (sphere), MSPD small
        (1, 1, 3, 0.88, moved(g(1, 1, 2), (-20, 0, 0))),  # between the two, nearer the invisible one: ignored
        (1, 1, 3, 0.52, moved(g(1, 1, 1), (-14, 3, 0))),  # the visible one, 14 mm
        (1, 1, 4, 0.97, g(1, 1, 0)),  # obj 4 is not in the image: not evaluated
        # scene 1 image 2: obj 6 has no estimate; obj 5 only a 5 % visible GT
        (1, 2, 2, 0.74, moved(g(1, 2, 0), (0, 22, 0))),  # 22 mm
        (1, 2, 1, 0.81, moved(g(1, 2, 2), (3, 0, 0), axis=(0, 0, 1), deg=12)),
        (1, 2, 5, 0.9, moved(g(1, 2, 3), (40, 0, 0))),  # FP of obj 5, which has no visible GT: left out
        (1, 2, 5, 0.35, g(1, 2, 3)),  # exact on the invisible GT: ignored
        # scene 1 image 3 is not a target image: not evaluated
        (1, 3, 1, 0.95, g(1, 3, 0)),
        (1, 3, 3, 0.95, moved(g(1, 3, 1), (200, 0, 0))),
        # scene 2 image 0: three obj 3
        (2, 0, 3, 0.93, moved(g(2, 0, 0), (2, -2, 0))),
        (2, 0, 3, 0.77, moved(g(2, 0, 1), (0, 0, 30), axis=(0, 0, 1), deg=3)),
        (2, 0, 3, 0.77, moved(g(2, 0, 1), (0, 0, 30), axis=(0, 0, 1), deg=3)),  # same pose and score: 2nd is FP
        (2, 0, 3, 0.61, moved(g(2, 0, 2), (35, 0, 0))),  # 35 mm
        (2, 0, 3, 0.68, moved(g(2, 0, 2), (9, 0, 0), axis=(1, 0, 0), deg=10)),
        (2, 0, 2, 0.999, moved(g(2, 0, 3), (0, 200, 0))),  # FP, tied in score with two exact obj 2
        (2, 0, 2, 0.999, moved(g(2, 0, 3), (0, -150, 0))),  # FP, tied too
        (2, 0, 2, 0.44, moved(g(2, 0, 3), (5, 5, 5))),
        (2, 0, 1, 0.98, moved(g(2, 0, 1), (0, 0, 40))),  # obj 1 is not in this image: not evaluated
    ]
    # scene 2 image 1: 97 estimates of obj 4 (not in the image, not evaluated) push the image past the
    # 100 estimates the toolkit keeps: its 4 lowest-scored estimates are dropped
    rows += [(2, 1, 4, 0.9 + 0.0005 * i, moved(g(2, 1, 0), (i, 0, 0))) for i in range(97)]
    rows += [
        (2, 1, 1, 0.85, moved(g(2, 1, 0), (0, 4, 0))),
        (2, 1, 2, 0.8, moved(g(2, 1, 1), (0, 0, 0), axis=(1, 0, 0), deg=6)),
        (2, 1, 3, 0.7, moved(g(2, 1, 2), (18, 0, 0))),
        (2, 1, 1, 0.3, g(2, 1, 3)),  # dropped (would be exact)
        (2, 1, 3, 0.25, g(2, 1, 2)),  # dropped
        (2, 1, 2, 0.2, moved(g(2, 1, 1), (100, 0, 0))),  # dropped
        (2, 1, 1, 0.15, g(2, 1, 0)),  # dropped
        # scene 2 image 2
        (2, 2, 2, 0.999, g(2, 2, 0)),  # exact, tied in score with the FPs of scene 2 image 0 (listed first)
        (2, 2, 1, 0.5, moved(g(2, 2, 1), (0, 0, -25), axis=(0, 1, 0), deg=4)),
        (2, 2, 1, 0.49, moved(g(2, 2, 1), (60, 0, 0))),
    ]
    return rows


def make_bop24_dataset(root: Path, targets: bool = True) -> Path:
    """Writes the dataset (models_eval/, camera.json, test_primesense/, test_targets_bop24.json) and
    ``pred.csv``; deterministic (no random numbers)."""
    from cosy_cli.objects import diameter_of

    root.mkdir(parents=True, exist_ok=True)
    bop.write_camera(root / "camera.json", bop.CameraInfo(K=K, width=W, height=H))
    infos = {}
    (root / "models_eval").mkdir(exist_ok=True)
    for o, (m, disc, cont) in _models().items():
        m.export(root / "models_eval" / f"obj_{o:06d}.ply")
        V = np.asarray(m.vertices)
        infos[o] = bop.ModelInfo(diameter_of(V), V.min(0), V.max(0) - V.min(0),
                                 np.array(disc) if disc else np.zeros((0, 4, 4)), cont)
    bop.write_models_info(root / "models_eval" / "models_info.json", infos)
    for scene in sorted({s for s, _ in GT}):
        d = root / SPLIT / f"{scene:06d}"
        ims = sorted(i for s, i in GT if s == scene)
        bop.write_scene_camera(d / "scene_camera.json", {i: bop.SceneCamera(K=K) for i in ims})
        bop.write_scene_gt(d / "scene_gt.json", {i: [bop.GtInstance(r[0], gt_pose(scene, i, k))
                                                     for k, r in enumerate(GT[(scene, i)])] for i in ims})
        bop.write_scene_gt_info(d / "scene_gt_info.json", {
            i: [bop.GtInfo(np.zeros(4), np.zeros(4), 100, 100, int(100 * r[4]), r[4]) for r in GT[(scene, i)]]
            for i in ims})
    if targets:
        entries = [{"im_id": i, "scene_id": s} for s, i in TARGET_IMAGES]
        (root / "test_targets_bop24.json").write_text(json.dumps(entries))
    rows = predictions()
    res = bop.PoseResults.from_arrays([r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows],
                                      [r[3] for r in rows], np.stack([r[4] for r in rows]))
    bop.write_results(root / "pred.csv", res)
    return root


# --------------------------------------------------------------------------------------------
# reference numbers: the BOP toolkit's scripts/eval_bop24_pose.py (commit cea62d6) run on the dataset
# above (as "tless", split test, primesense images of 720 px), its scores_th=*_min-visib=0.100.json
# --------------------------------------------------------------------------------------------
TOOLKIT = {"bop24_ap": 0.44559130913091316, "bop24_ap_mssd": 0.4087938079522238,
           "bop24_ap_mspd": 0.48238881030960246, "bop24_ap_mssd_mm": 0.27187293729372936}
TOOLKIT_VALID_GT = {1: 7, 2: 6, 3: 6, 6: 1}  # num_targets_per_object (> 0); obj 5 has none
TOOLKIT_AP = {  # object -> AP at each threshold
    "mssd": {
        1: [0.287128712871, 0.391089108911, 0.574257425743, 0.574257425743, 0.574257425743, 0.574257425743,
            0.673267326733, 0.673267326733, 0.673267326733, 0.673267326733],
        2: [0.168316831683, 0.30297029703, 0.373377337734, 0.373377337734, 0.484488448845, 0.484488448845,
            0.666666666667, 0.666666666667, 0.666666666667, 0.666666666667],
        3: [0.168316831683, 0.280528052805, 0.352663837812, 0.416030174446, 0.64796479648, 0.64796479648,
            0.64796479648, 0.889438943894, 0.889438943894, 0.889438943894],
        6: [0.0] * 10,
    },
    "mspd": {
        1: [0.148514851485, 0.475954738331, 0.673267326733, 0.673267326733, 0.831683168317, 0.831683168317,
            0.831683168317, 0.831683168317, 0.831683168317, 0.831683168317],
        2: [0.30297029703, 0.373377337734, 0.373377337734, 0.484488448845, 0.484488448845, 0.666666666667,
            0.666666666667, 0.666666666667, 0.666666666667, 0.666666666667],
        3: [0.252475247525, 0.420792079208, 0.511315417256, 0.595473833098, 0.755162659123, 0.889438943894,
            0.889438943894, 0.889438943894, 0.889438943894, 0.889438943894],
        6: [0.0] * 10,
    },
    "mssd_mm": {
        1: [0.148514851485, 0.148514851485, 0.287128712871, 0.391089108911, 0.391089108911, 0.574257425743,
            0.574257425743, 0.574257425743, 0.574257425743, 0.574257425743],
        2: [0.168316831683, 0.30297029703, 0.30297029703, 0.30297029703, 0.373377337734, 0.373377337734,
            0.373377337734, 0.484488448845, 0.484488448845, 0.484488448845],
        3: [0.0, 0.168316831683, 0.168316831683, 0.280528052805, 0.280528052805, 0.352663837812,
            0.352663837812, 0.416030174446, 0.416030174446, 0.551390853371],
        6: [0.0] * 10,
    },
}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_bop24_dataset(tmp_path_factory.mktemp("bop24ds") / "tless")


def test_bop24_matches_the_toolkit(dataset, tmp_path):
    from cosy_cli.evaluation import evaluate_stage

    s = evaluate_stage.main("bop19", dataset, SPLIT, dataset / "pred.csv", tmp_path / "ev", metrics="bop24",
                            log=lambda *_: None, progress=False)
    for k, v in TOOLKIT.items():
        assert s[k] == pytest.approx(v, abs=1e-12), k
    b = s["bop24"]
    assert {int(o): p["bop24_valid_gt"] for o, p in b["per_object"].items()} == TOOLKIT_VALID_GT
    for m, per_obj in TOOLKIT_AP.items():
        for o, aps in per_obj.items():
            assert b["curves"][m]["per_object"][str(o)] == pytest.approx(aps, abs=1e-11), (m, o)
            assert b["per_object"][str(o)][f"bop24_ap_{m}"] == pytest.approx(np.mean(aps), abs=1e-11)
    # what the data exercises, as counted by the protocol
    c = b["counts"]
    assert c["images"] == len(TARGET_IMAGES) and c["estimates_over_cap"] == 4
    assert c["objects_without_valid_gt"] == [5]
    assert b["max_estimates_per_image"] == 100
    assert b["image_width_px"] == {"1": 720.0, "2": 720.0}
    assert s["warnings"] == [] and "bop19_average_recall" not in s
    saved = json.loads((tmp_path / "ev" / "scores.json").read_text())
    assert saved["bop24_ap"] == pytest.approx(TOOLKIT["bop24_ap"], abs=1e-12)
    assert saved["per_object"]["1"]["bop24_ap_mspd"] == pytest.approx(np.mean(TOOLKIT_AP["mspd"][1]), abs=1e-11)


# --------------------------------------------------------------------------------------------
# the pure functions, by hand
# --------------------------------------------------------------------------------------------
def test_average_precision_by_hand():
    from cosy_cli.evaluation.bop24 import average_precision

    # TP FP TP FP TP FP against 4 GT: recall .25 .25 .5 .5 .75 .75, precision 1 .5 2/3 .5 .6 .5;
    # levels 0..0.25 (26 of them) -> 1, 0.26..0.50 (25) -> 2/3, 0.51..0.75 (25) -> 0.6, 0.76..1 (25) -> 0
    tp = [True, False, True, False, True, False]
    assert average_precision(tp, 4) == pytest.approx((26 + 25 * 2 / 3 + 25 * 0.6) / 101, abs=1e-12)
    assert average_precision([True, True], 4) == pytest.approx(51 / 101, abs=1e-12)  # levels 0..0.5
    assert average_precision([False, True], 1) == pytest.approx(0.5, abs=1e-12)
    assert average_precision([], 3) == 0.0
    assert np.isnan(average_precision([True], 0))


def test_greedy_matching_per_threshold():
    from cosy_cli.evaluation.bop24 import greedy_match_thresholds

    E = np.array([[1.0, 3.0], [2.0, 9.0], [0.5, 8.0]])  # rows in score order
    m = greedy_match_thresholds(E, [1.5, 5, 10])
    # the first estimate takes GT 0 although the third fits it better; GT 1 only below 10
    assert m.tolist() == [[0, -1, -1], [0, -1, -1], [0, 1, -1]]
    assert greedy_match_thresholds(np.array([[2.0, 2.0]]), [5]).tolist() == [[0]]  # tie: lower GT index
    assert greedy_match_thresholds(np.array([[5.0]]), [5, 5.0001]).tolist() == [[-1], [0]]  # strictly below
    assert greedy_match_thresholds(np.zeros((2, 0)), [1]).tolist() == [[-1, -1]]


def test_outcomes_cap_and_normalisation():
    from cosy_cli.evaluation import bop24 as b

    # unmatched: FP; matched to a GT under 10 % visible: ignored; 10 % is enough
    assert b.outcomes([np.nan, 0.05, 0.1, 0.9]).tolist() == [0, -1, 1, 1]
    est = pd.DataFrame({"est_index": [0, 1, 2, 3], "scene_id": [1, 1, 1, 1], "im_id": [0, 0, 0, 5],
                        "score": [0.5, 0.9, 0.5, 0.1]})
    assert b.keep_top_per_image(est, 2)["est_index"].tolist() == [0, 1, 3]  # tie on 0.5: file order
    assert b.max_estimates_per_image("tless") == 100 and b.max_estimates_per_image("xyzibd") == 200
    err = pd.DataFrame({"obj_id": [1, 1], "scene_id": [1, 1], "mssd": [10.0, 10.0], "mspd": [36.0, 36.0],
                        "te": [60.0, 10.0]})
    n = b.normalized_errors(err, {1: 50.0}, {1: 720.0})
    assert n["mssd"].tolist() == [np.inf, 0.2] and n["mssd_mm"].tolist() == [np.inf, 10.0]  # sphere shortcut
    assert n["mspd"].tolist() == pytest.approx([32.0, 32.0])  # x 640 / 720


def test_bop24_scores_by_hand():
    """One image: obj 1 with GT A, B (visible) and C (5 % visible), obj 2 with GT D; obj 3 estimated
    but absent."""
    from cosy_cli.evaluation.bop24 import bop24_scores

    gt = pd.DataFrame({"scene_id": [1] * 4, "im_id": [0] * 4, "gt_index": [0, 1, 2, 3], "obj_id": [1, 1, 1, 2],
                       "visib_fract": [0.9, 0.8, 0.05, 0.5]})
    est = pd.DataFrame({"est_index": range(7), "scene_id": [1] * 7, "im_id": [0] * 7,
                        "obj_id": [1, 1, 1, 1, 2, 2, 3], "score": [0.95, 0.9, 0.85, 0.8, 0.7, 0.6, 0.99]})
    exact_on = {0: 2, 1: 0, 2: 0, 3: 1, 5: 3}  # estimate -> the GT it sits on (4: far from everything)
    rows = []
    for e, o in zip(est["est_index"], est["obj_id"]):
        for g in gt.loc[gt["obj_id"] == o, "gt_index"]:
            hit = exact_on.get(e) == g
            rows.append((e, g, 1, 0, o, 0.0 if hit else 100.0, 0.0 if hit else 200.0, 0.0 if hit else 100.0))
    errors = pd.DataFrame(rows, columns=["est_index", "gt_index", "scene_id", "im_id", "obj_id", "mssd", "mspd", "te"])
    ims = pd.DataFrame({"scene_id": [1], "im_id": [0]})
    s = bop24_scores(gt, ims, est, errors, {1: 50.0, 2: 50.0, 3: 50.0}, {1: 640.0})
    # obj 1: estimate 0 on C: ignored; 1 on A: TP; 2 duplicate on A: FP; 3 on B: TP -> TP FP TP over 2 GT:
    # levels 0..0.5 -> 1, 0.51..1 -> 2/3.  obj 2: FP then TP over 1 GT -> 0.5 at every level.
    ap1, ap2 = (51 + 50 * 2 / 3) / 101, 0.5
    for m in ("mssd", "mspd", "mssd_mm"):
        assert s["per_object"]["1"][f"bop24_ap_{m}"] == pytest.approx(ap1, abs=1e-12)
        assert s["per_object"]["2"][f"bop24_ap_{m}"] == pytest.approx(ap2, abs=1e-12)
        assert s[f"bop24_ap_{m}"] == pytest.approx((ap1 + ap2) / 2, abs=1e-12)
        assert s["curves"][m]["tp"] == [3] * 10 and s["curves"][m]["fp"] == [2] * 10
        assert s["curves"][m]["ignored"] == [1] * 10
    assert s["bop24_ap"] == pytest.approx((ap1 + ap2) / 2, abs=1e-12)
    assert set(s["per_object"]) == {"1", "2"}  # obj 3 is not in the image: not evaluated
    assert s["counts"]["estimates_evaluated"] == 6 and s["counts"]["valid_gt"] == 3
    # no estimate at all: AP 0; no GT instance visible enough: no AP (NaN), nothing fails
    none = bop24_scores(gt, ims, est.iloc[:0], errors.iloc[:0], {1: 50.0, 2: 50.0}, {1: 640.0})
    assert none["bop24_ap"] == 0.0 and none["counts"]["objects"] == 2
    dim = bop24_scores(gt.assign(visib_fract=0.05), ims, est, errors, {1: 50.0, 2: 50.0, 3: 50.0}, {1: 640.0})
    assert np.isnan(dim["bop24_ap"]) and dim["per_object"] == {} and dim["counts"]["objects_without_valid_gt"] == [1, 2]


# --------------------------------------------------------------------------------------------
# the stage: which images, both protocols, the command line
# --------------------------------------------------------------------------------------------
def test_images_without_a_bop24_targets_file(tmp_path):
    from cosy_cli.errors import CosyWarning
    from cosy_cli.evaluation import evaluate_stage

    root = make_bop24_dataset(tmp_path / "ds", targets=False)
    with pytest.warns(CosyWarning, match="BOP24 evaluates every image with GT"):
        s = evaluate_stage.main("bop19", root, SPLIT, root / "pred.csv", tmp_path / "ev1", metrics="bop24",
                                progress=False, log=lambda *_: None)
    assert s["bop24"]["counts"]["images"] == len(GT)  # scene 1 image 3 too
    assert s["bop24"]["per_object"]["1"]["bop24_valid_gt"] == TOOLKIT_VALID_GT[1] + 1
    # a BOP19 targets file: its images (in its order)
    bop.write_targets(root / "test_targets_bop19.json", pd.DataFrame(
        [(sc, im, o, 1) for sc, im in TARGET_IMAGES for o in sorted({r[0] for r in GT[(sc, im)]})],
        columns=["scene_id", "im_id", "obj_id", "inst_count"]))
    with pytest.warns(CosyWarning, match="BOP24 evaluates the images of test_targets_bop19.json"):
        s = evaluate_stage.main("bop19", root, SPLIT, root / "pred.csv", tmp_path / "ev2", metrics="bop24",
                                progress=False, log=lambda *_: None)
    assert s["bop24_ap"] == pytest.approx(TOOLKIT["bop24_ap"], abs=1e-12)
    # --targets: that file's images, for BOP24 as for BOP19
    (tmp_path / "t.json").write_text(json.dumps([{"scene_id": 2, "im_id": 2}]))
    s = evaluate_stage.main("bop19", root, SPLIT, root / "pred.csv", tmp_path / "ev3", metrics="bop24",
                            targets=tmp_path / "t.json", progress=False, log=lambda *_: None)
    assert s["bop24"]["counts"]["images"] == 1 and set(s["bop24"]["per_object"]) == {"1", "2"}
    assert s["warnings"] == []


def test_bop19_and_bop24_side_by_side(dataset, tmp_path):
    """A dataset with only test_targets_bop24.json: BOP19 takes every GT instance of its images as a
    target (a warning), BOP24 its images; both in scores.json and the summary."""
    from cosy_cli.errors import CosyWarning
    from cosy_cli.evaluation import evaluate_stage

    said = []
    with pytest.warns(CosyWarning) as w:
        s = evaluate_stage.main("bop19", dataset, SPLIT, dataset / "pred.csv", tmp_path / "ev", metrics="bop19,bop24",
                                progress=False, log=said.append)
    text = "\n".join(str(x.message) for x in w)
    assert "test_targets_bop24.json lists images without inst_count" in text and "VSD skipped" in text
    n_gt = sum(len(GT[k]) for k in TARGET_IMAGES)
    assert s["bop19"]["counts"]["targets"] == n_gt and s["counts"]["targets"] == n_gt
    assert s["bop19_average_recall_mssd"] is not None
    assert s["bop24_ap"] == pytest.approx(TOOLKIT["bop24_ap"], abs=1e-12)
    assert set(s["per_object"]["1"]) >= {"bop19_average_recall_mssd", "bop24_ap_mssd", "bop24_valid_gt"}
    log = "\n".join(said)
    for k in ("bop19_average_recall_mssd:", "bop24_ap:", "bop24_ap_mssd:", "bop24_ap_mspd:", "bop24_ap_mssd_mm:"):
        assert k in log
    assert f"bop24_ap: {TOOLKIT['bop24_ap']:.4f}" in log


def test_cli_bop24(dataset, tmp_path):
    from click.testing import CliRunner

    from cosy_cli.cli.main import cli

    runner = CliRunner()
    assert "bop24" in runner.invoke(cli, ["evaluate", "--help"]).output
    base = ["evaluate", "--dataset", str(dataset), "--split", SPLIT, "--predictions", str(dataset / "pred.csv"),
            "--metrics", "bop24"]
    r = runner.invoke(cli, base + ["--out", str(tmp_path / "ev")])
    assert r.exit_code == 0, r.output
    assert f"bop24_ap: {TOOLKIT['bop24_ap']:.4f}" in r.output
    assert json.loads((tmp_path / "ev" / "scores.json").read_text())["bop24_ap_mspd"] == pytest.approx(
        TOOLKIT["bop24_ap_mspd"], abs=1e-12)
    # --protocol names the same option (the BOP toolkit's word)
    r = runner.invoke(cli, base[:-2] + ["--protocol", "bop24", "--out", str(tmp_path / "ev_p")])
    assert r.exit_code == 0 and f"bop24_ap: {TOOLKIT['bop24_ap']:.4f}" in r.output, r.output
    # bad targets: an image without GT, an entry without im_id
    (tmp_path / "t1.json").write_text(json.dumps([{"scene_id": 2, "im_id": 0}, {"scene_id": 2, "im_id": 9}]))
    r = runner.invoke(cli, base + ["--out", str(tmp_path / "ev1"), "--targets", str(tmp_path / "t1.json")])
    assert r.exit_code == 2 and "scene 2 image 9 has no ground truth" in r.output and "entry 1" in r.output
    assert "Traceback" not in r.output
    (tmp_path / "t2.json").write_text(json.dumps([{"scene_id": 2}]))
    r = runner.invoke(cli, base + ["--out", str(tmp_path / "ev2"), "--targets", str(tmp_path / "t2.json")])
    assert r.exit_code == 2 and "missing key 'im_id'" in r.output and "entry 0" in r.output
