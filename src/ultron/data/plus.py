"""Reading what PLUS and 3D Slicer write: tracked ultrasound sequences and PLUS configurations.

A *sequence* (``.igs.mha``, ``.seq.mha``, ``.mha``/``.mhd``, ``.igs.nrrd``, ``.seq.nrrd``,
``.nrrd``/``.nhdr``; raw or compressed) holds N 2D frames and per-frame fields named
``Seq_Frame<NNNN>_<Field>``: tracking transforms ``<From>To<To>Transform`` (16 numbers, a
row-major 4 × 4 matrix, mm), their ``…TransformStatus`` (``OK``, ``INVALID``, ``MISSING`` …),
``Timestamp`` and the image status (``ImageStatus`` in MetaImage, ``Status`` in NRRD). The
header gives ``UltrasoundImageOrientation`` (``ultrasound image orientation`` in NRRD).

How each format is read:

- **MetaImage** (``.mha``/``.mhd``) by a small, validated header reader of this module plus
  numpy / zlib for the payload: the header is plain ``Key = Value`` text up to
  ``ElementDataFile``, the payload raw bytes or one zlib stream (``CompressedData = True``).
  SimpleITK 2.5 would also return the per-frame fields (as metadata strings), but it is not a
  dependency of ultron (≈ 260 MB installed) and reports a truncated payload as "No such file
  or directory".
- **NRRD** (``.nrrd``/``.nhdr``) with pynrrd, which returns the per-frame ``key:=value`` fields
  as strings and decodes raw and gzip payloads (also detached data files), in
  :mod:`ultron.data.plus_nrrd`; the frame layout and fields are interpreted here for both.

The configuration is read by :mod:`ultron.data.plus_config`.

Every problem is an :class:`~ultron.errors.UltronInputError` naming the file and the field.
"""

from __future__ import annotations

import math
import re
import zlib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ultron.data.plus_orientation import ORIENTATION_FLIPS, orientation_flips
from ultron.data.validation import contained_path, input_file
from ultron.errors import UltronInputError
from ultron.memory import check_fits_in_memory

#: File name endings read as sequences (longest first, so that a stem drops the whole ending).
SEQUENCE_SUFFIXES = (
    ".igs.mha",
    ".seq.mha",
    ".igs.mhd",
    ".seq.mhd",
    ".igs.nrrd",
    ".seq.nrrd",
    ".igs.nhdr",
    ".seq.nhdr",
    ".mha",
    ".mhd",
    ".nrrd",
    ".nhdr",
)
_METAIMAGE_SUFFIXES = (".mha", ".mhd")

#: Image statuses and transform statuses that mean "valid".
STATUS_OK = "OK"
#: Image-status field names: MetaImage sequences write ``ImageStatus``, NRRD ones ``Status``.
IMAGE_STATUS_FIELDS = ("ImageStatus", "Status")

#: A per-frame field's key, ``Seq_Frame0012_ProbeToTrackerTransform``: (frame, field name).
FRAME_FIELD = re.compile(r"^seq_frame(\d+)_(.+)$", re.IGNORECASE)
_NAN_TOKEN = re.compile(r"^[-+]?nan(\(.*\))?$", re.IGNORECASE)
_MAX_HEADER_LINE = 1 << 20
#: What a labelmap sequence (``read_sequence(…, labelmap=True)``) may hold besides uint8: the
#: MetaImage element types of 8- and 16-bit integers, as Slicer writes labelmaps (the NRRD
#: types are in :mod:`ultron.data.plus_nrrd`).
_LABELMAP_METAIMAGE = {"MET_UCHAR": "u1", "MET_CHAR": "i1", "MET_USHORT": "u2", "MET_SHORT": "i2"}


