"""Round trips of every BOP reader/writer, and the errors they give on bad input."""

import json

import numpy as np
import pandas as pd
import pytest
import trimesh

from cosy_cli import geometry as G
from cosy_cli.errors import CosyError
from cosy_cli.io import bop, images
from cosy_cli.io.atomic import atomic_dir, atomic_path, write_text
from cosy_cli.io.dataset import BopDataset


def rand_pose(rng):
    return G.make_pose(G.random_rotations(1, rng)[0], rng.normal(size=3) * 100 + [0, 0, 600])


def test_camera_round_trip(tmp_path):
    cam = bop.CameraInfo(K=np.array([[572.4114, 0, 325.2611], [0, 573.57043, 242.04899], [0, 0, 1]]), width=640,
                         height=480, depth_scale=0.1)
    bop.write_camera(tmp_path / "camera.json", cam)
    back = bop.read_camera(tmp_path / "camera.json")
    assert np.allclose(back.K, cam.K) and (back.width, back.height, back.depth_scale) == (640, 480, 0.1)


def test_scene_camera_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    cams = {i: bop.SceneCamera(K=np.array([[500, 0, 320 + i], [0, 500, 240], [0, 0, 1.0]]), depth_scale=0.1,
                               T_cam_world=rand_pose(rng) if i != 3 else None, extra={"elev": 45} if i == 2 else {})
            for i in (0, 2, 3, 10)}
    bop.write_scene_camera(tmp_path / "sc.json", cams)
    back = bop.read_scene_camera(tmp_path / "sc.json")
    assert list(back) == [0, 2, 3, 10]
    for i in cams:
        assert np.allclose(back[i].K, cams[i].K)
        if cams[i].T_cam_world is None:
            assert back[i].T_cam_world is None
        else:
            assert np.allclose(back[i].T_cam_world, cams[i].T_cam_world, atol=1e-6)
    assert back[2].extra == {"elev": 45}


@pytest.mark.parametrize("K, depth_scale, message", [
    ([[0, 0, 320], [0, 500, 240], [0, 0, 1]], 1.0, "fx and fy must be > 0, got fx=0"),
    ([[500, 0, 320], [0, -500, 240], [0, 0, 1]], 1.0, "fx and fy must be > 0"),
    ([[500, 0, 320], [0, 500, 240], [0, 0, 0]], 1.0, "last row is 0 0 0, expected 0 0 1"),
    ([[500, 0, 320], [0, 500, 240], [0, 0, 1]], 0.0, "depth_scale must be > 0"),
])
def test_scene_camera_that_is_no_pinhole_camera_is_refused_naming_the_image(tmp_path, K, depth_scale, message):
    """A K with fx = 0 or a singular last row made estimate, refine and the figures divide by zero
    or invert a singular matrix: the reader refuses it, naming the image (cosy validate, which
    lists every such image, reads without the check)."""
    good = np.array([[500, 0, 320], [0, 500, 240], [0, 0, 1.0]])
    cams = {0: bop.SceneCamera(K=good), 5: bop.SceneCamera(K=np.array(K, float), depth_scale=depth_scale)}
    bop.write_scene_camera(tmp_path / "sc.json", cams)
    with pytest.raises(CosyError, match=message) as e:
        bop.read_scene_camera(tmp_path / "sc.json")
    assert "image 5" in str(e.value) and "sc.json" in str(e.value)
    assert bop.read_scene_camera(tmp_path / "sc.json", check_intrinsics=False)[5].depth_scale == depth_scale


def test_scene_gt_and_info_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    gt = {5: [bop.GtInstance(3, rand_pose(rng)), bop.GtInstance(3, rand_pose(rng))], 7: []}
    bop.write_scene_gt(tmp_path / "gt.json", gt)
    back = bop.read_scene_gt(tmp_path / "gt.json")
    assert [g.obj_id for g in back[5]] == [3, 3] and back[7] == []
    assert np.allclose(back[5][1].T_cam_obj, gt[5][1].T_cam_obj, atol=1e-6)
    info = {5: [bop.GtInfo(np.array([1, 2, 30, 40]), np.array([2, 3, 20, 30]), 1200, 1100, 900, 0.75)] * 2, 7: []}
    bop.write_scene_gt_info(tmp_path / "info.json", info)
    bi = bop.read_scene_gt_info(tmp_path / "info.json")
    assert bi[5][0].px_count_visib == 900 and np.isclose(bi[5][1].visib_fract, 0.75)
    assert np.allclose(bi[5][0].bbox_visib, [2, 3, 20, 30])


