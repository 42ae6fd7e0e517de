"""One view is a valid input: a dataset of one image, or a scene/group of one view, runs through
``cosy run``, ``cosy match`` and ``cosy refine``; its candidates pass through as the result."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from cosy_cli.cli.main import cli
from cosy_cli.io import bop
from one_view_fixtures import bop_rows, one_image_dataset, tiny_templates


@pytest.fixture(scope="module")
def one_image(tmp_path_factory):
    return one_image_dataset(tmp_path_factory.mktemp("one_image") / "ds")


@pytest.fixture(scope="module")
def templates(tmp_path_factory):
    return tiny_templates(tmp_path_factory.mktemp("one_view_tpl") / "templates")


def _synth(dataset, out, profile="realistic"):
    r = CliRunner().invoke(cli, ["synth-candidates", "--dataset", str(dataset), "--out", str(out),
                                 "--profile", profile, "--seed", "1"])
    assert r.exit_code == 0, r.output
    return out


def test_one_image_dataset_runs_through_cosy_run_to_evaluation(one_image, templates, tmp_path):
    run = tmp_path / "run"
    r = CliRunner().invoke(cli, ["run", "--dataset", str(one_image), "--out", str(run), "--from-gt", "--config", "fast",
                                 "--templates-dir", str(templates), "--to", "evaluate"])
    assert r.exit_code == 0, r.output
    assert "single view: 1 of 1 group(s) had one view" in r.output
    m = json.loads((run / "run.json").read_text())
    assert m["status"] == "done" and m["single_view"] == {"groups": 1, "groups_total": 1, "scene_ids": [1]}
    # the predictions are the candidates (same rows, same poses and scores), in the BOP results format
    cands, preds = run / "estimate" / "candidates.csv", run / "refine" / "predictions.csv"
    assert len(bop_rows(cands)) == 8 and bop_rows(preds) == bop_rows(cands)
    assert preds.read_text().splitlines()[0] == ",".join(bop.RESULTS_COLUMNS)
    scene = json.loads((run / "refine" / "scene.json").read_text())
    (g,) = scene["groups"]
    assert g["single_view"] and g["note"] == "single view: candidates passed through"
    assert g["cameras"] == [{"im_id": 0, "T_world_cam": np.eye(4).tolist(), "placed_by": "single view"}] \
        and g["unplaced_im_ids"] == []
    assert "single-view group(s): candidates passed through" in (run / "scenes" / "000001" / "log.txt").read_text()
    # evaluated: single view and "multi-view" score the same predictions alike
    sv, mv = m["metrics"]["single_view"], m["metrics"]["multi_view"]
    assert mv == sv and sv["recall_adds_0.1d"] > 0
    cams = json.loads((run / "evaluate" / "multi_view" / "scores.json").read_text())["cameras"]
    assert cams["views"] == 1 and cams["views_placed"] == 1 and cams["pairs"] == 0


def test_match_and_refine_cli_on_a_one_view_scene_among_others(tmp_path):
    """Scene 2 reduced to one image next to scenes 1 and 3 of 8 images: scene 2 passes through,
    the others are matched and refined as before."""
    ds = one_image_dataset(tmp_path / "ds", keep={1: None, 2: [3], 3: None})
    cands = _synth(ds, tmp_path / "cands.csv")
    runner = CliRunner()
    m, out = tmp_path / "match", tmp_path / "refine"
    r = runner.invoke(cli, ["match", "--dataset", str(ds), "--candidates", str(cands), "--out", str(m)])
    assert r.exit_code == 0, r.output
    assert "1 single-view group(s): candidates passed through" in r.output
    doc = json.loads((m / "groups.json").read_text())
    assert doc["summary"]["single_view_groups"] == 1
    by_scene = {g["scene_id"]: g for g in doc["groups"]}
    g2 = by_scene[2]
    assert g2["single_view"] and g2["im_ids"] == [3] and g2["view_pairs"] == [] and g2["discarded"] == []
    c = bop.read_results(cands).table
    rows2 = np.flatnonzero(c["scene_id"].to_numpy() == 2)
    assert len(rows2) > 0
    assert [o["cand_ids"] for o in g2["objects"]] == [[int(i)] for i in rows2]  # one object per candidate
    assert "single_view" not in by_scene[1] and len(by_scene[1]["im_ids"]) == 8
    matches = np.loadtxt(m / "matches.csv", delimiter=",", skiprows=1, dtype=np.int64, usecols=(0, 6))
    assert sorted(matches[matches[:, 0] == 2, 1].tolist()) == list(range(len(rows2)))
    assert "\n2," not in (m / "view_pairs.csv").read_text()

    r = runner.invoke(cli, ["refine", "--dataset", str(ds), "--matches", str(m), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "1 single-view group(s): candidates passed through" in r.output
    scene = json.loads((out / "scene.json").read_text())
    assert scene["summary"]["single_view_groups"] == 1
    s2 = [g for g in scene["groups"] if g["scene_id"] == 2][0]
    assert s2["note"] == "single view: candidates passed through" and s2["gauge_im_id"] == 3
    assert s2["cameras"][0]["T_world_cam"] == np.eye(4).tolist()
    sub = tmp_path / "scene2_cands.csv"
    res = bop.read_results(cands)
    sel = res.table["scene_id"].to_numpy() == 2
    bop.write_results(sub, bop.PoseResults(res.table[sel].reset_index(drop=True), res.T_cam_obj[sel]))
    assert [x for x in bop_rows(out / "predictions.csv") if x[0] == 2] == bop_rows(sub)
    # the multi-view scenes were refined: every object in each of their 8 views
    others = [g for g in scene["groups"] if g["scene_id"] != 2]
    assert all(len(g["cameras"]) == 8 and g["stats"]["iterations"] > 0 for g in others)


def test_one_view_with_known_cameras_puts_the_view_in_the_dataset_world(one_image, tmp_path):
    cands = _synth(one_image, tmp_path / "cands.csv", "clean")
    runner = CliRunner()
    m, out = tmp_path / "match", tmp_path / "refine"
    r = runner.invoke(cli, ["match", "--dataset", str(one_image), "--candidates", str(cands), "--out", str(m),
                            "--known-cameras"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(cli, ["refine", "--dataset", str(one_image), "--matches", str(m), "--out", str(out)])
    assert r.exit_code == 0, r.output
    (g,) = json.loads((out / "scene.json").read_text())["groups"]
    from cosy_cli.geometry.poses import invert
    from cosy_cli.io.dataset import BopDataset

    T_wc = invert(BopDataset(one_image, "test").scene_camera(1)[0].T_cam_world)
    assert np.allclose(g["cameras"][0]["T_world_cam"], T_wc, atol=1e-6)
    res = bop.read_results(cands)
    o = g["objects"][0]
    assert np.allclose(o["T_world_obj"], T_wc @ res.T_cam_obj[o["cand_ids"][0]], atol=1e-3)
    assert bop_rows(out / "predictions.csv") == bop_rows(cands)
