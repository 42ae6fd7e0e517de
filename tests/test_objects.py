import numpy as np
import pytest
import trimesh

from cosy_cli import geometry as G
from cosy_cli.errors import CosyError
from cosy_cli.io import bop
from cosy_cli.objects import (ObjectDatabase, continuous_steps_for_max_step, model_info_from_mesh, symmetry_residuals,
                              symmetry_set)


def flip(axis):
    return G.make_pose(G.axis_angle_to_matrix(np.pi * np.asarray(axis, float)), np.zeros(3))


@pytest.fixture(scope="module")
def models_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("models")
    box = trimesh.creation.box([40, 60, 80])
    cyl = trimesh.creation.cylinder(radius=25, height=70, sections=256)
    # an off-centre origin: a box whose centre sits at (0, 0, 10) carries translations in its symmetries
    off = trimesh.creation.box([30, 30, 50])
    off.apply_translation([0, 0, 10])
    infos = {
        1: model_info_from_mesh(box, np.stack([flip([1, 0, 0]), flip([0, 1, 0]), flip([0, 0, 1])])),
        2: model_info_from_mesh(cyl, flip([1, 0, 0])[None], [{"axis": np.array([0, 0, 1.0]), "offset": np.zeros(3)}]),
        3: model_info_from_mesh(off, None, [])
    }
    # 4-fold symmetry of the square prism about the vertical axis through (0, 0, 10)
    quarter = G.make_pose(G.axis_angle_to_matrix(np.array([0, 0, np.pi / 2])), np.zeros(3))
    half_x = G.make_pose(G.axis_angle_to_matrix(np.array([np.pi, 0, 0])), [0, 0, 20.0])
    infos[3].symmetries_discrete = np.stack([quarter, half_x])
    for i, m in zip((1, 2, 3), (box, cyl, off)):
        m.export(d / f"obj_{i:06d}.ply")
    bop.write_models_info(d / "models_info.json", infos)
    return d


def test_database_loads_models(models_dir):
    db = ObjectDatabase.from_models_dir(models_dir, n_points=500, seed=3)
    assert db.obj_ids == [1, 2, 3] and 2 in db and 9 not in db
    box = db[1]
    assert np.isclose(box.diameter, np.linalg.norm([40, 60, 80]), rtol=1e-6)
    assert box.points.shape == (500, 3)
    assert np.allclose(box.points, ObjectDatabase.from_models_dir(models_dir, n_points=500, seed=3)[1].points)
    assert np.abs(box.points).max(0) == pytest.approx([20, 30, 40], abs=1e-6)
    with pytest.raises(CosyError, match="object 9 is not in the models"):
        db[9]


def test_symmetry_sets(models_dir):
    db = ObjectDatabase.from_models_dir(models_dir)
    assert len(db[1].symmetries) == 4
    assert len(db[2].symmetries) == 128  # 64 rotations about z, each with and without the flip
    assert len(db[2].symmetries_with_steps(continuous_steps_for_max_step(0.01))) == 2 * 315
    assert np.allclose(db[2].symmetries[0], np.eye(4))
    # the discrete set is closed under composition only if declared so: here it is
    assert db[1].is_symmetric and not db[3].info.symmetries_continuous


@pytest.mark.parametrize("obj_id", [1, 2, 3])
def test_every_symmetry_maps_mesh_onto_itself(models_dir, obj_id):
    obj = ObjectDatabase.from_models_dir(models_dir, n_points=400)[obj_id]
    res = symmetry_residuals(obj.points, obj.symmetries, obj.surface_distance)
    assert res.max() < 0.1, res.max()


def test_wrong_symmetry_is_detected(models_dir):
    obj = ObjectDatabase.from_models_dir(models_dir, n_points=400)[1]
    quarter = G.make_pose(G.axis_angle_to_matrix(np.array([0, 0, np.pi / 2])), np.zeros(3))
    assert symmetry_residuals(obj.points, quarter[None], obj.surface_distance)[0] > 5.0


def test_symmetry_set_combines_continuous_and_discrete():
    S = symmetry_set(flip([1, 0, 0])[None], [{"axis": [0, 0, 1.0], "offset": [0, 0, 0]}], 4)
    assert len(S) == 8
    # a group: products stay in the set
    for a in S:
        for b in S:
            assert np.min(np.abs(S - a @ b).reshape(len(S), -1).max(1)) < 1e-9


def test_missing_model_file(tmp_path, models_dir):
    import shutil
    shutil.copytree(models_dir, tmp_path / "m")
    (tmp_path / "m" / "obj_000002.ply").unlink()
    with pytest.raises(CosyError, match="obj_000002.ply"):
        ObjectDatabase.from_models_dir(tmp_path / "m")
