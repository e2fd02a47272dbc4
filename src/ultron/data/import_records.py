"""The import records of a dataset (``dataset.json``'s ``metadata.imports``), checked as the
dataset loads.

``label --masks``, ``label --export`` and ``label --auto`` read a PLUS sweep's record to map
masks between the recording's frames and the sweep's: which frames were kept (``frames``),
the recording's frame count and size (``file_frames``, ``file_shape``), the calibration
(``image_to_probe``) and the clip rectangle (``clip``). A record edited by hand or damaged is
one :class:`~ultron.errors.UltronInputError` naming dataset.json and the entry, not a traceback
in the middle of a command. Records of other sources are only checked to be objects.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ultron.errors import UltronInputError

#: The key of the import records in ``dataset.json``'s metadata.
IMPORTS_KEY = "imports"
#: A PLUS record's digest of the recording's per-frame fields
#: (:meth:`~ultron.data.sequence_frames.SequenceFile.frame_fields_digest`): ``label --export``
#: copies a recording's header only when it is the one imported.
FRAME_FIELDS_KEY = "frame_fields_digest"


def check_import_records(
    metadata: Mapping[str, Any], n_frames: Mapping[str, int], where: str | Path
) -> None:
    """Refuse (naming ``where``, the dataset.json, and the entry) import records that are not
    objects, and PLUS records whose fields are not what the import writes; ``n_frames``: each
    sweep's frame count (a PLUS record lists one recording frame per sweep frame)."""
    imports = metadata.get(IMPORTS_KEY)
    if imports is None:
        return
    if not isinstance(imports, dict):
        raise UltronInputError(
            where, f"metadata.{IMPORTS_KEY}", "expected an object: sweep name → import record"
        )
    for name, record in imports.items():
        field = f"metadata.{IMPORTS_KEY}.{name}"
        if not isinstance(record, dict):
            raise UltronInputError(where, field, "expected an object (the import's record)")
        if record.get("source") == "plus":
            _check_plus_record(record, n_frames.get(name), where, field)


def _check_plus_record(record: dict, n_frames: int | None, where: str | Path, field: str) -> None:
    frames = _integers(record.get("frames"), where, f"{field}.frames", "frame numbers")
    if n_frames is not None and len(frames) != n_frames:
        raise UltronInputError(
            where,
            f"{field}.frames",
            f"{len(frames)} frame numbers; the sweep has {n_frames} frames",
        )
    if any(b <= a for a, b in itertools.pairwise(frames)) or min(frames, default=0) < 0:
        raise UltronInputError(where, f"{field}.frames", "expected increasing numbers ≥ 0")
    file_frames = record.get("file_frames")
    if file_frames is not None and (
        not _is_integer(file_frames) or file_frames <= max(frames, default=-1)
    ):
        raise UltronInputError(
            where, f"{field}.file_frames", f"{file_frames!r}; expected an integer above every"
            f" kept frame number (largest {max(frames, default=-1)})",
        )  # fmt: skip
    if record.get("file_shape") is not None:
        shape = _integers(record["file_shape"], where, f"{field}.file_shape", "the frame size")
        if len(shape) != 2 or min(shape) < 1:
            raise UltronInputError(where, f"{field}.file_shape", "expected [rows, columns] ≥ 1")
    for key in ("image_to_probe", "fitted_image_to_probe"):
        if key in record or key == "image_to_probe":
            _matrix(record.get(key), where, f"{field}.{key}")
    clip = record.get("clip")
    if clip is not None:
        parts = clip if isinstance(clip, dict) else {}
        origin = _integers(parts.get("origin"), where, f"{field}.clip.origin", "pixel indices")
        size = _integers(parts.get("size"), where, f"{field}.clip.size", "pixel counts")
        if len(origin) != 2 or len(size) != 2 or min(origin) < 0 or min(size) < 1:
            raise UltronInputError(
                where, f"{field}.clip", "expected {origin: [i, j] ≥ 0, size: [w, h] ≥ 1}"
            )
    for key in ("orientation", "sequence", "sequence_path", FRAME_FIELDS_KEY):
        if record.get(key) is not None and not isinstance(record[key], str):
            raise UltronInputError(where, f"{field}.{key}", f"{record[key]!r:.60}; expected text")


def _is_integer(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _integers(value: object, where: str | Path, field: str, what: str) -> list[int]:
    if not isinstance(value, list) or not all(_is_integer(v) for v in value):
        raise UltronInputError(where, field, f"{value!r:.60}; expected a list of {what} (integers)")
    return value


def _matrix(value: object, where: str | Path, field: str) -> None:
    rows = value if isinstance(value, list) else []
    entries = [v for row in rows if isinstance(row, list) and len(row) == 4 for v in row]
    numbers = all(_is_number(v) and math.isfinite(v) for v in entries)
    if len(rows) != 4 or len(entries) != 16 or not numbers:
        raise UltronInputError(
            where, field, f"{value!r:.60}; expected a 4 × 4 matrix of finite numbers"
        )


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


__all__ = ["FRAME_FIELDS_KEY", "IMPORTS_KEY", "check_import_records"]
