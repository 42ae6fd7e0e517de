"""PoseNet to ONNX and back: export with a dynamic batch dimension, run with onnxruntime.

The ONNX graph takes ``input`` (B, C, H, W) float32 in [0, 1] (normalisation is inside the graph,
see :mod:`~cosy_cli.singleview.networks.model`) and returns ``update`` (B, 9). The PoseNet config (kind,
backbone, n_inputs, crop_size) is stored in the model's metadata under ``cosy_posenet``.
"""

from __future__ import annotations

import copy
import warnings
from pathlib import Path

import numpy as np
import torch

from ...io.atomic import atomic_path
from ...onnxrt import open_session, stamp_card  # noqa: F401 (open_session: also imported from here)
from .model import PoseNet, PoseNetConfig

INPUT_NAME = "input"
OUTPUT_NAME = "update"
METADATA_KEY = "cosy_posenet"
OPSET = 17


def export_onnx(model: PoseNet, path: str | Path, crop_size: tuple[int, int] | None = None,
                opset: int = OPSET, dynamo: bool = False) -> Path:
    """Write ``model`` to ``path`` (one self-contained .onnx file, atomically); returns the path.

    crop_size (width, height) px defaults to the model's own; the batch dimension is dynamic.
    By default the TorchScript-based exporter (about 1 s for B0; deprecated since torch 2.9);
    ``dynamo=True`` uses the torch.export-based one (needs onnxscript; about 12 s for B0 here),
    same outputs.
    """
    cfg = model.config
    w, h = crop_size or cfg.crop_size
    if (w, h) != tuple(cfg.crop_size):
        raise ValueError(f"export_onnx: the network was built for crops {cfg.crop_size}, not {(w, h)}")
    net = copy.deepcopy(model).cpu().float().eval()
    net.set_export_mode(True)
    dummy = torch.rand(2, cfg.n_inputs, h, w)
    path = Path(path)
    with atomic_path(path) as tmp:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the legacy exporter's deprecation and constant-folding notes
            if dynamo:
                torch.onnx.export(net, (dummy,), str(tmp), input_names=[INPUT_NAME], output_names=[OUTPUT_NAME],
                                  dynamic_shapes={"x": {0: torch.export.Dim("batch", min=1, max=4096)}},
                                  opset_version=max(opset, 18), dynamo=True, external_data=False, verbose=False)
            else:
                torch.onnx.export(net, (dummy,), str(tmp), input_names=[INPUT_NAME], output_names=[OUTPUT_NAME],
                                  dynamic_axes={INPUT_NAME: {0: "batch"}, OUTPUT_NAME: {0: "batch"}},
                                  opset_version=opset, dynamo=False, external_data=False)
        stamp_card(tmp, METADATA_KEY, cfg.to_dict())
    return path


class OnnxPoseNet:
    """An exported PoseNet run by onnxruntime: ``net(x)`` with x (B, C, H, W) float32 in [0, 1]
    returns (B, 9) float32, the same as ``PoseNet.forward``. ``config`` is the PoseNetConfig."""

    def __init__(self, path: str | Path, providers: list[str] | None = None, threads: int | None = None):
        self.session, card = open_session(path, METADATA_KEY, providers, threads,
                                          missing=" (export one with `cosy export`)")
        self.config = PoseNetConfig.from_dict(card)
        self.path = Path(path)

    @property
    def kind(self) -> str:
        return self.config.kind

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype=np.float32)
        w, h = self.config.crop_size
        if x.ndim != 4 or x.shape[1:] != (self.config.n_inputs, h, w):
            raise ValueError(f"OnnxPoseNet expects (B, {self.config.n_inputs}, {h}, {w}), got {x.shape}")
        return self.session.run([OUTPUT_NAME], {INPUT_NAME: x})[0]
