"""Synthetic data: eight fixed procedural T-LESS-like objects and BOP datasets of them on a table.

    from cosy_cli.synth import generate_dataset, write_models
    generate_dataset("out/synth", scenes=3, views=8, objects_per_scene=6, seed=0)   # cosy synth
    write_models("out/synth")                                                      # models only

Lengths in mm, poses T_a_b (4x4), OpenCV cameras. See :mod:`.objects` and :mod:`.scenes`.
"""

from .objects import (
    OBJECT_IDS, OBJECTS, ObjectSpec, RestPose, eval_mesh, model_info, object_mesh, object_meshes, object_spec,
    resting_rotation, solid_mesh, write_models,
)
from .scenes import (
    DEPTH_SCALE, TABLE_ID, SceneLayout, SynthSummary, camera_matrix, generate_dataset, gt_infos, mask_bbox,
    place_objects, random_background, render_view, sample_cameras, sample_scene, scene_rng, table_mesh, write_split,
)


def main(out, scenes: int, views: int, objects_per_scene: int, *, seed: int = 0, width: int = 640, height: int = 480,
         split: str = "test", overwrite: bool = False, models_only: bool = False, progress: bool = True) -> SynthSummary:
    """Stage entry point of ``cosy synth`` (see :func:`generate_dataset`)."""
    return generate_dataset(out, scenes, views, objects_per_scene, seed=seed, width=width, height=height, split=split,
                            overwrite=overwrite, models_only=models_only, progress=progress)


__all__ = [
    "OBJECT_IDS", "OBJECTS", "ObjectSpec", "RestPose", "eval_mesh", "model_info", "object_mesh", "object_meshes",
    "object_spec", "resting_rotation", "solid_mesh", "write_models", "DEPTH_SCALE", "TABLE_ID", "SceneLayout",
    "SynthSummary", "camera_matrix", "generate_dataset", "gt_infos", "mask_bbox", "place_objects",
    "random_background", "render_view", "sample_cameras", "sample_scene", "scene_rng", "table_mesh", "write_split",
    "main",
]
