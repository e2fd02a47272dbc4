"""A person's bone segmentation as a sweep's labels: ``ultron label DATASET --masks MASKS``.

An annotator segments bone in the frames of the recording itself, in 3D Slicer or any other
tool, as one 2D mask per frame: ``MASKS`` is a ``.npy`` integer array (N, H, W), a folder of
``0.png, 1.png, …`` (grey, one per frame) or an 8- or 16-bit sequence file as PLUS and Slicer
write them (a labelmap sequence). The masks are read in the frames' own geometry:

- a sweep imported from PLUS / Slicer (``import-plus``): the recording's whole frames, every
  frame of the file (skipped ones included), in MF orientation — row 0 at the transducer face,
  columns towards the probe's marked side, as PLUS and Slicer display B-mode
  (``orientation`` declares another of PLUS's orientations; a sequence file's own
  ``UltrasoundImageOrientation`` wins). They are then taken through the
  steps the import took the B-mode (:func:`~ultron.data.plus_import.frames_as_imported`: the
  frames kept, the clip rectangle, the columns kept, the resampling onto the rigid pixel grid,
  the downsampling), so each label lies on the pixel whose echo the annotator marked;
- any other sweep: the sweep's own frames, (N, H, W) of its ``images.npy``; so too masks of a
  PLUS sweep that have the sweep's shape and not the recording's (its labels, edited).

Labels follow the annotation convention the simulator's annotator and the paper use: bone
(:data:`~ultron.data.validation.LABEL_TARGET`) where the mask is bone, background everywhere
else in an annotated frame (acoustic shadow included: the compensated loss decides what it
costs), and 255 in a frame nobody annotated, in pixels the mask marks unsure
(``unsure_value``), and in pixels of the sweep that the recording's frame does not cover. A
sweep pixel that the resampling or downsampling draws from several mask pixels takes the label
of the larger share of the known ones: bone where at least half of its known part is bone,
unsure where less than half of it is known.

Which frames are annotated: with ``annotated="nonempty"`` (the default) the frames whose mask
holds some bone or unsure pixel — a segmentation sequence holds an empty mask for every frame
nobody painted; with ``"all"`` every frame, an empty mask meaning "no bone here".
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ultron.data.auto_label_dataset import MASKS_KEY as METADATA_KEY
from ultron.data.auto_label_dataset import METADATA_KEY as AUTO_LABELS_KEY
from ultron.data.auto_label_dataset import (
    auto_label_records,
    check_labelling,
    label_shares,
    record_matches,
    write_labels,
)
from ultron.data.dataset import SweepDataset
from ultron.data.importers import png_numbers, read_png_files
from ultron.data.plus import SEQUENCE_SUFFIXES, read_sequence
from ultron.data.plus_import import check_recording_frames, frames_as_imported
from ultron.data.plus_orientation import orientation_flips
from ultron.data.validation import (
    LABEL_BACKGROUND,
    LABEL_TARGET,
    LABEL_UNANNOTATED,
    input_file,
    load_npy,
)
from ultron.errors import UltronInputError, argument_error

#: What ``annotated`` may say.
ANNOTATED = ("nonempty", "all")
#: A mask value's share, in 1/255, at or above which a resampled pixel takes it (one half).
_HALF = 128
#: Frames of masks read and mapped at once (:func:`sweep_mask_labels`).
CHUNK_FRAMES = 32


@dataclass(frozen=True)
class MaskImportConfig:
    """How a mask reads as labels (module doc).

    Attributes:
        bone_value: The mask value that marks bone (default: every value other than 0 and
            unsure_value).
        unsure_value: A mask value that marks pixels the annotator leaves unsure (label 255;
            default: none).
        annotated: nonempty (frames whose mask marks something are annotated, the others
            unsure) or all (every frame is annotated; an empty mask means no bone).
        orientation: PLUS's orientation of the masks of a PLUS sweep: MF (row 0 at the
            transducer, as PLUS and Slicer display B-mode), MN, UF or UN (a sequence file's
            own UltrasoundImageOrientation wins).
        frames: The frame each mask belongs to, when the masks are of some frames only:
            frame numbers of the recording's file (a PLUS sweep) or of the sweep, one per
            mask, in the masks' order; the frames not listed are unsure (default: one mask per
            frame).
    """

    bone_value: int | None = None
    unsure_value: int | None = None
    annotated: str = "nonempty"
    orientation: str = "MF"
    frames: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        for name in ("bone_value", "unsure_value"):
            value = getattr(self, name)
            if value is not None and (
                isinstance(value, bool) or not isinstance(value, int) or not 0 < value < 2**16
            ):
                raise argument_error(name, f"expected an integer in [1, 65535], got {value!r}")
        if self.bone_value is not None and self.bone_value == self.unsure_value:
            raise argument_error("unsure_value", "must differ from the bone value")
        if self.annotated not in ANNOTATED:
            raise argument_error(
                "annotated", f"expected one of {', '.join(ANNOTATED)}, got {self.annotated!r}"
            )
        orientation_flips(self.orientation, "argument", "orientation")
        if self.frames is not None:
            numbers = list(self.frames)
            if not numbers or any(
                isinstance(v, bool) or not isinstance(v, int) or v < 0 for v in numbers
            ):
                raise argument_error("frames", f"expected frame numbers ≥ 0, got {self.frames!r}")
            if len(set(numbers)) != len(numbers):
                raise argument_error("frames", "lists a frame more than once")


@dataclass(frozen=True)
class MaskImportSummary:
    """What an import wrote into one sweep."""

    sweep: str
    frames: int
    annotated_frames: int
    bone: float
    background: float
    unsure: float
    replaced: bool
    #: Lines the command prints as warnings (:func:`_coding_warning`).
    warnings: tuple[str, ...] = ()

    def lines(self, root: str | Path) -> list[str]:
        """The command's report: where the labels went and what they hold."""
        return [
            f"{Path(root) / self.sweep / 'labels.npy'}: {self.annotated_frames} of {self.frames}"
            f" frames annotated; bone {100 * self.bone:.2f} %, background"
            f" {100 * self.background:.1f} %, unsure {100 * self.unsure:.1f} % of the pixels"
            + (" (replaced the sweep's labels)" if self.replaced else "")
        ]