@dataclass(frozen=True)
class SequenceFile:
    """The frames and fields of one sequence file.

    ``pixels`` is uint8 (N, H, W) in the file's orientation (row = image y, column = image x);
    ``fields`` are the header fields other than per-frame ones; ``frame_fields[k]`` holds frame
    k's fields, named without their ``Seq_Frame<NNNN>_`` prefix. ``size_field`` names the field
    holding the frame count (``DimSize`` or ``sizes``) for messages.
    """

    path: Path
    pixels: np.ndarray
    orientation: str
    fields: Mapping[str, str]
    frame_fields: tuple[Mapping[str, str], ...]
    size_field: str

    @property
    def n_frames(self) -> int:
        return int(self.pixels.shape[0])

    def field(self, name: str) -> str | None:
        """A header field by name, ignoring case and spaces (``UltrasoundImageType`` matches
        NRRD's ``ultrasound image type``)."""
        return _lookup(self.fields, name)

    def frame_field_key(self, frame: int, name: str) -> str:
        """The header key of frame ``frame``'s field ``name``, as PLUS writes it."""
        return f"Seq_Frame{frame:04d}_{name}"

    def transform_names(self) -> list[str]:
        """The per-frame transforms some frame has (``ProbeToTracker`` for the field
        ``ProbeToTrackerTransform``), sorted."""
        names = {
            key[: -len("Transform")]
            for fields in self.frame_fields
            for key in fields
            if key.endswith("Transform") and len(key) > len("Transform")
        }
        return sorted(names)


# --------------------------------------------------------------------------- helpers
def _normal_key(name: str) -> str:
    return name.replace(" ", "").replace("_", "").lower()


def _lookup(fields: Mapping[str, str], name: str) -> str | None:
    wanted = _normal_key(name)
    for key, value in fields.items():
        if _normal_key(key) == wanted:
            return value
    return None


def sequence_stem(path: str | Path) -> str:
    """The file name without its sequence ending (``a.igs.mha`` → ``a``)."""
    name = Path(path).name
    lower = name.lower()
    for suffix in SEQUENCE_SUFFIXES:
        if lower.endswith(suffix) and len(name) > len(suffix):
            return name[: -len(suffix)]
    return Path(path).stem


def parse_matrix(text: str, where: str | Path, field: str) -> np.ndarray:
    """A row-major 4 × 4 matrix from 16 whitespace-separated numbers (NaN allowed: a frame's
    transform may be NaN when its status is not OK)."""
    tokens = text.split()
    if len(tokens) != 16:
        raise UltronInputError(
            where,
            field,
            f"expected 16 numbers (a row-major 4 × 4 matrix), got {len(tokens)}",
        )
    values = []
    for token in tokens:
        if _NAN_TOKEN.match(token):
            values.append(math.nan)
            continue
        try:
            values.append(float(token))
        except ValueError:
            raise UltronInputError(where, field, f"{token!r} is not a number") from None
    return np.array(values, dtype=np.float64).reshape(4, 4)


def _split_frame_fields(
    fields: Mapping[str, str], n_frames: int, path: Path, size_field: str
) -> tuple[dict[str, str], tuple[dict[str, str], ...]]:
    """Header fields → (non-frame fields, per-frame fields); a frame number beyond the frame
    count of ``size_field`` is an error."""
    plain: dict[str, str] = {}
    frames: list[dict[str, str]] = [{} for _ in range(n_frames)]
    for key, value in fields.items():
        match = FRAME_FIELD.match(key)
        if match is None:
            plain[key] = value
            continue
        frame = int(match.group(1))
        if frame >= n_frames:
            raise UltronInputError(
                path,
                key,
                f"frame {frame} is beyond the {n_frames} frames of {size_field}"
                f" (frame count does not match the per-frame fields)",
            )
        frames[frame][match.group(2)] = value
    return plain, tuple(frames)


