"""UltrON (and its "w/o loss" ablation): occupancy f(θ) from a fitted acoustic field.

1. Choose the label fraction's frames (``select_label_frames``) and gather their annotated
   pixels. 2. For each pixel, θ from the fitted field (normalised with the field's saved
   statistics) and T along that frame's own scanline (exclusive, detached). 3. Fit f_ω with the
   attenuation-compensated BCE (``ultron``) or plain BCE (``ultron-noloss``). 4. Evaluate
   f(θ(x)) on a grid over the scanned region (voxel = the finer pixel spacing), zero outside
   every frame's field of view, and mesh it.

Nothing here reads the reference mesh.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch

from ultron.data.dataset import SweepDataset
from ultron.data.geometry import field_of_view_bounds_mm, median_frame_gap_mm
from ultron.data.labels import FrameSelection, gather_labelled_pixels, select_label_frames
from ultron.errors import UltronInputError, argument_error
from ultron.fields.occupancy import OccupancyNetwork
from ultron.mesh.extract import ExtractionConfig, extract_surface
from ultron.mesh.grid import GridSpec, evaluate_coarse_to_fine, field_of_view_mask
from ultron.methods.runinfo import StageTimer
from ultron.train.occupancy import OccupancyTrainConfig, OccupancyTrainingData, fit_occupancy

METHOD_LOSSES = {"ultron": "ultron", "ultron-noloss": "bce"}


@dataclass(frozen=True)
class UltronConfig:
    """Settings of an UltrON reconstruction."""

    label_fraction: float = 0.1
    seed: int = 0
    occupancy: OccupancyTrainConfig = field(default_factory=OccupancyTrainConfig)
    voxel_mm: float | None = None
    coarse_factor: int = 2
    chunk_points: int = 65_536
    extraction: ExtractionConfig = field(default_factory=ExtractionConfig)

    def __post_init__(self) -> None:
        if not 0 < self.label_fraction <= 1:
            raise argument_error(
                "label_fraction", f"expected a value in (0, 1], got {self.label_fraction}"
            )
        if self.voxel_mm is not None and not self.voxel_mm > 0:
            raise argument_error("voxel_mm", f"expected > 0, got {self.voxel_mm}")
        if not isinstance(self.coarse_factor, int) or self.coarse_factor < 1:
            raise argument_error(
                "coarse_factor", f"expected a positive integer, got {self.coarse_factor!r}"
            )


@dataclass
class Reconstruction:
    """What a method produced: the mesh (world mm), its occupancy volume and bookkeeping."""

    mesh: Any
    volume: np.ndarray
    grid: GridSpec
    info: dict[str, Any]


def elevation_half_thickness_mm(dataset: SweepDataset, voxel_mm: float) -> float:
    """Half-thickness of the slab each frame is taken to image: 0.75 × the largest median gap
    between consecutive frames of a sweep (so that neighbouring slabs overlap), ≥ one voxel."""
    gaps = [median_frame_gap_mm(s.probe_to_world) for s in dataset.sweeps if s.n_frames > 1]
    return max(0.75 * max(gaps, default=0.0), voxel_mm)


def scan_grid(dataset: SweepDataset, voxel_mm: float | None) -> GridSpec:
    """The meshing grid over everything the probe saw, voxel ≤ the finer pixel spacing."""
    probe = dataset.probe
    voxel = voxel_mm or min(probe.lateral_spacing_mm, probe.axial_spacing_mm)
    bounds = field_of_view_bounds_mm(dataset.all_poses(), probe).numpy()
    return GridSpec.from_bounds(bounds, voxel)


def occupancy_training_data(
    dataset: SweepDataset, fitted, selection: FrameSelection
) -> OccupancyTrainingData:
    """Per labelled pixel: normalised θ, T along its frame's scanline (detached), label."""
    if fitted.theta_stats is None:
        raise UltronInputError("field", "theta_stats", "the field has no θ statistics (refit it)")
    fitted.check_probe(dataset.probe)
    pixels = gather_labelled_pixels(dataset, selection)
    theta = torch.zeros(len(pixels), len(fitted.channels))
    transmission = torch.zeros(len(pixels))
    for sweep_index, sweep in enumerate(dataset.sweeps):
        sel = np.flatnonzero(pixels.sweep_index == sweep_index)
        if sel.size == 0:
            continue
        t, tr = fitted.pixel_theta_transmission(
            sweep.probe_to_world, pixels.frame[sel], pixels.row[sel], pixels.col[sel]
        )
        theta[sel], transmission[sel] = t, tr
    inputs = fitted.theta_stats.normalise(theta)
    labels = torch.from_numpy(pixels.label.astype(np.uint8))
    return OccupancyTrainingData(inputs.float(), transmission.detach().float(), labels)


