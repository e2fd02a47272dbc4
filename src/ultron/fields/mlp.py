"""The ``mlp`` backend: Ultra-NeRF's network (8 × 128, skip at 4, ReLU, NeRF encoding L = 10)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ultron.errors import argument_error
from ultron.fields.base import AcousticField
from ultron.fields.networks import PositionalEncoding, SkipMLP
from ultron.fields.properties import HeadConfig, initial_raw_bias, n_raw_channels


@dataclass(frozen=True)
class MLPFieldConfig:
    """The paper's trunk: ``depth`` × ``width`` ReLU layers, skip at ``skip_at``, γ with L bands."""

    width: int = 128
    depth: int = 8
    skip_at: int = 4
    n_frequencies: int = 10

    def __post_init__(self) -> None:
        for name in ("width", "depth", "n_frequencies"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < (0 if name == "n_frequencies" else 1):
                raise argument_error(f"mlp.{name}", f"expected a positive integer, got {value!r}")


class MLPField(AcousticField):
    """θ(u) = heads(SkipMLP(γ(u))) on unit-cube coordinates u ∈ [−1, 1]³."""

    def __init__(
        self, config: MLPFieldConfig, learn_density: bool = False, heads: HeadConfig | None = None
    ) -> None:
        super().__init__(learn_density, heads)
        self.config = config
        self.encoding = PositionalEncoding(config.n_frequencies, include_input=True)
        self.trunk = SkipMLP(
            self.encoding.output_dim(3),
            n_raw_channels(learn_density),
            width=config.width,
            depth=config.depth,
            skip_at=config.skip_at,
        )
        with torch.no_grad():
            self.trunk.output.bias.copy_(initial_raw_bias(learn_density, self.head_config))

    def raw(self, points_unit: torch.Tensor) -> torch.Tensor:
        return self.trunk(self.encoding(points_unit.to(torch.float32)))
