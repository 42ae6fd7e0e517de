"""``cosy symmetries``: propose the symmetries of each mesh of a BOP models folder."""

from __future__ import annotations

import os
from pathlib import Path

import click

from .. import console
from .common import user_errors


@click.command("symmetries")
@click.option("--models", "models_dir", required=True, type=click.Path(path_type=Path),
              help="BOP models folder: obj_XXXXXX.ply meshes (mm) and models_info.json "
                   "(created with --write if missing).")
@click.option("--write", is_flag=True, help="Store the proposed symmetries in models_info.json (other fields kept).")
@click.option("--tolerance-mm", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Largest 95th-percentile surface distance of a symmetry, mm [1% of the diameter, in 0.5..2].")
@click.option("--obj-id", "obj_ids", type=int, multiple=True, help="Only this object (repeatable) [all].")
@click.option("--points", "n_points", type=click.IntRange(min=100), default=1000, show_default=True,
              help="Surface samples per object for the verification.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the surface sampling.")
@user_errors
def symmetries(models_dir: Path, write: bool, tolerance_mm, obj_ids, n_points: int, seed: int) -> None:
    """Propose the discrete and continuous symmetries of each object mesh.

    Prints one row per object (continuous axes, discrete symmetries, worst residual in mm) and
    whether it agrees with models_info.json. Only proper rotations are proposed (no reflections).
    """
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from ..objects import detect_symmetries

    detect_symmetries.main(models_dir, write=write, tolerance_mm=tolerance_mm, obj_ids=list(obj_ids) or None,
                           n_points=n_points, seed=seed, echo=console.echo)


COMMANDS = [symmetries]
