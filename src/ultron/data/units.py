"""Warnings for geometry that is implausible in millimetres: poses recorded in metres, a
reference mesh in other units or far from the scanned region.

ultron reads every length in millimetres and cannot tell a 50 mm probe path recorded in metres
(0.05) from a probe held still; what it can tell is that the numbers do not fit together:

* the probe path: the frame origins of a sweep of at least :data:`MIN_FRAMES` frames span less
  than 1/:data:`PATH_RATIO` of the probe's width (a 40 mm probe moved 0.4 mm in all);
* two boxes that should overlap (a reference and the field of view, a mesh and its
  reference): their sizes differ by more than :data:`SIZE_RATIO`× or they lie further apart
  than the larger one's size.

Each is a warning, not an error: a user may know better.
"""

from __future__ import annotations

import numpy as np

from ultron.data.dataset import SweepDataset
from ultron.data.geometry import field_of_view_bounds_mm

#: Sweeps with fewer frames are not judged by their path.
MIN_FRAMES = 10
#: A path spanning less than the probe's width / PATH_RATIO is implausible.
PATH_RATIO = 100.0
#: Boxes that should overlap but differ in size by more than this factor.
SIZE_RATIO = 20.0


def path_warnings(dataset: SweepDataset) -> list[str]:
    """One line per sweep whose probe path is implausibly short for the probe (module doc)."""
    lines = []
    width = dataset.probe.width_mm
    for sweep in dataset.sweeps:
        if sweep.n_frames < MIN_FRAMES:
            continue
        origins = sweep.probe_to_world[:, :3, 3]
        span = float(np.linalg.norm(origins.max(axis=0) - origins.min(axis=0)))
        if span < width / PATH_RATIO:
            lines.append(
                f"sweep {sweep.name}: the probe's path spans {span:.3g} mm over"
                f" {sweep.n_frames} frames for a {width:g} mm wide probe: are the poses in"
                " metres? ultron reads millimetres"
            )
    return lines


def box_mismatch(box: np.ndarray, other: np.ndarray, name: str, other_name: str) -> str | None:
    """A warning when ``box`` (2, 3) and ``other`` (2, 3), in mm, cannot be the same object in
    the same units (module doc); None when they fit."""
    box, other = np.asarray(box, float), np.asarray(other, float)
    size = float(np.linalg.norm(box[1] - box[0]))
    other_size = float(np.linalg.norm(other[1] - other[0]))
    if min(size, other_size) <= 0:
        return None
    ratio = max(size, other_size) / min(size, other_size)
    if ratio > SIZE_RATIO:
        return (
            f"{name} is {size:.3g} mm across and {other_name} {other_size:.3g} mm"
            f" ({ratio:.0f}×): are both in millimetres?"
        )
    gap = np.maximum(0.0, np.maximum(box[0] - other[1], other[0] - box[1]))
    distance = float(np.linalg.norm(gap))
    if distance > max(size, other_size):
        return (
            f"{name} lies {distance:.3g} mm away from {other_name}: are both in the same frame"
            " and in millimetres?"
        )
    return None


def units_warnings(
    dataset: SweepDataset, reference_vertices: np.ndarray | None = None
) -> list[str]:
    """The probe paths' warnings and, given the reference's vertices (V, 3) mm, whether the
    reference fits the scanned region (the frames' field of view)."""
    lines = path_warnings(dataset)
    if reference_vertices is not None and len(reference_vertices):
        vertices = np.asarray(reference_vertices, float)
        reference_box = np.stack([vertices.min(axis=0), vertices.max(axis=0)])
        scanned = field_of_view_bounds_mm(dataset.all_poses(), dataset.probe).numpy()
        mismatch = box_mismatch(reference_box, scanned, "the reference", "the scanned region")
        if mismatch is not None:
            lines.append(mismatch)
    return lines
