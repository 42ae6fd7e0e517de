"""The frame of the figures' top view: which way is up in a group's world, and two horizontal axes.

A recovered world is the frame of one of its cameras (or the dataset's world with known cameras),
so its x-y plane is what that camera sees head-on: a front view for a camera that looks ahead.
The top view instead looks down the scene's up direction, estimated as

1. the normal of the plane the objects rest on, when one can be found: the lowest points of the
   objects (their model points posed in the world, lowest along the current estimate of up) are
   fitted with a plane robustly (every triplet, then a least-squares fit of the inliers), and the
   estimate is refined with that plane's normal a few times, starting from the cameras' up and
   from their backward direction (cameras that look straight down). The plane is kept when at least
   three objects, half of them or more, rest on it, their contacts span an area (not a line),
   every camera is above it (the cameras look at the objects from above the table) and at most a
   fifth of the objects reach below it;
2. else the cameras' mean up direction (OpenCV cameras: -y of each camera in the world), which is
   the true vertical for cameras held upright and level, and tilted by the pitch of cameras that
   look down;
3. else (cameras' up directions cancel out) the up direction of the reference camera.

The plot axes (e1, e2) are horizontal: e1 is the reference camera's x (its image's rightwards)
made horizontal, e2 = up x e1, so (e1, e2, up) is right-handed and the plot is the scene seen
from above (not mirrored), with the reference camera looking roughly towards +e2.

Pure numpy; lengths in mm; poses ``T_world_x`` (4x4).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

SUPPORT_PLANE = "support plane"
CAMERAS_UP = "cameras' mean up"
CAMERA_UP = "camera's up"


@dataclass
class TopViewFrame:
    up: np.ndarray  # (3,) unit, pointing from the scene towards the cameras' side
    e1: np.ndarray  # (3,) unit, horizontal: plot x
    e2: np.ndarray  # (3,) unit, horizontal: plot y; e1 x e2 = up
    source: str  # SUPPORT_PLANE, CAMERAS_UP or CAMERA_UP
    plane_point: np.ndarray | None = None  # a point of the support plane (world, mm)
    support_objects: int = 0  # objects found resting on the support plane

    @property
    def P(self) -> np.ndarray:
        """(2, 3): world point -> plot coordinates (mm)."""
        return np.stack([self.e1, self.e2])

    def describe(self, camera: str = "the camera", objects: str = "objects") -> str:
        """How up was chosen, for the figure's title; ``camera``: the reference camera's name,
        ``objects``: what the objects that gave the plane are."""
        if self.source == SUPPORT_PLANE:
            return f"looking down the support plane's normal ({self.support_objects} {objects} on it)"
        if self.source == CAMERAS_UP:
            return "looking down the cameras' mean up (-y)"
        return f"looking down {camera}'s up (-y)"


def _unit(v) -> np.ndarray | None:
    v = np.asarray(v, dtype=np.float64)
    n = float(np.linalg.norm(v))
    return v / n if n > 1e-9 else None


def cameras_up(cam_T: list[np.ndarray], ref: int = 0) -> tuple[np.ndarray, str]:
    """(up, source): the mean of the cameras' -y axes in the world, or the reference camera's
    -y when they cancel out (|mean| < 0.3); +z of the world without cameras."""
    if not cam_T:
        return np.array([0.0, 0.0, 1.0]), CAMERA_UP
    ups = np.array([-np.asarray(T)[:3, 1] for T in cam_T], dtype=np.float64)
    m = ups.mean(0)
    if len(ups) > 1 and np.linalg.norm(m) >= 0.3:
        return m / np.linalg.norm(m), CAMERAS_UP
    u = _unit(ups[min(ref, len(ups) - 1)])
    return (u if u is not None else np.array([0.0, 0.0, 1.0])), CAMERA_UP


def lowest_points(objects_world: list[np.ndarray], up: np.ndarray) -> np.ndarray:
    """(n, 3): for each object (its points in the world, (k, 3)), its lowest point along ``up``
    (the mean of the points within 1 mm of the lowest, so a flat base gives its middle)."""
    out = []
    for X in objects_world:
        X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
        h = X @ up
        out.append(X[h <= h.min() + 1.0].mean(0))
    return np.array(out).reshape(-1, 3)


def fit_plane(points: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Robust plane through ``points`` (n, 3): (unit normal, a point on it, inlier mask), or None
    when fewer than 3 points. Every triplet (a sample of 500 when there are many) proposes a
    plane; the one with most points within ``tol`` mm wins (ties: the smaller sum of distances),
    then its inliers are fitted by least squares. The normal's sign is arbitrary."""
    X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(X)
    if n < 3:
        return None
    trip = list(combinations(range(n), 3))
    if len(trip) > 500:
        rng = np.random.default_rng(0)
        trip = [tuple(t) for t in rng.choice(n, size=(500, 3))]
    best = None
    for i, j, k in trip:
        nrm = _unit(np.cross(X[j] - X[i], X[k] - X[i]))
        if nrm is None:
            continue
        d = np.abs((X - X[i]) @ nrm)
        inl = d <= tol
        key = (int(inl.sum()), -float(np.minimum(d, tol).sum()))
        if best is None or key > best[0]:
            best = (key, inl)
    if best is None:
        return None
    inl = best[1]
    c = X[inl].mean(0)
    _, _, vt = np.linalg.svd(X[inl] - c)
    nrm = vt[2]
    inl = np.abs((X - c) @ nrm) <= tol
    return nrm, c, inl


