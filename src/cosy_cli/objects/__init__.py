"""Object database: meshes, sampled points, diameters, symmetry sets, symmetry detection."""

from .database import (MeshFileError, ObjectDatabase, ObjectModel, check_mesh_arrays, check_ply_data, diameter_of,
                       load_mesh, model_info_from_mesh)
from .symmetries import (
    BOP_MAX_SYM_DISC_STEP, PAPER_CONTINUOUS_STEPS, continuous_steps_for_max_step, continuous_symmetry_transforms,
    symmetry_residuals, symmetry_set,
)

__all__ = [
    "ObjectDatabase", "ObjectModel", "diameter_of", "load_mesh", "model_info_from_mesh", "BOP_MAX_SYM_DISC_STEP",
    "MeshFileError", "check_mesh_arrays", "check_ply_data",
    "PAPER_CONTINUOUS_STEPS", "continuous_steps_for_max_step", "continuous_symmetry_transforms",
    "symmetry_residuals", "symmetry_set",
]
