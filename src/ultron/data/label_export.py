"""A sweep's labels in its recording's frames: ``ultron label DATASET --export OUT``.

The inverse of ``label --masks`` (:mod:`ultron.data.label_import`): a sweep's labels —
automatic, imported or given — written as one mask per frame of the recording it came from, so
that a person can check them over the B-mode in 3D Slicer or any other tool, correct the frames
that ``label --auto``'s quality summary flags, and read them back with ``label --masks``.

- A sweep imported from PLUS / Slicer (``import-plus``): the masks have the recording's whole
  frames, every frame of the file. Each pixel of a frame the import kept takes the label of the
  sweep pixel the import made of it — the steps of
  :func:`~ultron.data.plus_import.frames_as_imported` (clip rectangle, columns kept, resampling
  onto the rigid pixel grid, downsampling) inverted, nearest pixel. Pixels outside the clip
  rectangle and frames the import skipped are left empty (0).
- Any other sweep: its own frames, as they are.

Values: bone ``bone_value`` (1), unsure ``unsure_value`` (2), background 0, and every pixel of a
frame nobody annotated 0 — an empty mask, which ``label --masks`` (``--annotated nonempty``, its
default) reads as a frame nobody annotated. A frame annotated as all background, with no bone
and no unsure pixel, reads back the same way: :class:`LabelExport` counts them.

Formats, by ``OUT``'s ending: ``.npy`` (N, H, W) in ``orientation`` (MF by default, as ``label
--masks`` reads one); a MetaImage sequence (``.mha``, ``.seq.mha``, ``.igs.mha``) or an NRRD
one (``.nrrd``, ``.seq.nrrd``) in the recording's own orientation, recorded in its
``UltrasoundImageOrientation``. Given the ``recording`` (the sequence file the sweep was
imported from), a MetaImage export is its twin — the recording's header, per-frame
timestamps and transforms included, with only the pixel type and data replaced — so a viewer
places each mask where it places the frame. An NRRD export is a labelmap volume sequence as 3D
Slicer's Sequences module documents one (the list axis, then three spatial axes of one slice;
``DataNodeClassName`` a labelmap; ``axis 0 index values`` the recording's per-frame timestamps,
else the frame numbers), carrying the recording's per-frame fields when it is given.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ultron import atomic
from ultron.data.dataset import SweepDataset, one_sweep
from ultron.data.import_records import FRAME_FIELDS_KEY
from ultron.data.plus import read_metaimage_header, read_sequence, sequence_stem
from ultron.data.plus_geometry import RESAMPLE_RESIDUAL_MM, fit_image_plane, rigid_to_image_pixels
from ultron.data.plus_import import check_recording_frames, clipped_calibration
from ultron.data.plus_orientation import orientation_flips
from ultron.data.tracking_files import frame_times
from ultron.data.validation import LABEL_TARGET, LABEL_UNANNOTATED
from ultron.errors import UltronInputError, argument_error
from ultron.outputs import check_output_file, is_inside

#: Endings of MetaImage exports (one file: the header and the data together).
METAIMAGE_SUFFIXES = (".igs.mha", ".seq.mha", ".mha")
#: Endings of NRRD exports (one file).
NRRD_SUFFIXES = (".igs.nrrd", ".seq.nrrd", ".nrrd")
#: Frames mapped or written at once (bounds the working memory of a full-size recording).
_CHUNK_FRAMES = 32
#: Slicer's per-item index of a volume sequence (its list axis comes first: axis 0).
_INDEX_VALUES = "axis 0 index values"
#: MetaImage header fields that describe the data and are written anew in a twin.
_PAYLOAD_FIELDS = (
    "ElementType",
    "ElementNumberOfChannels",
    "CompressedData",
    "CompressedDataSize",
    "BinaryData",
    "BinaryDataByteOrderMSB",
    "ElementByteOrderMSB",
    "HeaderSize",
    "ElementDataFile",
)


@dataclass(frozen=True)
class LabelExportConfig:
    """How labels are written as masks (module doc).

    Attributes:
        bone_value: The mask value written for bone (1–65535).
        unsure_value: The mask value written for unsure pixels of an annotated frame (1–65535,
            not bone_value).
        orientation: PLUS's orientation of a .npy export (MF: row 0 at the transducer, as
            label --masks reads one); a sequence file is written in the recording's own.
    """

    bone_value: int = 1
    unsure_value: int = 2
    orientation: str = "MF"

    def __post_init__(self) -> None:
        for name in ("bone_value", "unsure_value"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 0 < value < 2**16:
                raise argument_error(name, f"expected an integer in [1, 65535], got {value!r}")
        if self.bone_value == self.unsure_value:
            raise argument_error("unsure_value", "must differ from the bone value")
        orientation_flips(self.orientation, "argument", "orientation")

    @property
    def dtype(self) -> np.dtype:
        """uint8 where both values fit, else uint16."""
        return np.dtype(np.uint8 if max(self.bone_value, self.unsure_value) < 256 else np.uint16)


@dataclass(frozen=True)
class LabelExport:
    """What an export wrote."""

    path: Path
    frames: int
    shape: tuple[int, int]
    orientation: str
    annotated_frames: int
    empty_annotated_frames: int
    read_back: str
    recording: Path | None = None
    note: str | None = None

    def lines(self) -> tuple[list[str], list[str]]:
        """The command's report and its warnings."""
        lines = [
            f"{self.path}: {self.frames} masks of {self.shape[0]} × {self.shape[1]} pixels"
            f" ({self.orientation}), {self.annotated_frames} frames annotated",
            f"read back (after editing) with: {self.read_back}",
        ]
        if self.recording is not None:
            lines.insert(1, f"header and per-frame fields from {self.recording}")
        warnings = [] if self.note is None else [self.note]
        if self.empty_annotated_frames:
            warnings.append(
                f"{self.empty_annotated_frames} annotated frames hold no bone and no unsure"
                " pixel: their empty masks read back as frames nobody annotated (add"
                " --annotated all to read every frame as annotated)"
            )
        return lines, warnings


