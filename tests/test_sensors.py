"""Multi-sensor BOP datasets (IPD, XYZ-IBD, ITODD-MV layout): reading, cosy synth --sensors, rig groups, cosy run."""

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cosy_cli.cli.main import cli
from cosy_cli.errors import CosyError
from cosy_cli.io import bop, images
from cosy_cli.io.dataset import BopDataset, RigDataset, parse_split_spec, with_sensor
from cosy_cli.multiview import match_stage
from cosy_cli.pipeline import run_stage

DATA = Path(__file__).resolve().parents[1] / "data_samples"

# sensor: (kind, width, height)
SENSORS = {"photoneo": ("gray", 40, 30), "cam1": ("rgb", 64, 36), "cam2": ("rgb", 32, 24)}


def _K(w, h, f=50.0):
    return np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])


def _pose(x):
    T = np.eye(4)
    T[:3, 3] = [x, 0.0, 500.0]
    return T


def make_multi_sensor(root: Path, sensors=SENSORS, n_images=2, info=None) -> Path:
    """A hand-made multi-sensor split: one scene, ``n_images`` instants per sensor."""
    scene = root / "test" / "000001"
    for k, (s, (kind, w, h)) in enumerate(sensors.items()):
        bop.write_camera(root / f"camera_{s}.json", bop.CameraInfo(K=_K(w, h), width=w, height=h))
        cams = {}
        for im in range(n_images):
            img = np.full((h, w, 3), 40 * (k + 1) + im, np.uint8)
            img[..., 0] += 10  # not grey in RGB
            (images.write_gray if kind == "gray" else images.write_rgb)(scene / f"{kind}_{s}" / f"{im:06d}.png", img)
            images.write_depth(scene / f"depth_{s}" / f"{im:06d}.png", np.full((h, w), 500.0, np.float32))
            cams[im] = bop.SceneCamera(K=_K(w, h), T_cam_world=_pose(100.0 * k))
        bop.write_scene_camera(scene / f"scene_camera_{s}.json", cams)
    if info is not None:
        (root / "dataset_info.json").write_text(json.dumps(info))
    return root


def test_multi_sensor_layout_is_read_per_sensor(tmp_path):
    root = make_multi_sensor(tmp_path / "ds", info={"eval_sensor": "cam1"})
    ds = BopDataset(root, "test")
    assert ds.sensors == ["cam1", "cam2", "photoneo"] and ds.is_multi_sensor
    assert ds.eval_sensor == "cam1" and ds.scene_file(1, "scene_camera").name == "scene_camera_cam1.json"
    assert ds.camera_path.name == "camera_cam1.json"
    assert ds.image_size(1, 0) == (64, 36) and ds.image_dir(1).name == "rgb_cam1" and not ds.is_gray(1)
    g = BopDataset(root, "test", sensor="photoneo")
    assert g.image_dir(1).name == "gray_photoneo" and g.is_gray(1) and g.camera_path.name == "camera_photoneo.json"
    img = g.read_rgb(1, 1)  # grey: one channel on disk, three equal ones when read
    assert img.shape == (30, 40, 3) and (img[..., 0] == img[..., 1]).all() and (img[..., 1] == img[..., 2]).all()
    assert images.is_gray_file(g.rgb_path(1, 1)) and not images.is_gray_file(ds.rgb_path(1, 1))
    assert g.read_depth(1, 0).shape == (30, 40)
    assert g.mask_path(1, 0, 2).parent.name == "mask_photoneo"
    # the split spec carries the sensor through every stage
    assert BopDataset(root, "test:cam2").image_size(1, 0) == (32, 24)
    assert parse_split_spec("test:cam2") == ("test", "cam2") and with_sensor("test", "cam2") == "test:cam2"
    assert BopDataset(root, "test:cam2").split_spec == "test:cam2"


def test_the_evaluation_sensor_default(tmp_path):
    # the BOP toolkit's evaluation sensor of a known dataset, by folder name
    xyz = make_multi_sensor(tmp_path / "xyzibd", {"xyz": ("gray", 40, 30), "realsense": ("rgb", 32, 24)})
    assert BopDataset(xyz, "test").eval_sensor == "xyz"
    only = make_multi_sensor(tmp_path / "one", {"cam0": ("rgb", 40, 30)})
    assert BopDataset(only, "test").eval_sensor == "cam0"
    amb = make_multi_sensor(tmp_path / "mine", {"a": ("rgb", 40, 30), "b": ("gray", 32, 24)})
    with pytest.raises(CosyError, match=r"several sensors \(a, b\).*--sensor"):
        BopDataset(amb, "test").read_rgb(1, 0)
    with pytest.raises(CosyError, match=r"no sensor 'c' in test \(sensors: a, b\)"):
        BopDataset(amb, "test", sensor="c")
    r = CliRunner().invoke(cli, ["validate", "--dataset", str(amb), "--sensor", "c"])
    assert r.exit_code == 2 and "sensors: a, b" in r.output


