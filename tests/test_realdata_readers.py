"""Tolerant, honest readers: the published BOP files (LM-O, YCB-V) are read like the BOP toolkit
reads them. Rotations orthonormal only to 0.05 are repaired with one warning per file, worse ones
are errors naming file and row; `cosy validate` exits 0 with warnings and 2 with ``--strict``.

The real-data tests read ``../shared/realdata/`` (lmo_dev: LM-O test scenes as published; ycbv_0000:
YCB-V train_real frames with ``camera_uw.json``) and are skipped when it is absent.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from cosy_cli.cli.main import cli  # noqa: E402
from cosy_cli.errors import CosyError, CosyWarning  # noqa: E402
from cosy_cli.geometry.rotations import random_rotations  # noqa: E402
from cosy_cli.io import bop  # noqa: E402

from realdata import LMO, YCBV, needs  # noqa: E402

needs_realdata = needs(LMO, YCBV)


def _cosy_warnings(record) -> list[str]:
    return [str(w.message) for w in record if issubclass(w.category, CosyWarning)]


def _sheared(R: np.ndarray, dev: float) -> np.ndarray:
    """R times a shear with |S^T S - I| = dev (to first order): a rotation orthonormal only to ``dev``."""
    S = np.eye(3)
    S[0, 1] = dev
    return R @ S


# --------------------------------------------------------------------------------------------
# readers (synthetic files: always run)
# --------------------------------------------------------------------------------------------
def _write_gt(path: Path, Rs: list[np.ndarray]) -> None:
    gt = {"0": [{"cam_R_m2c": R.reshape(-1).tolist(), "cam_t_m2c": [0.0, 0.0, 500.0 + 10 * k], "obj_id": k + 1}
                for k, R in enumerate(Rs)]}
    path.write_text(json.dumps(gt))


def test_scene_gt_rotation_within_tolerance_is_repaired_with_one_warning(tmp_path):
    R = random_rotations(3, np.random.default_rng(0))
    p = tmp_path / "scene_gt.json"
    _write_gt(p, [R[0], _sheared(R[1], 0.02), _sheared(R[2], 0.004)])
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        gt = bop.read_scene_gt(p)
    msgs = _cosy_warnings(rec)
    assert len(msgs) == 1, msgs
    assert str(p) in msgs[0] and "2 of 3 cam_R_m2c rotations" in msgs[0] and "image 0, instance 1 (obj_id 2)" in msgs[0]
    assert "0.02" in msgs[0], msgs[0]
    Rr = np.stack([g.T_cam_obj[:3, :3] for g in gt[0]])
    assert bop.rotation_errors(Rr).max() < 1e-9
    assert np.allclose(Rr[0], R[0], atol=1e-12)  # an exact rotation is kept
    assert np.abs(Rr[1] - R[1]).max() < 0.02  # the nearest rotation: close to where it came from
    # read, written, read again: clean, no warning
    bop.write_scene_gt(tmp_path / "again.json", gt)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CosyWarning)
        again = bop.read_scene_gt(tmp_path / "again.json")
    assert bop.rotation_errors(np.stack([g.T_cam_obj[:3, :3] for g in again[0]])).max() < 1e-8


def test_scene_gt_rotation_beyond_tolerance_is_an_error_naming_file_and_row(tmp_path):
    R = random_rotations(2, np.random.default_rng(1))
    p = tmp_path / "scene_gt.json"
    _write_gt(p, [R[0], _sheared(R[1], 0.2)])
    with pytest.raises(CosyError) as e:
        bop.read_scene_gt(p)
    msg = str(e.value)
    assert str(p) in msg and "image 0, instance 1 (obj_id 2)" in msg and "cam_R_m2c is not a rotation matrix" in msg
    assert "tolerated up to 0.05" in msg
    # keep_bad (cosy validate): read, the bad one as it is, for a per-row report
    gt = bop.read_scene_gt(p, rotations="keep_bad")
    assert bop.rotation_errors(gt[0][1].T_cam_obj[:3, :3]) > 0.05


def test_results_csv_repaired_and_written_clean(tmp_path):
    R = random_rotations(3, np.random.default_rng(2))
    R[1] = _sheared(R[1], 0.01)
    res = bop.PoseResults.from_arrays([1, 1, 1], [0, 0, 0], [1, 2, 3], [0.9, 0.8, 0.7],
                                      np.stack([np.eye(4)] * 3))
    res.T_cam_obj[:, :3, :3] = R
    p = tmp_path / "cands.csv"
    bop.write_results(p, res)  # the writer orthonormalises: a clean file
    with warnings.catch_warnings():
        warnings.simplefilter("error", CosyWarning)
        back = bop.read_results(p)
    assert bop.rotation_errors(back.T_cam_obj[:, :3, :3]).max() < 1e-8
    # a file written by another tool with R at 0.01: read with one warning naming the row
    lines = p.read_text().splitlines()
    parts = lines[2].split(",")
    parts[4] = " ".join(f"{v:.9g}" for v in _sheared(np.eye(3), 0.01).reshape(-1))
    lines[2] = ",".join(parts)
    p.write_text("\n".join(lines) + "\n")
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        back = bop.read_results(p)
    (msg,) = _cosy_warnings(rec)
    assert str(p) in msg and "1 of 3 R rotations" in msg and "row 2" in msg
    assert bop.rotation_errors(back.T_cam_obj[:, :3, :3]).max() < 1e-9
    parts[4] = " ".join(f"{v:.9g}" for v in _sheared(np.eye(3), 0.2).reshape(-1))
    lines[2] = ",".join(parts)
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(CosyError, match=r"row 2: R is not a rotation matrix"):
        bop.read_results(p)


def test_nearest_rotation_and_reflection():
    R = random_rotations(5, np.random.default_rng(3))
    noisy = R + np.random.default_rng(4).normal(scale=0.003, size=R.shape)
    Rn = bop.nearest_rotation(noisy)
    assert bop.rotation_errors(Rn).max() < 1e-12 and np.all(np.linalg.det(Rn) > 0)
    assert np.abs(Rn - R).max() < 0.02
    flip = np.diag([1.0, 1.0, -1.0])  # a reflection is never "repaired": det <= 0 is an error
    assert np.isinf(bop.rotation_errors(flip))
    assert np.allclose(bop.clean_rotations(flip), flip)


# --------------------------------------------------------------------------------------------
# the published files
# --------------------------------------------------------------------------------------------
def _validate(*args):
    res = CliRunner().invoke(cli, ["validate", *args])
    assert "Traceback" not in res.stdout
    if res.exception is not None:
        assert isinstance(res.exception, SystemExit), repr(res.exception)
    warned = [ln for ln in res.stderr.splitlines() if ln.startswith("warning: ")]
    return res, warned


@needs_realdata
def test_validate_lmo_ok_with_warnings_and_strict_fails():
    args = ["--dataset", str(LMO), "--split", "test"]
    res, warned = _validate(*args, "--verbose")  # every warning, one line each
    assert res.exit_code == 0, res.output
    n = len(warned)
    assert f"result:    OK, {n} warnings" in res.stdout, res.stdout
    sym = [w for w in warned if "symmetries_discrete[0]" in w]
    assert len(sym) == 2, warned
    assert "object 10" in sym[0] and "4.4" in sym[0] and "mm off the mesh" in sym[0]  # eggbox: 4.5 mm
    assert "object 11" in sym[1] and "6.8" in sym[1]  # glue: 6.8 mm
    rot = [w for w in warned if "scene_gt.json" in w]
    assert len(rot) >= 20 and len(rot) == len({w.split(":")[1] for w in rot})  # one per file
    assert all("cam_R_m2c rotations orthonormal only to" in w for w in rot)
    # by default the repaired rotations of the split are one line: files, rows, the worst and where
    plain, summarised = _validate(*args)
    assert plain.exit_code == 0 and f"result:    OK, {n} warnings" in plain.stdout
    assert [w for w in summarised if "symmetries_discrete[0]" in w] == sym
    rot_sum = [w for w in summarised if "scene_gt.json" in w]
    assert len(rot_sum) == 1 and len(summarised) == n - len(rot) + 1, summarised
    rows = sum(int(w.split(" of ")[0].split(": ")[-1]) for w in rot)
    worst = max(float(w.split("|R^T R - I| = ")[1].split(" ")[0]) for w in rot)
    assert f"{rows} of " in rot_sum[0] and f"in {len(rot)} scene_gt.json files (worst {worst:.3g}: " in rot_sum[0]
    assert "--verbose lists each file" in rot_sum[0]
    strict, _ = _validate(*args, "--strict")
    assert strict.exit_code == 2 and f"{n} warnings and --strict" in strict.stderr


@needs_realdata
def test_validate_ycbv_ok_with_warnings_and_strict_fails():
    args = ["--dataset", str(YCBV), "--split", "train_real"]
    res, warned = _validate(*args)
    assert res.exit_code == 0, res.output
    assert "camera file: camera_uw.json" in res.stdout  # found without --camera
    assert f"result:    OK, {len(warned)} warnings" in res.stdout, res.output
    assert any("object 21, symmetries_discrete[0]" in w and "approximate symmetry" in w for w in warned), warned
    assert any("no scene_gt_info.json" in w for w in warned), warned
    strict, _ = _validate(*args, "--camera", "camera_uw.json", "--strict")
    assert strict.exit_code == 2 and f"{len(warned)} warnings and --strict" in strict.stderr


@needs_realdata
def test_validate_lmo_bad_rotation_is_a_problem_naming_file_and_row(tmp_path):
    root = tmp_path / "lmo"
    root.mkdir()
    for name in ("camera.json", "models"):
        (root / name).symlink_to(LMO / name)
    scene = root / "test" / "000001"
    scene.mkdir(parents=True)
    for f in (LMO / "test" / "000001").iterdir():
        if f.name != "scene_gt.json":
            (scene / f.name).symlink_to(f)
    gt = json.loads((LMO / "test" / "000001" / "scene_gt.json").read_text())
    im = sorted(gt, key=int)[0]
    gt[im][0]["cam_R_m2c"] = [1.1 * v for v in gt[im][0]["cam_R_m2c"]]
    (scene / "scene_gt.json").write_text(json.dumps(gt))
    res, warned = _validate("--dataset", str(root), "--split", "test")
    assert res.exit_code == 2
    problems = [ln for ln in res.stderr.splitlines() if ln.strip() and not ln.startswith("warning: ")]
    assert len(problems) == 1, problems
    assert str(scene / "scene_gt.json") in problems[0] and f"image {im}, instance 0" in problems[0]
    assert "cam_R_m2c is not a rotation matrix" in problems[0]
    assert any(str(scene / "scene_gt.json") in w for w in warned)  # the others of the file: repaired


@needs_realdata
def test_synth_candidates_then_match_on_lmo(tmp_path):
    cands, out = tmp_path / "cands.csv", tmp_path / "match"
    r = CliRunner().invoke(cli, ["synth-candidates", "--dataset", str(LMO), "--out", str(cands), "--verbose"])
    assert r.exit_code == 0, r.output
    gt_warnings = [ln for ln in r.stderr.splitlines() if ln.startswith("warning: ")]
    assert gt_warnings and all("scene_gt.json" in w for w in gt_warnings), gt_warnings  # the GT, repaired when read
    assert len(gt_warnings) == len({w.split(":")[1] for w in gt_warnings})  # one per file
    with warnings.catch_warnings():
        warnings.simplefilter("error", CosyWarning)  # what cosy writes is clean
        res = bop.read_results(cands)
    assert len(res) > 100 and bop.rotation_errors(res.T_cam_obj[:, :3, :3]).max() < 1e-8
    r = CliRunner().invoke(cli, ["match", "--dataset", str(LMO), "--candidates", str(cands), "--out", str(out), "-v"])
    assert r.exit_code == 0, r.output
    assert "cands.csv" not in r.stderr
    assert "not a rotation" not in r.output
    matches = pd.read_csv(out / "matches.csv")
    assert len(matches) == len(res) and (matches["object_id"] >= 0).sum() > len(res) // 2
