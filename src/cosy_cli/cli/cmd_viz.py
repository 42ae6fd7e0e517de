"""``cosy viz``: paper-style figures per group of views and the HTML report of a ``cosy run`` folder."""

from __future__ import annotations

import os
from pathlib import Path

import click

from .. import console
from .common import user_errors


@click.command("viz")
@click.option("--run", "run_dir", required=True, type=click.Path(path_type=Path),
              help="Output folder of cosy run (run.json, scenes/, evaluate/).")
@click.option("--scene", "scene_ids", type=int, multiple=True,
              help="Only the groups of this scene id (repeatable; default: every scene of the run).")
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="Folder of the figures (PNG, one per group of views) [RUN_DIR/figures].")
@click.option("--groups-per-scene", type=click.IntRange(min=1), default=None,
              help="Only the first N groups of each scene (default: all).")
@click.option("--overwrite", is_flag=True, help="Redraw figures that are already there and up to date.")
@user_errors
def viz(run_dir: Path, scene_ids, out, groups_per_scene, overwrite: bool) -> None:
    """Figures of a run (per group: views with their single-view candidates, the refined scene
    re-projected, a top view of the recovered cameras and objects) and RUN_DIR/report.html
    (settings, stage timings, single- vs multi-view metrics, every figure).

    Figures already present are kept unless --overwrite or the scene's outputs changed.
    """
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from .. import viz as viz_mod

    viz_mod.main(run_dir, out=out, scene_ids=list(scene_ids) or None, overwrite=overwrite, log=console.echo,
                 progress=True, groups_per_scene=groups_per_scene)


COMMANDS = [viz]
