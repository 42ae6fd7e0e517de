"""Stage outputs as a cache: reuse a complete, current output folder; refuse a stale one."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Callable, Iterable

from ..errors import CosyError


def user_cache_dir(kind: str) -> Path:
    """cosy's per-user cache folder for ``kind`` (e.g. "meshes"): ``$COSY_CACHE_DIR/kind``, else
    ``$XDG_CACHE_HOME/cosy/kind``, else ``~/.cache/cosy/kind`` (not created here)."""
    import os

    root = os.environ.get("COSY_CACHE_DIR")
    if not root:
        root = str(Path(os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")) / "cosy")
    return Path(root) / kind


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
    from . import manifest

    reasons = stale_reasons() + manifest.folder_stale_reasons(out)
    if reasons:
        raise CosyError(f"exists but was made from other inputs: {'; '.join(reasons)} (use --overwrite to recompute)",
                        path=out)
    log(f"{stage}: {out} exists and is up to date, skipping (use --overwrite to recompute)")
    return True


def _plain(obj):
    """``obj`` as JSON would give it back (tuples -> lists, int keys -> str...)."""
    import json

    return json.loads(json.dumps(obj))


def sidecar_stale_reasons(doc_path: str | Path, conf: dict | None, inputs: dict) -> list[str]:
    """Why an output described by the JSON document ``doc_path`` (keys ``conf`` and ``inputs``) was
    not made from ``conf`` and ``inputs`` (empty: it was). ``conf`` None: the settings are not
    recorded apart (they are part of ``inputs``)."""
    import json

    doc_path = Path(doc_path)
    try:
        doc = json.loads(doc_path.read_text())
    except (OSError, json.JSONDecodeError):
        return [f"{doc_path.name} missing or unreadable"]
    if not isinstance(doc, dict):
        return [f"{doc_path.name} is not a JSON object"]
    reasons = []
    if conf is not None:
        old, new = doc.get("conf") or {}, _plain(conf)
        changed = sorted(k for k in set(new) | set(old) if old.get(k) != new.get(k))
        if changed:
            reasons.append(f"settings changed ({', '.join(changed)})")
    old, new = doc.get("inputs") or {}, _plain(inputs)
    changed = sorted(k for k in set(new) | set(old) if old.get(k) != new.get(k))
    if changed:
        reasons.append(f"inputs changed ({', '.join(changed)})")
    return reasons


def reuse_existing_file(out: str | Path, doc_path: str | Path, stage: str, overwrite: bool, conf: dict, inputs: dict,
                        log=print) -> bool:
    """The single-file version of :func:`reuse_existing_output`: True when ``out`` exists and its
    sidecar ``doc_path`` records the same ``conf`` and ``inputs`` (skip the stage); False when the
    stage must run (no output yet, or ``overwrite``); a :class:`CosyError` naming what changed
    otherwise."""
    out = Path(out)
    if overwrite or not out.exists():
        return False
    from . import manifest

    reasons = sidecar_stale_reasons(doc_path, conf, inputs)
    changed = manifest.mismatch(out, hint=False)
    if changed is not None:
        reasons.append(changed)
    if reasons:
        raise CosyError(f"exists but was made from other inputs or settings: {'; '.join(reasons)} "
                        "(use --overwrite to recompute)", path=out)
    log(f"{stage}: {out} exists and is up to date, skipping (use --overwrite to recompute)")
    return True
