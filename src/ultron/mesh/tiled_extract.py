"""Surface extraction from a binarised volume held in tiles, equal to the single-array one.

:func:`~ultron.mesh.extract.extract_surface_single_grid` meshes one dense array: it keeps the
large 26-connected components of the occupied voxels, crops to their box with a 3-voxel
margin, smooths the 0.5 level set (:func:`~ultron.mesh.smoothing.smooth_constrained`) and runs
PyMCubes. Every step is done here on :class:`~ultron.mesh.tiles.BinaryTiles`, in memory that
grows with the surface, not with the box:

1. components: each tile is labelled on its own, labels of voxels touching across a tile face,
   edge or corner are joined (``scipy.sparse.csgraph``) and the components' sizes summed;
2. the smoothing's signed distance, d = EDT − ½ inside and ½ − EDT outside, matters only in
   its band |d| ≤ 4 inside the padded crop: per tile, it is computed from the tile and a
   5-voxel halo (a band voxel's nearest voxel of the other side lies within 4.5 voxels);
3. the smoothing's quadratic problem lives on the band alone: its matrix is assembled from the
   band's sorted keys (:func:`band_second_differences`: the entries, in the order, of
   :func:`~ultron.mesh.smoothing.second_difference_system` on the dense band) and solved by
   the same projected Jacobi iteration, so the smoothed values are the same to the bit; only
   band voxels' values reach a crossed edge, the others count by their sign;
4. marching cubes per tile (:mod:`ultron.mesh.marching`), merged into PyMCubes' order.

The mesh equals the single-array one exactly — the same vertices in the same order and the
same faces (``tests/test_tiled_mesh.py``).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, sparse

from ultron.mesh.marching import block_triangles, merge_blocks
from ultron.mesh.smoothing import band_second_differences, projected_jacobi
from ultron.mesh.tiles import BinaryTiles, Key, TileLayout, gather
from ultron.parallel import thread_map

#: The single-array extraction's crop margin, smoothing band radius and iteration settings.
CROP_MARGIN = 3
BAND_RADIUS = 4
HALO = BAND_RADIUS + 1
MAX_ITERS, REL_TOL = 500, 1e-6
#: Half of the 26 neighbour offsets (each touching pair of tiles is visited once).
FORWARD = tuple(o for o in itertools.product((-1, 0, 1), repeat=3) if o > (0, 0, 0))
_STRUCTURE = np.ones((3, 3, 3), dtype=bool)
#: Embedding value of voxels outside the band (only their sign reaches marching cubes).
_FAR = 1e6


@dataclass(frozen=True)
class Box:
    """The padded crop: box coordinates (i, j, k) are grid voxel ``origin`` + (i, j, k)."""

    origin: np.ndarray
    shape: np.ndarray

    def keys(self, ijk: np.ndarray) -> np.ndarray:
        """C-order keys (…,) of grid voxels (…, 3) inside the box."""
        local = ijk - self.origin
        return (local[..., 0] * self.shape[1] + local[..., 1]) * self.shape[2] + local[..., 2]

    def contains(self, ijk: np.ndarray) -> np.ndarray:
        local = ijk - self.origin
        return ((local >= 0) & (local < self.shape)).all(axis=-1)


def _layer(faces: dict, offset: tuple[int, ...]) -> np.ndarray:
    """A tile's labels next to its neighbour at ``offset`` (size 1 along its non-zero axes),
    from its six faces ``faces[(axis, high)]``."""
    axes = [a for a, o in enumerate(offset) if o]
    layer = faces[(axes[0], offset[axes[0]] > 0)]
    for axis in axes[1:]:
        index = [slice(None)] * 3
        n = layer.shape[axis]
        index[axis] = slice(n - 1, n) if offset[axis] > 0 else slice(0, 1)
        layer = layer[tuple(index)]
    return layer


def _touching_pairs(a: np.ndarray, b: np.ndarray, offset: tuple[int, ...]) -> np.ndarray:
    """Label pairs (P, 2) of 26-adjacent set voxels of two touching layers ``a``, ``b``:
    along the axes where ``offset`` is 0 they may be one voxel apart."""
    free = [axis for axis, o in enumerate(offset) if o == 0]
    pairs = [np.zeros((0, 2), dtype=np.int64)]
    for shift in itertools.product((-1, 0, 1), repeat=len(free)):
        sa, sb = [slice(None)] * 3, [slice(None)] * 3
        for axis, s in zip(free, shift, strict=True):
            n = a.shape[axis]
            sa[axis], sb[axis] = slice(max(0, -s), n - max(0, s)), slice(max(0, s), n + min(0, s))
        x, y = a[tuple(sa)].reshape(-1), b[tuple(sb)].reshape(-1)
        both = (x > 0) & (y > 0)
        pairs.append(np.stack([x[both], y[both]], axis=1).astype(np.int64))
    return np.unique(np.concatenate(pairs), axis=0)


def _labels(tiles: BinaryTiles, key: Key) -> tuple[np.ndarray, int]:
    """A tile's 26-connected labels (int32, 1…n) and n (a full tile: all 1)."""
    if key in tiles.full:
        lo, hi = tiles.layout.bounds(key)
        return np.ones(tuple(hi - lo), dtype=np.int32), 1
    labels, n = ndimage.label(tiles.mixed[key], structure=_STRUCTURE)
    return labels, n


