"""What a geometry-only pose can reach on the YCB-V frames of ``../shared/realdata/ycbv_0000``.

The meshes there have no texture images. Each object's GT pose is composed with each of its
near-symmetries (:func:`cosy_cli.singleview.training_free.depth_hypotheses.near_symmetries`: rigid motions that
carry most of the surface onto itself, e.g. a box turned over, a mug turned about its body when
its handle is hidden), and every variant is evaluated like a prediction (BOP19: VSD, MSSD, MSPD,
``cosy evaluate``). Prints per object the BOP19 AR of the GT and the mean over the GT and its
variants (what a uniform pick among them would score), and the same mean over only the variants
whose visible-depth score (:func:`~cosy_cli.singleview.training_free.depth_hypotheses.visible_depth_score`, the
score the depth path picks with) is within ``--tie`` of the GT's: the poses depth cannot tell
apart.

    .venv/bin/python benchmarks/bench_ycbv_ambiguity.py [--work DIR] [--tie 0.02]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

REALDATA = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"
sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "cosy_bench_ycbv_ambiguity")
    ap.add_argument("--tie", type=float, default=0.02, help="visible-depth score margin of an indistinguishable variant")
    args = ap.parse_args()
    src = REALDATA / "ycbv_0000"
    if not src.is_dir():
        print(f"skipped: {src} is absent")
        return
    warnings.filterwarnings("ignore")
    from bench_realdata_multiview import prepare_ycbv
    from cosy_cli.evaluation import evaluate_stage
    from cosy_cli.evaluation.protocols import BOP19_THRESHOLDS as TH
    from cosy_cli.io import bop
    from cosy_cli.io.dataset import BopDataset
    from cosy_cli.objects import ObjectDatabase
    from cosy_cli.singleview.training_free.depth_hypotheses import near_symmetries, visible_depth_score

    root, split = prepare_ycbv(src, args.work / "ycbv_0000"), "train_real"  # + scene_gt_info.json (VSD needs it)
    ds = BopDataset(root, split)
    db = ObjectDatabase.from_models_dir(root / "models")
    infos = ds.models_info()
    gt = ds.scene_gt(0)
    cams = ds.scene_camera(0)
    objs = sorted({g.obj_id for insts in gt.values() for g in insts})
    near = {o: np.concatenate([np.eye(4)[None], near_symmetries(db[o])]) for o in objs}  # identity first
    n_var = max(len(v) for v in near.values())
    ar = {}  # (im, obj, variant) -> BOP19 AR of that pose
    for j in range(n_var):  # one predictions file per variant index (objects with fewer repeat none)
        rows = [(0, im, g.obj_id, 1.0, g.T_cam_obj @ near[g.obj_id][j]) for im, insts in gt.items() for g in insts
                if j < len(near[g.obj_id])]
        path = args.work / f"variant_{j}.csv"
        preds = bop.PoseResults.from_arrays([r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows],
                                            [r[3] for r in rows], np.stack([r[4] for r in rows]),
                                            [-1.0] * len(rows))
        path.write_text(bop.format_results(preds))
        evaluate_stage.main(None, root, split, path, args.work / f"eval_{j}", overwrite=True, metrics="bop19",
                            log=lambda *_: None, progress=False)
        e = pd.read_csv(args.work / f"eval_{j}" / "errors.csv")
        vsd = [c for c in e.columns if c.startswith("vsd")]
        v_rec = (e[vsd].to_numpy()[:, :, None] < TH["vsd"][None, None]).mean((1, 2))  # mean over tau and thresholds
        d = np.array([infos[int(o)].diameter for o in e["obj_id"]])
        m_rec = (e["mssd"].to_numpy()[:, None] < TH["mssd"][None] * d[:, None]).mean(1)
        p_rec = (e["mspd"].to_numpy()[:, None] < TH["mspd"][None]).mean(1)
        for im, o, a in zip(e["im_id"], e["obj_id"], (v_rec + m_rec + p_rec) / 3):
            ar[(int(im), int(o), j)] = float(a)
    per = {o: {"gt": [], "all": [], "tie": [], "n_tie": []} for o in objs}
    for im, insts in gt.items():
        depth = ds.read_depth(0, im)
        for g in insts:
            o = g.obj_id
            T = g.T_cam_obj @ near[o]
            sc = np.asarray(visible_depth_score(depth, cams[im].K, np.full(len(T), o), T, db)).reshape(-1)
            tie = np.flatnonzero(sc >= sc[0] - args.tie)
            a = np.array([ar[(im, o, j)] for j in range(len(T))])
            per[o]["gt"].append(a[0])
            per[o]["all"].append(a.mean())
            per[o]["tie"].append(a[tie].mean())
            per[o]["n_tie"].append(len(tie))
    print(f"| obj_id | near-symmetries | GT | mean over GT + variants | variants within {args.tie} of the GT's "
          "depth score (mean count) | their mean |")
    print("| --- | --- | --- | --- | --- | --- |")
    for o in objs:
        p = per[o]
        print(f"| {o} | {len(near[o]) - 1} | {np.mean(p['gt']):.3f} | {np.mean(p['all']):.3f} | "
              f"{np.mean(p['n_tie']):.1f} | {np.mean(p['tie']):.3f} |")
    print(f"BOP19 AR over the objects: GT {np.mean([np.mean(per[o]['gt']) for o in objs]):.3f}, uniform pick among "
          f"the variants {np.mean([np.mean(per[o]['all']) for o in objs]):.3f}, among those depth cannot tell apart "
          f"{np.mean([np.mean(per[o]['tie']) for o in objs]):.3f} ({len(gt)} frames)")


if __name__ == "__main__":
    main()
