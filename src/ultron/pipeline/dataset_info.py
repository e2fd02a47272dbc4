"""``info``: what a dataset directory holds and what looks wrong in it.

The summary (:func:`dataset_info`) reads the dataset once and gathers what ``ultron info``
shows: its sweeps, labelled frames, the field of view's bounding box and the outlier poses
(:func:`ultron.data.outliers.pose_outliers`) that ``reconstruct``, ``finetune`` and
``fit-field`` refuse. Implausible lengths (:func:`ultron.data.units.units_warnings`) need the
reference mesh, read only by :meth:`DatasetInfo.units_warnings`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ultron.data.dataset import SweepDataset
from ultron.data.geometry import field_of_view_bounds_mm
from ultron.data.outliers import PoseOutlier, pose_outliers
from ultron.data.resolution import dataset_grain_px, lit_column_range
from ultron.data.units import units_warnings
from ultron.mesh.export import load_mesh
from ultron.train.field_config import FieldTrainConfig
from ultron.train.fit_shape import resolve_fit_shape


@dataclass(frozen=True)
class DatasetInfo:
    """A loaded dataset with what ``info`` reports about it: the number of labelled frames,
    the bounding box of every pixel the probe saw (``bounds_mm``: lowest and highest corner,
    world mm), the outlier poses and the columns [start, stop) with signal in some frame
    (``lit_columns``; the others are 0 in every frame, and the field fit ignores them)."""

    dataset: SweepDataset
    n_labelled: int
    bounds_mm: tuple[tuple[float, float, float], tuple[float, float, float]]
    outliers: tuple[PoseOutlier, ...]
    lit_columns: tuple[int, int]

    def units_warnings(self) -> list[str]:
        """One line per implausible length (poses or reference not in millimetres, a reference
        away from the scanned region). It reads the reference mesh, so it is a call of its
        own: a reference that cannot be read is an error after the summary has been shown."""
        reference = self.dataset.reference
        vertices = None if reference is None else load_mesh(reference).vertices
        return units_warnings(self.dataset, vertices)

    def lines(self) -> list[str]:
        """What ``info`` prints under its table of sweeps: frames, image size, probe, pixel
        spacing, the columns with signal, the bounding box and the reference."""
        data, probe = self.dataset, self.dataset.probe
        reference = data.reference.name if data.reference else "none"
        if data.reference_visible_path:
            reference += f" (visible part: {data.reference_visible_path.name})"
        return [
            f"sweeps: {len(data.sweeps)}   frames: {data.n_frames}   labelled frames:"
            f" {self.n_labelled}",
            f"image size: {probe.height_px} rows (depth) × {probe.width_px} columns (scanlines)",
            f"probe: {probe.width_mm:g} mm wide × {probe.depth_mm:g} mm deep",
            f"pixel spacing: {probe.lateral_spacing_mm:.4f} mm lateral ×"
            f" {probe.axial_spacing_mm:.4f} mm axial",
            *self._blank_columns_line(),
            *self._grain_line(),
            "bounding box (mm): "
            + "  ".join(
                f"{axis} [{lo:.2f}, {hi:.2f}]"
                for axis, lo, hi in zip("xyz", *self.bounds_mm, strict=True)
            ),
            f"reference: {reference}",
        ]

    def _blank_columns_line(self) -> list[str]:
        """The line about columns that are 0 in every frame, when there are any."""
        (start, stop), width = self.lit_columns, self.dataset.probe.width_px
        if (start, stop) == (0, width):
            return []
        return [
            f"columns with signal: {start}–{stop - 1} of {width}; the other"
            f" {width - (stop - start)} are 0 in every frame (outside the aperture: the field"
            " fit ignores them)"
        ]

    def _grain_line(self) -> list[str]:
        """The frames' axial speckle grain and the shape ``fit-field --fit-shape auto`` fits
        them at (:mod:`ultron.data.resolution`), when the grain can be measured."""
        data = self.dataset
        grain = dataset_grain_px(data)
        if not math.isfinite(grain):
            return []
        shape = resolve_fit_shape(FieldTrainConfig(fit_shape="auto"), data).fit_shape
        fit = "their own size" if shape is None else f"{shape[0]} × {shape[1]}"
        return [
            f"axial speckle grain: {grain:.2f} pixels ({grain * data.probe.axial_spacing_mm:.3f}"
            f" mm); the field is fitted at {fit} (fit-field --fit-shape auto)"
        ]

    def outlier_lines(self) -> list[str]:
        """A warning per outlier pose (at most 10, then a count): reconstruct, finetune and
        fit-field refuse such a dataset."""
        lines = [f"warning: outlier pose: {o.describe()}" for o in self.outliers[:10]]
        if len(self.outliers) > 10:
            lines.append(f"warning: {len(self.outliers) - 10} more outlier poses")
        if self.outliers:
            lines.append(
                "warning: reconstruct, finetune and fit-field refuse a dataset with outlier"
                " poses (every grid is sized on the scanned volume)"
            )
        return lines


def dataset_info(dataset_dir: str | Path) -> DatasetInfo:
    """Load and validate the dataset at ``dataset_dir`` (an error names the file and field at
    fault) and summarise it (:class:`DatasetInfo`)."""
    data = SweepDataset.load(dataset_dir)
    lo, hi = field_of_view_bounds_mm([s.probe_to_world for s in data.sweeps], data.probe).tolist()
    return DatasetInfo(
        dataset=data,
        n_labelled=sum(len(s.labelled_frames) for s in data.sweeps),
        bounds_mm=(tuple(lo), tuple(hi)),  # type: ignore[arg-type]
        outliers=tuple(pose_outliers(data)),
        lit_columns=lit_column_range(np.any([s.images.any(axis=(0, 1)) for s in data.sweeps], 0)),
    )
