"""``cosy doctor``: what this installation is and whether it can work here.

The versions of cosy, Python and the libraries its results depend on (and, in a source checkout,
where they differ from ``requirements/lock.txt``, the versions the tests passed with), the threads
each numeric library will use, onnxruntime's execution providers, and the OpenGL platform that
rendering will use, checked with a real render of one triangle. Paste its output into a problem
report. Rendering that cannot work is the one failure: the stages need it.
"""

from __future__ import annotations

import os
import platform
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from . import __version__

# The distributions whose versions decide cosy's results, as pip names them.
KEY_PACKAGES = ("numpy", "scipy", "torch", "onnxruntime", "onnx", "opencv-python-headless", "pyrender",
                "PyOpenGL", "trimesh", "pandas", "pillow", "click", "matplotlib", "pycocotools",
                "efficientnet-pytorch", "manifold3d", "fast-simplification")
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_WAIT_POLICY", "LP_NUM_THREADS")
GL_ENV = ("COSY_GL", "PYOPENGL_PLATFORM", "EGL_DEVICE_ID")


@dataclass
class Report:
    """Lines of the report (``(topic, text)``) and the reason rendering cannot work ("" when it can)."""

    lines: list = field(default_factory=list)
    render_problem: str = ""

    def add(self, topic: str, text: str) -> None:
        self.lines.append((topic, text))

    def text(self) -> str:
        width = max((len(t) for t, _ in self.lines), default=0)
        return "\n".join(f"{t:<{width}}  {x}" for t, x in self.lines)


def _canonical(name: str) -> str:
    return name.lower().replace("_", "-").replace(".", "-")


def installed_versions(names=KEY_PACKAGES) -> dict:
    """{pip name: installed version, or None when it is not installed}."""
    from importlib import metadata

    out = {}
    for n in names:
        try:
            out[n] = metadata.version(n)
        except metadata.PackageNotFoundError:
            out[n] = None
    return out


def read_lock(path: str | Path) -> dict:
    """{canonical pip name: version} of a lock file of ``name==version`` lines (comments skipped)."""
    pins = {}
    for line in Path(path).read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if "==" in line:
            name, version = line.split("==", 1)
            pins[_canonical(name.split("[", 1)[0].strip())] = version.strip()
    return pins


def source_lock() -> Path | None:
    """requirements/lock.txt of the source checkout cosy runs from (an editable install), if any."""
    p = Path(__file__).resolve().parents[2] / "requirements" / "lock.txt"
    return p if p.is_file() else None


def lock_differences(lock: Path) -> list[str]:
    """'name installed X, locked Y' for each installed distribution whose version differs from the
    lock (local labels such as +cpu ignored), and the locked ones that are missing."""
    from importlib import metadata

    pins = read_lock(lock)
    have = {}
    for d in metadata.distributions():
        name = d.metadata.get("Name")
        if name:
            have[_canonical(name)] = d.version
    out = []
    for name, want in sorted(pins.items()):
        got = have.get(name)
        if got is None:
            out.append(f"{name} missing (locked {want})")
        elif got.split("+", 1)[0] != want.split("+", 1)[0]:
            out.append(f"{name} {got} (locked {want})")
    return out


