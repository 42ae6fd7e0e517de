"""Tests of cosy_cli.training.train and the `cosy train` / `cosy export` commands (tiny, fast runs)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from cosy_cli.rendering import SceneRenderer  # noqa: F401  (selects the GL platform first)
from cosy_cli.cli.main import cli  # noqa: E402
from cosy_cli.errors import CosyError  # noqa: E402
from cosy_cli.training import train  # noqa: E402

TINY = dict(kind="refiner", crop_size=[64, 48], batch_size=2, n_points=50, warmup=2, checkpoint_every=2, log_every=1)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from cosy_cli.synth.objects import write_models

    root = tmp_path_factory.mktemp("ds")
    write_models(root)
    return root


@pytest.fixture(scope="module")
def run(dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "run"
    s = train.main(dict(TINY, iterations=3), dataset, "train_pbr", out, log=lambda *_: None, progress=False)
    return out, s


def test_schedule_and_curriculum():
    c = train.resolve_conf(None, lr=1e-3, warmup=10, iterations=100, schedule="cosine")
    assert train.learning_rate(c, 0) == pytest.approx(1e-4)
    assert train.learning_rate(c, 9) == pytest.approx(1e-3)
    assert train.learning_rate(c, 100) == pytest.approx(5e-5)
    assert train.curriculum(c, 0) == pytest.approx(0.3)
    assert train.curriculum(c, 50) == train.curriculum(c, 99) == 1.0
    with pytest.raises(CosyError):
        train.resolve_conf(None, bogus=1)


def test_run_writes_outputs(run):
    out, s = run
    for name in ("checkpoint.pt", "config.json", "log.csv", "loss.png"):
        assert (out / name).is_file(), name
    rows = train.read_log(out / "log.csv")
    assert [r["step"] for r in rows] == [1, 2, 3]
    assert all(np.isfinite(r["loss_total"]) and r["loss_total"] > 0 for r in rows)
    ck = torch.load(out / "checkpoint.pt", weights_only=False)
    assert ck["step"] == s["step"] == 3 and ck["samples"] == 6
    assert ck["optimizer"]["state"]  # Adam moments saved


def test_refuse_existing_and_resume(run, dataset):
    out, _ = run
    with pytest.raises(CosyError, match="--resume"):
        train.main(dict(TINY, iterations=5), dataset, "train_pbr", out, log=lambda *_: None, progress=False)
    with pytest.raises(CosyError, match="different settings"):
        train.main(dict(TINY, iterations=5, lr=1e-2), dataset, "train_pbr", out, resume=True, progress=False,
                   log=lambda *_: None)
    before = torch.load(out / "checkpoint.pt", weights_only=False)
    s = train.main(dict(TINY, iterations=5), dataset, "train_pbr", out, resume=True, log=lambda *_: None,
                   progress=False)
    after = torch.load(out / "checkpoint.pt", weights_only=False)
    assert s["step"] == 5 and after["samples"] == 10
    steps = [r["step"] for r in train.read_log(out / "log.csv")]
    assert steps == [1, 2, 3, 4, 5]  # continued, not restarted
    # Adam's step counter went on from the restored state (3 + 2), not from zero
    st_b = next(iter(before["optimizer"]["state"].values()))
    st_a = next(iter(after["optimizer"]["state"].values()))
    assert float(st_b["step"]) == 3 and float(st_a["step"]) == 5


def test_export_matches_torch(run, tmp_path):
    from cosy_cli.singleview.networks.onnx import OnnxPoseNet

    out, _ = run
    path = train.export(out, tmp_path / "m.onnx", log=lambda *_: None)
    net, ck = train.load_run(out)
    x = np.random.default_rng(0).random((3, 6, 48, 64), dtype=np.float32)
    with torch.no_grad():
        ref = net(torch.from_numpy(x)).numpy()
    got = OnnxPoseNet(path)(x)
    np.testing.assert_allclose(got, ref, atol=1e-4)
    card = (tmp_path / "m.md").read_text()
    assert "64 x 48" in card and "efficientnet-b0" in card and "measured accuracy: not measured" in card
    assert f"{ck['step']} steps" in card


def test_cli_errors(tmp_path, run):
    r = CliRunner().invoke(cli, ["train", "refiner", "--dataset", str(tmp_path / "missing"), "--out",
                                 str(tmp_path / "run")])
    assert r.exit_code == 2
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "dataset folder not found" in lines[0]
    r = CliRunner().invoke(cli, ["export", "--run", str(tmp_path / "none"), "--out", str(tmp_path / "m.onnx")])
    assert r.exit_code == 2 and "run folder not found" in r.output
