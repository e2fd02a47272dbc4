"""Which part of the reference surface the simulated sweeps could see (``reference_visible.ply``).

Ground truth for diagnosis only: the metrics' visible completeness and CD
(:mod:`ultron.metrics.surface`) are measured against it; no reconstruction reads it.

A vertex v (outward unit normal n) of the reference mesh is visible when SOME frame, at its
TRUE pose (rotation columns x̂, ŷ (the beam), ẑ (elevation), origin t), sees it: with
(x, y, z) = ((v − t)·x̂, (v − t)·ŷ, (v − t)·ẑ) its probe coordinates,

* in the image: |x| ≤ W_mm/2 and 0 ≤ y ≤ D_mm;
* in the elevational slab: |z| ≤ h, h = max(elevation_span_mm, ½·median frame spacing of the
  sweep), so that consecutive frames cover the whole sweep;
* facing the transducer within the incidence limit: −n·ŷ ≥ cos θ_max (θ_max = 70°);
* not shadowed: the frame's true transmission (:mod:`ultron.phantom.simulator`) just above
  it, at row ⌊y/Δ⌋ and the nearest column round(x/s_lat + W/2), is ≥ T_min (0.3).

This is :func:`ultron.mesh.observed.observed_points` (the one implementation of "observed")
with the true poses and the true transmission. A face is visible when its three vertices are;
``reference_visible.ply`` is the sub-mesh of those faces.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ultron.data.dataset import ProbeGeometry
from ultron.data.geometry import median_frame_gap_mm
from ultron.errors import argument_error
from ultron.mesh.observed import (
    DEFAULT_MAX_INCIDENCE_DEG,
    DEFAULT_MIN_TRANSMISSION,
    observed_points,
    observed_submesh,
)


def slab_half_thickness_mm(probe_to_world: np.ndarray, elevation_span_mm: float) -> float:
    """h = max(elevation_span_mm, ½·median |t_{i+1} − t_i|) over the sweep's frame origins."""
    poses = np.asarray(probe_to_world, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or poses.shape[0] < 1:
        raise argument_error("probe_to_world", f"expected (N, 4, 4) poses, got {poses.shape}")
    if not (math.isfinite(elevation_span_mm) and elevation_span_mm >= 0):
        raise argument_error("elevation_span_mm", f"expected ≥ 0, got {elevation_span_mm}")
    if poses.shape[0] < 2:
        return float(elevation_span_mm)
    return float(max(elevation_span_mm, 0.5 * median_frame_gap_mm(poses)))


def reference_visibility(
    mesh,
    sweeps: Sequence[tuple[str, np.ndarray, np.ndarray]],
    probe: ProbeGeometry,
    elevation_span_mm: float,
    max_incidence_deg: float = DEFAULT_MAX_INCIDENCE_DEG,
    min_transmission: float = DEFAULT_MIN_TRANSMISSION,
) -> tuple[Any, dict[str, Any]]:
    """The visible sub-mesh of the reference ``mesh`` (None when nothing is visible) and the
    criterion's parameters and counts (``phantom.json``'s ``"reference_visible"``).

    ``sweeps``: (name, TRUE poses (N, 4, 4), true transmission (N, H, W)) per sweep.
    """
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
    visible = np.zeros(len(vertices), dtype=bool)
    slabs = {}
    for name, poses, transmission in sweeps:
        slabs[name] = slab_half_thickness_mm(poses, elevation_span_mm)
        visible |= observed_points(
            vertices, normals, poses, probe, transmission, slabs[name], max_incidence_deg,
            min_transmission,
        )  # fmt: skip
    submesh = observed_submesh(mesh, visible)
    info = {
        "criterion": "a vertex is visible if some frame (true pose) has it inside the image,"
        " within the elevational slab |probe z| <= h, its outward normal facing the transducer"
        " within max_incidence_deg, and the true transmission at its pixel (row floor(depth/dy),"
        " nearest column) >= min_transmission; a face if its three vertices are",
        "max_incidence_deg": max_incidence_deg,
        "min_transmission": min_transmission,
        "slab_half_thickness_mm": slabs,
        "vertices_visible": int(visible.sum()),
        "faces_visible": len(submesh.faces),
        "faces_total": len(mesh.faces),
    }
    return (submesh if len(submesh.faces) else None), info
