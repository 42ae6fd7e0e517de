"""The resumable training machinery shared by ``cosy train {coarse,refiner}``
(:mod:`cosy_cli.training.train`) and ``cosy train detector`` (:mod:`cosy_cli.detection.train`).

A run folder holds ``checkpoint.pt`` (the trainer's model entries, then ``step``, ``samples``,
``loss`` (last logged means), ``config`` (the run record), ``rng`` (torch RNG state, and for the
pose networks the in-process numpy generator's) and ``saved`` (UTC time); written atomically),
``config.json`` (the run record), ``log.csv`` (one row of means every ``log_every`` steps, at
each checkpoint and at the end) and ``loss.png`` (redrawn at each checkpoint).

- :func:`check_run_folder`, :func:`start_run`: an existing checkpoint is refused unless
  ``resume`` (settings other than :data:`RESUMABLE_CHANGES` must match the run's) or
  ``overwrite`` (the run's files are removed);
- :func:`run_loop`: the step loop: learning rate per step (:func:`learning_rate`: linear warm-up,
  then constant or cosine to 5 %), progress bar, log rows, checkpoints every
  ``checkpoint_every`` steps, at the end and on KeyboardInterrupt (optionally SIGTERM too:
  :func:`stop_on_sigterm`);
- :func:`load_run`, :func:`write_model_card`: the export side.

Heavy imports (torch, matplotlib) happen inside the functions.
"""

from __future__ import annotations

import csv
import math
import os
import time
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from ..errors import CosyError
from ..io.atomic import atomic_path, write_json, write_text

CHECKPOINT = "checkpoint.pt"
CONFIG = "config.json"
LOG = "log.csv"
PLOT = "loss.png"
RUN_FILES = (CHECKPOINT, LOG, PLOT, CONFIG)
# Settings that may differ between a run and its resumption.
RESUMABLE_CHANGES = frozenset({"iterations", "device", "workers", "checkpoint_every", "log_every"})


def learning_rate(conf: dict, step: int) -> float:
    """LR of step ``step`` (0-based): linear warm-up over ``conf["warmup"]`` steps, then
    ``conf["lr"]`` constant (``schedule`` "constant") or cosine down to 5 % at ``iterations``."""
    lr = conf["lr"]
    w = conf["warmup"]
    if w > 0 and step < w:
        return lr * (step + 1) / w
    if conf["schedule"] == "cosine":
        span = max(1, conf["iterations"] - w)
        t = min(1.0, (step - w) / span)
        return lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * t)))
    return lr


# ---------------------------------------------------------------------------------- run folder
def check_run_folder(out: str | Path, resume: bool, overwrite: bool) -> Path:
    """The checkpoint path of run folder ``out``; :class:`CosyError` if it holds a checkpoint
    and neither ``resume`` nor ``overwrite`` is set, or if ``resume`` has nothing to resume."""
    out = Path(out)
    ckpt_path = out / CHECKPOINT
    if ckpt_path.exists() and not resume and not overwrite:
        raise CosyError("run folder already holds a checkpoint: continue it with --resume or start again with "
                        "--overwrite", path=out)
    if resume and not ckpt_path.is_file():
        raise CosyError("nothing to resume: no checkpoint.pt in the run folder", path=out)
    return ckpt_path


def load_checkpoint(path: str | Path, what: str = "checkpoint") -> dict:
    """``torch.load`` of a checkpoint on the CPU; :class:`CosyError` "unreadable {what}" if it fails."""
    import torch

    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:
        raise CosyError(f"unreadable {what}: {e}", path=path) from None


def start_run(out: str | Path, record: dict, *, resume: bool, overwrite: bool,
              resumable: Iterable[str] = RESUMABLE_CHANGES, added: dict | None = None) -> dict | None:
    """Begin a run in folder ``out`` (checked with :func:`check_run_folder` first) whose settings
    are ``record``. ``resume``: the checkpoint, whose recorded config must equal ``record`` but for
    the keys ``resumable`` and for settings added since the run was recorded (``added``: {key: the
    value that does what runs did before the key existed}) that keep that value; ``overwrite``: the
    run's files are removed, None; else None."""
    ckpt_path = Path(out) / CHECKPOINT
    if resume:
        ckpt = load_checkpoint(ckpt_path)
        old = ckpt["config"]
        added = added or {}
        diff = sorted(k for k in set(old) | set(record) if k not in resumable and old.get(k) != record.get(k)
                      and not (k not in old and k in added and record.get(k) == added[k]))
        if diff:
            detail = "; ".join(f"{k}: {old.get(k)!r} in the run, {record.get(k)!r} now" for k in diff)
            raise CosyError(f"cannot resume with different settings ({detail})", path=ckpt_path)
        return ckpt
    if overwrite:
        for name in RUN_FILES:
            (Path(out) / name).unlink(missing_ok=True)
    return None


