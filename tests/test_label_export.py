"""``ultron label --export``: a sweep's labels as masks of its recording's frames — the inverse of
``label --masks`` through every step a PLUS import took (orientation, skipped frames, clip
rectangle, blank columns, the rigid grid of a sheared calibration, downsampling); the twin of
the recording's header; the round trip; bad input."""

from __future__ import annotations

import shlex
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from conftest import assert_refused
from plus_synthetic import write_mha
from test_bad_input_corpus import runner
from test_label_import import _recording_with_an_echo, imported_echo
from ultron.cli.main import app
from ultron.data.dataset import SweepDataset
from ultron.data.label_export import (
    LabelExportConfig,
    coded_masks,
    export_labels,
    recording_pixel_map,
)
from ultron.data.plus import read_sequence
from ultron.errors import UltronInputError


def _label(*args: str):
    return runner.invoke(app, ["label", *args], terminal_width=400)


def _import(tmp_path: Path, shear_deg: float, downsample: str):
    """The echo recording (stored UN, frame 2 invalid) imported, labelled from its masks."""
    return imported_echo(tmp_path, shear_deg, downsample, "s.igs.mha")


def test_coded_masks_hand_worked():
    """Bone → bone value, unsure of an annotated frame → unsure value, background and every
    pixel of a frame nobody annotated → 0, and 0 outside the covered pixels."""
    labels = np.array([[[1, 0, 255], [255, 1, 0]], [[255] * 3] * 2], dtype=np.uint8)
    masks = coded_masks(labels, LabelExportConfig(bone_value=7, unsure_value=3))
    assert masks.tolist() == [[[7, 0, 3], [3, 7, 0]], [[0] * 3] * 2]
    covered = np.array([[True, True, False], [True, True, True]])
    assert coded_masks(labels, LabelExportConfig(), covered)[0].tolist() == [[1, 0, 0], [2, 1, 0]]
    assert coded_masks(labels, LabelExportConfig(bone_value=300)).dtype == np.uint16


def test_pixel_map_of_a_clipped_downsampled_import_hand_worked(tmp_path: Path):
    """No shear, the clip rectangle narrowed to the signal (origin (3, 2), 54 × 36),
    downsampled 2×: recording pixel (3 + 2c, 2 + 2r) is sweep pixel (r, c); the pixels outside
    the clip rectangle are not covered."""
    out, _, _ = _import(tmp_path, 0.0, "2")
    record = SweepDataset.load(out).metadata["imports"]["s"]
    assert record["clip"] == {"origin": [3, 2], "size": [54, 36]}  # narrowed to the signal
    rows, columns, covered = recording_pixel_map(record, (18, 27), "dataset.json")
    assert rows.shape == (40, 60) and covered.sum() == 36 * 54
    assert not covered[:2].any() and not covered[:, :3].any() and not covered[:, 57:].any()
    for r, c in ((0, 0), (5, 7), (17, 26)):
        assert (rows[2 + 2 * r, 3 + 2 * c], columns[2 + 2 * r, 3 + 2 * c]) == (r, c)


def test_masks_of_the_sweeps_own_frames_round_trip(tmp_path: Path):
    """A sweep not imported from PLUS: its labels as they are, coded, and read back unchanged."""

    data = SweepDataset.load(_simulated(tmp_path))
    labels = data.sweep("s").labels
    result = _label(str(tmp_path / "d"), "--export", str(tmp_path / "e.npy"))
    assert result.exit_code == 0, result.output
    masks = np.load(tmp_path / "e.npy")
    assert masks.shape == labels.shape and masks.dtype == np.uint8
    assert np.array_equal(masks == 1, labels == 1) and (masks[[0, 4]] == 0).all()
    assert np.array_equal(masks[1:4] == 2, labels[1:4] == 255)
    command = shlex.split(result.output.split("read back (after editing) with: ")[1].strip())
    again = runner.invoke(app, command[1:], terminal_width=400)
    assert again.exit_code == 0, again.output
    assert np.array_equal(SweepDataset.load(tmp_path / "d").sweep("s").labels, labels)
    assert "warning" not in again.stderr
    naive = _label(str(tmp_path / "d"), "--masks", str(tmp_path / "e.npy"), "--replace")
    assert naive.exit_code == 0, naive.output  # unsure read as bone, as asked, and said so
    assert "warning: the masks hold the values 1, 2 besides 0, all read as bone" in naive.stderr
    assert (SweepDataset.load(tmp_path / "d").sweep("s").labels[1:4] != 255).all()


