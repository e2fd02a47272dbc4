"""``import-ultranerf`` and ``import-plus``: one recorded sweep added to an ``ultron-sweeps/1``
dataset directory (created, or extended by a new sweep).

The readers are :func:`ultron.data.importers.read_ultranerf` and
:func:`ultron.data.plus_import.read_plus`, the writer
:func:`ultron.data.importers.add_sweep_to_dataset`; this module runs them in the order that
refuses bad input before any work: the output folder is checked before the recording is read,
so a long read cannot end in an unwritable ``--out``.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Generic, TypeVar

from ultron.data.dataset import SWEEP_KINDS, ProbeGeometry
from ultron.data.importers import (
    DEFAULT_ORTHONORMALIZE_TOLERANCE,
    ImportReport,
    add_sweep_to_dataset,
    read_ultranerf,
)
from ultron.data.plus import sequence_stem
from ultron.data.plus_import import AUTO_DOWNSAMPLE, PlusImportReport, read_plus
from ultron.data.plus_orientation import orientation_flips
from ultron.errors import UltronInputError, argument_error
from ultron.outputs import check_dataset_out, is_inside

#: The reader's report: :class:`ImportReport` (Ultra-NeRF) or :class:`PlusImportReport`.
ReportT = TypeVar("ReportT", ImportReport, PlusImportReport)


@dataclass(frozen=True)
class ImportedSweep(Generic[ReportT]):
    """What an import added: the sweep's name, its probe geometry as read, how many sweeps the
    dataset holds now, and the reader's report (frames read, repairs made)."""

    name: str
    probe: ProbeGeometry
    n_sweeps: int
    report: ReportT

    def lines(self, out: str | Path, kind: str) -> list[str]:
        """What an import prints: for a PLUS recording its orientation, calibration, world
        frame, clip, kept and skipped frames and probe, then the frames added to ``out``."""
        report = self.report
        plus = isinstance(report, PlusImportReport)
        lines = plus_lines(report, self.probe, self.n_sweeps == 1) if plus else []
        lines.append(
            f"imported {report.n_frames} frames of {report.image_shape[0]}×"
            f"{report.image_shape[1]} as sweep {self.name!r} ({kind}) into {out}"
            f" ({self.n_sweeps} sweep(s))"
        )
        if isinstance(report, ImportReport) and report.n_poses_beyond_tolerance:
            lines.append(
                f"re-orthonormalised the rotation blocks: {report.n_poses_beyond_tolerance} poses"
                " deviated by more than the format's 1e-3 (largest"
                f" {report.max_rotation_deviation:.2e})"
            )
        return lines


