"""Single-view core: crops, the DeepIM/CosyPose pose update, the disentangled symmetric loss,
PoseNet and its ONNX export (paper Appendix A)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cosy_cli.geometry.camera import crop_affine, crop_intrinsics, project
from cosy_cli.geometry.poses import make_pose
from cosy_cli.geometry.rotations import axis_angle_to_matrix, random_rotations
from cosy_cli.objects.symmetries import symmetry_set
from cosy_cli.singleview.networks.crops import (
    CANONICAL_ROTATION, boxes_from_detections, boxes_from_poses, canonical_depth_from_boxes, canonical_poses, crop_images, make_crops,
)
from cosy_cli.singleview.networks.losses import disentangled_loss, pad_symmetries, symmetric_l1_distance
from cosy_cli.singleview.networks.pose_update import (
    IDENTITY_OUTPUT, apply_update, apply_update_parts, identity_output, split_output, update_targets,
)

K = np.array([[600.0, 0, 319.5], [0, 610.0, 239.5], [0, 0, 1]])
CROP = (64, 48)  # (width, height) px: small for test speed


def _box_points(size=(80.0, 50.0, 30.0), n=300, seed=0):
    """Points (n, 3) mm on the surface of a box centred at the origin."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(-1, 1, (n, 3))
    ax = rng.integers(0, 3, n)
    p[np.arange(n), ax] = np.sign(p[np.arange(n), ax])
    return p * np.asarray(size) / 2


def _random_poses(n, rng, z=(400.0, 900.0), xy=80.0):
    R = random_rotations(n, rng)
    t = np.stack([rng.uniform(-xy, xy, n), rng.uniform(-xy, xy, n), rng.uniform(*z, n)], -1)
    return make_pose(R, t)


# ----------------------------------------------------------------------------------------- crops
def test_crop_intrinsics_match_the_affine_and_the_resampled_image():
    rng = np.random.default_rng(0)
    pts = np.stack([rng.uniform(-60, 60, 20), rng.uniform(-40, 40, 20), rng.uniform(500, 800, 20)], -1)
    boxes = np.array([[250.3, 180.7, 350.3, 255.7], [100.0, 50.0, 420.0, 290.0]])
    Kc = crop_intrinsics(K, boxes, CROP)
    A = crop_affine(boxes, CROP)
    uv = project(pts, K)  # (20, 2)
    via_affine = uv[None] @ A[:, :, :2].transpose(0, 2, 1) + A[:, None, :, 2]
    via_Kc = project(np.broadcast_to(pts, (2,) + pts.shape), Kc)
    np.testing.assert_allclose(via_Kc, via_affine, atol=1e-9)

    # A Gaussian blob drawn at a sub-pixel position lands where K_crop projects it.
    H, W = 480, 640
    X = np.array([12.0, -7.0, 600.0])
    u, v = project(X[None], K)[0]
    yy, xx = np.mgrid[0:H, 0:W]
    img = (255 * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 6.0 ** 2))).astype(np.uint8)
    img = np.repeat(img[..., None], 3, axis=-1)
    box = np.array([[u - 40.2, v - 25.1, u + 30.4, v + 30.0]])
    crop = crop_images(img, box, CROP)[0, ..., 0].astype(np.float64)
    crop[crop < 20] = 0
    gy, gx = np.mgrid[0:CROP[1], 0:CROP[0]]
    centroid = np.array([(gx * crop).sum(), (gy * crop).sum()]) / crop.sum()
    expected = project(X[None], crop_intrinsics(K, box, CROP)[0])[0]
    np.testing.assert_allclose(centroid, expected, atol=0.15)


