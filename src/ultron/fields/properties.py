"""Named outputs of an acoustic field: θ = (α, β, φ[, scatter density])."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields

import torch
import torch.nn.functional as F

from ultron.errors import argument_error

#: Channel order of :meth:`AcousticProperties.stack` (without and with a learned density).
CHANNELS: tuple[str, ...] = ("attenuation", "reflection", "scattering")
CHANNELS_WITH_DENSITY: tuple[str, ...] = (*CHANNELS, "density")

#: Raw-output values that the decoders' last bias starts at, chosen so an untrained field is a
#: weak attenuator (α ≈ 0.005 /mm), a rare reflector (β ≈ 1e-3 per sample) and mid-grey φ.
INITIAL_ATTENUATION_PER_MM = 0.005
INITIAL_REFLECTION = 1e-3
INITIAL_SCATTERING = 0.5
INITIAL_DENSITY = 0.75


@dataclass(frozen=True)
class AcousticProperties:
    """Acoustic properties θ at a set of points, each tensor of the same shape (…).

    - ``attenuation``: α ≥ 0, in 1/mm (A = exp(−∫α ds));
    - ``reflection``: β ∈ (0, 1), fraction reflected per sample;
    - ``scattering``: φ ∈ (0, 1), scattering amplitude;
    - ``density``: optional learned scatterer probability p ∈ (0, 1) (``None``: fixed p).
    """

    attenuation: torch.Tensor
    reflection: torch.Tensor
    scattering: torch.Tensor
    density: torch.Tensor | None = None

    @property
    def channels(self) -> tuple[str, ...]:
        """Names of the channels :meth:`stack` returns, in order."""
        return CHANNELS if self.density is None else CHANNELS_WITH_DENSITY

    @property
    def shape(self) -> torch.Size:
        return self.attenuation.shape

    def stack(self) -> torch.Tensor:
        """θ as one (…, C) tensor in the order of :attr:`channels`."""
        return torch.stack([getattr(self, name) for name in self.channels], dim=-1)

    @classmethod
    def unstack(
        cls, values: torch.Tensor, channels: tuple[str, ...] = CHANNELS
    ) -> AcousticProperties:
        """Inverse of :meth:`stack` for a (…, C) tensor with the named channel order."""
        if channels not in (CHANNELS, CHANNELS_WITH_DENSITY):
            raise argument_error("channels", f"expected {CHANNELS} or {CHANNELS_WITH_DENSITY}")
        if values.shape[-1] != len(channels):
            raise argument_error(
                "values", f"expected {len(channels)} channels, got shape {tuple(values.shape)}"
            )
        return cls(**dict(zip(channels, values.unbind(-1), strict=True)))

    def map(self, function: Callable[[torch.Tensor], torch.Tensor]) -> AcousticProperties:
        """Apply ``function`` to every present tensor (reshape, index, detach…)."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        return AcousticProperties(
            **{k: (function(v) if v is not None else None) for k, v in values.items()}
        )


def n_raw_channels(learn_density: bool) -> int:
    """Number of raw network outputs: 3, or 4 with a learned scatter density."""
    return 4 if learn_density else 3


def properties_from_raw(raw: torch.Tensor, learn_density: bool) -> AcousticProperties:
    """Heads from raw network outputs (…, 3|4): α = softplus, β, φ, p = sigmoid."""
    expected = n_raw_channels(learn_density)
    if raw.shape[-1] != expected:
        raise argument_error("raw", f"expected {expected} channels, got {tuple(raw.shape)}")
    return AcousticProperties(
        attenuation=F.softplus(raw[..., 0]),
        reflection=torch.sigmoid(raw[..., 1]),
        scattering=torch.sigmoid(raw[..., 2]),
        density=torch.sigmoid(raw[..., 3]) if learn_density else None,
    )


def initial_raw_bias(learn_density: bool) -> torch.Tensor:
    """Raw values whose heads give the INITIAL_* properties (inverse softplus / logit)."""
    alpha = math.log(math.expm1(INITIAL_ATTENUATION_PER_MM))
    values = [alpha, _logit(INITIAL_REFLECTION), _logit(INITIAL_SCATTERING)]
    if learn_density:
        values.append(_logit(INITIAL_DENSITY))
    return torch.tensor(values)


def _logit(p: float) -> float:
    return math.log(p / (1 - p))
