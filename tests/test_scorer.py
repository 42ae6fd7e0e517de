"""The learned hypothesis scorer: its target, its data, `cosy train scorer`, `cosy estimate --scorer`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cosy_cli.cli.main import cli
from cosy_cli.evaluation import pose_error
from cosy_cli.geometry.rotations import axis_angle_to_matrix
from cosy_cli.singleview import estimate_stage
from cosy_cli.training.scorer_target import ar_contribution, max_errors

SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"
SCENE = SAMPLES / "test" / "000001"
TINY = {"shards": 1, "val_shards": 1, "images_per_shard": 2, "iterations": 12, "checkpoint_every": 6, "log_every": 3,
        "workers": 0, "batch_size": 4, "warmup": 2, "verify_top": 12, "keep_best": 4, "keep_random": 2,
        "perturbed": 4}


def _run(args):
    return CliRunner().invoke(cli, args, catch_exceptions=False)


def test_target_errors_match_the_metrics_and_the_thresholds():
    rng = np.random.default_rng(3)
    P = rng.normal(size=(150, 3)) * 40
    S = np.stack([np.eye(4), np.diag([-1.0, -1.0, 1.0, 1.0])])  # a half-turn symmetry about z
    Tg = np.eye(4)
    Tg[:3, 3] = [30, -20, 700]
    Te = np.repeat(Tg[None], 6, 0)
    Te[:, :3, :3] = axis_angle_to_matrix(rng.normal(size=(6, 3)) * 0.15)
    Te[:, :3, 3] += rng.normal(size=(6, 3)) * 5
    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    e1, e2 = max_errors(Te, Tg, K, P, S)
    np.testing.assert_allclose(e1, pose_error.mssd(Te, Tg, P, S), rtol=1e-9)
    np.testing.assert_allclose(e2, pose_error.mspd(Te, Tg, K, P, S), rtol=1e-9)
    # the symmetric copy of the ground truth is exact
    Ts = Tg @ S[1]
    a, b = max_errors(Ts[None], Tg, K, P, S)
    assert a[0] < 1e-9 and b[0] < 1e-6
    # thresholds: MSSD 0.05..0.5 x diameter, MSPD 5..50 px x width / 640
    v = ar_contribution([4.0, 12.0, 60.0], [4.0, 12.0, 60.0], 100.0, 640)
    np.testing.assert_allclose(v, [1.0, 0.5 * (0.8 + 0.8), 0.0])
    assert ar_contribution([0.0], [15.0], 100.0, 1280)[0] == pytest.approx(0.5 * (1.0 + 0.9))  # 10..100 px


@pytest.fixture(scope="module")
def tiny_scorer(tmp_path_factory):
    from cosy_cli.training import scorer

    out = tmp_path_factory.mktemp("scorer") / "scorer.onnx"
    r = scorer.main(dict(TINY, arch="plain"), SAMPLES / "models", out, log=lambda *_: None, progress=False)
    return out, r


def test_train_scorer_writes_data_a_run_and_an_onnx(tiny_scorer):
    from cosy_cli.singleview.scorer.runtime import OnnxScorer
    from cosy_cli.training.scorer_data import load_shards

    out, r = tiny_scorer
    run = Path(r["run"])
    assert out.is_file() and (run / "checkpoint.pt").is_file() and (run / "log.csv").is_file()
    d = load_shards(run / "shards", [0])
    n = len(d["target"])
    assert n == r["hypotheses"] > 0 and d["rgba"].shape == (n, 64, 64, 4) and d["terms"].shape == (n, 8)
    assert d["det"].max() < len(d["obs_rgb"]) and set(np.unique(d["perturbed"])) <= {0, 1}
    assert 0 <= d["target"].min() and d["target"].max() <= 1
    # the poses near the ground truth earn more recall than the template matcher's hypotheses
    assert d["target"][d["perturbed"] == 1].mean() > d["target"][d["perturbed"] == 0].mean()
    sc = OnnxScorer(out)
    assert sc.crop == 64 and sc.obj_ids == list(range(1, 9)) and sc.unseen([1, 42]) == [42]
    assert sc.card["validation"]["detections"] > 0


def test_the_verifier_feeds_the_scorer_what_training_stored(tiny_scorer):
    """Inference inputs are the training inputs: score(inputs=True) assembled and run through the
    exported network gives exactly the verifier's learned scores."""
    from cosy_cli.io.dataset import BopDataset
    from cosy_cli.objects import ObjectDatabase
    from cosy_cli.singleview.scorer.features import assemble
    from cosy_cli.singleview.scorer.runtime import OnnxScorer
    from cosy_cli.singleview.training_free.verify import Verifier, VerifyConf, observe

    out, _ = tiny_scorer
    ds = BopDataset(SAMPLES, "test")
    gt = ds.scene_gt(1)[0]
    rgb = ds.read_rgb(1, 0)
    K = ds.scene_camera(1)[0].K
    db = ObjectDatabase.from_models_dir(SAMPLES / "models")
    T = np.stack([g.T_cam_obj for g in gt[:3]])
    obj = np.array([g.obj_id for g in gt[:3]])
    info = ds.scene_gt_info(1)[0][:3]
    boxes = np.array([[b.bbox_visib[0], b.bbox_visib[1], b.bbox_visib[0] + b.bbox_visib[2],
                       b.bbox_visib[1] + b.bbox_visib[3]] for b in info], float)
    scorer = OnnxScorer(out)
    with Verifier(db, VerifyConf(scorer_scope="all"), scorer=scorer) as v:
        obs = [observe(rgb, K, b, v.conf) for b in boxes]
        det = np.repeat(np.arange(3), 2)
        Th = np.repeat(T, 2, 0)
        Th[1::2, :3, 3] += [8.0, 0, 0]
        learned, terms = v.score(obs, det, obj[det], Th, terms=True)
        raw = v.score(obs, det, obj[det], Th, inputs=True)
    x = assemble(np.stack([obs[d].rgb for d in raw["udet"]]), np.stack([obs[d].in_box for d in raw["udet"]]),
                 np.stack([obs[d].not_bg for d in raw["udet"]]), raw["ridx"], raw["rgba"], raw["gain"])
    np.testing.assert_allclose(learned, scorer(x, raw["terms"]), rtol=1e-5)
    assert np.all((learned > 0) & (learned < 1)) and "total" in terms
    np.testing.assert_allclose(terms["total"], raw["total"])


