"""``cosy estimate``: single-view object candidates from 2D detections (CosyPose stage 1)."""

from __future__ import annotations

from pathlib import Path

import click

from .. import console
from .common import resolve_scenes, scene_options, user_errors

COARSE_METHODS = ("network", "templates", "auto")
REFINER_METHODS = ("network", "none", "auto")


def _method_or_model(value: str | None, methods: tuple, network: str = "network"):
    """(method, model path): a method name, or an ONNX path (which means the network method)."""
    if value is None:
        return None, None
    if value in methods:
        return value, None
    return network, Path(value)


@click.command("estimate")
@scene_options
@click.option("--models", "models_dir", type=click.Path(path_type=Path), default=None,
              help="Models folder (obj_XXXXXX.ply in mm + models_info.json) [the dataset's models/].")
@click.option("--detections", type=click.Path(path_type=Path), default=None,
              help="BOP detections JSON (scene_id, image_id, category_id, score, bbox [x, y, w, h] px).")
@click.option("--from-gt", is_flag=True, help="Use the visible GT boxes (scene_gt_info bbox_visib, visib_fract >= 0.1).")
@click.option("--out", required=True, type=click.Path(path_type=Path),
              help="Candidates CSV (BOP results; also OUT.timing.csv and OUT.json).")
@click.option("--conf", default="default", show_default=True,
              help="default (best available: see --coarse/--refiner/--depth-refine), paper (coarse + refiner "
                   "networks, RGB only) or templates-icp (training-free).")
@click.option("--coarse", default=None,
              help="network | templates | auto, or a coarse ONNX model (implies network; also a CosyPose coarse "
                   "run directory or its `cosy export --run` ONNX) [auto: the shipped coarse model if any, else "
                   "templates].")
@click.option("--refiner", default=None,
              help="network | none | auto, or a refiner ONNX model (implies network; also a CosyPose refiner run "
                   "directory or its `cosy export --run` ONNX) [auto: the shipped refiner if any].")
@click.option("--depth-refine", type=click.Choice(["icp", "none", "auto"]), default=None,
              help="Point-to-plane ICP of each candidate on the depth image [auto: icp when the split has depth].")
@click.option("--refiner-iterations", type=click.IntRange(min=0), default=None, help="Refiner iterations [paper: 4].")
@click.option("--top-k", type=click.IntRange(min=1), default=None,
              help="Template hypotheses per detection kept after verification; with depth, each goes through ICP "
                   "and the best by depth and image agreement is kept [12].")
@click.option("--icp-screen", type=click.IntRange(min=0), default=None,
              help="With depth: the first N verified hypotheses get a short ICP and the --top-k best of them by "
                   "depth and image agreement the full one (0: the first --top-k directly) [32].")
@click.option("--hypotheses", type=click.IntRange(min=1), default=None,
              help="Poses per detection to write: the CSV keeps the best, the runners-up (best first, at most "
                   "--top-k) go to OUT's sidecar NAME.hypotheses.csv for `cosy match --hypotheses` [1: no sidecar].")
@click.option("--verify-top", default=None, metavar="N|auto",
              help="Templates: this many hypotheses per detection scored by rendering them against the image "
                   "(0: template score only) [auto: 64 with ICP on depth, else 48].")
@click.option("--rgb-refine", type=click.Choice(["search", "contour", "search+contour", "none", "auto"]), default=None,
              help="Templates: refine the best hypothesis on the image: a local search on the rendering score, "
                   "aligning its outline with the image's (contour), or both [auto: contour when no depth "
                   "refinement runs].")
@click.option("--box-scales", default=None, metavar="F1,F2,...",
              help="Templates: also verify each hypothesis at these factors of its distance, for boxes that fit "
                   "loosely (a detector's): 0.87,1,1.15 costs 1.7x the time [1: the distance the box's size says].")
@click.option("--masks", type=click.Choice(["auto", "none"]), default=None,
              help="Detections' segmentations (a `segmentation` RLE or polygons per detection, as in BOP's default "
                   "detections): auto uses them where present, in the verification of the template hypotheses "
                   "(each pose's silhouette against the mask); none: boxes only [auto].")
@click.option("--mask-band", type=click.IntRange(0, 32), default=None,
              help="Templates, detections with masks: half the verified hypotheses come from matching only the "
                   "image gradients within this many cells (of 64 across the box) of the mask, and its outline "
                   "[0: off].")
