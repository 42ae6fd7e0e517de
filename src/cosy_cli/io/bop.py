"""Readers and writers for the BOP file formats (thodan/bop_toolkit ``docs/bop_datasets_format.md``).

Every reader validates what it reads and raises :class:`~cosy_cli.errors.CosyError` naming the
file, the key or row, and what was expected. Every writer is atomic (temp file + rename).

Units and frames
----------------
* Lengths in BOP files are millimetres: translations, model vertices, diameters.
* ``cam_R_m2c``/``cam_t_m2c`` give ``T_cam_obj`` (maps model points into the camera frame).
* ``cam_R_w2c``/``cam_t_w2c`` give ``T_cam_world`` (maps world points into the camera frame).
* Depth images hold ``depth_mm / depth_scale``: multiply by ``depth_scale`` to get millimetres.
* Cameras are OpenCV cameras: x right, y down, looking along +z.
"""

from __future__ import annotations

import io as _io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Mapping

import numpy as np

if TYPE_CHECKING:  # pandas is imported where a function needs it: reading results needs only numpy
    import pandas as pd

from ..errors import CosyError
from . import atomic

RESULTS_COLUMNS = ["scene_id", "im_id", "obj_id", "score", "R", "t", "time"]
GT_INFO_KEYS = ("bbox_obj", "bbox_visib", "px_count_all", "px_count_valid", "px_count_visib", "visib_fract")


# --------------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------------
def load_json(path: str | Path) -> Any:
    """Read a JSON file; a missing file or a syntax error becomes a :class:`CosyError`."""
    path = Path(path)
    if not path.is_file():
        raise CosyError("file not found", path=path)
    try:
        with open(path, "r", encoding="utf-8") as f:
            return json.load(f)
    except json.JSONDecodeError as e:
        raise CosyError(f"invalid JSON (line {e.lineno}, column {e.colno}: {e.msg})", path=path) from None
    except UnicodeDecodeError as e:
        raise CosyError(f"not a UTF-8 text file ({e.reason})", path=path) from None


def _numbers(value: Any, n: int, path: Path, where: str, what: str) -> np.ndarray:
    """``value`` as a float64 vector of exactly ``n`` finite numbers, else a CosyError."""
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise CosyError(f"{what}: expected {n} numbers, got {value!r:.80}", path=path, where=where) from None
    if arr.size != n:
        raise CosyError(f"{what}: expected {n} numbers, got {arr.size}", path=path, where=where)
    if not np.all(np.isfinite(arr)):
        raise CosyError(f"{what}: non-finite value in {arr.tolist()}", path=path, where=where)
    return arr


def _int_key(key: str, path: Path) -> int:
    try:
        return int(key)
    except (TypeError, ValueError):
        raise CosyError(f"key {key!r} is not an integer id", path=path) from None


def _require(d: Any, key: str, path: Path, where: str) -> Any:
    if not isinstance(d, Mapping):
        raise CosyError(f"expected an object with key '{key}', got {type(d).__name__}", path=path, where=where)
    if key not in d:
        raise CosyError(f"missing key '{key}'", path=path, where=where)
    return d[key]


def _json_list(path: Path, items: str) -> list:
    """The JSON list in ``path`` (a CosyError saying it expected a list of ``items`` otherwise)."""
    data = load_json(path)
    if not isinstance(data, list):
        raise CosyError(f"expected a JSON list of {items}", path=path)
    return data


def _int_fields(d: Any, keys, path: Path, where: str) -> list[int]:
    """The integer values of ``keys`` of the JSON object ``d`` (a CosyError naming the key otherwise)."""
    out = []
    for k in keys:
        v = _require(d, k, path, where)
        if not isinstance(v, int) or isinstance(v, bool):
            raise CosyError(f"{k}: expected an integer, got {v!r}", path=path, where=where)
        out.append(v)
    return out


def _top_dict(data: Any, path: Path) -> dict:
    if not isinstance(data, dict):
        raise CosyError(f"expected a JSON object keyed by id, got {type(data).__name__}", path=path)
    return data


def pose_from_Rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 pose from a 3x3 rotation and a translation (same length unit as ``t``)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64).reshape(3, 3)
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def rotation_errors(R: np.ndarray) -> np.ndarray:
    """Max-abs deviation of ``R^T R`` from identity, +inf where det(R) <= 0. R: (..., 3, 3)."""
    R = np.asarray(R, dtype=np.float64)
    dev = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(axis=(-1, -2))
    return np.where(np.linalg.det(R) > 0, dev, np.inf)


ROTATION_TOL = 1e-3  # |R^T R - I| of a clean rotation (files store 6-10 significant digits): no warning
# Up to this, a rotation read from a file is accepted and replaced by the nearest rotation, with
# one warning per file: the published BOP releases (LM-O GT: 1e-2) are orthonormal only that far,
# and the BOP toolkit accepts them. Beyond it, or det <= 0: an error naming the file and row.
ROTATION_REPAIR_TOL = 0.05
ROTATION_MODES = ("repair", "keep_bad", "raw")


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """The rotation nearest to each R (..., 3, 3) in the Frobenius norm (SVD: U diag(1, 1, d) V^T)."""
    R = np.asarray(R, dtype=np.float64)
    U, _, Vt = np.linalg.svd(R)
    d = np.where(np.linalg.det(U @ Vt) < 0, -1.0, 1.0)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


