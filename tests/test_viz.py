"""cosy viz: group figures and the HTML report of a run folder (built here from data_samples/)."""

from __future__ import annotations

import json
import os
import re
import shutil
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cosy_cli import viz
from cosy_cli.cli.main import cli
from cosy_cli.errors import CosyError
from cosy_cli.evaluation import evaluate_stage
from cosy_cli.io import bop
from cosy_cli.multiview import match_stage, refine_stage
from cosy_cli.synth import candidates as sc

DATA = Path(__file__).resolve().parents[1] / "data_samples"
quiet = lambda *a, **k: None  # noqa: E731


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """A run folder as cosy run writes it: scene 1 with candidates, match, refine and evaluation;
    scene 2 with candidates only (an interrupted run); scene 3 without any candidate."""
    R = tmp_path_factory.mktemp("run")
    all_c = R / "all_candidates.csv"
    sc.main(DATA, "test", all_c, profile="realistic", seed=3, log=quiet)
    res = bop.read_results(all_c)
    for s in (1, 2, 3):
        keep = np.flatnonzero(res.table["scene_id"].to_numpy() == s)
        keep = keep[:0] if s == 3 else keep
        sub = bop.PoseResults(res.table.iloc[keep].reset_index(drop=True), res.T_cam_obj[keep])
        bop.write_results(R / "scenes" / f"{s:06d}" / "candidates.csv", sub)
    d = R / "scenes" / "000001"
    match_stage.main(match_stage.resolve_conf("paper"), DATA, "test", d / "candidates.csv", d / "match", log=quiet,
                     progress=False)
    refine_stage.main(None, DATA, "test", d / "match", d / "refine", log=quiet, progress=False)
    (R / "estimate").mkdir()
    shutil.copy(d / "candidates.csv", R / "estimate" / "candidates.csv")
    (R / "refine").mkdir()
    shutil.copy(d / "refine" / "predictions.csv", R / "refine" / "predictions.csv")
    shutil.copy(d / "refine" / "scene.json", R / "refine" / "scene.json")
    for sub, preds in (("single_view", R / "estimate" / "candidates.csv"),
                       ("multi_view", R / "refine" / "predictions.csv")):
        evaluate_stage.main({"vsd": False}, DATA, "test", preds, R / "evaluate" / sub, scene_ids=[1], log=quiet,
                            progress=False)
    (R / "run.json").write_text(json.dumps({
        "format": "cosy-run", "version": 1, "dataset": str(DATA.resolve()), "split": "test", "scene_ids": [1, 2, 3],
        "config": "default <fast & small>", "confs": {"match": {"threshold_mm": 20.0}, "refine": {"iterations": 100}},
        "code_version": "test", "stages": {"estimate": {"status": "skipped", "time_s": 0.0},
                                           "match": {"status": "done", "time_s": 0.5}}}))
    return R


class _Links(HTMLParser):
    def __init__(self):
        super().__init__()
        self.links = []

    def handle_starttag(self, tag, attrs):
        for k, v in attrs:
            if k in ("href", "src") and v and not v.startswith("#"):
                self.links.append(v)


def test_visible_mask_ious_exact():
    inst = np.full((10, 10), -1)
    inst[0:4, 0:4] = 0  # 16 px, label 5
    inst[6:10, 6:10] = 1  # 16 px, label 7
    gt = np.zeros((3, 10, 10), dtype=bool)
    gt[0, 0:4, 0:2] = True  # inside instance 0: IoU 8/16
    gt[1, 6:10, 6:10] = True  # instance 1 exactly, but labelled 5: no same-label overlap
    gt[2, 6:10, 6:10] = True  # exact, label 7
    iou = viz.visible_mask_ious(inst, [5, 7], gt, [5, 5, 7])
    np.testing.assert_allclose(iou, [0.5, 0.0, 1.0])
    assert viz.visible_mask_ious(inst, [], gt, [5, 5, 7]).tolist() == [0, 0, 0]


