"""Tests of cosy_cli.rendering: camera convention, exact depth, occlusion, crops, colours."""

from __future__ import annotations

import os

import numpy as np
import pytest

from cosy_cli.rendering import SceneRenderer, patch_pyrender, projection_matrix  # before pyrender/OpenGL

import cv2  # noqa: E402
import trimesh  # noqa: E402

from cosy_cli.geometry import (  # noqa: E402
    backproject_depth, crop_affine, crop_intrinsics, fit_box_to_aspect, invert, look_at, make_pose, project,
    rotation_about_axis, transform_points,
)

W, H = 160, 120
# off-centre principal point, fx != fy
K = np.array([[180.0, 0.0, 70.3], [0.0, 170.0, 52.8], [0.0, 0.0, 1.0]])

ASYM, PLANE, CUBE, QUAD, TEXQUAD = 1, 2, 3, 4, 5


def asymmetric_mesh() -> trimesh.Trimesh:
    """An L-shaped block with a peg: no symmetry (mm)."""
    base = trimesh.creation.box((80, 50, 30))
    arm = trimesh.creation.box((20, 50, 40))
    arm.apply_translation([30, 0, 35])
    peg = trimesh.creation.cylinder(radius=6, height=30, sections=24)
    peg.apply_transform(make_pose(rotation_about_axis([1, 0, 0], [np.pi / 2])[0], [-25, 35, 0]))
    return trimesh.util.concatenate([base, arm, peg])


def rot(axis, deg):
    return rotation_about_axis(axis, [np.deg2rad(deg)])[0]


@pytest.fixture(scope="module")
def meshes():
    cube = trimesh.creation.box((50, 50, 50))
    cube.visual.vertex_colors = np.tile([30, 200, 40, 255], (len(cube.vertices), 1)).astype(np.uint8)
    quad = trimesh.Trimesh([[-40, -40, 0], [40, -40, 0], [40, 40, 0], [-40, 40, 0]], [[0, 1, 2], [0, 2, 3]],
                           process=False)
    # texture: red top-left quadrant, blue top-right, green bottom half (image rows top first)
    img = np.zeros((64, 64, 3), np.uint8)
    img[:32, :32] = [255, 0, 0]
    img[:32, 32:] = [0, 0, 255]
    img[32:] = [0, 255, 0]
    from PIL import Image

    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)  # uv (0,0) = image bottom-left
    texquad = trimesh.Trimesh(quad.vertices.copy(), quad.faces.copy(), process=False,
                              visual=trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(img)))
    return {ASYM: asymmetric_mesh(), PLANE: trimesh.creation.box((1000, 1000, 10)), CUBE: cube, QUAD: quad,
            TEXQUAD: texquad}


@pytest.fixture(scope="module")
def renderer(meshes):
    r = SceneRenderer(meshes, W, H)
    yield r
    r.close()


def pose(R=np.eye(3), t=(0, 0, 500)):
    return make_pose(np.asarray(R, float), np.asarray(t, float))


# ---------------------------------------------------------------- camera convention


def test_projection_matrix_matches_opencv_projection():
    rng = np.random.default_rng(0)
    pts = rng.uniform([-300, -200, 50], [300, 200, 3000], (100, 3))
    P = projection_matrix(K, W, H, 10.0, 10_000.0)
    clip = np.c_[pts, np.ones(len(pts))] @ P.T
    ndc = clip[:, :3] / clip[:, 3:]
    window = (ndc[:, :2] + 1) / 2 * [W, H]  # window coordinates, row 0 = image row 0
    np.testing.assert_allclose(window - 0.5, project(pts, K), atol=1e-9)
    # depth range: znear -> -1, zfar -> +1
    for z, want in ((10.0, -1.0), (10_000.0, 1.0)):
        c = P @ [0, 0, z, 1]
        assert c[2] / c[3] == pytest.approx(want)


