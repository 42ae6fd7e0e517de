"""Evaluation: pure pose-error functions (:mod:`.pose_error`), the BOP19 and CosyPose AUC protocols
(:mod:`.protocols`), BOP 2024 6D detection AP (:mod:`.bop24`), oracle poses for diagnosis (:mod:`.oracle`), the ``cosy evaluate`` stage
(:mod:`.evaluate_stage`) and its report (:mod:`.plots`).

    from cosy_cli.evaluation import add, adi, mssd, mspd, re, te, vsd   # mm / px / degrees
"""

from .pose_error import (add, adi, depth_to_distance, mspd, mssd, re, sphere_projections_overlap, spheres_overlap, te,
                         visibility_mask_est, visibility_mask_gt, vsd)
from .protocols import auc_posecnn, bop19_scores, auc_scores, greedy_match, camera_pose_errors

__all__ = ["add", "adi", "mssd", "mspd", "re", "te", "vsd", "depth_to_distance", "visibility_mask_gt",
           "visibility_mask_est", "sphere_projections_overlap", "spheres_overlap", "auc_posecnn", "bop19_scores",
           "auc_scores", "greedy_match", "camera_pose_errors"]
