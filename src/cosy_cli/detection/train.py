"""Training and export of the detector (``cosy train detector``, ``cosy export`` of a detector run).

Data: on-the-fly renders of random scenes of the dataset's objects (``models/``) through its
camera (``camera.json``; default the synthetic 640 x 480 one) at the network's input size,
with domain randomisation (:mod:`cosy_cli.detection.data`). The ``split`` argument only names
the dataset the run belongs to (recorded in the config): the split's images are not used.

Each step: a batch of rendered images and their encoded targets -> :class:`CenterNet` ->
:func:`~cosy_cli.detection.model.detection_loss` (focal heatmap loss + GIoU box loss) ->
Adam. Learning rate: linear warm-up, then constant or cosine decay to 5 % at ``iterations``
(:func:`cosy_cli.training.train.learning_rate`). An exponential moving average of the weights
(decay ``ema``) is kept and is what gets exported. Rendering runs in ``workers`` spawned worker
processes (0: in the training process). channels-last memory layout on the CPU (about 20 %
faster here).

Run folder (as for the pose networks): ``checkpoint.pt`` (model, EMA model, optimiser, step,
RNG state, config; atomic; every ``checkpoint_every`` steps, at the end and on Ctrl-C),
``config.json``, ``log.csv`` (means over ``log_every`` steps) and ``loss.png``; SIGTERM (``kill
PID`` of a background run, whose SIGINT the shell ignores) also saves a checkpoint. ``resume``
continues from the checkpoint (settings that shape the model and the data must match;
``iterations``, ``device``, ``workers``, intervals may change); without it a run folder with a
checkpoint is refused unless ``overwrite``.
"""

from __future__ import annotations

import copy
import json
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np

from ..conf import merge_conf
from ..errors import CosyError
from ..io.atomic import atomic_path, write_json, write_text

CHECKPOINT = "checkpoint.pt"
CONFIG = "config.json"
LOG = "log.csv"
PLOT = "loss.png"
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
RESUMABLE_CHANGES = {"iterations", "device", "workers", "checkpoint_every", "log_every"}


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
    from ..io import bop
    from ..objects import ObjectDatabase

    dataset = Path(dataset)
    if not dataset.is_dir():
        raise CosyError("dataset folder not found", path=dataset)
    db = ObjectDatabase.from_models_dir(dataset / "models")
    if len(db) == 0:
        raise CosyError("no objects in models_info.json", path=dataset / "models" / "models_info.json")
    meshes = {int(o.obj_id): o.mesh for o in db}
    cam = dataset / "camera.json"
    if cam.is_file():
        ci = bop.read_camera(cam)
        return meshes, ci.K, (ci.width, ci.height)
    from ..synth.scenes import camera_matrix

    return meshes, camera_matrix(640, 480), (640, 480)


# ---------------------------------------------------------------------------------- log
def read_log(path: Path) -> list[dict]:
    """Rows of a detector run's log.csv as dicts of numbers ([] if none)."""
    from ..training.train import read_log as _read

    return _read(path)


def _fmt(v) -> str:
    return str(v) if isinstance(v, (int, np.integer)) else f"{v:.6g}"


def _truncate_log(path: Path, step: int) -> None:
    rows = [r for r in read_log(path) if r["step"] <= step]
    lines = [",".join(LOG_FIELDS)] + [",".join(_fmt(r[k]) for k in LOG_FIELDS) for r in rows]
    write_text(path, "\n".join(lines) + "\n")


