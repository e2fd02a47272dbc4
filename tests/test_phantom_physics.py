"""Scanline physics of the simulator against hand-worked numbers (a bone slab in gel)."""

from __future__ import annotations

import math

import pytest
import torch

from ultron.data.dataset import ProbeGeometry
from ultron.phantom.scanline import (
    deposit_echoes,
    echo_amplitudes,
    interface_crossings,
    round_trip_attenuation_db,
    transmission_amplitude,
)
from ultron.phantom.simulator import (
    BModeConfig,
    axial_psf_matrix,
    elevation_weights,
    gaussian_beam_sigma,
    lateral_psf_matrices,
    log_compress,
)

# One scanline, Δ = 1 mm: gel, then a 3 mm bone slab from 2.5 mm to 5.5 mm, then gel.
SDF = torch.tensor([2.5, 1.5, 0.5, -0.5, -1.5, -0.5, 0.5, 1.5, 2.5, 3.5])[:, None]
R = 0.42  # intensity reflection used for the hand numbers
GEL_DB, BONE_DB = 0.25, 10.0  # one-way dB/mm


def slab():
    occupancy = (0.5 - SDF).clamp(0, 1)
    attenuation = round_trip_attenuation_db(occupancy, 1.0, GEL_DB, BONE_DB)
    return occupancy, attenuation, interface_crossings(SDF)


def test_slab_occupancy_and_attenuation():
    occupancy, attenuation, _ = slab()
    assert occupancy[:, 0].tolist() == [0, 0, 0, 1, 1, 1, 0, 0, 0, 0]
    # A_r = 2·Σ_{k<r} α_k: 0.5 dB per gel sample, 20 dB per bone sample
    expected = [0.0, 0.5, 1.0, 1.5, 21.5, 41.5, 61.5, 62.0, 62.5, 63.0]
    torch.testing.assert_close(attenuation[:, 0], torch.tensor(expected))


def test_slab_crossings():
    _, _, crossings = slab()
    assert crossings.entering[:, 0].nonzero().flatten().tolist() == [2]  # between rows 2 and 3
    assert crossings.exiting[:, 0].nonzero().flatten().tolist() == [5]
    assert crossings.fraction[2, 0].item() == pytest.approx(0.5)  # depth 2.5 mm
    assert crossings.fraction[5, 0].item() == pytest.approx(0.5)  # depth 5.5 mm
    assert crossings.fraction[0, 0].item() == 0.0


def test_slab_echoes_and_shadow():
    _, attenuation, crossings = slab()
    cos = torch.ones_like(crossings.fraction)
    echo = echo_amplitudes(crossings, cos, attenuation, R, 4.0, 0.25)[:, 0]
    entry = math.sqrt(R) * 10 ** (-1.25 / 20)  # A(2.5 mm) = 1.0 + 0.5·(1.5 − 1.0)
    exit_ = math.sqrt(R) * (1 - R) * 10 ** (-51.5 / 20)  # A(5.5 mm) = 41.5 + 0.5·20
    assert echo[2].item() == pytest.approx(entry, rel=1e-5)
    assert echo[5].item() == pytest.approx(exit_, rel=1e-5)
    assert echo[[0, 1, 3, 4, 6, 7, 8]].abs().max().item() == 0.0
    # oblique incidence: g(60°) = 0.75·0.5⁴ + 0.25·0.5
    oblique = echo_amplitudes(crossings, 0.5 * cos, attenuation, R, 4.0, 0.25)[2, 0]
    assert oblique.item() == pytest.approx(entry * math.sqrt(0.75 / 16 + 0.125), rel=1e-5)

    tau = transmission_amplitude(crossings, attenuation, R)[:, 0]
    assert tau[1].item() == pytest.approx(10 ** (-0.5 / 20), rel=1e-6)
    assert tau[4].item() == pytest.approx((1 - R) * 10 ** (-21.5 / 20), rel=1e-5)
    assert tau[7].item() == pytest.approx((1 - R) ** 2 * 10 ** (-62 / 20), rel=1e-5)
    # 62 dB + two interfaces: the gel behind 3 mm of bone is in deep acoustic shadow
    assert tau[7].item() < 1e-3 * tau[1].item()

    deposited = deposit_echoes(echo[:, None], crossings.fraction)[:, 0]
    assert deposited[2].item() == pytest.approx(entry / 2, rel=1e-5)
    assert deposited[3].item() == pytest.approx(entry / 2, rel=1e-5)
    assert deposited.sum().item() == pytest.approx(entry + exit_, rel=1e-5)


def test_psf_matrices():
    probe = ProbeGeometry(38.0, 70.0, 128, 96)
    axial = axial_psf_matrix(probe, 0.3)
    step = probe.axial_spacing_mm
    assert axial.diagonal().eq(1.0).all()
    assert axial[0, 1].item() == pytest.approx(math.exp(-(step**2) / (2 * 0.09)), rel=1e-5)
    config = BModeConfig()
    lateral = lateral_psf_matrices(probe, config)
    torch.testing.assert_close(lateral.sum(dim=1), torch.ones(128, 96))
    focus_row = round(config.lateral_focus_mm / step)
    # a focused beam: the kernel is narrowest (highest peak) at the transmit focus
    assert lateral[focus_row, 48, 48] > lateral[0, 48, 48]
    assert lateral[focus_row, 48, 48] > lateral[-1, 48, 48]
    sigma = gaussian_beam_sigma(torch.tensor([45.0, 65.0]), 0.45, 45.0, 20.0)
    torch.testing.assert_close(sigma, torch.tensor([0.45, 0.45 * math.sqrt(2)]))
    weights = elevation_weights(probe, config)
    assert weights.shape == (3, 128)
    torch.testing.assert_close(weights.sum(0), torch.ones(128))
    torch.testing.assert_close(weights[0], weights[2])


def test_log_compression_hand_worked():
    config = BModeConfig(gain_db=-3.0, dynamic_range_db=50.0)
    ref = math.sqrt(R)
    env = torch.tensor([ref, ref * 10 ** (-7 / 20), ref * 10 ** (-47 / 20), ref * 1e-4, ref * 10])
    # 255·(1 + (−x − 3)/50): x = 0 → 239.7, x = 7 → 204, x = 47 → 0; clipped at both ends
    assert log_compress(env, ref, config).tolist() == [240, 204, 0, 0, 255]


def test_reflection_of_config_is_the_impedance_formula():
    config = BModeConfig()
    z1, z2 = config.gel.impedance_mrayl, config.bone.impedance_mrayl
    assert config.reflection == pytest.approx(((z2 - z1) / (z2 + z1)) ** 2)
    assert 0.35 < config.reflection < 0.5  # gel/cortical bone: ≈ 42 % of the intensity
