"""The trainable 2D detector: boxes/NMS, target encoding, training, ONNX export and runner, CLI."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from cosy_cli.rendering import SceneRenderer  # noqa: F401  (selects the GL platform first)
from cosy_cli.cli.main import cli  # noqa: E402
from cosy_cli.detection.boxes import box_iou, nms, nms_per_class, xywh_to_xyxy, xyxy_to_xywh  # noqa: E402
from cosy_cli.detection.model import (  # noqa: E402
    CenterNet, DetectorConfig, ExportWrapper, decode_targets, detection_loss, encode_targets, stack_targets,
)
from cosy_cli.errors import CosyError  # noqa: E402

DATA = Path(__file__).resolve().parents[1] / "data_samples"
TINY_NET = dict(input_size=(64, 48), stride=8, channels=(4, 8, 8, 16, 16), depth=(0, 0, 1, 1), fpn=8, head=8)


# ------------------------------------------------------------------------------------ boxes
def test_box_iou_hand_made():
    a = np.array([[0, 0, 10, 10], [5, 5, 10, 10], [100, 100, 1, 1], [0, 0, 0, 5]])
    b = np.array([[0, 0, 10, 10], [5, 0, 10, 10], [50, 50, 5, 5]])
    iou = box_iou(a, b)
    assert iou.shape == (4, 3)
    assert iou[0, 0] == pytest.approx(1.0)
    assert iou[0, 1] == pytest.approx(50 / 150)  # half overlap
    assert iou[1, 0] == pytest.approx(25 / 175)  # quarter overlap
    assert iou[1, 1] == pytest.approx(50 / 150)
    assert iou[2].max() == 0.0 and iou[:, 2].max() == 0.0  # disjoint
    assert np.all(iou[3] == 0.0)  # empty box
    assert box_iou(np.zeros((0, 4)), b).shape == (0, 3)
    with pytest.raises(ValueError):
        box_iou(np.zeros((2, 3)), b)
    xyxy = xywh_to_xyxy(a)
    assert np.allclose(xyxy_to_xywh(xyxy), a)


def test_nms_keeps_the_best_of_each_cluster():
    boxes = np.array([[0, 0, 10, 10], [1, 0, 10, 10], [50, 50, 10, 10], [0, 1, 10, 10], [51, 50, 10, 10],
                      [0, 0, 4, 4]])
    scores = np.array([0.9, 0.95, 0.5, 0.3, 0.6, 0.8])
    keep = nms(boxes, scores, 0.5)
    assert keep.tolist() == [1, 5, 4]  # by score; 0 and 3 suppressed by 1, 2 by 4; the small one survives
    assert nms(boxes, scores, 0.99).tolist() == list(np.argsort(-scores))  # nothing suppressed
    assert nms(np.zeros((0, 4)), np.zeros(0)).tolist() == []


def test_nms_per_class_only_within_a_class():
    boxes = np.array([[0, 0, 10, 10], [1, 0, 10, 10], [0, 0, 10, 10], [100, 0, 10, 10]])
    scores = np.array([0.9, 0.8, 0.7, 0.6])
    labels = np.array([1, 1, 2, 2])
    keep = nms_per_class(boxes, scores, labels, 0.5)
    assert keep.tolist() == [0, 2, 3]  # box 1 suppressed by 0 (same class); 2 overlaps 0 but is another class
    assert nms_per_class(boxes, scores, np.ones(4), 0.5).tolist() == nms(boxes, scores, 0.5).tolist()
    # random cases against a per-class loop
    rng = np.random.default_rng(0)
    b = np.concatenate([rng.uniform(0, 100, (60, 2)), rng.uniform(5, 40, (60, 2))], 1)
    s = rng.uniform(0, 1, 60)
    lab = rng.integers(0, 3, 60)
    keep = nms_per_class(b, s, lab, 0.4)
    expect = np.concatenate([np.flatnonzero(lab == c)[nms(b[lab == c], s[lab == c], 0.4)] for c in range(3)])
    assert sorted(keep.tolist()) == sorted(expect.tolist())
    assert np.all(np.diff(s[keep]) <= 0)


# ------------------------------------------------------------------------------------ targets
def test_encoding_then_decoding_recovers_the_boxes():
    cfg = DetectorConfig(obj_ids=[3, 5, 9], input_size=(320, 240), stride=8)
    boxes = np.array([[10.0, 20.0, 70.0, 90.0], [100.0, 100.0, 131.0, 180.0], [200.5, 30.0, 318.0, 140.0],
                      [40.0, 150.0, 120.0, 238.0]])
    labels = np.array([0, 2, 1, 2])
    t = encode_targets(boxes, labels, cfg, ignore_xyxy=np.array([[250.0, 200.0, 270.0, 230.0]]),
                       ignore_labels=np.array([0]))
    assert t["heat"].shape == (3, 30, 40) and t["ltrb"].shape == (4, 30, 40) and t["n_obj"] == 4
    assert t["heat"].max() == 1.0 and (t["heat"] == 1.0).sum() == 4
    assert t["ignore"][0, 26, 32] == 1.0 and t["ignore"][1].max() == 0.0
    xyxy, scores, cls = decode_targets(t["heat"], t["ltrb"], cfg.stride)
    assert len(xyxy) == 4
    iou = box_iou(xyxy_to_xywh(boxes), xyxy_to_xywh(xyxy))
    match = iou.argmax(1)
    assert np.allclose(xyxy[match], boxes, atol=1e-4)
    assert cls[match].tolist() == labels.tolist()


def _tiny_batch(cfg: DetectorConfig, n: int = 4, seed: int = 0):
    """Images with bright rectangles on noise (class = colour channel) and their targets."""
    rng = np.random.default_rng(seed)
    w, h = cfg.input_size
    imgs = rng.uniform(0, 0.3, (n, 3, h, w)).astype(np.float32)
    targets = []
    for i in range(n):
        x1, y1 = rng.integers(0, w - 24), rng.integers(0, h - 20)
        x2, y2 = x1 + rng.integers(12, 24), y1 + rng.integers(10, 20)
        c = int(rng.integers(cfg.n_classes))
        imgs[i, c, y1:y2, x1:x2] = 1.0
        targets.append(encode_targets(np.array([[x1, y1, x2, y2]], float), np.array([c]), cfg))
    t = {k: torch.as_tensor(v) for k, v in stack_targets(targets).items() if k != "n_obj"}
    return torch.from_numpy(imgs), t


def test_training_steps_reduce_the_loss():
    torch.manual_seed(0)
    cfg = DetectorConfig(obj_ids=[1, 2, 3], **TINY_NET)
    net = CenterNet(cfg).train()
    x, t = _tiny_batch(cfg)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(40):
        heat, box = net(x)
        terms = detection_loss(heat, box, t, cfg.stride)
        opt.zero_grad()
        terms["total"].backward()
        opt.step()
        losses.append(float(terms["total"].detach()))
    assert np.isfinite(losses).all()
    assert losses[-1] < 0.5 * losses[0]


# ------------------------------------------------------------------------------------ ONNX
@pytest.fixture(scope="module")
def tiny_onnx(tmp_path_factory):
    from cosy_cli.detection.train import export_onnx

    torch.manual_seed(1)
    cfg = DetectorConfig(obj_ids=[4, 7, 8], **TINY_NET)
    net = CenterNet(cfg).eval()
    with torch.no_grad():  # a heatmap with some confident peaks even untrained
        net.heat[-1].bias.fill_(0.0)
    path = export_onnx(net, tmp_path_factory.mktemp("onnx") / "tiny.onnx")
    return net, path


def test_onnx_matches_torch(tiny_onnx):
    from cosy_cli.detection.network import OnnxDetector

    net, path = tiny_onnx
    det = OnnxDetector(path)
    x = torch.rand(3, 3, 48, 64)
    with torch.no_grad():
        peaks_t, ltrb_t = ExportWrapper(net)(x)
    peaks_o, ltrb_o = det.raw(x.numpy())
    assert peaks_o.shape == (3, 3, 6, 8) and ltrb_o.shape == (3, 4, 6, 8)
    assert np.abs(peaks_o - peaks_t.numpy()).max() < 1e-4
    assert np.abs(ltrb_o - ltrb_t.numpy()).max() < 1e-4 * max(1.0, float(ltrb_t.abs().max()))


def test_onnx_detector_outputs(tiny_onnx):
    from cosy_cli.detection.network import OnnxDetector

    _, path = tiny_onnx
    det = OnnxDetector(path, providers=("cpu",))
    assert det.obj_ids == [4, 7, 8] and det.input_size == (64, 48)
    rng = np.random.default_rng(0)
    for H, W in ((480, 640), (300, 500), (37, 53)):
        rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        boxes, scores, ids = det.detect(rgb, min_score=0.0, max_per_image=30)
        assert boxes.shape == (len(scores), 4) and ids.shape == scores.shape
        assert boxes.dtype == np.float64 and scores.dtype == np.float64 and ids.dtype == np.int64
        assert 0 < len(scores) <= 30
        assert np.all(np.diff(scores) <= 0) and scores.min() >= 0 and scores.max() <= 1
        assert set(ids.tolist()) <= {4, 7, 8}
        assert np.all(boxes[:, :2] >= 0) and np.all(boxes[:, 2:] >= 0)
        assert np.all(boxes[:, 0] + boxes[:, 2] <= W - 1 + 1e-9) and np.all(boxes[:, 1] + boxes[:, 3] <= H - 1 + 1e-9)
        for c in set(ids.tolist()):  # per-class NMS applied
            m = ids == c
            iou = box_iou(boxes[m], boxes[m])
            assert np.all(iou[np.triu_indices(int(m.sum()), 1)] <= 0.5 + 1e-9)
    few = det.detect(rgb, min_score=0.0, max_per_image=2)
    assert len(few[0]) <= 2
    none = det.detect(rgb, min_score=1.01)
    assert none[0].shape == (0, 4)
    with pytest.raises(ValueError):
        det.detect(rgb.astype(np.float32))


def test_missing_or_bad_model_file(tmp_path):
    from cosy_cli.detection.network import OnnxDetector

    with pytest.raises(CosyError, match="cosy train detector"):
        OnnxDetector(tmp_path / "nope.onnx")
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not an onnx model")
    with pytest.raises(CosyError, match="ONNX"):
        OnnxDetector(bad)


# ------------------------------------------------------------------------------------ CLI
def test_cli_train_resume_export(tmp_path):
    from cosy_cli.detection.network import OnnxDetector
    from cosy_cli.detection.train import read_log

    out = tmp_path / "run"
    args = ["train", "detector", "--dataset", str(DATA), "--out", str(out), "--input", "64x48", "--batch-size", "2",
            "--workers", "0", "--warmup", "1", "--checkpoint-every", "1", "--quiet"]
    r = CliRunner().invoke(cli, args + ["--iterations", "2"])
    assert r.exit_code == 0, r.output
    assert (out / "checkpoint.pt").is_file() and (out / "loss.png").is_file()
    assert [row["step"] for row in read_log(out / "log.csv")] == [1, 2]
    r = CliRunner().invoke(cli, args + ["--iterations", "3"])  # no --resume: refused
    assert r.exit_code == 2 and "--resume" in r.output
    r = CliRunner().invoke(cli, args + ["--iterations", "3", "--resume"])
    assert r.exit_code == 0, r.output
    ck = torch.load(out / "checkpoint.pt", map_location="cpu", weights_only=False)
    assert ck["step"] == 3 and ck["samples"] == 6
    assert [row["step"] for row in read_log(out / "log.csv")] == [1, 2, 3]
    r = CliRunner().invoke(cli, args[:-1] + ["--iterations", "4", "--resume", "--input", "96x64"])
    assert r.exit_code == 2 and "input_size" in r.output  # the model's shape cannot change on resume

    onnx_path = tmp_path / "detector.onnx"
    r = CliRunner().invoke(cli, ["export", "--run", str(out), "--out", str(onnx_path), "--accuracy", "AP50 0.1"])
    assert r.exit_code == 0, r.output
    card = (tmp_path / "detector.md").read_text()
    assert "AP50 0.1" in card and "64 x 48" in card and "3 steps" in card
    det = OnnxDetector(onnx_path)
    assert det.obj_ids == list(range(1, 9)) and det.input_size == (64, 48)
    from cosy_cli.io.images import read_rgb

    boxes, scores, ids = det.detect(read_rgb(DATA / "test" / "000001" / "rgb" / "000000.png"), min_score=0.0)
    assert boxes.shape[1] == 4 and len(boxes) == len(scores) == len(ids)


def test_export_an_efficientnet_lite0_detector_in_int8(tmp_path):
    """`cosy export --precision int8` of an EfficientNet-Lite0 detector run: quantize/dequantize
    pairs in its backbone (calibrated on scenes rendered as in training), int8 on the card, outputs
    close to the float32 export's; the plain backbone refused (exit 2, nothing written)."""
    import onnx

    from cosy_cli.detection.network import OnnxDetector
    from cosy_cli.detection.train import calibration_images

    out = tmp_path / "run"
    args = ["train", "detector", "--dataset", str(DATA), "--out", str(out), "--input", "128x96", "--batch-size", "2",
            "--workers", "0", "--warmup", "1", "--iterations", "2", "--backbone", "efficientnet-lite0", "--quiet"]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    for prec in ("fp32", "int8"):
        r = CliRunner().invoke(cli, ["export", "--run", str(out), "--out", str(tmp_path / f"{prec}.onnx"),
                                     "--precision", prec])
        assert r.exit_code == 0, r.output
    ops = {n.op_type for n in onnx.load(str(tmp_path / "int8.onnx")).graph.node}
    ops32 = {n.op_type for n in onnx.load(str(tmp_path / "fp32.onnx")).graph.node}
    assert {"QuantizeLinear", "DequantizeLinear"} <= ops and "QuantizeLinear" not in ops32
    assert "int8" in (tmp_path / "int8.md").read_text() and "int8" not in (tmp_path / "fp32.md").read_text()
    a, b = OnnxDetector(tmp_path / "fp32.onnx"), OnnxDetector(tmp_path / "int8.onnx")
    x = calibration_images(json.loads((out / "config.json").read_text()), n=4, seed=3)[0]["image"]
    (pa, la), (pb, lb) = a.raw(x), b.raw(x)
    assert not np.array_equal(la, lb)
    np.testing.assert_allclose(lb, la, rtol=0.25, atol=2.0)  # box edge distances, input px
    plain = tmp_path / "plain"
    r = CliRunner().invoke(cli, ["train", "detector", "--dataset", str(DATA), "--out", str(plain), "--input", "64x48",
                                 "--batch-size", "2", "--workers", "0", "--iterations", "1", "--quiet"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(cli, ["export", "--run", str(plain), "--out", str(tmp_path / "p.onnx"), "--precision", "int8"])
    assert r.exit_code == 2 and "EfficientNet-Lite0" in r.output and not (tmp_path / "p.onnx").exists()


def test_cli_rejects_pose_options_for_the_detector(tmp_path):
    r = CliRunner().invoke(cli, ["train", "detector", "--dataset", str(DATA), "--out", str(tmp_path / "r"),
                                 "--crop", "64x48"])
    assert r.exit_code != 0 and "--input" in r.output
    r = CliRunner().invoke(cli, ["train", "detector", "--dataset", str(DATA), "--out", str(tmp_path / "r"),
                                 "--input", "70x48"])
    assert r.exit_code == 2 and "multiples of 16" in r.output


def test_sigterm_saves_a_checkpoint(tmp_path):
    """A background run stopped with `kill PID` (SIGTERM) saves its checkpoint like Ctrl-C."""
    import os
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "cosy_cli", "train", "detector", "--dataset", str(DATA), "--out", str(out),
           "--input", "64x48", "--batch-size", "1", "--workers", "0", "--iterations", "100000",
           "--checkpoint-every", "100000", "--quiet"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=dict(os.environ))
    try:
        t0 = time.time()
        while not ((out / "log.csv").is_file() and len((out / "log.csv").read_text().splitlines()) >= 2):
            assert p.poll() is None, p.stdout.read().decode()
            assert time.time() - t0 < 60, "no training step logged within 60 s"
            time.sleep(0.2)
        p.send_signal(signal.SIGTERM)
        p.wait(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    text = p.stdout.read().decode()
    assert p.returncode == 130, text
    assert "checkpoint saved at step" in text
    ck = torch.load(out / "checkpoint.pt", map_location="cpu", weights_only=False)
    assert ck["step"] >= 20


# ------------------------------------------------------------------------------------ warm start, sampling, bench
def test_warm_start_from_onnx_reproduces_the_exported_network(tmp_path):
    """The ONNX holds BatchNorms folded into its convs: init_from_onnx recovers a torch model that
    computes the same outputs (eval mode, and training mode on its calibration batch)."""
    from cosy_cli.detection.network import OnnxDetector
    from cosy_cli.detection.train import export_onnx, init_from_onnx

    torch.manual_seed(3)
    cfg = DetectorConfig(obj_ids=[1, 2, 3], **TINY_NET)
    src = CenterNet(cfg)
    with torch.no_grad():  # non-trivial BatchNorms, as after training
        for m in src.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.uniform_(0.5, 1.5)
                m.bias.uniform_(-0.3, 0.3)
    path = export_onnx(src.eval(), tmp_path / "src.onnx")
    rng = np.random.default_rng(0)
    calib = rng.uniform(0, 1, (8, 3, 48, 64)).astype(np.float32)
    net = CenterNet(cfg)
    info = init_from_onnx(net, path, calib)
    assert info["convs"] == sum(isinstance(m, torch.nn.Conv2d) for m in net.modules())
    assert info["batchnorms"] == sum(isinstance(m, torch.nn.BatchNorm2d) for m in net.modules())
    x = rng.uniform(0, 1, (3, 3, 48, 64)).astype(np.float32)
    peaks, ltrb = OnnxDetector(path).raw(x)
    with torch.no_grad():
        p2, l2 = ExportWrapper(net.eval())(torch.from_numpy(x))
        h_train, _ = net.train()(torch.from_numpy(calib))
        h_eval, _ = net.eval()(torch.from_numpy(calib))
    np.testing.assert_allclose(p2.numpy(), peaks, atol=1e-5)
    np.testing.assert_allclose(l2.numpy(), ltrb, rtol=1e-4)
    np.testing.assert_allclose(h_train.numpy(), h_eval.numpy(), atol=1e-3)
    other = CenterNet(DetectorConfig(obj_ids=[1, 2, 3], **dict(TINY_NET, fpn=16)))
    with pytest.raises(CosyError, match="shape|architecture"):
        init_from_onnx(other, path, calib)


@pytest.fixture(scope="module")
def meshes():
    from cosy_cli.detection.train import load_dataset_objects

    return load_dataset_objects(DATA)


def test_class_weights_and_confusable_pairs(meshes):
    from cosy_cli.detection.data import DetectionSampleGenerator, normalised_weights, pair_table

    m, K, size = meshes
    gen = DetectionSampleGenerator(m, K, size, (160, 120), seed=0, class_weights={7: 9.0})
    first = np.array([gen._choose(1)[0][0] for _ in range(2000)])
    assert abs(np.mean(first == 7) - 9 / 16) < 0.05  # 9 / (9 + 7 x 1)
    ids, pair = gen._choose(20)
    assert not pair and len(ids) == 20 and set(ids.tolist()) == set(range(1, 9))  # all objects, then repeats
    gen = DetectionSampleGenerator(m, K, size, (160, 120), seed=1, confusable=[[6, 7, 3.0], [4, 5]], p_pair=1.0)
    firsts = [tuple(sorted(gen._choose(int(n))[0][:2].tolist())) for n in np.random.default_rng(0).integers(1, 5, 400)]
    assert set(firsts) == {(6, 7), (4, 5)} and abs(firsts.count((6, 7)) / 400 - 0.75) < 0.07
    b = gen.batch(10)  # rendered: the pair shows up together (unless a member is hidden or out of view)
    cls = {o: k for k, o in enumerate(gen.obj_ids.tolist())}
    both = [any({cls[a], cls[c]} <= set(lab.tolist()) for a, c in ((6, 7), (4, 5))) for lab in b["labels"]]
    assert b["images"].shape == (10, 120, 160, 3)
    assert sum(both) >= 5, b["labels"]
    gen.close()
    assert normalised_weights(None, [1, 2]) is None
    np.testing.assert_allclose(normalised_weights({"2": 3}, [1, 2]), [0.25, 0.75])
    with pytest.raises(ValueError):
        normalised_weights({9: 1.0}, [1, 2])
    with pytest.raises(ValueError):
        pair_table([[1, 1]], [1, 2])


def test_cli_detector_warm_start_and_sampling_options(tmp_path):
    from cosy_cli.detection.train import DEFAULT_CONF, export_onnx, model_config

    net = CenterNet(model_config(dict(DEFAULT_CONF, input_size=[64, 48]), range(1, 9))).eval()
    init = export_onnx(net, tmp_path / "init.onnx")
    out = tmp_path / "run"
    args = ["train", "detector", "--dataset", str(DATA), "--out", str(out), "--input", "64x48", "--batch-size", "2",
            "--workers", "0", "--warmup", "1", "--iterations", "1", "--init", str(init),
            "--class-weights", "7=3,6=2", "--confusable", "6:7:2,4:5"]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    assert "warm start" in r.output
    ck = torch.load(out / "checkpoint.pt", map_location="cpu", weights_only=False)
    c = ck["config"]
    assert c["class_weights"] == {"7": 3.0, "6": 2.0} and c["confusable"] == [[6, 7, 2.0], [4, 5]]
    assert c["p_pair"] == 0.5
    r = CliRunner().invoke(cli, args[:-6] + ["--iterations", "2", "--resume", "--class-weights", "7=3,6=2",
                                             "--confusable", "6:7:2,4:5"])  # resumable without --init
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(cli, args[:-6] + ["--overwrite", "--confusable", "6:9"])
    assert r.exit_code == 2 and "lacks" in r.output
    r = CliRunner().invoke(cli, args[:-6] + ["--overwrite", "--class-weights", "7:3"])
    assert r.exit_code == 2 and "OBJ=WEIGHT" in r.output


def test_bench_detect_makes_the_seed_set_and_scores_gt_boxes(tmp_path):
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import bench_detect

    ds = bench_detect.ensure_seed_set(tmp_path / "held", seed=31337, scenes=1, views=2, objects=4)
    assert (ds / "test" / "000001" / "scene_gt.json").is_file()
    s = bench_detect.evaluate(ds, from_gt=True, progress=False)
    assert s["AP50"] == pytest.approx(1.0) and s["images_run"] == 2
    assert "none" in bench_detect.confusions_line(s)
    assert bench_detect.synth_cmd(ds, 7, 6, 6, 8)[-9:] == ["--scenes", "6", "--views", "6", "--objects", "8",
                                                          "--seed", "7", "--quiet"]


def test_detector_onboarding_from_meshes_alone_with_the_real_preset(tmp_path):
    """`cosy train detector --models DIR --preset real`: the meshes without a dataset, the camera beside
    them, the appearance of real photographs (own colours, clutter, jitter, busy scenes) and a warm
    start from the shipped detector; the default preset keeps the generator's own defaults."""
    from cosy_cli.detection import data as det_data
    from cosy_cli.detection.train import DEFAULT_CONF, resolve_conf

    real, default = resolve_conf("real"), resolve_conf()
    assert real["p_mesh_colors"] == 0.6 and real["max_distractors"] == 10 and real["min_objects"] == 3
    assert real["clutter_shapes"] == 32 and real["backdrop"] == [0.7, 8, 30] and real["p_photo_texture"] == 0.5
    assert real["init"].endswith("detector.onnx") and Path(real["init"]).is_file()
    import inspect

    gen = inspect.signature(det_data.DetectionSampleGenerator.__init__).parameters
    for k in ("p_mesh_colors", "max_distractors", "gain_jitter", "min_objects", "backdrop", "photos"):
        if k == "photos":  # the default preset draws the scenes it always drew
            assert default["backgrounds"] is None and gen[k].default is None and gen["p_photo"].default == 0
            continue
        assert default[k] == (list(gen[k].default) if k == "backdrop" else gen[k].default), k
    assert tuple(default["saturation"]) == gen["saturation"].default and tuple(default["blur"]) == gen["blur"].default
    with pytest.raises(CosyError, match="appearance"):
        resolve_conf(None, p_mesh_colors=1.5)

    out, photos = tmp_path / "run", tmp_path / "photos"
    photos.mkdir()
    for i in range(2):
        cv2.imwrite(str(photos / f"p{i}.jpg"), np.full((90, 120, 3), 60 * i, np.uint8))
    args = ["train", "detector", "--models", str(DATA / "models"), "--out", str(out), "--preset", "real",
            "--input", "64x48", "--batch-size", "2", "--workers", "0", "--warmup", "1", "--iterations", "2",
            "--backgrounds", str(photos)]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    rec = json.loads((out / "config.json").read_text())
    assert rec["models"] == str((DATA / "models").resolve()) and "dataset" not in rec
    assert rec["image_size"] == [640, 480] and rec["p_mesh_colors"] == 0.6 and rec["max_distractors"] == 10
    assert "warm start from" in r.output and "2 background photographs" in r.output
    r = CliRunner().invoke(cli, ["export", "--run", str(out), "--out", str(tmp_path / "det.onnx")])
    assert r.exit_code == 0, r.output
    card = (tmp_path / "det.md").read_text()
    assert "the models folder `data_samples/models`" in card and "own mesh colours with probability 0.6" in card
    assert "photographs of the folder `photos` as the background of 50% of the images" in card
    assert "windows of them on 50% of the table and clutter surfaces" in card
    # what the CLI refuses: both sources, the scorer's preset, --models for the pose networks
    for bad, said in ((args + ["--dataset", str(DATA)], "not both"), ([a if a != "real" else "long" for a in args],
                      "not a preset of the detector"),
                      (["train", "refiner", "--models", str(DATA / "models"), "--dataset", str(DATA), "--out",
                        str(tmp_path / "r")], "--models and --camera are for"),
                      (["train", "coarse", "--dataset", str(DATA), "--backgrounds", str(photos), "--out",
                        str(tmp_path / "c")], "--backgrounds is for the detector, the box classifier and the scorer"),
                      ([a if a != str(out) else str(tmp_path / "r2") for a in args[:-2]] + ["--backgrounds",
                       str(DATA / "models")], "no image")):
        r = CliRunner().invoke(cli, bad)
        assert r.exit_code == 2 and said in r.output, r.output


def test_classifier_onboarding_from_meshes_alone_with_the_real_preset(tmp_path):
    """`cosy train classifier --models DIR --preset real --backgrounds PHOTOS`: the detector's real
    appearance, uniform classes (the sample objects' tuning dropped for other objects), the shipped
    detector's backbone; the model card says so; the default preset is unchanged."""
    from cosy_cli.detection import classifier_train as ct
    from cosy_cli.detection.train import APPEARANCE_KEYS, CONFS

    real, default = ct.resolve_conf("real"), ct.resolve_conf()
    assert all(real[k] == ct.resolve_conf(None, **{k: CONFS["real"][k]})[k] for k in APPEARANCE_KEYS)
    assert real["class_weights"] is None and real["confusable"] is None and real["init"].endswith("detector.onnx")
    assert default["backgrounds"] is None and default["max_distractors"] == 0 and default["confusable"]
    with pytest.raises(CosyError, match="p_photo_texture"):
        ct.resolve_conf("real", p_photo_texture=2)

    photos, out = tmp_path / "photos", tmp_path / "clf"
    photos.mkdir()
    for i in range(2):
        cv2.imwrite(str(photos / f"p{i}.jpg"), np.full((90, 120, 3), 60 * i + 30, np.uint8))
    models = tmp_path / "models"  # objects 1, 2, 5 of the samples: the samples' pairs and weights name others
    models.mkdir()
    info = json.loads((DATA / "models" / "models_info.json").read_text())
    for o in ("1", "2", "5"):
        (models / f"obj_{int(o):06d}.ply").write_bytes((DATA / "models" / f"obj_{int(o):06d}.ply").read_bytes())
    (models / "models_info.json").write_text(json.dumps({o: info[o] for o in ("1", "2", "5")}))
    args = ["train", "classifier", "--models", str(models), "--camera", str(DATA / "camera.json"), "--out", str(out),
            "--preset", "real", "--batch-size", "8", "--warmup", "1", "--iterations", "2", "--backgrounds", str(photos)]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    assert "2 background photographs" in r.output and "BatchNorms recalibrated" in r.output
    rec = json.loads((out / "config.json").read_text())
    assert rec["models"] == str(models.resolve()) and "dataset" not in rec and rec["obj_ids"] == [1, 2, 5]
    assert rec["p_mesh_colors"] == 0.6 and rec["backgrounds"] == str(photos) and rec["class_weights"] is None
    r = CliRunner().invoke(cli, ["export", "--run", str(out), "--out", str(tmp_path / "clf.onnx")])
    assert r.exit_code == 0, r.output
    card = (tmp_path / "clf.md").read_text()
    assert "models of `models`" in card and "photographs of the folder `photos`" in card
    # the real preset also learns to move boxes onto the objects (a box head, wider box jitter)
    assert rec["box_head"] is True and rec["jitter"] == 0.12 and "a box head" in card
    from cosy_cli.detection.classifier import OnnxClassifier

    assert OnnxClassifier(tmp_path / "clf.onnx").has_box_head
    assert "loss_box" in (out / "log.csv").read_text().splitlines()[0]
    # the default preset on objects the samples' tuning does not name: it is dropped, the run trains
    r = CliRunner().invoke(cli, [a for a in args if a not in ("--preset", "real", "--backgrounds", str(photos))]
                           + ["--out", str(tmp_path / "clf2"), "--iterations", "1"])
    assert r.exit_code == 0, r.output
    rec = json.loads((tmp_path / "clf2" / "config.json").read_text())
    assert rec["confusable"] is None and rec["class_weights"] is None and rec["p_pair"] == 0
    # weights naming an object the models lack: a clear error
    r = CliRunner().invoke(cli, [a for a in args if a not in ("--backgrounds", str(photos))]
                           + ["--out", str(tmp_path / "clf3"), "--class-weights", "7=2"])
    assert r.exit_code == 2 and "class_weights names objects [7]" in r.output, r.output


def test_resuming_a_run_recorded_before_a_setting_existed(tmp_path):
    """A run recorded before a setting was added resumes when the setting keeps the value that does
    what runs did before; another value is refused."""
    import torch

    from cosy_cli.training import loop

    torch.save({"config": {"lr": 1.0}, "step": 3}, tmp_path / loop.CHECKPOINT)
    assert loop.start_run(tmp_path, {"lr": 1.0, "new": 0.0}, resume=True, overwrite=False,
                          added={"new": 0.0})["step"] == 3
    with pytest.raises(CosyError, match="new: None in the run, 0.5 now"):
        loop.start_run(tmp_path, {"lr": 1.0, "new": 0.5}, resume=True, overwrite=False, added={"new": 0.0})
    with pytest.raises(CosyError, match="new"):
        loop.start_run(tmp_path, {"lr": 1.0, "new": 0.0}, resume=True, overwrite=False)


def test_clutter_shapes_and_a_cluttered_backdrop(meshes):
    """Unlabelled clutter of many shapes and sizes, and a backdrop of it behind the objects: the
    labels stay those of the objects, the background is no longer empty."""
    from cosy_cli.detection.data import CLUTTER_ID0, DetectionSampleGenerator, clutter_meshes
    from cosy_cli.detection.train import resolve_conf

    a, b = clutter_meshes(14, seed=3), clutter_meshes(14, seed=3)
    assert sorted(a) == list(range(1, 15))
    assert all(np.allclose(a[k].vertices, b[k].vertices) for k in a)
    ext = np.array([m.extents for m in a.values()])
    assert ext.min() > 5 and ext.max() < 450 and len({round(float(e), 3) for e in ext[:, 0]}) == 14
    assert not np.allclose(clutter_meshes(3, seed=4)[1].extents, a[1].extents)

    m, K, size = meshes
    clutter = {CLUTTER_ID0 + k: v for k, v in a.items()}
    fg = {}
    for backdrop in ((0.0, 0, 0), (1.0, 12, 12)):
        gen = DetectionSampleGenerator(m, K, size, (160, 120), seed=5, p_table=0.0, max_objects=2,
                                       distractors=clutter, backdrop=backdrop)
        rendered = []
        orig = gen._compose
        gen._compose = lambda rgb, foreground: (rendered.append(foreground.mean()), orig(rgb, foreground))[1]
        batch = gen.batch(6)
        gen.close()
        fg[backdrop[0]] = float(np.mean(rendered))
        for lab in batch["labels"]:
            assert len(lab) <= 2 and (lab < len(m)).all()
    assert fg[1.0] > fg[0.0] + 0.08, fg  # the backdrop covers a part of what was empty background
    conf = resolve_conf("real", clutter_shapes=8, backdrop=[0.5, 2, 6])
    assert conf["backdrop"] == [0.5, 2, 6] and conf["clutter_shapes"] == 8
    with pytest.raises(CosyError, match="backdrop"):
        resolve_conf(None, backdrop=[0.5, 6, 2])


def test_camera_distance_and_floating_depth_ranges(meshes):
    """The distance range of the rendered scenes (a user's working distance): table scenes seen from
    farther, floating objects within the given depths; the defaults are passed as before (nothing)."""
    from cosy_cli.detection.data import DetectionSampleGenerator
    from cosy_cli.detection.train import appearance_kwargs, resolve_conf

    m, K, size = meshes

    def depths(**kw):
        gen = DetectionSampleGenerator(m, K, size, (160, 120), seed=7, max_objects=3, **kw)
        z = np.concatenate([T[:, 2, 3] for T in gen.batch(8)["T_cam_obj"]])
        gen.close()
        return z

    near, far = depths(p_table=1.0), depths(p_table=1.0, camera_distance=(1600.0, 1800.0))
    assert np.median(near) < 1000 and np.median(far) > 1300, (np.median(near), np.median(far))
    z = depths(p_table=0.0, float_depth=(1300.0, 1400.0))
    assert len(z) and z.min() >= 1300 * 0.9 - 1e-6 and z.max() <= 1400 * 1.1 + 1e-6  # a look-alike pair: +-10 %
    z = depths(p_table=0.0)
    assert z.min() >= 250 * 0.9 and z.max() <= 1200 * 1.1
    assert "camera_distance" not in appearance_kwargs(resolve_conf("real"), log=lambda s: None)
    c = resolve_conf("real", camera_distance=[500, 2000], float_depth=[400, 1800])
    kw = appearance_kwargs(c, log=lambda s: None)
    assert kw["camera_distance"] == (500.0, 2000.0) and kw["float_depth"] == (400.0, 1800.0)
    for bad in ([900, 500], [0, 500], [500]):
        with pytest.raises(CosyError, match="camera_distance"):
            resolve_conf("real", camera_distance=bad)


def test_photographs_as_backgrounds(meshes, tmp_path):
    """--backgrounds: random windows of the user's photographs fill the background of a share of the
    images (the objects and their labels unchanged); the folder is read once, shrunk."""
    from cosy_cli.detection.data import DetectionSampleGenerator, photo_window
    from cosy_cli.io.images import read_photo_folder

    rng = np.random.default_rng(0)
    photo = np.zeros((300, 500, 3), np.uint8)
    photo[:, :250] = (0, 0, 255)  # left half blue, right half red
    photo[:, 250:] = (255, 0, 0)
    wins = [photo_window(photo, 48, 64, rng) for _ in range(40)]
    assert all(w.shape == (48, 64, 3) and w.dtype == np.float32 for w in wins)
    blue = [float((w[..., 2] > 128).mean()) for w in wins]
    assert min(blue) < 0.5 < max(blue) and any(0 < b < 1 for b in blue)  # windows differ, some straddle
    assert all(np.isin(w[..., 1], [0.0]).all() for w in wins)  # only the photo's colours (no green)

    (tmp_path / "a.png").write_bytes(b"")  # not an image: a clear error names it
    with pytest.raises(CosyError, match="unreadable"):
        read_photo_folder(tmp_path)
    (tmp_path / "a.png").unlink()
    cv2.imwrite(str(tmp_path / "big.jpg"), np.full((1200, 1600, 3), 200, np.uint8))
    (tmp_path / "notes.txt").write_text("not an image")
    got = read_photo_folder(tmp_path, max_side=400)
    assert len(got) == 1 and got[0].shape == (300, 400, 3)

    m, K, size = meshes
    share = {}
    for p in (0.0, 1.0):
        gen = DetectionSampleGenerator(m, K, size, (160, 120), seed=5, p_table=0.0, max_objects=2,
                                       photos=[photo[:, :250].copy()], p_photo=p)
        batch = gen.batch(6)
        gen.close()
        img = batch["images"].astype(np.float32)
        share[p] = float(((img[..., 2] > img[..., 0] + 40) & (img[..., 2] > img[..., 1] + 40)).mean())
        for lab in batch["labels"]:
            assert len(lab) <= 2 and (lab < len(m)).all()
    assert share[1.0] > 0.5 and share[0.0] < 0.3, share  # blue photo behind the objects

    # photographs on the table and clutter surfaces: the same scenes and boxes, the surfaces now green
    green = np.zeros((200, 300, 3), np.uint8)
    green[..., 1] = 255
    got = {}
    for p in (0.0, 1.0):
        gen = DetectionSampleGenerator(m, K, size, (160, 120), seed=6, p_table=1.0, max_objects=2, photos=[green],
                                       p_photo=0.0, p_photo_texture=p)
        batch = gen.batch(4)
        gen.close()
        img = batch["images"].astype(np.float32)
        got[p] = (float(((img[..., 1] > img[..., 0] + 30) & (img[..., 1] > img[..., 2] + 30)).mean()), batch["boxes"])
    assert got[1.0][0] > got[0.0][0] + 0.2, (got[0.0][0], got[1.0][0])
    assert all(np.array_equal(a, b) for a, b in zip(got[0.0][1], got[1.0][1]))
    with pytest.raises(CosyError, match="p_photo_texture"):
        from cosy_cli.detection.train import resolve_conf as _rc
        _rc("real", p_photo_texture=1.5)
