"""The training loop of the render-and-compare networks (``cosy train {coarse,refiner}``).

Data: the objects of the dataset's ``models/`` (:class:`~cosy_cli.objects.ObjectDatabase`) rendered
on the fly with domain randomisation (:class:`~cosy_cli.training.data.SampleGenerator`) through the
dataset's camera (``camera.json`` if present). The ``split`` argument only says which dataset this
run belongs to (it is recorded in the config): the images of the split are *not* used.

Each step: a generator batch -> :func:`~cosy_cli.singleview.model.prepare_inputs` -> PoseNet ->
:func:`~cosy_cli.singleview.losses.disentangled_loss` (mm, on ``n_points`` model points per object,
min over the symmetries) -> mean -> backward -> Adam. Learning rate: linear warm-up over
``warmup`` steps, then constant (``schedule="constant"``) or cosine decay to 5 % at ``iterations``
(``"cosine"``). fp32 (bf16 autocast measured 10x slower on the 2-core CPU); torch threads = cores.

Curriculum (refiner only): the input-pose perturbation is scaled by
``c(step) = c0 + (1 - c0) * min(1, step / (curriculum_frac * iterations))`` with c0 = 0.3 and
curriculum_frac = 0.5 (small perturbations first, full ones from half-way on), quantised to steps
of 0.05 (worker processes are restarted when it changes, as their generator's curriculum is fixed).

Run folder: ``checkpoint.pt`` (model + optimiser + step + RNG states + config, atomic, every
``checkpoint_every`` steps, at the end and on KeyboardInterrupt), ``config.json``, ``log.csv``
(appended every ``log_every`` steps: means over those steps) and ``loss.png`` (updated at each
checkpoint). ``resume=True`` continues from the checkpoint (the settings that shape the model and
the data must match, ``iterations`` may grow); without it a run folder with a checkpoint is refused
unless ``overwrite``.
"""

from __future__ import annotations

import csv
import math
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
LOG_FIELDS = ["step", "time_s", "lr", "loss_total", "loss_xy", "loss_z", "loss_rot", "samples_per_s"]

DEFAULT_CONF = {
    "kind": "refiner",
    "backbone": "efficientnet-b0",
    "crop_size": [128, 96],       # (width, height) px
    "n_inputs": 6,
    "iterations": 100_000,
    "batch_size": 32,
    "lr": 3e-4,
    "warmup": 500,                # steps of linear warm-up
    "schedule": "constant",       # or "cosine"
    "curriculum_start": 0.3,
    "curriculum_frac": 0.5,
    "n_points": 300,              # model points per object in the loss
    "seed": 0,
    "device": "cpu",
    "workers": 0,
    "checkpoint_every": 200,
    "log_every": 10,
}
# Settings that may differ between a run and its resumption.
RESUMABLE_CHANGES = {"iterations", "device", "workers", "checkpoint_every", "log_every"}


def resolve_conf(conf: dict | None = None, **overrides) -> dict:
    """Defaults, then ``conf``, then the overrides that are not None; checked."""
    c = merge_conf({"default": DEFAULT_CONF}, conf or {}, overrides, default="default", what="training")
    if c["kind"] not in ("coarse", "refiner"):
        raise CosyError(f"kind must be coarse or refiner, not {c['kind']!r}")
    c["crop_size"] = [int(v) for v in c["crop_size"]]
    for k in ("iterations", "batch_size", "warmup", "n_points", "seed", "workers", "checkpoint_every", "log_every",
              "n_inputs"):
        c[k] = int(c[k])
    for k in ("lr", "curriculum_start", "curriculum_frac"):
        c[k] = float(c[k])
    if c["schedule"] not in ("constant", "cosine"):
        raise CosyError(f"schedule must be constant or cosine, not {c['schedule']!r}")
    if (len(c["crop_size"]) != 2 or min(c["crop_size"]) < 32 or c["iterations"] < 1 or c["batch_size"] < 1
            or c["lr"] <= 0 or c["n_points"] < 3 or c["workers"] < 0 or c["checkpoint_every"] < 1
            or c["log_every"] < 1 or c["warmup"] < 0 or not 0 <= c["curriculum_start"] <= 1
            or c["curriculum_frac"] <= 0):
        raise CosyError("training settings out of range (crop >= 32 px per side, iterations/batch size/points/"
                        "checkpoint and log intervals >= 1, lr > 0, workers >= 0, curriculum start in [0, 1])")
    return c


