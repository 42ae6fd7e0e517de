"""Speed of the training-free single-view chain (`cosy estimate` with templates), the working tree
against a git revision, side by side.

Both chains run through :class:`cosy_cli.singleview.estimate_stage.Estimator` (the code `cosy
estimate` runs, default settings) on the visible GT boxes of real images; the reference chain swaps
in the verification, template-matching and ICP modules of ``--ref`` (default ``HEAD``: the last commit),
loaded from git into this process (the renderer is the working tree's for both: its default
per-fragment program, the one the reference used, but also its cheaper state changes, so the
reference is if anything a little faster than it was). All variants run on each image in turn, so
that their timings share the machine's load (2 shared cores: absolute figures vary 2x with the
load, ratios much less). After the speed-ups are committed, compare with ``--ref 51abf49`` (the
commit before them).

* ``--data lmo``: ``lmo_dev`` (LM-O, RGB only: templates -> verification -> the default RGB
  refinement (contour alignment; ``*-search`` variants: the RGB search)), scenes
  ``--scenes`` (odd: where settings are chosen; even: held out);
* ``--data ycbv``: ``ycbv_0000`` frames ``--frames`` (RGB-D: templates -> verification -> short-ICP
  screen of 32 -> ICP of the best 12 -> pick by depth fit + image score; ``new-noscreen``: ICP of
  the first 16, no screen);
* ``--data lmo-depth``: the proxy RGB-D LM-O of ``bench_realdata_singleview.py`` (real RGB, depth
  rendered from the GT: ``prepare_lmo_depth``), scenes ``--scenes``, the same RGB-D chain.

Prints per variant: the median seconds per image (and mean), the detections per image, the
per-step medians (template matching, verification + the rest of the coarse step, RGB search,
contour alignment, ICP), and the per-detection mean of the BOP AR (MSSD, MSPD) recalls (one
candidate per GT instance, as in bench_realdata_singleview.py --sweep) and rotations within 15
deg. The renderers and templates are built before timing (templates once per object set; the
first image is run once untimed).

    .venv/bin/python benchmarks/bench_stage1_speed.py --data lmo --scenes odd
    .venv/bin/python benchmarks/bench_stage1_speed.py --data lmo --scenes even
    .venv/bin/python benchmarks/bench_stage1_speed.py --data ycbv --frames 1-5
    .venv/bin/python benchmarks/bench_stage1_speed.py --data lmo-depth --scenes even --variants new-noscreen,new
    .venv/bin/python benchmarks/bench_stage1_speed.py --data lmo-depth --scenes even --ref c349180 --variants ref-nocascade,new
    .venv/bin/python benchmarks/bench_stage1_speed.py --data lmo --variants new --profile  # cProfile of new
    .venv/bin/python benchmarks/bench_stage1_speed.py --data lmo --variants new,new+scorer --scorer lmo-scorer.onnx
    .venv/bin/python benchmarks/bench_stage1_speed.py --data lmo --variants new,new+scorer,new+scorer2 \
        --scorer lmo-scorer-fp32.onnx --scorer2 lmo-scorer.onnx  # float32 against int8
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import argparse  # noqa: E402
import contextlib  # noqa: E402
import importlib.util  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_realdata_singleview import REALDATA, _parse_range  # noqa: E402

# variant -> (code: "new" | "ref", VerifyConf overrides, estimate setting overrides)
VARIANTS = {
    "ref": ("ref", {}, {}),
    "new": ("new", {}, {}),
    "ref-search": ("ref", {}, {"rgb_refine": "search"}),  # the RGB search instead of the contour alignment
    "new-search": ("new", {}, {"rgb_refine": "search"}),
    "new-1000": ("new", {"rank_faces": 1000}, {}),  # the code's speed-ups alone (the former 1000-face first pass)
    "new-1000-search": ("new", {"rank_faces": 1000}, {"rgb_refine": "search"}),
    "new-pixel": ("new", {"shading": "pixel"}, {}),  # lit per fragment
    "new-rf1500-search": ("new", {"refine_faces": 1500}, {"rgb_refine": "search"}),
    "new-rf1000-search": ("new", {"refine_faces": 1000}, {"rgb_refine": "search"}),
    "new-rank300": ("new", {"rank_faces": 300}, {}),
    "new-rank300-search": ("new", {"rank_faces": 300}, {"rgb_refine": "search"}),
    "new-keep6": ("new", {"rank_keep": 6}, {}),
    "new-keep6-search": ("new", {"rank_keep": 6}, {"rgb_refine": "search"}),
    "new-noscreen": ("new", {}, {"icp_screen": 0, "top_k": 16}),  # with depth: the first 16 to ICP, no short-ICP screen
    "new-nocascade": ("new", {"rank_faces": 0}, {}),  # every hypothesis verified with the full copies (with depth: the default up to c349180)
    "ref-nocascade": ("ref", {"rank_faces": 0}, {}),  # the same in --ref's modules (--ref c349180: that commit's RGB-D chain)
    "new-vt96": ("new", {}, {"verify_top": 96}),  # more hypotheses verified
    "new-vt128": ("new", {}, {"verify_top": 128}),
    "new-sk8": ("new", {"scorer_keep": 8}, {}),  # with +scorer: it orders 8 hypotheses per detection, not 16
}


def load_ref_module(name: str, rev: str):
    """The module ``<name>`` of ``cosy_cli.singleview`` (its ``training_free/`` or ``networks/``
    subpackage since they exist, the package itself before) as it is at git revision ``rev``,
    imported as ``_ref_<name>`` in the package it came from (its relative imports resolve to the
    working tree)."""
    for sub in ("training_free", "networks", ""):
        rel = "/".join(p for p in ("src/cosy_cli/singleview", sub, f"{name}.py") if p)
        r = subprocess.run(["git", "-C", str(REPO), "show", f"{rev}:{rel}"], capture_output=True, text=True)
        if r.returncode == 0:
            break
    else:
        raise SystemExit(f"no module {name} of cosy_cli.singleview at {rev}")
    path = Path(tempfile.mkdtemp(prefix="cosy_ref_")) / f"{name}.py"
    path.write_text(r.stdout)
    modname = ".".join(p for p in ("cosy_cli.singleview", sub, f"_ref_{name}") if p)
    spec = importlib.util.spec_from_file_location(modname, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[modname] = mod
    spec.loader.exec_module(mod)
    return mod


class Clock:
    """Accumulates the time spent in wrapped functions (per image)."""

    def __init__(self):
        self.t = 0.0

    def wrap(self, fn):
        def timed(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                self.t += time.perf_counter() - t0
        return timed


@contextlib.contextmanager
def swapped(module, name, value):
    old = getattr(module, name)
    setattr(module, name, value)
    try:
        yield
    finally:
        setattr(module, name, old)


def prepare(data: str, work: Path):
    """(dataset root, split, models dir) of ``data``: YCB-V as the real-data benchmarks copy it
    (completed with gt-info once), the proxy RGB-D LM-O as bench_realdata_singleview makes it."""
    if data == "lmo":
        return REALDATA / "lmo_dev", "test", REALDATA / "lmo_dev" / "models"
    if data == "lmo-depth":
        from bench_realdata_singleview import prepare_lmo_depth

        root = prepare_lmo_depth(REALDATA / "lmo_dev", work / "lmo_depth_proxy")
        return root, "test", root / "models"
    from bench_realdata_multiview import prepare_ycbv

    root = prepare_ycbv(REALDATA / "ycbv_0000", work / "ycbv_0000")
    return root, "train_real", root / "models"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", choices=("lmo", "lmo-depth", "ycbv"), default="lmo")
    ap.add_argument("--scenes", default="odd", help="lmo: odd | even | all | comma-separated ids")
    ap.add_argument("--frames", default="1-5", help="ycbv: image ids, e.g. 1-5 (chose) or 6-10 (held out)")
    ap.add_argument("--ref", default="HEAD", help="git revision of the reference chain's verify.py / templates.py")
    ap.add_argument("--variants", default="ref,new", help=f"comma-separated of {', '.join(VARIANTS)}; NAME+scorer: "
                    "with --scorer (scorer_scope rank), NAME+scorer-all: scope all, NAME+scorer2: --scorer2")
    ap.add_argument("--scorer", type=Path, default=None, help="a learned scorer (cosy train scorer) for +scorer variants")
    ap.add_argument("--scorer2", type=Path, default=None, help="a second scorer for NAME+scorer2 variants (scope rank), "
                    "e.g. the same run exported in float32 and in int8 (cosy export --precision)")
    ap.add_argument("--images", type=int, default=0, help="only the first N images (0: all)")
    ap.add_argument("--profile", action="store_true", help="cProfile the last variant; print the top functions")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "cosy_bench_realdata_sv")
    args = ap.parse_args()
    if not REALDATA.is_dir():
        print(f"skipped: {REALDATA} is absent")
        return
    warnings.filterwarnings("ignore", message=".*decimated copy.*")
    from cosy_cli.detection.boxes import clip_xyxy
    from cosy_cli.detection.importers import detections_from_gt
    from cosy_cli.evaluation.pose_error import mspd, mssd
    from cosy_cli.io.dataset import BopDataset
    from cosy_cli.objects import ObjectDatabase
    from cosy_cli.singleview import estimate_stage as es
    from cosy_cli.singleview.training_free import templates as tpl
    from cosy_cli.singleview.training_free import icp, verify

    args.work.mkdir(parents=True, exist_ok=True)
    root, split, models = prepare(args.data, args.work)
    ds = BopDataset(root, split)
    db = ObjectDatabase.from_models_dir(models)
    dbe = ObjectDatabase.from_models_dir(root / "models_eval") if (root / "models_eval").is_dir() else db
    tdir = args.work / f"templates_{'lmo' if args.data == 'lmo-depth' else args.data}"  # the same models
    es.ensure_templates(models, tdir, log=lambda *_: None)  # built once per object set
    ts = tpl.TemplateSet.load(tdir)
    if args.data in ("lmo", "lmo-depth"):
        ids = list(range(1, 32))
        scene_ids = {"even": [i for i in ids if i % 2 == 0], "odd": [i for i in ids if i % 2 == 1],
                     "all": ids}.get(args.scenes) or [int(x) for x in args.scenes.split(",")]
        im_ids = None
    else:
        scene_ids, im_ids = [0], set(_parse_range(args.frames))
    dets = detections_from_gt(ds, scene_ids, 0.1)
    has_depth = args.data != "lmo"
    names = args.variants.split(",")
    ref = {}
    if any(VARIANTS[n.partition("+")[0]][0] == "ref" for n in names):
        ref = {m: load_ref_module(m, args.ref) for m in ("verify", "templates", "icp")}
    chains = {}
    for n in names:
        base, _, learned = n.partition("+")  # NAME+scorer / NAME+scorer-all: with --scorer, scope rank / all
        code, over, est_over = VARIANTS[base]
        vmod = ref["verify"] if code == "ref" else verify
        tmod = ref["templates"] if code == "ref" else tpl
        imod = ref["icp"] if code == "ref" else icp
        scope = "all" if learned == "scorer-all" else "rank"
        run_conf = es.decide(es.resolve_conf("default", **est_over, scorer_scope=scope), coarse_model=None,
                             refiner_model=None, has_depth=has_depth)
        run_conf.update(coarse="templates", refiner="none")
        est = es.Estimator(run_conf, db, templates=ts,
                           scorer_model=(args.scorer2 if learned == "scorer2" else args.scorer) if learned else None)
        est._verifier = vmod.Verifier(db, vmod.VerifyConf(**over, **({"scorer_scope": scope} if learned else {})),
                                      **({"scorer": est.scorer} if learned else {}))
        chains[n] = (est, tmod, imod)
    syms = {o: dbe[o].symmetries_with_steps(64) for o in dbe.obj_ids}
    th_mssd, th_mspd = np.arange(0.05, 0.51, 0.05), np.arange(5, 51, 5)
    res = {n: {"t": [], "match": [], "coarse": [], "rgb_refine": [], "contour": [], "icp": [], "ar": [], "rot": [],
               "dets": [], "method": ""} for n in names}
    groups = [(k, v) for k, v in dets.groupby(["scene_id", "im_id"]).indices.items()
              if im_ids is None or k[1] in im_ids]
    if args.images:
        groups = groups[:args.images]
    prof = None
    if args.profile:
        import cProfile

        prof = cProfile.Profile()
    first = True
    for (sid, im), idx in groups:
        d = dets.iloc[idx]
        rgb, K = ds.read_rgb(sid, im), ds.scene_camera(sid)[im].K
        depth = ds.read_depth(sid, im) if has_depth else None
        boxes = clip_xyxy(d[["x", "y", "w", "h"]].to_numpy(), rgb.shape[1], rgb.shape[0])
        obj = d["obj_id"].to_numpy()
        gt = ds.scene_gt(sid)[im]
        T_gt = np.stack([gt[g].T_cam_obj for g in d["gt_index"]])
        if first:  # warm-up: renderers, GPU meshes, decimated copies (built once per object set)
            for n in names:
                est, tmod, imod = chains[n]
                with swapped(tpl, "match_templates", tmod.match_templates), \
                        swapped(icp, "refine_with_depth", imod.refine_with_depth):
                    est.estimate(rgb, depth, K, boxes, obj)
            first = False
        for j, n in enumerate(names):
            est, tmod, imod = chains[n]
            clock = Clock()
            on = prof is not None and j == len(names) - 1
            with swapped(tpl, "match_templates", clock.wrap(tmod.match_templates)), \
                    swapped(icp, "refine_with_depth", imod.refine_with_depth):
                if on:
                    prof.enable()
                t0 = time.perf_counter()
                r = est.estimate(rgb, depth, K, boxes, obj)
                dt = time.perf_counter() - t0
                if on:
                    prof.disable()
            R = res[n]
            R["t"].append(dt)
            R["dets"].append(len(obj))
            R["match"].append(clock.t)
            R["coarse"].append(r.times.get("coarse", 0.0) - clock.t)
            R["rgb_refine"].append(r.times.get("rgb_refine", 0.0))
            R["contour"].append(r.times.get("contour", 0.0))
            R["method"] = es.describe(est.conf) + (f", rgb_refine {est.conf.get('rgb_refine')}"
                                                   if not has_depth else "")
            R["icp"].append(r.times.get("icp", 0.0))
            T = r.T
            for i, o in enumerate(obj):
                m, S = dbe[int(o)], syms[int(o)]
                e1 = mssd(T[i:i + 1], T_gt[i:i + 1], m.points, S)[0] / m.diameter
                e2 = mspd(T[i:i + 1], T_gt[i:i + 1], K, m.points, S)[0] * 640.0 / rgb.shape[1]
                R["ar"].append(((e1 < th_mssd).mean() + (e2 < th_mspd).mean()) / 2)
                c = (np.einsum("ij,sij->s", T[i, :3, :3], T_gt[i, :3, :3] @ S[:, :3, :3]) - 1) / 2
                R["rot"].append(np.degrees(np.arccos(np.clip(c, -1, 1))).min() < 15)
    for n in names:
        chains[n][0].close()
    load = os.getloadavg()[0]
    print(f"{args.data} {'frames ' + args.frames if args.data == 'ycbv' else args.scenes}: {len(groups)} images, "
          f"ref = {args.ref}, load {load:.1f}")
    for n in names:
        R = {k: np.asarray(v) for k, v in res[n].items()}
        med = {k: np.median(R[k]) * 1e3 for k in ("match", "coarse", "rgb_refine", "contour", "icp")}
        print(f"{n:10s} {np.median(R['t']):.3f} s/image median (mean {R['t'].mean():.3f}; "
              f"{np.median(R['dets']):.0f} detections/image, {R['dets'].min()}-{R['dets'].max()})  "
              f"steps ms median: match {med['match']:.0f}, verify {med['coarse']:.0f}, "
              f"search {med['rgb_refine']:.0f}, contour {med['contour']:.0f}, icp {med['icp']:.0f}  "
              f"AR(MSSD,MSPD) {R['ar'].mean():.3f}  rot<15 {R['rot'].mean():.3f}  ({len(R['ar'])} detections; "
              f"{res[n]['method']})", flush=True)
    if len(names) > 1:
        base = np.asarray(res[names[0]]["t"])
        for n in names[1:]:
            ratio = np.asarray(res[n]["t"]) / base
            print(f"{n} / {names[0]}: time ratio per image median {np.median(ratio):.2f}")
    if prof is not None:
        import pstats

        pstats.Stats(prof).sort_stats("tottime").print_stats(20)


if __name__ == "__main__":
    main()