def test_pose_crops_centre_the_object_origin_and_contain_the_object():
    rng = np.random.default_rng(1)
    pts = _box_points()
    T = _random_poses(5, rng)
    img = rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)
    cb = make_crops(img, K, CROP, T_cam_obj=T, points=pts)
    assert cb.crops.shape == (5, CROP[1], CROP[0], 3) and cb.crops.dtype == np.uint8 and cb.K.shape == (5, 3, 3)
    w = cb.boxes[:, 2] - cb.boxes[:, 0]
    h = cb.boxes[:, 3] - cb.boxes[:, 1]
    np.testing.assert_allclose(w / h, CROP[0] / CROP[1])
    origin = project(T[:, None, :3, 3], cb.K)[:, 0]
    np.testing.assert_allclose(origin, np.broadcast_to([(CROP[0] - 1) / 2, (CROP[1] - 1) / 2], origin.shape), atol=1e-9)
    cam = pts[None] @ T[:, :3, :3].transpose(0, 2, 1) + T[:, None, :3, 3]
    uv = project(cam, cb.K)
    assert (uv >= -0.5).all() and (uv[..., 0] <= CROP[0] - 0.5).all() and (uv[..., 1] <= CROP[1] - 0.5).all()
    # The projected extent fills the enlarged crop along its tighter axis: about 1 / 1.4.
    extent = np.maximum(np.abs(uv[..., 0] - origin[:, None, 0]).max(1) / (CROP[0] / 2),
                        np.abs(uv[..., 1] - origin[:, None, 1]).max(1) / (CROP[1] / 2))
    np.testing.assert_allclose(extent, 1 / 1.4, rtol=1e-6)
    # Per-crop images and a pixel-wise comparison with boxes_from_poses.
    np.testing.assert_allclose(boxes_from_poses(K, T, pts, CROP), cb.boxes)
    per = crop_images(np.stack([img] * 5), cb.boxes, CROP)
    np.testing.assert_array_equal(per, cb.crops)


def test_detection_crops_fit_the_aspect_and_contain_the_box():
    boxes = np.array([[100.0, 100.0, 140.0, 200.0], [10.0, 10.0, 10.0, 12.0]])
    win = boxes_from_detections(boxes, CROP)
    np.testing.assert_allclose((win[:, 2] - win[:, 0]) / (win[:, 3] - win[:, 1]), CROP[0] / CROP[1])
    assert (win[:, :2] <= boxes[:, :2]).all() and (win[:, 2:] >= boxes[:, 2:]).all()
    cb = make_crops(np.zeros((480, 640, 3), np.uint8), K, CROP, boxes=boxes)
    assert cb.crops.shape == (2, CROP[1], CROP[0], 3)


def test_canonical_pose_projects_to_the_box_centre():
    boxes = np.array([[100.0, 120.0, 180.0, 200.0], [0.0, 0.0, 640.0, 480.0], [600.0, 10.0, 630.0, 31.0]])
    T0 = canonical_poses(K, boxes)
    np.testing.assert_allclose(T0[:, 2, 3], 1000.0)
    np.testing.assert_allclose(T0[:, :3, :3], np.broadcast_to(CANONICAL_ROTATION, (3, 3, 3)))
    assert np.allclose(CANONICAL_ROTATION @ CANONICAL_ROTATION.T, np.eye(3)) and np.linalg.det(CANONICAL_ROTATION) > 0
    # Object z axis points up in the image (-y camera), seen from 30 deg above.
    np.testing.assert_allclose(CANONICAL_ROTATION[:, 2], [0, -np.cos(np.radians(30)), -np.sin(np.radians(30))],
                               atol=1e-12)
    centre = np.stack([(boxes[:, 0] + boxes[:, 2]) / 2 - 0.5, (boxes[:, 1] + boxes[:, 3]) / 2 - 0.5], -1)
    np.testing.assert_allclose(project(T0[:, None, :3, 3], K)[:, 0], centre, atol=1e-9)
    # ... and onto the centre of the crop made from that pose.
    cb = make_crops(np.zeros((480, 640, 3), np.uint8), K, CROP, T_cam_obj=T0, points=_box_points())
    np.testing.assert_allclose(project(T0[:, None, :3, 3], cb.K)[:, 0],
                               np.broadcast_to([(CROP[0] - 1) / 2, (CROP[1] - 1) / 2], (3, 2)), atol=1e-9)
    # Depth matched to the box: an object of diameter d spans max(w, h) px at that depth.
    z = canonical_depth_from_boxes(K, boxes, 100.0)
    np.testing.assert_allclose(z * np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]), 605.0 * 100.0)
    R = axis_angle_to_matrix(np.array([0.3, 0.0, 0.0]))
    T1 = canonical_poses(K, boxes, depth_mm=z, R=R)
    np.testing.assert_allclose(T1[:, 2, 3], z)
    np.testing.assert_allclose(project(T1[:, None, :3, 3], K)[:, 0], centre, atol=1e-9)


def test_canonical_pose_agrees_with_the_training_data():
    """The coarse network must see at test time the input pose it was trained with."""
    data = pytest.importorskip("cosy_cli.training.data")
    boxes = np.array([[100.0, 120.0, 180.0, 200.0], [600.0, 10.0, 630.0, 31.0]])
    np.testing.assert_allclose(canonical_poses(K, boxes, data.DEFAULT_COARSE_DISTANCE_MM),
                               data.canonical_pose(K, boxes), atol=1e-9)
    np.testing.assert_allclose(canonical_depth_from_boxes(K, boxes, 70.0), data.depth_from_box(K, boxes, 70.0))


