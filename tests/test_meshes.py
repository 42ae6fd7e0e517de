"""Meshes checked where they are read (truncated files, NaN vertices, faces out of range, no faces),
colours and textures rendered, missing textures grey, big meshes rendered from a cached decimated copy."""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from cosy_cli.cli.main import cli
from cosy_cli import console
from cosy_cli.errors import CosyError, CosyWarning
from realdata import LMO, MEGAPOSE, needs

from cosy_cli.objects.database import (MeshFileError, ObjectDatabase, check_mesh_arrays, check_ply_data,
                                       load_mesh)

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "data_samples"
LMO_MODELS = LMO / "models"

K = np.array([[500.0, 0, 159.5], [0, 500.0, 119.5], [0, 0, 1]])
# seen from the camera: model x right, model y up (image rows go down), model +z towards the camera
T_FRONT = np.diag([1.0, -1.0, -1.0, 1.0])
T_FRONT[2, 3] = 100.0
FLAT = dict(ambient=1.0, light_intensity=0.0)  # albedo exactly: no shading


def _cut(path: Path, frac: float = 0.5) -> None:
    b = path.read_bytes()
    path.write_bytes(b[:int(len(b) * frac)])


def _ascii_ply(path: Path, V, F, extra_header: str = "", vertex_props=("x", "y", "z"), rows=None) -> Path:
    lines = ["ply", "format ascii 1.0"] + ([extra_header] if extra_header else [])
    lines += [f"element vertex {len(V)}"] + [f"property float {p}" for p in vertex_props]
    lines += [f"element face {len(F)}", "property list uchar int vertex_indices", "end_header"]
    rows = V if rows is None else rows
    lines += [" ".join(f"{x:g}" for x in r) for r in rows]
    lines += ["3 " + " ".join(str(int(i)) for i in f) for f in F]
    path.write_text("\n".join(lines) + "\n")
    return path


# a 20 x 20 mm square in the model's z = 0 plane, uv (0, 0) at its bottom-left corner (x, y = -10)
SQUARE_V = np.array([[-10, -10, 0], [10, -10, 0], [10, 10, 0], [-10, 10, 0]], dtype=float)
SQUARE_UV = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=float)
SQUARE_F = np.array([[0, 1, 2], [0, 2, 3]])
QUADRANTS = {"top-left": (255, 0, 0), "top-right": (0, 255, 0), "bottom-left": (0, 0, 255),
             "bottom-right": (255, 255, 0)}


def _quadrant_texture(path: Path) -> Path:
    """64 x 64 PNG, image row 0 at the top: red | green over blue | yellow."""
    img = np.zeros((64, 64, 3), np.uint8)
    img[:32, :32], img[:32, 32:] = QUADRANTS["top-left"], QUADRANTS["top-right"]
    img[32:, :32], img[32:, 32:] = QUADRANTS["bottom-left"], QUADRANTS["bottom-right"]
    Image.fromarray(img).save(path)
    return path


def _textured_ply(folder: Path, texture: str = "tex.png") -> Path:
    rows = np.hstack([SQUARE_V, SQUARE_UV])
    return _ascii_ply(folder / "square.ply", SQUARE_V, SQUARE_F, extra_header=f"comment TextureFile {texture}",
                      vertex_props=("x", "y", "z", "texture_u", "texture_v"), rows=rows)


def _textured_obj(folder: Path, texture: str = "tex.png") -> Path:
    (folder / "square.mtl").write_text(f"newmtl m\nKa 1 1 1\nKd 1 1 1\nmap_Kd {texture}\n")
    lines = ["mtllib square.mtl"] + [f"v {x:g} {y:g} {z:g}" for x, y, z in SQUARE_V]
    lines += [f"vt {u:g} {v:g}" for u, v in SQUARE_UV] + ["usemtl m"]
    lines += ["f " + " ".join(f"{i + 1}/{i + 1}" for i in f) for f in SQUARE_F]
    path = folder / "square.obj"
    path.write_text("\n".join(lines) + "\n")
    return path


def _quadrant_pixels(rgb: np.ndarray) -> dict[str, tuple]:
    """Colours at the centres of the square's quadrants (the square spans 100 px, centred)."""
    cx, cy, q = 159, 119, 25
    at = {"top-left": (cy - q, cx - q), "top-right": (cy - q, cx + q), "bottom-left": (cy + q, cx - q),
          "bottom-right": (cy + q, cx + q)}
    return {k: tuple(int(c) for c in rgb[r, c_]) for k, (r, c_) in at.items()}


def _render(mesh, T=T_FRONT, **kw):
    from cosy_cli.rendering import SceneRenderer

    with SceneRenderer({1: mesh}, 320, 240, **{k: kw.pop(k) for k in ("max_faces",) if k in kw}) as r:
        return r.render(K, [1], T[None], **{**FLAT, **kw})