def _frame_axes(
    sizes: list[int], kinds: list[str] | None, path: Path, size_field: str, kinds_field: str
) -> tuple[int, int, int | None]:
    """File axes (0 = fastest) of image x, image y and the frame list (None: one frame)."""
    if kinds is None:  # PLUS: without Kinds the last axis lists the frames
        kinds = ["domain"] * len(sizes)
        if len(sizes) > 2:
            kinds[-1] = "list"
    if len(kinds) != len(sizes):
        raise UltronInputError(
            path, kinds_field, f"{len(kinds)} kinds for the {len(sizes)} axes of {size_field}"
        )
    lists = [i for i, kind in enumerate(kinds) if kind.lower() in ("list", "time")]
    domains = [i for i, kind in enumerate(kinds) if kind.lower() in ("domain", "space")]
    other = [kind for kind in kinds if kind.lower() not in ("list", "time", "domain", "space")]
    if other or len(lists) > 1 or len(domains) < 2:
        raise UltronInputError(
            path,
            kinds_field,
            f"axes {kinds} are not 2D frames: expected two spatial axes and at most one frame"
            " list (no vector or colour axis)",
        )
    thick = [sizes[i] for i in domains[2:] if sizes[i] != 1]
    if thick:
        raise UltronInputError(
            path, size_field, f"frames are 3D ({sizes}); only 2D frames can be imported"
        )
    return domains[0], domains[1], (lists[0] if lists else None)


def _placeholder(sizes: list[int], axes: tuple[int, int, int | None], dtype) -> np.ndarray:
    """A read-only all-zero (N, H, W) view of no memory: a header-only read's ``pixels``."""
    x_axis, y_axis, list_axis = axes
    n = sizes[list_axis] if list_axis is not None else 1
    return np.broadcast_to(np.zeros((), dtype=dtype), (n, sizes[y_axis], sizes[x_axis]))


def _arrange_frames(flat: np.ndarray, sizes: list[int], axes: tuple[int, int, int | None]):
    """Raw values (fastest axis first in the file) → (N, H, W)."""
    x_axis, y_axis, list_axis = axes
    nd = len(sizes)
    array = flat.reshape(sizes[::-1])
    order = [nd - 1 - a for a in (list_axis, y_axis, x_axis) if a is not None]
    rest = [k for k in range(nd) if k not in order]
    array = array.transpose(order + rest)
    n = sizes[list_axis] if list_axis is not None else 1
    return np.ascontiguousarray(array.reshape(n, sizes[y_axis], sizes[x_axis]))


# --------------------------------------------------------------------------- MetaImage
def _header_lines(path: Path) -> Iterator[tuple[int, str, int]]:
    """(line number, text, offset after the line) of a MetaImage header, up to and including
    ``ElementDataFile``."""
    try:
        with path.open("rb") as handle:
            for number in range(1, 10**9):
                raw = handle.readline(_MAX_HEADER_LINE)
                if not raw:
                    return
                if not raw.endswith(b"\n") and len(raw) == _MAX_HEADER_LINE:
                    raise UltronInputError(
                        path, "header", f"line {number} is too long: not a MetaImage header"
                    )
                yield number, raw.decode("latin-1").strip(), handle.tell()
    except OSError as exc:
        raise UltronInputError(path, "header", f"cannot be read ({exc.strerror})") from None


def read_metaimage_header(path: Path) -> tuple[dict[str, str], int]:
    """The ``Key = Value`` fields of a MetaImage header (in order) and the byte offset where a
    ``LOCAL`` payload starts (right after the ``ElementDataFile`` line)."""
    fields: dict[str, str] = {}
    for number, line, offset in _header_lines(path):
        if not line:
            continue
        key, sep, value = line.partition("=")
        key, value = key.strip(), value.strip()
        if not sep or not key or not key.replace("_", "").isalnum():
            raise UltronInputError(
                path, "header", f"line {number} is not 'Key = Value': not a MetaImage header"
            )
        if key in fields:
            raise UltronInputError(path, key, f"given twice (line {number})")
        fields[key] = value
        if key.lower() == "elementdatafile":
            return fields, offset
    raise UltronInputError(
        path, "ElementDataFile", "missing: the header never ends (not a MetaImage sequence?)"
    )


def _int_list(fields: Mapping[str, str], name: str, path: Path) -> list[int] | None:
    value = _lookup(fields, name)
    if value is None:
        return None
    try:
        numbers = [int(token) for token in value.split()]
    except ValueError:
        raise UltronInputError(path, name, f"expected integers, got {value!r}") from None
    if not numbers or min(numbers) < 1:
        raise UltronInputError(path, name, f"expected positive integers, got {value!r}")
    return numbers


