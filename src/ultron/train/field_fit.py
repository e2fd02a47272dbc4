"""Fitting an acoustic field to tracked B-mode frames (Ultra-NeRF stage 1).

Each step renders ``frames_per_batch`` whole-depth patches of ``patch_width`` adjacent
scanlines from random training frames (so the PSF and the SSIM see 2D neighbourhoods) and
minimises 0.75·(1 − SSIM) + 0.25·MSE plus the backend's smoothness prior and the optional
β-weighted TV of φ, with Adam and an exponential learning-rate decay (×0.1 over
``decay_steps``, a function of the step: :func:`learning_rate_at`). Seeded by one integer;
checkpoints (model, optimiser, generator, step) make a run resumable, bit-identically (every
``checkpoint_every`` steps and at the end, with the training log written just before each, so
that a resumed run's log holds every entry up to the checkpoint exactly once), and
field.json records the dataset's content hash (``dataset_sha256``,
:meth:`SweepDataset.content_hash`) so that a checkpoint is never resumed on another dataset.

Where we differ from Ultra-NeRF (and why):

- ``train_scatterers="expected"`` (default) renders training patches with E[S] instead of a
  fresh relaxed-Bernoulli draw per step (``"sample"``, the paper's choice, is available). With
  draws, the loss E_S[(T·G∗(Sφ) − y)²] adds the variance term Var(S)·φ², which shrinks φ: the
  expected image then under-estimates the mean intensity (by up to 1 − p = 25 % where the PSF
  covers few pixels, as when fitting at a reduced resolution, where one pixel also averages
  many scatterers). E[S] fits the mean B-mode directly, converges faster on a CPU, and keeps
  the renderer's sampling for synthesis.
- The PSF σ is given in pixels of the dataset's native frames and rescaled to the fitting
  resolution (its size in mm is kept), see :meth:`RenderConfig.rescaled`.
- Frames may be fitted at a reduced ``fit_shape`` (area resampling with exact pixel
  positions), to fit CPU budgets.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ultron import atomic
from ultron.data.dataset import ProbeGeometry, SweepDataset
from ultron.data.geometry import UnitCube
from ultron.data.orientation import field_cube
from ultron.device import describe_device, resolve_device
from ultron.errors import UltronInputError, argument_error
from ultron.fields.base import AcousticField
from ultron.fields.factory import FieldConfig, build_field
from ultron.models.field_dir import (
    CHECKPOINT,
    FIELD_FORMAT,
    FIELD_JSON,
    FIT_DONE,
    THETA_STATS,
    clear_field_dir,
    fit_is_done,
    read_checkpoint,
    read_field_json,
    read_train_log,
    save_checkpoint,
    write_train_log,
)
from ultron.models.fitted import FittedField, ThetaStatistics, load_field, probe_to_dict
from ultron.parallel import default_workers
from ultron.render.renderer import RenderConfig
from ultron.train.confidence_cache import CONFIDENCE_CACHE
from ultron.train.field_batch import (
    FieldObjective,
    batch_inputs,
    draw_batch,
    sample_patches,
)
from ultron.train.field_config import (
    DEFAULT_LR,
    FIELD_PRESETS,
    MIN_FIT_SIDE,
    PAPER_ITERATIONS,
    PAPER_MLP_DECAY_STEPS,
    SCATTERER_MODES,
    SHADOW_WARMUP_ITERS,
    FieldTrainConfig,
    comparable_config,
    field_preset,
    learning_rate_at,
)
from ultron.train.fit_shape import resolve_fit_shape
from ultron.train.frames import FrameSet, checked_subset, copy_baselines, resampled_probe
from ultron.train.loop import Progress, run_training
from ultron.train.losses import METRIC_SSIM_K2, psnr, ssim
from ultron.train.transmission_check import record_transmission_check


def training_objective(
    module: AcousticField,
    frames: FrameSet,
    cube: UnitCube,
    render_config: RenderConfig,
    config: FieldTrainConfig,
    generator: torch.Generator,
    hold_scattering: bool = False,
    objective: FieldObjective | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The loss of a batch of random patches to minimise (image loss, the field's
    regularisation and the configured priors), the image loss and the MSE (detached).

    The batch is drawn from ``generator`` (the fit's CPU generator, :func:`draw_batch`) and
    its loss computed on the module's device, where ``frames.images`` must be
    (:meth:`FrameSet.to`), by ``objective`` (a fit's :class:`FieldObjective`, e.g. replaying
    CUDA graphs; default: the eager loss).

    ``hold_scattering`` renders with φ held at its initial value (the curriculum's first phase:
    the image's dark regions can then only be explained by a loss of transmission).
    """
    if objective is None:
        objective = FieldObjective(module, render_config, config, frames.probe.axial_spacing_mm)
    batch = draw_batch(module, frames, cube, config, generator)
    inputs = batch_inputs(batch, frames, config, frames.images.device)
    hold = module.head_config.initial_scattering if hold_scattering else None
    return objective(inputs, hold)


