"""Where the tests find the real data (``../shared/realdata`` beside the repository, or
``$COSY_REALDATA``) and the skip marks for when a folder of it is absent."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REALDATA = Path(os.environ.get("COSY_REALDATA", Path(__file__).resolve().parents[2] / "shared" / "realdata"))
LMO = REALDATA / "lmo_dev"  # real LM-O RGB scenes (split test)
YCBV = REALDATA / "ycbv_0000"  # real YCB-V RGB-D frames (split train_real)
MEGAPOSE = REALDATA / "megapose_examples"  # real photos with textured HOPE meshes (not BOP layout)


def needs(*folders: Path) -> pytest.MarkDecorator:
    """Skip a test when one of these real-data folders is absent, saying which."""
    missing = [str(f) for f in folders if not Path(f).is_dir()]
    return pytest.mark.skipif(bool(missing), reason=f"real data not found: {', '.join(missing)} "
                                                    "(see ../shared/realdata/README.md)")


def orthonormal(T):
    """A copy of the 4x4 pose T with its rotation replaced by the nearest rotation (the published
    LM-O rotations are orthonormal only to about 1e-2)."""
    import numpy as np

    from cosy_cli.io.bop import nearest_rotation

    T = np.array(T, dtype=np.float64)
    T[:3, :3] = nearest_rotation(T[:3, :3])
    return T


def gt_cameras(ds, scene_id: int, views) -> dict:
    """T_world_cam {im_id: (4, 4)} mm of LM-O views from the GT object poses: world = the first
    view's camera, each view placed by the mean over the objects both views see of
    T_cam0_obj inv(T_cam_obj) (the arrangement of a scene is rigid within 10 mm)."""
    import numpy as np

    from cosy_cli.geometry.poses import invert

    gt = ds.scene_gt(scene_id)
    views = list(views)
    ref = {g.obj_id: orthonormal(g.T_cam_obj) for g in gt[views[0]]}
    return {v: orthonormal(np.mean([ref[g.obj_id] @ invert(orthonormal(g.T_cam_obj)) for g in gt[v]
                                    if g.obj_id in ref], 0)) for v in views}
