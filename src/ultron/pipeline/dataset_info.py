"""``info``: what a dataset directory holds and what looks wrong in it.

The summary (:func:`dataset_info`) reads the dataset once and gathers what ``ultron info``
shows: its sweeps, labelled frames, the field of view's bounding box and the outlier poses
(:func:`ultron.data.outliers.pose_outliers`) that ``reconstruct``, ``finetune`` and
``fit-field`` refuse. Implausible lengths (:func:`ultron.data.units.units_warnings`) need the
reference mesh, read only by :meth:`DatasetInfo.units_warnings`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ultron.data.dataset import SweepDataset
from ultron.data.geometry import field_of_view_bounds_mm
from ultron.data.outliers import PoseOutlier, pose_outliers
from ultron.data.resolution import signal_columns
from ultron.data.units import units_warnings
from ultron.mesh.export import load_mesh


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
        lit_columns=signal_columns(
            np.stack([s.images.any(axis=(0, 1)) for s in data.sweeps]).any(axis=0)[None, None]
        ),
    )
