"""Outlier poses: a frame whose probe lies far from all the others (a tracking glitch, a pose
in metres among poses in mm) would stretch every grid sized on the scanned volume to
astronomical sizes.

The rule is robust (median-based, so up to half of the frames may be wrong without moving
it): with t_i the translation (probe origin) of frame i over all sweeps, m the per-axis median
of the t_i and d_i = |t_i − m|, frame i is an outlier when

    d_i > :data:`OUTLIER_FACTOR` · median(d) + :data:`OUTLIER_FLOOR_MM`

(10 × the median distance + 50 mm; the distances of real and simulated sweeps: docs/data.md,
"outlier poses").
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ultron.data.dataset import SweepDataset
from ultron.errors import UltronInputError

#: A frame is an outlier beyond this multiple of the median distance to the median position…
OUTLIER_FACTOR = 10.0
#: … plus this many mm (so that frames of a probe held almost still are not outliers).
OUTLIER_FLOOR_MM = 50.0


@dataclass(frozen=True)
class PoseOutlier:
    """One frame whose probe origin lies too far from the median position of all frames."""

    sweep: str
    frame: int
    translation_mm: tuple[float, float, float]
    distance_mm: float
    median_distance_mm: float
    threshold_mm: float

    def describe(self) -> str:
        """``sweep row, frame 3: pose translation (1e+06, 0, 0) mm lies 1e+06 mm from …``
        (without the sweep for poses of no sweep, ``sweep`` empty)."""
        x, y, z = self.translation_mm
        sweep = f"sweep {self.sweep}, " if self.sweep else ""
        return (
            f"{sweep}frame {self.frame}: pose translation ({x:.4g}, {y:.4g}, {z:.4g})"
            f" mm lies {self.distance_mm:.4g} mm from the median position of all frames, more"
            f" than {OUTLIER_FACTOR:g} × their median distance {self.median_distance_mm:.3g} mm"
            f" + {OUTLIER_FLOOR_MM:g} mm = {self.threshold_mm:.4g} mm"
        )


def _outliers(poses: np.ndarray, names: np.ndarray, frames: np.ndarray) -> list[PoseOutlier]:
    """The outliers (module doc) among ``poses`` (N, 4, 4) mm, frame i named by
    (``names[i]``, ``frames[i]``)."""
    translations = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)[:, :3, 3]
    if translations.shape[0] == 0:
        return []
    distance = np.linalg.norm(translations - np.median(translations, axis=0), axis=1)
    median_distance = float(np.median(distance))
    threshold = OUTLIER_FACTOR * median_distance + OUTLIER_FLOOR_MM
    return [
        PoseOutlier(
            str(names[i]),
            int(frames[i]),
            tuple(float(v) for v in translations[i]),
            float(distance[i]),
            median_distance,
            threshold,
        )
        for i in np.flatnonzero(distance > threshold)
    ]


def pose_outliers(dataset: SweepDataset) -> list[PoseOutlier]:
    """Every outlier frame of ``dataset`` (module doc), in sweep and frame order."""
    names = np.concatenate([[s.name] * s.n_frames for s in dataset.sweeps])
    frames = np.concatenate([np.arange(s.n_frames) for s in dataset.sweeps])
    return _outliers(dataset.all_poses(), names, frames)


def pose_array_outliers(poses: np.ndarray) -> list[PoseOutlier]:
    """Every outlier among poses (N, 4, 4) of no sweep (e.g. ``ultron render --poses``), by
    the same rule (module doc), in frame order; their ``sweep`` is empty."""
    n = int(np.asarray(poses).reshape(-1, 4, 4).shape[0])
    return _outliers(poses, np.full(n, ""), np.arange(n))


def check_pose_outliers(dataset: SweepDataset, root: str | Path | None = None) -> None:
    """Refuse a dataset with an outlier pose: a one-line error naming the first one's
    ``poses.npy`` (under ``root``, the dataset directory, when given) and how many there are."""
    outliers = pose_outliers(dataset)
    if not outliers:
        return
    first = outliers[0]
    where = f"sweep {first.sweep!r}" if root is None else Path(root) / first.sweep / "poses.npy"
    more = f" ({len(outliers)} outlier frames in all)" if len(outliers) > 1 else ""
    raise UltronInputError(
        where,
        "poses",
        f"{first.describe()}{more}; a tracking glitch or a unit error? Every grid is sized on"
        " the scanned volume: fix or remove the frame (`ultron info` lists the outliers)",
    )


def check_pose_array_outliers(poses: np.ndarray, where: str | Path) -> None:
    """Refuse poses (N, 4, 4) of no sweep holding an outlier (:func:`pose_array_outliers`): a
    one-line error naming ``where`` (the file they came from) and the first outlier frame."""
    outliers = pose_array_outliers(poses)
    if not outliers:
        return
    more = f" ({len(outliers)} outlier frames in all)" if len(outliers) > 1 else ""
    raise UltronInputError(
        where,
        "poses",
        f"{outliers[0].describe()}{more}; a tracking glitch or a unit error? Fix or remove"
        " the frame",
    )
