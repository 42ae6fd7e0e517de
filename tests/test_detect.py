"""`cosy detect` (sources, importers, checks, caching), `cosy evaluate-detections` (COCO AP, confusion)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from cosy_cli.cli.main import cli
from cosy_cli.detection import importers, stage
from cosy_cli.errors import CosyError, DatasetProblems
from cosy_cli.evaluation import detection_ap
from cosy_cli.io import bop, images
from cosy_cli.io.dataset import BopDataset

SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"
SCENE = SAMPLES / "test" / "000001"
COLS = ["scene_id", "im_id", "obj_id", "score", "x", "y", "w", "h"]


@pytest.fixture(scope="module")
def ds():
    return BopDataset(SAMPLES, "test")


@pytest.fixture(scope="module")
def gt_dets(ds):
    """GT boxes of scene 1 with distinct scores and times (what a detector could have written)."""
    d = importers.detections_from_gt(ds, [1], 0.1).drop(columns=["gt_index"])
    rng = np.random.default_rng(0)
    d["score"] = np.round(rng.uniform(0.3, 1.0, len(d)), 4)
    d["time"] = 0.125
    d["segmentation"] = None
    return d


def _run(args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def _write(path: Path, data) -> Path:
    path.write_text(json.dumps(data))
    return path


# ------------------------------------------------------------------------------------------------
# ground truth boxes
# ------------------------------------------------------------------------------------------------
def test_gt_boxes_are_the_boxes_of_the_rendered_visible_masks(ds):
    dets = importers.detections_from_gt(ds, [1], 0.1)
    assert len(dets) == 64
    for r in dets.itertuples(index=False):
        m = images.read_mask(ds.mask_path(1, r.im_id, r.gt_index, visib=True))
        ys, xs = np.nonzero(m)
        # BOP's bbox convention (bop_toolkit calc_2d_bbox): w = x_max - x_min, h = y_max - y_min
        np.testing.assert_array_equal([r.x, r.y, r.w, r.h],
                                      [xs.min(), ys.min(), xs.max() - xs.min(), ys.max() - ys.min()])
        assert ds.scene_gt(1)[r.im_id][r.gt_index].obj_id == r.obj_id and r.score == 1.0
    # the visibility threshold drops the less visible instances (scene 2 has one under 0.5)
    assert len(importers.detections_from_gt(ds, [2], 0.5)) == len(importers.detections_from_gt(ds, [2], 0.1)) - 1


def test_estimate_stage_uses_the_moved_gt_importer():
    from cosy_cli.singleview import estimate_stage

    assert estimate_stage.detections_from_gt is importers.detections_from_gt


# ------------------------------------------------------------------------------------------------
# importers: round trips
# ------------------------------------------------------------------------------------------------
def test_bop_round_trip(tmp_path, ds, gt_dets):
    p = tmp_path / "dets.json"
    importers.write_detections(p, gt_dets)
    back = importers.read_detections_any(p)
    assert back.attrs["format"] == "bop"
    pd.testing.assert_frame_equal(back[COLS + ["time"]], gt_dets[COLS + ["time"]].reset_index(drop=True))
    # checked against the dataset: nothing to clip, same table; the BOP reader of io agrees
    pd.testing.assert_frame_equal(importers.read_detections_any(p, ds)[COLS], back[COLS])
    pd.testing.assert_frame_equal(bop.read_detections(p)[COLS], back[COLS])


def test_coco_round_trip_with_encoded_and_mapped_image_ids(tmp_path, ds, gt_dets):
    p = tmp_path / "coco_results.json"
    importers.write_coco_results(p, gt_dets)
    raw = json.loads(p.read_text())
    assert set(raw[0]) == {"image_id", "category_id", "bbox", "score"}
    assert raw[0]["image_id"] == 1 * 1_000_000 + int(gt_dets.iloc[0].im_id)
    back = importers.read_detections_any(p, ds)
    assert back.attrs["format"] == "coco" and (back["time"] == -1).all()
    pd.testing.assert_frame_equal(back[COLS], gt_dets[COLS].reset_index(drop=True))

    # image ids of a COCO dataset file: file_name holds the BOP scene and image ids
    ims = sorted(set(gt_dets["im_id"]))
    ids = {im: 7 + 3 * k for k, im in enumerate(ims)}  # arbitrary COCO ids
    names = [f"test/000001/rgb/{im:06d}.png" if k % 2 else f"000001/rgb/{im:06d}.png" for k, im in enumerate(ims)]
    coco_ds = _write(tmp_path / "coco_dataset.json", {
        "images": [{"id": ids[im], "file_name": n, "width": 640, "height": 480} for im, n in zip(ims, names)],
        "annotations": [], "categories": []})
    q = tmp_path / "coco_results_mapped.json"
    _write(q, importers.coco_results(gt_dets, image_ids=[ids[i] for i in gt_dets["im_id"]]))
    back = importers.read_detections_any(q, ds, coco_images=coco_ds)
    pd.testing.assert_frame_equal(back[COLS], gt_dets[COLS].reset_index(drop=True))
    # an id the dataset file lacks is named
    _write(q, [{"image_id": 999, "category_id": 1, "bbox": [1, 2, 3, 4], "score": 0.5}])
    with pytest.raises(CosyError, match=r"detection 0: image_id 999 is not in the images of .*coco_dataset.json"):
        importers.read_detections_any(q, coco_images=coco_ds)


def test_empty_file_is_an_empty_table(tmp_path, ds):
    d = importers.read_detections_any(_write(tmp_path / "e.json", []), ds)
    assert len(d) == 0 and list(d.columns) == importers.TABLE_COLUMNS


# ------------------------------------------------------------------------------------------------
# importers: bad input
# ------------------------------------------------------------------------------------------------
def _det(**kw):
    d = {"scene_id": 1, "image_id": 0, "category_id": 1, "score": 0.9, "bbox": [100, 100, 50, 40]}
    d.update(kw)
    return d


@pytest.mark.parametrize("data, match", [
    ({"detections": []}, r"bad\.json: expected a JSON list of detections"),
    ({"images": [], "annotations": []}, r"bad\.json: this is a COCO dataset file .* --coco-images"),
    ([_det(), {"scene_id": 1, "image_id": 0, "category_id": 1, "score": 0.9}],
     r"bad\.json: detection 1: missing key\(s\) 'bbox'"),
    ([_det(), "oops"], r"bad\.json: detection 1: expected an object"),
    ([_det(category_id=2.5)], r"bad\.json: detection 0: category_id: expected an integer"),
    ([_det(score=float("nan"))], r"bad\.json: detection 0: score: expected a finite number"),
    ([_det(bbox=[1, 2, 3])], r"bad\.json: detection 0: bbox: expected \[x, y, w, h\]"),
    ([_det(bbox=[1, 2, 0, 5])], r"bad\.json: detection 0: bbox .* width and height must be > 0"),
])
def test_wrong_json_shape_is_refused_with_file_and_index(tmp_path, data, match):
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(data))  # NaN is written as the (non-standard) JSON literal NaN
    with pytest.raises(CosyError, match=match):
        importers.read_detections_any(p)


@pytest.mark.parametrize("det, match", [
    (_det(category_id=99), r"detection 0: category_id 99 is not an object of the dataset \(models_info.json has"),
    (_det(scene_id=7), r"detection 0: scene_id 7 is not a scene of"),
    (_det(image_id=999), r"detection 0: image_id 999 is not an image of scene 1"),
    (_det(bbox=[700, 100, 50, 40]), r"detection 0: bbox .* lies outside the 640x480 image 0 of scene 1"),
    (_det(bbox=[-60, 100, 50, 40]), r"detection 0: bbox .* lies outside the 640x480 image"),
    (_det(bbox=[600, 100, 90, 40]), r"detection 0: bbox .* leaves by 50.0 px \(more than 4 px\) the 640x480 image"),
])
def test_detections_that_do_not_fit_the_dataset_are_refused(tmp_path, ds, det, match):
    p = _write(tmp_path / "dets.json", [det])
    with pytest.raises(CosyError, match=r"dets\.json: " + match):
        importers.read_detections_any(p, ds)


def test_small_overhang_is_clipped_and_many_problems_are_listed(tmp_path, ds):
    p = _write(tmp_path / "dets.json", [_det(bbox=[-3, 470, 50, 12.5])])
    d = importers.read_detections_any(p, ds)
    np.testing.assert_allclose(d[["x", "y", "w", "h"]].to_numpy(), [[0, 470, 47, 10]])
    p = _write(tmp_path / "dets.json", [_det(), _det(category_id=99), _det(), _det(image_id=999),
                                        _det(bbox=[900, 0, 5, 5])] + [_det(category_id=50)] * 30)
    with pytest.raises(DatasetProblems) as e:
        importers.read_detections_any(p, ds)
    lines = e.value.problems
    assert len(lines) == importers.MAX_PROBLEM_LINES + 1 and "33 in all" in lines[-1]
    assert all(str(p) in line for line in lines)
    assert "detection 1: category_id 99" in lines[0] and any("detection 3: image_id 999" in x for x in lines)
    assert any("detection 4: bbox" in x and "outside" in x for x in lines)


# ------------------------------------------------------------------------------------------------
# the stage and the command
# ------------------------------------------------------------------------------------------------
def test_detect_from_gt_feeds_estimate_and_is_cached(tmp_path, ds):
    out = tmp_path / "dets.json"
    r = _run(["detect", "--scene", SCENE, "--from-gt", "--out", out, "--quiet"])
    assert r.exit_code == 0, r.output
    dets = importers.read_detections_any(out, ds)
    mask_boxes = importers.detections_from_gt(ds, [1], 0.1)
    pd.testing.assert_frame_equal(dets[COLS], mask_boxes[COLS])
    doc = json.loads((tmp_path / "dets.meta.json").read_text())
    assert doc["inputs"]["source"] == "gt" and doc["detections"] == 64 and doc["detections_per_object"]["3"] == 8
    # cached: a second run skips; other settings are refused without --overwrite
    r = _run(["detect", "--scene", SCENE, "--from-gt", "--out", out])
    assert r.exit_code == 0 and "skipping" in r.output
    r = _run(["detect", "--scene", SCENE, "--from-gt", "--out", out, "--min-score", "0.5"])
    assert r.exit_code == 2 and "settings changed (min_score)" in r.output and "--overwrite" in r.output
    r = _run(["detect", "--scene", SCENE, "--from-gt", "--out", out, "--min-score", "0.5", "--overwrite"])
    assert r.exit_code == 0 and "skipping" not in r.output

    # `cosy estimate --detections` takes the file unchanged (tiny templates: fast)
    from cosy_cli.singleview.training_free import templates

    tpl = tmp_path / "templates"
    templates.main({"viewpoints": 30, "inplane": 6}, SAMPLES / "models", tpl, log=lambda *_: None)
    cands = tmp_path / "cands.csv"
    r = _run(["estimate", "--scene", SCENE, "--detections", out, "--coarse", "templates", "--refiner", "none",
              "--depth-refine", "none", "--top-k", "1", "--templates-dir", tpl, "--out", cands, "--quiet"])
    assert r.exit_code == 0, r.output
    res = bop.read_results(cands)
    assert len(res) == 64 and set(res.table["obj_id"]) == set(range(1, 9))


def _import_filtered(src: Path, out: Path, *options):
    """`cosy detect --from-json src` of scene 1 with filter options: the detections it kept."""
    r = _run(["detect", "--dataset", SAMPLES, "--scene-id", 1, "--from-json", src, "--out", out, *options, "--quiet"])
    assert r.exit_code == 0, r.output
    return bop.read_detections(out)


def test_detect_imports_coco_results_and_filters(tmp_path, ds, gt_dets):
    src = tmp_path / "coco.json"
    d = gt_dets.copy()
    d.loc[d.index[:5], "score"] = 0.1  # under --min-score
    importers.write_coco_results(src, d)
    out = tmp_path / "dets.json"
    back = _import_filtered(src, out, "--max-per-image", 6)
    expect = stage.keep_best(d[d["score"] >= 0.3], 0.3, 6)
    assert len(back) == len(expect) and back.groupby("im_id").size().max() == 6
    assert (back["score"] >= 0.3).all()
    doc = json.loads((tmp_path / "dets.meta.json").read_text())
    assert doc["inputs"]["detections"]["sha1"] and doc["conf"]["max_per_image"] == 6
    # the source file changed -> refused
    importers.write_coco_results(src, d.iloc[1:])
    r = _run(["detect", "--dataset", SAMPLES, "--scene-id", 1, "--from-json", src, "--out", out,
              "--max-per-image", 6])
    assert r.exit_code == 2 and "inputs changed (detections)" in r.output


def test_at_most_n_detections_per_object_and_image(tmp_path, ds, gt_dets):
    """--max-per-object keeps the best N of each object in each image (one instance of each object
    per image, as in LM-O: the best-scored box of each label)."""
    d = pd.concat([gt_dets.assign(score=0.9), gt_dets.assign(score=0.5, x=gt_dets["x"] + 7)], ignore_index=True)
    importers.write_detections(tmp_path / "dup.json", d)
    back = _import_filtered(tmp_path / "dup.json", tmp_path / "one.json", "--max-per-object", 1)
    assert back.groupby(["im_id", "obj_id"]).size().max() == 1 and len(back) == len(gt_dets)
    assert (back["score"] == 0.9).all()  # the better of each pair
    both = stage.keep_best(d, 0.3, 100, 0)
    assert len(both) == len(d) and len(stage.keep_best(d, 0.3, 100, 2)) == len(d)
    assert stage.resolve_conf("default")["max_per_object"] == 0


def test_bad_input_exits_2_with_one_line(tmp_path):
    bad = _write(tmp_path / "bad.json", [_det(category_id=42)])
    out = tmp_path / "dets.json"
    r = _run(["detect", "--scene", SCENE, "--from-json", bad, "--out", out])
    assert r.exit_code == 2 and not out.exists()
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "bad.json: detection 0: category_id 42" in lines[0]
    r = _run(["detect", "--scene", SCENE, "--from-json", _write(tmp_path / "d.json", {"a": 1}), "--out", out])
    assert r.exit_code == 2 and "d.json: expected a JSON list" in r.output and len(r.output.strip().splitlines()) == 1
    r = _run(["detect", "--scene", SCENE, "--from-json", bad, "--from-gt", "--out", out])
    assert r.exit_code == 2 and "--from-json and --from-gt" in r.output
    r = _run(["detect", "--scene", SCENE, "--model", tmp_path / "nope.onnx", "--out", out])
    assert r.exit_code == 2 and "nope.onnx" in r.output and "cosy train detector" in r.output
    r = _run(["detect", "--scene", SCENE, "--from-gt", "--coco-images", bad, "--out", out])
    assert r.exit_code == 2 and "--coco-images goes with --from-json" in r.output


class FakeDetector:
    """Returns fixed boxes: one overhanging the image, one of an unknown label, one per known label."""

    def __init__(self):
        self.calls = []

    def detect(self, rgb, min_score, max_per_image, nms_iou):
        self.calls.append((rgb.shape, min_score, max_per_image, nms_iou))
        boxes = np.array([[600, 400, 80, 120], [10, 10, 30, 30], [100, 100, 40, 40], [200, 100, 40, 40]], float)
        return boxes, np.array([0.9, 0.8, 0.7, 0.6]), np.array([3, 99, 5, 6])


def test_model_branch_with_an_injected_detector(tmp_path, ds):
    fake = FakeDetector()
    lines = []
    s = stage.main({"min_score": 0.5, "max_per_image": 2}, SAMPLES, "test", tmp_path / "d.json", scene_ids=[1],
                   detector=fake, log=lines.append, progress=False)
    # one untimed warm-up call, then one per image
    assert len(fake.calls) == 1 + 8 and fake.calls[0] == ((480, 640, 3), 0.5, 2, 0.5)
    d = bop.read_detections(tmp_path / "d.json")
    assert len(d) == 16 and set(d["obj_id"]) == {3, 5}  # label 99 dropped, then at most 2 per image
    assert any("obj_id 99 x8" in x for x in lines)
    first = d[d["obj_id"] == 3].iloc[0]
    np.testing.assert_allclose([first.x, first.y, first.w, first.h], [600, 400, 40, 80])  # clipped to 640x480
    assert (d["time"] > 0).all() and s["time_per_image_s"] > 0
    assert s["detections_per_object"] == {"3": 8, "5": 8}


def test_the_shipped_detector_is_the_default(tmp_path, monkeypatch):
    monkeypatch.setattr(stage, "SHIPPED_DETECTOR", tmp_path / "missing.onnx")
    with pytest.raises(CosyError, match="no detector model was given and none is shipped"):
        stage.main(None, SAMPLES, "test", tmp_path / "d.json", scene_ids=[1])


def test_model_branch_with_a_real_exported_detector(tmp_path, ds):
    """An (untrained) detector exported to ONNX goes through OnnxDetector: boxes inside the image,
    labels of the dataset, the detector's time per image; the file passes the dataset checks."""
    from cosy_cli.detection.model import CenterNet, DetectorConfig
    from cosy_cli.detection.train import export_onnx

    model = tmp_path / "det.onnx"
    export_onnx(CenterNet(DetectorConfig(obj_ids=sorted(ds.models_info()), input_size=(64, 48))), model)
    out = tmp_path / "d.json"
    r = _run(["detect", "--scene", SCENE, "--model", model, "--min-score", 0, "--max-per-image", 5, "--out", out,
              "--quiet"])
    assert r.exit_code == 0, r.output
    d = importers.read_detections_any(out, ds)
    assert len(d) == 8 * 5 and d.groupby("im_id").size().eq(5).all()
    assert set(d["obj_id"]) <= set(ds.models_info()) and (d["time"] > 0).all()
    assert ((d["x"] + d["w"]) <= 640).all() and ((d["y"] + d["h"]) <= 480).all()
    doc = json.loads((tmp_path / "d.meta.json").read_text())
    assert doc["inputs"]["model"]["sha1"] and doc["time_per_image_s"] > 0