# --------------------------------------------------------------------------------------------
# broken files -> one CosyError naming the file
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["obj_000001.ply", "obj_000003.ply"])
@pytest.mark.parametrize("frac", [0.3, 0.5, 0.95, 0.999])
def test_truncated_binary_ply(tmp_path, name, frac):
    p = tmp_path / name
    shutil.copy(SAMPLES / "models" / name, p)
    _cut(p, frac)
    with pytest.raises(MeshFileError, match="truncated PLY") as e:
        load_mesh(p)
    assert str(p) in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("endian", ["<", ">"])
def test_binary_ply_quads_and_triangles(tmp_path, endian):
    """Faces of varying length (a quad and a triangle): sizes walked row by row."""
    import struct

    name = "binary_little_endian" if endian == "<" else "binary_big_endian"
    header = (f"ply\nformat {name} 1.0\nelement vertex 5\nproperty float x\nproperty float y\nproperty float z\n"
              "element face 2\nproperty list uchar int vertex_indices\nend_header\n").encode()
    V = [(-10, -10, 0), (10, -10, 0), (10, 10, 0), (-10, 10, 0), (0, 20, 0)]
    body = b"".join(struct.pack(endian + "3f", *v) for v in V)
    body += struct.pack(endian + "B4i", 4, 0, 1, 2, 3) + struct.pack(endian + "B3i", 3, 3, 2, 4)
    p = tmp_path / "mixed.ply"
    p.write_bytes(header + body)
    assert check_ply_data(p).count("face") == 2  # complete (trimesh 5.2 itself reads no mixed binary faces)
    p.write_bytes(header + body[:-5])
    with pytest.raises(MeshFileError, match="within element 'face'"):
        load_mesh(p)


def test_truncated_header(tmp_path):
    p = tmp_path / "h.ply"
    shutil.copy(SAMPLES / "models" / "obj_000002.ply", p)
    p.write_bytes(p.read_bytes()[:60])
    with pytest.raises(CosyError, match="end_header"):
        load_mesh(p)


def test_truncated_ascii_ply(tmp_path):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=2, radius=30)
    full = _ascii_ply(tmp_path / "full.ply", m.vertices, m.faces)
    assert len(load_mesh(full).faces) == len(m.faces)
    lines = full.read_text().splitlines()
    for n_drop in (1, 50, len(m.faces) + 10):  # last face, many faces, into the vertices
        p = tmp_path / f"cut{n_drop}.ply"
        p.write_text("\n".join(lines[:-n_drop]) + "\n")
        with pytest.raises(MeshFileError, match=r"truncated PLY file: the header declares 162 vertices and "
                                                r"320 faces") as e:
            load_mesh(p)
        assert str(p) in str(e.value)
    p = tmp_path / "midline.ply"  # cut in the middle of the last line
    p.write_text("\n".join(lines)[:-3])
    with pytest.raises(MeshFileError, match="truncated PLY file: data line"):
        load_mesh(p)


@needs(LMO_MODELS)
def test_truncated_lmo_model(tmp_path):
    p = tmp_path / "obj_000005.ply"
    shutil.copy(LMO_MODELS / "obj_000005.ply", p)
    _cut(p, 0.5)
    with pytest.raises(MeshFileError, match="declares 22831 vertices and 45666 faces"):
        load_mesh(p)


