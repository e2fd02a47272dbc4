"""The one training loop (:func:`ultron.train.loop.run_training`): the step it takes, the
learning-rate schedule, cadence, progress, hooks, non-finite losses, resumption, and that
scalars are read only when reported."""

from __future__ import annotations

import math

import pytest
import torch

from ultron.errors import UltronInputError
from ultron.train.loop import descend, is_log_step, run_training


class Counted:
    """A scalar that counts how often it is read as a float."""

    reads = 0

    def __init__(self, value: float) -> None:
        self.value = value

    def __float__(self) -> float:
        Counted.reads += 1
        return self.value


def _toy() -> tuple[torch.nn.Parameter, torch.optim.Optimizer]:
    weight = torch.nn.Parameter(torch.zeros(1))
    return weight, torch.optim.SGD([weight], lr=1.0)


def _objective(weight: torch.nn.Parameter, scalars=lambda k: {"loss": 1.0}):
    """Loss = weight (gradient 1): plain SGD moves the weight by −lr each update."""
    return lambda k: (weight.sum(), scalars(k))


def test_the_loop_takes_each_step_at_the_scheduled_rate():
    weight, optimiser = _toy()
    seen_lr, reports = [], []

    def scalars(k: int) -> dict:
        seen_lr.append(optimiser.param_groups[0]["lr"])
        return {"loss": torch.tensor(float(k)), "other": 2.0 * k}

    log = run_training(
        _objective(weight, scalars), 12, name="toy", log_every=5, learning_rate=lambda k: 0.5**k,
        optimizers=[optimiser], progress=reports.append, stage={"stage": "s1"},
    )  # fmt: skip
    assert seen_lr == [0.5**k for k in range(12)]  # the rate of update k while it runs
    # every update took one SGD step of −rate (the gradient of the weight is 1)
    assert weight.item() == pytest.approx(-sum(0.5**k for k in range(12)), abs=1e-12)
    assert [e["step"] for e in log] == [1, 5, 10, 12]  # first, every 5th, last
    assert [e["loss"] for e in log] == [0.0, 4.0, 9.0, 11.0]
    assert log[1]["other"] == 8.0 and all(e["seconds"] >= 0 for e in log)
    assert [r["step"] for r in reports] == [1, 5, 10, 12]
    assert reports[0]["iterations"] == 12 and reports[0]["stage"] == "s1"


def test_a_resumed_schedule_ignores_the_rate_the_optimiser_carries():
    weight, optimiser = _toy()
    optimiser.param_groups[0]["lr"] = 123.0  # e.g. the last rate of a loaded checkpoint
    seen = []
    run_training(
        _objective(weight, lambda k: seen.append(optimiser.param_groups[0]["lr"]) or {}),
        6, name="toy", log_every=10, start=3, learning_rate=lambda k: 0.1 * k,
        optimizers=[optimiser],
    )  # fmt: skip
    assert seen == pytest.approx([0.3, 0.4, 0.5])
    assert weight.item() == pytest.approx(-1.2)


def test_without_a_schedule_the_optimisers_rate_stands():
    weight, optimiser = _toy()
    run_training(_objective(weight), 3, name="toy", log_every=1, optimizers=[optimiser])
    assert optimiser.param_groups[0]["lr"] == 1.0 and weight.item() == pytest.approx(-3.0)


def test_descend_clears_stale_gradients_and_steps_every_optimiser():
    a, b = torch.nn.Parameter(torch.ones(1)), torch.nn.Parameter(torch.ones(1))
    optimisers = [torch.optim.SGD([a], lr=0.5), torch.optim.SGD([b], lr=0.25)]
    a.grad, b.grad = torch.full((1,), 100.0), torch.full((1,), 100.0)  # stale: must not add up
    descend(optimisers, (2 * a + 4 * b).sum())
    assert a.item() == pytest.approx(0.0) and b.item() == pytest.approx(0.0)


def test_scalars_are_read_only_at_reported_updates():
    weight, optimiser = _toy()
    Counted.reads = 0
    objective = _objective(weight, lambda k: {"loss": Counted(1.0)})
    run_training(objective, 100, name="toy", log_every=50, optimizers=[optimiser])
    assert Counted.reads == 3  # updates 1, 50 and 100
    Counted.reads = 0
    run_training(objective, 10, name="toy", log_every=50, every_update=True, optimizers=[optimiser])
    assert Counted.reads == 10


def test_hooks_resumption_and_every_update():
    weight, optimiser = _toy()
    kept_by_hook, after = [], []

    def on_entry(entry: dict) -> bool:
        kept_by_hook.append(entry["step"])
        return entry["step"] == 7  # e.g. a held-out check at update 7

    previous = [{"step": 4, "loss": 1.0}]
    log = run_training(
        _objective(weight), 10, name="toy", log_every=4, start=4, every_update=True,
        on_entry=on_entry, after_update=after.append, log=previous, optimizers=[optimiser],
    )  # fmt: skip
    assert log is previous
    assert [e["step"] for e in log] == [4, 7, 8, 10]  # resumed: updates 5 … 10
    assert kept_by_hook == [5, 6, 7, 8, 9, 10] and after == [5, 6, 7, 8, 9, 10]
    assert is_log_step(1, 10, 4) and is_log_step(10, 10, 4) and not is_log_step(5, 10, 4)


def test_a_non_finite_loss_names_the_fit_and_the_update():
    weight, optimiser = _toy()
    objective = _objective(weight, lambda k: {"loss": math.nan if k >= 2 else 1.0})
    with pytest.raises(FloatingPointError, match="occupancy loss became nan at update 5"):
        run_training(objective, 20, name="occupancy", log_every=5, optimizers=[optimiser])


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [({"iterations": -1}, "iterations"), ({"log_every": 0}, "log_every"),
     ({"iterations": 2.5}, "iterations"), ({"log_every": True}, "log_every"),
     ({"optimizers": []}, "optimizers")],
)  # fmt: skip
def test_bad_arguments(kwargs: dict, name: str):
    weight, optimiser = _toy()
    arguments = {"iterations": 3, "log_every": 1, "optimizers": [optimiser]} | kwargs
    with pytest.raises(UltronInputError, match=name):
        run_training(_objective(weight), arguments.pop("iterations"), name="toy", **arguments)
