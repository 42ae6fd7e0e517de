"""``cosy symmetries``: proposed symmetries of meshes whose symmetry groups are known."""

import shutil

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner

from cosy_cli import geometry as G
from cosy_cli.cli.main import cli
from cosy_cli.errors import CosyError
from cosy_cli.io import bop
from cosy_cli.objects import diameter_of, model_info_from_mesh, symmetry_residuals, symmetry_set
from cosy_cli.objects.detect_symmetries import (
    SurfaceIndex, compare_symmetries, default_tolerance, detect_symmetries, main, rotation_axes,
)

OFFSET = np.array([10.0, -5.0, 20.0])


def _flip(axis):
    return G.make_pose(G.axis_angle_to_matrix(np.pi * np.asarray(axis, float)), np.zeros(3))


def _shapes() -> dict:
    top = trimesh.creation.cylinder(radius=15, height=30, sections=128).apply_translation([0, 0, 40])
    stepped = trimesh.boolean.union([trimesh.creation.cylinder(radius=30, height=60, sections=128), top],
                                    engine="manifold")
    arm_x = trimesh.creation.box([60, 20, 20])
    arm_y = trimesh.creation.box([20, 40, 20]).apply_translation([-20, 20, 0])  # arms of different lengths
    return {
        1: trimesh.creation.box([40, 60, 80]),
        2: trimesh.creation.box([50, 50, 50]),
        3: trimesh.creation.cylinder(radius=30, height=80, sections=128),
        4: trimesh.creation.cone(radius=30, height=60, sections=128),
        5: stepped,
        6: trimesh.creation.box([40, 40, 70]),
        7: trimesh.creation.cylinder(radius=30, height=20, sections=6),
        8: trimesh.boolean.union([arm_x, arm_y], engine="manifold"),
        9: trimesh.creation.box([30, 40, 50]).apply_translation(OFFSET),
    }


@pytest.fixture(scope="module")
def shapes():
    return _shapes()


@pytest.fixture(scope="module")
def models(tmp_path_factory, shapes):
    d = tmp_path_factory.mktemp("models")
    infos = {}
    for obj_id, mesh in shapes.items():
        mesh.export(d / f"obj_{obj_id:06d}.ply")
        infos[obj_id] = model_info_from_mesh(mesh)
    infos[1].symmetries_discrete = np.stack([_flip([0, 1, 0]), _flip([1, 0, 0]), _flip([0, 0, 1])])  # right
    infos[3].symmetries_discrete = _flip([0, 1, 0])[None]  # right, with the flip about y instead of x
    infos[3].symmetries_continuous = [{"axis": np.array([0, 0, 1.0]), "offset": np.zeros(3)}]
    infos[3].extra = {"note": "kept"}
    infos[6].symmetries_discrete = _flip([0, 0, 1])[None]  # incomplete: the 4-fold axis is missing
    bop.write_models_info(d / "models_info.json", infos)
    return d


@pytest.fixture(scope="module")
def run(models):
    lines = []
    reports = main(models, echo=lines.append, progress=False)
    return {r.obj_id: r for r in reports}, lines


def _axes(S):
    return [(np.round(u, 6), n) for u, n in rotation_axes(S)]


def test_box_three_half_turns(run):
    p = run[0][1].proposal
    assert p.symmetries_continuous == [] and len(p.symmetries_discrete) == 3
    assert sorted(tuple(np.abs(u)) for u, n in _axes(p.symmetries_discrete)) == [(0, 0, 1), (0, 1, 0), (1, 0, 0)]
    assert all(n == 2 for _, n in _axes(p.symmetries_discrete))
    assert np.allclose(p.symmetries_discrete[:, :3, 3], 0) and p.inertia == "distinct"


def test_cube_has_the_23_rotations_of_the_octahedral_group(run):
    S = run[0][2].proposal.symmetries_discrete
    assert len(S) == 23 and not run[0][2].proposal.symmetries_continuous
    R = S[:, :3, :3]
    assert np.allclose(np.linalg.det(R), 1)
    group = np.concatenate([np.eye(3)[None], R])
    for A in group:  # closed under composition, all distinct
        prods = A @ group
        assert all(np.abs(group - P).max(axis=(1, 2)).min() < 1e-9 for P in prods)
    assert len({tuple(np.round(g, 6).ravel()) for g in group}) == 24
    orders = sorted(n for _, n in _axes(S))
    assert orders == [2] * 6 + [3] * 4 + [4] * 3


def test_cylinder_continuous_about_z_plus_one_flip(run):
    p = run[0][3].proposal
    assert len(p.symmetries_continuous) == 1
    (c,) = p.symmetries_continuous
    assert np.allclose(c["axis"], [0, 0, 1]) and np.allclose(c["offset"], 0)
    assert len(p.symmetries_discrete) == 1
    (u, n), = _axes(p.symmetries_discrete)
    assert n == 2 and abs(u[2]) < 1e-9