def write_plot(out: Path) -> None:
    """loss.png of a run: total, heatmap and box losses against the step (log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = read_log(Path(out) / LOG)
    if not rows:
        return
    steps = np.array([r["step"] for r in rows])
    fig, ax = plt.subplots(figsize=(7, 4), dpi=100)
    for key, label in (("loss_total", "total"), ("loss_heat", "heatmap (focal)"), ("loss_box", "box (1 - GIoU)")):
        ax.plot(steps, [r[key] for r in rows], label=label, lw=1.5 if key == "loss_total" else 1)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_title(f"{Path(out).name}: detector training loss")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    with atomic_path(Path(out) / PLOT) as tmp:
        fig.savefig(tmp)
    plt.close(fig)


# ---------------------------------------------------------------------------------- training
def _stop_on_sigterm() -> Callable[[], None]:
    """Make SIGTERM raise KeyboardInterrupt (so ``kill PID`` of a background run saves a
    checkpoint like Ctrl-C: shells start background jobs with SIGINT ignored). Returns the
    function that restores the previous handler. No-op outside the main thread."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return lambda: None

    def handler(signum, frame):
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, handler)
    return lambda: signal.signal(signal.SIGTERM, old)


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
    from tqdm import tqdm

    from ..training.train import learning_rate
    from .data import DetectionSampleGenerator, DetectionStream, batch_targets
    from .model import CenterNet, detection_loss

    conf = resolve_conf(conf)
    out = Path(out)
    ckpt_path = out / CHECKPOINT
    if ckpt_path.exists() and not resume and not overwrite:
        raise CosyError("run folder already holds a checkpoint: continue it with --resume or start again with "
                        "--overwrite", path=out)
    if resume and not ckpt_path.is_file():
        raise CosyError("nothing to resume: no checkpoint.pt in the run folder", path=out)

    meshes, K, image_size = load_dataset_objects(dataset)
    obj_ids = sorted(meshes)
    record = dict(conf, dataset=str(Path(dataset).resolve()), split=split, obj_ids=obj_ids,
                  camera_K=np.asarray(K).tolist(), image_size=list(image_size))

    ckpt = None
    if resume:
        try:
            ckpt = torch.load(ckpt_path, map_location="cpu", weights_only=False)
        except Exception as e:
            raise CosyError(f"unreadable checkpoint: {e}", path=ckpt_path) from None
        old = ckpt["config"]
        diff = sorted(k for k in set(old) | set(record) if k not in RESUMABLE_CHANGES and old.get(k) != record.get(k))
        if diff:
            detail = "; ".join(f"{k}: {old.get(k)!r} in the run, {record.get(k)!r} now" for k in diff)
            raise CosyError(f"cannot resume with different settings ({detail})", path=ckpt_path)
    elif overwrite:
        for name in (CHECKPOINT, LOG, PLOT, CONFIG):
            (out / name).unlink(missing_ok=True)

    torch.set_num_threads(os.cpu_count() or 1)
    want_cuda = conf["device"] == "cuda"
    if want_cuda and not torch.cuda.is_available():
        log("warning: --device cuda but no CUDA device is available: training on the CPU")
    device = torch.device("cuda" if want_cuda and torch.cuda.is_available() else "cpu")
    torch.manual_seed(conf["seed"])
    mcfg = model_config(conf, obj_ids)
    model = CenterNet(mcfg)
    ema = copy.deepcopy(model)
    opt = torch.optim.Adam(model.parameters(), lr=conf["lr"])
    step, samples, last = 0, 0, {}
    if ckpt is not None:
        model.load_state_dict(ckpt["model"]["state_dict"])
        ema.load_state_dict(ckpt["ema"]["state_dict"])
        opt.load_state_dict(ckpt["optimizer"])
        step, samples, last = int(ckpt["step"]), int(ckpt["samples"]), dict(ckpt.get("loss", {}))
        torch.set_rng_state(ckpt["rng"]["torch"])
        _truncate_log(out / LOG, step)
    fmt = torch.channels_last if device.type == "cpu" else torch.contiguous_format
    model.to(device, memory_format=fmt).train()
    ema.to(device).eval()
    for p in ema.parameters():
        p.requires_grad_(False)
    for group in opt.param_groups:
        for p in group["params"]:
            for k, v in opt.state.get(p, {}).items():
                if torch.is_tensor(v) and k != "step":
                    opt.state[p][k] = v.to(device)

    out.mkdir(parents=True, exist_ok=True)
    write_json(out / CONFIG, record)

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

    def save() -> None:
        ck = {"model": model.checkpoint(), "ema": ema.checkpoint(), "optimizer": opt.state_dict(), "step": step,
              "samples": samples, "loss": last, "config": record, "rng": {"torch": torch.get_rng_state()},
              "saved": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
        with atomic_path(ckpt_path) as tmp:
            torch.save(ck, tmp)
        write_plot(out)

    acc = {"total": 0.0, "heat": 0.0, "box": 0.0, "objects": 0.0}
    n_acc, t_acc, t_run0 = 0, 0.0, time.time()
    old_rows = read_log(out / LOG) if resume else []
    t_offset = old_rows[-1]["time_s"] if old_rows else 0.0
    new_log = not (out / LOG).is_file()
    logf = open(out / LOG, "a", newline="")
    if new_log:
        logf.write(",".join(LOG_FIELDS) + "\n")

    def flush_log(lr: float) -> None:
        nonlocal acc, n_acc, t_acc, last
        if n_acc == 0:
            return
        last = {k: acc[k] / n_acc for k in ("total", "heat", "box")}
        row = {"step": step, "time_s": t_offset + time.time() - t_run0, "lr": lr, "loss_total": last["total"],
               "loss_heat": last["heat"], "loss_box": last["box"], "objects_per_image": acc["objects"] / n_acc,
               "images_per_s": n_acc * conf["batch_size"] / max(t_acc, 1e-9)}
        logf.write(",".join(_fmt(row[k]) for k in LOG_FIELDS) + "\n")
        logf.flush()
        acc = {k: 0.0 for k in acc}
        n_acc, t_acc = 0, 0.0

    lr = learning_rate(conf, step)
    decay = conf["ema"]
    restore_term = _stop_on_sigterm()
    ema_params = list(ema.parameters())
    model_params = list(model.parameters())
    bar = tqdm(total=conf["iterations"], initial=min(step, conf["iterations"]), desc="train detector", unit="step",
               disable=not progress, dynamic_ncols=True)
    try:
        while step < conf["iterations"]:
            t0 = time.time()
            b = next_batch()
            n_obj = float(np.mean(np.asarray(b["n_obj"])))
            t = _to_device(b, device)
            x = t.pop("images").contiguous(memory_format=fmt)
            lr = learning_rate(conf, step)
            for group in opt.param_groups:
                group["lr"] = lr
            heat, box = model(x)
            terms = detection_loss(heat, box, t, mcfg.stride, conf["box_weight"])
            opt.zero_grad(set_to_none=True)
            terms["total"].backward()
            opt.step()
            step += 1
            samples += conf["batch_size"]
            with torch.no_grad():
                d = min(decay, (1 + step) / (10 + step))  # short runs: the average warms up
                torch._foreach_mul_(ema_params, d)
                torch._foreach_add_(ema_params, model_params, alpha=1 - d)
                for eb, mb in zip(ema.buffers(), model.buffers()):
                    eb.copy_(mb)
            for k in ("total", "heat", "box"):
                acc[k] += float(terms[k].detach())
            acc["objects"] += n_obj
            n_acc += 1
            t_acc += time.time() - t0
            bar.update(1)
            bar.set_postfix(loss=f"{acc['total'] / n_acc:.3f}", lr=f"{lr:.1e}")
            if n_acc >= conf["log_every"] or step == conf["iterations"] or step % conf["checkpoint_every"] == 0:
                flush_log(lr)
            if step % conf["checkpoint_every"] == 0 and step < conf["iterations"]:
                save()
    except KeyboardInterrupt:
        flush_log(lr)
        logf.close()
        save()
        log(f"interrupted: checkpoint saved at step {step} in {ckpt_path} (continue with --resume)")
        raise
    finally:
        bar.close()
        restore_term()
        if gen is not None:
            gen.close()
        it = None
    logf.close()
    save()
    log(f"trained detector to step {step} ({samples} images); checkpoint: {ckpt_path}")
    return {"step": step, "samples": samples, "loss": last, "checkpoint": ckpt_path}


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
    import torch

    from .model import CenterNet

    path = Path(run) / CHECKPOINT
    if not Path(run).is_dir():
        raise CosyError("run folder not found", path=run)
    if not path.is_file():
        raise CosyError("no checkpoint.pt in the run folder (train one with `cosy train detector`)", path=run)
    try:
        ck = torch.load(path, map_location="cpu", weights_only=False)
        net = CenterNet.from_checkpoint(ck["ema" if use_ema and "ema" in ck else "model"])
    except Exception as e:
        raise CosyError(f"unreadable detector checkpoint: {e}", path=path) from None
    return net.eval(), ck


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
    card = "\n".join([
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
        f"- checkpoint saved: {ck.get('saved', 'unknown')}; exported: "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}",
        f"- measured accuracy: {accuracy or 'not measured'}",
        "",
    ])
    write_text(out.with_suffix(".md"), card)
    log(f"exported {out} and {out.with_suffix('.md')}")
    return out


__all__ = ["DEFAULT_CONF", "resolve_conf", "main", "export", "export_onnx", "load_run", "run_kind", "read_log",
           "write_plot", "model_config", "load_dataset_objects"]
