"""The second-stage box classifier of `cosy detect`: crops, the rescoring rule, the stage setting,
the shipped model on rendered crops, bad classifier files."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cosy_cli.cli.main import cli
from cosy_cli.detection import stage
from cosy_cli.detection.classifier import (
    ClassifierConfig, OnnxClassifier, build_network, crop_boxes, export_onnx, rescore, xywh_to_xyxy_continuous,
)
from cosy_cli.errors import CosyError
from cosy_cli.io import bop

SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"
SCENE = SAMPLES / "test" / "000001"
IDS = [1, 2, 3, 4, 5, 6, 7, 8]


def _run(args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


@pytest.fixture(scope="module")
def untrained(tmp_path_factory) -> Path:
    """An untrained classifier of the sample objects, exported (small: a real ONNX file)."""
    import torch

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("clf") / "clf.onnx"
    export_onnx(build_network(ClassifierConfig(obj_ids=IDS, crop=32, widths=(8, 8, 8, 8))).eval(), path)
    return path


# ------------------------------------------------------------------------------------------------
# crops
# ------------------------------------------------------------------------------------------------
def test_crop_is_centred_on_the_box_with_the_margin():
    img = np.zeros((200, 300, 3), np.uint8)
    img[50:90, 100:180] = 255  # columns 100..179, rows 50..89: continuous box [100, 50, 180, 90]
    c = crop_boxes(img, np.array([[100.0, 50.0, 180.0, 90.0]]), 64, 1.25)[0]
    # side 1.25 x 80 = 100 image px -> 64 px: the white box spans 80 x 0.64 = 51.2 px wide, 25.6 tall
    white = c[..., 0] > 127
    cols, rows = np.flatnonzero(white.any(0)), np.flatnonzero(white.any(1))
    assert abs((cols[0] + cols[-1] + 1) / 2 - 32) <= 0.6 and abs((rows[0] + rows[-1] + 1) / 2 - 32) <= 0.6
    assert abs(len(cols) - 51.2) <= 1.5 and abs(len(rows) - 25.6) <= 1.5
    # a box at the image corner: the outside is grey
    c = crop_boxes(img, np.array([[0.0, 0.0, 20.0, 20.0]]), 32, 1.5)[0]
    assert (c[0, 0] == 127).all()
    np.testing.assert_allclose(xywh_to_xyxy_continuous([[100, 50, 79, 39]]), [[100, 50, 180, 90]])


# ------------------------------------------------------------------------------------------------
# rescoring rule
# ------------------------------------------------------------------------------------------------
def _probs(rows):
    p = np.array(rows, float)
    return np.concatenate([p, np.zeros((len(p), 1))], 1)  # background 0


def test_rescore_keeps_one_label_when_sure_and_two_when_unsure():
    boxes = np.array([[0, 0, 10, 10], [50, 50, 10, 10]], float)
    one = np.zeros(8)
    one[2] = 0.95
    one[0] = 0.05
    unsure = np.zeros(8)
    unsure[5], unsure[6] = 0.55, 0.45  # objects 6 and 7
    b, s, lab, src = rescore(boxes, np.array([0.9, 0.8]), np.array([3, 7]), _probs([one, unsure]), IDS,
                             label_mix=0.0, label_ratio=0.2, background=0.0)
    got = sorted(zip(src.tolist(), lab.tolist(), np.round(s, 4).tolist()))
    assert got == [(0, 3, round(0.9 * 0.95, 4)), (1, 6, round(0.8 * 0.55, 4)), (1, 7, round(0.8 * 0.45, 4))]
    assert np.all(np.diff(s) <= 0)  # best first
    np.testing.assert_array_equal(b[src == 1], np.repeat(boxes[1:2], 2, 0))
    # label_ratio 1: the best label only; label_mix: the detector's label counts too
    _, s, lab, _ = rescore(boxes, np.array([0.9, 0.8]), np.array([3, 7]), _probs([one, unsure]), IDS,
                           label_mix=0.5, label_ratio=1.0)
    assert lab.tolist() == [3, 7] and np.allclose(s, [0.9 * (0.5 * 0.95 + 0.5), 0.8 * (0.5 * 0.45 + 0.5)])


def test_rescore_background_and_unknown_labels():
    p = np.zeros((2, 9))
    p[:, 0] = 0.2
    p[:, 8] = 0.8  # mostly background
    _, s, lab, _ = rescore(np.zeros((2, 4)), np.array([1.0, 0.5]), np.array([1, 42]), p, IDS, background=1.0)
    # box 0: objectness 1 x (1 - 0.8), label 1 only (the only object with p > 0); label 42 unknown: as it came
    assert sorted(zip(lab.tolist(), np.round(s, 6).tolist())) == [(1, 0.2), (42, 0.5)]
    with pytest.raises(ValueError, match="columns"):
        rescore(np.zeros((1, 4)), np.ones(1), np.ones(1), np.ones((1, 5)), IDS)
    # an image the detector found nothing in (a black frame): nothing out, no error
    b, s, lab, rows = rescore(np.zeros((0, 4)), np.zeros(0), np.zeros(0), np.zeros((0, 9)), IDS)
    assert b.shape == (0, 4) and len(s) == len(lab) == len(rows) == 0
    assert len(rescore(np.zeros((0, 4)), np.zeros(0), np.zeros(0), np.zeros(0), IDS)[0]) == 0


def test_detect_with_the_shipped_classifier_on_an_image_without_objects(tmp_path):
    """The shipped detector and box classifier on a scene with one all-black image: that image
    gets no detection, the others theirs (the empty box set once crashed the classifier step)."""
    import shutil

    from cosy_cli.io.images import read_rgb, write_rgb

    ds = tmp_path / "ds"
    shutil.copytree(SAMPLES, ds, ignore=shutil.ignore_patterns("000002", "000003"))
    rgb_dir = ds / "test" / "000001" / "rgb"
    first = sorted(rgb_dir.iterdir())[0]
    write_rgb(first, np.zeros_like(read_rgb(first)))
    r = CliRunner().invoke(cli, ["detect", "--dataset", str(ds), "--out", str(tmp_path / "d.json"), "--quiet"])
    assert r.exit_code == 0, r.output
    d = bop.read_detections(tmp_path / "d.json")
    im_black = int(first.stem)
    assert (d["im_id"] != im_black).all() and d["im_id"].nunique() == len(list(rgb_dir.iterdir())) - 1


# ------------------------------------------------------------------------------------------------
# the stage setting
# ------------------------------------------------------------------------------------------------
class TwoBoxDetector:
    """Two boxes per image, both labelled 6 (a look-alike pair seen as one object)."""

    obj_ids = IDS

    def detect(self, rgb, min_score, max_per_image, nms_iou):
        return np.array([[100, 100, 60, 40], [300, 200, 50, 50]], float), np.array([0.9, 0.7]), np.array([6, 6])


class FixedClassifier:
    """Says 6 or 7 (0.6 / 0.4) for the first box, 2 for the others."""

    obj_ids = IDS

    def __init__(self):
        self.calls = 0

    def classify(self, rgb, boxes):
        self.calls += 1
        p = np.zeros((len(boxes), 9))
        p[:, 1] = 1.0
        if len(boxes) and boxes[0][0] == 100:
            p[0] = 0
            p[0, 5], p[0, 6] = 0.6, 0.4
        return p


def test_detect_with_and_without_a_classifier(tmp_path):
    s0 = stage.main({"min_score": 0.1, "classifier": "none"}, SAMPLES, "test", tmp_path / "a.json", scene_ids=[1],
                    detector=TwoBoxDetector(), progress=False)
    d0 = bop.read_detections(tmp_path / "a.json")
    assert s0["classifier"] is None and len(d0) == 16 and set(d0["obj_id"]) == {6}
    clf = FixedClassifier()
    s1 = stage.main({"min_score": 0.1, "label_ratio": 0.5, "label_mix": 0.0}, SAMPLES, "test", tmp_path / "b.json",
                    scene_ids=[1], detector=TwoBoxDetector(), classifier=clf, progress=False)
    d1 = bop.read_detections(tmp_path / "b.json")
    assert clf.calls == 1 + 8  # warm-up + one per image
    one = d1[d1["im_id"] == d1["im_id"].iloc[0]].sort_values("score", ascending=False)
    assert one["obj_id"].tolist() == [2, 6, 7]
    np.testing.assert_allclose(one["score"], [0.7, 0.9 * 0.6, 0.9 * 0.4])
    assert s1["classifier"]["label_ratio"] == 0.5 and s1["classifier"]["time_per_image_s"] >= 0
    # min_score is the detector's threshold: a box it kept stays under all its plausible labels
    stage.main({"min_score": 0.5, "label_ratio": 0.5, "label_mix": 0.0}, SAMPLES, "test", tmp_path / "c.json",
               scene_ids=[1], detector=TwoBoxDetector(), classifier=FixedClassifier(), progress=False)
    d2 = bop.read_detections(tmp_path / "c.json")
    assert len(d2) == 24 and np.isclose(d2["score"].min(), 0.9 * 0.4)
    doc = json.loads((tmp_path / "b.meta.json").read_text())
    assert doc["inputs"]["classifier"]["object"].endswith("FixedClassifier")
    assert "box classifier" in doc["source"]


def test_classifier_setting_through_the_command_line(tmp_path, untrained):
    """A real (untrained) exported detector + classifier through `cosy detect --classifier PATH`."""
    from cosy_cli.detection.model import CenterNet, DetectorConfig
    from cosy_cli.detection.train import export_onnx as export_detector

    det = tmp_path / "det.onnx"
    export_detector(CenterNet(DetectorConfig(obj_ids=IDS, input_size=(64, 48))), det)
    out = tmp_path / "d.json"
    r = _run(["detect", "--scene", SCENE, "--model", det, "--classifier", untrained, "--label-ratio", 0.5,
              "--min-score", 0, "--max-per-image", 4, "--out", out, "--quiet"])
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "d.meta.json").read_text())
    assert doc["conf"]["classifier"] == str(untrained) and doc["conf"]["label_ratio"] == 0.5
    assert doc["inputs"]["classifier"]["sha1"] and doc["classifier"]["time_per_image_s"] > 0
    d = bop.read_detections(out)
    assert 0 < len(d) <= 8 * 4 and set(d["obj_id"]) <= set(IDS)
    # auto with a detector that is not the shipped one: no classifier
    r = _run(["detect", "--scene", SCENE, "--model", det, "--min-score", 0, "--out", tmp_path / "e.json", "--quiet"])
    assert r.exit_code == 0 and json.loads((tmp_path / "e.meta.json").read_text())["classifier"] is None


def test_a_classifier_without_mask_head_cannot_add_masks_to_gt_boxes(tmp_path, untrained):
    r = _run(["detect", "--scene", SCENE, "--from-gt", "--classifier", untrained, "--out", tmp_path / "d.json"])
    assert r.exit_code == 2 and "no mask head" in r.output and "Traceback" not in r.output
    r = _run(["detect", "--scene", SCENE, "--from-gt", "--out", tmp_path / "d.json"])  # no classifier: as before
    assert r.exit_code == 0, r.output
    assert all(d.get("segmentation") is None for d in json.loads((tmp_path / "d.json").read_text()))


def test_bad_classifier_files_are_user_errors(tmp_path, untrained):
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not an onnx file")
    with pytest.raises(CosyError, match="not a readable ONNX"):
        OnnxClassifier(junk)
    with pytest.raises(CosyError, match="not found"):
        OnnxClassifier(tmp_path / "missing.onnx")
    with pytest.raises(CosyError, match="cosy_classifier"):  # the detector is an ONNX but not a classifier
        OnnxClassifier(stage.SHIPPED_DETECTOR)
    # a classifier of other objects
    other = tmp_path / "other.onnx"
    export_onnx(build_network(ClassifierConfig(obj_ids=[1, 2], crop=32, widths=(8, 8, 8, 8))).eval(), other)
    with pytest.raises(CosyError, match="knows objects"):
        stage.load_classifier(str(other), IDS, IDS)
    assert stage.load_classifier("none", IDS) is None
    assert stage.load_classifier(str(untrained), IDS, IDS).obj_ids == IDS
    r = _run(["detect", "--scene", SCENE, "--classifier", junk, "--out", tmp_path / "d.json", "--quiet"])
    assert r.exit_code == 2 and "not a readable ONNX" in r.output


# ------------------------------------------------------------------------------------------------
# the shipped classifier
# ------------------------------------------------------------------------------------------------
@pytest.mark.skipif(not stage.SHIPPED_CLASSIFIER.is_file(), reason="no classifier shipped")
def test_shipped_classifier_labels_rendered_crops():
    """Crops of the visible boxes of rendered scenes (the detector's domain-randomised generator,
    a seed no training used): far above chance (1/9), and the shipped rule on the GT boxes."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    from cosy_cli.detection.data import DetectionSampleGenerator
    from cosy_cli.detection.train import load_dataset_objects

    clf = OnnxClassifier(stage.SHIPPED_CLASSIFIER)
    assert clf.obj_ids == IDS
    meshes, K, size = load_dataset_objects(SAMPLES)
    gen = DetectionSampleGenerator(meshes, K, size, input_size=size, seed=123456, max_objects=6, min_visib=0.5)
    try:
        b = gen.batch(6)
    finally:
        gen.close()
    right = total = 0
    for img, boxes, labels in zip(b["images"], b["boxes"], b["labels"]):
        if not len(boxes):
            continue
        p = clf.classify_crops(crop_boxes(img, boxes, clf.config.crop, clf.config.margin))
        assert p.shape == (len(boxes), 9) and np.allclose(p.sum(1), 1, atol=1e-4)
        right += int((p.argmax(1) == labels).sum())
        total += len(labels)
    assert total >= 12 and right / total >= 0.6, (right, total)


