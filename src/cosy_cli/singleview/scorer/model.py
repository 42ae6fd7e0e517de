"""The scorer network: a small CNN over the observed crop stacked with the render of a hypothesis.

Input (:func:`~cosy_cli.singleview.scorer.features.assemble`): ``image`` (n, 9, S, S) float32 (the
observed crop's RGB - 0.5, the render's RGB after the verifier's brightness gain - 0.5, the
render's mask, the detection box's mask, the crop's not-background probability) and ``terms``
(n, T) float32 (the training-free score terms, the template score, whether the mesh has colours,
the training-free total). Early fusion (the two images stacked at the first layer) lets the first
filters compare image and render pixel by pixel, where misalignment shows.

Layers: four 3x3 stride-2 convolutions (widths ``widths``, BatchNorm, ReLU; 64 -> 4 px), global
mean and max pooling, concatenated with the terms, then an MLP to one logit. About 7 M
multiply-adds per hypothesis at S = 64 (448 hypotheses, 7 detections x 64, in about 0.1 s on two
CPU cores with onnxruntime). Output: the logit of the hypothesis' expected AR contribution
(:func:`cosy_cli.training.scorer_target.ar_contribution`); the verifier uses its sigmoid.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

METADATA_KEY = "cosy_scorer"
IMAGE_CHANNELS = 9
TERM_NAMES = ("orient", "colour", "region", "box", "prior", "coloured", "total", "area_ratio")


ARCHS = ("plain", "lite0")


class ScorerNet(nn.Module):
    def __init__(self, widths=(24, 48, 64, 96), hidden: int = 64, n_terms: int = len(TERM_NAMES)):
        super().__init__()
        layers, c = [], IMAGE_CHANNELS
        for w in widths:
            layers += [nn.Conv2d(c, w, 3, stride=2, padding=1, bias=False), nn.BatchNorm2d(w), nn.ReLU(inplace=True)]
            c = w
        self.features = nn.Sequential(*layers)
        self.head = nn.Sequential(nn.Linear(2 * c + n_terms, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, 1))
        self.widths = tuple(int(w) for w in widths)
        self.hidden = int(hidden)
        self.n_terms = int(n_terms)

    arch = "plain"

    def forward(self, image: torch.Tensor, terms: torch.Tensor) -> torch.Tensor:
        f = self.features(image)
        pooled = torch.cat([f.mean((2, 3)), f.amax((2, 3)), terms], 1)
        return self.head(pooled)[:, 0]


class Lite0ScorerNet(nn.Module):
    """The scorer on ImageNet features: the same inputs as :class:`ScorerNet`, compared late.

    The observed crop and the render pasted onto it (the render where its mask is, the crop
    elsewhere: where the hypothesis is right the two images differ only in texture and light) go
    through the first four stages of EfficientNet-Lite0 as ImageNet trained them, frozen (strides
    8 and 16: 40 and 112 channels; at S = 64 px, 8 x 8 and 4 x 4 maps). Per stride the head sees
    both maps and their absolute difference; the masks (render, box, not-background) join at
    stride 8. Two convolutions per stride, global mean and max pooling, the terms, an MLP to one
    logit. Features from photographs, not from renders alone, are what should carry over to real
    images."""

    arch = "lite0"

    def __init__(self, widths=(64, 128), hidden: int = 64, n_terms: int = len(TERM_NAMES), pretrained: bool = True):
        super().__init__()
        from ...detection import efficientnet_lite as el

        self.stage8, end = el.STAGE_ENDS[2], el.STAGE_ENDS[3] + 1  # the last blocks of strides 8 and 16
        stem, blocks = el.build()
        self.stem, self.blocks = stem, blocks[:end]
        if pretrained:
            own = {k: v for k, v in el.imagenet_state().items()
                   if k.startswith("stem.") or int(k.split(".")[1]) < end}
            self.load_state_dict(own, strict=False)
        for p in list(self.stem.parameters()) + list(self.blocks.parameters()):
            p.requires_grad_(False)
        w8, w16 = int(widths[0]), int(widths[1])
        c8, c16 = el.WIDTHS[2], el.WIDTHS[3]

        def cbr(cin, cout, s):
            return [nn.Conv2d(cin, cout, 3, stride=s, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True)]

        self.head8 = nn.Sequential(*cbr(3 * c8 + 3, w8, 1), *cbr(w8, w8, 2))
        self.head16 = nn.Sequential(*cbr(3 * c16 + w8, w16, 1), *cbr(w16, w16, 2))
        self.head = nn.Sequential(nn.Linear(2 * w16 + n_terms, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, 1))
        self.widths = (w8, w16)
        self.hidden = int(hidden)
        self.n_terms = int(n_terms)

    def train(self, mode: bool = True):
        super().train(mode)
        self.stem.eval()
        self.blocks.eval()  # frozen: the ImageNet BatchNorm statistics stay
        return self

    def trunk(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.stem(x)
        for i, b in enumerate(self.blocks):
            x = b(x)
            if i == self.stage8:
                f8 = x
        return f8, x

    @staticmethod
    def split(image: torch.Tensor) -> tuple:
        """(observed crop, render pasted onto it, masks pooled to stride 8) of the 9-channel ``image``;
        the images hold x - 0.5 for x in [0, 1]."""
        obs, ren, mask = image[:, 0:3], image[:, 3:6], image[:, 6:7]
        return obs, mask * ren + (1.0 - mask) * obs, F.avg_pool2d(image[:, 6:9], 8)

    def maps(self, image: torch.Tensor, first: torch.Tensor | None = None, ridx: torch.Tensor | None = None) -> tuple:
        """The frozen trunk's maps of the 9-channel ``image`` (n, 9, S, S): (observed stride 8,
        pasted stride 8, observed stride 16, pasted stride 16, the masks pooled to stride 8).
        ``first`` (U,) one hypothesis of each of the U observations and ``ridx`` (n,) the observation
        of each hypothesis: the observed crop goes through the trunk once (default: once per hypothesis)."""
        obs, pasted, m8 = self.split(image)
        with torch.no_grad():  # EfficientNet-Lite0 takes (x - 0.5) / 0.5
            if first is None:
                n = image.shape[0]
                f8, f16 = self.trunk(2.0 * torch.cat([obs, pasted], 0))
                return f8[:n], f8[n:], f16[:n], f16[n:], m8
            o8, o16 = self.trunk(2.0 * obs[first])
            p8, p16 = self.trunk(2.0 * pasted)
        return o8[ridx], p8, o16[ridx], p16, m8

    def head_logit(self, o8, p8, o16, p16, m8, terms) -> torch.Tensor:
        """The trainable part: the logit from the trunk's maps (:meth:`maps`) and the terms."""
        g8 = self.head8(torch.cat([o8, p8, (o8 - p8).abs(), m8], 1))
        g16 = self.head16(torch.cat([o16, p16, (o16 - p16).abs(), g8], 1))
        pooled = torch.cat([g16.mean((2, 3)), g16.amax((2, 3)), terms], 1)
        return self.head(pooled)[:, 0]

    def forward(self, image: torch.Tensor, terms: torch.Tensor, first: torch.Tensor | None = None,
                ridx: torch.Tensor | None = None) -> torch.Tensor:
        return self.head_logit(*self.maps(image, first, ridx), terms)