def make_optimizer(module: AcousticField, lr: float) -> torch.optim.Optimizer:
    """Adam (the fused CPU kernel where this torch build has it)."""
    try:
        return torch.optim.Adam(module.parameters(), lr=lr, fused=True)
    except (RuntimeError, TypeError):
        return torch.optim.Adam(module.parameters(), lr=lr)


def _field_meta(
    config: FieldTrainConfig,
    resolved: FieldConfig,
    render: RenderConfig,
    frames: FrameSet,
    cube: UnitCube,
    step: int,
    dataset_sha256: str,
    device: torch.device,
) -> dict[str, Any]:
    return {
        "format": FIELD_FORMAT,
        "fitted_on": describe_device(device),
        "units": "mm",
        "dataset_sha256": dataset_sha256,
        "field": resolved.to_dict(),
        "render": render.to_dict(),
        "probe": probe_to_dict(frames.probe),
        "unit_cube": cube.to_dict(),
        "train": config.to_dict(),
        "holdout_frames": frames.holdout_index.tolist(),
        "step": step,
    }


@torch.no_grad()
def evaluate_frames(
    fitted: FittedField, frames: FrameSet, index: torch.Tensor, limit: int | None = None
) -> dict[str, float]:
    """PSNR / SSIM (standard constants) of expected renders of frames ``index`` vs the data,
    on the frames' lit columns (:attr:`FrameSet.lit_columns`)."""
    index = checked_subset(index, limit)
    if index.numel() == 0:
        return {}
    rendered = torch.from_numpy(fitted.render(frames.probe_to_world[index], expected=True))
    rendered = rendered[..., frames.lit].contiguous()
    target = frames.images[index][..., frames.lit].cpu()
    return {
        "psnr": psnr(rendered, target),
        "ssim": float(ssim(rendered, target, k1=0.01, k2=METRIC_SSIM_K2)),
    }


@torch.no_grad()
def theta_statistics(
    fitted: FittedField, frames: FrameSet, max_frames: int = 32
) -> ThetaStatistics:
    """Per-channel mean / std of θ over (up to ``max_frames`` evenly spaced) training frames."""
    index = frames.train_index
    if index.numel() > max_frames:
        index = index[np.linspace(0, index.numel() - 1, max_frames).round().astype(np.int64)]
    theta = torch.from_numpy(fitted.render_maps(frames.probe_to_world[index], expected=True).theta)
    flat = theta.reshape(-1, theta.shape[-1]).to(torch.float64)
    std = flat.std(dim=0).clamp(min=1e-8)
    return ThetaStatistics(fitted.channels, tuple(flat.mean(0).tolist()), tuple(std.tolist()))


def check_fit_frames(
    probe: ProbeGeometry, config: FieldTrainConfig, where: str | Path = "dataset"
) -> None:
    """Refuse frames smaller than the loss's SSIM window (:data:`MIN_FIT_SIDE` px on each side)
    at the fit resolution, naming ``where`` (the dataset's dataset.json) and its probe. An
    unresolved ``"auto"`` is checked at the frames' own size (auto never goes below the window
    nor above the frames)."""
    shape = config.fit_shape if isinstance(config.fit_shape, tuple) else None
    rows, cols = resampled_probe(probe, shape).image_shape
    if min(rows, cols) < MIN_FIT_SIDE:
        raise UltronInputError(
            where,
            "probe",
            f"frames of {rows} × {cols} px at the fit resolution are smaller than the SSIM"
            f" window of the loss ({MIN_FIT_SIDE} px on each side); fit at a --fit-shape of"
            f" at least {MIN_FIT_SIDE}x{MIN_FIT_SIDE}",
        )


