"""One update of the field fit: a batch drawn on the host, its loss computed on the device.

The batch (:func:`draw_batch`) is every random draw of an update, made on the fit's CPU
generator in one fixed order — the patches, the scatterers' noise, the regulariser's windows —
with the patches' world geometry in float64. Its loss (:class:`FieldLoss`) is device work
alone: nothing in it draws, synchronises or copies from the host. So on a CUDA device the
forward and backward of the loss can be captured once in CUDA graphs and replayed every
update (:class:`GraphedFieldLoss`): a step of the fit is then a handful of launches instead of
hundreds of small kernels each launched from Python (docs/devices.md). The eager and the
graphed loss compute the same thing from the same batch.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import torch

from ultron.data.geometry import UnitCube
from ultron.errors import argument_error
from ultron.fields.base import AcousticField
from ultron.render import physics
from ultron.render.renderer import RenderConfig, pixel_points_mm, render_properties
from ultron.train.field_config import FieldTrainConfig
from ultron.train.frames import FrameSet
from ultron.train.losses import (
    confidence_transmission_prior,
    ssim_kernel,
    ultranerf_loss,
    weighted_scattering_tv,
)

#: The loss's optional inputs, in the order a graphed loss takes them.
OPTIONAL_INPUTS = ("confidence", "noise", "draws")


def sample_patches(
    frames: FrameSet, n_frames: int, patch_width: int, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """Random training patches: frame indices (B,) and their adjacent columns (B, P), drawn
    among the frames' lit columns (:attr:`FrameSet.lit_columns`: a column 0 in every frame
    was never insonified, and patches of it can hold a fit on an all-black image)."""
    lit = frames.lit
    width = lit.stop - lit.start
    patch = min(patch_width, width)
    pick = torch.randint(0, frames.train_index.shape[0], (n_frames,), generator=generator)
    start = lit.start + torch.randint(0, width - patch + 1, (n_frames,), generator=generator)
    return frames.train_index[pick], start[:, None] + torch.arange(patch)


@dataclass(frozen=True)
class FieldBatch:
    """Every random draw of one update, on the host (CPU)."""

    frame_index: torch.Tensor  # (B,) int64: the frames of the patches
    cols: torch.Tensor  # (B, P) int64: each patch's adjacent columns
    points_unit: torch.Tensor  # (B, H, P, 3) float32: the patches' pixels in the unit cube
    noise: torch.Tensor | None  # (B, H, P) uniform noise of drawn scatterers, or None
    draws: torch.Tensor | None  # the field's regulariser draws, or None


def draw_batch(
    module: AcousticField,
    frames: FrameSet,
    cube: UnitCube,
    config: FieldTrainConfig,
    generator: torch.Generator,
) -> FieldBatch:
    """One update's batch from the fit's CPU ``generator``: the patches
    (:func:`sample_patches`), their pixels' world points (float64, then unit-cube float32),
    the scatterers' noise when ``config`` draws scatterers, the regulariser's draws."""
    frame_index, cols = sample_patches(
        frames, config.frames_per_batch, config.patch_width, generator
    )
    points_mm = pixel_points_mm(frames.probe_to_world[frame_index], frames.probe, cols)
    points_unit = cube.to_unit(points_mm, dtype=torch.float32)
    noise = None
    if config.train_scatterers != "expected":
        noise = physics.scatterer_noise(tuple(points_unit.shape[:-1]), generator, torch.float32)
    return FieldBatch(frame_index, cols, points_unit, noise, module.regularization_draws(generator))


def batch_inputs(
    batch: FieldBatch, frames: FrameSet, config: FieldTrainConfig, device: torch.device
) -> dict[str, torch.Tensor]:
    """The tensors :class:`FieldLoss` reads, on ``device`` (the frames' images' device): the
    unit points, the target patches, and those of :data:`OPTIONAL_INPUTS` the fit uses."""
    patch_cols = batch.cols[:, None, :].expand(-1, frames.probe.height_px, -1).to(device)
    index = batch.frame_index.to(device)
    inputs = {
        "points_unit": batch.points_unit.to(device),
        "target": torch.gather(frames.images[index], 2, patch_cols),
    }
    if config.confidence_prior_weight > 0:
        if frames.confidence is None:
            raise argument_error("frames", "the confidence prior needs FrameSet.with_confidence()")
        inputs["confidence"] = torch.gather(frames.confidence[index], 2, patch_cols)
    if batch.noise is not None:
        inputs["noise"] = batch.noise.to(device)
    if batch.draws is not None:
        inputs["draws"] = batch.draws.to(device)
    return inputs


class FieldLoss(torch.nn.Module):
    """The fit's objective on one batch: Ultra-NeRF's image loss of the rendered patches plus
    the field's regulariser and the configured priors; returns (total, image loss, MSE), the
    last two detached.

    The PSF's kernels, the SSIM window and, for expected scatterers of a fixed probability,
    E[S] are built once on the field's device; ``hold_scattering`` renders with φ held at
    that value (the curriculum's first phase).
    """

    def __init__(
        self,
        field: AcousticField,
        render_config: RenderConfig,
        config: FieldTrainConfig,
        step_mm: float,
        hold_scattering: float | None = None,
    ) -> None:
        super().__init__()
        self.field = field
        self.render_config, self.config = render_config, config
        self.step_mm, self.hold_scattering = step_mm, hold_scattering
        device = next(field.parameters()).device
        axial, lateral = render_config.kernels(torch.float32, device)
        self.register_buffer("psf_axial", axial, persistent=False)
        self.register_buffer("psf_lateral", lateral, persistent=False)
        self.register_buffer("ssim_window", ssim_kernel(dtype=torch.float32, device=device), False)
        expected = physics.relaxed_bernoulli_mean(
            render_config.scatter_probability, render_config.scatter_temperature
        )
        self.register_buffer("expected_scatterers", expected.to(torch.float32).to(device), False)
        probability = torch.tensor(render_config.scatter_probability, dtype=torch.float32)
        self.register_buffer("scatter_probability", probability.to(device), persistent=False)

    def forward(
        self,
        points_unit: torch.Tensor,
        target: torch.Tensor,
        confidence: torch.Tensor | None = None,
        noise: torch.Tensor | None = None,
        draws: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        properties = self.field(points_unit)
        if self.hold_scattering is not None:
            held = torch.full_like(properties.scattering, self.hold_scattering)
            properties = replace(properties, scattering=held)
        rendered = render_properties(
            properties, self.step_mm, self.render_config,
            scatterers=self._scatterers(properties.density, noise),
            kernels=(self.psf_axial, self.psf_lateral),
        )  # fmt: skip
        loss, mse = ultranerf_loss(
            rendered.intensity, target, self.config.ssim_weight, self.config.mse_weight,
            kernel=self.ssim_window,
        )  # fmt: skip
        total = loss + self.field.regularization(draws=draws)
        if self.config.confidence_prior_weight > 0:
            if confidence is None:
                raise argument_error("confidence", "the confidence prior needs the batch's maps")
            total = total + self.config.confidence_prior_weight * confidence_transmission_prior(
                rendered.transmission, confidence, self.config.confidence_prior_margin
            )
        if self.config.scattering_tv_weight > 0:
            total = total + self.config.scattering_tv_weight * weighted_scattering_tv(
                rendered.properties.scattering, rendered.properties.reflection
            )
        return total, loss.detach(), mse.detach()

    def _scatterers(self, density: torch.Tensor | None, noise: torch.Tensor | None):
        """S: drawn from ``noise`` (p the learned density or the configured probability) or,
        without noise, its expectation (:func:`~ultron.render.physics.relaxed_bernoulli_mean`)."""
        temperature = self.render_config.scatter_temperature
        if noise is None:
            if density is None:
                return self.expected_scatterers
            return physics.relaxed_bernoulli_mean(density, temperature)
        if density is None:
            probability = self.scatter_probability
            return physics.scatterers_from_noise(probability, noise, temperature).detach()
        return physics.scatterers_from_noise(density, noise, temperature)


class _Positional(torch.nn.Module):
    """A :class:`FieldLoss` taking its present inputs positionally (what a CUDA graph takes)."""

    def __init__(self, loss: FieldLoss, names: tuple[str, ...]) -> None:
        super().__init__()
        self.loss, self.names = loss, names

    def forward(self, *tensors: torch.Tensor):
        return self.loss(**dict(zip(self.names, tensors, strict=True)))


class FieldObjective:
    """The fit's :class:`FieldLoss` per curriculum phase, eager or replayed from CUDA graphs.

    With ``graphs`` (a CUDA device) the forward and backward of each phase's loss are
    captured with :func:`torch.cuda.make_graphed_callables` from the phase's first batch;
    calling the objective then copies a batch's inputs (:func:`batch_inputs`) into the graph's
    buffers and replays the forward, and ``total.backward()`` replays the backward, leaving
    the gradients in the parameters' ``.grad`` as the eager loss does. Those gradients are the
    graph's own buffers, overwritten by the next replay: every update sets ``.grad`` to None
    before its backward and steps before the next forward (:func:`ultron.train.loop.descend`),
    never accumulating over two (pytorch/pytorch#181723). If a capture fails, a warning says
    why and the eager loss is used from then on (the same result, slower).
    """

    def __init__(
        self,
        field: AcousticField,
        render_config: RenderConfig,
        config: FieldTrainConfig,
        step_mm: float,
        graphs: bool = False,
    ) -> None:
        self._parts = (field, render_config, config, step_mm)
        self._device = next(field.parameters()).device
        self._eager: dict[float | None, FieldLoss] = {}
        self._graphed: dict[float | None, torch.nn.Module] = {}
        #: Why the capture failed (then the loss runs eagerly); None otherwise.
        self.failed: str | None = None if graphs else "graphs not requested"

    @property
    def graphed(self) -> bool:
        """Whether the updates replay CUDA graphs."""
        return self.failed is None

    def __call__(
        self, inputs: dict[str, torch.Tensor], hold_scattering: float | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(total, image loss, MSE) of a batch's ``inputs``, φ held at ``hold_scattering``."""
        if self.failed is None and hold_scattering not in self._graphed:
            self._capture(inputs, hold_scattering)
        if self.failed is not None:
            return self._loss(hold_scattering)(**inputs)
        with torch.cuda.device(self._device):  # a graph replays on the device it was made on
            return self._graphed[hold_scattering](*(inputs[name] for name in _names(inputs)))

    def _loss(self, hold_scattering: float | None) -> FieldLoss:
        if hold_scattering not in self._eager:
            self._eager[hold_scattering] = FieldLoss(*self._parts, hold_scattering)
        return self._eager[hold_scattering]

    def _capture(self, inputs: dict[str, torch.Tensor], hold_scattering: float | None) -> None:
        if self._device.type != "cuda":  # a CUDA build would "capture" CPU work as no kernels
            self._fall_back(f"the field is on {self._device}, not a CUDA device")
            return
        names = _names(inputs)
        sample = tuple(inputs[name].clone() for name in names)
        positional = _Positional(self._loss(hold_scattering), names)
        # The capture makes the parameters' gradient accumulators on its own stream (its warm-up
        # backward already does), and its outputs keep them; the replayed backward's gradients
        # reach them in order, so PyTorch's warning that their streams differ (on stderr from
        # the warm-up on) says nothing here.
        quiet = getattr(torch.autograd.graph, "set_warn_on_accumulate_grad_stream_mismatch", None)
        if quiet is not None:
            quiet(False)
        try:
            with torch.cuda.device(self._device):
                self._graphed[hold_scattering] = torch.cuda.make_graphed_callables(
                    positional, sample, allow_unused_input=True
                )
        except RuntimeError as error:  # an operation that a CUDA graph cannot capture
            self._fall_back(str(error).splitlines()[0][:200])

    def _fall_back(self, reason: str) -> None:
        """Fit eagerly from now on, saying why in one warning."""
        self.failed = reason
        warnings.warn(
            f"field fit: CUDA graph capture failed ({reason}); fitting without graphs",
            RuntimeWarning,
            stacklevel=4,
        )


def _names(inputs: dict[str, torch.Tensor]) -> tuple[str, ...]:
    """The inputs' names in a graphed loss's positional order."""
    return ("points_unit", "target", *(name for name in OPTIONAL_INPUTS if name in inputs))
