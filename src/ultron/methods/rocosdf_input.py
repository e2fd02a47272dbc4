"""RoCoSDF's input: each view's bone points in world mm, and their normalisation.

Input (:func:`view_point_clouds`): the bone pixels (label 1) of the selected frames, mapped to
world mm through their own frame's pose, grouped into two views:

* ``row``: sweeps of kind ``row`` AND of kind ``tilted``. The simulator's tilted sweeps
  (``ultron.phantom.protocols``: ``tilt_p10`` / ``tilt_m10``) are the row sweep with the probe
  rotated ±10° about its elevation axis: the image plane stays transverse and the probe still
  moves cranio-caudally, so their elevational smear lies along the same world axis as the row
  sweep's. They carry the row view's information (and the row view's artefact), so they join
  the row group; a separate group would need a third SDF that RoCoSDF does not have.
* ``column``: sweeps of kind ``column``. Sweeps of kind ``other`` are not used.

With ``voxel_mm`` (default 0.5 mm) each group's points are compounded into a voxel mask (a
lattice anchored at the world origin, shared by both groups) and replaced by the centres of the
occupied voxels — the code's input is the segmented volumetric mask as a point cloud. No hole
filling is done between frames: each voxel holds what was observed.

RoCoSDF (two views) refuses a view whose bone points lie in one plane (:func:`check_views_fusable`):
from a single frame (or frames at one position) the view's SDF is a thin shell around a planar
curve, the fused f_csg has a zero level only where the two shells cross, and stage 2's
near-surface sampling then accepts almost none of its candidates per round: it would run all
its rounds, for many minutes, after stage 1's (figures in
docs/decisions.md#rocosdf-one-plane-views-methodsrocosdf_inputpy).

Normalisation (:func:`cloud_normalisation`, a :class:`~ultron.data.geometry.UnitCube`): ONE
transform for all views, u = (x − c)/s with c the centre of the union's bounding box and s its
largest extent (mm), so the data lies in [−0.5, 0.5]³; every output is mapped back to mm. UNSR
on a single view uses the same transform (and meshing box) as RoCoSDF whenever the other view
has bone points too — its field is then exactly RoCoSDF's stage-1 field of that view, as in the
paper's figures — and otherwise the view's own.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from types import MappingProxyType

import numpy as np

from ultron.data.dataset import SweepDataset
from ultron.data.geometry import UnitCube
from ultron.data.labels import FrameSelection, gather_labelled_pixels
from ultron.errors import UltronInputError, argument_error

VIEWS = ("row", "column")
VIEW_KINDS = MappingProxyType({"row": ("row", "tilted"), "column": ("column",)})


def cloud_normalisation(clouds: Iterable[np.ndarray]) -> UnitCube:
    """The normalisation of the union of ``clouds`` (each (N, 3) mm, not all empty), as
    RoCoSDF's code sets it: centred on the union's bounding box, ``half_extent_mm`` = its
    *largest extent* (not half of it), so the clouds lie in [−0.5, 0.5]³ (module doc)."""
    stacked = [np.asarray(c, dtype=np.float64).reshape(-1, 3) for c in clouds]
    points = np.concatenate(stacked) if stacked else np.zeros((0, 3))
    if len(points) == 0 or not np.isfinite(points).all():
        raise argument_error("clouds", "expected finite points, got none or non-finite ones")
    lo, hi = points.min(axis=0), points.max(axis=0)
    extent = float((hi - lo).max())
    return UnitCube(tuple(float(c) for c in (lo + hi) / 2), max(extent, 1e-6))


def check_views(views: Sequence[str]) -> tuple[str, ...]:
    """``views`` (a name or names among :data:`VIEWS`, distinct) in canonical order."""
    chosen = tuple(views) if not isinstance(views, str) else (views,)
    if not chosen or len(set(chosen)) != len(chosen) or any(v not in VIEWS for v in chosen):
        raise argument_error("views", f"expected distinct views among {VIEWS}, got {views!r}")
    return tuple(v for v in VIEWS if v in chosen)  # canonical order


def _voxel_centres(points_mm: np.ndarray, voxel_mm: float) -> np.ndarray:
    """Centres of the voxels (lattice anchored at the world origin) holding any of the points."""
    index = np.unique(np.floor(points_mm / voxel_mm).astype(np.int64), axis=0)
    return (index + 0.5) * voxel_mm


def view_point_clouds(
    dataset: SweepDataset,
    selection: FrameSelection,
    voxel_mm: float | None = 0.5,
    views: Sequence[str] = VIEWS,
    dataset_name: str | None = None,
) -> dict[str, np.ndarray]:
    """World-mm bone points (N, 3) float64 of each view in ``views`` (see module doc).

    Raises :class:`UltronInputError` when the dataset has no sweep of a view's kinds, or when a
    view has no bone pixel (label 1) in the selected frames.
    """
    views = check_views(views)
    if voxel_mm is not None and not (np.isfinite(voxel_mm) and voxel_mm > 0):
        raise argument_error("voxel_mm", f"expected None or > 0, got {voxel_mm}")
    where = dataset_name or "dataset"
    kinds = ", ".join(f"{s.name} ({s.kind})" for s in dataset.sweeps)
    for view in views:
        if not any(s.kind in VIEW_KINDS[view] for s in dataset.sweeps):
            raise UltronInputError(
                where,
                "sweeps",
                f"RoCoSDF's {view} view needs a sweep of kind {' or '.join(VIEW_KINDS[view])!r};"
                f" the dataset has: {kinds}",
            )
    pixels = gather_labelled_pixels(dataset, selection)
    clouds: dict[str, np.ndarray] = {}
    for view in views:
        view_sweeps = [i for i, s in enumerate(dataset.sweeps) if s.kind in VIEW_KINDS[view]]
        bone = np.flatnonzero(np.isin(pixels.sweep_index, view_sweeps) & (pixels.label == 1))
        if bone.size == 0:
            names = [s.name for s in dataset.sweeps if s.kind in VIEW_KINDS[view]]
            raise UltronInputError(
                where,
                "labels",
                f"the selected frames of the {view} view's sweeps {names} contain no bone pixel (label 1)",
            )
        points = pixels.world_mm(dataset, bone)
        clouds[view] = _voxel_centres(points, voxel_mm) if voxel_mm is not None else points
        if len(clouds[view]) < 2:
            raise UltronInputError(
                where,
                "labels",
                f"the {view} view has {len(clouds[view])} bone point(s); at least 2 are needed",
            )
    return clouds


#: A view's bone points must span at least this many voxels (or finest pixel spacings, without
#: voxels) across their thinnest direction: one plane's voxel centres span up to √3 voxels.
MIN_THICKNESS_VOXELS = 2.0


def cloud_thickness_mm(points_mm: np.ndarray) -> float:
    """Extent (mm) of points (N, 3) along their thinnest principal direction (0 for < 3)."""
    points = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    if len(points) < 3:
        return 0.0
    centred = points - points.mean(axis=0)
    _, vectors = np.linalg.eigh(centred.T @ centred)
    return float(np.ptp(centred @ vectors[:, 0]))


def check_views_fusable(
    dataset: SweepDataset,
    selection: FrameSelection,
    clouds_mm: dict[str, np.ndarray],
    voxel_mm: float | None,
    dataset_name: str | None = None,
) -> None:
    """Refuse (one-line :class:`UltronInputError`) a view whose bone points lie in one plane:
    RoCoSDF's fusion needs each view spread across frames at different positions (module doc)."""
    probe = dataset.probe
    spacing = voxel_mm or min(probe.axial_spacing_mm, probe.lateral_spacing_mm)
    needed = MIN_THICKNESS_VOXELS * spacing
    for view, points in clouds_mm.items():
        thickness = cloud_thickness_mm(points)
        if thickness >= needed:
            continue
        names = [s.name for s in dataset.sweeps if s.kind in VIEW_KINDS[view]]
        n_frames = sum(len(selection.frames.get(name, ())) for name in names)
        raise UltronInputError(
            dataset_name or "dataset", "labels", f"RoCoSDF fuses two views, but the {view}"
            f" view's bone points lie in one plane ({thickness:.2g} mm across it, from"
            f" {n_frames} selected frame(s) of sweeps {names}), so its fusion would find almost"
            f" no surface and run for many minutes; each view needs bone labelled in frames"
            f" ≥ {needed:g} mm apart: use more frames (--label-fraction) or unsr-row / unsr-col",
        )  # fmt: skip
