"""Several pose hypotheses per detection: a sidecar CSV next to a candidates file.

A candidates CSV stays a pure BOP results file (scene_id,im_id,obj_id,score,R,t,time: one pose
per detection, what the BOP toolkit and every cosy stage read). ``cosy estimate --hypotheses N``
also writes ``<name>.hypotheses.csv`` beside it (``cands.csv`` -> ``cands.hypotheses.csv``)::

    det_id,rank,score,R,t

one row per hypothesis: ``det_id`` = 0-based data row of the candidates CSV it belongs to,
``rank`` 0.. (0 = the pose of that row, then the runners-up best first), ``score`` = the
ranking score of the hypothesis (not comparable with the detection score of the main CSV),
``R`` row-major (9 numbers), ``t`` in mm (3 numbers), both space-separated as in BOP results.
``cosy match --hypotheses K`` lets each detection choose among its first K hypotheses.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import CosyError
from .bop import clean_rotations, repair_rotations

COLUMNS = ("det_id", "rank", "score", "R", "t")
SUFFIX = ".hypotheses.csv"


def sidecar_path(candidates_csv: str | Path) -> Path:
    """``cands.csv`` -> ``cands.hypotheses.csv`` (same folder)."""
    p = Path(candidates_csv)
    stem = p.name[:-4] if p.name.lower().endswith(".csv") else p.name
    return p.with_name(stem + SUFFIX)


def format_hypotheses(det_id, rank, score, T_cam_obj) -> str:
    """The CSV text of hypotheses (arrays of equal length; T_cam_obj (n, 4, 4), t in mm)."""
    T = np.asarray(T_cam_obj, dtype=np.float64).reshape(-1, 4, 4)
    R = clean_rotations(T[:, :3, :3]).reshape(-1, 9).tolist() if len(T) else []
    t = T[:, :3, 3].tolist()
    lines = [",".join(COLUMNS)]
    for d, r, s, Ri, ti in zip(np.asarray(det_id).tolist(), np.asarray(rank).tolist(), np.asarray(score).tolist(),
                               R, t):
        lines.append(f"{int(d)},{int(r)},{float(s):.9g}," + " ".join(f"{v:.9g}" for v in Ri) + ","
                     + " ".join(f"{v:.6f}" for v in ti))
    return "\n".join(lines) + "\n"


def read_hypotheses(path: str | Path, n_candidates: int | None = None):
    """Read a hypotheses sidecar. Returns (det_id (n,), rank (n,), score (n,), T_cam_obj (n, 4, 4))
    sorted by (det_id, rank). Raises :class:`CosyError` naming the file and row on a malformed
    row, a det_id outside [0, n_candidates), a negative or repeated (det_id, rank), or a rotation
    that is not one (|R^T R - I| > 0.05)."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise CosyError(f"cannot read the hypotheses file ({e})", path=path) from None
    if not lines or [c.strip() for c in lines[0].split(",")] != list(COLUMNS):
        raise CosyError(f"expected the header {','.join(COLUMNS)}", path=path, where="row 0 (header)")
    det, rank, score, T, rows = [], [], [], [], []
    for k, line in enumerate(lines[1:], 1):
        if not line.strip():
            continue
        f = line.split(",")
        try:
            if len(f) != 5:
                raise ValueError(f"{len(f)} fields")
            d, r, s = int(f[0]), int(f[1]), float(f[2])
            R = np.array(f[3].split(), dtype=np.float64)
            t = np.array(f[4].split(), dtype=np.float64)
            if R.size != 9 or t.size != 3:
                raise ValueError("R needs 9 numbers and t 3")
            if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and np.isfinite(s)):
                raise ValueError("non-finite number")
        except ValueError as e:
            raise CosyError(f"expected det_id,rank,score,R (9 numbers),t (3 numbers, mm): {e}", path=path,
                            where=f"row {k}") from None
        if d < 0 or (n_candidates is not None and d >= n_candidates) or r < 0:
            raise CosyError(f"det_id {d} / rank {r} out of range (det_id: a data row of the candidates CSV, 0.."
                            f"{'' if n_candidates is None else n_candidates - 1}; rank >= 0)",
                            path=path, where=f"row {k}")
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R.reshape(3, 3), t
        det.append(d), rank.append(r), score.append(s), T.append(M), rows.append(k)
    det, rank = np.array(det, dtype=np.int64), np.array(rank, dtype=np.int64)
    score = np.array(score, dtype=np.float64)
    T = np.stack(T) if T else np.zeros((0, 4, 4))
    # as every BOP reader: nearest rotation within the tolerance (one warning), else an error naming the row
    T[:, :3, :3] = repair_rotations(T[:, :3, :3], lambda i: f"row {rows[i]}", path=path)[0]
    o = np.lexsort((rank, det))
    det, rank, score, T = det[o], rank[o], score[o], T[o]
    dup = np.flatnonzero((det[1:] == det[:-1]) & (rank[1:] == rank[:-1]))
    if len(dup):
        raise CosyError(f"det_id {det[dup[0]]} has rank {rank[dup[0]]} twice", path=path)
    return det, rank, score, T
