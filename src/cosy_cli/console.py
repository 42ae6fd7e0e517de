"""What cosy prints while it works: one verbosity for the process, warnings, summaries of tolerated
input problems, notes on internal steps and progress.

Three levels (the CLI sets them from ``-q/--quiet`` and ``-v/--verbose``):

- ``QUIET``: errors and genuine warnings only (things to act on, e.g. a wrong depth_scale). No
  stage lines, no final line, no progress, no summaries of tolerated input.
- ``NORMAL`` (the default): the stages' lines and their final "wrote" line on stdout; genuine
  warnings, one ``warning: ...`` line each on stderr; tolerated input problems
  (:class:`~cosy_cli.errors.ToleratedInput`, e.g. the rounding of the published LM-O rotations)
  summarised once per kind and split folder (how many files and rows, the worst and where);
  progress bars on a terminal, a few plain lines in a log or pipe.
- ``VERBOSE``: as normal, plus every tolerated problem as its own line and ``note: ...`` lines
  on expected internal steps (decimated render copies, caches built or reused).

Everything here writes to ``sys.stdout``/``sys.stderr`` as they are at the call (so redirections
and test runners see it). Library code that runs outside the CLI keeps Python's warnings: the
routing below is installed only for the time of a command (:func:`command_output`).
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
import warnings
from pathlib import Path

QUIET, NORMAL, VERBOSE = 0, 1, 2

_level = NORMAL
_pending: dict[tuple, list[dict]] = {}  # (group, what, fix) -> one record per file, in reading order
_seen: set[tuple] = set()  # (group, what, fix, path) already counted: a file read again is not counted twice
_said: set[str] = set()  # genuine warnings already printed
_bars = 0  # live terminal bars: lines are written through tqdm.write so they do not cut a bar


def level() -> int:
    return _level


def set_level(value: int) -> None:
    global _level
    if value not in (QUIET, NORMAL, VERBOSE):
        raise ValueError(f"unknown verbosity {value!r}")
    _level = value


def is_quiet() -> bool:
    return _level <= QUIET


def is_verbose() -> bool:
    return _level >= VERBOSE


# ------------------------------------------------------------------------------------------
# lines
# ------------------------------------------------------------------------------------------
def _write(text: str, stream) -> None:
    if _bars:
        from tqdm import tqdm

        tqdm.write(text, file=stream)
    else:
        print(text, file=stream, flush=True)


def echo(message: str) -> None:
    """A stage's line on stdout (not with --quiet). The summaries of tolerated problems recorded
    until now come first, so that they stand next to the step that read the files and a
    stage's final line stays last."""
    if _level > QUIET:
        flush()
        _write(message, sys.stdout)


def done(message: str) -> None:
    """A command's final line, saying what it wrote where (after the pending summaries)."""
    echo(message)


def info(message: str) -> None:
    """An expected internal step (a decimated render copy, a cache built or reused): ``note: ...``
    on stderr with --verbose only."""
    if _level >= VERBOSE:
        _write(f"note: {message}", sys.stderr)


def warning(message: str) -> None:
    """A genuine warning, something the user should act on: ``warning: ...`` on stderr, at every
    level; the same text again in the same command (a later stage meeting the same file) is not
    repeated."""
    if message in _said:
        return
    _said.add(message)
    _write(f"warning: {message}", sys.stderr)


# ------------------------------------------------------------------------------------------
# tolerated input problems
# ------------------------------------------------------------------------------------------
def tolerated(record: dict, text: str) -> None:
    """One file's tolerated problem (a :class:`~cosy_cli.errors.ToleratedInput`'s ``record``, its
    one-line ``text``). --verbose prints it now; normally it waits for :func:`flush`, which prints
    one summary per (split folder, problem); --quiet drops it. A file already counted in this
    process (read again by a later stage) is not counted again."""
    key = (record["group"], record["what"], record["fix"])
    if key + (record["path"],) in _seen:
        return
    _seen.add(key + (record["path"],))
    if _level >= VERBOSE:
        _write(f"warning: {text}", sys.stderr)
    elif _level > QUIET:
        _pending.setdefault(key, []).append({**record, "text": text})


def _shown(path: str, base: str | None = None) -> str:
    """``path`` relative to ``base`` (or to the working folder) when it lies below it."""
    p = Path(path)
    for b in ([Path(base)] if base else []) + [Path.cwd()]:
        try:
            rel = p.resolve().relative_to(b.resolve())
            return str(rel) if str(rel) != "." else str(p)
        except ValueError:
            continue
    return str(p)