def test_tile_windows_cover_the_image_and_overlap():
    from cosy_cli.detection.network import tile_windows

    for n in (2, 3, 4):
        w = np.array(tile_windows(640, 480, n))
        assert len(w) == n * n and (w[:, 0] >= 0).all() and (w[:, 2] <= 640).all() and (w[:, 3] <= 480).all()
        cover = np.zeros((480, 640), bool)
        for x0, y0, x1, y1 in w:
            cover[y0:y1, x0:x1] = True
        assert cover.all()
        assert np.allclose(w[:, 2] - w[:, 0], 640 * 1.25 / n, atol=1)  # (1 + overlap) / n of the image
        xs = np.unique(w[:, 0])
        assert (np.diff(xs) < (w[0, 2] - w[0, 0])).all()  # neighbours overlap
    with pytest.raises(ValueError):
        tile_windows(640, 480, 0)


def test_tiles_find_small_objects_that_the_whole_image_misses(tmp_path, ds):
    """The shipped detector on the sample images shrunk to half size in a corner of a grey canvas:
    with tiles=2 its boxes of the full-size images are found again (same label, IoU > 0.5) more often;
    on the full-size images every box of the plain pass is kept or replaced by a better one."""
    import cv2

    from cosy_cli.detection.boxes import box_iou
    from cosy_cli.detection.network import OnnxDetector

    det = OnnxDetector(stage.SHIPPED_DETECTOR)
    found = {0: [], 2: []}
    for im in ds.image_ids(1)[:4]:
        rgb = ds.read_rgb(1, im)
        b0, s0, o0 = det.detect(rgb, 0.3, 100)
        b2, s2, o2 = det.detect(rgb, 0.3, 100, tiles=2)
        same = (box_iou(b0, b2) > 0.5) & (o0[:, None] == o2[None]) & (s2[None] >= s0[:, None] - 1e-9)
        assert same.any(1).all()
        assert ((b2[:, 0] + b2[:, 2]) <= 640).all() and ((b2[:, 1] + b2[:, 3]) <= 480).all()
        small = np.full_like(rgb, 128)
        small[:240, :320] = cv2.resize(rgb, (320, 240), interpolation=cv2.INTER_AREA)
        for t in (0, 2):
            b, _, o = det.detect(small, 0.3, 100, tiles=t)
            hit = (box_iou(b0 / 2, b) > 0.5) & (o0[:, None] == o[None]) if len(b) else np.zeros((len(b0), 1), bool)
            found[t].extend(hit.any(1))
    assert np.mean(found[2]) >= np.mean(found[0]) + 0.15, (np.mean(found[0]), np.mean(found[2]))
    out = tmp_path / "d.json"
    r = _run(["detect", "--scene", SCENE, "--tiles", 2, "--classifier", "none", "--out", out, "--quiet"])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "d.meta.json").read_text())["conf"]["tiles"] == 2
    r = _run(["detect", "--scene", SCENE, "--classifier", "none", "--out", tmp_path / "e.json", "--quiet"])
    assert "tiles" not in json.loads((tmp_path / "e.meta.json").read_text())["conf"]  # the default is not recorded


