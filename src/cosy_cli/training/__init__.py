"""Training data for the render-and-compare networks (coarse and refiner), generated on the fly.

    from cosy_cli.training import SampleGenerator
    gen = SampleGenerator(meshes_or_db, kind="refiner", crop_size=(128, 96), seed=0)
    batch = gen.batch(32)   # observed / rendered crops, K_crop, T_input, T_gt, obj_id, ...

See :mod:`cosy_cli.training.data`.
"""

from .data import (  # noqa: F401
    CANONICAL_ROTATION, DEFAULT_PERTURBATION, Perturbation, SampleGenerator, TrainingStream, canonical_pose,
    depth_from_box, make_loader, perturb_poses, synthetic_source,
)

__all__ = ["SampleGenerator", "TrainingStream", "make_loader", "canonical_pose", "depth_from_box", "perturb_poses",
           "Perturbation", "DEFAULT_PERTURBATION", "CANONICAL_ROTATION", "synthetic_source"]
