"""Label compounding baseline on an analytic sphere scanned by parallel frames."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ultron.data.dataset import ProbeGeometry, Sweep, SweepDataset
from ultron.data.geometry import frame_pixels_world
from ultron.data.labels import select_label_frames
from ultron.errors import UltronInputError
from ultron.mesh import extract_surface
from ultron.mesh.compounding import CompoundingConfig, compound_labels

RADIUS = 6.0
CENTER = np.array([0.0, 10.0, 0.0])


@pytest.fixture(scope="module")
def sphere_dataset() -> SweepDataset:
    """Frames in x–y planes stepping 0.5 mm in z, labelled 1 inside the sphere."""
    probe = ProbeGeometry(width_mm=20.0, depth_mm=20.0, height_px=50, width_px=50)
    z = np.arange(-8.0, 8.01, 0.5)
    poses = np.tile(np.eye(4), (len(z), 1, 1))
    poses[:, 2, 3] = z
    points = frame_pixels_world(torch.as_tensor(poses), probe).numpy()
    labels = (np.linalg.norm(points - CENTER, axis=-1) < RADIUS).astype(np.uint8)
    images = np.zeros(labels.shape, np.uint8)
    return SweepDataset(probe, [Sweep("row", "row", images, poses, labels)])


@pytest.mark.parametrize(
    "config",
    [CompoundingConfig(), CompoundingConfig(mode="max", interpolation="trilinear")],
    ids=["mean-nearest", "max-trilinear"],
)
def test_compounded_sphere_is_close(sphere_dataset, config):
    selection = select_label_frames(sphere_dataset, 1.0, seed=0)
    compounded = compound_labels(sphere_dataset, selection, config)
    mesh = extract_surface(compounded.volume, compounded.grid)
    radii = np.linalg.norm(mesh.vertices - CENTER, axis=1)
    assert abs(np.median(radii) - RADIUS) < 0.5
    assert abs(mesh.area - 4 * np.pi * RADIUS**2) / (4 * np.pi * RADIUS**2) < 0.1


def test_sparse_frames_are_filled_between(sphere_dataset):
    # every 4th frame (2 mm apart): the automatic radius (half the gap) closes the gaps
    selection = select_label_frames(sphere_dataset, 0.25, seed=0)
    compounded = compound_labels(sphere_dataset, selection)
    assert compounded.hole_fill_radius_mm == pytest.approx(1.0)
    i, j, _ = np.rint(compounded.grid.world_to_index(CENTER)).astype(int)
    column = compounded.volume[i, j, :]
    z = compounded.grid.origin_mm[2] + np.arange(len(column)) * compounded.grid.voxel_mm
    assert (column[np.abs(z) < RADIUS - 1.5] > 0.5).all()
    # without hole filling, the column through the centre has gaps between the frames
    unfilled = compound_labels(
        sphere_dataset, selection, CompoundingConfig(hole_fill_radius_mm=0.0)
    )
    assert (unfilled.volume[i, j, np.abs(z) < RADIUS - 1.5] < 0.5).any()


def test_bad_config():
    with pytest.raises(UltronInputError, match="mode"):
        CompoundingConfig(mode="median")
    with pytest.raises(UltronInputError, match="interpolation"):
        CompoundingConfig(interpolation="cubic")
