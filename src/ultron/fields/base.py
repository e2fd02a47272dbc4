"""The acoustic field interface: unit-cube points → named acoustic properties θ."""

from __future__ import annotations

import torch
from torch import nn

from ultron.device import module_device
from ultron.fields.properties import AcousticProperties, HeadConfig, properties_from_raw


class AcousticField(nn.Module):
    """Base class of field backends.

    A backend maps points in the normalised unit cube (…, 3) to raw outputs (…, 3|4) with
    :meth:`raw`; :meth:`forward` applies the named heads (:class:`~ultron.fields.properties.HeadConfig`).
    :meth:`regularization` is the backend's own smoothness prior (0 when it has none).
    """

    def __init__(self, learn_density: bool = False, heads: HeadConfig | None = None) -> None:
        super().__init__()
        self.learn_density = bool(learn_density)
        self.head_config = heads or HeadConfig.paper()

    def raw(self, points_unit: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def heads(self, raw: torch.Tensor) -> AcousticProperties:
        return properties_from_raw(raw, self.learn_density, self.head_config)

    def forward(self, points_unit: torch.Tensor) -> AcousticProperties:
        return self.heads(self.raw(points_unit))

    def regularization(
        self, generator: torch.Generator | None = None, draws: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Smoothness penalty of the parameters (a scalar; zero for backends without one).

        Backends may evaluate it stochastically; ``generator`` makes that reproducible, or
        ``draws`` (:meth:`regularization_draws`, on the parameters' device) gives the draws.
        """
        return torch.zeros((), device=module_device(self))

    def regularization_draws(self, generator: torch.Generator | None) -> torch.Tensor | None:
        """The random draws :meth:`regularization` makes from ``generator`` (None: none)."""
        return None