# ------------------------------------------------------------------------------------------------
# training command
# ------------------------------------------------------------------------------------------------
def test_train_resume_and_export_a_classifier(tmp_path):
    """`cosy train classifier` (backbone of the shipped detector), --resume, `cosy export`: an ONNX
    the runner loads."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    run = tmp_path / "run"
    base = ["train", "classifier", "--dataset", SAMPLES, "--out", run, "--batch-size", 8, "--checkpoint-every", 1,
            "--init", stage.SHIPPED_DETECTOR]
    r = _run(base + ["--iterations", 2])
    assert r.exit_code == 0, r.output
    assert "BatchNorms recalibrated" in r.output and (run / "checkpoint.pt").is_file()
    r = _run(base + ["--iterations", 2])
    assert r.exit_code == 2 and "--resume" in r.output
    r = _run(base + ["--iterations", 3, "--resume"])
    assert r.exit_code == 0, r.output
    assert [row.split(",")[0] for row in (run / "log.csv").read_text().split()[1:]] == ["1", "2", "3"]
    r = _run(["export", "--run", run, "--out", tmp_path / "c.onnx"])
    assert r.exit_code == 0, r.output
    clf = OnnxClassifier(tmp_path / "c.onnx")
    assert clf.obj_ids == IDS and clf.config.arch == "detector"
    p = clf.classify(np.zeros((480, 640, 3), np.uint8), np.array([[10, 10, 50, 60], [600, 400, 80, 120]], float))
    assert p.shape == (2, 9) and np.allclose(p.sum(1), 1, atol=1e-4)
    # a run recorded before the box and mask heads existed resumes as it was (neither head), its old log rows kept
    rec = json.loads((run / "config.json").read_text())
    assert rec["box_head"] is False and rec["mask_head"] is False
    for k in ("box_head", "box_weight", "mask_head", "mask_weight"):
        rec.pop(k)
    (run / "config.json").write_text(json.dumps(rec))
    lines = (run / "log.csv").read_text().splitlines()
    (run / "log.csv").write_text("\n".join(",".join(v.split(",")[:-2]) for v in lines) + "\n")
    r = _run(base + ["--iterations", 4, "--resume"])
    assert r.exit_code == 0, r.output
    rows = (run / "log.csv").read_text().splitlines()
    assert rows[0].endswith(",loss_box,loss_mask") and [v.split(",")[0] for v in rows[1:]] == ["1", "2", "3", "4"]
    rec = json.loads((run / "config.json").read_text())
    assert rows[1].endswith(",,") and rec["box_head"] is False and rec["mask_head"] is False


def test_export_an_efficientnet_lite0_classifier_in_int8(tmp_path):
    """`cosy export --precision int8` of an EfficientNet-Lite0 classifier run: its backbone's
    convolutions become quantize/dequantize pairs (calibrated on crops rendered as in training),
    the card says int8, the probabilities stay close to the float32 export's; a classifier on the
    detector's backbone is refused with exit code 2; the float32 export is unchanged."""
    import onnx

    from cosy_cli.detection.classifier_train import calibration_feeds

    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    run = tmp_path / "run"
    r = _run(["train", "classifier", "--dataset", SAMPLES, "--out", run, "--batch-size", 8, "--iterations", 2,
              "--backbone", "efficientnet-lite0"])
    assert r.exit_code == 0, r.output
    r = _run(["export", "--run", run, "--out", tmp_path / "fp32.onnx"])
    assert r.exit_code == 0, r.output
    r = _run(["export", "--run", run, "--out", tmp_path / "int8.onnx", "--precision", "int8"])
    assert r.exit_code == 0, r.output
    assert "convolutions of the EfficientNet-Lite0 backbone in int8" in r.output
    assert "int8" in (tmp_path / "int8.md").read_text() and "int8" not in (tmp_path / "fp32.md").read_text()
    ops = [n.op_type for n in onnx.load(str(tmp_path / "int8.onnx")).graph.node]
    ops32 = {n.op_type for n in onnx.load(str(tmp_path / "fp32.onnx")).graph.node}
    assert {"QuantizeLinear", "DequantizeLinear"} <= set(ops) and "QuantizeLinear" not in ops32
    a, b = OnnxClassifier(tmp_path / "fp32.onnx"), OnnxClassifier(tmp_path / "int8.onnx")
    assert b.config.arch == "lite0" and b.obj_ids == a.obj_ids == IDS
    crops = calibration_feeds(json.loads((run / "config.json").read_text()), n=16, seed=5)
    x = (np.concatenate([f["crops"] for f in crops]).transpose(0, 2, 3, 1) * 255).round().astype(np.uint8)
    pa, pb = a.classify_crops(x), b.classify_crops(x)
    assert not np.array_equal(pa, pb)
    np.testing.assert_allclose(pb, pa, atol=0.15)
    # the detector's backbone has nothing to quantize this way
    plain = tmp_path / "plain"
    r = _run(["train", "classifier", "--dataset", SAMPLES, "--out", plain, "--batch-size", 8, "--iterations", 1])
    assert r.exit_code == 0, r.output
    r = _run(["export", "--run", plain, "--out", tmp_path / "p.onnx", "--precision", "int8"])
    assert r.exit_code == 2 and "EfficientNet-Lite0" in r.output and not (tmp_path / "p.onnx").exists()