def write_config(out: str | Path, record: dict) -> None:
    """Create the run folder and write its ``config.json``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / CONFIG, record)


def load_dataset(dataset: str | Path, n_points: int = 1000, seed: int = 0):
    """(ObjectDatabase of ``dataset/models`` (``n_points`` surface points per object, ``seed``),
    K (3x3) and (width, height) of ``dataset/camera.json``, both None without one)."""
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


# ---------------------------------------------------------------------------------- torch state
def select_device(conf: dict, log: Callable[[str], None] = print):
    """torch threads = cores; the device of ``conf["device"]`` (the CPU, with a warning, when CUDA
    is asked for and missing); torch seeded with ``conf["seed"]``."""
    import torch

    torch.set_num_threads(os.cpu_count() or 1)
    want_cuda = conf["device"] == "cuda"
    if want_cuda and not torch.cuda.is_available():
        from ..errors import warn

        warn("--device cuda but no CUDA device is available: training on the CPU")
    device = torch.device("cuda" if want_cuda and torch.cuda.is_available() else "cpu")
    torch.manual_seed(conf["seed"])
    return device


def optimizer_to(opt, device) -> None:
    """Move the optimiser's state tensors (not its step counters) to ``device``, after the model."""
    import torch

    for group in opt.param_groups:
        for p in group["params"]:
            for k, v in opt.state.get(p, {}).items():
                if torch.is_tensor(v) and k != "step":
                    opt.state[p][k] = v.to(device)


def rng_state(numpy_rng: np.random.Generator | None = None, *, numpy: bool = True) -> dict:
    """RNG states for a checkpoint: {"torch": torch's CPU state} and, if ``numpy``,
    "numpy_generator": the bit-generator state of ``numpy_rng`` (None without one)."""
    import torch

    st = {"torch": torch.get_rng_state()}
    if numpy:
        st["numpy_generator"] = None if numpy_rng is None else numpy_rng.bit_generator.state
    return st


def resume_progress(ckpt: dict, out: str | Path, log_fields: list[str]) -> tuple[int, int, dict]:
    """(step, samples, last logged loss means) of a checkpoint; restores torch's RNG state and
    drops the log rows written after the checkpoint (by an interrupted run)."""
    import torch

    step, samples, last = int(ckpt["step"]), int(ckpt["samples"]), dict(ckpt.get("loss", {}))
    torch.set_rng_state(ckpt["rng"]["torch"])
    truncate_log(Path(out) / LOG, step, log_fields)
    return step, samples, last


