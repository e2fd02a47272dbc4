"""``ultron compound``: B-mode image compounding into a NIfTI volume, as PLUS does it."""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from ultron.cli.common import (
    ThreadsOption,
    apply_threads,
    check_choice,
    check_range,
    console,
    sweep_names,
    user_errors,
)

if TYPE_CHECKING:
    from ultron.mesh.image_compounding import CompoundedImage, ImageCompoundingConfig

_NIFTI_SUFFIXES = (".nii", ".nii.gz")


def _check_out(out: Path) -> None:
    """``--out`` must be a .nii / .nii.gz file name this process can write."""
    from ultron.errors import UltronInputError
    from ultron.outputs import check_output_file

    if not out.name.endswith(_NIFTI_SUFFIXES) or out.name in _NIFTI_SUFFIXES:
        raise UltronInputError(out, "--out", "expected a NIfTI file name ending in .nii or .nii.gz")
    check_output_file(out)


@user_errors
def compound(
    dataset: Annotated[Path, typer.Argument(help="Dataset directory (ultron-sweeps/1).")],
    out: Annotated[
        Path, typer.Option("--out", help="Output volume, .nii.gz or .nii (written atomically).")
    ],
    spacing: Annotated[
        float, typer.Option("--spacing", help="Voxel size on all three axes, mm (PLUS: 0.5).")
    ] = 0.5,
    sweeps: Annotated[
        str | None,
        typer.Option("--sweeps", help="Comma-separated sweeps to compound (default: all)."),
    ] = None,
    interpolation: Annotated[
        str,
        typer.Option(
            "--interpolation",
            help="nearest (a pixel fills its nearest voxel) or linear (its 8 neighbours, with"
            " trilinear weights).",
        ),
    ] = "nearest",
    reduce: Annotated[
        str,
        typer.Option("--reduce", help="How a voxel combines its pixels: mean (weighted) or max."),
    ] = "mean",
    fill_holes: Annotated[
        int,
        typer.Option(
            "--fill-holes",
            help="Fill empty voxels with PLUS's stick filler: N = the longest stick in voxels,"
            " both filled ends included (PLUS's StickLengthLimit; 0 = no filling).",
        ),
    ] = 0,
    threads: ThreadsOption = None,
) -> None:
    """Compound B-mode frames into a NIfTI volume (PLUS's volume reconstruction).

    Every pixel of the chosen sweeps is pasted into a grid over the pixels'
    bounding box (origin at its lowest corner, as PLUS places it) at --spacing
    mm; voxels no pixel reached read 0 unless --fill-holes fills them.

    Coordinates: ultron's world is read as LPS (as 3D Slicer reads ultron's
    meshes and PLUS's MetaImages); NIfTI is RAS, so the file's affine maps
    voxel (i, j, k) to (−x, −y, z) for world point (x, y, z): Slicer shows the
    volume where it shows the meshes.
    """
    apply_threads(threads)
    from ultron.data.dataset import SweepDataset
    from ultron.data.outliers import check_pose_outliers
    from ultron.mesh.image_compounding import (
        ImageCompoundingConfig,
        check_volume_memory,
        compound_images,
        compounding_grid,
        save_compounded,
        select_sweeps,
    )
    from ultron.mesh.splat import INTERPOLATIONS, REDUCTIONS, SplatConfig
    from ultron.pipeline.resources import memory_limit

    check_range("--spacing", spacing, 0.0, low_open=True)
    check_range("--fill-holes", fill_holes, 0)
    check_choice("--interpolation", interpolation, INTERPOLATIONS)
    check_choice("--reduce", reduce, REDUCTIONS)
    config = ImageCompoundingConfig(spacing, SplatConfig(interpolation, reduce), fill_holes)
    names = sweep_names(sweeps)
    _check_out(out)
    data = SweepDataset.load(dataset)
    chosen = select_sweeps(data, names)
    check_pose_outliers(data, dataset)
    grid = compounding_grid(data, chosen, spacing)
    check_volume_memory(grid, *memory_limit())
    start = time.perf_counter()
    result = compound_images(data, config, [s.name for s in chosen], grid)
    save_compounded(result, out)
    frames = sum(s.n_frames for s in chosen)
    for line in _summary(result, config, frames, len(chosen), out, time.perf_counter() - start):
        console.print(line, highlight=False, soft_wrap=True)


def _summary(
    result: CompoundedImage,
    config: ImageCompoundingConfig,
    n_frames: int,
    n_sweeps: int,
    out: Path,
    seconds: float,
) -> list[str]:
    """The lines ``compound`` prints: settings, grid, filled shares, output."""
    grid, n = result.grid, result.volume.size
    filled, holes = int(result.filled.sum()), int(result.hole_filled.sum())
    origin = ", ".join(f"{o:.3f}" for o in grid.origin_mm)
    filling = (
        f"stick hole filling ≤ {config.fill_holes} voxels" if config.fill_holes else "no filling"
    )
    return [
        f"compounded {n_frames} frames of {n_sweeps} sweep(s): {config.splat.interpolation},"
        f" {config.splat.reduce}, {filling}",
        f"grid: {' × '.join(map(str, grid.shape))} voxels of {grid.voxel_mm:g} mm, origin"
        f" ({origin}) mm (world, LPS); NIfTI affine in RAS",
        f"filled by pixels: {filled / n:.1%} of the voxels; by hole filling: {holes / n:.1%}",
        f"wrote {out} in {seconds:.1f} s",
    ]


def register(app: typer.Typer) -> None:
    app.command("compound")(compound)
