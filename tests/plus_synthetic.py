"""Small synthetic PLUS recordings written as PLUS / IGSIO writes them (for the tests and the
bad-input corpus): a MetaImage (``.seq.mha``) or NRRD (``.seq.nrrd``) sequence, raw or
compressed, with per-frame ``ProbeToTracker`` / ``ReferenceToTracker`` transforms and their
statuses, and a PLUS configuration holding the Image → Probe calibration."""

from __future__ import annotations

import gzip
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

#: Header pairs (key, value) of a sequence, in order.
Header = list[tuple[str, str]]


def rotation(axis: tuple[float, float, float], degrees: float) -> np.ndarray:
    """Rotation by ``degrees`` about ``axis`` (Rodrigues)."""
    k = np.asarray(axis, dtype=np.float64)
    k = k / np.linalg.norm(k)
    angle = np.deg2rad(degrees)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def rigid(axis, degrees: float, translation) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3] = rotation(axis, degrees)
    matrix[:3, 3] = translation
    return matrix


def calibration(spacing=(0.3, 0.25), shear_deg: float = 0.0) -> np.ndarray:
    """An Image → Probe matrix: image x along a rotated probe axis, scaled; image y at
    90° + ``shear_deg`` from it in the image plane."""
    base = rotation((0.3, -0.5, 1.0), 25.0)
    ax = spacing[0] * base[:, 0]
    tilt = np.deg2rad(shear_deg)
    ay = spacing[1] * (np.cos(tilt) * base[:, 1] - np.sin(tilt) * base[:, 0])
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2] = ax, ay, base[:, 2]
    matrix[:3, 3] = (12.0, -4.0, 7.5)
    return matrix


@dataclass
class Recording:
    """Frames in MF orientation (row = image y towards far, column = image x towards the
    marked side) and the per-frame transforms of a synthetic tracked sweep."""

    frames: np.ndarray
    transforms: dict[str, np.ndarray]
    statuses: dict[str, list[str]] = field(default_factory=dict)
    image_status: list[str] | None = None

    @property
    def n(self) -> int:
        return int(self.frames.shape[0])


def recording(n: int = 4, height: int = 12, width: int = 16, seed: int = 0) -> Recording:
    """Random frames, a probe moving along a line, a fixed reference."""
    rng = np.random.default_rng(seed)
    frames = rng.integers(0, 256, size=(n, height, width), dtype=np.uint8)
    probe = np.stack(
        [rigid((1, 2, 3), 10.0 + 3 * k, (100.0 + 2 * k, -50.0, 20.0)) for k in range(n)]
    )
    reference = np.stack([rigid((0, 1, 0.2), 40.0, (250.0, 90.0, 3.0))] * n)
    return Recording(frames, {"ProbeToTracker": probe, "ReferenceToTracker": reference})


def plus_world(rec: Recording, image_to_probe: np.ndarray, frame: int, i: float, j: float):
    """PLUS's placement of pixel (i, j): ReferenceToTracker⁻¹ · ProbeToTracker · ImageToProbe."""
    reference = rec.transforms["ReferenceToTracker"][frame]
    probe = rec.transforms["ProbeToTracker"][frame]
    return (np.linalg.inv(reference) @ probe @ image_to_probe @ np.array([i, j, 0.0, 1.0]))[:3]


def _matrix_text(matrix: np.ndarray) -> str:
    return " ".join(f"{value:.17g}" for value in np.asarray(matrix).reshape(-1))


def frame_fields(rec: Recording, image_status_key: str = "ImageStatus") -> Header:
    pairs: Header = []
    for k in range(rec.n):
        for name, matrices in rec.transforms.items():
            pairs.append((f"Seq_Frame{k:04d}_{name}Transform", _matrix_text(matrices[k])))
            status = rec.statuses.get(name, ["OK"] * rec.n)[k]
            pairs.append((f"Seq_Frame{k:04d}_{name}TransformStatus", status))
        pairs.append((f"Seq_Frame{k:04d}_Timestamp", f"{10 + 0.1 * k:.3f}"))
        image_status = "OK" if rec.image_status is None else rec.image_status[k]
        pairs.append((f"Seq_Frame{k:04d}_{image_status_key}", image_status))
    return pairs


def to_file_orientation(frames: np.ndarray, orientation: str) -> np.ndarray:
    """MF frames as a file of ``orientation`` stores them (U: columns mirrored, N: rows)."""
    out = frames
    if orientation[0] == "U":
        out = out[:, :, ::-1]
    if orientation[1] == "N":
        out = out[:, ::-1, :]
    return np.ascontiguousarray(out)


