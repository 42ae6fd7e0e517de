"""SceneRenderer: RGB, exact depth and instance maps of posed meshes, headless (pyrender + OpenGL).

Conventions (the house ones): poses ``T_cam_obj`` are 4x4 maps from object to OpenCV camera
coordinates (x right, y down, z forward), lengths in mm, intrinsics ``K`` in pixels with the centre
of the top-left pixel at (0, 0). Renders follow :func:`cosy_cli.geometry.project` exactly: a point
that projects to (u, v) is drawn in pixel column round(u), row round(v).

How it works. pyrender provides the headless context (EGL/OSMesa, see :mod:`.platform`), the
trimesh -> GPU conversion (``pyrender.Mesh.from_trimesh``: flat or smooth normals, vertex/face
colours, UVs) and texture upload. The forward pass is our own, one shader and one draw call per
instance, into our own *single-sample* framebuffer with three colour attachments:

- RGBA8 colour: albedo (flat colour, vertex colours or texture) x (ambient + intensity x
  max(0, n . -light_dir)), Lambert shading with normals turned towards the camera, no gamma;
- R32F depth: the camera-frame z (mm) of the visible surface, interpolated per pixel centre (not
  read back from the non-linear z-buffer, so it is exact to float precision, and never blended
  across edges since nothing is multisampled); 0 where no object;
- R32I instance: index of the visible instance, -1 where no object.

The projection matrix (:func:`projection_matrix`) takes OpenCV camera coordinates straight to clip
space with the image's row order equal to OpenGL's window row order, so reading the framebuffer
gives the image top row first: no flips and no ``T_GL_CV`` (pyrender's own cameras are OpenGL ones;
:data:`cosy_cli.geometry.T_GL_CV` converts if you use them directly).

Closed meshes (watertight, wound outwards) are drawn with back faces culled, which halves the
work of llvmpipe's triangle setup, its bottleneck; open ones are drawn two-sided, lit on the side
facing the camera.

Several images (crops, silhouettes) are rendered as tiles of one framebuffer (an atlas: one
viewport per tile, clipped and scissored to it) and read back with one ``glReadPixels`` per
attachment. One OpenGL context per renderer, reused for every size; GPU meshes are cached per
object id.

Speed with many small crops (llvmpipe's triangle setup is the bottleneck, and it grows with the
values interpolated per triangle): ``shading="vertex"`` lights per vertex (6 values interpolated
instead of 12, 3 when neither depth nor a texture is drawn; the same image to 1 grey level for
flat-shaded meshes); renders
without colours (``with_rgb=False``: silhouettes, depth, instances) use a program that
interpolates the depth alone (the same depth and instances); ``with_instance=False`` reads the
colour back as RGBA (the native format, alpha = mask) instead of RGB + the instance map;
consecutive instances of one mesh and tiles of one camera do not re-send their state.
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from ..lifetime import Closing
from .decimate import MAX_RENDER_FACES, render_copy
from .platform import create_context, select_gl_platform
from .pyrender_patch import patch_pyrender

_PLATFORM = select_gl_platform()  # must precede the first import of OpenGL

from OpenGL import GL as gl  # noqa: E402
from OpenGL.GL import shaders as gl_shaders  # noqa: E402  (before any OpenGL.EGL import: PyOpenGL 3.1.0 bug)

DEFAULT_COLOR = (0.7, 0.7, 0.7)  # RGB 0..1 of meshes without colours or texture
MAX_ATLAS_SIDE = 2048  # pixels: side of the framebuffer that tiles are packed into (grown for bigger images)

# Pieces every program shares: the vertex inputs with the pose and projection uniforms, and the
# three fragment outputs (colour, camera z in mm, instance index).
_VS_INPUTS = """
#version 330 core
layout(location = 0) in vec3 position;
layout(location = 1) in vec3 normal;
layout(location = 2) in vec2 texcoord;
layout(location = 3) in vec4 color;
uniform mat4 MV;  // object (mm) -> OpenCV camera (mm)
uniform mat4 P;   // OpenCV camera -> clip
"""
_FS_OUTPUTS = """
layout(location = 0) out vec4 out_color;
layout(location = 1) out float out_depth;
layout(location = 2) out int out_instance;
"""

_LIGHTING = """
uniform vec3 light_dir;      // unit direction the light travels, camera frame
uniform vec2 light;          // (directional intensity, ambient)
// Lambert + ambient, two-sided: the normal is turned to face the camera (point p, camera frame)
float shade(vec3 normal, vec3 p) {
    float len = length(normal);
    vec3 n = len > 1e-12 ? normal / len : -normalize(p);
    if (dot(n, p) > 0.0) n = -n;
    return light.y + light.x * max(dot(n, -light_dir), 0.0);
}
"""

_VERTEX_SHADER = _VS_INPUTS + """out vec3 v_pos;
out vec3 v_normal;
out vec2 v_uv;
out vec4 v_color;
void main() {
    vec4 p = MV * vec4(position, 1.0);
    v_pos = p.xyz;
    v_normal = mat3(MV) * normal;  // rigid poses: the rotation is its own inverse transpose
    v_uv = texcoord;
    v_color = color;
    gl_Position = P * p;
}
"""

_FRAGMENT_SHADER = """
#version 330 core
in vec3 v_pos;
in vec3 v_normal;
in vec2 v_uv;
in vec4 v_color;
uniform vec4 base_color;
uniform ivec3 flags;         // (use vertex colours, use texture, instance index)
uniform sampler2D base_texture;
""" + _LIGHTING + _FS_OUTPUTS + """void main() {
    vec4 albedo = base_color;
    if (flags.x != 0) albedo *= v_color;
    if (flags.y != 0) albedo *= texture(base_texture, v_uv);
    out_color = vec4(clamp(albedo.rgb * shade(v_normal, v_pos), 0.0, 1.0), 1.0);
    out_depth = v_pos.z;
    out_instance = flags.z;
}
"""


# Vertex-lit variant (``SceneRenderer(shading="vertex")``): the same colours for flat-shaded meshes
# (smooth=False: a face's three vertices carry its normal, and a plane's normal faces the camera at
# every point of it or at none), computed once per vertex, so that only the shaded colour (3
# components), the depth and the UVs are interpolated instead of 12 components: 64 x 64 crops of
# 1000-3000-face meshes render ~1.2-1.5x faster on llvmpipe (its triangle setup is the bottleneck).
# Colours agree with the per-pixel program to 1 grey level.
_VERTEX_LIT_VS = _VS_INPUTS + """uniform vec4 base_color;
uniform ivec3 flags;         // (use vertex colours, use texture, instance index)
""" + _LIGHTING + """out vec3 v_rgb;
out vec2 v_uv;
out float v_z;
void main() {
    vec4 p = MV * vec4(position, 1.0);
    vec4 albedo = base_color;
    if (flags.x != 0) albedo *= color;
    v_rgb = albedo.rgb * shade(mat3(MV) * normal, p.xyz);
    v_uv = texcoord;
    v_z = p.z;
    gl_Position = P * p;
}
"""

_VERTEX_LIT_FS = """
#version 330 core
in vec3 v_rgb;
in vec2 v_uv;
in float v_z;
uniform ivec3 flags;
uniform sampler2D base_texture;
""" + _FS_OUTPUTS + """void main() {
    vec3 c = v_rgb;
    if (flags.y != 0) c *= texture(base_texture, v_uv).rgb;
    out_color = vec4(clamp(c, 0.0, 1.0), 1.0);
    out_depth = v_z;
    out_instance = flags.z;
}
"""


# The vertex-lit program when neither depth nor a texture is needed: the colour alone is interpolated.
_VERTEX_LIT_RGB_VS = (_VERTEX_LIT_VS.replace("out vec2 v_uv;\nout float v_z;\n", "")
                      .replace("    v_uv = texcoord;\n    v_z = p.z;\n", ""))
_VERTEX_LIT_RGB_FS = """
#version 330 core
in vec3 v_rgb;
uniform ivec3 flags;
""" + _FS_OUTPUTS + """void main() {
    out_color = vec4(clamp(v_rgb, 0.0, 1.0), 1.0);
    out_depth = 0.0;
    out_instance = flags.z;
}
"""

# Without colours (``with_rgb=False``: silhouettes, depth, instances) only the depth is interpolated.
_MASK_VS = """
#version 330 core
layout(location = 0) in vec3 position;
uniform mat4 MV;
uniform mat4 P;
out float v_z;
void main() {
    vec4 p = MV * vec4(position, 1.0);
    v_z = p.z;
    gl_Position = P * p;
}
"""

_MASK_FS = """
#version 330 core
in float v_z;
uniform ivec3 flags;
""" + _FS_OUTPUTS + """void main() {
    out_color = vec4(1.0);
    out_depth = v_z;
    out_instance = flags.z;
}
"""

_UNIFORMS = ("MV", "P", "base_color", "flags", "base_texture", "light_dir", "light")


@dataclass
class RenderOutput:
    """What a render returns (single image: (H, W, ...); batches: (B, H, W, ...)).

    rgb: uint8 RGB, or None when rendered ``with_rgb=False``.
    depth: float32 camera-frame z in mm of the visible surface, 0 where no object; None when
    rendered ``with_depth=False``.
    instance: int32 index into the call's ``obj_ids`` of the visible instance, -1 where none;
    None when rendered ``with_instance=False``.
    rgba: uint8 RGBA (alpha 255 on objects, 0 elsewhere) when rendered ``with_instance=False``
    (read back as one 4-byte attachment); ``rgb`` is then a view of it.
    """

    rgb: np.ndarray | None
    depth: np.ndarray | None
    instance: np.ndarray | None
    rgba: np.ndarray | None = None

    @property
    def mask(self) -> np.ndarray:
        """bool: any object visible."""
        return self.instance >= 0 if self.instance is not None else self.rgba[..., 3] > 0


def projection_matrix(K: np.ndarray, width: int, height: int, znear: float, zfar: float) -> np.ndarray:
    """OpenGL clip matrices (..., 4, 4) for OpenCV camera coordinates and intrinsics K (..., 3, 3).

    Pixel (u, v) = K-projection of a point (centres at integers) lands on window pixel
    (u + 0.5, v + 0.5) of a ``width`` x ``height`` viewport, with window row 0 = image row 0.
    Camera z in [znear, zfar] (same unit as the points) maps to NDC depth [-1, 1].
    """
    K = np.asarray(K, dtype=np.float64)
    P = np.zeros(K.shape[:-2] + (4, 4))
    P[..., 0, 0] = 2 * K[..., 0, 0] / width
    P[..., 0, 1] = 2 * K[..., 0, 1] / width
    P[..., 0, 2] = (2 * K[..., 0, 2] + 1) / width - 1
    P[..., 1, 1] = 2 * K[..., 1, 1] / height
    P[..., 1, 2] = (2 * K[..., 1, 2] + 1) / height - 1
    P[..., 2, 2] = (zfar + znear) / (zfar - znear)
    P[..., 2, 3] = -2 * zfar * znear / (zfar - znear)
    P[..., 3, 2] = 1.0
    return P


class _GpuMesh:
    """One object's vertex array (positions, normals, [uv], [colours]) and texture on the GPU."""

    def __init__(self, mesh, smooth: bool, default_color, cull: bool | None = None,
                 max_faces: int | None = MAX_RENDER_FACES):
        import pyrender
        import trimesh

        if not isinstance(mesh, trimesh.Trimesh):
            mesh = getattr(mesh, "mesh", mesh)  # an ObjectModel
        if not isinstance(mesh, trimesh.Trimesh):
            raise TypeError(f"expected a trimesh.Trimesh (vertices in mm), got {type(mesh).__name__}")
        if len(mesh.faces) == 0:
            raise ValueError("mesh has no faces")
        mesh = render_copy(mesh, max_faces)  # big meshes: a decimated copy, cached on disk
        if smooth and mesh.visual.kind == "face":
            smooth = False  # face colours need unmerged vertices
        if cull is None:
            # Back faces of a closed, consistently outward-wound surface are never visible: cull them
            # (halves llvmpipe's triangle setup, its bottleneck). Open or inconsistent meshes: two-sided.
            # Checked with vertices merged by position (files split vertices along UV/colour seams).
            closed = trimesh.Trimesh(mesh.vertices, mesh.faces, process=True)
            cull = bool(closed.is_watertight and closed.is_winding_consistent and closed.volume > 0)
        self.cull = bool(cull)
        self.pyrender_mesh = pyrender.Mesh.from_trimesh(mesh, smooth=smooth)
        prim = self.pyrender_mesh.primitives[0]
        material = prim.material
        texture = getattr(material, "baseColorTexture", None)
        if prim.texcoord_0 is None:
            texture = None
        self.texture = texture
        self.has_colors = prim.color_0 is not None
        if not mesh.visual.defined:
            self.base_color = (*map(float, default_color), 1.0)
        elif texture is not None or self.has_colors:
            # trimesh gives textured meshes a default diffuse of 0.4: take the texture as it is
            self.base_color = (1.0, 1.0, 1.0, 1.0)
        else:
            self.base_color = tuple(float(c) for c in np.asarray(material.baseColorFactor)[:4])

        attrs = [(0, prim.positions), (1, prim.normals), (2, prim.texcoord_0 if texture is not None else None),
                 (3, prim.color_0)]
        attrs = [(loc, np.asarray(a, dtype=np.float32).reshape(len(prim.positions), -1))
                 for loc, a in attrs if a is not None]
        data = np.ascontiguousarray(np.hstack([a for _, a in attrs]), dtype=np.float32)
        self.vao = gl.glGenVertexArrays(1)
        gl.glBindVertexArray(self.vao)
        self.buffers = [gl.glGenBuffers(1)]
        gl.glBindBuffer(gl.GL_ARRAY_BUFFER, self.buffers[0])
        gl.glBufferData(gl.GL_ARRAY_BUFFER, data.nbytes, data, gl.GL_STATIC_DRAW)
        offset = 0
        for loc, a in attrs:
            gl.glVertexAttribPointer(loc, a.shape[1], gl.GL_FLOAT, gl.GL_FALSE, data.shape[1] * 4,
                                     ctypes.c_void_p(offset))
            gl.glEnableVertexAttribArray(loc)
            offset += a.shape[1] * 4
        self.indexed = prim.indices is not None
        if self.indexed:
            idx = np.ascontiguousarray(prim.indices, dtype=np.uint32).ravel()
            self.buffers.append(gl.glGenBuffers(1))
            gl.glBindBuffer(gl.GL_ELEMENT_ARRAY_BUFFER, self.buffers[1])
            gl.glBufferData(gl.GL_ELEMENT_ARRAY_BUFFER, idx.nbytes, idx, gl.GL_STATIC_DRAW)
            self.count = idx.size
        else:
            self.count = len(prim.positions)
        gl.glBindVertexArray(0)
        if texture is not None:
            texture._add_to_context()

    def draw(self):
        if self.indexed:
            gl.glDrawElements(gl.GL_TRIANGLES, self.count, gl.GL_UNSIGNED_INT, None)
        else:
            gl.glDrawArrays(gl.GL_TRIANGLES, 0, self.count)

    def delete(self):
        gl.glDeleteVertexArrays(1, [self.vao])
        gl.glDeleteBuffers(len(self.buffers), self.buffers)
        if self.texture is not None:
            self.texture.delete()


