"""``cosy onboard``: a detector and its box classifier for a set of meshes, trained side by side.

What `cosy run --config onboarded` needs for objects nobody trained a detector for, from their
meshes alone (no real image): the detector (``cosy train detector --preset real``) and the box
classifier with its box and mask heads (``cosy train classifier --preset real``), each in its own
process at the same time (on 2 CPU cores the pair took 46-60 min side by side, where one after
the other took 31 + 51 min), then both exported. With ``long``, the detector's training then
continues at 480 x 352 px for ``long_iterations`` more steps (real LM-O AP50 about 0.16 -> 0.25
for the detector alone, 32-48 min more on 2 cores).

Folder ``out``: ``detector/`` and ``classifier/`` (the two runs: checkpoints, logs, loss plots;
``detector480/`` with ``long``), ``detector.log`` / ``classifier.log`` (what each process printed),
``detector.onnx`` and ``classifier.onnx`` with their model cards, ``onboard.json`` (settings,
commands, times). Ctrl-C or SIGTERM stops both processes, which save a checkpoint: ``resume``
continues where they stopped.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

from ..conf import merge_conf
from ..errors import CosyError
from ..io.atomic import write_json

CONFS = {
    "default": {
        "detector_iterations": None,    # None: the preset's (2500 at 320 x 240)
        "classifier_iterations": None,  # None: the preset's (3000)
        "long": False,                  # then continue the detector at 480 x 352 (the better, longer recipe)
        "long_iterations": 1500,
        "seed": 0,
        "device": "cpu",
        "distance": None,               # [near, far] mm of the rendered scenes (None: the preset's 300-1100)
        "classifier_backbone": None,    # detector | efficientnet-lite0 (None: the preset's, the detector's backbone)
        "detector_backbone": None,      # plain | efficientnet-lite0 (None: the preset's, plain)
        "classifier_precision": None,   # int8 | fp32: an EfficientNet-Lite0 classifier's export (None: fp32)
    },
}
RECORD = "onboard.json"


def resolve_conf(conf: str | dict | None = None, **overrides) -> dict:
    c = merge_conf(CONFS, conf, overrides, default="default", what="onboard")
    try:
        for k in ("detector_iterations", "classifier_iterations"):
            c[k] = None if c[k] is None else int(c[k])
        c["long_iterations"], c["seed"] = int(c["long_iterations"]), int(c["seed"])
        c["long"] = bool(c["long"])
        c["distance"] = None if c["distance"] is None else [float(v) for v in c["distance"]]
        if c["classifier_backbone"] not in (None, "detector", "efficientnet-lite0"):
            raise ValueError(f"classifier_backbone must be detector or efficientnet-lite0, got {c['classifier_backbone']!r}")
        if c["detector_backbone"] not in (None, "plain", "efficientnet-lite0"):
            raise ValueError(f"detector_backbone must be plain or efficientnet-lite0, got {c['detector_backbone']!r}")
        if c["classifier_precision"] not in (None, "int8", "fp32"):
            raise ValueError(f"classifier_precision must be int8 or fp32, got {c['classifier_precision']!r}")
        if c["classifier_precision"] == "int8" and c["classifier_backbone"] != "efficientnet-lite0":
            raise ValueError("classifier_precision int8 is for the efficientnet-lite0 classifier backbone")
    except (TypeError, ValueError) as e:
        raise CosyError(f"onboard settings: {e}") from None
    if any(c[k] is not None and c[k] < 1 for k in ("detector_iterations", "classifier_iterations")) \
            or c["long_iterations"] < 1 or c["device"] not in ("cpu", "cuda") \
            or (c["distance"] is not None and not (len(c["distance"]) == 2 and 0 < c["distance"][0] <= c["distance"][1])):
        raise CosyError("onboard settings out of range (iterations >= 1, device cpu or cuda, distance [near, far] "
                        "with 0 < near <= far mm)")
    return c


def train_command(kind: str, models_dir: Path, camera: Path | None, run: Path, conf: dict, *,
                  backgrounds: Path | None = None, iterations: int | None = None, resume: bool = False,
                  extra: list | None = None) -> list[str]:
    """The ``cosy train KIND --preset real`` command line (a list) of one run of the onboarding."""
    cmd = [sys.executable, "-m", "cosy_cli", "train", kind, "--models", str(models_dir), "--preset", "real",
           "--out", str(run), "--seed", str(conf["seed"]), "--device", conf["device"]]
    if camera is not None:
        cmd += ["--camera", str(camera)]
    if backgrounds is not None:
        cmd += ["--backgrounds", str(backgrounds)]
    if iterations is not None:
        cmd += ["--iterations", str(iterations)]
    if conf.get("distance"):
        cmd += ["--distance", ",".join(f"{v:g}" for v in conf["distance"])]
    if conf.get(f"{kind}_backbone"):
        cmd += ["--backbone", conf[f"{kind}_backbone"]]
    if resume and (run / "checkpoint.pt").is_file():
        cmd += ["--resume"]
    return cmd + list(extra or [])


def _last_step(run: Path) -> int:
    """The last step in a run's log.csv (0 when there is none yet)."""
    try:
        lines = (run / "log.csv").read_text().strip().splitlines()
        return int(lines[-1].split(",")[0]) if len(lines) > 1 else 0
    except (OSError, ValueError, IndexError):
        return 0


