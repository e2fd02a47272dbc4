"""What a reconstruction runs with: :class:`ReconstructionRequest`.

It sits below both the registry (whose methods read it) and the pipeline (which builds and
runs it), so that neither imports the other's module for it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ultron.device import resolve_device
from ultron.errors import argument_error
from ultron.mesh.compounding import CompoundingConfig
from ultron.mesh.export import check_mesh_coordinates
from ultron.methods.catalog import FIELD_METHODS, METHOD_NAMES
from ultron.methods.on_method import ONConfig
from ultron.methods.ultron_method import UltronConfig
from ultron.metrics.surface import MetricsConfig

ROCOSDF_PRESETS = ("fast", "paper")


def check_method_name(name: str) -> str:
    """``name`` when it is a catalogued method; otherwise an error naming ``method``."""
    if name not in METHOD_NAMES:
        raise argument_error("method", f"expected one of {METHOD_NAMES}, got {name!r}")
    return name


@dataclass(frozen=True)
class ReconstructionRequest:
    """What to run: the method, its label fraction and seed, and per-stage settings."""

    method: str = "ultron"
    label_fraction: float = 0.1
    seed: int = 0
    ultron: UltronConfig = field(default_factory=UltronConfig)
    compounding: CompoundingConfig = field(default_factory=CompoundingConfig)
    on: ONConfig = field(default_factory=ONConfig)
    rocosdf_preset: str = "fast"
    metrics: MetricsConfig = field(default_factory=MetricsConfig)
    mesh_coordinates: str = "lps"
    #: Where the networks train and are evaluated (:func:`ultron.device.resolve_device`).
    device: str = "cpu"

    def __post_init__(self) -> None:
        check_method_name(self.method)
        if not 0 < self.label_fraction <= 1:
            raise argument_error(
                "label_fraction", f"expected a value in (0, 1], got {self.label_fraction}"
            )
        check_mesh_coordinates(self.mesh_coordinates, "mesh_coordinates")
        resolve_device(self.device, "device")
        if self.rocosdf_preset not in ROCOSDF_PRESETS:
            raise argument_error(
                "preset", f"expected one of {ROCOSDF_PRESETS}, got {self.rocosdf_preset!r}"
            )
        source = self.ultron.visibility.source
        if source != "field" and self.method not in FIELD_METHODS:
            flag = "--oracle-transmission" if source == "oracle" else f"--visibility {source}"
            raise argument_error(
                "visibility", f"{flag} applies to --method {' or '.join(FIELD_METHODS)} only, "
                f"not {self.method!r}",
            )  # fmt: skip


__all__ = ["ROCOSDF_PRESETS", "ReconstructionRequest", "check_method_name"]
