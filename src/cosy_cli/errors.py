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