def _simulated(tmp_path: Path) -> Path:
    """A dataset of one sweep of its own frames (5 of 6 × 8) with labels: frames 0 and 4
    nobody annotated, some unsure pixels in the others."""
    from ultron.data.dataset import ProbeGeometry, Sweep

    rng = np.random.default_rng(1)
    poses = np.repeat(np.eye(4)[None], 5, axis=0)
    poses[:, 2, 3] = np.arange(5.0)
    labels = rng.choice(np.array([0, 1, 255], dtype=np.uint8), size=(5, 6, 8), p=[0.5, 0.3, 0.2])
    labels[[0, 4]] = 255
    images = rng.integers(0, 256, size=(5, 6, 8), dtype=np.uint8)
    sweep = Sweep("s", "row", images, poses, labels=labels)
    SweepDataset(ProbeGeometry(8.0, 6.0, 6, 8), [sweep]).save(tmp_path / "d")
    return tmp_path / "d"


@pytest.mark.parametrize(("shear_deg", "downsample"), [(0.0, "1"), (4.0, "1"), (4.0, "2")])
def test_plus_labels_land_on_the_masks_they_came_from(tmp_path: Path, shear_deg, downsample):
    """Masks → labels → exported masks: on the recording's pixels that the import kept (the
    clip rectangle of the valid frames), the exported bone is the annotator's — exactly where
    nothing was resampled, but for the edges of the band where a shear or downsampling
    resampled it (within a recording pixel of it, where a sweep pixel is two); the invalid frame and the pixels outside the clip are empty; and the export
    read back gives the labels again (exactly without a shear)."""
    out, _, masks = _import(tmp_path, shear_deg, downsample)
    labels = SweepDataset.load(out).sweep("s").labels.copy()
    result = _label(str(out), "--export", str(tmp_path / "e.npy"))
    assert result.exit_code == 0, result.output
    assert "5 masks of 40 × 60 pixels (MF), 4 frames annotated" in result.output
    exported = np.load(tmp_path / "e.npy")
    assert exported.shape == masks.shape and (exported[2] == 0).all()
    region = (slice(None), slice(2, 38), slice(3, 57))
    assert (exported[:, :2] == 0).all() and (exported[:, :, :3] == 0).all()
    valid = [0, 1, 3, 4]
    ours, theirs = exported[valid][region] == 1, masks[valid][region] == 1
    if downsample == "1":
        agree = ours == theirs
        assert agree.all() if shear_deg == 0.0 else agree.mean() > 0.99
    else:  # a sweep pixel is 2 × 2 of the recording's: the band's edges move by one pixel
        near = np.ones((1, 3, 3), dtype=bool)
        assert not (ours & ~ndimage.binary_dilation(theirs, near)).any()
        assert not (theirs & ~ndimage.binary_dilation(ours, near)).any()
    back = _label(str(out), "--masks", str(tmp_path / "e.npy"), "--unsure-value", "2",
                  "--replace")  # fmt: skip
    assert back.exit_code == 0, back.output
    again = SweepDataset.load(out).sweep("s").labels
    assert np.array_equal(again == 255, labels == 255)
    same = again == labels
    assert same.all() if shear_deg == 0.0 else same.mean() > 0.995


