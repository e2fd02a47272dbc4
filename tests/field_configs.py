"""A small, fast field-fit configuration shared by the field tests (overrides per test file)."""

from __future__ import annotations

from ultron.fields import FieldConfig, GridFieldConfig
from ultron.train.field_config import FieldTrainConfig


def quick_field_config(cell_mm: float = 1.0, **overrides) -> FieldTrainConfig:
    """20 iterations of a coarse grid field on 2 frames × 8-column patches, a checkpoint every
    10 steps, a log line every 5, validation off (``check_every`` 1000); ``overrides`` win."""
    values = dict(
        field=FieldConfig(grid=GridFieldConfig(cell_mm=cell_mm)),
        iterations=20,
        frames_per_batch=2,
        patch_width=8,
        holdout_every=5,
        check_every=1000,
        checkpoint_every=10,
        log_every=5,
    )
    values.update(overrides)
    return FieldTrainConfig(**values)
