"""``cosy synth``: write a synthetic BOP dataset of the eight procedural objects."""

from __future__ import annotations

from pathlib import Path

import click

from .. import console
from .common import user_errors


def _human_bytes(n: int) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GB"


@click.command("synth")
@click.option("--out", "out", required=True, type=click.Path(path_type=Path),
              help="Dataset folder to create (refused if it exists and is not empty, unless --overwrite; "
                   "a new --split is added to a dataset made by cosy synth with the same size).")
@click.option("--scenes", type=click.IntRange(min=1), default=3, show_default=True, help="Number of scenes.")
@click.option("--views", type=click.IntRange(min=1), default=8, show_default=True, help="Images (cameras) per scene.")
@click.option("--objects", "objects", type=click.IntRange(min=1), default=6, show_default=True,
              help="Objects per scene (distinct up to 8, then repeats).")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True,
              help="Random seed: the same seed gives the same dataset, byte for byte.")
@click.option("--width", type=click.IntRange(min=16), default=640, show_default=True, help="Image width in pixels.")
@click.option("--height", type=click.IntRange(min=16), default=480, show_default=True, help="Image height in pixels.")
@click.option("--split", default="test", show_default=True,
              help="Split folder: test (with test_targets_bop19.json), train_pbr, val...")
@click.option("--overwrite", is_flag=True, help="Replace an existing --out (or only its --split, for a dataset of "
                                                "the same objects and camera).")
@click.option("--models-only", is_flag=True, help="Write only models/, models_eval/ and camera.json.")
@click.option("--sensors", type=click.IntRange(min=2), default=None,
              help="Write the multi-sensor layout (BOP industrial datasets): a calibrated rig of N sensors "
                   "(cam0..), own intrinsics and image sizes, the last one grey; --views instants per scene.")
@user_errors
def synth(out: Path, scenes: int, views: int, objects: int, seed: int, width: int, height: int, split: str,
          overwrite: bool, models_only: bool, sensors: int | None) -> None:
    """Write a BOP dataset of 8 procedural T-LESS-like objects resting on a table.

    The objects are fixed (the same models for every seed); scenes, cameras, colours, lights and
    backgrounds are random under --seed. Writes models/ (with true symmetries in
    models_info.json), models_eval/, camera.json, <split>/<scene>/{rgb,depth,mask,mask_visib}/,
    scene_camera.json (with cam_R_w2c, cam_t_w2c), scene_gt.json, scene_gt_info.json and, for
    the test split, test_targets_bop19.json. Lengths in mm; depth png x 0.1 = mm.

    With --sensors N: the multi-sensor layout instead (camera_SENSOR.json, dataset_info.json
    naming the evaluation sensor cam0, per scene rgb_SENSOR/ or gray_SENSOR/, depth_SENSOR/,
    masks and scene_*_SENSOR.json with the rig's extrinsics, test_targets_bop19/bop24.json of
    cam0 and test_targets_multiview_bop25.json, one entry per instant).
    """
    from ..synth import main

    if sensors is not None:
        if models_only:
            raise click.UsageError("--sensors and --models-only do not go together")
        from ..synth.rig import generate_rig_dataset

        s = generate_rig_dataset(out, sensors, scenes, views, objects, seed=seed, width=width, height=height,
                                 split=split, overwrite=overwrite, progress=True)
        console.done(f"synth: wrote {s.out}: {s.mode} '{s.split}': {s.n_scenes} scenes, {sensors} sensors, "
                     f"{s.n_images} images, {s.n_instances} object instances, "
                     f"{_human_bytes(s.bytes_on_disk)} on disk, {s.seconds:.1f} s")
        return

    s = main(out, scenes, views, objects, seed=seed, width=width, height=height, split=split, overwrite=overwrite,
             models_only=models_only, progress=True)
    if models_only:
        console.done(f"synth: wrote {s.out}: {s.mode}: {s.n_objects} object models, "
                     f"{_human_bytes(s.bytes_on_disk)} on disk, {s.seconds:.1f} s")
        return
    console.done(f"synth: wrote {s.out}: {s.mode} '{s.split}': {s.n_scenes} scenes, {s.n_images} images "
                 f"({width} x {height}), {s.n_instances} object instances of {s.n_objects} objects, "
                 f"{_human_bytes(s.bytes_on_disk)} on disk, {s.seconds:.1f} s")

COMMANDS = [synth]