def plus_lines(report: PlusImportReport, probe: ProbeGeometry, first: bool = True) -> list[str]:
    """The lines ``import-plus`` prints about the orientation, calibration, frames and world;
    ``first``: the dataset's first sweep, whose ``--downsample`` the others share (only then
    does the import suggest ``auto``)."""
    fit = report.fit
    flips = [axis for axis, flip in zip(("columns", "rows"), report.flips, strict=True) if flip]
    height, width = report.file_shape
    tracked = report.calibration_spread_mm is not None
    calibration = (
        f"Image → {report.world} per frame ({report.chain}, no --config: the calibration is in"
        f" the tracking; the frames' own calibrations agree to {report.calibration_spread_mm:.2g}"
        " mm)"
        if tracked
        else f"Image → {report.probe_frame}"
    )
    lines = [
        f"frames: {report.n_frames_file} of {height}×{width} (rows × columns), orientation"
        f" {report.orientation} → MF ({'flipped ' + ' and '.join(flips) if flips else 'no flip'})",
        f"{calibration}: {fit.spacing_mm[0]:.5f} mm per column ×"
        f" {fit.spacing_mm[1]:.5f} mm per row; its image axes are {abs(fit.shear_deg):.2f}° from"
        f" perpendicular: a rigid pose would move pixels by at most {fit.residual_max_mm:.3f} mm"
        f" (RMS {fit.residual_rms_mm:.3f} mm) from PLUS's map"
        + (
            "; frames resampled onto the rigid grid (every echo where PLUS puts it)"
            if report.resampled
            else ""
        ),
        f"world frame: {report.world} ({report.chain}{'' if tracked else ' · ImageToProbe'})",
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
    grain = report.grain_px
    if grain is not None and math.isfinite(grain):
        line = f"axial speckle grain: {grain:.2f} pixels of the file's frames"
        if first and report.downsample == 1 and grain > FINE_GRAIN_PX:
            line += (
                "; on frames this much finer than their speckle UltrON is slower and less"
                ' accurate (measured: docs/data.md, "The working resolution"):'
                " --downsample auto shrinks them to 2 pixels per grain"
            )
        lines.append(line)
    if report.downsample != 1:
        lines.append(f"downsampled by {report.downsample:g} to {probe.height_px}×{probe.width_px}")
    lines.append(
        f"probe: {probe.width_mm:.3f} mm wide × {probe.depth_mm:.3f} mm deep; pixel spacing"
        f" {probe.lateral_spacing_mm:.5f} mm lateral × {probe.axial_spacing_mm:.5f} mm axial"
    )
    return lines


def safe_sweep_name(path: str | Path) -> str:
    """A valid sweep name from ``path``'s last component (made absolute first, so ``.`` names
    the current folder): characters other than letters, digits, ``_``, ``.`` and ``-``
    become ``_`` and leading ``._-`` are dropped, since a sweep name starts with a letter or
    digit; ``sweep`` if nothing is left."""
    name = re.sub(r"[^A-Za-z0-9_.-]", "_", Path(path).resolve().name).lstrip("._-")
    return name or "sweep"


def import_ultranerf_sweep(
    src: str | Path,
    out: str | Path,
    width_mm: float,
    depth_mm: float,
    *,
    sweep_name: str | None = None,
    kind: str = "other",
    orthonormalize_tolerance: float = DEFAULT_ORTHONORMALIZE_TOLERANCE,
    replace: bool = False,
) -> ImportedSweep[ImportReport]:
    """Add an Ultra-NeRF sweep folder to a dataset (:func:`~ultron.data.importers.
    read_ultranerf`). ``out`` is checked first (``--out``).

    Args:
        src: Ultra-NeRF folder: images/0.png… or images.npy, and poses.npy.
        out: Dataset directory (created, or extended by a new sweep).
        width_mm: Probe width (lateral field of view), mm.
        depth_mm: Imaging depth, mm.
        sweep_name: Name of the new sweep (default: SRC's folder name).
        kind: Sweep kind: row, column, tilted or other.
        orthonormalize_tolerance: Largest rotation-block deviation from orthonormal that is
            repaired (nearest rotation), in [0, 1).
        replace: Replace an existing sweep of the same name.
    """
    check_dataset_out(out)  # before the frames are read
    name = sweep_name or safe_sweep_name(src)
    if Path(out, name).exists() and is_inside(src, Path(out, name)):
        raise UltronInputError(
            src, "SRC", f"is the folder of sweep {name!r} of {out}, which the import would write:"
            " import from a copy elsewhere, or name the sweep otherwise (--sweep-name)",
        )  # fmt: skip
    sweep, probe, report = read_ultranerf(
        src, width_mm, depth_mm, name, kind, orthonormalize_tolerance
    )
    dataset = add_sweep_to_dataset(out, sweep, probe, replace=replace)
    return ImportedSweep(name, probe, len(dataset.sweeps), report)


def import_plus_sweep(
    sequence: str | Path,
    config: str | Path | None,
    out: str | Path,
    *,
    to: str = "Reference",
    sweep_name: str | None = None,
    kind: str = "other",
    downsample: float | str = "auto",
    replace: bool = False,
    keep_blank_columns: bool = False,
    tracking: Sequence[str | Path] = (),
    orientation: str | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> ImportedSweep[PlusImportReport]:
    """Add a tracked PLUS / 3D Slicer recording to a dataset as a sweep
    (:func:`~ultron.data.plus_import.read_plus`); the import's provenance is kept in
    ``dataset.json``. ``kind`` (``--kind``) and ``out`` (``--out``) are checked before the
    recording is read.

    Args:
        sequence: PLUS / 3D Slicer sequence: .igs.mha, .seq.mha, .mha, .igs.nrrd, .seq.nrrd
            (raw or compressed).
        config: PLUS configuration XML holding the Image → Probe matrix (and the clip
            rectangle). Not needed where the frames carry Image → Reference transforms (PLUS's
            ImageToReference, as a 3D Slicer recording of PLUS's stream holds them), which
            hold the calibration.
        out: Dataset directory (created, or extended by a new sweep).
        to: World frame: Reference (moves with the patient) or Tracker.
        sweep_name: Name of the new sweep (default: the file's stem).
        kind: Sweep kind: row, column, tilted or other.
        downsample: auto (default): shrink the frames to two pixels per axial speckle grain,
            measured on them (the resolution the field is fitted at; a sweep added to a
            dataset takes its first PLUS sweep's factor); or this factor ≥ 1 (1: the file's
            own pixels; area-averaged, spacings updated).
        replace: Replace an existing sweep of the same name.
        keep_blank_columns: Keep the columns that are 0 in every frame (default: drop them,
            as outside the probe's aperture; a dataset holding PLUS sweeps already keeps its
            first sweep's columns, so that they share one probe geometry).
        tracking: A transform sequence saved apart from the frames, as 3D Slicer saves each
            tracked transform (.seq.mha; repeat for more): every frame gets its transforms
            interpolated at the frame's time (docs/data.md).
        orientation: The frames' orientation (MF, MN, UF or UN) where the file does not record
            it, as in a volume sequence saved by 3D Slicer.
        progress: Told (stage, done, total) as the import reads, resamples (read_plus) and
            writes ("writing", 0, 1) the sweep.
    """
    if kind not in SWEEP_KINDS:
        raise argument_error("--kind", f"{kind!r} is not one of {', '.join(SWEEP_KINDS)}")
    if orientation is not None:  # checked when given, also where the file records its own
        orientation_flips(orientation, "argument", "--orientation")
    check_dataset_out(out)  # before the recording is read
    name = sweep_name or safe_sweep_name(sequence_stem(sequence))
    first = _first_plus_import(Path(out))  # a sweep added to a dataset shares its geometry
    if downsample == AUTO_DOWNSAMPLE and first is not None:
        downsample = float(first.get("downsample", 1.0))
    sweep, probe, report = read_plus(
        sequence, config, to=to, name=name, kind=kind, downsample=downsample,
        columns=None if keep_blank_columns else _kept_columns(first),
        tracking=tracking, orientation=orientation, progress=progress,
    )  # fmt: skip
    if progress is not None:
        progress("writing", 0, 1)
    dataset = add_sweep_to_dataset(
        out, sweep, probe, replace=replace, sweep_metadata=report.metadata
    )
    return ImportedSweep(name, probe, len(dataset.sweeps), report)


#: Pixels per axial speckle grain above which the import suggests ``--downsample auto``.
FINE_GRAIN_PX = 3.0


def _first_plus_import(out: Path) -> dict | None:
    """The import record of the first PLUS sweep of the dataset at ``out``, or None."""
    meta_path = out / "dataset.json"
    if not meta_path.is_file():
        return None
    try:
        imports = json.loads(meta_path.read_text()).get("metadata", {}).get("imports", {})
    except (OSError, ValueError, AttributeError):
        return None  # the dataset's own loader names what is wrong with it
    for entry in imports.values() if isinstance(imports, dict) else ():
        if isinstance(entry, dict) and entry.get("source") == "plus":
            return entry
    return None


def _kept_columns(first: dict | None) -> tuple[int, int] | str | None:
    """The columns a PLUS sweep added to a dataset keeps, from ``first``, the import record of
    the dataset's first PLUS sweep (:func:`_first_plus_import`): the columns it kept (None: all,
    as a sweep imported before blank columns were dropped), or ``"signal"`` for a new dataset
    (:func:`~ultron.data.plus_import.read_plus`)."""
    if first is None:
        return "signal"
    kept = first.get("kept_columns")
    return None if kept is None else (int(kept[0]), int(kept[1]))
