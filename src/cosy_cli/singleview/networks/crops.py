"""Crops for the render-and-compare networks (paper Appendix A, "Cropping strategy").

The crop of iteration k is defined by the current pose estimate T_cam_obj^k only (the paper's
option (b), at training and test time): it is centred on the projection of the object origin
(the translation of T_cam_obj^k, which is also the point whose image-plane shift (v_x, v_y) the
network predicts), its half sizes are the largest horizontal/vertical distances (px) from that
centre to the projected model points, enlarged by ``scale`` (1.4 by default) and widened to the
network aspect ratio. The observed image is resampled into the crop with ``cv2.warpAffine`` and
:func:`cosy_cli.geometry.crop_affine`; the crop's intrinsics come from
:func:`cosy_cli.geometry.crop_intrinsics`, so the renderer can draw the object straight at crop
resolution with ``K_crop``.

Conventions: boxes are (x1, y1, x2, y2) in pixel-edge coordinates (BOP bbox convention,
x2 = x + w); sizes are (width, height) in px; lengths in mm; poses T_cam_obj 4x4 (OpenCV camera).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ...geometry.camera import crop_affine, crop_intrinsics, fit_box_to_aspect, project
from ...geometry.poses import look_at, make_pose

DEFAULT_SCALE = 1.4  # enlargement of the projected object's extent (DeepIM / CosyPose value)
CANONICAL_DEPTH_MM = 1000.0  # the paper's coarse input: the object 1 m from the camera
MIN_CROP_PX = 4.0  # smallest crop side in original pixels (degenerate projections)
# The coarse model's fixed input orientation R_cam_obj: the object seen from 30 deg above its
# xy-plane, from its -y side, its z axis pointing up in the image (the same view as
# ``cosy_cli.training.data.CANONICAL_ROTATION``; a model trained with one must run with the other).
_ELEVATION = math.radians(30.0)
CANONICAL_ROTATION = look_at(np.array([0.0, -math.cos(_ELEVATION), math.sin(_ELEVATION)]), np.zeros(3),
                             up=(0.0, 0.0, 1.0))[:3, :3].T.copy()


@dataclass
class CropBatch:
    """N crops of one size.

    crops: (N, h, w, 3) uint8 (or the input dtype); K: (N, 3, 3) intrinsics of the crops;
    boxes: (N, 4) the crop windows in the original image (px, may extend past the borders:
    outside pixels are filled with ``border_value``).
    """

    crops: np.ndarray
    K: np.ndarray
    boxes: np.ndarray


def boxes_from_poses(K: np.ndarray, T_cam_obj: np.ndarray, points: np.ndarray, out_size: tuple[int, int],
                     scale: float = DEFAULT_SCALE, min_size_px: float = MIN_CROP_PX) -> np.ndarray:
    """Crop windows (N, 4) px defined by poses.

    K: (3, 3) or (N, 3, 3); T_cam_obj: (N, 4, 4) (mm); points: (P, 3) or (N, P, 3) model points in
    the object frame (mm), e.g. ``ObjectModel.points`` or the 8 corners of the model box.
    out_size: the network input (width, height) px. The window is centred on the projection of
    the object origin; half-width = scale * max |u - u_c| (likewise for height), then the smaller
    side is widened to the aspect ratio width/height. Objects whose origin is behind the camera
    give meaningless windows; callers reject them (``T[:, 2, 3] > 0``).
    """
    K = np.asarray(K, dtype=np.float64)
    T = np.asarray(T_cam_obj, dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64)
    pts = np.broadcast_to(pts, (len(T),) + pts.shape[-2:])
    Kb = np.broadcast_to(K, (len(T), 3, 3))
    cam = pts @ np.swapaxes(T[:, :3, :3], -1, -2) + T[:, None, :3, 3]
    uv = project(cam, Kb)  # (N, P, 2)
    c = project(T[:, None, :3, 3], Kb)[:, 0]  # (N, 2) pixel-centre coordinates
    half = np.abs(uv - c[:, None]).max(axis=1) * scale  # (N, 2)
    c = c + 0.5  # pixel-edge coordinates: the origin lands on the crop's centre
    half = np.maximum(half, min_size_px / 2)
    aspect = out_size[0] / out_size[1]
    hw = np.maximum(half[:, 0], half[:, 1] * aspect)
    hh = hw / aspect
    return np.stack([c[:, 0] - hw, c[:, 1] - hh, c[:, 0] + hw, c[:, 1] + hh], axis=-1)


def boxes_from_detections(boxes: np.ndarray, out_size: tuple[int, int], scale: float = DEFAULT_SCALE,
                          min_size_px: float = MIN_CROP_PX) -> np.ndarray:
    """Crop windows (N, 4) px around detection boxes (N, 4): enlarged by ``scale`` about their
    centres and fitted to the aspect ratio of ``out_size`` (width, height). Not the paper's
    strategy (it crops from the pose only); useful to look at detections."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4).copy()
    c = (b[:, :2] + b[:, 2:]) / 2
    half = np.maximum((b[:, 2:] - b[:, :2]) / 2, min_size_px / 2)
    b = np.concatenate([c - half, c + half], axis=-1)
    return fit_box_to_aspect(b, out_size[0] / out_size[1], scale)