# ------------------------------------------------------------------------------------------------
# box refinement (box head)
# ------------------------------------------------------------------------------------------------
def test_box_deltas_are_edge_offsets_in_crop_units():
    from cosy_cli.detection.classifier import (
        BOX_DELTA_SCALE, apply_box_deltas, box_deltas, crop_sides, xyxy_continuous_to_xywh,
    )

    box = np.array([[10.0, 20.0, 60.0, 120.0], [300.0, 200.0, 340.0, 210.0]])
    gt = np.array([[12.0, 15.0, 70.0, 110.0], [290.0, 190.0, 360.0, 230.0]])
    d = box_deltas(box, gt, 1.2)
    np.testing.assert_allclose(apply_box_deltas(box, d, 1.2), gt)
    side = crop_sides(box, 1.2)
    np.testing.assert_allclose(side, [120.0, 48.0])  # 1.2 x the longer side
    np.testing.assert_allclose(d[0], (gt[0] - box[0]) / (BOX_DELTA_SCALE * 120.0))
    # a degenerate move keeps a box of at least 2 px; BOP boxes round-trip through the continuous corners
    assert (np.diff(apply_box_deltas(box, -d * 100, 1.2).reshape(-1, 2, 2), axis=1) >= 2 - 1e-9).all()
    xywh = np.array([[5.0, 6.0, 30.0, 40.0]])
    np.testing.assert_allclose(xyxy_continuous_to_xywh(xywh_to_xyxy_continuous(xywh)), xywh)