def test_nan_vertices_faces_out_of_range_no_faces(tmp_path):
    V, F = SQUARE_V.copy(), SQUARE_F.copy()
    V[2, 1] = np.nan
    with pytest.raises(MeshFileError, match=r"1 of 4 vertices are NaN or infinite \(first: vertex 2"):
        load_mesh(_ascii_ply(tmp_path / "nan.ply", V, F))
    V[2, 1] = np.inf
    with pytest.raises(MeshFileError, match="NaN or infinite"):
        load_mesh(_ascii_ply(tmp_path / "inf.ply", V, F))
    F[1, 2] = 7
    with pytest.raises(MeshFileError, match="face 1 uses vertex index 7 but the mesh has 4 vertices") as e:
        load_mesh(_ascii_ply(tmp_path / "oob.ply", SQUARE_V, F))
    assert "oob.ply" in str(e.value)
    with pytest.raises(MeshFileError, match="no faces"):
        load_mesh(_ascii_ply(tmp_path / "nofaces.ply", SQUARE_V, np.zeros((0, 3), int)))
    (tmp_path / "nofaces.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(MeshFileError, match="no"):
        load_mesh(tmp_path / "nofaces.obj")
    (tmp_path / "oob.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 9\n")
    with pytest.raises(MeshFileError, match="oob.obj"):
        load_mesh(tmp_path / "oob.obj")
    with pytest.raises(CosyError, match="no faces"):
        check_mesh_arrays(SQUARE_V, None, "x.ply")
    check_ply_data(SAMPLES / "models" / "obj_000003.ply")  # an intact file passes


def test_object_model_mesh_is_checked_lazily(tmp_path):
    models = tmp_path / "models"
    shutil.copytree(SAMPLES / "models", models)
    _cut(models / "obj_000004.ply")
    db = ObjectDatabase.from_models_dir(models)
    assert len(db[1].vertices) > 0
    with pytest.raises(MeshFileError, match="obj_000004.ply: truncated"):
        _ = db[4].points


@pytest.fixture(scope="module")
def broken_samples(tmp_path_factory) -> Path:
    """A copy of data_samples with models/obj_000003.ply cut in half, and candidates for it."""
    root = tmp_path_factory.mktemp("broken") / "ds"
    shutil.copytree(SAMPLES, root)
    _cut(root / "models" / "obj_000003.ply")
    r = CliRunner().invoke(cli, ["synth-candidates", "--dataset", str(root), "--out", str(root.parent / "c.csv"),
                                 "--profile", "clean"])
    assert r.exit_code == 0, r.output
    return root


def _one_line_error(r, root: Path):
    assert r.exit_code == 2, r.output
    assert "Traceback" not in r.output
    hits = [ln for ln in r.output.splitlines() if "obj_000003.ply" in ln]
    assert len(hits) == 1 and "truncated PLY file" in hits[0], r.output


def test_cli_match_exits_2(broken_samples, tmp_path):
    r = CliRunner().invoke(cli, ["match", "--dataset", str(broken_samples), "--candidates",
                                 str(broken_samples.parent / "c.csv"), "--out", str(tmp_path / "m")])
    _one_line_error(r, broken_samples)
    assert r.output.strip().splitlines()[-1].startswith("error:")


def test_cli_validate_exits_2(broken_samples):
    r = CliRunner().invoke(cli, ["validate", "--dataset", str(broken_samples)])
    _one_line_error(r, broken_samples)


def test_cli_templates_exits_2(broken_samples, tmp_path):
    r = CliRunner().invoke(cli, ["templates", "--models", str(broken_samples / "models"), "--out",
                                 str(tmp_path / "tpl")])
    _one_line_error(r, broken_samples)


# --------------------------------------------------------------------------------------------
# colours and textures
# --------------------------------------------------------------------------------------------
@needs(LMO_MODELS)
def test_vertex_colours_lmo():
    mesh = load_mesh(LMO_MODELS / "obj_000001.ply")
    assert mesh.visual.kind == "vertex"
    T = np.eye(4)
    T[2, 3] = 400.0
    out = _render(mesh, T)
    px = out.rgb[out.mask].astype(float)
    assert len(px) > 2000
    vc = np.asarray(mesh.visual.vertex_colors)[:, :3].astype(float)
    assert np.abs(px.mean(0) - vc.mean(0)).max() < 15, (px.mean(0), vc.mean(0))
    grey = _render(load_mesh(LMO_MODELS / "obj_000001.ply"), T, colors=[[0.7, 0.7, 0.7]])
    assert np.abs(grey.rgb[grey.mask].astype(float).mean(0) - px.mean(0)).max() > 30  # not grey


def test_vertex_colours_synthetic(tmp_path):
    import trimesh

    m = trimesh.creation.box(extents=(20, 20, 20))
    c = np.where(m.vertices[:, :1] < 0, [[255, 0, 0, 255]], [[0, 0, 255, 255]]).astype(np.uint8)
    m = trimesh.Trimesh(m.vertices, m.faces, vertex_colors=c, process=False)
    p = tmp_path / "box.ply"
    m.export(p)
    rgb = _render(load_mesh(p)).rgb
    for du in (-40, 0, 40):  # the face towards the camera (z = 90 mm): colours interpolated in x
        t = (du * 90 / 500 + 10) / 20
        px = rgb[119, 159 + du].astype(float)
        assert np.abs(px - [255 * (1 - t), 0, 255 * t]).max() <= 3, (du, px)


@pytest.mark.parametrize("kind", ["ply", "obj"])
def test_texture_rendered_upright(tmp_path, kind):
    _quadrant_texture(tmp_path / "tex.png")
    path = (_textured_ply if kind == "ply" else _textured_obj)(tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CosyWarning)
        mesh = load_mesh(path)
    assert mesh.visual.kind == "texture"
    out = _render(mesh)
    assert _quadrant_pixels(out.rgb) == QUADRANTS
    Image.fromarray(out.rgb).save(tmp_path / f"textured_{kind}.png")


@pytest.mark.parametrize("kind", ["ply", "obj", "obj-no-mtl"])
def test_missing_texture_one_warning_and_grey(tmp_path, kind):
    from cosy_cli.rendering import DEFAULT_COLOR

    if kind == "ply":
        path = _textured_ply(tmp_path, "missing.png")
    else:
        path = _textured_obj(tmp_path, "missing.png")
        if kind == "obj-no-mtl":
            (tmp_path / "square.mtl").unlink()
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        mesh = load_mesh(path)
        load_mesh(path)  # loaded again (another stage, another renderer): no second warning
    msgs = [str(x.message) for x in w if issubclass(x.category, CosyWarning)]
    assert len(msgs) == 1 and str(path) in msgs[0] and "missing" in msgs[0], msgs
    assert "\n" not in msgs[0]
    rgb = _render(mesh).rgb
    grey = tuple(int(round(255 * c)) for c in DEFAULT_COLOR)
    for v in _quadrant_pixels(rgb).values():
        assert np.abs(np.subtract(v, grey)).max() <= 1, v


@needs(MEGAPOSE)
def test_hope_textured_mesh_is_not_grey():
    mesh = load_mesh(MEGAPOSE / "mustard" / "meshes" / "mustard" / "obj_000016.ply")
    assert mesh.visual.kind == "texture"
    T = np.eye(4)
    T[:3, :3] = [[0, 1, 0], [0, 0, -1], [-1, 0, 0]]  # bottle upright (cap up), label towards the camera
    T[2, 3] = 450.0
    out = _render(mesh, T)
    px = out.rgb[out.mask].astype(float)
    assert len(px) > 1000
    r, g, b = px.mean(0)
    assert r > 100 and g > 90 and b < 50, (r, g, b)  # mustard yellow (a grey mesh: 178, 178, 178)


# --------------------------------------------------------------------------------------------
# big meshes: a decimated copy for rendering, cached on disk
# --------------------------------------------------------------------------------------------
def test_big_mesh_rendered_from_cached_decimated_copy(tmp_path, monkeypatch, capsys):
    import fast_simplification
    import trimesh

    from cosy_cli.rendering import MAX_RENDER_FACES, decimate

    monkeypatch.setenv("COSY_CACHE_DIR", str(tmp_path / "cache"))
    decimate.clear_memory_cache()
    sphere = trimesh.creation.icosphere(subdivisions=7, radius=40)  # 327,680 faces
    colours = np.where(sphere.vertices[:, :1] < 0, [[255, 0, 0, 255]], [[0, 255, 0, 255]]).astype(np.uint8)
    path = tmp_path / "sphere.ply"
    trimesh.Trimesh(sphere.vertices, sphere.faces, vertex_colors=colours, process=False).export(path)
    mesh = load_mesh(path)
    assert len(mesh.faces) > MAX_RENDER_FACES
    T = np.eye(4)
    T[2, 3] = 200.0
    capsys.readouterr()
    with warnings.catch_warnings(record=True) as w, console.command_output(console.VERBOSE):
        warnings.simplefilter("always")
        small = _render(mesh, T)
        again = _render(mesh, T)  # second renderer in the process: the copy in memory, said once
    assert not [x for x in w if issubclass(x.category, CosyWarning)]  # an internal step, not a warning
    notes = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("note: ")]
    assert len(notes) == 1 and "decimated copy" in notes[0] and "sphere.ply" in notes[0], notes
    cached = list((tmp_path / "cache" / "meshes").glob("*.npz"))
    assert len(cached) == 1
    full = _render(mesh, T, max_faces=None)
    iou = (small.mask & full.mask).sum() / (small.mask | full.mask).sum()
    assert iou > 0.98, iou
    assert np.array_equal(small.mask, again.mask)
    assert tuple(small.rgb[119, 159 - 40]) == (255, 0, 0) and tuple(small.rgb[119, 159 + 40]) == (0, 255, 0)
    copy = decimate.render_copy(mesh)
    assert len(copy.faces) <= MAX_RENDER_FACES and len(mesh.faces) == len(sphere.faces)  # original kept

    # a new process (memory cache empty) reads the copy from disk: no decimation
    decimate.clear_memory_cache()
    monkeypatch.setattr(fast_simplification, "simplify", lambda *a, **k: pytest.fail("decimated again"))
    with console.command_output(console.NORMAL):  # said with --verbose only
        from_disk = _render(mesh, T)
    assert "decimated" not in capsys.readouterr().err
    decimate.clear_memory_cache()
    with console.command_output(console.VERBOSE):
        assert np.array_equal(_render(mesh, T).mask, small.mask)
    assert "(cached " in capsys.readouterr().err
    assert np.array_equal(from_disk.mask, small.mask)
    decimate.clear_memory_cache()