def _faces(labels: np.ndarray) -> dict[tuple[int, bool], np.ndarray]:
    out = {}
    for axis, high in itertools.product(range(3), (False, True)):
        index = [slice(None)] * 3
        n = labels.shape[axis]
        index[axis] = slice(n - 1, n) if high else slice(0, 1)
        out[(axis, high)] = labels[tuple(index)].copy()
    return out


def kept_components(tiles: BinaryTiles, min_fraction: float) -> dict[Key, np.ndarray | bool]:
    """:func:`~ultron.mesh.extract.keep_large_voxel_components` on tiles (module doc, 1):
    tile key → kept block or ``True`` (entirely kept); tiles left empty are dropped."""
    from scipy.sparse.csgraph import connected_components

    keys = sorted(set(tiles.mixed) | tiles.full)
    first, sizes, faces = {}, [], {}
    for key in keys:
        labels, n = _labels(tiles, key)
        first[key] = sum(len(s) for s in sizes)
        sizes.append(np.bincount(labels.reshape(-1), minlength=n + 1)[1:])
        faces[key] = _faces(labels)
    edges = [np.zeros((0, 2), dtype=np.int64)]
    for key, offset in itertools.product(keys, FORWARD):
        other = tuple(k + o for k, o in zip(key, offset, strict=True))
        if other in first:
            back = tuple(-o for o in offset)
            pairs = _touching_pairs(_layer(faces[key], offset), _layer(faces[other], back), offset)
            edges.append(pairs - 1 + np.array([first[key], first[other]]))
    sizes = np.concatenate(sizes).astype(np.float64)
    links = np.concatenate(edges)
    graph = sparse.coo_matrix(
        (np.ones(len(links)), (links[:, 0], links[:, 1])), shape=(len(sizes), len(sizes))
    )
    n_components, component = connected_components(graph, directed=False)
    totals = np.bincount(component, weights=sizes, minlength=n_components)
    keep = totals >= min_fraction * totals.max() if n_components > 1 else np.ones(1, dtype=bool)
    kept: dict[Key, np.ndarray | bool] = {}
    for key in keys:
        labels, n = _labels(tiles, key)
        local = np.r_[False, keep[component[first[key] : first[key] + n]]]
        if key in tiles.full and local[1]:
            kept[key] = True
        elif key not in tiles.full and local.any():
            kept[key] = local[labels]
    return kept


def padded_crop(kept: dict[Key, np.ndarray | bool], layout: TileLayout) -> Box:
    """The box of the kept voxels grown by :data:`CROP_MARGIN` (may reach beyond the grid)."""
    lows, highs = [], []
    for key, block in kept.items():
        lo, hi = layout.bounds(key)
        if block is not True:
            where = np.argwhere(block)
            lo, hi = lo + where.min(axis=0), lo + where.max(axis=0) + 1
        lows.append(lo)
        highs.append(hi)
    lo, hi = np.min(lows, axis=0), np.max(highs, axis=0)
    return Box(lo - CROP_MARGIN, hi - lo + 2 * CROP_MARGIN)