def test_sequence_export_is_the_recordings_twin(tmp_path: Path):
    """A .seq.mha export with --recording: the recording's per-frame fields and orientation
    (UN), the masks of the .npy export stored UN; a .seq.nrrd one is a Slicer labelmap volume
    sequence indexed by the recording's timestamps (by frame number without a recording) and
    carries the per-frame fields too; both read back as the .npy does."""
    out, sequence, _ = _import(tmp_path, 4.0, "1")
    assert _label(str(out), "--export", str(tmp_path / "e.npy")).exit_code == 0
    npy = np.load(tmp_path / "e.npy")
    recording = read_sequence(sequence)
    for name in ("e.seq.mha", "e.seq.nrrd"):
        result = _label(str(out), "--export", str(tmp_path / name), "--recording", str(sequence))
        assert result.exit_code == 0, result.output
        twin = read_sequence(tmp_path / name, labelmap=True)
        assert twin.orientation == "UN" and twin.frame_fields == recording.frame_fields
        assert np.array_equal(twin.pixels[:, ::-1, ::-1], npy)
    import nrrd

    slicer = nrrd.read_header(str(tmp_path / "e.seq.nrrd"))  # Slicer's volume sequence
    assert list(slicer["sizes"]) == [5, 60, 40, 1] and slicer["kinds"][0] == "list"
    assert slicer["DataNodeClassName"] == "vtkMRMLLabelMapVolumeNode"
    stamps = [fields["Timestamp"] for fields in recording.frame_fields]
    index = [float(v) for v in slicer["axis 0 index values"].split()]
    assert index == [float(t) for t in stamps] and slicer["labels"][0] == "time"
    found = _label(str(out), "--export", str(tmp_path / "f.seq.mha"))  # where the import read it
    assert f"header and per-frame fields from {sequence}" in found.output
    assert (tmp_path / "f.seq.mha").read_bytes() == (tmp_path / "e.seq.mha").read_bytes()
    sequence.rename(tmp_path / "moved.igs.mha")  # gone from there: frame numbers index it
    gone = _label(str(out), "--export", str(tmp_path / "f.seq.nrrd"))
    assert gone.exit_code == 0 and f"{sequence}, which the import read, is no longer" in gone.stderr
    untimed = nrrd.read_header(str(tmp_path / "f.seq.nrrd"))
    assert untimed["axis 0 index values"] == "0 1 2 3 4" and untimed["labels"][0] == "frame"
    write_mha(sequence, _recording_with_an_echo(n=3)[0], "UN")  # another file in its place
    other = _label(str(out), "--export", str(tmp_path / "g.seq.nrrd"))
    assert other.exit_code == 0 and "written without the recording's header" in other.stderr
    header = (tmp_path / "e.seq.mha").read_bytes().split(b"ElementDataFile = LOCAL\n")[0]
    original = (tmp_path / "moved.igs.mha").read_bytes().split(b"ElementDataFile = LOCAL\n")[0]
    kept = [line for line in original.splitlines() if not line.startswith(b"Element")]
    assert set(kept) <= set(header.splitlines())


def test_empty_annotated_frames_warn_and_values_are_written_as_asked(tmp_path: Path):
    """A frame annotated as all background reads back as nobody's: a warning says so; bone and
    unsure values above 255 are written as 16-bit masks."""
    root = _simulated(tmp_path)
    labels = np.load(root / "s" / "labels.npy")
    labels[2] = 0
    np.save(root / "s" / "labels.npy", labels)
    result = _label(str(root), "--export", str(tmp_path / "e.npy"), "--bone-value", "1000",
                    "--unsure-value", "7")  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "1 annotated frames hold no bone and no unsure pixel" in result.stderr
    masks = np.load(tmp_path / "e.npy")
    assert masks.dtype == np.uint16 and set(np.unique(masks)) == {0, 7, 1000}
    assert "--bone-value 1000 --unsure-value 7" in result.output


