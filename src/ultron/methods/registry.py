"""Every reconstruction method behind one interface, found through one registry.

``METHODS`` maps a method's name (``reconstruct --method``) to a :class:`Method`: whether it
needs a fitted acoustic field, the class of its settings (``config_class``: a
:class:`~ultron.methods.request.ReconstructionRequest` carries one instance, its
``method_config``), how to take them from a preset that sets every stage (``config_of``), the
voxel it meshes at, and ``fit(dataset, inputs)`` →
:class:`~ultron.methods.ultron_method.Reconstruction`. The names
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
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any, Protocol

import torch

from ultron.data.dataset import SweepDataset
from ultron.data.labels import FrameSelection, select_label_frames
from ultron.device import CPU
from ultron.errors import argument_error
from ultron.methods.catalog import FIELD_METHODS, METHOD_NAMES
from ultron.methods.compounding_method import CompoundingMethodConfig, reconstruct_compounding
from ultron.methods.on_method import ONConfig, reconstruct_on
from ultron.methods.rocosdf import RoCoSDFConfig, reconstruct_rocosdf
from ultron.methods.ultron_method import (
    Reconstruction,
    Stage2Fit,
    UltronConfig,
    mesh_ultron,
    train_ultron,
)
from ultron.pipeline.resources import check_compounding_grid
from ultron.timing import StageTimer
from ultron.train.visibility import VisibilityConfig


class StageSettings(Protocol):
    """Settings of every method under one name (a pipeline preset, the benchmark's
    configuration): UltrON's (also compounding's extraction and observed crop), ON's and the
    name of RoCoSDF's preset. :meth:`Method.config_of` takes a method's own from them."""

    ultron: UltronConfig
    on: ONConfig
    rocosdf_preset: str


@dataclass(frozen=True)
class MethodInputs:
    """What a method runs with besides the dataset: its settings (``config``, an instance of
    its ``config_class``), the label fraction and seed, the stage timer, the fitted field (None
    unless the method needs one), the oracle's true T per sweep (diagnostic runs), the
    dataset's name for input errors, the device, and the directory where its fits keep their
    checkpoints (None: none; :mod:`ultron.train.fit_checkpoint`)."""

    config: Any
    timer: StageTimer = field(default_factory=StageTimer)
    label_fraction: float = 0.1
    seed: int = 0
    fitted: Any = None
    truth: Mapping[str, Any] | None = None
    dataset_name: str | None = None
    device: torch.device = CPU
    checkpoints: Path | None = None


class Method(Protocol):
    """A reconstruction method (module doc)."""

    name: str
    needs_field: bool
    #: Whether it meshes on the grid over the scanned region (whose memory a run checks
    #: before any work); compounding meshes the labelled bone's box, RoCoSDF and UNSR their
    #: own grid around the labelled points.
    scan_grid: bool
    config_class: type

    def config_of(self, stages: StageSettings) -> Any:
        """Its settings (a ``config_class``) under ``stages``, a preset that sets every method."""
        ...

    def meshing_voxel(self, config: Any) -> float | None:
        """The voxel, mm, ``config`` asks this method to mesh at (None: its default, the finer
        pixel spacing); the run checks the grid's memory with it before any work."""
        ...

    def visibility(self, config: Any) -> VisibilityConfig | None:
        """The source of its loss's transmission T (None: it uses none), whose files (the
        oracle's) a run reads before any work."""
        ...

    def check_resources(
        self,
        dataset: SweepDataset,
        config: Any,
        selection: FrameSelection,
        root: str | Path,
        max_memory_gib: float | None,
    ) -> None:
        """Refuse, before any work, a run on ``selection`` whose own grid (one not over the
        scanned region) would exceed the memory limit; ``root`` is named in the error."""
        ...

    def fit(self, dataset: SweepDataset, inputs: MethodInputs) -> Reconstruction: ...


class FieldMethod(Method, Protocol):
    """A method that reads a fitted acoustic field (``needs_field``), its stage 2 and stage 3
    apart: ``fit`` is ``finish(train(…))``, and a run given several fields trains on each and
    finishes the one whose f fits its labels best (:func:`ultron.pipeline.run.run_on_fields`)."""

    def train(self, dataset: SweepDataset, inputs: MethodInputs) -> Stage2Fit: ...

    def finish(
        self, dataset: SweepDataset, inputs: MethodInputs, trained: Stage2Fit
    ) -> Reconstruction: ...


