"""ON, the coordinate occupancy network baseline (METHOD.md §4).

The same network as UltrON's f_ω (8 × 128, skip at 4, ReLU, sigmoid), but on the positionally
encoded world position of each labelled pixel mapped to the unit cube of the scanned region
(:class:`~ultron.data.geometry.UnitCube` of the field-of-view box, so the reference mesh is
never read), trained with plain BCE on the same labelled pixels (same label-fraction
selection), class-balanced (``positive_weight=None``; UltrON's loss is unweighted since f
reads θ's neighbourhood, see :mod:`ultron.train.occupancy`), meshed exactly as UltrON is
(:func:`mesh_occupancy`).

Positional encoding: coordinates need more bands than θ (NeRF uses 10 for positions); the
default of 8 bands resolves a period of 2/2⁷ of the cube's half-extent (≈ 1 mm on the default
phantom's ≈ 70 mm half-extent), the scale of the labels' 2 mm band.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from ultron.data.dataset import SweepDataset
from ultron.data.geometry import UnitCube, field_of_view_bounds_mm
from ultron.data.labels import gather_labelled_pixels, select_label_frames
from ultron.device import module_device
from ultron.errors import argument_error
from ultron.fields.occupancy import OccupancyNetworkConfig
from ultron.mesh.occupancy_mesh import MeshingConfig, mesh_occupancy
from ultron.methods.ultron_method import Reconstruction, TrainedModel
from ultron.timing import StageTimer
from ultron.train.fit_checkpoint import OCCUPANCY_FIT, checkpoint_in, resumed_steps
from ultron.train.occupancy import OccupancyTrainConfig, OccupancyTrainingData, fit_occupancy


def _on_training() -> OccupancyTrainConfig:
    return OccupancyTrainConfig(
        loss="bce", positive_weight=None, network=OccupancyNetworkConfig(n_frequencies=8)
    )


@dataclass(frozen=True)
class ONConfig:
    """Settings of the ON baseline: its training and its meshing (UltrON's, by default)."""

    occupancy: OccupancyTrainConfig = field(default_factory=_on_training)
    meshing: MeshingConfig = field(default_factory=MeshingConfig)

    def __post_init__(self) -> None:
        if self.occupancy.loss != "bce":
            raise argument_error(
                "occupancy.loss", f"ON trains with 'bce', got {self.occupancy.loss!r}"
            )


def scan_unit_cube(dataset: SweepDataset) -> UnitCube:
    """The unit cube of everything the probe saw (from the poses and probe geometry only)."""
    return UnitCube.from_bounds(field_of_view_bounds_mm(dataset.all_poses(), dataset.probe))


def on_training_data(dataset: SweepDataset, cube: UnitCube, selection) -> OccupancyTrainingData:
    """Unit-cube positions of the selected frames' labelled pixels, T = 1, labels."""
    pixels = gather_labelled_pixels(dataset, selection)
    positions = cube.to_unit(torch.from_numpy(pixels.world_mm(dataset)), dtype=torch.float32)
    labels = torch.from_numpy(pixels.label.astype(np.uint8))
    return OccupancyTrainingData(positions, torch.ones(len(pixels)), labels)


def reconstruct_on(
    dataset: SweepDataset,
    label_fraction: float,
    seed: int,
    config: ONConfig | None = None,
    timer: StageTimer | None = None,
    device: torch.device | str = "cpu",
    checkpoints: Path | None = None,
) -> Reconstruction:
    """Fit ON on ``label_fraction`` of the annotated frames (on ``device``; resumable with a
    ``checkpoints`` directory, :mod:`ultron.train.fit_checkpoint`) and mesh it."""
    config = config or ONConfig()
    timer = timer or StageTimer()
    occupancy = replace(config.occupancy, seed=seed)
    with timer.stage("labels"):
        selection = select_label_frames(dataset, label_fraction, seed)
        cube = scan_unit_cube(dataset)
        data = on_training_data(dataset, cube, selection)
    with timer.stage("occupancy_fit"):
        saved = checkpoint_in(checkpoints, OCCUPANCY_FIT)
        network, log = fit_occupancy(
            data, occupancy, progress=timer.fit_progress, device=device, checkpoint=saved
        )

    def fn(points_mm: torch.Tensor) -> torch.Tensor:
        unit = cube.to_unit(points_mm, dtype=torch.float32)
        return network.occupancy(unit.to(module_device(network))).cpu()

    mesh, volume, grid = mesh_occupancy(fn, dataset, config.meshing, timer, module_device(network))
    info = {
        "selection": selection.to_dict(),
        "n_label_frames": selection.n_frames,
        "n_labelled_pixels": len(data.labels),
        "n_bone_pixels": int(data.labels.sum()),
        "unit_cube": cube.to_dict(),
        "occupancy_config": occupancy.to_dict(),
        "occupancy_log": log,
        **resumed_steps({OCCUPANCY_FIT: saved}),
        "grid": grid.to_dict(),
    }  # fmt: skip
    model = {"input": "unit_cube", "unit_cube": cube.to_dict()}
    return Reconstruction(
        mesh=mesh,
        volume=volume,
        grid=grid,
        info=info,
        model=TrainedModel(network, model),
        selection=selection,
    )