def test_models_info_round_trip_with_symmetries(tmp_path):
    flip = G.make_pose(G.axis_angle_to_matrix(np.array([np.pi, 0, 0])), [0, 0, 12.5])
    infos = {
        1: bop.ModelInfo(102.3, np.array([-10, -20, -30.0]), np.array([20, 40, 60.0]), flip[None],
                         [{"axis": np.array([0, 0, 1.0]), "offset": np.array([0, 0, 6.25])}]),
        2: bop.ModelInfo(50.0, np.zeros(3), np.ones(3)),
    }
    bop.write_models_info(tmp_path / "models_info.json", infos)
    raw = json.loads((tmp_path / "models_info.json").read_text())
    assert len(raw["1"]["symmetries_discrete"][0]) == 16 and "symmetries_continuous" not in raw["2"]
    back = bop.read_models_info(tmp_path / "models_info.json")
    assert np.allclose(back[1].symmetries_discrete[0], flip)
    assert np.allclose(back[1].symmetries_continuous[0]["offset"], [0, 0, 6.25])
    assert back[2].symmetries_discrete.shape == (0, 4, 4)


def test_targets_round_trip(tmp_path):
    t = pd.DataFrame({"scene_id": [1, 1, 2], "im_id": [0, 3, 7], "obj_id": [5, 6, 5], "inst_count": [1, 2, 1]})
    bop.write_targets(tmp_path / "t.json", t)
    assert bop.read_targets(tmp_path / "t.json").equals(t)


def test_results_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    T = np.stack([rand_pose(rng) for _ in range(4)])
    res = bop.PoseResults.from_arrays([1, 1, 2, 2], [0, 1, 0, 5], [3, 4, 3, 1], [0.9, 0.5, 1.0, 0.25], T, 0.125)
    bop.write_results(tmp_path / "r.csv", res)
    text = (tmp_path / "r.csv").read_text().splitlines()
    assert text[0] == "scene_id,im_id,obj_id,score,R,t,time"
    back = bop.read_results(tmp_path / "r.csv")
    assert back.table[["scene_id", "im_id", "obj_id"]].values.tolist() == [[1, 0, 3], [1, 1, 4], [2, 0, 3], [2, 5, 1]]
    assert np.allclose(back.T_cam_obj, T, atol=1e-6)
    assert np.allclose(back.table.score, [0.9, 0.5, 1.0, 0.25]) and np.allclose(back.table.time, 0.125)


def test_results_reads_bop_toolkit_style_file(tmp_path):
    # the exact layout of a BOP challenge submission: spaces inside R and t, time column
    (tmp_path / "r.csv").write_text(
        "scene_id,im_id,obj_id,score,R,t,time\n"
        "48,1,2,0.87,1 0 0 0 1 0 0 0 1,-10.5 20 800.25,0.3\n"
        "48,1,5,0.5,0 -1 0 1 0 0 0 0 1,0 0 1000,0.3\n")
    r = bop.read_results(tmp_path / "r.csv")
    assert len(r) == 2 and np.allclose(r.T_cam_obj[0, :3, 3], [-10.5, 20, 800.25])
    assert np.allclose(r.T_cam_obj[1, :3, :3] @ [1, 0, 0], [0, 1, 0])


@pytest.mark.parametrize("body, message", [
    ("scene_id,im_id,obj_id,score,R\n", "missing column(s) t"),
    ("scene_id,im_id,obj_id,score,R,t,time\n1,2,3,0.5,1 0 0 0 1 0 0 0,0 0 1,1\n", "row 1: column R: expected 9"),
    ("scene_id,im_id,obj_id,score,R,t,time\n1,2,3,0.5,1 0 0 0 1 0 0 0 1,0 0 1,1\n1,x,3,0.5,1 0 0 0 1 0 0 0 1,0 0 1,1\n",
     "row 2: column im_id: expected an integer"),
    ("scene_id,im_id,obj_id,score,R,t,time\n1,2,3,0.5,2 0 0 0 1 0 0 0 1,0 0 1,1\n", "row 1: R is not a rotation"),
    ("scene_id,im_id,obj_id,score,R,t,time\n1,2,3,0.5,1 0 0 0 1 0 0 0 1,0 nan 1,1\n", "row 1: column t: non-finite"),
    ("scene_id,im_id,obj_id,score,R,t,time\n1,2,3,nan,1 0 0 0 1 0 0 0 1,0 0 1,1\n", "row 1: column score"),
])
def test_results_errors_name_file_and_row(tmp_path, body, message):
    p = tmp_path / "cands.csv"
    p.write_text(body)
    with pytest.raises(CosyError) as e:
        bop.read_results(p)
    assert message in str(e.value) and str(p) in str(e.value)