def learning_rate(conf: dict, step: int) -> float:
    """LR of step ``step`` (0-based): linear warm-up, then constant or cosine to 5 % at ``iterations``."""
    lr = conf["lr"]
    w = conf["warmup"]
    if w > 0 and step < w:
        return lr * (step + 1) / w
    if conf["schedule"] == "cosine":
        span = max(1, conf["iterations"] - w)
        t = min(1.0, (step - w) / span)
        return lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * t)))
    return lr


def curriculum(conf: dict, step: int) -> float:
    """Perturbation scale of the refiner's input poses at ``step``, quantised to 0.05."""
    c0 = conf["curriculum_start"]
    t = min(1.0, step / max(1.0, conf["curriculum_frac"] * conf["iterations"]))
    return round((c0 + (1 - c0) * t) * 20) / 20


def _load_objects(dataset: Path, n_points: int, seed: int):
    from ..io import bop
    from ..objects import ObjectDatabase

    dataset = Path(dataset)
    if not dataset.is_dir():
        raise CosyError("dataset folder not found", path=dataset)
    db = ObjectDatabase.from_models_dir(dataset / "models", n_points=n_points, seed=seed)
    if len(db) == 0:
        raise CosyError("no objects in models_info.json", path=dataset / "models" / "models_info.json")
    cam = dataset / "camera.json"
    K = size = None
    if cam.is_file():
        ci = bop.read_camera(cam)
        K, size = ci.K, (ci.width, ci.height)
    return db, K, size


