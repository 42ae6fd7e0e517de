"""Benchmark of `cosy estimate` (single-view candidates, CosyPose stage 1) on held-out scenes.

Held-out synthetic scenes of the `data_samples/` objects (a new seed: by default `cosy synth
--scenes 4 --views 6 --objects 6 --seed 101`, written to --dataset if missing), GT visible boxes as
detections. For each chain it prints, after every step (coarse, ICP, refiner iterations 1/2/4),
the recall of ADD-S < 0.1 diameter and the mean / median ADD-S (mm), and the time per detection
and per image (one process, this machine's cores).

    .venv/bin/python benchmarks/bench_estimate.py [--dataset HELDOUT] [--chains all]

Chains: templates (alone), templates-icp, templates-refiner, templates-icp-refiner, network
(coarse + refiner networks, when a coarse model exists). Networks: the shipped ONNX models unless
--coarse/--refiner name others.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import argparse  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from cosy_cli.evaluation.pose_error import adi  # noqa: E402
from cosy_cli.io.dataset import BopDataset  # noqa: E402
from cosy_cli.objects import ObjectDatabase  # noqa: E402
from cosy_cli.singleview import estimate_stage  # noqa: E402

CHAINS = {
    "templates": {"coarse": "templates", "refiner": "none", "depth_refine": "none", "top_k": 1},
    "templates-old": {"coarse": "templates", "refiner": "none", "depth_refine": "none", "top_k": 1, "verify_top": 0,
                      "rgb_refine": "none"},
    "templates-search": {"coarse": "templates", "refiner": "none", "depth_refine": "none", "top_k": 1,
                         "rgb_refine": "search"},  # RGB: the local-search refinement (default before contour)
    "templates-contour": {"coarse": "templates", "refiner": "none", "depth_refine": "none", "top_k": 1,
                          "rgb_refine": "contour"},  # RGB: contour alignment (= "templates", the default)
    "templates-icp-old": {"coarse": "templates", "refiner": "none", "depth_refine": "icp", "top_k": 5,
                          "verify_top": 0},
    "templates-icp": {"coarse": "templates", "refiner": "none", "depth_refine": "icp"},
    "templates-refiner": {"coarse": "templates", "refiner": "network", "depth_refine": "none", "top_k": 1},
    "templates-icp-refiner": {"coarse": "templates", "refiner": "network", "depth_refine": "icp"},
    "network": {"coarse": "network", "refiner": "network", "depth_refine": "none", "top_k": 1},
}


def gt_poses(ds: BopDataset, dets) -> np.ndarray:
    cache = {}
    out = np.zeros((len(dets), 4, 4))
    for i, (sid, im, gi) in enumerate(zip(dets["scene_id"], dets["im_id"], dets["gt_index"])):
        if sid not in cache:
            cache[sid] = ds.scene_gt(sid)
        out[i] = cache[sid][im][gi].T_cam_obj
    return out


def score_steps(summary: dict, ds: BopDataset, db: ObjectDatabase) -> list[tuple]:
    dets = summary["detections_table"].iloc[summary["det_index"]]
    T_gt = gt_poses(ds, dets)
    obj = dets["obj_id"].to_numpy()
    rows = []
    for name, T in summary["steps"].items():
        err = np.zeros(len(T))
        diam = np.zeros(len(T))
        for o in np.unique(obj):
            m = obj == o
            err[m] = adi(T[m], T_gt[m], db[o].points)
            diam[m] = db[o].diameter
        rows.append((name, float((err < 0.1 * diam).mean()), float(err.mean()), float(np.median(err))))
    return rows


def ensure_heldout(dataset: Path) -> Path:
    """The held-out synthetic dataset at ``dataset``, made with `cosy synth --seed 101` (4 scenes x 6
    views x 6 objects of the data_samples objects) when it is missing."""
    if not (Path(dataset) / "test").is_dir():
        subprocess.run([sys.executable, "-m", "cosy_cli", "synth", "--out", str(dataset), "--scenes", "4",
                        "--views", "6", "--objects", "6", "--seed", "101", "--quiet"], check=True)
    return Path(dataset)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=Path(tempfile.gettempdir()) / "cosy_heldout")
    ap.add_argument("--chains", default="all", help=f"comma-separated of {', '.join(CHAINS)} or all")
    ap.add_argument("--coarse", type=Path, default=None, help="coarse ONNX [shipped]")
    ap.add_argument("--refiner", type=Path, default=None, help="refiner ONNX [shipped]")
    ap.add_argument("--templates-dir", type=Path, default=Path(tempfile.gettempdir()) / "cosy_bench_templates")
    ap.add_argument("--scenes", type=int, default=None, help="only the first N scenes")
    args = ap.parse_args()
    ensure_heldout(args.dataset)
    ds = BopDataset(args.dataset, "test")
    db = ObjectDatabase.from_models_dir(ds.models_dir)
    scenes = ds.scene_ids[: args.scenes] if args.scenes else None
    coarse = args.coarse or (estimate_stage.SHIPPED_COARSE if estimate_stage.SHIPPED_COARSE.is_file() else None)
    refiner = args.refiner or (estimate_stage.SHIPPED_REFINER if estimate_stage.SHIPPED_REFINER.is_file() else None)
    names = list(CHAINS) if args.chains == "all" else args.chains.split(",")
    print(f"dataset {args.dataset} (held-out, GT visible boxes, visib_fract >= 0.1); coarse model {coarse}; "
          f"refiner model {refiner}")
    print(f"{'chain':24s} {'step':12s} {'recall':>7s} {'mean ADD-S':>11s} {'median':>8s}")
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            c = dict(CHAINS[name])
            if "network" in (c["coarse"], c["refiner"]) and (refiner is None or (c["coarse"] == "network" and coarse is None)):
                print(f"{name:24s} skipped: no model")
                continue
            conf = estimate_stage.resolve_conf("default", **c)
            s = estimate_stage.main(conf, args.dataset, "test", Path(tmp) / f"{name}.csv", overwrite=True,
                                    scene_ids=scenes, from_gt=True, coarse_model=coarse, refiner_model=refiner,
                                    templates_dir=args.templates_dir, log=lambda *_: None, progress=False,
                                    keep_steps=True)
            for step, rec, mean, med in score_steps(s, ds, db):
                print(f"{name:24s} {step:12s} {rec:7.3f} {mean:9.2f} mm {med:6.2f} mm")
            print(f"{name:24s} time: {s['time_per_detection_s'] * 1e3:.0f} ms per detection, "
                  f"{s['time_per_image_s'] * 1e3:.0f} ms per image ({s['detections']} detections, "
                  f"{s['images_with_detections']} images)")


if __name__ == "__main__":
    main()
