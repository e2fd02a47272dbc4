"""Checkpoints of a fit that runs after the field — the occupancy fit of stage 2
(:func:`ultron.train.occupancy.fit_occupancy`) and RoCoSDF's SDF fits
(:mod:`ultron.train.neural_pull`) — so that an interrupted ``reconstruct`` resumes each fit
where it stopped and ends bit for bit where an uninterrupted run ends.

A checkpoint is one file, a ``torch.save`` of plain data (read with ``weights_only=True``)::

    {"format": FORMAT, "fingerprint": hex, "step": n, "iterations": N,
     "modules": [state, …], "optimizers": [state, …], "generator": state,
     "batches": [{"order": permutation or None, "cursor": c}, …], "log": [entries]}

written atomically (:mod:`ultron.atomic`) every ``every`` updates and after the last one.
``fingerprint`` is a SHA-256 digest of everything that decides the fit
(:func:`fit_fingerprint`): for the occupancy fit its training data's tensors, settings, initial
network, trained parameters and anchor; for an SDF fit its samples, settings, initial networks
and generator. A fit resumes only a checkpoint whose fingerprint is its own; any other file at
the path — another fit's (other labels, field, seed or settings), an older format, an unreadable
one — is ignored and overwritten at the first save, so a stale checkpoint can never change a
result, only fail to save time.
"""

from __future__ import annotations

import hashlib
import io
import json
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from ultron import atomic
from ultron.arguments import check_integer
from ultron.device import cpu_state

#: Names the file's layout (bumped when it changes; another format is never resumed).
FORMAT = "ultron-fit-checkpoint/1"
#: Updates between two checkpoints of a fit (and one after its last update).
CHECKPOINT_EVERY = 250
#: The occupancy fit's name: its checkpoint file in a method's checkpoint directory
#: (:func:`checkpoint_in`) and its key in run.json's ``resumed_from_step``.
OCCUPANCY_FIT = "occupancy"


class MinibatchOrder:
    """Index batches of ``batch_size`` (at most n) from random permutations of n drawn from
    ``generator``: a new permutation when the current one has fewer than ``batch_size`` left
    (the first drawn at the first batch). Its state — the permutation and the cursor — goes
    into a checkpoint, so that a resumed fit draws the batches an uninterrupted one draws."""

    def __init__(self, n: int, batch_size: int, generator: torch.Generator) -> None:
        check_integer("n", n, 1)
        check_integer("batch_size", batch_size, 1)
        self.n, self.batch_size, self.generator = n, batch_size, generator
        self.order: torch.Tensor | None = None
        self.cursor = 0

    def __iter__(self) -> MinibatchOrder:
        return self

    def __next__(self) -> torch.Tensor:
        if self.order is None:
            self.order, self.cursor = torch.randperm(self.n, generator=self.generator), 0
        if self.cursor + self.batch_size > self.n:
            self.order, self.cursor = torch.randperm(self.n, generator=self.generator), 0
        batch = self.order[self.cursor : self.cursor + min(self.batch_size, self.n)]
        self.cursor += self.batch_size
        return batch

    def state(self) -> dict[str, Any]:
        """The permutation (None before the first batch; 32-bit where n allows, half the
        file) and the cursor."""
        order = self.order
        if order is not None and self.n <= torch.iinfo(torch.int32).max:
            order = order.to(torch.int32)
        return {"order": order, "cursor": self.cursor}

    def restore(self, state: Mapping[str, Any]) -> None:
        """Continue from :meth:`state`'s result."""
        order = state["order"]
        if order is not None:
            if tuple(order.shape) != (self.n,):
                raise ValueError(f"a permutation of {tuple(order.shape)}, expected ({self.n},)")
            order = order.to(torch.int64)  # randperm's dtype: the same indices, exactly
        self.order, self.cursor = order, int(state["cursor"])


def fit_fingerprint(tensors: Iterable[torch.Tensor], settings: Mapping[str, Any]) -> str:
    """SHA-256 (hex) of ``settings`` (as sorted JSON) and of each tensor's shape, dtype and
    bytes, in order: equal only for the same fit."""
    digest = hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode())
    for tensor in tensors:
        values = tensor.detach().cpu().contiguous()
        digest.update(f"{tuple(values.shape)} {values.dtype};".encode())
        digest.update(memoryview(values.numpy()).cast("B"))
    return digest.hexdigest()


