"""``compound``: B-mode image compounding of a dataset into a NIfTI volume, as PLUS does it.

The algorithm (grid, splatting, hole filling, the file's coordinates) is
:mod:`ultron.mesh.image_compounding`; this module runs it on a dataset directory in the order
that refuses bad input before any work: the output name, the dataset, the chosen sweeps,
outlier poses and the grid's memory are checked before a frame is compounded, and the volume
is written atomically, so a refused or failed call leaves no partial file.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ultron.data.dataset import SweepDataset
from ultron.data.outliers import check_pose_outliers
from ultron.errors import UltronInputError, argument_error
from ultron.memory import memory_limit
from ultron.mesh.image_compounding import (
    CompoundedImage,
    ImageCompoundingConfig,
    Progress,
    check_volume_memory,
    compound_images,
    compounding_grid,
    save_compounded,
    select_sweeps,
)
from ultron.outputs import check_not_a_dataset_file, check_not_inside_output, check_output_file

#: File endings of a NIfTI volume.
NIFTI_SUFFIXES = (".nii", ".nii.gz")


@dataclass(frozen=True)
class CompoundSummary:
    """What :func:`compound_volume` made: the compounded volume (grid, filled shares), the
    settings, the file written, how many frames of how many sweeps went in, and the time the
    compounding and the writing took, seconds."""

    result: CompoundedImage
    config: ImageCompoundingConfig
    out: Path
    n_frames: int
    n_sweeps: int
    seconds: float

    def lines(self) -> list[str]:
        """What ``compound`` prints: settings, grid, filled shares, output."""
        result, config = self.result, self.config
        grid, n = result.grid, result.volume.size
        filled, holes = int(result.filled.sum()), int(result.hole_filled.sum())
        origin = ", ".join(f"{o:.3f}" for o in grid.origin_mm)
        filling = (
            f"stick hole filling ≤ {config.fill_holes} voxels"
            if config.fill_holes
            else "no filling"
        )
        return [
            f"compounded {self.n_frames} frames of {self.n_sweeps} sweep(s):"
            f" {config.splat.interpolation}, {config.splat.reduce}, {filling}",
            f"grid: {' × '.join(map(str, grid.shape))} voxels of {grid.voxel_mm:g} mm, origin"
            f" ({origin}) mm (world, LPS); NIfTI affine in RAS",
            f"filled by pixels: {filled / n:.1%} of the voxels; by hole filling: {holes / n:.1%}",
            f"wrote {self.out} in {self.seconds:.1f} s",
        ]


def check_nifti_out(out: str | Path, option: str = "--out") -> Path:
    """``out`` as a path: a ``.nii`` / ``.nii.gz`` file name (more than the ending alone) this
    process can write, checked before any work so a long run cannot fail at its last step; an
    error names ``option``."""
    path = Path(out)
    if not path.name.endswith(NIFTI_SUFFIXES) or path.name in NIFTI_SUFFIXES:
        raise UltronInputError(path, option, "expected a NIfTI file name ending in .nii or .nii.gz")
    check_output_file(path, option)
    check_not_inside_output(path, option)  # a run's own files are its run's to replace
    check_not_a_dataset_file(path, option)
    return path


def compound_volume(
    dataset_dir: str | Path,
    out: str | Path,
    config: ImageCompoundingConfig,
    sweep_names: Sequence[str] | None = None,
    max_memory_gib: float | None = None,
    progress: Progress | None = None,
) -> CompoundSummary:
    """Compound the B-mode frames of the sweeps ``sweep_names`` (all when None) of the dataset
    at ``dataset_dir`` onto PLUS's grid at ``config.spacing_mm`` and write the volume to
    ``out`` (NIfTI, atomically).

    Checks come first, in this order, each a one-line error naming its option: ``out``
    (``--out``), the dataset, the sweep names (``--sweeps``), outlier poses (which would make
    the grid span the outlier) and the grid's working memory against ``max_memory_gib``
    (GiB, ``--max-memory``) or this process's limit (:func:`ultron.memory.memory_limit`;
    ``--spacing``). ``progress``, when given, is told (stage, done, total) as the frames are
    splatted (:func:`~ultron.mesh.image_compounding.compound_images`) and as the volume is
    written ("writing", 0, 1)."""
    if not isinstance(config, ImageCompoundingConfig):
        raise argument_error(
            "config", f"expected an ImageCompoundingConfig, got {type(config).__name__}"
        )
    path = check_nifti_out(out)
    data = SweepDataset.load(dataset_dir)
    chosen = select_sweeps(data, sweep_names)
    check_pose_outliers(data, dataset_dir)
    grid = compounding_grid(data, chosen, config.spacing_mm)
    check_volume_memory(grid, *memory_limit(max_memory_gib))
    start = time.perf_counter()
    result = compound_images(data, config, [s.name for s in chosen], grid, progress)
    if progress is not None:
        progress("writing", 0, 1)
    save_compounded(result, path)
    return CompoundSummary(
        result=result,
        config=config,
        out=path,
        n_frames=sum(s.n_frames for s in chosen),
        n_sweeps=len(chosen),
        seconds=time.perf_counter() - start,
    )
