"""Label compounding: the no-learning baseline that users run today in 3D Slicer / PLUS.

The annotated pixels of the selected frames are pasted into a voxel grid with their poses
(PLUS-style forward compounding): each pixel's label (1 bone, 0 background; 255 ignored) is
splatted into the voxel containing it ("nearest") or into its 8 neighbours with trilinear
weights ("trilinear"), and the voxel keeps the MEAN (weighted average) or the MAX of what it
received. Voxels that received nothing are filled by normalised convolution — a Gaussian-
weighted average of the observed voxels around them (σ = radius / 2) — if an observed voxel lies
within the hole-filling radius, as PLUS's kernel hole filling does. The result is meshed by the
same smoothing + marching cubes as every other method.

The default radius is half the largest median gap between consecutive selected frames of a
sweep (at least a voxel diagonal, √3 voxels, so that a voxel missed between observed
neighbours is always filled; at most 10 mm): the smallest radius that closes the gaps a sparse
label fraction leaves between frames, without inventing bone far from any annotation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ultron.data.dataset import SweepDataset
from ultron.data.geometry import apply_pose, median_frame_gap_mm, probe_points_mm
from ultron.data.labels import FrameSelection, LabelledPixels, gather_labelled_pixels
from ultron.errors import UltronInputError, argument_error
from ultron.mesh.grid import GridSpec

MAX_AUTO_RADIUS_MM = 10.0


@dataclass(frozen=True)
class CompoundingConfig:
    """Settings of :func:`compound_labels` (``None`` = derived from the data, see module doc)."""

    voxel_mm: float | None = None
    mode: str = "mean"
    interpolation: str = "nearest"
    hole_fill_radius_mm: float | None = None
    margin_mm: float = 5.0

    def __post_init__(self) -> None:
        if self.mode not in ("mean", "max"):
            raise argument_error("mode", f"expected 'mean' or 'max', got {self.mode!r}")
        if self.interpolation not in ("nearest", "trilinear"):
            raise argument_error(
                "interpolation", f"expected 'nearest' or 'trilinear', got {self.interpolation!r}"
            )
        if self.voxel_mm is not None and not self.voxel_mm > 0:
            raise argument_error("voxel_mm", f"expected a positive size, got {self.voxel_mm}")
        if self.hole_fill_radius_mm is not None and not self.hole_fill_radius_mm >= 0:
            raise argument_error(
                "hole_fill_radius_mm", f"expected ≥ 0, got {self.hole_fill_radius_mm}"
            )


@dataclass(frozen=True)
class CompoundedVolume:
    """The compounded label volume (values in [0, 1]) on its grid, and what was observed."""

    volume: np.ndarray
    observed: np.ndarray
    grid: GridSpec
    hole_fill_radius_mm: float


def labelled_pixels_world(dataset: SweepDataset, pixels: LabelledPixels) -> np.ndarray:
    """World mm (M, 3) of labelled pixels, each through its own frame's pose."""
    out = np.empty((len(pixels), 3), dtype=np.float64)
    for sweep_index, sweep in enumerate(dataset.sweeps):
        sel = np.flatnonzero(pixels.sweep_index == sweep_index)
        if sel.size == 0:
            continue
        poses = torch.as_tensor(sweep.probe_to_world[pixels.frame[sel]])
        probe = probe_points_mm(
            torch.as_tensor(pixels.row[sel], dtype=torch.float64),
            torch.as_tensor(pixels.col[sel], dtype=torch.float64),
            dataset.probe,
        )
        out[sel] = apply_pose(poses, probe[:, None, :])[:, 0].numpy()
    return out


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


def compound_labels(
    dataset: SweepDataset, selection: FrameSelection, config: CompoundingConfig | None = None
) -> CompoundedVolume:
    """Forward-compound the selected frames' labels into a voxel grid and fill its holes."""
    from scipy import ndimage

    config = config or CompoundingConfig()
    pixels = gather_labelled_pixels(dataset, selection)
    points = labelled_pixels_world(dataset, pixels)
    bone = points[pixels.label == 1]
    if len(bone) == 0:
        raise UltronInputError("dataset", "labels", "the selected frames contain no bone (label 1)")
    probe = dataset.probe
    voxel = config.voxel_mm or min(probe.lateral_spacing_mm, probe.axial_spacing_mm)
    bounds = np.stack([bone.min(0) - config.margin_mm, bone.max(0) + config.margin_mm])
    grid = GridSpec.from_bounds(bounds, voxel)
    index = grid.world_to_index(points)
    inside = ((index > -0.5) & (index < np.asarray(grid.shape) - 0.5)).all(axis=1)
    index, values = index[inside], pixels.label[inside].astype(np.float64)

    if config.interpolation == "nearest":
        corners = [(np.rint(index).astype(np.int64), np.ones(len(index)))]
    else:
        base = np.floor(index).astype(np.int64)
        frac = index - base
        corners = []
        for offset in np.ndindex(2, 2, 2):
            weight = np.prod(np.where(offset, frac, 1 - frac), axis=1)
            corners.append((base + np.asarray(offset), weight))

    shape = np.asarray(grid.shape)
    weight_sum = np.zeros(grid.n_voxels)
    value_sum = np.zeros(grid.n_voxels)
    value_max = np.zeros(grid.n_voxels)
    for ijk, weight in corners:
        ok = ((ijk >= 0) & (ijk < shape)).all(axis=1) & (weight > 0)
        flat = np.ravel_multi_index(ijk[ok].T, grid.shape)
        weight_sum += np.bincount(flat, weights=weight[ok], minlength=grid.n_voxels)
        value_sum += np.bincount(flat, weights=weight[ok] * values[ok], minlength=grid.n_voxels)
        np.maximum.at(value_max, flat, values[ok])
    observed = (weight_sum > 0).reshape(grid.shape)
    if config.mode == "mean":
        volume = np.divide(
            value_sum, weight_sum, out=np.zeros_like(value_sum), where=weight_sum > 0
        )
    else:
        volume = value_max
    volume = volume.reshape(grid.shape)

    radius = config.hole_fill_radius_mm
    if radius is None:
        radius = auto_hole_fill_radius_mm(dataset, selection, voxel)
    if radius > 0:
        sigma = max(radius / 2 / voxel, 0.5)
        smooth_value = ndimage.gaussian_filter(volume * observed, sigma, mode="constant")
        smooth_weight = ndimage.gaussian_filter(observed.astype(np.float64), sigma, mode="constant")
        distance = ndimage.distance_transform_edt(~observed) * voxel
        holes = (~observed) & (distance <= radius) & (smooth_weight > 1e-6)
        volume[holes] = smooth_value[holes] / smooth_weight[holes]
    return CompoundedVolume(
        volume=volume.astype(np.float32),
        observed=observed,
        grid=grid,
        hole_fill_radius_mm=float(radius),
    )
