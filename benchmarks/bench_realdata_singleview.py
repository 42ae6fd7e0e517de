"""Training-free single-view candidates on real images: the old chain against the new one.

Data (read from ../shared/realdata/, skipped with a message when absent), visible GT boxes as
detections (`cosy estimate --from-gt`):

* ``lmo``: ``lmo_dev/`` (LM-O, RGB only), BOP AR (MSSD, MSPD) with its targets file and
  ``models_eval/``. Settings were chosen on the odd scene ids; report on ``--scenes even``.
* ``ycbv``: ``ycbv_0000/`` (RGB-D), copied to a work folder and completed with `cosy gt-info`
  (the release has no scene_gt_info.json); BOP19 AR (VSD, MSSD, MSPD) on frames ``--frames``
  (a targets file of those frames). Settings were chosen on frames 1-5; report on 6-10.

Variants: ``old`` (template score only: ``verify_top 0``, top 5 to ICP, no RGB refinement: the
chain before issue 18), ``verify`` (templates verified by rendering, no refinement), ``new`` (the
default: verification, then the RGB refinement (rgb_refine auto: contour) where there is no
depth, or ICP on 16 hypotheses picked by depth fit + image score), ``new-top5`` (new, 5
hypotheses to ICP), ``new-vt64`` (64 hypotheses verified), ``new-fitonly`` (ICP pick by depth fit
alone: ``image_weight 0``), ``search``, ``contour`` and ``search+contour`` (RGB: the local search,
the contour alignment (:mod:`cosy_cli.singleview.contour`), or both). Also prints
the fraction of rotations within 15 deg (modulo symmetries), the median translation error (mm)
and time per image.

    .venv/bin/python benchmarks/bench_realdata_singleview.py --data lmo --scenes even
    .venv/bin/python benchmarks/bench_realdata_singleview.py --data ycbv --frames 6-10
    .venv/bin/python benchmarks/bench_realdata_singleview.py --data lmo --scenes odd --sweep all

``--sweep``: the speed/accuracy of verification settings (``SWEEP``: the first settings ``prev``,
each speed-up alone, the default, two faster ones), all on each image in turn in one process, so
that the timings share the machine's load; the first image is run once untimed (renderers and
decimated copies are made once per object set), and the time per image is the median (and mean)
over images, with the detections per image. For the working tree against a git revision of the
code (not only of the settings) see bench_stage1_speed.py.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import argparse  # noqa: E402
import json  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
VARIANTS = {
    "old": {"verify_top": 0, "rgb_refine": "none", "top_k": 5},
    "verify": {"rgb_refine": "none"},
    "new": {},
    "new-top5": {"top_k": 5},
    "new-vt64": {"verify_top": 64},
    "new-fitonly": {"image_weight": 0.0},
    "search": {"rgb_refine": "search"},
    "contour": {"rgb_refine": "contour"},
    "search+contour": {"rgb_refine": "search+contour"},
}


def _parse_range(text: str) -> list[int]:
    a, _, b = text.partition("-")
    return list(range(int(a), int(b or a) + 1))


def rotation_stats(pred_csv: Path, ds, db, scene_ids, im_ids=None) -> tuple[float, float]:
    """(fraction with rotation error < 15 deg modulo symmetries, median translation error mm) of the
    candidates of ``pred_csv`` against the GT instance of their detection (same object, image;
    nearest translation)."""
    from cosy_cli.io import bop

    res = bop.read_results(pred_csv)
    rot, tr = [], []
    gts = {s: ds.scene_gt(s) for s in scene_ids}
    tab = res.table
    for i in range(len(res)):
        s, im, o = int(tab.scene_id.iloc[i]), int(tab.im_id.iloc[i]), int(tab.obj_id.iloc[i])
        if im_ids is not None and im not in im_ids:
            continue
        inst = [g for g in gts.get(s, {}).get(im, []) if g.obj_id == o]
        if not inst:
            continue
        T = res.T_cam_obj[i]
        g = min(inst, key=lambda g: np.linalg.norm(g.T_cam_obj[:3, 3] - T[:3, 3]))
        S = db[o].symmetries_with_steps(64)[:, :3, :3]
        c = (np.einsum("ij,sij->s", T[:3, :3], g.T_cam_obj[:3, :3] @ S) - 1) / 2
        rot.append(np.degrees(np.arccos(np.clip(c, -1, 1))).min())
        tr.append(np.linalg.norm(T[:3, 3] - g.T_cam_obj[:3, 3]))
    return float(np.mean(np.array(rot) < 15)), float(np.median(tr))


def run(data: str, scene_ids, targets, variants, work: Path, templates_dir: Path, im_ids=None) -> None:
    from cosy_cli.evaluation import evaluate_stage
    from cosy_cli.io.dataset import BopDataset
    from cosy_cli.objects import ObjectDatabase
    from cosy_cli.singleview import estimate_stage

    if data == "lmo":
        root, split, metrics = REALDATA / "lmo_dev", "test", "bop19"
    else:
        from bench_realdata_multiview import prepare_ycbv

        root, split, metrics = prepare_ycbv(REALDATA / "ycbv_0000", work / "ycbv_0000"), "train_real", "bop19"
    ds = BopDataset(root, split)
    db = ObjectDatabase.from_models_dir(root / ("models_eval" if (root / "models_eval").is_dir() else "models"))
    for name in variants:
        conf = estimate_stage.resolve_conf("default", **VARIANTS[name])
        out = work / f"{data}_{name}.csv"
        s = estimate_stage.main(conf, root, split, out, overwrite=True, scene_ids=scene_ids, from_gt=True,
                                templates_dir=templates_dir, log=lambda *_: None, progress=False)
        sc = evaluate_stage.main(None, root, split, out, work / f"eval_{data}_{name}", overwrite=True,
                                 targets=targets, metrics=metrics, scene_ids=scene_ids, log=lambda *_: None,
                                 progress=False)
        r15, tmed = rotation_stats(out, ds, db, scene_ids or ds.scene_ids, im_ids)
        ar = sc.get("bop19_average_recall")
        print(f"{data:5s} {name:14s} AR(MSSD,MSPD) {sc['bop19_average_recall_mssd_mspd']:.3f}  "
              f"BOP19 AR {'n/a' if ar is None else f'{ar:.3f}'}  MSSD {sc['bop19_average_recall_mssd']:.3f}  "
              f"MSPD {sc['bop19_average_recall_mspd']:.3f}  rot<15 {r15:.3f}  median t err {tmed:.0f} mm  "
              f"{s['time_per_image_s']:.2f} s/image ({s['detections']} detections, {s['method']})", flush=True)


# --sweep: speed/accuracy of verification settings, side by side (interleaved per image, one process)
PREV = {"verify_top": 64, "rank_faces": 0, "rounds": 4, "samples": 24, "refine_faces": 0,
        "shading": "pixel"}  # the first settings (before speed-ups)
SWEEP = {
    "prev": PREV,
    "vt32": {**PREV, "verify_top": 32},
    "faces1000": {**PREV, "max_faces": 1000},
    "crop48": {**PREV, "crop": 48},
    "r3x16": {**PREV, "rounds": 3, "samples": 16},
    "cascade+r3x16": {**PREV, "rank_faces": 1000, "rank_keep": 8, "rounds": 3, "samples": 16},
    "default-1000": {"rank_faces": 1000},  # the default before the 600-face first pass
    "default-pixel": {"shading": "pixel"},  # per-fragment lighting (the same colours to 1 grey level)
    "search1500": {"refine_faces": 1500},  # the search on 1500-face copies
    "default": {},  # cascade (600 / 3000 faces) + search r3x16 + 48 hypotheses, lit per vertex
    "fast2000": {"verify_top": 48, "rank_faces": 800, "rank_keep": 6, "rounds": 2, "samples": 16, "max_faces": 2000,
                 "refine_faces": 0},
    "fast1500": {"verify_top": 32, "rank_faces": 0, "rounds": 2, "samples": 16, "max_faces": 1500, "refine_faces": 0},
}


def sweep(scene_ids, names, templates_dir: Path) -> None:
    """Per variant: the RGB chain (templates -> verification -> RGB search) on the visible GT boxes of
    lmo_dev scenes ``scene_ids``, all variants on each image in turn; prints the per-detection mean
    of the BOP AR (MSSD, MSPD) recalls (one candidate per GT instance, so the same as the
    evaluation's), rotations within 15 deg and seconds per image."""
    import time

    from cosy_cli.detection.boxes import clip_xyxy
    from cosy_cli.detection.importers import detections_from_gt
    from cosy_cli.evaluation.pose_error import mspd, mssd
    from cosy_cli.io.dataset import BopDataset
    from cosy_cli.objects import ObjectDatabase
    from cosy_cli.singleview import templates as tpl
    from cosy_cli.singleview.estimate_stage import VERIFY_TOP_RGB, ensure_templates
    from cosy_cli.singleview.verify import Verifier, VerifyConf

    root = REALDATA / "lmo_dev"
    ds = BopDataset(root, "test")
    db = ObjectDatabase.from_models_dir(root / "models")
    dbe = ObjectDatabase.from_models_dir(root / "models_eval")
    ensure_templates(root / "models", templates_dir, log=lambda *_: None)
    ts = tpl.TemplateSet.load(templates_dir)
    dets = detections_from_gt(ds, scene_ids or ds.scene_ids, 0.1)
    syms = {o: dbe[o].symmetries_with_steps(64) for o in dbe.obj_ids}
    th_mssd, th_mspd = np.arange(0.05, 0.51, 0.05), np.arange(5, 51, 5)
    vers, res = {}, {n: {"ar": [], "rot": [], "t": [], "dets": []} for n in names}
    for n in names:
        p = dict(SWEEP[n])
        vers[n] = (p.pop("verify_top", VERIFY_TOP_RGB), Verifier(db, VerifyConf(**p)))
    first = True
    for (sid, im), idx in dets.groupby(["scene_id", "im_id"]).indices.items():
        d = dets.iloc[idx]
        rgb, K = ds.read_rgb(sid, im), ds.scene_camera(sid)[im].K
        boxes = clip_xyxy(d[["x", "y", "w", "h"]].to_numpy(), rgb.shape[1], rgb.shape[0])
        ids = d["obj_id"].to_numpy()
        gt = ds.scene_gt(sid)[im]
        T_gt = np.stack([gt[g].T_cam_obj for g in d["gt_index"]])
        if first:  # untimed warm-up: renderers and decimated copies are made once per object set
            for n in names:
                nv, v = vers[n]
                h = tpl.match_templates(ts, rgb, K, boxes, ids, top_k=nv, params=tpl.MatchParams(nms_deg=10.0))
                r = v.rank(rgb, K, boxes, ids, h.T_cam_obj, h.scores)
                v.refine(r.obs, ids, r.T_cam_obj[:, 0], r.prior[:, 0], r.score[:, 0])
            first = False
        for n in names:
            nv, v = vers[n]
            t0 = time.perf_counter()
            h = tpl.match_templates(ts, rgb, K, boxes, ids, top_k=nv, params=tpl.MatchParams(nms_deg=10.0))
            r = v.rank(rgb, K, boxes, ids, h.T_cam_obj, h.scores)
            T, _ = v.refine(r.obs, ids, r.T_cam_obj[:, 0], r.prior[:, 0], r.score[:, 0])
            res[n]["t"].append(time.perf_counter() - t0)
            res[n]["dets"].append(len(ids))
            for i, o in enumerate(ids):
                m, S = dbe[int(o)], syms[int(o)]
                e1 = mssd(T[i:i + 1], T_gt[i:i + 1], m.points, S)[0] / m.diameter
                e2 = mspd(T[i:i + 1], T_gt[i:i + 1], K, m.points, S)[0] * 640.0 / rgb.shape[1]
                res[n]["ar"].append(((e1 < th_mssd).mean() + (e2 < th_mspd).mean()) / 2)
                c = (np.einsum("ij,sij->s", T[i, :3, :3], T_gt[i, :3, :3] @ S[:, :3, :3]) - 1) / 2
                res[n]["rot"].append(np.degrees(np.arccos(np.clip(c, -1, 1))).min() < 15)
    for n in names:
        vers[n][1].close()
        r = res[n]
        print(f"lmo sweep {n:18s} AR(MSSD,MSPD) {np.mean(r['ar']):.3f}  rot<15 {np.mean(r['rot']):.3f}  "
              f"{np.median(r['t']):.3f} s/image median (mean {np.mean(r['t']):.3f}; "
              f"{np.median(r['dets']):.0f} detections/image, {len(r['ar'])} detections, {len(r['t'])} images)",
              flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", choices=("lmo", "ycbv"), default="lmo")
    ap.add_argument("--scenes", default="even", help="lmo: even | odd | all | comma-separated ids")
    ap.add_argument("--frames", default="6-10", help="ycbv: image ids evaluated, e.g. 6-10 (held out) or 1-5")
    ap.add_argument("--variants", default="old,new", help=f"comma-separated of {', '.join(VARIANTS)}")
    ap.add_argument("--sweep", default=None,
                    help=f"lmo only: compare verification settings side by side instead ({', '.join(SWEEP)} or all)")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "cosy_bench_realdata_sv")
    args = ap.parse_args()
    if not REALDATA.is_dir():
        print(f"skipped: {REALDATA} is absent")
        return
    args.work.mkdir(parents=True, exist_ok=True)
    variants = args.variants.split(",")
    if args.data == "lmo":
        ids = list(range(1, 32))
        scene_ids = {"even": [i for i in ids if i % 2 == 0], "odd": [i for i in ids if i % 2 == 1],
                     "all": None}.get(args.scenes) if args.scenes in ("even", "odd", "all") else \
            [int(x) for x in args.scenes.split(",")]
        if args.sweep:
            sweep(scene_ids, list(SWEEP) if args.sweep == "all" else args.sweep.split(","), args.work / "templates_lmo")
            return
        targets = None
        run("lmo", scene_ids, targets, variants, args.work, args.work / "templates_lmo")
    else:
        frames = _parse_range(args.frames)
        targets = args.work / f"ycbv_targets_{args.frames}.json"
        targets.write_text(json.dumps([{"scene_id": 0, "im_id": i, "obj_id": o, "inst_count": 1}
                                       for i in frames for o in (8, 14, 21)]))
        run("ycbv", [0], targets, variants, args.work, args.work / "templates_ycbv", set(frames))


if __name__ == "__main__":
    main()
