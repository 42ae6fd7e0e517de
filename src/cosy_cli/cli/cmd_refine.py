"""``cosy refine``: object-level bundle adjustment of the scene and cameras (paper stage 3).

Imports stay light: the stage module is imported when the command runs.
"""

from __future__ import annotations

import os
from pathlib import Path

import click

from .common import dataset_options, user_errors


@click.command("refine")
@dataset_options("BOP dataset folder (scene_camera.json per scene, models/ with models_info.json).")
@click.option("--matches", required=True, type=click.Path(path_type=Path),
              help="Output folder of cosy match (groups.json, candidates.csv...).")
@click.option("--out", required=True, type=click.Path(path_type=Path),
              help="Output folder: scene.json (cameras + objects per group), predictions.csv (BOP results).")
@click.option("--iterations", type=click.IntRange(min=1), default=None,
              help="Levenberg-Marquardt iterations at most [paper: 100].")
@click.option("--loss-threshold-px", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Truncation of the per-point reprojection error, pixels [25].")
@click.option("--keep-unmatched", is_flag=True, default=None,
              help="Also output the candidates not used in a scene, unchanged, with their score x 0.1.")
@click.option("--nms-mm", type=click.FloatRange(min=0), default=None,
              help="Merge objects of one label whose centres are closer than this, mm (0: off) [0].")
@click.option("--exclusion-frac", type=click.FloatRange(min=0), default=None,
              help="Drop the weaker of two objects (any labels) whose centres are closer than this fraction of "
                   "the smaller diameter: two solids cannot overlap (0: off) [0.5].")
@click.option("--overwrite", is_flag=True, help="Recompute even if OUT exists and is complete.")
@user_errors
def refine(dataset: Path, split: str, matches: Path, out: Path, iterations, loss_threshold_px, keep_unmatched, nms_mm,
           exclusion_frac, overwrite: bool) -> None:
    """Refine cameras and objects jointly per group (CosyPose stage 3): every object in every placed view.

    Writes OUT atomically; skips when OUT is complete and up to date (unless --overwrite).
    Lengths in mm; world frame = the gauge camera of each group (or the dataset's world frame
    when match ran with --known-cameras).
    """
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from ..multiview import refine_stage

    c = refine_stage.resolve_conf(None, iterations=iterations, loss_threshold_px=loss_threshold_px,
                                  keep_unmatched=keep_unmatched, nms_mm=nms_mm,
                                  exclusion_frac=exclusion_frac)
    refine_stage.main(c, dataset, split, matches, out, overwrite=overwrite, log=click.echo)


COMMANDS = [refine]
