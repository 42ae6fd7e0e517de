"""Realistic single-view object candidates from ground truth (``cosy synth-candidates``).

Turns the GT poses of a BOP split into a BOP results CSV the way a single-view detector + pose
estimator errs, so that the multi-view stages can be developed and measured without networks:

* missed detections (``p_miss``), only GT instances with ``visib_fract >= min_visib_fract``
  (when ``scene_gt_info.json`` exists) get a candidate;
* depth error: the translation is scaled along its viewing ray by ``1 + depth_rel * N(0, 1)``
  (1 % of the distance); lateral error ``N(0, lateral_mm)`` across the ray (1 mm); rotation error
  with RMS angle ``rot_deg`` (2 deg) about the model origin;
* symmetric flips (``p_flip``): the pose is multiplied by a random non-identity element of the
  object's symmetry set (equivalent pose, different representation);
* gross errors (``p_gross``): a random rotation and a centre off by 0.5-1.5 diameters;
* look-alike confusions (``p_lookalike``): the label becomes a look-alike object (``--lookalikes
  6:7`` or found automatically: objects whose sorted bounding-box sizes and diameters agree
  within 5 %), pose unchanged;
* false positives: per image ``Poisson(fp_per_image)`` candidates of a random object at a random
  rotation, centred on a random pixel at a depth within the image's GT depth range.

``profile="clean"`` gives the exact GT poses: no misses, no noise, no flips, no false positives.
A sidecar CSV (``gt_out``) says where each candidate came from: ``cand_id`` (0-based row of the
results CSV), ``gt_index`` (index in scene_gt.json of the image, -1 for false positives),
``instance_id`` (physical instance in the scene: GT instances with the same obj_id whose world
poses agree within 5 mm when the cameras' world poses are known, else the GT index), ``gt_obj_id``,
``kind`` (ok, gross, lookalike, fp) and ``flipped``.
Units: mm, degrees where a name says so.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import CosyError
from ..geometry.poses import invert, make_pose
from ..geometry.rotations import axis_angle_to_matrix, random_rotations
from ..io import atomic, bop
from ..io.bop import PoseResults
from ..io.dataset import BopDataset
from ..objects.symmetries import symmetry_set


@dataclass(frozen=True)
class CandidateNoise:
    p_miss: float = 0.1
    depth_rel: float = 0.01  # std of the relative depth error
    lateral_mm: float = 1.0  # std of the error across the viewing ray, mm
    rot_deg: float = 2.0  # RMS rotation error, degrees
    p_flip: float = 0.5  # probability of a symmetric flip (symmetric objects only)
    p_gross: float = 0.03
    p_lookalike: float = 0.1  # probability of a label swap (objects with a look-alike only)
    fp_per_image: float = 0.3  # mean number of false positives per image
    min_visib_fract: float = 0.1


PROFILES: dict[str, CandidateNoise] = {
    "realistic": CandidateNoise(),
    "clean": CandidateNoise(p_miss=0.0, depth_rel=0.0, lateral_mm=0.0, rot_deg=0.0, p_flip=0.0, p_gross=0.0,
                            p_lookalike=0.0, fp_per_image=0.0),
}
SIDECAR_COLUMNS = ["cand_id", "scene_id", "im_id", "gt_index", "instance_id", "gt_obj_id", "kind", "flipped"]


def noise_profile(profile: str = "realistic", **overrides) -> CandidateNoise:
    """A named profile with some knobs overridden (None values are ignored)."""
    if profile not in PROFILES:
        raise CosyError(f"unknown profile {profile!r} (known: {', '.join(PROFILES)})")
    known = {f.name for f in fields(CandidateNoise)}
    bad = [k for k in overrides if k not in known]
    if bad:
        raise CosyError(f"unknown noise option(s) {', '.join(bad)} (known: {', '.join(sorted(known))})")
    noise = replace(PROFILES[profile], **{k: v for k, v in overrides.items() if v is not None})
    for f in fields(noise):
        v = getattr(noise, f.name)
        if not (math.isfinite(v) and v >= 0) or (f.name.startswith("p_") and v > 1):
            expected = "a probability in [0, 1]" if f.name.startswith("p_") else ">= 0"
            raise CosyError(f"{f.name} = {v}: expected {expected}")
    return noise


# --------------------------------------------------------------------------------------------
# look-alikes
# --------------------------------------------------------------------------------------------
def parse_lookalikes(text: str | None) -> dict[int, list[int]] | None:
    """``"6:7,3:4"`` -> {6: [7], 7: [6], 3: [4], 4: [3]} (symmetric); None/"" -> None (automatic);
    ``"none"`` -> {} (no confusions)."""
    if text is None or str(text).strip() == "":
        return None
    if str(text).strip().lower() == "none":
        return {}
    out: dict[int, list[int]] = {}
    for part in str(text).split(","):
        ids = part.strip().split(":")
        try:
            a, b = (int(x) for x in ids)
        except ValueError:
            raise CosyError(f"--lookalikes: expected pairs like 6:7,3:4, got {part.strip()!r}") from None
        out.setdefault(a, []).append(b)
        out.setdefault(b, []).append(a)
    return {k: sorted(set(v)) for k, v in out.items()}


def find_lookalikes(infos: dict[int, bop.ModelInfo], rel_tol: float = 0.05) -> dict[int, list[int]]:
    """Objects whose sorted bbox sizes and diameters agree within ``rel_tol``."""
    ids = sorted(infos)
    out: dict[int, list[int]] = {}
    for i, a in enumerate(ids):
        sa, da = np.sort(infos[a].size_xyz), infos[a].diameter
        for b in ids[i + 1:]:
            sb, db = np.sort(infos[b].size_xyz), infos[b].diameter
            if np.all(np.abs(sa - sb) <= rel_tol * np.maximum(sa, sb)) and abs(da - db) <= rel_tol * max(da, db):
                out.setdefault(a, []).append(b)
                out.setdefault(b, []).append(a)
    return out


# --------------------------------------------------------------------------------------------
# simulation
# --------------------------------------------------------------------------------------------
def _instance_ids(cams: dict[int, bop.SceneCamera], gt: dict[int, list[bop.GtInstance]], tol_mm: float = 5.0):
    """{(im_id, gt_index): instance id} for one scene."""
    known = all(cams.get(im) is not None and cams[im].T_cam_world is not None for im in gt)
    out = {}
    if not known:
        for im, insts in gt.items():
            for k in range(len(insts)):
                out[(im, k)] = k
        return out
    inst_pos: list[tuple[int, np.ndarray]] = []
    for im in sorted(gt):
        T_world_cam = invert(cams[im].T_cam_world)
        for k, g in enumerate(gt[im]):
            p = (T_world_cam @ g.T_cam_obj)[:3, 3]
            match = -1
            for n, (o, q) in enumerate(inst_pos):
                if o == g.obj_id and np.linalg.norm(p - q) < tol_mm:
                    match = n
                    break
            if match < 0:
                inst_pos.append((g.obj_id, p))
                match = len(inst_pos) - 1
            out[(im, k)] = match
    return out


def _image_size(ds: BopDataset, K: np.ndarray) -> tuple[float, float]:
    cam = ds.camera()
    if cam is not None:
        return float(cam.width), float(cam.height)
    return 2.0 * float(K[0, 2]) + 1.0, 2.0 * float(K[1, 2]) + 1.0


def simulate_candidates(ds: BopDataset, noise: CandidateNoise, seed: int = 0,
                        lookalikes: dict[int, list[int]] | None = None) -> tuple[PoseResults, pd.DataFrame]:
    """Candidates for every scene of ``ds`` (GT needed) and the sidecar table (see module doc)."""
    rng = np.random.default_rng(seed)
    infos = ds.models_info()
    obj_list = sorted(infos)
    if lookalikes is None:
        lookalikes = find_lookalikes(infos)
    syms = {o: symmetry_set(i.symmetries_discrete, i.symmetries_continuous, 64) for o, i in infos.items()}
    rows = []  # (scene, im, obj, score, T, gt_index, instance, gt_obj, kind, flipped)
    for scene_id in ds.scene_ids:
        if not ds.has_gt(scene_id):
            raise CosyError("scene_gt.json is missing: synth-candidates needs ground truth",
                            path=ds.scene_file(scene_id, "scene_gt"))
        gt = ds.scene_gt(scene_id)
        cams = ds.scene_camera(scene_id)
        info_path = ds.scene_file(scene_id, "scene_gt_info")
        gt_info = ds.scene_gt_info(scene_id) if info_path.is_file() else None
        inst_ids = _instance_ids(cams, gt)
        for im_id, insts in gt.items():
            if im_id not in cams:
                raise CosyError(f"image {im_id} of scene_gt.json has no entry in scene_camera.json",
                                path=ds.scene_file(scene_id, "scene_camera"))
            K = cams[im_id].K
            img_rows = []
            depths = []
            for k, g in enumerate(insts):
                if g.obj_id not in infos:
                    raise CosyError(f"obj_id {g.obj_id} is not in {ds.models_info_path}",
                                    path=ds.scene_file(scene_id, "scene_gt"), where=f"image {im_id}, instance {k}")
                if gt_info is not None:
                    gi = gt_info.get(im_id, [])
                    if k >= len(gi):
                        raise CosyError(f"no entry for instance {k}", path=info_path, where=f"image {im_id}")
                    if gi[k].visib_fract < noise.min_visib_fract:
                        continue
                depths.append(g.T_cam_obj[2, 3])
                if rng.random() < noise.p_miss:
                    continue
                T = g.T_cam_obj.copy()
                kind = "ok"
                obj = g.obj_id
                diam = infos[obj].diameter
                flipped = 0
                S = syms[obj]
                if len(S) > 1 and rng.random() < noise.p_flip:
                    T = T @ S[1 + int(rng.integers(len(S) - 1))]
                    flipped = 1
                if rng.random() < noise.p_gross:
                    kind = "gross"
                    T[:3, :3] = random_rotations(1, rng)[0]
                    d = rng.normal(size=3)
                    d -= d.dot(T[:3, 3]) / max(T[:3, 3].dot(T[:3, 3]), 1e-12) * T[:3, 3]  # a GT at the camera centre: any d
                    d /= max(np.linalg.norm(d), 1e-9)
                    T[:3, 3] = T[:3, 3] + d * diam * rng.uniform(0.5, 1.5)
                    T[:3, 3] *= 1.0 + 0.1 * rng.normal()
                    score = rng.uniform(0.3, 0.9)
                else:
                    sig = math.radians(noise.rot_deg) / math.sqrt(3.0)
                    T[:3, :3] = T[:3, :3] @ axis_angle_to_matrix(rng.normal(scale=sig, size=3))
                    t = T[:3, 3]
                    ray = t / max(np.linalg.norm(t), 1e-9)
                    lat = rng.normal(scale=noise.lateral_mm, size=3) if noise.lateral_mm > 0 else np.zeros(3)
                    lat -= lat.dot(ray) * ray
                    T[:3, 3] = t * (1.0 + noise.depth_rel * rng.normal()) + lat
                    score = rng.uniform(0.6, 1.0)
                if lookalikes.get(obj) and rng.random() < noise.p_lookalike:
                    alts = lookalikes[obj]
                    obj = int(alts[int(rng.integers(len(alts)))])
                    if kind == "ok":
                        kind = "lookalike"
                        score = rng.uniform(0.4, 0.9)
                img_rows.append((scene_id, im_id, obj, score, T, k, inst_ids[(im_id, k)], g.obj_id, kind, flipped))
            n_fp = int(rng.poisson(noise.fp_per_image)) if noise.fp_per_image > 0 else 0
            if n_fp:
                W, H = _image_size(ds, K)
                zlo, zhi = (min(depths), max(depths)) if depths else (500.0, 1000.0)
                for _ in range(n_fp):
                    obj = int(obj_list[int(rng.integers(len(obj_list)))])
                    u, v = rng.uniform(0.1, 0.9) * W, rng.uniform(0.1, 0.9) * H
                    z = rng.uniform(0.9 * zlo, 1.1 * zhi)
                    ray = np.linalg.solve(K, np.array([u, v, 1.0]))
                    T = make_pose(random_rotations(1, rng)[0], ray * z / ray[2])
                    img_rows.append((scene_id, im_id, obj, rng.uniform(0.1, 0.7), T, -1, -1, -1, "fp", 0))
            img_rows.sort(key=lambda r: -r[3])  # like a detector: by decreasing score
            rows.extend(img_rows)
    if not rows:
        return PoseResults.empty(), pd.DataFrame({c: pd.Series(dtype=object if c == "kind" else np.int64)
                                                  for c in SIDECAR_COLUMNS})
    cols = list(zip(*rows))
    res = PoseResults.from_arrays(cols[0], cols[1], cols[2], cols[3], np.stack(cols[4]), time=-1.0)
    side = pd.DataFrame({
        "cand_id": np.arange(len(rows)), "scene_id": cols[0], "im_id": cols[1], "gt_index": cols[5],
        "instance_id": cols[6], "gt_obj_id": cols[7], "kind": cols[8], "flipped": cols[9],
    })
    return res, side


def main(dataset: str | Path, split: str, out: str | Path, profile: str = "realistic", seed: int = 0,
         gt_out: str | Path | None = None, lookalikes: str | dict | None = None, overwrite: bool = True,
         log=print, **knobs) -> dict:
    """Write candidates (BOP results CSV, atomically) and optionally the sidecar CSV.

    ``knobs`` override fields of the profile's :class:`CandidateNoise`. Returns a summary dict.
    """
    out = Path(out)
    if out.exists() and not overwrite:
        raise CosyError("exists (use --overwrite)", path=out)
    noise = noise_profile(profile, **knobs)
    ds = BopDataset(dataset, split)
    la = parse_lookalikes(lookalikes) if not isinstance(lookalikes, dict) else lookalikes
    res, side = simulate_candidates(ds, noise, seed=seed, lookalikes=la)
    bop.write_results(out, res)
    if gt_out is not None:
        atomic.write_text(gt_out, side.to_csv(index=False))
    kinds = side["kind"].value_counts().to_dict()
    summary = {"candidates": len(res), "kinds": {k: int(v) for k, v in kinds.items()}, "noise": asdict(noise),
               "seed": seed}
    log(f"synth-candidates: {len(res)} candidates ({', '.join(f'{k} {v}' for k, v in sorted(kinds.items()))}) -> {out}")
    return summary
