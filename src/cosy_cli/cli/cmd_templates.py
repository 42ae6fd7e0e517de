"""``cosy templates``: render each object from a sphere of viewpoints and store gradient templates
(the training-free coarse pose of ``cosy estimate``)."""

from __future__ import annotations

import os
from pathlib import Path

import click

from .. import console
from .common import user_errors


def _size(ctx, param, value):
    if value is None:
        return None
    from ..singleview.training_free.templates import parse_size

    try:
        w, h = parse_size(value)
    except ValueError as e:
        raise click.BadParameter(str(e)) from None
    if min(w, h) < 16:
        raise click.BadParameter(f"{value}: each side must be at least 16 px")
    return w, h


@click.command("templates")
@click.option("--models", "models_dir", required=True, type=click.Path(path_type=Path),
              help="BOP models folder (models_info.json and obj_XXXXXX.ply, mm).")
@click.option("--out", required=True, type=click.Path(path_type=Path),
              help="Templates folder: obj_XXXXXX.npz per object and manifest.json.")
@click.option("--conf", default="default", show_default=True,
              help="Named configuration (default: 600 viewpoints x 36 in-plane, 128x96, 64 features; fast: 300 x 24).")
@click.option("--viewpoints", type=click.IntRange(min=1), default=None,
              help="Viewpoints on the sphere before the symmetry dedupe [600].")
@click.option("--inplane", type=click.IntRange(min=1), default=None,
              help="In-plane rotations per viewpoint (rotated analytically, not rendered) [36].")
@click.option("--crop", default=None, callback=_size, metavar="WxH", help="Template render size in px [128x96].")
@click.option("--features", type=click.IntRange(min=4), default=None, help="Gradient features per template [64].")
@click.option("--overwrite", is_flag=True, help="Rebuild everything, also when OUT was made with other settings.")
@user_errors
def templates(models_dir: Path, out: Path, conf: str, viewpoints, inplane, crop, features, overwrite: bool) -> None:
    """Build the templates of every object of a models folder (LINEMOD-like gradient features of
    renders from a sphere of viewpoints, poses in mm).

    Skips when OUT is up to date; rebuilds only the objects whose model file or models_info entry
    changed. Files are written atomically, so an interrupted build resumes."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from ..singleview.training_free import templates as tpl

    c = tpl.resolve_conf(conf, viewpoints=viewpoints, inplane=inplane, crop=crop, features=features)
    tpl.main(c, models_dir, out, overwrite=overwrite, log=console.echo)


COMMANDS = [templates]