def test_bad_exports_are_one_line_errors_and_write_nothing(tmp_path: Path):
    out, sequence, _ = _import(tmp_path, 0.0, "1")
    other = _recording_with_an_echo(n=4)[0]
    short = write_mha(tmp_path / "short.igs.mha", other, "UN")
    renamed = tmp_path / "other.igs.mha"
    renamed.write_bytes(sequence.read_bytes())
    simulated = _simulated(tmp_path)
    cases = [
        ([str(out), "--export", str(tmp_path / "x.txt")], "expected a file ending in .npy"),
        ([str(out), "--export", str(tmp_path / "x.npy"), "--recording", str(sequence)],
         "a .npy export has no header"),
        ([str(out), "--export", str(tmp_path / "x.seq.mha"), "--recording", str(short)],
         "4 frames; the recording (s.igs.mha) has 5"),
        ([str(out), "--export", str(tmp_path / "x.seq.mha"), "--recording", str(renamed)],
         "the sweep was imported from s.igs.mha, not other.igs.mha"),
        ([str(simulated), "--export", str(tmp_path / "x.seq.mha"), "--recording", str(sequence)],
         "was not imported from PLUS"),
        ([str(simulated), "--export", str(tmp_path / "x.npy"), "--orientation", "UN"],
         "its masks are of its own frames"),
        ([str(out), "--auto", "--export", str(tmp_path / "x.npy")], "pass exactly one of"),
        ([str(out), "--recording", str(sequence), "--auto"], "goes with --export, not --auto"),
        ([str(out), "--auto", "--frames", "0:3"], "goes with --masks, not --auto"),
        ([str(out), "--auto", "--unsure-value", "2"], "goes with --masks or --export, not"),
        ([str(out), "--export", str(tmp_path / "x.npy"), "--annotated", "all"],
         "--annotated: goes with --masks, not --export"),
        ([str(out), "--export", str(tmp_path / "x.npy"), "--replace"],
         "goes with --auto or --masks, not --export"),
        ([str(out), "--export", str(tmp_path / "x.npy"), "--unsure-value", "1"],
         "must differ from the bone value"),
        ([str(out), "--export", str(sequence)], "is the recording the sweep was imported from"),
        ([str(out), "--export", str(out / "s" / "labels.npy")], "part of the dataset at"),
        ([str(out), "--export", str(out / "s" / "new.npy")], "is in s, part of the dataset"),
    ]  # fmt: skip
    before = {path: path.read_bytes() for path in (sequence, out / "s" / "labels.npy")}
    assert_refused(_label, cases)
    assert all(path.read_bytes() == data for path, data in before.items())
    assert not (out / "s" / "new.npy").exists()
    assert not list(tmp_path.glob("x*")) and not list(tmp_path.glob(".x*"))
    (out / "s" / "labels.npy").unlink()  # a sweep without labels
    with pytest.raises(UltronInputError, match="the sweep has no labels"):
        export_labels(out, "s", tmp_path / "x.npy")


def test_auto_labels_name_the_recordings_frames_and_how_to_correct_them(tmp_path: Path):
    """label --auto on a PLUS sweep whose frame 2 was skipped: the quality summary's last column
    is each frame's number in the recording (0, 1, 3, 4); the frames to check are named in both
    numberings, with the export command that shows them over the recording."""
    from ultron.data.auto_label_dataset import QUALITY_FILE, SweepLabelSummary

    out, _, _ = _import(tmp_path, 0.0, "1")
    result = _label(str(out), "--auto", "--replace")
    assert result.exit_code == 0, result.output
    rows = (out / "s" / QUALITY_FILE).read_text().splitlines()
    assert rows[0] == "frame,bone_scanlines,evidence,unsure,check,recording_frame"
    assert [row.split(",")[-1] for row in rows[1:]] == ["0", "1", "3", "4"]
    summary = SweepLabelSummary(
        "s", 4, 0.1, 0.2, 0.7, False, 1.0, frames_to_check=(2, 3),
        recording_frames=(0, 1, 3, 4), recording="s.igs.mha",
    )  # fmt: skip
    lines, _ = summary.lines("my data")
    assert "check 2, 3 (the recording's 3, 4) (per frame:" in lines[1]
    assert lines[2] == (
        "  to correct them over the recording: ultron label 'my data' --export"
        " s_labels.seq.mha --sweeps s --recording s.igs.mha"
    )
    where = replace(summary, recording="/data/s.igs.mha")  # where the import read it: found
    assert where.lines("d")[0][2].endswith("--export s_labels.seq.mha --sweeps s")
    plain = SweepLabelSummary("s", 4, 0.1, 0.2, 0.7, False, 1.0, frames_to_check=(2, 3))
    assert len(plain.lines("d")[0]) == 2 and "recording" not in plain.lines("d")[0][1]


