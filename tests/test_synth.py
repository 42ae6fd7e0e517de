"""cosy synth: procedural objects (true symmetries, look-alikes) and the synthetic BOP dataset."""

import json

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner

from cosy_cli import geometry as G
from cosy_cli.errors import CosyError
from cosy_cli.io import BopDataset, bop, images
from cosy_cli.objects import ObjectDatabase, symmetry_residuals, symmetry_set
from cosy_cli.synth import OBJECTS, generate_dataset, gt_infos, mask_bbox, objects as synth_objects

W, H = 160, 120
TINY = dict(scenes=2, views=3, objects_per_scene=5, width=W, height=H, progress=False)


def rot(axis, deg):
    return G.make_pose(G.rotation_about_axis(np.asarray(axis, float), np.radians([deg]))[0], np.zeros(3))


X, Y, Z = (1, 0, 0), (0, 1, 0), (0, 0, 1)


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "ds"
    s = generate_dataset(out, seed=3, **TINY)
    assert s.mode == "created" and s.n_images == 6
    return out


@pytest.fixture(scope="module")
def ds(root):
    return BopDataset(root, "test")


@pytest.fixture(scope="module")
def db(root):
    return ObjectDatabase.from_models_dir(root / "models", n_points=150, seed=0)


# --------------------------------------------------------------------------------------------
# objects
# --------------------------------------------------------------------------------------------
def _test_symmetries(model):
    """Declared discrete symmetries, continuous ones at 8 steps plus two odd angles."""
    S = symmetry_set(model.info.symmetries_discrete, model.info.symmetries_continuous, n_continuous=8)
    if model.info.symmetries_continuous:
        for c in model.info.symmetries_continuous:
            odd = G.make_pose(G.rotation_about_axis(c["axis"], np.radians([7.3, 201.7])), np.zeros(3))
            S = np.concatenate([S, odd, odd @ S[1:2]])
    return S