def test_silhouette_matches_projected_model(renderer, meshes):
    T = pose(rot([0.3, 1, 0.2], 40) @ rot([1, 0, 0], 25), (12, -8, 450))
    mask = renderer.render_silhouettes(K, [ASYM], T[None])[0]
    assert mask.any() and not mask[0].any() and not mask[-1].any()  # fully in view
    uv = project(transform_points(T, meshes[ASYM].vertices), K)
    # every vertex projects into the silhouette (a vertex on the outline may be up to half a pixel out)
    dilated = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    px = np.round(uv).astype(int)
    assert dilated[px[:, 1], px[:, 0]].all()
    # surface points well inside faces as well
    surf, _ = trimesh.sample.sample_surface(meshes[ASYM], 3000, seed=0)
    px = np.round(project(transform_points(T, surf), K)).astype(int)
    assert dilated[px[:, 1], px[:, 0]].all()
    ys, xs = np.nonzero(mask)
    # covered pixel centres lie inside the projected bounding box (exactly), and the mask's box
    # (pixel i spans [i - 0.5, i + 0.5]) matches it within a pixel
    assert xs.min() >= uv[:, 0].min() and xs.max() <= uv[:, 0].max()
    assert ys.min() >= uv[:, 1].min() and ys.max() <= uv[:, 1].max()
    np.testing.assert_allclose([xs.min() - 0.5, ys.min() - 0.5], uv.min(0), atol=1.0)
    np.testing.assert_allclose([xs.max() + 0.5, ys.max() + 0.5], uv.max(0), atol=1.0)

    def centroid(T):
        ys, xs = np.nonzero(renderer.render_silhouettes(K, [ASYM], T[None])[0])
        return np.array([xs.mean(), ys.mean()])

    c0 = centroid(T)
    cx = centroid(pose(T[:3, :3], T[:3, 3] + [15, 0, 0]))
    cy = centroid(pose(T[:3, :3], T[:3, 3] + [0, 15, 0]))
    assert cx[0] > c0[0] + 3 and abs(cx[1] - c0[1]) < 1  # +x in the camera: right
    assert cy[1] > c0[1] + 3 and abs(cy[0] - c0[0]) < 1  # +y in the camera: down


def test_pixel_centres_at_integer_coordinates(renderer):
    """A fronto-parallel square covers exactly the pixels whose centres project inside it."""
    z = 600.0
    t = np.array([3.1, -2.7, z])
    out = renderer.render(K, [QUAD], pose(t=t)[None])
    corners = project(np.array([[-40, -40, 0], [40, 40, 0]]) + t, K)  # (u, v) of the square's edges
    u = np.arange(W)
    v = np.arange(H)
    want = ((u[None] > corners[0, 0]) & (u[None] < corners[1, 0])) & ((v[:, None] > corners[0, 1]) &
                                                                     (v[:, None] < corners[1, 1]))
    # no pixel centre lies within 1e-3 px of an edge for this pose, so the test is exact
    assert np.abs(np.r_[corners.ravel()] - np.round(corners.ravel())).min() > 1e-3
    np.testing.assert_array_equal(out.mask, want)


def test_world_up_is_image_up_with_look_at(renderer, meshes):
    """A camera from look_at (world z up): a point high in the world is higher in the image."""
    T_cam_world = invert(look_at([400, -300, 200], [0, 0, 0], up=[0, 0, 1]))
    lo = renderer.render_silhouettes(K, [CUBE], (T_cam_world @ pose(t=(0, 0, -60)))[None])[0]
    hi = renderer.render_silhouettes(K, [CUBE], (T_cam_world @ pose(t=(0, 0, 60)))[None])[0]
    assert np.nonzero(hi)[0].mean() < np.nonzero(lo)[0].mean() - 5


# ---------------------------------------------------------------- depth


def test_plane_depth_is_exact(renderer):
    # box 1000 x 1000 x 10: its front face (z = -5 in the model) at exactly 500 mm
    out = renderer.render(K, [PLANE], pose(t=(0, 0, 505))[None])
    assert out.mask.all()
    np.testing.assert_allclose(out.depth, 500.0, atol=0.01)
    # tilted by 30 degrees about the camera's y axis: depth of the plane through (0,0,505)-5n
    R = rot([0, 1, 0], 30)
    out = renderer.render(K, [PLANE], pose(R, (0, 0, 600))[None])
    n = R[:, 2]
    d = n @ (np.array([0, 0, 600.0]) - 5 * n)
    rays = backproject_depth(np.ones((H, W)), K)  # (x, y, 1) per pixel
    z = d / (rays @ n)
    assert out.mask.all()
    np.testing.assert_allclose(out.depth, z, atol=0.01)


