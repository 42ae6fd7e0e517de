"""Units of work of a run and their records: the cache of ``cosy run``.

A unit (one stage on one scene, or one run-wide step) is up to date when its record
``<folder>/.cosy/<unit>.json`` holds the same key — a hash of the stage settings, the hashes of its
input files and the code version — and every output it lists still exists with the recorded hash.
The record is written (atomically) only after the stage's own atomic outputs are in place, so a
unit interrupted anywhere is simply run again; an output without a current record is never trusted.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Callable, Iterable

from .. import __version__
from ..io import atomic
from ..io.cache import file_sha1

RECORDS = ".cosy"


@lru_cache(maxsize=1)
def code_version() -> str:
    """``<version>+<sha1 of the code>``: the package version and a digest of every source file and
    shipped model of the installed ``cosy_cli`` package (names and contents). Any change to the
    code that runs, committed or not, makes a new version; a change elsewhere (README, tests,
    benchmarks) does not, so cached stages are not recomputed for it."""
    root = Path(__file__).resolve().parents[1]  # the cosy_cli package
    h = hashlib.sha1()
    for f in sorted(p for p in root.rglob("*") if p.is_file() and p.suffix in (".py", ".onnx", ".json")
                    and "__pycache__" not in p.parts):
        h.update(str(f.relative_to(root)).encode())
        h.update(file_sha1(f).encode())
    return f"{__version__}+{h.hexdigest()[:12]}"


def path_digest(path: str | Path) -> str | None:
    """sha1 of a file, or of a folder's files (names and contents, records excluded); None if absent."""
    path = Path(path)
    if path.is_file():
        return file_sha1(path)
    if not path.is_dir():
        return None
    h = hashlib.sha1()
    for f in sorted(p for p in path.rglob("*") if p.is_file() and RECORDS not in p.relative_to(path).parts):
        h.update(str(f.relative_to(path)).encode())
        h.update(file_sha1(f).encode())
    return h.hexdigest()


@dataclass(frozen=True)
class UnitKey:
    """What a unit's result depends on (``doc``: stage, settings, input digests, code version)
    and its hash (``digest``)."""

    digest: str
    doc: dict


def unit_key(stage: str, conf, inputs: dict) -> UnitKey:
    """The key of a unit: its stage, settings, input digests (``{name: digest or value}``) and code."""
    doc = json.loads(json.dumps({"stage": stage, "conf": conf, "inputs": inputs, "code": code_version()},
                                sort_keys=True, default=str))
    return UnitKey(hashlib.sha1(json.dumps(doc, sort_keys=True).encode()).hexdigest(), doc)


def record_path(folder: Path, unit: str) -> Path:
    return Path(folder) / RECORDS / f"{unit}.json"


def is_current(folder: Path, unit: str, key: UnitKey) -> bool:
    """True when the unit's record has ``key`` and all its outputs exist unchanged."""
    try:
        rec = json.loads(record_path(folder, unit).read_text())
    except (OSError, json.JSONDecodeError):
        return False
    if rec.get("key") != key.digest:
        return False
    return all(path_digest(Path(folder) / rel) == digest for rel, digest in rec.get("outputs", {}).items())


def read_record(folder: Path, unit: str) -> dict | None:
    try:
        return json.loads(record_path(folder, unit).read_text())
    except (OSError, json.JSONDecodeError):
        return None


def write_record(folder: Path, unit: str, key: UnitKey, outputs: Iterable[str], **extra) -> dict:
    """Record a finished unit: its key (with what it was made from: settings, input digests, code
    version) and the digest of each output (paths relative to ``folder``)."""
    folder = Path(folder)
    rec = {"key": key.digest, "made_from": key.doc, "outputs": {rel: path_digest(folder / rel) for rel in outputs},
           **extra}
    record_path(folder, unit).parent.mkdir(parents=True, exist_ok=True)
    atomic.write_json(record_path(folder, unit), rec)
    return rec


def forget(folder: Path, unit: str) -> None:
    record_path(folder, unit).unlink(missing_ok=True)


def run_unit(folder: Path, unit: str, key: UnitKey, outputs: list[str], work: Callable[[], object],
             force: bool = False) -> tuple[bool, float]:
    """Run ``work`` unless the unit is current (and not ``force``); returns (ran, seconds spent now)."""
    import time

    if not force and is_current(folder, unit, key):
        return False, 0.0
    forget(folder, unit)
    t0 = time.perf_counter()
    work()
    dt = time.perf_counter() - t0
    write_record(folder, unit, key, outputs, time_s=round(dt, 3))
    return True, dt
