"""Resource guards: the grids a run will allocate, sized from the dataset and the options
before anything is allocated.

One outlier pose (a frame at +1e6 mm) or a tiny probe (0.5 mm wide: 5 µm pixels) makes the
meshing grid over "everything the probe saw" at the finer pixel spacing ask for petabytes, and
the acoustic field's finest planes for millions of nodes per side. :func:`check_run_resources`
refuses such a run at once with a one-line error saying which input made it so:

1. outlier poses (:func:`ultron.data.outliers.check_pose_outliers`), named by frame;
2. the meshing grid (:func:`ultron.mesh.occupancy_mesh.scan_grid`'s rule: the field of
   view's bounding box, padded by 2 voxels, at ``voxel_mm`` or the finer pixel spacing) at
   :data:`MESH_BYTES_PER_FOV_VOXEL` bytes per voxel of the tiles the field of view reaches,
   :data:`VOLUME_BYTES_PER_VOXEL` per voxel of the occupancy volume and
   :data:`MESH_FIXED_BYTES` — the coarse-to-fine evaluation's float32
   volumes, the masks, marching cubes and the constrained smoothing's arrays (the demo's
   estimate beside its measured peak:
   docs/decisions.md#resource-guards-memory-estimates-pipelineresourcespy) — against the
   memory limit; label compounding, which meshes the labelled bone's box instead, by
   :func:`check_compounding_grid` once its frames are chosen (:func:`compounding_memory`);
3. for a field that will be fitted (:func:`field_fit_memory`): the grid backend's planes
   (finest cell = pixel spacing at the fit resolution; at most ``fields.grid.MAX_RESOLUTION``
   nodes per side) and its dense volume at :data:`FIELD_BYTES_PER_VALUE` bytes per value
   (weight, gradient, Adam's two moments), the frames at the fit resolution (float32, twice with the confidence
   prior's maps, plus the largest sweep's float32 copy while resampling), the larger of a
   training step's and a no-gradient render chunk's working memory (samples ×
   :data:`FIELD_TRAIN_BYTES_PER_SAMPLE` / :data:`FIELD_RENDER_BYTES_PER_SAMPLE`) and
   :data:`FIELD_FIXED_BYTES`. The process itself (Python, torch) is not counted.

The memory limit is ``--max-memory`` (GiB) where given, else this machine's memory (physical
memory, or the cgroup's limit where lower).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from ultron.data.dataset import ProbeGeometry, SweepDataset
from ultron.data.geometry import field_of_view_bounds_mm
from ultron.data.labels import (
    FrameSelection,
    bone_points_mm,
    chunk_pixels_bound,
    count_labelled_pixels,
)
from ultron.data.orientation import field_cube
from ultron.data.outliers import check_pose_outliers
from ultron.errors import UltronInputError
from ultron.memory import memory_limit
from ultron.mesh.compounding import CHUNK_PIXELS, CompoundingConfig, compounding_grid
from ultron.mesh.grid import GridSpec, grid_shape
from ultron.mesh.occupancy_mesh import (
    MeshingConfig,
    elevation_half_thickness_mm,
    scan_grid,
    scan_voxel_mm,
)
from ultron.mesh.tiles import MAX_VOLUME_VOXELS, reached_tiles, tile_for_factor, volume_factor
from ultron.models.fitted import RENDER_CHUNK_FRAMES
from ultron.train.field_fit import check_fit_frames
from ultron.train.fit_shape import resolve_fit_shape
from ultron.train.frames import resampled_probe

if TYPE_CHECKING:
    from ultron.train.field_config import FieldTrainConfig

#: Peak bytes per voxel of the tiles the field of view reaches (module doc, 2).
MESH_BYTES_PER_FOV_VOXEL = 16
#: Bytes per voxel of the occupancy volume: float32, and its copy and gzip while written.
VOLUME_BYTES_PER_VOXEL = 9
#: The meshing's working memory independent of the grid: a tile's arrays, the tables.
MESH_FIXED_BYTES = 256 * 1024**2
#: Grids larger than this are sized by their voxel count alone (no tile is counted).
MAX_COUNTED_VOXELS = 1e13
#: Label compounding's peak bytes per labelled pixel splatted at once (its indices, world
#: point, signed distance and splat weights: a run of frames of at most
#: ``mesh.compounding.CHUNK_PIXELS`` image pixels at a time) and per voxel of its grid while
#: compounding (splat sums, hole filling's distance transform) and while meshing (the volume,
#: tiles, smoothing band), rounded up from the real fibula's and the PLUS phantom's measured
#: peaks (module doc, 2).
COMPOUNDING_BYTES_PER_PIXEL = 150
COMPOUNDING_BYTES_PER_VOXEL = 60
COMPOUNDING_MESH_BYTES_PER_VOXEL = 85
#: Bytes per value of the field's planes while fitting: float32 weight, gradient, Adam m and v.
FIELD_BYTES_PER_VALUE = 16
#: A field fit's working memory per rendered sample, bytes, per backend: a training step keeps
#: the autograd tape of its patches' samples (frames_per_batch × patch_width × rows). The peak
#: RSS's measured growth per sample, rounded up (how it was measured:
#: docs/decisions.md#resource-guards-memory-estimates-pipelineresourcespy).
FIELD_TRAIN_BYTES_PER_SAMPLE = {"grid": 1024, "mlp": 10 * 1024}
#: … and the no-gradient renders of the held-out checks and θ statistics (RENDER_CHUNK_FRAMES
#: whole frames at once), measured the same way and rounded up.
FIELD_RENDER_BYTES_PER_SAMPLE = {"grid": 512, "mlp": 2560}
#: A field fit's working memory independent of its size (optimiser, allocator), from its
#: measurement above the import baseline (docs/decisions.md, same section).
FIELD_FIXED_BYTES = 64 * 1024**2
_GIB = 1024**3


def _size(n_bytes: float) -> str:
    for unit, scale in (("PiB", 1024**5), ("TiB", 1024**4), ("GiB", _GIB), ("MiB", 1024**2)):
        if n_bytes >= scale:
            return f"{n_bytes / scale:.3g} {unit}"
    return f"{n_bytes:.0f} B"


def describe_probe(probe: ProbeGeometry) -> str:
    """``38 mm wide / 96 columns = 0.396 mm, 70 mm deep / 128 rows = 0.547 mm``."""
    return (
        f"{probe.width_mm:g} mm wide / {probe.width_px} columns = {probe.lateral_spacing_mm:.3g}"
        f" mm, {probe.depth_mm:g} mm deep / {probe.height_px} rows ="
        f" {probe.axial_spacing_mm:.3g} mm"
    )


def meshing_grid_shape(
    dataset: SweepDataset, voxel_mm: float | None
) -> tuple[tuple[int, int, int], float, tuple[float, float, float]]:
    """The shape ``scan_grid(dataset, voxel_mm)`` will have, computed with Python integers
    (no overflow, nothing allocated), its voxel and the scanned extent in mm."""
    voxel = scan_voxel_mm(dataset, voxel_mm)
    bounds = field_of_view_bounds_mm(dataset.all_poses(), dataset.probe).numpy()
    extent = tuple(float(e) for e in bounds[1] - bounds[0])
    return grid_shape(bounds, voxel), voxel, extent  # type: ignore[return-value]


@dataclass(frozen=True)
class MeshingMemory:
    """The meshing's estimated memory (module doc, 2): the grid, the voxels of the tiles the
    field of view may reach, the occupancy volume's voxels, and bytes."""

    sides: tuple[int, int, int]
    voxel_mm: float
    extent_mm: tuple[float, float, float]
    fov_voxels: float
    volume_voxels: float

    @property
    def grid_voxels(self) -> float:
        return float(math.prod(self.sides))

    @property
    def total(self) -> float:
        return (
            self.fov_voxels * MESH_BYTES_PER_FOV_VOXEL
            + self.volume_voxels * VOLUME_BYTES_PER_VOXEL
            + MESH_FIXED_BYTES
        )

    def describe(self) -> str:
        """``31.8 M voxels (133 × 198 × 1206 of 0.396 mm over the 51 × 76 × 475 mm …)``."""
        return (
            f"the meshing grid has {self.grid_voxels:.3g} voxels"
            f" ({' × '.join(map(str, self.sides))} of {self.voxel_mm:.3g} mm over the"
            f" {' × '.join(f'{e:.4g}' for e in self.extent_mm)} mm the probe saw), of which"
            f" the field of view's tiles hold {self.fov_voxels:.3g}: ≈ {_size(self.total)}"
        )