def test_classic_datasets_have_no_sensors():
    ds = BopDataset(DATA, "test")
    assert ds.sensors == [] and ds.eval_sensor is None and ds._sensor_for(ds.scene_ids[0]) is None
    assert ds.split_spec == "test"
    with pytest.raises(CosyError, match="no multi-sensor layout"):
        BopDataset(DATA, "test:rig")


def test_the_rig_is_one_dataset_of_rig_views(tmp_path):
    root = make_multi_sensor(tmp_path / "ds", info={"eval_sensor": "photoneo"})
    rig = BopDataset(root, "test:rig")
    assert isinstance(rig, RigDataset) and rig.split_spec == "test:rig"
    cams = rig.scene_camera(1)
    assert sorted(cams) == [0, 1, 2, 3, 4, 5]  # im_id x 3 + sensor index
    assert rig.view_of(4) == ("cam2", 1) and rig.view_id("photoneo", 1) == 5
    assert rig.image_size(1, 4) == (32, 24) and rig.image_size(1, 5) == (40, 30)
    assert rig.is_gray(1, 5) and not rig.is_gray(1, 0)
    assert np.allclose(cams[4].T_cam_world, _pose(200.0))  # cam2 was written third: x = 200 mm
    groups = match_stage.make_groups(rig, [1], None, "instant")
    assert [g["im_ids"] for g in groups] == [[0, 1, 2], [3, 4, 5]]
    with pytest.raises(CosyError, match="instant"):
        match_stage.make_groups(BopDataset(root, "test:cam1"), [1], None, "instant")


def test_multiview_targets_reader_and_groups(tmp_path):
    root = make_multi_sensor(tmp_path / "ds", info={"eval_sensor": "cam1"})
    p = root / "test_targets_multiview_bop25.json"
    p.write_text(json.dumps([{"scene_id": 1, "im_id": [["cam1", 0], ["photoneo", 0]]},
                             {"scene_id": 1, "im_id": [["cam1", 1], ["cam2", 1], ["photoneo", 0]], "note": 1}]))
    t = bop.read_multiview_targets(p)
    assert t[0].views == [("cam1", 0), ("photoneo", 0)] and t[1].extra == {"note": 1}
    rig = BopDataset(root, "test:rig")
    assert [g["im_ids"] for g in match_stage.make_groups(rig, [1], None, "targets")] == [[0, 2], [2, 3, 4]]
    # one sensor of it: that sensor's images of each entry
    one = BopDataset(root, "test:cam1")
    assert [g["im_ids"] for g in match_stage.make_groups(one, [1], None, "targets")] == [[0], [1]]
    for bad, msg in (([{"scene_id": 1, "im_id": [["cam1", "0"]]}], "entry 0: im_id: expected"),
                     ([{"im_id": [["cam1", 0]]}], "entry 0"), ({"a": 1}, "expected a JSON list"),
                     ([{"scene_id": 1, "im_id": [["cam1", 0], ["cam1", 0]]}], "listed twice")):
        p.write_text(json.dumps(bad))
        with pytest.raises(CosyError, match=msg):
            bop.read_multiview_targets(p)
    p.write_text(json.dumps([{"scene_id": 1, "im_id": [["cam1", 7]]}]))
    with pytest.raises(CosyError, match="no image 7 of sensor 'cam1'"):
        match_stage.make_groups(rig, [1], None, "targets")


def test_single_sensor_targets_group_without_known_cameras(tmp_path):
    import shutil

    root = tmp_path / "ds"
    shutil.copytree(DATA, root)
    ds = BopDataset(root, "test")
    sid = ds.scene_ids[0]
    ims = ds.image_ids(sid)
    (root / "test_targets_multiview_bop25.json").write_text(json.dumps(
        [{"scene_id": sid, "im_id": [["default", i] for i in ims[:2]]}, {"scene_id": sid, "im_id": ims[2:4]}]))
    assert [g["im_ids"] for g in match_stage.make_groups(ds, [sid], None, "targets")] == [ims[:2], ims[2:4]]
    assert run_stage.plan_groups(ds, None) == ("test", None, "targets")
    assert run_stage.plan_groups(BopDataset(DATA, "test"), None) == ("test", None, None)  # as before
    with pytest.raises(CosyError, match="--groups instant"):
        run_stage.plan_groups(ds, "instant")


