"""Meshing: grids, chunked evaluation, surface extraction, exports."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from ultron.data.dataset import ProbeGeometry
from ultron.errors import UltronInputError
from ultron.mesh import (
    ExtractionConfig,
    GridSpec,
    NoSurfaceError,
    evaluate_on_grid,
    extract_surface,
    field_of_view_mask,
    load_mesh,
    nifti_affine,
    save_mesh,
    save_volume_nifti,
)
from ultron.mesh.marching import marching_cubes

RADIUS = 8.0
CENTER = torch.tensor([3.0, -2.0, 5.0])


def sphere_occupancy(points: torch.Tensor) -> torch.Tensor:
    return ((points - CENTER).norm(dim=-1) < RADIUS).float()


@pytest.fixture(scope="module")
def sphere_grid() -> GridSpec:
    bounds = np.stack([CENTER.numpy() - RADIUS, CENTER.numpy() + RADIUS])
    return GridSpec.from_bounds(bounds, voxel_mm=0.3)


@pytest.fixture(scope="module")
def sphere_mesh(sphere_grid):
    volume = evaluate_on_grid(sphere_occupancy, sphere_grid, chunk_points=10_000)
    return extract_surface(volume, sphere_grid)


def test_grid_points_match_affine():
    grid = GridSpec((1.0, 2.0, 3.0), 0.5, (4, 5, 6))
    points = grid.points_mm(0, grid.n_voxels).reshape(4, 5, 6, 3)
    torch.testing.assert_close(points[2, 3, 4], torch.tensor([2.0, 3.5, 5.0]))
    np.testing.assert_allclose(grid.affine @ [2, 3, 4, 1], [2.0, 3.5, 5.0, 1.0])
    np.testing.assert_allclose(grid.world_to_index(grid.index_to_world([[1, 2, 3]])), [[1, 2, 3]])


def test_chunked_evaluation_equals_single_pass(sphere_grid):
    a = evaluate_on_grid(sphere_occupancy, sphere_grid, chunk_points=777)
    b = evaluate_on_grid(sphere_occupancy, sphere_grid, chunk_points=10**8)
    assert np.array_equal(a, b)


def test_masked_voxels_are_zero_and_not_evaluated(sphere_grid):
    mask = np.zeros(sphere_grid.shape, dtype=bool)
    mask[: sphere_grid.shape[0] // 2] = True
    seen = []

    def fn(points):
        seen.append(len(points))
        return sphere_occupancy(points)

    volume = evaluate_on_grid(fn, sphere_grid, mask=mask)
    assert volume[~mask].max() == 0
    assert sum(seen) == mask.sum()


def test_sphere_area_within_two_percent(sphere_mesh):
    expected = 4 * np.pi * RADIUS**2
    assert abs(sphere_mesh.area - expected) / expected < 0.02
    assert sphere_mesh.is_watertight
    assert sphere_mesh.volume > 0  # outward normals


def test_sphere_vertices_in_mm(sphere_mesh):
    radii = np.linalg.norm(sphere_mesh.vertices - CENTER.numpy(), axis=1)
    # every vertex lies within one voxel of the true sphere
    assert np.abs(radii - RADIUS).max() < 0.3
    np.testing.assert_allclose(sphere_mesh.vertices.mean(axis=0), CENTER.numpy(), atol=0.05)


def test_small_components_are_dropped(sphere_grid):
    def with_speck(points):
        speck_centre = CENTER + torch.tensor([6.5, 6.5, 6.5])
        speck = ((points - speck_centre).norm(dim=-1) < 0.8).float()
        return sphere_occupancy(points) + speck

    volume = evaluate_on_grid(with_speck, sphere_grid)
    kept = extract_surface(volume, sphere_grid)
    assert len(kept.split(only_watertight=False)) == 1
    everything = extract_surface(volume, sphere_grid, ExtractionConfig(min_component_fraction=0.0))
    assert len(everything.split(only_watertight=False)) == 2


def test_the_observed_surface_meshes_every_piece(sphere_grid):
    """Before an observed crop every piece is meshed, however small against the largest (a
    long bone's segment beside the shadow-filled blob); the whole iso-surface, which has no
    crop, still drops the pieces under 5 % of the largest."""
    from ultron.mesh.observed import OBSERVED_EXTRACTION, ObservedSurfaceConfig

    def surface_extraction(surface):
        return ObservedSurfaceConfig(surface=surface).extraction

    def with_piece(points):  # a piece of 1.2 % of the sphere's volume
        piece = ((points - CENTER - torch.tensor([6.0, 6.0, 6.0])).norm(dim=-1) < 1.8).float()
        return sphere_occupancy(points) + piece

    volume = evaluate_on_grid(with_piece, sphere_grid)
    assert surface_extraction("observed") == OBSERVED_EXTRACTION
    observed = extract_surface(volume, sphere_grid, surface_extraction("observed"))
    parts = observed.split(only_watertight=False)
    assert len(parts) == 2
    assert min(p.area for p in parts) == pytest.approx(4 * np.pi * 1.8**2, rel=0.15)
    whole = extract_surface(volume, sphere_grid, surface_extraction("all"))
    assert len(whole.split(only_watertight=False)) == 1
    with pytest.raises(UltronInputError, match="surface"):
        surface_extraction("visible")


def test_no_surface_is_a_clear_error(sphere_grid):
    with pytest.raises(NoSurfaceError, match="no surface"):
        extract_surface(np.zeros(sphere_grid.shape, np.float32), sphere_grid)
    with pytest.raises(NoSurfaceError, match="every voxel"):
        extract_surface(np.ones(sphere_grid.shape, np.float32), sphere_grid)


def test_bad_extraction_arguments(sphere_grid):
    with pytest.raises(UltronInputError, match="occupancy"):
        extract_surface(np.zeros((3, 3, 3)), sphere_grid)
    with pytest.raises(UltronInputError, match="threshold"):
        ExtractionConfig(threshold=1.5)
    with pytest.raises(UltronInputError, match="voxel_mm"):
        GridSpec.from_bounds(np.zeros((2, 3)), voxel_mm=0)
    for bad in (np.zeros((4, 4)), np.zeros((1, 4, 4)), np.full((3, 3, 3), np.nan)):
        with pytest.raises(UltronInputError, match="inside_positive"):
            marching_cubes(bad)


def test_marching_cubes_of_a_hand_worked_cube():
    # one corner inside at +1, seven outside at −1: one triangle, its vertices halfway along
    # the corner's three edges
    cube = -np.ones((2, 2, 2))
    cube[0, 0, 0] = 1.0
    vertices, faces = marching_cubes(cube)
    assert len(faces) == 1
    expected = {(0.5, 0.0, 0.0), (0.0, 0.5, 0.0), (0.0, 0.0, 0.5)}
    assert {tuple(float(c) for c in v) for v in vertices[faces[0]]} == expected


def test_field_of_view_mask_covers_one_frame_slab():
    probe = ProbeGeometry(width_mm=10.0, depth_mm=10.0, height_px=20, width_px=20)
    grid = GridSpec.from_bounds(np.array([[-8.0, -3.0, -4.0], [8.0, 13.0, 4.0]]), voxel_mm=0.5)
    mask = field_of_view_mask(grid, np.eye(4)[None], probe, elevation_half_thickness_mm=1.0)
    centres = grid.points_mm(0, grid.n_voxels).reshape(*grid.shape, 3).numpy()
    x, y, z = centres[..., 0], centres[..., 1], centres[..., 2]
    inside = (np.abs(x) < 4.5) & (y > 0.25) & (y < 9.25) & (np.abs(z) < 0.75)
    outside = (np.abs(x) > 5.5) | (y < -0.75) | (y > 10.25) | (np.abs(z) > 1.5)
    assert mask[inside].all()
    assert not mask[outside].any()


def test_mesh_export_round_trip(tmp_path: Path, sphere_mesh):
    for suffix in (".ply", ".stl", ".obj"):
        path = save_mesh(sphere_mesh, tmp_path / f"m{suffix}")
        loaded = load_mesh(path)
        assert abs(loaded.area - sphere_mesh.area) / sphere_mesh.area < 1e-4
    with pytest.raises(UltronInputError, match="suffix"):
        save_mesh(sphere_mesh, tmp_path / "m.xyz")


def test_load_mesh_errors(tmp_path: Path):
    with pytest.raises(UltronInputError, match="missing"):
        load_mesh(tmp_path / "none.ply")
    empty = tmp_path / "empty.ply"
    empty.write_text(
        "ply\nformat ascii 1.0\nelement vertex 0\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n"
    )
    with pytest.raises(UltronInputError, match="empty"):
        load_mesh(empty)


def test_nifti_affine_maps_voxel_to_mm(tmp_path: Path):
    import nibabel as nib

    grid = GridSpec((10.0, -20.0, 30.0), 0.5, (6, 7, 8))
    volume = np.zeros(grid.shape, np.float32)
    volume[2, 3, 4] = 1.0
    path = save_volume_nifti(volume, grid, tmp_path / "occ.nii.gz")
    image = nib.load(path)
    assert np.array_equal(np.asarray(image.dataobj), volume)
    world = np.array([10.0 + 2 * 0.5, -20.0 + 3 * 0.5, 30.0 + 4 * 0.5])
    # NIfTI is RAS; ultron's world mm is read by Slicer as LPS: x and y flip sign
    np.testing.assert_allclose(image.affine @ [2, 3, 4, 1], [-world[0], -world[1], world[2], 1.0])
    np.testing.assert_allclose(nifti_affine(grid), image.affine)


@pytest.mark.parametrize(
    ("name", "content"),
    [("e.stl", b"ultron".ljust(80, b" ") + bytes(4)), ("e.stl", b"solid empty\nendsolid empty\n"),
     ("e.ply", b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n"),
     ("e.obj", b"# nothing yet\n")],
)  # fmt: skip
def test_an_empty_mesh_file_reads_as_an_empty_reconstruction(tmp_path: Path, name, content):
    """A mesh file of its format without triangles is an empty reconstruction (metrics inf);
    text or bytes of something else under a mesh suffix are not (test_bad_input_corpus)."""
    path = tmp_path / name
    path.write_bytes(content)
    assert len(load_mesh(path, allow_empty=True).faces) == 0
    with pytest.raises(UltronInputError, match="empty"):
        load_mesh(path)
