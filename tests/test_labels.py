"""Label-fraction selection: deterministic, spread across sweeps, every annotated pixel gathered."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import make_pose
from ultron.data.dataset import ProbeGeometry, Sweep, SweepDataset
from ultron.data.labels import (
    FrameSelection,
    LabelledPixels,
    count_labelled_pixels,
    gather_labelled_pixels,
    labelled_surface_points_mm,
    select_label_frames,
    selection_warnings,
    surface_outer_side,
    unused_label_warnings,
)
from ultron.errors import UltronInputError


def sweep_with_labels(name: str, n: int, unannotated: tuple[int, ...] = ()) -> Sweep:
    labels = np.zeros((n, 4, 5), dtype=np.uint8)
    labels[:, 2, 1] = 1
    labels[:, 0, :] = 255
    labels[list(unannotated)] = 255
    poses = np.stack([make_pose(translation=(0.0, 0.0, float(i))) for i in range(n)])
    return Sweep(name, "row", np.zeros((n, 4, 5), np.uint8), poses, labels)


@pytest.fixture
def dataset() -> SweepDataset:
    probe = ProbeGeometry(5.0, 4.0, 4, 5)
    return SweepDataset(
        probe,
        [
            sweep_with_labels("a", 60),
            sweep_with_labels("b", 60, (0, 1, 2)),
            sweep_with_labels("c", 30),
        ],
    )


def test_fraction_counts_and_spread(dataset):
    selection = select_label_frames(dataset, 0.1, seed=0)
    # 147 annotated frames → ceil(14.7) = 15, split 6/6/3 in proportion, all sweeps used
    assert selection.n_frames == 15
    assert {k: len(v) for k, v in selection.frames.items()} == {"a": 6, "b": 6, "c": 3}
    a = selection.frames["a"]
    # evenly spaced: gaps of exactly 10 frames
    assert np.all(np.diff(a) == 10)
    assert set(selection.frames["b"]).isdisjoint({0, 1, 2})  # never an unannotated frame


def test_deterministic_from_seed(dataset):
    one = select_label_frames(dataset, 0.05, seed=3)
    two = select_label_frames(dataset, 0.05, seed=3)
    assert one.to_dict() == two.to_dict()
    others = [select_label_frames(dataset, 0.05, seed=s).to_dict()["frames"] for s in range(8)]
    assert len({str(o) for o in others}) > 1  # the seed matters


def test_full_fraction_takes_every_annotated_frame(dataset):
    selection = select_label_frames(dataset, 1.0, seed=0)
    assert selection.n_frames == 147
    assert np.array_equal(selection.frames["b"], np.arange(3, 60))


def test_tiny_fraction_still_selects_one_frame(dataset):
    assert select_label_frames(dataset, 0.001, seed=0).n_frames == 1


def test_a_sweep_left_without_labels_is_named(dataset):
    """1 % of 147 annotated frames is 2 frames for 3 sweeps: by the largest remainder (a 0.82,
    b 0.78, c 0.41) sweep c gets none; 3 / 147 = 0.0204 rounds up to 0.021, whose 4 frames
    label each sweep. A sweep without annotation is not named."""
    probe = dataset.probe
    unannotated = Sweep("d", "row", np.zeros((2, 4, 5), np.uint8), np.stack([np.eye(4)] * 2))
    with_blank = SweepDataset(probe, [*dataset.sweeps, unannotated])
    selection = select_label_frames(with_blank, 0.01, seed=0)
    assert selection.n_frames == 2 and len(selection.frames["c"]) == 0
    assert selection_warnings(with_blank, selection) == [
        "label fraction 0.01 selects 2 of 147 annotated frames for 3 annotated sweeps: c gets no"
        " labelled frame; a label fraction of at least 0.021 labels one frame in each"
    ]
    enough = select_label_frames(with_blank, 0.021, seed=0)
    assert min(len(f) for n, f in enough.frames.items() if n != "d") >= 1
    assert selection_warnings(with_blank, enough) == []
    assert selection_warnings(dataset, select_label_frames(dataset, 0.1, seed=0)) == []


def test_unused_labels_are_named_where_every_label_is_meant_to_count(dataset):
    """147 of 150 frames annotated by hand: a fraction is the experiment, no line. The same
    labels marked automatic: 10 % reads 15 of 147, the other 132 named. Hand labels on 20 of
    150 frames (under half): 10 % reads 2, the other 18 named. A fraction of 1 never warns."""
    tenth = select_label_frames(dataset, 0.1, seed=0)
    assert unused_label_warnings(dataset, tenth) == []
    auto = SweepDataset(dataset.probe, dataset.sweeps, metadata={"auto_labels": {"a": {}}})
    assert unused_label_warnings(auto, select_label_frames(auto, 0.1, seed=0)) == [
        "label fraction 0.1 reads 15 of the 147 annotated frames (automatic labels of sweep(s)"
        " a); the other 132 are not used. --label-fraction 1 reads every one (a fraction below"
        " 1 hides labels, for experiments such as the paper's 10 %)"
    ]
    assert unused_label_warnings(auto, select_label_frames(auto, 1.0, seed=0)) == []
    hand = sweep_with_labels("a", 60, tuple(range(20, 60)))
    sparse = SweepDataset(dataset.probe, [hand, sweep_with_labels("c", 90, tuple(range(90)))])
    (line,) = unused_label_warnings(sparse, select_label_frames(sparse, 0.1, seed=0))
    assert line.startswith("label fraction 0.1 reads 2 of the 20 annotated frames (20 of the 150")
    assert "the other 18 are not used" in line
    half = SweepDataset(dataset.probe, [sweep_with_labels("a", 60, tuple(range(30)))])
    assert unused_label_warnings(half, select_label_frames(half, 0.1, seed=0)) == []


def test_gathered_pixels_skip_255(dataset):
    selection = select_label_frames(dataset, 0.1, seed=1)
    pixels = gather_labelled_pixels(dataset, selection)
    # 3 annotated rows × 5 columns per frame, one bone pixel each
    assert len(pixels) == 15 * 15
    assert int(pixels.label.sum()) == 15
    assert set(np.unique(pixels.row)) == {1, 2, 3}
    bone = pixels.label == 1
    assert set(pixels.row[bone]) == {2} and set(pixels.col[bone]) == {1}


@pytest.mark.parametrize("fraction", [0.0, -0.1, 1.5])
def test_bad_fraction(dataset, fraction):
    with pytest.raises(UltronInputError, match="label_fraction"):
        select_label_frames(dataset, fraction, seed=0)


def test_no_labels_is_a_clear_error():
    probe = ProbeGeometry(5.0, 4.0, 4, 5)
    unlabelled = Sweep("a", "row", np.zeros((2, 4, 5), np.uint8), np.stack([np.eye(4)] * 2))
    with pytest.raises(UltronInputError, match=r"^dataset: labels: no annotated frame"):
        select_label_frames(SweepDataset(probe, [unlabelled]), 0.5, seed=0)
    with pytest.raises(UltronInputError, match=r"^runs/d: labels: no annotated frame"):
        select_label_frames(SweepDataset(probe, [unlabelled]), 0.5, 0, where="runs/d")


def test_surface_outer_side_by_hand():
    # one frame, rows top to bottom; columns: a band under a 3-row unsure gap, a band right
    # under background, no band, a band at the top row, a gap broken by a background pixel
    u, b, g = 255, 1, 0
    labels = np.array(
        [
            [g, g, g, b, u],
            [u, g, u, b, g],
            [u, g, u, u, u],
            [u, b, u, u, u],
            [b, b, u, u, b],
            [b, u, u, u, b],
        ],
        dtype=np.uint8,
    )
    outer = surface_outer_side(labels, 2)
    expected = np.zeros_like(outer)
    expected[[2, 3], 0] = True  # two of the gap's three rows; none where the band meets 0
    expected[[2, 3], 4] = True  # the run above the band stops at the background pixel
    np.testing.assert_array_equal(outer, expected)
    np.testing.assert_array_equal(surface_outer_side(labels, 5)[:, 0], [0, 1, 1, 1, 0, 0])
    assert not surface_outer_side(labels, 0).any()
    # frames stack: each frame on its own
    stacked = surface_outer_side(np.stack([labels, labels[::-1]]), 2)
    np.testing.assert_array_equal(stacked[0], expected)
    np.testing.assert_array_equal(stacked[1], surface_outer_side(labels[::-1], 2))


@pytest.mark.parametrize("rows", [-1, 1.5, True])
def test_surface_outer_side_rejects_bad_rows(rows):
    with pytest.raises(UltronInputError, match="rows"):
        surface_outer_side(np.zeros((3, 3), np.uint8), rows)
    with pytest.raises(UltronInputError, match="labels"):
        surface_outer_side(np.zeros(3, np.uint8), 1)


def test_gathered_outer_side_reads_as_background(dataset):
    selection = select_label_frames(dataset, 0.1, seed=1)
    plain = gather_labelled_pixels(dataset, selection)
    # the fixture's bone pixel (row 2) sits right under background (row 1): nothing to add
    assert len(gather_labelled_pixels(dataset, selection, outer_side_mm=2.0)) == len(plain)
    # unannotate the pixel above it: the gap (rows 1 and 0 of column 1) reads as background
    sweeps = []
    for sweep in dataset.sweeps:
        labels = sweep.labels.copy()
        labels[:, 1, 1] = 255
        sweeps.append(Sweep(sweep.name, sweep.kind, sweep.images, sweep.probe_to_world, labels))
    gapped = SweepDataset(dataset.probe, sweeps)
    base = gather_labelled_pixels(gapped, selection)  # the labels as stored
    assert len(base) == len(plain) - 15  # 15 frames chosen
    # 1 mm rows: 2 mm reaches both rows above the bone pixel
    for mm, added_rows in ((0.5, set()), (1.0, {1}), (1.99, {1}), (2.0, {0, 1}), (9, {0, 1})):
        pixels = gather_labelled_pixels(gapped, selection, outer_side_mm=mm)
        assert len(pixels) == len(base) + 15 * len(added_rows)
        assert count_labelled_pixels(gapped, selection, mm) == len(pixels)
        at_column = (pixels.col == 1) & (pixels.row < 2)
        assert set(pixels.row[at_column]) == added_rows and not pixels.label[at_column].any()
    for bad in (-1.0, float("nan"), "2"):
        with pytest.raises(UltronInputError, match="outer_side_mm"):
            gather_labelled_pixels(gapped, selection, outer_side_mm=bad)


def test_labelled_surface_points_are_the_top_of_each_bone_band():
    probe = ProbeGeometry(5.0, 4.0, 4, 5)  # 1 mm pixels: pixel (r, c) at x = c − 2.5, y = r
    labels = np.full((3, 4, 5), 255, np.uint8)
    labels[0, 1:3, 3] = 1  # a band whose top is row 1
    labels[0, 0, 0] = 1  # a band that starts at the transducer
    labels[0, [0, 2, 3], 4] = 1  # two bands in one column ...
    labels[0, 1, 4] = 0  # ... with background between them
    labels[1, 0, :] = 0  # a selected frame without bone
    labels[2, 3, 1] = 1  # bone in a frame that is not selected
    poses = np.stack([make_pose(translation=(0.0, 0.0, float(i))) for i in range(3)])
    data = SweepDataset(probe, [Sweep("a", "row", np.zeros((3, 4, 5), np.uint8), poses, labels)])
    points = labelled_surface_points_mm(data, FrameSelection(0.5, 0, {"a": np.array([0, 1])}))
    got = sorted(map(tuple, points.round(9).tolist()))
    assert got == [(-2.5, 0.0, 0.0), (0.5, 1.0, 0.0), (1.5, 0.0, 0.0), (1.5, 2.0, 0.0)]
    assert labelled_surface_points_mm(
        data, FrameSelection(0.5, 0, {"a": np.array([2])})
    ).tolist() == [[-1.5, 3.0, 2.0]]
    assert labelled_surface_points_mm(data, FrameSelection(0.5, 0, {"a": np.array([1])})).shape == (
        0,
        3,
    )
    assert labelled_surface_points_mm(data, None).shape == (0, 3)


def test_in_front_of_bone_by_hand():
    # two frames of two sweeps; per scanline (sweep, frame, column) the rows top to bottom:
    #   (0, 0, 0): 0 0 1 1 0 1 0  → rows 0, 1 in front; the gap and the rows under the
    #                                first bone run are not (they may lie in its shadow)
    #   (0, 0, 1): 0 0 0          → no bone in this scanline: none in front
    #   (0, 1, 0): 1 0            → bone at the top: none
    #   (1, 0, 0): 0 0 0 1        → rows 0-2 in front, though sweep 0's column 0 differs
    #   (1, 0, 2): 0 1 (unordered) → row 0 in front
    lines = [
        (0, 0, 0, [0, 0, 1, 1, 0, 1, 0]),
        (0, 0, 1, [0, 0, 0]),
        (0, 1, 0, [1, 0]),
        (1, 0, 0, [0, 0, 0, 1]),
    ]
    s, f, r, c, lab = [], [], [], [], []
    for sweep, frame, col, column in lines:
        for row, value in enumerate(column):
            s.append(sweep), f.append(frame), r.append(row), c.append(col), lab.append(value)
    s += [1, 1]
    f += [0, 0]
    r += [1, 0]  # the bone pixel first: the order of the pixels does not matter
    c += [2, 2]
    lab += [1, 0]
    pixels = LabelledPixels(*(np.array(v, dtype=np.int64) for v in (s, f, r, c)),
                            np.array(lab, dtype=np.uint8))  # fmt: skip
    expected = [1, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1, 0, 0, 1]  # the lines in order
    np.testing.assert_array_equal(pixels.in_front_of_bone(), np.array(expected, dtype=bool))
    # no bone label anywhere: nothing is in front
    none = pixels.take(pixels.label == 0)
    assert not none.in_front_of_bone().any() and none.in_front_of_bone().shape == (len(none),)


def test_gathered_background_above_the_fixture_bone_is_in_front(dataset):
    # the fixture's bone pixel is row 2 of column 1 under a background pixel (row 1): that one
    # is in front; the other columns hold no bone, and the row under the bone is not in front
    pixels = gather_labelled_pixels(dataset, select_label_frames(dataset, 0.1, seed=1))
    front = pixels.in_front_of_bone()
    np.testing.assert_array_equal(front, (pixels.col == 1) & (pixels.row == 1))


def test_world_mm_is_each_pixel_through_its_own_frames_pose():
    """Hand-worked: p = ((c − W/2)·W_mm/W, r·D_mm/H, 0) mapped by R·p + t of the pixel's own
    frame, for pixels of two sweeps in shuffled frame order, whole and as a subset."""
    probe = ProbeGeometry(5.0, 4.0, 4, 5)  # 1 mm pixels both ways
    rng = np.random.default_rng(3)
    sweeps = []
    for name in ("a", "b"):
        rotations = [np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(4)]
        poses = np.stack([make_pose(r, rng.normal(size=3) * 10) for r in rotations])
        labels = np.zeros((4, 4, 5), dtype=np.uint8)
        sweeps.append(Sweep(name, "row", np.zeros((4, 4, 5), np.uint8), poses, labels))
    dataset = SweepDataset(probe, sweeps)
    n = 40
    pixels = LabelledPixels(
        sweep_index=rng.integers(0, 2, n),
        frame=rng.integers(0, 4, n),
        row=rng.integers(0, 4, n),
        col=rng.integers(0, 5, n),
        label=np.zeros(n, dtype=np.uint8),
    )
    every = np.stack([s.probe_to_world for s in dataset.sweeps])  # (2, 4, 4, 4)
    pose = every[pixels.sweep_index, pixels.frame]
    local = np.stack([pixels.col - 2.5, pixels.row * 1.0, np.zeros(n)], axis=1)
    expected = np.einsum("nij,nj->ni", pose[:, :3, :3], local) + pose[:, :3, 3]
    np.testing.assert_allclose(pixels.world_mm(dataset), expected, rtol=0, atol=1e-12)
    subset = np.array([7, 3, 31, 3, 0])
    np.testing.assert_allclose(
        pixels.world_mm(dataset, subset), expected[subset], rtol=0, atol=1e-12
    )
    assert pixels.world_mm(dataset, np.zeros(0, dtype=np.int64)).shape == (0, 3)
