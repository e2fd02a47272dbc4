"""Image losses and metrics: Gaussian-window SSIM, MSE, PSNR, the Ultra-NeRF regulariser and
the confidence-map prior on the transmission."""

from __future__ import annotations

import math
from typing import Any

import torch

from ultron.errors import argument_error
from ultron.render.physics import convolution_matrix, gaussian_kernel_1d, separable_filter

#: Ultra-NeRF's loss SSIM constants (METHOD.md §2) and the standard metric ones (Wang et al.).
LOSS_SSIM_K2 = 0.1
METRIC_SSIM_K2 = 0.03


def _as_batch(name: str, image: torch.Tensor) -> torch.Tensor:
    if not torch.is_tensor(image) or image.ndim < 2:
        raise argument_error(name, "expected a tensor of shape (..., H, W)")
    return image.reshape(-1, 1, image.shape[-2], image.shape[-1])


def ssim_map(
    x: torch.Tensor,
    y: torch.Tensor,
    window: int = 7,
    sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = LOSS_SSIM_K2,
    data_range: float = 1.0,
    kernel: torch.Tensor | None = None,
) -> torch.Tensor:
    """Local SSIM (Wang et al. 2004) with a Gaussian window, over the valid region.

        SSIM = (2 μx μy + C1)(2 σxy + C2) / ((μx² + μy² + C1)(σx² + σy² + C2)),
        C1 = (k1 L)², C2 = (k2 L)²

    ``x`` and ``y`` are (…, H, W) with H, W ≥ ``window``; returns (B, 1, H−w+1, W−w+1).
    ``kernel``: the window's 1D Gaussian already on the images' device and dtype
    (:func:`ssim_kernel`), so that nothing is built or copied from the host.
    """
    if x.shape != y.shape:
        raise argument_error("y", f"shape {tuple(y.shape)} differs from x {tuple(x.shape)}")
    a, b = _as_batch("x", x), _as_batch("y", y)
    if min(a.shape[-2:]) < window:
        raise argument_error("x", f"images must be at least {window} pixels on each side")
    if kernel is None:
        kernel = ssim_kernel(window, sigma, a.dtype, a.device)
    elif kernel.shape != (window,):
        raise argument_error("kernel", f"expected ({window},), got {tuple(kernel.shape)}")
    c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2
    stacked = torch.cat([a, b, a * a, b * b, a * b], dim=1)  # (B, 5, H, W)
    height, width = a.shape[-2:]
    blurred = separable_filter(
        stacked,
        convolution_matrix(kernel, height, valid=True),
        convolution_matrix(kernel, width, valid=True),
    )
    mu_x, mu_y, xx, yy, xy = blurred.unbind(1)
    var_x, var_y, cov = xx - mu_x**2, yy - mu_y**2, xy - mu_x * mu_y
    num = (2 * mu_x * mu_y + c1) * (2 * cov + c2)
    den = (mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2)
    return (num / den).unsqueeze(1)


def ssim_kernel(
    window: int = 7,
    sigma: float = 1.5,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """The 1D Gaussian window of :func:`ssim_map` (built on the CPU, moved to ``device``)."""
    return gaussian_kernel_1d(window, sigma, dtype).to(device)


def ssim(x: torch.Tensor, y: torch.Tensor, **kwargs: Any) -> torch.Tensor:
    """Mean of :func:`ssim_map` (a scalar)."""
    return ssim_map(x, y, **kwargs).mean()


def psnr(x: torch.Tensor, y: torch.Tensor, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio 10·log10(L² / MSE) in dB."""
    mse = float(torch.mean((x.to(torch.float64) - y.to(torch.float64)) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(data_range**2 / mse)


def ultranerf_loss(
    rendered: torch.Tensor,
    target: torch.Tensor,
    ssim_weight: float = 0.75,
    mse_weight: float = 0.25,
    window: int = 7,
    sigma: float = 1.5,
    kernel: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Ultra-NeRF's image loss 0.75·(1 − SSIM) + 0.25·MSE (SSIM k1 = 0.01, k2 = 0.1).

    Returns (loss, mse). ``kernel``: the SSIM window, as in :func:`ssim_map`.
    """
    mse = torch.mean((rendered - target) ** 2)
    structural = ssim(
        rendered, target, window=window, sigma=sigma, k1=0.01, k2=LOSS_SSIM_K2, kernel=kernel
    )
    return ssim_weight * (1 - structural) + mse_weight * mse, mse


def weighted_scattering_tv(scattering: torch.Tensor, reflection: torch.Tensor) -> torch.Tensor:
    """Total variation of φ weighted by (β_max − β) (METHOD.md §2 optional regulariser).

        TV_w = mean[(β_max − β) · (|∂_depth φ| + |∂_lateral φ|)]

    on (…, H, W) maps; smooths speckle amplitude away from strong reflectors.
    """
    weight = (reflection.amax(dim=(-2, -1), keepdim=True) - reflection).detach()
    d_depth = (scattering[..., 1:, :] - scattering[..., :-1, :]).abs()
    d_lateral = (scattering[..., :, 1:] - scattering[..., :, :-1]).abs()
    return (weight[..., 1:, :] * d_depth).mean() + (weight[..., :, 1:] * d_lateral).mean()


def confidence_transmission_prior(
    transmission: torch.Tensor, confidence: torch.Tensor, margin: float
) -> torch.Tensor:
    """One-sided prior that the rendered transmission T does not exceed the image's ultrasound
    confidence C (Karamalis et al. 2012) by more than ``margin``:

        P = mean[ max(0, T − C − m)² ]

    on (…, H, W) maps of equal shape. C is the random-walk confidence of the B-mode frame itself:
    low under a strong reflector and deep in the frame. The prior only pulls T *down* where the
    image says little signal can arrive; it never pushes T up (confidence is not a transmission
    scale: it also falls with depth in lit tissue, which the margin absorbs).
    """
    if transmission.shape != confidence.shape:
        raise argument_error(
            "confidence",
            f"shape {tuple(confidence.shape)} differs from transmission {tuple(transmission.shape)}",
        )
    if not (math.isfinite(margin) and 0 <= margin < 1):
        raise argument_error("margin", f"expected a value in [0, 1), got {margin}")
    return torch.relu(transmission - confidence - margin).pow(2).mean()
