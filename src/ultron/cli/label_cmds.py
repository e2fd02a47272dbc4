"""``ultron label``: automatic bone labels from the B-mode (:mod:`ultron.data.auto_labels`) or
a person's masks (:mod:`ultron.data.label_import`)."""

from __future__ import annotations

from pathlib import Path

from ultron.arguments import sweep_names
from ultron.cli.common import command, print_lines, stage_progress


@command("dataset", documented_by=("ultron.data.label_import:MaskImportConfig",))
def label(
    dataset: Path,
    auto: bool = False,
    masks: Path | None = None,
    sweeps: list[str] | None = None,
    replace: bool = False,
    bone_value: int | None = None,
    unsure_value: int | None = None,
    annotated: str = "nonempty",
    orientation: str = "MF",
    frames: str | None = None,
    threads: int | None = None,
) -> None:
    """Write bone labels (1 bone, 0 background, 255 unsure) into a dataset's sweeps: detected
    from the B-mode (--auto) or read from a person's segmentation (--masks).

    Args:
        dataset: Dataset directory (ultron-sweeps/1).
        auto: Detect bone automatically: the last dominant echo of each scanline, traced as
            one continuous surface.
        masks: One mask per frame, as .npy (N, H, W), a folder of 0.png, 1.png, … or an 8- or
            16-bit labelmap sequence (.seq.nrrd, .mha, …): of a PLUS sweep, the recording's
            whole frames (every frame of the file); of any other sweep, its frames
            (docs/auto-labels.md). Needs one sweep (--sweeps NAME).
        frames: The frames the masks belong to, one per mask, when they are of some frames only:
            numbers and ranges A:B[:S] (B left out), comma-separated, of the recording's file (a
            PLUS sweep) or of the sweep: 0:1000:10 for every 10th of 1000 (PNGs named by
            frame number with gaps give their frames themselves).
        sweeps: Sweep to label (repeat, or comma-separate; default: all sweeps).
        replace: Overwrite the labels a sweep already has.
    """
    from ultron.data.auto_label_dataset import check_labelling, label_checked_sweeps
    from ultron.errors import argument_error

    if auto == (masks is not None):
        raise argument_error("--auto", "pass exactly one of --auto and --masks MASKS")
    if masks is not None:
        _import_masks(dataset, masks, sweep_names(sweeps), replace, bone_value, unsure_value,
                      annotated, orientation, frames)  # fmt: skip
        return
    # refused before the progress bar opens; the checked dataset is the one labelled
    data, names = check_labelling(dataset, sweep_names(sweeps), replace, option="--sweeps")
    with stage_progress("labelling", unit="frames", width=24) as report:
        summaries = label_checked_sweeps(dataset, data, names, progress=report)
    for summary in summaries:
        print_lines(*summary.lines(dataset))


def _import_masks(dataset: Path, masks: Path, names: list[str] | None, replace: bool,
                  bone_value: int | None, unsure_value: int | None, annotated: str,
                  orientation: str, frames: str | None) -> None:  # fmt: skip
    from ultron.data.dataset import SweepDataset
    from ultron.data.label_import import MaskImportConfig, import_mask_labels, parse_frames
    from ultron.errors import argument_error

    numbers = None if frames is None else parse_frames(frames)
    config = MaskImportConfig(bone_value, unsure_value, annotated, orientation, numbers)
    if names is None:
        names = [s.name for s in SweepDataset.load(dataset).sweeps]
    if len(names) != 1:
        raise argument_error(
            "--sweeps", f"--masks labels one sweep: name it (--sweeps NAME; here {len(names)})"
        )
    summary = import_mask_labels(dataset, names[0], masks, config, replace)
    print_lines(summary.lines(dataset))
