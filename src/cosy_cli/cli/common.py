"""Shared CLI plumbing: user errors become one line on stderr and exit code 2."""

from __future__ import annotations

import functools
import os
import sys

import click

from ..errors import CosyError, DatasetProblems

USER_ERROR_EXIT = 2


def dataset_options(dataset_help: str):
    """The ``--dataset DIR`` and ``--split NAME`` options every dataset-reading stage takes."""
    from pathlib import Path

    def decorate(fn):
        fn = click.option("--split", default="test", show_default=True, help="Split folder (test, val...).")(fn)
        return click.option("--dataset", required=True, type=click.Path(path_type=Path), help=dataset_help)(fn)

    return decorate


def scene_options(fn):
    """``--scene DIR`` | ``--dataset DIR [--split S] [--scene-id N ...]``: the scenes a per-image
    stage runs on (resolve them with :func:`resolve_scenes`)."""
    from pathlib import Path

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
        dataset, split, sid = scene_location(scene)
        return dataset, split, [sid]
    return dataset, split, (list(scene_ids) or None)


def setup_runtime() -> None:
    """Environment that must be set before numpy/torch/OpenGL are imported by a command; tolerated
    input problems (:class:`~cosy_cli.errors.CosyWarning`) print as one ``warning: ...`` line each."""
    import warnings

    from ..errors import CosyWarning

    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    previous = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, CosyWarning):
            click.echo(f"warning: {message}", err=True)
        else:
            previous(message, category, filename, lineno, file, line)

    warnings.showwarning = show
    warnings.simplefilter("always", CosyWarning)  # one per file is the caller's job, not a filter's


def user_errors(fn):
    """Decorator for click commands: CosyError -> 'error: ...' lines, exit 2, no traceback."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
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

    return wrapper
