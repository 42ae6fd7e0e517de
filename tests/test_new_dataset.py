"""``cosy new-dataset``: MegaPose's real photos + textured HOPE meshes -> BOP datasets that
``cosy validate`` accepts and ``cosy estimate`` runs on, with their boxes imported.

Reads ../shared/realdata/megapose_examples (or $COSY_REALDATA/megapose_examples); the tests that
need it skip when it is absent."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cosy_cli.cli.main import cli
from cosy_cli.io import bop, images

from realdata import MEGAPOSE, needs  # noqa: E402
BBQ, MUSTARD = MEGAPOSE / "barbecue-sauce", MEGAPOSE / "mustard"
needs_megapose = needs(BBQ, MUSTARD)


def run(*args) -> tuple[int, str, str]:
    res = CliRunner().invoke(cli, [str(a) for a in args])
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        raise res.exception
    return res.exit_code, res.stdout, res.stderr


def new_dataset(*args) -> tuple[int, str, str]:
    return run("new-dataset", *args)


def user_error(*args) -> str:
    """Run new-dataset expecting a user error: exit 2 and one 'error: ...' line, no traceback."""
    code, out, err = new_dataset(*args)
    assert code == 2, (code, out, err)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


def render_object(mesh_path: Path, size=(320, 480)) -> np.ndarray:
    """RGB of the mesh (mm) seen from its side at 400 mm."""
    from cosy_cli.geometry.poses import make_pose
    from cosy_cli.geometry.rotations import rotation_about_axis
    from cosy_cli.objects.database import load_mesh
    from cosy_cli.rendering import SceneRenderer

    w, h = size
    K = np.array([[600.0, 0, w / 2], [0, 600.0, h / 2], [0, 0, 1]])
    R = rotation_about_axis(np.array([1.0, 0, 0]), [np.pi / 2])[0] @ rotation_about_axis(np.array([0, 0, 1.0]),
                                                                                         [4.8])[0]
    with SceneRenderer({1: load_mesh(mesh_path)}, w, h) as r:
        return r.render(K, [1], make_pose(R, np.array([0, 0, 400.0]))[None]).rgb


def colourfulness(rgb: np.ndarray) -> float:
    """Mean (max - min channel) over the rendered pixels: 0 for a grey, untextured render."""
    px = rgb[rgb.sum(-1) > 0].astype(np.float64)
    return float((px.max(1) - px.min(1)).mean())


@pytest.fixture(scope="module")
def bbq_dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("nd") / "bbq"
    code, stdout, err = new_dataset("--images", BBQ, "--meshes", BBQ / "meshes",
                                    "--boxes", BBQ / "inputs" / "object_data.json", "--out", out)
    assert code == 0, err
    assert "barbecue-sauce" in stdout  # the id -> name mapping is printed
    return out


@needs_megapose
def test_barbecue_sauce_bop_dataset(bbq_dataset):
    out = bbq_dataset
    code, stdout, err = run("validate", "--dataset", out)
    assert code == 0, err
    # models in mm: the HOPE bottle is ~15 cm tall
    infos = bop.read_models_info(out / "models" / "models_info.json")
    assert list(infos) == [1]
    assert 50 < infos[1].diameter < 300
    assert infos[1].extra.get("symmetries_proposed") is True
    assert json.loads((out / "models" / "models_names.json").read_text()) == {"1": "barbecue-sauce"}
    assert json.loads((out / "test" / "000001" / "image_names.json").read_text()) == {"0": "image_rgb.png"}
    # the image is copied unchanged, with MegaPose's K
    assert (out / "test" / "000001" / "rgb" / "000000.png").read_bytes() == (BBQ / "image_rgb.png").read_bytes()
    K = np.asarray(json.loads((BBQ / "camera_data.json").read_text())["K"])
    cams = bop.read_scene_camera(out / "test" / "000001" / "scene_camera.json")
    np.testing.assert_allclose(cams[0].K, K, rtol=1e-7)
    cam = bop.read_camera(out / "camera.json")
    assert (cam.width, cam.height) == (640, 480)
    # texture kept: the PLY reads back textured and renders as the source mesh does (not grey)
    ply = (out / "models" / "obj_000001.ply").read_bytes()[:600]
    assert b"comment TextureFile obj_000001.png" in ply and b"texture_u" in ply
    rgb_new = render_object(out / "models" / "obj_000001.ply")
    rgb_src = render_object(BBQ / "meshes" / "barbecue-sauce" / "hope_000002.ply")
    assert colourfulness(rgb_new) > 40
    assert np.abs(rgb_new.astype(int) - rgb_src).mean() < 0.5
    # boxes: BOP detections with the obj_id of the label, as `cosy detect --from-json` reads them
    from cosy_cli.detection.importers import read_detections_any
    from cosy_cli.io.dataset import BopDataset

    dets = read_detections_any(out / "detections.json", BopDataset(out, "test"))
    assert len(dets) == 1
    d = dets.iloc[0]
    assert (d.scene_id, d.im_id, d.obj_id) == (1, 0, 1)
    np.testing.assert_allclose([d.x, d.y, d.w, d.h], [384, 234, 522 - 384, 455 - 234])


@needs_megapose
def test_mustard_full_hd(tmp_path):
    out = tmp_path / "mustard"
    code, _, err = new_dataset("--images", MUSTARD, "--meshes", MUSTARD / "meshes", "--boxes",
                               MUSTARD / "inputs" / "object_data.json", "--out", out, "--no-symmetries")
    assert code == 0, err
    code, _, err = run("validate", "--dataset", out)
    assert code == 0, err
    cam = bop.read_camera(out / "camera.json")
    assert (cam.width, cam.height) == (1920, 1080)
    info = bop.read_models_info(out / "models" / "models_info.json")[1]
    assert 50 < info.diameter < 300 and "symmetries_proposed" not in info.extra
    det = json.loads((out / "detections.json").read_text())
    assert det == [{"scene_id": 1, "image_id": 0, "category_id": 1, "score": 1.0,
                    "bbox": [728.0, 819.0, 232.0, 261.0], "time": -1.0}]


@needs_megapose
def test_two_objects_ids_by_name_and_one_camera_per_dataset(tmp_path):
    out = tmp_path / "two"
    code, stdout, err = new_dataset("--images", BBQ, "--meshes", MUSTARD / "meshes", "--meshes", BBQ / "meshes",
                                    "--boxes", BBQ / "inputs" / "object_data.json", "--out", out, "--no-symmetries",
                                    "--scene-id", 5, "--split", "val")
    assert code == 0, err
    assert json.loads((out / "models" / "models_names.json").read_text()) == {"1": "barbecue-sauce", "2": "mustard"}
    det = json.loads((out / "detections.json").read_text())
    assert [(d["scene_id"], d["category_id"]) for d in det] == [(5, 1)]
    assert (out / "val" / "000005" / "rgb" / "000000.png").is_file()
    # 640x480 and 1920x1080 images cannot share one camera.json
    msg = user_error("--images", BBQ, "--images", MUSTARD, "--meshes", BBQ / "meshes", "--out", tmp_path / "mixed")
    assert "different sizes" in msg and not (tmp_path / "mixed").exists()
    # an existing output is not replaced without --overwrite
    assert "--overwrite" in user_error("--images", BBQ, "--meshes", BBQ / "meshes", "--out", out)


@needs_megapose
def test_mesh_units_obj_in_metres(tmp_path):
    from cosy_cli.objects.database import load_mesh

    src = load_mesh(BBQ / "meshes" / "barbecue-sauce" / "hope_000002.ply")
    d_mm = float(np.linalg.norm(src.vertices.max(0) - src.vertices.min(0)))
    src.apply_scale(0.001)
    (tmp_path / "obj").mkdir()
    src.export(tmp_path / "obj" / "sauce.obj")  # OBJ + MTL + texture PNG, in metres
    out = tmp_path / "m"
    code, _, err = new_dataset("--images", BBQ, "--meshes", tmp_path / "obj" / "sauce.obj", "--mesh-units", "m",
                               "--out", out, "--no-symmetries")
    assert code == 0, err
    mesh = load_mesh(out / "models" / "obj_000001.ply")
    assert mesh.visual.kind == "texture"
    np.testing.assert_allclose(np.linalg.norm(mesh.vertices.max(0) - mesh.vertices.min(0)), d_mm, rtol=1e-5)
    assert colourfulness(render_object(out / "models" / "obj_000001.ply")) > 40
    # cm: x10 (1.5 m: plausible, no warning); metres read as mm: a warning that names the likely units
    code, _, err = new_dataset("--images", BBQ, "--meshes", BBQ / "meshes", "--mesh-units", "cm", "--out",
                               tmp_path / "cm", "--no-symmetries")
    assert code == 0, err
    info = bop.read_models_info(tmp_path / "cm" / "models" / "models_info.json")[1]
    assert info.diameter == pytest.approx(1538.67, rel=1e-3)
    code, _, err = new_dataset("--images", BBQ, "--meshes", tmp_path / "obj", "--out", tmp_path / "mm",
                               "--no-symmetries")
    assert code == 0, err
    warned = [ln for ln in err.splitlines() if ln.startswith("warning: ")]  # a warning to act on: even with --quiet
    assert len(warned) == 1 and re.search(r"0\.154 mm across .*--mesh-units m would make it 154 mm", warned[0]), err


@needs_megapose
def test_depth_per_image_intrinsics_and_jpeg(tmp_path):
    """Two images (png, jpg) with their own K (a dict keyed by file name, and IMAGE_STEM.json),
    depth as 16-bit PNG in 0.1 mm units and as float metres (.npy)."""
    imgs, dep = tmp_path / "imgs", tmp_path / "depth"
    imgs.mkdir(), dep.mkdir()
    rgb = images.read_rgb(BBQ / "image_rgb.png")
    images.write_rgb(imgs / "view10.png", rgb)
    images.write_rgb(imgs / "view2.jpg", rgb)
    K = json.loads((BBQ / "camera_data.json").read_text())["K"]
    (imgs / "view10.json").write_text(json.dumps({"cam_K": sum(K, [])}))
    ks = tmp_path / "K.json"
    ks.write_text(json.dumps({"view2.jpg": {"fx": 600, "fy": 601, "cx": 320, "cy": 240, "width": 640,
                                            "height": 480}}))
    z_mm = np.full((480, 640), 812.3)
    images.write_depth(dep / "view2.png", z_mm, 0.1)  # uint16 in 0.1 mm
    np.save(dep / "view10.npy", (z_mm / 0.1).astype(np.float32))  # floats in the same 0.1 mm units
    msg = user_error("--images", imgs, "--intrinsics", ks, "--depth", dep, "--meshes", BBQ / "meshes", "--out",
                     tmp_path / "x")
    assert "--depth-scale" in msg
    out = tmp_path / "ds"
    code, _, err = new_dataset("--images", imgs, "--intrinsics", ks, "--depth", dep, "--depth-scale", 0.1,
                               "--meshes", BBQ / "meshes", "--out", out, "--no-symmetries")
    assert code == 0, err
    names = json.loads((out / "test" / "000001" / "image_names.json").read_text())
    assert names == {"0": "view2.jpg", "1": "view10.png"}  # natural order
    assert (out / "test" / "000001" / "rgb" / "000000.jpg").is_file()
    cams = bop.read_scene_camera(out / "test" / "000001" / "scene_camera.json")
    assert cams[0].K[0, 0] == 600 and cams[1].K[0, 0] == pytest.approx(K[0][0])
    from cosy_cli.io.dataset import BopDataset

    ds = BopDataset(out, "test")
    for im in (0, 1):
        np.testing.assert_allclose(ds.read_depth(1, im), z_mm, atol=0.06)
    code, _, err = run("validate", "--dataset", out)
    assert code == 0, err


@needs_megapose
def test_bad_inputs_one_line(tmp_path):
    lone = tmp_path / "lone"
    lone.mkdir()
    shutil.copy(BBQ / "image_rgb.png", lone / "photo.png")
    meshes = ("--meshes", BBQ / "meshes")
    # no K anywhere
    msg = user_error("--images", lone, *meshes, "--out", tmp_path / "o1")
    assert "photo.png" in msg and "intrinsics" in msg
    # principal point outside the image
    k = tmp_path / "k.json"
    k.write_text(json.dumps([[600, 0, 1500], [0, 600, 240], [0, 0, 1]]))
    msg = user_error("--images", lone, "--intrinsics", k, *meshes, "--out", tmp_path / "o2")
    assert "principal point" in msg and "k.json" in msg
    # the camera's stated resolution is not the image's
    k.write_text(json.dumps({"K": [[600, 0, 320], [0, 600, 240], [0, 0, 1]], "resolution": [1080, 1920]}))
    assert "1920x1080" in user_error("--images", lone, "--intrinsics", k, *meshes, "--out", tmp_path / "o3")
    # K in an unknown form
    k.write_text(json.dumps({"focal": 600}))
    assert "expected" in user_error("--images", lone, "--intrinsics", k, *meshes, "--out", tmp_path / "o4")
    # depth of another size
    k.write_text(json.dumps({"fx": 600, "fy": 600, "cx": 320, "cy": 240}))
    dep = tmp_path / "depth"
    dep.mkdir()
    images.write_depth(dep / "photo.png", np.ones((240, 320)), 1.0)
    msg = user_error("--images", lone, "--intrinsics", k, "--depth", dep, "--depth-scale", 1, *meshes, "--out",
                     tmp_path / "o5")
    assert "320x240" in msg and "640x480" in msg
    # a box label that is no object, a box outside the image
    boxes = tmp_path / "boxes.json"
    boxes.write_text(json.dumps([{"label": "barbecue_sauce", "bbox_modal": [1, 2, 30, 40]}]))
    msg = user_error("--images", lone, "--intrinsics", k, "--boxes", boxes, *meshes, "--out", tmp_path / "o6")
    assert "did you mean 'barbecue-sauce'" in msg
    boxes.write_text(json.dumps([{"label": "barbecue-sauce", "bbox_modal": [600, 400, 700, 470]}]))
    assert "leaves the 640x480 image" in user_error("--images", lone, "--intrinsics", k, "--boxes", boxes, *meshes,
                                                    "--out", tmp_path / "o7")
    # no meshes
    (tmp_path / "empty").mkdir()
    assert "no mesh files" in user_error("--images", lone, "--intrinsics", k, "--meshes", tmp_path / "empty",
                                         "--out", tmp_path / "o8")
    assert not any((tmp_path / f"o{i}").exists() for i in range(1, 9))


@needs_megapose
def test_estimate_runs_on_new_dataset(bbq_dataset, tmp_path):
    """templates + estimate with the imported boxes (CPU: templates coarse, a few seconds)."""
    out = tmp_path / "est" / "candidates.csv"
    code, stdout, err = run("templates", "--models", bbq_dataset / "models", "--out", tmp_path / "templates",
                            "--conf", "fast")
    assert code == 0, err
    code, stdout, err = run("estimate", "--dataset", bbq_dataset, "--detections", bbq_dataset / "detections.json",
                            "--templates-dir", tmp_path / "templates", "--out", out, "--quiet")
    assert code == 0, err
    res = bop.read_results(out)
    assert len(res) == 1 and int(res.table.obj_id[0]) == 1
    assert 100 < float(res.T_cam_obj[0, 2, 3]) < 2000  # mm in front of the camera


@needs_megapose
def test_exif_turned_jpeg_and_depth_in_metres(tmp_path):
    """A phone JPEG stored landscape with EXIF orientation 6 is written upright (PNG) and checked
    against the upright K; float depth in metres (.npy) with --depth-scale 1000 becomes mm."""
    from PIL import Image

    imgs, dep = tmp_path / "imgs", tmp_path / "depth"
    imgs.mkdir(), dep.mkdir()
    exif = Image.Exif()
    exif[0x0112] = 6  # rotate 90 degrees clockwise when shown
    Image.open(BBQ / "image_rgb.png").save(imgs / "phone.jpg", exif=exif.tobytes(), quality=92)
    (imgs / "camera.json").write_text(json.dumps({"fx": 600, "fy": 600, "cx": 240, "cy": 320, "width": 480,
                                                  "height": 640}))
    z_m = np.linspace(0.5, 1.5, 480 * 640, dtype=np.float32).reshape(640, 480)
    np.save(dep / "phone.npy", z_m)
    out = tmp_path / "ds"
    code, stdout, err = new_dataset("--images", imgs, "--depth", dep, "--depth-scale", 1000, "--meshes",
                                    BBQ / "meshes", "--out", out, "--no-symmetries")
    assert code == 0, err
    assert "EXIF" in stdout
    assert images.image_size(out / "test" / "000001" / "rgb" / "000000.png") == (480, 640)
    from cosy_cli.io.dataset import BopDataset

    np.testing.assert_allclose(BopDataset(out, "test").read_depth(1, 0), z_m * 1000, atol=0.06)
    code, _, err = run("validate", "--dataset", out)
    assert code == 0, err