def test_depth_not_blended_at_edges(renderer):
    """A cube (surface 400..450 mm deep) in front of a plane (500 mm): every depth is on the cube
    or on the plane (or 0 off both), never in between as a multisampled blend would be."""
    T = np.stack([pose(t=(0, 0, 505)), pose(rot([0, 0, 1], 20), (-10, 5, 425))])
    out = renderer.render(K, [PLANE, CUBE], T)
    d = out.depth
    on_plane = np.abs(d - 500) < 0.01
    on_cube = (d >= 400 - 0.01) & (d <= 450 + 0.01)
    assert (on_plane | on_cube).all()
    assert on_cube.sum() > 100 and on_plane.sum() > 100
    # and alone over the background: 0 or on the cube
    out = renderer.render(K, [CUBE], T[1:])
    assert ((out.depth == 0) | ((out.depth > 400 - 0.01) & (out.depth < 450.01))).all()
    assert ((out.depth > 0) == out.mask).all()


def test_backprojected_depth_lies_on_the_surface(renderer, meshes):
    T = pose(rot([1, 1, 0.3], 70), (-15, 10, 420))
    out = renderer.render(K, [ASYM], T[None])
    pts = backproject_depth(out.depth, K)[out.depth > 0]
    assert len(pts) > 500
    local = transform_points(invert(T), pts)
    _, dist, _ = trimesh.proximity.closest_point(meshes[ASYM], local)
    assert dist.max() < 0.5, dist.max()
    assert np.median(dist) < 0.01


# ---------------------------------------------------------------- instances


def test_occlusion_and_unoccluded_silhouettes(renderer):
    far = pose(rot([1, 0, 0], 20), (10, 0, 600))
    near = pose(rot([0, 1, 0], 30), (-15, 5, 450))
    for order in ((0, 1), (1, 0)):  # draw order must not matter
        ids = [[CUBE, ASYM][i] for i in order]
        T = np.stack([[far, near][i] for i in order])
        near_idx = order.index(1)
        out = renderer.render(K, ids, T)
        sil = renderer.render_silhouettes(K, ids, T)
        overlap = sil[0] & sil[1]
        assert overlap.sum() > 50
        assert (out.instance[overlap] == near_idx).all()
        np.testing.assert_array_equal(out.instance >= 0, sil[0] | sil[1])
        for i in range(2):
            alone = renderer.render(K, [ids[i]], T[i:i + 1])
            np.testing.assert_array_equal(sil[i], alone.mask)
        # the far one's visible pixels are its silhouette minus the near one's
        np.testing.assert_array_equal(out.instance == 1 - near_idx, sil[1 - near_idx] & ~sil[near_idx])


def test_repeated_obj_ids(renderer):
    ts = np.array([[-60, -30, 500], [0, 25, 520], [55, -20, 480]], float)
    T = np.stack([pose(rot([0, 0, 1], 10 * i), t) for i, t in enumerate(ts)])
    out = renderer.render(K, [CUBE, CUBE, CUBE], T)
    centres = project(ts, K)
    for i in range(3):
        ys, xs = np.nonzero(out.instance == i)
        assert len(xs) > 100
        np.testing.assert_allclose([xs.mean(), ys.mean()], centres[i], atol=2.0)
    sil = renderer.render_silhouettes(K, [CUBE] * 3, T)
    assert sil.shape == (3, H, W)


def test_empty_scene_and_errors(renderer):
    out = renderer.render(K, [], np.zeros((0, 4, 4)))
    assert (out.instance == -1).all() and (out.depth == 0).all() and (out.rgb == 0).all()
    assert renderer.render_silhouettes(K, [], np.zeros((0, 4, 4))).shape == (0, H, W)
    with pytest.raises(KeyError):
        renderer.render(K, [99], pose()[None])
    with pytest.raises(ValueError):
        renderer.render(K, [CUBE, CUBE], pose()[None])
    with pytest.raises(ValueError):
        renderer.render(K, [CUBE], pose()[None], background=np.zeros((10, 10, 3), np.uint8))


# ---------------------------------------------------------------- colours, lighting, background


