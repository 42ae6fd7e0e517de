import numpy as np
import pytest
import torch

from cosy_cli import geometry as G
from cosy_cli.geometry import torch_ops as TG
from cosy_cli.objects import symmetry_set


@pytest.fixture
def rng():
    return np.random.default_rng(0)


def random_poses(n, rng, t_scale=100.0):
    return G.make_pose(G.random_rotations(n, rng), rng.normal(size=(n, 3)) * t_scale)


def test_invert_compose(rng):
    T = random_poses(10, rng)
    I = G.compose(T, G.invert(T))
    assert np.allclose(I, np.eye(4), atol=1e-12)
    T_a_b, T_b_c = random_poses(2, rng)
    p = rng.normal(size=(5, 3))
    assert np.allclose(G.transform_points(G.compose(T_a_b, T_b_c), p),
                       G.transform_points(T_a_b, G.transform_points(T_b_c, p)))


def test_rotation_conversions_round_trip(rng):
    R = G.random_rotations(200, rng)
    assert np.allclose(G.quaternion_to_matrix(G.matrix_to_quaternion(R)), R, atol=1e-12)
    assert np.allclose(G.axis_angle_to_matrix(G.matrix_to_axis_angle(R)), R, atol=1e-9)
    assert np.allclose(G.rot6d_to_matrix(G.matrix_to_rot6d(R)), R, atol=1e-12)
    assert G.is_rotation(R).all()


def test_rotation_edge_cases():
    # angle pi and angle 0 are where naive conversions break
    for v in ([np.pi, 0, 0], [0, np.pi, 0], [0, 0, 1e-12], [0, 0, 0], [np.pi / np.sqrt(2), np.pi / np.sqrt(2), 0]):
        R = G.axis_angle_to_matrix(np.array(v))
        assert np.allclose(G.axis_angle_to_matrix(G.matrix_to_axis_angle(R)), R, atol=1e-9)
        assert np.isclose(np.degrees(G.rotation_angle(R)), np.degrees(np.linalg.norm(v)), atol=1e-6)


def test_axis_angle_known_value():
    R = G.axis_angle_to_matrix(np.array([0, 0, np.pi / 2]))
    assert np.allclose(R @ [1, 0, 0], [0, 1, 0])


def test_rot6d_gram_schmidt_of_noisy_input(rng):
    R = G.random_rotations(5, rng)
    x = G.matrix_to_rot6d(R) + rng.normal(size=(5, 6)) * 1e-3
    assert G.is_rotation(G.rot6d_to_matrix(x), tol=1e-9).all()


def test_torch_matches_numpy(rng):
    R = G.random_rotations(8, rng)
    x = G.matrix_to_rot6d(R) + rng.normal(size=(8, 6)) * 0.1
    assert np.allclose(TG.rot6d_to_matrix(torch.tensor(x)).numpy(), G.rot6d_to_matrix(x), atol=1e-12)
    v = rng.normal(size=(8, 3))
    assert np.allclose(TG.axis_angle_to_matrix(torch.tensor(v)).numpy(), G.axis_angle_to_matrix(v), atol=1e-12)
    T = random_poses(8, rng)
    assert np.allclose(TG.invert(torch.tensor(T)).numpy(), G.invert(T), atol=1e-12)
    p = rng.normal(size=(8, 20, 3)) * 50 + [0, 0, 500]
    K = np.array([[500, 0, 320], [0, 510, 240], [0, 0, 1.0]])
    assert np.allclose(TG.project(torch.tensor(p), torch.tensor(K)).numpy(), G.project(p, K), atol=1e-9)


def test_project_known_point():
    K = np.array([[600, 0, 320], [0, 600, 240], [0, 0, 1.0]])
    uv = G.project(np.array([[100.0, -50.0, 1000.0]]), K)
    assert np.allclose(uv, [[380, 210]])


def test_crop_intrinsics_match_affine_resampling(rng):
    """A point projected with K and mapped by the crop affine lands where K_crop projects it."""
    K = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1.0]])
    boxes = np.array([[100.0, 80.0, 260.0, 200.0], [10.5, 20.25, 50.5, 50.25]])
    Kc = G.crop_intrinsics(K, boxes, (128, 96))
    A = G.crop_affine(boxes, (128, 96))
    p = rng.normal(size=(30, 3)) * 30 + [0, 0, 600]
    uv = G.project(p, K)
    for i in range(len(boxes)):
        uv_crop = uv @ A[i, :, :2].T + A[i, :, 2]
        assert np.allclose(G.project(p, Kc[i]), uv_crop, atol=1e-9)
    # the box's edges map onto the crop's edges (pixel-edge coordinates)
    corner_edges = np.array([[boxes[0, 0] - 0.5, boxes[0, 1] - 0.5], [boxes[0, 2] - 0.5, boxes[0, 3] - 0.5]])
    mapped = corner_edges @ A[0, :, :2].T + A[0, :, 2]
    assert np.allclose(mapped, [[-0.5, -0.5], [127.5, 95.5]])