@dataclass
class FitCheckpoint:
    """Where a fit keeps its checkpoint (``path``) and how often (``every`` updates); the fit
    sets ``resumed_from`` to the step it resumed at (None: it started afresh)."""

    path: Path
    every: int = CHECKPOINT_EVERY
    resumed_from: int | None = None

    def __post_init__(self) -> None:
        self.path = Path(self.path)
        check_integer("every", self.every, 1)

    def matching(self, fingerprint: str, iterations: int) -> dict[str, Any] | None:
        """The checkpoint at ``path`` if it is this fit's (``fingerprint``) and within its
        ``iterations``; None otherwise (module doc: never an error)."""
        try:
            data = self.path.read_bytes()
            state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
        except Exception:  # missing, unreadable or foreign: the fit starts afresh
            return None
        if not isinstance(state, dict) or state.get("format") != FORMAT:
            return None
        if state.get("fingerprint") != fingerprint or state.get("iterations") != iterations:
            return None
        step = state.get("step")
        return state if isinstance(step, int) and 0 < step <= iterations else None

    def save(self, fingerprint: str, step: int, iterations: int, fit: FitState) -> None:
        """Write ``fit``'s state after ``step`` of ``iterations`` updates (CPU tensors, so that
        it resumes on any device)."""
        state = {
            "format": FORMAT,
            "fingerprint": fingerprint,
            "step": step,
            "iterations": iterations,
            "modules": [cpu_state(m.state_dict()) for m in fit.modules],
            "optimizers": [cpu_state(o.state_dict()) for o in fit.optimizers],
            "generator": fit.generator.get_state(),
            "batches": [b.state() for b in fit.batches],
            "log": fit.log,
        }
        buffer = io.BytesIO()
        torch.save(state, buffer)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        atomic.write_bytes(self.path, buffer.getvalue())


def checkpoint_in(directory: Path | None, name: str) -> FitCheckpoint | None:
    """The checkpoint of the fit called ``name`` in a method's checkpoint ``directory``
    (``directory/name.pt``); None without a directory (a fit that keeps none)."""
    return None if directory is None else FitCheckpoint(Path(directory) / f"{name}.pt")


@dataclass
class FitState:
    """What a fit's checkpoint holds: its networks, optimisers, the CPU generator its draws
    come from, its minibatch orders (none where each batch is drawn afresh) and its log so far
    (the list :func:`~ultron.train.loop.run_training` appends to)."""

    modules: Sequence[torch.nn.Module]
    optimizers: Sequence[torch.optim.Optimizer]
    generator: torch.Generator
    batches: Sequence[MinibatchOrder] = ()
    log: list[dict[str, Any]] = field(default_factory=list)

    def restore(self, state: Mapping[str, Any]) -> int:
        """Load :meth:`FitCheckpoint.save`'s ``state``; returns the step to continue from."""
        pairs = ((self.modules, "modules"), (self.optimizers, "optimizers"),
                 (self.batches, "batches"))  # fmt: skip
        for objects, key in pairs:
            if len(objects) != len(state[key]):
                raise ValueError(f"{len(state[key])} {key} saved, {len(objects)} in the fit")
        for module, saved in zip(self.modules, state["modules"], strict=True):
            module.load_state_dict(saved)
        for optimizer, saved in zip(self.optimizers, state["optimizers"], strict=True):
            optimizer.load_state_dict(saved)
        for order, saved in zip(self.batches, state["batches"], strict=True):
            order.restore(saved)
        self.generator.set_state(state["generator"])
        self.log[:] = list(state["log"])
        return int(state["step"])


def resumable(
    checkpoint: FitCheckpoint | None,
    fingerprint: Callable[[], str],
    iterations: int,
    fit: FitState,
) -> tuple[int, Callable[[int], None] | None]:
    """For :func:`~ultron.train.loop.run_training`: the update to start from and its
    ``after_update``. With a ``checkpoint`` of this fit (``fingerprint()``, computed only when
    there is a checkpoint: it hashes the fit's data) ``fit`` is restored from it and
    ``checkpoint.resumed_from`` set; ``after_update`` saves every ``checkpoint.every`` updates
    and after the last. Without one: (0, None)."""
    if checkpoint is None:
        return 0, None
    start, fingerprint = 0, fingerprint()
    state = checkpoint.matching(fingerprint, iterations)
    if state is not None:  # this fit's own: restoring it cannot fail but by a bug
        start = checkpoint.resumed_from = fit.restore(state)

    def after_update(done: int) -> None:  # the log grows in place: saved with the state
        if done % checkpoint.every == 0 or done == iterations:
            checkpoint.save(fingerprint, done, iterations, fit)

    return start, after_update


def resumed_steps(checkpoints: Mapping[str, FitCheckpoint | None]) -> dict[str, dict[str, int]]:
    """run.json's record of the fits (by name) that resumed from a checkpoint:
    ``{"resumed_from_step": {name: step}}``; empty when none did, so that such a run's
    run.json is the one before checkpoints."""
    steps = {
        name: int(c.resumed_from)
        for name, c in checkpoints.items()
        if c is not None and c.resumed_from is not None
    }
    return {"resumed_from_step": steps} if steps else {}
