"""A small, fast field-fit configuration shared by the field tests (overrides per test file),
and the small random-speckle sweep they fit it to."""

from __future__ import annotations

import numpy as np

from ultron.data.dataset import ProbeGeometry, Sweep, SweepDataset
from ultron.fields import FieldConfig, GridFieldConfig
from ultron.train.field_config import FieldTrainConfig

#: The probe of :func:`random_sweep`.
RANDOM_SWEEP_PROBE = ProbeGeometry(width_mm=8.0, depth_mm=9.0, height_px=24, width_px=16)


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


def random_sweep(n: int = 10) -> SweepDataset:
    """One sweep ``row`` of ``n`` uniformly random 24 × 16 frames (seed 0), 4 mm long along z."""
    rng = np.random.default_rng(0)
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, 2, 3] = np.linspace(0.0, 4.0, n)
    images = rng.integers(0, 256, size=(n, 24, 16), dtype=np.uint8)
    return SweepDataset(RANDOM_SWEEP_PROBE, [Sweep("row", "row", images, poses)])
