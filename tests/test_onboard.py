"""`cosy onboard`: the detector and the box classifier trained side by side, exported, resumed."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from cosy_cli.cli.main import cli

SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"


def _run(args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def _step(run: Path) -> int:
    """The run's last step (its checkpoint's)."""
    import torch

    return int(torch.load(run / "checkpoint.pt", map_location="cpu", weights_only=False)["step"])


def test_onboard_trains_both_side_by_side_exports_and_resumes(tmp_path):
    from cosy_cli.detection.classifier import OnnxClassifier
    from cosy_cli.detection.network import OnnxDetector

    out = tmp_path / "onb"
    base = ["onboard", "--models", SAMPLES / "models", "--out", out]
    r = _run(base + ["--detector-iterations", 2, "--classifier-iterations", 2])
    assert r.exit_code == 0, r.output
    rec = json.loads((out / "onboard.json").read_text())
    assert rec["commands"]["detector"][2:4] == ["train", "detector"] and "--preset" in rec["commands"]["classifier"]
    assert _step(out / "detector") == 2 and _step(out / "classifier") == 2
    clf = OnnxClassifier(out / "classifier.onnx")
    assert clf.has_box_head and clf.has_mask_head and clf.obj_ids == list(range(1, 9))
    det = OnnxDetector(out / "detector.onnx")
    boxes, scores, labels = det.detect(np.zeros((480, 640, 3), np.uint8), 0.0, 5, 0.5)
    assert len(boxes) == 5
    # the folder is not overwritten by mistake; --resume continues both runs
    r = _run(base + ["--detector-iterations", 2, "--classifier-iterations", 2])
    assert r.exit_code == 2 and "--resume" in r.output
    r = _run(base + ["--detector-iterations", 3, "--classifier-iterations", 3, "--resume"])
    assert r.exit_code == 0, r.output
    assert _step(out / "detector") == 3 and _step(out / "classifier") == 3
    # --long: the detector continues at 480 x 352 from the first run's weights; --distance reaches every run;
    # --classifier-backbone the classifier alone
    r = _run(base + ["--detector-iterations", 1, "--classifier-iterations", 1, "--long", "--long-iterations", 1,
                     "--distance", "400,1500", "--classifier-backbone", "efficientnet-lite0", "--overwrite"])
    assert r.exit_code == 0, r.output
    assert json.loads((out / "classifier" / "config.json").read_text())["arch"] == "lite0"
    assert OnnxClassifier(out / "classifier.onnx").config.arch == "lite0"
    assert json.loads((out / "detector" / "config.json").read_text())["backbone"] == "plain"
    assert _step(out / "detector480") == 1
    cfg = json.loads((out / "detector480" / "config.json").read_text())
    assert list(cfg["input_size"]) == [480, 352] and cfg["init"].endswith("detector320.onnx")
    for run in ("detector", "classifier", "detector480"):
        cfg = json.loads((out / run / "config.json").read_text())
        assert cfg["camera_distance"] == [400.0, 1500.0] and cfg["float_depth"] == [400.0, 1500.0], run
    assert "the camera 400-1500 mm from table scenes" in (out / "detector.md").read_text()
    assert "detector480" in json.loads((out / "onboard.json").read_text())["minutes"]
    # both on EfficientNet-Lite0, the classifier exported in int8
    r = _run(base + ["--detector-iterations", 1, "--classifier-iterations", 1, "--detector-backbone",
                     "efficientnet-lite0", "--classifier-backbone", "efficientnet-lite0", "--classifier-precision",
                     "int8", "--overwrite"])
    assert r.exit_code == 0, r.output
    assert json.loads((out / "detector" / "config.json").read_text())["backbone"] == "lite0"
    assert OnnxDetector(out / "detector.onnx").config["backbone"] == "lite0"
    assert "int8" in (out / "classifier.md").read_text() and "in int8" in r.output
    from cosy_cli.detection import train as det_train

    assert det_train.resolve_conf("real", backbone="lite0")["iterations"] == det_train.LITE0_REAL["iterations"]
    assert det_train.resolve_conf("real", backbone="lite0", iterations=7)["iterations"] == 7
    assert det_train.resolve_conf("real")["iterations"] == 2500


def test_onboard_reports_a_failed_training_and_bad_inputs(tmp_path):
    empty = tmp_path / "photos"
    empty.mkdir()
    r = _run(["onboard", "--models", SAMPLES / "models", "--out", tmp_path / "o", "--backgrounds", empty,
              "--detector-iterations", 1, "--classifier-iterations", 1])
    assert r.exit_code == 2 and "failed" in r.output and "Traceback" not in r.output, r.output
    r = _run(["onboard", "--models", tmp_path, "--out", tmp_path / "o2"])
    assert r.exit_code == 2 and "models_info.json" in r.output
    r = _run(["onboard", "--models", SAMPLES / "models", "--out", tmp_path / "o4", "--classifier-precision", "int8"])
    assert r.exit_code == 2 and "efficientnet-lite0" in r.output, r.output
    r = _run(["onboard", "--models", SAMPLES / "models", "--out", tmp_path / "o3", "--distance", "900,500"])
    assert r.exit_code == 2 and "NEAR <= FAR" in r.output, r.output
    r = _run(["train", "scorer", "--models", SAMPLES / "models", "--out", tmp_path / "s.onnx", "--distance", "300,900"])
    assert r.exit_code == 2 and "--distance is for the detector" in r.output, r.output
