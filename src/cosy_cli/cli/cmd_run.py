"""``cosy run``: the whole pipeline in one run folder, cached and resumable."""

from __future__ import annotations

from pathlib import Path

import click

from .. import console
from .common import resolve_scenes, scene_options, user_errors

STAGE_NAMES = ["detect", "estimate", "match", "refine", "evaluate", "viz"]


@click.command("run")
@scene_options
@click.option("--out", required=True, type=click.Path(path_type=Path),
              help="Run folder (run.json, scenes/, refine/predictions.csv, report.html).")
@click.option("--config", "config", default="default", show_default=True,
              help="default (best available), paper (networks, RGB only), fast (fewer hypotheses, no VSD), "
                   "onboarded (boxes of a detector trained from meshes: 100 proposals down to score 0.01, two box-head "
                   "passes of the classifier, the best 3 boxes of each object per image through stage 1 and the one "
                   "whose pose fits best kept, each hypothesis also verified nearer and farther; the classifier's "
                   "masks where it has a mask head) or onboarded-fast (the same with 80 proposals, only the best 15 "
                   "moved: within 0.25 s per image with an int8 EfficientNet-Lite0 classifier).")
@click.option("--detections", type=click.Path(path_type=Path), default=None,
              help="Detections made elsewhere (BOP detections JSON or COCO results).")
@click.option("--coco-images", type=click.Path(path_type=Path), default=None,
              help="COCO dataset JSON mapping the COCO image ids of --detections to BOP scene/image ids.")
@click.option("--from-gt", is_flag=True, help="Visible GT boxes as detections (ablations).")
@click.option("--model", type=click.Path(path_type=Path), default=None, help="Detector ONNX [the shipped one].")
@click.option("--classifier", default=None, metavar="auto|none|PATH",
              help="Box classifier of the detect stage (same as --set detect.classifier=...) [auto].")
@click.option("--candidates", type=click.Path(path_type=Path), default=None,
              help="Existing single-view candidates (BOP results CSV): start at match.")
@click.option("--models", "models_dir", type=click.Path(path_type=Path), default=None,
              help="Models folder [the dataset's models/].")
@click.option("--templates-dir", type=click.Path(path_type=Path), default=None,
              help="Templates of the coarse step (built when missing) [RUN_DIR/templates].")
@click.option("--scorer", "scorer_model", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="Learned hypothesis scorer for the estimate stage (`cosy train scorer`) [none: the "
                   "training-free verification score].")
@click.option("--views-per-group", type=click.IntRange(min=2), default=None,
              help="Groups of N consecutive views per scene [all views of a scene in one group].")
@click.option("--known-cameras", is_flag=True, default=None,
              help="Use the cameras of scene_camera.json (a calibrated rig, a SLAM trajectory).")
@click.option("--groups", "grouping", type=click.Choice(["scene", "instant", "targets"]), default=None,
              help="Multi-view groups: scene (all views of a scene, or --views-per-group), instant (the sensors' "
                   "images of one im_id), targets (one per entry of test_targets_multiview_bop25.json) [targets "
                   "when the dataset has that file; else instant for a multi-sensor dataset run as a rig; else scene].")
@click.option("--from", "first", type=click.Choice(STAGE_NAMES), default="detect", show_default=True,
              help="First stage to run (earlier outputs are used as they are).")
@click.option("--to", "last", type=click.Choice(STAGE_NAMES), default="viz", show_default=True,
              help="Last stage to run.")
@click.option("--set", "settings", multiple=True, metavar="STAGE.KEY=VALUE",
              help="Override one stage setting, e.g. --set detect.min_score=0.1 --set match.threshold_mm=30 "
                   "(repeatable; the keys are listed in run.json under confs).")
@click.option("--workers", type=click.IntRange(min=1), default=1, show_default=True,
              help="Scenes in parallel (spawned processes).")
@click.option("--dask-scheduler", default=None, help="Run the scenes on this Dask cluster (tcp://HOST:PORT).")
@click.option("--overwrite", is_flag=True, help="Rerun every stage even if it is up to date.")
@user_errors
def run(scene, dataset, split, scene_ids, out, config, detections, coco_images, from_gt, model, classifier, candidates,
        models_dir,
        templates_dir, scorer_model, views_per_group, known_cameras, grouping, first, last, settings, workers, dask_scheduler,
        overwrite) -> None:
    """Detect -> estimate -> match -> refine -> evaluate -> report, per scene, in one run folder.

    A stage whose settings, inputs and code did not change is skipped; a changed setting reruns
    its stage and the ones after it; an interrupted run resumes where it stopped.
    RUN_DIR/refine/predictions.csv is the final BOP results file, RUN_DIR/report.html the report.
    """
    from ..pipeline import run_stage

    dataset, split, scene_ids = resolve_scenes(scene, dataset, split, scene_ids)

    overrides = run_stage.parse_settings(settings)
    if classifier is not None:
        overrides.setdefault("detect", {})["classifier"] = classifier
    overrides.setdefault("match", {}).update(
        {k: v for k, v in (("views_per_group", views_per_group), ("known_cameras", known_cameras or None)) if v is not None})
    run_stage.main(config, dataset, split, out, overwrite=overwrite, scene_ids=scene_ids,
                   detections=detections, coco_images=coco_images, from_gt=from_gt, model=model,
                   candidates=candidates, models_dir=models_dir,
                   templates_dir=templates_dir, scorer_model=scorer_model, overrides=overrides, first=first,
                   last=last,
                   workers=workers, dask_scheduler=dask_scheduler, log=console.echo, progress=True, groups=grouping)


COMMANDS = [run]
