"""The scorer's inputs, built from what :meth:`~cosy_cli.singleview.training_free.verify.Verifier.score`
has already computed (no extra render), and the same function for training samples.

Per hypothesis: ``image`` (9, S, S) float32: the observed crop's RGB - 0.5; the render's RGB times
the verifier's brightness gain of that hypothesis, clipped to [0, 1], - 0.5; the render's mask;
the detection box's mask in the crop; the crop's not-background probability (the verifier's colour
model). ``terms`` (T,) float32 in the order of :data:`~cosy_cli.singleview.scorer.model.TERM_NAMES`:
the oriented-gradient, colour, region and box terms, the template score (0 without one), 1 if the
mesh has colours, the training-free total, and the silhouette's area over the detection box's area
(clipped to 4).
"""

from __future__ import annotations

import numpy as np


def assemble(obs_rgb: np.ndarray, in_box: np.ndarray, not_bg: np.ndarray, ridx: np.ndarray, rgba: np.ndarray,
             gain: np.ndarray) -> np.ndarray:
    """(n, 9, S, S) float32 network images of n hypotheses: ``obs_rgb`` (U, S, S, 3) float 0..1,
    ``in_box`` (U, S, S) bool, ``not_bg`` (U, S, S) float of the U observations, ``ridx`` (n,) the
    observation of each hypothesis, ``rgba`` (n, S, S, 4) uint8 renders (alpha 255 on the object),
    ``gain`` (n,) brightness gains."""
    n, S = len(ridx), rgba.shape[1]
    x = np.empty((n, 9, S, S), np.float32)
    x[:, 0:3] = np.moveaxis(np.asarray(obs_rgb, np.float32), -1, 1)[ridx]
    x[:, 0:3] -= np.float32(0.5)
    r = np.moveaxis(rgba[..., :3], -1, 1).astype(np.float32)
    r *= (np.asarray(gain, np.float32) / np.float32(255.0))[:, None, None, None]
    np.clip(r, 0.0, 1.0, out=r)
    r -= np.float32(0.5)
    x[:, 3:6] = r
    x[:, 6] = rgba[..., 3] > 0
    x[:, 7] = np.asarray(in_box)[ridx]
    x[:, 8] = np.asarray(not_bg, np.float32)[ridx]
    return x


def term_vector(terms: dict, prior, coloured, total, area_ratio) -> np.ndarray:
    """(n, T) float32 scalar inputs (see the module docstring) from the verifier's term arrays."""
    n = len(total)
    pr = np.zeros(n) if prior is None else np.nan_to_num(np.asarray(prior, np.float64))
    cols = [terms["orient"], terms["colour"], terms["region"], terms["box"], pr, np.asarray(coloured, np.float64),
            total, np.clip(area_ratio, 0.0, 4.0)]
    return np.stack([np.asarray(c, np.float64).reshape(n) for c in cols], 1).astype(np.float32)
