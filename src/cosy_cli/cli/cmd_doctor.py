"""``cosy doctor``: the installation's versions, threads, providers and a rendering check."""

from __future__ import annotations

import sys

import click

from .. import console
from .common import USER_ERROR_EXIT, user_errors


@click.command("doctor")
@click.option("--no-render", is_flag=True, help="Skip the rendering check (a 1-triangle render).")
@user_errors
def doctor(no_render: bool) -> None:
    """Print cosy's version and its key dependencies' (and where they differ from the locked,
    tested versions), CPU threads, onnxruntime's providers and the OpenGL platform rendering will
    use, checked with a 1-triangle render. Exit code 2, with the reason on the last line, when
    rendering cannot work. Paste its output into a problem report."""
    from .. import doctor as diag

    rep = diag.report(render=not no_render)
    console.echo(rep.text())  # with --quiet: only the error below, if any
    if rep.render_problem:
        click.echo(f"error: rendering cannot work: {rep.render_problem}", err=True)
        sys.exit(USER_ERROR_EXIT)


COMMANDS = [doctor]
