"""Label compounding, the no-learning baseline (what a PLUS / 3D Slicer user does today).

The selected frames' labelled pixels are pasted into a voxel grid
(:func:`ultron.mesh.compounding.compound_labels`: bone share per voxel, hole filling between
frames), the grid is meshed like every other method's (:func:`ultron.mesh.extract.extract_surface`)
and the surface is split into its observed / inferred parts with T ≡ 1 (compounding has no
transmission: a face counts as observed where some frame saw it facing the probe).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ultron.data.dataset import SweepDataset
from ultron.data.labels import select_label_frames
from ultron.mesh.compounding import CompoundingConfig, compound_labels
from ultron.mesh.extract import ExtractionConfig, extract_surface
from ultron.mesh.observed import CroppedExtraction, ObservedSurfaceConfig
from ultron.methods.evidence import faced_observation
from ultron.methods.ultron_method import Reconstruction
from ultron.timing import StageTimer


@dataclass(frozen=True)
class CompoundingMethodConfig(CroppedExtraction):
    """Settings of a compounding run: the volume (:class:`~ultron.mesh.compounding.
    CompoundingConfig`), its surface extraction and the observed-surface crop (by default
    UltrON's, so that both methods mesh alike; a preset hands it UltrON's; ``extraction`` None:
    the one that goes with ``observed.surface``)."""

    volume: CompoundingConfig = field(default_factory=CompoundingConfig)
    extraction: ExtractionConfig | None = None
    observed: ObservedSurfaceConfig = field(default_factory=ObservedSurfaceConfig)


def reconstruct_compounding(
    dataset: SweepDataset,
    label_fraction: float,
    seed: int,
    config: CompoundingMethodConfig,
    timer: StageTimer,
) -> Reconstruction:
    """Compound ``label_fraction`` of the annotated frames (chosen with ``seed``), mesh the
    volume with ``config.surface_extraction`` and keep its ``config.observed`` part."""
    with timer.stage("labels"):
        selection = select_label_frames(dataset, label_fraction, seed)
    with timer.stage("mesh"):
        compounded = compound_labels(dataset, selection, config.volume)
        mesh = extract_surface(compounded.volume, compounded.grid, config.surface_extraction,
                               advance=timer.counter("smoothing iterations"))  # fmt: skip
    with timer.stage("mesh_observed"):
        observation = faced_observation(mesh, dataset, compounded.grid.voxel_mm, config.observed)
    info = {
        **observation.info,
        "selection": selection.to_dict(),
        "n_label_frames": selection.n_frames,
        "hole_fill_radius_mm": compounded.hole_fill_radius_mm,
        "compounding_config": config.volume.__dict__,
    }
    return Reconstruction(
        mesh=observation.kept,
        volume=compounded.volume,
        grid=compounded.grid,
        info=info,
        observation=observation,
        selection=selection,
    )
