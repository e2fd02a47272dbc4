"""Stage-1 training data of RoCoSDF / Neural-Pull: subsampled input points and pulled queries.

Points: above ``max_points``, farthest-point samples of the configured sizes, concatenated
(both start at point 0, as the reference code's Open3D call does). σ_p = distance to the
``sigma_neighbour``-th nearest neighbour. Queries: ``queries_per_point`` per point,
q = p + N(0, σ_p²I), plus grid queries over [−0.5, 0.5]³ and [−1, 1]³; each query's target is
its nearest input point (KD-tree).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from ultron.errors import argument_error


class QueryConfig(Protocol):
    """The settings :func:`make_queries` reads (:class:`ultron.train.neural_pull.ViewFitConfig`
    has them)."""

    max_points: int
    fps_sizes: tuple[int, ...]
    sigma_neighbour: int
    queries_per_point: int
    grid_queries: int


def farthest_point_sampling(points: np.ndarray, n_samples: int, start: int = 0) -> np.ndarray:
    """Indices (n_samples,) of a greedy farthest-point sample of ``points`` (N, 3), from ``start``.

    Each step picks the point farthest from those chosen so far, keeping every point's squared
    distance to the chosen set: O(N) per sample, vectorised over the points with per-axis
    arrays and preallocated buffers (no (N, 3) temporaries).
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise argument_error("points", f"expected a non-empty (N, 3) array, got shape {pts.shape}")
    axes = np.ascontiguousarray(pts.T)
    n = min(int(n_samples), len(pts))
    chosen = np.empty(n, dtype=np.int64)
    distance = np.full(len(pts), np.inf)
    total, term = np.empty(len(pts)), np.empty(len(pts))
    current = int(start)
    for k in range(n):
        chosen[k] = current
        total.fill(0.0)
        for axis in axes:
            np.subtract(axis, axis[current], out=term)
            np.multiply(term, term, out=term)
            total += term
        np.minimum(distance, total, out=distance)
        current = int(np.argmax(distance))
    return chosen


def subsample_points(points: np.ndarray, max_points: int, fps_sizes: Sequence[int]) -> np.ndarray:
    """The cloud itself if it has ≤ ``max_points`` points, else its FPS samples of each size in
    ``fps_sizes`` concatenated (all from point 0, so smaller samples are prefixes of larger)."""
    if len(points) <= max_points:
        return np.asarray(points, dtype=np.float64)
    order = farthest_point_sampling(points, max(fps_sizes))
    return np.concatenate([np.asarray(points, dtype=np.float64)[order[:k]] for k in fps_sizes])


def neighbour_sigma(points: np.ndarray, k: int = 50) -> np.ndarray:
    """σ_p (N,): distance from each point to its k-th nearest point, itself counted first."""
    from scipy.spatial import cKDTree

    k = min(k, len(points))
    if k < 2:
        raise argument_error("points", f"need at least 2 points to set σ_p, got {len(points)}")
    distances, _ = cKDTree(points).query(points, k=k, workers=-1)
    return distances[:, -1]


def two_cube_grid_points(
    n: int, resolution: tuple[int, int], rng: np.random.Generator, jitter: bool = False
) -> np.ndarray:
    """``n`` distinct points of the union of a res₀³ grid over [−0.5, 0.5]³ and a res₁³ grid
    over [−1, 1]³ (drawn uniformly without replacement), float64 (n, 3). With ``jitter`` each
    point is moved uniformly within its grid cell (± half a spacing per axis)."""
    sizes = [r**3 for r in resolution]
    n = min(n, sum(sizes))
    flat = rng.choice(sum(sizes), size=n, replace=False)
    out = np.empty((n, 3))
    for which, (half, res) in enumerate(zip((0.5, 1.0), resolution, strict=True)):
        mask = (flat >= sizes[0]) if which else (flat < sizes[0])
        local = flat[mask] - (sizes[0] if which else 0)
        ijk = np.stack(np.unravel_index(local, (res, res, res)), axis=1)
        spacing = 2 * half / (res - 1)
        out[mask] = -half + ijk * spacing
        if jitter:
            out[mask] += (rng.random((len(local), 3)) - 0.5) * spacing
    return out


@dataclass(frozen=True)
class QuerySet:
    """Stage-1 training data: queries (Q, 3), their nearest input points (Q, 3), the input
    points used (N, 3) after subsampling, all float32 tensors in normalised coordinates."""

    queries: torch.Tensor
    targets: torch.Tensor
    points: torch.Tensor


def make_queries(
    points_unit: np.ndarray, config: QueryConfig, rng: np.random.Generator
) -> QuerySet:
    """Queries and targets for one view's cloud (see module doc)."""
    from scipy.spatial import cKDTree

    points = as_points(points_unit, "points_unit")
    points = subsample_points(points, config.max_points, config.fps_sizes)
    sigma = neighbour_sigma(points, config.sigma_neighbour)
    noise = rng.standard_normal((len(points), config.queries_per_point, 3))
    near = (points[:, None, :] + sigma[:, None, None] * noise).reshape(-1, 3)
    grid = two_cube_grid_points(config.grid_queries, (70, 50), rng)
    queries = np.concatenate([near, grid])
    _, nearest = cKDTree(points).query(queries, k=1, workers=-1)
    return QuerySet(
        queries=torch.from_numpy(queries).float(),
        targets=torch.from_numpy(points[nearest]).float(),
        points=torch.from_numpy(points).float(),
    )


def as_points(points: np.ndarray, name: str) -> np.ndarray:
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3 or len(array) < 2 or not np.isfinite(array).all():
        raise argument_error(
            name, f"expected a finite (N ≥ 2, 3) point array, got shape {array.shape}"
        )
    return array


def numpy_rng(generator: torch.Generator) -> np.random.Generator:
    """A numpy generator seeded from one draw of the torch ``generator`` (one seed, both libraries)."""
    seed = int(torch.randint(0, 2**62, (1,), generator=generator))
    return np.random.default_rng(seed)