def test_estimate_and_run_take_a_scorer(tmp_path, tiny_scorer):
    out_scorer, _ = tiny_scorer
    tdir = Path(tiny_scorer[1]["run"]) / "templates"
    out = tmp_path / "c.csv"
    args = ["estimate", "--scene", str(SCENE), "--from-gt", "--coarse", "templates", "--refiner", "none",
            "--depth-refine", "none", "--verify-top", "8", "--top-k", "2", "--templates-dir", str(tdir)]
    r = _run(args + ["--scorer", str(out_scorer), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "learned scorer" in r.output
    doc = json.loads((tmp_path / "c.json").read_text())
    assert doc["conf"]["scorer"] is True and doc["inputs"]["scorer_model"]["sha1"]
    assert "scorer_scope" not in doc["conf"]  # the default (rank) is not recorded
    # rebox auto: 2 passes with a scorer (recorded, reported), none without one; --rebox 0 turns it off
    assert doc["conf"]["rebox"] == estimate_stage.REBOX_WITH_SCORER and "rebox:" in r.output
    r = _run(args + ["--scorer", str(out_scorer), "--rebox", "0", "--out", str(tmp_path / "r0.csv")])
    assert r.exit_code == 0, r.output
    assert "rebox" not in json.loads((tmp_path / "r0.json").read_text())["conf"] and "rebox:" not in r.output
    r = _run(args + ["--out", str(tmp_path / "none.csv")])
    assert r.exit_code == 0, r.output
    assert "rebox" not in json.loads((tmp_path / "none.json").read_text())["conf"]
    r = _run(args + ["--scorer", str(out_scorer), "--scorer-scope", "all", "--out", str(tmp_path / "all.csv")])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "all.json").read_text())["conf"]["scorer_scope"] == "all"
    r = _run(args + ["--scorer", str(out_scorer), "--scorer-keep", "4", "--out", str(tmp_path / "k4.csv")])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "k4.json").read_text())["conf"]["scorer_keep"] == 4
    from cosy_cli.io import bop

    assert len(bop.read_results(out)) == len(bop.read_results(out).table) > 0
    # a file that is not a scorer, and one that does not exist: exit 2, the file named
    r = _run(args + ["--scorer", str(Path(__file__).resolve().parent.parent / "src/cosy_cli/assets/detector.onnx"),
                     "--out", str(tmp_path / "d.csv"), "--overwrite"])
    assert r.exit_code == 2 and "detector.onnx" in r.output and "cosy train scorer" in r.output
    r = _run(args + ["--scorer", str(tmp_path / "none.onnx"), "--out", str(tmp_path / "e.csv")])
    assert r.exit_code == 2 and "none.onnx" in r.output
    # cosy run passes it on to the estimate stage
    r = _run(["run", "--scene", str(SCENE), "--from-gt", "--out", str(tmp_path / "run"), "--to", "refine",
              "--templates-dir", str(tdir), "--scorer", str(out_scorer), "--set", "estimate.verify_top=8",
              "--set", "estimate.top_k=2", "--set", "estimate.coarse=templates", "--set", "estimate.refiner=none",
              "--set", "estimate.depth_refine=none", "--quiet"])
    assert r.exit_code == 0, r.output
    sdir = tmp_path / "run" / "scenes" / "000001"
    cand = json.loads((sdir / "candidates.json").read_text())
    sha1 = doc["inputs"]["scorer_model"]["sha1"]
    assert cand["inputs"]["scorer_model"]["sha1"] == sha1
    # ... and to the refine stage's image check (cosy refine --scorer)
    assert json.loads((sdir / "refine" / "scene.json").read_text())["scorer_model"]["sha1"] == sha1
    ref = ["refine", "--dataset", str(SCENE.parent.parent), "--split", "test", "--matches", str(sdir / "match"),
           "--out", str(tmp_path / "ref")]
    r = _run(ref + ["--scorer", str(out_scorer), "--scorer-use", "all"])
    assert r.exit_code == 0, r.output
    ref_doc = json.loads((tmp_path / "ref" / "scene.json").read_text())
    assert ref_doc["scorer_model"]["sha1"] == sha1 and ref_doc["conf"]["image_check_scorer"] == "all"
    r = _run(ref + ["--scorer", str(out_scorer), "--scorer-use", "all"])
    assert r.exit_code == 0 and "up to date" in r.output, r.output
    r = _run(ref)  # without the scorer: out of date, refused without --overwrite
    assert r.exit_code == 2 and "the scorer changed" in r.output, r.output
    r = _run(ref + ["--overwrite"])
    assert r.exit_code == 0, r.output
    assert "scorer_model" not in json.loads((tmp_path / "ref" / "scene.json").read_text())
    r = _run(ref + ["--scorer", str(tmp_path / "none.onnx"), "--overwrite"])
    assert r.exit_code == 2 and "none.onnx" in r.output


