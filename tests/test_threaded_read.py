"""The grid field's reads shared out over torch's CPU threads: the same bits as one call."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

import ultron.fields.grid as grid
from ultron.fields.grid import GridField, GridFieldConfig, threaded_read
from ultron.parallel import torch_threads


@pytest.fixture
def two_threads():
    with torch_threads(2):
        yield


def _plain(values: torch.Tensor, where: torch.Tensor) -> torch.Tensor:
    return F.grid_sample(values, where, mode="bilinear", padding_mode="border", align_corners=True)


@pytest.mark.parametrize("n", [20_001, 20_000])  # a run padded, and runs of equal length
@pytest.mark.parametrize("dims", [2, 3])
def test_a_shared_out_read_equals_one_call_bit_for_bit(two_threads, n: int, dims: int) -> None:
    generator = torch.Generator().manual_seed(0)
    grid_shape = (17, 23) if dims == 2 else (9, 11, 13)
    values = torch.randn(1, 5, *grid_shape, generator=generator)
    where = torch.rand(n, dims, generator=generator) * 2.4 - 1.2  # some beyond the border
    where = where.view(1, 1, n, 2) if dims == 2 else where.view(1, 1, 1, n, 3)
    with torch.no_grad():
        read = threaded_read(values, where)
    expected = _plain(values, where)
    assert read.shape == expected.shape
    assert torch.equal(read, expected)


def test_a_read_that_needs_a_gradient_is_one_call(two_threads, monkeypatch) -> None:
    values = torch.randn(1, 2, 8, 8, requires_grad=True)
    where = torch.rand(1, 1, 20_000, 2) * 2 - 1
    calls, original = [], F.grid_sample

    def spy(input, grid, **kwargs):
        calls.append(input.shape[0])
        return original(input, grid, **kwargs)

    monkeypatch.setattr(grid.F, "grid_sample", spy)
    threaded_read(values, where).sum().backward()
    with torch.no_grad():
        threaded_read(values, where)
    assert calls == [1, 2]  # batch 1 with autograd; one run per thread without
    assert values.grad is not None and values.grad.abs().sum() > 0


def test_a_long_box_field_reads_the_same_bits_shared_out(two_threads, monkeypatch) -> None:
    # per-axis planes and a dense volume: the layout of a long bone's field
    config = GridFieldConfig().resolved(200.0, 2.0, (0.3, 0.5, 1.0))
    assert config.axis_extent is not None and config.volume_nodes is not None
    field = GridField(config, generator=torch.Generator().manual_seed(1)).eval()
    points = torch.rand(30_001, 3, generator=torch.Generator().manual_seed(2)) * 2 - 1
    with torch.no_grad():
        shared = field(points).stack()
        monkeypatch.setattr(grid, "_POINTS_PER_THREAD", 10**12)  # every read one call
        single = field(points).stack()
    assert torch.equal(shared, single)