@pytest.fixture(scope="module")
def rig_dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("rig") / "ds"
    r = CliRunner().invoke(cli, ["synth", "--out", str(out), "--sensors", "3", "--scenes", "2", "--views", "3",
                                 "--objects", "4", "--width", "240", "--height", "180", "--quiet"])
    assert r.exit_code == 0, r.output
    return out


def test_synth_sensors_writes_the_multi_sensor_layout(rig_dataset):
    root = rig_dataset
    info = json.loads((root / "dataset_info.json").read_text())
    assert info["eval_sensor"] == "cam0" and info["sensors"] == ["cam0", "cam1", "cam2"]
    ds = BopDataset(root, "test")
    assert ds.sensors == ["cam0", "cam1", "cam2"] and ds.eval_sensor == "cam0"
    sizes, Ks, grey = {}, {}, []
    for s in ds.sensors:
        one = BopDataset(root, "test", sensor=s)
        sizes[s] = one.image_size(1, 0)
        cam = bop.read_camera(root / f"camera_{s}.json")
        assert (cam.width, cam.height) == sizes[s]
        Ks[s] = one.scene_camera(1)[0].K
        assert np.allclose(Ks[s], cam.K)
        if images.is_gray_file(one.rgb_path(1, 0)):
            grey.append(s)
        for kind in ("depth", "mask", "mask_visib"):
            assert (root / "test" / "000001" / f"{kind}_{s}").is_dir()
        assert one.scene_gt(1)[0] and one.scene_gt_info(1)[0]
    assert sizes["cam0"] == (240, 180) and len(set(sizes.values())) == 3
    assert len({float(K[0, 0]) for K in Ks.values()}) == 3
    assert grey == ["cam2"] and (root / "test" / "000001" / "gray_cam2").is_dir()
    # the rig: fixed sensor-to-sensor poses, one world frame per scene
    rig = BopDataset(root, "test:rig")
    cams = rig.scene_camera(1)
    rel = [cams[rig.view_id("cam1", i)].T_cam_world @ np.linalg.inv(cams[rig.view_id("cam0", i)].T_cam_world)
           for i in range(3)]
    assert np.allclose(rel[0], rel[1], atol=1e-3) and np.allclose(rel[0], rel[2], atol=1e-3)
    assert np.linalg.norm(rel[0][:3, 3]) > 100  # a baseline
    mv = json.loads((root / "test_targets_multiview_bop25.json").read_text())
    assert mv[0] == {"scene_id": 1, "im_id": [["cam0", 0], ["cam1", 0], ["cam2", 0]]} and len(mv) == 6
    b24 = json.loads((root / "test_targets_bop24.json").read_text())
    assert {(e["scene_id"], e["im_id"]) for e in b24} == {(s, i) for s in (1, 2) for i in range(3)}
    t = bop.read_targets(root / "test_targets_bop19.json")
    vis = BopDataset(root, "test:cam0").scene_gt_info(1)[0]
    assert int(t[(t.scene_id == 1) & (t.im_id == 0)].inst_count.sum()) == sum(g.visib_fract >= 0.1 for g in vis)


def test_run_on_a_rig_beats_single_view_on_the_evaluation_sensor(rig_dataset, tmp_path):
    out = tmp_path / "run"
    r = CliRunner().invoke(cli, ["run", "--dataset", str(rig_dataset), "--out", str(out), "--from-gt",
                                 "--config", "fast", "--to", "evaluate", "--quiet"])
    assert r.exit_code == 0, r.output
    m = json.loads((out / "run.json").read_text())
    assert m["split"] == "test:rig" and m["rig"]["eval_sensor"] == "cam0"
    assert m["confs"]["match"]["groups"] == "targets" and m["confs"]["match"]["known_cameras"] is True
    groups = json.loads((out / "refine" / "scene.json").read_text())["groups"]
    assert len(groups) == 6 and all(len(g["cameras"]) == 3 for g in groups)
    pred = bop.read_results(out / "refine" / "predictions_cam0.csv")
    assert set(pred.column("im_id").tolist()) <= {0, 1, 2} and len(pred) > 0
    sv = json.loads((out / "evaluate" / "single_view" / "scores.json").read_text())
    mv = json.loads((out / "evaluate" / "multi_view" / "scores.json").read_text())
    key = "bop19_average_recall_mssd_mspd"
    assert mv[key] > sv[key] + 0.01, (sv[key], mv[key])


