"""Stage 2: fitting an occupancy network from labelled pixels (METHOD.md §3).

Losses, with f the predicted occupancy, T the transmission reaching the pixel (exclusive,
detached, never normalised) and y the label:

* ``ultron`` — attenuation-compensated BCE(T·f, y):
      L = −[ y·log(p) + (1 − y)·log(1 − p) ],  p = clamp(T·f, ε, 1 − ε)
  A background label in acoustic shadow (T ≈ 0) costs nothing whatever f is, so occluded
  bone labelled 0 does not teach the network "no bone"; where T = 1 it is plain BCE.
  The clamp keeps the logarithms finite; where T·f < ε the clamp also stops the gradient.
  With ``negatives="observed"`` the background labels count only where the beam reached
  them, at full weight (:func:`observed_negatives_bce`): T decides *which* negatives are
  evidence instead of scaling each by T (for a bone label the compensated loss's gradient in
  f does not depend on T, so bone labels count as in the paper). With ``negatives="front"``
  a background label in front of its scanline's first bone label counts too, whatever T
  says: the annotation shows the beam crossed it to reach the bone.
* ``ultron-noloss`` (the paper's ablation) and ``on`` — plain BCE(f, y).

Class balance: bone is a small share of the labelled pixels (a few percent). By default the
loss is unweighted, as in the paper (``positive_weight = 1``), so f = 0.5 — the iso-level the
mesh is cut at — is where bone is as likely as not. ``positive_weight=None`` gives each class
equal total weight instead (positives weighted by n_neg / n_pos, capped at
``max_positive_weight``: a "balanced" BCE, which the ON baseline keeps). Balancing moves the
0.5 level to a posterior of 1 / (1 + w): with w = 20, every point that is bone with 5 %
probability is meshed. On tuning data, balancing called far more of the lit background bone
and lost precision for its extra recall, so the unweighted loss is the default; figures in
docs/decisions.md#occupancy-class-balance-trainoccupancypy.

Optimisation: Adam (lr 1e-4) with an exponential decay that reaches ``final_lr_factor``× the
initial rate at the last iteration, shuffled minibatches drawn with a seeded generator.

Anchor (fine-tuning): with an :class:`OccupancyAnchor` — inputs g(a) of points a and the
occupancy f₀(g(a)) a network predicted there before the fit — every step adds

    λ · mean over an anchor minibatch of BCE(f(g(a)), f₀(g(a)))

(λ the anchor's ``weight``): the labels teach f where they are, the anchor keeps f's answer
elsewhere ("learning without forgetting", Li and Hoiem 2016).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import torch

from ultron.arguments import check_count
from ultron.device import resolve_device
from ultron.errors import argument_error
from ultron.fields.occupancy import OccupancyNetwork, OccupancyNetworkConfig
from ultron.train.fit_checkpoint import FitCheckpoint, FitState, fit_fingerprint, resumable
from ultron.train.loop import Progress, run_training
from ultron.train.occupancy_data import (
    LABEL_LOSS_POINTS,
    OccupancyAnchor,
    OccupancyTrainingData,
    label_loss_pick,
    minibatch_orders,
    rows_read,
)

LOSSES = ("ultron", "bce")
#: How the compensated loss treats background labels: scaled by T (``weighted``, the paper's
#: BCE(T·f, y)) or kept at full weight where T ≥ ``observed_transmission`` and dropped
#: elsewhere (``observed``, the default). The T-weighted negatives let f grow towards the probe
#: and sideways wherever the field's T is below 1 in lit gel (as it is just above bone with the
#: confidence prior); with hard observed negatives that gel is free space. Chosen on tuning
#: datasets because it lowered MAD, and HD95 and the visible CD on most runs, at a small cost
#: in visible completeness and F-score; figures in
#: docs/decisions.md#occupancy-observed-negatives-trainoccupancypy.
#: ``front`` is ``observed`` with every background label in front of its scanline's first bone
#: label counted whatever T says (:func:`observed_negatives_bce`'s ``in_front``): the annotation
#: shows the beam reached it. An option, not the default: what it gains on the real recordings
#: and costs on the simulated benchmark is in
#: docs/decisions.md#occupancy-background-in-front-of-the-bone-counts-trainoccupancypy.
NEGATIVES = ("weighted", "observed", "front")
#: T above which a background label is observed free space: the observed-surface criterion's
#: and the simulated annotator's threshold (:mod:`ultron.mesh.observed`), not tuned.
OBSERVED_TRANSMISSION = 0.3
EPSILON = 1e-6
#: The arithmetic of the fit's network passes: ``float32`` throughout (the default), or
#: ``bfloat16`` mixed precision — the linear layers' products in bfloat16 under
#: :func:`torch.autocast`, the weights, the optimiser, the logits' sigmoid and the loss in float32
#: (:func:`occupancy_in`). Faster on a CPU with native bfloat16 products (AVX512-BF16, AMX) or
#: a GPU; elsewhere it can be slower. Measured in
#: docs/decisions.md#occupancy-fit-in-bfloat16-an-option-trainoccupancypy.
PRECISIONS = ("float32", "bfloat16")


#: Updates between the entries of the loss log.
LOG_EVERY = 50


def attenuation_compensated_bce(
    occupancy: torch.Tensor,
    transmission: torch.Tensor,
    target: torch.Tensor,
    weight: torch.Tensor | None = None,
    eps: float = EPSILON,
) -> torch.Tensor:
    """Mean of −w·[y log p + (1−y) log(1−p)], p = clamp(T·f, ε, 1−ε) (see module doc)."""
    if occupancy.shape != transmission.shape or occupancy.shape != target.shape:
        raise argument_error(
            "occupancy/transmission/target",
            f"shapes differ: {tuple(occupancy.shape)}, {tuple(transmission.shape)}, {tuple(target.shape)}",
        )
    p = (transmission * occupancy).clamp(eps, 1 - eps)
    loss = -(target * torch.log(p) + (1 - target) * torch.log1p(-p))
    if weight is not None:
        loss = loss * weight
    return loss.mean()


def observed_negatives_bce(
    occupancy: torch.Tensor,
    transmission: torch.Tensor,
    target: torch.Tensor,
    min_transmission: float = OBSERVED_TRANSMISSION,
    weight: torch.Tensor | None = None,
    eps: float = EPSILON,
    in_front: torch.Tensor | None = None,
) -> torch.Tensor:
    """BCE whose background labels count only where they were observed as free space:

        L = mean over all labels of −w·m·[y log p + (1−y) log(1−p)],  p = clamp(f, ε, 1−ε),
        m = 1 for y = 1,  m = 1[T ≥ τ  or  F] for y = 0     (τ = ``min_transmission``)

    A background label in shadow (T < τ) is no evidence of free space and costs nothing, as in
    the compensated loss; one the beam reached (T ≥ τ) costs the full BCE, where the
    compensated loss would scale it by T. F (``in_front``, bool, default none) marks labels the
    annotation shows the beam reached whatever T says — those in front of their scanline's
    first bone label (:meth:`~ultron.data.labels.LabelledPixels.in_front_of_bone`). The mean
    runs over every label (dropped ones count as zeros), as the compensated loss's does.
    """
    if not (isinstance(min_transmission, int | float) and 0 <= min_transmission <= 1):
        raise argument_error(
            "min_transmission", f"expected a value in [0, 1], got {min_transmission!r}"
        )
    if transmission.shape != occupancy.shape:
        raise argument_error(
            "transmission",
            f"expected shape {tuple(occupancy.shape)}, got {tuple(transmission.shape)}",
        )
    observed = (target > 0.5) | (transmission >= min_transmission)
    if in_front is not None:
        if in_front.shape != occupancy.shape or in_front.dtype != torch.bool:
            raise argument_error(
                "in_front",
                f"expected a bool tensor of shape {tuple(occupancy.shape)}, got "
                f"{in_front.dtype} {tuple(in_front.shape)}",
            )
        observed = observed | in_front
    mask = observed.to(occupancy.dtype)
    return binary_cross_entropy(occupancy, target, mask if weight is None else mask * weight, eps)


def binary_cross_entropy(
    occupancy: torch.Tensor,
    target: torch.Tensor,
    weight: torch.Tensor | None = None,
    eps: float = EPSILON,
) -> torch.Tensor:
    """Plain BCE(f, y): the compensated loss with T = 1."""
    return attenuation_compensated_bce(occupancy, torch.ones_like(occupancy), target, weight, eps)


@dataclass(frozen=True)
class OccupancyTrainConfig:
    """Settings of :func:`fit_occupancy`."""

    loss: str = "ultron"
    iters: int = 1500
    batch_size: int = 4096
    lr: float = 1e-4
    final_lr_factor: float = 0.1
    positive_weight: float | None = 1.0
    max_positive_weight: float = 20.0
    negatives: str = "observed"
    observed_transmission: float = OBSERVED_TRANSMISSION
    seed: int = 0
    network: OccupancyNetworkConfig = field(default_factory=OccupancyNetworkConfig)
    precision: str = "float32"

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise argument_error("loss", f"expected one of {LOSSES}, got {self.loss!r}")
        check_count("iters", self.iters, 0)
        if self.batch_size < 1:
            raise argument_error("batch_size", f"expected ≥ 1, got {self.batch_size}")
        if not self.lr > 0:
            raise argument_error("lr", f"expected > 0, got {self.lr}")
        if not 0 < self.final_lr_factor <= 1:
            raise argument_error(
                "final_lr_factor", f"expected in (0, 1], got {self.final_lr_factor}"
            )
        if self.positive_weight is not None and not (
            math.isfinite(self.positive_weight) and self.positive_weight > 0
        ):
            raise argument_error("positive_weight", f"expected > 0, got {self.positive_weight}")
        if self.precision not in PRECISIONS:
            raise argument_error(
                "precision", f"expected one of {PRECISIONS}, got {self.precision!r}"
            )
        if self.negatives not in NEGATIVES:
            raise argument_error(
                "negatives", f"expected one of {NEGATIVES}, got {self.negatives!r}"
            )
        if not (
            isinstance(self.observed_transmission, int | float)
            and 0 <= self.observed_transmission <= 1
        ):
            raise argument_error(
                "observed_transmission",
                f"expected a value in [0, 1], got {self.observed_transmission!r}",
            )

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def parse_positive_weight(text: str) -> float | None:
    """From the CLI: a weight > 0 for the bone labels, or ``"balanced"`` (None: n_neg / n_pos)."""
    if text.strip().lower() == "balanced":
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argument_error(
            "positive_weight", f"expected a number > 0 or 'balanced', got {text!r}"
        )
    return value


def positive_class_weight(labels: torch.Tensor, config: OccupancyTrainConfig) -> float:
    """The configured ``positive_weight``; when it is None, n_neg / n_pos capped at
    ``max_positive_weight`` (1 when a class is absent)."""
    if config.positive_weight is not None:
        return float(config.positive_weight)
    n_pos = float(labels.sum())
    n_neg = float(labels.numel()) - n_pos
    if n_pos == 0 or n_neg == 0:
        return 1.0
    return float(min(max(n_neg / n_pos, 1.0), config.max_positive_weight))


def fit_occupancy(
    data: OccupancyTrainingData,
    config: OccupancyTrainConfig,
    network: OccupancyNetwork | None = None,
    trainable: Callable[[OccupancyNetwork], list[torch.nn.Parameter]] | None = None,
    progress: Progress | None = None,
    device: torch.device | str = "cpu",
    anchor: OccupancyAnchor | None = None,
    checkpoint: FitCheckpoint | None = None,
) -> tuple[OccupancyNetwork, list[dict[str, float]]]:
    """Train (a copy-free, in-place) ``network`` on ``data``; returns it and a loss log (every
    :data:`LOG_EVERY` updates, :func:`ultron.train.loop.run_training`).

    ``trainable`` selects the parameters to optimise (default: all), e.g. for fine-tuning with
    frozen layers. ``progress`` receives the logged entries (``step``, ``iterations``,
    ``loss``, ``seconds``). The network (built on the CPU, so its initial weights do not
    depend on the device) and the data are moved to ``device`` and the network is returned
    there; the minibatch order comes from a CPU generator seeded by ``config.seed``, the same
    on every device. ``anchor`` adds the anchor term (module doc), its minibatches drawn from
    the same generator after the labels' (``anchor`` None draws nothing more). With
    ``checkpoint`` the fit saves its state every ``checkpoint.every`` updates and after the
    last, and first resumes a checkpoint of this same fit found at ``checkpoint.path``
    (:mod:`ultron.train.fit_checkpoint`), setting ``checkpoint.resumed_from``: the
    result is the uninterrupted fit's, bit for bit.
    """
    device = resolve_device(device, "device")
    n_anchor = None if anchor is None else anchor.inputs.shape[0]
    generator, orders = minibatch_orders(
        data.labels.shape[0], config.batch_size, config.seed, n_anchor
    )
    network = (network or _initial_network(config, data.inputs.shape[1])).to(device)
    inputs, transmission = data.inputs.to(device), data.transmission.to(device)
    in_front = _front_mask(data, config)
    in_front = None if in_front is None else in_front.to(device)
    parameters = trainable(network) if trainable else list(network.parameters())
    optimiser = torch.optim.Adam(parameters, lr=config.lr)
    gamma = config.final_lr_factor ** (1.0 / max(config.iters, 1))
    labels = data.labels.to(device, torch.float32)
    pos_weight = positive_class_weight(labels, config)
    batches = orders[0]
    if anchor is not None:
        anchor_inputs, anchor_targets = anchor.inputs.to(device), anchor.targets.to(device)
        anchor_batches = orders[1]

    def objective(step: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        drawn = next(batches)
        batch = drawn.to(device)
        y = labels[batch]
        weight = torch.where(y > 0.5, pos_weight, 1.0)
        f = occupancy_in(network, inputs[data.input_index(drawn).to(device)], config.precision)
        front = None if in_front is None else in_front[batch]
        loss = _loss(f, transmission[batch], y, weight, config, front)
        if anchor is None:
            return loss, {"loss": loss.detach()}
        held = next(anchor_batches).to(device)
        held_f = occupancy_in(network, anchor_inputs[held], config.precision)
        kept = binary_cross_entropy(held_f, anchor_targets[held].float())
        return loss + anchor.weight * kept, {"loss": loss.detach(), "anchor": kept.detach()}

    fit = FitState([network], [optimiser], generator, orders)
    start, after_update = resumable(
        checkpoint,
        lambda: _fingerprint(data, config, network, parameters, anchor),
        config.iters,
        fit,
    )
    network.train()
    run_training(
        objective, config.iters, name="occupancy", log_every=LOG_EVERY, progress=progress,
        optimizers=[optimiser], learning_rate=lambda k: config.lr * gamma**k, start=start,
        log=fit.log, after_update=after_update,
    )  # fmt: skip
    network.eval()
    return network, fit.log


def occupancy_in(network: OccupancyNetwork, inputs: torch.Tensor, precision: str) -> torch.Tensor:
    """σ(f_ω(inputs)) with f_ω's passes in ``precision`` (:data:`PRECISIONS`): for ``bfloat16``
    the network runs under :func:`torch.autocast` on the inputs' device and its logits are
    cast to float32 before the sigmoid, so that f near 0 and 1 keeps float32's resolution in
    the loss; ``float32`` is :meth:`OccupancyNetwork.occupancy` itself."""
    if precision not in PRECISIONS:
        raise argument_error("precision", f"expected one of {PRECISIONS}, got {precision!r}")
    if precision == "float32":
        return network.occupancy(inputs)
    with torch.autocast(device_type=inputs.device.type, dtype=torch.bfloat16):
        logits = network(inputs)
    return torch.sigmoid(logits.float())


def _fingerprint(
    data: OccupancyTrainingData,
    config: OccupancyTrainConfig,
    network: OccupancyNetwork,
    parameters: list[torch.nn.Parameter],
    anchor: OccupancyAnchor | None,
) -> str:
    """:func:`~ultron.train.fit_checkpoint.fit_fingerprint` of a fit before its first
    update: its data, settings, initial network, trained parameters and anchor."""
    trained = {id(p) for p in parameters}
    names = [name for name, p in network.named_parameters() if id(p) in trained]
    tensors = [data.inputs, data.transmission, data.labels, *network.state_dict().values()]
    if data.input_rows is not None:  # only data holding some pixels' inputs carries them
        tensors.append(data.input_rows)
    front = _front_mask(data, config)
    if front is not None:  # only a fit that reads the mask depends on it
        tensors.append(front)
    settings = {"config": config.to_dict(), "trained": names, "anchor": None}
    if anchor is not None:
        tensors += [anchor.inputs, anchor.targets]
        settings["anchor"] = anchor.weight
    return fit_fingerprint(tensors, settings)


def label_loss(
    network: OccupancyNetwork,
    data: OccupancyTrainingData,
    config: OccupancyTrainConfig,
    max_points: int = LABEL_LOSS_POINTS,
    chunk: int = 65536,
) -> float:
    """The training loss of the trained ``network`` over the labelled pixels (``config``'s
    loss and class weight, every ⌈n / ``max_points``⌉-th pixel in label order): how well f(θ)
    separates the labels with this field's θ and T. Deterministic (no minibatch draw), so that
    two fits on the same labels — e.g. on fields fitted with different seeds — compare
    (docs/stage2-transmission.md). No gradient; runs on the network's device."""
    if isinstance(max_points, bool) or not isinstance(max_points, int) or max_points < 1:
        raise argument_error("max_points", f"expected a positive integer, got {max_points!r}")
    device = next(network.parameters()).device
    pick = label_loss_pick(data.labels.shape[0], max_points)
    labels = data.labels.to(torch.float32)
    pos_weight = positive_class_weight(labels, config)
    in_front = _front_mask(data, config)
    total = 0.0
    with torch.no_grad():
        for start in range(0, len(pick), chunk):
            at = pick[start : start + chunk]
            y = labels[at].to(device)
            weight = torch.where(y > 0.5, pos_weight, 1.0)
            f = network.occupancy(data.inputs_at(at).to(device))
            front = None if in_front is None else in_front[at].to(device)
            loss = _loss(f, data.transmission[at].to(device), y, weight, config, front)
            total += float(loss) * len(at)
    return total / len(pick)