#: The most frames ``--frames`` may list: 11 hours of a recording at 25 frames/s, far beyond any
#: sweep; counted before a range is expanded, so ``0:3000000000`` is refused at once.
MAX_LISTED_FRAMES = 10**6


def parse_frames(text: str) -> tuple[int, ...]:
    """``--frames``' text as frame numbers: comma-separated items, each a number ``N`` or a
    range ``A:B`` or ``A:B:S`` (from A up to B, B left out, in steps of S, as Python counts):
    ``0:100:10,105`` is 0, 10, …, 90, 105. More than :data:`MAX_LISTED_FRAMES` is an error."""
    numbers: list[int] = []
    listed = 0
    for item in text.split(","):
        parts = item.strip().split(":")
        try:
            values = [int(part) for part in parts]
        except ValueError:
            values = []
        if not values or len(values) > 3 or min(values) < 0 or (len(values) == 3 and not values[2]):
            raise argument_error(
                "frames", f"expected numbers or ranges A:B[:S] of numbers ≥ 0, got {item!r}"
            )
        span = values if len(values) == 1 else range(*values)
        listed += len(span)
        if listed > MAX_LISTED_FRAMES:
            raise argument_error(
                "frames", f"lists more than {MAX_LISTED_FRAMES:,} frames (at {item!r}): no"
                " recording has that many; give the frames the masks are of",
            )  # fmt: skip
        numbers.extend(span)
    return tuple(numbers)


