"""Stage 3 for any occupancy function: evaluate it over the scanned region and mesh it.

The grid covers everything the probe saw (:func:`scan_grid`, voxel :func:`scan_voxel_mm`); only
its tiles that some frame's field of view reaches are evaluated, coarse to fine, and the
surface is extracted from those tiles (:func:`mesh_occupancy`). UltrON, its ablation,
fine-tuning and ON mesh their networks this way; compounding meshes its own label volume.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ultron.data.dataset import SweepDataset
from ultron.data.geometry import field_of_view_bounds_mm, median_frame_gap_mm
from ultron.data.resolution import resolved_spacing_mm
from ultron.device import evaluation_chunk
from ultron.errors import argument_error
from ultron.mesh.extract import ExtractionConfig, extract_surface_tiles
from ultron.mesh.grid import GridSpec, field_of_view_volume_mm3, meshing_voxel_mm
from ultron.mesh.tiles import evaluate_tiles, field_of_view_tiles, tile_for_factor
from ultron.timing import StageTimer


@dataclass(frozen=True)
class MeshingConfig:
    """How an occupancy function is meshed (:func:`mesh_occupancy`): the voxel (None: the
    scan grid's, :func:`scan_grid`), the coarse-to-fine evaluation's factor, the points per
    evaluation chunk on a CPU and the iso-surface extraction. UltrON's, its ablation's,
    fine-tuning's and ON's."""

    voxel_mm: float | None = None
    coarse_factor: int = 2
    chunk_points: int = 65_536
    extraction: ExtractionConfig = field(default_factory=ExtractionConfig)

    def __post_init__(self) -> None:
        if self.voxel_mm is not None and not self.voxel_mm > 0:
            raise argument_error("voxel_mm", f"expected > 0, got {self.voxel_mm}")
        if not isinstance(self.coarse_factor, int) or self.coarse_factor < 1:
            raise argument_error(
                "coarse_factor", f"expected a positive integer, got {self.coarse_factor!r}"
            )
        if isinstance(self.chunk_points, bool) or not isinstance(self.chunk_points, int):
            raise argument_error("chunk_points", f"expected an integer, got {self.chunk_points!r}")
        if self.chunk_points < 1:
            raise argument_error("chunk_points", f"expected ≥ 1, got {self.chunk_points}")


def elevation_half_thickness_mm(dataset: SweepDataset, voxel_mm: float) -> float:
    """Half-thickness of the slab each frame is taken to image: 0.75 × the largest median gap
    between consecutive frames of a sweep (so that neighbouring slabs overlap), ≥ one voxel."""
    gaps = [median_frame_gap_mm(s.probe_to_world) for s in dataset.sweeps if s.n_frames > 1]
    return max(0.75 * max(gaps, default=0.0), voxel_mm)


def scan_voxel_mm(dataset: SweepDataset, voxel_mm: float | None) -> float:
    """The meshing voxel of :func:`scan_grid`: ``voxel_mm`` when given, else the finer pixel
    spacing, grown where the field of view (:func:`~ultron.mesh.grid.field_of_view_volume_mm3`)
    would hold more than :data:`~ultron.mesh.grid.MAX_REGION_VOXELS` voxels of it
    (:func:`~ultron.mesh.grid.meshing_voxel_mm`)."""
    if voxel_mm:
        return voxel_mm
    half = elevation_half_thickness_mm(dataset, 0.0)
    region = field_of_view_volume_mm3(dataset.all_poses(), dataset.probe, half)
    return meshing_voxel_mm(dataset.probe, None, region, finest_mm=resolved_spacing_mm(dataset))


def scan_grid(dataset: SweepDataset, voxel_mm: float | None) -> GridSpec:
    """The meshing grid over everything the probe saw, voxel :func:`scan_voxel_mm`. Only its
    tiles that the field of view reaches are evaluated (:func:`mesh_occupancy`)."""
    bounds = field_of_view_bounds_mm(dataset.all_poses(), dataset.probe).numpy()
    return GridSpec.from_bounds(bounds, scan_voxel_mm(dataset, voxel_mm))


def mesh_occupancy(
    fn, dataset: SweepDataset, config: MeshingConfig, timer: StageTimer, device=None
) -> tuple:
    """Evaluate ``fn`` on the scan grid inside the field of view and extract the surface;
    returns (mesh, occupancy volume, the volume's grid). ``device``: where ``fn`` computes,
    which sets the evaluation chunk (:func:`~ultron.device.evaluation_chunk` of
    ``config.chunk_points``).

    The grid is worked in tiles (:mod:`ultron.mesh.tiles`): the field-of-view mask is
    rasterised on the coarse grid of the coarse-to-fine evaluation
    (:func:`~ultron.mesh.grid.evaluate_coarse_to_fine`, so it is exact to one coarse voxel),
    kept only in the tiles some frame reaches, and only those tiles (with a one-tile rim) are
    evaluated and binarised; the surface is extracted from the tiles
    (:func:`~ultron.mesh.extract.extract_surface_tiles`). Mesh and volume equal those of the
    dense grid (for a power-of-two coarse factor, bit for bit), in memory that grows with the
    field of view, not its bounding box. The volume is the occupancy at the meshing voxel up to
    :data:`~ultron.mesh.tiles.MAX_VOLUME_VOXELS` voxels, beyond that at a power-of-two
    multiple of it (block means; its grid says which), zero outside the field of view.
    """
    grid = scan_grid(dataset, config.voxel_mm)
    factor = config.coarse_factor
    tile = tile_for_factor(factor)
    with timer.stage("mesh_fov_mask"):
        mask = field_of_view_tiles(
            grid.coarsened(factor),
            dataset.all_poses(),
            dataset.probe,
            elevation_half_thickness_mm(dataset, grid.voxel_mm),
            tile // factor,
        )
    with timer.stage("mesh_evaluate"):
        evaluated = evaluate_tiles(
            fn, grid, config.extraction.threshold, factor, mask, tile,
            evaluation_chunk(device, config.chunk_points), advance=timer.counter("tiles"),
        )  # fmt: skip
    with timer.stage("mesh_extract"):
        mesh = extract_surface_tiles(
            evaluated.tiles, grid, config.extraction, timer.counter("smoothing iterations")
        )
    return mesh, evaluated.volume.values, evaluated.volume.grid
