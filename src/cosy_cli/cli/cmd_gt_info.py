"""``cosy gt-info``: write a split's scene_gt_info.json (and masks) from its GT poses, meshes and depth."""

from __future__ import annotations

from pathlib import Path

import click

from .. import console
from .common import sensor_option, user_errors


@click.command("gt-info")
@click.option("--dataset", required=True, type=click.Path(path_type=Path),
              help="BOP dataset folder (models/, <split>/<scene>/scene_gt.json...).")
@click.option("--split", default="test", show_default=True, help="Split folder (test, train_real, train_pbr...).")
@click.option("--split-type", default=None, help="Split type suffix, e.g. primesense for test_primesense.")
@sensor_option
@click.option("--scene-id", "scene_ids", type=int, multiple=True, help="Only these scenes (repeatable).")
@click.option("--masks", is_flag=True, help="Also write mask/ and mask_visib/ PNGs (as calc_gt_masks.py).")
@click.option("--models-dir", default="models", show_default=True,
              help="Meshes, relative to the dataset folder or absolute (T-LESS: models_cad).")
@click.option("--delta", "delta_mm", type=click.FloatRange(min=0), default=None,
              help="Visibility tolerance in mm (default 15, the BOP toolkit's).")
@click.option("--visibility", type=click.Choice(["auto", "depth", "zbuffer"]), default=None,
              help="Occlusion from: measured depth where the image has one, else the z-buffer of all GT objects "
                   "(auto, default); depth only; z-buffer only.")
@click.option("--overwrite", is_flag=True, help="Recompute scenes whose scene_gt_info.json is already complete.")
@user_errors
def gt_info(dataset: Path, split: str, split_type: str | None, scene_ids: tuple[int, ...], masks: bool,
            models_dir: str, delta_mm: float | None, visibility: str | None, overwrite: bool) -> None:
    """Compute scene_gt_info.json per scene as the BOP toolkit's calc_gt_info.py does.

    bbox_obj, bbox_visib ([x, y, w, h]), px_count_all, px_count_valid, px_count_visib, visib_fract;
    visibility within --delta mm of the measured depth where the split has depth, else of the
    z-buffer of all GT objects. Resumable: complete scenes are skipped unless --overwrite.
    """
    from ..dataset_tools import gt_info as stage

    conf = None if visibility is None else {"visibility": visibility}
    summary = stage.main(conf, dataset, split, scene_ids=list(scene_ids) or None, masks=masks, split_type=split_type,
                         models_dir=models_dir, delta_mm=delta_mm, overwrite=overwrite, progress=True)
    split, _, sensor = split.partition(":")
    split_dir = Path(dataset) / (f"{split}_{split_type}" if split_type else split)
    console.done(f"{summary.line()} -> {split_dir}/*/scene_gt_info{'_' + sensor if sensor else ''}.json")


COMMANDS = [gt_info]
