"""Benchmark of ``cosy evaluate``: time for N estimates without VSD (target: 1,000 in < 10 s) and
with VSD, on a ``cosy synth`` dataset (T-LESS-like parts, symmetric objects, depth).

Estimates: ``cosy synth-candidates --profile realistic`` plus noisy copies (10 % depth / 5 mm /
5 degrees) until there are N rows, so that every target has several hypotheses (top-k selection
and greedy matching are exercised).

Usage: ``python benchmarks/bench_evaluate.py [--n 1000] [--scenes 4 --views 8 --objects 8]``.
Prints the in-process time of ``evaluate_stage.main`` (no VSD, then VSD) and the whole command in a
fresh process (start-up included).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import argparse  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
COSY = str(Path(sys.executable).parent / "cosy")


def make_predictions(ds: Path, out: Path, n: int, seed: int = 0) -> int:
    from cosy_cli.geometry.rotations import rotation_about_axis
    from cosy_cli.io import bop
    from cosy_cli.synth import candidates as sc

    base = out.with_name("base.csv")
    sc.main(ds, "test", base, profile="realistic", seed=seed, log=lambda *_: None)
    res = bop.read_results(base)
    rng = np.random.default_rng(seed)
    k = max(0, n - len(res))
    pick = rng.integers(0, len(res), k)
    T = res.T_cam_obj[pick].copy()
    ang = np.radians(rng.normal(0, 5, k))
    axes = rng.normal(size=(k, 3))
    for i in range(k):
        T[i, :3, :3] = T[i, :3, :3] @ rotation_about_axis(axes[i], ang[i:i + 1])[0]
    T[:, :3, 3] *= (1 + rng.normal(0, 0.1, k))[:, None]
    T[:, :3, 3] += rng.normal(0, 5, (k, 3))
    tab = res.table
    allT = np.concatenate([res.T_cam_obj, T])[:n]
    ids = {c: np.concatenate([tab[c].to_numpy(), tab[c].to_numpy()[pick]])[:n] for c in ("scene_id", "im_id", "obj_id")}
    score = np.concatenate([tab["score"].to_numpy(), rng.random(k) * 0.5])[:n]
    bop.write_results(out, bop.PoseResults.from_arrays(ids["scene_id"], ids["im_id"], ids["obj_id"], score, allT))
    return len(score)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=1000)
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--objects", type=int, default=8)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    args = ap.parse_args()

    from cosy_cli.evaluation import evaluate_stage

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        ds = tmp / "ds"
        subprocess.run([COSY, "synth", "--out", str(ds), "--scenes", str(args.scenes), "--views", str(args.views),
                        "--objects", str(args.objects), "--width", str(args.width), "--height", str(args.height),
                        "--seed", "0"], check=True, capture_output=True)
        pred = tmp / "pred.csv"
        n = make_predictions(ds, pred, args.n)
        print(f"dataset: {args.scenes} scenes x {args.views} views x {args.objects} objects, "
              f"{args.width}x{args.height}; {n} estimates")
        q = lambda *_: None  # noqa: E731
        t = time.perf_counter()
        s = evaluate_stage.main(evaluate_stage.resolve_conf("bop19", vsd=False), ds, "test", pred, tmp / "e1", log=q,
                                progress=False)
        t_novsd = time.perf_counter() - t
        print(f"no VSD, in process:   {t_novsd:6.2f} s   (AR_MSSD {s['bop19_average_recall_mssd']:.4f}, "
              f"AR_MSPD {s['bop19_average_recall_mspd']:.4f}, AUC ADD-S {s['auc_adds']:.4f}, "
              f"pairs {s['counts']['pairs']})")
        t = time.perf_counter()
        r = subprocess.run([COSY, "evaluate", "--dataset", str(ds), "--predictions", str(pred), "--out",
                            str(tmp / "e2"), "--no-vsd"], capture_output=True, text=True)
        t_cli = time.perf_counter() - t
        assert r.returncode == 0, r.stderr
        print(f"no VSD, cosy command: {t_cli:6.2f} s   (fresh process, start-up included)")
        t = time.perf_counter()
        s = evaluate_stage.main("bop19", ds, "test", pred, tmp / "e3", log=q, progress=False)
        t_vsd = time.perf_counter() - t
        print(f"with VSD, in process: {t_vsd:6.2f} s   (AR {s['bop19_average_recall']:.4f}, "
              f"AR_VSD {s['bop19_average_recall_vsd']:.4f}, {s['bop19']['counts']['estimates_evaluated']} "
              f"estimates rendered against their targets)")


if __name__ == "__main__":
    main()
