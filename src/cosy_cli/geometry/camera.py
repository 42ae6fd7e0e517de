"""Pinhole cameras (OpenCV/BOP convention: x right, y down, z forward), batched.

Pixel coordinates: the centre of the top-left pixel is (0, 0), as in OpenCV and BOP.
"""

from __future__ import annotations

import numpy as np

# Maps OpenCV camera coordinates to OpenGL camera coordinates (x right, y up, looking down -z).
T_GL_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def project(points_cam: np.ndarray, K: np.ndarray, eps: float = 1e-9) -> np.ndarray:
    """Project points (..., N, 3) in the camera frame with K (..., 3, 3) -> pixels (..., N, 2).

    Depths are clamped to ``eps`` (same unit as the points) so points behind the camera do not
    divide by zero; callers that care test ``z > 0`` themselves.
    """
    p = np.asarray(points_cam, dtype=np.float64) @ np.swapaxes(np.asarray(K, dtype=np.float64), -1, -2)
    return p[..., :2] / np.maximum(p[..., 2:3], eps)


def projected_boxes(points, T_cam_obj: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N, 4) [x1, y1, x2, y2] px, pixel-edge coordinates (pixel i spans [i, i + 1)), of the
    projections of N point sets ``points`` ((N, P, 3), (P, 3) for all, or a list of (P_i, 3); object
    frame, mm) by ``T_cam_obj`` (N, 4, 4) with K (3, 3), clipped to the width x height image. A row
    is NaN where a pose is not finite or puts a point at or behind the camera's plane."""
    T = np.asarray(T_cam_obj, dtype=np.float64).reshape(-1, 4, 4)
    if isinstance(points, (list, tuple)):  # sets of different sizes: pad each with its first point
        n = max((len(p) for p in points), default=0)
        points = [np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in points]
        points = np.stack([np.concatenate([p, np.repeat(p[:1], n - len(p), 0)]) for p in points]) \
            if points else np.zeros((0, 0, 3))
    P = np.broadcast_to(np.asarray(points, dtype=np.float64), (len(T),) + np.shape(points)[-2:])
    pc = np.einsum("nij,npj->npi", T[:, :3, :3], P) + T[:, None, :3, 3]
    ok = np.all(np.isfinite(T.reshape(len(T), 16)), 1) & np.all(pc[..., 2] > 1e-6, 1)
    uv = project(pc, K) + 0.5  # OpenCV pixel centres are at integers; edges at half-integers
    box = np.concatenate([uv.min(1, initial=np.inf), uv.max(1, initial=-np.inf)], 1)
    box[:, [0, 2]] = np.clip(box[:, [0, 2]], 0.0, float(width))
    box[:, [1, 3]] = np.clip(box[:, [1, 3]], 0.0, float(height))
    return np.where(ok[:, None], box, np.nan)


def backproject_depth(depth_mm: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W) depth in mm -> (H, W, 3) points in the camera frame (mm); 0 depth gives 0s."""
    H, W = depth_mm.shape
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    z = depth_mm.astype(np.float64)
    x = (u - K[0, 2]) * z / K[0, 0]
    y = (v - K[1, 2]) * z / K[1, 1]
    return np.stack([x, y, z], axis=-1)


def crop_intrinsics(K: np.ndarray, boxes: np.ndarray, out_size: tuple[int, int]) -> np.ndarray:
    """Intrinsics of crops resized to ``out_size`` = (width, height) pixels.

    ``boxes`` (..., 4) are (x1, y1, x2, y2) in pixel-edge coordinates (pixel i spans [i, i+1],
    the BOP ``bbox`` convention: x1 = x, x2 = x + w): the box edges map onto the crop's edges
    0..width and 0..height, as ``cv2.warpAffine`` with :func:`crop_affine` resamples it.
    Returns K_crop (..., 3, 3).
    """
    K = np.asarray(K, dtype=np.float64)
    boxes = np.asarray(boxes, dtype=np.float64)
    w_out, h_out = out_size
    sx = w_out / (boxes[..., 2] - boxes[..., 0])
    sy = h_out / (boxes[..., 3] - boxes[..., 1])
    shape = np.broadcast_shapes(K.shape[:-2], boxes.shape[:-1])
    Kc = np.broadcast_to(K, shape + (3, 3)).copy()
    Kc[..., 0, 0] = Kc[..., 0, 0] * sx
    Kc[..., 0, 1] = Kc[..., 0, 1] * sx
    Kc[..., 0, 2] = (Kc[..., 0, 2] + 0.5 - boxes[..., 0]) * sx - 0.5
    Kc[..., 1, 1] = Kc[..., 1, 1] * sy
    Kc[..., 1, 2] = (Kc[..., 1, 2] + 0.5 - boxes[..., 1]) * sy - 0.5
    return Kc


def crop_affine(boxes: np.ndarray, out_size: tuple[int, int]) -> np.ndarray:
    """2x3 affine maps (..., 2, 3) from original pixels to crop pixels, consistent with
    :func:`crop_intrinsics` (pixel centres at integer coordinates)."""
    boxes = np.asarray(boxes, dtype=np.float64)
    w_out, h_out = out_size
    sx = w_out / (boxes[..., 2] - boxes[..., 0])
    sy = h_out / (boxes[..., 3] - boxes[..., 1])
    A = np.zeros(boxes.shape[:-1] + (2, 3))
    A[..., 0, 0] = sx
    A[..., 0, 2] = (0.5 - boxes[..., 0]) * sx - 0.5
    A[..., 1, 1] = sy
    A[..., 1, 2] = (0.5 - boxes[..., 1]) * sy - 0.5
    return A


def fit_box_to_aspect(boxes: np.ndarray, aspect: float, scale: float = 1.0) -> np.ndarray:
    """Enlarge (x1, y1, x2, y2) boxes about their centres by ``scale`` and then to the
    width/height ratio ``aspect`` (never shrinking a side)."""
    boxes = np.asarray(boxes, dtype=np.float64)
    c = (boxes[..., :2] + boxes[..., 2:]) / 2
    w = (boxes[..., 2] - boxes[..., 0]) * scale
    h = (boxes[..., 3] - boxes[..., 1]) * scale
    w2 = np.maximum(w, h * aspect)
    h2 = np.maximum(h, w / aspect)
    return np.stack([c[..., 0] - w2 / 2, c[..., 1] - h2 / 2, c[..., 0] + w2 / 2, c[..., 1] + h2 / 2], -1)
