"""``ultron label``: automatic bone labels from the B-mode (:mod:`ultron.data.auto_labels`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ultron.arguments import sweep_names
from ultron.cli.common import (
    ThreadsOption,
    apply_threads,
    print_lines,
    stage_progress,
    user_errors,
)


@user_errors
def label(
    dataset: Annotated[Path, typer.Argument(help="Dataset directory (ultron-sweeps/1).")],
    auto: Annotated[
        bool,
        typer.Option(
            "--auto",
            help="Detect bone automatically: the last dominant echo of each scanline, traced as"
            " one continuous surface (the only mode; required).",
        ),
    ] = False,
    sweeps: Annotated[
        list[str] | None,
        typer.Option(
            "--sweeps",
            help="Sweep to label (repeat, or comma-separate; default: all sweeps).",
        ),
    ] = None,
    replace: Annotated[
        bool,
        typer.Option("--replace", help="Overwrite the labels a sweep already has."),
    ] = False,
    threads: ThreadsOption = None,
) -> None:
    """Write bone labels (1 bone, 0 background, 255 unsure) into a dataset's sweeps."""
    apply_threads(threads)
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


def register(app: typer.Typer) -> None:
    app.command("label")(label)
