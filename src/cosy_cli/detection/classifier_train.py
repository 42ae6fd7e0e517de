"""Training and export of the second-stage box classifier (``cosy train classifier``).

Data: the detector's on-the-fly domain-randomised scenes (:class:`~cosy_cli.detection.data.
DetectionSampleGenerator`) rendered at the dataset camera's full image size (the classifier
crops the full-resolution image at inference), with class weights and look-alike pairs shown
side by side. From each image: every visible GT box (visible fraction >= ``min_visib``; occluded
and truncated ones included), each cropped ``reuse`` times with independent box jitter (each
edge moved by N(0, ``jitter`` x box size), what a detector's box error looks like), plus
``background_per_image`` crops of random boxes that overlap no object box by IoU > 0.2 (class
"background"). Loss: cross-entropy with label smoothing 0.05, class-balanced by the sampling
weights. Adam, warm-up + cosine, EMA of the weights (exported).

Run folder and resuming: as the detector's (:mod:`cosy_cli.training.loop`): ``checkpoint.pt``
every ``checkpoint_every`` steps, on Ctrl-C and on SIGTERM; ``--resume``.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Callable

import numpy as np

from ..conf import merge_conf
from ..errors import CosyError
from ..training import loop
from .classifier import ClassifierConfig, crop_boxes

LOG_FIELDS = ["step", "time_s", "lr", "loss_total", "accuracy", "crops_per_s"]

DEFAULT_CONF = {
    "kind": "classifier",
    "crop": 112,
    "margin": 1.2,
    "arch": "detector",           # plain | detector (the detector's backbone, warm-started from init)
    "widths": [16, 24, 48, 96, 160],
    "depth": [0, 1, 2, 2],
    "init": None,                 # arch detector: an exported detector ONNX whose backbone starts the run
    "iterations": 4000,
    "batch_size": 64,
    "lr": 2e-3,
    "warmup": 100,
    "schedule": "cosine",
    "ema": 0.995,
    "jitter": 0.07,
    "reuse": 2,
    "background_per_image": 1,
    "min_visib": 0.15,
    "max_objects": 8,
    "class_weights": {"4": 1.5, "6": 2.5, "7": 2.5},
    "confusable": [[6, 7, 6], [4, 7, 2], [4, 5, 1], [1, 6, 1], [5, 7, 1], [1, 2, 1]],
    "p_pair": 0.6,
    "threads": 1,
    "seed": 0,
    "device": "cpu",
    "workers": 0,
    "checkpoint_every": 100,
    "log_every": 20,
}


def resolve_conf(conf: dict | None = None, **overrides) -> dict:
    c = merge_conf({"default": DEFAULT_CONF}, conf or {}, overrides, default="default", what="classifier training")
    try:
        for k in ("crop", "iterations", "batch_size", "warmup", "reuse", "background_per_image", "max_objects",
                  "threads", "seed", "workers", "checkpoint_every", "log_every"):
            c[k] = int(c[k])
        for k in ("margin", "lr", "ema", "jitter", "min_visib", "p_pair"):
            c[k] = float(c[k])
        c["widths"] = [int(w) for w in c["widths"]]
        c["depth"] = [int(d) for d in c["depth"]]
        c["init"] = str(c["init"]) if c["init"] else None
        c["class_weights"] = {str(int(k)): float(v) for k, v in dict(c["class_weights"] or {}).items()} or None
        c["confusable"] = [[int(r[0]), int(r[1])] + ([float(r[2])] if len(r) == 3 else []) for r in
                           (c["confusable"] or [])] or None
    except (TypeError, ValueError, IndexError) as e:
        raise CosyError(f"classifier training settings: {e}") from None
    if (c["crop"] < 16 or c["margin"] < 1 or c["iterations"] < 1 or c["batch_size"] < 2 or c["lr"] <= 0
            or c["reuse"] < 1 or c["threads"] < 1 or not 0 <= c["ema"] < 1 or c["arch"] not in ("plain", "detector")
            or len(c["widths"]) != (4 if c["arch"] == "plain" else 5)):
        raise CosyError("classifier training settings out of range (crop >= 16, margin >= 1, arch plain (4 widths) "
                        "or detector (5 widths), ...)")
    return c


def _jitter(xyxy: np.ndarray, rng: np.random.Generator, sigma: float) -> np.ndarray:
    wh = np.maximum(xyxy[:, 2:] - xyxy[:, :2], 1.0)
    d = rng.normal(0, sigma, xyxy.shape) * np.concatenate([wh, wh], 1)
    out = xyxy + d
    out[:, 2:] = np.maximum(out[:, 2:], out[:, :2] + 2.0)
    return out


def _background_boxes(rng, boxes: np.ndarray, n: int, w: int, h: int) -> np.ndarray:
    from .boxes import box_iou

    out = []
    for _ in range(20 * n):
        if len(out) >= n:
            break
        s = rng.uniform(30, 200)
        a = rng.uniform(0.6, 1.6)
        bw, bh = s * np.sqrt(a), s / np.sqrt(a)
        x, y = rng.uniform(-0.2 * bw, w - 0.8 * bw), rng.uniform(-0.2 * bh, h - 0.8 * bh)
        b = np.array([x, y, x + bw, y + bh])
        if len(boxes):
            xywh = np.concatenate([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]], 1)
            if box_iou(np.array([[x, y, bw, bh]]), xywh).max() > 0.2:
                continue
        out.append(b)
    return np.array(out).reshape(-1, 4)


class CropSampler:
    """Batches of (crops (B, S, S, 3) uint8, class indices (B,)) from rendered scenes."""

    def __init__(self, meshes, K, image_size, conf: dict, obj_ids, seed, step: int = 0):
        from .data import DetectionSampleGenerator

        self.conf = conf
        self.size = (int(image_size[0]), int(image_size[1]))
        self.obj_ids = list(obj_ids)
        self.gen = DetectionSampleGenerator(
            meshes, K, image_size, input_size=self.size, seed=seed, obj_ids=obj_ids, max_objects=conf["max_objects"],
            min_visib=conf["min_visib"],
            class_weights={int(k): v for k, v in (conf["class_weights"] or {}).items()} or None,
            confusable=conf["confusable"], p_pair=conf["p_pair"])
        self.rng = np.random.default_rng([int(conf["seed"]), 99, int(step)])  # box jitter, background boxes
        self.pool_x: list = []
        self.pool_y: list = []

    def _fill(self) -> None:
        c = self.conf
        b = self.gen.batch(4)
        C = len(self.obj_ids)
        for img, boxes, labels in zip(b["images"], b["boxes"], b["labels"]):
            for _ in range(c["reuse"]):
                if len(boxes):
                    self.pool_x.append(crop_boxes(img, _jitter(boxes, self.rng, c["jitter"]), c["crop"], c["margin"]))
                    self.pool_y.append(labels)
            bg = _background_boxes(self.rng, boxes, c["background_per_image"], *self.size)
            if len(bg):
                self.pool_x.append(crop_boxes(img, bg, c["crop"], c["margin"]))
                self.pool_y.append(np.full(len(bg), C, np.int64))

    def batch(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        while sum(len(y) for y in self.pool_y) < n:
            self._fill()
        x, y = np.concatenate(self.pool_x), np.concatenate(self.pool_y)
        perm = self.rng.permutation(len(y))
        take, rest = perm[:n], perm[n:]
        self.pool_x, self.pool_y = [x[rest]], [y[rest]]
        return x[take], y[take]

    def close(self) -> None:
        self.gen.close()


def step_of(ckpt) -> int:
    return 0 if ckpt is None else int(ckpt["step"])


def write_plot(out: Path) -> None:
    loop.write_plot(out, [("loss_total", "cross-entropy")], "loss", f"{Path(out).name}: box classifier training")


def main(conf: dict | None, dataset: str | Path, split: str, out: str | Path, overwrite: bool = False,
         resume: bool = False, log: Callable[[str], None] = print, progress: bool = True) -> dict:
    """Train (or resume) a box classifier in run folder ``out``."""
    import torch
    import torch.nn.functional as F

    from .classifier import build_network
    from .train import load_dataset_objects

    conf = resolve_conf(conf)
    out = Path(out)
    loop.check_run_folder(out, resume, overwrite)
    meshes, K, image_size = load_dataset_objects(dataset)
    obj_ids = sorted(meshes)
    record = dict(conf, dataset=str(Path(dataset).resolve()), split=split, obj_ids=obj_ids,
                  camera_K=np.asarray(K).tolist(), image_size=list(image_size))
    if conf["init"] and not resume and not Path(conf["init"]).is_file():
        raise CosyError("warm-start detector (init) not found", path=conf["init"])
    ckpt = loop.start_run(out, record, resume=resume, overwrite=overwrite,
                          resumable=loop.RESUMABLE_CHANGES | {"threads", "init"})
    device = loop.select_device(conf, log)
    torch.set_num_threads(conf["threads"])
    cfg = ClassifierConfig(obj_ids=obj_ids, crop=conf["crop"], margin=conf["margin"], widths=tuple(conf["widths"]),
                           arch=conf["arch"], depth=tuple(conf["depth"]))
    model = build_network(cfg)
    sampler = CropSampler(meshes, K, image_size, conf, obj_ids, np.random.SeedSequence([conf["seed"], step_of(ckpt)]),
                          step_of(ckpt))
    if ckpt is None and conf["init"]:
        if conf["arch"] != "detector":
            raise CosyError("init (a detector's backbone) needs arch detector")
        from .classifier import init_from_detector

        x, _ = sampler.batch(64)
        info = init_from_detector(model, conf["init"], x.transpose(0, 3, 1, 2).astype(np.float32) / 255.0)
        log(f"train classifier: backbone of {conf['init']} ({info['tensors']} tensors, {info['batchnorms']} "
            "BatchNorms recalibrated on crops)")
    ema = copy.deepcopy(model)
    opt = torch.optim.Adam(model.parameters(), lr=conf["lr"], weight_decay=1e-5)
    step, samples, last = 0, 0, {}
    if ckpt is not None:
        model.load_state_dict(ckpt["model"]["state_dict"])
        ema.load_state_dict(ckpt["ema"]["state_dict"])
        opt.load_state_dict(ckpt["optimizer"])
        step, samples, last = loop.resume_progress(ckpt, out, LOG_FIELDS)
    model.to(device).train()
    ema.to(device).eval()
    for p in ema.parameters():
        p.requires_grad_(False)
    loop.optimizer_to(opt, device)
    loop.write_config(out, record)
    ema_params, model_params = list(ema.parameters()), list(model.parameters())

    def train_step(step: int):
        x, y = sampler.batch(conf["batch_size"])
        xt = torch.from_numpy(np.ascontiguousarray(x.transpose(0, 3, 1, 2))).to(device).float().div_(255.0)
        yt = torch.from_numpy(y).to(device)
        lr = loop.learning_rate(conf, step)
        for g in opt.param_groups:
            g["lr"] = lr
        logits = model(xt)
        loss = F.cross_entropy(logits, yt, label_smoothing=0.05)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        done = step + 1
        with torch.no_grad():
            d = min(conf["ema"], (1 + done) / (10 + done))
            torch._foreach_mul_(ema_params, d)
            torch._foreach_add_(ema_params, model_params, alpha=1 - d)
            for eb, mb in zip(ema.buffers(), model.buffers()):
                eb.copy_(mb)
            acc = float((logits.argmax(1) == yt).float().mean())
        return lr, {"total": float(loss.detach()), "acc": acc}, {"acc": f"{acc:.2f}"}

    def log_row(means: loop.Means):
        m = means.means(("total", "acc"))
        return {"total": m["total"], "acc": m["acc"]}, {"loss_total": m["total"], "accuracy": m["acc"],
                                                       "crops_per_s": means.rate(conf["batch_size"])}

    return loop.run_loop(
        out, conf, record, step=step, samples=samples, loss=last, train_step=train_step, log_row=log_row,
        checkpoint=lambda: {"model": model.checkpoint(), "ema": ema.checkpoint(), "optimizer": opt.state_dict()},
        rng=lambda: loop.rng_state(numpy=False), plot=write_plot, log_fields=LOG_FIELDS, resume=resume,
        unit="crops", cleanup=sampler.close, sigterm=True, log=log, progress=progress)


def load_run(run: str | Path, use_ema: bool = True):
    """(classifier network in eval mode, checkpoint dict) of a classifier run folder."""
    from .classifier import network_from_checkpoint

    return loop.load_run(run, lambda ck: network_from_checkpoint(ck["ema" if use_ema and "ema" in ck else "model"]),
                         "cosy train classifier", "classifier checkpoint")


def export(run: str | Path, out: str | Path, accuracy: str | None = None, log: Callable[[str], None] = print) -> Path:
    """Export a classifier run's EMA weights to ONNX ``out`` and write a short model card next to
    it (the shipped card, assets/classifier.md, is written by hand with the measured figures)."""
    from .classifier import export_onnx

    net, ck = load_run(run)
    export_onnx(net, out, {"training_steps": int(ck["step"]), "training_crops": int(ck["samples"])})
    c, cfg = ck["config"], net.config
    n = sum(p.numel() for p in net.parameters())
    return loop.write_model_card(out, [
        f"# {Path(out).name}: cosy second-stage box classifier",
        "",
        f"- classes: objects {', '.join(map(str, cfg.obj_ids))} (models of `{Path(c['dataset']).name}`) + background",
        f"- input: {cfg.crop} x {cfg.crop} px RGB crop, square of {cfg.margin:g} x the box's longer side",
        (f"- network: 8 conv + BN + ReLU (widths {list(cfg.widths)}), global average pool, linear; "
         if cfg.arch == "plain" else
         f"- network: the detector's backbone (conv + BN + ReLU, widths {list(cfg.widths)}, extra convs per stage "
         f"{list(cfg.depth)}), average and max over the cells of the last two stages, linear; ")
        + f"{n / 1e3:.0f} k parameters",
        f"- training: {ck['step']} steps, {ck['samples']} crops, batch {c['batch_size']}, Adam lr {c['lr']:g}, "
        f"EMA {c['ema']:g}, seed {c['seed']}",
    ], ck, accuracy, log)


__all__ = ["DEFAULT_CONF", "resolve_conf", "main", "load_run", "export", "CropSampler"]