def _check_step(out: Path, step: object, iterations: int) -> None:
    """Refuse to resume a checkpoint at ``step`` beyond ``iterations`` (a shorter fit than the
    checkpoint's cannot be had by resuming it, and silently returning the longer one would
    mislabel it)."""
    if isinstance(step, int) and not isinstance(step, bool) and step > iterations:
        raise UltronInputError(
            out / FIELD_JSON,
            "step",
            f"the checkpoint is at step {step}, beyond --iters {iterations}; pass --no-resume"
            f" to fit afresh with {iterations} iterations, or --iters ≥ {step} to resume",
        )


def check_resumable(out_dir: str | Path, config: FieldTrainConfig, dataset_sha256: str) -> bool:
    """Whether :func:`fit_field` (with ``resume``) would continue a checkpoint in ``out_dir``:
    False without one; True if it was fitted on the dataset of content hash ``dataset_sha256``
    (:meth:`SweepDataset.content_hash`) with a comparable configuration and is not beyond
    ``config.iterations`` (field.json's ``step``; :func:`fit_field` checks the checkpoint's own
    again); otherwise a one-line :class:`UltronInputError` naming field.json. A field.json
    without ``dataset_sha256`` (from before it was recorded) is not checked for the dataset."""
    out = Path(out_dir)
    if not (out / CHECKPOINT).is_file():
        return False
    meta = read_field_json(out)
    recorded = meta.get("dataset_sha256")
    if recorded is not None and recorded != dataset_sha256:
        raise UltronInputError(
            out / FIELD_JSON,
            "dataset_sha256",
            "checkpoint was fitted on another dataset; use a new --out or --no-resume"
            f" (recorded {str(recorded)[:12]}…, this dataset {dataset_sha256[:12]}…)",
        )
    saved = meta.get("train", {})
    try:  # fills entries added since (their defaults are the earlier behaviour)
        saved = FieldTrainConfig.from_dict(saved).to_dict()
    except (TypeError, UltronInputError):
        pass
    if comparable_config(saved) != comparable_config(config.to_dict()):
        raise UltronInputError(
            out / FIELD_JSON,
            "train",
            "checkpoint was fitted with a different configuration; use a new --out directory",
        )
    _check_step(out, meta.get("step"), config.iterations)
    return True


def _resume(
    out: Path,
    module: AcousticField,
    optimizer: torch.optim.Optimizer,
    generator: torch.Generator,
    iterations: int,
) -> tuple[int, list[dict[str, Any]]]:
    """Load FIELD_DIR ``out``'s checkpoint into the run's state; returns (step, log). A
    checkpoint beyond ``iterations`` is an error (before anything is loaded or written)."""
    state = read_checkpoint(out)
    step = int(state["step"])
    _check_step(out, step, iterations)
    try:
        module.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
    except (RuntimeError, ValueError) as exc:  # e.g. square planes saved by an earlier release
        raise UltronInputError(
            out / CHECKPOINT,
            "model",
            "the checkpoint's field does not match the one this release builds for the data"
            f" ({str(exc).splitlines()[0][:120]}); fit again with --no-resume or a new --out",
        ) from None
    generator.set_state(state["generator"])
    return step, read_train_log(out, step)


def _prepare(
    dataset: SweepDataset,
    config: FieldTrainConfig,
    progress: Progress | None = None,
    out: Path | None = None,
) -> tuple[FrameSet, UnitCube, AcousticField, FieldConfig]:
    """The fit's frames (with confidence maps where the prior needs them, as many at a time as
    :func:`~ultron.parallel.default_workers`: torch's threads (``--threads``), at most the
    cores: a ``progress`` with a ``stage(name, done, total)`` method is told as they are
    computed; kept in ``out``, when given, until the fit ends, so that a resumed fit reads
    them: :mod:`ultron.train.confidence_cache`), unit cube and freshly initialised field (in
    training mode) with its resolved configuration."""
    frames = FrameSet.from_dataset(dataset, config.fit_shape, config.holdout_every)
    if config.confidence_prior_weight > 0:
        stage = getattr(progress, "stage", None)
        report = None if stage is None else (lambda done, n: stage("confidence maps", done, n))
        cache = None if out is None else out / CONFIDENCE_CACHE
        frames = frames.with_confidence(report, default_workers(), cache)
    cube, extent = field_cube(dataset.all_poses(), frames.probe, config.orientation)
    pixel_mm = min(frames.probe.axial_spacing_mm, frames.probe.lateral_spacing_mm)
    module, resolved = build_field(config.field, cube.half_extent_mm, pixel_mm, config.seed, extent)
    return frames, cube, module.train(), resolved