def _initial_network(config: OccupancyTrainConfig, in_dim: int) -> OccupancyNetwork:
    """A fresh network for ``in_dim`` inputs, initialised from ``config.seed`` (torch's global
    RNG untouched)."""
    network_config = config.network
    if network_config.in_dim != in_dim:
        network_config = OccupancyNetworkConfig(**{**asdict(network_config), "in_dim": in_dim})
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        return OccupancyNetwork(network_config)


def _front_mask(data: OccupancyTrainingData, config: OccupancyTrainConfig) -> torch.Tensor | None:
    """``data.in_front`` where ``config`` reads it (the compensated loss with the ``front``
    negatives), else None: the fit, its fingerprint and :func:`label_loss` carry it only then."""
    if config.loss == "ultron" and config.negatives == "front":
        return data.in_front
    return None


def _loss(
    f: torch.Tensor,
    transmission: torch.Tensor,
    y: torch.Tensor,
    weight: torch.Tensor,
    config: OccupancyTrainConfig,
    in_front: torch.Tensor | None = None,
) -> torch.Tensor:
    """The configured loss of a batch (module doc); ``in_front`` the batch's part of
    :func:`_front_mask` (None unless the ``front`` negatives read it)."""
    if config.loss == "ultron" and config.negatives in ("observed", "front"):
        return observed_negatives_bce(
            f, transmission, y, config.observed_transmission, weight, in_front=in_front
        )
    if config.loss == "ultron":
        return attenuation_compensated_bce(f, transmission, y, weight)
    return binary_cross_entropy(f, y, weight)


__all__ = [  # with the data's names (train/occupancy_data.py): stage 2's one import
    "EPSILON",
    "LABEL_LOSS_POINTS",
    "LOG_EVERY",
    "LOSSES",
    "NEGATIVES",
    "OBSERVED_TRANSMISSION",
    "PRECISIONS",
    "OccupancyAnchor",
    "OccupancyTrainConfig",
    "OccupancyTrainingData",
    "attenuation_compensated_bce",
    "binary_cross_entropy",
    "fit_occupancy",
    "label_loss",
    "observed_negatives_bce",
    "occupancy_in",
    "parse_positive_weight",
    "positive_class_weight",
    "rows_read",
]
