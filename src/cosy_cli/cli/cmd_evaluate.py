"""``cosy evaluate``: BOP19, BOP24 and CosyPose (AUC) scores of pose predictions, errors.csv and report.png."""

from __future__ import annotations

import os
from pathlib import Path

import click

from .. import console
from .common import dataset_options, user_errors


@click.command("evaluate")
@dataset_options("BOP dataset folder with ground truth (scene_gt.json, scene_gt_info.json, depth/ for VSD).")
@click.option("--predictions", required=True, type=click.Path(path_type=Path),
              help="Predictions CSV (BOP results: scene_id,im_id,obj_id,score,R,t,time; pose in the camera, mm).")
@click.option("--out", required=True, type=click.Path(path_type=Path),
              help="Output folder: errors.csv, scores.json, curves.csv, gt_errors.csv, report.png.")
@click.option("--targets", type=click.Path(path_type=Path), default=None,
              help="Targets file, for every protocol [bop19: DATASET/test_targets_bop19.json, without one every GT "
                   "instance is a target; bop24: the images of DATASET/test_targets_bop24.json, else of the bop19 "
                   "file, else every image with GT].")
@click.option("--metrics", "--protocol", "metrics", default="bop19,auc", show_default=True,
              help="Comma-separated protocols (--protocol is the same option): bop19 (6D localization: VSD, MSSD, MSPD average recalls of the top "
                   "inst_count estimates), bop24 (6D detection: MSSD, MSPD average precisions, every estimate, up to "
                   "100 per image), auc (CosyPose/PoseCNN AUC of ADD-S, ADD(-S), top-1), vivo (CosyPose T-LESS ViVo: "
                   "AUC of ADD-S, ADD-S<0.1d, mAP@ADD-S<0.1d).")
@click.option("--scene-id", "scene_ids", type=int, multiple=True,
              help="Only these scenes (repeatable): their GT and targets; other scenes' predictions are ignored [all].")
@click.option("--scene-json", type=click.Path(path_type=Path), default=None,
              help="scene.json of cosy refine: adds relative camera pose errors and the fraction of views placed.")
@click.option("--models-dir", default="models_eval", show_default=True,
              help="Models folder (relative to DATASET or absolute); models/ is used with a warning if absent.")
@click.option("--vsd-delta", type=click.FloatRange(min=0, min_open=True), default=None,
              help="VSD visibility tolerance, mm [15; the toolkit uses 5 for ITODD].")
@click.option("--no-vsd", is_flag=True, help="Skip VSD (no rendering): BOP19 reports MSSD and MSPD only.")
@click.option("--oracle", type=click.Choice(["depth", "rotation", "translation"]), default=None,
              help="Diagnostic, not a BOP score: score each estimate with its distance along its ray (depth), its "
                   "rotation or its translation taken from the GT instance it is compared with: what the "
                   "estimates would reach were that part exact.")
@click.option("--overwrite", is_flag=True, help="Recompute even if OUT exists and is complete.")
@user_errors
def evaluate(dataset: Path, split: str, predictions: Path, out: Path, targets, metrics: str, scene_ids, scene_json,
             models_dir: str, vsd_delta, no_vsd: bool, oracle, overwrite: bool) -> None:
    """Evaluate pose predictions: BOP19 (VSD, MSSD, MSPD), CosyPose AUC (ADD-S, ADD(-S)) and, on request, BOP24
    (MSSD, MSPD average precision). Lengths in mm."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from ..evaluation import evaluate_stage

    conf = evaluate_stage.resolve_conf("bop19", vsd_delta=vsd_delta, vsd=False if no_vsd else None)
    evaluate_stage.main(conf, dataset, split, predictions, out, overwrite=overwrite, targets=targets, metrics=metrics,
                        scene_json=scene_json, models_dir=models_dir, scene_ids=list(scene_ids) or None, oracle=oracle,
                        log=console.echo)


COMMANDS = [evaluate]
