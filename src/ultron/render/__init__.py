"""Ultra-NeRF scanline rendering: pure physics functions and a thin field renderer."""

from ultron.render.physics import (
    apply_psf,
    attenuation_transmission,
    bmode_intensity,
    convolution_matrix,
    exclusive_cumsum,
    gaussian_kernel_1d,
    gaussian_psf,
    log_amplification,
    reflection_transmission,
    relaxed_bernoulli_mean,
    sample_scatterers,
    separable_filter,
    total_transmission,
)
from ultron.render.renderer import (
    RenderConfig,
    RenderedFrames,
    pixel_points_mm,
    render_field,
    render_properties,
)

__all__ = [
    "RenderConfig",
    "RenderedFrames",
    "apply_psf",
    "attenuation_transmission",
    "bmode_intensity",
    "convolution_matrix",
    "exclusive_cumsum",
    "gaussian_kernel_1d",
    "gaussian_psf",
    "log_amplification",
    "pixel_points_mm",
    "reflection_transmission",
    "relaxed_bernoulli_mean",
    "render_field",
    "render_properties",
    "sample_scatterers",
    "separable_filter",
    "total_transmission",
]