def _write_plot(out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = read_log(out / LOG)
    if not rows:
        return
    steps = np.array([r["step"] for r in rows])
    fig, ax = plt.subplots(figsize=(7, 4), dpi=100)
    for key, label in (("loss_total", "total"), ("loss_xy", "image-plane xy"), ("loss_z", "depth z"),
                       ("loss_rot", "rotation")):
        ax.plot(steps, [r[key] for r in rows], label=label, lw=1.5 if key == "loss_total" else 1)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("disentangled symmetric L1 loss (mm)")
    ax.set_title(f"{out.name}: training loss")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    with atomic_path(out / PLOT) as tmp:
        fig.savefig(tmp)
    plt.close(fig)


def read_log(path: Path) -> list[dict]:
    """Rows of a run's log.csv as dicts of numbers ([] if there is none)."""
    path = Path(path)
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        return [{k: (int(v) if k == "step" else float(v)) for k, v in r.items()} for r in csv.DictReader(f)]


def _truncate_log(path: Path, step: int) -> None:
    """Drop log rows after ``step`` (logged after the last checkpoint of an interrupted run)."""
    rows = [r for r in read_log(path) if r["step"] <= step]
    lines = [",".join(LOG_FIELDS)] + [",".join(_fmt(r[k]) for k in LOG_FIELDS) for r in rows]
    write_text(path, "\n".join(lines) + "\n")


def _fmt(v) -> str:
    return str(v) if isinstance(v, int) else f"{v:.6g}"


def _rng_state(gen) -> dict:
    import torch

    st = {"torch": torch.get_rng_state(), "numpy_generator": None}
    if gen is not None:
        st["numpy_generator"] = gen.rng.bit_generator.state
    return st


def main(conf: dict | None, dataset: str | Path, split: str, out: str | Path, overwrite: bool = False,
         resume: bool = False, log: Callable[[str], None] = print, progress: bool = True) -> dict:
    """Train (or resume) a PoseNet in run folder ``out``; returns a summary dict
    {"step", "samples", "loss" (last logged means), "checkpoint"}. See the module docstring."""
    import torch
    from tqdm import tqdm

    from ..singleview.losses import disentangled_loss, pad_symmetries
    from ..singleview.model import PoseNet, prepare_inputs
    from .data import SampleGenerator, TrainingStream, make_loader

    conf = resolve_conf(conf)
    out = Path(out)
    ckpt_path = out / CHECKPOINT
    if ckpt_path.exists() and not resume and not overwrite:
        raise CosyError("run folder already holds a checkpoint: continue it with --resume or start again with "
                        "--overwrite", path=out)
    if resume and not ckpt_path.is_file():
        raise CosyError("nothing to resume: no checkpoint.pt in the run folder", path=out)

    db, K, image_size = _load_objects(Path(dataset), conf["n_points"], conf["seed"])
    obj_ids = [int(o) for o in db.obj_ids]
    record = dict(conf, dataset=str(Path(dataset).resolve()), split=split, obj_ids=obj_ids)

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

    w, h = conf["crop_size"]
    model = PoseNet(conf["kind"], conf["backbone"], conf["n_inputs"], (w, h))
    if device.type == "cuda":
        model.set_export_mode(False)  # memory-efficient Swish
    opt = torch.optim.Adam(model.parameters(), lr=conf["lr"])
    step, samples, last = 0, 0, {}
    if ckpt is not None:
        model.load_state_dict(ckpt["model"]["state_dict"])
        model.to(device)
        opt.load_state_dict(ckpt["optimizer"])
        step, samples, last = int(ckpt["step"]), int(ckpt["samples"]), dict(ckpt.get("loss", {}))
        torch.set_rng_state(ckpt["rng"]["torch"])
        _truncate_log(out / LOG, step)
    model.to(device).train()
    for group in opt.param_groups:  # optimiser state tensors follow the model
        for p in group["params"]:
            for k, v in opt.state.get(p, {}).items():
                if torch.is_tensor(v) and k != "step":
                    opt.state[p][k] = v.to(device)

    out.mkdir(parents=True, exist_ok=True)
    write_json(out / CONFIG, record)

    points = torch.as_tensor(np.stack([o.points for o in db]), dtype=torch.float32, device=device)  # (n_obj, P, 3)
    syms = pad_symmetries([o.symmetries for o in db]).to(device)  # (n_obj, S, 4, 4)

    gen_kw = dict(kind=conf["kind"], crop_size=(w, h), K=K, image_size=image_size)
    data_seed = np.random.SeedSequence([conf["seed"], step])  # a resumed run draws new samples
    gen, loader, it, loader_c = None, None, None, None

    def next_batch(c: float) -> dict:
        nonlocal gen, loader, it, loader_c
        if conf["workers"] == 0:
            if gen is None:
                gen = SampleGenerator(db, seed=data_seed, **gen_kw)
                if ckpt is not None and ckpt["rng"].get("numpy_generator") is not None:
                    gen.rng.bit_generator.state = ckpt["rng"]["numpy_generator"]
            gen.curriculum = c
            return gen.batch(conf["batch_size"])
        if loader is None or loader_c != c:
            it = loader = None  # ends the old workers
            stream = TrainingStream(db, conf["batch_size"], seed=int(data_seed.generate_state(1)[0]) + step,
                                    curriculum=c, **gen_kw)
            loader, loader_c = make_loader(stream, conf["workers"]), c
            it = iter(loader)
        return {k: (v.numpy() if torch.is_tensor(v) else v) for k, v in next(it).items()}

    def save() -> None:
        ck = {"model": model.checkpoint(), "optimizer": opt.state_dict(), "step": step, "samples": samples,
              "loss": last, "config": record, "rng": _rng_state(gen),
              "saved": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
        with atomic_path(ckpt_path) as tmp:
            torch.save(ck, tmp)
        _write_plot(out)

    acc = {k: 0.0 for k in ("total", "xy", "z", "rot")}
    n_acc, t_acc, t_run0 = 0, 0.0, time.time()
    t_offset = read_log(out / LOG)[-1]["time_s"] if resume and read_log(out / LOG) else 0.0
    new_log = not (out / LOG).is_file()
    logf = open(out / LOG, "a", newline="")
    if new_log:
        logf.write(",".join(LOG_FIELDS) + "\n")
    def flush_log(lr: float) -> None:
        """One log row: means of the steps since the last row."""
        nonlocal acc, n_acc, t_acc, last
        if n_acc == 0:
            return
        last = {k: acc[k] / n_acc for k in acc}
        row = {"step": step, "time_s": t_offset + time.time() - t_run0, "lr": lr,
               "loss_total": last["total"], "loss_xy": last["xy"], "loss_z": last["z"],
               "loss_rot": last["rot"], "samples_per_s": n_acc * conf["batch_size"] / max(t_acc, 1e-9)}
        logf.write(",".join(_fmt(row[k]) for k in LOG_FIELDS) + "\n")
        logf.flush()
        acc = {k: 0.0 for k in acc}
        n_acc, t_acc = 0, 0.0

    lr = learning_rate(conf, step)
    bar = tqdm(total=conf["iterations"], initial=min(step, conf["iterations"]), desc=f"train {conf['kind']}",
               unit="step", disable=not progress, dynamic_ncols=True)
    try:
        while step < conf["iterations"]:
            t0 = time.time()
            c = curriculum(conf, step) if conf["kind"] == "refiner" else 1.0
            b = next_batch(c)
            lr = learning_rate(conf, step)
            for group in opt.param_groups:
                group["lr"] = lr
            x = torch.from_numpy(prepare_inputs(b["observed"], b["rendered"],
                                                b["rendered_mask"] if conf["n_inputs"] == 7 else None)).to(device)
            oi = torch.as_tensor(b["obj_index"], dtype=torch.long, device=device)
            f32 = (lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32, device=device))
            pred = model(x)
            terms = disentangled_loss(pred, f32(b["T_input"]), f32(b["T_gt"]), f32(b["K_crop"]), points[oi], syms[oi])
            loss = terms["total"].mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            step += 1
            samples += conf["batch_size"]
            for k in acc:
                acc[k] += float(terms[k].detach().mean())
            n_acc += 1
            t_acc += time.time() - t0
            bar.update(1)
            bar.set_postfix(loss=f"{acc['total'] / n_acc:.1f}mm", lr=f"{lr:.1e}", c=f"{c:.2f}")
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
        if gen is not None:
            gen.close()
        loader = it = None
    logf.close()
    save()
    log(f"trained {conf['kind']} to step {step} ({samples} samples); checkpoint: {ckpt_path}")
    return {"step": step, "samples": samples, "loss": last, "checkpoint": ckpt_path}


def load_run(run: str | Path) -> tuple[object, dict]:
    """(PoseNet in eval mode on the CPU, checkpoint dict) of run folder ``run``."""
    import torch

    from ..singleview.model import PoseNet

    path = Path(run) / CHECKPOINT
    if not Path(run).is_dir():
        raise CosyError("run folder not found", path=run)
    if not path.is_file():
        raise CosyError("no checkpoint.pt in the run folder (train one with `cosy train`)", path=run)
    try:
        ck = torch.load(path, map_location="cpu", weights_only=False)
        net = PoseNet.from_checkpoint(ck["model"])
    except Exception as e:
        raise CosyError(f"unreadable checkpoint: {e}", path=path) from None
    return net.eval(), ck


def export(run: str | Path, out: str | Path, accuracy: str | None = None, log: Callable[[str], None] = print) -> Path:
    """Export the run's network to ONNX ``out`` and write the model card ``out`` with suffix .md
    (objects, crop size, backbone, training steps and samples, final loss, date, accuracy)."""
    from ..singleview.onnx import export_onnx

    out = Path(out)
    net, ck = load_run(run)
    export_onnx(net, out)
    c = ck["config"]
    loss = ck.get("loss") or {}
    loss_txt = (f"{loss['total']:.2f} mm (xy {loss['xy']:.2f}, z {loss['z']:.2f}, rotation {loss['rot']:.2f})"
                if loss else "not logged")
    w, h = net.config.crop_size
    card = "\n".join([
        f"# {out.name}: CosyPose {c['kind']} network",
        "",
        f"- kind: {c['kind']} (input: observed + rendered RGB crops{', + rendered mask' if c['n_inputs'] == 7 else ''}, "
        f"{net.config.n_inputs} channels in [0, 1]; output: 9-vector pose update)",
        f"- backbone: {c['backbone']}",
        f"- crop size: {w} x {h} px (width x height)",
        f"- objects: {', '.join(str(o) for o in c['obj_ids'])} (models of {c['dataset']})",
        f"- training data: on-the-fly domain-randomised renders of those models (split '{c['split']}' "
        "names the dataset; its images were not used)",
        f"- training: {ck['step']} steps, {ck['samples']} samples, batch {c['batch_size']}, Adam lr {c['lr']:g} "
        f"({c['schedule']}, {c['warmup']} warm-up steps), seed {c['seed']}",
        f"- final training loss (disentangled symmetric L1, last logged mean): {loss_txt}",
        f"- checkpoint saved: {ck.get('saved', 'unknown')}; exported: "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}",
        f"- measured accuracy: {accuracy or 'not measured'}",
        "",
    ])
    write_text(out.with_suffix(".md"), card)
    log(f"exported {out} and {out.with_suffix('.md')}")
    return out


__all__ = ["DEFAULT_CONF", "resolve_conf", "learning_rate", "curriculum", "main", "export", "load_run", "read_log"]
