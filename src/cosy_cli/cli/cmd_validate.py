"""``cosy validate``: check a whole BOP dataset, print a summary, list every problem (exit 2)."""

from __future__ import annotations

from pathlib import Path

import click

from ..errors import DatasetProblems
from .common import user_errors


@click.command("validate")
@click.option("--dataset", "dataset", required=True, type=click.Path(path_type=Path),
              help="BOP dataset folder (camera.json, models/, <split>/...).")
@click.option("--split", default="test", show_default=True, help="Split folder to check (test, train_pbr, val...).")
@click.option("--split-type", default=None, help="Split type suffix, e.g. primesense for test_primesense.")
@click.option("--models-dir", default="models", show_default=True,
              help="Models folder, relative to the dataset folder (or absolute).")
@click.option("--max-images", type=click.IntRange(min=1), default=None,
              help="Check the image files of at most N images per scene (default: all).")
@click.option("--full", is_flag=True, help="Decode every image, depth image and mask (default: a sample per scene).")
@click.option("--symmetry-tol", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Tolerated symmetry residual in mm (default: max(1 mm, 1% of the diameter)).")
@click.option("--max-per-check", type=click.IntRange(min=0), default=20, show_default=True,
              help="Problem lines per file and kind of check before the rest are only counted (0: all).")
@user_errors
def validate(dataset: Path, split: str, split_type: str | None, models_dir: str, max_images: int | None,
             full: bool, symmetry_tol: float | None, max_per_check: int) -> None:
    """Check a BOP dataset: files, JSON, rotations, intrinsics, image sizes, GT, models, symmetries, targets.

    Prints a summary on stdout. Exit 0 when no problem is found; otherwise exit 2 with one line
    per problem on stderr: <file>: <where>: <what is wrong, what was expected>.
    """
    from ..validate import validate_dataset

    report = validate_dataset(dataset, split, split_type, models_dir=models_dir, max_images=max_images, full=full,
                              symmetry_tol_mm=symmetry_tol, max_per_check=max_per_check)
    click.echo(report.summary())
    if report.problems:
        raise DatasetProblems(report.problems)


COMMANDS = [validate]
