"""Every reconstruction method behind one interface, found through one registry.

``METHODS`` maps a method's name (``reconstruct --method``) to a :class:`Method`: whether it
needs a fitted acoustic field, the class of its settings (held by the
:class:`~ultron.methods.request.ReconstructionRequest`), the voxel it meshes at, and
``fit(dataset, inputs)`` → :class:`~ultron.methods.ultron_method.Reconstruction`. The names
and which need a field come from :mod:`ultron.methods.catalog` (readable
without torch, for the CLI); this module checks at import that both list the same methods.
The pipeline, the benchmark and the reports read them instead of keeping their own lists:

=================  ====================================================  ============
name               module                                                needs field
=================  ====================================================  ============
``ultron``         :mod:`ultron.methods.ultron_method` (compensated)     yes
``ultron-noloss``  :mod:`ultron.methods.ultron_method` (plain BCE)       yes
``compounding``    :mod:`ultron.methods.compounding_method`              no
``on``             :mod:`ultron.methods.on_method`                       no
``rocosdf``        :mod:`ultron.methods.rocosdf` (row + column views)    no
``unsr-row``       :mod:`ultron.methods.rocosdf` (row view, stage 1)     no
``unsr-col``       :mod:`ultron.methods.rocosdf` (column view, stage 1)  no
=================  ====================================================  ============
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any, Protocol

import torch

from ultron.data.dataset import SweepDataset
from ultron.data.labels import FrameSelection, select_label_frames
from ultron.device import CPU
from ultron.errors import argument_error
from ultron.mesh.compounding import CompoundingConfig
from ultron.methods.catalog import FIELD_METHODS, METHOD_NAMES
from ultron.methods.compounding_method import reconstruct_compounding
from ultron.methods.on_method import ONConfig, reconstruct_on
from ultron.methods.request import ReconstructionRequest, check_method_name
from ultron.methods.rocosdf import RoCoSDFConfig, reconstruct_rocosdf
from ultron.methods.ultron_method import Reconstruction, UltronConfig, reconstruct_ultron
from ultron.pipeline.resources import check_compounding_grid
from ultron.timing import StageTimer


@dataclass(frozen=True)
class MethodInputs:
    """What a method runs with besides the dataset: the request (label fraction, seed and
    every method's settings), the fitted field (None unless the method needs one), the stage
    timer, the oracle's true T per sweep (diagnostic runs), the dataset's name for input
    errors, and the device."""

    request: ReconstructionRequest
    timer: StageTimer
    fitted: Any = None
    truth: Mapping[str, Any] | None = None
    dataset_name: str | None = None
    device: torch.device = CPU


class Method(Protocol):
    """A reconstruction method (module doc)."""

    name: str
    needs_field: bool
    #: Whether it meshes on the grid over the scanned region (whose memory a run checks
    #: before any work); compounding meshes the labelled bone's box, RoCoSDF and UNSR their
    #: own grid around the labelled points.
    scan_grid: bool
    config_class: type

    def meshing_voxel(self, request: ReconstructionRequest) -> float | None:
        """The voxel, mm, ``request`` asks this method to mesh at (None: its default, the
        finer pixel spacing); the run checks the grid's memory with it before any work."""
        ...

    def check_resources(
        self,
        dataset: SweepDataset,
        request: ReconstructionRequest,
        selection: FrameSelection,
        root: str | Path,
        max_memory_gib: float | None,
    ) -> None:
        """Refuse, before any work, a run on ``selection`` whose own grid (one not over the
        scanned region) would exceed the memory limit; ``root`` is named in the error."""
        ...

    def fit(self, dataset: SweepDataset, inputs: MethodInputs) -> Reconstruction: ...


@dataclass(frozen=True)
class MethodBase:
    """The defaults of a :class:`Method`: no field, meshed on the scan grid."""

    name: str
    scan_grid: bool = True
    config_class: type = object

    @property
    def needs_field(self) -> bool:
        """Whether it reads a fitted acoustic field (:mod:`ultron.methods.catalog`)."""
        return self.name in FIELD_METHODS

    def meshing_voxel(self, request: ReconstructionRequest) -> float | None:
        """UltrON's meshing voxel: the voxel of every method meshed like UltrON."""
        return request.ultron.voxel_mm

    def check_resources(
        self,
        dataset: SweepDataset,
        request: ReconstructionRequest,
        selection: FrameSelection,
        root: str | Path,
        max_memory_gib: float | None,
    ) -> None:
        """Nothing beyond the scan grid's check (:func:`~ultron.pipeline.resources.check_run_resources`)."""


@dataclass(frozen=True)
class UltronMethod(MethodBase):
    """UltrON (``ultron``, ``loss`` "ultron": the attenuation-compensated loss) or its ablation
    (``ultron-noloss``, ``loss`` "bce")."""

    loss: str = "ultron"
    config_class: type = UltronConfig

    def fit(self, dataset: SweepDataset, inputs: MethodInputs) -> Reconstruction:
        if inputs.fitted is None:
            raise argument_error("field", f"method {self.name!r} needs a fitted acoustic field")
        request = inputs.request
        config = replace(request.ultron, label_fraction=request.label_fraction, seed=request.seed)
        return reconstruct_ultron(
            dataset, inputs.fitted, self.loss, config, inputs.timer, inputs.truth, inputs.device
        )


@dataclass(frozen=True)
class CompoundingMethod(MethodBase):
    """Label compounding, meshed with UltrON's extraction and observed-surface settings."""

    scan_grid: bool = False
    config_class: type = CompoundingConfig

    def meshing_voxel(self, request: ReconstructionRequest) -> float | None:
        return request.compounding.voxel_mm

    def check_resources(
        self,
        dataset: SweepDataset,
        request: ReconstructionRequest,
        selection: FrameSelection,
        root: str | Path,
        max_memory_gib: float | None,
    ) -> None:
        """Its grid, the labelled bone's box, and labelled pixels within the memory limit."""
        check_compounding_grid(dataset, selection, request.compounding, root, max_memory_gib)

    def fit(self, dataset: SweepDataset, inputs: MethodInputs) -> Reconstruction:
        r = inputs.request
        return reconstruct_compounding(
            dataset, r.label_fraction, r.seed, r.compounding, r.ultron.extraction,
            r.ultron.observed, inputs.timer,
        )  # fmt: skip


@dataclass(frozen=True)
class ONMethod(MethodBase):
    """The coordinate occupancy network."""

    config_class: type = ONConfig

    def meshing_voxel(self, request: ReconstructionRequest) -> float | None:
        return request.on.meshing.voxel_mm

    def fit(self, dataset: SweepDataset, inputs: MethodInputs) -> Reconstruction:
        r = inputs.request
        return reconstruct_on(dataset, r.label_fraction, r.seed, r.on, inputs.timer, inputs.device)


@dataclass(frozen=True)
class SDFMethod(MethodBase):
    """RoCoSDF on the row and column views, or UNSR (its stage 1) on one view."""

    views: tuple[str, ...] = ("row", "column")
    scan_grid: bool = False
    config_class: type = RoCoSDFConfig

    def fit(self, dataset: SweepDataset, inputs: MethodInputs) -> Reconstruction:
        request = inputs.request
        with inputs.timer.stage("labels"):
            selection = select_label_frames(dataset, request.label_fraction, request.seed)
        return reconstruct_rocosdf(
            dataset, selection, RoCoSDFConfig.preset(request.rocosdf_preset), request.seed,
            self.views, progress=inputs.timer.fit_progress, timer=inputs.timer,
            dataset_name=inputs.dataset_name, device=inputs.device,
        )  # fmt: skip


METHODS: Mapping[str, Method] = MappingProxyType(
    {
        method.name: method
        for method in (
            UltronMethod("ultron", loss="ultron"),
            UltronMethod("ultron-noloss", loss="bce"),
            CompoundingMethod("compounding"),
            ONMethod("on"),
            SDFMethod("rocosdf", views=("row", "column")),
            SDFMethod("unsr-row", views=("row",)),
            SDFMethod("unsr-col", views=("column",)),
        )
    }
)
if tuple(METHODS) != METHOD_NAMES:  # the catalog and the registry list the same methods
    raise RuntimeError(f"registry {tuple(METHODS)} differs from the catalog {METHOD_NAMES}")


def get_method(name: str) -> Method:
    """The registered method ``name``; an unknown one is an error naming ``method``."""
    return METHODS[check_method_name(name)]


__all__ = ["METHODS", "Method", "MethodInputs", "get_method"]
