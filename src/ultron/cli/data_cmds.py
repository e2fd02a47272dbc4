"""``ultron import-ultranerf``, ``ultron import-plus`` and ``ultron info``."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from ultron.cli.common import check_range, console, user_errors

if TYPE_CHECKING:
    from ultron.data.dataset import ProbeGeometry
    from ultron.data.outliers import PoseOutlier
    from ultron.data.plus_import import PlusImportReport


@user_errors
def import_ultranerf(
    src: Annotated[
        Path, typer.Argument(help="Ultra-NeRF folder: images/0.png… or images.npy, and poses.npy.")
    ],
    width_mm: Annotated[
        float, typer.Option("--width-mm", help="Probe width (lateral field of view), mm.")
    ],
    depth_mm: Annotated[float, typer.Option("--depth-mm", help="Imaging depth, mm.")],
    out: Annotated[
        Path, typer.Option("--out", help="Dataset directory (created, or extended by a new sweep).")
    ],
    sweep_name: Annotated[
        str | None,
        typer.Option("--sweep-name", help="Name of the new sweep (default: SRC's folder name)."),
    ] = None,
    kind: Annotated[
        str, typer.Option("--kind", help="Sweep kind: row, column, tilted or other.")
    ] = "other",
    orthonormalize_tol: Annotated[
        float,
        typer.Option(
            "--orthonormalize-tol",
            help="Largest rotation-block deviation from orthonormal that is repaired (nearest"
            " rotation), in [0, 1).",
        ),
    ] = 0.05,
    replace: Annotated[
        bool, typer.Option("--replace", help="Replace an existing sweep of the same name.")
    ] = False,
) -> None:
    """Import an Ultra-NeRF sweep into an ultron-sweeps/1 dataset (repeat to add sweeps)."""
    from ultron.data.importers import MAX_ORTHONORMALIZE_TOLERANCE
    from ultron.pipeline.sweep_import import import_ultranerf_sweep

    check_range("--width-mm", width_mm, 0.0, low_open=True)
    check_range("--depth-mm", depth_mm, 0.0, low_open=True)
    tolerance_max = MAX_ORTHONORMALIZE_TOLERANCE
    check_range("--orthonormalize-tol", orthonormalize_tol, 0.0, tolerance_max, high_open=True)
    imported = import_ultranerf_sweep(
        src, out, width_mm, depth_mm, sweep_name=sweep_name, kind=kind,
        orthonormalize_tolerance=orthonormalize_tol, replace=replace,
    )  # fmt: skip
    report = imported.report
    console.print(
        f"imported {report.n_frames} frames of {report.image_shape[0]}×{report.image_shape[1]}"
        f" as sweep {imported.name!r} ({kind}) into {out} ({imported.n_sweeps} sweep(s))"
    )
    if report.n_poses_beyond_tolerance:
        console.print(
            f"re-orthonormalised the rotation blocks: {report.n_poses_beyond_tolerance} poses"
            f" deviated by more than the format's 1e-3 (largest {report.max_rotation_deviation:.2e})"
        )


@user_errors
def import_plus(
    sequence: Annotated[
        Path,
        typer.Argument(
            help="PLUS / 3D Slicer sequence: .igs.mha, .seq.mha, .mha, .igs.nrrd, .seq.nrrd"
            " (raw or compressed)."
        ),
    ],
    config: Annotated[
        Path,
        typer.Option("--config", help="PLUS configuration XML holding the Image → Probe matrix."),
    ],
    out: Annotated[
        Path, typer.Option("--out", help="Dataset directory (created, or extended by a new sweep).")
    ],
    to: Annotated[
        str,
        typer.Option("--to", help="World frame: Reference (moves with the patient) or Tracker."),
    ] = "Reference",
    sweep_name: Annotated[
        str | None,
        typer.Option("--sweep-name", help="Name of the new sweep (default: the file's stem)."),
    ] = None,
    kind: Annotated[
        str, typer.Option("--kind", help="Sweep kind: row, column, tilted or other.")
    ] = "other",
    downsample: Annotated[
        float,
        typer.Option(
            "--downsample",
            help="Shrink frames by this factor ≥ 1 (area-averaged; spacings updated).",
        ),
    ] = 1.0,
    replace: Annotated[
        bool, typer.Option("--replace", help="Replace an existing sweep of the same name.")
    ] = False,
    keep_blank_columns: Annotated[
        bool,
        typer.Option(
            "--keep-blank-columns",
            help="Keep the columns that are 0 in every frame (default: drop them, as outside"
            " the probe's aperture).",
        ),
    ] = False,
) -> None:
    """Import a tracked PLUS / 3D Slicer recording as a sweep (repeat to add sweeps)."""
    from ultron.pipeline.sweep_import import import_plus_sweep

    check_range("--downsample", downsample, 1.0)
    imported = import_plus_sweep(
        sequence, config, out, to=to, sweep_name=sweep_name, kind=kind, downsample=downsample,
        replace=replace, keep_blank_columns=keep_blank_columns,
    )  # fmt: skip
    report = imported.report
    for line in _plus_summary(report, imported.probe):
        console.print(line, highlight=False, soft_wrap=True)
    console.print(
        f"imported {report.n_frames} frames of {report.image_shape[0]}×{report.image_shape[1]}"
        f" as sweep {imported.name!r} ({kind}) into {out} ({imported.n_sweeps} sweep(s))",
        highlight=False,
        soft_wrap=True,
    )


def _plus_summary(report: PlusImportReport, probe: ProbeGeometry) -> list[str]:
    """The lines ``import-plus`` prints about the orientation, calibration, frames and world."""
    fit = report.fit
    flips = [axis for axis, flip in zip(("columns", "rows"), report.flips, strict=True) if flip]
    height, width = report.file_shape
    lines = [
        f"frames: {report.n_frames_file} of {height}×{width} (rows × columns), orientation"
        f" {report.orientation} → MF ({'flipped ' + ' and '.join(flips) if flips else 'no flip'})",
        f"Image → {report.probe_frame}: {fit.spacing_mm[0]:.5f} mm per column ×"
        f" {fit.spacing_mm[1]:.5f} mm per row; its image axes are {abs(fit.shear_deg):.2f}° from"
        f" perpendicular: a rigid pose would move pixels by at most {fit.residual_max_mm:.3f} mm"
        f" (RMS {fit.residual_rms_mm:.3f} mm) from PLUS's map"
        + (
            "; frames resampled onto the rigid grid (every echo where PLUS puts it)"
            if report.resampled
            else ""
        ),
        f"world frame: {report.world} ({report.chain} · ImageToProbe)",
    ]
    if report.clip is not None:
        (i0, j0), (w, h) = report.clip
        lines.append(f"clip rectangle: origin ({i0}, {j0}), {w} × {h} pixels")
    if report.kept_columns is not None:
        start, stop = report.kept_columns
        lines.append(
            f"kept columns {start}–{stop - 1}: the others are 0 in every frame (outside the"
            " aperture; --keep-blank-columns keeps them)"
        )
    skipped = sum(report.skipped.values())
    reasons = ", ".join(f"{n} × {reason}" for reason, n in sorted(report.skipped.items()))
    lines.append(
        f"skipped {skipped} of {report.n_frames_file} frames" + (f": {reasons}" if reasons else "")
    )
    if report.downsample != 1:
        lines.append(f"downsampled by {report.downsample:g} to {probe.height_px}×{probe.width_px}")
    lines.append(
        f"probe: {probe.width_mm:.3f} mm wide × {probe.depth_mm:.3f} mm deep; pixel spacing"
        f" {probe.lateral_spacing_mm:.5f} mm lateral × {probe.axial_spacing_mm:.5f} mm axial"
    )
    return lines


@user_errors
def info(
    dataset: Annotated[Path, typer.Argument(help="Dataset directory (ultron-sweeps/1).")],
) -> None:
    """Summarise a dataset: sweeps, frames, image size, pixel spacing, labels, extent."""
    from rich.table import Table

    from ultron.pipeline.dataset_info import dataset_info

    summary = dataset_info(dataset)
    data, probe = summary.dataset, summary.dataset.probe
    table = Table(title=f"{dataset}")
    for column in ("sweep", "kind", "frames", "labelled frames"):
        table.add_column(
            column, justify="right" if column != "sweep" and column != "kind" else "left"
        )
    for sweep in data.sweeps:
        labelled = "—" if sweep.labels is None else str(len(sweep.labelled_frames))
        table.add_row(sweep.name, sweep.kind, str(sweep.n_frames), labelled)
    console.print(table)
    lines = [
        f"sweeps: {len(data.sweeps)}   frames: {data.n_frames}   labelled frames:"
        f" {summary.n_labelled}",
        f"image size: {probe.height_px} rows (depth) × {probe.width_px} columns (scanlines)",
        f"probe: {probe.width_mm:g} mm wide × {probe.depth_mm:g} mm deep",
        f"pixel spacing: {probe.lateral_spacing_mm:.4f} mm lateral × {probe.axial_spacing_mm:.4f} mm axial",
        *_blank_columns_line(summary.lit_columns, probe.width_px),
        "bounding box (mm): "
        + "  ".join(
            f"{axis} [{lo:.2f}, {hi:.2f}]"
            for axis, lo, hi in zip("xyz", *summary.bounds_mm, strict=True)
        ),
        f"reference: {data.reference.name if data.reference else 'none'}"
        + (
            f" (visible part: {data.reference_visible_path.name})"
            if data.reference_visible_path
            else ""
        ),
    ]
    for line in lines:
        console.print(line, highlight=False)
    _warn_outliers(summary.outliers)
    for line in summary.units_warnings():
        console.print(f"warning: {line}", highlight=False)


def _blank_columns_line(lit: tuple[int, int], width: int) -> list[str]:
    """The line about columns that are 0 in every frame, when there are any."""
    start, stop = lit
    if (start, stop) == (0, width):
        return []
    return [
        f"columns with signal: {start}–{stop - 1} of {width}; the other {width - (stop - start)}"
        " are 0 in every frame (outside the aperture: the field fit ignores them)"
    ]


def _warn_outliers(outliers: Sequence[PoseOutlier]) -> None:
    """Print a warning per outlier pose (at most 10, then a count): reconstruct, finetune and
    fit-field refuse such a dataset."""
    for outlier in outliers[:10]:
        console.print(f"warning: outlier pose: {outlier.describe()}", highlight=False)
    if len(outliers) > 10:
        console.print(f"warning: {len(outliers) - 10} more outlier poses", highlight=False)
    if outliers:
        console.print(
            "warning: reconstruct, finetune and fit-field refuse a dataset with outlier poses"
            " (every grid is sized on the scanned volume)",
            highlight=False,
        )


def register(app: typer.Typer) -> None:
    app.command("import-ultranerf")(import_ultranerf)
    app.command("import-plus")(import_plus)
    app.command("info")(info)
