"""The ``cosy`` command: one click group, one sub-command per stage or tool.

Commands hold no logic: they parse options, call a stage's ``main`` and map user errors to
exit code 2 (see :mod:`cosy_cli.cli.common`).
"""

from __future__ import annotations

import click

from .. import __version__
from .common import setup_runtime, verbosity_options

setup_runtime()


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="cosy")
@verbosity_options
def cli(quiet: bool, verbose: bool) -> None:
    """cosy: multi-view multi-object 6D pose estimation (CosyPose) over BOP datasets.

    Lengths are millimetres, poses are T_a_b (maps frame b into frame a), cameras are OpenCV.
    -q/--quiet and -v/--verbose go here or after any command.
    """


# Each module cosy_cli.cli.cmd_<name> defines COMMANDS, a list of click commands.
COMMAND_MODULES = ["synth", "validate", "symmetries", "templates", "detect", "estimate", "match", "refine", "evaluate",
                   "train", "onboard", "run", "viz", "gt_info", "new_dataset", "doctor"]


def _register() -> None:
    import importlib

    for name in COMMAND_MODULES:
        try:
            mod = importlib.import_module(f"{__package__}.cmd_{name}")
        except ModuleNotFoundError as e:
            if e.name == f"{__package__}.cmd_{name}":
                continue  # not built yet: not listed
            raise
        for cmd in mod.COMMANDS:
            cli.add_command(cmd)


_register()