# ------------------------------------------------------------------------------------------------
# COCO AP and confusion
# ------------------------------------------------------------------------------------------------
def test_coco_ap_of_gt_is_one_and_of_shifted_boxes_less(ds, gt_dets):
    s = detection_ap.coco_ap(gt_dets, ds, [1])
    assert s["AP"] == pytest.approx(1.0) and s["AP50"] == pytest.approx(1.0) and s["AP75"] == pytest.approx(1.0)
    assert s["gt"] == 64 and s["images"] == 8 and s["tool"].startswith("pycocotools")
    assert all(v["AP50"] == pytest.approx(1.0) for v in s["per_object"].values())
    shifted = gt_dets.copy()
    shifted["x"] += 0.2 * shifted["w"]  # IoU 0.67: found at IoU .5, lost from .7 on
    s = detection_ap.coco_ap(shifted, ds, [1])
    assert s["AP50"] == pytest.approx(1.0) and s["AP75"] == 0.0 and 0.2 < s["AP"] < 0.5
    # only half the detections: recall 0.5
    assert detection_ap.coco_ap(gt_dets.iloc[::2], ds, [1])["AP50"] < 0.6
    assert detection_ap.coco_ap(gt_dets.iloc[:0], ds, [1])["AP"] == 0.0


def test_mask_ap_of_the_gt_masks_is_one_and_of_their_boxes_less(tmp_path, ds, gt_dets):
    """Mask AP (pycocotools "segm") against the published visible masks: the GT masks as
    segmentations score 1; their boxes filled as masks pass at IoU 0.5 less often and never at
    0.95; detections without segmentations get no mask AP."""
    import cv2

    from cosy_cli.io.masks import encode_mask

    assert detection_ap.coco_mask_ap(gt_dets, ds, [1]) is None  # no segmentations
    d = importers.detections_from_gt(ds, [1], 0.1)
    exact, boxes = d.drop(columns=["gt_index"]), d.drop(columns=["gt_index"])
    segs, fills = [], []
    for r in d.itertuples():
        m = cv2.imread(str(ds.mask_path(1, r.im_id, r.gt_index, visib=True)), cv2.IMREAD_GRAYSCALE) > 0
        segs.append(encode_mask(m))
        f = np.zeros_like(m)
        f[int(r.y):int(r.y + r.h) + 1, int(r.x):int(r.x + r.w) + 1] = True
        fills.append(encode_mask(f))
    exact["segmentation"] = pd.Series(segs, index=exact.index, dtype=object)
    boxes["segmentation"] = pd.Series(fills, index=boxes.index, dtype=object)
    s = detection_ap.coco_mask_ap(exact, ds, [1])
    assert s["AP"] == pytest.approx(1.0) and s["AP50"] == pytest.approx(1.0)
    s = detection_ap.coco_mask_ap(boxes, ds, [1])
    assert s["AP"] < 0.7 and s["AP"] < s["AP50"]
    assert detection_ap.coco_ap(boxes, ds, [1])["AP"] == pytest.approx(1.0)  # box AP does not look at masks
    p = tmp_path / "dets.json"
    importers.write_detections(p, boxes)
    r = _run(["evaluate-detections", "--dataset", SAMPLES, "--split", "test", "--scene-id", 1, "--detections", p,
              "--out", tmp_path / "ev"])
    assert r.exit_code == 0, r.output
    assert "mask AP" in r.output
    assert json.loads((tmp_path / "ev" / "scores.json").read_text())["mask"]["AP"] == pytest.approx(s["AP"])