def summary_line(records: list[dict]) -> str:
    """One line for the records of one (split folder, problem): how many files and rows, the worst
    and where. A single file keeps its own line."""
    if len(records) == 1:
        return records[0]["text"]
    r0 = records[0]
    rows = sum(int(r["rows"]) for r in records)
    total = sum(int(r["total"]) for r in records)
    worst = max(records, key=lambda r: float(r["worst"]))
    names = {Path(r["path"]).name for r in records}
    files = f"{len(records)} {names.pop()} files" if len(names) == 1 else f"{len(records)} files"
    at = _shown(worst["path"], r0["group"]) + (f", {worst['worst_at']}" if worst.get("worst_at") else "")
    return (f"{_shown(r0['group'])}: {rows} of {total} {r0['what']} in {files} (worst {float(worst['worst']):.3g}: "
            f"{at}); {r0['fix']}; --verbose lists each file")


def flush() -> None:
    """Print the summaries of the tolerated problems recorded since the last flush (a stage calls
    it when it is done with a split; :func:`done` and the end of a command do too)."""
    items = list(_pending.values())
    _pending.clear()
    for records in items:
        _write(f"warning: {summary_line(records)}", sys.stderr)


def forget() -> None:
    """Drop what was recorded (pending summaries, the files already counted, the warnings said)."""
    _pending.clear()
    _seen.clear()
    _said.clear()


def _show_warning(message, category, filename, lineno, file=None, line=None, _previous=None):
    from .errors import CosyWarning, ToleratedInput

    if isinstance(message, ToleratedInput) and message.record is not None:
        tolerated(message.record, str(message))
    elif issubclass(category, CosyWarning):
        warning(str(message))
    elif _previous is not None:
        _previous(message, category, filename, lineno, file, line)


def replay(caught: list[dict]) -> None:
    """Issue again warnings a worker process caught (:func:`capture_records`), here."""
    from .errors import CosyWarning, ToleratedInput

    for w in caught:
        if w.get("record") is not None:
            warnings.warn(ToleratedInput(w["text"], record=w["record"]), stacklevel=2)
        else:
            warnings.warn(CosyWarning(w["text"]), stacklevel=2)


def capture_records(caught) -> list[dict]:
    """The cosy warnings of a ``warnings.catch_warnings(record=True)`` list as picklable dicts (for :func:`replay`)."""
    from .errors import CosyWarning, ToleratedInput

    out = []
    for w in caught:
        if issubclass(w.category, CosyWarning):
            rec = w.message.record if isinstance(w.message, ToleratedInput) else None
            out.append({"text": str(w.message), "record": rec})
        else:  # not ours: passed on as it came
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return out


def worker_state() -> dict:
    """What a worker process of this command needs to print as the command does (picklable):
    the verbosity and the warnings already said."""
    return {"level": _level, "said": sorted(_said)}


def enter_worker(state: dict | None) -> None:
    """In a worker process a command started (spawned: nothing is inherited), with the command's
    :func:`worker_state`: cosy's warnings become ``warning:`` lines at the command's verbosity,
    and those the command already said (a missing texture met again by each worker) are not
    repeated. Tolerated input problems are the reading process's to summarise: workers drop them
    unless --verbose."""
    from .errors import CosyWarning

    if state is None:
        return
    set_level(state["level"])
    _said.update(state["said"])
    previous = warnings.showwarning

    def show(*args, **kwargs):
        _show_warning(*args, **kwargs, _previous=previous)

    warnings.showwarning = show
    warnings.simplefilter("always", CosyWarning)


@contextlib.contextmanager
def command_output(value: int = NORMAL):
    """One command's output: the verbosity, cosy's warnings routed here (genuine ones one line
    each, tolerated ones summarised), the pending summaries printed at the end. Restores the
    previous verbosity and warning handling on exit."""
    from .errors import CosyWarning

    global _level
    old = _level, dict(_pending), set(_seen), set(_said)
    forget()
    set_level(value)
    with warnings.catch_warnings():
        previous = warnings.showwarning

        def show(*args, **kwargs):
            _show_warning(*args, **kwargs, _previous=previous)

        warnings.showwarning = show
        warnings.simplefilter("always", CosyWarning)  # one per file is the caller's job, not a filter's
        try:
            yield
        finally:
            flush()
            _level = old[0]
            for now, before in zip((_pending, _seen, _said), old[1:]):
                now.clear()
                now.update(before)


# ------------------------------------------------------------------------------------------
# progress
# ------------------------------------------------------------------------------------------
PLAIN_STEP = 0.25  # plain progress lines: at most one per quarter of the work...
PLAIN_MIN_S = 30.0  # ...and at most one per this many seconds (whichever is rarer)
_clock = time.monotonic


