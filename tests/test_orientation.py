"""The field's axes from the sweep (ultron.data.orientation) and the oriented unit cube."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from conftest import make_pose
from ultron.data.dataset import ProbeGeometry
from ultron.data.geometry import UnitCube, field_of_view_bounds_mm, field_of_view_corners_mm
from ultron.data.orientation import (
    field_axes,
    field_cube,
    nearest_to_world,
    rotation_degrees,
    sweep_axes,
)
from ultron.errors import UltronInputError
from ultron.train.field_config import FieldTrainConfig

PROBE = ProbeGeometry(width_mm=30.0, depth_mm=40.0, height_px=80, width_px=60)


def linear_sweep(turn: np.ndarray, n: int = 12, step_mm: float = 2.0) -> np.ndarray:
    """Probe-to-world poses (n, 4, 4) of a sweep along the probe's elevation (+z), the whole
    sweep then turned by ``turn`` (3 × 3) about the world origin."""
    local = np.stack([make_pose(None, (0.0, 0.0, step_mm * i)) for i in range(n)])
    world = np.eye(4)
    world[:3, :3] = turn
    return world @ local


def test_sweep_axes_by_hand():
    # the probe travels along world +z with its beam along world +y: A = (z, y, z × y = −x)
    poses = linear_sweep(np.eye(3))
    np.testing.assert_allclose(np.abs(sweep_axes(poses)), [[0, 0, 1], [0, 1, 0], [1, 0, 0]])
    axes = sweep_axes(poses)
    assert np.allclose(axes[1], [0, 1, 0]) and np.allclose(abs(axes[0] @ [0, 0, 1]), 1)
    assert np.linalg.det(axes) == pytest.approx(1.0)
    # a probe that does not move: the travel direction is its lateral axis, across the beam
    still = np.stack([make_pose() for _ in range(4)])
    np.testing.assert_allclose(np.abs(sweep_axes(still)[0]), [1, 0, 0], atol=1e-12)


def test_nearest_to_world_relabels_axes_and_keeps_a_rotation():
    turn = Rotation.from_euler("xyz", [3, -2, 4], degrees=True).as_matrix()
    relabelled = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]], float) @ turn  # det +1
    nearest = nearest_to_world(relabelled)
    np.testing.assert_allclose(nearest, turn, atol=1e-12)
    assert rotation_degrees(np.eye(3)) == 0.0
    assert rotation_degrees(Rotation.from_euler("z", 30, degrees=True).as_matrix()) == (
        pytest.approx(30.0)
    )


def test_field_axes_keep_the_world_for_an_aligned_sweep_and_turn_with_an_oblique_one():
    aligned = linear_sweep(Rotation.from_euler("y", 2, degrees=True).as_matrix())
    assert field_axes(aligned) is None  # 2° < the 5° snap: no rotation at all
    assert field_axes(aligned, snap_degrees=1.0) is not None
    turn = Rotation.from_euler("xz", [20, 25], degrees=True).as_matrix()
    oblique = linear_sweep(turn)
    axes = field_axes(oblique)
    assert axes is not None
    # the field's axes are the sweep's: travel, beam and their cross product, turned with it
    np.testing.assert_allclose(axes, turn.T, atol=1e-9)
    assert field_axes(oblique, "world") is None
    with pytest.raises(UltronInputError, match="orientation"):
        field_axes(oblique, "pca")


def test_field_cube_of_an_aligned_sweep_is_the_world_cube_bit_for_bit():
    poses = linear_sweep(np.eye(3))
    cube, extent = field_cube(poses, PROBE)
    bounds = field_of_view_bounds_mm(poses, PROBE)
    assert cube == UnitCube.from_bounds(bounds) and cube.axes is None
    assert extent == cube.box_extent(bounds)


def test_oriented_cube_is_tighter_and_holds_the_field_of_view():
    turn = Rotation.from_euler("xz", [20, 25], degrees=True).as_matrix()
    poses = linear_sweep(turn, n=40)
    cube, extent = field_cube(poses, PROBE)
    world = UnitCube.from_bounds(field_of_view_bounds_mm(poses, PROBE))
    corners = field_of_view_corners_mm(poses, PROBE)
    unit = cube.to_unit(corners)
    assert unit.abs().max() == pytest.approx(1 / 1.05)  # the longest side, grown by the margin
    half = unit.abs().max(dim=0).values.numpy()
    np.testing.assert_allclose(extent, np.minimum(half + 0.05 * half.max(), 1.0), rtol=1e-9)
    # the aligned box is the sweep's own: far less volume than the world box around it
    assert math.prod(extent) < 0.5 * math.prod(
        world.box_extent(field_of_view_bounds_mm(poses, PROBE))
    )


def test_oriented_cube_round_trip_and_serialisation():
    turn = Rotation.from_euler("xyz", [10, -35, 60], degrees=True).as_matrix()
    cube = UnitCube((1.0, -2.0, 3.0), 12.5, tuple(map(tuple, turn)))
    points = torch.randn(100, 3, dtype=torch.float64) * 10
    back = cube.to_world(cube.to_unit(points))
    torch.testing.assert_close(back, points, rtol=0, atol=1e-12)
    # u = A (x − c) / h, by hand for one point
    x = np.array([4.0, 5.0, -6.0])
    expected = turn @ (x - np.array([1.0, -2.0, 3.0])) / 12.5
    np.testing.assert_allclose(cube.to_unit(torch.tensor(x)).numpy(), expected, atol=1e-14)
    assert UnitCube.from_dict(cube.to_dict()) == cube
    plain = UnitCube((0.0, 0.0, 0.0), 1.0)
    assert "axes" not in plain.to_dict() and UnitCube.from_dict(plain.to_dict()) == plain


@pytest.mark.parametrize(
    "axes",
    [
        ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),  # not 3 × 3
        ((2.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),  # not orthonormal
        ((-1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),  # a reflection
        ((math.nan, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    ],
)
def test_unit_cube_rejects_axes_that_are_not_a_rotation(axes):
    with pytest.raises(UltronInputError, match="axes"):
        UnitCube((0.0, 0.0, 0.0), 1.0, axes)


def test_unit_cube_from_points_rejects_bad_points():
    with pytest.raises(UltronInputError, match="points_mm"):
        UnitCube.from_points(np.zeros((0, 3)))
    with pytest.raises(UltronInputError, match="points_mm"):
        UnitCube.from_points(np.array([[0.0, math.inf, 0.0]]))


def test_field_config_orientation():
    assert FieldTrainConfig().orientation == "world"
    with pytest.raises(UltronInputError, match="orientation"):
        FieldTrainConfig(orientation="tilted")
    # the world's axes are written as before the option (field.json, the cache's key) and a
    # field.json without it was fitted on them
    assert "orientation" not in FieldTrainConfig().to_dict()
    assert FieldTrainConfig.from_dict(FieldTrainConfig().to_dict()).orientation == "world"
    oriented = FieldTrainConfig(orientation="auto")
    assert oriented.to_dict()["orientation"] == "auto"
    assert FieldTrainConfig.from_dict(oriented.to_dict()) == oriented


def test_the_cli_refuses_what_the_library_refuses(tmp_path):
    """fit-field hands --orientation to the library, whose check names the option and lists
    the library's choices."""
    from typer.testing import CliRunner

    from ultron.cli.main import app
    from ultron.data.orientation import ORIENTATIONS

    args = ["fit-field", str(tmp_path), "--out", str(tmp_path / "f"), "--orientation", "tilted"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2
    assert result.stderr.startswith(
        f"error: argument: --orientation: expected one of {ORIENTATIONS}"
    )
    assert not (tmp_path / "f").exists()


def test_a_field_fitted_along_a_turned_sweep_is_the_unturned_fit(tmp_path):
    """The same frames recorded along the world's axes and turned by 30°: with orientation
    "auto" the turned sweep's field is fitted in the sweep's own frame, which is the unturned
    sweep's world frame, so both fits see the same unit-cube points (to rounding) and render
    the same frames; field.json keeps the axes and the loaded field renders as fitted."""
    from test_field_fit import quick_config, tiny_dataset
    from ultron.data.dataset import Sweep, SweepDataset
    from ultron.models.fitted import load_field
    from ultron.train import fit_field

    data = tiny_dataset(12)
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("xz", [30, -20], degrees=True).as_matrix()
    sweep = data.sweeps[0]
    turned = SweepDataset(
        data.probe, [Sweep(sweep.name, sweep.kind, sweep.images, turn @ sweep.probe_to_world)]
    )
    config = quick_config(iterations=5, orientation="auto")
    plain = fit_field(data, config, tmp_path / "plain")
    oriented = fit_field(turned, config, tmp_path / "turned")
    assert plain.unit_cube.axes is None and oriented.unit_cube.axes is not None
    np.testing.assert_allclose(oriented.unit_cube.axes, turn[:3, :3].T, atol=1e-9)
    rendered = oriented.render(turned.all_poses(), seed=1)
    np.testing.assert_allclose(rendered, plain.render(data.all_poses(), seed=1), atol=1e-4)
    loaded = load_field(tmp_path / "turned")
    assert loaded.unit_cube == oriented.unit_cube
    np.testing.assert_array_equal(loaded.render(turned.all_poses(), seed=1), rendered)
    # on the world's axes the turned sweep is another fit
    world = fit_field(turned, quick_config(iterations=5), tmp_path / "world")
    assert world.unit_cube.axes is None
    assert not np.allclose(world.render(turned.all_poses(), seed=1), rendered, atol=1e-4)
