"""Integrity between stages: each stage lists the files it wrote (sha1 + size) in a manifest;
the stage that reads them checks them first and refuses a file changed or truncated since.

Where the manifest of an output lives:

* a folder output (``cosy match``, ``cosy refine``, ``cosy evaluate``): ``OUT/manifest.json``,
  written inside the folder before it is renamed into place (so it is as atomic as the folder);
* a single-file output (``cosy detect``'s detections JSON, ``cosy estimate``'s candidates CSV):
  the sidecar ``<file name>.manifest.json`` next to it, e.g. ``candidates.csv.manifest.json``.

Manifest format (JSON)::

    {"format": "cosy-manifest", "version": 1, "stage": "estimate",
     "files": {"candidates.csv": {"sha1": "...", "size": 1234}}}

File names are relative to the manifest's folder. A file that no manifest lists (a CSV made by
the user or another tool) is read as before, by the validating readers of :mod:`cosy_cli.io.bop`.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Iterable, Mapping

from ..errors import CosyError
from . import atomic

FORMAT = ("cosy-manifest", 1)
FOLDER_MANIFEST = "manifest.json"
SIDECAR_SUFFIX = ".manifest.json"


def entry_of_bytes(data: bytes) -> dict:
    """``{"sha1", "size"}`` of some bytes (size in bytes)."""
    return {"sha1": hashlib.sha1(data).hexdigest(), "size": len(data)}


def entry_of_file(path: str | os.PathLike) -> dict:
    """``{"sha1", "size"}`` of a file (size in bytes)."""
    from .cache import file_sha1

    return {"sha1": file_sha1(path), "size": Path(path).stat().st_size}


def sidecar_path(path: str | os.PathLike) -> Path:
    """The manifest of a single-file output: ``<file name>.manifest.json`` beside it."""
    path = Path(path)
    return path.with_name(path.name + SIDECAR_SUFFIX)


def folder_manifest_path(folder: str | os.PathLike) -> Path:
    return Path(folder) / FOLDER_MANIFEST


def _doc(stage: str, files: Mapping[str, dict]) -> dict:
    return {"format": FORMAT[0], "version": FORMAT[1], "stage": stage,
            "files": {str(k): {"sha1": v["sha1"], "size": int(v["size"])} for k, v in sorted(files.items())}}


def write_folder_manifest(folder: str | os.PathLike, stage: str, names: Iterable[str]) -> Path:
    """Record ``names`` (files of ``folder``) in ``folder/manifest.json``. Call it on the
    temporary folder of :func:`cosy_cli.io.atomic.atomic_dir`, after the files are written."""
    folder = Path(folder)
    path = folder_manifest_path(folder)
    atomic.write_json(path, _doc(stage, {n: entry_of_file(folder / n) for n in names}))
    return path


def write_file_manifest(path: str | os.PathLike, stage: str, data: bytes | None = None,
                        extra: Mapping[str, bytes] | None = None) -> Path:
    """Record the single-file output ``path`` in its sidecar manifest (atomically). ``data``:
    the bytes about to be written to ``path`` (the manifest can then be written first), else
    the file as it is on disk. ``extra``: companion files written beside ``path`` (file name ->
    their bytes), listed in the same manifest (check them with :func:`verify_companion`)."""
    path = Path(path)
    entry = entry_of_bytes(data) if data is not None else entry_of_file(path)
    side = sidecar_path(path)
    files = {path.name: entry, **{str(k): entry_of_bytes(v) for k, v in (extra or {}).items()}}
    atomic.write_json(side, _doc(stage, files))
    return side


def companion_listed(path: str | os.PathLike, companion: str | os.PathLike) -> bool | None:
    """Whether the manifest of ``path`` lists the file ``companion`` (beside it): None when no
    manifest lists ``path`` (a user-made file)."""
    found = find(path)
    if found is None:
        return None
    return isinstance(found[1]["files"].get(Path(companion).name), dict)


def verify_companion(path: str | os.PathLike, companion: str | os.PathLike) -> None:
    """Check ``companion`` against the manifest of ``path`` that lists it (CosyError on a
    mismatch or when it is missing; nothing when no manifest lists it)."""
    found = find(path)
    companion = Path(companion)
    if found is None or not isinstance(found[1]["files"].get(companion.name), dict):
        return
    m, doc, _ = found
    want = found[1]["files"][companion.name]
    stage = str(doc.get("stage") or "the stage")
    if not companion.is_file():
        raise CosyError(f"{companion} is missing, but {stage} wrote it (listed in {m}); rerun {stage}")
    got = entry_of_file(companion)
    if got["size"] != want.get("size") or got["sha1"] != want.get("sha1"):
        raise CosyError(f"{companion} changed or truncated since {stage} wrote it (listed in {m}); rerun {stage} "
                        f"or pass --overwrite there")


def remove_file_manifest(path: str | os.PathLike) -> None:
    sidecar_path(path).unlink(missing_ok=True)


def _read(manifest: Path) -> dict | None:
    """A manifest's document; None when absent or when the file is someone else's (a
    ``manifest.json`` of another tool next to a user's CSV). A damaged cosy manifest: CosyError."""
    if not manifest.is_file():
        return None
    try:
        text = manifest.read_text()
    except (OSError, UnicodeDecodeError):
        return None
    ours = FORMAT[0] in text[:200]
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as e:
        if not ours:
            return None
        raise CosyError(f"unreadable manifest ({e}); rerun the stage that wrote it, or delete it",
                        path=manifest) from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT[0]:
        return None
    if doc.get("version") != FORMAT[1] or not isinstance(doc.get("files"), dict):
        raise CosyError(f"not a {FORMAT[0]} version {FORMAT[1]} manifest (a newer cosy?)", path=manifest)
    return doc


def find(path: str | os.PathLike) -> tuple[Path, dict, dict] | None:
    """The manifest that lists the file ``path``: (manifest path, its document, the file's entry),
    looking at the sidecar ``<file>.manifest.json`` first, then the folder's ``manifest.json``.
    None when no manifest lists it."""
    path = Path(path)
    for m in (sidecar_path(path), folder_manifest_path(path.parent)):
        doc = _read(m)
        if doc is not None and isinstance(doc["files"].get(path.name), dict):
            return m, doc, doc["files"][path.name]
    return None


def mismatch(path: str | os.PathLike, hint: bool = True) -> str | None:
    """Why ``path`` is not the file its manifest lists (None: it is, or no manifest lists it):
    ``"FILE changed or truncated since STAGE wrote it (...); rerun STAGE ..."`` (the advice
    after ``;`` only with ``hint``)."""
    path = Path(path)
    found = find(path)
    if found is None:
        return None
    m, doc, want = found
    stage = str(doc.get("stage") or "the stage")
    advice = f"; rerun {stage} or pass --overwrite there (or delete {m} to read the file as it is now)" if hint else ""
    if not path.is_file():
        return f"{path} is missing, but {stage} wrote it (listed in {m}){advice}"
    got = entry_of_file(path)
    if got["size"] == want.get("size") and got["sha1"] == want.get("sha1"):
        return None
    return (f"{path} changed or truncated since {stage} wrote it (sha1 {got['sha1'][:12]}, {got['size']} bytes; "
            f"expected sha1 {str(want.get('sha1'))[:12]}, {want.get('size')} bytes){advice}")


def verify(path: str | os.PathLike) -> bool:
    """Check the file ``path`` against the manifest that lists it. Raises :class:`CosyError`
    (one line) on a mismatch; returns True when a manifest vouched for it, False when none lists
    it (a user-made file: read it with the validating readers)."""
    reason = mismatch(path)
    if reason is not None:
        raise CosyError(reason)
    return find(path) is not None


def verify_folder(folder: str | os.PathLike, required: Iterable[str] = ()) -> bool:
    """Check every file listed in ``folder/manifest.json``; ``required``: names that must be
    listed when a manifest is present. Returns False when the folder has no manifest."""
    folder = Path(folder)
    doc = _read(folder_manifest_path(folder))
    if doc is None:
        return False
    missing = [n for n in required if n not in doc["files"]]
    if missing:
        raise CosyError(f"does not list {', '.join(missing)}; rerun {doc.get('stage') or 'the stage'} "
                        "or pass --overwrite there", path=folder_manifest_path(folder))
    for name in doc["files"]:
        verify(folder / name)
    return True


def folder_stale_reasons(folder: str | os.PathLike) -> list[str]:
    """For reusing an output folder: the files that differ from its manifest (empty: none, or no manifest)."""
    folder = Path(folder)
    try:
        doc = _read(folder_manifest_path(folder))
    except CosyError as e:
        return [str(e)]
    if doc is None:
        return []
    return [r for r in (mismatch(folder / n, hint=False) for n in doc["files"]) if r is not None]