def _tail(path: Path, n: int = 6) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").strip().splitlines()[-n:])
    except OSError:
        return "(no output)"


def run_side_by_side(jobs: dict, out: Path, totals: dict, *, log: Callable[[str], None] = print,
                     progress: bool = True, poll_s: float = 2.0) -> dict:
    """Start every command of ``jobs`` ({name: (command list, run folder)}) as its own process (its
    output in ``out/NAME.log``), show their steps against ``totals`` ({name: steps}) in one
    progress bar, wait for all. A process that fails stops the others (they save a checkpoint) and
    raises :class:`CosyError` with the end of its log; Ctrl-C stops them all the same way. Returns
    {name: seconds}."""
    from ..console import progress as progress_bar

    procs, files, t0, took = {}, {}, time.perf_counter(), {}
    try:
        for name, (cmd, _) in jobs.items():
            files[name] = open(out / f"{name}.log", "a")
            procs[name] = subprocess.Popen(cmd, stdout=files[name], stderr=subprocess.STDOUT)
        bar = progress_bar(total=sum(totals.values()), desc="onboard", unit="step", enabled=progress)
        done_steps = 0
        while procs.keys() - took.keys():
            time.sleep(poll_s)
            steps = sum(min(_last_step(run), totals[name]) for name, (_, run) in jobs.items())
            if steps > done_steps:
                bar.update(steps - done_steps)
                done_steps = steps
            for name, p in procs.items():
                if name in took or p.poll() is None:
                    continue
                took[name] = time.perf_counter() - t0
                if p.returncode != 0:
                    raise CosyError(f"cosy train {jobs[name][0][4]} failed (exit code {p.returncode}); the end of "
                                    f"its log:\n{_tail(out / f'{name}.log')}", path=out / f"{name}.log")
                log(f"onboard: {name} trained in {took[name] / 60:.1f} min")
        bar.close()
    except BaseException:
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)  # each saves a checkpoint before it exits
        for p in procs.values():
            try:
                p.wait(timeout=120)
            except subprocess.TimeoutExpired:
                p.kill()
        raise
    finally:
        for f in files.values():
            f.close()
    return took


