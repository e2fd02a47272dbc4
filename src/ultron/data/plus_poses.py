"""Where a PLUS / 3D Slicer recording's pixels go: each frame's tracked transforms, read with
their statuses and composed along a chain into the world frame (``ProbeTo<To>``, or
``<To>ToTracker⁻¹ · ProbeToTracker``), and the calibration that maps pixels into the chain's
source frame — the PLUS configuration's Image → Probe, or, without one, the one the frames'
own ``ImageTo<To>`` transforms hold (:func:`~ultron.data.plus_geometry.factor_image_to_world`).
:mod:`ultron.data.plus_import` builds a sweep on this placement.
"""

from __future__ import annotations

import re
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ultron.data.plus import IMAGE_STATUS_FIELDS, STATUS_OK, parse_matrix
from ultron.data.plus_config import PlusConfig
from ultron.data.plus_geometry import factor_image_to_world
from ultron.data.sequence_frames import SequenceFile
from ultron.data.validation import ROTATION_TOLERANCE, pose_errors
from ultron.errors import UltronInputError

#: The frame a tracker reports in; ``--to X`` other than it composes XToTracker⁻¹ · …ToTracker.
TRACKER = "Tracker"
#: PLUS's frame of the image's pixels: a per-frame ``ImageTo<X>`` holds the calibration.
IMAGE = "Image"
#: The source frame of a transform name: PLUS splits at the "To" followed by a capital.
_FROM = re.compile(r"^(.+?)To(?=[A-Z])")


@dataclass(frozen=True)
class WorldPoses:
    """Per frame: the chain's source frame (Probe, or Image) → world matrix (NaN where
    invalid), whether the frame is valid, and why the others were skipped (reason → count);
    the chain's transforms by name (``ProbeToTracker``)."""

    source_to_world: np.ndarray
    valid: np.ndarray
    skipped: Counter[str]
    description: str
    chain: tuple[str, ...] = ()


def _status(seq: SequenceFile, frame: int, name: str) -> str:
    """A frame's status field ``name`` (OK when absent: older PLUS files have none)."""
    return seq.frame_fields[frame].get(name, STATUS_OK).strip() or STATUS_OK


