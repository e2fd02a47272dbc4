"""B-mode image compounding (``ultron compound``): splatting, hole filling, the NIfTI affine,
a synthetic round trip, and bad input."""

from __future__ import annotations

import os
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import torch
from scipy import ndimage
from typer.testing import CliRunner

from conftest import make_pose, rotation_z
from ultron.cli.main import app
from ultron.data.dataset import ProbeGeometry, Sweep, SweepDataset
from ultron.data.geometry import frame_pixels_world
from ultron.errors import UltronInputError
from ultron.mesh.grid import GridSpec
from ultron.mesh.holes import (
    STICK_DIRECTIONS,
    fill_holes_nearest,
    fill_holes_stick,
    filled_box,
    nearest_back,
)
from ultron.mesh.image_compounding import (
    ImageCompoundingConfig,
    compound_images,
    compounding_grid,
)
from ultron.mesh.splat import SplatConfig, Splatter

runner = CliRunner()
LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


def tiny_grid(shape=(4, 3, 3)) -> GridSpec:
    """Voxel (i, j, k) at (i, j, k) mm."""
    return GridSpec((0.0, 0.0, 0.0), 1.0, shape)


def splat(points, values, interpolation: str, reduce: str, shape=(4, 3, 3)):
    splatter = Splatter(tiny_grid(shape), SplatConfig(interpolation, reduce))
    splatter.add(np.asarray(points, dtype=np.float64), np.asarray(values, dtype=np.float32))
    return splatter.result()


# --------------------------------------------------------------------------- splatting by hand
def test_nearest_mean_and_max():
    # two samples round to voxel (1, 1, 1), one to (2, 1, 1); one lies outside the grid
    points = [[1.2, 0.9, 1.0], [0.6, 1.4, 1.3], [2.4, 1.0, 1.0], [9.0, 1.0, 1.0]]
    values = [10.0, 30.0, 7.0, 99.0]
    volume, filled = splat(points, values, "nearest", "mean")
    assert volume[1, 1, 1] == pytest.approx(20.0) and volume[2, 1, 1] == pytest.approx(7.0)
    assert filled.sum() == 2 and volume[~filled].max() == 0.0
    volume, filled = splat(points, values, "nearest", "max")
    assert volume[1, 1, 1] == 30.0 and volume[2, 1, 1] == 7.0 and filled.sum() == 2


def test_linear_mean_weights():
    # a sample at x = 1.25 gives voxel 1 weight 0.75 and voxel 2 weight 0.25 (y, z on nodes);
    # a second one at x = 2 gives voxel 2 weight 1
    volume, filled = splat([[1.25, 1.0, 1.0], [2.0, 1.0, 1.0]], [8.0, 4.0], "linear", "mean")
    assert volume[1, 1, 1] == pytest.approx(8.0)
    assert volume[2, 1, 1] == pytest.approx((0.25 * 8 + 1.0 * 4) / 1.25)
    assert filled.sum() == 2
    # a sample at a cell's centre reaches its 8 corners with weight 1/8 each
    volume, filled = splat([[1.5, 0.5, 0.5]], [16.0], "linear", "mean")
    assert filled.sum() == 8 and np.allclose(volume[filled], 16.0)


def test_linear_max_uses_corners_of_weight_at_least_one_eighth():
    # x = 1.1, y = 1.5: corners at x = 2 have weight 0.1·0.5 = 0.05 < 1/8 and are skipped
    volume, filled = splat([[1.1, 1.5, 1.0], [1.0, 1.0, 1.0]], [50.0, 20.0], "linear", "max")
    assert filled[1, 1, 1] and filled[1, 2, 1] and not filled[2, 1, 1] and not filled[2, 2, 1]
    assert volume[1, 1, 1] == 50.0 and volume[1, 2, 1] == 50.0
    assert filled.sum() == 2


