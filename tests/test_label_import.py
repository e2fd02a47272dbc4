"""``ultron label --masks``: a person's segmentation as a sweep's labels — on a sweep of the
dataset's own frames, and on a PLUS sweep through every step its import took (orientation,
skipped frames, clip rectangle, blank columns, the rigid grid of a sheared calibration,
downsampling); the frames annotated, bone and unsure values; bad input."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from plus_synthetic import (
    Recording,
    calibration,
    recording,
    to_file_orientation,
    write_config,
    write_mha,
    write_nrrd,
)
from test_bad_input_corpus import runner
from ultron.cli.main import app
from ultron.data.dataset import ProbeGeometry, Sweep, SweepDataset
from ultron.data.label_import import (
    MAX_LISTED_FRAMES,
    MaskImportConfig,
    mask_labels,
    parse_frames,
)
from ultron.errors import UltronInputError

#: Grey levels of the synthetic recording: tissue and the bone's echo band.
TISSUE, ECHO = 30, 240


def _files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def _label(*args: str):
    return runner.invoke(app, ["label", *args], terminal_width=400)


@pytest.fixture
def own_frames(tmp_path: Path) -> Path:
    """A dataset of one simulated-style sweep (5 frames of 6 × 8) without labels."""
    rng = np.random.default_rng(0)
    poses = np.repeat(np.eye(4)[None], 5, axis=0)
    poses[:, 2, 3] = np.arange(5.0)
    images = rng.integers(0, 256, size=(5, 6, 8), dtype=np.uint8)
    SweepDataset(ProbeGeometry(8.0, 6.0, 6, 8), [Sweep("s", "row", images, poses)]).save(
        tmp_path / "d"
    )
    return tmp_path / "d"


def test_mask_values_frames_and_unsure_read_as_the_convention():
    """Bone where the mask is bone, background elsewhere in an annotated frame, 255 in an
    empty frame (nonempty) or nowhere (all), and where the mask says unsure."""
    masks = np.zeros((3, 2, 3), dtype=np.uint16)
    masks[0, 0, 1] = 7
    masks[0, 1, 2] = 300
    masks[2, 1, 0] = 9
    labels = mask_labels(masks, MaskImportConfig())
    assert labels[0].tolist() == [[0, 1, 0], [0, 0, 1]]
    assert (labels[1] == 255).all() and labels[2].tolist() == [[0, 0, 0], [1, 0, 0]]
    every = mask_labels(masks, MaskImportConfig(annotated="all"))
    assert (every[1] == 0).all() and np.array_equal(every[0], labels[0])
    valued = mask_labels(masks, MaskImportConfig(bone_value=7, unsure_value=9))
    assert valued[0].tolist() == [[0, 1, 0], [0, 0, 0]]
    assert valued[2].tolist() == [[0, 0, 0], [255, 0, 0]]  # annotated: it marks something
    assert (valued[1] == 255).all()


@pytest.mark.parametrize(
    ("changes", "name"),
    [
        ({"bone_value": 0}, "bone_value"),
        ({"unsure_value": True}, "unsure_value"),
        ({"bone_value": 3, "unsure_value": 3}, "unsure_value"),
        ({"annotated": "some"}, "annotated"),
        ({"orientation": "FM"}, "orientation"),
    ],
)
def test_config_refuses_bad_values(changes, name):
    with pytest.raises(UltronInputError, match=name):
        MaskImportConfig(**changes)


def test_masks_of_the_sweeps_own_frames(own_frames: Path, tmp_path: Path):
    masks = np.zeros((5, 6, 8), dtype=np.uint8)
    masks[1, 3:5, 2:6] = 255  # a 0/255 PNG-style mask
    masks[3, 2, :] = 255
    np.save(tmp_path / "m.npy", masks)
    result = _label(str(own_frames), "--masks", str(tmp_path / "m.npy"))
    assert result.exit_code == 0, result.output
    assert "2 of 5 frames annotated" in result.output
    data = SweepDataset.load(own_frames)
    labels = data.sweep("s").labels
    assert np.array_equal(labels[1], (masks[1] > 0).astype(np.uint8))
    assert (labels[[0, 2, 4]] == 255).all()
    record = data.metadata["label_imports"]["s"]
    assert record["masks"] == str((tmp_path / "m.npy").resolve())
    assert record["config"]["annotated"] == "nonempty"


def test_masks_replace_automatic_labels_and_drop_their_record(own_frames: Path, tmp_path: Path):
    """Replaced labels are a person's now: the sweep's ``auto_labels`` record goes, so that the
    report no longer calls them automatic; without --replace nothing is written."""
    meta_path = own_frames / "dataset.json"
    meta = json.loads(meta_path.read_text())
    meta.setdefault("metadata", {})["auto_labels"] = {"s": {"method": "x"}}
    meta_path.write_text(json.dumps(meta))
    np.save(own_frames / "s" / "labels.npy", np.full((5, 6, 8), 255, dtype=np.uint8))
    meta["sweeps"][0]["labels"] = "labels.npy"
    meta_path.write_text(json.dumps(meta))
    masks = np.zeros((5, 6, 8), dtype=np.uint8)
    masks[2, 4, 1:7] = 1
    np.save(tmp_path / "m.npy", masks)
    before = _files(own_frames)
    refused = _label(str(own_frames), "--masks", str(tmp_path / "m.npy"))
    assert refused.exit_code == 2
    assert "already has labels; pass --replace to overwrite them with the masks" in refused.stderr
    assert _files(own_frames) == before
    result = _label(str(own_frames), "--masks", str(tmp_path / "m.npy"), "--replace")
    assert result.exit_code == 0, result.output
    assert "replaced the sweep's labels" in result.output
    data = SweepDataset.load(own_frames)
    assert "auto_labels" not in data.metadata and "s" in data.metadata["label_imports"]
    assert int((data.sweep("s").labels == 1).sum()) == 6


def test_masks_interrupted_before_the_last_write_are_still_called_masks(
    own_frames: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    """Ctrl-C after the new labels are written, before ``dataset.json`` drops the sweep's
    automatic-label record: the record no longer describes the labels, so the sweep's labels
    are the masks'."""
    import ultron.data.auto_label_dataset as module
    from ultron.data.label_import import import_mask_labels, label_sources

    meta_path = own_frames / "dataset.json"
    meta = json.loads(meta_path.read_text())
    meta.setdefault("metadata", {})["auto_labels"] = {"s": {"method": "x"}}
    meta["sweeps"][0]["labels"] = "labels.npy"
    np.save(own_frames / "s" / "labels.npy", np.full((5, 6, 8), 255, dtype=np.uint8))
    meta_path.write_text(json.dumps(meta))
    assert label_sources(SweepDataset.load(own_frames)) == {"s": "auto"}  # an old record
    masks = np.zeros((5, 6, 8), dtype=np.uint8)
    masks[2, 4, 1:7] = 1
    np.save(tmp_path / "m.npy", masks)
    original, calls = module.save_dataset_json, []

    def interrupted(*args):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        original(*args)

    monkeypatch.setattr(module, "save_dataset_json", interrupted)
    with pytest.raises(KeyboardInterrupt):
        import_mask_labels(own_frames, None, tmp_path / "m.npy", replace=True)
    data = SweepDataset.load(own_frames)
    assert "s" in data.metadata["auto_labels"]  # not yet dropped, but stale
    assert label_sources(data) == {"s": "masks"}
    assert int((data.sweep("s").labels == 1).sum()) == 6


