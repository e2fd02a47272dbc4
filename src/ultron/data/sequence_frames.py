"""The frames and fields of a PLUS / 3D Slicer sequence file, whatever its format: how the
frame axis and the image axes lie in the payload, the per-frame fields
(``Seq_Frame<NNNN>_<Field>``) split from the plain ones, and the ultrasound image orientation.
:mod:`ultron.data.plus` (MetaImage) and :mod:`ultron.data.plus_nrrd` (NRRD) read a file's
header and payload and build a :class:`SequenceFile` with these.

Every problem is an :class:`~ultron.errors.UltronInputError` naming the file and the field.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ultron.data.plus_orientation import ORIENTATION_FLIPS, orientation_flips
from ultron.errors import UltronInputError

#: A per-frame field's key, ``Seq_Frame0012_ProbeToTrackerTransform``: (frame, field name).
FRAME_FIELD = re.compile(r"^seq_frame(\d+)_(.+)$", re.IGNORECASE)


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
        return lookup_field(self.fields, name)

    def frame_field_key(self, frame: int, name: str) -> str:
        """The header key of frame ``frame``'s field ``name``, as PLUS writes it."""
        return f"Seq_Frame{frame:04d}_{name}"

    def frame_fields_digest(self) -> str:
        """A BLAKE2b digest (32 hex digits) of every frame's fields, in order: the timestamps,
        transforms and statuses that tell one recording from another of the same size."""
        text = json.dumps([sorted(fields.items()) for fields in self.frame_fields])
        return hashlib.blake2b(text.encode("utf-8"), digest_size=16).hexdigest()

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


def _normal_key(name: str) -> str:
    return name.replace(" ", "").replace("_", "").lower()


def lookup_field(fields: Mapping[str, str], name: str) -> str | None:
    wanted = _normal_key(name)
    for key, value in fields.items():
        if _normal_key(key) == wanted:
            return value
    return None


def split_frame_fields(
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


def frame_axes(
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


def placeholder_pixels(sizes: list[int], axes: tuple[int, int, int | None], dtype) -> np.ndarray:
    """A read-only all-zero (N, H, W) view of no memory: a header-only read's ``pixels``."""
    x_axis, y_axis, list_axis = axes
    n = sizes[list_axis] if list_axis is not None else 1
    return np.broadcast_to(np.zeros((), dtype=dtype), (n, sizes[y_axis], sizes[x_axis]))


def arrange_frames(flat: np.ndarray, sizes: list[int], axes: tuple[int, int, int | None]):
    """Raw values (fastest axis first in the file) → (N, H, W)."""
    x_axis, y_axis, list_axis = axes
    nd = len(sizes)
    array = flat.reshape(sizes[::-1])
    order = [nd - 1 - a for a in (list_axis, y_axis, x_axis) if a is not None]
    rest = [k for k in range(nd) if k not in order]
    array = array.transpose(order + rest)
    n = sizes[list_axis] if list_axis is not None else 1
    return np.ascontiguousarray(array.reshape(n, sizes[y_axis], sizes[x_axis]))


def sequence_orientation(
    plain: Mapping[str, str], default: str | None, path: Path, field: str
) -> str:
    """The file's ``UltrasoundImageOrientation``, else ``default`` (None: it is required, and
    its absence an error saying how to give it, as a volume sequence saved by Slicer lacks it)."""
    orientation = lookup_field(plain, "UltrasoundImageOrientation")
    if orientation is None and default is None:
        raise UltronInputError(
            path, field, f"missing; expected one of {', '.join(sorted(ORIENTATION_FLIPS))};"
            " give the frames' orientation with --orientation",
        )  # fmt: skip
    orientation = default if orientation is None else orientation
    orientation_flips(orientation, path, field)
    return str(orientation)


def header_fields(
    fields: Mapping[str, str],
    sizes: list[int],
    axes: tuple[int, int, int | None],
    default_orientation: str | None,
    path: Path,
    size_field: str,
    orientation_field: str,
) -> tuple[dict[str, str], tuple[dict[str, str], ...], str]:
    """A header's (non-frame fields, per-frame fields, orientation) for frames laid out as
    ``sizes`` / ``axes`` (:func:`frame_axes`): :func:`split_frame_fields` over the frame count
    and :func:`sequence_orientation`, as every format's reader needs them."""
    n_frames = sizes[axes[2]] if axes[2] is not None else 1
    plain, frames = split_frame_fields(fields, n_frames, path, size_field)
    orientation = sequence_orientation(plain, default_orientation, path, orientation_field)
    return plain, frames, orientation
