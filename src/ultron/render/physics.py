"""Ultra-NeRF scanline physics as pure functions (METHOD.md §2).

Every function works on tensors laid out as images, ``(..., H, W)``: dimension −2 runs along the
beam (depth samples n = 0..H−1, ordered, spaced by the physical step Δ in mm) and dimension −1
across adjacent scanlines (lateral). No function keeps state; random draws take a
``torch.Generator``.

Where the original code and METHOD.md differ we follow METHOD.md: transmissions are *exclusive*
(the sample itself is not included, so T₀ = 1), the reflection transmission is computed as the
exponential of a cumulative log sum, and the log amplification divides by log(1 + π) so that the
reflection term stays in [0, 1].
"""

from __future__ import annotations

import math

import torch

from ultron.errors import argument_error

#: Probability that a sample holds a scatterer (Ultra-NeRF's Bernoulli p).
DEFAULT_SCATTER_PROBABILITY = 0.75
#: Temperature of the relaxed Bernoulli (binary Concrete) scatterer distribution.
DEFAULT_SCATTER_TEMPERATURE = 0.1
#: Side of the PSF kernel in pixels, per axis (7 × 7, as in Ultra-NeRF).
DEFAULT_PSF_SIZE = 7
#: Standard deviation of the Gaussian PSF in pixels, per axis (Ultra-NeRF: variance 1).
DEFAULT_PSF_SIGMA_PX = 1.0

_LOG_EPS = 1e-7


def _check_image_like(name: str, tensor: torch.Tensor) -> None:
    if not torch.is_tensor(tensor):
        raise argument_error(name, f"expected a torch tensor, got {type(tensor).__name__}")
    if tensor.ndim < 2:
        raise argument_error(name, f"expected shape (..., H, W), got {tuple(tensor.shape)}")


def exclusive_cumsum(values: torch.Tensor, dim: int = -2) -> torch.Tensor:
    """Exclusive cumulative sum along ``dim``: s_n = Σ_{k<n} v_k (so s_0 = 0)."""
    total = torch.cumsum(values, dim=dim)
    return total - values


def attenuation_transmission(alpha_per_mm: torch.Tensor, step_mm: float) -> torch.Tensor:
    """Attenuation transmission along each scanline (dimension −2).

        A_n = exp(−Σ_{k<n} α_k Δ)

    ``alpha_per_mm`` (…, H, W) is the attenuation coefficient α ≥ 0 in 1/mm and ``step_mm``
    the physical sample spacing Δ in mm. Exclusive: A_0 = 1. A constant α gives A = exp(−α d)
    at depth d = nΔ.
    """
    _check_image_like("alpha_per_mm", alpha_per_mm)
    if not (isinstance(step_mm, int | float) and math.isfinite(step_mm) and step_mm > 0):
        raise argument_error("step_mm", f"expected a positive step in mm, got {step_mm!r}")
    return torch.exp(-exclusive_cumsum(alpha_per_mm * step_mm, dim=-2))


def reflection_transmission(beta: torch.Tensor) -> torch.Tensor:
    """Reflection transmission along each scanline (dimension −2).

        R_n = Π_{k<n} (1 − β_k) = exp(Σ_{k<n} log(1 − β_k))

    ``beta`` (…, H, W) is the reflection coefficient β ∈ (0, 1) per sample. Exclusive: R_0 = 1,
    and a single reflector β at sample m leaves R = 1 up to m and 1 − β after it.
    """
    _check_image_like("beta", beta)
    log_pass = torch.log(torch.clamp(1.0 - beta, min=_LOG_EPS))
    return torch.exp(exclusive_cumsum(log_pass, dim=-2))


def total_transmission(
    alpha_per_mm: torch.Tensor, beta: torch.Tensor, step_mm: float
) -> torch.Tensor:
    """Ultra-NeRF's transmittance T_n = A_n · R_n (exclusive, T_0 = 1).

    Computed as one exponential of the summed log terms:
    T_n = exp(Σ_{k<n} [log(1 − β_k) − α_k Δ]).
    """
    _check_image_like("alpha_per_mm", alpha_per_mm)
    _check_image_like("beta", beta)
    if not (isinstance(step_mm, int | float) and math.isfinite(step_mm) and step_mm > 0):
        raise argument_error("step_mm", f"expected a positive step in mm, got {step_mm!r}")
    log_pass = torch.log(torch.clamp(1.0 - beta, min=_LOG_EPS)) - alpha_per_mm * step_mm
    return torch.exp(exclusive_cumsum(log_pass, dim=-2))