def occupancy_function(fitted, network: OccupancyNetwork):
    """points (M, 3) world mm → f(θ(x)) ∈ (0, 1)."""

    def fn(points_mm: torch.Tensor) -> torch.Tensor:
        theta = fitted.query(points_mm).stack()
        return network.occupancy(fitted.theta_stats.normalise(theta))

    return fn


def mesh_occupancy(fn, dataset: SweepDataset, config: UltronConfig, timer: StageTimer) -> tuple:
    """Evaluate ``fn`` on the scan grid inside the field of view and extract the surface.

    The field-of-view mask is rasterised on the coarse grid of the coarse-to-fine evaluation
    (:func:`~ultron.mesh.grid.evaluate_coarse_to_fine`), so it is exact to one coarse voxel.
    """
    grid = scan_grid(dataset, config.voxel_mm)
    coarse = grid.coarsened(config.coarse_factor)
    with timer.stage("mesh_fov_mask"):
        mask = field_of_view_mask(
            coarse,
            dataset.all_poses(),
            dataset.probe,
            elevation_half_thickness_mm(dataset, grid.voxel_mm),
        )
    with timer.stage("mesh_evaluate"):
        volume = evaluate_coarse_to_fine(
            fn,
            grid,
            config.extraction.threshold,
            config.coarse_factor,
            config.chunk_points,
            coarse_mask=mask,
        )
    with timer.stage("mesh_extract"):
        mesh = extract_surface(volume, grid, config.extraction)
    return mesh, volume, grid


def reconstruct_ultron(
    dataset: SweepDataset, fitted, method: str, config: UltronConfig, timer: StageTimer
) -> Reconstruction:
    """Run stages 2 and 3 of UltrON (``method`` ``ultron`` or ``ultron-noloss``)."""
    if method not in METHOD_LOSSES:
        raise argument_error("method", f"expected one of {tuple(METHOD_LOSSES)}, got {method!r}")
    occupancy_config = replace(config.occupancy, loss=METHOD_LOSSES[method])
    with timer.stage("labels"):
        selection = select_label_frames(dataset, config.label_fraction, config.seed)
        data = occupancy_training_data(dataset, fitted, selection)
    with timer.stage("occupancy_fit"):
        network, log = fit_occupancy(data, occupancy_config)
    mesh, volume, grid = mesh_occupancy(occupancy_function(fitted, network), dataset, config, timer)
    info = {
        "selection": selection.to_dict(),
        "n_label_frames": selection.n_frames,
        "n_labelled_pixels": len(data.labels),
        "n_bone_pixels": int(data.labels.sum()),
        "occupancy_config": occupancy_config.to_dict(),
        "occupancy_log": log,
        "grid": grid.to_dict(),
    }
    model = {
        "input": "theta",
        "theta_channels": list(fitted.channels),
        "loss": occupancy_config.loss,
    }
    return Reconstruction(
        mesh=mesh, volume=volume, grid=grid, info=info | {"network": network, "model": model}
    )