def clean_rotations(R: np.ndarray) -> np.ndarray:
    """R (..., 3, 3) with every matrix within :data:`ROTATION_REPAIR_TOL` of a rotation replaced by
    the nearest rotation, the others left as they are. Writers use it: a file read then written
    holds rotations orthonormal to ~1e-9 (the digits written)."""
    R = np.array(R, dtype=np.float64, copy=True)
    flat = R.reshape(-1, 3, 3)
    if len(flat):
        err = rotation_errors(flat)
        fix = (err > 1e-12) & (err <= ROTATION_REPAIR_TOL)
        if fix.any():
            flat[fix] = nearest_rotation(flat[fix])
    return flat.reshape(R.shape)


def _split_folder(path: str | Path) -> Path:
    """The folder a file's tolerated problems are summarised for: the split folder of a file in a
    scene folder (SPLIT/000001/scene_gt.json), else the file's own folder."""
    p = Path(path)
    return p.parent.parent if p.parent.name.isdigit() else p.parent


def repair_rotations(R: np.ndarray, where, *, path: str | Path, what: str = "R",
                     rotations: str = "repair") -> tuple[np.ndarray, np.ndarray]:
    """Check rotations R (n, 3, 3) read from ``path``; returns (R repaired, |R^T R - I| after repair).

    Every R within :data:`ROTATION_REPAIR_TOL` is replaced by the nearest rotation (SVD). When
    some were off by more than :data:`ROTATION_TOL`, one :func:`~cosy_cli.errors.tolerate` for the
    whole file says how many, the worst deviation and where (``where(i)`` describes row i; the CLI
    sums the files of a split into one line). Worse
    ones (or det <= 0): ``rotations="repair"`` raises a :class:`CosyError` naming the first such
    row; ``"keep_bad"`` returns them as read, their deviation in the second array (> the repair
    tolerance; 0-ish elsewhere), for a caller that reports each; ``"raw"`` returns R unchecked.
    """
    if rotations not in ROTATION_MODES:
        raise ValueError(f"rotations must be one of {ROTATION_MODES}, got {rotations!r}")
    R = np.array(R, dtype=np.float64, copy=True).reshape(-1, 3, 3)
    if len(R) == 0:
        return R, np.zeros(0)
    err = rotation_errors(R)
    if rotations == "raw":
        return R, err
    bad = err > ROTATION_REPAIR_TOL
    if bad.any() and rotations == "repair":
        i = int(np.flatnonzero(bad)[0])
        more = int(bad.sum()) - 1
        raise CosyError(f"{what} is not a rotation matrix (|R^T R - I| = {err[i]:.3g}, det = {np.linalg.det(R[i]):.3g}; "
                        f"expected orthonormal with det +1, tolerated up to {ROTATION_REPAIR_TOL:g})"
                        + (f"; {more} more row(s) like it" if more else ""), path=path, where=where(i))
    off = (err > ROTATION_TOL) & ~bad
    if off.any():
        from ..errors import tolerate

        j = int(np.flatnonzero(off)[np.argmax(err[off])])
        fix = f"replaced by the nearest rotation (tolerated up to {ROTATION_REPAIR_TOL:g})"
        tolerate(f"{int(off.sum())} of {len(R)} {what} rotations orthonormal only to |R^T R - I| = {err[j]:.3g} "
                 f"(worst: {where(j)}); {fix}", path=path, group=_split_folder(path),
                 what=f"{what} rotations orthonormal only to |R^T R - I| > {ROTATION_TOL:g}", fix=fix,
                 rows=int(off.sum()), total=len(R), worst=float(err[j]), worst_at=where(j))
    fix = (err > 1e-12) & ~bad
    if fix.any():
        R[fix] = nearest_rotation(R[fix])
        err[fix] = rotation_errors(R[fix])
    return R, err


def _fmt(x: float) -> float:
    """Floats for JSON output, rounded to keep files readable but exact to well below 1e-6 mm."""
    return float(f"{float(x):.10g}")


def _floats(a: Iterable[float]) -> list[float]:
    return [_fmt(v) for v in np.asarray(a, dtype=np.float64).reshape(-1)]


# --------------------------------------------------------------------------------------------
# camera.json and scene_camera.json
# --------------------------------------------------------------------------------------------
@dataclass
class CameraInfo:
    """Intrinsics of ``camera.json`` (the dataset's default sensor)."""

    K: np.ndarray  # (3, 3), pixels
    width: int
    height: int
    depth_scale: float = 1.0


def read_camera(path: str | Path) -> CameraInfo:
    path = Path(path)
    d = load_json(path)
    if not isinstance(d, dict):
        raise CosyError("expected a JSON object with fx, fy, cx, cy, width, height", path=path)
    vals = {}
    for k in ("fx", "fy", "cx", "cy", "width", "height"):
        vals[k] = float(_numbers(_require(d, k, path, "camera"), 1, path, "camera", k)[0])
    K = np.array([[vals["fx"], 0, vals["cx"]], [0, vals["fy"], vals["cy"]], [0, 0, 1.0]])
    depth_scale = float(_numbers(d.get("depth_scale", 1.0), 1, path, "camera", "depth_scale")[0])
    return CameraInfo(K=K, width=int(vals["width"]), height=int(vals["height"]), depth_scale=depth_scale)