def _rendered_batch(seed: int, **conf) -> dict:
    """Six rendered images of the sample objects from the classifier's training sampler (seeded)."""
    from cosy_cli.detection import classifier_train as ct
    from cosy_cli.detection.train import load_dataset_objects

    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    meshes, K, size = load_dataset_objects(SAMPLES, None, None)
    c = ct.resolve_conf(None, soft_targets="none", background_per_image=0, reuse=1, crop=64, **conf)
    sampler = ct.CropSampler(meshes, K, size, c, IDS, seed, appearance=None)
    try:
        return sampler.gen.batch(6)
    finally:
        sampler.close()


def test_box_head_learns_to_move_jittered_boxes_onto_rendered_objects(tmp_path):
    """The whole box refinement chain, trained and applied: crops of jittered boxes of rendered
    objects and their targets (the training sampler's code), a box-head classifier overfit on them
    (the loss falls, so targets, crops and head agree), exported to ONNX, then
    ``OnnxClassifier.classify_refine`` on the same images moves the boxes onto the objects (IoU with
    the visible boxes up), and ``cosy detect`` applies it (refine_boxes) or not (0)."""
    import torch
    import torch.nn.functional as F

    from cosy_cli.detection import classifier_train as ct
    from cosy_cli.detection.boxes import box_iou
    from cosy_cli.detection.classifier import xyxy_continuous_to_xywh

    b = _rendered_batch(5, jitter=0.12, box_head=True)
    rng = np.random.default_rng(0)
    imgs, gts, jits, xs, ds = [], [], [], [], []
    for img, boxes in zip(b["images"], b["boxes"]):
        if len(boxes) == 0:
            continue
        jit = ct._jitter(boxes, rng, 0.12)
        imgs.append(img), gts.append(boxes), jits.append(jit)
        xs.append(crop_boxes(img, jit, 64, 1.2))
        ds.append(ct.box_deltas(jit, boxes, 1.2))
    x = torch.from_numpy(np.concatenate(xs).transpose(0, 3, 1, 2).copy()).float() / 255
    d = torch.from_numpy(np.concatenate(ds)).float()
    assert len(x) >= 12
    torch.manual_seed(0)
    net = build_network(ClassifierConfig(obj_ids=IDS, crop=64, widths=(16, 32, 48, 64), box_head=True))
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(300):
        loss = F.smooth_l1_loss(net.forward_all(x)[1], d, beta=0.1)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert np.mean(losses[-10:]) < 0.1 * np.mean(losses[:10])
    net.eval()
    with torch.no_grad():  # BatchNorm statistics of these crops (a tiny set: eval mode must fit too)
        net.train()
        for _ in range(20):
            net.forward_all(x)
        net.eval()
    path = export_onnx(net, tmp_path / "box.onnx")
    clf = OnnxClassifier(path)
    assert clf.has_box_head
    before, after = [], []
    for img, gt, jit in zip(imgs, gts, jits):
        gt_xywh, jit_xywh = xyxy_continuous_to_xywh(gt), xyxy_continuous_to_xywh(jit)
        probs, moved = clf.classify_refine(img, jit_xywh, passes=1)
        assert probs.shape == (len(gt), 9)
        before.append(np.diag(box_iou(jit_xywh, gt_xywh)))
        after.append(np.diag(box_iou(moved, gt_xywh)))
        _, same = clf.classify_refine(img, jit_xywh, passes=0)
        np.testing.assert_allclose(same, jit_xywh)
    before, after = np.concatenate(before), np.concatenate(after)
    assert after.mean() > before.mean() + 0.1 and after.mean() > 0.85, (before.mean(), after.mean())
    # the detect stage moves a detector's boxes with it, unless refine_boxes is 0
    out = {}
    for n in (0, 1):
        stage.main({"min_score": 0.1, "refine_boxes": n}, SAMPLES, "test", tmp_path / f"d{n}.json", scene_ids=[1],
                   detector=TwoBoxDetector(), classifier=clf, progress=False)
        out[n] = bop.read_detections(tmp_path / f"d{n}.json").sort_values(["im_id", "obj_id", "score"])
        meta = json.loads((tmp_path / f"d{n}.meta.json").read_text())
        assert meta["classifier"]["refine_boxes"] == n
    raw = TwoBoxDetector().detect(np.zeros((480, 640, 3), np.uint8), 0.1, 30, 0.5)[0]
    assert np.isin(np.round(out[0][["x", "y"]].to_numpy(), 6), np.round(raw[:, :2], 6)).all()
    assert not np.isin(np.round(out[1][["x", "y"]].to_numpy(), 6), np.round(raw[:, :2], 6)).all()


