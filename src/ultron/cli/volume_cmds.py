"""``ultron compound``: B-mode image compounding into a NIfTI volume, as PLUS does it."""

from __future__ import annotations

from pathlib import Path

from ultron.arguments import sweep_names
from ultron.cli.common import command, print_lines, stage_progress


@command(
    "dataset",
    aliases={"spacing_mm": "spacing", "max_memory_gib": "max_memory"},
    documented_by=(
        "ultron.mesh.image_compounding:ImageCompoundingConfig",
        "ultron.mesh.splat:SplatConfig",
    ),
)
def compound(
    dataset: Path,
    out: Path,
    spacing: float = 0.5,
    sweeps: str | None = None,
    interpolation: str = "nearest",
    reduce: str = "mean",
    fill_holes: int = 0,
    max_memory: float | None = None,
    threads: int | None = None,
) -> None:
    """Compound B-mode frames into a NIfTI volume (PLUS's volume reconstruction).

    Every pixel of the chosen sweeps is pasted into a grid over the pixels'
    bounding box (origin at its lowest corner, as PLUS places it) at --spacing
    mm; voxels no pixel reached read 0 unless --fill-holes fills them.

    Coordinates: ultron's world is read as LPS (as 3D Slicer reads ultron's
    meshes and PLUS's MetaImages); NIfTI is RAS, so the file's affine maps
    voxel (i, j, k) to (−x, −y, z) for world point (x, y, z): Slicer shows the
    volume where it shows the meshes.

    Args:
        dataset: Dataset directory (ultron-sweeps/1).
        out: Output volume, .nii.gz or .nii (written atomically).
        sweeps: Comma-separated sweeps to compound (default: all).
    """
    from ultron.mesh.image_compounding import ImageCompoundingConfig
    from ultron.mesh.splat import SplatConfig
    from ultron.pipeline.compound import compound_volume

    config = ImageCompoundingConfig(spacing, SplatConfig(interpolation, reduce), fill_holes)
    with stage_progress("compound", unit="frames") as report:
        summary = compound_volume(
            dataset, out, config, sweep_names(sweeps), max_memory, progress=report
        )
    print_lines(summary.lines())