def main(conf: str | dict | None, models_dir: str | Path, out: str | Path, *, camera: str | Path | None = None,
         backgrounds: str | Path | None = None, overwrite: bool = False, resume: bool = False,
         log: Callable[[str], None] = print, progress: bool = True) -> dict:
    """Train the detector and the box classifier of the meshes in ``models_dir`` side by side in
    ``out`` and export them (``out/detector.onnx``, ``out/classifier.onnx``); returns the record
    written to ``out/onboard.json``."""
    import shutil

    conf = resolve_conf(conf)
    models_dir, out = Path(models_dir), Path(out)
    if not (models_dir / "models_info.json").is_file():
        raise CosyError("not a models folder (models_info.json and obj_XXXXXX.ply expected)", path=models_dir)
    for p, what in ((camera, "camera file"), (backgrounds, "backgrounds folder")):
        if p is not None and not Path(p).exists():
            raise CosyError(f"{what} not found", path=p)
    if out.exists() and any(out.iterdir()):
        if overwrite:
            shutil.rmtree(out)
        elif not resume:
            raise CosyError("exists and is not empty: --resume continues its training, --overwrite starts again",
                            path=out)
    out.mkdir(parents=True, exist_ok=True)
    camera = None if camera is None else Path(camera)
    backgrounds = None if backgrounds is None else Path(backgrounds)
    from . import classifier_train, train as det_train

    runs = {"detector": out / "detector", "classifier": out / "classifier"}
    clf_arch = {"efficientnet-lite0": "lite0"}.get(conf["classifier_backbone"])
    det_arch = {"efficientnet-lite0": "lite0"}.get(conf["detector_backbone"])
    totals = {"detector": conf["detector_iterations"]
              or int(det_train.resolve_conf("real", backbone=det_arch)["iterations"]),
              "classifier": conf["classifier_iterations"]
              or int(classifier_train.resolve_conf("real", arch=clf_arch)["iterations"])}
    jobs = {name: (train_command(name, models_dir, camera, runs[name], conf, backgrounds=backgrounds,
                                 iterations=conf[f"{name}_iterations"], resume=resume), runs[name])
            for name in runs}
    record = {"conf": conf, "models": str(models_dir.resolve()), "camera": None if camera is None else str(camera),
              "backgrounds": None if backgrounds is None else str(backgrounds),
              "commands": {n: j[0][1:] for n, j in jobs.items()}, "minutes": {}}
    log(f"onboard: training the detector ({totals['detector']} steps) and the box classifier "
        f"({totals['classifier']} steps) side by side in {out} (logs: detector.log, classifier.log)")
    t0 = time.perf_counter()
    took = run_side_by_side(jobs, out, totals, log=log, progress=progress)
    record["minutes"].update({n: round(s / 60, 2) for n, s in took.items()})
    det_run = runs["detector"]
    if conf["long"]:
        det_train.export(det_run, out / "detector320.onnx", log=log)
        run480 = out / "detector480"
        cmd = train_command("detector", models_dir, camera, run480, conf, backgrounds=backgrounds,
                            iterations=conf["long_iterations"], resume=resume,
                            extra=["--input", "480x352", "--init", str(out / "detector320.onnx")])
        record["commands"]["detector480"] = cmd[1:]
        log(f"onboard: the detector continues at 480 x 352 for {conf['long_iterations']} steps")
        took = run_side_by_side({"detector480": (cmd, run480)}, out, {"detector480": conf["long_iterations"]},
                                log=log, progress=progress)
        record["minutes"]["detector480"] = round(took["detector480"] / 60, 2)
        det_run = run480
    det_train.export(det_run, out / "detector.onnx", log=log)
    classifier_train.export(runs["classifier"], out / "classifier.onnx", log=log,
                            precision=conf["classifier_precision"])
    record["minutes"]["total"] = round((time.perf_counter() - t0) / 60, 2)
    write_json(out / RECORD, json.loads(json.dumps(record)))
    log(f"onboard: {out / 'detector.onnx'} and {out / 'classifier.onnx'} in {record['minutes']['total']:.1f} min; "
        f"use them with `cosy run --dataset DIR --model {out / 'detector.onnx'} --classifier "
        f"{out / 'classifier.onnx'} --config onboarded --out RUN`")
    return record


__all__ = ["CONFS", "resolve_conf", "main", "train_command", "run_side_by_side"]
