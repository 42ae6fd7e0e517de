"""Detections' segmentations: RLE / polygon reading (io/masks.py) and their use by `cosy estimate`
(the verification's mask term)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from pycocotools import mask as mask_util

from cosy_cli.cli.main import cli
from cosy_cli.io.masks import SegmentationError, decode_segmentation, encode_mask
from test_estimate import SAMPLES, SCENE


def _random_mask(rng, H=37, W=53):
    m = np.zeros((H, W), bool)
    for _ in range(3):
        y, x = rng.integers(0, H - 5), rng.integers(0, W - 5)
        m[y:y + rng.integers(2, 15), x:x + rng.integers(2, 20)] = True
    return m


def test_rle_round_trip_and_pycocotools_forms():
    rng = np.random.default_rng(0)
    for k in range(20):
        m = _random_mask(rng)
        if k % 3 == 0:
            m[0, 0] = True  # a mask that starts with a foreground pixel: the RLE starts with an empty run
        rle = encode_mask(m)
        assert rle["size"] == [37, 53] and sum(rle["counts"]) == 37 * 53
        assert np.array_equal(decode_segmentation(rle, (37, 53)), m)
        # the same RLE as pycocotools computes (compressed, then uncompressed to runs by its decoder)
        coco = mask_util.encode(np.asfortranarray(m.astype(np.uint8)))
        assert np.array_equal(mask_util.decode(mask_util.frPyObjects(rle, 37, 53)), m.astype(np.uint8))
        coco["counts"] = coco["counts"].decode()  # as JSON files hold it
        assert np.array_equal(decode_segmentation(coco, (37, 53)), m)
    # COCO polygons: a square of 10 x 10 px
    sq = decode_segmentation([[10, 10, 20, 10, 20, 20, 10, 20]], (37, 53))
    assert 90 <= sq.sum() <= 121 and sq[15, 15] and not sq[5, 5]


@pytest.mark.parametrize("seg,shape,msg", [
    ({"counts": [5, 5], "size": [3, 4]}, (3, 4), "summing to 12"),
    ({"counts": [12], "size": [3, 4]}, (4, 4), "3x4 .*4x4"),
    ({"size": [3, 4]}, (3, 4), "counts"),
    ({"counts": 7, "size": [3, 4]}, (3, 4), "list of run lengths"),
    ([[1, 2, 3]], (3, 4), "at least 3 points"),
    ("abc", (3, 4), "RLE dict or a list of polygons"),
])
def test_malformed_segmentations_say_what_is_wrong(seg, shape, msg):
    with pytest.raises(SegmentationError, match=msg):
        decode_segmentation(seg, shape)


def _gt_detections_with_masks(scene_dir, im_ids=None):
    gt = json.loads((scene_dir / "scene_gt.json").read_text())
    info = json.loads((scene_dir / "scene_gt_info.json").read_text())
    from PIL import Image

    dets = []
    for k in sorted(gt, key=int):
        if im_ids is not None and int(k) not in im_ids:
            continue
        for j, (g, i) in enumerate(zip(gt[k], info[k])):
            if i["visib_fract"] < 0.1:
                continue
            m = np.asarray(Image.open(scene_dir / "mask_visib" / f"{int(k):06d}_{j:06d}.png")) > 0
            dets.append({"scene_id": 1, "image_id": int(k), "category_id": g["obj_id"], "score": 1.0,
                         "bbox": i["bbox_visib"], "segmentation": encode_mask(m)})
    return dets


def test_estimate_uses_the_detections_masks(tmp_path):
    """BOP default-detections style input (bbox + RLE segmentation): `cosy estimate` uses the masks
    (recorded in its settings, said in its log), gives as good poses on the sample scene, and
    refuses a segmentation of the wrong size naming the detection."""
    from cosy_cli.evaluation.pose_error import adi
    from cosy_cli.io import bop
    from cosy_cli.io.dataset import BopDataset
    from cosy_cli.objects import ObjectDatabase

    dets = _gt_detections_with_masks(SCENE, im_ids={0, 1})
    f = tmp_path / "dets.json"
    f.write_text(json.dumps(dets))
    tpl = tmp_path / "tpl"
    from cosy_cli.singleview.training_free import templates

    templates.main({"viewpoints": 200, "inplane": 24}, SAMPLES / "models", tpl, log=lambda *_: None)
    outs = {}
    for masks in ("auto", "none"):
        out = tmp_path / f"c_{masks}.csv"
        r = CliRunner().invoke(cli, ["estimate", "--scene", str(SCENE), "--detections", str(f), "--masks", masks,
                                     "--coarse", "templates", "--refiner", "none", "--depth-refine", "icp",
                                     "--templates-dir", str(tpl), "--out", str(out)], catch_exceptions=False)
        assert r.exit_code == 0, r.output
        doc = json.loads((tmp_path / f"c_{masks}.json").read_text())
        assert (doc["conf"].get("masks") == "detections") == (masks == "auto")
        assert ("have a segmentation" in r.output) == (masks == "auto")
        outs[masks] = bop.read_results(out)
    ds = BopDataset(SAMPLES, "test")
    db = ObjectDatabase.from_models_dir(SAMPLES / "models")
    gt = ds.scene_gt(1)
    recall = {}
    for masks, res in outs.items():
        ok = []
        for row, T in zip(res.table.itertuples(index=False), res.T_cam_obj):
            errs = [adi(T, g.T_cam_obj, db[row.obj_id].points)[0] for g in gt[row.im_id] if g.obj_id == row.obj_id]
            ok.append(min(errs) < 0.1 * db[row.obj_id].diameter)
        recall[masks] = float(np.mean(ok))
    assert len(outs["auto"]) == len(dets)
    assert recall["auto"] >= 0.8 and recall["auto"] >= recall["none"] - 0.1, recall
    bad = [dict(dets[0], segmentation={"counts": [10], "size": [2, 5]})] + dets[1:]
    f.write_text(json.dumps(bad))
    r = CliRunner().invoke(cli, ["estimate", "--scene", str(SCENE), "--detections", str(f), "--coarse", "templates",
                                 "--refiner", "none", "--templates-dir", str(tpl), "--out",
                                 str(tmp_path / "bad.csv")], catch_exceptions=False)
    assert r.exit_code == 2 and "dets.json" in r.output and "detection 0" in r.output and "2x5" in r.output
    assert "Traceback" not in r.output


def test_the_mask_term_prefers_the_pose_whose_silhouette_is_the_mask():
    """The verifier's mask term: the silhouette's IoU with the detection's segmentation, about 1 for
    the true pose, lower for a pose turned by 30 degrees; zero weight without a segmentation."""
    from painted_part import painted_part_view

    from cosy_cli.geometry.rotations import rotation_about_axis
    from cosy_cli.rendering import SceneRenderer
    from cosy_cli.singleview.training_free.verify import Verifier, observe

    db, obj, rgb, K, T, box = painted_part_view()
    with SceneRenderer({obj.obj_id: obj.mesh}, rgb.shape[1], rgb.shape[0]) as r:
        mask = r.render(K, [obj.obj_id], T[None]).instance >= 0
    turned = T.copy()
    turned[:3, :3] = rotation_about_axis(np.array([0.0, 1.0, 0.0]), [np.radians(30)])[0] @ T[:3, :3]
    with Verifier(db) as v:
        with_mask, without = observe(rgb, K, box, v.conf, mask), observe(rgb, K, box, v.conf)
        assert with_mask.seg is not None and without.seg is None
        poses = np.stack([T, turned])
        s_m, t_m = v.score([with_mask], np.array([0, 0]), np.full(2, obj.obj_id), poses, terms=True)
        s_0, t_0 = v.score([without], np.array([0, 0]), np.full(2, obj.obj_id), poses, terms=True)
    assert t_m["mask"][0] > 0.9 and t_m["mask"][1] < t_m["mask"][0] - 0.1, t_m["mask"]
    assert np.all(t_0["mask"] == 0)
    # the other terms are the same; the total moves towards the mask term by its weight
    for k in ("orient", "colour", "region", "box"):
        np.testing.assert_allclose(t_m[k], t_0[k])
    assert s_m[0] - s_m[1] > s_0[0] - s_0[1]