def support_plane(objects_world: list[np.ndarray], cam_centres: np.ndarray, up0: np.ndarray, *,
                  tol: float | None = None, iterations: int = 4) -> tuple[np.ndarray, np.ndarray, int] | None:
    """(up, point, number of objects on it) of the plane the objects rest on, or None when no
    plane passes the checks of the module docstring. ``up0``: the first estimate of up (the lowest
    points are taken along it); ``tol``: mm from the plane for an object to rest on it (default:
    max(10, 3 % of the objects' spread))."""
    if len(objects_world) < 3:
        return None
    C = np.asarray(cam_centres, dtype=np.float64).reshape(-1, 3)
    up = _unit(up0)
    if up is None:
        return None
    result = None
    for _ in range(iterations):
        B = lowest_points(objects_world, up)
        spread = float(np.ptp(B, axis=0).max())
        t = tol if tol is not None else max(10.0, 0.03 * spread)
        fit = fit_plane(B, t)
        if fit is None:
            return None
        nrm, p0, inl = fit
        if np.dot(nrm, up) < 0:
            nrm = -nrm
        k = int(inl.sum())
        if k < 3 or k < 0.5 * len(B):
            return None
        # the contacts span an area: the second principal spread is not small next to the first
        sv = np.linalg.svd(B[inl] - B[inl].mean(0), compute_uv=False) / np.sqrt(k)
        if sv[1] < max(0.15 * sv[0], 5.0):
            return None
        # the cameras look at the objects from above
        if len(C) and not np.all((C - p0) @ nrm > t):
            return None
        # nothing rests under a support: at most a fifth of the objects reach below it (pose errors)
        below = sum(float(np.min((np.asarray(X).reshape(-1, 3) - p0) @ nrm)) < -2 * t for X in objects_world)
        if below > 0.2 * len(objects_world):
            return None
        result = (nrm, p0, k)
        if np.dot(nrm, up) > np.cos(np.radians(0.5)):
            break
        up = nrm
    return result


def top_view_frame(cam_T: list[np.ndarray], objects_world: list[np.ndarray] | None = None, *,
                   ref: int = 0) -> TopViewFrame:
    """The top view's frame of a group: ``cam_T`` its cameras (T_world_cam), ``objects_world`` each
    object's model points in the world ((k, 3) arrays; its centre alone is not enough to find the
    plane it rests on), ``ref`` the index of the camera whose right is the plot's +x (the gauge)."""
    objects_world = list(objects_world or [])
    C = np.array([np.asarray(T)[:3, 3] for T in cam_T]).reshape(-1, 3)
    up, source = cameras_up(cam_T, ref)
    # the lowest points are taken along a first guess of up: the cameras' up, and their mean
    # backward direction (for cameras looking straight down, whose up is horizontal); the plane
    # more objects rest on wins
    plane = None
    back = -np.mean([np.asarray(T)[:3, 2] for T in cam_T], axis=0) if cam_T else np.zeros(3)
    for up0 in [up] + ([back] if np.linalg.norm(back) > 0.3 else []):
        p = support_plane(objects_world, C, up0)
        if p is not None and (plane is None or p[2] > plane[2]):
            plane = p
    point = None
    n_on = 0
    if plane is not None:
        up, point, n_on = plane
        source = SUPPORT_PLANE
    x = np.asarray(cam_T[min(ref, len(cam_T) - 1)])[:3, 0] if cam_T else np.array([1.0, 0, 0])
    e1 = _unit(x - np.dot(x, up) * up)
    if e1 is None:  # the reference camera's x is vertical: its z made horizontal, turned to the right
        z = np.asarray(cam_T[min(ref, len(cam_T) - 1)])[:3, 2] if cam_T else np.array([0, 1.0, 0])
        e2 = _unit(z - np.dot(z, up) * up)
        if e2 is None:
            e2 = _unit(np.cross(up, [1.0, 0, 0])) if abs(up[0]) < 0.9 else _unit(np.cross(up, [0, 1.0, 0]))
        e1 = np.cross(e2, up)
    e2 = np.cross(up, e1)
    return TopViewFrame(up=up, e1=e1, e2=e2, source=source, plane_point=point, support_objects=n_on)
