"""Training and export of the detector (``cosy train detector``, ``cosy export`` of a detector run).

Data: on-the-fly renders of random scenes of the dataset's objects (``models/``) through its
camera (``camera.json``; default the synthetic 640 x 480 one) at the network's input size,
with domain randomisation (:mod:`cosy_cli.detection.data`). The ``split`` argument only names
the dataset the run belongs to (recorded in the config): the split's images are not used.

Each step: a batch of rendered images and their encoded targets -> :class:`CenterNet` ->
:func:`~cosy_cli.detection.model.detection_loss` (focal heatmap loss + GIoU box loss) ->
Adam. Learning rate: linear warm-up, then constant or cosine decay to 5 % at ``iterations``
(:func:`cosy_cli.training.loop.learning_rate`). An exponential moving average of the weights
(decay ``ema``) is kept and is what gets exported. Rendering runs in ``workers`` spawned worker
processes (0: in the training process). channels-last memory layout on the CPU (about 20 %
faster here).

Run folder (as for the pose networks): ``checkpoint.pt`` (model, EMA model, optimiser, step,
RNG state, config; atomic; every ``checkpoint_every`` steps, at the end and on Ctrl-C),
``config.json``, ``log.csv`` (means over ``log_every`` steps) and ``loss.png``; SIGTERM (``kill
PID`` of a background run, whose SIGINT the shell ignores) also saves a checkpoint. ``resume``
continues from the checkpoint (settings that shape the model and the data must match;
``iterations``, ``device``, ``workers``, intervals may change); without it a run folder with a
checkpoint is refused unless ``overwrite``. That machinery is shared with the pose networks'
training: :mod:`cosy_cli.training.loop`.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Callable

import numpy as np

from ..conf import merge_conf
from ..errors import CosyError
from ..io.atomic import atomic_path
from ..training import loop
from ..training.loop import CHECKPOINT, CONFIG, LOG, PLOT, RESUMABLE_CHANGES, read_log  # noqa: F401

LOG_FIELDS = ["step", "time_s", "lr", "loss_total", "loss_heat", "loss_box", "objects_per_image", "images_per_s"]
METADATA_KEY = "cosy_detector"

DEFAULT_CONF = {
    "kind": "detector",
    "input_size": [320, 240],     # (width, height) px of the network input
    "stride": 8,
    "channels": [16, 24, 48, 96, 160],
    "depth": [0, 1, 2, 2],
    "fpn": 48,
    "head": 48,
    "iterations": 100_000,
    "batch_size": 16,
    "lr": 1e-3,
    "warmup": 300,
    "schedule": "cosine",
    "ema": 0.999,
    "box_weight": 2.0,
    "max_objects": 10,
    "p_table": 0.75,
    "min_visib": 0.1,
    "seed": 0,
    "device": "cpu",
    "workers": 0,
    "checkpoint_every": 200,
    "log_every": 20,
}


def resolve_conf(conf: dict | None = None, **overrides) -> dict:
    """Defaults, then ``conf``, then the overrides that are not None; checked."""
    c = merge_conf({"default": DEFAULT_CONF}, conf or {}, overrides, default="default", what="detector training")
    if c["kind"] != "detector":
        raise CosyError(f"kind must be detector here, not {c['kind']!r}")
    c["input_size"] = [int(v) for v in c["input_size"]]
    c["channels"] = [int(v) for v in c["channels"]]
    c["depth"] = [int(v) for v in c["depth"]]
    for k in ("stride", "fpn", "head", "iterations", "batch_size", "warmup", "max_objects", "seed", "workers",
              "checkpoint_every", "log_every"):
        c[k] = int(c[k])
    for k in ("lr", "ema", "box_weight", "p_table", "min_visib"):
        c[k] = float(c[k])
    if c["schedule"] not in ("constant", "cosine"):
        raise CosyError(f"schedule must be constant or cosine, not {c['schedule']!r}")
    if c["device"] not in ("cpu", "cuda"):
        raise CosyError(f"device must be cpu or cuda, not {c['device']!r}")
    w, h = c["input_size"] if len(c["input_size"]) == 2 else (0, 0)
    if c["stride"] not in (4, 8, 16) or w < 32 or h < 32 or w % 16 or h % 16 or w % c["stride"] or h % c["stride"]:
        raise CosyError(f"--input must be WIDTHxHEIGHT, multiples of 16 px (and of the stride {c['stride']}), "
                        f"at least 32, got {c['input_size']}")
    if (c["iterations"] < 1 or c["batch_size"] < 1 or c["lr"] <= 0 or c["workers"] < 0 or c["checkpoint_every"] < 1
            or c["log_every"] < 1 or c["warmup"] < 0 or not 0 <= c["ema"] < 1 or c["max_objects"] < 1
            or not 0 <= c["p_table"] <= 1 or not 0 <= c["min_visib"] < 1):
        raise CosyError("detector training settings out of range (iterations/batch size/intervals/max objects >= 1, "
                        "lr > 0, workers >= 0, ema in [0, 1), p_table in [0, 1], min_visib in [0, 1))")
    return c


def model_config(conf: dict, obj_ids):
    from .model import DetectorConfig

    return DetectorConfig(obj_ids=list(obj_ids), input_size=tuple(conf["input_size"]), stride=conf["stride"],
                          channels=tuple(conf["channels"]), depth=tuple(conf["depth"]), fpn=conf["fpn"],
                          head=conf["head"])


def load_dataset_objects(dataset: str | Path):
    """({obj_id: trimesh mesh (mm)}, K (3x3), (width, height)) of a BOP dataset folder."""
    db, K, size = loop.load_dataset(dataset)
    meshes = {int(o.obj_id): o.mesh for o in db}
    if K is not None:
        return meshes, K, size
    from ..synth.scenes import camera_matrix

    return meshes, camera_matrix(640, 480), (640, 480)


# ---------------------------------------------------------------------------------- training
def write_plot(out: Path) -> None:
    """loss.png of a run: total, heatmap and box losses against the step (log scale)."""
    loop.write_plot(out, [("loss_total", "total"), ("loss_heat", "heatmap (focal)"), ("loss_box", "box (1 - GIoU)")],
                    "loss", f"{Path(out).name}: detector training loss")


def _to_device(t: dict, device):
    import torch

    out = {}
    for k, v in t.items():
        if k == "n_obj":
            continue
        out[k] = torch.as_tensor(np.asarray(v) if not torch.is_tensor(v) else v).to(device, non_blocking=True)
    return out


def main(conf: dict | None, dataset: str | Path, split: str, out: str | Path, overwrite: bool = False,
         resume: bool = False, log: Callable[[str], None] = print, progress: bool = True) -> dict:
    """Train (or resume) a detector in run folder ``out``; returns {"step", "samples", "loss",
    "checkpoint"}. See the module docstring."""
    import torch

    from .data import DetectionSampleGenerator, DetectionStream, batch_targets
    from .model import CenterNet, detection_loss

    conf = resolve_conf(conf)
    out = Path(out)
    loop.check_run_folder(out, resume, overwrite)

    meshes, K, image_size = load_dataset_objects(dataset)
    obj_ids = sorted(meshes)
    record = dict(conf, dataset=str(Path(dataset).resolve()), split=split, obj_ids=obj_ids,
                  camera_K=np.asarray(K).tolist(), image_size=list(image_size))
    ckpt = loop.start_run(out, record, resume=resume, overwrite=overwrite)
    device = loop.select_device(conf, log)
    mcfg = model_config(conf, obj_ids)
    model = CenterNet(mcfg)
    ema = copy.deepcopy(model)
    opt = torch.optim.Adam(model.parameters(), lr=conf["lr"])
    step, samples, last = 0, 0, {}
    if ckpt is not None:
        model.load_state_dict(ckpt["model"]["state_dict"])
        ema.load_state_dict(ckpt["ema"]["state_dict"])
        opt.load_state_dict(ckpt["optimizer"])
        step, samples, last = loop.resume_progress(ckpt, out, LOG_FIELDS)
    fmt = torch.channels_last if device.type == "cpu" else torch.contiguous_format
    model.to(device, memory_format=fmt).train()
    ema.to(device).eval()
    for p in ema.parameters():
        p.requires_grad_(False)
    loop.optimizer_to(opt, device)
    loop.write_config(out, record)

    data_seed = np.random.SeedSequence([conf["seed"], step])  # a resumed run draws new scenes
    gen_kw = dict(max_objects=conf["max_objects"], p_table=conf["p_table"], min_visib=conf["min_visib"])
    gen, it = None, None
    if conf["workers"] == 0:
        gen = DetectionSampleGenerator(meshes, K, image_size, mcfg.input_size, seed=data_seed, obj_ids=obj_ids,
                                       **gen_kw)
    else:
        from ..training.data import make_loader

        stream = DetectionStream(meshes, K, image_size, mcfg, conf["batch_size"],
                                 seed=int(data_seed.generate_state(1)[0]), **gen_kw)
        it = iter(make_loader(stream, conf["workers"], prefetch_factor=2))

    def next_batch() -> dict:
        if gen is not None:
            return batch_targets(gen.batch(conf["batch_size"]), mcfg)
        return next(it)

    decay = conf["ema"]
    ema_params = list(ema.parameters())
    model_params = list(model.parameters())

    def train_step(step: int):
        b = next_batch()
        n_obj = float(np.mean(np.asarray(b["n_obj"])))
        t = _to_device(b, device)
        x = t.pop("images").contiguous(memory_format=fmt)
        lr = loop.learning_rate(conf, step)
        for group in opt.param_groups:
            group["lr"] = lr
        heat, box = model(x)
        terms = detection_loss(heat, box, t, mcfg.stride, conf["box_weight"])
        opt.zero_grad(set_to_none=True)
        terms["total"].backward()
        opt.step()
        done = step + 1  # steps done, this one included
        with torch.no_grad():
            d = min(decay, (1 + done) / (10 + done))  # short runs: the average warms up
            torch._foreach_mul_(ema_params, d)
            torch._foreach_add_(ema_params, model_params, alpha=1 - d)
            for eb, mb in zip(ema.buffers(), model.buffers()):
                eb.copy_(mb)
        values = {k: float(terms[k].detach()) for k in ("total", "heat", "box")}
        return lr, dict(values, objects=n_obj), {}

    def log_row(means: loop.Means):
        last = means.means(("total", "heat", "box"))
        return last, {"loss_total": last["total"], "loss_heat": last["heat"], "loss_box": last["box"],
                      "objects_per_image": means.mean("objects"), "images_per_s": means.rate(conf["batch_size"])}

    def cleanup() -> None:
        nonlocal it
        if gen is not None:
            gen.close()
        it = None

    return loop.run_loop(
        out, conf, record, step=step, samples=samples, loss=last, train_step=train_step, log_row=log_row,
        checkpoint=lambda: {"model": model.checkpoint(), "ema": ema.checkpoint(), "optimizer": opt.state_dict()},
        rng=lambda: loop.rng_state(numpy=False), plot=write_plot, log_fields=LOG_FIELDS, resume=resume,
        unit="images", loss_format="{:.3f}", cleanup=cleanup, sigterm=True, log=log, progress=progress)


# ---------------------------------------------------------------------------------- export
def run_kind(run: str | Path) -> str | None:
    """The "kind" recorded in a run folder's config.json (None when it has none)."""
    p = Path(run) / CONFIG
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text()).get("kind")
    except (OSError, ValueError):
        return None


