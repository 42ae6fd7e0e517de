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


def setup_runtime() -> None:
    """Environment that must be set before numpy/torch/OpenGL are imported by a command."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


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