def sample_scatterers(
    probability: torch.Tensor | float,
    shape: tuple[int, ...],
    generator: torch.Generator | None,
    temperature: float = DEFAULT_SCATTER_TEMPERATURE,
    dtype: torch.dtype = torch.float32,
    device: torch.device | None = None,
) -> torch.Tensor:
    """Draw relaxed-Bernoulli (binary Concrete) scatterer indicators S ∈ (0, 1).

        L = log U − log(1 − U),  U ~ Uniform(0, 1)
        S = sigmoid((logit p + L) / τ)

    ``probability`` p is a float or a tensor broadcastable to ``shape``; gradients flow to a
    tensor p (a learned density) through the reparameterisation, never to the noise. The noise
    comes from ``generator`` (pass one for reproducible draws) on the generator's device and is
    then moved to ``device`` (default: p's), so a CPU generator gives the same draws on every
    device.
    """
    if not temperature > 0:
        raise argument_error("temperature", f"expected > 0, got {temperature}")
    if torch.is_tensor(probability):  # (a check that synchronises an accelerator)
        inside = bool(((probability > 0) & (probability < 1)).all())
    else:
        inside = 0 < float(probability) < 1
    if not inside:
        raise argument_error("probability", "expected values strictly inside (0, 1)")
    p = torch.as_tensor(probability, dtype=dtype, device=device)
    uniform = scatterer_noise(shape, generator, dtype)
    return scatterers_from_noise(p, uniform.to(p.device), temperature)


def scatterer_noise(
    shape: tuple[int, ...], generator: torch.Generator | None, dtype: torch.dtype = torch.float32
) -> torch.Tensor:
    """The uniform noise U ~ Uniform(0, 1) of :func:`sample_scatterers`, drawn from
    ``generator`` on the generator's device (one draw of ``shape``)."""
    return torch.rand(shape, generator=generator, dtype=dtype, device=_device_of(generator))


def scatterers_from_noise(
    probability: torch.Tensor, uniform: torch.Tensor, temperature: float
) -> torch.Tensor:
    """Scatterer indicators from given noise (the deterministic half of
    :func:`sample_scatterers`, no check of p and no synchronisation: it can be captured in a
    CUDA graph):

        U' = clamp(U, 10⁻⁶, 1 − 10⁻⁶),  S = sigmoid((logit p + log U' − log(1 − U')) / τ)
    """
    uniform = uniform.clamp(1e-6, 1 - 1e-6)
    logistic = torch.log(uniform) - torch.log1p(-uniform)
    return torch.sigmoid((torch.logit(probability) + logistic) / temperature)


def _device_of(generator: torch.Generator | None) -> torch.device | None:
    return None if generator is None else generator.device


def relaxed_bernoulli_mean(
    probability: torch.Tensor | float,
    temperature: float = DEFAULT_SCATTER_TEMPERATURE,
    n_quadrature: int = 256,
) -> torch.Tensor:
    """Expected value of a relaxed-Bernoulli draw, E[S] = ∫₀¹ sigmoid((logit p + logit u)/τ) du.

    Evaluated with the midpoint rule over u (deterministic, differentiable in p). For τ → 0 it
    tends to p; at τ = 0.1 it differs from p by a few 1e-3. Used to render the *expected*
    B-mode (the scatterer average) instead of one speckle realisation.
    """
    if not temperature > 0:
        raise argument_error("temperature", f"expected > 0, got {temperature}")
    p = torch.as_tensor(probability)
    if not torch.is_floating_point(p):
        p = p.to(torch.get_default_dtype())
    u = (torch.arange(n_quadrature, dtype=p.dtype, device=p.device) + 0.5) / n_quadrature
    logistic = torch.log(u) - torch.log1p(-u)
    values = torch.sigmoid((torch.logit(p)[..., None] + logistic) / temperature)
    return values.mean(dim=-1)