def test_colours_lighting_and_override(renderer):
    T = pose(t=(0, 0, 500))[None]
    ys, xs = int(round(K[1, 2])), int(round(K[0, 2]))
    # own vertex colour (30, 200, 40), front face facing a head-on light: full albedo
    own = renderer.render(K, [CUBE], T, ambient=0.3, light_dir=(0, 0, 1))
    np.testing.assert_allclose(own.rgb[ys, xs], [30, 200, 40], atol=1)
    # override with a flat colour; a NaN row keeps the mesh's own colours
    red = renderer.render(K, [CUBE], T, colors=[[1.0, 0.0, 0.0]])
    np.testing.assert_allclose(red.rgb[ys, xs], [255, 0, 0], atol=1)
    kept = renderer.render(K, [CUBE], T, colors=[[np.nan] * 3])
    np.testing.assert_array_equal(kept.rgb, own.rgb)
    # light travelling sideways: the front face only gets the ambient part
    side = renderer.render(K, [CUBE], T, colors=[[1.0, 1.0, 1.0]], light_dir=(1, 0, 0), ambient=0.25,
                           light_intensity=0.8)
    np.testing.assert_allclose(side.rgb[ys, xs], [0.25 * 255] * 3, atol=1)
    # oblique light: Lambert's cosine
    obl = renderer.render(K, [CUBE], T, colors=[[1.0, 1.0, 1.0]], light_dir=(0, -1, 1), ambient=0.1,
                          light_intensity=0.5)
    np.testing.assert_allclose(obl.rgb[ys, xs], [(0.1 + 0.5 / np.sqrt(2)) * 255] * 3, atol=1)
    # default-coloured mesh (no visuals) is grey
    grey = renderer.render(K, [PLANE], pose(t=(0, 0, 505))[None], light_dir=(0, 0, 1))
    np.testing.assert_allclose(grey.rgb[ys, xs], [0.7 * 255] * 3, atol=1)


def test_texture_orientation(renderer):
    out = renderer.render(K, [TEXQUAD], pose(t=(0, 0, 400))[None], light_dir=(0, 0, 1))
    # OpenCV camera: model x is image-right, model y image-down. Model (x, y) = (-20, -20) carries
    # uv (0.25, 0.25): the texture's bottom half (green); (+-20, +20) carry v = 0.75, the texture's
    # top half: red at u = 0.25, blue at u = 0.75.
    pts = np.array([[-20, -20, 400], [20, -20, 400], [-20, 20, 400], [20, 20, 400]], float)
    px = project(pts, K).round().astype(int)
    got = out.rgb[px[:, 1], px[:, 0]]
    np.testing.assert_array_equal(got, [[0, 255, 0], [0, 255, 0], [255, 0, 0], [0, 0, 255]])


def test_open_mesh_is_two_sided(renderer):
    front = renderer.render(K, [QUAD], pose(t=(0, 0, 400))[None])
    back = renderer.render(K, [QUAD], pose(rot([0, 1, 0], 180), (0, 0, 400))[None])
    np.testing.assert_array_equal(front.mask, back.mask)
    np.testing.assert_allclose(back.depth[back.mask], 400.0, atol=0.01)
    np.testing.assert_array_equal(front.rgb, back.rgb)


def test_back_face_culling_only_where_safe(renderer, meshes):
    """Closed meshes are culled even with vertices split per face (as in textured files); an
    inside-out box is not culled and still renders like the box."""
    box = meshes[CUBE]
    split = trimesh.Trimesh(box.vertices[box.faces].reshape(-1, 3), np.arange(3 * len(box.faces)).reshape(-1, 3),
                            process=False)
    inverted = trimesh.Trimesh(box.vertices.copy(), box.faces[:, ::-1].copy(), process=False)
    renderer.add_mesh(10, split)
    renderer.add_mesh(11, inverted)
    assert renderer._meshes[CUBE].cull and renderer._meshes[10].cull
    assert not renderer._meshes[11].cull and not renderer._meshes[QUAD].cull
    T = pose(rot([1, 2, 0.5], 50), (5, 0, 450))[None]
    ref = renderer.render(K, [CUBE], T, colors=[[0.5, 0.5, 0.5]])
    for obj_id in (10, 11):
        out = renderer.render(K, [obj_id], T, colors=[[0.5, 0.5, 0.5]])
        np.testing.assert_array_equal(out.mask, ref.mask)
        np.testing.assert_allclose(out.depth, ref.depth, atol=0.01)
        np.testing.assert_allclose(out.rgb, ref.rgb, atol=1)


