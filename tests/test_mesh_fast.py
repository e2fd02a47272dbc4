"""The fast meshing paths give the same answers as the direct ones."""

from __future__ import annotations

import mcubes
import numpy as np
import pytest
import torch

from ultron.mesh import (
    evaluate_coarse_to_fine,
    evaluate_on_grid,
    extract_surface,
    smooth_constrained,
)
from ultron.mesh.smoothing import second_difference_system

CENTER = torch.tensor([1.0, -2.0, 0.5])


def two_blobs(points: torch.Tensor) -> torch.Tensor:
    """Smooth occupancy: a 6 mm ball and a thin 1.2 mm-thick plate."""
    ball = torch.sigmoid(4 * (6.0 - (points - CENTER).norm(dim=-1)))
    plate = torch.sigmoid(4 * (0.6 - (points[:, 2] - 8.0).abs())) * (points[:, 0].abs() < 7)
    return torch.maximum(ball, plate)


@pytest.mark.parametrize(("max_iters", "rel_tol"), [(500, 1e-6), (0, 1e-6), (7, 1e-6), (30, 0.0)])
def test_constrained_smoothing_equals_pymcubes(max_iters, rel_tol):
    """Converged (the energy check stops it), no step, stopped by max_iters between two energy
    checks and on one (rel_tol 0: never converged)."""
    rng = np.random.default_rng(3)
    ijk = np.mgrid[:26, :24, :22]
    binary = ((ijk[0] - 13) ** 2 / 60 + (ijk[1] - 11) ** 2 / 30 + (ijk[2] - 10) ** 2 / 25 < 1) | (
        rng.random((26, 24, 22)) < 0.01
    )
    ours = smooth_constrained(binary, max_iters=max_iters, rel_tol=rel_tol)
    theirs = mcubes.smooth_constrained(binary, max_iters=max_iters, rel_tol=rel_tol)
    np.testing.assert_allclose(ours, theirs, atol=1e-9)


def test_second_difference_system_is_neumann_laplacian_squared():
    band = np.zeros((5, 1, 1), dtype=bool)
    band[1:4] = True  # a 3-voxel line: D = [[-1, 1, 0], [1, -2, 1], [0, 1, -1]] along x
    q = second_difference_system(band).toarray()
    d = np.array([[-1.0, 1, 0], [1, -2, 1], [0, 1, -1]])
    # along y and z every voxel lacks both neighbours: rows of zeros
    np.testing.assert_allclose(q, d.T @ d)


def test_smoothing_rejects_bad_arguments():
    with pytest.raises(ValueError, match="binary"):
        smooth_constrained(np.zeros((4, 4), dtype=bool))
    with pytest.raises(ValueError, match="band_radius"):
        smooth_constrained(np.zeros((4, 4, 4), dtype=bool), band_radius=0)


@pytest.mark.parametrize("factor", [2, 3])
def test_coarse_to_fine_keeps_the_binarised_volume(grid, factor):
    exact = evaluate_on_grid(two_blobs, grid, chunk_points=50_000)
    calls = []

    def counted(points):
        calls.append(len(points))
        return two_blobs(points)

    fast = evaluate_coarse_to_fine(counted, grid, 0.5, factor=factor, chunk_points=50_000)
    assert fast.shape == grid.shape
    assert np.array_equal(fast >= 0.5, exact >= 0.5)
    assert sum(calls) < 0.6 * grid.n_voxels  # most voxels were interpolated, not evaluated


def test_coarse_to_fine_respects_the_coarse_mask(grid):
    coarse = grid.coarsened(2)
    mask = np.ones(coarse.shape, dtype=bool)
    mask[: coarse.shape[0] // 2] = False
    fast = evaluate_coarse_to_fine(two_blobs, grid, 0.5, factor=2, coarse_mask=mask)
    # fine voxels whose nearest coarse node is masked out are empty
    cut = (coarse.shape[0] // 2) * 2 - 1
    assert fast[:cut].max() < 0.5
    assert (fast[cut + 2 :] >= 0.5).any()
    with pytest.raises(ValueError, match="coarse_mask"):
        evaluate_coarse_to_fine(two_blobs, grid, 0.5, factor=2, coarse_mask=mask[1:])


def test_coarsened_grid_nodes_are_fine_voxels(grid):
    coarse = grid.coarsened(3)
    np.testing.assert_allclose(
        coarse.index_to_world([[2, 1, 4]]), grid.index_to_world([[6, 3, 12]])
    )
    assert all((c - 1) * 3 >= n - 1 for c, n in zip(coarse.shape, grid.shape, strict=True))
    with pytest.raises(ValueError, match="factor"):
        grid.coarsened(0)


def test_speckle_components_dropped_before_smoothing(grid):
    volume = evaluate_on_grid(two_blobs, grid)
    rng = np.random.default_rng(0)
    speckle = rng.random(grid.shape) < 0.002
    clean = extract_surface(volume, grid)
    noisy = extract_surface(np.maximum(volume, speckle.astype(np.float32)), grid)
    assert abs(noisy.area - clean.area) / clean.area < 0.02
