"""Meshing: evaluate an occupancy callable on a grid, extract the surface, export it."""

from ultron.mesh.export import load_mesh, nifti_affine, save_mesh, save_volume_nifti
from ultron.mesh.extract import ExtractionConfig, NoSurfaceError, extract_surface
from ultron.mesh.grid import (
    GridSpec,
    evaluate_coarse_to_fine,
    evaluate_on_grid,
    field_of_view_mask,
)
from ultron.mesh.smoothing import smooth_constrained

__all__ = [
    "ExtractionConfig",
    "GridSpec",
    "NoSurfaceError",
    "evaluate_coarse_to_fine",
    "evaluate_on_grid",
    "extract_surface",
    "field_of_view_mask",
    "load_mesh",
    "nifti_affine",
    "save_mesh",
    "save_volume_nifti",
    "smooth_constrained",
]
