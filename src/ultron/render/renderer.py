"""Thin renderer: probe pixels → field → θ → Ultra-NeRF B-mode, in image layout (N, H, C).

Frames are rendered scanline by scanline at the image's own rows (N_samples = H, step
Δ = depth_mm / H, METHOD.md §1); columns may be a subset (adjacent-scanline patches in
training) or all W scanlines.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

import torch

from ultron.data.dataset import ProbeGeometry
from ultron.data.geometry import UnitCube, apply_pose, as_pose_tensor, probe_points_mm
from ultron.device import module_device
from ultron.errors import argument_error, config_from_dict
from ultron.fields.base import AcousticField
from ultron.fields.properties import AcousticProperties
from ultron.render import physics


@dataclass(frozen=True)
class RenderConfig:
    """Scatterer distribution and PSF of the renderer (Ultra-NeRF's values by default).

    The PSF is given in pixels of the rendered image, as in Ultra-NeRF (7 × 7, σ = 1 px).
    :meth:`rescaled` converts σ to another pixel grid of the same probe, keeping its size in mm.
    """

    scatter_probability: float = physics.DEFAULT_SCATTER_PROBABILITY
    scatter_temperature: float = physics.DEFAULT_SCATTER_TEMPERATURE
    psf_size: int = physics.DEFAULT_PSF_SIZE
    psf_sigma_axial_px: float = physics.DEFAULT_PSF_SIGMA_PX
    psf_sigma_lateral_px: float = physics.DEFAULT_PSF_SIGMA_PX

    def __post_init__(self) -> None:
        if not 0 < self.scatter_probability < 1:
            raise argument_error("scatter_probability", "expected a value inside (0, 1)")
        if not self.scatter_temperature > 0:
            raise argument_error("scatter_temperature", "expected > 0")
        physics.gaussian_psf(self.psf_size, self.psf_sigma_axial_px, self.psf_sigma_lateral_px)

    def kernels(
        self, dtype: torch.dtype = torch.float32, device: torch.device | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(axial, lateral) 1D PSF kernels (built on the CPU, then moved to ``device``)."""
        return (
            physics.gaussian_kernel_1d(self.psf_size, self.psf_sigma_axial_px, dtype).to(device),
            physics.gaussian_kernel_1d(self.psf_size, self.psf_sigma_lateral_px, dtype).to(device),
        )

    def rescaled(self, native: ProbeGeometry, target: ProbeGeometry) -> RenderConfig:
        """This config with σ (given in ``native`` pixels) expressed in ``target`` pixels.

            σ_target = σ_native · spacing_native / spacing_target   (per axis)

        so the PSF keeps its physical size when frames are fitted at a reduced resolution.
        """
        axial = native.axial_spacing_mm / target.axial_spacing_mm
        lateral = native.lateral_spacing_mm / target.lateral_spacing_mm
        return replace(
            self,
            psf_sigma_axial_px=self.psf_sigma_axial_px * axial,
            psf_sigma_lateral_px=self.psf_sigma_lateral_px * lateral,
        )

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> RenderConfig:
        return config_from_dict(cls, data, "render config")


@dataclass(frozen=True)
class RenderedFrames:
    """A rendering, every tensor (…, H, C): B-mode I = b + r', its terms, T and θ."""

    intensity: torch.Tensor
    speckle: torch.Tensor
    reflection: torch.Tensor
    transmission: torch.Tensor
    properties: AcousticProperties


def pixel_points_mm(
    probe_to_world: torch.Tensor, probe: ProbeGeometry, cols: torch.Tensor | None = None
) -> torch.Tensor:
    """World points (N, H, C, 3) of the image pixels of the given columns, float64.

    ``cols`` is None (all W columns), a (C,) tensor shared by all frames, or (N, C) per frame.
    Rows are all H samples of each scanline, in depth order.
    """
    poses = as_pose_tensor(probe_to_world).to(torch.float64)
    n = poses.shape[0]
    rows = torch.arange(probe.height_px, dtype=torch.float64, device=poses.device)
    if cols is None:
        cols = torch.arange(probe.width_px, dtype=torch.float64)
    cols = torch.as_tensor(cols, dtype=torch.float64, device=poses.device)
    if cols.ndim == 1:
        points = probe_points_mm(rows[:, None], cols[None, :], probe)  # (H, C, 3)
        points = points.unsqueeze(0).expand(n, *points.shape)
    elif cols.ndim == 2 and cols.shape[0] == n:
        points = probe_points_mm(rows[None, :, None], cols[:, None, :], probe)  # (N, H, C, 3)
    else:
        raise argument_error("cols", f"expected (C,) or (N={n}, C), got {tuple(cols.shape)}")
    return apply_pose(poses, points)


def render_properties(
    properties: AcousticProperties,
    step_mm: float,
    config: RenderConfig,
    generator: torch.Generator | None = None,
    expected: bool = False,
    *,
    scatterers: torch.Tensor | None = None,
    kernels: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> RenderedFrames:
    """Render θ laid out as (…, H, C) scanlines into B-mode (Ultra-NeRF, METHOD.md §2).

    T = A·R (exclusive), S ~ relaxed Bernoulli(p, τ) drawn from ``generator`` without gradient
    (p = the learned density when present, then reparameterised), or its expectation E[S]
    when ``expected``; I = T·(G ∗ (S·φ)) + log(1 + π T β)/log(1 + π). Everything is computed
    on θ's device; the draws come from ``generator``'s (a CPU generator draws the same S on
    every device, :func:`~ultron.render.physics.sample_scatterers`).

    Given ``scatterers`` (S, broadcastable to θ) and ``kernels`` (the PSF's (axial, lateral)
    1D kernels on θ's device, :meth:`RenderConfig.kernels`), nothing is drawn, built or
    copied from the host: the rendering is device work alone (a fit's CUDA graph captures it).
    """
    if scatterers is not None or kernels is not None:
        if scatterers is None or kernels is None:
            raise argument_error("scatterers", "expected scatterers and kernels together")
        return _render_with(properties, step_mm, scatterers, kernels)
    if not expected and generator is None:
        raise argument_error("generator", "sampling scatterers needs a torch.Generator")
    dtype, device = properties.scattering.dtype, properties.scattering.device
    probability: torch.Tensor | float = (
        properties.density if properties.density is not None else config.scatter_probability
    )
    if expected:
        scatterers = physics.relaxed_bernoulli_mean(probability, config.scatter_temperature)
        scatterers = torch.as_tensor(scatterers, dtype=dtype, device=device)
    else:
        scatterers = physics.sample_scatterers(
            probability,
            tuple(properties.shape),
            generator,
            config.scatter_temperature,
            dtype,
            device,
        )
        if properties.density is None:
            scatterers = scatterers.detach()
    return _render_with(properties, step_mm, scatterers, config.kernels(dtype, device))


def _render_with(
    properties: AcousticProperties,
    step_mm: float,
    scatterers: torch.Tensor,
    kernels: tuple[torch.Tensor, torch.Tensor],
) -> RenderedFrames:
    """:func:`render_properties` with the scatterers and the PSF's kernels given."""
    transmission = physics.total_transmission(
        properties.attenuation, properties.reflection, step_mm
    )
    intensity, speckle, reflection = physics.bmode_intensity(
        transmission, properties.reflection, properties.scattering, scatterers, *kernels
    )
    return RenderedFrames(intensity, speckle, reflection, transmission, properties)


def render_field(
    field: AcousticField,
    unit_cube: UnitCube,
    probe: ProbeGeometry,
    probe_to_world: torch.Tensor,
    config: RenderConfig,
    cols: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
    expected: bool = False,
    hold_scattering: float | None = None,
) -> RenderedFrames:
    """Query ``field`` at the pixels of ``cols`` (see :func:`pixel_points_mm`) and render.

    The pixel geometry is computed in float64 on the poses' device (the CPU, as a rule: MPS has
    no float64) and its unit-cube coordinates are moved, as float32, to the field's device,
    where the rendering happens; the result stays there.
    ``hold_scattering``: render with φ replaced by this constant (a fit's curriculum: the
    image's dark regions can then only be explained by a loss of transmission).
    Differentiable w.r.t. the field; wrap in ``torch.no_grad()`` for inference.
    """
    points_mm = pixel_points_mm(probe_to_world, probe, cols)
    unit = unit_cube.to_unit(points_mm, dtype=torch.float32).to(module_device(field))
    properties = field(unit)
    if hold_scattering is not None:
        held = torch.full_like(properties.scattering, hold_scattering)
        properties = replace(properties, scattering=held)
    return render_properties(properties, probe.axial_spacing_mm, config, generator, expected)