def load_run(run: str | Path, use_ema: bool = True):
    """(CenterNet in eval mode on the CPU, checkpoint dict) of a detector run folder."""
    from .model import CenterNet

    return loop.load_run(run, lambda ck: CenterNet.from_checkpoint(ck["ema" if use_ema and "ema" in ck else "model"]),
                         "cosy train detector", "detector checkpoint")


def export_onnx(net, path: str | Path, extra_metadata: dict | None = None, opset: int = 17) -> Path:
    """Write the detector ``net`` (CenterNet) as one self-contained ONNX file (atomic): input
    ``image`` (B, 3, H, W) float32 RGB in [0, 1] (dynamic batch), outputs ``peaks`` (B, C, h, w)
    and ``ltrb`` (B, 4, h, w) (see :class:`~cosy_cli.detection.model.ExportWrapper`).

    Metadata: ``cosy_detector`` (JSON: the DetectorConfig, kind "detector", plus
    ``extra_metadata``), and the plain keys ``kind``, ``obj_ids`` (JSON list), ``input_size``
    ("WxH")."""
    import warnings

    import onnx
    import torch

    from .model import ExportWrapper

    cfg = net.config
    wrapper = ExportWrapper(copy.deepcopy(net).cpu().float().eval().to(memory_format=torch.contiguous_format))
    w, h = cfg.input_size
    dummy = torch.rand(2, 3, h, w)
    path = Path(path)
    meta = dict(cfg.to_dict(), kind="detector", **(extra_metadata or {}))
    with atomic_path(path) as tmp:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(wrapper, (dummy,), str(tmp), input_names=["image"], output_names=["peaks", "ltrb"],
                              dynamic_axes={"image": {0: "batch"}, "peaks": {0: "batch"}, "ltrb": {0: "batch"}},
                              opset_version=opset, dynamo=False, external_data=False)
        m = onnx.load(str(tmp))
        for key, value in ((METADATA_KEY, json.dumps(meta)), ("kind", "detector"),
                           ("obj_ids", json.dumps(cfg.obj_ids)), ("input_size", f"{w}x{h}")):
            entry = m.metadata_props.add()
            entry.key, entry.value = key, value
        onnx.save(m, str(tmp))
    return path


