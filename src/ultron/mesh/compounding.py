"""Label compounding: the no-learning baseline that users run today in 3D Slicer / PLUS.

The annotated pixels of the selected frames are pasted into a voxel grid with their poses by
the splatting ``ultron compound`` uses for B-mode images (:mod:`ultron.mesh.splat`: nearest or
linear, mean or max), the holes between frames are filled (:mod:`ultron.mesh.holes`), and the
result is meshed by the same smoothing + marching cubes as every other method.

What each pixel carries (``signed_distance``, the default): not its label but its in-frame
signed distance to the edge of the bone label (mm, positive in bone, from the frame's 2D
Euclidean distance transforms with the pixel spacings, truncated at ± ``clip_mm``; 255 pixels
count as not bone and are not splatted, except those directly above a band of bone labels,
within ``outer_side_mm`` of its top edge (:func:`~ultron.data.labels.surface_outer_side`): the
label puts the surface at that edge, and splatting its outer side keeps the surface there.
Without it, where the labeller leaves a gap of unsure pixels above the band (``label --auto``
claims background only ≥ 1.5 mm above any echo that could be bone), the hole filling carries
the band's values into the gap and the surface moves out by about half the gap: figures in
docs/real-sweeps.md#compounding-automatic-labels-the-surface-at-the-labels-top-edge).
Interpolating signed distances between frames moves a contour smoothly from one frame to the
next (shape-based interpolation), where interpolating 0/1 labels puts a step halfway. The
volume written is the occupancy clip(0.5 + d / (2·clip_mm), 0, 1), so its 0.5 level is the
zero of the signed distance; with ``signed_distance=False`` it is the compounded label (mean
or max of 0/1).

Hole filling, within ``hole_fill_radius_mm`` r: first PLUS's stick filler with sticks up to
2r (:func:`~ultron.mesh.holes.fill_holes_stick`: linear interpolation between the two frames on
either side of a hole), then the nearest observed voxel for what is left within r of one (sweep
ends, where no second frame lies beyond). The default r is half the largest median gap between
consecutive selected frames of a sweep (at least a voxel diagonal, √3 voxels; at most 10 mm):
the smallest radius that closes the gaps a sparse label fraction leaves between frames, without
inventing bone far from any annotation.

Why (issue 17): the previous baseline filled holes with a Gaussian-weighted average of the 0/1
labels (σ = r/2); across a ≈ 2 mm band of bone labels with 0s above and below, that average
never reached 0.5, so no hole became bone, and the constrained smoothing then erased most of
the one-voxel-thick sheets the labelled frames left (figures in
docs/decisions.md#label-compounding-hole-filling-meshcompoundingpy). ``reconstruct`` also
meshed the band's closed surface, floor and walls included; it now keeps the surface some
frame faces (:func:`ultron.methods.evidence.faced_observation`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ultron.data.dataset import SweepDataset
from ultron.data.geometry import median_frame_gap_mm
from ultron.data.labels import (
    OUTER_SIDE_MM,
    FrameSelection,
    LabelledPixels,
    bone_points_mm,
    count_labelled_pixels,
    gather_labelled_pixels,
    selection_chunks,
)
from ultron.data.resolution import resolved_spacing_mm
from ultron.errors import UltronInputError, argument_error
from ultron.mesh.grid import GridSpec, meshing_voxel_mm
from ultron.mesh.holes import fill_holes_nearest, fill_holes_stick
from ultron.mesh.splat import SplatConfig, Splatter
from ultron.parallel import thread_map

MAX_AUTO_RADIUS_MM = 10.0
#: Image pixels whose labels are splatted at a time (:func:`compound_labels`).
CHUNK_PIXELS = 2**21
#: Accepted spellings of the interpolation (``trilinear`` is the earlier name of ``linear``).
_INTERPOLATIONS = {"nearest": "nearest", "linear": "linear", "trilinear": "linear"}


@dataclass(frozen=True)
class CompoundingConfig:
    """Settings of :func:`compound_labels` (``None`` = derived from the data, see module doc;
    the voxel: the finer pixel spacing, grown where the bone's box would hold more than
    :data:`~ultron.mesh.grid.MAX_REGION_VOXELS` voxels, :func:`~ultron.mesh.grid.meshing_voxel_mm`)."""

    voxel_mm: float | None = None
    mode: str = "mean"
    interpolation: str = "nearest"
    hole_fill_radius_mm: float | None = None
    margin_mm: float = 5.0
    signed_distance: bool = True
    clip_mm: float = 2.0
    outer_side_mm: float = OUTER_SIDE_MM

    def __post_init__(self) -> None:
        if self.mode not in ("mean", "max"):
            raise argument_error("mode", f"expected 'mean' or 'max', got {self.mode!r}")
        if self.interpolation not in _INTERPOLATIONS:
            raise argument_error(
                "interpolation", f"expected 'nearest' or 'linear', got {self.interpolation!r}"
            )
        if self.voxel_mm is not None and not self.voxel_mm > 0:
            raise argument_error("voxel_mm", f"expected a positive size, got {self.voxel_mm}")
        if self.hole_fill_radius_mm is not None and not self.hole_fill_radius_mm >= 0:
            raise argument_error(
                "hole_fill_radius_mm", f"expected ≥ 0, got {self.hole_fill_radius_mm}"
            )
        if not self.outer_side_mm >= 0:
            raise argument_error("outer_side_mm", f"expected ≥ 0, got {self.outer_side_mm}")
        if not self.clip_mm > 0:
            raise argument_error("clip_mm", f"expected a positive distance, got {self.clip_mm}")

    @property
    def splat(self) -> SplatConfig:
        return SplatConfig(_INTERPOLATIONS[self.interpolation], self.mode)


@dataclass(frozen=True)
class CompoundedVolume:
    """The compounded label volume (occupancy in [0, 1]) on its grid, and what was observed."""

    volume: np.ndarray
    observed: np.ndarray
    grid: GridSpec
    hole_fill_radius_mm: float


def auto_hole_fill_radius_mm(
    dataset: SweepDataset, selection: FrameSelection, voxel_mm: float
) -> float:
    """Half the largest median gap between consecutive selected frames of a sweep."""
    gaps = []
    for sweep in dataset.sweeps:
        frames = selection.frames.get(sweep.name)
        if frames is None or len(frames) < 2:
            continue
        gaps.append(median_frame_gap_mm(sweep.probe_to_world[frames]))
    radius = 0.5 * max(gaps) if gaps else 0.0
    return float(np.clip(radius, np.sqrt(3) * voxel_mm, MAX_AUTO_RADIUS_MM))


def label_signed_distance(
    labels: np.ndarray, spacing_mm: tuple[float, float], clip_mm: float
) -> np.ndarray:
    """In-frame signed distance (H, W) float32 to the edge of the bone label (1), mm: positive
    in bone, truncated at ± ``clip_mm``; ``spacing_mm`` = (axial, lateral) pixel spacing."""
    from scipy import ndimage

    bone = np.asarray(labels) == 1
    if not bone.any() or bone.all():
        return np.full(bone.shape, clip_mm if bone.all() else -clip_mm, dtype=np.float32)
    inside = ndimage.distance_transform_edt(bone, sampling=spacing_mm)
    outside = ndimage.distance_transform_edt(~bone, sampling=spacing_mm)
    return np.clip(inside - outside, -clip_mm, clip_mm).astype(np.float32)


def pixel_values(
    dataset: SweepDataset, pixels: LabelledPixels, config: CompoundingConfig
) -> np.ndarray:
    """What each labelled pixel splats: its label, or its signed distance (module doc)."""
    if not config.signed_distance:
        return pixels.label.astype(np.float32)
    spacing = (dataset.probe.axial_spacing_mm, dataset.probe.lateral_spacing_mm)
    values = np.empty(len(pixels), dtype=np.float32)
    if len(pixels) == 0:
        return values
    # the pixels grouped by (sweep, frame) once; the frames' distance transforms on threads
    groups = list(pixels.frame_groups().values())

    def frame_values(at: np.ndarray) -> np.ndarray:
        sweep = dataset.sweeps[int(pixels.sweep_index[at[0]])]
        labels = sweep.labels[int(pixels.frame[at[0]])]
        distance = label_signed_distance(labels, spacing, config.clip_mm)
        return distance[pixels.row[at], pixels.col[at]]

    for at, found in zip(groups, thread_map(frame_values, groups), strict=True):
        values[at] = found
    return values


def fill_label_holes(
    volume: np.ndarray, observed: np.ndarray, radius_mm: float, voxel_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """Sticks up to 2r, then the nearest observed voxel within r (module doc); returns the
    volume and every voxel that holds a value."""
    if radius_mm <= 0:
        return volume, observed
    length = int(np.ceil(2 * radius_mm / voxel_mm - 1e-9)) + 1
    known = observed
    if length >= 3:
        volume, by_stick = fill_holes_stick(volume, observed, length)
        known = observed | by_stick
    volume, by_nearest = fill_holes_nearest(volume, known, radius_mm / voxel_mm)
    return volume, known | by_nearest


def compounding_grid(
    dataset: SweepDataset, bone_mm: np.ndarray, config: CompoundingConfig
) -> GridSpec:
    """The grid the labels are compounded on: the box of the bone pixels ``bone_mm`` (M, 3),
    grown by ``config.margin_mm``, at :class:`CompoundingConfig`'s voxel."""
    if len(bone_mm) == 0:
        raise UltronInputError("dataset", "labels", "the selected frames contain no bone (label 1)")
    bounds = np.stack([bone_mm.min(0) - config.margin_mm, bone_mm.max(0) + config.margin_mm])
    region_mm3 = float(np.prod(np.ptp(bounds, 0)))
    voxel = meshing_voxel_mm(
        dataset.probe, config.voxel_mm, region_mm3, finest_mm=resolved_spacing_mm(dataset)
    )
    return GridSpec.from_bounds(bounds, voxel)


