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
  dependency of ultron (a large install; docs/data.md) and reports a truncated payload as "No
  such file or directory".
- **NRRD** (``.nrrd``/``.nhdr``) with pynrrd, which returns the per-frame ``key:=value`` fields
  as strings and decodes raw and gzip payloads (also detached data files), in
  :mod:`ultron.data.plus_nrrd`; the frame layout, per-frame fields and orientation of both by
  :mod:`ultron.data.sequence_frames`.

The configuration is read by :mod:`ultron.data.plus_config`.

Every problem is an :class:`~ultron.errors.UltronInputError` naming the file and the field.
"""

from __future__ import annotations

import math
import re
import zlib
from collections.abc import Iterator, Mapping
from pathlib import Path

import numpy as np

from ultron.data.sequence_frames import (
    SequenceFile,
    arrange_frames,
    frame_axes,
    header_fields,
    lookup_field,
    placeholder_pixels,
)
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

_NAN_TOKEN = re.compile(r"^[-+]?nan(\(.*\))?$", re.IGNORECASE)
_MAX_HEADER_LINE = 1 << 20
#: What a labelmap sequence (``read_sequence(…, labelmap=True)``) may hold besides uint8: the
#: MetaImage element types of 8- and 16-bit integers, as Slicer writes labelmaps (the NRRD
#: types are in :mod:`ultron.data.plus_nrrd`).
_LABELMAP_METAIMAGE = {"MET_UCHAR": "u1", "MET_CHAR": "i1", "MET_USHORT": "u2", "MET_SHORT": "i2"}


# --------------------------------------------------------------------------- helpers


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
    value = lookup_field(fields, name)
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
    element = (lookup_field(fields, "ElementType") or "").upper()
    if element != "MET_UCHAR" and not (labelmap and element in _LABELMAP_METAIMAGE):
        labelmap_types = "MET_UCHAR, MET_CHAR, MET_USHORT or MET_SHORT (a labelmap)"
        expected = labelmap_types if labelmap else "MET_UCHAR (8-bit B-mode)"
        raise UltronInputError(path, "ElementType", f"{element or 'missing'}; expected {expected}")
    msb = (lookup_field(fields, "BinaryDataByteOrderMSB") or "False").lower() == "true"
    dtype = np.dtype(_LABELMAP_METAIMAGE[element]).newbyteorder(">" if msb else "<")
    channels = lookup_field(fields, "ElementNumberOfChannels")
    if channels not in (None, "1"):
        raise UltronInputError(
            path, "ElementNumberOfChannels", f"{channels}; expected 1 (grey B-mode)"
        )
    if (lookup_field(fields, "BinaryData") or "True").lower() != "true":
        raise UltronInputError(path, "BinaryData", "only binary pixel data can be read")
    kinds = lookup_field(fields, "Kinds")
    axes = frame_axes(sizes, kinds.split() if kinds else None, path, "DimSize", "Kinds")
    return sizes, axes, dtype


def _payload_source(fields: Mapping[str, str], path: Path, offset: int) -> tuple[Path, int]:
    data_file = lookup_field(fields, "ElementDataFile") or ""
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
    compressed = (lookup_field(fields, "CompressedData") or "False").lower() == "true"
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
        size = lookup_field(fields, "CompressedDataSize")
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


def _read_metaimage(
    path: Path,
    default_orientation: str | None = None,
    labelmap: bool = False,
    header_only: bool = False,
) -> SequenceFile:
    fields, offset = read_metaimage_header(path)
    sizes, axes, dtype = _metaimage_layout(fields, path, labelmap)
    plain, frames, orientation = header_fields(
        fields, sizes, axes, default_orientation, path, "DimSize", "UltrasoundImageOrientation"
    )
    if header_only:
        pixels = placeholder_pixels(sizes, axes, dtype)
        return SequenceFile(path, pixels, orientation, plain, frames, "DimSize")
    payload = _read_metaimage_payload(plain, path, offset, math.prod(sizes) * dtype.itemsize)
    flat = payload.view(dtype).astype(dtype.newbyteorder("="), copy=False)  # B-mode: no copy
    pixels = arrange_frames(flat, sizes, axes)
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
