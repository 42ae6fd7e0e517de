"""`cosy validate`: a tiny valid BOP dataset passes; each corruption gives exactly its problem lines."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner

from cosy_cli.cli.main import cli
from cosy_cli.geometry import make_pose, project, rotation_about_axis, transform_points
from cosy_cli.geometry.rotations import random_rotations
from cosy_cli.io import bop, images
from cosy_cli.objects import ObjectModel, model_info_from_mesh
from cosy_cli.validate import check_symmetries, validate_dataset

W, H = 64, 48
K = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
BOX = (40.0, 60.0, 80.0)  # x, y, z sizes (mm): its symmetries are the three 180° turns
N_SCENES, N_IMAGES = 2, 3


def _rot(axis, deg) -> np.ndarray:
    return rotation_about_axis(np.asarray(axis, dtype=np.float64), np.radians([deg]))[0]


def _sym(axis, deg) -> np.ndarray:
    return make_pose(_rot(axis, deg), np.zeros(3))


def _write_models(models: Path) -> dict[int, trimesh.Trimesh]:
    box = trimesh.creation.box(BOX)
    a = trimesh.creation.box((60, 20, 20))
    b = trimesh.creation.box((20, 60, 20))
    b.apply_translation((-20, 20, 0))
    ell = a.union(b, engine="manifold")  # an asymmetric L
    cyl = trimesh.creation.cylinder(radius=20, height=50, sections=64)
    meshes = {1: box, 2: ell, 3: cyl}
    models.mkdir(parents=True)
    for obj_id, m in meshes.items():
        m.export(models / f"obj_{obj_id:06d}.ply")
    infos = {
        1: model_info_from_mesh(box, [_sym((1, 0, 0), 180), _sym((0, 1, 0), 180), _sym((0, 0, 1), 180)]),
        2: model_info_from_mesh(ell),
        3: model_info_from_mesh(cyl, symmetries_continuous=[{"axis": np.array([0, 0, 1.0]), "offset": np.zeros(3)}]),
    }
    bop.write_models_info(models / "models_info.json", infos)
    return meshes


def _write_dataset(root: Path) -> None:
    meshes = _write_models(root / "models")
    bop.write_camera(root / "camera.json", bop.CameraInfo(K=K, width=W, height=H, depth_scale=1.0))
    rng = np.random.default_rng(0)
    targets = []
    for scene_id in range(1, N_SCENES + 1):
        sdir = root / "test" / f"{scene_id:06d}"
        R_obj = random_rotations(3, rng)
        T_world_obj = make_pose(R_obj, np.array([[-150.0, 0, 500], [0, 0, 550], [150, 0, 500]]))
        cams, gt, info = {}, {}, {}
        for im in range(N_IMAGES):
            T_cam_world = make_pose(_rot((0, 1, 0), 4.0 * (im - 1)), np.array([0.0, 5.0 * im, 0.0]))
            cams[im] = bop.SceneCamera(K=K, depth_scale=1.0, T_cam_world=T_cam_world)
            rgb = np.full((H, W, 3), 40 * scene_id + 10 * im, np.uint8)
            depth = np.full((H, W), 1500.0)
            gt[im], info[im] = [], []
            for k, obj_id in enumerate((1, 2, 3)):
                T = T_cam_world @ T_world_obj[k]
                uv = project(transform_points(T, meshes[obj_id].bounding_box.vertices), K)
                x1, y1 = np.clip(np.floor(uv.min(0)).astype(int), 0, [W - 1, H - 1])
                x2, y2 = np.clip(np.ceil(uv.max(0)).astype(int), 1, [W, H])
                mask = np.zeros((H, W), bool)
                mask[y1:y2, x1:x2] = True
                depth[mask] = T[2, 3]
                rgb[mask] = (200, 50 * k, 100)
                for folder in ("mask", "mask_visib"):
                    images.write_mask(sdir / folder / f"{im:06d}_{k:06d}.png", mask)
                gt[im].append(bop.GtInstance(obj_id=obj_id, T_cam_obj=T))
                box = np.array([x1, y1, x2 - x1, y2 - y1], float)
                n = int(mask.sum())
                info[im].append(bop.GtInfo(box, box, n, n, n, 1.0))
            images.write_rgb(sdir / "rgb" / f"{im:06d}.png", rgb)
            images.write_depth(sdir / "depth" / f"{im:06d}.png", depth)
            if im != 1:
                targets += [{"scene_id": scene_id, "im_id": im, "obj_id": o, "inst_count": 1} for o in (1, 2, 3)]
        bop.write_scene_camera(sdir / "scene_camera.json", cams)
        bop.write_scene_gt(sdir / "scene_gt.json", gt)
        bop.write_scene_gt_info(sdir / "scene_gt_info.json", info)
    import pandas as pd

    bop.write_targets(root / "test_targets_bop19.json", pd.DataFrame(targets))


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("bop") / "ds"
    _write_dataset(root)
    return root


@pytest.fixture
def ds(base, tmp_path) -> Path:
    """A fresh copy of the valid dataset, to corrupt."""
    dst = tmp_path / "ds"
    shutil.copytree(base, dst)
    return dst


def _run(root: Path, *args: str):
    res = CliRunner().invoke(cli, ["validate", "--dataset", str(root), *args])
    assert "Traceback" not in res.output
    if res.exception is not None:
        assert isinstance(res.exception, SystemExit), repr(res.exception)
    return res


def _problems(res) -> list[str]:
    return [ln for ln in res.stderr.splitlines() if ln.strip()]


def _edit_json(path: Path, fn) -> None:
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


S1 = Path("test") / "000001"


def test_valid_dataset_passes(base):
    res = _run(base)
    assert res.exit_code == 0, res.output
    assert _problems(res) == []
    out = res.stdout
    for expected in (f"dataset:   {base}", "split:     test", "scenes:    2", "images:    6 (6 checked, 4 decoded)",
                     "GT:        18 instances", "objects:   3 (2 symmetric)", "depth:     yes", "masks:     yes",
                     "targets:   yes (test_targets_bop19.json, 12 entries)", "result:    OK", "time:"):
        assert expected in out, (expected, out)


def test_report_api_counts_and_full_decode(base):
    rep = validate_dataset(base, full=True, progress=False)
    assert rep.ok, rep.problems
    assert (rep.n_scenes, rep.n_images, rep.n_images_decoded, rep.n_gt_instances) == (2, 6, 6, 18)
    assert (rep.n_objects, rep.n_symmetric, rep.has_depth, rep.has_masks) == (3, 2, True, True)
    rep = validate_dataset(base, max_images=1, progress=False)
    assert rep.ok and rep.n_images_checked == 2 and rep.n_images == 6


def _rm(rel):
    def f(root: Path):
        (root / rel).unlink()
    return f


def _truncate(rel):
    def f(root: Path):
        p = root / rel
        p.write_text(p.read_text()[:150])
    return f


def _scale_R(root: Path):
    def f(d):
        d["1"][0]["cam_R_m2c"] = [1.1 * v for v in d["1"][0]["cam_R_m2c"]]
    _edit_json(root / S1 / "scene_gt.json", f)


def _small_image(root: Path):
    images.write_rgb(root / S1 / "rgb" / "000002.png", np.zeros((H // 2, W // 2, 3), np.uint8))


def _behind(root: Path):
    def f(d):
        d["2"][1]["cam_t_m2c"][2] = -550.0
    _edit_json(root / "test" / "000002" / "scene_gt.json", f)


def _square_sym(root: Path):
    def f(d):
        d["1"]["symmetries_discrete"].append(_sym((0, 0, 1), 90).reshape(-1).tolist())
    _edit_json(root / "models" / "models_info.json", f)


def _wrong_axis(root: Path):
    def f(d):
        d["3"]["symmetries_continuous"][0]["axis"] = [1, 0, 0]
    _edit_json(root / "models" / "models_info.json", f)


def _unknown_obj(root: Path):
    def f(d):
        d["1"][2]["obj_id"] = 99
    _edit_json(root / S1 / "scene_gt.json", f)


def _bad_target(root: Path):
    def f(d):
        d[0]["im_id"] = 7
    _edit_json(root / "test_targets_bop19.json", f)


def _no_camera_json(root: Path):
    (root / "camera.json").unlink()


def _wrong_diameter(root: Path):
    _edit_json(root / "models" / "models_info.json", lambda d: d["2"].update(diameter=d["2"]["diameter"] * 1.05))


def _truncated_png(root: Path):
    p = root / S1 / "rgb" / "000002.png"  # decoded by the default sample (first and last image)
    p.write_bytes(p.read_bytes()[:100])


CORRUPTIONS = {
    # name: (corrupt, substrings of the one problem line)
    "missing rgb image": (_rm(S1 / "rgb" / "000001.png"), [str(S1 / "rgb" / "000001.png"), "image 1", "not found"]),
    "missing model": (_rm(Path("models") / "obj_000002.ply"), ["obj_000002.ply", "model file not found"]),
    "truncated scene_gt": (_truncate(S1 / "scene_gt.json"), [str(S1 / "scene_gt.json"), "invalid JSON"]),
    "non-orthonormal R": (_scale_R, [str(S1 / "scene_gt.json"), "image 1, instance 0 (obj_id 1)",
                                     "cam_R_m2c is not a rotation matrix"]),
    "wrong image size": (_small_image, [str(S1 / "rgb" / "000002.png"), "image 2", "32x24 px, expected 64x48",
                                        "camera.json"]),
    "object behind camera": (_behind, ["000002/scene_gt.json", "image 2, instance 1 (obj_id 2)",
                                       "object behind the camera", "t_z = -550 mm"]),
    "wrong discrete symmetry": (_square_sym, ["models_info.json", "object 1, symmetries_discrete[3]",
                                              "does not map the model onto itself"]),
    "wrong continuous symmetry": (_wrong_axis, ["models_info.json", "object 3, symmetries_continuous[0]",
                                                "rotated by", "does not map the model onto itself"]),
    "unknown obj_id": (_unknown_obj, [str(S1 / "scene_gt.json"), "image 1, instance 2 (obj_id 99)",
                                      "obj_id 99 is not in models_info.json (known: 1, 2, 3)"]),
    "bad target": (_bad_target, ["test_targets_bop19.json", "entry 0", "image 7 is not in scene 1"]),
    "truncated png": (_truncated_png, [str(S1 / "rgb" / "000002.png"), "unreadable image"]),
    "missing mask": (_rm(S1 / "mask_visib" / "000001_000002.png"), ["000001_000002.png", "image 1, instance 2",
                                                                   "mask not found"]),
    "no camera.json": (_no_camera_json, ["camera.json", "file not found"]),
    "wrong diameter": (_wrong_diameter, ["models_info.json", "object 2", "diameter", "expected within 1%"]),
}


@pytest.mark.parametrize("name", list(CORRUPTIONS))
def test_each_corruption_gives_one_line(ds, name):
    corrupt, expected = CORRUPTIONS[name]
    corrupt(ds)
    res = _run(ds)
    assert res.exit_code == 2, res.output
    lines = _problems(res)
    assert len(lines) == 1, lines
    for s in expected:
        assert s in lines[0], (s, lines[0])
    assert "result:    1 problem line(s)" in res.stdout  # the summary comes first, on stdout


def test_several_problems_all_reported(ds):
    for name in ("missing rgb image", "non-orthonormal R", "wrong discrete symmetry", "object behind camera"):
        CORRUPTIONS[name][0](ds)
    res = _run(ds)
    assert res.exit_code == 2
    lines = _problems(res)
    assert len(lines) == 4, lines
    for key in ("not found", "not a rotation matrix", "symmetries_discrete[3]", "object behind the camera"):
        assert sum(key in ln for ln in lines) == 1, (key, lines)


def _problems_only(res) -> list[str]:
    return [ln for ln in _problems(res) if not ln.startswith("warning: ")]


def _warnings(res) -> list[str]:
    return [ln for ln in _problems(res) if ln.startswith("warning: ")]


def test_missing_scene_gt_info_is_a_warning(ds):
    _rm(S1 / "scene_gt_info.json")(ds)
    res = _run(ds)
    assert res.exit_code == 0, res.output
    assert _problems_only(res) == []
    (w,) = _warnings(res)
    assert str(S1 / "scene_gt_info.json") in w and "no scene_gt_info.json in 1 of 2 scene(s)" in w
    assert "result:    OK, 1 warning" in res.stdout
    strict = _run(ds, "--strict")
    assert strict.exit_code == 2 and "1 warning and --strict" in strict.stderr


def _perturb_R(d, eps):
    """Shear the rotation of image 1, instance 0 so that |R^T R - I| is about ``eps``."""
    R = np.array(d["1"][0]["cam_R_m2c"]).reshape(3, 3)
    d["1"][0]["cam_R_m2c"] = (R @ (np.eye(3) + np.array([[0, eps / 2, 0], [0, 0, 0], [0, 0, 0]]))).reshape(-1).tolist()


def test_nearly_orthonormal_rotation_is_repaired_with_one_warning(ds):
    _edit_json(ds / S1 / "scene_gt.json", lambda d: _perturb_R(d, 0.02))
    res = _run(ds)
    assert res.exit_code == 0, res.output
    assert _problems_only(res) == []
    (w,) = _warnings(res)
    assert str(S1 / "scene_gt.json") in w and "1 of 9 cam_R_m2c rotations" in w and "image 1, instance 0" in w
    assert _run(ds, "--strict").exit_code == 2


def test_approximate_symmetry_is_a_warning_with_the_figure(ds):
    # a 1° twist about z added to the 180° turn about x of the 40x60x80 box: the far corners move ~0.9 mm
    # (tolerance 1.08 mm here): make it 4° (~4 mm, 3.5% of the diameter) for a warning, 15° for an error
    for deg, warned in ((4.0, True), (15.0, False)):
        root = ds.parent / f"sym{deg:g}"
        shutil.copytree(ds, root)

        def f(d):
            d["1"]["symmetries_discrete"][0] = (_sym((0, 0, 1), deg) @ _sym((1, 0, 0), 180)).reshape(-1).tolist()
        _edit_json(root / "models" / "models_info.json", f)
        res = _run(root)
        if warned:
            assert res.exit_code == 0, res.output
            (w,) = _warnings(res)
            assert "object 1, symmetries_discrete[0]" in w and "approximate symmetry" in w and "% of the" in w, w
        else:
            assert res.exit_code == 2, res.output
            (e,) = _problems_only(res)
            assert "object 1, symmetries_discrete[0]" in e and "does not map the model onto itself" in e, e


def test_camera_file_auto_detected_and_chosen(ds):
    (ds / "camera.json").rename(ds / "camera_uw.json")
    res = _run(ds)
    assert res.exit_code == 0, res.output
    assert "camera file: camera_uw.json" in res.stdout
    assert _run(ds, "--camera", "camera_uw.json").exit_code == 0
    bad = _run(ds, "--camera", "camera_cmu.json")
    assert bad.exit_code == 2 and "camera_cmu.json: camera file not found" in bad.stderr


def test_depth_inconsistent_with_gt(ds):
    p = ds / S1 / "depth" / "000000.png"
    images.write_depth(p, images.read_depth(p) * 3)
    lines = _problems(_run(ds))
    assert len(lines) == 3 and all("median depth" in ln and "image 0, instance" in ln for ln in lines), lines


def test_gt_absent_is_not_a_problem(ds):
    for s in range(1, N_SCENES + 1):
        for f in ("scene_gt.json", "scene_gt_info.json"):
            (ds / "test" / f"{s:06d}" / f).unlink()
    res = _run(ds)
    assert res.exit_code == 0, res.output
    assert "GT:        absent" in res.stdout


def test_max_per_check_counts_the_rest(ds):
    for im in range(N_IMAGES):
        (ds / S1 / "rgb" / f"{im:06d}.png").unlink()
    lines = _problems(_run(ds, "--max-per-check", "1"))
    assert len(lines) == 2 and "not found" in lines[0] and "2 more problem(s)" in lines[1], lines
    assert len(_problems(_run(ds, "--max-per-check", "0"))) == 3


def test_missing_dataset_and_split(tmp_path, ds):
    res = _run(tmp_path / "nope")
    assert res.exit_code == 2 and "dataset folder not found" in res.stderr
    res = _run(ds, "--split", "val")
    assert res.exit_code == 2
    assert [ln for ln in _problems(res) if "split folder 'val' not found" in ln], res.stderr


def test_check_symmetries_residuals(base):
    from cosy_cli.io.bop import read_models_info

    infos = read_models_info(base / "models" / "models_info.json")
    box = ObjectModel(1, base / "models" / "obj_000001.ply", infos[1])
    checks = check_symmetries(box)
    assert [c.label for c in checks] == [f"symmetries_discrete[{j}]" for j in range(3)]
    assert all(c.ok and c.residual_mm < 0.3 * c.tol_mm for c in checks), checks
    infos[1].symmetries_discrete = _sym((0, 0, 1), 90)[None]
    (bad,) = check_symmetries(ObjectModel(1, box.mesh_path, infos[1]))
    assert not bad.ok and 9.0 < bad.residual_mm <= 10.0 + 0.25 * bad.tol_mm  # a 40x60 box turned by 90° sticks out 10 mm


def test_real_cli_subprocess(ds):
    _unknown_obj(ds)
    exe = Path(sys.executable).parent / "cosy"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", PYOPENGL_PLATFORM="egl")
    r = subprocess.run([str(exe), "validate", "--dataset", str(ds)], capture_output=True, text=True, env=env,
                       timeout=120)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    assert len([ln for ln in r.stderr.splitlines() if "obj_id 99" in ln]) == 1
    assert "scenes:    2" in r.stdout