def compound_labels(
    dataset: SweepDataset, selection: FrameSelection, config: CompoundingConfig | None = None
) -> CompoundedVolume:
    """Forward-compound the selected frames' labels into a voxel grid and fill its holes."""
    config = config or CompoundingConfig()
    # a run of frames at a time: the pixels' indices, positions and values are ~150 B each
    # (8 M auto-labelled pixels on the real fibula); the voxels get them in the same order
    # (a chunk without annotated pixels has no band, so no outer side: the plain count decides)
    chunks = [
        chunk
        for chunk in selection_chunks(dataset, selection, CHUNK_PIXELS)
        if count_labelled_pixels(dataset, chunk) > 0
    ]
    if not chunks:
        raise UltronInputError("dataset", "labels", "the selected frames have no annotated pixel")
    grid = compounding_grid(dataset, bone_points_mm(dataset, selection), config)
    voxel = grid.voxel_mm
    splatter = Splatter(grid, config.splat)
    for chunk in chunks:
        pixels = gather_labelled_pixels(dataset, chunk, outer_side_mm=config.outer_side_mm)
        splatter.add(pixels.world_mm(dataset), pixel_values(dataset, pixels, config))
    volume, observed = splatter.result()

    radius = config.hole_fill_radius_mm
    if radius is None:
        radius = auto_hole_fill_radius_mm(dataset, selection, voxel)
    volume, known = fill_label_holes(volume, observed, radius, voxel)
    if config.signed_distance:
        occupancy = np.clip(0.5 + volume / (2 * config.clip_mm), 0.0, 1.0)
        volume = np.where(known, occupancy, 0.0)
    return CompoundedVolume(
        volume=volume.astype(np.float32),
        observed=observed,
        grid=grid,
        hole_fill_radius_mm=float(radius),
    )
