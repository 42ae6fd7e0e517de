"""Tests of cosy_cli.training.data: on-the-fly render-and-compare training samples."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cosy_cli.rendering import SceneRenderer  # noqa: F401  (selects the GL platform first)
from cosy_cli.geometry import make_pose, project, transform_points  # noqa: E402
from cosy_cli.geometry.rotations import matrix_to_axis_angle  # noqa: E402
from cosy_cli.training.data import (  # noqa: E402
    CANONICAL_ROTATION, Perturbation, SampleGenerator, TrainingStream, canonical_pose, make_loader, perturb_poses,
    synthetic_source,
)

CROP = (128, 96)


@pytest.fixture(scope="module")
def source():
    return synthetic_source()


@pytest.fixture(scope="module")
def clean_gen(source):
    """Refiner samples without occluders and without input noise (T_input == T_gt)."""
    meshes, syms = source
    g = SampleGenerator(meshes, symmetries=syms, seed=3, curriculum=0.0, occluder_probs=(1.0,), resting=True)
    yield g
    g.close()


def test_shapes_and_dtypes(source):
    meshes, syms = source
    for kind in ("refiner", "coarse"):
        g = SampleGenerator(meshes, kind=kind, symmetries=syms, seed=0, with_visibility=True)
        b = g.batch(5)
        g.close()
        w, h = CROP
        assert b["observed"].shape == (5, h, w, 3) and b["observed"].dtype == np.uint8
        assert b["rendered"].shape == (5, h, w, 3) and b["rendered"].dtype == np.uint8
        assert b["observed_mask"].shape == (5, h, w) and b["observed_mask"].dtype == bool
        assert b["rendered_mask"].shape == (5, h, w) and b["rendered_mask"].dtype == bool
        assert b["K_crop"].shape == (5, 3, 3) and b["T_input"].shape == (5, 4, 4) and b["T_gt"].shape == (5, 4, 4)
        assert b["obj_id"].shape == (5,) and np.isin(b["obj_id"], g.obj_ids).all()
        assert (g.obj_ids[b["obj_index"]] == b["obj_id"]).all()
        assert g.points.shape == (len(g.obj_ids), 1000, 3)
        assert all(np.allclose(S[0], np.eye(4)) for S in g.symmetries)
        assert len(g.symmetries[list(g.obj_ids).index(2)]) > 1  # the cylinder is symmetric
        assert ((0 <= b["visib_fract"]) & (b["visib_fract"] <= 1)).all()
        assert b["rendered_mask"].any((1, 2)).all()  # the input pose is always in view


def test_deterministic_under_seed(source):
    meshes, syms = source
    a = SampleGenerator(meshes, symmetries=syms, seed=7)
    b = SampleGenerator(meshes, symmetries=syms, seed=7)
    c = SampleGenerator(meshes, symmetries=syms, seed=8)
    for _ in range(2):  # the second batch also uses the background pool of the first
        x, y, z = a.batch(4), b.batch(4), c.batch(4)
        for k in x:
            np.testing.assert_array_equal(x[k], y[k], err_msg=k)
        assert not np.array_equal(x["observed"], z["observed"])
    for g in (a, b, c):
        g.close()


def test_object_where_gt_pose_projects(clean_gen):
    g = clean_gen
    b = g.batch(16)
    w, h = CROP
    sil = g.renderer.render_crops(b["K_crop"], b["obj_id"], b["T_gt"], CROP, with_rgb=False).instance >= 0
    # no occluders: the visible target is its whole silhouette
    np.testing.assert_array_equal(sil, b["observed_mask"])
    uv = project(transform_points(b["T_gt"], g.hull[b["obj_index"]]), b["K_crop"])
    for i in range(len(uv)):
        ys, xs = np.nonzero(sil[i])
        assert len(xs) > 20
        lo, hi = uv[i].min(0), uv[i].max(0)
        inside = (lo > 0) & (hi < np.array([w - 1, h - 1]))
        got_lo, got_hi = np.array([xs.min(), ys.min()]), np.array([xs.max(), ys.max()])
        assert np.all(np.abs(got_lo - lo)[inside] <= 2), (i, got_lo, lo)
        assert np.all(np.abs(got_hi - hi)[inside] <= 2), (i, got_hi, hi)
    # the crop is centred on the projection of the (input) pose's origin
    c = project(b["T_input"][:, None, :3, 3], b["K_crop"])[:, 0]
    np.testing.assert_allclose(c, np.broadcast_to([(w - 1) / 2, (h - 1) / 2], c.shape), atol=1e-6)
    # the observed object differs from the background (composited behind it)
    assert (b["observed"][~b["observed_mask"]].std() > 5)


def test_rendered_matches_observed_at_gt(clean_gen):
    b = clean_gen.batch(16)
    np.testing.assert_allclose(b["T_input"], b["T_gt"])
    inter = (b["rendered_mask"] & b["observed_mask"]).sum((1, 2))
    union = (b["rendered_mask"] | b["observed_mask"]).sum((1, 2))
    iou = inter / np.maximum(union, 1)
    assert (iou > 0.95).all(), iou
    # rendered crops: neutral grey object on black
    assert (b["rendered"][~b["rendered_mask"]] == 0).all()
    obj = b["rendered"][b["rendered_mask"]].astype(int)
    assert (np.abs(obj[:, 0] - obj[:, 1]) <= 1).all()


def test_occluders_hide_part_of_target(source):
    meshes, syms = source
    g = SampleGenerator(meshes, symmetries=syms, seed=1, occluder_probs=(0, 0, 0, 1), with_visibility=True)
    b = g.batch(12)
    g.close()
    assert (b["n_occluders"] == 3).all()
    assert b["visib_fract"].mean() < 0.99
    assert b["observed_mask"].any((1, 2)).mean() > 0.5


def test_perturbation_statistics():
    rng = np.random.default_rng(0)
    n = 4000
    T = make_pose(np.broadcast_to(np.eye(3), (n, 3, 3)), np.tile([0.0, 0.0, 600.0], (n, 1)))
    p = Perturbation(rot_std_deg=15.0, xy_std_mm=10.0, z_std_mm=50.0)
    Tp = perturb_poses(T, rng, p, scale=1.0)
    w = np.degrees(matrix_to_axis_angle(Tp[:, :3, :3]))
    np.testing.assert_allclose(w.std(0), 15.0, rtol=0.08)
    dt = Tp[:, :3, 3] - T[:, :3, 3]
    np.testing.assert_allclose(dt.std(0), [10.0, 10.0, 50.0], rtol=0.08)
    np.testing.assert_allclose(dt.mean(0), 0.0, atol=3.0)
    half = perturb_poses(T, rng, p, scale=0.5)
    np.testing.assert_allclose((half[:, :3, 3] - T[:, :3, 3]).std(0), [5.0, 5.0, 25.0], rtol=0.08)
    rel = perturb_poses(T, rng, Perturbation(z_std_rel=0.05), scale=1.0)
    np.testing.assert_allclose((rel[:, 2, 3] - 600.0).std(), 30.0, rtol=0.08)
    np.testing.assert_allclose(perturb_poses(T, rng, p, scale=0.0), T)


def test_refiner_batch_perturbation_follows_curriculum(source):
    meshes, syms = source
    g = SampleGenerator(meshes, symmetries=syms, seed=2, curriculum=0.5, occluder_probs=(1.0,), augment=False,
                        perturbation=Perturbation(rot_std_deg=10.0, xy_std_mm=8.0, z_std_mm=40.0))
    b = g.batch(64)
    g.close()
    dt = b["T_input"][:, :3, 3] - b["T_gt"][:, :3, 3]
    assert 2.0 < dt[:, :2].std() < 7.0 and 10.0 < dt[:, 2].std() < 32.0
    dR = b["T_input"][:, :3, :3] @ np.swapaxes(b["T_gt"][:, :3, :3], 1, 2)
    assert 2.5 < np.degrees(matrix_to_axis_angle(dR)).std() < 8.0


def test_coarse_inputs_are_canonical(source):
    meshes, syms = source
    g = SampleGenerator(meshes, kind="coarse", symmetries=syms, seed=4, coarse_distance_mm=900.0,
                        occluder_probs=(1.0,), box_jitter=0.0, coarse_crop="detection")
    b = g.batch(8)
    w, h = CROP
    np.testing.assert_allclose(b["T_input"][:, :3, :3], np.broadcast_to(CANONICAL_ROTATION, (8, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(b["T_input"][:, 2, 3], 900.0)
    c = project(b["T_input"][:, None, :3, 3], b["K_crop"])[:, 0]
    np.testing.assert_allclose(c, np.broadcast_to([(w - 1) / 2, (h - 1) / 2], c.shape), atol=1e-6)
    # the detection box (no jitter) is the projected GT model: its crop holds the whole object
    assert (b["observed_mask"][:, 0].sum() + b["observed_mask"][:, -1].sum()) == 0
    assert b["observed_mask"].any((1, 2)).all()
    g.close()
    # canonical_pose: origin on the ray through the box centre at the given depth
    K = np.array([[600.0, 0.0, 320.0], [0.0, 610.0, 240.0], [0.0, 0.0, 1.0]])
    T = canonical_pose(K, np.array([100.0, 50.0, 200.0, 130.0]), 1000.0)
    np.testing.assert_allclose(project(T[None, :3, 3], K)[0], [149.5, 89.5], atol=1e-9)
    assert math.isclose(T[2, 3], 1000.0)
    # pose crops (the paper's) with another fixed orientation
    g = SampleGenerator(meshes, kind="coarse", symmetries=syms, seed=4, canonical_rotation=np.eye(3))
    b = g.batch(4)
    g.close()
    np.testing.assert_allclose(b["T_input"][:, :3, :3], np.broadcast_to(np.eye(3), (4, 3, 3)))
    np.testing.assert_allclose(b["T_input"][:, 2, 3], 1000.0)
    c = project(b["T_input"][:, None, :3, 3], b["K_crop"])[:, 0]
    np.testing.assert_allclose(c, np.broadcast_to([(w - 1) / 2, (h - 1) / 2], c.shape), atol=1e-6)
    assert b["rendered_mask"].any((1, 2)).all()


def test_render_crops_tiles_occlusion(source):
    meshes, _ = source
    from cosy_cli.rendering import SceneRenderer

    K = np.array([[200.0, 0.0, 63.5], [0.0, 200.0, 47.5], [0.0, 0.0, 1.0]])
    near = make_pose(np.eye(3), [0.0, 0.0, 500.0])
    far = make_pose(np.eye(3), [0.0, 0.0, 900.0])
    with SceneRenderer({1: meshes[1]}, 128, 96) as r:
        out = r.render_crops(np.stack([K, K]), [1, 1, 1], np.stack([far, near, far]), CROP, tiles=[0, 0, 1])
    assert out.rgb.shape == (2, 96, 128, 3)
    assert set(np.unique(out.instance[0])) == {-1, 1}  # the near block hides the far one
    assert set(np.unique(out.instance[1])) == {-1, 2}


def test_stream_in_process(source):
    import torch

    meshes, syms = source
    stream = TrainingStream(meshes, batch_size=3, seed=5, n_batches=2, symmetries=syms)
    batches = list(make_loader(stream, num_workers=0))
    assert len(batches) == 2
    assert isinstance(batches[0]["observed"], torch.Tensor) and batches[0]["observed"].shape == (3, 96, 128, 3)
    assert not torch.equal(batches[0]["observed"], batches[1]["observed"])


def test_coarse_box_distance_fills_crop(source):
    meshes, syms = source
    g = SampleGenerator(meshes, kind="coarse", symmetries=syms, seed=6, coarse_distance_mm="box",
                        occluder_probs=(1.0,), box_jitter=0.0)
    b = g.batch(16)
    g.close()
    z = b["T_input"][:, 2, 3]
    assert not np.allclose(z, z[0])
    # the canonical render is about as large as the observed object (same crop, similar depth)
    ratio = b["rendered_mask"].sum((1, 2)) / b["observed_mask"].sum((1, 2))
    assert np.median(ratio) > 0.3 and np.median(ratio) < 3.0, ratio
    np.testing.assert_allclose(g.diameters[list(g.obj_ids).index(1)],
                               np.linalg.norm(np.ptp(meshes[1].vertices, 0)), rtol=1e-6)  # the block


def test_spawned_workers(source):
    import torch

    meshes, syms = source
    stream = TrainingStream(meshes, batch_size=2, seed=9, n_batches=1, symmetries=syms, n_color_variants=0)
    batches = list(make_loader(stream, num_workers=2))
    assert len(batches) == 2  # one per worker
    a, b = batches
    assert isinstance(a["T_gt"], torch.Tensor)
    assert not torch.equal(a["T_gt"], b["T_gt"])  # workers are seeded differently


def test_from_object_database(tmp_path):
    from cosy_cli.objects import ObjectDatabase
    from cosy_cli.synth.objects import write_models

    write_models(tmp_path)
    db = ObjectDatabase.from_models_dir(tmp_path / "models", obj_ids={2, 4})
    g = SampleGenerator(db, seed=0)
    b = g.batch(4)
    g.close()
    assert list(g.obj_ids) == [2, 4] and set(b["obj_id"]) <= {2, 4}
    assert len(g.symmetries[0]) > 1 and len(g.symmetries[1]) == 1  # cylinder vs L-bracket
    np.testing.assert_allclose(g.points[0], db[2].points)
    assert np.isclose(g.diameters[1], db[4].diameter, rtol=1e-3)
