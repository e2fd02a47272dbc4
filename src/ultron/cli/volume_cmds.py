"""``ultron compound``: B-mode image compounding into a NIfTI volume, as PLUS does it."""

from __future__ import annotations

from pathlib import Path

import typer

from ultron.arguments import check_choice, check_range, sweep_names
from ultron.cli.common import apply_threads, command, print_lines


@command("dataset")
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
        spacing: Voxel size on all three axes, mm (PLUS: 0.5).
        sweeps: Comma-separated sweeps to compound (default: all).
        interpolation: nearest (a pixel fills its nearest voxel) or linear (its 8 neighbours,
            with trilinear weights).
        reduce: How a voxel combines its pixels: mean (weighted) or max.
        fill_holes: Fill empty voxels with PLUS's stick filler: N = the longest stick in
            voxels, both filled ends included (PLUS's StickLengthLimit; 0 = no filling).
        max_memory: GiB the volume may take, estimated before any work (default: the
            machine's memory, or the cgroup's or ulimit -v's limit).
    """
    apply_threads(threads)
    from ultron.mesh.image_compounding import ImageCompoundingConfig
    from ultron.mesh.splat import INTERPOLATIONS, REDUCTIONS, SplatConfig
    from ultron.pipeline.compound import compound_volume

    check_range("--spacing", spacing, 0.0, low_open=True)
    check_range("--fill-holes", fill_holes, 0)
    check_range("--max-memory", max_memory, 0.0, low_open=True)
    check_choice("--interpolation", interpolation, INTERPOLATIONS)
    check_choice("--reduce", reduce, REDUCTIONS)
    config = ImageCompoundingConfig(spacing, SplatConfig(interpolation, reduce), fill_holes)
    summary = compound_volume(dataset, out, config, sweep_names(sweeps), max_memory)
    print_lines(summary.lines())


def register(app: typer.Typer) -> None:
    app.command("compound")(compound)
