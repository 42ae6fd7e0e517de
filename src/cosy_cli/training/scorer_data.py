"""Training samples of the learned hypothesis scorer, written as shards a run resumes from.

One shard: ``images`` rendered scenes of the dataset's objects from the detector's generator
(:class:`~cosy_cli.detection.data.DetectionSampleGenerator`: objects resting on a table or floating,
occluded by each other, random backgrounds, lights, colour noise, blur and sensor noise; with
probability ``p_mesh_colors`` an object of a coloured mesh keeps its own colours, as a real object
does), among up to ``max_distractors`` unlabelled shapes of ``cosy synth`` as clutter (with
``backgrounds``, a folder of photographs: windows of them behind ``p_photo`` of the images and on
``p_photo_texture`` of the surfaces), with a
stronger white-balance (``gain_jitter``), saturation and blur jitter than the detector's, at the
dataset camera's full image size. Every object at least ``min_visib`` visible is a
detection, its box the visible box moved by N(0, ``box_jitter`` x its size) per edge (what a
detector's boxes look like; exact with probability ``p_exact_box``). Its hypotheses are exactly
what ``cosy estimate`` would verify: the template matcher's best ``verify_top`` (the real hard
negatives), scored by the verifier with its coarse copies, of which the ``keep_best`` best by the
training-free score and ``keep_random`` others are kept; plus ``perturbed`` poses near the ground
truth (rotations of 1-40 deg about a random axis, log-uniform, image shifts, depth changes: what
the refinement steps try), rendered with the full copies. Each hypothesis stores the verifier's
render and terms (:meth:`~cosy_cli.singleview.training_free.verify.Verifier.score` with
``inputs``) and its target, the AR contribution (:mod:`.scorer_target`).

A shard is an ``.npz`` written atomically; shard i uses seed (seed, i), so a run that stops
resumes with the same data, and ``workers`` processes write shards in parallel.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..detection.data import DISTRACTOR_ID0  # renderer ids of the clutter meshes
from ..io.atomic import atomic_path
from .scorer_target import ar_contribution, max_errors

DATA_DEFAULTS = {
    "crop": 64,                    # side px of the verification crops the scorer sees (the verifier's is 64)
    "images_per_shard": 24,
    "verify_top": 48,
    "keep_best": 8,
    "keep_random": 8,
    "perturbed": 8,
    "min_visib": 0.1,
    "box_jitter": 0.04,
    "p_exact_box": 0.3,
    "p_mesh_colors": 0.6,
    "min_objects": 3,
    "max_objects": 8,
    "max_distractors": 4,          # unlabelled clutter: cosy synth's shapes, random colours
    "gain_jitter": 0.25,           # per-channel gain (white balance) U(1 -+ this)
    "saturation": [0.6, 1.3],
    "blur": [0.6, 0.4, 1.5],       # probability, sigma range (px of the full image)
    "n_points": 300,
    "backgrounds": None,           # a folder of photographs: random windows of them behind the objects ...
    "p_photo": 0.5,                # ... in this share of the images
    "p_photo_texture": 0.5,        # ... and on this share of the table and clutter surfaces
}


def shard_path(folder: Path, i: int) -> Path:
    return Path(folder) / f"shard_{i:05d}.npz"


def _jitter_boxes(boxes: np.ndarray, rng, sigma: float, p_exact: float, W: int, H: int) -> np.ndarray:
    wh = np.maximum(boxes[:, 2:] - boxes[:, :2], 1.0)
    d = rng.normal(0, sigma, boxes.shape) * np.concatenate([wh, wh], 1)
    d[rng.random(len(boxes)) < p_exact] = 0.0
    out = boxes + d
    out[:, [0, 2]] = np.clip(out[:, [0, 2]], 0, W)
    out[:, [1, 3]] = np.clip(out[:, [1, 3]], 0, H)
    out[:, 2:] = np.maximum(out[:, 2:], out[:, :2] + 2.0)
    return out


def perturb_near(T: np.ndarray, K: np.ndarray, rng, n: int) -> np.ndarray:
    """(m, n, 4, 4) poses near each of T (m, 4, 4) mm seen with intrinsics K (3, 3): a rotation about
    the object origin by a random axis x an angle log-uniform in 1-40 deg, an image shift of
    N(0, 1 + angle / 4) px at the object's depth and the depth x exp(N(0, 0.01 + angle / 1000))."""
    from ..geometry.rotations import axis_angle_to_matrix

    m = len(T)
    ang = np.exp(rng.uniform(np.log(1.0), np.log(40.0), (m, n)))
    axis = rng.normal(size=(m, n, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    dR = axis_angle_to_matrix((axis * np.radians(ang)[..., None]).reshape(-1, 3)).reshape(m, n, 3, 3)
    out = np.repeat(T[:, None], n, 1).copy()
    out[..., :3, :3] = dR @ T[:, None, :3, :3]
    t = T[:, :3, 3]
    px = rng.normal(size=(m, n, 2)) * (1.0 + ang[..., None] / 4.0)
    shift = np.zeros((m, n, 3))
    shift[..., 0] = px[..., 0] * t[:, None, 2] / K[0, 0]
    shift[..., 1] = px[..., 1] * t[:, None, 2] / K[1, 1]
    dz = np.exp(rng.normal(size=(m, n)) * (0.01 + ang / 1000.0))
    out[..., :3, 3] = (t[:, None] + shift) * dz[..., None]
    return out


class ShardMaker:
    """Writes shards for one object set (an ObjectDatabase ``db``, templates ``templates``, the dataset
    camera K (3, 3) and image size (w, h)); ``conf``: :data:`DATA_DEFAULTS` plus ``seed``."""

    def __init__(self, db, templates, K, image_size, conf: dict, verify_conf=None):
        from ..detection.data import DetectionSampleGenerator  # noqa: F401 (imported in make)
        from ..singleview.training_free.verify import Verifier, VerifyConf

        self.db, self.templates, self.conf = db, templates, conf
        self.K = np.asarray(K, np.float64)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.verifier = Verifier(db, verify_conf or VerifyConf(crop=int(conf["crop"])))
        self.meshes = {o.obj_id: o.mesh for o in db}
        from ..synth.objects import object_meshes

        self.distractors = {DISTRACTOR_ID0 + k: m for k, m in object_meshes().items()} \
            if conf["max_distractors"] > 0 else {}
        self.obj_index = {o.obj_id: i for i, o in enumerate(db)}
        self.points = {}
        for o in db:
            P = np.asarray(o.points, np.float64)
            if len(P) > conf["n_points"]:
                P = P[np.random.default_rng(0).choice(len(P), conf["n_points"], replace=False)]
            self.points[o.obj_id] = P
        self.sym = {o.obj_id: np.asarray(o.symmetries, np.float64) for o in db}
        self.diam = {o.obj_id: float(o.diameter) for o in db}
        from ..detection.train import photo_kwargs

        self.photos = photo_kwargs(conf)

    def close(self):
        self.verifier.close()

    def make(self, i: int) -> dict:
        """The arrays of shard ``i`` (see the module docstring)."""
        from ..detection.data import DetectionSampleGenerator
        from ..singleview.training_free.templates import MatchParams, match_templates
        from ..singleview.training_free.verify import observe

        c = self.conf
        rng = np.random.default_rng([int(c["seed"]), int(i), 7])
        gen = DetectionSampleGenerator(self.meshes, self.K, self.image_size, self.image_size,
                                       seed=[int(c["seed"]), int(i)], max_objects=c["max_objects"],
                                       min_objects=c["min_objects"],
                                       min_visib=c["min_visib"], p_mesh_colors=c["p_mesh_colors"],
                                       distractors=self.distractors, max_distractors=c["max_distractors"],
                                       gain_jitter=c["gain_jitter"], saturation=c["saturation"], blur=c["blur"],
                                       **self.photos)
        try:
            b = gen.batch(int(c["images_per_shard"]))
        finally:
            gen.close()
        W, H = self.image_size
        vc = self.verifier.conf
        rows = {k: [] for k in ("obs_rgb", "in_box", "not_bg", "det_obj", "rgba", "gain", "terms", "target",
                                "e_mssd", "e_mspd", "det", "perturbed")}
        n_det = 0
        for k in range(len(b["images"])):
            img, K = b["images"][k], b["K"][k]
            labels = b["labels"][k]
            if not len(labels):
                continue
            obj_ids = gen.obj_ids[labels]
            boxes = _jitter_boxes(b["boxes"][k], rng, c["box_jitter"], c["p_exact_box"], W, H)
            T_gt = b["T_cam_obj"][k]
            N = len(boxes)
            h = match_templates(self.templates, img, K, boxes, obj_ids, top_k=c["verify_top"],
                                params=MatchParams(nms_deg=10.0))
            obs = [observe(img, K, bx, vc) for bx in boxes]
            valid = np.isfinite(h.scores)
            di, hi = np.nonzero(valid)
            got = self.verifier.score(obs, di, obj_ids[di], h.T_cam_obj[di, hi], h.scores[di, hi],
                                      max_faces=vc.rank_faces if 0 < vc.rank_faces < vc.max_faces else None,
                                      inputs=True)
            pick = []
            for d in range(N):  # the keep_best by training-free score, keep_random of the others
                idx = np.flatnonzero(di == d)
                if not len(idx):
                    continue
                order = idx[np.argsort(-got["total"][idx], kind="stable")]
                best, rest = order[:c["keep_best"]], order[c["keep_best"]:]
                pick.append(np.concatenate([best, rng.permutation(rest)[:c["keep_random"]]]))
            pick = np.concatenate(pick) if pick else np.zeros(0, np.int64)
            Tp = perturb_near(T_gt, K, rng, c["perturbed"])
            dp = np.repeat(np.arange(N), c["perturbed"])
            got_p = self.verifier.score(obs, dp, obj_ids[dp], Tp.reshape(-1, 4, 4), None, inputs=True)
            # both parts in one list: observation index d of the shard = n_det + detection
            parts = [(di[pick], h.T_cam_obj[di[pick], hi[pick]], got, pick, 0), (dp, Tp.reshape(-1, 4, 4), got_p,
                                                                               np.arange(len(dp)), 1)]
            for dets, T, g, sel, pert in parts:
                if not len(dets):
                    continue
                e1, e2 = np.zeros(len(dets)), np.zeros(len(dets))
                for o in np.unique(obj_ids[dets]):
                    m = obj_ids[dets] == o
                    e1[m], e2[m] = max_errors(T[m], T_gt[dets[m]], K, self.points[int(o)], self.sym[int(o)])
                diam = np.array([self.diam[int(o)] for o in obj_ids[dets]])
                rows["rgba"].append(g["rgba"][sel])
                rows["gain"].append(g["gain"][sel])
                rows["terms"].append(g["terms"][sel])
                rows["target"].append(ar_contribution(e1, e2, diam, W).astype(np.float32))
                rows["e_mssd"].append(e1.astype(np.float32))
                rows["e_mspd"].append(e2.astype(np.float32))
                rows["det"].append((n_det + dets).astype(np.int32))
                rows["perturbed"].append(np.full(len(dets), pert, np.uint8))
            for o in obs:
                rows["obs_rgb"].append(np.round(o.rgb * 255).astype(np.uint8))
                rows["in_box"].append(o.in_box)
                rows["not_bg"].append(np.round(o.not_bg * 255).astype(np.uint8))
            rows["det_obj"].append(obj_ids.astype(np.int32))
            n_det += N
        S = vc.crop
        empty = {"obs_rgb": (0, S, S, 3), "in_box": (0, S, S), "not_bg": (0, S, S), "rgba": (0, S, S, 4)}
        out = {}
        for k, v in rows.items():
            if v:
                out[k] = np.concatenate(v) if k in ("det_obj", "rgba", "gain", "terms", "target", "e_mssd", "e_mspd",
                                                    "det", "perturbed") else np.stack(v)
            else:
                out[k] = np.zeros(empty.get(k, (0,)), np.float32)
        return out


def write_shard(maker: ShardMaker, folder: Path, i: int) -> Path:
    path = shard_path(folder, i)
    arrays = maker.make(i)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
    return path


_MAKER = None


def _worker_init(args):
    global _MAKER
    import os

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    models_dir, templates_dir, K, size, conf, output = args
    from .. import console

    console.enter_worker(output)
    from ..objects import ObjectDatabase
    from ..singleview.training_free.templates import TemplateSet

    db = ObjectDatabase.from_models_dir(models_dir)
    _MAKER = ShardMaker(db, TemplateSet.load(templates_dir), K, size, conf)


def _worker_shard(job):
    folder, i = job
    return str(write_shard(_MAKER, Path(folder), i))


def write_shards(models_dir, templates_dir, K, image_size, conf: dict, folder: Path, indices, workers: int = 1,
                 progress: bool = True):
    """Write the missing shards of ``indices`` into ``folder`` (``workers`` processes), for the
    objects of ``models_dir`` and their templates in ``templates_dir``."""
    from ..console import progress as progress_bar

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    todo = [i for i in indices if not shard_path(folder, i).is_file()]
    if not todo:
        return
    bar = progress_bar(total=len(todo), desc="scorer data", unit="shard", enabled=progress)
    try:
        if workers <= 1:
            from ..objects import ObjectDatabase
            from ..singleview.training_free.templates import TemplateSet

            maker = ShardMaker(ObjectDatabase.from_models_dir(models_dir), TemplateSet.load(templates_dir), K,
                               image_size, conf)
            try:
                for i in todo:
                    write_shard(maker, folder, i)
                    bar.update(1)
            finally:
                maker.close()
        else:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            from .. import console

            ctx = mp.get_context("spawn")
            args = (str(models_dir), str(templates_dir), K, image_size, conf, console.worker_state())
            with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_init, initargs=(args,)) as ex:
                for _ in ex.map(_worker_shard, [(str(folder), i) for i in todo]):
                    bar.update(1)
    finally:
        bar.close()


def load_shards(folder: Path, indices) -> dict:
    """The shards ``indices`` of ``folder`` joined: observations renumbered (``det`` indexes the
    joined ``obs_rgb``, ``in_box``, ``not_bg``, ``det_obj``)."""
    parts = [dict(np.load(shard_path(folder, i))) for i in indices]
    out, offset = {}, 0
    for p in parts:
        p["det"] = p["det"].astype(np.int64) + offset
        offset += len(p["obs_rgb"])
    for k in parts[0]:
        out[k] = np.concatenate([p[k] for p in parts])
    return out


__all__ = ["DATA_DEFAULTS", "ShardMaker", "write_shards", "load_shards", "shard_path", "perturb_near"]
