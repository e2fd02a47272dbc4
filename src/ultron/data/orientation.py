"""The acoustic field's axes: aligned with the sweep where it runs oblique to the world's.

The grid field (:mod:`ultron.fields.grid`) factorises θ over axis-aligned planes, so what it
represents best is structure aligned with its axes: a bone running along one axis is a curve
in one plane, while the same bone 20° off every axis projects onto each plane as a band whose
product blurs it. A tracker's world frame is arbitrary (a real recording's bone is rarely
along it); the sweep's own frame is not. Like nerfstudio's ``auto_orient_and_center_poses``,
the field is fitted in a frame taken from the poses:

    b = normalise(mean of the probes' beam axes (+y)),
    s = first principal direction of the probe origins, projected onto the plane ⊥ b
        (the direction the probe travelled; the mean lateral axis where it did not move),
    A = rows (s, b, s × b),

then re-labelled and re-signed (one of the 24 proper signed permutations P) to lie closest to
the world's axes, R = P A, so that a sweep already along them keeps its axes. Where R is within
:data:`SNAP_DEGREES` of the identity the world's axes are kept exactly (no rotation at all): a
simulated sweep, recorded along the world's axes, is fitted as before, bit for bit.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import torch

from ultron.data.dataset import ProbeGeometry
from ultron.data.geometry import UnitCube, as_pose_tensor, field_of_view_corners_mm
from ultron.errors import argument_error

#: Field orientations: "auto" (this module's rule) or "world" (the tracker's axes).
ORIENTATIONS = ("auto", "world")
#: Rotations of the field's frame smaller than this (degrees) are not applied.
SNAP_DEGREES = 5.0


def sweep_axes(poses: np.ndarray | torch.Tensor) -> np.ndarray:
    """The sweep's frame A (3 × 3, rows: travel s, beam b, s × b in world coordinates) of
    probe-to-world ``poses`` (N, 4, 4) (module doc), before any re-labelling."""
    tensor = as_pose_tensor(poses, "poses").to(torch.float64).numpy()
    beam = _unit(tensor[:, :3, 1].mean(axis=0), "poses", "the probes' beam axes cancel out")
    origins = tensor[:, :3, 3] - tensor[:, :3, 3].mean(axis=0)
    across = origins - np.outer(origins @ beam, beam)
    scatter = across.T @ across
    values, vectors = np.linalg.eigh(scatter)
    travel = vectors[:, -1]
    if not values[-1] > 1e-12 * max(1.0, float(np.abs(origins).max()) ** 2):  # no motion
        lateral = tensor[:, :3, 0].mean(axis=0)
        travel = lateral - (lateral @ beam) * beam
    travel = _unit(travel - (travel @ beam) * beam, "poses", "no direction across the beam")
    return np.stack([travel, beam, np.cross(travel, beam)])


def nearest_to_world(axes: np.ndarray) -> np.ndarray:
    """The rotation P·axes closest to the identity over the 24 proper signed permutations P
    (largest trace): the same frame with its axes named after the world axes they lie along."""
    axes = np.asarray(axes, dtype=np.float64)
    best, best_trace = axes, -math.inf
    for order in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            candidate = np.asarray(signs)[:, None] * axes[list(order)]
            if np.linalg.det(candidate) > 0 and np.trace(candidate) > best_trace + 1e-12:
                best, best_trace = candidate, float(np.trace(candidate))
    return best


def rotation_degrees(rotation: np.ndarray) -> float:
    """The angle of a rotation matrix, in degrees."""
    cosine = (float(np.trace(rotation)) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, cosine))))


def field_axes(
    poses: np.ndarray | torch.Tensor, orientation: str = "auto", snap_degrees: float = SNAP_DEGREES
) -> np.ndarray | None:
    """The field's axes (rows, a rotation) for ``orientation``, or None for the world's: always
    for "world", and for "auto" where the sweep's frame is within ``snap_degrees`` of them."""
    if orientation not in ORIENTATIONS:
        raise argument_error("orientation", f"expected one of {ORIENTATIONS}, got {orientation!r}")
    if not snap_degrees >= 0:
        raise argument_error("snap_degrees", f"expected ≥ 0, got {snap_degrees}")
    if orientation == "world":
        return None
    rotation = nearest_to_world(sweep_axes(poses))
    return None if rotation_degrees(rotation) < snap_degrees else rotation


def field_cube(
    poses: np.ndarray | torch.Tensor, probe: ProbeGeometry, orientation: str = "auto"
) -> tuple[UnitCube, tuple[float, float, float]]:
    """The field's unit cube over every pixel the probe saw, along :func:`field_axes`, and the
    field of view's half-extent per cube axis (:meth:`UnitCube.points_extent`)."""
    corners = field_of_view_corners_mm(poses, probe)
    cube = UnitCube.from_points(corners, axes=field_axes(poses, orientation))
    return cube, cube.points_extent(corners)


def _unit(vector: np.ndarray, name: str, why: str) -> np.ndarray:
    norm = float(np.linalg.norm(vector))
    if not norm > 1e-9:
        raise argument_error(name, why)
    return vector / norm
