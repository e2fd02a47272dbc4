"""``ultron import-ultranerf``, ``ultron import-plus`` and ``ultron info``."""

from __future__ import annotations

from pathlib import Path

from ultron.cli.common import command, console, print_lines, stage_progress


@command(
    "src",
    aliases={"orthonormalize_tolerance": "orthonormalize_tol"},
    documented_by=("ultron.pipeline.sweep_import:import_ultranerf_sweep",),
)
def import_ultranerf(
    src: Path,
    width_mm: float,
    depth_mm: float,
    out: Path,
    sweep_name: str | None = None,
    kind: str = "other",
    orthonormalize_tol: float = 0.05,
    replace: bool = False,
) -> None:
    """Import an Ultra-NeRF sweep into an ultron-sweeps/1 dataset (repeat to add sweeps)."""
    from ultron.pipeline.sweep_import import import_ultranerf_sweep

    imported = import_ultranerf_sweep(
        src, out, width_mm, depth_mm, sweep_name=sweep_name, kind=kind,
        orthonormalize_tolerance=orthonormalize_tol, replace=replace,
    )  # fmt: skip
    print_lines(imported.lines(out, kind))


@command("sequence", documented_by=("ultron.pipeline.sweep_import:import_plus_sweep",))
def import_plus(
    sequence: Path,
    out: Path,
    config: Path | None = None,
    to: str = "Reference",
    sweep_name: str | None = None,
    kind: str = "other",
    downsample: str = "auto",
    replace: bool = False,
    keep_blank_columns: bool = False,
    tracking: list[Path] | None = None,
    orientation: str | None = None,
) -> None:
    """Import a tracked PLUS / 3D Slicer recording as a sweep (repeat to add sweeps)."""
    from ultron.pipeline.sweep_import import import_plus_sweep

    with stage_progress("import", unit="frames") as report:
        imported = import_plus_sweep(
            sequence, config, out, to=to, sweep_name=sweep_name, kind=kind,
            downsample=downsample_factor(downsample), replace=replace,
            keep_blank_columns=keep_blank_columns, tracking=tracking or (),
            orientation=orientation, progress=report,
        )  # fmt: skip
    print_lines(imported.lines(out, kind))


def downsample_factor(text: str) -> float | str:
    """``--downsample``'s value: ``auto`` or a number (checked by the library); anything else
    is a one-line error naming the option."""
    from ultron.errors import argument_error

    if text.strip().lower() == "auto":
        return "auto"
    try:
        return float(text)
    except ValueError:
        raise argument_error(
            "--downsample", f"expected a number ≥ 1 or auto, got {text!r}"
        ) from None


@command("dataset")
def info(dataset: Path) -> None:
    """Summarise a dataset: sweeps, frames, image size, pixel spacing, labels, extent.

    Args:
        dataset: Dataset directory (ultron-sweeps/1).
    """
    from rich.table import Table

    from ultron.data.label_import import label_sources
    from ultron.pipeline.dataset_info import dataset_info

    summary = dataset_info(dataset)
    data = summary.dataset
    table = Table(title=f"{dataset}")
    for column in ("sweep", "kind", "frames", "labelled frames", "labels"):
        table.add_column(
            column, justify="right" if column in ("frames", "labelled frames") else "left"
        )
    sources = label_sources(data)
    for sweep in data.sweeps:
        labelled = "—" if sweep.labels is None else str(len(sweep.labelled_frames))
        table.add_row(sweep.name, sweep.kind, str(sweep.n_frames), labelled, sources[sweep.name])
    console.print(table)
    print_lines(summary.lines())
    print_lines(summary.outlier_lines())
    print_lines(f"warning: {line}" for line in summary.units_warnings())
