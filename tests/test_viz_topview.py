"""The top view's frame (cosy_cli.viz.topview) on synthetic tabletop scenes: up from the plane the
objects rest on, else from the cameras; horizontal plot axes forming a right-handed frame."""

from __future__ import annotations

import numpy as np
import pytest

from cosy_cli.geometry.poses import invert
from cosy_cli.viz import topview as tv

UP = np.array([0.0, 0.0, 1.0])  # the table's normal in the synthetic scene's own frame (table: z = 0)


def look_at(centre, target, up=UP) -> np.ndarray:
    """T_world_cam of an OpenCV camera (x right, y down, z forward) at ``centre`` looking at
    ``target``, held upright (no roll)."""
    z = np.asarray(target, float) - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = centre
    return T


def camera(azimuth_deg, elevation_deg, dist, target=(0.0, 0.0, 0.0)) -> np.ndarray:
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    c = np.asarray(target) + dist * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    return look_at(c, target)


def box(x, y, size, yaw_deg, n=6) -> np.ndarray:
    """Points on the surface of a box (w, d, h) resting on the table at (x, y), turned by yaw."""
    w, d, h = size
    g = np.linspace(-0.5, 0.5, n)
    pts = np.array([[a, b, c] for a in g for b in g for c in g])
    pts = pts[np.abs(pts).max(1) > 0.49] * [w, d, h] + [0, 0, h / 2]
    t = np.radians(yaw_deg)
    R = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])
    return pts @ R.T + [x, y, 0]


def ellipsoid(x, y, radii, yaw_deg, n=24) -> np.ndarray:
    """Points on an ellipsoid (semi-axes a, b, c) resting on the table at (x, y), turned by yaw."""
    a, b, c = radii
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, n, endpoint=False), np.linspace(0, np.pi, n))
    pts = np.c_[(a * np.sin(v) * np.cos(u)).ravel(), (b * np.sin(v) * np.sin(u)).ravel(), (c * np.cos(v)).ravel() + c]
    t = np.radians(yaw_deg)
    R = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])
    return pts @ R.T + [x, y, 0]


def in_camera0(cams: list[np.ndarray], objects: list[np.ndarray]):
    """The scene as the pipeline recovers it: world = camera 0's frame. Returns (cams, objects,
    the table's normal, a rotation taking scene directions to that world)."""
    A = invert(cams[0])
    R = A[:3, :3]
    return ([A @ T for T in cams], [X @ R.T + A[:3, 3] for X in objects], R @ UP, R)


