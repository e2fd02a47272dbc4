"""The one training loop of every fit (acoustic field, occupancy, RoCoSDF's SDFs).

:func:`run_training` performs updates ``start … iterations − 1`` of a fit: before update k
(0-based) it sets every parameter group's learning rate to ``learning_rate(k)`` (when the fit
schedules it so; a fit may instead step a torch scheduler inside its update), calls
``update(k)`` — the fit's own batch, loss, backward pass and optimiser step, returning its
scalars (tensors or floats, ``loss`` among them) — and, at the *reported* updates, makes an
entry ``{"step": n, **scalars, "seconds": s}`` with n = k + 1 the updates done and s the
seconds since the loop began. The scalars become Python floats only then, so an accelerator
is not synchronised at every update. An entry's ``loss`` must be finite
(:class:`FloatingPointError` naming the fit and the update otherwise).

Reported updates: every one when ``every_update`` (a progress bar that moves each step),
else the first, every ``log_every``-th and the last. The log keeps the first, every
``log_every``-th and the last entry, and any entry that ``on_entry`` (the fit's hook, e.g.
a held-out check) marks by returning True; ``after_update`` runs after every update (e.g. a
checkpoint). ``progress``, the one progress signature of every fit, receives
``{"iterations": N, **stage, **entry}`` for each reported update. Random draws belong to the
fit: its ``update`` draws from its own seeded generators, never from torch's global state.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import torch

from ultron.errors import argument_error

#: The progress callback of every fit: one dict per reported update (module doc).
Progress = Callable[[dict[str, Any]], None]


def set_learning_rate(optimizers: Iterable[torch.optim.Optimizer], rate: float) -> None:
    """Set the learning rate of every parameter group of ``optimizers`` to ``rate``."""
    for optimizer in optimizers:
        for group in optimizer.param_groups:
            group["lr"] = rate


def is_log_step(done: int, iterations: int, log_every: int) -> bool:
    """Whether the log keeps the entry after ``done`` updates: the first, every
    ``log_every``-th and the last."""
    return done == 1 or done % log_every == 0 or done == iterations


def run_training(
    update: Callable[[int], Mapping[str, torch.Tensor | float]],
    iterations: int,
    *,
    name: str,
    log_every: int,
    start: int = 0,
    learning_rate: Callable[[int], float] | None = None,
    optimizers: Iterable[torch.optim.Optimizer] = (),
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
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 0:
        raise argument_error("iterations", f"expected an integer ≥ 0, got {iterations!r}")
    if isinstance(log_every, bool) or not isinstance(log_every, int) or log_every < 1:
        raise argument_error("log_every", f"expected an integer ≥ 1, got {log_every!r}")
    optimizers = list(optimizers)
    extra = dict(stage or {})
    log = [] if log is None else log
    started = time.perf_counter()
    for k in range(start, iterations):
        if learning_rate is not None:
            set_learning_rate(optimizers, learning_rate(k))
        scalars = update(k)
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
