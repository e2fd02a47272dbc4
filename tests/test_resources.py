"""Outlier poses and the grids' memory, estimated before anything is allocated."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ultron.data.dataset import ProbeGeometry, SweepDataset
from ultron.data.labels import gather_labelled_pixels, select_label_frames
from ultron.data.outliers import (
    OUTLIER_FLOOR_MM,
    check_pose_array_outliers,
    check_pose_outliers,
    pose_array_outliers,
    pose_outliers,
)
from ultron.errors import UltronInputError
from ultron.mesh.compounding import CompoundingConfig, compound_labels
from ultron.mesh.label_fusion import DENSE_FRAME_SHARE, LabelFusionConfig
from ultron.mesh.occupancy_mesh import scan_grid
from ultron.methods.registry import get_method
from ultron.methods.ultron_method import UltronConfig
from ultron.pipeline.resources import (
    COMPOUNDING_BYTES_PER_PIXEL,
    COMPOUNDING_BYTES_PER_VOXEL,
    COMPOUNDING_MESH_BYTES_PER_VOXEL,
    FIELD_BYTES_PER_VALUE,
    FIELD_FIXED_BYTES,
    FIELD_RENDER_BYTES_PER_SAMPLE,
    FIELD_TRAIN_BYTES_PER_SAMPLE,
    MESH_FIXED_BYTES,
    check_compounding_grid,
    check_field_grid,
    check_meshing_grid,
    check_run_resources,
    compounding_memory,
    field_fit_memory,
    memory_limit,
    meshing_grid_shape,
)
from ultron.train.field_config import FieldTrainConfig


def _moved(dataset: SweepDataset, sweep: int, frame: int, offset_mm: float) -> SweepDataset:
    poses = dataset.sweeps[sweep].probe_to_world.copy()
    poses[frame, :3, 3] += offset_mm
    sweeps = list(dataset.sweeps)
    sweeps[sweep] = replace(sweeps[sweep], probe_to_world=poses)
    return replace(dataset, sweeps=sweeps)


def _probe(dataset: SweepDataset, width_mm: float) -> SweepDataset:
    probe = dataset.probe
    return replace(
        dataset, probe=ProbeGeometry(width_mm, probe.depth_mm, probe.height_px, probe.width_px)
    )


def test_outlier_poses(tiny_dataset: SweepDataset):
    assert pose_outliers(tiny_dataset) == []
    check_pose_outliers(tiny_dataset)
    # 20 mm off stays within 10 × the median distance + 50 mm; 1e6 mm does not
    assert pose_outliers(_moved(tiny_dataset, 1, 2, 20.0)) == []
    moved = _moved(tiny_dataset, 1, 2, 1e6)
    (outlier,) = pose_outliers(moved)
    assert (outlier.sweep, outlier.frame) == ("column", 2)
    assert outlier.distance_mm > 1e6 and outlier.threshold_mm >= OUTLIER_FLOOR_MM
    with pytest.raises(UltronInputError, match=r"^ds/column/poses.npy: poses: sweep column, fr"):
        check_pose_outliers(moved, "ds")
    twice = _moved(moved, 0, 0, -1e6)
    with pytest.raises(
        UltronInputError, match=r"sweep row, frame 0: .*\(2 outlier frames in all\)"
    ):
        check_run_resources(twice, "ds", mesh=False)


def test_outlier_poses_of_a_poses_file(tiny_dataset: SweepDataset):
    poses = tiny_dataset.all_poses().copy()
    assert pose_array_outliers(poses) == [] and pose_array_outliers(poses[:1]) == []
    check_pose_array_outliers(poses, "p.npy")
    poses[5, :3, 3] += 1e6
    (outlier,) = pose_array_outliers(poses)
    assert (outlier.sweep, outlier.frame) == ("", 5)
    with pytest.raises(UltronInputError, match=r"^p.npy: poses: frame 5: pose translation \(1e"):
        check_pose_array_outliers(poses, "p.npy")


def test_meshing_grid_estimate_is_scan_grids_shape(tiny_dataset: SweepDataset):
    for voxel in (None, 0.7):
        shape, _, _ = meshing_grid_shape(tiny_dataset, voxel)
        assert shape == scan_grid(tiny_dataset, voxel).shape
    check_meshing_grid(tiny_dataset, "ds", None, None)


def test_meshing_grid_too_large(tiny_dataset: SweepDataset):
    with pytest.raises(UltronInputError, match=r"^argument: voxel_mm: .*--max-memory 1e-06 GiB"):
        check_meshing_grid(tiny_dataset, "ds", 0.5, 1e-6)
    with pytest.raises(UltronInputError, match=r"^ds/dataset.json: probe: the meshing grid"):
        check_meshing_grid(tiny_dataset, "ds", None, 1e-6)  # the default voxel, named "probe"
    # a given voxel whose ratio overflows a float is sized without allocating and refused
    with pytest.raises(UltronInputError, match="meshing grid"):
        check_meshing_grid(tiny_dataset, "ds", 1e-300, None)


def test_compounding_estimate_is_compound_labels_grid(tiny_dataset: SweepDataset, monkeypatch):
    """Compounding's estimate sizes the grid compound_labels builds (the labelled bone's box,
    not the field of view) and the labelled pixels splatted at once (all of them, or a run of
    frames of at most CHUNK_PIXELS image pixels, one frame at least); a limit under it is
    refused with one line naming the dataset, the grid and the pixels, one above it passes."""
    import ultron.pipeline.resources as resources

    selection = select_label_frames(tiny_dataset, 1.0, 0)
    frame_pixels = tiny_dataset.probe.height_px * tiny_dataset.probe.width_px
    for chunk in (10**9, 1):  # every pixel in one run; a frame at a time
        monkeypatch.setattr(resources, "CHUNK_PIXELS", chunk)
        for config in (CompoundingConfig(), CompoundingConfig(voxel_mm=0.9, margin_mm=2.0)):
            total, grid, n_pixels = compounding_memory(tiny_dataset, selection, config)
            built = compound_labels(tiny_dataset, selection, config).grid
            assert grid.shape == built.shape and grid.voxel_mm == built.voxel_mm
            np.testing.assert_array_equal(grid.origin_mm, built.origin_mm)
            gathered = gather_labelled_pixels(
                tiny_dataset, selection, outer_side_mm=config.outer_side_mm
            )
            assert n_pixels == len(gathered)  # what compound_labels splats
            assert n_pixels > frame_pixels  # so the two runs' estimates differ
            at_once = n_pixels if chunk > n_pixels else frame_pixels
            voxels = math.prod(grid.shape)
            assert (
                total
                == max(
                    at_once * COMPOUNDING_BYTES_PER_PIXEL + voxels * COMPOUNDING_BYTES_PER_VOXEL,
                    voxels * COMPOUNDING_MESH_BYTES_PER_VOXEL,
                )
                + MESH_FIXED_BYTES
            )
    gib = total / 1024**3
    check_compounding_grid(tiny_dataset, selection, config, "ds", 1.01 * gib)
    pattern = (
        r"^ds/dataset.json: labels: compounding's meshing grid has .* voxels \(.* of 0.9 mm over"
        r" the labelled bone's box\) and .* labelled pixels: .*, more than --max-memory"
    )
    with pytest.raises(UltronInputError, match=pattern):
        check_compounding_grid(tiny_dataset, selection, config, "ds", 0.99 * gib)
    # the run refuses before any work, without the field of view's (larger) estimate
    assert not get_method("compounding").scan_grid
    # UltrON fusing the labels builds the same grid, and checks it the same way where the
    # fusion applies; not without fusion, nor by default where 5 of 7 frames are labelled
    ultron = get_method("ultron")
    fused = UltronConfig(label_fusion=LabelFusionConfig(min_frame_share=0.0, volume=config))
    assert selection.n_frames < DENSE_FRAME_SHARE * tiny_dataset.n_frames
    for unfused in (
        UltronConfig(label_fusion=None),
        UltronConfig(label_fusion=replace(fused.label_fusion, min_frame_share=DENSE_FRAME_SHARE)),
    ):
        ultron.check_resources(tiny_dataset, unfused, selection, "ds", 1e-6 * gib)
    ultron.check_resources(tiny_dataset, fused, selection, "ds", 1.01 * gib)
    with pytest.raises(UltronInputError, match=pattern):
        ultron.check_resources(tiny_dataset, fused, selection, "ds", 0.99 * gib)


def test_tiny_pixels_get_a_voxel_from_the_region_not_a_petabyte_grid(tiny_dataset: SweepDataset):
    """0.17 µm pixels once asked for petabytes (a grid at the pixel spacing over the field of
    view); the voxel now follows the region's volume (:data:`MAX_REGION_VOXELS`)."""
    from ultron.mesh.grid import MAX_REGION_VOXELS

    small = _probe(tiny_dataset, 1e-3)
    shape, voxel, _ = meshing_grid_shape(small, None)
    assert voxel > 100 * small.probe.lateral_spacing_mm
    assert math.prod(shape) < 100 * MAX_REGION_VOXELS
    check_meshing_grid(small, "ds", None, None)
    # refused under a small limit, the message says the voxel grew from the pixel spacing
    with pytest.raises(UltronInputError, match=rf"of {voxel:.3g} mm .*, grown to {voxel:.3g} mm"):
        check_meshing_grid(small, "ds", None, 1e-6)


