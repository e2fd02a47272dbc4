"""Build an ``ultron-sweeps/1`` sweep from a PLUS / 3D Slicer recording.

PLUS places pixel (i, j) of frame k (i: column, j: row of the MF-oriented frame) at

    x = (To)ToTracker⁻¹ · ProbeToTracker · ImageToProbe · [i, j, 0, 1]ᵀ

(``To`` = Reference by default; a file that records ``ProbeTo<To>`` directly is read as it is;
without a configuration, the frames' own ``ImageTo<To>`` is the whole product: the per-frame
transforms and the calibration are read in :mod:`ultron.data.plus_poses`).
ultron's format places pixel (r, c) at probe point ((c − W/2)·s_x, r·s_y, 0) of a rigid
probe-to-world pose, so the affine ImageToProbe (it holds the pixel scale and, from a
calibration fit, usually a small shear) is factored into a rigid pose and two pixel spacings,
and the frames are resampled onto the rigid map's pixel grid where the fit moves a pixel
(:mod:`ultron.data.plus_geometry`), so the imported sweep places every echo where PLUS does,
corners included. Frames are flipped to MF (PLUS's orientation of B-mode frames, row 0 at the
transducer face as the format wants), clipped to the configuration's clip rectangle, narrowed
to the columns that hold signal (:func:`signal_columns`) and optionally area-downsampled with
the spacings updated.

Why the blank columns go: a linear probe's image is often stored wider than its aperture, with
columns that are 0 in every frame. Those columns were never insonified; kept, they ask the
acoustic field to render black tissue beside the bone, and a fit can settle there, rendering
every frame black (figures: docs/real-sweeps.md, "Blank columns"). The clip rectangle recorded
in the metadata is the narrowed one, so the pose of pixel (r, c) is PLUS's map of pixel
(r, c + start) of the clipped frame. The rigid fit spans the kept columns only; where the frames
are resampled onto its grid, the grid's corners and the kept rectangle's differ by up to the
fit's residual (a few pixels at each corner, read as 0 on one side and left out on the other).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ultron.data.dataset import ProbeGeometry, Sweep
from ultron.data.import_records import FRAME_FIELDS_KEY
from ultron.data.plus import read_sequence
from ultron.data.plus_config import PlusConfig, read_config
from ultron.data.plus_geometry import (
    RESAMPLE_RESIDUAL_MM,
    ImagePlaneFit,
    downsample_frames,
    downsampled_shape,
    fit_image_plane,
    resample_to_rigid,
)
from ultron.data.plus_orientation import orientation_flips
from ultron.data.plus_poses import Placement, WorldPoses, placement
from ultron.data.resolution import (
    GRAIN_FRAMES,
    PIXELS_PER_GRAIN,
    axial_grain_px,
    signal_columns,
)
from ultron.data.sequence_frames import SequenceFile
from ultron.errors import UltronInputError, argument_error


@dataclass(frozen=True)
class PlusImportReport:
    """What :func:`read_plus` did, for the CLI's summary and the dataset's metadata."""

    n_frames_file: int
    n_frames: int
    skipped: dict[str, int]
    file_shape: tuple[int, int]
    image_shape: tuple[int, int]
    orientation: str
    flips: tuple[bool, bool]
    probe_frame: str
    world: str
    chain: str
    clip: tuple[tuple[int, int], tuple[int, int]] | None
    fit: ImagePlaneFit
    downsample: float
    #: The frames were resampled onto the rigid grid (plus_geometry.resample_to_rigid).
    resampled: bool = False
    #: The frames' axial speckle grain, pixels (:func:`speckle_downsample`; ``--downsample
    #: auto`` shrinks them to 2 pixels per grain).
    grain_px: float | None = None
    #: The columns [start, stop) of the clipped frames that were kept (the others blank in
    #: every frame, :func:`signal_columns`); None: every column kept.
    kept_columns: tuple[int, int] | None = None
    #: The calibration came with the tracking (per-frame ImageTo<X>, no configuration): how
    #: far (mm) the frames' own calibrations move a frame corner from the common one; None:
    #: the calibration is the configuration's.
    calibration_spread_mm: float | None = None
    metadata: dict[str, Any] = field(default_factory=dict)


def _oriented_clipped(
    seq: SequenceFile, config: PlusConfig | None
) -> tuple[np.ndarray, tuple | None]:
    """Frames flipped to MF and clipped to the configuration's clip rectangle (if any)."""
    flip_columns, flip_rows = orientation_flips(seq.orientation, seq.path, "orientation")
    frames = seq.pixels[:, :: -1 if flip_rows else 1, :: -1 if flip_columns else 1]
    if config is None or config.clip_origin is None or config.clip_size is None:
        return np.ascontiguousarray(frames), None
    (i0, j0), (w, h) = config.clip_origin, config.clip_size
    height, width = frames.shape[1:]
    if i0 + w > width or j0 + h > height:
        swapped = ""
        if i0 + w <= height and j0 + h <= width:  # the header can tell: it fits the transpose
            swapped = (
                f"; it fits {height} × {width} frames: are width and height swapped in the"
                f" sequence's {seq.size_field}?"
            )
        raise UltronInputError(
            config.path,
            "VolumeReconstruction ClipRectangleSize",
            f"clip rectangle origin ({i0}, {j0}) size {w} × {h} exceeds the {width} × {height}"
            f" frames of {seq.path.name}{swapped}",
        )
    clipped = np.ascontiguousarray(frames[:, j0 : j0 + h, i0 : i0 + w])
    return clipped, ((i0, j0), (w, h))


