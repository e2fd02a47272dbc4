"""The field fit's configuration (:class:`FieldTrainConfig`), its presets and its learning-rate
schedule (:func:`learning_rate_at`); :mod:`ultron.train.field_fit` fits with them."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from dataclasses import field as dataclass_field
from typing import Any

from ultron.arguments import check_count, check_seed
from ultron.data.orientation import ORIENTATIONS
from ultron.errors import argument_error
from ultron.fields.factory import FieldConfig
from ultron.fields.properties import HeadConfig
from ultron.render.renderer import RenderConfig

#: Default learning rates and decay horizons (steps for a ×0.1 decay) per backend: the grid's
#: features want a large rate decayed over the run; the MLP uses the paper's 1e-4 / 250k steps.
DEFAULT_LR = {"grid": 1e-2, "mlp": 1e-4}
PAPER_MLP_DECAY_STEPS = 250_000

#: How scatterers enter training renders: drawn per step (Ultra-NeRF) or their expectation.
SCATTERER_MODES = ("sample", "expected")

#: Fitted frames and training patches need this many pixels on each side: the SSIM window of
#: the loss and the held-out checks (:func:`ultron.train.losses.ssim_map`'s default).
MIN_FIT_SIDE = 7


@dataclass(frozen=True)
class FieldTrainConfig:
    """Everything that defines a field fit (saved to field.json; resume requires a match).

    ``scattering_warmup_iters``: for that many first steps (at most half the run) φ is held at
    its initial value, so the dark regions of the images can only be explained by a loss of
    transmission (α or β); then φ is released (above the heads' floor). On the tuning phantoms
    this put more of the deep shadow into T at an unchanged held-out SSIM (figures in
    docs/decisions.md#field-fit-scattering-warm-up-trainfield_configpy).
    ``confidence_prior_weight`` / ``_margin``: weight w and margin m of the one-sided prior
    w · mean[max(0, T − C − m)²] (:func:`~ultron.train.losses.confidence_transmission_prior`),
    C the ultrasound confidence map of each training frame (Karamalis et al. 2012, computed once
    per fit at the fitting resolution). With Ultra-NeRF's heads alone the field explains the
    dark region under bone by φ → 0 and leaves T ≈ 1 there, so the attenuation-compensated loss
    compensates nothing; the prior tells the field where the image itself says no signal
    arrives. Chosen (w = 1, m = 0.3, set once, not swept) on tuning datasets no benchmark uses:
    it moved the deep shadow into T and lowered UltrON(10 %)'s visible CD (the compensated loss
    now matters), at a coarser accuracy (MAD, HD95); figures in
    docs/decisions.md#field-fit-confidence-prior-trainfield_configpy. ``paper`` and ``shadow``
    presets leave it off.
    See :func:`field_preset` for the paper's configuration.

    Attributes:
        field: The network: backend, grid or MLP settings, heads.
        render: The scanline renderer's settings.
        iterations: Training iterations.
        seed: Seed of initialisation and batches.
        frames_per_batch: Frames a training batch draws its patches from.
        patch_width: Scanlines per training patch.
        learning_rate: Initial learning rate (default: the backend's).
        lr_decay_steps: Steps over which the rate falls tenfold (default: the run's length on
            the grid, the paper's 250k on the MLP).
        holdout_every: Hold out every K-th frame for checks (0: none).
        check_every: Held-out check every N steps.
        checkpoint_every: Save checkpoint.pt (with train_log.jsonl and field.json) every N
            steps and at the last; an interrupted fit resumes from the latest.
        log_every: Steps between train_log.jsonl entries.
        fit_shape: Fit at (H, W) pixels (frames area-resampled), None for the frames' own
            size, or auto (the frames' own, or coarser where their pixels are finer than half a
            speckle grain).
        ssim_weight: Weight of the SSIM term of the image loss.
        mse_weight: Weight of the squared-error term of the image loss.
        scattering_tv_weight: Weight of a total-variation prior on φ (0: off).
        max_check_frames: Held-out frames a check renders at most.
        train_scatterers: expected (E[S]) or sample (Ultra-NeRF's per-step draw) in training.
        scattering_warmup_iters: Steps with φ held constant before it is learned.
        confidence_prior_weight: Weight of the one-sided prior T ≤ C + m (m the margin), C the frame's
            ultrasound confidence map (0: off).
        confidence_prior_margin: The prior's margin.
        orientation: The field's axes: world (the tracker's) or auto (the sweep's where it
            runs more than 5° oblique to the tracker's; measured worse on the real fibula:
            docs/field.md).
    """

    field: FieldConfig = dataclass_field(default_factory=FieldConfig)
    render: RenderConfig = dataclass_field(default_factory=RenderConfig)
    iterations: int = 3000
    seed: int = 0
    frames_per_batch: int = 8
    patch_width: int = 32
    learning_rate: float | None = None
    lr_decay_steps: int | None = None
    holdout_every: int = 10
    check_every: int = 250
    checkpoint_every: int = 500
    log_every: int = 25
    #: (H, W) to fit at, None for the frames' own size, or "auto"
    #: (:func:`ultron.train.fit_shape.auto_fit_shape`: no finer than the speckle needs).
    fit_shape: tuple[int, int] | str | None = "auto"
    ssim_weight: float = 0.75
    mse_weight: float = 0.25
    scattering_tv_weight: float = 0.0
    max_check_frames: int = 32
    train_scatterers: str = "expected"
    scattering_warmup_iters: int = 0
    confidence_prior_weight: float = 1.0
    confidence_prior_margin: float = 0.3
    #: The field's axes: "world" (the tracker's) or "auto" (the sweep's, where it runs
    #: oblique to the world's: :mod:`ultron.data.orientation`; measured worse on the real
    #: fibula, docs/field.md).
    orientation: str = "world"

    def __post_init__(self) -> None:
        positive = ("iterations", "frames_per_batch", "patch_width", "check_every")
        for name in (*positive, "checkpoint_every", "log_every", "max_check_frames"):
            check_count(name, getattr(self, name))
        check_seed("seed", self.seed)
        check_count("holdout_every", self.holdout_every, 0)
        if self.holdout_every == 1:
            raise argument_error(
                "holdout_every", "expected 0 (none) or an integer ≥ 2 (1 holds out every frame)"
            )
        if self.patch_width < MIN_FIT_SIDE:
            raise argument_error(
                "patch_width",
                f"expected ≥ {MIN_FIT_SIDE} (the SSIM window), got {self.patch_width}",
            )
        if self.learning_rate is not None and not self.learning_rate > 0:
            raise argument_error("learning_rate", f"expected > 0, got {self.learning_rate}")
        if self.lr_decay_steps is not None and self.lr_decay_steps < 1:
            raise argument_error("lr_decay_steps", "expected ≥ 1")
        if self.fit_shape == "native":
            object.__setattr__(self, "fit_shape", None)
        elif isinstance(self.fit_shape, str):
            if self.fit_shape != "auto":
                raise argument_error(
                    "fit_shape", f"expected (H, W), 'auto' or 'native', got {self.fit_shape!r}"
                )
        elif self.fit_shape is not None:
            shape = tuple(int(s) for s in self.fit_shape)
            if len(shape) != 2 or min(shape) < MIN_FIT_SIDE:
                raise argument_error(
                    "fit_shape", f"expected (H, W) with both ≥ {MIN_FIT_SIDE}, got {shape}"
                )
            object.__setattr__(self, "fit_shape", shape)
        if self.train_scatterers not in SCATTERER_MODES:
            raise argument_error(
                "train_scatterers",
                f"expected one of {SCATTERER_MODES}, got {self.train_scatterers!r}",
            )
        check_count("scattering_warmup_iters", self.scattering_warmup_iters, 0)
        for name in (
            "ssim_weight",
            "mse_weight",
            "scattering_tv_weight",
            "confidence_prior_weight",
        ):
            if not getattr(self, name) >= 0 or not math.isfinite(getattr(self, name)):
                raise argument_error(name, "expected a finite value ≥ 0")
        if not 0 <= self.confidence_prior_margin < 1:
            raise argument_error("confidence_prior_margin", "expected a value in [0, 1)")
        if self.orientation not in ORIENTATIONS:
            raise argument_error(
                "orientation", f"expected one of {ORIENTATIONS}, got {self.orientation!r}"
            )

    @property
    def effective_scattering_warmup(self) -> int:
        """Steps with φ held: ``scattering_warmup_iters``, at most half the run (so φ is always
        learned for at least the second half, also in short test or preview fits)."""
        return min(self.scattering_warmup_iters, self.iterations // 2)

    @property
    def lr(self) -> float:
        """The initial learning rate (``learning_rate``, else the backend's default)."""
        return self.learning_rate or DEFAULT_LR[self.field.backend]

    @property
    def decay_steps(self) -> int:
        """Steps over which the learning rate falls ×0.1: ``lr_decay_steps`` if set, else the
        run's ``iterations`` (grid) or the paper's 250k steps (mlp)."""
        if self.lr_decay_steps is not None:
            return self.lr_decay_steps
        return self.iterations if self.field.backend == "grid" else PAPER_MLP_DECAY_STEPS

    def with_volume(self, volume_cell_mm: float | None) -> FieldTrainConfig:
        """This fit with the grid field's dense volume at ``volume_cell_mm`` on every box (0 or
        None: no volume, not even a long box's), as a new configuration."""
        cell = volume_cell_mm or None
        grid = replace(self.field.grid, volume_cell_mm=cell, long_box_volume_mm=cell)
        return replace(self, field=replace(self.field, grid=grid))

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        if self.orientation == "world":  # as written before the option: the same cache keys
            del data["orientation"]
        data["field"] = self.field.to_dict()
        shape = self.fit_shape
        data["fit_shape"] = list(shape) if isinstance(shape, tuple) else shape
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FieldTrainConfig:
        """From field.json's ``train``; a field fitted before the confidence prior existed was
        fitted without it (weight 0), one fitted before ``orientation`` on the world's axes."""
        values = dict(data)
        values.setdefault("confidence_prior_weight", 0.0)
        values.setdefault("orientation", "world")  # fields fitted before it: the world's axes
        values["field"] = FieldConfig.from_dict(values.get("field", {}))
        values["render"] = RenderConfig.from_dict(values.get("render", {}))
        values.setdefault("fit_shape", None)  # fields fitted before "auto": their own size
        if isinstance(values["fit_shape"], list):
            values["fit_shape"] = tuple(values["fit_shape"])
        return cls(**values)


#: Named starting points of a field fit (:func:`field_preset`).
FIELD_PRESETS = ("default", "shadow", "paper")
SHADOW_WARMUP_ITERS = 500
PAPER_ITERATIONS = 75_000


def field_preset(name: str = "default", **changes: Any) -> FieldTrainConfig:
    """A fresh field-fit configuration.

    - ``default``: the grid backend with Ultra-NeRF's heads and a reflection gain of 4
      (:class:`~ultron.fields.properties.HeadConfig`), and the confidence prior on T;
    - ``shadow``: the grid backend with the identifiable heads (:meth:`HeadConfig.identifiable`)
      and a 500-step φ warm-up: the field puts the acoustic shadow in T;
    - ``paper``: Ultra-NeRF as published: the 8 × 128 MLP, the paper's heads, no curriculum,
      scatterers drawn every step, 75k iterations, lr 1e-4 decaying ×0.1 per 250k steps.

    ``changes`` override fields (e.g. ``iterations``, ``seed``, ``backend``, ``heads``,
    ``scattering_floor`` of the heads, or ``volume_cell_mm`` of the grid, 0 for none); presets are built anew on every call, never mutated."""
    if name not in FIELD_PRESETS:
        raise argument_error("preset", f"expected one of {FIELD_PRESETS}, got {name!r}")
    if name == "paper":
        base = FieldTrainConfig(
            field=FieldConfig(backend="mlp", heads=HeadConfig.paper()),
            iterations=PAPER_ITERATIONS,
            train_scatterers="sample",
            scattering_warmup_iters=0,
            confidence_prior_weight=0.0,
        )
    elif name == "shadow":
        base = FieldTrainConfig(
            field=FieldConfig(heads=HeadConfig.identifiable()),
            scattering_warmup_iters=SHADOW_WARMUP_ITERS,
            confidence_prior_weight=0.0,
        )
    else:
        base = FieldTrainConfig()
    if "scattering_floor" in changes:
        heads = changes.pop("heads", base.field.heads)
        changes["heads"] = replace(heads, scattering_floor=changes.pop("scattering_floor"))
    with_volume = "volume_cell_mm" in changes
    volume = changes.pop("volume_cell_mm", None)
    field_changes = {k: changes.pop(k) for k in ("backend", "heads", "grid") if k in changes}
    if field_changes:
        changes["field"] = replace(base.field, **field_changes)
    config = replace(base, **changes)
    return config.with_volume(volume) if with_volume else config


def learning_rate_at(config: FieldTrainConfig, step: int) -> float:
    """The learning rate of update ``step`` (0-based): ``lr · 0.1^(step / decay_steps)``.

    A function of the step and the configuration alone (no scheduler state is checkpointed),
    so a resumed run uses exactly the rates of an uninterrupted run of its configuration; with
    a raised ``iterations`` (which sets ``decay_steps`` for the grid backend) that is the
    schedule of the new total, see :func:`ultron.train.field_fit.fit_field`.
    """
    return config.lr * 0.1 ** (step / config.decay_steps)


def comparable_config(config: dict[str, Any]) -> dict[str, Any]:
    """A config dict without the entries a resumed run may change."""
    return {
        k: v
        for k, v in config.items()
        if k not in ("iterations", "check_every", "checkpoint_every", "log_every")
    }


__all__ = [
    "DEFAULT_LR",
    "FIELD_PRESETS",
    "MIN_FIT_SIDE",
    "PAPER_ITERATIONS",
    "PAPER_MLP_DECAY_STEPS",
    "SCATTERER_MODES",
    "SHADOW_WARMUP_ITERS",
    "FieldTrainConfig",
    "comparable_config",
    "field_preset",
    "learning_rate_at",
]