def _recording_with_an_echo(n: int = 5):
    """Frames of tissue with a bright band (the bone's echo) and a stripe, blank columns at both
    sides, frame 2 invalid; the masks mark band and stripe, in MF, on every frame of the file."""
    rec = recording(n=n, height=40, width=60)
    rec.frames[:] = TISSUE
    rec.frames[:, :, :3] = 0
    rec.frames[:, :, 57:] = 0
    masks = np.zeros(rec.frames.shape, dtype=np.uint8)
    for k in range(n):
        top = 14 + 2 * k
        rec.frames[k, top : top + 6, 12 + k : 48 - k] = ECHO
        masks[k, top : top + 6, 12 + k : 48 - k] = 1
        rec.frames[k, :, 50:53] = ECHO  # down the whole depth: a shear moves its ends apart
        masks[k, :, 50:53] = 1
    rec.image_status = ["OK", "OK", "INVALID", "OK", "OK"][:n]
    return rec, masks


def imported_echo(
    tmp_path: Path, shear_deg: float, downsample: str, name: str = "s.mha"
) -> tuple[Path, Path, np.ndarray]:
    """:func:`_recording_with_an_echo` stored UN as ``name``, imported with a calibration of
    ``shear_deg`` and a clip rectangle, ``--downsample``, then labelled from its masks (saved as
    ``m.npy``): the dataset, the recording and the masks."""
    rec, masks = _recording_with_an_echo()
    cal = calibration(spacing=(0.3, 0.3), shear_deg=shear_deg)
    config = write_config(tmp_path / "c.xml", cal, clip=((1, 2), (58, 36)))
    sequence = write_mha(tmp_path / name, rec, "UN")
    out = tmp_path / "ds"
    imported = runner.invoke(
        app, ["import-plus", str(sequence), "--config", str(config), "--out", str(out),
              "--downsample", downsample],
    )  # fmt: skip
    assert imported.exit_code == 0, imported.output
    np.save(tmp_path / "m.npy", masks)
    result = _label(str(out), "--masks", str(tmp_path / "m.npy"))
    assert result.exit_code == 0, result.output
    return out, sequence, masks