def write_camera(path: str | Path, cam: CameraInfo) -> None:
    K = cam.K
    atomic.write_json(path, {
        "cx": _fmt(K[0, 2]), "cy": _fmt(K[1, 2]), "depth_scale": _fmt(cam.depth_scale),
        "fx": _fmt(K[0, 0]), "fy": _fmt(K[1, 1]), "height": int(cam.height), "width": int(cam.width),
    })


@dataclass
class SceneCamera:
    """One image's camera (``scene_camera.json`` entry)."""

    K: np.ndarray  # (3, 3) pixels
    depth_scale: float = 1.0  # depth image value x depth_scale = mm
    T_cam_world: np.ndarray | None = None  # (4, 4) mm, from cam_R_w2c / cam_t_w2c
    extra: dict = field(default_factory=dict)  # other keys, kept for round trips


def focal_problem(K: np.ndarray) -> str | None:
    """Why K (3, 3) px has no usable focal lengths (fx or fy <= 0), or None."""
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        return f"cam_K: fx and fy must be > 0, got fx={K[0, 0]:g}, fy={K[1, 1]:g}"
    return None


def last_row_problem(K: np.ndarray) -> str | None:
    """Why K (3, 3) is no pinhole matrix (a last row other than 0 0 1, e.g. singular), or None."""
    if np.abs(K[2] - [0.0, 0.0, 1.0]).max() > 1e-6:
        return f"cam_K: last row is {' '.join(f'{float(v):.6g}' for v in K[2])}, expected 0 0 1"
    return None


def depth_scale_problem(depth_scale: float) -> str | None:
    """Why a depth scale (mm per depth unit) is unusable (<= 0), or None."""
    return f"depth_scale must be > 0, got {depth_scale:g}" if depth_scale <= 0 else None


def intrinsics_problem(K: np.ndarray, depth_scale: float = 1.0) -> str | None:
    """The first reason why a camera matrix K (3, 3) px and depth scale cannot be a pinhole camera
    (:func:`focal_problem`, :func:`last_row_problem`, :func:`depth_scale_problem`), or None.
    Every stage would otherwise divide by fx or invert a singular K."""
    return focal_problem(K) or last_row_problem(K) or depth_scale_problem(depth_scale)


def read_scene_camera(path: str | Path, *, rotations: str = "repair",
                      check_intrinsics: bool = True) -> dict[int, SceneCamera]:
    """``scene_camera.json``: {im_id: SceneCamera}. ``cam_R_w2c`` rotations are checked and repaired
    as :func:`repair_rotations` does with ``rotations`` ("repair", "keep_bad" or "raw"). A K that
    is no pinhole camera (:func:`intrinsics_problem`) is a CosyError naming the image, unless
    ``check_intrinsics`` is False (``cosy validate``, which lists every such image itself)."""
    path = Path(path)
    data = _top_dict(load_json(path), path)
    out: dict[int, SceneCamera] = {}
    for key, entry in data.items():
        im_id = _int_key(key, path)
        where = f"image {key}"
        K = _numbers(_require(entry, "cam_K", path, where), 9, path, where, "cam_K").reshape(3, 3)
        depth_scale = float(_numbers(entry.get("depth_scale", 1.0), 1, path, where, "depth_scale")[0])
        bad = intrinsics_problem(K, depth_scale) if check_intrinsics else None
        if bad:
            raise CosyError(f"{bad} (run cosy validate for every problem of the dataset)", path=path, where=where)
        T = None
        has_R, has_t = "cam_R_w2c" in entry, "cam_t_w2c" in entry
        if has_R != has_t:
            missing = "cam_t_w2c" if has_R else "cam_R_w2c"
            raise CosyError(f"'{missing}' missing (cam_R_w2c and cam_t_w2c come together)", path=path, where=where)
        if has_R:
            T = pose_from_Rt(_numbers(entry["cam_R_w2c"], 9, path, where, "cam_R_w2c"),
                             _numbers(entry["cam_t_w2c"], 3, path, where, "cam_t_w2c"))
        extra = {k: v for k, v in entry.items() if k not in ("cam_K", "depth_scale", "cam_R_w2c", "cam_t_w2c")}
        out[im_id] = SceneCamera(K=K, depth_scale=depth_scale, T_cam_world=T, extra=extra)
    out = dict(sorted(out.items()))
    posed = [im for im, c in out.items() if c.T_cam_world is not None]
    if posed:
        R, _ = repair_rotations(np.stack([out[im].T_cam_world[:3, :3] for im in posed]),
                                lambda i: f"image {posed[i]}", path=path, what="cam_R_w2c", rotations=rotations)
        for im, Ri in zip(posed, R):
            out[im].T_cam_world[:3, :3] = Ri
    return out


def write_scene_camera(path: str | Path, cams: Mapping[int, SceneCamera]) -> None:
    data = {}
    for im_id in sorted(cams):
        c = cams[im_id]
        e: dict[str, Any] = {"cam_K": _floats(c.K), "depth_scale": _fmt(c.depth_scale)}
        if c.T_cam_world is not None:
            e["cam_R_w2c"] = _floats(clean_rotations(c.T_cam_world[:3, :3]))
            e["cam_t_w2c"] = _floats(c.T_cam_world[:3, 3])
        e.update(c.extra)
        data[str(int(im_id))] = e
    atomic.write_json(path, data)


# --------------------------------------------------------------------------------------------
# scene_gt.json and scene_gt_info.json
# --------------------------------------------------------------------------------------------
@dataclass
class GtInstance:
    obj_id: int
    T_cam_obj: np.ndarray  # (4, 4), translation in mm


