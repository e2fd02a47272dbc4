"""UltrON (and its "w/o loss" ablation): occupancy f(θ) from a fitted acoustic field.

1. Choose the label fraction's frames (``select_label_frames``) and gather their annotated
   pixels. 2. For each pixel, f's input g(x) from the fitted field: θ and θ of its world-axis
   neighbours, normalised with the field's saved statistics (:mod:`ultron.fields.context`;
   ``context.radii_mm=()`` is the paper's θ alone), and T along that frame's own scanline
   (exclusive, detached) from the configured source (:mod:`ultron.train.visibility`: the
   fitted field by default, or the frame's confidence map, the annotation, or — diagnostic
   only — the simulator's true T). 3. Fit f_ω with the attenuation-compensated BCE
   (``ultron``) or plain BCE (``ultron-noloss``, which ignores T but records its source), both
   unweighted as in the paper (``OccupancyTrainConfig.positive_weight``). By default the
   compensated loss keeps a background label at full weight where T ≥ 0.3 and drops it below
   (``OccupancyTrainConfig.negatives="observed"``: only observed free space is evidence);
   ``negatives="weighted"`` scales it by T, the paper's BCE(T·f, y). 4. Evaluate
   f(g(x)) on a grid over the scanned region (voxel = the finer pixel spacing), zero outside
   every frame's field of view, and mesh it (with ``label_fusion``, by default when the run
   labels nearly every frame, max(f, the compounded labels): the annotated bone stays bone).
   5. Keep the observed surface
   (:mod:`ultron.mesh.observed`, ``surface="observed"``, the default): the faces that some frame
   saw facing the probe with a transmission ≥ 0.3 above them and, with ``echo_support`` (the
   default), that some frame shows as bone — an echo ``label --auto``'s detector scores as bone
   or a deep shadow beginning under it (:mod:`ultron.mesh.echo_support`): a surface f(θ) puts in
   lit soft tissue that no frame shows as bone is not observed. The faces within 1 mm of the
   labelled surface of the frames f trained on are observed as well
   (``observed.label_support_mm``): the annotator saw bone there, even where the field's T has
   decayed. With a working T the
   compensated loss leaves f unconstrained in deep shadow *by design* (the paper's Fig. 1c: the
   shape is defined only where it was observed), so f(θ) may call a whole shadow column bone;
   its walls and floors are surface nobody observed, and are dropped. The occupancy volume
   (occupancy.nii.gz) is left whole. The observation's T is the oracle's with
   ``--oracle-transmission`` and the fitted field's otherwise (the ``labels`` source has no T
   for unannotated frames; confidence maps are not a transmission scale).

Nothing here reads the reference mesh.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ultron.data.dataset import SweepDataset
from ultron.data.labels import (
    OUTER_SIDE_MM,
    FrameSelection,
    gather_labelled_pixels,
    labelled_surface_points_mm,
    select_label_frames,
)
from ultron.device import module_device
from ultron.errors import UltronInputError, argument_error
from ultron.fields.context import ThetaContextConfig, theta_features
from ultron.fields.occupancy import OccupancyNetwork
from ultron.mesh.compounding import CompoundedVolume, compound_labels
from ultron.mesh.echo_support import EchoSupportConfig, echo_support_maps
from ultron.mesh.extract import ExtractionConfig, extract_surface
from ultron.mesh.grid import GridSpec
from ultron.mesh.label_bridges import bridged_labelled_surface_mm
from ultron.mesh.label_fusion import (
    LabelFusionConfig,
    add_label_surface,
    fuse_with_labels,
    labelled_frame_share,
)
from ultron.mesh.observed import (
    CroppedExtraction,
    ObservedSurfaceConfig,
    SurfaceObservation,
    faced_observation,
    observe_surface,
)
from ultron.mesh.occupancy_mesh import MeshingConfig, elevation_half_thickness_mm, mesh_occupancy
from ultron.models.fitted import TransmissionMaps
from ultron.timing import Advanced, StageTimer
from ultron.train.fit_checkpoint import (
    OCCUPANCY_FIT,
    FitCheckpoint,
    checkpoint_in,
    resumed_steps,
)
from ultron.train.occupancy import (
    LOSSES,
    OccupancyTrainConfig,
    OccupancyTrainingData,
    fit_occupancy,
    label_loss,
    rows_read,
)
from ultron.train.visibility import (
    VisibilityConfig,
    field_theta_transmission,
    frame_transmission,
    in_labelled_shadow,
    pixel_transmission,
)

#: run.json's counts of the background labels in front of their scanline's first bone label,
#: and of those whose T is below the observed negatives' threshold (which the ``front``
#: negatives count and the ``observed`` drop).
FRONT_COUNTS = ("n_background_in_front", "n_background_in_front_below_threshold")


def check_outer_side_mm(value: object) -> None:
    """``label_outer_side_mm`` (UltrON's settings, a network's recorded meta) must be a finite
    number ≥ 0 (mm); otherwise an error naming it."""
    number = isinstance(value, int | float) and not isinstance(value, bool)
    if not (number and math.isfinite(value) and value >= 0):
        raise argument_error(
            "label_outer_side_mm", f"expected a finite number ≥ 0 (mm), got {value!r:.60}"
        )


@dataclass(frozen=True)
class UltronConfig(CroppedExtraction):
    """Settings of an UltrON reconstruction (``visibility``: the source of the loss's T,
    ``context``: the neighbourhood f_ω reads besides θ(x), ``label_outer_side_mm``: how far
    above a band of bone labels unsure pixels are read as background,
    :func:`~ultron.data.labels.surface_outer_side`; 0: the labels as stored;
    ``echo_support``: a frame observes only the surface it shows as bone,
    :mod:`ultron.mesh.echo_support`; None: T alone decides; ``extraction``: None, the one that
    goes with ``observed.surface``, :attr:`surface_extraction`; ``label_fusion``: mesh
    max(f, C), C the labels f trained on compounded, when the run labels nearly every frame
    (:mod:`ultron.mesh.label_fusion`); None: f alone)."""

    occupancy: OccupancyTrainConfig = field(default_factory=OccupancyTrainConfig)
    voxel_mm: float | None = None
    coarse_factor: int = 2
    chunk_points: int = 65_536
    extraction: ExtractionConfig | None = None
    visibility: VisibilityConfig = field(default_factory=VisibilityConfig)
    observed: ObservedSurfaceConfig = field(default_factory=ObservedSurfaceConfig)
    context: ThetaContextConfig = field(default_factory=ThetaContextConfig)
    label_outer_side_mm: float = OUTER_SIDE_MM
    echo_support: EchoSupportConfig | None = field(default_factory=EchoSupportConfig)
    label_fusion: LabelFusionConfig | None = field(default_factory=LabelFusionConfig)

    def __post_init__(self) -> None:
        for name, kind in (
            ("echo_support", EchoSupportConfig),
            ("label_fusion", LabelFusionConfig),
        ):
            value = getattr(self, name)
            if value is not None and not isinstance(value, kind):
                raise argument_error(
                    name, f"expected a {kind.__name__} or None, got {type(value).__name__}"
                )
        check_outer_side_mm(self.label_outer_side_mm)
        _ = self.meshing  # its checks (MeshingConfig)

    @property
    def meshing(self) -> MeshingConfig:
        """The meshing part of these settings (:func:`mesh_occupancy`)."""
        return MeshingConfig(
            self.voxel_mm, self.coarse_factor, self.chunk_points, self.surface_extraction
        )


@dataclass(frozen=True)
class ThetaModel:
    """How an f_ω on θ was trained: its loss, its input context and its class weight — what
    its ``network.pt`` records (:meth:`to_meta`) and fine-tuning reads back (:meth:`from_meta`).
    """

    loss: str = "ultron"
    context: ThetaContextConfig = field(default_factory=ThetaContextConfig)
    positive_weight: float | None = 1.0
    negatives: str = "observed"
    label_outer_side_mm: float = OUTER_SIDE_MM

    def __post_init__(self) -> None:
        check_outer_side_mm(self.label_outer_side_mm)
        object.__setattr__(self, "label_outer_side_mm", float(self.label_outer_side_mm))

    def to_meta(self, channels: Sequence[str], visibility: VisibilityConfig) -> dict[str, Any]:
        """The ``meta`` of the network's ``network.pt`` (θ ``channels``, T's source)."""
        return {
            "input": "theta",
            "theta_channels": list(channels),
            "theta_context": self.context.to_dict(),
            "loss": self.loss,
            "positive_weight": self.positive_weight,
            "negatives": self.negatives,
            "label_outer_side_mm": self.label_outer_side_mm,
            **visibility.to_dict(),
        }

    @classmethod
    def from_meta(cls, meta: dict[str, Any]) -> ThetaModel:
        """From ``network.pt``'s meta; missing keys are the pre-context defaults (θ alone,
        balanced loss, background labels weighted by T, labels read as stored); a bad entry
        is an argument error naming it."""
        return cls(
            loss=meta.get("loss", "ultron"),
            context=ThetaContextConfig.from_dict(meta.get("theta_context")),
            positive_weight=meta.get("positive_weight"),
            negatives=meta.get("negatives", "weighted"),
            label_outer_side_mm=meta.get("label_outer_side_mm", 0.0),
        )


@dataclass(frozen=True)
class TrainedModel:
    """A method's trained network and what reusing it needs (its input, loss, sources …),
    saved as the run's ``network.pt`` (:mod:`ultron.pipeline.model_io`)."""

    network: torch.nn.Module
    meta: dict[str, Any]


