"""Images that disagree with what the dataset says about them are refused by every stage that reads
them (issue 20): a CosyError naming the file and both sizes (exit 2), a warning for a depth scale
that puts the GT objects far from their measured depth. Each case is a corrupted copy of one scene
of ``data_samples/`` cut to a few images (fast)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from cosy_cli.cli.main import cli
from cosy_cli.errors import CosyError, CosyWarning
from cosy_cli.io.dataset import BopDataset, depth_vs_gt, image_size_problem
from cosy_cli.validate import validate_dataset

SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"
SCENE = "000001"
KEEP = (0, 1)  # image ids kept in the copies
SMALL_TEMPLATES = {"viewpoints": 60, "inplane": 12}


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> Path:
    """data_samples cut to scene 1, images 0 and 1 (models and camera.json as they are)."""
    root = tmp_path_factory.mktemp("clean") / "ds"
    (root / "test").mkdir(parents=True)
    shutil.copy(SAMPLES / "camera.json", root / "camera.json")
    shutil.copytree(SAMPLES / "models", root / "models")
    src, dst = SAMPLES / "test" / SCENE, root / "test" / SCENE
    dst.mkdir()
    for name in ("scene_camera.json", "scene_gt.json", "scene_gt_info.json"):
        d = json.loads((src / name).read_text())
        (dst / name).write_text(json.dumps({k: v for k, v in d.items() if int(k) in KEEP}))
    n_inst = {im: len(json.loads((src / "scene_gt.json").read_text())[str(im)]) for im in KEEP}
    for folder in ("rgb", "depth"):
        (dst / folder).mkdir()
        for im in KEEP:
            shutil.copy(src / folder / f"{im:06d}.png", dst / folder / f"{im:06d}.png")
    for folder in ("mask", "mask_visib"):
        (dst / folder).mkdir()
        for im in KEEP:
            for k in range(n_inst[im]):
                shutil.copy(src / folder / f"{im:06d}_{k:06d}.png", dst / folder / f"{im:06d}_{k:06d}.png")
    return root


@pytest.fixture(scope="module")
def templates_dir(tmp_path_factory, clean) -> Path:
    from cosy_cli.singleview.training_free import templates

    out = tmp_path_factory.mktemp("tpl") / "templates"
    templates.main(SMALL_TEMPLATES, clean / "models", out, log=lambda *_: None)
    return out


def _copy(clean: Path, tmp_path: Path) -> Path:
    root = tmp_path / "ds"
    shutil.copytree(clean, root, ignore=shutil.ignore_patterns("models"))
    (root / "models").symlink_to(clean / "models", target_is_directory=True)
    return root


def _scene(root: Path) -> Path:
    return root / "test" / SCENE


def _shrink(path: Path, size=(320, 240)) -> None:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(path), cv2.resize(img, size, interpolation=cv2.INTER_NEAREST))


def _run(args):
    return CliRunner().invoke(cli, args, catch_exceptions=False)


def _estimate(root: Path, tmp_path: Path, templates_dir: Path, *extra):
    return _run(["estimate", "--dataset", str(root), "--from-gt", "--coarse", "templates", "--refiner", "none",
                 "--templates-dir", str(templates_dir), "--out", str(tmp_path / "c.csv"), "--quiet", *extra])


def _error_line(r) -> str:
    lines = [ln for ln in r.output.splitlines() if ln.startswith("error:")]
    assert r.exit_code == 2 and len(lines) == 1, r.output
    return lines[0]


# ---- the rules, without files ----------------------------------------------------------------
def test_size_rules():
    K = np.array([[800.0, 0, 319.5], [0, 800, 239.5], [0, 0, 1]])
    cam = ((640, 480), "camera.json")
    assert image_size_problem((640, 480), K, camera=cam) is None
    assert image_size_problem((320, 240), K, camera=cam) == "320x240 image, but camera.json says 640x480"
    K2 = K.copy()
    K2[:2, 2] = 325.3, 242.0
    assert image_size_problem((320, 240), K2, camera=cam) == \
        "320x240 image, but camera.json says 640x480 (and cam_K's principal point (325.3, 242) lies outside it)"
    # a camera file of another split: every image of the scene 400x400, principal point central -> accepted
    K3 = K.copy()
    K3[:2, 2] = 200, 200
    assert image_size_problem((400, 400), K3, camera=cam, scene_uniform=True) is None
    assert image_size_problem((400, 400), K3, camera=cam, scene_uniform=False).startswith("400x400 image, but camera")
    # no camera size: the scene's other images, then the principal point
    scene = ((640, 480), "the other images of scene 1")
    assert image_size_problem((320, 240), K, scene=scene) == \
        "320x240 image, but the other images of scene 1 are 640x480"
    K4 = K.copy()
    K4[0, 2] = 900
    assert "principal point at (900, 239.5), outside it" in image_size_problem((640, 480), K4, scene=scene)
    assert image_size_problem((640, 480), K4, camera=cam) is not None


def test_depth_vs_gt_measures_the_objects():
    K = np.array([[600.0, 0, 160], [0, 600, 120], [0, 0, 1]])
    T = np.eye(4)[None].repeat(2, 0)
    T[0, :3, 3] = 0, 0, 800
    T[1, :3, 3] = 300, 0, 800  # centre projects outside the 320x240 image
    corners = np.array([[x, y, z] for x in (-30, 30) for y in (-30, 30) for z in (-30, 30)], float)[None].repeat(2, 0)
    depth = np.full((240, 320), 790.0, np.float32)
    measured, z_min, z_max = depth_vs_gt(depth, K, T, corners)
    assert measured[0] == pytest.approx(790) and np.isnan(measured[1])
    assert (z_min[0], z_max[0]) == (770, 830)


# ---- the stages ------------------------------------------------------------------------------
def test_clean_copy_passes(clean, tmp_path, templates_dir):
    r = _estimate(clean, tmp_path, templates_dir)
    assert r.exit_code == 0, r.output
    assert "warning" not in r.output
    rep = validate_dataset(clean, "test", full=True, progress=False)
    assert rep.ok and not rep.warnings, (rep.problems, rep.warnings)
    ds = BopDataset(clean, "test")
    ds.check_image_files(depth=True)
    assert ds.read_mask(1, 0, 0, visib=True).shape == (480, 640)


def test_smaller_rgb_is_refused_by_every_stage(clean, tmp_path, templates_dir):
    root = _copy(clean, tmp_path)
    bad = _scene(root) / "rgb" / "000001.png"
    _shrink(bad)
    line = _error_line(_estimate(root, tmp_path, templates_dir))
    assert line == f"error: {bad}: 320x240 image, but camera.json says 640x480", line
    line = _error_line(_run(["detect", "--dataset", str(root), "--out", str(tmp_path / "d.json"), "--quiet"]))
    assert str(bad) in line and "320x240 image, but camera.json says 640x480" in line
    # imported detections are checked against the image sizes too
    dets = tmp_path / "imported.json"
    dets.write_text(json.dumps([{"scene_id": 1, "image_id": 0, "category_id": 1, "score": 0.9, "bbox": [1, 2, 30, 40]}]))
    line = _error_line(_run(["detect", "--dataset", str(root), "--from-json", str(dets), "--out", str(tmp_path / "d.json")]))
    assert str(bad) in line and "320x240" in line
    r = _run(["validate", "--dataset", str(root), "--split", "test"])
    assert r.exit_code == 2 and str(bad) in r.output and "32" in r.output and "320x240 px, expected 640x480" in r.output
    line = _error_line(_run(["gt-info", "--dataset", str(root), "--overwrite", "--quiet"]))
    assert str(bad) in line and "320x240 image, but camera.json says 640x480" in line
    # the readers every other stage uses (viz, evaluate)
    ds = BopDataset(root, "test")
    with pytest.raises(CosyError, match="320x240 image, but camera.json says 640x480"):
        ds.read_rgb(1, 1)
    with pytest.raises(CosyError, match="320x240 image"):
        ds.image_size(1, 1)
    with pytest.raises(CosyError, match="320x240 image"):  # its depth is fine, its image is not
        ds.read_depth(1, 1)
    assert BopDataset(root, "test", check_images=False).read_rgb(1, 1).shape == (240, 320, 3)


def test_without_a_camera_size_the_scene_and_cam_K_decide(clean, tmp_path, templates_dir):
    root = _copy(clean, tmp_path)
    cam = json.loads((root / "camera.json").read_text())
    del cam["width"], cam["height"]
    (root / "camera.json").write_text(json.dumps(cam))
    bad = _scene(root) / "rgb" / "000001.png"
    _shrink(bad)
    line = _error_line(_estimate(root, tmp_path, templates_dir))
    assert line == f"error: {bad}: 320x240 image, but the other images of scene 1 are 640x480", line


def test_principal_point_outside_the_image_is_refused(clean, tmp_path, templates_dir):
    root = _copy(clean, tmp_path)
    path = _scene(root) / "scene_camera.json"
    cams = json.loads(path.read_text())
    cams["1"]["cam_K"][2] = 1500.0  # cx
    path.write_text(json.dumps(cams))
    line = _error_line(_estimate(root, tmp_path, templates_dir))
    rgb = _scene(root) / "rgb" / "000001.png"
    assert line.startswith(f"error: {rgb}: 640x480 image, but its cam_K puts the principal point at (1500, 239.5), "
                           "outside it"), line
    r = _run(["validate", "--dataset", str(root), "--split", "test"])
    assert r.exit_code == 2 and "principal point (1500, 239.5)" in r.output


def test_depth_of_another_size_is_refused(clean, tmp_path, templates_dir):
    root = _copy(clean, tmp_path)
    bad = _scene(root) / "depth" / "000001.png"
    _shrink(bad)
    line = _error_line(_estimate(root, tmp_path, templates_dir, "--depth-refine", "icp"))
    assert line == f"error: {bad}: 320x240 depth image, but its image rgb/000001.png is 640x480", line
    r = _run(["validate", "--dataset", str(root), "--split", "test"])
    assert r.exit_code == 2 and str(bad) in r.output and "depth image is 320x240 px, expected 640x480" in r.output
    ds = BopDataset(root, "test")
    with pytest.raises(CosyError, match="320x240 depth image, but its image rgb/000001.png is 640x480"):
        ds.read_depth(1, 1)


def test_mask_of_another_size_is_refused(clean, tmp_path):
    root = _copy(clean, tmp_path)
    bad = _scene(root) / "mask_visib" / "000001_000000.png"
    _shrink(bad)
    ds = BopDataset(root, "test")
    with pytest.raises(CosyError, match="320x240 mask, but its image rgb/000001.png is 640x480") as e:
        ds.read_mask(1, 1, 0, visib=True)
    assert str(bad) in str(e.value)
    r = _run(["validate", "--dataset", str(root), "--split", "test"])
    assert r.exit_code == 2 and str(bad) in r.output and "mask is 320x240 px, expected 640x480" in r.output


def test_depth_scale_that_misplaces_the_gt_objects_warns(clean, tmp_path, templates_dir):
    root = _copy(clean, tmp_path)
    path = _scene(root) / "scene_camera.json"
    cams = json.loads(path.read_text())
    for c in cams.values():
        c["depth_scale"] = 1.0  # the files hold 0.1 mm units: depth reads 10x too far
    path.write_text(json.dumps(cams))
    # the real command line (pytest would catch the warning otherwise): one line on stderr, exit 0
    r = subprocess.run([sys.executable, "-m", "cosy_cli", "estimate", "--dataset", str(root), "--from-gt",
                        "--coarse", "templates", "--refiner", "none", "--depth-refine", "icp", "--templates-dir",
                        str(templates_dir), "--out", str(tmp_path / "c.csv"), "--quiet"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    warned = [ln for ln in r.stderr.splitlines() if "wrong depth_scale" in ln]  # (tmp_path holds "depth_scale" too)
    assert len(warned) == 1, r.stderr
    assert warned[0].startswith(f"warning: {_scene(root) / 'depth' / '000000.png'}: the measured depth at the GT "
                                "objects is 9.47 times their GT distance (8 of 8 object(s) more than 10% off"), warned
    # the reader warns once, naming the depth image
    ds = BopDataset(root, "test")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds.read_depth(1, 0)
        ds.read_depth(1, 1)
    ours = [str(w.message) for w in caught if issubclass(w.category, CosyWarning)]
    assert len(ours) == 1 and "wrong depth_scale (1 in scene_camera.json)" in ours[0], ours
    # validate: without visible masks, the same check as one warning; with them, per-instance problems
    shutil.rmtree(_scene(root) / "mask_visib")
    rep = validate_dataset(root, "test", progress=False)
    assert any("times their GT distance" in w and "wrong depth_scale" in w for w in rep.warnings), rep.warnings


def test_camera_file_of_another_split_is_tolerated(clean, tmp_path):
    """Every image of the scene 320x240 with cam_K scaled (principal point central): camera.json
    (640x480) describes another split, as T-LESS's does for train_primesense; with cam_K left as
    it was, the same images are refused."""
    root = _copy(clean, tmp_path)
    sdir = _scene(root)
    for p in [*sdir.glob("rgb/*.png"), *sdir.glob("depth/*.png"), *sdir.glob("mask*/*.png")]:
        _shrink(p)
    ds = BopDataset(root, "test")
    with pytest.raises(CosyError, match="000000.png: 320x240 image, but camera.json says 640x480"):
        ds.check_image_files(depth=True)
    path = sdir / "scene_camera.json"
    cams = json.loads(path.read_text())
    for c in cams.values():
        c["cam_K"] = [v / 2 if i in (0, 2, 4, 5) else v for i, v in enumerate(c["cam_K"])]
    path.write_text(json.dumps(cams))
    ds = BopDataset(root, "test")
    ds.check_image_files(depth=True)
    assert ds.read_rgb(1, 1).shape == (240, 320, 3) and ds.read_mask(1, 1, 0).shape == (240, 320)
    rep = validate_dataset(root, "test", progress=False)
    assert not any("320x240" in p for p in rep.problems), rep.problems
    assert any("camera.json says 640x480: it describes another split" in n for n in rep.notes), rep.notes
