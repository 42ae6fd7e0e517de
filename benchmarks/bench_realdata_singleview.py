"""Training-free single-view candidates on real images: the old chain against the new one.

Data (read from ../shared/realdata/, skipped with a message when absent), visible GT boxes as
detections (`cosy estimate --from-gt`):

* ``lmo``: ``lmo_dev/`` (LM-O, RGB only), BOP AR (MSSD, MSPD) with its targets file and
  ``models_eval/``. Settings were chosen on the odd scene ids; report on ``--scenes even``.
* ``lmo-depth``: a *proxy* RGB-D LM-O made from ``lmo_dev`` by :func:`prepare_lmo_depth` (the
  real RGB with depth rendered from the published GT poses, see there): no real LM-O depth is in
  ``../shared``, and this measures the depth path on LM-O's objects, occlusions and boxes. BOP19
  AR (VSD against the proxy depth); settings chosen on ``--scenes odd``, report ``even``.
* ``ycbv``: ``ycbv_0000/`` (RGB-D), copied to a work folder and completed with `cosy gt-info`
  (the release has no scene_gt_info.json); BOP19 AR (VSD, MSSD, MSPD) on frames ``--frames``
  (a targets file of those frames). Settings were chosen on frames 1-5; report on 6-10.

Variants: ``old`` (template score only: ``verify_top 0``, top 5 to ICP, no RGB refinement: the
chain before issue 18), ``verify`` (templates verified by rendering, no refinement), ``new`` (the
default: verification, then the RGB refinement (rgb_refine auto: contour) where there is no
depth, or a short ICP of 32 hypotheses and the full ICP of the best 12, picked by depth fit +
image score), ``new-top5`` (new, 5 hypotheses to ICP), ``new-noscreen`` (with depth: the first 16
verified hypotheses to ICP, no short-ICP screen: the default before 2026-12-02), ``new-vt64``
(64 hypotheses verified), ``new-fitonly`` (ICP pick by depth fit alone: ``image_weight 0``), ``search``, ``contour`` and ``search+contour`` (RGB: the local search,
the contour alignment (:mod:`cosy_cli.singleview.training_free.contour`), or both); ``NAME+scorer``
runs NAME with the learned scorer of ``--scorer FILE`` (``cosy train scorer``). Also prints
the fraction of rotations within 15 deg (modulo symmetries), the median translation error (mm)
and time per image.

    .venv/bin/python benchmarks/bench_realdata_singleview.py --data lmo --scenes even
    .venv/bin/python benchmarks/bench_realdata_singleview.py --data ycbv --frames 6-10
    .venv/bin/python benchmarks/bench_realdata_singleview.py --data lmo-depth --scenes even --variants old,new
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
import shutil  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
VARIANTS = {
    "old": {"verify_top": 0, "rgb_refine": "none", "top_k": 5},
    "verify": {"rgb_refine": "none"},
    "new": {},
    "new-top5": {"top_k": 5},
    "new-noscreen": {"icp_screen": 0, "top_k": 16},
    "new-vt64": {"verify_top": 64},
    "new-fitonly": {"image_weight": 0.0},
    "search": {"rgb_refine": "search"},
    "contour": {"rgb_refine": "contour"},
    "search+contour": {"rgb_refine": "search+contour"},
    "new-all": {"scorer_scope": "all"},  # with +scorer: its prediction is every verification score
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


PROXY_SEED = 20261202
PROXY_VERSION = "1"  # bump when prepare_lmo_depth changes: the work copy is remade


def prepare_lmo_depth(src: Path, dst: Path) -> Path:
    """A proxy RGB-D copy of ``lmo_dev`` (``src``) in ``dst``: the real RGB images (linked), the
    published GT files, and for each image a depth map (mm, uint16 PNG, depth_scale 1) rendered from
    the published GT poses of the 8 annotated objects on the plane they stand on, then degraded
    towards a Kinect-like sensor. What is not real: the depth itself. It lacks the unannotated
    objects (the benchvise in the middle, the clutter) except where the published visible boxes
    say an object was hidden, and sensor effects beyond those modelled. Steps, seeded:

    1. the support plane: the face of the convex hull of the posed models' surface samples that
       has the camera on its inner side and touches (within 4 mm) the most objects (at least 3 in
       every image of ``lmo_dev``); rays that meet it within 2.5 m see it, the rest is missing;
    2. each object's depth shifted by N(0, 3 mm) (real depth against GT-posed meshes is off by a
       few mm per object, as YCB-V's is);
    3. pixels of an object outside its published visible box (``scene_gt_info`` ``bbox_visib``,
       grown by 2 px) were hidden by something unannotated: moved 30-80 mm towards the camera;
    4. the share of each object without a valid measurement in the real depth (1 -
       ``px_count_valid`` / ``px_count_all``) dropped in smooth blobs;
    5. noise N(0, 1.5e-6 z^2) mm (1.5 mm at 1 m), 60 % of the pixels at depth edges (> 25 mm
       within 5 x 5) and 2 % at random dropped, rounded to 1 mm.
    Made once per ``PROXY_VERSION`` (about 20 s)."""
    import cv2
    from scipy.spatial import ConvexHull

    from cosy_cli.io.dataset import BopDataset
    from cosy_cli.objects import ObjectDatabase
    from cosy_cli.rendering import SceneRenderer

    marker = dst / "proxy_version.txt"
    if marker.is_file() and marker.read_text() == PROXY_VERSION:
        return dst
    shutil.rmtree(dst, ignore_errors=True)
    dst.mkdir(parents=True)
    for name in ("models", "models_eval"):
        (dst / name).symlink_to(src / name)
    for f in src.glob("*.json"):
        shutil.copy(f, dst / f.name)
    rng = np.random.default_rng(PROXY_SEED)
    ds = BopDataset(src, "test")
    db = ObjectDatabase.from_models_dir(src / "models")
    samples = {o: db[o].mesh.vertices[rng.choice(len(db[o].mesh.vertices), 1500, replace=False)] for o in db.obj_ids}
    with SceneRenderer({o: db[o].mesh for o in db.obj_ids}, 640, 480) as r:
        for sid in ds.scene_ids:
            d_in, d_out = src / "test" / f"{sid:06d}", dst / "test" / f"{sid:06d}"
            (d_out / "depth").mkdir(parents=True)
            (d_out / "rgb").symlink_to(d_in / "rgb")
            for f in d_in.glob("*.json"):
                shutil.copy(f, d_out / f.name)
            cams, infos = ds.scene_camera(sid), ds.scene_gt_info(sid)
            for im, gts in ds.scene_gt(sid).items():
                K, info = cams[im].K, infos[im]
                ids = [g.obj_id for g in gts]
                T = np.stack([g.T_cam_obj for g in gts])
                out = r.render(K, ids, T, with_rgb=False)
                H, W = out.depth.shape
                depth, inst = out.depth.astype(np.float64), out.instance
                # 1. the support plane (outward hull normal n, n.x + d = 0; the camera at 0 needs d < 0)
                P = np.concatenate([samples[o] @ T[i, :3, :3].T + T[i, :3, 3] for i, o in enumerate(ids)])
                owner = np.repeat(np.arange(len(ids)), [len(samples[o]) for o in ids])
                eqs = np.unique(np.round(ConvexHull(P).equations, 6), axis=0)
                eqs = eqs[eqs[:, 3] < 0]
                touch = np.array([len(np.unique(owner[P @ e[:3] + e[3] > -4.0])) for e in eqs])
                n, d0 = eqs[np.argmax(touch), :3], eqs[np.argmax(touch), 3]
                vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
                den = (uu - K[0, 2]) / K[0, 0] * n[0] + (vv - K[1, 2]) / K[1, 1] * n[1] + n[2]
                z = -d0 / np.where(np.abs(den) > 1e-6, den, np.inf)
                depth[inst < 0] = np.where((z > 0) & (z < 2500), z, 0.0)[inst < 0]
                blobs = cv2.GaussianBlur(rng.random((H, W)).astype(np.float32), (0, 0), 4)
                for i in range(len(ids)):
                    m = inst == i
                    if not m.any():
                        continue
                    depth[m] += rng.normal(0.0, 3.0)  # 2.
                    x, y, w, h = (int(v) for v in info[i].bbox_visib)  # 3.
                    hidden = m.copy()
                    hidden[max(y - 2, 0):y + h + 2, max(x - 2, 0):x + w + 2] = False
                    depth[hidden] -= rng.uniform(30.0, 80.0)
                    drop = 1.0 - info[i].px_count_valid / max(info[i].px_count_all, 1)  # 4.
                    seen = m & ~hidden
                    if drop > 0.02 and seen.sum() > 10:
                        depth[seen & (blobs < np.quantile(blobs[seen], drop))] = 0.0
                valid = depth > 0  # 5.
                depth[valid] += rng.normal(0.0, 1.5e-6 * depth[valid] ** 2)
                dmax = cv2.dilate(depth.astype(np.float32), np.ones((5, 5), np.uint8))
                dmin = -cv2.dilate(-np.where(valid, depth, 1e5).astype(np.float32), np.ones((5, 5), np.uint8))
                depth[((dmax - dmin) > 25) & (rng.random((H, W)) < 0.6)] = 0.0
                depth[rng.random((H, W)) < 0.02] = 0.0
                cv2.imwrite(str(d_out / "depth" / f"{im:06d}.png"), np.clip(np.rint(depth), 0, 65535).astype(np.uint16))
    marker.write_text(PROXY_VERSION)
    return dst


def gt_mask_detections(root: Path, split: str, work: Path, min_visib: float = 0.1) -> Path:
    """A detections JSON of the visible GT boxes (visib_fract >= min_visib, as --from-gt) with each
    instance's visible mask as a BOP RLE ``segmentation``: what a perfect segmenter would give (an
    upper bound for masks from BOP's default detections). Masks: the split's ``mask_visib/`` PNGs,
    else rendered from the GT poses by ``cosy gt-info --masks`` in a copy of the dataset."""
    import cv2

    from cosy_cli.dataset_tools import gt_info
    from cosy_cli.io.masks import encode_mask

    if not any((root / split).glob("*/mask_visib")):
        copy = work / f"{root.name}_masks"
        if not any(copy.glob(f"{split}/*/mask_visib")):
            shutil.rmtree(copy, ignore_errors=True)
            shutil.copytree(root, copy)
            gt_info.main(None, copy, split, masks=True, overwrite=True, progress=False)
        root = copy
    dets = []
    for sd in sorted(p for p in (root / split).iterdir() if p.is_dir()):
        gt = json.loads((sd / "scene_gt.json").read_text())
        info = json.loads((sd / "scene_gt_info.json").read_text())
        for k in sorted(gt, key=int):
            for j, (g, i) in enumerate(zip(gt[k], info[k])):
                if i["visib_fract"] < min_visib:
                    continue
                m = cv2.imread(str(sd / "mask_visib" / f"{int(k):06d}_{j:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
                dets.append({"scene_id": int(sd.name), "image_id": int(k), "category_id": g["obj_id"], "score": 1.0,
                             "bbox": i["bbox_visib"], "time": -1, "segmentation": encode_mask(m)})
    out = work / f"{root.name}_{split}_gt_masks.json"
    out.write_text(json.dumps(dets))
    return out


def classifier_mask_detections(root: Path, split: str, work: Path, classifier: Path, scene_ids=None,
                               min_visib: float = 0.1) -> Path:
    """A detections JSON of the visible GT boxes (as --from-gt) whose ``segmentation`` is what a box
    classifier's mask head (``cosy train classifier --preset real``) sees in each box (what ``cosy
    detect --from-gt --classifier`` adds): its masks with perfect boxes, to compare with the GT
    masks (:func:`gt_mask_detections`). Prints the mean IoU of those masks with the GT visible masks."""
    from cosy_cli.detection import importers
    from cosy_cli.detection.classifier import OnnxClassifier
    from cosy_cli.detection.stage import add_masks
    from cosy_cli.io.dataset import BopDataset
    from cosy_cli.io.masks import decode_segmentation

    clf = OnnxClassifier(classifier)
    if not clf.has_mask_head:
        raise SystemExit(f"{classifier} has no mask head")
    ds = BopDataset(root, split)
    gt = importers.read_detections_any(gt_mask_detections(root, split, work, min_visib), ds)
    if scene_ids is not None:
        gt = gt[gt["scene_id"].isin(scene_ids).to_numpy()].reset_index(drop=True)
    dets, _ = add_masks(gt.assign(segmentation=None), ds, clf, 0.5, log=lambda *_: None, progress=False)
    ious = []
    for g, d in zip(gt.itertuples(), dets.itertuples()):
        shape = tuple(g.segmentation["size"])
        m, t = decode_segmentation(d.segmentation, shape), decode_segmentation(g.segmentation, shape)
        ious.append((m & t).sum() / max((m | t).sum(), 1))
    print(f"classifier masks on the GT boxes: mean IoU with the GT visible masks {np.mean(ious):.3f} "
          f"(median {np.median(ious):.3f}, {len(ious)} instances; >= 0.5: {np.mean(np.array(ious) >= 0.5):.2f})",
          flush=True)
    path = work / f"{root.name}_{split}_{Path(classifier).stem}_masks.json"
    importers.write_detections(path, dets)
    return path


def run(data: str, scene_ids, targets, variants, work: Path, templates_dir: Path, im_ids=None,
        scorer: Path | None = None, classifier: Path | None = None) -> None:
    from cosy_cli.evaluation import evaluate_stage
    from cosy_cli.io.dataset import BopDataset
    from cosy_cli.objects import ObjectDatabase
    from cosy_cli.singleview import estimate_stage

    if data == "lmo":
        root, split, metrics = REALDATA / "lmo_dev", "test", "bop19"
    elif data == "lmo-depth":
        root, split, metrics = prepare_lmo_depth(REALDATA / "lmo_dev", work / "lmo_depth_proxy"), "test", "bop19"
    else:
        from bench_realdata_multiview import prepare_ycbv

        root, split, metrics = prepare_ycbv(REALDATA / "ycbv_0000", work / "ycbv_0000"), "train_real", "bop19"
    ds = BopDataset(root, split)
    db = ObjectDatabase.from_models_dir(root / ("models_eval" if (root / "models_eval").is_dir() else "models"))
    for name in variants:
        # NAME+masks: the GT boxes with the GT visible masks as segmentations (a perfect segmenter);
        # NAME+clfmasks: the GT boxes with the masks of a classifier's mask head (--classifier)
        plain, clfmasks, _ = name.partition("+clfmasks")
        plain, masks, _ = plain.partition("+masks")
        base, _, learned = plain.partition("+scorer")
        conf = estimate_stage.resolve_conf("default", **VARIANTS[base])
        out = work / f"{data}_{name}.csv"
        dets = gt_mask_detections(root, split, work) if masks else None
        if clfmasks:
            dets = classifier_mask_detections(root, split, work, classifier, scene_ids)
        s = estimate_stage.main(conf, root, split, out, overwrite=True, scene_ids=scene_ids, from_gt=dets is None,
                                detections=dets, templates_dir=templates_dir,
                                scorer_model=scorer if plain != base else None, log=lambda *_: None, progress=False)
        sc = evaluate_stage.main(None, root, split, out, work / f"eval_{data}_{name}", overwrite=True,
                                 targets=targets, metrics=metrics, scene_ids=scene_ids, log=lambda *_: None,
                                 progress=False)
        r15, tmed = rotation_stats(out, ds, db, scene_ids or ds.scene_ids, im_ids)
        ar = sc.get("bop19_average_recall")
        ci = sc.get("bop19_ci", {}).get("bop19_average_recall_mssd_mspd")
        ci_txt = f" [{ci[0]:.3f}, {ci[1]:.3f}]" if ci else ""
        print(f"{data:5s} {name:14s} AR(MSSD,MSPD) {sc['bop19_average_recall_mssd_mspd']:.3f}{ci_txt}  "
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
    from cosy_cli.singleview.training_free import templates as tpl
    from cosy_cli.singleview.estimate_stage import VERIFY_TOP_RGB, ensure_templates
    from cosy_cli.singleview.training_free.verify import Verifier, VerifyConf

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
    ap.add_argument("--data", choices=("lmo", "lmo-depth", "ycbv"), default="lmo")
    ap.add_argument("--scenes", default="even", help="lmo: even | odd | all | comma-separated ids")
    ap.add_argument("--frames", default="6-10", help="ycbv: image ids evaluated, e.g. 6-10 (held out) or 1-5")
    ap.add_argument("--variants", default="old,new",
                    help=f"comma-separated of {', '.join(VARIANTS)}; NAME+masks: with the GT visible masks as the "
                         "detections' segmentations")
    ap.add_argument("--sweep", default=None,
                    help=f"lmo only: compare verification settings side by side instead ({', '.join(SWEEP)} or all)")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "cosy_bench_realdata_sv")
    ap.add_argument("--classifier", type=Path, default=None,
                    help="a box classifier with a mask head (cosy train classifier --preset real): a variant named "
                         "NAME+clfmasks runs NAME on the GT boxes with its masks")
    ap.add_argument("--scorer", type=Path, default=None,
                    help="a learned scorer (cosy train scorer): a variant named NAME+scorer runs NAME with it")
    args = ap.parse_args()
    if any("+scorer" in v for v in args.variants.split(",")) and args.scorer is None:
        ap.error("variants NAME+scorer need --scorer FILE")
    if any("+clfmasks" in v for v in args.variants.split(",")) and args.classifier is None:
        ap.error("variants NAME+clfmasks need --classifier FILE")
    if not REALDATA.is_dir():
        print(f"skipped: {REALDATA} is absent")
        return
    args.work.mkdir(parents=True, exist_ok=True)
    variants = args.variants.split(",")
    if args.data in ("lmo", "lmo-depth"):
        ids = list(range(1, 32))
        scene_ids = {"even": [i for i in ids if i % 2 == 0], "odd": [i for i in ids if i % 2 == 1],
                     "all": None}.get(args.scenes) if args.scenes in ("even", "odd", "all") else \
            [int(x) for x in args.scenes.split(",")]
        if args.sweep:
            if args.data != "lmo":
                ap.error("--sweep compares the RGB chain: use it with --data lmo")
            sweep(scene_ids, list(SWEEP) if args.sweep == "all" else args.sweep.split(","), args.work / "templates_lmo")
            return
        run(args.data, scene_ids, None, variants, args.work, args.work / "templates_lmo", scorer=args.scorer,
            classifier=args.classifier)
    else:
        frames = _parse_range(args.frames)
        targets = args.work / f"ycbv_targets_{args.frames}.json"
        targets.write_text(json.dumps([{"scene_id": 0, "im_id": i, "obj_id": o, "inst_count": 1}
                                       for i in frames for o in (8, 14, 21)]))
        run("ycbv", [0], targets, variants, args.work, args.work / "templates_ycbv", set(frames), scorer=args.scorer)


if __name__ == "__main__":
    main()