@dataclass
class Reconstruction:
    """What a method produced: the mesh (world mm), its occupancy volume and run.json's account
    of it (``info``: JSON-able)."""

    mesh: Any
    volume: np.ndarray
    grid: GridSpec
    info: dict[str, Any]
    #: The trained network, for methods that train one (None: compounding).
    model: TrainedModel | None = None
    #: The extracted surface split into observed / inferred (``mesh`` is its ``kept`` part);
    #: None when the method did not compute it (the pipeline then does, with T ≡ 1).
    observation: SurfaceObservation | None = None
    #: The frames whose labels the method used (None: no label, e.g. an unadapted network).
    selection: FrameSelection | None = None


def occupancy_training_data(
    dataset: SweepDataset,
    fitted,
    selection: FrameSelection,
    visibility: VisibilityConfig | None = None,
    truth: Mapping[str, np.ndarray] | None = None,
    context: ThetaContextConfig | None = None,
    outer_side_mm: float = 0.0,
    advance: Advanced | None = None,
    keep: TransmissionMaps | None = None,
    reads: OccupancyTrainConfig | None = None,
) -> OccupancyTrainingData:
    """Per labelled pixel: f's input g(x) (:func:`~ultron.fields.context.theta_features` with
    ``context``, default θ and its neighbours at 1 and 2 mm), T (detached) from ``visibility``
    (default: the fitted field, computed in the same rendering pass as θ), label. ``truth``
    maps sweep names to the true T for the oracle
    (:func:`~ultron.train.visibility.load_oracle_truth`). ``outer_side_mm`` > 0 adds, as
    background, the unsure pixels directly above each band of bone labels within that distance
    (:func:`~ultron.data.labels.gather_labelled_pixels`). ``advance`` is told how many of g(x)'s
    θ queries are done (:func:`~ultron.fields.context.theta_features`). The data marks the
    background labels in front of their scanline's first bone label (``in_front``). ``keep``,
    when given, keeps the field's T of every labelled frame (the observed crop reads them).
    ``reads``, the settings of the fit to come, limits g(x) to the pixels that fit reads
    (:func:`~ultron.train.occupancy.rows_read`) when it reads fewer than all."""
    if fitted.theta_stats is None:
        raise UltronInputError(
            "field",
            "theta_stats",
            "the field has no θ statistics (its fit was interrupted: run fit-field again to finish it)",
        )
    fitted.check_probe(dataset.probe)
    pixels = gather_labelled_pixels(dataset, selection, outer_side_mm=outer_side_mm)
    theta, field_t = field_theta_transmission(dataset, fitted, pixels, keep)
    transmission = pixel_transmission(
        visibility or VisibilityConfig(), dataset, pixels, truth=truth, field_transmission=field_t
    )
    rows = input_rows = None
    if reads is not None:
        rows = rows_read(len(pixels), reads.batch_size, reads.iters, reads.seed)
        if len(rows) == len(pixels):  # every pixel read: the whole query, as without reads
            rows = None
        else:
            theta = theta[rows]
            input_rows = torch.full((len(pixels),), -1, dtype=torch.int64)
            input_rows[rows] = torch.arange(len(rows))
    world = torch.from_numpy(pixels.world_mm(dataset, None if rows is None else rows.numpy()))
    inputs = theta_features(fitted, world, context or ThetaContextConfig(), theta, advance)
    labels = torch.from_numpy(pixels.label.astype(np.uint8))
    shadow = in_labelled_shadow(dataset, pixels)
    front = torch.from_numpy(pixels.in_front_of_bone())
    transmission = transmission.detach().float()
    return OccupancyTrainingData(inputs, transmission, labels, shadow, front, input_rows)


