"""Label support between labelled frames (:mod:`ultron.mesh.label_bridges`): hand-worked
distances across the beam plane, bridges only between frames whose labelled cross-sections
agree, a frame without bone breaking the run, and invalid inputs."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from conftest import make_pose
from ultron.data.dataset import ProbeGeometry, Sweep, SweepDataset
from ultron.data.labels import FrameSelection, labelled_surface_points_mm
from ultron.errors import UltronInputError
from ultron.mesh.label_bridges import (
    across_plane_mm,
    bridge_points_mm,
    bridged_labelled_surface_mm,
)
from ultron.mesh.observed import ObservedSurfaceConfig
from ultron.methods.ultron_method import UltronConfig, labelled_support_points_mm

Z = np.array([0.0, 0.0, 1.0])


def test_across_plane_distance_by_hand() -> None:
    points = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    other = np.array([[0.6, 0.8, 5.0], [3.0, 0.0, 5.5], [10.0, 0.0, 0.0]])
    offsets, across = across_plane_mm(points, other, Z)
    # nearest of (0, 0, 0) is (0.6, 0.8, 5) (|d| = √26); across the z-plane: √(0.36 + 0.64) = 1
    np.testing.assert_allclose(offsets, [[0.6, 0.8, 5.0], [0.0, 0.0, 5.5]])
    np.testing.assert_allclose(across, [1.0, 0.0], atol=1e-12)
    # an oblique elevation axis: the offset (0, 0, 5.5) is 5.5·sin 30° = 2.75 across its plane
    axis = np.array([0.0, np.sin(np.pi / 6), np.cos(np.pi / 6)])
    np.testing.assert_allclose(across_plane_mm(points[1:], other[1:2], axis)[1], [2.75])
    # a tracked pose's axis is a unit vector only to 1e-3: it is normalised, not refused
    np.testing.assert_allclose(across_plane_mm(points, other, 1.001 * Z)[1], across, atol=1e-12)


def _curve(z: float, y: float = 10.0, n: int = 9) -> np.ndarray:
    return np.stack([np.linspace(-4.0, 4.0, n), np.full(n, y), np.full(n, z)], axis=1)


def test_agreeing_frames_are_bridged_along_elevation() -> None:
    a, b = _curve(0.0), _curve(4.0, y=10.3)  # the same cross-section, 0.3 mm deeper at z = 4
    points = bridge_points_mm(a, b, Z, Z, tolerance_mm=1.0, step_mm=0.25)
    # each of the 2 × 9 band-top points starts a segment of ⌈√(16 + 0.09) / 0.25⌉ + 1 = 18 points
    assert points.shape == (2 * 9 * 18, 3)
    assert points[:, 2].min() == 0.0 and points[:, 2].max() == 4.0
    # every point lies on the straight segment between the two curves
    np.testing.assert_allclose(points[:, 1], 10.0 + 0.3 * points[:, 2] / 4.0, atol=1e-12)
    assert set(np.round(points[:, 0], 9)) == set(np.round(a[:, 0], 9))


def test_frames_that_disagree_are_not_bridged() -> None:
    a = _curve(0.0)
    shifted = _curve(4.0, y=11.5)  # 1.5 mm deeper: beyond τ = 1 mm
    assert bridge_points_mm(a, shifted, Z, Z, 1.0).shape == (0, 3)
    assert bridge_points_mm(a, shifted, Z, Z, 1.5).shape[0] > 0
    # agreement is asked both ways: a short curve that lies on a long one agrees from its own
    # side only, and the median of the long one's distances is far
    short = _curve(4.0, n=3)[:, :] * np.array([0.1, 1.0, 1.0])
    assert bridge_points_mm(a, short, Z, Z, 1.0).shape == (0, 3)


def test_a_point_without_a_partner_is_not_bridged() -> None:
    a = np.concatenate([_curve(0.0), [[20.0, 10.0, 0.0]]])  # one point far off the other curve
    points = bridge_points_mm(a, _curve(4.0), Z, Z, 1.0)
    assert not np.any(np.isclose(points[:, 0], 20.0))


def _dataset(bone_rows: list[int | None]) -> SweepDataset:
    """Frames 2 mm apart along z; frame i has a bone band whose top is row bone_rows[i] in every
    column (1 mm pixels), or only background (None)."""
    n = len(bone_rows)
    labels = np.zeros((n, 6, 5), np.uint8)
    for i, row in enumerate(bone_rows):
        if row is not None:
            labels[i, row:, :] = 1
    poses = np.stack([make_pose(translation=(0.0, 0.0, 2.0 * i)) for i in range(n)])
    sweep = Sweep("a", "row", np.zeros((n, 6, 5), np.uint8), poses, labels)
    return SweepDataset(ProbeGeometry(5.0, 6.0, 6, 5), [sweep])


def test_bridged_labelled_surface_of_a_dataset() -> None:
    data = _dataset([2, 2, 5, 2, None, 2])
    everything = FrameSelection(1.0, 0, {"a": np.arange(6)})
    tops = labelled_surface_points_mm(data, everything)
    points = bridged_labelled_surface_mm(data, everything, 1.0, step_mm=0.5)
    np.testing.assert_array_equal(points[: len(tops)], tops)  # the band tops come first
    bridged = points[len(tops) :]
    # only frames 0 and 1 agree (frame 2's band is 3 mm deeper; frame 4 has no bone, so frames
    # 3 and 5 are not consecutive labelled surface): 2 × 5 columns × (2 / 0.5 + 1) points
    assert bridged.shape == (2 * 5 * 5, 3)
    assert bridged[:, 2].min() == 0.0 and bridged[:, 2].max() == 2.0
    np.testing.assert_allclose(bridged[:, 1], 2.0)
    # the selection decides which frames are consecutive: frames 0 and 3 agree, 6 mm apart
    sparse = FrameSelection(0.5, 0, {"a": np.array([0, 3])})
    assert bridged_labelled_surface_mm(data, sparse, 1.0, step_mm=0.5)[:, 2].max() == 6.0
    assert bridged_labelled_surface_mm(data, None, 1.0).shape == (0, 3)


def test_the_method_counts_bridges_only_when_asked() -> None:
    data = _dataset([2, 2])
    selection = FrameSelection(1.0, 0, {"a": np.arange(2)})
    observed = UltronConfig().observed
    assert observed.label_bridges  # the default
    with_bridges = labelled_support_points_mm(data, selection, observed)
    without = labelled_support_points_mm(data, selection, replace(observed, label_bridges=False))
    np.testing.assert_array_equal(without, labelled_surface_points_mm(data, selection))
    assert len(with_bridges) > len(without)


def test_invalid_inputs_name_the_argument() -> None:
    a = _curve(0.0)
    with pytest.raises(UltronInputError, match="tolerance_mm"):
        bridge_points_mm(a, a, Z, Z, -1.0)
    with pytest.raises(UltronInputError, match="step_mm"):
        bridge_points_mm(a, a, Z, Z, 1.0, step_mm=0.0)
    with pytest.raises(UltronInputError, match="points_mm"):
        across_plane_mm(np.zeros((0, 3)), a, Z)
    with pytest.raises(UltronInputError, match="other_mm"):
        across_plane_mm(a, np.zeros((4, 2)), Z)
    for axis in (np.zeros(3), np.array([0.0, 0.0, np.nan]), np.ones(2)):
        with pytest.raises(UltronInputError, match="elevation_axis"):
            across_plane_mm(a, a, axis)
    with pytest.raises(UltronInputError, match="label_bridges"):
        ObservedSurfaceConfig(label_bridges="yes")  # type: ignore[arg-type]
