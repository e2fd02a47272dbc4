"""Named outputs of an acoustic field: θ = (α, β, φ[, scatter density])."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any

import torch
import torch.nn.functional as F

from ultron.errors import argument_error, config_from_dict

#: Channel order of :meth:`AcousticProperties.stack` (without and with a learned density).
CHANNELS: tuple[str, ...] = ("attenuation", "reflection", "scattering")
CHANNELS_WITH_DENSITY: tuple[str, ...] = (*CHANNELS, "density")

#: Raw-output values that the decoders' last bias starts at in the paper's heads, chosen so an
#: untrained field is a weak attenuator (α ≈ 0.005 /mm), a rare reflector (β ≈ 1e-3 per sample)
#: and mid-grey φ.
INITIAL_ATTENUATION_PER_MM = 0.005
INITIAL_REFLECTION = 1e-3
INITIAL_SCATTERING = 0.5
INITIAL_DENSITY = 0.75
#: The reflection head's gain g_β of the default heads (Ultra-NeRF's: 1); see HeadConfig.
REFLECTION_GAIN = 4.0


@dataclass(frozen=True)
class HeadConfig:
    """How raw network outputs become θ, and where an untrained field starts.

        α = s_α · softplus(a),   β = sigmoid(b₀ + g_β · (b − b₀)),
        φ = φ_min + (1 − φ_min) · sigmoid(c),   b₀ = logit(β_init)

    The default is Ultra-NeRF's parameterisation (φ_min = 0, s_α = 1, the INITIAL_* values)
    with a reflection gain g_β = 4; :meth:`paper` is Ultra-NeRF's exactly (g_β = 1, so β =
    sigmoid(b)).
    :meth:`identifiable` adds the two changes that make the shadow identifiable:

    - a **scattering floor** φ_min: soft tissue and bone always scatter, so a dark region
      under a bright reflector cannot be explained by φ → 0 and must be explained by a loss of
      transmission T (α or β above it) — which is what the attenuation-compensated loss needs.
      Set it to 0 where the anatomy holds anechoic fluid (a cyst, a vessel, the bladder);
    - an initial attenuation such that T at the bottom of a 70 mm frame starts near 0.5
      (``initial_attenuation_per_mm`` 0.01), so α starts where its gradient is informative.

    On the tuning phantoms the paper's heads leave T high in the shadow (explaining it by
    φ → 0) and the floor brings it near 0. It is not the default because UltrON(10 %) on such a
    field scored a worse visible CD: the θ it gives separates bone from gel less well. Figures
    in docs/decisions.md#field-heads-scattering-floor-fieldspropertiespy.

    ``reflection_gain`` g_β scales the reflection head's raw output about its start b₀, so the
    field still starts at β_init. At β_init = 10⁻³ the sigmoid's slope is ≈ 10⁻³, against 0.25
    for φ at 0.5: a bright echo is first explained by φ, and whether β ever leaves its start in
    a 3000-step fit depends on the seed. A field whose β stays there explains the bone's echo
    by φ alone, and UltrON on it loses surface; with g_β = 4 the reflection head learns four
    times faster in its raw output. Figures in
    docs/decisions.md#field-heads-reflection-gain-fieldspropertiespy.
    """

    scattering_floor: float = 0.0
    attenuation_scale_per_mm: float = 1.0
    initial_attenuation_per_mm: float = INITIAL_ATTENUATION_PER_MM
    initial_reflection: float = INITIAL_REFLECTION
    initial_scattering: float = INITIAL_SCATTERING
    initial_density: float = INITIAL_DENSITY
    reflection_gain: float = REFLECTION_GAIN

    def __post_init__(self) -> None:
        if not (math.isfinite(self.scattering_floor) and 0 <= self.scattering_floor < 1):
            raise argument_error("heads.scattering_floor", "expected a value in [0, 1)")
        for name in ("attenuation_scale_per_mm", "initial_attenuation_per_mm", "reflection_gain"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise argument_error(f"heads.{name}", f"expected a finite value > 0, got {value!r}")
        for name in ("initial_reflection", "initial_scattering", "initial_density"):
            if not 0 < getattr(self, name) < 1:
                raise argument_error(f"heads.{name}", "expected a value inside (0, 1)")
        if not self.scattering_floor < self.initial_scattering:  # φ starts above its floor
            raise argument_error(
                "heads.scattering_floor",
                f"expected a value below the initial scattering {self.initial_scattering:g},"
                f" got {self.scattering_floor:g}",
            )

    @classmethod
    def paper(cls) -> HeadConfig:
        """Ultra-NeRF's heads exactly (no floor, α = softplus, β = sigmoid, the paper-port
        initial values)."""
        return cls(reflection_gain=1.0)

    @classmethod
    def identifiable(cls) -> HeadConfig:
        """The heads that put the shadow in T: φ_min = 0.1 and α starting at 0.01 /mm."""
        return cls(scattering_floor=0.1, initial_attenuation_per_mm=0.01)

    def to_dict(self) -> dict[str, float]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> HeadConfig:
        """From field.json's ``heads``; a field saved before ``reflection_gain`` existed had
        none (1)."""
        return config_from_dict(cls, {"reflection_gain": 1.0, **data}, "heads")


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


def properties_from_raw(
    raw: torch.Tensor, learn_density: bool, heads: HeadConfig | None = None
) -> AcousticProperties:
    """Heads from raw network outputs (…, 3|4), see :class:`HeadConfig` (default: paper)."""
    heads = heads or HeadConfig.paper()
    expected = n_raw_channels(learn_density)
    if raw.shape[-1] != expected:
        raise argument_error("raw", f"expected {expected} channels, got {tuple(raw.shape)}")
    floor = heads.scattering_floor
    return AcousticProperties(
        attenuation=heads.attenuation_scale_per_mm * F.softplus(raw[..., 0]),
        reflection=torch.sigmoid(_reflection_raw(raw[..., 1], heads)),
        scattering=floor + (1.0 - floor) * torch.sigmoid(raw[..., 2]),
        density=torch.sigmoid(raw[..., 3]) if learn_density else None,
    )


def _reflection_raw(raw: torch.Tensor, heads: HeadConfig) -> torch.Tensor:
    """b₀ + g_β · (b − b₀): the raw reflection output scaled about its start (b itself at g_β =
    1, bit for bit)."""
    gain = heads.reflection_gain
    if gain == 1.0:
        return raw
    start = _logit(heads.initial_reflection)
    return start + gain * (raw - start)


def initial_raw_bias(learn_density: bool, heads: HeadConfig | None = None) -> torch.Tensor:
    """Raw values whose heads give the configured initial properties (inverse of the heads)."""
    heads = heads or HeadConfig.paper()
    alpha = heads.initial_attenuation_per_mm / heads.attenuation_scale_per_mm
    floor = heads.scattering_floor
    values = [
        math.log(math.expm1(alpha)),
        _logit(heads.initial_reflection),
        _logit((heads.initial_scattering - floor) / (1.0 - floor)),
    ]
    if learn_density:
        values.append(_logit(heads.initial_density))
    return torch.tensor(values)


def _logit(p: float) -> float:
    return math.log(p / (1 - p))