def save_checkpoint(path: str | Path, ck: dict) -> None:
    """Write ``ck`` plus "saved" (UTC time) atomically with ``torch.save``."""
    import torch

    ck = dict(ck, saved=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
    with atomic_path(path) as tmp:
        torch.save(ck, tmp)


# ---------------------------------------------------------------------------------- log.csv
def read_log(path: str | Path) -> list[dict]:
    """Rows of a run's log.csv as dicts of numbers ([] if there is none)."""
    path = Path(path)
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        # a field added since the run began is empty in its older rows: NaN
        return [{k: (int(v) if k == "step" else float(v) if v not in ("", None) else float("nan"))
                 for k, v in r.items()} for r in csv.DictReader(f)]


def format_value(v) -> str:
    """A log.csv cell: integers as they are, other numbers with 6 significant digits."""
    return str(v) if isinstance(v, (int, np.integer)) else f"{v:.6g}"


def truncate_log(path: str | Path, step: int, fields: list[str]) -> None:
    """Drop log rows after ``step`` (logged after the last checkpoint of an interrupted run)."""
    rows = [r for r in read_log(path) if r["step"] <= step]
    lines = [",".join(fields)] + [",".join(format_value(r[k]) if k in r else "" for k in fields) for r in rows]
    write_text(path, "\n".join(lines) + "\n")


class CsvLog:
    """log.csv of a run, opened for appending (the header first when the file is new).
    :meth:`elapsed` counts on from the last logged time of a resumed run."""

    def __init__(self, path: str | Path, fields: list[str], resume: bool):
        path = Path(path)
        self.fields = list(fields)
        self.t0 = time.time()
        old_rows = read_log(path) if resume else []
        self.t_offset = old_rows[-1]["time_s"] if old_rows else 0.0
        new = not path.is_file()
        self._f = open(path, "a", newline="")
        if new:
            self._f.write(",".join(self.fields) + "\n")

    def elapsed(self) -> float:
        """Seconds of training of the run so far (s)."""
        return self.t_offset + time.time() - self.t0

    def write(self, row: dict) -> None:
        self._f.write(",".join(format_value(row[k]) for k in self.fields) + "\n")
        self._f.flush()

    def close(self) -> None:
        self._f.close()


class Means:
    """Sums of per-step values and of step time since the last log row."""

    def __init__(self):
        self.reset()

    def reset(self) -> None:
        self.sums: dict[str, float] = {}
        self.n = 0
        self.seconds = 0.0

    def add(self, seconds: float, values: dict) -> None:
        for k, v in values.items():
            self.sums[k] = self.sums.get(k, 0.0) + v
        self.n += 1
        self.seconds += seconds

    def mean(self, key: str) -> float:
        return self.sums[key] / self.n

    def means(self, keys: Iterable[str] | None = None) -> dict:
        return {k: self.sums[k] / self.n for k in (self.sums if keys is None else keys)}

    def rate(self, batch_size: int) -> float:
        """Samples per second over the steps summed."""
        return self.n * batch_size / max(self.seconds, 1e-9)


def write_plot(out: str | Path, curves: list[tuple[str, str]], ylabel: str, title: str) -> None:
    """``out``/loss.png: the log columns ``curves`` [(key, label)] against the step, log scale
    (the first one thicker). Nothing without log rows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    rows = read_log(out / LOG)
    if not rows:
        return
    steps = np.array([r["step"] for r in rows])
    fig, ax = plt.subplots(figsize=(7, 4), dpi=100)
    for i, (key, label) in enumerate(curves):
        ax.plot(steps, [r[key] for r in rows], label=label, lw=1.5 if i == 0 else 1)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    with atomic_path(out / PLOT) as tmp:
        fig.savefig(tmp)
    plt.close(fig)


# ---------------------------------------------------------------------------------- the loop
def stop_on_sigterm(requested: dict | None = None) -> Callable[[], None]:
    """Make SIGTERM stop a run like Ctrl-C (so ``kill PID`` of a background run saves a
    checkpoint: shells start background jobs with SIGINT ignored). With ``requested`` (a dict) the
    signal only sets ``requested["stop"]`` and the loop stops at the end of the current step: an
    exception raised asynchronously inside a C call (an OpenGL render) can surface as another
    error type and skip the checkpoint. Without it, SIGTERM raises KeyboardInterrupt at once.
    Returns the function that restores the previous handler. No-op outside the main thread."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return lambda: None

    def handler(signum, frame):
        if requested is None:
            raise KeyboardInterrupt
        requested["stop"] = True

    old = signal.signal(signal.SIGTERM, handler)
    return lambda: signal.signal(signal.SIGTERM, old)


def run_loop(out: str | Path, conf: dict, record: dict, *, step: int, samples: int, loss: dict,
             train_step: Callable[[int], tuple[float, dict, dict]],
             log_row: Callable[[Means], tuple[dict, dict]],
             checkpoint: Callable[[], dict], rng: Callable[[], dict], plot: Callable[[Path], None],
             log_fields: list[str], resume: bool, unit: str = "samples", loss_format: str = "{:.3f}",
             cleanup: Callable[[], None] = lambda: None, sigterm: bool = False,
             log: Callable[[str], None] = print, progress: bool = True) -> dict:
    """Train from ``step`` to ``conf["iterations"]`` in run folder ``out``; returns {"step",
    "samples", "loss" (last logged means), "checkpoint" (path)}.

    train_step(step): one optimisation step at 0-based ``step`` -> (lr used, {name: value} to
    average in the log, e.g. "total" (shown on the progress bar with ``loss_format``), extra
    progress-bar fields). log_row(means): (the loss means kept as "loss", the log row's columns
    other than step, time_s and lr). checkpoint(): the checkpoint's leading entries (model,
    optimiser...), followed by step, samples, loss, config (``record``), rng (``rng()``), saved;
    ``plot(out)`` is drawn after each checkpoint. cleanup(): called when the loop ends, however.
    ``sigterm``: SIGTERM saves a checkpoint like Ctrl-C. A KeyboardInterrupt is re-raised after
    the checkpoint is saved."""
    from ..console import progress as progress_bar

    out = Path(out)
    ckpt_path = out / CHECKPOINT
    iterations, batch_size = conf["iterations"], conf["batch_size"]
    last = dict(loss)
    means = Means()
    csv_log = CsvLog(out / LOG, log_fields, resume)

    def flush_log(lr: float) -> None:
        """One log row: means of the steps since the last row."""
        nonlocal last
        if means.n == 0:
            return
        last, columns = log_row(means)
        csv_log.write(dict(columns, step=step, time_s=csv_log.elapsed(), lr=lr))
        means.reset()

    def save() -> None:
        save_checkpoint(ckpt_path, dict(checkpoint(), step=step, samples=samples, loss=last, config=record,
                                        rng=rng()))
        plot(out)

    lr = learning_rate(conf, step)
    term = {"stop": False}  # set by SIGTERM: stop after the current step
    restore_term = stop_on_sigterm(term) if sigterm else (lambda: None)
    bar = progress_bar(total=iterations, initial=min(step, iterations), desc=f"train {conf['kind']}", unit="step",
                       enabled=progress, leave=True)
    try:
        while step < iterations:
            t0 = time.time()
            lr, values, extra = train_step(step)
            step += 1
            samples += batch_size
            means.add(time.time() - t0, values)
            bar.update(1)
            bar.set_postfix(loss=loss_format.format(means.mean("total")), lr=f"{lr:.1e}", **extra)
            if means.n >= conf["log_every"] or step == iterations or step % conf["checkpoint_every"] == 0:
                flush_log(lr)
            if step % conf["checkpoint_every"] == 0 and step < iterations:
                save()
            if term["stop"]:
                raise KeyboardInterrupt
    except KeyboardInterrupt:
        flush_log(lr)
        csv_log.close()
        save()
        from ..console import warning  # said also with --quiet: a script must know how to continue

        warning(f"interrupted: checkpoint saved at step {step} in {ckpt_path} (continue with --resume)")
        raise
    finally:
        bar.close()
        restore_term()
        cleanup()
    csv_log.close()
    save()
    log(f"trained {conf['kind']} to step {step} ({samples} {unit}); checkpoint: {ckpt_path}")
    return {"step": step, "samples": samples, "loss": last, "checkpoint": ckpt_path}


# ---------------------------------------------------------------------------------- export
def load_run(run: str | Path, build: Callable[[dict], object], train_command: str = "cosy train",
             what: str = "checkpoint") -> tuple[object, dict]:
    """(``build(checkpoint)`` in eval mode, checkpoint dict) of run folder ``run``;
    :class:`CosyError` for a missing folder or checkpoint (naming ``train_command``) or an
    unreadable {what} (loading or building)."""
    import torch

    path = Path(run) / CHECKPOINT
    if not Path(run).is_dir():
        raise CosyError("run folder not found", path=run)
    if not path.is_file():
        raise CosyError(f"no checkpoint.pt in the run folder (train one with `{train_command}`)", path=run)
    try:
        ck = torch.load(path, map_location="cpu", weights_only=False)
        net = build(ck)
    except Exception as e:
        raise CosyError(f"unreadable {what}: {e}", path=path) from None
    return net.eval(), ck


def write_model_card(out: str | Path, lines: list[str], ck: dict, accuracy: str | None = None,
                     log: Callable[[str], None] = print) -> Path:
    """The model card next to the exported ``out`` (same name, .md): ``lines``, then the
    checkpoint's save date, the export date and the measured ``accuracy``."""
    out = Path(out)
    card = "\n".join(lines + [
        f"- checkpoint saved: {ck.get('saved', 'unknown')}; exported: "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}",
        f"- measured accuracy: {accuracy or 'not measured'}",
        "",
    ])
    write_text(out.with_suffix(".md"), card)
    log(f"exported {out} and {out.with_suffix('.md')}")
    return out.with_suffix(".md")


__all__ = ["CHECKPOINT", "CONFIG", "LOG", "PLOT", "RESUMABLE_CHANGES", "learning_rate", "check_run_folder",
           "load_checkpoint", "start_run", "write_config", "load_dataset", "select_device", "optimizer_to",
           "rng_state", "resume_progress", "save_checkpoint", "read_log", "format_value", "truncate_log", "CsvLog",
           "Means", "write_plot", "stop_on_sigterm", "run_loop", "load_run", "write_model_card"]
