"""Surface extraction: occupancy on a grid → PyMCubes smoothing → marching cubes → mesh in mm.

Follows METHOD.md §5: the occupancy is binarised at 0.5, smoothed with PyMCubes' ``smooth``
(whose output is positive inside and has its zero level on a smooth surface between inside and
outside voxels), and triangulated by marching cubes at level 0; vertices are mapped from voxel
indices to world mm. The smoothing is PyMCubes' constrained (Lempitsky) method, assembled
vectorised in :mod:`ultron.mesh.smoothing` (PyMCubes' own assembly loops over voxels in Python).

Small disconnected pieces (speckle-like false positives) are dropped twice: before smoothing, a
26-connected component of occupied voxels is kept when it has at least
``min_component_fraction`` of the largest component's voxels (this also keeps the smoothing
band small); after marching cubes, a mesh component is kept when its area is at least that
fraction of the largest one's (default 5%).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ultron.errors import UltronError, argument_error
from ultron.mesh.grid import GridSpec
from ultron.mesh.marching import marching_cubes
from ultron.mesh.smoothing import smooth_constrained
from ultron.mesh.tiled_extract import extract_tiles
from ultron.mesh.tiles import DEFAULT_TILE, BinaryTiles


class NoSurfaceError(UltronError):
    """The occupancy volume has no inside/outside transition: there is no surface to mesh."""


@dataclass(frozen=True)
class ExtractionConfig:
    """Settings of :func:`extract_surface`."""

    threshold: float = 0.5
    smooth: bool = True
    min_component_fraction: float = 0.05

    def __post_init__(self) -> None:
        if not 0.0 < self.threshold < 1.0:
            raise argument_error("threshold", f"expected a value in (0, 1), got {self.threshold}")
        if not 0.0 <= self.min_component_fraction <= 1.0:
            raise argument_error(
                "min_component_fraction",
                f"expected a value in [0, 1], got {self.min_component_fraction}",
            )


def extract_surface(
    occupancy: np.ndarray,
    grid: GridSpec,
    config: ExtractionConfig | None = None,
    tile: int = DEFAULT_TILE,
    advance: Callable[[int, int], None] | None = None,
):
    """Mesh the ``occupancy`` volume (values in [0, 1], shape ``grid.shape``) in world mm;
    ``advance`` as in :func:`extract_surface_tiles`.

    Returns a ``trimesh.Trimesh`` with outward normals. Raises :class:`NoSurfaceError` when no
    voxel (or every voxel) is occupied, or when nothing survives component filtering. The work
    is done in tiles of ``tile`` voxels (:func:`extract_surface_tiles`); the mesh is exactly
    :func:`extract_surface_single_grid`'s.
    """
    config = config or ExtractionConfig()
    volume = np.asarray(occupancy)
    if volume.shape != grid.shape:
        raise argument_error("occupancy", f"expected shape {grid.shape}, got {volume.shape}")
    return extract_surface_tiles(
        BinaryTiles.from_volume(volume, config.threshold, tile), grid, config, advance
    )


def extract_surface_tiles(
    tiles: BinaryTiles,
    grid: GridSpec,
    config: ExtractionConfig | None = None,
    advance: Callable[[int, int], None] | None = None,
):
    """:func:`extract_surface` of a volume held binarised in tiles
    (:class:`~ultron.mesh.tiles.BinaryTiles`, at ``config.threshold``): the same mesh as the
    single-array path, in memory that grows with the surface (:mod:`ultron.mesh.tiled_extract`).
    ``advance``, when given, is told the smoothing's iterations as they run (done, at most)."""
    config = config or ExtractionConfig()
    if tiles.layout.shape != grid.shape:
        raise argument_error(
            "tiles", f"expected a layout of shape {grid.shape}, got {tiles.layout.shape}"
        )
    _check_occupied(tiles.n_inside, grid.n_voxels, config.threshold, tiles.max_value)
    vertices, faces = extract_tiles(tiles, config.min_component_fraction, config.smooth, advance)
    return mesh_on_grid(vertices, faces, grid, config.min_component_fraction)