def _frame_matrix(
    seq: SequenceFile, frame: int, transform: str, affine: bool = False
) -> tuple[np.ndarray, bool]:
    """(matrix, status OK) of frame ``frame``'s ``<transform>Transform``; a malformed matrix is
    an error whatever its status, a non-finite or (unless ``affine``: an Image → X transform
    holds the pixel scale) non-rigid one only with status OK."""
    key = f"{transform}Transform"
    text = seq.frame_fields[frame].get(key)
    label = seq.frame_field_key(frame, key)
    if text is None:
        have = sum(key in fields for fields in seq.frame_fields)
        raise UltronInputError(
            seq.path,
            seq.size_field,
            f"{seq.n_frames} frames, but {key} is given for {have}"
            f" ({label} is missing): frame count does not match the transform fields",
        )
    matrix = parse_matrix(text, seq.path, label)
    ok = _status(seq, frame, f"{key}Status").upper() == STATUS_OK
    if ok:
        if not np.isfinite(matrix).all():
            raise UltronInputError(seq.path, label, "holds NaN or inf but its status is OK")
        if np.abs(matrix[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-6:
            raise UltronInputError(seq.path, label, f"last row is {matrix[3].tolist()}")
        ortho, det = (float(e[0]) for e in pose_errors(matrix[None]))
        if not affine and max(ortho, det) > ROTATION_TOLERANCE:
            raise UltronInputError(
                seq.path,
                label,
                f"not rigid: rotation block deviates from orthonormal by {ortho:.2e}"
                f" (det error {det:.2e}; at most {ROTATION_TOLERANCE:g})",
            )
        matrix[3] = (0.0, 0.0, 0.0, 1.0)
    return matrix, ok


def _affine_inverse(matrix: np.ndarray) -> np.ndarray:
    """Inverse of an affine 4 × 4 with its last row exactly (0, 0, 0, 1)."""
    inverse = np.eye(4)
    inverse[:3, :3] = np.linalg.inv(matrix[:3, :3])
    inverse[:3, 3] = -inverse[:3, :3] @ matrix[:3, 3]
    return inverse


def transform_chain(seq: SequenceFile, probe: str, target: str) -> tuple[str, ...]:
    """The per-frame transforms giving probe → ``target``: ``(ProbeToTarget,)``, or
    ``(ProbeToTracker, TargetToTracker)`` composed as TargetToTracker⁻¹ · ProbeToTracker."""
    names = seq.transform_names()
    direct = f"{probe}To{target}"
    if direct in names:
        return (direct,)
    via = (f"{probe}To{TRACKER}", f"{target}To{TRACKER}")
    if target != TRACKER and all(name in names for name in via):
        return via
    wanted = direct if target == TRACKER else f"{direct}, or {via[0]} and {via[1]}"
    raise UltronInputError(
        seq.path,
        "--to",
        f"{target}: the sequence has no {wanted} transform"
        f" (it has {', '.join(names) or 'no transforms'})",
    )


def world_poses(seq: SequenceFile, chain: tuple[str, ...]) -> WorldPoses:
    """Source → world of every frame along ``chain`` (:func:`transform_chain`; an Image → X
    first link may be affine); frames whose image status or a used transform's status is not
    OK are marked invalid and counted."""
    poses = np.full((seq.n_frames, 4, 4), np.nan)
    valid = np.zeros(seq.n_frames, dtype=bool)
    skipped: Counter[str] = Counter()
    affine = [name.startswith(f"{IMAGE}To") for name in chain]
    for frame in range(seq.n_frames):
        matrices = [
            _frame_matrix(seq, frame, name, scaled)
            for name, scaled in zip(chain, affine, strict=True)
        ]
        reasons = []
        image_status = next((f for f in IMAGE_STATUS_FIELDS if f in seq.frame_fields[frame]), None)
        if image_status and _status(seq, frame, image_status).upper() != STATUS_OK:
            reasons.append(f"{image_status} {_status(seq, frame, image_status)}")
        for name, (_, ok) in zip(chain, matrices, strict=True):
            if not ok:
                key = f"{name}TransformStatus"
                reasons.append(f"{key} {_status(seq, frame, key)}")
        if reasons:
            skipped.update(reasons[:1])
            continue
        pose = matrices[0][0]
        if len(chain) == 2:
            pose = _affine_inverse(matrices[1][0]) @ pose
        poses[frame], valid[frame] = pose, True
    text = chain[0] if len(chain) == 1 else f"{chain[1]}⁻¹ · {chain[0]}"
    return WorldPoses(poses, valid, skipped, text, tuple(chain))


def _probe_frame(seq: SequenceFile, config: PlusConfig) -> str:
    """The frame the calibration maps the image to (Probe, unless the configuration
    calibrates the image to another frame that the sequence tracks)."""
    tracked = {match.group(1) for name in seq.transform_names() if (match := _FROM.match(name))}
    candidates = sorted(config.image_to, key=lambda name: (name != "Probe", name))
    for name in candidates:
        if name in tracked:
            return name
    raise UltronInputError(
        seq.path,
        "transforms",
        f"no per-frame transform from {' or '.join(candidates)} (the frame the configuration's"
        f" Image → {candidates[0]} calibration maps to); the sequence has"
        f" {', '.join(seq.transform_names()) or 'no transforms'}",
    )


@dataclass(frozen=True)
class Placement:
    """Where a recording's pixels go (:func:`placement`): the frames' poses and status, the
    valid frames' rigid probe → world poses, the Image → Probe calibration of the whole frame,
    the frame it maps to, and the file and field that gave the calibration."""

    world: WorldPoses
    probe_to_world: np.ndarray
    image_to_probe: np.ndarray
    probe_frame: str
    where: Path
    field: str
    #: See :attr:`PlusImportReport.calibration_spread_mm`.
    spread_mm: float | None = None


def placement(seq: SequenceFile, config: PlusConfig | None, target: str) -> Placement:
    """The pixels' placement in the ``target`` frame: with a configuration, its Image → Probe
    calibration and the probe's per-frame tracking; without, the per-frame Image → ``target``
    transforms, which hold the calibration (:func:`~ultron.data.plus_geometry.
    factor_image_to_world`). No valid frame is an error naming the file."""
    if config is None:
        try:
            world = world_poses(seq, transform_chain(seq, IMAGE, target))
        except UltronInputError as exc:
            if exc.field != "--to":
                raise
            raise UltronInputError(
                seq.path, "--config", f"not given, and {exc.problem.removeprefix(f'{target}: ')}: without a PLUS"
                " configuration (its Image → Probe calibration) the frames must carry Image →"
                f" {target} transforms, which hold the calibration",
            ) from None  # fmt: skip
    else:
        probe_frame = _probe_frame(seq, config)
        world = world_poses(seq, transform_chain(seq, probe_frame, target))
    if not world.valid.any():
        reasons = ", ".join(f"{n} × {r}" for r, n in world.skipped.most_common())
        raise UltronInputError(
            seq.path, "frames", f"all {seq.n_frames} frames are invalid ({reasons})"
        )
    poses = world.source_to_world[world.valid]
    if config is not None:
        label = f"Transform Image → {probe_frame}"
        calibration = config.image_to[probe_frame]
        return Placement(world, poses, calibration, probe_frame, config.path, label)
    height, width = seq.pixels.shape[1:]
    label = f"{world.description} (per frame)"
    factored = factor_image_to_world(poses, width, height, seq.path, label)
    return Placement(
        world, factored.plane_to_world, factored.image_to_plane, "image plane", seq.path,
        label, factored.spread_mm,
    )  # fmt: skip
