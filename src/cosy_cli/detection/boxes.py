"""Axis-aligned 2D boxes [x, y, w, h] (pixels, BOP/COCO detection layout): IoU and non-maximum
suppression, pure vectorised numpy.

A box [x, y, w, h] covers x..x+w, y..y+h (continuous coordinates); its area is w * h. Boxes with
w or h <= 0 have zero area and an IoU of 0 with everything (also with themselves).
"""

from __future__ import annotations

import numpy as np


def _as_boxes(b, name: str) -> np.ndarray:
    b = np.asarray(b, dtype=np.float64)
    if b.ndim == 1 and b.size == 0:
        b = b.reshape(0, 4)
    if b.ndim != 2 or b.shape[1] != 4:
        raise ValueError(f"{name} must be (N, 4) boxes [x, y, w, h], got shape {b.shape}")
    return b


def box_iou(a_xywh, b_xywh) -> np.ndarray:
    """(N, M) intersection over union of boxes a (N, 4) and b (M, 4), [x, y, w, h] px."""
    a = _as_boxes(a_xywh, "a_xywh")
    b = _as_boxes(b_xywh, "b_xywh")
    aw, ah = np.maximum(a[:, 2], 0), np.maximum(a[:, 3], 0)
    bw, bh = np.maximum(b[:, 2], 0), np.maximum(b[:, 3], 0)
    ix = np.minimum(a[:, None, 0] + aw[:, None], b[None, :, 0] + bw[None]) - np.maximum(a[:, None, 0], b[None, :, 0])
    iy = np.minimum(a[:, None, 1] + ah[:, None], b[None, :, 1] + bh[None]) - np.maximum(a[:, None, 1], b[None, :, 1])
    inter = np.maximum(ix, 0) * np.maximum(iy, 0)
    union = (aw * ah)[:, None] + (bw * bh)[None] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def nms(boxes_xywh, scores, iou_threshold: float = 0.5) -> np.ndarray:
    """Greedy non-maximum suppression: indices (int64) of the kept boxes, by decreasing score
    (ties keep the input order). A box is dropped when its IoU with a kept, higher-scored box
    is > ``iou_threshold``.

    The IoU matrix is computed once (N x N, fine for the few hundred boxes of a detector);
    the greedy pass walks the boxes in score order and suppresses rows with one vector op."""
    boxes = _as_boxes(boxes_xywh, "boxes_xywh")
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if len(scores) != len(boxes):
        raise ValueError(f"{len(boxes)} boxes but {len(scores)} scores")
    order = np.argsort(-scores, kind="stable")
    if len(order) == 0:
        return order.astype(np.int64)
    over = box_iou(boxes[order], boxes[order]) > iou_threshold  # (N, N) in score order
    alive = np.ones(len(order), dtype=bool)
    for i in range(len(order)):
        if alive[i]:
            alive[i + 1:] &= ~over[i, i + 1:]
    return order[alive].astype(np.int64)


def nms_per_class(boxes_xywh, scores, labels, iou_threshold: float = 0.5) -> np.ndarray:
    """NMS within each label only (boxes of different labels never suppress each other):
    kept indices (int64) sorted by decreasing score.

    Done as one :func:`nms` on boxes shifted apart per label (the usual offset trick: the boxes
    of label k are moved by k x (the span of all boxes + 1) in x, so that boxes of different
    labels never overlap)."""
    boxes = _as_boxes(boxes_xywh, "boxes_xywh")
    labels = np.asarray(labels).reshape(-1)
    if len(labels) != len(boxes):
        raise ValueError(f"{len(boxes)} boxes but {len(labels)} labels")
    if len(boxes) == 0:
        return np.zeros(0, dtype=np.int64)
    _, group = np.unique(labels, return_inverse=True)
    span = float(np.max(boxes[:, 0] + np.maximum(boxes[:, 2], 0)) - np.min(boxes[:, 0])) + 1.0
    shifted = boxes.copy()
    shifted[:, 0] += group * (span + 1.0) - np.min(boxes[:, 0])
    return nms(shifted, scores, iou_threshold)


def xywh_to_xyxy(b) -> np.ndarray:
    """(..., 4) [x, y, w, h] -> [x1, y1, x2, y2]."""
    b = np.asarray(b, dtype=np.float64)
    return np.concatenate([b[..., :2], b[..., :2] + b[..., 2:]], axis=-1)


def xyxy_to_xywh(b) -> np.ndarray:
    """(..., 4) [x1, y1, x2, y2] -> [x, y, w, h]."""
    b = np.asarray(b, dtype=np.float64)
    return np.concatenate([b[..., :2], b[..., 2:] - b[..., :2]], axis=-1)


def clip_xyxy(boxes_xywh, width, height) -> np.ndarray:
    """(N, 4) [x, y, w, h] px -> (N, 4) [x1, y1, x2, y2] clipped to [0, width] x [0, height] px
    (``width``/``height``: numbers, or (N,) arrays for boxes of different images)."""
    b = xywh_to_xyxy(np.asarray(boxes_xywh, dtype=np.float64).reshape(-1, 4))
    return np.stack([np.clip(b[:, 0], 0, width), np.clip(b[:, 1], 0, height),
                     np.clip(b[:, 2], 0, width), np.clip(b[:, 3], 0, height)], 1)


__all__ = ["box_iou", "nms", "nms_per_class", "xywh_to_xyxy", "xyxy_to_xywh", "clip_xyxy"]