def _narrowed(
    frames: np.ndarray, clip: tuple | None, columns: tuple[int, int] | None, where: Path
) -> tuple[np.ndarray, tuple | None, tuple[int, int] | None]:
    """``frames`` narrowed to ``columns`` [start, stop) (None: all), the clip rectangle that
    now describes them (origin moved by ``start``, width ``stop − start``) and the columns kept
    (None where all are). Columns outside the frames are an error naming the recording."""
    height, width = frames.shape[1:]
    if columns is None or tuple(columns) == (0, width):
        return frames, clip, None
    start, stop = (int(c) for c in columns)
    if not 0 <= start < stop <= width:
        raise UltronInputError(
            where,
            "columns",
            f"columns {start}–{stop - 1} (the dataset's first PLUS sweep keeps them) lie outside"
            f" this recording's {width} columns; import it into another dataset",
        )
    (i0, j0), _ = clip if clip is not None else ((0, 0), (width, height))
    narrowed = np.ascontiguousarray(frames[:, :, start:stop])
    return narrowed, ((i0 + start, j0), (stop - start, height)), (start, stop)


def read_plus(
    sequence: str | Path,
    config: str | Path | None,
    *,
    to: str = "Reference",
    name: str = "sweep",
    kind: str = "other",
    downsample: float | str = 1.0,
    columns: tuple[int, int] | str | None = "signal",
    tracking: Sequence[str | Path] = (),
    orientation: str | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> tuple[Sweep, ProbeGeometry, PlusImportReport]:
    """Read a PLUS / Slicer sequence and its PLUS configuration as one :class:`Sweep` in the
    ``to`` frame (Reference or Tracker, or any frame the file tracks) and its probe geometry.
    Without a configuration (``config`` None) the frames' own Image → ``to`` transforms (PLUS's
    ``ImageToReference``) place the pixels: they hold the calibration, factored out of them
    (:func:`~ultron.data.plus_geometry.factor_image_to_world`); no clip rectangle applies.

    ``columns`` narrows the clipped frames: ``"signal"`` to the columns where some imported
    frame has signal (:func:`signal_columns`), a (start, stop) pair to those columns (a sweep
    added to a dataset whose first sweep was narrowed), None to none.
    Frames with an image or transform status other than OK are skipped (counted in the
    report); every other problem is an :class:`UltronInputError` naming file and field.
    ``tracking``: transform sequences saved apart from the frames (3D Slicer's; each frame gets
    their transforms at its time, :func:`~ultron.data.tracking_files.with_tracking`);
    ``orientation``: the frames' orientation where the file does not record it.
    ``progress``, when given, is told (stage, done, total): ("reading", 0, 1) as the file is
    read, then ("resampling", frames done, frames) as sheared frames are resampled.
    """
    if isinstance(columns, str) and columns != "signal":
        raise argument_error(
            "columns", f"expected 'signal', (start, stop) or None, got {columns!r}"
        )
    auto = downsample == AUTO_DOWNSAMPLE
    if not auto and (
        isinstance(downsample, bool | str) or not (math.isfinite(downsample) and downsample >= 1)
    ):
        raise argument_error(
            "--downsample", f"expected a finite number ≥ 1 or 'auto', got {downsample!r}"
        )
    target = to[:1].upper() + to[1:]
    if not target.isascii() or not target.isalnum():
        raise argument_error("--to", f"expected a frame name such as Reference, got {to!r}")
    plus_config = read_config(config) if config is not None else None
    if progress is not None:
        progress("reading", 0, 1)
    raw, seq = _tracked_sequence(sequence, orientation, tracking)
    placed = placement(seq, plus_config, target)
    world = placed.world
    _check_tracking_used(tracking, world)
    frames, clip = _oriented_clipped(seq, plus_config)
    frames = frames[world.valid]
    wanted = signal_columns(frames) if columns == "signal" else columns
    frames, clip, kept = _narrowed(frames, clip, wanted, seq.path)  # type: ignore[arg-type]
    calibration = clipped_calibration(placed.image_to_probe, clip)
    height, width = frames.shape[1:]
    fit = fit_image_plane(calibration, width, height, placed.where, placed.field)
    poses = placed.probe_to_world @ fit.dataset_probe_to_probe(width)
    factor, grain_px = speckle_downsample(frames, fit.spacing_mm)
    if auto:
        downsample = factor
    shape = downsampled_shape(height, width, downsample)
    if min(shape) < MIN_FRAME_PX < min(height, width):
        raise argument_error(
            "--downsample", f"{downsample:g} leaves frames of {shape[0]} × {shape[1]} pixels (of"
            f" {height} × {width}); keep them at least {MIN_FRAME_PX} × {MIN_FRAME_PX}",
        )  # fmt: skip
    advance = None if progress is None else (lambda done, n: progress("resampling", done, n))
    images, resampled = on_sweep_grid(frames, calibration, fit, shape, advance)
    probe = ProbeGeometry(width * fit.spacing_mm[0], height * fit.spacing_mm[1], *shape)
    sweep = Sweep(name=name, kind=kind, images=images, probe_to_world=poses)
    report = PlusImportReport(
        n_frames_file=seq.n_frames,
        n_frames=int(world.valid.sum()),
        skipped=dict(world.skipped),
        file_shape=(int(seq.pixels.shape[1]), int(seq.pixels.shape[2])),
        image_shape=shape,
        orientation=seq.orientation,
        flips=orientation_flips(seq.orientation, seq.path, "orientation"),
        probe_frame=placed.probe_frame,
        world=target,
        chain=world.description,
        clip=clip,
        fit=fit,
        downsample=float(downsample),
        grain_px=grain_px,
        resampled=resampled,
        kept_columns=kept,
        calibration_spread_mm=placed.spread_mm,
    )
    metadata = _import_metadata(seq, plus_config, placed, report, np.flatnonzero(world.valid))
    metadata[FRAME_FIELDS_KEY] = raw.frame_fields_digest()  # tells the recording by its fields
    if tracking:
        metadata["tracking"] = [Path(path).name for path in tracking]
    return sweep, probe, replace(report, metadata=metadata)


#: The fewest rows or columns ``--downsample`` may leave a frame: what a scanline needs about
#: an echo (``label --auto``); a frame recorded smaller is imported as it is.
MIN_FRAME_PX = 3
#: ``--downsample``'s value that sets the factor from the frames' speckle
#: (:func:`speckle_downsample`).
AUTO_DOWNSAMPLE = "auto"


def speckle_downsample(frames: np.ndarray, spacing_mm: tuple[float, float]) -> tuple[float, float]:
    """The factor ≥ 1 that leaves :data:`~ultron.data.resolution.PIXELS_PER_GRAIN` pixels per
    axial speckle grain, and the grain in pixels (nan where unmeasurable: factor 1), measured
    on up to :data:`~ultron.data.resolution.GRAIN_FRAMES` evenly spaced frames of ``frames``
    (N, H, W) with pixel spacings ``spacing_mm`` (lateral, axial) — the resolution the field is
    fitted at (``fit_shape="auto"``), so that every stage works at the one the images carry."""
    height, width = frames.shape[1:]
    probe = ProbeGeometry(width * spacing_mm[0], height * spacing_mm[1], height, width)
    picks = np.linspace(0, len(frames) - 1, min(GRAIN_FRAMES, len(frames))).round().astype(int)
    grain = axial_grain_px(frames[picks], probe)
    factor = grain / PIXELS_PER_GRAIN if math.isfinite(grain) else 1.0
    return max(1.0, round(factor, 2)), grain


def _check_tracking_used(tracking: Sequence[str | Path], world: WorldPoses) -> None:
    """Refuse a ``--tracking`` file none of whose transforms is on the chain that places the
    frames (``world.chain``): given, it was meant to track them, and it would change nothing."""
    from ultron.data.tracking_files import read_transform_sequences

    for path in tracking:
        names = [t.name for t in read_transform_sequences(path)]
        if not set(names) & set(world.chain):
            raise UltronInputError(
                path, "--tracking", f"holds {', '.join(f'{n}Transform' for n in names)}; none is"
                f" on the chain that places the frames ({world.description}), so it would"
                " change nothing: give the file that tracks the probe, or --to its frame",
            )  # fmt: skip


def _tracked_sequence(
    sequence: str | Path, orientation: str | None, tracking: Sequence[str | Path]
) -> tuple[SequenceFile, SequenceFile]:
    """The recording as the file holds it (``orientation``: the frames' where the file does
    not record it), and with its frames given the transforms of the ``tracking`` files at
    their times (:func:`read_plus`; the same recording without ``tracking``)."""
    seq = read_sequence(sequence, orientation)
    if not tracking:
        return seq, seq
    from ultron.data.tracking_files import with_tracking

    return seq, with_tracking(seq, tracking)


def clipped_calibration(image_to_probe: np.ndarray, clip: tuple | None) -> np.ndarray:
    """The Image → Probe matrix of the clipped frames: PLUS's ``image_to_probe`` of the whole
    frame with its origin moved to the clip rectangle's (``((i0, j0), (w, h))``; None: none)."""
    calibration = np.array(image_to_probe, dtype=np.float64)
    if clip is not None:
        calibration[:3, 3] += clip[0][0] * calibration[:3, 0] + clip[0][1] * calibration[:3, 1]
    return calibration


def on_sweep_grid(
    frames: np.ndarray,
    calibration: np.ndarray,
    fit: ImagePlaneFit,
    shape: tuple[int, int],
    advance: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, bool]:
    """uint8 clipped, MF ``frames`` on the sweep's pixel grid: resampled onto the rigid fit's
    grid where the fit moves a pixel by more than :data:`RESAMPLE_RESIDUAL_MM` (then True;
    ``advance`` is told the frames resampled, :func:`resample_to_rigid`), then
    area-downsampled to ``shape``."""
    resampled = fit.residual_max_mm > RESAMPLE_RESIDUAL_MM
    if resampled:  # the rigid map places pixels off PLUS's: move the grey levels instead
        frames = resample_to_rigid(frames, calibration, fit, advance)
    return downsample_frames(frames, shape), resampled


def check_recording_frames(
    shape: tuple[int, int, int], record: dict[str, Any], where: str | Path, counted: bool = True
) -> None:
    """Refuse (naming ``where``) frames of ``shape`` (N, H, W) as a PLUS sweep's recording
    (``record``: the import's provenance, ``dataset.json``'s ``metadata.imports.<sweep>``) when
    their count (not for frames that are ``counted`` elsewhere: some frames only) or size does
    not fit it: the file's count and size where the record has them (imports since
    2026-12-04), else room for the frames kept and the clip rectangle."""
    kept = np.asarray(record["frames"], dtype=np.int64)
    n, height, width = shape
    expected = record.get("file_frames")
    if counted and ((expected is not None and n != expected) or n <= int(kept.max(initial=-1))):
        wanted = expected if expected is not None else f"at least {int(kept.max()) + 1}"
        raise UltronInputError(
            where, "frames", f"{n} frames; the recording ({record.get('sequence')}) has {wanted}"
        )
    file_shape = record.get("file_shape")
    if file_shape is not None and (height, width) != tuple(file_shape):
        raise UltronInputError(
            where, "frames", f"frames of {height} × {width} pixels (rows × columns); the"
            f" recording's are {file_shape[0]} × {file_shape[1]}",
        )  # fmt: skip
    clip = record.get("clip")
    if clip is not None:
        (i0, j0), (w, h) = clip["origin"], clip["size"]
        if i0 + w > width or j0 + h > height:
            raise UltronInputError(
                where, "frames", f"frames of {height} × {width} pixels cannot hold the import's"
                f" clip rectangle (origin {i0}, {j0}, size {w} × {h})",
            )  # fmt: skip


def frames_as_imported(
    frames: np.ndarray, record: dict[str, Any], shape: tuple[int, int], where: str | Path
) -> np.ndarray:
    """uint8 (K, H, W) frames of a recording taken the way :func:`read_plus` took its B-mode
    (``record`` as in :func:`check_recording_frames`, which the caller has passed): ``frames``
    are K of the frames it kept, MF-oriented and of the file's whole size; they are clipped to
    the recorded (narrowed) clip rectangle, resampled where it resampled and downsampled to
    ``shape``, the sweep's image shape. Anything of the recording (a mask per frame) then lies
    on the sweep's pixels as its B-mode does."""
    clip = record.get("clip")
    if clip is not None:
        (i0, j0), (w, h) = clip["origin"], clip["size"]
        frames = frames[:, j0 : j0 + h, i0 : i0 + w]
        clip = ((i0, j0), (w, h))
    frames = np.ascontiguousarray(frames)
    calibration = clipped_calibration(np.asarray(record["image_to_probe"]), clip)
    fit = fit_image_plane(
        calibration, frames.shape[2], frames.shape[1], where, "metadata.imports.image_to_probe"
    )
    images, _ = on_sweep_grid(frames, calibration, fit, shape)
    return images


def _import_metadata(
    seq: SequenceFile,
    config: PlusConfig | None,
    placed: Placement,
    report: PlusImportReport,
    frames: np.ndarray,
) -> dict[str, Any]:
    """Provenance of an imported sweep, kept in ``dataset.json``'s metadata."""
    fit = report.fit
    return {
        "source": "plus",
        "sequence": seq.path.name,
        "sequence_path": str(seq.path.resolve()),
        "config": None if config is None else config.path.name,
        "calibration_from": placed.field,
        "calibration_spread_mm": placed.spread_mm,
        "world": report.world,
        "transforms": report.chain,
        "orientation": report.orientation,
        "clip": None if report.clip is None else {"origin": report.clip[0], "size": report.clip[1]},
        "kept_columns": None if report.kept_columns is None else list(report.kept_columns),
        "image_to_probe": placed.image_to_probe.tolist(),
        "fitted_image_to_probe": fit.image_to_probe().tolist(),
        "pixel_spacing_mm": list(fit.spacing_mm),
        "shear_deg": fit.shear_deg,
        "rigid_fit_residual_mm": {"max": fit.residual_max_mm, "rms": fit.residual_rms_mm},
        "resampled_to_rigid_grid": report.resampled,
        "downsample": report.downsample,
        "frames": frames.tolist(),
        "file_frames": report.n_frames_file,
        "file_shape": list(report.file_shape),
        "skipped": report.skipped,
    }
