"""Benchmark of the object-level bundle adjustment (cosy refine's core, paper stage 3).

Prints (1) milliseconds per group on one core (BLAS pinned to one thread) for 4 views x 6
objects and 16 views x 20 objects, and (2) accuracy on simulated scenes (6 views x 8 objects):
candidates = ground truth + noise (depth 1 % of the distance by default, 1 mm lateral, 2 deg
rotation, random symmetric flips; only inliers, as cosy match would keep), cameras initialised
from simulated pairwise relative poses as RANSAC would give them. Figures (the issue's measure):
mean ADD-S (D_l, mm) of the input candidates vs the refined predictions in the same views (and
its % change), median relative camera error over view pairs (deg / mm), for the residual points
of the default (the 8 bounding-box corners, as the original CosyPose) and, on the same scenes,
64 surface points (cosy's former default); then the exact-candidate check.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_refine.py [--scenes 20] [--seed 0] [--depth-frac 0.01]

Measured (2-core machine shared with other jobs, 2026-12-01, defaults): 4 x 6: 4.7 ms per group
median (bundle_adjust 2.3 ms), 16 x 20: 24.6 ms (19.3 ms); accuracy (20 scenes, seed 0, depth
noise 1 %): ADD-S 7.18 -> 2.90 mm (-59.6 %), cameras 0.58 deg / 8.4 mm with the box corners;
7.18 -> 3.14 mm (-56.3 %), 0.69 deg / 9.6 mm with 64 surface points. With ``--depth-frac 0.0055``
(input ADD-S ~4 mm, like the issue's hidden cases; the original CosyPose code: -38 %) on 20
held-out scenes: -39.6 % (3.98 -> 2.40 mm), 0.56 deg / 6.6 mm, vs -33.7 %, 0.62 deg / 7.8 mm
before (surface points, best-score start).

The scene simulator below is also used by tests/test_bundle_adjustment.py.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402

import numpy as np  # noqa: E402

from cosy_cli.geometry import axis_angle_to_matrix, invert, look_at, make_pose, random_rotations  # noqa: E402
from cosy_cli.multiview.bundle_adjustment import (  # noqa: E402
    LabelGeometry, bundle_adjust, initialise_cameras, initialise_objects, predictions_from_scene,
)
from cosy_cli.objects import symmetry_set  # noqa: E402

K_DEFAULT = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
IMAGE_SIZE = (640, 480)


# --------------------------------------------------------------------------------------------
# Simulated objects and scenes
# --------------------------------------------------------------------------------------------

def _flip(axis) -> np.ndarray:
    return make_pose(axis_angle_to_matrix(np.pi * np.asarray(axis, dtype=np.float64)), np.zeros(3))


@dataclass
class SimLabel:
    name: str
    geometry: LabelGeometry  # what the optimiser uses (bounding-box corners by default, 64-step continuous set)
    eval_points: np.ndarray  # (P, 3) mm, for ADD-S
    eval_symmetries: np.ndarray  # finer set for evaluation (continuous in 360 steps)


def make_labels(n_points: int = 64, seed: int = 0, point_set: str | None = None) -> list[SimLabel]:
    """Three labels built from trimesh primitives (mm): a box (3 half-turn symmetries), a tall
    cylinder (continuous about z + a half-turn flip), an asymmetric union of three boxes. The
    optimiser's points come from 1000 surface samples: ``point_set`` (None: the default of
    :meth:`LabelGeometry.create`, the bounding-box corners; "surface": ``n_points`` of them)."""
    import trimesh

    box = trimesh.creation.box(extents=(80.0, 50.0, 30.0))
    cyl = trimesh.creation.cylinder(radius=30.0, height=120.0, sections=64)
    a = trimesh.creation.box(extents=(70.0, 40.0, 20.0))
    b = trimesh.creation.box(extents=(20.0, 20.0, 50.0))
    b.apply_translation((20.0, 8.0, 30.0))
    c = trimesh.creation.box(extents=(15.0, 30.0, 12.0))
    c.apply_translation((-28.0, 25.0, -4.0))
    asym = trimesh.util.concatenate([a, b, c])
    out = []
    flips = np.stack([_flip([1, 0, 0]), _flip([0, 1, 0]), _flip([0, 0, 1])])
    cont = [{"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 0.0]}]
    specs = [
        ("box", box, flips, [], None),
        ("cylinder", cyl, flips[:1], cont, (0.0, 0.0, 1.0)),
        ("asymmetric", asym, np.zeros((0, 4, 4)), [], None),
    ]
    for i, (name, mesh, disc, cnt, axis) in enumerate(specs):
        pts, _ = trimesh.sample.sample_surface(mesh, 1000, seed=seed + i)
        pts = np.asarray(pts, dtype=np.float64)
        kw = {} if point_set is None else {"point_set": point_set}
        geo = LabelGeometry.create(pts, symmetry_set(disc, cnt, 64), axis=axis, offset=np.zeros(3), n_points=n_points,
                                   **kw)
        out.append(SimLabel(name, geo, pts[:300], symmetry_set(disc, cnt, 360)))
    return out


@dataclass
class SimScene:
    T_world_cam: np.ndarray  # (V, 4, 4)
    T_world_obj: np.ndarray  # (N, 4, 4)
    obj_label: np.ndarray  # (N,)
    K: np.ndarray  # (V, 3, 3)
    visible: np.ndarray  # (V, N) bool


def make_scene(rng: np.random.Generator, n_views: int, n_objects: int, n_labels: int = 3,
               p_missed: float = 0.15, area_mm: float = 500.0) -> SimScene:
    """Objects on a table (world z = 0 plane, centres 60 mm up, random orientations) seen by
    cameras 650-1000 mm away at 25-65 deg elevation around it, looking near its centre.
    ``visible[v, n]``: the object's centre projects into the image and it was not missed (each
    object is kept in at least two views)."""
    area_mm = max(area_mm, 170.0 * np.sqrt(n_objects))  # room for every object
    pos, tries = [], 0
    while len(pos) < n_objects:  # rejection sampling: centres at least 110 mm apart
        p = rng.uniform(-area_mm / 2, area_mm / 2, 2)
        tries += 1
        if all(np.linalg.norm(p - q) > 110.0 for q in pos) or tries > 10000:
            pos.append(p)
    pos = np.array(pos)
    T_world_obj = make_pose(random_rotations(n_objects, rng), np.c_[pos, np.full(n_objects, 60.0)])
    obj_label = rng.integers(0, n_labels, n_objects)
    obj_label[:min(n_labels, n_objects)] = np.arange(min(n_labels, n_objects))  # every label present
    az = rng.uniform(0, 2 * np.pi) + np.linspace(0, 2 * np.pi, n_views, endpoint=False) * rng.uniform(0.3, 1.0)
    el = np.radians(rng.uniform(25, 65, n_views))
    dist = rng.uniform(650, 1000, n_views)
    eye = np.c_[dist * np.cos(el) * np.cos(az), dist * np.cos(el) * np.sin(az), dist * np.sin(el)]
    target = np.c_[rng.normal(0, 40, (n_views, 2)), np.zeros(n_views)]
    T_world_cam = look_at(eye, target)
    K = np.tile(K_DEFAULT, (n_views, 1, 1))
    c = (invert(T_world_cam)[:, None] @ T_world_obj[None])[..., :3, 3]  # (V, N, 3)
    uv = c[..., :2] / c[..., 2:] * 600.0 + [320.0, 240.0]
    inside = (c[..., 2] > 0) & np.all((uv > 0) & (uv < np.array(IMAGE_SIZE)), axis=-1)
    visible = inside & (rng.random(inside.shape) > p_missed)
    for n in range(n_objects):  # keep each object in >= 2 views
        if visible[:, n].sum() < 2:
            idx = np.flatnonzero(inside[:, n])[:2]
            visible[idx, n] = True
    return SimScene(T_world_cam, T_world_obj, obj_label, K, visible)


@dataclass
class SimCandidates:
    cand_view: np.ndarray  # (M,)
    cand_obj: np.ndarray  # (M,)
    T_cam_cand: np.ndarray  # (M, 4, 4)
    T_cam_gt: np.ndarray  # (M, 4, 4)
    score: np.ndarray  # (M,)


def make_candidates(rng: np.random.Generator, scene: SimScene, labels: list[SimLabel], *, depth_frac=0.01,
                    lateral_mm=1.0, rot_deg=2.0, flips=True) -> SimCandidates:
    """One candidate per visible (view, object): GT pose with noise applied in the camera frame
    (depth scaled by 1 + N(0, depth_frac), lateral N(0, lateral_mm), rotation by an angle
    N(0, rot_deg) about a random axis through the object's origin) and, with ``flips``, a
    uniformly random symmetry of its label (T_gt S is as valid as T_gt) and, for a label with
    a continuous axis, a uniformly random angle about it (not one of the 64 discrete steps)."""
    v, n = np.nonzero(scene.visible)
    M = len(v)
    T_gt = invert(scene.T_world_cam[v]) @ scene.T_world_obj[n]
    t = T_gt[:, :3, 3] * (1.0 + rng.normal(0, depth_frac, (M, 1)))
    t[:, :2] += rng.normal(0, lateral_mm, (M, 2))
    ax = rng.normal(size=(M, 3))
    ax /= np.linalg.norm(ax, axis=1, keepdims=True)
    dR = axis_angle_to_matrix(ax * np.radians(rng.normal(0, rot_deg, (M, 1))))
    T = make_pose(dR @ T_gt[:, :3, :3], t)
    if flips:
        for i in range(M):
            S = labels[scene.obj_label[n[i]]].geometry.symmetries
            T[i] = T[i] @ S[rng.integers(len(S))]
            g = labels[scene.obj_label[n[i]]].geometry
            if g.axis is not None:
                T[i, :3, :3] = T[i, :3, :3] @ axis_angle_to_matrix(g.axis * rng.uniform(0, 2 * np.pi))
    return SimCandidates(v, n, T, T_gt, rng.uniform(0.5, 1.0, M))


def _sym_rms(T_ref: np.ndarray, T: np.ndarray, geo: LabelGeometry) -> np.ndarray:
    """min over S of sqrt(mean_x ||T_ref S x - T[h] x||^2) (mm) for poses T (H, 4, 4), in closed
    form from the points' second moments (the RMS version of D_l)."""
    Xh = np.c_[geo.points, np.ones(len(geo.points))]
    M2 = Xh.T @ Xh / len(Xh)
    B = (invert(T_ref) @ T)[:, :3, :]  # (H, 3, 4)
    S = geo.symmetries[:, :3, :]
    SS = np.sum((S @ M2) * S, axis=(1, 2))
    BB = np.sum((B @ M2) * B, axis=(1, 2))
    cross = (B @ M2).reshape(len(B), 12) @ S.reshape(len(S), 12).T  # (H, S)
    return np.sqrt(np.maximum(SS[None] - 2 * cross + BB[:, None], 0.0).min(1))


def simulated_pair_poses(scene: SimScene, cands: SimCandidates, labels: list[SimLabel], inlier_mm: float = 20.0,
                         min_inliers: int = 3):
    """Relative camera poses as cosy match's RANSAC would give them: for every view pair, every
    shared object k and symmetry S, the hypothesis T_a_b = T_a_k S inv(T_b_k); kept: the one
    with most inlier objects (symmetric RMS distance < inlier_mm), then the lowest summed
    distance. Pairs with fewer than ``min_inliers`` inliers are dropped.
    Returns ({(a, b): T_a_b}, {(a, b): inliers})."""
    V = len(scene.T_world_cam)
    lookup = {(int(a), int(b)): i for i, (a, b) in enumerate(zip(cands.cand_view, cands.cand_obj))}
    geos = [L.geometry for L in labels]
    poses, inliers = {}, {}
    for a in range(V):
        for b in range(a + 1, V):
            common = [k for k in range(len(scene.T_world_obj)) if (a, k) in lookup and (b, k) in lookup]
            if len(common) < min_inliers:
                continue
            hyp = np.concatenate([
                cands.T_cam_cand[lookup[(a, k)]] @ geos[scene.obj_label[k]].symmetries
                @ invert(cands.T_cam_cand[lookup[(b, k)]]) for k in common])  # (H, 4, 4)
            cnt = np.zeros(len(hyp), dtype=int)
            dsum = np.zeros(len(hyp))
            for j in common:
                d = _sym_rms(cands.T_cam_cand[lookup[(a, j)]], hyp @ cands.T_cam_cand[lookup[(b, j)]],
                             geos[scene.obj_label[j]])
                cnt += d < inlier_mm
                dsum += np.minimum(d, inlier_mm)
            i = int(np.lexsort((dsum, -cnt))[0])
            if cnt[i] >= min_inliers:
                poses[(a, b)] = hyp[i]
                inliers[(a, b)] = int(cnt[i])
    return poses, inliers


def add_s(T_est: np.ndarray, T_gt: np.ndarray, obj_label: np.ndarray, labels: list[SimLabel]) -> np.ndarray:
    """D_l (mm) per pose pair: min over the label's (finely discretised) symmetries of the mean
    point distance, mean_x ||T_est S x - T_gt x||; ADD for the asymmetric label."""
    out = np.empty(len(T_est))
    for lab in np.unique(obj_label):
        L = labels[lab]
        XT = L.eval_points.T  # (3, P)
        for i in np.flatnonzero(obj_label == lab):  # a benchmark metric: one pose pair at a time
            TS = T_est[i] @ L.eval_symmetries  # (S, 4, 4)
            p1 = TS[:, :3, :3] @ XT + TS[:, :3, 3:]  # (S, 3, P)
            p2 = T_gt[i, :3, :3] @ XT + T_gt[i, :3, 3:]
            out[i] = np.sqrt(np.sum((p1 - p2) ** 2, axis=1)).mean(axis=1).min()
    return out


def perturb(rng: np.random.Generator, T: np.ndarray, deg: float, mm: float) -> np.ndarray:
    """Poses (B, 4, 4) moved by N(0, mm) per axis and rotated by N(0, deg) about a random axis
    through their origin (right-multiplied: in their own frame)."""
    ax = rng.normal(size=(len(T), 3))
    ax /= np.linalg.norm(ax, axis=1, keepdims=True)
    angle = np.radians(rng.normal(0, deg, (len(T), 1)))
    dT = make_pose(axis_angle_to_matrix(ax * angle), rng.normal(0, mm, (len(T), 3)))
    return T @ dT


def run_refine(scene: SimScene, cands: SimCandidates, labels: list[SimLabel], pair_poses=None, pair_inliers=None,
               init_noise=None, rng=None, **kw):
    """initialise_cameras -> initialise_objects -> bundle_adjust on simulated data. Returns
    (result, placed view indices, T_cam_pred (M, 4, 4) for candidates in placed views, mask).
    ``init_noise`` = (deg, mm): perturbs the initial cameras (but the gauge) and objects."""
    V = len(scene.T_world_cam)
    if pair_poses is None:
        pair_poses, pair_inliers = simulated_pair_poses(scene, cands, labels)
    placed, unplaced = initialise_cameras(list(range(V)), pair_poses, pair_inliers)
    views = list(placed)  # gauge first
    vidx = np.full(V, -1)
    vidx[views] = np.arange(len(views))
    keep = vidx[cands.cand_view] >= 0
    cv, co = vidx[cands.cand_view[keep]], cands.cand_obj[keep]
    Twc = np.stack([placed[v] for v in views])
    geos = [L.geometry for L in labels]
    Two, sym, _ = initialise_objects(Twc, cv, co, cands.T_cam_cand[keep], scene.obj_label, geos, cands.score[keep])
    if init_noise is not None:
        Twc[1:] = perturb(rng, Twc[1:], *init_noise)
        Two = perturb(rng, Two, *init_noise)
    res = bundle_adjust(Twc, Two, cv, co, cands.T_cam_cand[keep], scene.K[views], scene.obj_label, geos,
                        symmetries=np.stack([geos[scene.obj_label[o]].symmetries[s] for o, s in zip(co, sym)]),
                        **kw)
    T_pred = predictions_from_scene(res.T_world_cam, res.T_world_obj)[cv, co]
    return res, views, T_pred, keep


def camera_errors(scene: SimScene, views: list[int], T_world_cam_est: np.ndarray):
    """Relative pose error (deg, mm) between every pair of placed views."""
    from cosy_cli.geometry import relative_pose_error

    a, b = np.triu_indices(len(views), 1)
    v = np.asarray(views)
    T_est = invert(T_world_cam_est[a]) @ T_world_cam_est[b]
    T_gt = invert(scene.T_world_cam[v[a]]) @ scene.T_world_cam[v[b]]
    return relative_pose_error(T_est, T_gt)


# --------------------------------------------------------------------------------------------
# Benchmark
# --------------------------------------------------------------------------------------------

def _timing(labels, n_views, n_objects, repeats, seed):
    rng = np.random.default_rng(seed)
    scene = make_scene(rng, n_views, n_objects, p_missed=0.0)
    scene.visible[:] = True  # every object in every view: V x N candidates
    cands = make_candidates(rng, scene, labels)
    pair_poses, pair_inliers = simulated_pair_poses(scene, cands, labels)
    times, its, times_ba = [], [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        res, *_ = run_refine(scene, cands, labels, pair_poses, pair_inliers)
        times.append(time.perf_counter() - t0)
        times_ba.append(res.time_s)
        its.append(res.iterations)
    return (len(cands.cand_view), np.median(times) * 1e3, np.min(times) * 1e3, np.median(times_ba) * 1e3,
            int(np.median(its)))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--depth-frac", type=float, default=0.01, help="candidate depth noise, fraction of the distance")
    ap.add_argument("--lateral-mm", type=float, default=1.0)
    ap.add_argument("--rot-deg", type=float, default=2.0)
    args = ap.parse_args(argv)
    try:
        from threadpoolctl import threadpool_limits
        threadpool_limits(1)
    except ImportError:
        pass
    labels = make_labels()

    print("== timing (one core, BLAS 1 thread; per group: initialise cameras from pair poses and objects, "
          "then bundle_adjust)")
    for V, N in [(4, 6), (16, 20)]:
        M, ms, best, ms_ba, its = _timing(labels, V, N, args.repeats if V < 10 else max(5, args.repeats // 4),
                                          args.seed)
        print(f"{V:2d} views x {N:2d} objects ({M:3d} candidates): {ms:7.2f} ms per group median, {best:7.2f} best "
              f"(bundle_adjust alone {ms_ba:7.2f} ms median, {its} LM iterations)")

    noise = dict(depth_frac=args.depth_frac, lateral_mm=args.lateral_mm, rot_deg=args.rot_deg)
    print(f"== accuracy: {args.scenes} simulated scenes of 6 views x 8 objects (noise: depth "
          f"{100 * args.depth_frac:.3g} %, lateral {args.lateral_mm:g} mm, rotation {args.rot_deg:g} deg, random symmetric "
          "flips); same scenes for both point sets")
    for name, labs in [("bounding-box corners (default)", labels),
                       ("64 surface points (former default)", make_labels(point_set="surface"))]:
        _accuracy(name, labs, args.scenes, args.seed, noise)
    rng = np.random.default_rng(args.seed + 2)

    print("== exact candidates (no noise, random flips and spins), initial poses perturbed by 2 deg / 10 mm")
    worst_obj, worst_cam_r, worst_cam_t, worst_cost = 0.0, 0.0, 0.0, 0.0
    for _ in range(10):
        scene = make_scene(rng, 6, 8)
        cands = make_candidates(rng, scene, labels, depth_frac=0.0, lateral_mm=0.0, rot_deg=0.0)
        res, views, T_pred, keep = run_refine(scene, cands, labels, init_noise=(2.0, 10.0), rng=rng)
        # exact: each prediction is its candidate up to the (continuously refined) symmetry S
        T_sym = cands.T_cam_cand[keep] @ res.symmetries
        d = np.linalg.norm(transform(T_pred, labels, scene, cands, keep) - transform(T_sym, labels, scene, cands, keep),
                           axis=-1).max()
        r, t = camera_errors(scene, views, res.T_world_cam)
        worst_obj = max(worst_obj, float(d))
        worst_cam_r, worst_cam_t = max(worst_cam_r, float(r.max())), max(worst_cam_t, float(t.max()))
        worst_cost = max(worst_cost, res.final_cost)
    print(f"max point distance prediction vs exact candidate: {worst_obj:.2e} mm (target <= 0.1); "
          f"max camera error {worst_cam_r:.1e} deg, {worst_cam_t:.1e} mm; max final cost {worst_cost:.1e} px^2")


def _accuracy(name, labels, n_scenes, seed, noise):
    rng = np.random.default_rng(seed + 1)
    err_in, err_out, rot_e, tr_e, its, placed_frac, n_cands = [], [], [], [], [], [], 0
    per_label_in = {i: [] for i in range(len(labels))}
    per_label_out = {i: [] for i in range(len(labels))}
    for _ in range(n_scenes):
        scene = make_scene(rng, 6, 8)
        cands = make_candidates(rng, scene, labels, **noise)
        res, views, T_pred, keep = run_refine(scene, cands, labels)
        lab = scene.obj_label[cands.cand_obj[keep]]
        e_in = add_s(cands.T_cam_cand[keep], cands.T_cam_gt[keep], lab, labels)
        e_out = add_s(T_pred, cands.T_cam_gt[keep], lab, labels)
        err_in.append(e_in)
        err_out.append(e_out)
        for i in per_label_in:
            per_label_in[i].append(e_in[lab == i])
            per_label_out[i].append(e_out[lab == i])
        r, t = camera_errors(scene, views, res.T_world_cam)
        rot_e.append(r)
        tr_e.append(t)
        its.append(res.iterations)
        placed_frac.append(len(views) / 6)
        n_cands += int(keep.sum())
    e_in, e_out = np.concatenate(err_in), np.concatenate(err_out)
    r, t = np.concatenate(rot_e), np.concatenate(tr_e)
    print(f"-- {name}: {n_cands} candidates in placed views; views placed: {100 * np.mean(placed_frac):.1f} %")
    print(f"   mean ADD-S input candidates: {e_in.mean():6.2f} mm -> refined: {e_out.mean():6.2f} mm "
          f"({100 * (e_out.mean() / e_in.mean() - 1):+.1f} %; original CosyPose on the issue's cases: -38 %)")
    print("   per label: " + ", ".join(
        f"{L.name} {np.concatenate(per_label_in[i]).mean():.2f} -> {np.concatenate(per_label_out[i]).mean():.2f} mm"
        for i, L in enumerate(labels)))
    print(f"   relative camera error, median over view pairs: {np.median(r):.3f} deg, {np.median(t):.2f} mm "
          f"(targets <= 1 deg, <= 12 mm); 90th percentile {np.percentile(r, 90):.3f} deg, {np.percentile(t, 90):.2f} mm;"
          f" LM iterations median {int(np.median(its))}, max {max(its)}")


def transform(T: np.ndarray, labels, scene, cands, keep) -> np.ndarray:
    """Model points of each candidate's label under poses T (M, 4, 4) -> (M, P, 3) mm."""
    X = np.stack([labels[scene.obj_label[o]].geometry.points for o in cands.cand_obj[keep]])
    return X @ np.swapaxes(T[:, :3, :3], 1, 2) + T[:, None, :3, 3]


if __name__ == "__main__":
    main()
