"""``cosy onboard``: a detector and its box classifier for your meshes, trained side by side and exported."""

from __future__ import annotations

from pathlib import Path

import click

from .. import console
from .common import distance_range, user_errors


@click.command("onboard")
@click.option("--models", "models_dir", required=True, type=click.Path(path_type=Path, file_okay=False),
              help="Models folder (obj_XXXXXX.ply in mm + models_info.json) of the objects to detect.")
@click.option("--camera", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="BOP camera.json of the images the detector will see (intrinsics, image size) [the camera.json "
                   "beside the models folder, else 640x480].")
@click.option("--backgrounds", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="A folder of photographs without the objects (any scenes; png, jpg): backgrounds and surface "
                   "textures of the rendered training images. Matters most on real photographs.")
@click.option("--out", required=True, type=click.Path(path_type=Path, file_okay=False),
              help="Folder: detector.onnx, classifier.onnx, the two training runs, their logs, onboard.json.")
@click.option("--long", "long_", is_flag=True,
              help="Then continue the detector at 480x352 px (1500 steps: 32-48 min more on 2 cores; real LM-O "
                   "AP50 about 0.16 -> 0.25 for the detector alone).")
@click.option("--long-iterations", type=click.IntRange(min=1), default=None,
              help="With --long: detector steps at 480x352 [1500].")
@click.option("--detector-iterations", type=click.IntRange(min=1), default=None,
              help="Detector training steps [2500, the real preset's].")
@click.option("--classifier-iterations", type=click.IntRange(min=1), default=None,
              help="Box classifier training steps [3000, the real preset's].")
@click.option("--distance", callback=distance_range, default=None,
              help="NEAR,FAR mm: how far the rendered objects are from the camera; match your camera's working "
                   "distance [300,1100].")
@click.option("--classifier-backbone", type=click.Choice(["detector", "efficientnet-lite0"]), default=None,
              help="The box classifier's backbone: the detector's [default], or EfficientNet-Lite0 from its ImageNet "
                   "weights (1500 steps; on real LM-O AP50 0.32 -> 0.41, but about 4 s per image in cosy detect "
                   "with --config onboarded's 100 proposals).")
@click.option("--detector-backbone", type=click.Choice(["plain", "efficientnet-lite0"]), default=None,
              help="The detector's backbone: plain [default], or EfficientNet-Lite0 from its ImageNet weights "
                   "(1000 steps).")
@click.option("--classifier-precision", type=click.Choice(["int8", "fp32"]), default=None,
              help="An EfficientNet-Lite0 classifier's export: int8 (its backbone's convolutions, calibrated on "
                   "rendered crops; about 2x faster) or float32 [fp32].")
@click.option("--seed", type=int, default=None, help="Seed of both trainings [0].")
@click.option("--device", type=click.Choice(["cpu", "cuda"]), default=None, help="Where both train [cpu].")
@click.option("--resume", is_flag=True, help="Continue the trainings of OUT where they stopped.")
@click.option("--overwrite", is_flag=True, help="Delete OUT and start again.")
@user_errors
def onboard(models_dir, camera, backgrounds, out, long_, long_iterations, detector_iterations, classifier_iterations, distance,
            classifier_backbone, detector_backbone, classifier_precision, seed, device, resume, overwrite) -> None:
    """Onboard your objects from their meshes alone: train the 2D detector and its box classifier
    (boxes moved onto the objects, masks) on domain-randomised renders, side by side, and export
    both for `cosy run --model OUT/detector.onnx --classifier OUT/classifier.onnx --config onboarded`.

    On 2 CPU cores, 8 objects: 46-109 min (both presets side by side, measured; --long adds 32-48 min).
    Ctrl-C saves both runs' checkpoints; --resume continues.
    """
    from ..detection import onboard as stage

    if resume and overwrite:
        raise click.UsageError("--resume and --overwrite exclude each other")
    c = stage.resolve_conf("default", detector_iterations=detector_iterations,
                           classifier_iterations=classifier_iterations, long=long_ or None,
                           long_iterations=long_iterations, seed=seed, device=device, distance=distance,
                           classifier_backbone=classifier_backbone, detector_backbone=detector_backbone,
                           classifier_precision=classifier_precision)
    stage.main(c, models_dir, out, camera=camera, backgrounds=backgrounds, overwrite=overwrite, resume=resume,
               log=console.echo, progress=True)


COMMANDS = [onboard]
