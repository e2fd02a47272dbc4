"""PLUS's orientation strings of B-mode frames and the flips that bring a frame to MF (PLUS's
orientation of B-mode, the one its Image → Probe calibration refers to)."""

from __future__ import annotations

from pathlib import Path

from ultron.errors import UltronInputError

#: PLUS's orientation strings of B-mode frames → (flip columns, flip rows) to reach MF, the
#: orientation PLUS holds B-mode frames in and its Image → Probe calibration refers to. First
#: letter: image x (columns) towards the Marked or Unmarked side of the transducer; second:
#: image y (rows) towards Far (deeper) or Near. A third letter (Ascending / Descending) orders
#: the slices of a 3D frame: for 2D frames it changes nothing (PLUS: MFA = MF, UFD = UF).
ORIENTATION_FLIPS: dict[str, tuple[bool, bool]] = {
    **dict.fromkeys(("MF", "MFA", "MFD"), (False, False)),
    **dict.fromkeys(("MN", "MNA", "MND"), (False, True)),
    **dict.fromkeys(("UF", "UFA", "UFD"), (True, False)),
    **dict.fromkeys(("UN", "UNA", "UND"), (True, True)),
}
#: PLUS's orientations of RF data (scanlines along image x) and 3D frames in slice-first order.
RF_ORIENTATIONS = ("FM", "FU", "NM", "NU", "AMF")


def orientation_flips(orientation: str | None, where: str | Path, field: str) -> tuple[bool, bool]:
    """(flip columns, flip rows) that bring frames of ``orientation`` to MF (see
    :data:`ORIENTATION_FLIPS`); an unknown, missing or RF orientation is an error."""
    if orientation is None:
        raise UltronInputError(
            where, field, f"missing; expected one of {', '.join(sorted(ORIENTATION_FLIPS))}"
        )
    key = orientation.strip().upper()
    if key in ORIENTATION_FLIPS:
        return ORIENTATION_FLIPS[key]
    if key in RF_ORIENTATIONS:
        raise UltronInputError(
            where,
            field,
            f"{orientation!r} is PLUS's orientation of RF scanlines or slice-first 3D frames;"
            " only B-mode frames (MF, MN, UF, UN and their 3-letter forms) can be imported",
        )
    raise UltronInputError(
        where,
        field,
        f"unknown orientation {orientation!r}; expected one of"
        f" {', '.join(sorted(ORIENTATION_FLIPS))}",
    )