def test_figures_and_report(run):
    logs = []
    out = viz.main(run, progress=False, log=logs.append)
    names = sorted(p.name for p in out["figures"])
    assert names == ["scene_000001_group_000.png", "scene_000002_group_000.png"]
    assert out["made"] == 2 and not out["failed"]
    assert any("scene(s) 3 (no candidates)" in m for m in logs)
    for p in out["figures"]:
        assert 50_000 < p.stat().st_size < 1_500_000, p
    from PIL import Image

    w, h = Image.open(run / "figures" / "scene_000001_group_000.png").size
    assert 1200 <= w <= 2600 and h > 0.3 * w  # three rows: candidates, refined, top view
    w2, h2 = Image.open(run / "figures" / "scene_000002_group_000.png").size
    assert h2 < h  # candidates only (no refine output): row 1 and the legend
    index = json.loads((run / "figures" / "index.json").read_text())
    assert index["scene_000001_group_000.png"]["views_placed"] == 8
    assert index["scene_000002_group_000.png"]["refined"] is False
    # 8 objects on the sample scenes' ground plane: the top view looks down its normal
    assert index["scene_000001_group_000.png"]["top_view_up"] == "support plane"
    # the refined objects re-projected through the recovered cameras cover the GT visible masks
    assert out["mask_iou_mean"]["scene_000001_group_000.png"] > 0.7

    html = (run / "report.html").read_text()
    parser = _Links()
    parser.feed(html)
    assert parser.links, "no links"
    for link in parser.links:
        assert (run / link).is_file(), link
    assert "figures/scene_000001_group_000.png" in parser.links
    assert "evaluate/multi_view/report.png" in parser.links
    for sub in ("single_view", "multi_view"):
        scores = json.loads((run / "evaluate" / sub / "scores.json").read_text())
        for k in ("auc_adds", "recall_adds_0.1d", "bop19_average_recall_mssd"):
            assert f">{scores[k]:.3f}<" in html, (sub, k)
    assert "default &lt;fast &amp; small&gt;" in html and "<fast" not in html
    assert re.search(r"<td>match</td><td>done</td>", html)

    # a second call keeps the figures; changed candidates redraw that scene's figure only
    again = viz.main(run, progress=False, log=quiet)
    assert again["made"] == 0 and again["kept"] == 2
    cands = run / "scenes" / "000002" / "candidates.csv"
    t = (run / "figures" / "scene_000002_group_000.png").stat().st_mtime + 5
    os.utime(cands, (t, t))
    third = viz.main(run, progress=False, log=quiet)
    assert third["made"] == 1 and third["kept"] == 1


def test_reprojection_ious_helper(run):
    rows = viz.reprojection_ious(run, 1, 0)
    iou = np.array([r["iou"] for r in rows])
    assert len(iou) >= 40  # 8 views x ~8 visible GT instances
    assert np.median(iou) > 0.8 and (iou > 0.5).mean() > 0.9


def test_unplaced_view_and_group_figure(run, tmp_path):
    R = tmp_path / "run"
    shutil.copytree(run / "scenes" / "000001", R / "scenes" / "000001")
    doc = json.loads((run / "run.json").read_text())
    doc["scene_ids"] = [1]
    (R / "run.json").write_text(json.dumps(doc))
    p = R / "scenes" / "000001" / "refine" / "scene.json"
    sj = json.loads(p.read_text())
    g = sj["groups"][0]
    cam = next(c for c in g["cameras"] if c["im_id"] != g["gauge_im_id"])
    g["cameras"].remove(cam)
    g["unplaced_im_ids"].append(cam["im_id"])
    p.write_text(json.dumps(sj))
    info = {}
    out = viz.group_figure(R, 1, 0, tmp_path / "fig.png", info=info)
    assert out.is_file() and 50_000 < out.stat().st_size < 1_500_000
    assert info["views_placed"] == 7 and info["views"] == 8
    # no evaluate folder: a report without metrics, and still only links to existing files
    html = viz.write_report(R, [out, tmp_path / "missing.png"], out_html=R / "report.html").read_text()
    assert "No evaluation in this run" in html and "missing.png" not in html
    # a damaged match output: that scene is reported, not a traceback
    (R / "scenes" / "000001" / "match" / "groups.json").write_text(json.dumps({"groups": [{"scene_id": 1}]}))
    res = viz.main(R, progress=False, log=quiet)
    assert res["made"] == 0 and len(res["failed"]) == 1 and res["failed"][0].startswith("scene 1: ")
    assert "unexpected content" in (R / "report.html").read_text()