def test_train_scorer_command_line_errors(tmp_path):
    r = _run(["train", "scorer", "--out", str(tmp_path / "s.onnx")])
    assert r.exit_code == 2 and "--models" in r.output
    r = _run(["train", "scorer", "--models", str(tmp_path), "--out", str(tmp_path / "s.onnx")])
    assert r.exit_code == 2 and "models_info.json" in r.output
    r = _run(["train", "scorer", "--models", str(SAMPLES / "models"), "--out", str(tmp_path / "s.pt")])
    assert r.exit_code == 2 and ".onnx" in r.output
    r = _run(["train", "refiner", "--models", str(SAMPLES / "models"), "--out", str(tmp_path / "r")])
    assert r.exit_code == 2 and "--dataset" in r.output
    for crop, word in (("96x64", "square"), ("40x40", "multiple of 16")):
        r = _run(["train", "scorer", "--models", str(SAMPLES / "models"), "--out", str(tmp_path / "s.onnx"),
                  "--crop", crop])
        assert r.exit_code == 2 and word in r.output and not (tmp_path / "s.run").exists()


def test_scorer_data_at_another_crop_side_and_on_photographs(tmp_path):
    """The crop setting: the shards hold what a verifier of that side renders and observes. The
    backgrounds setting: the same shard with photographs behind the objects differs."""
    from cosy_cli.objects import ObjectDatabase
    from cosy_cli.singleview.estimate_stage import ensure_templates
    from cosy_cli.singleview.training_free.templates import TemplateSet
    from cosy_cli.training import scorer
    from cosy_cli.training.scorer_data import ShardMaker

    c = scorer.resolve_conf(dict(TINY, images_per_shard=1), crop=48)
    assert c["crop"] == 48 and scorer.resolve_conf(None)["crop"] == 64
    ensure_templates(SAMPLES / "models", tmp_path / "t", log=lambda *_: None)
    K = np.array([[572.0, 0, 320], [0, 572.0, 240], [0, 0, 1]])

    def shard_zero(conf):
        maker = ShardMaker(ObjectDatabase.from_models_dir(SAMPLES / "models"), TemplateSet.load(tmp_path / "t"), K,
                           (640, 480), conf)
        try:
            return maker, maker.make(0)
        finally:
            maker.close()

    maker, d = shard_zero(c)
    n = len(d["target"])
    assert maker.verifier.conf.crop == 48 and n > 0
    assert d["rgba"].shape == (n, 48, 48, 4) and d["obs_rgb"].shape[1:] == (48, 48, 3)
    import cv2

    photos = tmp_path / "photos"
    photos.mkdir()
    rng = np.random.default_rng(0)
    for i in range(2):  # a smooth random picture, not noise
        small = rng.integers(0, 255, (6, 8, 3), dtype=np.uint8)
        cv2.imwrite(str(photos / f"p{i}.png"), cv2.resize(small, (320, 240), interpolation=cv2.INTER_CUBIC))
    c2 = scorer.resolve_conf(dict(c, p_photo=1.0, p_photo_texture=0.0), backgrounds=photos)
    assert c2["backgrounds"] == str(photos.resolve())
    maker, d2 = shard_zero(c2)
    assert len(maker.photos["photos"]) == 2 and d2["obs_rgb"].shape[1:] == (48, 48, 3)
    assert not np.array_equal(d2["obs_rgb"][:1], d["obs_rgb"][:1])


