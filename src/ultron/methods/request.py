"""What a reconstruction runs with: :class:`ReconstructionRequest`.

One method, its label fraction and seed, and that method's own settings
(``method_config``, an instance of the registry's :attr:`~ultron.methods.registry.Method.config_class`):
the request carries no other method's settings. A preset that sets every stage at once
(:mod:`ultron.pipeline.presets`, the benchmark's configuration) hands each method its own
through :meth:`~ultron.methods.registry.Method.config_of`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from ultron.arguments import check_fraction, check_seed
from ultron.device import resolve_device
from ultron.errors import argument_error
from ultron.mesh.export import check_mesh_coordinates
from ultron.methods.registry import get_method
from ultron.metrics.surface import MetricsConfig


@dataclass(frozen=True)
class ReconstructionRequest:
    """What to run: the method, its label fraction and seed, its settings (``method_config``:
    None takes the method's defaults), the metrics, the mesh files' coordinates and the device."""

    method: str = "ultron"
    label_fraction: float = 0.1
    seed: int = 0
    method_config: Any = None
    metrics: MetricsConfig = field(default_factory=MetricsConfig)
    mesh_coordinates: str = "lps"
    #: Where the networks train and are evaluated (:func:`ultron.device.resolve_device`).
    device: str = "cpu"

    def __post_init__(self) -> None:
        config_class = get_method(self.method).config_class
        if self.method_config is None:
            object.__setattr__(self, "method_config", config_class())
        elif not isinstance(self.method_config, config_class):
            raise argument_error(
                "method_config",
                f"method {self.method!r} takes a {config_class.__name__}, got"
                f" {type(self.method_config).__name__}",
            )
        check_seed("seed", self.seed)
        check_fraction("label_fraction", self.label_fraction)
        check_mesh_coordinates(self.mesh_coordinates, "mesh_coordinates")
        resolve_device(self.device, "device")


__all__ = ["ReconstructionRequest"]
