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
