"""CosyPose's published networks: run directories, the network, and every step of the original
stage-1 path, checked against the original code's recorded inputs and outputs
(../shared/fixtures/cosypose_networks beside the repository, see its README for the tolerances used here).

Poses: the fixture is in metres, cosy in mm (converted here)."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

FIX = Path(os.environ.get("COSY_COSYPOSE_FIXTURES",
                          Path(__file__).resolve().parents[2] / "shared" / "fixtures" / "cosypose_networks"))
pytestmark = pytest.mark.skipif(not (FIX / "case.npz").is_file(), reason="CosyPose network fixtures not present")

RUNS = {"refiner": "run_b3", "coarse": "run_b3_coarse"}
# README section 5 (unchained mode: stored inputs of each iteration)
TOL = {"boxes_px": 1e-4, "K_crop_rel": 1e-6, "images_crop": 1e-5, "features": 1e-4, "pose": 1e-3, "T_m": 1e-5}
CHAINED = 10.0  # looser factor for iteration 2 fed from our iteration 1


def _mm(T):
    T = np.array(T, np.float64)
    T[..., :3, 3] *= 1000.0
    return T


@pytest.fixture(scope="module")
def case():
    return dict(np.load(FIX / "case.npz"))


@pytest.fixture(scope="module")
def cc():
    from cosy_cli.singleview.networks import cosypose_compat

    return cosypose_compat


@pytest.fixture(scope="module")
def points(cc):
    return cc.MeshPoints.from_models_dir(FIX / "mesh")


@pytest.fixture(scope="module")
def nets(cc):
    import torch

    torch.set_num_threads(2)
    return {p: cc.TorchCosyPoseNet(FIX / r) for p, r in RUNS.items()}


def _labels(case):
    return [int(str(lab)[-6:]) for lab in case["labels"]]


# ------------------------------------------------------------------------------------------------
# run directories
# ------------------------------------------------------------------------------------------------
def test_config_yaml_is_read_safely(cc):
    import yaml

    text = (FIX / "run_b3" / "config.yaml").read_text()
    with pytest.raises(yaml.YAMLError):  # what a plain safe loader says about the python tags
        yaml.safe_load(text)
    cfg = cc.load_config(FIX / "run_b3" / "config.yaml")
    assert cfg["input_resize"] == [640, 480]
    assert cfg["save_dir"] == "/cosypose/local_data/experiments/bop-ycbv-pbr-refiner--985772"
    assert cfg["train_ds_names"] == [["ycbv.pbr", 1]] and cfg["val_ds_names"] == cfg["train_ds_names"]
    r = cc.read_run(FIX / "run_b3")
    assert (r.kind, r.init_method, r.backbone, r.n_pose_dims) == ("refiner", "v0", "efficientnet-b3", 9)
    assert (r.object_ds_name, r.urdf_ds_name, r.run_id) == ("ycbv.bop", "ycbv", "bop-ycbv-pbr-refiner--985772")
    c = cc.read_run(FIX / "run_b3_coarse")
    assert (c.kind, c.init_method) == ("coarse", "z-up+auto-depth")


def test_arbitrary_python_objects_are_refused(cc, tmp_path):
    from cosy_cli.errors import CosyError

    p = tmp_path / "config.yaml"
    p.write_text("!!python/object:argparse.Namespace\nx: !!python/object/apply:os.system ['echo pwned']\n")
    with pytest.raises(CosyError, match="unsupported python tag"):
        cc.load_config(p)


def test_missing_init_method_defaults_to_v0_and_missing_files_are_named(cc, tmp_path):
    from cosy_cli.errors import CosyError

    run = tmp_path / "run"
    run.mkdir()
    text = (FIX / "run_b3_coarse" / "config.yaml").read_text()
    (run / "config.yaml").write_text("".join(ln for ln in text.splitlines(True) if not ln.startswith("init_method")))
    with pytest.raises(CosyError, match="checkpoint.pth.tar missing"):
        cc.read_run(run)
    (run / "checkpoint.pth.tar").symlink_to(FIX / "run_b3_coarse" / "checkpoint.pth.tar")
    r = cc.read_run(run)
    assert r.kind == "coarse" and r.init_method == "v0"

    from cosy_cli.cli.main import cli

    empty = tmp_path / "empty"
    empty.mkdir()
    res = CliRunner().invoke(cli, ["export", "--run", str(empty), "--out", str(tmp_path / "x.onnx")])
    assert res.exit_code == 2
    assert "config.yaml and checkpoint.pth.tar missing" in res.output and "checkpoint.pt" in res.output


def test_checkpoint_loads_on_cpu_weights_only(cc):
    sd = cc.load_state_dict(FIX / "run_b3" / "checkpoint.pth.tar")
    assert len(sd) == 574
    assert tuple(sd["backbone._conv_stem.weight"].shape) == (40, 6, 3, 3)
    assert tuple(sd["pose_fc.weight"].shape) == (9, 1536)


# ------------------------------------------------------------------------------------------------
# mesh database and initialisation
# ------------------------------------------------------------------------------------------------
def test_mesh_database_points_are_the_originals(cc, points, case):
    mp = np.load(FIX / "mesh" / "mesh_points.npz")
    for i, lab in enumerate(mp["labels"]):
        oid = int(str(lab)[-6:])
        np.testing.assert_allclose(points.padded[oid] * 1e-3, mp["points_padded"][i], atol=1e-8)
    assert np.array_equal(points.sample_ids, mp["sample_ids"])
    got = points.select(_labels(case)) * 1e-3
    np.testing.assert_allclose(got, case["refiner_sample_points"], atol=1e-8)
    np.testing.assert_allclose(got, case["coarse_init_sample_points"], atol=1e-8)
    # a modern loader's file order gives other points
    assert np.abs(mp["obj_000001_sample_points_if_file_order"] - mp["obj_000001_sample_points"]).max() > 1e-3


@pytest.mark.parametrize("method,key", [("z-up+auto-depth", "coarse_TCO_init"), ("v0", "coarse_TCO_init_v0")])
def test_coarse_initial_poses(cc, points, case, method, key):
    T = cc.init_poses(case["K"], case["detection_boxes"], points.select(_labels(case)), method)
    ref = _mm(case[key])
    np.testing.assert_allclose(T[:, :3, :3], ref[:, :3, :3], atol=1e-6)
    np.testing.assert_allclose(T[:, :3, 3], ref[:, :3, 3], atol=TOL["T_m"] * 1e3)


# ------------------------------------------------------------------------------------------------
# the network path, iterations 1 and 2
# ------------------------------------------------------------------------------------------------
def _check_step(rec, case, p, it, factor=1.0, report=None):
    """Compare a StepRecord with the stored arrays of iteration ``it``; returns max abs diffs."""
    d = {
        "boxes_rend_px": np.abs(rec.boxes_rend - case[f"{p}_it{it}_boxes_rend"]).max(),
        "boxes_crop_px": np.abs(rec.boxes_crop - case[f"{p}_it{it}_boxes_crop"]).max(),
        "K_crop_rel": (np.abs(rec.K_crop - case[f"{p}_it{it}_K_crop"]).max(axis=(1, 2))
                       / np.abs(case[f"{p}_it{it}_K_crop"]).max(axis=(1, 2))).max(),
        "images_crop": np.abs(rec.images_crop - case[f"{p}_it{it}_images_crop"]).max(),
        "pose": np.abs(rec.pose - case[f"{p}_it{it}_pose"]).max(),
        "T_out_m": np.abs(rec.T_output[:, :3, 3] * 1e-3 - case[f"{p}_it{it}_TCO_output"][:, :3, 3]).max(),
        "R_out": np.abs(rec.T_output[:, :3, :3] - case[f"{p}_it{it}_TCO_output"][:, :3, :3]).max(),
    }
    if report is not None:
        report[f"{p} it{it}{' chained' if factor > 1 else ''}"] = d
    print(p, it, "chained" if factor > 1 else "", {n: f"{x:.2e}" for n, x in d.items()})
    assert d["boxes_rend_px"] <= TOL["boxes_px"] * factor and d["boxes_crop_px"] <= TOL["boxes_px"] * factor
    assert d["K_crop_rel"] <= TOL["K_crop_rel"] * factor
    # chained: the crop box moves with the pose (<= 1e-3 px here), and a sharp edge moves with it
    assert d["images_crop"] <= (TOL["images_crop"] if factor == 1 else TOL["boxes_px"] * factor)
    assert d["pose"] <= TOL["pose"] * factor
    assert d["T_out_m"] <= TOL["T_m"] * factor and d["R_out"] <= TOL["pose"] * factor
    return d


def test_roi_align_from_the_stored_boxes_is_the_originals(cc, case):
    for p in RUNS:
        for it in (1, 2):
            crops = cc.roi_align(case["images"], case[f"{p}_it{it}_boxes_crop"])
            assert np.abs(crops - case[f"{p}_it{it}_images_crop"]).max() <= TOL["images_crop"]
            Kc = cc.K_crop_resize(case["K"], case[f"{p}_it{it}_boxes_crop"])
            ref = case[f"{p}_it{it}_K_crop"]
            assert (np.abs(Kc - ref).max(axis=(1, 2)) / np.abs(ref).max(axis=(1, 2))).max() <= TOL["K_crop_rel"]


@pytest.mark.parametrize("p", list(RUNS))
def test_iterations_reproduce_the_original(cc, nets, points, case, p):
    import torch

    stage = cc.CosyPoseRenderAndCompare(nets[p], renderer=None, points=points)
    labels = _labels(case)
    report = {}
    # iteration 1, with the backbone map and pooled features
    T1 = _mm(case[f"{p}_it1_TCO_input"])
    rec = stage.forward(case["images"], case["K"], labels, T1, renders=case[f"{p}_it1_renders"])
    _check_step(rec, case, p, 1, report=report)
    # the network alone, on the stored input (image crop + injected render) of iteration 1
    x = torch.as_tensor(np.concatenate([case[f"{p}_it1_images_crop"], case[f"{p}_it1_renders"]], 1))
    with torch.no_grad():
        fmap = nets[p].module.feature_map(x).numpy()
    assert fmap.shape == (3, 1536, 7, 10)  # 7 rows: the static padding for 300 px (dynamic would give 8)
    report[f"{p} it1 network"] = {"fmap": np.abs(fmap - case[f"{p}_it1_backbone_fmap"]).max()}
    assert report[f"{p} it1 network"]["fmap"] <= TOL["features"]
    # pooled features from our own crops (float32 noise through 26 blocks: ~1e-4 on the map)
    x = torch.as_tensor(np.concatenate([rec.images_crop, rec.renders], 1))
    with torch.no_grad():
        feat = nets[p].module.features(x).numpy()
    report[f"{p} it1"]["pooled_features"] = np.abs(feat - case[f"{p}_it1_pooled_features"]).max()
    assert report[f"{p} it1"]["pooled_features"] <= TOL["features"]
    # iteration 2 unchained (stored input) and chained (our iteration-1 output), stored render injected
    T2 = _mm(case[f"{p}_it2_TCO_input"])
    rec2 = stage.forward(case["images"], case["K"], labels, T2, renders=case[f"{p}_it2_renders"])
    _check_step(rec2, case, p, 2, report=report)
    x2 = torch.as_tensor(np.concatenate([rec2.images_crop, rec2.renders], 1))
    with torch.no_grad():
        feat2 = nets[p].module.features(x2).numpy()
    report[f"{p} it2"]["pooled_features"] = np.abs(feat2 - case[f"{p}_it2_pooled_features"]).max()
    assert report[f"{p} it2"]["pooled_features"] <= TOL["features"]
    rec2c = stage.forward(case["images"], case["K"], labels, rec.T_output, renders=case[f"{p}_it2_renders"])
    _check_step(rec2c, case, p, 2, factor=CHAINED, report=report)
    for k, v in report.items():
        print(k, {n: f"{x:.2e}" for n, x in v.items()})


# ------------------------------------------------------------------------------------------------
# ONNX export and the estimate stage
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    from cosy_cli.cli.main import cli

    out = tmp_path_factory.mktemp("cp") / "coarse.onnx"
    r = CliRunner().invoke(cli, ["export", "--run", str(FIX / "run_b3_coarse"), "--out", str(out)],
                           catch_exceptions=False)
    assert r.exit_code == 0, r.output
    return out


def test_export_onnx_matches_the_original(cc, exported, case):
    net = cc.OnnxCosyPoseNet(exported, threads=2)
    assert net.kind == "coarse" and net.init_method == "z-up+auto-depth"
    card = exported.with_suffix(".md").read_text()
    assert "coarse" in card and "z-up+auto-depth" in card and "ycbv.bop" in card and "ycbv/models" in card
    for it in (1, 2):
        x = np.concatenate([case[f"coarse_it{it}_images_crop"], case[f"coarse_it{it}_renders"]], 1)
        assert np.abs(net(x) - case[f"coarse_it{it}_pose"]).max() <= TOL["pose"]
    assert net(x[:1]).shape == (1, 9)  # dynamic batch


def _tiny_dataset(case, root: Path) -> Path:
    """The fixture's three images as one BOP scene (each with its own K), the fixture meshes as models."""
    from cosy_cli.io.images import write_rgb

    shutil.copytree(FIX / "mesh", root / "models", ignore=shutil.ignore_patterns("*.npz"))
    (root / "camera.json").write_text(json.dumps({"width": 640, "height": 480, "fx": 600.0, "fy": 600.0,
                                                  "cx": 320.0, "cy": 240.0, "depth_scale": 1.0}))
    scene = root / "test" / "000001"
    (scene / "rgb").mkdir(parents=True)
    cams, dets = {}, []
    for i in range(3):
        rgb = np.round(case["images"][i].transpose(1, 2, 0) * 255).astype(np.uint8)
        write_rgb(scene / "rgb" / f"{i:06d}.png", rgb)
        cams[str(i)] = {"cam_K": case["K"][i].reshape(-1).tolist(), "depth_scale": 1.0}
        x1, y1, x2, y2 = (float(v) for v in case["detection_boxes"][i])
        dets.append({"scene_id": 1, "image_id": i, "category_id": _labels(case)[i], "score": 1.0,
                     "bbox": [x1, y1, x2 - x1, y2 - y1], "time": 0.0})
    (scene / "scene_camera.json").write_text(json.dumps(cams))
    (root / "dets.json").write_text(json.dumps(dets))
    return root


