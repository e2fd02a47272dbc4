"""Physics-based B-mode simulation of a linear probe over an SDF phantom (vectorised, CPU).

Per frame, every scanline is sampled at the image rows (step Δ = depth/H) on ``E`` elevation
planes (offsets across the beam thickness). With d the signed distance of the phantom and
occupancy o = clamp(½ − d/Δ, 0, 1), along each scanline:

* round-trip attenuation (dB, exclusive of the sample itself)
  A_r = 2Δ·Σ_{k<r} [α_gel + o_k(α_bone − α_gel)]·f,   amplitude factor 10^(−A_r/20);
* interfaces where d changes sign between rows r−1 and r, located at the linear zero crossing
  (sub-pixel), with intensity reflection R = ((Z_b − Z_g)/(Z_b + Z_g))² and incidence factor
  g(θ) = (1 − d_f)cosⁿθ + d_f·cosθ from the SDF normal; each crossed interface transmits 1 − R
  each way (amplitude factor 1 − R round trip);
* specular echo amplitude √(R·g(θ))·(1 − R)^{m}·10^(−A/20) at the crossing (m interfaces
  above it), deposited at its sub-pixel depth;
* speckle: the world-anchored complex scatterer field (``speckle.py``) of the local tissue,
  times the transmission (1 − R)^{m}·10^(−A_r/20) to that sample — so bone casts an acoustic
  shadow (bone attenuates ≈ 10 dB/mm one way at 5 MHz);
* elevation: the planes are summed coherently with a Gaussian beam profile of depth-dependent
  width σ_el(z) = σ₀·√(1 + ((z − z_f)/z_R)²) (fixed lens focus);
* PSF: an axial Gaussian (pulse length) and a lateral Gaussian whose width grows away from the
  transmit focus in the same way — a depth-dependent PSF applied as exact per-row matrices;
* receiver noise (complex Gaussian), time-gain compensation exp of +2α_gel·f·z (the gel's
  round-trip loss, so gel brightness is flat with depth while shadows stay dark), envelope
  |·|, log compression to a dynamic range, uint8.

True transmission (ground truth for diagnosis, ``SimulatedFrames.transmission``, saved as
``<sweep>/transmission.npy``): on the centre elevation plane, per pixel, exclusive (row 0 = 1)
and as the displayed image sees it, i.e. with the TGC's compensation of the gel taken out,

    T_r = clip((1 − R)^{m_r} · 10^(−(A_r − A_gel,r)/20), 0, 1),   A_gel,r = c_TGC·2α_gel·f·z_r,

from τ_r = (1 − R)^{m_r}·10^(−A_r/20) above (the round-trip amplitude, i.e. the one-way
intensity transmission) times the TGC amplitude gain 10^(A_gel,r/20) (c_TGC =
``tgc_compensation``): 1 in gel above the bone, (1 − R)·10^(−bone loss/20) ≈ 0 in its shadow.
It comes from the same (true) poses and the same chunk computation as the images.

Display scale: a normally incident, unattenuated gel/bone echo (amplitude √R) displays at
``gain_db`` below full scale; ``dynamic_range_db`` below that is black.

Simplifications: straight rays at an assumed 1540 m/s (no refraction, no speed-of-sound
distortion — everything behind the first bone surface is shadowed anyway), single reflections
(no reverberation or multiple-reflection tails), real-valued specular echoes added to complex
speckle, and one incidence factor for both reflection and transmission.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ultron.data.dataset import ProbeGeometry
from ultron.data.geometry import as_pose_tensor, frame_pixels_world
from ultron.errors import argument_error
from ultron.phantom.scanline import (
    Crossings,
    deposit_echoes,
    echo_amplitudes,
    interface_crossings,
    round_trip_attenuation_db,
    transmission_amplitude,
)
from ultron.phantom.speckle import ScattererField
from ultron.phantom.tissue import (
    CORTICAL_BONE,
    GEL_PULP,
    Tissue,
    amplitude_from_db,
    intensity_reflection,
)
from ultron.phantom.volume import SdfVolume


@dataclass(frozen=True)
class BModeConfig:
    """Every parameter of the B-mode simulator (defaults: a 5 MHz linear probe on gel + bone)."""

    frequency_mhz: float = 5.0
    gel: Tissue = GEL_PULP
    bone: Tissue = CORTICAL_BONE
    specular_exponent: float = 4.0
    diffuse_fraction: float = 0.25
    axial_psf_sigma_mm: float = 0.3
    lateral_psf_sigma_mm: float = 0.45  # at the transmit focus
    lateral_focus_mm: float = 45.0
    lateral_rayleigh_mm: float = 20.0
    elevation_sigma_mm: float = 0.7  # at the lens focus
    elevation_focus_mm: float = 30.0
    elevation_rayleigh_mm: float = 20.0
    elevation_planes: int = 3
    elevation_span_mm: float = 1.0  # outermost plane offset
    speckle_voxel_mm: float = 0.5
    tgc_compensation: float = 1.0  # share of the gel's round-trip attenuation compensated
    noise_db: float = -80.0  # receiver noise RMS re a normal gel/bone echo, before TGC
    gain_db: float = -3.0
    dynamic_range_db: float = 50.0
    frames_per_chunk: int = 16

    def __post_init__(self) -> None:
        positive = (
            "frequency_mhz",
            "specular_exponent",
            "axial_psf_sigma_mm",
            "lateral_psf_sigma_mm",
            "lateral_rayleigh_mm",
            "elevation_sigma_mm",
            "elevation_rayleigh_mm",
            "speckle_voxel_mm",
            "dynamic_range_db",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise argument_error(name, f"expected a positive number, got {value}")
        for name in ("diffuse_fraction", "tgc_compensation"):
            value = getattr(self, name)
            if not (0.0 <= value <= 1.0):
                raise argument_error(name, f"expected a number in [0, 1], got {value}")
        for name in ("elevation_planes", "frames_per_chunk"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise argument_error(name, f"expected a positive integer, got {value!r}")
        if not (math.isfinite(self.elevation_span_mm) and self.elevation_span_mm >= 0):
            raise argument_error("elevation_span_mm", f"expected ≥ 0, got {self.elevation_span_mm}")

    @property
    def reflection(self) -> float:
        """Intensity reflection coefficient of the gel/bone interface."""
        return intensity_reflection(self.gel.impedance_mrayl, self.bone.impedance_mrayl)

    def elevation_offsets_mm(self) -> torch.Tensor:
        """Offsets of the elevation planes along probe +z, mm (a single plane: 0)."""
        if self.elevation_planes == 1:
            return torch.zeros(1, dtype=torch.float64)
        span = self.elevation_span_mm
        return torch.linspace(-span, span, self.elevation_planes, dtype=torch.float64)


@dataclass
class BoneInterfaces:
    """Gel/bone interfaces met by the centre-plane scanlines of simulated frames.

    Each is (N, H, W), indexed at the row r of the first sample past the interface (row 0 never
    holds one): ``entering`` gel→bone, ``exiting`` bone→gel, ``depth_mm`` the sub-pixel depth
    of the crossing (NaN where none) and ``echo_db`` its displayed echo relative to a normally
    incident, unattenuated one (after TGC; −inf where none).
    """

    entering: torch.Tensor
    exiting: torch.Tensor
    depth_mm: torch.Tensor
    echo_db: torch.Tensor


@dataclass
class SimulatedFrames:
    """B-mode images (N, H, W) uint8, the centre-plane bone interfaces and the centre-plane
    true transmission (N, H, W) float32 in [0, 1] (module doc)."""

    images: torch.Tensor
    interfaces: BoneInterfaces
    transmission: torch.Tensor


def gaussian_beam_sigma(
    depth_mm: torch.Tensor, sigma_focus_mm: float, focus_mm: float, rayleigh_mm: float
) -> torch.Tensor:
    """Gaussian-beam width σ(z) = σ₀·√(1 + ((z − z_f)/z_R)²)."""
    return sigma_focus_mm * torch.sqrt(1.0 + ((depth_mm - focus_mm) / rayleigh_mm) ** 2)


def axial_psf_matrix(probe: ProbeGeometry, sigma_mm: float) -> torch.Tensor:
    """(H, H) matrix K with K[r, s] = exp(−((r − s)Δ)²/(2σ²)): peak 1, so a point echo of
    amplitude a keeps amplitude a at its row."""
    depth = torch.arange(probe.height_px, dtype=torch.float32) * probe.axial_spacing_mm
    return torch.exp(-((depth[:, None] - depth[None, :]) ** 2) / (2 * sigma_mm**2))


def lateral_psf_matrices(probe: ProbeGeometry, config: BModeConfig) -> torch.Tensor:
    """(H, W, W) per-row lateral blur, Gaussian of width σ_lat(z_r), rows normalised to sum 1
    (a laterally extended reflector keeps its amplitude)."""
    depth = torch.arange(probe.height_px, dtype=torch.float64) * probe.axial_spacing_mm
    sigma = gaussian_beam_sigma(
        depth, config.lateral_psf_sigma_mm, config.lateral_focus_mm, config.lateral_rayleigh_mm
    )
    x = torch.arange(probe.width_px, dtype=torch.float64) * probe.lateral_spacing_mm
    diff2 = (x[:, None] - x[None, :]) ** 2
    kernel = torch.exp(-diff2[None] / (2 * sigma[:, None, None] ** 2))
    return (kernel / kernel.sum(dim=1, keepdim=True)).to(torch.float32)


def elevation_weights(probe: ProbeGeometry, config: BModeConfig) -> torch.Tensor:
    """(E, H) weights of the elevation planes per row: exp(−e²/(2σ_el(z)²)), summing to 1."""
    depth = torch.arange(probe.height_px, dtype=torch.float64) * probe.axial_spacing_mm
    sigma = gaussian_beam_sigma(
        depth, config.elevation_sigma_mm, config.elevation_focus_mm, config.elevation_rayleigh_mm
    )
    offsets = config.elevation_offsets_mm()
    weights = torch.exp(-(offsets[:, None] ** 2) / (2 * sigma[None, :] ** 2))
    return (weights / weights.sum(dim=0, keepdim=True)).to(torch.float32)


def log_compress(envelope: torch.Tensor, reference: float, config: BModeConfig) -> torch.Tensor:
    """uint8 = round(255·clip(1 + (20·log10(env/ref) + gain_db)/DR, 0, 1))."""
    db = 20.0 * torch.log10(envelope.clamp(min=1e-12) / reference) + config.gain_db
    level = (1.0 + db / config.dynamic_range_db).clamp(0.0, 1.0)
    return torch.round(255.0 * level).to(torch.uint8)


def simulate_frames(
    probe_to_world: torch.Tensor,
    probe: ProbeGeometry,
    volume: SdfVolume,
    scatterers: ScattererField,
    config: BModeConfig,
    generator: torch.Generator,
) -> SimulatedFrames:
    """Simulate B-mode frames at the TRUE poses ``probe_to_world`` (N, 4, 4), in chunks."""
    poses = as_pose_tensor(probe_to_world).to(torch.float64)
    if poses.shape[0] == 0:
        raise argument_error("probe_to_world", "expected at least one pose")
    constants = _FrameConstants.build(probe, config)
    images, parts, transmissions = [], [], []
    for start in range(0, poses.shape[0], config.frames_per_chunk):
        chunk = poses[start : start + config.frames_per_chunk]
        image, interfaces, transmission = _simulate_chunk(
            chunk, probe, volume, scatterers, config, constants, generator
        )
        images.append(image)
        parts.append(interfaces)
        transmissions.append(transmission)
    merged = BoneInterfaces(
        *(torch.cat([getattr(p, name) for p in parts]) for name in BoneInterfaces.__annotations__)
    )
    return SimulatedFrames(torch.cat(images), merged, torch.cat(transmissions))


@dataclass(frozen=True)
class _FrameConstants:
    depth_mm: torch.Tensor  # (H,)
    axial: torch.Tensor  # (H, H)
    lateral: torch.Tensor  # (H, W, W)
    elevation: torch.Tensor  # (E, H)
    tgc: torch.Tensor  # (H,) amplitude gain

    @classmethod
    def build(cls, probe: ProbeGeometry, config: BModeConfig) -> _FrameConstants:
        depth = torch.arange(probe.height_px, dtype=torch.float32) * probe.axial_spacing_mm
        gel_db_mm = config.gel.attenuation_db_per_mm(config.frequency_mhz)
        tgc_db = config.tgc_compensation * 2.0 * gel_db_mm * depth
        return cls(
            depth,
            axial_psf_matrix(probe, config.axial_psf_sigma_mm),
            lateral_psf_matrices(probe, config),
            elevation_weights(probe, config),
            amplitude_from_db(-tgc_db),
        )


def _incidence_cosines(
    crossings: Crossings, points: torch.Tensor, poses: torch.Tensor, volume: SdfVolume
) -> torch.Tensor:
    """|cos| of the incidence angle between the beam and the SDF normal at each interface
    crossing (computed only there; 0 elsewhere), shaped like ``crossings.fraction``."""
    cos_incidence = torch.zeros_like(crossings.fraction)
    index = crossings.any.nonzero(as_tuple=True)
    if index[0].numel():
        f = crossings.fraction[index][:, None]
        p0 = points[index[0], index[1], index[2], index[3]]
        p1 = points[index[0], index[1], index[2] + 1, index[3]]
        normals = volume.normals(p0 + f * (p1 - p0))
        beam = poses[index[0], :3, 1]
        cos_incidence[index] = (normals * beam).sum(-1).abs().to(torch.float32)
    return cos_incidence


def _centre_plane_interfaces(
    crossings: Crossings,
    echo: torch.Tensor,
    config: BModeConfig,
    step: float,
    gel_db: float,
    centre_plane: int,
) -> BoneInterfaces:
    """The bone interfaces of the centre elevation plane, per pixel: entering / exiting, depth
    (mm) and the echo (dB re. the reflection, with the TGC at its depth)."""
    n, rows_minus_one, width = crossings.entering[:, centre_plane].shape
    reflection = config.reflection
    pad = torch.zeros((n, 1, width), dtype=torch.bool)
    enter_c = torch.cat([pad, crossings.entering[:, centre_plane]], 1)
    exit_c = torch.cat([pad, crossings.exiting[:, centre_plane]], 1)
    rows = torch.arange(1, rows_minus_one + 1, dtype=torch.float32)[None, :, None]
    depth_c = (rows - 1.0 + crossings.fraction[:, centre_plane]) * step
    depth_c = torch.cat([pad.to(torch.float32), depth_c], 1)
    tgc_cross = amplitude_from_db(-config.tgc_compensation * 2.0 * gel_db * depth_c)
    echo_c = torch.cat([pad.to(torch.float32), echo[:, centre_plane]], 1) * tgc_cross
    has = enter_c | exit_c
    return BoneInterfaces(
        entering=enter_c,
        exiting=exit_c,
        depth_mm=torch.where(has, depth_c, float("nan")),
        echo_db=torch.where(
            has, 20.0 * torch.log10(echo_c.clamp(min=1e-30) / math.sqrt(reflection)), -math.inf
        ),
    )


def _simulate_chunk(
    poses: torch.Tensor,
    probe: ProbeGeometry,
    volume: SdfVolume,
    scatterers: ScattererField,
    config: BModeConfig,
    constants: _FrameConstants,
    generator: torch.Generator,
) -> tuple[torch.Tensor, BoneInterfaces, torch.Tensor]:
    step = probe.axial_spacing_mm
    offsets = config.elevation_offsets_mm()
    centre = frame_pixels_world(poses, probe)  # (n, H, W, 3)
    elevation_axis = poses[:, :3, 2]
    points = (
        centre[:, None]
        + offsets[None, :, None, None, None] * elevation_axis[:, None, None, None, :]
    ).to(torch.float32)  # (n, E, H, W, 3)
    sdf = volume.sample(points)  # (n, E, H, W)
    occupancy = (0.5 - sdf / step).clamp(0.0, 1.0)
    gel_db = config.gel.attenuation_db_per_mm(config.frequency_mhz)
    bone_db = config.bone.attenuation_db_per_mm(config.frequency_mhz)
    attenuation_db = round_trip_attenuation_db(occupancy, step, gel_db, bone_db)
    crossings = interface_crossings(sdf)

    cos_incidence = _incidence_cosines(crossings, points, poses, volume)
    reflection = config.reflection
    echo = echo_amplitudes(
        crossings,
        cos_incidence,
        attenuation_db,
        reflection,
        config.specular_exponent,
        config.diffuse_fraction,
    )  # (n, E, H−1, W)

    # Speckle of the local tissue, attenuated and shadowed, plus the specular echoes.
    transmission = transmission_amplitude(crossings, attenuation_db, reflection)
    gel_field, bone_field = scatterers.sample(points)  # (n, E, H, W, 2)
    occ = occupancy[..., None]
    signal = (gel_field * (1.0 - occ) + bone_field * occ) * transmission[..., None]
    signal[..., 0] += deposit_echoes(echo, crossings.fraction)

    # Elevation beam profile, then the depth-dependent PSF.
    rf = torch.einsum("eh,nehwc->nhwc", constants.elevation, signal)
    rf = torch.einsum("hk,nkwc->nhwc", constants.axial, rf)
    rf = torch.einsum("nhwc,hwv->nhvc", rf, constants.lateral)
    noise_sigma = 10.0 ** (config.noise_db / 20.0) / math.sqrt(2.0)
    rf = rf + noise_sigma * torch.randn(rf.shape, generator=generator, dtype=rf.dtype)
    envelope = rf.norm(dim=-1) * constants.tgc[None, :, None]
    images = log_compress(envelope, math.sqrt(reflection), config)

    centre_plane = config.elevation_planes // 2
    true_transmission = (transmission[:, centre_plane] * constants.tgc[None, :, None]).clamp(0, 1)
    interfaces = _centre_plane_interfaces(crossings, echo, config, step, gel_db, centre_plane)
    return images, interfaces, true_transmission
