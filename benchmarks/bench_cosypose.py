"""Speed of CosyPose's stage 1 in cosy: coarse + N refiner iterations per detection, with rendering,
batched over the detections of one 640x480 image (EfficientNet-B3, 240x320 crops).

    OPENBLAS_NUM_THREADS=1 PYOPENGL_PLATFORM=egl .venv/bin/python benchmarks/bench_cosypose.py \\
        --coarse COARSE(.onnx|run dir) --refiner REFINER(.onnx|run dir) [--providers cuda] [--threads 2]

Defaults: the fixture run directories (../shared/fixtures/cosypose_networks beside the repository, random weights: the
same compute as the published networks), exported to ONNX in a temporary folder, their meshes and
one of their images. Prints ms per detection for 1 and 6 detections and the split between the
network, rendering and cropping.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

FIX = Path(__file__).resolve().parents[2] / "shared" / "fixtures" / "cosypose_networks"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--coarse", default=None)
    ap.add_argument("--refiner", default=None)
    ap.add_argument("--models", default=str(FIX / "mesh"))
    ap.add_argument("--providers", choices=["cpu", "cuda"], default="cpu")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--iterations", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--detections", default="1,6")
    args = ap.parse_args()

    import torch

    torch.set_num_threads(args.threads)
    from cosy_cli.objects import ObjectDatabase
    from cosy_cli.rendering import SceneRenderer
    from cosy_cli.singleview.networks import cosypose_compat as cc

    tmp = Path(tempfile.mkdtemp(prefix="bench_cosypose_"))
    coarse = args.coarse or cc.export_onnx(FIX / "run_b3_coarse", tmp / "coarse.onnx", log=lambda *_: None)
    refiner = args.refiner or cc.export_onnx(FIX / "run_b3", tmp / "refiner.onnx", log=lambda *_: None)
    providers = ["CUDAExecutionProvider", "CPUExecutionProvider"] if args.providers == "cuda" else None

    def open_net(p):
        p = Path(p)
        return cc.OnnxCosyPoseNet(p, providers=providers, threads=args.threads) if p.is_file() \
            else cc.TorchCosyPoseNet(p, device="cuda" if providers else "cpu")

    case = np.load(FIX / "case.npz")
    rgb = np.round(case["images"][0].transpose(1, 2, 0) * 255).astype(np.uint8)
    K = case["K"][0].astype(np.float64)
    box0 = case["detection_boxes"][0].astype(np.float64)
    db = ObjectDatabase.from_models_dir(args.models)
    ids = db.obj_ids
    points = cc.MeshPoints.from_models_dir(args.models)
    timers = {"network": 0.0, "render": 0.0}

    def timed(fn, key):
        def wrapped(*a):
            t = time.perf_counter()
            r = fn(*a)
            timers[key] += time.perf_counter() - t
            return r
        return wrapped

    with SceneRenderer({o.obj_id: o.mesh for o in db}, 64, 64) as ren:
        def make(path):
            net = open_net(path)
            st = cc.CosyPoseRenderAndCompare(net, ren, points)
            net_call = net.__call__
            st.net = type("T", (), {"kind": net.kind, "init_method": net.init_method,
                                    "__call__": lambda self, x: timed(net_call, "network")(x)})()
            st.render_fn = timed(lambda Kc, o, T: cc.render_crops(ren, Kc, o, T), "render")
            return st

        co, rf = make(coarse), make(refiner)
        print(f"coarse {coarse}\nrefiner {refiner}\nproviders {args.providers}, threads {args.threads}, "
              f"coarse + {args.iterations} refiner iterations")
        for n in (int(v) for v in args.detections.split(",")):
            rng = np.random.default_rng(0)
            boxes = box0 + rng.uniform(-15, 15, (n, 4))
            labels = [ids[i % len(ids)] for i in range(n)]
            co.coarse(rgb, K, boxes[:1], labels[:1])  # warm-up
            best = None
            for _ in range(args.repeats):
                for k in timers:
                    timers[k] = 0.0
                t = time.perf_counter()
                T = co.coarse(rgb, K, boxes, labels)
                rf.iterate(rgb, K, T, labels, args.iterations)
                total = time.perf_counter() - t
                if best is None or total < best[0]:
                    best = (total, dict(timers))
            total, tm = best
            other = total - sum(tm.values())
            print(f"{n} detection(s): {total * 1e3 / n:.0f} ms per detection ({total * 1e3:.0f} ms total): network "
                  f"{tm['network'] * 1e3 / n:.0f}, rendering {tm['render'] * 1e3 / n:.0f}, crops and the rest "
                  f"{other * 1e3 / n:.0f} ms per detection")


if __name__ == "__main__":
    main()