def _read_per_image_lists(path: Path, parse_instance) -> dict:
    """{im_id: [parse_instance(entry, where), ...]} from a JSON object of per-image lists."""
    data = _top_dict(load_json(path), path)
    out: dict = {}
    for key, insts in data.items():
        im_id = _int_key(key, path)
        if not isinstance(insts, list):
            raise CosyError(f"expected a list of instances, got {type(insts).__name__}", path=path, where=f"image {key}")
        out[im_id] = [parse_instance(inst, f"image {key}, instance {i}") for i, inst in enumerate(insts)]
    return dict(sorted(out.items()))


def read_scene_gt(path: str | Path, *, rotations: str = "repair") -> dict[int, list[GtInstance]]:
    """``scene_gt.json``: {im_id: [GtInstance]}. ``cam_R_m2c`` rotations are checked and repaired
    as :func:`repair_rotations` does with ``rotations`` ("repair", "keep_bad" or "raw"): within
    :data:`ROTATION_REPAIR_TOL` replaced by the nearest rotation (one warning for the file when
    some were off by more than :data:`ROTATION_TOL`), worse ones an error naming image and instance."""
    path = Path(path)

    def parse(inst: Any, where: str) -> GtInstance:
        obj_id = _require(inst, "obj_id", path, where)
        if not isinstance(obj_id, int) or isinstance(obj_id, bool):
            raise CosyError(f"obj_id: expected an integer, got {obj_id!r}", path=path, where=where)
        R = _numbers(_require(inst, "cam_R_m2c", path, where), 9, path, where, "cam_R_m2c")
        t = _numbers(_require(inst, "cam_t_m2c", path, where), 3, path, where, "cam_t_m2c")
        return GtInstance(obj_id=obj_id, T_cam_obj=pose_from_Rt(R, t))

    out = _read_per_image_lists(path, parse)
    flat = [(im, k, g) for im, lst in out.items() for k, g in enumerate(lst)]
    if flat:
        R, _ = repair_rotations(np.stack([g.T_cam_obj[:3, :3] for _, _, g in flat]),
                                lambda i: f"image {flat[i][0]}, instance {flat[i][1]} (obj_id {flat[i][2].obj_id})",
                                path=path, what="cam_R_m2c", rotations=rotations)
        for (_, _, g), Ri in zip(flat, R):
            g.T_cam_obj[:3, :3] = Ri
    return out


def write_scene_gt(path: str | Path, gt: Mapping[int, list[GtInstance]]) -> None:
    data = {
        str(int(im_id)): [
            {"cam_R_m2c": _floats(clean_rotations(g.T_cam_obj[:3, :3])), "cam_t_m2c": _floats(g.T_cam_obj[:3, 3]), "obj_id": int(g.obj_id)}
            for g in gt[im_id]
        ]
        for im_id in sorted(gt)
    }
    atomic.write_json(path, data)


@dataclass
class GtInfo:
    bbox_obj: np.ndarray  # (4,) x, y, w, h in pixels (-1s when the object is outside the image)
    bbox_visib: np.ndarray  # (4,)
    px_count_all: int
    px_count_valid: int
    px_count_visib: int
    visib_fract: float


def read_scene_gt_info(path: str | Path) -> dict[int, list[GtInfo]]:
    path = Path(path)

    def parse(inst: Any, where: str) -> GtInfo:
        vals = {k: _numbers(_require(inst, k, path, where), 4 if k.startswith("bbox") else 1, path, where, k)
                for k in GT_INFO_KEYS}
        return GtInfo(
            bbox_obj=vals["bbox_obj"], bbox_visib=vals["bbox_visib"],
            px_count_all=int(vals["px_count_all"][0]), px_count_valid=int(vals["px_count_valid"][0]),
            px_count_visib=int(vals["px_count_visib"][0]), visib_fract=float(vals["visib_fract"][0]),
        )

    return _read_per_image_lists(path, parse)


def write_scene_gt_info(path: str | Path, info: Mapping[int, list[GtInfo]]) -> None:
    data = {
        str(int(im_id)): [
            {
                "bbox_obj": [int(round(v)) for v in g.bbox_obj], "bbox_visib": [int(round(v)) for v in g.bbox_visib],
                "px_count_all": int(g.px_count_all), "px_count_valid": int(g.px_count_valid),
                "px_count_visib": int(g.px_count_visib), "visib_fract": _fmt(g.visib_fract),
            }
            for g in info[im_id]
        ]
        for im_id in sorted(info)
    }
    atomic.write_json(path, data)


# --------------------------------------------------------------------------------------------
# models_info.json
# --------------------------------------------------------------------------------------------
@dataclass
class ModelInfo:
    """One entry of ``models_info.json``; lengths in mm."""

    diameter: float
    min_xyz: np.ndarray  # (3,)
    size_xyz: np.ndarray  # (3,)
    symmetries_discrete: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))  # (K, 4, 4), t in mm
    symmetries_continuous: list[dict] = field(default_factory=list)  # [{"axis": (3,), "offset": (3,) mm}]
    extra: dict = field(default_factory=dict)


