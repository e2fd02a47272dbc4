"""Digital vertebra phantoms and a physics-based B-mode simulator (``ultron simulate``).

World frame (all phantoms and simulated datasets, millimetres): origin at the centre of the
vertebral body, +x lateral (patient left–right), +y posterior → anterior, +z caudal → cranial.
The phantom sits in a gelatin block whose scanned surface is the plane
``y = phantom.surface_y_mm`` (10 mm posterior of the spinous process tip); the probe lies on
that surface on the posterior side and looks anteriorly: the beam, probe +y, points along world
+y into the phantom.

Modules: ``primitives`` (SDF primitives, smooth union), ``shapes`` (vertebrae, ``PHANTOMS``),
``volume`` (SDF grid, reference mesh), ``tissue`` (acoustic parameters), ``speckle``
(world-anchored scatterers), ``scanline`` (per-scanline physics), ``simulator`` (B-mode frames),
``protocols`` (sweeps, tracking error), ``annotation`` (label simulator), ``visibility`` (the
visible part of the reference, ground truth for metrics), ``dataset`` (``SimulationConfig``,
``simulate_dataset``), ``preview`` (PNG montage).
"""

from ultron.phantom.annotation import AnnotationConfig, annotate
from ultron.phantom.dataset import SimulationConfig, phantom_json, simulate_dataset
from ultron.phantom.protocols import (
    DEFAULT_SWEEPS,
    ScanConfig,
    SweepSpec,
    TrackingNoise,
    perturb_poses,
    plan_sweep,
    sweep_spec,
)
from ultron.phantom.shapes import PHANTOMS, Phantom, VertebraShape, get_phantom
from ultron.phantom.simulator import BModeConfig, BoneInterfaces, SimulatedFrames, simulate_frames
from ultron.phantom.speckle import ScattererField, scatterer_field
from ultron.phantom.tissue import CORTICAL_BONE, GEL_PULP, Tissue, intensity_reflection
from ultron.phantom.visibility import reference_visibility
from ultron.phantom.volume import SdfVolume

__all__ = [
    "CORTICAL_BONE",
    "DEFAULT_SWEEPS",
    "GEL_PULP",
    "PHANTOMS",
    "AnnotationConfig",
    "BModeConfig",
    "BoneInterfaces",
    "Phantom",
    "ScanConfig",
    "ScattererField",
    "SdfVolume",
    "SimulatedFrames",
    "SimulationConfig",
    "SweepSpec",
    "Tissue",
    "TrackingNoise",
    "VertebraShape",
    "annotate",
    "get_phantom",
    "intensity_reflection",
    "perturb_poses",
    "phantom_json",
    "plan_sweep",
    "reference_visibility",
    "scatterer_field",
    "simulate_dataset",
    "simulate_frames",
    "sweep_spec",
]
