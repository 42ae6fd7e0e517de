"""Integrity between stages: each stage lists the files it wrote (sha1 + size) in a manifest,
the next stage refuses a file changed or truncated since (exit 2, one line naming file and
stage); a file without a manifest (made by the user) is fully validated instead."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from cosy_cli.cli.main import cli
from cosy_cli.io import manifest
from cosy_cli.io.cache import file_sha1
from one_view_fixtures import one_image_dataset, tiny_templates


def _ok(args):
    r = CliRunner().invoke(cli, [str(a) for a in args])
    assert r.exit_code == 0, r.output
    return r


def _refused(args, *expected):
    r = CliRunner().invoke(cli, [str(a) for a in args])
    assert r.exit_code == 2, r.output
    assert "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1, r.output
    for e in expected:
        assert e in r.output, (e, r.output)
    return r


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    """detect -> estimate -> match -> refine -> evaluate on 3 views of data_samples scene 1."""
    root = tmp_path_factory.mktemp("integrity")
    ds = one_image_dataset(root / "ds", keep={1: [0, 1, 2]})
    tpl = tiny_templates(root / "templates")
    p = {"ds": ds, "dets": root / "dets.json", "cands": root / "cands.csv", "match": root / "match",
         "refine": root / "refine", "eval": root / "eval", "tpl": tpl}
    _ok(["detect", "--dataset", ds, "--from-gt", "--out", p["dets"], "--quiet"])
    _ok(["estimate", "--dataset", ds, "--detections", p["dets"], "--out", p["cands"], "--templates-dir", tpl,
         "--quiet"])
    _ok(["match", "--dataset", ds, "--candidates", p["cands"], "--out", p["match"]])
    _ok(["refine", "--dataset", ds, "--matches", p["match"], "--out", p["refine"]])
    _ok(["evaluate", "--dataset", ds, "--predictions", p["refine"] / "predictions.csv", "--out", p["eval"],
         "--no-vsd", "--scene-json", p["refine"] / "scene.json"])
    return p


def _cut_last_row(path: Path) -> None:
    """Drop the last data row: still a well-formed CSV, only the manifest can tell."""
    lines = path.read_text().splitlines(keepends=True)
    assert len(lines) > 2
    path.write_text("".join(lines[:-1]))


def _cut_mid_row(path: Path) -> int:
    """Cut the file in the middle of its 2nd data row; returns that row's number (1-based)."""
    text = path.read_text()
    lines = text.splitlines(keepends=True)
    path.write_text("".join(lines[:2]) + lines[2][: len(lines[2]) // 3])
    return 2


def test_every_stage_records_what_it_wrote(chain):
    expected = {manifest.sidecar_path(chain["dets"]): ("cosy detect", [chain["dets"]]),
                manifest.sidecar_path(chain["cands"]): ("cosy estimate", [chain["cands"]]),
                chain["match"] / "manifest.json": ("cosy match", [chain["match"] / f for f in
                                                                  ("matches.csv", "view_pairs.csv", "groups.json",
                                                                   "candidates.csv")]),
                chain["refine"] / "manifest.json": ("cosy refine", [chain["refine"] / "scene.json",
                                                                    chain["refine"] / "predictions.csv"]),
                chain["eval"] / "manifest.json": ("cosy evaluate", [chain["eval"] / "scores.json"])}
    for m, (stage, files) in expected.items():
        doc = json.loads(m.read_text())
        assert doc["format"] == "cosy-manifest" and doc["stage"] == stage
        for f in files:
            assert doc["files"][f.name] == {"sha1": file_sha1(f), "size": f.stat().st_size}, f


@pytest.mark.parametrize("how", ["truncated", "changed"])
def test_changed_or_truncated_candidates_refused_by_match(chain, tmp_path, how):
    cands = tmp_path / "cands.csv"
    shutil.copy(chain["cands"], cands)
    shutil.copy(manifest.sidecar_path(chain["cands"]), manifest.sidecar_path(cands))
    if how == "truncated":
        _cut_last_row(cands)
    else:  # one digit of a score
        text = cands.read_text()
        i = text.index("\n") + 1
        row = text[i:text.index("\n", i)].split(",")
        row[3] = "0.123"
        cands.write_text(text[:i] + ",".join(row) + text[text.index("\n", i):])
    out = tmp_path / "match"
    _refused(["match", "--dataset", chain["ds"], "--candidates", cands, "--out", out],
             f"{cands} changed or truncated since cosy estimate wrote it", "expected sha1",
             "rerun cosy estimate or pass --overwrite there")
    assert not out.exists()


def test_changed_or_truncated_match_output_refused_by_refine(chain, tmp_path):
    for name, cut in (("matches.csv", _cut_mid_row), ("candidates.csv", _cut_last_row),
                      ("groups.json", lambda p: p.write_text(p.read_text()[:200]))):
        m = tmp_path / f"match_{name}"
        shutil.copytree(chain["match"], m)
        cut(m / name)
        out = tmp_path / f"refine_{name}"
        _refused(["refine", "--dataset", chain["ds"], "--matches", m, "--out", out],
                 f"{m / name} changed or truncated since cosy match wrote it", "rerun cosy match")
        assert not out.exists()
    # a hand-edited folder without its manifest is read as it is (here: a cut matches.csv, unused by refine)
    m = tmp_path / "match_matches.csv"
    (m / "manifest.json").unlink()
    _ok(["refine", "--dataset", chain["ds"], "--matches", m, "--out", tmp_path / "refine_hand"])


def test_changed_or_truncated_predictions_refused_by_evaluate(chain, tmp_path):
    r = tmp_path / "refine"
    shutil.copytree(chain["refine"], r)
    _cut_last_row(r / "predictions.csv")
    out = tmp_path / "eval"
    _refused(["evaluate", "--dataset", chain["ds"], "--predictions", r / "predictions.csv", "--out", out, "--no-vsd"],
             f"{r / 'predictions.csv'} changed or truncated since cosy refine wrote it", "rerun cosy refine")
    assert not out.exists()


def test_changed_detections_refused_by_estimate(chain, tmp_path):
    dets = tmp_path / "dets.json"
    shutil.copy(chain["dets"], dets)
    shutil.copy(manifest.sidecar_path(chain["dets"]), manifest.sidecar_path(dets))
    doc = json.loads(dets.read_text())
    dets.write_text(json.dumps(doc[:-1]))
    _refused(["estimate", "--dataset", chain["ds"], "--detections", dets, "--out", tmp_path / "c.csv",
              "--templates-dir", chain["tpl"], "--quiet"], f"{dets} changed or truncated since cosy detect wrote it")
    assert not (tmp_path / "c.csv").exists()


def test_user_csv_cut_mid_row_is_refused_naming_the_row(chain, tmp_path):
    """No manifest (a file made by hand or by another tool): the readers refuse a row cut short."""
    cands = tmp_path / "user_cands.csv"
    shutil.copy(chain["cands"], cands)
    row = _cut_mid_row(cands)
    _refused(["match", "--dataset", chain["ds"], "--candidates", cands, "--out", tmp_path / "m"],
             str(cands), f"row {row}:", "the row is cut short")
    preds = tmp_path / "user_preds.csv"
    shutil.copy(chain["refine"] / "predictions.csv", preds)
    row = _cut_mid_row(preds)
    _refused(["evaluate", "--dataset", chain["ds"], "--predictions", preds, "--out", tmp_path / "e", "--no-vsd"],
             str(preds), f"row {row}:", "cut short")


def test_a_damaged_output_is_not_reused_as_up_to_date(chain, tmp_path):
    m = tmp_path / "match"
    shutil.copytree(chain["match"], m)
    args = ["match", "--dataset", chain["ds"], "--candidates", chain["cands"], "--out", m]
    assert "up to date, skipping" in _ok(args).output
    _cut_last_row(m / "matches.csv")
    _refused(args, "exists but was made from other inputs", "matches.csv changed or truncated since cosy match",
             "--overwrite")
    _ok(args + ["--overwrite"])
    assert manifest.verify_folder(m)
    # the same for a single-file output (estimate's candidates)
    c = tmp_path / "cands.csv"
    for f in (chain["cands"], chain["cands"].with_suffix(".json"), chain["cands"].with_suffix(".timing.csv"),
              manifest.sidecar_path(chain["cands"])):
        shutil.copy(f, tmp_path / f.name)
    args = ["estimate", "--dataset", chain["ds"], "--detections", chain["dets"], "--out", c, "--templates-dir",
            chain["tpl"]]
    assert "up to date, skipping" in _ok(args).output
    _cut_last_row(c)
    _refused(args, "cands.csv changed or truncated since cosy estimate wrote it")


def test_manifests_of_other_tools_are_ignored_and_damaged_ones_refused(tmp_path):
    f = tmp_path / "a.csv"
    f.write_text("x\n1\n")
    (tmp_path / "manifest.json").write_text('{"name": "a web app manifest"}')  # someone else's
    assert manifest.verify(f) is False
    manifest.write_file_manifest(f, "cosy test")
    assert manifest.verify(f) is True
    side = manifest.sidecar_path(f)
    side.write_text(side.read_text()[:60])  # a cut cosy manifest: refused, not ignored
    with pytest.raises(manifest.CosyError, match="unreadable manifest"):
        manifest.verify(f)