def read_masks(
    path: str | Path, orientation: str = "MF"
) -> tuple[np.ndarray, str, tuple[int, ...] | None]:
    """The masks at ``path``, their orientation and, for PNGs named by frame number with gaps
    (``0.png, 10.png, 20.png, …``), the frames they are of (else None): a ``.npy`` integer
    array (N, H, W), a folder of numbered PNGs (both in ``orientation``) or an 8- or 16-bit
    sequence file as PLUS and Slicer write them (a labelmap sequence: its own
    ``UltrasoundImageOrientation``, else ``orientation``); anything else is an error naming
    the file."""
    path = Path(path)
    frames = None
    if path.is_dir():
        by_number = png_numbers(path)
        masks = read_png_files(list(by_number.values()))
        if list(by_number) != list(range(len(by_number))):
            frames = tuple(by_number)
    elif path.name.lower().endswith(SEQUENCE_SUFFIXES):
        sequence = read_sequence(path, orientation, "MASKS", labelmap=True)
        masks, orientation = sequence.pixels, sequence.orientation
    else:
        input_file(path, "MASKS")
        if path.suffix.lower() != ".npy":
            raise UltronInputError(
                path, "MASKS", "expected a .npy array (N, H, W), a folder of 0.png, 1.png, … or"
                f" a sequence file ({', '.join(SEQUENCE_SUFFIXES)})",
            )  # fmt: skip
        masks = load_npy(path, "masks", mmap=True)
    if masks.ndim != 3 or min(masks.shape) < 1:
        raise UltronInputError(path, "masks", f"expected shape (N, H, W), got {masks.shape}")
    if masks.dtype.kind not in "uib":
        raise UltronInputError(path, "masks", f"expected integer values, got dtype {masks.dtype}")
    if masks.dtype.kind == "i" and masks.size and int(masks.min()) < 0:
        raise UltronInputError(path, "masks", f"negative value {int(masks.min())}")
    return masks, orientation, frames


def mask_labels(masks: np.ndarray, config: MaskImportConfig) -> np.ndarray:
    """uint8 labels of ``masks`` in their own geometry (module doc): 1, 0 or 255."""
    unsure = np.zeros(masks.shape, dtype=bool)
    if config.unsure_value is not None:
        unsure = masks == config.unsure_value
    if config.bone_value is None:
        bone = (masks != 0) & ~unsure
    else:
        bone = masks == config.bone_value
    labels = np.where(bone, LABEL_TARGET, LABEL_BACKGROUND).astype(np.uint8)
    labels[unsure] = LABEL_UNANNOTATED
    if config.annotated == "nonempty":
        labels[~(bone | unsure).any(axis=(1, 2))] = LABEL_UNANNOTATED
    return labels


def labels_on_sweep(
    labels: np.ndarray, record: dict[str, Any], shape: tuple[int, int], where: str | Path
) -> np.ndarray:
    """MF ``labels`` of K frames the import kept, of the recording's whole size, on a PLUS
    sweep's pixels: the bone share and the known share (0–255) taken through the import's steps
    (:func:`~ultron.data.plus_import.frames_as_imported`), then read as the module doc says."""
    out = np.full((len(labels), *shape), LABEL_UNANNOTATED, dtype=np.uint8)
    annotated = (labels != LABEL_UNANNOTATED).any(axis=(1, 2))
    if not annotated.any():  # frames nobody annotated stay unsure: nothing to resample
        return out
    labels = labels[annotated]
    known = np.where(labels != LABEL_UNANNOTATED, 255, 0).astype(np.uint8)
    bone = np.where(labels == LABEL_TARGET, 255, 0).astype(np.uint8)
    known = frames_as_imported(known, record, shape, where).astype(np.int32)
    bone = frames_as_imported(bone, record, shape, where).astype(np.int32)
    mapped = np.where(2 * bone >= known, LABEL_TARGET, LABEL_BACKGROUND).astype(np.uint8)
    mapped[known < _HALF] = LABEL_UNANNOTATED
    out[annotated] = mapped
    return out


