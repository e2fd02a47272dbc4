"""Analytic cases of the Ultra-NeRF scanline physics (ultron.render)."""

from __future__ import annotations

import math

import pytest
import torch

from ultron.errors import UltronInputError
from ultron.fields.properties import AcousticProperties
from ultron.render import (
    RenderConfig,
    apply_psf,
    attenuation_transmission,
    convolution_matrix,
    exclusive_cumsum,
    gaussian_kernel_1d,
    gaussian_psf,
    log_amplification,
    reflection_transmission,
    relaxed_bernoulli_mean,
    render_properties,
    sample_scatterers,
    total_transmission,
)

F64 = torch.float64


def test_exclusive_cumsum_hand_worked() -> None:
    values = torch.tensor([[1.0], [2.0], [3.0], [4.0]])
    assert exclusive_cumsum(values).flatten().tolist() == [0.0, 1.0, 3.0, 6.0]


def test_constant_attenuation_gives_exponential_decay() -> None:
    alpha, step = 0.03, 0.25  # 1/mm, mm
    a = torch.full((2, 50, 3), alpha, dtype=F64)
    got = attenuation_transmission(a, step)
    depth_mm = torch.arange(50, dtype=F64) * step
    expected = torch.exp(-alpha * depth_mm)[None, :, None].expand_as(got)
    torch.testing.assert_close(got, expected, rtol=1e-12, atol=1e-14)
    assert got[0, 0, 0] == 1.0  # exclusive: the first sample is unattenuated


def test_attenuation_step_is_physical_not_a_pixel_count() -> None:
    """Halving the step with twice the samples reaches the same depth with the same T."""
    coarse = attenuation_transmission(torch.full((11, 1), 0.1, dtype=F64), 1.0)
    fine = attenuation_transmission(torch.full((21, 1), 0.1, dtype=F64), 0.5)
    torch.testing.assert_close(coarse[10], fine[20])
    assert math.isclose(float(coarse[10]), math.exp(-1.0), rel_tol=1e-12)


def test_single_reflector_gives_exclusive_step() -> None:
    beta = torch.zeros(10, 2, dtype=F64)
    beta[4, :] = 0.3
    r = reflection_transmission(beta)
    assert torch.all(r[:5] == 1.0)  # up to and including the reflector: no loss
    torch.testing.assert_close(r[5:], torch.full((5, 2), 0.7, dtype=F64))


def test_two_reflectors_multiply() -> None:
    beta = torch.zeros(6, 1, dtype=F64)
    beta[1], beta[3] = 0.5, 0.2
    r = reflection_transmission(beta).flatten()
    torch.testing.assert_close(r, torch.tensor([1, 1, 0.5, 0.5, 0.4, 0.4], dtype=F64))


def test_total_transmission_is_product() -> None:
    g = torch.Generator().manual_seed(0)
    alpha = torch.rand(3, 20, 4, generator=g, dtype=F64) * 0.2
    beta = torch.rand(3, 20, 4, generator=g, dtype=F64) * 0.3
    t = total_transmission(alpha, beta, 0.4)
    torch.testing.assert_close(
        t, attenuation_transmission(alpha, 0.4) * reflection_transmission(beta)
    )


def test_psf_sums_to_one_and_is_hand_worked() -> None:
    psf = gaussian_psf(7, 1.0, 2.0, dtype=F64)
    assert psf.shape == (7, 7)
    assert math.isclose(float(psf.sum()), 1.0, rel_tol=1e-12)
    k = gaussian_kernel_1d(3, 1.0, dtype=F64)
    e = math.exp(-0.5)
    torch.testing.assert_close(k, torch.tensor([e, 1.0, e], dtype=F64) / (1 + 2 * e))


def test_apply_psf_keeps_constants_and_spreads_an_impulse() -> None:
    ka, kl = gaussian_kernel_1d(7, 1.0, F64), gaussian_kernel_1d(7, 1.5, F64)
    const = torch.full((2, 12, 10), 0.7, dtype=F64)
    torch.testing.assert_close(apply_psf(const, ka, kl), const)
    impulse = torch.zeros(15, 15, dtype=F64)
    impulse[7, 7] = 1.0
    torch.testing.assert_close(apply_psf(impulse, ka, kl)[4:11, 4:11], ka[:, None] * kl[None, :])


def test_convolution_matrix_matches_conv1d() -> None:
    g = torch.Generator().manual_seed(3)
    x = torch.rand(2, 11, dtype=F64, generator=g)
    k = gaussian_kernel_1d(5, 1.2, F64)
    valid = torch.nn.functional.conv1d(x[:, None], k.view(1, 1, -1))[:, 0]
    torch.testing.assert_close(x @ convolution_matrix(k, 11, valid=True).T, valid)
    padded = torch.nn.functional.pad(x[:, None], (2, 2), mode="replicate")
    same = torch.nn.functional.conv1d(padded, k.view(1, 1, -1))[:, 0]
    torch.testing.assert_close(x @ convolution_matrix(k, 11).T, same)
    with pytest.raises(UltronInputError, match="size"):
        convolution_matrix(k, 4, valid=True)


def test_log_amplification_maps_unit_interval() -> None:
    r = torch.tensor([0.0, 0.5, 1.0], dtype=F64)
    out = log_amplification(r)
    assert out[0] == 0.0 and math.isclose(float(out[2]), 1.0, rel_tol=1e-12)
    assert math.isclose(float(out[1]), math.log(1 + math.pi / 2) / math.log(1 + math.pi))