def test_stick_hole_filling_by_hand():
    volume = np.zeros((7, 3, 3), np.float32)
    filled = np.zeros(volume.shape, bool)
    volume[0], volume[4] = 10.0, 50.0
    filled[0] = filled[4] = True
    out, new = fill_holes_stick(volume, filled, 9)
    # the x stick is the shortest: linear interpolation between the two planes
    assert np.allclose(out[:5, 1, 1], [10, 20, 30, 40, 50])
    assert new[1:4].all() and not new[5:].any()  # beyond x = 4 no second end
    # PLUS's own weights lean towards the +x end: ((r + 1)·v₊ + f·v₋) / (f + r + 1)
    plus, _ = fill_holes_stick(volume, filled, 9, plus_weights=True)
    assert plus[1, 1, 1] == pytest.approx((2 * 50 + 3 * 10) / 5)
    # a stick of exactly the limit fills, its middle voxel 2 steps from either end included
    out, new = fill_holes_stick(volume, filled, 5)
    assert new[1:4].all() and np.allclose(out[:5, 1, 1], [10, 20, 30, 40, 50])
    # a stick of 5 voxels (4 steps + 1) is longer than a limit of 4: nothing filled
    out, new = fill_holes_stick(volume, filled, 4)
    assert not new.any() and np.array_equal(out, volume)


def test_a_stick_limit_beyond_the_volume_fills_as_the_volume_allows():
    """No stick is longer than the volume, so any larger limit fills the same (and costs no
    more: the reach is the volume's, not the limit's)."""
    volume = np.zeros((7, 3, 3), np.float32)
    filled = np.zeros(volume.shape, bool)
    volume[0], volume[6] = 10.0, 70.0
    filled[0] = filled[6] = True
    out, new = fill_holes_stick(volume, filled, 9)
    for huge in (10**4, 10**9):
        other, other_new = fill_holes_stick(volume, filled, huge)
        assert np.array_equal(other, out) and np.array_equal(other_new, new)
    assert np.allclose(out[:, 1, 1], [10, 20, 30, 40, 50, 60, 70])


def test_stick_ties_are_averaged():
    # hole at the centre of a 3×3×3 cube: x stick ends 10 | 30, y stick ends 0 | 100
    volume = np.zeros((3, 3, 3), np.float32)
    filled = np.zeros(volume.shape, bool)
    for index, value in (((0, 1, 1), 10), ((2, 1, 1), 30), ((1, 0, 1), 0), ((1, 2, 1), 100)):
        volume[index], filled[index] = value, True
    out, new = fill_holes_stick(volume, filled, 3)
    assert new[1, 1, 1] and out[1, 1, 1] == pytest.approx((20 + 50) / 2)


def _stick_fill_by_walking(volume, filled, length):
    """The stick filler as PLUS states it: from every hole walk each of the 13 directions both
    ways to the first filled voxel; the shortest usable stick (ties averaged) interpolates."""
    out, new = volume.astype(np.float64).copy(), np.zeros(volume.shape, bool)
    for v in zip(*np.nonzero(~filled), strict=True):
        found = []
        for d in STICK_DIRECTIONS:
            ends = []
            for sign in (1, -1):
                for j in range(1, length):
                    p = tuple(c + sign * j * s for c, s in zip(v, d, strict=True))
                    if not all(0 <= c < n for c, n in zip(p, volume.shape, strict=True)):
                        break
                    if filled[p]:
                        ends.append((j, float(volume[p])))
                        break
            if len(ends) == 2 and ends[0][0] + ends[1][0] + 1 <= length:
                (f, ahead), (r, behind) = ends
                found.append(
                    ((f + r + 1) * np.sqrt(np.dot(d, d)), (r * ahead + f * behind) / (f + r))
                )
        if found:
            shortest = min(s for s, _ in found)
            tied = [value for s, value in found if np.isclose(s, shortest, rtol=1e-6)]
            out[v], new[v] = np.mean(tied), True
    return out, new


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_stick_hole_filling_equals_walking_every_stick(seed):
    rng = np.random.default_rng(seed)
    shape = tuple(int(n) for n in rng.integers(5, 11, size=3))
    filled = rng.random(shape) < 0.08
    volume = np.where(filled, rng.random(shape) * 100, 0).astype(np.float32)
    length = int(rng.integers(3, 9))
    previous = torch.get_num_threads()
    try:  # the directions swept one at a time, then one per core on threads: the same volume
        torch.set_num_threads(1)
        out, new = fill_holes_stick(volume, filled, length)
        torch.set_num_threads(3)
        out_threads, new_threads = fill_holes_stick(volume, filled, length)
    finally:
        torch.set_num_threads(previous)
    assert np.array_equal(out, out_threads) and np.array_equal(new, new_threads)
    expected, expected_new = _stick_fill_by_walking(volume, filled, length)
    assert new.any() and np.array_equal(new, expected_new)
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-4)