def render_check(size=(64, 48)) -> tuple[str, str]:
    """Render one triangle 500 mm in front of the camera and check its depth: ("GL renderer /
    version, time", "") when it works, ("", one-line reason) when it does not."""
    import numpy as np

    from .errors import CosyError

    try:
        import trimesh

        from .rendering import SceneRenderer

        w, h = size
        K = np.array([[60.0, 0, w / 2], [0, 60.0, h / 2], [0, 0, 1]])
        tri = trimesh.Trimesh(vertices=[[-40.0, -40.0, 0], [40.0, -40.0, 0], [0.0, 40.0, 0]], faces=[[0, 1, 2], [0, 2, 1]],
                              process=False)
        T = np.eye(4)
        T[2, 3] = 500.0
        t0 = time.perf_counter()
        with SceneRenderer({1: tri}, w, h, max_faces=None, cull_back_faces=False) as r:
            out = r.render(K, [1], T[None])
            gl = r.gl_renderer
        ms = 1e3 * (time.perf_counter() - t0)
    except CosyError as e:
        return "", str(e)
    except Exception as e:  # a broken driver or GL library raises its own types
        return "", f"rendering failed ({type(e).__name__}: {' '.join(str(e).split())})"
    z = float(out.depth[h // 2, w // 2])
    if abs(z - 500.0) > 0.5 or not out.rgb[h // 2, w // 2].any() or out.depth[0, 0] != 0:
        return "", (f"rendering runs but draws wrongly: a triangle 500 mm away rendered at depth {z:.1f} mm "
                    f"({gl})")
    return f"{gl}; a test triangle rendered right ({ms:.0f} ms with context creation)", ""


def report(render: bool = True) -> Report:
    """Everything ``cosy doctor`` prints."""
    rep = Report()
    here = Path(__file__).resolve().parent
    rep.add("cosy", f"{__version__} ({here})")
    rep.add("python", f"{platform.python_version()} ({platform.python_implementation()}, {sys.executable})")
    rep.add("system", f"{platform.system()} {platform.release()} {platform.machine()}"
                      + (f", {platform.libc_ver()[0]} {platform.libc_ver()[1]}" if platform.libc_ver()[0] else ""))
    versions = installed_versions()
    rep.add("packages", ", ".join(f"{n} {v or 'NOT INSTALLED'}" for n, v in versions.items()))
    lock = source_lock()
    if lock is not None:
        diff = lock_differences(lock)
        rep.add("lock", f"{lock.name}: all {len(read_lock(lock))} locked versions installed" if not diff else
                f"{lock.name}: {len(diff)} differ from the tested versions: {'; '.join(diff[:12])}"
                + (" ..." if len(diff) > 12 else ""))
    else:
        rep.add("lock", "none (not a source checkout): versions as listed above")
    try:
        n_aff = len(os.sched_getaffinity(0))
    except AttributeError:
        n_aff = os.cpu_count()
    env = ", ".join(f"{k}={os.environ[k]}" for k in THREAD_ENV if k in os.environ) or "no thread variables set"
    rep.add("cpu", f"{os.cpu_count()} logical cores, {n_aff} usable by this process; {env}")
    try:
        import torch

        cuda = torch.cuda.is_available()
        rep.add("torch", f"{torch.__version__}: {torch.get_num_threads()} intra-op / {torch.get_num_interop_threads()} "
                         f"inter-op threads; CUDA {'available (' + torch.cuda.get_device_name(0) + ')' if cuda else 'not available'}")
    except Exception as e:
        rep.add("torch", f"cannot be imported ({type(e).__name__}: {e})")
    try:
        import onnxruntime as ort

        rep.add("onnxruntime", f"{ort.__version__}: providers {', '.join(ort.get_available_providers())}")
    except Exception as e:
        rep.add("onnxruntime", f"cannot be imported ({type(e).__name__}: {e})")
    try:
        import cv2

        rep.add("opencv", f"{cv2.__version__}: {cv2.getNumThreads()} threads")
    except Exception as e:
        rep.add("opencv", f"cannot be imported ({type(e).__name__}: {e})")
    try:
        from threadpoolctl import threadpool_info

        pools = [f"{p.get('internal_api')} {p.get('version')} ({p.get('num_threads')} threads)" for p in threadpool_info()]
        rep.add("blas/openmp", ", ".join(pools) or "none loaded")
    except Exception as e:
        rep.add("blas/openmp", f"unknown ({type(e).__name__}: {e})")
    gl_env = ", ".join(f"{k}={os.environ[k]}" for k in GL_ENV if k in os.environ) or "defaults"
    if render:
        ok, problem = render_check()
        rep.render_problem = problem
        rep.add("rendering", f"{os.environ.get('PYOPENGL_PLATFORM', '?')} ({gl_env}): " + (ok or f"FAILS: {problem}"))
    else:
        rep.add("rendering", f"{os.environ.get('COSY_GL') or os.environ.get('PYOPENGL_PLATFORM') or 'egl'} "
                             f"({gl_env}): not checked")
    return rep