# ----------------------------------------------------------------------------------- pose update
def _torch_setup(n=6, seed=0):
    rng = np.random.default_rng(seed)
    T_in = torch.tensor(_random_poses(n, rng))
    T_tg = torch.tensor(_random_poses(n, rng))
    boxes = np.stack([np.full(n, 200.0), np.full(n, 150.0), rng.uniform(300, 400, n), rng.uniform(250, 300, n)], -1)
    Kc = torch.tensor(crop_intrinsics(K, boxes, CROP))
    return T_in, T_tg, Kc


def test_pose_update_round_trip_and_identity():
    T_in, T_tg, Kc = _torch_setup()
    out = update_targets(T_in, T_tg, Kc)
    assert out.shape == (6, 9)
    torch.testing.assert_close(apply_update(T_in, out, Kc), T_tg, atol=1e-9, rtol=0)
    torch.testing.assert_close(apply_update(T_in, identity_output(6, torch.float64), Kc), T_in, atol=1e-12, rtol=0)
    assert tuple(identity_output(1)[0].tolist()) == IDENTITY_OUTPUT


def test_pose_update_follows_the_paper_equations():
    T = torch.tensor(make_pose(np.eye(3), np.array([30.0, -20.0, 500.0])))[None]
    Kc = torch.tensor([[[250.0, 0, 31.5], [0, 200.0, 23.5], [0, 0, 1]]], dtype=torch.float64)
    R = torch.tensor(axis_angle_to_matrix(np.array([0.0, 0.2, 0.0])))[None]
    out = apply_update_parts(T, Kc, R, torch.tensor([[10.0, -4.0]], dtype=torch.float64),
                             torch.tensor([1.2], dtype=torch.float64))[0]
    z = 1.2 * 500.0
    expected_t = [(10.0 / 250.0 + 30.0 / 500.0) * z, (-4.0 / 200.0 - 20.0 / 500.0) * z, z]
    torch.testing.assert_close(out[:3, 3], torch.tensor(expected_t, dtype=torch.float64))
    torch.testing.assert_close(out[:3, :3], R[0])  # R^{k+1} = R R^k with R^k = I
    # v_x, v_y are pixel shifts of the projected origin in the crop.
    uv0 = T[0, :3, 3] @ Kc[0].T
    uv1 = out[:3, 3] @ Kc[0].T
    torch.testing.assert_close(uv1[:2] / uv1[2] - uv0[:2] / uv0[2], torch.tensor([10.0, -4.0], dtype=torch.float64))
    # The rotation is applied in the camera frame (on the left).
    R0 = torch.tensor(axis_angle_to_matrix(np.array([0.5, 0.1, -0.3])))
    T2 = T.clone()
    T2[0, :3, :3] = R0
    out2 = apply_update_parts(T2, Kc, R, torch.zeros(1, 2, dtype=torch.float64), torch.ones(1, dtype=torch.float64))
    torch.testing.assert_close(out2[0, :3, :3], R[0] @ R0)


# ------------------------------------------------------------------------------------------ loss
def _symmetric_setup():
    """Points of an 80x50x30 mm box (D2 symmetric) and of a cylinder (axis z, 16 steps, flip)."""
    box_pts = torch.tensor(_box_points())
    box_syms = symmetry_set(np.stack([make_pose(axis_angle_to_matrix(np.pi * a), np.zeros(3)) for a in np.eye(3)]), [])
    rng = np.random.default_rng(3)
    ang = rng.uniform(0, 2 * np.pi, 300)
    cyl_pts = torch.tensor(np.stack([30 * np.cos(ang), 30 * np.sin(ang), rng.uniform(-40, 40, 300)], -1))
    flip = make_pose(axis_angle_to_matrix(np.array([np.pi, 0, 0])), np.zeros(3))[None]
    cyl_syms = symmetry_set(flip, [{"axis": np.array([0, 0, 1.0]), "offset": np.zeros(3)}], n_continuous=16)
    return (box_pts, torch.tensor(box_syms)), (cyl_pts, torch.tensor(cyl_syms))