def test_fit_box_to_aspect():
    b = G.fit_box_to_aspect(np.array([[0, 0, 10, 40.0]]), aspect=4 / 3, scale=1.0)[0]
    w, h = b[2] - b[0], b[3] - b[1]
    assert np.isclose(w / h, 4 / 3) and np.isclose(h, 40) and np.allclose((b[:2] + b[2:]) / 2, [5, 20])


def test_look_at_is_opencv_camera():
    T_world_cam = G.look_at(np.array([0, -500.0, 500.0]), np.zeros(3))
    T_cam_world = G.invert(T_world_cam)
    target_cam = G.transform_points(T_cam_world, np.zeros((1, 3)))[0]
    assert np.allclose(target_cam[:2], 0, atol=1e-9) and target_cam[2] > 0
    # a point above the target (world +z) appears higher in the image: smaller y
    above = G.transform_points(T_cam_world, np.array([[0, 0, 50.0]]))[0]
    assert above[1] < 0
    assert G.is_rotation(T_world_cam[:3, :3]).all()


def brute_force_dl(T1, T2, X, S):
    best = np.inf
    for s in S:
        d = np.mean([np.linalg.norm((T1 @ s @ np.append(x, 1))[:3] - (T2 @ np.append(x, 1))[:3]) for x in X])
        best = min(best, d)
    return best


def test_symmetric_distance_against_brute_force(rng):
    X = rng.normal(size=(40, 3)) * 30
    S = symmetry_set(np.array([G.make_pose(G.axis_angle_to_matrix(np.array([np.pi, 0, 0])), [0, 0, 4.0])]),
                     [{"axis": np.array([0, 0, 1.0]), "offset": np.array([0, 0, 2.0])}], n_continuous=8)
    T1 = random_poses(6, rng)
    T2 = random_poses(6, rng)
    d, idx = G.symmetric_distance(T1, T2, X, S, return_index=True)
    for i in range(6):
        assert np.isclose(d[i], brute_force_dl(T1[i], T2[i], X, S))
        assert np.isclose(G.symmetric_distances_all(T1[i], T2[i], X, S)[idx[i]], d[i])
    # zero for a pose and its symmetric twin
    assert np.allclose(G.symmetric_distance(T1 @ S[5], T1, X, S), 0, atol=1e-9)
    # torch version agrees
    dt = TG.symmetric_distances_all(torch.tensor(T1), torch.tensor(T2), torch.tensor(X), torch.tensor(S)).numpy()
    assert np.allclose(dt.min(-1), d)


def test_symmetric_distance_batched_many(rng):
    X = rng.normal(size=(32, 3)) * 30
    S = symmetry_set(np.zeros((0, 4, 4)), [{"axis": [0, 0, 1.0], "offset": [0, 0, 0]}], 64)
    T1 = random_poses(5000, rng)
    d = G.symmetric_distance(T1, T1, X, S)
    assert d.shape == (5000,) and np.allclose(d, 0)
    d2 = G.symmetric_distance(T1[:, None], T1[None, :7], X, S)
    assert d2.shape == (5000, 7)


def test_projected_boxes_bound_the_projection_in_pixel_edge_coordinates():
    """The box of a posed point set: the extreme projections + 0.5 (OpenCV centres at integers,
    pixel i spans [i, i + 1)), clipped to the image; NaN behind the camera; lists of sets of
    different sizes give the same boxes as each set alone."""
    from cosy_cli.geometry.camera import projected_boxes

    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    P = np.array([[x, y, z] for x in (-10.0, 10.0) for y in (-20.0, 20.0) for z in (-5.0, 5.0)])
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 1000.0]
    b = projected_boxes(P[None], T[None], K, 640, 480)[0]
    # nearest face (z = 995 mm) gives the extremes: 320 +- 10 * 500 / 995, 240 +- 20 * 500 / 995
    np.testing.assert_allclose(b, [320.5 - 5000 / 995, 240.5 - 10000 / 995, 320.5 + 5000 / 995, 240.5 + 10000 / 995])
    T2 = T.copy()
    T2[:3, 3] = [-330.0 * 2, 0.0, 1000.0]  # far to the left: clipped at x = 0
    T3 = T.copy()
    T3[2, 3] = -5.0  # straddles the camera plane
    out = projected_boxes([P, P[:2], P], np.stack([T, T, T2]), K, 640, 480)
    np.testing.assert_allclose(out[0], b)
    np.testing.assert_allclose(out[1], projected_boxes(P[None, :2], T[None], K, 640, 480)[0])
    assert out[2, 0] == out[2, 2] == 0.0
    assert np.isnan(projected_boxes(P[None], T3[None], K, 640, 480)).all()