def _check_fit_inputs(dataset: SweepDataset, config: FieldTrainConfig, out_dir: str | Path) -> Path:
    """``dataset`` is a dataset whose frames the loss can take, ``out_dir`` not a file."""
    if not isinstance(dataset, SweepDataset):
        raise argument_error("dataset", "expected a SweepDataset")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise UltronInputError(out, "out", "exists and is not a directory")
    check_fit_frames(dataset.probe, config)
    return out


@dataclass
class _FieldRun:
    """One fit's state and the steps :func:`fit_field` hands to the training loop."""

    out: Path
    config: FieldTrainConfig
    frames: FrameSet
    cube: UnitCube
    module: AcousticField
    resolved: FieldConfig
    optimizer: torch.optim.Optimizer
    generator: torch.Generator
    render_config: RenderConfig
    dataset_sha256: str
    device: torch.device
    log: list[dict[str, Any]]
    #: The field being fitted, joined to the renderer (for the held-out checks), built once.
    fitted: FittedField = field(init=False)
    #: The batch loss, built once (on a CUDA device: replayed from CUDA graphs).
    loss: FieldObjective = field(init=False)
    #: What the checked held-out frames score without a field (:func:`copy_baselines`).
    baselines: dict[str, float] = field(init=False)

    def __post_init__(self) -> None:
        self.fitted = FittedField(
            self.module, self.resolved, self.cube, self.frames.probe, self.render_config
        )
        self.baselines = copy_baselines(self.frames, self.config.max_check_frames)
        self.loss = FieldObjective(
            self.module, self.render_config, self.config, self.frames.probe.axial_spacing_mm,
            graphs=self.device.type == "cuda",
        )  # fmt: skip

    def objective(self, k: int) -> tuple[torch.Tensor, dict[str, float | torch.Tensor]]:
        """Update k's loss (0-based) and its scalars; ``lr`` is the rate of the next update."""
        self.module.train()
        hold = k < self.config.effective_scattering_warmup
        total, loss, mse = training_objective(
            self.module, self.frames, self.cube, self.render_config, self.config,
            self.generator, hold, self.loss,
        )  # fmt: skip
        mse_value = max(float(mse.detach()), 1e-12)
        return total, {"loss": loss.detach(), "psnr": 10 * math.log10(1 / mse_value),
                       "lr": learning_rate_at(self.config, k + 1)}  # fmt: skip

    def held_out_check(self, entry: dict[str, Any]) -> bool:
        """Add the held-out PSNR / SSIM at the check's updates; True there (always logged)."""
        done = entry["step"]
        if done % self.config.check_every == 0 or done == self.config.iterations:
            limit = self.config.max_check_frames
            self.module.eval()  # the next update sets train mode again
            metrics = evaluate_frames(self.fitted, self.frames, self.frames.holdout_index, limit)
            entry.update({f"holdout_{k}": v for k, v in metrics.items()})
            # the same frames: both are empty without held-out frames
            entry.update({f"holdout_{k}_psnr": v for k, v in self.baselines.items()})
        return "holdout_psnr" in entry

    def checkpoint(self, done: int) -> None:
        if done % self.config.checkpoint_every == 0 or done == self.config.iterations:
            self.save(done)

    def save(self, at_step: int) -> None:
        """The log first (it may run ahead of the checkpoint, never fall behind), then
        checkpoint.pt, then field.json."""
        write_train_log(self.out, self.log)
        save_checkpoint(
            self.out, self.module, self.optimizer, self.generator, at_step, self.config.iterations
        )
        meta = _field_meta(
            self.config, self.resolved, self.render_config, self.frames, self.cube, at_step,
            self.dataset_sha256, self.device,
        )  # fmt: skip
        atomic.write_json(self.out / FIELD_JSON, meta)