def _metaimage_layout(
    fields: Mapping[str, str], path: Path, labelmap: bool = False
) -> tuple[list[int], tuple, np.dtype]:
    sizes = _int_list(fields, "DimSize", path)
    if sizes is None:
        raise UltronInputError(path, "DimSize", "missing: the frame size and count are unknown")
    ndims = _int_list(fields, "NDims", path)
    if ndims is not None and ndims != [len(sizes)]:
        raise UltronInputError(path, "DimSize", f"has {len(sizes)} sizes but NDims is {ndims}")
    element = (_lookup(fields, "ElementType") or "").upper()
    if element != "MET_UCHAR" and not (labelmap and element in _LABELMAP_METAIMAGE):
        labelmap_types = "MET_UCHAR, MET_CHAR, MET_USHORT or MET_SHORT (a labelmap)"
        expected = labelmap_types if labelmap else "MET_UCHAR (8-bit B-mode)"
        raise UltronInputError(path, "ElementType", f"{element or 'missing'}; expected {expected}")
    msb = (_lookup(fields, "BinaryDataByteOrderMSB") or "False").lower() == "true"
    dtype = np.dtype(_LABELMAP_METAIMAGE[element]).newbyteorder(">" if msb else "<")
    channels = _lookup(fields, "ElementNumberOfChannels")
    if channels not in (None, "1"):
        raise UltronInputError(
            path, "ElementNumberOfChannels", f"{channels}; expected 1 (grey B-mode)"
        )
    if (_lookup(fields, "BinaryData") or "True").lower() != "true":
        raise UltronInputError(path, "BinaryData", "only binary pixel data can be read")
    kinds = _lookup(fields, "Kinds")
    axes = _frame_axes(sizes, kinds.split() if kinds else None, path, "DimSize", "Kinds")
    return sizes, axes, dtype


def _payload_source(fields: Mapping[str, str], path: Path, offset: int) -> tuple[Path, int]:
    data_file = _lookup(fields, "ElementDataFile") or ""
    if data_file.upper() == "LOCAL":
        return path, offset
    if data_file.upper() == "LIST" or "%" in data_file or not data_file:
        raise UltronInputError(
            path, "ElementDataFile", f"{data_file!r}: only LOCAL or one data file is supported"
        )
    source = contained_path(path.parent, data_file, path, "ElementDataFile")
    input_file(source, "ElementDataFile")
    return source, 0


def _inflate(compressed: bytes, n_bytes: int, path: Path) -> bytes:
    """One zlib (or gzip) stream that must decode to exactly ``n_bytes``."""
    inflater = zlib.decompressobj(zlib.MAX_WBITS | 32)
    try:
        data = inflater.decompress(compressed, n_bytes + 1)
    except zlib.error as exc:
        raise UltronInputError(
            path, "CompressedData", f"corrupt compressed payload (zlib: {exc})"
        ) from None
    if len(data) > n_bytes:
        raise UltronInputError(
            path, "CompressedData", f"payload holds more than the {n_bytes} bytes of DimSize"
        )
    if len(data) < n_bytes or not inflater.eof:
        raise UltronInputError(
            path,
            "CompressedData",
            f"truncated compressed payload: it decodes to {len(data)} of the {n_bytes} bytes"
            " DimSize needs",
        )
    return data


