"""Benchmark of `cosy detect` (2D detection, the pipeline's first stage) on held-out scenes.

Runs the shipped detector (or --model) over a held-out synthetic dataset of the `data_samples/`
objects (default /work/heldout; else /tmp/cosy_heldout, made with `cosy synth --seed 101` when
missing, as benchmarks/bench_estimate.py does) and prints COCO AP, AP50, AP75 (pycocotools;
GT = visible boxes of instances with visib_fract >= 0.1, less visible ones ignored), per-object
AP50, the label confusion between objects (look-alikes) and the detector's time per image.

    .venv/bin/python benchmarks/bench_detect.py [--dataset DIR] [--model DETECTOR.onnx] [--scenes N]

Detections are kept from score 0.05 for AP (COCO practice: AP ranks by score); AP50 is also
given for the stage's default --min-score 0.3 (same detections, filtered). --from-gt evaluates
the GT boxes themselves (a sanity check: AP 1).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_estimate import ensure_heldout  # noqa: E402

from cosy_cli.detection import importers, stage  # noqa: E402
from cosy_cli.errors import CosyError  # noqa: E402
from cosy_cli.evaluation import detection_ap  # noqa: E402
from cosy_cli.io.dataset import BopDataset  # noqa: E402

DEFAULT_DATASETS = (Path("/work/heldout"), Path(tempfile.gettempdir()) / "cosy_heldout")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=None,
                    help=f"held-out BOP dataset [{DEFAULT_DATASETS[0]} if present, else {DEFAULT_DATASETS[1]}]")
    ap.add_argument("--model", type=Path, default=None, help="detector ONNX [the shipped one]")
    ap.add_argument("--from-gt", action="store_true", help="evaluate the GT boxes (sanity check)")
    ap.add_argument("--scenes", type=int, default=None, help="only the first N scenes")
    ap.add_argument("--providers", choices=["cpu", "cuda"], default="cpu")
    ap.add_argument("--min-score", type=float, default=0.05)
    args = ap.parse_args()
    dataset = args.dataset or next((d for d in DEFAULT_DATASETS if (d / "test").is_dir()), DEFAULT_DATASETS[1])
    ensure_heldout(dataset)
    ds = BopDataset(dataset, "test")
    scenes = ds.scene_ids[: args.scenes] if args.scenes else ds.scene_ids
    conf = stage.resolve_conf("default", min_score=args.min_score, providers=args.providers)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "dets.json"
        try:
            s = stage.main(conf, dataset, "test", out, overwrite=True, scene_ids=scenes, model=args.model,
                           from_gt=args.from_gt, log=lambda *_: None, progress=True)
        except CosyError as e:
            sys.exit(f"error: {e}")
        dets = importers.read_detections_any(out, ds)
    first = ds.image_ids(scenes[0])[0]
    h, w = ds.read_rgb(scenes[0], first).shape[:2]
    print(f"dataset {dataset} (held-out), scenes {scenes}, {s['images']} images of {w}x{h}; source: {s['source']}")
    scores = detection_ap.coco_ap(dets, ds, scenes, conf["min_visib_fract"])
    table = detection_ap.confusion_matrix(dets, ds, scenes, conf["min_visib_fract"])
    scores["confusion"] = detection_ap.confusion_summary(table)
    print(detection_ap.format_scores(scores))
    at_default = stage.keep_best(dets, stage.CONFS["default"]["min_score"], conf["max_per_image"])
    s30 = detection_ap.coco_ap(at_default, ds, scenes, conf["min_visib_fract"])
    print(f"with --min-score {stage.CONFS['default']['min_score']}: AP {s30['AP']:.3f}  AP50 {s30['AP50']:.3f}  "
          f"AP75 {s30['AP75']:.3f}  ({s30['detections']} detections)")
    wrong = [(int(g), c, int(n)) for g, row in table.iterrows() for c, n in row.items()
             if c not in (g, detection_ap.MISSED) and n > 0]
    if wrong:
        print("look-alike confusions (GT object -> label of its best-overlapping detection, IoU >= 0.5): "
              + ", ".join(f"{g} -> {c}: {n}/{int(table.loc[g].sum())}"
                          for g, c, n in sorted(wrong, key=lambda x: -x[2])))
    else:
        found = int(sum(table.loc[g, g] for g in table.index if g in table.columns))
        print(f"look-alike confusions: none ({found} of {int(table.to_numpy().sum())} GT boxes found, all with "
              "their own label)")
    if s.get("time_per_image_s"):
        print(f"detector time per {w}x{h} image: mean {s['time_per_image_s'] * 1e3:.1f} ms, median "
              f"{s['time_per_image_median_s'] * 1e3:.1f} ms (resize + network + decoding + NMS; {args.providers}, "
              f"{os.cpu_count()} cores)")


if __name__ == "__main__":
    main()
