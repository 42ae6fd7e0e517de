"""Label groups in cosy match (issue 19, beyond the paper): candidates of look-alike labels matched
together, the object labelled by the vote of its members."""

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
from cosy_cli.geometry.poses import invert, look_at, make_pose  # noqa: E402
from cosy_cli.geometry.rotations import rotation_about_axis  # noqa: E402
from cosy_cli.io import bop  # noqa: E402
from cosy_cli.io.dataset import BopDataset  # noqa: E402
from cosy_cli.multiview import label_groups as lg  # noqa: E402
from cosy_cli.multiview import match_stage  # noqa: E402
from cosy_cli.multiview.matching import MatchParams, match_group  # noqa: E402
from cosy_cli.synth import candidates as sc  # noqa: E402


@pytest.fixture(scope="module")
def tables(tmp_path_factory) -> Path:
    """2 scenes x 6 views of the simple models: box 1, cylinder 2, L shape 3, look-alikes 6/7."""
    return make_table_dataset(tmp_path_factory.mktemp("lg"), n_scenes=2, n_views=6, n_objects=8, seed=3)


@pytest.fixture(autouse=True)
def _own_cache(tmp_path_factory, monkeypatch):
    """Look-alike fits cached in a folder of this test session (not the user's cache)."""
    monkeypatch.setenv("COSY_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "cosy_cache"))


def _Rz(deg):
    return rotation_about_axis(np.array([0.0, 0, 1]), np.array([np.radians(deg)]))[0]


def _four_views(mislabel: bool = True):
    """4 views of 5 objects (two L shapes, a box, a cylinder, object 6); object 6's candidate in
    view 2 is labelled 7 (the look-alike). Returns (view, obj_id, T_cam_obj, index of object 6's
    candidates, T_cam_world)."""
    world = [(3, make_pose(_Rz(10), np.array([-120.0, 40, 15]))), (3, make_pose(_Rz(200), np.array([110.0, -60, 15]))),
             (1, make_pose(_Rz(35), np.array([20.0, 120, 15]))), (2, make_pose(np.eye(3), np.array([-30.0, -130, 35]))),
             (6, make_pose(_Rz(-70), np.array([40.0, 10, 15])))]
    T_cw = []
    for k in range(4):
        a = np.radians(90 * k + 20)
        T_wc = look_at(np.array([650 * np.cos(a), 650 * np.sin(a), 450.0]), np.zeros(3), np.array([0, 0, 1.0]))
        T_cw.append(invert(T_wc))
    view, lab, T, six = [], [], [], []
    rng = np.random.default_rng(0)
    for v in range(4):
        for o, Two in world:
            T_co = T_cw[v] @ Two
            T_co[:3, 3] += rng.normal(0, 1.0, 3)  # 1 mm noise
            if o == 6:
                six.append(len(view))
            view.append(v)
            lab.append(7 if (o == 6 and v == 2 and mislabel) else o)
            T.append(T_co)
    return np.array(view), np.array(lab), np.stack(T), np.array(six), np.stack(T_cw)


def test_mislabelled_view_joins_with_groups_and_is_voted(tables):
    ds = BopDataset(tables, "test")
    ids = sorted(ds.models_info())
    view, obj, T, six, _ = _four_views()
    score = np.full(len(view), 0.9)
    score[six[2]] = 0.95  # the wrong label scores best in its view: the vote still says 6
    results = {}
    for setting in ("none", "auto", [[6, 7]]):
        res = lg.resolve(lg.normalize_setting(setting), ds)
        table = match_stage.load_label_table(ds, ids, groups=res)
        r = match_group(view, table.index_of(obj), T, 4, table, MatchParams())
        results[str(setting)] = r
        labels, votes = lg.vote_labels(r.object_id, obj, score, r.cand_fit)
        o6 = r.object_id[six[0]]
        assert o6 >= 0 and labels[o6] == 6
        if setting == "none":  # the paper: the candidate labelled 7 has no partner, it is discarded
            assert r.object_id[six[2]] == -1
            assert (r.object_id[six[[0, 1, 3]]] == o6).all()
            assert set(votes[o6]) == {6}
        else:  # matched with the object and outvoted (3 x 0.9 fit-weighted against 1 x 0.95)
            assert (r.object_id[six] == o6).all()
            assert set(votes[o6]) == {6, 7} and votes[o6][6] > votes[o6][7] > 0
        assert r.linked.all()
        assert np.all((r.cand_fit > 0) == (r.object_id >= 0)) and r.cand_fit.max() <= 1.0
    # known cameras: the same objects, no RANSAC
    view, obj, T, six, T_cw = _four_views()
    for setting, joined in (("none", False), ("auto", True)):
        table = match_stage.load_label_table(ds, ids, groups=lg.resolve(setting, ds))
        r = match_group(view, table.index_of(obj), T, 4, table, MatchParams(), T_cam_world=T_cw)
        assert (r.object_id[six[2]] == r.object_id[six[0]]) == joined and r.object_id[six[0]] >= 0
        assert r.linked.all()
    # everything else is the same: the other objects and the camera poses
    a, b = results["none"], results["auto"]
    others = np.setdiff1d(np.arange(len(view)), six)
    assert np.array_equal(a.object_id[others] >= 0, b.object_id[others] >= 0)
    # the view pairs' poses, counts and links are the paper's, exactly (grouped labels only add associations)
    assert np.array_equal(a.T_ab, b.T_ab) and np.array_equal(a.n_inliers, b.n_inliers)
    assert np.array_equal(a.linked, b.linked) and np.array_equal(a.threshold_mm, b.threshold_mm)


def test_none_is_the_paper_exactly(tables):
    """label_groups none, and auto on candidates of labels without a look-alike: the same results
    as same-label matching, bit for bit (realistic candidates, the default settings)."""
    ds = BopDataset(tables, "test")
    ids = sorted(ds.models_info())
    plain = match_stage.load_label_table(ds, ids)
    none = match_stage.load_label_table(ds, ids, groups=lg.resolve("none", ds))
    auto = match_stage.load_label_table(ds, ids, groups=lg.resolve("auto", ds))
    assert not none.cross and auto.cross
    res, _ = sc.simulate_candidates(ds, sc.PROFILES["realistic"], seed=1)
    t = res.table
    c = match_stage.resolve_conf("paper")
    params = MatchParams(threshold_mm=c["threshold_mm"], threshold_rel=c["threshold_rel"], adaptive_k=c["adaptive_k"],
                         weak_links=c["weak_links"])
    for s in ds.scene_ids:
        sel = np.flatnonzero(t.scene_id.to_numpy() == s)
        ims = np.unique(t.im_id.to_numpy()[sel])
        view = np.searchsorted(ims, t.im_id.to_numpy()[sel])
        obj = t.obj_id.to_numpy()[sel]
        no67 = ~np.isin(obj, [6, 7])
        for tab_b, keep in ((none, np.ones(len(sel), bool)), (auto, no67)):
            Tk = res.T_cam_obj[sel][keep]
            ra = match_group(view[keep], plain.index_of(obj[keep]), Tk, len(ims), plain, params, s)
            rb = match_group(view[keep], tab_b.index_of(obj[keep]), Tk, len(ims), tab_b, params, s)
            for f in ("object_id", "n_inliers", "T_ab", "linked", "edges", "edge_dist", "edge_kept", "threshold_mm",
                      "link_kind", "cand_fit"):
                assert np.array_equal(getattr(ra, f), getattr(rb, f)), f


def test_groups_only_join_allowed_labels(tables):
    """With the box (1) and the L shape (3) grouped instead, object 6/7 stay apart."""
    ds = BopDataset(tables, "test")
    ids = sorted(ds.models_info())
    view, obj, T, six, _ = _four_views()
    table = match_stage.load_label_table(ds, ids, groups=lg.resolve([[1, 3]], ds))
    r = match_group(view, table.index_of(obj), T, 4, table, MatchParams())
    assert r.object_id[six[2]] == -1
    # a box and an L shape are different shapes: grouped, but their candidates are not associated
    for o in range(r.n_objects):
        assert len(set(obj[r.object_id == o])) == 1


def test_vote_ties_and_weights():
    labels, votes = lg.vote_labels(np.array([0, 0, 0, 1, -1]), np.array([6, 7, 7, 5, 6]),
                                   np.array([0.9, 0.5, 0.3, 0.8, 1.0]), np.array([1.0, 1.0, 1.0, 0.5, 0.0]))
    assert list(labels) == [6, 5]  # 0.9 > 0.8
    assert votes[0] == pytest.approx({6: 0.9, 7: 0.8}) and votes[1] == pytest.approx({5: 0.4})
    # a tie goes to the label of the best-scoring member
    labels, _ = lg.vote_labels(np.array([0, 0]), np.array([7, 6]), np.array([0.5, 0.25]), np.array([0.5, 1.0]))
    assert labels[0] == 7


def test_setting_parsing():
    assert lg.normalize_setting(None) == "auto" and lg.normalize_setting("AUTO") == "auto"
    assert lg.normalize_setting("none") == "none"
    assert lg.normalize_setting("6:7,5:8") == [[5, 8], [6, 7]]
    assert lg.normalize_setting(" 7:6 , 8:7:6") == [[6, 7], [6, 7, 8]]
    assert lg.normalize_setting("[[7, 6], [5, 8]]") == [[5, 8], [6, 7]]
    assert lg.normalize_setting([[6, 7]]) == [[6, 7]]
    for bad in ("6-7", "6:x", "6", "6:6", "[[6]]", "[6, 7]", "{", 3.5):
        with pytest.raises(CosyError, match="label_groups"):
            lg.normalize_setting(bad)
    c = match_stage.resolve_conf("paper", label_groups="7:6")
    assert c["label_groups"] == [[6, 7]]
    assert match_stage.resolve_conf("paper")["label_groups"] == "auto"
    assert match_stage.resolve_conf("paper-norefit")["label_groups"] == "none"


def _write_cands(tables: Path, path: Path) -> Path:
    csv, _ = path / "c.csv", None
    sc.main(tables, "test", csv, profile="clean", seed=4, p_lookalike=0.25, lookalikes="6:7", log=lambda *_: None,
            gt_out=path / "c_gt.csv")
    return csv


def test_cli_explicit_groups_and_bad_input(tables, tmp_path):
    csv = _write_cands(tables, tmp_path)
    runner = CliRunner()
    base = ["match", "--dataset", str(tables), "--split", "test", "--candidates", str(csv)]
    for bad, what in (("6:99", "obj_id 99 is not a model"), ("6-7", "expected groups of obj_ids")):
        r = runner.invoke(cli, base + ["--out", str(tmp_path / "bad"), "--label-groups", bad])
        assert r.exit_code == 2, r.output
        lines = [x for x in r.output.strip().splitlines() if x.strip()]
        assert len(lines) == 1 and what in lines[0], r.output
        assert not (tmp_path / "bad").exists()
    out = tmp_path / "m"
    r = runner.invoke(cli, base + ["--out", str(out), "--label-groups", "7:6"])
    assert r.exit_code == 0, r.output
    doc = json.loads((out / "groups.json").read_text())
    assert doc["conf"]["label_groups"] == [[6, 7]]
    rec = doc["label_groups"]
    assert rec["groups"] == [[6, 7]] and rec["pairs"][0]["frames_agree"] is True
    side = pd.read_csv(tmp_path / "c_gt.csv").set_index("cand_id")
    m = pd.read_csv(out / "matches.csv")
    n_voted, right = 0, []
    for g in doc["groups"]:
        for o in g["objects"]:
            gt = side.loc[o["cand_ids"], "gt_obj_id"]
            assert gt.nunique() == 1  # one physical object
            right.append(o["obj_id"] == gt.iloc[0])
            assert (m.set_index("cand_id").loc[o["cand_ids"], "object_obj_id"] == o["obj_id"]).all()
            if "votes" in o:
                n_voted += 1
                assert set(map(int, o["votes"])) == set(o["cand_obj_ids"]) <= {6, 7}
                assert int(max(o["votes"], key=o["votes"].get)) == o["obj_id"]
                assert o["vote_only_cand_ids"] == []  # 6/7: frames agree, every member is a measurement
    assert n_voted > 0 and doc["summary"]["relabelled_candidates"] > 0
    assert np.mean(right) > 0.9  # 1 in 4 candidates of 6/7 mislabelled: the objects' votes are right
    # none: the paper's outputs (no other label in an object)
    out2 = tmp_path / "m2"
    r = runner.invoke(cli, base + ["--out", str(out2), "--label-groups", "none"])
    assert r.exit_code == 0, r.output
    doc2 = json.loads((out2 / "groups.json").read_text())
    assert all("votes" not in o for g in doc2["groups"] for o in g["objects"])
    assert doc2["label_groups"]["setting"] == "none" and doc2["summary"]["relabelled_candidates"] == 0


def test_auto_groups_from_models(tables, tmp_path):
    """6/7 (one small boss more) look alike in their frames; a copy of 6 in another frame is found
    with its alignment; the box, cylinder and L shape are not grouped."""
    import shutil

    import trimesh

    root = tmp_path / "ds"
    shutil.copytree(tables, root)
    mesh = trimesh.load(root / "models" / "obj_000006.ply", force="mesh", process=False)
    T_8_6 = make_pose(rotation_about_axis(np.array([0.0, 1, 0]), np.array([np.pi / 2]))[0], np.array([5.0, -3, 2]))
    mesh.apply_transform(T_8_6)  # model 8 = model 6 in another frame
    (root / "models" / "obj_000008.ply").write_bytes(mesh.export(file_type="ply", encoding="binary"))
    infos = bop.read_models_info(root / "models" / "models_info.json")
    from cosy_cli.objects.database import model_info_from_mesh

    infos[8] = model_info_from_mesh(mesh, np.zeros((0, 4, 4)), [])
    bop.write_models_info(root / "models" / "models_info.json", infos)
    ds = BopDataset(root, "test")
    res = lg.resolve("auto", ds)
    assert res.groups() == [[6, 7, 8]]
    fits = {(f.a, f.b): f for f in res.pairs}
    assert set(fits) == {(6, 7), (6, 8), (7, 8)}
    assert fits[(6, 7)].frames_agree and fits[(6, 7)].rel < 0.02
    f = fits[(6, 8)]
    assert not f.frames_agree and f.rel < 0.02
    # T_a_b maps model 8's frame into model 6's: the inverse of the transform applied
    E = f.T_a_b @ T_8_6
    print("alignment error", np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1))), E[:3, 3])
    assert np.linalg.norm(E[:3, :3] - np.eye(3)) < 0.05 and np.linalg.norm(E[:3, 3]) < 2.0
    rec = res.record()
    assert rec["groups"] == [[6, 7, 8]] and "T_a_b" in rec["pairs"][1]
    # computed once: cached on disk, keyed by the models (a changed model is fitted again)
    cached = list(lg.cache_dir().glob("*.json"))
    assert len(cached) >= 1
    lg._memo.clear()
    again = {(f.a, f.b): f for f in lg.resolve("auto", ds).pairs}
    assert np.allclose(again[(6, 8)].T_a_b, f.T_a_b) and again[(6, 8)].chamfer_mm == f.chamfer_mm
    # a candidate of 8 is matched with candidates of 6 through the alignment
    ids = sorted(ds.models_info())
    view, obj, T, six, _ = _four_views(mislabel=False)
    obj = obj.copy()
    T = T.copy()
    T[six[1]] = T[six[1]] @ invert(T_8_6)  # the pose of model 8 on object 6
    obj[six[1]] = 8
    table = match_stage.load_label_table(ds, ids, groups=res)
    r = match_group(view, table.index_of(obj), T, 4, table, MatchParams())
    assert (r.object_id[six] == r.object_id[six[0]]).all() and r.object_id[six[0]] >= 0
    table0 = match_stage.load_label_table(ds, ids, groups=lg.resolve("none", ds))
    r0 = match_group(view, table0.index_of(obj), T, 4, table0, MatchParams())
    assert r0.object_id[six[1]] == -1