def test_scatterers_are_seeded_and_match_their_expectation() -> None:
    a = sample_scatterers(0.75, (200, 200), torch.Generator().manual_seed(5))
    b = sample_scatterers(0.75, (200, 200), torch.Generator().manual_seed(5))
    assert torch.equal(a, b)
    assert float(a.min()) >= 0 and float(a.max()) <= 1
    # mean of 40k draws vs the quadrature expectation (std of the mean ≈ 0.002)
    assert abs(float(a.mean()) - float(relaxed_bernoulli_mean(0.75))) < 0.01
    # near-binary at τ = 0.1: most draws are within 0.05 of 0 or 1
    assert float(((a < 0.05) | (a > 0.95)).float().mean()) > 0.8


def test_relaxed_bernoulli_mean_limits() -> None:
    assert abs(float(relaxed_bernoulli_mean(0.75, 1e-3)) - 0.75) < 1e-3
    total = relaxed_bernoulli_mean(0.3) + relaxed_bernoulli_mean(0.7)
    assert math.isclose(float(total), 1.0, rel_tol=1e-6)  # symmetry of the logistic noise


def test_uniform_medium_renders_phi_times_mean_scatterer() -> None:
    shape = (1, 16, 9)
    props = AcousticProperties(
        torch.zeros(shape, dtype=F64),
        torch.zeros(shape, dtype=F64),
        torch.full(shape, 0.4, dtype=F64),
    )
    out = render_properties(props, 0.5, RenderConfig(), expected=True)
    torch.testing.assert_close(
        out.intensity,
        torch.full(shape, 0.4, dtype=F64) * relaxed_bernoulli_mean(torch.tensor(0.75, dtype=F64)),
    )
    assert torch.all(out.transmission == 1.0)


def test_renderer_gradcheck_float64() -> None:
    g = torch.Generator().manual_seed(1)
    shape = (1, 7, 5)
    alpha = (torch.rand(shape, generator=g, dtype=F64) * 0.2).requires_grad_()
    beta = (torch.rand(shape, generator=g, dtype=F64) * 0.3 + 0.01).requires_grad_()
    phi = torch.rand(shape, generator=g, dtype=F64).requires_grad_()
    config = RenderConfig()

    def render(a: torch.Tensor, b: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        props = AcousticProperties(a, b, p)
        return render_properties(
            props, 0.3, config, torch.Generator().manual_seed(2), expected=False
        ).intensity

    assert torch.autograd.gradcheck(render, (alpha, beta, phi))

    def render_expected(a: torch.Tensor, b: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        return render_properties(AcousticProperties(a, b, p), 0.3, config, expected=True).intensity

    assert torch.autograd.gradcheck(render_expected, (alpha, beta, phi))


def test_learned_density_gets_gradients() -> None:
    shape = (1, 8, 8)
    density = torch.full(shape, 0.6, dtype=F64, requires_grad=True)
    props = AcousticProperties(
        torch.zeros(shape, dtype=F64),
        torch.zeros(shape, dtype=F64),
        torch.full(shape, 0.5, dtype=F64),
        density,
    )
    out = render_properties(props, 0.5, RenderConfig(), torch.Generator().manual_seed(0))
    out.intensity.sum().backward()
    assert density.grad is not None and float(density.grad.abs().sum()) > 0


@pytest.mark.parametrize(
    ("call", "name"),
    [
        (lambda: attenuation_transmission(torch.zeros(4, 2), 0.0), "step_mm"),
        (lambda: attenuation_transmission(torch.zeros(4), 1.0), "alpha_per_mm"),
        (lambda: gaussian_kernel_1d(4, 1.0), "size"),
        (lambda: gaussian_kernel_1d(5, 0.0), "sigma_px"),
        (lambda: sample_scatterers(1.5, (2, 2), None), "probability"),
        (lambda: RenderConfig(scatter_probability=1.0), "scatter_probability"),
        (
            lambda: render_properties(
                AcousticProperties(*(torch.zeros(1, 4, 4) for _ in range(3))), 1.0, RenderConfig()
            ),
            "generator",
        ),
    ],
)
def test_bad_inputs_name_the_argument(call, name: str) -> None:
    with pytest.raises(UltronInputError, match=name):
        call()


def test_psf_rescaling_keeps_its_size_in_mm() -> None:
    from ultron.data.dataset import ProbeGeometry

    native = ProbeGeometry(80.0, 140.0, 512, 256)
    reduced = ProbeGeometry(80.0, 140.0, 128, 128)
    config = RenderConfig(psf_sigma_axial_px=1.0, psf_sigma_lateral_px=2.0).rescaled(
        native, reduced
    )
    assert config.psf_sigma_axial_px == pytest.approx(0.25)  # 4× coarser rows
    assert config.psf_sigma_lateral_px == pytest.approx(1.0)  # 2× coarser columns
    assert RenderConfig.from_dict(config.to_dict()) == config


@pytest.mark.parametrize("module", ["ultron.render", "ultron.fields", "ultron.train"])
def test_packages_import_first_without_cycles(module: str) -> None:
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-c", f"import {module}"], capture_output=True)
    assert result.returncode == 0, result.stderr.decode()
