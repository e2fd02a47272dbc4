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
from ultron.mesh.compounding import CompoundedVolume, CompoundingConfig, compound_labels
from ultron.mesh.grid import GridSpec
from ultron.mesh.label_fusion import LabelFusionConfig, fuse_with_labels, labelled_frame_share

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
    with pytest.raises(UltronInputError, match="outer_side_mm"):
        CompoundingConfig(outer_side_mm=-0.5)


def test_label_signed_distance_by_hand():
    from ultron.mesh.compounding import label_signed_distance

    labels = np.zeros((8, 3), np.uint8)
    labels[3:5] = 1  # a band of two rows
    labels[7] = 255  # unannotated counts as not bone
    distance = label_signed_distance(labels, (0.5, 1.0), clip_mm=1.0)
    # rows 3–4 are bone: +0.5 mm to the nearest non-bone row; rows 2 and 5 are −0.5 mm, rows
    # 1 and 6 −1.0 mm, row 0 clipped at −1
    assert np.allclose(distance[:, 1], [-1.0, -1.0, -0.5, 0.5, 0.5, -0.5, -1.0, -1.0])
    assert np.all(label_signed_distance(np.zeros((2, 2), np.uint8), (1, 1), 2.0) == -2.0)


def test_pixel_values_take_each_pixel_from_its_own_frame():
    from ultron.data.labels import LabelledPixels
    from ultron.mesh.compounding import label_signed_distance, pixel_values

    probe = ProbeGeometry(width_mm=6.0, depth_mm=8.0, height_px=8, width_px=6)
    rng = np.random.default_rng(2)
    sweeps = []
    for name in ("row", "column"):
        labels = np.zeros((4, 8, 6), np.uint8)
        for k in range(4):  # a bone band at a different depth in every frame
            labels[k, 2 + k : 4 + k] = 1
        poses = np.tile(np.eye(4), (4, 1, 1))
        sweeps.append(Sweep(name, name, np.zeros_like(labels), poses, labels))
    dataset = SweepDataset(probe, sweeps)
    n = 300  # pixels of both sweeps and every frame, in no order
    pixels = LabelledPixels(*(rng.integers(0, hi, n) for hi in (2, 4, 8, 6)), np.zeros(n, np.uint8))
    config = CompoundingConfig()
    values = pixel_values(dataset, pixels, config)
    for i in range(n):
        labels = sweeps[pixels.sweep_index[i]].labels[pixels.frame[i]]
        expected = label_signed_distance(labels, (1.0, 1.0), config.clip_mm)
        assert values[i] == expected[pixels.row[i], pixels.col[i]]
    empty = LabelledPixels(*(np.zeros(0, np.int64) for _ in range(4)), np.zeros(0, np.uint8))
    assert pixel_values(dataset, empty, config).shape == (0,)


def test_frame_groups_by_hand():
    from ultron.data.labels import LabelledPixels

    sweep, frame = np.array([1, 0, 1, 0, 1]), np.array([2, 3, 2, 0, 0])
    pixels = LabelledPixels(sweep, frame, np.zeros(5, np.int64), np.zeros(5, np.int64),
                            np.zeros(5, np.uint8))  # fmt: skip
    groups = pixels.frame_groups()
    assert list(groups) == [(0, 0), (0, 3), (1, 0), (1, 2)]
    assert [g.tolist() for g in groups.values()] == [[3], [1], [4], [0, 2]]
    empty = LabelledPixels(*(np.zeros(0, np.int64) for _ in range(4)), np.zeros(0, np.uint8))
    assert empty.frame_groups() == {}