def test_bad_input(run, tmp_path):
    with pytest.raises(CosyError, match="run.json is missing") as e:
        viz.main(tmp_path, progress=False, log=quiet)
    assert str(tmp_path) in str(e.value)
    (tmp_path / "run.json").write_text(json.dumps({"format": "cosy-match", "dataset": str(DATA), "split": "test",
                                                   "scene_ids": [1]}))
    with pytest.raises(CosyError, match="expected format 'cosy-run'"):
        viz.main(tmp_path, progress=False, log=quiet)
    (tmp_path / "run.json").write_text(json.dumps({"dataset": str(DATA), "split": "test"}))
    with pytest.raises(CosyError, match="scene_ids"):
        viz.main(tmp_path, progress=False, log=quiet)
    with pytest.raises(CosyError, match="scene 7 is not a scene of this run"):
        viz.main(run, scene_ids=[7], progress=False, log=quiet)
    res = CliRunner().invoke(cli, ["viz", "--run", str(tmp_path / "nowhere")])
    assert res.exit_code == 2 and "run folder not found" in res.output
    res = CliRunner().invoke(cli, ["viz", "--run", str(run), "--scene", "9"])
    assert res.exit_code == 2 and "scene 9 is not a scene of this run" in res.output


def test_palette_png_keeps_the_figure_colours():
    """A figure too large for MAX_PNG_BYTES is stored with 256 colours: the objects' colours (legend
    boxes, contours), white and black come back exactly, whatever colours the photos hold."""
    from PIL import Image

    from cosy_cli.viz import figures as F

    rng = np.random.default_rng(0)
    img = np.full((240, 480, 3), 255, dtype=np.uint8)
    img[:, 240:] = rng.integers(0, 256, (240, 240, 3))  # a "photo" of every colour
    img[:, 240:, 0] = np.linspace(0, 255, 240).astype(np.uint8)  # and smooth shades
    colors = F.PALETTE + [F.CAMERA_COLOR, F.GT_COLOR, F.DISCARDED_COLOR, "#000000"]
    for k, c in enumerate(colors):
        img[10 + 10 * (k // 4): 18 + 10 * (k // 4), 10 + 20 * (k % 4): 28 + 20 * (k % 4)] = np.round(F._rgb01(c) * 255)
    out = np.asarray(F._quantize(Image.fromarray(img)).convert("RGB"))
    for k, c in enumerate(colors):
        patch = out[10 + 10 * (k // 4): 18 + 10 * (k // 4), 10 + 20 * (k % 4): 28 + 20 * (k % 4)]
        assert (patch == np.round(F._rgb01(c) * 255)).all(), c
    assert (out[200:, :200] == 255).all()  # white stays white


def test_camera_labels_helpers():
    from cosy_cli.viz import figures as F

    assert F._id_list([10, 1, 2, 6, 7, 8, 9]) == "1, 2, 6–10"
    assert F._id_list([3, 4]) == "3, 4" and F._id_list([]) == ""
    pts = [np.array([0.0, 0]), np.array([5.0, 0]), np.array([100.0, 0]), np.array([3.0, 4])]
    assert F._clusters(pts, 10.0) == [[0, 1, 3], [2]]


def test_metrics_table_compares_values_as_shown():
    # equal to 3 decimals: neither is bold, and the difference is +0.000 (not a red -0.000)
    html = viz.report.metrics_table({"single view": {"auc_adds": 0.41404, "recall_adds_0.1d": 0.5},
                                     "multi-view": {"auc_adds": 0.41396, "recall_adds_0.1d": 0.6}})
    row = next(r for r in html.splitlines() if "auc_adds" in r)
    assert "better" not in row and "neg" not in row and "+0.000" in row and "-0.000" not in row
    row = next(r for r in html.splitlines() if "recall_adds_0.1d" in r)
    assert row.count("better") == 1 and 'class="num pos">+0.100' in row
