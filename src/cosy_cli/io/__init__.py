"""BOP files in and out: readers that validate, atomic writers, dataset layout."""

from .atomic import atomic_dir, atomic_path, write_bytes, write_json, write_text
from .bop import (
    CameraInfo, GtInfo, GtInstance, ModelInfo, PoseResults, SceneCamera, load_json, read_camera,
    read_detections, read_models_info, read_results, read_scene_camera, read_scene_gt,
    read_scene_gt_info, read_targets, write_camera, write_detections, write_models_info,
    write_results, write_scene_camera, write_scene_gt, write_scene_gt_info, write_targets,
)
from .dataset import BopDataset

__all__ = [
    "atomic_dir", "atomic_path", "write_bytes", "write_json", "write_text", "CameraInfo", "GtInfo",
    "GtInstance", "ModelInfo", "PoseResults", "SceneCamera", "load_json", "read_camera",
    "read_detections", "read_models_info", "read_results", "read_scene_camera", "read_scene_gt",
    "read_scene_gt_info", "read_targets", "write_camera", "write_detections", "write_models_info",
    "write_results", "write_scene_camera", "write_scene_gt", "write_scene_gt_info", "write_targets",
    "BopDataset",
]