class _Framebuffer:
    """Single-sample framebuffer: RGBA8 colour, R32F depth (mm), R32I instance, 32F z-buffer.
    Grows (never shrinks) to the largest region asked for."""

    FORMATS = (gl.GL_RGBA8, gl.GL_R32F, gl.GL_R32I)

    def __init__(self):
        self.fbo = None
        self.renderbuffers = []
        self.size = (0, 0)

    def ensure(self, width: int, height: int):
        if width <= self.size[0] and height <= self.size[1]:
            return
        width = -(-max(width, self.size[0]) // 16) * 16
        height = -(-max(height, self.size[1]) // 16) * 16
        limit = int(gl.glGetIntegerv(gl.GL_MAX_RENDERBUFFER_SIZE))
        if width > limit or height > limit:
            raise ValueError(f"{width} x {height} pixels exceeds this OpenGL's framebuffer limit ({limit})")
        self.delete()
        self.fbo = gl.glGenFramebuffers(1)
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self.fbo)
        self.renderbuffers = list(np.atleast_1d(gl.glGenRenderbuffers(4)))
        for i, (rb, fmt) in enumerate(zip(self.renderbuffers, self.FORMATS + (gl.GL_DEPTH_COMPONENT32F,))):
            gl.glBindRenderbuffer(gl.GL_RENDERBUFFER, rb)
            gl.glRenderbufferStorage(gl.GL_RENDERBUFFER, fmt, width, height)
            attachment = gl.GL_DEPTH_ATTACHMENT if i == 3 else gl.GL_COLOR_ATTACHMENT0 + i
            gl.glFramebufferRenderbuffer(gl.GL_FRAMEBUFFER, attachment, gl.GL_RENDERBUFFER, rb)
        status = gl.glCheckFramebufferStatus(gl.GL_FRAMEBUFFER)
        if status != gl.GL_FRAMEBUFFER_COMPLETE:
            raise RuntimeError(f"incomplete OpenGL framebuffer (status {status:#x})")
        self.size = (width, height)

    def delete(self):
        if self.fbo is not None:
            gl.glDeleteFramebuffers(1, [self.fbo])
            gl.glDeleteRenderbuffers(len(self.renderbuffers), self.renderbuffers)
        self.fbo, self.renderbuffers, self.size = None, [], (0, 0)


class SceneRenderer(Closing):
    """Renders posed instances of a fixed set of meshes (mm) with one headless OpenGL context.

    ``meshes``: obj_id -> trimesh.Trimesh (vertices in mm; vertex/face colours or a texture are
    used when present, else ``default_color``). ``width`` x ``height``: the default image size
    (any size can be asked per call). ``znear``/``zfar``: clipping planes in mm. ``smooth``:
    interpolated vertex normals (scanned meshes) instead of flat faces (CAD-like parts).
    ``cull_back_faces``: None (default) culls back faces of closed, outward-wound meshes (twice as
    fast on llvmpipe) and draws open ones two-sided; True/False forces it for every mesh.
    ``max_faces``: meshes with more faces are drawn from a decimated copy cached on disk
    (:func:`cosy_cli.rendering.decimate.render_copy`; None: always the full mesh).
    ``shading``: "pixel" (default: lighting per fragment) or "vertex" (lighting per vertex, fewer
    interpolated values: ~1.2-1.5x faster on llvmpipe; the same image to 1 grey level for flat
    shading, Gouraud shading with ``smooth``).

    Not thread-safe; one renderer per thread or process. Worker processes that render with EGL
    must be started with the ``spawn`` method (a forked EGL context is unusable).
    """

    def __init__(self, meshes: Mapping[int, object], width: int, height: int, *, znear: float = 10.0,
                 zfar: float = 10_000.0, smooth: bool = False, default_color=DEFAULT_COLOR,
                 cull_back_faces: bool | None = None, max_faces: int | None = MAX_RENDER_FACES,
                 shading: str = "pixel"):
        if not (0 < znear < zfar):
            raise ValueError(f"need 0 < znear < zfar (mm), got {znear}, {zfar}")
        if shading not in ("pixel", "vertex"):
            raise ValueError(f"shading must be 'pixel' or 'vertex', got {shading!r}")
        self.shading = shading
        self.width, self.height = int(width), int(height)
        self.znear, self.zfar = float(znear), float(zfar)
        self.smooth = smooth
        self.default_color = default_color
        self.cull_back_faces = cull_back_faces
        self.max_faces = max_faces
        self.platform = _PLATFORM
        self._closed = True
        patch_pyrender()  # other pyrender users in this process must not terminate our EGL display
        self._ctx, self._release = create_context(_PLATFORM)
        self._closed = False
        self.gl_renderer = " / ".join(gl.glGetString(e).decode() for e in (gl.GL_RENDERER, gl.GL_VERSION))
        self._program = self._compile()
        self._uniform = {name: gl.glGetUniformLocation(self._program, name) for name in _UNIFORMS}
        self._programs = {}  # name -> (program, uniforms) of the special-purpose programs, made on first use
        self._fb = _Framebuffer()
        self._fb.ensure(self.width, self.height)
        self._meshes: dict[int, _GpuMesh] = {}
        for obj_id, mesh in meshes.items():
            self.add_mesh(obj_id, mesh)

    # ------------------------------------------------------------------ public API

    @property
    def obj_ids(self) -> list[int]:
        return sorted(self._meshes)

    def add_mesh(self, obj_id: int, mesh) -> None:
        """Upload (or replace) the mesh of ``obj_id`` (trimesh.Trimesh in mm, or an ObjectModel)."""
        self._make_current()
        old = self._meshes.pop(int(obj_id), None)
        if old is not None:
            old.delete()
        self._meshes[int(obj_id)] = _GpuMesh(mesh, self.smooth, self.default_color, self.cull_back_faces,
                                             self.max_faces)

    def render(self, K, obj_ids: Sequence[int], T_cam_obj, *, colors=None, background=None, light_dir=None,
               light_intensity=None, ambient: float = 0.3, with_rgb: bool = True,
               size: tuple[int, int] | None = None) -> RenderOutput:
        """Render the instances ``obj_ids[i]`` at poses ``T_cam_obj[i]`` (n, 4, 4; mm) seen by K (3, 3).

        colors: None (each mesh's own colours) or (n, 3) RGB in 0..1 per instance (a flat albedo,
        still lit; a row of NaNs keeps that instance's own colours). background: None (black) or an
        (H, W, 3) uint8 image shown where no object is. light_dir: (3,) direction the light travels,
        in the camera frame (default (0, 0, 1): from the camera). light_intensity: directional
        light strength (default 1 - ambient); ambient: ambient light strength.
        size: (width, height) of this image, default the renderer's. Returns (H, W) maps.
        """
        w, h = self._size(size)
        K = self._check_K(K, None)
        ids, T = self._check_instances(obj_ids, T_cam_obj)
        n = len(ids)
        out = self._render_tiles(1, K[None], w, h, ids, T, np.zeros(n, dtype=np.int64), np.arange(n),
                                 self._check_colors(colors, n), self._lighting(light_dir, light_intensity, ambient),
                                 with_rgb=with_rgb)
        out = RenderOutput(None if out.rgb is None else out.rgb[0], out.depth[0], out.instance[0])
        if background is not None:
            bg = np.asarray(background)
            if bg.shape != (h, w, 3):
                raise ValueError(f"background must be ({h}, {w}, 3) uint8, got shape {bg.shape}")
            if out.rgb is not None:
                empty = out.instance < 0
                out.rgb[empty] = bg[empty]
        return out

    def render_silhouettes(self, K, obj_ids: Sequence[int], T_cam_obj, *,
                           size: tuple[int, int] | None = None) -> np.ndarray:
        """(n, H, W) bool: the pixels of each instance rendered alone (ignoring occlusion)."""
        w, h = self._size(size)
        K = self._check_K(K, None)
        ids, T = self._check_instances(obj_ids, T_cam_obj)
        n = len(ids)
        out = self._render_tiles(n, K[None], w, h, ids, T, np.arange(n), np.arange(n), None,
                                 self._lighting(None, None, 0.3), with_rgb=False, with_depth=False,
                                 K_per_tile=False)
        return out.instance >= 0

    def render_crops(self, K_crops, obj_ids: Sequence[int], T_cam_obj, size: tuple[int, int], *, colors=None,
                     light_dir=None, light_intensity=None, ambient: float = 0.3,
                     with_rgb: bool = True, tiles=None, with_depth: bool = True,
                     with_instance: bool = True) -> RenderOutput:
        """B images of ``size`` = (w, h), image b showing only instance b: K_crops (B, 3, 3)
        (e.g. from :func:`cosy_cli.geometry.crop_intrinsics`), obj_ids (B,), T_cam_obj (B, 4, 4) mm.
        Returns rgb (B, h, w, 3), depth (B, h, w), instance (B, h, w) (= b on the object, -1 elsewhere).
        Lighting and colours as in :meth:`render` (colors: (B, 3)).

        tiles: optional (n,) non-decreasing image index of each of n instances, to draw several
        instances (with occlusion) into one image: then K_crops has one row per image (at least
        max(tiles) + 1; images without instances come out empty) and ``instance`` holds the index
        i into ``obj_ids`` of the visible instance. with_depth=False: ``depth`` is None (not read back).
        with_instance=False (needs with_rgb): ``instance`` is None; ``rgba`` (B, h, w, 4) holds the
        colours and alpha 255 on objects (``mask``), read back as one attachment (faster)."""
        w, h = self._size(size)
        ids, T = self._check_instances(obj_ids, T_cam_obj)
        n = len(ids)
        if tiles is None:
            tile_of, n_tiles = np.arange(n), n
        else:
            tile_of = np.asarray(tiles, dtype=np.int64).reshape(-1)
            if tile_of.shape != (n,) or (n and (tile_of[0] < 0 or np.any(np.diff(tile_of) < 0))):
                raise ValueError(f"tiles must be ({n},) non-decreasing indices >= 0")
            n_tiles = int(tile_of[-1]) + 1 if n else 0
            if len(np.asarray(K_crops).reshape(-1, 3, 3)) != n_tiles:
                n_tiles = len(np.asarray(K_crops).reshape(-1, 3, 3))
                if n and tile_of[-1] >= n_tiles:
                    raise ValueError(f"tiles reach image {tile_of[-1]} but K_crops has {n_tiles} rows")
        K = self._check_K(K_crops, n_tiles)
        if not with_instance and not with_rgb:
            raise ValueError("with_instance=False needs with_rgb=True (the mask is the colour's alpha)")
        return self._render_tiles(n_tiles, K, w, h, ids, T, tile_of, np.arange(n), self._check_colors(colors, n),
                                  self._lighting(light_dir, light_intensity, ambient), with_rgb=with_rgb,
                                  with_depth=with_depth, with_instance=with_instance)

    def close(self) -> None:
        """Free the GPU meshes, framebuffer and OpenGL context. Idempotent."""
        if self._closed:
            return
        try:
            self._make_current()
            for m in self._meshes.values():
                m.delete()
            self._fb.delete()
            gl.glDeleteProgram(self._program)
            for prog, _ in self._programs.values():
                gl.glDeleteProgram(prog)
        finally:
            self._meshes = {}
            self._closed = True
            self._release()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass

    # ------------------------------------------------------------------ internals

    def _make_current(self):
        if self._closed:
            raise RuntimeError("this SceneRenderer is closed")
        self._ctx.make_current()  # ~10 us; other renderers (ours or pyrender's) may have switched

    def _special_program(self, name, vs, fs):
        if name not in self._programs:
            prog = self._compile(vs, fs)
            self._programs[name] = (prog, {k: gl.glGetUniformLocation(prog, k) for k in _UNIFORMS})
        return self._programs[name]

    def _compile(self, vs=None, fs=None):
        vao = gl.glGenVertexArrays(1)  # core profiles validate programs against a bound VAO
        gl.glBindVertexArray(vao)
        if vs is None:
            vertex = self.shading == "vertex"
            vs, fs = (_VERTEX_LIT_VS, _VERTEX_LIT_FS) if vertex else (_VERTEX_SHADER, _FRAGMENT_SHADER)
        program = gl_shaders.compileProgram(gl_shaders.compileShader(vs, gl.GL_VERTEX_SHADER),
                                            gl_shaders.compileShader(fs, gl.GL_FRAGMENT_SHADER))
        gl.glBindVertexArray(0)
        gl.glDeleteVertexArrays(1, [vao])
        return program

    def _size(self, size):
        w, h = (self.width, self.height) if size is None else (int(size[0]), int(size[1]))
        if w <= 0 or h <= 0:
            raise ValueError(f"image size must be positive, got {w} x {h}")
        return w, h

    @staticmethod
    def _check_K(K, n):
        K = np.asarray(K, dtype=np.float64)
        want = (3, 3) if n is None else (n, 3, 3)
        if K.shape != want:
            raise ValueError(f"K must have shape {want}, got {K.shape}")
        return K

    def _check_instances(self, obj_ids, T_cam_obj):
        ids = [int(i) for i in np.asarray(obj_ids).reshape(-1)]
        T = np.asarray(T_cam_obj, dtype=np.float64)
        if T.shape != (len(ids), 4, 4):
            raise ValueError(f"T_cam_obj must be ({len(ids)}, 4, 4) for {len(ids)} obj_ids, got {T.shape}")
        unknown = sorted(set(ids) - set(self._meshes))
        if unknown:
            raise KeyError(f"no mesh for obj_id(s) {unknown} in this renderer (it has {self.obj_ids})")
        return ids, T

    @staticmethod
    def _check_colors(colors, n):
        if colors is None:
            return None
        c = np.asarray(colors)
        if c.shape != (n, 3):
            raise ValueError(f"colors must be ({n}, 3) RGB in 0..1, got shape {c.shape}")
        c = c.astype(np.float64) / 255.0 if np.issubdtype(c.dtype, np.integer) else c.astype(np.float64)
        return c

    @staticmethod
    def _lighting(light_dir, light_intensity, ambient):
        d = np.array([0.0, 0.0, 1.0]) if light_dir is None else np.asarray(light_dir, dtype=np.float64).reshape(3)
        norm = np.linalg.norm(d)
        if not norm > 0:
            raise ValueError("light_dir must be a non-zero 3-vector")
        intensity = max(0.0, 1.0 - ambient) if light_intensity is None else float(light_intensity)
        return d / norm, intensity, float(ambient)

    def _render_tiles(self, n_tiles, Ks, w, h, ids, T, tile_of, instance_value, colors, lighting, *,
                      with_rgb=True, with_depth=True, K_per_tile=True, with_instance=True) -> RenderOutput:
        """Draw instance i into tile ``tile_of[i]`` (non-decreasing) with instance value
        ``instance_value[i]``; tile t uses Ks[t] (or Ks[0] for all if not K_per_tile).
        Returns (n_tiles, h, w) maps (depth None if not with_depth; without with_instance, instance
        is None and the colour is read back as RGBA)."""
        self._make_current()
        side = max(MAX_ATLAS_SIDE, w, h)
        cols_max, rows_max = max(1, side // w), max(1, side // h)
        per_chunk = cols_max * rows_max
        Ps = projection_matrix(Ks, w, h, self.znear, self.zfar).astype(np.float32)
        new_P = np.any(Ps[1:] != Ps[:-1], axis=(1, 2))  # tile t + 1's projection differs from tile t's
        p_tile = -1
        # column-major float32 model-view matrices for glUniformMatrix4fv
        MV = np.ascontiguousarray(np.swapaxes(T, -1, -2), dtype=np.float32)
        rgba = None if with_instance or not with_rgb else np.empty((n_tiles, h, w, 4), np.uint8)
        rgb = None if not with_rgb else rgba[..., :3] if rgba is not None else np.empty((n_tiles, h, w, 3), np.uint8)
        depth = np.empty((n_tiles, h, w), np.float32) if with_depth else None
        inst = np.empty((n_tiles, h, w), np.int32) if with_instance else None
        bounds = np.searchsorted(tile_of, np.arange(0, n_tiles + per_chunk, per_chunk))

        program, u = self._program, self._uniform
        if not with_rgb:  # nothing but depth to interpolate: the cheapest program (same depth and instances)
            program, u = self._special_program("mask", _MASK_VS, _MASK_FS)
        elif self.shading == "vertex" and not with_depth and colors is None and \
                not any(self._meshes[i].texture is not None for i in set(ids)):  # the same colours
            program, u = self._special_program("vertex_rgb", _VERTEX_LIT_RGB_VS, _VERTEX_LIT_RGB_FS)
        gl.glUseProgram(program)
        light_dir, intensity, ambient = lighting
        gl.glUniform3f(u["light_dir"], *map(float, light_dir))
        gl.glUniform2f(u["light"], intensity, ambient)
        gl.glUniform1i(u["base_texture"], 0)
        gl.glActiveTexture(gl.GL_TEXTURE0)
        gl.glEnable(gl.GL_DEPTH_TEST)
        gl.glDepthFunc(gl.GL_LESS)
        gl.glDepthMask(gl.GL_TRUE)
        gl.glCullFace(gl.GL_BACK)
        gl.glFrontFace(_FRONT_FACE)
        gl.glDisable(gl.GL_BLEND)
        gl.glEnable(gl.GL_SCISSOR_TEST)
        if not K_per_tile:
            gl.glUniformMatrix4fv(u["P"], 1, gl.GL_TRUE, Ps[0])

        for c, t0 in enumerate(range(0, n_tiles, per_chunk)):
            m = min(per_chunk, n_tiles - t0)
            cols = min(m, cols_max)
            rows = -(-m // cols)
            W, H = cols * w, rows * h
            self._fb.ensure(W, H)
            gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self._fb.fbo)
            # outputs not asked for are neither written nor cleared
            gl.glDrawBuffers(3, [gl.GL_COLOR_ATTACHMENT0 if with_rgb else gl.GL_NONE,
                                 gl.GL_COLOR_ATTACHMENT1 if with_depth else gl.GL_NONE,
                                 gl.GL_COLOR_ATTACHMENT2 if with_instance else gl.GL_NONE])
            gl.glScissor(0, 0, W, H)
            if with_rgb:
                gl.glClearBufferfv(gl.GL_COLOR, 0, _ZEROS4)
            if with_depth:
                gl.glClearBufferfv(gl.GL_COLOR, 1, _ZEROS4)
            if with_instance:
                gl.glClearBufferiv(gl.GL_COLOR, 2, _MINUS_ONE4)
            gl.glClearBufferfv(gl.GL_DEPTH, 0, _ONES4)
            tile = -1
            culling = False
            gl.glDisable(gl.GL_CULL_FACE)
            last_mesh, last_state, last_tex = None, (None, None), None
            for i in range(bounds[c], bounds[c + 1]):
                if tile_of[i] != tile:
                    tile = int(tile_of[i])
                    k = tile - t0
                    x0, y0 = (k % cols) * w, (k // cols) * h
                    gl.glViewport(x0, y0, w, h)
                    gl.glScissor(x0, y0, w, h)
                    if K_per_tile and (p_tile < 0 or (new_P[tile - 1] if p_tile == tile - 1
                                                     else not np.array_equal(Ps[tile], Ps[p_tile]))):
                        gl.glUniformMatrix4fv(u["P"], 1, gl.GL_TRUE, Ps[tile])
                    p_tile = tile  # the uniform holds Ps[p_tile] (or an equal matrix)
                mesh = self._meshes[ids[i]]
                if mesh.cull != culling:
                    culling = mesh.cull
                    (gl.glEnable if culling else gl.glDisable)(gl.GL_CULL_FACE)
                if mesh is not last_mesh:
                    gl.glBindVertexArray(mesh.vao)
                gl.glUniformMatrix4fv(u["MV"], 1, gl.GL_FALSE, MV[i])
                inst_value = int(instance_value[i]) if with_instance else 0
                use_tex = False
                if colors is not None and not np.isnan(colors[i]).any():
                    state = ((*map(float, colors[i]), 1.0), (0, 0, inst_value))
                else:
                    use_tex = mesh.texture is not None
                    state = (mesh.base_color, (int(mesh.has_colors), int(use_tex), inst_value))
                # consecutive instances of one mesh (hypotheses of one detection) share these: not resent
                if state[0] != last_state[0]:
                    gl.glUniform4f(u["base_color"], *state[0])
                if state[1] != last_state[1]:
                    gl.glUniform3i(u["flags"], *state[1])
                if use_tex and mesh.texture is not last_tex:
                    mesh.texture._bind()
                    last_tex = mesh.texture
                last_mesh, last_state = mesh, state
                mesh.draw()
            gl.glBindVertexArray(0)

            sl = slice(t0, t0 + m)
            gl.glPixelStorei(gl.GL_PACK_ALIGNMENT, 1)
            if rgba is not None:  # the native format: a plain copy (RGB is converted per pixel)
                rgba[sl] = _untile(self._read(0, W, H, gl.GL_RGBA, gl.GL_UNSIGNED_BYTE, np.uint8, 4),
                                   m, rows, cols, h, w)
            elif with_rgb:
                rgb[sl] = _untile(self._read(0, W, H, gl.GL_RGB, gl.GL_UNSIGNED_BYTE, np.uint8, 3), m, rows, cols, h, w)
            if with_depth:
                depth[sl] = _untile(self._read(1, W, H, gl.GL_RED, gl.GL_FLOAT, np.float32, 1), m, rows, cols, h, w)
            if with_instance:
                inst[sl] = _untile(self._read(2, W, H, gl.GL_RED_INTEGER, gl.GL_INT, np.int32, 1), m, rows, cols, h, w)
        gl.glDisable(gl.GL_SCISSOR_TEST)
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, 0)
        return RenderOutput(rgb, depth, inst, rgba)

    @staticmethod
    def _read(attachment, W, H, fmt, typ, dtype, channels):
        buf = np.empty((H, W, channels) if channels > 1 else (H, W), dtype)
        gl.glReadBuffer(gl.GL_COLOR_ATTACHMENT0 + attachment)
        gl.glReadPixels(0, 0, W, H, fmt, typ, buf)
        return buf


# Our projection keeps image rows in window order (y down), which mirrors the window: triangles
# wound counter-clockwise seen from outside (trimesh's convention) appear clockwise.
_FRONT_FACE = gl.GL_CW
_ZEROS4 = np.zeros(4, np.float32)
_ONES4 = np.ones(4, np.float32)
_MINUS_ONE4 = np.full(4, -1, np.int32)


def _untile(atlas: np.ndarray, m: int, rows: int, cols: int, h: int, w: int) -> np.ndarray:
    """(rows*h, cols*w, ...) atlas, tile k at block (k // cols, k % cols) -> (m, h, w, ...)."""
    if rows == 1 and cols == 1:
        return atlas[None]
    rest = atlas.shape[2:]
    tiles = atlas.reshape((rows, h, cols, w) + rest).swapaxes(1, 2).reshape((rows * cols, h, w) + rest)
    return tiles[:m]