def gaussian_kernel_1d(
    size: int = DEFAULT_PSF_SIZE,
    sigma_px: float = DEFAULT_PSF_SIGMA_PX,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Normalised 1D Gaussian g_i ∝ exp(−i²/(2σ²)), i = −(size−1)/2 … (size−1)/2, Σ g_i = 1."""
    if not isinstance(size, int) or size < 1 or size % 2 == 0:
        raise argument_error("size", f"expected a positive odd integer, got {size!r}")
    if not sigma_px > 0:
        raise argument_error("sigma_px", f"expected > 0, got {sigma_px}")
    offsets = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    kernel = torch.exp(-(offsets**2) / (2 * sigma_px**2))
    return (kernel / kernel.sum()).to(dtype)


def gaussian_psf(
    size: int = DEFAULT_PSF_SIZE,
    sigma_axial_px: float = DEFAULT_PSF_SIGMA_PX,
    sigma_lateral_px: float = DEFAULT_PSF_SIGMA_PX,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """The separable 2D PSF G = g_axial ⊗ g_lateral, shape (size, size), summing to 1."""
    axial = gaussian_kernel_1d(size, sigma_axial_px, dtype)
    lateral = gaussian_kernel_1d(size, sigma_lateral_px, dtype)
    return axial[:, None] * lateral[None, :]


def convolution_matrix(
    kernel: torch.Tensor, size: int, valid: bool = False, dtype: torch.dtype | None = None
) -> torch.Tensor:
    """The 1D convolution with an odd ``kernel`` as a banded matrix M, so that y = M·x.

        y[i] = Σ_t k[t] · x[clamp(i + t − c, 0, n − 1)],   c = (len(k) − 1)/2

    ``valid=False`` gives the n × n matrix with replicated borders; ``valid=True`` the
    (n − len(k) + 1) × n matrix of the windows that lie inside (no padding). For the small
    kernels and scanline lengths here a matrix product is faster on a CPU than a convolution.
    """
    if kernel.ndim != 1 or kernel.shape[0] % 2 == 0:
        raise argument_error(
            "kernel", f"expected an odd-length 1D kernel, got {tuple(kernel.shape)}"
        )
    taps = kernel.shape[0]
    center = (taps - 1) // 2
    if size < 1 or (valid and size < taps):
        raise argument_error("size", f"expected ≥ {taps if valid else 1}, got {size}")
    out_rows = size - taps + 1 if valid else size
    device = kernel.device
    rows = torch.arange(out_rows, device=device)[:, None].expand(out_rows, taps)
    offsets = torch.arange(taps, device=device)[None, :]
    cols = rows + offsets if valid else (rows + offsets - center).clamp(0, size - 1)
    matrix = torch.zeros(out_rows, size, dtype=dtype or kernel.dtype, device=device)
    values = kernel.to(matrix.dtype)[None, :].expand(out_rows, taps)
    return matrix.index_put_(
        (rows.reshape(-1), cols.reshape(-1)), values.reshape(-1), accumulate=True
    )


def separable_filter(
    values: torch.Tensor, matrix_axial: torch.Tensor, matrix_lateral: torch.Tensor
) -> torch.Tensor:
    """Filter (…, H, W) images by two banded matrices: y = M_axial · x · M_lateralᵀ.

    Each product is one matrix multiplication over all images (rows folded together).
    """
    *batch, height, width = values.shape
    columns = values.transpose(-1, -2).reshape(-1, height) @ matrix_axial.transpose(0, 1)
    out_height = matrix_axial.shape[0]
    rows = columns.reshape(*batch, width, out_height).transpose(-1, -2).reshape(-1, width)
    out = rows @ matrix_lateral.transpose(0, 1)
    return out.reshape(*batch, out_height, matrix_lateral.shape[0])


def apply_psf(
    values: torch.Tensor, kernel_axial: torch.Tensor, kernel_lateral: torch.Tensor
) -> torch.Tensor:
    """Separable convolution (G ∗ v) over (depth, lateral) of ``values`` (…, H, W).

        (G ∗ v)[n, c] = Σ_i Σ_j g_axial[i] g_lateral[j] v[n − i, c − j]

    Borders are replicated, so a constant image is unchanged (the kernels sum to 1). The
    kernels are symmetric Gaussians, so convolution and correlation coincide; it is evaluated
    as banded matrix products (:func:`convolution_matrix`).
    """
    _check_image_like("values", values)
    height, width = values.shape[-2:]
    matrix_axial = convolution_matrix(kernel_axial.flip(0), height, dtype=values.dtype)
    matrix_lateral = convolution_matrix(kernel_lateral.flip(0), width, dtype=values.dtype)
    return separable_filter(values, matrix_axial, matrix_lateral)


def log_amplification(reflection: torch.Tensor) -> torch.Tensor:
    """Log compression of the reflected intensity: r' = log(1 + π r) / log(1 + π).

    Maps [0, 1] onto [0, 1] (METHOD.md: divide, not multiply, by log(1 + π)).
    """
    return torch.log1p(math.pi * reflection) / math.log1p(math.pi)


def bmode_intensity(
    transmission: torch.Tensor,
    beta: torch.Tensor,
    phi: torch.Tensor,
    scatterers: torch.Tensor,
    kernel_axial: torch.Tensor,
    kernel_lateral: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """B-mode intensity I = b + r' of Ultra-NeRF, all (…, H, W).

        b  = T · (G ∗ (S · φ))                   speckle (scattering) term
        r  = T · β,  r' = log(1 + π r)/log(1 + π) reflection term, log amplified
        I  = b + r'

    Returns (I, b, r'). ``scatterers`` S is a draw (:func:`sample_scatterers`) or its
    expectation (:func:`relaxed_bernoulli_mean`), broadcastable to ``phi``.
    """
    speckle = transmission * apply_psf(scatterers * phi, kernel_axial, kernel_lateral)
    reflection = log_amplification(transmission * beta)
    return speckle + reflection, speckle, reflection
