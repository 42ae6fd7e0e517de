"""Speed of the on-the-fly training-sample generator (cosy_cli.training.data), samples per second.

    .venv/bin/python benchmarks/bench_training_data.py [--batch 32] [--batches 20] [--workers 2]
        [--crop 128 96] [--kind refiner coarse]

Objects: the 8 fixed synthetic parts (cosy_cli.synth.objects), default domain randomisation
(0-3 occluders, vertex-colour variants, backgrounds, augmentation). Single process: the median
and best batch time over ``--batches`` batches after 2 warm-up batches (includes the
observed + rendered crops, compositing and augmentation). With ``--workers N > 0``: the same
through ``make_loader`` (N spawned workers, each with its own OpenGL context), measured over
``--batches`` batches after the first 2N + 1 (worker start-up and prefetched batches excluded).
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

from cosy_cli.rendering import SceneRenderer  # noqa: E402,F401 (selects the GL platform first)
from cosy_cli.training.data import SampleGenerator, TrainingStream, make_loader, synthetic_source  # noqa: E402


def bench_single(meshes, syms, kind, batch, batches, crop):
    g = SampleGenerator(meshes, kind=kind, crop_size=crop, symmetries=syms, seed=0, resting=True)
    for _ in range(2):
        g.batch(batch)
    times = []
    for _ in range(batches):
        t = time.perf_counter()
        g.batch(batch)
        times.append(time.perf_counter() - t)
    g.close()
    times = np.array(times)
    return batch / np.median(times), batch / times.min(), np.median(times)


def bench_workers(meshes, syms, kind, batch, batches, crop, workers):
    stream = TrainingStream(meshes, batch_size=batch, seed=0, crop_size=crop, kind=kind, symmetries=syms,
                            resting=True)
    loader = make_loader(stream, num_workers=workers)
    it = iter(loader)
    t0 = time.perf_counter()
    next(it)
    startup = time.perf_counter() - t0
    for _ in range(2 * workers):  # batches prefetched during start-up
        next(it)
    t = time.perf_counter()
    for _ in range(batches):
        next(it)
    dt = time.perf_counter() - t
    del it, loader
    return batch * batches / dt, startup


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--batches", type=int, default=20)
    ap.add_argument("--workers", type=int, default=0, help="also measure a DataLoader with N spawned workers")
    ap.add_argument("--crop", type=int, nargs=2, default=(128, 96), metavar=("W", "H"))
    ap.add_argument("--kind", nargs="+", default=["refiner", "coarse"])
    args = ap.parse_args()
    meshes, syms = synthetic_source()
    crop = tuple(args.crop)
    print(f"crop {crop[0]}x{crop[1]}, batch {args.batch}, {os.cpu_count()} CPUs")
    for kind in args.kind:
        med, best, t = bench_single(meshes, syms, kind, args.batch, args.batches, crop)
        print(f"{kind:8s} 1 process : {med:7.1f} samples/s (median; best {best:.1f}), {1000 * t:.1f} ms per batch")
        if args.workers > 0:
            rate, startup = bench_workers(meshes, syms, kind, args.batch, args.batches, crop, args.workers)
            print(f"{kind:8s} {args.workers} workers : {rate:7.1f} samples/s (worker start-up {startup:.1f} s)")


if __name__ == "__main__":
    main()