@click.option("--mask-weight", type=click.FloatRange(min=0), default=None,
              help="Weight of a pose silhouette's IoU with the detection's mask in the verification [2, chosen for "
                   "exact masks; masks from a classifier onboarded from meshes are less sure].")
@click.option("--templates-dir", type=click.Path(path_type=Path), default=None,
              help="Templates folder (built by `cosy templates` if missing) [OUT's folder/templates].")
@click.option("--scorer", "scorer_model", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="Learned hypothesis scorer (`cosy train scorer`; ONNX): orders the verified template hypotheses "
                   "instead of the training-free score [none].")
@click.option("--scorer-scope", type=click.Choice(["rank", "all"]), default=None,
              help="With --scorer: rank orders each detection's best --scorer-keep hypotheses by it, the refinement "
                   "stays training-free; all puts its prediction in every verification score (3-4x slower) [rank].")
@click.option("--scorer-keep", type=click.IntRange(1, 256), default=None,
              help="With --scorer (scope rank): hypotheses per detection it orders, the best of the training-free "
                   "first pass [16].")
@click.option("--score", "score", type=click.Choice(["detection", "pose"]), default=None,
              help="A candidate's score: the detection's, or the detection's x the verification score of its final "
                   "pose (the --scorer's probability, else the training-free score): with several boxes of one "
                   "object, the one whose pose fits the image ranks first [detection].")
@click.option("--max-per-object", type=click.IntRange(min=0), default=None,
              help="Keep the best N candidates of each object in each image, by their score (with --score pose: "
                   "the boxes whose poses fit the image best) [0: all].")
@click.option("--rebox", type=click.IntRange(0, 3), default=None,
              help="Passes that estimate each kept candidate again from the box its pose projects to and keep the "
                   "pose whose verification score is higher (loose detector boxes) [0: off].")
@click.option("--providers", type=click.Choice(["cpu", "cuda"]), default=None, help="onnxruntime provider [cpu].")
@click.option("--batch-size", type=click.IntRange(min=1), default=None, help="Crops per network call [32].")
@click.option("--overwrite", is_flag=True, help="Recompute even if OUT exists and is up to date.")
@user_errors
def estimate(scene, dataset, split, scene_ids, models_dir, detections, from_gt, out, conf, coarse, refiner,
             depth_refine, refiner_iterations, top_k, icp_screen, hypotheses, verify_top, rgb_refine, box_scales, masks,
             mask_band, mask_weight, templates_dir, scorer_model, scorer_scope, scorer_keep, score, max_per_object,
             rebox, providers,
             batch_size,
             overwrite) -> None:
    """Single-view 6D pose candidates for every detection (CosyPose stage 1).

    Writes one row per detection (label, the detector's score, T_cam_obj with t in mm) that
    `cosy match` reads. Skips when OUT is up to date (unless --overwrite).
    """
    from ..singleview import estimate_stage

    dataset, split, scene_ids = resolve_scenes(scene, dataset, split, scene_ids)
    coarse_method, coarse_model = _method_or_model(coarse, COARSE_METHODS)
    refiner_method, refiner_model = _method_or_model(refiner, REFINER_METHODS)
    c = estimate_stage.resolve_conf(conf, coarse=coarse_method, refiner=refiner_method, depth_refine=depth_refine,
                                    refiner_iterations=refiner_iterations, top_k=top_k, icp_screen=icp_screen,
                                    verify_top=verify_top,
                                    hypotheses=hypotheses,
                                    rgb_refine=rgb_refine, providers=providers, masks=masks, box_scales=box_scales,
                                    batch_size=batch_size, mask_weight=mask_weight, mask_band=mask_band,
                                    scorer_scope=scorer_scope, scorer_keep=scorer_keep, score=score,
                                    max_per_object=max_per_object, rebox=rebox)
    estimate_stage.main(c, dataset, split, out, overwrite=overwrite, scene_ids=scene_ids,
                        detections=detections, from_gt=from_gt, models_dir=models_dir, coarse_model=coarse_model,
                        refiner_model=refiner_model, templates_dir=templates_dir, scorer_model=scorer_model,
                        log=console.echo, progress=True)


COMMANDS = [estimate]
