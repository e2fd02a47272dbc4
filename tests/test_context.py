"""f_ω's input g(x): θ at x and at its world-axis neighbours (ultron.fields.context)."""

from __future__ import annotations

import pytest
import torch

from ultron.errors import UltronInputError
from ultron.fields.context import (
    STENCIL_DIRECTIONS,
    ThetaContextConfig,
    stencil_offsets_mm,
    theta_features,
)
from ultron.fields.occupancy import OccupancyNetworkConfig
from ultron.fields.properties import CHANNELS, AcousticProperties
from ultron.models.fitted import ThetaStatistics


class LinearField:
    """A stand-in for a fitted field whose θ is a known affine function of the position:
    attenuation = x, reflection = 2y, scattering = z − 1 (mm), normalised with mean (0, 0, −1)
    and std (1, 2, 1), so that normalised θ(p) = p exactly."""

    channels = CHANNELS
    theta_stats = ThetaStatistics(CHANNELS, (0.0, 0.0, -1.0), (1.0, 2.0, 1.0))

    def query(self, points_mm):
        p = torch.as_tensor(points_mm, dtype=torch.float64).float()
        return AcousticProperties.unstack(
            torch.stack([p[:, 0], 2 * p[:, 1], p[:, 2] - 1], dim=-1), CHANNELS
        )


def test_features_are_the_normalised_theta_of_the_stencil_by_hand():
    points = torch.tensor([[1.0, 2.0, 3.0], [-4.0, 0.5, 0.0]], dtype=torch.float64)
    config = ThetaContextConfig(radii_mm=(1.0, 2.5))
    g = theta_features(LinearField(), points, config)
    assert g.shape == (2, config.n_inputs(3)) == (2, 39) and g.dtype == torch.float32
    # block 0 is θ̂(x) = x; block 1 + 6·i + j is θ̂(x + r_i·e_j) = x + r_i·e_j
    torch.testing.assert_close(g[:, :3], points.float())
    for i, r in enumerate(config.radii_mm):
        for j, e in enumerate(STENCIL_DIRECTIONS):
            block = 1 + 6 * i + j
            expected = points + r * torch.tensor(e, dtype=torch.float64)
            torch.testing.assert_close(g[:, 3 * block : 3 * block + 3], expected.float())
    # e.g. the second point's +z neighbour at 2.5 mm, written out
    torch.testing.assert_close(g[1, 3 * 11 : 3 * 12], torch.tensor([-4.0, 0.5, 2.5]))


def test_precomputed_centre_is_used_and_checked():
    points = torch.zeros(4, 3, dtype=torch.float64)
    centre = torch.tensor([[5.0, 4.0, 0.0]]).repeat(4, 1)  # raw θ: normalised (5, 2, 1)
    g = theta_features(LinearField(), points, ThetaContextConfig(radii_mm=()), centre=centre)
    torch.testing.assert_close(g, torch.tensor([[5.0, 2.0, 1.0]]).repeat(4, 1))
    with pytest.raises(UltronInputError, match="centre"):
        theta_features(LinearField(), points, ThetaContextConfig(), centre=centre[:2])
    with pytest.raises(UltronInputError, match="points_mm"):
        theta_features(LinearField(), torch.zeros(4, 2), ThetaContextConfig())


def test_config_parsing_round_trip_and_validation():
    assert ThetaContextConfig().radii_mm == (1.0, 2.0)
    assert ThetaContextConfig.parse("none").radii_mm == ()
    assert ThetaContextConfig.parse("0.5, 3").radii_mm == (0.5, 3.0)
    config = ThetaContextConfig(radii_mm=(1.5,))
    assert ThetaContextConfig.from_dict(config.to_dict()) == config
    # a model saved before contexts were recorded read θ alone; one saved before
    # encode_neighbours existed encoded its neighbours
    assert ThetaContextConfig.from_dict(None).radii_mm == ()
    assert ThetaContextConfig.from_dict({"radii_mm": [1.0]}).encode_neighbours
    assert ThetaContextConfig(radii_mm=()).n_inputs(3) == 3
    assert stencil_offsets_mm(ThetaContextConfig(radii_mm=())).shape == (0, 3)
    for bad in ("1,x", "", "-1", "0", "nan"):
        with pytest.raises(UltronInputError, match="theta_context"):
            ThetaContextConfig.parse(bad)


def test_network_config_encodes_theta_alone_unless_asked():
    base = OccupancyNetworkConfig(width=32)
    network = ThetaContextConfig().network(base, 3)
    assert (network.in_dim, network.encoded_inputs, network.width) == (39, 3, 32)
    assert ThetaContextConfig(encode_neighbours=True).network(base, 3).encoded_inputs is None
    paper = ThetaContextConfig(radii_mm=()).network(base, 4)
    assert (paper.in_dim, paper.encoded_inputs) == (4, None)
