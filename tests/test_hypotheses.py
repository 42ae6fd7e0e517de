"""Several pose hypotheses per detection: the sidecar of cosy estimate, and cosy match choosing
among them (mutually exclusive hypotheses; hypotheses = 1 is the paper, bit-identical)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

sys.path.insert(0, str(Path(__file__).parent))

from multiview_fixtures import make_table_dataset  # noqa: E402

from cosy_cli.cli.main import cli  # noqa: E402
from cosy_cli.errors import CosyError  # noqa: E402
from cosy_cli.io import bop, manifest  # noqa: E402
from cosy_cli.io import hypotheses as hyp_io  # noqa: E402
from cosy_cli.io.dataset import BopDataset  # noqa: E402
from cosy_cli.multiview import match_stage  # noqa: E402
from cosy_cli.multiview.matching import MatchParams, match_group  # noqa: E402
from cosy_cli.singleview import estimate_stage  # noqa: E402
from cosy_cli.synth import candidates as sc  # noqa: E402

QUIET = dict(log=lambda *_: None, progress=False)


@pytest.fixture(scope="module")
def tables(tmp_path_factory) -> Path:
    """2 scenes x 4 views x 6 objects of the simple models."""
    return make_table_dataset(tmp_path_factory.mktemp("tables"), n_scenes=2, n_views=4, n_objects=6, seed=11)


def _cands(root: Path, out: Path, profile="realistic", seed=0, **knobs) -> tuple[Path, pd.DataFrame]:
    csv, side = out / f"c_{profile}_{seed}.csv", out / f"c_{profile}_{seed}_gt.csv"
    sc.main(root, "test", csv, profile=profile, seed=seed, gt_out=side, log=lambda *_: None, **knobs)
    return csv, pd.read_csv(side)


def _shift(T: np.ndarray, mm: float, seed: int | None = None) -> np.ndarray:
    """T moved by ``mm`` along its camera's x axis, or with ``seed`` in a random direction per
    pose (a pose no other view agrees with)."""
    T = T.copy()
    if seed is None:
        T[..., 0, 3] += mm
    else:
        d = np.random.default_rng(seed).normal(size=T.shape[:-2] + (3,))
        T[..., :3, 3] += mm * d / np.linalg.norm(d, axis=-1, keepdims=True)
    return T


def _with_sidecar(csv: Path, T_alt: np.ndarray, swap: np.ndarray, out_csv: Path, listed: bool = True) -> Path:
    """A candidates CSV whose rows ``swap`` hold a wrong pose (rank 0) and the right one at rank 1;
    every other row has a wrong rank 1. Written like cosy estimate (manifest listing the sidecar)."""
    res = bop.read_results(csv)
    n = len(res)
    T0 = res.T_cam_obj.copy()
    T1 = _shift(T0, 300.0, seed=7)
    T0[swap], T1[swap] = T1[swap], res.T_cam_obj[swap]
    tab = res.table
    main = bop.PoseResults.from_arrays(tab.scene_id, tab.im_id, tab.obj_id, tab.score, T0, tab.time)
    text = bop.format_results(main)
    side = hyp_io.sidecar_path(out_csv)
    hyp_text = hyp_io.format_hypotheses(np.repeat(np.arange(n), 2), np.tile([0, 1], n), np.ones(2 * n),
                                        np.stack([T0, T1], 1).reshape(-1, 4, 4))
    manifest.write_file_manifest(out_csv, "cosy estimate", text.encode(),
                                 extra={side.name: hyp_text.encode()} if listed else None)
    side.write_text(hyp_text)
    out_csv.write_text(text)
    return out_csv


def _match(root, csv, out, **conf):
    c = match_stage.resolve_conf("paper", **conf)
    return match_stage.main(c, root, "test", csv, out, overwrite=True, **QUIET)


def test_sidecar_path_and_round_trip(tmp_path):
    assert hyp_io.sidecar_path(tmp_path / "cands.csv") == tmp_path / "cands.hypotheses.csv"
    rng = np.random.default_rng(0)
    from cosy_cli.geometry.rotations import random_rotations

    T = np.tile(np.eye(4), (6, 1, 1))
    T[:, :3, :3] = random_rotations(6, rng)
    T[:, :3, 3] = rng.normal(0, 300, (6, 3))
    p = tmp_path / "h.csv"
    p.write_text(hyp_io.format_hypotheses([2, 0, 0, 1, 1, 2], [0, 1, 0, 0, 1, 1], np.arange(6.0), T))
    det, rank, score, T2 = hyp_io.read_hypotheses(p, 3)
    assert det.tolist() == [0, 0, 1, 1, 2, 2] and rank.tolist() == [0, 1, 0, 1, 0, 1]
    o = [2, 1, 3, 4, 0, 5]
    assert np.allclose(T2, T[o], atol=1e-5) and np.allclose(score, np.arange(6.0)[o])
    with pytest.raises(CosyError, match="det_id 2"):
        hyp_io.read_hypotheses(p, 2)  # only 2 candidates
    p.write_text(p.read_text().replace("\n1,1,", "\n1,0,", 1))
    with pytest.raises(CosyError, match="twice"):
        hyp_io.read_hypotheses(p, 3)
    p.write_text("det_id,rank,score,R,t\n0,0,1,1 0 0 0 1 0 0 0,1 2 3\n")
    with pytest.raises(CosyError, match="row 1"):
        hyp_io.read_hypotheses(p, 3)
    # rotations as in every BOP reader: within 0.05 replaced by the nearest one, beyond an error
    p.write_text("det_id,rank,score,R,t\n0,0,1,1.01 0 0 0 1 0 0 0 1,1 2 3\n")
    with pytest.warns(UserWarning, match="nearest rotation"):
        T3 = hyp_io.read_hypotheses(p, 3)[3]
    assert np.allclose(T3[0, :3, :3], np.eye(3), atol=1e-9)
    p.write_text("det_id,rank,score,R,t\n0,0,1,1 0 0 0 1 0 0 0 1,1 2 3\n0,1,1,1.2 0 0 0 1 0 0 0 1,1 2 3\n")
    with pytest.raises(CosyError, match="row 2"):
        hyp_io.read_hypotheses(p, 3)


def test_det_without_alternatives_is_bit_identical(tables, tmp_path):
    """match_group with det = one per candidate (and zero prior) equals the paper's matching."""
    csv, _ = _cands(tables, tmp_path, "realistic", seed=3, fp_per_image=1.0, p_gross=0.1)
    ds = BopDataset(tables, "test")
    table = match_stage.load_label_table(ds, sorted(ds.models_info()))
    res = bop.read_results(csv)
    sel = np.flatnonzero(res.table.scene_id.to_numpy() == 1)
    im = res.table.im_id.to_numpy()[sel]
    lab = table.index_of(res.table.obj_id.to_numpy()[sel])
    params = MatchParams(threshold_rel=0.1, adaptive_k=3, weak_links=True)
    a = match_group(im, lab, res.T_cam_obj[sel], 4, table, params)
    b = match_group(im, lab, res.T_cam_obj[sel], 4, table, params, det=np.arange(len(sel))[::-1])
    for f in ("object_id", "pair_views", "n_inliers", "linked", "edges", "edge_kept", "T_ab", "edge_dist", "cand_fit"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f


def test_hypotheses_1_ignores_the_sidecar_bit_identically(tables, tmp_path):
    csv, _ = _cands(tables, tmp_path, "realistic", seed=1)
    mine = _with_sidecar(csv, None, np.zeros(0, dtype=np.int64), tmp_path / "own.csv")
    plain = tmp_path / "plain.csv"
    plain.write_text(mine.read_text())  # the same rows, no sidecar, no manifest
    _match(tables, mine, tmp_path / "a")
    _match(tables, plain, tmp_path / "b")
    for f in ("matches.csv", "view_pairs.csv", "candidates.csv"):
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    doc = json.loads((tmp_path / "a" / "groups.json").read_text())
    assert "hypotheses" not in doc and "hyp_ranks" not in doc["groups"][0]["objects"][0]


def test_match_chooses_the_hypothesis_the_other_views_agree_with(tables, tmp_path):
    csv, side = _cands(tables, tmp_path, "clean")
    n = len(side)
    swap = np.random.default_rng(0).choice(n, n // 3, replace=False)
    mine = _with_sidecar(csv, None, swap, tmp_path / "own.csv")
    # one pose per detection: the swapped ones (300 mm off) are discarded
    s1 = _match(tables, mine, tmp_path / "h1")
    assert s1["discarded"] >= len(swap) * 3 // 4
    s2 = _match(tables, mine, tmp_path / "h2", hypotheses=2)
    assert s2["discarded"] == 0
    m = pd.read_csv(tmp_path / "h2" / "matches.csv")
    assert list(m.columns)[-1] == "hyp_rank"
    want = np.zeros(n, dtype=np.int64)
    want[swap] = 1
    assert np.array_equal(m.hyp_rank.to_numpy(), want)
    # at most one detection per view per object; candidates.csv carries the chosen (true) poses
    assert not m[m.object_id >= 0].duplicated(["scene_id", "group_id", "object_id", "im_id"]).any()
    chosen = bop.read_results(tmp_path / "h2" / "candidates.csv")
    truth = bop.read_results(csv)
    assert np.allclose(chosen.T_cam_obj, truth.T_cam_obj, atol=1e-4)
    assert chosen.table[["scene_id", "im_id", "obj_id"]].equals(truth.table[["scene_id", "im_id", "obj_id"]])
    doc = json.loads((tmp_path / "h2" / "groups.json").read_text())
    assert doc["hypotheses"]["per_candidate"] == 2 and doc["hypotheses"]["chosen_not_rank0"] == len(swap)
    o = doc["groups"][0]["objects"][0]
    assert len(o["hyp_ranks"]) == len(o["cand_ids"])
    assert all(want[c] == r for g in doc["groups"] for o in g["objects"] for c, r in zip(o["cand_ids"], o["hyp_ranks"]))
    # cosy refine reads the chosen poses from the match folder
    from cosy_cli.multiview import refine_stage

    r = refine_stage.main(refine_stage.resolve_conf(None), tables, "test", tmp_path / "h2", tmp_path / "r",
                          overwrite=True, **QUIET)
    assert r is not None and (tmp_path / "r" / "predictions.csv").is_file()


def test_mutually_exclusive_hypotheses(tables, tmp_path):
    """Two hypotheses of a detection that both agree with the other views: one is chosen, the
    detection is in one object only, its other hypothesis unused."""
    csv, side = _cands(tables, tmp_path, "clean")
    ds = BopDataset(tables, "test")
    table = match_stage.load_label_table(ds, sorted(ds.models_info()))
    res = bop.read_results(csv)
    sel = np.flatnonzero(res.table.scene_id.to_numpy() == 1)
    n = len(sel)
    im = res.table.im_id.to_numpy()[sel]
    lab = table.index_of(res.table.obj_id.to_numpy()[sel])
    T = res.T_cam_obj[sel]
    T_near = _shift(T, 2.0)  # a second hypothesis as good as the first
    det = np.repeat(np.arange(n), 2)
    r = match_group(np.repeat(im, 2), np.repeat(lab, 2), np.stack([T, T_near], 1).reshape(-1, 4, 4), 4, table,
                    MatchParams(), det=det)
    inside = r.object_id >= 0
    assert np.bincount(det[inside], minlength=n).max() == 1  # at most one hypothesis per detection
    assert np.bincount(det[inside], minlength=n).min() == 1  # every detection placed
    views = np.repeat(im, 2)
    objs = pd.DataFrame({"o": r.object_id[inside], "v": views[inside]})
    assert not objs.duplicated().any()
    # associations pair detections one-to-one in every view pair
    e = det[r.edges]
    for p in np.unique(r.edge_pair):
        ep = e[r.edge_pair == p]
        assert len(np.unique(ep[:, 0])) == len(ep) and len(np.unique(ep[:, 1])) == len(ep)


def test_sidecar_must_belong_to_the_csv(tables, tmp_path):
    csv, _ = _cands(tables, tmp_path, "clean")
    swap = np.arange(3)
    mine = _with_sidecar(csv, None, swap, tmp_path / "own.csv", listed=False)  # not in the manifest: stale
    assert match_stage.hypotheses_file(mine) is None
    s = _match(tables, mine, tmp_path / "a", hypotheses=2)
    assert pd.read_csv(tmp_path / "a" / "matches.csv").hyp_rank.eq(0).all() and s["discarded"] >= 1
    mine = _with_sidecar(csv, None, swap, tmp_path / "own2.csv")
    side = hyp_io.sidecar_path(mine)
    side.write_text(side.read_text().replace("\n0,1,", "\n0,2,", 1))  # changed since estimate wrote it
    with pytest.raises(CosyError, match="changed"):
        _match(tables, mine, tmp_path / "b", hypotheses=2)


def test_cli_options(tables, tmp_path):
    csv, _ = _cands(tables, tmp_path, "clean")
    mine = _with_sidecar(csv, None, np.arange(4), tmp_path / "own.csv")
    r = CliRunner().invoke(cli, ["match", "--dataset", str(tables), "--candidates", str(mine), "--out",
                                 str(tmp_path / "m"), "--hypotheses", "2", "--hypothesis-penalty", "0.5"])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "m" / "groups.json").read_text())["conf"]["hypotheses"] == 2
    r = CliRunner().invoke(cli, ["estimate", "--help"])
    assert "--hypotheses" in r.output
    r = CliRunner().invoke(cli, ["match", "--dataset", str(tables), "--candidates", str(mine), "--out",
                                 str(tmp_path / "m2"), "--hypotheses", "0"])
    assert r.exit_code == 2


