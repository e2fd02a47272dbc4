"""Shape generalisation: adapt a trained UltrON f_ω to a new vertebra (METHOD.md §3, Table 2).

f_ω maps acoustic properties to occupancy, not positions to occupancy, so a network trained on
one vertebra (say L3) can be applied to another (L2) through the new dataset's own fitted field:
θ(x) of the new field, normalised with the *new* field's saved statistics. Fine-tuning copies
the trained network, freezes its last two linear layers (output included) and trains the rest
on 1 % of the new shape's annotated frames for 100 iterations with the loss the network was
trained with (the attenuation-compensated BCE for ``ultron``). ``iters = 0`` is the paper's
"w/o fine-tuning" row: the trained network applied as it is.

Beyond the paper, the fit is anchored (``FinetuneConfig.anchor_weight``, 0 for the paper's plain
fine-tuning): at pixels drawn uniformly from every frame of the new dataset, the copy is held
to the occupancy the trained network predicted there before fine-tuning
(:class:`~ultron.train.occupancy.OccupancyAnchor`), so that a few labelled frames correct f
where they look without erasing what it finds elsewhere.

The loss's transmission T comes from the same source as the model's training (``field``,
``confidence``, ``labels`` or the diagnostic ``oracle``, recorded in its ``network.pt``; a model
saved before sources were recorded used ``field``), computed on the new dataset, unless
``FinetuneConfig.visibility`` (``finetune --visibility``) overrides it. An oracle-trained model
therefore needs the new dataset's true ``transmission.npy`` (checked before any work) unless
another source is given.

The model's input (θ and its neighbourhood, :mod:`ultron.fields.context`) and class weight
are those it was trained with, recorded in its ``network.pt`` (a model saved before they were
recorded read θ alone with the balanced loss).

Meshing and metrics are exactly those of ``reconstruct``; the outputs are the same files, plus
the fine-tuned ``network.pt`` (itself a valid MODEL_DIR).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch
from torch import nn

from ultron.arguments import check_count, check_fraction, check_integer, check_seed
from ultron.data.dataset import SweepDataset
from ultron.data.labels import LabelledPixels, select_label_frames
from ultron.device import module_device, resolve_device
from ultron.errors import UltronInputError, argument_error
from ultron.fields.context import theta_features
from ultron.fields.occupancy import OccupancyNetwork
from ultron.mesh.export import check_mesh_coordinates
from ultron.mesh.occupancy_mesh import mesh_occupancy
from ultron.methods.ultron_method import (
    Reconstruction,
    ThetaModel,
    TrainedModel,
    UltronConfig,
    keep_observed_surface,
    occupancy_function,
    occupancy_training_data,
)
from ultron.metrics.surface import MetricsConfig
from ultron.timing import StageTimer
from ultron.train.loop import Progress
from ultron.train.occupancy import OccupancyAnchor, OccupancyTrainConfig, fit_occupancy
from ultron.train.visibility import VisibilityConfig


@dataclass(frozen=True)
class FinetuneConfig:
    """Settings of :func:`ultron.pipeline.finetune.finetune` (the paper's: 1 % of frames,
    100 iterations, 2 frozen).

    The paper does not give the fine-tuning learning rate. ``lr`` 1e-3 (decaying to 1e-4) was
    chosen on seed-1 data, never on the benchmark's seed 0: it came close to full training,
    where 1e-4 did much worse (100 iterations move f_ω too little) and so did 3e-3.
    ``batch_size`` 1024 (training uses 4096): on the same data it was as accurate as the larger
    batches, and the 8 × 128 GEMMs make the step's cost proportional to the batch. Figures in
    docs/decisions.md#fine-tuning-learning-rate-and-batch-methodsfinetunepy.

    ``anchor_weight`` λ (module doc; 0: the paper's plain fine-tuning) and ``anchor_points``,
    the pixels it is held at: on tuning shapes, plain fine-tuning on 1 % of the frames undid
    what the trained network had found and did worse than no fine-tuning; with λ = 1 (set
    once) it did not. Figures in
    docs/decisions.md#fine-tuning-an-anchor-against-forgetting-methodsfinetunepy.

    Attributes:
        label_fraction: Share of annotated frames used, in (0, 1].
        iters: Fine-tuning iterations; 0 applies the model as is.
        frozen_layers: The network's last linear layers held fixed.
        seed: Seed of label selection and training.
        lr: Learning rate at the first iteration.
        final_lr_factor: The last iteration's rate as a share of ``lr``.
        batch_size: Labelled pixels per step.
        anchor_weight: Weight of the term that holds the network, at pixels of every frame, to
            what it predicted before fine-tuning; 0 fine-tunes as the paper does (on few
            labels the plain fit can lose surface the model had found).
        anchor_points: Pixels the anchor holds the network at.
        meshing: How the fine-tuned network is meshed (UltrON's stage 3).
        metrics: How the mesh is scored.
        visibility: Source of the loss's T: field, confidence or labels (unset: the model's).
        mesh_coordinates: Coordinates of the mesh files: lps or ras.
        device: Where the field and the network compute.
    """

    label_fraction: float = 0.01
    iters: int = 100
    frozen_layers: int = 2
    seed: int = 0
    lr: float = 1e-3
    final_lr_factor: float = 0.1
    batch_size: int = 1024
    anchor_weight: float = 1.0
    anchor_points: int = 2**17
    meshing: UltronConfig = field(default_factory=UltronConfig)
    metrics: MetricsConfig = field(default_factory=MetricsConfig)
    visibility: VisibilityConfig | None = None  # None: the model's own source
    mesh_coordinates: str = "lps"
    device: str = "cpu"  # where the field and f_ω compute (ultron.device.resolve_device)

    def __post_init__(self) -> None:
        check_mesh_coordinates(self.mesh_coordinates, "mesh_coordinates")
        resolve_device(self.device, "device")
        check_fraction("label_fraction", self.label_fraction)
        check_count("iters", self.iters, 0)
        check_integer("frozen_layers", self.frozen_layers)
        check_seed("seed", self.seed)
        check_integer("anchor_points", self.anchor_points, 1)
        weight = self.anchor_weight
        number = isinstance(weight, int | float) and not isinstance(weight, bool)
        if not (number and np.isfinite(weight) and weight >= 0):
            raise argument_error("anchor_weight", f"expected a number ≥ 0, got {weight!r}")

    def training(self, model: ThetaModel) -> OccupancyTrainConfig:
        """The occupancy-training settings of the fine-tuning loop for ``model``."""
        return OccupancyTrainConfig(
            loss=model.loss,
            positive_weight=model.positive_weight,
            negatives=model.negatives,
            iters=self.iters,
            batch_size=self.batch_size,
            lr=self.lr,
            final_lr_factor=self.final_lr_factor,
            seed=self.seed,
        )


def freeze_last_layers(network: OccupancyNetwork, n: int) -> list[nn.Parameter]:
    """Freeze the last ``n`` linear layers in place; return the parameters left trainable."""
    n_layers = len(network.trunk.hidden) + 1
    if not 0 <= n <= n_layers:
        raise argument_error("frozen_layers", f"expected 0…{n_layers} linear layers, got {n}")
    layers = network.last_layers(n) if n > 0 else []
    frozen = {id(p) for layer in layers for p in layer.parameters()}
    trainable = []
    for parameter in network.parameters():
        parameter.requires_grad_(id(parameter) not in frozen)
        if id(parameter) not in frozen:
            trainable.append(parameter)
    return trainable


def anchor_pixels(dataset: SweepDataset, n: int, seed: int) -> LabelledPixels:
    """``n`` pixels drawn uniformly (with replacement) from every pixel of every frame of
    ``dataset``, in (sweep, frame) order; their ``label`` is 0 and means nothing."""
    check_integer("n", n, 1)
    frames = np.array([sweep.n_frames for sweep in dataset.sweeps], dtype=np.int64)
    height, width = dataset.probe.height_px, dataset.probe.width_px
    draw = np.sort(np.random.default_rng(seed).integers(0, frames.sum() * height * width, n))
    frame_index, pixel = np.divmod(draw, height * width)
    sweep_index = np.searchsorted(np.cumsum(frames), frame_index, side="right")
    starts = np.concatenate([[0], np.cumsum(frames)[:-1]])
    return LabelledPixels(
        sweep_index=sweep_index,
        frame=frame_index - starts[sweep_index],
        row=pixel // width,
        col=pixel % width,
        label=np.zeros(n, dtype=np.uint8),
    )


def prediction_anchor(
    dataset: SweepDataset,
    fitted,
    network: OccupancyNetwork,
    spec: ThetaModel,
    config: FinetuneConfig,
) -> OccupancyAnchor:
    """The anchor of ``config``: ``network``'s occupancy, before fine-tuning, at
    :func:`anchor_pixels` of ``dataset``, with its inputs from ``fitted``."""
    pixels = anchor_pixels(dataset, config.anchor_points, config.seed)
    with torch.no_grad():
        world = torch.from_numpy(pixels.world_mm(dataset))
        inputs = theta_features(fitted, world, spec.context).cpu()
        network.eval()
        targets = network.occupancy(inputs.to(module_device(network))).cpu()
    return OccupancyAnchor(inputs, targets, float(config.anchor_weight))


def check_theta_model(network: nn.Module, meta: dict[str, Any], fitted, where: str) -> ThetaModel:
    """The model must be UltrON's f_ω(θ) with the new field's θ channels and an input as wide
    as its recorded context; returns how it was trained."""
    if not isinstance(network, OccupancyNetwork) or meta.get("input") != "theta":
        raise UltronInputError(
            where, "method", f"expected an UltrON network on θ (--method ultron or ultron-noloss), "
            f"got a {type(network).__name__} of method {meta.get('method')!r}",
        )  # fmt: skip
    channels = list(meta.get("theta_channels", []))
    if channels != list(fitted.channels):
        raise UltronInputError(
            where, "theta_channels", f"the model takes {channels}, the field gives {list(fitted.channels)}"
        )  # fmt: skip
    try:
        model = ThetaModel.from_meta(meta)
    except UltronInputError as exc:  # a recorded entry ThetaModel refuses: name the file
        if exc.where != "argument":
            raise
        raise UltronInputError(where, exc.field, exc.problem) from None
    expected = model.context.n_inputs(len(channels))
    if network.config.in_dim != expected:
        raise UltronInputError(
            where, "theta_context", f"{model.context.to_dict()} needs {expected} inputs, "
            f"the network takes {network.config.in_dim}",
        )  # fmt: skip
    return model


def finetune_ultron(
    dataset: SweepDataset,
    fitted,
    network: OccupancyNetwork,
    spec: ThetaModel,
    config: FinetuneConfig,
    timer: StageTimer | None = None,
    progress: Progress | None = None,
    visibility: VisibilityConfig | None = None,
    truth: dict[str, Any] | None = None,
) -> Reconstruction:
    """Fine-tune a copy of ``network`` (trained as ``spec`` says) on ``dataset`` (θ from
    ``fitted``) and mesh it.

    T comes from ``visibility`` (default ``config.visibility``, else the fitted field);
    ``truth`` holds the oracle's true T per sweep. With ``config.iters == 0`` no label is read
    and the copy is applied unchanged.
    """
    timer = timer or StageTimer()
    visibility = visibility or config.visibility or VisibilityConfig()
    model = copy.deepcopy(network)
    selection = None
    info: dict[str, Any] = {"finetune_config": {k: v for k, v in config.__dict__.items()
                                                if k not in ("meshing", "metrics", "visibility",
                                                             "mesh_coordinates")},
                            **visibility.to_dict()}  # fmt: skip
    if config.iters > 0:
        with timer.stage("labels"):
            selection = select_label_frames(dataset, config.label_fraction, config.seed)
            data = occupancy_training_data(
                dataset, fitted, selection, visibility, truth, spec.context,
                spec.label_outer_side_mm,
            )  # fmt: skip
        anchor = None
        if config.anchor_weight > 0:
            with timer.stage("anchor"):
                anchor = prediction_anchor(dataset, fitted, network, spec, config)
        trainable = freeze_last_layers(model, config.frozen_layers)
        with timer.stage("finetune"):
            model, log = fit_occupancy(
                data, config.training(spec), model, lambda _: trainable, progress,
                fitted.device, anchor,
            )  # fmt: skip
        for parameter in model.parameters():
            parameter.requires_grad_(True)
        info |= {
            "selection": selection.to_dict(),
            "n_label_frames": selection.n_frames,
            **data.summary(config.training(spec).observed_transmission),
            "occupancy_log": log,
        }
    model.eval()
    mesh, volume, grid = mesh_occupancy(
        occupancy_function(fitted, model, spec.context), dataset, config.meshing.meshing, timer,
        module_device(model),
    )  # fmt: skip
    with timer.stage("mesh_observed"):
        meshing = replace(config.meshing, visibility=visibility)
        observation = keep_observed_surface(
            mesh, dataset, fitted, meshing, grid.voxel_mm, truth, selection=selection
        )
    info |= observation.info
    info["grid"] = grid.to_dict()
    meta = spec.to_meta(fitted.channels, visibility)
    return Reconstruction(
        mesh=observation.kept,
        volume=volume,
        grid=grid,
        info=info,
        model=TrainedModel(model, meta),
        observation=observation,
        selection=selection,
    )
