"""PoseNet: the render-and-compare network of CosyPose (paper Appendix A, "Network architecture").

An EfficientNet feature extractor (``efficientnet_pytorch``, randomly initialised: the paper
trains from scratch too), global average pooling and one linear layer with 9 outputs
(:mod:`~cosy_cli.singleview.networks.pose_update` layout: 6D rotation, v_x, v_y px, v_z). The coarse and
the refiner networks are this same class with different ``kind`` and weights.

Input: (B, C, H, W) float32 in [0, 1], H x W the crop size (height, width) px, channels:
observed crop RGB (3), rendered crop RGB (3), optionally the rendered object mask (1). The
network normalises inside ``forward`` (so exported ONNX models take the same [0, 1] input):
RGB channels with the ImageNet mean/std, the mask to [-1, 1]. :func:`prepare_inputs` builds the
input from uint8 crops.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn

from .pose_update import IDENTITY_OUTPUT, N_OUTPUTS

KINDS = ("coarse", "refiner")
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass
class PoseNetConfig:
    """What is needed to rebuild a PoseNet (stored in checkpoints and ONNX metadata).

    crop_size: (width, height) px of the network input.
    xy_scale_px, z_scale: output scales (see :class:`PoseNet`); xy_scale_px defaults to
    crop width / 16 px (8 px for 128-px crops).
    """

    kind: str = "refiner"
    backbone: str = "efficientnet-b0"
    n_inputs: int = 6
    crop_size: tuple[int, int] = (128, 96)
    xy_scale_px: float | None = None
    z_scale: float = 0.1

    def __post_init__(self):
        if self.xy_scale_px is None:
            self.xy_scale_px = self.crop_size[0] / 16.0

    def to_dict(self) -> dict:
        d = asdict(self)
        d["crop_size"] = list(self.crop_size)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "PoseNetConfig":
        return cls(kind=str(d["kind"]), backbone=str(d["backbone"]), n_inputs=int(d["n_inputs"]),
                   crop_size=tuple(int(v) for v in d["crop_size"]), xy_scale_px=d.get("xy_scale_px"),
                   z_scale=float(d.get("z_scale", 0.1)))


class PoseNet(nn.Module):
    """EfficientNet + average pooling + Linear(features, 9).

    kind: "coarse" or "refiner"; backbone: an ``efficientnet_pytorch`` name (efficientnet-b0 ..
    b7); n_inputs: 6 (observed + rendered RGB) or 7 (+ rendered mask); crop_size (width, height)
    px.

    The linear head's raw outputs r (9) are mapped to the update as
    ``IDENTITY_OUTPUT + r * (1, 1, 1, 1, 1, 1, xy_scale_px, xy_scale_px, z_scale)``: the same
    function class as the paper's plain linear layer, rescaled so that one unit of r is a typical
    refinement step (a few px in the crop, 10 % of depth) rather than 1 px and 100 % of depth,
    which keeps Adam's equal-sized steps from blowing up the depth. The head starts at zero, so an
    untrained network outputs exactly the identity update (the pose is left unchanged).
    """

    def __init__(self, kind: str = "refiner", backbone: str = "efficientnet-b0", n_inputs: int = 6,
                 crop_size: tuple[int, int] = (128, 96), xy_scale_px: float | None = None, z_scale: float = 0.1):
        super().__init__()
        from efficientnet_pytorch import EfficientNet

        if kind not in KINDS:
            raise ValueError(f"PoseNet kind must be one of {KINDS}, got {kind!r}")
        if n_inputs not in (6, 7):
            raise ValueError(f"PoseNet n_inputs must be 6 (two RGB crops) or 7 (+ mask), got {n_inputs}")
        self.config = PoseNetConfig(kind, backbone, int(n_inputs), (int(crop_size[0]), int(crop_size[1])),
                                    xy_scale_px, float(z_scale))
        w, h = self.config.crop_size
        self.backbone = EfficientNet.from_name(backbone, in_channels=n_inputs, image_size=[h, w], include_top=False)
        _init_backbone(self.backbone)
        # Plain Swish: traceable for ONNX and, measured on the 2-core CPU, faster to train than the
        # library's default memory-efficient Swish (1.2 vs 1.9 s per B0 step at batch 32, 128x96).
        self.backbone.set_swish(memory_efficient=False)
        n_feat = self.backbone._conv_head.out_channels
        self.pool = nn.AdaptiveAvgPool2d(1)
        self.head = nn.Linear(n_feat, N_OUTPUTS)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        c = self.config
        self.register_buffer("out_offset", torch.tensor(IDENTITY_OUTPUT).view(1, -1), persistent=False)
        self.register_buffer("out_scale", torch.tensor([1.0] * 6 + [c.xy_scale_px] * 2 + [c.z_scale]).view(1, -1),
                             persistent=False)
        mean = list(IMAGENET_MEAN) * 2 + [0.5] * (n_inputs - 6)
        std = list(IMAGENET_STD) * 2 + [0.5] * (n_inputs - 6)
        self.register_buffer("mean", torch.tensor(mean).view(1, -1, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(std).view(1, -1, 1, 1), persistent=False)

    @property
    def kind(self) -> str:
        return self.config.kind

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, n_inputs, H, W) in [0, 1] -> (B, 9) update (6D rotation, v_x, v_y px, v_z)."""
        x = (x - self.mean) / self.std
        f = self.pool(self.backbone.extract_features(x)).flatten(1)
        return self.out_offset + self.head(f) * self.out_scale

    def set_export_mode(self, export: bool = True) -> None:
        """Plain (traceable) Swish for ONNX export (the default); ``False`` switches to the
        memory-efficient Swish (less activation memory on GPUs, not traceable)."""
        self.backbone.set_swish(memory_efficient=not export)

    def checkpoint(self) -> dict:
        """{"config": ..., "state_dict": ...}: everything :meth:`from_checkpoint` needs."""
        return {"config": self.config.to_dict(), "state_dict": self.state_dict()}

    @classmethod
    def from_checkpoint(cls, ckpt: dict) -> "PoseNet":
        cfg = PoseNetConfig.from_dict(ckpt["config"])
        net = cls(cfg.kind, cfg.backbone, cfg.n_inputs, cfg.crop_size, cfg.xy_scale_px, cfg.z_scale)
        net.load_state_dict(ckpt["state_dict"])
        return net