def test_vote_only_members_are_not_measurements_in_refine(tables, tmp_path):
    """A member that only voted (groups.json ``vote_only_cand_ids``: its label's model is not in the
    object's frame) is left out of the object's bundle adjustment by cosy refine."""
    csv = _write_cands(tables, tmp_path)
    runner = CliRunner()
    m_out, r_out = tmp_path / "m", tmp_path / "r"
    r = runner.invoke(cli, ["match", "--dataset", str(tables), "--split", "test", "--candidates", str(csv),
                            "--out", str(m_out), "--label-groups", "6:7"])
    assert r.exit_code == 0, r.output
    doc = json.loads((m_out / "groups.json").read_text())
    # as if 6 and 7 were differently shaped: every member of the other label only votes
    vote_only = set()
    for g in doc["groups"]:
        for o in g["objects"]:
            if "votes" in o:
                o["vote_only_cand_ids"] = [c for c, lab in zip(o["cand_ids"], o["cand_obj_ids"]) if lab != o["obj_id"]]
                vote_only |= set(o["vote_only_cand_ids"])
    assert vote_only
    (m_out / "groups.json").write_text(json.dumps(doc))
    (m_out / "manifest.json").unlink()  # a hand-edited match folder is read as it is
    r = runner.invoke(cli, ["refine", "--dataset", str(tables), "--split", "test", "--matches", str(m_out),
                            "--out", str(r_out)])
    assert r.exit_code == 0, r.output
    used = {int(c) for g in json.loads((r_out / "scene.json").read_text())["groups"]
            for o in g["objects"] for c in o["cand_ids"]}
    assert used and not (used & vote_only)


