"""Hand-worked probe geometry: pixels, scanlines, samples, bounds, normalisation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from conftest import make_pose, rotation_z
from ultron.data.dataset import ProbeGeometry
from ultron.data.geometry import (
    UnitCube,
    field_of_view_bounds_mm,
    frame_pixels_world,
    pixel_to_world,
    probe_mm_to_pixel,
    probe_points_mm,
    scanline_rays,
    scanline_sample_points,
)
from ultron.errors import UltronInputError

PROBE = ProbeGeometry(width_mm=40.0, depth_mm=60.0, height_px=120, width_px=80)
H, W = PROBE.height_px, PROBE.width_px


def test_spacing():
    assert PROBE.lateral_spacing_mm == pytest.approx(0.5)
    assert PROBE.axial_spacing_mm == pytest.approx(0.5)


def test_identity_pose_top_centre_pixel_is_origin():
    point = pixel_to_world(
        torch.eye(4, dtype=torch.float64)[None], torch.tensor(0.0), torch.tensor(W / 2), PROBE
    )
    assert torch.equal(point[0], torch.zeros(3, dtype=torch.float64))


def test_identity_pose_bottom_centre_pixel_depth():
    point = pixel_to_world(
        torch.eye(4, dtype=torch.float64)[None], torch.tensor(H - 1.0), torch.tensor(W / 2), PROBE
    )
    expected = torch.tensor([0.0, (H - 1) * 60.0 / H, 0.0], dtype=torch.float64)
    torch.testing.assert_close(point[0], expected, rtol=0, atol=1e-12)


def test_lateral_pixel_offset():
    # column 0 lies half the probe width to the left of the centre
    point = probe_points_mm(torch.tensor(0.0), torch.tensor(0.0), PROBE)
    torch.testing.assert_close(point, torch.tensor([-20.0, 0.0, 0.0]))


def test_probe_mm_to_pixel_inverts_probe_points():
    rows = torch.tensor([0.0, 17.25, H - 1.0], dtype=torch.float64)
    cols = torch.tensor([0.0, 31.5, W - 1.0], dtype=torch.float64)
    points = probe_points_mm(rows, cols, PROBE).numpy()
    back_rows, back_cols = probe_mm_to_pixel(points[:, 0], points[:, 1], PROBE)
    np.testing.assert_allclose(back_rows, rows.numpy(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(back_cols, cols.numpy(), rtol=0, atol=1e-12)
    # hand-worked: the probe's centre line 30 mm deep is row H/2, column W/2
    assert probe_mm_to_pixel(0.0, 30.0, PROBE) == (H / 2, W / 2)


def test_rotation_about_z_by_90_degrees_swaps_axes():
    pose = torch.as_tensor(make_pose(rotation_z(90.0), (10.0, 0.0, 5.0)))[None]
    # a pixel 30 mm deep on the centre line: probe (0, 30, 0) → world (−30, 0, 0) + t
    point = pixel_to_world(pose, torch.tensor(60.0), torch.tensor(W / 2), PROBE)[0]
    torch.testing.assert_close(
        point, torch.tensor([-20.0, 0.0, 5.0], dtype=torch.float64), atol=1e-12, rtol=0
    )
    # a pixel at the left edge, depth 0: probe (−20, 0, 0) → world (0, −20, 0) + t
    point = pixel_to_world(pose, torch.tensor(0.0), torch.tensor(0.0), PROBE)[0]
    torch.testing.assert_close(
        point, torch.tensor([10.0, -20.0, 5.0], dtype=torch.float64), atol=1e-12, rtol=0
    )


def test_frame_pixels_world_matches_pointwise():
    poses = torch.as_tensor(np.stack([make_pose(rotation_z(30.0), (1, 2, 3)), make_pose()]))
    grid = frame_pixels_world(poses, PROBE)
    assert grid.shape == (2, H, W, 3)
    single = pixel_to_world(poses, torch.tensor(17.0), torch.tensor(33.0), PROBE)
    torch.testing.assert_close(grid[:, 17, 33], single)


def test_scanlines_and_samples_land_on_pixels():
    poses = torch.as_tensor(np.stack([make_pose(rotation_z(-40.0), (5, -3, 2))]))
    origins, directions = scanline_rays(poses, PROBE)
    assert origins.shape == directions.shape == (1, W, 3)
    torch.testing.assert_close(directions.norm(dim=-1), torch.ones(1, W, dtype=torch.float64))
    samples = scanline_sample_points(origins, directions, H, PROBE.axial_spacing_mm)
    assert samples.shape == (1, W, H, 3)
    # sample k of scanline c is pixel (k, c)
    pixels = frame_pixels_world(poses, PROBE)
    torch.testing.assert_close(samples.transpose(1, 2), pixels, atol=1e-10, rtol=0)
    # ordered along the ray: depth increases monotonically
    depth = ((samples - origins[..., None, :]) * directions[..., None, :]).sum(-1)
    assert (depth.diff(dim=-1) > 0).all()


def test_bounds_of_identity_frame():
    bounds = field_of_view_bounds_mm(np.eye(4)[None], PROBE)
    expected = torch.tensor(
        [[-20.0, 0.0, 0.0], [(W - 1) * 0.5 - 20.0, (H - 1) * 0.5, 0.0]], dtype=torch.float64
    )
    torch.testing.assert_close(bounds, expected)


def test_bounds_contain_every_pixel():
    rng = np.random.default_rng(3)
    poses = np.stack([make_pose(rotation_z(a), rng.normal(size=3) * 10) for a in (0, 33, 71, 150)])
    bounds = field_of_view_bounds_mm(poses, PROBE)
    pixels = frame_pixels_world(torch.as_tensor(poses), PROBE).reshape(-1, 3)
    assert (pixels >= bounds[0] - 1e-9).all() and (pixels <= bounds[1] + 1e-9).all()
    # tight: some pixel touches each face
    assert torch.allclose(pixels.min(0).values, bounds[0]) and torch.allclose(
        pixels.max(0).values, bounds[1]
    )


def test_unit_cube_is_isotropic_and_contains_box():
    bounds = torch.tensor([[0.0, -10.0, 5.0], [40.0, 10.0, 6.0]], dtype=torch.float64)
    cube = UnitCube.from_bounds(bounds, margin=0.0)
    unit = cube.to_unit(bounds)
    torch.testing.assert_close(unit[:, 0], torch.tensor([-1.0, 1.0], dtype=torch.float64))
    # same scale on every axis: the 20 mm y side maps to half the x side
    assert (unit[1] - unit[0])[1].item() == pytest.approx(1.0)
    assert (unit[1] - unit[0])[2].item() == pytest.approx(0.05)


def test_unit_cube_round_trip_exact():
    generator = torch.Generator().manual_seed(0)
    cube = UnitCube.from_bounds(torch.tensor([[31.5, -118.1, 12.4], [114.9, 29.9, 88.4]]))
    points32 = (torch.rand(10_000, 3, generator=generator) * 300 - 150).to(torch.float32)
    back = cube.to_world(cube.to_unit(points32, dtype=torch.float64), dtype=torch.float32)
    assert torch.equal(back, points32)  # bit-exact for float32 coordinates
    points64 = points32.double() + 1e-3
    torch.testing.assert_close(cube.to_world(cube.to_unit(points64)), points64, rtol=0, atol=1e-12)
    assert UnitCube.from_dict(cube.to_dict()) == cube


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(center_mm=(0.0, 0.0), half_extent_mm=1.0),
        dict(center_mm=(0.0, 0.0, 0.0), half_extent_mm=0.0),
        dict(center_mm=(0.0, float("nan"), 0.0), half_extent_mm=1.0),
    ],
)
def test_unit_cube_rejects_bad_arguments(kwargs):
    with pytest.raises(UltronInputError):
        UnitCube(**kwargs)


def test_probe_geometry_rejects_bad_arguments():
    with pytest.raises(UltronInputError, match="width_mm"):
        ProbeGeometry(0.0, 10.0, 4, 4)
    with pytest.raises(UltronInputError, match="height_px"):
        ProbeGeometry(10.0, 10.0, 0, 4)


def test_pose_shape_is_checked():
    with pytest.raises(UltronInputError, match="probe_to_world"):
        pixel_to_world(torch.eye(3), torch.tensor(0.0), torch.tensor(0.0), PROBE)