def mha_header(rec: Recording, orientation: str = "MF", compressed: bool = False) -> Header:
    n, height, width = rec.frames.shape
    pairs: Header = [
        ("ObjectType", "Image"),
        ("NDims", "3"),
        ("AnatomicalOrientation", "RAI"),
        ("BinaryData", "True"),
        ("BinaryDataByteOrderMSB", "False"),
        ("CompressedData", "True" if compressed else "False"),
        ("DimSize", f"{width} {height} {n}"),
        ("Kinds", "domain domain list"),
        ("ElementSpacing", "1 1 1"),
        ("ElementType", "MET_UCHAR"),
        ("UltrasoundImageOrientation", orientation),
    ]
    return pairs + frame_fields(rec)


def write_mha(
    path: Path,
    rec: Recording,
    orientation: str = "MF",
    compressed: bool = False,
    edit: Callable[[Header], Header] | None = None,
    payload_edit: Callable[[bytes], bytes] | None = None,
) -> Path:
    """A PLUS-style MetaImage sequence; ``edit`` changes the header pairs, ``payload_edit``
    the (compressed) payload bytes."""
    payload = to_file_orientation(rec.frames, orientation[:2]).tobytes()
    header = mha_header(rec, orientation, compressed)
    if compressed:
        payload = zlib.compress(payload)
        header.insert(6, ("CompressedDataSize", str(len(payload))))
    if edit is not None:
        header = edit(header)
    if payload_edit is not None:
        payload = payload_edit(payload)
    text = "".join(f"{key} = {value}\n" for key, value in header)
    path.write_bytes(text.encode("latin-1") + b"ElementDataFile = LOCAL\n" + payload)
    return path


def write_nrrd(
    path: Path,
    rec: Recording,
    orientation: str = "MF",
    compressed: bool = False,
    edit: Callable[[Header], Header] | None = None,
    payload_edit: Callable[[bytes], bytes] | None = None,
) -> Path:
    """An IGSIO-style NRRD sequence (``name: value`` fields, ``name:=value`` key-values, the
    image status as ``Seq_Frame<NNNN>_Status``)."""
    n, height, width = rec.frames.shape
    payload = to_file_orientation(rec.frames, orientation[:2]).tobytes()
    if compressed:
        payload = gzip.compress(payload)
    fields: Header = [
        ("dimension", "3"),
        ("encoding", "gz" if compressed else "raw"),
        ("endian", "little"),
        ("kinds", "domain domain          list"),
        ("sizes", f"{width} {height}                {n}"),
        ("type", "uint8"),
        ("space dimension", "2"),
        ("space directions", "(1,0) (0,1) none"),
        ("space origin", "(0,0)"),
    ]
    values = [
        ("ultrasound image orientation", orientation),
        ("ultrasound image type", "BRIGHTNESS"),
    ]
    values += frame_fields(rec, image_status_key="Status")
    if edit is not None:
        fields, values = edit(fields), edit(values)
    if payload_edit is not None:
        payload = payload_edit(payload)
    lines = ["NRRD0004", "# Complete NRRD file format specification at:"]
    lines += [f"{key}: {value}" for key, value in fields]
    lines += [f"{key}:={value}" for key, value in values]
    path.write_bytes(("\n".join(lines) + "\n\n").encode("latin-1") + payload)
    return path


def write_config(
    path: Path,
    image_to_probe: np.ndarray | None,
    clip: tuple[tuple[int, int], tuple[int, int]] | None = None,
    matrix_text: str | None = None,
) -> Path:
    """A PLUS configuration with the Image → Probe calibration (or none) and a clip rectangle."""
    transforms = [
        '    <Transform From="Phantom" To="Reference" Matrix="1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1"/>'
    ]
    if image_to_probe is not None or matrix_text is not None:
        text = matrix_text if matrix_text is not None else _matrix_text(image_to_probe)
        transforms.append(f'    <Transform From="Image" To="Probe" Matrix="{text}" Error="1"/>')
    reconstruction = '  <VolumeReconstruction OutputSpacing="0.5 0.5 0.5"'
    if clip is not None:
        (i0, j0), (w, h) = clip
        reconstruction += f' ClipRectangleOrigin="{i0} {j0}" ClipRectangleSize="{w} {h}"'
    body = "\n".join(
        [
            '<PlusConfiguration version="2.1">',
            "  <CoordinateDefinitions>",
            *transforms,
            "  </CoordinateDefinitions>",
            reconstruction + ' Interpolation="LINEAR"/>',
            "</PlusConfiguration>",
            "",
        ]
    )
    path.write_text(body)
    return path
