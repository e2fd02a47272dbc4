"""SSIM / PSNR / regulariser checks against hand-worked values (ultron.train.losses)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from ultron.errors import UltronInputError
from ultron.train import psnr, ssim, ssim_map, ultranerf_loss, weighted_scattering_tv
from ultron.train.losses import confidence_transmission_prior

F64 = torch.float64


def test_ssim_of_identical_images_is_one() -> None:
    x = torch.rand(2, 20, 15, dtype=F64, generator=torch.Generator().manual_seed(0))
    assert math.isclose(float(ssim(x, x)), 1.0, rel_tol=1e-12)


def test_ssim_of_constant_images_is_the_luminance_term() -> None:
    """σ = 0 everywhere: SSIM = (2ab + C1)/(a² + b² + C1) (the C2 factors cancel)."""
    a, b, c1 = 0.2, 0.6, 0.01**2
    x, y = torch.full((9, 9), a, dtype=F64), torch.full((9, 9), b, dtype=F64)
    got = ssim_map(x, y)
    assert got.shape == (1, 1, 3, 3)
    torch.testing.assert_close(got, torch.full_like(got, (2 * a * b + c1) / (a * a + b * b + c1)))


def test_ssim_rejects_bad_shapes() -> None:
    with pytest.raises(UltronInputError, match="y"):
        ssim(torch.zeros(8, 8), torch.zeros(8, 9))
    with pytest.raises(UltronInputError, match="x"):
        ssim(torch.zeros(5, 8), torch.zeros(5, 8))


def test_psnr_and_loss_hand_worked() -> None:
    x, y = torch.zeros(8, 8), torch.full((8, 8), 0.1)
    assert math.isclose(psnr(x, y), 20.0, rel_tol=1e-6)  # MSE 0.01 → 20 dB
    loss, mse = ultranerf_loss(y, y)
    assert float(loss) == pytest.approx(0.0, abs=1e-6) and float(mse) == 0.0


def test_weighted_scattering_tv_ignores_the_brightest_reflector() -> None:
    phi = torch.zeros(1, 4, 4, dtype=F64)
    phi[..., 2:, :] = 1.0  # an edge between rows 1 and 2
    beta = torch.zeros(1, 4, 4, dtype=F64)
    assert float(weighted_scattering_tv(phi, beta)) == 0.0  # β_max − β = 0 everywhere
    beta[..., 0, 0] = 0.5  # weight 0.5 elsewhere: 4 of 12 depth differences are 1
    assert float(weighted_scattering_tv(phi, beta)) == pytest.approx(0.5 * 4 / 12)


def test_confidence_prior_is_one_sided_and_hand_worked() -> None:
    t = torch.tensor([[0.9, 0.2], [1.0, 0.5]], dtype=torch.float64, requires_grad=True)
    c = torch.tensor([[0.5, 0.5], [0.1, 0.9]], dtype=torch.float64)
    # excesses over C + 0.3: 0.1, none, 0.6, none → (0.01 + 0.36) / 4
    prior = confidence_transmission_prior(t, c, 0.3)
    assert prior.item() == pytest.approx(0.0925, abs=1e-12)
    prior.backward()
    # only T above C + m is pulled down: dP/dT = 2·excess / 4
    assert torch.allclose(t.grad, torch.tensor([[0.05, 0.0], [0.3, 0.0]], dtype=torch.float64))
    assert torch.autograd.gradcheck(
        lambda x: confidence_transmission_prior(x, c, 0.3), (t.detach().requires_grad_(),)
    )
    with pytest.raises(UltronInputError, match="confidence"):
        confidence_transmission_prior(t, c[:1], 0.3)
    with pytest.raises(UltronInputError, match="margin"):
        confidence_transmission_prior(t, c, float("nan"))


def test_ssim_equals_scikit_image():
    """Our SSIM is Wang et al.'s: with scikit-image's Gaussian window (σ 1.5, truncated at
    3.5 σ: 11 taps; scikit-image fixes the truncation, so the loss's 7-tap window cannot be
    compared) and population covariances, the mean over the valid region is scikit-image's to
    float64 rounding, for both constants the code uses."""
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(0)
    x = rng.random((40, 33))
    for noise in (0.02, 0.1, 0.5):
        y = np.clip(x + noise * rng.standard_normal(x.shape), 0, 1)
        for k2 in (0.03, 0.1):
            ours = float(ssim(torch.tensor(x), torch.tensor(y), window=11, k1=0.01, k2=k2))
            reference = structural_similarity(
                x, y, data_range=1.0, gaussian_weights=True, sigma=1.5,
                use_sample_covariance=False, K1=0.01, K2=k2,
            )  # fmt: skip
            assert ours == pytest.approx(reference, abs=1e-12), (noise, k2)
