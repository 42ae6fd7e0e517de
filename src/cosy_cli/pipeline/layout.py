"""Where things are in a run folder of ``cosy run`` (shared by the pipeline and ``cosy viz``)."""

from __future__ import annotations

from pathlib import Path

RUN_FORMAT = ("cosy-run", 1)  # run.json: {"format": RUN_FORMAT[0], "version": RUN_FORMAT[1], ...}
MANIFEST = "run.json"


def scene_dir(run_dir: str | Path, scene_id: int) -> Path:
    """A scene's folder of a run: ``RUN_DIR/scenes/000001``."""
    return Path(run_dir) / "scenes" / f"{int(scene_id):06d}"
