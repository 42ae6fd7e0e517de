"""``cosy refine``: object-level bundle adjustment of the scene and cameras (paper stage 3).

Imports stay light: the stage module is imported when the command runs.
"""

from __future__ import annotations

import os
from pathlib import Path

import click

from .. import console
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
@click.option("--output", "output", type=click.Choice(["scene+candidates", "scene"]), default=None,
              help="predictions.csv: the refined objects in every placed view + the single-view candidates no "
                   "refined object explains, scored strictly below (the paper's ba_output+all_cand), or the "
                   "refined scene alone [scene+candidates].")
@click.option("--explained-frac", type=click.FloatRange(min=0), default=None,
              help="A candidate is explained by a refined prediction of its label in its image whose centre is "
                   "closer than this fraction of the diameter [0.5].")
@click.option("--min-agreeing", type=click.IntRange(min=0), default=None,
              help="Views in which a refined object needs a candidate that agrees with it (mean reprojection "
                   "error under half the loss threshold), else it is dropped; a view without one gets no refined predictions "
                   "(0: off) [2].")
@click.option("--keep-unmatched", is_flag=True, default=None, hidden=True,
              help="Old name of --output scene+candidates.")
@click.option("--nms-mm", type=click.FloatRange(min=0), default=None,
              help="Merge objects of one label whose centres are closer than this, mm (0: off) [0].")
@click.option("--exclusion-frac", type=click.FloatRange(min=0), default=None,
              help="Drop the weaker of two objects (any labels) whose centres are closer than this fraction of "
                   "the smaller diameter: two solids cannot overlap (0: off) [0.5].")
@click.option("--image-check", type=click.Choice(["auto", "on", "none"]), default=None,
              help="Check each refined object in each view against the view's RGB image (beyond the paper): "
                   "the refined pose and the view's own candidates are scored by rendering; a candidate that "
                   "clearly disagrees (> 0.1 x diameter) and scores 0.02 higher replaces the refined pose "
                   "(scene.json records which per view; in `cosy run`, --set refine.image_check_align=true adds a contour "
                   "alignment of the refined pose). auto: when the images exist; on: required [auto].")
@click.option("--leftover-check/--no-leftover-check", "leftover_check", default=None,
              help="With the image check, on RGB views without depth: candidates that no refined object explains "
                   "and that may be one object across views (same label, centres agreeing through the cameras) "
                   "are scored in all those views; each takes the one of their poses that explains the views best "
                   "when it scores 0.02 higher than its own (scene.json: leftovers) [on].")
@click.option("--feature-cameras", type=click.Choice(["leftovers", "scene", "none"]), default=None,
              help="Without known cameras: each view's rotation and baseline direction relative to the gauge view "
                   "from SIFT features (scale from the objects), where the image pair is trusted. leftovers: they "
                   "carry the leftover check's candidates across views; scene: the objects are also adjusted "
                   "again with them held; none: the objects alone (the paper) [leftovers].")
@click.option("--scorer", "scorer_model", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="Learned hypothesis scorer (`cosy train scorer`): the image check's leftover choice uses its "
                   "score instead of the training-free verification score [none].")
@click.option("--scorer-use", type=click.Choice(["leftovers", "all", "none"]), default=None,
              help="With --scorer: where its score replaces the verification score: the leftover check, also the "
                   "check of the refined poses (all), or nowhere [leftovers].")
@click.option("--overwrite", is_flag=True, help="Recompute even if OUT exists and is complete.")
@user_errors
def refine(dataset: Path, split: str, matches: Path, out: Path, iterations, loss_threshold_px, output, explained_frac,
           min_agreeing, keep_unmatched, nms_mm, exclusion_frac, image_check, leftover_check, feature_cameras,
           scorer_model, scorer_use, overwrite: bool) -> None:
    """Refine cameras and objects jointly per group (CosyPose stage 3): every object in every placed view.

    Writes OUT atomically; skips when OUT is complete and up to date (unless --overwrite).
    Lengths in mm; world frame = the gauge camera of each group (or the dataset's world frame
    when match ran with --known-cameras).
    """
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from ..multiview import refine_stage

    c = refine_stage.resolve_conf(None, iterations=iterations, loss_threshold_px=loss_threshold_px,
                                  output=output or ("scene+candidates" if keep_unmatched else None),
                                  explained_frac=explained_frac, min_agreeing=min_agreeing, nms_mm=nms_mm,
                                  exclusion_frac=exclusion_frac, image_check=image_check,
                                  image_check_leftovers=leftover_check, feature_cameras=feature_cameras,
                                  image_check_scorer=scorer_use)
    refine_stage.main(c, dataset, split, matches, out, overwrite=overwrite, scorer_model=scorer_model,
                      log=console.echo)


COMMANDS = [refine]