@pytest.mark.parametrize("obj_id", [4, 5])
def test_cone_and_stepped_cylinder_only_continuous(run, obj_id):
    p = run[0][obj_id].proposal
    assert len(p.symmetries_continuous) == 1 and np.allclose(p.symmetries_continuous[0]["axis"], [0, 0, 1])
    assert len(p.symmetries_discrete) == 0
    # the axis passes through the centroid: on the z axis, offset is its point closest to the origin
    assert np.allclose(p.symmetries_continuous[0]["offset"], 0, atol=1e-9)


def test_square_and_hexagonal_prisms(run):
    sq = run[0][6].proposal.symmetries_discrete
    assert len(sq) == 7
    axes = _axes(sq)
    assert axes[0][1] == 4 and np.allclose(np.abs(axes[0][0]), [0, 0, 1])
    assert sorted(n for _, n in axes[1:]) == [2, 2, 2, 2] and all(abs(u[2]) < 1e-9 for u, _ in axes[1:])
    hx = run[0][7].proposal.symmetries_discrete
    assert len(hx) == 11
    axes = _axes(hx)
    assert axes[0][1] == 6 and np.allclose(np.abs(axes[0][0]), [0, 0, 1])
    assert [n for _, n in axes[1:]] == [2] * 6


def test_asymmetric_l_shape_has_none(run):
    p = run[0][8].proposal
    assert len(p.symmetries_discrete) == 0 and p.symmetries_continuous == []


def test_off_centre_box_symmetries_carry_translation(run, shapes):
    S = run[0][9].proposal.symmetries_discrete
    assert len(S) == 3
    assert np.abs(S[:, :3, 3]).max() > 10  # rotations about axes through (10, -5, 20), not the origin
    assert np.allclose(G.transform_points(S, OFFSET[None]), OFFSET)
    V = np.asarray(shapes[9].vertices)
    key = lambda P: np.array(sorted(map(tuple, np.round(P, 6))))  # noqa: E731
    for T in S:  # maps the vertex set onto itself
        assert np.allclose(key(G.transform_points(T, V)), key(V))


def test_every_proposed_symmetry_maps_the_mesh_onto_itself(run, shapes):
    for obj_id, mesh in shapes.items():
        p = run[0][obj_id].proposal
        S = symmetry_set(p.symmetries_discrete, p.symmetries_continuous, 12)
        pts, _ = trimesh.sample.sample_surface(mesh, 150, seed=1)
        res = symmetry_residuals(pts, S, lambda q, m=mesh: trimesh.proximity.closest_point(m, q)[1])
        assert res.max() < 0.1, (obj_id, res.max())
        assert p.residual_max_mm < 0.1
        assert p.tolerance_mm == pytest.approx(default_tolerance(diameter_of(mesh.vertices)))


def test_table_compares_with_models_info(run):
    reports, lines = run
    assert lines[0].split()[:3] == ["obj", "continuous", "discrete"]
    assert reports[1].existing == "agree" and reports[3].existing == "agree"  # flip about y == flip about x
    assert reports[6].existing == "differ" and reports[8].existing == "agree"  # none declared, none found
    assert reports[2].existing == "differ"  # none declared, 23 found
    row6 = next(line for line in lines if line.startswith("6 "))
    assert "differ (has 1 discrete, 0 continuous)" in row6 and "7: 4-fold z, 4 x 2-fold" in row6
    assert lines[-1].startswith("(report only")


def test_write_round_trip(models, tmp_path, run):
    d = tmp_path / "models"
    shutil.copytree(models, d)
    before = bop.read_models_info(d / "models_info.json")
    lines = []
    main(d, write=True, obj_ids=[3, 6, 9], echo=lines.append, progress=False)
    after = bop.read_models_info(d / "models_info.json")
    assert lines[-1].startswith(f"updated {d / 'models_info.json'}") and "obj 6: discrete 1 -> 7" in lines[-1]
    assert "obj 3" not in lines[-1]  # agrees: the existing entry is kept as written
    assert np.allclose(after[3].symmetries_discrete, before[3].symmetries_discrete)
    assert after[3].extra == {"note": "kept"}
    for obj_id in (6, 9):
        assert np.allclose(after[obj_id].symmetries_discrete, run[0][obj_id].proposal.symmetries_discrete, atol=1e-6)
    for obj_id in before:  # everything else untouched
        assert after[obj_id].diameter == pytest.approx(before[obj_id].diameter)
        if obj_id not in (6, 9):
            assert np.allclose(after[obj_id].symmetries_discrete, before[obj_id].symmetries_discrete)
    again = main(d, obj_ids=[6, 9], echo=lambda s: None, progress=False)
    assert [r.existing for r in again] == ["agree", "agree"]