def test_estimate_runs_cosypose_networks(cc, exported, nets, case, tmp_path, points):
    """`cosy estimate --coarse ONNX --refiner RUN_DIR` gives what the compat loop gives directly."""
    from cosy_cli.cli.main import cli
    from cosy_cli.io import bop
    from cosy_cli.objects import ObjectDatabase
    from cosy_cli.rendering import SceneRenderer

    root = _tiny_dataset(case, tmp_path / "ds")
    out = tmp_path / "cands.csv"
    r = CliRunner().invoke(cli, ["estimate", "--dataset", str(root), "--split", "test", "--detections",
                                 str(root / "dets.json"), "--coarse", str(exported), "--refiner",
                                 str(FIX / "run_b3"), "--depth-refine", "none", "--refiner-iterations", "1",
                                 "--out", str(out)], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    assert "coarse network -> refiner x1" in r.output
    res = bop.read_results(out)
    order = np.argsort(res.table["im_id"].to_numpy())
    got = res.T_cam_obj[order]
    assert len(got) == 3
    db = ObjectDatabase.from_models_dir(root / "models")
    labels = _labels(case)
    with SceneRenderer({o.obj_id: o.mesh for o in db}, 64, 64) as ren:
        coarse = cc.CosyPoseRenderAndCompare(cc.OnnxCosyPoseNet(exported), ren, points)
        refiner = cc.CosyPoseRenderAndCompare(nets["refiner"], ren, points)
        for i in range(3):
            rgb = np.round(case["images"][i].transpose(1, 2, 0) * 255).astype(np.uint8)
            T0 = coarse.initial_poses(case["K"][i], case["detection_boxes"][i:i + 1], [labels[i]])
            np.testing.assert_allclose(T0[:, :3, 3], _mm(case["coarse_TCO_init"][i:i + 1])[:, :3, 3], atol=1e-2)
            T = refiner.step(rgb, case["K"][i], coarse.step(rgb, case["K"][i], T0, [labels[i]]), [labels[i]])
            np.testing.assert_allclose(got[i][:3, 3], T[0, :3, 3], atol=0.05)  # mm (CSV keeps 6 digits)
            np.testing.assert_allclose(got[i][:3, :3], T[0, :3, :3], atol=1e-5)


def test_renders_use_the_mesh_colours_on_black(cc, case, points):
    from cosy_cli.objects import ObjectDatabase
    from cosy_cli.rendering import SceneRenderer

    db = ObjectDatabase.from_models_dir(FIX / "mesh")
    with SceneRenderer({o.obj_id: o.mesh for o in db}, 64, 64) as ren:
        T = _mm(case["refiner_it1_TCO_input"])
        rend = cc.render_crops(ren, case["refiner_it1_K_crop"].astype(np.float64), _labels(case), T)
    assert rend.shape == (3, 3, 240, 320) and rend.dtype == np.float32
    stored = case["refiner_it1_renders"]
    for b in range(3):
        ours, ref = rend[b].sum(0) > 0, stored[b].sum(0) > 0
        iou = (ours & ref).sum() / (ours | ref).sum()
        assert iou > 0.9, iou  # same silhouette as the original's renders (splats of the same mesh)
        assert (rend[b][:, ~ours] == 0).all()  # black background
        # coloured like the mesh (the vertex colours): same chromaticity as the stored render (the
        # fixture's renders are point splats with their own shading; brightness is not compared)
        both = ours & ref
        chroma = [x[:, both] / np.maximum(x[:, both].sum(0), 1e-6) for x in (rend[b], stored[b])]
        print("chromaticity diff", np.abs(chroma[0] - chroma[1]).mean())
        assert np.abs(chroma[0] - chroma[1]).mean() < 0.05
