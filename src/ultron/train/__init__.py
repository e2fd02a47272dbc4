"""Training: losses (SSIM, MSE, PSNR), frame preparation and field fitting with checkpoints."""

from ultron.train.field_fit import (
    FIELD_PRESETS,
    FieldTrainConfig,
    evaluate_frames,
    field_preset,
    fit_field,
    learning_rate_at,
    theta_statistics,
)
from ultron.train.frames import FrameSet, holdout_indices, resample_frames, resampled_probe
from ultron.train.losses import psnr, ssim, ssim_map, ultranerf_loss, weighted_scattering_tv

__all__ = [
    "FIELD_PRESETS",
    "FieldTrainConfig",
    "FrameSet",
    "evaluate_frames",
    "field_preset",
    "fit_field",
    "holdout_indices",
    "learning_rate_at",
    "psnr",
    "resample_frames",
    "resampled_probe",
    "ssim",
    "ssim_map",
    "theta_statistics",
    "ultranerf_loss",
    "weighted_scattering_tv",
]
