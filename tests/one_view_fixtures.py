"""Small inputs for the one-view and stage-integrity tests, cut from ``data_samples/``.

``one_image_dataset``: a BOP dataset of ONE image (scene 1, image 0 of data_samples: RGB, depth,
masks, GT, targets), or with ``keep`` several scenes, some of them reduced to one image.
``tiny_templates``: templates of the training-free coarse step, coarse and quick to build.
``bop_rows``: the rows of a BOP results CSV as comparable tuples.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[1] / "data_samples"
TINY_TEMPLATES = {"viewpoints": 40, "inplane": 8}


def one_image_dataset(root: Path, keep: dict[int, list[int] | None] | None = None) -> Path:
    """A copy of data_samples with only the scenes of ``keep`` ({scene_id: image ids, None: all};
    default {1: [0]}: one image), their files, GT and targets. Returns ``root``."""
    keep = {1: [0]} if keep is None else keep
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    for name in ("camera.json", "models", "models_eval"):
        src = DATA / name
        (shutil.copytree if src.is_dir() else shutil.copy)(src, root / name)
    for sid, ims in keep.items():
        src, dst = DATA / "test" / f"{sid:06d}", root / "test" / f"{sid:06d}"
        dst.mkdir(parents=True)
        cams = json.loads((src / "scene_camera.json").read_text())
        ims = [int(i) for i in cams] if ims is None else list(ims)
        for name in ("scene_camera", "scene_gt", "scene_gt_info"):
            doc = json.loads((src / f"{name}.json").read_text())
            (dst / f"{name}.json").write_text(json.dumps({str(i): doc[str(i)] for i in ims}))
        for sub in ("rgb", "depth", "mask", "mask_visib"):
            (dst / sub).mkdir()
            for f in (src / sub).iterdir():
                if int(f.stem.split("_")[0]) in ims:
                    shutil.copy(f, dst / sub / f.name)
    targets = json.loads((DATA / "test_targets_bop19.json").read_text())
    targets = [t for t in targets if t["scene_id"] in keep and (keep[t["scene_id"]] is None
                                                                 or t["im_id"] in keep[t["scene_id"]])]
    (root / "test_targets_bop19.json").write_text(json.dumps(targets))
    return root


def tiny_templates(folder: Path) -> Path:
    from cosy_cli.singleview.training_free import templates as tpl

    tpl.main(TINY_TEMPLATES, DATA / "models", folder, log=lambda m: None, progress=False)
    return folder


def bop_rows(path: Path) -> list[tuple]:
    """(scene_id, im_id, obj_id, score, R (9), t (3)) of every row, rounded, sorted."""
    from cosy_cli.io import bop

    res = bop.read_results(path)
    tab = res.table
    rows = []
    for k in range(len(res)):
        T = res.T_cam_obj[k]
        rows.append((int(tab["scene_id"].iat[k]), int(tab["im_id"].iat[k]), int(tab["obj_id"].iat[k]),
                     round(float(tab["score"].iat[k]), 6), tuple(np.round(T[:3, :3].ravel(), 6)),
                     tuple(np.round(T[:3, 3], 3))))
    return sorted(rows)
