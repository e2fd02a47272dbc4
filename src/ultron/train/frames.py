"""Training frames: resampling a dataset to the fitting resolution, the hold-out split, and what
the held-out frames score without a field (:func:`copy_baselines`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ultron.data.dataset import ProbeGeometry, SweepDataset
from ultron.data.resolution import lit_column_range
from ultron.errors import argument_error
from ultron.train.confidence import confidence_maps
from ultron.train.confidence_cache import cached_confidence_maps
from ultron.train.losses import psnr


def _resample_axis(images: torch.Tensor, new_size: int, dim: int) -> torch.Tensor:
    """Anti-aliased resampling of one axis that keeps ultron's pixel positions exact.

    Pixel k of an axis of n pixels sits at k·s (plus a constant) with s = extent/n; the new
    pixel k' of n' pixels sits at k'·s', i.e. at old fractional index k'·n/n'. The axis is
    box-filtered over round(n/n') old pixels centred on that index (an area average) and read
    there by linear interpolation.
    """
    old_size = images.shape[dim]
    if new_size == old_size:
        return images
    moved = images.movedim(dim, -1)
    shape = moved.shape
    flat = moved.reshape(-1, 1, old_size)
    factor = old_size / new_size
    width = max(1, round(factor))
    if width > 1:
        left = (width - 1) // 2
        flat = F.pad(flat, (left, width - 1 - left), mode="replicate")
        flat = F.avg_pool1d(flat, width, stride=1)
        offset = (width - 1) / 2 - left  # the box centre lies `offset` after index i
    else:
        offset = 0.0
    position = torch.arange(new_size, dtype=torch.float64) * factor - offset
    position = position.clamp(0, old_size - 1)
    lo = position.floor().long().clamp(max=old_size - 1)
    hi = (lo + 1).clamp(max=old_size - 1)
    frac = (position - lo).to(flat.dtype)
    out = flat[..., lo] * (1 - frac) + flat[..., hi] * frac
    return out.reshape(*shape[:-1], new_size).movedim(-1, dim)


def resample_frames(images: np.ndarray | torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """Frames (N, H, W) (uint8 or float in [0, 1]) as float32 (N, H', W') in [0, 1]."""
    tensor = torch.as_tensor(np.asarray(images) if not torch.is_tensor(images) else images)
    if tensor.ndim != 3:
        raise argument_error("images", f"expected (N, H, W), got {tuple(tensor.shape)}")
    if len(shape) != 2 or min(shape) < 1:
        raise argument_error("shape", f"expected (H, W) of positive sizes, got {shape}")
    frames = tensor.to(torch.float32)
    if tensor.dtype == torch.uint8:
        frames = frames / 255.0
    frames = _resample_axis(frames, int(shape[0]), 1)
    return _resample_axis(frames, int(shape[1]), 2).contiguous()


def resampled_probe(probe: ProbeGeometry, shape: tuple[int, int] | None) -> ProbeGeometry:
    """The same probe (width_mm, depth_mm) imaged at ``shape`` = (H, W) pixels."""
    if shape is None:
        return probe
    return ProbeGeometry(probe.width_mm, probe.depth_mm, int(shape[0]), int(shape[1]))


def holdout_indices(n_frames: int, holdout_every: int) -> np.ndarray:
    """Global frame indices held out: every K-th frame (indices K−1, 2K−1, …); none for K ≤ 0."""
    if holdout_every <= 0:
        return np.zeros(0, dtype=np.int64)
    if holdout_every == 1:
        raise argument_error("holdout_every", "1 would hold out every frame; use ≥ 2 or 0")
    return np.arange(holdout_every - 1, n_frames, holdout_every, dtype=np.int64)


@dataclass(frozen=True)
class FrameSet:
    """All frames of a dataset at the fitting resolution, with the train/hold-out split.

    The images (and confidence maps) live on the fit's device (:meth:`to`); poses and indices
    stay on the CPU, where the pixel geometry is computed in float64 and batches are drawn.
    """

    images: torch.Tensor  # (N, H, W) float32 in [0, 1]
    probe_to_world: torch.Tensor  # (N, 4, 4) float64
    probe: ProbeGeometry
    train_index: torch.Tensor  # (N_train,) int64
    holdout_index: torch.Tensor  # (N_holdout,) int64
    confidence: torch.Tensor | None = None  # (N, H, W) float32 confidence maps, when asked
    #: The columns [start, stop) in which some frame has signal (None: all). The others are 0
    #: in every frame, never insonified: no patch is drawn from them and no check scores them
    #: (:func:`ultron.data.resolution.lit_column_range`).
    lit_columns: tuple[int, int] | None = None

    @property
    def lit(self) -> slice:
        """The lit columns as a slice of the images' last axis."""
        return slice(*(self.lit_columns or (0, self.probe.width_px)))

    def with_confidence(
        self,
        report: Callable[[int, int], None] | None = None,
        workers: int = 1,
        cache: Path | None = None,
    ) -> FrameSet:
        """These frames with their ultrasound confidence maps (at the fitting resolution,
        :func:`ultron.train.confidence.confidence_maps` with its default settings, ``workers``
        frames at a time); ``report`` is told (frames done, frames) as they are computed.
        ``cache``: a file that keeps them (:mod:`ultron.train.confidence_cache`), read when it
        holds these frames' maps, else written."""
        images = self.images.cpu().numpy()
        if cache is None:
            maps = confidence_maps(images, workers=workers, report=report)
        else:
            maps, _ = cached_confidence_maps(images, cache, workers=workers, report=report)
        confidence = torch.from_numpy(maps.astype(np.float32)).to(self.images.device)
        return replace(self, confidence=confidence)

    def to(self, device: torch.device) -> FrameSet:
        """These frames with the images (and confidence maps) on ``device``."""
        confidence = None if self.confidence is None else self.confidence.to(device)
        return replace(self, images=self.images.to(device), confidence=confidence)

    @classmethod
    def from_dataset(
        cls, dataset: SweepDataset, shape: tuple[int, int] | None, holdout_every: int
    ) -> FrameSet:
        probe = resampled_probe(dataset.probe, shape)
        images = torch.cat(
            [resample_frames(s.images, probe.image_shape) for s in dataset.sweeps], dim=0
        )
        poses = torch.as_tensor(dataset.all_poses(), dtype=torch.float64)
        held = holdout_indices(images.shape[0], holdout_every)
        train = np.setdiff1d(np.arange(images.shape[0]), held)
        if train.size == 0:
            raise argument_error("holdout_every", "no training frame is left")
        lit = lit_column_range(images.amax(dim=(0, 1)).numpy() != 0)
        return cls(
            images, poses, probe, torch.as_tensor(train), torch.as_tensor(held), lit_columns=lit
        )


def checked_subset(index: torch.Tensor, limit: int | None) -> torch.Tensor:
    """``index`` itself, or ``limit`` of its entries evenly spaced when it holds more: the
    held-out frames a check renders."""
    if limit is not None and index.numel() > limit:
        return index[np.linspace(0, index.numel() - 1, limit).round().astype(np.int64)]
    return index


def copy_baselines(frames: FrameSet, limit: int | None = None) -> dict[str, float]:
    """PSNR (dB) on the held-out frames (those a check renders: :func:`checked_subset`) of two
    predictions that need no field: every held-out frame replaced by the mean training frame
    (``mean_frame``) and by the training frame whose probe origin lies nearest
    (``nearest_frame``). A field that generalises across frames scores above them; one that
    only reproduces its training frames does not. ``black_frame`` is what an all-black image
    scores: a fit that never left its black start scores about that. Scored on the lit
    columns, as the field's checks are. Empty without held-out frames."""
    held = checked_subset(frames.holdout_index, limit)
    if held.numel() == 0:
        return {}
    train = frames.train_index
    origin = frames.probe_to_world[:, :3, 3]
    distance = torch.cdist(origin[held], origin[train])
    nearest = train[distance.argmin(dim=1)]
    images = frames.images[..., frames.lit]  # on the fit's device: only the scores leave it
    target = images[held]
    mean = images[train].mean(dim=0, keepdim=True).expand_as(target)
    return {
        "mean_frame": psnr(mean, target),
        "nearest_frame": psnr(images[nearest], target),
        "black_frame": psnr(torch.zeros_like(target), target),
    }
