"""The detector network: a small anchor-free centre-heatmap detector ("Objects as Points",
Zhou et al. 2019, with TTFNet-style box regression), plain torch, fast on a CPU.

Network. Input (B, 3, H, W) float32 RGB in [0, 1] at the config's ``input_size`` (normalised
inside ``forward``, so the ONNX graph takes the same input). Backbone ``plain``: VGG-like 3x3
conv + BatchNorm + ReLU blocks, each stage starting with a stride-2 conv (strides 2, 4, 8, 16,
32); ``lite0``: EfficientNet-Lite0 (:mod:`cosy_cli.detection.efficientnet_lite`, started from its
ImageNet weights; its first stages may stay fixed in training, :class:`FrozenStages`). Then a
top-down feature pyramid (1x1 laterals, nearest upsampling, a 3x3 conv per level)
down to the output stride (default 8). Two heads on that map:

- ``heat``: (B, C, h, w) logits of the per-class centre heatmap (C = number of objects);
- ``box``: (B, 4, h, w) raw distances from the cell centre to the box's left, top, right and
  bottom edges: ``ltrb = exp(box) * stride`` input pixels.

Targets (:func:`encode_targets`, numpy). Per object, an elliptical Gaussian (sigma = 0.54 / 6
of the box width / height, TTFNet) centred on the box centre, on its class channel, max over
objects; the cell holding the centre is exactly 1. Box targets (ltrb in input pixels) at the
cells where the object's Gaussian >= ``BOX_REGION``, weighted by that Gaussian (smaller boxes
win where objects overlap). "Ignore" boxes (barely visible objects) mask the heatmap's negative
loss on their class channel inside the box.

Losses (:func:`detection_loss`): the penalty-reduced focal loss of CenterNet on the heatmap
(alpha 2, beta 4), normalised by the number of objects; GIoU loss of the decoded boxes,
weighted by the Gaussian, normalised by the weight sum.

Decoding (:func:`decode`, numpy, on the exported graph's outputs): the exported graph
(:class:`ExportWrapper`) already applies the sigmoid, keeps only the 3x3 local maxima of the
heatmap (max-pool peak extraction) and turns ``box`` into ltrb pixels; then top-K over classes
and cells, boxes in input pixels, scaled to the image by the caller.

Coordinates: box corners are continuous pixel coordinates of the network input; cell (i, j)
covers input pixels [j s, (j + 1) s) x [i s, (i + 1) s) and its centre is ((j + 0.5) s,
(i + 0.5) s).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
BACKBONES = ("plain", "lite0")
GAUSS_ALPHA = 0.54  # sigma = alpha * size / 6 (TTFNet)
BOX_REGION = 0.3  # box regression where the object's Gaussian >= this
HEAT_PRIOR = 0.01  # initial heatmap probability (bias of the last heat conv)
MAX_LOG_LTRB = 8.0  # clamp of the raw box output before exp (e^8 cells is far outside any image)


@dataclass
class DetectorConfig:
    """What is needed to rebuild the network (checkpoints, ONNX metadata).

    obj_ids: the class of channel k is object ``obj_ids[k]``. input_size: (width, height) px.
    stride: output stride (4, 8 or 16). backbone: ``plain`` or ``lite0``. channels: backbone stage
    widths (strides 2..32; lite0: its own); depth: extra 3x3 convs in the stages of stride 4..32
    (plain); fpn, head: widths of the pyramid and the heads.
    """

    obj_ids: list = field(default_factory=list)
    input_size: tuple = (320, 240)
    stride: int = 8
    channels: tuple = (16, 24, 48, 96, 160)
    depth: tuple = (0, 1, 2, 2)
    fpn: int = 48
    head: int = 48
    backbone: str = "plain"

    def __post_init__(self):
        self.obj_ids = [int(o) for o in self.obj_ids]
        self.input_size = tuple(int(v) for v in self.input_size)
        self.channels = tuple(int(v) for v in self.channels)
        self.depth = tuple(int(v) for v in self.depth)
        if self.stride not in (4, 8, 16):
            raise ValueError(f"stride must be 4, 8 or 16, got {self.stride}")
        if len(self.channels) != 5 or len(self.depth) != 4:
            raise ValueError("channels: 5 stage widths (strides 2..32); depth: 4 (strides 4..32)")
        if self.backbone not in BACKBONES:
            raise ValueError(f"backbone must be one of {', '.join(BACKBONES)}, got {self.backbone!r}")
        if self.backbone == "lite0":
            from .efficientnet_lite import WIDTHS

            if self.channels != WIDTHS:
                raise ValueError(f"backbone lite0: channels are {list(WIDTHS)}, got {list(self.channels)}")
        w, h = self.input_size
        if w % 16 or h % 16 or w % self.stride or h % self.stride:
            raise ValueError(f"input size must be a multiple of 16 px (and of the stride) per side, got {w} x {h}")
        if not self.obj_ids:
            raise ValueError("a detector needs at least one object id")

    @property
    def n_classes(self) -> int:
        return len(self.obj_ids)

    @property
    def output_size(self) -> tuple[int, int]:
        """(w, h) cells of the output maps."""
        return self.input_size[0] // self.stride, self.input_size[1] // self.stride

    def to_dict(self) -> dict:
        d = asdict(self)
        for k in ("input_size", "channels", "depth"):
            d[k] = list(d[k])
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "DetectorConfig":
        known = {k: d[k] for k in ("obj_ids", "input_size", "stride", "channels", "depth", "fpn", "head", "backbone")
                 if k in d}
        return cls(**known)


def _cbr(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


def backbone(channels, depth) -> tuple[nn.Sequential, nn.ModuleList]:
    """The detector's backbone: (stem (stride 2, ``channels[0]``), stages (each one stride-2 conv
    to ``channels[i + 1]`` and ``depth[i]`` more convs)). The box classifier builds the same
    modules under the same names, so it can start from a detector's weights."""
    stem = _cbr(3, channels[0], 2)
    stages, prev = [], channels[0]
    for c, d in zip(channels[1:], depth):
        stages.append(nn.Sequential(_cbr(prev, c, 2), *[_cbr(c, c) for _ in range(d)]))
        prev = c
    return stem, nn.ModuleList(stages)


