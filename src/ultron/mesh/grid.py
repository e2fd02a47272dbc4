"""Regular sampling grids in world mm, chunked evaluation of a field on them, and the mask of
voxels that some frame actually imaged."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ultron.data.dataset import ProbeGeometry
from ultron.data.geometry import (
    as_bounds_mm,
    as_pose_tensor,
    field_of_view_bounds_mm,
    pixel_to_world,
)
from ultron.device import map_chunks
from ultron.errors import argument_error

PointsFn = Callable[[torch.Tensor], torch.Tensor]


#: The most voxels a meshed region gets at the default voxel (2²³ ≈ 8.4 M): a region that
#: would hold more at the finer pixel spacing gets a larger voxel (see :func:`meshing_voxel_mm`).
MAX_REGION_VOXELS = 2**23


def meshing_voxel_mm(
    probe: ProbeGeometry,
    voxel_mm: float | None,
    region_mm3: float | None = None,
    max_voxels: int = MAX_REGION_VOXELS,
    finest_mm: float | None = None,
) -> float:
    """The meshing voxel: ``voxel_mm`` when given; else s, the finest detail the frames carry
    (``finest_mm``, :func:`ultron.data.resolution.resolved_spacing_mm`: the probe's finer
    pixel spacing unless the pixels are finer than half the speckle grain; default the pixel
    spacing), grown where the region to be gridded (``region_mm3``: a compounding's box, the
    field of view UltrON evaluates) would hold more than ``max_voxels`` voxels of s:

        v = max(s, (region_mm3 / max_voxels)^(1/3)).

    A long bone's recording is then meshed far faster and in far less memory than on a grid at
    the pixel spacing (figures in
    docs/decisions.md#meshing-grid-voxel-size-and-field-of-view-volume-meshgridpy); a small
    region keeps the pixel spacing."""
    if voxel_mm:
        return voxel_mm
    spacing = min(probe.lateral_spacing_mm, probe.axial_spacing_mm)
    if finest_mm is not None:
        spacing = max(spacing, float(finest_mm))
    if region_mm3 is None or not math.isfinite(region_mm3) or region_mm3 <= 0:
        return spacing
    return max(spacing, (region_mm3 / max_voxels) ** (1.0 / 3.0))


def grid_shape(
    bounds_mm: np.ndarray | torch.Tensor, voxel_mm: float, pad_voxels: int = 2
) -> tuple[int, int, int]:
    """Voxels per axis of the grid of ``voxel_mm`` covering a (2, 3) [min, max] box, padded
    by ``pad_voxels``: ceil(extent / voxel) + 1 + 2·pad, in Python integers (nothing allocated,
    no overflow: a side whose ratio exceeds 1e30 counts as 1e30, so absurd grids can be sized
    and refused before allocation)."""
    box = as_bounds_mm(bounds_mm)
    extent = (float(e) for e in box[1] - box[0])
    return tuple(math.ceil(min(e / voxel_mm, 1e30)) + 1 + 2 * pad_voxels for e in extent)


@dataclass(frozen=True)
class GridSpec:
    """A regular grid: voxel (i, j, k) has its centre at origin_mm + voxel_mm·(i, j, k).

    Axes are world x, y, z in that order; ``shape`` = (nx, ny, nz).
    """

    origin_mm: tuple[float, float, float]
    voxel_mm: float
    shape: tuple[int, int, int]

    def __post_init__(self) -> None:
        if not (np.isfinite(self.voxel_mm) and self.voxel_mm > 0):
            raise argument_error("voxel_mm", f"expected a positive voxel size, got {self.voxel_mm}")
        if len(self.shape) != 3 or min(self.shape) < 2:
            raise argument_error("shape", f"expected three sizes ≥ 2, got {self.shape}")

    @classmethod
    def from_bounds(
        cls, bounds_mm: np.ndarray | torch.Tensor, voxel_mm: float, pad_voxels: int = 2
    ) -> GridSpec:
        """The grid of ``voxel_mm`` covering a (2, 3) [min, max] box, padded by ``pad_voxels``."""
        box = as_bounds_mm(bounds_mm)
        if not (np.isfinite(voxel_mm) and voxel_mm > 0):
            raise argument_error("voxel_mm", f"expected a positive voxel size, got {voxel_mm}")
        origin = box[0] - pad_voxels * voxel_mm
        shape = grid_shape(box, voxel_mm, pad_voxels)
        return cls(tuple(float(o) for o in origin), float(voxel_mm), shape)

    def to_dict(self) -> dict[str, object]:
        """JSON-able ``{"origin_mm": [...], "voxel_mm": v, "shape": [...]}`` (for run.json)."""
        return {"origin_mm": list(self.origin_mm), "voxel_mm": self.voxel_mm,
                "shape": list(self.shape)}  # fmt: skip

    @property
    def n_voxels(self) -> int:
        return int(np.prod(self.shape))

    @property
    def affine(self) -> np.ndarray:
        """4 × 4 matrix mapping voxel indices (i, j, k, 1) to world mm."""
        affine = np.eye(4)
        affine[:3, :3] *= self.voxel_mm
        affine[:3, 3] = self.origin_mm
        return affine

    def index_to_world(self, ijk: np.ndarray) -> np.ndarray:
        """World mm of (fractional) voxel indices (..., 3)."""
        return np.asarray(self.origin_mm) + np.asarray(ijk, dtype=np.float64) * self.voxel_mm

    def world_to_index(self, points_mm: np.ndarray) -> np.ndarray:
        """Fractional voxel indices (..., 3) of world points."""
        return (
            np.asarray(points_mm, dtype=np.float64) - np.asarray(self.origin_mm)
        ) / self.voxel_mm

    def points_mm(self, start: int, stop: int) -> torch.Tensor:
        """World points (M, 3) float32 of flat voxel indices start..stop−1 (C order)."""
        return self.flat_points_mm(torch.arange(start, stop, dtype=torch.int64))

    def flat_points_mm(self, flat: torch.Tensor) -> torch.Tensor:
        """World points (M, 3) float32 of flat (C-order) voxel indices."""
        ny, nz = self.shape[1], self.shape[2]
        ijk = torch.stack([flat // (ny * nz), (flat // nz) % ny, flat % nz], dim=-1)
        origin = torch.tensor(self.origin_mm, dtype=torch.float64)
        return (origin + ijk.to(torch.float64) * self.voxel_mm).to(torch.float32)

    def coarsened(self, factor: int) -> GridSpec:
        """The grid of every ``factor``-th node: coarse node I is this grid's voxel factor·I
        (the last coarse node may lie up to factor − 1 voxels beyond this grid)."""
        if not isinstance(factor, int) or factor < 1:
            raise argument_error("factor", f"expected a positive integer, got {factor!r}")
        shape = tuple(max(2, -(-(n - 1) // factor) + 1) for n in self.shape)
        return GridSpec(self.origin_mm, self.voxel_mm * factor, shape)


def evaluate_on_grid(
    fn: PointsFn, grid: GridSpec, chunk_points: int = 131_072, mask: np.ndarray | None = None
) -> np.ndarray:
    """Evaluate ``fn`` (points (M, 3) world mm → values (M,)) on every voxel centre, in chunks.

    Memory stays bounded by ``chunk_points`` per call. Voxels where ``mask`` is False are not
    evaluated and get 0. Returns float32 (nx, ny, nz).
    """
    if mask is not None and mask.shape != grid.shape:
        raise argument_error("mask", f"expected shape {grid.shape}, got {mask.shape}")
    out = np.zeros(grid.n_voxels, dtype=np.float32)
    flat = np.arange(grid.n_voxels) if mask is None else np.flatnonzero(mask)
    out[flat] = evaluate_at(fn, grid, flat, chunk_points)
    return out.reshape(grid.shape)


def evaluate_at(
    fn: PointsFn, grid: GridSpec, flat_indices: np.ndarray, chunk_points: int = 131_072
) -> np.ndarray:
    """``fn`` at the centres of the voxels with these flat (C-order) indices, float32 (M,)."""
    if chunk_points < 1:
        raise argument_error("chunk_points", f"expected ≥ 1, got {chunk_points}")
    flat = torch.from_numpy(np.asarray(flat_indices, dtype=np.int64))
    values = map_chunks(lambda chunk: _call(fn, grid.flat_points_mm(chunk)), flat, chunk_points)
    return values.numpy()


def evaluate_coarse_to_fine(
    fn: PointsFn,
    grid: GridSpec,
    level: float,
    factor: int = 2,
    chunk_points: int = 131_072,
    coarse_mask: np.ndarray | None = None,
) -> np.ndarray:
    """``fn`` on ``grid``, evaluated exactly only near the ``level`` set.

    1. Evaluate on ``grid.coarsened(factor)`` (zero where ``coarse_mask`` is False).
    2. A coarse cell is *ambiguous* when its 8 corner values do not all lie on the same side
       of ``level``; ambiguous cells are dilated by one cell.
    3. Fine voxels inside dilated ambiguous cells are evaluated exactly (zero where the
       nearest coarse node is masked); every other fine voxel takes the trilinear
       interpolation of its cell's corners, which lies on the same side of ``level`` as all of
       them, so the binarised volume is unchanged wherever the coarse cell was unambiguous.

    Structures thinner than one coarse cell that fall between coarse nodes can be missed;
    ``factor = 1`` evaluates every voxel. Returns float32 ``grid.shape``.
    """
    coarse = grid.coarsened(factor)
    if coarse_mask is not None and coarse_mask.shape != coarse.shape:
        raise argument_error(
            "coarse_mask", f"expected shape {coarse.shape}, got {coarse_mask.shape}"
        )
    if factor == 1:
        return evaluate_on_grid(fn, grid, chunk_points, coarse_mask)
    values = evaluate_on_grid(fn, coarse, chunk_points, coarse_mask)
    ambiguous, fine = ambiguous_cells_and_upsampled(values, level, factor)
    fine = fine[: grid.shape[0], : grid.shape[1], : grid.shape[2]].copy()
    cells = [
        np.minimum(np.arange(n) // factor, c - 2)
        for n, c in zip(grid.shape, coarse.shape, strict=True)
    ]
    refine = ambiguous[np.ix_(*cells)]
    if coarse_mask is not None:
        nodes = [np.minimum((np.arange(n) + factor // 2) // factor, c - 1)
                 for n, c in zip(grid.shape, coarse.shape, strict=True)]  # fmt: skip
        inside = coarse_mask[np.ix_(*nodes)]
        fine[refine & ~inside] = 0.0
        refine &= inside
    flat = np.flatnonzero(refine)
    fine.reshape(-1)[flat] = evaluate_at(fn, grid, flat, chunk_points)
    return fine


def ambiguous_cells_and_upsampled(
    values: np.ndarray, level: float, factor: int
) -> tuple[np.ndarray, np.ndarray]:
    """Steps 2–3 of :func:`evaluate_coarse_to_fine` on coarse node ``values`` (float32, 3D):
    the dilated ambiguous cells (bool, one per cell: shape − 1) and the trilinear
    interpolation of the nodes at ``factor`` times their density (node I ↔ fine index
    factor·I; shape factor·(shape − 1) + 1)."""
    above = torch.from_numpy(values >= level)[None, None].float()
    corners_max = torch.nn.functional.max_pool3d(above, 2, stride=1)
    corners_min = -torch.nn.functional.max_pool3d(-above, 2, stride=1)
    ambiguous = (corners_max != corners_min).float()
    ambiguous = torch.nn.functional.max_pool3d(ambiguous, 3, stride=1, padding=1)[0, 0] > 0
    size = [factor * (n - 1) + 1 for n in values.shape]
    fine = torch.nn.functional.interpolate(
        torch.from_numpy(values)[None, None], size=size, mode="trilinear", align_corners=True
    )[0, 0]
    return ambiguous.numpy(), fine.numpy()


def _call(fn: PointsFn, points: torch.Tensor) -> torch.Tensor:
    values = torch.as_tensor(fn(points)).reshape(-1).to(torch.float32)
    if values.shape[0] != points.shape[0]:
        raise argument_error(
            "fn", f"returned {values.shape[0]} values for {points.shape[0]} points"
        )
    return values


def field_of_view_mask(
    grid: GridSpec,
    probe_to_world: np.ndarray | torch.Tensor | Sequence[np.ndarray],
    probe: ProbeGeometry,
    elevation_half_thickness_mm: float,
) -> np.ndarray:
    """Boolean (nx, ny, nz) mask of voxels lying in some frame's field of view.

    Each frame images the slab |z_probe| ≤ ``elevation_half_thickness_mm`` of its image
    rectangle. The slab is rasterised by sampling it at half-voxel spacing (in-plane and in
    elevation) and marking the voxels containing the samples, which is exact up to half a voxel
    and avoids testing every voxel against every frame (:func:`field_of_view_samples`).
    """
    mask = np.zeros(grid.shape, dtype=bool)
    for ijk in field_of_view_samples(grid, probe_to_world, probe, elevation_half_thickness_mm):
        mask[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    return mask


def field_of_view_volume_mm3(
    probe_to_world: np.ndarray | torch.Tensor,
    probe: ProbeGeometry,
    elevation_half_thickness_mm: float,
    voxel_mm: float = 2.0,
) -> float:
    """The volume (mm³) the frames' slabs cover together: their :func:`field_of_view_mask` on a
    grid of ``voxel_mm`` (larger where the field of view's box would hold more than
    :data:`MAX_REGION_VOXELS` of them) over that box, voxels counted × voxel volume (exact to
    about a voxel at the slabs' borders; cheap even for a long sweep, see
    docs/decisions.md#meshing-grid-voxel-size-and-field-of-view-volume-meshgridpy)."""
    bounds = field_of_view_bounds_mm(as_pose_tensor(probe_to_world), probe).numpy()
    box_mm3 = float(np.prod(np.maximum(bounds[1] - bounds[0], voxel_mm)))
    voxel_mm = max(voxel_mm, (box_mm3 / MAX_REGION_VOXELS) ** (1.0 / 3.0))
    coarse = GridSpec.from_bounds(bounds, voxel_mm, pad_voxels=1)
    mask = field_of_view_mask(coarse, probe_to_world, probe, elevation_half_thickness_mm)
    return float(np.count_nonzero(mask)) * voxel_mm**3


def field_of_view_samples(
    grid: GridSpec,
    probe_to_world: np.ndarray | torch.Tensor | Sequence[np.ndarray],
    probe: ProbeGeometry,
    elevation_half_thickness_mm: float,
) -> Iterator[np.ndarray]:
    """The voxels (M, 3) int64 of ``grid`` holding samples of the frames' slabs at half-voxel
    spacing (:func:`field_of_view_mask`), per chunk of frames (repeats possible)."""
    shape = np.asarray(grid.shape, dtype=np.float64)
    points = slab_points(probe_to_world, probe, elevation_half_thickness_mm, grid.voxel_mm / 2)
    for chunk in points:
        index = grid.world_to_index(chunk)
        np.rint(index, out=index)  # whole numbers: the bounds test reads them exactly
        inside = (index >= 0) & (index < shape)
        keep = inside[:, 0] & inside[:, 1] & inside[:, 2]
        yield index[keep].astype(np.int64)


def slab_points(
    probe_to_world: np.ndarray | torch.Tensor | Sequence[np.ndarray],
    probe: ProbeGeometry,
    elevation_half_thickness_mm: float,
    step_mm: float,
    frames_per_chunk: int = 16,
) -> Iterator[np.ndarray]:
    """World points (M, 3) float64 sampling each frame's slab (its image rectangle, pixel
    centre to pixel centre, × |z_probe| ≤ ``elevation_half_thickness_mm``) at a spacing of
    at most ``step_mm`` along each of its axes, per chunk of frames."""
    poses = as_pose_tensor(probe_to_world).to(torch.float64)
    if not elevation_half_thickness_mm >= 0:
        raise argument_error(
            "elevation_half_thickness_mm", f"expected ≥ 0, got {elevation_half_thickness_mm}"
        )
    if not (np.isfinite(step_mm) and step_mm > 0):
        raise argument_error("step_mm", f"expected a positive spacing, got {step_mm}")
    width_mm = (probe.width_px - 1) * probe.lateral_spacing_mm
    depth_mm = (probe.height_px - 1) * probe.axial_spacing_mm
    cols = torch.linspace(
        0, probe.width_px - 1, max(2, int(np.ceil(width_mm / step_mm)) + 1), dtype=torch.float64
    )
    rows = torch.linspace(
        0, probe.height_px - 1, max(2, int(np.ceil(depth_mm / step_mm)) + 1), dtype=torch.float64
    )
    n_elev = max(1, int(np.ceil(2 * elevation_half_thickness_mm / step_mm)) + 1)
    elevations = torch.linspace(
        -elevation_half_thickness_mm, elevation_half_thickness_mm, n_elev, dtype=torch.float64
    )
    for start in range(0, poses.shape[0], frames_per_chunk):
        chunk = poses[start : start + frames_per_chunk]
        plane = pixel_to_world(chunk, rows[:, None], cols[None, :], probe)  # (n, R, C, 3)
        normal = chunk[:, :3, 2]  # probe +z (elevation) in world
        slab = (
            plane[:, None] + elevations[None, :, None, None, None] * normal[:, None, None, None, :]
        )
        yield slab.reshape(-1, 3).numpy()
