"""Exact point-to-triangle-mesh distances, vectorised (numpy + scipy KD-trees).

The distance from a point p to a triangle (a, b, c) is, with w = p − a, the unit normal n̂ and
the barycentric coordinates (u, v) of p's projection on the triangle's plane
(u = e₁·w, v = e₂·w with the dual basis e₁ = (ac × n)/|n|², e₂ = (n × ab)/|n|², n = ab × ac):

    d(p, abc) = |n̂·w|                                   if u ≥ 0, v ≥ 0, u + v ≤ 1,
    d(p, abc) = min over the edges e of |p − clamp_e(p)|  otherwise,

clamp_e(p) = e₀ + clip(((p − e₀)·ê)/|ê|², 0, 1)·ê the nearest point of edge e = (e₀, e₀ + ê). A
degenerate triangle (|n| = 0) is its edges. The distance to the mesh is the minimum over its
triangles, found without visiting them all. The triangles are grouped into clusters (the
cells of a grid three median triangle radii wide), each bounded by an oriented box (its
vertices' principal axes; centre O, half-diagonal ρ). Then per point:

1. an upper bound ub = min d(p, t) over the triangles of the cluster whose centre is nearest
   (KD-tree);
2. a cluster can hold a nearer point only if its box is nearer than ub, so only if its centre
   is within ub + max ρ: those clusters (KD-tree query) whose box distance is < ub are kept.
   Clusters much larger than the rest (at most 256) are checked for every point instead, so
   that a few big triangles do not widen every search;
3. their triangles t with |p − c_t| − r_t < ub (c_t centroid, r_t its farthest vertex) are
   measured exactly, and d(p) = min(ub, their distances).

Every pruning step uses a lower bound of the distance, so the result is the exact minimum over
all triangles (up to floating-point rounding, ≈ 1e-12 mm). Work is chunked to bound memory.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any

import numpy as np

from ultron.errors import argument_error

#: Rows of the per-triangle table (SoA, (21, F)): vertex a, edges ab, ac, unit normal n̂, dual
#: basis e₁, e₂, then 1/|ab|², 1/|ac|², 1/|bc|² (0 for a zero-length edge).
_A, _AB, _AC, _N, _E1, _E2, _INV = 0, 3, 6, 9, 12, 15, 18
_POINTS_PER_CHUNK = 4096
_PAIRS_PER_BATCH = 32_768
_MAX_BIG_CLUSTERS = 256
_NEIGHBOURS = 24
_CELL_PER_RADIUS = 3.0


def _dot(x, y) -> np.ndarray:
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


def triangle_table(triangles: np.ndarray) -> np.ndarray:
    """The (21, F) float64 table of :func:`point_triangle_distances` from (F, 3, 3) vertices."""
    tri = np.asarray(triangles, dtype=np.float64)
    if tri.ndim != 3 or tri.shape[1:] != (3, 3):
        raise argument_error("triangles", f"expected shape (F, 3, 3), got {tri.shape}")
    a = tri[:, 0]
    ab, ac, bc = tri[:, 1] - a, tri[:, 2] - a, tri[:, 2] - tri[:, 1]
    normal = np.cross(ab, ac)
    norm2 = np.einsum("ij,ij->i", normal, normal)
    inv_norm2 = np.divide(1.0, norm2, out=np.zeros_like(norm2), where=norm2 > 0)
    e1 = np.cross(ac, normal) * inv_norm2[:, None]
    e2 = np.cross(normal, ab) * inv_norm2[:, None]
    unit = normal * np.sqrt(inv_norm2)[:, None]

    def inv_length2(edge: np.ndarray) -> np.ndarray:
        length2 = np.einsum("ij,ij->i", edge, edge)
        return np.divide(1.0, length2, out=np.zeros_like(length2), where=length2 > 0)

    inv = np.stack([inv_length2(ab), inv_length2(ac), inv_length2(bc)], axis=1)
    return np.ascontiguousarray(np.concatenate([a, ab, ac, unit, e1, e2, inv], axis=1).T)


def _segment_distance2(w, edge, inv_length2) -> np.ndarray:
    """|w − s·edge|², s = clip((w·edge)/|edge|², 0, 1): squared distance from w to the segment."""
    s = np.clip(_dot(w, edge) * inv_length2, 0.0, 1.0)
    r = (w[0] - s * edge[0], w[1] - s * edge[1], w[2] - s * edge[2])
    return _dot(r, r)


def point_triangle_distances2(points_t: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Squared exact distances (module doc) of points (3, ...) to triangles (21, ...) pairwise
    (broadcast over the trailing dimensions)."""
    w = points_t - table[_A : _A + 3]
    ab, ac = table[_AB : _AB + 3], table[_AC : _AC + 3]
    h = _dot(w, table[_N : _N + 3])
    u, v = _dot(w, table[_E1 : _E1 + 3]), _dot(w, table[_E2 : _E2 + 3])
    degenerate = (table[_E1] == 0) & (table[_E1 + 1] == 0) & (table[_E1 + 2] == 0)
    inside = (u >= 0) & (v >= 0) & (u + v <= 1) & ~degenerate
    edges = np.minimum(
        _segment_distance2(w, ab, table[_INV]), _segment_distance2(w, ac, table[_INV + 1])
    )
    w_b = (w[0] - ab[0], w[1] - ab[1], w[2] - ab[2])
    edges = np.minimum(edges, _segment_distance2(w_b, ac - ab, table[_INV + 2]))
    return np.where(inside, h * h, edges)


