"""User-facing errors. The CLI maps :class:`CosyError` to a one-line message and exit code 2."""

from __future__ import annotations


class CosyError(Exception):
    """A problem with the user's input (file, row, key, value): reported without a traceback."""

    def __init__(self, message: str, *, path: object | None = None, where: str | None = None):
        self.path = None if path is None else str(path)
        self.where = where
        self.detail = message
        parts = [p for p in (self.path, where) if p]
        prefix = ": ".join(parts)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class DatasetProblems(CosyError):
    """Several independent problems found while checking a dataset (one line each)."""

    def __init__(self, problems: list[str]):
        self.problems = list(problems)
        super().__init__("\n".join(self.problems) if self.problems else "no problems")


class CosyWarning(UserWarning):
    """Something in the user's input that cosy tolerates or that the user should act on: one
    line, without stopping the stage. The CLI prints it as ``warning: ...`` on stderr, at every
    verbosity (see :mod:`cosy_cli.console`)."""


class ToleratedInput(CosyWarning):
    """A tolerated input problem that recurs file after file of a split (e.g. the rounding of the
    published LM-O rotations, repaired when read): the CLI summarises them once per split folder
    and problem (how many files and rows, the worst, where) and lists each with --verbose.

    ``record``: {"group" (the split folder), "what", "fix", "path", "rows", "total", "worst",
    "worst_at"}, see :func:`tolerate`."""

    def __init__(self, text: str, record: dict | None = None):
        super().__init__(text)
        self.record = record


def _line(message: str, path: object | None, where: str | None) -> str:
    parts = [str(p) for p in (path, where) if p is not None and p != ""]
    return f"{': '.join(parts)}: {message}" if parts else message


def warn(message: str, *, path: object | None = None, where: str | None = None) -> None:
    """Report something the user should know as one line ``path: where: message`` (a :class:`CosyWarning`).

    Call it once per file with a summary (how many, the worst, where), not once per row. The CLI
    prints it as ``warning: ...`` on stderr; ``cosy validate`` and tests can collect them with
    ``warnings.catch_warnings(record=True)``. A problem cosy repairs that recurs in file after
    file of a split goes to :func:`tolerate` instead; an expected internal step is no warning
    (:func:`cosy_cli.console.info`).
    """
    import warnings

    warnings.warn(CosyWarning(_line(message, path, where)), stacklevel=2)


def tolerate(message: str, *, path: object, group: object, what: str, fix: str, rows: int, total: int,
             worst: float, worst_at: str = "") -> None:
    """Report a tolerated, repaired problem of one file (a :class:`ToleratedInput`; its line is
    ``path: message``). ``group``: the folder its summary speaks for (the split folder of a scene
    file); ``what``: the problem as counted rows, e.g. "cam_R_m2c rotations orthonormal only to
    |R^T R - I| > 0.001"; ``fix``: what cosy did; ``rows`` of ``total`` rows have it, the worst
    value ``worst`` at ``worst_at`` (e.g. "image 5, instance 0")."""
    import warnings

    record = {"group": str(group), "what": what, "fix": fix, "path": str(path), "rows": int(rows),
              "total": int(total), "worst": float(worst), "worst_at": worst_at}
    warnings.warn(ToleratedInput(_line(message, path, None), record=record), stacklevel=2)