@pytest.fixture(scope="module")
def tiny_lite0_scorer(tmp_path_factory, tiny_scorer):
    """A lite0 scorer trained through the command line on the tiny scorer's data (the same
    settings, so its shards and templates are reused)."""
    import shutil

    from cosy_cli.training import scorer

    out = tmp_path_factory.mktemp("lite0") / "scorer.onnx"
    run = scorer.run_folder(out)
    run.mkdir()
    shutil.copytree(Path(tiny_scorer[1]["run"]) / "shards", run / "shards")
    shutil.copytree(Path(tiny_scorer[1]["run"]) / "templates", run / "templates")
    r = scorer.main(dict(TINY, arch="lite0"), SAMPLES / "models", out, log=lambda *_: None, progress=False)
    return out, r


def test_lite0_scorer_trains_only_its_head_on_cached_maps_equal_to_inference(tiny_lite0_scorer):
    """The lite0 scorer: ImageNet trunk frozen through training; the maps cached for training give
    the logits the whole network gives on the same inputs; the ONNX file gives them too."""
    import torch

    from cosy_cli.detection import efficientnet_lite
    from cosy_cli.singleview.scorer.runtime import OnnxScorer
    from cosy_cli.training import loop, scorer
    from cosy_cli.training.scorer_data import load_shards

    out, r = tiny_lite0_scorer
    run = Path(r["run"])
    net, ck = loop.load_run(run, scorer._build, "cosy train scorer", "scorer checkpoint")
    assert ck["config"]["arch"] == "lite0" and ck["step"] == TINY["iterations"]
    ref = efficientnet_lite.imagenet_state()
    own = net.state_dict()
    for k in ("stem.1.weight", "blocks.4.project.0.weight", "blocks.10.dw.2.running_mean"):
        assert torch.equal(own[k], ref[k]), k  # frozen, BatchNorm statistics included
    assert "blocks.11.expand.0.weight" not in own  # the trunk ends at stride 16
    d = load_shards(run / "shards", [1])  # the validation shard
    maps = scorer.ensure_maps(net, run / "shards", run / "maps", [1], progress=False)
    assert maps["p8"].dtype == np.float16 and len(maps["p8"]) == len(d["target"]) and len(maps["o8"]) == len(d["obs_rgb"])
    cached, direct = scorer._MapBatches(d, maps), scorer._Batches(d)
    idx = np.arange(min(40, len(d["target"])))
    with torch.no_grad():
        a = cached.logits(net.eval(), idx).numpy()
        b = direct.logits(net, idx).numpy()
    np.testing.assert_allclose(a, b, atol=0.05 * (1 + np.abs(b).max()))  # float16 maps
    x, t = direct.inputs(idx)
    p = 1 / (1 + np.exp(-b))
    # the exported float32 network is the torch one
    out32 = out.with_name("scorer_fp32.onnx")
    scorer.export(run, out32, log=lambda *_: None, precision="fp32")
    sc = OnnxScorer(out32)
    assert sc.card["arch"] == "lite0" and sc.card.get("precision", "fp32") == "fp32"
    np.testing.assert_allclose(sc(x, t), p, atol=1e-5)
    # each observed crop through the trunk once (the observation of each hypothesis given): the same
    np.testing.assert_allclose(sc(x, t, d["det"][idx]), p, atol=1e-5)
    assert 0 < sc.card["validation"]["val_pick"] <= sc.card["validation"]["val_oracle"]
    # the default export: the trunk's convolutions in int8, close to float32 but not equal to it
    q = OnnxScorer(out)
    # its card: the validation measured on the int8 file, the float32 network's beside it
    assert q.card["precision"] == "int8" and q.card["validation_fp32"] == sc.card["validation"]
    assert 0 < q.card["validation"]["val_pick"] <= q.card["validation"]["val_oracle"]
    import onnx

    ops = {n.op_type for n in onnx.load(str(out)).graph.node}
    assert {"QuantizeLinear", "DequantizeLinear"} <= ops
    pq = q(x, t, d["det"][idx])
    assert not np.array_equal(pq, sc(x, t, d["det"][idx]))
    np.testing.assert_allclose(pq, p, atol=0.1)  # on the LM-O scorer: median 0.007, 95th percentile 0.06
    from scipy.stats import spearmanr

    assert spearmanr(pq, p).correlation > 0.9  # the order of the hypotheses is what the verifier uses
    with pytest.raises(ValueError, match="already quantized"):
        from cosy_cli.singleview.scorer.model import quantize_trunk

        quantize_trunk(out, [{}])


