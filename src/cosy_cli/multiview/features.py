"""Relative camera rotations from image features (beyond the paper; ``cosy refine --feature-cameras``).

CosyPose places the cameras of a group from the objects alone: the relative poses that RANSAC
finds over object candidates, then the object-level bundle adjustment. With 3-8 objects about 1 m
away whose single-view depths are off by a few percent, that leaves the cameras a few degrees
wrong (real LM-O dev scenes, cosy's own RGB candidates: median 4.6 deg and 80 mm against the
GT-derived cameras), and every pose carried from one view to another inherits it. The images of a
static scene say much more about the rotation between two views: SIFT features matched with
Lowe's ratio test and an essential matrix (RANSAC, normalised coordinates, so that the two views
may have different intrinsics) give the rotation and the direction of the translation (same
scenes: median 1.4 deg, translation direction 2.8 deg). The scale is not in the images; the
object-level estimate keeps it (:func:`feature_camera`).

How ``cosy refine`` uses them (``feature_cameras``): "leftovers" (default) carries the leftover
candidates of the image check across views with these cameras; "scene" also adjusts the objects
again with them held. On the odd LM-O dev scenes (chosen there) the cameras' errors against the
GT-derived ones went from 4.6 deg / 80 mm (objects alone) to 1.4 deg / 22 mm, and multi-view AR
(MSSD, MSPD) with cosy's own candidates 0.429 -> 0.435 (leftovers; 0.444 with the final rules
below) / 0.439 (scene); but "scene"
cost 0.025 on synthetic candidates made from the GT (1 %/2 deg: 0.898 -> 0.873), whose cameras the
objects reproduce better than the images do (the LM-O GT is rigid only within 10 mm), while
"leftovers" left them as they were or better (0.903). With the GT-derived cameras the leftover
check would reach 0.458, but GT rotations with these translations gave 0.420 and the reverse
0.418: that oracle mostly measures agreement with the GT annotation itself.

A pair is trusted only when it has at least ``min_inliers`` essential-matrix inliers and its
rotation agrees with the object-level one within ``max_disagree_deg`` (a scene whose texture
repeats, or with too little background, can give a confident wrong essential matrix: one LM-O
pair with 9 inliers came out 175 deg off). 30 deg was chosen on the odd scenes (15 / 30 / 180:
0.440 / 0.444 / 0.442), after a held-out even scene had shown a 76-inlier pair refused against a
camera the objects had placed through 3 inliers. A view the objects could not place at all (no
object matched) gets its camera from the images alone (:func:`camera_without_objects`) with
``min_inliers_alone`` inliers, the scale from the candidates of labels seen once in each view.

Poses are 4x4 ``T_a_b`` (maps frame b into frame a); lengths in mm; OpenCV cameras.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.poses import invert, rotation_angle


PARALLAX_QUANTILE = 0.75  # parallax_px: this quantile of the matches' distances to the best homography


@dataclass
class FeatureConf:
    """Settings (chosen on the odd LM-O dev scenes)."""

    n_features: int = 4000        # SIFT keypoints per image at most
    ratio: float = 0.8            # Lowe's ratio test
    ransac_px: float = 1.0        # essential-matrix RANSAC threshold, px (at the first view's focal length)
    min_inliers: int = 30         # a pair with fewer inliers is not used
    min_inliers_alone: int = 60   # ... and for a view the objects could not place (no rotation to compare with)
    max_disagree_deg: float = 30.0  # ... nor one whose rotation differs more from the object-level one


@dataclass
class PairPose:
    """The relative pose of two views from their images: ``T_a_b`` (4, 4) with a unit translation
    (direction only: the images do not give the scale), the number of inlier matches, and the
    parallax of the matches (:func:`parallax_px`, px; about 0 for views from one point, whatever
    their rotation)."""

    T_a_b: np.ndarray
    n_inliers: int
    n_matches: int
    parallax_px: float = 0.0


class FeatureCache:
    """SIFT keypoints and descriptors per image, computed once (images as (H, W, 3) uint8 RGB)."""

    def __init__(self, conf: FeatureConf | None = None):
        import cv2

        self.conf = conf or FeatureConf()
        self._sift = cv2.SIFT_create(nfeatures=self.conf.n_features)
        self._cache: dict = {}

    def features(self, key, rgb: np.ndarray):
        hit = self._cache.get(key)
        if hit is None:
            import cv2

            grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
            kp, desc = self._sift.detectAndCompute(grey, None)
            pts = np.array([k.pt for k in kp], dtype=np.float64).reshape(-1, 2)
            hit = (pts, desc)
            self._cache[key] = hit
        return hit


def relative_pose(cache: FeatureCache, key_a, rgb_a: np.ndarray, K_a: np.ndarray, key_b, rgb_b: np.ndarray,
                  K_b: np.ndarray) -> PairPose | None:
    """T_a_b of view b in view a's camera frame from matched SIFT features, translation of unit
    length; None when there are too few matches to try (fewer than 8)."""
    import cv2

    c = cache.conf
    pa, da = cache.features(key_a, rgb_a)
    pb, db = cache.features(key_b, rgb_b)
    if da is None or db is None or len(pa) < 8 or len(pb) < 8:
        return None
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    pairs = np.array([(m[0].queryIdx, m[0].trainIdx) for m in knn
                      if len(m) == 2 and m[0].distance < c.ratio * m[1].distance], dtype=np.int64).reshape(-1, 2)
    if len(pairs) < 8:
        return None
    na = cv2.undistortPoints(pa[pairs[:, 0]].reshape(-1, 1, 2), np.asarray(K_a, np.float64), None)
    nb = cv2.undistortPoints(pb[pairs[:, 1]].reshape(-1, 1, 2), np.asarray(K_b, np.float64), None)
    E, mask = cv2.findEssentialMat(na, nb, np.eye(3), method=cv2.RANSAC, prob=0.999,
                                   threshold=c.ransac_px / float(K_a[0, 0]))
    if E is None or E.shape != (3, 3):
        return None
    n_in, R, t, _ = cv2.recoverPose(E, na, nb, np.eye(3), mask=mask)
    T_b_a = np.eye(4)  # recoverPose: x_b = R x_a + t
    T_b_a[:3, :3], T_b_a[:3, 3] = R, np.asarray(t, dtype=np.float64).reshape(3)
    return PairPose(invert(T_b_a), int(n_in), int(len(pairs)), parallax_px(pa[pairs[:, 0]], pb[pairs[:, 1]]))


def parallax_px(xa: np.ndarray, xb: np.ndarray) -> float:
    """How far matched points xa (n, 2) of view a and xb (n, 2) of view b (px) are from being one
    homography apart: the PARALLAX_QUANTILE quantile of the distances (px) between xb and the best
    homography's image of xa (RANSAC, 3 px). Views taken from one point (any rotation) give a few
    px at most, whatever the scene; views from points apart give tens to hundreds on a scene with
    depth (a flat scene alone gives none: one plane is one homography)."""
    import cv2

    if len(xa) < 8:
        return 0.0
    H, _ = cv2.findHomography(xa.reshape(-1, 1, 2), xb.reshape(-1, 1, 2), cv2.RANSAC, 3.0)
    if H is None:
        return float("inf")
    p = np.concatenate([xa, np.ones((len(xa), 1))], 1) @ H.T
    d = np.linalg.norm(p[:, :2] / np.where(np.abs(p[:, 2:]) > 1e-9, p[:, 2:], 1e-9) - xb, axis=1)
    return float(np.quantile(d, PARALLAX_QUANTILE))


def feature_camera(T_world_ref: np.ndarray, T_world_cam: np.ndarray, pair: PairPose | None,
                   conf: FeatureConf, centres_ref: np.ndarray | None = None,
                   centres_cam: np.ndarray | None = None) -> np.ndarray | None:
    """A view's camera T_world_cam (4, 4) mm with the rotation and translation direction of the
    image pair (ref, view) and the scale of the object-level estimate: the object-level baseline
    projected on the feature direction. None when the pair is not trusted (too few inliers, a
    rotation more than ``max_disagree_deg`` from the object-level one, or a direction that points
    away from the object-level baseline)."""
    if pair is None or pair.n_inliers < conf.min_inliers:
        return None
    T_ref_cam_obj = invert(T_world_ref) @ T_world_cam  # object-level estimate, in the reference camera
    T_ref_cam = pair.T_a_b
    if np.degrees(rotation_angle(T_ref_cam_obj[:3, :3].T @ T_ref_cam[:3, :3])) > conf.max_disagree_deg:
        return None
    if centres_ref is not None and len(centres_ref):
        s = _median_scale(T_ref_cam, centres_ref, centres_cam)
    else:
        s = float(T_ref_cam_obj[:3, 3] @ _direction(T_ref_cam))
    return _scaled_camera(T_world_ref, T_ref_cam, s)


def camera_without_objects(T_world_ref: np.ndarray, pair: PairPose | None, conf: FeatureConf,
                           centres_ref: np.ndarray, centres_cam: np.ndarray) -> np.ndarray | None:
    """The camera T_world_cam (4, 4) mm of a view that the objects could not place (no object
    matched across the views): rotation and baseline direction from the image pair (ref, view),
    the scale from the candidates of labels seen once in each view (``centres_ref`` /
    ``centres_cam`` (n, 3) mm, same order; median along the direction). Trusted only with
    ``min_inliers_alone`` inliers (there is no object-level rotation to check it against) and at
    least one such pair of candidates; None otherwise."""
    if pair is None or pair.n_inliers < conf.min_inliers_alone or not len(centres_ref):
        return None
    return _scaled_camera(T_world_ref, pair.T_a_b, _median_scale(pair.T_a_b, centres_ref, centres_cam))


def _direction(T_ref_cam: np.ndarray) -> np.ndarray:
    """The unit baseline direction of an image pair's pose (its translation has no scale)."""
    return T_ref_cam[:3, 3] / max(np.linalg.norm(T_ref_cam[:3, 3]), 1e-12)


def _median_scale(T_ref_cam: np.ndarray, centres_ref, centres_cam) -> float:
    """The baseline length (mm) that objects seen in both views give: X_ref = R X_cam + s d for
    each (candidates' centres (n, 3) mm in the reference and the view), median over them."""
    R = T_ref_cam[:3, :3]
    return float(np.median((np.asarray(centres_ref) - np.asarray(centres_cam) @ R.T) @ _direction(T_ref_cam)))


def _scaled_camera(T_world_ref: np.ndarray, T_ref_cam: np.ndarray, s: float) -> np.ndarray | None:
    """T_world_cam of the image pair's pose with its baseline scaled to ``s`` mm; None when s <= 0
    (the objects put the view on the other side)."""
    if s <= 0.0:
        return None
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = T_ref_cam[:3, :3], s * _direction(T_ref_cam)
    return T_world_ref @ T