def sweep_mask_labels(
    dataset: SweepDataset,
    sweep: str,
    masks: np.ndarray,
    config: MaskImportConfig,
    where: Path,
    orientation: str | None = None,
) -> np.ndarray:
    """The labels ``masks`` (in ``orientation``, default ``config.orientation``) give sweep
    ``sweep`` of ``dataset`` (module doc): masks of a PLUS sweep's recording taken through the
    import's steps; masks of the sweep's own frames, (N, H, W) of its ``images.npy``, as they
    are — of a PLUS sweep too, when that is their shape and not the recording's (labels made
    on the sweep and edited). With ``config.frames`` the masks are of the frames listed. The
    masks may be memory-mapped: they are read :data:`CHUNK_FRAMES` frames at a time, so a
    recording of 10³ full-size frames needs no more than a few of them in memory."""
    target = dataset.sweep(sweep)
    record = (dataset.metadata.get("imports") or {}).get(sweep)
    labels = np.full(target.images.shape, LABEL_UNANNOTATED, dtype=np.uint8)
    numbers = None if config.frames is None else np.asarray(config.frames, dtype=np.int64)
    if numbers is not None and len(numbers) != len(masks):
        raise UltronInputError(
            where, "masks", f"{len(masks)} masks for the {len(numbers)} frames --frames lists"
        )
    if _of_recording(masks.shape, target.images.shape, record, numbers is None):
        try:
            check_recording_frames(masks.shape, record, where, counted=numbers is None)
        except UltronInputError as exc:  # name the other form masks may take, too
            n, height, width = target.images.shape
            raise UltronInputError(
                exc.where,
                exc.field,
                f"{exc.problem} (or, masks of the sweep's own frames, {n} of {height} × {width})",
            ) from None
        flips = orientation_flips(orientation or config.orientation, where, "orientation")
        kept = np.asarray(record["frames"], dtype=np.int64)
        on_sweep, of_mask = _pairs(kept, numbers, record.get("file_frames"), where)

        def mapped(chunk: np.ndarray) -> np.ndarray:
            chunk = chunk[:, :: -1 if flips[1] else 1, :: -1 if flips[0] else 1]
            return labels_on_sweep(
                mask_labels(chunk, config), record, target.images.shape[1:], where
            )
    else:
        if masks.shape[1:] != target.images.shape[1:] or (
            numbers is None and len(masks) != len(target.images)
        ):
            raise UltronInputError(
                where, "masks", f"shape {masks.shape}; sweep {sweep!r} has frames of"
                f" {target.images.shape} (N, H, W), which masks of a sweep not imported from"
                " PLUS must match",
            )  # fmt: skip
        on_sweep, of_mask = _pairs(np.arange(len(labels)), numbers, len(labels), where)

        def mapped(chunk: np.ndarray) -> np.ndarray:
            return mask_labels(chunk, config)

    for start in range(0, len(on_sweep), CHUNK_FRAMES):
        chunk = np.asarray(masks[of_mask[start : start + CHUNK_FRAMES]])
        labels[on_sweep[start : start + CHUNK_FRAMES]] = mapped(chunk)
    return labels  # 0, 1 and 255 by construction


def _pairs(
    frames: np.ndarray, numbers: np.ndarray | None, n_numbers: int | None, where: Path
) -> tuple[np.ndarray, np.ndarray]:
    """(sweep frame, mask) index pairs: sweep frame i shows frame ``frames[i]`` (of the file,
    or of the sweep); mask k is of frame ``numbers[k]`` (None: of frame k). A number at or
    beyond ``n_numbers`` (the frames there are; None: unknown) is an error naming ``where``."""
    if numbers is None:
        return np.arange(len(frames)), frames
    if n_numbers is not None and int(numbers.max()) >= n_numbers:
        raise UltronInputError(
            where, "frames", f"--frames lists frame {int(numbers.max())}; there are {n_numbers}"
        )
    position = {int(f): k for k, f in enumerate(numbers)}
    on_sweep = np.asarray([i for i, f in enumerate(frames) if int(f) in position], dtype=np.int64)
    of_mask = np.asarray([position[int(frames[i])] for i in on_sweep], dtype=np.int64)
    return on_sweep, of_mask


def _of_recording(
    shape: tuple[int, ...], sweep_shape: tuple[int, ...], record: Any, counted: bool = True
) -> bool:
    """Whether masks of ``shape`` are read as a PLUS recording's (``record``: the sweep's import
    provenance; None or another source: never): unless they have the sweep's shape and not the
    recording's (a record without the recording's size: unless they have the sweep's). Not
    ``counted`` (masks of listed frames): their frame size alone decides."""
    if not (isinstance(record, dict) and record.get("source") == "plus"):
        return False
    frames, size = record.get("file_frames"), record.get("file_shape")
    if not counted:
        shape, sweep_shape = tuple(shape[1:]), tuple(sweep_shape[1:])
        recording = None if size is None else tuple(size)
    else:
        recording = None if frames is None or size is None else (frames, *size)
    if tuple(shape) != tuple(sweep_shape):
        return True
    return recording is not None and tuple(shape) == recording


