"""Rendering speed of cosy_cli.rendering.SceneRenderer (frames per second, ms per frame).

    .venv/bin/python benchmarks/bench_rendering.py [--repeats 20] [--subdivisions 4]

Scenes: procedural blob objects (~100 mm, vertex-coloured, 20 * 4**subdivisions triangles) at
0.6-0.9 m from a 640x480 camera (fx = fy = 600 px), poses fixed by a seed. Cases: full frames
RGB + depth + instance at 640x480 and 320x240 with 1 and 6 objects, depth-only, silhouettes of
6 objects, and a batch of 32 crops at 128x96 (one object per crop, render-and-compare size).
Reports the median (and the minimum: less sensitive to other processes on a shared machine) over
``--repeats`` timed calls after 3 warm-up calls.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from cosy_cli.rendering import SceneRenderer  # noqa: E402 (selects the GL platform before pyrender)


def blob_mesh(seed: int, subdivisions: int, radius: float = 50.0):
    """A lumpy, asymmetric, vertex-coloured closed mesh of about ``radius`` mm."""
    import trimesh

    rng = np.random.default_rng(seed)
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    v = m.vertices
    bumps = sum(a * np.sin(f * v @ d + p) for a, f, d, p in zip(
        rng.uniform(0.05, 0.15, 4), rng.uniform(1, 4, 4), rng.normal(size=(4, 3)), rng.uniform(0, 6, 4)))
    scale = rng.uniform(0.6, 1.4, 3)
    m.vertices = v * (1 + bumps)[:, None] * scale * radius
    colors = np.clip((v * 0.5 + 0.5) * 255, 0, 255).astype(np.uint8)
    m.visual.vertex_colors = np.concatenate([colors, np.full((len(v), 1), 255, np.uint8)], 1)
    return m


def scene_poses(n: int, rng: np.random.Generator, K: np.ndarray, width: int, height: int) -> np.ndarray:
    from cosy_cli.geometry import make_pose, random_rotations

    z = rng.uniform(600, 900, n)
    uv = np.stack([rng.uniform(0.2, 0.8, n) * width, rng.uniform(0.2, 0.8, n) * height], 1)
    xy = (uv - K[:2, 2]) / np.diag(K)[:2] * z[:, None]
    return make_pose(random_rotations(n, rng), np.concatenate([xy, z[:, None]], 1))


def timeit(fn, repeats: int) -> tuple[float, float]:
    """(median, min) seconds per call after 3 warm-up calls."""
    for _ in range(3):
        fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times)), float(np.min(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--subdivisions", type=int, default=4, help="icosphere subdivisions (4: 5120 faces)")
    args = ap.parse_args()

    rng = np.random.default_rng(0)
    meshes = {i: blob_mesh(i, args.subdivisions) for i in range(1, 7)}
    W, H = 640, 480
    K = np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]])
    K_half = K.copy()
    K_half[:2] = K[:2] / 2
    K_half[:2, 2] = (K[:2, 2] + 0.5) / 2 - 0.5
    T6 = scene_poses(6, rng, K, W, H)
    ids6 = list(range(1, 7))

    from cosy_cli.geometry import crop_intrinsics, fit_box_to_aspect, project

    B, cw, ch = 32, 128, 96
    crop_ids = [int(i) for i in rng.integers(1, 7, B)]
    T_crops = scene_poses(B, rng, K, W, H)
    centres = project(T_crops[:, None, :3, 3], K)[:, 0]
    boxes = fit_box_to_aspect(np.concatenate([centres - 60, centres + 60], 1), cw / ch)
    K_crops = crop_intrinsics(K, boxes, (cw, ch))

    with SceneRenderer(meshes, W, H) as r:
        print(f"OpenGL: {r.gl_renderer} (platform {r.platform}); "
              f"{len(meshes[1].faces)} faces per object; median of {args.repeats}")
        cases = [
            ("640x480 rgb+depth, 1 object", 1, lambda: r.render(K, ids6[:1], T6[:1])),
            ("640x480 rgb+depth, 6 objects", 1, lambda: r.render(K, ids6, T6)),
            ("640x480 depth only, 6 objects", 1, lambda: r.render(K, ids6, T6, with_rgb=False)),
            ("320x240 rgb+depth, 1 object", 1, lambda: r.render(K_half, ids6[:1], T6[:1], size=(320, 240))),
            ("320x240 rgb+depth, 6 objects", 1, lambda: r.render(K_half, ids6, T6, size=(320, 240))),
            ("640x480 silhouettes of 6 objects", 6, lambda: r.render_silhouettes(K, ids6, T6)),
            (f"{B} crops {cw}x{ch} rgb+depth", B, lambda: r.render_crops(K_crops, crop_ids, T_crops, (cw, ch))),
        ]
        print(f"{'case':<36} {'ms/call':>9} {'calls/s':>9} {'ms/image':>9} {'min ms/call':>12}")
        for name, images, fn in cases:
            t, t_min = timeit(fn, args.repeats)
            print(f"{name:<36} {1e3 * t:9.2f} {1 / t:9.1f} {1e3 * t / images:9.2f} {1e3 * t_min:12.2f}")


if __name__ == "__main__":
    main()
