"""Stage outputs as a cache: reuse a complete, current output folder; refuse a stale one."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Callable, Iterable

from ..errors import CosyError


def file_sha1(path: str | Path) -> str:
    h = hashlib.sha1()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def is_complete(out: str | Path, output_files: Iterable[str]) -> bool:
    out = Path(out)
    return out.is_dir() and all((out / f).is_file() for f in output_files)


def reuse_existing_output(out: str | Path, stage: str, output_files: Iterable[str], overwrite: bool,
                          stale_reasons: Callable[[], list[str]], log=print) -> bool:
    """True when ``out`` is a complete output made from the same inputs and settings (skip the
    stage). False when the stage must run (no output yet, or ``overwrite``). A complete output
    made from other inputs, or an incomplete folder, raises :class:`CosyError` unless ``overwrite``."""
    out = Path(out)
    if overwrite or not out.exists():
        return False
    if not is_complete(out, output_files):
        raise CosyError(f"exists but is not a complete {stage} output (use --overwrite to replace it)", path=out)
    reasons = stale_reasons()
    if reasons:
        raise CosyError(f"exists but was made from other inputs: {'; '.join(reasons)} (use --overwrite to recompute)",
                        path=out)
    log(f"{stage}: {out} exists and is up to date, skipping (use --overwrite to recompute)")
    return True