def test_lite0_scorer_from_the_command_line(tmp_path, monkeypatch):
    """`cosy train scorer` trains the lite0 arch by default, the plain one with --backbone plain or
    --preset plain; a backbone of the pose networks is refused with exit code 2; a wrong arch in
    the settings is named."""
    from cosy_cli.errors import CosyError
    from cosy_cli.training import scorer

    seen = {}
    monkeypatch.setattr(scorer, "main", lambda conf, *a, **k: seen.update(conf))
    args = ["train", "scorer", "--models", str(SAMPLES / "models"), "--out", str(tmp_path / "s.onnx")]
    assert _run(args + ["--backbone", "efficientnet-lite0"]).exit_code == 0 and seen["arch"] == "lite0"
    assert _run(args).exit_code == 0 and seen["arch"] == "lite0" and seen["shards"] == 100
    assert _run(args + ["--backbone", "plain"]).exit_code == 0 and seen["arch"] == "plain"
    assert _run(args + ["--preset", "plain"]).exit_code == 0 and seen["arch"] == "plain" and seen["shards"] == 150
    r = _run(args + ["--backbone", "efficientnet-b0"])
    assert r.exit_code == 2 and "efficientnet-lite0" in r.output
    with pytest.raises(CosyError, match="arch"):
        scorer.resolve_conf(None, arch="resnet")


def _two_detections(seed):
    """The sample image of scene 1, its first two objects' visible GT boxes, and six hypotheses of
    each: the GT pose first, then five turned and shifted at random (``seed``)."""
    from cosy_cli.io.dataset import BopDataset
    from cosy_cli.objects import ObjectDatabase

    ds = BopDataset(SAMPLES, "test")
    gt = ds.scene_gt(1)[0][:2]
    rgb, K = ds.read_rgb(1, 0), ds.scene_camera(1)[0].K
    db = ObjectDatabase.from_models_dir(SAMPLES / "models")
    info = ds.scene_gt_info(1)[0][:2]
    boxes = np.array([[b.bbox_visib[0], b.bbox_visib[1], b.bbox_visib[0] + b.bbox_visib[2],
                       b.bbox_visib[1] + b.bbox_visib[3]] for b in info], float)
    obj = np.array([g.obj_id for g in gt])
    rng = np.random.default_rng(seed)
    T = np.repeat(np.stack([g.T_cam_obj for g in gt])[:, None], 6, 1)
    T[:, 1:, :3, :3] = axis_angle_to_matrix(rng.normal(size=(2, 5, 3)) * 0.4) @ T[:, 1:, :3, :3]
    T[:, 1:, :3, 3] += rng.normal(size=(2, 5, 3)) * 6
    return rgb, K, db, boxes, obj, T