def test_absurd_pixel_aspect_is_refused(tiny_dataset: SweepDataset):
    from ultron.pipeline.resources import MAX_PIXEL_ASPECT, check_probe_aspect

    check_probe_aspect(tiny_dataset, "ds")
    probe = tiny_dataset.probe
    ratio = probe.axial_spacing_mm / probe.lateral_spacing_mm
    ok = _probe(tiny_dataset, probe.width_mm * ratio / (0.99 * MAX_PIXEL_ASPECT))
    check_probe_aspect(ok, "ds")  # just under the limit
    for width in (1e-3, 1e-300, 1e6):
        with pytest.raises(UltronInputError, match=r"^ds/dataset.json: probe: its pixels are"):
            check_probe_aspect(_probe(tiny_dataset, width), "ds")


def test_field_grid(tiny_dataset: SweepDataset):
    config = FieldTrainConfig()
    check_field_grid(tiny_dataset, Path("ds"), config, None)
    small = _probe(tiny_dataset, 1e-3)
    with pytest.raises(UltronInputError, match=r"dataset.json: probe: acoustic field: .*nodes"):
        check_field_grid(small, "ds", config, None)
    with pytest.raises(UltronInputError, match=r"planes of \[\d+, \d+\] nodes .*--max-memory"):
        check_field_grid(tiny_dataset, "ds", config, 1e-9)
    mlp = replace(config, field=replace(config.field, backend="mlp"))
    check_field_grid(small, "ds", mlp, None)  # no grid to size


