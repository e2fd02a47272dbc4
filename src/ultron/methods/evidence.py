"""The observed / inferred split and the per-vertex evidence of every method's surface.

UltrON computes its observation with the field's T (:func:`~ultron.methods.ultron_method.
keep_observed_surface`). Methods without a transmission use :func:`~ultron.mesh.observed.faced_observation`: the
criterion of :mod:`ultron.mesh.observed` with T ≡ 1, over every frame, in the slab UltrON's
crop uses — label compounding crops its surface with it (``--surface observed``, the default:
it drops the floor and walls of the compounded label band, which no frame sees from above); ON
and RoCoSDF keep their closed surfaces and are only flagged. :func:`reconstruction_evidence`
then adds each vertex's distance to the labelled bone (:mod:`ultron.mesh.evidence`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from ultron.data.dataset import SweepDataset
from ultron.data.labels import bone_points_mm
from ultron.mesh.evidence import SurfaceEvidence, surface_evidence
from ultron.mesh.extract import weld_coincident
from ultron.mesh.observed import NO_TRANSMISSION, ObservedSurfaceConfig, faced_observation
from ultron.methods.ultron_method import Reconstruction

__all__ = [
    "NO_TRANSMISSION",
    "EvidencedSurface",
    "faced_observation",
    "reconstruction_evidence",
    "with_observation",
]


def with_observation(
    result: Reconstruction, dataset: SweepDataset, observed: ObservedSurfaceConfig | None = None
) -> Reconstruction:
    """``result`` as it is when it carries its observation; else with
    :func:`faced_observation` (``observed``'s criterion, default the annotator's, and
    ``surface="all"``: the method's surface is flagged, never cropped)."""
    if result.observation is not None:
        return result
    config = replace(observed or ObservedSurfaceConfig(), surface="all")
    observation = faced_observation(result.mesh, dataset, result.grid.voxel_mm, config)
    return replace(result, observation=observation)


@dataclass(frozen=True)
class EvidencedSurface:
    """A mesh as it is written (:func:`~ultron.mesh.extract.weld_coincident`) and the
    evidence of each of its vertices."""

    mesh: Any
    evidence: SurfaceEvidence


def reconstruction_evidence(
    result: Reconstruction, dataset: SweepDataset, observed: ObservedSurfaceConfig | None = None
) -> tuple[Reconstruction, dict[str, EvidencedSurface]]:
    """``result`` with its observation (:func:`with_observation`; :func:`ultron.pipeline.run.
    run_method` already adds it, with the default criterion) and the surfaces to write with
    their evidence: its mesh (``"mesh"``) and, when the observed crop dropped faces, the whole
    extracted surface (``"extracted"``), each with its coincident vertices merged and its
    faces without area dropped (:func:`~ultron.mesh.extract.weld_coincident`)."""
    result = with_observation(result, dataset, observed)
    observation = result.observation
    bone = bone_points_mm(dataset, result.selection)
    extracted = surface_evidence(observation.extracted.vertices, observation.observed, bone)
    kept = SurfaceEvidence(
        extracted.observed[observation.kept_vertices],
        extracted.label_distance_mm[observation.kept_vertices],
    )
    surfaces = {"mesh": _welded(result.mesh, kept)}
    if observation.cropped:
        surfaces["extracted"] = _welded(observation.extracted, extracted)
    return result, surfaces


def _welded(mesh, evidence: SurfaceEvidence) -> EvidencedSurface:
    welded, new_index = weld_coincident(mesh)
    return EvidencedSurface(welded, evidence.merged(new_index, len(welded.vertices)))


def evidence_summary(surfaces: dict[str, EvidencedSurface]) -> dict[str, Any]:
    """run.json's ``surface_evidence``: per mesh, :meth:`SurfaceEvidence.summary`."""
    return {name: item.evidence.summary() for name, item in surfaces.items()}
