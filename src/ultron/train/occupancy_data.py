"""The data stage 2 fits on (:mod:`ultron.train.occupancy`): per labelled pixel its input g(x),
transmission T and label, and the anchor of a fine-tune; and which of the pixels a fit reads.

A fit of ``iters`` minibatches of ``batch_size`` reads at most iters·batch_size pixels (plus
:func:`label_loss_pick`'s); a long recording with every frame labelled can hold more.
:func:`rows_read` replays the fit's seeded draws, so that g(x) — the stage's dearest part, a
field query per pixel and stencil neighbour — is computed only for the pixels the fit reads
(``input_rows``): the fit draws the same batches and sees the same inputs as with every
pixel's, up to the last bits of the field's batched query (docs/decisions.md, "Stage 2's
inputs only where the fit reads them").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from ultron.arguments import check_count
from ultron.errors import argument_error
from ultron.train.fit_checkpoint import MinibatchOrder
from ultron.train.visibility import transmission_summary

#: At most this many labelled pixels (evenly strided) score
#: :func:`~ultron.train.occupancy.label_loss`.
LABEL_LOSS_POINTS = 2**18


@dataclass(frozen=True)
class OccupancyTrainingData:
    """Precomputed per-pixel inputs (P, D), transmission T (P,) and labels y (P,) ∈ {0, 1};
    ``labelled_shadow`` (P,) bool, when given, marks the pixels in the labels' own shadow
    (:func:`ultron.train.visibility.in_labelled_shadow`) — a diagnostic the fit does not read;
    ``in_front`` (P,) bool, when given, the background labels in front of their scanline's
    first bone label (:meth:`~ultron.data.labels.LabelledPixels.in_front_of_bone`), which the
    ``front`` negatives count whatever T says (:data:`~ultron.train.occupancy.NEGATIVES`).

    ``input_rows`` (P,) int64, when given, holds each pixel's row of ``inputs`` (K, D), −1 for
    a pixel whose input was not computed (:func:`rows_read`); None: ``inputs`` has a row per
    pixel. Read the inputs through :meth:`input_index` / :meth:`inputs_at`."""

    inputs: torch.Tensor
    transmission: torch.Tensor
    labels: torch.Tensor
    labelled_shadow: torch.Tensor | None = None
    in_front: torch.Tensor | None = None
    input_rows: torch.Tensor | None = None

    def __post_init__(self) -> None:
        n = self.labels.shape[0]
        masks = {"labelled_shadow": self.labelled_shadow, "in_front": self.in_front}
        masks["input_rows"] = self.input_rows
        given = {name: mask for name, mask in masks.items() if mask is not None}
        n_inputs = n if self.input_rows is None else self.inputs.shape[0]
        if (
            self.inputs.ndim != 2
            or self.inputs.shape[0] != n_inputs
            or self.transmission.shape != (n,)
            or any(mask.shape != (n,) for mask in given.values())
        ):
            extra = "".join(f", {name} {tuple(mask.shape)}" for name, mask in given.items())
            raise argument_error(
                "training data",
                f"inputs {tuple(self.inputs.shape)}, transmission {tuple(self.transmission.shape)}"
                f"{extra} and labels {tuple(self.labels.shape)} do not match",
            )
        if self.in_front is not None and self.in_front.dtype != torch.bool:
            raise argument_error("in_front", f"expected a bool tensor, got {self.in_front.dtype}")
        if n == 0:
            raise argument_error("training data", "no labelled pixels")
        if self.input_rows is not None:
            self._check_rows(self.input_rows)

    def _check_rows(self, rows: torch.Tensor) -> None:
        """``input_rows``: int64, each −1 or a row of ``inputs``, each row named once."""
        if rows.dtype != torch.int64:
            raise argument_error("input_rows", f"expected an int64 tensor, got {rows.dtype}")
        named = rows[rows >= 0]
        n_inputs = self.inputs.shape[0]
        if bool((rows < -1).any()) or bool((named >= n_inputs).any()):
            raise argument_error("input_rows", f"expected −1 or a row in [0, {n_inputs})")
        if len(named) != n_inputs or bool((torch.bincount(named, minlength=n_inputs) != 1).any()):
            raise argument_error(
                "input_rows", f"expected each of the {n_inputs} rows of inputs named once"
            )

    def input_index(self, index: torch.Tensor) -> torch.Tensor:
        """The rows of ``inputs`` holding pixels ``index``'s inputs (``index`` itself when every
        pixel has one); an error naming the pixels whose input was not computed."""
        if self.input_rows is None:
            return index
        rows = self.input_rows[index]
        missing = rows < 0
        if bool(missing.any()):
            first = int(torch.as_tensor(index).reshape(-1)[missing.reshape(-1)][0])
            raise argument_error(
                "index",
                f"{int(missing.sum())} pixels (the first {first}) have no input computed: "
                "the data holds only the rows a fit with other settings reads (rows_read)",
            )
        return rows

    def inputs_at(self, index: torch.Tensor) -> torch.Tensor:
        """The inputs (len(index), D) of pixels ``index`` (:meth:`input_index`)."""
        return self.inputs[self.input_index(index)]

    def summary(self, observed_transmission: float) -> dict[str, Any]:
        """run.json's account of this data: its labelled and bone pixels and its transmission
        statistics (:func:`~ultron.train.visibility.transmission_summary`)."""
        summary = {
            "n_labelled_pixels": len(self.labels),
            "n_bone_pixels": int(self.labels.sum()),
            "n_inputs_computed": len(self.inputs),
            "transmission_stats": transmission_summary(
                self.transmission, self.labels, self.labelled_shadow, observed_transmission
            ),
        }
        if self.in_front is not None:  # how many the observed negatives keep against T
            dark = self.in_front & (self.transmission < observed_transmission)
            summary["n_background_in_front"] = int(self.in_front.sum())
            summary["n_background_in_front_below_threshold"] = int(dark.sum())
        return summary


@dataclass(frozen=True)
class OccupancyAnchor:
    """Inputs (Q, D) of anchor points, the occupancy targets (Q,) in [0, 1] the fit is held to
    there, and the term's weight λ ≥ 0 (module doc)."""

    inputs: torch.Tensor
    targets: torch.Tensor
    weight: float = 1.0

    def __post_init__(self) -> None:
        if self.inputs.ndim != 2 or self.targets.shape != (self.inputs.shape[0],):
            raise argument_error(
                "anchor",
                f"inputs {tuple(self.inputs.shape)} and targets {tuple(self.targets.shape)}"
                " do not match",
            )
        if self.inputs.shape[0] == 0:
            raise argument_error("anchor", "no anchor points")
        if not (math.isfinite(self.weight) and self.weight >= 0):
            raise argument_error("anchor.weight", f"expected a number ≥ 0, got {self.weight!r}")
        if not bool(((self.targets >= 0) & (self.targets <= 1)).all()):
            raise argument_error("anchor", "targets must lie in [0, 1]")


