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
    """Something in the user's input that cosy tolerates and repairs (e.g. a rotation orthonormal
    only to 1e-2): reported once, as one line, without stopping the stage."""


def warn(message: str, *, path: object | None = None, where: str | None = None) -> None:
    """Report a tolerated input problem as one line ``path: where: message`` (a :class:`CosyWarning`).

    Call it once per file with a summary (how many, the worst, where), not once per row. The CLI
    prints it as ``warning: ...`` on stderr; ``cosy validate`` and tests can collect them with
    ``warnings.catch_warnings(record=True)``.
    """
    import warnings

    parts = [str(p) for p in (path, where) if p is not None and p != ""]
    text = f"{': '.join(parts)}: {message}" if parts else message
    warnings.warn(CosyWarning(text), stacklevel=2)
