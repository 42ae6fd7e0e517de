"""``cosy validate``: check a whole BOP dataset, print a summary, list every warning and problem
(exit 2 on problems, and with ``--strict`` on warnings too)."""

from __future__ import annotations

from pathlib import Path

import click

from .. import console
from ..errors import CosyError, DatasetProblems
from .common import sensor_option, user_errors


@click.command("validate")
@click.option("--dataset", "dataset", required=True, type=click.Path(path_type=Path),
              help="BOP dataset folder (camera.json, models/, <split>/...).")
@click.option("--split", default="test", show_default=True, help="Split folder to check (test, train_pbr, val...).")
@click.option("--split-type", default=None, help="Split type suffix, e.g. primesense for test_primesense.")
@sensor_option
@click.option("--camera", default=None,
              help="Dataset camera file, relative to the dataset folder (or absolute), e.g. camera_uw.json "
                   "(default: camera_<split-type>.json, camera.json, or the only camera_*.json there).")
@click.option("--models-dir", default="models", show_default=True,
              help="Models folder, relative to the dataset folder (or absolute).")
@click.option("--max-images", type=click.IntRange(min=1), default=None,
              help="Check the image files of at most N images per scene (default: all).")
@click.option("--full", is_flag=True, help="Decode every image, depth image and mask (default: a sample per scene).")
@click.option("--symmetry-tol", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Symmetry residual in mm taken as exact (default: max(1 mm, 1% of the diameter)); above it a "
                   "warning up to 5% of the diameter, a problem beyond.")
@click.option("--max-per-check", type=click.IntRange(min=0), default=20, show_default=True,
              help="Problem lines per file and kind of check before the rest are only counted (0: all).")
@click.option("--strict", is_flag=True, help="Warnings fail too (exit 2).")
@user_errors
def validate(dataset: Path, split: str, split_type: str | None, camera: str | None, models_dir: str,
             max_images: int | None, full: bool, symmetry_tol: float | None, max_per_check: int, strict: bool) -> None:
    """Check a BOP dataset: files, JSON, rotations, intrinsics, image sizes, GT, models, symmetries, targets.

    Prints a summary on stdout ("result: OK", "OK, N warnings" or the problem count). On stderr,
    before it, one line per warning, "warning: <file>: <where>: <what>" (tolerated, as the BOP
    toolkit does: rotations orthonormal only to 0.05, repaired when read, summed up over the files
    of the split unless --verbose; symmetries that move the surface by up to 5% of the diameter;
    no scene_gt_info.json), then one line per problem:
    <file>: <where>: <what is wrong, what was expected>. Exit 0 without problems (with --strict:
    without warnings either), else 2.
    """
    from ..validate import validate_dataset

    report = validate_dataset(dataset, split, split_type, models_dir=models_dir, max_images=max_images, full=full,
                              symmetry_tol_mm=symmetry_tol, max_per_check=max_per_check, camera=camera)
    console.replay(report.warning_records)  # genuine ones one line each, tolerated ones summarised
    console.flush()
    console.echo(report.summary())
    if report.problems:
        raise DatasetProblems(report.problems)
    if strict and report.warnings:
        n = len(report.warnings)
        raise CosyError(f"{n} warning{'' if n == 1 else 's'} and --strict: the dataset is not accepted")


COMMANDS = [validate]
