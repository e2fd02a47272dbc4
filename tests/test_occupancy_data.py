"""Stage 2's data: the pixels a fit reads, and data holding only their inputs."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from conftest import SMALL_OCCUPANCY, random_occupancy_data
from ultron.errors import UltronInputError
from ultron.fields.occupancy import OccupancyNetworkConfig
from ultron.train.occupancy import (
    OccupancyAnchor,
    OccupancyTrainConfig,
    OccupancyTrainingData,
    fit_occupancy,
    label_loss,
    rows_read,
)
from ultron.train.occupancy_data import label_loss_pick, minibatch_orders

SMALL = OccupancyNetworkConfig(**SMALL_OCCUPANCY)
#: 15 batches of 64 of 2000 pixels and label_loss's every 20th: fewer than all are read
CONFIG = OccupancyTrainConfig(iters=15, batch_size=64, lr=1e-3, seed=4, network=SMALL)
MAX_POINTS = 100


def _data(n: int = 2000) -> OccupancyTrainingData:
    return random_occupancy_data(n, front=True)


def _only(data: OccupancyTrainingData, rows: torch.Tensor) -> OccupancyTrainingData:
    """``data`` holding the inputs of ``rows`` only."""
    input_rows = torch.full((len(data.labels),), -1, dtype=torch.int64)
    input_rows[rows] = torch.arange(len(rows))
    return replace(data, inputs=data.inputs[rows].clone(), input_rows=input_rows)


def test_label_loss_pick_by_hand():
    assert label_loss_pick(10, 4).tolist() == [0, 3, 6, 9]  # every ⌈10 / 4⌉ = 3rd
    assert label_loss_pick(3, 8).tolist() == [0, 1, 2]
    with pytest.raises(UltronInputError, match="max_points"):
        label_loss_pick(3, 0)


def test_rows_read_are_the_fits_draws_and_the_label_loss_pixels():
    n = 2000
    _, orders = minibatch_orders(n, CONFIG.batch_size, CONFIG.seed)
    drawn = torch.cat([next(orders[0]) for _ in range(CONFIG.iters)])
    expected = torch.unique(torch.cat([drawn, label_loss_pick(n, MAX_POINTS)]))
    rows = rows_read(n, CONFIG.batch_size, CONFIG.iters, CONFIG.seed, max_points=MAX_POINTS)
    assert torch.equal(rows, expected)
    assert 100 < len(rows) < n  # some pixels are never read
    # an anchor drawing from the same generator moves the labels' second permutation
    many = 40  # 40 × 64 > 2000: a second permutation
    alone = rows_read(n, CONFIG.batch_size, many, CONFIG.seed, max_points=MAX_POINTS)
    anchored = rows_read(n, CONFIG.batch_size, many, CONFIG.seed, 500, max_points=MAX_POINTS)
    assert not torch.equal(alone, anchored)
    assert len(rows_read(n, 4096, 1, 0)) == n  # one batch covers all


@pytest.mark.parametrize("anchored", [False, True])
def test_a_fit_on_the_rows_read_equals_the_fit_on_every_pixels_inputs(anchored):
    data = _data()
    config = replace(CONFIG, negatives="front")  # the in_front mask is read too
    anchor = OccupancyAnchor(torch.rand(300, 3), torch.rand(300)) if anchored else None
    n_anchor = None if anchor is None else 300
    rows = rows_read(2000, config.batch_size, config.iters, config.seed, n_anchor, MAX_POINTS)
    part = _only(data, rows)
    full_net, full_log = fit_occupancy(data, config, anchor=anchor)
    part_net, part_log = fit_occupancy(part, config, anchor=anchor)
    for a, b in zip(full_net.state_dict().values(), part_net.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    losses = [[e["loss"] for e in log] for log in (full_log, part_log)]
    assert losses[0] == losses[1] and len(losses[0]) > 0
    assert label_loss(part_net, part, config, MAX_POINTS) == label_loss(
        full_net, data, config, MAX_POINTS
    )
    assert part.summary(0.3)["n_inputs_computed"] == len(rows) < 2000


def test_reading_a_pixel_whose_input_was_not_computed_is_an_error():
    data = _data()
    other_seed = replace(CONFIG, seed=5)
    rows = rows_read(2000, CONFIG.batch_size, CONFIG.iters, CONFIG.seed, max_points=MAX_POINTS)
    part = _only(data, rows)
    with pytest.raises(UltronInputError, match="no input computed"):
        fit_occupancy(part, other_seed)
    with pytest.raises(UltronInputError, match="no input computed"):
        label_loss(fit_occupancy(part, CONFIG)[0], part, CONFIG)  # every 8th: not all read
    missing = int(torch.nonzero(part.input_rows < 0)[0, 0])
    with pytest.raises(UltronInputError, match=f"the first {missing}"):
        part.inputs_at(torch.tensor([int(rows[0]), missing]))
    assert torch.equal(part.inputs_at(rows[:5]), data.inputs[rows[:5]])


def test_input_rows_validation():
    data = _data(6)
    rows = torch.tensor([0, -1, 1, -1, 2, -1])
    good = replace(data, inputs=data.inputs[[0, 2, 4]], input_rows=rows)
    assert torch.equal(good.inputs_at(torch.tensor([4, 0])), data.inputs[[4, 0]])
    for inputs, input_rows, match in (
        (data.inputs[:3], rows.to(torch.int32), "int64"),
        (data.inputs[:3], torch.tensor([0, -2, 1, -1, 2, -1]), "−1 or a row"),
        (data.inputs[:3], torch.tensor([0, -1, 1, -1, 3, -1]), "−1 or a row"),
        (data.inputs[:3], torch.tensor([0, -1, 1, -1, 1, -1]), "named once"),
        (data.inputs[:4], rows, "do not match|named once"),
        (data.inputs[:3], rows[:5], "do not match"),
    ):
        with pytest.raises(UltronInputError, match=match):
            replace(data, inputs=inputs, input_rows=input_rows)
