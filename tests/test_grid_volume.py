"""The grid field's dense volume level: where its nodes sit, how it is read and its prior."""

from __future__ import annotations

import json
import math

import pytest
import torch

from ultron.errors import UltronError
from ultron.fields.factory import FieldConfig
from ultron.fields.grid import VOLUME_TV_WINDOW, GridField, GridFieldConfig, _volume_tv_drawn


def test_volume_nodes_cover_the_planes_reach_at_the_cell() -> None:
    # a compact box keeps square planes over the whole cube: 100 mm / 2 mm + 1 nodes per axis
    square = GridFieldConfig(volume_cell_mm=2.0).resolved(50.0, 0.3, (0.8, 0.9, 1.0))
    assert square.axis_extent is None
    assert square.volume_nodes == (51, 51, 51)
    # a long box gets per-axis planes; the volume spans the same box per axis
    long = GridFieldConfig(volume_cell_mm=2.0).resolved(200.0, 0.3, (0.3, 0.5, 1.0))
    assert long.axis_extent == (0.3, 0.5, 1.0)
    assert long.volume_nodes == (61, 101, 201)  # ⌈400·e / 2⌉ + 1
    planes_only = GridFieldConfig(long_box_volume_mm=None).resolved(200.0, 0.3, (0.3, 0.5, 1.0))
    assert long.resolutions == planes_only.resolutions
    assert long.n_values() == planes_only.n_values() + 4 * 61 * 101 * 201
    assert long.resolved(1.0, 1.0) == long  # resolved once, kept


def test_the_volume_is_read_trilinearly_with_x_along_its_last_axis() -> None:
    config = GridFieldConfig(volume_cell_mm=10.0, volume_features=3).resolved(50.0, 5.0)
    field = GridField(config)
    nx, ny, nz = config.volume_nodes
    x = torch.linspace(-1, 1, nx).view(1, 1, nx)
    y = torch.linspace(-1, 1, ny).view(1, ny, 1)
    z = torch.linspace(-1, 1, nz).view(nz, 1, 1)
    with torch.no_grad():  # channel c holds the linear function x, y or z of the node
        field.volume.copy_(
            torch.stack([x + 0 * y + 0 * z, 0 * x + y + 0 * z, 0 * x + 0 * y + z])[None]
        )
    points = torch.rand(500, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    read = field.features(points)[:, -3:]  # trilinear interpolation reproduces linear functions
    torch.testing.assert_close(read, points, atol=1e-5, rtol=0)


def test_the_volume_prior_is_the_mean_squared_step_over_its_axes() -> None:
    step = 0.3
    n = VOLUME_TV_WINDOW + 9
    ramp = step * torch.arange(n, dtype=torch.float64)  # along x: every x-step is `step`
    volume = ramp.view(1, 1, 1, 1, n).expand(1, 2, 5, 6, n).contiguous()
    window = iter(torch.tensor([[0, 0, 4]]))
    # y and z steps are 0: (step² + 0 + 0) / 3, on the window as on the whole volume
    assert _volume_tv_drawn(volume, window).item() == pytest.approx(step**2 / 3, rel=1e-12)


def test_the_volume_prior_reads_the_drawn_window() -> None:
    volume = torch.randn(1, 2, 40, 36, 34, dtype=torch.float64)
    corner = (5, 3, 1)
    tv = _volume_tv_drawn(volume, iter(torch.tensor([corner])))
    block = volume[
        :, :, 5 : 5 + VOLUME_TV_WINDOW, 3 : 3 + VOLUME_TV_WINDOW, 1 : 1 + VOLUME_TV_WINDOW
    ]
    expected = sum(block.diff(dim=a).pow(2).mean() for a in (2, 3, 4)) / 3
    assert tv.item() == pytest.approx(expected.item(), rel=1e-12)


def test_the_volume_prior_gradient() -> None:
    volume = torch.randn(1, 2, 4, 5, 6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: _volume_tv_drawn(v, iter(())), (volume,))


def test_the_drawn_prior_takes_one_window_of_a_large_volume() -> None:
    config = GridFieldConfig(volume_cell_mm=2.0).resolved(100.0, 0.3, (0.3, 0.5, 1.0))
    field = GridField(config)
    draws = field.regularization_draws(torch.Generator().manual_seed(3))
    planes_only = GridField(
        GridFieldConfig(long_box_volume_mm=None).resolved(100.0, 0.3, (0.3, 0.5, 1.0))
    )
    plane_draws = planes_only.regularization_draws(torch.Generator().manual_seed(3))
    assert draws.shape[0] == plane_draws.shape[0] + 1  # the planes' rows, then the volume's
    torch.testing.assert_close(draws[:-1], plane_draws)
    nz, ny, nx = field.volume.shape[2:]
    assert all(
        0 <= c <= max(0, n - VOLUME_TV_WINDOW) for c, n in zip(draws[-1], (nz, ny, nx), strict=True)
    )
    drawn = field.regularization(draws=draws)
    again = field.regularization(torch.Generator().manual_seed(3))
    assert drawn.item() == again.item()
    drawn.backward()
    assert field.volume.grad.abs().sum() > 0


def test_a_volume_round_trips_through_field_json() -> None:
    config = FieldConfig(grid=GridFieldConfig(volume_cell_mm=2.0).resolved(60.0, 0.5))
    data = config.to_dict()
    assert list(data["grid"]["volume_nodes"]) == [61, 61, 61]
    assert FieldConfig.from_dict(json.loads(json.dumps(data))) == config


@pytest.mark.parametrize(
    ("changes", "name"),
    [
        ({"volume_cell_mm": 0.0}, "volume_cell_mm"),
        ({"volume_cell_mm": math.nan}, "volume_cell_mm"),
        ({"volume_features": 0}, "volume_features"),
        ({"volume_nodes": (4, 4)}, "volume_nodes"),
        ({"volume_nodes": (1, 4, 4)}, "volume_nodes"),
    ],
)
def test_bad_volume_settings_name_the_setting(changes: dict, name: str) -> None:
    with pytest.raises(UltronError, match=f"grid.{name}"):
        GridFieldConfig(**changes)


def test_a_field_saved_before_the_volume_loads_without_one() -> None:
    planes = GridFieldConfig(volume_cell_mm=None).resolved(60.0, 0.5)
    saved = FieldConfig(grid=planes).to_dict()  # as field.json was written before the volume
    assert not any(key.startswith("volume") for key in saved["grid"])
    loaded = FieldConfig.from_dict(json.loads(json.dumps(saved)))
    assert loaded.grid.volume_cell_mm is None and loaded.grid.volume_nodes is None
    assert loaded.grid.n_values() == planes.n_values()
    assert GridField(loaded.grid).volume is None


def test_without_a_volume_the_saved_settings_are_those_written_before_it() -> None:
    # field.json and the field cache's key hold the same keys as before the volume existed
    data = FieldConfig().to_dict()
    assert not any(key.startswith("volume") for key in data["grid"])
    assert FieldConfig.from_dict(data) == FieldConfig()
    with_volume = FieldConfig(grid=GridFieldConfig(volume_cell_mm=2.0)).to_dict()
    assert with_volume["grid"]["volume_cell_mm"] == 2.0
    assert FieldConfig.from_dict(with_volume).grid.volume_cell_mm == 2.0
