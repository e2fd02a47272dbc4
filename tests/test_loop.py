"""The one training loop (:func:`ultron.train.loop.run_training`): cadence, learning rate,
progress, hooks, non-finite losses, resumption, and that scalars are read only when reported."""

from __future__ import annotations

import math

import pytest
import torch

from ultron.errors import UltronInputError
from ultron.train.loop import is_log_step, run_training


class Counted:
    """A scalar that counts how often it is read as a float."""

    reads = 0

    def __init__(self, value: float) -> None:
        self.value = value

    def __float__(self) -> float:
        Counted.reads += 1
        return self.value


def _optimiser() -> torch.optim.Optimizer:
    return torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=1.0)


def test_cadence_learning_rate_and_progress():
    optimiser = _optimiser()
    seen_lr, reports = [], []

    def update(k: int) -> dict:
        seen_lr.append(optimiser.param_groups[0]["lr"])
        return {"loss": torch.tensor(float(k)), "other": 2.0 * k}

    log = run_training(
        update, 12, name="toy", log_every=5, learning_rate=lambda k: 0.5**k,
        optimizers=[optimiser], progress=reports.append, stage={"stage": "s1"},
    )  # fmt: skip
    assert seen_lr == [0.5**k for k in range(12)]  # set before each update
    assert [e["step"] for e in log] == [1, 5, 10, 12]  # first, every 5th, last
    assert [e["loss"] for e in log] == [0.0, 4.0, 9.0, 11.0]
    assert log[1]["other"] == 8.0 and all(e["seconds"] >= 0 for e in log)
    assert [r["step"] for r in reports] == [1, 5, 10, 12]
    assert reports[0]["iterations"] == 12 and reports[0]["stage"] == "s1"


def test_scalars_are_read_only_at_reported_updates():
    Counted.reads = 0
    run_training(lambda k: {"loss": Counted(1.0)}, 100, name="toy", log_every=50)
    assert Counted.reads == 3  # updates 1, 50 and 100
    Counted.reads = 0
    run_training(lambda k: {"loss": Counted(1.0)}, 10, name="toy", log_every=50, every_update=True)
    assert Counted.reads == 10


def test_hooks_resumption_and_every_update():
    kept_by_hook, after = [], []

    def on_entry(entry: dict) -> bool:
        kept_by_hook.append(entry["step"])
        return entry["step"] == 7  # e.g. a held-out check at update 7

    previous = [{"step": 4, "loss": 1.0}]
    log = run_training(
        lambda k: {"loss": 1.0}, 10, name="toy", log_every=4, start=4, every_update=True,
        on_entry=on_entry, after_update=after.append, log=previous,
    )  # fmt: skip
    assert log is previous
    assert [e["step"] for e in log] == [4, 7, 8, 10]  # resumed: updates 5 … 10
    assert kept_by_hook == [5, 6, 7, 8, 9, 10] and after == [5, 6, 7, 8, 9, 10]
    assert is_log_step(1, 10, 4) and is_log_step(10, 10, 4) and not is_log_step(5, 10, 4)


def test_a_non_finite_loss_names_the_fit_and_the_update():
    def update(k: int) -> dict:
        return {"loss": math.nan if k >= 2 else 1.0}

    with pytest.raises(FloatingPointError, match="occupancy loss became nan at update 5"):
        run_training(update, 20, name="occupancy", log_every=5)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [({"iterations": -1}, "iterations"), ({"log_every": 0}, "log_every"),
     ({"iterations": 2.5}, "iterations"), ({"log_every": True}, "log_every")],
)  # fmt: skip
def test_bad_arguments(kwargs: dict, name: str):
    arguments = {"iterations": 3, "log_every": 1} | kwargs
    with pytest.raises(UltronInputError, match=name):
        run_training(lambda k: {"loss": 0.0}, arguments.pop("iterations"), name="toy", **arguments)
