"""Occupancy networks: UltrON's f_ω(θ) and the coordinate ON baseline share one architecture.

f_ω: γ(input) → 8 × 128 ReLU layers with the input re-concatenated at layer 4 → 1 logit →
sigmoid. For UltrON the input is θ(x) normalised per channel with the acoustic field's saved
statistics (and θ of its neighbours, :mod:`ultron.fields.context`); for ON it is the world
point mapped to the unit cube. γ is the NeRF positional encoding with ``n_frequencies`` bands,
applied to the first ``encoded_inputs`` inputs (all by default); the rest enter the trunk as
they are.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import nn

from ultron.errors import argument_error
from ultron.fields.networks import PositionalEncoding, SkipMLP


@dataclass(frozen=True)
class OccupancyNetworkConfig:
    """Architecture of :class:`OccupancyNetwork` (the paper's defaults); ``encoded_inputs``:
    how many leading inputs γ encodes (None: all)."""

    in_dim: int = 3
    n_frequencies: int = 4
    width: int = 128
    depth: int = 8
    skip_at: int = 4
    encoded_inputs: int | None = None

    def __post_init__(self) -> None:
        if self.in_dim < 1:
            raise argument_error("in_dim", f"expected ≥ 1, got {self.in_dim}")
        if self.encoded_inputs is not None and not 0 <= self.encoded_inputs <= self.in_dim:
            raise argument_error(
                "encoded_inputs",
                f"expected None or 0 … in_dim={self.in_dim}, got {self.encoded_inputs}",
            )
        if self.n_frequencies < 0:
            raise argument_error("n_frequencies", f"expected ≥ 0, got {self.n_frequencies}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> OccupancyNetworkConfig:
        return cls(**data)


class OccupancyNetwork(nn.Module):
    """f_ω: (…, in_dim) → occupancy logits (…); :meth:`occupancy` applies the sigmoid."""

    def __init__(self, config: OccupancyNetworkConfig | None = None) -> None:
        super().__init__()
        self.config = config or OccupancyNetworkConfig()
        self.encoding = PositionalEncoding(self.config.n_frequencies)
        self.n_encoded = (
            self.config.in_dim if self.config.encoded_inputs is None else self.config.encoded_inputs
        )
        self.trunk = SkipMLP(
            self.encoding.output_dim(self.n_encoded) + self.config.in_dim - self.n_encoded,
            1,
            width=self.config.width,
            depth=self.config.depth,
            skip_at=self.config.skip_at,
        )

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        if inputs.shape[-1] != self.config.in_dim:
            raise argument_error(
                "inputs", f"expected (..., {self.config.in_dim}), got {tuple(inputs.shape)}"
            )
        encoded = self.encoding(inputs[..., : self.n_encoded])
        if self.n_encoded < self.config.in_dim:
            encoded = torch.cat([encoded, inputs[..., self.n_encoded :]], dim=-1)
        return self.trunk(encoded).squeeze(-1)

    def occupancy(self, inputs: torch.Tensor) -> torch.Tensor:
        """σ(f_ω(inputs)) ∈ (0, 1)."""
        return torch.sigmoid(self.forward(inputs))

    def last_layers(self, n: int = 2) -> list[nn.Module]:
        """The last ``n`` linear layers (output layer included), e.g. to freeze for fine-tuning."""
        layers = [*self.trunk.hidden, self.trunk.output]
        return layers[-n:]