def _read_metaimage_payload(
    fields: Mapping[str, str], path: Path, offset: int, n_bytes: int
) -> np.ndarray:
    source, start = _payload_source(fields, path, offset)
    compressed = (_lookup(fields, "CompressedData") or "False").lower() == "true"
    held = source.stat().st_size - start
    if not compressed and held != n_bytes:
        problem = "truncated payload" if held < n_bytes else "payload longer than DimSize"
        raise UltronInputError(
            path, "ElementDataFile", f"{problem}: {held} bytes where DimSize needs {n_bytes}"
            " (a wrong DimSize, or a file cut short or appended to)",
        )  # fmt: skip
    check_fits_in_memory(2 * n_bytes, path, "DimSize", f"frames of {n_bytes} bytes")
    with source.open("rb") as handle:
        handle.seek(start)
        if not compressed:
            return np.frombuffer(handle.read(n_bytes), dtype=np.uint8)
        size = _lookup(fields, "CompressedDataSize")
        limit = -1
        if size is not None:
            if not size.strip().isdigit():
                raise UltronInputError(path, "CompressedDataSize", f"{size!r} is not a size")
            limit = int(size)
        blob = handle.read(limit)
        if limit >= 0 and len(blob) < limit:
            raise UltronInputError(
                path,
                "CompressedDataSize",
                f"truncated compressed payload: {len(blob)} of {limit} bytes present",
            )
    return np.frombuffer(_inflate(blob, n_bytes, path), dtype=np.uint8)


def _orientation(plain: Mapping[str, str], default: str | None, path: Path, field: str) -> str:
    """The file's ``UltrasoundImageOrientation``, else ``default`` (None: it is required, and
    its absence an error saying how to give it, as a volume sequence saved by Slicer lacks it)."""
    orientation = _lookup(plain, "UltrasoundImageOrientation")
    if orientation is None and default is None:
        raise UltronInputError(
            path, field, f"missing; expected one of {', '.join(sorted(ORIENTATION_FLIPS))};"
            " give the frames' orientation with --orientation",
        )  # fmt: skip
    orientation = default if orientation is None else orientation
    orientation_flips(orientation, path, field)
    return str(orientation)


def _read_metaimage(
    path: Path,
    default_orientation: str | None = None,
    labelmap: bool = False,
    header_only: bool = False,
) -> SequenceFile:
    fields, offset = read_metaimage_header(path)
    sizes, axes, dtype = _metaimage_layout(fields, path, labelmap)
    n_frames = sizes[axes[2]] if axes[2] is not None else 1
    plain, frames = _split_frame_fields(fields, n_frames, path, "DimSize")
    orientation = _orientation(plain, default_orientation, path, "UltrasoundImageOrientation")
    if header_only:
        pixels = _placeholder(sizes, axes, dtype)
        return SequenceFile(path, pixels, orientation, plain, frames, "DimSize")
    payload = _read_metaimage_payload(plain, path, offset, math.prod(sizes) * dtype.itemsize)
    flat = payload.view(dtype).astype(dtype.newbyteorder("="), copy=False)  # B-mode: no copy
    pixels = _arrange_frames(flat, sizes, axes)
    return SequenceFile(path, pixels, orientation, plain, frames, "DimSize")


def read_sequence(
    path: str | Path,
    default_orientation: str | None = None,
    field: str = "SEQUENCE",
    labelmap: bool = False,
    header_only: bool = False,
) -> SequenceFile:
    """Read a PLUS / Slicer sequence file (MetaImage or NRRD, by its ending). A file without
    ``UltrasoundImageOrientation`` (a labelmap sequence) takes ``default_orientation``; with
    None (B-mode) it is an error. ``field`` names the file in messages about the file as a
    whole. B-mode must be uint8; a ``labelmap`` may hold 8- or 16-bit integers (Slicer's
    labelmaps are often 16-bit), kept as they are. ``header_only`` reads the header alone (the
    fields, the per-frame fields, the frames' count and size): ``pixels`` is then a read-only
    all-zero view of that shape, holding no memory, and the payload is not checked."""
    path = Path(path)
    input_file(path, field)
    lower = path.name.lower()
    try:
        if lower.endswith(_METAIMAGE_SUFFIXES):
            return _read_metaimage(path, default_orientation, labelmap, header_only)
        if lower.endswith((".nrrd", ".nhdr")):
            from ultron.data.plus_nrrd import read_nrrd_sequence

            return read_nrrd_sequence(path, default_orientation, labelmap, header_only)
    except OSError as exc:
        raise UltronInputError(path, field, f"cannot be read ({exc.strerror})") from None
    raise UltronInputError(
        path, field, f"unknown file type; expected one of {', '.join(SEQUENCE_SUFFIXES)}"
    )
