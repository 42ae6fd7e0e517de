"""``cosy run``: detect -> estimate -> match -> refine per scene, then merge, evaluate and report.

Layout of RUN_DIR::

    run.json                      the manifest: dataset, scenes, config and resolved settings of
                                  every stage, code version, per-stage status and timings
    templates/                    templates of the training-free coarse step (built once)
    scenes/000001/detections.json     BOP detections of the scene (detect)
    scenes/000001/candidates.csv      single-view candidates, BOP results (estimate; + .json, .timing.csv)
    scenes/000001/match/              cosy match output
    scenes/000001/refine/             cosy refine output (scene.json, predictions.csv)
    scenes/000001/.cosy/<stage>.json  unit records (see :mod:`cosy_cli.pipeline.units`)
    detect/detections.json        all scenes' detections
    estimate/candidates.csv       all scenes' single-view candidates
    refine/predictions.csv        all scenes' refined predictions: the final BOP results file
    refine/scene.json             all groups' cameras and objects
    evaluate/single_view/, evaluate/multi_view/   cosy evaluate outputs (when the split has GT)
    figures/, report.html         cosy viz

Each scene is one task (serial, ``workers`` processes, or a Dask cluster); a unit whose settings,
inputs and code did not change is skipped, so a changed setting reruns its stage and, through
their inputs, the stages after it, and an interrupted run resumes where it stopped.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Callable

from .. import console
from ..conf import merge_conf
from ..errors import CosyError
from ..io import atomic
from ..io import manifest as integrity
from ..io.dataset import BopDataset, with_sensor
from . import units
from .layout import MANIFEST, RUN_FORMAT, scene_dir

STAGES = ("detect", "estimate", "match", "refine", "evaluate", "viz")
SCENE_STAGES = ("detect", "estimate", "match", "refine")

# Named run configurations: the settings given to each stage (a stage's named preset or a dict of
# overrides over its default).
CONFS: dict[str, dict] = {
    "default": {"detect": "default", "estimate": "default", "match": "paper", "refine": None,
                "evaluate": "bop19"},
    # The paper's chain: networks on RGB, the paper's matching settings without the refit.
    "paper": {"detect": "default", "estimate": "paper", "match": "paper-norefit", "refine": None,
              "evaluate": "bop19"},
    # Boxes from a detector onboarded from meshes alone (`cosy train detector/classifier --preset real`):
    # many right boxes score low and fit loosely. Up to 100 proposals down to score 0.01 for the box
    # classifier, whose box head moves each twice; the best 3 boxes of each object in each image go
    # through stage 1 and the one whose pose fits the image best is kept (score "pose": the detection's
    # x the verification's, the learned scorer's with --scorer; one instance of each object per image, as
    # in LM-O and YCB-V); each template hypothesis also verified nearer and farther; a classifier with a
    # mask head adds each detection's mask (the detect default), which the verification uses. Chosen on
    # the odd lmo_dev scenes (docs/results.md).
    "onboarded": {"detect": {"min_score": 0.01, "max_per_image": 100, "refine_boxes": 2, "max_per_object": 3},
                  "estimate": {"box_scales": [0.87, 1.0, 1.15], "score": "pose", "max_per_object": 1},
                  "match": "paper", "refine": None, "evaluate": "bop19"},
    # onboarded, with the detect stage within 0.25 s per 640 x 480 image on 2 cores for an EfficientNet-Lite0
    # pair (with the classifier exported in int8): 80 proposals, only the best 15 after the first look moved
    # (odd lmo_dev scenes: AP50 0.470 -> 0.455, 1.19 -> 0.25 s per image; docs/results.md)
    "onboarded-fast": {"detect": {"min_score": 0.01, "max_per_image": 80, "refine_boxes": 2, "refine_top": 15,
                                  "max_per_object": 3},
                       "estimate": {"box_scales": [0.87, 1.0, 1.15], "score": "pose", "max_per_object": 1},
                       "match": "paper", "refine": None, "evaluate": "bop19"},
    # Quicker: fewer template hypotheses, fewer ICP iterations, no VSD (BOP19 AR from MSSD/MSPD).
    "fast": {"detect": "default", "estimate": {"top_k": 3, "icp_screen": 0, "icp_iterations": 10}, "match": "paper",
             "refine": None, "evaluate": {"vsd": False}},
}


def resolve_confs(config: str | dict | None = "default", **overrides) -> dict:
    """The full settings of every stage for a named run configuration, with per-stage overrides
    (``estimate={"top_k": 3}``, ``match={"views_per_group": 4}``; None ignored)."""
    from ..detection import stage as detect_stage
    from ..evaluation import evaluate_stage
    from ..multiview import match_stage, refine_stage
    from ..singleview import estimate_stage

    base = merge_conf(CONFS, config, {}, default="default", what="run")
    resolvers = {"detect": detect_stage.resolve_conf, "estimate": estimate_stage.resolve_conf,
                 "match": match_stage.resolve_conf, "refine": refine_stage.resolve_conf,
                 "evaluate": evaluate_stage.resolve_conf}
    out = {}
    for stage, resolve in resolvers.items():
        extra = {k: v for k, v in (overrides.get(stage) or {}).items() if v is not None}
        out[stage] = resolve(base.get(stage), **extra)
    return json.loads(json.dumps(out))


def runs(stage: str, first: str, last: str) -> bool:
    """Whether ``stage`` is among the stages ``first`` .. ``last`` (names of :data:`STAGES`)."""
    return STAGES.index(first) <= STAGES.index(stage) <= STAGES.index(last)


def parse_settings(items) -> dict:
    """``["detect.min_score=0.1", "match.views_per_group=4"]`` -> ``{"detect": {"min_score": 0.1}, ...}``
    (values read as JSON when they parse, else kept as strings)."""
    out: dict[str, dict] = {}
    for item in items or ():
        key, sep, value = str(item).partition("=")
        stage, dot, name = key.strip().partition(".")
        if not sep or not dot or not name or stage not in SCENE_STAGES + ("evaluate",):
            raise CosyError(f"--set {item!r}: expected STAGE.KEY=VALUE with STAGE one of "
                            f"{', '.join(SCENE_STAGES + ('evaluate',))}")
        try:
            val = json.loads(value)
        except json.JSONDecodeError:
            val = value
        out.setdefault(stage, {})[name] = val
    return out


# ------------------------------------------------------------------------------------------
# one scene
# ------------------------------------------------------------------------------------------
def _digest_of(path) -> str | None:
    return None if path is None else units.path_digest(path)


def run_scene(task: dict) -> dict:
    """Run the scene stages of one scene (a picklable task for process pools and Dask).

    task: run_dir, dataset, split, scene_id, confs, source ("gt" | "model" | "json" |
    "candidates"), source_file, coco_images, models_dir, templates_dir, first, last (stage names),
    force (stages to rerun regardless). Returns {"scene_id", "units": {stage: {"ran", "time_s"}},
    "warnings": [...]}: the scene's cosy warnings, caught here (a worker process prints nothing)
    and issued again by the run (:func:`cosy_cli.console.replay`), which summarises them.
    """
    import warnings

    from ..errors import CosyWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", CosyWarning)
        result = _run_scene(task)
    result["warnings"] = console.capture_records(caught)
    return result


def _run_scene(task: dict) -> dict:
    if task.get("single_thread"):
        os.environ.setdefault("OMP_NUM_THREADS", "1")
        try:
            import torch

            torch.set_num_threads(1)
        except ImportError:  # pragma: no cover
            pass
    run_dir, sid = Path(task["run_dir"]), int(task["scene_id"])
    sdir = scene_dir(run_dir, sid)
    sdir.mkdir(parents=True, exist_ok=True)
    dataset, split, confs = task["dataset"], task["split"], task["confs"]
    force = set(task.get("force") or ())
    log_path = sdir / "log.txt"

    def log(msg: str) -> None:
        with open(log_path, "a") as f:
            f.write(msg.rstrip() + "\n")

    def wanted(stage: str) -> bool:
        return runs(stage, task["first"], task["last"])

    def need(rel: str, stage: str) -> Path:
        p = sdir / rel
        if not p.exists():
            raise CosyError(f"scene {sid}: {rel} is missing; run from an earlier stage than "
                            f"'{task['first']}' (it is made by {stage})", path=p)
        return p

    done: dict[str, dict] = {}

    def unit(stage: str, conf, inputs: dict, outputs: list[str], work) -> None:
        """Run ``work`` for ``stage`` of this scene unless its record is current."""
        key = units.unit_key(stage, conf, {**inputs, "scene": sid, "dataset": str(dataset), "split": split})
        ran, dt = units.run_unit(sdir, stage, key, outputs, work, stage in force)
        done[stage] = {"ran": ran, "time_s": dt}

    dets, cands = sdir / "detections.json", sdir / "candidates.csv"
    if task["source"] == "candidates":
        if wanted("detect") or wanted("estimate"):
            src = Path(task["source_file"])

            def copy_candidates():
                from ..io import bop

                integrity.verify(src)
                res = bop.read_results(src)
                sel = (res.table["scene_id"] == sid).to_numpy()
                text = bop.format_results(bop.PoseResults(res.table[sel].reset_index(drop=True), res.T_cam_obj[sel]))
                integrity.write_file_manifest(cands, "cosy run", text.encode("utf-8"))
                atomic.write_text(cands, text)

            unit("estimate", None, {"candidates_file": _digest_of(src)}, ["candidates.csv"], copy_candidates)
    else:
        if wanted("detect"):
            from ..detection import stage as detect_stage

            src = task.get("source_file")
            inputs = {"source": task["source"], "file": _digest_of(src), "coco_images": _digest_of(task.get("coco_images"))}
            if task["source"] == "gt":
                inputs["gt_info"] = _digest_of(BopDataset(dataset, split).scene_file(sid, "scene_gt_info"))
            clf = str(confs["detect"].get("classifier", "auto"))
            if task["source"] == "model":  # the box classifier that follows the detector (its file, not its name)
                inputs["classifier"] = _digest_of(detect_stage.SHIPPED_CLASSIFIER if clf == "auto"
                                                  else None if clf == "none" else clf)
            elif clf not in ("auto", "none"):  # boxes from elsewhere: the classifier adds its masks
                inputs["classifier"] = _digest_of(clf)
            unit("detect", confs["detect"], inputs, ["detections.json"], lambda: detect_stage.main(
                confs["detect"], dataset, split, dets, overwrite=True, scene_ids=[sid],
                model=src if task["source"] == "model" else None,
                from_json=src if task["source"] == "json" else None, coco_images=task.get("coco_images"),
                from_gt=task["source"] == "gt", log=log, progress=False))
        if wanted("estimate"):
            from ..singleview import estimate_stage

            need("detections.json", "detect")
            est_inputs = {"detections": _digest_of(dets),
                          "models": _digest_of(Path(task["models_dir"]) / "models_info.json")}
            if task.get("scorer_model"):  # recorded only when used: earlier runs stay up to date
                est_inputs["scorer"] = _digest_of(task["scorer_model"])
            unit("estimate", confs["estimate"], est_inputs,
                 ["candidates.csv", "candidates.json", "candidates.timing.csv"], lambda: estimate_stage.main(
                     confs["estimate"], dataset, split, cands, overwrite=True, scene_ids=[sid], detections=dets,
                     models_dir=task["models_dir"], templates_dir=task["templates_dir"],
                     scorer_model=task.get("scorer_model"), log=log, progress=False))
    if wanted("match"):
        from ..multiview import match_stage

        need("candidates.csv", "estimate")
        unit("match", confs["match"], {"candidates": _digest_of(cands)}, ["match"], lambda: match_stage.main(
            confs["match"], dataset, split, cands, sdir / "match", overwrite=True, log=log, progress=False))
    if wanted("refine"):
        from ..multiview import refine_stage

        need("match", "match")
        ref_inputs = {"match": _digest_of(sdir / "match")}
        if task.get("scorer_model"):  # the image check's scorer; recorded only when used
            ref_inputs["scorer"] = _digest_of(task["scorer_model"])
        unit("refine", confs["refine"], ref_inputs, ["refine"], lambda: refine_stage.main(
            confs["refine"], dataset, split, sdir / "match", sdir / "refine", overwrite=True,
            scorer_model=task.get("scorer_model"), log=log, progress=False))
    return {"scene_id": sid, "units": done}


# ------------------------------------------------------------------------------------------
# merging the scenes
# ------------------------------------------------------------------------------------------
def merge_csv(parts: list[Path], out: Path, sidecar_manifest: bool = True) -> None:
    """Concatenate CSV files with the same header (written atomically; with ``sidecar_manifest``
    its manifest ``<out>.manifest.json``, see :mod:`cosy_cli.io.manifest`). Each part is checked
    against its own manifest first."""
    header, lines = None, []
    for p in parts:
        integrity.verify(p)
        text = p.read_text().splitlines()
        if not text:
            continue
        if header is None:
            header = text[0]
        elif text[0] != header:
            raise CosyError(f"header differs from {parts[0]}", path=p)
        lines.extend(t for t in text[1:] if t)
    out.parent.mkdir(parents=True, exist_ok=True)
    text = "\n".join([header or ""] + lines) + "\n"
    if sidecar_manifest:
        integrity.write_file_manifest(out, "cosy run", text.encode("utf-8"))
    atomic.write_text(out, text)


def merge_detections(parts: list[Path], out: Path) -> None:
    data = []
    for p in parts:
        data.extend(json.loads(p.read_text()))
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic.write_json(out, data, indent=None)


def single_view_counts(sdirs: list[Path]) -> dict:
    """Groups of one view in the scenes' refine outputs (their candidates passed through):
    {"groups", "groups_total", "scene_ids"}."""
    n = total = 0
    scenes = []
    for d in sdirs:
        try:
            doc = json.loads((d / "refine" / "scene.json").read_text())
        except (OSError, json.JSONDecodeError):
            continue
        k = sum(bool(g.get("single_view")) for g in doc.get("groups", []))
        n, total = n + k, total + len(doc.get("groups", []))
        if k:
            scenes.append(int(d.name))
    return {"groups": n, "groups_total": total, "scene_ids": scenes}


def merge_scene_json(parts: list[Path], out: Path) -> None:
    """One refine ``scene.json`` holding the groups of every scene (settings of the first part;
    each scene's summary under ``scene_summaries``)."""
    for p in parts:
        integrity.verify(p)
    docs = [json.loads(p.read_text()) for p in parts]
    merged = {k: v for k, v in docs[0].items() if k not in ("groups", "summary", "matches", "groups_sha1")}
    merged["matches"] = [d.get("matches") for d in docs]
    merged["scene_summaries"] = {str(g["scene_id"]): d.get("summary") for d in docs for g in d["groups"][:1]}
    merged["groups"] = [g for d in docs for g in d["groups"]]
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic.write_json(out, merged)


# ------------------------------------------------------------------------------------------
# the run
# ------------------------------------------------------------------------------------------
def _execute(tasks: list[dict], workers: int, dask_scheduler: str | None, progress: bool) -> list[dict]:
    from ..console import progress as progress_bar

    bar = progress_bar(total=len(tasks), desc="scenes", unit="scene", enabled=progress)
    results = []

    def finished(result: dict) -> None:  # a scene's result, its warnings issued here (summarised by the run)
        console.replay(result.pop("warnings", []))
        results.append(result)
        bar.update(1)

    try:
        if dask_scheduler:
            from distributed import Client, as_completed

            with Client(dask_scheduler) as client:
                futures = client.map(run_scene, tasks, pure=False)
                for fut in as_completed(futures):
                    finished(fut.result())
        elif workers > 1:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor, as_completed as done_first

            # spawned, not forked: EGL/OpenGL contexts and torch threads do not survive a fork
            with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn")) as pool:
                futs = [pool.submit(run_scene, {**t, "single_thread": True}) for t in tasks]
                for fut in done_first(futs):
                    finished(fut.result())
        else:
            for t in tasks:
                finished(run_scene(t))
    finally:
        bar.close()
    return sorted(results, key=lambda r: r["scene_id"])


def plan_groups(ds: BopDataset, groups: str | None) -> tuple[str, str | None, str | None]:
    """How a run groups the views of ``ds``: (split spec to run on, the sensor whose images get
    the predictions when the run is a rig (None otherwise), the match stage's ``groups``
    setting (None: its default)).

    A multi-sensor dataset read without a sensor (or with sensor ``rig``) runs as a rig: all its
    sensors at once (:class:`~cosy_cli.io.dataset.RigDataset`), cameras known from their
    extrinsics, grouped by ``test_targets_multiview_bop25.json`` when the dataset has one, else by
    instant (``groups`` chooses: ``scene`` puts every instant of a static scene in one group);
    predictions are for the evaluation sensor's images. One sensor of a multi-sensor dataset is
    grouped by scene; a single-sensor dataset by its multi-view targets file when it has one
    (without known cameras), else by scene."""
    from ..io.dataset import RIG, split_spec_sensor

    chosen = split_spec_sensor(ds.split_spec)
    if ds.is_multi_sensor and chosen in (None, RIG):
        grouping = groups or ("targets" if ds.multiview_targets_path() is not None else "instant")
        return with_sensor(ds.split, RIG), ds.eval_sensor, grouping
    if groups == "instant":
        raise CosyError("--groups instant groups the sensors of a multi-sensor dataset (no --sensor, or --sensor rig)",
                        path=ds.split_dir)
    if groups is None and not ds.is_multi_sensor and ds.multiview_targets_path() is not None:
        return ds.split_spec, None, "targets"
    return ds.split_spec, None, groups


def write_sensor_results(ds, src: Path, sensor: str, dst: Path) -> None:
    """The rows of a rig run's BOP results ``src`` (rig views of ``ds``) that are images of
    ``sensor``, as BOP results of that sensor's im_ids (``dst``, with its manifest)."""
    import numpy as np

    from ..io import bop

    integrity.verify(src)
    res = bop.read_results(src)
    views = res.table["im_id"].to_numpy()
    of = [ds.view_of(int(v)) for v in views]
    keep = np.array([s == sensor for s, _ in of], dtype=bool)
    tab = res.table[keep].reset_index(drop=True).copy()
    tab["im_id"] = np.array([im for (s, im) in of if s == sensor], dtype=np.int64)
    text = bop.format_results(bop.PoseResults(tab, res.T_cam_obj[keep]))
    integrity.write_file_manifest(dst, "cosy run", text.encode("utf-8"))
    atomic.write_text(dst, text)


def main(config: str | dict | None, dataset: str | Path, split: str, out: str | Path, overwrite: bool = False, *,
         scene_ids: list[int] | None = None, detections: str | Path | None = None, coco_images=None,
         from_gt: bool = False, model: str | Path | None = None, candidates: str | Path | None = None,
         models_dir: str | Path | None = None, templates_dir: str | Path | None = None,
         scorer_model: str | Path | None = None, overrides: dict | None = None, first: str = "detect",
         last: str = "viz", workers: int = 1, dask_scheduler: str | None = None, log: Callable[[str], None] = print,
         progress: bool = True, groups: str | None = None) -> dict:
    """Run the pipeline into the run folder ``out``; returns the manifest (also ``out/run.json``).

    Sources of the first stage, at most one: ``detections`` (a BOP or COCO detections file),
    ``from_gt`` (visible GT boxes), ``candidates`` (single-view candidates, BOP results CSV: starts
    at match), else ``model`` (a detector ONNX, default the shipped one). ``first``/``last``:
    the stages to run (earlier stages' outputs are used as they are). ``overwrite`` reruns
    every stage. ``overrides``: per-stage settings over the named ``config``. ``templates_dir``:
    templates of the coarse step, built when missing (default ``out/templates``). ``scorer_model``:
    a learned hypothesis scorer for the estimate stage (``cosy train scorer``).

    ``groups``: the match stage's grouping (scene, instant, targets; None: :func:`plan_groups`).
    A multi-sensor dataset without a sensor in ``split`` (or with ``SPLIT:rig``) runs as a rig
    (:func:`plan_groups`): its predictions for the evaluation sensor's images are written to
    ``estimate/candidates_<sensor>.csv`` and ``refine/predictions_<sensor>.csv`` (BOP results of
    that sensor's im_ids) and evaluated.
    """
    t_start = time.perf_counter()
    if sum(x is not None for x in (detections, candidates, model)) + bool(from_gt) > 1:
        raise CosyError("give at most one of --detections, --from-gt, --candidates and --model")
    for name, v in (("--from", first), ("--to", last)):
        if v not in STAGES:
            raise CosyError(f"{name}: unknown stage {v!r} (stages: {', '.join(STAGES)})")
    if STAGES.index(first) > STAGES.index(last):
        raise CosyError(f"--from {first} comes after --to {last}")
    out = Path(out).resolve()
    if out.exists() and not out.is_dir():
        raise CosyError("exists and is not a folder", path=out)
    manifest_path = out / MANIFEST
    if out.is_dir() and any(out.iterdir()) and not manifest_path.is_file():
        raise CosyError("exists, is not empty and is not a cosy run folder (no run.json)", path=out)
    split, rig_sensor, grouping = plan_groups(BopDataset(dataset, split), groups)
    overrides = {k: dict(v) for k, v in (overrides or {}).items()}
    if grouping is not None:
        overrides.setdefault("match", {})["groups"] = grouping
    if rig_sensor is not None:
        overrides.setdefault("match", {})["known_cameras"] = True
    ds = BopDataset(dataset, split)
    dataset = Path(dataset).resolve()
    scene_ids = ds.select_scenes(scene_ids)
    for f in (detections, candidates, model, coco_images, scorer_model):
        if f is not None and not Path(f).is_file():
            raise CosyError("file not found", path=f)
    confs = resolve_confs(config, **(overrides or {}))
    models_dir = Path(models_dir).resolve() if models_dir is not None else ds.models_dir.resolve()
    source = ("candidates" if candidates is not None else "json" if detections is not None
              else "gt" if from_gt else "model")
    source_file = candidates or detections or model
    if source == "model" and source_file is None:
        from ..detection.stage import SHIPPED_DETECTOR

        if not SHIPPED_DETECTOR.is_file():
            raise CosyError(f"no detector model was given (--model) and none is shipped (expected {SHIPPED_DETECTOR}); "
                            "use --from-gt, --detections FILE or --candidates FILE, or train one with "
                            "`cosy train detector` + `cosy export`")
        source_file = SHIPPED_DETECTOR
    source_file = None if source_file is None else str(Path(source_file).resolve())
    config_name = config if isinstance(config, str) else "custom"
    has_gt = all(ds.has_gt(s) for s in scene_ids)
    if STAGES.index(first) > STAGES.index("refine") and not (out / "refine" / "predictions.csv").is_file():
        raise CosyError(f"--from {first}: no refine/predictions.csv in the run folder yet", path=out)

    out.mkdir(parents=True, exist_ok=True)
    old = json.loads(manifest_path.read_text()) if manifest_path.is_file() else {}
    manifest = {"format": RUN_FORMAT[0], "version": RUN_FORMAT[1], "code_version": units.code_version(),
                "dataset": str(dataset), "split": split, "scene_ids": scene_ids, "config": config_name,
                "confs": confs, "source": {"kind": source, "file": source_file},
                "models_dir": str(models_dir), "status": "running", "stages": old.get("stages", {})}
    if rig_sensor is not None:
        manifest["rig"] = {"sensors": ds.sensors, "eval_sensor": rig_sensor, "groups": confs["match"]["groups"],
                           "view_id": "im_id x number of sensors + index of the sensor"}
    atomic.write_json(manifest_path, manifest)
    force = set(STAGES) if overwrite else set()

    # templates once, before the scenes run in parallel
    templates_dir = Path(templates_dir).resolve() if templates_dir is not None else out / "templates"
    if source != "candidates" and runs("estimate", first, last):
        from ..singleview import estimate_stage

        if estimate_stage.uses_templates(confs["estimate"]):
            estimate_stage.ensure_templates(models_dir, templates_dir, log=lambda m: None)

    tasks = [{"run_dir": str(out), "dataset": str(dataset), "split": split, "scene_id": s, "confs": confs,
              "source": source, "source_file": source_file,
              "coco_images": None if coco_images is None else str(Path(coco_images).resolve()),
              "models_dir": str(models_dir), "templates_dir": str(templates_dir), "first": first,
              "scorer_model": None if scorer_model is None else str(Path(scorer_model).resolve()),
              "last": min(last, "refine", key=STAGES.index), "force": sorted(force)}
             for s in scene_ids]
    stage_times: dict[str, dict] = {}
    if STAGES.index(first) <= STAGES.index("refine"):
        log(f"run: {len(tasks)} scene(s) of {ds.split_dir}, config {config_name}, "
            f"{'dask ' + dask_scheduler if dask_scheduler else f'{workers} worker(s)'} -> {out}")
        results = _execute(tasks, workers, dask_scheduler, progress)
        console.flush()  # the scene stages' tolerated input problems, one summary per kind
        for stage in SCENE_STAGES:
            rs = [r["units"][stage] for r in results if stage in r["units"]]
            if rs:
                stage_times[stage] = {"status": "done" if any(r["ran"] for r in rs) else "skipped",
                                      "scenes_run": sum(r["ran"] for r in rs), "scenes": len(rs),
                                      "time_s": round(sum(r["time_s"] for r in rs), 3)}

    # merge the scenes into the run-wide files
    sdirs = [scene_dir(out, s) for s in scene_ids]
    merged = []
    for rel, dst, fn in (("detections.json", out / "detect" / "detections.json", merge_detections),
                         ("candidates.csv", out / "estimate" / "candidates.csv", merge_csv),
                         ("refine/predictions.csv", out / "refine" / "predictions.csv",
                          lambda parts, dst: merge_csv(parts, dst, sidecar_manifest=False)),
                         ("refine/scene.json", out / "refine" / "scene.json", merge_scene_json)):
        parts = [d / rel for d in sdirs]
        if all(p.is_file() for p in parts) and parts:
            fn(parts, dst)
            merged.append(str(dst.relative_to(out)))
    if {"refine/predictions.csv", "refine/scene.json"} <= set(merged):  # checked by evaluate
        integrity.write_folder_manifest(out / "refine", "cosy run", ("scene.json", "predictions.csv"))
    eval_split, eval_files = split, {"single_view": (out / "estimate" / "candidates.csv", None),
                                     "multi_view": (out / "refine" / "predictions.csv", out / "refine" / "scene.json")}
    if rig_sensor is not None:  # the rig views of the evaluation sensor, as that sensor's images
        eval_split = with_sensor(ds.split, rig_sensor)
        for name, rel in (("single_view", "estimate/candidates.csv"), ("multi_view", "refine/predictions.csv")):
            src = out / rel
            dst = src.with_name(f"{src.stem}_{rig_sensor}.csv")
            if src.is_file():
                write_sensor_results(ds, src, rig_sensor, dst)
                merged.append(str(dst.relative_to(out)))
            eval_files[name] = (dst, None)
    single = single_view_counts(sdirs)
    if single["groups"]:
        log(f"run: {single['groups']} single-view group(s) of {single['groups_total']} "
            f"(scenes {', '.join(map(str, single['scene_ids']))}): candidates passed through as predictions")

    evals = {}
    if runs("evaluate", first, last):
        if not has_gt:
            log("run: the split has no GT for every scene; evaluate skipped")
            stage_times["evaluate"] = {"status": "not run (no GT)", "time_s": 0.0}
        else:
            from ..evaluation import evaluate_stage

            t_ev, ran_any = 0.0, False
            for name, (pred, sj) in eval_files.items():
                if not pred.is_file():
                    continue
                key = units.unit_key("evaluate", confs["evaluate"], {
                    "predictions": _digest_of(pred), "scene_json": _digest_of(sj), "scenes": scene_ids,
                    "dataset": str(dataset), "split": eval_split})
                ran, dt = units.run_unit(out / "evaluate", name, key, [name], lambda: evaluate_stage.main(
                    confs["evaluate"], dataset, eval_split, pred, out / "evaluate" / name, overwrite=True, scene_json=sj,
                    models_dir=models_dir, scene_ids=scene_ids, log=lambda m: None, progress=progress),
                    "evaluate" in force)
                t_ev += dt
                ran_any |= ran
                evals[name] = json.loads((out / "evaluate" / name / "scores.json").read_text())
            stage_times["evaluate"] = {"status": "done" if ran_any else "skipped", "time_s": round(t_ev, 3)}
            console.flush()

    if runs("viz", first, last):
        t0 = time.perf_counter()
        try:
            from .. import viz
        except ImportError:
            viz = None
        if viz is not None and hasattr(viz, "main"):
            stage_times["viz"] = {"status": "done", "time_s": 0.0}
            preview = {**manifest, "stages": {**manifest["stages"], **stage_times}, "status": "done"}
            r = viz.main(out, overwrite="viz" in force, log=lambda m: None, progress=progress, manifest=preview)
            stage_times["viz"] = {"status": "done" if r.get("made") else "skipped",
                                  "time_s": round(time.perf_counter() - t0, 3)}

    manifest["stages"] = {**manifest["stages"], **stage_times}
    manifest["merged"] = merged
    manifest["single_view"] = single
    manifest["metrics"] = {name: {**{k: s.get(k) for k in SUMMARY_METRICS if k in s},
                                  **({"bop19_ci": s["bop19_ci"]} if s.get("bop19_ci") else {})}
                           for name, s in evals.items()}
    manifest["status"] = "done"
    manifest["time_s"] = round(time.perf_counter() - t_start, 3)
    atomic.write_json(manifest_path, manifest)
    console.flush()
    for line in summary_lines(manifest, out):
        log(line)
    return manifest


SUMMARY_METRICS = ("bop19_average_recall", "bop19_average_recall_vsd", "bop19_average_recall_mssd",
                   "bop19_average_recall_mspd", "bop19_average_recall_mssd_mspd", "auc_adds", "recall_adds_0.1d")


def summary_lines(manifest: dict, out: Path) -> list[str]:
    """The terminal summary: stages (status, time), what the run wrote where, and last the metrics
    table, single view vs multi-view (a log of the run ends with its results)."""
    lines = ["", f"{'stage':<10} {'status':<18} {'time':>9}"]
    for stage in STAGES:
        st = manifest["stages"].get(stage)
        if st:
            n = f" ({st['scenes_run']}/{st['scenes']} scenes)" if "scenes" in st else ""
            lines.append(f"{stage:<10} {st['status'] + n:<18} {st['time_s']:>8.1f}s")
    lines += ["", wrote_line(out, (manifest.get("rig") or {}).get("eval_sensor"))]
    sv = manifest.get("single_view") or {}
    if sv.get("groups"):
        lines.append(f"single view: {sv['groups']} of {sv['groups_total']} group(s) had one view "
                     "(their candidates passed through as predictions)")
    m = manifest.get("metrics") or {}
    if m:
        names = list(m)
        lines += ["", f"{'metric':<32}" + "".join(f"{n:>13}" for n in names)]
        for k in SUMMARY_METRICS:
            vals = [m[n].get(k) for n in names]
            if any(v is not None for v in vals):
                lines.append(f"{k:<32}" + "".join(f"{v:>13.3f}" if v is not None else f"{'-':>13}" for v in vals))
                cis = [(m[n].get("bop19_ci") or {}) for n in names]
                if k in ("bop19_average_recall", "bop19_average_recall_mssd_mspd") and any(c.get(k) for c in cis):
                    first = next(c for c in cis if c.get(k))
                    label = f"  {first['level'] * 100:.0f} % interval ({first['unit']}s)"
                    lines.append(f"{label:<32}" + "".join(
                        f"{f'{c[k][0]:.3f}-{c[k][1]:.3f}' if c.get(k) else '-':>13}" for c in cis))
    return lines


def wrote_line(out: Path, sensor: str | None = None) -> str:
    """What the run wrote where (the final predictions, the report): the line after its stages.
    ``sensor``: a rig run's evaluation sensor (its final predictions are that sensor's)."""
    final = f"refine/predictions_{sensor}.csv" if sensor else "refine/predictions.csv"
    made = [rel for rel in (final, "report.html") if (out / rel).is_file()]
    return (f"run: wrote {out}" + (f" (final predictions: {made[0]}" + "".join(f", {m}" for m in made[1:]) + ")"
                                   if final in made else f" ({', '.join(made)})" if made else "")
            + "; run.json lists every stage")
