"""Marching cubes on a block of a larger array, giving exactly PyMCubes' output on the whole.

PyMCubes (``mcubes.marching_cubes``, called only by :func:`marching_cubes` below, the one
every ultron surface goes through) visits the cubes of an array in C order; cube (i, j, k)
has corners v0 … v7 = (i, j, k), (i+1, j, k), (i+1, j+1, k), (i, j+1, k), then the same at
k+1, and bit m of its case index is set when v_m ≤ level. It creates the vertex of a crossed edge when it visits the cube of which that edge
is the "upper" edge 6 (x, from v6 to v7), 5 (y, from v5 to v6) or 10 (z, from v2 to v6), in
that order, at

    p = (x₂ − x₁)·(level − f₁)/(f₂ − f₁) + x₁

along the edge (x₁, f₁ the first named end) — except on the array's low faces, where no such
cube exists. Where every voxel of the low faces lies at or below the level (a padded crop, as
:func:`~ultron.mesh.extract.extract_surface` meshes), the vertex of edge e therefore has index
rank(creator(e)) with creator = (the cube of which e is edge 6, 5 or 10, the edge's axis),
and the faces are the cubes' triangles in C order of the cubes. :func:`block_triangles`
computes a block's triangles and vertices with those global keys, so that blocks of any size
merge (:func:`merge_blocks`) into exactly the whole array's output: same vertex coordinates to
the bit, same order.

The case table is read from the installed PyMCubes itself (each of the 256 cases meshed once
on a 2 × 2 × 2 array), so it cannot drift from the library; ``tests/test_tiled_mesh.py`` checks
the whole against ``mcubes.marching_cubes``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from ultron.errors import argument_error

#: Corner m of a cube, offset (x, y, z) from its lowest corner (PyMCubes' order).
CORNERS = np.array(
    [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]
)
#: Edge e of a cube: (axis, offset of its lower end from the cube's lowest corner).
EDGES = np.array(
    [(0, 0, 0, 0), (1, 1, 0, 0), (0, 0, 1, 0), (1, 0, 0, 0), (0, 0, 0, 1), (1, 1, 0, 1),
     (0, 0, 1, 1), (1, 0, 0, 1), (2, 0, 0, 0), (2, 1, 0, 0), (2, 1, 1, 0), (2, 0, 1, 0)]
)  # fmt: skip
#: Offset from an edge's lower end to the cube that creates its vertex (edge 6, 5 or 10).
CREATOR_OFFSET = np.array([(0, -1, -1), (-1, 0, -1), (-1, -1, 0)])


def marching_cubes(inside_positive: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """PyMCubes' marching cubes of the level 0 of a 3-D array that is positive inside: the one
    call of it in ultron (the blockwise path below is proven equal to it).

    Returns (vertices (V, 3) float64 in the array's fractional indices, faces (F, 3)); map
    the vertices with :func:`mesh_on_grid`.
    """
    import mcubes

    volume = np.asarray(inside_positive)
    if volume.ndim != 3 or min(volume.shape) < 2:
        raise argument_error(
            "inside_positive", f"expected a 3-D array of ≥ 2 per axis, got shape {volume.shape}"
        )
    if not np.isfinite(volume).all():
        raise argument_error("inside_positive", "contains NaN or inf")
    return mcubes.marching_cubes(volume, 0.0)


@functools.cache
def triangle_table() -> np.ndarray:
    """(256, 16) int: per case index, the edges of its triangles (three per triangle, −1
    after the last), as the installed PyMCubes triangulates them."""
    midpoints = {tuple(2 * e[1:] + np.eye(3, dtype=int)[e[0]]): n for n, e in enumerate(EDGES)}
    table = np.full((256, 16), -1, dtype=np.int64)
    for case in range(256):
        cube = np.ones((2, 2, 2))
        for m, corner in enumerate(CORNERS):
            if case >> m & 1:
                cube[tuple(corner)] = -1.0
        vertices, faces = marching_cubes(cube)
        edges = [midpoints[tuple(np.rint(2 * v).astype(int))] for v in vertices]
        flat = [edges[int(i)] for i in np.asarray(faces).reshape(-1)]
        table[case, : len(flat)] = flat
    return table


@dataclass(frozen=True)
class BlockTriangles:
    """A block's share of the whole array's marching cubes, in global keys of a box.

    ``face_edges`` (F, 3) edge keys of each triangle's corners, ``face_cubes`` (F,) the key of
    its cube (faces of one cube in PyMCubes' order), ``edge_keys`` (V,) the block's vertices'
    edge keys and ``positions`` (V, 3) their coordinates in the box's index frame.
    """

    face_edges: np.ndarray
    face_cubes: np.ndarray
    edge_keys: np.ndarray
    positions: np.ndarray


def _flat(ijk: np.ndarray, shape: np.ndarray) -> np.ndarray:
    """C-order flat index of (…, 3) coordinates in a box of ``shape``."""
    return (ijk[..., 0] * shape[1] + ijk[..., 1]) * shape[2] + ijk[..., 2]


def block_triangles(
    values: np.ndarray, start: np.ndarray, box_shape: np.ndarray, level: float = 0.0
) -> BlockTriangles:
    """Triangles of the cubes whose lowest corner is ``values[:-1, :-1, :-1]``.

    ``values`` (a + 1, b + 1, c + 1) float64 holds the array at box coordinates ``start`` +
    (i, j, k) (one layer beyond the block's cubes on each high face); keys are C-order indices
    in the box of ``box_shape`` (cube key = its lowest corner's, edge key = 3 × its lower end's
    + axis). Every crossed edge's ends must lie in ``values``.
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 3 or min(values.shape) < 2:
        raise argument_error("values", f"expected a 3D block of sides ≥ 2, got {values.shape}")
    start, box_shape = np.asarray(start, dtype=np.int64), np.asarray(box_shape, dtype=np.int64)
    below = values <= level
    cubes = [s - 1 for s in values.shape]
    case = np.zeros(cubes, dtype=np.int64)
    for m, (dx, dy, dz) in enumerate(CORNERS):
        case |= (
            below[dx : dx + cubes[0], dy : dy + cubes[1], dz : dz + cubes[2]].astype(np.int64) << m
        )
    active = np.argwhere((case != 0) & (case != 255))  # C order
    table = triangle_table()
    rows = table[case[tuple(active.T)]]  # (A, 16)
    slot_cube, slot = np.nonzero(rows >= 0)
    edge_numbers = rows[slot_cube, slot]
    local_nodes = active[slot_cube] + EDGES[edge_numbers, 1:]
    edge_keys = 3 * _flat(start + local_nodes, box_shape) + EDGES[edge_numbers, 0]
    face_edges = edge_keys.reshape(-1, 3)
    face_cubes = _flat(start + active[slot_cube[::3]], box_shape)
    keys, first = np.unique(edge_keys, return_index=True)
    lower, axis = local_nodes[first], EDGES[edge_numbers[first], 0]
    if ((start + lower + CREATOR_OFFSET[axis]) < 0).any():
        raise argument_error("values", "a crossed edge lies on the box's low faces (pad it)")
    positions = _edge_positions(values, lower, axis, start, level)
    return BlockTriangles(face_edges, face_cubes, keys, positions)


def _edge_positions(
    values: np.ndarray, lower: np.ndarray, axis: np.ndarray, start: np.ndarray, level: float
) -> np.ndarray:
    """Box coordinates (V, 3) of the vertices on the edges from block node ``lower`` along
    ``axis``, with the arithmetic of the edge's creator (module doc): x edges from their upper
    end, in box coordinates (``start`` + block coordinates) as PyMCubes computes them."""
    rows = np.arange(len(axis))
    upper = lower + np.eye(3, dtype=np.int64)[axis]
    f_low, f_up = values[tuple(lower.T)], values[tuple(upper.T)]
    low_box, up_box = (lower + start)[rows, axis], (upper + start)[rows, axis]
    is_x = axis == 0
    x1 = np.where(is_x, up_box, low_box).astype(np.float64)
    x2 = np.where(is_x, low_box, up_box).astype(np.float64)
    f1, f2 = np.where(is_x, f_up, f_low), np.where(is_x, f_low, f_up)
    with np.errstate(divide="ignore", invalid="ignore"):
        along = np.where(f2 == f1, (x2 + x1) / 2, (x2 - x1) * (level - f1) / (f2 - f1) + x1)
    positions = (lower + start).astype(np.float64)
    positions[rows, axis] = along
    return positions


def merge_blocks(
    blocks: list[BlockTriangles], box_shape: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The whole array's (vertices (V, 3) float64 in box coordinates, faces (F, 3) int64)
    from the blocks of a partition of its cubes, in PyMCubes' order (module doc)."""
    box_shape = np.asarray(box_shape, dtype=np.int64)
    if not blocks:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    cubes = np.concatenate([b.face_cubes for b in blocks])
    face_edges = np.concatenate([b.face_edges for b in blocks])[np.argsort(cubes, kind="stable")]
    keys = np.concatenate([b.edge_keys for b in blocks])
    positions = np.concatenate([b.positions for b in blocks])
    keys, first = np.unique(keys, return_index=True)
    positions = positions[first]
    lower = np.stack(np.unravel_index(keys // 3, tuple(box_shape)), axis=-1)
    axis = keys % 3
    creator = 3 * _flat(lower + CREATOR_OFFSET[axis], box_shape) + axis
    order = np.argsort(creator, kind="stable")
    rank = np.empty(len(keys), dtype=np.int64)
    rank[order] = np.arange(len(keys))
    faces = rank[np.searchsorted(keys, face_edges)]
    return positions[order], faces
