"""Two process-wide fixes to pyrender (0.1.45) for code that uses its own renderers.

1. Exact depth. pyrender renders off-screen into a 4x multisampled framebuffer and blits it into
   a single-sample one: colours *and depth* are blended along silhouettes (a pixel on an edge gets
   a depth between the object and what is behind it) and rendering is 2-5x slower on llvmpipe.
   The patch replaces the ``glRenderbufferStorageMultisample`` name in ``pyrender.renderer`` (the
   only place pyrender allocates multisampled storage) by a wrapper asking for 0 samples, which
   OpenGL defines as ordinary single-sample storage; the blit that follows copies pixels one to
   one, so depth is the exact z-buffer value.
2. Shared EGL display. Deleting a ``pyrender.OffscreenRenderer`` (or garbage-collecting its
   platform) calls ``eglTerminate`` on the process-wide EGL display, which destroys every other
   EGL context of the process, :class:`~cosy_cli.rendering.SceneRenderer`'s included. The patch
   makes pyrender's EGL platform destroy only its own context.

:class:`~cosy_cli.rendering.SceneRenderer` does not use pyrender's framebuffers (it has its own,
single-sample); it applies this patch when created, for the second fix. Idempotent.
"""

from __future__ import annotations

from .platform import egl_delete_context_keep_display, load_triton_first, select_gl_platform


def patch_pyrender() -> None:
    """Apply both fixes (see the module docstring) once per process; also loads triton before any
    GL context where it is installed (:func:`~cosy_cli.rendering.platform.load_triton_first`)."""
    platform = select_gl_platform()
    load_triton_first()
    import pyrender.renderer as pr

    if getattr(pr, "_cosy_patched", False):
        return
    original = pr.glRenderbufferStorageMultisample

    def storage_single_sample(target, samples, internalformat, width, height):
        return original(target, 0, internalformat, width, height)

    pr.glRenderbufferStorageMultisample = storage_single_sample
    if platform == "egl":
        from pyrender.platforms import egl

        egl.EGLPlatform.delete_context = egl_delete_context_keep_display
    pr._cosy_patched = True
