"""The fit shape ``"auto"`` (the default of :class:`~ultron.train.field_config.
FieldTrainConfig`): the frames' own size, or coarser where their pixels are finer than half the
speckle grain they carry (:mod:`ultron.data.resolution` measures it), because frames finer
than their speckle can make the fit fail, as the PLUS spine phantom's did at their own size
(docs/decisions.md#speckle-resolution-dataresolutionpy-trainfit_shapepy).
"""

from __future__ import annotations

from dataclasses import replace

from ultron.data.dataset import SweepDataset
from ultron.data.resolution import PIXELS_PER_GRAIN, axial_grain_px, resolved_shape
from ultron.train.field_config import MIN_FIT_SIDE, FieldTrainConfig

#: ``fit_shape`` values that are not an explicit (H, W).
FIT_SHAPE_MODES = ("auto", "native")

__all__ = [
    "FIT_SHAPE_MODES",
    "PIXELS_PER_GRAIN",
    "auto_fit_shape",
    "axial_grain_px",
    "resolve_fit_shape",
]


def auto_fit_shape(dataset: SweepDataset) -> tuple[int, int] | None:
    """The shape ``fit_shape="auto"`` fits ``dataset`` at (before the SSIM window's minimum):
    :func:`ultron.data.resolution.resolved_shape`."""
    return resolved_shape(dataset)


def resolve_fit_shape(config: FieldTrainConfig, dataset: SweepDataset) -> FieldTrainConfig:
    """``config`` with ``fit_shape="auto"`` replaced by :func:`auto_fit_shape` ``(dataset)``
    (each side at least :data:`MIN_FIT_SIDE`); any other config unchanged. A fit records the
    resolved shape (field.json), so resuming it compares like with like."""
    if config.fit_shape != "auto":
        return config
    shape = resolved_shape(dataset)
    if shape is not None:
        shape = (max(MIN_FIT_SIDE, shape[0]), max(MIN_FIT_SIDE, shape[1]))
    return replace(config, fit_shape=shape)
