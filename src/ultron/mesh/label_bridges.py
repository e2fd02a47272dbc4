"""Label support between labelled frames, where their labelled cross-sections agree.

Label support (:mod:`ultron.mesh.observed`) counts a reconstructed surface as observed near the
labelled surface of the frames a method trained on. Those frames are millimetres apart at
sparse labels (every tenth frame at 10 %), so the surface between them has only the
field's transmission and the echoes to stand on, and deep walls fail both.

Where two consecutive labelled frames A and B of a sweep show the *same* labelled cross-section,
the bone runs straight between them (a long bone scanned along its axis), and the surface that
joins their labelled surfaces is as well supported as they are. For a band-top point p of A,
with q its nearest band-top point of B and e A's elevation axis (the probe's +z in world,
unit), the distance across the beam plane is

    d⊥(p) = √(|q − p|² − ((q − p)·e)²),

the part of the offset that is not the frames' elevational gap. A and B *agree* when the
median of d⊥ over A's points (with A's axis) and the median over B's points (with B's axis)
are both ≤ τ. Between agreeing frames, every point p of either frame with d⊥(p) ≤ τ is joined
to its q by a segment sampled every ``step_mm``; the segments' points join the labelled
surface. τ is the label support distance itself: two cross-sections that agree to within the
distance at which the labels support a surface support the surface between them.

On a vertebra, whose cross-section changes within a few millimetres, consecutive labelled frames
rarely agree and nothing is added (figures in docs/real-sweeps.md).
"""

from __future__ import annotations

import itertools
import math

import numpy as np
from scipy.spatial import cKDTree

from ultron.data.dataset import SweepDataset
from ultron.data.labels import FrameSelection, labelled_surface_pixels
from ultron.errors import argument_error

#: Spacing (mm) of the points sampled along a bridge, a quarter of the default support distance.
BRIDGE_STEP_MM = 0.25


def across_plane_mm(
    points_mm: np.ndarray, other_mm: np.ndarray, elevation_axis: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """For each of ``points_mm`` (P, 3): the offset q − p to its nearest point q of
    ``other_mm`` (Q, 3), and d⊥ (module docstring), the offset's length across the plane whose
    normal is ``elevation_axis`` (3,; normalised here: a tracked pose's rotation is orthonormal
    only to the format's 1e-3). Returns (offsets (P, 3), d⊥ (P,))."""
    points_mm, other_mm = np.asarray(points_mm, float), np.asarray(other_mm, float)
    axis = np.asarray(elevation_axis, float)
    if points_mm.ndim != 2 or points_mm.shape[1] != 3 or not len(points_mm):
        raise argument_error(
            "points_mm", f"expected a non-empty (P, 3) array, got {points_mm.shape}"
        )
    if other_mm.ndim != 2 or other_mm.shape[1] != 3 or not len(other_mm):
        raise argument_error("other_mm", f"expected a non-empty (Q, 3) array, got {other_mm.shape}")
    norm = float(np.linalg.norm(axis)) if axis.shape == (3,) else math.nan
    if not (math.isfinite(norm) and norm > 0.5):
        raise argument_error(
            "elevation_axis", f"expected a finite 3-vector of length about 1 (> 0.5), got {axis!r}"
        )
    axis = axis / norm
    _, nearest = cKDTree(other_mm).query(points_mm)
    offsets = other_mm[nearest] - points_mm
    along = offsets @ axis
    return offsets, np.sqrt(np.maximum((offsets * offsets).sum(axis=1) - along**2, 0.0))


def bridge_points_mm(
    a_mm: np.ndarray,
    b_mm: np.ndarray,
    axis_a: np.ndarray,
    axis_b: np.ndarray,
    tolerance_mm: float,
    step_mm: float = BRIDGE_STEP_MM,
) -> np.ndarray:
    """The points (M, 3) of the bridges between two labelled frames' surfaces ``a_mm`` and
    ``b_mm`` with elevation axes ``axis_a`` and ``axis_b`` (module docstring, τ =
    ``tolerance_mm``); (0, 3) when the frames do not agree. Each segment p → q holds
    ⌈|q − p| / step_mm⌉ + 1 evenly spaced points, both ends included."""
    if not (math.isfinite(tolerance_mm) and tolerance_mm >= 0):
        raise argument_error("tolerance_mm", f"expected a finite value ≥ 0, got {tolerance_mm}")
    if not (math.isfinite(step_mm) and step_mm > 0):
        raise argument_error("step_mm", f"expected a finite value > 0, got {step_mm}")
    sides = [across_plane_mm(a_mm, b_mm, axis_a), across_plane_mm(b_mm, a_mm, axis_b)]
    if any(np.median(across) > tolerance_mm for _, across in sides):
        return np.zeros((0, 3))
    segments = []
    for start, (offsets, across) in zip((a_mm, b_mm), sides, strict=True):
        near = across <= tolerance_mm
        start, offsets = np.asarray(start, float)[near], offsets[near]
        counts = np.ceil(np.linalg.norm(offsets, axis=1) / step_mm).astype(np.int64) + 1
        for n in np.unique(counts):
            group = counts == n
            t = np.linspace(0.0, 1.0, int(n))[:, None, None]
            segments.append((start[group][None] + t * offsets[group][None]).reshape(-1, 3))
    return np.concatenate(segments) if segments else np.zeros((0, 3))


def bridged_labelled_surface_mm(
    dataset: SweepDataset,
    selection: FrameSelection | None,
    tolerance_mm: float,
    step_mm: float = BRIDGE_STEP_MM,
) -> np.ndarray:
    """The labelled surface of the selected frames
    (:func:`~ultron.data.labels.labelled_surface_pixels`, world mm) and the bridges
    (:func:`bridge_points_mm`) between each pair of consecutive selected frames of a sweep
    when both hold labelled surface (a selected frame without bone breaks the run); (0, 3)
    when ``selection`` is None or holds no bone label."""
    pixels = labelled_surface_pixels(dataset, selection)
    if pixels is None or selection is None:
        return np.zeros((0, 3))
    points = pixels.world_mm(dataset)
    by_frame = {key: points[index] for key, index in pixels.frame_groups().items()}
    parts = [points]
    for sweep_index, sweep in enumerate(dataset.sweeps):
        frames = np.sort(selection.frames.get(sweep.name, np.zeros(0, np.int64)))
        for first, second in itertools.pairwise(frames):
            a, b = by_frame.get((sweep_index, int(first))), by_frame.get((sweep_index, int(second)))
            if a is not None and b is not None:  # a selected frame without bone breaks the run
                axes = sweep.probe_to_world[[first, second], :3, 2]
                parts.append(bridge_points_mm(a, b, axes[0], axes[1], tolerance_mm, step_mm))
    return np.concatenate(parts)