@pytest.mark.parametrize("downsample", ["1", "2"])
def test_plus_masks_land_on_the_echo_they_mark(tmp_path: Path, downsample: str):
    """A recording stored UN, with a sheared calibration (the frames are resampled onto the
    rigid grid), a clip rectangle, blank columns and an invalid frame: the masks, drawn in MF on
    the recording's frames, land on the imported echo. Where a label is known, bone ⇔ the
    imported grey level is above the midpoint of tissue and echo (both went through the same
    linear steps), but for ties at the band's edges."""
    out, _, masks = imported_echo(tmp_path, 4.0, downsample)
    data = SweepDataset.load(out)
    record = data.metadata["imports"]["s"]
    assert record["resampled_to_rigid_grid"] and record["kept_columns"] is not None
    images, labels = data.sweep("s").images, data.sweep("s").labels
    assert labels.shape == images.shape and images.shape[0] == 4  # frame 2 was skipped
    known = labels != 255
    assert known.mean() > 0.9  # only the resampling's corners fall outside the recording
    bright = images >= (TISSUE + ECHO) / 2
    agree = (labels == 1) == bright
    assert agree[known].mean() > 0.995
    assert (labels == 1).sum() > 0.9 * bright[known].sum()
    # the masks given in the file's own orientation give the same labels
    np.save(tmp_path / "un.npy", to_file_orientation(masks, "UN"))
    again = _label(str(out), "--masks", str(tmp_path / "un.npy"), "--orientation", "UN",
                   "--replace")  # fmt: skip
    assert again.exit_code == 0, again.output
    assert np.array_equal(SweepDataset.load(out).sweep("s").labels, labels)


def _plain_import(tmp_path: Path) -> tuple[Path, np.ndarray]:
    """:func:`_recording_with_an_echo` imported with an exact calibration (no resampling) and
    its masks."""
    rec, masks = _recording_with_an_echo()
    config = write_config(tmp_path / "c.xml", calibration())
    out = tmp_path / "ds"
    imported = runner.invoke(
        app, ["import-plus", str(write_mha(tmp_path / "s.mha", rec)), "--config", str(config),
              "--out", str(out), "--downsample", "1"],
    )  # fmt: skip
    assert imported.exit_code == 0, imported.output
    return out, masks


def test_masks_are_read_a_few_frames_at_a_time_with_the_same_labels(tmp_path: Path, monkeypatch):
    """Memory-mapped masks mapped two frames at a time give the labels of one pass over all."""
    import ultron.data.label_import as label_import

    out, masks = _plain_import(tmp_path)
    np.save(tmp_path / "m.npy", masks)
    data = SweepDataset.load(out)
    read, orientation, named = label_import.read_masks(tmp_path / "m.npy")
    assert named is None
    assert isinstance(read, np.memmap)
    config = MaskImportConfig()
    whole = label_import.sweep_mask_labels(data, "s", read, config, tmp_path, orientation)
    own = np.where(whole == 1, 7, 0).astype(np.uint8)  # the sweep's own shape, as masks
    own_whole = label_import.sweep_mask_labels(data, "s", own, config, tmp_path)
    monkeypatch.setattr(label_import, "CHUNK_FRAMES", 2)
    assert np.array_equal(
        label_import.sweep_mask_labels(data, "s", read, config, tmp_path, orientation), whole
    )
    assert np.array_equal(
        label_import.sweep_mask_labels(data, "s", own, config, tmp_path), own_whole
    )
    assert (own_whole == 1).sum() == (whole == 1).sum()


