"""Every reconstruction method behind one interface, found through one registry.

``METHODS`` maps a method's name (``reconstruct --method``) to a :class:`Method`: whether it
needs a fitted acoustic field, the class of its settings (held by the
:class:`~ultron.pipeline.run.ReconstructionRequest`), and ``fit(dataset, inputs)`` →
:class:`~ultron.methods.ultron_method.Reconstruction`. The CLI, the benchmark and the reports
read it instead of keeping their own lists:

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
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Protocol

import torch

from ultron.data.dataset import SweepDataset
from ultron.data.labels import select_label_frames
from ultron.device import CPU
from ultron.errors import argument_error
from ultron.mesh.compounding import CompoundingConfig
from ultron.methods.compounding_method import reconstruct_compounding
from ultron.methods.on_method import ONConfig, reconstruct_on
from ultron.methods.rocosdf import RoCoSDFConfig, reconstruct_rocosdf
from ultron.methods.ultron_method import Reconstruction, UltronConfig, reconstruct_ultron
from ultron.timing import StageTimer

if TYPE_CHECKING:
    from ultron.pipeline.run import ReconstructionRequest


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
    #: before any work); RoCoSDF and UNSR mesh on their own grid around the labelled points.
    scan_grid: bool
    config_class: type

    def fit(self, dataset: SweepDataset, inputs: MethodInputs) -> Reconstruction: ...


@dataclass(frozen=True)
class MethodBase:
    """The defaults of a :class:`Method`: no field, meshed on the scan grid."""

    name: str
    needs_field: bool = False
    scan_grid: bool = True
    config_class: type = object


@dataclass(frozen=True)
class UltronMethod(MethodBase):
    """UltrON (``ultron``) or its ablation without the compensated loss (``ultron-noloss``)."""

    needs_field: bool = True
    config_class: type = UltronConfig

    def fit(self, dataset: SweepDataset, inputs: MethodInputs) -> Reconstruction:
        if inputs.fitted is None:
            raise argument_error("field", f"method {self.name!r} needs a fitted acoustic field")
        request = inputs.request
        config = replace(request.ultron, label_fraction=request.label_fraction, seed=request.seed)
        return reconstruct_ultron(
            dataset, inputs.fitted, self.name, config, inputs.timer, inputs.truth, inputs.device
        )


@dataclass(frozen=True)
class CompoundingMethod(MethodBase):
    """Label compounding, meshed with UltrON's extraction and observed-surface settings."""

    config_class: type = CompoundingConfig

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
            self.views, timer=inputs.timer, dataset_name=inputs.dataset_name,
            device=inputs.device,
        )  # fmt: skip


METHODS: Mapping[str, Method] = MappingProxyType(
    {
        method.name: method
        for method in (
            UltronMethod("ultron"),
            UltronMethod("ultron-noloss"),
            CompoundingMethod("compounding"),
            ONMethod("on"),
            SDFMethod("rocosdf", views=("row", "column")),
            SDFMethod("unsr-row", views=("row",)),
            SDFMethod("unsr-col", views=("column",)),
        )
    }
)
#: The methods that read a fitted acoustic field.
FIELD_METHODS = tuple(name for name, method in METHODS.items() if method.needs_field)


def get_method(name: str) -> Method:
    """The registered method ``name``; an unknown one is an error naming ``method``."""
    if name not in METHODS:
        raise argument_error("method", f"expected one of {tuple(METHODS)}, got {name!r}")
    return METHODS[name]


__all__ = ["FIELD_METHODS", "METHODS", "Method", "MethodInputs", "get_method"]