@dataclass(frozen=True)
class MethodBase:
    """The defaults of a :class:`Method`: no field, meshed on the scan grid, no T."""

    name: str
    scan_grid: bool = True
    config_class: type = object

    @property
    def needs_field(self) -> bool:
        """Whether it reads a fitted acoustic field (:mod:`ultron.methods.catalog`)."""
        return self.name in FIELD_METHODS

    def visibility(self, config: Any) -> VisibilityConfig | None:
        return None

    def check_resources(
        self,
        dataset: SweepDataset,
        config: Any,
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

    def config_of(self, stages: StageSettings) -> UltronConfig:
        return stages.ultron

    def meshing_voxel(self, config: UltronConfig) -> float | None:
        return config.voxel_mm

    def visibility(self, config: UltronConfig) -> VisibilityConfig | None:
        return config.visibility

    def check_resources(
        self,
        dataset: SweepDataset,
        config: UltronConfig,
        selection: FrameSelection,
        root: str | Path,
        max_memory_gib: float | None,
    ) -> None:
        """With ``config.label_fusion`` applying to ``selection``, the compounded labels' grid
        as compounding checks it (an upper bound: fusion reads that grid and does not mesh it)."""
        fusion = config.label_fusion
        if fusion is not None and fusion.applies(dataset, selection):
            check_compounding_grid(dataset, selection, fusion.volume, root, max_memory_gib)

    def fit(self, dataset: SweepDataset, inputs: MethodInputs) -> Reconstruction:
        return self.finish(dataset, inputs, self.train(dataset, inputs))

    def train(self, dataset: SweepDataset, inputs: MethodInputs) -> Stage2Fit:
        """Stage 2 alone (:func:`~ultron.methods.ultron_method.train_ultron`) on
        ``inputs.fitted``: a run given several fields trains on each and meshes once."""
        if inputs.fitted is None:
            raise argument_error("field", f"method {self.name!r} needs a fitted acoustic field")
        return train_ultron(
            dataset, inputs.fitted, self.loss, inputs.label_fraction, inputs.seed, inputs.config,
            inputs.timer, inputs.truth, inputs.device, inputs.checkpoints,
        )  # fmt: skip

    def finish(
        self, dataset: SweepDataset, inputs: MethodInputs, trained: Stage2Fit
    ) -> Reconstruction:
        """Stage 3 of :meth:`train`'s result (:func:`~ultron.methods.ultron_method.mesh_ultron`)."""
        return mesh_ultron(dataset, trained, inputs.config, inputs.timer, inputs.truth)


@dataclass(frozen=True)
class CompoundingMethod(MethodBase):
    """Label compounding, meshed with UltrON's extraction and observed-surface settings."""

    scan_grid: bool = False
    config_class: type = CompoundingMethodConfig

    def config_of(self, stages: StageSettings) -> CompoundingMethodConfig:
        return CompoundingMethodConfig(
            extraction=stages.ultron.extraction, observed=stages.ultron.observed
        )

    def meshing_voxel(self, config: CompoundingMethodConfig) -> float | None:
        return config.volume.voxel_mm

    def check_resources(
        self,
        dataset: SweepDataset,
        config: CompoundingMethodConfig,
        selection: FrameSelection,
        root: str | Path,
        max_memory_gib: float | None,
    ) -> None:
        """Its grid, the labelled bone's box, and labelled pixels within the memory limit."""
        check_compounding_grid(dataset, selection, config.volume, root, max_memory_gib)

    def fit(self, dataset: SweepDataset, inputs: MethodInputs) -> Reconstruction:
        return reconstruct_compounding(
            dataset, inputs.label_fraction, inputs.seed, inputs.config, inputs.timer
        )


@dataclass(frozen=True)
class ONMethod(MethodBase):
    """The coordinate occupancy network."""

    config_class: type = ONConfig

    def config_of(self, stages: StageSettings) -> ONConfig:
        return stages.on

    def meshing_voxel(self, config: ONConfig) -> float | None:
        return config.meshing.voxel_mm

    def fit(self, dataset: SweepDataset, inputs: MethodInputs) -> Reconstruction:
        return reconstruct_on(
            dataset, inputs.label_fraction, inputs.seed, inputs.config, inputs.timer,
            inputs.device, inputs.checkpoints,
        )  # fmt: skip


@dataclass(frozen=True)
class SDFMethod(MethodBase):
    """RoCoSDF on the row and column views, or UNSR (its stage 1) on one view."""

    views: tuple[str, ...] = ("row", "column")
    scan_grid: bool = False
    config_class: type = RoCoSDFConfig

    def config_of(self, stages: StageSettings) -> RoCoSDFConfig:
        return RoCoSDFConfig.preset(stages.rocosdf_preset)

    def meshing_voxel(self, config: RoCoSDFConfig) -> float | None:
        """None: its grid has a fixed resolution around the labelled points (no scan grid)."""
        return None

    def fit(self, dataset: SweepDataset, inputs: MethodInputs) -> Reconstruction:
        with inputs.timer.stage("labels"):
            selection = select_label_frames(dataset, inputs.label_fraction, inputs.seed)
        return reconstruct_rocosdf(
            dataset, selection, inputs.config, inputs.seed, self.views,
            progress=inputs.timer.fit_progress, timer=inputs.timer,
            dataset_name=inputs.dataset_name, device=inputs.device,
            checkpoints=inputs.checkpoints,
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


def check_method_name(name: str) -> str:
    """``name`` when it is a catalogued method; otherwise an error naming ``method``."""
    if name not in METHOD_NAMES:
        raise argument_error("method", f"expected one of {METHOD_NAMES}, got {name!r}")
    return name


def get_method(name: str) -> Method:
    """The registered method ``name``; an unknown one is an error naming ``method``."""
    return METHODS[check_method_name(name)]


__all__ = [
    "METHODS",
    "FieldMethod",
    "Method",
    "MethodInputs",
    "StageSettings",
    "check_method_name",
    "get_method",
]