def test_declared_symmetries_hold(db):
    assert db.obj_ids == list(range(1, 9))
    for model in db:
        pts = np.concatenate([model.points, model.vertices[:: max(1, len(model.vertices) // 150)]])
        S = _test_symmetries(model)
        both = np.concatenate([S, G.invert(S)])  # S(M) in M and M in S(M)
        res = symmetry_residuals(pts, both, model.surface_distance)
        assert res.max() < 0.1, (model.obj_id, res.max())


# rotations that are NOT symmetries of each object (by construction)
NOT_SYMMETRIES = {
    1: [rot(Z, 90), rot(X, 90), rot(Y, 90)],
    2: [rot(X, 90), rot(Y, 90)],
    3: [rot(X, 180), rot(Y, 90)],
    4: [rot(X, 180), rot(Y, 180), rot(Z, 180), rot(Z, 90)],
    5: [rot(Z, 45), rot(X, 180), rot(Y, 90)],
    6: [rot(X, 180), rot(Y, 180), rot(Z, 180), rot(Z, 90)],
    7: [rot(X, 180), rot(Y, 180), rot(Z, 180), rot(Z, 90)],
    8: [rot(Z, 30), rot(Z, 90), rot(X, 90)],
}


def test_other_rotations_are_not_symmetries(db):
    for model in db:
        res = symmetry_residuals(model.points, np.stack(NOT_SYMMETRIES[model.obj_id]), model.surface_distance)
        assert res.min() > 2.0, (model.obj_id, res)
    asym = [m.obj_id for m in db if not m.is_symmetric]
    assert asym == [4, 6, 7]


def test_models_info_and_conventions(root, db):
    infos = bop.read_models_info(root / "models" / "models_info.json")
    assert bop.read_models_info(root / "models_eval" / "models_info.json").keys() == infos.keys()
    for o in OBJECTS:
        info, mesh = infos[o.obj_id], db[o.obj_id].mesh
        V = mesh.vertices
        assert np.allclose((V.min(0) + V.max(0)) / 2, 0, atol=1e-6)  # origin at the bbox centre
        assert np.allclose(info.min_xyz, V.min(0), atol=1e-6) and np.allclose(info.size_xyz, np.ptp(V, 0), atol=1e-6)
        assert 40 <= info.size_xyz.max() <= 150 and 60 < info.diameter < 160
        assert mesh.vertex_normals.shape == V.shape and mesh.visual.kind == "vertex"
        assert (root / "models_eval" / f"obj_{o.obj_id:06d}.ply").is_file()
    assert len(infos[8].symmetries_discrete) == 11 and len(infos[5].symmetries_discrete) == 3
    assert len(infos[2].symmetries_continuous) == 1 and len(infos[2].symmetries_discrete) == 1


def test_lookalike_pair_differs_by_a_small_detail(db):
    a, b = db[6], db[7]
    assert np.allclose(a.info.size_xyz, b.info.size_xyz) and np.isclose(a.diameter, b.diameter)
    d_ba = b.surface_distance(a.points)  # points of 6 on 7
    d_ab = a.surface_distance(b.points)
    dense_b = np.asarray(trimesh.sample.sample_surface(b.mesh, 5000, seed=2)[0])
    hausdorff = max(d_ba.max(), a.surface_distance(dense_b).max())
    assert 3.0 < hausdorff < 0.1 * a.diameter, hausdorff  # a small but real detail
    assert np.median(d_ba) < 1e-3 and np.median(d_ab) < 1e-3  # otherwise the same surface


def test_models_are_fixed(tmp_path):
    synth_objects.write_models(tmp_path / "a")
    synth_objects.write_models(tmp_path / "b")
    for sub in ("models", "models_eval"):
        for p in sorted((tmp_path / "a" / sub).iterdir()):
            assert p.read_bytes() == (tmp_path / "b" / sub / p.name).read_bytes(), p.name


def test_resting_rotations_put_a_face_down():
    rng = np.random.default_rng(0)
    for o in OBJECTS:
        V = synth_objects.solid_mesh(o.obj_id).vertices
        for _ in range(10):
            R = synth_objects.resting_rotation(o.obj_id, rng)
            assert G.is_rotation(R)
            z = V @ R[2]
            low = z < z.min() + 0.05
            # several vertices touch the table, spread out (a face or a cylinder's line, not a corner)
            spread = np.ptp((V[low] @ R[:2].T), axis=0).max()
            assert low.sum() >= 2 and spread > 15, (o.obj_id, low.sum(), spread)


# --------------------------------------------------------------------------------------------
# the dataset
# --------------------------------------------------------------------------------------------
def test_dataset_files_read_back(root, ds):
    assert ds.scene_ids == [1, 2]
    cam = ds.camera()
    assert (cam.width, cam.height) == (W, H) and cam.depth_scale == pytest.approx(0.1)
    targets = bop.read_targets(root / "test_targets_bop19.json")
    assert set(targets.scene_id) == {1, 2}
    for sid in ds.scene_ids:
        cams, gt, info = ds.scene_camera(sid), ds.scene_gt(sid), ds.scene_gt_info(sid)
        assert list(cams) == list(gt) == list(info) == [0, 1, 2]
        for im in cams:
            assert cams[im].T_cam_world is not None and np.allclose(cams[im].K, cam.K)
            assert ds.read_rgb(sid, im).shape == (H, W, 3)
            depth = ds.read_depth(sid, im)
            assert depth.shape == (H, W) and depth.max() > 100
            assert len(gt[im]) == len(info[im]) == 5
            assert len({g.obj_id for g in gt[im]}) == 5  # distinct objects
            for i, (g, gi) in enumerate(zip(gt[im], info[im])):
                m = images.read_mask(ds.mask_path(sid, im, i))
                mv = images.read_mask(ds.mask_path(sid, im, i, visib=True))
                assert m.sum() == gi.px_count_all and mv.sum() == gi.px_count_visib
                assert not (mv & ~m).any()
                assert gi.px_count_valid == (m & (depth > 0)).sum()
                assert gi.visib_fract == pytest.approx(mv.sum() / max(m.sum(), 1), abs=1e-6)
                assert np.array_equal(gi.bbox_visib, mask_bbox(mv)) and np.array_equal(gi.bbox_obj, mask_bbox(m))
            want = {}
            for g, gi in zip(gt[im], info[im]):
                if gi.visib_fract >= 0.1:
                    want[g.obj_id] = want.get(g.obj_id, 0) + 1
            rows = targets[(targets.scene_id == sid) & (targets.im_id == im)]
            assert dict(zip(rows.obj_id, rows.inst_count)) == want


def test_deterministic_under_seed(root, tmp_path):
    same = tmp_path / "same"
    generate_dataset(same, seed=3, **TINY)
    other = tmp_path / "other"
    generate_dataset(other, seed=4, **TINY)
    for f in ("scene_gt.json", "scene_camera.json", "scene_gt_info.json", "rgb/000001.png", "depth/000002.png",
              "mask_visib/000000_000003.png"):
        a = (root / "test" / "000002" / f).read_bytes()
        assert a == (same / "test" / "000002" / f).read_bytes(), f
        if f.endswith(".json"):
            assert a != (other / "test" / "000002" / f).read_bytes(), f
    assert (root / "test_targets_bop19.json").read_bytes() == (same / "test_targets_bop19.json").read_bytes()
    for sub in ("models", "models_eval"):
        for p in (root / sub).iterdir():
            assert p.read_bytes() == (other / sub / p.name).read_bytes(), p
    # scene k depends only on (seed, k): a shorter run gives the same first scene
    short = tmp_path / "short"
    generate_dataset(short, seed=3, **(TINY | {"scenes": 1}))
    assert (short / "test/000001/scene_gt.json").read_bytes() == (root / "test/000001/scene_gt.json").read_bytes()


def test_depth_agrees_with_gt_poses(ds, db):
    checked = 0
    for sid in ds.scene_ids:
        for im, cam in ds.scene_camera(sid).items():
            depth = ds.read_depth(sid, im)
            P = G.backproject_depth(depth, cam.K)
            for i, (g, gi) in enumerate(zip(ds.scene_gt(sid)[im], ds.scene_gt_info(sid)[im])):
                if gi.px_count_visib < 20:
                    continue
                mv = images.read_mask(ds.mask_path(sid, im, i, visib=True))
                pts = P[mv & (depth > 0)][::3]
                local = G.transform_points(G.invert(g.T_cam_obj), pts)
                d = db[g.obj_id].surface_distance(local)
                assert np.median(d) < 0.5 and np.percentile(d, 95) < 1.0, (sid, im, g.obj_id, np.median(d))
                checked += 1
    assert checked >= 15


def test_objects_in_front_and_centred_in_masks(ds):
    K = ds.camera().K
    for sid in ds.scene_ids:
        for im in ds.image_ids(sid):
            for g, gi in zip(ds.scene_gt(sid)[im], ds.scene_gt_info(sid)[im]):
                assert g.T_cam_obj[2, 3] > 150
                x, y, w, h = gi.bbox_obj
                if w < 0 or x <= 0 or y <= 0 or x + w >= W - 1 or y + h >= H - 1:
                    continue  # cut by the image border: the centre may lie outside
                u, v = G.project(g.T_cam_obj[None, :3, 3], K)[0]
                assert x - 1 <= u <= x + w + 1 and y - 1 <= v <= y + h + 1


def test_camera_poses_consistent_and_objects_on_table(ds, db):
    for sid in ds.scene_ids:
        cams, gt = ds.scene_camera(sid), ds.scene_gt(sid)
        T_world_obj = np.stack([G.invert(cams[im].T_cam_world)[None] @ np.stack([g.T_cam_obj for g in gt[im]])
                                for im in cams])  # (V, N, 4, 4)
        assert np.abs(T_world_obj - T_world_obj[0]).max() < 1e-4  # T_cam_obj == T_cam_world @ T_world_obj
        ids = [g.obj_id for g in gt[0]]
        for T, o in zip(T_world_obj[0], ids):
            z = G.transform_points(T, db[o].vertices)[:, 2]
            assert abs(z.min()) < 1e-3  # resting on the table z = 0
        # no two objects intersect: surface samples of each lie outside every other solid
        solids = [synth_objects.solid_mesh(o) for o in ids]
        for i, (Ti, si) in enumerate(zip(T_world_obj[0], solids)):
            pts = G.transform_points(Ti, trimesh.sample.sample_surface(si, 300, seed=i)[0])
            for j, (Tj, sj) in enumerate(zip(T_world_obj[0], solids)):
                if i != j:
                    assert not sj.contains(G.transform_points(G.invert(Tj), pts)).any(), (sid, ids[i], ids[j])
        for T in (cams[im].T_cam_world for im in cams):
            eye = G.invert(T)[:3, 3]
            assert 350 < np.linalg.norm(eye) < 900 and eye[2] > 100  # above the table, 400-800 mm away


def test_gt_info_of_masks():
    m = np.zeros((2, 6, 8), bool)
    m[0, 1:4, 2:7] = True
    vis = m.copy()
    vis[0, 1, :] = False
    depth = np.ones((6, 8), np.float32)
    depth[3, 2] = 0
    a, b = gt_infos(m, vis, depth)
    assert a.bbox_obj.tolist() == [2, 1, 4, 2] and a.bbox_visib.tolist() == [2, 2, 4, 1]
    assert (a.px_count_all, a.px_count_visib, a.px_count_valid) == (15, 10, 14)
    assert a.visib_fract == pytest.approx(10 / 15)
    assert b.bbox_obj.tolist() == [-1, -1, -1, -1] and b.visib_fract == 0.0


def test_output_folder_rules(root, tmp_path):
    out = tmp_path / "ds"
    out.mkdir()
    (out / "note.txt").write_text("mine")
    with pytest.raises(CosyError, match="not empty"):
        generate_dataset(out, seed=0, **(TINY | {"scenes": 1, "views": 1}))
    assert (out / "note.txt").read_text() == "mine"
    s = generate_dataset(out, seed=0, models_only=True, overwrite=True, **(TINY | {"scenes": 1, "views": 1}))
    assert s.mode == "replaced" and not (out / "note.txt").exists() and (out / "models" / "models_info.json").is_file()
    # a split added beside the models, then another one; the first stays
    s = generate_dataset(out, seed=0, split="test", **(TINY | {"scenes": 1, "views": 1}))
    assert s.mode == "added split" and (out / "test_targets_bop19.json").is_file()
    s = generate_dataset(out, seed=0, split="train_pbr", **(TINY | {"scenes": 1, "views": 2}))
    assert s.mode == "added split" and BopDataset(out, "train_pbr").image_ids(1) == [0, 1]
    assert BopDataset(out, "test").image_ids(1) == [0]
    with pytest.raises(CosyError, match="exists already"):
        generate_dataset(out, seed=0, split="train_pbr", **(TINY | {"scenes": 1, "views": 1}))
    s = generate_dataset(out, seed=0, split="train_pbr", overwrite=True, **(TINY | {"scenes": 1, "views": 1}))
    assert s.mode == "replaced split" and BopDataset(out, "train_pbr").image_ids(1) == [0]
    # train_pbr and test scenes differ for the same seed
    assert (out / "train_pbr/000001/scene_gt.json").read_bytes() != (out / "test/000001/scene_gt.json").read_bytes()
    with pytest.raises(CosyError, match="--views"):
        generate_dataset(tmp_path / "x", seed=0, **(TINY | {"views": 0}))


def test_cli(tmp_path):
    from cosy_cli.cli.main import cli

    out = tmp_path / "cli"
    r = CliRunner().invoke(cli, ["synth", "--out", str(out), "--scenes", "1", "--views", "2", "--objects", "3",
                                 "--width", "96", "--height", "72"])
    assert r.exit_code == 0, r.output
    assert "1 scenes, 2 images" in r.output and "on disk" in r.output
    assert json.loads((out / "camera.json").read_text())["width"] == 96
    r = CliRunner().invoke(cli, ["synth", "--out", str(out), "--scenes", "1", "--views", "2", "--quiet"])
    assert r.exit_code == 2 and "error:" in r.output


def test_more_objects_than_models_repeat(tmp_path):
    out = tmp_path / "many"
    generate_dataset(out, seed=1, **(TINY | {"scenes": 1, "views": 2, "objects_per_scene": 11}))
    ds = BopDataset(out, "test")
    ids = [g.obj_id for g in ds.scene_gt(1)[0]]
    assert len(ids) == 11 and set(ids) == set(range(1, 9))
    targets = bop.read_targets(out / "test_targets_bop19.json")
    assert targets.inst_count.max() >= 2 and targets.inst_count.sum() <= 22