def extract_surface_single_grid(
    occupancy: np.ndarray, grid: GridSpec, config: ExtractionConfig | None = None
):
    """The reference extraction on one dense array (module docstring): PyMCubes' smoothing
    band and marching cubes over the whole crop. Same mesh as :func:`extract_surface`, in
    memory that grows with the crop (≈ 60 bytes per voxel)."""
    config = config or ExtractionConfig()
    volume = np.asarray(occupancy)
    if volume.shape != grid.shape:
        raise argument_error("occupancy", f"expected shape {grid.shape}, got {volume.shape}")
    if not np.isfinite(volume).all():
        raise argument_error("occupancy", "contains NaN or inf")
    binary = volume >= config.threshold
    max_value = float(volume.max()) if volume.size else 0.0
    _check_occupied(int(binary.sum()), binary.size, config.threshold, max_value)
    binary = keep_large_voxel_components(binary, config.min_component_fraction)
    # crop to the occupied box (smoothing cost grows with the volume), with a margin that also
    # closes objects touching the grid border
    margin = 3
    nonzero = np.argwhere(binary)
    lo = nonzero.min(axis=0)
    hi = nonzero.max(axis=0) + 1
    crop = binary[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
    padded = np.pad(crop, margin, constant_values=False)
    embedding = smooth_constrained(padded) if config.smooth else padded.astype(np.float64) - 0.5
    vertices, faces = marching_cubes(embedding)
    return mesh_on_grid(vertices - margin + lo, faces, grid, config.min_component_fraction)


def _check_occupied(n_inside: int, n_voxels: int, threshold: float, max_value: float) -> None:
    if n_inside == 0:
        raise NoSurfaceError(
            f"no surface: no voxel has occupancy ≥ {threshold} (max {max_value:.3f}); a learned"
            " method's fit was too short or saw too little bone: more labelled frames"
            " (--label-fraction), more steps (--occupancy-iters, --field-iters) or a field fitted"
            " longer may reach it"
        )
    if n_inside == n_voxels:
        raise NoSurfaceError(
            "no surface: every voxel is occupied (the grid lies inside the object)"
        )


def mesh_on_grid(
    vertices: np.ndarray, faces: np.ndarray, grid: GridSpec, min_component_fraction: float
):
    """The mesh in world mm from marching cubes' vertices in ``grid``'s indices — the one
    vertex mapping of every extracted surface (``grid.index_to_world``) —, components below
    ``min_component_fraction`` of the area dropped, normals outward. Raises
    :class:`NoSurfaceError` without faces."""
    import trimesh

    if len(faces) == 0:
        raise NoSurfaceError("no surface: marching cubes produced no triangles")
    vertices_mm = grid.index_to_world(vertices)
    # process=False: PyMCubes can emit distinct vertices at identical positions; merging them
    # (or dropping the zero-area faces between them) would break the mesh's watertightness.
    mesh = trimesh.Trimesh(vertices=vertices_mm, faces=faces, process=False)
    if min_component_fraction > 0:
        mesh = keep_large_components(mesh, min_component_fraction)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def keep_large_voxel_components(binary: np.ndarray, min_fraction: float) -> np.ndarray:
    """Keep 26-connected components with ≥ ``min_fraction`` × the largest one's voxel count."""
    from scipy import ndimage

    labels, n = ndimage.label(binary, structure=np.ones((3, 3, 3), dtype=bool))
    if n <= 1:
        return binary
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    keep = sizes >= min_fraction * sizes.max()
    keep[0] = False
    return keep[labels]


def keep_large_components(mesh, min_fraction: float):
    """Keep connected components whose area is ≥ ``min_fraction`` × the largest one's."""
    import trimesh

    parts = mesh.split(only_watertight=False)
    if len(parts) <= 1:
        return mesh
    areas = np.array([p.area for p in parts])
    keep = [p for p, a in zip(parts, areas, strict=True) if a >= min_fraction * areas.max()]
    return trimesh.util.concatenate(keep)


def weld_coincident(mesh) -> tuple[Any, np.ndarray]:
    """``mesh`` with its coincident vertices merged and the faces without area dropped, and
    (V,) int64: the new index of each old vertex (−1 for one no face uses any more).

    Marching cubes puts a vertex exactly on a grid node wherever the constrained smoothing
    clipped the node's value to the level: once for every crossed edge that ends there, so
    one point has several copies, and the faces between copies have no area (docs/decisions.md,
    "Meshes as written"). Vertices are merged when their coordinates are equal to the bit,
    keeping the order of their first copy; the faces keep their order and winding. A face
    whose corners merge, or whose area is exactly 0 (collinear corners), is dropped: it is a
    segment or a point, not surface. The area and every positive-area face are unchanged.
    """
    import trimesh

    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    if len(vertices) == 0:
        return trimesh.Trimesh(vertices, faces, process=False), np.zeros(0, dtype=np.int64)
    first, inverse = _equal_rows(vertices)
    order = np.argsort(first, kind="stable")  # merged points in the order of their first copy
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    merged = rank[inverse]
    corners = merged[faces]
    points = vertices[first[order]]
    edges = points[corners[:, 1:]] - points[corners[:, :1]]
    # merged corners give a zero edge, or two equal ones: a cross product of exactly 0
    keep = np.cross(edges[:, 0], edges[:, 1]).any(axis=1)
    used = np.zeros(len(points), dtype=bool)
    used[corners[keep].reshape(-1)] = True
    renumber = np.cumsum(used) - 1
    new_index = np.where(used[merged], renumber[merged], -1).astype(np.int64)
    welded = trimesh.Trimesh(points[used], renumber[corners[keep]], process=False)
    return welded, new_index


def _equal_rows(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For the (N, 3) ``points``: each group of equal rows' first index (in the groups' sorted
    order) and each row's group, as ``np.unique(points, axis=0, return_index=True,
    return_inverse=True)`` gives them, by one lexicographic sort of the columns (twice as fast
    on a mesh's vertices)."""
    order = np.lexsort(points.T[::-1])
    ordered = points[order]
    starts = np.ones(len(points), dtype=bool)
    np.any(ordered[1:] != ordered[:-1], axis=1, out=starts[1:])
    inverse = np.empty(len(points), dtype=np.int64)
    inverse[order] = np.cumsum(starts) - 1
    return np.minimum.reduceat(order, np.flatnonzero(starts)), inverse
