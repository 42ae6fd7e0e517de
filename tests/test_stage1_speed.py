"""Tests of the faster stage-1 paths (issue 18 item 5): the renderer's vertex-lit program and RGBA
read-back, atlas (tiled) renders against single renders, the verification score's gathered terms
against a plain per-hypothesis computation on whole crops, the windowed anti-alias blur of
``observe`` and the batched hull projection of ``poses_from_templates``.

Speed itself is measured by benchmarks/bench_stage1_speed.py (no timing assertions here)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cosy_cli.rendering import SceneRenderer  # before pyrender/OpenGL

from cosy_cli.geometry.camera import crop_affine  # noqa: E402
from cosy_cli.geometry.poses import make_pose  # noqa: E402
from cosy_cli.geometry.rotations import random_rotations, rotation_about_axis  # noqa: E402
from cosy_cli.objects.database import ObjectDatabase  # noqa: E402
from cosy_cli.singleview.training_free import templates as tp  # noqa: E402
from cosy_cli.singleview.training_free.verify import Verifier, VerifyConf, observe  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "data_samples" / "models"


@pytest.fixture(scope="module")
def painted():
    """Two sample parts with a two-colour vertex paint (ObjectDatabase, {obj_id: mesh})."""
    import trimesh

    db = ObjectDatabase.from_models_dir(SAMPLES, obj_ids=[2, 4])
    meshes = {}
    for o in db:
        mesh = o.mesh.copy()
        v = np.asarray(mesh.vertices)
        col = np.where((v[:, 0] > np.median(v[:, 0]))[:, None], [200, 60, 40, 255], [40, 90, 200, 255])
        mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=col.astype(np.uint8))
        o._mesh = mesh  # noqa: SLF001 (the test paints the parts)
        meshes[o.obj_id] = mesh
    return db, meshes


def crop_poses(db, n, seed=0):
    """n (obj_ids, T_cam_obj, K) of random views that fill a 64 x 64 crop about half."""
    rng = np.random.default_rng(seed)
    ids = np.array(db.obj_ids)[rng.integers(0, len(db.obj_ids), n)]
    R = random_rotations(n, rng)
    z = np.array([db[int(o)].diameter for o in ids]) * 8.0
    t = np.stack([rng.normal(0, 0.05, n) * z, rng.normal(0, 0.05, n) * z, z], -1)
    K = np.array([[300.0, 0, 31.5], [0, 300.0, 31.5], [0, 0, 1]])
    return ids, make_pose(R, t), K


def test_vertex_lit_rgba_render_matches_the_per_pixel_program(painted):
    db, meshes = painted
    ids, T, K = crop_poses(db, 12)
    Ks = np.repeat(K[None], len(ids), 0)
    with SceneRenderer(meshes, 64, 64) as rp, SceneRenderer(meshes, 64, 64, shading="vertex") as rv:
        a = rp.render_crops(Ks, ids, T, (64, 64))
        b = rv.render_crops(Ks, ids, T, (64, 64))
        c = rv.render_crops(Ks, ids, T, (64, 64), with_depth=False, with_instance=False)
        m = rp.render_crops(Ks, ids, T, (64, 64), with_rgb=False)  # no colours: the depth-only program
        sil = rp.render_silhouettes(K, ids, T, size=(64, 64))
        with pytest.raises(ValueError):
            rv.render_crops(Ks, ids, T, (64, 64), with_rgb=False, with_instance=False)
    assert a.mask.mean() > 0.1
    assert np.array_equal(a.instance, b.instance)
    assert np.abs(a.rgb.astype(int) - b.rgb.astype(int)).max() <= 1  # lit per vertex: flat faces, same colours
    np.testing.assert_allclose(a.depth, b.depth, atol=1e-3)
    assert m.rgb is None and np.array_equal(m.instance, a.instance) and np.array_equal(sil, a.mask)
    np.testing.assert_allclose(m.depth, a.depth, rtol=1e-6)
    # RGBA read-back: no instance map, the mask is the alpha, the colours are the same
    assert c.instance is None and c.depth is None and c.rgba.shape == (len(ids), 64, 64, 4)
    assert np.array_equal(c.mask, a.mask)
    assert np.array_equal(c.rgb, b.rgb)
    assert set(np.unique(c.rgba[..., 3])) <= {0, 255}
    with pytest.raises(ValueError):
        SceneRenderer(meshes, 64, 64, shading="phong")


def test_atlas_render_equals_single_renders(painted):
    """Many crops in one atlas (grouped by object and by camera, as verification draws them, so the
    renderer skips repeated state) against each crop rendered alone; also images left empty."""
    db, meshes = painted
    ids, T, K = crop_poses(db, 10, seed=1)
    ids = np.sort(ids)  # runs of one object
    Ks = np.repeat(K[None], len(ids), 0)
    Ks[5:, 0, 2] += 3.0  # a second camera for the second half
    with SceneRenderer(meshes, 64, 64, shading="vertex") as r:
        atlas = r.render_crops(Ks, ids, T, (64, 64), with_depth=False, with_instance=False)
        for i in range(len(ids)):
            one = r.render_crops(Ks[i:i + 1], ids[i:i + 1], T[i:i + 1], (64, 64), with_depth=False,
                                 with_instance=False)
            assert np.array_equal(atlas.rgba[i], one.rgba[0]), i
        # images 1 and 3 without instances; image 2 has two (occluding each other)
        tiles = np.array([0, 2, 2, 4])
        Kt = np.repeat(K[None], 5, 0)
        Kt[2, 1, 2] -= 2.0
        out = r.render_crops(Kt, ids[:4], T[:4], (64, 64), tiles=tiles)
        assert not out.mask[1].any() and not out.mask[3].any()
        for img, inst in ((0, [0]), (4, [3])):
            one = r.render_crops(Kt[img:img + 1], ids[inst], T[inst], (64, 64))
            assert np.array_equal(out.rgb[img], one.rgb[0]) and np.array_equal(out.instance[img] >= 0, one.mask[0])
            np.testing.assert_allclose(out.depth[img], one.depth[0], rtol=1e-5)  # float32 interpolation
        both = r.render(Kt[2], ids[1:3], T[1:3], size=(64, 64))
        assert np.array_equal(out.rgb[2], both.rgb)
        assert np.array_equal(np.where(out.instance[2] >= 0, out.instance[2] - 1, -1), both.instance)


def _reference_terms(v: Verifier, obs, det, ids, T):
    """The verification terms computed per hypothesis on whole crops (slow, plain)."""
    from cosy_cli.singleview.training_free.templates import orientation_bins

    c, S = v.conf, v.conf.crop
    Ks = np.stack([obs[d].K for d in det])
    out = v.renderer.render_crops(Ks, ids, T, (S, S), with_depth=False)
    terms = {k: np.zeros(len(T)) for k in ("orient", "colour", "region", "box")}
    for b in range(len(T)):
        o = obs[det[b]]
        m = out.instance[b] >= 0
        if not m.any():
            continue
        rgb = out.rgb[b].astype(np.float32) / np.float32(255)
        g = out.rgb[b].astype(np.float32).sum(-1) / np.float32(765)
        p = np.pad(m, 1)
        inner = m & p[:-2, 1:-1] & p[2:, 1:-1] & p[1:-1, :-2] & p[1:-1, 2:]
        gx, gy = np.zeros_like(g), np.zeros_like(g)
        gx[:, 1:-1], gy[1:-1] = g[:, 2:] - g[:, :-2], g[2:] - g[:-2]
        edges = (m & ~inner) | (inner & (gx * gx + gy * gy > np.float32(0.08 ** 2)))
        gm = g + np.float32(0.25) * m
        gxm, gym = np.zeros_like(g), np.zeros_like(g)
        gxm[:, 1:-1], gym[1:-1] = gm[:, 2:] - gm[:, :-2], gm[2:] - gm[:-2]
        ob = orientation_bins(np.arctan2(gym, gxm))
        ys, xs = np.nonzero(edges)
        terms["orient"][b] = o.resp[ob[ys, xs], ys, xs].mean()
        I, R = o.rgb[m].astype(np.float64), rgb[m].astype(np.float64)
        gain = np.clip((I * R).sum() / max((R * R).sum(), 1e-9), 0.3, 3.0)
        terms["colour"][b] = np.maximum(0.0, 1.0 - np.linalg.norm(I - gain * R, axis=-1) / c.colour_tol).mean()
        inside, outside = m & o.in_box, ~m & o.in_box
        pin = o.not_bg[inside].mean() if inside.any() else 0.0
        pout = o.not_bg[outside].mean() if outside.any() else 0.0
        terms["region"][b] = np.clip(0.5 + 0.5 * (pin - pout), 0, 1)
        ys, xs = np.nonzero(m)
        x1, x2, y1, y2 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
        bx = o.box_crop
        iw = max(min(x2, bx[2]) - max(x1, bx[0]), 0)
        ih = max(min(y2, bx[3]) - max(y1, bx[1]), 0)
        barea = (bx[2] - bx[0]) * (bx[3] - bx[1])
        terms["box"][b] = iw * ih / barea * min(1.0, barea / ((x2 - x1) * (y2 - y1))) ** c.box_excess
    return terms


def test_gathered_score_terms_equal_whole_crop_terms(painted):
    db, meshes = painted
    W, H = 320, 240
    K = np.array([[400.0, 0, 159.5], [0, 400.0, 119.5], [0, 0, 1]])
    rng = np.random.default_rng(3)
    Tg = [make_pose(rotation_about_axis(rng.normal(size=3), [0.8])[0], np.array([-40.0, 5.0, 700.0])),
          make_pose(rotation_about_axis(rng.normal(size=3), [1.3])[0], np.array([45.0, -10.0, 650.0]))]
    bg = (rng.integers(0, 255, (H // 8, W // 8, 3)).repeat(8, 0).repeat(8, 1)).astype(np.uint8)
    with SceneRenderer(meshes, W, H) as r:
        img = r.render(K, [2, 4], np.stack(Tg), background=bg)
    boxes = []
    for i in range(2):
        ys, xs = np.nonzero(img.instance == i)
        boxes.append([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1])
    conf = VerifyConf(max_faces=100_000, rank_faces=0, refine_faces=0)  # the meshes as they are
    obs = [observe(img.rgb, K, np.asarray(b, float), conf) for b in boxes]
    # hypotheses near the true poses and far off, several per detection, one empty (out of view)
    det = np.repeat([0, 1], 7)
    ids = np.array([2, 4])[det]
    T = np.stack([Tg[d] for d in det])
    for i in range(len(T)):
        T[i, :3, :3] = rotation_about_axis(rng.normal(size=3), [0.05 * i])[0] @ T[i, :3, :3]
    T[3, :3, 3] = [0.0, 0.0, -500.0]  # behind the camera: nothing drawn
    with Verifier(db, conf) as v:
        total, got = v.score(obs, det, ids, T, terms=True)
        ref = _reference_terms(v, obs, det, ids, T)
    drawn = np.arange(len(T)) != 3
    assert total[3] == 0.0 and np.all(total[drawn] > 0)
    for k in ref:
        np.testing.assert_allclose(got[k][drawn], ref[k][drawn], atol=2e-5, err_msg=k)
    assert ref["orient"][drawn].std() > 0.01 and ref["colour"][drawn].std() > 0.01  # the poses differ


def test_observe_blurs_only_the_window_with_the_same_pixels():
    """A small box in a big image is shrunk with an anti-alias blur of the window only: the crop
    equals the one from blurring the whole image, also for windows past the image border."""
    import cv2

    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (480, 640, 3)).astype(np.uint8)
    rgb = cv2.resize(cv2.resize(rgb, (160, 120)), (640, 480))  # some structure at several scales
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    conf = VerifyConf()
    for box in ([200.0, 150, 420, 330], [-60, -30, 180, 200], [500, 380, 700, 520], [0, 0, 640, 480]):
        o = observe(rgb, K, np.array(box, float), conf)
        side = o.window[2] - o.window[0]
        scale = conf.crop / side
        assert scale < 0.7
        full = cv2.GaussianBlur(rgb, (0, 0), 0.5 / scale)
        want = cv2.warpAffine(full, crop_affine(o.window, (conf.crop, conf.crop)), (conf.crop, conf.crop),
                              flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        assert np.array_equal((o.rgb * 255).round().astype(np.uint8), want), box


def test_template_poses_batched_like_one_by_one():
    """poses_from_templates projects every pose's hull in one product: the same poses as placing the
    templates one at a time, for any shape of index / boxes, and the projected hull fits the box."""
    db = ObjectDatabase.from_models_dir(SAMPLES, obj_ids=[4])
    with SceneRenderer({4: db[4].mesh}, 128, 96) as r:
        t = tp.build_object_templates(r, db[4], tp.resolve_conf("default", viewpoints=20, inplane=4))
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    idx = np.arange(12).reshape(3, 4) % t.n_templates
    boxes = np.array([100.0, 120, 180, 190]) + np.arange(12).reshape(3, 4, 1) * 7.0
    T = tp.poses_from_templates(t, idx, K, boxes, refine=3)
    assert T.shape == (3, 4, 4, 4)
    for i in range(3):
        for j in range(4):
            one = tp.poses_from_templates(t, idx[i, j:j + 1], K, boxes[i, j:j + 1], refine=3)[0]
            np.testing.assert_allclose(T[i, j], one, atol=1e-9)
    # after the distance corrections the less shrunk side of the projected hull matches the box (depth_from "max")
    hull = t.hull.astype(np.float64)
    cam = hull @ np.swapaxes(T[..., :3, :3], -1, -2) + T[..., None, :3, 3]
    uv = cam[..., :2] / cam[..., 2:] * np.array([K[0, 0], K[1, 1]])
    size = uv.max(-2) - uv.min(-2)
    obs = np.stack([boxes[..., 2] - boxes[..., 0], boxes[..., 3] - boxes[..., 1]], -1)
    np.testing.assert_allclose((size / obs).min(-1), 1.0, atol=0.01)
    single = tp.poses_from_templates(t, np.array(3), K, boxes[0, 0], refine=2)
    assert single.shape == (4, 4)