def test_nearest_back_writes_into_reused_buffers():
    """A sweep into buffers left dirty by another direction equals one into fresh memory (the
    stick filler reuses them); buffers of another size or type are refused by name."""
    rng = np.random.default_rng(3)
    filled = rng.random((6, 7, 5)) < 0.2
    volume = np.where(filled, rng.random(filled.shape) * 10, 0).astype(np.float32)
    buffers = [np.full(volume.size, 7.0, dtype=np.float32) for _ in range(2)]
    for direction in ((1, -1, 0), (0, 0, 1), (-1, 1, 1)):
        fresh = nearest_back(volume, filled, direction)
        reused = nearest_back(volume, filled, direction, buffers)
        for a, b in zip(fresh, reused, strict=True):
            assert np.array_equal(a, b) and np.shares_memory(b, buffers[0]) != np.shares_memory(
                b, buffers[1]
            )
    with pytest.raises(UltronInputError, match="out"):
        nearest_back(volume, filled, (1, 0, 0), [np.zeros(volume.size, np.float64)] * 2)
    with pytest.raises(UltronInputError, match="out"):
        nearest_back(volume, filled, (1, 0, 0), [np.zeros(3, np.float32)] * 2)


@pytest.mark.parametrize("seed", [0, 1])
def test_hole_fillers_work_on_the_filled_box_alone(seed):
    # filled voxels in one corner region of a larger volume: the fillers crop to their box
    # (and the nearest filler's distance around it); the result is the whole volume's
    rng = np.random.default_rng(seed)
    shape = (13, 11, 12)
    filled = np.zeros(shape, bool)
    filled[2:7, 3:8, 1:6] = rng.random((5, 5, 5)) < 0.15
    volume = np.where(filled, rng.random(shape) * 100, 0).astype(np.float32)
    assert filled_box(filled, 0) == tuple(
        slice(int(i.min()), int(i.max()) + 1) for i in np.nonzero(filled)
    )
    out, new = fill_holes_stick(volume, filled, 5)
    expected, expected_new = _stick_fill_by_walking(volume, filled, 5)
    assert new.any() and np.array_equal(new, expected_new)
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-4)
    distance, nearest = ndimage.distance_transform_edt(~filled, return_indices=True)
    # the exact boundary (√k), as float64 rounds it, and beyond any distance in the grid
    for radius in (0.0, 1.0, 1.5, np.sqrt(2), 2.0, np.sqrt(5), 2.9, np.sqrt(13), 1e200):
        out, new = fill_holes_nearest(volume, filled, radius)
        assert np.array_equal(new, ~filled & (distance <= radius))
        assert np.array_equal(out[new], volume[tuple(axis[new] for axis in nearest)])
        assert np.array_equal(out[~new], volume[~new])
    assert filled_box(np.zeros(shape, bool), 2) is None
    out, new = fill_holes_stick(volume, np.zeros(shape, bool), 5)
    assert not new.any() and np.array_equal(out, volume)


def test_nearest_hole_filling():
    volume = np.zeros((6, 1, 1), np.float32)
    filled = np.zeros(volume.shape, bool)
    volume[0], filled[0] = 5.0, True
    out, new = fill_holes_nearest(volume, filled, 2.0)
    assert new[1:3, 0, 0].all() and not new[3:].any() and np.allclose(out[:3, 0, 0], 5.0)


# --------------------------------------------------------------------------- datasets
def one_frame_dataset(pose: np.ndarray, image: np.ndarray, spacing: float = 0.5) -> SweepDataset:
    h, w = image.shape
    probe = ProbeGeometry(width_mm=w * spacing, depth_mm=h * spacing, height_px=h, width_px=w)
    return SweepDataset(probe, [Sweep("row", "row", image[None], pose[None])])


def sweep_dataset(seed: int) -> tuple[SweepDataset, np.ndarray]:
    """Six rotated, shifted frames of dim speckle; one bright pixel; its world point."""
    rng = np.random.default_rng(seed)
    probe = ProbeGeometry(width_mm=8.0, depth_mm=6.0, height_px=24, width_px=32)
    images = rng.integers(0, 40, size=(6, 24, 32), dtype=np.uint8)
    poses = np.stack([make_pose(rotation_z(3.0 * i), (0.3, 1.0, 0.9 * i)) for i in range(6)])
    images[3, 11, 19] = 255
    world = frame_pixels_world(torch.as_tensor(poses), probe).numpy()[3, 11, 19]
    return SweepDataset(probe, [Sweep("row", "row", images, poses)]), world