@pytest.fixture(scope="module")
def band_dataset() -> SweepDataset:
    """Frames in x–y planes every 8 mm in z; a 2 mm band of bone labels at depth 10–12 mm
    (1 inside, 0 above and below): the label band sparse frames leave in a real sweep."""
    probe = ProbeGeometry(width_mm=20.0, depth_mm=20.0, height_px=40, width_px=40)
    z = np.arange(-16.0, 16.01, 8.0)
    poses = np.tile(np.eye(4), (len(z), 1, 1))
    poses[:, 2, 3] = z
    points = frame_pixels_world(torch.as_tensor(poses), probe).numpy()
    labels = ((points[..., 1] >= 10.0) & (points[..., 1] < 12.0)).astype(np.uint8)
    images = np.zeros(labels.shape, np.uint8)
    return SweepDataset(probe, [Sweep("row", "row", images, poses, labels)])


def test_thin_band_is_filled_between_sparse_frames(band_dataset):
    # a Gaussian-weighted average of 0/1 labels (the earlier filler) never reaches 0.5 across a
    # 2 mm band; interpolating signed distances between the frames keeps it
    selection = select_label_frames(band_dataset, 1.0, seed=0)
    compounded = compound_labels(band_dataset, selection)
    assert compounded.hole_fill_radius_mm == pytest.approx(4.0)
    grid = compounded.grid
    for z in (-12.0, -4.0, 2.0, 6.0):  # between frames
        inside = np.rint(grid.world_to_index([0.0, 11.0, z])).astype(int)
        above = np.rint(grid.world_to_index([0.0, 8.0, z])).astype(int)
        assert compounded.volume[tuple(inside)] >= 0.5
        assert compounded.volume[tuple(above)] < 0.5


def test_reconstruction_keeps_the_surface_facing_the_probe(band_dataset):
    from dataclasses import replace

    from ultron.mesh.observed import ObservedSurfaceConfig
    from ultron.pipeline.run import ReconstructionRequest, run_method
    from ultron.timing import StageTimer

    request = ReconstructionRequest(method="compounding", label_fraction=1.0)
    faced = run_method(band_dataset, request, None, StageTimer())
    # the beam runs along +y: kept faces look back up the beam (normal y < 0), near y = 10
    normals = faced.mesh.face_normals  # (the criterion is on vertex normals)
    assert (normals[:, 1] < -np.cos(np.radians(70.0))).mean() > 0.95
    assert (normals[:, 1] <= 0).all()  # (zero-area faces have a zero normal)
    assert abs(np.median(faced.mesh.triangles_center[:, 1]) - 10.0) < 0.5
    assert faced.info["faces_kept"] < faced.info["faces_extracted"]
    config = replace(request.method_config, observed=ObservedSurfaceConfig("all"))
    every = replace(request, method_config=config)
    closed = run_method(band_dataset, every, None, StageTimer())
    assert (closed.mesh.face_normals[:, 1] > 0.9).any()  # the band's floor


@pytest.mark.parametrize("config", [CompoundingConfig(), CompoundingConfig(interpolation="linear")])
def test_compounding_by_runs_of_frames_equals_all_at_once(sphere_dataset, config, monkeypatch):
    """Splatting the labels a few frames at a time (two sweeps, uneven runs) gives the volume
    of one pass over every pixel, bit for bit."""
    import ultron.mesh.compounding as compounding

    sweep = sphere_dataset.sweeps[0]
    halves = [slice(0, 13), slice(13, None)]
    two = SweepDataset(
        sphere_dataset.probe,
        [
            Sweep(f"s{k}", "row", sweep.images[h], sweep.probe_to_world[h], sweep.labels[h])
            for k, h in enumerate(halves)
        ],
    )
    selection = select_label_frames(two, 0.5, seed=1)
    monkeypatch.setattr(compounding, "CHUNK_PIXELS", 10**9)
    whole = compound_labels(two, selection, config)
    monkeypatch.setattr(compounding, "CHUNK_PIXELS", 3 * 50 * 50 + 7)  # three frames a run
    runs = compound_labels(two, selection, config)
    assert np.array_equal(whole.volume, runs.volume)
    assert np.array_equal(whole.observed, runs.observed)
    assert whole.volume.max() > 0.5


