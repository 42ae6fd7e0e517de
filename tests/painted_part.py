"""A test scene shared by the RGB stage-1 tests: a sample part painted in two colours (vertex
colours), rendered at a known pose over a blocky random background (320 x 240 px)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cosy_cli.rendering import SceneRenderer  # before pyrender/OpenGL

from cosy_cli.geometry.poses import make_pose  # noqa: E402
from cosy_cli.geometry.rotations import rotation_about_axis  # noqa: E402
from cosy_cli.objects.database import ObjectDatabase  # noqa: E402

SAMPLES = Path(__file__).resolve().parents[1] / "data_samples" / "models"


def painted_part_view(obj_id: int = 4):
    """(db, obj, rgb (240, 320, 3) uint8, K (3, 3), T_cam_obj (4, 4) with t in mm, visible box
    x1, y1, x2, y2 px): the object's mesh in ``db`` is replaced by the painted copy."""
    import trimesh

    db = ObjectDatabase.from_models_dir(SAMPLES, obj_ids=[obj_id])
    obj = db[obj_id]
    mesh = obj.mesh.copy()
    v = np.asarray(mesh.vertices)
    col = np.where((v[:, 0] > np.median(v[:, 0]))[:, None], [200, 60, 40, 255], [40, 90, 200, 255])
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=col.astype(np.uint8))
    obj._mesh = mesh  # noqa: SLF001 (the test paints the part)
    W, H = 320, 240
    K = np.array([[400.0, 0, 159.5], [0, 400.0, 119.5], [0, 0, 1]])
    R = rotation_about_axis(np.array([1.0, 0.3, 0.2]), [0.9])[0]
    T = make_pose(R, np.array([5.0, -8.0, 8.0 * obj.diameter]))
    rng = np.random.default_rng(0)
    bg = (rng.integers(0, 255, (H // 8, W // 8, 3)).repeat(8, 0).repeat(8, 1)).astype(np.uint8)
    with SceneRenderer({obj_id: mesh}, W, H) as r:
        out = r.render(K, [obj_id], T[None], background=bg)
    ys, xs = np.nonzero(out.instance >= 0)
    box = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], dtype=float)
    return db, obj, out.rgb, K, T, box
