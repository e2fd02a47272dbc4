"""Exact point-to-triangle-mesh distances, through libigl's AABB tree.

The distance from a point p to a mesh is the minimum over its triangles T of

    d(p, T) = min_{q ∈ T} |p − q|,

where the closest point q lies inside T (then d is the height of p over T's plane), on one of
T's edges or at one of its vertices. libigl's ``AABB.squared_distance`` finds that minimum
exactly (a bounding-volume hierarchy pruned with lower bounds, then the closed-form closest
point of each remaining triangle; up to floating-point rounding, ≈ 1e-12 mm) in C++.

It replaced a hand-written numpy search (KD-trees of triangle clusters) because it is faster
with the same distances (``benchmarks/distances.py`` measures it and checks against an
independent brute force; figures in docs/decisions.md#surface-distances-libigl-metricsdistancepy).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ultron.errors import argument_error

#: Points per libigl call: bounds the (n, 3) closest-point arrays it returns.
_POINTS_PER_CHUNK = 262_144


@dataclass(frozen=True)
class MeshDistanceIndex:
    """The search structure of :func:`mesh_distances` for one mesh: ``vertices`` (V, 3) float64,
    ``faces`` (F, 3) int64 and libigl's AABB ``tree`` built over them."""

    vertices: np.ndarray
    faces: np.ndarray
    tree: Any

    @property
    def n_triangles(self) -> int:
        return int(self.faces.shape[0])


def build_distance_index(triangles: np.ndarray) -> MeshDistanceIndex:
    """Index (F, 3, 3) triangle vertices (mm) for :func:`mesh_distances`; F ≥ 1."""
    import igl

    tri = np.asarray(triangles, dtype=np.float64)
    if tri.ndim != 3 or tri.shape[1:] != (3, 3) or tri.shape[0] == 0:
        raise argument_error("triangles", f"expected shape (F ≥ 1, 3, 3), got {tri.shape}")
    if not np.isfinite(tri).all():
        raise argument_error("triangles", "vertices contain NaN or inf")
    vertices = np.ascontiguousarray(tri.reshape(-1, 3))
    faces = np.arange(len(vertices), dtype=np.int64).reshape(-1, 3)
    tree = igl.AABB()
    tree.init(vertices, faces)
    return MeshDistanceIndex(vertices, faces, tree)


def mesh_distances(points: np.ndarray, index: MeshDistanceIndex) -> np.ndarray:
    """Exact distance (mm) from each of ``points`` (n, 3) to the indexed mesh (module doc)."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise argument_error("points", f"expected shape (n, 3), got {points.shape}")
    if not np.isfinite(points).all():
        raise argument_error("points", "contain NaN or inf")
    out = np.empty(len(points))
    for start in range(0, len(points), _POINTS_PER_CHUNK):
        chunk = np.ascontiguousarray(points[start : start + _POINTS_PER_CHUNK])
        squared, _, _ = index.tree.squared_distance(index.vertices, index.faces, chunk)
        out[start : start + len(chunk)] = np.sqrt(np.maximum(squared, 0.0))
    return out


__all__ = ["MeshDistanceIndex", "build_distance_index", "mesh_distances"]
