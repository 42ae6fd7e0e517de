"""Running an exported detector with onnxruntime: :class:`OnnxDetector`.

    det = OnnxDetector("detector.onnx")
    boxes, scores, obj_ids = det.detect(rgb)   # rgb uint8 (H, W, 3) of any size

The image is resized (area interpolation when shrinking, linear when enlarging) to the
network's input size, run through the graph (sigmoid heatmap peaks + box edge distances,
see :mod:`cosy_cli.detection.model`), decoded (top-K peaks over all classes and cells),
scaled back to the image, clipped to it and filtered by per-class NMS.

Box convention of the output, [x, y, w, h] in pixels of the given image as BOP's
``bbox_visib``: x, y = the first covered pixel column / row, w = x_max - x_min and
h = y_max - y_min of the covered pixel indices (so a box covering columns 10..19 has x = 10,
w = 9). Internally the network predicts continuous extents ([x_min, x_max + 1)).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import CosyError
from ..onnxrt import open_session
from .boxes import nms_per_class

METADATA_KEY = "cosy_detector"
TOP_K = 100  # peaks decoded per image before NMS


class OnnxDetector:
    """An exported cosy detector run by onnxruntime.

    path: the .onnx file (from ``cosy export`` of a ``cosy train detector`` run). providers:
    "cpu", "cuda" or onnxruntime provider names; providers that this onnxruntime lacks are
    skipped (the CPU is always last). threads: onnxruntime intra-op threads (default: its own).

    Attributes: ``obj_ids`` (list of int: the BOP obj_id of each class), ``input_size``
    ((width, height) the network runs at), ``config`` (the metadata dict), ``path``.
    """

    def __init__(self, path: str | Path, providers: Sequence[str] = ("cpu",), threads: int | None = None):
        path = Path(path)
        self.session, cfg = open_session(
            path, METADATA_KEY, providers, threads,
            missing=": train a detector with `cosy train detector --dataset DIR --out RUN` and export it with "
                    "`cosy export --run RUN --out detector.onnx`",
            not_ours="not a detector exported by cosy (`cosy export` of a `cosy train detector` run)")
        try:
            self.obj_ids: list[int] = [int(o) for o in cfg["obj_ids"]]
            self.input_size: tuple[int, int] = (int(cfg["input_size"][0]), int(cfg["input_size"][1]))
            self.stride = int(cfg["stride"])
        except (ValueError, KeyError, TypeError, IndexError) as e:
            raise CosyError(f"ONNX model has malformed '{METADATA_KEY}' metadata ({e})", path=path) from None
        if cfg.get("kind", "detector") != "detector":
            raise CosyError(f"ONNX model is a {cfg.get('kind')!r} network, not a detector", path=path)
        self.config = cfg
        self.path = path
        self.providers = self.session.get_providers()
        self._input = self.session.get_inputs()[0].name
        self._outputs = [o.name for o in self.session.get_outputs()]

    def __repr__(self) -> str:
        return f"OnnxDetector({str(self.path)!r}, objects={self.obj_ids}, input_size={self.input_size})"

    def preprocess(self, rgb: np.ndarray) -> np.ndarray:
        """(1, 3, h, w) float32 in [0, 1] network input of an (H, W, 3) uint8 RGB image."""
        import cv2

        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[0] < 1 or rgb.shape[1] < 1:
            raise ValueError(f"detect expects an RGB image (H, W, 3), got shape {rgb.shape}")
        if rgb.dtype != np.uint8:
            raise ValueError(f"detect expects a uint8 image, got {rgb.dtype}")
        w, h = self.input_size
        H, W = rgb.shape[:2]
        if (W, H) != (w, h):
            interp = cv2.INTER_AREA if W >= w and H >= h else cv2.INTER_LINEAR
            rgb = cv2.resize(rgb, (w, h), interpolation=interp)
        return (rgb.transpose(2, 0, 1)[None].astype(np.float32) * np.float32(1 / 255.0))

    def raw(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The graph's outputs (peaks (B, C, h, w), ltrb (B, 4, h, w)) for input x (B, 3, h, w)."""
        peaks, ltrb = self.session.run(self._outputs, {self._input: np.ascontiguousarray(x, dtype=np.float32)})
        return peaks, ltrb

    def detect(self, rgb: np.ndarray, min_score: float = 0.3, max_per_image: int = 30, nms_iou: float = 0.5,
               tiles: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Detections in one image.

        rgb: uint8 (H, W, 3) RGB of any size. Returns boxes (N, 4) float64 [x, y, w, h] px of this
        image (see the module docstring), scores (N,) float64 in [0, 1], obj_ids (N,) int64;
        per-class NMS at IoU ``nms_iou``, scores >= ``min_score``, at most ``max_per_image``,
        sorted by decreasing score.

        tiles: 0 = the whole image only; n >= 2 = also an n x n grid of overlapping windows
        (:func:`tile_windows`), each resized to the input size (objects seen about n times larger:
        small and far objects), in the same batch; a window's boxes that touch one of its edges
        inside the image (an object cut by the window) are dropped, the whole image's pass sees
        those; all boxes then share one per-class NMS."""
        from .model import decode

        rgb = np.asarray(rgb)
        H, W = rgb.shape[:2]
        windows = [(0, 0, W, H)] + (tile_windows(W, H, int(tiles)) if int(tiles) >= 2 else [])
        x = np.concatenate([self.preprocess(rgb[y0:y1, x0:x1]) for x0, y0, x1, y1 in windows])
        peaks, ltrb = self.raw(x)
        k = max(TOP_K, int(max_per_image))
        parts = []
        for b, (x0, y0, x1, y1) in enumerate(windows):
            xyxy, scores, cls = decode(peaks[b], ltrb[b], self.stride, k=k, min_score=float(min_score))
            sx, sy = (x1 - x0) / self.input_size[0], (y1 - y0) / self.input_size[1]
            xyxy = xyxy * np.array([sx, sy, sx, sy]) + np.array([x0, y0, x0, y0], dtype=np.float64)
            if b:  # a tile: drop what its inner edges cut (within 1 % of the window)
                m = 0.01 * max(x1 - x0, y1 - y0)
                cut = (((xyxy[:, 0] <= x0 + m) & (x0 > 0)) | ((xyxy[:, 2] >= x1 - m) & (x1 < W))
                       | ((xyxy[:, 1] <= y0 + m) & (y0 > 0)) | ((xyxy[:, 3] >= y1 - m) & (y1 < H)))
                xyxy, scores, cls = xyxy[~cut], scores[~cut], cls[~cut]
            parts.append((xyxy, scores, cls))
        xyxy = np.concatenate([p[0] for p in parts]).reshape(-1, 4)
        scores = np.concatenate([p[1] for p in parts])
        cls = np.concatenate([p[2] for p in parts]).astype(np.int64)
        xyxy[:, [0, 2]] = np.clip(xyxy[:, [0, 2]], 0.0, W)
        xyxy[:, [1, 3]] = np.clip(xyxy[:, [1, 3]], 0.0, H)
        # continuous extents [x1, x2) -> BOP pixel-index boxes: x = x1, w = (x2 - 1) - x1
        x1 = np.minimum(xyxy[:, 0], W - 1.0)
        y1 = np.minimum(xyxy[:, 1], H - 1.0)
        w = np.maximum(xyxy[:, 2] - 1.0 - x1, 0.0)
        h = np.maximum(xyxy[:, 3] - 1.0 - y1, 0.0)
        boxes = np.stack([x1, y1, w, h], axis=1)
        ok = (xyxy[:, 2] > xyxy[:, 0]) & (xyxy[:, 3] > xyxy[:, 1])  # not entirely outside the image
        boxes, scores, cls = boxes[ok], scores[ok], cls[ok]
        keep = nms_per_class(boxes, scores, cls, nms_iou)[: max(0, int(max_per_image))]
        obj_ids = np.asarray(self.obj_ids, dtype=np.int64)[cls[keep]]
        return boxes[keep], scores[keep], obj_ids


def tile_windows(width: int, height: int, n: int, overlap: float = 0.25) -> list[tuple[int, int, int, int]]:
    """An n x n grid of windows (x0, y0, x1, y1) px covering a width x height image, each
    (1 + ``overlap``) / n of the image's width and height (so neighbours overlap and an object up
    to about ``overlap`` / n of the image wide lies whole in one of them), row by row."""
    if n < 1:
        raise ValueError(f"tiles: expected n >= 1, got {n}")
    ww, wh = min(width, round(width * (1 + overlap) / n)), min(height, round(height * (1 + overlap) / n))
    xs = np.round(np.linspace(0, width - ww, n)).astype(int) if n > 1 else np.array([0])
    ys = np.round(np.linspace(0, height - wh, n)).astype(int) if n > 1 else np.array([0])
    return [(int(x), int(y), int(x) + ww, int(y) + wh) for y in ys for x in xs]


__all__ = ["OnnxDetector", "tile_windows"]
