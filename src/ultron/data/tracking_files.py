"""Tracking saved apart from the frames: the transform sequences 3D Slicer writes.

A recording made in 3D Slicer (frames and tracking streamed from PLUS over OpenIGTLink into
the Sequences module) is saved as one file per sequence: the frames as a volume sequence
(``Image_Reference.seq.nrrd``, its items indexed by time, ``axis N index values``) and each
tracked transform as a ``.seq.mha`` holding only per-frame fields
(``Seq_Frame0000_ProbeToTrackerTransform``, ``…TransformStatus``, ``…Timestamp``; ``DimSize =
0 0 M``), sampled at the tracker's own times. :func:`with_tracking` gives every frame the
transforms at its time, so that ``import-plus`` reads such a recording as it reads a PLUS file
with per-frame transforms.

A transform at the frame's time t is interpolated between the two samples around it (t₀ ≤ t ≤
t₁) — the rotation by spherical linear interpolation (with
:class:`scipy.spatial.transform.Rotation`), the translation linearly — as PLUS interpolates
tracking at a frame's time. An Image → X transform (``ImageToReference``: the calibration's
scale and shear in it) is split into rotation · stretch and its stretch interpolated linearly,
so the pixel scale is kept. It is found when both samples have status OK and lie at most
:data:`MAX_GAP_INTERVALS` of the transform's median sampling interval apart; a frame inside a
longer gap in the tracking, or outside the tracked span, has none (status ``NO_TRACKING``: the
import skips and counts it). A frame at a sample's own time (a sequence Slicer saved
synchronised to the frames) takes that sample exactly.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ultron.data.importers import nearest_rotation
from ultron.data.plus import STATUS_OK, parse_matrix, read_metaimage_header
from ultron.data.sequence_frames import FRAME_FIELD, SequenceFile
from ultron.data.validation import input_file
from ultron.errors import UltronInputError

#: Two samples this many median sampling intervals apart or closer bracket a frame's time.
MAX_GAP_INTERVALS = 2.0
#: A frame this close (s) to a sample's time takes the sample itself.
SAME_TIME_S = 1e-6
#: The status of a frame without tracking at its time.
NO_TRACKING = "NO_TRACKING"
_INDEX_VALUES = re.compile(r"^axis\s*\d+\s*index\s*values$", re.IGNORECASE)


@dataclass(frozen=True)
class TransformSequence:
    """One tracked transform over time: ``name`` (``ProbeToTracker``), the samples' times (s,
    increasing), their matrices and whether each sample's status is OK."""

    path: Path
    name: str
    times_s: np.ndarray
    matrices: np.ndarray
    ok: np.ndarray


def read_transform_sequences(path: str | Path) -> list[TransformSequence]:
    """The transforms of a Slicer transform sequence file (``.seq.mha``; module doc), each
    sampled at the file's per-frame ``Timestamp``. A frame without a numeric timestamp, a
    malformed matrix or a file without transforms is an error naming the file and field."""
    path = Path(path)
    input_file(path, "--tracking")
    if not path.name.lower().endswith((".mha", ".mhd")):
        raise UltronInputError(
            path, "--tracking", "expected a transform sequence as Slicer saves one (.seq.mha)"
        )
    fields, _ = read_metaimage_header(path)
    frames: dict[int, dict[str, str]] = {}
    for key, value in fields.items():
        match = FRAME_FIELD.match(key)
        if match:
            frames.setdefault(int(match.group(1)), {})[match.group(2)] = value
    names = sorted(
        {k[: -len("Transform")] for f in frames.values() for k in f if k.endswith("Transform")}
    )
    if not names:
        raise UltronInputError(path, "Seq_Frame*_*Transform", "no per-frame transform")
    order = sorted(frames)
    times = np.array([_time(frames[k], path, k) for k in order])
    if np.any(np.diff(times) <= 0):
        raise UltronInputError(path, "Timestamp", "the frames' timestamps do not increase")
    sequences = []
    for name in names:
        matrices = np.full((len(order), 4, 4), np.nan)
        ok = np.zeros(len(order), dtype=bool)
        for i, k in enumerate(order):
            text = frames[k].get(f"{name}Transform")
            status = frames[k].get(f"{name}TransformStatus", STATUS_OK).strip().upper()
            if text is not None:
                matrices[i] = parse_matrix(text, path, f"Seq_Frame{k:04d}_{name}Transform")
                ok[i] = status == STATUS_OK and bool(np.isfinite(matrices[i]).all())
        sequences.append(TransformSequence(path, name, times, matrices, ok))
    return sequences


def _time(fields: dict[str, str], path: Path, frame: int) -> float:
    text = fields.get("Timestamp")
    try:
        value = float(text) if text is not None else float("nan")
    except ValueError:
        value = float("nan")
    if not np.isfinite(value):
        raise UltronInputError(
            path, f"Seq_Frame{frame:04d}_Timestamp", f"expected a time in seconds, got {text!r}"
        )
    return value


