"""What backs each vertex of a reconstructed surface: was it observed, and how far is the
nearest labelled bone echo.

Per vertex v of a surface:

* ``observed`` — some frame observed v (:mod:`ultron.mesh.observed`: in a frame's image and
  elevational slab, facing the probe, T ≥ the threshold just above it). An *inferred* vertex
  (observed = 0) is shape the method filled in where no frame saw bone: shadow walls and
  floors, the far side of a vertebra.
* ``label_distance_mm`` — d(v) = min_p ‖v − p‖ over the world positions p of the bone-labelled
  pixels the method was trained on: how far the surface is from the nearest annotated
  evidence (∞ when the method used no bone label). It is the uncertainty written with the
  mesh: the occupancy's entropy, the other candidate, is ≈ 1 bit on every iso-surface vertex by
  construction (f = ½ there) and says nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ultron.errors import argument_error

#: The PLY vertex properties (and their types) that carry the evidence.
VERTEX_PROPERTIES = {"observed": np.uint8, "label_distance_mm": np.float32}
#: Distances (mm) from the labelled bone beyond which run.json counts a surface's vertices: a
#: count, unlike the percentiles, does not fall when surface near the labels is added.
FAR_FROM_LABELS_MM = (2.0, 3.0)


def nearest_distance_mm(points_mm: np.ndarray, targets_mm: np.ndarray) -> np.ndarray:
    """d_i = min_j ‖points_i − targets_j‖ (P,) float64, exact (k-d tree); +∞ when there is no
    target."""
    from scipy.spatial import cKDTree

    points = np.asarray(points_mm, dtype=np.float64)
    targets = np.asarray(targets_mm, dtype=np.float64)
    for name, value in (("points_mm", points), ("targets_mm", targets)):
        if value.ndim != 2 or value.shape[1] != 3:
            raise argument_error(name, f"expected (N, 3), got {value.shape}")
        if not np.isfinite(value).all():
            raise argument_error(name, "expected finite coordinates")
    if len(targets) == 0:
        return np.full(len(points), np.inf)
    if len(points) == 0:
        return np.zeros(0)
    return cKDTree(targets).query(points, k=1)[0]


@dataclass(frozen=True)
class SurfaceEvidence:
    """Per vertex of one mesh: ``observed`` (V,) bool and ``label_distance_mm`` (V,) float."""

    observed: np.ndarray
    label_distance_mm: np.ndarray

    def __post_init__(self) -> None:
        observed = np.asarray(self.observed)
        if observed.ndim != 1 or observed.dtype != bool:
            raise argument_error("observed", "expected a (V,) boolean array")
        if np.shape(self.label_distance_mm) != observed.shape:
            raise argument_error("label_distance_mm", f"expected shape {observed.shape}")

    def vertex_attributes(self) -> dict[str, np.ndarray]:
        """The PLY vertex properties (:data:`VERTEX_PROPERTIES`)."""
        values = {"observed": self.observed, "label_distance_mm": self.label_distance_mm}
        return {k: np.asarray(values[k]).astype(t) for k, t in VERTEX_PROPERTIES.items()}

    def summary(self) -> dict[str, Any]:
        """run.json's account: vertex count, share observed, label distance median / 95th
        percentile / max over the vertices with a finite distance (None when there is none),
        and how many vertices lie farther than each of :data:`FAR_FROM_LABELS_MM` from every
        label (``vertices_beyond_mm``; None without labels)."""
        n = int(self.observed.size)
        finite = np.asarray(self.label_distance_mm, dtype=np.float64)
        finite = finite[np.isfinite(finite)]
        stats = beyond = None
        if finite.size:
            stats = {"median": float(np.median(finite)), "p95": float(np.percentile(finite, 95)),
                     "max": float(finite.max())}  # fmt: skip
            beyond = {f"{d:g}": int(np.count_nonzero(finite > d)) for d in FAR_FROM_LABELS_MM}
        return {
            "vertices": n,
            "observed_share": float(self.observed.mean()) if n else math.nan,
            "label_distance_mm": stats,
            "vertices_beyond_mm": beyond,
        }


def surface_evidence(
    vertices_mm: np.ndarray, observed: np.ndarray, bone_points_mm: np.ndarray
) -> SurfaceEvidence:
    """The evidence of a surface with ``vertices_mm`` (V, 3), their ``observed`` flags (V,)
    and the labelled bone points (P, 3) its method used (module docstring)."""
    vertices = np.asarray(vertices_mm, dtype=np.float64)
    flags = np.asarray(observed)
    if flags.shape != (len(vertices),) or flags.dtype != bool:
        raise argument_error("observed", f"expected ({len(vertices)},) booleans")
    return SurfaceEvidence(flags, nearest_distance_mm(vertices, bone_points_mm))
