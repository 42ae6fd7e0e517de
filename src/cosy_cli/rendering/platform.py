"""Choosing and creating the headless OpenGL platform (EGL or OSMesa) for pyrender.

PyOpenGL binds its platform (``PYOPENGL_PLATFORM``) once, the first time ``OpenGL`` is imported,
so :func:`select_gl_platform` must run before ``pyrender`` or ``OpenGL`` is imported anywhere in
the process. ``cosy_cli.rendering`` calls it on import; import it before anything that pulls in
pyrender/OpenGL.

- ``COSY_GL=egl`` (default): EGL without a display (Mesa's llvmpipe on a CPU, the vendor
  driver on a GPU; ``EGL_DEVICE_ID`` picks a device, default 0). Needs the system packages
  ``libegl1 libegl-mesa0 libgl1-mesa-dri``. Sets ``PYGLET_HEADLESS=true`` unless it is set: pyrender
  imports pyglet, which otherwise needs X11 libraries.
- ``COSY_GL=osmesa``: the fallback, Mesa's off-screen software renderer. Needs ``libosmesa6``
  and ``PyOpenGL>=3.1.4`` (pyrender pins 3.1.0: install the newer one after pyrender).

Without ``COSY_GL``, an existing ``PYOPENGL_PLATFORM`` of ``egl`` or ``osmesa`` is respected;
any other value is replaced by ``egl`` (cosy never opens windows).
"""

from __future__ import annotations

import ctypes
import functools
import os
import sys

from ..errors import CosyError

PLATFORMS = ("egl", "osmesa")


def select_gl_platform() -> str:
    """Set ``PYOPENGL_PLATFORM`` from ``COSY_GL`` (before OpenGL is imported); returns it.

    Raises :class:`CosyError` for an unknown ``COSY_GL`` or when OpenGL was already imported
    with a different platform (too late to switch in this process).
    """
    want = os.environ.get("COSY_GL", "").strip().lower()
    current = os.environ.get("PYOPENGL_PLATFORM", "").strip().lower()
    if want and want not in PLATFORMS:
        raise CosyError(f"COSY_GL={os.environ['COSY_GL']!r} is not a headless OpenGL platform: "
                        f"expected one of {', '.join(PLATFORMS)}")
    if not want:
        want = current if current in PLATFORMS else "egl"
    if "OpenGL.platform" in sys.modules and current != want:
        raise CosyError(f"OpenGL was imported with PYOPENGL_PLATFORM={current or '(unset)'} before "
                        f"cosy_cli.rendering could select {want!r}: import cosy_cli.rendering first, "
                        f"or set PYOPENGL_PLATFORM={want} in the environment")
    os.environ["PYOPENGL_PLATFORM"] = want
    if want == "egl":
        # pyrender imports pyglet, whose default (windowed) mode loads X11 libraries that a GPU
        # server may not have ('XRenderFindVisualFormat'); its headless mode uses EGL alone
        os.environ.setdefault("PYGLET_HEADLESS", "true")
    return want


def egl_delete_context_keep_display(self) -> None:
    """``delete_context`` for pyrender's EGLPlatform that destroys the context only: pyrender's
    own also ``eglTerminate``s the display, which is shared by every EGL context of the process."""
    from OpenGL import EGL

    if getattr(self, "_egl_context", None) is not None:
        address = lambda p: ctypes.cast(p, ctypes.c_void_p).value  # noqa: E731
        if address(EGL.eglGetCurrentContext()) == address(self._egl_context):
            EGL.eglMakeCurrent(self._egl_display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, EGL.EGL_NO_CONTEXT)
        EGL.eglDestroyContext(self._egl_display, self._egl_context)
        self._egl_context = None


@functools.cache  # every renderer asks; the answer is the process's
def load_triton_first() -> bool:
    """Load triton's native library now, before Mesa's software rasteriser loads its LLVM, when
    triton is installed (it comes with torch's CUDA builds, also on machines without a GPU).
    Both carry their own LLVM: triton loaded after an EGL/OSMesa context exists segfaults the
    process (seen with torch 2.14.1+cu130 and Mesa 22.3's llvmpipe: the first ``torch.optim``
    optimiser or ``torch.compile`` imports ``torch._dynamo``, which imports triton); loaded
    before, both work. Returns whether triton is loaded. Without triton (torch's CPU builds):
    nothing to do."""
    if "triton" in sys.modules:
        return True
    import importlib.util

    try:
        if importlib.util.find_spec("triton") is None:
            return False
        import triton  # noqa: F401
    except Exception:  # a broken triton is torch's problem, not rendering's: its import would fail later anyway
        return False
    return True


def create_context(platform: str):
    """A current headless OpenGL context: ``(platform_object, release_function)``.

    The context renders into framebuffer objects only, so its own surface is 1 x 1. Releasing an
    EGL context destroys it but (unlike pyrender's EGL platform) does not ``eglTerminate`` the
    display, which would break every other live context of the process. Loads triton first where
    it is installed (:func:`load_triton_first`).
    """
    load_triton_first()
    if platform == "egl":
        try:
            from pyrender.platforms import egl

            class _EGLContext(egl.EGLPlatform):
                delete_context = egl_delete_context_keep_display

            device = egl.get_device_by_index(int(os.environ.get("EGL_DEVICE_ID", "0")))
            ctx = _EGLContext(1, 1, device=device)
            ctx.init_context()
            ctx.make_current()
        except Exception as e:  # EGL reports failures as assorted exception types
            raise CosyError(f"cannot create a headless EGL OpenGL context ({type(e).__name__}: {e}); "
                            "install libegl1 libegl-mesa0 libgl1-mesa-dri, or set COSY_GL=osmesa "
                            "(needs libosmesa6 and PyOpenGL>=3.1.4)") from None
        return ctx, ctx.delete_context
    if platform == "osmesa":
        try:
            from pyrender.platforms.osmesa import OSMesaPlatform

            ctx = OSMesaPlatform(1, 1)
            ctx.init_context()
            ctx.make_current()
        except Exception as e:
            raise CosyError(f"cannot create an OSMesa OpenGL context ({type(e).__name__}: {e}); "
                            "install libosmesa6 and PyOpenGL>=3.1.4, or use COSY_GL=egl") from None

        return ctx, ctx.delete_context
    raise CosyError(f"unknown OpenGL platform {platform!r}: expected one of {', '.join(PLATFORMS)}")