def test_estimate_writes_ranked_alternatives():
    """The sidecar text of cosy estimate: rank 0 = the CSV's pose, then the alternatives that exist."""
    N = 2
    T = np.tile(np.eye(4), (N, 1, 1))
    T[:, 2, 3] = [500.0, 700.0]
    alt = np.tile(np.eye(4), (N, 3, 1, 1))
    alt[:, :, 0, 3] = np.arange(1, 4)[None] * 10.0
    r = estimate_stage.ImageEstimate(T, alternatives=alt[:, :3], alt_score=np.array([[0.9, 0.8, 0.7], [0.5, 0.4, 0.3]]),
                                     best_score=np.array([1.0, 0.6]))
    s0, aT, aS = estimate_stage._alternatives(r, 4)  # one more than there are: NaN score, left out
    assert np.isnan(aS[:, 3]).all()
    text = estimate_stage._hypotheses_text(T, s0, aT, aS)
    lines = text.strip().splitlines()
    assert lines[0] == "det_id,rank,score,R,t" and len(lines) == 1 + N * 4
    import io as _io
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "x.hypotheses.csv"
        p.write_text(text)
        det, rank, score, T2 = hyp_io.read_hypotheses(p, N)
    assert rank.tolist() == [0, 1, 2, 3] * 2 and np.allclose(score[:4], [1.0, 0.9, 0.8, 0.7])
    assert np.allclose(T2[0], T[0]) and np.allclose(T2[5], alt[1, 0])
    assert _io  # noqa
    with pytest.raises(CosyError):
        estimate_stage.resolve_conf(None, hypotheses=0)


SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"


@pytest.fixture(scope="module")
def sample_templates(tmp_path_factory):
    """Templates of the sample objects at a reduced resolution (fast to build)."""
    from cosy_cli.singleview.training_free import templates

    out = tmp_path_factory.mktemp("tpl") / "templates"
    templates.main({"viewpoints": 200, "inplane": 24}, SAMPLES / "models", out, log=lambda *_: None)
    return out


@pytest.mark.parametrize("depth", ["icp", "none"])
def test_estimate_sidecar_end_to_end(tmp_path, sample_templates, depth):
    """cosy estimate --hypotheses 3: the CSV is the same as without (a pure BOP results file), the
    sidecar holds rank 0 = the CSV's pose then distinct runners-up, the manifest lists both, and
    cosy match reads it; rerunning with 1 removes the sidecar."""
    base = ["estimate", "--scene", str(SAMPLES / "test" / "000001"), "--from-gt", "--coarse", "templates",
            "--refiner", "none", "--depth-refine", depth, "--templates-dir", str(sample_templates), "--quiet"]
    if depth == "none":
        base += ["--verify-top", "8", "--top-k", "4"]
    r1 = CliRunner().invoke(cli, base + ["--out", str(tmp_path / "one.csv")], catch_exceptions=False)
    r3 = CliRunner().invoke(cli, base + ["--out", str(tmp_path / "three.csv"), "--hypotheses", "3"],
                            catch_exceptions=False)
    assert r1.exit_code == 0 and r3.exit_code == 0, r3.output
    assert not (tmp_path / "one.hypotheses.csv").exists()
    one, three = bop.read_results(tmp_path / "one.csv"), bop.read_results(tmp_path / "three.csv")
    assert (tmp_path / "three.csv").read_text().splitlines()[0] == "scene_id,im_id,obj_id,score,R,t,time"
    assert np.allclose(one.T_cam_obj, three.T_cam_obj)
    side = tmp_path / "three.hypotheses.csv"
    det, rank, score, T = hyp_io.read_hypotheses(side, len(three))
    assert np.array_equal(np.unique(det), np.arange(len(three))) and rank.max() == 2
    assert np.allclose(T[rank == 0], three.T_cam_obj, atol=1e-5)
    r0 = dict(zip(det[rank == 0].tolist(), T[rank == 0]))
    assert any(not np.allclose(t, r0[d], atol=1e-3) for d, t in zip(det[rank > 0].tolist(), T[rank > 0]))
    doc = json.loads(manifest.sidecar_path(tmp_path / "three.csv").read_text())
    assert set(doc["files"]) == {"three.csv", "three.hypotheses.csv"}
    manifest.verify(tmp_path / "three.csv")
    manifest.verify_companion(tmp_path / "three.csv", side)
    assert match_stage.load_hypotheses(tmp_path / "three.csv", len(three), 3)[1].any()
    # rerun with one hypothesis: the sidecar goes (it would not belong to the new CSV)
    r = CliRunner().invoke(cli, base + ["--out", str(tmp_path / "three.csv"), "--overwrite"], catch_exceptions=False)
    assert r.exit_code == 0 and not side.exists()
