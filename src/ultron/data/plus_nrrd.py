"""Reading a PLUS / Slicer sequence stored as NRRD (``.nrrd``/``.nhdr``, ``.igs.nrrd``,
``.seq.nrrd``) with pynrrd, which returns the per-frame ``key:=value`` fields as strings and
decodes raw and gzip payloads (also detached data files). The frame layout, the per-frame
fields and the orientation are interpreted as for MetaImage, by :mod:`ultron.data.sequence_frames`;
:func:`ultron.data.plus.read_sequence` is the public entry point.

Every problem is an :class:`~ultron.errors.UltronInputError` naming the file and the field.
"""

from __future__ import annotations

import math
import zlib
from pathlib import Path

import numpy as np

from ultron.data.sequence_frames import (
    SequenceFile,
    arrange_frames,
    frame_axes,
    header_fields,
    placeholder_pixels,
)
from ultron.data.validation import contained_path
from ultron.errors import UltronInputError

_UINT8_NAMES = ("uchar", "unsigned char", "uint8", "uint8_t")
#: NRRD types a labelmap sequence may hold besides uint8: 8- and 16-bit integers, as Slicer
#: writes labelmaps.
_LABELMAP_NRRD = {
    **dict.fromkeys(("signed char", "int8", "int8_t"), "i1"),
    **dict.fromkeys(_UINT8_NAMES, "u1"),
    **dict.fromkeys(("short", "short int", "signed short", "signed short int"), "i2"),
    **dict.fromkeys(("int16", "int16_t"), "i2"),
    **dict.fromkeys(("ushort", "unsigned short", "unsigned short int", "uint16", "uint16_t"), "u2"),
}


def _nrrd_header(path: Path, handle, labelmap: bool = False) -> dict[str, object]:
    import nrrd

    try:
        header = nrrd.read_header(handle)
    except (nrrd.NRRDError, ValueError, UnicodeDecodeError) as exc:
        raise UltronInputError(path, "header", f"not a readable NRRD header ({exc})") from None
    if "sizes" not in header:
        raise UltronInputError(path, "sizes", "missing: the frame size and count are unknown")
    for key in ("data file", "datafile"):
        if key in header:  # a detached payload: one file, inside the header's folder
            name = str(header[key])
            if name.upper().startswith("LIST") or "%" in name:
                raise UltronInputError(path, key, f"{name!r}: only one data file is supported")
            contained_path(path.parent, name, path, key)
    kind = str(header.get("type", "")).lower()
    if kind not in _UINT8_NAMES and not (labelmap and kind in _LABELMAP_NRRD):
        expected = "8- or 16-bit integers (a labelmap)" if labelmap else "uint8 (B-mode)"
        raise UltronInputError(
            path, "type", f"{header.get('type', 'missing')}; expected {expected}"
        )
    return header


def read_nrrd_sequence(
    path: Path,
    default_orientation: str | None = None,
    labelmap: bool = False,
    header_only: bool = False,
) -> SequenceFile:
    import nrrd

    with path.open("rb") as handle:
        header = _nrrd_header(path, handle, labelmap)
        sizes = [int(s) for s in np.atleast_1d(header["sizes"])]
        if not sizes or min(sizes) < 1:
            raise UltronInputError(path, "sizes", f"expected positive sizes, got {sizes}")
        kinds = header.get("kinds")
        axes = frame_axes(sizes, [str(k) for k in kinds] if kinds else None, path, "sizes", "kinds")
        text = {str(k): str(v) for k, v in header.items()}
        plain, frames, orientation = header_fields(
            text, sizes, axes, default_orientation, path, "sizes", "ultrasound image orientation"
        )
        dtype = np.dtype(_LABELMAP_NRRD[str(header["type"]).lower()] if labelmap else np.uint8)
        if header_only:
            pixels = placeholder_pixels(sizes, axes, dtype)
            return SequenceFile(path, pixels, orientation, plain, frames, "sizes")
        try:
            data = nrrd.read_data(header, handle, str(path), index_order="F")
        except (nrrd.NRRDError, OSError, EOFError, zlib.error, ValueError) as exc:
            raise UltronInputError(path, "data", f"truncated or corrupt payload ({exc})") from None
    flat = np.asarray(data, dtype=dtype).reshape(-1, order="F")
    if flat.size != math.prod(sizes):
        raise UltronInputError(
            path, "data", f"truncated payload: {flat.size} of {math.prod(sizes)} values"
        )
    pixels = arrange_frames(flat, sizes, axes)
    return SequenceFile(path, pixels, orientation, plain, frames, "sizes")
