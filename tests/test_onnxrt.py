"""Opening cosy's ONNX models: one session per file and settings in a process, a changed file
opened anew, the card a caller gets its own copy."""

import shutil

import numpy as np
import pytest

from cosy_cli import onnxrt
from cosy_cli.detection import stage
from cosy_cli.detection.network import METADATA_KEY, OnnxDetector
from cosy_cli.errors import CosyError


@pytest.fixture()
def model(tmp_path):
    if not stage.SHIPPED_DETECTOR.is_file():
        pytest.skip("the shipped detector is not in this checkout")
    dst = tmp_path / "det.onnx"
    shutil.copyfile(stage.SHIPPED_DETECTOR, dst)
    return dst


def test_same_file_same_session_changed_file_new_one(model):
    s1, card1 = onnxrt.open_session(model, METADATA_KEY)
    s2, card2 = onnxrt.open_session(model, METADATA_KEY)
    assert s2 is s1 and card2 == card1
    card2["obj_ids"] = []  # a caller's copy: the next one is untouched
    assert onnxrt.open_session(model, METADATA_KEY)[1] == card1
    # other settings: another session
    assert onnxrt.open_session(model, METADATA_KEY, threads=1)[0] is not s1
    # the file rewritten (as cosy export does, atomically): opened anew, its new card
    onnxrt.update_card(model, METADATA_KEY, note="changed")
    s3, card3 = onnxrt.open_session(model, METADATA_KEY)
    assert s3 is not s1 and card3["note"] == "changed"
    # both detectors run alike on a session shared between them
    d1, d2 = OnnxDetector(model), OnnxDetector(model)
    assert d1.session is d2.session
    rgb = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    a, b = d1.detect(rgb, 0.01, 20, 0.5), d2.detect(rgb, 0.01, 20, 0.5)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    model.unlink()
    with pytest.raises(CosyError, match="not found"):
        onnxrt.open_session(model, METADATA_KEY)


def test_cache_is_bounded(model, tmp_path, monkeypatch):
    monkeypatch.setattr(onnxrt, "SESSION_CACHE_SIZE", 2)
    first = onnxrt.open_session(model, METADATA_KEY, threads=1)[0]
    onnxrt.open_session(model, METADATA_KEY, threads=2)
    onnxrt.open_session(model, METADATA_KEY, threads=3)
    assert len(onnxrt._SESSIONS) <= 2
    assert onnxrt.open_session(model, METADATA_KEY, threads=1)[0] is not first
