"""`cosy estimate`: detections in, BOP candidates out (templates + ICP chain, shipped networks), errors."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cosy_cli.cli.main import cli
from cosy_cli.detection.importers import detections_from_gt
from cosy_cli.evaluation.pose_error import adi
from cosy_cli.io import bop
from cosy_cli.io import hypotheses as hyp_io
from cosy_cli.io.dataset import BopDataset
from cosy_cli.objects import ObjectDatabase
from cosy_cli.singleview import estimate_stage

SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"
SCENE = SAMPLES / "test" / "000001"
SMALL_TEMPLATES = {"viewpoints": 200, "inplane": 24}


@pytest.fixture(scope="module")
def ds():
    return BopDataset(SAMPLES, "test")


@pytest.fixture(scope="module")
def templates_dir(tmp_path_factory):
    """Templates of the sample objects at a reduced resolution (fast to build)."""
    from cosy_cli.singleview.training_free import templates

    out = tmp_path_factory.mktemp("tpl") / "templates"
    templates.main(SMALL_TEMPLATES, SAMPLES / "models", out, log=lambda *_: None)
    return out


def _run(args):
    return CliRunner().invoke(cli, args, catch_exceptions=False)


def test_gt_detections_are_the_visible_boxes(ds):
    dets = detections_from_gt(ds, [1], 0.1)
    info, gt = ds.scene_gt_info(1), ds.scene_gt(1)
    n = sum(1 for im in info for i in info[im] if i.visib_fract >= 0.1)
    assert len(dets) == n > 0
    r = dets.iloc[0]
    box = info[int(r.im_id)][int(r.gt_index)].bbox_visib
    np.testing.assert_allclose([r.x, r.y, r.w, r.h], box)
    assert gt[int(r.im_id)][int(r.gt_index)].obj_id == r.obj_id
    assert len(detections_from_gt(ds, [1], 0.99)) < n


def test_unknown_labels_are_skipped_and_reported(ds):
    dets = detections_from_gt(ds, [1], 0.1)
    dets.loc[0, "obj_id"] = 99
    lines = []
    kept = estimate_stage.check_detections(dets, ds, [1], {1, 2, 3, 4, 5, 6, 7, 8}, "dets.json", lines.append)
    assert len(kept) == len(dets) - 1
    assert "obj_id 99" in lines[0] and "dets.json" in lines[0]
    dets.loc[1, "im_id"] = 999
    with pytest.raises(Exception, match="im_id 999"):
        estimate_stage.check_detections(dets, ds, [1], {1, 2, 3, 4, 5, 6, 7, 8}, "dets.json", lines.append)


def test_boxes_are_clipped_to_the_image():
    b = estimate_stage.clip_boxes(np.array([[-10, 5, 30, 20], [630, 470, 40, 40]]), 640, 480)
    np.testing.assert_allclose(b, [[0, 5, 20, 25], [630, 470, 640, 480]])


def test_templates_icp_candidates_from_a_scene(tmp_path, templates_dir, ds):
    out = tmp_path / "cands.csv"
    r = _run(["estimate", "--scene", str(SCENE), "--from-gt", "--coarse", "templates", "--refiner", "none",
              "--depth-refine", "icp", "--templates-dir", str(templates_dir), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "coarse templates" in r.output and "ICP" in r.output
    res = bop.read_results(out)
    dets = detections_from_gt(ds, [1], 0.1)
    assert len(res) == len(dets)
    assert (res.table["score"] == 1.0).all() and (res.table["time"] > 0).all()
    # accuracy against GT: the candidates are in the right camera frame and mostly correct
    db = ObjectDatabase.from_models_dir(SAMPLES / "models")
    gt = ds.scene_gt(1)
    ok = []
    for (im, gi, o), T in zip(dets[["im_id", "gt_index", "obj_id"]].itertuples(index=False), res.T_cam_obj):
        ok.append(adi(T, gt[im][gi].T_cam_obj, db[o].points)[0] < 0.1 * db[o].diameter)
    assert np.mean(ok) >= 0.7, f"recall {np.mean(ok):.2f}"
    timing = (tmp_path / "cands.timing.csv").read_text().splitlines()
    assert timing[0].startswith("scene_id,im_id,detections,time_s")
    doc = json.loads((tmp_path / "cands.json").read_text())
    assert doc["conf"]["coarse"] == "templates" and doc["conf"]["depth_refine"] == "icp"
    # cached: a second run skips; other settings are refused without --overwrite
    r = _run(["estimate", "--scene", str(SCENE), "--from-gt", "--coarse", "templates", "--refiner", "none",
              "--depth-refine", "icp", "--templates-dir", str(templates_dir), "--out", str(out)])
    assert r.exit_code == 0 and "skipping" in r.output
    r = _run(["estimate", "--scene", str(SCENE), "--from-gt", "--coarse", "templates", "--refiner", "none",
              "--depth-refine", "icp", "--top-k", "2", "--templates-dir", str(templates_dir), "--out", str(out)])
    assert r.exit_code == 2 and "settings changed (top_k)" in r.output


def test_bad_input_gives_clear_errors(tmp_path, templates_dir):
    out = str(tmp_path / "c.csv")
    r = _run(["estimate", "--scene", str(SCENE), "--out", out])
    assert r.exit_code == 2 and "--detections" in r.output and "--from-gt" in r.output
    r = _run(["estimate", "--scene", str(SCENE), "--from-gt", "--refiner", str(tmp_path / "nope.onnx"), "--out", out])
    assert r.exit_code == 2 and "nope.onnx" in r.output and "cosy train refiner" in r.output
    r = _run(["estimate", "--scene", str(tmp_path / "missing" / "000001"), "--from-gt", "--out", out])
    assert r.exit_code == 2 and "scene folder not found" in r.output
    # a dataset without depth: ICP is refused with a clear message, auto falls back to RGB only
    nodepth = tmp_path / "nodepth"
    shutil.copytree(SAMPLES / "models", nodepth / "models")
    shutil.copytree(SCENE, nodepth / "test" / "000001", ignore=shutil.ignore_patterns("depth"))
    r = _run(["estimate", "--scene", str(nodepth / "test" / "000001"), "--from-gt", "--coarse", "templates",
              "--refiner", "none", "--depth-refine", "icp", "--templates-dir", str(templates_dir), "--out", out])
    assert r.exit_code == 2 and "depth" in r.output and "--depth-refine none" in r.output
    # a detections file with an empty box
    dets = tmp_path / "dets.json"
    dets.write_text(json.dumps([{"scene_id": 1, "image_id": 0, "category_id": 1, "score": 0.9, "bbox": [1, 2, 0, 5]}]))
    r = _run(["estimate", "--scene", str(SCENE), "--detections", str(dets), "--out", out])
    assert r.exit_code == 2 and "dets.json" in r.output and "non-positive" in r.output


def test_verification_settings_from_the_cli(tmp_path, templates_dir):
    """--verify-top / --rgb-refine reach the settings (and the summary); bad values are refused."""
    out = tmp_path / "v.csv"
    r = _run(["estimate", "--scene", str(SCENE), "--from-gt", "--coarse", "templates", "--refiner", "none",
              "--depth-refine", "none", "--verify-top", "8", "--rgb-refine", "none", "--top-k", "2",
              "--templates-dir", str(templates_dir), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "8 verified by rendering" in r.output and "RGB refinement" not in r.output
    doc = json.loads((tmp_path / "v.json").read_text())
    assert doc["conf"]["verify_top"] == 8 and doc["conf"]["rgb_refine"] == "none"
    r = _run(["estimate", "--scene", str(SCENE), "--from-gt", "--rgb-refine", "sometimes", "--out", str(out)])
    assert r.exit_code == 2 and "sometimes" in r.output
    with pytest.raises(Exception, match="image_weight"):
        estimate_stage.resolve_conf("default", image_weight=-1)
    # --box-scales: every hypothesis also verified nearer and farther (loose detector boxes)
    out2 = tmp_path / "bs.csv"
    r = _run(["estimate", "--scene", str(SCENE), "--from-gt", "--coarse", "templates", "--refiner", "none",
              "--depth-refine", "none", "--verify-top", "8", "--rgb-refine", "none", "--top-k", "2",
              "--box-scales", "0.87,1,1.15", "--templates-dir", str(templates_dir), "--out", str(out2)])
    assert r.exit_code == 0, r.output
    assert "8 x 3 distances verified by rendering" in r.output
    assert json.loads((tmp_path / "bs.json").read_text())["conf"]["box_scales"] == [0.87, 1.0, 1.15]
    assert len(bop.read_results(out2)) == len(bop.read_results(out))
    for bad in ("0", "1,1", "near"):
        r = _run(["estimate", "--scene", str(SCENE), "--from-gt", "--box-scales", bad, "--out", str(out2)])
        assert r.exit_code == 2 and "box_scales" in r.output, (bad, r.output)
    assert estimate_stage.resolve_conf("default")["box_scales"] == [1.0]
    # --mask-weight: recorded when not the default, reaches the verifier; negative refused
    assert "mask_weight" not in json.loads((tmp_path / "v.json").read_text())["conf"]
    out3 = tmp_path / "mw.csv"
    r = _run(["estimate", "--scene", str(SCENE), "--from-gt", "--coarse", "templates", "--refiner", "none",
              "--depth-refine", "none", "--verify-top", "8", "--rgb-refine", "none", "--top-k", "2",
              "--mask-weight", "0.5", "--mask-band", "3", "--templates-dir", str(templates_dir), "--out", str(out3)])
    assert r.exit_code == 0, r.output
    conf = json.loads((tmp_path / "mw.json").read_text())["conf"]
    assert conf["mask_weight"] == 0.5 and conf["mask_band"] == 3
    r = _run(["estimate", "--scene", str(SCENE), "--from-gt", "--mask-weight", "-1", "--out", str(out3)])
    assert r.exit_code == 2 and "mask-weight" in r.output
    with pytest.raises(Exception, match="mask_band"):
        estimate_stage.resolve_conf("default", mask_band=-1)
    assert estimate_stage.resolve_conf("default", mask_band="3")["mask_band"] == 3
    from cosy_cli.objects import ObjectDatabase

    db = ObjectDatabase.from_models_dir(SCENE.parent.parent / "models")
    for w in (0.5, 2.0):
        est = estimate_stage.Estimator(estimate_stage.resolve_conf("default", mask_weight=w), db)
        try:
            assert est.verifier.conf.w_mask == w
        finally:
            est.close()
    from cosy_cli.errors import CosyError

    with pytest.raises(CosyError, match="icp_screen: expected a whole number, got 'many'"):
        estimate_stage.resolve_conf("default", icp_screen="many")
    with pytest.raises(CosyError, match="ICP screen >= 0"):
        estimate_stage.resolve_conf("default", icp_screen=-1)
    assert estimate_stage.resolve_conf("default", icp_screen="8")["icp_screen"] == 8  # `--set` values arrive as text
    c = estimate_stage.decide(estimate_stage.resolve_conf("default", coarse="templates", refiner="none"),
                              coarse_model=None, refiner_model=None, has_depth=False)
    assert c["rgb_refine"] == estimate_stage.RGB_REFINE_AUTO == "contour"
    assert "contour alignment" in estimate_stage.describe(c)
    assert c["verify_top"] == estimate_stage.VERIFY_TOP_RGB
    c = estimate_stage.decide(estimate_stage.resolve_conf("default", coarse="templates", refiner="none"),
                              coarse_model=None, refiner_model=None, has_depth=True)
    assert c["rgb_refine"] == "none" and c["depth_refine"] == "icp"
    assert c["verify_top"] == estimate_stage.VERIFY_TOP_DEPTH
    r = _run(["estimate", "--scene", str(SCENE), "--from-gt", "--verify-top", "many", "--out", str(out)])
    assert r.exit_code == 2 and "verify_top" in r.output and "many" in r.output


def test_pose_score_ranks_the_box_whose_pose_fits_first(tmp_path, templates_dir, ds):
    """--score pose: a candidate's score is the detection's x the verification score of its final
    pose. Each object of two sample images gets its GT box and a decoy (the box of another object
    in that image under this object's label, listed first), both with the detector's score 0.8:
    the detector cannot tell them apart; the pose score ranks the right box first."""
    gt = detections_from_gt(ds, [1], 0.1)
    gt = gt[gt.im_id.isin([0, 1])].reset_index(drop=True)
    dets, right = [], []
    for im, g in gt.groupby("im_id"):
        g = g.reset_index(drop=True)
        for i, r in g.iterrows():
            o = g.iloc[(i + 1) % len(g)]  # the next object's box, this object's label
            for box, is_right in (((o.x, o.y, o.w, o.h), False), ((r.x, r.y, r.w, r.h), True)):
                dets.append({"scene_id": 1, "image_id": int(im), "category_id": int(r.obj_id), "score": 0.8,
                             "bbox": [float(v) for v in box], "time": -1.0})
                right.append(is_right)
    right = np.array(right)
    det_path = tmp_path / "dets.json"
    det_path.write_text(json.dumps(dets))
    args = ["estimate", "--scene", str(SCENE), "--detections", str(det_path), "--coarse", "templates",
            "--refiner", "none", "--depth-refine", "none", "--verify-top", "16", "--rgb-refine", "none",
            "--top-k", "2", "--templates-dir", str(templates_dir)]
    tables = {}
    for score in ("detection", "pose"):
        out = tmp_path / f"{score}.csv"
        r = _run(args + ["--score", score, "--out", str(out)])
        assert r.exit_code == 0, r.output
        tables[score] = bop.read_results(out).table.reset_index(drop=True)
    det_t, pose_t = tables["detection"], tables["pose"]
    assert len(det_t) == len(pose_t) == len(dets)
    assert (det_t["score"] == 0.8).all()
    np.testing.assert_array_equal(pose_t["obj_id"], [d["category_id"] for d in dets])  # rows in the file's order
    p = pose_t["score"].to_numpy()
    assert ((p > 0) & (p <= 0.8)).all() and len(np.unique(p)) > len(p) // 2
    # per (image, label): the box that ranks first by the pose score is the right one
    top = pose_t.assign(right=right).sort_values("score", ascending=False, kind="stable").groupby(
        ["im_id", "obj_id"]).head(1)
    assert len(top) == len(gt) and top["right"].mean() >= 0.75, top
    conf = json.loads((tmp_path / "pose.json").read_text())["conf"]
    assert conf["score"] == "pose" and "score" not in json.loads((tmp_path / "detection.json").read_text())["conf"]
    # --max-per-object 1: the best candidate of each object and image is kept, the others dropped
    r = _run(args + ["--score", "pose", "--max-per-object", "1", "--out", str(tmp_path / "best.csv")])
    assert r.exit_code == 0, r.output
    assert "16 dropped" in r.output
    best = bop.read_results(tmp_path / "best.csv").table.reset_index(drop=True)
    assert len(best) == len(gt) and not best.duplicated(["im_id", "obj_id"]).any()
    merged = best.merge(top[["im_id", "obj_id", "score"]], on=["im_id", "obj_id"], suffixes=("", "_top"))
    np.testing.assert_allclose(merged["score"], merged["score_top"])
    assert json.loads((tmp_path / "best.json").read_text())["conf"]["max_per_object"] == 1
    timing = (tmp_path / "best.timing.csv").read_text().splitlines()
    assert sum(int(row.split(",")[2]) for row in timing[1:]) == len(dets)  # every detection was estimated
    r = _run(args + ["--score", "best", "--out", str(tmp_path / "x.csv")])
    assert r.exit_code == 2 and "best" in r.output


def test_rebox_estimates_again_from_the_box_of_the_pose(tmp_path, templates_dir, ds):
    """--rebox 1: each candidate is estimated again from the box its pose projects to, and the pose
    whose verification score is higher is kept. The boxes given here lose their top 35 % (as the
    onboarded detector's boxes lose the thin top of LM-O's watering can and glue): no candidate's
    score goes down, some poses are replaced, and the poses come nearer the GT (ADI, RGB only)."""
    gt = detections_from_gt(ds, [1], 0.1)
    gt = gt[gt.im_id.isin([0, 1, 2])].reset_index(drop=True)
    dets = [{"scene_id": 1, "image_id": int(r.im_id), "category_id": int(r.obj_id), "score": 0.8,
             "bbox": [float(r.x), float(r.y + 0.35 * r.h), float(r.w), float(0.65 * r.h)], "time": -1.0}
            for r in gt.itertuples()]
    det_path = tmp_path / "cut.json"
    det_path.write_text(json.dumps(dets))
    args = ["estimate", "--scene", str(SCENE), "--detections", str(det_path), "--coarse", "templates",
            "--refiner", "none", "--depth-refine", "none", "--verify-top", "16", "--rgb-refine", "contour",
            "--top-k", "3", "--score", "pose", "--hypotheses", "3", "--templates-dir", str(templates_dir)]
    tables, sidecars = {}, {}
    for n in (0, 1):
        out = tmp_path / f"rebox{n}.csv"
        r = _run(args + ["--rebox", str(n), "--out", str(out)])
        assert r.exit_code == 0, r.output
        assert ("rebox:" in r.output) == (n > 0), r.output
        tables[n] = bop.read_results(out)
        sidecars[n] = hyp_io.read_hypotheses(hyp_io.sidecar_path(out), len(tables[n]))
        conf = json.loads((tmp_path / f"rebox{n}.json").read_text())["conf"]
        assert conf.get("rebox", 0) == n and (n > 0 or "rebox" not in conf)  # recorded only when used
    t0, t1 = tables[0], tables[1]
    assert len(t0) == len(t1) == len(dets)
    s0, s1 = t0.table["score"].to_numpy(), t1.table["score"].to_numpy()  # rows in the file's order
    assert (s1 >= s0 - 1e-9).all()
    assert (s1 > s0 + 1e-9).any()
    # the sidecar: rank 0 is the row's pose; a replaced pose brings the runners-up of its own ranking
    moved = ~np.all(np.isclose(t0.T_cam_obj, t1.T_cam_obj), axis=(1, 2))
    assert moved.any() and not moved.all()
    for n, t in tables.items():
        det, rank, _, T = sidecars[n]
        np.testing.assert_allclose(T[rank == 0][np.argsort(det[rank == 0])], t.T_cam_obj, atol=1e-3)
    alt = {n: {(int(d), int(k)): T for d, k, T in zip(*sidecars[n][:2], sidecars[n][3]) if k > 0} for n in (0, 1)}
    for i in range(len(dets)):
        same = all(np.allclose(alt[0][(i, k)], alt[1][(i, k)]) for k in (1, 2)
                   if (i, k) in alt[0] and (i, k) in alt[1])
        assert same != moved[i], i
    db = ObjectDatabase.from_models_dir(SAMPLES / "models")
    scene_gt = ds.scene_gt(1)

    def err(t):
        return np.array([adi(T, scene_gt[int(g.im_id)][int(g.gt_index)].T_cam_obj, db[int(g.obj_id)].points)[0]
                         / db[int(g.obj_id)].diameter for T, g in zip(t.T_cam_obj, gt.itertuples())])
    e0, e1 = err(t0), err(t1)
    # (measured: median ADI 0.165 -> 0.127 of the diameter, within 0.1 of it 25 % -> 46 %; 19 of 24 replaced)
    assert np.median(e1) < np.median(e0) and (e1 < 0.1).mean() > (e0 < 0.1).mean(), (e0, e1)
    r = _run(args + ["--rebox", "4", "--out", str(tmp_path / "x.csv")])
    assert r.exit_code == 2 and "rebox" in r.output