def occupancy_function(fitted, network: OccupancyNetwork, context: ThetaContextConfig):
    """points (M, 3) world mm → f(g(x)) ∈ (0, 1) on the CPU, g the input of ``context``
    (computed by the field on its device; f on the network's)."""

    def fn(points_mm: torch.Tensor) -> torch.Tensor:
        features = theta_features(fitted, points_mm, context)
        return network.occupancy(features.to(module_device(network))).cpu()

    return fn


def labelled_support_points_mm(
    dataset: SweepDataset, selection: FrameSelection, observed: ObservedSurfaceConfig
) -> np.ndarray:
    """The labelled surface the observed crop counts as observed: the band tops of the frames
    f trained on, and with ``observed.label_bridges`` the bridges between consecutive ones
    that agree (:mod:`ultron.mesh.label_bridges`)."""
    if observed.label_bridges:
        return bridged_labelled_surface_mm(dataset, selection, observed.label_support_mm)
    return labelled_surface_points_mm(dataset, selection)


def keep_observed_surface(
    mesh,
    dataset: SweepDataset,
    fitted,
    config: UltronConfig,
    voxel_mm: float,
    truth: Mapping[str, np.ndarray] | None = None,
    advance: Advanced | None = None,
    selection: FrameSelection | None = None,
    rendered: TransmissionMaps | None = None,
) -> SurfaceObservation:
    """Which vertices of ``mesh`` some frame observed, and the part kept (module docstring,
    step 5; :func:`~ultron.mesh.observed.observe_surface`). ``advance`` is told the frames
    whose T is rendered so far, of all frames. ``selection``: the frames whose labels the
    network trained on; their labelled surface counts as observed within
    ``config.observed.label_support_mm`` (None: the labels do not count), with the bridges
    between them (:func:`labelled_support_points_mm`).

    Each frame's T comes from the oracle (diagnostic runs) or the fitted field (read from
    ``rendered`` for the frames stage 2 rendered already: :func:`train_ultron`); the elevational
    slab is the one the field-of-view mask uses (0.75 × the frame gap, ≥ one voxel of the
    meshing grid, ``voxel_mm``).
    """
    source = "oracle" if config.visibility.source == "oracle" else "field"
    maps = support = labelled = None
    if len(mesh.faces):
        visibility = replace(config.visibility, source=source)
        kept = rendered if source == "field" else None  # the field's own T, already rendered
        total, maps = dataset.n_frames, []
        for sweep in dataset.sweeps:
            offset = sum(m.shape[0] for m in maps)
            counted = None if advance is None else (lambda d, _, o=offset: advance(o + d, total))
            maps.append(frame_transmission(visibility, dataset, sweep.name, fitted=fitted,
                                           truth=truth, advance=counted, rendered=kept))  # fmt: skip
        if config.echo_support is not None:
            support = echo_support_maps(dataset, config.echo_support)
        if selection is not None and config.observed.label_support_mm > 0:
            labelled = labelled_support_points_mm(dataset, selection, config.observed)
    observation = observe_surface(
        mesh,
        dataset.all_poses(),
        dataset.probe,
        maps,
        elevation_half_thickness_mm(dataset, voxel_mm),
        config.observed,
        source,
        support,
        labelled,
    )
    if support is None:
        return observation
    # run.json: the echo support's settings beside its flag (they decide what was kept)
    settings = {"echo_support_config": config.echo_support.to_dict()}
    return replace(observation, info=observation.info | settings)


