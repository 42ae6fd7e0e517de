"""Speed of the 2D detector on this CPU: milliseconds per 640 x 480 image with OnnxDetector
(resize + onnxruntime + decoding + per-class NMS), median of N runs after warm-up; also the
network alone (onnxruntime, batch 1) and torch for comparison.

    .venv/bin/python benchmarks/bench_detector_speed.py [--model detector.onnx] [--n 50] [--threads 2]

Model: --model, else the shipped detector (src/cosy_cli/assets/detector.onnx), else an untrained
network of the default architecture (speed does not depend on the weights). Images: the RGB
images of data_samples/ (640 x 480).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _median_ms(fn, n: int, warmup: int = 3) -> tuple[float, float]:
    for _ in range(warmup):
        fn()
    t = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    t = np.array(t) * 1000
    return float(np.median(t)), float(np.percentile(t, 90))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=None)
    ap.add_argument("--n", type=int, default=50, help="timed runs per figure")
    ap.add_argument("--threads", type=int, default=None, help="onnxruntime intra-op threads (default: its own)")
    args = ap.parse_args()

    import torch

    from cosy_cli.detection.model import CenterNet, ExportWrapper
    from cosy_cli.detection.network import OnnxDetector
    from cosy_cli.detection.train import export_onnx, model_config, resolve_conf
    from cosy_cli.io.images import read_rgb
    from cosy_cli.shipped import shipped

    tmp = tempfile.TemporaryDirectory()
    model = args.model
    label = str(model)
    if model is None and shipped("detector.onnx").is_file():
        model, label = shipped("detector.onnx"), "shipped detector.onnx"
    net = None
    if model is None:
        net = CenterNet(model_config(resolve_conf(None), list(range(1, 9)))).eval()
        model = export_onnx(net, Path(tmp.name) / "untrained.onnx")
        label = "untrained default-architecture detector (8 classes)"

    det = OnnxDetector(model, threads=args.threads)
    images = [read_rgb(p) for p in sorted((ROOT / "data_samples" / "test").glob("*/rgb/*.png"))]
    assert images and images[0].shape == (480, 640, 3), "data_samples images are 640 x 480"
    it = iter(range(10**9))

    def detect():
        det.detect(images[next(it) % len(images)])

    x = det.preprocess(images[0])
    full = _median_ms(detect, args.n)
    pre = _median_ms(lambda: det.preprocess(images[0]), args.n)
    onnx_only = _median_ms(lambda: det.raw(x), args.n)
    if net is None:
        cfg = det.config
        net = CenterNet(model_config(resolve_conf(None, input_size=list(det.input_size), stride=cfg["stride"],
                                                  channels=cfg["channels"], depth=cfg["depth"], fpn=cfg["fpn"],
                                                  head=cfg["head"]), det.obj_ids)).eval()
    wrapper = ExportWrapper(net).eval()
    xt = torch.from_numpy(x)
    with torch.no_grad():
        torch_ms = _median_ms(lambda: wrapper(xt), args.n)
    w, h = det.input_size
    print(f"model: {label}; input {w} x {h}; onnxruntime {__import__('onnxruntime').__version__}, "
          f"threads {args.threads or 'default'}; torch threads {torch.get_num_threads()}; {os.cpu_count()} CPUs")
    print(f"OnnxDetector.detect, 640 x 480 image: median {full[0]:.1f} ms, p90 {full[1]:.1f} ms "
          f"({1000 / full[0]:.1f} images/s) over {args.n} runs")
    print(f"  resize to input: {pre[0]:.1f} ms; network (onnxruntime, batch 1): {onnx_only[0]:.1f} ms; "
          f"decode + NMS: {max(0.0, full[0] - pre[0] - onnx_only[0]):.1f} ms")
    print(f"  same network in torch (batch 1): {torch_ms[0]:.1f} ms")
    tmp.cleanup()


if __name__ == "__main__":
    main()