def test_barely_visible_instances_are_ignored(ds):
    d = importers.detections_from_gt(ds, [2], 0.0)
    info = ds.scene_gt_info(2)
    low = np.array([info[i][g].visib_fract < 0.5 for i, g in zip(d["im_id"], d["gt_index"])])
    assert low.sum() == 1
    assert detection_ap.coco_ap(d, ds, [2], 0.5)["AP"] == pytest.approx(1.0)       # found: not a false positive
    assert detection_ap.coco_ap(d[~low], ds, [2], 0.5)["AP"] == pytest.approx(1.0)  # missed: not a miss
    assert detection_ap.coco_ap(d[~low], ds, [2], 0.1)["AP"] < 1.0                  # a target at 0.1


def test_confusion_table_and_evaluate_command(tmp_path, ds, gt_dets):
    d = gt_dets.copy()
    swap = d.index[d["obj_id"] == 2][:3]
    d.loc[swap, "obj_id"] = 7  # three GT boxes of object 2 detected as 7
    d = d.drop(d.index[d["obj_id"] == 4][:2])  # two of object 4 missed
    t = detection_ap.confusion_matrix(d, ds, [1])
    assert t.loc[2, 7] == 3 and t.loc[2, 2] == 5 and t.loc[4, "missed"] == 2 and t.loc[1, 1] == 8
    assert int(t.to_numpy().sum()) == 64
    p = tmp_path / "dets.json"
    importers.write_detections(p, d)
    r = _run(["evaluate-detections", "--dataset", SAMPLES, "--split", "test", "--scene-id", 1, "--detections", p,
              "--out", tmp_path / "ev"])
    assert r.exit_code == 0, r.output
    scores = json.loads((tmp_path / "ev" / "scores.json").read_text())
    assert scores["confusion"]["2"] == {"gt": 8, "correct": 5, "other_label": 3, "missed": 0,
                                        "confused_with": {"7": 3}}
    assert scores["per_object"]["4"]["AP50"] < 1.0 and scores["per_object"]["1"]["AP50"] == pytest.approx(1.0)
    csv = pd.read_csv(tmp_path / "ev" / "confusion.csv", index_col=0)
    assert csv.loc[2, "7"] == 3 and list(csv.columns)[-1] == "missed"
    assert "7 x3" in r.output


