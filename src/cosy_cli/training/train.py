"""The training loop of the render-and-compare networks (``cosy train {coarse,refiner}``).

Data: the objects of the dataset's ``models/`` (:class:`~cosy_cli.objects.ObjectDatabase`) rendered
on the fly with domain randomisation (:class:`~cosy_cli.training.data.SampleGenerator`) through the
dataset's camera (``camera.json`` if present). The ``split`` argument only says which dataset this
run belongs to (it is recorded in the config): the images of the split are *not* used.

Each step: a generator batch -> :func:`~cosy_cli.singleview.networks.model.prepare_inputs` -> PoseNet ->
:func:`~cosy_cli.singleview.networks.losses.disentangled_loss` (mm, on ``n_points`` model points per object,
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
unless ``overwrite``. The run folder, log and loop machinery is shared with the detector's training:
:mod:`cosy_cli.training.loop`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from ..conf import merge_conf
from ..errors import CosyError
from . import loop
from .loop import CHECKPOINT, CONFIG, LOG, PLOT, RESUMABLE_CHANGES, learning_rate, read_log  # noqa: F401

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


def curriculum(conf: dict, step: int) -> float:
    """Perturbation scale of the refiner's input poses at ``step``, quantised to 0.05."""
    c0 = conf["curriculum_start"]
    t = min(1.0, step / max(1.0, conf["curriculum_frac"] * conf["iterations"]))
    return round((c0 + (1 - c0) * t) * 20) / 20


def _load_objects(dataset: Path, n_points: int, seed: int):
    """(ObjectDatabase, K or None, (width, height) or None) of a dataset (see :func:`loop.load_dataset`)."""
    return loop.load_dataset(dataset, n_points=n_points, seed=seed)


def _write_plot(out: Path) -> None:
    loop.write_plot(out, [("loss_total", "total"), ("loss_xy", "image-plane xy"), ("loss_z", "depth z"),
                          ("loss_rot", "rotation")], "disentangled symmetric L1 loss (mm)",
                    f"{Path(out).name}: training loss")


def main(conf: dict | None, dataset: str | Path, split: str, out: str | Path, overwrite: bool = False,
         resume: bool = False, log: Callable[[str], None] = print, progress: bool = True) -> dict:
    """Train (or resume) a PoseNet in run folder ``out``; returns a summary dict
    {"step", "samples", "loss" (last logged means), "checkpoint"}. See the module docstring."""
    import torch

    from ..singleview.networks.losses import disentangled_loss, pad_symmetries
    from ..singleview.networks.model import PoseNet, prepare_inputs
    from .data import SampleGenerator, TrainingStream, make_loader

    conf = resolve_conf(conf)
    out = Path(out)
    loop.check_run_folder(out, resume, overwrite)

    db, K, image_size = _load_objects(Path(dataset), conf["n_points"], conf["seed"])
    obj_ids = [int(o) for o in db.obj_ids]
    record = dict(conf, dataset=str(Path(dataset).resolve()), split=split, obj_ids=obj_ids)
    ckpt = loop.start_run(out, record, resume=resume, overwrite=overwrite)
    device = loop.select_device(conf, log)

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
        step, samples, last = loop.resume_progress(ckpt, out, LOG_FIELDS)
    model.to(device).train()
    loop.optimizer_to(opt, device)
    loop.write_config(out, record)

    points = torch.as_tensor(np.stack([o.points for o in db]), dtype=torch.float32, device=device)  # (n_obj, P, 3)
    syms = pad_symmetries([o.symmetries for o in db]).to(device)  # (n_obj, S, 4, 4)

    gen_kw = dict(kind=conf["kind"], crop_size=(w, h), K=K, image_size=image_size)
    data_seed = np.random.SeedSequence([conf["seed"], step])  # a resumed run draws new samples
    gen, loader, it, loader_c = None, None, None, None

    def next_batch(c: float, step: int) -> dict:
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

    def train_step(step: int):
        c = curriculum(conf, step) if conf["kind"] == "refiner" else 1.0
        b = next_batch(c, step)
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
        return lr, {k: float(terms[k].detach().mean()) for k in ("total", "xy", "z", "rot")}, {"c": f"{c:.2f}"}

    def log_row(means: loop.Means):
        last = means.means()
        return last, {"loss_total": last["total"], "loss_xy": last["xy"], "loss_z": last["z"],
                      "loss_rot": last["rot"], "samples_per_s": means.rate(conf["batch_size"])}

    def cleanup() -> None:
        nonlocal loader, it
        if gen is not None:
            gen.close()
        loader = it = None

    return loop.run_loop(
        out, conf, record, step=step, samples=samples, loss=last, train_step=train_step, log_row=log_row,
        checkpoint=lambda: {"model": model.checkpoint(), "optimizer": opt.state_dict()},
        rng=lambda: loop.rng_state(gen.rng if gen is not None else None), plot=_write_plot,
        log_fields=LOG_FIELDS, resume=resume, unit="samples", loss_format="{:.1f}mm", cleanup=cleanup, sigterm=True,
        log=log, progress=progress)


def load_run(run: str | Path) -> tuple[object, dict]:
    """(PoseNet in eval mode on the CPU, checkpoint dict) of run folder ``run``."""
    from ..singleview.networks.model import PoseNet

    return loop.load_run(run, lambda ck: PoseNet.from_checkpoint(ck["model"]), "cosy train", "checkpoint")


def export(run: str | Path, out: str | Path, accuracy: str | None = None, log: Callable[[str], None] = print) -> Path:
    """Export the run's network to ONNX ``out`` and write the model card ``out`` with suffix .md
    (objects, crop size, backbone, training steps and samples, final loss, date, accuracy)."""
    from ..singleview.networks.onnx import export_onnx

    out = Path(out)
    net, ck = load_run(run)
    export_onnx(net, out)
    c = ck["config"]
    loss = ck.get("loss") or {}
    loss_txt = (f"{loss['total']:.2f} mm (xy {loss['xy']:.2f}, z {loss['z']:.2f}, rotation {loss['rot']:.2f})"
                if loss else "not logged")
    w, h = net.config.crop_size
    loop.write_model_card(out, [
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
    ], ck, accuracy, log)
    return out


__all__ = ["DEFAULT_CONF", "resolve_conf", "learning_rate", "curriculum", "main", "export", "load_run", "read_log"]