def test_missing_models_info_is_created(tmp_path, shapes):
    d = tmp_path / "m"
    d.mkdir()
    for obj_id in (1, 8):
        shapes[obj_id].export(d / f"obj_{obj_id:06d}.ply")
    lines = []
    reports = main(d, echo=lines.append, progress=False)
    assert [r.existing for r in reports] == ["none", "none"] and not (d / "models_info.json").exists()
    main(d, write=True, echo=lines.append, progress=False)
    assert lines[-1].startswith("created")
    infos = bop.read_models_info(d / "models_info.json")
    assert sorted(infos) == [1, 8]
    assert infos[1].diameter == pytest.approx(np.linalg.norm([40, 60, 80]))
    assert len(infos[1].symmetries_discrete) == 3 and len(infos[8].symmetries_discrete) == 0


def test_rotated_off_centre_hexagonal_prism():
    mesh = trimesh.creation.cylinder(radius=30, height=20, sections=6)
    T = G.make_pose(G.random_rotations(1, np.random.default_rng(5))[0], [12.0, -30.0, 7.0])
    mesh.apply_transform(T)
    p = detect_symmetries(mesh)
    assert len(p.symmetries_discrete) == 11 and not p.symmetries_continuous
    u, n = rotation_axes(p.symmetries_discrete)[0]
    assert n == 6 and abs(float(u @ T[:3, 2])) == pytest.approx(1, abs=1e-6)
    pts, _ = trimesh.sample.sample_surface(mesh, 200, seed=2)
    res = symmetry_residuals(pts, p.symmetries_discrete, lambda q: trimesh.proximity.closest_point(mesh, q)[1])
    assert res.max() < 0.1


def test_tolerance_decides_near_symmetries():
    mesh = trimesh.creation.box([50, 50.4, 80])  # almost a square prism: 0.2 mm off
    assert len(detect_symmetries(mesh).symmetries_discrete) == 7  # default tolerance ~1 mm
    assert len(detect_symmetries(mesh, 0.1).symmetries_discrete) == 3


def test_surface_index_matches_exact_distances():
    mesh = trimesh.creation.cylinder(radius=30, height=80, sections=64)  # fan caps: thin triangles
    idx = SurfaceIndex(mesh.vertices, mesh.faces, n_samples=5000)
    rng = np.random.default_rng(0)
    pts, _ = trimesh.sample.sample_surface(mesh, 400, seed=3)
    pts = pts + rng.normal(scale=2.0, size=pts.shape)
    exact = trimesh.proximity.closest_point(mesh, pts)[1]
    assert np.abs(idx.distance(pts, k=8) - exact).max() < 1e-9


def test_compare_symmetries():
    z = [{"axis": np.array([0, 0, 1.0]), "offset": np.zeros(3)}]
    assert compare_symmetries(_flip([1, 0, 0])[None], z, _flip([0.6, 0.8, 0])[None], z, 1.0)
    assert not compare_symmetries(_flip([1, 0, 0])[None], z, np.zeros((0, 4, 4)), z, 1.0)
    shifted = _flip([1, 0, 0])
    shifted[:3, 3] = [0, 0, 10]
    assert not compare_symmetries(_flip([1, 0, 0])[None], [], shifted[None], [], 1.0)
    assert compare_symmetries(np.stack([_flip([1, 0, 0]), _flip([0, 1, 0]), _flip([0, 0, 1])]), [],
                              np.stack([_flip([0, 0, 1]), _flip([1, 0, 0]), _flip([0, 1, 0])]), [], 1.0)


def test_bad_input(tmp_path, models):
    with pytest.raises(CosyError, match="models folder not found"):
        main(tmp_path / "nope", echo=lambda s: None)
    with pytest.raises(CosyError, match=r"object\(s\) \[42\] not found"):
        main(models, obj_ids=[42], echo=lambda s: None)
    d = tmp_path / "bad"
    d.mkdir()
    (d / "obj_000001.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2")
    with pytest.raises(CosyError, match="obj_000001.ply"):
        main(d, echo=lambda s: None, progress=False)
    (tmp_path / "empty").mkdir()
    with pytest.raises(CosyError, match="no models_info.json and no obj_XXXXXX.ply"):
        main(tmp_path / "empty", echo=lambda s: None)


def test_cli(models, tmp_path):
    runner = CliRunner()
    res = runner.invoke(cli, ["symmetries", "--models", str(models), "--obj-id", "8", "--obj-id", "1"])
    assert res.exit_code == 0, res.output
    assert "obj" in res.output and "agree" in res.output
    res = runner.invoke(cli, ["symmetries", "--models", str(tmp_path / "missing")])
    assert res.exit_code == 2 and "error:" in res.output and "models folder not found" in res.output
    res = runner.invoke(cli, ["symmetries", "--models", str(models), "--tolerance-mm", "0"])
    assert res.exit_code == 2