def export(run: str | Path, out: str | Path, accuracy: str | None = None, log: Callable[[str], None] = print) -> Path:
    """Export a detector run (its EMA weights) to ONNX ``out`` and write the model card next to
    it (same name, .md): objects, input size, architecture, training, loss, accuracy."""
    out = Path(out)
    net, ck = load_run(run)
    c = ck["config"]
    export_onnx(net, out, {"training_steps": int(ck["step"]), "training_images": int(ck["samples"])})
    cfg = net.config
    loss = ck.get("loss") or {}
    loss_txt = (f"{loss['total']:.3f} (heatmap focal {loss['heat']:.3f}, box 1 - GIoU {loss['box']:.3f})"
                if loss else "not logged")
    n_params = sum(p.numel() for p in net.parameters())
    w, h = cfg.input_size
    ow, oh = cfg.output_size
    loop.write_model_card(out, [
        f"# {out.name}: cosy 2D object detector",
        "",
        f"- objects (category_id = BOP obj_id): {', '.join(str(o) for o in cfg.obj_ids)} (models of {c['dataset']})",
        f"- input: RGB resized to {w} x {h} px (width x height), values in [0, 1]; any image size is resized "
        "by the runner (`cosy_cli.detection.network.OnnxDetector`)",
        f"- architecture: anchor-free centre-heatmap detector (CenterNet-style): plain conv + BatchNorm + ReLU "
        f"backbone (widths {list(cfg.channels)}, extra convs per stage {list(cfg.depth)}), top-down pyramid "
        f"({cfg.fpn} channels) to stride {cfg.stride} ({ow} x {oh} cells); heads: per-class centre heatmap "
        f"(focal loss) and distances to the 4 box edges (GIoU loss); {n_params / 1e6:.2f} M parameters; "
        "decoding: 3x3 max-pool peaks (in the graph), top-K, per-class NMS",
        f"- ONNX outputs: `peaks` (B, {cfg.n_classes}, {oh}, {ow}) sigmoid scores at local maxima, "
        f"`ltrb` (B, 4, {oh}, {ow}) input pixels; opset 17, dynamic batch",
        f"- training data: on-the-fly domain-randomised renders of those models (random layouts on a table or "
        f"floating, colours, lights, backgrounds, occlusion, truncation; split '{c['split']}' names the dataset, "
        "its images were not used); boxes = visible-mask boxes, instances under "
        f"{c['min_visib']:g} visible ignored",
        f"- training: {ck['step']} steps, {ck['samples']} images, batch {c['batch_size']}, Adam lr {c['lr']:g} "
        f"({c['schedule']}, {c['warmup']} warm-up steps), EMA {c['ema']:g} (exported), seed {c['seed']}",
        f"- final training loss (last logged mean): {loss_txt}",
    ], ck, accuracy, log)
    return out


__all__ = ["DEFAULT_CONF", "resolve_conf", "main", "export", "export_onnx", "load_run", "run_kind", "read_log",
           "write_plot", "model_config", "load_dataset_objects"]