def _isatty(stream) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


class PlainProgress:
    """Progress for a log or a pipe: a few whole lines (``desc: 25% (12/48 images, 31 s)``), no
    carriage returns. A line when the work passes a further quarter and at least
    :data:`PLAIN_MIN_S` passed since the last one (or the start); without a total, one per
    :data:`PLAIN_MIN_S`; at the end, one more if any was printed or the work took that long."""

    def __init__(self, iterable=None, *, total=None, desc: str = "", unit: str = "it", initial: int = 0,
                 stream=None, **_ignored):
        self.iterable = iterable
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)
        self.total, self.n, self.desc, self.unit = total, int(initial), desc, unit
        self.stream = stream
        self.t0 = self.last = _clock()
        self.printed = 0
        self.next_fraction = PLAIN_STEP
        self.closed = False
        self.postfix = ""

    def _line(self, now: float) -> str:
        unit = self.unit if self.unit.endswith("s") or self.unit == "it" else self.unit + "s"
        head = f"{self.desc}: " if self.desc else ""
        if self.total:
            done = f"{100.0 * self.n / self.total:.0f}% ({self.n}/{self.total} {unit}, {now - self.t0:.0f} s)"
        else:
            done = f"{self.n} {unit}, {now - self.t0:.0f} s"
        return head + done + (f", {self.postfix}" if self.postfix else "")

    def _emit(self, now: float) -> None:
        print(self._line(now), file=self.stream or sys.stderr, flush=True)
        self.printed += 1
        self.last = now

    def update(self, n: int = 1) -> None:
        self.n += n
        now = _clock()
        if now - self.last < PLAIN_MIN_S:
            return
        if self.total:
            fraction = self.n / self.total
            if fraction >= self.next_fraction and self.n < self.total:
                self._emit(now)
                self.next_fraction = (int(fraction / PLAIN_STEP) + 1) * PLAIN_STEP
        else:
            self._emit(now)

    def set_postfix(self, ordered_dict=None, refresh=True, **kwargs) -> None:
        items = {**(ordered_dict or {}), **kwargs}
        self.postfix = ", ".join(f"{k}={v}" for k, v in items.items())

    def set_postfix_str(self, s: str = "", refresh=True) -> None:
        self.postfix = str(s)

    def set_description(self, desc=None, refresh=True) -> None:
        self.desc = desc or ""

    def refresh(self, *args, **kwargs) -> None:
        pass

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        now = _clock()
        if self.printed or now - self.t0 >= PLAIN_MIN_S:
            self._emit(now)

    def __iter__(self):
        try:
            for x in self.iterable:
                yield x
                self.update(1)
        finally:
            self.close()

    def __len__(self):
        return self.total or 0

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


class _TerminalBar:
    """tqdm on a terminal, counted so that lines printed meanwhile go through ``tqdm.write``."""

    def __init__(self, bar):
        global _bars
        self._bar = bar
        self._open = True
        _bars += 1

    def __getattr__(self, name):
        return getattr(self._bar, name)

    def close(self) -> None:
        global _bars
        if self._open:
            self._open = False
            _bars -= 1
        self._bar.close()

    def __iter__(self):
        try:
            yield from self._bar
        finally:
            self.close()

    def __len__(self):
        return len(self._bar)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def progress(iterable=None, *, total=None, desc: str = "", unit: str = "it", enabled: bool = True,
             leave: bool = False, initial: int = 0, **kwargs):
    """A progress bar over ``iterable`` (or one updated by hand: ``total``, ``.update(n)``,
    ``.close()``, ``.set_postfix()``). A tqdm bar when stderr is a terminal, a few plain lines
    (:class:`PlainProgress`) otherwise; nothing when ``enabled`` is false or with --quiet.
    ``COSY_PROGRESS=bar|lines|off`` overrides the choice."""
    from tqdm import tqdm

    mode = os.environ.get("COSY_PROGRESS", "").strip().lower()
    if not enabled or _level <= QUIET or mode == "off":
        return tqdm(iterable, total=total, disable=True)
    stream = sys.stderr
    if mode == "bar" or (mode != "lines" and _isatty(stream)):
        return _TerminalBar(tqdm(iterable, total=total, desc=desc, unit=unit, leave=leave, initial=initial,
                                 file=stream, dynamic_ncols=True, **kwargs))
    return PlainProgress(iterable, total=total, desc=desc, unit=unit, initial=initial, stream=stream)
