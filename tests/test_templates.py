"""Tests of cosy_cli.singleview.training_free.templates: viewpoints and symmetry dedupe, descriptors against
re-renders, retrieval on renders at random poses, the stage's manifest/skip/rebuild logic, the CLI."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from cosy_cli.rendering import SceneRenderer  # before pyrender/OpenGL

from cosy_cli.errors import CosyError  # noqa: E402
from cosy_cli.geometry.poses import make_pose  # noqa: E402
from cosy_cli.geometry.rotations import random_rotations, rotation_about_axis  # noqa: E402
from cosy_cli.objects.database import ObjectDatabase  # noqa: E402
from cosy_cli.singleview.training_free import templates as tp  # noqa: E402

DATA = Path(__file__).resolve().parents[1] / "data_samples"
MODELS = DATA / "models"
ASYM, BOX, CYL, HEX = 4, 1, 3, 8  # L-bracket (no symmetry), box (3 flips), stepped cylinder (z), hex nut (11)


def camera_K() -> tuple[np.ndarray, int, int]:
    c = json.loads((DATA / "camera.json").read_text())
    return np.array([[c["fx"], 0, c["cx"]], [0, c["fy"], c["cy"]], [0, 0, 1.0]]), c["width"], c["height"]


def rot_err_sym(R_est: np.ndarray, R_gt: np.ndarray, symmetries: np.ndarray) -> float:
    """Smallest angle (deg) between R_est and R_gt S over the symmetries S."""
    dR = R_est.T @ (R_gt @ symmetries[:, :3, :3])
    return float(np.degrees(np.arccos(np.clip((np.trace(dR, axis1=-2, axis2=-1) - 1) / 2, -1, 1))).min())


@pytest.fixture(scope="module")
def db():
    return ObjectDatabase.from_models_dir(MODELS, obj_ids=[ASYM, BOX, CYL, HEX])


@pytest.fixture(scope="module")
def templates(db):
    """300 viewpoints x 36 in-plane (10 deg): enough for 15 deg retrieval, quick to build."""
    return tp.build_templates(db, {"viewpoints": 300, "inplane": 36}, obj_ids=[ASYM, BOX, CYL], progress=False)


# ---------------------------------------------------------------------------------------- viewpoints
def test_fibonacci_sphere_is_even():
    d = tp.fibonacci_sphere(500)
    assert np.allclose(np.linalg.norm(d, axis=1), 1)
    assert np.abs(d.mean(0)).max() < 0.01
    cos = d @ d.T
    np.fill_diagonal(cos, -1)
    nearest = np.degrees(np.arccos(cos.max(1)))
    spacing = np.degrees(tp.sphere_spacing(500))
    assert 0.6 * spacing < nearest.min() and nearest.max() < 1.2 * spacing


def test_symmetry_dedupe_covers_every_orbit(db):
    n = 600
    d = tp.fibonacci_sphere(n)
    spacing = tp.sphere_spacing(n)
    assert len(tp.dedupe_viewpoints(d, np.eye(4)[None], 0.5 * spacing)) == n  # no symmetry: all kept
    flip = np.stack([np.eye(3), rotation_about_axis([0, 0, 1], [np.pi])[0]])
    cont = rotation_about_axis([0, 0, 1], 2 * np.pi * np.arange(64) / 64)
    n_kept = {}
    for name, S, f in (("flip", flip, 0.7), ("box", db[BOX].symmetries, 0.5), ("continuous", cont, 0.5)):
        thr = f * spacing
        keep = tp.dedupe_viewpoints(d, S, thr)
        n_kept[name] = len(keep)
        R = np.asarray(S)[:, :3, :3]
        # every viewpoint has a kept one within the threshold of its orbit (none of its views is lost)
        orbit = np.einsum("sij,nj->nsi", R, d)
        best = np.arccos(np.clip((orbit @ d[keep].T).max(axis=(1, 2)), -1, 1))
        assert best.max() <= thr + 1e-9
        # kept viewpoints are not equivalent to each other
        c = np.einsum("nsi,mi->nsm", orbit[keep], d[keep]).max(1)
        np.fill_diagonal(c, -1)
        assert c.max() < np.cos(thr)
    assert n / 2 <= n_kept["flip"] < 0.55 * n
    assert n / 4 <= n_kept["box"] < 0.45 * n
    # about z: one kept viewpoint per latitude band of the threshold's width (a meridian)
    assert n_kept["continuous"] <= 1.2 * np.pi / (0.5 * spacing)


def test_symmetric_objects_get_fewer_templates(db, templates):
    assert templates[ASYM].n_viewpoints == 300
    assert templates[BOX].n_viewpoints < 0.7 * 300  # 4 symmetries
    cyl = templates[CYL]
    assert cyl.n_viewpoints < 30  # continuous about z: a meridian
    polar = np.degrees(np.arccos(cyl.directions[:, 2]))
    assert np.all(np.diff(np.sort(polar)) > 0.5 * np.degrees(0.5 * tp.sphere_spacing(300)))
    assert templates[CYL].n_templates == cyl.n_viewpoints * 36


# ---------------------------------------------------------------------------------------- descriptors
def test_features_lie_on_edges_of_the_rerendered_template(db, templates):
    """A template's stored pose (in-plane rotation composed), re-rendered, has strong gradients of
    the stored orientation at its features, and its silhouette box is the stored box."""
    t = templates[ASYM]
    rng = np.random.default_rng(1)
    idx = rng.choice(t.n_templates, 8, replace=False)
    assert len(set(t.inplane[idx].tolist())) > 3  # rotated ones, not only the rendered in-plane angle
    with SceneRenderer({ASYM: db[ASYM].mesh}, *t.crop) as ren:
        out = ren.render_crops(np.broadcast_to(t.K, (8, 3, 3)), [ASYM] * 8, t.T_cam_obj(idx), t.crop,
                               colors=np.full((8, 3), tp.GREY))
    gx, gy = tp.sobel(out.rgb.astype(np.float32).mean(-1))
    mag = np.hypot(gx, gy)
    bins = tp.orientation_bins(np.arctan2(gy, gx))
    strong = mag >= 0.5 * tp.resolve_conf()["min_gradient"]
    px = np.rint(t.feature_pixels(idx)).astype(int)  # (8, F, 2)
    H, W = mag.shape[1:]
    on_edge, same_bin = [], []
    for j in range(8):
        for (x, y), b in zip(px[j], t.bins[idx[j]]):
            # the 3 x 3 neighbourhood (the matching spreads orientations over it too)
            ys, xs = np.meshgrid(np.clip(np.arange(y - 1, y + 2), 0, H - 1), np.clip(np.arange(x - 1, x + 2), 0, W - 1),
                                 indexing="ij")
            s = strong[j, ys, xs]
            on_edge.append(s.any())
            d = np.abs(bins[j, ys, xs][s].astype(int) - int(b))
            same_bin.append(s.any() and np.minimum(d, tp.N_BINS - d).min() <= 1)
        ys, xs = np.nonzero(out.instance[j] >= 0)
        box = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], float)
        p0 = np.array([(t.crop[0] - 1) / 2 + 0.5, (t.crop[1] - 1) / 2 + 0.5])
        lo = p0 - t.origin[idx[j]] * t.box_size[idx[j]]
        np.testing.assert_allclose(box, np.r_[lo, lo + t.box_size[idx[j]]], atol=1.5)
    assert np.mean(on_edge) > 0.95, np.mean(on_edge)
    assert np.mean(same_bin) > 0.95, np.mean(same_bin)
    # features are spread: nearest-neighbour distance of a template's features (px)
    f = t.feature_pixels(idx[0])
    dd = np.linalg.norm(f[:, None] - f[None], axis=-1) + np.eye(len(f)) * 1e9
    assert np.median(dd.min(1)) > 3


# ---------------------------------------------------------------------------------------- retrieval
def test_retrieval_on_renders_at_random_poses(db, templates):
    """Renders of the object (own colours, random light and background) at random poses in a real
    image size: the top-1 rotation is within 15 deg (min over symmetries) for most, the depth within a few %."""
    K, W, H = camera_K()
    rng = np.random.default_rng(0)
    n = 8
    R = random_rotations(n, rng)
    z = rng.uniform(450, 750, n)
    uv = rng.uniform([120, 100], [W - 120, H - 100], (n, 2))
    t_gt = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0] * z, (uv[:, 1] - K[1, 2]) / K[1, 1] * z, z], 1)
    T_gt = make_pose(R, t_gt)
    errs, dz, scores = [], [], []
    with SceneRenderer({ASYM: db[ASYM].mesh}, W, H) as ren:
        for i in range(n):
            bg = np.full((H, W, 3), rng.integers(60, 200, 3), np.uint8)
            out = ren.render(K, [ASYM], T_gt[i:i + 1], background=bg,
                             light_dir=rng.normal(size=3) * [1, 1, 0.3] + [0, 0, 1])
            ys, xs = np.nonzero(out.instance >= 0)
            box = np.array([[xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]], float)
            h = tp.match_templates(templates, out.rgb, K, box, [ASYM], top_k=5)
            assert h.T_cam_obj.shape == (1, 5, 4, 4) and h.scores.shape == (1, 5) and h.template_index.shape == (1, 5)
            assert np.all(np.diff(h.scores[0]) <= 0) and h.scores[0, 0] <= 1
            errs.append(rot_err_sym(h.T_cam_obj[0, 0, :3, :3], R[i], db[ASYM].symmetries))
            dz.append(h.T_cam_obj[0, 0, 2, 3] / z[i] - 1)
            scores.append(h.scores[0, 0])
    errs, dz = np.array(errs), np.array(dz)
    assert np.mean(errs < 15) >= 0.75, errs
    assert np.median(errs) < 10, errs
    good = errs < 15
    assert np.median(np.abs(dz[good])) < 0.03, dz
    assert np.median(scores) > 0.7


def test_pose_from_template_puts_the_object_on_its_ray():
    """The template's on-axis pose placed off-axis: the origin projects where the normalised box
    position says, the rotation is R_ray R_template, the distance follows the box size."""
    R_t = rotation_about_axis([1, 0, 0], [0.3])[0].astype(np.float32).astype(np.float64)  # as stored
    t = tp.ObjectTemplates(
        obj_id=1, R=R_t[None].astype(np.float32), xy=np.zeros((1, 4, 2), np.float16), bins=np.zeros((1, 4), np.uint8),
        origin=np.array([[0.25, 0.5]], np.float32), box_size=np.array([[40.0, 20.0]], np.float32),
        depth_offset=np.zeros(1, np.float32), viewpoint=np.zeros(1, np.int32), inplane=np.zeros(1, np.int32),
        directions=np.zeros((1, 3), np.float32), hull=np.zeros((0, 3), np.float32), render_distance=500.0,
        focal=400.0, crop=(128, 96), n_inplane=1)
    K = np.array([[800.0, 0, 320], [0, 800.0, 240], [0, 0, 1]])
    box = np.array([400.0, 100.0, 480.0, 140.0])  # twice the template's size at twice its focal: same distance
    T = tp.poses_from_templates(t, np.array([0]), K, box[None], depth_from="max", refine=0)[0]
    uv = K @ T[:3, 3]
    np.testing.assert_allclose(uv[:2] / uv[2], [400 + 0.25 * 80 - 0.5, 100 + 0.5 * 40 - 0.5], atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(T[:3, 3]), 500.0)
    ray = T[:3, 3] / np.linalg.norm(T[:3, 3])
    R_ray = T[:3, :3] @ R_t.T
    np.testing.assert_allclose(R_ray @ [0, 0, 1], ray, atol=1e-12)
    np.testing.assert_allclose(R_ray.T @ R_ray, np.eye(3), atol=1e-12)
    assert abs(np.degrees(np.arccos((np.trace(R_ray) - 1) / 2)) - np.degrees(np.arccos(ray[2]))) < 1e-4  # smallest
    # an occluded side (half the height) does not move the distance with depth_from="max"
    T2 = tp.poses_from_templates(t, np.array([0]), K, np.array([[400.0, 100.0, 480.0, 120.0]]), refine=0)[0]
    assert abs(np.linalg.norm(T2[:3, 3]) - 500.0) < 1e-9


def test_response_maps_follow_the_box_and_the_image_metric():
    """A diagonal edge (45 deg) seen through a box twice as wide as high: cells on the edge respond
    to the 45 deg orientation (bin 2 in the image's metric, not the crop's), at the right place."""
    H, W = 240, 320
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    img = np.where((xx - 100) + (yy - 60) > 60, 200, 40).astype(np.uint8)  # edge along x + y = 220
    rgb = np.repeat(img[..., None], 3, -1)
    box = np.array([100.0, 60.0, 220.0, 120.0])  # 120 x 60 px
    p = tp.MatchParams(spread=0)
    r = tp.response_maps(rgb, box, p)
    S = p.grid + 2 * p.pad
    assert r.shape == (tp.N_BINS, S, S) and r.dtype == np.uint8
    # cell centres -> image: x = x1 + (c + 0.5 - pad) * w / grid
    c = np.arange(S) + 0.5 - p.pad
    X = box[0] + c[None, :] * 120 / p.grid
    Y = box[1] + c[:, None] * 60 / p.grid
    on = np.abs((X - 100) + (Y - 60) - 60) < 1.0
    off = np.abs((X - 100) + (Y - 60) - 60) > 6.0  # beyond the Sobel and interpolation reach
    assert r[2][on].mean() > 250  # gradient direction (1, 1): 45 deg, bin 2
    assert np.all(r[:, off] == 0)
    assert np.mean(np.argmax(r[:, on], 0) == 2) > 0.95
    assert r[6][on].mean() < 10  # the perpendicular orientation hardly responds


def test_response_maps_with_a_mask_keep_its_band_and_its_outline():
    """With a detection mask and mask_band > 0: an image edge far from the mask no longer responds
    (clutter), and the mask's own outline responds even where the image shows no edge (an object
    the colour of its background); without the mask, or with mask_band 0, the maps are as before."""
    H, W = 240, 320
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    img = np.where(xx > 200, 200, 60).astype(np.uint8)  # a vertical image edge at x = 200 (clutter)
    rgb = np.repeat(img[..., None], 3, -1)
    mask = (xx - 120) ** 2 + (yy - 120) ** 2 < 40 ** 2  # a disc on a flat region: no image edge there
    box = np.array([70.0, 70.0, 230.0, 170.0])
    plain = tp.response_maps(rgb, box, tp.MatchParams(spread=0))
    np.testing.assert_array_equal(tp.response_maps(rgb, box, tp.MatchParams(spread=0), mask), plain)  # band 0: off
    masked = tp.response_maps(rgb, box, tp.MatchParams(spread=0, mask_band=3), mask)
    p = tp.MatchParams()
    c = np.arange(p.grid + 2 * p.pad) + 0.5 - p.pad
    X, Y = np.meshgrid(box[0] + c * 160 / p.grid, box[1] + c * 100 / p.grid)
    edge = np.abs(X - 200) < 1.5
    rim = np.abs(np.hypot(X - 120, Y - 120) - 40) < 1.0
    assert plain.max(0)[edge].mean() > 250 and plain.max(0)[rim].mean() < 5
    assert masked.max(0)[edge].mean() < 5 and masked.max(0)[rim].mean() > 200
    no_outline = tp.response_maps(rgb, box, tp.MatchParams(spread=0, mask_band=3, mask_outline=False), mask)
    assert no_outline.max(0)[rim].mean() < 5 and no_outline.max(0)[edge].mean() < 5


def test_template_set_round_trip(tmp_path, db):
    ts = tp.build_templates(db, SMALL, obj_ids=[HEX], progress=False)
    ts.save(tmp_path / "t")
    back = tp.TemplateSet.load(tmp_path / "t")
    a, b = ts[HEX], back[HEX]
    for k in tp.ObjectTemplates._ARRAYS:
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
        assert getattr(a, k).dtype == getattr(b, k).dtype
    assert (b.render_distance, b.focal, b.crop, b.n_inplane, b.model_sha1) == \
        (a.render_distance, a.focal, a.crop, a.n_inplane, a.model_sha1)
    assert back.conf == json.loads(json.dumps(ts.conf))


def test_match_rejects_unknown_objects(templates):
    K, W, H = camera_K()
    with pytest.raises(CosyError, match="no templates for object 99"):
        tp.match_templates(templates, np.zeros((H, W, 3), np.uint8), K, np.array([[10, 10, 50, 60.0]]), [99])
    h = tp.match_templates(templates, np.zeros((H, W, 3), np.uint8), K, np.zeros((0, 4)), [])
    assert h.T_cam_obj.shape == (0, 5, 4, 4)


# ---------------------------------------------------------------------------------------- the stage
SMALL = {"viewpoints": 24, "inplane": 4, "crop": (64, 48), "features": 16}


def small_models(tmp_path: Path, ids=(BOX, HEX)) -> Path:
    d = tmp_path / "models"
    d.mkdir()
    info = json.loads((MODELS / "models_info.json").read_text())
    (d / "models_info.json").write_text(json.dumps({str(i): info[str(i)] for i in ids}))
    for i in ids:
        shutil.copy(MODELS / f"obj_{i:06d}.ply", d / f"obj_{i:06d}.ply")
    return d


def test_stage_builds_skips_rebuilds_changed_objects(tmp_path):
    import trimesh

    models = small_models(tmp_path)
    out = tmp_path / "templates"
    logs = []
    tp.main(SMALL, models, out, log=logs.append, progress=False)
    man = json.loads((out / "manifest.json").read_text())
    assert man["complete"] and set(man["objects"]) == {str(BOX), str(HEX)}
    assert man["conf"]["viewpoints"] == 24 and len(man["models_info_sha1"]) == 40
    ts = tp.TemplateSet.load(out)
    assert ts.obj_ids == [BOX, HEX] and ts[HEX].n_templates == ts[HEX].n_viewpoints * 4
    assert ts[BOX].xy.shape[1:] == (16, 2)
    mtimes = {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")}

    logs.clear()
    tp.main(SMALL, models, out, log=logs.append, progress=False)  # up to date: nothing written
    assert any("up to date" in m for m in logs)
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")} == mtimes

    mesh = trimesh.load(models / f"obj_{HEX:06d}.ply", process=False)  # the model changes
    mesh.vertices *= 1.2
    mesh.export(models / f"obj_{HEX:06d}.ply")
    logs.clear()
    tp.main(SMALL, models, out, log=logs.append, progress=False)
    assert any(f"rebuilding object(s) {HEX}" in m for m in logs)
    now = {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")}
    assert now[f"obj_{BOX:06d}.npz"] == mtimes[f"obj_{BOX:06d}.npz"]
    assert now[f"obj_{HEX:06d}.npz"] != mtimes[f"obj_{HEX:06d}.npz"]
    ts2 = tp.TemplateSet.load(out)
    assert ts2[HEX].render_distance == pytest.approx(1.2 * ts[HEX].render_distance, rel=1e-4)

    with pytest.raises(CosyError, match="other settings.*inplane"):  # other settings: refused...
        tp.main({**SMALL, "inplane": 6}, models, out, progress=False, log=logs.append)
    tp.main({**SMALL, "inplane": 6}, models, out, overwrite=True, progress=False, log=logs.append)  # ...or rebuilt
    assert tp.TemplateSet.load(out)[BOX].n_inplane == 6

    info = json.loads((models / "models_info.json").read_text())  # an object leaves the models
    del info[str(HEX)]
    (models / "models_info.json").write_text(json.dumps(info))
    tp.main({**SMALL, "inplane": 6}, models, out, progress=False, log=logs.append)
    assert tp.TemplateSet.load(out).obj_ids == [BOX] and not (out / f"obj_{HEX:06d}.npz").exists()


def test_stage_resumes_an_interrupted_build_and_refuses_foreign_folders(tmp_path):
    models = small_models(tmp_path)
    out = tmp_path / "templates"
    tp.main(SMALL, models, out, progress=False, log=lambda *a: None)
    man = json.loads((out / "manifest.json").read_text())
    del man["objects"][str(HEX)]  # as if interrupted after the first object
    man["complete"] = False
    (out / "manifest.json").write_text(json.dumps(man))
    (out / f"obj_{HEX:06d}.npz").unlink()
    with pytest.raises(CosyError, match="incomplete"):
        tp.TemplateSet.load(out)
    mtime = (out / f"obj_{BOX:06d}.npz").stat().st_mtime_ns
    tp.main(SMALL, models, out, progress=False, log=lambda *a: None)
    assert tp.TemplateSet.load(out).obj_ids == [BOX, HEX]
    assert (out / f"obj_{BOX:06d}.npz").stat().st_mtime_ns == mtime
    assert not list(out.glob(".*tmp*"))  # no temporary files left

    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(CosyError, match="not a templates folder"):
        tp.main(SMALL, models, foreign, progress=False, log=lambda *a: None)
    with pytest.raises(CosyError, match="no manifest.json"):
        tp.TemplateSet.load(foreign)


def test_conf_checks():
    assert tp.resolve_conf(None, crop="160x120")["crop"] == (160, 120)
    with pytest.raises(CosyError, match="unknown templates setting"):
        tp.resolve_conf({"viewpoint": 3})
    with pytest.raises(CosyError, match="fill"):
        tp.resolve_conf(None, fill=1.5)
    with pytest.raises(CosyError, match="unknown templates configuration"):
        tp.resolve_conf("nope")


# ---------------------------------------------------------------------------------------- CLI
def test_cli_builds_and_reports_bad_models(tmp_path):
    from click.testing import CliRunner

    from cosy_cli.cli.main import cli

    models = small_models(tmp_path, ids=(HEX,))
    out = tmp_path / "tpl"
    args = ["templates", "--models", str(models), "--out", str(out), "--viewpoints", "24", "--inplane", "4",
            "--crop", "64x48", "--features", "16"]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    assert (out / "manifest.json").is_file() and (out / f"obj_{HEX:06d}.npz").is_file()
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0 and "up to date" in r.output
    r = CliRunner().invoke(cli, ["templates", "--models", str(tmp_path / "nope"), "--out", str(tmp_path / "x")])
    assert r.exit_code == 2
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and "models folder not found" in lines[0]
    (models / "models_info.json").write_text("{")
    r = CliRunner().invoke(cli, ["templates", "--models", str(models), "--out", str(tmp_path / "y")])
    assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1 and "models_info.json" in r.output
    r = CliRunner().invoke(cli, args[:5] + ["--crop", "64"])
    assert r.exit_code == 2 and "WIDTHxHEIGHT" in r.output


def test_hypotheses_at_other_distances_keep_their_projected_centre():
    """at_distances: each hypothesis slides along its line of sight (t x factor): the projection of
    the object's origin stays, its image size scales by 1 / factor, scores and indices follow."""
    from cosy_cli.singleview.training_free.templates import TemplateHypotheses, at_distances

    rng = np.random.default_rng(0)
    T = np.tile(np.eye(4), (2, 3, 1, 1))
    T[..., :3, 3] = rng.uniform([-100, -100, 500], [100, 100, 900], (2, 3, 3))
    h = TemplateHypotheses(T, rng.uniform(0, 1, (2, 3)), np.arange(6).reshape(2, 3))
    v = at_distances(h, [0.87, 1.0, 1.15])
    assert v.T_cam_obj.shape == (2, 9, 4, 4) and v.scores.shape == (2, 9)
    np.testing.assert_allclose(v.T_cam_obj[:, 1::3], T)  # factor 1: the hypotheses as they were
    np.testing.assert_allclose(v.T_cam_obj[:, 0::3, 2, 3], 0.87 * T[..., 2, 3])
    t = v.T_cam_obj[..., :3, 3]
    proj = t[..., :2] / t[..., 2:]
    np.testing.assert_allclose(proj, np.repeat(T[..., :2, 3] / T[..., 2:3, 3], 3, 1))
    np.testing.assert_allclose(v.T_cam_obj[..., :3, :3], np.repeat(T[..., :3, :3], 3, 1))
    assert (v.template_index[:, :3] == h.template_index[:, :1]).all() and (v.scores[:, 3:6] == h.scores[:, 1:2]).all()


def test_interleave_takes_hypotheses_in_turn_without_repeats():
    def hyp(idx):
        idx = np.asarray(idx)
        T = np.tile(np.eye(4), idx.shape + (1, 1))
        T[..., 0, 3] = idx
        return tp.TemplateHypotheses(T, idx / 100.0, idx)

    a, b = hyp([[1, 2, 3, 4]]), hyp([[9, 2, 8, -1]])
    h = tp.interleave(a, b, 5)
    assert h.template_index.tolist() == [[1, 9, 2, 3, 8]]  # a, b, a, (b's 2 taken), a, b
    np.testing.assert_allclose(h.T_cam_obj[0, :, 0, 3], [1, 9, 2, 3, 8])
    np.testing.assert_allclose(h.scores[0], [0.01, 0.09, 0.02, 0.03, 0.08])
    short = tp.interleave(hyp([[1]]), hyp([[1]]), 3)  # fewer distinct templates than asked: -1 / NaN after
    assert short.template_index.tolist() == [[1, -1, -1]] and np.isnan(short.scores[0, 1:]).all()