# ------------------------------------------------------------------------------------------------
# mask head
# ------------------------------------------------------------------------------------------------
def test_crop_masks_and_paste_masks_are_inverse():
    """A visible mask cropped the way the training targets are (crop_masks) and pasted back the
    way cosy detect does (paste_masks) is the same mask; a crop that leaves the image pastes only
    what lies inside it."""
    from cosy_cli.detection.classifier import crop_masks, paste_masks

    inst = -np.ones((120, 160), np.int64)
    yy, xx = np.mgrid[:120, :160]
    inst[(xx - 60) ** 2 / 30 ** 2 + (yy - 50) ** 2 / 20 ** 2 <= 1] = 3   # an ellipse
    inst[(xx >= 120) & (yy >= 80)] = 5                                    # a block cut by the image's corner
    boxes = np.array([[30.0, 30.0, 91.0, 71.0], [120.0, 80.0, 160.0, 120.0]])
    masks = crop_masks(inst, np.array([3, 5]), boxes, 64, 1.2)
    assert masks.shape == (2, 16, 16) and 0 <= masks.min() and masks.max() <= 1
    assert abs(masks[0].sum() * (61 * 1.2 / 16) ** 2 - (inst == 3).sum()) < 0.02 * (inst == 3).sum()  # areas kept
    pasted = paste_masks(masks, boxes, 1.2, (120, 160))
    for m, k in zip(pasted, (3, 5)):
        gt = inst == k
        assert m.shape == gt.shape and (m & gt).sum() / (m | gt).sum() > 0.9
    # a mask shifted by half the crop: the paste follows the box it is given
    shifted = paste_masks(masks[:1], boxes[:1] + [40, 0, 40, 0], 1.2, (120, 160))[0]
    assert (shifted & (inst == 3)).sum() < 0.3 * (inst == 3).sum()
    assert paste_masks(np.zeros((0, 16, 16)), np.zeros((0, 4)), 1.2, (120, 160)) == []