class TwoLabelsOneObject:
    """One object seen as two look-alikes (overlapping boxes, labels 6 and 7), and a separate object."""

    def detect(self, rgb, min_score, max_per_image, nms_iou):
        boxes = np.array([[100, 100, 50, 50], [102, 101, 50, 50], [300, 200, 40, 40]], float)
        return boxes, np.array([0.6, 0.8, 0.5]), np.array([6, 7, 3])


def test_agnostic_nms_keeps_the_better_label_of_one_object(tmp_path):
    kw = dict(scene_ids=[1], detector=TwoLabelsOneObject(), log=lambda m: None, progress=False)
    stage.main({"min_score": 0.1}, SAMPLES, "test", tmp_path / "a.json", **kw)
    stage.main({"min_score": 0.1, "agnostic_nms_iou": 0.7}, SAMPLES, "test", tmp_path / "b.json", **kw)
    a, b = bop.read_detections(tmp_path / "a.json"), bop.read_detections(tmp_path / "b.json")
    assert sorted(a[a["im_id"] == 0]["obj_id"]) == [3, 6, 7]
    assert sorted(b[b["im_id"] == 0]["obj_id"]) == [3, 7]


def test_ap_from_matches_is_cocos_and_intervals_hold_it(ds, gt_dets):
    """Noisy detections (shifted, relabelled, dropped, false positives, random scores): our AP from
    COCOeval's per-image matches equals pycocotools' per-object AP50 exactly, and every interval
    holds its point value; perfect detections give a zero-width interval at 1."""
    rng = np.random.default_rng(7)
    d = pd.concat([gt_dets, gt_dets.sample(frac=0.5, random_state=1)], ignore_index=True)
    d["x"] += rng.normal(0, 0.15, len(d)) * d["w"]
    d["y"] += rng.normal(0, 0.15, len(d)) * d["h"]
    flip = rng.random(len(d)) < 0.15
    d.loc[flip, "obj_id"] = rng.choice(d["obj_id"].unique(), int(flip.sum()))
    d["score"] = rng.random(len(d))
    d = d.drop(d.index[rng.random(len(d)) < 0.2])
    s = detection_ap.coco_ap(d, ds, [1])
    assert s["AP50_ci"]["unit"] == "image" and s["AP50_ci"]["units"] == 8
    lo, hi = s["AP50_ci"]["AP50"]
    assert lo <= s["AP50"] <= hi and hi - lo > 0.02
    for o, v in s["per_object"].items():
        if v["gt"]:
            assert v["AP50_ci"][0] <= v["AP50"] <= v["AP50_ci"][1], (o, v)

    # the same AP from the per-image matches, without weights: pycocotools' number to 1e-12
    import contextlib
    import io

    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    gt = detection_ap._gt_boxes(ds, [1])
    img = detection_ap._image_index(ds, [1])
    with contextlib.redirect_stdout(io.StringIO()):
        coco_gt = COCO()
        coco_gt.dataset = {"images": [{"id": n} for n in img.values()],
                           "categories": [{"id": int(o)} for o in sorted(set(gt.obj_id) | set(d.obj_id))],
                           "annotations": [{"id": n + 1, "image_id": img[(r.scene_id, r.im_id)], "category_id": r.obj_id,
                                            "bbox": [r.x, r.y, r.w, r.h], "area": r.w * r.h, "iscrowd": 0}
                                           for n, r in enumerate(gt.itertuples())]}
        coco_gt.createIndex()
        E = COCOeval(coco_gt, coco_gt.loadRes([{"image_id": img[(r.scene_id, r.im_id)], "category_id": int(r.obj_id),
                                                "bbox": [r.x, r.y, r.w, r.h], "score": r.score}
                                               for r in d.itertuples()]), "bbox")
        E.evaluate()
        E.accumulate()
    I0, A0 = len(E.params.imgIds), len(E.params.areaRng)
    for k, cat in enumerate(E.params.catIds):
        ev = [e for e in E.evalImgs[k * A0 * I0:(k * A0 + 1) * I0] if e is not None]
        sc = np.concatenate([e["dtScores"][:100] for e in ev])
        m = np.concatenate([e["dtMatches"][0, :100] for e in ev])
        ig = np.concatenate([e["dtIgnore"][0, :100] for e in ev]).astype(bool)
        o = np.argsort(-sc, kind="mergesort")
        n_gt = sum(int((np.asarray(e["gtIgnore"]) == 0).sum()) for e in ev)
        ours = detection_ap.ap_from_matches(sc[o], (m[o] > 0) & ~ig[o], (m[o] == 0) & ~ig[o], n_gt)
        p = E.eval["precision"][0, :, k, 0, -1]
        assert ours == pytest.approx(p.mean() if (p > -1).any() else -1.0, abs=1e-12), cat
    perfect = detection_ap.coco_ap(gt_dets, ds, [1])
    assert perfect["AP50_ci"]["AP50"] == pytest.approx([1.0, 1.0])
