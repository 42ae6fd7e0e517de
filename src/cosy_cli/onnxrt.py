"""Opening cosy's exported ONNX models with onnxruntime, and the model card they carry.

Every network cosy exports (detector, box classifier, PoseNet, CosyPose's published networks)
stores what it is as JSON in the ONNX metadata under its own key (:func:`stamp_card`); the
runners open it with :func:`open_session`, which reports a missing, unreadable or foreign file as
a :class:`~cosy_cli.errors.CosyError` naming the file. Used by ``detection`` and ``singleview``
(both below nothing else here), so it lives at the package root.
"""

from __future__ import annotations

import json
from collections import OrderedDict
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


SESSION_CACHE_SIZE = 8  # sessions kept open per process (open_session)
_SESSIONS: "OrderedDict[tuple, tuple]" = OrderedDict()


def open_session(path: str | Path, metadata_key: str, providers: str | Sequence[str] | None = None,
                 threads: int | None = None, *, missing: str = "", not_ours: str = "not exported by cosy"):
    """(onnxruntime session over ``path``, the JSON card stored under ``metadata_key``).

    providers: "cpu", "cuda" or onnxruntime names; those this onnxruntime lacks are skipped and
    the CPU is always last. threads: intra-op threads (default: onnxruntime's own). User errors
    (missing file, unreadable model, no or malformed card) raise CosyError naming the file;
    ``missing`` / ``not_ours`` say what to do about them.

    The process keeps the last ``SESSION_CACHE_SIZE`` sessions open: opening the same file (same
    inode, size and modification time) with the same settings again returns its session (and a
    fresh copy of its card) instead of building it again. ``cosy run`` opens its models once per
    scene, and a new session is slow to open and on its first images (with an int8
    EfficientNet-Lite0 classifier the run's detect stage took 1.2-1.3x the time of ``cosy detect``
    alone before, the same time now). A changed file is opened anew."""
    import onnxruntime as ort

    path = Path(path)
    if not path.is_file():
        raise CosyError(f"ONNX model not found{missing}", path=path)
    available = set(ort.get_available_providers())
    use = [p for p in provider_names(providers) if p in available]
    if "CPUExecutionProvider" not in use:
        use.append("CPUExecutionProvider")
    st = path.stat()
    key = (str(path.resolve()), st.st_ino, st.st_size, st.st_mtime_ns, tuple(use), int(threads or 0), metadata_key)
    hit = _SESSIONS.get(key)
    if hit is not None:
        _SESSIONS.move_to_end(key)
        return hit[0], json.loads(hit[1])
    session, card = _build_session(path, metadata_key, use, threads, not_ours)
    _SESSIONS[key] = (session, json.dumps(card))
    while len(_SESSIONS) > SESSION_CACHE_SIZE:
        _SESSIONS.popitem(last=False)
    return session, card


def _build_session(path: Path, metadata_key: str, use: list, threads: int | None, not_ours: str):
    """open_session's work: the session and its card, errors as CosyError."""
    import onnxruntime as ort

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


QUANTIZED_OPS = ("Conv", "Clip")


def quantize_convs(path: str | Path, feeds, node_parts: Sequence[str], key: str) -> int:
    """Rewrite the ONNX file at ``path`` with the convolutions (and their ReLU6, ``Clip``) whose
    node names contain one of ``node_parts`` (torch's export names them after the module path,
    e.g. "/blocks.3/dw/dw.1/Conv", under a wrapper's name when there is one) in int8: weights per output channel (int8),
    activations uint8 with ranges from onnxruntime's min/max calibration over ``feeds`` (a list
    of input dicts), as quantize/dequantize pairs that onnxruntime fuses into integer
    convolutions; the rest stays float32. The metadata is kept, and the card under ``key`` gains
    ``"precision": "int8"``. Written atomically; returns the number of convolutions quantized.
    The same inputs give the same file (deterministic calibration)."""
    import contextlib
    import io
    import tempfile

    import onnx
    from onnxruntime.quantization import (CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType,
                                          quantize_static)
    from onnxruntime.quantization.shape_inference import quant_pre_process

    from .io.atomic import atomic_path

    model = onnx.load(str(path))
    meta = {p.key: p.value for p in model.metadata_props}
    feeds = list(feeds)
    if not feeds:
        raise ValueError("quantize_convs: no calibration inputs")

    class _Reader(CalibrationDataReader):
        def __init__(self):
            self.it = iter(feeds)

        def get_next(self):
            return next(self.it, None)

    with tempfile.TemporaryDirectory() as work, atomic_path(path) as tmp:
        # onnxruntime's pre-processing (shape inference, its graph optimisations: BatchNorm folded
        # into the convolutions) first: quantized without it, the model runs slower than in float32
        pre = Path(work) / "pre.onnx"
        quant_pre_process(model, str(pre))
        # the convolutions and their ReLU6 (Clip): quantized after the Clip, the activations keep
        # their [0, 6] range (a convolution's own output range is far wider)
        nodes = [n.name for n in onnx.load(str(pre)).graph.node
                 if n.op_type in QUANTIZED_OPS and any(part in n.name for part in node_parts)]
        if not nodes:
            raise ValueError(f"{path}: no convolution named ...{'..., ...'.join(node_parts)}... to quantize")
        with contextlib.redirect_stdout(io.StringIO()):  # its calibration prints progress
            quantize_static(str(pre), str(tmp), _Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                            op_types_to_quantize=list(QUANTIZED_OPS), nodes_to_quantize=nodes,
                            calibrate_method=CalibrationMethod.MinMax)
        q = onnx.load(str(tmp))  # the card and the rest of the metadata, as they were
        del q.metadata_props[:]
        for k, v in meta.items():
            entry = q.metadata_props.add()
            entry.key, entry.value = k, v
        onnx.save(q, str(tmp))
    update_card(path, key, precision="int8")
    return sum(1 for n in nodes if n.endswith("Conv"))
