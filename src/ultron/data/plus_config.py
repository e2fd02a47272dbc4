"""Reading PLUS configuration files (device-set XML).

What ultron needs from one: every ``CoordinateDefinitions/Transform`` between the image frame
and another frame (``From="Image" To="Probe" Matrix="…"``: the calibration, pixel (i, j, 0, 1)
of the MF-oriented frame → probe, mm, holding the pixel scale; a transform given as
``From="Probe" To="Image"`` is inverted, as PLUS's transform repository does) and the volume
reconstruction's optional clip rectangle (``VolumeReconstruction ClipRectangleOrigin`` /
``ClipRectangleSize``, pixels of the MF-oriented frame). Every problem is an
:class:`~ultron.errors.UltronInputError` naming the file and the element.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ultron.data.plus import parse_matrix
from ultron.data.validation import input_file
from ultron.errors import UltronInputError


@dataclass(frozen=True)
class PlusConfig:
    """What ultron reads from a PLUS configuration: every calibration from the image frame
    (``image_to[X]``: pixel (i, j, 0, 1) → frame X, mm; transforms given as X → Image are
    inverted, as PLUS's transform repository does) and the volume reconstruction's clip
    rectangle (origin and size in pixels (i, j), or None)."""

    path: Path
    image_to: Mapping[str, np.ndarray]
    clip_origin: tuple[int, int] | None = None
    clip_size: tuple[int, int] | None = None


def _config_matrix(element: ET.Element, path: Path, label: str) -> np.ndarray:
    text = element.get("Matrix")
    if text is None:
        raise UltronInputError(path, label, "has no Matrix attribute")
    matrix = parse_matrix(text, path, label)
    if not np.isfinite(matrix).all():
        raise UltronInputError(path, label, "Matrix holds NaN or inf")
    if np.abs(matrix[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-9:
        raise UltronInputError(path, label, f"last row is {matrix[3].tolist()}, not [0 0 0 1]")
    return matrix


def _image_transforms(root: ET.Element, path: Path) -> dict[str, np.ndarray]:
    """Image → X for every X the configuration relates to the image (X → Image inverted). A
    frame given two different transforms (twice, or once each way) is an error: which one
    PLUS would use is not for ultron to guess."""
    found: dict[str, tuple[np.ndarray, str]] = {}
    for element in root.iter("Transform"):
        source, target = element.get("From", ""), element.get("To", "")
        label = f"Transform {source} → {target}"
        if source == "Image" and target:
            other, matrix = target, _config_matrix(element, path, label)
        elif target == "Image" and source:
            other, matrix = source, _config_matrix(element, path, label)
            if abs(np.linalg.det(matrix[:3, :3])) < 1e-300:
                raise UltronInputError(path, label, "Matrix is singular (cannot be inverted)")
            matrix = np.linalg.inv(matrix)
        else:
            continue
        if other in found and not np.allclose(found[other][0], matrix, rtol=0.0, atol=1e-6):
            raise UltronInputError(
                path, label, f"differs from the {found[other][1]} before it: one calibration"
                " of the image per frame; remove the one not meant",
            )  # fmt: skip
        found.setdefault(other, (matrix, label))
    return {other: matrix for other, (matrix, _) in found.items()}


def _clip_rectangle(root: ET.Element, path: Path) -> tuple[tuple[int, int], tuple[int, int]] | None:
    for element in root.iter("VolumeReconstruction"):
        origin, size = element.get("ClipRectangleOrigin"), element.get("ClipRectangleSize")
        if origin is None and size is None:
            continue
        parsed = []
        for name, text in (("ClipRectangleOrigin", origin), ("ClipRectangleSize", size)):
            label = f"VolumeReconstruction {name}"
            tokens = (text or "").split()
            if len(tokens) not in (2, 3) or not all(t.lstrip("-").isdigit() for t in tokens):
                raise UltronInputError(path, label, f"expected 2 integers, got {text!r}")
            parsed.append((int(tokens[0]), int(tokens[1])))
        (i0, j0), (w, h) = parsed
        if min(i0, j0) < 0 or min(w, h) < 1:
            raise UltronInputError(
                path,
                "VolumeReconstruction ClipRectangleSize",
                f"origin {parsed[0]} and size {parsed[1]}: expected origin ≥ 0 and size ≥ 1",
            )
        return parsed[0], parsed[1]
    return None


def read_config(path: str | Path) -> PlusConfig:
    """Read a PLUS configuration: its Image → X calibrations and its clip rectangle."""
    path = Path(path)
    input_file(path, "--config")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise UltronInputError(path, "--config", f"not valid XML ({exc})") from None
    except OSError as exc:
        raise UltronInputError(path, "--config", f"cannot be read ({exc.strerror})") from None
    image_to = _image_transforms(root, path)
    if not image_to:
        raise UltronInputError(
            path,
            "CoordinateDefinitions",
            'no Image → Probe transform (<Transform From="Image" To="Probe" Matrix="…"/>):'
            " the calibration is needed to place the pixels",
        )
    clip = _clip_rectangle(root, path)
    return PlusConfig(
        path=path,
        image_to=image_to,
        clip_origin=clip[0] if clip else None,
        clip_size=clip[1] if clip else None,
    )
