"""``cosy train scorer``: onboard the learned hypothesis scorer for a set of meshes, on a CPU.

Three phases in one run folder (``<out stem>.run/`` next to the exported ``out``), each resumable:

1. templates of the meshes (``templates/``, as ``cosy estimate`` builds them);
2. training data (``shards/``, :mod:`.scorer_data`): ``shards`` shards for training and
   ``val_shards`` more with other seeds for validation, written by ``workers`` processes;
3. training (:mod:`.loop`: ``checkpoint.pt``, ``log.csv``, ``loss.png``): the
   :class:`~cosy_cli.singleview.scorer.model.ScorerNet` on all stored hypotheses of
   ``batch_size`` random detections of the training shards per step. The loss: binary
   cross-entropy against the soft AR targets (a calibrated score) plus ``rank_weight`` x a listwise
   term that ranks each detection's hypotheses (cross-entropy between the softmax of the logits
   and the softmax of target / ``rank_temperature``: what the ranking and the accept tests use).
   AdamW with warm-up and a cosine schedule, random horizontal flips of observation and render
   together. Every ``checkpoint_every``
   steps and at the end it is validated on the validation shards: per detection, the target (AR
   contribution) of the template hypothesis the scorer ranks first (``val_pick``) next to that of
   the training-free score's first (``val_pick_tf``) and the best possible (``val_oracle``).

Then the final weights are exported (:func:`~cosy_cli.singleview.scorer.model.export_onnx`) with a
card naming the objects, the verification crop and the validation figures. Nothing is chosen on
real images: the validation shards only report.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Callable

import numpy as np

from ..conf import merge_conf
from ..errors import CosyError
from ..io.atomic import atomic_path
from . import loop
from .scorer_data import DATA_DEFAULTS, load_shards, write_shards

PRECISIONS = ("int8", "fp32")
# settings a run may change when it resumes: the loop's, and the precision (used only by the export)
RESUMABLE = loop.RESUMABLE_CHANGES | {"precision"}
LOG_FIELDS = ["step", "time_s", "lr", "loss_total", "loss_bce", "loss_rank", "val_pick", "val_pick_tf", "val_oracle", "hyps_per_s"]

DEFAULT_CONF = dict(DATA_DEFAULTS, **{
    "kind": "scorer",
    "arch": "lite0",             # lite0: a head on frozen ImageNet EfficientNet-Lite0 maps; plain: a small CNN from scratch
    "shards": 100,               # training shards of images_per_shard images (about 10 min with 2 workers)
    "val_shards": 4,
    "widths": None,              # None: the arch's (plain [24, 48, 64, 96], lite0 [64, 128])
    "precision": "int8",         # lite0's exported trunk: int8 (calibrated on validation renders) or fp32
    "hidden": 64,
    "iterations": 6000,          # steps of batch_size detections (lite0: about 8 min on 2 cores, after its maps)
    "batch_size": 6,             # detections per step, each with all its stored hypotheses (about 24)
    "rank_weight": 1.0,
    "rank_temperature": 0.1,
    "lr": 2e-3,
    "warmup": 200,
    "schedule": "cosine",
    "weight_decay": 1e-4,
    "seed": 0,
    "device": "cpu",
    "workers": 2,
    "checkpoint_every": 500,
    "log_every": 50,
})

# default: 100 shards and 6000 steps chosen on the odd LM-O scenes against 40 and 3000 (0.401 vs 0.386 AR)
CONFS = {"default": DEFAULT_CONF,
         # a longer onboarding: three times the data, five times the steps
         "long": dict(DEFAULT_CONF, shards=300, iterations=30000),
         # the first scorer: a CNN from scratch (learns the renders, not real photographs)
         "plain": dict(DEFAULT_CONF, arch="plain", shards=150, iterations=8000)}


def resolve_conf(conf: str | dict | None = None, **overrides) -> dict:
    c = merge_conf(CONFS, conf, {k: v for k, v in overrides.items() if v is not None}, default="default",
                   what="scorer training")
    try:
        for k in ("shards", "val_shards", "hidden", "iterations", "batch_size", "warmup", "seed", "workers",
                  "checkpoint_every", "log_every", "images_per_shard", "verify_top", "keep_best", "keep_random",
                  "perturbed", "min_objects", "max_objects", "n_points", "max_distractors", "crop"):
            c[k] = int(c[k])
        c["saturation"] = [float(v) for v in c["saturation"]]
        c["blur"] = [float(v) for v in c["blur"]]
        for k in ("lr", "weight_decay", "rank_weight", "rank_temperature", "min_visib", "box_jitter", "p_exact_box",
                  "p_mesh_colors", "gain_jitter", "p_photo", "p_photo_texture"):
            c[k] = float(c[k])
        c["widths"] = None if c["widths"] is None else [int(w) for w in c["widths"]]
    except (TypeError, ValueError) as e:
        raise CosyError(f"scorer training settings: {e}") from None
    if c["shards"] < 1 or c["val_shards"] < 1 or c["iterations"] < 1 or c["batch_size"] < 2 or c["lr"] <= 0 \
            or c["images_per_shard"] < 1 or c["verify_top"] < 1 or (c["widths"] is not None and len(c["widths"]) < 1) \
            or c["workers"] < 0 \
            or c["rank_weight"] < 0 or c["rank_temperature"] <= 0:
        raise CosyError("scorer training settings out of range (shards, val_shards, iterations, images_per_shard, "
                        "verify_top >= 1; batch_size >= 2 detections; lr, rank_temperature > 0; rank_weight >= 0)")
    if c["backgrounds"] is not None:
        c["backgrounds"] = str(Path(c["backgrounds"]).resolve())
    if not (32 <= c["crop"] <= 256 and c["crop"] % 16 == 0):
        raise CosyError(f"scorer training setting crop: a side of 32 to 256 px, a multiple of 16, got {c['crop']}")
    from ..singleview.scorer.model import ARCHS

    if c["arch"] not in ARCHS:
        raise CosyError(f"scorer training setting arch: expected one of {', '.join(ARCHS)}, got {c['arch']!r}")
    if c["precision"] not in PRECISIONS:
        raise CosyError(f"scorer training setting precision: expected one of {', '.join(PRECISIONS)}, "
                        f"got {c['precision']!r}")
    if c["arch"] == "lite0" and c["widths"] is not None and len(c["widths"]) != 2:
        raise CosyError("scorer arch lite0: widths are two numbers (the head's channels at strides 8 and 16)")
    return c


def run_folder(out: str | Path) -> Path:
    """The run folder of an exported scorer ``out``: ``<out without suffix>.run`` beside it."""
    out = Path(out)
    return out.with_name(out.stem + ".run")


class _Batches:
    """Network inputs of hypotheses of loaded shards (:func:`~cosy_cli.singleview.scorer.features.assemble`);
    :meth:`logits` runs a :class:`~cosy_cli.singleview.scorer.model.ScorerNet` on them."""

    def __init__(self, data: dict):
        self.d = data

    def inputs(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        from ..singleview.scorer.features import assemble

        d = self.d
        det = d["det"][idx]
        u, inv = np.unique(det, return_inverse=True)
        x = assemble(d["obs_rgb"][u].astype(np.float32) / np.float32(255.0), d["in_box"][u],
                     d["not_bg"][u].astype(np.float32) / np.float32(255.0), inv, d["rgba"][idx], d["gain"][idx])
        return x, d["terms"][idx]

    def logits(self, net, idx: np.ndarray, flip: np.ndarray | None = None):
        import torch

        dev = next(net.parameters()).device
        x, t = self.inputs(idx)
        if flip is not None:
            x[flip] = x[flip][..., ::-1]
        return net(torch.from_numpy(np.ascontiguousarray(x)).to(dev), torch.from_numpy(t).to(dev))


class _MapBatches(_Batches):
    """For the lite0 scorer: its frozen trunk's maps of every stored hypothesis, computed once
    (:func:`ensure_maps`, float16), so that training runs only the head."""

    def __init__(self, data: dict, maps: dict):
        super().__init__(data)
        self.m = maps

    def logits(self, net, idx: np.ndarray, flip: np.ndarray | None = None):
        import torch

        dev = next(net.parameters()).device
        m, det = self.m, self.d["det"][idx]
        arrs = [m["o8"][det], m["p8"][idx], m["o16"][det], m["p16"][idx], m["m8"][idx]]
        if flip is not None:  # the maps of a mirrored image are close to the mirrored maps
            for a in arrs:
                a[flip] = a[flip][..., ::-1]
        ts = [torch.from_numpy(np.ascontiguousarray(a, np.float32)).to(dev) for a in arrs]
        return net.head_logit(*ts, torch.from_numpy(self.d["terms"][idx]).to(dev))


def ensure_maps(net, shard_folder: Path, map_folder: Path, indices, progress: bool = True) -> dict:
    """The lite0 scorer's trunk maps (:meth:`~cosy_cli.singleview.scorer.model.Lite0ScorerNet.maps`)
    of the shards ``indices``, one ``.npz`` per shard in ``map_folder`` (written atomically, reused
    when present), joined as :func:`~cosy_cli.training.scorer_data.load_shards` joins the shards."""
    import torch

    from ..console import progress as progress_bar
    from .scorer_data import shard_path

    map_folder = Path(map_folder)
    map_folder.mkdir(parents=True, exist_ok=True)
    todo = [i for i in indices if not shard_path(map_folder, i).is_file()]
    bar = progress_bar(total=len(todo), desc="scorer maps", unit="shard", enabled=progress and bool(todo))
    was = net.training
    net.eval()
    try:
        for i in todo:
            b = _Batches(load_shards(shard_folder, [i]))
            n = len(b.d["target"])
            out = {"o8": [], "o16": [], "p8": [], "p16": [], "m8": []}
            with torch.no_grad():
                obs = b.d["obs_rgb"]  # the observations once, (x - 0.5) / 0.5
                for s in range(0, len(obs), 256):
                    x = torch.from_numpy(np.moveaxis(obs[s:s + 256], -1, 1).astype(np.float32) / np.float32(127.5) - 1)
                    f8, f16 = net.trunk(x)
                    out["o8"].append(f8.numpy().astype(np.float16))
                    out["o16"].append(f16.numpy().astype(np.float16))
                for s in range(0, n, 256):  # the renders pasted onto them
                    x, _ = b.inputs(np.arange(s, min(n, s + 256)))
                    _, pasted, m8 = net.split(torch.from_numpy(x))
                    f8, f16 = net.trunk(2.0 * pasted)
                    out["p8"].append(f8.numpy().astype(np.float16))
                    out["p16"].append(f16.numpy().astype(np.float16))
                    out["m8"].append(m8.numpy().astype(np.float16))
            out = {k: np.concatenate(v) for k, v in out.items()}
            with atomic_path(shard_path(map_folder, i)) as tmp:
                with open(tmp, "wb") as f:
                    np.savez(f, **out)
            bar.update(1)
    finally:
        bar.close()
        net.train(was)
    parts = [dict(np.load(shard_path(map_folder, i))) for i in indices]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def validate(net, batches: _Batches, batch: int = 512) -> dict:
    """Scores of every hypothesis of the batches' data, and per detection the target of the template
    hypothesis ranked first by the network, by the training-free total, and the best (means over
    detections)."""
    import torch

    data = batches.d
    n = len(data["target"])
    pred = np.empty(n)
    was = net.training
    net.eval()
    with torch.no_grad():
        for i in range(0, n, batch):
            idx = np.arange(i, min(n, i + batch))
            pred[idx] = batches.logits(net, idx).cpu().numpy()
    net.train(was)
    return _picks(data, pred)


def validate_onnx(path: Path, batches: _Batches, detections: int = 64) -> dict:
    """:func:`validate` of an exported scorer (onnxruntime, e.g. the int8 one), ``detections``
    detections at a time (each observed crop through the trunk once)."""
    from ..singleview.scorer.runtime import OnnxScorer

    data = batches.d
    sc = OnnxScorer(path)
    pred = np.empty(len(data["target"]))
    groups = _groups(data["det"])
    for i in range(0, len(groups), detections):
        g = groups[i:i + detections]
        idx = np.sort(g[g >= 0])
        x, t = batches.inputs(idx)
        p = np.clip(sc(x, t, data["det"][idx]), 1e-12, 1 - 1e-12)
        pred[idx] = np.log(p / (1 - p))  # logits, as validate's
    return _picks(data, pred)


def _picks(data: dict, pred: np.ndarray) -> dict:
    """Per detection the target of the template hypothesis that ``pred`` (one score per stored
    hypothesis) ranks first, that the training-free total ranks first, and the best (means)."""
    tmpl = data["perturbed"] == 0
    det = data["det"][tmpl]
    tgt, p, tf = data["target"][tmpl], pred[tmpl], data["terms"][tmpl][:, 6]
    picks, picks_tf, best = [], [], []
    order = np.argsort(det, kind="stable")
    det, tgt, p, tf = det[order], tgt[order], p[order], tf[order]
    starts = np.flatnonzero(np.r_[True, det[1:] != det[:-1]])
    for s, e in zip(starts, np.r_[starts[1:], len(det)]):
        picks.append(tgt[s + np.argmax(p[s:e])])
        picks_tf.append(tgt[s + np.argmax(tf[s:e])])
        best.append(tgt[s:e].max())
    return {"val_pick": float(np.mean(picks)), "val_pick_tf": float(np.mean(picks_tf)),
            "val_oracle": float(np.mean(best)), "detections": len(picks)}


def main(conf: str | dict | None, models_dir: str | Path, out: str | Path, overwrite: bool = False, *,
         camera: str | Path | None = None, resume: bool = False, log: Callable[[str], None] = print,
         progress: bool = True) -> dict:
    """Onboard a scorer for the objects of ``models_dir`` (BOP models folder, mm) and export it to
    ``out`` (.onnx). camera: a BOP camera.json whose intrinsics and image size the training images
    use (default: the ``camera.json`` of the models folder's dataset, else 640 x 480, f = 572 px)."""
    import torch

    from ..io import bop
    from ..objects import ObjectDatabase
    from ..singleview.estimate_stage import ensure_templates
    from ..singleview.scorer.model import build
    from ..singleview.training_free.verify import VerifyConf

    t_start = time.time()
    c = resolve_conf(conf)
    models_dir = Path(models_dir)
    if not (models_dir / "models_info.json").is_file():
        raise CosyError("not a BOP models folder (no models_info.json)", path=models_dir)
    out = Path(out)
    if out.suffix.lower() != ".onnx":
        raise CosyError("the scorer is exported as ONNX: give --out a file name ending in .onnx", path=out)
    run = run_folder(out)
    if out.is_file() and not overwrite and not resume:
        raise CosyError("already exists (use --overwrite to train again, --resume to continue a run)", path=out)
    cam_path = Path(camera) if camera is not None else models_dir.parent / "camera.json"
    if cam_path.is_file():
        ci = bop.read_camera(cam_path)
        K, size = ci.K, (ci.width, ci.height)
    elif camera is not None:
        raise CosyError("camera file not found", path=cam_path)
    else:
        from ..synth.scenes import camera_matrix

        K, size = camera_matrix(640, 480), (640, 480)
    db = ObjectDatabase.from_models_dir(models_dir)
    if len(db) == 0:
        raise CosyError("no objects in models_info.json", path=models_dir / "models_info.json")
    record = dict(c, models=str(models_dir.resolve()), models_info_sha1=_sha1(models_dir / "models_info.json"),
                  K=np.asarray(K).tolist(), image_size=list(size), margin=VerifyConf.margin)
    if overwrite and run.is_dir():
        import shutil

        shutil.rmtree(run)
    loop.check_run_folder(run, resume, overwrite)
    if (run / loop.CONFIG).is_file() and not resume:  # an interrupted run before its first checkpoint
        old = json.loads((run / loop.CONFIG).read_text())
        if any(old.get(k) != record.get(k) for k in record if k not in RESUMABLE):
            raise CosyError("the run folder holds data of other settings: use --overwrite to start again", path=run)
    ckpt = loop.start_run(run, record, resume=resume, overwrite=False, resumable=RESUMABLE)
    loop.write_config(run, record)

    # 1-2. templates and data
    tdir = run / "templates"
    ensure_templates(models_dir, tdir, log=log)
    n_tr, n_val = c["shards"], c["val_shards"]
    if c["backgrounds"]:  # the shard makers read them (each worker its own copy)
        from ..detection.train import photo_note
        from ..io.images import photo_files

        log(photo_note(c, len(photo_files(c["backgrounds"])), "train scorer"))
    t0 = time.time()
    write_shards(models_dir, tdir, K, size, dict(c), run / "shards", range(n_tr + n_val), workers=c["workers"],
                 progress=progress)
    t_data = time.time() - t0
    train = load_shards(run / "shards", range(n_tr))
    val = load_shards(run / "shards", range(n_tr, n_tr + n_val))
    n_hyp = len(train["target"])
    groups = _groups(train["det"])
    if len(groups) < c["batch_size"]:
        raise CosyError(f"the training shards hold only {len(groups)} detections (objects too small to see?)",
                        path=run)
    log(f"train scorer: {n_hyp} hypotheses of {len(train['obs_rgb'])} detections "
        f"(validation: {len(val['obs_rgb'])} detections); data {t_data / 60:.1f} min")

    # 3. training
    device = loop.select_device(c, log)
    torch.manual_seed(c["seed"])
    net = build(c["arch"], c["widths"], c["hidden"])
    if c["arch"] == "lite0":  # the frozen trunk's maps of every hypothesis, once
        t0 = time.time()
        batches = _MapBatches(train, ensure_maps(net, run / "shards", run / "maps", range(n_tr), progress=progress))
        val_batches = _MapBatches(val, ensure_maps(net, run / "shards", run / "maps", range(n_tr, n_tr + n_val),
                                                   progress=progress))
        log(f"train scorer: ImageNet maps of the hypotheses {(time.time() - t0) / 60:.1f} min")
    else:
        batches, val_batches = _Batches(train), _Batches(val)
    net = net.to(device)
    opt = torch.optim.AdamW([p for p in net.parameters() if p.requires_grad], lr=c["lr"],
                            weight_decay=c["weight_decay"])
    rng = np.random.default_rng([c["seed"], 1])
    step, samples, last = 0, 0, {}
    if ckpt is not None:
        net.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        step, samples, last = loop.resume_progress(ckpt, run, LOG_FIELDS)
        if ckpt["rng"].get("numpy_generator"):
            rng.bit_generator.state = ckpt["rng"]["numpy_generator"]
    bce = torch.nn.BCEWithLogitsLoss()
    state = {"val": {}}

    def train_step(s: int):
        lr = loop.learning_rate(c, s)
        for g in opt.param_groups:
            g["lr"] = lr
        pick = groups[rng.integers(0, len(groups), c["batch_size"])]  # (D, M) hypothesis indices, -1 padding
        valid = pick >= 0
        idx = pick[valid]
        flip = rng.random(len(idx)) < 0.5
        y = torch.from_numpy(train["target"][idx]).to(device)
        logit = batches.logits(net, idx, flip)
        loss_bce = bce(logit, y)
        # listwise: per detection, softmax of the logits against softmax of target / temperature
        m = torch.from_numpy(valid).to(device)
        L = torch.full(pick.shape, -1e4, device=device).masked_scatter(m, logit)
        Y = torch.full(pick.shape, -1e4, device=device).masked_scatter(m, y / c["rank_temperature"])
        loss_rank = -(torch.softmax(Y, 1) * torch.log_softmax(L, 1)).sum(1).mean()
        loss = loss_bce + c["rank_weight"] * loss_rank
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if (s + 1) % c["checkpoint_every"] == 0 or s + 1 == c["iterations"]:
            state["val"] = validate(net, val_batches)
        return lr, {"total": loss.item(), "bce": loss_bce.item(), "rank": loss_rank.item()}, {}

    def log_row(means: loop.Means):
        v = state["val"]
        return {"total": means.mean("total")}, {
            "loss_total": means.mean("total"), "loss_bce": means.mean("bce"), "loss_rank": means.mean("rank"),
            "val_pick": v.get("val_pick", float("nan")),
            "val_pick_tf": v.get("val_pick_tf", float("nan")), "val_oracle": v.get("val_oracle", float("nan")),
            "hyps_per_s": means.rate(c["batch_size"]) * n_hyp / len(groups)}

    def plot(folder: Path):
        loop.write_plot(folder, [("loss_total", "total"), ("loss_bce", "BCE"), ("loss_rank", "ranking")], "loss",
                        "scorer training")

    if step < c["iterations"]:
        loop.run_loop(run, c, record, step=step, samples=samples, loss=last, train_step=train_step, log_row=log_row,
                      checkpoint=lambda: {"model": net.state_dict(), "optimizer": opt.state_dict()},
                      rng=lambda: loop.rng_state(rng), plot=plot, log_fields=LOG_FIELDS, resume=resume,
                      unit="detections", loss_format="{:.4f}", sigterm=True, log=log, progress=progress)
    net.eval()
    v = validate(net.cpu(), val_batches)
    v = _export(net, out, record, db.obj_ids, n_tr, n_hyp, v, val_batches)
    total = time.time() - t_start
    log(f"train scorer: validation (rendered, held-out seeds), AR of the first-ranked template hypothesis "
        f"{v['val_pick']:.3f} (training-free score {v['val_pick_tf']:.3f}, best possible {v['val_oracle']:.3f}) "
        f"over {v['detections']} detections; {total / 60:.1f} min in all -> {out}")
    return {"out": str(out), "run": str(run), "validation": v, "minutes": total / 60, "data_minutes": t_data / 60,
            "hypotheses": n_hyp}


def _export(net, out: Path, record: dict, obj_ids, n_shards: int, n_hyp: int, validation: dict,
            calibration: _Batches) -> dict:
    """The ONNX file; a lite0 scorer's trunk in int8 where ``record["precision"]`` says so (runs
    recorded before the setting existed: float32), calibrated on ``calibration``'s hypotheses.
    Returns the validation of the file written (int8: measured on it with onnxruntime)."""
    from ..singleview.scorer.model import export_onnx, quantize_trunk

    card = {"crop": record["crop"], "margin": record["margin"], "obj_ids": [int(o) for o in obj_ids],
            "models_info_sha1": record["models_info_sha1"], "iterations": record["iterations"], "shards": n_shards,
            "images": n_shards * record["images_per_shard"], "hypotheses": n_hyp, "seed": record["seed"],
            "validation": validation}
    export_onnx(net.cpu(), out, card)
    if record.get("arch", "plain") == "lite0" and record.get("precision", "fp32") == "int8":
        quantize_trunk(out, _calibration_feeds(calibration))
        # the card's validation: that of the int8 network (the float32 one's kept beside it)
        from ..onnxrt import update_card
        from ..singleview.scorer.model import METADATA_KEY

        validation_fp32, validation = validation, validate_onnx(out, calibration)
        update_card(out, METADATA_KEY, validation=validation, validation_fp32=validation_fp32)
    return validation


def _calibration_feeds(batches: _Batches, detections: int = 64, per_feed: int = 8) -> list[dict]:
    """Inputs of the exported lite0 scorer (image, terms, first, ridx) for the first ``detections``
    detections of ``batches`` (all their stored hypotheses), ``per_feed`` detections per input."""
    groups = _groups(batches.d["det"])[:detections]
    feeds = []
    for i in range(0, len(groups), per_feed):
        g = groups[i:i + per_feed]
        idx = g[g >= 0]
        image, terms = batches.inputs(idx)
        _, first, ridx = np.unique(batches.d["det"][idx], return_index=True, return_inverse=True)
        feeds.append({"image": image, "terms": terms, "first": first.astype(np.int64),
                      "ridx": ridx.reshape(-1).astype(np.int64)})
    return feeds


def export(run: str | Path, out: str | Path, log: Callable[[str], None] = print, precision: str | None = None) -> Path:
    """``cosy export --run RUN``: the scorer of a run folder's checkpoint (e.g. of an interrupted
    run) to ``out``, validated on the run's validation shards. ``precision`` ("int8" | "fp32"; a
    lite0 scorer's trunk): None, the run's setting (float32 for runs recorded before it existed)."""
    run = Path(run)
    net, ck = loop.load_run(run, lambda ck: _build(ck), "cosy train scorer", "scorer checkpoint")
    record = ck["config"]
    n_tr, n_val = record["shards"], record["val_shards"]
    val = load_shards(run / "shards", range(n_tr, n_tr + n_val))
    if record.get("arch", "plain") == "lite0":
        maps = ensure_maps(net, run / "shards", run / "maps", range(n_tr, n_tr + n_val), progress=False)
        v = validate(net, _MapBatches(val, maps))
    else:
        v = validate(net, _Batches(val))
    obj_ids = json.loads(Path(record["models"], "models_info.json").read_text()).keys() \
        if Path(record["models"], "models_info.json").is_file() else []
    if precision is not None:
        record = dict(record, precision=precision)
    v = _export(net, Path(out), record, sorted(int(o) for o in obj_ids), n_tr, -1, v, _Batches(val))
    log(f"exported the scorer of step {ck['step']} (validation AR of the first-ranked hypothesis {v['val_pick']:.3f}, "
        f"training-free {v['val_pick_tf']:.3f}) -> {out}")
    return Path(out)


def _build(ck: dict):
    from ..singleview.scorer.model import build

    c = ck["config"]
    net = build(c.get("arch", "plain"), c["widths"], c["hidden"], pretrained=False)
    net.load_state_dict(ck["model"])
    return net


def _groups(det: np.ndarray) -> np.ndarray:
    """(G, M) int64: the hypothesis indices of each of the G detections of ``det`` (n,), -1 padded."""
    order = np.argsort(det, kind="stable")
    d = det[order]
    starts = np.flatnonzero(np.r_[True, d[1:] != d[:-1]])
    counts = np.diff(np.r_[starts, len(d)])
    out = np.full((len(starts), int(counts.max()) if len(counts) else 0), -1, np.int64)
    col = np.arange(len(d)) - np.repeat(starts, counts)
    out[np.repeat(np.arange(len(starts)), counts), col] = order
    return out


def _sha1(path: Path) -> str:
    from ..io.cache import file_sha1

    return file_sha1(path)
