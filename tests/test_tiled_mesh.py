"""Tiled meshing equals the single-grid meshing: marching cubes, smoothing band, components,
coarse-to-fine evaluation and the stitched mesh."""

from __future__ import annotations

import mcubes
import numpy as np
import pytest
import torch

from ultron.data.dataset import ProbeGeometry
from ultron.errors import UltronInputError
from ultron.mesh import GridSpec, evaluate_coarse_to_fine
from ultron.mesh.extract import (
    ExtractionConfig,
    NoSurfaceError,
    extract_surface,
    extract_surface_single_grid,
    extract_surface_tiles,
)
from ultron.mesh.grid import field_of_view_mask
from ultron.mesh.marching import block_triangles, merge_blocks
from ultron.mesh.smoothing import band_second_differences, second_difference_system
from ultron.mesh.tiles import (
    BinaryTiles,
    PooledVolume,
    TileLayout,
    evaluate_tiles,
    field_of_view_tiles,
    gather,
    tile_for_factor,
    volume_factor,
)

CENTER = (1.0, -2.0, 0.5)


def rational_blobs(points: torch.Tensor) -> torch.Tensor:
    """A 6 mm ball, a 1.2 mm plate and a 0.6 mm speck from +, ×, / only: each value is
    correctly rounded whatever the batch, so chunkings agree to the bit."""
    x, y, z = (points[:, i].double() for i in range(3))
    r2 = (x - CENTER[0]) ** 2 + (y - CENTER[1]) ** 2 + (z - CENTER[2]) ** 2
    ball = 36.0 / (36.0 + r2 * r2 / 36.0)
    plate = 0.36 / (0.36 + (z - 8.0) ** 2) * (x.abs() < 7)
    speck = 0.25 / (0.25 + (x + 7) ** 2 + (y - 5) ** 2 + (z + 4) ** 2)
    return torch.maximum(torch.maximum(ball, plate), speck).float()


@pytest.fixture(scope="module")
def sweep():
    """A probe and 50 poses: a transverse pass and a crossing sagittal one over the blobs."""
    probe = ProbeGeometry(width_mm=14.0, depth_mm=16.0, height_px=16, width_px=12)
    poses = []
    for z in np.linspace(-6, 10, 30):
        pose = np.eye(4)
        pose[:3, 3] = [0.0, -10.0, z]
        poses.append(pose)
    for x in np.linspace(-8, 8, 20):
        pose = np.eye(4)
        pose[:3, :3] = [[0, 0, -1], [0, 1, 0], [1, 0, 0]]
        pose[:3, 3] = [x, -10.0, 2.0]
        poses.append(pose)
    return probe, np.stack(poses)


def assert_same_mesh(a, b) -> None:
    assert np.array_equal(np.asarray(a.vertices), np.asarray(b.vertices))
    assert np.array_equal(np.asarray(a.faces), np.asarray(b.faces))