def box_tiles(
    kept: dict[Key, np.ndarray | bool], layout: TileLayout, box: Box, cubes: bool = False
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Voxel ranges [lo, hi) of the tiles of the lattice next to a kept tile, clipped to the
    box (``cubes``: to the box's cubes, whose lowest corners stop one voxel short)."""
    end = box.origin + box.shape - (1 if cubes else 0)
    ranges = []
    for key in layout.neighbourhood(kept, clip=False):
        lo, hi = layout.span(key)
        lo, hi = np.maximum(lo, box.origin), np.minimum(hi, end)
        if (hi > lo).all():
            ranges.append((lo, hi))
    return ranges


def band_distances(
    kept: dict[Key, np.ndarray | bool], layout: TileLayout, box: Box
) -> tuple[np.ndarray, np.ndarray]:
    """Keys (sorted) and signed distances of the band voxels (module doc, 2); the tiles'
    distance transforms run on threads (:func:`~ultron.parallel.thread_map`: they release the
    GIL)."""

    def tile_band(span: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray] | None:
        lo, hi = span
        block = gather(kept, layout, lo - HALO, hi + HALO)
        if block.all() or not block.any():
            return None
        inside = ndimage.distance_transform_edt(block) - 0.5
        outside = -ndimage.distance_transform_edt(~block) + 0.5
        core = tuple(slice(HALO, -HALO) for _ in range(3))
        distance = np.where(block, inside, outside)[core]
        ijk = np.argwhere(np.abs(distance) <= BAND_RADIUS)
        return box.keys(ijk + lo), distance[tuple(ijk.T)]

    keys, values = [np.zeros(0, dtype=np.int64)], [np.zeros(0)]
    for found in thread_map(tile_band, box_tiles(kept, layout, box)):
        if found is not None:
            keys.append(found[0])
            values.append(found[1])
    keys_all, values_all = np.concatenate(keys), np.concatenate(values)
    order = np.argsort(keys_all)
    return keys_all[order], values_all[order]


def smooth_band(
    keys: np.ndarray,
    distance: np.ndarray,
    shape: np.ndarray,
    advance: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """:func:`~ultron.mesh.smoothing.smooth_constrained`'s values on the band (module doc, 3);
    ``advance`` is told the iterations done (:func:`~ultron.mesh.smoothing.projected_jacobi`)."""
    q = band_second_differences(keys, shape)
    upper = np.where(distance < 0, distance, np.inf)
    lower = np.where(distance > 0, distance, -np.inf)
    upper[np.abs(upper) < 1] = 0
    lower[np.abs(lower) < 1] = 0
    return projected_jacobi(
        q, distance, lower, upper, MAX_ITERS, REL_TOL, advance=advance, overwrite_q=True
    )


def mesh_tiles(
    kept: dict[Key, np.ndarray | bool],
    layout: TileLayout,
    box: Box,
    band: tuple[np.ndarray, np.ndarray] | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes of the embedding (band values, else ±far; without a band ±½, the
    unsmoothed binary) tile by tile: (vertices in box coordinates, faces), PyMCubes' order."""
    blocks = []
    for lo, hi in box_tiles(kept, layout, box, cubes=True):
        inside = gather(kept, layout, lo, hi + 1)
        if not inside.any():
            continue
        values = np.where(inside, 0.5, -0.5) if band is None else np.where(inside, _FAR, -_FAR)
        if band is not None:
            ijk = np.argwhere(np.ones(inside.shape, dtype=bool)) + lo
            mine = box.contains(ijk)
            keys = box.keys(ijk[mine])
            found = np.minimum(np.searchsorted(band[0], keys), len(band[0]) - 1)
            hit = band[0][found] == keys
            flat = values.reshape(-1)
            flat[np.flatnonzero(mine)[hit]] = band[1][found[hit]]
        part = block_triangles(values, lo - box.origin, box.shape)
        if len(part.face_cubes):
            blocks.append(part)
    return merge_blocks(blocks, box.shape)


def extract_tiles(
    tiles: BinaryTiles,
    min_fraction: float,
    smooth: bool,
    advance: Callable[[int, int], None] | None = None,
) -> tuple:
    """Steps 1–4 (module doc): (vertices (V, 3) in grid index coordinates, faces (F, 3)).
    ``tiles`` must hold a set voxel; the mesh may be empty. ``advance`` is told the smoothing's
    iterations (:func:`smooth_band`)."""
    layout = tiles.layout
    kept = kept_components(tiles, min_fraction)
    box = padded_crop(kept, layout)
    band = None
    if smooth:
        keys, distance = band_distances(kept, layout, box)
        band = (keys, smooth_band(keys, distance, box.shape, advance))
    vertices, faces = mesh_tiles(kept, layout, box, band)
    return vertices - CROP_MARGIN + (box.origin + CROP_MARGIN), faces
