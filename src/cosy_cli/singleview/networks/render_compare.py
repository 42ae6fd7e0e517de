"""Inference with the render-and-compare networks (paper Section 3.1, Appendix A).

:class:`RenderAndCompare` runs one exported PoseNet (coarse or refiner, an
:class:`~cosy_cli.singleview.networks.onnx.OnnxPoseNet` or any callable with the same contract) on the
detections of one image: for each current pose T^k it crops the observed image around the
projected object (the paper's crop strategy, exactly as in training: convex-hull extent x 1.4,
fitted to the network aspect ratio), renders the object at T^k into the same crop with the crop
intrinsics, runs the network on the 6-channel (or 7 with the rendered mask) input and applies
the predicted update ``T^{k+1} = F(T^k, v, R)``. The coarse network starts from the canonical pose
(object 1 m away on the ray through the box centre, fixed orientation); the refiner iterates.

Lengths in mm, poses T_cam_obj (4, 4) in the OpenCV camera, boxes (x1, y1, x2, y2) px in
pixel-edge coordinates.
"""

from __future__ import annotations

import numpy as np
import torch

from ...geometry.camera import crop_intrinsics
from .crops import DEFAULT_SCALE, boxes_from_poses, canonical_poses, crop_images
from .model import prepare_inputs
from .pose_update import apply_update

NEUTRAL_COLOR = (0.7, 0.7, 0.7)  # the rendered branch's albedo in training (training.data.NEUTRAL_COLOR)


class RenderAndCompare:
    """One network, its renderer and the objects' convex hulls.

    net: callable (B, C, H, W) float32 in [0, 1] -> (B, 9) with a ``config`` (PoseNetConfig:
    kind, crop_size, n_inputs); renderer: a :class:`~cosy_cli.rendering.SceneRenderer` holding
    the meshes of the objects; hulls: obj_id -> (P, 3) convex-hull vertices (mm) that size the
    crops; batch_size: crops per network call.
    """

    def __init__(self, net, renderer, hulls: dict[int, np.ndarray], batch_size: int = 32,
                 crop_scale: float = DEFAULT_SCALE):
        self.net = net
        self.renderer = renderer
        self.crop_size = tuple(int(v) for v in net.config.crop_size)
        self.n_inputs = int(net.config.n_inputs)
        self.batch_size = int(batch_size)
        self.crop_scale = float(crop_scale)
        n_max = max(len(h) for h in hulls.values())
        # Pad every hull to n_max points by repeating its first vertex (extremes unchanged).
        self._hull = {int(o): np.concatenate([h, np.repeat(h[:1], n_max - len(h), 0)]) for o, h in hulls.items()}

    @property
    def kind(self) -> str:
        return self.net.config.kind

    def step(self, rgb: np.ndarray, K: np.ndarray, T_cam_obj: np.ndarray, obj_ids: np.ndarray) -> np.ndarray:
        """One network iteration on N poses of one image: T^{k+1} (N, 4, 4) mm.

        rgb (H, W, 3) uint8; K (3, 3); T_cam_obj (N, 4, 4) mm; obj_ids (N,). Poses whose origin is
        not in front of the camera are returned unchanged."""
        T = np.asarray(T_cam_obj, dtype=np.float64).reshape(-1, 4, 4)
        ids = np.asarray(obj_ids, dtype=np.int64).reshape(-1)
        out = T.copy()
        valid = np.flatnonzero(T[:, 2, 3] > 1e-3)
        for s in range(0, len(valid), self.batch_size):
            idx = valid[s:s + self.batch_size]
            out[idx] = self._step_batch(rgb, K, T[idx], ids[idx])
        return out

    def make_inputs(self, rgb: np.ndarray, K: np.ndarray, T: np.ndarray, ids: np.ndarray):
        """The network input for poses T (B, 4, 4) mm of objects ids (B,) in image rgb with
        intrinsics K: (x (B, C, h, w) float32, K_crop (B, 3, 3), crop boxes (B, 4) px, rendered
        crops (B, h, w, 3) uint8)."""
        w, h = self.crop_size
        hull = np.stack([self._hull[int(o)] for o in ids])
        boxes = boxes_from_poses(K, T, hull, (w, h), scale=self.crop_scale)
        K_crop = np.ascontiguousarray(np.broadcast_to(crop_intrinsics(np.asarray(K, dtype=np.float64), boxes, (w, h)),
                                                      (len(T), 3, 3)))
        observed = crop_images(rgb, boxes, (w, h))
        ren = self.renderer.render_crops(K_crop, ids, T, (w, h), colors=np.tile(NEUTRAL_COLOR, (len(T), 1)))
        x = prepare_inputs(observed, ren.rgb, (ren.instance >= 0) if self.n_inputs == 7 else None)
        return x, K_crop, boxes, ren.rgb

    def _step_batch(self, rgb, K, T, ids):
        x, K_crop, _, _ = self.make_inputs(rgb, K, T, ids)
        update = np.asarray(self.net(x), dtype=np.float64)
        with torch.no_grad():
            T_new = apply_update(*(torch.tensor(np.asarray(a, dtype=np.float64)) for a in (T, update, K_crop)))
        return T_new.numpy()

    def coarse(self, rgb: np.ndarray, K: np.ndarray, boxes: np.ndarray, obj_ids: np.ndarray) -> np.ndarray:
        """The coarse estimate (N, 4, 4) mm: one step from the canonical pose of each detection box."""
        return self.step(rgb, K, canonical_poses(K, boxes), obj_ids)

    def iterate(self, rgb: np.ndarray, K: np.ndarray, T_cam_obj: np.ndarray, obj_ids: np.ndarray,
                iterations: int) -> list[np.ndarray]:
        """Poses after 1..iterations refiner steps (list of (N, 4, 4) mm, one per iteration)."""
        T = np.asarray(T_cam_obj, dtype=np.float64)
        history = []
        for _ in range(int(iterations)):
            T = self.step(rgb, K, T, obj_ids)
            history.append(T)
        return history

