"""Headless rendering of posed object meshes: RGB, exact depth (mm) and instance maps.

    from cosy_cli.rendering import SceneRenderer
    with SceneRenderer({1: mesh_mm}, 640, 480) as r:
        out = r.render(K, [1], T_cam_obj[None])          # out.rgb, out.depth (mm), out.instance
        masks = r.render_silhouettes(K, [1], T_cam_obj[None])
        crops = r.render_crops(K_crops, ids, T_cam_objs, size=(128, 96))

OpenGL platform. Rendering is off-screen through pyrender's headless platforms, chosen by the
environment variable ``COSY_GL``:

- ``COSY_GL=egl`` (default): EGL without a display (Mesa llvmpipe on CPUs; system packages
  ``libegl1 libegl-mesa0 libgl1-mesa-dri``; ``EGL_DEVICE_ID`` selects a GPU).
- ``COSY_GL=osmesa``: fallback, Mesa OSMesa (``libosmesa6`` and ``PyOpenGL>=3.1.4``).

It is copied into ``PYOPENGL_PLATFORM``, which PyOpenGL reads once, when ``OpenGL`` is first
imported: importing this package does that, so import ``cosy_cli.rendering`` before pyrender or
OpenGL (otherwise a :class:`~cosy_cli.errors.CosyError` says what to do). Without ``COSY_GL`` an
existing ``PYOPENGL_PLATFORM=egl|osmesa`` is kept.

Worker processes that render must be started with the ``spawn`` method
(``multiprocessing.get_context("spawn")``): an EGL context does not survive ``fork``. Create the
renderer inside the worker. On a CPU, Mesa's llvmpipe rasterises with one thread per core
(``LP_NUM_THREADS``); with as many rendering workers as cores, set ``LP_NUM_THREADS=1`` (or 0: no
extra threads) in the workers' environment to avoid oversubscription.

No multisampling anywhere: depth is the exact depth of the visible surface at each pixel centre,
never a blend across a silhouette. :func:`patch_pyrender` gives the same to code that uses
``pyrender.OffscreenRenderer`` directly (pyrender's default is a 4x multisampled framebuffer) and
stops pyrender's EGL platform from terminating the process-wide EGL display when it is deleted
(which kills every other context); creating a :class:`SceneRenderer` applies it.
"""

from .platform import select_gl_platform

select_gl_platform()

from .pyrender_patch import patch_pyrender  # noqa: E402
from .decimate import MAX_RENDER_FACES, render_copy  # noqa: E402
from .renderer import DEFAULT_COLOR, RenderOutput, SceneRenderer, projection_matrix  # noqa: E402

__all__ = ["SceneRenderer", "RenderOutput", "projection_matrix", "patch_pyrender",
           "select_gl_platform", "DEFAULT_COLOR", "MAX_RENDER_FACES", "render_copy"]