def test_selection_chunks_cover_the_selection_in_order(sphere_dataset):
    from ultron.data.labels import gather_labelled_pixels, selection_chunks

    selection = select_label_frames(sphere_dataset, 1.0, seed=0)
    chunks = selection_chunks(sphere_dataset, selection, 4 * 50 * 50)
    frames = [c.frames["row"] for c in chunks]
    assert [len(f) for f in frames[:-1]] == [4] * (len(frames) - 1) and 1 <= len(frames[-1]) <= 4
    assert np.array_equal(np.concatenate(frames), selection.frames["row"])
    one_frame = selection_chunks(sphere_dataset, selection, 1)  # smaller than a frame: one each
    assert [len(c.frames["row"]) for c in one_frame] == [1] * selection.n_frames
    whole = gather_labelled_pixels(sphere_dataset, selection)
    parts = [gather_labelled_pixels(sphere_dataset, c) for c in chunks]
    for name in ("frame", "row", "col", "label"):
        assert np.array_equal(
            getattr(whole, name), np.concatenate([getattr(p, name) for p in parts])
        )
    for bad in (0, -3, 2.5, True):
        with pytest.raises(UltronInputError, match="max_pixels"):
            selection_chunks(sphere_dataset, selection, bad)


def _crossing_depth_mm(compounded, x: float, z: float) -> float:
    """Depth y (mm) where the occupancy first reaches 0.5 down the column at (x, z), linear
    between voxel centres."""
    grid = compounded.grid
    i, _, k = np.rint(grid.world_to_index([x, 0.0, z])).astype(int)
    column = compounded.volume[i, :, k].astype(np.float64)
    j = int(np.argmax(column >= 0.5))
    assert j > 0 and column[j - 1] < 0.5
    t = (0.5 - column[j - 1]) / (column[j] - column[j - 1])
    y0 = grid.index_to_world(np.array([i, j - 1, k], dtype=float))[1]
    return float(y0 + t * grid.voxel_mm)


@pytest.mark.parametrize("interpolation", ["nearest", "linear"])
def test_unsure_gap_above_the_band_keeps_the_surface_at_its_top(band_dataset, interpolation):
    # the labeller leaves 2 mm of unsure pixels between the background and the band (as
    # label --auto does above a detected echo); the band's top edge is at y = 9.75 mm (between
    # the pixel centres at 9.5 and 10.0)
    sweep = band_dataset.sweeps[0]
    y = frame_pixels_world(torch.as_tensor(sweep.probe_to_world), band_dataset.probe).numpy()
    labels = sweep.labels.copy()
    labels[(y[..., 1] >= 8.0) & (y[..., 1] < 10.0)] = 255
    gapped = SweepDataset(
        band_dataset.probe, [Sweep("row", "row", sweep.images, sweep.probe_to_world, labels)]
    )
    selection = select_label_frames(gapped, 1.0, seed=0)
    edge = 9.75
    errors = {}
    for outer_side_mm in (2.0, 0.0):  # the default, and the labels as stored
        config = CompoundingConfig(interpolation=interpolation, outer_side_mm=outer_side_mm)
        compounded = compound_labels(gapped, selection, config)
        depths = [_crossing_depth_mm(compounded, 0.0, z) for z in (-8.0, -4.0, 0.0, 2.0)]
        errors[outer_side_mm > 0] = np.abs(np.array(depths) - edge)  # on and between frames
    assert CompoundingConfig().outer_side_mm == 2.0
    assert errors[True].max() < 0.1
    # without it the gap is a hole: filled from the band on the frames (the surface moves
    # out), interpolated between them, so the surface ripples from frame to frame
    assert errors[False].max() >= 0.2


