"""``cosy detect``: 2D detections into a BOP detections file; ``cosy evaluate-detections``: their COCO AP."""

from __future__ import annotations

from pathlib import Path

import click

from .. import console
from .common import dataset_options, resolve_scenes, scene_options, user_errors


@click.command("detect")
@scene_options
@click.option("--out", required=True, type=click.Path(path_type=Path),
              help="Detections JSON (BOP format, what `cosy estimate --detections` reads; also OUT_STEM.meta.json).")
@click.option("--model", type=click.Path(path_type=Path), default=None,
              help="Exported detector ONNX [the detector shipped with cosy]. The default source.")
@click.option("--from-json", type=click.Path(path_type=Path), default=None,
              help="Import detections made by another tool: BOP detections ({scene_id, image_id, category_id, score, "
                   "bbox}) or COCO results ({image_id, category_id, bbox, score}; category_id = obj_id), checked "
                   "against the dataset.")
@click.option("--coco-images", type=click.Path(path_type=Path), default=None,
              help="With COCO results: the COCO dataset JSON whose images' file_name (…/SCENE_ID/rgb/IM_ID.png) "
                   "maps image_id to the BOP scene and image [without it: image_id = scene_id * 1000000 + im_id].")
@click.option("--from-gt", is_flag=True, help="The visible GT boxes (scene_gt_info bbox_visib), score 1.")
@click.option("--min-score", type=click.FloatRange(0, 1), default=None, help="Keep detections scored >= this [0.3].")
@click.option("--max-per-image", type=click.IntRange(min=1), default=None, help="At most N per image, best first [30].")
@click.option("--max-per-object", type=click.IntRange(0), default=None,
              help="At most this many detections per object and image, best first [0: no limit; 1 for datasets "
                   "with one instance of each object, such as LM-O or YCB-V].")
@click.option("--nms-iou", type=click.FloatRange(0, 1, min_open=True), default=None,
              help="Detector: per-class NMS IoU threshold [0.5].")
@click.option("--agnostic-nms-iou", type=click.FloatRange(0, 1, min_open=True), default=None,
              help="Detector: also suppress boxes of other labels overlapping a better one by more (one object "
                   "seen as two look-alikes) [1.0: off].")
@click.option("--min-visib", "min_visib", type=click.FloatRange(0, 1), default=None,
              help="--from-gt: instances at least this visible (visib_fract) [0.1, the BOP targets' threshold].")
@click.option("--providers", type=click.Choice(["cpu", "cuda"]), default=None, help="onnxruntime provider [cpu].")
@click.option("--classifier", default=None, metavar="auto|none|PATH",
              help="Detector: second-stage box classifier that relabels each box from a close-up crop and keeps "
                   "a second label when unsure (score x its probability): auto = the shipped one with the shipped "
                   "detector when it knows the dataset's objects, none, or an exported classifier ONNX [auto]. With "
                   "--from-gt or --from-json, a classifier PATH with a mask head adds its masks to the boxes.")
@click.option("--label-ratio", type=click.FloatRange(0, 1, min_open=True), default=None,
              help="With a classifier: also emit a box under every label whose probability is at least this x "
                   "the best label's [0.2].")
@click.option("--refine-boxes", type=click.IntRange(0, 5), default=None,
              help="With a classifier that has a box head (`cosy train classifier --preset real`): passes that "
                   "move each box onto its object, each from a crop of the moved box [1; 0: off].")
@click.option("--masks", type=click.Choice(["auto", "none"]), default=None,
              help="With a classifier that has a mask head (`cosy train classifier --preset real`): auto = each "
                   "detection gets its segmentation (RLE), which `cosy estimate` uses in its verification [auto].")
@click.option("--mask-threshold", type=click.FloatRange(0, 1, min_open=True, max_open=True), default=None,
              help="With --masks auto: a pixel is in the mask when the mask head's probability is at least this [0.5].")
@click.option("--mask-boxes/--no-mask-boxes", default=None,
              help="With masks: each box becomes its mask's bounding box (tighter than the box head's) [no].")
@click.option("--refine-top", type=click.IntRange(min=0), default=None,
              help="Classifier with a box head: only the boxes ranked this high after its first look are moved "
                   "(--refine-boxes passes, a look each); the others keep their box and first look [0: all].")
@click.option("--tiles", type=click.Choice(["0", "2", "3", "4"]), default=None,
              help="Detector: also run it on an N x N grid of overlapping windows of the image, each seen N times "
                   "larger (small and far objects), boxes merged by NMS [0: the whole image only].")
@click.option("--overwrite", is_flag=True, help="Recompute even if OUT exists and is up to date.")
@user_errors
def detect(scene, dataset, split, scene_ids, out, model, from_json, coco_images, from_gt, min_score, max_per_image,
           max_per_object, nms_iou, agnostic_nms_iou, min_visib, providers, classifier, label_ratio, refine_boxes,
           refine_top, masks, mask_threshold, mask_boxes, tiles, overwrite) -> None:
    """2D detections of the dataset's objects, one BOP detections file (CosyPose's first input).

    Sources: the shipped detector (default) or --model, --from-json (another tool's detections,
    BOP or COCO results format), or --from-gt. Boxes are [x, y, w, h] in pixels. Skips when OUT
    is up to date (unless --overwrite).
    """
    from ..detection import stage

    dataset, split, scene_ids = resolve_scenes(scene, dataset, split, scene_ids)
    c = stage.resolve_conf("default", min_score=min_score, max_per_image=max_per_image,
                           max_per_object=max_per_object, nms_iou=nms_iou,
                           agnostic_nms_iou=agnostic_nms_iou, min_visib_fract=min_visib, providers=providers,
                           classifier=classifier, label_ratio=label_ratio, refine_boxes=refine_boxes,
                           refine_top=refine_top, masks=masks, mask_threshold=mask_threshold, mask_boxes=mask_boxes,
                           tiles=None if tiles is None else int(tiles))
    stage.main(c, dataset, split, out, overwrite=overwrite, scene_ids=scene_ids, model=model, from_json=from_json,
               coco_images=coco_images, from_gt=from_gt, log=console.echo, progress=True)


@click.command("evaluate-detections")
@dataset_options("BOP dataset folder with ground truth (scene_gt.json, scene_gt_info.json).")
@click.option("--scene-id", "scene_ids", type=int, multiple=True, help="Only these scenes (repeatable) [all].")
@click.option("--detections", required=True, type=click.Path(path_type=Path),
              help="Detections JSON (BOP or COCO results format, as `cosy detect --from-json` reads).")
@click.option("--coco-images", type=click.Path(path_type=Path), default=None,
              help="With COCO results: the COCO dataset JSON mapping image ids (see `cosy detect`).")
@click.option("--out", required=True, type=click.Path(path_type=Path),
              help="Output folder: scores.json, confusion.csv.")
@click.option("--min-visib", "min_visib", type=click.FloatRange(0, 1), default=0.1, show_default=True,
              help="GT boxes of instances at least this visible; less visible ones are ignored (COCO crowd).")
@user_errors
def evaluate_detections(dataset, split, scene_ids, detections, coco_images, out, min_visib) -> None:
    """COCO AP, AP50, AP75 (pycocotools) of 2D detections against the visible GT boxes, per-object
    AP50, and the label confusion between objects (which GT objects are detected under another
    object's label)."""
    from ..evaluation import detection_ap

    detection_ap.main(dataset, split, detections, out, scene_ids=list(scene_ids) or None, coco_images=coco_images,
                      min_visib_fract=min_visib, log=console.echo)


COMMANDS = [detect, evaluate_detections]