def import_mask_labels(
    root: str | Path,
    sweep: str | None,
    masks_path: str | Path,
    config: MaskImportConfig | None = None,
    replace: bool = False,
) -> MaskImportSummary:
    """Write the labels of the masks at ``masks_path`` into sweep ``sweep`` of the dataset at
    ``root``, with the masks' provenance under ``metadata.label_imports.<sweep>`` of
    ``dataset.json`` (an automatic-labels record of the sweep is dropped: its labels are a
    person's now), in :func:`~ultron.data.auto_label_dataset.write_labels`' interruptible
    order. Everything is checked before anything is written; a sweep that
    has labels is refused unless ``replace``. ``sweep`` None: the dataset's only sweep."""
    config = config or MaskImportConfig()
    if not isinstance(config, MaskImportConfig):
        raise argument_error("config", f"expected a MaskImportConfig, got {type(config).__name__}")
    root, masks_path = Path(root), Path(masks_path)
    dataset, (name,) = check_labelling(
        root, None if sweep is None else [sweep], replace, "--sweeps", "the masks", "--masks", 1
    )
    masks, orientation, named = read_masks(masks_path, config.orientation)
    if named is not None:  # PNGs named by the frames they are of
        if config.frames is not None and tuple(config.frames) != named:
            raise UltronInputError(
                masks_path, "frames", f"the PNG names give frames {_listed(named)}; --frames"
                f" lists {_listed(config.frames)}",
            )  # fmt: skip
        config = dataclasses.replace(config, frames=named)
    labels = sweep_mask_labels(dataset, name, masks, config, masks_path, orientation)
    if not (labels == LABEL_TARGET).any():
        raise UltronInputError(
            masks_path, "masks", f"no bone pixel reaches sweep {name!r}'s frames (bone_value"
            f" {config.bone_value if config.bone_value is not None else 'any non-zero'})",
        )  # fmt: skip
    replaced = dataset.sweep(name).labels is not None
    imports = dict(dataset.metadata.get(METADATA_KEY) or {})
    imports[name] = {"masks": str(masks_path.resolve()), "config": asdict(config)}
    write_labels(root, dataset, {name: labels}, METADATA_KEY, imports, AUTO_LABELS_KEY)
    annotated = int((labels != LABEL_UNANNOTATED).any(axis=(1, 2)).sum())
    return MaskImportSummary(
        name, int(labels.shape[0]), annotated, **label_shares(labels), replaced=replaced,
        warnings=_coding_warning(masks, config),
    )  # fmt: skip


def _coding_warning(masks: np.ndarray, config: MaskImportConfig) -> tuple[str, ...]:
    """A warning where neither value was given and the masks hold more than one value besides
    0: every one of them was read as bone, though one may mark unsure pixels (``label
    --export`` writes unsure as 2)."""
    if config.bone_value is not None or config.unsure_value is not None or masks.dtype == bool:
        return ()
    flat = np.asarray(masks).reshape(-1)
    small = flat.dtype in (np.uint8, np.uint16)  # a count per value; else sort them
    present = np.flatnonzero(np.bincount(flat)) if small else np.unique(flat)
    values = [int(v) for v in present if v != 0]
    if len(values) < 2:
        return ()
    listed = ", ".join(str(v) for v in values[:6]) + (", …" if len(values) > 6 else "")
    return (
        f"the masks hold the values {listed} besides 0, all read as bone: if one marks unsure"
        " pixels (label --export writes them as 2), read them again with --unsure-value VALUE"
        " --replace",
    )


def label_sources(dataset: SweepDataset) -> dict[str, str]:
    """Where each sweep's labels came from: ``auto`` (``label --auto``), ``masks`` (``label
    --masks``), ``given`` (written with the dataset: the simulator's annotator, CT-derived
    labels, a script) or ``none``."""
    automatic = auto_label_records(dataset)
    imported = dataset.metadata.get(METADATA_KEY) or {}
    sources = {}
    for sweep in dataset.sweeps:
        if sweep.labels is None:
            sources[sweep.name] = "none"
        elif sweep.name in automatic:
            sources[sweep.name] = "auto"
        else:
            record = imported.get(sweep.name)
            masks = isinstance(record, dict) and record_matches(record, sweep.labels)
            sources[sweep.name] = "masks" if masks else "given"
    return sources


def _listed(frames: tuple[int, ...]) -> str:
    """The first frames of ``frames`` for a message."""
    head = ", ".join(str(f) for f in frames[:5])
    return head + (f", … ({len(frames)} in all)" if len(frames) > 5 else "")