def test_contour_crops_of_a_large_image_blur_only_their_window():
    """Per detection, the anti-aliased crop of a shrunk window equals the crop of the whole image
    blurred (the work no longer scales with the image: 4K images of IPD and ITODD-MV)."""
    import cv2

    from cosy_cli.singleview.training_free import contour

    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (700, 900, 3), dtype=np.uint8)
    K = _K(900, 700, 800.0)
    boxes = np.array([[100.0, 120.0, 420.0, 400.0], [600.0, 300.0, 890.0, 690.0], [0.0, 0.0, 899.0, 699.0]])
    conf = contour.ContourConf()
    _, crops, _, _ = contour.observe_windows(img, K, boxes, conf)
    win = contour.windows(boxes, conf.margin)
    A = contour.crop_affine(win, (conf.crop, conf.crop))
    for i in range(len(boxes)):
        scale = conf.crop / (win[i, 2] - win[i, 0])
        assert scale < 0.7
        ref = cv2.warpAffine(cv2.GaussianBlur(img, (0, 0), 0.5 / scale), A[i], (conf.crop, conf.crop),
                             flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        assert np.array_equal(crops[i], ref)


def test_verification_compares_a_grey_image_with_the_render_s_grey_levels():
    """A grey sensor (three equal channels) sees a coloured mesh as grey levels: the colour term of
    the right pose is as high as on the colour image (it compared red and blue with grey before)."""
    from painted_part import painted_part_view

    from cosy_cli.singleview.training_free.verify import Verifier, observe

    db, obj, rgb, K, T, box = painted_part_view()
    g = np.rint(rgb @ np.array([0.299, 0.587, 0.114])).astype(np.uint8)
    grey = np.repeat(g[..., None], 3, -1)
    with Verifier(db) as v:
        o_rgb, o_grey = observe(rgb, K, box, v.conf), observe(grey, K, box, v.conf)
        assert not o_rgb.grey and o_grey.grey
        colour = {}
        for name, o in (("rgb", o_rgb), ("grey", o_grey)):
            _, terms = v.score([o], np.array([0]), np.array([obj.obj_id]), T[None], terms=True)
            colour[name] = float(terms["colour"][0])
        o_grey.grey = False  # as if it were a colour image: red and blue against grey
        _, terms = v.score([o_grey], np.array([0]), np.array([obj.obj_id]), T[None], terms=True)
    assert colour["rgb"] > 0.8 and abs(colour["grey"] - colour["rgb"]) < 0.05, colour
    assert float(terms["colour"][0]) < colour["grey"] - 0.3


def test_verification_crops_of_a_large_image_are_made_from_their_window():
    """The verification's crop of a shrunk detection window (4K frame) is warped from the blurred
    window alone, with the same pixels as the whole image blurred, windows at the borders included."""
    import cv2

    from cosy_cli.geometry.camera import crop_affine
    from cosy_cli.singleview.training_free.verify import VerifyConf, observe

    conf = VerifyConf()
    S = conf.crop
    rng = np.random.default_rng(0)
    img = cv2.resize(rng.integers(0, 255, (270, 480, 3)).astype(np.uint8), (3840, 2160))
    K = np.array([[3000.0, 0, 1919.5], [0, 3000.0, 1079.5], [0, 0, 1]])
    for box in ([1000, 600, 1400, 1100], [10, 5, 500, 400], [3500, 1900, 3839, 2159], [100, 100, 2000, 2000]):
        x1, y1, x2, y2 = (float(v) for v in box)
        side = max(x2 - x1, y2 - y1) * (1 + 2 * conf.margin)
        cx, cy = (x1 + x2) / 2, (y1 + y2) / 2
        win = np.array([cx - side / 2, cy - side / 2, cx + side / 2, cy + side / 2])
        whole = cv2.GaussianBlur(img, (0, 0), 0.5 * side / S)
        ref = cv2.warpAffine(whole, crop_affine(win, (S, S)), (S, S), flags=cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_REPLICATE)
        got = observe(img, K, np.array(box, float), conf).rgb
        assert np.array_equal(np.rint(got * 255).astype(np.uint8), ref), box