def test_one_box_under_two_grouped_labels_is_one_candidate(tables):
    """The box classifier emits an unsure box under 6 and 7: the weaker copy is left out before
    matching (label groups on), so the two labels do not link two objects through one view; other
    labels, far-apart boxes and 'none' are untouched."""
    ds = BopDataset(tables, "test")
    diam = {o: float(i.diameter) for o, i in ds.models_info().items()}
    view, obj, T, six, _ = _four_views(mislabel=False)
    # every view's object 6 also emitted as 7 (same pose + 2 mm), scored lower except in view 1
    dup_T = T[six].copy()
    dup_T[:, :3, 3] += 2.0
    view2 = np.concatenate([view, view[six]])
    obj2 = np.concatenate([obj, np.full(len(six), 7)])
    T2 = np.concatenate([T, dup_T])
    score = np.full(len(view2), 0.8)
    score[len(view):] = 0.3
    score[len(view) + 1] = 0.9  # view 1: the 7 is the better-scored copy
    auto = lg.resolve("auto", ds)
    drop = lg.same_detection_duplicates(view2, obj2, T2, score, auto, diam)
    expected = np.zeros(len(view2), dtype=bool)
    expected[len(view) + np.array([0, 2, 3])] = True  # the weaker 7 copies
    expected[six[1]] = True  # view 1: the weaker 6
    assert np.array_equal(drop, expected)
    assert not lg.same_detection_duplicates(view2, obj2, T2, score, lg.resolve("none", ds), diam).any()
    far = T2.copy()
    far[len(view):, :3, 3] += 0.2 * max(diam[6], diam[7])  # another object, not the same box
    assert not lg.same_detection_duplicates(view2, obj2, far, score, auto, diam).any()
    # after leaving them out, the object is matched whole, voted 6 (3 views of 0.8 against 1 of 0.9)
    keep = ~drop
    table = match_stage.load_label_table(ds, sorted(ds.models_info()), groups=auto)
    r = match_group(view2[keep], table.index_of(obj2[keep]), T2[keep], 4, table, MatchParams())
    kept6 = np.flatnonzero(np.isin(np.flatnonzero(keep), np.concatenate([six, len(view) + np.arange(len(six))])))
    o = r.object_id[kept6]
    assert len(kept6) == 4 and (o == o[0]).all() and o[0] >= 0
    labels, _ = lg.vote_labels(r.object_id, obj2[keep], score[keep], r.cand_fit)
    assert labels[o[0]] == 6