def read_models_info(path: str | Path, *, rotations: str = "repair") -> dict[int, ModelInfo]:
    """``models_info.json``: {obj_id: ModelInfo}. The rotations of ``symmetries_discrete`` are checked
    and repaired as :func:`repair_rotations` does with ``rotations`` (one warning for the file)."""
    path = Path(path)
    data = _top_dict(load_json(path), path)
    out: dict[int, ModelInfo] = {}
    for key, e in data.items():
        obj_id = _int_key(key, path)
        where = f"object {key}"
        diameter = float(_numbers(_require(e, "diameter", path, where), 1, path, where, "diameter")[0])
        if diameter <= 0:
            raise CosyError(f"diameter must be > 0 mm, got {diameter}", path=path, where=where)
        mins = np.array([float(_numbers(_require(e, f"min_{a}", path, where), 1, path, where, f"min_{a}")[0]) for a in "xyz"])
        sizes = np.array([float(_numbers(_require(e, f"size_{a}", path, where), 1, path, where, f"size_{a}")[0]) for a in "xyz"])
        disc = e.get("symmetries_discrete", [])
        if not isinstance(disc, list):
            raise CosyError("symmetries_discrete: expected a list of 16-number lists", path=path, where=where)
        S = np.stack([_numbers(s, 16, path, where, f"symmetries_discrete[{j}]").reshape(4, 4) for j, s in enumerate(disc)]) \
            if disc else np.zeros((0, 4, 4))
        if len(S):
            if not np.allclose(S[:, 3], [0, 0, 0, 1], atol=1e-6):
                raise CosyError("symmetries_discrete: last row of each 4x4 must be 0 0 0 1", path=path, where=where)
        cont = e.get("symmetries_continuous", [])
        if not isinstance(cont, list):
            raise CosyError("symmetries_continuous: expected a list of {axis, offset}", path=path, where=where)
        conts = []
        for j, c in enumerate(cont):
            axis = _numbers(_require(c, "axis", path, f"{where}, symmetries_continuous[{j}]"), 3, path, where, "axis")
            if np.linalg.norm(axis) < 1e-9:
                raise CosyError(f"symmetries_continuous[{j}].axis is zero", path=path, where=where)
            offset = _numbers(c.get("offset", [0, 0, 0]), 3, path, where, "offset")
            conts.append({"axis": axis, "offset": offset})
        known = {"diameter", "symmetries_discrete", "symmetries_continuous"} | {f"{p}_{a}" for p in ("min", "size") for a in "xyz"}
        extra = {k: v for k, v in e.items() if k not in known}
        out[obj_id] = ModelInfo(diameter, mins, sizes, S, conts, extra)
    out = dict(sorted(out.items()))
    syms = [(o, j) for o, m in out.items() for j in range(len(m.symmetries_discrete))]
    if syms:
        R, _ = repair_rotations(np.stack([out[o].symmetries_discrete[j, :3, :3] for o, j in syms]),
                                lambda i: f"object {syms[i][0]}, symmetries_discrete[{syms[i][1]}]", path=path,
                                what="symmetries_discrete", rotations=rotations)
        for (o, j), Ri in zip(syms, R):
            out[o].symmetries_discrete[j, :3, :3] = Ri
    return out


def write_models_info(path: str | Path, infos: Mapping[int, ModelInfo]) -> None:
    data = {}
    for obj_id in sorted(infos):
        m = infos[obj_id]
        e: dict[str, Any] = {"diameter": _fmt(m.diameter)}
        for i, a in enumerate("xyz"):
            e[f"min_{a}"] = _fmt(m.min_xyz[i])
        for i, a in enumerate("xyz"):
            e[f"size_{a}"] = _fmt(m.size_xyz[i])
        if len(m.symmetries_discrete):
            S = np.array(m.symmetries_discrete, dtype=np.float64).reshape(-1, 4, 4)
            S[:, :3, :3] = clean_rotations(S[:, :3, :3])
            e["symmetries_discrete"] = [_floats(Sj) for Sj in S]
        if m.symmetries_continuous:
            e["symmetries_continuous"] = [{"axis": _floats(c["axis"]), "offset": _floats(c["offset"])}
                                          for c in m.symmetries_continuous]
        e.update(m.extra)
        data[str(int(obj_id))] = e
    atomic.write_json(path, data)


# --------------------------------------------------------------------------------------------
# test targets
# --------------------------------------------------------------------------------------------
def read_target_images(path: str | Path) -> tuple[pd.DataFrame, bool]:
    """The images of a targets file, BOP 2024 (``test_targets_bop24.json``: a list of {scene_id,
    im_id}) or BOP19 (with obj_id and inst_count): (scene_id, im_id) in the file's order, each once,
    indexed by the entry that lists it first; and whether any entry has an ``inst_count`` (then it
    is read as a BOP19 file, :func:`read_targets`)."""
    import pandas as pd

    path = Path(path)
    data = _json_list(path, "{scene_id, im_id[, obj_id, inst_count]}")
    rows = []
    for i, e in enumerate(data):
        rows.append(_int_fields(e, ("scene_id", "im_id"), path, f"entry {i}"))
    counts = any("inst_count" in e for e in data)
    return pd.DataFrame(rows, columns=["scene_id", "im_id"], dtype=np.int64).drop_duplicates(), counts


TARGET_COLUMNS = ["scene_id", "im_id", "obj_id", "inst_count"]


def read_targets(path: str | Path) -> pd.DataFrame:
    """``test_targets_bop19.json``: a list of {scene_id, im_id, obj_id, inst_count}."""
    import pandas as pd

    path = Path(path)
    data = _json_list(path, "{im_id, inst_count, obj_id, scene_id}")
    rows = []
    for i, e in enumerate(data):
        where = f"entry {i}"
        row = _int_fields(e, TARGET_COLUMNS, path, where)
        if row[3] < 1:
            raise CosyError(f"inst_count must be >= 1, got {row[3]}", path=path, where=where)
        rows.append(row)
    return pd.DataFrame(rows, columns=TARGET_COLUMNS, dtype=np.int64)