class FrozenStages:
    """For a network whose backbone is ``stem`` + ``stages`` (:func:`backbone`) or ``stem`` +
    ``blocks`` (EfficientNet-Lite0): :meth:`freeze` keeps the first stages fixed in training (no
    gradient; their BatchNorms stay in eval mode, their statistics as they are, whatever
    ``train()`` is called with)."""

    frozen = 0

    def backbone_stages(self) -> list:
        """The backbone's modules grouped by output stride (2, 4, 8, 16, 32)."""
        if hasattr(self, "blocks"):
            from .efficientnet_lite import stage_groups

            return stage_groups(self.stem, self.blocks)
        return [[self.stem]] + [[st] for st in self.stages]

    def freeze(self, n_stages: int) -> int:
        """Freeze the first ``n_stages`` backbone stages; returns the number of their parameters."""
        self.frozen = int(n_stages)
        n = 0
        for group in self.backbone_stages()[:self.frozen]:
            for m in group:
                for p in m.parameters():
                    p.requires_grad_(False)
                    n += p.numel()
        self.train(self.training)
        return n

    def train(self, mode: bool = True):
        super().train(mode)
        if self.frozen:
            for group in self.backbone_stages()[:self.frozen]:
                for m in group:
                    m.eval()
        return self


class CenterNet(FrozenStages, nn.Module):
    """The detector: ``forward(x)`` with x (B, 3, H, W) in [0, 1] -> (heat logits (B, C, h, w),
    box raw (B, 4, h, w)); see the module docstring."""

    def __init__(self, config: DetectorConfig):
        super().__init__()
        self.config = config
        ch = config.channels
        mean, std = IMAGENET_MEAN, IMAGENET_STD
        if config.backbone == "lite0":
            from . import efficientnet_lite

            self.stem, self.blocks = efficientnet_lite.build()
            mean, std = efficientnet_lite.MEAN, efficientnet_lite.STD
        else:
            self.stem, self.stages = backbone(ch, config.depth)
        self.first_level = {4: 0, 8: 1, 16: 2}[config.stride]  # index in stages of the output stride
        used = ch[1 + self.first_level:]
        self.laterals = nn.ModuleList([nn.Conv2d(c, config.fpn, 1) for c in used])
        self.smooth = nn.ModuleList([_cbr(config.fpn, config.fpn) for _ in used[:-1]])
        self.heat = nn.Sequential(_cbr(config.fpn, config.head), nn.Conv2d(config.head, config.n_classes, 1))
        self.box = nn.Sequential(_cbr(config.fpn, config.head), nn.Conv2d(config.head, 4, 1))
        self.register_buffer("mean", torch.tensor(mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(std).view(1, 3, 1, 1), persistent=False)
        self._init()

    def _init(self):
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
        last_heat, last_box = self.heat[-1], self.box[-1]
        nn.init.normal_(last_heat.weight, std=0.01)
        nn.init.constant_(last_heat.bias, -math.log((1 - HEAT_PRIOR) / HEAT_PRIOR))
        nn.init.normal_(last_box.weight, std=0.01)
        nn.init.constant_(last_box.bias, math.log(2.0))  # ltrb = 2 cells

    def forward(self, x: torch.Tensor):
        x = (x - self.mean) / self.std
        if self.config.backbone == "lite0":
            from .efficientnet_lite import maps

            feats = maps(self.stem, self.blocks, x)[1:]
        else:
            x = self.stem(x)
            feats = []
            for stage in self.stages:
                x = stage(x)
                feats.append(x)
        feats = feats[self.first_level:]
        y = self.laterals[-1](feats[-1])
        for i in range(len(feats) - 2, -1, -1):
            y = F.interpolate(y, size=feats[i].shape[-2:], mode="nearest") + self.laterals[i](feats[i])
            y = self.smooth[i](y)
        return self.heat(y), self.box(y)

    def checkpoint(self) -> dict:
        return {"config": self.config.to_dict(), "state_dict": self.state_dict()}

    @classmethod
    def from_checkpoint(cls, ck: dict) -> "CenterNet":
        net = cls(DetectorConfig.from_dict(ck["config"]))
        net.load_state_dict(ck["state_dict"])
        return net


class ExportWrapper(nn.Module):
    """What the ONNX graph computes: input (B, 3, H, W) [0, 1] -> ``peaks`` (B, C, h, w): the
    sigmoid heatmap where a cell is a 3x3 local maximum, 0 elsewhere; ``ltrb`` (B, 4, h, w):
    distances (input px) from the cell centre to the box edges."""

    def __init__(self, net: CenterNet):
        super().__init__()
        self.net = net

    def forward(self, x):
        heat, box = self.net(x)
        return peaks_and_ltrb(heat, box, self.net.config.stride)


def peaks_and_ltrb(heat_logits: torch.Tensor, box_raw: torch.Tensor, stride: int):
    heat = torch.sigmoid(heat_logits)
    peak = F.max_pool2d(heat, 3, stride=1, padding=1)
    peaks = heat * (peak == heat).to(heat.dtype)
    ltrb = torch.exp(torch.clamp(box_raw, max=MAX_LOG_LTRB)) * float(stride)
    return peaks, ltrb


# ---------------------------------------------------------------------------------- targets
def encode_targets(boxes_xyxy: np.ndarray, labels: np.ndarray, config: DetectorConfig,
                   ignore_xyxy: np.ndarray | None = None, ignore_labels: np.ndarray | None = None) -> dict:
    """Training targets of one image from its boxes (N, 4) [x1, y1, x2, y2] in input pixels and
    labels (N,) (class indices 0..C-1).

    Returns heat (C, h, w) float32 in [0, 1]; ignore (C, h, w) float32 (1: no negative loss);
    ltrb (4, h, w) float32 input px; weight (h, w) float32 (the box regression weight);
    n_obj (int)."""
    C = config.n_classes
    w, h = config.output_size
    s = float(config.stride)
    heat = np.zeros((C, h, w), np.float32)
    ignore = np.zeros((C, h, w), np.float32)
    ltrb = np.zeros((4, h, w), np.float32)
    weight = np.zeros((h, w), np.float32)
    area_at = np.full((h, w), np.inf, np.float32)  # box area owning each regression cell
    boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    labels = np.asarray(labels, dtype=np.int64).reshape(-1)
    xs = (np.arange(w) + 0.5) * s
    ys = (np.arange(h) + 0.5) * s
    n_obj = 0
    for (x1, y1, x2, y2), c in zip(boxes, labels):
        bw, bh = x2 - x1, y2 - y1
        if bw <= 0 or bh <= 0:
            continue
        cx, cy = (x1 + x2) / 2, (y1 + y2) / 2
        j, i = int(np.clip(cx // s, 0, w - 1)), int(np.clip(cy // s, 0, h - 1))
        sx, sy = max(GAUSS_ALPHA * bw / 6 / s, 0.3), max(GAUSS_ALPHA * bh / 6 / s, 0.3)  # cells
        gx = np.exp(-0.5 * ((np.arange(w) - j) / sx) ** 2)
        gy = np.exp(-0.5 * ((np.arange(h) - i) / sy) ** 2)
        g = (gy[:, None] * gx[None]).astype(np.float32)  # peak exactly 1 at (i, j)
        np.maximum(heat[c], g, out=heat[c])
        n_obj += 1
        region = (g >= BOX_REGION) & (bw * bh < area_at)
        region[i, j] = region[i, j] or bw * bh <= area_at[i, j]
        if region.any():
            ii, jj = np.nonzero(region)
            ltrb[0, ii, jj] = xs[jj] - x1
            ltrb[1, ii, jj] = ys[ii] - y1
            ltrb[2, ii, jj] = x2 - xs[jj]
            ltrb[3, ii, jj] = y2 - ys[ii]
            weight[ii, jj] = g[ii, jj]
            area_at[ii, jj] = bw * bh
    if ignore_xyxy is not None and len(ignore_xyxy):
        for (x1, y1, x2, y2), c in zip(np.asarray(ignore_xyxy, np.float64).reshape(-1, 4), ignore_labels):
            j0, j1 = int(np.clip(x1 // s, 0, w)), int(np.clip(np.ceil(x2 / s), 0, w))
            i0, i1 = int(np.clip(y1 // s, 0, h)), int(np.clip(np.ceil(y2 / s), 0, h))
            ignore[int(c), i0:i1, j0:j1] = 1.0
        ignore[heat > 0.05] = 0.0  # a real object there: its Gaussian keeps its loss
    return {"heat": heat, "ignore": ignore, "ltrb": ltrb, "weight": weight, "n_obj": n_obj}


def stack_targets(targets: list[dict]) -> dict:
    """Batch of :func:`encode_targets` dicts -> dict of stacked arrays."""
    return {k: np.stack([t[k] for t in targets]) if k != "n_obj" else np.array([t[k] for t in targets])
            for k in targets[0]}


# ---------------------------------------------------------------------------------- losses
def focal_loss(heat_logits: torch.Tensor, heat_gt: torch.Tensor, ignore: torch.Tensor | None = None,
               alpha: float = 2.0, beta: float = 4.0) -> torch.Tensor:
    """CenterNet's penalty-reduced pixel-wise focal loss, summed, divided by the number of
    positives (cells where the target is 1; at least 1)."""
    logp = F.logsigmoid(heat_logits)
    log1mp = F.logsigmoid(-heat_logits)
    p = torch.exp(logp)
    pos = (heat_gt >= 1.0 - 1e-4).to(p.dtype)
    pos_loss = -(pos * (1 - p) ** alpha * logp).sum()
    neg_w = (1 - pos) * (1 - heat_gt) ** beta
    if ignore is not None:
        neg_w = neg_w * (1 - ignore)
    neg_loss = -(neg_w * p ** alpha * log1mp).sum()
    return (pos_loss + neg_loss) / pos.sum().clamp(min=1.0)


def giou_loss(box_raw: torch.Tensor, ltrb_gt: torch.Tensor, weight: torch.Tensor, stride: int) -> torch.Tensor:
    """Weighted mean of 1 - GIoU between the predicted and target boxes at each cell (both
    given as ltrb about the cell centre)."""
    pred = torch.exp(torch.clamp(box_raw, max=MAX_LOG_LTRB)) * float(stride)  # (B, 4, h, w)
    m = weight > 0
    if not bool(m.any()):
        return box_raw.sum() * 0.0
    p = pred.permute(0, 2, 3, 1)[m]  # (n, 4)
    g = ltrb_gt.permute(0, 2, 3, 1)[m]
    w = weight[m]
    pa = (p[:, 0] + p[:, 2]) * (p[:, 1] + p[:, 3])
    ga = (g[:, 0] + g[:, 2]) * (g[:, 1] + g[:, 3])
    iw = torch.minimum(p[:, 0], g[:, 0]) + torch.minimum(p[:, 2], g[:, 2])
    ih = torch.minimum(p[:, 1], g[:, 1]) + torch.minimum(p[:, 3], g[:, 3])
    inter = iw.clamp(min=0) * ih.clamp(min=0)
    union = pa + ga - inter
    iou = inter / union.clamp(min=1e-6)
    cw = torch.maximum(p[:, 0], g[:, 0]) + torch.maximum(p[:, 2], g[:, 2])
    chh = torch.maximum(p[:, 1], g[:, 1]) + torch.maximum(p[:, 3], g[:, 3])
    enclose = (cw * chh).clamp(min=1e-6)
    giou = iou - (enclose - union) / enclose
    return ((1 - giou) * w).sum() / w.sum().clamp(min=1e-6)


def detection_loss(heat_logits, box_raw, targets: dict, stride: int, box_weight: float = 2.0) -> dict:
    """{"total", "heat", "box"} scalar tensors of a batch; ``targets`` holds torch tensors of
    :func:`stack_targets`."""
    lh = focal_loss(heat_logits, targets["heat"], targets.get("ignore"))
    lb = giou_loss(box_raw, targets["ltrb"], targets["weight"], stride)
    return {"total": lh + box_weight * lb, "heat": lh, "box": lb}


# ---------------------------------------------------------------------------------- decoding
def decode(peaks: np.ndarray, ltrb: np.ndarray, stride: int, k: int = 100, min_score: float = 0.0):
    """Top-k detections of one image from the export graph's outputs: peaks (C, h, w) (sigmoid
    scores at 3x3 local maxima, 0 elsewhere) and ltrb (4, h, w) input px.

    Returns boxes (n, 4) [x1, y1, x2, y2] input px (float64), scores (n,), class indices (n,)
    int64, sorted by decreasing score, scores >= min_score, n <= k."""
    C, h, w = peaks.shape
    flat = peaks.reshape(-1)
    k = min(int(k), flat.size)
    if k <= 0:
        return np.zeros((0, 4)), np.zeros(0), np.zeros(0, np.int64)
    top = np.argpartition(-flat, k - 1)[:k] if k < flat.size else np.arange(flat.size)
    top = top[np.argsort(-flat[top], kind="stable")]
    top = top[flat[top] >= max(min_score, 1e-12)]
    cls, rem = np.divmod(top, h * w)
    i, j = np.divmod(rem, w)
    cx, cy = (j + 0.5) * stride, (i + 0.5) * stride
    d = ltrb[:, i, j].astype(np.float64)  # (4, n)
    boxes = np.stack([cx - d[0], cy - d[1], cx + d[2], cy + d[3]], axis=1)
    return boxes, flat[top].astype(np.float64), cls.astype(np.int64)


def decode_targets(heat: np.ndarray, ltrb: np.ndarray, stride: int, k: int = 100):
    """Boxes (xyxy), scores, classes recovered from encoded targets (heat (C, h, w), ltrb (4, h, w)):
    the peaks where the target heat is 1. For tests of the encoding."""
    peaks = np.where(heat >= 1.0 - 1e-6, heat, 0.0)
    return decode(peaks, ltrb, stride, k=k, min_score=0.5)


__all__ = ["DetectorConfig", "CenterNet", "ExportWrapper", "peaks_and_ltrb", "encode_targets", "stack_targets",
           "focal_loss", "giou_loss", "detection_loss", "decode", "decode_targets"]
