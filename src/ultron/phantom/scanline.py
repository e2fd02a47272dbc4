"""Pure per-scanline physics of the B-mode simulator.

Every tensor is (..., H, W): rows (samples along the beam, step Δ, ordered by depth) are the
second-to-last dimension, scanlines the last. Interfaces lie between rows r and r + 1 and are
held in (..., H − 1, W) tensors at index r.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ultron.phantom.tissue import amplitude_from_db, incidence_factor

_NEPER_PER_DB_AMPLITUDE = math.log(10.0) / 20.0


@dataclass
class Crossings:
    """Gel/bone interfaces between rows r and r + 1, each (..., H − 1, W): ``entering``
    (gel → bone), ``exiting`` (bone → gel) and ``fraction`` t ∈ [0, 1] — the crossing lies at
    depth (r + t)·Δ (0 where there is none)."""

    entering: torch.Tensor
    exiting: torch.Tensor
    fraction: torch.Tensor

    @property
    def any(self) -> torch.Tensor:
        return self.entering | self.exiting


def interface_crossings(sdf: torch.Tensor) -> Crossings:
    """Sign changes of the SDF d between rows r and r + 1 (d ≥ 0 gel, d < 0 bone), located at
    the zero of the linear interpolant: t = d_r / (d_r − d_{r+1})."""
    above, below = sdf[..., :-1, :], sdf[..., 1:, :]
    entering = (above >= 0) & (below < 0)
    exiting = (above < 0) & (below >= 0)
    crossing = entering | exiting
    fraction = torch.where(crossing, above / (above - below).where(crossing, 1.0), 0.0)
    return Crossings(entering, exiting, fraction)


def round_trip_attenuation_db(
    occupancy: torch.Tensor, step_mm: float, gel_db_per_mm: float, bone_db_per_mm: float
) -> torch.Tensor:
    """Round-trip attenuation to each sample, exclusive of the sample itself (dB):

    A_r = 2Δ · Σ_{k<r} [α_gel + o_k·(α_bone − α_gel)],   o_k the bone occupancy of sample k.
    """
    alpha = gel_db_per_mm + occupancy * (bone_db_per_mm - gel_db_per_mm)
    cumulative = torch.cumsum(alpha, dim=-2) * (2.0 * step_mm)
    return torch.cat([torch.zeros_like(cumulative[..., :1, :]), cumulative[..., :-1, :]], -2)


def _interfaces_above(crossings: Crossings) -> torch.Tensor:
    """m_r: number of interfaces between the transducer and row r, (..., H, W)."""
    count = torch.cumsum(crossings.any.to(crossings.fraction.dtype), dim=-2)
    return torch.cat([torch.zeros_like(count[..., :1, :]), count], -2)


def transmission_amplitude(
    crossings: Crossings, attenuation_db: torch.Tensor, reflection: float
) -> torch.Tensor:
    """Round-trip amplitude transmission to each sample:

    τ_r = (1 − R)^{m_r} · 10^(−A_r/20),

    each interface passing 1 − R of the intensity each way (amplitude factor 1 − R there and
    back), m_r interfaces above row r.
    """
    log_pass = math.log(1.0 - reflection)
    exponent = -_NEPER_PER_DB_AMPLITUDE * attenuation_db + log_pass * _interfaces_above(crossings)
    return torch.exp(exponent)


def echo_amplitudes(
    crossings: Crossings,
    cos_incidence: torch.Tensor,
    attenuation_db: torch.Tensor,
    reflection: float,
    specular_exponent: float,
    diffuse_fraction: float,
) -> torch.Tensor:
    """Specular echo amplitude of every interface (0 elsewhere), (..., H − 1, W):

    a = √(R·g(θ)) · (1 − R)^m · 10^(−A(d)/20),   A(d) = A_r + t·(A_{r+1} − A_r),

    g the incidence factor, m the interfaces above this one.
    """
    crossing = crossings.any
    t = crossings.fraction
    at_crossing = attenuation_db[..., :-1, :] + t * (
        attenuation_db[..., 1:, :] - attenuation_db[..., :-1, :]
    )
    m_above = _interfaces_above(crossings)[..., :-1, :]
    strength = reflection * incidence_factor(cos_incidence, specular_exponent, diffuse_fraction)
    amplitude = (
        torch.sqrt(strength)
        * torch.exp(math.log(1.0 - reflection) * m_above)
        * amplitude_from_db(at_crossing)
    )
    return torch.where(crossing, amplitude, 0.0)


def deposit_echoes(echo: torch.Tensor, fraction: torch.Tensor) -> torch.Tensor:
    """Place each echo at its sub-pixel depth by splitting it linearly between its rows:

    e_r = a_r·(1 − t_r) + a_{r−1}·t_{r−1},   returning (..., H, W) from (..., H − 1, W).
    """
    shape = list(echo.shape)
    shape[-2] += 1
    out = echo.new_zeros(shape)
    out[..., :-1, :] += echo * (1.0 - fraction)
    out[..., 1:, :] += echo * fraction
    return out
