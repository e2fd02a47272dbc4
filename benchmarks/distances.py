"""Benchmark: exact point-to-surface distances (``ultron.metrics``) against a large mesh.

Builds the search index of MESH (default: the reference of a freshly simulated default L3
dataset, 320k faces) and measures the CPU and wall time of 100k points near the surface (the
mesh's own samples pushed 0.5 mm outwards, as an accuracy query) and of 20k points ~20 mm away
(a completeness query where a reconstruction misses a part), checking a sample of each against
a brute-force search over every triangle.

Usage::

    python benchmarks/distances.py                       # simulate L3 into a temporary folder
    python benchmarks/distances.py --mesh runs/l3/reference.ply --points 100000
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def timed(fn, *args):
    wall, cpu = time.perf_counter(), time.process_time()
    result = fn(*args)
    return result, time.perf_counter() - wall, time.process_time() - cpu


def brute_force(points: np.ndarray, mesh) -> np.ndarray:
    """min over every triangle of trimesh's closest-point distance (an independent kernel)."""
    from trimesh.triangles import closest_point

    tri = np.asarray(mesh.triangles)
    nearest = (closest_point(tri, np.broadcast_to(p, (len(tri), 3))) for p in points)
    return np.array(
        [np.linalg.norm(q - p, axis=1).min() for q, p in zip(nearest, points, strict=True)]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", type=Path, default=None, help="target mesh [default: L3]")
    parser.add_argument("--points", type=int, default=100_000)
    args = parser.parse_args()

    import trimesh

    from ultron.metrics import build_distance_index, mesh_distances

    with tempfile.TemporaryDirectory() as tmp:
        path = args.mesh
        if path is None:
            from ultron.phantom import SimulationConfig, simulate_dataset

            path = simulate_dataset(SimulationConfig(), out=Path(tmp) / "l3").reference
        mesh = trimesh.load(path, force="mesh", process=False)
    index, wall, cpu = timed(build_distance_index, np.asarray(mesh.triangles))
    print(f"mesh {path}: {len(mesh.faces)} faces; index {wall:.2f} s wall, {cpu:.2f} s CPU")
    rng = np.random.default_rng(0)
    points, faces = trimesh.sample.sample_surface(mesh, args.points, seed=0)
    near = points + 0.5 * np.asarray(mesh.face_normals)[faces]
    far = points[: args.points // 5] + rng.normal(scale=20.0, size=(args.points // 5, 3))
    for name, query in (("near (0.5 mm)", near), ("far (~20 mm)", far)):
        distances, wall, cpu = timed(mesh_distances, query, index)
        check = brute_force(query[:20], mesh)
        error = float(np.abs(distances[:20] - check).max())
        print(
            f"{name:>14}: {len(query)} points in {wall:.2f} s wall, {cpu:.2f} s CPU;"
            f" mean {distances.mean():.3f} mm; max |exact − brute force| {error:.1e} mm"
        )


if __name__ == "__main__":
    main()