def crop_images(images: np.ndarray, boxes: np.ndarray, out_size: tuple[int, int], *,
                interpolation: int = cv2.INTER_LINEAR, border_value: int = 0) -> np.ndarray:
    """Resample windows of images into crops (N, h, w, C).

    images: one image (H, W, C) or (H, W) shared by all boxes, or one per box (N, H, W, C) (give
    per-box single-channel images as (N, H, W, 1)); any dtype cv2 resamples (use
    ``interpolation=cv2.INTER_NEAREST`` for depth or masks); boxes (N, 4) px; out_size (width,
    height) px. Pixels outside the image get ``border_value``.
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    images = np.asarray(images)
    shared = images.ndim in (2, 3)
    A = crop_affine(boxes, out_size)
    w, h = out_size
    first = images if shared else images[0]
    out = np.empty((len(boxes), h, w) + first.shape[2:], dtype=first.dtype)
    for i in range(len(boxes)):  # one cv2 call per crop: N is the number of detections
        img = images if shared else images[i]
        r = cv2.warpAffine(img, A[i], (w, h), flags=interpolation, borderMode=cv2.BORDER_CONSTANT,
                           borderValue=border_value)
        out[i] = r.reshape(out.shape[1:])
    return out


def make_crops(images: np.ndarray, K: np.ndarray, out_size: tuple[int, int], *, T_cam_obj: np.ndarray | None = None,
               points: np.ndarray | None = None, boxes: np.ndarray | None = None, scale: float = DEFAULT_SCALE,
               border_value: int = 0) -> CropBatch:
    """Crops of the observed image(s) and their intrinsics.

    With ``T_cam_obj`` (N, 4, 4, mm) and ``points`` (model points, mm) the windows follow the
    paper's strategy (:func:`boxes_from_poses`); otherwise ``boxes`` (N, 4) px are detection boxes
    (:func:`boxes_from_detections`). images: (H, W, 3) or (N, H, W, 3); K: (3, 3) or (N, 3, 3).
    """
    if T_cam_obj is not None:
        if points is None:
            raise ValueError("make_crops: poses need the model points (mm) to size the crops")
        win = boxes_from_poses(K, T_cam_obj, points, out_size, scale)
    elif boxes is not None:
        win = boxes_from_detections(boxes, out_size, scale)
    else:
        raise ValueError("make_crops: give poses (+ points) or boxes")
    crops = crop_images(images, win, out_size, border_value=border_value)
    Kc = crop_intrinsics(np.asarray(K, dtype=np.float64), win, out_size)
    Kc = np.broadcast_to(Kc, (len(win), 3, 3)).copy()
    return CropBatch(crops=crops, K=Kc, boxes=win)


def canonical_depth_from_boxes(K: np.ndarray, boxes: np.ndarray, diameters_mm: np.ndarray) -> np.ndarray:
    """Depths (N,) mm at which an object of diameter d (mm) spans about as many pixels as the
    larger side of its box: z = f * d / max(w, h) with f the mean focal length (px). An object's
    projected extent is at most f * d / z, so this slightly underestimates the depth."""
    K = np.broadcast_to(np.asarray(K, dtype=np.float64), (len(np.atleast_2d(boxes)), 3, 3))
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    f = (K[:, 0, 0] + K[:, 1, 1]) / 2
    side = np.maximum(np.maximum(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]), 1.0)
    return f * np.broadcast_to(np.asarray(diameters_mm, dtype=np.float64), (len(b),)) / side


def canonical_poses(K: np.ndarray, boxes: np.ndarray, depth_mm: float | np.ndarray = CANONICAL_DEPTH_MM,
                    R: np.ndarray | None = None) -> np.ndarray:
    """The coarse model's input poses T_cam_obj^0 (N, 4, 4), mm.

    The object origin is placed at depth ``depth_mm`` (scalar or (N,); the paper uses 1 m, see
    :func:`canonical_depth_from_boxes` for a depth matched to the box size) on the camera ray
    through the centre of each box (N, 4) px, so it projects exactly onto the box centre. The
    orientation is ``R`` (3, 3) or (N, 3, 3) R_cam_obj, by default :data:`CANONICAL_ROTATION`
    (a fixed view from 30 deg above the object's xy-plane).
    """
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    K = np.broadcast_to(np.asarray(K, dtype=np.float64), (len(b), 3, 3))
    z = np.broadcast_to(np.asarray(depth_mm, dtype=np.float64), (len(b),))
    # Pixel-edge box -> centre in pixel-centre coordinates: ((x1 + x2) / 2 - 0.5).
    u = (b[:, 0] + b[:, 2]) / 2 - 0.5
    v = (b[:, 1] + b[:, 3]) / 2 - 0.5
    uv1 = np.stack([u, v, np.ones_like(u)], axis=-1)
    ray = np.linalg.solve(K, uv1[..., None])[..., 0]  # (N, 3), z component 1 for upper-triangular K
    t = ray / ray[:, 2:3] * z[:, None]
    Rb = np.broadcast_to(CANONICAL_ROTATION if R is None else np.asarray(R, dtype=np.float64), (len(b), 3, 3))
    return make_pose(Rb, t)
