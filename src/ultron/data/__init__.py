"""Data: the ``ultron-sweeps/1`` dataset format, probe geometry, rays and importers."""

from ultron.data.dataset import FORMAT, SWEEP_KINDS, ProbeGeometry, Sweep, SweepDataset
from ultron.data.geometry import (
    UnitCube,
    apply_pose,
    field_of_view_bounds_mm,
    frame_pixels_world,
    pixel_to_world,
    probe_points_mm,
    sample_depths_mm,
    scanline_rays,
    scanline_sample_points,
)
from ultron.data.importers import add_sweep_to_dataset, read_ultranerf
from ultron.data.plus_import import read_plus

__all__ = [
    "FORMAT",
    "SWEEP_KINDS",
    "ProbeGeometry",
    "Sweep",
    "SweepDataset",
    "UnitCube",
    "add_sweep_to_dataset",
    "apply_pose",
    "field_of_view_bounds_mm",
    "frame_pixels_world",
    "pixel_to_world",
    "probe_points_mm",
    "read_plus",
    "read_ultranerf",
    "sample_depths_mm",
    "scanline_rays",
    "scanline_sample_points",
]
