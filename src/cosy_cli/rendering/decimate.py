"""Decimated copies of big meshes, for rendering only, cached on disk.

Rendering time on a CPU (Mesa llvmpipe) grows with the number of triangles, and a scanned model
of a million faces looks the same at crop resolution as one of 100k. :func:`render_copy` gives
the renderer a copy with at most ``max_faces`` faces (quadric edge collapse, ``fast-simplification``)
that keeps vertex colours, face colours, or UVs and the texture image. Metrics, sampled points and
everything else keep the original mesh: only :class:`~cosy_cli.rendering.SceneRenderer` calls this.

The copy is cached under ``$COSY_CACHE_DIR/meshes`` (default ``$XDG_CACHE_HOME/cosy/meshes``,
else ``~/.cache/cosy/meshes``) as ``<sha1 of the mesh's arrays>.npz``, written atomically, so the
decimation runs once per mesh and machine; in a process it is also kept in memory. The first use
of a decimated copy in a process says so once, an internal step shown with --verbose only
(:func:`cosy_cli.console.info`).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

MAX_RENDER_FACES = 100_000  # meshes with more faces are rendered from a decimated copy
_VERSION = b"cosy-render-copy-3"
_memo: dict[str, object] = {}


def cache_dir() -> Path:
    """Where decimated copies are kept (created on first write)."""
    from ..io.cache import user_cache_dir

    return user_cache_dir("meshes")


def _visual_arrays(mesh) -> dict[str, np.ndarray]:
    """The per-vertex / per-face attributes the renderer draws: uv, vertex or face colours."""
    vis = mesh.visual
    if vis.kind == "texture" and getattr(vis, "uv", None) is not None and len(vis.uv) == len(mesh.vertices):
        return {"uv": np.asarray(vis.uv, dtype=np.float32)}
    if vis.kind == "vertex":
        return {"vertex_colors": np.asarray(vis.vertex_colors, dtype=np.uint8)}
    if vis.kind == "face":
        return {"face_colors": np.asarray(vis.face_colors, dtype=np.uint8)}
    return {}


def mesh_key(mesh, max_faces: int) -> str:
    """sha1 of the geometry and drawn attributes (not the texture image: the copy reuses it)."""
    h = hashlib.sha1(_VERSION + str(int(max_faces)).encode())
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    for name, a in sorted(_visual_arrays(mesh).items()):
        h.update(name.encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def _decimate(mesh, max_faces: int) -> dict[str, np.ndarray]:
    """Arrays of the decimated copy: vertices (float32), faces (int32) and the drawn attributes.

    Each new vertex is the survivor of a cluster of original vertices collapsed into it (followed
    through the collapse history). Meshes with UVs or colours keep the survivor's position and UV
    (moved to the quadric optimum, a vertex would show its texture displaced) and the cluster's
    mean colour."""
    import fast_simplification

    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.faces, dtype=np.int64)
    attrs = _visual_arrays(mesh)
    # textured files split vertices along UV seams (open borders): keep them, or the seams tear
    V2, F2, collapses = fast_simplification.simplify(V, F, target_count=int(max_faces), return_collapses=True,
                                                     preserve_border="uv" in attrs)
    out = {"vertices": np.asarray(V2, dtype=np.float32), "faces": np.asarray(F2, dtype=np.int32)}
    if not attrs:
        return out
    survivor = np.arange(len(V))
    collapses = np.asarray(collapses, dtype=np.int64).reshape(-1, 2)
    survivor[collapses[:, 1]] = collapses[:, 0]  # vertex i1 collapsed into i0
    while True:  # follow chains of collapses to the vertex that remains
        nxt = survivor[survivor]
        if np.array_equal(nxt, survivor):
            break
        survivor = nxt
    R = survivor[F]
    R = R[(R[:, 0] != R[:, 1]) & (R[:, 1] != R[:, 2]) & (R[:, 0] != R[:, 2])]
    kept = np.unique(R)  # the decimated mesh keeps these vertices, in this order
    if len(kept) == len(V2):
        new_of = np.full(len(V), -1)
        new_of[kept] = np.arange(len(kept))
        mapping = new_of[survivor]
        # survivors stay where they were (not at the quadric optimum): their UVs then stay exact
        out["vertices"] = V[kept].astype(np.float32)
    else:  # not the expected history: attributes of the nearest original vertex instead
        from scipy.spatial import cKDTree

        _, kept = cKDTree(V).query(np.asarray(V2))
        mapping = np.full(len(V), -1)
        mapping[kept] = np.arange(len(kept))
    n_new = len(V2)
    ok = mapping >= 0
    weight = np.maximum(np.bincount(mapping[ok], minlength=n_new), 1).astype(np.float64)
    for name, a in attrs.items():
        if name == "face_colors":  # colour of the nearest original face centre
            from scipy.spatial import cKDTree

            _, nearest = cKDTree(V[F].mean(axis=1)).query(np.asarray(V2)[np.asarray(F2)].mean(axis=1))
            out[name] = a[nearest]
        elif name == "uv":
            out[name] = a[kept]
        else:
            m = np.stack([np.bincount(mapping[ok], weights=a[ok, c].astype(np.float64), minlength=n_new) / weight
                          for c in range(a.shape[1])], axis=1)
            out[name] = np.clip(np.rint(m), 0, 255).astype(np.uint8)
    return out


def _build(mesh, arrays: dict[str, np.ndarray]):
    import trimesh

    copy = trimesh.Trimesh(arrays["vertices"].astype(np.float64), arrays["faces"].astype(np.int64), process=False)
    if "uv" in arrays:
        copy.visual = trimesh.visual.TextureVisuals(uv=arrays["uv"], material=mesh.visual.material)
    elif "vertex_colors" in arrays:
        copy.visual = trimesh.visual.ColorVisuals(copy, vertex_colors=arrays["vertex_colors"])
    elif "face_colors" in arrays:
        copy.visual = trimesh.visual.ColorVisuals(copy, face_colors=arrays["face_colors"])
    copy.metadata.update({k: v for k, v in mesh.metadata.items() if k in ("file_path", "file_name")})
    copy.metadata["decimated_from"] = len(mesh.faces)
    return copy


def render_copy(mesh, max_faces: int | None = MAX_RENDER_FACES, *, use_cache: bool = True):
    """``mesh`` itself when it has at most ``max_faces`` faces (or max_faces is None), else a
    decimated copy of about ``max_faces`` faces for rendering (see the module docstring)."""
    from ..console import info
    from ..io.atomic import atomic_path

    if max_faces is None or len(mesh.faces) <= max_faces:
        return mesh
    key = mesh_key(mesh, max_faces)
    if key in _memo:
        return _memo[key]
    path = cache_dir() / f"{key}.npz"
    arrays = None
    if use_cache and path.is_file():
        try:
            with np.load(path) as z:
                arrays = {k: z[k] for k in z.files}
            if "vertices" not in arrays or "faces" not in arrays:
                arrays = None
        except Exception:  # a damaged cache file: decimate again and replace it
            arrays = None
    cached = arrays is not None
    if arrays is None:
        arrays = _decimate(mesh, max_faces)
        if use_cache:
            try:
                with atomic_path(path) as tmp:
                    with open(tmp, "wb") as f:
                        np.savez(f, **arrays)
            except OSError:
                pass  # a read-only cache folder: render from the copy in memory
    copy = _build(mesh, arrays)
    _memo[key] = copy
    src = mesh.metadata.get("file_path")
    info(f"{src + ': ' if src else ''}{len(mesh.faces):,} faces: rendering a decimated copy with {len(copy.faces):,} faces "
         f"({'cached' if cached else 'written to'} {path}); poses and metrics use the full mesh")
    return copy


def clear_memory_cache() -> None:
    """Forget the decimated copies kept in this process (the disk cache stays)."""
    _memo.clear()
