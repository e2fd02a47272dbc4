"""The one training loop of every fit (acoustic field, occupancy, RoCoSDF's SDFs).

:func:`run_training` performs updates ``start … iterations − 1`` of a fit. Update k (0-based)
calls ``objective(k)`` — the fit's own batch and loss — which returns the loss to minimise and
the scalars to report (tensors or floats, ``loss`` among them); the loop then takes the step
(:func:`descend`: zero the gradients, back-propagate, step every optimiser) and advances the
learning-rate schedule. ``learning_rate(k)``, when given, is the rate of every parameter group
at update k, applied through :class:`torch.optim.lr_scheduler.LambdaLR` (a function of k
alone, so a run resumed at ``start`` takes exactly the rates of an uninterrupted one). At the
*reported* updates the loop makes an entry ``{"step": n, **scalars, "seconds": s}`` with
n = k + 1 the updates done and s the seconds since the loop began. The scalars become Python
floats only then, so an accelerator is not synchronised at every update. An entry's ``loss``
must be finite (:class:`FloatingPointError` naming the fit and the update otherwise).

Reported updates: every one when ``every_update`` (a progress bar that moves each step),
else the first, every ``log_every``-th and the last. The log keeps the first, every
``log_every``-th and the last entry, and any entry that ``on_entry`` (the fit's hook, e.g.
a held-out check) marks by returning True; ``after_update`` runs after every update (e.g. a
checkpoint). ``progress``, the one progress signature of every fit, receives
``{"iterations": N, **stage, **entry}`` for each reported update. Random draws belong to the
fit: its ``objective`` draws from its own seeded generators, never from torch's global state.
The updates run with freed memory kept for reuse (:func:`ultron.memory.freed_memory_reused`):
each allocates the same blocks as the one before.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import torch

from ultron.arguments import check_integer
from ultron.errors import argument_error
from ultron.memory import freed_memory_reused

#: The progress callback of every fit: one dict per reported update (module doc).
Progress = Callable[[dict[str, Any]], None]
#: Update k's loss to minimise and the scalars to report (module doc).
Objective = Callable[[int], tuple[torch.Tensor, Mapping[str, torch.Tensor | float]]]


def descend(optimizers: Sequence[torch.optim.Optimizer], loss: torch.Tensor) -> None:
    """One gradient step on ``loss``: every optimiser's gradients set to None, ∂loss/∂θ
    back-propagated, every optimiser stepped."""
    for optimizer in optimizers:
        optimizer.zero_grad(set_to_none=True)
    loss.backward()
    for optimizer in optimizers:
        optimizer.step()


def rate_schedules(
    optimizers: Sequence[torch.optim.Optimizer], learning_rate: Callable[[int], float], start: int
) -> list[torch.optim.lr_scheduler.LambdaLR]:
    """One :class:`~torch.optim.lr_scheduler.LambdaLR` per optimiser giving every parameter
    group the rate ``learning_rate(k)`` at update k, positioned at update ``start``. Its base
    rate is set to 1 (LambdaLR's rate is base · λ(k), exactly λ(k) then), so the schedule does
    not depend on the rate a resumed optimiser's state carries."""
    schedules = []
    for optimizer in optimizers:
        for group in optimizer.param_groups:
            group["initial_lr"] = 1.0
        schedules.append(
            torch.optim.lr_scheduler.LambdaLR(optimizer, learning_rate, last_epoch=start - 1)
        )
    return schedules


def is_log_step(done: int, iterations: int, log_every: int) -> bool:
    """Whether the log keeps the entry after ``done`` updates: the first, every
    ``log_every``-th and the last."""
    return done == 1 or done % log_every == 0 or done == iterations


def run_training(
    objective: Objective,
    iterations: int,
    *,
    name: str,
    log_every: int,
    optimizers: Iterable[torch.optim.Optimizer],
    start: int = 0,
    learning_rate: Callable[[int], float] | None = None,
    progress: Progress | None = None,
    every_update: bool = False,
    on_entry: Callable[[dict[str, Any]], bool] | None = None,
    after_update: Callable[[int], None] | None = None,
    stage: Mapping[str, Any] | None = None,
    log: list[dict[str, Any]] | None = None,
) -> list[dict[str, Any]]:
    """Run updates ``start`` … ``iterations − 1`` of the fit called ``name`` (module doc) and
    return the log: ``log`` (e.g. a resumed fit's entries so far) with the new entries
    appended. ``after_update(n)`` runs after each update, once its entry is logged (e.g. to
    save a checkpoint that holds the log)."""
    check_integer("iterations", iterations)
    check_integer("log_every", log_every, 1)
    optimizers = list(optimizers)
    if not optimizers:
        raise argument_error("optimizers", "expected at least one optimiser to step")
    schedules = [] if learning_rate is None else rate_schedules(optimizers, learning_rate, start)
    extra = dict(stage or {})
    log = [] if log is None else log
    started = time.perf_counter()
    with freed_memory_reused():  # each update allocates the same blocks again
        for k in range(start, iterations):
            loss, scalars = objective(k)
            descend(optimizers, loss)
            for schedule in schedules:
                schedule.step()
            done = k + 1
            keep = is_log_step(done, iterations, log_every)
            if keep or every_update:
                entry = _entry(scalars, done, started, name)
                if on_entry is not None and on_entry(entry):
                    keep = True
                if keep:
                    log.append(entry)
                if progress is not None:
                    progress({"iterations": iterations, **extra, **entry})
            if after_update is not None:
                after_update(done)
    return log


def _entry(
    scalars: Mapping[str, torch.Tensor | float], done: int, started: float, name: str
) -> dict[str, Any]:
    """The entry of update ``done``: its scalars as floats, ``loss`` checked to be finite."""
    entry = {"step": done, **{key: float(value) for key, value in scalars.items()}}
    entry["seconds"] = time.perf_counter() - started
    if not math.isfinite(entry.get("loss", 0.0)):
        raise FloatingPointError(f"{name} loss became {entry['loss']} at update {done}")
    return entry
