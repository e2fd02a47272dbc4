"""Checkpoints of a fit: an occupancy or SDF fit interrupted and resumed ends bit for bit where
an uninterrupted one ends; a checkpoint of another fit, or a damaged one, is never resumed."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace

import pytest
import torch

from conftest import SMALL_OCCUPANCY, random_occupancy_data
from ultron.errors import UltronInputError
from ultron.fields.occupancy import OccupancyNetwork, OccupancyNetworkConfig
from ultron.train.fit_checkpoint import (
    FitCheckpoint,
    MinibatchOrder,
    fit_fingerprint,
)
from ultron.train.occupancy import (
    OccupancyAnchor,
    OccupancyTrainConfig,
    OccupancyTrainingData,
    fit_occupancy,
)

SMALL = OccupancyNetworkConfig(**SMALL_OCCUPANCY)
CONFIG = OccupancyTrainConfig(iters=120, batch_size=64, lr=1e-3, seed=3, network=SMALL)


def _data(n: int = 1000, seed: int = 0) -> OccupancyTrainingData:
    return random_occupancy_data(n, seed)


def _reference_batches(n: int, batch_size: int, generator: torch.Generator) -> Iterator:
    """The minibatch draw as the fit made it before checkpoints (a generator function)."""
    order = torch.randperm(n, generator=generator)
    cursor = 0
    while True:
        if cursor + batch_size > n:
            order = torch.randperm(n, generator=generator)
            cursor = 0
        yield order[cursor : cursor + min(batch_size, n)]
        cursor += batch_size


def _same_fit(a: tuple, b: tuple) -> None:
    """Two fits' networks equal bit for bit, and their logs but for the seconds."""
    (net_a, log_a), (net_b, log_b) = a, b
    for (name, x), y in zip(net_a.state_dict().items(), net_b.state_dict().values(), strict=True):
        assert torch.equal(x, y), name
    strip = [{k: v for k, v in e.items() if k != "seconds"} for e in log_a]
    assert strip == [{k: v for k, v in e.items() if k != "seconds"} for e in log_b]


class Interrupted(Exception):
    pass


def _interrupt_after(step: int):
    def progress(entry: dict) -> None:
        if entry["step"] >= step:
            raise Interrupted

    return progress


def test_minibatches_cover_each_permutation_before_the_next():
    batches = MinibatchOrder(10, 4, torch.Generator().manual_seed(0))
    first, second, third = next(batches), next(batches), next(batches)
    assert torch.cat([first, second]).unique().numel() == 8  # one permutation, no repeats
    assert third.numel() == 4  # 2 left < 4: a new permutation
    assert next(MinibatchOrder(3, 8, torch.Generator())).sort().values.tolist() == [0, 1, 2]


@pytest.mark.parametrize(("n", "batch_size"), [(10, 4), (10, 5), (3, 8), (7, 7)])
def test_minibatches_draw_what_the_generator_function_drew(n, batch_size):
    ours = MinibatchOrder(n, batch_size, torch.Generator().manual_seed(5))
    reference = _reference_batches(n, batch_size, torch.Generator().manual_seed(5))
    for _ in range(12):
        assert torch.equal(next(ours), next(reference))


def test_minibatch_state_continues_the_draw():
    generator = torch.Generator().manual_seed(1)
    batches = MinibatchOrder(10, 4, generator)
    for _ in range(3):
        next(batches)
    state, generator_state = batches.state(), generator.get_state()
    expected = [next(batches) for _ in range(5)]
    resumed_generator = torch.Generator()
    resumed_generator.set_state(generator_state)
    resumed = MinibatchOrder(10, 4, resumed_generator)
    resumed.restore(state)
    assert all(torch.equal(next(resumed), e) for e in expected)
    with pytest.raises(ValueError, match="permutation"):
        MinibatchOrder(9, 4, generator).restore(state)


def test_minibatch_order_refuses_bad_sizes():
    with pytest.raises(UltronInputError, match="batch_size"):
        MinibatchOrder(10, 0, torch.Generator())
    with pytest.raises(UltronInputError, match="n"):
        MinibatchOrder(0, 4, torch.Generator())


def test_fingerprint_sees_every_tensor_and_setting():
    a, b = torch.arange(6.0), torch.arange(6.0).reshape(2, 3)
    base = fit_fingerprint([a], {"x": 1})
    assert base == fit_fingerprint([a.clone()], {"x": 1})
    assert base != fit_fingerprint([b], {"x": 1})  # same bytes, another shape
    assert base != fit_fingerprint([a.to(torch.float64)], {"x": 1})
    assert base != fit_fingerprint([a + 1e-6], {"x": 1})
    assert base != fit_fingerprint([a], {"x": 2})


def test_a_checkpointed_fit_is_the_plain_fit(tmp_path):
    checkpoint = FitCheckpoint(tmp_path / "occupancy.pt", every=50)
    _same_fit(fit_occupancy(_data(), CONFIG), fit_occupancy(_data(), CONFIG, checkpoint=checkpoint))
    assert checkpoint.resumed_from is None
    assert checkpoint.path.is_file()