@pytest.mark.parametrize("content, message", [
    ('{"0": [{"cam_R_m2c": [1,0,0,0,1,0,0,0,1], "cam_t_m2c": [0,0,1]}]}', "image 0, instance 0: missing key 'obj_id'"),
    ('{"0": [{"cam_R_m2c": [1,0,0,0,1,0,0,0], "cam_t_m2c": [0,0,1], "obj_id": 1}]}', "cam_R_m2c: expected 9 numbers, got 8"),
    ('{"0": [{"cam_R_m2c": [1,0,0,0,1,0,0,0,1], "cam_t_m2c": [0,0,1], "obj_id": 1}', "invalid JSON"),
    ('{"a": []}', "key 'a' is not an integer id"),
    ('[1, 2]', "expected a JSON object keyed by id"),
])
def test_scene_gt_errors(tmp_path, content, message):
    p = tmp_path / "scene_gt.json"
    p.write_text(content)
    with pytest.raises(CosyError) as e:
        bop.read_scene_gt(p)
    assert message in str(e.value) and "scene_gt.json" in str(e.value)


def test_missing_file_error(tmp_path):
    with pytest.raises(CosyError, match="file not found"):
        bop.read_models_info(tmp_path / "nope.json")


def test_detections_round_trip(tmp_path):
    df = pd.DataFrame({"scene_id": [1, 1], "im_id": [3, 3], "obj_id": [2, 7], "score": [0.9, 0.4],
                       "x": [10.0, 20.5], "y": [5.0, 6.0], "w": [30.0, 40.0], "h": [50.0, 60.0], "time": [0.1, 0.1],
                       "segmentation": [None, {"counts": "abc", "size": [480, 640]}]})
    bop.write_detections(tmp_path / "d.json", df)
    raw = json.loads((tmp_path / "d.json").read_text())
    assert raw[0]["image_id"] == 3 and raw[0]["category_id"] == 2 and "segmentation" not in raw[0]
    back = bop.read_detections(tmp_path / "d.json")
    assert back[["scene_id", "im_id", "obj_id"]].values.tolist() == [[1, 3, 2], [1, 3, 7]]
    assert np.allclose(back[["x", "y", "w", "h"]].values, df[["x", "y", "w", "h"]].values)
    (tmp_path / "bad.json").write_text('[{"scene_id": 1, "image_id": 1, "category_id": 1, "score": 1, "bbox": [0, 0, 0, 5]}]')
    with pytest.raises(CosyError, match="detection 0: bbox has non-positive"):
        bop.read_detections(tmp_path / "bad.json")


def test_images_round_trip(tmp_path):
    rng = np.random.default_rng(4)
    rgb = rng.integers(0, 255, size=(48, 64, 3), dtype=np.uint8)
    images.write_rgb(tmp_path / "a.png", rgb)
    assert np.array_equal(images.read_rgb(tmp_path / "a.png"), rgb)
    assert images.image_size(tmp_path / "a.png") == (64, 48)
    images.write_rgb(tmp_path / "a.jpg", rgb)
    assert images.read_rgb(tmp_path / "a.jpg").shape == (48, 64, 3) and images.image_size(tmp_path / "a.jpg") == (64, 48)
    depth = rng.uniform(300, 1500, size=(48, 64)).astype(np.float32)
    depth[0, 0] = 0
    images.write_depth(tmp_path / "d.png", depth, depth_scale=0.1)
    back = images.read_depth(tmp_path / "d.png", depth_scale=0.1)
    assert back.dtype == np.float32 and np.abs(back - depth).max() <= 0.05 + 1e-4 and back[0, 0] == 0
    mask = rng.random((48, 64)) > 0.5
    images.write_mask(tmp_path / "m.png", mask)
    assert np.array_equal(images.read_mask(tmp_path / "m.png"), mask)
    (tmp_path / "broken.png").write_bytes(b"\x89PNG garbage")
    with pytest.raises(CosyError, match="unreadable image"):
        images.read_rgb(tmp_path / "broken.png")


def test_gray_images_read_as_rgb(tmp_path):
    import cv2
    g = np.arange(48 * 64, dtype=np.uint8).reshape(48, 64)
    cv2.imwrite(str(tmp_path / "g.png"), g)
    rgb = images.read_rgb(tmp_path / "g.png")
    assert rgb.shape == (48, 64, 3) and np.array_equal(rgb[..., 0], g)


