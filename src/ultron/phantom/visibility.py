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

A face is visible when its three vertices are; ``reference_visible.ply`` is the sub-mesh of
those faces. The test runs per chunk of frames, vectorised over all vertices.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ultron.data.dataset import ProbeGeometry
from ultron.errors import argument_error
from ultron.mesh.observed import observed_points, observed_submesh


@dataclass(frozen=True)
class VisibilityConfig:
    """The visibility criterion: largest incidence angle and smallest true transmission."""

    max_incidence_deg: float = 70.0
    min_transmission: float = 0.3

    def __post_init__(self) -> None:
        if not (math.isfinite(self.max_incidence_deg) and 0 <= self.max_incidence_deg <= 90):
            raise argument_error(
                "max_incidence_deg", f"expected an angle in [0, 90], got {self.max_incidence_deg}"
            )
        if not (math.isfinite(self.min_transmission) and 0 <= self.min_transmission <= 1):
            raise argument_error(
                "min_transmission", f"expected a value in [0, 1], got {self.min_transmission}"
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
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    return float(max(elevation_span_mm, 0.5 * np.median(steps)))


def visible_vertices(
    vertices: np.ndarray,
    normals: np.ndarray,
    probe_to_world: np.ndarray,
    transmission: np.ndarray,
    probe: ProbeGeometry,
    half_thickness_mm: float,
    config: VisibilityConfig | None = None,
) -> np.ndarray:
    """(M,) bool: vertex m is visible in some frame of one sweep (module doc).

    ``vertices``, ``normals`` (M, 3) (unit, outward), ``probe_to_world`` (N, 4, 4) the TRUE
    poses and ``transmission`` (N, H, W) their true transmission maps.
    """
    config = config or VisibilityConfig()
    v = np.asarray(vertices, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    poses = np.asarray(probe_to_world, dtype=np.float64)
    t_maps = np.asarray(transmission)
    if v.ndim != 2 or v.shape[1] != 3 or n.shape != v.shape:
        raise argument_error("vertices", f"expected (M, 3) vertices and normals, got {v.shape}")
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise argument_error("probe_to_world", f"expected (N, 4, 4) poses, got {poses.shape}")
    if t_maps.shape != (poses.shape[0], *probe.image_shape):
        raise argument_error(
            "transmission",
            f"expected shape {(poses.shape[0], *probe.image_shape)}, got {t_maps.shape}",
        )
    if not (math.isfinite(half_thickness_mm) and half_thickness_mm >= 0):
        raise argument_error("half_thickness_mm", f"expected ≥ 0, got {half_thickness_mm}")
    return observed_points(
        v, n, poses, probe, t_maps, half_thickness_mm, config.max_incidence_deg,
        config.min_transmission,
    )  # fmt: skip


def visible_submesh(mesh, visible: np.ndarray):
    """The sub-mesh of ``mesh``'s faces whose three vertices are ``visible`` (unreferenced
    vertices dropped, order kept), or None when no face is."""
    sub = observed_submesh(mesh, visible)
    return sub if len(sub.faces) else None


def reference_visibility(
    mesh,
    sweeps: Sequence[tuple[str, np.ndarray, np.ndarray]],
    probe: ProbeGeometry,
    elevation_span_mm: float,
    config: VisibilityConfig | None = None,
) -> tuple[Any, dict[str, Any]]:
    """The visible sub-mesh of the reference ``mesh`` (None when nothing is visible) and the
    criterion's parameters and counts (``phantom.json``'s ``"reference_visible"``).

    ``sweeps``: (name, TRUE poses (N, 4, 4), true transmission (N, H, W)) per sweep.
    """
    config = config or VisibilityConfig()
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
    visible = np.zeros(len(vertices), dtype=bool)
    slabs = {}
    for name, poses, transmission in sweeps:
        slabs[name] = slab_half_thickness_mm(poses, elevation_span_mm)
        visible |= visible_vertices(
            vertices, normals, poses, transmission, probe, slabs[name], config
        )
    submesh = visible_submesh(mesh, visible)
    info = {
        "criterion": "a vertex is visible if some frame (true pose) has it inside the image,"
        " within the elevational slab |probe z| <= h, its outward normal facing the transducer"
        " within max_incidence_deg, and the true transmission at its pixel (row floor(depth/dy),"
        " nearest column) >= min_transmission; a face if its three vertices are",
        "max_incidence_deg": config.max_incidence_deg,
        "min_transmission": config.min_transmission,
        "slab_half_thickness_mm": slabs,
        "vertices_visible": int(visible.sum()),
        "faces_visible": 0 if submesh is None else len(submesh.faces),
        "faces_total": len(mesh.faces),
    }
    return submesh, info