def test_frames_parse_as_numbers_and_ranges():
    assert parse_frames("0:100:10,105") == (*range(0, 100, 10), 105)
    assert parse_frames(" 3 , 5:7") == (3, 5, 6)
    for bad in ("a", "1:2:0", "-1", "", "1:2:3:4", "2,,3"):
        with pytest.raises(UltronInputError, match="frames"):
            parse_frames(bad)
    with pytest.raises(UltronInputError, match="more than once"):
        MaskImportConfig(frames=(1, 2, 1))
    assert len(parse_frames(f"0:{MAX_LISTED_FRAMES}")) == MAX_LISTED_FRAMES
    for huge in ("0:3000000000", f"0:{MAX_LISTED_FRAMES},{MAX_LISTED_FRAMES}"):
        with pytest.raises(UltronInputError, match="lists more than"):  # not expanded first
            parse_frames(huge)


def test_masks_of_listed_frames_only(tmp_path: Path, own_frames: Path):
    """Masks of frames 0, 2 and 3 of a PLUS recording (--frames 0,2,3; frame 2 was skipped at
    import) give the labels of the whole recording's masks with every other frame empty; on a
    sweep of its own frames, masks of frames 1 and 3 land there."""
    out, masks = _plain_import(tmp_path)
    empty_elsewhere = masks.copy()
    empty_elsewhere[[1, 4]] = 0
    np.save(tmp_path / "all.npy", empty_elsewhere)
    assert _label(str(out), "--masks", str(tmp_path / "all.npy")).exit_code == 0
    expected = SweepDataset.load(out).sweep("s").labels
    np.save(tmp_path / "some.npy", masks[[0, 2, 3]])
    result = _label(str(out), "--masks", str(tmp_path / "some.npy"), "--frames", "0,2,3",
                    "--replace")  # fmt: skip
    assert result.exit_code == 0, result.output
    labels = SweepDataset.load(out).sweep("s").labels
    assert np.array_equal(labels, expected) and (labels[[1, 3]] == 255).all()
    for frames, needle in (("0,2", "3 masks for the 2 frames"), ("0:2,5", "lists frame 5")):
        refused = _label(str(out), "--masks", str(tmp_path / "some.npy"), "--frames", frames,
                         "--replace")  # fmt: skip
        assert refused.exit_code == 2 and needle in refused.stderr, refused.stderr
    # PNGs named by their frames, with gaps, are of those frames; --frames must agree
    from PIL import Image

    (tmp_path / "png").mkdir()
    for number in (0, 2, 3):
        Image.fromarray(masks[number] * 255).save(tmp_path / "png" / f"{number:04d}.png")
    result = _label(str(out), "--masks", str(tmp_path / "png"), "--replace")
    assert result.exit_code == 0, result.output
    assert np.array_equal(SweepDataset.load(out).sweep("s").labels, expected)
    refused = _label(str(out), "--masks", str(tmp_path / "png"), "--frames", "0,1,3", "--replace")
    assert refused.exit_code == 2
    assert "the PNG names give frames 0, 2, 3; --frames lists 0, 1, 3" in refused.stderr
    own = np.zeros((2, 6, 8), dtype=np.uint8)
    own[:, 2, 3] = 1
    np.save(tmp_path / "own.npy", own)
    result = _label(str(own_frames), "--masks", str(tmp_path / "own.npy"), "--frames", "1:4:2")
    assert result.exit_code == 0, result.output
    labels = SweepDataset.load(own_frames).sweep("s").labels
    assert (labels[[0, 2, 4]] == 255).all() and np.array_equal(labels[[1, 3]], own)


def test_plus_masks_png_folder(tmp_path: Path):
    """A folder of 0.png … (N − 1).png, one per frame of the recording, reads as the array."""
    from PIL import Image

    out, masks = _plain_import(tmp_path)
    (tmp_path / "png").mkdir()
    for k, mask in enumerate(masks):
        Image.fromarray(mask * 255).save(tmp_path / "png" / f"{k}.png")
    result = _label(str(out), "--masks", str(tmp_path / "png"))
    assert result.exit_code == 0, result.output
    data = SweepDataset.load(out)
    expected = masks[[0, 1, 3, 4]][:, :, 3:57]  # the valid frames, the columns kept
    assert np.array_equal(data.sweep("s").labels, expected)


