"""B-mode image compounding (``ultron compound``): every pixel of every frame pasted into a
voxel volume, as PLUS's volume reconstructor (``vtkPlusVolumeReconstructor``) does it.

* Pixels reach the world through the dataset's one pixel → world map
  (:func:`ultron.data.geometry.frame_pixels_world`: pixel (r, c) at probe point
  ((c − W/2)·W_mm/W, r·D_mm/H, 0), then the frame's probe-to-world pose).
* The grid is PLUS's: its origin is the lowest corner of the bounding box of every pixel centre
  of the chosen sweeps, its voxel ``spacing_mm`` on all three world axes, and it reaches at
  least to the box's highest corner (⌈extent / spacing⌉ + 1 voxels per axis, ≥ 2).
* Splatting (nearest or linear) and compounding (mean or max): :mod:`ultron.mesh.splat`, the
  implementation the label-compounding baseline uses too.
* Optional hole filling: PLUS's stick filler, :func:`ultron.mesh.holes.fill_holes_stick`.
* Frames are processed in chunks of about ``chunk_pixels`` pixels, so the working memory is the
  grid's (:func:`volume_bytes`) plus one chunk's.

Coordinates of the NIfTI file (:func:`save_compounded`): ultron's world is taken as LPS, as 3D
Slicer reads ultron's meshes; NIfTI is RAS by definition, so the affine is
diag(−1, −1, 1, 1) · grid affine (:func:`ultron.mesh.export.nifti_affine`): voxel (i, j, k)
holds world point (x, y, z) = origin + spacing·(i, j, k) and the file's affine maps it to RAS
(−x, −y, z). Slicer therefore shows the volume where it shows the meshes, and a MetaImage of
PLUS (whose Reference frame Slicer also reads as LPS) in the same place.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ultron.data.dataset import Sweep, SweepDataset
from ultron.data.geometry import field_of_view_bounds_mm, frame_pixels_world
from ultron.errors import UltronInputError, argument_error
from ultron.mesh.export import save_volume_nifti
from ultron.mesh.grid import GridSpec
from ultron.mesh.holes import fill_holes_stick
from ultron.mesh.splat import SplatConfig, Splatter

#: Working bytes per voxel: the splat's sums (16), the volume and masks (6), the stick
#: filler's arrays (28) and the NIfTI encoding (≈ 12).
BYTES_PER_VOXEL = 64
#: Pixels splatted per chunk of frames (bounds the per-chunk memory to ≈ 100 MB).
CHUNK_PIXELS = 1 << 21

#: Progress callback: (stage, done, total).
Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class ImageCompoundingConfig:
    """Settings of :func:`compound_images`.

    Attributes:
        spacing_mm: Voxel size on all three axes, mm (PLUS: 0.5).
        splat: How pixels are spread over voxels and combined (:class:`SplatConfig`).
        fill_holes: Fill empty voxels with PLUS's stick filler: N = the longest stick in
            voxels, both filled ends included (PLUS's StickLengthLimit; 0 = no filling).
        plus_weights: Weight the stick filler's ends as PLUS does.
        chunk_pixels: Pixels splatted at a time (bounds the working memory).
    """

    spacing_mm: float = 0.5
    splat: SplatConfig = field(default_factory=SplatConfig)
    fill_holes: int = 0
    plus_weights: bool = False
    chunk_pixels: int = CHUNK_PIXELS

    def __post_init__(self) -> None:
        if not (math.isfinite(self.spacing_mm) and self.spacing_mm > 0):
            raise argument_error(
                "spacing_mm", f"expected a finite number > 0, got {self.spacing_mm!r}"
            )
        if self.fill_holes != 0 and self.fill_holes < 3:
            raise argument_error(
                "fill_holes",
                f"expected 0 (off) or a stick length ≥ 3 voxels, got {self.fill_holes}",
            )
        if self.chunk_pixels < 1:
            raise argument_error("chunk_pixels", f"expected ≥ 1, got {self.chunk_pixels}")


@dataclass(frozen=True)
class CompoundedImage:
    """The compounded grey levels (float32, 0 in holes) on ``grid``; ``filled``: voxels some
    pixel reached; ``hole_filled``: voxels the hole filler gave a value."""

    volume: np.ndarray
    filled: np.ndarray
    hole_filled: np.ndarray
    grid: GridSpec


def select_sweeps(dataset: SweepDataset, names: Sequence[str] | None) -> list[Sweep]:
    """The sweeps called ``names`` (all when None), in the dataset's order; an unknown or
    repeated name is an error naming ``--sweeps``."""
    if names is None:
        return list(dataset.sweeps)
    available = [s.name for s in dataset.sweeps]
    unknown = [n for n in names if n not in available]
    if unknown or not names or len(set(names)) != len(names):
        problem = f"unknown sweep {unknown[0]!r}" if unknown else "empty or repeated names"
        raise argument_error("--sweeps", f"{problem}; available: {', '.join(available)}")
    return [s for s in dataset.sweeps if s.name in names]


def compounding_grid(dataset: SweepDataset, sweeps: Sequence[Sweep], spacing_mm: float) -> GridSpec:
    """PLUS's output grid over every pixel centre of ``sweeps`` (module doc)."""
    poses = [s.probe_to_world for s in sweeps]
    bounds = field_of_view_bounds_mm(poses, dataset.probe).numpy()
    extent = bounds[1] - bounds[0]
    shape = tuple(max(2, math.ceil(min(e / spacing_mm - 1e-9, 1e30)) + 1) for e in extent)
    return GridSpec(tuple(float(o) for o in bounds[0]), float(spacing_mm), shape)  # type: ignore[arg-type]


def volume_bytes(grid_shape: Sequence[int]) -> float:
    """Estimated peak working memory of compounding onto a grid of this shape, bytes."""
    return float(math.prod(int(n) for n in grid_shape)) * BYTES_PER_VOXEL


def check_volume_memory(grid: GridSpec, limit_bytes: float, limit_name: str) -> None:
    """Refuse a grid whose working memory exceeds the limit, naming ``--spacing``."""
    needed = volume_bytes(grid.shape)
    if needed > limit_bytes:
        sides = " × ".join(str(n) for n in grid.shape)
        raise argument_error(
            "--spacing",
            f"{grid.voxel_mm:g} mm makes a {sides} volume (≈ {needed / 1024**3:.3g} GiB to"
            f" compound), more than {limit_name}; choose a coarser spacing",
        )


def frame_samples(
    dataset: SweepDataset, sweeps: Sequence[Sweep], chunk_pixels: int = CHUNK_PIXELS
) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
    """(world points (M, 3) float64, grey levels (M,) float32) of every pixel, chunk by chunk
    of whole frames (about ``chunk_pixels`` pixels each)."""
    per_frame = dataset.probe.height_px * dataset.probe.width_px
    step = max(1, chunk_pixels // per_frame)
    for sweep in sweeps:
        poses = torch.as_tensor(sweep.probe_to_world, dtype=torch.float64)
        for start in range(0, sweep.n_frames, step):
            points = frame_pixels_world(poses[start : start + step], dataset.probe)
            values = torch.from_numpy(np.ascontiguousarray(sweep.images[start : start + step]))
            yield points.reshape(-1, 3), values.reshape(-1).to(torch.float32)


def compound_samples(
    samples: Iterable[tuple[torch.Tensor | np.ndarray, torch.Tensor | np.ndarray]],
    grid: GridSpec,
    config: ImageCompoundingConfig,
    progress: Progress | None = None,
    total: int = 0,
) -> CompoundedImage:
    """Splat every chunk of (points, values) onto ``grid`` and fill the holes. ``progress``,
    when given, is told ("splatting", samples splatted, ``total``) before the first chunk and
    after each, and ("filling holes", 0, 1) before the hole filler runs."""
    splatter = Splatter(grid, config.splat)
    done = 0
    if progress is not None:
        progress("splatting", 0, total)
    for points, values in samples:
        splatter.add(points, values)
        done += len(values)
        if progress is not None:
            progress("splatting", done, max(total, done))
    volume, filled = splatter.result()
    hole_filled = np.zeros_like(filled)
    if config.fill_holes:
        if progress is not None:
            progress("filling holes", 0, 1)
        volume, hole_filled = fill_holes_stick(
            volume, filled, config.fill_holes, plus_weights=config.plus_weights
        )
    return CompoundedImage(volume, filled, hole_filled, grid)


def compound_images(
    dataset: SweepDataset,
    config: ImageCompoundingConfig | None = None,
    sweep_names: Sequence[str] | None = None,
    grid: GridSpec | None = None,
    progress: Progress | None = None,
) -> CompoundedImage:
    """Compound the B-mode frames of ``sweep_names`` (all sweeps when None) onto ``grid``
    (default: :func:`compounding_grid` at ``config.spacing_mm``). ``progress``, when given, is
    told (stage, done, total) as :func:`compound_samples` says, counting frames."""
    config = config or ImageCompoundingConfig()
    sweeps = select_sweeps(dataset, sweep_names)
    grid = grid or compounding_grid(dataset, sweeps, config.spacing_mm)
    samples = frame_samples(dataset, sweeps, config.chunk_pixels)
    per_frame = dataset.probe.height_px * dataset.probe.width_px

    def in_frames(stage: str, done: int, total: int) -> None:
        if stage == "splatting":  # whole frames are splatted at a time
            done, total = done // per_frame, total // per_frame
        progress(stage, done, total)  # type: ignore[misc]

    total = sum(s.n_frames for s in sweeps) * per_frame
    return compound_samples(samples, grid, config, progress and in_frames, total)


def save_compounded(result: CompoundedImage, path: str | Path) -> Path:
    """Write the volume as NIfTI-1 (``.nii``/``.nii.gz``, float32 grey levels, RAS affine as in
    the module doc), atomically."""
    path = Path(path)
    if not (path.name.endswith(".nii") or path.name.endswith(".nii.gz")):
        raise UltronInputError(path, "--out", "expected a .nii or .nii.gz file name")
    return save_volume_nifti(result.volume, result.grid, path)