def fit_field(
    dataset: SweepDataset,
    config: FieldTrainConfig,
    out_dir: str | Path,
    progress: Progress | None = None,
    resume: bool = True,
    device: torch.device | str = "cpu",
) -> FittedField:
    """Fit a field to ``dataset`` and write FIELD_DIR ``out_dir``
    (:mod:`ultron.models.field_dir`).

    ``device`` (:func:`ultron.device.resolve_device`'s spellings) holds the field, the frames
    and the rendering; the batches and scatterer draws come from one seeded CPU generator, so
    a run draws the same batches on every device and a checkpoint (CPU tensors) resumes on any
    device. field.json records the device (``fitted_on``).

    With ``resume`` and a checkpoint in ``out_dir`` the run continues from it, provided it was
    fitted on the same dataset (field.json's ``dataset_sha256``, when recorded, equals
    :meth:`SweepDataset.content_hash`) with the same configuration (the check / checkpoint /
    log intervals may differ, and ``iterations`` may, but not below the checkpoint's step);
    otherwise an :class:`UltronInputError` naming field.json; a fit that ran to its end at
    ``config.iterations`` (its :data:`~ultron.models.field_dir.FIT_DONE` marker, written last)
    is loaded, its frames not prepared again. Without ``resume``, or without
    a checkpoint, the run starts afresh and first removes a previous fit's files from
    ``out_dir``. A save (every ``checkpoint_every`` steps and at the last) writes
    train_log.jsonl, then checkpoint.pt, then field.json; a resumed run keeps the log's
    entries up to the checkpoint's step, so its log holds every logged step once. Update k
    (0-based) uses :func:`learning_rate_at` ``(config, k)``, a function of k alone (a resumed
    run with a raised ``iterations`` follows the new total's schedule); Adam's moments and the
    batch generator continue from the checkpoint.

    The updates run in :func:`ultron.train.loop.run_training`; ``progress`` receives a dict
    per update (and, where it has a ``stage(name, done, total)`` method, is told how the
    preparation, e.g. the confidence maps, advances) (``step``, ``iterations``, ``loss``, ``psnr``, ``lr`` (the rate of the next
    update), ``seconds`` and, when checked, ``holdout_psnr`` / ``holdout_ssim``); the log
    keeps the first update, every ``log_every``-th, every checked one and the last.
    """
    if not isinstance(dataset, SweepDataset):
        raise argument_error("dataset", "expected a SweepDataset")
    config = resolve_fit_shape(config, dataset)
    out = _check_fit_inputs(dataset, config, out_dir)
    device = resolve_device(device, "device")
    dataset_sha256 = dataset.content_hash()
    resuming = resume and check_resumable(out, config, dataset_sha256)
    if resuming and fit_is_done(out, config.iterations):  # nothing left to fit or to write
        return load_field(out, device)
    (out / FIT_DONE).unlink(missing_ok=True)
    frames, cube, module, resolved = _prepare(dataset, config, progress, out)
    frames, module = frames.to(device), module.to(device)
    optimizer = make_optimizer(module, config.lr)
    generator = torch.Generator().manual_seed(config.seed)
    step, log = (
        _resume(out, module, optimizer, generator, config.iterations) if resuming else (0, [])
    )
    if not resuming:
        clear_field_dir(out)
    out.mkdir(parents=True, exist_ok=True)
    render_config = config.render.rescaled(dataset.probe, frames.probe)
    run = _FieldRun(out, config, frames, cube, module, resolved, optimizer, generator,
                    render_config, dataset_sha256, device, log)  # fmt: skip
    run_training(
        run.objective, config.iterations, name="field", log_every=config.log_every, start=step,
        learning_rate=lambda k: learning_rate_at(config, k), optimizers=[optimizer],
        progress=progress, every_update=True, on_entry=run.held_out_check,
        after_update=run.checkpoint, log=log,
    )  # fmt: skip
    if not (out / CHECKPOINT).is_file():
        run.save(step)
    module.eval()
    stats = theta_statistics(run.fitted, frames)
    atomic.write_json(out / THETA_STATS, stats.to_dict())
    fitted = replace_stats(run.fitted, stats)
    record_transmission_check(dataset, fitted, out)  # simulated data: T against the true T
    (out / CONFIDENCE_CACHE).unlink(missing_ok=True)  # the fit is whole: no resume needs them
    atomic.write_text(out / FIT_DONE, "ok\n")
    return fitted


def replace_stats(fitted: FittedField, stats: ThetaStatistics) -> FittedField:
    """The same fitted field carrying ``stats``."""
    return FittedField(
        fitted.field,
        fitted.field_config,
        fitted.unit_cube,
        fitted.probe,
        fitted.render_config,
        stats,
    )


__all__ = [
    "DEFAULT_LR",
    "FIELD_PRESETS",
    "PAPER_ITERATIONS",
    "PAPER_MLP_DECAY_STEPS",
    "SCATTERER_MODES",
    "SHADOW_WARMUP_ITERS",
    "FieldTrainConfig",
    "check_fit_frames",
    "check_resumable",
    "evaluate_frames",
    "field_preset",
    "fit_field",
    "learning_rate_at",
    "make_optimizer",
    "sample_patches",
    "theta_statistics",
    "training_objective",
]
