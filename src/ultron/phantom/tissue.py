"""Acoustic tissue parameters and the pure interface/attenuation formulas of the simulator.

Typical values (soft-tissue-mimicking gelatin with paper pulp, and cortical bone):

==========================  ===========  ===========  ==================  ====================
tissue                      c (m/s)      Z (MRayl)    α (dB/cm/MHz)       scatterers
==========================  ===========  ===========  ==================  ====================
gelatin + paper pulp        ≈ 1540       ≈ 1.58       ≈ 0.5               dense (≥ 10/mm³)
cortical bone               ≈ 3500       ≈ 7.4        ≈ 20                sparse, brighter
==========================  ===========  ===========  ==================  ====================

Sources: gelatin phantoms have c ≈ 1520–1650 m/s, ρ ≈ 1.03–1.05 g/cm³ and α ≈ 0.1–0.6
dB/cm/MHz, raised by added scatterers such as paper pulp or graphite (Culjat et al. 2010,
"A review of tissue substitutes for ultrasound imaging", Ultrasound Med. Biol. 36:861; Jiang
et al. 2021 used gelatin + paper pulp for robotic-ultrasound vertebra phantoms). Cortical bone
has ρ ≈ 1.9–2.0 g/cm³, c ≈ 3000–4000 m/s, Z ≈ 6–8 MRayl and α ≈ 14–22 dB/cm/MHz (Duck 1990,
"Physical Properties of Tissue", and Culjat et al. 2010). The intensity reflection coefficient
of a gel/bone interface is then ((7.4 − 1.58)/(7.4 + 1.58))² ≈ 0.42, so 58 % is transmitted, and
at 5 MHz bone attenuates by ≈ 10 dB per mm one way: everything below the first bone surface is
in acoustic shadow, as in vivo.

Scatterer amplitudes are relative to the amplitude √R of a normally incident gel/bone echo, so
the backscatter of the gel sits ≈ 25–30 dB below the bone echo after envelope detection, the
usual contrast of a bone surface over soft tissue in B-mode.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ultron.errors import argument_error

#: Amplitude ratios in dB: A = A₀·10^(−dB/20).
_DB_PER_DECADE = 20.0


@dataclass(frozen=True)
class Tissue:
    """Acoustic parameters of one medium.

    ``impedance_mrayl`` Z = ρc; ``attenuation_db_cm_mhz`` the (linear-in-frequency) attenuation
    coefficient; ``scatterer_density_per_mm3`` the number density of sub-resolution
    scatterers; ``scatterer_amplitude`` the RMS amplitude of one scatterer relative to a
    normally incident gel/bone echo.
    """

    name: str
    speed_m_s: float
    density_g_cm3: float
    attenuation_db_cm_mhz: float
    scatterer_density_per_mm3: float
    scatterer_amplitude: float

    def __post_init__(self) -> None:
        for field_name in (
            "speed_m_s",
            "density_g_cm3",
            "attenuation_db_cm_mhz",
            "scatterer_density_per_mm3",
            "scatterer_amplitude",
        ):
            value = getattr(self, field_name)
            if not (math.isfinite(value) and value >= 0):
                raise argument_error(field_name, f"expected a finite number ≥ 0, got {value}")
        if self.speed_m_s <= 0 or self.density_g_cm3 <= 0:
            raise argument_error(self.name, "speed and density must be positive")

    @property
    def impedance_mrayl(self) -> float:
        """Z = ρ·c in MRayl (10⁶ kg m⁻² s⁻¹)."""
        return self.density_g_cm3 * 1e3 * self.speed_m_s / 1e6

    def attenuation_db_per_mm(self, frequency_mhz: float) -> float:
        """One-way attenuation at ``frequency_mhz``: α_dB/mm = α₀·f/10 (α₀ in dB/cm/MHz)."""
        return self.attenuation_db_cm_mhz * frequency_mhz / 10.0


#: Gelatin with paper pulp (the paper's phantom medium).
GEL_PULP = Tissue(
    name="gelatin + paper pulp",
    speed_m_s=1540.0,
    density_g_cm3=1.025,
    attenuation_db_cm_mhz=0.5,
    scatterer_density_per_mm3=20.0,
    scatterer_amplitude=0.045,
)

#: Cortical bone.
CORTICAL_BONE = Tissue(
    name="cortical bone",
    speed_m_s=3600.0,
    density_g_cm3=2.05,
    attenuation_db_cm_mhz=20.0,
    scatterer_density_per_mm3=4.0,
    scatterer_amplitude=0.08,
)


def intensity_reflection(z1_mrayl: float, z2_mrayl: float) -> float:
    """Intensity reflection coefficient at normal incidence: R = ((Z₂ − Z₁)/(Z₂ + Z₁))²."""
    if z1_mrayl <= 0 or z2_mrayl <= 0:
        raise argument_error(
            "impedance", f"expected positive impedances, got {z1_mrayl}, {z2_mrayl}"
        )
    return ((z2_mrayl - z1_mrayl) / (z2_mrayl + z1_mrayl)) ** 2


def incidence_factor(
    cos_incidence: torch.Tensor, specular_exponent: float, diffuse_fraction: float
) -> torch.Tensor:
    """Share of a reflection that returns to the transducer at incidence angle θ:

    g(θ) = (1 − d)·cos^n θ + d·cos θ,

    a specular lobe (exponent n, smooth surface) plus a Lambertian part d from surface roughness
    (as in ray-based ultrasound simulators, e.g. Burger et al. 2013, IEEE TMI 32:609). g(0) = 1.
    """
    c = cos_incidence.abs().clamp(0.0, 1.0)
    return (1.0 - diffuse_fraction) * c**specular_exponent + diffuse_fraction * c


def amplitude_from_db(loss_db: torch.Tensor) -> torch.Tensor:
    """Amplitude factor of a loss in dB: a = 10^(−dB/20) = exp(−dB·ln10/20)."""
    return torch.exp(loss_db * (-math.log(10.0) / _DB_PER_DECADE))
