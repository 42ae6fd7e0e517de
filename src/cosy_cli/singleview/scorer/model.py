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
from torch import nn

METADATA_KEY = "cosy_scorer"
IMAGE_CHANNELS = 9
TERM_NAMES = ("orient", "colour", "region", "box", "prior", "coloured", "total", "area_ratio")


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

    def forward(self, image: torch.Tensor, terms: torch.Tensor) -> torch.Tensor:
        f = self.features(image)
        pooled = torch.cat([f.mean((2, 3)), f.amax((2, 3)), terms], 1)
        return self.head(pooled)[:, 0]


def export_onnx(net: ScorerNet, path, card: dict) -> None:
    """Write ``net`` (eval mode, a copy) atomically as ONNX with inputs ``image`` (n, 9, S, S),
    ``terms`` (n, T) and output ``logit`` (n,), the batch dimension dynamic; ``card`` (with at
    least "crop" = S and "margin", the verification crop it was trained on) goes in the metadata
    under :data:`METADATA_KEY`."""
    import copy
    import warnings

    from ...io.atomic import atomic_path
    from ...onnxrt import stamp_card

    net = copy.deepcopy(net).cpu().float().eval()
    S = int(card["crop"])
    image = torch.zeros(2, IMAGE_CHANNELS, S, S)
    terms = torch.zeros(2, net.n_terms)
    card = dict(card, kind="scorer", widths=list(net.widths), hidden=net.hidden, terms=list(TERM_NAMES))
    with atomic_path(path) as tmp:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(net, (image, terms), str(tmp), input_names=["image", "terms"], output_names=["logit"],
                              dynamic_axes={"image": {0: "n"}, "terms": {0: "n"}, "logit": {0: "n"}},
                              opset_version=17, dynamo=False, external_data=False)
        stamp_card(tmp, METADATA_KEY, card)