BATCHNORM_MOMENTUM = 0.1  # torch's default; efficientnet_pytorch sets 0.01


def _init_backbone(module: nn.Module) -> None:
    """He (fan-in) initialisation of convolutions, unit BatchNorm. (In eval mode an untrained
    network still has near-zero features, as BatchNorm's running statistics are not yet learned;
    train-mode forward passes set them.)

    BatchNorm's running statistics follow the batches with momentum :data:`BATCHNORM_MOMENTUM`
    (0.1) instead of efficientnet_pytorch's 0.01: with 0.01 they lag the weights by ~100 steps,
    and a network trained for a few hundred steps is far worse in eval mode than in train mode
    (overfitting 32 fixed refiner samples, 300 steps at lr 1e-3: pose error 65 -> 5.7 mm in train
    mode, 34 mm in eval mode; with 0.1, 16 samples, 200 steps at 2e-3: 85 -> 9.3 mm in eval mode). Only training sees the
    momentum; loaded weights (CosyPose's included) are unchanged."""
    for m in module.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.kaiming_normal_(m.weight, mode="fan_in")
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)
            m.momentum = BATCHNORM_MOMENTUM


def prepare_inputs(observed: np.ndarray, rendered: np.ndarray, masks: np.ndarray | None = None) -> np.ndarray:
    """Network input (B, C, H, W) float32 in [0, 1] from uint8 crops.

    observed, rendered: (B, H, W, 3) uint8 RGB; masks: optional (B, H, W) bool/uint8 (nonzero =
    object) for 7-channel networks.
    """
    parts = [np.asarray(observed, dtype=np.float32) / 255.0, np.asarray(rendered, dtype=np.float32) / 255.0]
    if masks is not None:
        parts.append((np.asarray(masks) > 0).astype(np.float32)[..., None])
    x = np.concatenate(parts, axis=-1)
    return np.ascontiguousarray(x.transpose(0, 3, 1, 2))