def build(arch: str = "plain", widths=None, hidden: int = 64, pretrained: bool = True) -> nn.Module:
    """The scorer network of ``arch`` (:data:`ARCHS`); ``widths`` None: the arch's defaults."""
    if arch == "plain":
        return ScorerNet(widths or (24, 48, 64, 96), hidden)
    if arch == "lite0":
        return Lite0ScorerNet(widths or (64, 128), hidden, pretrained=pretrained)
    raise ValueError(f"scorer arch: expected one of {', '.join(ARCHS)}, got {arch!r}")


def export_onnx(net: nn.Module, path, card: dict) -> None:
    """Write ``net`` (eval mode, a copy) atomically as ONNX with inputs ``image`` (n, 9, S, S),
    ``terms`` (n, T) and output ``logit`` (n,), the batch dimension dynamic; ``card`` (with at
    least "crop" = S and "margin", the verification crop it was trained on) goes in the metadata
    under :data:`METADATA_KEY`. Arch lite0 also takes ``first`` (U,) and ``ridx`` (n,) int64
    (:meth:`Lite0ScorerNet.maps`: each observed crop through the trunk once)."""
    import copy
    import warnings

    from ...io.atomic import atomic_path
    from ...onnxrt import stamp_card

    net = copy.deepcopy(net).cpu().float().eval()
    S = int(card["crop"])
    image = torch.zeros(2, IMAGE_CHANNELS, S, S)
    terms = torch.zeros(2, net.n_terms)
    card = dict(card, kind="scorer", arch=net.arch, widths=list(net.widths), hidden=net.hidden, terms=list(TERM_NAMES))
    args, names, axes = (image, terms), ["image", "terms"], {"image": {0: "n"}, "terms": {0: "n"}, "logit": {0: "n"}}
    if net.arch == "lite0":
        args += (torch.zeros(1, dtype=torch.int64), torch.zeros(2, dtype=torch.int64))
        names += ["first", "ridx"]
        axes.update(first={0: "u"}, ridx={0: "n"})
    with atomic_path(path) as tmp:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(net, args, str(tmp), input_names=names, output_names=["logit"], dynamic_axes=axes,
                              opset_version=17, dynamo=False, external_data=False)
        stamp_card(tmp, METADATA_KEY, card)


def quantize_trunk(path, feeds) -> int:
    """Rewrite the lite0 scorer at ``path`` (an :func:`export_onnx` file) with its frozen trunk's
    convolutions in int8 (:func:`cosy_cli.onnxrt.quantize_convs`: weights per output channel,
    activations calibrated over ``feeds``, a list of input dicts, e.g. rendered training
    hypotheses). The head stays in float32. The card gains ``"precision": "int8"``. Written
    atomically; returns the number of convolutions quantized. The same inputs give the same file
    (deterministic calibration)."""
    import json

    import onnx

    from ...detection.efficientnet_lite import ONNX_NODE_PARTS
    from ...onnxrt import quantize_convs

    model = onnx.load(str(path))
    meta = {p.key: p.value for p in model.metadata_props}
    if METADATA_KEY not in meta:
        raise ValueError(f"{path}: not a scorer exported by export_onnx (no '{METADATA_KEY}' metadata)")
    card = json.loads(meta[METADATA_KEY])
    if card.get("arch") != "lite0":
        raise ValueError(f"{path}: only the lite0 scorer has a frozen trunk to quantize (arch {card.get('arch')!r})")
    if card.get("precision") == "int8":
        raise ValueError(f"{path}: already quantized")
    feeds = list(feeds)
    if not feeds:
        raise ValueError("quantize_trunk: no calibration inputs")
    return quantize_convs(path, feeds, ONNX_NODE_PARTS, METADATA_KEY)  # the trunk: its frozen Lite0 layers
