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

Where a vertex lies against the labels (:func:`surface_places`): in the labelled frame nearest
it in elevation, the label of its pixel and, where that pixel is unsure, whether its scanline
holds a band of bone labels above it (the vertex is in that band's acoustic shadow), below it
(the vertex is in lit tissue the beam crossed to reach the echo) or none. It says where surface
far from every label sits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ultron.data.dataset import ProbeGeometry
from ultron.data.geometry import probe_mm_to_pixel
from ultron.data.validation import LABEL_BACKGROUND, LABEL_TARGET, LABEL_UNANNOTATED
from ultron.errors import argument_error

#: The PLY vertex properties (and their types) that carry the evidence.
VERTEX_PROPERTIES = {"observed": np.uint8, "label_distance_mm": np.float32}
#: Distances (mm) from the labelled bone beyond which run.json counts a surface's vertices: a
#: count, unlike the percentiles, does not fall when surface near the labels is added.
FAR_FROM_LABELS_MM = (2.0, 3.0)


def nearest_distance_mm(
    points_mm: np.ndarray, targets_mm: np.ndarray, within_mm: float = math.inf
) -> np.ndarray:
    """d_i = min_j ‖points_i − targets_j‖ (P,) float64, exact (k-d tree); +∞ when there is no
    target, and where d_i > ``within_mm`` (a bound that lets the search stop early: a caller
    that only compares d with a distance gets the same answer sooner).

    The tree is scipy's sliding-midpoint one (``balanced_tree=False``), queried on the torch
    threads' count (:func:`~ultron.parallel.default_workers`): the same distances as the
    balanced tree's, found sooner on a surface's vertices against labelled echoes, which
    cluster (docs/decisions.md, "Nearest labelled points: an early stop and the unbalanced
    tree")."""
    from scipy.spatial import cKDTree

    from ultron.parallel import default_workers

    points = np.asarray(points_mm, dtype=np.float64)
    targets = np.asarray(targets_mm, dtype=np.float64)
    for name, value in (("points_mm", points), ("targets_mm", targets)):
        if value.ndim != 2 or value.shape[1] != 3:
            raise argument_error(name, f"expected (N, 3), got {value.shape}")
        if not np.isfinite(value).all():
            raise argument_error(name, "expected finite coordinates")
    if not within_mm >= 0:
        raise argument_error("within_mm", f"expected ≥ 0, got {within_mm}")
    if len(targets) == 0:
        return np.full(len(points), np.inf)
    if len(points) == 0:
        return np.zeros(0)
    tree = cKDTree(targets, balanced_tree=False, compact_nodes=False)
    # scipy's bound excludes a neighbour at it (and is squared): search a little beyond it,
    # then drop what lies beyond ``within_mm`` itself
    bound = within_mm * (1 + 1e-9) + 1e-9
    distance = tree.query(points, k=1, distance_upper_bound=bound, workers=default_workers())[0]
    distance[distance > within_mm] = np.inf
    return distance


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

    def merged(self, new_index: np.ndarray, n_vertices: int) -> SurfaceEvidence:
        """The evidence of a mesh whose vertex ``new_index[i]`` replaces vertex i (−1: gone;
        :func:`~ultron.mesh.extract.weld_coincident`): a merged vertex is observed when any of
        its copies is, at the least of their label distances (copies share a position)."""
        new_index = np.asarray(new_index, dtype=np.int64)
        if new_index.shape != self.observed.shape:
            raise argument_error("new_index", f"expected shape {self.observed.shape}")
        there = new_index >= 0
        observed = np.zeros(n_vertices, dtype=bool)
        np.logical_or.at(observed, new_index[there], self.observed[there])
        distance = np.full(n_vertices, np.inf)
        np.minimum.at(distance, new_index[there], np.asarray(self.label_distance_mm)[there])
        return SurfaceEvidence(observed, distance)

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


#: :func:`surface_places`' answers, by index: no labelled frame's slab holds the vertex; its
#: pixel is labelled bone / background; it is unsure with a band of bone labels above it in its
#: scanline (in the band's shadow), below it (in the tissue above the echo), or no band.
SURFACE_PLACES = (
    "between_frames", "bone_label", "background_label", "below_band", "above_band", "no_band"
)  # fmt: skip


def surface_places(
    vertices_mm: np.ndarray,
    probe_to_world: np.ndarray,
    probe: ProbeGeometry,
    labels: np.ndarray,
    slab_half_thickness_mm: float,
) -> np.ndarray:
    """Index into :data:`SURFACE_PLACES` (V,) int8 of each vertex (V, 3) against the labelled
    frames (``probe_to_world`` (N, 4, 4), ``labels`` (N, H, W) uint8, row 0 at the transducer).

    The frame of vertex v is the one that holds it in its image (p = P_k⁻¹ v: |p_x| ≤ W_mm/2,
    0 ≤ p_y ≤ D_mm) with the smallest elevation |p_z|, none where that exceeds
    ``slab_half_thickness_mm``; its pixel is (⌊p_y/Δ⌉, ⌊p_x/Δ + W/2⌉), clipped to the frame. An
    unsure pixel (r, c) is ``below_band`` when a bone label lies in column c above row r,
    ``above_band`` when the column's bone labels all lie below it, ``no_band`` when it has none.
    """
    points = np.asarray(vertices_mm, dtype=np.float64)
    poses = np.asarray(probe_to_world, dtype=np.float64)
    labels = np.asarray(labels)
    if points.ndim != 2 or points.shape[1] != 3 or not np.isfinite(points).all():
        raise argument_error("vertices_mm", f"expected finite (V, 3), got {points.shape}")
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or not np.isfinite(poses).all():
        raise argument_error("probe_to_world", f"expected finite (N, 4, 4), got {poses.shape}")
    if labels.dtype != np.uint8 or labels.shape != (len(poses), *probe.image_shape):
        raise argument_error(
            "labels",
            f"expected uint8 {(len(poses), *probe.image_shape)}, got {labels.dtype} {labels.shape}",
        )
    if not (math.isfinite(slab_half_thickness_mm) and slab_half_thickness_mm >= 0):
        raise argument_error("slab_half_thickness_mm", "expected a finite value ≥ 0")
    best = np.full(len(points), np.inf)
    frame = np.full(len(points), -1)
    rows = np.zeros(len(points), dtype=np.int64)
    cols = np.zeros(len(points), dtype=np.int64)
    for k, pose in enumerate(poses):
        local = (points - pose[:3, 3]) @ pose[:3, :3]  # P⁻¹ v for a rigid P
        x, y, z = local[:, 0], local[:, 1], np.abs(local[:, 2])
        inside = (np.abs(x) <= probe.width_mm / 2) & (y >= 0) & (y <= probe.depth_mm)
        closer = inside & (z <= slab_half_thickness_mm) & (z < best)
        r, c = probe_mm_to_pixel(x[closer], y[closer], probe)
        best[closer], frame[closer] = z[closer], k
        rows[closer] = np.clip(np.rint(r), 0, probe.height_px - 1)
        cols[closer] = np.clip(np.rint(c), 0, probe.width_px - 1)
    places = np.zeros(len(points), dtype=np.int8)  # between_frames
    seen = frame >= 0
    value = labels[frame[seen], rows[seen], cols[seen]]
    if not np.isin(value, (LABEL_TARGET, LABEL_BACKGROUND, LABEL_UNANNOTATED)).all():
        raise argument_error("labels", "expected the values 0, 1 and 255 only")
    bone = labels[frame[seen], :, cols[seen]] == LABEL_TARGET  # (S, H): each vertex's scanline
    height = np.arange(probe.height_px)
    above = (bone & (height[None] < rows[seen, None])).any(axis=1)
    below = (bone & (height[None] > rows[seen, None])).any(axis=1)
    place = np.select(
        [value == LABEL_TARGET, value == LABEL_BACKGROUND, above, below],
        [1, 2, 3, 4],
        default=5,
    )
    places[seen] = place
    return places
