"""Poses, rotations, projection, crops and symmetric distances: small pure batched functions.

numpy versions live in ``poses``, ``rotations``, ``camera`` and ``distances``; torch versions
for networks and optimisers in ``torch_ops``.
"""

from .camera import (
    T_GL_CV, backproject_depth, crop_affine, crop_intrinsics, fit_box_to_aspect, project, projected_boxes,
)
from .distances import mean_point_distance, symmetric_distance, symmetric_distances_all
from .poses import compose, invert, is_rotation, look_at, make_pose, relative_pose_error, rotation_angle, transform_points
from .rotations import (
    axis_angle_to_matrix, matrix_to_axis_angle, matrix_to_quaternion, matrix_to_rot6d, quaternion_to_matrix,
    random_rotations, rot6d_to_matrix, rotation_about_axis,
)

__all__ = [
    "T_GL_CV", "backproject_depth", "crop_affine", "crop_intrinsics", "fit_box_to_aspect", "project",
    "projected_boxes",
    "mean_point_distance", "symmetric_distance", "symmetric_distances_all", "compose", "invert", "is_rotation",
    "look_at", "make_pose", "relative_pose_error", "rotation_angle", "transform_points", "axis_angle_to_matrix",
    "matrix_to_axis_angle", "matrix_to_quaternion", "matrix_to_rot6d", "quaternion_to_matrix", "random_rotations",
    "rot6d_to_matrix", "rotation_about_axis",
]