@pytest.mark.parametrize("fmt", ["mha", "nrrd"])
def test_a_recording_is_read_header_only_for_its_header(tmp_path: Path, fmt: str):
    """``read_sequence(…, header_only=True)`` gives the full read's fields, per-frame fields and
    frame shape without the pixels (a zero view of no memory), so that ``--recording`` costs a
    header; a payload cut short, which the full read refuses, is not read at all."""
    from plus_synthetic import recording, write_nrrd

    rec = recording(n=5, height=12, width=16)
    writer = write_mha if fmt == "mha" else write_nrrd
    path = writer(tmp_path / f"s.seq.{fmt}", rec, "UN", True)
    full, header = read_sequence(path), read_sequence(path, header_only=True)
    assert header.pixels.shape == full.pixels.shape == (5, 12, 16)
    assert header.frame_fields == full.frame_fields and header.fields == full.fields
    assert header.orientation == "UN" and not header.pixels.any()
    assert header.pixels.strides == (0, 0, 0) and not header.pixels.flags.writeable
    path.write_bytes(path.read_bytes()[:-40])
    with pytest.raises(UltronInputError, match=r"truncated|corrupt"):
        read_sequence(path)
    assert read_sequence(path, header_only=True).pixels.shape == (5, 12, 16)


def test_export_and_masks_need_one_sweep_named_where_there_are_more(tmp_path: Path):
    """Without --sweeps the one sweep of a dataset is taken (it is loaded once, by the library);
    with two sweeps, or two named, --export and --masks are refused naming --sweeps."""
    from ultron.data.dataset import ProbeGeometry, Sweep

    root = _simulated(tmp_path)
    assert _label(str(root), "--export", str(tmp_path / "one.npy")).exit_code == 0
    np.save(tmp_path / "m.npy", np.load(tmp_path / "one.npy"))
    data = SweepDataset.load(root)
    other = data.sweep("s")
    data.sweeps.append(Sweep("t", "row", other.images.copy(), other.probe_to_world.copy()))
    SweepDataset(ProbeGeometry(8.0, 6.0, 6, 8), data.sweeps).save(tmp_path / "two")
    two = str(tmp_path / "two")
    cases = [
        ([two, "--export", str(tmp_path / "e.npy")], "--sweeps: --export works on one sweep"),
        ([two, "--masks", str(tmp_path / "m.npy")], "--sweeps: --masks works on one sweep"),
        ([two, "--export", str(tmp_path / "e.npy"), "--sweeps", "s,t"], "(--sweeps NAME; here 2)"),
    ]  # fmt: skip
    assert_refused(_label, cases)
    assert not (tmp_path / "e.npy").exists()
    named = _label(two, "--masks", str(tmp_path / "m.npy"), "--sweeps", "t", "--unsure-value", "2")
    assert named.exit_code == 0, named.output
    assert np.array_equal(SweepDataset.load(two).sweep("t").labels, data.sweep("s").labels)


def test_a_recording_of_the_same_size_with_other_fields_lends_no_header(tmp_path: Path):
    """Another recording under the imported one's name, frame count and size (its probe
    elsewhere) is not the recording: refused as --recording, and where it replaced the file
    the import read, the export is written without its header and says so."""
    out, sequence, _ = _import(tmp_path, 0.0, "1")
    rec, _ = _recording_with_an_echo()
    rec.transforms["ProbeToTracker"][:, 0, 3] += 1.0
    (tmp_path / "elsewhere").mkdir()
    other = write_mha(tmp_path / "elsewhere" / "s.igs.mha", rec, "UN")
    assert_refused(
        _label,
        [([str(out), "--export", str(tmp_path / "x.seq.mha"), "--recording", str(other)],
          "per-frame fields (timestamps, transforms, statuses) are not those")],
    )  # fmt: skip
    same = _label(str(out), "--export", str(tmp_path / "y.seq.mha"), "--recording", str(sequence))
    assert same.exit_code == 0, same.output
    write_mha(sequence, rec, "UN")  # the file the import read, replaced by the other
    replaced = _label(str(out), "--export", str(tmp_path / "z.seq.mha"))
    assert replaced.exit_code == 0, replaced.output
    assert "written without the recording's header" in replaced.stderr
    assert "per-frame fields" in replaced.stderr