@pytest.mark.parametrize("seed", range(6))
def test_block_marching_cubes_is_pymcubes(seed):
    rng = np.random.default_rng(seed)
    shape = tuple(int(s) for s in rng.integers(4, 13, size=3))
    values = rng.normal(size=shape)
    if seed % 2:
        values = np.round(values)  # exact zeros: vertices on grid nodes
    values[0], values[:, 0], values[:, :, 0] = -1.0, -1.0, -1.0  # a padded crop's low faces
    expected_vertices, expected_faces = mcubes.marching_cubes(values, 0.0)
    box, side = np.asarray(shape), int(rng.integers(2, 6))
    blocks = []
    for start in np.ndindex(*(-(-(n - 1) // side) for n in shape)):
        lo = np.asarray(start) * side
        hi = np.minimum(lo + side, box - 1)
        blocks.append(
            block_triangles(
                values[tuple(slice(a, b + 1) for a, b in zip(lo, hi, strict=True))], lo, box
            )
        )
    vertices, faces = merge_blocks(blocks, box)
    assert np.array_equal(vertices, expected_vertices)
    assert np.array_equal(faces, expected_faces.astype(np.int64))


@pytest.mark.parametrize("shape", [(6, 5, 4), (2, 7, 3), (5, 1, 2), (3, 2, 9)])
def test_band_matrix_is_the_voxel_by_voxel_one(shape):
    """Q = Σ_a D_aᵀ D_a built voxel by voxel from the module doc's rule (a missing neighbour,
    outside the band or the box, contributes the voxel itself), and from the sorted keys;
    boxes under 3 voxels along an axis put the entries out of key order before sorting."""
    rng = np.random.default_rng(1)
    band = rng.random(shape) < 0.5
    voxels = [tuple(v) for v in np.argwhere(band)]
    index = {v: i for i, v in enumerate(voxels)}
    q = np.zeros((len(voxels), len(voxels)))
    for axis in range(3):
        d = np.zeros_like(q)
        for i, v in enumerate(voxels):
            d[i, i] = -2.0
            for offset in (-1, 1):
                w = list(v)
                w[axis] += offset
                d[i, index.get(tuple(w), i)] += 1.0
        q += d.T @ d
    ours = band_second_differences(np.flatnonzero(band), np.asarray(band.shape))
    rows = np.repeat(np.arange(ours.shape[0]), np.diff(ours.indptr))
    assert np.all((np.diff(ours.indices) > 0) | (np.diff(rows) > 0))  # each row's in order
    np.testing.assert_array_equal(ours.toarray(), q)
    np.testing.assert_array_equal(second_difference_system(band).toarray(), q)


@pytest.mark.parametrize("tile", [8, 13, 64])
@pytest.mark.parametrize("smooth", [True, False])
def test_tiled_extraction_equals_single_grid(grid, tile, smooth):
    volume = evaluate_coarse_to_fine(rational_blobs, grid, 0.5, 2)
    config = ExtractionConfig(smooth=smooth)
    assert_same_mesh(extract_surface(volume, grid, config, tile=tile),
                     extract_surface_single_grid(volume, grid, config))  # fmt: skip


@pytest.mark.parametrize("seed", range(3))
def test_tiled_extraction_of_a_surface_cut_by_the_grid_border(seed):
    rng = np.random.default_rng(seed)
    shape = tuple(int(s) for s in rng.integers(20, 34, size=3))
    grid = GridSpec((0.0, 0.0, 0.0), 0.5, shape)
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
    centre = np.array(shape) * rng.choice([-0.1, 1.1], size=3)  # beyond a corner
    radius = np.linalg.norm(np.array(shape) * 0.6)
    volume = (np.linalg.norm(ijk - centre, axis=-1) < radius).astype(np.float32)
    volume = np.maximum(volume, (rng.random(shape) < 0.003).astype(np.float32))  # specks
    assert_same_mesh(
        extract_surface(volume, grid, tile=7), extract_surface_single_grid(volume, grid)
    )


def test_tiled_extraction_errors(grid):
    empty = np.zeros(grid.shape, dtype=np.float32)
    with pytest.raises(NoSurfaceError, match="no voxel"):
        extract_surface(empty, grid)
    with pytest.raises(NoSurfaceError, match="every voxel"):
        extract_surface(empty + 1, grid, tile=16)
    with pytest.raises(UltronInputError, match="NaN"):
        extract_surface(empty + np.nan, grid)
    tiles = BinaryTiles(TileLayout((2, 2, 2)))
    with pytest.raises(UltronInputError, match="tiles"):
        extract_surface_tiles(tiles, grid)


@pytest.mark.parametrize(("factor", "tile"), [(2, 8), (2, 10), (1, 5), (4, 16)])
def test_tiled_evaluation_equals_the_dense_grid(grid, sweep, factor, tile):
    probe, poses = sweep
    coarse = grid.coarsened(factor)
    mask = field_of_view_mask(coarse, poses, probe, 0.4)
    tiles = field_of_view_tiles(coarse, poses, probe, 0.4, tile // factor)
    whole = gather(tiles, TileLayout(coarse.shape, tile // factor), np.zeros(3), coarse.shape)
    assert np.array_equal(whole, mask)
    dense = evaluate_coarse_to_fine(rational_blobs, grid, 0.5, factor, coarse_mask=mask)
    tiled = evaluate_tiles(rational_blobs, grid, 0.5, factor, tiles, tile)
    assert np.array_equal(tiled.volume.values, dense)  # bit for bit
    assert tiled.volume.grid == grid
    assert tiled.stats["tiles_evaluated"] <= tiled.stats["tiles_in_grid"]
    assert_same_mesh(extract_surface_tiles(tiled.tiles, grid),
                     extract_surface_single_grid(dense, grid))  # fmt: skip


def test_pooled_volume_keeps_block_means(grid):
    assert volume_factor((100, 100, 100), 10**6) == 1
    assert volume_factor((100, 100, 100), 10**6 - 1) == 2
    assert volume_factor((101, 9, 9), 51 * 25) == 2  # ⌈101/2⌉·⌈9/2⌉² = 51·25
    assert volume_factor((101, 9, 9), 51 * 25 - 1) == 4
    rng = np.random.default_rng(0)
    fine = rng.random(grid.shape).astype(np.float32)
    pooled = PooledVolume(grid, 4)
    layout = TileLayout(grid.shape, 16)
    for key in np.ndindex(*layout.counts):
        lo, hi = layout.bounds(key)
        pooled.add(lo, fine[tuple(slice(a, b) for a, b in zip(lo, hi, strict=True))])
    assert pooled.values.shape == tuple(-(-n // 4) for n in grid.shape)
    assert pooled.values[1, 2, 3] == pytest.approx(fine[4:8, 8:12, 12:16].mean(), rel=1e-6)
    edge = fine[-(grid.shape[0] % 4 or 4) :, :4, :4]
    assert pooled.values[-1, 0, 0] == pytest.approx(edge.mean(), rel=1e-6)
    centre = np.asarray(grid.origin_mm) + grid.voxel_mm * 1.5  # centroid of voxels 0…3
    np.testing.assert_allclose(pooled.grid.origin_mm, centre)
    assert pooled.grid.voxel_mm == pytest.approx(4 * grid.voxel_mm)


def test_tile_for_factor():
    assert tile_for_factor(2) == 64
    assert tile_for_factor(3) == 66
    with pytest.raises(UltronInputError, match="coarse_factor"):
        tile_for_factor(0)


@pytest.mark.parametrize("isolated", [False, True])
@pytest.mark.parametrize("rows_at_once", [1 << 16, 7])
@pytest.mark.parametrize("overwrite", [False, True])
def test_jacobi_step_matrix_is_the_sparse_expression(
    isolated, rows_at_once, overwrite, monkeypatch
):
    """J written on Q's entries has the bits of (1 − w)·I − w·D⁻¹(Q − D) built by sparse
    products, however many rows are scaled at once, and leaves Q as it was unless told to
    overwrite it; a band with an isolated voxel (an empty row of Q) takes the sparse path."""
    from scipy import sparse

    from ultron.mesh import smoothing
    from ultron.mesh.smoothing import jacobi_step_matrix

    monkeypatch.setattr(smoothing, "_ROWS_AT_ONCE", rows_at_once)

    band = np.random.default_rng(2).random((7, 6, 5)) < 0.9
    if isolated:
        band = np.pad(band, ((0, 3), (0, 0), (0, 0)))
        band[-1, 0, 0] = True
    q = band_second_differences(np.flatnonzero(band), np.asarray(band.shape))
    assert (np.diff(q.indptr) == 0).any() == isolated
    original = q.copy()
    with np.errstate(divide="ignore"):
        d = q.diagonal()
        expected = sparse.diags(-0.5 / d) @ (q - sparse.diags(d))
        ours = jacobi_step_matrix(q, 0.5, overwrite_q=overwrite)
    expected = (expected + sparse.identity(len(d)) * 0.5).tocsr()
    expected.sort_indices()
    for name in ("indptr", "indices", "data"):
        np.testing.assert_array_equal(getattr(ours, name), getattr(expected, name))
    # overwritten: J lives in Q's arrays (on the sparse path Q is left alone)
    shares = np.shares_memory(ours.data, q.data)
    assert shares == (overwrite and not isolated)
    if not shares:
        np.testing.assert_array_equal(q.data, original.data)
