"""A meshing grid in tiles: only the tiles the field of view reaches are evaluated and kept.

A long recording's field of view is a thin curved slab in a large bounding box (a 40 cm bone
in several passes); a dense array over the box costs memory for voxels nobody imaged. Here the
grid is cut into cubic tiles of ``tile`` voxels (:class:`TileLayout`), the field-of-view mask
is rasterised into the tiles it touches only (:func:`field_of_view_tiles`), and the
coarse-to-fine evaluation runs tile by tile (:func:`evaluate_tile`), each tile reading the
coarse nodes of its neighbours that the untiled evaluation
(:func:`~ultron.mesh.grid.evaluate_coarse_to_fine`) would read: a one-node halo below, two
above. The tile's values then equal the untiled ones bit for bit (for a coarse factor that is a
power of two: the trilinear weights are then exact; ``tests/test_tiled_mesh.py``). What a tile
keeps is its binarised occupancy (:class:`BinaryTiles`: a boolean block, or nothing for a
tile entirely inside or outside), which :mod:`ultron.mesh.tiled_extract` meshes.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field

import numpy as np
import torch

from ultron.data.dataset import ProbeGeometry
from ultron.data.geometry import as_pose_tensor
from ultron.errors import argument_error
from ultron.mesh.grid import (
    GridSpec,
    PointsFn,
    ambiguous_cells_and_upsampled,
    evaluate_at,
    field_of_view_mask,
    slab_points,
)

#: Voxels per tile side (a power of two, so every power-of-two coarse factor divides it).
DEFAULT_TILE = 64
Key = tuple[int, int, int]


def tile_for_factor(coarse_factor: int, tile: int = DEFAULT_TILE) -> int:
    """``tile`` rounded up to a multiple of the coarse factor (a tile must hold whole coarse
    cells)."""
    if isinstance(coarse_factor, bool) or not isinstance(coarse_factor, int) or coarse_factor < 1:
        raise argument_error("coarse_factor", f"expected a positive integer, got {coarse_factor!r}")
    return -(-tile // coarse_factor) * coarse_factor


@dataclass(frozen=True)
class TileLayout:
    """Tiles of ``tile`` voxels per side over a grid of ``shape``; tile (a, b, c) holds the
    voxels [tile·(a, b, c), tile·(a, b, c) + tile), clipped to the grid."""

    shape: tuple[int, int, int]
    tile: int = DEFAULT_TILE

    def __post_init__(self) -> None:
        if isinstance(self.tile, bool) or not isinstance(self.tile, int) or self.tile < 1:
            raise argument_error("tile", f"expected a positive integer, got {self.tile!r}")
        if len(self.shape) != 3 or min(self.shape) < 1:
            raise argument_error("shape", f"expected three sizes ≥ 1, got {self.shape}")

    @property
    def counts(self) -> tuple[int, int, int]:
        """Tiles per axis."""
        return tuple(-(-n // self.tile) for n in self.shape)  # type: ignore[return-value]

    def contains(self, key: Key) -> bool:
        return all(0 <= k < c for k, c in zip(key, self.counts, strict=True))

    def bounds(self, key: Key) -> tuple[np.ndarray, np.ndarray]:
        """Voxel range [lo, hi) of tile ``key`` (clipped to the grid)."""
        lo = self.tile * np.asarray(key, dtype=np.int64)
        return lo, np.minimum(lo + self.tile, np.asarray(self.shape, dtype=np.int64))

    def span(self, key: Key) -> tuple[np.ndarray, np.ndarray]:
        """Voxel range [lo, hi) of the lattice cell ``key`` (not clipped: keys beyond the
        layout name the cells of the infinite tiling)."""
        lo = self.tile * np.asarray(key, dtype=np.int64)
        return lo, lo + self.tile

    def neighbourhood(self, keys, reach: int = 1, clip: bool = True) -> list[Key]:
        """``keys`` and the tiles within ``reach`` tiles of one (Chebyshev), in C order;
        with ``clip`` only those inside the layout."""
        out = set()
        for key in keys:
            for step in itertools.product(range(-reach, reach + 1), repeat=3):
                near = tuple(k + s for k, s in zip(key, step, strict=True))
                if not clip or self.contains(near):
                    out.add(near)
        return sorted(out)


def gather(
    tiles: Mapping[Key, np.ndarray | bool],
    layout: TileLayout,
    lo: np.ndarray,
    hi: np.ndarray,
    default: bool | float = False,
    dtype: type = bool,
) -> np.ndarray:
    """The block of voxels [lo, hi) (may reach beyond the grid) from tiles stored as arrays of
    their clipped shape or as ``True`` (entirely set); absent tiles and voxels beyond the grid
    read ``default``."""
    lo, hi = np.asarray(lo, dtype=np.int64), np.asarray(hi, dtype=np.int64)
    out = np.full(tuple(hi - lo), default, dtype=dtype)
    first = np.maximum(lo, 0) // layout.tile
    last = (np.minimum(hi, layout.shape) - 1) // layout.tile
    for key in itertools.product(*(range(f, e + 1) for f, e in zip(first, last, strict=True))):
        value = tiles.get(key)
        if value is None:
            continue
        t_lo, t_hi = layout.bounds(key)
        a, b = np.maximum(lo, t_lo), np.minimum(hi, t_hi)
        if (b <= a).any():
            continue
        target = tuple(slice(s, e) for s, e in zip(a - lo, b - lo, strict=True))
        if value is True:
            out[target] = True
        else:
            out[target] = value[tuple(slice(s, e) for s, e in zip(a - t_lo, b - t_lo, strict=True))]
    return out


def field_of_view_tiles(
    grid: GridSpec,
    probe_to_world,
    probe: ProbeGeometry,
    elevation_half_thickness_mm: float,
    tile: int,
) -> dict[Key, np.ndarray]:
    """:func:`~ultron.mesh.grid.field_of_view_mask` of ``grid``, kept only in the tiles of
    ``tile`` voxels that some frame reaches: tile key → boolean block of its clipped shape
    (keys in C order). The mask is marked on the whole grid first — one byte a voxel of this
    grid, which the meshing passes coarsened (an eighth of the fine grid's voxels) — since
    marking the slabs' samples in place costs far less than grouping them by tile."""
    mask = field_of_view_mask(grid, probe_to_world, probe, elevation_half_thickness_mm)
    layout = TileLayout(grid.shape, tile)
    masks: dict[Key, np.ndarray] = {}
    for key in itertools.product(*(range(count) for count in layout.counts)):
        lo, hi = layout.bounds(key)
        block = mask[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
        if block.any():
            masks[key] = block.copy()
    return masks


def coarse_values(
    fn: PointsFn,
    coarse: GridSpec,
    coarse_mask: Mapping[Key, np.ndarray],
    tile_nodes: int,
    chunk_points: int = 131_072,
) -> dict[Key, np.ndarray]:
    """``fn`` at the field-of-view nodes of each tile of ``coarse_mask`` (tiles of
    ``tile_nodes`` nodes of ``coarse``): float32 blocks, 0 outside the field of view. Each node
    is evaluated once, whichever fine tiles read it."""
    out = {}
    for key, mask in coarse_mask.items():
        lo, _ = TileLayout(coarse.shape, tile_nodes).bounds(key)
        nodes = np.argwhere(mask) + lo
        flat = (nodes[:, 0] * coarse.shape[1] + nodes[:, 1]) * coarse.shape[2] + nodes[:, 2]
        values = np.zeros(mask.shape, dtype=np.float32)
        values[mask] = evaluate_at(fn, coarse, flat, chunk_points)
        out[key] = values
    return out


def evaluate_tile(
    fn: PointsFn,
    grid: GridSpec,
    key: Key,
    tile: int,
    level: float,
    factor: int,
    coarse_mask: Mapping[Key, np.ndarray],
    coarse: Mapping[Key, np.ndarray],
    chunk_points: int = 131_072,
) -> np.ndarray | None:
    """:func:`~ultron.mesh.grid.evaluate_coarse_to_fine` (``fn``, ``grid``, ``level``,
    ``factor``) restricted to the voxels of tile ``key`` (float32, the tile's clipped shape),
    or None when no coarse node it reads lies in the field of view (all its values are 0).

    ``coarse_mask`` holds the field-of-view mask of ``grid.coarsened(factor)`` in tiles of
    ``tile // factor`` nodes (:func:`field_of_view_tiles`), ``coarse`` the values there
    (:func:`coarse_values`); the tile reads them a node below and two above its own.
    """
    if tile % factor:
        raise argument_error(
            "tile", f"expected a multiple of the coarse factor {factor}, got {tile}"
        )
    coarse_grid = grid.coarsened(factor)
    lo, hi = TileLayout(grid.shape, tile).bounds(key)
    c_max = np.asarray(coarse_grid.shape) - 1
    cells = np.minimum(lo // factor, c_max - 1), np.minimum((hi - 1) // factor, c_max - 1)
    n0, n1 = np.maximum(cells[0] - 1, 0), np.minimum(cells[1] + 2, c_max)
    if factor == 1:
        n0, n1 = lo, hi - 1
    layout = TileLayout(coarse_grid.shape, tile // factor)
    mask = gather(coarse_mask, layout, n0, n1 + 1)
    if not mask.any():
        return None
    values = gather(coarse, layout, n0, n1 + 1, 0.0, np.float32)
    if factor == 1:
        return values
    return _refine(fn, grid, values, mask, (lo, hi), (n0, c_max), level, factor, chunk_points)


def _refine(fn, grid, values, mask, bounds, nodes, level, factor, chunk_points) -> np.ndarray:
    """Steps 2–3 of the coarse-to-fine evaluation on one tile's coarse block (``values`` at
    nodes n0 + (i, j, k), ``mask`` the field of view there), as the untiled code does them."""
    (lo, hi), (n0, c_max) = bounds, nodes
    ambiguous, fine = ambiguous_cells_and_upsampled(values, level, factor)
    offset = lo - factor * n0
    fine = fine[tuple(slice(o, o + h - s) for o, s, h in zip(offset, lo, hi, strict=True))]
    fine = fine.copy()
    index = [np.arange(s, h) for s, h in zip(lo, hi, strict=True)]
    cells = [np.minimum(i // factor, c - 1) - n for i, c, n in zip(index, c_max, n0, strict=True)]
    refine = ambiguous[np.ix_(*cells)]
    near = [
        np.minimum((i + factor // 2) // factor, c) - n
        for i, c, n in zip(index, c_max, n0, strict=True)
    ]
    inside = mask[np.ix_(*near)]
    fine[refine & ~inside] = 0.0
    refine &= inside
    local = np.argwhere(refine) + lo
    flat = (local[:, 0] * grid.shape[1] + local[:, 1]) * grid.shape[2] + local[:, 2]
    fine[refine] = evaluate_at(fn, grid, flat, chunk_points)
    return fine


@dataclass
class BinaryTiles:
    """A binarised volume in tiles: ``mixed`` tiles' boolean blocks, the keys of tiles that
    are entirely set (``full``), the number of set voxels and the largest value seen."""

    layout: TileLayout
    mixed: dict[Key, np.ndarray] = field(default_factory=dict)
    full: set[Key] = field(default_factory=set)
    n_inside: int = 0
    max_value: float = 0.0

    def add(self, key: Key, values: np.ndarray, threshold: float) -> None:
        """Record tile ``key``'s values (its clipped shape), binarised at ``threshold``."""
        if not np.isfinite(values).all():
            raise argument_error("occupancy", "contains NaN or inf")
        binary = values >= threshold
        count = int(binary.sum())
        self.n_inside += count
        self.max_value = max(self.max_value, float(values.max()))
        if count == binary.size:
            self.full.add(key)
        elif count:
            self.mixed[key] = binary

    def as_mapping(self) -> dict[Key, np.ndarray | bool]:
        """Tile key → boolean block or ``True`` (:func:`gather`'s input)."""
        return {**self.mixed, **dict.fromkeys(self.full, True)}

    @classmethod
    def from_volume(cls, volume: np.ndarray, threshold: float, tile: int = DEFAULT_TILE):
        """The tiles of a dense ``volume``, binarised at ``threshold``."""
        out = cls(TileLayout(tuple(volume.shape), tile))
        for key in itertools.product(*(range(c) for c in out.layout.counts)):
            lo, hi = out.layout.bounds(key)
            out.add(key, volume[tuple(slice(a, b) for a, b in zip(lo, hi, strict=True))], threshold)
        return out


def iterate_tiles(layout: TileLayout) -> Iterator[Key]:
    """Every tile key of ``layout`` in C order."""
    return itertools.product(*(range(c) for c in layout.counts))  # type: ignore[return-value]


#: Largest occupancy volume kept at the meshing voxel (float32: 512 MiB); a larger grid's
#: volume is kept at the smallest power-of-two multiple of the voxel that fits (block means).
MAX_VOLUME_VOXELS = 2**27


def volume_factor(shape: tuple[int, int, int], max_voxels: int = MAX_VOLUME_VOXELS) -> int:
    """The smallest power of two k with ∏⌈n / k⌉ ≤ ``max_voxels``."""
    if max_voxels < 1:
        raise argument_error("max_voxels", f"expected ≥ 1, got {max_voxels}")
    k = 1
    while np.prod([-(-n // k) for n in shape], dtype=np.float64) > max_voxels:
        k *= 2
    return k


class PooledVolume:
    """A float32 volume over ``grid`` at ``factor`` × its voxel, filled block by block
    (:meth:`add`): voxel J holds the mean of the grid's voxels factor·J … factor·J + factor − 1
    (those never added count as 0), so its centre lies at their centroid."""

    def __init__(self, grid: GridSpec, factor: int) -> None:
        if isinstance(factor, bool) or not isinstance(factor, int) or factor < 1:
            raise argument_error("factor", f"expected a positive integer, got {factor!r}")
        self.factor = factor
        self._fine = grid.shape
        shape = tuple(-(-n // factor) for n in grid.shape)
        origin = np.asarray(grid.origin_mm) + grid.voxel_mm * (factor - 1) / 2
        self.grid = grid if factor == 1 else GridSpec(tuple(origin), grid.voxel_mm * factor, shape)
        self._sum = np.zeros(shape, dtype=np.float32)
        self._done = False

    def add(self, lo: np.ndarray, values: np.ndarray) -> None:
        """Add the fine values of the block whose first voxel is ``lo``."""
        k = self.factor
        if self._done:
            raise argument_error("volume", "already read; add every block first")
        if k == 1:
            self._sum[tuple(slice(a, a + n) for a, n in zip(lo, values.shape, strict=True))] = (
                values
            )
            return
        total, at = values.astype(np.float32), []
        for axis, (a, n) in enumerate(zip(lo, values.shape, strict=True)):
            index = a + np.arange(n)
            starts = np.flatnonzero(np.r_[True, index[1:] % k == 0])
            total = np.add.reduceat(total, starts, axis=axis)
            at.append(slice(index[0] // k, index[-1] // k + 1))
        self._sum[tuple(at)] += total

    @property
    def values(self) -> np.ndarray:
        """The volume (float32, ``grid.shape``); no block may be added afterwards."""
        if self.factor > 1 and not self._done:
            for axis, n in enumerate(self._fine):
                counts = np.minimum(self.factor, n - self.factor * np.arange(self._sum.shape[axis]))
                self._sum /= counts.reshape([-1 if a == axis else 1 for a in range(3)]).astype(
                    np.float32
                )
        self._done = True
        return self._sum


@dataclass
class TiledEvaluation:
    """What :func:`evaluate_tiles` produced: the binarised tiles, the occupancy volume and
    counts (tiles of the grid and evaluated, points ``fn`` saw, volume voxels)."""

    tiles: BinaryTiles
    volume: PooledVolume
    stats: dict[str, int]


def evaluate_tiles(
    fn: PointsFn,
    grid: GridSpec,
    level: float,
    factor: int,
    coarse_mask: Mapping[Key, np.ndarray],
    tile: int = DEFAULT_TILE,
    chunk_points: int = 131_072,
    max_volume_voxels: int = MAX_VOLUME_VOXELS,
    advance: Callable[[int, int], None] | None = None,
) -> TiledEvaluation:
    """:func:`evaluate_tile` on every tile whose coarse nodes reach the field of view
    (``coarse_mask``: tiles of ``tile // factor`` coarse nodes, :func:`field_of_view_tiles`),
    binarised at ``level`` into :class:`BinaryTiles` and pooled into the occupancy volume
    (:class:`PooledVolume`, :func:`volume_factor` of ``max_volume_voxels``). ``advance``, when
    given, is told the tiles visited so far and their number after each tile."""
    layout = TileLayout(grid.shape, tile)
    seen = [0]

    def counted(points: torch.Tensor) -> torch.Tensor:
        seen[0] += points.shape[0]
        return fn(points)

    tiles = BinaryTiles(layout)
    volume = PooledVolume(grid, volume_factor(grid.shape, max_volume_voxels))
    coarse = coarse_values(
        counted, grid.coarsened(factor), coarse_mask, tile // factor, chunk_points
    )
    evaluated, voxels = 0, 0
    keys = layout.neighbourhood(coarse_mask)
    for done, key in enumerate(keys, start=1):
        values = evaluate_tile(
            counted, grid, key, tile, level, factor, coarse_mask, coarse, chunk_points
        )
        if advance is not None:
            advance(done, len(keys))
        if values is None:
            continue
        evaluated += 1
        voxels += values.size
        tiles.add(key, values, level)
        volume.add(layout.bounds(key)[0], values)
    stats = {
        "tile": tile,
        "tiles_in_grid": int(np.prod(layout.counts)),
        "tiles_in_field_of_view": len(coarse_mask),
        "tiles_evaluated": evaluated,
        "voxels_evaluated": voxels,
        "tiles_mixed": len(tiles.mixed),
        "tiles_full": len(tiles.full),
        "points_evaluated": seen[0],
        "grid_voxels": grid.n_voxels,
        "volume_voxels": int(np.prod(volume.grid.shape)),
        "volume_factor": volume.factor,
    }
    return TiledEvaluation(tiles, volume, stats)


def reached_tiles(
    grid: GridSpec,
    probe_to_world,
    probe: ProbeGeometry,
    elevation_half_thickness_mm: float,
    tile: int,
    factor: int = 2,
    max_samples: int = 20_000_000,
) -> set[Key]:
    """A cheap superset of the tiles :func:`evaluate_tiles` evaluates: the frames' slabs are
    sampled at a spacing s (4 voxels, or coarser to stay within ``max_samples``), and every
    tile within s·√3/2 + 2·``factor`` + 1 voxels of a sample is counted (the nearest sample's
    distance, plus the coarse-to-fine evaluation's reach beyond the field of view)."""
    poses = np.asarray(as_pose_tensor(probe_to_world))
    layout = TileLayout(grid.shape, tile)
    counts = np.asarray(layout.counts)
    sides = np.array([probe.width_mm, probe.depth_mm, 2 * elevation_half_thickness_mm])
    step = 4 * grid.voxel_mm
    while len(poses) * np.prod(sides / step + 2) > max_samples:
        step *= 2
    reach = step * np.sqrt(3) / 2 / grid.voxel_mm + 2 * factor + 1
    hit = np.zeros(tuple(counts), dtype=bool)  # one flag per tile: no sorting of keys
    for points in slab_points(poses, probe, elevation_half_thickness_mm, step):
        index = grid.world_to_index(points)
        low = np.clip(np.floor((index - reach) / tile), 0, counts - 1).astype(np.int64)
        high = np.clip(np.floor((index + reach) / tile), 0, counts - 1).astype(np.int64)
        for step_keys in itertools.product(range(int((high - low).max()) + 1), repeat=3):
            keys = low + np.asarray(step_keys)
            keys = keys[(keys <= high).all(axis=1)]
            hit[keys[:, 0], keys[:, 1], keys[:, 2]] = True
    return set(map(tuple, np.argwhere(hit).tolist()))
