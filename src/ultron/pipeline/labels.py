"""``label --auto``: automatic bone labels written into a dataset's sweeps.

The labelling and the files it writes are :mod:`ultron.data.auto_label_dataset`; this module
runs it in the order that refuses bad input before anything shows: the sweep names, existing
labels and writable folders are checked (:func:`~ultron.data.auto_label_dataset.check_labelling`)
before the progress display opens, and the dataset is read once.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path

from ultron.data.auto_label_dataset import (
    Progress,
    SweepLabelSummary,
    check_labelling,
    label_checked_sweeps,
)
from ultron.data.auto_labels import AutoLabelConfig

#: Opens a progress display and yields its callback (sweep name, frames done, frames), e.g.
#: the CLI's transient bar.
ProgressDisplay = Callable[[], AbstractContextManager[Progress]]


def label_dataset(
    dataset_dir: str | Path,
    sweeps: Sequence[str] | None = None,
    *,
    replace: bool = False,
    config: AutoLabelConfig | None = None,
    option: str = "sweeps",
    progress: ProgressDisplay | None = None,
) -> list[SweepLabelSummary]:
    """Label the chosen ``sweeps`` (default: all) of the dataset at ``dataset_dir``
    automatically and write the labels (one summary per sweep, in the order given).

    Existing labels are kept unless ``replace``; an unknown sweep is an error naming
    ``option`` (the argument that chose the sweeps, e.g. the CLI's ``--sweeps``). ``progress``
    is opened only once every check has passed, so a refused call shows no progress and
    writes nothing."""
    dataset, names = check_labelling(dataset_dir, sweeps, replace, option)
    with progress() if progress is not None else nullcontext(None) as report:
        return label_checked_sweeps(dataset_dir, dataset, names, config, report)
