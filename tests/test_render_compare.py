"""Inference with the render-and-compare networks: the inputs match training, ONNX runs in the loop."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cosy_cli.rendering import SceneRenderer  # noqa: F401  (selects the GL platform first)
from cosy_cli.singleview.networks.model import PoseNet  # noqa: E402
from cosy_cli.singleview.networks.onnx import OnnxPoseNet, export_onnx  # noqa: E402
from cosy_cli.singleview.networks.pose_update import update_targets  # noqa: E402
from cosy_cli.singleview.networks.render_compare import RenderAndCompare  # noqa: E402
from cosy_cli.training.data import SampleGenerator, synthetic_source  # noqa: E402

CROP = (64, 48)


class _Fixed:
    """A stand-in network returning preset updates (B, 9), with a PoseNet config."""

    def __init__(self, config, updates):
        self.config = config
        self.updates = np.asarray(updates, dtype=np.float32)

    def __call__(self, x):
        return self.updates[: len(x)]


@pytest.fixture(scope="module")
def gen():
    meshes, syms = synthetic_source()
    g = SampleGenerator(meshes, symmetries=syms, crop_size=CROP, seed=5, occluder_probs=(1.0,), augment=False)
    yield g
    g.close()


def _runner(gen, net):
    hulls = {int(o): h for o, h in zip(gen.obj_ids, gen.hull)}
    return RenderAndCompare(net, gen.renderer, hulls)


def test_inference_crops_and_renders_match_training(gen):
    """Same crop windows, crop intrinsics and rendered branch as the training samples: a model
    trained on SampleGenerator sees the same kind of input at test time."""
    b = gen.batch(6)
    rc = _runner(gen, PoseNet("refiner", crop_size=CROP))
    ids = b["obj_id"]
    for i in range(6):
        x, K_crop, boxes, rendered = rc.make_inputs(np.zeros((480, 640, 3), np.uint8), b["K"][i], b["T_input"][i:i + 1],
                                                    ids[i:i + 1])
        np.testing.assert_allclose(boxes[0], b["box"][i], atol=1e-6)
        np.testing.assert_allclose(K_crop[0], b["K_crop"][i], atol=1e-9)
        diff = np.abs(rendered[0].astype(int) - b["rendered"][i].astype(int))
        assert (diff > 2).mean() < 0.002, f"sample {i}: rendered branch differs from training"
        assert x.shape == (1, 6, CROP[1], CROP[0]) and x.dtype == np.float32


def test_exact_update_reaches_the_target(gen):
    """Feeding the true update (what a perfect network outputs) moves T_input onto T_gt in one
    step: crops, crop intrinsics and the update equations agree at inference."""
    b = gen.batch(4)
    net = PoseNet("refiner", crop_size=CROP)
    rc = _runner(gen, net)
    for i in range(4):
        T_in, T_gt = b["T_input"][i:i + 1].copy(), b["T_gt"][i:i + 1].copy()
        _, K_crop, _, _ = rc.make_inputs(np.zeros((480, 640, 3), np.uint8), b["K"][i], T_in, b["obj_id"][i:i + 1])
        target = update_targets(torch.from_numpy(T_in), torch.from_numpy(T_gt), torch.tensor(K_crop)).numpy()
        rc.net = _Fixed(net.config, target)
        T_out = rc.step(np.zeros((480, 640, 3), np.uint8), b["K"][i], T_in, b["obj_id"][i:i + 1])
        np.testing.assert_allclose(T_out[0, :3, 3], T_gt[0, :3, 3], atol=1e-3)
        np.testing.assert_allclose(T_out[0, :3, :3], T_gt[0, :3, :3], atol=1e-5)


def test_untrained_onnx_refiner_leaves_poses_unchanged(gen, tmp_path):
    """An exported untrained refiner outputs the identity update, so iterating keeps the poses;
    the coarse runner starts from the canonical pose at the box centre."""
    net = PoseNet("refiner", crop_size=CROP).eval()
    path = export_onnx(net, tmp_path / "r.onnx")
    onnx_net = OnnxPoseNet(path)
    rc = _runner(gen, onnx_net)
    b = gen.batch(5)
    K = b["K"][0]
    hist = rc.iterate(np.zeros((480, 640, 3), np.uint8), K, b["T_input"], b["obj_id"], 2)
    assert len(hist) == 2
    np.testing.assert_allclose(hist[-1], b["T_input"], atol=1e-4)
    behind = b["T_input"].copy()
    behind[0, 2, 3] = -100.0
    out = rc.step(np.zeros((480, 640, 3), np.uint8), K, behind, b["obj_id"])
    np.testing.assert_array_equal(out[0], behind[0])