def test_mask_head_learns_the_visible_masks_of_rendered_objects(tmp_path):
    """The mask chain, trained and applied: crops of jittered boxes of rendered objects with their
    visible-mask targets (the training sampler's code), a mask-head classifier overfit on them,
    exported to ONNX; ``classify_refine_masks`` + ``paste_masks`` on the same images give masks
    that fit the rendered objects' visible masks far better than their boxes do; ``cosy detect``
    writes them as segmentations (unless masks none) and ``cosy estimate`` reads them."""
    import torch
    import torch.nn.functional as F

    from cosy_cli.detection import classifier_train as ct
    from cosy_cli.detection.classifier import crop_masks, paste_masks, xyxy_continuous_to_xywh
    from cosy_cli.io.masks import decode_segmentation

    b = _rendered_batch(7, jitter=0.08, mask_head=True)
    rng = np.random.default_rng(0)
    cases, xs, ms = [], [], []
    for img, boxes, inst, ids in zip(b["images"], b["boxes"], b["instance"], b["instance_ids"]):
        if len(boxes) == 0:
            continue
        jit = ct._jitter(boxes, rng, 0.08)
        cases.append((img, jit, inst, ids))
        xs.append(crop_boxes(img, jit, 64, 1.2))
        ms.append(crop_masks(inst, ids, jit, 64, 1.2))
    x = torch.from_numpy(np.concatenate(xs).transpose(0, 3, 1, 2).copy()).float() / 255
    m = torch.from_numpy(np.concatenate(ms))
    assert len(x) >= 12 and m.shape[1:] == (16, 16)
    torch.manual_seed(0)
    net = build_network(ClassifierConfig(obj_ids=IDS, crop=64, widths=(16, 32, 48, 64), mask_head=True))
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(250):
        loss = F.binary_cross_entropy_with_logits(net.forward_all(x)[2], m)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert np.mean(losses[-10:]) < 0.3 * np.mean(losses[:10])
    with torch.no_grad():  # BatchNorm statistics of these crops (a tiny set: eval mode must fit too)
        net.train()
        for _ in range(20):
            net.forward_all(x)
    net.eval()
    clf = OnnxClassifier(export_onnx(net, tmp_path / "mask.onnx"))
    assert clf.has_mask_head and not clf.has_box_head
    iou_mask, iou_box = [], []
    for img, jit, inst, ids in cases:
        probs, xyxy, masks = clf.classify_refine_masks(img, xyxy_continuous_to_xywh(jit), passes=1)
        np.testing.assert_allclose(xyxy, jit)  # no box head: the boxes stay
        assert probs.shape == (len(jit), 9) and masks.shape == (len(jit), 16, 16)
        for k, pasted in enumerate(paste_masks(masks, xyxy, 1.2, img.shape[:2])):
            gt = inst == ids[k]
            box = np.zeros_like(gt)
            x1, y1, x2, y2 = np.round(jit[k]).astype(int)
            box[max(y1, 0):y2, max(x1, 0):x2] = True
            iou_mask.append((pasted & gt).sum() / max((pasted | gt).sum(), 1))
            iou_box.append((box & gt).sum() / max((box | gt).sum(), 1))
    assert np.mean(iou_mask) > 0.75 and np.mean(iou_mask) > np.mean(iou_box) + 0.1, (np.mean(iou_mask), np.mean(iou_box))

    # cosy detect: a segmentation per detection from the mask head, none with masks none
    for masks_setting in ("auto", "none"):
        out = tmp_path / f"d_{masks_setting}.json"
        stage.main({"min_score": 0.1, "masks": masks_setting}, SAMPLES, "test", out, scene_ids=[1],
                   detector=TwoBoxDetector(), classifier=clf, progress=False)
        dets = bop.read_detections(out)
        meta = json.loads((tmp_path / f"d_{masks_setting}.meta.json").read_text())
        assert meta["classifier"]["masks"] is (masks_setting == "auto")
        segs = dets["segmentation"].tolist()
        if masks_setting == "none":
            assert all(s is None for s in segs)
            continue
        assert len(segs) and all(isinstance(s, dict) for s in segs)
        for s, row in zip(segs, dets.itertuples()):
            mk = decode_segmentation(s, (480, 640))
            ys, xs_ = np.nonzero(mk)
            if len(ys):  # within the crop square of the detection's box
                side = 1.2 * max(row.w, row.h) + 2
                assert abs((xs_.mean()) - (row.x + row.w / 2)) < side / 2 and abs(ys.mean() - (row.y + row.h / 2)) < side / 2
    # --mask-boxes: each box becomes its mask's bounding box
    stage.main({"min_score": 0.1, "mask_boxes": True}, SAMPLES, "test", tmp_path / "mb.json", scene_ids=[1],
               detector=TwoBoxDetector(), classifier=clf, progress=False)
    mb = bop.read_detections(tmp_path / "mb.json")
    for row in mb.itertuples():
        mk = decode_segmentation(row.segmentation, (480, 640))
        if mk.sum() >= 20:
            ys, xs_ = np.nonzero(mk)
            np.testing.assert_allclose([row.x, row.y, row.w, row.h],
                                       [xs_.min(), ys.min(), xs_.max() + 1 - xs_.min(), ys.max() + 1 - ys.min()])
    # ... which cosy estimate reads as masks
    r = _run(["estimate", "--dataset", SAMPLES, "--split", "test", "--scene-id", 1, "--detections",
              tmp_path / "d_auto.json", "--out", tmp_path / "est"])
    assert r.exit_code == 0, r.output
    assert "have a segmentation" in r.output
    # boxes from elsewhere (here the GT boxes): the classifier adds its masks, boxes and labels stay
    stage.main({"classifier": "object"}, SAMPLES, "test", tmp_path / "gt.json", scene_ids=[1], from_gt=True,
               classifier=clf, progress=False)
    gt = bop.read_detections(tmp_path / "gt.json")
    plain = stage.importers.detections_from_gt(stage.BopDataset(SAMPLES, "test"), [1], 0.1)
    assert len(gt) == len(plain) and gt["segmentation"].map(lambda v: isinstance(v, dict)).all()
    assert sorted(map(tuple, gt[["im_id", "obj_id", "x", "y"]].to_numpy().tolist())) == \
        sorted(map(tuple, plain[["im_id", "obj_id", "x", "y"]].to_numpy().tolist()))
    assert json.loads((tmp_path / "gt.meta.json").read_text())["classifier"]["masks_added"] == len(gt)


