"""``ultron label``: automatic bone labels from the B-mode (:mod:`ultron.data.auto_labels`), a
person's masks (:mod:`ultron.data.label_import`), or a sweep's labels written as masks of its
recording's frames (:mod:`ultron.data.label_export`)."""

from __future__ import annotations

from pathlib import Path

from ultron.arguments import sweep_names
from ultron.cli.common import command, print_lines, stage_progress

#: The modes each option of ``label`` goes with (any other mode refuses it, not ignores it).
OPTION_MODES = {
    "--recording": ("--export",),
    "--bone-value": ("--masks", "--export"),
    "--unsure-value": ("--masks", "--export"),
    "--annotated": ("--masks",),
    "--frames": ("--masks",),
    "--replace": ("--auto", "--masks"),
}


@command("dataset", documented_by=("ultron.data.label_import:MaskImportConfig",))
def label(
    dataset: Path,
    auto: bool = False,
    masks: Path | None = None,
    export: Path | None = None,
    recording: Path | None = None,
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
    from the B-mode (--auto) or read from a person's segmentation (--masks); or write a sweep's
    labels as masks of its recording's frames, to check and correct them (--export).

    Args:
        dataset: Dataset directory (ultron-sweeps/1).
        auto: Detect bone automatically: the last dominant echo of each scanline, traced as
            one continuous surface.
        masks: One mask per frame, as .npy (N, H, W), a folder of 0.png, 1.png, … or an 8- or
            16-bit labelmap sequence (.seq.nrrd, .mha, …): of a PLUS sweep, the recording's
            whole frames (every frame of the file); of any other sweep, its frames
            (docs/auto-labels.md). Needs one sweep (--sweeps NAME).
        export: Write one sweep's labels (--sweeps NAME) as masks of the frames --masks reads:
            .npy, .seq.mha or .seq.nrrd (a Slicer labelmap sequence); bone --bone-value (1),
            unsure --unsure-value (2), background and frames nobody annotated 0.
        recording: With --export: the sequence file the sweep was imported from; a .seq.mha
            export copies its header (timestamps, per-frame transforms), a .seq.nrrd is
            indexed by its timestamps and carries its per-frame fields.
        bone_value: The mask value of bone: read (--masks; default every value but 0 and
            --unsure-value) or written (--export; default 1).
        unsure_value: The mask value of pixels left unsure: read (--masks; default none) or
            written (--export; default 2).
        frames: The frames the masks belong to, one per mask, when they are of some frames only:
            numbers and ranges A:B[:S] (B left out), comma-separated, of the recording's file (a
            PLUS sweep) or of the sweep: 0:1000:10 for every 10th of 1000 (PNGs named by
            frame number with gaps give their frames themselves).
        sweeps: Sweep to label (repeat, or comma-separate; default: all sweeps).
        replace: Overwrite the labels a sweep already has.
    """
    from ultron.data.auto_label_dataset import check_labelling, label_checked_sweeps
    from ultron.data.auto_labels import AutoLabelConfig
    from ultron.errors import argument_error

    if auto + (masks is not None) + (export is not None) != 1:
        raise argument_error("--auto", "pass exactly one of --auto, --masks MASKS and --export OUT")
    mode = "--auto" if auto else "--masks" if masks is not None else "--export"
    given = {
        "--recording": recording is not None, "--bone-value": bone_value is not None,
        "--unsure-value": unsure_value is not None, "--annotated": annotated != "nonempty",
        "--frames": frames is not None, "--replace": replace,
    }  # fmt: skip
    for option in (option for option, on in given.items() if on):
        if mode not in OPTION_MODES[option]:
            raise argument_error(
                option, f"goes with {' or '.join(OPTION_MODES[option])}, not {mode}"
            )
    if export is not None:
        _export(dataset, export, sweep_names(sweeps), recording, bone_value, unsure_value,
                orientation)  # fmt: skip
        return
    if masks is not None:
        _import_masks(dataset, masks, sweep_names(sweeps), replace, bone_value, unsure_value,
                      annotated, orientation, frames)  # fmt: skip
        return
    # refused before the progress bar opens; the checked dataset is the one labelled
    data, names = check_labelling(
        dataset, sweep_names(sweeps), replace, option="--sweeps", relabel=AutoLabelConfig()
    )
    with stage_progress("labelling", unit="frames", width=24) as report:
        summaries = label_checked_sweeps(dataset, data, names, progress=report)
    for summary in summaries:
        print_lines(*summary.lines(dataset))


def _one_sweep(names: list[str] | None, option: str) -> str | None:
    """The one sweep ``--masks`` or ``--export`` (``option``) works on, where ``--sweeps`` names
    it (None: the library takes the dataset's only sweep)."""
    from ultron.data.dataset import one_sweep

    return None if names is None else one_sweep(names, option)


def _export(dataset: Path, out: Path, names: list[str] | None, recording: Path | None,
            bone_value: int | None, unsure_value: int | None, orientation: str) -> None:  # fmt: skip
    from ultron.data.label_export import LabelExportConfig, export_labels

    config = LabelExportConfig(
        1 if bone_value is None else bone_value, 2 if unsure_value is None else unsure_value,
        orientation,
    )  # fmt: skip
    name = _one_sweep(names, "--export")
    exported = export_labels(dataset, name, out, config, recording)
    print_lines(*exported.lines())


def _import_masks(dataset: Path, masks: Path, names: list[str] | None, replace: bool,
                  bone_value: int | None, unsure_value: int | None, annotated: str,
                  orientation: str, frames: str | None) -> None:  # fmt: skip
    from ultron.data.label_import import MaskImportConfig, import_mask_labels, parse_frames

    numbers = None if frames is None else parse_frames(frames)
    config = MaskImportConfig(bone_value, unsure_value, annotated, orientation, numbers)
    summary = import_mask_labels(dataset, _one_sweep(names, "--masks"), masks, config,
                                 replace)  # fmt: skip
    print_lines(summary.lines(dataset), summary.warnings)