def test_symmetric_distance_zero_up_to_symmetry_and_invariant():
    T_in, T_gt, Kc = _torch_setup(4)
    for pts, syms in _symmetric_setup():
        assert len(syms) in (4, 32)
        for S in syms:
            d = symmetric_l1_distance(T_gt @ S, T_gt, pts, syms)
            assert d.abs().max() < 1e-9
        d0 = symmetric_l1_distance(T_in, T_gt, pts, syms)
        assert (d0 > 1.0).all()
        for S in syms:
            torch.testing.assert_close(symmetric_l1_distance(T_in @ S, T_gt, pts, syms), d0)
        # Without symmetries, a symmetric pose is far.
        far = symmetric_l1_distance(T_gt @ syms[1], T_gt, pts, syms[:1])
        assert (far > 1.0).all()
        # A small rotation gives a small positive distance: L1 ~ sum of |dx|+|dy|+|dz|.
        dR = torch.tensor(make_pose(axis_angle_to_matrix(np.array([0.0, np.radians(2.0), 0.0])), np.zeros(3)))
        d_small = symmetric_l1_distance(T_gt @ dR, T_gt, pts, syms)  # about the object origin
        assert (d_small > 0.05).all() and (d_small < 5.0).all()


def test_symmetric_distance_gradient_is_the_plain_min_gradient():
    T_in, T_gt, _ = _torch_setup(3)
    _, (pts, syms) = _symmetric_setup()
    T1 = T_in.clone().requires_grad_(True)
    symmetric_l1_distance(T1, T_gt, pts, syms).sum().backward()
    T2 = T_in.clone().requires_grad_(True)
    p = torch.einsum("bij,snj->bsni", T2[:, :3, :3], (pts @ syms[:, :3, :3].transpose(-1, -2)
                                                       + syms[:, None, :3, 3])) + T2[:, None, None, :3, 3]
    g = pts @ T_gt[:, :3, :3].transpose(-1, -2) + T_gt[:, None, :3, 3]
    naive = (p - g[:, None]).abs().sum(-1).mean(-1).min(-1).values
    naive.sum().backward()
    torch.testing.assert_close(symmetric_l1_distance(T_in, T_gt, pts, syms), naive.detach())
    torch.testing.assert_close(T1.grad, T2.grad)


def test_disentangled_terms_respond_only_to_their_component():
    T_in, T_gt, Kc = _torch_setup(4)
    (pts, syms), _ = _symmetric_setup()
    tgt = update_targets(T_in, T_gt, Kc)
    zero = disentangled_loss(tgt, T_in, T_gt, Kc, pts, syms)
    for k in ("xy", "z", "rot", "total"):
        assert zero[k].abs().max() < 1e-9
    # Reaching the GT up to a symmetry is also zero loss.
    tgt_sym = update_targets(T_in, T_gt @ syms[2], Kc)
    assert disentangled_loss(tgt_sym, T_in, T_gt, Kc, pts, syms)["total"].abs().max() < 1e-9
    perturb = {"xy": (6, 8, 3.0), "z": (8, 9, 0.05), "rot": (0, 6, 0.1)}
    for name, (a, b, eps) in perturb.items():
        out = tgt.clone()
        out[:, a:b] += eps
        terms = disentangled_loss(out, T_in, T_gt, Kc, pts, syms)
        for k in ("xy", "z", "rot"):
            if k == name:
                assert (terms[k] > 0.1).all(), (name, terms)
            else:
                assert terms[k].abs().max() < 1e-9, (name, k, terms)
        torch.testing.assert_close(terms["total"], terms[name])
    # Per-sample symmetry sets padded with identities give the per-sample losses.
    (bp, bs), (cp, cs) = _symmetric_setup()
    out = tgt + 0.02
    pts2 = torch.stack([bp, cp, bp, cp])
    sym2 = pad_symmetries([bs, cs, bs, cs], dtype=torch.float64)
    both = disentangled_loss(out, T_in, T_gt, Kc, pts2, sym2)["total"]
    for i, (p, s) in enumerate([(bp, bs), (cp, cs), (bp, bs), (cp, cs)]):
        one = disentangled_loss(out[i:i + 1], T_in[i:i + 1], T_gt[i:i + 1], Kc[i:i + 1], p, s)["total"]
        torch.testing.assert_close(both[i:i + 1], one)