DEFAULT_SENSOR = "default"  # the sensor name of single-sensor datasets in test_targets_multiview_bop25.json


@dataclass
class MultiviewTarget:
    """One entry of ``test_targets_multiview_bop25.json``: the images seen together."""

    scene_id: int
    views: list[tuple[str, int]]  # (sensor, im_id); sensor "default" for single-sensor datasets
    extra: dict = field(default_factory=dict)  # other keys of the entry, kept as they are


def read_multiview_targets(path: str | Path) -> list[MultiviewTarget]:
    """``test_targets_multiview_bop25.json`` (BOP 2025 multi-view task): a list of
    ``{"scene_id": S, "im_id": [[SENSOR, IM_ID], ...]}``, one entry per multi-view group. An item
    that is a bare integer is the image of sensor ``default``; other keys of an entry are kept."""
    path = Path(path)
    data = _json_list(path, '{"scene_id": S, "im_id": [[SENSOR, IM_ID], ...]}')
    out = []
    for i, e in enumerate(data):
        where = f"entry {i}"
        (sid,) = _int_fields(e, ("scene_id",), path, where)
        items = _require(e, "im_id", path, where)
        if not isinstance(items, list) or not items:
            raise CosyError(f"im_id: expected a non-empty list of [SENSOR, IM_ID] pairs, got {items!r}",
                            path=path, where=where)
        views = []
        for item in items:
            if isinstance(item, int) and not isinstance(item, bool):
                views.append((DEFAULT_SENSOR, int(item)))
            elif (isinstance(item, list) and len(item) == 2 and isinstance(item[0], str)
                  and isinstance(item[1], int) and not isinstance(item[1], bool)):
                views.append((item[0], int(item[1])))
            else:
                raise CosyError(f"im_id: expected [SENSOR, IM_ID] pairs, got {item!r}", path=path, where=where)
        if len(set(views)) != len(views):
            raise CosyError("im_id: an image is listed twice", path=path, where=where)
        out.append(MultiviewTarget(int(sid), views, {k: v for k, v in e.items() if k not in ("scene_id", "im_id")}))
    return out


def write_targets(path: str | Path, targets: pd.DataFrame) -> None:
    cols = ["im_id", "inst_count", "obj_id", "scene_id"]  # the key order of the BOP files
    data = [{k: int(r[k]) for k in cols} for r in targets.to_dict("records")]
    atomic.write_json(path, data, indent=None)


# --------------------------------------------------------------------------------------------
# BOP results CSV (pose estimates)
# --------------------------------------------------------------------------------------------
class PoseResults:
    """Rows of a BOP results CSV: ids, score, time in ``table`` and poses in ``T_cam_obj``.

    ``table`` has columns scene_id, im_id, obj_id (int64), score, time (float64, seconds);
    ``T_cam_obj`` is (n, 4, 4) with translations in mm. Row i of both describe one estimate.
    ``column(name)`` gives one column as a numpy array; the DataFrame ``table`` is made (and
    pandas imported) only when asked for, so that the multi-view stages read and write results
    without pandas.
    """

    def __init__(self, table: "pd.DataFrame | None" = None, T_cam_obj: np.ndarray | None = None, *,
                 columns: dict | None = None):
        self._table = table
        self._cols = None if table is not None else dict(columns or {})
        self.T_cam_obj = np.zeros((0, 4, 4)) if T_cam_obj is None else T_cam_obj

    @property
    def table(self) -> "pd.DataFrame":
        if self._table is None:
            import pandas as pd

            self._table = pd.DataFrame(self._cols)
            self._cols = None  # the DataFrame is the data from now on (callers may change it)
        return self._table

    @table.setter
    def table(self, value: "pd.DataFrame") -> None:
        self._table, self._cols = value, None

    def column(self, name: str) -> np.ndarray:
        """One column (scene_id, im_id, obj_id, score or time) as a numpy array."""
        if self._table is None:
            return self._cols[name]
        return self._table[name].to_numpy()

    def __len__(self) -> int:
        return len(self.T_cam_obj) if self._table is None else len(self._table)

    @classmethod
    def empty(cls) -> "PoseResults":
        return cls.from_arrays(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0),
                               np.zeros((0, 4, 4)), np.zeros(0))

    @classmethod
    def from_arrays(cls, scene_id, im_id, obj_id, score, T_cam_obj, time=None) -> "PoseResults":
        n = len(np.atleast_1d(scene_id))
        cols = {
            "scene_id": np.asarray(scene_id, dtype=np.int64).reshape(n),
            "im_id": np.asarray(im_id, dtype=np.int64).reshape(n),
            "obj_id": np.asarray(obj_id, dtype=np.int64).reshape(n),
            "score": np.asarray(score, dtype=np.float64).reshape(n),
            "time": (np.full(n, -1.0) if time is None else np.broadcast_to(np.asarray(time, dtype=np.float64), (n,)).copy()),
        }
        return cls(None, np.asarray(T_cam_obj, dtype=np.float64).reshape(n, 4, 4), columns=cols)