def test_field_fit_memory_estimate(tiny_dataset: SweepDataset):
    """Planes, frames and working memory from the shapes alone (module doc 3)."""
    default = FieldTrainConfig(fit_shape=(16, 12), frames_per_batch=4, patch_width=8)
    assert field_fit_memory(tiny_dataset, default).volume  # a long box: the default volume
    config = default.with_volume(0)  # the planes alone
    memory = field_fit_memory(tiny_dataset, config)
    # the planes the fit builds (per-axis here: the tiny dataset's box is far from a cube)
    from ultron.train.field_fit import _prepare

    _, _, module, resolved = _prepare(tiny_dataset, config)
    values = sum(p.numel() for p in module.planes.parameters())
    assert memory.planes == values * FIELD_BYTES_PER_VALUE
    assert not memory.volume and module.volume is None
    with_volume = config.with_volume(2.0)
    memory_volume = field_fit_memory(tiny_dataset, with_volume)
    _, _, module, resolved = _prepare(tiny_dataset, with_volume)
    assert memory_volume.volume and module.volume.numel() == 4 * math.prod(
        resolved.grid.volume_nodes
    )
    assert memory_volume.planes == (values + module.volume.numel()) * FIELD_BYTES_PER_VALUE
    assert "and volume" in memory_volume.describe() and "and volume" not in memory.describe()
    assert resolved.grid.axis_extent is not None and memory.resolutions == resolved.grid.resolutions
    (fine, coarse) = memory.resolutions
    assert values < 3 * (8 * fine**2 + 4 * coarse**2) / 2  # less than half the square planes
    # 7 frames of 16 × 12 with their confidence maps, the 4-frame sweep's 8 × 6 copies
    assert memory.frames == 4 * (7 * 16 * 12 * 2 + 2 * 4 * 8 * 6)
    train = 4 * 8 * 16 * FIELD_TRAIN_BYTES_PER_SAMPLE["grid"]
    render = 8 * 16 * 12 * FIELD_RENDER_BYTES_PER_SAMPLE["grid"]
    assert memory.working == max(train, render)
    assert memory.total == memory.planes + memory.frames + memory.working + FIELD_FIXED_BYTES
    mlp = replace(config, field=replace(config.field, backend="mlp"), confidence_prior_weight=0)
    memory = field_fit_memory(tiny_dataset, mlp)
    assert memory.planes == 0 and memory.resolutions == ()
    assert memory.working == 4 * 8 * 16 * FIELD_TRAIN_BYTES_PER_SAMPLE["mlp"]
    assert memory.frames == 4 * (7 * 16 * 12 + 2 * 4 * 8 * 6)  # no confidence maps
    pattern = r"fitting it needs ≈ .* \(frames .*, working memory .*\), more than --max-memory"
    with pytest.raises(UltronInputError, match=rf"^ds/dataset.json: probe: .*{pattern}"):
        check_field_grid(tiny_dataset, "ds", mlp, 1e-9)


def test_fit_frames_below_the_ssim_window(tiny_dataset: SweepDataset):
    with pytest.raises(UltronInputError, match=r"^ds/dataset.json: probe: frames of 8 × 6 px"):
        check_run_resources(tiny_dataset, "ds", mesh=False, field_config=FieldTrainConfig())
    check_run_resources(
        tiny_dataset, "ds", mesh=False, field_config=FieldTrainConfig(fit_shape=(8, 7))
    )
    with pytest.raises(UltronInputError, match="patch_width"):
        FieldTrainConfig(patch_width=6)

    limit, name = memory_limit(None)
    assert limit > 2**28 and "machine" in name
    assert memory_limit(2.0) == (2.0 * 1024**3, "--max-memory 2 GiB")
    assert np.isfinite(limit)