def test_scorer_scope_rank_orders_only_the_final_hypotheses(tiny_scorer):
    """scorer_scope "rank": rank() orders each detection's best scorer_keep (by the training-free score)
    by the scorer's predictions; the others keep their training-free scores; score() stays
    training-free unless asked. A wrong scope in the estimate settings is named."""
    from cosy_cli.errors import CosyError
    from cosy_cli.singleview import estimate_stage
    from cosy_cli.singleview.scorer.runtime import OnnxScorer
    from cosy_cli.singleview.training_free.verify import Verifier, VerifyConf

    rgb, K, db, boxes, obj, T = _two_detections(seed=0)
    conf = VerifyConf(scorer_scope="rank", scorer_keep=3, rank_faces=0)
    with Verifier(db, conf, scorer=OnnxScorer(tiny_scorer[0])) as v:
        r = v.rank(rgb, K, boxes, obj, T)
        det = np.repeat(np.arange(2), 3)
        first, rest = r.T_cam_obj[:, :3].reshape(-1, 4, 4), r.T_cam_obj[:, 3:].reshape(-1, 4, 4)
        learned = v.score(r.obs, det, obj[det], first, learned=True)
        free = v.score(r.obs, det, obj[det], first)
        free_rest = v.score(r.obs, det, obj[det], rest)
    np.testing.assert_allclose(r.score[:, :3].reshape(-1), learned, rtol=1e-6)
    assert np.all(np.diff(r.score[:, :3], axis=1) <= 0)  # ordered by the scorer
    np.testing.assert_allclose(r.score[:, 3:].reshape(-1), free_rest, rtol=1e-6)
    assert np.all(free_rest.reshape(2, 3).max(1) <= free.reshape(2, 3).min(1) + 1e-12)  # the best 3 went ahead
    assert not np.allclose(learned, free)
    assert estimate_stage.resolve_conf(None, scorer_scope="rank")["scorer_scope"] == "rank"
    with pytest.raises(CosyError, match="scorer_scope"):
        estimate_stage.resolve_conf(None, scorer_scope="some")
    with pytest.raises(CosyError, match="scorer_keep"):
        estimate_stage.resolve_conf(None, scorer_keep=0)


class _SideScorer:
    """A stand-in scorer of another crop side: the mean green of the render pasted where its mask is
    (any deterministic function of the inputs would do); records the image sizes it was given."""

    def __init__(self, crop):
        self.crop, self.margin, self.sizes = crop, 0.2, []

    def __call__(self, image, terms, ridx=None):
        self.sizes.append(image.shape[-1])
        m = image[:, 6]
        return 1.0 / (1.0 + np.exp(-(image[:, 4] * m).sum((1, 2)) / np.maximum(m.sum((1, 2)), 1.0) - terms[:, 0]))


def test_a_scorer_of_another_crop_side_scores_through_its_own_verifier():
    """A scorer trained on 96 px crops behind 64 px verification: rank() orders by its predictions on
    the detections observed again at 96 px (its own renders and terms), the training-free scores stay
    at 64 px, and its scores are those of a 96 px verifier."""
    from cosy_cli.singleview.training_free.verify import Verifier, VerifyConf, observe

    rgb, K, db, boxes, obj, T = _two_detections(seed=1)
    conf = VerifyConf(scorer_scope="rank", scorer_keep=3, rank_faces=0)
    side = _SideScorer(96)
    det = np.repeat(np.arange(2), 3)
    with Verifier(db, conf, scorer=side) as v:
        r = v.rank(rgb, K, boxes, obj, T)
        first = r.T_cam_obj[:, :3].reshape(-1, 4, 4)
        assert r.obs[0].rgb.shape == (64, 64, 3) and set(side.sizes) == {96}
        free = v.score(r.obs, det, obj[det], first)
    with Verifier(db, VerifyConf(crop=96, scorer_scope="all", rank_faces=0), scorer=_SideScorer(96)) as v96:
        obs96 = [observe(rgb, K, b, v96.conf) for b in boxes]
        direct = v96.score(obs96, det, obj[det], first)
    np.testing.assert_allclose(r.score[:, :3].reshape(-1), direct, rtol=1e-6)
    assert np.all(np.diff(r.score[:, :3], axis=1) <= 0) and not np.allclose(direct, free)
    with pytest.raises(ValueError, match="margin"):
        bad = _SideScorer(96)
        bad.margin = 0.3
        Verifier(db, conf, scorer=bad)
