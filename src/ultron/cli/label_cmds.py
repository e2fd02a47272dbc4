"""``ultron label``: automatic bone labels from the B-mode (:mod:`ultron.data.auto_labels`)."""

from __future__ import annotations

from pathlib import Path

from ultron.arguments import sweep_names
from ultron.cli.common import command, print_lines, stage_progress


@command("dataset")
def label(
    dataset: Path,
    auto: bool = False,
    sweeps: list[str] | None = None,
    replace: bool = False,
    threads: int | None = None,
) -> None:
    """Write bone labels (1 bone, 0 background, 255 unsure) into a dataset's sweeps.

    Args:
        dataset: Dataset directory (ultron-sweeps/1).
        auto: Detect bone automatically: the last dominant echo of each scanline, traced as
            one continuous surface (the only mode; required).
        sweeps: Sweep to label (repeat, or comma-separate; default: all sweeps).
        replace: Overwrite the labels a sweep already has.
    """
    from ultron.data.auto_label_dataset import check_labelling, label_checked_sweeps
    from ultron.errors import argument_error

    if not auto:
        raise argument_error("--auto", "only automatic labelling exists: pass --auto")
    # refused before the progress bar opens; the checked dataset is the one labelled
    data, names = check_labelling(dataset, sweep_names(sweeps), replace, option="--sweeps")
    with stage_progress("labelling", unit="frames", width=24) as report:
        summaries = label_checked_sweeps(dataset, data, names, progress=report)
    for summary in summaries:
        print_lines(*summary.lines(dataset))
