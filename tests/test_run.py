"""cosy run: per-scene units, caching and invalidation, resume after a kill, workers and Dask."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cosy_cli.cli.main import cli
from cosy_cli.errors import CosyError
from cosy_cli.io import bop
from cosy_cli.pipeline import run_stage, units

DATA = Path(__file__).resolve().parents[1] / "data_samples"
SMALL_TEMPLATES = {"viewpoints": 200, "inplane": 24}


@pytest.fixture(scope="module")
def templates_dir(tmp_path_factory):
    from cosy_cli.singleview.training_free import templates as tpl

    d = tmp_path_factory.mktemp("run_templates") / "templates"
    tpl.main(SMALL_TEMPLATES, DATA / "models", d, log=lambda m: None, progress=False)
    return d


@pytest.fixture(scope="module")
def candidates(tmp_path_factory):
    """Simulated single-view candidates of data_samples (cheap input for the multi-view stages)."""
    out = tmp_path_factory.mktemp("run_cands") / "cands.csv"
    r = CliRunner().invoke(cli, ["synth-candidates", "--dataset", str(DATA), "--out", str(out), "--seed", "0"])
    assert r.exit_code == 0, r.output
    return out


def _quiet(**kw):
    return dict(log=lambda m: None, progress=False, **kw)


def _records(run_dir: Path) -> dict[str, float]:
    """mtime of every unit record: which units were (re)run."""
    return {str(p.relative_to(run_dir)): p.stat().st_mtime_ns for p in run_dir.rglob(".cosy/*.json")}


def _poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    res = bop.read_results(path)
    return res.table[["scene_id", "im_id", "obj_id"]].to_numpy(), res.T_cam_obj


def test_from_gt_runs_every_stage_and_the_second_run_skips(tmp_path, templates_dir):
    run = tmp_path / "run"
    m = run_stage.main("fast", DATA, "test", run, scene_ids=[1], from_gt=True, templates_dir=templates_dir,
                       last="evaluate", **_quiet())
    assert m["status"] == "done" and m["scene_ids"] == [1]
    for rel in ("scenes/000001/detections.json", "scenes/000001/candidates.csv", "scenes/000001/match/groups.json",
                "scenes/000001/refine/scene.json", "detect/detections.json", "estimate/candidates.csv",
                "refine/predictions.csv", "refine/scene.json", "evaluate/multi_view/scores.json", "run.json"):
        assert (run / rel).is_file(), rel
    mv, sv = m["metrics"]["multi_view"], m["metrics"]["single_view"]
    # scene 1 alone, scored on scene 1 only: multi-view beats single-view
    assert mv["recall_adds_0.1d"] >= sv["recall_adds_0.1d"] and mv["recall_adds_0.1d"] > 0.9
    # the summary gives the headline AR's bootstrap interval (over images: one scene)
    lo, hi = mv["bop19_ci"]["bop19_average_recall_mssd_mspd"]
    assert mv["bop19_ci"]["unit"] == "image" and lo <= mv["bop19_average_recall_mssd_mspd"] <= hi
    text = "\n".join(run_stage.summary_lines(m, run))
    assert f"{lo:.3f}-{hi:.3f}" in text and "95 % interval (images)" in text
    assert all(st["status"] == "done" for st in m["stages"].values())
    before = _records(run)
    m2 = run_stage.main("fast", DATA, "test", run, scene_ids=[1], from_gt=True, templates_dir=templates_dir,
                        last="evaluate", **_quiet())
    assert all(st["status"] == "skipped" for st in m2["stages"].values())
    assert _records(run) == before


def test_changed_setting_reruns_its_stage_and_the_later_ones(tmp_path, candidates):
    run = tmp_path / "run"
    kw = _quiet(scene_ids=[1, 2], candidates=candidates, last="refine")
    run_stage.main("fast", DATA, "test", run, **kw)
    before = _records(run)
    m = run_stage.main("fast", DATA, "test", run, overrides={"match": {"threshold_mm": 30.0}}, **kw)
    after = _records(run)
    assert m["stages"]["match"]["status"] == "done" and m["stages"]["refine"]["status"] == "done"
    assert m["stages"]["estimate"]["status"] == "skipped"
    for s in ("000001", "000002"):
        assert after[f"scenes/{s}/.cosy/estimate.json"] == before[f"scenes/{s}/.cosy/estimate.json"]
        assert after[f"scenes/{s}/.cosy/match.json"] != before[f"scenes/{s}/.cosy/match.json"]
        assert after[f"scenes/{s}/.cosy/refine.json"] != before[f"scenes/{s}/.cosy/refine.json"]
    assert json.loads((run / "run.json").read_text())["confs"]["match"]["threshold_mm"] == 30.0


def test_a_half_written_output_without_its_record_is_not_trusted(tmp_path, candidates):
    run = tmp_path / "run"
    kw = _quiet(scene_ids=[1], candidates=candidates, last="refine")
    run_stage.main(None, DATA, "test", run, **kw)
    ref = _poses(run / "refine" / "predictions.csv")
    # a crash between the stage's output and its record; then a file damaged behind our back
    units.forget(run / "scenes" / "000001", "refine")
    (run / "scenes" / "000001" / "refine" / "predictions.csv").write_text("scene_id,im_id\n1,")
    m = run_stage.main(None, DATA, "test", run, **kw)
    assert m["stages"]["refine"]["status"] == "done"
    (run / "scenes" / "000001" / "match" / "matches.csv").write_text("garbage")
    m = run_stage.main(None, DATA, "test", run, **kw)
    assert m["stages"]["match"]["status"] == "done"
    got = _poses(run / "refine" / "predictions.csv")
    assert np.array_equal(got[0], ref[0]) and np.allclose(got[1], ref[1])


def test_killed_run_resumes_without_redoing_finished_scenes(tmp_path, templates_dir):
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "cosy_cli", "run", "--dataset", str(DATA), "--split", "test", "--out", str(run),
           "--from-gt", "--config", "fast", "--templates-dir", str(templates_dir), "--to", "refine", "--quiet"]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    first_done = run / "scenes" / "000001" / ".cosy" / "refine.json"
    t0 = time.time()
    while not first_done.exists() and proc.poll() is None and time.time() - t0 < 240:
        time.sleep(0.05)
    assert first_done.exists(), proc.stderr.read().decode() if proc.poll() is not None else "timeout"
    time.sleep(0.3)  # now inside scene 2
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert json.loads((run / "run.json").read_text())["status"] == "running"
    assert not (run / "refine" / "predictions.csv").exists()
    scene1 = {k: v for k, v in _records(run).items() if k.startswith("scenes/000001")}
    assert len(scene1) == 4
    m = run_stage.main("fast", DATA, "test", run, from_gt=True, templates_dir=templates_dir, last="refine", **_quiet())
    assert m["status"] == "done"
    after = _records(run)
    assert all(after[k] == v for k, v in scene1.items())  # scene 1 was not redone
    assert m["stages"]["estimate"]["scenes_run"] in (1, 2)  # scene 3, and scene 2 unless it had finished
    assert set(bop.read_results(run / "refine" / "predictions.csv").table["scene_id"]) == {1, 2, 3}


def test_workers_and_serial_give_the_same_results(tmp_path, candidates):
    kw = _quiet(candidates=candidates, last="refine")
    run_stage.main(None, DATA, "test", tmp_path / "serial", **kw)
    run_stage.main(None, DATA, "test", tmp_path / "parallel", workers=2, **kw)
    a, b = (_poses(tmp_path / r / "refine" / "predictions.csv") for r in ("serial", "parallel"))
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    ga, gb = (json.loads((tmp_path / r / "refine" / "scene.json").read_text())["groups"] for r in ("serial", "parallel"))
    strip = [{k: v for k, v in g.items() if k != "stats"} for g in ga], [{k: v for k, v in g.items() if k != "stats"}
                                                                         for g in gb]
    assert strip[0] == strip[1] and len(ga) == 3


def test_dask_local_cluster(tmp_path, candidates):
    distributed = pytest.importorskip("distributed")
    kw = _quiet(scene_ids=[1, 2], candidates=candidates, last="refine")
    run_stage.main(None, DATA, "test", tmp_path / "serial", **kw)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as lc:
        m = run_stage.main(None, DATA, "test", tmp_path / "dask", dask_scheduler=lc.scheduler_address, **kw)
    assert m["status"] == "done"
    a, b = (_poses(tmp_path / r / "refine" / "predictions.csv") for r in ("serial", "dask"))
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


def test_bad_input(tmp_path, candidates):
    junk = tmp_path / "junk"
    junk.mkdir()
    (junk / "x.txt").write_text("mine")
    with pytest.raises(CosyError, match="not a cosy run folder"):
        run_stage.main(None, DATA, "test", junk, candidates=candidates, **_quiet())
    with pytest.raises(CosyError, match=r"scene\(s\) \[99\]"):
        run_stage.main(None, DATA, "test", tmp_path / "r1", candidates=candidates, scene_ids=[99], **_quiet())
    with pytest.raises(CosyError, match="at most one"):
        run_stage.main(None, DATA, "test", tmp_path / "r2", candidates=candidates, from_gt=True, **_quiet())
    with pytest.raises(CosyError, match="missing; run from an earlier stage"):
        run_stage.main(None, DATA, "test", tmp_path / "r3", from_gt=True, first="match", **_quiet())
    r = CliRunner().invoke(cli, ["run", "--dataset", str(DATA), "--out", str(tmp_path / "r4"), "--config", "nope",
                                 "--candidates", str(candidates)])
    assert r.exit_code == 2 and "unknown run configuration 'nope'" in r.output and "Traceback" not in r.output
    shutil.rmtree(junk)


def test_set_overrides_reach_the_stage_settings(tmp_path, candidates):
    assert run_stage.parse_settings(["detect.min_score=0.1", "match.views_per_group=4", "estimate.coarse=templates"]) \
        == {"detect": {"min_score": 0.1}, "match": {"views_per_group": 4}, "estimate": {"coarse": "templates"}}
    with pytest.raises(CosyError, match="STAGE.KEY=VALUE"):
        run_stage.parse_settings(["min_score=0.1"])
    r = CliRunner().invoke(cli, ["run", "--dataset", str(DATA), "--out", str(tmp_path / "r"), "--scene-id", "1",
                                 "--candidates", str(candidates), "--to", "match", "--quiet",
                                 "--set", "match.threshold_mm=30", "--views-per-group", "4"])
    assert r.exit_code == 0, r.output
    confs = json.loads((tmp_path / "r" / "run.json").read_text())["confs"]
    assert confs["match"]["threshold_mm"] == 30 and confs["match"]["views_per_group"] == 4
    groups = json.loads((tmp_path / "r" / "scenes" / "000001" / "match" / "groups.json").read_text())
    assert len(groups["groups"]) == 2
    # --classifier is detect.classifier; the onboarded configuration's settings (a detector trained from meshes)
    r = CliRunner().invoke(cli, ["run", "--dataset", str(DATA), "--out", str(tmp_path / "r2"), "--scene-id", "1",
                                 "--candidates", str(candidates), "--to", "match", "--quiet", "--classifier", "none",
                                 "--config", "onboarded"])
    assert r.exit_code == 0, r.output
    confs = json.loads((tmp_path / "r2" / "run.json").read_text())["confs"]
    assert confs["detect"]["classifier"] == "none" and confs["detect"]["max_per_object"] == 3
    assert confs["detect"]["min_score"] == 0.01 and confs["detect"]["max_per_image"] == 100
    assert confs["detect"]["refine_boxes"] == 2 and confs["estimate"]["box_scales"] == [0.87, 1.0, 1.15]
    assert confs["estimate"]["score"] == "pose" and confs["estimate"]["max_per_object"] == 1
    fast = run_stage.resolve_confs("onboarded-fast")
    assert fast["detect"]["max_per_image"] == 80 and fast["detect"]["refine_top"] == 15
    assert fast["estimate"] == run_stage.resolve_confs("onboarded")["estimate"]
    assert confs["match"] == run_stage.resolve_confs("default")["match"]


def test_code_version_follows_the_package_files_not_the_commit(tmp_path, monkeypatch):
    """The code version in every unit key is a digest of the package's files: editing one (even
    uncommitted) changes it, the same files give the same version wherever they lie."""
    import cosy_cli

    pkg = Path(cosy_cli.__file__).resolve().parent
    copy = tmp_path / "cosy_cli"
    shutil.copytree(pkg, copy, ignore=shutil.ignore_patterns("__pycache__", "*.onnx"))
    (copy / "assets").mkdir(exist_ok=True)

    def version_of(root: Path) -> str:
        monkeypatch.setattr(units, "__file__", str(root / "pipeline" / "units.py"))
        units.code_version.cache_clear()
        try:
            return units.code_version()
        finally:
            units.code_version.cache_clear()

    v1 = version_of(copy)
    assert v1 == version_of(copy) and v1.startswith(cosy_cli.__version__ + "+")
    (copy / "conf.py").write_text((copy / "conf.py").read_text() + "\n# an edit\n")
    v2 = version_of(copy)
    assert v2 != v1
    (copy / "notes.txt").write_text("not code")  # neither code nor a model: no new version
    assert version_of(copy) == v2
