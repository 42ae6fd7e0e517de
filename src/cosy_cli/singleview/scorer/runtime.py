"""An exported scorer run by onnxruntime (``cosy estimate --scorer FILE``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import CosyError
from ...onnxrt import open_session
from .model import METADATA_KEY, TERM_NAMES


class OnnxScorer:
    """``scorer(image, terms)`` -> (n,) float64 in (0, 1): the predicted AR contribution of each
    hypothesis (the sigmoid of the network's logit), in chunks of ``batch`` hypotheses.
    Attributes: ``card`` (what it was trained on: objects, crop, margin, ...), ``path``."""

    def __init__(self, path: str | Path, providers="cpu", batch: int = 512):
        self.path = Path(path)
        self.session, self.card = open_session(self.path, METADATA_KEY, providers,
                                               missing=" (train one with `cosy train scorer`)",
                                               not_ours="not a scorer exported by `cosy train scorer`")
        if self.card.get("kind") != "scorer" or list(self.card.get("terms", [])) != list(TERM_NAMES):
            raise CosyError("this scorer was exported by another version of cosy (its inputs differ): train it "
                            "again with `cosy train scorer`", path=self.path)
        self.crop = int(self.card["crop"])
        self.margin = float(self.card["margin"])
        self.obj_ids = [int(o) for o in self.card.get("obj_ids", [])]
        self.batch = int(batch)
        self.arch = str(self.card.get("arch", "plain"))

    def unseen(self, obj_ids) -> list[int]:
        """The objects of ``obj_ids`` that the scorer was not trained on (it compares an image with a
        render, so it still runs on them, but its figures were measured on its own objects)."""
        return sorted(set(int(o) for o in obj_ids) - set(self.obj_ids))

    def __call__(self, image: np.ndarray, terms: np.ndarray, ridx: np.ndarray | None = None) -> np.ndarray:
        """``ridx`` (n,): the observation of each hypothesis (those of one share its observed crop's
        channels), so that a lite0 scorer runs each observed crop through its trunk once."""
        n = len(image)
        out = np.empty(n)
        for i in range(0, n, self.batch):
            feed = {"image": np.ascontiguousarray(image[i:i + self.batch], np.float32),
                    "terms": np.ascontiguousarray(terms[i:i + self.batch], np.float32)}
            if self.arch == "lite0":
                r = np.arange(len(feed["image"])) if ridx is None else np.asarray(ridx)[i:i + self.batch]
                _, first, inv = np.unique(r, return_index=True, return_inverse=True)
                feed.update(first=first.astype(np.int64), ridx=inv.reshape(-1).astype(np.int64))
            logit = self.session.run(None, feed)[0]
            out[i:i + self.batch] = 1.0 / (1.0 + np.exp(-np.asarray(logit, np.float64).reshape(-1)))
        return out