def test_refine_top_moves_only_the_best_boxes_after_the_first_look(tmp_path):
    """The cascade of ``classify_refine_masks(select=...)``: the boxes ``select`` names (from the
    first look's probabilities) move and are looked at again exactly as without a cascade; the
    others keep their box, first-look probabilities and mask. Through `cosy detect --refine-top`."""
    import torch

    from cosy_cli.detection.model import CenterNet, DetectorConfig
    from cosy_cli.detection.train import export_onnx as export_detector

    torch.manual_seed(0)
    net = build_network(ClassifierConfig(obj_ids=IDS, crop=32, widths=(8, 8, 8, 8), box_head=True,
                                         mask_head=True)).eval()
    with torch.no_grad():  # a box head that moves boxes (the untrained one starts at zero offsets)
        net.box.bias.copy_(torch.tensor([0.3, -0.2, 0.25, 0.1]))
    path = tmp_path / "clf.onnx"
    export_onnx(net, path)
    clf = OnnxClassifier(path)
    rgb = np.random.default_rng(0).integers(0, 255, (120, 160, 3), dtype=np.uint8)
    boxes = np.array([[10, 10, 40, 30], [60, 20, 30, 50], [100, 60, 40, 40], [20, 70, 50, 30]], float)
    p0, xyxy0, m0 = clf.classify_refine_masks(rgb, boxes, 0)
    p_all, xyxy_all, m_all = clf.classify_refine_masks(rgb, boxes, 2)
    assert not np.allclose(xyxy_all, xyxy0)
    seen = []

    def select(probs):
        seen.append(probs)
        return [2, 0]

    p, xyxy, m = clf.classify_refine_masks(rgb, boxes, 2, select)
    np.testing.assert_allclose(seen[0], p0, atol=1e-6)
    for i, moved in ((0, True), (1, False), (2, True), (3, False)):
        ref_p, ref_xyxy, ref_m = (p_all, xyxy_all, m_all) if moved else (p0, xyxy0, m0)
        np.testing.assert_allclose(xyxy[i], ref_xyxy[i], atol=1e-6)
        np.testing.assert_allclose(p[i], ref_p[i], atol=1e-5)
        np.testing.assert_allclose(m[i], ref_m[i], atol=1e-5)
    _, moved_xywh = clf.classify_refine(rgb, boxes, 2, select)
    assert np.allclose(moved_xywh[1], boxes[1]) and not np.allclose(moved_xywh[0], boxes[0])
    # the stage setting: recorded where it applies, refused when negative
    det = tmp_path / "det.onnx"
    export_detector(CenterNet(DetectorConfig(obj_ids=IDS, input_size=(64, 48))), det)
    out = tmp_path / "d.json"
    r = _run(["detect", "--scene", SCENE, "--model", det, "--classifier", path, "--min-score", 0,
              "--max-per-image", 6, "--refine-boxes", 2, "--refine-top", 2, "--out", out, "--quiet"])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "d.meta.json").read_text())["conf"]["refine_top"] == 2
    r = _run(["detect", "--scene", SCENE, "--model", det, "--classifier", path, "--min-score", 0,
              "--out", tmp_path / "e.json", "--quiet"])
    assert r.exit_code == 0 and "refine_top" not in json.loads((tmp_path / "e.meta.json").read_text())["conf"]
    with pytest.raises(CosyError, match="refine_top"):
        stage.resolve_conf("default", refine_top=-1)