def frame_times(seq: SequenceFile) -> np.ndarray:
    """The time (s) of each frame of ``seq``: its per-frame ``Timestamp``, else a Slicer volume
    sequence's ``axis N index values``; none is an error naming the file."""
    stamps = [fields.get("Timestamp") for fields in seq.frame_fields]
    texts = None
    if all(stamp is not None for stamp in stamps):
        texts = stamps
    else:
        for key, value in seq.fields.items():
            if _INDEX_VALUES.match(key.strip()) and len(value.split()) == seq.n_frames:
                texts = value.split()
    try:
        times = np.array([float(t) for t in texts], dtype=np.float64) if texts else None
    except ValueError:
        times = None
    if times is None or not np.isfinite(times).all():
        raise UltronInputError(
            seq.path, "Timestamp", f"no time for each of its {seq.n_frames} frames (per-frame"
            " Timestamp, or Slicer's axis N index values): tracking saved apart cannot be"
            " matched to them",
        )  # fmt: skip
    return times


def poses_at(transform: TransformSequence, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``transform`` at ``times_s`` (module doc): (K, 4, 4) matrices (NaN where not found) and
    whether each was found. Between samples r₀, r₁ at weight w the rotation is
    r₀·exp(w·log(r₀⁻¹r₁)) — spherical linear interpolation, with scipy's rotations — for all
    frames at once."""
    from scipy.spatial.transform import Rotation

    times, queries = transform.times_s, np.asarray(times_s, dtype=np.float64)
    out = np.full((len(queries), 4, 4), np.nan)
    if len(times) == 0 or len(queries) == 0:
        return out, np.zeros(len(queries), dtype=bool)
    i1 = np.clip(np.searchsorted(times, queries), 0, len(times) - 1)
    i0 = np.maximum(i1 - 1, 0)
    nearest = np.where(np.abs(times[i0] - queries) <= np.abs(times[i1] - queries), i0, i1)
    exact = np.abs(times[nearest] - queries) <= SAME_TIME_S
    interval = float(np.median(np.diff(times))) if len(times) > 1 else 0.0
    between = (
        ~exact & (i0 < i1) & (times[i0] <= queries) & (queries <= times[i1])
        & transform.ok[i0] & transform.ok[i1]
        & (times[i1] - times[i0] <= MAX_GAP_INTERVALS * interval)
    )  # fmt: skip
    at_sample = exact & transform.ok[nearest]
    out[at_sample] = transform.matrices[nearest[at_sample]]
    if between.any():
        a, b = i0[between], i1[between]
        weight = (queries[between] - times[a]) / (times[b] - times[a])
        (turn0, stretch0), (turn1, stretch1) = (
            _polar(transform.matrices[k, :3, :3]) for k in (a, b)
        )
        r0, r1 = Rotation.from_matrix(turn0), Rotation.from_matrix(turn1)
        turn = Rotation.from_rotvec((r0.inv() * r1).as_rotvec() * weight[:, None])
        stretch = (1 - weight)[:, None, None] * stretch0 + weight[:, None, None] * stretch1
        moved = np.tile(np.eye(4), (len(a), 1, 1))
        moved[:, :3, :3] = (r0 * turn).as_matrix() @ stretch
        moved[:, :3, 3] = (1 - weight)[:, None] * transform.matrices[a, :3, 3]
        moved[:, :3, 3] += weight[:, None] * transform.matrices[b, :3, 3]
        out[between] = moved
    return out, at_sample | between


def _polar(blocks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """3 × 3 ``blocks`` as rotation · stretch, B = R·S: R = U·Vᵀ of B's singular value
    decomposition (the nearest rotation; its last column's sign flipped where det B < 0) and
    S = Rᵀ·B. A rigid transform's S is the identity up to the tracker's rounding; an Image → X
    transform's S holds the calibration's scale and shear, the same in every sample, so the
    interpolated transform keeps it."""
    turns = nearest_rotation(blocks)
    return turns, np.swapaxes(turns, -1, -2) @ blocks


def with_tracking(seq: SequenceFile, paths: Sequence[str | Path]) -> SequenceFile:
    """``seq`` with every frame given the transforms of the files ``paths`` at its time
    (module doc): ``<Name>Transform`` and ``<Name>TransformStatus`` (OK, or
    :data:`NO_TRACKING`) per frame, as a PLUS file with per-frame transforms holds them."""
    times = frame_times(seq)
    fields = [dict(f) for f in seq.frame_fields]
    for path in paths:
        for transform in read_transform_sequences(path):
            matrices, found = poses_at(transform, times)
            for k in range(seq.n_frames):
                matrix = matrices[k] if found[k] else np.eye(4)
                fields[k][f"{transform.name}Transform"] = " ".join(
                    f"{v:.17g}" for v in matrix.ravel()
                )
                fields[k][f"{transform.name}TransformStatus"] = (
                    STATUS_OK if found[k] else NO_TRACKING
                )
    return replace(seq, frame_fields=tuple(fields))