@dataclass(frozen=True)
class Stage2Fit:
    """UltrON's stage 2 on one fitted field, before meshing: the field, the label frames, the
    trained f_ω with its training config and log, its label loss (:func:`label_loss`) and
    run.json's account of the training data (``data_info``; the data itself is not kept) and
    its fit's checkpoint (``resumed_from``: the update it resumed at; None: no checkpoint)."""

    fitted: Any
    selection: FrameSelection
    config: OccupancyTrainConfig
    network: OccupancyNetwork
    log: list[dict[str, Any]]
    label_loss: float
    data_info: dict[str, Any]
    checkpoint: FitCheckpoint | None = None
    #: The field's T of the labelled frames, rendered for the training data and read again by
    #: the observed crop (:func:`keep_observed_surface`); None: none kept.
    transmission: TransmissionMaps | None = None


def train_ultron(
    dataset: SweepDataset,
    fitted,
    loss: str,
    label_fraction: float,
    seed: int,
    config: UltronConfig,
    timer: StageTimer,
    truth: Mapping[str, np.ndarray] | None = None,
    device: torch.device | str | None = None,
    checkpoints: Path | None = None,
) -> Stage2Fit:
    """Stage 2 of UltrON with ``loss`` (:data:`ultron.train.occupancy.LOSSES`: "ultron", the
    attenuation-compensated loss, or "bce", the ablation's) on ``label_fraction`` of the
    annotated frames, chosen with ``seed``; ``truth`` is the oracle's true T per sweep (only
    for ``config.visibility.source == "oracle"``). f_ω trains on ``device`` (default: the
    fitted field's); with ``checkpoints`` (a directory) the fit is resumable
    (:mod:`ultron.train.fit_checkpoint`)."""
    if loss not in LOSSES:
        raise argument_error("loss", f"expected one of {LOSSES}, got {loss!r}")
    occupancy_config = replace(
        config.occupancy,
        loss=loss,
        network=config.context.network(config.occupancy.network, len(fitted.channels)),
    )
    rendered = TransmissionMaps()
    with timer.stage("labels"):
        selection = select_label_frames(dataset, label_fraction, seed)
        data = occupancy_training_data(
            dataset, fitted, selection, config.visibility, truth, config.context,
            config.label_outer_side_mm, timer.counter("θ queries"), rendered, occupancy_config,
        )  # fmt: skip
    with timer.stage("occupancy_fit"):
        device = fitted.device if device is None else device
        saved = checkpoint_in(checkpoints, OCCUPANCY_FIT)
        network, log = fit_occupancy(
            data, occupancy_config, progress=timer.fit_progress, device=device, checkpoint=saved
        )
        fitted_loss = label_loss(network, data, occupancy_config)
    data_info = data.summary(occupancy_config.observed_transmission)
    return Stage2Fit(
        fitted, selection, occupancy_config, network, log, fitted_loss, data_info, saved, rendered
    )