def test_plus_masks_as_a_labelmap_sequence(tmp_path: Path):
    """A labelmap sequence as Slicer saves one: with its own orientation (UN here, whatever
    --orientation says) or without one (then --orientation, MF by default), raw or compressed;
    both give the labels of the same masks as an array."""
    out, masks = _plain_import(tmp_path)
    np.save(tmp_path / "m.npy", masks)
    assert _label(str(out), "--masks", str(tmp_path / "m.npy")).exit_code == 0
    expected = SweepDataset.load(out).sweep("s").labels
    flipped = write_mha(tmp_path / "seg.seq.mha", Recording(masks, {}), "UN", compressed=True)
    result = _label(str(out), "--masks", str(flipped), "--orientation", "MN", "--replace")
    assert result.exit_code == 0, result.output
    assert np.array_equal(SweepDataset.load(out).sweep("s").labels, expected)

    def without_orientation(pairs):
        return [pair for pair in pairs if "orientation" not in pair[0].lower()]

    plain = write_nrrd(tmp_path / "seg.seq.nrrd", Recording(masks, {}), edit=without_orientation)
    assert b"orientation" not in plain.read_bytes()
    result = _label(str(out), "--masks", str(plain), "--replace")
    assert result.exit_code == 0, result.output
    assert np.array_equal(SweepDataset.load(out).sweep("s").labels, expected)


@pytest.mark.parametrize("kind", ["MET_SHORT-lsb", "MET_USHORT-msb", "nrrd-short"])
def test_a_16_bit_labelmap_sequence(tmp_path: Path, kind: str):
    """Slicer's labelmaps are often 16-bit: a MetaImage of MET_SHORT / MET_USHORT (either byte
    order) or a NRRD of shorts holding segment values 0, 2 (bone, --bone-value 2) and 300 (another
    segment: background) gives the labels of the same masks as an 8-bit array."""
    import nrrd

    out, masks = _plain_import(tmp_path)
    np.save(tmp_path / "m.npy", masks)
    assert _label(str(out), "--masks", str(tmp_path / "m.npy")).exit_code == 0
    expected = SweepDataset.load(out).sweep("s").labels
    values = masks.astype(np.int16) * 2
    values[:, 0, 20:30] = 300  # another segment, in every frame
    path = tmp_path / "seg.seq.nrrd"
    if kind == "nrrd-short":
        header = {"kinds": ["domain", "domain", "list"], "ultrasound image orientation": "MF"}
        nrrd.write(str(path), values.transpose(2, 1, 0), header)  # x fastest, then y, frames
    else:
        element, order = kind.split("-")
        dtype = np.dtype("i2" if element == "MET_SHORT" else "u2").newbyteorder(
            ">" if order == "msb" else "<"
        )
        path = write_mha(tmp_path / "seg.seq.mha", Recording(masks, {}))
        text = path.read_bytes().split(b"ElementDataFile = LOCAL\n")[0].decode("latin-1")
        text = text.replace("MET_UCHAR", element).replace(
            "BinaryDataByteOrderMSB = False", f"BinaryDataByteOrderMSB = {order == 'msb'}"
        )
        path.write_bytes(
            (text + "ElementDataFile = LOCAL\n").encode("latin-1") + values.astype(dtype).tobytes()
        )
    result = _label(str(out), "--masks", str(path), "--bone-value", "2", "--replace")
    assert result.exit_code == 0, result.output
    assert np.array_equal(SweepDataset.load(out).sweep("s").labels, expected)
    # B-mode stays 8-bit: the same file is refused as a recording, naming the field
    imported = runner.invoke(
        app, ["import-plus", str(path), "--config", str(tmp_path / "c.xml"), "--out",
              str(tmp_path / "other")],
    )  # fmt: skip
    needle = "expected uint8 (B-mode)" if kind == "nrrd-short" else "expected MET_UCHAR (8-bit"
    assert imported.exit_code == 2 and needle in imported.stderr, imported.stderr


