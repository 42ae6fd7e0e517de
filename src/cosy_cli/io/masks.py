"""Instance masks in detections files: COCO run-length encoding (RLE) and polygons.

BOP's default detections (2023-25) and COCO results carry a ``segmentation`` per detection: an RLE
dict ``{"counts": [...] or "string", "size": [height, width]}`` (counts of alternating 0/1 runs in
column-major order, starting with 0s; the BOP toolkit writes the list form, pycocotools the
compressed string), or, in COCO, a list of polygons ``[[x1, y1, x2, y2, ...], ...]`` in pixels.

    mask = decode_segmentation(seg, (480, 640))   # (H, W) bool
    seg = encode_mask(mask)                        # {"counts": [...], "size": [H, W]} (BOP's form)
"""

from __future__ import annotations

import numpy as np


class SegmentationError(ValueError):
    """A segmentation that is not an RLE dict or a polygon list of the image's size."""


def decode_segmentation(seg, shape: tuple[int, int]) -> np.ndarray:
    """The (H, W) bool mask of a detection's ``segmentation`` for an image of ``shape`` (H, W).
    Raises SegmentationError (what is wrong) for another size or a malformed value."""
    from pycocotools import mask as mask_util

    H, W = int(shape[0]), int(shape[1])
    if isinstance(seg, dict):
        size = seg.get("size")
        counts = seg.get("counts")
        if not (isinstance(size, (list, tuple)) and len(size) == 2) or counts is None:
            raise SegmentationError("an RLE segmentation needs 'counts' and 'size' [height, width]")
        if (int(size[0]), int(size[1])) != (H, W):
            raise SegmentationError(f"segmentation of size {int(size[0])}x{int(size[1])} (height x width) for an "
                                    f"image of {H}x{W}")
        if isinstance(counts, (list, tuple)):
            c = np.asarray(counts, dtype=np.int64)
            if c.ndim != 1 or (c < 0).any() or int(c.sum()) != H * W:
                raise SegmentationError(f"RLE counts must be non-negative run lengths summing to {H * W} pixels")
            rle = mask_util.frPyObjects({"counts": [int(v) for v in c], "size": [H, W]}, H, W)
        elif isinstance(counts, (str, bytes)):
            rle = {"counts": counts.encode() if isinstance(counts, str) else counts, "size": [H, W]}
        else:
            raise SegmentationError("RLE counts must be a list of run lengths or a compressed string")
        try:
            m = mask_util.decode(rle)
        except Exception as e:  # noqa: BLE001 - pycocotools raises plain exceptions on bad strings
            raise SegmentationError(f"cannot decode the RLE ({e})") from None
        return m.astype(bool).reshape(H, W)
    if isinstance(seg, (list, tuple)) and seg:
        polys = [seg] if not isinstance(seg[0], (list, tuple)) else list(seg)
        try:
            polys = [[float(v) for v in p] for p in polys]
        except (TypeError, ValueError):
            raise SegmentationError("a polygon segmentation is a list of [x1, y1, x2, y2, ...] lists") from None
        if any(len(p) < 6 or len(p) % 2 for p in polys):
            raise SegmentationError("each polygon needs at least 3 points (x, y pairs)")
        rle = mask_util.merge(mask_util.frPyObjects(polys, H, W))
        return mask_util.decode(rle).astype(bool).reshape(H, W)
    raise SegmentationError(f"a segmentation is an RLE dict or a list of polygons, not {type(seg).__name__}")


def encode_mask(mask: np.ndarray) -> dict:
    """The RLE of an (H, W) bool mask in the BOP toolkit's form: {"counts": [runs], "size": [H, W]},
    runs of the column-major pixels starting with a run of 0s (possibly empty)."""
    m = np.asarray(mask, bool)
    flat = m.reshape(-1, order="F")
    change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    bounds = np.concatenate([[0], change, [flat.size]])
    runs = np.diff(bounds).tolist()
    if flat.size and flat[0]:
        runs = [0] + runs
    return {"counts": [int(r) for r in runs], "size": [int(m.shape[0]), int(m.shape[1])]}