def test_ply_models_ascii_and_binary_with_attributes(tmp_path):
    """PLYs with normals, colours, texture coordinates, ascii and binary, load through objects."""
    from cosy_cli.objects import load_mesh

    box = trimesh.creation.box([20, 30, 40])
    box.visual.vertex_colors = np.tile([200, 100, 50, 255], (len(box.vertices), 1))
    for enc in ("ascii", "binary"):
        p = tmp_path / f"obj_{enc}.ply"
        p.write_bytes(trimesh.exchange.ply.export_ply(box, encoding=enc, vertex_normal=True))
        m = load_mesh(p)
        assert np.allclose(m.vertices, box.vertices) and len(m.faces) == 12
        assert np.array_equal(np.asarray(m.visual.vertex_colors)[0, :3], [200, 100, 50])
    # texture coordinates (BOP stores them per vertex as texture_u/texture_v or s/t)
    uv = np.random.default_rng(0).random((len(box.vertices), 2))
    tex = trimesh.Trimesh(box.vertices, box.faces, visual=trimesh.visual.TextureVisuals(uv=uv), process=False)
    p = tmp_path / "obj_tex.ply"
    p.write_bytes(trimesh.exchange.ply.export_ply(tex, encoding="ascii"))
    m = load_mesh(p)
    assert len(m.vertices) == len(box.vertices)
    (tmp_path / "bad.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    with pytest.raises(CosyError, match="bad.ply"):
        load_mesh(tmp_path / "bad.ply")


def test_atomic_writes_leave_nothing_on_failure(tmp_path):
    target = tmp_path / "out.json"
    write_text(target, "old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash")
    assert target.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["out.json"]
    with pytest.raises(RuntimeError):
        with atomic_dir(tmp_path / "stage") as d:
            (d / "a.csv").write_text("x")
            raise RuntimeError("crash")
    assert not (tmp_path / "stage").exists() and [p.name for p in tmp_path.iterdir()] == ["out.json"]
    with atomic_dir(tmp_path / "stage") as d:
        (d / "a.csv").write_text("x")
    assert (tmp_path / "stage" / "a.csv").read_text() == "x"
    with pytest.raises(FileExistsError):
        with atomic_dir(tmp_path / "stage") as d:
            pass
    with atomic_dir(tmp_path / "stage", overwrite=True) as d:
        (d / "b.csv").write_text("y")
    assert sorted(p.name for p in (tmp_path / "stage").iterdir()) == ["b.csv"]


def _write_scene(d, sensor=None):
    suffix = f"_{sensor}" if sensor else ""
    img_dir = d / (sensor or "rgb")
    img_dir.mkdir(parents=True)
    cams = {0: bop.SceneCamera(K=np.eye(3)), 4: bop.SceneCamera(K=np.eye(3), depth_scale=0.5)}
    bop.write_scene_camera(d / f"scene_camera{suffix}.json", cams)
    bop.write_scene_gt(d / f"scene_gt{suffix}.json", {0: [], 4: []})
    for i in cams:
        images.write_rgb(img_dir / f"{i:06d}.jpg", np.zeros((4, 6, 3), np.uint8))
    (d / "depth").mkdir()
    images.write_depth(d / "depth" / "000004.png", np.full((4, 6), 100.0), depth_scale=0.5)


def test_dataset_layouts(tmp_path):
    _write_scene(tmp_path / "test_primesense" / "000002")
    ds = BopDataset(tmp_path, "test", split_type="primesense")
    assert ds.scene_ids == [2] and ds.image_ids(2) == [0, 4]
    assert ds.rgb_path(2, 4).name == "000004.jpg" and ds.read_rgb(2, 0).shape == (4, 6, 3)
    assert ds.read_depth(2, 4)[0, 0] == 100.0 and ds.read_depth(2, 0) is None
    # BOP-H3: per-sensor files and image folders
    _write_scene(tmp_path / "test_aria" / "000001", sensor="gray1")
    h3 = BopDataset(tmp_path, "test_aria")
    assert h3.scene_file(1, "scene_gt").name == "scene_gt_gray1.json"
    assert h3.image_dir(1).name == "gray1" and h3.image_ids(1) == [0, 4]
    with pytest.raises(CosyError, match="split folder 'val' not found"):
        _ = BopDataset(tmp_path, "val").scene_ids