def _with_label_surface(
    observation: SurfaceObservation,
    compounded: CompoundedVolume,
    dataset: SweepDataset,
    config: UltronConfig,
) -> tuple[SurfaceObservation, dict[str, float]]:
    """``observation`` with the compounded labels' own surface where it hides
    (:func:`~ultron.mesh.label_fusion.add_label_surface`): that surface meshed and cropped as
    label compounding does it (``config.observed``'s extraction and criterion, T ≡ 1)."""
    labels_mesh = extract_surface(compounded.volume, compounded.grid, config.observed.extraction)
    labels = faced_observation(labels_mesh, dataset, compounded.grid.voxel_mm, config.observed)
    return add_label_surface(observation, labels, config.label_fusion.surface_gap_mm)


def mesh_ultron(
    dataset: SweepDataset,
    trained: Stage2Fit,
    config: UltronConfig,
    timer: StageTimer,
    truth: Mapping[str, np.ndarray] | None = None,
) -> Reconstruction:
    """Stage 3 of UltrON: mesh the trained f_ω of ``trained`` (:func:`train_ultron`, with the
    same ``config`` and ``truth``) and keep its observed surface."""
    fitted, network, selection = trained.fitted, trained.network, trained.selection
    fn = occupancy_function(fitted, network, config.context)
    fusion, compounded = None, None
    if config.label_fusion is not None:
        applied = config.label_fusion.applies(dataset, selection)
        fusion = {"min_frame_share": config.label_fusion.min_frame_share,
                  "labelled_frame_share": labelled_frame_share(dataset, selection),
                  "surface_gap_mm": config.label_fusion.surface_gap_mm,
                  "applied": applied}  # fmt: skip
        if applied:
            with timer.stage("mesh_label_fusion"):
                compounded = compound_labels(dataset, selection, config.label_fusion.volume)
            fn = fuse_with_labels(fn, compounded)
            fusion.update(grid=compounded.grid.to_dict(),
                          hole_fill_radius_mm=compounded.hole_fill_radius_mm)  # fmt: skip
    mesh, volume, grid = mesh_occupancy(fn, dataset, config.meshing, timer, module_device(network))
    with timer.stage("mesh_observed"):
        observation = keep_observed_surface(
            mesh, dataset, fitted, config, grid.voxel_mm, truth, timer.counter("frames"),
            selection, trained.transmission,
        )  # fmt: skip
    if compounded is not None and config.label_fusion.surface_gap_mm is not None:
        with timer.stage("mesh_label_surface"):
            observation, added = _with_label_surface(observation, compounded, dataset, config)
        fusion.update(added)
    occupancy_config = trained.config
    info = {
        **observation.info,
        "selection": selection.to_dict(),
        "n_label_frames": selection.n_frames,
        "n_labelled_pixels": trained.data_info["n_labelled_pixels"],
        "n_bone_pixels": trained.data_info["n_bone_pixels"],
        "n_inputs_computed": trained.data_info["n_inputs_computed"],
        **config.visibility.to_dict(),
        "theta_context": config.context.to_dict(),
        "label_outer_side_mm": config.label_outer_side_mm,
        "transmission_stats": trained.data_info["transmission_stats"],
        **{key: trained.data_info[key] for key in FRONT_COUNTS if key in trained.data_info},
        "occupancy_config": occupancy_config.to_dict(),
        "occupancy_log": trained.log,
        **resumed_steps({OCCUPANCY_FIT: trained.checkpoint}),
        "occupancy_label_loss": trained.label_loss,
        "grid": grid.to_dict(),
        "label_fusion": fusion,
    }
    model = ThetaModel(
        occupancy_config.loss,
        config.context,
        occupancy_config.positive_weight,
        occupancy_config.negatives,
        config.label_outer_side_mm,
    ).to_meta(fitted.channels, config.visibility)
    return Reconstruction(
        mesh=observation.kept,
        volume=volume,
        grid=grid,
        info=info,
        model=TrainedModel(network, model),
        observation=observation,
        selection=selection,
    )
