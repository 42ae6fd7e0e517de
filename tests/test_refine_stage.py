"""cosy refine: the stage over cosy match's output (files, world frames, options, CLI)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

sys.path.insert(0, str(Path(__file__).parent))

from multiview_fixtures import make_table_dataset  # noqa: E402

from cosy_cli.cli.main import cli  # noqa: E402
from cosy_cli.geometry.poses import invert, relative_pose_error  # noqa: E402
from cosy_cli.io import bop  # noqa: E402
from cosy_cli.io.dataset import BopDataset  # noqa: E402
from cosy_cli.multiview import match_stage, refine_stage  # noqa: E402
from cosy_cli.objects import ObjectDatabase  # noqa: E402
from cosy_cli.synth import candidates as sc  # noqa: E402


@pytest.fixture(scope="module")
def tables(tmp_path_factory) -> Path:
    """2 scenes x 5 views x 7 objects of the simple models (box, cylinder, L, look-alikes)."""
    return make_table_dataset(tmp_path_factory.mktemp("tables"), n_scenes=2, n_views=5, n_objects=7, seed=11)


def _cands(root: Path, out: Path, profile="realistic", seed=0, **knobs):
    csv = out / f"c_{profile}_{seed}.csv"
    sc.main(root, "test", csv, profile=profile, seed=seed, gt_out=out / f"c_{profile}_{seed}_gt.csv",
            log=lambda *_: None, **knobs)
    return csv


def _match(root, csv, out, **conf):
    c = match_stage.resolve_conf("paper", **conf)
    match_stage.main(c, root, "test", csv, out, overwrite=True, log=lambda *_: None, progress=False)
    return out


def _refine(root, matches, out, **conf):
    return refine_stage.main(refine_stage.resolve_conf(None, **conf), root, "test", matches, out, overwrite=True,
                             log=lambda *_: None, progress=False)


def _errors(root: Path, res: bop.PoseResults) -> np.ndarray:
    """D_l (mm) of each estimate to the nearest GT instance of its label in its image (the
    continuous symmetries in 360 steps)."""
    ds = BopDataset(root, "test")
    db = ObjectDatabase.from_models_dir(ds.models_dir, n_points=200)
    out = []
    for i in range(len(res)):
        s, im, o = (int(res.table[c].iat[i]) for c in ("scene_id", "im_id", "obj_id"))
        m = db[o]
        X = m.points.T
        TS = res.T_cam_obj[i] @ m.symmetries_with_steps(360)
        p1 = TS[:, :3, :3] @ X + TS[:, :3, 3:]  # (S, 3, P)
        d = [np.sqrt(((p1 - (g.T_cam_obj[:3, :3] @ X + g.T_cam_obj[:3, 3:])) ** 2).sum(1)).mean(1).min()
             for g in ds.scene_gt(s)[im] if g.obj_id == o]
        out.append(min(d))
    return np.array(out)


def _camera_errors(root: Path, scene: dict):
    ds = BopDataset(root, "test")
    errs = []
    for g in scene["groups"]:
        cams = ds.scene_camera(g["scene_id"])
        C = {c["im_id"]: np.array(c["T_world_cam"]) for c in g["cameras"]}
        ids = sorted(C)
        for a in ids:
            for b in ids:
                if a < b:
                    errs.append(relative_pose_error(invert(C[a]) @ C[b],
                                                    cams[a].T_cam_world @ invert(cams[b].T_cam_world)))
    return np.array(errs)


def test_exact_candidates_give_an_exact_scene(tables, tmp_path):
    csv = _cands(tables, tmp_path, "clean", p_flip=1.0)
    m = _match(tables, csv, tmp_path / "m")
    summary = _refine(tables, m, tmp_path / "r")
    scene = json.loads((tmp_path / "r" / "scene.json").read_text())
    assert scene["format"] == "cosy-refine" and summary["views_placed"] == summary["views"] == 10
    for g in scene["groups"]:
        assert g["cameras"][0]["im_id"] == g["gauge_im_id"]
        np.testing.assert_allclose(g["cameras"][0]["T_world_cam"], np.eye(4), atol=1e-12)
        assert g["stats"]["converged"] and g["stats"]["final_cost_px2"] < 1e-10
        assert len(g["objects"]) == 7
    err = _camera_errors(tables, scene)
    assert err[:, 0].max() < 1e-3 and err[:, 1].max() < 0.01
    pred = bop.read_results(tmp_path / "r" / "predictions.csv")
    assert len(pred) == 2 * 5 * 7  # every object in every placed view
    assert _errors(tables, pred).max() < 0.3  # 0: the cylinder's 360-step evaluation set is the floor


def test_realistic_candidates_are_improved(tables, tmp_path):
    csv = _cands(tables, tmp_path, "realistic", seed=3)
    m = _match(tables, csv, tmp_path / "m")
    _refine(tables, m, tmp_path / "r", output="scene")
    cands = bop.read_results(m / "candidates.csv")
    matches = pd.read_csv(m / "matches.csv")
    used = matches.cand_id[matches.object_id >= 0].to_numpy()
    e_in = _errors(tables, bop.PoseResults(cands.table.iloc[used].reset_index(drop=True), cands.T_cam_obj[used]))
    pred = bop.read_results(tmp_path / "r" / "predictions.csv")
    e_out = _errors(tables, pred)
    # the same (image, object label) pairs as the matched inputs, good inputs only (< 30 mm)
    key = lambda t: list(zip(t.scene_id, t.im_id, t.obj_id))  # noqa: E731
    ok_in = e_in < 30
    keys = set(k for k, ok in zip(key(cands.table.iloc[used]), ok_in) if ok)
    sel = np.array([k in keys for k in key(pred.table)])
    assert sel.sum() >= 0.8 * ok_in.sum()
    assert np.median(e_out[sel]) < 0.8 * np.median(e_in[ok_in])
    scene = json.loads((tmp_path / "r" / "scene.json").read_text())
    err = _camera_errors(tables, scene)
    assert np.median(err[:, 0]) < 1.5 and np.median(err[:, 1]) < 15.0


def test_known_cameras_world_frame_and_output(tables, tmp_path):
    csv = _cands(tables, tmp_path, "realistic", seed=4, fp_per_image=1.0)
    m = _match(tables, csv, tmp_path / "m", known_cameras=True)
    _refine(tables, m, tmp_path / "r", output="scene")
    scene = json.loads((tmp_path / "r" / "scene.json").read_text())
    ds = BopDataset(tables, "test")
    assert scene["known_cameras"] and "dataset world" in scene["world_frame"]
    for g in scene["groups"]:
        cams = ds.scene_camera(g["scene_id"])
        for c in g["cameras"]:
            np.testing.assert_allclose(c["T_world_cam"], invert(cams[c["im_id"]].T_cam_world), atol=1e-6)
            assert c["placed_by"] == "known"
    base = bop.read_results(tmp_path / "r" / "predictions.csv")
    assert base.table.score.min() >= 1.0  # refined predictions: 1 + the object's score
    # default output (the paper's ba_output+all_cand): + the candidates no refined object explains
    summary = _refine(tables, m, tmp_path / "r2")
    more = bop.read_results(tmp_path / "r2" / "predictions.csv")
    assert summary["output"] == "scene+candidates" and summary["unmatched_predictions"] > 0
    assert len(more) == len(base) + summary["unmatched_predictions"]
    fb = more.table.score.to_numpy() < 1.0
    assert fb.sum() == summary["unmatched_predictions"]
    assert more.table.score[fb].max() < base.table.score.min()  # strictly below every refined prediction
    cands = bop.read_results(m / "candidates.csv")
    diam = {o: i.diameter for o, i in ds.models_info().items()}
    ref = more.table[~fb]
    for i in np.flatnonzero(fb):
        r = more.table.iloc[i]
        # a fallback is a candidate, unchanged, with half its score ...
        same = np.flatnonzero((cands.table.im_id == r.im_id) & (cands.table.obj_id == r.obj_id)
                              & (np.abs(cands.table.score * 0.5 - r.score) < 1e-6)).tolist()
        assert any(np.allclose(cands.T_cam_obj[c], more.T_cam_obj[i], atol=1e-4) for c in same)
        # ... that no refined prediction of its label in its image explains
        k = np.flatnonzero((ref.scene_id == r.scene_id) & (ref.im_id == r.im_id) & (ref.obj_id == r.obj_id))
        d = np.linalg.norm(more.T_cam_obj[ref.index[k], :3, 3] - more.T_cam_obj[i, :3, 3], axis=1)
        assert (d >= 0.5 * diam[int(r.obj_id)]).all()
    # the old setting is the new default
    assert refine_stage.resolve_conf(None, keep_unmatched=True)["output"] == "scene+candidates"
    assert refine_stage.resolve_conf({"keep_unmatched": False})["output"] == "scene"


def test_nms_merges_objects_of_a_label(tables, tmp_path):
    csv = _cands(tables, tmp_path, "clean")
    m = _match(tables, csv, tmp_path / "m")
    _refine(tables, m, tmp_path / "r", nms_mm=5000.0)  # everything of a label within 5 m: one object per label
    scene = json.loads((tmp_path / "r" / "scene.json").read_text())
    for g in scene["groups"]:
        labels = [o["obj_id"] for o in g["objects"]]
        assert len(labels) == len(set(labels))
        assert sum(o["n_candidates"] for o in g["objects"]) == g["stats"]["n_candidates"]
        assert g["stats"]["n_merged_objects"] == 7 - len(labels)


def test_cli_skip_overwrite_and_errors(tables, tmp_path):
    csv = _cands(tables, tmp_path, "clean")
    m = _match(tables, csv, tmp_path / "m")
    out = tmp_path / "r"
    runner = CliRunner()
    args = ["refine", "--dataset", str(tables), "--split", "test", "--matches", str(m), "--out", str(out)]
    r = runner.invoke(cli, args)
    assert r.exit_code == 0, r.output
    assert "views placed" in r.output and (out / "scene.json").is_file()
    r = runner.invoke(cli, args)
    assert r.exit_code == 0 and "up to date, skipping" in r.output
    r = runner.invoke(cli, args + ["--loss-threshold-px", "10"])
    assert r.exit_code == 2 and "settings changed" in r.output and "loss_threshold_px" in r.output
    r = runner.invoke(cli, args + ["--loss-threshold-px", "10", "--iterations", "20", "--overwrite"])
    assert r.exit_code == 0, r.output
    assert json.loads((out / "scene.json").read_text())["conf"]["iterations"] == 20
    # an incomplete match folder: one line naming it, exit 2, nothing written
    (m / "groups.json").rename(m / "groups.json.bak")
    out2 = tmp_path / "r2"
    r = runner.invoke(cli, ["refine", "--dataset", str(tables), "--matches", str(m), "--out", str(out2)])
    assert r.exit_code == 2 and "not a complete cosy match output" in r.output and "groups.json" in r.output
    assert not out2.exists()
    (m / "groups.json.bak").rename(m / "groups.json")
    r = runner.invoke(cli, ["refine", "--dataset", str(tables), "--split", "val", "--matches", str(m),
                            "--out", str(out2)])
    assert r.exit_code == 2 and not out2.exists()


def test_overlapping_objects_of_lookalike_labels_are_suppressed():
    """Two solids cannot share the space: the weaker of two coincident objects is dropped, even
    with different labels (a look-alike swapped in several views); far objects are untouched."""
    from cosy_cli.geometry import make_pose
    from cosy_cli.multiview.refine_stage import _nms

    T = make_pose(np.eye(3)[None].repeat(4, 0), np.array([[0, 0, 0], [5.0, 0, 0], [200, 0, 0], [203, 0, 0]]))
    obj_ids = np.array([6, 7, 6, 6])
    n_c = np.array([2, 6, 5, 3])
    score = np.array([0.9, 0.8, 0.7, 0.95])
    diam = np.full(4, 100.0)
    keep, into = _nms(T, obj_ids, n_c, score, 0.0, diam, 0.5)
    assert keep.tolist() == [False, True, True, False] and into.tolist() == [-1, 1, 2, -1]
    keep, into = _nms(T, obj_ids, n_c, score, 10.0, diam, 0.0)  # same-label 3D NMS only: a merge
    assert keep.tolist() == [True, True, True, False] and into.tolist() == [0, 1, 2, 2]


def test_foreign_or_edited_match_dir_and_unconnected_views(tables, tmp_path):
    """A foreign groups.json or an unknown obj_id: one line, exit 2, nothing written. A view
    that cannot be connected to the others is reported as unplaced, not guessed."""
    import shutil

    csv = _cands(tables, tmp_path, "clean")
    m = _match(tables, csv, tmp_path / "m")
    runner = CliRunner()

    def refine(mdir, out):
        return runner.invoke(cli, ["refine", "--dataset", str(tables), "--matches", str(mdir), "--out", str(out)])

    cases = {"foreign": ("format", "something-else", "expected format 'cosy-match'"),
             "unknown_obj": ("obj_id", 99, "object 99")}
    for name, (key, value, message) in cases.items():
        d = tmp_path / name
        shutil.copytree(m, d)
        doc = json.loads((d / "groups.json").read_text())
        if key == "format":
            doc["format"] = value
        else:
            doc["groups"][0]["objects"][0]["obj_id"] = value
        (d / "groups.json").write_text(json.dumps(doc))
        (d / "manifest.json").unlink()  # a hand-edited folder, to be read as it is (see test_stage_integrity.py)
        r = refine(d, tmp_path / f"out_{name}")
        assert r.exit_code == 2 and message in r.output and "Traceback" not in r.output, r.output
        assert not (tmp_path / f"out_{name}").exists()
    d = tmp_path / "cut"
    shutil.copytree(m, d)
    doc = json.loads((d / "groups.json").read_text())
    g = doc["groups"][0]
    lonely = g["im_ids"][-1]
    for vp in g["view_pairs"]:
        if lonely in (vp["im_id_a"], vp["im_id_b"]):
            vp["linked"], vp["n_inliers"] = False, 0
    (d / "groups.json").write_text(json.dumps(doc))
    (d / "manifest.json").unlink()
    r = refine(d, tmp_path / "out_cut")
    assert r.exit_code == 0, r.output
    scene = json.loads((tmp_path / "out_cut" / "scene.json").read_text())
    assert scene["groups"][0]["unplaced_im_ids"] == [lonely]
    assert lonely not in [c["im_id"] for c in scene["groups"][0]["cameras"]]
