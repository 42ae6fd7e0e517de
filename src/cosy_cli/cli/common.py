"""Shared CLI plumbing: user errors become one line on stderr and exit code 2."""

from __future__ import annotations

import functools
import os
import sys

import click

from ..errors import CosyError, DatasetProblems

USER_ERROR_EXIT = 2


SENSOR_HELP = ("Sensor of a multi-sensor dataset (IPD, XYZ-IBD, ITODD-MV: rgb_SENSOR/ or gray_SENSOR/ folders) "
               "[its evaluation sensor]; 'rig' is every sensor at once.")


def sensor_option(fn):
    """``--sensor NAME``, folded into the command's ``split`` as the split spec ``SPLIT:NAME``
    (:func:`cosy_cli.io.dataset.with_sensor`), which every stage passes along as its split."""

    @functools.wraps(fn)
    def wrapper(*args, sensor=None, **kwargs):
        if sensor:
            from ..io.dataset import with_sensor

            kwargs["split"] = with_sensor(kwargs.get("split") or "test", sensor)
        return fn(*args, **kwargs)

    return click.option("--sensor", default=None, metavar="NAME", help=SENSOR_HELP)(wrapper)


def dataset_options(dataset_help: str):
    """The ``--dataset DIR``, ``--split NAME`` and ``--sensor NAME`` options every dataset-reading stage takes."""
    from pathlib import Path

    def decorate(fn):
        fn = sensor_option(fn)
        fn = click.option("--split", default="test", show_default=True, help="Split folder (test, val...).")(fn)
        return click.option("--dataset", required=True, type=click.Path(path_type=Path), help=dataset_help)(fn)

    return decorate


def scene_options(fn):
    """``--scene DIR`` | ``--dataset DIR [--split S] [--scene-id N ...]``: the scenes a per-image
    stage runs on (resolve them with :func:`resolve_scenes`)."""
    from pathlib import Path

    fn = sensor_option(fn)
    fn = click.option("--scene-id", "scene_ids", type=int, multiple=True,
                      help="Only these scenes (repeatable; with --dataset).")(fn)
    fn = click.option("--split", default="test", show_default=True, help="Split folder (with --dataset).")(fn)
    fn = click.option("--dataset", type=click.Path(path_type=Path), default=None,
                      help="BOP dataset folder (all scenes of --split).")(fn)
    return click.option("--scene", type=click.Path(path_type=Path), default=None,
                        help="One BOP scene folder DATASET/SPLIT/SCENE_ID (instead of --dataset/--split).")(fn)


def scene_location(scene):
    """A BOP scene folder DATASET/SPLIT/SCENE_ID -> (dataset root, split, scene id)."""
    from pathlib import Path

    scene = Path(scene)
    if not scene.is_dir():
        raise CosyError("scene folder not found", path=scene)
    try:
        sid = int(scene.name)
    except ValueError:
        raise CosyError("a BOP scene folder is named by its scene id (e.g. test/000001)", path=scene) from None
    return scene.resolve().parent.parent, scene.resolve().parent.name, sid


def resolve_scenes(scene, dataset, split, scene_ids):
    """The options of :func:`scene_options` -> (dataset root, split, scene ids or None for all)."""
    if (scene is None) == (dataset is None):
        raise CosyError("give either --scene DIR or --dataset DIR")
    if scene is not None:
        if scene_ids:
            raise CosyError("--scene-id goes with --dataset, not --scene")
        sensor = split.partition(":")[2] if split else ""
        dataset, split, sid = scene_location(scene)
        return dataset, (f"{split}:{sensor}" if sensor else split), [sid]
    return dataset, split, (list(scene_ids) or None)


def setup_runtime() -> None:
    """Environment that must be set before numpy/torch/OpenGL are imported by a command."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


def verbosity_options(fn):
    """``-q/--quiet`` and ``-v/--verbose`` (see :mod:`cosy_cli.console`), on the ``cosy`` group and every command."""
    fn = click.option("-v", "--verbose", is_flag=True,
                      help="Also list every tolerated input problem and note internal steps (decimated render "
                           "copies, caches).")(fn)
    return click.option("-q", "--quiet", is_flag=True,
                        help="Only errors and warnings to act on: no progress, no summaries, no stage lines.")(fn)


def _verbosity(quiet: bool, verbose: bool) -> int:
    """The command's own flags, else those given to the ``cosy`` group, else normal."""
    from .. import console

    if quiet and verbose:
        raise click.UsageError("give at most one of --quiet and --verbose")
    if not (quiet or verbose):
        ctx = click.get_current_context(silent=True)
        root = ctx.find_root() if ctx is not None else None
        if root is not None and root is not ctx:
            quiet, verbose = bool(root.params.get("quiet")), bool(root.params.get("verbose"))
    return console.VERBOSE if verbose else console.QUIET if quiet else console.NORMAL


def user_errors(fn):
    """Decorator for click commands (under their options): adds ``-q/--quiet`` and ``-v/--verbose``
    and runs the command in a :func:`cosy_cli.console.command_output` (its warnings one line each, the
    tolerated input problems summarised at the end); CosyError -> 'error: ...' lines, exit 2, no
    traceback."""
    from .. import console

    @functools.wraps(fn)
    def wrapper(*args, quiet: bool = False, verbose: bool = False, **kwargs):
        try:
            with console.command_output(_verbosity(quiet, verbose)):
                return fn(*args, **kwargs)
        except DatasetProblems as e:
            for p in e.problems:
                click.echo(p, err=True)
            sys.exit(USER_ERROR_EXIT)
        except CosyError as e:
            click.echo(f"error: {e}", err=True)
            sys.exit(USER_ERROR_EXIT)
        except KeyboardInterrupt:
            click.echo("interrupted: finished outputs are kept, the unfinished one was not written", err=True)
            sys.exit(130)

    return verbosity_options(wrapper)


def distance_range(ctx, param, value):
    """click callback: NEAR,FAR (mm) of the rendered scenes of `cosy train` and `cosy onboard`."""
    if value is None:
        return None
    try:
        near, far = (float(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter(f"expected NEAR,FAR in mm such as 400,1500, got {value!r}") from None
    if not 0 < near <= far:
        raise click.BadParameter(f"expected 0 < NEAR <= FAR (mm), got {value!r}")
    return [near, far]
