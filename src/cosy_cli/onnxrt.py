"""Opening cosy's exported ONNX models with onnxruntime, and the model card they carry.

Every network cosy exports (detector, box classifier, PoseNet, CosyPose's published networks)
stores what it is as JSON in the ONNX metadata under its own key (:func:`stamp_card`); the
runners open it with :func:`open_session`, which reports a missing, unreadable or foreign file as
a :class:`~cosy_cli.errors.CosyError` naming the file. Used by ``detection`` and ``singleview``
(both below nothing else here), so it lives at the package root.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

from .errors import CosyError

PROVIDERS = {"cpu": "CPUExecutionProvider", "cuda": "CUDAExecutionProvider"}


def provider_names(providers: str | Sequence[str] | None) -> list[str]:
    """onnxruntime provider names of "cpu" / "cuda" / full names, in order, without repeats."""
    if providers is None:
        return ["CPUExecutionProvider"]
    if isinstance(providers, str):
        providers = [providers]
    out = []
    for p in providers:
        name = PROVIDERS.get(str(p).lower(), str(p))
        if name not in out:
            out.append(name)
    return out or ["CPUExecutionProvider"]


def open_session(path: str | Path, metadata_key: str, providers: str | Sequence[str] | None = None,
                 threads: int | None = None, *, missing: str = "", not_ours: str = "not exported by cosy"):
    """(onnxruntime session over ``path``, the JSON card stored under ``metadata_key``).

    providers: "cpu", "cuda" or onnxruntime names; those this onnxruntime lacks are skipped and
    the CPU is always last. threads: intra-op threads (default: onnxruntime's own). User errors
    (missing file, unreadable model, no or malformed card) raise CosyError naming the file;
    ``missing`` / ``not_ours`` say what to do about them."""
    import onnxruntime as ort

    path = Path(path)
    if not path.is_file():
        raise CosyError(f"ONNX model not found{missing}", path=path)
    available = set(ort.get_available_providers())
    use = [p for p in provider_names(providers) if p in available]
    if "CPUExecutionProvider" not in use:
        use.append("CPUExecutionProvider")
    opts = ort.SessionOptions()
    if threads:
        opts.intra_op_num_threads = int(threads)
    opts.log_severity_level = 3
    try:
        session = ort.InferenceSession(str(path), sess_options=opts, providers=use)
    except Exception as e:  # onnxruntime raises its own exception types
        raise CosyError(f"not a readable ONNX model: {e}", path=path) from None
    meta = session.get_modelmeta().custom_metadata_map
    if metadata_key not in meta:
        raise CosyError(f"ONNX model has no '{metadata_key}' metadata: {not_ours}", path=path)
    try:
        card = json.loads(meta[metadata_key])
    except ValueError as e:
        raise CosyError(f"ONNX model has malformed '{metadata_key}' metadata ({e})", path=path) from None
    return session, card


def stamp_card(path: str | Path, key: str, card: dict) -> None:
    """Store ``card`` (JSON) in the ONNX file's metadata under ``key`` (what :func:`open_session` reads)."""
    import onnx

    m = onnx.load(str(path))
    entry = m.metadata_props.add()
    entry.key = key
    entry.value = json.dumps(card)
    onnx.save(m, str(path))


def update_card(path: str | Path, key: str, **fields) -> dict:
    """Set ``fields`` in the JSON card stored under ``key`` in the ONNX file (rewritten
    atomically); returns the new card."""
    import onnx

    from .io.atomic import atomic_path

    m = onnx.load(str(path))
    entry = next((p for p in m.metadata_props if p.key == key), None)
    if entry is None:
        raise CosyError(f"ONNX model has no '{key}' metadata", path=Path(path))
    card = dict(json.loads(entry.value), **fields)
    entry.value = json.dumps(card)
    with atomic_path(path) as tmp:
        onnx.save(m, str(tmp))
    return card