def _linear_volume() -> CompoundedVolume:
    """C(i, j, k) = (i + 2j + 3k) / 40 on a 5 × 6 × 7 grid of 0.5 mm at (1, 2, 3) mm: linear,
    so trilinear reading is exact inside the grid."""
    i, j, k = np.meshgrid(np.arange(5), np.arange(6), np.arange(7), indexing="ij")
    grid = GridSpec((1.0, 2.0, 3.0), 0.5, (5, 6, 7))
    volume = ((i + 2 * j + 3 * k) / 40).astype(np.float32)
    return CompoundedVolume(volume, np.ones(volume.shape, bool), grid, 0.0)


def test_fusion_is_the_larger_of_f_and_the_trilinear_labels():
    compounded = _linear_volume()
    fused = fuse_with_labels(lambda p: torch.full((len(p),), 0.3), compounded)
    index = torch.tensor([[0.0, 0.0, 0.0], [4.0, 5.0, 6.0], [1.5, 2.25, 3.75], [2.0, 1.0, 0.5]])
    points_mm = torch.tensor(compounded.grid.origin_mm) + 0.5 * index
    by_hand = (index[:, 0] + 2 * index[:, 1] + 3 * index[:, 2]) / 40  # 0, 0.8, 0.4, 0.1625
    expected = torch.maximum(by_hand, torch.tensor(0.3))
    torch.testing.assert_close(fused(points_mm), expected)
    # outside the compounded grid f alone decides, and f's dtype is kept
    far = torch.tensor([[100.0, 100.0, 100.0], [-50.0, 2.0, 3.0]], dtype=torch.float64)
    result = fuse_with_labels(
        lambda p: torch.full((len(p),), 0.7, dtype=torch.float64), compounded
    )(far)
    assert result.dtype == torch.float64 and torch.equal(
        result, torch.full((2,), 0.7, dtype=torch.float64)
    )


def test_fusion_keeps_the_labelled_sphere_inside_an_empty_f(sphere_dataset):
    compounded = compound_labels(sphere_dataset, select_label_frames(sphere_dataset, 1.0, seed=0))
    fused = fuse_with_labels(lambda p: torch.zeros(len(p)), compounded)
    radius = torch.tensor([0.0, 0.5 * RADIUS, 1.5 * RADIUS])
    points_mm = torch.tensor(CENTER, dtype=torch.float32) + radius[:, None] * torch.tensor(
        [1.0, 0, 0]
    )
    assert fused(points_mm).tolist()[:2] == [1.0, 1.0] and fused(points_mm)[2] == 0.0


def test_fusion_refuses_anything_but_a_compounded_volume():
    with pytest.raises(UltronInputError, match="compounded"):
        fuse_with_labels(lambda p: p[:, 0], np.zeros((3, 3, 3)))


def test_fusion_applies_when_nearly_every_frame_is_labelled(sphere_dataset):
    """33 frames: the default fuses from ⌈0.9 × 33⌉ = 30 labelled frames up; a share of 0
    fuses at any label fraction."""
    n_frames = sphere_dataset.n_frames
    assert n_frames == 33
    default, always = LabelFusionConfig(), LabelFusionConfig(min_frame_share=0.0)
    for fraction, n_labelled in ((1.0, 33), (30 / 33, 30), (29 / 33, 29), (0.1, 4)):
        selection = select_label_frames(sphere_dataset, fraction, seed=0)
        assert selection.n_frames == n_labelled
        assert labelled_frame_share(sphere_dataset, selection) == n_labelled / 33
        assert default.applies(sphere_dataset, selection) == (n_labelled >= 30)
        assert always.applies(sphere_dataset, selection)


@pytest.mark.parametrize("share", [-0.1, 1.5, float("nan")])
def test_fusion_config_refuses_a_share_outside_0_1(share):
    with pytest.raises(UltronInputError, match="min_frame_share"):
        LabelFusionConfig(min_frame_share=share)
    with pytest.raises(UltronInputError, match="volume"):
        LabelFusionConfig(volume=None)