@pytest.mark.parametrize("anchored", [False, True])
def test_an_interrupted_fit_resumes_bit_for_bit(tmp_path, anchored):
    anchor = None
    if anchored:
        points = torch.rand(300, 3, generator=torch.Generator().manual_seed(9))
        anchor = OccupancyAnchor(points, (points[:, 1] > 0).float(), weight=0.5)
    uninterrupted = fit_occupancy(_data(), CONFIG, anchor=anchor)
    path = tmp_path / "occupancy.pt"
    with pytest.raises(Interrupted):  # dies at update 100 (reported), saved at 25, 50 and 75
        fit_occupancy(
            _data(), CONFIG, anchor=anchor, checkpoint=FitCheckpoint(path, every=25),
            progress=_interrupt_after(75),
        )  # fmt: skip
    checkpoint = FitCheckpoint(path, every=25)
    resumed = fit_occupancy(_data(), CONFIG, anchor=anchor, checkpoint=checkpoint)
    assert checkpoint.resumed_from == 75
    _same_fit(uninterrupted, resumed)


def test_a_finished_checkpoint_skips_the_updates(tmp_path):
    path = tmp_path / "occupancy.pt"
    first = fit_occupancy(_data(), CONFIG, checkpoint=FitCheckpoint(path))
    checkpoint = FitCheckpoint(path)
    reports: list[dict] = []
    again = fit_occupancy(_data(), CONFIG, checkpoint=checkpoint, progress=reports.append)
    assert checkpoint.resumed_from == CONFIG.iters and reports == []
    _same_fit(first, again)


def test_a_fine_tuned_fit_resumes_with_its_frozen_layers(tmp_path):
    def frozen_last_two(network: OccupancyNetwork) -> list[torch.nn.Parameter]:
        last = {id(p) for layer in network.last_layers(2) for p in layer.parameters()}
        return [p for p in network.parameters() if id(p) not in last]

    def start() -> OccupancyNetwork:
        torch.manual_seed(4)
        return OccupancyNetwork(OccupancyNetworkConfig(**{**SMALL.__dict__, "in_dim": 3}))

    uninterrupted = fit_occupancy(_data(), CONFIG, start(), frozen_last_two)
    path = tmp_path / "occupancy.pt"
    with pytest.raises(Interrupted):
        fit_occupancy(_data(), CONFIG, start(), frozen_last_two,
                      checkpoint=FitCheckpoint(path, every=40),
                      progress=_interrupt_after(100))  # fmt: skip
    checkpoint = FitCheckpoint(path, every=40)
    resumed = fit_occupancy(_data(), CONFIG, start(), frozen_last_two, checkpoint=checkpoint)
    assert checkpoint.resumed_from == 80  # died at update 100, saved at 40 and 80
    _same_fit(uninterrupted, resumed)


@pytest.mark.parametrize(
    "other",
    [
        {"data": _data(seed=1)},  # other labels or field
        {"config": OccupancyTrainConfig(**{**CONFIG.__dict__, "seed": 4})},
        {"config": OccupancyTrainConfig(**{**CONFIG.__dict__, "iters": 200})},
        {"trainable": lambda network: list(network.parameters())[:2]},
    ],
)
def test_another_fits_checkpoint_is_not_resumed(tmp_path, other):
    path = tmp_path / "occupancy.pt"
    fit_occupancy(_data(), CONFIG, checkpoint=FitCheckpoint(path))
    data, config = other.get("data", _data()), other.get("config", CONFIG)
    trainable = other.get("trainable")
    checkpoint = FitCheckpoint(path)
    resumed = fit_occupancy(data, config, trainable=trainable, checkpoint=checkpoint)
    assert checkpoint.resumed_from is None
    _same_fit(fit_occupancy(data, config, trainable=trainable), resumed)


def test_the_in_front_mask_decides_resumption_only_where_the_fit_reads_it(tmp_path):
    # the default negatives never read data.in_front: its checkpoint resumes with or without
    # the mask (a run.json diagnostic); the "front" negatives read it, so a changed mask refits
    plain = _data()
    front = plain.labels == 0

    def with_mask(mask: torch.Tensor) -> OccupancyTrainingData:
        return OccupancyTrainingData(plain.inputs, plain.transmission, plain.labels, in_front=mask)

    for config, data, resumes in (
        (CONFIG, with_mask(front), True),
        (replace(CONFIG, negatives="front"), with_mask(~front), False),
    ):
        path = tmp_path / f"{config.negatives}.pt"
        first = with_mask(front) if config.negatives == "front" else plain
        fit_occupancy(first, config, checkpoint=FitCheckpoint(path))
        checkpoint = FitCheckpoint(path)
        fit_occupancy(data, config, checkpoint=checkpoint)
        assert (checkpoint.resumed_from is not None) is resumes, config.negatives


@pytest.mark.parametrize("content", [b"", b"not a checkpoint", None])
def test_a_damaged_or_foreign_file_is_fitted_over(tmp_path, content):
    path = tmp_path / "occupancy.pt"
    if content is None:  # a readable file of another format
        torch.save({"format": "something-else/1", "step": 10}, path)
    else:
        path.write_bytes(content)
    checkpoint = FitCheckpoint(path)
    _same_fit(fit_occupancy(_data(), CONFIG), fit_occupancy(_data(), CONFIG, checkpoint=checkpoint))
    assert checkpoint.resumed_from is None
    assert FitCheckpoint(path).matching("x", CONFIG.iters) is None  # overwritten: ours now


def test_checkpoint_refuses_a_bad_interval(tmp_path):
    with pytest.raises(UltronInputError, match="every"):
        FitCheckpoint(tmp_path / "c.pt", every=0)