# --------------------------------------------------------------------------- geometry
def test_nifti_affine_maps_voxels_to_the_pixels_world_points(tmp_path: Path):
    # a rotated frame whose pixel spacing equals the voxel: every pixel lands on a voxel centre;
    # every pixel has its own grey level, so the voxel holding it is found by value
    image = (np.arange(20).reshape(5, 4) * 12 + 3).astype(np.uint8)
    pose = make_pose(rotation_z(90.0), (12.0, -3.0, 7.5))
    dataset = one_frame_dataset(pose, image)
    dataset.save(tmp_path / "d")
    out = tmp_path / "v.nii.gz"
    args = ["compound", str(tmp_path / "d"), "--spacing", "0.5", "--out", str(out)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    loaded = nib.load(out)
    data = np.asarray(loaded.dataobj)
    world = frame_pixels_world(torch.as_tensor(pose[None]), dataset.probe)[0].numpy()
    for (r, c), value in np.ndenumerate(image):
        (ijk,) = np.argwhere(data == value)
        ras = loaded.affine @ np.append(ijk, 1.0)
        assert np.allclose((LPS_TO_RAS @ ras)[:3], world[r, c], atol=1e-6)
    assert (data > 0).sum() == image.size


def test_grid_origin_is_the_lowest_pixel_corner():
    dataset, _ = sweep_dataset(0)
    grid = compounding_grid(dataset, dataset.sweeps, 0.5)
    poses = torch.as_tensor(dataset.sweeps[0].probe_to_world)
    points = frame_pixels_world(poses, dataset.probe).reshape(-1, 3).numpy()
    assert np.allclose(grid.origin_mm, points.min(axis=0))
    assert (grid.index_to_world(np.asarray(grid.shape) - 1) >= points.max(axis=0) - 1e-9).all()


@pytest.mark.parametrize("interpolation", ["nearest", "linear"])
def test_bright_pixel_lands_in_the_brightest_voxel(tmp_path: Path, interpolation: str):
    dataset, bright = sweep_dataset(1)
    dataset.save(tmp_path / "d")
    out = tmp_path / "v.nii"
    args = ["compound", str(tmp_path / "d"), "--spacing", "0.5", "--interpolation", interpolation,
            "--fill-holes", "5", "--out", str(out)]  # fmt: skip
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    loaded = nib.load(out)
    data = np.asarray(loaded.dataobj)
    ijk = np.unravel_index(np.argmax(data), data.shape)
    centre = (LPS_TO_RAS @ loaded.affine @ np.append(ijk, 1.0))[:3]
    assert np.all(np.abs(centre - bright) <= 0.25 + 1e-9)  # the voxel containing the pixel


def test_max_compounding_and_sweep_choice():
    dataset, _ = sweep_dataset(2)
    config = ImageCompoundingConfig(0.5, SplatConfig("nearest", "max"))
    result = compound_images(dataset, config, ["row"])
    assert result.volume.max() == 255.0
    with pytest.raises(UltronInputError, match="--sweeps"):
        compound_images(dataset, config, ["column"])


def test_frames_are_processed_in_chunks():
    dataset, _ = sweep_dataset(4)
    whole = compound_images(dataset, ImageCompoundingConfig(0.5, SplatConfig("linear", "mean")))
    chunked = compound_images(
        dataset, ImageCompoundingConfig(0.5, SplatConfig("linear", "mean"), chunk_pixels=1)
    )
    assert np.allclose(whole.volume, chunked.volume, atol=1e-4)
    assert np.array_equal(whole.filled, chunked.filled)


def test_progress_counts_frames_in_order_and_the_log_names_each_stage(tmp_path: Path):
    from ultron.pipeline.compound import compound_volume

    dataset, _ = sweep_dataset(4)
    dataset.save(tmp_path / "d")
    events: list[tuple[str, int, int]] = []
    config = ImageCompoundingConfig(0.5, fill_holes=3, chunk_pixels=1)  # a frame at a time
    compound_volume(
        tmp_path / "d", tmp_path / "v.nii.gz", config, progress=lambda *e: events.append(e)
    )
    n = dataset.sweeps[0].n_frames
    assert events == [("splatting", k, n) for k in range(n + 1)] + [
        ("filling holes", 0, 1),
        ("writing", 0, 1),
    ]
    result = runner.invoke(app, ["compound", str(tmp_path / "d"), "--out", str(tmp_path / "w.nii")])
    assert result.exit_code == 0, result.output
    lines = result.stdout.splitlines()  # off a terminal: a line as each stage starts
    assert lines[:2] == ["compound splatting …", "compound writing …"], lines


# --------------------------------------------------------------------------- bad input
def snapshot(root: Path) -> dict[str, object]:
    entries: dict[str, object] = {}
    for folder, dirs, files in os.walk(root):
        for name in dirs + files:
            path = Path(folder) / name
            entries[str(path.relative_to(root))] = "dir" if path.is_dir() else path.read_bytes()
    return entries


def _compound(*extra: str):
    def build(tmp: Path, data: Path) -> list[str]:
        return ["compound", str(data), "--out", str(tmp / "v.nii.gz"), *extra]

    return build


def _out_suffix(tmp: Path, data: Path) -> list[str]:
    return ["compound", str(data), "--out", str(tmp / "v.txt")]


def _no_frames(tmp: Path, data: Path) -> list[str]:
    np.save(data / "row" / "images.npy", np.zeros((0, 8, 6), np.uint8))
    return ["compound", str(data), "--out", str(tmp / "v.nii.gz")]


def _out_below_file(tmp: Path, data: Path) -> list[str]:
    (tmp / "file").write_text("x")
    return ["compound", str(data), "--out", str(tmp / "file" / "v.nii.gz")]


def _out_directory(tmp: Path, data: Path) -> list[str]:
    (tmp / "vol.nii.gz").mkdir()
    return ["compound", str(data), "--out", str(tmp / "vol.nii.gz")]


#: name → (build(tmp, dataset) → CLI arguments, hints the one error line must hold).
BAD_CASES = {
    "compound_spacing_zero": (_compound("--spacing", "0"), ("--spacing",)),
    "compound_spacing_negative": (_compound("--spacing", "-0.5"), ("--spacing",)),
    "compound_spacing_nan": (_compound("--spacing", "nan"), ("--spacing",)),
    "compound_spacing_tiny": (_compound("--spacing", "1e-6"), ("--spacing", "GiB")),
    "compound_over_max_memory": (
        _compound("--max-memory", "1e-6"),
        ("--spacing", "GiB", "more than --max-memory 1e-06 GiB"),
    ),
    "compound_max_memory_zero": (_compound("--max-memory", "0"), ("--max-memory",)),
    "compound_max_memory_nan": (_compound("--max-memory", "nan"), ("--max-memory",)),
    "compound_interpolation_cubic": (_compound("--interpolation", "cubic"), ("--interpolation",)),
    "compound_reduce_median": (_compound("--reduce", "median"), ("--reduce",)),
    "compound_fill_holes_two": (_compound("--fill-holes", "2"), ("--fill-holes",)),
    "compound_fill_holes_negative": (_compound("--fill-holes", "-1"), ("--fill-holes",)),
    "compound_unknown_sweep": (_compound("--sweeps", "row,nope"), ("--sweeps", "nope")),
    "compound_out_suffix": (_out_suffix, ("v.txt", "--out")),
    "compound_out_directory": (_out_directory, ("vol.nii.gz", "--out", "directory")),
    "compound_out_below_file": (_out_below_file, ("--out", "not a directory")),
    "compound_no_frames": (_no_frames, ("images.npy",)),
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_input_is_refused(case: str, tmp_path: Path, tiny_dataset_dir: Path):
    from test_bad_input_corpus import check_refused

    build, hints = BAD_CASES[case]
    args = build(tmp_path, tiny_dataset_dir)
    before = snapshot(tmp_path)
    check_refused(runner.invoke(app, args), hints)
    assert snapshot(tmp_path) == before


def test_unwritable_out_is_refused(tmp_path: Path, tiny_dataset_dir: Path, monkeypatch):
    import ultron.outputs
    from test_bad_input_corpus import check_refused

    locked = tmp_path / "locked"
    locked.mkdir()
    real_access = os.access
    monkeypatch.setattr(
        ultron.outputs.os, "access", lambda p, m: Path(p) != locked and real_access(p, m)
    )
    before = snapshot(tmp_path)
    args = ["compound", str(tiny_dataset_dir), "--out", str(locked / "v.nii.gz")]
    check_refused(runner.invoke(app, args), ("--out", "not writable"))
    assert snapshot(tmp_path) == before