def test_a_plus_sweeps_own_labels_edited_come_back_as_they_are(tmp_path: Path):
    """Masks of the sweep's shape, not the recording's, are the sweep's own labels edited (in
    numpy, napari …): with the label values named they come back bit for bit."""
    out, masks = _plain_import(tmp_path)
    np.save(tmp_path / "m.npy", masks)
    assert _label(str(out), "--masks", str(tmp_path / "m.npy")).exit_code == 0
    edited = SweepDataset.load(out).sweep("s").labels.copy()
    assert edited.shape != masks.shape
    edited[1][edited[1] == 1] = 0  # the annotator takes frame 1's bone back
    edited[3, :2] = 255
    np.save(tmp_path / "edited.npy", edited)
    result = _label(str(out), "--masks", str(tmp_path / "edited.npy"), "--bone-value", "1",
                    "--unsure-value", "255", "--annotated", "all", "--replace")  # fmt: skip
    assert result.exit_code == 0, result.output
    assert np.array_equal(SweepDataset.load(out).sweep("s").labels, edited)


@pytest.mark.parametrize(
    ("masks_of", "extra", "needle"),
    [
        (lambda m: m[:4], [], "4 frames; the recording (s.mha) has 5 (or, masks of the sweep's"),
        (lambda m: m[:, :, :50], [], "frames of 40 × 50 pixels (rows × columns); the recording's"),
        (lambda m: m * 0, [], "no bone pixel reaches sweep 's'"),
        (lambda m: m.astype(np.float32), [], "expected integer values"),
        (lambda m: m, ["--auto"], "pass exactly one of --auto, --masks MASKS and --export OUT"),
        (lambda m: m, ["--bone-value", "0"], "--bone-value"),
        (lambda m: m, ["--orientation", "XX"], "orientation"),
        (lambda m: m, ["--sweeps", "t"], "'t'"),
    ],
)
def test_bad_masks_are_refused_naming_what_and_nothing_is_written(
    tmp_path: Path, masks_of, extra, needle
):
    out, masks = _plain_import(tmp_path)
    np.save(tmp_path / "m.npy", masks_of(masks))
    before = _files(out)
    result = _label(str(out), "--masks", str(tmp_path / "m.npy"), *extra)
    assert result.exit_code == 2, result.output
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], lines
    assert _files(out) == before


def test_masks_need_one_sweep_and_a_readable_file(own_frames: Path, tmp_path: Path):
    with_two = SweepDataset.load(own_frames)
    with_two.sweeps.append(
        Sweep("t", "row", with_two.sweeps[0].images, with_two.sweeps[0].probe_to_world)
    )
    with_two.save(tmp_path / "two")
    np.save(tmp_path / "m.npy", np.ones((5, 6, 8), dtype=np.uint8))
    result = _label(str(tmp_path / "two"), "--masks", str(tmp_path / "m.npy"))
    assert result.exit_code == 2 and "--sweeps NAME" in result.stderr
    (tmp_path / "m.txt").write_text("1 2 3")
    result = _label(str(own_frames), "--masks", str(tmp_path / "m.txt"))
    assert result.exit_code == 2 and "expected a .npy array" in result.stderr
    result = _label(str(own_frames))
    assert (
        result.exit_code == 2
        and "pass exactly one of --auto, --masks MASKS and --export OUT" in result.stderr
    )


def test_info_names_where_each_sweeps_labels_came_from(own_frames: Path, tmp_path: Path):
    """none → masks (label --masks) → auto (label --auto --replace, which drops the masks'
    record) → given (labels written with the dataset)."""
    from ultron.data.label_import import label_sources

    assert label_sources(SweepDataset.load(own_frames)) == {"s": "none"}
    masks = np.zeros((5, 6, 8), dtype=np.uint8)
    masks[2, 4, 1:7] = 1
    np.save(tmp_path / "m.npy", masks)
    assert _label(str(own_frames), "--masks", str(tmp_path / "m.npy")).exit_code == 0
    info = runner.invoke(app, ["info", str(own_frames)], terminal_width=200)
    assert info.exit_code == 0 and re.search(r"│ s +│ row +│ +5 │ +1 │ masks +│", info.output)
    assert _label(str(own_frames), "--auto", "--replace").exit_code == 0
    data = SweepDataset.load(own_frames)
    assert label_sources(data) == {"s": "auto"} and "label_imports" not in data.metadata
    data.metadata = {}
    data.save(tmp_path / "plain")
    assert label_sources(SweepDataset.load(tmp_path / "plain")) == {"s": "given"}