def meshing_memory(dataset: SweepDataset, voxel_mm: float | None) -> MeshingMemory:
    """The memory of meshing ``dataset`` at ``voxel_mm`` (module doc, 2), before anything is
    allocated. The field of view's tiles are counted when the grid could be allocated at all
    (the grid's voxel count otherwise, Python integers)."""
    # the voxel once: with voxel_mm None it rasterises the field of view (≈ 0.7 s on a long sweep)
    sides, voxel, extent = meshing_grid_shape(dataset, scan_voxel_mm(dataset, voxel_mm))
    n_voxels = float(math.prod(sides))
    fov, volume = n_voxels, n_voxels
    if n_voxels <= MAX_COUNTED_VOXELS:
        grid = scan_grid(dataset, voxel)
        factor = MeshingConfig().coarse_factor
        tile = tile_for_factor(factor)
        half = elevation_half_thickness_mm(dataset, voxel)
        tiles = reached_tiles(grid, dataset.all_poses(), dataset.probe, half, tile, factor)
        fov = float(
            sum(math.prod(int(n) for n in _tile_sides(grid.shape, key, tile)) for key in tiles)
        )
        k = volume_factor(grid.shape, MAX_VOLUME_VOXELS)
        volume = float(math.prod(-(-n // k) for n in grid.shape))
    return MeshingMemory(sides, voxel, extent, fov, volume)


def compounding_memory(
    dataset: SweepDataset, selection: FrameSelection, config: CompoundingConfig
) -> tuple[float, GridSpec, int]:
    """Label compounding's estimated peak bytes (module doc, 2), its grid and the labelled
    pixels counted, from the selection's bone pixels alone (nothing grid-sized allocated)."""
    n_pixels = count_labelled_pixels(dataset, selection, config.outer_side_mm)
    grid = compounding_grid(dataset, bone_points_mm(dataset, selection), config)
    voxels = float(math.prod(grid.shape))
    # the pixels are splatted a run of frames at a time (compound_labels)
    at_once = min(n_pixels, chunk_pixels_bound(dataset, CHUNK_PIXELS))
    compounding = at_once * COMPOUNDING_BYTES_PER_PIXEL + voxels * COMPOUNDING_BYTES_PER_VOXEL
    meshing = voxels * COMPOUNDING_MESH_BYTES_PER_VOXEL
    return max(compounding, meshing) + MESH_FIXED_BYTES, grid, n_pixels


def check_compounding_grid(
    dataset: SweepDataset,
    selection: FrameSelection,
    config: CompoundingConfig,
    root: str | Path,
    max_memory_gib: float | None,
) -> None:
    """Refuse a compounding whose estimated memory (:func:`compounding_memory`) exceeds the
    limit, naming the grid and the labelled pixels."""
    total, grid, n_pixels = compounding_memory(dataset, selection, config)
    limit, limit_name = memory_limit(max_memory_gib)
    if total <= limit:
        return
    sides = " × ".join(map(str, grid.shape))
    raise UltronInputError(
        Path(root) / "dataset.json",
        "labels",
        f"compounding's meshing grid has {math.prod(grid.shape):.3g} voxels ({sides} of"
        f" {grid.voxel_mm:.3g} mm over the labelled bone's box) and {n_pixels:.3g} labelled"
        f" pixels: ≈ {_size(total)}, more than {limit_name}; label fewer frames"
        " (--label-fraction: a smaller bone box) or give it more memory",
    )


def _tile_sides(shape: tuple[int, int, int], key: tuple[int, int, int], tile: int) -> list[int]:
    return [min(tile, n - k * tile) for n, k in zip(shape, key, strict=True)]


def check_meshing_grid(
    dataset: SweepDataset, root: str | Path, voxel_mm: float | None, max_memory_gib: float | None
) -> None:
    """Refuse a meshing (module doc, 2) whose estimated memory exceeds the limit."""
    probe = dataset.probe
    memory = meshing_memory(dataset, voxel_mm)
    limit, limit_name = memory_limit(max_memory_gib)
    if memory.total <= limit:
        return
    if voxel_mm is None:
        where, field = Path(root) / "dataset.json", "probe"
        pixel_mm = min(probe.lateral_spacing_mm, probe.axial_spacing_mm)
        if memory.voxel_mm > pixel_mm * (1 + 1e-9):  # grown by the region rule or the speckle
            cause = (
                f"its voxel follows from the probe's finer pixel spacing ({describe_probe(probe)})"
                f", grown to {memory.voxel_mm:.3g} mm for the speckle's size and the region's"
                " (mesh.grid.meshing_voxel_mm); give it more memory"
            )
        else:
            cause = f"its voxel is the probe's finer pixel spacing ({describe_probe(probe)})"
    else:
        where, field, cause = "argument", "voxel_mm", f"its voxel is {voxel_mm:g} mm"
    raise UltronInputError(where, field, f"{memory.describe()}, more than {limit_name}; {cause}")


@dataclass(frozen=True)
class FieldFitMemory:
    """A field fit's estimated memory (bytes, module doc 3) and its grid's plane sides."""

    resolutions: tuple[int, ...]
    planes: float
    frames: float
    working: float
    fixed: float = FIELD_FIXED_BYTES
    #: Whether ``planes`` holds a dense volume's values too.
    volume: bool = False

    @property
    def total(self) -> float:
        return self.planes + self.frames + self.working + self.fixed

    def describe(self) -> str:
        """``planes of [237, 59] nodes per side and volume 21.2 MiB, frames 28.1 MiB, …, fixed
        64 MiB`` (the grid's values: its planes and, where it has one, its dense volume)."""
        planes = f"planes of {list(self.resolutions)} nodes per side" if self.resolutions else ""
        planes += " and volume" if planes and self.volume else ""
        parts = [(planes, self.planes), ("frames", self.frames)]
        parts += [("working memory", self.working), ("fixed", self.fixed)]
        return ", ".join(f"{name} {_size(n)}" for name, n in parts if name)


def field_fit_memory(dataset: SweepDataset, config: FieldTrainConfig) -> FieldFitMemory:
    """The memory a fit of ``config`` to ``dataset`` will take (module doc 3), from the
    dataset's shapes and the options alone. Raises the grid's :class:`UltronInputError` when
    its finest plane would exceed ``MAX_RESOLUTION`` nodes per side."""
    backend = config.field.backend
    config = resolve_fit_shape(config, dataset)
    probe = resampled_probe(dataset.probe, config.fit_shape)
    resolutions: tuple[int, ...] = ()
    values = 0
    if backend == "grid":
        cube, extent = field_cube(dataset.all_poses(), probe, config.orientation)
        pixel = min(probe.axial_spacing_mm, probe.lateral_spacing_mm)
        grid_config = config.field.grid.resolved(cube.half_extent_mm, pixel, extent)
        resolutions = grid_config.resolutions or ()
        values = grid_config.n_values()
    rows, cols = probe.image_shape
    native = max((s.n_frames for s in dataset.sweeps), default=0) * math.prod(
        dataset.probe.image_shape
    )
    maps = 2 if config.confidence_prior_weight > 0 else 1
    n_frames = sum(s.n_frames for s in dataset.sweeps)
    frames = 4.0 * (n_frames * rows * cols * maps + 2 * native)
    train = config.frames_per_batch * min(config.patch_width, cols) * rows
    working = max(
        float(train) * FIELD_TRAIN_BYTES_PER_SAMPLE[backend],
        float(RENDER_CHUNK_FRAMES * rows * cols) * FIELD_RENDER_BYTES_PER_SAMPLE[backend],
    )
    volume = backend == "grid" and grid_config.volume_nodes is not None
    grid_bytes = float(values) * FIELD_BYTES_PER_VALUE
    return FieldFitMemory(resolutions, grid_bytes, frames, working, volume=volume)


def check_field_grid(
    dataset: SweepDataset,
    root: str | Path,
    config: FieldTrainConfig,
    max_memory_gib: float | None,
) -> None:
    """Refuse a field fit of ``config`` whose grid planes (module doc, 3) exceed the backend's
    largest side, or whose estimated memory (:func:`field_fit_memory`) exceeds the limit."""
    config = resolve_fit_shape(config, dataset)
    probe = resampled_probe(dataset.probe, config.fit_shape)
    where = Path(root) / "dataset.json"
    cause = (
        f"the finest cell is the probe's finer pixel spacing at the fit resolution"
        f" ({describe_probe(probe)}); fit a field at a coarser --fit-shape with"
        " `ultron fit-field` and pass it with --field"
    )
    try:
        memory = field_fit_memory(dataset, config)
    except UltronInputError as exc:
        raise UltronInputError(where, "probe", f"acoustic field: {exc.problem}; {cause}") from None
    limit, limit_name = memory_limit(max_memory_gib)
    if memory.total <= limit:
        return
    if memory.planes < max(memory.frames, memory.working):
        n_frames = sum(s.n_frames for s in dataset.sweeps)
        cause = (
            f"{n_frames} frames of {probe.height_px} × {probe.width_px} px at the fit"
            " resolution; fit at a smaller --fit-shape"
        )
    raise UltronInputError(
        where, "probe", f"acoustic field: fitting it needs ≈ {_size(memory.total)}"
        f" ({memory.describe()}), more than {limit_name}; {cause}",
    )  # fmt: skip


#: The largest ratio between a probe's two pixel spacings (lateral / axial or its inverse) a run
#: accepts: scan-converted B-mode pixels are near square, RF-like ones ≈ 10 : 1; 0.17 µm by
#: 0.55 mm (a width typed in metres) is not a probe.
MAX_PIXEL_ASPECT = 100.0


def check_probe_aspect(dataset: SweepDataset, root: str | Path) -> None:
    """Refuse a probe whose pixel spacings differ by more than :data:`MAX_PIXEL_ASPECT`
    (a width or depth in the wrong unit), naming both spacings."""
    probe = dataset.probe
    lateral, axial = probe.lateral_spacing_mm, probe.axial_spacing_mm
    ratio = max(lateral / axial, axial / lateral)
    if ratio <= MAX_PIXEL_ASPECT:
        return
    raise UltronInputError(
        Path(root) / "dataset.json",
        "probe",
        f"its pixels are {ratio:.3g} times longer one way than the other ({describe_probe(probe)});"
        f" at most {MAX_PIXEL_ASPECT:g} is a probe: check width_mm and depth_mm (mm, not m or µm)",
    )


def check_run_resources(
    dataset: SweepDataset,
    root: str | Path,
    voxel_mm: float | None = None,
    mesh: bool = True,
    field_config: FieldTrainConfig | None = None,
    max_memory_gib: float | None = None,
) -> None:
    """Before any work: no outlier pose, the meshing grid (when ``mesh``: every method but
    RoCoSDF/UNSR, whose grid has a fixed resolution) and a field to fit (``field_config``,
    when one may be fitted) within the memory limit, the latter's frames no smaller than the
    loss's SSIM window, and a probe whose pixels are not absurdly elongated
    (:func:`check_probe_aspect`). ``root`` is the dataset directory, named in the errors."""
    check_probe_aspect(dataset, root)
    check_pose_outliers(dataset, root)
    if mesh:
        check_meshing_grid(dataset, root, voxel_mm, max_memory_gib)
    if field_config is not None:
        field_config = resolve_fit_shape(field_config, dataset)
        check_field_grid(dataset, root, field_config, max_memory_gib)
        check_fit_frames(dataset.probe, field_config, Path(root) / "dataset.json")