def minibatch_orders(
    n: int, batch_size: int, seed: int, n_anchor: int | None = None
) -> tuple[torch.Generator, list[MinibatchOrder]]:
    """The seeded CPU generator of a fit and its minibatch orders: the labels' (n pixels) and,
    with ``n_anchor`` points, the anchor's, both drawing from that generator, in that order at
    every step (:func:`~ultron.train.occupancy.fit_occupancy`)."""
    generator = torch.Generator().manual_seed(seed)
    orders = [MinibatchOrder(n, batch_size, generator)]
    if n_anchor is not None:
        orders.append(MinibatchOrder(n_anchor, batch_size, generator))
    return generator, orders


def label_loss_pick(n: int, max_points: int = LABEL_LOSS_POINTS) -> torch.Tensor:
    """The pixels :func:`~ultron.train.occupancy.label_loss` scores: every ⌈n / max_points⌉-th
    of n, in order."""
    check_count("n", n)
    check_count("max_points", max_points)
    return torch.arange(0, n, max(1, math.ceil(n / max_points)))


def rows_read(
    n: int,
    batch_size: int,
    iters: int,
    seed: int,
    n_anchor: int | None = None,
    max_points: int = LABEL_LOSS_POINTS,
) -> torch.Tensor:
    """The sorted pixels (int64) of n that a fit with these settings draws in its ``iters``
    minibatches (:func:`minibatch_orders`, replayed) together with the ones its
    :func:`~ultron.train.occupancy.label_loss` scores (``max_points``)."""
    check_count("iters", iters, 0)
    _, orders = minibatch_orders(n, batch_size, seed, n_anchor)
    drawn = torch.zeros(n, dtype=torch.bool)
    for _ in range(iters):
        drawn[next(orders[0])] = True
        for other in orders[1:]:
            next(other)
    drawn[label_loss_pick(n, max_points)] = True
    return torch.nonzero(drawn).reshape(-1)
