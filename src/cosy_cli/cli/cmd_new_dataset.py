"""``cosy new-dataset``: a BOP dataset from your own images, intrinsics, meshes (and 2D boxes)."""

from __future__ import annotations

import os
from pathlib import Path

import click

from .. import console
from .common import user_errors

_P = click.Path(path_type=Path)


@click.command("new-dataset")
@click.option("--images", "images_src", required=True, multiple=True, type=_P,
              help="Folder of images (png/jpg/tif...; not recursive) or one image file. Repeat it for more "
                   "scenes: scene ids --scene-id, +1, ...")
@click.option("--intrinsics", multiple=True, type=_P,
              help="JSON K (px): a 3x3 list, {\"cam_K\": [9]}, {\"fx\",\"fy\",\"cx\",\"cy\"}, {\"K\", \"resolution\": "
                   "[h, w]} (MegaPose camera_data.json), or an object keyed by image file name. Once for all, or "
                   "once per --images [default: IMAGE_STEM.json next to each image, else camera_data.json / "
                   "camera.json / intrinsics.json / K.json in the images folder].")
@click.option("--meshes", required=True, multiple=True, type=_P,
              help="Mesh files or folders (searched recursively; PLY, OBJ, OFF, STL, GLB...). Repeatable. Object "
                   "name = file stem, or the folder of a mesh alone in a subfolder (MegaPose meshes/LABEL/x.ply); "
                   "obj ids 1..N in name order.")
@click.option("--mesh-units", type=click.Choice(["mm", "cm", "m", "in"]), default="mm", show_default=True,
              help="Units of the mesh files (models are written in mm).")
@click.option("--depth", multiple=True, type=_P,
              help="Folder of depth images named like the images (16-bit png/tif, float tif or .npy); once per "
                   "--images.")
@click.option("--depth-scale", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Millimetres per stored depth unit (1: mm, 0.1: 0.1 mm, 1000: float metres). Required with "
                   "--depth.")
@click.option("--boxes", multiple=True, type=_P,
              help="2D boxes, once per --images: a JSON list of {\"label\": NAME, \"bbox_modal\": [x1, y1, x2, y2]} "
                   "(MegaPose object_data.json; bbox_xyxy, or bbox/bbox_xywh [x, y, w, h] also read), or an object "
                   "keyed by image file name. Written as OUT/detections.json (BOP detections).")
@click.option("--out", required=True, type=_P, help="The BOP dataset folder to write.")
@click.option("--split", default="test", show_default=True, help="Split folder name.")
@click.option("--scene-id", type=click.IntRange(min=0), default=1, show_default=True,
              help="Scene id of the first --images (the next ones +1).")
@click.option("--first-im-id", type=click.IntRange(min=0), default=0, show_default=True,
              help="BOP image id of each scene's first image.")
@click.option("--no-symmetries", is_flag=True,
              help="Do not propose symmetries (models_info.json then lists none; `cosy symmetries --write` adds them).")
@click.option("--symmetry-tolerance-mm", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Symmetry proposal tolerance, mm [1% of the diameter, in 0.5..2].")
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists.")
@user_errors
def new_dataset(images_src, intrinsics, meshes, mesh_units, depth, depth_scale, boxes, out, split, scene_id,
                first_im_id, no_symmetries, symmetry_tolerance_mm, overwrite) -> None:
    """Make a BOP dataset from your images, intrinsics and meshes (and 2D boxes), ready for
    `cosy validate`, `cosy templates`, `cosy estimate`.

    Writes camera.json, SPLIT/SCENE_ID/{rgb,depth,scene_camera.json,image_names.json},
    models/obj_XXXXXX.ply in mm (colours or texture kept), models/models_info.json (diameter,
    extents, proposed symmetries marked "symmetries_proposed"), models/models_names.json
    (obj_id -> name) and, with --boxes, detections.json. Example (MegaPose's examples):

    \b
      cosy new-dataset --images barbecue-sauce --meshes barbecue-sauce/meshes \\
          --boxes barbecue-sauce/inputs/object_data.json --out bbq_bop
    """
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from ..dataset_tools import new_dataset as stage

    c = stage.resolve_conf("default", split=split, scene_id=scene_id, first_im_id=first_im_id, mesh_units=mesh_units,
                           depth_scale=depth_scale, symmetries=not no_symmetries,
                           symmetry_tolerance_mm=symmetry_tolerance_mm)
    stage.main(c, list(images_src), list(meshes), out, overwrite=overwrite, intrinsics=list(intrinsics),
               depth=list(depth), boxes=list(boxes), log=console.echo, progress=True)


COMMANDS = [new_dataset]