def test_background_compositing(renderer):
    bg = np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8)
    T = pose(rot([1, 0, 0], 30), (0, 0, 450))[None]
    out = renderer.render(K, [ASYM], T, background=bg)
    plain = renderer.render(K, [ASYM], T)
    np.testing.assert_array_equal(out.rgb[~out.mask], bg[~out.mask])
    np.testing.assert_array_equal(out.rgb[out.mask], plain.rgb[out.mask])
    assert out.rgb.dtype == np.uint8 and out.depth.dtype == np.float32 and out.instance.dtype == np.int32
    no_rgb = renderer.render(K, [ASYM], T, with_rgb=False)
    assert no_rgb.rgb is None
    np.testing.assert_array_equal(no_rgb.depth, plain.depth)


# ---------------------------------------------------------------- sizes and crops


def test_other_sizes_with_the_same_renderer(renderer):
    T = pose(rot([0, 1, 1], 35), (5, 5, 450))[None]
    full = renderer.render(K, [ASYM], T)
    Kh = K.copy()
    Kh[:2] /= 2
    Kh[:2, 2] = (K[:2, 2] + 0.5) / 2 - 0.5  # same field of view at half resolution
    half = renderer.render(K=Kh, obj_ids=[ASYM], T_cam_obj=T, size=(W // 2, H // 2))
    assert half.depth.shape == (H // 2, W // 2)
    down = cv2.resize(full.mask.astype(np.float32), (W // 2, H // 2), interpolation=cv2.INTER_AREA) > 0.5
    assert (down ^ half.mask).sum() <= 0.05 * half.mask.sum()
    again = renderer.render(K, [ASYM], T)  # back to the default size
    np.testing.assert_array_equal(again.depth, full.depth)


def test_crops_agree_with_cropped_full_frames(meshes):
    Wf, Hf = 640, 480
    Kf = np.array([[600.0, 0, 331.2], [0, 590.0, 228.7], [0, 0, 1]])
    rng = np.random.default_rng(1)
    from cosy_cli.geometry import random_rotations

    n = 5
    ids = [ASYM, CUBE, ASYM, CUBE, ASYM]
    t = np.c_[rng.uniform(-150, 150, n), rng.uniform(-100, 100, n), rng.uniform(450, 800, n)]
    T = make_pose(random_rotations(n, rng), t)
    size = (128, 96)
    with SceneRenderer(meshes, Wf, Hf) as r:
        sil = r.render_silhouettes(Kf, ids, T)
        boxes = []
        for m in sil:
            ys, xs = np.nonzero(m)
            boxes.append([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1])
        boxes = fit_box_to_aspect(np.array(boxes, float), size[0] / size[1], scale=1.3)
        Kc = crop_intrinsics(Kf, boxes, size)
        crops = r.render_crops(Kc, ids, T, size)
        full = r.render(Kf, ids, T)
    assert crops.rgb.shape == (n, 96, 128, 3) and crops.depth.shape == (n, 96, 128)
    A = crop_affine(boxes, size)
    for b in range(n):
        warped = cv2.warpAffine(sil[b].astype(np.float32), A[b], size, flags=cv2.INTER_LINEAR) > 0.5
        m = crops.instance[b] >= 0
        assert set(np.unique(crops.instance[b])) == {-1, b}
        iou = (warped & m).sum() / (warped | m).sum()
        assert iou > 0.95, (b, iou)
        # depth agrees where both see the object well inside the silhouette
        dw = cv2.warpAffine(np.where(sil[b], full.depth * (full.instance == b), 0).astype(np.float32), A[b], size,
                            flags=cv2.INTER_NEAREST)
        inner = cv2.erode(m.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool) & (dw > 0)
        if inner.sum() > 50:
            assert np.median(np.abs(dw[inner] - crops.depth[b][inner])) < 2.0


def test_many_crops_span_several_atlases(meshes):
    """More tiles than fit one framebuffer: chunked, results identical to one-by-one renders."""
    with SceneRenderer({CUBE: meshes[CUBE]}, 64, 48) as r:
        n = 7
        Kc = np.tile(np.array([[300.0, 0, 300], [0, 300, 300], [0, 0, 1]]), (n, 1, 1))
        Kc[:, 0, 2] += np.arange(n) * 3
        T = np.stack([pose(rot([1, 1, 0], 10 * i), (0, 0, 400 + 10 * i)) for i in range(n)])
        import cosy_cli.rendering.renderer as rr

        old = rr.MAX_ATLAS_SIDE
        rr.MAX_ATLAS_SIDE = 1300  # 600x600 tiles: 2 x 2 per atlas -> 2 atlases
        try:
            batch = r.render_crops(Kc, [CUBE] * n, T, (600, 600))
        finally:
            rr.MAX_ATLAS_SIDE = old
        for i in range(n):
            one = r.render(Kc[i], [CUBE], T[i:i + 1], size=(600, 600))
            # equal up to float rounding (the tiles sit at other window offsets)
            np.testing.assert_allclose(batch.rgb[i], one.rgb, atol=1)
            np.testing.assert_allclose(batch.depth[i], one.depth, atol=0.01)
            np.testing.assert_array_equal(batch.instance[i] >= 0, one.instance >= 0)


# ---------------------------------------------------------------- pyrender itself


def test_patched_pyrender_depth_is_not_blended(renderer, meshes):
    """pyrender's own OffscreenRenderer, patched: no multisampling, and deleting it does not
    break our live renderer's EGL context."""
    patch_pyrender()
    import pyrender

    from cosy_cli.geometry import T_GL_CV

    scene = pyrender.Scene()
    scene.add(pyrender.Mesh.from_trimesh(meshes[CUBE]), pose=np.eye(4))
    cam = pyrender.IntrinsicsCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], znear=10, zfar=5000)
    T_cam_obj = pose(rot([0, 0, 1], 20), (0, 0, 425))
    scene.add(cam, pose=invert(T_cam_obj) @ np.linalg.inv(T_GL_CV))  # T_obj_cam of an OpenGL camera
    o = pyrender.OffscreenRenderer(W, H)
    _, depth = o.render(scene)
    from OpenGL import GL as gl

    gl.glBindRenderbuffer(gl.GL_RENDERBUFFER, o._renderer._main_db_ms)
    assert gl.glGetRenderbufferParameteriv(gl.GL_RENDERBUFFER, gl.GL_RENDERBUFFER_SAMPLES) == 0
    o.delete()
    assert (depth > 0).sum() > 100
    assert ((depth == 0) | ((depth > 399.9) & (depth < 450.1))).all()
    out = renderer.render(K, [CUBE], T_cam_obj[None])  # still alive
    assert out.mask.sum() > 100


def test_platform_selection(monkeypatch):
    from cosy_cli.errors import CosyError
    from cosy_cli.rendering import select_gl_platform

    monkeypatch.setenv("COSY_GL", "EGL")
    monkeypatch.delenv("PYGLET_HEADLESS", raising=False)
    assert select_gl_platform() == "egl"
    assert os.environ["PYGLET_HEADLESS"] == "true"  # pyrender's pyglet without X11 libraries
    monkeypatch.setenv("PYGLET_HEADLESS", "false")  # a user's own choice is kept
    assert select_gl_platform() == "egl" and os.environ["PYGLET_HEADLESS"] == "false"
    monkeypatch.setenv("COSY_GL", "glx")
    with pytest.raises(CosyError, match="COSY_GL"):
        select_gl_platform()
    monkeypatch.setenv("COSY_GL", "osmesa")  # OpenGL is already bound to EGL in this process
    with pytest.raises(CosyError, match="import cosy_cli.rendering first"):
        select_gl_platform()


def test_an_optimiser_after_rendering_when_torch_brings_triton():
    """torch's CUDA builds bring triton, whose LLVM segfaulted the process when loaded after
    Mesa's (the first torch.optim optimiser after a render imports torch._dynamo, then triton):
    rendering loads triton first. Runs in a fresh process; without triton (the locked CPU torch)
    there is nothing to load and load_triton_first says so."""
    import importlib.util
    import subprocess
    import sys

    code = (
        "import numpy as np, trimesh, torch\n"
        "from cosy_cli.rendering import SceneRenderer\n"
        "tri = trimesh.Trimesh([[-40.0, -40, 0], [40, -40, 0], [0, 40, 0]], [[0, 1, 2]], process=False)\n"
        "T = np.eye(4); T[2, 3] = 500\n"
        "with SceneRenderer({1: tri}, 64, 48, max_faces=None) as r:\n"
        "    assert abs(r.render(np.array([[60.0, 0, 32], [0, 60, 24], [0, 0, 1]]), [1], T[None]).depth[24, 32] - 500) < 0.5\n"
        "torch.optim.Adam(torch.nn.Linear(3, 3).parameters())\n"
        "print('ok')\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-2000:]
    if importlib.util.find_spec("triton") is None:
        from cosy_cli.rendering.platform import load_triton_first

        assert load_triton_first() is False