def _check_complete_rows(path: Path, header: list[str]) -> None:
    """Refuse a CSV data row with fewer fields than the header (a file cut mid-row), naming the
    row as the readers do (1-based data row, blank lines skipped)."""
    lines = np.array(path.read_text(encoding="utf-8", errors="replace").splitlines()[1:], dtype=str)
    if not len(lines):
        return
    lines = lines[np.char.strip(lines) != ""]
    fields = np.char.count(lines, ",") + 1
    short = np.flatnonzero(fields < len(header))
    if len(short):
        i = int(short[0])
        raise CosyError(f"{fields[i]} of {len(header)} fields ({','.join(header)}): the row is cut short "
                        "(a truncated file?)", path=path, where=f"row {i + 1}")


def read_results(path: str | Path, *, check_rotations: bool = True, rotations: str | None = None) -> PoseResults:
    """Read a BOP results CSV (``scene_id,im_id,obj_id,score,R,t,time``; R row-major, t in mm).

    Raises :class:`CosyError` naming the row (1-based data row, header excluded) on a missing
    column, a malformed number, a non-finite value or a non-orthonormal R. Rotations are checked
    and repaired as :func:`repair_rotations` does with ``rotations`` (default "repair": within
    :data:`ROTATION_REPAIR_TOL` replaced by the nearest rotation, one warning for the file when
    some were off by more than :data:`ROTATION_TOL`); ``check_rotations=False`` means "raw".
    """
    if rotations is None:
        rotations = "repair" if check_rotations else "raw"
    path = Path(path)
    if not path.is_file():
        raise CosyError("file not found", path=path)
    fast = _parse_results_fast(path)
    if fast is not None:  # a well-formed file: numpy alone (anything else: pandas, for its messages)
        ids, score, time, R, t = fast
        n = len(score)
        if n == 0:
            return PoseResults.empty()
        return _results_from(path, ids, score, time, R.reshape(n, 3, 3), t, rotations)
    import pandas as pd

    try:
        df = pd.read_csv(path, dtype=str, keep_default_na=False, skipinitialspace=True)
    except pd.errors.EmptyDataError:
        raise CosyError(f"empty file: expected a header {','.join(RESULTS_COLUMNS)}", path=path) from None
    except (pd.errors.ParserError, UnicodeDecodeError) as e:
        raise CosyError(f"not a valid CSV ({str(e).strip()})", path=path) from None
    df.columns = [c.strip() for c in df.columns]
    missing = [c for c in RESULTS_COLUMNS if c not in df.columns and c != "time"]
    if missing:
        raise CosyError(f"missing column(s) {', '.join(missing)}; expected header {','.join(RESULTS_COLUMNS)}", path=path)
    _check_complete_rows(path, list(df.columns))
    if "time" not in df.columns:
        df["time"] = "-1"
    n = len(df)
    if n == 0:
        return PoseResults.empty()

    def ints(col: str) -> np.ndarray:
        vals = pd.to_numeric(df[col], errors="coerce")
        bad = vals.isna() | (vals != np.round(vals))
        if bad.any():
            i = int(np.flatnonzero(bad.to_numpy())[0])
            raise CosyError(f"column {col}: expected an integer, got {df[col].iloc[i]!r}", path=path, where=f"row {i + 1}")
        return vals.to_numpy().astype(np.int64)

    def floats(col: str) -> np.ndarray:
        vals = pd.to_numeric(df[col], errors="coerce")
        bad = ~np.isfinite(vals.to_numpy(dtype=np.float64))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise CosyError(f"column {col}: expected a finite number, got {df[col].iloc[i]!r}", path=path, where=f"row {i + 1}")
        return vals.to_numpy(dtype=np.float64)

    def vectors(col: str, k: int) -> np.ndarray:
        text = df[col].str.strip()
        parts = text.str.split(r"\s+", regex=True)
        lens = parts.str.len().to_numpy()
        if (lens != k).any():
            i = int(np.flatnonzero(lens != k)[0])
            raise CosyError(f"column {col}: expected {k} space-separated numbers, got {df[col].iloc[i]!r}",
                            path=path, where=f"row {i + 1}")
        try:
            arr = np.array(np.concatenate(parts.to_numpy()), dtype=np.float64).reshape(n, k)
        except ValueError:
            for i, p in enumerate(parts):
                try:
                    np.array(p, dtype=np.float64)
                except ValueError:
                    raise CosyError(f"column {col}: not a number in {df[col].iloc[i]!r}", path=path, where=f"row {i + 1}") from None
            raise
        bad = ~np.isfinite(arr).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise CosyError(f"column {col}: non-finite value in {df[col].iloc[i]!r}", path=path, where=f"row {i + 1}")
        return arr

    R = vectors("R", 9).reshape(n, 3, 3)
    t = vectors("t", 3)
    return _results_from(path, [ints("scene_id"), ints("im_id"), ints("obj_id")], floats("score"), floats("time"),
                         R, t, rotations)


