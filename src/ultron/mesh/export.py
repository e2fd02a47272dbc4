"""Writing meshes (PLY, STL, OBJ) and occupancy volumes (NIfTI), atomically.

Coordinates: meshes are written in ultron's world mm. 3D Slicer reads PLY/STL/OBJ models as
LPS, while NIfTI is RAS by definition; the NIfTI affine is therefore the grid's world affine
with x and y negated (LPS → RAS), so that mesh and volume open aligned in Slicer. Reading the
volume back with nibabel gives RAS coordinates (−x, −y, z) of world points.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ultron import atomic
from ultron.errors import UltronInputError, argument_error
from ultron.mesh.grid import GridSpec

MESH_FORMATS = (".ply", ".stl", ".obj")
LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


def save_mesh(mesh, path: str | Path) -> Path:
    """Write ``mesh`` to ``path``; the format follows the suffix (.ply binary, .stl binary, .obj)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_FORMATS:
        raise argument_error("path", f"{path}: expected a suffix in {MESH_FORMATS}")
    if len(mesh.faces) == 0:
        raise UltronInputError(path, "mesh", "refusing to write an empty mesh")
    data = mesh.export(file_type=suffix[1:])
    atomic.write_bytes(path, data if isinstance(data, bytes) else data.encode("utf-8"))
    return path


def load_mesh(path: str | Path, allow_empty: bool = False):
    """Read a mesh file as one ``trimesh.Trimesh``; a missing, unreadable or empty file is an error."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise UltronInputError(path, "mesh", "file is missing")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for bad files
        raise UltronInputError(path, "mesh", f"not a readable mesh ({exc})") from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise UltronInputError(path, "mesh", f"expected a triangle mesh, got {type(mesh).__name__}")
    if not allow_empty and len(mesh.faces) == 0:
        raise UltronInputError(path, "mesh", "mesh is empty (no triangles)")
    if len(mesh.vertices) and not np.isfinite(mesh.vertices).all():
        raise UltronInputError(path, "mesh", "vertices contain NaN or inf")
    return mesh


def nifti_affine(grid: GridSpec) -> np.ndarray:
    """The NIfTI (RAS) affine of ``grid``: LPS_TO_RAS @ grid.affine."""
    return LPS_TO_RAS @ grid.affine


def save_volume_nifti(volume: np.ndarray, grid: GridSpec, path: str | Path) -> Path:
    """Write a float32 volume on ``grid`` as NIfTI-1 (``.nii`` or ``.nii.gz``), aligned for Slicer."""
    import nibabel as nib

    path = Path(path)
    if not (path.name.endswith(".nii") or path.name.endswith(".nii.gz")):
        raise argument_error("path", f"{path}: expected a .nii or .nii.gz file name")
    if volume.shape != grid.shape:
        raise argument_error("volume", f"expected shape {grid.shape}, got {volume.shape}")
    image = nib.Nifti1Image(np.asarray(volume, dtype=np.float32), nifti_affine(grid))
    image.header.set_xyzt_units("mm")
    image.set_qform(nifti_affine(grid), code=1)
    image.set_sform(nifti_affine(grid), code=1)
    data = image.to_bytes() if path.name.endswith(".nii") else _gzip(image.to_bytes())
    atomic.write_bytes(path, data)
    return path


def _gzip(data: bytes) -> bytes:
    import gzip

    return gzip.compress(data, compresslevel=6, mtime=0)