def angle_deg(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def check_axes(f: tv.TopViewFrame):
    """Orthonormal, right-handed (e1 x e2 = up: the scene seen from above, not mirrored)."""
    M = np.stack([f.e1, f.e2, f.up])
    np.testing.assert_allclose(M @ M.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(M) == pytest.approx(1.0)


# a table with objects of very different heights (a tall bottle, flat boxes) spread over 40 x 40 cm
TABLE = [((-150, -120), (60, 90, 30), 10), ((160, -140), (70, 70, 240), 35), ((140, 170), (120, 50, 20), 70),
         ((-170, 150), (50, 50, 160), 0), ((10, 20), (90, 90, 60), 50)]


def test_oblique_cameras_over_a_table_look_down_the_table_normal():
    objs = [box(x, y, s, yaw) for (x, y), s, yaw in TABLE]
    cams = [camera(az, 40, 700) for az in (-90, -60, -120)]  # looking down 40 degrees at the table
    cams_w, objs_w, up_true, R = in_camera0(cams, objs)
    f = tv.top_view_frame(cams_w, objs_w)
    assert f.source == tv.SUPPORT_PLANE and f.support_objects == 5
    assert angle_deg(f.up, up_true) < 1.0
    check_axes(f)
    # the table seen from above: the objects' centres keep their spread on the table in both plot axes
    centres = np.array([X.mean(0) for X in objs_w]) @ f.P.T
    assert np.ptp(centres, axis=0).min() > 0.8 * 320
    # the cameras are above the table, around the objects; the gauge camera's right is the plot's +x
    heights = (np.array([T[:3, 3] for T in cams_w]) - f.plane_point) @ f.up
    np.testing.assert_allclose(heights, 700 * np.sin(np.radians(40)), rtol=0.05)
    assert np.dot(f.e1, cams_w[0][:3, 0]) > 0.99
    cam_xy = np.array([T[:3, 3] for T in cams_w]) @ f.P.T
    assert np.all(np.linalg.norm(cam_xy - centres.mean(0), axis=1) > 400)
    assert "support plane" in f.describe()


def test_cameras_looking_straight_down_find_the_table():
    # their up (-y) is nearly horizontal: the lowest points along it are the sides of round objects
    # (at half their height), not their bases
    objs = [ellipsoid(x, y, (s[0] / 2, s[1] / 2, s[2] / 2), yaw) for (x, y), s, yaw in TABLE]
    cams = [camera(az, 88, 600) for az in (-90, -80)]
    cams_w, objs_w, up_true, _ = in_camera0(cams, objs)
    f = tv.top_view_frame(cams_w, objs_w)
    assert f.source == tv.SUPPORT_PLANE and angle_deg(f.up, up_true) < 1.0
    check_axes(f)


def test_camera_looking_ahead_gets_a_view_from_above_not_a_front_view():
    # one camera looking almost level (10 degrees down) at two objects, one behind the other; no
    # support plane (two objects): up from the camera. A front view (the camera's x-y plane) would
    # squeeze the 300 mm between them to 300 sin(10 deg) = 52 mm.
    objs = [box(0, -150, (60, 60, 80), 0), box(0, 150, (60, 60, 80), 0)]
    cams = [camera(-90, 10, 800)]
    cams_w, objs_w, up_true, _ = in_camera0(cams, objs)
    f = tv.top_view_frame(cams_w, objs_w)
    assert f.source == tv.CAMERA_UP
    assert angle_deg(f.up, up_true) < 10.5
    check_axes(f)
    c = np.array([X.mean(0) for X in objs_w]) @ f.P.T
    assert abs(c[1, 1] - c[0, 1]) > 0.95 * 300  # depth along the plot's y, the far object above
    assert abs(c[1, 0] - c[0, 0]) < 10
    cam = cams_w[0][:3, 3] @ f.P.T
    assert cam[1] < c[0, 1] < c[1, 1]  # the camera below (behind) both in the plot


def test_several_level_cameras_use_their_mean_up():
    cams = [camera(az, 5, 900) for az in (-100, -80, -60)]
    cams_w, _, up_true, _ = in_camera0(cams, [])
    f = tv.top_view_frame(cams_w, [], ref=1)
    assert f.source == tv.CAMERAS_UP and angle_deg(f.up, up_true) < 5.5
    check_axes(f)
    assert np.dot(f.e1, cams_w[1][:3, 0]) > 0.99  # the reference camera's right
    assert "mean up" in f.describe()


def test_objects_in_a_row_give_no_plane():
    objs = [box(x, 0, (50, 50, 50), 0) for x in (-200, 0, 200, 400)]  # collinear contacts: no plane
    cams_w, objs_w, up_true, _ = in_camera0([camera(-90, 30, 700), camera(-70, 30, 700)], objs)
    f = tv.top_view_frame(cams_w, objs_w)
    assert f.source == tv.CAMERAS_UP
    check_axes(f)


def test_cameras_under_the_plane_reject_it():
    objs = [box(x, y, s, yaw) for (x, y), s, yaw in TABLE]
    cams = [camera(-90, -30, 700), camera(-60, -30, 700)]  # looking up at the table from below
    cams_w, objs_w, _, _ = in_camera0(cams, objs)
    assert tv.top_view_frame(cams_w, objs_w).source != tv.SUPPORT_PLANE


def test_fit_plane_ignores_an_object_off_the_table():
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-200, 200, (7, 2)), rng.normal(0, 1.0, 7)]
    pts = np.vstack([pts, [[50, 50, 180]]])  # one object held in the air
    n, p, inl = tv.fit_plane(pts, tol=10.0)
    assert angle_deg(n, UP) < 1.5 or angle_deg(-n, UP) < 1.5
    assert inl.tolist() == [True] * 7 + [False]
    assert tv.fit_plane(pts[:2], tol=10.0) is None


def test_lowest_points_of_a_box_are_its_base():
    X = box(30, -40, (60, 80, 100), 25)
    b = tv.lowest_points([X], UP)[0]
    np.testing.assert_allclose(b, [30, -40, 0], atol=1e-9)
