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
again with them held, and places the views no object placed from the images alone
(:func:`camera_without_objects`), held as well. On the odd LM-O dev scenes (chosen there) the cameras' errors against the
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


OPENCV_REFUSED = "OpenCV refused the input"  # in a PairPose's failure when a cv2.error ended the pair
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
    their rotation). A pair the images give no pose for has ``T_a_b`` None, no inliers and a
    one-line ``failure`` saying why (too few matches, or what OpenCV refused)."""

    T_a_b: np.ndarray | None
    n_inliers: int
    n_matches: int
    parallax_px: float = 0.0
    failure: str = ""

    @property
    def ok(self) -> bool:
        return self.T_a_b is not None

    @staticmethod
    def failed(reason: str, n_matches: int = 0) -> "PairPose":
        return PairPose(None, 0, int(n_matches), 0.0, reason)


class FeatureCache:
    """SIFT keypoints and descriptors per image, computed once (images as (H, W, 3) uint8 RGB, or
    (H, W) grey). An image OpenCV cannot take gets no features, and ``failures[key]`` says why."""

    def __init__(self, conf: FeatureConf | None = None):
        import cv2

        self.conf = conf or FeatureConf()
        self._sift = cv2.SIFT_create(nfeatures=self.conf.n_features)
        self._cache: dict = {}
        self.failures: dict = {}

    def features(self, key, rgb: np.ndarray):
        hit = self._cache.get(key)
        if hit is None:
            import cv2

            img = np.ascontiguousarray(rgb)
            try:
                grey = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
                kp, desc = self._sift.detectAndCompute(grey, None)
            except cv2.error as e:
                self.failures[key] = opencv_failure(f"SIFT on image {key}", e)
                kp, desc = (), None
            pts = np.array([k.pt for k in kp], dtype=np.float64).reshape(-1, 2)
            hit = (pts, desc)
            self._cache[key] = hit
        return hit


def relative_pose(cache: FeatureCache, key_a, rgb_a: np.ndarray, K_a: np.ndarray, key_b, rgb_b: np.ndarray,
                  K_b: np.ndarray) -> PairPose:
    """T_a_b of view b in view a's camera frame from matched SIFT features, translation of unit
    length. Always a :class:`PairPose`: one without a pose (``failure`` says why) when there are
    too few matches to try (fewer than 8) or OpenCV cannot estimate one from them.

    The essential matrix is estimated with OpenCV's USAC (``USAC_ACCURATE``: graph-cut RANSAC
    with local optimisation, its own 5-point solver, a fixed seed): the same answer on OpenCV
    4.14, 5.0 and 5.1, where OpenCV 5.1's classic ``RANSAC`` aborts a whole estimate (an assertion
    in ``solvePoly``) when one random 5-point sample is degenerate, about 1 sample in 300 of real
    LM-O matches. Any other ``cv2.error`` on such data is a failed pair, not a crashed stage."""
    import cv2

    c = cache.conf
    pa, da = cache.features(key_a, rgb_a)
    pb, db = cache.features(key_b, rgb_b)
    if da is None or db is None or len(pa) < 8 or len(pb) < 8:
        why = "; ".join(cache.failures[k] for k in (key_a, key_b) if k in cache.failures)
        return PairPose.failed(why or f"too few features ({len(pa)} and {len(pb)}, 8 needed)")
    pairs = np.zeros((0, 2), np.int64)
    try:
        knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
        pairs = np.array([(m[0].queryIdx, m[0].trainIdx) for m in knn
                          if len(m) == 2 and m[0].distance < c.ratio * m[1].distance], dtype=np.int64).reshape(-1, 2)
        if len(pairs) < 8:
            return PairPose.failed(f"too few matches ({len(pairs)}, 8 needed)", len(pairs))
        na = cv2.undistortPoints(pa[pairs[:, 0]].reshape(-1, 1, 2), np.asarray(K_a, np.float64), None)
        nb = cv2.undistortPoints(pb[pairs[:, 1]].reshape(-1, 1, 2), np.asarray(K_b, np.float64), None)
        pose = essential_pose(na.reshape(-1, 2), nb.reshape(-1, 2), c.ransac_px / float(K_a[0, 0]))
    except cv2.error as e:
        return PairPose.failed(opencv_failure("feature matching", e), len(pairs))
    if isinstance(pose, str):
        return PairPose.failed(pose, len(pairs))
    T_b_a, n_in = pose
    return PairPose(invert(T_b_a), n_in, int(len(pairs)), parallax_px(pa[pairs[:, 0]], pb[pairs[:, 1]]))


def essential_pose(xa: np.ndarray, xb: np.ndarray, threshold: float) -> tuple[np.ndarray, int] | str:
    """(T_b_a (4, 4) with a unit translation, number of inliers) of two views from matched points
    xa, xb (n, 2) in normalised image coordinates (K^-1 applied): the essential matrix
    (``USAC_ACCURATE``, ``threshold`` in normalised units), then the cheirality check of
    ``recoverPose``. A one-line reason instead when OpenCV finds none or refuses the input (a
    ``cv2.error`` on degenerate points: never raised from here)."""
    import cv2

    xa = np.ascontiguousarray(xa, np.float64).reshape(-1, 1, 2)
    xb = np.ascontiguousarray(xb, np.float64).reshape(-1, 1, 2)
    if len(xa) < 5 or not (np.isfinite(xa).all() and np.isfinite(xb).all()):
        return f"no essential matrix: {len(xa)} points, {'not all finite' if len(xa) >= 5 else '5 needed'}"
    try:
        E, mask = cv2.findEssentialMat(xa, xb, np.eye(3), method=cv2.USAC_ACCURATE, prob=0.999,
                                       threshold=float(threshold))
        if E is None or E.shape[1:] != (3,) or len(E) < 3 or mask is None:
            return "no essential matrix found"
        n_in, R, t, _ = cv2.recoverPose(E[:3], xa, xb, np.eye(3), mask=mask)
    except cv2.error as e:
        return opencv_failure("essential matrix", e)
    T_b_a = np.eye(4)  # recoverPose: x_b = R x_a + t
    T_b_a[:3, :3], T_b_a[:3, 3] = R, np.asarray(t, dtype=np.float64).reshape(3)
    if not np.isfinite(T_b_a).all():
        return "essential matrix gave a non-finite pose"
    return T_b_a, int(n_in)


def opencv_failure(what: str, e: Exception) -> str:
    """A one-line reason for a ``cv2.error``: what was attempted and OpenCV's own message (its
    assertion and function), without the source path."""
    msg = " ".join(str(e).split())
    if ") " in msg and "error:" in msg:  # "OpenCV(5.1.0) /path/file.cpp:1601: error: (-215:...) ... in function 'f'"
        msg = msg[msg.index("error:") + len("error:"):].strip()
    return f"{what}: {OPENCV_REFUSED} ({msg})"


def parallax_px(xa: np.ndarray, xb: np.ndarray) -> float:
    """How far matched points xa (n, 2) of view a and xb (n, 2) of view b (px) are from being one
    homography apart: the PARALLAX_QUANTILE quantile of the distances (px) between xb and the best
    homography's image of xa (RANSAC, 3 px). Views taken from one point (any rotation) give a few
    px at most, whatever the scene; views from points apart give tens to hundreds on a scene with
    depth (a flat scene alone gives none: one plane is one homography). Fewer than 8 points: 0;
    no homography (OpenCV finds none or refuses the points): inf."""
    import cv2

    if len(xa) < 8:
        return 0.0
    try:
        H, _ = cv2.findHomography(np.asarray(xa, np.float64).reshape(-1, 1, 2),
                                  np.asarray(xb, np.float64).reshape(-1, 1, 2), cv2.RANSAC, 3.0)
    except cv2.error:
        H = None
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
    if pair is None or not pair.ok or pair.n_inliers < conf.min_inliers:
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
    if pair is None or not pair.ok or pair.n_inliers < conf.min_inliers_alone or not len(centres_ref):
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