def _results_from(path: Path, ids, score, time, R, t, rotations: str) -> PoseResults:
    """PoseResults of parsed columns, the rotations checked and repaired (:func:`repair_rotations`)."""
    n = len(score)
    R, _ = repair_rotations(R, lambda i: f"row {i + 1}", path=path, what="R", rotations=rotations)
    T = np.zeros((n, 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = t
    T[:, 3, 3] = 1.0
    return PoseResults.from_arrays(ids[0], ids[1], ids[2], score, T, time)


def _parse_results_fast(path: Path):
    """The columns of a well-formed results CSV (the header's columns in any order, no quotes, no
    missing field, every number valid and finite, integer ids): ([scene_id, im_id, obj_id],
    score, time, R (n, 9), t (n, 3)); None for anything else (the pandas reader then says what
    is wrong, naming the row)."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        return None
    if '"' in text:
        return None
    lines = [x for x in text.splitlines() if x.strip()]
    if not lines:
        return None
    header = [c.strip() for c in lines[0].split(",")]
    need = [c for c in RESULTS_COLUMNS if c != "time"]
    if len(set(header)) != len(header) or any(c not in header for c in need):
        return None
    rows = [x.split(",") for x in lines[1:]]
    if any(len(r) != len(header) for r in rows):
        return None
    n = len(rows)
    cols = dict(zip(header, zip(*rows))) if n else {c: () for c in header}
    try:
        def num(c):
            return np.array([x.strip() for x in cols[c]], dtype=np.float64) if n else np.zeros(0)

        ids = [num(c) for c in ("scene_id", "im_id", "obj_id")]
        score = num("score")
        time = num("time") if "time" in cols else np.full(n, -1.0)
        vec = {}
        for c, k in (("R", 9), ("t", 3)):
            parts = [x.split() for x in cols[c]]
            if any(len(q) != k for q in parts):
                return None
            vec[c] = np.array(parts, dtype=np.float64).reshape(n, k)
    except ValueError:
        return None
    if not all(np.isfinite(a).all() for a in ids + [score, time, vec["R"], vec["t"]]):
        return None
    if any((a != np.round(a)).any() for a in ids):
        return None
    return [a.astype(np.int64) for a in ids], score, time, vec["R"], vec["t"]


def format_results(res: PoseResults) -> str:
    """The CSV text of ``res`` (R row-major, t in mm, 6 decimals for t and 9 significant digits for R)."""
    buf = _io.StringIO()
    buf.write(",".join(RESULTS_COLUMNS) + "\n")
    R = clean_rotations(res.T_cam_obj[:, :3, :3]).reshape(-1, 9).tolist()
    t = res.T_cam_obj[:, :3, 3].tolist()
    cols = [res.column(c).tolist() for c in ("scene_id", "im_id", "obj_id", "score", "time")]
    for (scene_id, im_id, obj_id, score, time), Ri, ti in zip(zip(*cols), R, t):  # plain floats: fast
        buf.write(
            f"{int(scene_id)},{int(im_id)},{int(obj_id)},{float(score):.9g},"
            + " ".join(f"{v:.9g}" for v in Ri) + ","
            + " ".join(f"{v:.6f}" for v in ti) + f",{float(time):.6g}\n"
        )
    return buf.getvalue()


def write_results(path: str | Path, res: PoseResults) -> None:
    atomic.write_text(path, format_results(res))


# --------------------------------------------------------------------------------------------
# BOP detections (JSON list)
# --------------------------------------------------------------------------------------------
DETECTION_KEYS = ("scene_id", "image_id", "category_id", "score", "bbox")


def read_detections(path: str | Path) -> pd.DataFrame:
    """BOP detection file: a list of {scene_id, image_id, category_id, score, bbox [x, y, w, h] px, ...}.

    Returns a table with columns scene_id, im_id, obj_id, score, x, y, w, h, time (and
    ``segmentation`` as objects when present).
    """
    import pandas as pd

    path = Path(path)
    data = load_json(path)
    if not isinstance(data, list):
        raise CosyError("expected a JSON list of detections {scene_id, image_id, category_id, score, bbox}", path=path)
    rows = []
    for i, d in enumerate(data):
        where = f"detection {i}"
        for k in DETECTION_KEYS:
            _require(d, k, path, where)
        for k in ("scene_id", "image_id", "category_id"):
            if not isinstance(d[k], int) or isinstance(d[k], bool):
                raise CosyError(f"{k}: expected an integer, got {d[k]!r}", path=path, where=where)
        score = float(_numbers(d["score"], 1, path, where, "score")[0])
        box = _numbers(d["bbox"], 4, path, where, "bbox [x, y, w, h]")
        if box[2] <= 0 or box[3] <= 0:
            raise CosyError(f"bbox has non-positive width or height: {box.tolist()}", path=path, where=where)
        rows.append({"scene_id": d["scene_id"], "im_id": d["image_id"], "obj_id": d["category_id"], "score": score,
                     "x": box[0], "y": box[1], "w": box[2], "h": box[3], "time": float(d.get("time", -1.0)),
                     "segmentation": d.get("segmentation")})
    cols = ["scene_id", "im_id", "obj_id", "score", "x", "y", "w", "h", "time", "segmentation"]
    df = pd.DataFrame(rows, columns=cols)
    for c in ("scene_id", "im_id", "obj_id"):
        df[c] = df[c].astype(np.int64)
    return df


def write_detections(path: str | Path, dets: pd.DataFrame) -> None:
    out = []
    for r in dets.to_dict("records"):
        d = {"scene_id": int(r["scene_id"]), "image_id": int(r["im_id"]), "category_id": int(r["obj_id"]),
             "score": _fmt(r["score"]), "bbox": [_fmt(r[k]) for k in ("x", "y", "w", "h")],
             "time": _fmt(r.get("time", -1.0))}
        seg = r.get("segmentation")
        if seg is not None and not (isinstance(seg, float) and math.isnan(seg)):
            d["segmentation"] = seg
        out.append(d)
    atomic.write_json(path, out, indent=None)