def point_triangle_distances(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Exact distance from ``points[i]`` to ``triangles[i]`` ((n, 3) and (n, 3, 3)), mm."""
    points = np.asarray(points, dtype=np.float64)
    table = triangle_table(triangles)
    if points.shape != (table.shape[1], 3):
        raise argument_error("points", f"expected shape ({table.shape[1]}, 3), got {points.shape}")
    return np.sqrt(point_triangle_distances2(points.T, table))


@dataclass(frozen=True)
class MeshDistanceIndex:
    """The search structures of :func:`mesh_distances` for one mesh (module doc).

    Triangles, sorted by cluster (cluster k holds triangles ``starts[k]:starts[k + 1]``):
    ``table`` (21, F), ``centroids`` (F, 3), ``radii`` (F,). Clusters: oriented boxes
    ``box_centre`` (C, 3), ``box_axes`` (C, 3, 3) (rows: axes), ``box_half`` (C, 3)
    half-extents, ``box_radius`` (C,) half-diagonals; ``big`` the clusters checked for every
    point, ``searched`` the others, ``cluster_tree`` a KD-tree of their centres (None when all
    are big) and ``search_radius`` their largest half-diagonal.
    """

    table: np.ndarray
    centroids: np.ndarray
    radii: np.ndarray
    starts: np.ndarray
    box_centre: np.ndarray
    box_axes: np.ndarray
    box_half: np.ndarray
    box_radius: np.ndarray
    big: np.ndarray
    searched: np.ndarray
    search_radius: float
    cluster_tree: Any

    @property
    def n_triangles(self) -> int:
        return int(self.table.shape[1])


def build_distance_index(triangles: np.ndarray) -> MeshDistanceIndex:
    """Index (F, 3, 3) triangle vertices (mm) for :func:`mesh_distances`; F ≥ 1."""
    from scipy.spatial import cKDTree

    tri = np.asarray(triangles, dtype=np.float64)
    if tri.ndim != 3 or tri.shape[1:] != (3, 3) or tri.shape[0] == 0:
        raise argument_error("triangles", f"expected shape (F ≥ 1, 3, 3), got {tri.shape}")
    if not np.isfinite(tri).all():
        raise argument_error("triangles", "vertices contain NaN or inf")
    centroids = tri.mean(axis=1)
    radii = np.sqrt(((tri - centroids[:, None]) ** 2).sum(-1)).max(axis=1)
    cell = _CELL_PER_RADIUS * max(float(np.median(radii)), 1e-9)
    cells = np.floor((centroids - centroids.min(axis=0)) / cell).astype(np.int64)
    span = cells.max(axis=0) + 1
    key = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    order = np.argsort(key, kind="stable")
    key = key[order]
    first = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
    starts = np.concatenate([first, [len(key)]])
    counts = np.diff(starts)
    tri = tri[order]
    centre, axes, half = _oriented_boxes(tri, counts)
    box_radius = np.sqrt((half**2).sum(axis=1))
    big = _big_clusters(box_radius)
    searched = np.setdiff1d(np.arange(len(counts)), big)
    search = float(box_radius[searched].max()) if searched.size else 0.0
    return MeshDistanceIndex(
        triangle_table(tri), centroids[order], radii[order], starts, centre, axes, half,
        box_radius, big, searched, search, cKDTree(centre[searched]) if searched.size else None,
    )  # fmt: skip


def _big_clusters(box_radius: np.ndarray) -> np.ndarray:
    """Clusters whose half-diagonal exceeds twice the median and the (257)th largest: at most
    256 of them, searched for every point instead of widening every ball query."""
    if box_radius.size <= 1:
        return np.zeros(0, dtype=np.int64)
    limit = 2.0 * float(np.median(box_radius))
    if box_radius.size > _MAX_BIG_CLUSTERS:
        limit = max(limit, float(np.sort(box_radius)[-_MAX_BIG_CLUSTERS - 1]))
    return np.flatnonzero(box_radius > limit)


def _oriented_boxes(
    tri_sorted: np.ndarray, counts: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per cluster (consecutive runs of ``counts`` triangles): box centre (C, 3), principal axes
    (C, 3, 3) (rows) and half-extents (C, 3) of its vertices (the eigenvectors of their
    covariance; any orthonormal axes give a bounding box, these a tight one)."""
    n_clusters = counts.size
    vertices = tri_sorted.reshape(-1, 3)
    owner = np.repeat(np.arange(n_clusters), 3 * counts)
    per = 3.0 * counts[:, None]
    mean = np.stack([np.bincount(owner, vertices[:, i], n_clusters) for i in range(3)], 1) / per
    d = vertices - mean[owner]
    cov = np.empty((n_clusters, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = np.bincount(owner, d[:, i] * d[:, j], n_clusters)
    axes = np.swapaxes(np.linalg.eigh(cov)[1], 1, 2)
    local = np.einsum("nij,nj->ni", axes[owner], d)
    starts = np.concatenate([[0], np.cumsum(3 * counts)[:-1]])
    lo = np.minimum.reduceat(local, starts, axis=0)
    hi = np.maximum.reduceat(local, starts, axis=0)
    centre = mean + np.einsum("nji,nj->ni", axes, (lo + hi) / 2)
    return centre, axes, (hi - lo) / 2


def mesh_distances(points: np.ndarray, index: MeshDistanceIndex) -> np.ndarray:
    """Exact distance (mm) from each of ``points`` (n, 3) to the indexed mesh (module doc)."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise argument_error("points", f"expected shape (n, 3), got {points.shape}")
    if not np.isfinite(points).all():
        raise argument_error("points", "contain NaN or inf")
    out = np.empty(len(points))
    for start in range(0, len(points), _POINTS_PER_CHUNK):
        chunk = points[start : start + _POINTS_PER_CHUNK]
        out[start : start + len(chunk)] = np.sqrt(_chunk_distances2(chunk, index))
    return out


def _chunk_distances2(points: np.ndarray, index: MeshDistanceIndex) -> np.ndarray:
    """Squared distances of one chunk of points: upper bound from the nearest cluster, then
    every cluster and triangle whose lower bound is below it (module doc)."""
    n = len(points)
    nearest = _nearest_cluster(points, index)
    best = np.full(n, np.inf)
    _exact_into(best, points, *_expand(np.arange(n), nearest, index), index.table)
    bound = np.sqrt(best)
    pt, cluster = _candidate_clusters(points, bound, index)
    keep = cluster != nearest[pt]
    pt, cluster = pt[keep], cluster[keep]
    local = np.einsum("nij,nj->ni", index.box_axes[cluster], points[pt] - index.box_centre[cluster])
    outside = np.maximum(np.abs(local) - index.box_half[cluster], 0.0)
    keep = np.einsum("ni,ni->n", outside, outside) < best[pt]
    pt, tri = _expand(pt[keep], cluster[keep], index)
    gap = np.sqrt(((points[pt] - index.centroids[tri]) ** 2).sum(axis=1)) - index.radii[tri]
    keep = gap < bound[pt]
    _exact_into(best, points, pt[keep], tri[keep], index.table)
    return best


def _nearest_cluster(points: np.ndarray, index: MeshDistanceIndex) -> np.ndarray:
    """The cluster whose box centre is nearest to each point."""
    if index.cluster_tree is None:
        gap = ((points[:, None] - index.box_centre[index.big][None]) ** 2).sum(-1)
        return index.big[gap.argmin(axis=1)]
    _, nearest = index.cluster_tree.query(points, k=1)
    return index.searched[nearest]


def _expand(pt: np.ndarray, cluster: np.ndarray, index: MeshDistanceIndex):
    """(point, cluster) pairs → (point, triangle) pairs over each cluster's triangles."""
    sizes = index.starts[cluster + 1] - index.starts[cluster]
    first = np.repeat(index.starts[cluster] - (np.cumsum(sizes) - sizes), sizes)
    return np.repeat(pt, sizes), first + np.arange(int(sizes.sum()))


def _exact_into(
    best: np.ndarray, points: np.ndarray, pt: np.ndarray, tri: np.ndarray, table: np.ndarray
) -> None:
    """best[p] = min(best[p], d²(points[p], triangle t)) over the pairs, in cache-sized batches."""
    for s in range(0, len(pt), _PAIRS_PER_BATCH):
        p, t = pt[s : s + _PAIRS_PER_BATCH], tri[s : s + _PAIRS_PER_BATCH]
        np.minimum.at(best, p, point_triangle_distances2(points[p].T, table[:, t]))


def _candidate_clusters(
    points: np.ndarray, bound: np.ndarray, index: MeshDistanceIndex
) -> tuple[np.ndarray, np.ndarray]:
    """(point, cluster) pairs: the searched clusters whose centre is within r = bound + search
    radius (the only ones whose box can be nearer than bound; the nearest few from a k-NN
    query, a ball query where more may lie within r), and every big cluster."""
    n = len(points)
    pts, clusters = [np.zeros(0, dtype=np.int64)], [np.zeros(0, dtype=np.int64)]
    if index.cluster_tree is not None:
        radius = bound + index.search_radius
        k = min(_NEIGHBOURS, index.searched.size)
        dist, near = index.cluster_tree.query(points, k=k, distance_upper_bound=radius.max())
        dist, near = dist.reshape(n, k), near.reshape(n, k)
        more = dist[:, -1] <= radius if k < index.searched.size else np.zeros(n, dtype=bool)
        inside = (dist <= radius[:, None]) & ~more[:, None]
        pts.append(np.nonzero(inside)[0])
        clusters.append(near[inside])
        if more.any():
            rows = np.flatnonzero(more)
            found = index.cluster_tree.query_ball_point(points[rows], radius[rows])
            lengths = np.fromiter(map(len, found), dtype=np.int64, count=rows.size)
            flat = np.fromiter(itertools.chain.from_iterable(found), np.int64, int(lengths.sum()))
            pts.append(np.repeat(rows, lengths))
            clusters.append(flat)
        clusters[1:] = [index.searched[c] for c in clusters[1:]]
    if index.big.size:
        pts.append(np.repeat(np.arange(n), index.big.size))
        clusters.append(np.tile(index.big, n))
    return np.concatenate(pts), np.concatenate(clusters)