# ----------------------------------------------------------------------------- network and ONNX
def _calibrated_net(kind="refiner", n_inputs=6, seed=0):
    """A PoseNet with learned-looking BatchNorm statistics and a random head (so outputs depend
    on the input in eval mode, as a trained network's do)."""
    from cosy_cli.singleview.networks.model import PoseNet

    torch.manual_seed(seed)
    net = PoseNet(kind, "efficientnet-b0", n_inputs, CROP)
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.momentum = None  # cumulative average
    net.train()
    with torch.no_grad():
        for _ in range(2):
            net(torch.rand(8, n_inputs, CROP[1], CROP[0]))
        torch.nn.init.normal_(net.head.weight, std=0.05)
    return net.eval()


def test_posenet_starts_at_identity_and_overfits_a_tiny_batch():
    from cosy_cli.singleview.networks.model import PoseNet, prepare_inputs

    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    net = PoseNet("coarse", "efficientnet-b0", 6, CROP)
    assert net.kind == "coarse"
    obs = rng.integers(0, 256, (4, CROP[1], CROP[0], 3), dtype=np.uint8)
    ren = rng.integers(0, 256, (4, CROP[1], CROP[0], 3), dtype=np.uint8)
    x = torch.tensor(prepare_inputs(obs, ren))
    assert x.shape == (4, 6, CROP[1], CROP[0]) and 0 <= float(x.min()) and float(x.max()) <= 1
    out0 = net(x)
    torch.testing.assert_close(out0, identity_output(4))

    # Refiner-like targets: GT = input perturbed by up to 15 deg, 10 mm in x, y and 5 % in depth.
    T_in, _, Kc = (t.float() for t in _torch_setup(4, seed=5))
    rv = rng.normal(size=(4, 3))
    rv *= np.radians(rng.uniform(5, 15, (4, 1))) / np.linalg.norm(rv, axis=1, keepdims=True)
    dT = make_pose(axis_angle_to_matrix(rv), np.zeros((4, 3)))
    T_gt = T_in.double() @ torch.tensor(dT)
    T_gt[:, :2, 3] += torch.tensor(rng.uniform(-10, 10, (4, 2)))
    T_gt[:, 2, 3] *= torch.tensor(rng.uniform(0.95, 1.05, 4))
    T_gt = T_gt.float()
    (pts, syms), _ = _symmetric_setup()
    pts, syms = pts.float()[:100], syms.float()
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    losses = []
    for _ in range(30):
        loss = disentangled_loss(net(x), T_in, T_gt, Kc, pts, syms)["total"].mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    # Noisy (train-mode BatchNorm on 4 samples, stochastic depth) but clearly lower: ~43 -> ~12 mm.
    assert np.mean(losses[-5:]) < 0.5 * losses[0], losses


def test_posenet_seven_channels_and_checkpoint_round_trip():
    from cosy_cli.singleview.networks.model import PoseNet, prepare_inputs

    net = _calibrated_net(n_inputs=7)
    rng = np.random.default_rng(1)
    obs = rng.integers(0, 256, (2, CROP[1], CROP[0], 3), dtype=np.uint8)
    x = torch.tensor(prepare_inputs(obs, obs, masks=rng.random((2, CROP[1], CROP[0])) > 0.5))
    assert x.shape[1] == 7
    net2 = PoseNet.from_checkpoint(net.checkpoint()).eval()
    with torch.no_grad():
        torch.testing.assert_close(net2(x), net(x))
    with pytest.raises(ValueError):
        PoseNet("bogus")


@pytest.mark.parametrize("dynamo", [False, True], ids=["torchscript", "dynamo"])
def test_onnx_matches_torch(tmp_path, dynamo):
    from cosy_cli.errors import CosyError
    from cosy_cli.singleview.networks.onnx import OnnxPoseNet, export_onnx

    net = _calibrated_net()
    path = export_onnx(net, tmp_path / "refiner.onnx", dynamo=dynamo)
    runner = OnnxPoseNet(path)
    assert runner.kind == "refiner" and runner.config.crop_size == CROP
    for b in (1, 3):
        x = torch.rand(b, 6, CROP[1], CROP[0])
        with torch.no_grad():
            y = net(x).numpy()
        assert y.std(0).max() > 1e-3 or b == 1  # outputs depend on the input
        np.testing.assert_allclose(runner(x.numpy()), y, atol=1e-4, rtol=0)
    # The export left the torch model trainable (memory-efficient Swish) and unchanged.
    assert net.training is False and any(p.requires_grad for p in net.parameters())
    with pytest.raises(ValueError):
        runner(np.zeros((1, 6, 10, 10), np.float32))
    with pytest.raises(CosyError):
        OnnxPoseNet(tmp_path / "missing.onnx")