def recording_pixel_map(
    record: dict[str, Any], shape: tuple[int, int], where: str | Path
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which sweep pixel the import made of each pixel of a PLUS recording's (MF) frame.

    ``record`` is the sweep's import provenance (``metadata.imports.<sweep>``), ``shape`` the
    sweep's (H, W). Returns (row, column, covered), each of the recording's frame size: a
    pixel (i, j) inside the clip rectangle maps to the rigid grid's pixel (i', j') = M⁻¹·(i, j,
    1) (M: :func:`~ultron.data.plus_geometry.rigid_to_image_pixels`; the identity where the
    import did not resample), then to the sweep pixel whose centre lies nearest,
    (round(j'·H/h), round(i'·W/w)) for a clip rectangle of h × w (the downsampling's centres lie
    at k·w/W); ``covered`` is False outside the clip rectangle and where (i', j') falls off the
    rigid grid."""
    file_height, file_width = (int(v) for v in record["file_shape"])
    clip = record.get("clip")
    if clip is None:
        (i0, j0), (width, height) = (0, 0), (file_width, file_height)
    else:
        (i0, j0), (width, height) = clip["origin"], clip["size"]
    calibration = clipped_calibration(
        np.asarray(record["image_to_probe"]), None if clip is None else ((i0, j0), (width, height))
    )
    fit = fit_image_plane(calibration, width, height, where, "metadata.imports.image_to_probe")
    j, i = np.mgrid[0:height, 0:width].astype(np.float64)
    if fit.residual_max_mm > RESAMPLE_RESIDUAL_MM:  # as the import decided (on_sweep_grid)
        inverse = np.linalg.inv(rigid_to_image_pixels(calibration, fit))
        i, j = (inverse[k, 0] * i + inverse[k, 1] * j + inverse[k, 2] for k in (0, 1))
    inside = (i >= -0.5) & (i < width - 0.5) & (j >= -0.5) & (j < height - 0.5)
    rows = np.clip(np.rint(j * shape[0] / height), 0, shape[0] - 1).astype(np.int64)
    columns = np.clip(np.rint(i * shape[1] / width), 0, shape[1] - 1).astype(np.int64)
    full = [np.zeros((file_height, file_width), dtype=dtype) for dtype in (np.int64,) * 2 + (bool,)]
    for target, values in zip(full, (rows, columns, inside), strict=True):
        target[j0 : j0 + height, i0 : i0 + width] = values
    return full[0], full[1], full[2]


def coded_masks(
    labels: np.ndarray,
    config: LabelExportConfig,
    covered: np.ndarray | None = None,
    annotated: np.ndarray | None = None,
) -> np.ndarray:
    """Masks of ``labels`` (0, 1, 255; N, H, W): ``config``'s bone and unsure values,
    background 0, and 0 outside ``covered`` (H, W; None: everywhere covered) and in every frame
    that is not ``annotated`` (N; None: the frames with a known pixel)."""
    if annotated is None:
        annotated = (labels != LABEL_UNANNOTATED).any(axis=(1, 2))
    code = np.zeros(256, dtype=config.dtype)  # a label's mask value, read off in one gather
    code[LABEL_TARGET], code[LABEL_UNANNOTATED] = config.bone_value, config.unsure_value
    masks = code[labels]
    if covered is not None:
        masks[:, ~covered] = 0
    masks[~annotated] = 0
    return masks


def recording_masks(
    labels: np.ndarray,
    record: dict[str, Any],
    config: LabelExportConfig,
    where: str | Path,
    annotated: np.ndarray | None = None,
) -> np.ndarray:
    """MF masks (the recording's frames, every frame of the file) of a PLUS sweep's ``labels``
    (module doc); ``annotated`` as in :func:`coded_masks`."""
    rows, columns, covered = recording_pixel_map(record, labels.shape[1:], where)
    kept = np.asarray(record["frames"], dtype=np.int64)
    masks = np.zeros((int(record["file_frames"]), *rows.shape), dtype=config.dtype)
    if annotated is None:
        annotated = (labels != LABEL_UNANNOTATED).any(axis=(1, 2))
    chunks = np.flatnonzero(annotated)  # frames nobody annotated stay empty: nothing to map
    for first in range(0, len(chunks), _CHUNK_FRAMES):  # a few full-size frames at a time
        frames = chunks[first : first + _CHUNK_FRAMES]
        mapped = labels[frames][:, rows, columns]
        masks[kept[frames]] = coded_masks(mapped, config, covered, np.ones(len(frames), bool))
    return masks


def _plus_record(dataset: SweepDataset, sweep: str) -> dict[str, Any] | None:
    record = (dataset.metadata.get("imports") or {}).get(sweep)
    if not (isinstance(record, dict) and record.get("source") == "plus"):
        return None
    if record.get("file_frames") is None or record.get("file_shape") is None:
        raise UltronInputError(
            "dataset.json", f"metadata.imports.{sweep}", "an import made before 2026-12-04"
            " (no file_frames / file_shape): import the recording again to export its labels",
        )  # fmt: skip
    return record


def export_labels(
    root: str | Path,
    sweep: str | None,
    out: str | Path,
    config: LabelExportConfig | None = None,
    recording: str | Path | None = None,
) -> LabelExport:
    """Write sweep ``sweep``'s labels (of the dataset at ``root``) as masks at ``out``
    atomically (module doc); ``recording``: the sequence file the sweep was imported from,
    whose header a sequence export copies (default: the file the import read, where it still
    is). A sweep without labels, an ending not listed, or a
    recording whose frames differ from the import's is an error naming it. ``sweep`` None:
    the dataset's only sweep."""
    config = config or LabelExportConfig()
    root, out = Path(root), check_output_file(out, "--export")
    dataset = SweepDataset.load(root)
    if sweep is None:
        sweep = one_sweep([s.name for s in dataset.sweeps], "--export")
    target = dataset.sweep(sweep)
    if target.labels is None:
        raise UltronInputError(root / sweep, "labels.npy", "missing: the sweep has no labels")
    kind = _format(out)
    record = _plus_record(dataset, sweep)
    _check_not_an_input(out, root, dataset, [recording, (record or {}).get("sequence_path")])
    header, note = None, None
    if recording is not None:
        if record is None:
            raise argument_error("recording", f"sweep {sweep!r} was not imported from PLUS")
        header = _recording_header(Path(recording), record, kind)
    elif record is not None and (recording := _recorded(record, kind)) is not None:
        try:  # the file the import read, where it still is: not asked for, so not required
            header = _recording_header(recording, record, kind)
        except UltronInputError as exc:
            note = f"written without the recording's header: {exc}"
    elif record is not None and kind != "npy" and record.get("sequence_path"):
        if not Path(str(record["sequence_path"])).is_file():
            note = (
                f"written without the recording's header: {record['sequence_path']}, which the"
                " import read, is no longer there (--recording names where it is now)"
            )
    labels = np.asarray(target.labels)
    n_unsure = np.count_nonzero(labels == LABEL_UNANNOTATED, axis=(1, 2))  # per frame, once
    unsure, annotated = n_unsure > 0, n_unsure < labels[0].size
    orientation = config.orientation.strip().upper()
    if record is None:
        if orientation != "MF":
            raise argument_error(
                "orientation", f"sweep {sweep!r} was not imported from PLUS: its masks are of"
                " its own frames, as they are",
            )  # fmt: skip
        masks = coded_masks(labels, config, annotated=annotated)
    else:
        masks = recording_masks(labels, record, config, root / "dataset.json", annotated)
        if kind != "npy":
            orientation = str(record.get("orientation") or "MF")
    flip_columns, flip_rows = orientation_flips(orientation, "argument", "orientation")
    masks = masks[:, :: -1 if flip_rows else 1, :: -1 if flip_columns else 1]  # MF ↔ it
    _write(out, kind, masks, orientation, header)
    empty = annotated & ~unsure & ~(labels == LABEL_TARGET).any(axis=(1, 2))
    return LabelExport(
        out, len(masks), tuple(masks.shape[1:]), orientation, int(annotated.sum()),
        int(empty.sum()), _read_back(root, sweep, out, config, orientation, kind),
        None if header is None else Path(recording), note,  # type: ignore[arg-type]
    )  # fmt: skip


def _check_not_an_input(
    out: Path, root: Path, dataset: SweepDataset, recordings: list[Any]
) -> None:
    """Refuse an export path that would replace what it is made from: a file of the dataset
    (``dataset.json``, anything in a sweep's folder, the reference meshes) or the recording
    (``recordings``: the one given and the one the import read; None where unknown)."""
    owned = [root / "dataset.json", *(root / s.name for s in dataset.sweeps)]
    owned += [p for p in (dataset.reference, dataset.reference_visible_path) if p is not None]
    for path in owned:
        if is_inside(out, path):
            raise UltronInputError(
                out, "--export", f"is {'in ' if path.is_dir() else ''}{path.name}, part of the"
                f" dataset at {root}: the export would replace what it reads; write it elsewhere",
            )  # fmt: skip
    for recording in recordings:
        if recording and Path(str(recording)).exists() and is_inside(out, str(recording)):
            raise UltronInputError(
                out, "--export", "is the recording the sweep was imported from: the masks"
                " would replace its B-mode frames; write them to another file",
            )  # fmt: skip


def _recorded(record: dict[str, Any], kind: str) -> Path | None:
    """The recording the import read (``sequence_path``, imports since 2026-12-05) where it
    still is and a ``kind`` export can copy its header; else None."""
    path = Path(str(record.get("sequence_path") or ""))
    if kind == "npy" or not record.get("sequence_path") or not path.is_file():
        return None
    if kind == "metaimage" and not path.name.lower().endswith(METAIMAGE_SUFFIXES):
        return None
    return path


def _format(out: Path) -> str:
    lower = out.name.lower()
    if lower.endswith(".npy"):
        return "npy"
    if lower.endswith(METAIMAGE_SUFFIXES):
        return "metaimage"
    if lower.endswith(NRRD_SUFFIXES):
        return "nrrd"
    endings = ", ".join((".npy", *METAIMAGE_SUFFIXES, *NRRD_SUFFIXES))
    raise argument_error("export", f"{out.name}: expected a file ending in {endings}")


def _read_back(
    root: Path, sweep: str, out: Path, config: LabelExportConfig, orientation: str, kind: str
) -> str:
    """The ``label --masks`` command that reads the export back."""
    parts = ["ultron", "label", str(root), "--masks", str(out), "--sweeps", sweep]
    if config.bone_value != 1:
        parts += ["--bone-value", str(config.bone_value)]
    parts += ["--unsure-value", str(config.unsure_value)]
    if kind == "npy" and orientation != "MF":
        parts += ["--orientation", orientation]
    return shlex.join([*parts, "--replace"])


def _recording_header(path: Path, record: dict[str, Any], kind: str) -> dict[str, str]:
    """The header fields an export of ``kind`` copies from the recording at ``path`` (module
    doc), after checking that its frames are the ones the sweep was imported from."""
    if kind == "npy":
        raise argument_error("recording", "a .npy export has no header to copy it into")
    sequence = read_sequence(path, record.get("orientation"), field="--recording", header_only=True)
    check_recording_frames(sequence.pixels.shape, record, path)
    if sequence_stem(path) != sequence_stem(record.get("sequence") or path.name):
        raise UltronInputError(
            path, "--recording", f"the sweep was imported from {record.get('sequence')}, not"
            f" {path.name}",
        )  # fmt: skip
    digest = record.get(FRAME_FIELDS_KEY)  # imports since 2026-12-05
    if digest is not None and sequence.frame_fields_digest() != digest:
        raise UltronInputError(
            path, "--recording", "its per-frame fields (timestamps, transforms, statuses) are"
            " not those of the recording the sweep was imported from",
        )  # fmt: skip
    per_frame = {
        sequence.frame_field_key(k, name): value
        for k, fields in enumerate(sequence.frame_fields)
        for name, value in fields.items()
    }
    if kind == "nrrd":
        try:  # Slicer's index: the frames' times (per-frame, or a volume sequence's own)
            times = frame_times(sequence)
        except UltronInputError:
            return per_frame  # the frame numbers index it
        per_frame[_INDEX_VALUES] = " ".join(repr(float(t)) for t in times)
        return per_frame
    if not path.name.lower().endswith(METAIMAGE_SUFFIXES):
        raise argument_error(
            "export", "a MetaImage twin needs a MetaImage recording; export to .seq.nrrd instead"
        )
    fields, _ = read_metaimage_header(path)
    payload = {name.lower() for name in _PAYLOAD_FIELDS}
    return {key: value for key, value in fields.items() if key.lower() not in payload}


def _write(
    out: Path, kind: str, masks: np.ndarray, orientation: str, header: dict[str, str] | None
) -> None:
    """``masks`` (N, H, W) written atomically as ``kind``."""
    if kind == "npy":
        atomic.save_npy(out, masks)
        return
    n, height, width = masks.shape
    if kind == "nrrd":
        import nrrd

        header = dict(header or {})
        timed = _INDEX_VALUES in header
        fields = {  # Slicer's volume sequence: the list axis, then three spatial (one slice)
            "type": str(masks.dtype), "dimension": 4, "space": "left-posterior-superior",
            "sizes": [n, width, height, 1], "kinds": ["list", "domain", "domain", "domain"],
            "labels": ["time" if timed else "frame", "", "", ""],
            "space directions": np.vstack([np.full(3, np.nan), np.eye(3)]),
            "space origin": np.zeros(3), "encoding": "gzip",
            "DataNodeClassName": "vtkMRMLLabelMapVolumeNode", "axis 0 index type": "numeric",
            _INDEX_VALUES: header.pop(_INDEX_VALUES, " ".join(str(k) for k in range(n))),
            "UltrasoundImageOrientation": orientation, **header,
        }  # fmt: skip
        with atomic.atomic_open(out) as handle:  # the list axis varies fastest
            nrrd.write(handle, np.moveaxis(masks, 0, -1)[None], fields, index_order="C")
        return
    fields = header or {
        "ObjectType": "Image", "NDims": "3", "DimSize": f"{width} {height} {n}",
        "Kinds": "domain domain list",
    }  # fmt: skip
    fields = {**fields, "UltrasoundImageOrientation": orientation}
    element = "MET_UCHAR" if masks.dtype == np.uint8 else "MET_USHORT"
    fields.update(
        BinaryData="True", BinaryDataByteOrderMSB="False", CompressedData="False",
        ElementType=element, ElementDataFile="LOCAL",
    )  # fmt: skip
    text = "".join(f"{key} = {value}\n" for key, value in fields.items())
    little = masks.dtype.newbyteorder("<")
    with atomic.atomic_open(out) as handle:
        handle.write(text.encode("latin-1"))
        for start in range(0, n, _CHUNK_FRAMES):  # no second copy of a full-size recording
            handle.write(np.ascontiguousarray(masks[start : start + _CHUNK_FRAMES], little).data)
