"""``ultron label``: automatic bone labels from the B-mode (:mod:`ultron.data.auto_labels`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ultron.cli.common import (
    ThreadsOption,
    apply_threads,
    console,
    stage_progress,
    sweep_names,
    user_errors,
    warning_line,
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
    from ultron.data.auto_label_dataset import (
        MAX_LISTED,
        QUALITY_FILE,
        check_labelling,
        label_checked_sweeps,
    )
    from ultron.errors import argument_error

    if not auto:
        raise argument_error("--auto", "only automatic labelling exists: pass --auto")
    # refused before the progress bar opens; the checked dataset is the one labelled
    data, names = check_labelling(dataset, sweep_names(sweeps), replace, option="--sweeps")
    with stage_progress("labelling", unit="frames", width=24) as report:
        summaries = label_checked_sweeps(dataset, data, names, progress=report)
    for s in summaries:
        console.print(
            f"{s.name}: {s.frames} frames, bone {100 * s.bone:.2f} %, background"
            f" {100 * s.background:.1f} %, unsure {100 * s.unsure:.1f} %"
            f" ({'replaced' if s.replaced else 'wrote'} labels.npy, {s.seconds:.1f} s)",
            highlight=False,
            soft_wrap=True,
        )
        if s.frames and s.frames_without_bone == s.frames:
            warning_line(
                f"{Path(dataset) / s.name}: no bone found in any of its {s.frames} frames (a"
                " recording without bone, or frames the detector does not suit): its labels are"
                " background and unsure only, nothing to reconstruct from"
            )
        check = ", ".join(str(i) for i in s.frames_to_check[:MAX_LISTED])
        more = " …" if len(s.frames_to_check) > MAX_LISTED else ""
        console.print(
            f"  {s.frames_without_bone} frames without bone; {len(s.frames_to_check)} where the"
            f" surface dropped out{': check ' + check + more if check else ''}"
            f" (per frame: {Path(dataset) / s.name / QUALITY_FILE})",
            highlight=False,
            soft_wrap=True,
        )


def register(app: typer.Typer) -> None:
    app.command("label")(label)
