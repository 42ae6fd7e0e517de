"""``cosy viz``: paper-style figures per group of views and the HTML report of a ``cosy run`` folder.

    from cosy_cli import viz
    summary = viz.main(run_dir)                    # RUN_DIR/figures/*.png + RUN_DIR/report.html

The run folder (written by ``cosy run``)::

    RUN_DIR/run.json                      {"format": "cosy-run", "dataset", "split", "scene_ids", "config",
                                           "confs", "code_version", "stages": {name: {status, time_s}}}
    RUN_DIR/scenes/SSSSSS/candidates.csv  single-view candidates (BOP results)
    RUN_DIR/scenes/SSSSSS/match/          cosy match output (groups.json, matches.csv, candidates.csv)
    RUN_DIR/scenes/SSSSSS/refine/         cosy refine output (scene.json, predictions.csv)
    RUN_DIR/evaluate/{single_view,multi_view}/scores.json, report.png   (when the dataset has GT)

Only dataset, split and scene_ids of run.json are required. A scene without refine output gets
row 1 (candidates) only; a scene without candidates yet is skipped; a run without evaluate
output gets a report without metrics. Figures already present are kept unless ``overwrite`` or
one of the scene's inputs is newer than the figure.

Outputs: ``OUT/scene_SSSSSS_group_GGG.png`` (OUT defaults to ``RUN_DIR/figures``),
``OUT/index.json`` (what each figure shows: views placed, objects, visible-mask IoU with GT,
time) and ``RUN_DIR/report.html``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from ..errors import CosyError
from ..pipeline.layout import MANIFEST
from .figures import MeshRenderer, group_figure, read_run, reprojection_ious, scene_group_ids, visible_mask_ious
from .report import write_report

__all__ = ["main", "group_figure", "write_report", "read_run", "reprojection_ious", "visible_mask_ious",
           "scene_group_ids", "figure_name"]

INDEX = "index.json"


def figure_name(scene_id: int, group_id: int) -> str:
    return f"scene_{int(scene_id):06d}_group_{int(group_id):03d}.png"


def _caption(s: int, g: int, info: dict | None) -> str:
    text = f"Scene {s}, group {g}"
    if not info:
        return text
    parts = [f"{info.get('views', '?')} views"]
    if "views_placed" in info and info.get("objects") is not None and info.get("refined", True):
        parts.append(f"{info['views_placed']} placed, {info['objects']} objects")
    parts.append(f"{info.get('candidates', '?')} candidates")
    if info.get("mask_iou_mean") is not None:
        parts.append(f"visible-mask IoU of the re-projected objects with GT: mean {info['mask_iou_mean']:.2f} "
                     f"over {info.get('mask_iou_n', '?')} GT instances")
    return text + ": " + ", ".join(parts) + "."


def _read_index(path: Path) -> dict:
    try:
        doc = json.loads(path.read_text())
        return doc if isinstance(doc, dict) else {}
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return {}


def main(run_dir: str | Path, out: str | Path | None = None, scene_ids=None, overwrite: bool = False, *,
         log=print, progress: bool = True, groups_per_scene: int | None = None, manifest: dict | None = None) -> dict:
    """Figures of every group of the run's scenes (or of ``scene_ids``) and ``RUN_DIR/report.html``.

    ``groups_per_scene``: draw only the first N groups of each scene (None: all; a figure takes
    about 2-3 s on a 2-core CPU, so cap it for datasets with hundreds of groups). ``manifest``: what
    the report shows as the run's settings and stage timings instead of ``RUN_DIR/run.json``
    (which must still exist and name the dataset).

    Returns {"figures": [paths of all figures in the report], "made", "kept", "failed": [messages],
    "report": path, "time_s", "figure_time_s": {name: seconds}, "mask_iou_mean": {name: IoU}}.
    A figure that cannot be made (e.g. an image file missing) is reported in "failed", logged
    and listed in the report's notes; the others are still made. Bad input (not a run folder,
    a scene that is not in the run) raises :class:`CosyError`.
    """
    from ..io import atomic
    from ..io.dataset import BopDataset
    from ..objects.database import MeshFileError
    from . import figures as F

    t0 = time.perf_counter()
    run_dir = Path(run_dir)
    run = read_run(run_dir)
    all_ids = [int(s) for s in run["scene_ids"]]
    if scene_ids:
        ids = [int(s) for s in scene_ids]
        unknown = [s for s in ids if s not in all_ids]
        if unknown:
            shown = ", ".join(map(str, all_ids[:20])) + (" ..." if len(all_ids) > 20 else "")
            raise CosyError(f"scene {unknown[0]} is not a scene of this run (its scenes: {shown or 'none'})",
                            path=run_dir / MANIFEST, where="scene_ids")
    else:
        ids = all_ids
    out = Path(out) if out is not None else run_dir / "figures"
    index_path = out / INDEX
    index = _read_index(index_path)

    tasks, skipped_scenes, failed = [], [], []
    for s in ids:
        try:
            groups = scene_group_ids(run_dir, s)[:groups_per_scene]
        except CosyError as e:
            failed.append(f"scene {s}: {e}")
            log(f"viz: no figure for scene {s}: {e}")
            continue
        if not groups:
            skipped_scenes.append(s)
        tasks += [(s, g) for g in groups]
    if skipped_scenes:
        log(f"viz: nothing to draw for scene(s) {', '.join(map(str, skipped_scenes))} (no candidates)")

    made, kept = 0, 0
    times: dict[str, float] = {}
    ds = BopDataset(run["dataset"], run["split"])
    bar = None
    if progress and tasks:
        from ..console import progress as progress_bar

        bar = progress_bar(total=len(tasks), desc="viz", unit="figure")
    with MeshRenderer(ds) as mr:
        for s, g in tasks:
            name = figure_name(s, g)
            path = out / name
            newest = max((p.stat().st_mtime for p in F.input_files(run_dir, s)), default=0.0)
            if path.is_file() and not overwrite and path.stat().st_mtime >= newest and name in index:
                kept += 1
            else:
                info: dict = {}
                try:
                    group_figure(run_dir, s, g, path, renderer=mr, info=info)
                except MeshFileError:
                    raise  # a broken model file: every figure showing it would fail
                except CosyError as e:
                    failed.append(f"scene {s} group {g}: {e}")
                    log(f"viz: no figure for scene {s} group {g}: {e}")
                else:
                    made += 1
                    times[name] = round(info["time_s"], 3)
                    index[name] = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in info.items()
                                   if k != "ious"}
                    atomic.write_json(index_path, index)
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()

    # the report shows every figure of the run's scenes present in OUT (not only those made now)
    figs, captions = [], {}
    for s in all_ids:
        try:
            groups = scene_group_ids(run_dir, s)[:groups_per_scene]
        except CosyError:
            continue
        for g in groups:
            p = out / figure_name(s, g)
            if p.is_file():
                figs.append(p)
                captions[str(p)] = _caption(s, g, index.get(p.name))
    notes = [f"no figure for {m}" for m in failed]
    report = write_report(run_dir, figs, captions=captions, notes=notes, manifest=manifest)
    ious = {n: index[n].get("mask_iou_mean") for n in (p.name for p in figs)
            if n in index and index[n].get("mask_iou_mean") is not None}
    dt = time.perf_counter() - t0
    log(f"viz: {made} figure(s) made, {kept} kept" + (f", {len(failed)} failed" if failed else "")
        + (f" ({sum(times.values()) / max(made, 1):.1f} s per figure)" if made else "")
        + f"; report -> {report}")
    return {"figures": figs, "made": made, "kept": kept, "failed": failed, "report": report,
            "time_s": round(dt, 3), "figure_time_s": times, "mask_iou_mean": ious}
